"""Renderer studies of the supplementary's Sec. B and C, on a unit sphere under procedural HDR light.

    python -m pipelines.studies --out results/studies [--quick] [--only A,B,C,DE] [--device cpu|cuda]

A  sample count vs roughness (Fig. A): MC noise against a converged reference for N samples per
   pixel and roughness beta, BRDF sampling alone vs BRDF + env-map sampling with MIS.
B  SG approximation of an env map (Fig. B): fit error of K = 1..128 lobes vs K and parameter count.
C  light/material ambiguity (Fig. C): a sharp light on a rough sphere vs a smooth light (fitted to
   match) on a glossy one, compared in PSNR under SG and MC shading.
DE joint optimisation of light, albedo, roughness and specular from 24 views (Fig. D, E): SG shading
   for the table of Fig. E, MC shading for a subset of its rows.

Each study writes Markdown + CSV tables and PNG figures under --out and prints its table. Nothing is
downloaded: the env maps come from :func:`procedural_envmap`. --quick is a tiny version (smoke test).
"""
from __future__ import annotations

import argparse
import csv
import functools
import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from dibrpp import Cameras, Material, Renderer, icosphere, rasterize
from dibrpp.conventions import equirect_directions, equirect_solid_angles, linear_to_srgb
from dibrpp.io import write_png
from dibrpp.lights import EnvMap, SGLight, fit_sg_to_envmap
from dibrpp.renderer import build_gbuffer
from dibrpp.sg import sg_integral
from dibrpp.shading import MCShader

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


def to_display(linear: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    return linear_to_srgb(exposure * linear).clamp(0, 1)


ENV_EXPOSURE = 0.6  # display exposure for the env maps (their sky is ~1, the sun ~1000)


def fg_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of (B, H, W, C) values over the foreground of mask (B, H, W)."""
    m = mask.unsqueeze(-1)
    return (values * m).sum() / (values.shape[-1] * m.sum()).clamp_min(1)


def metal(beta: float, device) -> Material:
    """Figures A and C shade a metal: all its light goes through the GGX lobe whose width beta sets."""
    return Material(albedo=torch.tensor([[0.9, 0.9, 0.9]], device=device), roughness=beta, metallic=1.0)


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR (dB) of display images in [0, 1] over the foreground."""
    return float(-10 * torch.log10(fg_mean((a - b).square(), mask).clamp_min(1e-12)))


# ----------------------------------------------------------------------------- output


def write_table(rows: list[dict], out: Path, name: str, note: str = "") -> str:
    """``name``.csv and ``name``.md from rows of equal keys; floats at 4 significant digits."""
    out.mkdir(parents=True, exist_ok=True)
    keys = list(rows[0])
    with open(out / f"{name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    fmt = lambda v: f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r[k]) for k in keys) + " |" for r in rows]
    text = "\n".join(lines) + ("\n\n" + note if note else "")
    (out / f"{name}.md").write_text(text + "\n")
    return text


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def image_grid(images: list[list[torch.Tensor]], path: Path, row_labels, col_labels, title: str = "",
               width_ratios=None, cell: float = 1.6) -> None:
    """A grid of display images (H, W, 3) in [0, 1]; None leaves a cell empty."""
    plt = _pyplot()
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
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------- Figure A


@dataclass
class SizesA:
    res: int = 96
    betas: tuple = (0.0, 0.1, 0.2, 0.4)
    spps: tuple = (4, 16, 64, 256, 1024)
    ref_passes: int = 8  # reference: 2 independent halves of ref_passes // 2 renders of max(spps) spp each
    noise_free: float = 0.01  # display RMSE below which we call an image noise-free (~2.5 / 255)


def mc_image(g, env: EnvMap, frags, spp: int, mis: bool, seed: int) -> torch.Tensor:
    return frags.to_image(MCShader(spp=spp, mis=mis, seed=seed)(g, env))


def unbiased_rmse(x: torch.Tensor, ref1: torch.Tensor, ref2: torch.Tensor, mask: torch.Tensor) -> float:
    """RMSE of x against the mean of the references, without the references' own noise:
    E[(x - r1)(x - r2)] = E[(x - E r)^2] for independent x, r1, r2."""
    return math.sqrt(max(float(fg_mean((x - ref1) * (x - ref2), mask)), 0.0))


def study_a(out: Path, s: SizesA, device) -> str:
    """Figure A: MC noise vs sample count N and roughness beta, with and without env-map sampling + MIS."""
    env = procedural_envmap().to(device)
    sphere = icosphere(4, device=device)
    cams = orbit_views(1, s.res, device, elevations=(20.0,))
    frags = rasterize(sphere, cams)
    mask = frags.mask
    rows, grids, curves = [], {False: [], True: []}, {}
    for beta in s.betas:
        g = build_gbuffer(sphere, cams, metal(beta, device), frags)
        half = s.ref_passes // 2
        refs = [sum(mc_image(g, env, frags, max(s.spps), True, 1000 + 100 * h + i) for i in range(half)) / half
                for h in range(2)]
        ref_disp = [to_display(r) for r in refs]
        ref_spp = s.ref_passes * max(s.spps)
        for mis in (False, True):
            for spp in s.spps:
                img = to_display(mc_image(g, env, frags, spp, mis, seed=spp))
                rmse = unbiased_rmse(img, *ref_disp, mask)
                rows.append(dict(beta=beta, alpha=max(beta ** 2, 1e-3), sampling="BRDF+env MIS" if mis else "BRDF",
                                 spp=spp, display_rmse=rmse))
                curves.setdefault((beta, mis), []).append(rmse)
                grids[mis].append(img[0])
        for mis in (False, True):
            grids[mis].append(to_display(0.5 * (refs[0] + refs[1]))[0])

    ncol = len(s.spps) + 1
    labels = [f"N={n}" for n in s.spps] + [f"reference\n({ref_spp} spp, MIS)"]
    for mis, name in ((False, "brdf"), (True, "mis")):
        cells = [grids[mis][i * ncol:(i + 1) * ncol] for i in range(len(s.betas))]
        image_grid(cells, out / f"fig_a_grid_{name}.png", [f"β={b}" for b in s.betas], labels,
                   f"Fig. A: metal sphere, {'BRDF + env-map sampling (MIS)' if mis else 'BRDF sampling only'}")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for i, beta in enumerate(s.betas):
        for mis, style in ((False, "--"), (True, "-")):
            ax.loglog(s.spps, [max(v, 1e-5) for v in curves[(beta, mis)]], style, marker="o", color=f"C{i}",
                      label=f"β={beta} {'MIS' if mis else 'BRDF'}")
    ax.loglog(s.spps, [curves[(s.betas[-1], False)][0] * math.sqrt(s.spps[0] / n) for n in s.spps], ":", color="gray",
              label="∝ 1/√N")
    ax.axhline(s.noise_free, color="k", lw=0.8)
    ax.set_xticks(s.spps, [str(n) for n in s.spps])
    ax.minorticks_off()
    ax.set_xlabel("samples per pixel N")
    ax.set_ylabel("display RMSE vs reference")
    ax.legend(fontsize=7, ncol=2)
    ax.set_title("Fig. A: noise vs N (dashed: BRDF sampling, solid: + env-map MIS)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "fig_a_noise.png", dpi=100)
    plt.close(fig)

    needed = []
    for beta in s.betas:
        for mis in (False, True):
            ok = [n for n, v in zip(s.spps, curves[(beta, mis)]) if v <= s.noise_free]
            needed.append(dict(beta=beta, sampling="BRDF+env MIS" if mis else "BRDF",
                               min_spp_noise_free=ok[0] if ok else f">{max(s.spps)}",
                               rmse_at_max_spp=curves[(beta, mis)][-1]))
    note = (f"Display RMSE (sRGB, clipped) over the sphere against a {ref_spp}-spp MIS reference, with the "
            "reference's own noise removed (two independent halves). GGX alpha = beta^2 (alpha >= 1e-3). "
            f"Noise-free: RMSE <= {s.noise_free}. Paper: beta = 0.2 needs N = 256, beta = 0.4 is noisy at N = 1024; its "
            "text maps alpha = (beta + 1)^2 / 8, under which its beta in [0, 0.4] would be our beta in [0.35, 0.49].")
    write_table(rows, out, "fig_a_noise")
    return write_table(needed, out, "fig_a_summary", note)


# ----------------------------------------------------------------------------- Figure B


@dataclass
class SizesB:
    height: int = 128
    width: int = 256
    lobes: tuple = (1, 2, 4, 8, 16, 32, 64, 128)
    seeds: tuple = (0, 1, 2)
    iters: int = 300


def envmap_errors(approx: torch.Tensor, target: torch.Tensor) -> tuple[float, float]:
    """(relative L2 of the radiance, RMSE of the display images) of (1, H, W, 3) maps, solid-angle weighted."""
    h, w = target.shape[1:3]
    omega = equirect_solid_angles(h, w, device=target.device).expand(h, w).unsqueeze(-1)  # (H, W, 1)
    rel = torch.sqrt((omega * (approx - target).square()).sum() / (omega * target.square()).sum())
    disp = (to_display(approx, ENV_EXPOSURE) - to_display(target, ENV_EXPOSURE)).square()
    return float(rel), float(torch.sqrt((omega * disp).sum() / (3 * omega.sum())))


def study_b(out: Path, s: SizesB, device) -> str:
    """Figure B: SG mixtures of K lobes fitted to env maps; error vs K and vs parameter count."""
    rows, cells = [], []
    for seed in s.seeds:
        env = procedural_envmap(s.height, s.width, seed)
        line = [to_display(env.image[0], ENV_EXPOSURE)]
        for k in s.lobes:
            t0 = time.perf_counter()
            light = fitted_sg(seed, k, s.iters, s.height, s.width)
            approx = light.to_envmap(s.height, s.width).image
            rel, disp = envmap_errors(approx, env.image)
            rows.append(dict(envmap=seed, K=k, params=7 * k, params_pct=100 * 7 * k / env.image.numel(),
                             rel_l2_linear=rel, display_rmse=disp, fit_s=time.perf_counter() - t0))
            line.append(to_display(approx[0], ENV_EXPOSURE))
        cells.append(line)
    image_grid(cells, out / "fig_b_grid.png", [f"env {i}" for i in s.seeds], ["original"] + [f"K={k}" for k in s.lobes],
               "Fig. B: SG approximation of an env map", width_ratios=None, cell=1.3)

    plt = _pyplot()
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
    fig.tight_layout()
    fig.savefig(out / "fig_b_error.png", dpi=100)
    plt.close(fig)
    note = (f"Fits by dibrpp.lights.fit_sg_to_envmap ({s.iters} iterations) of {s.height}x{s.width} maps "
            f"({s.height * s.width * 3} values). rel_l2_linear: solid-angle weighted relative L2 of the radiance "
            f"(what the fit minimises; dominated by the sun); display_rmse: of the sRGB maps at exposure {ENV_EXPOSURE}.")
    return write_table(rows, out, "fig_b_fit", note)


# ----------------------------------------------------------------------------- Figure C


@dataclass
class SizesC:
    res: int = 128
    views: int = 4  # the smooth light is fitted in view 0; the others show how far the match carries
    lobes: int = 16
    fit_iters: int = 300
    iters: int = 300
    beta_sharp: float = 0.4  # sharp light, rough sphere
    beta_smooth: float = 0.1  # smooth light, glossy sphere
    mc_spp: int = 1024
    mc_iters: int = 100  # MC fit of the smooth light, from the SG fit
    mc_fit_spp: int = 16


def blurred_light(light: SGLight, beta_from: float, beta_to: float, n_dot_v: float = 0.7) -> SGLight:
    """The light that a sphere of roughness ``beta_to`` must see to look like one of ``beta_from`` under
    ``light``: the warped NDF lobe (sharpness 1 / (2 alpha^2 n.v)) convolved with a light lobe adds their
    variances 1 / lam, so 1 / lam' = 1 / lam + 2 n.v (alpha_from^2 - alpha_to^2); the lobe's integral
    2 pi a / lam is kept."""
    extra = 2 * n_dot_v * (max(beta_from, 0.032) ** 4 - max(beta_to, 0.032) ** 4)
    lam = 1 / (1 / light.sharpness + extra)
    return SGLight(light.axis, lam, light.amplitude * (lam / light.sharpness).unsqueeze(-1))


def match_light(render, target: torch.Tensor, mask: torch.Tensor, init: SGLight, iters: int, lr: float = 0.02) -> SGLight:
    """Fit all SG parameters of ``init`` (axes, log-sharpness, log-amplitude) so that the display image
    ``render(light)`` matches ``target`` (display MSE: what PSNR scores)."""
    params = [init.axis.clone(), init.sharpness.log(), init.amplitude.clamp_min(1e-8).log()]
    for p in params:
        p.requires_grad_(True)
    light = lambda: SGLight(params[0], params[1].exp(), params[2].exp())  # noqa: E731
    opt = torch.optim.Adam(params, lr=lr)
    for _ in range(iters):
        opt.zero_grad()
        fg_mean((to_display(render(light())) - target).square(), mask).backward()
        opt.step()
    return SGLight(params[0].detach(), params[1].exp().detach(), params[2].exp().detach())


ENV_FOR_SG = (256, 512)  # env-map size that MC renders an SG light at: ~0.7 deg texels resolve lam ~ 400


def study_c(out: Path, s: SizesC, device) -> str:
    """Figure C: sharp light + rough sphere vs smooth light + glossy sphere, the smooth light fitted in one view."""
    sphere = icosphere(4, device=device)
    cams = orbit_views(s.views, s.res, device)
    frags, frags0 = rasterize(sphere, cams), rasterize(sphere, cams[[0]])
    sg, mc = Renderer("sg"), Renderer("mc", spp=s.mc_spp, mis=True, seed=0)
    mc_target, mc_fit = Renderer("mc", spp=s.mc_spp, mis=True, seed=1), Renderer("mc", spp=s.mc_fit_spp, mis=True)
    sharp = fitted_sg(0, s.lobes, s.fit_iters, 128, 256).to(device)
    with torch.no_grad():  # (the MC target has its own random numbers: the fit must not learn the scoring noise)
        target_sg = to_display(sg(sphere, cams, metal(s.beta_sharp, device), sharp, frags).rgb)
        target_mc = to_display(mc_target(sphere, cams[[0]], metal(s.beta_sharp, device), sharp.to_envmap(*ENV_FOR_SG),
                                          frags0).rgb)
    # start from the closed-form blur of every lobe, fit the whole light to view 0 under SG shading, then
    # (from there) under MC shading, where the GGX lobe has tails that its single-SG approximation lacks
    glossy = metal(s.beta_smooth, device)
    smooth_sg = match_light(lambda lt: sg(sphere, cams[[0]], glossy, lt, frags0).rgb, target_sg[:1], frags0.mask,
                            blurred_light(sharp, s.beta_sharp, s.beta_smooth), s.iters)
    smooth_mc = match_light(lambda lt: mc_fit(sphere, cams[[0]], glossy, lt.to_envmap(*ENV_FOR_SG), frags0).rgb,
                            target_mc, frags0.mask, smooth_sg, s.mc_iters)
    cases = {f"sharp light, β={s.beta_sharp}": (sharp, s.beta_sharp),
             f"smooth light fitted (SG), β={s.beta_smooth}": (smooth_sg, s.beta_smooth),
             f"smooth light fitted (MC), β={s.beta_smooth}": (smooth_mc, s.beta_smooth),
             f"sharp light, β={s.beta_smooth}": (sharp, s.beta_smooth)}
    renders = {}
    with torch.no_grad():
        for name, (light, beta) in cases.items():
            env = light.to_envmap(*ENV_FOR_SG)
            renders[name] = dict(env=to_display(env.image[0], ENV_EXPOSURE),
                                 sg=to_display(sg(sphere, cams, metal(beta, device), light, frags).rgb),
                                 mc=to_display(mc(sphere, cams[[0]], metal(beta, device), env, frags0).rgb))
    names = list(cases)
    ref, mask = renders[names[0]], frags.mask
    rows = [dict(case=n, beta=cases[n][1], median_lobe_sharpness=float(cases[n][0].sharpness.median()),
                 psnr_sg_view0_db=psnr(renders[n]["sg"][:1], ref["sg"][:1], mask[:1]),
                 psnr_sg_other_views_db=psnr(renders[n]["sg"][1:], ref["sg"][1:], mask[1:]),
                 psnr_mc_view0_db=psnr(renders[n]["mc"], ref["mc"], mask[:1])) for n in names[1:]]
    diff = lambda a, b: (10 * (a - b).abs()).clamp(0, 1)  # noqa: E731
    cells = [[renders[n]["env"], renders[n]["sg"][0], renders[n]["mc"][0], renders[n]["sg"][1]] for n in names[:3]]
    cells.append([None] + [diff(a, b) for a, b in zip(cells[0][1:], cells[1][1:])])
    cells.append([None, None, diff(cells[0][2], cells[2][2]), None])
    image_grid(cells, out / "fig_c_ambiguity.png",
               names[:3] + ["|row 1 - row 2| x 10", "|row 1 - row 3| x 10"],
               ["light", "SG, view 0 (fitted)", f"MC {s.mc_spp} spp, view 0", "SG, view 1 (not fitted)"],
               f"Fig. C: PSNR in view 0: {rows[0]['psnr_sg_view0_db']:.1f} dB (SG fit, SG), "
               f"{rows[1]['psnr_mc_view0_db']:.1f} dB (MC fit, MC)", width_ratios=[2, 1, 1, 1], cell=1.8)
    note = (f"PSNR of the display images over the sphere against '{names[0]}' rendered the same way. Metal "
            f"sphere (base colour 0.9). The smooth lights (all parameters of {s.lobes} SG lobes) were fitted to view "
            f"0 only; the other {s.views - 1} orbit views show how far the match carries. MC renders a light as a "
            f"{ENV_FOR_SG[0]}x{ENV_FOR_SG[1]} env map at {s.mc_spp} spp (its noise bounds the MC PSNR). Last row: the "
            "roughness change alone, for scale.")
    return write_table(rows, out, "fig_c_ambiguity", note)


# ----------------------------------------------------------------------------- Figures D and E

# Fig. E of the supplementary (SG shading): beta_gt -> two cases of (beta_ini, beta_opt, s_opt); s_gt = 0.5, s_ini = 0.2.
PAPER_FIG_E = {
    0.05: ((0.20, 0.049, 0.567), (0.40, 0.049, 0.562)),
    0.10: ((0.05, 0.055, 0.603), (0.30, 0.055, 0.608)),
    0.20: ((0.05, 0.181, 0.613), (0.40, 0.184, 0.615)),
    0.30: ((0.10, 0.293, 0.625), (0.40, 0.294, 0.625)),
    0.40: ((0.05, 0.389, 0.629), (0.20, 0.389, 0.625)),
}
S_GT, S_INI = 0.5, 0.2
BETA_TOLERANCE = 0.02  # our goal beyond the paper: |beta_opt - beta_gt| <= 0.02 on every row


@dataclass
class SizesDE:
    res: int = 48
    views: int = 24
    views_per_step: int = 6  # the views are cycled in fixed groups (rasterized once)
    texture: tuple = (32, 64)
    lobes: int = 32
    fit_iters: int = 300
    iters: int = 1200
    lr: float = 0.05
    compile: bool = True  # SG shading through torch.compile (~3x faster steps, ~20 s to compile once)
    betas: tuple = tuple(PAPER_FIG_E)
    # MC (Fig. D) is dearer per step and noisy: a subset of (beta_gt, case index) rows, under a map whose
    # GT renders converge at an affordable spp (no sun: see the note of the table)
    mc_rows: tuple = ((0.1, 0), (0.3, 1))
    mc_env: tuple = (16, 32)
    mc_sun: float = 0.0
    mc_spp: int = 16
    mc_gt_spp: int = 1024
    mc_eval_spp: int = 256
    mc_iters: int = 500


def procedural_texture(height: int, width: int, device=None) -> torch.Tensor:
    """(1, H, W, 3) linear albedo: a 4 x 8 checker of two colours, darker towards the bottom."""
    v = torch.arange(height, device=device).view(-1, 1) * 4 // height
    u = torch.arange(width, device=device).view(1, -1) * 8 // width
    a, b = torch.tensor([0.7, 0.35, 0.2], device=device), torch.tensor([0.2, 0.45, 0.7], device=device)
    img = torch.where(((u + v) % 2 == 0).unsqueeze(-1), a, b)
    shade = 0.7 + 0.3 * torch.linspace(1, 0, height, device=device).view(-1, 1, 1)
    return (img * shade).unsqueeze(0)


@dataclass
class Views:
    """Fixed shape and cameras of a joint optimisation, rasterized once per group of views."""

    sphere: object
    groups: list  # [(Cameras, Fragments)]

    @classmethod
    def make(cls, s: SizesDE, device) -> "Views":
        sphere = icosphere(3, device=device)
        cams = orbit_views(s.views, s.res, device)
        n = s.views // s.views_per_step
        return cls(sphere, [(c, rasterize(sphere, c)) for c in (cams[list(range(g, s.views, n))] for g in range(n))])

    @property
    def mask(self) -> torch.Tensor:
        return torch.cat([f.mask for _, f in self.groups])

    def render(self, renderer, material: Material, light) -> torch.Tensor:
        """(views, H, W, 3) linear images, in group order."""
        return torch.cat([renderer(self.sphere, c, material, light, f).rgb for c, f in self.groups])


class SGParams:
    """SG light as unconstrained tensors: axes, log-sharpness and log-energy (lobe integral, RGB) per lobe.

    With the energy as a variable, sharpening a lobe moves no light in or out (with the peak amplitude as
    a variable it darkens the lobe), so a lobe can focus on a small bright source: with amplitudes, the
    joint optimisation never formed the highlights and stalled at a diffuse-only look."""

    def __init__(self, light: SGLight):
        energy = light.amplitude * sg_integral(light.sharpness).unsqueeze(-1)
        self.tensors = [light.axis.clone(), light.sharpness.log(), energy.clamp_min(1e-6).log()]

    def light(self) -> SGLight:
        axis, log_lam, log_energy = self.tensors
        return SGLight(axis, log_lam.exp(), log_energy.exp() / sg_integral(log_lam.exp()).unsqueeze(-1))

    def display(self) -> torch.Tensor:
        return self.light().to_envmap(64, 128).image[0]


class EnvParams:
    """Env map as log-radiance texels (HDR: bright sources are orders of magnitude above the sky)."""

    def __init__(self, env: EnvMap):
        self.tensors = [env.image.clamp_min(1e-6).log()]

    def light(self) -> EnvMap:
        return EnvMap(self.tensors[0].exp())

    def display(self) -> torch.Tensor:
        return self.tensors[0][0].exp()


def initial_light(shading: str, s: SizesDE, device):
    """The same start for every row: a dim grey light (SG: lobes at random axes, lam = 10)."""
    if shading == "sg":
        g = torch.Generator().manual_seed(0)
        axis = F.normalize(torch.randn(1, s.lobes, 3, generator=g), dim=-1).to(device)
        return SGParams(SGLight(axis, torch.full((1, s.lobes), 10.0, device=device),
                                torch.full((1, s.lobes, 3), 0.1, device=device)))
    return EnvParams(EnvMap(torch.full((1, *s.mc_env, 3), 0.5, device=device)))


def gt_light(shading: str, s: SizesDE, device):
    """SG: the K-lobe fit of the procedural map; MC: the map itself at the optimised map's size."""
    if shading == "sg":
        return SGParams(fitted_sg(0, s.lobes, s.fit_iters, 128, 256).to(device))
    return EnvParams(procedural_envmap(*s.mc_env, seed=0, supersample=4, sun=s.mc_sun).to(device))


def log_l1(img: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Foreground L1 of log(1 + radiance): highlights count without clipping (display space would clip)."""
    return fg_mean((torch.log1p(img) - torch.log1p(gt)).abs(), mask)


def joint_optimisation(views: Views, gts: list, shading: str, beta_ini: float, s: SizesDE, device) -> dict:
    """Adam on light, albedo texture, roughness and specular from the foreground image loss only, one
    group of views per step; bounds kept by projection after each step. Returns the results and loss curve."""
    light = initial_light(shading, s, device)
    tex = torch.full((1, *s.texture, 3), 0.5, device=device)
    beta = torch.tensor([beta_ini], device=device)
    spec = torch.tensor([S_INI], device=device)
    for p in light.tensors + [tex, beta, spec]:
        p.requires_grad_(True)
    renderer = Renderer("sg", compile=s.compile) if shading == "sg" else Renderer("mc", spp=s.mc_spp, mis=True)
    iters = s.iters if shading == "sg" else s.mc_iters
    opt = torch.optim.Adam([{"params": light.tensors + [tex]}, {"params": [beta, spec], "lr": s.lr / 3}], lr=s.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, iters, eta_min=s.lr / 30)
    curve = []
    for it in range(iters):
        (cams, frags), gt = views.groups[it % len(views.groups)], gts[it % len(views.groups)]
        mat = Material(albedo=tex, roughness=beta, specular=spec, wrap_u=True)
        loss = log_l1(renderer(views.sphere, cams, mat, light.light(), frags).rgb, gt, frags.mask)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            tex.clamp_(0, 1)
            beta.clamp_(0.035, 1)  # below ~0.032 alpha = beta^2 hits its floor and beta gets no gradient
            spec.clamp_(0, 2)
        curve.append(loss.item())
    return dict(light=light, tex=tex.detach(), beta=beta.item(), spec=spec.item(), curve=curve)


def study_de(out: Path, s: SizesDE, device) -> str:
    """Figures D (MC) and E (SG): joint optimisation from 24 views for each beta_gt and two initialisations."""
    views = Views.make(s, device)
    mask = views.mask
    gt_tex = procedural_texture(*s.texture, device=device)
    rows = []
    for shading in ("sg", "mc"):
        cases = [(b, c) for b in s.betas for c in (0, 1)] if shading == "sg" else list(s.mc_rows)
        gt_l, init_l = gt_light(shading, s, device), initial_light(shading, s, device)
        # GT images (MC: at high spp) and the renderer that scores the results (MC: fewer spp, its own seed)
        gt_renderer = Renderer("sg") if shading == "sg" else Renderer("mc", spp=s.mc_gt_spp, mis=True, seed=1)
        scorer = Renderer("sg") if shading == "sg" else Renderer("mc", spp=s.mc_eval_spp, mis=True, seed=2)
        grid = {}
        for beta_gt, case in cases:
            with torch.no_grad():
                gt_all = views.render(gt_renderer, Material(albedo=gt_tex, roughness=beta_gt, specular=S_GT, wrap_u=True),
                                      gt_l.light())
            beta_ini, paper_beta, paper_s = PAPER_FIG_E[beta_gt][case]
            t0 = time.perf_counter()
            r = joint_optimisation(views, list(gt_all.split(s.views_per_step)), shading, beta_ini, s, device)
            seconds = time.perf_counter() - t0
            with torch.no_grad():
                init_mat = Material(albedo=torch.full_like(gt_tex, 0.5), roughness=beta_ini, specular=S_INI, wrap_u=True)
                img_init = views.render(scorer, init_mat, init_l.light())
                opt_mat = Material(albedo=r["tex"], roughness=r["beta"], specular=r["spec"], wrap_u=True)
                img_opt = views.render(scorer, opt_mat, r["light"].light())
            l1 = lambda img: float(fg_mean((to_display(img) - to_display(gt_all)).abs(), mask))  # noqa: E731
            err = abs(r["beta"] - beta_gt)
            rows.append(dict(shading=shading.upper(), beta_gt=beta_gt, beta_ini=beta_ini, beta_opt=r["beta"],
                             abs_err=err, within_tol="yes" if err <= BETA_TOLERANCE else "no", s_gt=S_GT, s_ini=S_INI,
                             s_opt=r["spec"], image_l1_init=l1(img_init), image_l1_opt=l1(img_opt),
                             loss_first=r["curve"][0], loss_last=sum(r["curve"][-len(views.groups):]) / len(views.groups),
                             # the paper's numbers are for SG shading (Fig. E)
                             paper_beta_opt=paper_beta if shading == "sg" else "",
                             paper_s_opt=paper_s if shading == "sg" else "", seconds=seconds))
            print(f"  {shading} beta_gt={beta_gt} beta_ini={beta_ini}: beta_opt={r['beta']:.3f} s_opt={r['spec']:.3f} "
                  f"image L1 {rows[-1]['image_l1_init']:.4f} -> {rows[-1]['image_l1_opt']:.4f} ({seconds:.0f} s)")
            tag = f"{shading}_beta{beta_gt:.2f}_ini{beta_ini:.2f}"
            write_png(out / f"de_{tag}_env.png", ENV_EXPOSURE * r["light"].display())
            write_png(out / f"de_{tag}_texture.png", r["tex"][0])
            write_png(out / f"de_{tag}_renders.png", torch.cat(list(img_opt[::max(1, s.views // 6)]), 1))
            line = grid.setdefault(beta_gt, [to_display(gt_all[0])] + [None] * 6)
            line[1 + 3 * case:4 + 3 * case] = [to_display(r["light"].display(), ENV_EXPOSURE), linear_to_srgb(r["tex"][0]),
                                               to_display(img_opt[0])]
        head = [[None, to_display(gt_l.display(), ENV_EXPOSURE), linear_to_srgb(gt_tex[0])] + [None] * 4,
                [None, to_display(init_l.display(), ENV_EXPOSURE), linear_to_srgb(torch.full_like(gt_tex[0], 0.5)),
                 to_display(img_init[0])] + [None] * 3]
        image_grid(head + list(grid.values()), out / ("fig_e_sg.png" if shading == "sg" else "fig_d_mc.png"),
                   ["GT light, albedo", "init"] + [f"β_gt={b}" for b in grid],
                   ["GT render"] + [f"{part} (case {c})" for c in (1, 2) for part in ("light", "albedo", "render")],
                   f"Fig. {'E: SG' if shading == 'sg' else 'D: MC'} shading, joint optimisation of light, albedo, β, s "
                   f"(β_ini per row: paper's Fig. E)", width_ratios=[1, 2, 2, 1, 2, 2, 1])
    sg_rows = [r for r in rows if r["shading"] == "SG"]
    note = (f"{s.views} views of a unit sphere at {s.res}^2, {s.iters} (SG) / {s.mc_iters} (MC) Adam steps on log-L1 over "
            f"the foreground; image_l1 is in display space over all views (MC scored at {s.mc_eval_spp} spp against GT at "
            f"{s.mc_gt_spp} spp). s = Principled's Specular IOR Level (0.5: F0 = 0.04). SG: GT light = the {s.lobes}-lobe "
            f"fit of procedural env 0; MC: procedural env 0 at {s.mc_env[0]}x{s.mc_env[1]} without its sun (with it, "
            f"GT renders stay ~10 % noisy at 1024 spp). Goal |beta_opt - beta_gt| <= {BETA_TOLERANCE}: met on "
            f"{sum(r['within_tol'] == 'yes' for r in sg_rows)}/{len(sg_rows)} SG rows.")
    return write_table(rows, out, "fig_de_joint", note)


# ----------------------------------------------------------------------------- driver

QUICK = dict(
    A=SizesA(res=24, betas=(0.0, 0.2, 0.4), spps=(4, 16, 64), ref_passes=4),
    B=SizesB(height=32, width=64, lobes=(1, 4, 16), seeds=(0,), iters=40),
    C=SizesC(res=32, views=2, lobes=8, fit_iters=40, iters=30, mc_spp=16, mc_iters=5, mc_fit_spp=4),
    DE=SizesDE(res=24, views=4, views_per_step=2, texture=(8, 16), lobes=8, fit_iters=40, iters=60, compile=False,
               betas=(0.2,), mc_rows=((0.2, 0),), mc_env=(8, 16), mc_spp=4, mc_gt_spp=64, mc_eval_spp=64, mc_iters=30),
)
STUDIES = dict(A=(study_a, SizesA), B=(study_b, SizesB), C=(study_c, SizesC), DE=(study_de, SizesDE))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/studies")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--only", default="A,B,C,DE", help="comma-separated subset of A, B, C, DE")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    for key in (k.strip().upper() for k in args.only.split(",")):
        if key not in STUDIES:
            ap.error(f"unknown study {key!r}; choose from {', '.join(STUDIES)}")
        study, sizes = STUDIES[key]
        s = QUICK[key] if args.quick else sizes()
        t0 = time.perf_counter()
        print(f"\n== Figure {key} ({'quick' if args.quick else 'default'} sizes, {device}) ==")
        torch.manual_seed(0)
        print(study(out, s, device))
        print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
