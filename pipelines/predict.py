"""Predict shape, texture, material and light from one image with a trained run, and re-render it.

    python -m pipelines.predict --checkpoint runs/glossy/sg-seed0 --image photo.png --out pred/

Writes into --out: ``mesh.obj`` + ``mesh.mtl`` + ``texture.png`` (opens textured in Blender),
``envmap.exr`` (the predicted light as a world-frame equirect map), ``material.json`` and
``novel_views.png`` (re-renderings from 4 views around the object, light fixed in the world).

The image needs an alpha channel (the object's mask), as the datasets have; an RGB image is accepted
only with ``--background R,G,B``: pixels within ``--tolerance`` of that colour become transparent (the
documented foreground extraction for renders on a flat background). Any size is resized to the model's.
The input camera is taken to be the training set-up (distance, elevation and field of view of the
training dataset, stored with the run in ``camera.json``) at ``--azimuth`` degrees.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from dibrpp import Cameras
from dibrpp.display import display_image
from dibrpp.io import DataError, atomic_path, read_image, write_exr, write_png, write_textured_obj

from .model import encoder_input
from .runs import load_camera, load_run, make_renderer, run_folder


def load_input(path, size: int, background: tuple[float, float, float] | None, tolerance: float) -> torch.Tensor:
    """(size, size, 4) linear RGB + alpha from an image file, resized; see the module doc for RGB inputs."""
    img = torch.from_numpy(np.ascontiguousarray(read_image(path, linear=True))).float()
    if img.dim() == 2:
        img = img.unsqueeze(-1).expand(-1, -1, 3)
    if img.shape[-1] == 3:
        if background is None:
            raise DataError(f"{path}: no alpha channel; give the object's mask as alpha (RGBA PNG/EXR) or pass "
                            "--background R,G,B (sRGB 0-1) to cut out a flat background")
        bg = torch.tensor(background, dtype=img.dtype)
        distance = (display_image(img) - bg).abs().amax(-1)
        img = torch.cat([img, (distance > tolerance).float().unsqueeze(-1)], -1)
    img = img[..., :4]
    if img[..., 3].max() <= 0:
        raise DataError(f"{path}: the alpha channel is empty (no object)")
    resized = torch.nn.functional.interpolate(img.permute(2, 0, 1)[None], size=(size, size), mode="area")[0]
    return resized.permute(1, 2, 0)


def unweld_for_uvs(verts: torch.Tensor, faces: torch.Tensor, face_uvs: torch.Tensor) -> torch.Tensor:
    """Vertex position per UV index (the template's seam splits vertices in UV space only)."""
    out = torch.zeros(int(face_uvs.max()) + 1, 3, dtype=verts.dtype)
    out[face_uvs.reshape(-1)] = verts[faces.reshape(-1)]
    return out


@torch.no_grad()
def predict(run: Path, image: Path, out: Path, azimuth: float = 0.0, background=None, tolerance: float = 0.05,
            views: int = 4, spp: int = 64) -> dict:
    loaded = load_run(run)
    config, model = loaded.config, loaded.model
    setup = load_camera(run)
    orbit = lambda az, size: Cameras.orbit(setup["distance"], setup["elevation_deg"], az, setup["fov_deg"], size)  # noqa: E731
    rgba = load_input(image, config.image_size, background, tolerance)
    cam = orbit(azimuth, config.image_size)
    pred = model(encoder_input(rgba[None]), cam)
    light = pred.light(cam.world_to_camera)
    out.mkdir(parents=True, exist_ok=True)
    mesh = pred.meshes()
    write_png(out / "texture.png", pred.texture[0])
    write_textured_obj(out / "mesh.obj", unweld_for_uvs(mesh.verts[0], mesh.faces, mesh.face_uvs), mesh.face_uvs,
                       mesh.uvs, mesh.face_uvs, "texture.png")
    write_exr(out / "envmap.exr", light.to_envmap(64, 128).image[0])
    material = dict(roughness=float(pred.roughness[0]), specular=float(pred.specular[0]),
                    metallic=float(pred.metallic[0]), shading=config.shading, checkpoint=str(run),
                    input=str(image), input_camera=dict(setup, azimuth_deg=azimuth))
    with atomic_path(out / "material.json") as tmp:
        tmp.write_text(json.dumps(material, indent=1))
    azimuths = azimuth + torch.arange(views) * (360.0 / views)
    cams = orbit(azimuths, 2 * config.image_size)
    repeated = pred.select([0] * views)
    renders = make_renderer(config, seed=0, spp=spp)(repeated.meshes(), cams, repeated.material(),
                                            repeated.light(cam.world_to_camera.expand(views, 4, 4))).image
    strip = torch.cat([torch.cat([renders[i, ..., :3] * renders[i, ..., 3:], renders[i, ..., 3:]], -1)
                       for i in range(views)], 1)
    write_png(out / "novel_views.png", strip)
    return material


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True, help="a run folder (config.json + checkpoint.pt)")
    ap.add_argument("--image", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--azimuth", type=float, default=0.0, help="azimuth (deg) of the input camera")
    ap.add_argument("--background", help="R,G,B (sRGB, 0-1) of a flat background to cut out of an RGB image")
    ap.add_argument("--tolerance", type=float, default=0.05)
    ap.add_argument("--spp", type=int, default=64, help="MC samples per pixel of the novel views")
    args = ap.parse_args(argv)
    try:
        run = run_folder(args.checkpoint)
        background = None
        if args.background:
            try:
                background = tuple(float(x) for x in args.background.split(","))
                assert len(background) == 3
            except (ValueError, AssertionError):
                raise ValueError(f"--background {args.background!r}: expected R,G,B like 1,1,1") from None
        material = predict(run, Path(args.image), Path(args.out), args.azimuth, background, args.tolerance, spp=args.spp)
    except (DataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(material, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
