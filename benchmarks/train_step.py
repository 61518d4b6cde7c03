"""Training-iteration benchmark: time per iteration of the CPU default config and its split.

    python -m benchmarks.train_step --dataset data/glossy [--shading sg] [--iterations 20] [--device cuda]
        [--variant published] [--preset paper]

Phases: data (drawing the batch from the decoded tensors), encoder (forward), render + losses
(eq. 8 and the cross-view renders again under their own light: 48 renders of 64x64 for 8 objects x 2 views),
backward, optimiser step. Prints a table and writes Markdown/CSV under --out.
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


def time_iterations(config: TrainConfig, iterations: int, warmup: int = 2) -> dict:
    """Median seconds per phase over ``iterations`` training steps (after ``warmup``)."""
    torch.manual_seed(config.seed)
    ds = MultiViewDataset(config.dataset, split="train", views_per_item=1, with_envmap=False)
    data = TrainingViews(ds, ds.resolution, device=config.device)
    model = make_model(config, ds.resolution).to(config.device)
    opt = make_optimizer(model, config)
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1]).to(config.device)
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


def write_results(results: list[dict], config: TrainConfig, res: int, iterations: int, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    cols = ["shading", *PHASES, "total"]
    write_csv(out / "train.csv", results, cols)
    model = f"variant {config.variant}" if config.variant else "the default model"
    lines = [f"Training iteration on {config.device}, {model} ({config.batch_objects} objects x 2 views, "
             f"{4 * config.batch_objects} renders of {res}x{res}, K={config.lobes}, MC spp={config.spp}); ms, "
             f"median of {iterations}", "",
             markdown_table(cols, [[r["shading"]] + [f"{r[k]:.0f}" for k in cols[1:]] for r in results])]
    (out / "train.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'train.md'}")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
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
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    resolution = MultiViewDataset(args.dataset, split="train", views_per_item=1).resolution
    write_results(results, runs[0], resolution, args.iterations, Path(args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
