"""Your own environment maps (python -m datagen --envmaps DIR): reading .exr / .hdr, area-average resampling,
clear errors for bad maps before anything renders, and a tiny dataset lit by a folder of two hand-made maps."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from datagen import envmap_files
from dibrpp import conventions as conv
from dibrpp.io import DataError, read_exr, write_exr

ROOT = Path(__file__).resolve().parents[2]


def smooth_map(h, seed=0):
    """A smooth, direction-coded HDR map (no two directions alike) with a bright blob."""
    d = conv.equirect_directions(h, 2 * h, dtype=torch.float64).numpy()
    rng = np.random.default_rng(seed)
    sun = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    blob = 20 * np.exp(40 * ((d @ sun) - 1))
    base = np.stack([1.2 + d[..., 0], 1.1 + d[..., 1], 1.05 + d[..., 2]], -1) * rng.uniform(0.5, 1.5, 3)
    return (base + blob[..., None]).astype(np.float32)


def energy(env):
    h, w = env.shape[:2]
    return (env * conv.equirect_solid_angles(h, w, dtype=torch.float64).numpy()[..., None]).sum((0, 1))


def exact_energy(env):
    h, w = env.shape[:2]
    edges = np.linspace(0, np.pi, h + 1)
    dw = (np.cos(edges[:-1]) - np.cos(edges[1:])) * 2 * np.pi / w
    return (env * dw[:, None, None]).sum((0, 1))


# ----------------------------------------------------------------------------- Radiance .hdr

@pytest.mark.parametrize("rle", [True, False])
def test_hdr_round_trip_flat_and_run_length(tmp_path, rle):
    img = smooth_map(8)  # width 16: run-length encoded when asked
    img[0] = 3.0  # a constant row: runs
    img[1, :5] = 0.0
    envmap_files.write_hdr(tmp_path / "m.hdr", img, rle=rle)
    back = envmap_files.read_hdr(tmp_path / "m.hdr")
    assert back.shape == img.shape and back.dtype == np.float32
    # RGBE keeps 8 bits of mantissa per pixel, relative to the pixel's largest channel
    assert (np.abs(back - img) / img.max(-1, keepdims=True).clip(1e-6)).max() < 1 / 128
    assert np.all(back[1, :5] == 0)


def test_hdr_reader_agrees_with_blender(tmp_path):
    bpy = pytest.importorskip("bpy")
    img = smooth_map(8, seed=3)
    envmap_files.write_hdr(tmp_path / "m.hdr", img)
    im = bpy.data.images.load(str(tmp_path / "m.hdr"))
    px = np.array(im.pixels[:], np.float32).reshape(im.size[1], im.size[0], 4)[::-1, :, :3]  # bpy: bottom row first
    bpy.data.images.remove(im)
    np.testing.assert_array_equal(envmap_files.read_hdr(tmp_path / "m.hdr"), px)


def test_hdr_orientation_flags(tmp_path):
    img = smooth_map(4)
    envmap_files.write_hdr(tmp_path / "m.hdr", img)
    data = (tmp_path / "m.hdr").read_bytes()
    ref = envmap_files.read_hdr(tmp_path / "m.hdr")
    (tmp_path / "up.hdr").write_bytes(data.replace(b"-Y 4 +X 8", b"+Y 4 +X 8"))  # bottom row first
    np.testing.assert_array_equal(envmap_files.read_hdr(tmp_path / "up.hdr"), ref[::-1])
    (tmp_path / "t.hdr").write_bytes(data.replace(b"-Y 4 +X 8", b"+X 8 -Y 4"))  # transposed: refused
    with pytest.raises(ValueError, match="resolution line"):
        envmap_files.read_hdr(tmp_path / "t.hdr")


# ----------------------------------------------------------------------------- resampling

@pytest.mark.parametrize("src,dst", [(32, 8), (24, 8), (8, 8), (6, 16)])
def test_resampling_preserves_energy_and_orientation(src, dst):
    env = smooth_map(src)
    out = envmap_files.resample_equirect(env, dst)
    assert out.shape == (dst, 2 * dst, 3) and out.dtype == np.float32
    np.testing.assert_allclose(exact_energy(out), exact_energy(env), rtol=1e-5)
    if src == dst:
        np.testing.assert_allclose(out, env, rtol=1e-5)
    # Area averaging keeps the map where it was: a coarse map rendered from the fine one agrees with the
    # fine map averaged by blocks where sizes divide.
    if src % dst == 0:
        k = src // dst
        blocks = env.reshape(dst, k, 2 * dst, k, 3)
        rows = np.linspace(0, np.pi, src + 1)
        wrow = (np.cos(rows[:-1]) - np.cos(rows[1:])).reshape(dst, k)
        expected = (blocks * wrow[:, :, None, None, None]).sum((1, 3)) / (k * wrow.sum(1))[:, None, None]
        np.testing.assert_allclose(out, expected, rtol=1e-5)
    # a constant map stays constant
    np.testing.assert_allclose(envmap_files.resample_equirect(np.full((src, 2 * src, 3), 0.7, np.float32), dst), 0.7, rtol=1e-6)


# ----------------------------------------------------------------------------- bad maps

def _bad_maps(tmp_path):
    good = smooth_map(4)
    cases = {}
    d = tmp_path / "not_2to1"
    d.mkdir()
    write_exr(d / "square.exr", np.ones((8, 8, 3), np.float32))
    cases["not_2to1"] = (d, "square.exr", "not an equirectangular map")
    for name, value, match in (("nan", np.nan, "NaN/Inf"), ("inf", np.inf, "NaN/Inf"), ("negative", -0.5, "negative")):
        d = tmp_path / name
        d.mkdir()
        write_exr(d / "a_good.exr", good)
        bad = good.copy()
        bad[1, 2, 0] = value
        write_exr(d / f"{name}.exr", bad)
        cases[name] = (d, f"{name}.exr", match)
    d = tmp_path / "unreadable"
    d.mkdir()
    (d / "broken.exr").write_bytes(b"not an exr at all")
    cases["unreadable"] = (d, "broken.exr", "cannot read")
    d = tmp_path / "truncated_hdr"
    d.mkdir()
    envmap_files.write_hdr(d / "cut.hdr", good)
    (d / "cut.hdr").write_bytes((d / "cut.hdr").read_bytes()[:-20])
    cases["truncated_hdr"] = (d, "cut.hdr", "cannot read")
    d = tmp_path / "empty"
    d.mkdir()
    (d / "README.txt").write_text("no maps here")
    cases["empty"] = (d, "", "no .exr or .hdr files")
    return cases


def test_each_kind_of_bad_map_is_named_with_what_to_do(tmp_path):
    from datagen.config import make_config
    from datagen.generate import generate

    for kind, (folder, name, match) in _bad_maps(tmp_path).items():
        with pytest.raises(DataError, match=match) as e:
            cfg = make_config("glossy", envmaps=folder, num_objects=1, envs_per_object=1, views=1)
            generate(cfg, tmp_path / f"out_{kind}", workers=1, progress=False)
        msg = str(e.value)
        assert str(folder / name) in msg and "\n" not in msg, (kind, msg)
        assert any(w in msg for w in ("remove", "put", "convert", "clamp", "repair")), msg
        assert not (tmp_path / f"out_{kind}" / "manifest.json").exists()  # failed before anything was written


def test_cli_exit_status_2_and_one_line_error(tmp_path):
    folder, name, _ = _bad_maps(tmp_path)["negative"]
    r = subprocess.run([sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(tmp_path / "o"),
                        "--envmaps", str(folder), "--quiet"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0], r.stderr
    r = subprocess.run([sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(tmp_path / "o"),
                        "--envmaps", str(folder), "--num-envmaps", "3"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "--procedural-envmaps" in r.stderr
    r = subprocess.run([sys.executable, "-m", "datagen", "--dataset", "glossy", "--out", str(tmp_path / "o"),
                        "--procedural-envmaps", "3"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and "--envmaps" in r.stderr


# ----------------------------------------------------------------------------- the plan

def test_files_come_first_sorted_and_each_kind_is_split_4_to_1(tmp_path):
    from datagen.config import config_dict, make_config
    from datagen.plan import plan

    for i in range(10):
        (tmp_path / f"map_{9 - i:02d}.{'exr' if i % 2 else 'hdr'}").write_bytes(b"")  # only listed, not read
    (tmp_path / "notes.txt").write_text("ignored")
    assert [p.name for p in envmap_files.list_envmap_files(tmp_path)] == [f"map_{i:02d}.{'hdr' if i % 2 else 'exr'}"
                                                                for i in range(10)]
    cfg = make_config("glossy", envmaps=tmp_path, procedural_envmaps=5, num_objects=20)
    assert cfg.num_envmaps == 15 and cfg.num_file_envmaps == 10
    p = plan(cfg)
    assert p["env_kind"][:10] == ["file"] * 10 and set(p["env_kind"][10:]) <= {"outdoor", "indoor"}
    test = p["splits"]["envmaps"]["test"]
    assert len([e for e in test if e < 10]) == 2 and len([e for e in test if e >= 10]) == 1
    assert p["splits"]["test_objects_see_only_test_envmaps"] is True
    assert plan(cfg) == p  # deterministic; another seed splits differently
    assert plan(make_config("glossy", envmaps=tmp_path, procedural_envmaps=5, num_objects=20, seed=1)) != p
    # The procedural-only config is unchanged by the new options (old manifests keep matching).
    assert set(config_dict(make_config("glossy"))) == {
        "dataset", "num_objects", "num_envmaps", "envs_per_object", "views", "resolution", "spp", "seed",
        "texture_size", "envmap_height", "grid", "max_bounces", "preset"}



def test_outdoor_share_decides_how_many_procedural_maps_are_skies():
    from datagen.config import config_dict, make_config
    from datagen.plan import plan

    kinds = lambda **kw: plan(make_config("metallic", num_envmaps=40, **kw))["env_kind"]  # noqa: E731
    assert set(kinds(outdoor_share=1.0)) == {"outdoor"} and set(kinds(outdoor_share=0.0)) == {"indoor"}
    assert kinds() == kinds(outdoor_share=0.6)  # the default share, as before the option
    assert 0 < kinds().count("outdoor") < 40
    assert config_dict(make_config("metallic", outdoor_share=1.0))["outdoor_share"] == 1.0
    with pytest.raises(ValueError, match="outdoor-share"):
        make_config("metallic", outdoor_share=1.5)

# ----------------------------------------------------------------------------- a tiny dataset

@pytest.mark.cycles
def test_tiny_dataset_from_a_folder_of_one_exr_and_one_hdr(tmp_path):
    pytest.importorskip("bpy")
    pytest.importorskip("xatlas")
    from datagen.config import make_config
    from datagen.generate import generate
    from datagen.layout import DatasetLayout

    folder = tmp_path / "hdris"
    folder.mkdir()
    exr_map, hdr_map = smooth_map(8, seed=1), smooth_map(12, seed=2) * 0.5
    write_exr(folder / "b_studio.exr", exr_map)
    envmap_files.write_hdr(folder / "a_sky.hdr", hdr_map)
    hdr_read = envmap_files.read_hdr(folder / "a_sky.hdr")
    cfg = make_config("glossy", envmaps=folder, procedural_envmaps=1, num_objects=1, envs_per_object=3, views=1,
                        resolution=16, spp=2, texture_size=32, envmap_height=4, grid=32, max_bounces=1)
    out = tmp_path / "ds"
    stats = generate(cfg, out, workers=1, progress=False, preview=False)
    assert stats["rendered_views"] == 3
    lay = DatasetLayout(out)
    m = json.loads(lay.manifest.read_text())
    assert m["env_kind"][:2] == ["file", "file"] and m["env_kind"][2] in ("outdoor", "indoor")
    assert [s["file"] for s in m["envmap_sources"]] == ["a_sky.hdr", "b_studio.exr"]  # sorted by name
    assert [(s["height"], s["width"]) for s in m["envmap_sources"]] == [(12, 24), (8, 16)]
    assert m["envmap_sources"][0]["sha256"] == envmap_files.sha256_of(folder / "a_sky.hdr")
    assert m["config"]["envmaps_dir"] == str(folder) and m["config"]["procedural_envmaps"] == 1
    for i, src in enumerate((hdr_read, exr_map)):
        env = read_exr(lay.envmap(i), "RGB")
        np.testing.assert_allclose(env, envmap_files.resample_equirect(src, 4), rtol=1e-6)
        np.testing.assert_allclose(exact_energy(env), exact_energy(src), rtol=1e-4)
        rec = json.loads(lay.envmap_json(i).read_text())
        assert rec["kind"] == "file" and rec["source"]["file"] == m["envmap_sources"][i]["file"]
    for e in range(3):
        rgba = read_exr(lay.view_image(0, e, 0), "RGBA")
        assert rgba[..., 3].max() > 0.9 and rgba[..., :3].max() > 0  # the object is there, and lit
    # the loader reads it like any dataset
    from datagen.reader import MultiViewDataset

    ds = MultiViewDataset(out, split="all", views_per_item=1)
    assert len(ds) == 3 and ds[0]["envmap"].shape == (4, 8, 3)
    # a resumed run refuses a folder whose files changed, before rendering
    write_exr(folder / "b_studio.exr", exr_map * 2)
    with pytest.raises(DataError, match="other env map files"):
        generate(cfg, out, workers=1, progress=False)


def test_too_few_maps_and_bad_counts_say_what_to_do(tmp_path):
    from datagen.config import make_config

    write_exr(tmp_path / "only.exr", smooth_map(4))
    with pytest.raises(ValueError, match="1 in .* 0 procedural.*--procedural-envmaps"):
        make_config("glossy", envmaps=tmp_path, envs_per_object=2)
    assert make_config("glossy", envmaps=tmp_path, procedural_envmaps=1, envs_per_object=2).num_envmaps == 2
    with pytest.raises(ValueError, match="--procedural-envmaps must be >= 0"):
        make_config("glossy", envmaps=tmp_path, procedural_envmaps=-1)


def test_compression_noise_below_zero_is_accepted_and_becomes_zero(tmp_path):
    """Lossy EXRs (DWA, as Blender's bundled maps) hold values a hair below 0; a real negative is refused."""
    img = smooth_map(4)
    img[1, 2, 0] = -0.01 * img.mean()
    envmap_files.check_envmap("noisy.exr", img)
    assert envmap_files.resample_equirect(img, 2).min() >= 0
    img[1, 2, 0] = -0.5 * img.mean()
    with pytest.raises(envmap_files.EnvmapError, match="negative"):
        envmap_files.check_envmap("broken.exr", img)

