"""Real spherical harmonics up to l = 2 (9 coefficients), the DIB-R lighting baseline.

Ordering and constants are Ramamoorthi & Hanrahan's ("An Efficient Representation for Irradiance
Environment Maps", 2001): Y00; Y1-1 (y), Y10 (z), Y11 (x); Y2-2 (xy), Y2-1 (yz), Y20 (3z^2 - 1),
Y21 (xz), Y22 (x^2 - y^2).

Irradiance convention (the same as the SG and MC diffuse terms): E(n) = ∫ L(w) max(n.w, 0) dw, so a
Lambertian surface reflects radiance albedo / pi * E(n). Under a constant unit sky E = pi.
"""
from __future__ import annotations

import math

import torch

SH_COUNT = 9
_C0 = 0.5 * math.sqrt(1 / math.pi)  # 0.282095
_C1 = math.sqrt(3 / (4 * math.pi))  # 0.488603
_C2 = 0.5 * math.sqrt(15 / math.pi)  # 1.092548
_C3 = 0.25 * math.sqrt(5 / math.pi)  # 0.315392
_C4 = 0.25 * math.sqrt(15 / math.pi)  # 0.546274
# Clamped-cosine convolution per band (l = 0, 1, 2): pi, 2 pi / 3, pi / 4.
IRRADIANCE_BAND_FACTORS = (math.pi,) + (2 * math.pi / 3,) * 3 + (math.pi / 4,) * 5


def _check(coeffs: torch.Tensor, dirs: torch.Tensor) -> None:
    if dirs.dim() == 0 or dirs.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {tuple(dirs.shape)}")
    if coeffs.dim() < 2 or coeffs.shape[-2] != SH_COUNT:
        raise ValueError(f"SH coefficients must have shape (..., 9, C), got {tuple(coeffs.shape)}")


def sh_basis(dirs: torch.Tensor) -> torch.Tensor:
    """The 9 real SH basis functions at unit directions (..., 3) -> (..., 9)."""
    if dirs.dim() == 0 or dirs.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {tuple(dirs.shape)}")
    x, y, z = dirs.unbind(-1)
    return torch.stack([
        torch.full_like(x, _C0),
        _C1 * y, _C1 * z, _C1 * x,
        _C2 * x * y, _C2 * y * z, _C3 * (3 * z * z - 1), _C2 * x * z, _C4 * (x * x - y * y),
    ], -1)


def _weighted_sum(coeffs: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    # (..., 1, 9) @ (..., 9, C): matmul broadcasts the leading dimensions of both.
    return (basis.unsqueeze(-2) @ coeffs).squeeze(-2)


def sh_eval(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Radiance sum_lm L_lm Y_lm(w): coeffs (..., 9, C), dirs (..., 3) -> (..., C) (leading dims broadcast)."""
    _check(coeffs, dirs)
    return _weighted_sum(coeffs, sh_basis(dirs).to(coeffs.dtype))


def sh_irradiance(coeffs: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Irradiance E(n) = sum_lm A_l L_lm Y_lm(n), A_l = pi, 2 pi / 3, pi / 4 -> (..., C).

    coeffs (..., 9, C) are the radiance coefficients; normals (..., 3) unit; leading dims broadcast.
    Outgoing Lambertian radiance is albedo / pi * E (module docstring).
    """
    _check(coeffs, normals)
    bands = torch.tensor(IRRADIANCE_BAND_FACTORS, dtype=coeffs.dtype, device=coeffs.device)
    return _weighted_sum(coeffs, sh_basis(normals).to(coeffs.dtype) * bands)
