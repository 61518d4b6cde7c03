"""Figure C: light/material ambiguity. A sharp light on a rough sphere vs a smooth light (fitted to match) on
a glossy one, compared in PSNR under SG and MC shading."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from dibrpp import Renderer, icosphere, rasterize
from dibrpp.display import display_image
from dibrpp.lights import SGLight
from studies.common import (ENV_EXPOSURE, fg_mean, fitted_sg, foreground_psnr, image_grid, metal,
                            orbit_views, write_study_table)


@dataclass
class Sizes:
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
        fg_mean((display_image(render(light())) - target).square(), mask).backward()
        opt.step()
    return SGLight(params[0].detach(), params[1].exp().detach(), params[2].exp().detach())


ENV_FOR_SG = (256, 512)  # env-map size that MC renders an SG light at: ~0.7 deg texels resolve lam ~ 400


def run(out: Path, s: Sizes, device) -> str:
    """Figure C: sharp light + rough sphere vs smooth light + glossy sphere, the smooth light fitted in one view."""
    sphere = icosphere(4, device=device)
    cams = orbit_views(s.views, s.res, device)
    frags, frags0 = rasterize(sphere, cams), rasterize(sphere, cams[[0]])
    sg, mc = Renderer("sg"), Renderer("mc", spp=s.mc_spp, mis=True, seed=0)
    mc_target, mc_fit = Renderer("mc", spp=s.mc_spp, mis=True, seed=1), Renderer("mc", spp=s.mc_fit_spp, mis=True)
    sharp = fitted_sg(0, s.lobes, s.fit_iters, 128, 256).to(device)
    with torch.no_grad():  # (the MC target has its own random numbers: the fit must not learn the scoring noise)
        target_sg = display_image(sg(sphere, cams, metal(s.beta_sharp, device), sharp, frags).rgb)
        target_mc = display_image(mc_target(sphere, cams[[0]], metal(s.beta_sharp, device), sharp.to_envmap(*ENV_FOR_SG),
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
            renders[name] = dict(env=display_image(env.image[0], ENV_EXPOSURE),
                                 sg=display_image(sg(sphere, cams, metal(beta, device), light, frags).rgb),
                                 mc=display_image(mc(sphere, cams[[0]], metal(beta, device), env, frags0).rgb))
    names = list(cases)
    ref, mask = renders[names[0]], frags.mask
    rows = [dict(case=n, beta=cases[n][1], median_lobe_sharpness=float(cases[n][0].sharpness.median()),
                 psnr_sg_view0_db=foreground_psnr(renders[n]["sg"][:1], ref["sg"][:1], mask[:1]),
                 psnr_sg_other_views_db=foreground_psnr(renders[n]["sg"][1:], ref["sg"][1:], mask[1:]),
                 psnr_mc_view0_db=foreground_psnr(renders[n]["mc"], ref["mc"], mask[:1])) for n in names[1:]]
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
    return write_study_table(rows, out, "fig_c_ambiguity", note)



QUICK = Sizes(res=32, views=2, lobes=8, fit_iters=40, iters=30, mc_spp=16, mc_iters=5, mc_fit_spp=4)
