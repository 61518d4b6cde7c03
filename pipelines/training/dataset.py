"""Training tensors from a dataset: every training view decoded once, and the batches of view pairs.

The dataset's format is read by :class:`datagen.reader.MultiViewDataset` (the one reader); this module owns
what training draws from it: which (sample, view pair) items form an iteration's batch.
"""
from __future__ import annotations

import torch

from datagen.reader import MultiViewDataset
from dibrpp import Cameras, Renderer
from dibrpp.io import DataError


class TrainingViews:
    """Every view of a split decoded once into tensors (linear RGBA images as rendered, cameras), and the
    training batches drawn from them: (sample, view pair) items, a pure function of (seed, iteration, rank),
    so resumes are exact. ``envmaps``, ``normals`` (the GT mesh's rendered in every view), ``albedos`` (every
    view's) and ``roughness`` (each sample's object's) load GT only for the diagnostics (and the pixel normals' fit)
    that read it. The tensors live on ``device``; the batches' indices are drawn on the CPU, so a run draws the same
    batches on either. ``max_objects``: only the split's first objects (their every
    sample), for learning curves; 0 for all."""

    def __init__(self, ds: MultiViewDataset, image_size: int, envmaps: bool = False, normals: bool = False,
                 albedos: bool = False, roughness: bool = False, device: str | torch.device = "cpu",
                 max_objects: int = 0):
        if ds.resolution != image_size:
            raise DataError(f"{ds.root}: images are {ds.resolution}x{ds.resolution} but the config trains at "
                            f"{image_size}")
        objects = list(dict.fromkeys(obj for obj, _ in ds.samples))
        if max_objects > len(objects):
            raise DataError(f"{ds.root}: the split has {len(objects)} objects, fewer than the {max_objects} asked for; "
                            f"pass --train-objects {len(objects)} or less (0: all)")
        kept = set(objects[:max_objects] if max_objects else objects)
        self.samples = [(obj, env) for obj, env in ds.samples if obj in kept]
        n_samples, n_views = len(self.samples), ds.num_views
        imgs, w2c, fov = [], [], []
        for obj, env in self.samples:
            for v in range(n_views):
                imgs.append(ds.view_image(obj, env, v))
                m, f = ds.camera(obj, env, v)
                w2c.append(m)
                fov.append(f)
        self.envmap_of_sample = torch.tensor([env for _, env in self.samples])
        self.envmaps = {env: ds.envmap(env) for env in set(self.envmap_of_sample.tolist())} if envmaps else None
        self.images = torch.stack(imgs).view(n_samples, n_views, image_size, image_size, 4)
        self.world_to_camera = torch.stack(w2c).view(n_samples, n_views, 4, 4)
        self.fov = torch.tensor(fov, dtype=torch.float32).view(n_samples, n_views)
        self.resolution = image_size
        self.num_samples, self.num_views = n_samples, n_views
        self.normals = self._gt_normals(ds) if normals else None
        self.albedos = torch.stack([ds.view_albedo(obj, env, v) for obj, env in self.samples for v in range(n_views)]).view(
            n_samples, n_views, image_size, image_size, 3) if albedos else None
        self.roughness = torch.tensor([ds.material_params(obj)["roughness"] for obj, _ in self.samples],
                                      dtype=torch.float32, device=device) if roughness else None
        self.images, self.world_to_camera, self.fov = (t.to(device) for t in (self.images, self.world_to_camera, self.fov))
        self.normals, self.albedos = (None if t is None else t.to(device) for t in (self.normals, self.albedos))
        if self.envmaps is not None:
            self.envmaps = {env: m.to(device) for env, m in self.envmaps.items()}

    def _gt_normals(self, ds: MultiViewDataset) -> torch.Tensor:
        """(samples, views, S, S, 4) the GT mesh's world-frame normals and coverage in every view."""
        renderer = Renderer("sg")
        with torch.no_grad():
            return torch.stack([renderer.render_normals(ds.mesh(obj).expand(self.num_views), Cameras(
                self.world_to_camera[k], self.fov[k], self.resolution)).image for k, (obj, _) in enumerate(self.samples)])

    def batch(self, iteration: int, size: int, seed: int, rank: int = 0, world: int = 1) -> dict:
        """The iteration's batch: ``image`` (B, 2, S, S, 4), cameras of both views, and ``sample`` (B,)."""
        g = torch.Generator().manual_seed(seed * 1_000_003 + iteration)
        samples = torch.randint(self.num_samples, (size * world,), generator=g)[rank::world]
        v1 = torch.randint(self.num_views, (size * world,), generator=g)[rank::world]
        v2 = (v1 + 1 + torch.randint(self.num_views - 1, (size * world,), generator=g)[rank::world]) % self.num_views
        views = torch.stack([v1, v2], 1)
        s = samples.unsqueeze(1).expand(-1, 2)
        out = dict(image=self.images[s, views], world_to_camera=self.world_to_camera[s, views], fov=self.fov[s, views],
                   sample=samples)
        if self.normals is not None:
            out["normals"] = self.normals[s, views]
        if self.albedos is not None:
            out["albedo"] = self.albedos[s, views]
        if self.roughness is not None:
            out["roughness"] = self.roughness[samples]
        if self.envmaps is not None:
            out["envmap"] = torch.stack([self.envmaps[e] for e in self.envmap_of_sample[samples].tolist()])
        return out
