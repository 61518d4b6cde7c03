"""Metrics on cases with answers known by hand."""
import math

import numpy as np
import pytest
import torch
import trimesh

from pipelines.evaluation import metrics


def test_identical_inputs_score_zero():
    img = torch.rand(2, 8, 8, 3)
    mask = (torch.rand(2, 8, 8) > 0.3).float()
    assert torch.all(metrics.image_l1_foreground(img, img, mask) == 0)
    assert torch.all(metrics.image_l1_whole(img, img) == 0)
    assert torch.all(metrics.iou_loss(mask, mask) == 0)
    assert torch.allclose(metrics.ncc_loss(img, img), torch.zeros(2), atol=1e-6)


def test_ncc_ignores_a_global_scale_but_not_a_change_of_pattern():
    env = torch.rand(1, 16, 32, 3)
    assert metrics.ncc_loss(env, 3.7 * env).abs().item() < 1e-6
    other = torch.zeros_like(env)
    other[..., :16, :] = 1.0  # orthogonal to an image that is zero there
    masked = env.clone()
    masked[..., :16, :] = 0
    assert metrics.ncc_loss(masked, other).item() == pytest.approx(1.0)


def test_shifted_square_silhouette_iou_by_hand():
    gt = torch.zeros(1, 20, 20)
    gt[0, 5:15, 5:15] = 1  # 10 x 10
    pred = torch.zeros(1, 20, 20)
    pred[0, 5:15, 8:18] = 1  # shifted by 3 columns: overlap 10 x 7 = 70, union 130
    assert metrics.iou_loss(pred, gt).item() == pytest.approx(1 - 70 / 130)


def test_image_l1_counts_only_the_foreground():
    gt, pred = torch.zeros(1, 4, 4, 3), torch.zeros(1, 4, 4, 3)
    mask = torch.zeros(1, 4, 4)
    mask[0, :2] = 1
    pred[0, :2] = 0.25  # error 0.25 on the foreground
    pred[0, 2:] = 9.0  # background: ignored
    assert metrics.image_l1_foreground(pred, gt, mask).item() == pytest.approx(0.25)


def test_whole_image_l1_by_hand_on_a_2x2_image():
    """Every pixel and channel counts, the background too, as one mean (not DIB-R's x3 channel sum)."""
    gt = torch.zeros(1, 2, 2, 3)
    gt[0, 0, 0] = torch.tensor([0.2, 0.4, 0.6])  # the object: one pixel; the rest is black background
    mask = torch.zeros(1, 2, 2)
    mask[0, 0, 0] = 1
    pred = gt.clone()
    pred[0, 0, 0] = torch.tensor([0.5, 0.4, 0.0])  # |diff| 0.3 + 0 + 0.6 on the object
    pred[0, 1, 1] = torch.tensor([0.3, 0.3, 0.3])  # a spill onto the background: 0.9
    assert metrics.image_l1_whole(pred, gt).item() == pytest.approx((0.9 + 0.9) / 12)
    assert metrics.image_l1_foreground(pred, gt, mask).item() == pytest.approx(0.9 / 3)
    # per image of a batch
    both = metrics.image_l1_whole(torch.cat([pred, gt]), torch.cat([gt, gt]))
    assert both.tolist() == pytest.approx([0.15, 0.0])


def test_ldr_envmap_divides_by_the_mean_and_clips_at_one():
    env = torch.tensor([0.5, 1.0, 1.5, 5.0]).view(1, 1, 4, 1).expand(1, 1, 4, 3)  # grey, mean 2
    assert metrics.ldr_envmap(env)[0, 0, :, 0].tolist() == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert torch.equal(metrics.ldr_envmap(7.0 * env), metrics.ldr_envmap(env))  # any exposure: the same map
    assert torch.equal(metrics.ldr_envmap(torch.full((1, 2, 4, 3), 3.0)), torch.ones(1, 2, 4, 3))  # a constant: 1
    ring = torch.tensor([-2.0, 1.0, 4.0, 1.0]).view(1, 1, 4, 1).expand(1, 1, 4, 3)  # negative (SH) counts as 0
    assert metrics.ldr_envmap(ring)[0, 0, :, 0].tolist() == pytest.approx([0.0, 2 / 3, 1.0, 2 / 3])


def test_eq9_on_hdr_and_ldr_maps_by_hand():
    """A sun of 100 in three sky texels of 1, against a constant map: on HDR maps the sun holds the NCC, on LDR
    maps (mean 25.75, the sun clipped at 1) the sky does."""
    gt = torch.tensor([1.0, 1.0, 1.0, 100.0]).view(1, 1, 4, 1).expand(1, 1, 4, 3)
    losses = metrics.envmap_losses(torch.ones_like(gt), gt)
    assert losses["light_hdr"].item() == pytest.approx(1 - 103 / (2 * math.sqrt(10003)), abs=1e-6)
    sky = 1 / 25.75
    assert losses["light_ldr"].item() == pytest.approx(1 - (3 * sky + 1) / (2 * math.sqrt(3 * sky ** 2 + 1)), abs=1e-6)
    same = metrics.envmap_losses(3 * gt, gt)
    assert same["light_hdr"].abs().item() < 1e-6 and same["light_ldr"].abs().item() < 1e-6


def test_chamfer_zero_for_the_same_mesh_and_known_for_a_shift():
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    assert metrics.chamfer_distance(v, f, v, f, samples=4000) < 2e-3
    # a unit sphere vs a sphere of radius 1.1: every point is 0.1 away, in units of the GT diagonal
    s = trimesh.creation.icosphere(4)
    gt_v, sf = np.asarray(s.vertices), np.asarray(s.faces)
    diag = np.linalg.norm(gt_v.max(0) - gt_v.min(0))
    d = metrics.chamfer_distance(1.1 * gt_v, sf, gt_v, sf, samples=4000)
    assert d == pytest.approx((0.1 / diag) ** 2, rel=0.1)
    with pytest.raises(ValueError, match="degenerate"):
        metrics.chamfer_distance(v, f, np.zeros((3, 3)), np.array([[0, 1, 2]]))


# ----------------------------------------------------------------------------- light metrics (probe spheres)

def _sun_map(direction, h=32, sun=200.0, sky=(0.3, 0.4, 0.6)):
    """A sky of one colour with a small sun disc around ``direction`` (world frame)."""
    from dibrpp.conventions import equirect_directions

    d = equirect_directions(h, 2 * h)
    cos = (d * torch.tensor(direction, dtype=torch.float32)).sum(-1)
    img = torch.tensor(sky).expand(h, 2 * h, 3).clone()
    img[cos > math.cos(math.radians(8))] = sun
    return img[None]


def test_a_light_scores_zero_against_itself_and_ignores_its_intensity():
    from dibrpp.lights import EnvMap

    env = _sun_map([0.6, 0.0, 0.8])
    w2c = torch.eye(4)[None]
    same = metrics.light_metrics(EnvMap(env), EnvMap(env), metrics.ProbeScene(w2c))
    brighter = metrics.light_metrics(EnvMap(5.0 * env), EnvMap(env), metrics.ProbeScene(w2c))
    for k in ("probe_diffuse", "probe_metal", "probe_mirror", "colour_deg", "direction_deg"):
        tol = 0.5 if k == "direction_deg" else 1e-3  # degrees: acos near 1 in float32
        assert same[k].abs().max() < tol, k
        assert brighter[k].abs().max() < tol, k


def test_a_constant_light_scores_worse_than_the_truth_and_a_tint_shows_in_the_colour_angle():
    from dibrpp.lights import EnvMap

    env = _sun_map([0.6, 0.0, 0.8])
    w2c = torch.eye(4)[None]
    const = metrics.light_metrics(EnvMap(torch.ones(1, 8, 16, 3)), EnvMap(env), metrics.ProbeScene(w2c))
    assert const["probe_metal"] > 0.3 and const["probe_diffuse"] > 0.1
    tint = torch.tensor([1.0, 1.0, 0.5])
    tinted = metrics.light_metrics(EnvMap(env * tint), EnvMap(env), metrics.ProbeScene(w2c))
    want = math.degrees(math.acos(float(torch.nn.functional.cosine_similarity(
        metrics.mean_colour(metrics.ProbeScene(w2c).render(EnvMap(env))["diffuse"]),
        metrics.mean_colour(metrics.ProbeScene(w2c).render(EnvMap(env * tint))["diffuse"])))))
    assert tinted["colour_deg"].item() == pytest.approx(want, abs=0.05) and want > 5


def test_every_light_metric_has_its_constant_map_reference_under_the_same_definition():
    from dibrpp.lights import EnvMap

    sun = [0.6, 0.0, 0.8]
    env = torch.cat([_sun_map(sun), torch.ones(1, 32, 64, 3)])  # a sunny sky; a flat grey map (no dominant light)
    scene = metrics.ProbeScene(torch.eye(4)[None].expand(2, 4, 4))
    ref = metrics.constant_light_references(env, scene)
    names = ("light_hdr", "light_ldr", "probe_diffuse", "probe_metal", "probe_mirror", "colour_deg", "direction_deg")
    assert sorted(ref) == sorted(f"{k}_constant" for k in names)
    constant = torch.ones(2, 8, 16, 3)
    want = {**metrics.envmap_losses(torch.ones_like(env), env), **metrics.light_metrics(EnvMap(constant), EnvMap(env), scene)}
    for k in names[:-1]:  # what a constant prediction scores, metric by metric
        assert torch.allclose(ref[f"{k}_constant"], want[k], atol=1e-6, equal_nan=True), k
    # eq. 9 of a constant against a constant map is 0 on both; on the sky the LDR map scores it another way
    assert ref["light_hdr_constant"][1].abs() < 1e-6 and ref["light_ldr_constant"][1].abs() < 1e-6
    assert ref["light_hdr_constant"][0] > 0 and ref["light_ldr_constant"][0] != ref["light_hdr_constant"][0]
    # its direction: "straight above" against the sun 36.9 degrees from the zenith; none where there is no sun
    assert ref["direction_deg_constant"][0].item() == pytest.approx(math.degrees(math.acos(0.8)), abs=8.0)
    assert torch.isnan(ref["direction_deg_constant"][1])


def test_a_rotated_sun_gives_the_rotation_angle():
    from dibrpp.lights import EnvMap

    a = [math.cos(math.radians(40)), 0.0, math.sin(math.radians(40))]
    for turn in (30.0, 90.0, 150.0):
        t = math.radians(turn)  # the sun turned about +Z at the same elevation
        b = [a[0] * math.cos(t), a[0] * math.sin(t), a[2]]
        want = math.degrees(math.acos(sum(x * y for x, y in zip(a, b))))
        got = metrics.light_metrics(EnvMap(_sun_map(b)), EnvMap(_sun_map(a)), metrics.ProbeScene(torch.eye(4)[None]))["direction_deg"]
        assert got.item() == pytest.approx(want, abs=8.0)  # one cell of the 16 x 32 grid is 11 degrees


def test_direction_is_undefined_without_a_dominant_light():
    d, frac = metrics.dominant_direction(torch.ones(1, 16, 32, 3))
    assert frac.item() < metrics.SUN_FRACTION
    from dibrpp.lights import EnvMap

    flat = EnvMap(torch.ones(1, 16, 32, 3))
    assert torch.isnan(metrics.light_metrics(flat, flat, metrics.ProbeScene(torch.eye(4)[None]))["direction_deg"]).all()


def test_probes_in_a_white_furnace():
    """Under a constant unit light the diffuse probe shows its albedo, the mirror 1, the rough metal at most its albedo."""
    from dibrpp.lights import EnvMap

    r = metrics.ProbeScene(torch.eye(4)[None]).render(EnvMap(torch.ones(1, 16, 32, 3)))
    inside = r["diffuse"][0, ..., 3] > 0
    assert torch.allclose(r["diffuse"][0][inside][:, :3], torch.tensor(0.8), atol=0.01)
    assert torch.allclose(r["mirror"][0][inside][:, :3], torch.tensor(1.0), atol=1e-5)
    metal = r["metal"][0][inside][:, :3]
    assert metal.max() <= 0.9 + 0.01 and metal.mean() > 0.75


def test_normal_error_by_hand():
    """Normals turned by 30 degrees on half of the shared pixels, equal on the rest; pixels only one side covers
    do not count; a view without shared pixels has no error."""
    gt = torch.zeros(2, 4, 4, 3)
    gt[..., 2] = 1.0
    pred = gt.clone()
    turned = torch.tensor([math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])
    pred[0, :, :3] = turned  # 12 of 16 pixels turned, but the last column is covered by the prediction only
    alpha_gt = torch.ones(2, 4, 4)
    alpha_gt[0, :, 3] = 0.0
    alpha_gt[1] = 0.0
    median, within = metrics.normal_error_deg(pred * 2.0, torch.ones(2, 4, 4), gt, alpha_gt)
    assert median[0].item() == pytest.approx(30.0, abs=1e-3) and within[0].item() == 0.0
    assert torch.isnan(median[1]) and torch.isnan(within[1])
    pred[0, :2, :3] = gt[0, :2, :3]  # now 6 of the 12 shared pixels agree
    median, within = metrics.normal_error_deg(pred, torch.ones(2, 4, 4), gt, alpha_gt)
    assert within[0].item() == pytest.approx(0.5)


def test_direction_summary_resamples_whole_samples():
    """The 95 % intervals of the sunny views' median and shares resample samples (an object under a map), not views."""
    direction_summary = metrics.direction_summary
    # ten samples of eight views, each sample all right (10 degrees) or all wrong (60): half within 25
    errors = np.repeat([10.0, 60.0] * 5, 8)
    samples = np.repeat(np.arange(10), 8)
    s = direction_summary(errors, samples)
    assert s["within_25"] == 0.5 and s["within_45"] == 0.5 and s["median"] == 35.0
    lo, hi = s["within_25_ci"]
    assert 0.15 <= lo < 0.5 < hi <= 0.85  # ten draws: about +-0.3, where 80 independent views would give +-0.11
    assert direction_summary(errors, samples) == s  # seeded
    # the same errors as 80 samples of one view each: a narrower interval
    lo80, hi80 = direction_summary(errors, np.arange(80))["within_25_ci"]
    assert hi80 - lo80 < 0.6 * (hi - lo)
    # every sample the same: no spread
    assert direction_summary(np.full(16, 5.0), np.repeat([0, 1], 8))["within_25_ci"] == [1.0, 1.0]
    empty = direction_summary(np.array([]), np.array([]))
    assert math.isnan(empty["median"]) and math.isnan(empty["within_25_ci"][0])


def test_the_median_of_an_even_count_is_the_mean_of_the_middle_two_and_nan_is_ignored():
    from pipelines.evaluation.metrics import median, direction_summary

    errors = torch.tensor([34.51, 71.54, float("nan")])
    assert float(median(errors)) == pytest.approx((34.51 + 71.54) / 2)  # torch's median would say 34.51
    assert float(median(torch.tensor([3.0, 1.0, 2.0]))) == 2.0 and median(torch.tensor([])).isnan()
    summary = direction_summary(np.array([34.51, 71.54]), np.array([0, 1]))
    assert summary["median_ci"][0] <= float(median(errors)) <= summary["median_ci"][1]


def test_the_albedo_s_sky_blue_is_its_blue_where_it_faces_up_over_where_it_faces_sideways_beyond_the_gt_s():
    from pipelines.evaluation.albedo_metrics import albedo_sky_blue

    gt = torch.full((1, 2, 2, 3), 0.5)  # a grey albedo
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]).view(1, 2, 2, 3)
    alpha = torch.ones(1, 2, 2)
    pred = gt.clone()
    pred[0, 0, 0] = torch.tensor([0.2, 0.3, 0.5])  # the sky's blue kept on one up-facing pixel
    pred[0, 1, 1] = torch.tensor([0.1, 0.1, 0.8])  # bluer still, but facing down: neither set
    assert float(albedo_sky_blue(pred, gt, normals, alpha)[0]) == pytest.approx((0.5 - 1 / 3) / 2)
    pred[0, 1, 0] = torch.tensor([0.5, 0.3, 0.2])  # the ground's brown kept on the side: counts too
    assert float(albedo_sky_blue(pred, gt, normals, alpha)[0]) == pytest.approx((0.5 - 1 / 3) / 2 + (1 / 3 - 0.2))
    tinted = gt * torch.tensor([0.8, 0.9, 1.2])  # the whole albedo bluer (a tint the light leaves to it): no sky
    assert float(albedo_sky_blue(tinted, gt, normals, alpha)[0]) == pytest.approx(0.0, abs=1e-6)
    two_tone = gt.clone()
    two_tone[0, 0] = torch.tensor([0.1, 0.2, 0.7])  # the GT's own blue roof, predicted as it is: no sky
    assert float(albedo_sky_blue(two_tone, two_tone, normals, alpha)[0]) == pytest.approx(0.0)
    assert albedo_sky_blue(gt, gt, -normals.abs(), alpha)[0].isnan()  # nothing faces up


def test_the_albedo_s_scale_is_read_where_both_silhouettes_cover():
    from pipelines.evaluation.albedo_metrics import albedo_scale

    gt = torch.full((2, 2, 2, 3), 0.25)
    pred = 2 * gt
    pred[0, 1, 1] = 9.0  # outside the covered pixels: not counted
    covered = torch.tensor([[[True, True], [True, False]], [[False, False], [False, False]]])
    scale = albedo_scale(pred, gt, covered)
    assert float(scale[0]) == pytest.approx(2.0) and scale[1].isnan()  # nothing covered: NaN


def test_the_light_s_scale_weighs_texels_by_their_solid_angle():
    from pipelines.evaluation.albedo_metrics import light_scale

    gt = torch.ones(1, 8, 16, 3)
    assert float(light_scale(3 * gt, gt)[0]) == pytest.approx(3.0)
    pole, equator = gt.clone(), gt.clone()
    pole[:, 0] += 1.0  # one texel row at the pole: a sliver of the sphere
    equator[:, 3] += 1.0  # one row at the equator: the widest
    assert 1.0 < float(light_scale(pole, gt)[0]) < float(light_scale(equator, gt)[0]) < 2.0
    # the row between polar angles 3 pi / 8 and pi / 2 holds (cos 3 pi / 8 - cos pi / 2) / 2 of the sphere
    band = (math.cos(3 * math.pi / 8) - math.cos(4 * math.pi / 8)) / 2
    assert float(light_scale(equator, gt)[0]) == pytest.approx(1 + band, rel=1e-5)
