"""Training losses (Sec. E.2): multi-view image L1 (eq. 8), soft silhouette IoU, Laplacian smoothness and
a weight-free perceptual stand-in (multi-scale image-gradient L1; no pretrained VGG can be downloaded here).

Images are compared in :func:`hdr_srgb`, the sRGB curve continued above 1: it equals the display space
of the reported image metric below 1, and unlike the clipped display space it keeps gradients in
highlights (a sun reflected in a car is where the light's direction shows, and it is far above 1).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def hdr_srgb(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> sRGB encoding without the clip at 1 (monotone, C1 at 1, slope > 0 everywhere)."""
    x = rgb_linear.clamp_min(0.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(0.0031308) ** (1 / 2.4) - 0.055)


def image_l1(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 over foreground pixels; images (B, H, W, 3) in the same space, mask (B, H, W)."""
    m = target_mask.unsqueeze(-1)
    return ((pred_rgb - target_rgb * m).abs() * m).sum() / (3 * m.sum()).clamp_min(1)


def soft_iou_loss(soft_mask: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU of a differentiable silhouette and the target mask, averaged over the batch."""
    dims = tuple(range(1, soft_mask.dim()))
    inter = (soft_mask * target_mask).sum(dims)
    union = (soft_mask + target_mask - soft_mask * target_mask).sum(dims)
    return (1 - inter / union.clamp_min(1e-6)).mean()


def gradient_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, scales: int = 3) -> torch.Tensor:
    """L1 between image gradients at several scales: rewards sharp, aligned texture detail."""
    p, t = pred_rgb.permute(0, 3, 1, 2), target_rgb.permute(0, 3, 1, 2)
    total = p.new_zeros(())
    for s in range(scales):
        if s:
            p, t = F.avg_pool2d(p, 2), F.avg_pool2d(t, 2)
        for dim in (2, 3):
            total = total + (torch.diff(p, dim=dim) - torch.diff(t, dim=dim)).abs().mean()
    return total / scales
