"""The paper's evaluation metrics (Sec. E.3, E.6), per image or per sample; lower is better for all.

- image: L1 between GT and re-rendered images on the GT foreground (display space, as in training);
- 2D IoU loss: 1 - IoU of the GT mask and the predicted silhouette (both thresholded at 0.5);
- light / texture: 1 - NCC (eq. 9), NCC(a, b) = sum(a * b) / (|a|_2 |b|_2) -- invariant to a global scale,
  so a predicted light or texture that is right up to intensity scores 0;
- Chamfer distance between surface samples of the predicted and GT meshes, both scaled so that the GT
  bounding-box diagonal is 1 ("normalized as one", Sec. E.6), mean of the two directed squared distances.
"""
from __future__ import annotations

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree


def image_l1(pred_rgb: torch.Tensor, gt_rgb: torch.Tensor, gt_mask: torch.Tensor) -> torch.Tensor:
    """(B,) mean |pred - gt| over the GT foreground; rgb (B, H, W, 3), mask (B, H, W) in [0, 1]."""
    m = gt_mask.unsqueeze(-1)
    num = ((pred_rgb - gt_rgb).abs() * m).sum((1, 2, 3))
    return num / (3 * m.sum((1, 2, 3))).clamp_min(1e-8)


def iou_loss(pred_mask: torch.Tensor, gt_mask: torch.Tensor, threshold: float = 0.5) -> torch.Tensor:
    """(B,) 1 - |P and G| / |P or G| of masks (B, H, W) binarised at ``threshold`` (0 if both are empty)."""
    p, g = pred_mask > threshold, gt_mask > threshold
    inter = (p & g).sum((1, 2)).double()
    union = (p | g).sum((1, 2)).double()
    return torch.where(union > 0, 1 - inter / union.clamp_min(1), torch.zeros_like(union)).to(pred_mask.dtype)


def ncc_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B,) 1 - NCC (eq. 9) over everything but the batch dimension."""
    a, b = a.reshape(a.shape[0], -1).double(), b.reshape(b.shape[0], -1).double()
    ncc = (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-30)
    return (1 - ncc).float()


def chamfer_distance(pred_verts: np.ndarray, pred_faces: np.ndarray, gt_verts: np.ndarray, gt_faces: np.ndarray,
                     samples: int = 10_000, seed: int = 0) -> float:
    """Symmetric Chamfer distance between the surfaces, in units of the GT bounding-box diagonal."""
    scale = float(np.linalg.norm(gt_verts.max(0) - gt_verts.min(0)))
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError("the GT mesh is empty or degenerate; cannot normalise the Chamfer distance")
    pts = []
    for v, f in ((pred_verts, pred_faces), (gt_verts, gt_faces)):
        mesh = trimesh.Trimesh(np.asarray(v, np.float64) / scale, np.asarray(f), process=False)
        pts.append(np.asarray(trimesh.sample.sample_surface(mesh, samples, seed=seed)[0]))
    d_pg = cKDTree(pts[1]).query(pts[0])[0]
    d_gp = cKDTree(pts[0]).query(pts[1])[0]
    return float(0.5 * (np.mean(d_pg ** 2) + np.mean(d_gp ** 2)))
