"""Refinement at test time: a few dozen Adam steps on the predicted light and a global albedo gain per image,
against the input view itself, with the predicted mesh and material held (used by evaluate and predict).

The encoder's light is a guess from one forward pass; the renderer can check it against the very image it
came from. Only the light (SG axes, sharpness and amplitudes; env-map texels; SH coefficients, in log space
where they are positive) and one grey gain on the albedo move, so the shape and the paint stay the encoder's:
what the refinement can change is where the light comes from and how sharp it is, which is what the image of
a glossy object shows and a single regression misses.
"""
from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from .losses import foreground_l1, hdr_srgb
from ..model.encoder import MAX_SHARPNESS
from ..model.model_input import MAX_LOG_RADIANCE
from ..model.prediction import LIGHT_KINDS, Prediction, white_balance

# Tens of steps fit the light to the one view (evaluation uses 30). Each renders the view with gradients, about
# 0.1 s with SG and 0.6 s with MC at 64 px on 2 cores (after the first, which compiles the renderer): this many
# take 17 min and 1.7 h already.
MAX_STEPS = 10_000


def _free(params: dict, kind: str) -> dict:
    """The light's parameters as unconstrained leaves (logs of the positive ones)."""
    if kind == "sg":
        free = {"axis": params["axis"], "sharpness": params["sharpness"].log(), "amplitude": params["amplitude"].log()}
    elif kind == "env":
        free = {"image": params["image"].clamp_min(1e-6).log()}
    else:
        free = {"coeffs": params["coeffs"]}
    return {k: v.detach().clone().requires_grad_(True) for k, v in free.items()}


def _constrained(free: dict, kind: str) -> dict:
    if kind == "sg":
        light = {"axis": F.normalize(free["axis"], dim=-1, eps=1e-6),
                 "sharpness": free["sharpness"].exp().clamp(0.5, MAX_SHARPNESS),
                 "amplitude": free["amplitude"].clamp_max(MAX_LOG_RADIANCE).exp()}
    elif kind == "env":
        light = {"image": free["image"].clamp_max(MAX_LOG_RADIANCE).exp()}
    else:
        light = {"coeffs": free["coeffs"]}
    return white_balance(light, kind)


def refine_light(pred: Prediction, cameras, rgba: torch.Tensor, renderer, steps: int = 30,
                 lr: float = 0.05, on_step: Callable[[int], None] | None = None) -> tuple[Prediction, torch.Tensor]:
    """``pred`` with its light refined against the input views ``rgba`` (B, S, S, 4) linear, seen by
    ``cameras``; returns (refined prediction, (B,) albedo gains). The prediction's tensors are not changed.
    ``on_step(n)`` is called after each step with the number of steps done (progress, time estimates)."""
    kind = LIGHT_KINDS[pred.config.shading]
    base = pred.detached()
    meshes = base.meshes()
    free = _free(pred.light_params, kind)
    log_gain = torch.zeros(rgba.shape[0], device=rgba.device, requires_grad=True)
    opt = torch.optim.Adam([*free.values(), log_gain], lr=lr)
    target = hdr_srgb(rgba[..., :3])
    with torch.enable_grad():
        for done in range(1, steps + 1):
            current = base.with_light(_constrained(free, kind))
            current.texture = (base.texture * log_gain.exp().view(-1, 1, 1, 1)).clamp(0, 1)
            out = renderer(meshes, cameras, current.material(), current.light(cameras.world_to_camera))
            loss = foreground_l1(hdr_srgb(out.rgb), target, rgba[..., 3])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if on_step is not None:
                on_step(done)
    with torch.no_grad():
        gain = log_gain.exp()
        refined = base.with_light(_constrained(free, kind))
        refined.texture = (refined.texture * gain.view(-1, 1, 1, 1)).clamp(0, 1)
    return refined, gain
