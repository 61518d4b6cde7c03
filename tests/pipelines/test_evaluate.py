"""Evaluation of a (smoke) trained run on the real tiny dataset's test split."""
import json

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
