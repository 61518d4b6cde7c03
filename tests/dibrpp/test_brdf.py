import math

import pytest
import torch

from dibrpp.brdf import (ShadingPoint, alpha_from_roughness, dielectric_f0, eta_from_f0, fresnel_dielectric,
                         fresnel_sg, ggx_d)
from dibrpp.conventions import equirect_directions, equirect_solid_angles


def sphere_quadrature(h=400, w=800):
    d = equirect_directions(h, w, dtype=torch.float64).reshape(-1, 3)
    da = equirect_solid_angles(h, w, dtype=torch.float64).expand(h, w).reshape(-1)
    return d, da


def point(theta_v=0.6, alpha=0.3, metallic=0.0, specular=0.5, albedo=(0.7, 0.5, 0.3)):
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    v = torch.tensor([[math.sin(theta_v), 0.0, math.cos(theta_v)]], dtype=torch.float64)
    t = lambda x: torch.tensor([x], dtype=torch.float64)  # noqa: E731
    return ShadingPoint(n, v, torch.tensor([albedo], dtype=torch.float64), t(alpha), t(metallic), t(specular))


@pytest.mark.parametrize("alpha", [0.05, 0.2, 0.6])
def test_ggx_ndf_is_normalised(alpha):
    d, da = sphere_quadrature()
    cos = d[:, 2]
    integral = (ggx_d(cos, torch.tensor(alpha, dtype=torch.float64)) * cos.clamp_min(0) * da).sum()
    assert abs(integral - 1) < 0.01


def test_roughness_mappings():
    beta = torch.tensor([0.0, 0.2, 1.0])
    assert torch.allclose(alpha_from_roughness(beta, "blender"), torch.tensor([1e-3, 0.04, 1.0]))
    assert torch.allclose(alpha_from_roughness(beta, "karis"), (beta + 1) ** 2 / 8)


def test_fresnel_terms():
    # exact dielectric Fresnel at IOR 1.5: F0 = 0.04, grazing -> 1; specular level scales F0 like Principled
    eta = torch.tensor(1.5, dtype=torch.float64)
    assert abs(fresnel_dielectric(torch.tensor(1.0, dtype=torch.float64), eta) - 0.04) < 1e-9
    assert fresnel_dielectric(torch.tensor(1e-4, dtype=torch.float64), eta) > 0.99
    assert abs(dielectric_f0(torch.tensor(0.5)) - 0.04) < 1e-7 and abs(dielectric_f0(torch.tensor(1.0)) - 0.08) < 1e-7
    assert abs(eta_from_f0(torch.tensor(0.04)) - 1.5) < 1e-4
    # eq. (4) is within 1% of Schlick's (1 - c)^5 form
    c = torch.linspace(0, 1, 101, dtype=torch.float64)
    f0 = torch.tensor(0.5, dtype=torch.float64)
    assert torch.allclose(fresnel_sg(f0, c), f0 + (1 - f0) * (1 - c) ** 5, atol=0.01)


@pytest.mark.parametrize("alpha,metallic", [(0.05, 1.0), (0.3, 0.0), (0.3, 1.0), (0.7, 0.5)])
def test_sampling_pdf_matches_the_sampled_distribution(alpha, metallic):
    p = point(alpha=alpha, metallic=metallic)
    d, da = sphere_quadrature()
    # GGX reflections that fall below the horizon are lost samples (weight 0), so the pdf of the
    # upper hemisphere integrates to at most one
    assert (p.pdf(d.unsqueeze(0))[0] * da).sum() < 1.005
    # E[f cos / pdf] over samples equals the quadrature of f cos (the directional albedo)
    g = torch.Generator().manual_seed(0)
    dirs, pdf = p.sample(torch.rand(1, 200_000, 3, generator=g, dtype=torch.float64))
    assert torch.allclose(pdf, p.pdf(dirs))
    mc = (p.eval(dirs) / pdf.clamp_min(1e-300).unsqueeze(-1)).mean(1)[0]
    quad = (p.eval(d.unsqueeze(0))[0] * da.unsqueeze(-1)).sum(0)
    assert torch.allclose(mc, quad, rtol=0.02, atol=1e-3), (mc, quad)


def test_energy_is_conserved_and_metals_have_no_diffuse():
    d, da = sphere_quadrature()
    for metallic in (0.0, 1.0):
        p = point(alpha=0.5, metallic=metallic, albedo=(1.0, 1.0, 1.0))
        albedo = (p.eval(d.unsqueeze(0))[0] * da.unsqueeze(-1)).sum(0)
        assert torch.all(albedo <= 1.0) and torch.all(albedo > 0.6)
    metal = point(metallic=1.0)
    assert torch.allclose(metal.diffuse_weight(), torch.zeros(1, 3, dtype=torch.float64))
    # no specular lobe at all when Specular IOR Level = 0
    p = point(alpha=0.2, specular=0.0)
    r = torch.nn.functional.normalize(torch.tensor([[[-math.sin(0.6), 0.0, math.cos(0.6)]]], dtype=torch.float64), dim=-1)
    assert torch.allclose(p.eval(r), p.albedo / math.pi * r[..., 2:] * 1.0)
