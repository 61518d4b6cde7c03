"""Evaluate trained runs on the test split (unseen objects under unseen env maps) with the paper's metrics.

    python -m pipelines.evaluate --runs runs --out results/eval

Finds every run folder under ``--runs`` (``config.json`` + ``checkpoint.pt``), predicts from every test
view, and measures (Sec. E.3, E.6; see :mod:`pipelines.metrics`): image L1 of the re-rendering in the
input view, 2D IoU loss, light 1 - NCC (predicted light as a world-frame equirect map vs the GT env
map), texture 1 - NCC (unlit albedo renders vs Cycles' albedo AOV) and Chamfer distance to the GT mesh.
Writes ``<dataset>/<run>.json`` and a figure ``<dataset>/<run>.png`` (input, re-rendering, albedo and
light, ours vs GT) per run (a checkpoint evaluated before is not evaluated again), a
Markdown/CSV table of all runs and the paper-style tables (:mod:`pipelines.tables`).
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import torch

from dibrpp.io import DataError, atomic_path

from . import metrics
from .dataset import MultiViewDataset, collate
from .losses import to_display
from .report import write_report
from .tables import write_tables
from .train import TrainConfig, make_model, make_renderer

METRICS = ("image", "iou", "light", "texture", "chamfer")


def load_run(run: Path):
    """(config, model) of a finished or interrupted run folder."""
    config = TrainConfig(**json.loads((run / "config.json").read_text()))
    model = make_model(config)
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    model.load_state_dict(state["model"])
    model.eval()
    return config, model, state["iteration"]


@torch.no_grad()
def evaluate_run(run: Path, dataset: str | None = None, batch: int = 16, eval_spp: int = 64) -> dict:
    """Mean metrics over all test views of the run's dataset (or ``dataset``)."""
    config, model, iteration = load_run(run)
    ds = MultiViewDataset(dataset or config.dataset, split="test", views_per_item=1)
    config.spp = eval_spp
    renderer = make_renderer(config, seed=0)
    sums = dict.fromkeys(METRICS, 0.0)
    shown = set(range(0, len(ds), max(1, len(ds) // FIGURE_ROWS))[:FIGURE_ROWS])  # different samples
    figure_rows = []
    n = 0
    for start in range(0, len(ds), batch):
        items = [ds[i] for i in range(start, min(start + batch, len(ds)))]
        b = collate(items)
        rgba = b["image"][:, 0]
        cams = b["cameras"]
        inp = torch.cat([to_display(rgba[..., :3]), rgba[..., 3:]], -1)
        pred = model(inp.permute(0, 3, 1, 2))
        light = pred.light().in_frame(cams.world_to_camera[:, :3, :3])
        out = renderer(pred.meshes(), cams, pred.material(), light)
        gt_mask = rgba[..., 3]
        sums["image"] += metrics.image_l1(to_display(out.rgb), to_display(rgba[..., :3]), gt_mask).sum().item()
        sums["iou"] += metrics.iou_loss(out.alpha, gt_mask).sum().item()
        env = b["envmap"]
        pred_env = light.to_envmap(env.shape[1], env.shape[2]).image
        sums["light"] += metrics.ncc_loss(pred_env, env).sum().item()
        albedo = renderer.render_albedo(pred.meshes(), cams, pred.material()).rgb
        sums["texture"] += metrics.ncc_loss(albedo, b["albedo"][:, 0]).sum().item()
        for k in range(len(items)):
            if start + k in shown:
                figure_rows.append([to_display(rgba[k, ..., :3]) * rgba[k, ..., 3:], to_display(out.rgb[k]),
                                    to_display(albedo[k]), to_display(b["albedo"][k, 0]),
                                    _tonemap(pred_env[k]), _tonemap(env[k])])
        verts = pred.meshes().verts
        for k, obj in enumerate(b["object"].tolist()):
            gt = ds.mesh(obj)
            sums["chamfer"] += metrics.chamfer_distance(verts[k].numpy(), model.faces.numpy(),
                                                        gt.verts[0].numpy(), gt.faces.numpy(), samples=4000)
        n += len(items)
    result = {k: v / n for k, v in sums.items()}
    result.update(run=str(run), dataset=Path(ds.root).name, shading=config.shading, lobes=config.lobes,
                  seed=config.seed, iteration=iteration, trained_iterations=config.iterations, test_views=n)
    return result, figure_rows


FIGURE_ROWS = 4
FIGURE_COLUMNS = ("input", "re-rendering", "albedo (ours)", "albedo (GT)", "light (ours)", "light (GT)")


def _tonemap(env: torch.Tensor) -> torch.Tensor:
    """An HDR map scaled to its own mean (NCC ignores scale), sRGB-encoded, clipped."""
    return to_display(0.4 * env / env.mean().clamp_min(1e-8)).clamp(0, 1)


def write_figure(rows: list, path: Path, title: str) -> None:
    """Qualitative results like the paper's Fig. O-Q: one test view per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), len(FIGURE_COLUMNS), figsize=(2.2 * len(FIGURE_COLUMNS) + 1.2, 1.9 * len(rows)),
                             gridspec_kw=dict(width_ratios=[1, 1, 1, 1, 2, 2]), squeeze=False)
    for i, row in enumerate(rows):
        for j, img in enumerate(row):
            ax = axes[i, j]
            ax.imshow(img.clamp(0, 1).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(FIGURE_COLUMNS[j], fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def find_runs(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.rglob("checkpoint.pt") if (p.parent / "config.json").exists())


def write_table(results: list[dict], out: Path) -> str:
    out.mkdir(parents=True, exist_ok=True)
    cols = ["dataset", "shading", "lobes", "seed", "iteration", *METRICS]
    with open(out / "all_runs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(results)
    lines = ["| dataset | method | K | seed | iterations | Image L1 | 2D IoU loss | Light 1-NCC | Tex 1-NCC | Chamfer |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        lines.append(f"| {r['dataset']} | {r['shading']} | {r['lobes'] if r['shading'] in ('sg', 'sh-sg') else ''} | "
                     f"{r['seed']} | {r['iteration']} | " + " | ".join(f"{r[k]:.4f}" for k in METRICS) + " |")
    text = "\n".join(lines) + "\n"
    (out / "all_runs.md").write_text(text)
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", default="runs")
    ap.add_argument("--out", default="results/eval")
    ap.add_argument("--spp", type=int, default=64, help="MC samples per pixel for the re-renderings")
    args = ap.parse_args(argv)
    runs = find_runs(Path(args.runs))
    if not runs:
        print(f"error: no trained runs under {args.runs}; run `make train-glossy` (or another train-*) first",
              file=sys.stderr)
        return 2
    out = Path(args.out)
    results = []
    for run in runs:
        config = json.loads((run / "config.json").read_text())
        path = out / Path(config["dataset"]).name / f"{run.name}.json"
        iteration = torch.load(run / "checkpoint.pt", weights_only=False)["iteration"]
        if path.exists() and json.loads(path.read_text())["iteration"] == iteration:
            r = json.loads(path.read_text())  # this checkpoint was evaluated before
        else:
            try:
                r, figure_rows = evaluate_run(run, eval_spp=args.spp)
            except DataError as e:
                print(f"error: {run}: {e}", file=sys.stderr)
                return 2
            path.parent.mkdir(parents=True, exist_ok=True)
            write_figure(figure_rows, path.with_suffix(".png"),
                         f"{r['dataset']} / {run.name}: test views (unseen objects and env maps)")
            with atomic_path(path) as tmp:
                tmp.write_text(json.dumps(r, indent=1))
        if r["iteration"] < r["trained_iterations"]:
            print(f"warning: {run} stopped at iteration {r['iteration']} of {r['trained_iterations']}", file=sys.stderr)
        print(f"{run}: " + ", ".join(f"{k} {r[k]:.4f}" for k in METRICS))
        results.append(r)
    print(write_table(results, out))
    print(write_tables(out))
    report = write_report(out)
    print(f"wrote {out}/tables.md, tables.tex, table*.csv, all_runs.md and {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
