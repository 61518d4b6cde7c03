"""Training-iteration benchmark: time per iteration of the CPU default config and its split.

    python -m benchmarks.train_step --dataset data/glossy [--shading sg] [--iterations 20] [--device cuda]
        [--variant published] [--preset paper]

Phases: data (drawing the batch from the decoded tensors), encoder (forward), render + losses
(eq. 8 and the cross-view renders again under their own light: 48 renders of 64x64 for 8 objects x 2 views),
backward, optimiser step. Prints a table and writes Markdown/CSV under --out.

``--profile N`` also runs N steps under torch.profiler and writes ``profile_<shading>.md``: the operators that cost
most (self time, forward and backward apart), the time per encoder module, and the step's floating-point work
(the profiler's count for matrix products and convolutions) against the cores' peak, measured in the same run as the
rate of a large float32 matrix product at the same threads.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset
from dibrpp.cli_args import Parser, check_output_folder, non_negative_int, positive_int
from dibrpp.formatting import markdown_table, write_csv
from dibrpp.io import DataError
from dibrpp.mesh import uniform_laplacian
from pipelines.training.config import PRESETS, ConfigError, TrainConfig
from pipelines.training.dataset import TrainingViews
from pipelines.training.objective import multiview_losses
from pipelines.training.runs import make_model, make_optimizer, step_renderers

PHASES = ("data", "encoder", "render+losses", "backward", "optimizer")


def training_state(config: TrainConfig) -> tuple:
    """What a training step needs, as train builds it: the training views, the model, its optimiser, the Laplacian."""
    torch.manual_seed(config.seed)
    ds = MultiViewDataset(config.dataset, split="train", views_per_item=1, with_envmap=False)
    data = TrainingViews(ds, ds.resolution, device=config.device)
    model = make_model(config, ds.resolution).to(config.device)
    opt = make_optimizer(model, config)
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1]).to(config.device)
    return data, model, opt, laplacian


def time_iterations(config: TrainConfig, iterations: int, warmup: int = 2) -> dict:
    """Median seconds per phase over ``iterations`` training steps (after ``warmup``)."""
    data, model, opt, laplacian = training_state(config)
    cuda = config.device == "cuda"

    def now() -> float:  # a GPU's queued work counted in the phase that queued it
        if cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    encoder_s = []
    model.register_forward_pre_hook(lambda *_: encoder_s.append(-now()))
    model.register_forward_hook(lambda *_: encoder_s.__setitem__(-1, encoder_s[-1] + now()))
    rows = []
    for it in range(warmup + iterations):
        t0 = now()
        batch = data.batch(it, config.batch_objects, config.seed)
        t1 = now()
        renderer, second = step_renderers(config, it)  # as train shades a step, second samples included
        total, _, _ = multiview_losses(model, renderer, batch, config, laplacian, second)
        t2 = now()
        opt.zero_grad(set_to_none=True)
        total.backward()
        t3 = now()
        opt.step()
        t4 = now()
        enc = encoder_s[-1]
        rows.append(dict(data=t1 - t0, encoder=enc, **{"render+losses": t2 - t1 - enc}, backward=t3 - t2,
                         optimizer=t4 - t3, total=t4 - t0))
    rows = rows[warmup:]
    return {k: sorted(r[k] for r in rows)[len(rows) // 2] for k in (*PHASES, "total")}


SHADINGS = TrainConfig.__dataclass_fields__["shading"].metadata["choices"]


def build_parser() -> Parser:
    ap = Parser(prog="python -m benchmarks.train_step", description=__doc__)
    ap.add_argument("--dataset", default="data/glossy", metavar="DIR", help="dataset folder (python -m datagen)")
    ap.add_argument("--shading", nargs="+", default=["sg", "mc", "sh"], choices=SHADINGS,
                    help="shading methods to time, one after the other (default: sg mc sh)")
    ap.add_argument("--iterations", type=positive_int, default=10, metavar="N", help="timed iterations")
    ap.add_argument("--warmup", type=non_negative_int, default=2, metavar="N",
                    help="untimed iterations first (torch.compile compiles here)")
    ap.add_argument("--variant", default="", metavar="NAME", help="a named variant of pipelines.training.variants to time "
                    "(default: the default model)")
    ap.add_argument("--preset", default="cpu", choices=sorted(PRESETS), help="the training preset whose batch and "
                    "samples per pixel are timed (paper: 16 objects, 64 spp; the image size is the dataset's) "
                    "(default: cpu)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the step runs (default: cpu)")
    ap.add_argument("--out", default="results/bench", metavar="DIR", help="results folder (made if missing)")
    ap.add_argument("--profile", type=non_negative_int, default=0, metavar="N",
                    help="also profile N steps per shading (profile_<shading>.md; 0: no profile)")
    ap.add_argument("--threads", type=non_negative_int, default=0, metavar="N",
                    help="torch threads (0: torch's default, one per core)")
    return ap


def configs(args) -> list[TrainConfig]:
    """One config per --shading, --out and the dataset checked: all before any timing."""
    check_output_folder("--out", Path(args.out))
    try:
        TrainConfig.from_dict({"variant": args.variant})
    except ConfigError as e:
        raise DataError(f"--variant: {e}") from None
    try:
        MultiViewDataset(args.dataset, split="train", views_per_item=1)
    except DataError as e:
        raise DataError(f"{e}; run `make data` (or pass --dataset)") from None
    try:
        return [TrainConfig.preset(args.preset, dataset=args.dataset, shading=s, device=args.device,
                                   variant=args.variant, predict_metallic=False)
                for s in args.shading]
    except ConfigError as e:
        raise DataError(f"--dataset {args.dataset}: {e}") from None


def peak_gflops(seconds: float = 2.0) -> float:
    """The cores' float32 rate at this process's threads: GFLOP/s of repeated 1024^2 matrix products."""
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    a @ b  # warm
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        n += 1
    return 2 * 1024 ** 3 * n / (time.perf_counter() - t0) / 1e9


def profile_iterations(config: TrainConfig, iterations: int, warmup: int = 2) -> str:
    """A Markdown report of ``iterations`` training steps under torch.profiler (after ``warmup`` untraced ones)."""
    from torch.profiler import ProfilerActivity, profile, record_function

    data, model, opt, laplacian = training_state(config)
    modules = {m: name for name, m in model.named_children()}
    handles = [m.register_forward_pre_hook(lambda m, _: setattr(m, "_rf", record_function(f"module::{modules[m]}")
                                                                  .__enter__())) for m in modules]
    handles += [m.register_forward_hook(lambda m, *_: m._rf.__exit__(None, None, None)) for m in modules]

    def step(it: int) -> None:
        batch = data.batch(it, config.batch_objects, config.seed)
        renderer, second = step_renderers(config, it)
        with record_function("phase::forward"):
            total, _, _ = multiview_losses(model, renderer, batch, config, laplacian, second)
        opt.zero_grad(set_to_none=True)
        with record_function("phase::backward"):
            total.backward()
        with record_function("phase::optimizer"):
            opt.step()

    for it in range(warmup):
        step(it)
    with profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
        t0 = time.perf_counter()
        for it in range(warmup, warmup + iterations):
            step(it)
        seconds = (time.perf_counter() - t0) / iterations
    for h in handles:
        h.remove()
    events = prof.key_averages()
    per = lambda e: e.self_cpu_time_total / 1000 / iterations  # noqa: E731 (ms per step)
    phases = {e.key[7:]: e.cpu_time_total / 1000 / iterations for e in events if e.key.startswith("phase::")}
    module_ms = {e.key[8:]: e.cpu_time_total / 1000 / iterations for e in events if e.key.startswith("module::")}
    ops = sorted((e for e in events if not e.key.startswith(("phase::", "module::", "ProfilerStep"))),
                 key=per, reverse=True)[:25]
    flops = sum(e.flops for e in events) / iterations
    peak = peak_gflops()
    achieved = flops / seconds / 1e9
    lines = [f"Profile of {iterations} {config.shading.upper()} steps at {torch.get_num_threads()} threads "
             f"(after {warmup}): {1000 * seconds:.0f} ms a step under the profiler.", "",
             f"Floating-point work counted (matrix products, convolutions): {flops / 1e9:.2f} GFLOP a step, "
             f"{achieved:.1f} GFLOP/s against a matrix product's {peak:.1f} GFLOP/s at the same threads: "
             f"{100 * achieved / peak:.1f} % of the peak.", "",
             markdown_table(["phase", "ms a step"], [[k, f"{v:.0f}"] for k, v in phases.items()], align="lr"), "",
             "Encoder modules, forward (ms a step, with their children):", "",
             markdown_table(["module", "ms"], [[k, f"{v:.1f}"] for k, v in sorted(module_ms.items(), key=lambda kv: -kv[1])],
                            align="lr"), "",
             "Operators by self time (ms a step; forward and backward operators apart):", "",
             markdown_table(["operator", "self ms", "calls a step"],
                            [[e.key, f"{per(e):.1f}", f"{e.count / iterations:.0f}"] for e in ops], align="lrr")]
    return "\n".join(lines) + "\n"


def write_results(results: list[dict], config: TrainConfig, res: int, iterations: int, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    cols = ["shading", *PHASES, "total"]
    sg = next((r["total"] for r in results if r["shading"] == "sg"), None)
    if sg:  # each shading's step against SG's, timed in the same run
        results = [{**r, "x SG": r["total"] / sg} for r in results]
        cols.append("x SG")
    write_csv(out / "train.csv", results, cols)
    model = f"variant {config.variant}" if config.variant else "the default model"
    lines = [f"Training iteration on {config.device}, {model} ({config.batch_objects} objects x 2 views, "
             f"{4 * config.batch_objects} renders of {res}x{res}, K={config.lobes}, MC spp={config.spp}); ms, "
             f"median of {iterations}", "",
             markdown_table(cols, [[r["shading"]] + [f"{r[k]:.2f}" if k == "x SG" else f"{r[k]:.0f}" for k in cols[1:]]
                                   for r in results])]
    (out / "train.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'train.md'}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    results = []
    try:
        if args.device == "cuda" and not torch.cuda.is_available():
            raise DataError("--device cuda: torch sees no CUDA device here; use --device cpu")
        runs = configs(args)
        where = torch.cuda.get_device_name() if args.device == "cuda" else f"cpu, {torch.get_num_threads()} threads"
        print(f"torch {torch.__version__}, {where}; median of {args.iterations} iterations")
        for config in runs:
            r = time_iterations(config, args.iterations, args.warmup)
            r = {"shading": config.shading, **{k: 1000 * v for k, v in r.items()}}
            results.append(r)
            print(f"{config.shading:>5}: " + ", ".join(f"{k} {r[k]:.0f} ms" for k in (*PHASES, "total")))
            if args.profile:
                report = profile_iterations(config, args.profile, args.warmup)
                Path(args.out).mkdir(parents=True, exist_ok=True)
                (Path(args.out) / f"profile_{config.shading}.md").write_text(report)
                print(report)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    sg = next((r["total"] for r in results if r["shading"] == "sg"), None)
    if sg and len(results) > 1:
        print("against SG's step: " + ", ".join(f"{r['shading']} {r['total'] / sg:.2f}x" for r in results))
    resolution = MultiViewDataset(args.dataset, split="train", views_per_item=1).resolution
    write_results(results, runs[0], resolution, args.iterations, Path(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
