"""Evaluation of a (smoke) trained run on the real tiny dataset's test split."""
import json
import shutil
from pathlib import Path
from types import SimpleNamespace
from unittest import mock

import pytest

from dibrpp.io import DataError
from pipelines import evaluate, scoring
from pipelines.evaluation import summary
from pipelines.training import runs
from pipelines import train


def test_evaluate_finds_runs_and_writes_metrics(tiny_glossy, tiny_glossy_two_maps, tmp_path, capsys):
    runs = tmp_path / "runs"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy),
                       "--shading", "sh", "--iterations", "2", "--out", str(runs / "glossy" / "sh-seed0"),
                       "--no-progress", "--no-compile"]) == 0  # evaluated eagerly too: three evaluations, no compile
    out = tmp_path / "eval"
    capsys.readouterr()
    assert evaluate.main(["--runs", str(runs), "--out", str(out)]) == 0
    r = json.loads((out / "glossy" / "sh-seed0.json").read_text())
    assert r["shading"] == "sh" and r["iteration"] == 2 and r["test_views"] > 0 and r["dataset_kind"] == "glossy"
    for k in ("iou", "light_ldr", "light_hdr", "texture", *summary.CONSTANT_REFERENCES):
        assert k.startswith(("colour", "direction")) or 0 <= r[k] <= 1, (k, r[k])
    assert r["image_whole"] > 0 and r["image_foreground"] > 0 and 0 < r["chamfer"] < 1
    # the material beside the data's: the levels within their ranges, the scales positive
    assert 0 <= r["specular_level"] <= 1 and 0 <= r["specular_level_gt"] <= 1 and 0 <= r["roughness_error"] <= 1
    assert r["albedo_scale"] > 0 and r["light_scale"] > 0
    assert len(r["direction_deg_views"]) == len(r["direction_deg_constant_views"]) == r["views_with_dominant_light"]
    # the tiny set's one test object is lit by a map its train split uses too, and it is one sample: said, once each
    err = capsys.readouterr().err
    assert r["samples"] == 1 and r["envmaps_in_train_split"] == r["envmaps"] == 1
    assert err.count("warning: glossy's test split is lit by 1 of its 1 env maps that its train split also uses") == 1
    assert err.count("warning: glossy's test split holds 1 samples") == 1
    assert "| glossy | sh |" in (out / "all_runs.md").read_text()
    assert (out / "glossy" / "sh-seed0.png").stat().st_size > 1000 and (out / "tables.md").exists()
    assert (out / "glossy" / "sh-seed0_failures.png").stat().st_size > 1000
    assert "sh-seed0_failures.png" in (out / "report.html").read_text()
    assert evaluate.main(["--runs", str(tmp_path / "nothing"), "--out", str(out)]) == 2
    # the same run on its training views (the train/test gap)
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-train"), "--split", "train"]) == 0
    t = json.loads((tmp_path / "eval-train" / "glossy" / "sh-seed0.json").read_text())
    assert t["split"] == "train" and r["split"] == "test" and t["test_views"] > 0 and t["run"] == r["run"]
    assert t["image_whole"] != r["image_whole"]  # other views
    titles = [line for line in (tmp_path / "eval-train" / "tables.md").read_text().splitlines() if line.startswith("**")]
    assert titles and all("(train split" in line or "; train split" in line for line in titles), titles
    assert "test split" not in (tmp_path / "eval-train" / "tables.md").read_text()
    # ... and on another dataset's test split (the same kind of objects under other env maps)
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-other"),
                          "--dataset", str(tiny_glossy_two_maps)]) == 0
    o = json.loads((tmp_path / "eval-other" / "glossy-two-maps" / "sh-seed0.json").read_text())
    assert o["dataset"] == "glossy-two-maps" and o["trained_on"] == "glossy" and r["trained_on"] == "glossy"
    assert o["test_views"] > 0 and o["image_whole"] != r["image_whole"]
    assert "| glossy-two-maps (trained on glossy) | sh |" in (tmp_path / "eval-other" / "all_runs.md").read_text()
    # a glossy set by its manifest, whatever its folder is called: in Table 1
    assert "| glossy-two-maps (glossy) / DIB-R (SH) |" in (tmp_path / "eval-other" / "tables.md").read_text()
    # ... every sample of it (no run trained on it); refused on a run's own dataset, where it trained on some
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all"), "--dataset", str(tiny_glossy_two_maps),
                          "--split", "all"]) == 0
    a = json.loads((tmp_path / "eval-all" / "glossy-two-maps" / "sh-seed0.json").read_text())
    assert a["split"] == "all" and a["test_views"] > o["test_views"]
    with pytest.raises(SystemExit):
        evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all-own"), "--split", "all"])
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-all-own"), "--split", "all",
                          "--dataset", str(tiny_glossy)]) != 0
    # a set of another image size than the run was trained at: refused, naming both sizes and what to do
    other = Path(shutil.copytree(tiny_glossy, tmp_path / "glossy-48"))
    manifest = json.loads((other / "manifest.json").read_text())
    manifest["config"]["resolution"] = 48
    (other / "manifest.json").write_text(json.dumps(manifest))
    capsys.readouterr()
    assert evaluate.main(["--runs", str(runs), "--out", str(tmp_path / "eval-48"), "--dataset", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: 1 of 1 runs could not be evaluated") and "trained on 32x32 images" in err[-1]
    assert "holds 48x48" in err[-1] and "--resolution 32" in err[-1]
    assert not list((tmp_path / "eval-48").glob("*/*.json"))


def test_direction_figure_shows_default_seed0_runs_with_views_that_have_a_dominant_light(tmp_path):
    def result(dataset, shading, errors, variant=""):
        median = float(sorted(errors)[len(errors) // 2]) if errors else float("nan")
        return dict(dataset=dataset, shading=shading, seed=0, variant=variant, direction_deg=median,
                    direction_deg_views=errors, direction_deg_constant=60.0,
                    direction_deg_constant_views=[50.0, 60.0, 70.0][:len(errors)])

    results = [result("glossy", "sg", [10.0, 20.0, 90.0]), result("glossy", "sh", [30.0, 40.0, 120.0]),
               result("glossy", "sg", [1.0, 2.0, 3.0], variant="light_colour=free"),  # an ablation: not shown
               result("diffuse", "sg", [])]  # no view with a dominant light: no figure
    written = summary.write_direction_figures(results, tmp_path)
    assert written == [tmp_path / "direction_glossy.png"] and written[0].stat().st_size > 1000


def _fake_run(folder, dataset):
    from pipelines.training.config import TrainConfig

    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(TrainConfig(dataset=dataset).to_dict()))
    (folder / "checkpoint.pt").write_bytes(b"never read here")
    return folder


def test_runs_that_share_a_folder_name_keep_their_results_apart(tmp_path, capsys):
    from pipelines.training.runs import find_runs

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


def test_runs_of_one_name_evaluated_in_separate_calls_into_one_out_keep_their_results_apart(tmp_path):
    from pipelines.training.runs import find_runs

    runs, out = tmp_path / "runs", tmp_path / "eval"
    first, second = (_fake_run(runs / p / "sg-seed0", "data/glossy") for p in ("glossy", "glossy-maps200"))
    (out / "other").mkdir(parents=True)  # the first call's result, on --dataset data/other
    (out / "other" / "sg-seed0.json").write_text(json.dumps({"run": str(first)}))
    assert evaluate.result_paths(find_runs(first), first, out, "data/other") == {first: out / "other" / "sg-seed0.json"}
    assert evaluate.result_paths(find_runs(second), second, out, "data/other") == {
        second: out / "other" / "glossy-maps200__sg-seed0.json"}


def _fake_result(run, path, key, args):
    """What evaluate_and_write writes, without evaluating: a result with made-up metrics."""
    r = dict(run=str(run), dataset=path.parent.name, dataset_kind="glossy", trained_on=path.parent.name,
             shading=run.name.split("-")[0], lobes=32, seed=0, iteration=1, trained_iterations=1, split=args.split,
             variant="", image_whole=0.02, image_foreground=0.05, iou=0.1, light_ldr=0.2, light_hdr=0.8, texture=0.2,
             chamfer=0.01, samples=40, envmaps=8, envmaps_in_train_split=0, evaluated=key)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(r))
    return r


def test_tables_cover_every_result_the_out_folder_holds(tmp_path):
    root, out = tmp_path / "runs", tmp_path / "eval"
    _fake_run(root / "a" / "sg-seed0", "data/glossy")
    _fake_run(root / "b" / "sh-seed0", "data/glossy")
    with mock.patch.object(evaluate, "evaluate_and_write", _fake_result):
        assert evaluate.main(["--runs", str(root / "a"), "--out", str(out)]) == 0
        assert evaluate.main(["--runs", str(root / "b"), "--out", str(out)]) == 0
    table = (out / "all_runs.md").read_text()
    assert "| glossy | sg |" in table and "| glossy | sh |" in table  # the first call's run too
    assert "| glossy / DIB-R++ SG |" in (out / "tables.md").read_text()
    assert "Every evaluated run (2)" in (out / "report.html").read_text()


def test_a_second_evaluate_into_one_out_is_refused_while_the_first_runs(tmp_path, capsys):
    root, out = tmp_path / "runs", tmp_path / "eval"
    _fake_run(root / "sg-seed0", "data/glossy")
    with mock.patch.object(evaluate, "evaluate_and_write", _fake_result):
        with evaluate.exclusive_out(out):  # the first call, still running
            assert evaluate.main(["--runs", str(root), "--out", str(out)]) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith(f"error: --out {out} is being written by another evaluate (pid ")
            assert not list(out.glob("*/*.json"))
        assert evaluate.main(["--runs", str(root), "--out", str(out)]) == 0  # once it is done
    assert (out / "glossy" / "sg-seed0.json").exists()


def test_a_set_of_another_image_size_is_refused_before_anything_is_predicted():
    ds = SimpleNamespace(resolution=33, root=Path("data/odd"))
    runs.check_image_size(Path("runs/r"), 33, ds)  # the same size: fine
    with pytest.raises(DataError, match=r"runs/r was trained on 32x32 images but data/odd holds 33x33; .*"
                                        r"--resolution 32\) or a run trained on data/odd"):
        runs.check_image_size(Path("runs/r"), 32, ds)


def test_a_split_that_says_little_is_warned_about():
    def ds(samples, objects):
        return SimpleNamespace(samples=samples, manifest={"objects": objects})

    objects = [dict(split="train", envmaps=[0, 1]), dict(split="test", envmaps=[1, 2]), dict(split="test", envmaps=[3])]
    size = scoring.split_size(ds([(1, 1), (1, 2), (2, 3)], objects), "test")
    assert size == dict(samples=3, envmaps=3, envmaps_in_train_split=1)  # map 1 lights a train object too
    assert scoring.split_size(ds([(0, 0), (0, 1)], objects), "train")["envmaps_in_train_split"] is None
    r = dict(dataset="tiny", split="test", **size)
    lines = scoring.split_warnings(r)
    assert lines == ["warning: tiny's test split is lit by 1 of its 3 env maps that its train split also uses: the "
                     "light is not scored on unseen maps (the set has too few maps to hold some out; generate it "
                     "with more --num-envmaps)",
                     f"warning: tiny's test split holds 3 samples (objects under a map) on 3 env maps, fewer than "
                     f"{scoring.MIN_SAMPLES}: its means say little"]
    assert scoring.split_warnings(dict(r, samples=40, envmaps_in_train_split=0)) == []
