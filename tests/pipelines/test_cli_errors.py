"""Every pipelines CLI answers bad input with one clear line: exit status 2, exactly one line starting with
``error:`` on stderr, no traceback, and nothing left behind or lost. One test per case."""
import json
import os
import re
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dibrpp.io import read_image, write_exr
from pipelines import diagnose_light, evaluate, predict, train
from pipelines.model.framing import resize_input

REPO = Path(__file__).resolve().parents[2]


def assert_one_error(code, err: str, *names: str) -> str:
    """Exit status 2, one ``error:`` line naming each of ``names``, no traceback; returns the line."""
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2, err
    assert "Traceback" not in err, err
    assert len(lines) == 1, err
    for name in names:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def call(main, argv: list[str]) -> int:
    """A CLI's exit status, whether it returns it or exits (argparse's usage errors)."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def smoke_args(dataset, out, *extra) -> list[str]:
    return ["--preset", "smoke", "--dataset", str(dataset), "--iterations", "2",
            "--out", str(out), "--no-progress", *extra]


@pytest.fixture(scope="module")
def run(tiny_glossy, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "sg"
    assert train.main(smoke_args(tiny_glossy, out)) == 0
    return out


@pytest.fixture
def run_copy(run, tmp_path):
    return Path(shutil.copytree(run, tmp_path / "runs" / "sg"))


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


# ----------------------------------------------------------------------------- train

def test_train_config_file_of_garbage_json(tiny_glossy, tmp_path, capsys):
    (tmp_path / "c.json").write_text("{lr: fast,")
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r", "--config", str(tmp_path / "c.json")))
    assert_one_error(code, capsys.readouterr().err, "c.json", "not valid JSON")
    assert not (tmp_path / "r").exists()


def test_train_config_file_with_an_unknown_key_names_it(tiny_glossy, tmp_path, capsys):
    (tmp_path / "c.json").write_text(json.dumps({"learning_rate": 1e-3}))
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r", "--config", str(tmp_path / "c.json")))
    assert_one_error(code, capsys.readouterr().err, "c.json", "'learning_rate'")


def test_train_config_file_with_a_wrong_type(tiny_glossy, tmp_path, capsys):
    (tmp_path / "c.json").write_text(json.dumps({"lr": "fast"}))
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r", "--config", str(tmp_path / "c.json")))
    assert_one_error(code, capsys.readouterr().err, "lr", "'fast'")


def test_train_batch_objects_zero(tiny_glossy, tmp_path, capsys):
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r", "--batch-objects", "0"))
    assert_one_error(code, capsys.readouterr().err, "batch_objects")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("iterations", ["0", "-3"])
def test_train_iterations_below_one_leaves_no_run_folder(tiny_glossy, tmp_path, capsys, iterations):
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r") + ["--iterations", iterations])
    assert_one_error(code, capsys.readouterr().err, "iterations")
    assert not (tmp_path / "r").exists()


def resume_args(run, *extra) -> list[str]:
    return ["--out", str(run), "--resume", "--no-progress", *extra]


def test_train_resume_on_a_truncated_checkpoint(tiny_glossy, run_copy, capsys):
    truncate(run_copy / "checkpoint.pt")
    code = train.main(resume_args(run_copy, "--iterations", "4"))
    assert_one_error(code, capsys.readouterr().err, "checkpoint.pt", "truncated")


def test_train_resume_with_another_seed_is_refused_naming_it(tiny_glossy, run_copy, capsys):
    before = (run_copy / "checkpoint.pt").read_bytes()
    code = train.main(resume_args(run_copy, "--seed", "5"))
    assert_one_error(code, capsys.readouterr().err, "seed")
    assert (run_copy / "checkpoint.pt").read_bytes() == before  # nothing lost


def test_train_on_a_manifest_of_the_wrong_structure_names_the_file(tiny_glossy, tmp_path, capsys):
    data = Path(shutil.copytree(tiny_glossy, tmp_path / "data"))
    (data / "manifest.json").write_text(json.dumps(["not", "a", "manifest"]))
    code = train.main(smoke_args(data, tmp_path / "r"))
    assert_one_error(code, capsys.readouterr().err, "manifest.json")
    assert not (tmp_path / "r").exists()


# ----------------------------------------------------------------------------- evaluate

def eval_args(runs, out) -> list[str]:
    return ["--runs", str(runs), "--out", str(out), "--spp", "2", "--view-stride", "4"]


def test_evaluate_view_stride_zero(run, tmp_path, capsys):
    code = call(evaluate.main, ["--runs", str(run), "--out", str(tmp_path / "e"), "--view-stride", "0"])
    assert_one_error(code, capsys.readouterr().err, "--view-stride")
    assert not (tmp_path / "e").exists()


def test_evaluate_reports_a_run_with_a_garbage_config_and_evaluates_the_others(run, tmp_path, capsys):
    shutil.copytree(run, tmp_path / "runs" / "good")
    broken = Path(shutil.copytree(run, tmp_path / "runs" / "broken"))
    (broken / "config.json").write_text("{garbage")
    code = evaluate.main(eval_args(tmp_path / "runs", tmp_path / "e"))
    assert_one_error(code, capsys.readouterr().err, "1 of 2", str(broken), "config.json")
    assert json.loads((tmp_path / "e" / "glossy" / "good.json").read_text())["seed"] == 0
    assert "good" in (tmp_path / "e" / "report.html").read_text()


@pytest.mark.slow  # two evaluations and a training: ~60 s on 2 cores
def test_evaluate_a_retrained_run_again_instead_of_its_cached_metrics(tiny_glossy, tmp_path, capsys):
    out, results = tmp_path / "runs" / "sg", tmp_path / "e"
    assert train.main(smoke_args(tiny_glossy, out)) == 0
    assert evaluate.main(eval_args(out, results)) == 0
    assert json.loads((results / "glossy" / "sg.json").read_text())["seed"] == 0
    shutil.rmtree(out)
    assert train.main(smoke_args(tiny_glossy, out, "--seed", "1")) == 0
    capsys.readouterr()
    assert evaluate.main(eval_args(out, results)) == 0
    assert "run 1 of 1" in capsys.readouterr().err  # evaluated, not taken from the cache
    assert json.loads((results / "glossy" / "sg.json").read_text())["seed"] == 1


# ----------------------------------------------------------------------------- predict: images

def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_bytes(width: int, height: int, depth: int, colour_type: int, rows: bytes) -> bytes:
    header = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(rows))
            + _chunk(b"IEND", b""))


def write_png16(path: Path, words: np.ndarray) -> None:
    """A 16-bit PNG (grey, grey+alpha, RGB or RGBA by the channel count) of uint16 (H, W, C) ``words``; the rows
    cycle through PNG's five filters, as encoders that pick a filter per row produce."""
    h, w, c = words.shape
    data = np.ascontiguousarray(words, dtype=">u2").view(np.uint8).reshape(h, w * c * 2).astype(np.int32)
    bpp = 2 * c
    left = np.pad(data, ((0, 0), (bpp, 0)))[:, :-bpp]
    up = np.pad(data, ((1, 0), (0, 0)))[:-1]
    upleft = np.pad(up, ((0, 0), (bpp, 0)))[:, :-bpp]
    p = left + up - upleft
    pa, pb, pc = abs(p - left), abs(p - up), abs(p - upleft)
    paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
    predictors = [np.zeros_like(data), left, up, (left + up) // 2, paeth]
    rows = b"".join(bytes([y % 5]) + ((data[y] - predictors[y % 5][y]) % 256).astype(np.uint8).tobytes()
                    for y in range(h))
    path.write_bytes(png_bytes(w, h, 16, {1: 0, 2: 4, 3: 2, 4: 6}[c], rows))


def object_rgba(size: int = 24) -> np.ndarray:
    """uint8 (size, size, 4): a coloured square on a transparent background."""
    img = np.zeros((size, size, 4), np.uint8)
    img[size // 4: -size // 4, size // 4: -size // 4] = (200, 120, 40, 255)
    return img


def make_image(kind: str, folder: Path) -> tuple[Path, np.ndarray | None]:
    """An image file of ``kind`` and, for the 16-bit ones, the values read_image must give (sRGB, 0-1)."""
    rgba = object_rgba()
    if kind == "exr":
        write_exr(folder / "in.exr", rgba.astype(np.float32) / 255)
        return folder / "in.exr", None
    if kind in ("grey16", "grey-alpha16", "rgb16", "rgba16"):
        channels = {"grey16": [0], "grey-alpha16": [0, 3], "rgb16": [0, 1, 2], "rgba16": [0, 1, 2, 3]}[kind]
        levels = rgba[..., channels].astype(np.int64) * 257
        rows = np.arange(24)[:, None, None]  # a level per row, below the top one where it is 65535 (opaque)
        words = np.where(levels == 65535, levels - rows, levels + rows).astype(np.uint16)
        write_png16(folder / f"{kind}.png", words)
        expect = words / 65535.0
        if len(channels) <= 2:  # greyscale reads as RGB
            expect = np.concatenate([np.repeat(expect[..., :1], 3, -1), expect[..., 1:]], -1)
        return folder / f"{kind}.png", expect
    Image.fromarray(rgba, "RGBA").convert(kind).save(folder / f"{kind}.png")
    return folder / f"{kind}.png", None


@pytest.mark.parametrize("kind", ["RGBA", "RGB", "L", "LA", "P", "grey16", "grey-alpha16", "rgb16", "rgba16", "exr"])
def test_predict_reads_every_kind_of_image_at_its_own_depth(kind, tmp_path):
    path, expect = make_image(kind, tmp_path)
    if expect is not None:
        got = read_image(path, linear=False)
        assert got.shape == expect.shape and np.abs(got - expect).max() < 1e-6  # every one of the 65536 levels
    background = (0.0, 0.0, 0.0) if kind in ("RGB", "L", "grey16", "rgb16") else None
    rgba = resize_input(predict.read_input(path, background, 0.05), 32)
    assert rgba.shape == (32, 32, 4) and 0 < float(rgba[..., 3].mean()) < 1  # the object, on a background


def test_predict_16bit_greyscale_with_a_black_background_keeps_its_grey_levels(run, tmp_path, capsys):
    words = np.zeros((32, 32, 1), np.uint16)
    words[8:24, 8:24, 0] = np.linspace(1000, 60000, 16, dtype=np.uint16)[None, :]  # 16 grey levels, ~3.7 % apart
    write_png16(tmp_path / "grey.png", words)
    grey = read_image(tmp_path / "grey.png", linear=False)
    assert np.allclose(grey[8, 8:24, 0], np.linspace(1000, 60000, 16, dtype=np.uint16) / 65535, atol=1e-6)
    assert len(np.unique(grey)) == 17  # not binarised to 0/1
    args = ["--checkpoint", str(run), "--image", str(tmp_path / "grey.png"), "--out", str(tmp_path / "p"),
            "--background", "0,0,0", "--spp", "2"]
    assert predict.main(args) == 0
    err = capsys.readouterr().err
    assert "loading" in err and "rendering 4 novel views" in err and "error" not in err
    assert (tmp_path / "p" / "novel_views.png").exists()


def predict_args(run, image, out) -> list[str]:
    return ["--checkpoint", str(run), "--image", str(image), "--out", str(out), "--spp", "2"]


def test_predict_refuses_a_one_pixel_image(run, tmp_path, capsys):
    Image.fromarray(np.full((1, 1, 4), 255, np.uint8)).save(tmp_path / "dot.png")
    code = predict.main(predict_args(run, tmp_path / "dot.png", tmp_path / "p"))
    assert_one_error(code, capsys.readouterr().err, "dot.png", "too small")
    assert not (tmp_path / "p").exists()


def test_predict_refuses_a_huge_image(run, tmp_path, capsys):
    (tmp_path / "huge.png").write_bytes(png_bytes(15000, 15000, 8, 6, b"\0"))  # a decompression bomb's header
    code = predict.main(predict_args(run, tmp_path / "huge.png", tmp_path / "p"))
    assert_one_error(code, capsys.readouterr().err, "huge.png", "too large")


def test_predict_out_that_is_a_file(run, tmp_path, capsys):
    image, _ = make_image("RGBA", tmp_path)
    (tmp_path / "taken").write_text("keep me")
    code = predict.main(predict_args(run, image, tmp_path / "taken"))
    assert_one_error(code, capsys.readouterr().err, "--out", str(tmp_path / "taken"))
    assert (tmp_path / "taken").read_text() == "keep me"


def _make_read_only(folder: Path) -> bool:
    """chmod 555, and for root (whom permissions do not stop) the immutable attribute; False if neither holds."""
    folder.chmod(0o555)
    if os.geteuid() == 0:
        subprocess.run(["chattr", "+i", str(folder)], capture_output=True)
    try:
        (folder / "probe").touch()
    except OSError:
        return True
    (folder / "probe").unlink()
    return False


def test_predict_out_in_a_read_only_folder(run, tmp_path, capsys):
    image, _ = make_image("RGBA", tmp_path)
    folder = tmp_path / "locked"
    folder.mkdir()
    try:
        if not _make_read_only(folder):
            pytest.skip("cannot make a folder read-only here")
        code = predict.main(predict_args(run, image, folder / "pred"))
        assert_one_error(code, capsys.readouterr().err, "--out", str(folder))
    finally:
        if os.geteuid() == 0:
            subprocess.run(["chattr", "-i", str(folder)], capture_output=True)
        folder.chmod(0o755)


def test_predict_with_a_truncated_checkpoint(run_copy, tmp_path, capsys):
    image, _ = make_image("RGBA", tmp_path)
    truncate(run_copy / "checkpoint.pt")
    code = predict.main(predict_args(run_copy, image, tmp_path / "p"))
    assert_one_error(code, capsys.readouterr().err, "checkpoint.pt")
    assert not (tmp_path / "p").exists()


# ----------------------------------------------------------------------------- the repository

def test_no_checkpoint_is_unpickled_with_arbitrary_code():
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                            text=True, check=True).stdout.split("\n")
    pattern = re.compile(r"weights_only\s*=\s*False")
    offenders = [name for name in listed if name.endswith((".py", ".md", ".txt", ".cfg", ".toml", ".ipynb"))
                 and (REPO / name).is_file() and pattern.search((REPO / name).read_text(errors="replace"))]
    assert not offenders, f"torch.load without weights_only runs pickled code from a file: {offenders}"


def test_diagnose_light_on_a_set_of_another_image_size_is_refused_naming_both(run, tiny_glossy, tmp_path, capsys):
    other = Path(shutil.copytree(tiny_glossy, tmp_path / "glossy-48"))
    manifest = json.loads((other / "manifest.json").read_text())
    manifest["config"]["resolution"] = 48
    (other / "manifest.json").write_text(json.dumps(manifest))
    code = call(diagnose_light.main, ["--run", str(run), "--dataset", str(other), "--split", "all"])
    assert_one_error(code, capsys.readouterr().err, "32x32", "48x48")



# ----------------------------------------------------------------------------- the new surfaces' bad input

def test_train_resume_with_a_preset_is_refused_not_ignored(tiny_glossy, run_copy, capsys):
    before = (run_copy / "checkpoint.pt").read_bytes()
    code = train.main(["--out", str(run_copy), "--resume", "--preset", "paper", "--no-progress"])
    assert_one_error(code, capsys.readouterr().err, "--preset paper", "--resume")
    assert (run_copy / "checkpoint.pt").read_bytes() == before


def test_train_resume_on_an_empty_out_says_there_is_no_run(tmp_path, capsys):
    code = train.main(["--out", str(tmp_path / "nothing"), "--resume", "--no-progress"])
    assert_one_error(code, capsys.readouterr().err, "--out", "no run to resume")


def test_train_resume_on_a_corrupt_log_names_it(tiny_glossy, run_copy, capsys):
    (run_copy / "log.csv").write_text("iteration,total\nabc,def\n")
    code = train.main(["--out", str(run_copy), "--resume", "--iterations", "4", "--no-progress"])
    assert_one_error(code, capsys.readouterr().err, "log.csv")


def test_train_batch_objects_beyond_memory_is_refused(tiny_glossy, tmp_path, capsys):
    code = train.main(smoke_args(tiny_glossy, tmp_path / "r", "--batch-objects", "100000"))
    assert_one_error(code, capsys.readouterr().err, "batch_objects", "256")
    assert not (tmp_path / "r").exists()


def test_a_camera_json_with_nan_names_the_file(run_copy, tmp_path, capsys):
    camera = json.loads((run_copy / "camera.json").read_text())
    (run_copy / "camera.json").write_text(json.dumps({**camera, "elevation_deg": float("nan")}))
    image = tmp_path / "in.png"
    Image.fromarray(np.full((16, 16, 4), 200, np.uint8)).save(image)
    code = predict.main(["--checkpoint", str(run_copy), "--image", str(image), "--out", str(tmp_path / "p")])
    assert_one_error(code, capsys.readouterr().err, "camera.json")


@pytest.mark.parametrize("field, value", [("shading", "mc"), ("lobes", 16)])
def test_a_config_of_another_run_over_a_checkpoint_is_refused_by_predict_and_evaluate(run_copy, tmp_path, capsys,
                                                                                      field, value):
    config = json.loads((run_copy / "config.json").read_text())
    (run_copy / "config.json").write_text(json.dumps({**config, field: value}))
    image = tmp_path / "in.png"
    Image.fromarray(np.full((16, 16, 4), 200, np.uint8)).save(image)
    code = predict.main(["--checkpoint", str(run_copy), "--image", str(image), "--out", str(tmp_path / "p")])
    assert_one_error(code, capsys.readouterr().err, "config.json", field)
    code = evaluate.main(eval_args(run_copy, tmp_path / "e"))
    assert_one_error(code, capsys.readouterr().err, "config.json", field)
    assert not (tmp_path / "e" / "glossy" / "sg.json").exists()


def test_an_exr_alpha_above_one_is_refused_not_read_as_brighter_light(run, tmp_path, capsys):
    rgba = np.full((16, 16, 4), 0.5, np.float32)
    rgba[..., 3] = 3.0  # a scaled alpha: the colour divided by it would come out 3x too dark, the light too bright
    write_exr(tmp_path / "in.exr", rgba)
    code = predict.main(["--checkpoint", str(run), "--image", str(tmp_path / "in.exr"), "--out", str(tmp_path / "p")])
    assert_one_error(code, capsys.readouterr().err, "alpha outside [0, 1]")
    assert not (tmp_path / "p").exists()


def test_predict_background_on_an_image_with_alpha_is_refused_not_ignored(run, tmp_path, capsys):
    Image.fromarray(np.full((16, 16, 4), 200, np.uint8)).save(tmp_path / "in.png")
    code = predict.main(["--checkpoint", str(run), "--image", str(tmp_path / "in.png"), "--out", str(tmp_path / "p"),
                         "--background", "1,1,1"])
    assert_one_error(code, capsys.readouterr().err, "--background", "alpha")


@pytest.mark.parametrize("flag, value", [("--views", "100000"), ("--spp", "100000000"), ("--elevation", "95"),
                                         ("--fov", "0"), ("--distance", "-1"), ("--framing", "zoom")])
def test_predict_unbounded_or_impossible_camera_flags_are_refused(run, tmp_path, capsys, flag, value):
    Image.fromarray(np.full((16, 16, 4), 200, np.uint8)).save(tmp_path / "in.png")
    code = call(predict.main, ["--checkpoint", str(run), "--image", str(tmp_path / "in.png"),
                               "--out", str(tmp_path / "p"), flag, value])
    assert_one_error(code, capsys.readouterr().err, flag)
    assert not (tmp_path / "p").exists()


def test_a_truncated_mesh_in_a_dataset_is_an_error_naming_it(run, tiny_glossy, tmp_path, capsys):
    data = Path(shutil.copytree(tiny_glossy, tmp_path / "glossy"))
    for mesh in data.glob("objects/*/mesh.npz"):
        truncate(mesh)
    code = evaluate.main(eval_args(run, tmp_path / "e") + ["--dataset", str(data)])
    assert_one_error(code, capsys.readouterr().err, "mesh.npz", "unreadable mesh")
    code = call(diagnose_light.main, ["--run", str(run), "--dataset", str(data)])
    assert_one_error(code, capsys.readouterr().err, "mesh.npz")


@pytest.mark.parametrize("argv, said", [
    (["-m", "dibrpp", "render", "--mesh", "examples/car.obj", "--envmap", "examples/sky.exr", "--spp", "1000000000",
      "--out", "{tmp}/x.png"], "--spp"),
    (["-m", "dibrpp", "render", "--mesh", "examples/car.obj", "--envmap", "examples/sky.exr", "--spp", "4096",
      "--resolution", "8192", "--out", "{tmp}/x.png"], "samples"),
    (["-m", "datagen", "--dataset", "glossy", "--resolution", "100000", "--out", "{tmp}/d"], "--resolution"),
    (["-m", "pipelines.light_ceiling", "--dataset", "{tmp}", "--steps", "1000000000"], "--steps"),
])
def test_work_with_no_end_is_refused_before_it_starts(tmp_path, argv, said):
    import sys

    done = subprocess.run([sys.executable, *(a.replace("{tmp}", str(tmp_path)) for a in argv)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert_one_error(done.returncode, done.stderr, said)
