"""``python -m datagen``'s command line: sizes training cannot use are refused before anything renders, and every
flag says what it does in --help. Nothing here renders."""
from unittest import mock

import pytest

from datagen import __main__ as cli
from datagen.config import make_config


def test_a_resolution_training_cannot_take_is_refused_before_rendering(tmp_path, capsys):
    out = tmp_path / "ds"
    with mock.patch("datagen.generate.generate", side_effect=AssertionError("rendering started")):
        code = cli.main(["--dataset", "glossy", "--out", str(out), "--resolution", "33", "--quiet"])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line]
    assert code == 2 and len(lines) == 1, err
    assert lines[0] == ("error: --resolution 33: must be a multiple of 16 (the model's encoder downsamples images by "
                        "16, so training refuses other sizes); e.g. 32 or 48"), err
    assert not out.exists()
    with pytest.raises(ValueError, match="e.g. 16$"):
        make_config("glossy", resolution=8)
    assert make_config("glossy", resolution=48).resolution == 48


def test_every_flag_says_what_it_does():
    parser = cli.build_parser()
    silent = [a.option_strings[-1] for a in parser._actions
              if a.option_strings and a.help is None and a.dest != "help"]
    assert not silent, f"flags without a description in --help: {silent}"
    assert "preview.png" in parser.format_help()


def test_a_gpu_render_is_refused_by_name_where_cycles_finds_no_gpu(tmp_path, capsys):
    pytest.importorskip("bpy")
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    out = tmp_path / "set"
    assert cli.main(["--dataset", "glossy", "--out", str(out), "--num-objects", "2", "--cycles-device", "gpu"]) == 2
    assert "--cycles-device gpu: Cycles finds no GPU" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("value", ["12,abc", "27,90", "", "nan"])
def test_elevations_that_are_not_cameras_are_refused_in_one_line(tmp_path, capsys, value):
    with mock.patch("datagen.generate.generate", side_effect=AssertionError("rendering started")):
        with pytest.raises(SystemExit) as exit_:
            cli.main(["--dataset", "glossy", "--out", str(tmp_path / "ds"), "--elevations", value, "--quiet"])
    lines = [line for line in capsys.readouterr().err.splitlines() if line]
    assert exit_.value.code == 2 and len(lines) == 1 and "--elevations" in lines[0], lines
    assert "strictly between -90 and 90" in lines[0] and not (tmp_path / "ds").exists()
