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


def test_an_unknown_point_is_refused_by_name(capsys):
    assert scale_study.main(["run", "--points", "res128,res99"]) == 2
    assert "no point res99" in capsys.readouterr().err


@pytest.mark.slow  # two smoke runs, each trained and evaluated twice in its own process: ~2 min on 2 cores (resuming is train's and evaluate's, tested there)
def test_the_study_trains_evaluates_both_splits_and_draws_each_axis(tiny_glossy, tmp_path, monkeypatch, capsys):
    points = [scale_study.Point("base", "base", 0, "glossy", (), "glossy/sg-seed0", main=True),
              scale_study.Point("cars2", "cars", 2, "glossy", (), "cars2", ("--train-objects", "2")),
              scale_study.Point("gpu", "resolution", 256, "glossy", (), "gpu", gpu=True)]
    monkeypatch.setattr(scale_study, "POINTS", points)
    monkeypatch.setattr(scale_study, "BY_NAME", {p.name: p for p in points})
    runs, main_runs, out = tmp_path / "runs-scale", tmp_path / "runs", tmp_path / "out"
    where = ["--data", str(tiny_glossy.parent), "--runs", str(runs), "--main-runs", str(main_runs), "--out", str(out)]
    points_to_run = "base,cars2" if torch.cuda.is_available() else "base,cars2,gpu"
    assert scale_study.main(["run", *where, "--points", points_to_run,
                             "--train-args=--preset smoke --iterations 2 --shading sg --lobes 4"]) == 0
    said = capsys.readouterr().out
    if not torch.cuda.is_available():
        assert "gpu: needs a GPU; skipped" in said and not (runs / "gpu").exists()
    assert json.loads((runs / "cars2" / "config.json").read_text())["train_objects"] == 2
    for split in ("test", "train"):
        r = scale_study.result(out, split, runs / "cars2")
        assert r["split"] == split and r["iteration"] == 2
    assert scale_study.result(out, "train", main_runs / "glossy" / "sg-seed0")["view_stride"] == scale_study.TRAIN_SPLIT_STRIDE

    scale_study.main(["list", *where])
    listed = capsys.readouterr().out
    assert "cars2" in listed and "evaluated" in listed

    scale_study.main(["report", *where])
    assert "resolution: 1 point(s) evaluated; no curve" in capsys.readouterr().out
    table = (out / "scale.md").read_text()
    assert "## training cars" in table and "| 2 |" in table and "| 80 |" in table
    for png in ("scale_cars.png", "scale_cars_light.png"):
        assert (out / png).stat().st_size > 5000
