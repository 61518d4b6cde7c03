"""Table B: optimise an environment map with dibrpp's MC shading and with Mitsuba 3 -- same task, same machine.

The task (everything but the env map fixed): a unit icosphere (2562 vertices, smooth normals) of rough metal
(Principled meaning: base colour ALBEDO, Roughness 0.3 so GGX alpha = 0.09, Metallic 1), one orbit camera
(distance 3, elevation 20, azimuth 30, fov 45), lit by a procedural HDR sky (gradient + ground + sun,
``sky_radiance``); all of it in :mod:`benchmarks.envmap_task`. Each renderer renders its own reference from
the GT map at high spp, then optimises the map from constant grey with Adam on log-texels (lr 0.05 decaying
to 0.005) against that reference with an image L2 loss at 4 spp. Defaults: 256x256 image, 256x128 map, 300
iterations; --quick: 64x64, 32x16, 20.

- dibrpp (:mod:`benchmarks.envmap_dibrpp`): ``Renderer(MCShader(...))`` (rasterized once -- only the light
  changes -- then GGX + env-map MIS shading: 2 + 2 directions per pixel at 4 spp), torch Adam. One render per
  iteration; its backward replays independent samples (``grad_seed``), so the residual and the gradient are
  decorrelated and the gradient unbiased, as Mitsuba's prb with its primal and adjoint seeds
  (--dibrpp-gradient correlated: the same samples in both, biased, see DibrppBackend.step). Three runs
  (:data:`RUNS`): the C++ kernel at the task's spp, the kernel at twice the spp (as many directions per pixel as
  Mitsuba's camera rays take), and the PyTorch path through torch.compile (the previous implementation).
- Mitsuba 3 (:mod:`benchmarks.envmap_mitsuba`): variant llvm_ad_rgb, integrator prb (max_depth 2: direct
  light only; env map hidden behind the object, as dibrpp leaves the background black), the same mesh and
  normals, principled BSDF, an envmap emitter whose ``data`` is optimised with mi.ad.Adam. 4 spp = 4 camera
  rays, each with one emitter and one BSDF sample.

Each renderer runs in its own subprocesses (reference, then optimisation) so memory does not mix. Reported:
wall time of the timed iterations (a throw-away warm-up iteration comes first, reported apart: Dr.Jit compiles
its kernels there), peak RSS above the process's RSS after imports (Linux /proc VmHWM, reset at the
baseline), the first and last iteration's image loss and its noise floor (its value at the GT map), the image
error of the initial, optimised and GT maps re-rendered at the reference spp (the GT map's is that metric's own
noise floor, which differs between the renderers), and the
env-map error against the GT on the half of the sphere facing the camera (relative L2 and the paper's 1 - NCC,
solid-angle weighted, both maps on Blender's texel grid). Writes mitsuba.md, mitsuba.csv and mitsuba.png under --out.

Mitsuba needs ``pip install mitsuba drjit`` and, for the LLVM variants, LLVM 19 (Debian: ``apt-get install
libllvm19``; LLVM 15/16 abort inside Dr.Jit). Without them the Mitsuba row is skipped with one message.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from benchmarks.envmap_dibrpp import DibrppBackend
from benchmarks.envmap_mitsuba import MitsubaBackend, import_mitsuba, install_hint, mitsuba_missing
from benchmarks.envmap_task import (INIT_RADIANCE, QUICK, SIZES, Task, sky_radiance, visible_half_envmap_errors,
                                    visible_weight)
from benchmarks.memory import reset_peak_rss, rss_mb
from dibrpp import conventions as conv
from dibrpp import native
from dibrpp.cli_args import Parser, check_output_folder, positive_float, positive_int
from dibrpp.formatting import format_number, markdown_table, pyplot, save_figure, write_csv
from dibrpp.io import DataError

PAPER = {"dibrpp": {"time_s": 5.4, "peak_mb": 1475}, "mitsuba": {"time_s": 9.8, "peak_mb": 3287}}  # Table B, GPU


@dataclass(frozen=True)
class Run:
    """One column of Table B: a renderer and what it changes in the shared task."""

    renderer: str  # "dibrpp" or "mitsuba"
    label: str
    spp_factor: int = 1
    native: bool = True  # dibrpp: the C++ kernel, else the PyTorch path

    def task(self, task: Task) -> Task:
        return replace(task, spp=task.spp * self.spp_factor, dibrpp_native=self.native)

    def title(self, device: str) -> str:
        """The column's name: dibrpp's C++ kernel shades on the CPU only, on CUDA every dibrpp column is PyTorch."""
        if device == "cpu" or self.renderer != "dibrpp":
            return self.label
        eager = f"PyTorch on {device}"
        return self.label.replace("C++ kernel", eager).replace("PyTorch (before)", eager)


RUNS = {
    "dibrpp": Run("dibrpp", "dibrpp (C++ kernel)"),
    "dibrpp-2x": Run("dibrpp", "dibrpp, 2x spp (C++ kernel)", spp_factor=2),
    "dibrpp-pytorch": Run("dibrpp", "dibrpp, PyTorch (before)", native=False),
    "mitsuba": Run("mitsuba", "Mitsuba 3 (prb)"),
}


# ----------------------------------------------------------------------------- worker (one subprocess each)

def make_backend(name: str, task: Task):
    """The backend of renderer ``name`` ("dibrpp" or "mitsuba")."""
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
    if task.dibrpp_native:  # dibrpp's C++ library, as Mitsuba's libraries above
        native.mc_envmap()
    if task.device.startswith("cuda"):
        torch.zeros(1, device=task.device)


def run_reference(run: str, task: Task, scratch: Path) -> None:
    task = RUNS[run].task(task)
    backend = make_backend(RUNS[run].renderer, task)
    gt = sky_radiance(backend.texel_directions()).float().numpy()
    np.save(scratch / f"{run}_ref.npy", backend.render_still(gt, task.ref_spp, seed=1).astype(np.float32))


def run_optimisation(run: str, task: Task, scratch: Path) -> None:
    task, name = RUNS[run].task(task), RUNS[run].renderer
    prepare_imports(name, task)
    base = rss_mb("VmRSS")
    reset_peak_rss()
    backend = make_backend(name, task)
    ref = np.load(scratch / f"{run}_ref.npy")
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
            print(f"  [{run}] iteration {it:4d}  loss {losses[-1]:.5f}  {1000 * times[-1]:.0f} ms", flush=True)
    peak = rss_mb("VmHWM") - base
    env = torch.from_numpy(backend.envmap()).float()
    # Convergence without the 4-spp noise: the initial and final maps re-rendered at the reference spp, with
    # other random numbers than the reference's (shared ones would cancel the noise in the difference).
    native = backend.native_envmap()
    mse = lambda e, spp, seed: float(np.mean((backend.render_still(e, spp, seed) - ref) ** 2))  # noqa: E731
    gt_native = sky_radiance(backend.texel_directions()).float().numpy()
    clean = {"init": mse(np.full_like(native, INIT_RADIANCE), task.ref_spp, 2), "final": mse(native, task.ref_spp, 3),
             "at_gt": mse(gt_native, task.ref_spp, 12)}  # the noise floor of this metric
    # The per-iteration loss cannot go below the noise of a render at the task's spp: its value at the GT map.
    floor = float(np.mean([mse(gt_native, task.spp, seed) for seed in range(4, 12)]))
    dirs = conv.equirect_directions(task.env_height, task.env_width)  # both maps are compared on Blender's grid
    gt = sky_radiance(dirs)
    result = {
        "run": run, "renderer": name, "status": "ok", "spp": task.spp, "time_s": sum(times), "warmup_s": warmup,
        "median_iter_ms": 1000 * float(np.median(times)), "peak_mb": peak,
        "loss_init": losses[0], "loss_final": losses[-1], "loss_at_gt": floor,
        "clean_loss_init": clean["init"], "clean_loss_final": clean["final"], "clean_loss_at_gt": clean["at_gt"],
        **{f"env_{k}_init": v for k, v in visible_half_envmap_errors(torch.full_like(gt, INIT_RADIANCE), gt, dirs).items()},
        **{f"env_{k}_final": v for k, v in visible_half_envmap_errors(env, gt, dirs).items()},
    }
    if task.device.startswith("cuda") and name == "dibrpp":
        result["gpu_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    np.save(scratch / f"{run}_env.npy", env.numpy())
    np.save(scratch / f"{run}_losses.npy", np.array(losses))
    (scratch / f"{run}.json").write_text(json.dumps(result))


def worker_main(args) -> int:
    scratch = Path(args.scratch)
    task = Task(**json.loads((scratch / "task.json").read_text()))
    (run_reference if args.stage == "reference" else run_optimisation)(args.worker, task, scratch)
    return 0


# ----------------------------------------------------------------------------- driver, tables, figure

def run_renderer(run: str, scratch: Path) -> dict:
    for stage in ("reference", "optimise"):
        cmd = [sys.executable, "-m", "benchmarks.mitsuba", "--worker", run, "--stage", stage,
               "--scratch", str(scratch)]
        rc = subprocess.run(cmd).returncode
        if rc != 0:
            return {"run": run, "renderer": RUNS[run].renderer, "status": f"failed in {stage} (exit {rc})"}
    return json.loads((scratch / f"{run}.json").read_text())


def clipped_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two linear images clipped to [0, 1], over every pixel: how well the references agree."""
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * math.log10(1 / max(mse, 1e-12))


CSV_KEYS = ["run", "renderer", "status", "spp", "time_s", "warmup_s", "median_iter_ms", "peak_mb", "gpu_peak_mb",
            "loss_init", "loss_final", "loss_at_gt", "clean_loss_init", "clean_loss_final", "clean_loss_at_gt",
            "env_rel_l2_init", "env_rel_l2_final", "env_ncc_loss_init", "env_ncc_loss_final"]


def _relative(row: dict, peer: dict, key: str) -> str:
    """row[key] / peer[key] (this run's time or memory as a fraction of Mitsuba's), or a dash."""
    a, b = row.get(key), peer.get(key)
    return f"{a / b:.2f}" if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b > 0 else "—"


def write_tables(rows: dict, task: Task, agreement: float | None, out: Path) -> str:
    """Table B: one column per run (:data:`RUNS`), then the paper's; ratios against Mitsuba from this run."""
    write_csv(out / "mitsuba.csv", rows.values(), CSV_KEYS, extrasaction="ignore")
    runs = list(rows)
    peer = rows.get("mitsuba", {})
    paper = PAPER["dibrpp"], PAPER["mitsuba"]

    def line(label, key, spec, paper_cells=("", "")):
        return [label, *(format_number(rows[r].get(key), spec) for r in runs), *paper_cells]

    def relative(label, key, paper_key):
        return [label, *(_relative(rows[r], peer, key) for r in runs),
                f"{paper[0][paper_key] / paper[1][paper_key]:.2f}", "1.00"]

    body = [
        line("samples per pixel (directions: dibrpp 1 each, Mitsuba 2 per camera ray)", "spp", "d"),
        line(f"time of {task.iterations} iterations (s)", "time_s", ".2f", (paper[0]["time_s"], paper[1]["time_s"])),
        relative("time / Mitsuba 3's (goal <= 0.5)", "time_s", "time_s"),
        line("peak RSS above baseline (MB)", "peak_mb", ".0f", (paper[0]["peak_mb"], paper[1]["peak_mb"])),
        relative("peak RSS / Mitsuba 3's (goal <= 1)", "peak_mb", "peak_mb"),
        line("warm-up iteration (s)", "warmup_s", ".2f"),
        line("median iteration (ms)", "median_iter_ms", ".1f"),
    ]
    body += [line(label, key, spec) for label, key, spec in (
        ("image L2 loss per iteration, first", "loss_init", ".4g"),
        ("image L2 loss per iteration, last", "loss_final", ".4g"),
        ("image L2 loss per iteration at the GT map: its noise floor", "loss_at_gt", ".4g"),
        (f"image L2 re-rendered at {task.ref_spp} spp, initial map", "clean_loss_init", ".4g"),
        (f"image L2 re-rendered at {task.ref_spp} spp, optimised map", "clean_loss_final", ".4g"),
        (f"image L2 re-rendered at {task.ref_spp} spp, GT map: its noise floor", "clean_loss_at_gt", ".4g"),
        ("env-map rel. L2 (visible half), init", "env_rel_l2_init", ".3f"),
        ("env-map rel. L2 (visible half), final", "env_rel_l2_final", ".3f"),
        ("env-map 1 - NCC (visible half), init", "env_ncc_loss_init", ".4f"),
        ("env-map 1 - NCC (visible half), final", "env_ncc_loss_final", ".4f"))]
    if any("gpu_peak_mb" in rows[r] for r in runs):
        body.append(line("dibrpp peak CUDA memory (MB)", "gpu_peak_mb", ".0f"))
    lines = [
        f"Env-map optimisation, {task.iterations} Adam iterations, {task.resolution}x{task.resolution} image, "
        f"{task.env_width}x{task.env_height} env map, references at {task.ref_spp} spp; dibrpp on {task.device}, "
        f"Mitsuba {task.variant}; {task.threads} CPU thread(s).",
        "",
        markdown_table(["", *(RUNS[r].title(task.device) for r in runs), "paper DIB-R++", "paper Mitsuba 2"], body,
                       "l" + "r" * (len(runs) + 2)),
        "",
        "- Status: " + "; ".join(f"{RUNS[r].title(task.device)} {rows[r]['status']}" for r in runs) + ".",
        f"- Samples: dibrpp shades each pixel centre with spp directions (half GGX, half env-map, MIS); Mitsuba "
        f"traces spp camera rays per pixel, each with one emitter and one BSDF sample (2 x spp directions), so "
        f"dibrpp at {2 * task.spp} spp takes as many directions as Mitsuba at {task.spp}. dibrpp's gradient: "
        f"{task.dibrpp_gradient}; Mitsuba's prb is always decorrelated (independent primal and adjoint seeds).",
        f"- Adam on log-texels, learning rate {task.lr} decayed exponentially to {task.lr / 10:g}, from constant grey "
        f"{INIT_RADIANCE}. Time excludes the warm-up iteration; peak RSS covers set-up, warm-up and the iterations.",
        "- The per-iteration loss carries the render noise, which grows as the sun sharpens, and levels off at its "
        "noise floor; the re-rendered rows show the convergence itself, each renderer against its own reference.",
    ]
    if agreement is not None:
        lines.append(f"- The two renderers' references agree to {agreement:.1f} dB PSNR (linear, clipped to [0, 1]).")
    lines.append("- Paper: Table B of the supplementary, Mitsuba 2 on their GPU; memory there is GPU memory, here "
                 "process RSS; its ratio row is DIB-R++ / Mitsuba 2.")
    text = "\n".join(lines)
    (out / "mitsuba.md").write_text(text + "\n")
    return text


def write_figure(arrays: dict, rows: dict, out: Path, device: str = "cpu") -> None:
    plt = pyplot()
    show = lambda x: conv.linear_to_srgb(torch.from_numpy(np.asarray(x, np.float32))).numpy()  # noqa: E731
    err = lambda run: f" (rel. L2 {format_number(rows.get(run, {}).get('env_rel_l2_final'), '.3f')})"  # noqa: E731
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5))
    panels = [("GT env map (white line: edge of the visible half)", arrays["gt"]),
              (RUNS["dibrpp"].title(device) + err("dibrpp"), arrays.get("dibrpp_env")),
              (RUNS["mitsuba"].title(device) + err("mitsuba"), arrays.get("mitsuba_env")),
              (RUNS["dibrpp-2x"].title(device) + err("dibrpp-2x"), arrays.get("dibrpp-2x_env")),
              ("dibrpp reference", arrays.get("dibrpp_ref"))]
    visible = visible_weight(conv.equirect_directions(*arrays["gt"].shape[:2])) > 0
    for i, (ax, (title, img)) in enumerate(zip(axes.flat, panels)):
        ax.set_title(title, fontsize=10)
        ax.axis("off")
        if img is not None:
            ax.imshow(show(img), interpolation="nearest")
        if i < 4:
            ax.contour(visible, levels=[0.5], colors="w", linewidths=0.8)
    ax = axes.flat[5]
    for run in rows:
        if f"{run}_losses" in arrays:
            same = run == "dibrpp-pytorch"  # the kernel's samples: its curve lies on the kernel's
            label = RUNS[run].title(device) + (" (on the kernel's)" if same else "")
            line = ax.semilogy(arrays[f"{run}_losses"], label=label,
                               linewidth=0.8, linestyle=":" if same else "-")[0]
            ax.axhline(rows[run]["loss_at_gt"], color=line.get_color(), linestyle="--", linewidth=0.8)
    ax.set_xlabel("iteration")
    ax.set_title("image L2 loss per iteration (dashed: at the GT map)", fontsize=10)
    ax.legend(fontsize=8)
    save_figure(fig, out / "mitsuba.png")


def run_all(runs: list[str], task: Task) -> tuple[dict, dict]:
    """(run -> table row, name -> array the workers saved) of every run, each in its own subprocesses."""
    rows, arrays = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        (scratch / "task.json").write_text(json.dumps(asdict(task)))
        for run in runs:
            missing = mitsuba_missing(task.variant) if RUNS[run].renderer == "mitsuba" else []
            if missing:
                print(install_hint(missing))
                rows[run] = {"run": run, "renderer": "mitsuba", "status": "skipped: missing " + " and ".join(missing)}
                continue
            print(f"{RUNS[run].title(task.device)}: reference at {task.ref_spp} spp, then {task.iterations} iterations ...",
                  flush=True)
            rows[run] = run_renderer(run, scratch)
        for f in scratch.glob("*.npy"):
            arrays[f.stem] = np.load(f)
    return rows, arrays


def build_parser() -> Parser:
    ap = Parser(prog="python -m benchmarks.mitsuba", description=__doc__)
    ap.add_argument("--out", default="results/bench", metavar="DIR", help="results folder (made if missing)")
    ap.add_argument("--quick", action="store_true", help="64x64 image, 32x16 env map, 20 iterations (smoke test)")
    for field in SIZES:
        default = getattr(Task, field)
        real = isinstance(default, float)
        ap.add_argument("--" + field.replace("_", "-"), type=positive_float if real else positive_int,
                        metavar="X" if real else "N", help=f"default {default}, --quick {QUICK.get(field, default)}")
    ap.add_argument("--threads", type=positive_int, default=Task.threads, metavar="N",
                    help=f"CPU threads of torch and Dr.Jit (default: every CPU, {Task.threads} here)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="dibrpp's torch device")
    ap.add_argument("--variant", default=Task.variant, help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb)")
    ap.add_argument("--dibrpp-gradient", choices=("decorrelated", "correlated"), default=Task.dibrpp_gradient,
                    help="dibrpp's loss gradient: from a second independent render like Mitsuba's prb (default), "
                         "or plain autodiff of one render (cheaper, biased towards low-variance maps)")
    ap.add_argument("--runs", default=",".join(RUNS),
                    help=f"comma-separated columns to run, of {', '.join(RUNS)} (default: all)")
    ap.add_argument("--worker", choices=RUNS, help=argparse.SUPPRESS)
    ap.add_argument("--stage", choices=("reference", "optimise"), help=argparse.SUPPRESS)
    ap.add_argument("--scratch", help=argparse.SUPPRESS)
    return ap


def chosen_runs(args) -> list[str]:
    """The columns of --runs (dibrpp among them), --out and --device checked: a DataError before any work."""
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    unknown = sorted(set(runs) - set(RUNS))
    if unknown or "dibrpp" not in runs:
        raise DataError(f"--runs {args.runs}: {'unknown ' + ', '.join(unknown) if unknown else 'dibrpp is required'}; "
                        f"choose from {', '.join(RUNS)}")
    check_output_folder("--out", Path(args.out))
    if args.device == "cuda" and not torch.cuda.is_available():
        raise DataError("--device cuda: no CUDA device is available to torch here; use --device cpu")
    return runs


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker:
        return worker_main(args)
    try:
        runs = chosen_runs(args)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sizes = {**(QUICK if args.quick else {}), **{f: getattr(args, f) for f in SIZES if getattr(args, f) is not None}}
    task = Task(threads=args.threads, device=args.device, variant=args.variant, dibrpp_gradient=args.dibrpp_gradient,
                **sizes)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, arrays = run_all(runs, task)
    arrays["gt"] = sky_radiance(conv.equirect_directions(task.env_height, task.env_width)).numpy()
    both = {"dibrpp_ref", "mitsuba_ref"} <= arrays.keys()
    agreement = clipped_psnr(arrays["dibrpp_ref"], arrays["mitsuba_ref"]) if both else None
    print(write_tables(rows, task, agreement, out))
    write_figure(arrays, rows, out, task.device)
    print(f"wrote {out / 'mitsuba.md'}, {out / 'mitsuba.csv'}, {out / 'mitsuba.png'}")
    return 0 if rows["dibrpp"]["status"] == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())
