"""Where a run's light loses the sun: ``python -m pipelines.diagnose_light --run runs/metallic/sg-seed0``.

On the test views with a dominant light (or those of another dataset: ``--dataset DIR --split all``), the direction
error (median, share within 25 and 45 degrees) of the sources below, over all those views, by how high their light
stands (how high the sun stands decides where a mirror-like car shows it) and on each env map apart (where there
are few):

- the run's light, and (probe head) its sun lobe alone, with the sun's share of the light's power; each with its
  elevation error (signed: below the GT sun where negative); for a
  run that reads the input's full range, also its light from the clipped input (what an 8-bit picture gives);
- the mirror cue itself, no learning: the input scattered by the mirror directions of a surface's normals into
  a 32 x 64 world-frame map, whose dominant direction is taken (``metrics.dominant_direction``), read through
  the predicted surface and through the GT mesh, from the input clipped at 1 (as an 8-bit picture shows it)
  and at its full dynamic range;
- (probe head) the run's own head fed the cue read through the GT mesh instead of the predicted one;
- the predicted normals' error on the pixels both surfaces cover, and on those where the GT surface mirrors
  the sun (its mirror direction within 10 degrees of it): how wrong the normals are where the sun shows; and
  the same for each object's shape averaged over the views read (the predicted vertices' mean): whether the
  error is each view's own (it would average out) or the object's (entry 19: the object's);
- (SG light) the run's light with a sun added where the cue through its own surface is brightest above the
  horizon, as bright as the cue shows it (``light_probe.cue_sun_power``): what a live sun read off the probe
  would give, with the rough-metal probe's si-RMSE of both lights;
- the pixels that show the sun (the brightest, in views where they stand far above the rest), their mirror
  directions through the predicted surface and through the GT mesh averaged over one view, over it and the
  next view of the same object under the same map, and over every view of it: how much better several views
  place the sun than one (its highlight falls on different parts of the surface in each).

Each row is a limit the light head works within; docs/experiments.md (entries 12, 13, 16, 18 and 19) reads them.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset, collate
from dibrpp.cli_args import Parser, positive_int
from dibrpp.conventions import LUMINANCE_WEIGHTS, equirect_directions, equirect_solid_angles
from dibrpp.formatting import markdown_table
from dibrpp.io import DataError
from dibrpp.lights import EnvMap, SGLight
from dibrpp.sg import sg_integral

from .evaluation import metrics
from .model.light_probe import cue_sun_power, mirror_directions, pixel_samples, scatter_to_grid, world_to_probe
from .model.prediction import LIGHT_KINDS, white_balance
from .model.model_input import clip_input, encoder_input, input_radiance
from .scoring import strided_views
from .training.runs import check_image_size, load_run, run_folder

SUN_SHARPNESS = 300.0  # the added sun's lobe (~3 degrees): the probe metrics average the light over 7.5-degree cells


def mirror_cue(meshes, cameras, radiance, alpha, above_horizon: bool = False) -> torch.Tensor:
    """(B, 4, 32, 64) the mirror cue of ``meshes`` seen by ``cameras`` on a world-frame grid: radiance and coverage
    (``above_horizon``: only what the surface reflects from above the horizon)."""
    normals, to_camera, seen, weight = pixel_samples(meshes, cameras, radiance, alpha)
    mirror = mirror_directions(normals, to_camera)
    if above_horizon:
        weight = weight * (mirror[..., 2] > 0)
    return torch.cat(scatter_to_grid(mirror, seen, weight, 32, 64), 1)


def cue_peak(cue: torch.Tensor) -> torch.Tensor:
    """(B, 3) dominant direction of a :func:`mirror_cue` grid, over the cells the surface covers."""
    return metrics.dominant_direction((cue[:, :3] * (cue[:, 3:] > 0.05)).permute(0, 2, 3, 1))[0]


def cue_direction(meshes, cameras, radiance, alpha) -> torch.Tensor:
    """(B, 3) dominant direction of the mirror cue of ``meshes`` seen by ``cameras`` in the world frame."""
    return cue_peak(mirror_cue(meshes, cameras, radiance, alpha))


def with_cue_sun(light: SGLight, meshes, cameras, radiance, alpha) -> SGLight:
    """``light`` (world-frame SG) plus a sun where the mirror cue of ``meshes`` is brightest above the horizon,
    with the power the cue shows there above the sky's level."""
    cue = mirror_cue(meshes, cameras, radiance, alpha, above_horizon=True)
    axis = cue_peak(cue)
    cells = equirect_directions(32, 64).reshape(-1, 3)
    power = cue_sun_power(cue, axis, cells, equirect_solid_angles(32, 64).expand(-1, 64).reshape(-1))
    lam = torch.full((len(axis), 1), SUN_SHARPNESS)
    frame = light.world_to_light
    return SGLight(torch.cat([light.axis, (frame @ axis.unsqueeze(-1)).mT], 1), torch.cat([light.sharpness, lam], 1),
                   torch.cat([light.amplitude, (power / sg_integral(lam)).unsqueeze(1)], 1)).in_frame(frame)


def elevation_deg(directions: torch.Tensor) -> torch.Tensor:
    """(B,) elevation above the world's horizon (degrees) of (B, 3) unit directions."""
    return torch.rad2deg(torch.asin(directions[:, 2].clamp(-1, 1)))


def probe_to_world(directions: torch.Tensor, world_to_camera: torch.Tensor) -> torch.Tensor:
    """(B, 3) world-frame directions of (B, 3) directions given in each view's probe frame (world_to_camera (B, 4, 4))."""
    # one (1, 3) row per view: a (B, 3) @ (B, 3, 3) product would pair every view with every frame
    return (directions.unsqueeze(1) @ world_to_probe(world_to_camera.to(directions)))[:, 0]


def head_on_gt_cue(model, images: torch.Tensor, cameras, gt_meshes: list) -> dict:
    """The probe head's SG light when its grid is read through the GT meshes instead of the predicted ones."""
    images = model.visible_input(images)
    code = model.fc(model.backbone(model.stem(images)))
    radiance, alpha = input_radiance(images)
    samples = [pixel_samples(m, cameras[[k]], radiance[k:k + 1], alpha[k:k + 1]) for k, m in enumerate(gt_meshes)]
    light = model.light_from_samples(*(torch.cat(x) for x in zip(*samples)), cameras.world_to_camera, code,
                                     model.material_parameters(code)[2])
    return white_balance(light, "sg") if model.config.light_colour == "white" else light


SUN_PIXEL_SHARE = 0.5  # a pixel shows the sun where its radiance is at least this share of the view's brightest
SUN_VIEW_CONTRAST = 8.0  # a view shows the sun where its brightest pixel is this many times its median one


def sun_pixels(radiance: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """(B, N) weights of the pixels that show a compact light's reflection: luminance above SUN_PIXEL_SHARE of the
    view's brightest covered pixel, by how much, in views whose brightest pixel stands SUN_VIEW_CONTRAST times above
    their median (a sun or a lamp, not a bright sky); radiance (B, N, 3) linear, weight (B, N) coverage."""
    lum = (radiance * radiance.new_tensor(LUMINANCE_WEIGHTS)).sum(-1)
    covered = weight > 0.5
    brightest = torch.where(covered, lum, torch.zeros_like(lum)).amax(1, keepdim=True)
    median = torch.stack([metrics.median(v[m]) if m.any() else v.new_tensor(float("inf")) for v, m in zip(lum, covered)])
    shows_sun = brightest[:, 0] >= SUN_VIEW_CONTRAST * median
    share = torch.relu(lum / brightest.clamp_min(1e-6) - SUN_PIXEL_SHARE)
    return weight * share * shows_sun[:, None]


def sun_pixel_sums(meshes, cameras, rgba: torch.Tensor) -> torch.Tensor:
    """(B, 3) per view, the world-frame mirror directions of the pixels that show the sun (:func:`sun_pixels`)
    through ``meshes``, summed by their weights: normalised, the sun's direction as that view places it; summed
    over views, as they place it together."""
    normals, to_camera, radiance, weight = pixel_samples(meshes, cameras, rgba[..., :3], rgba[..., 3])
    return (mirror_directions(normals, to_camera) * sun_pixels(radiance, weight)[..., None]).sum(1)


def consensus_directions(sums: torch.Tensor, sample: torch.Tensor) -> dict:
    """{'one view', 'two views', 'all views'}: (N, 3) per view, the sun's direction from its own sun pixels' sums
    (N, 3), from them and the next view of its ``sample`` (N,) (cyclic), and from every view of its sample. A
    view that shows no sun has no direction (zero: a miss)."""
    nxt = torch.arange(len(sample))
    for key in sample.unique():
        idx = (sample == key).nonzero()[:, 0]
        nxt[idx] = idx.roll(-1)
    total = torch.zeros(int(sample.max()) + 1, 3).index_add_(0, sample, sums)[sample]
    unit = lambda v: torch.nn.functional.normalize(v, dim=-1, eps=1e-12)  # noqa: E731
    return {"one view": unit(sums), "two views": unit(sums + sums[nxt]), "all views": unit(total)}


def diagnose(run: Path, stride: int = 3, dataset: str | None = None,
             split: str = "test") -> tuple[list[list], list[str], list[list], list[str], list[list]]:
    """(rows over all sunny views of the run's test split (or ``dataset``'s ``split``), the by-map table's header,
    its rows: each source's median error and share within 25 degrees on each sunny env map, whose GT sun elevation
    the header gives; the by-elevation table's header and rows: the same, and the signed elevation error, over the
    views whose GT light stands in each band of ELEVATION_BANDS)."""
    loaded = load_run(run)
    model, config = loaded.model, loaded.config
    probe = model.config.light_head == "probe"
    dataset = dataset or config.dataset
    if split == "all" and Path(dataset).resolve() == Path(config.dataset).resolve():
        raise DataError(f"{run} trained on {dataset}: --split all would count the samples it trained on; use --split test")
    ds = MultiViewDataset(dataset, split=split, views_per_item=1)
    check_image_size(run, model.config.image_size, ds)
    views = strided_views(ds, stride)
    errors, lifts, shares, probes, maps, elevations, normals = {}, {}, [], {}, [], [], []
    sun_sums, samples, suns, sunny_views = {"predicted": [], "GT": []}, [], [], []
    shapes, read_views = {}, []  # each object's predicted vertices, and what its normals are measured on again
    pixel_normals = []  # the probe's own normals' errors, where the model has them
    with torch.no_grad():
        for start in range(0, len(views), 16):
            b = collate([ds[i] for i in views[start:start + 16]])
            rgba, cams, env = b["image"][:, 0], b["cameras"], b["envmap"]
            d_gt, frac = metrics.dominant_direction(env)
            sunny = frac >= metrics.SUN_FRACTION
            maps.append(torch.as_tensor(b["envmap_index"])[sunny])
            elevations.append(elevation_deg(d_gt[sunny]))
            images = encoder_input(rgba)
            pred = model(images, cams)
            gt_meshes = [ds.mesh(o) for o in b["object"].tolist()]
            clipped = input_radiance(clip_input(images))[0]  # as an 8-bit picture shows the view
            light = pred.light(cams.world_to_camera)
            found = {"the run's light": metrics.dominant_direction(light.to_envmap(64, 128).image)[0]}
            if isinstance(light, SGLight):
                sunlit = with_cue_sun(light, pred.meshes(), cams, *input_radiance(model.visible_input(images)))
                found["the run's light + a sun read off the cue (above the horizon)"] = metrics.dominant_direction(
                    sunlit.to_envmap(64, 128).image)[0]
                scene = metrics.ProbeScene(cams.world_to_camera)
                for k, lit in (("the run's light", light), ("with the cue's sun", sunlit)):
                    probes.setdefault(k, []).append(metrics.light_metrics(lit, EnvMap(env), scene)["probe_metal"])
            if model.config.input_range == "full":  # what it places from an 8-bit picture (a PNG given to predict)
                from_png = model(clip_input(images), cams).light(cams.world_to_camera).to_envmap(64, 128).image
                found["the run's light from the clipped input"] = metrics.dominant_direction(from_png)[0]
            normals.append(metrics.normal_errors(pred.meshes(), gt_meshes, cams, rgba, d_gt)[sunny])
            if pred.pixel_normals is not None:  # the normals the probe reads (variant pixel-normals)
                pixel_normals.append(metrics.normal_errors(pred.meshes(), gt_meshes, cams, rgba, d_gt,
                                                           pred.pixel_normals)[sunny])
            for o, v in zip(b["object"].tolist(), pred.verts):
                shapes.setdefault(o, []).append(v)
            read_views.append((b["object"].tolist(), cams, rgba, d_gt, sunny, gt_meshes))
            sun_sums["predicted"].append(sun_pixel_sums(pred.meshes(), cams, rgba))
            sun_sums["GT"].append(torch.cat([sun_pixel_sums(m, cams[[k]], rgba[k:k + 1])
                                             for k, m in enumerate(gt_meshes)]))
            samples.append(torch.as_tensor(b["object"]) * 10_000 + torch.as_tensor(b["envmap_index"]))
            suns.append(d_gt)
            sunny_views.append(sunny)
            for surface in ("predicted", "GT"):
                for name, radiance in (("clipped", clipped), ("full range", rgba[..., :3])):
                    if surface == "predicted":
                        d = cue_direction(pred.meshes(), cams, radiance, rgba[..., 3])
                    else:
                        d = torch.cat([cue_direction(m, cams[[k]], radiance[k:k + 1], rgba[k:k + 1, ..., 3])
                                       for k, m in enumerate(gt_meshes)])
                    found[f"mirror cue, {surface} surface, {name} input"] = d
            if probe and LIGHT_KINDS[config.shading] == "sg":
                p = pred.light_params
                found["the run's sun lobe alone"] = probe_to_world(p["axis"][:, -1], cams.world_to_camera)
                power = sg_integral(p["sharpness"], p["amplitude"]).mean(-1)
                sun = model.light_head.sun_lobes
                shares.append((power[:, -sun:].sum(1) / power.sum(1))[sunny])
                light = head_on_gt_cue(model, images, cams, gt_meshes)
                d = metrics.dominant_direction(pred.with_light(light).light(cams.world_to_camera).to_envmap(64, 128).image)[0]
                found["the run's head fed the cue through the GT mesh"] = d
            for k, d in found.items():
                errors.setdefault(k, []).append(metrics.angle_deg(d, d_gt)[sunny])
                lifts.setdefault(k, []).append((elevation_deg(d) - elevation_deg(d_gt))[sunny])
    _, sample = torch.cat(samples).unique(return_inverse=True)
    sun_dirs, sunny_all = torch.cat(suns), torch.cat(sunny_views)
    for surface, sums in sun_sums.items():  # the sun as one view places it, and as several do together
        for views, d in consensus_directions(torch.cat(sums), sample).items():
            errors[f"sun pixels, {surface} surface, {views} of the sample"] = [metrics.angle_deg(d, sun_dirs)[sunny_all]]
    mean_shape = {o: torch.stack(v).mean(0) for o, v in shapes.items()}
    with torch.no_grad():
        averaged = torch.cat([metrics.normal_errors(model.template().with_verts(torch.stack([mean_shape[o] for o in objs])),
                                                    gt_meshes, cams, rgba, d_gt)[sunny]
                              for objs, cams, rgba, d_gt, sunny, gt_meshes in read_views])
    rows, maps, elevations, normals = [], torch.cat(maps), torch.cat(elevations), torch.cat(normals)
    errors, lifts = {k: torch.cat(v) for k, v in errors.items()}, {k: torch.cat(v) for k, v in lifts.items()}
    normal_rows = ["normals' error (°), all pixels both surfaces cover",
                   f"normals' error (°), the pixels whose GT mirror direction is within {metrics.SUN_PIXEL_DEG:.0f}° of the sun",
                   "the GT normals' turn within a pixel (°) there: what a pixel's misplacement of the surface costs"]
    by_map = [[k] for k in errors] + [[k] for k in normal_rows]
    header = ["sunny views of each test map: median (≤ 25°)"]
    for m in maps.unique().tolist():
        on = maps == m
        header.append(f"map {m}: light {float(metrics.median(elevations[on])):.0f}° high, {int(on.sum())} views")
        for row, v in zip(by_map, errors.values()):
            v = v[on]
            row.append(f"{metrics.median(v):.1f}° ({100 * (v <= 25).float().mean():.0f} %)")
        for row, v in zip(by_map[len(errors):], normals[on].T):
            row.append(f"{metrics.median(v):.1f}° ({int((~v.isnan()).sum())} views)")
    for k, v in errors.items():
        if not len(v):
            views = "views" if split == "all" else f"{split} views"
            raise DataError(f"{run}: none of the {views} of {dataset} has a dominant light (a sun, a lamp) to place; "
                            "give a set lit by suns with --dataset DIR --split all (e.g. make data-metallic-sunny)")
        lift = f"{metrics.median(lifts[k]):+.1f}" if k in lifts else ""  # the consensus rows are not per view
        rows.append([k, f"{metrics.median(v):.1f}", f"{100 * (v <= 25).float().mean():.0f} %",
                     f"{100 * (v <= 45).float().mean():.0f} %", lift])
    for name, v, mean in zip(normal_rows[:2], normals.T, averaged.T):
        rows.append([f"({name}: {float(metrics.median(v)):.1f}, {int((~v.isnan()).sum())} views; each object's shape "
                     f"averaged over its views: {float(metrics.median(mean)):.1f})", "", "", "", ""])
    rows.append([f"({normal_rows[2]}: {float(metrics.median(normals[:, 2])):.1f})", "", "", "", ""])
    if pixel_normals:
        own = torch.cat(pixel_normals)
        rows.append([f"(the probe's pixel normals' error (°): all pixels {float(metrics.median(own[:, 0])):.1f}, the sun's "
                     f"pixels {float(metrics.median(own[:, 1])):.1f})", "", "", "", ""])
    if shares:
        rows.append(["(the sun's median share of the light's power)", f"{float(metrics.median(torch.cat(shares))):.3f}", "", "", ""])
    if probes:
        rows.append([f"(rough-metal probe si-RMSE, all {split} views read: " + ", ".join(
            f"{k} {float(torch.cat(v).mean()):.3f}" for k, v in probes.items()) + ")", "", "", "", ""])
    return rows, header, by_map, *by_elevation(errors, lifts, elevations)


# bands of the GT light's elevation (degrees): how high the sun stands decides where a mirror-like car shows it
ELEVATION_BANDS = ((-90, 20), (20, 35), (35, 50), (50, 90))
MAX_MAP_COLUMNS = 8  # a table by map beyond this many maps is printed as the table by elevation only


def by_elevation(errors: dict, lifts: dict, elevations: torch.Tensor) -> tuple[list[str], list[list]]:
    """The by-elevation table: per source (rows) and band of the GT light's elevation (columns), the median
    direction error, the share within 25 degrees and (per-view sources) the median signed elevation error."""
    header, rows = ["sunny views by their light's elevation: median (≤ 25 %, elevation error)"], [[k] for k in errors]
    for lo, hi in ELEVATION_BANDS:
        on = (elevations >= lo) & (elevations < hi)
        header.append(f"light {max(lo, 0)}–{hi}° high, {int(on.sum())} views")
        for row, (k, v) in zip(rows, errors.items()):
            if not on.any():
                row.append("")
                continue
            lift = f", {metrics.median(lifts[k][on]):+.1f}°" if k in lifts else ""
            row.append(f"{metrics.median(v[on]):.1f}° ({100 * (v[on] <= 25).float().mean():.0f} %{lift})")
    return header, rows


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.diagnose_light", description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, metavar="DIR", help="a run folder")
    ap.add_argument("--view-stride", type=positive_int, default=3, metavar="N",
                    help="every N-th test view of each object, as make eval (default: 3)")
    ap.add_argument("--dataset", metavar="DIR",
                    help="diagnose on this dataset instead of the one the run was trained on (e.g. make "
                         "data-metallic-sunny's, with --split all)")
    ap.add_argument("--split", choices=("test", "train", "all"), default="test",
                    help="the views to diagnose: test, train or all (every sample of a --dataset no run trained on) "
                         "(default: test)")
    args = ap.parse_args(argv)
    if args.split == "all" and not args.dataset:
        ap.error("--split all reads every sample, the training ones included; use it with a --dataset the run did not "
                 "train on")
    try:
        if args.dataset:  # a missing or broken --dataset: said before the run is loaded
            MultiViewDataset(args.dataset, split=args.split, views_per_item=1)
        rows, by_map_header, by_map, elevation_header, by_band = diagnose(
            run_folder(Path(args.run)), args.view_stride, args.dataset, args.split)
    except DataError as e:
        ap.error(str(e))
    print(markdown_table([f"sunny {args.split} views", "direction median (°)", "≤ 25°", "≤ 45°",
                          "elevation error (median, signed °)"], rows))
    print()
    print(markdown_table(elevation_header, by_band))
    print()
    if len(by_map_header) - 1 <= MAX_MAP_COLUMNS:
        print(markdown_table(by_map_header, by_map))
    else:
        print(f"({len(by_map_header) - 1} sunny maps: too many for a table by map; the table by elevation above)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
