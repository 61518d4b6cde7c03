"""Light objects the shaders take: :class:`EnvMap` (MC shading), :class:`SGLight` (closed-form SG
shading) and :class:`SHLight` (DIB-R's Lambertian baseline), and conversions between them.

Common rules:
- Every light has a batch dimension B; B = 1 broadcasts against any batch of queries, otherwise
  the first dimension of a query must equal B.
- A light may be expressed in a frame other than world (the encoder predicts light in a camera's
  frame): ``world_to_light`` is an optional (B, 3, 3) rotation (None = identity). Every query takes
  WORLD directions d and evaluates the light at ``world_to_light @ d``, so
  ``light.in_frame(R).eval(d) == light.eval(R @ d)`` for a light without a rotation.
- Query directions are normalised before use.
- Radiance is linear RGB; irradiance follows E(n) = ∫ L max(n.w, 0) dw (Lambertian: albedo / pi * E).
"""
from __future__ import annotations

import copy
import math

import torch
import torch.nn.functional as F

from . import conventions as conv
from .conventions import LUMINANCE_WEIGHTS
from .envmap_fit import fit_sg_lobes, sh_projection
from .envmap_sampling import UNIFORM_FLOOR, SamplingTables, build_sampling_tables, sample_directions, texel_pdf
from .io import DataError, read_exr
from .sg import sg_eval, sg_integral
from .sh import SH_COUNT, sh_eval, sh_irradiance

__all__ = ["LUMINANCE_WEIGHTS", "UNIFORM_FLOOR", "EnvMap", "Light", "SGLight", "SHLight", "SamplingTables",
           "fit_sg_to_envmap", "project_envmap_to_sh"]


def _check_finite(name: str, t: torch.Tensor) -> None:
    bad = ~torch.isfinite(t)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} non-finite values (NaN/Inf)")


def _check_shape(name: str, t: torch.Tensor, shape: tuple) -> None:
    """shape may hold None for 'any size'."""
    if t.dim() != len(shape) or any(s is not None and s != n for s, n in zip(shape, t.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {tuple(t.shape)}")


def _as_rotation(rot, batch: int, like: torch.Tensor) -> torch.Tensor | None:
    """Validate a world-to-light rotation (3, 3) or (B, 3, 3) -> (B, 3, 3) on ``like``'s device/dtype."""
    if rot is None:
        return None
    rot = torch.as_tensor(rot).to(device=like.device, dtype=like.dtype)
    if rot.dim() == 2:
        rot = rot.unsqueeze(0)
    _check_shape("world_to_light", rot, (None, 3, 3))
    _check_finite("world_to_light", rot)
    if rot.shape[0] != batch and 1 not in (rot.shape[0], batch):
        raise ValueError(f"world_to_light has batch {rot.shape[0]}, the light has batch {batch}")
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    err = float((rot @ rot.mT - eye).abs().max())
    if err > 1e-3 or bool((torch.linalg.det(rot) < 0).any()):
        raise ValueError(f"world_to_light must be proper rotations (R R^T = I, det R = 1); |R R^T - I| = {err:.2g}")
    return rot


class Light:
    """Base of the light objects: batch handling, the world -> light frame change, and the protocol that
    shaders rely on.

    - ``eval(dirs)``: radiance (B, ..., 3) at world directions (B, ..., 3); ``batch``, ``device``,
      ``dtype``; ``world_to_light`` ((B, 3, 3) or None); ``in_frame``, ``to``, ``to_envmap``.
    - ``tensors()``: the tensors that define the light, by attribute name: what ``to`` moves and what
      gradients reach. ``with_tensors(**new)``: a shallow copy with some of them replaced, which is how an
      autograd function (the MC path replay) rebuilds the light around its own inputs.
    """

    _fields: tuple[str, ...] = ()  # the light's tensor attributes; the first sets batch, device and dtype
    world_to_light: torch.Tensor | None

    def tensors(self) -> dict[str, torch.Tensor]:
        """name -> tensor: the light's own tensors in a fixed order, then ``world_to_light`` if it is set."""
        names = self._fields + ("world_to_light",)
        return {name: getattr(self, name) for name in names if getattr(self, name) is not None}

    def with_tensors(self, **tensors: torch.Tensor) -> "Light":
        """A shallow copy with the named tensors (names of :meth:`tensors`) replaced, unchecked: the new
        tensors must have the old ones' shapes (typically the same values, another autograd identity)."""
        unknown = set(tensors) - set(self._fields + ("world_to_light",))
        if unknown:
            raise ValueError(f"{type(self).__name__} has no tensors {sorted(unknown)}; it has {self._fields}")
        out = copy.copy(self)
        for name, t in tensors.items():
            setattr(out, name, t)
        return out

    @property
    def _data_batch(self) -> int:
        return getattr(self, self._fields[0]).shape[0]

    @property
    def batch(self) -> int:
        rot = self.world_to_light
        return self._data_batch if rot is None else max(self._data_batch, rot.shape[0])

    @property
    def device(self) -> torch.device:
        return getattr(self, self._fields[0]).device

    @property
    def dtype(self) -> torch.dtype:
        return getattr(self, self._fields[0]).dtype

    def _set_frame(self, world_to_light) -> None:
        self.world_to_light = _as_rotation(world_to_light, self._data_batch, getattr(self, self._fields[0]))

    def _copied(self):
        return copy.copy(self)

    def in_frame(self, world_to_light) -> "Light":
        """A copy whose frame is ``world_to_light`` ((3, 3) or (B, 3, 3), replacing any previous one)."""
        out = self._copied()
        out._set_frame(world_to_light)
        return out

    def to(self, device=None, dtype=None) -> "Light":
        out = self._copied()
        for name, t in self.tensors().items():
            setattr(out, name, t.to(device=device, dtype=dtype))
        return out

    def _flatten(self, x: torch.Tensor, last: int, name: str):
        """(b, ..., last) -> ((Beff, M, last) broadcast to the light's batch, leading output shape)."""
        if not isinstance(x, torch.Tensor) or x.dim() < 2 or x.shape[-1] != last:
            shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ValueError(f"{name} must be a tensor of shape (B, ..., {last}), got {shape}")
        b = x.shape[0]
        if b != self.batch and 1 not in (b, self.batch):
            raise ValueError(f"{name} has batch {b}, the light has batch {self.batch} (use 1 to broadcast)")
        beff = max(b, self.batch)
        m = math.prod(x.shape[1:-1])
        return x.reshape(b, m, last).expand(beff, m, last), (beff,) + tuple(x.shape[1:-1])

    def _to_light(self, d: torch.Tensor) -> torch.Tensor:
        rot = self.world_to_light
        return d if rot is None else d @ rot.mT.to(d.dtype)  # row vectors: (R d)^T = d^T R^T

    def _to_world(self, d: torch.Tensor) -> torch.Tensor:
        rot = self.world_to_light
        return d if rot is None else d @ rot.to(d.dtype)

    def _apply(self, fn, dirs: torch.Tensor, name: str = "dirs") -> torch.Tensor:
        """fn(light-frame unit directions (Beff, M, 3)) -> (Beff, M, ...), reshaped to dirs' shape."""
        d, lead = self._flatten(dirs, 3, name)
        out = fn(self._to_light(F.normalize(d, dim=-1, eps=1e-12)))
        return out.reshape(lead + tuple(out.shape[2:]))

    def eval(self, dirs: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def to_envmap(self, height: int, width: int) -> "EnvMap":
        """The light as an equirectangular map in the WORLD frame (radiance at texel centres)."""
        dirs = conv.equirect_directions(height, width, device=self.device, dtype=self.dtype).unsqueeze(0)
        return EnvMap(self.eval(dirs))


# ----------------------------------------------------------------------------- environment map

def _pole_safe(d: torch.Tensor) -> torch.Tensor:
    """Block the direction gradient within ~1e-3 rad (float32) of the poles, where atan2/acos have
    infinite or NaN derivatives; the values are unchanged."""
    if not d.requires_grad:
        return d
    near = d[..., 0].square() + d[..., 1].square() < 16 * torch.finfo(d.dtype).eps
    return torch.where(near.unsqueeze(-1), d.detach(), d)


class EnvMap(Light):
    """Equirectangular environment map (Blender mapping, see :mod:`dibrpp.conventions`).

    image: (B, H, W, 3) or (H, W, 3) linear HDR radiance, top row first.
    Radiance lookups are bilinear (wrap in u, clamp in v) and differentiable w.r.t. the texels and the
    directions. Importance sampling (:mod:`dibrpp.envmap_sampling`) draws texels in proportion to
    luminance x texel solid angle, with a UNIFORM_FLOOR fraction of uniform sphere sampling; its tables
    are built on first use from the detached image and rebuilt if the image is modified in place. The C++
    MC kernel (``dibrpp/csrc/mc_envmap.cpp``) repeats the look-up, sample and pdf.
    """

    _fields = ("image",)

    def __init__(self, image: torch.Tensor, world_to_light: torch.Tensor | None = None):
        image = torch.as_tensor(image)
        if image.dim() == 3:
            image = image.unsqueeze(0)
        _check_shape("environment map", image, (None, None, None, 3))
        if not image.is_floating_point() or 0 in image.shape:
            raise ValueError(f"environment map must be a non-empty float tensor, got {image.dtype} {tuple(image.shape)}")
        _check_finite("environment map", image)
        self.image = image
        self._set_frame(world_to_light)
        self._tables = None

    @classmethod
    def from_exr(cls, path, world_to_light=None) -> "EnvMap":
        """Read an RGB EXR (B = 1). DataError for non-finite, negative or all-black maps."""
        img = read_exr(path, "RGB")
        if (img < 0).any():
            raise DataError(f"{path}: {int((img < 0).sum())} negative values (min {img.min():.3g}); radiance cannot be "
                            "negative, clamp the map at 0")
        if not (img > 0).any():
            raise DataError(f"{path}: the environment map is black everywhere; it would light nothing")
        return cls(torch.from_numpy(img), world_to_light)

    def _copied(self):
        out = copy.copy(self)
        out._tables = None
        return out

    def with_tensors(self, **tensors: torch.Tensor) -> "EnvMap":
        out = super().with_tensors(**tensors)
        image = tensors.get("image")
        if image is not None and not _same_data(image, self.image):
            out._tables = None  # the cached tables follow the image's values: kept only for a view of the same data
        return out

    @property
    def height(self) -> int:
        return self.image.shape[1]

    @property
    def width(self) -> int:
        return self.image.shape[2]

    # ------------------------------------------------------------------ radiance

    def _flat_base(self, beff: int, device) -> torch.Tensor | int:
        """Offset of each query batch into the flattened (B*H*W) texels (0 when B = 1 broadcasts)."""
        if self.image.shape[0] == 1:
            return 0
        return (torch.arange(beff, device=device) * (self.height * self.width)).view(-1, 1)

    def _bilinear(self, d: torch.Tensor) -> torch.Tensor:
        h, w = self.height, self.width
        uv = conv.direction_to_equirect_uv(_pole_safe(d))
        x = uv[..., 0] * w - 0.5  # texel centres at half-integers
        y = uv[..., 1] * h - 0.5
        x0f, y0f = torch.floor(x), torch.floor(y)
        fx, fy = (x - x0f).unsqueeze(-1), (y - y0f).unsqueeze(-1)
        x0 = x0f.long() % w  # wrap around in u
        x1 = (x0 + 1) % w
        y0 = y0f.long()
        base = self._flat_base(d.shape[0], d.device)
        r0 = base + y0.clamp(0, h - 1) * w  # clamp in v
        r1 = base + (y0 + 1).clamp(0, h - 1) * w
        texels = self.image.reshape(-1, 3)
        return ((texels[r0 + x0] * (1 - fx) + texels[r0 + x1] * fx) * (1 - fy)
                + (texels[r1 + x0] * (1 - fx) + texels[r1 + x1] * fx) * fy)

    def lookup(self, dirs: torch.Tensor) -> torch.Tensor:
        """Bilinear radiance (B, ..., 3) at world directions (B, ..., 3)."""
        return self._apply(self._bilinear, dirs)

    eval = lookup

    def to_image(self, height: int, width: int) -> torch.Tensor:
        """(B, height, width, 3) equirect image in the WORLD frame, looked up at texel centres."""
        return self.to_envmap(height, width).image

    # ------------------------------------------------------------------ importance sampling

    def sampling_tables(self) -> SamplingTables:
        """The importance-sampling tables of the map (cached; rebuilt when the image changes in place)."""
        version = self.image._version
        if self._tables is None or self._tables[0] != version:
            self._tables = (version, build_sampling_tables(self.image))
        return self._tables[1]

    def sample(self, uniforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Directions drawn from the map: uniforms (B, ..., 2) in [0, 1) -> (world dirs (B, ..., 3),
        solid-angle pdf (B, ...)). Not differentiable (the tables are detached). See
        :func:`dibrpp.envmap_sampling.sample_directions`."""
        u, lead = self._flatten(uniforms, 2, "uniforms")
        beff, m = u.shape[:2]
        t = self.sampling_tables()
        u = (u.reshape(1, beff * m, 2) if t.cdf.shape[0] == 1 else u).to(torch.float64)
        dirs, pdf = sample_directions(t, u)
        dirs = dirs.reshape(beff, m, 3).to(uniforms.dtype)
        pdf = pdf.reshape(beff, m).to(uniforms.dtype)
        return self._to_world(dirs).reshape(lead + (3,)), pdf.reshape(lead)

    def pdf(self, dirs: torch.Tensor) -> torch.Tensor:
        """Solid-angle pdf (B, ...) of :meth:`sample` at world directions (B, ..., 3); never 0."""
        t = self.sampling_tables()
        with torch.no_grad():
            return self._apply(lambda d: texel_pdf(t, d, self._flat_base(d.shape[0], d.device)), dirs)


def _same_data(a: torch.Tensor, b: torch.Tensor) -> bool:
    return (a.data_ptr() == b.data_ptr() and a.shape == b.shape and a.stride() == b.stride()
            and a.dtype == b.dtype and a.device == b.device)


# ----------------------------------------------------------------------------- SG and SH lights

class SGLight(Light):
    """Mixture of K spherical Gaussians: axis (B, K, 3) (normalised here), sharpness (B, K) > 0,
    amplitude (B, K, 3) RGB radiance at the lobe centre. Differentiable w.r.t. all three."""

    _fields = ("axis", "sharpness", "amplitude")

    def __init__(self, axis: torch.Tensor, sharpness: torch.Tensor, amplitude: torch.Tensor, world_to_light=None):
        _check_shape("SG axis", axis, (None, None, 3))
        b, k = axis.shape[:2]
        _check_shape("SG sharpness", sharpness, (b, k))
        _check_shape("SG amplitude", amplitude, (b, k, 3))
        for name, t in (("SG axis", axis), ("SG sharpness", sharpness), ("SG amplitude", amplitude)):
            _check_finite(name, t)
        if bool((sharpness <= 0).any()):
            raise ValueError(f"SG sharpness must be > 0, got min {float(sharpness.min()):.3g}")
        if bool((axis.norm(dim=-1) < 1e-12).any()):
            raise ValueError("SG axes must be non-zero vectors")
        self.axis = F.normalize(axis, dim=-1)
        self.sharpness = sharpness
        self.amplitude = amplitude
        self._set_frame(world_to_light)

    @property
    def num_lobes(self) -> int:
        return self.axis.shape[1]

    def world_axis(self) -> torch.Tensor:
        """Lobe axes (B, K, 3) in the world frame (R^T mu)."""
        return self._to_world(self.axis)

    def eval(self, dirs: torch.Tensor) -> torch.Tensor:
        """Radiance (B, ..., 3) at world directions (B, ..., 3)."""
        return self._apply(lambda d: sg_eval(d, self.axis.unsqueeze(1), self.sharpness.unsqueeze(1),
                                             self.amplitude.unsqueeze(1)), dirs)

    def integral(self) -> torch.Tensor:
        """∫ L dw over the sphere, (B, 3)."""
        return sg_integral(self.sharpness, self.amplitude).sum(-2)


class SHLight(Light):
    """Order-2 real SH radiance, coeffs (B, 9, 3) (ordering in :mod:`dibrpp.sh`)."""

    _fields = ("coeffs",)

    def __init__(self, coeffs: torch.Tensor, world_to_light=None):
        _check_shape("SH coefficients", coeffs, (None, SH_COUNT, 3))
        _check_finite("SH coefficients", coeffs)
        self.coeffs = coeffs
        self._set_frame(world_to_light)

    def eval(self, dirs: torch.Tensor) -> torch.Tensor:
        """Radiance (B, ..., 3) at world directions (B, ..., 3) (may be negative: SH rings)."""
        return self._apply(lambda d: sh_eval(self.coeffs.unsqueeze(1), d), dirs)

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """E(n) = ∫ L max(n.w, 0) dw, (B, ..., 3) at world normals (B, ..., 3)."""
        return self._apply(lambda n: sh_irradiance(self.coeffs.unsqueeze(1), n), normals, "normals")


# ----------------------------------------------------------------------------- conversions

def project_envmap_to_sh(env: EnvMap) -> SHLight:
    """Order-2 SH projection c_lm = sum_texels L Y_lm dw (exact texel solid angles), in the map's frame.

    Differentiable w.r.t. the map."""
    return SHLight(sh_projection(env.image), env.world_to_light)


def fit_sg_to_envmap(env: EnvMap, num_lobes: int, iters: int = 300, lr: float = 0.05, seed: int = 0,
                     resolution: tuple[int, int] = (64, 128)) -> SGLight:
    """Fit ``num_lobes`` SG lobes per map to an env map, in the map's frame (same ``world_to_light``).

    Minimises the solid-angle-weighted relative L2 error of the lobes on the map area-averaged down to at
    most ``resolution`` (:func:`dibrpp.envmap_fit.fit_sg_lobes`: matching-pursuit initial axes, Adam on axes
    and log-sharpness, non-negative least-squares amplitudes). Deterministic for a seed; not
    differentiable w.r.t. the map. The result's ``fit_rel_error`` (B,) is the square root of the final
    error on the fitting grid.
    """
    axis, sharpness, amplitude, rel_error = fit_sg_lobes(env.image, num_lobes, iters, lr, seed, resolution)
    with torch.no_grad():
        light = SGLight(axis, sharpness, amplitude, env.world_to_light)
    light.fit_rel_error = rel_error
    return light
