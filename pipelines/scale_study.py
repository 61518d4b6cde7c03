"""What scale buys: the SG model along input resolution, training length and training cars (and env maps),
everything else at the base point (the glossy set at 64 x 64, 1500 iterations, its 80 training cars under its 32
training maps: the study's own base, a quarter of the default's length, where every point was measured).
``make study-scale``; details and results: docs/scale.md.

    python -m pipelines.scale_study list                      # the points, and which are done
    python -m pipelines.scale_study run [--points res128,its3000,...]
    python -m pipelines.scale_study report                    # curves and light rows into --out

Each point is a run folder, trained by ``pipelines.train`` and evaluated by ``pipelines.evaluate`` on the test
split and on the train split (every 12th view: as many views as the test split), each in its own process (an
entry point does not import another); a point's dataset is rendered by ``datagen`` when it is missing or
incomplete. The study's own runs go in ``--runs`` (default runs-scale/), outside the runs ``make eval`` tables: a
run on 20 cars or of 750 iterations is not a paper row. Every step resumes: rerun after an interruption. Each
length is its own run with its own schedule (the cosine tail over the run's last third): a checkpoint taken
half-way through a longer run is at the full learning rate, not a shorter run's end. Points marked GPU are
skipped where CUDA is not available.
"""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset, collate
from dibrpp.display import tonemap_envmap
from dibrpp.cli_args import Parser, check_output_folder
from dibrpp.io import DataError

from .evaluation.scale_figures import AXIS_LABELS, plot_axis, plot_light_row, table
from .model.model_input import encoder_input
from .scoring import figure_views
from .training.config import PRESETS, ConfigError, TrainConfig, add_config_arguments, config_overrides
from .training.runs import is_run, load_config, load_run

BASE = {"resolution": 64, "iterations": 1500, "cars": 80, "maps": 32}
TRAIN_SPLIT_STRIDE = 12  # 2 views a training sample: 320 views, as many as the test split's at stride 3


@dataclass(frozen=True)
class Point:
    name: str
    axis: str  # "base" is on every axis; "diagnostic" on none (a controlled run or another set: run, not plotted)
    value: int
    dataset: str  # folder under --data
    datagen: tuple[str, ...]  # how that dataset is rendered
    run: str  # folder under --runs
    train: tuple[str, ...] = ()  # flags beside the defaults and the base's length
    gpu: bool = False

    def train_flags(self) -> tuple[str, ...]:
        """The point's flags of pipelines.train: the base's length unless the point sets its own."""
        return ("--iterations", str(BASE["iterations"]), *self.train)


@dataclass(frozen=True)
class Folders:
    data: Path
    runs: Path  # the study's own runs
    out: Path

    def run(self, p: Point) -> Path:
        return self.runs / p.run


GLOSSY = ("--dataset", "glossy")
POINTS = [
    Point("base", "base", 0, "glossy", GLOSSY, "base"),
    *(Point(f"res{r}", "resolution", r, f"glossy-{r}", (*GLOSSY, "--resolution", str(r)), f"res{r}",
            gpu=r > 128) for r in (16, 32, 128, 256)),
    *(Point(f"its{n}", "iterations", n, "glossy", GLOSSY, f"its{n}", ("--iterations", str(n)))
      for n in (750, 3000, 6000, 12000, 24000)),
    *(Point(f"cars{n}", "cars", n, "glossy", GLOSSY, f"cars{n}", ("--train-objects", str(n)))
      for n in (10, 20, 40)),
    # 500 objects: 400 training cars; 200 env maps: 160 training maps (the splits are 4:1)
    Point("cars400", "cars", 400, "glossy-cars500", (*GLOSSY, "--num-objects", "500"), "cars400"),
    Point("maps160", "maps", 160, "glossy-maps200", (*GLOSSY, "--num-envmaps", "200"), "maps160"),
    # the metallic set (a mirror paint: the input a distorted picture of the map) at the best glossy point
    Point("metallic128", "diagnostic", 128, "metallic-128", ("--dataset", "metallic", "--resolution", "128"),
          "metallic128"),
    # and at the best glossy length (the default's)
    Point("metallic6000", "diagnostic", 6000, "metallic", ("--dataset", "metallic"), "metallic6000",
          ("--iterations", "6000")),
    # the light head told the GT map (a diagnostic variant): what holds it on unseen maps, the input's size, the
    # number of maps or the training's length
    *(Point(name, "diagnostic", 0, data, flags, name, ("--variant", "light-supervised-map", *train))
      for name, data, flags, train in (
          ("light-supervised-map", "glossy", GLOSSY, ()),
          ("res128-light-supervised-map", "glossy-128", (*GLOSSY, "--resolution", "128"), ()),
          ("res128-maps160-light-supervised-map", "glossy-maps200-128",
           (*GLOSSY, "--num-envmaps", "200", "--resolution", "128"), ()),
          ("its6000-light-supervised-map", "glossy", GLOSSY, ("--iterations", "6000")))),
]
BY_NAME = {p.name: p for p in POINTS}


def on_axis(axis: str) -> list[Point]:
    """The axis's points, the base point among them, by value."""
    points = [p for p in POINTS if p.axis == axis] + [BY_NAME["base"]]
    return sorted(points, key=lambda p: p.value or BASE[axis])


def value(p: Point, axis: str) -> int:
    return p.value if p.axis == axis else BASE[axis]


def sh(*cmd: str) -> None:
    """Run a CLI of this project in its own process; stop the study where it fails."""
    print("$", " ".join(cmd), flush=True)
    subprocess.run([sys.executable, *cmd], check=True)


def complete(dataset: Path) -> bool:
    """Whether every sample of ``dataset`` is on disk (datagen writes the manifest first, the samples after)."""
    try:
        MultiViewDataset(dataset, split="all")
    except (DataError, OSError):
        return False
    return True


def run_point(p: Point, folders: Folders, train_args: tuple[str, ...] = ()) -> None:
    """Render (if missing), train (or resume) and evaluate one point on both splits; ``train_args``: flags
    for every new run (a resumed run keeps its own)."""
    if p.gpu and not torch.cuda.is_available():
        print(f"== {p.name}: needs a GPU; skipped")
        return
    print(f"== {p.name}: {p.axis} {p.value or ''}", flush=True)
    dataset, run, out = folders.data / p.dataset, folders.run(p), folders.out
    wrong = mismatch(p, run)
    if wrong:
        raise DataError(f"{run}: trained with {wrong}, so it is not the point {p.name}; move it away and rerun")
    if not complete(dataset):
        sh("-m", "datagen", *p.datagen, "--out", str(dataset), "--quiet")
    device = ("--device", "cuda") if p.gpu else ()
    flags = () if is_run(run) else ("--dataset", str(dataset), "--seed", "0", *train_args, *p.train_flags(), *device)
    sh("-m", "pipelines.train", "--out", str(run), "--resume", "--no-progress", *flags)
    sh("-m", "pipelines.evaluate", "--runs", str(run), "--out", str(out / "test"), *device)
    sh("-m", "pipelines.evaluate", "--runs", str(run), "--out", str(out / "train"), "--split", "train",
       "--view-stride", str(TRAIN_SPLIT_STRIDE), *device)


def evaluated(out: Path, split: str) -> dict[Path, dict]:
    """Every evaluation in ``out/split`` by its run's folder (evaluate names a JSON after the run's folder, not
    its path)."""
    found = {}
    for path in sorted((out / split).glob("*/*.json")):
        try:
            r = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            print(f"warning: {path}: unreadable ({type(e).__name__}); ignored (rerun its point to evaluate it again)",
                  file=sys.stderr)
            continue
        if isinstance(r, dict) and isinstance(r.get("run"), str):
            found[Path(r["run"]).resolve()] = r
    return found


def result(out: Path, split: str, run: Path) -> dict | None:
    """The evaluation of ``run`` in ``out/split``."""
    return evaluated(out, split).get(run.resolve())


def train_minutes(run: Path) -> float | None:
    """The run's training wall time from its summary.json; None (with a warning where the file is broken) if none."""
    path = run / "summary.json"
    if not path.exists():
        return None
    try:
        return float(json.loads(path.read_text())["seconds"]) / 60
    except (OSError, ValueError, KeyError, TypeError) as e:
        print(f"warning: {path}: no training time in it ({type(e).__name__}); the point is tabled without one",
              file=sys.stderr)
        return None


def nominal(p: Point) -> dict:
    """What a point's run must have been trained with: its dataset's folder name, iterations, training cars."""
    words = p.train_flags()
    flags = dict(zip(words[::2], words[1::2]))  # the point's own length last wins
    return {"dataset": p.dataset, "iterations": int(flags["--iterations"]),
            "train_objects": int(flags.get("--train-objects", 0))}


def mismatch(p: Point, run: Path) -> str:
    """How the run in ``run`` differs from what the point stands for ('' where it does not, or is not a run)."""
    if not is_run(run):
        return ""
    try:
        config = load_config(run)
    except DataError as e:
        return str(e)
    trained = {"dataset": Path(config.dataset).name, "iterations": config.iterations,
               "train_objects": config.train_objects}
    return ", ".join(f"{k} {trained[k]!r}, not {v!r}" for k, v in nominal(p).items() if trained[k] != v)


def axis_rows(axis: str, folders: Folders) -> list[dict]:
    """One row per evaluated point of ``axis``: its value, both splits' metrics, its training time."""
    rows, tests, trains = [], evaluated(folders.out, "test"), evaluated(folders.out, "train")
    for p in on_axis(axis):
        run = folders.run(p)
        test, train = tests.get(run.resolve()), trains.get(run.resolve())
        if test is None:
            continue
        wrong = mismatch(p, run)
        if wrong:
            print(f"warning: {p.name}: {run} was trained with {wrong}; left out of the curves", file=sys.stderr)
            continue
        rows.append({"point": p.name, "value": value(p, axis), "run": run, "test": test, "train": train,
                     "minutes": train_minutes(run)})
    return rows


@torch.no_grad()
def predicted_lights(run: Path) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The run's predicted light and the GT map (tone-mapped equirects) in evaluate's figure views of its test
    split: different samples, the same at every point of an axis (the sets share their cars, maps and splits)."""
    loaded = load_run(run)
    ds = MultiViewDataset(loaded.config.dataset, split="test", views_per_item=1)
    b = collate([ds[i] for i in figure_views(ds)])
    pred = loaded.model(encoder_input(b["image"][:, 0]), b["cameras"])
    env = b["envmap"]
    maps = pred.light(b["cameras"].world_to_camera).to_envmap(env.shape[1], env.shape[2]).image
    return [tonemap_envmap(m) for m in maps], [tonemap_envmap(m) for m in env]


def report(folders: Folders) -> None:
    """Every axis's table, curves and light row; every run is read before anything is written, so a broken run
    leaves the earlier report as it was."""
    out = folders.out
    text = ["# Scale study: the SG model about its 1500-iteration base along each axis", "",
            "Test split (unseen cars under unseen maps) unless marked train; (×) is the ratio to a constant map's score.", ""]
    axes = {}
    for axis in BASE:
        rows = axis_rows(axis, folders)
        if len(rows) < 2:
            print(f"{axis}: {len(rows)} point(s) evaluated; no curve")
            continue
        axes[axis] = rows, [predicted_lights(r["run"]) for r in rows]
        text += [f"## {AXIS_LABELS[axis]}", "", table(axis, rows), ""]
    out.mkdir(parents=True, exist_ok=True)
    for axis, (rows, lights) in axes.items():
        plot_axis(axis, rows, out / f"scale_{axis}.png")
        plot_light_row(axis, rows, lights, out / f"scale_{axis}_light.png")
    (out / "scale.md").write_text("\n".join(text))
    print(f"wrote {out}/scale.md and the figures beside it")


def list_points(folders: Folders) -> None:
    tests, trains = evaluated(folders.out, "test"), evaluated(folders.out, "train")
    rows = []
    for p in POINTS:
        run = folders.run(p)
        state = ("not this point" if mismatch(p, run) else
                 "evaluated" if run.resolve() in tests and run.resolve() in trains else
                 "trained" if (run / "summary.json").exists() else "started" if is_run(run) else "-")
        rows.append((p.name, p.axis, p.dataset, str(run), f"{'GPU ' if p.gpu else ''}{state}"))
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    for r in rows:
        print(" ".join(c.ljust(w) for c, w in zip(r, widths)), r[4])


STUDY_FLAGS = ("dataset", "out", "seed", "iterations", "train_objects", "device")  # each point sets these itself


def check_train_args(text: str) -> tuple[str, ...]:
    """--train-args as pipelines.train reads them, checked before anything renders or trains."""
    ap = Parser(prog="--train-args")
    ap.add_argument("--preset", choices=sorted(PRESETS))
    ap.add_argument("--threads", type=int)
    add_config_arguments(ap)
    words = tuple(text.split())
    try:
        args, unknown = ap.parse_known_args(words)
        if unknown:
            raise DataError(f"--train-args: {' '.join(unknown)} is not a training flag")
        overrides = config_overrides(args)
        taken = [name for name in STUDY_FLAGS if name in overrides]
        if taken:
            raise DataError(f"--train-args: {', '.join('--' + n.replace('_', '-') for n in taken)} is what each point "
                            "sets itself (its axis); leave it out")
        TrainConfig(**overrides).validate()
    except (ConfigError, TypeError, ValueError) as e:
        raise DataError(f"--train-args: {e}") from None
    return words


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.scale_study", description=__doc__)
    ap.add_argument("command", choices=("list", "run", "report"))
    ap.add_argument("--points", help="comma-separated point names, in the order to run them (default: every point "
                    "the machine can run, in the listed order)")
    ap.add_argument("--data", default="data", type=Path, help="datasets folder (default: data)")
    ap.add_argument("--runs", default="runs-scale", type=Path, help="the study's own runs (default: runs-scale)")
    ap.add_argument("--out", default="results/scale", type=Path, help="results folder (default: results/scale)")
    ap.add_argument("--train-args", default="", help="flags for every new run, e.g. --train-args='--threads 1' (runs "
                    "that repeat bit for bit)")
    args = ap.parse_args(argv)
    names = [n for n in args.points.split(",") if n] if args.points is not None else [p.name for p in POINTS]
    if not names:
        print("error: --points is empty; name the points to run (python -m pipelines.scale_study list shows them)",
              file=sys.stderr)
        return 2
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        print(f"error: no point {', '.join(unknown)}; the points: {', '.join(BY_NAME)}", file=sys.stderr)
        return 2
    try:
        train_args = check_train_args(args.train_args)
        if args.command == "run" and not args.data.is_dir():
            raise DataError(f"--data {args.data}: no such folder; give the folder the datasets are in (or go in)")
        for flag, folder in (("--runs", args.runs), ("--out", args.out)):
            check_output_folder(flag, folder)
        folders = Folders(args.data, args.runs, args.out)
        if args.command == "list":
            list_points(folders)
        elif args.command == "report":
            report(folders)
        else:
            for name in names:
                run_point(BY_NAME[name], folders, train_args)
    except DataError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except subprocess.CalledProcessError as e:
        print(f"error: {' '.join(e.cmd[1:])} failed (exit {e.returncode}); fix it and rerun to resume", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
