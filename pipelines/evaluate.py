"""Evaluate trained runs on the test split (unseen objects under unseen env maps) with the paper's metrics.

    python -m pipelines.evaluate --runs runs --out results/eval [--refine-steps 30 --out results/eval-refine30]

Finds every run folder under ``--runs`` (``config.json`` + ``checkpoint.pt``), predicts from every test
view, and measures (Sec. E.3, E.6; see :mod:`pipelines.metrics`): image L1 of the re-rendering in the
input view over the whole image (the paper's) and over the GT foreground, 2D IoU loss, light 1 - NCC
(predicted light as a world-frame equirect map vs the GT env map, both as LDR maps and as HDR maps),
texture 1 - NCC (unlit albedo renders vs Cycles' albedo AOV), Chamfer distance to the GT mesh, the
probe-sphere light metrics and the predicted normals' angular error; beside each light metric, what a
constant env map scores. Writes ``<dataset>/<run>.json`` (runs sharing a folder name get their parent
folders in the name), a figure ``<dataset>/<run>.png`` (input, re-rendering, albedo and light ours vs GT,
novel views) and ``<dataset>/<run>_failures.png`` (the worst test view by each metric) per run; a result is
reused only while the run's checkpoint and config and the evaluation's settings are the same. Then a
Markdown/CSV table of every result ``--out`` holds, the paper-style tables (:mod:`pipelines.tables`) and the
HTML report. One evaluate writes an ``--out`` at a time. Details: docs/evaluation.md.
"""
from __future__ import annotations

import contextlib
import fcntl
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from datagen.reader import MultiViewDataset, collate
from dibrpp.cli_args import Parser, check_output_folder, non_negative_int, positive_int
from dibrpp.display import display_image, tonemap_envmap
from dibrpp.formatting import format_number, markdown_table, pyplot, save_figure, write_csv
from dibrpp.io import DataError, atomic_path
from dibrpp.lights import EnvMap

from . import metrics
from .model_input import encoder_input
from .refine import refine_light
from .report import evaluated_runs, write_report
from .runs import checkpoint_digest, find_runs, load_config, load_run, make_renderer
from .tables import write_tables

# the paper's metrics: image L1 over the whole image (the paper's) and the GT foreground (ours), eq. 9 on LDR maps
# (the paper's, as we read it) and on HDR maps
METRICS = ("image_whole", "image_foreground", "iou", "light_ldr", "light_hdr", "texture", "chamfer")
# what a result JSON holds; a cached result of an older format is evaluated again (3: the whole-image L1, eq. 9
# on LDR maps, the dataset's kind and its split's size)
RESULT_FORMAT = 3
LIGHT_METRICS = ("probe_diffuse", "probe_metal", "probe_mirror", "colour_deg", "direction_deg")
# a metric and its reference: what a constant env map scores under the same definition
CONSTANT_REFERENCES = tuple(f"{k}_constant" for k in ("light_ldr", "light_hdr", *LIGHT_METRICS))
FAILURE_METRICS = ("image_foreground", "iou", "light_hdr", "texture", "chamfer", "probe_metal")
# a split with fewer samples (objects under a map) gives means that say little: the direction's intervals
# resample whole samples
MIN_SAMPLES = 10
LOCK_FILE = ".evaluate.lock"  # in --out: one evaluate writes a results folder at a time


FIGURE_ROWS = 4
NOVEL_AZIMUTHS = (90.0, 180.0)  # novel views: the input camera moved this far along its orbit
FIGURE_COLUMNS = ("input", "re-rendering", "albedo (ours)", "albedo (GT)", "light (ours)", "light (GT)",
                  "metal probe (ours)", "metal probe (GT)", *(f"novel view +{a:.0f}°" for a in NOVEL_AZIMUTHS))
METRIC_NAMES = {"image_foreground": "image L1 (foreground)", "iou": "2D IoU loss", "light_hdr": "light 1-NCC (HDR)",
                "texture": "tex 1-NCC", "chamfer": "Chamfer", "probe_metal": "rough-metal probe si-RMSE"}


@torch.no_grad()
def predict_views(model, renderer, ds, items: list[dict], figure: bool = False, refine=None) -> tuple[dict, list]:
    """Per-view metrics (name -> (B,) tensor) of a batch of test views and, with ``figure``, one figure
    row per view (input, re-rendering, albedo and light ours vs GT, the rough-metal probe under both lights,
    novel views with the light fixed in the world)."""
    b = collate(items)
    rgba = b["image"][:, 0]
    cams = b["cameras"]
    pred = model(encoder_input(rgba), cams)
    if refine is not None:  # (steps, renderer): test-time refinement of the light against the input view
        pred, _ = refine_light(pred, cams, rgba, refine[1], steps=refine[0])
    light = pred.light(cams.world_to_camera)
    out = renderer(pred.meshes(), cams, pred.material(), light)
    gt_mask, env = rgba[..., 3], b["envmap"]
    pred_env = light.to_envmap(env.shape[1], env.shape[2]).image
    albedo = renderer.render_albedo(pred.meshes(), cams, pred.material()).rgb
    verts = pred.meshes().verts
    gt_meshes = [ds.mesh(obj) for obj in b["object"].tolist()]
    chamfer = [metrics.chamfer_distance(verts[k].numpy(), model.faces.numpy(), gt.verts[0].numpy(), gt.faces.numpy(),
                                        samples=4000) for k, gt in enumerate(gt_meshes)]
    normals = renderer.render_normals(pred.meshes(), cams)
    gt_normals = [renderer.render_normals(gt, cams[[k]]) for k, gt in enumerate(gt_meshes)]
    normal_deg, normal_within = metrics.normal_error_deg(
        normals.rgb, normals.alpha, torch.cat([g.rgb for g in gt_normals]), torch.cat([g.alpha for g in gt_normals]))
    shown_rgb, gt_rgb = display_image(out.rgb), display_image(rgba[..., :3])  # both composited on black
    per_view = {"normal_deg": normal_deg, "normal_within_10deg": normal_within,
                "image_whole": metrics.image_l1_whole(shown_rgb, gt_rgb),
                "image_foreground": metrics.image_l1_foreground(shown_rgb, gt_rgb, gt_mask),
                "iou": metrics.iou_loss(out.alpha, gt_mask),
                **metrics.envmap_losses(pred_env, env),
                "texture": metrics.ncc_loss(albedo, b["albedo"][:, 0]),
                "chamfer": torch.tensor(chamfer, dtype=torch.float64)}
    gt_light = EnvMap(env)
    probes = metrics.ProbeScene(cams.world_to_camera)
    per_view.update(metrics.light_metrics(light, gt_light, probes))
    per_view.update(metrics.constant_light_references(env, probes))
    rows = []
    if figure:
        novel = [display_image(renderer(pred.meshes(), cams.orbited(a), pred.material(), light).rgb) for a in NOVEL_AZIMUTHS]
        # probes scaled like the metric (best scale against the GT), so what is compared is what is shown
        shown = metrics.ProbeScene(cams.world_to_camera, resolution=64)
        probe, probe_gt = (shown.render(lt)["metal"] for lt in (light, gt_light))
        scale = metrics.si_scale(probe, probe_gt).view(-1, 1, 1, 1)
        exposure = 0.5 / metrics.mean_colour(probe_gt).mean(-1).clamp_min(1e-8).view(-1, 1, 1, 1)
        rows = [[display_image(rgba[k, ..., :3]) * rgba[k, ..., 3:], display_image(out.rgb[k]), display_image(albedo[k]),
                 display_image(b["albedo"][k, 0]), tonemap_envmap(pred_env[k]), tonemap_envmap(env[k]),
                 display_image(exposure[k] * scale[k] * probe[k, ..., :3]), display_image(exposure[k] * probe_gt[k, ..., :3]),
                 *(v[k] for v in novel)]
                for k in range(len(items))]
    return per_view, rows


def evaluate_run(run: Path, dataset: str | None = None, batch: int = 16, eval_spp: int = 64,
                 view_stride: int = 1, split: str = "test", refine_steps: int = 0) -> tuple[dict, dict]:
    """Mean metrics over the ``split`` views of the run's dataset (or ``dataset``; every ``view_stride``-th
    view of each sample; ``split="train"`` measures the train/test gap; ``refine_steps``: the light refined at
    test time against each input view, :mod:`pipelines.refine`), and figure rows:
    {"examples": a few different samples, "failures": the worst view by each metric, with its label}."""
    loaded = load_run(run)
    config, model, iteration = loaded.config, loaded.model, loaded.iteration
    ds = MultiViewDataset(dataset or config.dataset, split=split, views_per_item=1)
    check_image_size(run, model.config.image_size, ds)
    renderer = make_renderer(config, seed=0, spp=eval_spp)
    views = [i for i in range(len(ds)) if (i % ds.num_views) % view_stride == 0]
    refine = (refine_steps, make_renderer(config, seed=0, training=True)) if refine_steps else None
    per_view, t0 = {}, time.perf_counter()
    for start in tqdm(range(0, len(views), batch), desc=f"eval {run}", unit="batch", leave=False):
        values, _ = predict_views(model, renderer, ds, [ds[i] for i in views[start:start + batch]], refine=refine)
        for k, v in values.items():
            per_view.setdefault(k, []).append(v)
    per_view = {k: torch.cat(v) for k, v in per_view.items()}
    # means, but the direction error's median over the maps with a dominant light (it is an angle: a few
    # flipped predictions of 180 degrees should not hide that most are right)
    result = {k: float(v.nanmedian() if k.startswith(("direction_deg", "normal_deg")) else
                       v.nanmean() if k.startswith("normal") else v.mean()) for k, v in per_view.items()}
    result["views_with_dominant_light"] = int(torch.isfinite(per_view["direction_deg"]).sum())
    for k in ("direction_deg", "direction_deg_constant"):  # each such view's error, for the distribution figure
        v = per_view[k]
        result[k + "_views"] = [round(float(x), 2) for x in v[torch.isfinite(v)]]
    # the sunny views' median and shares within 25 / 45 degrees, with 95 % intervals over the samples they come from
    sunny = torch.isfinite(per_view["direction_deg"]).numpy()
    sample_of_view = np.array([i // ds.num_views for i in views])[sunny]
    summary = metrics.direction_summary(per_view["direction_deg"].numpy()[sunny], sample_of_view)
    result.update({f"direction_{k}": v for k, v in summary.items() if k != "median"},
                  direction_deg_ci=summary["median_ci"], samples_with_dominant_light=len(set(sample_of_view.tolist())))
    result.update(split_size(ds, split))
    result.update(run=str(run), dataset=Path(ds.root).name, dataset_kind=dataset_kind(ds),
                  trained_on=Path(config.dataset).name,
                  shading=config.shading, lobes=config.lobes,
                  seed=config.seed, iteration=iteration, trained_iterations=config.iterations, test_views=len(views),
                  view_stride=view_stride, variant=config.label(), split=split, refine_steps=refine_steps,
                  seconds_per_view=(time.perf_counter() - t0) / len(views))
    shown = list(range(0, len(ds), max(1, len(ds) // FIGURE_ROWS)))[:FIGURE_ROWS]  # different samples
    worst = {k: views[int(per_view[k].argmax())] for k in FAILURE_METRICS}
    _, example_rows = predict_views(model, renderer, ds, [ds[i] for i in shown], figure=True, refine=refine)
    _, failure_rows = predict_views(model, renderer, ds, [ds[i] for i in worst.values()], figure=True, refine=refine)
    labels = [f"worst {METRIC_NAMES[k]}\n({float(per_view[k].max()):.3g})" for k in worst]
    return result, {"examples": (example_rows, None), "failures": (failure_rows, labels)}


def check_image_size(run: Path, image_size: int, ds: MultiViewDataset) -> None:
    """A DataError unless the dataset's images are the size the run's model reads (as training refuses them)."""
    if ds.resolution != image_size:
        raise DataError(f"{run} was trained on {image_size}x{image_size} images but {ds.root} holds "
                        f"{ds.resolution}x{ds.resolution}; evaluate it on a dataset rendered at {image_size} "
                        f"(python -m datagen --resolution {image_size}) or a run trained on {ds.root}")


def dataset_kind(ds: MultiViewDataset) -> str | None:
    """The kind of set the manifest says it is (metallic, glossy, diffuse: what decides its paper table), whatever
    its folder is called; None where the manifest does not say."""
    kind = ds.manifest.get("dataset")
    return kind if isinstance(kind, str) else None


def split_size(ds: MultiViewDataset, split: str) -> dict:
    """How much the split holds: its samples (objects under a map), its env maps and, for the test split, how many
    of them also light the train split's objects (a set with few maps cannot hold any out; None if the manifest
    does not say)."""
    maps = {env for _, env in ds.samples}
    shared = None
    if split == "test":
        try:
            trained = {int(e) for o in ds.manifest["objects"] if o["split"] == "train" for e in o["envmaps"]}
            shared = len(maps & trained)
        except (KeyError, TypeError, ValueError):
            pass
    return dict(samples=len(ds.samples), envmaps=len(maps), envmaps_in_train_split=shared)


def split_warnings(r: dict) -> list[str]:
    """One warning line per reason a result's means say less than they seem to: test env maps that the train
    split also uses, too few samples."""
    lines, where = [], f"{r['dataset']}'s {r.get('split', 'test')} split"
    if r.get("envmaps_in_train_split"):
        lines.append(f"warning: {where} is lit by {r['envmaps_in_train_split']} of its {r['envmaps']} env maps that "
                     "its train split also uses: the light is not scored on unseen maps (the set has too few maps "
                     "to hold some out; generate it with more --num-envmaps)")
    if r.get("samples", MIN_SAMPLES) < MIN_SAMPLES:
        lines.append(f"warning: {where} holds {r['samples']} samples (objects under a map) on {r['envmaps']} env "
                     f"maps, fewer than {MIN_SAMPLES}: its means say little")
    return lines


def write_figure(rows: list, path: Path, title: str, row_labels: list[str] | None = None) -> None:
    """Qualitative results like the paper's Fig. O-Q: one test view per row."""
    plt = pyplot()
    ratios = [2 if c.startswith("light") else 1 for c in FIGURE_COLUMNS]
    fig, axes = plt.subplots(len(rows), len(FIGURE_COLUMNS), figsize=(2.2 * len(FIGURE_COLUMNS) + 1.2, 1.9 * len(rows)),
                             gridspec_kw=dict(width_ratios=ratios), squeeze=False)
    for i, row in enumerate(rows):
        for j, img in enumerate(row):
            ax = axes[i, j]
            ax.imshow(img.clamp(0, 1).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(FIGURE_COLUMNS[j], fontsize=9)
            if j == 0 and row_labels:
                ax.set_ylabel(row_labels[i], fontsize=8)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=110)


def write_direction_figures(results: list[dict], out: Path) -> list[Path]:
    """``direction_<dataset>.png``: per dataset, the share of test views (those with a dominant light) whose
    dominant-light direction error is at most x degrees, for each default seed-0 run and the constant guess."""
    plt = pyplot()
    written = []
    for dataset in sorted({r["dataset"] for r in results}):
        runs = [r for r in results if r["dataset"] == dataset and not r.get("variant") and r["seed"] == 0
                and r.get("trained_on", dataset) == dataset and r.get("direction_deg_views")]
        if not runs:
            continue
        fig, ax = plt.subplots(figsize=(5.2, 3.6))
        curves = [(f"{r['shading'].upper()} (median {r['direction_deg']:.0f}°)", r["direction_deg_views"], "-")
                  for r in sorted(runs, key=lambda r: r["shading"])]
        const = runs[0]
        curves.append((f"constant: straight above (median {const['direction_deg_constant']:.0f}°)",
                       const["direction_deg_constant_views"], "--"))
        for label, errors, style in curves:
            e = torch.tensor(sorted(errors))
            ax.step(torch.cat([torch.zeros(1), e]).numpy(), torch.arange(len(e) + 1).numpy() / len(e),
                    style, where="post", label=label)
        ax.axvline(30, color="grey", lw=0.8, ls=":")
        ax.set(xlim=(0, 180), ylim=(0, 1), xlabel="dominant-light direction error (°)",
               ylabel="share of views with at most this error",
               title=f"{dataset}: {len(const['direction_deg_views'])} test views with a sun or lamp")
        ax.legend(fontsize=8, loc="lower right")
        written.append(save_figure(fig, out / f"direction_{dataset}.png", dpi=110))
    return written


def dataset_label(r: dict) -> str:
    """The evaluated dataset, and the one the run was trained on where that is another."""
    trained = r.get("trained_on", r["dataset"])
    return r["dataset"] if trained == r["dataset"] else f"{r['dataset']} (trained on {trained})"


def share_with_interval(share: float | None, interval: list | None) -> str:
    """'45 % (29–61)': a share and its 95 % interval in percent; '' where the run has none (no view with a dominant
    light, or evaluated before the intervals were)."""
    if share is None or interval is None or share != share:
        return ""
    return f"{100 * share:.0f} % ({100 * interval[0]:.0f}–{100 * interval[1]:.0f})"


ALL_RUNS_HEADER = ("dataset", "method", "variant", "K", "seed", "iterations", "Image L1 (whole)", "Image L1 (fg)",
                   "2D IoU loss", "Light 1-NCC (LDR)", "Light 1-NCC (HDR)", "Tex 1-NCC", "Chamfer", "diffuse probe",
                   "metal probe", "mirror probe", "colour (°)", "direction (°)", "≤ 25° (95 % interval)", "normal (°)")


def constant_rows(results: list[dict]) -> list[dict]:
    """One reference row per evaluated dataset and split: every light metric of a constant env map, under the
    metric's own name (from the first result that has them)."""
    rows = {}
    for r in results:
        key = (r["dataset"], r.get("split", "test"))
        if key not in rows and "light_ldr_constant" in r:
            rows[key] = {"dataset": r["dataset"], "shading": "constant light", "split": key[1],
                         **{k.removesuffix("_constant"): r.get(k) for k in CONSTANT_REFERENCES}}
    return list(rows.values())


def write_table(results: list[dict], out: Path) -> str:
    """all_runs.md / .csv: every result, then each dataset's constant-light reference row; the CSV also gives each
    light metric's reference beside every run."""
    out.mkdir(parents=True, exist_ok=True)
    cols = ["dataset", "dataset_kind", "trained_on", "split", "shading", "variant", "lobes", "seed", "iteration",
            *METRICS, *LIGHT_METRICS, *CONSTANT_REFERENCES, "direction_within_25", "normal_deg"]
    write_csv(out / "all_runs.csv", results, cols, extrasaction="ignore")

    def cells(r):
        sg = r["shading"] in ("sg", "sh-sg")
        return [dataset_label(r), r["shading"], r.get("variant", ""), r["lobes"] if sg else "", r.get("seed", ""),
                r.get("iteration", ""), *(format_number(r.get(k), ".4f") for k in METRICS),
                *(format_number(r.get(k), ".3g") for k in LIGHT_METRICS),
                share_with_interval(r.get("direction_within_25"), r.get("direction_within_25_ci")),
                format_number(r.get("normal_deg"), ".3g")]

    rows = [cells(r) for r in (*results, *constant_rows(results))]
    text = markdown_table(ALL_RUNS_HEADER, rows, "llllrr" + "r" * (len(METRICS) + len(LIGHT_METRICS) + 2)) + "\n"
    (out / "all_runs.md").write_text(text)
    return text


def cached_result(path: Path, key: dict) -> dict | None:
    """The stored result of an evaluation with exactly this ``key`` (checkpoint and config digest, stride, spp,
    split, dataset), else None: a retrained run (same folder, other weights) is evaluated again."""
    try:
        before = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return before if isinstance(before, dict) and before.get("evaluated") == key else None


def evaluate_and_write(run: Path, path: Path, key: dict, args) -> dict:
    """Evaluate one run and write its result JSON and figures (the JSON last: it marks the run as done)."""
    r, figures = evaluate_run(run, args.dataset, eval_spp=args.spp, view_stride=args.view_stride, split=args.split,
                              refine_steps=args.refine_steps)
    r["spp"] = args.spp
    r["evaluated"] = key
    path.parent.mkdir(parents=True, exist_ok=True)
    rows, _ = figures["examples"]
    trained_on_them = args.split == "train" and not args.dataset
    seen = "objects and env maps it was trained on" if trained_on_them else "unseen objects and env maps"
    write_figure(rows, path.with_suffix(".png"), f"{r['dataset']} / {run.name}: {args.split} views ({seen})")
    rows, labels = figures["failures"]
    write_figure(rows, path.with_name(f"{path.stem}_failures.png"),
                 f"{r['dataset']} / {run.name}: failure cases, the worst {args.split} view by each metric", labels)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(r, indent=1))
    return r


def _dataset_name(run: Path, dataset: str | None) -> str | None:
    """The folder name of the dataset ``run`` is evaluated on; None if its config cannot be read (the run is
    reported as not evaluated when its turn comes)."""
    try:
        return Path(dataset or load_config(run).dataset).name
    except DataError:
        return None


def result_paths(runs: list[Path], root: Path, out: Path, dataset: str | None) -> dict[Path, Path]:
    """Where each run's result goes: ``out/<dataset>/<run folder name>.json``; where two runs evaluated on one
    dataset share a folder name (runs/a/sg-seed0, runs/b/sg-seed0), their path below ``root`` joined by "__"
    (``a__sg-seed0.json``). A DataError if two runs would still write one file."""
    datasets = {run: _dataset_name(run, dataset) for run in runs}
    shared = Counter((datasets[run], run.name) for run in runs)
    paths = {}
    for run in runs:
        name = run.name if shared[datasets[run], run.name] == 1 else "__".join(run.relative_to(root).parts)
        paths[run] = out / str(datasets[run]) / f"{name}.json"
    clash = [p for p, n in Counter(paths[run] for run in runs if datasets[run]).items() if n > 1]
    if clash:
        raise DataError(f"--runs {root}: several runs would write {clash[0]}; rename one of their folders")
    return paths


def evaluate_runs(runs: list[Path], paths: dict[Path, Path], args) -> list[str]:
    """Evaluate each run (or take its cached result) into its path, printing its metrics and, once per dataset
    and split, why they may say less than they seem to; the runs that could not be evaluated, with why."""
    failed, warned, t0, evaluated = [], set(), time.perf_counter(), 0
    for i, run in enumerate(runs, 1):
        try:
            config = load_config(run)
            if args.split == "all" and Path(args.dataset).resolve() == Path(config.dataset).resolve():
                raise DataError(f"--split all on {args.dataset}, the dataset it was trained on, would count its "
                                "training samples; use --split test")
            path = paths[run]
            key = dict(checkpoint=checkpoint_digest(run), view_stride=args.view_stride, spp=args.spp, split=args.split,
                       refine_steps=args.refine_steps, results=RESULT_FORMAT,
                       dataset=str(Path(args.dataset or config.dataset).resolve()))
            r = cached_result(path, key)
            if r is None:
                eta = ""
                if evaluated:
                    left = len(runs) - i + 1  # at most: some may be cached
                    eta = f", at most ~{(time.perf_counter() - t0) / evaluated * left / 60:.0f} min left"
                print(f"run {i} of {len(runs)}: {run}{eta}", file=sys.stderr)
                r = evaluate_and_write(run, path, key, args)
                evaluated += 1
        except DataError as e:
            print(f"run {i} of {len(runs)}: {run}: not evaluated: {e}", file=sys.stderr)
            failed.append(f"{run} ({e})")
            continue
        if r["iteration"] < r["trained_iterations"]:
            print(f"warning: {run} stopped at iteration {r['iteration']} of {r['trained_iterations']}", file=sys.stderr)
        if (r["dataset"], r.get("split")) not in warned:
            warned.add((r["dataset"], r.get("split")))
            for line in split_warnings(r):
                print(line, file=sys.stderr)
        print(f"{run}: " + ", ".join(f"{k} {format_number(r.get(k), '.4f')}" for k in (*METRICS, *LIGHT_METRICS)))
    return failed


@contextlib.contextmanager
def exclusive_out(out: Path):
    """Hold ``out``'s lock file for the block; a DataError at once if another evaluate holds it (two writing one
    folder would each write tables of what it has seen). The kernel drops the lock when its process ends, however
    it ends, so a lock file left behind blocks no one."""
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise DataError(f"--out {out} is being written by another evaluate (pid {holder}); wait for it to "
                            "finish or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)  # named in the message of a call refused meanwhile
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the lock


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.evaluate", description=__doc__)
    ap.add_argument("--runs", default="runs", metavar="DIR", help="folder of run folders (or one run folder) (default: runs)")
    ap.add_argument("--out", default="results/eval", metavar="DIR", help="results folder (default: results/eval)")
    ap.add_argument("--spp", type=positive_int, default=64, metavar="N", help="MC samples per pixel for the re-renderings (default: 64)")
    ap.add_argument("--view-stride", type=positive_int, default=3, metavar="N",
                    help="evaluate every n-th view of each test sample (default 3: 8 of the 24 views, every 45 degrees)")
    ap.add_argument("--split", choices=("test", "train", "all"), default="test",
                    help="the views to evaluate on: test (unseen objects and maps), train (the train/test gap; "
                         "use another --out) or all (every sample of a --dataset no run trained on, e.g. make "
                         "data-metallic-sunny) (default: test)")
    ap.add_argument("--dataset", metavar="DIR",
                    help="evaluate every run on this dataset instead of the one it was trained on (e.g. the same "
                         "objects under other env maps; use another --out)")
    ap.add_argument("--refine-steps", type=non_negative_int, default=0, metavar="N",
                    help="refine each prediction's light at test time with N Adam steps against its input view "
                         "(pipelines.refine; use another --out) (default: 0, off)")
    args = ap.parse_args(argv)
    if args.split == "all" and not args.dataset:
        ap.error("--split all evaluates every sample of another dataset (--dataset DIR): on a run's own dataset it "
                 "would count the samples it trained on; use --split test")
    try:
        check_output_folder("--out", Path(args.out))
        if args.dataset:  # a missing or broken --dataset would fail every run: said once, now
            MultiViewDataset(args.dataset, split=args.split, views_per_item=1)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = Path(args.out)
    runs = find_runs(Path(args.runs))
    try:
        if not runs:
            raise DataError(f"no trained runs under {args.runs}; run `make train-glossy` (or another train-*) first")
        paths = result_paths(runs, Path(args.runs), out, args.dataset)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        with exclusive_out(out):
            failed = evaluate_runs(runs, paths, args)
            found = [r for _, r in evaluated_runs(out)]  # this call's and every earlier call's into --out
            if found:
                print(write_table(found, out))
                write_direction_figures(found, out)
                print(write_tables(out))
                report = write_report(out)
                print(f"wrote {out}/tables.md, tables.tex, table*.csv, all_runs.md and {report}")
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if failed:
        print(f"error: {len(failed)} of {len(runs)} runs could not be evaluated: {'; '.join(failed)}",
              file=sys.stderr)
        return 2
    return 0

if __name__ == "__main__":
    sys.exit(main())
