"""The one place that owns the project's coordinate conventions (Blender's, measured).

World: right-handed, +Z up.  Camera: looks down its local -Z, +Y up (Blender/OpenGL).
Orbit camera at distance D, elevation el, azimuth az sits at
``D * (cos el cos az, cos el sin az, sin el)`` and looks at the origin with world up +Z.
Field of view is Blender's camera ``angle`` for a square image (sensor fit AUTO).

Environment maps are equirectangular, top row first: a direction d = (x, y, z) maps to
``u = 0.5 - atan2(y, x) / 2pi`` (column = u * W) and ``v = acos(z) / pi`` (row from the top = v * H).

NDC: x right, y up, both in [-1, 1] over the image; pixel (row r, column c) has its centre at
``x = (2c + 1) / W - 1``, ``y = 1 - (2r + 1) / H``.

Everything here is a plain function of torch tensors (float32/float64, any device) so the renderer
and the Blender dataset generator share it unchanged.
"""
from __future__ import annotations

import math

import torch

WORLD_UP = (0.0, 0.0, 1.0)


def _as_tensor(x, dtype=torch.float32, device=None) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(device=device) if device is not None else x
    return torch.as_tensor(x, dtype=dtype, device=device)


def orbit_position(distance, elevation_deg, azimuth_deg) -> torch.Tensor:
    """Camera centre(s) of orbit cameras; broadcasts its arguments, returns (..., 3)."""
    d = _as_tensor(distance)
    el = torch.deg2rad(_as_tensor(elevation_deg, dtype=d.dtype))
    az = torch.deg2rad(_as_tensor(azimuth_deg, dtype=d.dtype))
    d, el, az = torch.broadcast_tensors(d, el, az)
    return torch.stack([d * torch.cos(el) * torch.cos(az), d * torch.cos(el) * torch.sin(az), d * torch.sin(el)], -1)


def look_at(eye: torch.Tensor, target=None, up=WORLD_UP) -> torch.Tensor:
    """World-to-camera 4x4 matrices (..., 4, 4) for cameras at ``eye`` looking at ``target``.

    The camera's local axes are x = right, y = up, z = backwards (it looks down -z).
    """
    eye = _as_tensor(eye)
    target = torch.zeros_like(eye) if target is None else _as_tensor(target, eye.dtype, eye.device).expand_as(eye)
    up = _as_tensor(up, eye.dtype, eye.device).expand_as(eye)
    back = torch.nn.functional.normalize(eye - target, dim=-1)
    right = torch.linalg.cross(up, back, dim=-1)
    # A camera straight above/below the target: any right vector perpendicular to the view works.
    degenerate = right.norm(dim=-1, keepdim=True) < 1e-8
    right = torch.where(degenerate, _as_tensor((1.0, 0.0, 0.0), eye.dtype, eye.device).expand_as(eye), right)
    right = torch.nn.functional.normalize(right, dim=-1)
    cam_up = torch.linalg.cross(back, right, dim=-1)
    rot = torch.stack([right, cam_up, back], dim=-2)  # rows = camera axes in world coordinates
    trans = -(rot @ eye.unsqueeze(-1)).squeeze(-1)
    m = torch.zeros(eye.shape[:-1] + (4, 4), dtype=eye.dtype, device=eye.device)
    m[..., :3, :3] = rot
    m[..., :3, 3] = trans
    m[..., 3, 3] = 1.0
    return m


def orbit_world_to_camera(distance, elevation_deg, azimuth_deg) -> torch.Tensor:
    """World-to-camera matrices of orbit cameras looking at the origin."""
    return look_at(orbit_position(distance, elevation_deg, azimuth_deg))


def focal_ndc(fov_rad) -> torch.Tensor:
    """Focal length in NDC units for a square image whose full field of view is ``fov_rad``."""
    return 1.0 / torch.tan(_as_tensor(fov_rad) / 2)


def camera_to_ndc(points_cam: torch.Tensor, fov_rad) -> tuple[torch.Tensor, torch.Tensor]:
    """Perspective projection of camera-space points (..., 3) -> (ndc_xy (..., 2), depth (...,)).

    depth is the distance along the viewing axis (-z), positive in front of the camera.
    """
    f = focal_ndc(fov_rad).to(points_cam)
    depth = -points_cam[..., 2]
    safe = torch.where(depth.abs() < 1e-9, torch.full_like(depth, 1e-9), depth)
    f = f.reshape(f.shape + (1,) * (points_cam.dim() - 1 - f.dim())) if f.dim() else f
    xy = points_cam[..., :2] * (f / safe).unsqueeze(-1)
    return xy, depth


def pixel_centers_ndc(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """NDC coordinates (H, W, 2) of the pixel centres, row 0 at the top."""
    xs = (2 * torch.arange(width, device=device, dtype=dtype) + 1) / width - 1
    ys = 1 - (2 * torch.arange(height, device=device, dtype=dtype) + 1) / height
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1)


def ndc_to_pixel(xy: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Continuous pixel coordinates (col, row) with pixel centres at half-integers."""
    col = (xy[..., 0] + 1) * 0.5 * width
    row = (1 - xy[..., 1]) * 0.5 * height
    return torch.stack([col, row], -1)


def camera_ray_directions(height: int, width: int, fov_rad, device=None, dtype=torch.float32) -> torch.Tensor:
    """Unit ray directions (H, W, 3) in camera space through the pixel centres."""
    xy = pixel_centers_ndc(height, width, device, dtype)
    f = float(focal_ndc(fov_rad))
    d = torch.cat([xy / f, -torch.ones_like(xy[..., :1])], -1)
    return torch.nn.functional.normalize(d, dim=-1)


# ----------------------------------------------------------------------------- environment maps

def direction_to_equirect_uv(d: torch.Tensor) -> torch.Tensor:
    """Unit directions (..., 3) -> (u, v) in [0, 1]^2, u along columns, v = rows from the top."""
    u = 0.5 - torch.atan2(d[..., 1], d[..., 0]) / (2 * math.pi)
    # atan2 of (distance from the pole axis, z), not acos(z): exact for the slightly non-unit vectors that
    # float32 normalisation leaves, and well conditioned near the poles where acos loses ~1e-4
    v = torch.atan2(torch.hypot(d[..., 0], d[..., 1]), d[..., 2]) / math.pi
    return torch.stack([u % 1.0, v], -1)


def equirect_uv_to_direction(uv: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`direction_to_equirect_uv`."""
    phi = (0.5 - uv[..., 0]) * 2 * math.pi
    theta = uv[..., 1] * math.pi
    s = torch.sin(theta)
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), torch.cos(theta)], -1)


def equirect_directions(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Directions (H, W, 3) of the texel centres of an equirectangular map."""
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    return equirect_uv_to_direction(torch.stack([uu, vv], -1))


def equirect_solid_angles(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """Exact solid angle (H, 1) of each texel row of an equirectangular map (sums to 4pi over the map)."""
    edges = torch.arange(height + 1, device=device, dtype=torch.float64) / height * math.pi
    band = (torch.cos(edges[:-1]) - torch.cos(edges[1:])) * (2 * math.pi / width)
    return band.to(dtype).unsqueeze(-1)


# ----------------------------------------------------------------------------- colour

LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)  # Rec. 709 luminance of linear RGB


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, x * 12.92, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
