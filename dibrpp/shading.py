"""Deferred shaders: per-pixel radiance from the G-buffer of covered pixels.

- :class:`MCShader`: Monte-Carlo integration against an :class:`~dibrpp.lights.EnvMap` with BRDF
  importance sampling (GGX by inverse transform + cosine lobe) and, optionally, env-map sampling
  combined by multiple importance sampling (balance heuristic). Unbiased. Its gradients come from path
  replay by default (memory independent of the sample count: the samples are redrawn in backward).
- :class:`SGShader`: closed form against an :class:`~dibrpp.lights.SGLight` (cosine SG for the
  diffuse, warped NDF SG for the specular, eq. 6-7).
- :class:`SHShader`: DIB-R's Lambertian baseline under :class:`~dibrpp.lights.SHLight`, or under an
  SGLight (diffuse-only shading with SG light, the ablation of Table D).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from . import native
from . import sg as sgmath
from .brdf import ShadingPoint, geometry_term
from .jit import CompiledOrEager
from .lights import EnvMap, Light


@dataclass
class GBuffer:
    """Shading inputs of the N covered pixels (packed), plus their image index ``batch``."""

    point: ShadingPoint
    batch: torch.Tensor  # (N,)
    num_images: int

    def select(self, order: torch.Tensor, batch: torch.Tensor, num_images: int) -> "GBuffer":
        """The pixels ``order`` (indices into this G-buffer's) as images ``batch`` of ``num_images``
        (:meth:`~dibrpp.raster.Fragments.select_images` gives both)."""
        taken = {f.name: getattr(self.point, f.name)[order] for f in dataclasses.fields(self.point)
                 if isinstance(getattr(self.point, f.name), torch.Tensor)}
        return GBuffer(dataclasses.replace(self.point, **taken), batch, num_images)


@torch.compiler.disable
def _largest(counts: torch.Tensor) -> int:
    """The padded block's width, a Python int: outside torch.compile, whose graph has to break for a shape read
    from the data anyway (this way without a warning in every compiled MC run)."""
    return int(counts.max())


def per_image(fn, values: torch.Tensor, batch: torch.Tensor, num_images: int, shared: bool = False) -> torch.Tensor:
    """Apply ``fn`` (which takes a (B, M, ...) batch of per-image values) to packed (N, ...) values.

    Lights index their batch by image; packed pixels are sorted by image, so they are laid out in a
    padded (B, max_count, ...) block, processed at once, and packed back. With one image, or when
    ``shared`` (the light has batch 1 and broadcasts over the images), all values go in one row
    (1, N, ...): the same values without the padding copies.
    """
    if num_images == 1 or shared:
        return fn(values.unsqueeze(0))[0]
    counts = torch.bincount(batch, minlength=num_images)
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(batch.shape[0], device=batch.device) - start[batch]
    width = _largest(counts) if batch.numel() else 0
    padded = values.new_zeros((num_images, max(width, 1)) + values.shape[1:])
    padded = padded.index_put((batch, slot), values)
    out = fn(padded)
    return out[batch, slot]


class MCShader:
    """Monte-Carlo shading with ``spp`` samples per pixel.

    mis: half the samples from the BRDF, half from the env map, balance heuristic. seed: fixed
    random numbers for reproducible renders and tests (None: torch's global generator of the device).

    replay (default True): memory independent of ``spp``. When gradients are needed, the estimate is a
    custom autograd function (:class:`_MCReplay`) that evaluates the samples without building a graph
    and remembers only the random generator's state at the start of each chunk; its backward redraws
    exactly the same uniforms chunk by chunk (path replay, as in Mitsuba 3's prb integrator), recomputes
    each slice of samples with autograd on and back-propagates ``grad_output`` through it at once.
    Values are those of ``replay=False`` (the plain autograd path, which keeps every sample's
    intermediates until backward) bit for bit, and gradients agree to float rounding. No double backward.

    max_batch_samples: pixel x sample pairs drawn from the generator at once (this sets which uniform goes
    to which sample, so it is part of the estimator for a seed). eval_batch_samples: pixel x sample pairs
    evaluated at once, in forward and when replaying (only memory and speed depend on it).

    grad_seed: None (default): the backward replays the forward's own samples, the exact gradient of the
    returned estimate. A seed: the backward draws independent samples from it instead, so the gradient is
    that of a second, independent estimate, decorrelated from the returned value (Mitsuba's ``seed_grad``).
    A loss's residual from the value then times that gradient is unbiased for |E[image] - target|^2 at the
    cost of one render, where replaying the same samples biases it towards low-variance (blurred) lights.

    compile: evaluate the samples (direction sampling, BRDF, light look-ups, MIS weights) through
    torch.compile: one fused loop per slice instead of ~100 tensor passes, forward and replay (~1.6x
    faster per render on CPU once compiled; the first render compiles for about a minute).

    native (default True): where it applies, evaluate each chunk of samples with dibrpp's C++ kernel
    (:mod:`dibrpp.native`) instead: CPU float32 G-buffers under an :class:`~dibrpp.lights.EnvMap`, when
    nothing but the env map needs a gradient (renders without gradients, and light estimation from images
    of known objects, e.g. Table B). Same samples, same values to float rounding; much faster than either
    PyTorch path and no compilation at run time. Elsewhere (CUDA, SG/SH lights, gradients w.r.t. shape or
    material) the PyTorch code runs.
    """

    def __init__(self, spp: int = 64, mis: bool = True, seed: int | None = None, max_batch_samples: int = 1 << 21,
                 replay: bool = True, eval_batch_samples: int = 1 << 18, compile: bool = False,
                 grad_seed: int | None = None, native: bool = True):
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        if grad_seed is not None and not replay:
            raise ValueError("grad_seed draws the backward's samples when replaying; it needs replay=True")
        self.spp, self.mis, self.seed = int(spp), bool(mis), seed
        self.max_batch_samples = max_batch_samples
        self.replay, self.eval_batch_samples = bool(replay), int(eval_batch_samples)
        self.compile, self.grad_seed, self.native = bool(compile), grad_seed, bool(native)

    def __call__(self, g: GBuffer, light) -> torch.Tensor:
        plan = _MCPlan(self, g, light)
        inputs = plan.inputs()
        if (self.replay and plan.replayable and torch.is_grad_enabled()
                and any(isinstance(t, torch.Tensor) and t.requires_grad for t in inputs)):
            return _MCReplay.apply(plan, *inputs)
        return plan.estimate(inputs)


def _default_generator(device: torch.device) -> torch.Generator | None:
    """The generator ``torch.rand(..., generator=None)`` draws from on ``device`` (None if unknown)."""
    if device.type == "cpu":
        return torch.default_generator
    if device.type == "cuda":
        return torch.cuda.default_generators[device.index if device.index is not None else torch.cuda.current_device()]
    return None


_POINT_FIELDS = ("normal", "view", "albedo", "alpha", "metallic", "specular")


class _MCPlan:
    """One MC estimate: the sample chunks, their random numbers, and the contribution of a chunk as a
    function of the differentiable inputs (G-buffer tensors, then the light's tensors)."""

    def __init__(self, shader: MCShader, g: GBuffer, light):
        p = g.point
        self.g, self.point, self.light = g, p, light
        self.n_pix = p.normal.shape[0]
        self.device = p.normal.device
        self.mis = shader.mis
        self.grad_seed = shader.grad_seed
        self.sample_terms = _sample_terms_compiled if shader.compile else _MCPlan.terms
        self.n_light = shader.spp // 2 if shader.mis else 0
        self.n_brdf = shader.spp - self.n_light
        self.chunk = max(1, shader.max_batch_samples // max(self.n_pix, 1))
        self.sub = max(1, shader.eval_batch_samples // max(self.n_pix, 1))
        self.chunks = ([("brdf", min(self.chunk, self.n_brdf - s0)) for s0 in range(0, self.n_brdf, self.chunk)]
                       + [("light", min(self.chunk, self.n_light - s0)) for s0 in range(0, self.n_light, self.chunk)])
        if shader.seed is not None:
            self.gen = torch.Generator(device=self.device)
            self.gen.manual_seed(shader.seed)
        else:
            self.gen = _default_generator(self.device)
            if self.gen is None:  # a device whose global generator we cannot snapshot: a private one, seeded from it
                self.gen = torch.Generator(device=self.device)
                self.gen.manual_seed(int(torch.randint(0, 2 ** 62, (1,), device=self.device)))
        self.states: list[torch.Tensor] = []  # generator state at the start of each chunk (filled by estimate)
        # lights are rebuilt around the function's inputs (Light.with_tensors). The env-map sampling tables
        # (from the detached image) are built once here and shared by every copy.
        self.light_fields: tuple[str, ...] = ()
        self.replayable = isinstance(light, Light) and self.n_pix > 0
        if self.replayable:
            self.light_fields = tuple(light.tensors())
            if self.mis and hasattr(light, "sampling_tables"):
                light.sampling_tables()
        self.kernel = self._native_kernel(shader.replay) if shader.native else None

    def _native_kernel(self, replay: bool):
        """dibrpp's C++ module where it computes this estimate (see :class:`MCShader`'s ``native``), else None.

        Its gradient (the env map's) exists only through :class:`_MCReplay`, hence ``replay``."""
        p, light = self.point, self.light
        points = [getattr(p, n) for n in _POINT_FIELDS]
        if not (isinstance(light, EnvMap) and self.n_pix > 0 and self.device.type == "cpu"
                and (replay or not light.image.requires_grad)
                and light.device.type == "cpu" and light.batch in (1, self.g.num_images)
                and all(t.dtype == torch.float32 and not t.requires_grad for t in points)
                and light.image.dtype == torch.float32
                and (light.world_to_light is None or not light.world_to_light.requires_grad)):
            return None
        return native.mc_envmap()

    def _native_chunk(self, kernel_fn, light, kind: str, u: torch.Tensor, *extra):
        """Call ``forward`` or ``backward_image`` of the C++ module on one chunk of uniforms."""
        p = self.point
        points = [getattr(p, n).contiguous() for n in _POINT_FIELDS]
        rot = light.world_to_light
        rot = light.image.new_zeros(0) if rot is None else rot.detach().contiguous()
        tables = []
        if self.mis:
            t = light.sampling_tables()
            tables = [t.cdf, t.row_cdf, t.pdf, t.cos_edges.contiguous()]
        return kernel_fn(points, self.g.batch.contiguous(), light.image.detach().contiguous(), rot, tables,
                         u.contiguous(), 0 if kind == "brdf" else 1, p.geometry == "smith", self.mis,
                         self.n_brdf, self.n_light, *extra)

    def inputs(self) -> list:
        return [getattr(self.point, n) for n in _POINT_FIELDS] + [getattr(self.light, n) for n in self.light_fields]

    def bind(self, inputs):
        """(ShadingPoint, light) built around ``inputs`` (same order as :meth:`inputs`)."""
        k = len(_POINT_FIELDS)
        point = dataclasses.replace(self.point, **dict(zip(_POINT_FIELDS, inputs[:k])))
        if not self.light_fields:
            return point, self.light
        return point, self.light.with_tensors(**dict(zip(self.light_fields, inputs[k:])))

    def draw(self, i: int, gen: torch.Generator) -> torch.Tensor:
        kind, s = self.chunks[i]
        return torch.rand((self.n_pix, s, 3 if kind == "brdf" else 2), device=self.device, generator=gen)

    def slices(self, i: int) -> list[slice]:
        """The sample slices of chunk ``i`` evaluated at once."""
        s = self.chunks[i][1]
        return [slice(a, min(s, a + self.sub)) for a in range(0, s, self.sub)]

    def terms(self, point, light, kind: str, u: torch.Tensor) -> torch.Tensor:
        """(N, S, 3) per-sample terms f L w for uniforms u (N, S, 3) ("brdf") or (N, S, 2) ("light")."""
        g = self.g
        shared = getattr(light, "batch", None) == 1
        lookup = lambda d: per_image(light.lookup, d, g.batch, g.num_images, shared)  # noqa: E731
        n_brdf, n_light = self.n_brdf, self.n_light

        def weight(dirs, pdf_brdf):
            if not self.mis:
                return 1.0 / (n_brdf * pdf_brdf).clamp_min(1e-12)
            light_pdf = per_image(light.pdf, dirs, g.batch, g.num_images, shared).detach()
            return 1.0 / (n_brdf * pdf_brdf + n_light * light_pdf).clamp_min(1e-12)

        if kind == "brdf":
            dirs = point.sample_directions(u)
        else:
            # env-map sampling: the tables are fixed (detached), directions carry no gradient
            with torch.no_grad():
                dirs = per_image(lambda uu: light.sample(uu)[0], u, g.batch, g.num_images, shared)
        f, pdf = point.eval_and_pdf(dirs)
        return f * lookup(dirs) * weight(dirs, pdf).unsqueeze(-1)

    def estimate(self, inputs) -> torch.Tensor:
        """The estimate (N, 3), drawing the chunks' uniforms in order and remembering the generator states."""
        point, light = self.bind(inputs)
        self.states = []
        total = point.normal.new_zeros(self.n_pix, 3)
        for i, (kind, _) in enumerate(self.chunks):
            self.states.append(self.gen.get_state())
            u = self.draw(i, self.gen)
            if self.kernel is not None:
                total = total + self._native_chunk(self.kernel.forward, light, kind, u)
                continue
            parts = [self.sample_terms(self, point, light, kind, u[:, sl]) for sl in self.slices(i)]
            # one sum over the chunk's samples: the same additions, whatever the slices
            total = total + (parts[0] if len(parts) == 1 else torch.cat(parts, 1)).sum(1)
        return total

    def backward_uniforms(self):
        """The uniforms of each chunk for the backward: the forward's again, or fresh ones from ``grad_seed``."""
        gen = torch.Generator(device=self.device)
        if self.grad_seed is not None:
            gen.manual_seed(self.grad_seed)
        for i in range(len(self.chunks)):
            if self.grad_seed is None:
                gen.set_state(self.states[i])
            yield self.draw(i, gen)


_sample_terms_compiled = CompiledOrEager(_MCPlan.terms)


class _MCReplay(torch.autograd.Function):
    """MC estimate whose backward replays the samples instead of storing them (see :class:`MCShader`)."""

    @staticmethod
    def forward(ctx, plan: _MCPlan, *inputs):
        out = plan.estimate(inputs)  # autograd is off inside forward: nothing per sample is kept
        ctx.plan = plan
        tensors = [t if isinstance(t, torch.Tensor) else None for t in inputs]
        ctx.save_for_backward(*tensors)
        ctx.others = [None if isinstance(t, torch.Tensor) else t for t in inputs]
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        plan: _MCPlan = ctx.plan
        saved = [o if t is None else t for t, o in zip(ctx.saved_tensors, ctx.others)]
        needs = ctx.needs_input_grad[1:]
        grads: list[torch.Tensor | None] = [None] * len(saved)
        if plan.kernel is not None:  # only the env map needs a gradient (checked by _native_kernel)
            image_at = len(_POINT_FIELDS) + plan.light_fields.index("image")
            _, light = plan.bind(saved)
            grad_out = grad_out.contiguous()
            for (kind, _), u in zip(plan.chunks, plan.backward_uniforms()):
                g = plan._native_chunk(plan.kernel.backward_image, light, kind, u, grad_out)
                grads[image_at] = g if grads[image_at] is None else grads[image_at] + g
            grads[image_at] = grads[image_at].reshape(saved[image_at].shape)
            return (None, *grads)
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(True) if need else t for t, need in zip(saved, needs)]
            wrt = [t for t, need in zip(leaves, needs) if need]
            where = [i for i, need in enumerate(needs) if need]
            point, light = plan.bind(leaves)
            for i, ((kind, _), u) in enumerate(zip(plan.chunks, plan.backward_uniforms())):
                for sl in plan.slices(i):
                    part = plan.sample_terms(plan, point, light, kind, u[:, sl]).sum(1)
                    got = torch.autograd.grad(part, wrt, grad_out, allow_unused=True)
                    for j, gr in zip(where, got):
                        if gr is not None:
                            grads[j] = gr if grads[j] is None else grads[j] + gr
        return (None, *grads)


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


def make_shader(name: str, spp: int = 64, mis: bool = True, seed: int | None = None, compile: bool = False,
                replay: bool = True):
    """Shader by method name: "mc", "sg", "sh" (SH light) or "sh-sg" (diffuse-only with SG light).

    replay: MC only, see :class:`MCShader` (False: the plain autograd path)."""
    if name == "mc":
        return MCShader(spp=spp, mis=mis, seed=seed, replay=replay, compile=compile)
    if name == "sg":
        return SGShader(compile)
    if name in ("sh", "sh-sg"):
        return SHShader(compile)
    raise ValueError(f"unknown shading {name!r}; choose mc, sg, sh or sh-sg")
