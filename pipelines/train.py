"""Single-image inverse rendering with the multi-view consistency loss (Sec. E.1-E.2).

    python -m pipelines.train --dataset data/glossy --shading sg --seed 0 --out runs/glossy/sg_s0
    torchrun --nproc_per_node 2 -m pipelines.train ...        # data-parallel (gloo on CPU, NCCL on GPU)

Each iteration draws ``batch_objects`` (sample, view pair) items, predicts shape/texture/material/light
from both views and renders every prediction in both views with the light of the view it is rendered
in (eq. 8). Checkpoints are atomic; ``--resume`` continues bit-for-bit (batches are drawn from a
generator seeded by (seed, iteration), and the RNG state is saved).
"""
from __future__ import annotations

import argparse
import csv
import functools
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch
import torch.distributed as dist

from datagen.layout import CameraSetup, DatasetLayout
from dibrpp import Cameras, RasterSettings, Renderer
from dibrpp.io import DataError, atomic_path, write_png
from dibrpp.mesh import laplacian_smoothness, uniform_laplacian

from .display import display_srgb, tonemap_envmap
from .formatting import pyplot, save_figure
from .losses import gradient_loss, hdr_srgb, image_l1, soft_iou_loss
from .metrics import ProbeScene, si_rmse
from .model import Encoder, ModelConfig, encoder_input


@dataclass
class TrainConfig:
    dataset: str = "data/glossy"
    out: str = "runs/run"
    shading: str = "sg"
    lobes: int = 32
    seed: int = 0
    iterations: int = 1500
    batch_objects: int = 8
    lr: float = 3e-4
    spp: int = 8  # MC samples per pixel during training
    image_size: int = 64
    w_image: float = 1.0
    w_iou: float = 1.0
    w_laplacian: float = 0.02
    w_gradient: float = 0.5
    log_every: int = 10
    snapshot_every: int = 250
    checkpoint_every: int = 100
    predict_metallic: bool = False
    texture: str = "projected"  # projected | global (ModelConfig.texture)
    light_colour: str = "white"  # white | free (ModelConfig.light_colour)
    light_scale: str = "softplus"  # softplus | log (ModelConfig.light_scale)
    cross_view_only: bool = False  # image losses on renders in the other view only (not the input view)
    shared_light: bool = False  # cross-view renders lit by another object's light under the same env map
    # cross-view renders go to the same object under its other env map: the prediction's shape, albedo and
    # material, rendered in that image's view with the light predicted from it, must reproduce it. Paint is the
    # object's and reflections are the map's, so a reflection copied into the albedo is wrong there
    swap_light: bool = False
    # diagnostic, not a model: render with each object's GT roughness (object.json) instead of the predicted
    # one, to measure how much of the light's error is the roughness/light-blur ambiguity
    oracle_roughness: bool = False
    # diagnostic, not a model: the light supervised by the GT env map, to measure what the encoder and light
    # head can reach when told the answer. "map": L1 of log(1 + radiance) over the map; "probe": si-RMSE of the
    # rough-metal probe sphere (the light metric itself) seen from four directions; "" = off
    light_supervision: str = ""
    # ablation: L1 between the albedos predicted from the two views of an object (albedo is view-independent;
    # reflections copied into the look-up move between views), 0 = off
    w_albedo_consistency: float = 0.0
    # ablation: pull each albedo texel down to the darker of the object's two views where both views see it
    # (the darker one is held fixed). Reflections add light and move between views; the paint's colour does
    # neither, so the darker view holds less reflection. 0 = off
    w_albedo_darker: float = 0.0
    # the light head's learning rate as a multiple of lr. Its outputs must travel far (a sun's SG sharpness is
    # in the hundreds, the initial lobes' ~12) while Adam moves a bias by at most lr per step; 1 = one rate
    light_lr_scale: float = 1.0
    # curriculum: for this many iterations every object's renders use its mean albedo (so shading and
    # reflections must come from the light), then the texture's detail fades in over as many more; 0 = off
    flat_albedo_iterations: int = 0
    visibility: str = "dibr"  # silhouette gradient: dibr (soft silhouette) | edge_aa (antialiased edges; Sec. F.1)
    threads: int = 0  # torch threads per process (0: torch's default)
    compile: bool = True  # G-buffer and SG/SH/MC shading through torch.compile (falls back to eager where it cannot)

    @classmethod
    def preset(cls, name: str, **overrides) -> "TrainConfig":
        presets = {
            "cpu": {},  # 64x64, 1500 iterations: a run of each method finishes on 2 cores in ~10-15 min
            "smoke": dict(iterations=12, batch_objects=2, log_every=2, snapshot_every=6, checkpoint_every=4, spp=2),
            "paper": dict(iterations=200_000, image_size=256, batch_objects=16, spp=64, snapshot_every=2000,
                          checkpoint_every=1000, log_every=50),
        }
        if name not in presets:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(presets)}")
        return cls(**{**presets[name], **overrides})


# ----------------------------------------------------------------------------- data

class TrainingData:
    """All training views decoded once into tensors: linear RGBA images (HDR, as rendered) and cameras."""

    def __init__(self, root: str, image_size: int, split: str = "train", envmaps: bool = False):
        from .dataset import MultiViewDataset

        ds = MultiViewDataset(root, split=split, views_per_item=1, image="linear", with_envmap=False)
        if ds.resolution != image_size:
            raise DataError(f"{root}: images are {ds.resolution}x{ds.resolution} but the config trains at "
                            f"{image_size}; pass --image-size {ds.resolution}")
        n_samples, n_views = len(ds.samples), ds.num_views
        imgs, w2c, fov = [], [], []
        for s in range(n_samples):
            for v in range(n_views):
                item = ds[s * n_views + v]
                imgs.append(item["image"][0])
                w2c.append(item["world_to_camera"][0])
                fov.append(item["fov"][0])
        self.envmap_of_sample = torch.tensor([env for _, env in ds.samples])
        self.object_of_sample = torch.tensor([obj for obj, _ in ds.samples])
        self.roughness_of_sample = torch.tensor([float(ds.materials[obj]["roughness"]) for obj, _ in ds.samples])
        # GT env maps by index (only for the light-supervision diagnostic)
        self.envmaps = {env: ds.envmap(env) for env in set(self.envmap_of_sample.tolist())} if envmaps else None
        self.images = torch.stack(imgs).view(n_samples, n_views, image_size, image_size, 4)
        self.world_to_camera = torch.stack(w2c).view(n_samples, n_views, 4, 4)
        self.fov = torch.stack(fov).view(n_samples, n_views)
        self.resolution = image_size
        self.num_samples, self.num_views = n_samples, n_views

    def batch(self, iteration: int, size: int, seed: int, rank: int = 0, world: int = 1,
              shared_light: bool = False, swap_light: bool = False) -> dict:
        """The iteration's batch, a pure function of (seed, iteration, rank): resumes are exact.

        With ``shared_light`` the second half of the batch are partners of the first: item k + size/2 is
        another object lit by the same env map as item k; with ``swap_light`` it is the same object under
        another env map (either way the item itself where there is no such sample); ``partner`` (B,) gives
        each item's partner."""
        if shared_light and swap_light:
            raise ValueError("--shared-light and --swap-light pair the batch differently; choose one")
        g = torch.Generator().manual_seed(seed * 1_000_003 + iteration)
        samples = torch.randint(self.num_samples, (size * world,), generator=g)[rank::world]
        partner = torch.arange(len(samples))
        if shared_light or swap_light:
            half = len(samples) // 2
            anchors = samples[:half]
            key = self.envmap_of_sample if shared_light else self.object_of_sample
            same = key[anchors, None] == key[None, :]  # (half, samples)
            same[torch.arange(half), anchors] = False  # another sample if there is one
            alone = ~same.any(1)
            same[alone, anchors[alone]] = True
            pick = torch.rand(same.shape, generator=g) * same
            samples = torch.cat([anchors, pick.argmax(1), samples[2 * half:]])
            partner[:half], partner[half:2 * half] = torch.arange(half, 2 * half), torch.arange(half)
        v1 = torch.randint(self.num_views, (size * world,), generator=g)[rank::world]
        v2 = (v1 + 1 + torch.randint(self.num_views - 1, (size * world,), generator=g)[rank::world]) % self.num_views
        views = torch.stack([v1, v2], 1)
        s = samples.unsqueeze(1).expand(-1, 2)
        out = dict(image=self.images[s, views], world_to_camera=self.world_to_camera[s, views], fov=self.fov[s, views],
                   sample=samples, partner=partner, roughness=self.roughness_of_sample[samples])
        if self.envmaps is not None:
            out["envmap"] = torch.stack([self.envmaps[e] for e in self.envmap_of_sample[samples].tolist()])
        return out


# ----------------------------------------------------------------------------- one step

def albedo_detail(config: TrainConfig, iteration: int) -> float:
    """How much of the texture's detail the renders use at ``iteration`` (the flat-albedo curriculum)."""
    n = config.flat_albedo_iterations
    return 1.0 if n <= 0 else min(1.0, max(0.0, (iteration - n) / n))


def with_albedo_detail(texture: torch.Tensor, detail: float) -> torch.Tensor:
    """(B, Ht, Wt, 3) texture -> each texture's mean plus ``detail`` times its variation about the mean."""
    if detail >= 1.0:
        return texture  # exactly, not mean + (texture - mean)
    mean = texture.mean((1, 2), keepdim=True)
    return mean + detail * (texture - mean)


@functools.lru_cache(maxsize=1)
def _probe_scene() -> ProbeScene:
    """The probe spheres seen from four directions around the horizon, 20 degrees above it."""
    from dibrpp.conventions import orbit_world_to_camera

    return ProbeScene(orbit_world_to_camera(torch.tensor(3.0), 20.0, torch.tensor([0.0, 90.0, 180.0, 270.0])), resolution=16)


def supervised_light_loss(pred, views: Cameras, envmaps: torch.Tensor, kind: str) -> torch.Tensor:
    """The diagnostic light supervision (TrainConfig.light_supervision) of the 2B predictions (2i + j: item i,
    view j) by the items' GT world-frame env maps (B, H, W, 3)."""
    light = pred.light(views.world_to_camera)
    if kind == "map":
        env = envmaps.repeat_interleave(2, 0)
        pred_env = light.to_envmap(env.shape[1], env.shape[2]).image
        return (torch.log1p(pred_env) - torch.log1p(env)).abs().mean()
    if kind != "probe":
        raise ValueError(f"light_supervision must be '', 'map' or 'probe', got {kind!r}")
    scene = _probe_scene()
    metal = lambda table, k: scene.render_table(table[k:k + 1].expand(len(scene.view), -1, -1, -1), ["metal"])["metal"]  # noqa: E731
    gt = [metal(envmaps, i) for i in range(len(envmaps))]  # once per item: both its views share the map
    pred_table = light.to_envmap(envmaps.shape[1], envmaps.shape[2]).image
    return torch.stack([si_rmse(metal(pred_table, k), gt[k // 2]).mean() for k in range(len(pred_table))]).mean()


def multiview_losses(model, renderer: Renderer, batch: dict, config: TrainConfig, laplacian,
                     iteration: int | None = None) -> tuple[torch.Tensor, dict, dict]:
    """Eq. (8) plus the regularisers. Returns (total, {term: value}, tensors for snapshots). ``iteration``
    drives the curricula (None: the trained model, full detail)."""
    img = batch["image"]  # (B, 2, S, S, 4) linear RGB + alpha
    b, s = img.shape[0], img.shape[2]
    flat = img.reshape(b * 2, s, s, 4)
    views = Cameras(batch["world_to_camera"].reshape(b * 2, 4, 4), batch["fov"].reshape(-1), s)
    pred = model(encoder_input(flat), views)  # prediction from every view: index 2i + j
    # render prediction i (from view i) in view j with the light predicted from view j
    src = torch.arange(b * 2).view(b, 2).repeat_interleave(2, dim=1).reshape(-1)  # (b, [i1 i1 i2 i2])
    dst = torch.arange(b * 2).view(b, 2).repeat(1, 2).reshape(-1)  # (b, [v1 v2 v1 v2])
    if config.cross_view_only:
        # ... only in the other view: a texture that copies the input view's highlights and reflections gains
        # nothing (they move between views), so they have to come from the light and the specular lobe
        keep = src != dst
        src, dst = src[keep], dst[keep]
    lit_by = dst.clone()
    if config.shared_light or config.swap_light:
        cross = src != dst
        partner_view = 2 * batch["partner"][dst // 2] + dst % 2  # the same view of the render's partner item
    if config.shared_light:
        # ... but across views with the light predicted from the partner: another object under the same
        # env map. One world light must then light both objects, so it cannot carry one object's blur or
        # tint: what differs between them has to go to their materials.
        lit_by[cross] = partner_view[cross]
    if config.swap_light:
        # ... in the partner's view instead, against its image and with its light: the same object under
        # another env map. Only the light differs between the two images, so whatever the albedo copied from
        # one map's reflections is wrong under the other and has to come from the light
        dst[cross] = partner_view[cross]
        lit_by = dst.clone()
    cams = views[dst.tolist()]
    shape_pred = pred.select(src)
    if config.oracle_roughness:
        shape_pred.roughness = batch["roughness"][src // 2].to(shape_pred.roughness)
    detail = 1.0 if iteration is None else albedo_detail(config, iteration)
    if detail < 1.0:
        shape_pred.texture = with_albedo_detail(shape_pred.texture, detail)
    light = pred.select(lit_by).light(views.world_to_camera[lit_by])
    out = renderer(shape_pred.meshes(), cams, shape_pred.material(), light)
    target = flat[dst]
    rgb, target_rgb = hdr_srgb(out.rgb), hdr_srgb(target[..., :3])
    terms = {
        "image": image_l1(rgb, target_rgb, target[..., 3]),
        "iou": soft_iou_loss(out.silhouette, target[..., 3]),
        "laplacian": laplacian_smoothness(pred.verts, laplacian) / pred.config.template_radius ** 2,
        "gradient": gradient_loss(rgb, target_rgb * target[..., 3:]),
    }
    weights = {"image": config.w_image, "iou": config.w_iou, "laplacian": config.w_laplacian, "gradient": config.w_gradient}
    if config.light_supervision:
        terms["light_supervision"] = supervised_light_loss(pred, views, batch["envmap"], config.light_supervision)
        weights["light_supervision"] = 1.0
    if config.w_albedo_consistency:
        tex = pred.texture.view(b, 2, *pred.texture.shape[1:])  # prediction 2i + j is of item i, view j
        terms["albedo_consistency"] = (tex[:, 0] - tex[:, 1]).abs().mean()
        weights["albedo_consistency"] = config.w_albedo_consistency
    if config.w_albedo_darker:
        terms["albedo_darker"] = darker_view_albedo_loss(pred.texture, pred.facing)
        weights["albedo_darker"] = config.w_albedo_darker
    total = sum(weights[k] * v for k, v in terms.items())
    return total, terms, dict(input=flat, render=out.rgb, alpha=out.alpha, pred=pred, target=target, src=src,
                              world_to_camera=views.world_to_camera)


def darker_view_albedo_loss(texture: torch.Tensor, facing: torch.Tensor | None) -> torch.Tensor:
    """Mean amount by which each albedo texel exceeds the darker of its object's two views, over texels that
    face both input cameras. texture (2B, Ht, Wt, 3) and facing (2B, Ht, Wt), prediction 2i + j of item i, view j.
    The darker value is a fixed target, so only the brighter view's albedo is pulled (no collapse to a mean)."""
    if facing is None:
        raise ValueError("the darker-view albedo term needs the projected texture (--texture projected)")
    tex = texture.unflatten(0, (-1, 2))
    both = ((facing.unflatten(0, (-1, 2)) > 0).all(1)).unsqueeze(1).unsqueeze(-1)  # (B, 1, Ht, Wt, 1)
    darker = tex.min(1, keepdim=True).values.detach()
    excess = torch.where(tex > darker, tex - darker, 0.0) * both  # no gradient to the darker view itself
    return excess.sum() / (both.sum() * 2 * 3).clamp_min(1)


def check_finite(terms: dict) -> None:
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(f"the {name} loss became {value.item()}; stopping (the last good checkpoint is kept)")


def check_finite_gradients(model) -> None:
    for name, p in model.named_parameters():
        if p.grad is not None and not torch.isfinite(p.grad).all():
            raise FloatingPointError(f"the gradient of {name} became non-finite; stopping (the last good checkpoint is kept)")


# ----------------------------------------------------------------------------- run

def _setup_distributed():
    if "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def save_checkpoint(path: Path, model, opt, iteration: int, config: TrainConfig) -> None:
    state = {"model": model.state_dict(), "model_config": model.config.to_dict(), "optimizer": opt.state_dict(),
             "iteration": iteration, "config": asdict(config), "torch_rng": torch.get_rng_state()}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def make_optimizer(model: Encoder, config: TrainConfig) -> torch.optim.Adam:
    if config.light_lr_scale == 1.0:
        return torch.optim.Adam(model.parameters(), lr=config.lr)  # one group, as runs before the option had
    light = set(model.light_head.parameters())
    return torch.optim.Adam([{"params": [p for p in model.parameters() if p not in light]},
                             {"params": list(light), "lr": config.lr * config.light_lr_scale}], lr=config.lr)


def make_model(config: TrainConfig) -> Encoder:
    return Encoder(ModelConfig(shading=config.shading, lobes=config.lobes, image_size=config.image_size,
                               predict_metallic=config.predict_metallic, texture=config.texture,
                               light_colour=config.light_colour, light_scale=config.light_scale))


def dataset_camera_setup(dataset: str) -> dict:
    """The camera set-up of a dataset's views (orbit distance, elevation, field of view), from its manifest."""
    setup = CameraSetup.from_manifest(json.loads(DatasetLayout(dataset).manifest.read_text()))
    return dict(distance=setup.distance, elevation_deg=setup.elevation_deg, fov_deg=setup.fov_deg)


def run_camera_setup(run: Path) -> dict:
    """The camera set-up of the data a run was trained on (saved with the run as camera.json)."""
    path = Path(run) / "camera.json"
    if not path.is_file():
        raise DataError(f"{path} missing: the run predates saved camera set-ups; retrain it")
    return json.loads(path.read_text())


def load_checkpoint(path: Path) -> tuple[dict, Encoder]:
    """(state, model) of a checkpoint, the model built from the configuration saved with it."""
    state = torch.load(path, weights_only=False)
    if "model_config" not in state:
        raise DataError(f"{path} was written by an older version of the model (no model configuration saved with "
                        "it); retrain it, e.g. `make train-glossy`")
    try:
        model = Encoder(ModelConfig.from_dict(state["model_config"]))
    except ValueError as e:
        raise DataError(f"{path}: {e}") from e
    model.load_state_dict(state["model"])
    return state, model


def make_renderer(config: TrainConfig, seed: int, training: bool = False) -> Renderer:
    """The renderer of a run. ``training``: the losses read the soft mask ("dibr") or the coverage
    ("edge_aa"), so with "dibr" the anti-aliased coverage (only the image's alpha) is not computed."""
    filter_width = 0.0 if training and config.visibility == "dibr" else RasterSettings.filter_width
    settings = RasterSettings(cull_backfaces=True, visibility=config.visibility, filter_width=filter_width)
    return Renderer(config.shading, spp=config.spp, seed=seed, raster_settings=settings, compile=config.compile)


def train(config: TrainConfig, resume: bool = False, progress: bool = True) -> dict:
    rank, world = _setup_distributed()
    if config.threads:
        torch.set_num_threads(config.threads)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    data = TrainingData(config.dataset, config.image_size, envmaps=bool(config.light_supervision))
    model = make_model(config)
    opt = make_optimizer(model, config)
    ckpt = out / "checkpoint.pt"
    start = 0
    if resume and ckpt.exists():
        state, saved = load_checkpoint(ckpt)
        if saved.config != model.config:
            raise DataError(f"{ckpt} holds a model configured as {saved.config}, but this run asks for {model.config}; "
                            "choose another --out or the run's own settings")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["torch_rng"])
        start = state["iteration"]
    elif not resume and ckpt.exists():
        raise FileExistsError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
    ddp = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1])
    if rank == 0:
        (out / "config.json").write_text(json.dumps(asdict(config), indent=2))
        (out / "camera.json").write_text(json.dumps(dataset_camera_setup(config.dataset), indent=2))
    log_path = out / "log.csv"
    if rank == 0:
        _prepare_log(log_path, start)
    if start >= config.iterations:
        if rank == 0:
            print(f"{out}: already trained ({start} iterations); nothing to do")
        return {"model": model, "out": out}
    from tqdm import tqdm

    bar = tqdm(range(start, config.iterations), initial=start, total=config.iterations, disable=not progress or rank != 0,
               desc=f"{Path(config.dataset).name}/{config.shading}", unit="it")
    t_start = time.perf_counter()
    for it in bar:
        renderer = make_renderer(config, seed=config.seed * 7919 + it, training=True)  # MC noise differs per iteration, reproducibly
        batch = data.batch(it, config.batch_objects, config.seed, rank, world, config.shared_light,
                           config.swap_light)
        total, terms, snap = multiview_losses(ddp, renderer, batch, config, laplacian, it)
        check_finite({"total": total, **terms})
        opt.zero_grad(set_to_none=True)
        total.backward()
        check_finite_gradients(model)
        opt.step()
        done = it + 1
        if rank == 0:
            if done % config.log_every == 0 or done == config.iterations:
                with open(log_path, "a") as f:
                    f.write(",".join([str(done), f"{total.item():.6f}"] + [f"{terms[k].item():.6f}" for k in
                                     ("image", "iou", "laplacian", "gradient")] + [f"{time.perf_counter() - t_start:.2f}"]) + "\n")
                bar.set_postfix(loss=f"{total.item():.4f}", img=f"{terms['image'].item():.4f}", iou=f"{terms['iou'].item():.3f}")
            if done % config.snapshot_every == 0 or done == config.iterations:
                write_snapshot(out / "snapshots" / f"iter_{done:06d}.png", snap)
            if done % config.checkpoint_every == 0 or done == config.iterations:
                save_checkpoint(ckpt, model, opt, done, config)
    if rank == 0:
        plot_losses(log_path, out / "loss.png")
        summary = {"iterations": config.iterations, "seconds": time.perf_counter() - t_start,
                   "seconds_per_iteration": (time.perf_counter() - t_start) / max(1, config.iterations - start)}
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if world > 1:
        dist.destroy_process_group()
    return {"model": model, "out": out}


LOG_HEADER = "iteration,total,image,iou,laplacian,gradient,seconds\n"


def _prepare_log(log_path: Path, start: int) -> None:
    """A fresh log, or on resume the log cut back to the checkpoint (rows after it are logged again)."""
    rows = log_path.read_text().splitlines()[1:] if start and log_path.exists() else []
    kept = [r for r in rows if int(r.split(",")[0]) <= start]
    log_path.write_text(LOG_HEADER + "".join(r + "\n" for r in kept))


def write_snapshot(path: Path, snap: dict, rows: int = 4) -> None:
    """Input | re-render (in the input view; in the other view with ``cross_view_only``) | predicted albedo
    (the whole texture) | predicted light (world frame), for a few items."""
    n = min(rows, snap["input"].shape[0] // 2)
    pred = snap["pred"]
    s = snap["input"].shape[1]
    tiles = []
    for i in range(n):
        k = 2 * i
        inp = display_srgb(snap["input"][k, ..., :3] * snap["input"][k, ..., 3:])
        ren = display_srgb(snap["render"][int((snap["src"] == k).nonzero()[0])].detach())  # its first render
        tex = torch.nn.functional.interpolate(display_srgb(pred.texture[k].detach()).permute(2, 0, 1)[None], size=(s, 2 * s))[0].permute(1, 2, 0)
        light = pred.select([k]).light(snap["world_to_camera"][[k]]).to_envmap(s, 2 * s).image[0].detach()
        tiles.append(torch.cat([inp, ren, tex, tonemap_envmap(light)], 1))
    write_png(path, torch.cat(tiles, 0), srgb=False)


def plot_losses(log_path: Path, png_path: Path) -> None:
    with open(log_path) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    its = [int(r["iteration"]) for r in rows]
    fig, ax = pyplot().subplots(figsize=(7, 4))
    for key in ("total", "image", "iou", "laplacian", "gradient"):
        ax.plot(its, [float(r[key]) for r in rows], label=key)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(alpha=0.3)
    save_figure(fig, png_path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="cpu", help="cpu (default) | smoke | paper")
    ap.add_argument("--config", help="JSON file of TrainConfig fields (applied after the preset)")
    for f in fields(TrainConfig):
        if f.name in ("dataset", "out", "shading", "seed", "lobes", "iterations", "image_size", "spp", "batch_objects", "threads",
                      "w_albedo_consistency", "w_albedo_darker", "light_lr_scale", "flat_albedo_iterations"):
            ap.add_argument("--" + f.name.replace("_", "-"), type=type(f.default), default=None)
    ap.add_argument("--texture", choices=("projected", "global"), default=None,
                    help="albedo looked up from the input view (default) or decoded from the global code")
    ap.add_argument("--light-colour", choices=("white", "free"), default=None,
                    help="white-balanced light (default) or light of any colour")
    ap.add_argument("--visibility", choices=("dibr", "edge_aa"), default=None,
                    help="silhouette gradient: DIB-R's soft silhouette (default) or antialiased edges (Sec. F.1)")
    ap.add_argument("--light-scale", choices=("softplus", "log"), default=None,
                    help="light sharpness and intensity linear (default) or exponential in the head's output")
    ap.add_argument("--cross-view-only", action=argparse.BooleanOptionalAction, default=None,
                    help="render each prediction only in the other view of its pair, not in its input view (default: off)")
    ap.add_argument("--oracle-roughness", action=argparse.BooleanOptionalAction, default=None,
                    help="diagnostic: render with the GT roughness of each object instead of the predicted one")
    ap.add_argument("--light-supervision", choices=("map", "probe"), default=None,
                    help="diagnostic: supervise the light by the GT env map (on the map, or on the rough-metal probe)")
    ap.add_argument("--shared-light", action=argparse.BooleanOptionalAction, default=None,
                    help="light the cross-view renders with the light predicted for another object under the same "
                         "env map (default: off)")
    ap.add_argument("--swap-light", action=argparse.BooleanOptionalAction, default=None,
                    help="render each prediction in the other view of the same object under its other env map, "
                         "lit by the light predicted from that image (default: off)")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    overrides = json.loads(Path(args.config).read_text()) if args.config else {}
    overrides.update({k: v for k, v in vars(args).items() if k in {f.name for f in fields(TrainConfig)} and v is not None})
    try:
        config = TrainConfig.preset(args.preset, **overrides)
        if config.shading not in ("mc", "sg", "sh", "sh-sg"):
            raise ValueError(f"--shading {config.shading}: choose mc, sg, sh or sh-sg")
        manifest = Path(config.dataset, "manifest.json")
        if not manifest.exists():
            raise DataError(f"no dataset at {config.dataset} (manifest.json missing); run `make data` first")
        if "predict_metallic" not in overrides:
            # metallic parameter is predicted where the data has metals (the metallic set), else fixed at 0
            objects = json.loads(manifest.read_text()).get("objects", [])
            config.predict_metallic = any(o["material"]["metallic"] > 0 for o in objects)
        train(config, resume=args.resume, progress=not args.no_progress)
    except (DataError, ValueError, FileExistsError, FloatingPointError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
