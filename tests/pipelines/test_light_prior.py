import json
import shutil

import numpy as np
import pytest
import torch

from dibrpp import Cameras
from dibrpp.conventions import equirect_directions
from dibrpp.io import DataError
from pipelines import light_prior
from pipelines.light_prior import HEIGHT, SUN_CLIP, WIDTH, build, fit, log_luminance, solid_angle_weights
from pipelines.model import Encoder, ModelConfig
from pipelines.model_input import encoder_input


def synthetic_maps(n: int, seed: int = 0) -> np.ndarray:
    """Skies with known degrees of freedom in log luminance: the sky/ground contrast and a tilt towards +X (two
    components once turned about the vertical: towards X and Y), at random levels (which the prior ignores)."""
    rng = np.random.default_rng(seed)
    d = equirect_directions(2 * HEIGHT, 2 * WIDTH).numpy()
    contrast, tilt, level = rng.normal(0, 0.4, n), rng.normal(0, 0.15, n), rng.normal(0, 2, n)
    log = level[:, None, None] + contrast[:, None, None] * np.tanh(4 * d[None, ..., 2]) + tilt[:, None, None] * d[None, ..., 0]
    return np.repeat(np.exp(log)[..., None], 3, -1).astype(np.float32)


def test_the_prior_finds_the_maps_degrees_of_freedom():
    prior = fit(synthetic_maps(60), components=4)
    assert prior["explained"][2] > 0.999  # three components hold all of it, whatever the levels and turns
    w = solid_angle_weights()
    gram = (prior["basis"] * w) @ prior["basis"].T
    torch.testing.assert_close(gram, torch.eye(4), atol=1e-4, rtol=0)
    assert prior["std"][2] > 10 * prior["std"][3]


def test_the_sun_is_clipped_out_of_the_maps():
    maps = np.ones((1, 2 * HEIGHT, 2 * WIDTH, 3), np.float32)
    maps[0, 5, 7] = 1e5  # a sun
    log = log_luminance(torch.from_numpy(maps))
    assert float(log.max() - log.min()) <= np.log(SUN_CLIP) + 1e-4


def _maps_folder(path, maps, chunk=20):
    path.mkdir()
    for k in range(len(maps) // chunk):
        np.save(path / f"maps_{k:04d}.npy", maps[k * chunk:(k + 1) * chunk])
    (path / "manifest.json").write_text(json.dumps({"count": len(maps), "chunk": chunk, "height": 2 * HEIGHT,
                                                    "generator": "test"}))


def test_the_prior_is_cached_and_refitted_when_the_maps_change(tmp_path, monkeypatch):
    _maps_folder(tmp_path / "maps", synthetic_maps(40))
    first = build(tmp_path / "maps", components=3)
    calls = []
    monkeypatch.setattr(light_prior, "fit", lambda *a, **k: calls.append(1) or first)
    build(tmp_path / "maps", components=3)
    assert not calls  # read from the cache
    manifest = json.loads((tmp_path / "maps" / "manifest.json").read_text())
    (tmp_path / "maps" / "manifest.json").write_text(json.dumps({**manifest, "generator": "changed"}))
    build(tmp_path / "maps", components=3)
    assert calls  # refitted
    with pytest.raises(DataError, match="make light-prior"):
        build(tmp_path / "missing")
    (tmp_path / "maps" / "maps_0001.npy").unlink()
    with pytest.raises(DataError, match="1 of 2 chunks"):
        build(tmp_path / "maps")


def test_the_probe_heads_sky_is_the_prior_map_that_fits_the_mirror_cue_in_the_world():
    """The untrained head with a prior: a mirror-like object whose upper half is bright shows a bright sky over a
    dark ground; the fitted prior map has that split in the world frame from any azimuth."""
    torch.manual_seed(0)
    prior = fit(synthetic_maps(60), components=4)
    model = Encoder(ModelConfig(image_size=32, shading="sg", lobes=16, light_head="probe", light_prior=4))
    model.light_head.set_prior(prior)
    rgba = torch.zeros(1, 32, 32, 4)
    rgba[..., 3] = 1.0
    rgba[:, :16, :, :3], rgba[:, 16:, :, :3] = 0.9, 0.05
    for azimuth in (0.0, 150.0):
        cams = Cameras.orbit(40.0, 0.0, azimuth, 40.0, 32)
        with torch.no_grad():
            env = model(encoder_input(rgba), cams).light(cams.world_to_camera).to_envmap(16, 32).image[0]
        assert env[:6].mean() > 3 * env[-6:].mean(), azimuth
    with pytest.raises(ValueError, match="components"):
        Encoder(ModelConfig(shading="sg", light_head="probe", light_prior=20)).light_head.set_prior(prior)
    with pytest.raises(ValueError, match="MC"):
        Encoder(ModelConfig(shading="mc", light_head="probe", light_prior=4))


def test_a_run_trains_with_the_prior_keeps_it_and_can_be_diagnosed(tiny_glossy, tmp_path, capsys):
    from pipelines import diagnose_light, train
    from pipelines.runs import load_run

    _maps_folder(tmp_path / "maps", synthetic_maps(40))
    out = tmp_path / "runs" / "glossy" / "sg-light-prior-seed0"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--image-size", "32", "--iterations", "2",
                       "--light-prior", str(tmp_path / "maps"), "--out", str(out), "--no-progress"]) == 0
    saved = load_run(out).model.light_head.prior_maps.clone()
    shutil.rmtree(tmp_path / "maps")  # the run holds its prior
    assert saved.abs().sum() > 0 and torch.equal(load_run(out).model.light_head.prior_maps, saved)
    status = diagnose_light.main(["--run", str(out), "--view-stride", "2"])
    text = capsys.readouterr()
    assert status == 0 and "the run's sun lobe alone" in text.out and "a sun read off the cue" in text.out, text.err
    assert "without its learnt shift" in text.out and "elevation error" in text.out
    assert "° high" in text.out and "views of each test map" in text.out  # the by-map table
    assert "by their light's elevation" in text.out  # the by-elevation table
    assert "turn within a pixel" in text.out  # how fast the GT surface turns where it mirrors the sun
    with pytest.raises(SystemExit) as exit_:  # --split all counts the samples it trained on without a --dataset
        diagnose_light.main(["--run", str(out), "--split", "all"])
    assert exit_.value.code == 2 and "--dataset" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:  # ... and on its own dataset
        diagnose_light.main(["--run", str(out), "--dataset", str(tiny_glossy), "--split", "all"])
    assert exit_.value.code == 2 and "trained on" in capsys.readouterr().err
    assert "each object's shape averaged over its views" in text.out
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--light-prior", str(tmp_path / "maps"),
                       "--out", str(tmp_path / "other"), "--no-progress"]) == 2
    assert "make light-prior" in capsys.readouterr().err


@pytest.mark.slow
def test_prior_maps_are_rendered_resumably_and_refuse_other_settings(tmp_path):
    """Real Cycles renders (tiny maps): chunks and a manifest; a rerun renders nothing new; another seed into the
    same folder is refused; the maps are HDR skies and rooms the prior can be fitted to."""
    from datagen.prior_maps import generate

    out = tmp_path / "maps"
    generate(out, count=4, height=8, spp=2, workers=1, progress=False, chunk=2)
    first = {p.name: p.stat().st_mtime_ns for p in out.glob("maps_*.npy")}
    assert sorted(first) == ["maps_0000.npy", "maps_0001.npy"]
    generate(out, count=4, height=8, spp=2, workers=1, progress=False, chunk=2)
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("maps_*.npy")} == first
    with pytest.raises(DataError, match="other settings"):
        generate(out, count=4, height=8, seed=1, spp=2, workers=1, progress=False, chunk=2)
    maps, manifest = light_prior.read_maps(out)
    assert maps.shape == (4, 8, 16, 3) and manifest["count"] == 4 and (maps > 0).all() and np.isfinite(maps).all()
