"""The light fitted to one view through the GT surface (light_ceiling): on a hand-made scene and on a dataset."""
import pytest
import torch

from dibrpp import Cameras, Material, Renderer, icosphere
from dibrpp.lights import EnvMap, SGLight
from pipelines import light_ceiling
from pipelines.evaluation import metrics


def test_the_fit_finds_a_known_sun_on_a_glossy_sphere():
    """A sphere rendered under a sun over a dim blue sky: the light fitted to that one view puts its brightest
    direction where the sun is and scores the rough-metal probe far better than a constant map (after 30 steps:
    0.68x a constant map and 120 degrees off; after 300: 0.48x and 3 degrees)."""
    sun = torch.tensor([0.5, -0.3, 0.6])
    sun = sun / sun.norm()
    truth = SGLight(torch.stack([sun, torch.tensor([0.0, 0.0, 1.0])])[None], torch.tensor([[300.0, 2.0]]),
                    torch.tensor([[[60.0, 55.0, 50.0], [0.2, 0.3, 0.6]]]))
    renderer = Renderer("sg")
    mesh, cams = icosphere(3), Cameras.orbit(3.0, 20.0, 30.0, 40.0, 48)
    material = Material(albedo=torch.tensor([[0.5, 0.1, 0.1]]), roughness=0.25, metallic=0.0, specular=0.5)
    rgba = renderer(mesh, cams, material, truth).image
    fitted = light_ceiling.fit_view(renderer, mesh, cams, material, rgba, steps=300)
    gt_env = truth.to_envmap(64, 128).image
    scene = metrics.ProbeScene(cams.world_to_camera)
    scores = metrics.light_metrics(fitted, EnvMap(gt_env), scene)
    constant = metrics.constant_light_references(gt_env, scene)
    assert float(scores["direction_deg"]) < 10
    assert float(scores["probe_metal"]) < 0.6 * float(constant["probe_metal_constant"])


def test_the_cli_fits_views_of_a_dataset_and_writes_its_table_and_figure(tiny_glossy, tmp_path, capsys):
    out = tmp_path / "ceiling"
    assert light_ceiling.main(["--dataset", str(tiny_glossy), "--out", str(out), "--steps", "3",
                               "--view-stride", "1", "--max-views", "2"]) == 0
    text = capsys.readouterr().out
    table = (out / f"{tiny_glossy.name}.md").read_text()
    assert "(2; 3 steps)" in table and "constant map" in table and table.strip() in text
    rows = {line.split("|")[1].strip(): line for line in table.splitlines()[2:]}
    assert {"light_ldr", "probe_metal", "probe_mirror", "probe_diffuse"} <= set(rows)
    assert (out / f"{tiny_glossy.name}.png").stat().st_size > 0


def test_a_folder_that_is_no_dataset_is_refused_by_name(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        light_ceiling.main(["--dataset", str(tmp_path), "--out", str(tmp_path / "out")])
    assert e.value.code == 2
    assert str(tmp_path) in capsys.readouterr().err


def _sky_over_ground(sky_rgb, ground_rgb, height=16, width=32) -> torch.Tensor:
    """(1, H, W, 3) a map of one colour above the horizon and another below."""
    env = torch.empty(1, height, width, 3)
    env[:, : height // 2] = torch.tensor(sky_rgb)
    env[:, height // 2:] = torch.tensor(ground_rgb)
    return env


def test_the_sky_tests_pass_a_sky_as_blue_as_the_gt_and_fail_a_grey_one():
    """Scored as diagnose_sky scores a prediction: the GT's own sky passes both tests; a grey sky as bright passes
    neither (no bluer than its ground); one with a third of the GT's blue is a sky but not half the GT's; a map
    without a sky (a room lit from below) is left out (NaN)."""
    gt = _sky_over_ground([0.3, 0.5, 1.0], [0.3, 0.25, 0.2])
    grey = _sky_over_ground([0.6, 0.6, 0.6], [0.25, 0.25, 0.25])
    _, gt_bluer = metrics.sky_contrast(gt)
    third = _sky_over_ground([0.5, 0.55, 0.62], [0.3, 0.25, 0.2])
    _, third_bluer = metrics.sky_contrast(third)
    assert metrics.SKY_BLUER <= float(third_bluer) < 0.5 * float(gt_bluer)
    for table, sky, like_gt in ((gt, 1.0, 1.0), (grey, 0.0, 0.0), (third, 1.0, 0.0)):
        scores = light_ceiling.sky_scores(table, gt)
        assert float(scores["sky"]) == sky and float(scores["sky_like_gt"]) == like_gt
    room = _sky_over_ground([0.2, 0.2, 0.2], [1.0, 0.8, 0.6])
    assert light_ceiling.sky_scores(gt, room)["sky"].isnan().all()


def test_the_table_has_the_sky_rows_over_the_views_with_one():
    fitted = {k: torch.tensor([0.1, 0.2, 0.3]) for k in light_ceiling.METRICS}
    constant = {k: torch.tensor([0.2, 0.2, 0.2]) for k in light_ceiling.METRICS}
    fitted["direction_deg"] = constant["direction_deg"] = torch.full((3,), float("nan"))
    fitted["sky"], fitted["sky_like_gt"] = torch.tensor([1.0, 0.0, float("nan")]), torch.tensor([0.0, 0.0, float("nan")])
    rows = {r[0]: r for r in light_ceiling.summary(fitted, constant)}
    assert rows["a sky over a ground, 2 views with one"][1:3] == ["50 %", "0 %"]
    assert rows["… with half its GT's blue, 2 views with one"][1] == "0 %"
