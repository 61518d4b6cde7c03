"""Deferred shaders: per-pixel radiance from the G-buffer of covered pixels.

- :class:`MCShader`: Monte-Carlo integration against an :class:`~dibrpp.lights.EnvMap` with BRDF
  importance sampling (GGX by inverse transform + cosine lobe) and, optionally, env-map sampling
  combined by multiple importance sampling (balance heuristic). Unbiased.
- :class:`SGShader`: closed form against an :class:`~dibrpp.lights.SGLight` (cosine SG for the
  diffuse, warped NDF SG for the specular, eq. 6-7).
- :class:`SHShader`: DIB-R's Lambertian baseline under :class:`~dibrpp.lights.SHLight`, or under an
  SGLight (diffuse-only shading with SG light, the ablation of Table D).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from . import sg as sgmath
from .brdf import ShadingPoint, geometry_term


@dataclass
class GBuffer:
    """Shading inputs of the N covered pixels (packed), plus their image index ``batch``."""

    point: ShadingPoint
    batch: torch.Tensor  # (N,)
    num_images: int


def per_image(fn, values: torch.Tensor, batch: torch.Tensor, num_images: int) -> torch.Tensor:
    """Apply ``fn`` (which takes a (B, M, ...) batch of per-image values) to packed (N, ...) values.

    Lights index their batch by image; packed pixels are sorted by image, so they are laid out in a
    padded (B, max_count, ...) block, processed at once, and packed back.
    """
    counts = torch.bincount(batch, minlength=num_images)
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(batch.shape[0], device=batch.device) - start[batch]
    width = int(counts.max()) if batch.numel() else 0
    padded = values.new_zeros((num_images, max(width, 1)) + values.shape[1:])
    padded = padded.index_put((batch, slot), values)
    out = fn(padded)
    return out[batch, slot]


class MCShader:
    """Monte-Carlo shading with ``spp`` samples per pixel.

    mis: half the samples from the BRDF, half from the env map, balance heuristic. seed: fixed
    random numbers for reproducible renders and tests (None: torch's global generator).
    """

    def __init__(self, spp: int = 64, mis: bool = True, seed: int | None = None, max_batch_samples: int = 1 << 21):
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        self.spp, self.mis, self.seed = int(spp), bool(mis), seed
        self.max_batch_samples = max_batch_samples

    def _uniforms(self, shape, device, gen):
        return torch.rand(shape, device=device, generator=gen)

    def __call__(self, g: GBuffer, light) -> torch.Tensor:
        p = g.point
        n_pix = p.normal.shape[0]
        device = p.normal.device
        gen = None
        if self.seed is not None:
            gen = torch.Generator(device=device)
            gen.manual_seed(self.seed)
        n_light = self.spp // 2 if self.mis else 0
        n_brdf = self.spp - n_light
        chunk = max(1, self.max_batch_samples // max(n_pix, 1))
        total = p.normal.new_zeros(n_pix, 3)
        lookup = lambda d: per_image(light.lookup, d, g.batch, g.num_images)  # noqa: E731
        light_pdf = lambda d: per_image(light.pdf, d, g.batch, g.num_images)  # noqa: E731

        def weight(dirs, pdf_brdf):
            if not self.mis:
                return 1.0 / (n_brdf * pdf_brdf).clamp_min(1e-12)
            return 1.0 / (n_brdf * pdf_brdf + n_light * light_pdf(dirs).detach()).clamp_min(1e-12)

        for s0 in range(0, n_brdf, chunk):
            s = min(chunk, n_brdf - s0)
            dirs, pdf = p.sample(self._uniforms((n_pix, s, 3), device, gen))
            f = p.eval(dirs)
            total = total + (f * lookup(dirs) * weight(dirs, pdf).unsqueeze(-1)).sum(1)
        for s0 in range(0, n_light, chunk):
            s = min(chunk, n_light - s0)
            u = self._uniforms((n_pix, s, 2), device, gen)
            # env-map sampling: the tables are fixed (detached), directions carry no gradient
            dirs = per_image(lambda uu: light.sample(uu)[0], u, g.batch, g.num_images).detach()
            f = p.eval(dirs)
            total = total + (f * lookup(dirs) * weight(dirs, p.pdf(dirs)).unsqueeze(-1)).sum(1)
        return total


def sg_convolve(light, axis: torch.Tensor, sharpness: torch.Tensor, g: "GBuffer", compile: bool = False) -> torch.Tensor:
    """(N, 3) sum over the light's lobes of the integral of (unit-amplitude SG(axis, sharpness) x lobe).

    axis (N, 3), sharpness (N,) per pixel. Pixels are laid out per image so the cosines to all K lobes
    are one batched matrix product and the sum over lobes against the RGB amplitudes another.
    compile: evaluate the (B, M, K) product integrals with torch.compile (same values, much faster).
    """
    product_integral = sgmath.sg_product_integral_compiled if compile else sgmath.sg_product_integral
    b = g.num_images
    light_axis = light.world_axis().expand(b, -1, -1)  # (B, K, 3)
    light_lam = light.sharpness.expand(b, -1).unsqueeze(1)  # (B, 1, K)
    light_amp = light.amplitude.expand(b, -1, -1)  # (B, K, 3)

    def convolve(packed):  # (B, M, 4): axis and sharpness
        cos = packed[..., :3] @ light_axis.transpose(1, 2)  # (B, M, K)
        scale = product_integral(cos, packed[..., 3:], light_lam)
        return scale @ light_amp

    return per_image(convolve, torch.cat([axis, sharpness.unsqueeze(-1)], -1), g.batch, b)


def sg_cosine_irradiance(normal: torch.Tensor, light, g: "GBuffer", compile: bool = False) -> torch.Tensor:
    """(N, 3) approximate irradiance: sum_k <cosine SG at n, G_k>, clamped >= 0."""
    lam = normal.new_full(normal.shape[:1], sgmath.COSINE_SG_SHARPNESS)
    return (sgmath.COSINE_SG_AMPLITUDE * sg_convolve(light, normal, lam, g, compile)).clamp_min(0)


class SGShader:
    """Closed-form shading with a mixture of spherical Gaussians (DIB-R++ SG).

    compile: fuse the per pixel-lobe work with torch.compile (~20x faster on CPU once compiled; the
    first call compiles for tens of seconds). Worth it for training and benchmarks, not one render.
    """

    def __init__(self, compile: bool = False):
        self.compile = compile

    def __call__(self, g: GBuffer, light) -> torch.Tensor:
        p = g.point
        diffuse = p.diffuse_weight() / math.pi * sg_cosine_irradiance(p.normal, light, g, self.compile)
        w_axis, w_lam, w_amp = sgmath.warp_ndf_sg(p.normal, p.view, p.alpha)
        inner = w_amp.unsqueeze(-1) * sg_convolve(light, w_axis, w_lam, g, self.compile)
        n_dot_v = p.n_dot_v
        n_dot_l = (p.normal * w_axis).sum(-1)
        g_term = geometry_term(n_dot_v, n_dot_l.clamp(1e-4, 1), p.alpha, p.geometry)
        # F and G are taken at the lobe axis (h = n, so v.h = n.v); the n.l of the integrand cancels
        # the 1/(n.l) of eq. (1) and vanishes for lobes below the horizon.
        spec_scale = g_term * (n_dot_l > 0) / (4 * n_dot_v)
        fresnel = p.fresnel(n_dot_v.unsqueeze(1)).squeeze(1)
        specular = inner * fresnel * spec_scale.unsqueeze(-1)
        return diffuse + specular


class SHShader:
    """Lambertian-only shading (DIB-R): albedo / pi x irradiance from SH9, or from an SG light."""

    def __init__(self, compile: bool = False):
        self.compile = compile  # for the SG light (as in SGShader)

    def __call__(self, g: GBuffer, light) -> torch.Tensor:
        p = g.point
        if hasattr(light, "coeffs"):
            irr = per_image(light.irradiance, p.normal, g.batch, g.num_images)
        else:
            irr = sg_cosine_irradiance(p.normal, light, g, self.compile)
        return p.albedo / math.pi * irr


def make_shader(name: str, spp: int = 64, mis: bool = True, seed: int | None = None, compile: bool = False):
    """Shader by method name: "mc", "sg", "sh" (SH light) or "sh-sg" (diffuse-only with SG light)."""
    if name == "mc":
        return MCShader(spp=spp, mis=mis, seed=seed)
    if name == "sg":
        return SGShader(compile)
    if name in ("sh", "sh-sg"):
        return SHShader(compile)
    raise ValueError(f"unknown shading {name!r}; choose mc, sg, sh or sh-sg")
