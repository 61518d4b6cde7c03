"""The encoder's input, one owner for what it sees: linear RGBA -> colour on black + alpha, and back.

Colour is sRGB-encoded up to 1 and logarithmic above, so an EXR's sun reflection stays visible to the encoder
while an 8-bit picture's tensor is exactly the sRGB one; a model trained on clipped input clips it itself
(:func:`clip_input`; ``ModelConfig.input_range``). The loss compares images in another curve
(``pipelines.training.losses.hdr_srgb``, the display space's slope); this one keeps a CNN's input bounded.
"""
from __future__ import annotations

import torch

from dibrpp import conventions
from dibrpp.camera import Cameras

MAX_LOG_RADIANCE = 12.0  # exp(12) ~ 1.6e5: a bound against overflow far above any sun in the data (input and light)
# above radiance 1 the encoder's colour grows as 1 + ln(x) / HDR_LOG_SCALE (about the sRGB curve's slope at 1),
# so a sun's reflection (~1e4) reads ~4.8 where a clipped picture shows 1
HDR_LOG_SCALE = 2.4


def input_grid(points: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """Where world points (B, P, 3) land in the cameras' input images, as ``grid_sample`` coordinates (B, P, 2)
    (x right, y down in [-1, 1]; the cameras' NDC has y up)."""
    xy, _ = cameras.project(points)
    return torch.stack([xy[..., 0], -xy[..., 1]], -1)


def encode_colour(radiance: torch.Tensor) -> torch.Tensor:
    """Linear radiance -> the encoder's colour: sRGB up to 1, logarithmic above (1 + ln(x) / HDR_LOG_SCALE)."""
    hdr = 1 + torch.log(radiance.clamp_min(1.0)) / HDR_LOG_SCALE
    return torch.where(radiance > 1, hdr, conventions.linear_to_srgb(radiance))


def decode_colour(colour: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`encode_colour` (colours up to 1 decode as sRGB, clamped at 0; radiance bounded by
    exp(MAX_LOG_RADIANCE), as the light is, so that a colour divided by a tiny alpha stays finite)."""
    hdr = torch.exp(((colour.clamp_min(1.0) - 1) * HDR_LOG_SCALE).clamp_max(MAX_LOG_RADIANCE))
    return torch.where(colour > 1, hdr, conventions.srgb_to_linear(colour))


def encoder_input(rgba: torch.Tensor) -> torch.Tensor:
    """The encoder's input: (B, H, W, 4) linear RGBA -> (B, 4, H, W) colour (:func:`encode_colour`, full range) on
    black, alpha. A clipped-input model clips it itself (:func:`clip_input`)."""
    rgb = encode_colour(rgba[..., :3]) * rgba[..., 3:]
    return torch.cat([rgb, rgba[..., 3:]], -1).permute(0, 3, 1, 2)


def clip_input(images: torch.Tensor) -> torch.Tensor:
    """:func:`encoder_input` images as an 8-bit picture shows them: radiance clipped at 1."""
    one = conventions.linear_to_srgb(images.new_ones(()))
    return torch.cat([torch.minimum(images[:, :3], images[:, 3:] * one), images[:, 3:]], 1)


def decode_premultiplied(colour: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Linear radiance from encoder colour premultiplied by ``alpha`` (broadcasting; the division floored)."""
    return decode_colour((colour / alpha.clamp_min(1e-3)).clamp_min(0))


def input_radiance(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """What :func:`encoder_input` images show: linear radiance (B, H, W, 3) and alpha (B, H, W)."""
    alpha = images[:, 3].clamp(0, 1)
    return decode_premultiplied(images[:, :3], alpha.unsqueeze(1)).permute(0, 2, 3, 1), alpha
