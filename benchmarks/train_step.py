"""Training-iteration benchmark: time per iteration of the CPU default config and its split.

    python -m benchmarks.train_step --dataset data/glossy [--shading sg] [--iterations 20]

Phases: data (drawing the batch from the decoded tensors), encoder (forward), render + losses
(eq. 8: 32 renders of 64x64 for 8 objects x 2 views), backward, optimiser step. Prints a table and
writes Markdown/CSV under --out.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset
from dibrpp.formatting import markdown_table, write_csv
from dibrpp.io import DataError
from dibrpp.mesh import uniform_laplacian
from pipelines.config import TrainConfig
from pipelines.dataset import TrainingViews
from pipelines.objective import multiview_losses
from pipelines.runs import make_model, make_optimizer, make_renderer

PHASES = ("data", "encoder", "render+losses", "backward", "optimizer")


def time_iterations(config: TrainConfig, iterations: int, warmup: int = 2) -> dict:
    """Median seconds per phase over ``iterations`` training steps (after ``warmup``)."""
    torch.manual_seed(config.seed)
    data = TrainingViews(MultiViewDataset(config.dataset, split="train", views_per_item=1, with_envmap=False),
                         config.image_size)
    model = make_model(config)
    opt = make_optimizer(model, config)
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1])
    encoder_s = []
    model.register_forward_pre_hook(lambda *_: encoder_s.append(-time.perf_counter()))
    model.register_forward_hook(lambda *_: encoder_s.__setitem__(-1, encoder_s[-1] + time.perf_counter()))
    rows = []
    for it in range(warmup + iterations):
        t0 = time.perf_counter()
        batch = data.batch(it, config.batch_objects, config.seed)
        t1 = time.perf_counter()
        total, _, _ = multiview_losses(model, make_renderer(config, seed=it, training=True), batch, config, laplacian)
        t2 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        total.backward()
        t3 = time.perf_counter()
        opt.step()
        t4 = time.perf_counter()
        enc = encoder_s[-1]
        rows.append(dict(data=t1 - t0, encoder=enc, **{"render+losses": t2 - t1 - enc}, backward=t3 - t2,
                         optimizer=t4 - t3, total=t4 - t0))
    rows = rows[warmup:]
    return {k: sorted(r[k] for r in rows)[len(rows) // 2] for k in (*PHASES, "total")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", default="data/glossy")
    ap.add_argument("--shading", nargs="+", default=["sg", "mc", "sh"])
    ap.add_argument("--iterations", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2, help="untimed iterations first (torch.compile compiles here)")
    ap.add_argument("--out", default="results/bench")
    args = ap.parse_args(argv)
    try:
        resolution = MultiViewDataset(args.dataset, split="train", views_per_item=1).resolution
    except DataError as e:
        print(f"error: {e}; run `make data` (or pass --dataset)", file=sys.stderr)
        return 2
    results = []
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; median of {args.iterations} iterations")
    for shading in args.shading:
        config = TrainConfig.preset("cpu", dataset=args.dataset, shading=shading, image_size=resolution)
        try:
            r = time_iterations(config, args.iterations, args.warmup)
        except DataError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        r = {"shading": shading, **{k: 1000 * v for k, v in r.items()}}
        results.append(r)
        print(f"{shading:>5}: " + ", ".join(f"{k} {r[k]:.0f} ms" for k in (*PHASES, "total")))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cols = ["shading", *PHASES, "total"]
    write_csv(out / "train.csv", results, cols)
    cfg = TrainConfig.preset("cpu")
    lines = [f"Training iteration, CPU default config ({cfg.batch_objects} objects x 2 views, {4 * cfg.batch_objects} "
             f"renders of {resolution}x{resolution}, K={cfg.lobes}, MC spp={cfg.spp}); ms, median of "
             f"{args.iterations}", "",
             markdown_table(cols, [[r["shading"]] + [f"{r[k]:.0f}" for k in cols[1:]] for r in results])]
    (out / "train.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'train.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
