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

import contextlib
import copy
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import conventions as conv
from .io import DataError, read_exr
from .sg import sg_eval, sg_integral, sg_lobe_values
from .sh import SH_COUNT, sh_basis, sh_eval, sh_irradiance

# Fraction of the env-map sampling distribution that is uniform over the sphere, so that every
# direction has a non-zero pdf (bilinear lookups reach dark texels next to bright ones, and MIS
# weights need pdf > 0 wherever the BRDF samples).
UNIFORM_FLOOR = 0.01
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)  # Rec. 709, linear RGB


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


class _Light:
    """Batch handling and the world -> light frame change shared by all lights."""

    _tensors: tuple[str, ...] = ()  # tensor attributes that .to() moves
    world_to_light: torch.Tensor | None

    @property
    def _data_batch(self) -> int:
        return getattr(self, self._tensors[0]).shape[0]

    @property
    def batch(self) -> int:
        rot = self.world_to_light
        return self._data_batch if rot is None else max(self._data_batch, rot.shape[0])

    @property
    def device(self) -> torch.device:
        return getattr(self, self._tensors[0]).device

    @property
    def dtype(self) -> torch.dtype:
        return getattr(self, self._tensors[0]).dtype

    def _set_frame(self, world_to_light) -> None:
        self.world_to_light = _as_rotation(world_to_light, self._data_batch, getattr(self, self._tensors[0]))

    def _copied(self):
        return copy.copy(self)

    def in_frame(self, world_to_light) -> "_Light":
        """A copy whose frame is ``world_to_light`` ((3, 3) or (B, 3, 3), replacing any previous one)."""
        out = self._copied()
        out._set_frame(world_to_light)
        return out

    def to(self, device=None, dtype=None) -> "_Light":
        out = self._copied()
        for name in self._tensors + ("world_to_light",):
            t = getattr(self, name)
            if t is not None:
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

@dataclass
class _SamplingTables:
    """Piecewise-constant texel distribution of an env map (float64, detached), B = image batch."""

    cdf: torch.Tensor  # (B, H*W + 1) over texels in row-major order
    row_cdf: torch.Tensor  # (B, H + 1) marginal over rows (= cdf[:, ::W])
    pdf: torch.Tensor  # (B, H*W) solid-angle pdf of each texel = p_texel / texel solid angle
    cos_edges: torch.Tensor  # (H + 1,) cos(theta) of the row edges


def _build_tables(image: torch.Tensor) -> _SamplingTables:
    b, h, w, _ = image.shape
    img = image.detach().double()
    lum = (img @ img.new_tensor(LUMINANCE_WEIGHTS)).clamp_min(0)  # (B, H, W); SH maps may ring negative
    omega = conv.equirect_solid_angles(h, w, device=img.device, dtype=torch.float64)  # (H, 1)
    weight = (lum * omega).reshape(b, -1)
    total = weight.sum(-1, keepdim=True)
    uniform = (omega / (4 * math.pi)).expand(h, w).reshape(1, -1)
    p = torch.where(total > 0, (1 - UNIFORM_FLOOR) * weight / total.clamp_min(1e-300) + UNIFORM_FLOOR * uniform, uniform)
    cdf = F.pad(torch.cumsum(p, -1), (1, 0))
    cdf = cdf / cdf[:, -1:]
    p = cdf[:, 1:] - cdf[:, :-1]  # exactly the steps of the cdf, so sample() and pdf() agree
    edges = torch.arange(h + 1, device=img.device, dtype=torch.float64) * (math.pi / h)
    return _SamplingTables(cdf=cdf, row_cdf=cdf[:, ::w].contiguous(), pdf=(p.reshape(b, h, w) / omega).reshape(b, -1),
                           cos_edges=torch.cos(edges))


def _pole_safe(d: torch.Tensor) -> torch.Tensor:
    """Block the direction gradient within ~1e-3 rad (float32) of the poles, where atan2/acos have
    infinite or NaN derivatives; the values are unchanged."""
    if not d.requires_grad:
        return d
    near = d[..., 0].square() + d[..., 1].square() < 16 * torch.finfo(d.dtype).eps
    return torch.where(near.unsqueeze(-1), d.detach(), d)


class EnvMap(_Light):
    """Equirectangular environment map (Blender mapping, see :mod:`dibrpp.conventions`).

    image: (B, H, W, 3) or (H, W, 3) linear HDR radiance, top row first.
    Radiance lookups are bilinear (wrap in u, clamp in v) and differentiable w.r.t. the texels and the
    directions. Importance sampling draws texels from a piecewise-constant distribution proportional
    to luminance x texel solid angle, mixed with a UNIFORM_FLOOR fraction of uniform sphere sampling;
    the tables are built on first use from the detached image and rebuilt if the image is modified
    in place. The C++ MC kernel (``dibrpp/csrc/mc_envmap.cpp``) repeats the look-up, sample and pdf.
    """

    _tensors = ("image",)

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

    def _sampling_tables(self) -> _SamplingTables:
        version = self.image._version
        if self._tables is None or self._tables[0] != version:
            self._tables = (version, _build_tables(self.image))
        return self._tables[1]

    def sample(self, uniforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Directions drawn from the map: uniforms (B, ..., 2) in [0, 1) -> (world dirs (B, ..., 3),
        solid-angle pdf (B, ...)). Not differentiable (the tables are detached).

        u0 picks a row from the marginal, u1 a column from that row's conditional; the remainders
        place the direction uniformly in solid angle inside the texel.
        """
        u, lead = self._flatten(uniforms, 2, "uniforms")
        beff, m = u.shape[:2]
        t = self._sampling_tables()
        h, w = self.height, self.width
        u = (u.reshape(1, beff * m, 2) if t.cdf.shape[0] == 1 else u).to(torch.float64)
        u0, u1 = u[..., 0].contiguous(), u[..., 1].contiguous()
        row = (torch.searchsorted(t.row_cdf, u0, right=True) - 1).clamp(0, h - 1)
        row_lo = t.row_cdf.gather(1, row)
        row_p = t.row_cdf.gather(1, row + 1) - row_lo
        target = row_lo + u1 * row_p  # the column search runs inside the row's span of the flat cdf
        idx = torch.searchsorted(t.cdf, target, right=True) - 1
        idx = torch.minimum(torch.maximum(idx, row * w), row * w + (w - 1))
        lo = t.cdf.gather(1, idx)
        frac_col = ((target - lo) / (t.cdf.gather(1, idx + 1) - lo)).clamp(0, 1)
        frac_row = ((u0 - row_lo) / row_p).clamp(0, 1)
        cos_theta = t.cos_edges[row] + frac_row * (t.cos_edges[row + 1] - t.cos_edges[row])  # uniform in solid angle
        uv = torch.stack([(idx - row * w + frac_col) / w, torch.acos(cos_theta.clamp(-1, 1)) / math.pi], -1)
        dirs = conv.equirect_uv_to_direction(uv).reshape(beff, m, 3).to(uniforms.dtype)
        pdf = t.pdf.gather(1, idx).reshape(beff, m).to(uniforms.dtype)
        return self._to_world(dirs).reshape(lead + (3,)), pdf.reshape(lead)

    def pdf(self, dirs: torch.Tensor) -> torch.Tensor:
        """Solid-angle pdf (B, ...) of :meth:`sample` at world directions (B, ..., 3); never 0."""
        t = self._sampling_tables()
        h, w = self.height, self.width

        def texel_pdf(d):
            uv = conv.direction_to_equirect_uv(d)
            col = (uv[..., 0] * w).long().clamp(0, w - 1)
            row = (uv[..., 1] * h).long().clamp(0, h - 1)
            return t.pdf.reshape(-1)[self._flat_base(d.shape[0], d.device) + row * w + col].to(d.dtype)

        with torch.no_grad():
            return self._apply(texel_pdf, dirs)


# ----------------------------------------------------------------------------- SG and SH lights

class SGLight(_Light):
    """Mixture of K spherical Gaussians: axis (B, K, 3) (normalised here), sharpness (B, K) > 0,
    amplitude (B, K, 3) RGB radiance at the lobe centre. Differentiable w.r.t. all three."""

    _tensors = ("axis", "sharpness", "amplitude")

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


class SHLight(_Light):
    """Order-2 real SH radiance, coeffs (B, 9, 3) (ordering in :mod:`dibrpp.sh`)."""

    _tensors = ("coeffs",)

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

def _texel_grid(height: int, width: int, like: torch.Tensor):
    """Texel-centre directions (H*W, 3) and exact solid angles (H*W,) of an equirect grid."""
    dirs = conv.equirect_directions(height, width, device=like.device, dtype=like.dtype)
    omega = conv.equirect_solid_angles(height, width, device=like.device, dtype=like.dtype).expand(height, width)
    return dirs.reshape(-1, 3), omega.reshape(-1)


def project_envmap_to_sh(env: EnvMap) -> SHLight:
    """Order-2 SH projection c_lm = sum_texels L Y_lm dw (exact texel solid angles), in the map's frame.

    Differentiable w.r.t. the map."""
    dirs, omega = _texel_grid(env.height, env.width, env.image)
    basis = sh_basis(dirs) * omega.unsqueeze(-1)  # (N, 9)
    coeffs = torch.einsum("nk,bnc->bkc", basis, env.image.reshape(env.image.shape[0], -1, 3))
    return SHLight(coeffs, env.world_to_light)


def _area_downsample(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Solid-angle-weighted area average of (B, H, W, 3) down to at most (height, width)."""
    b, h, w, _ = image.shape
    height, width = min(height, h), min(width, w)
    if (height, width) == (h, w):
        return image
    omega = conv.equirect_solid_angles(h, w, device=image.device, dtype=image.dtype).expand(h, w)[None, None]
    num = F.adaptive_avg_pool2d(image.permute(0, 3, 1, 2) * omega, (height, width))
    return (num / F.adaptive_avg_pool2d(omega, (height, width))).permute(0, 2, 3, 1)


def _fibonacci_sphere(n: int, rotation: torch.Tensor) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))  # golden angle
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1) @ rotation.T


def _random_rotation(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.linalg.det(q) > 0 else -q


def _initial_axes(dirs: torch.Tensor, target: torch.Tensor, num_lobes: int, sharpness: float, seed: int) -> torch.Tensor:
    """(B, K, 3): matching pursuit puts half of the lobes (rounded up) on the brightest texel of what
    the previous lobes leave unexplained (bright features such as a sun are found at once); the rest
    cover the sphere evenly (a Fibonacci set, randomly rotated by ``seed``) for the background."""
    b = target.shape[0]
    n_spread = num_lobes // 2
    luma = target.new_tensor(LUMINANCE_WEIGHTS)
    # Once nothing positive is left (a broad lobe on a sun over-subtracts the whole map), the pick would
    # repeat, and identical lobes get identical gradients and never separate: take spread axes instead.
    fallback = _fibonacci_sphere(num_lobes - n_spread, _random_rotation(seed + 1)).to(target)
    residual, axes = target, []
    for i in range(num_lobes - n_spread):
        score = residual @ luma
        pick = score.argmax(-1)  # (B,)
        exhausted = (score.gather(1, pick.view(b, 1)) <= 0).view(b, 1, 1)
        axis = torch.where(exhausted, fallback[i].view(1, 1, 3), dirs[pick].unsqueeze(1))  # (B, 1, 3)
        amp = residual.gather(1, pick.view(b, 1, 1).expand(b, 1, 3)).clamp_min(0) * ~exhausted
        residual = residual - amp * sg_lobe_values(dirs, axis.unsqueeze(1), sharpness)
        axes.append(axis)
    spread = _fibonacci_sphere(n_spread, _random_rotation(seed)).to(target).expand(b, n_spread, 3)
    return torch.cat(axes + [spread], 1)


def _nonnegative_least_squares(basis: torch.Tensor, weight: torch.Tensor, target: torch.Tensor,
                               amp: torch.Tensor | None = None, iters: int = 200) -> torch.Tensor:
    """argmin_{a >= 0} sum w (G a - L)^2 for a non-negative basis G (B, N, K), targets L (B, N, C),
    by multiplicative updates (Lee & Seung): they keep a >= 0 and never increase the error.
    ``amp`` warm-starts; it is floored slightly above 0 so that a lobe switched off can come back."""
    gram = basis.mT @ (basis * weight)  # (B, K, K)
    rhs = (basis.mT @ (target * weight)).clamp_min(0)  # (B, K, C); negative radiance cannot be met
    if amp is None:
        amp = torch.ones_like(rhs) * (rhs.sum(1, keepdim=True) / gram.sum((1, 2)).view(-1, 1, 1).clamp_min(1e-30))
    amp = torch.maximum(amp, 1e-6 * amp.amax((1, 2), keepdim=True).clamp_min(1e-30))
    for _ in range(iters):
        amp = amp * rhs / (gram @ amp).clamp_min(1e-30)
    return amp


@contextlib.contextmanager
def _single_cpu_thread(device: torch.device):
    """The SG fit is a loop of small tensor ops: on CPU, intra-op threads only add synchronisation
    (measured 30x slower with 2 threads on a busy 2-core machine), so run it on one."""
    threads = torch.get_num_threads()
    if device.type == "cpu":
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def fit_sg_to_envmap(env: EnvMap, num_lobes: int, iters: int = 300, lr: float = 0.05, seed: int = 0,
                     resolution: tuple[int, int] = (64, 128)) -> SGLight:
    """Fit ``num_lobes`` SG lobes per map to an env map, in the map's frame (same ``world_to_light``).

    Minimises the solid-angle-weighted relative L2 error sum w (G - L)^2 / sum w L^2 on the map
    area-averaged down to at most ``resolution``. Initial axes: :func:`_initial_axes`; initial
    sharpness from the lobe count. Adam (``lr``, cosine-decayed over ``iters`` steps) moves axes and
    log-sharpness (so > 0, capped so that a lobe is no narrower than a texel); at every step the
    amplitudes are the non-negative least-squares optimum for the current lobes (variable
    projection: amplitude is the easy, convex part of the problem). Deterministic for a seed; not
    differentiable w.r.t. the map. The result's ``fit_rel_error`` (B,) is the square root of the
    final error on the fitting grid.
    """
    if num_lobes < 1 or iters < 0:
        raise ValueError(f"need num_lobes >= 1 and iters >= 0, got {num_lobes}, {iters}")
    target = _area_downsample(env.image.detach(), *resolution)
    b, h, w, _ = target.shape
    dirs, omega = _texel_grid(h, w, target)
    target = target.reshape(b, -1, 3)
    weight = (omega / omega.sum()).view(1, -1, 1)
    norm = (weight * target.square()).sum((1, 2)).clamp_min(1e-30)

    max_lam = (h / math.pi) ** 2  # lobe std 1/sqrt(lam) >= one texel
    lam0 = min(max(num_lobes / 3.0, 1.0), max_lam)
    axis = _initial_axes(dirs, target, num_lobes, lam0, seed).clone().requires_grad_(True)
    log_lam = torch.full((b, num_lobes), math.log(lam0), dtype=target.dtype, device=target.device, requires_grad=True)
    dirs = dirs.unsqueeze(0)  # (1, N, 3)

    def lobes():  # (B, N, K)
        return sg_lobe_values(dirs, F.normalize(axis, dim=-1).unsqueeze(1), log_lam.exp().unsqueeze(1))

    def rel_sq_error(basis, amp):
        return (weight * (basis @ amp - target).square()).sum((1, 2)) / norm

    amp = None
    with torch.enable_grad(), _single_cpu_thread(target.device):
        opt = torch.optim.Adam([axis, log_lam], lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(iters, 1))
        for _ in range(iters):
            opt.zero_grad(set_to_none=True)
            basis = lobes()
            with torch.no_grad():
                amp = _nonnegative_least_squares(basis, weight, target, amp, iters=200 if amp is None else 10)
            rel_sq_error(basis, amp).sum().backward()
            opt.step()
            sched.step()
            with torch.no_grad():
                log_lam.clamp_(max=math.log(max_lam))
    with torch.no_grad():
        basis = lobes()
        amp = _nonnegative_least_squares(basis, weight, target, amp, iters=200 if amp is None else 50)
        light = SGLight(F.normalize(axis.detach(), dim=-1), log_lam.detach().exp(), amp, env.world_to_light)
        light.fit_rel_error = rel_sq_error(basis, amp).sqrt()
    return light
