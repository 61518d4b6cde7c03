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
