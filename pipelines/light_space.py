"""Learn the space of env maps the light head predicts in: ``python -m pipelines.light_space --maps data/envmaps``.

Trains :class:`pipelines.model.light_space.LightSpace` (a small VAE) on a procedural env-map set
(``python -m datagen.envmap_set``; maps alone, no image), holding out its last maps, and writes the model
(``light_space.pt``), its card (``MODEL_CARD.md``: the reconstruction error on held-out maps beside two references)
and a figure of held-out maps against their reconstructions. ``make light-space`` renders the set and runs this.

The error is the mean absolute log-radiance error over the sphere at the space's 16 x 32 (a factor e^x), beside:
the set's mean map (the constant map: what a latent of nothing gives) and PCA with as many components as the latent
(the best linear space of that size, fitted to the same augmented training maps). Blender's bundled HDRIs (captured real
light) are scored too, and ``--check DIR`` scores the maps of any folder (e.g. a dataset's ``envmaps/``), each scaled
to the set's median mean radiance.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from datagen.envmap_set import read_set
from dibrpp.conventions import equirect_solid_angles
from dibrpp.cli_args import Parser, check_output_folder, non_negative_float, non_negative_int, positive_int
from dibrpp.display import display_image
from dibrpp.formatting import markdown_table, pyplot, save_figure
from dibrpp.io import DataError, atomic_path

from .model.light_space import FILE, LightSpace, SpaceConfig, area_downsample, augment, log_map_error, to_log_map

HELD_OUT = 0.15  # the share of the set's maps never trained on (its last ones)


def fit(space: LightSpace, maps: torch.Tensor, steps: int, batch: int, kl: float, lr: float, seed: int,
        progress: bool = True) -> list[float]:
    """Train ``space`` on (N, 3, H, 2H) radiance maps (augmented by turns and mirrors each step); returns the losses."""
    g = torch.Generator().manual_seed(seed)
    h = space.config.height
    with torch.no_grad():  # the mean map over every turn of every map: a row profile
        space.mean_map.copy_(to_log_map(maps, h).mean((0, 3), keepdim=True)
                             .expand_as(space.mean_map))
    opt = torch.optim.Adam(space.parameters(), lr=lr)
    losses = []
    for step in tqdm(range(steps), desc="light space", unit="step", disable=not progress):
        for group in opt.param_groups:  # cosine decay over the run
            group["lr"] = lr * 0.5 * (1 + np.cos(np.pi * step / steps))
        idx = torch.randint(0, len(maps), (batch,), generator=g)
        target = to_log_map(augment(maps[idx], g), h)
        mu, log_var = space.encode(target)
        z = mu + torch.randn(mu.shape, generator=g) * (0.5 * log_var).exp()
        recon = log_map_error(space.decode(z), target).mean()
        divergence = 0.5 * (mu ** 2 + log_var.exp() - 1 - log_var).sum(-1).mean()
        loss = recon + kl * divergence
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(recon.item())
    return losses


@torch.no_grad()
def pca_error(train_log: torch.Tensor, test_log: torch.Tensor, components: int) -> torch.Tensor:
    """(N,) the error of each test map's projection on the first ``components`` principal components of the
    training maps (flattened log maps, solid-angle weighted so the fit minimises what the metric counts)."""
    h, w = train_log.shape[2:]
    weight = equirect_solid_angles(h, w, dtype=train_log.dtype).view(1, 1, h, 1).expand(1, 3, h, w).flatten(1).sqrt()
    x = train_log.flatten(1) * weight
    mean = x.mean(0, keepdim=True)
    _, _, v = torch.linalg.svd(x - mean, full_matrices=False)
    basis = v[:components]
    y = test_log.flatten(1) * weight - mean
    projected = (y @ basis.T @ basis + mean) / weight
    return log_map_error(projected.view_as(test_log), test_log)


@torch.no_grad()
def scores(space: LightSpace, log_maps: torch.Tensor, train_log: torch.Tensor) -> dict:
    """Mean error of the space's reconstruction, of the mean map and of PCA of the latent's size, over ``log_maps``."""
    mu, _ = space.encode(log_maps)
    return {"space": float(log_map_error(space.decode(mu), log_maps).mean()),
            "mean map": float(log_map_error(space.mean_map.expand_as(log_maps), log_maps).mean()),
            "pca": float(pca_error(train_log, log_maps, space.config.latent).mean())}


def read_folder(folder: Path, height: int) -> tuple[torch.Tensor, list[str]]:
    """The maps of a folder of .exr / .hdr files, resampled to (N, 3, height, 2 height) radiance."""
    from datagen.envmap_files import load_envmap_source, scan_envmap_folder

    sources = scan_envmap_folder(folder)
    if not sources:
        raise DataError(f"{folder} holds no .exr or .hdr env map")
    maps = [load_envmap_source(folder, s, height) for s in sources]
    return torch.from_numpy(np.stack(maps)).permute(0, 3, 1, 2).float(), [s["file"] for s in sources]


def bundled_hdris() -> list[Path]:
    """Blender's bundled HDRIs (captured real light, never trained on), where bpy is installed."""
    from datagen.envmap_files import EnvmapError, blender_hdris

    try:
        return [blender_hdris()]
    except EnvmapError:
        return []


@torch.no_grad()
def figure(space: LightSpace, rows: list[tuple[str, torch.Tensor]], path: Path) -> None:
    """Each map (1, 3, H, W radiance at the space's size) beside its reconstruction, tone-mapped alike."""
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 2, figsize=(6, 1.6 * len(rows)), squeeze=False)
    for (name, radiance), (left, right) in zip(rows, axes):
        log_map = torch.log(radiance + 1e-3)
        decoded = space.decode(space.encode(log_map)[0]).exp().clamp_min(0)
        for ax, m, title in ((left, radiance, name), (right, decoded, "reconstructed")):  # both at the map's exposure
            ax.imshow(display_image(0.4 * m[0].permute(1, 2, 0) / radiance.mean().clamp_min(1e-8)).numpy())
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    save_figure(fig, path)


def main(argv=None) -> int:
    p = Parser(prog="python -m pipelines.light_space", description=__doc__)
    p.add_argument("--maps", type=Path, default=Path("data/envmaps"), help="the env-map set (python -m datagen.envmap_set)")
    p.add_argument("--out", type=Path, default=Path("models/light-space"), help="where the space and its card go")
    p.add_argument("--latent", type=positive_int, default=SpaceConfig.latent, help="latent dimensions")
    p.add_argument("--steps", type=positive_int, default=3000, help="training steps")
    p.add_argument("--batch", type=positive_int, default=32, help="maps per step")
    p.add_argument("--kl", type=non_negative_float, default=1e-3,
                   help="weight of the VAE's KL term (per latent, in log-error units)")
    p.add_argument("--train-maps", type=non_negative_int, default=0,
                   help="train on the first N training maps only (0: all): a curve")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the weights and the batches")
    p.add_argument("--check", type=Path, action="append", default=[], help="also score the maps of this folder")
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads (default: torch's)")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    config = SpaceConfig(latent=a.latent)
    if not a.maps.is_dir():
        p.error(f"--maps {a.maps}: not a folder; make the env-map set with `python -m datagen.envmap_set --out {a.maps}`")
    for folder in a.check:  # before the training, not after it
        if not folder.is_dir():
            p.error(f"--check {folder}: not a folder of env maps")
    try:
        check_output_folder("--out", a.out)
        raw, kinds = read_set(a.maps)
    except (DataError, FileNotFoundError, ValueError) as e:
        p.exit(2, f"error: {e}\n")
    maps = torch.from_numpy(raw).permute(0, 3, 1, 2)
    n_test = max(1, int(round(HELD_OUT * len(maps))))
    train_maps, test_maps = maps[:-n_test], maps[-n_test:]
    if a.train_maps:
        train_maps = train_maps[:a.train_maps]
    torch.manual_seed(a.seed)
    space = LightSpace(config)
    t0 = time.perf_counter()
    losses = fit(space, train_maps, a.steps, a.batch, a.kl, 2e-3, a.seed)
    seconds = time.perf_counter() - t0
    space.eval()
    g = torch.Generator().manual_seed(a.seed + 1)
    train_log = torch.cat([to_log_map(augment(train_maps, g), config.height) for _ in range(8)])
    test_log = to_log_map(test_maps, config.height)
    test_kinds = kinds[len(maps) - n_test:]
    results = {f"held-out ({n_test})": scores(space, test_log, train_log)}
    for kind in ("outdoor", "indoor"):
        chosen = [i for i, k in enumerate(test_kinds) if k == kind]
        if chosen:
            results[f"held-out {kind} ({len(chosen)})"] = scores(space, test_log[chosen], train_log)
    rows = [(f"held-out {test_kinds[i]}", test_maps[i:i + 1]) for i in range(min(4, n_test))]
    level = float(maps.mean((1, 2, 3)).median())
    folders = [(str(f), f) for f in a.check] + [("Blender's bundled HDRIs", f) for f in bundled_hdris()]
    for label, folder in folders:
        try:
            extra, names = read_folder(folder, maps.shape[2])
        except DataError as e:
            p.exit(2, f"error: {e}\n")
        extra = extra * (level / extra.mean((1, 2, 3), keepdim=True).clamp_min(1e-8))
        results[f"{label} ({len(names)})"] = scores(space, to_log_map(extra, config.height), train_log)
        rows += [(f"{folder.name}/{names[i]}", extra[i:i + 1]) for i in range(min(3, len(names)))]
    a.out.mkdir(parents=True, exist_ok=True)
    with atomic_path(a.out / FILE) as tmp:
        space.save(tmp)
    figure(space, [(n, area_downsample(m, config.height)) for n, m in rows],
           a.out / "reconstructions.png")
    summary = dict(config=vars(config), maps=str(a.maps), train_maps=len(train_maps), held_out=n_test, steps=a.steps,
                   batch=a.batch, kl=a.kl, seed=a.seed, seconds=round(seconds, 1), final_loss=float(np.mean(losses[-100:])),
                   errors=results)
    with atomic_path(a.out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1))
    table = markdown_table(["maps", "space", "mean map", f"PCA ({config.latent})"],
                           [[k, f"{v['space']:.3f}", f"{v['mean map']:.3f}", f"{v['pca']:.3f}"] for k, v in results.items()],
                           align="lrrr")
    card = (f"# Light space\n\nA VAE of env maps ({config.latent}-dim latent, {config.height} x {config.width} log radiance), "
            f"trained on {len(train_maps)} procedural maps of `{a.maps}` ({a.steps} steps of {a.batch}, KL weight {a.kl}, "
            f"seed {a.seed}, {seconds / 60:.1f} min). Retrain: `make light-space`.\n\n"
            f"Mean absolute log-radiance error over the sphere (a factor e^x), on maps it never saw:\n\n{table}\n\n"
            "![held-out maps and their reconstructions](reconstructions.png)\n")
    with atomic_path(a.out / "MODEL_CARD.md") as tmp:
        tmp.write_text(card)
    print(table)
    print(f"{a.out}: {FILE}, MODEL_CARD.md, metrics.json, reconstructions.png ({seconds:.0f} s of training)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
