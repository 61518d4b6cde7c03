"""End-to-end dataset generation through the real Blender path, at a tiny scale.

Proves the camera convention (GT mesh rasterised by dibrpp with the stored camera matches the Cycles
alpha), the albedo output (matches the texture), the env-map capture orientation, determinism and
resume-after-crash, and clear errors for bad input.
"""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("bpy")
pytest.importorskip("xatlas")

from datagen.config import config_dict, make_config, parse_shard  # noqa: E402
from datagen.generate import generate  # noqa: E402
from datagen.layout import DEFAULT_CAMERA, DatasetLayout  # noqa: E402
from datagen.manifest import GENERATOR_VERSION  # noqa: E402
from datagen.plan import azimuths, plan  # noqa: E402
from dibrpp.io import DataError, read_exr, read_png  # noqa: E402

pytestmark = pytest.mark.cycles

TINY = dict(num_objects=2, num_envmaps=2, envs_per_object=1, views=3, resolution=48, spp=4, texture_size=64,
            envmap_height=16, grid=40, max_bounces=1)


def tiny_config(dataset="metallic", **kw):
    return make_config(dataset, **{**TINY, **kw})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ds") / "metallic"
    stats = generate(tiny_config(), out, workers=1, progress=False)
    return out, stats


def _binary_files(root: Path) -> dict:
    skip = {"timing"}
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.suffix != ".json" and not (set(p.relative_to(root).parts) & skip)}


def _json_without_timing(root: Path) -> dict:
    out = {}
    for p in sorted(root.rglob("*.json")):
        if "timing" in p.relative_to(root).parts:
            continue
        d = json.loads(p.read_text())
        if isinstance(d, dict):
            d.pop("timing", None)
            d.pop("seconds", None)
        out[str(p.relative_to(root))] = d
    return out


def test_layout_manifest_and_splits(dataset):
    out, stats = dataset
    m = json.loads((out / "manifest.json").read_text())
    assert m["generator_version"] == GENERATOR_VERSION
    assert m["counts"]["objects"] == 2 and m["counts"]["images"] == 2 * 1 * 3
    assert sorted(m["splits"]["objects"]["train"] + m["splits"]["objects"]["test"]) == [0, 1]
    assert len(m["splits"]["objects"]["test"]) == 0 or len(m["splits"]["objects"]["test"]) == 1
    for o in m["objects"]:
        assert o["material"] == dict(roughness=0.0, metallic=1.0, specular_ior_level=0.5, subsurface_weight=0.0)
        d = out / "samples" / DatasetLayout.sample_name(o["index"], o["envmaps"][0])
        assert (d / "sample.json").exists()
        for v in range(3):
            rgba = read_exr(d / f"view_{v:02d}.exr", "RGBA")
            assert rgba.shape == (48, 48, 4)
            assert 0.02 < rgba[..., 3].mean() < 0.9  # the object is in view and not cropped to the border
            assert rgba[[0, -1], :, 3].max() < 0.5 and rgba[:, [0, -1], 3].max() < 0.5
    assert (out / "preview.png").exists()
    assert stats["rendered_views"] == 6 and stats["cycles_s"] > 0


def test_every_file_written_is_a_path_of_the_layout(dataset):
    """The writer and the reader share datagen.layout: every file on disk is one the layout names."""
    from datagen.layout import CameraSetup

    out, _ = dataset
    lay = DatasetLayout(out)
    m = json.loads(lay.manifest.read_text())
    named = {lay.manifest, lay.preview, lay.timing(0, 1), lay.run_lock(0, 1), lay.manifest_lock}
    for e in sorted({e for o in m["objects"] for e in o["envmaps"]}):
        named |= {lay.envmap(e), lay.envmap_png(e), lay.envmap_json(e)}
    for o in m["objects"]:
        i = o["index"]
        named |= {lay.mesh_npz(i), lay.mesh_obj(i), lay.mesh_mtl(i), lay.texture(i), lay.object_json(i)}
        for e in o["envmaps"]:
            named.add(lay.sample_json(i, e))
            for v in range(m["config"]["views"]):
                named |= {lay.view_image(i, e, v), lay.view_image(i, e, v, srgb=True), lay.view_mask(i, e, v),
                          lay.view_albedo(i, e, v), lay.view_camera(i, e, v)}
    assert {p for p in out.rglob("*") if p.is_file()} == named
    cam = CameraSetup.from_manifest(m)
    assert (cam.distance, cam.elevation_deg, cam.fov) == (DEFAULT_CAMERA.distance, DEFAULT_CAMERA.elevation_deg, DEFAULT_CAMERA.fov)
    assert list(cam.azimuths_deg) == azimuths(tiny_config()) and cam.resolution == 48
    view = json.loads(lay.view_camera(*lay.finished_samples()[0], 1).read_text())
    assert view["distance"] == cam.distance and view["fov"] == cam.fov and view["azimuth_deg"] == cam.azimuths_deg[1]


def test_gt_mesh_rasterised_with_stored_camera_matches_cycles_alpha(dataset):
    raster = pytest.importorskip("dibrpp.raster")
    from dibrpp.camera import Cameras
    from dibrpp.mesh import Meshes

    out, _ = dataset
    for sd in sorted((out / "samples").iterdir()):
        meta = json.loads((sd / "sample.json").read_text())
        with np.load(out / "objects" / f"obj_{meta['object']:04d}" / "mesh.npz") as m:
            mesh = Meshes(torch.from_numpy(m["verts"]).float(), torch.from_numpy(m["faces"]))
        for v in range(meta["views"]):
            cam = json.loads((sd / f"view_{v:02d}.json").read_text())
            cams = Cameras(torch.tensor(cam["world_to_camera"]).float(), torch.tensor([cam["fov"]]), cam["resolution"])
            frag = raster.rasterize(mesh, cams)
            ours = frag.mask[0].numpy() > 0.5
            alpha = read_exr(sd / f"view_{v:02d}.exr", "RGBA")[..., 3] > 0.5
            iou = (ours & alpha).sum() / (ours | alpha).sum()
            assert iou >= 0.95, (sd.name, v, iou)


def test_albedo_matches_texture(dataset):
    raster = pytest.importorskip("dibrpp.raster")
    from dibrpp.camera import Cameras
    from dibrpp.mesh import Meshes

    out, _ = dataset
    sd = sorted((out / "samples").iterdir())[0]
    meta = json.loads((sd / "sample.json").read_text())
    od = out / "objects" / f"obj_{meta['object']:04d}"
    with np.load(od / "mesh.npz") as m:
        mesh = Meshes(*(torch.from_numpy(m[k]) for k in ("verts", "faces", "uvs", "face_uvs")))
    mesh = Meshes(mesh.verts.float(), mesh.faces, mesh.uvs.float(), mesh.face_uvs)
    tex = torch.from_numpy(read_png(od / "texture.png", linear=True)[..., :3])
    cam = json.loads((sd / "view_00.json").read_text())
    cams = Cameras(torch.tensor(cam["world_to_camera"]).float(), torch.tensor([cam["fov"]]), cam["resolution"])
    frag = raster.rasterize(mesh, cams)
    uv = frag.interpolate(mesh.uvs, mesh.face_uvs)
    ours = frag.to_image(raster.sample_texture(tex[None], uv, frag.batch))[0].numpy()
    rgba = read_exr(sd / "view_00.exr", "RGBA")
    albedo = read_exr(sd / "view_00_albedo.exr", "RGB")
    interior = (rgba[..., 3] > 0.999) & (frag.mask[0].numpy() > 0.5)
    assert interior.sum() > 100
    err = np.abs(albedo[interior] - ours[interior])
    # Texture detail smaller than a pixel is averaged differently (pixel filter vs one lookup): use medians.
    assert np.median(err) < 0.02, np.median(err)
    assert np.mean(err) < 0.06, np.mean(err)


def test_panorama_capture_follows_envmap_convention():
    """The camera that captures skies/rooms reproduces a direction-coded world exactly."""
    import bpy

    from datagen import cycles
    from datagen import envmaps
    from dibrpp import conventions as conv

    h, w = 16, 32
    d = conv.equirect_directions(h, w, dtype=torch.float64)
    env = (torch.stack([d[..., 1].clamp_min(0), d[..., 2].clamp_min(0), d[..., 0].clamp_min(0)], -1) + 0.05)
    env = env.float().numpy()
    cycles.reset()
    cycles.make_world(env)
    got = envmaps.capture_world(h, w, spp=4, seed=0)
    assert bpy.context.scene.camera.data.type == "PANO"
    assert np.abs(got - env).mean() < 0.01
    assert np.abs(got - env[:, ::-1]).mean() > 0.05  # a mirrored capture would fail


def test_resume_after_crash_gives_identical_files(dataset, tmp_path):
    ref, _ = dataset
    out = tmp_path / "crashed"
    shutil.copytree(ref, out)
    # Simulate a kill -9 at various moments: a sample in flight (some views written, no marker), an
    # object whose marker was never written, a stray temporary file, the preview not yet made.
    samples = sorted((out / "samples").iterdir())
    (samples[0] / "sample.json").unlink()
    for f in samples[0].glob("view_01*"):
        f.unlink()
    (samples[0] / ".view_02.exr.tmp123.exr").write_bytes(b"partial")
    shutil.rmtree(samples[1])
    (out / "objects" / "obj_0001" / "object.json").unlink()
    (out / "objects" / "obj_0001" / "texture.png").unlink()
    (out / "preview.png").unlink()
    stats = generate(tiny_config(), out, workers=1, progress=False)
    assert stats["rendered_views"] == 1 + 3 and stats["skipped_samples"] == 0
    (samples[0] / ".view_02.exr.tmp123.exr").unlink()
    assert _binary_files(out) == _binary_files(ref)
    assert _json_without_timing(out) == _json_without_timing(ref)
    # A rerun of a finished dataset renders nothing, and keeps the timing of the run that rendered.
    timing = (out / "timing" / "shard_0_of_1.json").read_text()
    again = generate(tiny_config(), out, workers=1, progress=False, preview=False)
    assert again["rendered_views"] == 0 and again["skipped_samples"] == 2
    assert (out / "timing" / "shard_0_of_1.json").read_text() == timing


def test_corrupt_sample_and_changed_settings_are_clear_errors(dataset, tmp_path):
    ref, _ = dataset
    out = tmp_path / "corrupt"
    shutil.copytree(ref, out)
    victim = sorted((out / "samples").iterdir())[0] / "view_00.exr"
    victim.write_bytes(victim.read_bytes()[:100])
    with pytest.raises(DataError, match="corrupt"):
        generate(tiny_config(), out, workers=1, progress=False)
    with pytest.raises(DataError, match="different settings"):
        generate(tiny_config(spp=8), ref, workers=1, progress=False)


def test_bad_input():
    with pytest.raises(ValueError, match="unknown dataset"):
        make_config("plastic")
    with pytest.raises(ValueError, match="resolution"):
        make_config("glossy", resolution=0)
    with pytest.raises(ValueError, match="envs-per-object"):
        make_config("glossy", num_envmaps=2, envs_per_object=3)
    with pytest.raises(ValueError, match="shard"):
        parse_shard("3/2")
    with pytest.raises(DataError, match="cannot write"):
        generate(tiny_config(), "/proc/no_such_dir/ds", workers=1, progress=False)


def test_plan_is_deterministic_and_materials_follow_the_paper():
    a, b = plan(tiny_config("glossy", num_objects=10, num_envmaps=10)), plan(tiny_config("glossy", num_objects=10, num_envmaps=10))
    assert a == b
    assert len(a["splits"]["objects"]["test"]) == 2 and len(a["splits"]["envmaps"]["test"]) == 2
    for o in a["objects"]:
        mat = o["material"]
        assert mat["metallic"] == 0.0 and mat["specular_ior_level"] == 1.0 and 0.0 <= mat["roughness"] <= 0.4
        pool = a["splits"]["envmaps"][o["split"]]
        assert set(o["envmaps"]) <= set(pool)
    assert a["splits"]["test_objects_see_only_test_envmaps"]
    # the default size keeps the test split unseen (objects and env maps) with 3 maps per object
    default = plan(make_config("glossy"))
    assert default["splits"]["test_objects_see_only_test_envmaps"]
    assert all(set(o["envmaps"]) <= set(default["splits"]["envmaps"]["test"])
               for o in default["objects"] if o["split"] == "test")
    d = plan(tiny_config("diffuse", num_objects=10))
    assert all(o["material"]["subsurface_weight"] > 0 for o in d["objects"])
    tones = sorted(o["tone"] for o in d["objects"])
    assert all(k / 10 <= t < (k + 1) / 10 for k, t in enumerate(tones))  # balanced skin tones
    assert azimuths(tiny_config("diffuse", views=12))[0] == -82.5
    assert azimuths(tiny_config("metallic", views=24))[1] == 15.0


def test_optional_settings_enter_the_config_only_when_set():
    """--denoise / --envmaps are recorded when used; without them the manifest's config is what it always was,
    so datasets made before these options resume with the same command."""
    from datagen.__main__ import build_parser

    plain = config_dict(make_config("glossy"))
    assert not {"denoise", "envmaps_dir", "procedural_envmaps", "elevations"} & set(plain)
    assert config_dict(make_config("glossy", elevations=[12.0, 27.0]))["elevations"] == [12.0, 27.0]
    args = build_parser().parse_args(["--dataset", "glossy", "--out", "x", "--elevations", "12,27,42"])
    assert args.elevations == [12.0, 27.0, 42.0]
    assert config_dict(make_config("glossy", denoise=True))["denoise"] is True
    args = build_parser().parse_args(["--dataset", "diffuse", "--out", "x", "--denoise"])
    assert args.denoise is True and args.envmaps is None


def test_views_at_several_elevations_are_rendered_where_their_cameras_say(tmp_path):
    """--elevations: the views take the elevations in turn, one later on each next object (so that no elevation is
    tied to an azimuth); each view's camera record, the manifest and the rasterised GT mesh agree with Cycles."""
    from datagen.layout import CameraSetup
    from datagen.plan import elevations

    raster = pytest.importorskip("dibrpp.raster")
    from dibrpp.camera import Cameras
    from dibrpp.conventions import orbit_world_to_camera
    from dibrpp.mesh import Meshes

    cfg = tiny_config(num_objects=2, num_envmaps=1, elevations=[10.0, 45.0, 30.0])
    assert elevations(cfg, 0) == [10.0, 45.0, 30.0] and elevations(cfg, 1) == [45.0, 30.0, 10.0]
    assert elevations(tiny_config(), 5) == [DEFAULT_CAMERA.elevation_deg] * 3
    out = tmp_path / "metallic-elevations"
    generate(cfg, out, workers=1, progress=False, preview=False)
    m = json.loads((out / "manifest.json").read_text())
    cam = CameraSetup.from_manifest(m)
    assert m["config"]["elevations"] == [10.0, 45.0, 30.0] and cam.elevations_deg == (10.0, 45.0, 30.0)
    assert cam.elevation_deg == 30.0  # their median: the camera predict assumes
    for sample in sorted((out / "samples").iterdir()):
        obj = json.loads((sample / "sample.json").read_text())["object"]
        with np.load(out / "objects" / f"obj_{obj:04d}" / "mesh.npz") as mesh_file:
            mesh = Meshes(torch.from_numpy(mesh_file["verts"]).float(), torch.from_numpy(mesh_file["faces"]))
        assert json.loads((sample / "sample.json").read_text())["elevations_deg"] == elevations(cfg, obj)
        for v in range(cfg.views):
            view = json.loads((sample / f"view_{v:02d}.json").read_text())
            w2c = torch.tensor(view["world_to_camera"])
            assert view["elevation_deg"] == cam.view_elevation_deg(obj, v) == elevations(cfg, obj)[v]
            expected = orbit_world_to_camera(torch.tensor(cam.distance), view["elevation_deg"], view["azimuth_deg"])
            assert torch.allclose(w2c, expected.float(), atol=1e-4)
            ours = raster.rasterize(mesh, Cameras(w2c, torch.tensor([view["fov"]]), view["resolution"])).mask[0] > 0.5
            alpha = torch.from_numpy(read_exr(sample / f"view_{v:02d}.exr", "RGBA")[..., 3] > 0.5)
            assert (ours & alpha).sum() / (ours | alpha).sum() >= 0.95, (obj, v)
    with pytest.raises(ValueError, match="strictly between -90 and 90"):
        tiny_config(elevations=[27.0, 90.0])
