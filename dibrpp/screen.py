"""Screen-space building blocks shared by the rasterizer (:mod:`dibrpp.raster`) and the silhouettes
(:mod:`dibrpp.silhouette`), as plain functions of tensors.

Work is done on (primitive, pixel) candidate pairs enumerated over each primitive's pixel bounding box,
so it grows with the covered area plus the number of primitives, never with their product. Pixel
coordinates have the pixel centres at integers (column, row), rows going down.
"""
from __future__ import annotations

import torch


def box_pixel_pairs(lo: torch.Tensor, hi: torch.Tensor, width: int, height: int):
    """Enumerate (box, pixel) pairs over inclusive integer pixel boxes lo/hi (M, 2) as (col, row).

    Returns (owner index into the M boxes, col, row) for every pixel of every box inside the image.
    """
    lo = lo.clamp_min(0)
    hi = torch.stack([hi[:, 0].clamp_max(width - 1), hi[:, 1].clamp_max(height - 1)], 1)
    size = (hi - lo + 1).clamp_min(0)
    counts = size[:, 0] * size[:, 1]
    owner = torch.repeat_interleave(torch.arange(len(counts), device=lo.device), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=lo.device) - start[owner]
    box_w = size[owner, 0].clamp_min(1)
    col = lo[owner, 0] + local % box_w
    row = lo[owner, 1] + local // box_w
    return owner, col, row


def take(index: torch.Tensor, *arrays: torch.Tensor):
    """Rows ``index`` (indices, or a boolean mask turned into indices once) of each array, by index_select."""
    if index.dtype == torch.bool:
        index = index.nonzero(as_tuple=True)[0]
    return tuple(a.index_select(0, index) for a in arrays)


def gather_batched(x: torch.Tensor, batch: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (B, V, ...) at (batch, idx): batch (N,), idx (N, k) -> (N, k, ...), through one flat index_select."""
    flat = (batch.unsqueeze(1) * x.shape[1] + idx).reshape(-1)
    rows = x.reshape(x.shape[0] * x.shape[1], *x.shape[2:]).index_select(0, flat)
    return rows.view(*idx.shape, *x.shape[2:])


def edge_barycentrics(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """Screen-space barycentrics of points p (..., 2) in triangles (a, b, c); also the signed area."""
    area = (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    w0 = (b[..., 0] - p[..., 0]) * (c[..., 1] - p[..., 1]) - (b[..., 1] - p[..., 1]) * (c[..., 0] - p[..., 0])
    w1 = (c[..., 0] - p[..., 0]) * (a[..., 1] - p[..., 1]) - (c[..., 1] - p[..., 1]) * (a[..., 0] - p[..., 0])
    safe = torch.where(area.abs() < 1e-20, torch.full_like(area, 1e-20), area)
    b0, b1 = w0 / safe, w1 / safe
    return torch.stack([b0, b1, 1 - b0 - b1], -1), area


def segment_dist2(p, a, b):
    """Squared distance from points p (..., 2) to segments [a, b] (..., 2)."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-20)
    q = a + t.clamp(0, 1).unsqueeze(-1) * ab
    return ((p - q) ** 2).sum(-1)


def triangle_dist2(p, tri):
    """Squared distance (N,) from points p (N, 2) to the boundary of triangles tri (N, 3, 2)."""
    d = torch.stack([segment_dist2(p, tri[:, i], tri[:, (i + 1) % 3]) for i in range(3)], -1)
    return d.min(-1).values
