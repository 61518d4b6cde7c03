"""Evaluation of a (smoke) trained run on the real tiny dataset's test split."""
import json

import pytest

from pipelines import evaluate, train


def test_evaluate_finds_runs_and_writes_metrics(tiny_glossy, tiny_glossy_two_maps, tmp_path):
    runs = tmp_path / "runs"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--image-size", "32",
                       "--shading", "sh", "--iterations", "2", "--out", str(runs / "glossy" / "sh-seed0"),
                       "--no-progress"]) == 0
    out = tmp_path / "eval"
    assert evaluate.main(["--runs", str(runs), "--out", str(out)]) == 0
    r = json.loads((out / "glossy" / "sh-seed0.json").read_text())
    assert r["shading"] == "sh" and r["iteration"] == 2 and r["test_views"] > 0
    for k in ("iou", "light", "texture", "light_constant"):
        assert 0 <= r[k] <= 1, (k, r[k])
    assert r["image"] > 0 and 0 < r["chamfer"] < 1
    assert len(r["direction_deg_views"]) == len(r["direction_deg_constant_views"]) == r["views_with_dominant_light"]
    if r["views_with_dominant_light"]:
        lo, hi = r["direction_within_25_ci"]
        assert 0 <= lo <= r["direction_within_25"] <= hi <= 1 and r["samples_with_dominant_light"] >= 1
        assert f"{100 * r['direction_within_25']:.0f} % (" in (out / "all_runs.md").read_text()
    assert "| glossy | sh |" in (out / "all_runs.md").read_text()
    assert (out / "glossy" / "sh-seed0.png").stat().st_size > 1000 and (out / "tables.md").exists()
    assert (out / "glossy" / "sh-seed0_failures.png").stat().st_size > 1000
    assert "sh-seed0_failures.png" in (out / "report.html").read_text()
    assert evaluate.main(["--runs", str(tmp_path / "nothing"), "--out", str(out)]) == 2
    # the same run on its training views (the train/test gap)
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-train"), "--split", "train"]) == 0
    t = json.loads((tmp_path / "eval-train" / "glossy" / "sh-seed0.json").read_text())
    assert t["split"] == "train" and r["split"] == "test" and t["test_views"] > 0 and t["run"] == r["run"]
    assert t["image"] != r["image"]  # other views
    # ... and on another dataset's test split (the same kind of objects under other env maps)
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-other"),
                          "--dataset", str(tiny_glossy_two_maps)]) == 0
    o = json.loads((tmp_path / "eval-other" / "glossy-two-maps" / "sh-seed0.json").read_text())
    assert o["dataset"] == "glossy-two-maps" and o["trained_on"] == "glossy" and r["trained_on"] == "glossy"
    assert o["test_views"] > 0 and o["image"] != r["image"]
    assert "| glossy-two-maps (trained on glossy) | sh |" in (tmp_path / "eval-other" / "all_runs.md").read_text()
    # ... every sample of it (no run trained on it); refused on a run's own dataset, where it trained on some
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all"), "--dataset", str(tiny_glossy_two_maps),
                          "--split", "all"]) == 0
    a = json.loads((tmp_path / "eval-all" / "glossy-two-maps" / "sh-seed0.json").read_text())
    assert a["split"] == "all" and a["test_views"] > o["test_views"]
    with pytest.raises(SystemExit):
        evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all-own"), "--split", "all"])
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all-own"), "--split", "all",
                          "--dataset", str(tiny_glossy)]) != 0


def test_direction_figure_shows_default_seed0_runs_with_views_that_have_a_dominant_light(tmp_path):
    def result(dataset, shading, errors, variant=""):
        median = float(sorted(errors)[len(errors) // 2]) if errors else float("nan")
        return dict(dataset=dataset, shading=shading, seed=0, variant=variant, direction_deg=median,
                    direction_deg_views=errors, direction_deg_constant=60.0,
                    direction_deg_constant_views=[50.0, 60.0, 70.0][:len(errors)])

    results = [result("glossy", "sg", [10.0, 20.0, 90.0]), result("glossy", "sh", [30.0, 40.0, 120.0]),
               result("glossy", "sg", [1.0, 2.0, 3.0], variant="light_colour=free"),  # an ablation: not shown
               result("diffuse", "sg", [])]  # no view with a dominant light: no figure
    written = evaluate.write_direction_figures(results, tmp_path)
    assert written == [tmp_path / "direction_glossy.png"] and written[0].stat().st_size > 1000


def _fake_run(folder, dataset):
    from pipelines.config import TrainConfig

    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(TrainConfig(dataset=dataset).to_dict()))
    (folder / "checkpoint.pt").write_bytes(b"never read here")
    return folder


def test_runs_that_share_a_folder_name_keep_their_results_apart(tmp_path, capsys):
    from unittest import mock

    from dibrpp.io import DataError
    from pipelines.runs import find_runs

    root, out = tmp_path / "runs", tmp_path / "eval"
    for parent in ("a", "b"):
        _fake_run(root / parent / "sg-seed0", "data/glossy")
    _fake_run(root / "a" / "mc-seed0", "data/glossy")
    _fake_run(root / "b" / "mc-seed0", "data/metallic")  # same name, other dataset: no collision
    paths = evaluate.result_paths(find_runs(root), root, out, None)
    assert sorted(str(p.relative_to(out)) for p in paths.values()) == [
        "glossy/a__sg-seed0.json", "glossy/b__sg-seed0.json", "glossy/mc-seed0.json", "metallic/mc-seed0.json"]
    # every run on one --dataset: now the mc runs collide too
    on_one = evaluate.result_paths(find_runs(root), root, out, "data/other")
    assert sorted(p.name for p in on_one.values()) == ["a__mc-seed0.json", "a__sg-seed0.json", "b__mc-seed0.json",
                                                       "b__sg-seed0.json"]
    # unique names stay as they were: <dataset>/<run folder name>.json
    alone = evaluate.result_paths(find_runs(root / "a"), root / "a", out, None)
    assert sorted(str(p.relative_to(out)) for p in alone.values()) == ["glossy/mc-seed0.json", "glossy/sg-seed0.json"]
    # main writes each run to its own path
    written = []

    def record(run, path, key, args):
        written.append(path)
        raise DataError("not evaluated in this test")

    with mock.patch.object(evaluate, "evaluate_and_write", record):
        assert evaluate.main(["--runs", str(root), "--out", str(out)]) == 2
    assert sorted(written) == sorted(paths.values())
    # a run whose own name is another's joined path: refused, naming the file, before any evaluation
    _fake_run(root / "a__sg-seed0", "data/glossy")
    written.clear()
    with mock.patch.object(evaluate, "evaluate_and_write", record):
        assert evaluate.main(["--runs", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert not written and err[-1].startswith("error: --runs") and "a__sg-seed0.json" in err[-1]
