"""Table B: optimise an environment map with dibrpp's MC shading and with Mitsuba 3 -- same task, same machine.

The task (everything but the env map fixed): a unit icosphere (2562 vertices, smooth normals) of rough metal
(Principled meaning: base colour ALBEDO, Roughness 0.3 so GGX alpha = 0.09, Metallic 1), one orbit camera
(distance 3, elevation 20, azimuth 30, fov 45), lit by a procedural HDR sky (gradient + ground + sun,
``sky_radiance``). Each renderer renders its own reference from the GT map at high spp, then optimises the
map from constant grey with Adam on log-texels (lr 0.05 decaying to 0.005) against that reference with an
image L2 loss at 4 spp. Defaults: 256x256 image, 256x128 map, 300 iterations; --quick: 64x64, 32x16, 20.

- dibrpp: ``Renderer("mc")`` (rasterize, then GGX + env-map MIS shading: 2 + 2 directions per pixel), torch
  Adam. The loss gradient takes its residual from a second, independent render, as Mitsuba's prb does
  (--dibrpp-gradient correlated: plain autodiff of one render, cheaper but biased, see DibrppBackend.step).
- Mitsuba 3: variant llvm_ad_rgb, integrator prb (max_depth 2: direct light only; env map hidden behind the
  object, as dibrpp leaves the background black), the same mesh and normals, principled BSDF, an envmap
  emitter whose ``data`` is optimised with mi.ad.Adam. 4 spp = 4 camera rays, each with one emitter and one
  BSDF sample.

Each renderer runs in its own subprocesses (reference, then optimisation) so memory does not mix. Reported:
wall time of the timed iterations (a throw-away warm-up iteration comes first, reported apart: Dr.Jit compiles
its kernels there), peak RSS above the process's RSS after imports (Linux /proc VmHWM, reset at the
baseline), the first and last iteration's image loss and its noise floor (its value at the GT map), the image
error of the initial and optimised maps re-rendered at the reference spp (free of the 4-spp noise), and the
env-map error against the GT on the half of the sphere facing the camera (relative L2 and the paper's 1 - NCC,
solid-angle weighted, both maps on Blender's texel grid). Writes mitsuba.md, mitsuba.csv and mitsuba.png under --out.

Mitsuba needs ``pip install mitsuba drjit`` and, for the LLVM variants, LLVM 19 (Debian: ``apt-get install
libllvm19``; LLVM 15/16 abort inside Dr.Jit). Without them the Mitsuba row is skipped with one message.
"""
from __future__ import annotations

import argparse
import csv
import glob
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from dibrpp import Cameras, Material, Renderer, icosphere
from dibrpp import conventions as conv
from dibrpp.lights import EnvMap
from pipelines.bench_renderer import _reset_peak, _rss_mb
from pipelines.metrics import ncc_loss

CAMERA = {"distance": 3.0, "elevation_deg": 20.0, "azimuth_deg": 30.0, "fov_deg": 45.0}
SPHERE_SUBDIVISIONS = 4  # 2562 vertices, 5120 faces
ALBEDO = (0.95, 0.80, 0.60)  # Principled base colour = F0 of the metal
ROUGHNESS = 0.3
INIT_RADIANCE = 0.5  # constant grey initial env map
SUN_DIR = (0.2, 0.9, 0.6)  # reflected into the camera's half of the sphere
PAPER = {"dibrpp": {"time_s": 5.4, "peak_mb": 1475}, "mitsuba": {"time_s": 9.8, "peak_mb": 3287}}  # Table B, GPU
RENDERERS = ("dibrpp", "mitsuba")
STILL_SEEDS = 100_000  # Mitsuba seeds of high-spp renders: STILL_SEEDS * seed + pass, clear of the iterations' seeds
MITSUBA_PIP = ("mitsuba==3.9.1", "drjit==1.5.0")
LLVM_APT = "libllvm19"
LLVM_GLOBS = ("/usr/lib/*-linux-gnu/libLLVM.so.19*", "/usr/lib/*-linux-gnu/libLLVM-19.so*",
              "/usr/lib/llvm-19/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so.19*")


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
    seed: int = 0


QUICK = {"resolution": 64, "env_height": 16, "env_width": 32, "iterations": 20, "ref_spp": 64}
SIZES = ("resolution", "env_width", "env_height", "iterations", "spp", "ref_spp", "lr")  # overridable from the CLI


# ----------------------------------------------------------------------------- the shared scene

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


def envmap_errors(env: torch.Tensor, gt: torch.Tensor, dirs: torch.Tensor) -> dict:
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


# ----------------------------------------------------------------------------- dibrpp

class DibrppBackend:
    """Env-map optimisation with dibrpp; texels live at Blender's texel centres ((i + .5) / W, (j + .5) / H)."""

    name = "dibrpp"

    def __init__(self, task: Task):
        self.task, self.device = task, torch.device(task.device)
        self.mesh = icosphere(SPHERE_SUBDIVISIONS, device=self.device)
        self.cameras = Cameras.orbit(CAMERA["distance"], CAMERA["elevation_deg"], CAMERA["azimuth_deg"],
                                     CAMERA["fov_deg"], task.resolution, device=self.device)
        self.material = Material(albedo=torch.tensor([ALBEDO], device=self.device), roughness=ROUGHNESS, metallic=1.0)

    def texel_directions(self) -> torch.Tensor:
        return conv.equirect_directions(self.task.env_height, self.task.env_width)

    def render(self, env: torch.Tensor, spp: int, seed: int | None = None) -> torch.Tensor:
        renderer = Renderer("mc", spp=spp, mis=True, seed=seed)
        return renderer(self.mesh, self.cameras, self.material, EnvMap(env.unsqueeze(0))).rgb[0]

    def render_still(self, env: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """A map (H, W, 3) on this renderer's texel grid rendered without gradients."""
        with torch.no_grad():
            return self.render(torch.from_numpy(env).to(self.device), spp, seed).cpu().numpy()

    def start(self, ref: np.ndarray) -> None:
        """Fresh grey log-texels and optimiser."""
        self.ref = torch.from_numpy(ref).to(self.device)
        shape = (self.task.env_height, self.task.env_width, 3)
        self.log_env = torch.full(shape, math.log(INIT_RADIANCE), device=self.device, requires_grad=True)
        self.opt = torch.optim.Adam([self.log_env], lr=self.task.lr)

    def step(self, it: int) -> float:
        self.opt.param_groups[0]["lr"] = learning_rate(self.task, it)
        self.opt.zero_grad(set_to_none=True)
        env = self.log_env.exp()
        image = self.render(env, self.task.spp)
        if self.task.dibrpp_gradient == "correlated":
            # the residual and d image / d env share their samples: E[gradient] also minimises the render's
            # variance, which pulls the optimum towards a blurred sun
            loss = (image - self.ref).square().mean()
            loss.backward()
        else:
            # residual from a second, independent render: an unbiased gradient of |E[image] - ref|^2 (what
            # Mitsuba's prb computes; its primal and adjoint passes must use different seeds)
            with torch.no_grad():
                residual = self.render(env, self.task.spp) - self.ref
            loss = residual.square().mean()
            (2 * residual * image).mean().backward()
        self.opt.step()
        return loss.item()

    def native_envmap(self) -> np.ndarray:
        return self.log_env.detach().exp().cpu().numpy()

    envmap = native_envmap  # already on Blender's grid


# ----------------------------------------------------------------------------- Mitsuba 3

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


# ----------------------------------------------------------------------------- worker (one subprocess each)

def make_backend(name: str, task: Task):
    if name == "mitsuba":
        return MitsubaBackend(task, *import_mitsuba(task))
    return DibrppBackend(task)


def prepare_imports(name: str, task: Task) -> None:
    """Everything a renderer loads before its baseline: libraries and, on CUDA, the context."""
    torch.set_num_threads(task.threads)
    torch.manual_seed(task.seed)
    if name == "mitsuba":
        import_mitsuba(task)
        return
    torch.optim.Adam([torch.zeros(1, requires_grad=True)])  # the first optimiser imports torch._dynamo (seconds)
    if task.device.startswith("cuda"):
        torch.zeros(1, device=task.device)


def run_reference(name: str, task: Task, scratch: Path) -> None:
    backend = make_backend(name, task)
    gt = sky_radiance(backend.texel_directions()).float().numpy()
    np.save(scratch / f"{name}_ref.npy", backend.render_still(gt, task.ref_spp, seed=1).astype(np.float32))


def run_optimisation(name: str, task: Task, scratch: Path) -> None:
    prepare_imports(name, task)
    base = _rss_mb("VmRSS")
    _reset_peak()
    backend = make_backend(name, task)
    ref = np.load(scratch / f"{name}_ref.npy")
    # Warm-up: one full iteration on throw-away parameters (Dr.Jit compiles its kernels here).
    t0 = time.perf_counter()
    backend.start(ref)
    backend.step(0)
    warmup = time.perf_counter() - t0
    backend.start(ref)
    losses, times = [], []
    for it in range(task.iterations):
        t0 = time.perf_counter()
        losses.append(backend.step(it))
        times.append(time.perf_counter() - t0)
        if it % max(1, task.iterations // 10) == 0 or it == task.iterations - 1:
            print(f"  [{name}] iteration {it:4d}  loss {losses[-1]:.5f}  {1000 * times[-1]:.0f} ms", flush=True)
    peak = _rss_mb("VmHWM") - base
    env = torch.from_numpy(backend.envmap()).float()
    # Convergence without the 4-spp noise: the initial and final maps re-rendered at the reference spp, with
    # other random numbers than the reference's (shared ones would cancel the noise in the difference).
    native = backend.native_envmap()
    mse = lambda e, spp, seed: float(np.mean((backend.render_still(e, spp, seed) - ref) ** 2))  # noqa: E731
    clean = {"init": mse(np.full_like(native, INIT_RADIANCE), task.ref_spp, 2), "final": mse(native, task.ref_spp, 3)}
    # The per-iteration loss cannot go below the noise of a 4-spp render: its value at the GT map.
    gt_native = sky_radiance(backend.texel_directions()).float().numpy()
    floor = float(np.mean([mse(gt_native, task.spp, seed) for seed in range(4, 12)]))
    dirs = conv.equirect_directions(task.env_height, task.env_width)  # both maps are compared on Blender's grid
    gt = sky_radiance(dirs)
    result = {
        "renderer": name, "status": "ok", "time_s": sum(times), "warmup_s": warmup,
        "median_iter_ms": 1000 * float(np.median(times)), "peak_mb": peak,
        "loss_init": losses[0], "loss_final": losses[-1], "loss_at_gt": floor,
        "clean_loss_init": clean["init"], "clean_loss_final": clean["final"],
        **{f"env_{k}_init": v for k, v in envmap_errors(torch.full_like(gt, INIT_RADIANCE), gt, dirs).items()},
        **{f"env_{k}_final": v for k, v in envmap_errors(env, gt, dirs).items()},
    }
    if task.device.startswith("cuda") and name == "dibrpp":
        result["gpu_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    np.save(scratch / f"{name}_env.npy", env.numpy())
    np.save(scratch / f"{name}_losses.npy", np.array(losses))
    (scratch / f"{name}.json").write_text(json.dumps(result))


def worker_main(args) -> int:
    scratch = Path(args.scratch)
    task = Task(**json.loads((scratch / "task.json").read_text()))
    (run_reference if args.stage == "reference" else run_optimisation)(args.worker, task, scratch)
    return 0


# ----------------------------------------------------------------------------- driver, tables, figure

def run_renderer(name: str, scratch: Path) -> dict:
    for stage in ("reference", "optimise"):
        cmd = [sys.executable, "-m", "pipelines.bench_mitsuba", "--worker", name, "--stage", stage,
               "--scratch", str(scratch)]
        rc = subprocess.run(cmd).returncode
        if rc != 0:
            return {"renderer": name, "status": f"failed in {stage} (exit {rc})"}
    return json.loads((scratch / f"{name}.json").read_text())


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * math.log10(1 / max(mse, 1e-12))


CSV_KEYS = ["renderer", "status", "time_s", "warmup_s", "median_iter_ms", "peak_mb", "gpu_peak_mb", "loss_init",
            "loss_final", "loss_at_gt", "clean_loss_init", "clean_loss_final", "env_rel_l2_init", "env_rel_l2_final",
            "env_ncc_loss_init", "env_ncc_loss_final"]


def _fmt(row: dict, key: str, spec: str) -> str:
    return format(row[key], spec) if isinstance(row.get(key), (int, float)) else "—"


def _ratio(rows: dict, key: str) -> str:
    a, b = rows["dibrpp"].get(key), rows["mitsuba"].get(key)
    return f"{b / a:.2f}" if isinstance(a, (int, float)) and isinstance(b, (int, float)) and a > 0 else "—"


def write_tables(rows: dict, task: Task, agreement: float | None, out: Path) -> str:
    with open(out / "mitsuba.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_KEYS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows[n] for n in RENDERERS)
    d, m = rows["dibrpp"], rows["mitsuba"]
    p_ratio = {k: PAPER["mitsuba"][k] / PAPER["dibrpp"][k] for k in ("time_s", "peak_mb")}

    def line(label, key, spec, paper_key=None, ratio=True):
        paper = (f"{PAPER['dibrpp'][paper_key]} | {PAPER['mitsuba'][paper_key]} | {p_ratio[paper_key]:.2f}"
                 if paper_key else "| |")
        return f"| {label} | {_fmt(d, key, spec)} | {_fmt(m, key, spec)} | {_ratio(rows, key) if ratio else ''} | {paper} |"

    lines = [
        f"Env-map optimisation, {task.iterations} Adam iterations at {task.spp} spp, {task.resolution}x{task.resolution} image, "
        f"{task.env_width}x{task.env_height} env map, references at {task.ref_spp} spp; dibrpp on {task.device}, "
        f"Mitsuba {task.variant}; {task.threads} CPU thread(s).",
        "",
        "| | dibrpp (MC) | Mitsuba 3 (prb) | Mitsuba / dibrpp | paper DIB-R++ | paper Mitsuba 2 | paper ratio |",
        "|---|---:|---:|---:|---:|---:|---:|",
        line(f"time of {task.iterations} iterations (s)", "time_s", ".2f", "time_s"),
        line("peak RSS above baseline (MB)", "peak_mb", ".0f", "peak_mb"),
        line("warm-up iteration (s)", "warmup_s", ".2f"),
        line("median iteration (ms)", "median_iter_ms", ".1f"),
    ]
    lines += [line(label, key, spec, ratio=False) for label, key, spec in (
        (f"image L2 loss ({task.spp} spp), first iteration", "loss_init", ".4g"),
        (f"image L2 loss ({task.spp} spp), last iteration", "loss_final", ".4g"),
        (f"image L2 loss ({task.spp} spp) of the GT map: the noise floor", "loss_at_gt", ".4g"),
        (f"image L2 re-rendered at {task.ref_spp} spp, initial map", "clean_loss_init", ".4g"),
        (f"image L2 re-rendered at {task.ref_spp} spp, optimised map", "clean_loss_final", ".4g"),
        ("env-map rel. L2 (visible half), init", "env_rel_l2_init", ".3f"),
        ("env-map rel. L2 (visible half), final", "env_rel_l2_final", ".3f"),
        ("env-map 1 - NCC (visible half), init", "env_ncc_loss_init", ".4f"),
        ("env-map 1 - NCC (visible half), final", "env_ncc_loss_final", ".4f"))]
    if "gpu_peak_mb" in d:
        lines.append(line("dibrpp peak CUDA memory (MB)", "gpu_peak_mb", ".0f"))
    lines += [
        "",
        f"- Status: dibrpp {d['status']}; Mitsuba {m['status']}.",
        f"- Samples: dibrpp shades each pixel centre with {task.spp} directions ({task.spp - task.spp // 2} GGX + "
        f"{task.spp // 2} env-map, MIS); Mitsuba traces {task.spp} camera rays per pixel, each with one emitter and one "
        f"BSDF sample ({2 * task.spp} directions). dibrpp's gradient: {task.dibrpp_gradient}; Mitsuba's prb is "
        "always decorrelated (independent primal and adjoint seeds).",
        f"- Adam on log-texels, learning rate {task.lr} decayed exponentially to {task.lr / 10:g}, from constant grey "
        f"{INIT_RADIANCE}. Time excludes the warm-up iteration; peak RSS covers set-up, warm-up and the iterations.",
        f"- The per-iteration loss carries the {task.spp}-spp noise, which grows as the sun sharpens, and levels off at "
        "the noise floor; the re-rendered rows show the convergence itself.",
    ]
    if agreement is not None:
        lines.append(f"- The two renderers' references agree to {agreement:.1f} dB PSNR (linear, clipped to [0, 1]).")
    lines.append("- Paper: Table B of the supplementary, Mitsuba 2 on their GPU; memory there is GPU memory, here process RSS.")
    text = "\n".join(lines)
    (out / "mitsuba.md").write_text(text + "\n")
    return text


def write_figure(arrays: dict, rows: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    show = lambda x: conv.linear_to_srgb(torch.from_numpy(np.asarray(x, np.float32))).numpy()  # noqa: E731
    err = lambda name: f" (rel. L2 {_fmt(rows[name], 'env_rel_l2_final', '.3f')})"  # noqa: E731
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    panels = [("GT env map (white line: edge of the visible half)", arrays["gt"]),
              ("dibrpp: optimised env map" + err("dibrpp"), arrays.get("dibrpp_env")),
              ("Mitsuba 3: optimised env map" + err("mitsuba"), arrays.get("mitsuba_env")),
              ("dibrpp reference", arrays.get("dibrpp_ref")), ("Mitsuba 3 reference", arrays.get("mitsuba_ref"))]
    visible = visible_weight(conv.equirect_directions(*arrays["gt"].shape[:2])) > 0
    for i, (ax, (title, img)) in enumerate(zip(axes.flat, panels)):
        ax.set_title(title, fontsize=10)
        ax.axis("off")
        if img is not None:
            ax.imshow(show(img), interpolation="nearest")
        if i < 3:
            ax.contour(visible, levels=[0.5], colors="w", linewidths=0.8)
    ax = axes.flat[5]
    for name in RENDERERS:
        if f"{name}_losses" in arrays:
            line = ax.semilogy(arrays[f"{name}_losses"], label=name)[0]
            ax.axhline(rows[name]["loss_at_gt"], color=line.get_color(), linestyle="--", linewidth=0.8)
    ax.set_xlabel("iteration")
    ax.set_title("image L2 loss per iteration (dashed: at the GT map)", fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "mitsuba.png", dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/bench")
    ap.add_argument("--quick", action="store_true", help="64x64 image, 32x16 env map, 20 iterations (smoke test)")
    for field in SIZES:
        default = getattr(Task, field)
        ap.add_argument("--" + field.replace("_", "-"), type=type(default),
                        help=f"default {default}, --quick {QUICK.get(field, default)}")
    ap.add_argument("--threads", type=int, default=Task.threads, help="CPU threads of torch and Dr.Jit")
    ap.add_argument("--device", default="cpu", help="dibrpp's device (cpu, cuda)")
    ap.add_argument("--variant", default=Task.variant, help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb)")
    ap.add_argument("--dibrpp-gradient", choices=("decorrelated", "correlated"), default=Task.dibrpp_gradient,
                    help="dibrpp's loss gradient: from a second independent render like Mitsuba's prb (default), "
                         "or plain autodiff of one render (cheaper, biased towards low-variance maps)")
    ap.add_argument("--worker", choices=RENDERERS, help=argparse.SUPPRESS)
    ap.add_argument("--stage", choices=("reference", "optimise"), help=argparse.SUPPRESS)
    ap.add_argument("--scratch", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker_main(args)

    sizes = {**(QUICK if args.quick else {}), **{f: getattr(args, f) for f in SIZES if getattr(args, f) is not None}}
    task = Task(threads=args.threads, device=args.device, variant=args.variant, dibrpp_gradient=args.dibrpp_gradient,
                **sizes)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, arrays = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        (scratch / "task.json").write_text(json.dumps(asdict(task)))
        for name in RENDERERS:
            missing = mitsuba_missing(task.variant) if name == "mitsuba" else []
            if missing:
                print(install_hint(missing))
                rows[name] = {"renderer": name, "status": "skipped: missing " + " and ".join(missing)}
                continue
            print(f"{name}: reference at {task.ref_spp} spp, then {task.iterations} iterations ...", flush=True)
            rows[name] = run_renderer(name, scratch)
        for f in scratch.glob("*.npy"):
            arrays[f.stem] = np.load(f)
    arrays["gt"] = sky_radiance(conv.equirect_directions(task.env_height, task.env_width)).numpy()
    agreement = psnr(arrays["dibrpp_ref"], arrays["mitsuba_ref"]) if {"dibrpp_ref", "mitsuba_ref"} <= arrays.keys() else None
    print(write_tables(rows, task, agreement, out))
    write_figure(arrays, rows, out)
    print(f"wrote {out / 'mitsuba.md'}, {out / 'mitsuba.csv'}, {out / 'mitsuba.png'}")
    return 0 if rows["dibrpp"]["status"] == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())
