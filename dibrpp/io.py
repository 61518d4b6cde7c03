"""The one I/O module: EXR (linear HDR), PNG (sRGB 8-bit), meshes (via trimesh), atomic writes.

Every reader validates what it reads and raises :class:`DataError` with a message that says what is
wrong and what to do; every writer writes to a temporary file and renames, so a crash never leaves a
half-written file behind.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch


class DataError(ValueError):
    """A file that cannot be used as it is: missing, unreadable, wrong shape or non-finite."""


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds.

    The file gets the permissions of a normally written one (0o666 less the umask: 0644 under umask 022),
    not mkstemp's 0600, which would hide a dataset from the other users of a shared machine.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _create_temp_file(path.parent, f".{path.name}.", suffix or path.suffix)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class staged:
    """``with staged(out) as folder``: a new folder beside ``out`` (inside it where it exists) to write into; when the
    block succeeds its files move into ``out`` (made if missing) together, and the folder goes either way, so a
    failure leaves ``out`` as it was."""

    def __init__(self, out: Path):
        self.out = Path(out)

    def __enter__(self) -> Path:
        parent = self.out if self.out.is_dir() else self.out.parent
        parent.mkdir(parents=True, exist_ok=True)
        self.folder = Path(tempfile.mkdtemp(prefix=f".{self.out.name or 'out'}.", suffix=".partial", dir=parent))
        return self.folder

    def __exit__(self, kind, *exc) -> None:
        try:
            if kind is None:
                self.out.mkdir(parents=True, exist_ok=True)
                for path in sorted(self.folder.iterdir()):
                    os.replace(path, self.out / path.name)
        finally:
            shutil.rmtree(self.folder, ignore_errors=True)



def _create_temp_file(folder: Path, prefix: str, suffix: str) -> str:
    """Create a new, empty file ``folder/prefix<random>suffix`` with mode 0o666 less the umask."""
    for _ in range(100):
        name = os.path.join(folder, f"{prefix}{secrets.token_hex(4)}{suffix}")
        try:
            os.close(os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue
        return name
    raise FileExistsError(f"{folder}: could not find a free temporary file name {prefix}*{suffix}")


def _require_file(path) -> Path:
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not a file")
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    return path


# ----------------------------------------------------------------------------- EXR

def read_exr_channels(path) -> dict[str, np.ndarray]:
    """All channels of a (single- or multi-layer) EXR as float32 (H, W) arrays keyed by full name."""
    import OpenEXR

    path = _require_file(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError with little context
        raise DataError(f"{path}: not a readable OpenEXR file ({e}); re-export it as EXR") from e
    return channels


def read_exr(path, channels: str = "RGB", allow_nonfinite: bool = False) -> np.ndarray:
    """Read ``channels`` (e.g. "RGB", "RGBA") of an EXR into a float32 (H, W, C) array.

    Channel letters are matched against the last dotted component of the channel names, so
    multi-layer files written by Blender ("ViewLayer.Combined.R") read the same way.
    """
    found = read_exr_channels(path)
    by_letter = {}
    for name, arr in found.items():
        by_letter.setdefault(name.split(".")[-1], arr)
    missing = [c for c in channels if c not in by_letter]
    if missing:
        raise DataError(f"{path}: EXR has channels {sorted(found)}, missing {missing}; expected {channels}")
    img = np.stack([by_letter[c] for c in channels], -1)
    if not allow_nonfinite and not np.isfinite(img).all():
        bad = int((~np.isfinite(img)).sum())
        raise DataError(f"{path}: {bad} non-finite values (NaN/Inf) in channels {channels}; the file is corrupt")
    return img


def write_exr(path, image, channels: str | None = None) -> None:
    """Write a float (H, W, C) array/tensor as a single-part, ZIP-compressed float32 EXR, atomically."""
    import OpenEXR

    img = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    channels = channels or {1: "Y", 3: "RGB", 4: "RGBA"}.get(img.shape[-1])
    if channels is None or len(channels) != img.shape[-1]:
        raise ValueError(f"cannot name the channels of an image of shape {img.shape}; pass channels=")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {c: np.ascontiguousarray(img[..., i], dtype=np.float32) for i, c in enumerate(channels)}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, data).write(str(tmp))


# ----------------------------------------------------------------------------- PNG

def read_png(path, linear: bool = False) -> np.ndarray:
    """An 8/16-bit image as float32 (H, W, C) in [0, 1]; sRGB-decoded to linear if ``linear``."""
    from PIL import Image, UnidentifiedImageError

    path = _require_file(path)
    try:
        with Image.open(path) as im:
            has_alpha = im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info)
            mode = "RGBA" if has_alpha else "RGB"
            arr = np.asarray(im.convert(mode), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as e:
        raise DataError(f"{path}: not a readable image ({e})") from e
    if linear:
        from .conventions import srgb_to_linear

        rgb = srgb_to_linear(torch.from_numpy(arr[..., :3])).numpy()
        arr = np.concatenate([rgb, arr[..., 3:]], -1)
    return arr


def write_png(path, image, srgb: bool = True) -> None:
    """Write a linear float (H, W, C) image (C = 1, 3 or 4) as 8-bit PNG; colour sRGB-encoded, alpha kept linear."""
    from PIL import Image

    from .conventions import linear_to_srgb

    img = image.detach().cpu().float() if isinstance(image, torch.Tensor) else torch.as_tensor(np.asarray(image, dtype=np.float32))
    if img.dim() == 2:
        img = img.unsqueeze(-1)
    colour = img[..., :3]
    if srgb:
        colour = linear_to_srgb(colour)
    img = torch.cat([colour, img[..., 3:]], -1).clamp(0, 1)
    arr = (img.numpy() * 255 + 0.5).astype(np.uint8)
    arr = arr[..., 0] if arr.shape[-1] == 1 else arr
    with atomic_path(path) as tmp:
        Image.fromarray(arr).save(tmp, format="PNG")


def read_image(path, linear: bool = True) -> np.ndarray:
    """Any image as float32 (H, W, 3) colour or (H, W, 4) colour + alpha, at the file's own bit depth.

    ``.exr``: linear as stored (RGB, RGBA, or greyscale Y / YA expanded to RGB). Anything else Pillow opens
    (PNG, JPEG, TIFF, ...): 8- or 16-bit, greyscale, palette, with or without alpha, scaled to [0, 1] by its
    own bit depth (a 16-bit greyscale PNG keeps its 65536 levels); colour sRGB-decoded to linear when
    ``linear``, alpha as stored (straight, as image editors write it). A floating-point image (a 32-bit float
    greyscale TIFF) is linear as stored, like an EXR: neither decoded nor clipped. The pixels are turned as
    the file's EXIF orientation says (a phone's JPEG shows upright). An image too large for Pillow (a
    decompression bomb) is a :class:`DataError`.
    """
    if str(path).lower().endswith(".exr"):
        return _read_exr_colour(path)
    arr, is_float = _read_raster(_require_file(path))
    if linear and not is_float:
        from .conventions import srgb_to_linear

        rgb = srgb_to_linear(torch.from_numpy(np.ascontiguousarray(arr[..., :3]))).numpy()
        arr = np.concatenate([rgb, arr[..., 3:]], -1)
    return arr


def _read_exr_colour(path) -> np.ndarray:
    letters = {name.split(".")[-1] for name in read_exr_channels(path)}
    alpha = "A" if "A" in letters else ""
    if {"R", "G", "B"} <= letters:
        return read_exr(path, "RGB" + alpha)
    if "Y" in letters:
        grey = read_exr(path, "Y" + alpha)
        return np.concatenate([np.repeat(grey[..., :1], 3, -1), grey[..., 1:]], -1)
    raise DataError(f"{path}: EXR has channels {sorted(letters)}; expected R, G, B (and A) or Y (and A)")


def _read_raster(path: Path) -> tuple[np.ndarray, bool]:
    """((H, W, 3 or 4) float32, whether the file holds floating-point samples) from a file Pillow opens, at the
    file's bit depth (in [0, 1] unless floating-point), upright as its EXIF orientation says."""
    from PIL import Image, UnidentifiedImageError

    try:
        wide = _read_png_16bit_colour(path)
        with Image.open(path) as im:
            orientation = _exif_orientation(im)
            is_float = im.mode == "F"
            arr = wide if wide is not None else _pillow_pixels(im)
        return _upright(arr, orientation), is_float
    except Image.DecompressionBombError as e:
        raise DataError(f"{path}: too large to read ({str(e).split(',')[0]}); downscale it first") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, EOFError) as e:
        raise DataError(f"{path}: not a readable image ({e})") from e


def _exif_orientation(im) -> int:
    """The EXIF orientation tag (1: as stored; 2-8: mirrored and / or turned), 1 where there is none."""
    try:
        value = im.getexif().get(0x0112, 1)
    except Exception:  # a broken EXIF block: the pixels as stored
        return 1
    return value if isinstance(value, int) and 1 <= value <= 8 else 1


def _upright(arr: np.ndarray, orientation: int) -> np.ndarray:
    """``arr`` (H, W, C) as ``PIL.ImageOps.exif_transpose`` turns an image of that EXIF orientation."""
    turn = {1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
            5: lambda a: a.transpose(1, 0, 2), 6: lambda a: np.rot90(a, -1), 7: lambda a: np.rot90(a, 2).transpose(1, 0, 2),
            8: lambda a: np.rot90(a, 1)}[orientation]
    return np.ascontiguousarray(turn(arr))


def _pillow_pixels(im) -> np.ndarray:
    """Colour (+ alpha) of an opened Pillow image; 16- and 32-bit greyscale scaled by 65535."""
    if im.mode.startswith("I"):  # I;16 (16-bit greyscale PNG / TIFF), I (32-bit integer)
        grey = np.clip(np.asarray(im, dtype=np.float32) / 65535.0, 0.0, 1.0)
        return np.repeat(grey[..., None], 3, -1)
    if im.mode == "F":
        return np.repeat(np.asarray(im, dtype=np.float32)[..., None], 3, -1)
    has_alpha = "A" in im.mode or "a" in im.mode or "transparency" in im.info
    return np.asarray(im.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0


# Pillow decodes 16-bit colour PNGs to 8 bits (the high byte). The same stream decoded with a raw mode of the
# same pixel size gives the rest: "...;16L" unpacks the second byte of each (big-endian) sample, and an LA
# PNG's 4 bytes per pixel read as 8-bit RGBA are (L high, L low, A high, A low).
_PNG_16BIT_COLOUR = {"RGB;16B": ("RGB", "RGB;16L"), "RGBA;16B": ("RGBA", "RGBA;16L"), "LA;16B": ("RGBA", "RGBA")}


def _read_png_16bit_colour(path: Path) -> np.ndarray | None:
    """A 16-bit RGB / RGBA / LA PNG at full depth, as (H, W, 3 or 4) float32; None for any other image."""
    from PIL import Image

    with Image.open(path) as im:
        rawmode = _single_tile_rawmode(im)
        if im.format != "PNG" or rawmode not in _PNG_16BIT_COLOUR:
            return None
    mode, second = _PNG_16BIT_COLOUR[rawmode]
    try:
        if rawmode == "LA;16B":
            both = _decode_as(path, mode, second).astype(np.uint16)
            words = both[..., 0::2] * 256 + both[..., 1::2]  # (L, A)
            words = np.concatenate([np.repeat(words[..., :1], 3, -1), words[..., 1:]], -1)
        else:
            with Image.open(path) as im:
                high = np.asarray(im, dtype=np.uint16)
            words = high * 256 + _decode_as(path, mode, second)
    except (AttributeError, TypeError, KeyError) as e:  # a Pillow whose internals differ: 8 bits it is
        import warnings

        warnings.warn(f"{path}: read at 8 bits per channel (this Pillow cannot decode 16-bit colour: {e})")
        return None
    return words.astype(np.float32) / 65535.0


def _single_tile_rawmode(im) -> str | None:
    tiles = getattr(im, "tile", None) or []
    if len(tiles) != 1:
        return None
    args = tiles[0].args
    return args if isinstance(args, str) else (args[0] if args else None)


def _decode_as(path: Path, mode: str, rawmode: str) -> np.ndarray:
    """The PNG's pixel stream decoded into Pillow ``mode`` with ``rawmode`` (same bytes per pixel)."""
    from PIL import Image

    with Image.open(path) as im:
        im._mode = mode
        im.tile = [im.tile[0]._replace(args=rawmode)]
        return np.asarray(im, dtype=np.uint16)


def write_image(path, image) -> None:
    """Linear image to ``.exr`` (as is) or ``.png`` (sRGB preview) by extension."""
    suffix = Path(path).suffix.lower()
    if suffix == ".exr":
        write_exr(path, image)
    elif suffix == ".png":
        write_png(path, image)
    else:
        raise ValueError(f"{path}: unsupported output format {suffix!r}; use .exr or .png")


# ----------------------------------------------------------------------------- meshes

def load_mesh(path, device=None, with_uvs: bool = False):
    """Load an OBJ/PLY/GLB/... with trimesh into :class:`dibrpp.mesh.Meshes` (B = 1).

    Scenes are merged into one mesh. With ``with_uvs`` the file's per-vertex UVs are kept (an error
    if it has none).
    """
    import trimesh

    from .mesh import Meshes

    path = _require_file(path)
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as e:
        raise DataError(f"{path}: trimesh cannot read this mesh ({e})") from e
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not geoms:
            raise DataError(f"{path}: the file holds no triangle mesh")
        loaded = trimesh.util.concatenate(geoms)
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise DataError(f"{path}: the file holds no triangle mesh")
    verts = np.asarray(loaded.vertices, dtype=np.float32)
    if not np.isfinite(verts).all():
        raise DataError(f"{path}: {int((~np.isfinite(verts)).any(1).sum())} vertices are NaN/Inf; repair the mesh first")
    faces = torch.as_tensor(np.asarray(loaded.faces, dtype=np.int64))
    uvs = face_uvs = None
    if with_uvs:
        uv = getattr(loaded.visual, "uv", None)
        if uv is None or len(uv) != len(verts):
            raise DataError(f"{path}: the mesh has no per-vertex UV coordinates; drop --texture or unwrap it (e.g. xatlas)")
        uvs = torch.as_tensor(np.asarray(uv, dtype=np.float32))
        face_uvs = faces.clone()
    return Meshes(torch.as_tensor(verts), faces, uvs, face_uvs).to(device)


def save_mesh(path, verts, faces, uvs=None, texture_png: str | None = None) -> None:
    """Save one mesh (verts (V, 3), faces (F, 3), optional per-vertex uvs) atomically; format by extension."""
    import trimesh

    v = verts.detach().cpu().numpy() if isinstance(verts, torch.Tensor) else np.asarray(verts)
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    mesh = trimesh.Trimesh(v, f, process=False)
    if uvs is not None:
        uv = uvs.detach().cpu().numpy() if isinstance(uvs, torch.Tensor) else np.asarray(uvs)
        image = None
        if texture_png is not None:
            from PIL import Image

            image = Image.open(texture_png)
        mesh.visual = trimesh.visual.TextureVisuals(uv=uv, image=image)
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=Path(path).suffix.lstrip(".").lower())


def write_textured_obj(path, verts, faces, uvs, face_uvs, texture_file: str = "texture.png") -> None:
    """OBJ with per-corner UVs (``f v/vt``) plus an MTL of the same stem whose map_Kd is ``texture_file``
    (relative to the OBJ; the caller writes the image). Opens textured in Blender and MeshLab."""
    path = Path(path)
    arrays = [t.detach().cpu().numpy() if isinstance(t, torch.Tensor) else np.asarray(t) for t in (verts, faces, uvs, face_uvs)]
    verts, faces, uvs, face_uvs = arrays
    mtl = path.with_suffix(".mtl")
    with atomic_path(mtl) as tmp:
        tmp.write_text(f"newmtl albedo\nKd 1 1 1\nmap_Kd {texture_file}\n")
    lines = [f"mtllib {mtl.name}", "usemtl albedo"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uvs]
    lines += [f"f {a}/{d} {b}/{e} {c}/{f}" for (a, b, c), (d, e, f) in zip(faces + 1, face_uvs + 1)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
