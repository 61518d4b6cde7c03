"""Prediction on a user's image with a (smoke) trained run: files that open elsewhere, clear errors."""
import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from dibrpp.io import read_exr, read_image, write_exr
from pipelines import predict, train


@pytest.fixture(scope="module")
def run(tiny_glossy, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "sg"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--image-size", "32", "--iterations", "2",
                       "--out", str(out), "--no-progress"]) == 0
    return out


def test_predict_writes_textured_mesh_envmap_material_and_views(run, tiny_glossy, tmp_path, capsys):
    image = next((tiny_glossy / "samples").glob("*/view_01.png"))
    big = tmp_path / "big.png"
    Image.open(image).resize((100, 100)).save(big)  # any size is resized
    out = tmp_path / "pred"
    assert predict.main(["--checkpoint", str(run), "--image", str(big), "--out", str(out), "--spp", "4"]) == 0
    assert "no radiance above 1" in capsys.readouterr().err  # the default model reads the full range: say so
    rgba = read_image(image)  # the same view as a linear EXR with a sun's reflection in it: no note
    h = rgba.shape[0] // 2
    rgba[h - 2:h + 2, h - 2:h + 2, :3], rgba[h - 2:h + 2, h - 2:h + 2, 3] = 50.0, 1.0
    write_exr(tmp_path / "view.exr", rgba)
    assert predict.main(["--checkpoint", str(run), "--image", str(tmp_path / "view.exr"), "--out", str(tmp_path / "x"),
                         "--spp", "2"]) == 0
    assert "no radiance above 1" not in capsys.readouterr().err
    mesh = trimesh.load(out / "mesh.obj", process=False)
    assert len(mesh.faces) == 1280 and mesh.visual.uv is not None and mesh.visual.material.image is not None
    assert read_exr(out / "envmap.exr").shape == (64, 128, 3)
    material = json.loads((out / "material.json").read_text())
    assert 0 <= material["roughness"] <= 1 and material["shading"] == "sg"
    assert np.asarray(Image.open(out / "novel_views.png")).shape == (64, 4 * 64, 4)


def test_rgb_input_needs_a_background_and_errors_are_clear(run, tmp_path, capsys):
    rgb = np.full((40, 40, 3), 255, np.uint8)
    rgb[10:30, 10:30] = (200, 30, 30)
    Image.fromarray(rgb).save(tmp_path / "photo.png")
    args = ["--checkpoint", str(run), "--image", str(tmp_path / "photo.png"), "--spp", "2"]
    assert predict.main(args + ["--out", str(tmp_path / "a")]) == 2
    assert "no alpha channel" in capsys.readouterr().err and not (tmp_path / "a").exists()
    assert predict.main(args + ["--out", str(tmp_path / "b"), "--background", "1,1,1"]) == 0
    (tmp_path / "broken.png").write_bytes(b"not a png")
    assert predict.main(["--checkpoint", str(run), "--image", str(tmp_path / "broken.png"), "--out", str(tmp_path / "c")]) == 2
    assert predict.main(["--checkpoint", str(tmp_path), "--image", str(tmp_path / "photo.png"), "--out", str(tmp_path / "d")]) == 2
    assert "not a run folder" in capsys.readouterr().err
