"""Remake the example inputs of ``python -m dibrpp render`` (README, docs/renderer.md):

    python -m examples.make            # or --out DIR

The scene is ``datagen.example_scene``'s. ``examples/car.obj``: one procedural car of the datasets' generator
(``datagen.shapes``, seed 3), meshed on a coarse grid and scaled into the unit sphere (the datasets' objects span
[-18, 18]), so that a camera at the default distance of 3 sees all of it from any direction. ``examples/sky.exr``: a
64 x 128 analytic sky, blue above a grey ground, with a warm sun; linear RGB, Blender's orientation (+Z up, +X at
the centre). Both are deterministic. ``examples/car_photo.exr`` (linear RGBA) and ``car_photo.png`` (8-bit sRGB
RGBA): the car as a photo of it would frame it, the input of ``make demo``: rendered by Blender Cycles at 256 x 256
and cropped to 256 x 208, a red glossy paint, under the sky, from 15 degrees of elevation at 80 units (the datasets'
cameras: 27 degrees at 60, their objects scaled into [-18, 18]): the car smaller in the frame than in training, and
off-centre.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from datagen.example_scene import car_mesh, photo, sky
from dibrpp.cli_args import Parser, check_output_folder
from dibrpp.io import DataError, atomic_path, write_exr, write_png

HERE = Path(__file__).resolve().parent


def write_obj(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    lines = ["# a procedural car: python -m examples.make"]
    lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in verts]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")


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
