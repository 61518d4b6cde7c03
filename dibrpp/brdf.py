"""The simplified Disney BRDF of DIB-R++ (eq. 1-5), with Principled BSDF meanings (see DESIGN.md).

Parameters: base colour ``a`` (diffuse albedo, linear), roughness beta, metallic m, and
``specular`` = Principled "Specular IOR Level" (0.5 => F0 = 0.04 at IOR 1.5, 0 => no specular lobe).

Choices that follow Cycles rather than the paper's literal text (all listed in docs/deviations.md#renderer):
- NDF alpha = beta^2 (``roughness_map="blender"``); the paper's (beta+1)^2/8 is ``"karis"``.
- Shadowing: Smith GGX height-correlated (``geometry="smith"``); the paper's Schlick G (eq. 3) is ``"schlick"``.
- Metals have no diffuse lobe: diffuse is weighted by (1 - m), and for dielectrics by 1 - F(n.v).
- Dielectric Fresnel is exact (IOR from the specular level); metals use eq. (4) with F0 = base colour.

The C++ MC kernel (``dibrpp/csrc/mc_envmap.cpp``) repeats ShadingPoint's sampling, eval and pdf: change both
(``tests/dibrpp/test_mc_native.py`` compares them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

DIELECTRIC_IOR = 1.5
MIN_ALPHA = 1e-3  # GGX alpha floor: a perfect mirror has an infinitely sharp lobe


@dataclass
class BRDFOptions:
    roughness_map: str = "blender"  # "blender": alpha = beta^2; "karis": alpha = (beta + 1)^2 / 8 (paper eq. 2)
    geometry: str = "smith"  # "smith": height-correlated Smith GGX (Cycles); "schlick": eq. (3)

    def __post_init__(self):
        if self.roughness_map not in ("blender", "karis"):
            raise ValueError(f"roughness_map must be 'blender' or 'karis', got {self.roughness_map!r}")
        if self.geometry not in ("smith", "schlick"):
            raise ValueError(f"geometry must be 'smith' or 'schlick', got {self.geometry!r}")


@dataclass
class Material:
    """Per-image material; every field broadcasts over the batch.

    albedo: (B, 3) constant base colour, or a (B, Ht, Wt, 3) linear UV texture (needs mesh UVs).
    roughness / metallic / specular: (B,) or scalars, Principled meanings.
    """

    albedo: torch.Tensor
    roughness: torch.Tensor | float = 0.5
    metallic: torch.Tensor | float = 0.0
    specular: torch.Tensor | float = 0.5
    wrap_u: bool = False  # texture wraps in u (template sphere seam)
    options: BRDFOptions = field(default_factory=BRDFOptions)

    @property
    def is_texture(self) -> bool:
        return self.albedo.dim() == 4

    def scalar(self, name: str, batch: torch.Tensor, dtype=torch.float32) -> torch.Tensor:
        """Per-pixel value (N,) of a scalar parameter for pixels of images ``batch``."""
        v = torch.as_tensor(getattr(self, name), dtype=dtype, device=batch.device).reshape(-1)
        return v[batch] if v.numel() > 1 else v.expand(batch.shape[0])


def alpha_from_roughness(beta: torch.Tensor, mapping: str = "blender") -> torch.Tensor:
    beta = beta.clamp(0.0, 1.0)
    alpha = beta * beta if mapping == "blender" else (beta + 1) ** 2 / 8
    return alpha.clamp_min(MIN_ALPHA)


def ggx_d(n_dot_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX / Trowbridge-Reitz NDF (eq. 2)."""
    a2 = alpha * alpha
    c2 = n_dot_h.clamp(0, 1) ** 2
    return a2 / (math.pi * (c2 * (a2 - 1) + 1) ** 2)


def smith_lambda(cos: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    c2 = cos.clamp(1e-6, 1) ** 2
    tan2 = (1 - c2) / c2
    return 0.5 * (torch.sqrt(1 + alpha * alpha * tan2) - 1)


def geometry_term(n_dot_v, n_dot_l, alpha, kind: str = "smith") -> torch.Tensor:
    """Shadowing-masking G(l, v): height-correlated Smith GGX, or the paper's Schlick form (eq. 3)."""
    if kind == "smith":
        return 1.0 / (1 + smith_lambda(n_dot_v, alpha) + smith_lambda(n_dot_l, alpha))
    g1 = lambda c: c / (c * (1 - alpha) + alpha)  # noqa: E731
    return g1(n_dot_v.clamp(0, 1)) * g1(n_dot_l.clamp(0, 1))


def fresnel_sg(f0: torch.Tensor, v_dot_h: torch.Tensor) -> torch.Tensor:
    """Schlick Fresnel with the spherical-Gaussian exponent of eq. (4)."""
    c = v_dot_h.clamp(0, 1)
    return f0 + (1 - f0) * torch.exp2((-5.55473 * c - 6.98316) * c)


def fresnel_dielectric(cos_i: torch.Tensor, eta: torch.Tensor) -> torch.Tensor:
    """Exact unpolarised Fresnel reflectance of a dielectric interface (from outside, relative IOR eta)."""
    c = cos_i.clamp(0, 1)
    g2 = eta * eta - 1 + c * c
    g = torch.sqrt(g2.clamp_min(0))
    a = (g - c) / (g + c).clamp_min(1e-12)
    b = (c * (g + c) - 1) / (c * (g - c) + 1)
    return torch.where(g2 > 0, 0.5 * a * a * (1 + b * b), torch.ones_like(c))


def dielectric_f0(specular: torch.Tensor, ior: float = DIELECTRIC_IOR) -> torch.Tensor:
    """F0 of Principled's dielectric: the IOR's F0 scaled by 2 x Specular IOR Level (0.5 => unchanged)."""
    base = ((ior - 1) / (ior + 1)) ** 2
    return (base * 2 * specular).clamp(0, 0.999)


def eta_from_f0(f0: torch.Tensor) -> torch.Tensor:
    s = torch.sqrt(f0.clamp(1e-8, 0.999))
    return (1 + s) / (1 - s)


@dataclass
class ShadingPoint:
    """Per-pixel BRDF inputs (N pixels): unit normal n, unit view direction v, parameters."""

    normal: torch.Tensor  # (N, 3)
    view: torch.Tensor  # (N, 3)
    albedo: torch.Tensor  # (N, 3) linear
    alpha: torch.Tensor  # (N,)
    metallic: torch.Tensor  # (N,)
    specular: torch.Tensor  # (N,)
    geometry: str = "smith"

    @property
    def n_dot_v(self) -> torch.Tensor:
        return (self.normal * self.view).sum(-1).clamp(1e-4, 1)

    @property
    def f0_dielectric(self) -> torch.Tensor:
        return dielectric_f0(self.specular)

    def fresnel(self, v_dot_h: torch.Tensor) -> torch.Tensor:
        """(N, S, 3) Fresnel of the layered specular: (1 - m) dielectric + m metal (eq. 5 as in Principled)."""
        m = self.metallic.view(-1, 1, 1)
        f_d = fresnel_dielectric(v_dot_h, eta_from_f0(self.f0_dielectric).unsqueeze(-1)).unsqueeze(-1)
        f_d = f_d * (self.specular > 0).view(-1, 1, 1)
        f_m = fresnel_sg(self.albedo.unsqueeze(1), v_dot_h.unsqueeze(-1))
        return (1 - m) * f_d + m * f_m

    def diffuse_weight(self) -> torch.Tensor:
        """(N, 3) factor of a/pi: (1 - m)(1 - F_dielectric(n.v)) a."""
        f_d = fresnel_dielectric(self.n_dot_v, eta_from_f0(self.f0_dielectric)) * (self.specular > 0)
        return ((1 - self.metallic) * (1 - f_d)).unsqueeze(-1) * self.albedo

    def _half_vector_terms(self, light_dirs: torch.Tensor):
        """Shared by :meth:`eval` and :meth:`pdf`: raw n.l, n.h, v.h (N, S) and the GGX D(n.h) for directions (N, S, 3)."""
        n, v = self.normal.unsqueeze(1), self.view.unsqueeze(1)
        n_dot_l = (n * light_dirs).sum(-1)
        h = torch.nn.functional.normalize(light_dirs + v, dim=-1, eps=1e-12)
        n_dot_h = (n * h).sum(-1)
        v_dot_h = (v * h).sum(-1)
        return n_dot_l, n_dot_h, v_dot_h, ggx_d(n_dot_h, self.alpha.unsqueeze(1))  # ggx_d clamps n.h to [0, 1]

    def _eval(self, terms) -> torch.Tensor:
        n_dot_l, n_dot_h, v_dot_h, d = terms
        above = (n_dot_l > 0).to(n_dot_l.dtype)
        n_dot_l = n_dot_l.clamp(1e-6, 1)
        v_dot_h = v_dot_h.clamp(0, 1)
        alpha = self.alpha.unsqueeze(1)
        n_dot_v = self.n_dot_v.unsqueeze(1)
        spec = d * geometry_term(n_dot_v, n_dot_l, alpha, self.geometry) / (4 * n_dot_v)
        spec = self.fresnel(v_dot_h) * spec.unsqueeze(-1)  # (n.l) cancels the 1/(n.l) of eq. (1)
        diffuse = self.diffuse_weight().unsqueeze(1) / math.pi * n_dot_l.unsqueeze(-1)
        return (spec + diffuse) * above.unsqueeze(-1)

    def _pdf(self, terms) -> torch.Tensor:
        n_dot_l, n_dot_h, v_dot_h, d = terms
        pdf_spec = d * n_dot_h.clamp(0, 1) / (4 * v_dot_h.clamp_min(1e-6))
        pdf_diff = n_dot_l.clamp_min(0) / math.pi
        p_spec = self.specular_selection_probability().unsqueeze(1)
        pdf = p_spec * pdf_spec + (1 - p_spec) * pdf_diff
        return torch.where(n_dot_l > 0, pdf, torch.zeros_like(pdf))

    def eval(self, light_dirs: torch.Tensor) -> torch.Tensor:
        """BRDF times cosine, f(l, v) (n.l), for light directions (N, S, 3) -> (N, S, 3)."""
        return self._eval(self._half_vector_terms(light_dirs))

    def eval_and_pdf(self, light_dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(:meth:`eval`, :meth:`pdf`) at once, sharing the half vector and the GGX term (same values)."""
        terms = self._half_vector_terms(light_dirs)
        return self._eval(terms), self._pdf(terms)

    def specular_selection_probability(self) -> torch.Tensor:
        """(N,) probability of sampling the GGX lobe rather than the cosine lobe (a variance heuristic)."""
        spec_w = (1 - self.metallic) * self.f0_dielectric * (self.specular > 0) + self.metallic
        diff_w = self.diffuse_weight().mean(-1)
        p = spec_w / (spec_w + diff_w).clamp_min(1e-8)
        p = torch.where((spec_w > 0) & (diff_w > 0), p.clamp(0.25, 0.9), p)
        return p.detach()

    def sample(self, u: torch.Tensor):
        """Sample light directions from the BRDF mixture. u: (N, S, 3) uniforms -> (dirs (N, S, 3), pdf (N, S))."""
        dirs = self.sample_directions(u)
        return dirs, self.pdf(dirs)

    def sample_directions(self, u: torch.Tensor) -> torch.Tensor:
        """The directions (N, S, 3) of :meth:`sample` alone."""
        n, v = self.normal, self.view
        t, b = _tangent_frame(n)
        alpha = self.alpha.unsqueeze(1)
        # GGX half vector by inverse transform: tan^2(theta) = alpha^2 xi / (1 - xi)
        xi = u[..., 0].clamp(0, 1 - 1e-7)
        ratio = torch.sqrt(xi / (1 - xi))
        cos_h = torch.rsqrt(1 + (alpha * ratio) ** 2)
        sin_h = alpha * ratio * cos_h  # = sqrt(1 - cos^2), with a finite gradient at cos = 1
        phi = 2 * math.pi * u[..., 1]
        h_local = torch.stack([sin_h * torch.cos(phi), sin_h * torch.sin(phi), cos_h], -1)
        h = _to_world(h_local, t, b, n)
        l_spec = 2 * (v.unsqueeze(1) * h).sum(-1, keepdim=True) * h - v.unsqueeze(1)
        # cosine-weighted hemisphere
        r = torch.sqrt(u[..., 0])
        l_diff_local = torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - u[..., 0]).clamp_min(0))], -1)
        l_diff = _to_world(l_diff_local, t, b, n)
        p_spec = self.specular_selection_probability().unsqueeze(1)
        pick_spec = (u[..., 2] < p_spec).unsqueeze(-1)
        return torch.where(pick_spec, l_spec, l_diff)

    def pdf(self, light_dirs: torch.Tensor) -> torch.Tensor:
        """Solid-angle pdf (N, S) of :meth:`sample` for given directions."""
        return self._pdf(self._half_vector_terms(light_dirs))


def _tangent_frame(n: torch.Tensor):
    """Orthonormal tangent/bitangent (N, 3) for unit normals (Duff et al. 2017, branchless)."""
    sign = torch.where(n[:, 2] >= 0, 1.0, -1.0).to(n)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = torch.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], -1)
    bt = torch.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], -1)
    return t, bt


def _to_world(local: torch.Tensor, t, b, n) -> torch.Tensor:
    return local[..., :1] * t.unsqueeze(1) + local[..., 1:2] * b.unsqueeze(1) + local[..., 2:] * n.unsqueeze(1)
