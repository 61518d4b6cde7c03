"""Predict shape, texture, material and light from one image with a trained run, and re-render it.

    python -m pipelines.predict --checkpoint runs/glossy/sg-seed0 --image photo.png --out pred/

Writes into --out: ``model.glb`` (one file: the mesh, its UVs, the albedo texture and a metallic-roughness
material; opens in Blender, three.js and glTF viewers), ``mesh.obj`` + ``mesh.mtl`` + ``texture.png`` (the same
mesh as OBJ), ``envmap.exr`` and ``envmap.hdr`` (the predicted light as a world-frame equirect map),
``material.json`` and ``novel_views.png`` (re-renderings from ``--views`` views around the object, light fixed in
the world). The files are written into a temporary folder and moved into --out together once all are written.

The image (PNG, JPEG, TIFF, ... read at its own bit depth, 8 or 16 bits, turned upright as its EXIF orientation
says; a float TIFF or an EXR, linear) needs an alpha channel (the object's mask), as the datasets have. Alpha is
straight, as image editors write it: a pixel's colour is the object's own colour, its alpha how much of the pixel
the object covers (a premultiplied EXR, as renderers write it, reads the same way, its outline a little darker,
as the datasets' views are read). A pixel is the object's where its alpha is above 0.5. An image without alpha
is accepted only with ``--background R,G,B``: pixels within ``--tolerance`` of that colour become transparent
(the documented foreground extraction for renders on a flat background), or with ``--mask FILE`` (a grey or RGBA
image of the same size: white, or opaque, is the object); ``--mask`` on an image whose alpha already masks it is
refused (an alpha that is opaque everywhere is no mask and is replaced). Any size from 8 x 8 pixels is taken. The model reads an object's size in
the frame as its size and has no translation of its own, so the image is framed as the training views frame their
object (``pipelines.model.framing``: its size and centroid, recorded in the run's ``camera.json``): ``--framing
auto`` (the default) keeps an image whose object already sits as theirs do (a dataset's view) and crops and pads
any other; ``object`` always re-frames, ``as-is`` never (it pads to a square). Then it is resized to the model's. Its radiance must be finite, non-negative and at most
exp(12) ~ 1.6e5, the brightest light the model predicts (a scaled EXR is refused, not read as a brighter sun).
Give a linear EXR where you have one: the model reads the input's full range, and a sun's reflection that an
8-bit picture clips at 1 is where it finds the sun (an 8-bit picture places the light about as well as a model
trained on clipped input does).
The input camera is an orbit camera looking at the object's centre: ``--azimuth``, ``--elevation``, ``--fov`` and
``--distance``, each the training set-up's (``camera.json``) unless given. The elevation sets which way is up in the
predicted light; the azimuth places the camera around the object (0: its front, cars and heads facing +X; 90: its
left side), which decides the side of the predicted shape the image colours, and turns the predicted light about
the vertical (the light is given in the object's frame, in which the camera stands at that azimuth); the field of view and distance set the perspective the shape is read with (a re-framed image
keeps the object's size in the frame as in training, whatever the photo's zoom).

What a photo can give: the model has seen procedural cars (or heads) of its dataset, on their own, from one
elevation and distance, under its env maps. A photo of a similar object, cut out, gives a shape, an albedo and a
light of that kind; an 8-bit photo clips the highlights the light is read from, so an EXR of the view places the
light better; other objects, clutter or shadows on the ground are outside what it learnt. Cutting out a photo
and choosing the camera: docs/photo.md.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from dibrpp import Cameras
from dibrpp.cli_args import (Parser, check_output_folder, finite_float, float_in, int_in, non_negative_float, unit_rgb)
from dibrpp.io import DataError, atomic_path, staged, write_exr, write_png, write_textured_obj

from .evaluation.prediction_figure import OVERVIEW, REPORT, write_overview, write_report
from .gltf import write_glb
from .photo_input import read_input, read_true_light, read_view, sun_angle_deg
from .training.refine import MAX_STEPS, refine_light
from .training.runs import load_camera, load_run, make_renderer, run_folder

LONG_REFINEMENT_S = 30.0  # a refinement expected to take longer is announced with its estimate
MAX_VIEWS, MAX_SPP = 72, 4096  # novel views (every 5 degrees) and their MC samples: more only fills the memory
# an input camera outside these is said, not refused: degrees of field of view, times the training distance
USUAL_FOV_DEG, USUAL_DISTANCE = (10.0, 100.0), (1 / 3, 10.0)


def say(message: str) -> None:
    """What predict is doing, on stderr (stdout is the material's JSON)."""
    print(message, file=sys.stderr, flush=True)


def unweld_for_uvs(verts: torch.Tensor, faces: torch.Tensor, face_uvs: torch.Tensor) -> torch.Tensor:
    """Vertex position per UV index (the template's seam splits vertices in UV space only)."""
    out = torch.zeros(int(face_uvs.max()) + 1, 3, dtype=verts.dtype)
    out[face_uvs.reshape(-1)] = verts[faces.reshape(-1)]
    return out


@torch.no_grad()
def predict(run: Path, image: Path, out: Path, azimuth: float = 0.0, background=None, tolerance: float = 0.05,
            views: int = 4, spp: int = 64, refine_steps: int = 0, device: str = "cpu", elevation: float | None = None,
            fov: float | None = None, distance: float | None = None, framing_mode: str = "auto", mask=None,
            true_light: Path | None = None) -> dict:
    check_output_folder("--out", out)
    image_rgba = read_input(image, background, tolerance, mask)  # a bad image is refused before the model loads
    known = read_true_light(true_light) if true_light is not None else None
    say(f"loading {run}")
    loaded = load_run(run)
    config, model = loaded.config, loaded.model.to(device)
    trained = checked_camera(run)
    setup = dict(distance=trained["distance"] if distance is None else distance,
                 elevation_deg=trained["elevation_deg"] if elevation is None else elevation,
                 fov_deg=trained["fov_deg"] if fov is None else fov)
    warn_unusual_camera(setup, trained)
    orbit = lambda az, side: Cameras.orbit(setup["distance"], setup["elevation_deg"], az, setup["fov_deg"], side)  # noqa: E731
    say(f"predicting shape, texture, material and light from {image}")
    pred, cam, rgba = read_view(model, image_rgba, image, trained, setup, azimuth, framing_mode, device, say)
    reach = float(pred.meshes().verts[0].norm(dim=-1).max())
    if setup["distance"] <= reach:
        raise DataError(f"--distance {setup['distance']:g}: the camera sits inside the predicted object, which reaches "
                        f"{reach:.3g} from its centre (the training camera stood at {trained['distance']:g}); give a "
                        "larger --distance")
    gain, t0 = torch.ones(1), time.perf_counter()
    if refine_steps:
        say(f"refining the light: {refine_steps} steps against the input view")
        with RefineProgress(refine_steps) as progress:
            pred, gain = refine_light(pred, cam.to(device), rgba[None].to(device),
                                      make_renderer(config, seed=0, training=True, device=device, eager=True),
                                      refine_steps, on_step=progress)
    pred, gain = pred.to("cpu"), gain.cpu()  # written and rendered from here on the CPU
    material = dict(roughness=float(pred.roughness[0]), specular=float(pred.specular[0]),
                    metallic=float(pred.metallic[0]), shading=config.shading, checkpoint=str(run),
                    input=str(image), input_camera=dict(setup, azimuth_deg=azimuth), framing=framing_mode,
                    refine_steps=refine_steps,
                    albedo_gain=float(gain[0]), refine_seconds=round(time.perf_counter() - t0, 3) if refine_steps else 0.0)
    with staged(out) as folder:
        write_results(folder, pred, material, config, cam, orbit, rgba, views, spp, known, true_light)
    say(f"wrote {out}/: {OVERVIEW} and {REPORT} (open it), {', '.join(OUTPUTS)}")
    return material


OUTPUTS = ("model.glb", "mesh.obj", "mesh.mtl", "texture.png", "envmap.exr", "envmap.hdr", "material.json",
           "novel_views.png")


def write_results(out: Path, pred, material: dict, config, cam: Cameras, orbit, rgba: torch.Tensor, views: int,
                  spp: int, known: torch.Tensor | None, true_light: Path | None) -> None:
    """Every output of :func:`predict` into ``out`` (see the module doc); ``material`` gains the sun's angle where
    the true light is ``known``."""
    from datagen.envmap_files import write_hdr

    light = pred.light(cam.world_to_camera)
    mesh = pred.meshes()
    verts = unweld_for_uvs(mesh.verts[0], mesh.faces, mesh.face_uvs)
    write_png(out / "texture.png", pred.texture[0])
    write_textured_obj(out / "mesh.obj", verts, mesh.face_uvs, mesh.uvs, mesh.face_uvs, "texture.png")
    write_glb(out / "model.glb", verts.numpy(), mesh.face_uvs.numpy(), mesh.uvs.numpy(),
              (out / "texture.png").read_bytes(), material["roughness"], material["metallic"],
              extras={"specular": material["specular"], "shading": material["shading"]})
    predicted_map = light.to_envmap(64, 128).image[0]
    write_exr(out / "envmap.exr", predicted_map)
    write_hdr(out / "envmap.hdr", predicted_map.clamp_min(0).numpy())
    if known is not None:
        material.update(true_light=str(true_light), sun_angle_deg=round(sun_angle_deg(predicted_map, known), 1))
        say(f"the predicted sun is {material['sun_angle_deg']:.0f} degrees from {true_light}'s")
    with atomic_path(out / "material.json") as tmp:
        tmp.write_text(json.dumps(material, indent=1))
    size = rgba.shape[0]
    say(f"rendering {views} novel views at {2 * size} px ({config.shading}"
        + (f", {spp} spp" if config.shading == "mc" else "") + ")")
    azimuth = material["input_camera"]["azimuth_deg"]
    cams = orbit(azimuth + torch.arange(views) * (360.0 / views), 2 * size)
    repeated = pred.select([0] * views)
    renderer = make_renderer(config, seed=0, spp=spp, device="cpu", eager=True)
    renders = renderer(repeated.meshes(), cams, repeated.material(),
                       repeated.light(cam.world_to_camera.expand(views, 4, 4))).image
    strip = torch.cat([torch.cat([renders[i, ..., :3] * renders[i, ..., 3:], renders[i, ..., 3:]], -1)
                       for i in range(views)], 1)
    write_png(out / "novel_views.png", strip)
    input_view = orbit(azimuth, 2 * size)
    write_overview(out / OVERVIEW, f"{Path(material['input']).name}: {config.shading.upper()} model "
                   f"{material['checkpoint']}", rgba, renderer.render_normals(pred.meshes(), input_view).image[0],
                   renderer.render_albedo(pred.meshes(), input_view, pred.material()).image[0],
                   predicted_map, list(renders),
                   None if known is None else (known, f"true light ({material['sun_angle_deg']:.0f}° between the suns)"))
    write_report(out, material)


def checked_camera(run: Path) -> dict:
    """The run's camera.json (:func:`load_camera`), refused where it places no camera: a distance not above 0, an
    elevation not strictly between -90 and 90 degrees, a field of view not strictly between 0 and 180."""
    setup = load_camera(run)
    bad = [f"{name} {setup[name]:g} ({what})" for name, ok, what in (
        ("distance", setup["distance"] > 0, "a distance is above 0"),
        ("elevation_deg", -90 < setup["elevation_deg"] < 90, "strictly between -90 and 90"),
        ("fov_deg", 0 < setup["fov_deg"] < 180, "strictly between 0 and 180")) if not ok]
    if bad:
        raise DataError(f"{Path(run) / 'camera.json'}: {', '.join(bad)}; the run's camera set-up is corrupt: restore "
                        "the file or retrain the run")
    return setup


def warn_unusual_camera(setup: dict, trained: dict) -> None:
    """A warning naming a field of view or a distance far from any the model can have learnt from (see USUAL_*)."""
    fov, ratio = setup["fov_deg"], setup["distance"] / trained["distance"]
    if not USUAL_FOV_DEG[0] <= fov <= USUAL_FOV_DEG[1]:
        say(f"warning: --fov {fov:g} degrees is outside {USUAL_FOV_DEG[0]:g}-{USUAL_FOV_DEG[1]:g} (the training views': "
            f"{trained['fov_deg']:.1f}); the shape is read with a perspective unlike any it learnt")
    if not USUAL_DISTANCE[0] <= ratio <= USUAL_DISTANCE[1]:
        say(f"warning: --distance {setup['distance']:g} is {ratio:.3g} times the training camera's "
            f"({trained['distance']:g}); the shape is read with a perspective unlike any it learnt")


class RefineProgress:
    """``on_step`` of :func:`refine_light`: a progress bar on stderr and, when the steps will take longer than
    LONG_REFINEMENT_S, their estimate. A step's time is the second's: the first may compile the renderer."""

    def __init__(self, steps: int, clock=time.perf_counter):
        from tqdm import tqdm

        self.steps, self.clock = steps, clock
        self.last = clock()
        self.bar = tqdm(total=steps, desc="refining", unit="step", file=sys.stderr, leave=False)

    def __call__(self, done: int) -> None:
        now = self.clock()
        step_s, self.last = now - self.last, now
        self.bar.update(1)
        left_s = step_s * (self.steps - done)
        if done == 2 and left_s > LONG_REFINEMENT_S:
            self.bar.write(f"refining the light: about {format_duration(left_s)} for the {self.steps - done} steps "
                           f"left ({step_s:.2f} s a step)", file=sys.stderr)

    def __enter__(self) -> "RefineProgress":
        return self

    def __exit__(self, *exc) -> None:
        self.bar.close()


def format_duration(seconds: float) -> str:
    """"40 s", "12 min", "1.7 h"."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def build_parser() -> Parser:
    ap = Parser(prog="python -m pipelines.predict", description=__doc__)
    ap.add_argument("--checkpoint", required=True, metavar="RUN",
                    help="a run folder (config.json + checkpoint.pt), or its checkpoint.pt")
    ap.add_argument("--image", required=True, metavar="FILE", help="the input image: PNG/JPEG/TIFF (sRGB) or EXR "
                    "(linear), with the object's mask as straight alpha (or see --mask, --background)")
    ap.add_argument("--out", required=True, metavar="DIR", help="folder for the results (made if missing)")
    ap.add_argument("--azimuth", type=finite_float, default=0.0, metavar="DEG",
                    help="azimuth of the input camera around the object (0: its front; 90: its left side)")
    ap.add_argument("--elevation", type=float_in(-89.0, 89.0), metavar="DEG",
                    help="elevation of the input camera above the ground plane (default: the training data's)")
    ap.add_argument("--fov", type=float_in(1.0, 150.0), metavar="DEG",
                    help="field of view of the input camera (default: the training data's)")
    ap.add_argument("--distance", type=float_in(0.0, 1e4, open_low=True), metavar="D",
                    help="distance of the input camera from the object's centre, in the data's units (default: the "
                         "training data's)")
    ap.add_argument("--framing", choices=("auto", "object", "as-is"), default="auto",
                    help="object: crop and pad the image so that its object has the training views' size and place; "
                         "as-is: pad it to a square as it is; auto: as-is where the object already sits about as in "
                         "the training views (a dataset's view), else object (default: auto)")
    ap.add_argument("--mask", metavar="FILE", help="the object's mask as an image of the input's size (white or opaque: "
                    "the object; above 0.5 counts), for an image without alpha (or with one opaque everywhere)")
    ap.add_argument("--background", type=unit_rgb, metavar="R,G,B",
                    help="sRGB colour (0-1) of a flat background to cut out of an image without alpha")
    ap.add_argument("--tolerance", type=non_negative_float, default=0.05, metavar="FLOAT",
                    help="with --background: largest sRGB difference from it that is still background")
    ap.add_argument("--views", type=int_in(1, MAX_VIEWS), default=4, metavar="N",
                    help="novel views rendered around the object")
    ap.add_argument("--spp", type=int_in(1, MAX_SPP), default=64, metavar="N", help="MC samples per pixel of the novel views")
    ap.add_argument("--refine-steps", type=int_in(0, MAX_STEPS), default=0, metavar="N",
                    help=f"refine the predicted light with N Adam steps against the input view (pipelines.training.refine; "
                         f"tens suffice, at most {MAX_STEPS}; the time they take is shown as they run)")
    ap.add_argument("--true-light", metavar="FILE", type=Path,
                    help="the env map the image was taken under (.exr or .hdr; world frame, +Z up, the project's "
                         "convention; in the frame --azimuth places the camera in): shown beside the prediction, with "
                         "the angle between their suns")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                    help="where the model predicts and refines (the outputs are rendered on the CPU) (default: cpu)")
    return ap


def main(argv=None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: torch sees no CUDA device here; install a CUDA build of torch or use --device cpu")
    if not args.out.strip():
        ap.error("--out: expected a folder, got an empty string")
    try:
        run = run_folder(args.checkpoint)
        if args.mask is not None and args.background is not None:
            ap.error("--mask and --background both give the object's mask: pass one")
        material = predict(run, Path(args.image), Path(args.out), args.azimuth, args.background, args.tolerance,
                           views=args.views, spp=args.spp, refine_steps=args.refine_steps, device=args.device,
                           elevation=args.elevation, fov=args.fov, distance=args.distance, framing_mode=args.framing,
                           mask=args.mask, true_light=args.true_light)
    except (DataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk filled up, or the folder went away while predicting
        print(f"error: --out {args.out}: cannot write the results ({e}); free space or choose another folder",
              file=sys.stderr)
        return 2
    print(json.dumps(material, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
