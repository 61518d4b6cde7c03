"""Figure B: SG approximation of an env map. Fit error of K = 1..128 lobes vs K and vs parameter count."""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from dibrpp.conventions import equirect_solid_angles
from dibrpp.display import display_image
from dibrpp.formatting import pyplot, save_figure
from studies.common import ENV_EXPOSURE, fitted_sg, image_grid, procedural_envmap, write_study_table


@dataclass
class Sizes:
    height: int = 128
    width: int = 256
    lobes: tuple = (1, 2, 4, 8, 16, 32, 64, 128)
    seeds: tuple = (0, 1, 2)
    iters: int = 300


def envmap_fit_errors(approx: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    """(relative L2 of the radiance, RMSE of the display images) of (1, H, W, 3) maps, solid-angle weighted."""
    h, w = target.shape[1:3]
    omega = equirect_solid_angles(h, w, device=target.device).expand(h, w).unsqueeze(-1)  # (H, W, 1)
    rel = torch.sqrt((omega * (approx - target).square()).sum() / (omega * target.square()).sum())
    disp = (display_image(approx, ENV_EXPOSURE) - display_image(target, ENV_EXPOSURE)).square()
    return float(rel), float(torch.sqrt((omega * disp).sum() / (3 * omega.sum())))


def run(out: Path, s: Sizes, device) -> str:
    """Figure B: SG mixtures of K lobes fitted to env maps; error vs K and vs parameter count."""
    rows, cells = [], []
    for seed in s.seeds:
        env = procedural_envmap(s.height, s.width, seed)
        line = [display_image(env.image[0], ENV_EXPOSURE)]
        for k in s.lobes:
            t0 = time.perf_counter()
            light = fitted_sg(seed, k, s.iters, s.height, s.width)
            approx = light.to_envmap(s.height, s.width).image
            rel, disp = envmap_fit_errors(approx, env.image)
            rows.append(dict(envmap=seed, K=k, params=7 * k, params_pct=100 * 7 * k / env.image.numel(),
                             rel_l2_linear=rel, display_rmse=disp, fit_s=time.perf_counter() - t0))
            line.append(display_image(approx[0], ENV_EXPOSURE))
        cells.append(line)
    image_grid(cells, out / "fig_b_grid.png", [f"env {i}" for i in s.seeds], ["original"] + [f"K={k}" for k in s.lobes],
               "Fig. B: SG approximation of an env map", width_ratios=None, cell=1.3)

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for i, seed in enumerate(s.seeds):
        mine = [r for r in rows if r["envmap"] == seed]
        axes[0].semilogx([r["K"] for r in mine], [r["display_rmse"] for r in mine], "o-", color=f"C{i}",
                         label=f"env {seed}, display RMSE")
        axes[0].semilogx([r["K"] for r in mine], [r["rel_l2_linear"] for r in mine], "s--", color=f"C{i}",
                         label=f"env {seed}, linear rel. L2")
        axes[1].semilogx([r["params"] for r in mine], [r["display_rmse"] for r in mine], "o-", color=f"C{i}",
                         label=f"env {seed}")
    axes[1].axvline(s.height * s.width * 3, color="k", lw=0.8, label=f"image values ({s.height * s.width * 3})")
    axes[0].set_xlabel("K (SG lobes)")
    axes[0].set_ylabel("error")
    axes[1].set_xlabel("parameters (7 K)")
    axes[1].set_ylabel("display RMSE")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.suptitle(f"Fig. B: fit error vs K ({s.height}x{s.width} maps)", fontsize=9)
    save_figure(fig, out / "fig_b_error.png")
    note = (f"Fits by dibrpp.lights.fit_sg_to_envmap ({s.iters} iterations) of {s.height}x{s.width} maps "
            f"({s.height * s.width * 3} values). rel_l2_linear: solid-angle weighted relative L2 of the radiance "
            f"(what the fit minimises; dominated by the sun); display_rmse: of the sRGB maps at exposure {ENV_EXPOSURE}.")
    return write_study_table(rows, out, "fig_b_fit", note)



QUICK = Sizes(height=32, width=64, lobes=(1, 4, 16), seeds=(0,), iters=40)
