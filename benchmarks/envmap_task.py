"""Table B's task, shared by both renderers: the scene, the sizes, the GT sky and how results are scored.

A unit icosphere of rough metal seen by one orbit camera, lit by a procedural HDR sky (:func:`sky_radiance`);
the env map is optimised from constant grey (:data:`INIT_RADIANCE`) with Adam on log-texels at the rate
:func:`learning_rate`. :mod:`benchmarks.envmap_dibrpp` and :mod:`benchmarks.envmap_mitsuba` are the two sides,
:mod:`benchmarks.mitsuba` runs them and writes the table.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch

from dibrpp import Cameras
from pipelines.evaluation.metrics import ncc_loss

CAMERA = {"distance": 3.0, "elevation_deg": 20.0, "azimuth_deg": 30.0, "fov_deg": 45.0}
SPHERE_SUBDIVISIONS = 4  # 2562 vertices, 5120 faces
ALBEDO = (0.95, 0.80, 0.60)  # Principled base colour = F0 of the metal
ROUGHNESS = 0.3
INIT_RADIANCE = 0.5  # constant grey initial env map
SUN_DIR = (0.2, 0.9, 0.6)  # reflected into the camera's half of the sphere


@dataclass
class Task:
    resolution: int = 256
    env_height: int = 128
    env_width: int = 256
    iterations: int = 300
    spp: int = 4
    ref_spp: int = 512
    lr: float = 0.05
    threads: int = os.cpu_count() or 1
    device: str = "cpu"  # dibrpp side
    variant: str = "llvm_ad_rgb"  # Mitsuba side
    dibrpp_gradient: str = "decorrelated"  # or "correlated" (plain autodiff of one render): see DibrppBackend.step
    dibrpp_native: bool = True  # dibrpp's C++ MC kernel; False: the PyTorch path (torch.compile), as before it
    seed: int = 0


QUICK = {"resolution": 64, "env_height": 16, "env_width": 32, "iterations": 20, "ref_spp": 64}
SIZES = ("resolution", "env_width", "env_height", "iterations", "spp", "ref_spp", "lr")  # overridable from the CLI


def sky_radiance(d: torch.Tensor) -> torch.Tensor:
    """The GT environment: linear RGB radiance (..., 3) at world unit directions (..., 3), +Z up."""
    z = d[..., 2:3]
    horizon, zenith, ground = (d.new_tensor(c) for c in ((1.0, 0.95, 0.9), (0.25, 0.45, 0.9), (0.25, 0.2, 0.15)))
    sky = horizon + (zenith - horizon) * z.clamp(0, 1).sqrt()
    sun_dir = torch.nn.functional.normalize(d.new_tensor(SUN_DIR), dim=0)
    sun = 20.0 * torch.exp(200.0 * ((d * sun_dir).sum(-1, keepdim=True) - 1)) * d.new_tensor((1.0, 0.9, 0.75))
    return torch.where(z >= 0, sky, ground) + sun


def camera_position() -> torch.Tensor:
    return Cameras.orbit(CAMERA["distance"], CAMERA["elevation_deg"], CAMERA["azimuth_deg"], CAMERA["fov_deg"], 1).centers[0]


def visible_weight(dirs: torch.Tensor) -> torch.Tensor:
    """(H, W) solid-angle weight (sin theta) of texels on the camera's side of the sphere, 0 elsewhere.

    A camera sees a sphere's reflections of that half well; the other half only at grazing angles."""
    facing = (dirs @ torch.nn.functional.normalize(camera_position(), dim=0)) > 0
    return (1 - dirs[..., 2].square()).clamp_min(0).sqrt() * facing


def visible_half_envmap_errors(env: torch.Tensor, gt: torch.Tensor, dirs: torch.Tensor) -> dict:
    """Relative L2 and 1 - NCC (eq. 9) of an env map (H, W, 3) against the GT on the visible half."""
    w = visible_weight(dirs).unsqueeze(-1).double()
    env, gt = env.double(), gt.double()
    rel_l2 = math.sqrt(float((w * (env - gt).square()).sum() / (w * gt.square()).sum()))
    ncc = float(ncc_loss((env * w.sqrt()).unsqueeze(0), (gt * w.sqrt()).unsqueeze(0)))
    return {"rel_l2": rel_l2, "ncc_loss": ncc}


def learning_rate(task: Task, it: int) -> float:
    """Exponential decay to a tenth over the run: at 4 spp most texels get a sample only every few iterations,
    and Adam turns those sparse noisy gradients into full-size steps; a constant rate lets them random-walk."""
    return task.lr * 0.1 ** (it / max(task.iterations - 1, 1))
