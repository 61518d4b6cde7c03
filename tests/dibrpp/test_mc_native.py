"""dibrpp's C++ MC kernel (MCShader(native=True), the default where it applies): the same samples and values as
the PyTorch path to float rounding, the same env-map gradients, finite differences, and the PyTorch path wherever
the kernel does not apply."""
import shutil

import pytest
import torch

from dibrpp import Cameras, Material, Renderer, icosphere, native
from dibrpp.brdf import ShadingPoint
from dibrpp.lights import EnvMap
from dibrpp.shading import GBuffer, MCShader, _MCPlan

from test_mc_replay import FIELDS, env_image, finite_difference, point_tensors, rotation

F32 = torch.float32


# Without a C++ compiler there is no kernel, and dibrpp runs the PyTorch path (README, Set-up).
pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: no kernel to test")


def test_the_kernel_is_built():
    """`make setup` builds it; None here would mean every MC render silently takes the slow path."""
    assert native.mc_envmap() is not None


def gbuffer(n_pix=60, images=1, metallic=0.4, geometry="smith", seed=0):
    values = point_tensors(n_pix, seed=seed, dtype=F32, metallic=metallic)
    batch = torch.sort(torch.randint(0, images, (n_pix,), generator=torch.Generator().manual_seed(1)))[0]
    return GBuffer(ShadingPoint(*(values[k] for k in FIELDS), geometry=geometry), batch, images)


def value_and_env_grad(shader, g, image, rot=None):
    image = image.clone().requires_grad_(True)
    out = shader(g, EnvMap(image, rot))
    w = torch.rand(out.shape, generator=torch.Generator().manual_seed(7))
    (out * w).sum().backward()
    return out.detach(), image.grad


CASES = [  # (mis, images, light batch, rotated, metallic, geometry)
    (True, 1, 1, False, 0.4, "smith"),
    (False, 1, 1, False, 0.4, "smith"),
    (True, 1, 1, False, 1.0, "smith"),  # metal: the dielectric Fresnel term is skipped
    (True, 1, 1, False, 0.0, "schlick"),
    (True, 3, 1, True, 0.4, "smith"),  # images share a rotated map
    (True, 3, 3, False, 0.4, "smith"),  # one map per image
]


@pytest.mark.parametrize("mis, images, light_batch, rotated, metallic, geometry", CASES)
def test_kernel_matches_pytorch_values_and_env_gradients(mis, images, light_batch, rotated, metallic, geometry):
    g = gbuffer(images=images, metallic=metallic, geometry=geometry)
    image = env_image(16, 32, batch=light_batch, dtype=F32)
    rot = rotation(F32) if rotated else None
    # several generator chunks: the kernel takes the same uniforms chunk by chunk
    kw = dict(spp=24, mis=mis, seed=5, grad_seed=9, max_batch_samples=60 * 5)
    assert _MCPlan(MCShader(**kw), g, EnvMap(image, rot)).kernel is not None
    ref, ref_grad = value_and_env_grad(MCShader(native=False, **kw), g, image, rot)
    out, grad = value_and_env_grad(MCShader(**kw), g, image, rot)
    assert ref.abs().max() > 0.1 and ref_grad.abs().sum() > 0
    assert torch.allclose(out, ref, rtol=1e-4, atol=1e-5), (out - ref).abs().max()
    assert torch.allclose(grad, ref_grad, rtol=1e-4, atol=1e-5), (grad - ref_grad).abs().max()


def test_kernel_render_of_a_sphere_matches_pytorch():
    mesh, cams = icosphere(2), Cameras.orbit(3.0, 20.0, torch.tensor([30.0, 200.0]), 45.0, 32)
    material = Material(albedo=torch.tensor([[0.8, 0.5, 0.3]]), roughness=0.3, metallic=0.7)
    light = EnvMap(env_image(16, 32, dtype=F32))
    with torch.no_grad():
        a, b = (Renderer(MCShader(spp=16, seed=3, native=n))(mesh, cams, material, light).rgb for n in (True, False))
    assert torch.allclose(a, b, rtol=1e-4, atol=1e-5), (a - b).abs().max()


def test_kernel_env_gradient_agrees_with_finite_differences():
    g = gbuffer(n_pix=40)
    image = env_image(8, 16, dtype=F32) * 1.0
    shader = MCShader(spp=16, seed=2)  # the gradient of this very estimate (no grad_seed)
    w = torch.rand(40, 3, generator=torch.Generator().manual_seed(3))
    img = image.clone().requires_grad_(True)
    (shader(g, EnvMap(img)) * w).sum().backward()
    # a texel the samples reach; the MIS weights use the detached map, which the difference below also moves,
    # so the estimate is evaluated with its sampling tables held at the unperturbed map
    index = tuple(int(i) for i in (img.grad.abs() == img.grad.abs().max()).nonzero()[0])
    tables = EnvMap(image).sampling_tables()

    def loss():
        light = EnvMap(image)
        light._tables = (light.image._version, tables)
        with torch.no_grad():
            return (shader(g, light) * w).sum().double()

    fd = finite_difference(loss, image, index, 1e-2)
    assert abs(fd - float(img.grad[index])) <= 1e-3 * abs(fd) + 1e-4, (fd, float(img.grad[index]))


def test_pytorch_path_where_the_kernel_does_not_apply():
    g = gbuffer()
    image = env_image(8, 16, dtype=F32)
    assert _MCPlan(MCShader(spp=4), g, EnvMap(image)).kernel is not None
    # a material gradient: the kernel has none, so autograd runs in PyTorch and the albedo gets its gradient
    albedo = g.point.albedo.clone().requires_grad_(True)
    g_grad = GBuffer(ShadingPoint(g.point.normal, g.point.view, albedo, g.point.alpha, g.point.metallic,
                                  g.point.specular), g.batch, 1)
    assert _MCPlan(MCShader(spp=4), g_grad, EnvMap(image)).kernel is None
    MCShader(spp=4, seed=1)(g_grad, EnvMap(image)).sum().backward()
    assert albedo.grad is not None and albedo.grad.abs().sum() > 0
    # float64, or an env-map gradient without replay (no custom backward to carry it)
    g64 = GBuffer(ShadingPoint(*(getattr(g.point, k).double() for k in FIELDS)), g.batch, 1)
    assert _MCPlan(MCShader(spp=4), g64, EnvMap(image.double())).kernel is None
    assert _MCPlan(MCShader(spp=4, replay=False), g, EnvMap(image.requires_grad_(True))).kernel is None
    assert _MCPlan(MCShader(spp=4, native=False), g, EnvMap(image)).kernel is None


def test_disabled_by_environment(monkeypatch):
    monkeypatch.setenv("DIBRPP_NATIVE", "0")
    native.mc_envmap.cache_clear()
    try:
        assert native.mc_envmap() is None
        assert _MCPlan(MCShader(spp=4), gbuffer(), EnvMap(env_image(8, 16, dtype=F32))).kernel is None
    finally:
        monkeypatch.delenv("DIBRPP_NATIVE")
        native.mc_envmap.cache_clear()
    assert native.mc_envmap() is not None


@pytest.mark.slow  # compiles the second build (~30 s)
def test_simd_and_baseline_builds_compute_the_same_values():
    """The AVX2 build's lane loops are the baseline build's, vectorised: no FMA contraction, exact division and
    square root in both, so the values are identical, not just close."""
    if "-mavx2" not in native.simd_flags():
        pytest.skip("this CPU has no AVX2: one build only")
    g = gbuffer(n_pix=200, images=3, metallic=0.4)
    image = env_image(16, 32, batch=3, dtype=F32)
    plan = _MCPlan(MCShader(spp=8, seed=5), g, EnvMap(image, rotation(F32)))
    light = plan.light
    baseline = native.mc_envmap(simd=False)
    assert baseline is not None
    go = torch.rand(200, 3, generator=torch.Generator().manual_seed(2))
    for i, (kind, _) in enumerate(plan.chunks):
        u = plan.draw(i, plan.gen)
        for fn in ("forward", "backward_image"):
            extra = (go,) if fn == "backward_image" else ()
            a = plan._native_chunk(getattr(plan.kernel, fn), light, kind, u, *extra)
            b = plan._native_chunk(getattr(baseline, fn), light, kind, u, *extra)
            assert torch.equal(a, b), (kind, fn, (a - b).abs().max())
