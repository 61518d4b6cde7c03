"""Spherical Gaussian (SG) primitives: G(v; mu, lam, a) = a * exp(lam * (mu . v - 1)).

Shapes follow one rule everywhere: a lobe is an axis (..., 3) (unit length), a sharpness (...) and
an amplitude (..., C) with a trailing channel dimension; the leading dimensions of all arguments
broadcast against each other (torch rules), and 0-dim tensors or Python floats broadcast as scalars.

These are hot-path functions of the shaders, so they check shapes (free) but not values (a value
check would synchronise the GPU); the light objects in :mod:`dibrpp.lights` validate values.
"""
from __future__ import annotations

import math

import torch

from .brdf import MIN_ALPHA
from .jit import CompiledOrEager

# Clamped cosine max(n . w, 0) ~ one SG with axis n (Wang et al. 2009, used by DIB-R++).
COSINE_SG_SHARPNESS = 2.133
COSINE_SG_AMPLITUDE = 1.17
# Warping (eq. 7) divides by n.v: floor it so grazing views give a very sharp, not infinite, lobe.
NDV_EPS = 1e-4


def _check_last(name: str, t: torch.Tensor, size: int) -> None:
    if t.dim() == 0 or t.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got {tuple(t.shape)}")


def sg_lobe_values(dirs: torch.Tensor, axis: torch.Tensor, sharpness: torch.Tensor) -> torch.Tensor:
    """Unit-amplitude lobe values exp(lam (mu . v - 1)) -> (..., K); shapes as in :func:`sg_eval`."""
    _check_last("dirs", dirs, 3)
    _check_last("axis", axis, 3)
    cos = torch.einsum("...d,...kd->...k", dirs, axis)  # einsum: broadcasts without materialising (..., K, 3)
    return torch.exp(sharpness * (cos - 1))


def sg_eval(dirs: torch.Tensor, axis: torch.Tensor, sharpness: torch.Tensor, amplitude: torch.Tensor) -> torch.Tensor:
    """Sum of K SG lobes at unit directions -> (..., C).

    dirs (..., 3); axis (..., K, 3); sharpness (..., K); amplitude (..., K, C). The lobe tensors'
    leading ``...`` broadcast with each other and with the leading ``...`` of ``dirs`` (a direction
    is compared with all K lobes of its broadcast partner), e.g. dirs (B, N, 3) with axis
    (B, 1, K, 3), sharpness (B, 1, K), amplitude (B, 1, K, C) gives (B, N, C).
    """
    if amplitude.dim() < 2:
        raise ValueError(f"amplitude must have shape (..., K, C), got {tuple(amplitude.shape)}")
    return torch.einsum("...k,...kc->...c", sg_lobe_values(dirs, axis, sharpness), amplitude)


def sg_integral(sharpness: torch.Tensor, amplitude: torch.Tensor | None = None) -> torch.Tensor:
    """Integral over the sphere, 2 pi a / lam (1 - exp(-2 lam)).

    sharpness (...) -> (...) for unit amplitude, or with amplitude (..., C) -> (..., C).
    expm1 keeps it exact for small lam (the limit lam -> 0 is 4 pi a).
    """
    sharpness = torch.as_tensor(sharpness)
    unit = -2 * math.pi * torch.expm1(-2 * sharpness) / sharpness
    return unit if amplitude is None else amplitude * unit.unsqueeze(-1)


def _one_minus_exp_over_d(d: torch.Tensor) -> torch.Tensor:
    """(1 - exp(-2d)) / d for d >= 0, with its series below 1e-3 (smooth value and gradient at d = 0)."""
    small = d < 1e-3
    safe = torch.where(small, torch.ones_like(d), d)
    series = 2 + d * (-2 + d * (4.0 / 3 - d * (2.0 / 3)))
    return torch.where(small, series, -torch.expm1(-2 * safe) / safe)


def sg_product_integral(cos: torch.Tensor, sharpness1: torch.Tensor, sharpness2: torch.Tensor,
                        one_minus_cos: torch.Tensor | None = None) -> torch.Tensor:
    """∫ G1 G2 dw for unit amplitudes, from the cosine between the unit axes (everything broadcasts).

    2 pi exp(d - lam1 - lam2) (1 - exp(-2d)) / d, d = |lam1 mu1 + lam2 mu2|, in a stable form (finite
    values and gradients for lam up to ~1e6 in float32):
      d^2 = (lam1 - lam2)^2 + 2 lam1 lam2 (1 + cos)      (a sum of non-negative terms),
      d - lam1 - lam2 = -2 lam1 lam2 (1 - cos) / (d + lam1 + lam2)   (no cancellation).
    Taking the cosine (a dot product, or a matrix product for many lobes) keeps shading cheap; pass
    ``one_minus_cos`` (|mu1 - mu2|^2 / 2) when both lobes can be very sharp, as float32 ``1 - cos`` loses
    the digits that matter there.
    """
    cos = cos.clamp(-1, 1)
    one_minus_cos = 1 - cos if one_minus_cos is None else one_minus_cos
    lam1, lam2 = sharpness1, sharpness2
    d2 = (lam1 - lam2).square() + 2 * lam1 * lam2 * (1 + cos)
    # d = 0 only for equal sharpness on opposite axes; flooring d^2 keeps sqrt's gradient finite there.
    d = torch.sqrt(d2.clamp_min(1e-12))
    exponent = -2 * lam1 * lam2 * one_minus_cos / (d + lam1 + lam2)
    return 2 * math.pi * torch.exp(exponent) * _one_minus_exp_over_d(d)


sg_product_integral_compiled = CompiledOrEager(sg_product_integral)


def sg_inner_product(axis1, sharpness1, amplitude1, axis2, sharpness2, amplitude2) -> torch.Tensor:
    """Exact integral of the product of two SG lobes, ∫ G1 G2 dw -> (..., C).

    Axes (..., 3) (unit), sharpness (...), amplitudes (..., C); everything broadcasts (module
    docstring). See :func:`sg_product_integral` for the stable form.
    """
    axis1, axis2 = torch.as_tensor(axis1), torch.as_tensor(axis2)
    _check_last("axis1", axis1, 3)
    _check_last("axis2", axis2, 3)
    lam1, lam2 = torch.as_tensor(sharpness1).to(axis1), torch.as_tensor(sharpness2).to(axis1)
    one_plus_cos = 0.5 * (axis1 + axis2).square().sum(-1)
    one_minus_cos = 0.5 * (axis1 - axis2).square().sum(-1)
    scale = sg_product_integral(one_plus_cos - 1, lam1, lam2, one_minus_cos)
    return amplitude1 * amplitude2 * scale.unsqueeze(-1)


def ndf_sg(alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """GGX NDF as an SG around the normal (eq. 6): (sharpness 2 / alpha^2, amplitude 1 / (pi alpha^2)).

    alpha is clamped to >= :data:`dibrpp.brdf.MIN_ALPHA` (1e-3, a mirror) so that lam <= 2e6 and the
    amplitude stay finite in float32. ∫ G dw = 2 pi a / lam = 1 (up to exp(-2 lam)), like ∫ D (n.h) dw.
    """
    a2 = torch.as_tensor(alpha).clamp_min(MIN_ALPHA).square()
    return 2 / a2, 1 / (math.pi * a2)


def warp_ndf_sg(normal: torch.Tensor, view: torch.Tensor, alpha: torch.Tensor):
    """NDF SG warped into light directions (eq. 7) -> (axis (..., 3), sharpness (...), amplitude (...)).

    axis = reflect(view about normal) = 2 (n.v) n - v; sharpness = lam / (4 max(n.v, NDV_EPS));
    amplitude unchanged. normal, view: unit vectors (..., 3); alpha (...) GGX alpha.
    """
    _check_last("normal", normal, 3)
    _check_last("view", view, 3)
    lam, amp = ndf_sg(alpha)
    n_dot_v = (normal * view).sum(-1)
    axis = torch.nn.functional.normalize(2 * n_dot_v.unsqueeze(-1) * normal - view, dim=-1, eps=1e-12)
    sharpness = lam / (4 * n_dot_v.clamp_min(NDV_EPS))
    return axis, sharpness, amp.expand_as(sharpness)
