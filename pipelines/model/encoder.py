"""The single-image encoder of DIB-R++ (Sec. E.1): shape, texture, material and light from one image.

Shape, texture and material are predicted in the canonical (world) frame; light in the frame of the
input camera (:meth:`Prediction.light` rotates it into the world with the camera's rotation).

What differs from a plain "global vector -> fully connected heads" encoder, and why:

- **Shape** = template sphere scaled per axis, plus bounded per-vertex offsets, made left/right
  symmetric (cars and heads are mirror-symmetric about the XZ plane). The scale reaches every object's
  extent (half-sides 3-21 world units against the data's 4-18), which a capped offset alone could not.
- **Material** heads reach the ends of their ranges at finite logits (specular and metallic are exactly 0
  or 1 in the data), and roughness starts where the BRDF's alpha floor starts, so its whole range has
  gradient.
- **Texture** reads the input image: every texel of the predicted surface is projected into the input
  view, and a small network maps what it sees there (colour, features, whether it faces the camera) plus
  a global code to the albedo. A texture decoded from one global vector has to memorise colours.
- **Light** is white-balanced (its mean radiance over the sphere is grey), so the one colour
  degree of freedom a diffuse image cannot tell apart -- a tinted light on a paint vs. the tint in the
  paint -- goes to the albedo (docs/results.md#light-and-albedo-colour).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import nn

from dibrpp.brdf import MIN_ALPHA
from dibrpp.camera import Cameras
from dibrpp.mesh import Meshes, icosphere, vertex_normals

from .light_probe import ProbeLightHead, facing_mirror_cue, pixel_samples, probe_grid, world_to_probe
from .model_input import MAX_LOG_RADIANCE, clip_input, input_grid, input_radiance
from .pixel_normals import PixelNormalNet
from .prediction import LIGHT_KINDS, Prediction, white_balance
from .template import mirror_index, texel_barycentrics

MODEL_VERSION = 9  # bump when parameters or their meaning change (training.earlier_runs reads version 8)
MAX_SHARPNESS = 3000.0  # SG lobes no narrower than ~1 degree (a sun)

# the allowed values of the model's string options
CHOICES = {"texture": ("projected", "global"), "light_colour": ("white", "free", "sky-ground"),
           "light_head": ("global", "probe"),
           "input_range": ("full", "clipped"), "probe_normals": ("surface", "pixels"), "specular": ("learnt", "fixed")}
# Principled's Specular IOR Level whose F0 is 0.04 (IOR 1.5): the metallic-roughness convention's dielectric
DIELECTRIC_SPECULAR = 0.5


@dataclass
class ModelConfig:
    shading: str = "sg"  # mc | sg | sh | sh-sg
    lobes: int = 32  # SG lobes
    image_size: int = 64
    template_subdivisions: int = 3  # 642 vertices
    template_radius: float = 12.0  # objects are normalised to [-18, 18]
    scale_range: tuple[float, float] = (0.25, 1.75)  # per-axis scale of the template (half-sides 3..21)
    max_offset: float = 6.0  # bound of a vertex offset after scaling (world units)
    symmetric: bool = True  # mirror symmetry about the XZ plane (y -> -y)
    texture_height: int = 32
    texture_width: int = 64
    texture: str = "projected"  # projected: looks the input image up | global: decoded from the global code
    # white: white-balanced light | free: any colour | sky-ground: white-balanced, and the probe head's sky tinted by
    # a colour above the horizon and one below (ProbeLightHead.hemisphere_colour; as white with the global head)
    light_colour: str = "white"
    # global: the light regressed from the global code | probe: read from the input through the predicted
    # geometry (pipelines.model.light_probe), in the probe frame
    light_head: str = "global"
    # what the encoder sees of the input: its full range (an EXR's sun reflections; :func:`encoder_input`) or
    # clipped at 1, as an 8-bit picture shows it
    input_range: str = "full"
    # the normals the probe head's mirror cue reads: the predicted surface's, or, in evaluation (not in training),
    # an image-space network's (pipelines.model.pixel_normals, fitted to the GT mesh's)
    probe_normals: str = "surface"
    env_height: int = 16
    env_width: int = 32
    predict_metallic: bool = False
    roughness_range: tuple[float, float] = (math.sqrt(MIN_ALPHA), 1.0)
    # fixed: DIELECTRIC_SPECULAR for every object | learnt: the specular level from the global code (a metal's
    # reflectance is its albedo either way)
    specular: str = "fixed"
    width: int = 32  # channels of the first conv layer
    # side of the feature map the global code is read from: 0 for the image side / 16 (4 at 64², 8 at 128²), or
    # at most this side, one more downsampling block per halving (the fully connected layer's size then stays the same)
    global_grid: int = 0

    def validate(self) -> None:
        if self.shading not in LIGHT_KINDS:
            raise ValueError(f"unknown shading {self.shading!r}; choose from {sorted(LIGHT_KINDS)}")
        if self.image_size % 16:
            raise ValueError(f"image_size must be a multiple of 16, got {self.image_size}")
        for name, allowed in CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be {' or '.join(map(repr, allowed))}, got {getattr(self, name)!r}")
        if self.light_head == "probe" and self.shading == "sh":
            raise ValueError("the probe light head predicts SG lobes or env maps, not SH")
        if self.probe_normals == "pixels" and self.light_head != "probe":
            raise ValueError("probe_normals 'pixels' gives the probe head's pixels their normals; use it with "
                             "light_head 'probe'")

    def grid_side(self) -> int:
        """The side of the feature map the global code is read from: the image side / 16, halved (one more
        downsampling block each) while it is even and above ``global_grid``."""
        side = self.image_size // 16
        while self.global_grid and side > self.global_grid and side % 2 == 0:
            side //= 2
        return side

    def to_dict(self) -> dict:
        return {"version": MODEL_VERSION, **asdict(self)}

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        if d.get("version") != MODEL_VERSION:
            raise ValueError(f"the checkpoint was written by model version {d.get('version')}, this code reads version "
                             f"{MODEL_VERSION}; retrain it (e.g. `make train-glossy`)")
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names - {"version"}
        if unknown:
            raise ValueError(f"the checkpoint's model configuration has unknown fields {sorted(unknown)}")
        tuples = {"scale_range", "roughness_range"}
        d = {"specular": "learnt", **d}  # a model written before the option learnt its specular level
        return cls(**{k: tuple(v) if k in tuples else v for k, v in d.items() if k in names})


def squash(x: torch.Tensor, lo: float = 0.0, hi: float = 1.0, margin: float = 0.05) -> torch.Tensor:
    """A sigmoid onto [lo, hi] that reaches both ends at finite x (it overshoots by ``margin`` and is clamped)."""
    t = (1 + 2 * margin) * torch.sigmoid(x) - margin
    return lo + (hi - lo) * t.clamp(0, 1)


def _inverse_softplus(value: torch.Tensor) -> torch.Tensor:
    return value.expm1().log()


@dataclass
class TexelView:
    """The texels of the predicted surface seen from the input camera: how squarely each faces the camera (B, T;
    0: away), and where it projects (B, Ht, Wt, 2; grid_sample coordinates)."""
    facing: torch.Tensor
    grid: torch.Tensor


def _down_block(cin, cout):
    return nn.Sequential(nn.Conv2d(cin, cout, 4, 2, 1), nn.GroupNorm(8, cout), nn.LeakyReLU(0.2, inplace=True))


class Encoder(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        config.validate()
        self.config = c = config
        w = c.width
        self.stem = _down_block(4, w)  # (w, S/2, S/2): kept for the texture's image look-up
        grid = c.grid_side()
        extra = [_down_block(8 * w, 8 * w) for _ in range(int(math.log2(c.image_size // 16 // grid)))]  # one per halving
        self.backbone = nn.Sequential(_down_block(w, 2 * w), _down_block(2 * w, 4 * w), _down_block(4 * w, 8 * w), *extra)
        feat = 8 * w * grid ** 2
        self.fc = nn.Sequential(nn.Flatten(), nn.Linear(feat, 512), nn.LeakyReLU(0.2, inplace=True))
        template = icosphere(c.template_subdivisions, radius=1.0)
        self.register_buffer("template_dirs", template.verts)  # unit sphere
        self.register_buffer("faces", template.faces)
        self.register_buffer("uvs", template.uvs)
        self.register_buffer("face_uvs", template.face_uvs)
        self.register_buffer("mirror", mirror_index(template.verts[0]))
        face, bary = texel_barycentrics(template, c.texture_height, c.texture_width)
        self.register_buffer("texel_face", face)
        self.register_buffer("texel_bary", bary)
        n_verts = template.verts.shape[1]
        self.shape_head = nn.Linear(512, n_verts * 3 + 3)  # offsets + per-axis scale (a sigmoid onto scale_range)
        th, tw = c.texture_height // 8, c.texture_width // 8
        self.tex_fc = nn.Linear(512, 4 * w * th * tw)
        self.tex_dec = nn.Sequential(
            nn.Upsample(scale_factor=2), nn.Conv2d(4 * w, 2 * w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True),
            nn.Upsample(scale_factor=2), nn.Conv2d(2 * w, w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True),
            nn.Upsample(scale_factor=2), nn.Conv2d(w, w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True))
        fused = w + (4 + w + 1 if c.texture == "projected" else 0)
        self.tex_out = nn.Sequential(nn.Conv2d(fused, w, 3, 1, 1), nn.LeakyReLU(0.2, inplace=True),
                                     nn.Conv2d(w, 3, 3, 1, 1))
        self.material_head = nn.Linear(512, 3)
        if c.probe_normals == "pixels":
            with torch.random.fork_rng(devices=[]):  # its own draws: every other weight starts as the default's
                self.pixel_normals = PixelNormalNet()
        kind = LIGHT_KINDS[c.shading]
        if c.light_head == "probe":
            self.light_head = ProbeLightHead(kind, c.lobes, c.env_height, c.env_width, MAX_SHARPNESS, MAX_LOG_RADIANCE,
                                             sky_ground=c.light_colour == "sky-ground")
        else:
            light_out = {"sg": c.lobes * 7, "sh": 27, "env": c.env_height * c.env_width * 3}[kind]
            self.light_head = nn.Linear(512, light_out)
        self._init_heads()

    def _init_heads(self):
        c = self.config
        nn.init.zeros_(self.shape_head.weight)
        nn.init.zeros_(self.shape_head.bias)
        with torch.no_grad():  # start at the template radius: the scale logit that gives scale 1
            lo, hi = c.scale_range
            self.shape_head.bias[-3:] = torch.logit(torch.tensor((1.0 - lo) / (hi - lo)))
        if c.light_head == "probe":
            return  # ProbeLightHead starts at the projected map
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
                sharpness, amplitude = max(2.0, 0.5 * k ** 0.5 * 4), F.softplus(torch.tensor(-2.0))
                b[:, 3], b[:, 4:] = _inverse_softplus(torch.tensor(sharpness)), _inverse_softplus(amplitude)
            elif kind == "sh":
                self.light_head.bias.view(9, 3)[0] = 1.5  # ambient start
            else:
                self.light_head.bias.fill_(float(_inverse_softplus(F.softplus(torch.tensor(-0.5)))))

    def template(self) -> Meshes:
        return Meshes(self.template_dirs, self.faces, self.uvs, self.face_uvs)

    def _shape(self, raw: torch.Tensor) -> torch.Tensor:
        c = self.config
        b = raw.shape[0]
        lo, hi = c.scale_range
        scale = c.template_radius * (lo + (hi - lo) * torch.sigmoid(raw[:, -3:]))  # (B, 3)
        offsets = c.max_offset * torch.tanh(raw[:, :-3].view(b, -1, 3) / c.max_offset)
        if c.symmetric:
            offsets = 0.5 * (offsets + offsets[:, self.mirror] * offsets.new_tensor([1.0, -1.0, 1.0]))
        return self.template_dirs * scale.unsqueeze(1) + offsets

    def _texture(self, f: torch.Tensor, stem: torch.Tensor, images: torch.Tensor,
                 texels: "TexelView | None") -> tuple[torch.Tensor, torch.Tensor | None]:
        """Linear albedo (B, Ht, Wt, 3) in (0, 1), and the texels' facing of the input camera (projected only)."""
        c = self.config
        b, th, tw = f.shape[0], c.texture_height // 8, c.texture_width // 8
        feats, facing = [self.tex_dec(self.tex_fc(f).view(b, -1, th, tw))], None
        if c.texture == "projected":
            feats.append(self._projected(stem, images, texels))
            facing = feats[-1][:, -1]
        return torch.sigmoid(self.tex_out(torch.cat(feats, 1))).permute(0, 2, 3, 1), facing

    def _texel_view(self, verts: torch.Tensor, cameras: Cameras | None) -> "TexelView":
        """Where each texel of the predicted surface lies in the input view, and which way it faces."""
        if cameras is None:
            raise ValueError("a projected texture needs the input cameras: call the encoder with cameras=...")
        c = self.config
        b = verts.shape[0]
        corners = self.faces[self.texel_face]  # (T, 3) vertex indices
        weights = self.texel_bary[None, :, :, None]
        pos = (verts[:, corners] * weights).sum(2)
        nrm = F.normalize((vertex_normals(verts, self.faces)[:, corners] * weights).sum(2), dim=-1, eps=1e-12)
        to_cam = F.normalize(cameras.centers.to(pos).unsqueeze(1) - pos, dim=-1)
        facing = (nrm * to_cam).sum(-1).clamp_min(0)
        grid = input_grid(pos, cameras).view(b, c.texture_height, c.texture_width, 2)
        return TexelView(facing, grid)

    def _projected(self, stem, images, texels: "TexelView") -> torch.Tensor:
        """What the input view shows at each texel of the predicted surface: colour and alpha, stem
        features, and how squarely the texel faces the camera (0 where it faces away)."""
        c = self.config
        b = images.shape[0]
        seen = torch.cat([F.grid_sample(images, texels.grid, align_corners=False, padding_mode="zeros"),
                          F.grid_sample(stem, texels.grid, align_corners=False, padding_mode="zeros")], 1)
        facing = texels.facing.view(b, 1, c.texture_height, c.texture_width)
        return torch.cat([seen * (facing > 0), facing], 1)

    def _probe_light(self, images: torch.Tensor, verts: torch.Tensor, cameras: Cameras, code: torch.Tensor,
                     metallic: torch.Tensor, pixel_normals: torch.Tensor | None = None) -> dict:
        """The light read from the input through the predicted surface (pipelines.model.light_probe); ``pixel_normals``
        (B, S, S, 3): the normals its pixels read instead of the surface's (held: fitted apart from the model)."""
        b = images.shape[0]
        normals, to_camera, radiance, weight = pixel_samples(self.template().with_verts(verts), cameras,
                                                             *input_radiance(images))
        if pixel_normals is not None:
            normals = torch.where(weight.unsqueeze(-1) > 0, pixel_normals.detach().flatten(1, 2), normals)
        return self.light_from_samples(normals, to_camera, radiance, weight,
                                       cameras.world_to_camera.to(images).expand(b, 4, 4), code, metallic)

    def light_from_samples(self, normals: torch.Tensor, to_camera: torch.Tensor, radiance: torch.Tensor,
                           weight: torch.Tensor, world_to_camera: torch.Tensor, code: torch.Tensor,
                           metallic: torch.Tensor) -> dict:
        """The probe head's light from surface samples (light_probe.probe_grid's arguments) and the global code."""
        h, w = self.config.env_height, self.config.env_width
        grid = probe_grid(normals, to_camera, radiance, weight, world_to_camera, h, w)
        sun_grid = facing_mirror_cue(normals, to_camera, radiance, weight, world_to_camera, h, w)
        return self.light_head(grid, code, world_to_probe(world_to_camera).mT, metallic, sun_grid)

    def material_parameters(self, code: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B,) roughness, specular and metallic (0 unless the model predicts it) from the global code."""
        mat = self.material_head(code)
        lo, hi = self.config.roughness_range
        metallic = squash(mat[:, 2]) if self.config.predict_metallic else torch.zeros_like(mat[:, 2])
        learnt = self.config.specular == "learnt"
        specular = squash(mat[:, 1]) if learnt else torch.full_like(mat[:, 1], DIELECTRIC_SPECULAR)
        return squash(mat[:, 0], lo, hi), specular, metallic

    def visible_input(self, images: torch.Tensor) -> torch.Tensor:
        """The part of :func:`encoder_input` images this model reads (clipped at 1 unless it reads the full range)."""
        return images if self.config.input_range == "full" else clip_input(images)

    def forward(self, images: torch.Tensor, cameras: Cameras | None = None) -> Prediction:
        """images: (B, 4, S, S) from :func:`pipelines.model.model_input.encoder_input`; cameras: the B input views (needed by the
        projected texture and the probe light head)."""
        c = self.config
        images = self.visible_input(images)
        stem = self.stem(images)
        f = self.fc(self.backbone(stem))
        verts = self._shape(self.shape_head(f))
        texels = self._texel_view(verts.detach(), cameras) if c.texture == "projected" else None
        texture, facing = self._texture(f, stem, images, texels)
        roughness, specular, metallic = self.material_parameters(f)
        kind = LIGHT_KINDS[c.shading]
        pixel_normals = None
        # read in evaluation only: read in training too, the light is fitted to the rounded mesh it is rendered
        # through, and the probes and the albedo get worse (docs/experiments.md, entry 35)
        if c.probe_normals == "pixels" and not self.training:
            pixel_normals = self.pixel_normals(images, cameras.world_to_camera.to(images).expand(images.shape[0], 4, 4))
        if c.light_head == "probe":
            if cameras is None:
                raise ValueError("the probe light head needs the input cameras: call the encoder with cameras=...")
            light = self._probe_light(images, verts.detach(), cameras, f, metallic, pixel_normals)
        else:
            light = self._light_from_code(f)
        if c.light_colour != "free":
            light = white_balance(light, kind)
        return Prediction(verts, texture, roughness, specular, metallic, light, c, self.template(), facing, pixel_normals)

    def _light_from_code(self, f: torch.Tensor) -> dict:
        """The light regressed from the global code (the paper's head)."""
        c = self.config
        b = f.shape[0]
        raw = self.light_head(f)
        kind = LIGHT_KINDS[c.shading]
        if kind == "sg":
            raw = raw.view(b, c.lobes, 7)
            light = {"axis": F.normalize(raw[..., :3], dim=-1, eps=1e-6),
                     "sharpness": (F.softplus(raw[..., 3]) + 0.5).clamp_max(MAX_SHARPNESS),
                     "amplitude": F.softplus(raw[..., 4:])}
        elif kind == "sh":
            light = {"coeffs": raw.view(b, 9, 3)}
        else:
            light = {"image": F.softplus(raw.view(b, c.env_height, c.env_width, 3))}
        return light
