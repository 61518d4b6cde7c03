"""Importance sampling of an equirectangular environment map, as plain functions of tensors.

:meth:`dibrpp.lights.EnvMap.sample` and :meth:`~dibrpp.lights.EnvMap.pdf` run on these. Texels are drawn
from a piecewise-constant distribution proportional to luminance x texel solid angle, mixed with a
UNIFORM_FLOOR fraction of uniform sphere sampling; inside a texel the direction is uniform in solid angle.
Directions here are in the map's own frame. The C++ MC kernel (``dibrpp/csrc/mc_envmap.cpp``) repeats the
sample and the pdf, and reads :class:`SamplingTables` as they are.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import conventions as conv

# Fraction of the env-map sampling distribution that is uniform over the sphere, so that every
# direction has a non-zero pdf (bilinear lookups reach dark texels next to bright ones, and MIS
# weights need pdf > 0 wherever the BRDF samples).
UNIFORM_FLOOR = 0.01


@dataclass
class SamplingTables:
    """Piecewise-constant texel distribution of an env map (float64, detached), B = image batch."""

    cdf: torch.Tensor  # (B, H*W + 1) over texels in row-major order
    row_cdf: torch.Tensor  # (B, H + 1) marginal over rows (= cdf[:, ::W])
    pdf: torch.Tensor  # (B, H*W) solid-angle pdf of each texel = p_texel / texel solid angle
    cos_edges: torch.Tensor  # (H + 1,) cos(theta) of the row edges

    @property
    def height(self) -> int:
        return self.cos_edges.shape[0] - 1

    @property
    def width(self) -> int:
        return self.pdf.shape[1] // self.height


def texel_means(values: torch.Tensor) -> torch.Tensor:
    """(B, H, W) the mean over each texel of the bilinear interpolation of ``values`` (B, H, W) that
    :meth:`~dibrpp.lights.EnvMap.lookup` reads: a separable [1/8, 3/4, 1/8] filter, wrapping around in u and
    clamped in v as the look-up is. Texels next to a bright one (a sun) get its share of the look-up, so their pdf
    follows it; drawn by texel value alone, they were reached only by the uniform floor and the BRDF's samples."""
    k = values.new_tensor([0.125, 0.75, 0.125])
    v = F.pad(values.unsqueeze(1), (1, 1, 0, 0), mode="circular")
    v = F.conv2d(v, k.view(1, 1, 1, 3))
    v = F.pad(v, (0, 0, 1, 1), mode="replicate")
    return F.conv2d(v, k.view(1, 1, 3, 1)).squeeze(1)


def build_sampling_tables(image: torch.Tensor) -> SamplingTables:
    """Tables of the (B, H, W, 3) radiance ``image`` (its detached values)."""
    b, h, w, _ = image.shape
    img = image.detach().double()
    lum = (img @ img.new_tensor(conv.LUMINANCE_WEIGHTS)).clamp_min(0)  # (B, H, W); SH maps may ring negative
    lum = texel_means(lum)
    omega = conv.equirect_solid_angles(h, w, device=img.device, dtype=torch.float64)  # (H, 1)
    weight = (lum * omega).reshape(b, -1)
    total = weight.sum(-1, keepdim=True)
    uniform = (omega / (4 * math.pi)).expand(h, w).reshape(1, -1)
    p = torch.where(total > 0, (1 - UNIFORM_FLOOR) * weight / total.clamp_min(1e-300) + UNIFORM_FLOOR * uniform, uniform)
    cdf = F.pad(torch.cumsum(p, -1), (1, 0))
    cdf = cdf / cdf[:, -1:]
    p = cdf[:, 1:] - cdf[:, :-1]  # exactly the steps of the cdf, so sample() and pdf() agree
    edges = torch.arange(h + 1, device=img.device, dtype=torch.float64) * (math.pi / h)
    return SamplingTables(cdf=cdf, row_cdf=cdf[:, ::w].contiguous(), pdf=(p.reshape(b, h, w) / omega).reshape(b, -1),
                          cos_edges=torch.cos(edges))


def sample_directions(t: SamplingTables, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions drawn from the tables: uniforms u (Bt, M, 2) float64 in [0, 1), Bt the tables' batch ->
    (map-frame unit directions (Bt, M, 3), solid-angle pdf (Bt, M)), float64.

    u0 picks a row from the marginal, u1 a column from that row's conditional; the remainders place the
    direction uniformly in solid angle inside the texel.
    """
    h, w = t.height, t.width
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
    return conv.equirect_uv_to_direction(uv), t.pdf.gather(1, idx)


def texel_pdf(t: SamplingTables, d: torch.Tensor, base: torch.Tensor | int) -> torch.Tensor:
    """Solid-angle pdf (Beff, M) of :func:`sample_directions` at map-frame unit directions d (Beff, M, 3), in d's
    dtype; ``base`` (Beff, 1) offsets each row of d into the flattened (B*H*W) texels (0 when B = 1)."""
    h, w = t.height, t.width
    uv = conv.direction_to_equirect_uv(d)
    col = (uv[..., 0] * w).long().clamp(0, w - 1)
    row = (uv[..., 1] * h).long().clamp(0, h - 1)
    return t.pdf.reshape(-1)[base + row * w + col].to(d.dtype)
