"""What every part of the Cycles API shares: the ``bpy`` module, arrays, images and a scratch folder."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from dibrpp.io import DataError

LINEAR_COLORSPACE = "Linear Rec.709"

_SCRATCH: str | None = None


def scratch_dir() -> str:
    """One per-process scratch folder for Cycles' EXR output, removed at exit."""
    global _SCRATCH
    if _SCRATCH is None or not os.path.isdir(_SCRATCH):
        import atexit
        import shutil

        _SCRATCH = tempfile.mkdtemp(prefix="dibrpp_cycles_")
        atexit.register(shutil.rmtree, _SCRATCH, True)
    return _SCRATCH


def bpy_module():
    """``bpy``, imported on first use, with a clear message where Blender is not installed."""
    try:
        import bpy  # noqa: PLC0415
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "datagen needs Blender as a Python module: `pip install bpy==5.0.1` (Python 3.11, numpy<2), "
            "or `make setup`"
        ) from e
    return bpy


def as_array(x, dtype=None) -> np.ndarray:
    """A numpy array of ``x`` (numpy, list or torch tensor)."""
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def reset() -> None:
    """Empty Blender: factory settings without the default cube/camera/light, all images freed."""
    bpy = bpy_module()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for img in list(bpy.data.images):
        bpy.data.images.remove(img)


def image_from_array(name: str, pixels: np.ndarray, colorspace: str):
    """A float bpy image from an (H, W, C) array given top row first (bpy stores bottom row first)."""
    bpy = bpy_module()
    arr = as_array(pixels, np.float32)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"{name}: expected an (H, W, 3) or (H, W, 4) image, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: image contains NaN or Inf")
    h, w = arr.shape[:2]
    if arr.shape[-1] == 3:
        arr = np.concatenate([arr, np.ones((h, w, 1), np.float32)], -1)
    img = bpy.data.images.new(name, width=w, height=h, alpha=True, float_buffer=True)
    img.colorspace_settings.name = colorspace
    img.pixels.foreach_set(np.ascontiguousarray(arr[::-1]).reshape(-1))
    img.pack()  # keep the pixels with the .blend data; Cycles reads packed/generated buffers alike
    return img


def load_image(path, colorspace: str):
    """A bpy image read from ``path``; DataError if it is missing or Blender cannot read it."""
    bpy = bpy_module()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such image file")
    try:
        img = bpy.data.images.load(str(path.resolve()), check_existing=False)
    except RuntimeError as e:
        raise DataError(f"{path}: Blender cannot read this image ({e})") from e
    img.colorspace_settings.name = colorspace
    return img


def empty_node_tree(owner):
    """(nodes, links) of a new material's or world's node tree, emptied of Blender's default nodes."""
    nodes, links = owner.node_tree.nodes, owner.node_tree.links
    for n in list(nodes):
        nodes.remove(n)
    return nodes, links
