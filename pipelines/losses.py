"""Training losses (Sec. E.2): multi-view image L1 (eq. 8), silhouette IoU, Laplacian smoothness and a
weight-free perceptual stand-in (multi-scale image-gradient L1; no pretrained VGG can be downloaded here)."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from dibrpp.conventions import linear_to_srgb


def to_display(rgb_linear: torch.Tensor) -> torch.Tensor:
    """Linear HDR -> the sRGB [0, 1] space in which images are compared (as the dataset's PNGs)."""
    return linear_to_srgb(rgb_linear)


def image_l1(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """Mean L1 over foreground pixels; images (B, H, W, 3) in display space, mask (B, H, W)."""
    m = target_mask.unsqueeze(-1)
    return ((pred_rgb - target_rgb * m).abs() * m).sum() / (3 * m.sum()).clamp_min(1)


def iou_loss(soft_mask: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """1 - soft IoU, averaged over the batch."""
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
