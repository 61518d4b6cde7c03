"""Procedural shapes: car-like vehicles and head-like busts, as watertight meshes with xatlas UVs.

Each shape is a signed-distance function built from smooth unions of rounded primitives, meshed with
marching cubes (so it is closed and smooth), centred and scaled so its bounding box fits
[-EXTENT, EXTENT]^3 with the longest side touching it (the paper's [-18, 18] normalisation).
World +Z is up; cars point along +X, heads face +X (so azimuth 0 is a front view).

A shape also carries a *part label* per point (``part(p)``), used by the texture painter:
cars: body, cabin (windows), wheel; heads: skin, lips, brows, ears, nose.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

EXTENT = 18.0


# ----------------------------------------------------------------------------- SDF primitives

def _smin(a, b, k):
    """Polynomial smooth minimum (k = blend radius)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def _round_box(p, center, half, r):
    q = np.abs(p - center) - (np.asarray(half) - r)
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0) - r


def _ellipsoid(p, center, radii):
    q = (p - center) / radii
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / radii, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-9)


def _cylinder_y(p, center, radius, half_width, r=0.3):
    """Rounded cylinder with its axis along Y (a wheel)."""
    q = p - center
    d = np.stack([np.hypot(q[..., 0], q[..., 2]) - radius + r, np.abs(q[..., 1]) - half_width + r], -1)
    return np.minimum(np.maximum(d[..., 0], d[..., 1]), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=-1) - r


@dataclass
class Shape:
    kind: str
    params: dict
    sdf: Callable[[np.ndarray], np.ndarray]
    part: Callable[[np.ndarray], np.ndarray]  # (N, 3) -> (N,) int part label
    part_names: tuple
    bounds: tuple  # (lo (3,), hi (3,)) box that contains the surface


# ----------------------------------------------------------------------------- cars

def car_shape(rng: np.random.Generator) -> Shape:
    """A random car-like vehicle (before normalisation, roughly in metres x 4)."""
    L = rng.uniform(14.0, 19.0)  # half length
    W = rng.uniform(6.5, 8.5)  # half width
    H = rng.uniform(2.6, 4.0)  # half height of the body slab
    clearance = rng.uniform(1.2, 2.2)
    body_c = np.array([0.0, 0.0, clearance + H])
    body_r = rng.uniform(1.2, 2.2)
    cab_len = L * rng.uniform(0.4, 0.62)
    cab_off = rng.uniform(-0.25, 0.1) * L
    cab_h = rng.uniform(1.7, 2.6)
    cab_w = W * rng.uniform(0.78, 0.92)
    cab_c = np.array([cab_off, 0.0, clearance + 2 * H + cab_h * 0.35])
    cab_r = rng.uniform(1.2, 1.6)
    wheel_r = rng.uniform(2.6, 3.6)
    wheel_w = rng.uniform(1.2, 1.8)
    axle = L * rng.uniform(0.58, 0.72)
    wheel_z = wheel_r
    wy = W - wheel_w * 0.6
    wheels = [np.array([sx * axle, sy * wy, wheel_z]) for sx in (-1, 1) for sy in (-1, 1)]
    spoiler = rng.random() < 0.3
    blend = rng.uniform(1.0, 2.0)

    def parts(p):
        body = _round_box(p, body_c, (L, W, H), body_r)
        # taper the nose/tail: cut with a slanted plane-ish smooth box
        cabin = _round_box(p, cab_c, (cab_len, cab_w, cab_h), cab_r)
        wheel = np.min([_cylinder_y(p, c, wheel_r, wheel_w) for c in wheels], axis=0)
        extra = np.full_like(body, np.inf)
        if spoiler:
            extra = _round_box(p, np.array([-L * 0.92, 0.0, clearance + 2 * H + 1.4]), (1.0, W * 0.9, 0.35), 0.3)
        return body, cabin, wheel, extra

    def sdf(p):
        body, cabin, wheel, extra = parts(p)
        d = _smin(body, cabin, blend)
        d = np.minimum(d, extra)
        # wheel arches: carve the body around the wheels, then add the wheels
        arch = np.min([_cylinder_y(p, c, wheel_r * 1.12, W * 2) for c in wheels], axis=0)
        d = np.maximum(d, -arch)
        return np.minimum(d, wheel)

    def part(p):
        body, cabin, wheel, extra = parts(p)
        lab = np.zeros(len(p), np.int64)
        lab[cabin < body - 0.2] = 1
        lab[(p[:, 2] > clearance + 2 * H + 0.6) & (cabin < 0.6)] = 1
        lab[wheel < 0.25] = 2
        return lab

    top = clearance + 2 * H + 2 * cab_h + 2.5
    bounds = (np.array([-L - 1, -W - 1, -0.5]), np.array([L + 1, W + 1, top]))
    params = dict(half_length=L, half_width=W, body_half_height=H, clearance=clearance, cabin_half_length=cab_len,
                  cabin_offset=cab_off, cabin_half_height=cab_h, wheel_radius=wheel_r, wheel_half_width=wheel_w,
                  axle=axle, spoiler=bool(spoiler))
    return Shape("car", params, sdf, part, ("body", "window", "wheel"), bounds)


# ----------------------------------------------------------------------------- heads

def head_shape(rng: np.random.Generator) -> Shape:
    """A random head-like bust facing +X: skull, jaw, nose, brows, ears, lips, neck."""
    s = rng.uniform(0.9, 1.1)
    skull_r = np.array([rng.uniform(9.0, 10.5), rng.uniform(7.8, 9.0), rng.uniform(9.5, 11.0)]) * s
    skull_c = np.array([0.0, 0.0, 4.0])
    jaw_r = np.array([rng.uniform(6.5, 8.0), rng.uniform(5.5, 7.0), rng.uniform(5.5, 7.0)]) * s
    jaw_c = np.array([2.8, 0.0, -4.0 * s])
    nose_len = rng.uniform(1.8, 3.2) * s
    nose_c = np.array([skull_r[0] * 0.97 + nose_len * 0.45, 0.0, 0.0])
    nose_r = np.array([nose_len, rng.uniform(1.0, 1.5) * s, rng.uniform(2.4, 3.2) * s])
    brow_z = rng.uniform(3.2, 4.4) * s
    brow_c = [np.array([skull_r[0] * 0.85, sy * 2.8 * s, brow_z]) for sy in (-1, 1)]
    brow_r = np.array([1.4, 2.6, 0.9]) * s
    ear_c = [np.array([-0.5, sy * skull_r[1] * 0.98, 1.0 * s]) for sy in (-1, 1)]
    ear_r = np.array([2.0, 0.9, 3.0]) * s * rng.uniform(0.85, 1.15)
    lip_c = np.array([jaw_c[0] + jaw_r[0] * 0.9, 0.0, -3.6 * s])
    lip_r = np.array([1.2, 2.6, 1.1]) * s
    cheek = rng.uniform(0.0, 1.0)
    cheek_c = [np.array([skull_r[0] * 0.6, sy * 4.2 * s, -0.8 * s]) for sy in (-1, 1)]
    cheek_r = np.array([3.0, 2.6, 2.6]) * s * (0.8 + 0.4 * cheek)
    neck_r = rng.uniform(4.2, 5.2) * s
    eye_c = [np.array([skull_r[0] * 0.83, sy * 3.0 * s, 2.0 * s]) for sy in (-1, 1)]
    eye_r = np.array([1.0, 1.5, 0.9]) * s

    def parts(p):
        skull = _ellipsoid(p, skull_c, skull_r)
        jaw = _ellipsoid(p, jaw_c, jaw_r)
        nose = _ellipsoid(p, nose_c, nose_r)
        brow = np.min([_ellipsoid(p, c, brow_r) for c in brow_c], axis=0)
        ear = np.min([_ellipsoid(p, c, ear_r) for c in ear_c], axis=0)
        lips = _ellipsoid(p, lip_c, lip_r)
        cheeks = np.min([_ellipsoid(p, c, cheek_r) for c in cheek_c], axis=0)
        q = p - np.array([-1.0, 0.0, -8.0 * s])
        neck = np.maximum(np.hypot(q[..., 0], q[..., 1]) - neck_r, np.abs(q[..., 2]) - 6.0 * s)
        eyes = np.min([_ellipsoid(p, c, eye_r) for c in eye_c], axis=0)
        return skull, jaw, nose, brow, ear, lips, cheeks, neck, eyes

    def sdf(p):
        skull, jaw, nose, brow, ear, lips, cheeks, neck, eyes = parts(p)
        d = _smin(skull, jaw, 3.0)
        d = _smin(d, cheeks, 1.5)
        d = _smin(d, nose, 0.5)
        d = _smin(d, brow, 1.0)
        d = _smin(d, lips, 0.6)
        d = _smin(d, ear, 0.8)
        d = _smin(d, neck, 2.5)
        d = np.maximum(d, -eyes + 0.0 * d)  # eye sockets
        d = _smin(d, eyes + 0.5, 0.6)  # eyeballs slightly recessed
        return d

    def part(p):
        skull, jaw, nose, brow, ear, lips, cheeks, neck, eyes = parts(p)
        lab = np.zeros(len(p), np.int64)  # skin
        lab[lips < 0.35] = 1
        lab[brow < 0.3] = 2
        lab[(skull < 0.6) & (p[:, 2] > skull_c[2] + skull_r[2] * 0.35) & (p[:, 0] < skull_r[0] * 0.7)] = 3  # hair cap
        lab[eyes < 0.7] = 4
        return lab

    lo = np.array([-skull_r[0] - 2, -skull_r[1] - 3, -14.5 * s])
    hi = np.array([nose_c[0] + nose_r[0] + 2, skull_r[1] + 3, skull_c[2] + skull_r[2] + 2])
    params = dict(scale=s, skull_radii=skull_r.tolist(), nose_length=nose_len, cheek=cheek, neck_radius=neck_r)
    return Shape("head", params, sdf, part, ("skin", "lips", "brows", "hair", "eyes"), (lo, hi))


# ----------------------------------------------------------------------------- meshing

def mesh_shape(shape: Shape, grid: int = 64):
    """Marching cubes of the SDF -> (verts (V, 3) float64, faces (F, 3) int64), watertight, outward-wound,
    normalised so the bounding box is centred and its longest side spans [-EXTENT, EXTENT]."""
    import trimesh
    from skimage.measure import marching_cubes

    lo, hi = (np.asarray(b, np.float64) for b in shape.bounds)
    step = (hi - lo).max() / (grid - 1)
    n = np.ceil((hi - lo) / step).astype(int) + 3
    origin = lo - step
    axes = [origin[i] + step * np.arange(n[i]) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    vol = shape.sdf(pts).reshape(n)
    vol[[0, -1]] = vol[:, [0, -1]] = vol[:, :, [0, -1]] = 1.0  # closed at the grid border
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(step,) * 3)
    verts = verts + origin
    mesh = trimesh.Trimesh(verts, faces, process=True)
    # keep the largest connected piece (marching cubes can leave specks)
    pieces = mesh.split(only_watertight=False)
    if len(pieces) > 1:
        mesh = max(pieces, key=lambda m: len(m.faces))
    mesh.fix_normals()
    v = np.asarray(mesh.vertices, np.float64)
    center = (v.max(0) + v.min(0)) / 2
    scale = EXTENT / ((v.max(0) - v.min(0)).max() / 2)
    v = (v - center) * scale
    return v, np.asarray(mesh.faces, np.int64), dict(center=center.tolist(), scale=float(scale))


def unwrap(verts: np.ndarray, faces: np.ndarray, resolution: int = 256, padding: int = 2):
    """xatlas UV atlas: returns (uvs (T, 2) float32 in [0, 1], OBJ v-up; face_uvs (F, 3) int64)."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(verts.astype(np.float32), faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    pack.bilinear = True
    chart = xatlas.ChartOptions()
    atlas.generate(chart, pack)
    vmapping, indices, uvs = atlas[0]
    # xatlas keeps face order; indices index the split vertices, vmapping maps them back.
    if not np.array_equal(vmapping[indices], faces):
        raise RuntimeError("xatlas changed the face order; cannot map UV corners back to the mesh")
    return uvs.astype(np.float32), indices.astype(np.int64)


def make_shape(kind: str, rng: np.random.Generator, grid: int = 64) -> dict:
    """One procedural object: {'verts', 'faces', 'shape', 'params'} (UVs come from :func:`unwrap`)."""
    if kind == "car":
        shape = car_shape(rng)
    elif kind == "head":
        shape = head_shape(rng)
    else:
        raise ValueError(f"unknown shape kind {kind!r}; expected 'car' or 'head'")
    verts, faces, norm = mesh_shape(shape, grid)
    return dict(verts=verts, faces=faces, shape=shape, normalisation=norm)
