"""pipelines.export_model: a model folder written whole or not at all, never into the run it exports."""
import json
import shutil
from pathlib import Path

import pytest

from pipelines import export_model, train


@pytest.fixture(scope="module")
def run(tiny_glossy, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "sg"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--iterations", "2", "--out", str(out),
                       "--no-progress"]) == 0
    return out


def error_line(code, err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("inside", [False, True])
def test_out_in_the_run_folder_is_refused_before_anything_is_written(run, capsys, inside):
    before = snapshot(run)
    out = run / "model" if inside else run
    code = export_model.main(["--run", str(run), "--out", str(out)])
    line = error_line(code, capsys.readouterr().err)
    assert f"--out {out}: is {'inside ' if inside else ''}the run folder" in line
    assert snapshot(run) == before


def test_empty_out_is_refused(run, capsys):
    with pytest.raises(SystemExit) as exit_:
        export_model.main(["--run", str(run), "--out", ""])
    assert "--out: expected a folder, got an empty string" in error_line(exit_.value.code, capsys.readouterr().err)


def test_a_failed_export_leaves_the_model_in_out_as_it_was(run, tmp_path, capsys):
    """The run's dataset gone: the evaluation fails after the checkpoint was converted; --out keeps its earlier model
    and gains no file, and no temporary folder is left beside or in it."""
    copy = Path(shutil.copytree(run, tmp_path / "run"))
    config = json.loads((copy / "config.json").read_text())
    (copy / "config.json").write_text(json.dumps({**config, "dataset": str(tmp_path / "moved")}))
    out = tmp_path / "models" / "glossy"
    out.mkdir(parents=True)
    (out / "checkpoint.pt").write_bytes(b"the earlier model")
    (out / "MODEL_CARD.md").write_text("# the earlier model\n")
    before = snapshot(out)
    code = export_model.main(["--run", str(copy), "--out", str(out)])
    assert "no manifest.json" in error_line(code, capsys.readouterr().err)
    assert snapshot(out) == before and sorted(p.name for p in out.iterdir()) == sorted(before)
    assert [p.name for p in (tmp_path / "models").iterdir()] == ["glossy"]


@pytest.mark.slow
def test_an_export_replaces_the_model_in_out_whole(run, tmp_path, capsys):
    out = tmp_path / "glossy"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"the earlier model")
    assert export_model.main(["--run", str(run), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["MODEL_CARD.md", "camera.json", "checkpoint.pt", "config.json",
                                                     "metrics.json"]
    assert (out / "checkpoint.pt").read_bytes() != b"the earlier model"
    assert "# glossy" in (out / "MODEL_CARD.md").read_text()
    assert json.loads((out / "metrics.json").read_text())["run"] == str(out)  # not the folder it was staged in
