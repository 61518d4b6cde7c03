"""Table B, the Mitsuba 3 side: finding Mitsuba and LLVM, and the env-map optimisation with path replay
backpropagation (variant llvm_ad_rgb, integrator prb, mi.ad.Adam).

Mitsuba needs ``pip install mitsuba drjit`` and, for the LLVM variants, LLVM 19 (Debian: ``apt-get install
libllvm19``; LLVM 15/16 abort inside Dr.Jit). :func:`mitsuba_missing` says what is missing without importing
drjit.
"""
from __future__ import annotations

import glob
import importlib.util
import math
import os
import sys

import numpy as np
import torch

from benchmarks.envmap_task import (ALBEDO, CAMERA, INIT_RADIANCE, ROUGHNESS, SPHERE_SUBDIVISIONS, Task,
                                    camera_position, learning_rate)
from dibrpp import conventions as conv
from dibrpp import icosphere

STILL_SEEDS = 100_000  # Mitsuba seeds of high-spp renders: STILL_SEEDS * seed + pass, clear of the iterations' seeds
MITSUBA_PIP = ("mitsuba==3.9.1", "drjit==1.5.0")
LLVM_APT = "libllvm19"
LLVM_GLOBS = ("/usr/lib/*-linux-gnu/libLLVM.so.19*", "/usr/lib/*-linux-gnu/libLLVM-19.so*",
              "/usr/lib/llvm-19/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so.19*")


def find_libllvm() -> str | None:
    """DRJIT_LIBLLVM_PATH if set, else an installed LLVM 19 shared library (what Dr.Jit's LLVM backend loads)."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path and os.path.exists(path):
        return path
    hits = sorted(p for pattern in LLVM_GLOBS for p in glob.glob(pattern))
    return hits[0] if hits else None


def mitsuba_missing(variant: str) -> list[str]:
    """What the Mitsuba side lacks (empty: nothing), checked without importing drjit."""
    missing = [f"Python package {m}" for m in ("mitsuba", "drjit") if importlib.util.find_spec(m) is None]
    if variant.startswith("llvm") and find_libllvm() is None:
        missing.append("the LLVM 19 shared library libLLVM.so.19* (Dr.Jit's LLVM backend)")
    return missing


def install_hint(missing: list[str]) -> str:
    return (f"Mitsuba side skipped: missing {' and '.join(missing)}. Install with: {sys.executable} -m pip install "
            f"{' '.join(MITSUBA_PIP)} && apt-get install -y {LLVM_APT} (or `make setup`); set DRJIT_LIBLLVM_PATH "
            "if libLLVM 19 lives elsewhere.")


def import_mitsuba(task: Task):
    """(mi, dr) with the variant set; DRJIT_LIBLLVM_PATH must be in the environment before drjit loads."""
    llvm = find_libllvm()
    if llvm:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(task.variant)
    if task.variant.startswith("llvm"):
        dr.set_thread_count(task.threads)
    return mi, dr


# Mitsuba's envmap maps a local direction to u = atan2(x, -z) / 2pi, v = acos(y) / pi (Y up); this rotation
# (columns: local x -> world +Y, local y -> +Z, local z -> +X) makes its (u, v) Blender's for every world
# direction. Its texel centres differ in v: column i sits at u = (i + .5) / W like Blender's, but row j at
# v = j / (H - 1) (first and last rows on the poles), so each renderer samples the GT at its own texels.
MITSUBA_ENV_TO_WORLD = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


class MitsubaBackend:
    """Env-map optimisation with Mitsuba 3 (path replay backpropagation)."""

    name = "mitsuba"
    key = "env.data"

    def __init__(self, task: Task, mi, dr):
        self.task, self.mi, self.dr = task, mi, dr
        h, w = task.env_height, task.env_width
        mesh = icosphere(SPHERE_SUBDIVISIONS)
        shape = mi.Mesh("sphere", mesh.verts.shape[0], mesh.faces.shape[0], has_vertex_normals=True)
        p = mi.traverse(shape)
        p["vertex_positions"] = mi.Float(mesh.verts.reshape(-1).numpy())
        p["faces"] = mi.UInt32(mesh.faces.reshape(-1).int().numpy())
        p["vertex_normals"] = mi.Float(mesh.vertex_normals()[0].reshape(-1).numpy())  # dibrpp's very normals
        p.update()
        shape.set_bsdf(mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": list(ALBEDO)},
                                     "roughness": ROUGHNESS, "metallic": 1.0}))
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "prb", "max_depth": 2, "hide_emitters": True},
            "sensor": {
                "type": "perspective", "fov": CAMERA["fov_deg"], "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(origin=camera_position().tolist(), target=[0, 0, 0], up=[0, 0, 1]),
                "film": {"type": "hdrfilm", "width": task.resolution, "height": task.resolution,
                         "pixel_format": "rgb", "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": task.spp},
            },
            "sphere": shape,
            "env": {"type": "envmap", "bitmap": mi.Bitmap(np.full((h, w, 3), INIT_RADIANCE, np.float32)),
                    "to_world": mi.ScalarTransform4f(MITSUBA_ENV_TO_WORLD)},
        })
        self.params = mi.traverse(self.scene)
        # The emitter's data carries a wrap-around column on each side: gather them from the H x W texels.
        rows, cols, ch = np.meshgrid(np.arange(h), np.arange(-1, w + 1) % w, np.arange(3), indexing="ij")
        self.pad_index = mi.UInt32(((rows * w + cols) * 3 + ch).reshape(-1))

    def texel_directions(self) -> torch.Tensor:
        h, w = self.task.env_height, self.task.env_width
        u = (torch.arange(w) + 0.5) / w
        v = torch.arange(h) / (h - 1)
        return conv.equirect_uv_to_direction(torch.stack(torch.meshgrid(u, v, indexing="xy"), -1))

    def set_envmap(self, env) -> None:
        h, w = self.task.env_height, self.task.env_width
        flat = self.dr.gather(self.mi.Float, env.array, self.pad_index)
        self.params[self.key] = self.mi.TensorXf(flat, (h, w + 2, 3))
        self.params.update()

    def render(self, spp: int, seed: int):
        return self.mi.render(self.scene, self.params, spp=spp, seed=seed)

    def render_still(self, env: np.ndarray, spp: int, seed: int) -> np.ndarray:
        self.set_envmap(self.mi.TensorXf(env.astype(np.float32)))
        passes = max(1, spp // 64)  # bounded memory: average passes of <= 64 spp
        return sum(np.array(self.render(spp // passes, seed=STILL_SEEDS * seed + k)) for k in range(passes)) / passes

    def start(self, ref: np.ndarray) -> None:
        self.ref = self.mi.TensorXf(ref.astype(np.float32))
        self.opt = self.mi.ad.Adam(lr=self.task.lr)
        self.opt["log_env"] = self.mi.TensorXf(np.full((self.task.env_height, self.task.env_width, 3),
                                                       math.log(INIT_RADIANCE), np.float32))

    def step(self, it: int) -> float:
        dr = self.dr
        self.opt.set_learning_rate(learning_rate(self.task, it))
        self.set_envmap(dr.exp(self.opt["log_env"]))
        loss = dr.mean(dr.square(self.render(self.task.spp, seed=it) - self.ref), axis=None)
        dr.backward(loss)
        self.opt.step()
        return float(loss.array[0])

    def native_envmap(self) -> np.ndarray:
        return np.exp(np.array(self.opt["log_env"]))

    def envmap(self) -> np.ndarray:
        """The optimised map on Blender's texel grid (linear in v between Mitsuba's rows), as dibrpp's."""
        env = self.native_envmap()
        h = env.shape[0]
        y = (np.arange(h) + 0.5) / h * (h - 1)
        j0 = np.minimum(np.floor(y).astype(int), h - 2)
        f = (y - j0)[:, None, None]
        return env[j0] * (1 - f) + env[j0 + 1] * f
