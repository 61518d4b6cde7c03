"""Your own environment maps: read, check and resample a folder of HDRIs (``python -m datagen --envmaps DIR``).

Convention (the project's, which is Blender's; see DESIGN.md and :mod:`dibrpp.conventions`): a map is an
equirectangular (latitude-longitude) image of linear HDR radiance, **width = 2 x height**, top row first,
exactly as Blender's Environment Texture node reads it with default mapping:

* the top row is straight up (+Z), the bottom row straight down, the middle row the horizon;
* the image centre (u = 0.5) is the +X direction, u = 0.25 is +Y, u = 0.75 is -Y, the left/right edge -X
  (for a direction d: ``u = 0.5 - atan2(d_y, d_x) / 2 pi``, row ``acos(d_z) / pi * H`` from the top);
* the map is seen from inside, as a panorama: right of the centre in the image is to the right when
  facing +X with +Z up.

Maps from HDRI collections (Poly Haven / HDRI Haven, ...) are made for Blender and need nothing. A map
made in another convention must be turned into this one before use; both are plain numpy operations:

* a rotation about the vertical axis is a roll of the columns: a map whose centre is the -Z direction of
  a Y-up world (OpenGL / three.js style) has that direction at Blender's +Y (a Y-up world maps to Blender
  as (x, y, z) -> (x, -z, y)), i.e. at u = 0.25: ``env = np.roll(env, -env.shape[1] // 4, axis=1)``;
  a rotation by ``a`` degrees about +Z (counter-clockwise seen from above) is
  ``np.roll(env, -round(a / 360 * W), axis=1)``;
* a map seen from outside (mirrored) is flipped: ``env = env[:, ::-1]``;
* a map stored bottom row first is flipped vertically: ``env = env[::-1]``;
* cube maps, light probes (mirror balls) and half (upper-hemisphere) maps must be converted to a full
  equirect map with another tool first; they are refused (not 2:1).

Files: OpenEXR (``.exr``; RGB, RGBA or a single Y channel; the first layer of a multi-layer file) and
Radiance RGBE (``.hdr`` / ``.pic``; read here in numpy, flat or run-length encoded, the ``-Y h +X w``
orientation and its flips, decoded as Blender decodes it; the header's EXPOSURE is ignored, as most
tools do), any resolution. They
are taken in sorted file-name order. Every map is checked before anything renders (readable, 2:1,
finite, non-negative up to the compression noise of lossy EXRs, which becomes 0) and resampled to the dataset's ``envmap_height`` x ``2 * envmap_height`` by area
averaging over solid angle, which preserves the map's energy (the integral of radiance over the
sphere) exactly, whether it shrinks or grows. The manifest records each map's file name, sha256 and
original resolution; a resumed run refuses a folder whose files changed.
"""
from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import numpy as np

from dibrpp.io import DataError, read_exr_channels

__all__ = ["ENVMAP_SUFFIXES", "EnvmapError", "list_envmap_files", "read_envmap_file", "read_hdr", "write_hdr",
           "check_envmap", "resample_equirect", "scan_envmap_folder", "load_envmap_source", "sha256_of", "blender_hdris"]

ENVMAP_SUFFIXES = (".exr", ".hdr", ".pic")


class EnvmapError(DataError):
    """An environment map file that cannot be used; the message names the file and says what to do."""


# ----------------------------------------------------------------------------- folder

def list_envmap_files(folder) -> list[Path]:
    """The .exr / .hdr / .pic files of ``folder`` (not recursive), sorted by name; other files are ignored."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EnvmapError(f"--envmaps {folder}: no such folder; give a folder of .exr / .hdr environment maps")
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in ENVMAP_SUFFIXES),
                   key=lambda p: p.name)
    if not files:
        raise EnvmapError(f"--envmaps {folder}: no .exr or .hdr files in this folder; put equirect HDR maps there")
    return files


def blender_hdris() -> Path:
    """The folder of the eight HDRIs that ship with Blender (its studio lights: captured Poly Haven maps, CC0,
    1024 x 512): real light to try ``--envmaps`` on without downloading anything."""
    import importlib.util

    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        raise EnvmapError("bpy is not installed, so Blender's bundled HDRIs are not there; run `make setup`")
    found = sorted(Path(spec.origin).parent.glob("*/datafiles/studiolights/world"))
    if not found or not list_envmap_files(found[-1]):
        raise EnvmapError(f"no studiolights/world HDRIs under {Path(spec.origin).parent}; give --envmaps a folder of your own")
    return found[-1]


def sha256_of(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ----------------------------------------------------------------------------- Radiance RGBE

_HDR_SIZE = re.compile(rb"^([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*$")


def read_hdr(path) -> np.ndarray:
    """A Radiance RGBE (.hdr) file as an (H, W, 3) float32 array, top row first; raises ValueError if malformed."""
    data = Path(path).read_bytes()
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ValueError("no Radiance header (#?RADIANCE or #?RGBE)")
    pos, fmt = 0, None
    while True:  # header lines up to an empty line
        end = data.find(b"\n", pos)
        if end < 0:
            raise ValueError("header never ends")
        line, pos = data[pos:end].strip(), end + 1
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[7:].strip()
    if fmt not in (None, b"32-bit_rle_rgbe"):
        raise ValueError(f"pixel format {fmt.decode(errors='replace')} is not supported (only 32-bit_rle_rgbe)")
    end = data.find(b"\n", pos)
    m = _HDR_SIZE.match(data[pos:end if end >= 0 else len(data)])
    if not m:
        raise ValueError("resolution line is not '-Y h +X w' (or its flips); transposed files are not supported")
    h, w = int(m.group(2)), int(m.group(4))
    buf = np.frombuffer(data, np.uint8, offset=end + 1)
    rgbe = np.empty((h, w, 4), np.uint8)
    i = 0
    for y in range(h):
        if 8 <= w < 32768 and i + 4 <= len(buf) and buf[i] == 2 and buf[i + 1] == 2 and buf[i + 2] < 128:
            if (int(buf[i + 2]) << 8 | int(buf[i + 3])) != w:
                raise ValueError(f"scanline {y}: run-length width does not match the image width {w}")
            i += 4
            for c in range(4):  # new-style RLE: each component of the scanline in turn
                x = 0
                while x < w:
                    if i >= len(buf):
                        raise ValueError("file is truncated")
                    n = int(buf[i])
                    if n > 128:  # a run of one value
                        n -= 128
                        if x + n > w or i + 1 >= len(buf):
                            raise ValueError(f"scanline {y}: bad run-length data")
                        rgbe[y, x:x + n, c] = buf[i + 1]
                        i += 2
                    else:  # n literal values
                        if n == 0 or x + n > w or i + 1 + n > len(buf):
                            raise ValueError(f"scanline {y}: bad run-length data")
                        rgbe[y, x:x + n, c] = buf[i + 1:i + 1 + n]
                        i += 1 + n
                    x += n
        else:  # flat scanline (old-style RLE is not supported)
            if i + 4 * w > len(buf):
                raise ValueError("file is truncated")
            rgbe[y] = buf[i:i + 4 * w].reshape(w, 4)
            i += 4 * w
    e = rgbe[..., 3].astype(np.int32)
    # mantissa / 256 * 2^(e - 128), as Blender, OpenImageIO and stb_image decode it (Radiance adds 0.5)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    img = (rgbe[..., :3].astype(np.float64) * scale[..., None]).astype(np.float32)
    if m.group(1) == b"+":  # +Y: bottom row first
        img = img[::-1]
    if m.group(3) == b"-":  # -X: right to left
        img = img[:, ::-1]
    return np.ascontiguousarray(img)


def _rle_component(row: np.ndarray) -> bytes:
    out, x, w = bytearray(), 0, len(row)
    while x < w:
        run = 1
        while x + run < w and run < 127 and row[x + run] == row[x]:
            run += 1
        if run >= 4:
            out += bytes((128 + run, int(row[x])))
            x += run
            continue
        start = x  # literal: until the next run of 4 or more
        while x < w and x - start < 128:
            r = 1
            while x + r < w and r < 4 and row[x + r] == row[x]:
                r += 1
            if r >= 4:
                break
            x += 1
        out += bytes((x - start,)) + row[start:x].tobytes()
    return bytes(out)


def write_hdr(path, image, rle: bool = True) -> None:
    """Write an (H, W, 3) non-negative float image as a Radiance RGBE file (top row first, ``-Y H +X W``)."""
    img = np.asarray(image, np.float64)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got shape {img.shape}")
    h, w = img.shape[:2]
    mx = img.max(-1)
    mant, ex = np.frexp(mx)
    ok = mx > 1e-32
    scale = np.where(ok, mant * 256.0 / np.where(ok, mx, 1.0), 0.0)
    rgbe = np.zeros((h, w, 4), np.uint8)
    rgbe[..., :3] = np.clip(np.round(img * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(ok, ex + 128, 0).astype(np.uint8)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for y in range(h):
        if rle and 8 <= w < 32768:
            out += bytes((2, 2, w >> 8, w & 255))
            for c in range(4):
                out += _rle_component(rgbe[y, :, c])
        else:
            out += rgbe[y].tobytes()
    from dibrpp.io import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_bytes(bytes(out))


# ----------------------------------------------------------------------------- read + check

def _read_exr_rgb(path: Path) -> np.ndarray:
    try:
        channels = read_exr_channels(path)
    except DataError as e:
        detail = str(e.__cause__ or e).strip().splitlines()
        raise ValueError(f"not a readable OpenEXR file: {detail[0][:120] if detail else 'unknown error'}") from e
    layers: dict[str, dict[str, np.ndarray]] = {}
    for name, arr in channels.items():
        layer, _, letter = name.rpartition(".")
        layers.setdefault(layer, {})[letter] = arr
    for layer in sorted(layers, key=lambda n: (n != "", n)):  # the unnamed layer first, then by name
        ch = layers[layer]
        if all(c in ch for c in "RGB"):
            return np.stack([ch["R"], ch["G"], ch["B"]], -1)
        if "Y" in ch:
            return np.repeat(ch["Y"][..., None], 3, -1)
    raise ValueError(f"no RGB or Y channels (has {sorted(channels)})")


def read_envmap_file(path) -> np.ndarray:
    """An environment map file as (H, W, 3) float32, top row first, unchecked; EnvmapError if unreadable."""
    path = Path(path)
    what = "re-export it as OpenEXR (.exr) or Radiance (.hdr), or remove it from the folder"
    try:
        if path.suffix.lower() == ".exr":
            img = _read_exr_rgb(path)
        elif path.suffix.lower() in (".hdr", ".pic"):
            img = read_hdr(path)
        else:
            raise ValueError(f"unknown file type {path.suffix!r} (use .exr or .hdr)")
    except (OSError, ValueError) as e:  # DataError is a ValueError
        msg = str(e).replace(f"{path}: ", "")
        raise EnvmapError(f"{path}: cannot read this environment map ({msg}); {what}") from e
    return np.asarray(img, np.float32)


# negative values count as compression noise (and become 0) if none is below -5 % of the map's mean radiance
# and together they hold at most 0.1 % of its energy (Blender's bundled maps: at most 1.4 % and 0.0002 %)
NEGATIVE_VALUE, NEGATIVE_ENERGY = 0.05, 1e-3


def check_envmap(path, img: np.ndarray) -> None:
    """Refuse a map that is not a 2:1 equirect image of finite, non-negative radiance (EnvmapError);
    slightly negative values (``NEGATIVE_VALUE``, ``NEGATIVE_ENERGY``) are compression noise and allowed."""
    h, w = img.shape[:2]
    if w != 2 * h or h < 2:
        raise EnvmapError(f"{path}: {w} x {h} pixels is not an equirectangular map (width must be exactly twice "
                          "the height); convert it to a 2:1 latitude-longitude map or remove it from the folder")
    bad = ~np.isfinite(img)
    if bad.any():
        raise EnvmapError(f"{path}: {int(bad.sum())} NaN/Inf values; repair the map (e.g. replace them by "
                          "their neighbours' values) or remove it from the folder")
    # lossy EXR compression (DWA, as in Blender's own bundled maps) leaves values a hair below zero; those
    # are set to 0 when resampling, larger ones mean a broken map
    neg = img < 0
    mean = max(float(img.mean()), 1e-12)
    if neg.any() and (img.min() < -NEGATIVE_VALUE * mean or -img[neg].sum() > NEGATIVE_ENERGY * img[~neg].sum()):
        raise EnvmapError(f"{path}: {int(neg.sum())} negative values (min {float(img.min()):.4g}); radiance cannot "
                          "be negative: clamp them to 0 or remove the map from the folder")


# ----------------------------------------------------------------------------- resampling

def _row_edges(n: int) -> np.ndarray:
    return np.linspace(0.0, math.pi, n + 1)  # polar angle of the row boundaries, top first


def _overlap_matrix(src_edges: np.ndarray, dst_edges: np.ndarray, measure) -> np.ndarray:
    """W[i, j] = measure(dst cell i ∩ src cell j) / measure(dst cell i): area-average weights."""
    lo = np.maximum(dst_edges[:-1, None], src_edges[None, :-1])
    hi = np.minimum(dst_edges[1:, None], src_edges[None, 1:])
    overlap = np.where(hi > lo, measure(lo, np.maximum(hi, lo)), 0.0)
    return overlap / measure(dst_edges[:-1], dst_edges[1:])[:, None]


def resample_equirect(env: np.ndarray, height: int) -> np.ndarray:
    """Resample an (h, 2h, C) equirect map to (height, 2 * height, C) by area averaging over solid angle.

    Each output pixel is the solid-angle-weighted mean of the input over its footprint (rows weighted by
    cos(top) - cos(bottom), columns by their overlap in azimuth), so sum(L * solid angle) is preserved
    exactly, for shrinking and for growing.
    """
    env = np.asarray(env)
    h, w = env.shape[:2]
    rows = _overlap_matrix(_row_edges(h), _row_edges(height), lambda a, b: np.cos(a) - np.cos(b))
    cols = _overlap_matrix(np.linspace(0.0, 1.0, w + 1), np.linspace(0.0, 1.0, 2 * height + 1), lambda a, b: b - a)
    out = np.empty((height, 2 * height, env.shape[2]), np.float64)
    for c in range(env.shape[2]):
        tmp = np.empty((h, 2 * height))
        for r0 in range(0, h, 512):  # bounded memory for big maps
            tmp[r0:r0 + 512] = env[r0:r0 + 512, :, c].astype(np.float64) @ cols.T
        out[..., c] = rows @ tmp
    return np.maximum(out, 0.0).astype(np.float32)


# ----------------------------------------------------------------------------- dataset use

def scan_envmap_folder(folder) -> list[dict]:
    """Check every map of ``folder`` (sorted) and describe it: file, sha256, height, width.

    Reads every file completely, so a bad map is refused (EnvmapError naming it) before anything renders.
    """
    sources = []
    for p in list_envmap_files(folder):
        img = read_envmap_file(p)
        check_envmap(p, img)
        sources.append(dict(file=p.name, sha256=sha256_of(p), height=int(img.shape[0]), width=int(img.shape[1])))
    return sources


def load_envmap_source(folder, source: dict, height: int) -> np.ndarray:
    """The map ``source`` (an entry of :func:`scan_envmap_folder`) resampled to (height, 2 * height, 3)."""
    p = Path(folder) / source["file"]
    if not p.is_file() or sha256_of(p) != source["sha256"]:
        raise EnvmapError(f"{p}: the file is gone or changed since the run started (sha256 differs); put the "
                          "original back, or generate into a new --out")
    img = read_envmap_file(p)
    check_envmap(p, img)
    return resample_equirect(img, height)
