"""The reader of the datasets `python -m datagen` writes (format: docs/datasets.md#on-disk-format): the one
place that parses a manifest and decodes views, used by training, evaluation and the studies.

    ds = MultiViewDataset("data/metallic", split="train", views_per_item=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=8, shuffle=True, collate_fn=collate)
    batch = next(iter(loader))
    batch["image"]    # (B, V, H, W, 4) linear RGBA (alpha = mask);  batch["cameras"]: dibrpp Cameras of B*V views
    batch["albedo"]   # (B, V, H, W, 3) linear base colour x coverage;  batch["envmap"]: (B, He, We, 3)

Each item is one view of one (object, env map) sample plus ``views_per_item - 1`` other views of the
same sample (for the multi-view consistency loss), chosen deterministically from ``seed`` and the
index. Ground-truth meshes are per object (``ds.mesh(obj)`` -> dibrpp Meshes with UVs,
``ds.texture(obj)``). Everything read is validated (missing views, shapes, NaN/Inf) and decoded
tensors are cached in memory. Paths come from :class:`datagen.layout.DatasetLayout` (``ds.layout``),
which imports neither bpy nor torch; ``ds.camera_setup`` is the orbit camera of the manifest
(distance, elevation, fov), for code that must place cameras like the data's.
"""
from __future__ import annotations

import json
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from datagen.layout import CameraSetup, DatasetLayout
from dibrpp.camera import Cameras
from dibrpp.io import DataError, read_exr, read_png
from dibrpp.mesh import Meshes


class MultiViewDataset(torch.utils.data.Dataset):
    def __init__(self, root, split: str = "train", views_per_item: int = 2, image: str = "linear",
                 cache_items: int = 4096, seed: int = 0, with_envmap: bool = True):
        self.root = Path(root)
        self.layout = DatasetLayout(self.root)
        if split not in ("train", "test", "all"):
            raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
        if image not in ("linear", "srgb"):
            raise ValueError(f"image must be 'linear' (EXR) or 'srgb' (PNG), got {image!r}")
        mpath = self.layout.manifest
        if not mpath.is_file():
            raise DataError(f"{self.root}: no manifest.json; is this a dataset folder written by `python -m datagen`? "
                            "(`make data` renders the default sets)")
        try:
            self.manifest = json.loads(mpath.read_text())
        except json.JSONDecodeError as e:
            raise DataError(f"{mpath}: corrupt JSON ({e})") from e
        try:
            cfg = self.manifest["config"]
            self.resolution = int(cfg["resolution"])
            self.num_views = int(cfg["views"])
            objs = [o for o in self.manifest["objects"] if split == "all" or o["split"] == split]
            self.samples = [(int(o["index"]), int(e)) for o in objs for e in o["envmaps"]]
            self.materials = {int(o["index"]): dict(o["material"]) for o in objs}
            self.has_metals = any(float(o["material"]["metallic"]) > 0 for o in self.manifest["objects"])
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{mpath}: not a dataset manifest ({type(e).__name__}: {e}); regenerate the dataset "
                            "with `python -m datagen` or restore the file") from None
        if not 1 <= views_per_item <= self.num_views:
            raise ValueError(f"views_per_item must be in [1, {self.num_views}], got {views_per_item}")
        self.views_per_item = views_per_item
        self.image = image
        self.seed = seed
        self.with_envmap = with_envmap
        self._validate_files()
        self._cache: OrderedDict = OrderedDict()
        self._cache_items = cache_items

    @property
    def camera_setup(self) -> CameraSetup:
        """The data's orbit camera from the manifest: distance, elevation_deg, fov (radians; fov_deg),
        azimuths_deg, resolution."""
        try:
            return CameraSetup.from_manifest(self.manifest)
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{self.layout.manifest}: no readable camera set-up ({e!r}); regenerate the dataset "
                            "with `python -m datagen`") from e

    # ------------------------------------------------------------------ validation
    def sample_dir(self, obj: int, env: int) -> Path:
        return self.layout.sample_dir(obj, env)

    def _validate_files(self) -> None:
        missing = []
        lay = self.layout
        for obj, env in self.samples:
            d = self.sample_dir(obj, env)
            if not lay.sample_json(obj, env).is_file():
                missing.append(f"{d.name} (unfinished: no sample.json)")
                continue
            for v in range(self.num_views):
                for p in (lay.view_image(obj, env, v), lay.view_albedo(obj, env, v), lay.view_camera(obj, env, v)):
                    if not p.is_file():
                        missing.append(f"{d.name}/{p.name}")
            for p in (lay.mesh_npz(obj), lay.envmap(env)):
                if not p.is_file():
                    missing.append(str(p.relative_to(self.root)))
        if missing:
            more = f" (and {len(missing) - 8} more)" if len(missing) > 8 else ""
            raise DataError(f"{self.root}: dataset incomplete, missing {', '.join(missing[:8])}{more}; "
                            "rerun the same `python -m datagen` command to finish it")
        if not self.samples:
            raise DataError(f"{self.root}: no samples in this split")

    # ------------------------------------------------------------------ cached readers
    def _cached(self, key, fn):
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        val = fn()
        self._cache[key] = val
        if len(self._cache) > self._cache_items:
            self._cache.popitem(last=False)
        return val

    def _image(self, path: Path, channels: str) -> torch.Tensor:
        def load():
            if path.suffix == ".exr":
                arr = read_exr(path, channels)
            else:
                arr = read_png(path)
            r = self.resolution
            if arr.shape != (r, r, len(channels)):
                raise DataError(f"{path}: shape {arr.shape}, expected {(r, r, len(channels))} from the manifest")
            return torch.from_numpy(np.ascontiguousarray(arr))
        return self._cached(("img", str(path)), load)

    def camera(self, obj: int, env: int, view: int) -> tuple[torch.Tensor, float]:
        def load():
            p = self.layout.view_camera(obj, env, view)
            try:
                c = json.loads(p.read_text())
                m = torch.tensor(c["world_to_camera"], dtype=torch.float32)
                fov = float(c["fov"])
            except (OSError, KeyError, ValueError, TypeError) as e:
                raise DataError(f"{p}: unreadable camera ({e})") from e
            if m.shape != (4, 4) or not torch.isfinite(m).all():
                raise DataError(f"{p}: world_to_camera must be a finite 4x4 matrix")
            return m, fov
        return self._cached(("cam", obj, env, view), load)

    def view_image(self, obj: int, env: int, view: int) -> torch.Tensor:
        """(S, S, 4) RGBA image of one view, linear or sRGB as this dataset was opened."""
        return self._image(self.layout.view_image(obj, env, view, srgb=self.image == "srgb"), "RGBA")

    def view_albedo(self, obj: int, env: int, view: int) -> torch.Tensor:
        """(S, S, 3) linear base colour x coverage of one view."""
        return self._image(self.layout.view_albedo(obj, env, view), "RGB")

    def envmap(self, env: int) -> torch.Tensor:
        return self._cached(("env", env), lambda: torch.from_numpy(
            read_exr(self.layout.envmap(env), "RGB")))

    def mesh(self, obj: int) -> Meshes:
        """Ground-truth mesh (B = 1) with per-corner UVs (v up)."""
        def load():
            p = self.layout.mesh_npz(obj)
            try:
                with np.load(p) as m:
                    arrays = {k: m[k] for k in ("verts", "faces", "uvs", "face_uvs")}
            except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as e:
                raise DataError(f"{p}: unreadable mesh ({e})") from e
            try:
                return Meshes(torch.from_numpy(arrays["verts"]).float(), torch.from_numpy(arrays["faces"]),
                              torch.from_numpy(arrays["uvs"]).float(), torch.from_numpy(arrays["face_uvs"]))
            except ValueError as e:
                raise DataError(f"{p}: invalid mesh ({e})") from e
        return self._cached(("mesh", obj), load)

    def material_params(self, obj: int) -> dict:
        """The object's scalar material as the renderer's ``Material`` takes it (roughness, metallic, specular: the
        Principled BSDF's specular IOR level)."""
        m = self.materials[obj]
        return dict(roughness=float(m["roughness"]), metallic=float(m["metallic"]), specular=float(m["specular_ior_level"]))

    def texture(self, obj: int) -> torch.Tensor:
        """Ground-truth albedo texture (S, S, 3), linear (decoded from the sRGB PNG), top row first."""
        return self._cached(("tex", obj), lambda: torch.from_numpy(
            read_png(self.layout.texture(obj), linear=True)[..., :3]))

    # ------------------------------------------------------------------ Dataset protocol
    def __len__(self) -> int:
        return len(self.samples) * self.num_views

    def views_for(self, idx: int) -> list[int]:
        v0 = idx % self.num_views
        others = [v for v in range(self.num_views) if v != v0]
        rng = np.random.default_rng([self.seed, idx])
        return [v0] + [int(v) for v in rng.choice(others, self.views_per_item - 1, replace=False)]

    def __getitem__(self, idx: int) -> dict:
        if not 0 <= idx < len(self):
            raise IndexError(idx)
        obj, env = self.samples[idx // self.num_views]
        views = self.views_for(idx)
        imgs, albs, w2cs, fovs = [], [], [], []
        for v in views:
            imgs.append(self.view_image(obj, env, v))
            albs.append(self.view_albedo(obj, env, v))
            m, fov = self.camera(obj, env, v)
            w2cs.append(m)
            fovs.append(fov)
        image = torch.stack(imgs)
        item = dict(image=image, mask=image[..., 3], albedo=torch.stack(albs), world_to_camera=torch.stack(w2cs),
                    fov=torch.tensor(fovs, dtype=torch.float32), views=torch.tensor(views), object=obj, envmap_index=env,
                    roughness=float(self.materials[obj]["roughness"]), metallic=float(self.materials[obj]["metallic"]))
        if self.with_envmap:
            item["envmap"] = self.envmap(env)
        return item

    def cameras(self, item: dict) -> Cameras:
        return Cameras(item["world_to_camera"].reshape(-1, 4, 4), item["fov"].reshape(-1), self.resolution)


def collate(items: list[dict]) -> dict:
    """Stack items; adds 'cameras' (dibrpp Cameras of all B*V views, item-major)."""
    out = {}
    for k in items[0]:
        vals = [it[k] for it in items]
        out[k] = torch.stack(vals) if isinstance(vals[0], torch.Tensor) else torch.tensor(vals)
    res = items[0]["image"].shape[-2]
    out["cameras"] = Cameras(out["world_to_camera"].reshape(-1, 4, 4), out["fov"].reshape(-1), res)
    return out

