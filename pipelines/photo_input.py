"""A photo as a model's input: the image read and checked (linear RGB with straight alpha, the object's coverage,
from the file's own alpha, a ``--mask`` image or a flat ``--background`` cut out; see predict's doc), the model's
reading of it from an orbit camera, and the light it was taken under where that is known (``--true-light``)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from dibrpp.display import display_image
from dibrpp.io import DataError, read_image

from .model import framing
from .model.model_input import MAX_LOG_RADIANCE

MIN_SIDE = 8  # pixels: a smaller image holds no object to speak of
# The brightest light the model predicts (and the most its input decodes to): no light it can place explains
# brighter pixels, so such an image is scaled (or corrupt), not lit by a brighter sun.
MAX_RADIANCE = math.exp(MAX_LOG_RADIANCE)


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
    if (mask is not None or background is not None) and img.shape[-1] == 4 and bool((img[..., 3] >= 1).all()):
        img = img[..., :3]  # an alpha opaque everywhere masks nothing: the mask is cut another way
    if mask is not None:
        if img.shape[-1] == 4:
            raise DataError(f"{path}: has an alpha channel, which is the object's mask; --mask {mask} would replace "
                            "it: drop --mask (or the alpha)")
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
    if img[..., 3].max() <= framing.COVERED:
        source = f"--mask {mask}" if mask is not None else str(path)
        raise DataError(f"{source}: the object's coverage is at most {float(img[..., 3].max()):.2f}, never above "
                        f"{framing.COVERED}, where a pixel counts as the object's; make the object opaque (alpha 1) or "
                        "white in the mask (a coloured mask reads as its mean grey: pure red is 0.33)")
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


def foreground_mask(path, rgb: torch.Tensor, background, tolerance: float) -> torch.Tensor:
    """(H, W, 1): 1 where the pixel's sRGB colour is farther than ``tolerance`` from ``background``."""
    if background is None:
        raise DataError(f"{path}: no alpha channel; give the object's mask as alpha (RGBA PNG/EXR) or pass "
                        "--background R,G,B (sRGB 0-1) to cut out a flat background")
    distance = (display_image(rgb) - torch.tensor(background, dtype=rgb.dtype)).abs().amax(-1)
    return (distance > tolerance).float().unsqueeze(-1)


def read_view(model, rgba: torch.Tensor, path, trained: dict, setup: dict, azimuth: float, framing_mode: str = "auto",
              device: str = "cpu", say=print):
    """The model's prediction from one image (``rgba``: :func:`read_input`'s) seen by an orbit camera (``setup``:
    distance, elevation_deg and fov_deg; ``azimuth`` in degrees; ``trained``: the run's camera.json, whose framing
    the image is given): (the prediction, the camera, the framed (S, S, 4) input the model read)."""
    from dibrpp import Cameras

    from .model.model_input import encoder_input

    size = model.config.image_size  # the side of the images the run trained on
    framed = framing.resize_input(framing.frame_input(path, rgba, trained, framing_mode, say), size)
    if model.config.input_range == "full" and float(rgba[..., :3].max()) <= 1.0:
        say(f"note: {path} holds no radiance above 1 (an 8-bit picture clips the sun's reflection); this model reads "
            "the full range and places the light best from a linear EXR of the same view")
    cam = Cameras.orbit(setup["distance"], setup["elevation_deg"], azimuth, setup["fov_deg"], size)
    return model(encoder_input(framed[None].to(device)), cam.to(device)), cam, framed


def read_true_light(path: Path) -> torch.Tensor:
    """(64, 128, 3) the env map an image was taken under (world frame, the project's convention; .exr or .hdr),
    resampled as the datasets resample a file map."""
    from datagen.envmap_files import EnvmapError, check_envmap, read_envmap_file, resample_equirect

    if not Path(path).is_file():
        raise DataError(f"--true-light {path}: no such file; give an env map (.exr or .hdr)")
    try:
        env = read_envmap_file(path)
        check_envmap(path, env)
    except EnvmapError as e:
        raise DataError(f"--true-light {e}") from None
    return torch.from_numpy(np.ascontiguousarray(resample_equirect(env, 64))).float()


def sun_angle_deg(predicted: torch.Tensor, true: torch.Tensor) -> float:
    """Degrees between the dominant directions (evaluation.metrics.dominant_direction, the eval's sun) of two
    world-frame maps (H, W, 3)."""
    from .evaluation.metrics import dominant_direction

    suns = dominant_direction(torch.stack([predicted, true]))[0]
    return math.degrees(math.acos(float((suns[0] * suns[1]).sum().clamp(-1, 1))))
