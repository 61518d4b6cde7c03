"""The scale study's runner on the real tiny dataset: each point trained, evaluated on both splits, plotted."""
import json

import pytest
import torch

from pipelines import scale_study


def test_each_axis_holds_the_base_point_and_at_least_four_points_in_order():
    for axis, base in scale_study.BASE.items():
        points = scale_study.on_axis(axis)
        values = [scale_study.value(p, axis) for p in points]
        assert values == sorted(values) and base in values, axis
        assert "base" in [p.name for p in points]
    assert all(len(scale_study.on_axis(a)) >= 4 for a in ("resolution", "iterations", "cars"))


def test_every_point_trains_at_the_study_s_base_length_unless_it_sets_its_own():
    from pipelines.training.config import TrainConfig

    assert scale_study.BASE["iterations"] != TrainConfig().iterations  # the study's own base, not the default's length
    for name in ("base", "cars10", "res128", "maps160", "light-supervised-map"):
        assert scale_study.nominal(scale_study.BY_NAME[name])["iterations"] == scale_study.BASE["iterations"], name
    assert scale_study.nominal(scale_study.BY_NAME["its3000"])["iterations"] == 3000


def test_an_unknown_point_is_refused_by_name(capsys):
    assert scale_study.main(["run", "--points", "res128,res99"]) == 2
    assert "no point res99" in capsys.readouterr().err


# two smoke runs, each trained and evaluated twice in its own process, eagerly (a cold torch.compile in each process
# took most of the 140 s it ran): resuming is train's and evaluate's, tested there
@pytest.mark.slow
def test_the_study_trains_evaluates_both_splits_and_draws_each_axis(tiny_glossy, tmp_path, monkeypatch, capsys):
    two = ("--iterations", "2")  # the points' own length: a run is a point's only if trained as the point says
    points = [scale_study.Point("base", "base", 0, "glossy", (), "base", two),
              scale_study.Point("cars2", "cars", 2, "glossy", (), "cars2", ("--train-objects", "2", *two)),
              scale_study.Point("gpu", "resolution", 256, "glossy", (), "gpu", gpu=True)]
    monkeypatch.setattr(scale_study, "POINTS", points)
    monkeypatch.setattr(scale_study, "BY_NAME", {p.name: p for p in points})
    runs, out = tmp_path / "runs-scale", tmp_path / "out"
    where = ["--data", str(tiny_glossy.parent), "--runs", str(runs), "--out", str(out)]
    points_to_run = "base,cars2" if torch.cuda.is_available() else "base,cars2,gpu"
    assert scale_study.main(["run", *where, "--points", points_to_run,
                             "--train-args=--preset smoke --shading sg --lobes 4 --no-compile"]) == 0
    said = capsys.readouterr().out
    if not torch.cuda.is_available():
        assert "gpu: needs a GPU; skipped" in said and not (runs / "gpu").exists()
    assert json.loads((runs / "cars2" / "config.json").read_text())["train_objects"] == 2
    for split in ("test", "train"):
        r = scale_study.result(out, split, runs / "cars2")
        assert r["split"] == split and r["iteration"] == 2
    assert scale_study.result(out, "train", runs / "base")["view_stride"] == scale_study.TRAIN_SPLIT_STRIDE

    scale_study.main(["list", *where])
    listed = capsys.readouterr().out
    assert "cars2" in listed and "evaluated" in listed

    scale_study.main(["report", *where])
    assert "resolution: 1 point(s) evaluated; no curve" in capsys.readouterr().out
    table = (out / "scale.md").read_text()
    assert "## training cars" in table and "| 2 |" in table and "| 80 |" in table
    for png in ("scale_cars.png", "scale_cars_light.png"):
        assert (out / png).stat().st_size > 5000


def _where(tmp_path):
    return ["--data", str(tmp_path / "data"), "--runs", str(tmp_path / "runs-scale"), "--out",
            str(tmp_path / "out" / "scale")]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    return err


def test_list_and_report_need_no_data_and_report_makes_its_folder(tmp_path, capsys):
    assert scale_study.main(["list", *_where(tmp_path)]) == 0  # a fresh checkout has no data/ yet
    assert "base" in capsys.readouterr().out
    assert scale_study.main(["report", *_where(tmp_path)]) == 0
    assert (tmp_path / "out" / "scale" / "scale.md").exists()


def test_a_corrupt_evaluation_is_ignored_with_a_warning_naming_it(tmp_path, capsys):
    broken = tmp_path / "out" / "scale" / "test" / "glossy" / "its750.json"
    broken.parent.mkdir(parents=True)
    broken.write_text('{"run": ')
    for command in ("list", "report"):
        assert scale_study.main([command, *_where(tmp_path)]) == 0
        assert f"warning: {broken}: unreadable" in capsys.readouterr().err


@pytest.mark.parametrize("args, said", [
    (["--points", ""], "--points is empty"),
    (["--train-args=--iterations 5"], "--iterations is what each point sets itself"),
    (["--train-args=--train-objects 5"], "--train-objects is what each point sets itself"),
    (["--train-args=--no-such-flag"], "--no-such-flag is not a training flag"),
    (["--train-args=--lr -1"], "--train-args: "),
    (["--bogus"], "unrecognized arguments"),
])
def test_bad_flags_are_one_error_line_before_anything_runs(tmp_path, capsys, args, said):
    try:
        status = scale_study.main(["run", *_where(tmp_path), *args])
    except SystemExit as e:  # argparse's own errors
        status = e.code
    assert status == 2
    assert said in _one_error_line(capsys)
    assert not (tmp_path / "runs-scale").exists()


def test_a_run_that_is_not_what_its_point_says_is_neither_tabled_nor_resumed(tmp_path, capsys):
    from pipelines.training.config import TrainConfig

    base = tmp_path / "runs-scale" / "base"  # a 4-iteration run where the 1500-iteration base belongs
    base.mkdir(parents=True)
    (base / "config.json").write_text(json.dumps(TrainConfig(dataset=str(tmp_path / "data" / "glossy"),
                                                             iterations=4).to_dict()))
    (base / "checkpoint.pt").write_bytes(b"")
    (tmp_path / "data").mkdir()
    assert scale_study.main(["list", *_where(tmp_path)]) == 0
    assert "not this point" in [line for line in capsys.readouterr().out.splitlines() if line.startswith("base ")][0]
    assert scale_study.main(["run", *_where(tmp_path), "--points", "base"]) == 2
    assert "iterations 4, not 1500" in _one_error_line(capsys)


def test_a_broken_summary_is_tabled_without_a_time_and_a_broken_run_stops_the_report_before_any_figure(
        tmp_path, monkeypatch, capsys):
    run = tmp_path / "runs-scale" / "its750"
    run.mkdir(parents=True)
    (run / "summary.json").write_text("{garbage")
    assert scale_study.train_minutes(run) is None and "summary.json: no training time" in capsys.readouterr().err
    (run / "summary.json").write_text('{"iterations": 750}')
    assert scale_study.train_minutes(run) is None and "no training time" in capsys.readouterr().err
    (run / "config.json").write_text("{}")
    (run / "checkpoint.pt").write_bytes(b"PK\x03\x04 truncated")
    rows = [{"point": name, "value": v, "run": run, "test": {}, "train": None, "minutes": None}
            for name, v in (("its750", 750), ("base", 1500))]
    monkeypatch.setattr(scale_study, "axis_rows", lambda axis, folders: rows if axis == "iterations" else [])
    monkeypatch.setattr(scale_study, "table", lambda axis, rows: "")
    assert scale_study.main(["report", *_where(tmp_path)]) == 2
    assert "checkpoint.pt" in _one_error_line(capsys)
    assert not list((tmp_path / "out").rglob("*.png")) and not list((tmp_path / "out").rglob("scale.md"))
