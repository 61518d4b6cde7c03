"""Contact sheet of a generated dataset: a few objects x views (over grey), their albedo, and env maps."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from dibrpp.io import read_exr, read_png, write_png

from .layout import DatasetLayout


def contact_sheet(out, max_objects: int = 6, max_views: int = 8, path=None) -> Path:
    layout = DatasetLayout(out)
    manifest = layout.read_manifest()
    samples = layout.finished_samples()
    if not samples:
        raise FileNotFoundError(f"{out}: no finished samples to preview")
    # one sample per object first, so the sheet shows different objects
    seen, picked = set(), []
    for obj, env in samples:
        if obj not in seen:
            seen.add(obj)
            picked.append((obj, env))
    picked = picked[:max_objects]
    views = manifest["config"]["views"]
    cols = sorted(set(np.linspace(0, views - 1, min(max_views, views)).round().astype(int).tolist()))
    res = manifest["config"]["resolution"]
    grey = 0.18
    rows = []
    for obj, e in picked:
        tiles = []
        for v in cols:
            rgba = read_exr(layout.view_image(obj, e, v), "RGBA")
            tiles.append(rgba[..., :3] + (1 - rgba[..., 3:]) * grey)
        alb = read_exr(layout.view_albedo(obj, e, cols[0]), "RGB")
        a = read_png(layout.view_mask(obj, e, cols[0]))[..., :1]
        tiles.append(alb + (1 - a) * grey)
        env = read_exr(layout.envmap(e), "RGB")
        env = env / (1 + env)  # tone map for display (the sheet is sRGB-encoded after this)
        idx_r = np.linspace(0, env.shape[0] - 1, res // 2).round().astype(int)
        idx_c = np.linspace(0, env.shape[1] - 1, res).round().astype(int)
        env_tile = np.full((res, res, 3), grey, np.float32)
        env_tile[res // 4: res // 4 + res // 2] = env[idx_r][:, idx_c]
        tiles.append(env_tile)
        rows.append(np.concatenate(tiles, 1))
    sheet = np.concatenate(rows, 0)
    path = Path(path) if path else layout.preview
    write_png(path, sheet)
    return path
