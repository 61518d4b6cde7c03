"""A learned space of environment maps: a small latent decoded to an equirect HDR map, learnt on maps alone.

After Weber et al. (*Learning to Estimate Indoor Lighting from 3D Objects*, 3DV 2018) and Hold-Geoffroy et al. (*Deep
Sky Modeling for Single Image Outdoor Lighting Estimation*, CVPR 2019): an autoencoder learns the procedural skies and
rooms (``python -m datagen.envmap_set``; ``python -m pipelines.light_space``), and the light head predicts a point of
its latent (``light_head="space"``), so every light it can give is a map of that kind -- a sky brighter and bluer than
its ground, a room's windows -- instead of any sum of lobes.

Maps are read at the probe grid's size (16 x 32, the area average over solid angle of the data's 64 x 128) as log
radiance, in a frame whose pole is the world's up and whose azimuth is free (the set is augmented by every turn about
up and by mirroring, so the latent learns no preferred azimuth). The sun is a cell of that grid; the head's own sun
lobe (:class:`~pipelines.model.light_probe.ProbeLightHead`) sharpens it where the image shows it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dibrpp import conventions

LOG_EPS = 1e-3  # radiance floor of the log map (as the probe grid's)
# the head's latent stays within this many of the prior's standard deviations per dimension, where the decoder has seen maps
LATENT_BOUND = 3.0
FILE = "light_space.pt"


@dataclass(frozen=True)
class SpaceConfig:
    latent: int = 16
    height: int = 16
    width: int = 32
    channels: int = 32


def _pad(x: torch.Tensor) -> torch.Tensor:
    """Wrap-around in azimuth, replicate at the poles (one cell each side)."""
    return F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1), mode="replicate")


def _with_height(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) features with each cell's height on the sphere (the z of its centre) as one more channel."""
    h, w = x.shape[2:]
    z = conventions.equirect_directions(h, 1, x.device, x.dtype)[:, 0, 2]
    return torch.cat([x, z.view(1, 1, h, 1).expand(x.shape[0], 1, h, w)], 1)


class _Conv(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 3, stride)

    def forward(self, x):
        return F.leaky_relu(self.conv(_pad(x)), 0.2)


class LightSpace(nn.Module):
    """Encoder (log map -> mean and log-variance of the latent) and decoder (latent -> log map), a VAE whose small KL
    weight keeps the latent's every point near a map of the set. The decoder's convolutions see each cell's height
    (sin elevation) beside its features, so what it draws can depend on elevation (sky, horizon, ground) while a turn
    of the features about up stays a turn of the map."""

    def __init__(self, config: SpaceConfig = SpaceConfig()):
        super().__init__()
        self.config = c = config
        ch, h, w = c.channels, c.height // 8, c.width // 8
        self.encode_net = nn.Sequential(_Conv(3, ch // 2, 2), _Conv(ch // 2, ch, 2), _Conv(ch, ch, 2), nn.Flatten(),
                                        nn.Linear(ch * h * w, 2 * c.latent))
        self.decode_fc = nn.Linear(c.latent, ch * (c.height // 4) * (c.width // 4))
        self.decode_mid = _Conv(ch + 1, ch)
        self.decode_fine = _Conv(ch + 1, ch // 2)
        self.decode_out = nn.Conv2d(ch // 2 + 1, 3, 3)
        self.register_buffer("mean_map", torch.zeros(1, 3, c.height, c.width))  # the set's mean log map (rows)

    def encode(self, log_map: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 3, H, W) log maps -> the latent's mean and log-variance (B, L) each."""
        mu, log_var = self.encode_net(log_map - self.mean_map).chunk(2, -1)
        return mu, log_var.clamp(-12, 6)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) latents -> (B, 3, H, W) log maps (radiance: exp(.) - LOG_EPS, at least 0)."""
        c = self.config
        x = self.decode_fc(z).view(-1, c.channels, c.height // 4, c.width // 4)
        x = self.decode_mid(_with_height(F.interpolate(x, scale_factor=2)))
        x = self.decode_fine(_with_height(F.interpolate(x, scale_factor=2)))
        return self.mean_map + self.decode_out(_pad(_with_height(x)))

    def save(self, path) -> None:
        torch.save({"config": asdict(self.config), "state": self.state_dict()}, path)

    @classmethod
    def load(cls, path, map_location="cpu") -> "LightSpace":
        saved = torch.load(path, map_location=map_location, weights_only=True)
        space = cls(SpaceConfig(**saved["config"]))
        space.load_state_dict(saved["state"])
        return space


def area_downsample(maps: torch.Tensor, height: int) -> torch.Tensor:
    """(B, 3, H, 2H) equirect radiance -> (B, 3, height, 2 height): each cell the solid-angle weighted mean of the
    cells it covers (H a multiple of ``height``), so a sun's power is kept in its cell."""
    b, c, big, _ = maps.shape
    if big % height:
        raise ValueError(f"a {big}-row map does not downsample to {height} rows evenly")
    k = big // height
    w = conventions.equirect_solid_angles(big, 2 * big, maps.device, maps.dtype).view(1, 1, big, 1)
    return F.avg_pool2d(maps * w, k) / F.avg_pool2d(w.expand(1, 1, big, k), k)


def to_log_map(maps: torch.Tensor, height: int) -> torch.Tensor:
    """(B, 3, H, 2H) radiance -> the space's (B, 3, height, 2 height) log radiance."""
    return torch.log(area_downsample(maps, height).clamp_min(0) + LOG_EPS)


def augment(maps: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Each (B, 3, H, W) map turned about up by a random whole number of columns, and half of them mirrored (a map
    seen in a mirror is a map)."""
    b, _, _, w = maps.shape
    shifts = torch.randint(0, w, (b,), generator=generator)
    cols = (torch.arange(w).unsqueeze(0) + shifts.unsqueeze(1)) % w
    flip = torch.rand(b, generator=generator) < 0.5
    cols = torch.where(flip.unsqueeze(1), cols.flip(1), cols)
    return torch.gather(maps, 3, cols.view(b, 1, 1, w).expand_as(maps).to(maps.device))


def log_map_error(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) the mean absolute log-radiance error over the sphere (cells weighted by solid angle)."""
    h, w = target.shape[2:]
    solid = conventions.equirect_solid_angles(h, w, target.device, target.dtype).view(1, 1, h, 1)
    return ((predicted - target).abs() * solid).sum((1, 2, 3)) / (3 * w * solid.sum())


def yaw_frame(probe_to_world: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) rotations from each view's probe frame to its space frame: the pole the world's up, the centre the
    camera's forward (the probe frame's +X) turned into the horizontal plane."""
    up = probe_to_world[:, 2]  # the world's up, in probe coordinates
    forward = up.new_tensor([1.0, 0.0, 0.0]).expand_as(up)
    forward = forward - (forward * up).sum(-1, keepdim=True) * up
    # a camera looking straight down or up has no forward in the plane: take its up instead
    fallback = up.new_tensor([0.0, 0.0, 1.0]).expand_as(up)
    forward = torch.where(forward.norm(dim=-1, keepdim=True) < 1e-4, fallback - (fallback * up).sum(-1, True) * up,
                          forward)
    forward = F.normalize(forward, dim=-1)
    return torch.stack([forward, torch.cross(up, forward, dim=-1), up], 1)


def sample_log_map(log_map: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """(B, K, 3) bilinear log radiance of (B, 3, H, W) space-frame maps at unit directions ``dirs`` (B, K, 3), wrapping
    in azimuth."""
    uv = conventions.direction_to_equirect_uv(dirs)
    padded = F.pad(log_map, (1, 1, 0, 0), mode="circular")  # so that a column past either edge wraps
    w = log_map.shape[3]
    x = (uv[..., 0] * w + 1) / (w + 2) * 2 - 1
    xy = torch.stack([x, 2 * uv[..., 1] - 1], -1).unsqueeze(1)
    return F.grid_sample(padded, xy.to(log_map), align_corners=False, padding_mode="border")[:, :, 0].permute(0, 2, 1)


