"""What the renderer studies share: the procedural scene (env maps, SG fits, orbit cameras, a metal), image
measures over the sphere's foreground, and writing tables and image grids."""
from __future__ import annotations

import functools
import math
from pathlib import Path

import torch
import torch.nn.functional as F

from dibrpp import Cameras, Material
from dibrpp.conventions import equirect_directions
from dibrpp.lights import EnvMap, SGLight, fit_sg_to_envmap
from dibrpp.formatting import markdown_table, pyplot, save_figure, write_csv

# ----------------------------------------------------------------------------- shared scene


def _blob(d: torch.Tensor, axis: torch.Tensor, radius_deg: float) -> torch.Tensor:
    """exp(-angle^2 / radius^2) around ``axis`` (an SG with lam = 1 / radius^2): a smooth light spot."""
    return torch.exp(((d * axis).sum(-1, keepdim=True) - 1) / math.radians(radius_deg) ** 2)


def _random_direction(g: torch.Generator, min_el: float, max_el: float) -> torch.Tensor:
    el = math.radians(min_el + (max_el - min_el) * float(torch.rand((), generator=g)))
    az = 2 * math.pi * float(torch.rand((), generator=g))
    return torch.tensor([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def procedural_envmap(height: int = 128, width: int = 256, seed: int = 0, supersample: int = 1,
                      sun: float = 1000.0) -> EnvMap:
    """An outdoor-like HDR map: sky gradient over a darker ground, a small sun of radiance ``sun``
    (radius 1 deg; at 1000 it brings ~20 % of all the light) and three coloured spots (radiance ~40, radius 4 deg).
    ``seed`` varies colours and positions; ``supersample`` area-averages a finer map (keeps the sun's
    energy in maps too coarse to point-sample it)."""
    g = torch.Generator().manual_seed(seed)
    d = equirect_directions(height * supersample, width * supersample)
    z = d[..., 2:]
    zenith = torch.tensor([0.15, 0.3, 0.8]) + 0.1 * torch.rand(3, generator=g)
    horizon = torch.tensor([0.8, 0.85, 0.9])
    ground = torch.tensor([0.25, 0.2, 0.15]) * (0.5 + torch.rand(3, generator=g))
    img = torch.where(z > 0, horizon + (zenith - horizon) * z.clamp_min(0).sqrt(), ground * (1 + z))
    img = img + sun * torch.tensor([1.0, 0.9, 0.75]) * _blob(d, _random_direction(g, 15, 60), 1.0)
    for _ in range(3):
        img = img + 40.0 * (0.3 + 0.7 * torch.rand(3, generator=g)) * _blob(d, _random_direction(g, -30, 50), 4.0)
    if supersample > 1:
        img = F.avg_pool2d(img.permute(2, 0, 1), supersample).permute(1, 2, 0)
    return EnvMap(img)


@functools.lru_cache(maxsize=None)
def fitted_sg(seed: int, lobes: int, iters: int, height: int, width: int) -> SGLight:
    """SG fit of ``procedural_envmap(height, width, seed)`` (cached: Fig. B, C and E share fits)."""
    return fit_sg_to_envmap(procedural_envmap(height, width, seed), lobes, iters=iters)


def orbit_views(n: int, res: int, device, elevations=(30.0, -10.0), distance: float = 3.0) -> Cameras:
    """n cameras evenly around the sphere, alternating between ``elevations`` (so the lower half of the
    light is seen too); the unit sphere fills most of a 45 deg field of view at distance 3."""
    az = torch.arange(n, dtype=torch.float32) * (360.0 / n)
    el = torch.tensor(elevations, dtype=torch.float32)[torch.arange(n) % len(elevations)]
    return Cameras.orbit(distance, el, az, 45.0, res, device=device)


ENV_EXPOSURE = 0.6  # display exposure for the env maps (their sky is ~1, the sun ~1000)


def fg_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (B, H, W, C) values over the foreground of mask (B, H, W)."""
    m = mask.unsqueeze(-1)
    return (values * m).sum() / (values.shape[-1] * m.sum()).clamp_min(1)


def metal(beta: float, device) -> Material:
    """Figures A and C shade a metal: all its light goes through the GGX lobe whose width beta sets."""
    return Material(albedo=torch.tensor([[0.9, 0.9, 0.9]], device=device), roughness=beta, metallic=1.0)


def foreground_psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB) of display images in [0, 1] over the foreground."""
    return float(-10 * torch.log10(fg_mean((a - b).square(), mask).clamp_min(1e-12)))



# ----------------------------------------------------------------------------- output


def write_study_table(rows: list[dict], out: Path, name: str, note: str = "") -> str:
    """``name``.csv and ``name``.md from rows of equal keys; floats at 4 significant digits. Returns the Markdown."""
    out.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0])
    write_csv(out / f"{name}.csv", rows, keys)
    text = markdown_table(keys, [[r[k] for k in keys] for r in rows], float_spec=".4g") + ("\n\n" + note if note else "")
    (out / f"{name}.md").write_text(text + "\n")
    return text


def image_grid(images: list[list[torch.Tensor]], path: Path, row_labels, col_labels, title: str = "",
               width_ratios=None, cell: float = 1.6) -> None:
    """A grid of display images (H, W, 3) in [0, 1]; None leaves a cell empty."""
    plt = pyplot()
    rows, cols = len(images), len(images[0])
    ratios = width_ratios or [1] * cols
    fig, axes = plt.subplots(rows, cols, figsize=(cell * sum(ratios) + 0.8, cell * rows + 0.6), squeeze=False,
                             gridspec_kw=dict(width_ratios=ratios))
    for i in range(rows):
        for j in range(cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if images[i][j] is None:
                ax.axis("off")
            else:
                ax.imshow(images[i][j].detach().cpu().clamp(0, 1).numpy(), interpolation="nearest")
            if i == 0 and col_labels:
                ax.set_title(col_labels[j], fontsize=8)
            if j == 0 and row_labels:
                ax.set_ylabel(row_labels[i], fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    save_figure(fig, path)
