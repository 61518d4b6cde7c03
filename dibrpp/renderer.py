"""Rasterizer + deferred shader: the DIB-R++ renderer, batched over cameras and meshes."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .brdf import Material, ShadingPoint, alpha_from_roughness
from .camera import Cameras
from .jit import CompiledOrEager
from .mesh import Meshes
from .raster import Fragments, RasterSettings, rasterize, sample_texture
from .shading import GBuffer, make_shader


@dataclass
class RenderOutput:
    """A render: ``image`` (B, H, W, 4) linear RGB + alpha.

    alpha: the anti-aliased coverage (``Fragments.coverage``), which matches Cycles' film-transparent
    alpha (Blackman-Harris 1.5 px). RGB: with ``visibility="dibr"`` the hard-coverage render (0 where
    no pixel centre is covered); with ``"edge_aa"`` premultiplied by the coverage, like Cycles' RGB.
    For a silhouette loss read :attr:`silhouette`, not ``alpha``.
    """

    image: torch.Tensor  # (B, H, W, 4)
    fragments: Fragments
    gbuffer: GBuffer

    @property
    def rgb(self) -> torch.Tensor:
        return self.image[..., :3]

    @property
    def alpha(self) -> torch.Tensor:
        """(B, H, W) anti-aliased coverage (the image's alpha channel)."""
        return self.image[..., 3]

    @property
    def soft_mask(self) -> torch.Tensor:
        """(B, H, W) DIB-R soft silhouette (the hard mask when it was not computed, e.g. with "edge_aa")."""
        return self.fragments.soft_mask

    @property
    def silhouette(self) -> torch.Tensor:
        """(B, H, W) what a silhouette (IoU) loss should read: the soft mask ("dibr") or the coverage ("edge_aa")."""
        return self.fragments.silhouette


def shading_albedo(material: Material, meshes: Meshes, frags: Fragments) -> torch.Tensor:
    """(N, 3) linear base colour of the covered pixels: texture lookup at interpolated UVs, or constant."""
    if material.is_texture:
        if not meshes.has_uvs:
            raise ValueError("a texture needs a mesh with UVs (uvs and face_uvs)")
        uv = frags.interpolate(meshes.uvs, meshes.face_uvs)
        tex = material.albedo
        tb = frags.batch if tex.shape[0] > 1 else torch.zeros_like(frags.batch)
        return sample_texture(tex, uv, tb, wrap_u=material.wrap_u)
    albedo = material.albedo.reshape(-1, 3).to(frags.bary)
    return albedo[frags.batch] if albedo.shape[0] > 1 else albedo.expand(frags.batch.shape[0], 3)


def build_gbuffer(meshes: Meshes, cameras: Cameras, material: Material, frags: Fragments) -> GBuffer:
    meshes = meshes.expand(len(cameras))
    position = frags.interpolate(meshes.verts, meshes.faces)
    normal = torch.nn.functional.normalize(frags.interpolate(meshes.vertex_normals(), meshes.faces), dim=-1, eps=1e-12)
    view = torch.nn.functional.normalize(cameras.centers.to(position)[frags.batch] - position, dim=-1, eps=1e-12)
    # Two-sided surfaces: a visible back face is shaded with its normal turned towards the viewer.
    geo = meshes.face_normals()[frags.batch, frags.pix_face]
    facing = torch.where((geo * view).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(normal)
    normal = bend_towards_view(normal * facing, view)
    opts = material.options
    scalar = lambda name: material.scalar(name, frags.batch, position.dtype)  # noqa: E731
    point = ShadingPoint(
        normal=normal,
        view=view,
        albedo=shading_albedo(material, meshes, frags),
        alpha=alpha_from_roughness(scalar("roughness"), opts.roughness_map),
        metallic=scalar("metallic").clamp(0, 1),
        specular=scalar("specular").clamp_min(0),
        geometry=opts.geometry,
    )
    return GBuffer(point, frags.batch, len(cameras))


# ~10 gathers and elementwise passes over the covered pixels, fused (forward ~3x, backward ~6x faster on CPU)
build_gbuffer_compiled = CompiledOrEager(build_gbuffer)


def bend_towards_view(normal: torch.Tensor, view: torch.Tensor, min_cos: float = 0.02) -> torch.Tensor:
    """Tilt interpolated normals that face away from the viewer (near silhouettes) until n.v = min_cos.

    Interpolated vertex normals can point away from the camera on visible faces; the BRDF is undefined
    there (Cycles bends such normals the same way).
    """
    n_dot_v = (normal * view).sum(-1, keepdim=True)
    tangent = torch.nn.functional.normalize(normal - n_dot_v * view, dim=-1, eps=1e-12)
    bent = min_cos * view + math.sqrt(1 - min_cos ** 2) * tangent
    return torch.where(n_dot_v < min_cos, bent, normal)


class Renderer:
    """``Renderer(shading)(meshes, cameras, material, light)`` -> :class:`RenderOutput`.

    shading: "mc" | "sg" | "sh" | "sh-sg" or a shader object. Works on whatever device the inputs are on.
    compile: the G-buffer (positions, normals, texture look-ups) and the shading (SG/SH product integrals,
        MC samples) through torch.compile (see :class:`~dibrpp.shading.SGShader`, :class:`~dibrpp.shading.MCShader`):
        the same values to float rounding, much faster once compiled (the first render compiles for tens of
        seconds, MC about a minute). Worth it for training and benchmarks, not for one render.
    """

    def __init__(self, shading="sg", spp: int = 64, mis: bool = True, seed: int | None = None,
                 raster_settings: RasterSettings | None = None, compile: bool = False):
        self.shader = (make_shader(shading, spp=spp, mis=mis, seed=seed, compile=compile)
                       if isinstance(shading, str) else shading)
        self.raster_settings = raster_settings or RasterSettings()
        self.build_gbuffer = build_gbuffer_compiled if compile else build_gbuffer

    def rasterize(self, meshes: Meshes, cameras: Cameras) -> Fragments:
        return rasterize(meshes, cameras, self.raster_settings)

    def __call__(self, meshes: Meshes, cameras: Cameras, material: Material, light, fragments: Fragments | None = None) -> RenderOutput:
        frags = fragments if fragments is not None else self.rasterize(meshes, cameras)
        return self.shade(frags, self.build_gbuffer(meshes, cameras, material, frags), light)

    def gbuffer(self, meshes: Meshes, cameras: Cameras, material: Material) -> tuple[Fragments, GBuffer]:
        """Rasterize and build the G-buffer: everything of a render that does not depend on the light."""
        frags = self.rasterize(meshes, cameras)
        return frags, self.build_gbuffer(meshes, cameras, material, frags)

    def gbuffer_of_images(self, meshes: Meshes, cameras: Cameras, material: Material,
                          images: torch.Tensor) -> tuple[Fragments, GBuffer]:
        """:meth:`gbuffer` of the B renders, repeated as ``images`` (M,) lists them (indices into B): a render
        shaded under several lights is rasterized once."""
        frags, g = self.gbuffer(meshes, cameras, material)
        selected, order = frags.select_images(images)
        return selected, g.select(order, selected.batch, len(images))

    def shade(self, frags: Fragments, g: GBuffer, light) -> RenderOutput:
        """Shade a G-buffer under ``light``. With fixed geometry, camera and material (e.g. optimising only
        the light) rasterize once with :meth:`gbuffer` and shade it every step."""
        return RenderOutput(_compose(frags, self.shader(g, light)), frags, g)

    def render_albedo(self, meshes: Meshes, cameras: Cameras, material: Material) -> RenderOutput:
        """Unlit base colour (the texture metric's input), alpha = coverage."""
        frags = self.rasterize(meshes, cameras)
        g = build_gbuffer(meshes, cameras, material, frags)
        return RenderOutput(_compose(frags, g.point.albedo), frags, g)

    def render_normals(self, meshes: Meshes, cameras: Cameras) -> RenderOutput:
        """World-space shading normals (no lighting), alpha = coverage."""
        frags = self.rasterize(meshes, cameras)
        g = build_gbuffer(meshes, cameras, Material(albedo=torch.ones(1, 3, device=frags.bary.device)), frags)
        return RenderOutput(_compose(frags, g.point.normal), frags, g)


def _compose(frags: Fragments, rgb_packed: torch.Tensor) -> torch.Tensor:
    """RGB + coverage alpha; "edge_aa" blends the outline's pixels with the (black) background by the coverage."""
    rgb = frags.antialias(rgb_packed) if frags.visibility == "edge_aa" else frags.to_image(rgb_packed)
    return torch.cat([rgb, frags.alpha.unsqueeze(-1).to(rgb.dtype)], -1)
