"""Every command line, every argument, bad values: exit status 2, an ``error:`` line that names the argument or the
value, no traceback, and the long work never started.

The arguments come from each CLI's own parser (``parser._actions``), so a new flag is fuzzed without editing this
file: numbers get non-numeric, non-finite, zero and negative values (unless the table below says they are valid
there), choices and free-form strings get garbage, paths get a missing path and a file where a folder is expected
(or the reverse). A path or string flag this file has not classified fails :func:`test_every_flag_is_classified`.

Each CLI's ``main(argv)`` runs in-process with its long work (training, rendering, benchmarking, ...) replaced by
a sentinel: reaching it means the bad value was accepted. The data it would read is faked where a real dataset
would be needed, so nothing here renders or trains.
"""
from __future__ import annotations

import argparse
import importlib
import io
import json
import os
import subprocess
import sys
import traceback
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from unittest import mock

import numpy as np
import pytest
from PIL import Image

from pipelines.training.config import TrainConfig

REPO = Path(__file__).resolve().parents[1]
FAKE_DATASET = "fake-dataset"  # a folder of this name stands for a dataset (see fake_reader)


class Reached(Exception):
    """The CLI accepted every argument and started its long work."""


@dataclass
class Cli:
    name: str  # the command, as a user types it
    main: str  # "module:function" taking argv
    base: list[str]  # valid arguments; {placeholders} are files made by the `world` fixture
    work: tuple[str, ...]  # "module:attribute" where the long work starts (replaced by the sentinel)
    fakes: tuple[str, ...] = ()  # "module:attribute" dataset readers that fake FAKE_DATASET (see fake_reader)
    parser: str | None = None  # "module:function" building the parser (else caught from main)
    command: str | None = None  # subcommand
    paths: dict = field(default_factory=dict)  # dest -> dir-in | file-in | dir-out | file-out
    strings: tuple[str, ...] = ()  # free-form string dests that must refuse garbage
    free: tuple[str, ...] = ()  # dests that accept any value (not fuzzed)
    zero_ok: tuple[str, ...] = ()  # numeric dests where 0 is valid
    negative_ok: tuple[str, ...] = ()  # numeric dests where -1 is valid


STUDY_RUNS = tuple(f"studies.{m}:run" for m in ("noise", "sg_fit", "ambiguity", "joint_fit"))
CLIS = [
    Cli("python -m pipelines.train", "pipelines.train:main",
        ["--dataset", "{data}", "--out", "{out}", "--no-progress"], ("pipelines.train:train",),
        fakes=("pipelines.train:open_train_split",), paths=dict(dataset="dir-in", out="dir-out", config="file-in"),
        strings=("variant", "variant_runs"), zero_ok=("threads",)),
    Cli("python -m pipelines.export_model", "pipelines.export_model:main", ["--run", "{run}", "--out", "{out}"],
        ("pipelines.export_model:export",), paths=dict(run="dir-in", out="dir-out"),
        free=("retrain", "commit")),  # text for the model card
    Cli("python -m pipelines.evaluate", "pipelines.evaluate:main", ["--runs", "{run}", "--out", "{out}"],
        ("pipelines.evaluate:evaluate_and_write",), paths=dict(runs="dir-in", out="dir-out", dataset="dir-in"),
        zero_ok=("refine_steps",)),
    Cli("python -m pipelines.predict", "pipelines.predict:main",
        ["--checkpoint", "{run}", "--image", "{image}", "--out", "{out}"], ("pipelines.predict:load_run",),
        paths=dict(checkpoint="dir-in", image="file-in", out="dir-out", mask="file-in", true_light="file-in"),
        strings=("background",),
        zero_ok=("azimuth", "tolerance", "refine_steps", "elevation"), negative_ok=("azimuth", "elevation")),
    Cli("python -m datagen", "datagen.__main__:main", ["--dataset", "glossy", "--out", "{out}", "--quiet"],
        ("datagen.generate:_make_assets",), parser="datagen.__main__:build_parser",
        paths=dict(out="dir-out", envmaps="dir-in"), strings=("shard", "elevations"),
        zero_ok=("seed", "procedural_envmaps", "max_bounces", "outdoor_share")),
    Cli("python -m pipelines.scale_study", "pipelines.scale_study:main",
        ["run", "--points", "its750", "--data", "{data}", "--runs", "{out}", "--out", "{out}"],
        ("pipelines.scale_study:run_point",), paths=dict(data="dir-in", runs="dir-out", out="dir-out"),
        strings=("points",), free=("train_args",)),
    Cli("python -m pipelines.diagnose_light", "pipelines.diagnose_light:main", ["--run", "{run}"],
        ("pipelines.diagnose_light:diagnose",), paths=dict(run="dir-in", dataset="dir-in")),
    Cli("python -m pipelines.diagnose_sky", "pipelines.diagnose_sky:main", ["--runs", "{run}"],
        ("pipelines.diagnose_sky:diagnose",), paths=dict(runs="dir-in", dataset="dir-in")),
    Cli("python -m pipelines.light_turns", "pipelines.light_turns:main", ["--runs", "{run}", "--out", "{out}"],
        ("pipelines.light_turns:measure",), paths=dict(runs="dir-in", out="dir-out")),
    Cli("python -m pipelines.light_ceiling", "pipelines.light_ceiling:main", ["--dataset", "{data}", "--out", "{out}"],
        ("pipelines.light_ceiling:ceiling",), fakes=("pipelines.light_ceiling:MultiViewDataset",),
        paths=dict(dataset="dir-in", out="dir-out")),
    Cli("python -m pipelines.diagnose_shape", "pipelines.diagnose_shape:main", ["--dataset", "{data}"],
        ("pipelines.diagnose_shape:diagnose",), paths=dict(dataset="dir-in"), strings=("signals",)),
    Cli("python -m dibrpp render", "dibrpp.cli:main",
        ["--mesh", "{mesh}", "--envmap", "{envmap}", "--out", "{outfile}"], ("dibrpp.io:load_mesh",),
        parser="dibrpp.cli:build_parser", command="render",
        paths=dict(mesh="file-in", texture="file-in", envmap="file-in", out="file-out"), strings=("albedo",),
        zero_ok=("roughness", "metallic", "specular", "elevation", "azimuth", "seed"),
        negative_ok=("elevation", "azimuth", "seed")),  # torch takes any 64-bit seed
    Cli("python -m studies", "studies.__main__:main", ["--out", "{out}"], STUDY_RUNS,
        paths=dict(out="dir-out"), strings=("only",), zero_ok=("threads",)),
    Cli("python -m studies.noise_study", "studies.noise_study:main", ["--out", "{out}"],
        ("studies.noise_study:make_objects",), parser="studies.noise_study:build_parser", paths=dict(out="dir-out")),
    Cli("python -m studies.reflections", "studies.reflections:main", ["--dataset", "{data}", "--out", "{out}"],
        ("studies.reflections:Renderer",), fakes=("studies.reflections:MultiViewDataset",),
        paths=dict(dataset="dir-in", out="dir-out"), zero_ok=("threads",)),
    Cli("python -m benchmarks.renderer", "benchmarks.renderer:main", ["--out", "{out}"],
        ("benchmarks.renderer:bench_training",), paths=dict(out="dir-out")),
    Cli("python -m benchmarks.train_step", "benchmarks.train_step:main", ["--dataset", "{data}", "--out", "{out}"],
        ("benchmarks.train_step:time_iterations",), fakes=("benchmarks.train_step:MultiViewDataset",),
        paths=dict(dataset="dir-in", out="dir-out"), zero_ok=("warmup", "profile", "threads"), strings=("variant",)),
    Cli("python -m benchmarks.mitsuba", "benchmarks.mitsuba:main", ["--out", "{out}", "--runs", "dibrpp"],
        ("benchmarks.mitsuba:run_renderer",), paths=dict(out="dir-out"), strings=("runs",),
        free=("variant",)),  # the Mitsuba variant only matters to Mitsuba's columns
]
BY_NAME = {c.name: c for c in CLIS}


# Bad values a CLI is known to still accept or crash on, "<cli> <flag> <value>": reason (strict xfails: a fixed one
# fails here until it is taken off this list). None today.
KNOWN: dict[str, str] = {}


# ----------------------------------------------------------------------------- the parsers and their arguments

def _resolve(target: str):
    module, attr = target.split(":")
    return getattr(importlib.import_module(module), attr)


class _Caught(Exception):
    pass


def cli_parser(cli: Cli) -> argparse.ArgumentParser:
    """The CLI's parser (its subcommand's), built by its builder or caught from main at parse time."""
    if cli.parser:
        parser = _resolve(cli.parser)()
    else:
        def catch(self, *args, **kwargs):
            raise _Caught(self)

        with mock.patch.object(argparse.ArgumentParser, "parse_args", catch):
            try:
                _resolve(cli.main)([])
            except _Caught as caught:
                parser = caught.args[0]
    if cli.command:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[cli.command]
    return parser


def fuzzed_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """Options that take a value and are shown in --help (hidden ones are internal plumbing)."""
    return [a for a in parser._actions if a.option_strings and a.nargs != 0 and a.help != argparse.SUPPRESS
            and not isinstance(a, (argparse._HelpAction, argparse.BooleanOptionalAction))]


def numeric_kind(action: argparse.Action):
    """int or float if the argument parses numbers, else None."""
    if action.type is None or action.choices is not None:
        return None
    refused = (ValueError, TypeError, argparse.ArgumentTypeError)
    try:
        one = action.type("1")
    except refused:
        return None
    if isinstance(one, bool) or not isinstance(one, (int, float)):
        return None
    try:
        return float if isinstance(action.type("1.5"), float) else int
    except refused:
        return int


def config_bad_values(dest: str, kind) -> list[str] | None:
    """A TrainConfig field's out-of-range values, from its declared minimum."""
    meta = next((f.metadata for f in TrainConfig.__dataclass_fields__.values() if f.name == dest), None)
    if meta is None or meta.get("minimum") is None:
        return None
    low = meta["minimum"]
    below = [str(low - 1)] if kind is int else [str(low - 0.5)]
    return below + (["0"] if dest == "lr" else [])


def bad_values(cli: Cli, action: argparse.Action) -> list[str] | None:
    """Values this argument must refuse; None if the argument is not classified."""
    dest = action.dest
    if dest in cli.free:
        return []
    if dest in cli.paths:
        return {"dir-in": ["{missing}", "{a_file}"], "file-in": ["{missing}", "{a_dir}"],
                "dir-out": ["{a_file}", "{a_file}/sub"], "file-out": ["{a_dir}", "{missing}/out.png"]}[cli.paths[dest]]
    if action.choices is not None:
        return ["garbage-choice"]
    kind = numeric_kind(action)
    if kind is None:
        return ["garbage!"] if dest in cli.strings else None
    values = ["abc"] + (["nan", "inf"] if kind is float else [])
    from_config = config_bad_values(dest, kind) if cli.name == "python -m pipelines.train" else None
    if from_config is not None:
        return values + from_config
    return (values + ([] if dest in cli.zero_ok else ["0"]) + ([] if dest in cli.negative_ok else ["-1"]))


def cases():
    for cli in CLIS:
        for action in fuzzed_actions(cli_parser(cli)):
            for value in bad_values(cli, action) or []:
                case_id = f"{cli.name} {action.option_strings[-1]} {value}"
                marks = [pytest.mark.xfail(reason=KNOWN[case_id], strict=True)] if case_id in KNOWN else []
                yield pytest.param(cli.name, action.option_strings[-1], action.dest, value, id=case_id, marks=marks)


# ----------------------------------------------------------------------------- running a CLI in-process

def fake_reader(real):
    """``real`` (a dataset reader) for any folder but FAKE_DATASET, which reads as a small glossy set."""
    def read(root, *args, **kwargs):
        if Path(root).name != FAKE_DATASET or not Path(root).is_dir():
            return real(root, *args, **kwargs)
        camera = SimpleNamespace(distance=4.0, elevation_deg=20.0, fov_deg=40.0, azimuths_deg=[0.0, 90.0])
        return SimpleNamespace(has_metals=False, resolution=32, camera_setup=camera, samples=[], materials={},
                               root=str(root))
    return read


def _sentinel(*args, **kwargs):
    raise Reached


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict:
    """The files the base arguments and the bad values name."""
    root = tmp_path_factory.mktemp("fuzz")
    (root / FAKE_DATASET).mkdir()
    run = root / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(TrainConfig(dataset=str(root / FAKE_DATASET)).to_dict()))
    (run / "checkpoint.pt").write_bytes(b"not read: the work is faked")
    rgba = np.zeros((16, 16, 4), np.uint8)
    rgba[4:12, 4:12] = 200
    Image.fromarray(rgba).save(root / "image.png")
    (root / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (root / "envmap.exr").write_bytes(b"not read: the work is faked")
    (root / "a-file.txt").write_text("a file")
    (root / "a-dir").mkdir()
    return dict(data=root / FAKE_DATASET, run=run, image=root / "image.png", mesh=root / "mesh.obj",
                envmap=root / "envmap.exr", a_file=root / "a-file.txt", a_dir=root / "a-dir",
                missing=root / "missing" / "nothing", root=root)


def fill(text: str, world: dict, tmp_path: Path) -> str:
    return text.format(**{k: str(v) for k, v in world.items()}, out=str(tmp_path / "out"),
                       outfile=str(tmp_path / "out.png"))


def run_cli(cli: Cli, argv: list[str]) -> tuple[object, str]:
    """(exit status, or "reached" / the traceback of an exception that escaped; stdout + stderr)."""
    patches = [mock.patch(target.replace(":", "."), _sentinel) for target in cli.work]
    patches += [mock.patch(target.replace(":", "."), fake_reader(_resolve(target))) for target in cli.fakes]
    text = io.StringIO()
    for p in patches:
        p.start()
    try:
        with redirect_stdout(text), redirect_stderr(text):
            status = _resolve(cli.main)(([cli.command] if cli.command else []) + argv)
    except SystemExit as e:
        status = e.code
    except Reached:
        status = "reached"
    except Exception:  # noqa: BLE001 (what a user would see as a traceback)
        status = traceback.format_exc()
    finally:
        for p in reversed(patches):
            p.stop()
    return status, text.getvalue()


def with_value(base: list[str], flag: str, value: str) -> list[str]:
    """``base`` with ``flag`` set to ``value`` (its own setting, if any, taken out)."""
    argv = list(base)
    if flag in argv:
        i = argv.index(flag)
        del argv[i:i + 2]
    return argv + [flag, value]


# ----------------------------------------------------------------------------- the tests

@pytest.mark.parametrize("name", list(BY_NAME))
def test_the_base_arguments_reach_the_work(name, world, tmp_path):
    """The fuzz is only meaningful if the valid base arguments get as far as the (faked) work."""
    cli = BY_NAME[name]
    status, output = run_cli(cli, [fill(a, world, tmp_path) for a in cli.base])
    assert status == "reached", output + str(status)


@pytest.mark.parametrize("name", list(BY_NAME))
def test_every_flag_is_classified(name):
    """A new path or string flag needs a line in CLIS (what it expects); numbers and choices are automatic."""
    cli = BY_NAME[name]
    unclassified = [a.option_strings[-1] for a in fuzzed_actions(cli_parser(cli)) if bad_values(cli, a) is None]
    assert not unclassified, f"{name}: say in CLIS what {unclassified} expect (paths / strings / free)"


def test_every_command_line_is_fuzzed():
    """Every module run with ``python -m`` (it has a ``__main__`` guard) is in CLIS."""
    entry = {"dibrpp.__main__": "dibrpp.cli"}  # python -m dibrpp runs dibrpp.cli.main
    found = set()
    for package in ("pipelines", "datagen", "dibrpp", "benchmarks", "studies"):
        for path in (REPO / package).glob("*.py"):
            if 'if __name__ == "__main__"' in path.read_text():
                module = f"{package}.{path.stem}"
                found.add(entry.get(module, module))
    covered = {c.main.split(":")[0] for c in CLIS}
    assert found <= covered, f"add to CLIS: {sorted(found - covered)}"


@pytest.mark.parametrize("name, flag, dest, value", list(cases()))
def test_a_bad_value_is_one_clear_error(name, flag, dest, value, world, tmp_path):
    cli = BY_NAME[name]
    bad = fill(value, world, tmp_path)
    status, output = run_cli(cli, with_value([fill(a, world, tmp_path) for a in cli.base], flag, bad))
    assert status != "reached", f"{name} {flag} {bad!r} was accepted: the work started"
    assert "Traceback" not in str(status) + output, f"{name} {flag} {bad!r}:\n{status}\n{output}"
    assert status == 2, f"{name} {flag} {bad!r}: exit status {status}\n{output}"
    errors = [line for line in output.splitlines() if "error:" in line]
    assert errors, output
    names = (flag, dest, dest.replace("_", "-"), bad, Path(bad).name)
    assert any(n.lower() in line.lower() for line in errors for n in names), \
        f"the error does not name {flag} or {bad!r}: {errors}"


def test_the_help_of_every_command_line_shows_defaults():
    """Every option with a default says it in --help (types show as metavars or choices)."""
    missing = {}
    for cli in CLIS:
        parser = cli_parser(cli)
        formatter = parser._get_formatter()
        for action in fuzzed_actions(parser):
            if action.default is None or action.default is False or action.default in ("", []):
                continue
            if "default" not in (formatter._expand_help(action) if action.help else "").lower():
                missing.setdefault(cli.name, []).append(action.option_strings[-1])
    assert not missing, f"--help shows no default for: {missing}"


def test_an_unknown_subcommand_of_dibrpp(world, tmp_path):
    status, output = run_cli(Cli("python -m dibrpp", "dibrpp.cli:main", [], ()), ["garbage"])
    assert status == 2 and "error:" in output and "garbage" in output and "Traceback" not in output


@pytest.mark.parametrize("name", list(BY_NAME))
def test_python_dash_m_answers_an_unknown_option_with_status_2(name):
    """The ``python -m`` wiring itself (``sys.exit(main())``): an unknown option is an argparse error."""
    cli = BY_NAME[name]
    module = name.split()[2]
    command = [sys.executable, "-m", module, *([cli.command] if cli.command else []), "--no-such-option"]
    r = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=REPO,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert r.returncode == 2 and "error:" in r.stderr and "Traceback" not in r.stderr, r.stderr
