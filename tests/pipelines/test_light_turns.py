"""Where a run places the example sky's sun as it turns (light_turns): the turned sky checked by hand, the CLI's
outputs, and its renders kept for the next call."""
import json
import math

import pytest
import torch

from datagen import example_scene
from pipelines import light_turns, train
from pipelines.photo_input import sun_angle_deg


def test_the_turned_sky_moves_its_sun_by_the_turn():
    """Two suns at 40 degrees of elevation, 90 degrees apart in azimuth, are acos(cos^2 40 cos 90 + sin^2 40) = 65.6
    degrees apart; the eval's sun finds both; turn 0 is the shipped example's sky, its sun 40 degrees left of the
    camera's azimuth."""
    base, turned = (torch.from_numpy(example_scene.sky(sun_azimuth=a)) for a in (70.0, 160.0))
    expected = math.degrees(math.acos(math.sin(math.radians(40.0)) ** 2))
    assert sun_angle_deg(base, turned) == pytest.approx(expected, abs=2.0)
    assert sun_angle_deg(base, base) == pytest.approx(0.0, abs=1e-3)
    assert light_turns.sun_azimuths(4) == [70.0, 160.0, 250.0, 340.0]
    assert [light_turns.relative_azimuth(a) for a in (30.0, 70.0, 210.0, 250.0)] == [0.0, 40.0, -180.0, -140.0]


def test_the_cli_reads_every_turn_from_both_cameras_and_keeps_its_renders(tiny_glossy, tmp_path, capsys):
    pytest.importorskip("bpy")
    run = tmp_path / "run"
    assert train.main(["--preset", "smoke", "--dataset", str(tiny_glossy), "--iterations", "2", "--out", str(run),
                       "--no-progress"]) == 0
    out = tmp_path / "turns"
    args = ["--runs", str(run), "--out", str(out), "--turns", "2", "--spp", "2"]
    assert light_turns.main(args) == 0
    result = json.loads((out / "light_turns.json").read_text())
    cameras = result["runs"][str(run)]
    assert set(cameras) == {"photo", "training"}
    for camera in cameras.values():
        assert [t["relative_azimuth_deg"] for t in camera["turns"]] == [40.0, -140.0]
        assert all(0.0 <= t["angle_deg"] <= 180.0 for t in camera["turns"])
        assert camera["turn0_deg"] == camera["turns"][0]["angle_deg"] <= camera["worst_deg"]
    table = (out / "light_turns.md").read_text()
    assert "median over 2 turns" in table and table.count(str(run)) == 2
    assert (out / "light_turns.png").stat().st_size > 10_000
    renders = sorted((out / "renders").iterdir())
    assert len(renders) == 4  # two cameras, two turns
    stamps = [p.stat().st_mtime_ns for p in renders]
    capsys.readouterr()
    assert light_turns.main(args) == 0
    assert "rendering" not in capsys.readouterr().out
    assert [p.stat().st_mtime_ns for p in sorted((out / "renders").iterdir())] == stamps


def test_a_missing_run_is_one_error(tmp_path, capsys):
    assert light_turns.main(["--runs", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.startswith("error:")
    assert not (tmp_path / "out" / "light_turns.md").exists()
