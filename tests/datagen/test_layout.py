"""datagen.layout: the one description of a dataset's files, shared by the writer and the reader.

No rendering here: the layout against a generated dataset is checked in test_generate.py.
"""
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from datagen.layout import DEFAULT_CAMERA, CameraSetup, DatasetLayout


def test_import_pulls_in_neither_blender_nor_torch():
    code = ("import sys, datagen.layout; bad = [m for m in ('bpy', 'torch') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 0, r.stdout + r.stderr


def test_paths_follow_the_documented_tree(tmp_path):
    lay = DatasetLayout(tmp_path)
    rel = lambda p: p.relative_to(tmp_path).as_posix()  # noqa: E731
    assert rel(lay.manifest) == "manifest.json" and rel(lay.preview) == "preview.png"
    assert rel(lay.timing(1, 4)) == "timing/shard_1_of_4.json"
    assert [rel(p) for p in (lay.envmap(7), lay.envmap_png(7), lay.envmap_json(7))] == [
        "envmaps/env_0007.exr", "envmaps/env_0007.png", "envmaps/env_0007.json"]
    obj_files = (lay.mesh_npz(3), lay.mesh_obj(3), lay.mesh_mtl(3), lay.texture(3), lay.object_json(3))
    assert [rel(p) for p in obj_files] == [
        f"objects/obj_0003/{n}" for n in ("mesh.npz", "mesh.obj", "mesh.mtl", "texture.png", "object.json")]
    assert rel(lay.sample_json(3, 12)) == "samples/obj_0003_env_0012/sample.json"
    views = [lay.view_image(3, 12, 5), lay.view_image(3, 12, 5, srgb=True), lay.view_mask(3, 12, 5),
             lay.view_albedo(3, 12, 5), lay.view_camera(3, 12, 5)]
    assert [p.name for p in views] == lay.view_files(5) == [
        "view_05.exr", "view_05.png", "view_05_mask.png", "view_05_albedo.exr", "view_05.json"]
    assert {p.parent for p in views} == {lay.sample_dir(3, 12)}


def test_sample_names_round_trip_and_finished_samples(tmp_path):
    lay = DatasetLayout(tmp_path)
    assert lay.parse_sample_name(lay.sample_name(12, 345)) == (12, 345)
    with pytest.raises(ValueError, match="not a sample folder"):
        lay.parse_sample_name("obj_1_envmap_2")
    for obj, env, done in ((2, 1, True), (0, 3, True), (1, 0, False)):
        lay.sample_dir(obj, env).mkdir(parents=True)
        if done:
            lay.sample_json(obj, env).write_text("{}")
    (lay.samples_dir / "stray").mkdir()
    (lay.samples_dir / "stray" / "sample.json").write_text("{}")
    assert lay.finished_samples() == [(0, 3), (2, 1)]


def test_camera_setup_round_trips_through_the_manifest():
    assert DEFAULT_CAMERA.distance == 60.0 and DEFAULT_CAMERA.elevation_deg == 27.0
    assert DEFAULT_CAMERA.fov_deg == pytest.approx(39.5978, abs=1e-3)  # Blender's default 50 mm camera
    cam = CameraSetup(60.0, 27.0, 0.7, azimuths_deg=(0.0, 90.0), resolution=64)
    manifest = json.loads(json.dumps({"camera": cam.to_manifest()}))
    assert CameraSetup.from_manifest(manifest) == cam
    with pytest.raises(KeyError):
        CameraSetup.from_manifest({"config": {}})
    assert math.isclose(CameraSetup.from_manifest({"camera": {"distance": 2, "elevation_deg": 0, "fov": 1}}).fov, 1.0)
