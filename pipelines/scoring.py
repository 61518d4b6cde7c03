"""Scoring one trained run on a split of a dataset: every view predicted, re-rendered and measured against the
ground truth (:mod:`pipelines.evaluation.metrics`), means and the direction's intervals, figure rows; what
``pipelines.evaluate`` runs per run. The model predicts and renders on its own device; the metrics are taken on
the CPU."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from datagen.reader import MultiViewDataset, collate
from dibrpp.display import display_image, tonemap_envmap
from dibrpp.lights import EnvMap

from .evaluation import albedo_metrics, metrics
from .evaluation.summary import NOVEL_AZIMUTHS
from .model.model_input import encoder_input
from .training.refine import refine_light
from .training.runs import check_image_size, load_run, make_renderer
from .training.variants import VARIANTS

FAILURE_METRICS = ("image_foreground", "iou", "light_hdr", "texture", "chamfer", "probe_metal")
# a split with fewer samples (objects under a map) gives means that say little: the direction's intervals
# resample whole samples
MIN_SAMPLES = 10
EVAL_SPP, EVAL_VIEW_STRIDE = 64, 3  # make eval's: MC samples of the re-renderings; every 3rd view (every 45 degrees)
FIGURE_ROWS = 4
MEDIAN_METRICS = ("direction_deg", "normal_deg", "specular_level", "albedo_scale", "light_scale")
METRIC_NAMES = {"image_foreground": "image L1 (foreground)", "iou": "2D IoU loss", "light_hdr": "light 1-NCC (HDR)",
                "texture": "tex 1-NCC", "chamfer": "Chamfer", "probe_metal": "rough-metal probe si-RMSE"}


@torch.no_grad()
def predict_views(model, renderer, ds, items: list[dict], figure: bool = False, refine=None) -> tuple[dict, list]:
    """Per-view metrics (name -> (B,) tensor) of a batch of test views and, with ``figure``, one figure
    row per view (input, re-rendering, albedo and light ours vs GT, the rough-metal probe under both lights,
    novel views with the light fixed in the world)."""
    b = collate(items)
    rgba = b["image"][:, 0]
    cams = b["cameras"]
    device = next(model.parameters()).device
    on_device, cams_on_device = rgba.to(device), cams.to(device)
    pred = model(encoder_input(on_device), cams_on_device)
    if refine is not None:  # (steps, renderer): test-time refinement of the light against the input view
        pred, _ = refine_light(pred, cams_on_device, on_device, refine[1], steps=refine[0])
    out = renderer(pred.meshes(), cams_on_device, pred.material(), pred.light(cams_on_device.world_to_camera))
    albedo = renderer.render_albedo(pred.meshes(), cams_on_device, pred.material()).rgb.cpu()
    gt_meshes = [ds.mesh(obj) for obj in b["object"].tolist()]
    normals = renderer.render_normals(pred.meshes(), cams_on_device)
    gt_normals = [renderer.render_normals(gt.to(device), cams_on_device[[k]]) for k, gt in enumerate(gt_meshes)]
    gt_n, gt_alpha = (torch.cat([getattr(g, key) for g in gt_normals]).cpu() for key in ("rgb", "alpha"))
    normal_deg, normal_within = metrics.normal_error_deg(normals.rgb.cpu(), normals.alpha.cpu(), gt_n, gt_alpha)
    pred, out_rgb, out_alpha = pred.to("cpu"), out.rgb.cpu(), out.alpha.cpu()  # the metrics, on the CPU
    light = pred.light(cams.world_to_camera)
    gt_mask, env = rgba[..., 3], b["envmap"]
    pred_env = light.to_envmap(env.shape[1], env.shape[2]).image
    verts = pred.meshes().verts
    chamfer = [metrics.chamfer_distance(verts[k].numpy(), model.faces.cpu().numpy(), gt.verts[0].numpy(),
                                        gt.faces.numpy(), samples=4000) for k, gt in enumerate(gt_meshes)]
    shown_rgb, gt_rgb = display_image(out_rgb), display_image(rgba[..., :3])  # both composited on black
    per_view = {"normal_deg": normal_deg, "normal_within_10deg": normal_within,
                "image_whole": metrics.image_l1_whole(shown_rgb, gt_rgb),
                "image_foreground": metrics.image_l1_foreground(shown_rgb, gt_rgb, gt_mask),
                "iou": metrics.iou_loss(out_alpha, gt_mask),
                **metrics.envmap_losses(pred_env, env),
                "texture": metrics.ncc_loss(albedo, b["albedo"][:, 0]),
                "albedo_sky_blue": albedo_metrics.albedo_sky_blue(albedo, b["albedo"][:, 0], gt_n, gt_alpha),
                "chamfer": torch.tensor(chamfer, dtype=torch.float64),
                **material_values(pred, [ds.material_params(obj) for obj in b["object"].tolist()]),
                "albedo_scale": albedo_metrics.albedo_scale(albedo, b["albedo"][:, 0], (gt_mask > 0.5) & (out_alpha > 0.5)),
                "light_scale": albedo_metrics.light_scale(pred_env, env)}
    gt_light = EnvMap(env)
    probes = metrics.ProbeScene(cams.world_to_camera)
    per_view.update(metrics.light_metrics(light, gt_light, probes))
    per_view.update(metrics.constant_light_references(env, probes))
    rows = []
    if figure:
        novel = [display_image(renderer(pred.meshes(), cams.orbited(a), pred.material(), light).rgb) for a in NOVEL_AZIMUTHS]
        # probes scaled like the metric (best scale against the GT), so what is compared is what is shown
        shown = metrics.ProbeScene(cams.world_to_camera, resolution=64)
        probe, probe_gt = (shown.render(lt)["metal"] for lt in (light, gt_light))
        scale = metrics.si_scale(probe, probe_gt).view(-1, 1, 1, 1)
        exposure = 0.5 / metrics.mean_colour(probe_gt).mean(-1).clamp_min(1e-8).view(-1, 1, 1, 1)
        rows = [[display_image(rgba[k, ..., :3]) * rgba[k, ..., 3:], display_image(out_rgb[k]), display_image(albedo[k]),
                 display_image(b["albedo"][k, 0]), tonemap_envmap(pred_env[k]), tonemap_envmap(env[k]),
                 display_image(exposure[k] * scale[k] * probe[k, ..., :3]), display_image(exposure[k] * probe_gt[k, ..., :3]),
                 *(v[k] for v in novel)]
                for k in range(len(items))]
    return per_view, rows


def material_values(pred, gt: list[dict]) -> dict:
    """Per-view (B,) scalar material: the predicted specular level beside the GT's, and the roughness's absolute
    error (``gt``: each view's object's ``MultiViewDataset.material_params``)."""
    truth = lambda key: torch.tensor([m[key] for m in gt], dtype=torch.float32)  # noqa: E731
    return {"specular_level": pred.specular.flatten().float(), "specular_level_gt": truth("specular"),
            "roughness_error": (pred.roughness.flatten().float() - truth("roughness")).abs()}


def figure_views(ds: MultiViewDataset) -> list[int]:
    """The views a run's figure shows: the first of FIGURE_ROWS samples spread over the split."""
    return list(range(0, len(ds), max(1, len(ds) // FIGURE_ROWS)))[:FIGURE_ROWS]


def strided_views(ds: MultiViewDataset, stride: int) -> list[int]:
    """Every ``stride``-th view of each sample of ``ds`` (make eval's views at stride 3: one every 45 degrees)."""
    return [i for i in range(len(ds)) if (i % ds.num_views) % stride == 0]


def evaluate_run(run: Path, dataset: str | None = None, batch: int = 16, eval_spp: int = 64,
                 view_stride: int = 1, split: str = "test", refine_steps: int = 0,
                 device: str = "cpu") -> tuple[dict, dict]:
    """Mean metrics over the ``split`` views of the run's dataset (or ``dataset``; every ``view_stride``-th
    view of each sample; ``split="train"`` measures the train/test gap; ``refine_steps``: the light refined at
    test time against each input view, :mod:`pipelines.training.refine`; ``device``: where the model predicts and
    renders), and figure rows:
    {"examples": a few different samples, "failures": the worst view by each metric, with its label}."""
    loaded = load_run(run)
    config, model, iteration = loaded.config, loaded.model.to(device), loaded.iteration
    ds = MultiViewDataset(dataset or config.dataset, split=split, views_per_item=1)
    check_image_size(run, model.config.image_size, ds)
    renderer = make_renderer(config, seed=0, spp=eval_spp, device=device)
    views = strided_views(ds, view_stride)
    refine = (refine_steps, make_renderer(config, seed=0, training=True, device=device)) if refine_steps else None
    per_view, t0 = {}, time.perf_counter()
    for start in tqdm(range(0, len(views), batch), desc=f"eval {run}", unit="batch", leave=False):
        values, _ = predict_views(model, renderer, ds, [ds[i] for i in views[start:start + batch]], refine=refine)
        for k, v in values.items():
            per_view.setdefault(k, []).append(v)
    per_view = {k: torch.cat(v) for k, v in per_view.items()}
    # means, but the direction error's median over the maps with a dominant light (it is an angle: a few
    # flipped predictions of 180 degrees should not hide that most are right), and medians of the material's
    # levels and ratios
    result = {k: float(metrics.median(v) if k.startswith(MEDIAN_METRICS) else
                       v.nanmean() if k.startswith(("normal", "albedo_sky")) else v.mean()) for k, v in per_view.items()}
    result["views_with_dominant_light"] = int(torch.isfinite(per_view["direction_deg"]).sum())
    for k in ("direction_deg", "direction_deg_constant"):  # each such view's error, for the distribution figure
        v = per_view[k]
        result[k + "_views"] = [round(float(x), 2) for x in v[torch.isfinite(v)]]
    # the sunny views' median and shares within 25 / 45 degrees, with 95 % intervals over the samples they come from
    sunny = torch.isfinite(per_view["direction_deg"]).numpy()
    sample_of_view = np.array([i // ds.num_views for i in views])[sunny]
    summary = metrics.direction_summary(per_view["direction_deg"].numpy()[sunny], sample_of_view)
    result.update({f"direction_{k}": v for k, v in summary.items() if k != "median"},
                  direction_deg_ci=summary["median_ci"], samples_with_dominant_light=len(set(sample_of_view.tolist())))
    result.update(split_size(ds, split))
    result.update(run=str(run), dataset=Path(ds.root).name, dataset_kind=dataset_kind(ds),
                  trained_on=Path(config.dataset).name,
                  shading=config.shading, lobes=config.lobes,
                  seed=config.seed, iteration=iteration, trained_iterations=config.iterations, test_views=len(views),
                  view_stride=view_stride, variant=config.label(), split=split, refine_steps=refine_steps,
                  variant_kind=VARIANTS[config.variant].kind if config.variant in VARIANTS else "",
                  seconds_per_view=(time.perf_counter() - t0) / len(views))
    shown = figure_views(ds)
    worst = {k: views[int(per_view[k].argmax())] for k in FAILURE_METRICS}
    _, example_rows = predict_views(model, renderer, ds, [ds[i] for i in shown], figure=True, refine=refine)
    _, failure_rows = predict_views(model, renderer, ds, [ds[i] for i in worst.values()], figure=True, refine=refine)
    labels = [f"worst {METRIC_NAMES[k]}\n({float(per_view[k].max()):.3g})" for k in worst]
    return result, {"examples": (example_rows, None), "failures": (failure_rows, labels)}


def dataset_kind(ds: MultiViewDataset) -> str | None:
    """The kind of set the manifest says it is (metallic, glossy, diffuse: what decides its paper table), whatever
    its folder is called; None where the manifest does not say."""
    kind = ds.manifest.get("dataset")
    return kind if isinstance(kind, str) else None


def split_size(ds: MultiViewDataset, split: str) -> dict:
    """How much the split holds: its samples (objects under a map), its env maps and, for the test split, how many
    of them also light the train split's objects (a set with few maps cannot hold any out; None if the manifest
    does not say)."""
    maps = {env for _, env in ds.samples}
    shared = None
    if split == "test":
        try:
            trained = {int(e) for o in ds.manifest["objects"] if o["split"] == "train" for e in o["envmaps"]}
            shared = len(maps & trained)
        except (KeyError, TypeError, ValueError):
            pass
    return dict(samples=len(ds.samples), envmaps=len(maps), envmaps_in_train_split=shared)


def split_warnings(r: dict) -> list[str]:
    """One warning line per reason a result's means say less than they seem to: test env maps that the train
    split also uses, too few samples."""
    lines, where = [], f"{r['dataset']}'s {r.get('split', 'test')} split"
    if r.get("envmaps_in_train_split"):
        lines.append(f"warning: {where} is lit by {r['envmaps_in_train_split']} of its {r['envmaps']} env maps that "
                     "its train split also uses: the light is not scored on unseen maps (the set has too few maps "
                     "to hold some out; generate it with more --num-envmaps)")
    if r.get("samples", MIN_SAMPLES) < MIN_SAMPLES:
        lines.append(f"warning: {where} holds {r['samples']} samples (objects under a map) on {r['envmaps']} env "
                     f"maps, fewer than {MIN_SAMPLES}: its means say little")
    return lines
