"""Remake the example inputs of ``python -m dibrpp render`` (README, docs/renderer.md):

    python -m examples.make            # or --out DIR

``examples/car.obj``: one procedural car of the datasets' generator (``datagen.shapes``, seed 3), meshed on a
coarse grid and scaled into the unit sphere (the datasets' objects span [-18, 18]), so that a camera at the
default distance of 3 sees all of it from any direction. ``examples/sky.exr``: a 64 x 128 analytic sky, blue
above a grey ground, with a warm sun; linear RGB, Blender's orientation (+Z up, +X at the centre). Both are
deterministic. ``examples/car_photo.exr`` (linear RGBA) and ``car_photo.png`` (8-bit sRGB RGBA): the car as a
photo of it would frame it, the input of ``make demo``: rendered by Blender Cycles at 256 x 256 and cropped to
256 x 208, a red glossy paint, under the sky, from 15 degrees of elevation at 80 units (the datasets' cameras: 27
degrees at 60, their objects scaled into [-18, 18]): the car smaller in the frame than in training, and off-centre.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

from datagen.shapes import car_shape, mesh_shape
from dibrpp import conventions
from dibrpp.cli_args import Parser, check_output_folder
from dibrpp.io import DataError, atomic_path, write_exr, write_png

HERE = Path(__file__).resolve().parent
GRID = 36  # marching-cubes cells along the car's length: ~150 KB of OBJ, still round wheels
SUN_ELEVATION, SUN_AZIMUTH, SUN_RADIUS = 40.0, 70.0, 3.0  # degrees; the sun lights the side at azimuth 45
SUN_RADIANCE = np.array([400.0, 370.0, 320.0])  # 2.5 times the sky's irradiance on the ground
SUPERSAMPLE = 4  # per texel side: the sun disc's edge is averaged, not aliased
# the photo: the datasets' object scale and field of view, another elevation and distance
PHOTO_SCALE, PHOTO_FOV, PHOTO_ELEVATION, PHOTO_AZIMUTH, PHOTO_DISTANCE = 18.0, 39.6, 15.0, 30.0, 80.0
PHOTO_SIDE, PHOTO_ROWS = 256, (40, 248)  # rendered square, then cropped to a landscape photo, the car off-centre
PHOTO_PAINT = dict(base_color=(0.55, 0.04, 0.03), roughness=0.25, metallic=0.0, specular_ior_level=0.5)


def car_mesh(seed: int = 3, grid: int = GRID) -> tuple[np.ndarray, np.ndarray]:
    """(verts (V, 3), faces (F, 3)) of a procedural car centred in the unit sphere, touching it."""
    verts, faces, _ = mesh_shape(car_shape(np.random.default_rng(seed)), grid)
    return verts / np.linalg.norm(verts, axis=-1).max(), faces


def write_obj(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    lines = ["# a procedural car: python -m examples.make"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in verts]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def sky(height: int = 64) -> np.ndarray:
    """(height, 2 height, 3) linear radiance: a sky fading from blue at the zenith to white at the horizon, a
    grey ground, and a sun disc of SUN_RADIUS degrees."""
    fine = conventions.equirect_directions(height * SUPERSAMPLE, 2 * height * SUPERSAMPLE, dtype=torch.float64)
    d = fine.numpy()
    up = d[..., 2:]
    zenith, horizon = np.array([0.1, 0.18, 0.4]), np.array([0.4, 0.4, 0.4])
    upper = horizon + (zenith - horizon) * np.sqrt(np.clip(up, 0, 1))
    ground = np.array([0.12, 0.11, 0.1])
    env = np.where(up > 0, upper, ground)
    el, az = math.radians(SUN_ELEVATION), math.radians(SUN_AZIMUTH)
    sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    env = np.where((d @ sun >= math.cos(math.radians(SUN_RADIUS)))[..., None], SUN_RADIANCE, env)
    texels = env.reshape(height, SUPERSAMPLE, 2 * height, SUPERSAMPLE, 3).mean((1, 3))
    return texels.astype(np.float32)


def photo(verts: np.ndarray, faces: np.ndarray, env: np.ndarray) -> np.ndarray:
    """(208, 256, 4) linear RGBA: the car rendered by Cycles as a photo would frame it (see the module doc)."""
    from datagen.cycles.render import render_scene
    from dibrpp import Cameras

    camera = Cameras.orbit(PHOTO_DISTANCE, PHOTO_ELEVATION, PHOTO_AZIMUTH, PHOTO_FOV, PHOTO_SIDE)
    rgba = render_scene(verts * PHOTO_SCALE, faces, world_to_camera=camera.world_to_camera[0].numpy(),
                        fov=math.radians(PHOTO_FOV), envmap=env, resolution=PHOTO_SIDE, spp=256, max_bounces=2,
                        **PHOTO_PAINT)["rgba"]
    return rgba[PHOTO_ROWS[0]:PHOTO_ROWS[1]]


def make(folder: Path = HERE) -> tuple[Path, ...]:
    """Write ``car.obj``, ``sky.exr`` and the photo (``car_photo.exr``, ``car_photo.png``) into ``folder``;
    returns their paths."""
    mesh, env, exr, png = (folder / name for name in ("car.obj", "sky.exr", "car_photo.exr", "car_photo.png"))
    verts, faces = car_mesh()
    write_obj(mesh, verts, faces)
    env_map = sky()
    write_exr(env, env_map)
    rgba = photo(verts, faces, env_map)
    write_exr(exr, rgba)
    # sRGB-encoded, clipped at 1: what an 8-bit photo keeps; straight alpha, as image editors write it (the render's
    # colour is premultiplied: divided by alpha where the object covers part of a pixel)
    alpha = rgba[..., 3:]
    write_png(png, np.concatenate([np.where(alpha > 0, rgba[..., :3] / np.maximum(alpha, 1e-8), 0.0), alpha], -1))
    return mesh, env, exr, png


def main(argv=None) -> int:
    ap = Parser(prog="python -m examples.make", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(HERE), metavar="DIR", help="folder for car.obj, sky.exr and the photo")
    args = ap.parse_args(argv)
    try:
        check_output_folder("--out", Path(args.out))
        written = make(Path(args.out))
    except (DataError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
