"""What images look like to a person: the clipped sRGB display space (also the image metric's space, and what
the datasets' PNGs hold) and a tone map for HDR environment maps. One owner for figures in every package."""
from __future__ import annotations

import torch

from .conventions import linear_to_srgb


def display_image(linear: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Linear HDR (..., 3) -> sRGB in [0, 1] after scaling by ``exposure``, clipped at 1 as a display shows it."""
    return linear_to_srgb(linear * exposure)


def tonemap_envmap(env: torch.Tensor) -> torch.Tensor:
    """An HDR map (..., H, W, 3) scaled to its own mean (the light metrics ignore scale), sRGB, clipped."""
    mean = env.mean(dim=(-3, -2, -1), keepdim=True).clamp_min(1e-8)
    return display_image(0.4 * env / mean)
