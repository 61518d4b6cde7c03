"""A light prior learned from env maps alone: ``python -m pipelines.light_prior --maps data/light-prior``.

A low-dimensional model of what skies and rooms look like (Weber et al., 3DV 2018; Hold-Geoffroy et al., CVPR
2017, 2019): principal components of the **log luminance** of the procedural generator's maps
(:mod:`datagen.prior_maps`, no object rendered), on the light head's 16 x 32 grid, weighted by solid angle.
The sun is clipped out before the fit: the probe head keeps an explicit sun lobe (direction as a distribution
over the grid's cells, intensity, size), and the prior models what is left: the sky/ground split, the glow
around the sun, windows and walls. Each map is turned about the vertical at random a few times, so the
components do not depend on where the sun stands in azimuth.

The fit is cached in the maps' folder as ``prior.pt`` together with the maps' manifest (which names the
generator's digest); it is refitted when the maps change. A run copies the components into its model
(buffers saved with every checkpoint), so a trained run keeps the prior it was trained with.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from datagen.prior_maps import MANIFEST, chunk_path
from dibrpp import conventions
from dibrpp.cli_args import Parser, positive_int
from dibrpp.formatting import pyplot, save_figure
from dibrpp.io import DataError, atomic_path

PRIOR_FILE = "prior.pt"
FIGURE_FILE = "components.png"
COMPONENTS = 16
HEIGHT, WIDTH = 16, 32  # the probe head's grid
SUN_CLIP = 8.0  # cells brighter than this many times the map's median are clipped to it (the sun's share)
TURNS = 8  # random turns about the vertical per map


def read_manifest(folder: Path) -> tuple[dict, list[Path]]:
    """The manifest of a :mod:`datagen.prior_maps` folder and its chunk files, all of them present."""
    folder = Path(folder)
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (FileNotFoundError, NotADirectoryError):
        raise DataError(f"{folder}: no env maps for the light prior; make them with `make light-prior`") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{folder / MANIFEST}: not a manifest of env maps ({e}); rebuild with `make light-prior`") from None
    expected = manifest["count"] // manifest["chunk"]
    chunks = [chunk_path(folder, k) for k in range(expected)]
    done = sum(c.exists() for c in chunks)
    if done < expected:
        raise DataError(f"{folder}: {done} of {expected} chunks of maps; finish them with `make light-prior`")
    return manifest, chunks


def read_maps(folder: Path) -> tuple[np.ndarray, dict]:
    """(N, H, 2H, 3) maps and the manifest of a :mod:`datagen.prior_maps` folder."""
    manifest, chunks = read_manifest(folder)
    return np.concatenate([np.load(c) for c in chunks]), manifest


def log_luminance(maps: torch.Tensor) -> torch.Tensor:
    """(N, H, W, 3) linear maps -> (N, HEIGHT * WIDTH) log luminance on the head's grid, the sun clipped to
    SUN_CLIP x the map's median, each map's solid-angle-weighted mean removed (the prior models shape, not level)."""
    lum = (maps * maps.new_tensor(conventions.LUMINANCE_WEIGHTS)).sum(-1, keepdim=True).permute(0, 3, 1, 2)
    lum = torch.nn.functional.adaptive_avg_pool2d(lum, (HEIGHT, WIDTH)).flatten(1).clamp_min(1e-6)
    lum = torch.minimum(lum, SUN_CLIP * lum.median(1, keepdim=True).values)
    log = lum.log()
    w = solid_angle_weights(log.dtype)
    return log - (log * w).sum(1, keepdim=True)


def solid_angle_weights(dtype=torch.float32) -> torch.Tensor:
    """(HEIGHT * WIDTH,) each cell's share of the sphere."""
    w = conventions.equirect_solid_angles(HEIGHT, WIDTH, dtype=torch.float64).expand(-1, WIDTH).flatten()
    return (w / w.sum()).to(dtype)


def fit(maps: np.ndarray, components: int = COMPONENTS, seed: int = 0) -> dict:
    """Weighted PCA of the maps' log luminance (with TURNS random turns each): {"mean": (HEIGHT * WIDTH,),
    "basis": (K, HEIGHT * WIDTH) orthonormal under the solid-angle weights, "std": (K,), "explained": (K,)}."""
    g = torch.Generator().manual_seed(seed)
    x = log_luminance(torch.from_numpy(maps).double()).view(-1, HEIGHT, WIDTH)
    shifts = torch.randint(0, WIDTH, (len(x), TURNS), generator=g)
    x = torch.stack([torch.roll(x[i], int(s), dims=1) for i in range(len(x)) for s in shifts[i]]).flatten(1)
    w = solid_angle_weights(x.dtype)
    mean = x.mean(0)
    _, s, vt = torch.linalg.svd((x - mean) * w.sqrt(), full_matrices=False)
    basis = vt[:components] / w.sqrt()  # orthonormal under sum(w * a * b)
    variance = s ** 2 / (len(x) - 1)
    return {"mean": mean.float(), "basis": basis.float(), "std": variance[:components].sqrt().float(),
            "explained": (variance[:components].cumsum(0) / variance.sum()).float()}


def build(folder: Path, components: int = COMPONENTS) -> dict:
    """The prior of the maps in ``folder``: read from its cache (the maps are not read), or fitted and cached."""
    folder = Path(folder)
    manifest, _ = read_manifest(folder)
    key = {"manifest": manifest, "components": components, "sun_clip": SUN_CLIP, "grid": [HEIGHT, WIDTH], "turns": TURNS}
    cache = folder / PRIOR_FILE
    if cache.exists():
        prior = torch.load(cache, weights_only=True)
        if prior.get("key") == json.dumps(key, sort_keys=True):
            return prior
    prior = {**fit(read_maps(folder)[0], components), "key": json.dumps(key, sort_keys=True)}
    with atomic_path(cache) as tmp:
        torch.save(prior, tmp)
    return prior


def write_figure(prior: dict, path: Path, shown: int = 5) -> Path:
    """The mean log-luminance map and the first components (each times its spread), world frame, +Z on top."""
    plt = pyplot()
    maps = [prior["mean"]] + [prior["basis"][k] * prior["std"][k] for k in range(min(shown, len(prior["std"])))]
    fig, axes = plt.subplots(1, len(maps), figsize=(3 * len(maps), 2.0))
    for k, (ax, m) in enumerate(zip(axes, maps)):
        lim = float(m.abs().max())
        ax.imshow(m.view(HEIGHT, WIDTH).numpy(), cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax.set_title("mean" if k == 0 else f"component {k} (x its std. dev.)", fontsize=9)
        ax.axis("off")
    return save_figure(fig, path, dpi=80)


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.light_prior",
                description="fit the light prior (log-luminance PCA) to the env maps of datagen.prior_maps")
    ap.add_argument("--maps", default="data/light-prior", metavar="DIR", help="folder of maps (default: data/light-prior)")
    ap.add_argument("--components", type=positive_int, default=COMPONENTS, metavar="K",
                    help=f"principal components (default: {COMPONENTS})")
    args = ap.parse_args(argv)
    if not Path(args.maps).is_dir():
        ap.error(f"--maps {args.maps}: not a folder of env maps; make them with `make light-prior`")
    try:
        prior = build(Path(args.maps), args.components)
    except DataError as e:
        ap.error(str(e))
    write_figure(prior, Path(args.maps) / FIGURE_FILE)
    explained = ", ".join(f"{k}: {100 * float(prior['explained'][k - 1]):.0f} %" for k in (1, 2, 4, 8, len(prior["std"])))
    print(f"light prior: {len(prior['std'])} components of {HEIGHT} x {WIDTH} log luminance; variance explained by "
          f"the first {explained}; cached in {Path(args.maps) / PRIOR_FILE} (figure: {FIGURE_FILE})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
