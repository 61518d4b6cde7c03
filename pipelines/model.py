"""The single-image encoder of DIB-R++ (Sec. E.1): shape, texture, material and light from one image.

Shape, texture and material are predicted in the canonical (world) frame; light in the frame of the
input camera (the renderer rotates it back with the camera's rotation).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from dibrpp.brdf import Material
from dibrpp.lights import EnvMap, SGLight, SHLight
from dibrpp.mesh import Meshes, icosphere

LIGHT_KINDS = {"mc": "env", "sg": "sg", "sh": "sh", "sh-sg": "sg"}


@dataclass
class ModelConfig:
    shading: str = "sg"  # mc | sg | sh | sh-sg
    lobes: int = 32  # SG lobes
    image_size: int = 64
    template_subdivisions: int = 3  # 642 vertices
    template_radius: float = 12.0  # objects are normalised to [-18, 18]
    max_offset: float = 12.0  # bound of a vertex offset (world units)
    texture_height: int = 32
    texture_width: int = 64
    env_height: int = 16
    env_width: int = 32
    predict_metallic: bool = False
    roughness_range: tuple[float, float] = (0.02, 0.8)
    width: int = 32  # channels of the first conv layer


def _conv(cin, cout):
    return nn.Sequential(nn.Conv2d(cin, cout, 4, 2, 1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2, inplace=True))


class Prediction:
    """What the encoder predicts for a batch of B images; converts to renderer objects."""

    def __init__(self, offsets, texture, roughness, specular, metallic, light_params, config: ModelConfig, template: Meshes):
        self.offsets, self.texture = offsets, texture
        self.roughness, self.specular, self.metallic = roughness, specular, metallic
        self.light_params, self.config, self.template = light_params, config, template

    def meshes(self) -> Meshes:
        return self.template.with_verts(self.template.verts + self.offsets)

    def material(self) -> Material:
        return Material(albedo=self.texture, roughness=self.roughness, metallic=self.metallic,
                        specular=self.specular, wrap_u=True)

    def light(self):
        """The light in the input camera's frame (no rotation set)."""
        p = self.light_params
        kind = LIGHT_KINDS[self.config.shading]
        if kind == "sg":
            return SGLight(p["axis"], p["sharpness"], p["amplitude"])
        if kind == "sh":
            return SHLight(p["coeffs"])
        return EnvMap(p["image"])

    def select(self, idx) -> "Prediction":
        pick = lambda t: t[idx]  # noqa: E731
        return Prediction(pick(self.offsets), pick(self.texture), pick(self.roughness), pick(self.specular),
                          pick(self.metallic), {k: pick(v) for k, v in self.light_params.items()}, self.config, self.template)


class Encoder(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = c = config
        if c.shading not in LIGHT_KINDS:
            raise ValueError(f"unknown shading {c.shading!r}; choose from {sorted(LIGHT_KINDS)}")
        if c.image_size % 16:
            raise ValueError("image_size must be a multiple of 16")
        w = c.width
        self.backbone = nn.Sequential(_conv(4, w), _conv(w, 2 * w), _conv(2 * w, 4 * w), _conv(4 * w, 8 * w))
        feat = 8 * w * (c.image_size // 16) ** 2
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(feat, 512), nn.LeakyReLU(0.2, inplace=True))
        template = icosphere(c.template_subdivisions, radius=c.template_radius)
        self.register_buffer("template_verts", template.verts)
        self.register_buffer("faces", template.faces)
        self.register_buffer("uvs", template.uvs)
        self.register_buffer("face_uvs", template.face_uvs)
        n_verts = template.verts.shape[1]
        self.shape_head = nn.Linear(512, n_verts * 3)
        th, tw = c.texture_height // 8, c.texture_width // 8
        self.tex_fc = nn.Linear(512, 4 * w * th * tw)
        self.tex_dec = nn.Sequential(
            nn.Upsample(scale_factor=2), nn.Conv2d(4 * w, 2 * w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True),
            nn.Upsample(scale_factor=2), nn.Conv2d(2 * w, w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True),
            nn.Upsample(scale_factor=2), nn.Conv2d(w, 3, 3, 1, 1))
        self.material_head = nn.Linear(512, 3)
        kind = LIGHT_KINDS[c.shading]
        light_out = {"sg": c.lobes * 7, "sh": 27, "env": c.env_height * c.env_width * 3}[kind]
        self.light_head = nn.Linear(512, light_out)
        self._init_heads()

    def _init_heads(self):
        c = self.config
        for head in (self.shape_head,):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        nn.init.normal_(self.light_head.weight, std=1e-3)
        nn.init.zeros_(self.light_head.bias)
        kind = LIGHT_KINDS[c.shading]
        with torch.no_grad():
            if kind == "sg":
                # lobes start spread over the sphere (Fibonacci), moderately sharp, dim
                k = c.lobes
                i = torch.arange(k, dtype=torch.float32) + 0.5
                z = 1 - 2 * i / k
                phi = math.pi * (1 + 5 ** 0.5) * i
                axes = torch.stack([torch.sqrt(1 - z * z) * torch.cos(phi), torch.sqrt(1 - z * z) * torch.sin(phi), z], -1)
                b = self.light_head.bias.view(k, 7)
                b[:, :3] = axes
                b[:, 3] = math.log(math.expm1(max(2.0, 0.5 * k ** 0.5 * 4)))  # softplus^-1 of the sharpness
                b[:, 4:] = -2.0
            elif kind == "sh":
                self.light_head.bias.view(9, 3)[0] = 1.5  # ambient start
            else:
                self.light_head.bias.fill_(-0.5)

    def template(self) -> Meshes:
        return Meshes(self.template_verts, self.faces, self.uvs, self.face_uvs)

    def forward(self, images: torch.Tensor) -> Prediction:
        """images: (B, 4, S, S) sRGB-encoded RGB + alpha in [0, 1]."""
        c = self.config
        f = self.fc(self.backbone(images))
        b = images.shape[0]
        offsets = c.max_offset * torch.tanh(self.shape_head(f).view(b, -1, 3) / c.max_offset * 4) / 4
        t = self.tex_fc(f).view(b, -1, c.texture_height // 8, c.texture_width // 8)
        texture = torch.sigmoid(self.tex_dec(t)).permute(0, 2, 3, 1)  # linear albedo in (0, 1)
        mat = torch.sigmoid(self.material_head(f))
        lo, hi = c.roughness_range
        roughness = lo + (hi - lo) * mat[:, 0]
        specular = mat[:, 1]
        metallic = mat[:, 2] if c.predict_metallic else torch.zeros_like(mat[:, 2])
        raw = self.light_head(f)
        kind = LIGHT_KINDS[c.shading]
        if kind == "sg":
            raw = raw.view(b, c.lobes, 7)
            light = {"axis": torch.nn.functional.normalize(raw[..., :3], dim=-1, eps=1e-6),
                     "sharpness": torch.nn.functional.softplus(raw[..., 3]) + 0.5,
                     "amplitude": torch.nn.functional.softplus(raw[..., 4:])}
        elif kind == "sh":
            light = {"coeffs": raw.view(b, 9, 3)}
        else:
            light = {"image": torch.nn.functional.softplus(raw.view(b, c.env_height, c.env_width, 3))}
        return Prediction(offsets, texture, roughness, specular, metallic, light, c, self.template())
