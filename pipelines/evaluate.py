"""Evaluate trained runs on the test split (unseen objects under unseen env maps) with the paper's metrics.

    python -m pipelines.evaluate --runs runs --out results/eval [--refine-steps 30 --out results/eval-refine30]

Finds every run folder under ``--runs`` (``config.json`` + ``checkpoint.pt``), predicts from every test
view, and measures (Sec. E.3, E.6; see :mod:`pipelines.evaluation.metrics`): image L1 of the re-rendering in the
input view over the whole image (the paper's) and over the GT foreground, 2D IoU loss, light 1 - NCC
(predicted light as a world-frame equirect map vs the GT env map, both as LDR maps and as HDR maps),
texture 1 - NCC (unlit albedo renders vs Cycles' albedo AOV), Chamfer distance to the GT mesh, the
probe-sphere light metrics and the predicted normals' angular error; beside each light metric, what a
constant env map scores. Writes ``<dataset>/<run>.json`` (runs sharing a folder name get their parent
folders in the name), a figure ``<dataset>/<run>.png`` (input, re-rendering, albedo and light ours vs GT,
novel views) and ``<dataset>/<run>_failures.png`` (the worst test view by each metric) per run; a result is
reused only while the run's checkpoint and config and the evaluation's settings are the same. Then a
Markdown/CSV table of every result ``--out`` holds, the paper-style tables (:mod:`pipelines.evaluation.tables`) and the
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


import torch

from datagen.reader import MultiViewDataset
from dibrpp.cli_args import Parser, check_output_folder, int_in, positive_int
from dibrpp.formatting import format_number
from dibrpp.io import DataError, atomic_path

from .evaluation.report import evaluated_runs, write_report
from .evaluation.summary import LIGHT_METRICS, METRICS, write_direction_figures, write_figure, write_table
from .evaluation.tables import write_tables
from .scoring import EVAL_SPP, EVAL_VIEW_STRIDE, evaluate_run, split_warnings
from .training.refine import MAX_STEPS
from .training.runs import checkpoint_digest, find_runs, load_config

# what a result JSON holds; a cached result of an older format is evaluated again (3: the whole-image L1, eq. 9
# on LDR maps, the dataset's kind and its split's size; 4: the variant's registry kind; 5: the albedo's sky blue;
# 6: the material's levels and scale; 7: the albedo's sky blue, up over sideways)
RESULT_FORMAT = 7
LOCK_FILE = ".evaluate.lock"  # in --out: one evaluate writes a results folder at a time


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
                              refine_steps=args.refine_steps, device=args.device)
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


def _written_for_another_run(path: Path, run: Path) -> bool:
    """Whether ``path`` holds the result of a run in another folder (an earlier call's runs/a/sg-seed0 where this
    one evaluates runs/b/sg-seed0 into the same --out)."""
    try:
        before = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    other = before.get("run") if isinstance(before, dict) else None
    return isinstance(other, str) and Path(other).resolve() != run.resolve()


def result_paths(runs: list[Path], root: Path, out: Path, dataset: str | None) -> dict[Path, Path]:
    """Where each run's result goes: ``out/<dataset>/<run folder name>.json``; where two runs evaluated on one
    dataset share a folder name (runs/a/sg-seed0, runs/b/sg-seed0), their path below ``root`` joined by "__"
    (``a__sg-seed0.json``), and where an earlier call wrote that file for a run in another folder, this run's
    parent folder and name so joined. A DataError if two runs would still write one file."""
    datasets = {run: _dataset_name(run, dataset) for run in runs}
    shared = Counter((datasets[run], run.name) for run in runs)
    paths = {}
    for run in runs:
        name = run.name if shared[datasets[run], run.name] == 1 else "__".join(run.relative_to(root).parts)
        if _written_for_another_run(out / str(datasets[run]) / f"{name}.json", run):
            name = f"{run.parent.name}__{run.name}"  # an earlier call's run of the same name: keep its result
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
    ap.add_argument("--spp", type=positive_int, default=EVAL_SPP, metavar="N",
                    help=f"MC samples per pixel for the re-renderings (default: {EVAL_SPP})")
    ap.add_argument("--view-stride", type=positive_int, default=EVAL_VIEW_STRIDE, metavar="N",
                    help=f"evaluate every n-th view of each test sample (default {EVAL_VIEW_STRIDE}: 8 of the 24 views, "
                         "every 45 degrees)")
    ap.add_argument("--split", choices=("test", "train", "all"), default="test",
                    help="the views to evaluate on: test (unseen objects and maps), train (the train/test gap; "
                         "use another --out) or all (every sample of a --dataset no run trained on, e.g. make "
                         "data-metallic-sunny) (default: test)")
    ap.add_argument("--dataset", metavar="DIR",
                    help="evaluate every run on this dataset instead of the one it was trained on (e.g. the same "
                         "objects under other env maps; use another --out)")
    ap.add_argument("--refine-steps", type=int_in(0, MAX_STEPS), default=0, metavar="N",
                    help="refine each prediction's light at test time with N Adam steps against its input view "
                         f"(pipelines.training.refine; at most {MAX_STEPS}; use another --out) (default: 0, off)")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"),
                    help="where the model predicts and renders (the metrics are taken on the CPU) (default: cpu)")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: torch sees no CUDA device here; install a CUDA build of torch or use --device cpu")
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
