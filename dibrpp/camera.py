"""Batched perspective cameras in Blender's convention (see :mod:`dibrpp.conventions`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from . import conventions as conv


@dataclass
class Cameras:
    """A batch of square-image perspective cameras.

    world_to_camera: (B, 4, 4) rigid transforms; fov: (B,) full field of view in radians;
    resolution: image side in pixels (one value for the batch).
    """

    world_to_camera: torch.Tensor
    fov: torch.Tensor
    resolution: int

    def __post_init__(self):
        if self.world_to_camera.dim() == 2:
            self.world_to_camera = self.world_to_camera.unsqueeze(0)
        if self.world_to_camera.shape[-2:] != (4, 4):
            raise ValueError(f"world_to_camera must be (B, 4, 4), got {tuple(self.world_to_camera.shape)}")
        fov = torch.as_tensor(self.fov, dtype=self.world_to_camera.dtype, device=self.world_to_camera.device)
        self.fov = fov.reshape(-1).expand(len(self))
        if not torch.all((self.fov > 0) & (self.fov < math.pi)):
            raise ValueError("fov must be in (0, pi) radians")
        if int(self.resolution) <= 0:
            raise ValueError(f"resolution must be a positive number of pixels, got {self.resolution}")
        self.resolution = int(self.resolution)

    @classmethod
    def orbit(cls, distance, elevation_deg, azimuth_deg, fov_deg, resolution, device=None) -> "Cameras":
        """Orbit cameras looking at the origin; arguments broadcast to a batch."""
        w2c = conv.orbit_world_to_camera(
            torch.as_tensor(distance, dtype=torch.float32), elevation_deg, azimuth_deg
        ).reshape(-1, 4, 4)
        fov = torch.deg2rad(torch.as_tensor(fov_deg, dtype=torch.float32)).expand(w2c.shape[0])
        return cls(w2c.to(device), fov.to(device), resolution)

    def __len__(self) -> int:
        return self.world_to_camera.shape[0]

    def __getitem__(self, idx) -> "Cameras":
        idx = [idx] if isinstance(idx, int) else idx
        return Cameras(self.world_to_camera[idx], self.fov[idx], self.resolution)

    def to(self, device) -> "Cameras":
        return Cameras(self.world_to_camera.to(device), self.fov.to(device), self.resolution)

    def orbited(self, delta_azimuth_deg: float) -> "Cameras":
        """The same cameras moved ``delta_azimuth_deg`` further along their orbit about world +Z (novel views)."""
        a = math.radians(delta_azimuth_deg)
        c, s = math.cos(a), math.sin(a)
        # a camera at azimuth az + delta sees point p as the camera at az sees p rotated by -delta
        rz_inverse = self.world_to_camera.new_tensor([[c, s, 0, 0], [-s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        return Cameras(self.world_to_camera @ rz_inverse, self.fov, self.resolution)

    @property
    def device(self):
        return self.world_to_camera.device

    @property
    def rotation(self) -> torch.Tensor:
        """(B, 3, 3) world-to-camera rotation."""
        return self.world_to_camera[:, :3, :3]

    @property
    def centers(self) -> torch.Tensor:
        """(B, 3) camera positions in world space."""
        r, t = self.rotation, self.world_to_camera[:, :3, 3]
        return -(r.transpose(1, 2) @ t.unsqueeze(-1)).squeeze(-1)

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points (B, N, 3) or (N, 3) -> camera space (B, N, 3)."""
        if points.dim() == 2:
            points = points.unsqueeze(0).expand(len(self), -1, -1)
        r, t = self.rotation.to(points), self.world_to_camera[:, :3, 3].to(points)
        return points @ r.transpose(1, 2) + t.unsqueeze(1)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points -> (NDC xy (B, N, 2), depth (B, N))."""
        return conv.camera_to_ndc(self.to_camera(points), self.fov.to(points.dtype).view(-1, 1))

    def view_directions_world(self) -> torch.Tensor:
        """(B, H, W, 3) unit directions from each pixel centre towards the camera, in world space."""
        h = w = self.resolution
        xy = conv.pixel_centers_ndc(h, w, self.device, self.world_to_camera.dtype)
        f = conv.focal_ndc(self.fov).view(-1, 1, 1, 1)
        rays = torch.cat([xy.unsqueeze(0) / f, -torch.ones(len(self), h, w, 1, device=self.device)], -1)
        rays = torch.nn.functional.normalize(rays, dim=-1)
        return -(rays @ self.rotation.unsqueeze(1))  # camera->world rotation is R^T; row-vector form uses R
