"""The sky against the ground of a light (diagnose_sky), on hand-made maps and on a trained run."""
import pytest
import torch

from dibrpp.conventions import LUMINANCE_WEIGHTS, equirect_directions
from pipelines import diagnose_sky, train
from pipelines.evaluation import metrics


def _map(sky, ground, sun=None, h=32, w=64):
    """(1, H, W, 3): ``sky`` above the horizon, ``ground`` below, and a bright ``sun`` cell high in the sky."""
    up = equirect_directions(h, w)[..., 2] > 0
    env = torch.where(up[..., None], torch.tensor(sky), torch.tensor(ground)).clone()
    if sun is not None:
        env[h // 4, w // 3] = torch.tensor(sun)
    return env[None]


def test_a_blue_sky_over_a_brown_ground_is_measured_as_painted_and_its_sun_left_out():
    sky, ground = (0.4, 0.6, 1.0), (0.3, 0.2, 0.1)
    ratio, bluer = metrics.sky_contrast(_map(sky, ground, sun=(5000.0, 4800.0, 4000.0)))
    lum = torch.tensor(LUMINANCE_WEIGHTS)
    torch.testing.assert_close(ratio, (torch.tensor(sky) @ lum / (torch.tensor(ground) @ lum))[None])
    torch.testing.assert_close(bluer, torch.tensor([1.0 / 2.0 - 0.1 / 0.6]))
    assert metrics.has_sky(ratio, bluer).all()


def test_a_constant_map_with_a_sun_has_no_sky():
    ratio, bluer = metrics.sky_contrast(_map((0.5, 0.5, 0.5), (0.5, 0.5, 0.5), sun=(900.0, 900.0, 900.0)))
    torch.testing.assert_close(ratio, torch.ones(1))
    torch.testing.assert_close(bluer, torch.zeros(1))
    assert not metrics.has_sky(ratio, bluer).any()


def test_the_cli_reads_a_run_and_says_what_it_measured(tiny_glossy, tmp_path, capsys):
    run = tmp_path / "sg"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--iterations", "2", "--out", str(run),
                       "--no-progress"]) == 0
    code = diagnose_sky.main(["--runs", str(run), "--view-stride", "1"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "a constant map (the reference" in captured.out and "| 0 %" in captured.out
    # the target's own count: the views under the dataset's outdoor maps (its manifest's env_kind)
    import json
    from datagen.reader import MultiViewDataset
    from pipelines.scoring import strided_views
    ds = MultiViewDataset(tiny_glossy, split="test", views_per_item=1)
    kinds = json.loads((tiny_glossy / "manifest.json").read_text())["env_kind"]
    outdoor = sum(kinds[ds[i]["envmap_index"]] == "outdoor" for i in strided_views(ds, 1))
    assert "… of the views under outdoor maps" in captured.out and f"% of {outdoor} |" in captured.out
    # --dataset names the set whose test views are read: here the run's own, so the same table
    assert diagnose_sky.main(["--runs", str(run), "--view-stride", "1", "--dataset", str(tiny_glossy)]) == 0
    assert captured.out.splitlines()[2:] == capsys.readouterr().out.splitlines()[2:]


def test_a_folder_that_is_no_run_is_refused_by_name(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        diagnose_sky.main(["--runs", str(tmp_path)])
    assert e.value.code == 2
    assert "not a run folder" in capsys.readouterr().err
