"""Prediction on a user's image with a (smoke) trained run: files that open elsewhere, clear errors."""
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from dibrpp.io import read_exr, read_image, write_exr
from pipelines import photo_input, predict
from pipelines.model import framing
from pipelines import train


@pytest.fixture(scope="module")
def run(tiny_glossy, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "sg"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--iterations", "2",
                       "--out", str(out), "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def predicted(run, tiny_glossy, tmp_path_factory):  # predict's outputs for one of the tiny set's views
    out = tmp_path_factory.mktemp("predicted") / "pred"
    image = next((tiny_glossy / "samples").glob("*/view_01.png"))
    assert predict.main(["--checkpoint", str(run), "--image", str(image), "--out", str(out), "--spp", "2"]) == 0
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


# ----------------------------------------------------------------------------- input refused before the model loads

@pytest.fixture
def fake_run(tmp_path, monkeypatch):
    """A folder that passes for a run; loading it fails the test (bad input must be refused before)."""
    from pipelines.training.config import TrainConfig

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps(TrainConfig(dataset=str(tmp_path)).to_dict()))
    (run / "checkpoint.pt").write_bytes(b"never read")
    monkeypatch.setattr(predict, "load_run", lambda *a: pytest.fail("the model loaded for input it must refuse"))
    return run


def one_error(code, err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:"), err
    return lines[0]


def exr_view(tmp_path, scale: float = 1.0, name: str = "view.exr"):
    """An RGBA EXR of a square object whose radiance is ``scale`` times 0.5, with a sun's reflection of 50."""
    rgba = np.zeros((24, 24, 4), np.float32)
    rgba[6:18, 6:18] = 0.5, 0.3, 0.2, 1.0
    rgba[11:13, 11:13, :3] = 50.0
    with np.errstate(invalid="ignore"):  # inf x 0 is NaN: non-finite either way
        rgba[..., :3] *= scale
    write_exr(tmp_path / name, rgba)
    return tmp_path / name


@pytest.mark.parametrize("scale, message", [
    (1e30, "radiance up to 5e+31, above 1.63e+05 (exp(12), the brightest light the model predicts); the image looks "
           "scaled: give it in scene-linear units"),
    (-1.0, "negative values (min -50); radiance cannot be negative, clamp the image at 0"),
    (float("inf"), "non-finite values (NaN/Inf)"),
])
def test_radiance_no_light_explains_is_refused(fake_run, tmp_path, capsys, scale, message):
    image = exr_view(tmp_path, scale)
    code = predict.main(["--checkpoint", str(fake_run), "--image", str(image), "--out", str(tmp_path / "p")])
    assert message in one_error(code, capsys.readouterr().err)
    assert not (tmp_path / "p").exists()


def test_a_float_tiff_with_nan_is_refused(fake_run, tmp_path, capsys):
    grey = np.zeros((16, 16), np.float32)
    grey[4:12, 4:12] = 0.5
    grey[8, 8] = np.nan
    Image.fromarray(grey, "F").save(tmp_path / "grey.tif")
    code = predict.main(["--checkpoint", str(fake_run), "--image", str(tmp_path / "grey.tif"), "--out",
                         str(tmp_path / "p"), "--background", "0,0,0"])
    assert "grey.tif: 3 non-finite values (NaN/Inf)" in one_error(code, capsys.readouterr().err)


def test_a_folder_for_image_says_so(fake_run, tmp_path, capsys):
    code = predict.main(["--checkpoint", str(fake_run), "--image", str(tmp_path), "--out", str(tmp_path / "p")])
    line = one_error(code, capsys.readouterr().err)
    assert f"--image {tmp_path}: is a folder; --image takes one image file" in line


def test_refine_steps_are_bounded(fake_run, tmp_path, capsys):
    argv = ["--checkpoint", str(fake_run), "--image", str(exr_view(tmp_path)), "--out", str(tmp_path / "p"),
            "--refine-steps", "1000000"]
    with pytest.raises(SystemExit) as exit_:
        predict.main(argv)
    line = one_error(exit_.value.code, capsys.readouterr().err)
    assert "--refine-steps: expected an integer in 0..10000, got 1000000" in line
    assert "at most 10000" in " ".join(predict.build_parser().format_help().split())


def test_a_long_refinement_says_how_long_after_its_second_step(capsys):
    """The first step compiles the renderer: the estimate comes from the second."""
    times = iter([0.0, 60.0, 60.5, 61.0, 100.0, 100.0, 100.1])
    clock = lambda: next(times)  # noqa: E731
    with predict.RefineProgress(1000, clock) as progress:
        progress(1)
        progress(2)
        progress(3)
    assert "refining the light: about 8 min for the 998 steps left (0.50 s a step)" in capsys.readouterr().err
    with predict.RefineProgress(20, clock) as progress:  # 2 s left: no estimate
        progress(1)
        progress(2)
    assert "refining the light" not in capsys.readouterr().err


def test_a_known_light_is_shown_beside_the_prediction_with_the_angle_between_their_suns(run, tiny_glossy, tmp_path,
                                                                                       capsys):
    """--true-light: the map the image was taken under goes into the overview and the report, with the angle between
    the suns, which is the eval's (a map against itself: 0; turned about up, the angle between the two suns)."""
    from dibrpp import conventions
    import torch

    d = conventions.equirect_directions(64, 128, dtype=torch.float64)
    sun = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64) / 2 ** 0.5
    sky = (0.5 + 200 * torch.exp(300 * ((d * sun).sum(-1, keepdim=True) - 1))).expand(64, 128, 3).float()
    assert photo_input.sun_angle_deg(sky, sky) == pytest.approx(0.0, abs=1e-3)
    # turned by 90 degrees about up, a sun at 45 degrees of elevation moves by acos(1/2) = 60 degrees
    assert photo_input.sun_angle_deg(torch.roll(sky, 32, 1), sky) == pytest.approx(60.0, abs=3.0)
    write_exr(tmp_path / "sky.exr", sky)
    image = next((tiny_glossy / "samples").glob("*/view_01.png"))
    out = tmp_path / "pred"
    assert predict.main(["--checkpoint", str(run), "--image", str(image), "--out", str(out), "--spp", "2",
                         "--true-light", str(tmp_path / "sky.exr")]) == 0
    material = json.loads((out / "material.json").read_text())
    assert 0.0 <= material["sun_angle_deg"] <= 180.0 and material["true_light"] == str(tmp_path / "sky.exr")
    assert "degrees from" in capsys.readouterr().err and "sun_angle_deg" in (out / "report.html").read_text()
    (tmp_path / "bad.exr").write_text("not an image")
    assert predict.main(["--checkpoint", str(run), "--image", str(image), "--out", str(tmp_path / "p2"),
                         "--true-light", str(tmp_path / "bad.exr")]) == 2
    assert capsys.readouterr().err.startswith("error: --true-light")
    assert not (tmp_path / "p2").exists()  # refused before anything is written


# ----------------------------------------------------------------------------- straight alpha

def test_the_shipped_photo_stores_straight_alpha():
    """examples/car_photo.png is the EXR's view with straight alpha: at the silhouette its colour is the car's (the
    EXR's premultiplied colour over alpha), not darkened toward 0 as alpha goes to 0."""
    examples = Path(__file__).resolve().parents[2] / "examples"
    png, exr = read_image(examples / "car_photo.png"), read_exr(examples / "car_photo.exr", "RGBA")
    alpha = exr[..., 3]
    assert np.abs(png[..., 3] - alpha).max() <= 0.5 / 255 + 1e-6
    edge, inside = (alpha > 0.02) & (alpha < 0.5), alpha > 0.999
    straight = exr[..., :3] / np.maximum(alpha, 1e-6)[..., None]
    unclipped = edge & (straight.max(-1) < 1)
    assert unclipped.sum() > 100
    assert np.abs(png[unclipped][:, :3] - straight[unclipped]).max() < 0.02  # 8-bit sRGB steps at these levels
    assert np.median(png[edge][:, :3].sum(-1)) > 0.3 * np.median(png[inside][:, :3].sum(-1))


def test_the_colour_under_transparent_pixels_does_not_bleed_into_the_resized_input():
    """Straight alpha leaves a transparent pixel's colour free (white in one editor, black in another): resizing
    averages premultiplied colour, so the outline reads the same either way, and an object's own colour stays."""
    import torch

    def image(under):
        rgba = torch.zeros(64, 64, 4)
        rgba[..., :3] = under
        rgba[16:48, 16:48] = torch.tensor([0.6, 0.2, 0.1, 1.0])
        rgba[16:48, 15, :3], rgba[16:48, 15, 3] = torch.tensor([0.6, 0.2, 0.1]), 0.5  # a half-covered column
        return rgba

    white, black = framing.resize_input(image(1.0), 16), framing.resize_input(image(0.0), 16)
    assert torch.allclose(white, black, atol=1e-6)
    covered = white[..., 3] > 0
    assert torch.allclose(white[covered][:, :3], torch.tensor([0.6, 0.2, 0.1]).expand(int(covered.sum()), 3), atol=1e-5)


# ----------------------------------------------------------------------------- one file to open elsewhere

def test_model_glb_holds_the_mesh_uvs_texture_and_material(predicted):
    """model.glb, read back by trimesh: the OBJ's mesh (turned to glTF's +Y up) with its UVs, the albedo image, and
    the predicted roughness and metallic; envmap.hdr is envmap.exr in Radiance RGBE."""
    from datagen.envmap_files import read_envmap_file

    obj = trimesh.load(predicted / "mesh.obj", process=False)
    scene = trimesh.load(predicted / "model.glb", process=False)
    (glb,) = scene.geometry.values()
    assert len(glb.faces) == len(obj.faces) == 1280 and len(glb.vertices) == len(obj.vertices)
    x, y, z = np.asarray(obj.vertices).T
    assert np.allclose(glb.vertices, np.stack([x, z, -y], -1), atol=1e-5)
    assert np.array_equal(glb.faces, obj.faces)
    assert np.allclose(glb.visual.uv, obj.visual.uv, atol=1e-6)  # trimesh reads glTF's v back into OBJ's
    material = json.loads((predicted / "material.json").read_text())
    pbr = glb.visual.material
    assert pbr.roughnessFactor == pytest.approx(material["roughness"], abs=1e-6)
    assert pbr.metallicFactor == pytest.approx(material["metallic"], abs=1e-6)
    texture = np.asarray(Image.open(predicted / "texture.png").convert("RGB"))
    assert np.array_equal(np.asarray(pbr.baseColorTexture.convert("RGB")), texture)
    exr, hdr = read_exr(predicted / "envmap.exr"), read_envmap_file(predicted / "envmap.hdr")
    assert hdr.shape == exr.shape and np.allclose(hdr, exr, rtol=0.02, atol=1e-3)


BLENDER_READS_THE_GLB = """
import sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=sys.argv[1])
(obj,) = [o for o in bpy.context.scene.objects if o.type == "MESH"]
nodes = obj.active_material.node_tree.nodes
(bsdf,) = [n for n in nodes if n.type == "BSDF_PRINCIPLED"]
base = bsdf.inputs["Base Color"]
linked = base.is_linked and base.links[0].from_node.type == "TEX_IMAGE" and base.links[0].from_node.image is not None
print("RESULT", len(obj.data.polygons), bsdf.inputs["Roughness"].default_value, bsdf.inputs["Metallic"].default_value,
      linked, len(obj.data.uv_layers))
"""


def test_blender_imports_model_glb_with_its_texture_and_material(predicted):
    """Blender's own glTF importer (in a process of its own, as datagen runs bpy): a Principled BSDF with the predicted
    roughness and metallic, its Base Color fed by an image texture, and the mesh's UV layer."""
    import subprocess
    import sys

    pytest.importorskip("bpy")
    r = subprocess.run([sys.executable, "-c", BLENDER_READS_THE_GLB, str(predicted / "model.glb")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    (line,) = [line for line in r.stdout.splitlines() if line.startswith("RESULT")]
    _, faces, roughness, metallic, linked, uv_layers = line.split()
    material = json.loads((predicted / "material.json").read_text())
    assert int(faces) == 1280 and linked == "True" and int(uv_layers) == 1
    assert float(roughness) == pytest.approx(material["roughness"], abs=1e-5)
    assert float(metallic) == pytest.approx(material["metallic"], abs=1e-5)


# ----------------------------------------------------------------------------- bad input: one error line, or read right

def error_line(code, err: str) -> str:
    """The one ``error:`` line of a run that failed after saying what it did (exit status 2, no traceback)."""
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def rgba_png(path, alpha: float = 1.0, size: int = 24):
    rgba = np.zeros((size, size, 4), np.uint8)
    rgba[6:18, 6:18] = 200, 60, 40, round(255 * alpha)
    Image.fromarray(rgba).save(path)
    return path


@pytest.mark.parametrize("case", ["grey mask", "red mask", "semi-transparent"])
def test_a_mask_never_above_one_half_is_refused_saying_where_a_pixel_counts(fake_run, tmp_path, capsys, case):
    mask = np.zeros((24, 24, 3), np.uint8)
    mask[6:18, 6:18] = (255, 0, 0) if case == "red mask" else (127, 127, 127)  # 50 % grey in 8 bits
    Image.fromarray(mask).save(tmp_path / "mask.png")
    Image.fromarray(np.full((24, 24, 3), 90, np.uint8)).save(tmp_path / "photo.png")
    extra = ["--mask", str(tmp_path / "mask.png")] if "mask" in case else []
    image = rgba_png(tmp_path / "half.png", 0.4) if case == "semi-transparent" else tmp_path / "photo.png"
    code = predict.main(["--checkpoint", str(fake_run), "--image", str(image), "--out", str(tmp_path / "p"), *extra])
    line = one_error(code, capsys.readouterr().err)
    assert "never above 0.5, where a pixel counts as the object's" in line
    assert not (tmp_path / "p").exists()


def test_a_mask_over_an_alpha_is_refused_and_over_an_opaque_alpha_taken(fake_run, tmp_path, capsys):
    mask = np.zeros((24, 24), np.uint8)
    mask[4:20, 4:20] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    code = predict.main(["--checkpoint", str(fake_run), "--image", str(rgba_png(tmp_path / "cut.png")), "--out",
                         str(tmp_path / "p"), "--mask", str(tmp_path / "mask.png")])
    assert "has an alpha channel, which is the object's mask; --mask" in one_error(code, capsys.readouterr().err)
    opaque = np.full((24, 24, 4), 255, np.uint8)
    Image.fromarray(opaque).save(tmp_path / "opaque.png")
    rgba = predict.read_input(tmp_path / "opaque.png", None, 0.05, mask=tmp_path / "mask.png")
    assert float(rgba[..., 3].sum()) == 16 * 16


def test_a_jpeg_is_turned_upright_and_a_float_tiff_read_linear_unclipped(tmp_path):
    from PIL import ImageOps

    rgb = np.full((20, 40, 3), 255, np.uint8)
    rgb[2:8, 2:10] = 0  # a dark patch at the top left of the stored pixels
    im = Image.fromarray(rgb)
    exif = im.getexif()
    exif[0x0112] = 6  # shown turned 90 degrees clockwise
    im.save(tmp_path / "phone.jpg", exif=exif, quality=95)
    upright = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "phone.jpg")), np.float32) / 255
    seen = read_image(tmp_path / "phone.jpg", linear=False)
    assert seen.shape == (40, 20, 3) and np.abs(seen - upright).max() < 1e-6 and seen[3:8, 13:17].max() < 0.2
    grey = np.zeros((16, 16), np.float32)
    grey[4:12, 4:12] = 3.5  # linear radiance above 1
    Image.fromarray(grey, "F").save(tmp_path / "hdr.tif")
    rgba = predict.read_input(tmp_path / "hdr.tif", (0.0, 0.0, 0.0), 0.05)
    assert float(rgba[8, 8, 0]) == pytest.approx(3.5) and float(rgba[..., 3].sum()) == 64


@pytest.mark.parametrize("damage, said", [
    ("text", "unreadable checkpoint (not a file torch.save wrote)"),
    ("faces", "the template's faces index 0..99999, outside its 642 entries"),
    ("list", "the model configuration is a list, not a mapping"),
    ("subdivisions", "template_subdivisions 11, expected an integer in 0..6"),
])
def test_a_damaged_checkpoint_is_one_error_naming_it(run, tiny_glossy, tmp_path, capsys, damage, said):
    import shutil

    import torch

    copy = Path(shutil.copytree(run, tmp_path / "run"))
    state = torch.load(copy / "checkpoint.pt", weights_only=True)
    if damage == "faces":
        state["model"]["faces"][0, 0] = 99999
    elif damage == "list":
        state["model_config"] = list(state["model_config"].items())
    elif damage == "subdivisions":
        state["model_config"]["template_subdivisions"] = 11
    torch.save(state, copy / "checkpoint.pt")
    if damage == "text":
        (copy / "checkpoint.pt").write_text("a note, not weights\n")
    image = next((tiny_glossy / "samples").glob("*/view_01.png"))
    code = predict.main(["--checkpoint", str(copy), "--image", str(image), "--out", str(tmp_path / "p")])
    line = error_line(code, capsys.readouterr().err)
    assert str(copy / "checkpoint.pt") in line and said in line and not (tmp_path / "p").exists()


def test_cameras_that_place_nothing_are_refused_and_unusual_ones_named(run, tiny_glossy, tmp_path, capsys):
    import shutil

    image = str(next((tiny_glossy / "samples").glob("*/view_01.png")))
    copy = Path(shutil.copytree(run, tmp_path / "run"))
    camera = json.loads((copy / "camera.json").read_text())
    (copy / "camera.json").write_text(json.dumps({**camera, "distance": -60}))
    code = predict.main(["--checkpoint", str(copy), "--image", image, "--out", str(tmp_path / "a")])
    assert f"{copy / 'camera.json'}: distance -60 (a distance is above 0)" in error_line(code, capsys.readouterr().err)
    code = predict.main(["--checkpoint", str(run), "--image", image, "--out", str(tmp_path / "b"), "--distance", "1"])
    assert "--distance 1: the camera sits inside the predicted object" in error_line(code, capsys.readouterr().err)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    with pytest.raises(SystemExit) as exit_:
        predict.main(["--checkpoint", str(run), "--image", image, "--out", ""])
    assert "--out: expected a folder, got an empty string" in error_line(exit_.value.code, capsys.readouterr().err)
    assert predict.main(["--checkpoint", str(run), "--image", image, "--out", str(tmp_path / "c"), "--fov", "5",
                         "--distance", "6000", "--views", "1", "--spp", "1"]) == 0
    err = capsys.readouterr().err
    assert "warning: --fov 5 degrees is outside 10-100" in err and "warning: --distance 6000 is 100 times" in err


def test_a_late_failure_leaves_an_earlier_result_as_it_was(run, tiny_glossy, tmp_path, capsys, monkeypatch):
    """The outputs move into --out together: a failure while writing the last of them (a full disk, here made to
    happen at the overview) leaves the earlier result's files as they were and adds none."""
    image = str(next((tiny_glossy / "samples").glob("*/view_01.png")))
    out = tmp_path / "pred"
    out.mkdir()
    (out / "material.json").write_text('{"roughness": "earlier"}')

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(predict, "write_overview", full_disk)
    code = predict.main(["--checkpoint", str(run), "--image", image, "--out", str(out), "--spp", "1", "--views", "1"])
    assert "No space left on device" in error_line(code, capsys.readouterr().err)
    assert sorted(p.name for p in out.iterdir()) == ["material.json"]
    assert (out / "material.json").read_text() == '{"roughness": "earlier"}'
    assert [p.name for p in tmp_path.iterdir()] == ["pred"]  # no temporary folder left
