"""How the training views frame their object, and an image re-framed that way.

The datasets' orbit cameras look at the object's centre from a fixed distance and elevation, so in every training
view the object is about as large and sits about at the same place (a little below the centre: the camera looks
down on it). The model has no translation of its own and reads an object's size as its scale, so a photo that
frames its object otherwise is read wrongly. A run stores how its training views frame their object in
``camera.json``: ``object_size``, the median square root of the object's covered area over the image side (the
measure of size that varies least with the view: 8 % over the glossy set's, against 18 % for the bounding box's
longer side), and ``object_centre``, the median centroid of the covered pixels (row, column over the side).
:func:`reframe` crops and pads an image to the square in which its object has that size and centroid;
:func:`frame_input` decides whether an input image needs it, and :func:`resize_input` brings it to the model's side.
Images are linear RGBA with straight alpha (colour unscaled by coverage).
"""
from __future__ import annotations

from typing import Callable

import torch

COVERED = 0.5  # alpha above which a pixel is the object's
# an image whose object is within these of the training views' is used as it is: re-framing it costs more (it
# throws away the view's own size, which tells the car's) than it gains
SIZE_TOLERANCE = 0.25  # relative, about three times the spread of the training views' sizes
CENTRE_TOLERANCE = 0.08  # of the side, about three times the spread of their centroids


def object_extent(alpha: torch.Tensor) -> tuple[float, float, float] | None:
    """(centroid row, centroid column, square root of the covered area), in pixels, of the pixels of ``alpha``
    (H, W) above COVERED; None where there are none."""
    covered = (alpha > COVERED).float()
    area = float(covered.sum())
    if area == 0:
        return None
    rows = torch.arange(alpha.shape[0], dtype=torch.float32) + 0.5
    cols = torch.arange(alpha.shape[1], dtype=torch.float32) + 0.5
    return float(covered.sum(1) @ rows) / area, float(covered.sum(0) @ cols) / area, area ** 0.5


def training_framing(alpha: torch.Tensor) -> dict:
    """``object_size`` and ``object_centre`` (see the module doc): medians over square views (N, S, S)."""
    extents = torch.tensor([e for e in map(object_extent, alpha) if e is not None]) / alpha.shape[-1]
    if not len(extents):
        return {}
    row, col, size = (round(float(v), 4) for v in extents.quantile(0.5, dim=0))
    return {"object_size": size, "object_centre": [row, col]}


def image_framing(alpha: torch.Tensor) -> dict:
    """The object's size and centroid in an image of any shape, over its longer side (``predict`` pads an image to
    a square around its centre)."""
    height, width = alpha.shape
    side = max(height, width)
    extent = object_extent(alpha)
    if extent is None:
        raise ValueError(f"no pixel's alpha is above {COVERED}, where a pixel counts as the object's; give the object "
                         "a mask that is opaque (1) where it covers the pixel")
    row, col, size = extent
    return {"object_size": size / side, "object_centre": [(row + (side - height) / 2) / side,
                                                          (col + (side - width) / 2) / side]}


def frames_like(seen: dict, trained: dict) -> bool:
    """Whether an image's object (:func:`image_framing`) is framed within the tolerances of the training views'."""
    size_ratio = seen["object_size"] / trained["object_size"]
    off = max(abs(a - b) for a, b in zip(seen["object_centre"], trained["object_centre"]))
    return abs(size_ratio - 1) <= SIZE_TOLERANCE and off <= CENTRE_TOLERANCE


def reframe(rgba: torch.Tensor, trained: dict) -> torch.Tensor:
    """(side, side, 4): the square window of ``rgba`` (H, W, 4) in which its object has the training views' size
    and centroid (``trained``: :func:`training_framing`); outside the image, transparent."""
    row, col, size = object_extent(rgba[..., 3])
    side = max(round(size / trained["object_size"]), 1)
    top = round(row - trained["object_centre"][0] * side)
    left = round(col - trained["object_centre"][1] * side)
    window = torch.zeros(side, side, rgba.shape[-1], dtype=rgba.dtype)
    rows = slice(max(top, 0), min(top + side, rgba.shape[0]))
    cols = slice(max(left, 0), min(left + side, rgba.shape[1]))
    window[rows.start - top:rows.stop - top, cols.start - left:cols.stop - left] = rgba[rows, cols]
    return window


def frame_input(path, rgba: torch.Tensor, trained: dict, mode: str, say: Callable[[str], None] = print) -> torch.Tensor:
    """The image framed for the model (``mode``: predict's ``--framing``; ``trained``: the run's camera.json): as the
    training views frame their object (object), as it is (as-is), or as it is unless its object's size or place
    differs from the training views' beyond their spread (auto), each said through ``say`` where it matters."""
    if "object_size" not in trained:
        if mode == "object":
            say(f"note: the run records no framing of its training views (trained before it was recorded); {path} "
                "is used as framed")
        return rgba
    seen = image_framing(rgba[..., 3])
    like = frames_like(seen, trained)
    if mode == "object" or (mode == "auto" and not like):
        if mode == "auto":
            say(f"note: the object spans {seen['object_size'] / trained['object_size']:.2f}x the training views' size "
                f"in {path}, centred at {seen['object_centre'][0]:.2f}, {seen['object_centre'][1]:.2f} (theirs "
                f"{trained['object_centre'][0]:.2f}, {trained['object_centre'][1]:.2f}): re-framed as they frame it")
        return reframe(rgba, trained)
    if not like:
        say(f"warning: the object in {path} is framed unlike the training views' (size {seen['object_size']:.2f} of the "
            f"side against {trained['object_size']:.2f}); the model reads its size as the car's: use --framing auto")
    return rgba


def pad_to_square(img: torch.Tensor) -> torch.Tensor:
    """Transparent borders around the shorter side, so that resizing keeps the object's proportions."""
    height, width = img.shape[:2]
    side = max(height, width)
    top, left = (side - height) // 2, (side - width) // 2
    return torch.nn.functional.pad(img, (0, 0, left, side - width - left, top, side - height - top))


def resize_input(img: torch.Tensor, size: int) -> torch.Tensor:
    """(size, size, 4): straight-alpha ``img`` padded to a square (transparent) and resized by area averaging of
    its premultiplied colour, so that the colour under transparent pixels (any, in a straight-alpha file) does not
    bleed into the object's outline."""
    square = pad_to_square(img)
    alpha = square[..., 3:]
    premultiplied = torch.cat([square[..., :3] * alpha, alpha], -1)
    resized = torch.nn.functional.interpolate(premultiplied.permute(2, 0, 1)[None], size=(size, size), mode="area")[0]
    resized = resized.permute(1, 2, 0)
    coverage = resized[..., 3:]
    colour = torch.where(coverage > 0, resized[..., :3] / coverage.clamp_min(1e-12), torch.zeros_like(resized[..., :3]))
    return torch.cat([colour, coverage], -1)
