"""Procedural albedo textures baked into an xatlas UV atlas.

:func:`bake_positions` rasterises the atlas in UV space (vectorised numpy) to get, for every texel,
the 3D surface point and normal it covers; a painter turns those into sRGB colours; gutters are
dilated so bilinear lookups at chart borders do not bleed the background in. Texture images are top
row first and sRGB-encoded (8-bit PNG on disk); UVs follow the OBJ convention (v up).
"""
from __future__ import annotations

import colorsys

import numpy as np

# Monk Skin Tone scale (10 tones, light to dark), sRGB: a balanced palette by construction.
SKIN_TONES = np.array([
    (0xF6, 0xED, 0xE4), (0xF3, 0xE7, 0xDB), (0xF7, 0xEA, 0xD0), (0xEA, 0xDA, 0xBA), (0xD7, 0xBD, 0x96),
    (0xA0, 0x7E, 0x56), (0x82, 0x5C, 0x43), (0x60, 0x41, 0x34), (0x3A, 0x31, 0x2A), (0x29, 0x24, 0x20),
], np.float64) / 255.0


def bake_positions(verts, faces, normals, uvs, face_uvs, size: int):
    """Rasterise the UV atlas: returns (pos (S, S, 3), nrm (S, S, 3), covered (S, S) bool), top row first."""
    uv = np.asarray(uvs, np.float64)[np.asarray(face_uvs)]  # (F, 3, 2)
    px = np.stack([uv[..., 0] * size - 0.5, (1.0 - uv[..., 1]) * size - 0.5], -1)  # texel-centre coords
    lo = np.floor(px.min(1)).astype(np.int64)
    hi = np.ceil(px.max(1)).astype(np.int64)
    lo = np.clip(lo, 0, size - 1)
    hi = np.clip(hi, 0, size - 1)
    w = hi[:, 0] - lo[:, 0] + 1
    h = hi[:, 1] - lo[:, 1] + 1
    counts = w * h
    fid = np.repeat(np.arange(len(uv)), counts)
    start = np.repeat(np.cumsum(counts) - counts, counts)
    k = np.arange(counts.sum()) - start
    x = lo[fid, 0] + k % w[fid]
    y = lo[fid, 1] + k // w[fid]
    a, b, c = px[fid, 0], px[fid, 1], px[fid, 2]
    v0, v1, p = b - a, c - a, np.stack([x, y], -1) - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    den = np.where(np.abs(den) < 1e-12, 1e-12, den)
    l1 = (p[:, 0] * v1[:, 1] - v1[:, 0] * p[:, 1]) / den
    l2 = (v0[:, 0] * p[:, 1] - p[:, 0] * v0[:, 1]) / den
    l0 = 1 - l1 - l2
    eps = -1e-3
    inside = (l0 >= eps) & (l1 >= eps) & (l2 >= eps)
    fid, x, y = fid[inside], x[inside], y[inside]
    bary = np.stack([l0, l1, l2], -1)[inside]
    f = np.asarray(faces)[fid]
    pos = (np.asarray(verts)[f] * bary[..., None]).sum(1)
    nrm = (np.asarray(normals)[f] * bary[..., None]).sum(1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True).clip(1e-9)
    P = np.zeros((size, size, 3))
    N = np.zeros((size, size, 3))
    cov = np.zeros((size, size), bool)
    P[y, x], N[y, x], cov[y, x] = pos, nrm, True
    return P, N, cov


def dilate(img: np.ndarray, covered: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Grow colours into uncovered texels (gutters) by averaging covered 4-neighbours."""
    img = img.copy()
    cov = covered.copy()
    for _ in range(iterations):
        acc = np.zeros_like(img)
        cnt = np.zeros(cov.shape)
        for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            sc = np.roll(cov, (dy, dx), (0, 1))
            acc += np.roll(img, (dy, dx), (0, 1)) * sc[..., None]
            cnt += sc
        grow = (~cov) & (cnt > 0)
        if not grow.any():
            break
        img[grow] = acc[grow] / cnt[grow][:, None]
        cov = cov | grow
    img[~cov] = img[cov].mean(0) if cov.any() else 0.5
    return img


class Noise3:
    """Cheap smooth 3D noise: a sum of random sinusoids (deterministic from the generator)."""

    def __init__(self, rng: np.random.Generator, scale: float, octaves: int = 12):
        self.w = rng.normal(size=(octaves, 3)) / scale
        self.phi = rng.uniform(0, 2 * np.pi, octaves)
        self.a = 1.0 / np.sqrt(octaves)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        return (np.sin(p @ self.w.T + self.phi) * self.a).sum(-1)


def _hsv(h, s, v):
    return np.array(colorsys.hsv_to_rgb(h % 1.0, np.clip(s, 0, 1), np.clip(v, 0, 1)))


def paint_car(pos, nrm, part, rng: np.random.Generator, params: dict) -> tuple[np.ndarray, dict]:
    """sRGB colours (N, 3) for car surface points (original shape coordinates)."""
    L, W = params["half_length"], params["half_width"]
    hue = rng.uniform()
    if rng.random() < 0.25:  # neutral paints: white, silver, grey, black
        base = np.full(3, rng.choice([0.92, 0.75, 0.5, 0.12]))
    else:
        base = _hsv(hue, rng.uniform(0.45, 0.95), rng.uniform(0.45, 0.95))
    second = _hsv(hue + rng.uniform(0.3, 0.7), rng.uniform(0.0, 0.9), rng.uniform(0.2, 1.0))
    col = np.tile(base, (len(pos), 1))
    style = dict(base=base.tolist(), second=second.tolist())
    z = pos[:, 2]
    ztop = z.max()
    if rng.random() < 0.4:  # two-tone: upper body a second colour
        thr = rng.uniform(0.55, 0.8) * ztop
        col[z > thr] = second
        style["two_tone_above"] = float(thr)
    if rng.random() < 0.5:  # racing stripes along the length on top surfaces
        sw = rng.uniform(0.8, 2.2)
        gap = rng.uniform(0.0, 1.5)
        stripe = (np.abs(np.abs(pos[:, 1]) - gap) < sw) & (nrm[:, 2] > 0.25)
        col[stripe] = second if "two_tone_above" not in style else base
        style["stripes"] = dict(width=float(sw), gap=float(gap))
    if rng.random() < 0.5:  # round decal on each door
        cx = rng.uniform(-0.3, 0.3) * L
        cz = rng.uniform(0.35, 0.55) * ztop
        r = rng.uniform(1.5, 3.0)
        decal_col = _hsv(rng.uniform(), rng.uniform(0.0, 1.0), rng.uniform(0.6, 1.0))
        dd = np.hypot(pos[:, 0] - cx, pos[:, 2] - cz)
        side = np.abs(nrm[:, 1]) > 0.5
        col[side & (dd < r)] = decal_col
        col[side & (dd < r * 0.45)] = second
        style["decal"] = dict(x=float(cx), z=float(cz), radius=float(r))
    # lights: headlights at the front (+X), tail lights at the back
    front = (nrm[:, 0] > 0.6) & (pos[:, 0] > 0) & (np.abs(np.abs(pos[:, 1]) - 0.62 * W) < 0.14 * W)
    band = (z > 0.3 * ztop) & (z < 0.5 * ztop)
    col[front & band] = (0.97, 0.95, 0.85)
    back = (nrm[:, 0] < -0.6) & (pos[:, 0] < 0) & (np.abs(np.abs(pos[:, 1]) - 0.62 * W) < 0.16 * W)
    col[back & band] = (0.75, 0.04, 0.03)
    col[part == 1] = _hsv(0.6, 0.25, rng.uniform(0.06, 0.18))  # windows
    tyre = part == 2
    col[tyre] = 0.04
    # rims: the wheel's flat outer face near the hub
    rim = tyre & (np.abs(nrm[:, 1]) > 0.7)
    rim_grey = rng.uniform(0.35, 0.8)
    col[rim] = rim_grey
    grain = Noise3(rng, scale=1.5)(pos)[:, None] * 0.04
    col = np.clip(col * (1 + grain), 0, 1)
    return col, style


def paint_head(pos, nrm, part, rng: np.random.Generator, tone: float) -> tuple[np.ndarray, dict]:
    """sRGB colours for head surface points; ``tone`` in [0, 1] walks the skin palette light to dark."""
    x = tone * (len(SKIN_TONES) - 1)
    i = int(np.clip(np.floor(x), 0, len(SKIN_TONES) - 2))
    skin = SKIN_TONES[i] * (1 - (x - i)) + SKIN_TONES[i + 1] * (x - i)
    skin = np.clip(skin * rng.uniform(0.95, 1.05, 3), 0, 1)
    hair_choices = np.array([(0.05, 0.04, 0.03), (0.25, 0.15, 0.08), (0.55, 0.4, 0.2), (0.75, 0.62, 0.38),
                             (0.5, 0.2, 0.08), (0.6, 0.6, 0.6)])
    hair = hair_choices[rng.integers(len(hair_choices))]
    col = np.tile(skin, (len(pos), 1))
    blotch = Noise3(rng, scale=4.0)(pos)
    col *= (1 + 0.05 * blotch)[:, None]
    # blush on the cheeks and nose: a warm shift
    warm = np.exp(-((np.abs(pos[:, 1]) - 4.0) ** 2 + (pos[:, 2] + 0.8) ** 2) / 6.0) * (nrm[:, 0] > 0.2)
    col = col * (1 - 0.12 * warm[:, None]) + np.array([0.8, 0.3, 0.3]) * skin.mean() * 0.12 * warm[:, None] * 1.5
    lips = skin * np.array([0.85, 0.62, 0.62]) + np.array([0.08, 0.0, 0.0])
    col[part == 1] = lips
    col[part == 2] = hair * 0.9 + skin * 0.1
    col[part == 3] = hair
    eye = part == 4
    col[eye] = (0.85, 0.85, 0.82)
    iris = eye & (nrm[:, 0] > 0.85)
    col[iris] = hair_choices[rng.integers(3)] * 0.8 + 0.05
    freckles = (Noise3(rng, scale=0.35)(pos) > 1.1) & (part == 0)
    col[freckles] *= 0.85
    col = np.clip(col, 0, 1)
    return col, dict(skin=skin.tolist(), tone=float(tone), hair=hair.tolist())


def bake_texture(obj: dict, uvs, face_uvs, size: int, rng: np.random.Generator, tone: float | None = None):
    """Texture (S, S, 3) float sRGB in [0, 1] for an object from :func:`datagen.shapes.make_shape`."""
    import trimesh

    verts, faces = obj["verts"], obj["faces"]
    normals = np.asarray(trimesh.Trimesh(verts, faces, process=False).vertex_normals)
    pos, nrm, cov = bake_positions(verts, faces, normals, uvs, face_uvs, size)
    norm = obj["normalisation"]
    orig = pos[cov] / norm["scale"] + np.asarray(norm["center"])  # back to the shape's own coordinates
    shape = obj["shape"]
    part = shape.part(orig)
    if shape.kind == "car":
        colours, style = paint_car(orig, nrm[cov], part, rng, shape.params)
    else:
        colours, style = paint_head(orig, nrm[cov], part, rng, 0.5 if tone is None else tone)
    img = np.zeros((size, size, 3))
    img[cov] = colours
    img = dilate(img, cov, iterations=max(4, size // 32))
    return img.astype(np.float32), style
