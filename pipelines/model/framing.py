"""How much of the frame the object fills, and an image re-framed the way the training views frame it.

The datasets' orbit cameras look at the object's centre from a fixed distance, so in every training view the
object sits at the centre and its bounding box spans about the same share of the image side (the run's
``object_fill``, stored in ``camera.json``). A photo frames its object as it likes: :func:`reframe` crops and
pads it to a square around the object's box so that the box spans that share, centred.
"""
from __future__ import annotations

import torch

COVERED = 0.5  # alpha above which a pixel is the object's


def object_box(alpha: torch.Tensor) -> tuple[float, float, float, float] | None:
    """(centre row, centre column, height, width) in pixels of the pixels of ``alpha`` (H, W) above COVERED;
    None where there are none."""
    rows = torch.nonzero((alpha > COVERED).any(1)).flatten()
    cols = torch.nonzero((alpha > COVERED).any(0)).flatten()
    if rows.numel() == 0:
        return None
    top, bottom, left, right = float(rows[0]), float(rows[-1]) + 1, float(cols[0]), float(cols[-1]) + 1
    return (top + bottom) / 2, (left + right) / 2, bottom - top, right - left


def object_fill(alpha: torch.Tensor) -> float:
    """The median over views (N, H, W) of the object box's longer side over the image side."""
    fills = [max(box[2], box[3]) / alpha.shape[-1] for box in map(object_box, alpha) if box is not None]
    return float(torch.tensor(fills).quantile(0.5)) if fills else 0.0


def image_fill(alpha: torch.Tensor) -> float:
    """The object box's longer side over the image's longer side (0 without an object)."""
    box = object_box(alpha)
    return max(box[2], box[3]) / max(alpha.shape) if box is not None else 0.0


def reframe(rgba: torch.Tensor, fill: float) -> torch.Tensor:
    """(side, side, 4): a square window of ``rgba`` (H, W, 4) centred on the object's box, of a side that makes
    the box's longer side ``fill`` of it; outside the image, transparent."""
    cy, cx, height, width = object_box(rgba[..., 3])
    side = max(round(max(height, width) / fill), 1)
    top, left = round(cy - side / 2), round(cx - side / 2)
    padded = torch.zeros(side, side, rgba.shape[-1], dtype=rgba.dtype)
    rows = slice(max(top, 0), min(top + side, rgba.shape[0]))
    cols = slice(max(left, 0), min(left + side, rgba.shape[1]))
    padded[rows.start - top:rows.stop - top, cols.start - left:cols.stop - left] = rgba[rows, cols]
    return padded
