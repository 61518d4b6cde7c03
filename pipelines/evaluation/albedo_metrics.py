"""The albedo's and the light's colour and scale against the ground truth (ours, beside the paper's metrics): the
albedo's sky blue, the albedo's scale and the light's scale."""
from __future__ import annotations

import torch

from dibrpp.conventions import equirect_solid_angles


UP_FACING_COS = 0.5  # a surface faces up (mirrors the sky) where its normal is within 60 degrees of up,
# and sideways (mirrors the horizon and the ground) where it is within 30 degrees of horizontal


def albedo_sky_blue(albedo: torch.Tensor, gt_albedo: torch.Tensor, gt_normals: torch.Tensor,
                    gt_alpha: torch.Tensor) -> torch.Tensor:
    """(B,) how much bluer the predicted albedo is where the GT surface faces up (and mirrors the sky) than where it
    faces sideways (and mirrors the ground), beyond the GT albedo's own difference: the blue chromaticity
    b / (r + g + b), predicted minus GT, averaged over each set of pixels, up minus sideways. Albedos (B, H, W, 3)
    rendered in the input view, GT world normals (B, H, W, 3) and coverage (B, H, W); NaN where either set is empty.
    0 where the albedo's colour does not follow the mirrored direction; a model that paints the sky's and the
    ground's reflections into the albedo scores above 0. A tint of the whole albedo (which white-balanced light
    leaves to it) cancels."""
    covered, up_z = gt_alpha > 0.5, gt_normals[..., 2]
    up, side = covered & (up_z > UP_FACING_COS), covered & (up_z.abs() < UP_FACING_COS)
    blue = lambda a: a[..., 2] / a.sum(-1).clamp_min(1e-4)  # noqa: E731
    excess = blue(albedo) - blue(gt_albedo)
    mean_over = lambda m: (excess * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1)  # noqa: E731
    empty = ~(up.flatten(1).any(1) & side.flatten(1).any(1))
    return torch.where(empty, float("nan"), mean_over(up) - mean_over(side))


def albedo_scale(albedo: torch.Tensor, gt_albedo: torch.Tensor, covered: torch.Tensor) -> torch.Tensor:
    """(B,) the predicted albedo's brightness over the GT's: the ratio of their sums over the pixels both
    silhouettes cover (``covered`` (B, H, W) bool) and the three channels; NaN where none is covered. With
    :func:`light_scale` it shows inverse rendering's scale ambiguity: the image fixes albedo x light, not each."""
    both = covered.unsqueeze(-1)
    gt = (gt_albedo * both).sum((1, 2, 3))
    return (albedo * both).sum((1, 2, 3)) / gt.clamp_min(1e-12) + torch.where(gt > 0, 0.0, float("nan"))


def light_scale(pred_env: torch.Tensor, gt_env: torch.Tensor) -> torch.Tensor:
    """(B,) the predicted light's mean radiance over the GT map's (equirect maps (B, H, W, 3) of one size;
    texels weighted by their solid angle, the channels averaged)."""
    w = equirect_solid_angles(gt_env.shape[1], gt_env.shape[2], dtype=torch.float64).view(1, -1, 1, 1)
    power = lambda env: (env.double().clamp_min(0) * w).sum((1, 2, 3))  # noqa: E731
    return (power(pred_env) / power(gt_env).clamp_min(1e-30)).float()
