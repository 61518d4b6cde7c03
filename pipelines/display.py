"""What images look like to a person: the clipped sRGB display space (also the image metric's space) and a
tone map for HDR environment maps."""
from __future__ import annotations

import torch

from dibrpp.conventions import linear_to_srgb


def display_srgb(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> sRGB in [0, 1], clipped at 1 as a display (and the dataset's PNGs) shows it."""
    return linear_to_srgb(rgb_linear)


def tonemap_envmap(env: torch.Tensor) -> torch.Tensor:
    """An HDR map (..., H, W, 3) scaled to its own mean (the light metrics ignore scale), sRGB, clipped."""
    mean = env.mean(dim=(-3, -2, -1), keepdim=True).clamp_min(1e-8)
    return display_srgb(0.4 * env / mean)
