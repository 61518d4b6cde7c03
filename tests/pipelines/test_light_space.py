"""The learned space of env maps (pipelines.model.light_space, pipelines.light_space, datagen.envmap_set) and the probe
head's sky decoded from it (light_head "space")."""
import json
import math

import numpy as np
import pytest
import torch

from dibrpp import Cameras, conventions
from dibrpp.conventions import orbit_world_to_camera
from pipelines.model.light_probe import world_to_probe
from pipelines.model.light_space import (LATENT_BOUND, LightSpace, SpaceConfig, area_downsample, augment,
                                         log_map_error, sample_log_map, to_log_map, yaw_frame)


def _sky(n: int, height: int = 32, seed: int = 0) -> torch.Tensor:
    """(n, 3, H, 2H) hand-made skies: a bluish sky over a darker ground, a bright sun at a random place."""
    g = torch.Generator().manual_seed(seed)
    d = conventions.equirect_directions(height, 2 * height, dtype=torch.float64)  # (H, W, 3)
    maps = []
    for _ in range(n):
        sun = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64) * torch.tensor([1, 1, 0.3])
                                            + torch.tensor([0, 0, 0.5]), dim=0)
        up = d[..., 2:]
        sky = torch.where(up > 0, torch.tensor([0.6, 0.8, 1.2]), torch.tensor([0.3, 0.25, 0.2]) * (0.5 + torch.rand(1, generator=g)))
        sky = sky + 50 * torch.exp(400 * ((d * sun).sum(-1, keepdim=True) - 1))
        maps.append(sky.permute(2, 0, 1))
    return torch.stack(maps).float()


def test_area_downsampling_keeps_a_maps_power():
    """The integral of radiance over the sphere is the same at the space's size (a sun is not lost between cells)."""
    maps = _sky(3).double()
    power = lambda m: (m * conventions.equirect_solid_angles(m.shape[2], m.shape[3], dtype=m.dtype)  # noqa: E731
                       .view(1, 1, -1, 1)).sum((2, 3))
    small = area_downsample(maps, 8)
    assert small.shape == (3, 3, 8, 16)
    assert torch.allclose(power(small), power(maps), rtol=1e-9)
    with pytest.raises(ValueError, match="downsample"):
        area_downsample(maps, 5)


@pytest.mark.parametrize("elevation", [-60.0, 0.0, 12.0, 27.0, 42.0, 80.0])
def test_the_space_frame_has_the_worlds_up_as_its_pole_and_the_camera_ahead(elevation):
    # (the orbit camera is float32: orthonormal to ~1e-7)
    azimuths = torch.tensor([0.0, 37.0, 200.0])
    w2c = torch.stack([orbit_world_to_camera(60.0, elevation, float(a)) for a in azimuths]).double()
    probe_to_world = world_to_probe(w2c).mT
    to_space = yaw_frame(probe_to_world)
    assert torch.allclose(to_space @ to_space.mT, torch.eye(3, dtype=torch.float64).expand(3, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(to_space), torch.ones(3, dtype=torch.float64))
    world_up_in_probe = probe_to_world[:, 2]
    assert torch.allclose(torch.einsum("bij,bj->bi", to_space, world_up_in_probe),
                          torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(3, 3), atol=1e-5)
    # the camera looks at the origin: its view direction, seen in the space frame, is ahead (+X) and below the horizon
    for b, azimuth in enumerate(azimuths):
        to_object = -conventions.orbit_position(60.0, elevation, float(azimuth)).double()
        seen = to_space[b] @ world_to_probe(w2c[b:b + 1])[0] @ (to_object / to_object.norm())
        assert abs(float(seen[1])) < 1e-5 and float(seen[0]) > 0
        assert float(seen[2]) == pytest.approx(-math.sin(math.radians(elevation)), abs=1e-5)


def test_a_log_map_is_read_at_its_cells_and_wraps_at_the_seam():
    log_map = torch.randn(2, 3, 8, 16, dtype=torch.float64)
    dirs = conventions.equirect_directions(8, 16, dtype=torch.float64).view(1, -1, 3).expand(2, -1, -1)
    assert torch.allclose(sample_log_map(log_map, dirs), log_map.flatten(2).mT, atol=1e-9)
    # -X, the seam (u = 0 and u = 1): halfway between the first and the last column
    seam = torch.tensor([[[-1.0, 0.0, 0.0]]], dtype=torch.float64).expand(2, 1, 3)
    rows = log_map[:, :, 3:5].mean(2)  # the horizon lies between rows 3 and 4
    assert torch.allclose(sample_log_map(log_map, seam)[:, 0], 0.5 * (rows[..., 0] + rows[..., -1]), atol=1e-9)


def test_augmentation_turns_and_mirrors_whole_maps():
    maps = torch.arange(2 * 3 * 4 * 8, dtype=torch.float32).view(2, 3, 4, 8)
    out = augment(maps, torch.Generator().manual_seed(0))
    for m, o in zip(maps, out):
        turns = [torch.roll(m, s, -1) for s in range(8)] + [torch.roll(m.flip(-1), s, -1) for s in range(8)]
        assert any(torch.equal(o, t) for t in turns)


def test_the_space_learns_skies_better_than_their_mean_map(tmp_path):
    """A few hundred steps on hand-made skies: held-out skies come back closer than the mean map does; saved and
    loaded, the space decodes the same."""
    from pipelines.light_space import fit

    torch.manual_seed(0)
    space = LightSpace(SpaceConfig(latent=4, height=8, width=16, channels=16))
    maps = _sky(24)
    losses = fit(space, maps[:20], steps=300, batch=16, kl=1e-3, lr=3e-3, seed=0, progress=False)
    assert np.mean(losses[-20:]) < 0.6 * np.mean(losses[:20])
    test = to_log_map(maps[20:], 8)
    with torch.no_grad():
        decoded = space.decode(space.encode(test)[0])
        assert log_map_error(decoded, test).mean() < 0.6 * log_map_error(space.mean_map.expand_as(test), test).mean()
    space.save(tmp_path / "s.pt")
    loaded = LightSpace.load(tmp_path / "s.pt")
    with torch.no_grad():
        assert torch.equal(loaded.decode(torch.zeros(1, 4)), space.decode(torch.zeros(1, 4)))


def _space_folder(tmp_path):
    from pipelines.model.light_space import FILE

    torch.manual_seed(0)
    space = LightSpace(SpaceConfig())
    space.mean_map.fill_(-0.5)
    folder = tmp_path / "light-space"
    folder.mkdir()
    space.save(folder / FILE)
    return folder


def test_the_space_sky_is_a_decoded_map_the_head_cannot_change(tmp_path, monkeypatch):
    """light_head "space": the sky's lobes are the decoded map at their axes; only the head's latent trains (the
    decoder is held), its latent is bounded, and the light is white-balanced."""
    from pipelines.model.model_input import encoder_input
    from pipelines.training import runs
    from pipelines.training.config import TrainConfig

    monkeypatch.setattr(runs, "LIGHT_SPACE", _space_folder(tmp_path))
    config = TrainConfig(variant="light-space", light_head="space", light_colour="white")
    model = runs.make_model(config, 64)
    assert model.config.sky == "space" and model.light_head.sky_ground is None
    assert not any(p.requires_grad for p in model.light_head.space.parameters())
    w2c = torch.stack([orbit_world_to_camera(60.0, 27.0, a) for a in (0.0, 120.0)])
    cams = Cameras(w2c, torch.full((2,), 0.7), 64)
    pred = model(encoder_input(torch.rand(2, 64, 64, 4, generator=torch.Generator().manual_seed(1))), cams)
    pred.light_params["amplitude"].sum().backward()
    assert model.light_head.to_latent.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.light_head.space.parameters())
    with torch.no_grad():  # a latent pushed far is held within the bound
        model.light_head.to_latent.bias.fill_(100.0)
        h = torch.randn(2, 32, 16, 32)
        z = model.light_head.space_latent(h, torch.randn(2, 512), world_to_probe(w2c).mT)
    assert z.abs().max() <= LATENT_BOUND + 1e-6


def test_a_model_with_the_space_sky_says_where_the_space_is_missing(tmp_path, monkeypatch):
    from dibrpp.io import DataError
    from pipelines.training import runs
    from pipelines.training.config import TrainConfig

    monkeypatch.setattr(runs, "LIGHT_SPACE", tmp_path / "nowhere")
    with pytest.raises(DataError, match="make light-space"):
        runs.make_model(TrainConfig(light_head="space"), 64)
    (tmp_path / "nowhere").mkdir()
    (tmp_path / "nowhere" / "light_space.pt").write_text("not a model")
    with pytest.raises(DataError, match="make light-space"):
        runs.make_model(TrainConfig(light_head="space"), 64)


def test_the_env_map_set_draws_no_datasets_map_and_resumes(tmp_path):
    """Its seeds are a stream of their own (no dataset's map is among them); two maps render, the manifest follows,
    and a rerun renders nothing."""
    pytest.importorskip("bpy")
    from datagen import envmap_set
    from datagen.config import make_config
    from datagen.plan import ENV, seed_for

    ours = {int(envmap_set.map_seed(0, i).generate_state(1)[0]) for i in range(600)}
    for dataset in ("metallic", "glossy", "diffuse"):
        cfg = make_config(dataset)
        assert not ours & {seed_for(cfg, ENV, i, 1) for i in range(600)}
    out = tmp_path / "maps"
    assert envmap_set.render_set(out, 2, height=8, progress=False) == 2
    maps, kinds = envmap_set.read_set(out)
    assert maps.shape == (2, 8, 16, 3) and np.isfinite(maps).all() and (maps >= 0).all()
    assert set(kinds) <= {"outdoor", "indoor"}
    assert envmap_set.render_set(out, 2, height=8, progress=False) == 0
    with pytest.raises(SystemExit, match="other settings"):
        envmap_set.render_set(out, 2, height=16, progress=False)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["count"] == 2 and manifest["format"] == envmap_set.FORMAT


def test_a_light_space_run_trains_resumes_and_loads_with_its_decoder(tiny_glossy, tmp_path, monkeypatch):
    """The variant trains with the decoder held (the checkpoint keeps it: a run loads without models/light-space)."""
    from pipelines.train import train
    from pipelines.training import runs
    from pipelines.training.config import TrainConfig

    space = _space_folder(tmp_path)
    monkeypatch.setattr(runs, "LIGHT_SPACE", space)
    out = tmp_path / "run"
    cfg = dict(dataset=str(tiny_glossy), out=str(out), iterations=2, batch_objects=2, log_every=1, checkpoint_every=2,
               lobes=4, compile=False, variant="light-space", light_head="space", light_colour="white")
    train(TrainConfig(**cfg), progress=False)
    held = LightSpace.load(space / "light_space.pt").state_dict()
    saved = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    assert all(torch.equal(saved[f"light_head.space.{k}"], v) for k, v in held.items())
    monkeypatch.setattr(runs, "LIGHT_SPACE", tmp_path / "gone")
    train(TrainConfig(**{**cfg, "iterations": 3}), resume=True, progress=False)
    run = runs.load_run(out)
    assert run.config.label() == "light-space" and run.model.config.sky == "space"
