"""Single-image inverse rendering with the multi-view consistency loss (Sec. E.1-E.2).

    python -m pipelines.train --dataset data/glossy --shading sg --seed 0 --out runs/glossy/sg-seed0
    python -m pipelines.train --variant published ...    # a named variant (--list-variants)
    python -m pipelines.train --out runs/glossy/sg-seed0 --resume   # continue a run with its own settings
    torchrun --nproc_per_node 2 -m pipelines.train ...        # data-parallel on the CPU (gloo)

Each iteration draws ``batch_objects`` (sample, view pair) items, predicts shape/texture/material/light
from both views and renders every prediction in both views with the light of the view it is rendered
in (eq. 8; :mod:`pipelines.training.objective`); Adam's rate decays over the run's last third (``lr_schedule``).
Checkpoints are atomic; ``--resume`` continues bit-for-bit (batches are drawn from a generator seeded by
(seed, iteration), and the RNG state is saved) and refuses changed settings. Every TrainConfig field is a
flag; settings apply in the order preset < variant < --config < flags.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path

from dataclasses import replace

import torch
import torch.distributed as dist

from datagen.reader import MultiViewDataset
from dibrpp.cli_args import Parser, check_output_folder, non_negative_int
from dibrpp.display import display_image, tonemap_envmap
from dibrpp.formatting import pyplot, save_figure
from dibrpp.io import DataError, write_png
from dibrpp.mesh import uniform_laplacian

from .training import runs
from .training.config import (PRESETS, ConfigError, TrainConfig, add_config_arguments, config_overrides, describe_variants,
                     variant_runs)
from .model.framing import training_framing
from .training.dataset import TrainingViews
from .training.objective import multiview_losses
from .training.runs import load_checkpoint, make_model, make_optimizer, save_checkpoint

def check_finite(terms: dict) -> None:
    for name, value in terms.items():
        if not torch.isfinite(value):
            raise FloatingPointError(f"the {name} loss became {value.item()}; stopping (the last good checkpoint is kept)")


def check_finite_gradients(model) -> None:
    """Stop on a non-finite gradient, naming it. The gradients' total norm is one fused pass (~2 ms a step against
    ~10 for a check per tensor); only where it is not finite are the tensors looked at one by one. A norm that
    overflows float32 (gradients near 1e19) stops the run too: it has diverged."""
    grads = {name: p.grad for name, p in model.named_parameters() if p.grad is not None}
    if not grads or torch.isfinite(torch.nn.utils.get_total_norm(list(grads.values()))):
        return
    bad = next((name for name, g in grads.items() if not torch.isfinite(g).all()), None)
    what = f"the gradient of {bad} became non-finite" if bad else "the gradients' norm overflowed float32"
    raise FloatingPointError(f"{what}; stopping (the last good checkpoint is kept)")


def learning_rate_factor(schedule: str, iteration: int, iterations: int) -> float:
    """The multiple of the base learning rate at (0-based) ``iteration`` of a run of ``iterations``: 1 for
    "constant"; for "cosine-tail" 1 over the first two thirds, then a cosine down to 0 over the last third (a
    resumed run given more iterations continues on the longer run's schedule)."""
    if schedule == "constant":
        return 1.0
    start = 2 * iterations // 3
    if iteration < start:
        return 1.0
    return 0.5 * (1 + math.cos(math.pi * (iteration - start) / max(1, iterations - start)))


def set_learning_rate(opt: torch.optim.Optimizer, config: TrainConfig, iteration: int) -> None:
    """Each parameter group's learning rate at ``iteration``: its base ("initial_lr", saved with the optimiser's
    state, so a resumed run keeps it) times the schedule's factor."""
    factor = learning_rate_factor(config.lr_schedule, iteration, config.iterations)
    for group in opt.param_groups:
        group["lr"] = group.setdefault("initial_lr", group["lr"]) * factor


# ----------------------------------------------------------------------------- run

def _setup_distributed(device: str):
    """(rank, world size) of a torchrun launch, (0, 1) otherwise. On CUDA each rank trains on its own GPU (torchrun's
    LOCAL_RANK) and the gradients are reduced over NCCL; on the CPU over gloo."""
    if "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1:
        if device == "cuda":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))  # "cuda" is this rank's GPU from here on
        dist.init_process_group("nccl" if device == "cuda" else "gloo")
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


# settings a resumed run may change: how long it trains and how it reports, not what it trains
CHANGEABLE_ON_RESUME = ("iterations", "log_every", "checkpoint_every", "compile", "out", "device")


def check_resumable(run: Path, config: TrainConfig) -> None:
    """Refuse to resume a run with other settings than it was trained with, naming them."""
    saved = runs.load_config(run).to_dict()
    changed = [k for k, v in config.to_dict().items() if k not in CHANGEABLE_ON_RESUME and saved.get(k) != v]
    if changed:
        diff = ", ".join(f"{k}: {saved.get(k)!r} -> {getattr(config, k)!r}" for k in changed)
        raise DataError(f"{run} was trained with other settings ({diff}); resume it with `--out {run} --resume` "
                        "alone (it reads its own settings), or train the new settings into another --out")


def open_train_split(dataset: str) -> MultiViewDataset:
    return MultiViewDataset(dataset, split="train", views_per_item=1, image="linear", with_envmap=False)


def check_trainable_size(ds: MultiViewDataset) -> int:
    """The dataset's image size, which the model sees: refused unless the encoder can downsample it by 16."""
    if ds.resolution % 16:
        lower, upper = 16 * max(1, ds.resolution // 16), 16 * (ds.resolution // 16 + 1)
        raise DataError(f"{ds.root}: its images are {ds.resolution}x{ds.resolution}, and the model needs a multiple "
                        f"of 16 (its encoder halves the image four times); render the set with --resolution {lower} "
                        f"or {upper}")
    return ds.resolution


def other_busy_cores() -> float:
    """How many cores other processes keep busy now: the kernel's count of runnable tasks less this one, the least
    of three readings 0.1 s apart (the load average lags: a job that has just ended still counts there)."""
    try:
        readings = []
        for _ in range(3):
            readings.append(int(Path("/proc/loadavg").read_text().split()[3].split("/")[0]) - 1)
            time.sleep(0.1)
        return float(max(0, min(readings)))
    except (OSError, ValueError, IndexError):
        return os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0


def warn_if_cores_are_busy(threads: int, busy: float | None = None) -> None:
    """One line where other processes keep a core busy: torch's threads then wait on each other at every step, and a
    step at 2 threads on 2 cores was measured 6-20x slower (0.45 s -> 3-9 s)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    busy = other_busy_cores() if busy is None else busy
    if threads > 1 and busy >= 1.0 and busy + threads > cores + 0.5:
        print(f"warning: other processes keep {busy:.0f} of {cores} cores busy; at {threads} threads each step may be "
              "several times slower: pass --threads 1, or wait for them", file=sys.stderr)


def restore(ckpt: Path, model, opt) -> int:
    """Load a checkpoint into the model and optimiser (and the RNG); returns its iteration."""
    state, saved = load_checkpoint(ckpt)
    if saved.config != model.config:
        raise DataError(f"{ckpt} holds a model configured as {saved.config}, but this run asks for {model.config}; "
                        "choose another --out or the run's own settings")
    if "optimizer" not in state:
        raise DataError(f"{ckpt}: a shipped model (weights only, no optimizer state) cannot be resumed; train a run "
                        "of your own (its card says how) and resume that")
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["torch_rng"])
    return int(state["iteration"])


def train(config: TrainConfig, resume: bool = False, progress: bool = True,
          dataset: MultiViewDataset | None = None, threads: int = 0) -> dict:
    """Train (or with ``resume`` continue) the run ``config.out``; ``dataset``: its training split, if open;
    ``threads``: torch's threads in this process (0: torch's default, one per core)."""
    config.validate()
    if config.device == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: torch sees no CUDA device here; install a CUDA build of torch or use --device cpu")
    rank, world = _setup_distributed(config.device)
    if threads:
        torch.set_num_threads(threads)
    if rank == 0 and config.device == "cpu":
        warn_if_cores_are_busy(torch.get_num_threads())
    out = Path(config.out)
    ckpt = out / runs.CHECKPOINT
    if ckpt.exists() and not resume:
        raise FileExistsError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
    ds = dataset or open_train_split(config.dataset)  # before the run folder exists: bad data leaves nothing
    if config.predict_metallic is None:  # the metallic parameter is predicted where the data has metals
        config = replace(config, predict_metallic=ds.has_metals)
    if ckpt.exists():
        check_resumable(out, config)
    torch.manual_seed(config.seed)
    data = TrainingViews(ds, check_trainable_size(ds), envmaps=config.supervision in ("light-map", "light-probe"),
                         normals=config.probe_normals == "pixels", albedos=config.supervision == "albedo",
                         roughness=config.supervision == "roughness", device=config.device,
                         max_objects=config.train_objects)
    model = make_model(config, data.resolution).to(config.device)
    if config.probe_normals == "pixels":  # fitted once, before the model trains, held, read in evaluation
        runs.fitted_pixel_normals(out, model, data, config.seed, progress and rank == 0)
    opt = make_optimizer(model, config)
    start = restore(ckpt, model, opt) if ckpt.exists() else 0
    on_gpu = [torch.cuda.current_device()] if config.device == "cuda" else None
    ddp = torch.nn.parallel.DistributedDataParallel(model, device_ids=on_gpu) if world > 1 else model
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1]).to(config.device)
    if start >= config.iterations:  # before anything is written: a finished run's folder stays as it is
        if rank == 0:
            print(f"{out}: already trained ({start} iterations); nothing to do")
        return {"model": model, "out": out}
    log = TrainingLog(out / runs.LOG, start) if rank == 0 else None
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        runs.save_config(out, config)
        runs.save_camera(out, ds.camera_setup, training_framing(data.images[..., 3].flatten(0, 1).cpu()))
        log.prepare()
    from tqdm import tqdm

    bar = tqdm(range(start, config.iterations), initial=start, total=config.iterations, disable=not progress or rank != 0,
               desc=f"{Path(config.dataset).name}/{config.shading}", unit="it")
    t_start = time.perf_counter()
    for it in bar:
        renderer, second = runs.step_renderers(config, it)
        batch = data.batch(it, config.batch_objects, config.seed, rank, world)
        total, terms, snap = multiview_losses(ddp, renderer, batch, config, laplacian, second)
        check_finite({"total": total, **terms})
        opt.zero_grad(set_to_none=True)
        total.backward()
        check_finite_gradients(model)
        if config.lr_schedule != "constant":  # constant: the optimiser's state as before schedules existed
            set_learning_rate(opt, config, it)
        opt.step()
        done = it + 1
        if rank == 0:
            if done % config.log_every == 0 or done == config.iterations:
                log.write(done, total, terms, time.perf_counter() - t_start, snap["pred"])
                bar.set_postfix(loss=f"{total.item():.4f}", img=f"{terms['image'].item():.4f}", iou=f"{terms['iou'].item():.3f}")
            if done % config.checkpoint_every == 0 or done == config.iterations:
                write_snapshot(out / runs.SNAPSHOTS / f"iter_{done:06d}.png", snap)
                save_checkpoint(ckpt, model, opt, done, config)
    if rank == 0:
        log.close()
        plot_losses(out / runs.LOG, out / runs.LOSS_PLOT)
        seconds = time.perf_counter() - t_start
        summary = {"iterations": config.iterations, "seconds": log.seconds_before + seconds,
                   "seconds_per_iteration": seconds / max(1, config.iterations - start)}
        (out / runs.SUMMARY).write_text(json.dumps(summary, indent=2))
    if world > 1:
        dist.destroy_process_group()
    return {"model": model, "out": out}


LOG_TERMS = ("image", "iou", "laplacian", "gradient")
LOG_HEADER = "iteration,total,image,iou,laplacian,gradient,seconds\n"


class TrainingLog:
    """log.csv (the eq. 8 terms) and TensorBoard (every term, the diagnostics' too, and the batch's median
    material: a reflection that blurs or dims along training shows there). On resume the CSV is cut back to the
    checkpoint (rows after it are logged again) and its ``seconds`` continue from the checkpoint's row."""

    def __init__(self, path: Path, start: int):
        self.path, self.start = path, start
        self.seconds_before = 0.0
        self.board = None

    def prepare(self) -> None:
        rows = self.path.read_text().splitlines()[1:] if self.start and self.path.exists() else []
        try:
            kept = [r for r in rows if int(r.split(",")[0]) <= self.start]
            self.seconds_before = float(kept[-1].split(",")[-1]) if kept else 0.0
        except ValueError:
            raise DataError(f"{self.path}: not a training log (a row that is no 'iteration,...,seconds'); delete it to "
                            "resume with a log that starts at the checkpoint") from None
        self.path.write_text(LOG_HEADER + "".join(r + "\n" for r in kept))
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # tensorboard is optional: the CSV holds the main terms
            return
        self.board = SummaryWriter(str(self.path.parent / runs.TENSORBOARD), purge_step=self.start + 1)

    def write(self, iteration: int, total: torch.Tensor, terms: dict, seconds: float, pred=None) -> None:
        row = [str(iteration), f"{total.item():.6f}", *(f"{terms[k].item():.6f}" for k in LOG_TERMS),
               f"{self.seconds_before + seconds:.2f}"]
        with open(self.path, "a") as f:
            f.write(",".join(row) + "\n")
        if self.board is not None:
            self.board.add_scalar("loss/total", total.item(), iteration)
            for k, v in terms.items():
                self.board.add_scalar(f"loss/{k}", v.item(), iteration)
            self.board.add_scalar("time/seconds", self.seconds_before + seconds, iteration)
            for name in ("roughness", "specular", "metallic") if pred is not None else ():
                self.board.add_scalar(f"material/{name}", getattr(pred, name).detach().median().item(), iteration)

    def close(self) -> None:
        if self.board is not None:
            self.board.close()


def write_snapshot(path: Path, snap: dict, rows: int = 4) -> None:
    """Input | re-render (in the input view) | predicted albedo (the whole texture) | predicted light (world frame),
    for a few items."""
    n = min(rows, snap["input"].shape[0] // 2)
    pred = snap["pred"]
    s = snap["input"].shape[1]
    tiles = []
    for i in range(n):
        k = 2 * i
        inp = display_image(snap["input"][k, ..., :3] * snap["input"][k, ..., 3:])
        ren = display_image(snap["render"][int((snap["src"] == k).nonzero()[0])].detach())  # its first render
        tex = torch.nn.functional.interpolate(display_image(pred.texture[k].detach()).permute(2, 0, 1)[None], size=(s, 2 * s))[0].permute(1, 2, 0)
        light = pred.select([k]).light(snap["world_to_camera"][[k]]).to_envmap(s, 2 * s).image[0].detach()
        tiles.append(torch.cat([inp, ren, tex, tonemap_envmap(light)], 1))
    write_png(path, torch.cat(tiles, 0), srgb=False)


def plot_losses(log_path: Path, png_path: Path) -> None:
    with open(log_path) as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return
    its = [int(r["iteration"]) for r in rows]
    fig, ax = pyplot().subplots(figsize=(7, 4))
    for key in ("total", "image", "iou", "laplacian", "gradient"):
        ax.plot(its, [float(r[key]) for r in rows], label=key)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.legend()
    ax.grid(alpha=0.3)
    save_figure(fig, png_path)


def parse_config(args: argparse.Namespace) -> tuple[TrainConfig, MultiViewDataset]:
    """The run's TrainConfig from the preset, the variant, the --config file and the flags (in that order), and
    its training split. ``--resume`` without --config starts from the run's own config in --out."""
    flags = config_overrides(args)
    run = Path(flags.get("out", TrainConfig.out))
    if args.resume and runs.is_run(run) and args.preset is not None:
        raise ConfigError(f"--resume continues {run} with its own settings; --preset {args.preset} cannot change them: "
                          "drop --preset (or start a new run in another --out)")
    if args.resume and not runs.is_run(run) and "dataset" not in flags and not args.config:
        raise DataError(f"--out {run}: no run to resume (no config.json and checkpoint.pt); start one with --dataset "
                        "DIR (--resume may stay: it starts the run where there is none)")
    if args.config:
        values = runs.read_json(args.config, "config file")
        if not isinstance(values, dict):
            raise ConfigError(f"{args.config}: a config file must be a JSON object of TrainConfig fields")
    elif args.resume and runs.is_run(run):
        values = runs.load_config(run).to_dict()  # a flag on top that changes it is refused by check_resumable
    else:
        values = {}
    try:
        config = TrainConfig.from_dict({**values, **flags}, preset=args.preset or "cpu")
    except ConfigError as e:
        raise ConfigError(f"{args.config}: {e}" if args.config else str(e)) from None
    return config, open_train_split(config.dataset)


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.train", description=__doc__)
    ap.add_argument("--preset", choices=sorted(PRESETS), help="size of the run (default: cpu)")
    ap.add_argument("--config", metavar="JSON", help="file of TrainConfig fields (after the preset and variant)")
    ap.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint, with the "
                    "settings in its config.json (a flag that changes what it trains is refused)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--threads", type=non_negative_int, default=0, metavar="N",
                    help="torch threads in this process (0: torch's default, one per core; a run warns when other "
                         "processes keep a core busy, which slows every step several times)")
    ap.add_argument("--list-variants", action="store_true", help="print the named variants and exit")
    ap.add_argument("--variant-runs", metavar="KINDS", help="print 'dataset variant seed' of every run of the "
                    "variants of these comma-separated kinds (ablation, diagnostic, paper, published) and exit: make's loops")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    try:
        if args.list_variants or args.variant_runs:
            print(describe_variants() if args.list_variants else variant_runs(args.variant_runs.split(",")))
            return 0
        config, ds = parse_config(args)
        check_output_folder("--out", Path(config.out))
        train(config, resume=args.resume, progress=not args.no_progress, dataset=ds, threads=args.threads)
    except (DataError, ValueError, FileExistsError, FloatingPointError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
