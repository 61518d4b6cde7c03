"""The example scene: one procedural car, an analytic sky whose sun stands at any azimuth, and the car rendered by
Cycles from an orbit camera under it. ``python -m examples.make`` writes the shipped example files from it
(``examples/car.obj``, ``sky.exr``, ``car_photo.exr``); ``python -m pipelines.light_turns`` turns its sky about the
vertical to measure where a model places a known sun.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from dibrpp import conventions

from .shapes import car_shape, mesh_shape

GRID = 36  # marching-cubes cells along the car's length: ~150 KB of OBJ, still round wheels
SUN_ELEVATION, SUN_AZIMUTH, SUN_RADIUS = 40.0, 70.0, 3.0  # degrees; the sun lights the side at azimuth 45
SUN_RADIANCE = np.array([400.0, 370.0, 320.0])  # 2.5 times the sky's irradiance on the ground
SUPERSAMPLE = 4  # per texel side: the sun disc's edge is averaged, not aliased
# the photo: the datasets' object scale and field of view, another elevation and distance
PHOTO_SCALE, PHOTO_FOV, PHOTO_ELEVATION, PHOTO_AZIMUTH, PHOTO_DISTANCE = 18.0, 39.6, 15.0, 30.0, 80.0
PHOTO_SIDE, PHOTO_ROWS = 256, (40, 248)  # rendered square, then cropped to a landscape photo, the car off-centre
PHOTO_PAINT = dict(base_color=(0.55, 0.04, 0.03), roughness=0.25, metallic=0.0, specular_ior_level=0.5)


def car_mesh(seed: int = 3, grid: int = GRID) -> tuple[np.ndarray, np.ndarray]:
    """(verts (V, 3), faces (F, 3)) of a procedural car centred in the unit sphere, touching it."""
    verts, faces, _ = mesh_shape(car_shape(np.random.default_rng(seed)), grid)
    return verts / np.linalg.norm(verts, axis=-1).max(), faces


def sky(height: int = 64, sun_azimuth: float = SUN_AZIMUTH) -> np.ndarray:
    """(height, 2 height, 3) linear radiance: a sky fading from blue at the zenith to white at the horizon, a
    grey ground, and a sun disc of SUN_RADIUS degrees at SUN_ELEVATION and ``sun_azimuth`` degrees."""
    fine = conventions.equirect_directions(height * SUPERSAMPLE, 2 * height * SUPERSAMPLE, dtype=torch.float64)
    d = fine.numpy()
    up = d[..., 2:]
    zenith, horizon = np.array([0.1, 0.18, 0.4]), np.array([0.4, 0.4, 0.4])
    upper = horizon + (zenith - horizon) * np.sqrt(np.clip(up, 0, 1))
    ground = np.array([0.12, 0.11, 0.1])
    env = np.where(up > 0, upper, ground)
    el, az = math.radians(SUN_ELEVATION), math.radians(sun_azimuth)
    sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    env = np.where((d @ sun >= math.cos(math.radians(SUN_RADIUS)))[..., None], SUN_RADIANCE, env)
    texels = env.reshape(height, SUPERSAMPLE, 2 * height, SUPERSAMPLE, 3).mean((1, 3))
    return texels.astype(np.float32)


def render_car(verts: np.ndarray, faces: np.ndarray, env: np.ndarray, distance: float, elevation: float,
               azimuth: float, fov: float, side: int, spp: int = 256) -> np.ndarray:
    """(side, side, 4) linear RGBA (premultiplied, as Cycles writes it): the car at the datasets' object scale, in
    the example's red paint, under ``env``, from an orbit camera (degrees; ``distance`` in the datasets' units)."""
    from dibrpp import Cameras

    from .cycles.render import render_scene

    camera = Cameras.orbit(distance, elevation, azimuth, fov, side)
    return render_scene(verts * PHOTO_SCALE, faces, world_to_camera=camera.world_to_camera[0].numpy(),
                        fov=math.radians(fov), envmap=env, resolution=side, spp=spp, max_bounces=2,
                        **PHOTO_PAINT)["rgba"]


def photo(verts: np.ndarray, faces: np.ndarray, env: np.ndarray, spp: int = 256) -> np.ndarray:
    """(208, 256, 4) linear RGBA: the car rendered by Cycles as a photo would frame it (rendered at PHOTO_SIDE square
    from PHOTO_ELEVATION at PHOTO_DISTANCE, cropped to PHOTO_ROWS: smaller in the frame than in training, and
    off-centre)."""
    rgba = render_car(verts, faces, env, PHOTO_DISTANCE, PHOTO_ELEVATION, PHOTO_AZIMUTH, PHOTO_FOV, PHOTO_SIDE, spp)
    return rgba[PHOTO_ROWS[0]:PHOTO_ROWS[1]]
