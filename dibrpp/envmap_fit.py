"""An equirectangular environment map in the other lights' bases, as plain functions of tensors:
its order-2 SH projection (:func:`sh_projection`) and a fitted mixture of K spherical Gaussians
(:func:`fit_sg_lobes`). :func:`dibrpp.lights.project_envmap_to_sh` and :func:`dibrpp.lights.fit_sg_to_envmap`
wrap them into light objects; everything here stays in the map's own frame.
"""
from __future__ import annotations

import contextlib
import math

import torch
import torch.nn.functional as F

from . import conventions as conv
from .sg import sg_lobe_values
from .sh import sh_basis


def _texel_grid(height: int, width: int, like: torch.Tensor):
    """Texel-centre directions (H*W, 3) and exact solid angles (H*W,) of an equirect grid."""
    dirs = conv.equirect_directions(height, width, device=like.device, dtype=like.dtype)
    omega = conv.equirect_solid_angles(height, width, device=like.device, dtype=like.dtype).expand(height, width)
    return dirs.reshape(-1, 3), omega.reshape(-1)


def sh_projection(image: torch.Tensor) -> torch.Tensor:
    """Order-2 SH coefficients (B, 9, 3) of a (B, H, W, 3) map: c_lm = sum_texels L Y_lm dw (exact texel
    solid angles). Differentiable w.r.t. the map."""
    dirs, omega = _texel_grid(image.shape[1], image.shape[2], image)
    basis = sh_basis(dirs) * omega.unsqueeze(-1)  # (N, 9)
    return torch.einsum("nk,bnc->bkc", basis, image.reshape(image.shape[0], -1, 3))


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
    luma = target.new_tensor(conv.LUMINANCE_WEIGHTS)
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


def fit_sg_lobes(image: torch.Tensor, num_lobes: int, iters: int = 300, lr: float = 0.05, seed: int = 0,
                 resolution: tuple[int, int] = (64, 128)):
    """Fit ``num_lobes`` SG lobes per map to a (B, H, W, 3) map: (axis (B, K, 3) unit, sharpness (B, K),
    amplitude (B, K, 3), relative error (B,)), all detached.

    Minimises the solid-angle-weighted relative L2 error sum w (G - L)^2 / sum w L^2 on the map
    area-averaged down to at most ``resolution``. Initial axes: :func:`_initial_axes`; initial
    sharpness from the lobe count. Adam (``lr``, cosine-decayed over ``iters`` steps) moves axes and
    log-sharpness (so > 0, capped so that a lobe is no narrower than a texel); at every step the
    amplitudes are the non-negative least-squares optimum for the current lobes (variable
    projection: amplitude is the easy, convex part of the problem). Deterministic for a seed; not
    differentiable w.r.t. the map. The relative error is the square root of the final error on the
    fitting grid.
    """
    if num_lobes < 1 or iters < 0:
        raise ValueError(f"need num_lobes >= 1 and iters >= 0, got {num_lobes}, {iters}")
    target = _area_downsample(image.detach(), *resolution)
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
        return F.normalize(axis.detach(), dim=-1), log_lam.detach().exp(), amp, rel_sq_error(basis, amp).sqrt()
