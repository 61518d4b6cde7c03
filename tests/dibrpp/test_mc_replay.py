"""MC shading by path replay (MCShader(replay=True), the default): same values and gradients as the plain
autograd path (replay=False), finite differences, and memory that does not grow with the sample count."""
import math

import pytest
import torch

from dibrpp import Cameras, Material, Renderer, icosphere
from dibrpp.brdf import ShadingPoint
from dibrpp.conventions import equirect_directions
from dibrpp.lights import EnvMap
from dibrpp.shading import GBuffer, MCShader

D = torch.float64
FIELDS = ("normal", "view", "albedo", "alpha", "metallic", "specular")


def env_image(h=8, w=16, batch=1, dtype=D):
    d = equirect_directions(h, w, dtype=dtype)
    sun = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.7], dtype=dtype), dim=0)
    img = 0.3 + 0.4 * d[..., 2:].clamp_min(0) * torch.tensor([0.5, 0.7, 1.0], dtype=dtype) \
        + 2 * torch.exp(6 * ((d * sun).sum(-1, keepdim=True) - 1))
    return torch.stack([img * (1 + 0.3 * b) for b in range(batch)])


def point_tensors(n_pix=40, seed=0, dtype=D, metallic=0.4):
    g = torch.Generator().manual_seed(seed)
    normal = torch.nn.functional.normalize(torch.randn(n_pix, 3, generator=g, dtype=D), dim=-1)
    view = torch.nn.functional.normalize(normal + 0.6 * torch.randn(n_pix, 3, generator=g, dtype=D), dim=-1)
    view = torch.where((normal * view).sum(-1, keepdim=True) < 0.05, normal, view)
    values = {"normal": normal, "view": view, "albedo": torch.rand(n_pix, 3, generator=g, dtype=D),
              "alpha": 0.05 + 0.5 * torch.rand(n_pix, generator=g, dtype=D),
              "metallic": torch.full((n_pix,), metallic, dtype=D), "specular": 0.2 + 0.6 * torch.rand(n_pix, generator=g, dtype=D)}
    return {k: v.to(dtype) for k, v in values.items()}


def rotation(dtype=D):
    a, b = 0.4, -0.3
    rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=dtype)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]], dtype=dtype)
    return rz @ rx


def shade_with_grads(shader, values, image, batch, num_images, rot=None):
    """(estimate, {name: grad}) for a fixed random linear loss of the estimate."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in values.items()}
    leaves["image"] = image.clone().requires_grad_(True)
    if rot is not None:
        leaves["rot"] = rot.clone().requires_grad_(True)
    # the G-buffer's unit vectors are functions of the leaves, as in the renderer
    point = ShadingPoint(torch.nn.functional.normalize(leaves["normal"], dim=-1),
                         torch.nn.functional.normalize(leaves["view"], dim=-1),
                         *(leaves[k] for k in FIELDS[2:]))
    out = shader(GBuffer(point, batch, num_images), EnvMap(leaves["image"], leaves.get("rot")))
    w = torch.rand(out.shape, generator=torch.Generator().manual_seed(7), dtype=out.dtype).to(out.device)
    (out * w).sum().backward()
    return out.detach(), {k: t.grad for k, t in leaves.items()}


CASES = [  # (mis, images, light batch, world_to_light)
    (True, 1, 1, False),
    (False, 1, 1, False),
    (True, 3, 1, True),  # images share a rotated map
    (True, 3, 3, False),  # one map per image (padded per-image layout)
]


@pytest.mark.filterwarnings("ignore:Converting a tensor with requires_grad=True to a scalar")  # the rotation check in lights
@pytest.mark.parametrize("mis, images, light_batch, rotated", CASES)
@pytest.mark.parametrize("dtype", [D, torch.float32])
def test_replay_matches_plain_autograd_values_and_every_gradient(mis, images, light_batch, rotated, dtype):
    n_pix = 40
    values = point_tensors(n_pix, dtype=dtype)
    batch = torch.sort(torch.randint(0, images, (n_pix,), generator=torch.Generator().manual_seed(1)))[0]
    image = env_image(batch=light_batch, dtype=dtype)
    rot = rotation(dtype) if rotated else None
    # several generator chunks (7 samples) and several recomputation slices per chunk (3 samples)
    kw = dict(spp=37, mis=mis, seed=5, max_batch_samples=n_pix * 7, eval_batch_samples=n_pix * 3)
    plain_out, plain = shade_with_grads(MCShader(replay=False, **kw), values, image, batch, images, rot)
    out, grads = shade_with_grads(MCShader(replay=True, **kw), values, image, batch, images, rot)
    assert torch.equal(out, plain_out)  # same samples, same arithmetic: the render does not change
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == D else dict(rtol=1e-4, atol=1e-5)
    assert plain.keys() == grads.keys()
    for name in plain:
        assert plain[name] is not None and grads[name] is not None, name
        assert plain[name].abs().sum() > 0, name  # every input really has a gradient
        # env-map samples are float32 directions (the uniforms are float32), so the rotation's gradient sums
        # float32 products over the samples of a recomputation slice: float32 rounding in either dtype
        t = dict(rtol=1e-5, atol=1e-6) if name == "rot" else tol
        assert torch.allclose(grads[name], plain[name], **t), (name, (grads[name] - plain[name]).abs().max())


def test_replay_with_the_global_generator_matches_plain_and_leaves_it_as_plain_does():
    values, image, batch = point_tensors(30), env_image(), torch.zeros(30, dtype=torch.long)
    results = []
    for replay in (False, True):
        torch.manual_seed(123)
        out, grads = shade_with_grads(MCShader(spp=12, seed=None, replay=replay, max_batch_samples=30 * 4), values,
                                      image, batch, 1)
        results.append((out, grads, torch.rand(4)))  # backward must not consume the global generator
    (out0, g0, next0), (out1, g1, next1) = results
    assert torch.equal(out0, out1) and torch.equal(next0, next1)
    for name in g0:
        assert torch.allclose(g0[name], g1[name], rtol=1e-10, atol=1e-12), name


def test_replay_without_gradients_is_the_plain_estimate():
    values, image, batch = point_tensors(30), env_image(), torch.zeros(30, dtype=torch.long)
    g = GBuffer(ShadingPoint(*(values[k] for k in FIELDS)), batch, 1)
    with torch.no_grad():
        a = MCShader(spp=9, seed=2, replay=True)(g, EnvMap(image))
    b = MCShader(spp=9, seed=2, replay=False)(g, EnvMap(image))
    assert torch.equal(a, b)


def finite_difference(fn, t: torch.Tensor, index: tuple, eps: float) -> float:
    old = t.data[index].item()
    t.data[index] = old + eps
    up = fn().item()
    t.data[index] = old - eps
    down = fn().item()
    t.data[index] = old
    return (up - down) / (2 * eps)


def test_replay_gradients_agree_with_finite_differences():
    values = point_tensors(12)
    batch = torch.zeros(12, dtype=torch.long)
    w = torch.rand(12, 3, dtype=D, generator=torch.Generator().manual_seed(3))
    rough = torch.tensor([0.45], dtype=D, requires_grad=True)  # one roughness for all pixels, alpha = beta^2
    image = env_image().requires_grad_(True)

    def loss(mis):
        point = ShadingPoint(values["normal"], values["view"], values["albedo"], (rough * rough).expand(12),
                             values["metallic"], values["specular"])
        return (MCShader(spp=24, mis=mis, seed=4, max_batch_samples=12 * 5, eval_batch_samples=12 * 2)(
            GBuffer(point, batch, 1), EnvMap(image)) * w).sum()

    # roughness moves the sampled directions; with fixed random numbers the estimate is smooth in it
    loss(True).backward()
    fd = finite_difference(lambda: loss(True), rough, (0,), 1e-7)
    assert abs(fd - rough.grad.item()) <= 1e-6 + 1e-4 * abs(fd), (fd, rough.grad.item())
    # a texel under the sun (BRDF sampling only: with MIS the env sampling tables move with the texels)
    rough.grad, image.grad = None, None
    loss(False).backward()
    texel = tuple(int(i) for i in torch.nonzero(image.grad[0].abs().sum(-1) == image.grad[0].abs().sum(-1).max())[0])
    index = (0, *texel, 1)
    fd = finite_difference(lambda: loss(False), image, index, 1e-6)
    assert abs(image.grad[index].item()) > 0
    assert abs(fd - image.grad[index].item()) <= 1e-9 + 1e-6 * abs(fd), (fd, image.grad[index].item())


def saved_bytes(shader, values, image, batch) -> int:
    """Bytes of the tensors autograd saves for backward while computing the estimate."""
    total = 0

    def pack(t):
        nonlocal total
        total += t.numel() * t.element_size()
        return t

    leaves = {k: v.clone().requires_grad_(True) for k, v in values.items()}
    light = EnvMap(image.clone().requires_grad_(True))
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = shader(GBuffer(ShadingPoint(*(leaves[k] for k in FIELDS)), batch, 1), light)
    out.sum().backward()  # and the backward runs
    assert light.image.grad is not None and leaves["alpha"].grad is not None
    return total


def test_saved_memory_does_not_grow_with_the_sample_count():
    values, image, batch = point_tensors(64, dtype=torch.float32), env_image(dtype=torch.float32), torch.zeros(64, dtype=torch.long)
    replay = [saved_bytes(MCShader(spp=n, seed=0, max_batch_samples=64 * 32), values, image, batch) for n in (16, 256)]
    plain = [saved_bytes(MCShader(spp=n, seed=0, max_batch_samples=64 * 32, replay=False), values, image, batch)
             for n in (16, 256)]
    assert replay[1] <= replay[0]  # only the inputs and the generator states of a few chunks
    assert plain[1] > 8 * plain[0]  # the plain path keeps every sample's intermediates
    assert replay[1] < plain[0]


def test_renderer_gradients_to_vertices_roughness_and_env_match_plain():
    mesh, cams = icosphere(2), Cameras.orbit(3.0, 10.0, torch.tensor([20.0, 140.0]), 40.0, 16)
    base = env_image(16, 32, dtype=torch.float32)

    def render(replay):
        verts = mesh.verts.clone().requires_grad_(True)
        rough = torch.tensor([0.3, 0.6], requires_grad=True)
        img = base.clone().requires_grad_(True)
        mat = Material(albedo=torch.tensor([[0.7, 0.5, 0.3]]), roughness=rough, metallic=0.5, specular=0.5)
        out = Renderer(MCShader(spp=8, seed=1, replay=replay))(mesh.with_verts(verts), cams, mat, EnvMap(img)).image
        (out * torch.linspace(0, 1, out.numel()).view(out.shape)).sum().backward()
        return out.detach(), verts.grad, rough.grad, img.grad

    for plain, replay in zip(render(False), render(True)):
        assert torch.allclose(plain, replay, rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("seed", [3, None])
def test_replay_on_cuda_matches_plain(seed):
    values = {k: v.cuda() for k, v in point_tensors(50).items()}
    image, batch = env_image().cuda(), torch.zeros(50, dtype=torch.long, device="cuda")
    results = []
    for replay in (False, True):
        torch.cuda.manual_seed(9)
        results.append(shade_with_grads(MCShader(spp=16, seed=seed, replay=replay, max_batch_samples=50 * 5,
                                                 eval_batch_samples=50 * 2), values, image, batch, 1))
    (out0, g0), (out1, g1) = results
    assert torch.equal(out0, out1)
    for name in g0:
        assert torch.allclose(g0[name], g1[name], rtol=1e-10, atol=1e-12), name


def test_evaluation_slices_do_not_change_the_estimate():
    values, image = point_tensors(30, dtype=torch.float32), env_image(dtype=torch.float32)
    g = GBuffer(ShadingPoint(*(values[k] for k in FIELDS)), torch.zeros(30, dtype=torch.long), 1)
    outs = [MCShader(spp=20, seed=1, max_batch_samples=30 * 8, eval_batch_samples=e)(g, EnvMap(image))
            for e in (30 * 3, 30, 1 << 30)]
    assert torch.equal(outs[0], outs[1]) and torch.equal(outs[0], outs[2])


def test_grad_seed_keeps_the_value_and_takes_the_gradient_of_an_independent_estimate():
    """MCShader(seed=a, grad_seed=b): the value of seed a's estimate, the gradient of seed b's (Mitsuba's
    seed / seed_grad), so a residual from the value times the gradient is decorrelated."""
    values, image, batch = point_tensors(30), env_image(), torch.zeros(30, dtype=torch.long)
    kw = dict(spp=10, max_batch_samples=30 * 4)  # several chunks: each must be redrawn from grad_seed in order
    out, grads = shade_with_grads(MCShader(seed=1, grad_seed=2, **kw), values, image, batch, 1)
    out_a, _ = shade_with_grads(MCShader(seed=1, **kw), values, image, batch, 1)
    _, grads_b = shade_with_grads(MCShader(seed=2, **kw), values, image, batch, 1)
    _, grads_a = shade_with_grads(MCShader(seed=1, **kw), values, image, batch, 1)
    assert torch.equal(out, out_a)
    for name in grads:
        assert torch.allclose(grads[name], grads_b[name], rtol=1e-10, atol=1e-12), name
    assert not torch.allclose(grads["image"], grads_a["image"])  # really other samples


def test_grad_seed_needs_replay():
    with pytest.raises(ValueError, match="replay"):
        MCShader(spp=4, grad_seed=1, replay=False)


# a cold torch.compile of MC's path: ~140 s alone on 2 cores, several times that beside another job
@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_compiled_mc_render_matches_eager_values_and_gradients():
    """Renderer(compile=True): the G-buffer and the MC samples through torch.compile, same numbers."""
    from dibrpp import renderer, shading

    mesh, cams = icosphere(2), Cameras.orbit(3.0, 20.0, torch.tensor([30.0, 200.0]), 45.0, 24)
    env = env_image(16, 32, dtype=torch.float32)

    def render(compile):
        verts = mesh.verts.clone().requires_grad_(True)
        image = env.clone().requires_grad_(True)
        albedo = torch.tensor([[0.8, 0.5, 0.3]], requires_grad=True)
        out = Renderer("mc", spp=6, seed=3, compile=compile)(mesh.with_verts(verts), cams,
                                                             Material(albedo=albedo, roughness=0.3, metallic=0.5),
                                                             EnvMap(image)).rgb
        (out * torch.linspace(0, 1, out.numel()).view_as(out)).sum().backward()
        return out.detach(), verts.grad, image.grad, albedo.grad

    for eager, compiled in zip(render(False), render(True)):
        assert torch.allclose(eager, compiled, rtol=1e-4, atol=1e-5), (eager - compiled).abs().max()
    assert not (renderer.build_gbuffer_compiled.failed or shading._sample_terms_compiled.failed)
