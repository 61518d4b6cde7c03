"""Predict shape, texture, material and light from one image with a trained run, and re-render it.

    python -m pipelines.predict --checkpoint runs/glossy/sg-seed0 --image photo.png --out pred/

Writes into --out: ``mesh.obj`` + ``mesh.mtl`` + ``texture.png`` (opens textured in Blender),
``envmap.exr`` (the predicted light as a world-frame equirect map), ``material.json`` and
``novel_views.png`` (re-renderings from ``--views`` views around the object, light fixed in the world).

The image (PNG, JPEG, TIFF, ... read at its own bit depth, 8 or 16 bits; or a linear EXR) needs an alpha
channel (the object's mask), as the datasets have; an image without one is accepted only with
``--background R,G,B``: pixels within ``--tolerance`` of that colour become transparent (the documented
foreground extraction for renders on a flat background), or with ``--mask FILE`` (a grey or RGBA image of the same
size: white, or opaque, is the object). Any size from 8 x 8 pixels is taken. The model reads an object's size in
the frame as its size and has no translation of its own, so the image is framed as the training views frame their
object (``pipelines.model.framing``: its size and centroid, recorded in the run's ``camera.json``): ``--framing
auto`` (the default) keeps an image whose object already sits as theirs do (a dataset's view) and crops and pads
any other; ``object`` always re-frames, ``as-is`` never (it pads to a square). Then it is resized to the model's. Its radiance must be finite, non-negative and at most
exp(12) ~ 1.6e5, the brightest light the model predicts (a scaled EXR is refused, not read as a brighter sun).
Give a linear EXR where you have one: the model reads the input's full range, and a sun's reflection that an
8-bit picture clips at 1 is where it finds the sun (docs/experiments.md, entry 13).
The input camera is an orbit camera looking at the object's centre: ``--azimuth``, ``--elevation``, ``--fov`` and
``--distance``, each the training set-up's (``camera.json``) unless given. The elevation sets which way is up in the
predicted light; the field of view and distance set the perspective the shape is read with (a re-framed image
keeps the object's size in the frame as in training, whatever the photo's zoom).

What a photo can give: the model has seen procedural cars (or heads) of its dataset, on their own, from one
elevation and distance, under its env maps. A photo of a similar object, cut out, gives a shape, an albedo and a
light of that kind; an 8-bit photo clips the highlights the light is read from, so an EXR of the view places the
light better; other objects, clutter or shadows on the ground are outside what it learnt.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from dibrpp import Cameras
from dibrpp.cli_args import (Parser, check_output_folder, finite_float, float_in, int_in, non_negative_float, unit_rgb)
from dibrpp.display import display_image
from dibrpp.io import DataError, atomic_path, read_image, write_exr, write_png, write_textured_obj

from .evaluation.metrics import dominant_direction
from .evaluation.prediction_figure import OVERVIEW, REPORT, write_overview, write_report
from .model import framing
from .model.model_input import MAX_LOG_RADIANCE, encoder_input
from .training.refine import MAX_STEPS, refine_light
from .training.runs import load_camera, load_run, make_renderer, run_folder

MIN_SIDE = 8  # pixels: a smaller image holds no object to speak of
# The brightest light the model predicts (and the most its input decodes to): no light it can place explains
# brighter pixels, so such an image is scaled (or corrupt), not lit by a brighter sun.
MAX_RADIANCE = math.exp(MAX_LOG_RADIANCE)
LONG_REFINEMENT_S = 30.0  # a refinement expected to take longer is announced with its estimate
MAX_VIEWS, MAX_SPP = 72, 4096  # novel views (every 5 degrees) and their MC samples: more only fills the memory


def say(message: str) -> None:
    """What predict is doing, on stderr (stdout is the material's JSON)."""
    print(message, file=sys.stderr, flush=True)


def read_input(path, background: tuple[float, float, float] | None, tolerance: float, mask=None) -> torch.Tensor:
    """(H, W, 4) linear RGB + alpha of an image file, checked: big enough, with an object in it (see the module
    doc for RGB inputs and ``mask``)."""
    if Path(path).is_dir():
        raise DataError(f"--image {path}: is a folder; --image takes one image file (PNG, JPEG, TIFF or EXR)")
    img = torch.from_numpy(np.ascontiguousarray(read_image(path, linear=True))).float()
    height, width = img.shape[:2]
    if min(height, width) < MIN_SIDE:
        raise DataError(f"{path}: {width} x {height} pixels is too small; give an image of at least "
                        f"{MIN_SIDE} x {MIN_SIDE} pixels showing the object")
    check_radiance(path, img[..., :3])
    if mask is not None:
        img = torch.cat([img[..., :3], read_mask(mask, (height, width))], -1)
    elif img.shape[-1] == 3:
        img = torch.cat([img, foreground_mask(path, img, background, tolerance)], -1)
    elif background is not None:
        raise DataError(f"{path}: has an alpha channel, which is the object's mask; --background cuts a mask out of "
                        "an image without one: drop --background (or the alpha)")
    alpha = img[..., 3]
    if not (torch.isfinite(alpha).all() and alpha.min() >= 0 and alpha.max() <= 1 + 1e-3):
        raise DataError(f"{path}: alpha outside [0, 1] (min {float(alpha.min()):.3g}, max {float(alpha.max()):.3g}); "
                        "alpha is the object's coverage: give a straight (not scaled) alpha")
    img[..., 3] = alpha.clamp(0, 1)
    if img[..., 3].max() <= 0:
        raise DataError(f"{path}: the alpha channel is empty (no object)")
    return img


def read_mask(path, size: tuple[int, int]) -> torch.Tensor:
    """(H, W, 1) the object's coverage from a mask image: its alpha where it has one, else its grey level."""
    mask = torch.from_numpy(np.ascontiguousarray(read_image(path, linear=False))).float()
    if tuple(mask.shape[:2]) != size:
        raise DataError(f"--mask {path}: {mask.shape[1]} x {mask.shape[0]} pixels, the image {size[1]} x {size[0]}; "
                        "give a mask of the image's size")
    coverage = mask[..., 3] if mask.shape[-1] == 4 else mask[..., :3].mean(-1)
    return coverage.clamp(0, 1).unsqueeze(-1)


def check_radiance(path, rgb: torch.Tensor) -> None:
    """Refuse colour that is no radiance the model could have seen: NaN / Inf (a float TIFF can hold them),
    negative, or above :data:`MAX_RADIANCE`."""
    finite = torch.isfinite(rgb)
    if not finite.all():
        raise DataError(f"{path}: {int((~finite).sum())} non-finite values (NaN/Inf); the file is corrupt")
    if (rgb < 0).any():
        raise DataError(f"{path}: {int((rgb < 0).sum())} negative values (min {float(rgb.min()):.3g}); radiance "
                        "cannot be negative, clamp the image at 0")
    peak = float(rgb.max())
    if peak > MAX_RADIANCE:
        raise DataError(f"{path}: radiance up to {peak:.3g}, above {MAX_RADIANCE:.3g} (exp({MAX_LOG_RADIANCE:g}), the "
                        "brightest light the model predicts); the image looks scaled: give it in scene-linear units "
                        "(a sun's reflection in the datasets is about 1e4)")


def resize_input(img: torch.Tensor, size: int) -> torch.Tensor:
    """(size, size, 4): ``img`` padded to a square (transparent) and resized by area averaging."""
    resized = torch.nn.functional.interpolate(pad_to_square(img).permute(2, 0, 1)[None], size=(size, size),
                                              mode="area")[0]
    return resized.permute(1, 2, 0)


def foreground_mask(path, rgb: torch.Tensor, background, tolerance: float) -> torch.Tensor:
    """(H, W, 1): 1 where the pixel's sRGB colour is farther than ``tolerance`` from ``background``."""
    if background is None:
        raise DataError(f"{path}: no alpha channel; give the object's mask as alpha (RGBA PNG/EXR) or pass "
                        "--background R,G,B (sRGB 0-1) to cut out a flat background")
    distance = (display_image(rgb) - torch.tensor(background, dtype=rgb.dtype)).abs().amax(-1)
    return (distance > tolerance).float().unsqueeze(-1)


def pad_to_square(img: torch.Tensor) -> torch.Tensor:
    """Transparent borders around the shorter side, so that resizing keeps the object's proportions."""
    height, width = img.shape[:2]
    side = max(height, width)
    top, left = (side - height) // 2, (side - width) // 2
    return torch.nn.functional.pad(img, (0, 0, left, side - width - left, top, side - height - top))


def frame_input(path, rgba: torch.Tensor, trained: dict, mode: str) -> torch.Tensor:
    """The image framed for the model (``--framing``; ``trained``: the run's camera.json): as the training views
    frame their object (object), as it is (as-is), or as it is unless its object's size or place differs from the
    training views' beyond their spread (auto), each said where it matters."""
    if "object_size" not in trained:
        if mode == "object":
            say(f"note: the run records no framing of its training views (trained before it was recorded); {path} "
                "is used as framed")
        return rgba
    seen = framing.image_framing(rgba[..., 3])
    like = framing.frames_like(seen, trained)
    if mode == "object" or (mode == "auto" and not like):
        if mode == "auto":
            say(f"note: the object spans {seen['object_size'] / trained['object_size']:.2f}x the training views' size "
                f"in {path}, centred at {seen['object_centre'][0]:.2f}, {seen['object_centre'][1]:.2f} (theirs "
                f"{trained['object_centre'][0]:.2f}, {trained['object_centre'][1]:.2f}): re-framed as they frame it")
        return framing.reframe(rgba, trained)
    if not like:
        say(f"warning: the object in {path} is framed unlike the training views' (size {seen['object_size']:.2f} of the "
            f"side against {trained['object_size']:.2f}); the model reads its size as the car's: use --framing auto")
    return rgba


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
    size = model.config.image_size  # the side of the images the run trained on
    trained = load_camera(run)
    setup = dict(distance=trained["distance"] if distance is None else distance,
                 elevation_deg=trained["elevation_deg"] if elevation is None else elevation,
                 fov_deg=trained["fov_deg"] if fov is None else fov)
    orbit = lambda az, side: Cameras.orbit(setup["distance"], setup["elevation_deg"], az, setup["fov_deg"], side)  # noqa: E731
    rgba = resize_input(frame_input(image, image_rgba, trained, framing_mode), size)
    if model.config.input_range == "full" and float(image_rgba[..., :3].max()) <= 1.0:
        say(f"note: {image} holds no radiance above 1 (an 8-bit picture clips the sun's reflection); this model reads "
            "the full range and places the light best from a linear EXR of the same view")
    say(f"predicting shape, texture, material and light from {image}")
    cam = orbit(azimuth, size)
    pred = model(encoder_input(rgba[None].to(device)), cam.to(device))
    gain, t0 = torch.ones(1), time.perf_counter()
    if refine_steps:
        say(f"refining the light: {refine_steps} steps against the input view")
        with RefineProgress(refine_steps) as progress:
            pred, gain = refine_light(pred, cam.to(device), rgba[None].to(device),
                                      make_renderer(config, seed=0, training=True, device=device, eager=True),
                                      refine_steps, on_step=progress)
    pred, gain = pred.to("cpu"), gain.cpu()  # written and rendered from here on the CPU
    light = pred.light(cam.world_to_camera)
    out.mkdir(parents=True, exist_ok=True)
    mesh = pred.meshes()
    write_png(out / "texture.png", pred.texture[0])
    write_textured_obj(out / "mesh.obj", unweld_for_uvs(mesh.verts[0], mesh.faces, mesh.face_uvs), mesh.face_uvs,
                       mesh.uvs, mesh.face_uvs, "texture.png")
    write_exr(out / "envmap.exr", light.to_envmap(64, 128).image[0])
    material = dict(roughness=float(pred.roughness[0]), specular=float(pred.specular[0]),
                    metallic=float(pred.metallic[0]), shading=config.shading, checkpoint=str(run),
                    input=str(image), input_camera=dict(setup, azimuth_deg=azimuth), framing=framing_mode,
                    refine_steps=refine_steps,
                    albedo_gain=float(gain[0]), refine_seconds=round(time.perf_counter() - t0, 3) if refine_steps else 0.0)
    predicted_map = light.to_envmap(64, 128).image[0]
    if known is not None:
        material.update(true_light=str(true_light), sun_angle_deg=round(sun_angle_deg(predicted_map, known), 1))
        say(f"the predicted sun is {material['sun_angle_deg']:.0f} degrees from {true_light}'s")
    with atomic_path(out / "material.json") as tmp:
        tmp.write_text(json.dumps(material, indent=1))
    say(f"rendering {views} novel views at {2 * size} px ({config.shading}"
        + (f", {spp} spp" if config.shading == "mc" else "") + ")")
    azimuths = azimuth + torch.arange(views) * (360.0 / views)
    cams = orbit(azimuths, 2 * size)
    repeated = pred.select([0] * views)
    renderer = make_renderer(config, seed=0, spp=spp, device="cpu", eager=True)
    renders = renderer(repeated.meshes(), cams, repeated.material(),
                       repeated.light(cam.world_to_camera.expand(views, 4, 4))).image
    strip = torch.cat([torch.cat([renders[i, ..., :3] * renders[i, ..., 3:], renders[i, ..., 3:]], -1)
                       for i in range(views)], 1)
    write_png(out / "novel_views.png", strip)
    input_view = orbit(azimuth, 2 * size)
    write_overview(out / OVERVIEW, f"{image.name}: {config.shading.upper()} model {run}", rgba,
                   renderer.render_normals(pred.meshes(), input_view).image[0],
                   renderer.render_albedo(pred.meshes(), input_view, pred.material()).image[0],
                   predicted_map, list(renders),
                   None if known is None else (known, f"true light ({material['sun_angle_deg']:.0f}° between the suns)"))
    write_report(out, material)
    say(f"wrote {out}/: {OVERVIEW} and {REPORT} (open it), mesh.obj, mesh.mtl, texture.png, envmap.exr, "
        "material.json, novel_views.png")
    return material


def read_true_light(path: Path) -> torch.Tensor:
    """(64, 128, 3) the env map an image was taken under (world frame, the project's convention; .exr or .hdr),
    resampled as the datasets resample a file map."""
    from datagen.envmap_files import EnvmapError, check_envmap, read_envmap_file, resample_equirect

    try:
        env = read_envmap_file(path)
        check_envmap(path, env)
    except EnvmapError as e:
        raise DataError(f"--true-light {e}") from None
    return torch.from_numpy(np.ascontiguousarray(resample_equirect(env, 64))).float()


def sun_angle_deg(predicted: torch.Tensor, true: torch.Tensor) -> float:
    """Degrees between the dominant directions (evaluation.metrics.dominant_direction, the eval's sun) of two
    world-frame maps (H, W, 3)."""
    suns = dominant_direction(torch.stack([predicted, true]))[0]
    return math.degrees(math.acos(float((suns[0] * suns[1]).sum().clamp(-1, 1))))


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
                    "(linear), with the object's mask as alpha (or see --background)")
    ap.add_argument("--out", required=True, metavar="DIR", help="folder for the results (made if missing)")
    ap.add_argument("--azimuth", type=finite_float, default=0.0, metavar="DEG", help="azimuth of the input camera")
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
                    "the object), for an image without alpha")
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
