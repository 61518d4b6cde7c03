"""The sun read off the mirror cue (the probe head's sun, diagnose_light's row), on hand-made cases."""
import math

import torch

from dibrpp import Cameras
from dibrpp.conventions import equirect_directions, equirect_solid_angles
from dibrpp.lights import SGLight
from dibrpp.mesh import Meshes, icosphere
from dibrpp.sg import sg_integral
from pipelines.diagnose_light import probe_to_world, with_cue_sun
from pipelines.model.light_probe import (ProbeLightHead, camera_to_probe, cue_sun_power, mirror_directions, pixel_samples,
                                  sg_on_grid)


def _probe_grid_with(cells: dict, h=16, w=32, sky=1.0):
    """A probe grid whose mirror cue is ``sky`` on every cell, covered, except cells {(row, col): radiance}."""
    grid = torch.zeros(1, 4, h, w)
    grid[:, :3], grid[:, 3] = sky, 1.0
    for (r, c), v in cells.items():
        grid[0, :3, r, c] = v
    return grid


def test_cue_sun_power_is_the_cues_excess_near_the_axis_on_a_hand_made_grid():
    h, w = 16, 32
    dirs = equirect_directions(h, w).reshape(-1, 3)
    solid = equirect_solid_angles(h, w).expand(-1, w).reshape(-1)
    grid = _probe_grid_with({(5, 10): 11.0, (5, 11): 6.0, (12, 25): 50.0})  # the last one far from the axis
    axis = dirs[5 * w + 10][None]
    expected = 10.0 * solid[5 * w + 10] + 5.0 * solid[5 * w + 11]
    torch.testing.assert_close(cue_sun_power(grid, axis, dirs, solid), expected.expand(1, 3))
    grid[0, 3, 5, 11] = 0.0  # a cell the object does not show holds no light
    torch.testing.assert_close(cue_sun_power(grid, axis, dirs, solid), (10.0 * solid[5 * w + 10]).expand(1, 3))


def test_a_sun_read_off_the_cue_sits_at_the_mirror_direction_of_the_brightest_pixel_above_the_horizon():
    sphere, cams = icosphere(3, radius=10.0), Cameras.orbit(40.0, 25.0, 30.0, 40.0, 24)
    radiance, alpha = torch.full((1, 24, 24, 3), 0.5), torch.ones(1, 24, 24)
    normals, to_camera, _, weight = pixel_samples(sphere, cams, radiance, alpha)
    mirror = mirror_directions(normals, to_camera)[0]
    covered = weight[0] > 0
    above = int(torch.nonzero(covered & (mirror[:, 2] > 0.4))[0])
    below = int(torch.nonzero(covered & (mirror[:, 2] < -0.4))[0])
    radiance.view(1, -1, 3)[0, above] = 500.0
    radiance.view(1, -1, 3)[0, below] = 5000.0  # brighter, but below the horizon: a glint, not the sun
    sky = SGLight(torch.tensor([[[0.0, 0.0, 1.0]]]), torch.tensor([[2.0]]), torch.ones(1, 1, 3))
    lit = with_cue_sun(sky.in_frame(torch.eye(3)[None]), sphere, cams, radiance, alpha)
    assert lit.axis.shape == (1, 2, 3)
    assert math.degrees(math.acos(float(lit.axis[0, 1] @ mirror[above]))) < 8.0
    assert (sg_integral(lit.sharpness, lit.amplitude)[0, 1] > 0).all()


def test_probe_sun_stays_above_the_horizon_and_keeps_at_least_the_cues_power():
    """A bright reflection below the horizon does not draw the sun, and on metal the sun's power is at least what
    the cue shows near it even when the head's own intensity says nothing (a second lobe on its axis carries what
    the cue adds)."""
    torch.manual_seed(0)
    h, w = 16, 32
    grid = torch.cat([_probe_grid_with({(3, 8): 20.0, (12, 8): 200.0}), torch.zeros(1, 4, h, w)], 1)  # + diffuse cue
    heads = {"probe": ProbeLightHead("sg", 8, h, w, 3000.0, 12.0, code=4)}
    dirs = equirect_directions(h, w).reshape(-1, 3)
    for head in heads.values():
        with torch.no_grad():
            head.sun.bias[1:] = -30.0  # a head that learnt to switch its sun off
    with torch.no_grad():
        light = {s: head(grid, torch.zeros(1, 4), torch.eye(3)[None], torch.ones(1)) for s, head in heads.items()}
    up = light["probe"]["axis"][0, -1]
    assert up[2] > 0.5 and float(up @ dirs[3 * w + 8]) > 0.95
    assert light["probe"]["axis"].shape[1] == 9 and heads["probe"].sun_lobes == 2  # the head's sun and the cue's
    power = sg_integral(light["probe"]["sharpness"], light["probe"]["amplitude"])[0, -2:].sum(0)
    cue = cue_sun_power(grid, up[None], dirs, equirect_solid_angles(h, w).expand(-1, w).reshape(-1))[0]
    assert (power >= 0.999 * cue).all() and (cue > 0).all()
    assert sg_integral(light["probe"]["sharpness"], light["probe"]["amplitude"])[0, -2].max() < 1e-6  # its own: off
    # on paint (not metal) the cue also shows diffuse shading: no floor, the sun stays above the horizon
    with torch.no_grad():
        paint = heads["probe"](grid, torch.zeros(1, 4), torch.eye(3)[None], torch.zeros(1))
    torch.testing.assert_close(paint["axis"], light["probe"]["axis"])
    assert float(paint["amplitude"][0, -1].abs().max()) == 0.0


def test_normal_turn_is_the_largest_angle_to_a_covered_neighbour():
    """A 4 x 4 view whose left half faces +x and right half +y: the two columns at the break turn 90 degrees, the
    others none; an uncovered neighbour does not count, and an uncovered pixel turns 0."""
    from pipelines.evaluation.metrics import normal_turn_deg
    n = torch.zeros(1, 4, 4, 3)
    n[..., :2, 0], n[..., 2:, 1] = 1.0, 1.0
    turn = normal_turn_deg(n.view(1, 16, 3), torch.ones(1, 16), 4).view(4, 4)
    torch.testing.assert_close(turn, torch.tensor([[0.0, 90.0, 90.0, 0.0]]).expand(4, 4))
    covered = torch.ones(4, 4)
    covered[:, 2] = 0.0  # the right half's break column uncovered: the left half's break sees no turn
    turn = normal_turn_deg(n.view(1, 16, 3), covered.view(1, 16), 4).view(4, 4)
    torch.testing.assert_close(turn, torch.zeros(4, 4))


def test_normal_errors_are_zero_on_the_true_surface_and_counted_where_it_mirrors_the_sun():
    """The same sphere as prediction and GT: no error anywhere; the sun straight back at the camera is mirrored by
    the pixels facing it, a sun straight behind the sphere by none (NaN); a sphere squashed in depth is wrong
    where it is seen."""
    from pipelines.evaluation.metrics import normal_errors
    sphere, cams = icosphere(3, radius=10.0), Cameras.orbit(40.0, 25.0, 30.0, 40.0, 24)
    rgba = torch.ones(1, 24, 24, 4)
    _, to_camera, _, weight = pixel_samples(sphere, cams, rgba[..., :3], rgba[..., 3])
    toward = torch.nn.functional.normalize((to_camera[0] * weight[0, :, None]).sum(0), dim=0)[None]
    err = normal_errors(sphere, [sphere], cams, rgba, toward)
    assert err.shape == (1, 3) and float(err[0, 0]) < 0.5 and float(err[0, 1]) < 0.5
    # facing the camera, a sphere of radius 10 seen from 40 at 40 degrees over 24 pixels turns ~5.2 degrees a pixel
    pixel = 2 * 30.0 * math.tan(math.radians(20.0)) / 24  # the pixel's size at the sphere's front (distance 30)
    assert abs(float(err[0, 2]) - math.degrees(pixel / 10.0)) < 1.0
    assert torch.isnan(normal_errors(sphere, [sphere], cams, rgba, -toward)[0, 1:]).all()
    squashed = Meshes(sphere.verts * torch.tensor([1.0, 1.0, 0.5]), sphere.faces, sphere.uvs, sphere.face_uvs)
    assert float(normal_errors(squashed, [sphere], cams, rgba, toward)[0, 0]) > 5.0
    # normals given per pixel are measured instead of the surface's, on its pixels: the GT's own, none off
    true_normals = pixel_samples(sphere, cams, rgba[..., :3], rgba[..., 3])[0].view(1, 24, 24, 3)
    assert float(normal_errors(squashed, [sphere], cams, rgba, toward, true_normals)[0, 0]) < 0.5


def test_consensus_directions_add_each_views_sun_pixels_to_the_next_view_and_to_every_view_of_its_sample():
    from pipelines.diagnose_light import consensus_directions
    x, y, z = torch.eye(3)
    sums = torch.stack([2 * x, 2 * y, torch.zeros(3), 3 * z, z])  # samples 0, 0, 0, 1, 1; view 2 shows no sun
    d = consensus_directions(sums, torch.tensor([0, 0, 0, 1, 1]))
    s = 2 ** -0.5
    assert torch.allclose(d["one view"], torch.stack([x, y, torch.zeros(3), z, z]))
    assert torch.allclose(d["two views"], torch.stack([s * (x + y), y, x, z, z]))  # view 2's next is view 0
    assert torch.allclose(d["all views"], torch.stack([s * (x + y)] * 3 + [z, z]))


def _two_views_of_a_sun_on_a_sphere(sun: torch.Tensor, res: int = 32):
    sphere = icosphere(3, radius=10.0)
    a, b = Cameras.orbit(40.0, 25.0, 30.0, 40.0, res), Cameras.orbit(40.0, 35.0, 100.0, 40.0, res)
    cams = Cameras(torch.cat([a.world_to_camera, b.world_to_camera]), torch.cat([a.fov, b.fov]), res)
    images = torch.ones(2, res, res, 4)
    normals, to_camera, _, weight = pixel_samples(sphere.expand(2), cams, images[..., :3], images[..., 3])
    cos = (mirror_directions(normals, to_camera) * sun).sum(-1)
    bright = (cos > torch.cos(torch.deg2rad(torch.tensor(6.0)))) & (weight > 0.5)
    images[..., :3] = torch.where(bright.view(2, res, res, 1), 100.0, 1.0)
    return sphere, cams, images, bright


def test_sun_pixels_are_the_reflection_in_views_that_show_one_and_none_under_a_bright_sky():
    from pipelines.diagnose_light import sun_pixels
    sun = torch.nn.functional.normalize(torch.tensor([0.3, 0.2, 1.0]), dim=0)
    sphere, cams, images, bright = _two_views_of_a_sun_on_a_sphere(sun)
    _, _, radiance, weight = pixel_samples(sphere.expand(2), cams, images[..., :3], images[..., 3])
    w = sun_pixels(radiance, weight)
    assert bright.sum(1).min() > 0 and torch.equal(w > 0, bright)
    assert float(sun_pixels(torch.ones_like(radiance), weight).sum()) == 0  # a uniform sky has no sun
    from pipelines.diagnose_light import consensus_directions, sun_pixel_sums
    from pipelines.evaluation.metrics import angle_deg
    found = consensus_directions(sun_pixel_sums(sphere, cams, images), torch.tensor([0, 0]))
    for d in found.values():  # through the true surface every view, and both together, mirror the sun
        assert float(angle_deg(d, sun.expand_as(d)).max()) < 3.0


def test_each_views_sun_axis_is_turned_to_the_world_by_its_own_frame():
    """diagnose_light's sun-lobe row: a sun axis in each view's probe frame back in the world frame, per view."""
    cams = Cameras.orbit(60.0, 27.0, torch.tensor([0.0, 90.0, 200.0]), 30.0, 16)
    sun = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8]), dim=0)
    in_probe = (camera_to_probe() @ cams.world_to_camera[:, :3, :3] @ sun).squeeze(-1)
    assert not torch.allclose(in_probe[0], in_probe[1])  # the views see it in different directions
    torch.testing.assert_close(probe_to_world(in_probe, cams.world_to_camera), sun.expand(3, 3))


def test_the_facing_sun_cue_leaves_out_the_grazing_pixels_and_the_sun_follows_it():
    """The facing cue: on a sphere the pixels that graze the camera (n.v < 0.3) mirror the directions within ~35
    degrees of straight behind it; the facing cue covers none of those, the full cue does; and the head's sun is
    read off the cue it is given (its brightest cell), the sky lobes off the full grid."""
    from pipelines.model.light_probe import FACING_MIN, facing_mirror_cue, probe_grid

    sphere, cams = icosphere(3, radius=10.0), Cameras.orbit(40.0, 25.0, 30.0, 40.0, 48)
    rgba = torch.ones(1, 48, 48, 4)
    normals, to_camera, seen, weight = pixel_samples(sphere, cams, rgba[..., :3], rgba[..., 3])
    h, w = 16, 32
    full = probe_grid(normals, to_camera, seen, weight, cams.world_to_camera, h, w)
    facing = facing_mirror_cue(normals, to_camera, seen, weight, cams.world_to_camera, h, w)
    behind = (equirect_directions(h, w).reshape(-1, 3) @ torch.tensor([1.0, 0.0, 0.0])) > math.cos(math.radians(15))
    assert FACING_MIN == 0.3 and facing.shape == (1, 4, h, w)
    assert float(full[0, 3].flatten()[behind].min()) > 0 and float(facing[0, 3].flatten()[behind].max()) == 0.0
    torch.testing.assert_close(facing[0, 3].flatten()[~behind].gt(0).float().mean(), torch.tensor(1.0), atol=0.25, rtol=0)
    grid = torch.cat([_probe_grid_with({(3, 8): 200.0}), torch.zeros(1, 4, h, w)], 1)
    head = ProbeLightHead("sg", 8, h, w, 3000.0, 12.0, code=4)
    dirs = equirect_directions(h, w).reshape(-1, 3)
    with torch.no_grad():
        own = head(grid, torch.zeros(1, 4), torch.eye(3)[None], torch.ones(1))
        told = head(grid, torch.zeros(1, 4), torch.eye(3)[None], torch.ones(1), _probe_grid_with({(5, 20): 200.0}))
    assert float(own["axis"][0, -1] @ dirs[3 * w + 8]) > 0.95 and float(told["axis"][0, -1] @ dirs[5 * w + 20]) > 0.95
    torch.testing.assert_close(told["amplitude"][:, :-2], own["amplitude"][:, :-2])


def test_the_learnt_shift_places_the_sun_on_paint_and_the_cue_on_metal():
    """The learnt shift of the sun's logits is scaled by 1 - metallic: a metal's sun is where the cue is brightest
    (a metal's cue is the light's picture), paint's follows the shift (its cue adds the paint's diffuse shading)."""
    h, w = 16, 32
    dirs = equirect_directions(h, w).reshape(-1, 3)
    grid = torch.cat([_probe_grid_with({(3, 8): 200.0}), torch.zeros(1, 4, h, w)], 1)
    shift = torch.zeros(1, 4, h, w)
    shift[0, 3, 5, 20] = 60.0  # the last layer's output: a large shift of the sun's logits toward cell (5, 20)
    head = ProbeLightHead("sg", 8, h, w, 3000.0, 12.0, code=4)
    conv = head._conv
    head._conv = lambda layer, x: conv(layer, x) + (shift if layer is head.out else 0)
    with torch.no_grad():
        paint, metal = (head(grid, torch.zeros(1, 4), torch.eye(3)[None], torch.tensor([m])) for m in (0.0, 1.0))
    assert float(paint["axis"][0, -1] @ dirs[5 * w + 20]) > 0.95
    assert float(metal["axis"][0, -1] @ dirs[3 * w + 8]) > 0.95
    torch.testing.assert_close(paint["amplitude"][:, :-2], metal["amplitude"][:, :-2])  # the sky is the same


def test_an_sg_lobe_on_the_grid_keeps_its_power_and_its_place():
    """sg_on_grid (MC's probe sun on its grid): the grid integrates to the lobe's power however sharp it is (a lobe
    narrower than a cell included), is brightest at the cell nearest the axis, and is the lobe itself where the
    cells resolve it."""
    h, w = 64, 128
    solid = equirect_solid_angles(h, w).view(1, 1, h, 1)
    cells = equirect_directions(h, w)
    dirs = cells.reshape(-1, 3)
    axes = torch.nn.functional.normalize(torch.tensor(
        [[0.3, 0.2, 0.9], [0.0, 0.0, 1.0], [-1.0, 1e-4, 0.1], [0.5, -0.5, -0.7]]), dim=-1)
    amplitude = torch.tensor([[2.0, 1.0, 0.5]]).expand(4, 3)
    for lam in (1.0, 30.0, 3000.0):
        sharpness = torch.full((4, 1), lam)
        grid = sg_on_grid(axes, sharpness, amplitude, cells.permute(2, 0, 1)[None])
        torch.testing.assert_close((grid * solid).sum((2, 3)), sg_integral(sharpness[:, 0], amplitude), rtol=1e-4, atol=0)
        assert torch.equal(grid.mean(1).flatten(1).argmax(-1), (axes @ dirs.T).argmax(-1))
    broad = sg_on_grid(axes, torch.full((4, 1), 5.0), amplitude, cells.permute(2, 0, 1)[None])
    exact = SGLight(axes.unsqueeze(1), torch.full((4, 1), 5.0), amplitude.unsqueeze(1)).eval(dirs.expand(4, -1, -1))
    torch.testing.assert_close(broad.flatten(2).mT, exact, rtol=2e-3, atol=0)


def test_mcs_probe_sun_is_the_sg_light_on_the_grid():
    """kind "env": MC's grid is the SG head's light on a grid four times finer than the probe's, its sky lobes and
    its sun's lobe (no floor) evaluated at the cells, the sun above the horizon where the cue is brightest, and the
    sky and the sun's lobe apart."""
    h, w = 16, 32
    solid = equirect_solid_angles(4 * h, 4 * w).view(1, 1, 4 * h, 1)
    dirs, coarse = equirect_directions(4 * h, 4 * w).reshape(-1, 3), equirect_directions(h, w).reshape(-1, 3)
    grid = torch.cat([_probe_grid_with({(3, 8): 200.0, (12, 20): 400.0}), torch.zeros(1, 4, h, w)], 1)  # one below
    torch.manual_seed(0)
    head = ProbeLightHead("env", 8, h, w, 3000.0, 12.0, code=4)
    torch.manual_seed(0)
    sg = ProbeLightHead("sg", 8, h, w, 3000.0, 12.0, code=4)
    args = (grid, torch.zeros(1, 4), torch.eye(3)[None], torch.zeros(1))
    with torch.no_grad():
        out, lobes = head(*args), sg(*args)
    assert out["image"].shape == (1, 4 * h, 4 * w, 3)
    torch.testing.assert_close(out["sun_log_p"], lobes["sun_log_p"])
    sky_lobes = SGLight(lobes["axis"][:, :-2], lobes["sharpness"][:, :-2], lobes["amplitude"][:, :-2])
    torch.testing.assert_close(out["sky"].reshape(1, -1, 3), sky_lobes.eval(coarse[None]))
    sun = (out["image"].reshape(1, -1, 3) - sky_lobes.eval(dirs[None])).mT.reshape(1, 3, 4 * h, 4 * w)
    power = sg_integral(lobes["sharpness"][:, -2], lobes["amplitude"][:, -2])  # the SG head's own sun lobe
    torch.testing.assert_close((sun * solid).sum((2, 3)), power, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(out["sun_axis"], lobes["axis"][:, -1])
    torch.testing.assert_close(out["sun_amplitude"], lobes["amplitude"][:, -2])
    assert int(sun.mean(1).flatten().argmax()) == int((dirs @ lobes["axis"][0, -1]).argmax())
    assert float(lobes["axis"][0, -1] @ coarse[3 * w + 8]) > 0.95  # above the horizon, not the brighter cell below


def test_the_table_by_elevation_bands_each_view_by_how_high_its_light_stands():
    from pipelines.diagnose_light import ELEVATION_BANDS, by_elevation

    errors = {"run": torch.tensor([10.0, 30.0, 20.0, 50.0, 5.0]), "consensus": torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0])}
    lifts = {"run": torch.tensor([-1.0, -2.0, 3.0, -10.0, 0.0])}  # the consensus rows have no per-view lift
    header, rows = by_elevation(errors, lifts, torch.tensor([10.0, 25.0, 40.0, 60.0, 15.0]))
    assert len(header) == 1 + len(ELEVATION_BANDS) and header[1] == "light 0–20° high, 2 views"
    # medians of an even count are the mean of the middle two: (10 + 5) / 2, (-1 + 0) / 2, (1 + 5) / 2
    assert rows[0] == ["run", "7.5° (100 %, -0.5°)", "30.0° (0 %, -2.0°)", "20.0° (100 %, +3.0°)", "50.0° (0 %, -10.0°)"]
    assert rows[1] == ["consensus", "3.0° (100 %)", "2.0° (100 %)", "3.0° (100 %)", "4.0° (100 %)"]
    header, rows = by_elevation(errors, lifts, torch.tensor([10.0, 12.0, 14.0, 16.0, 18.0]))  # every light low
    assert header[2] == "light 20–35° high, 0 views" and rows[0][2:] == ["", "", ""]
