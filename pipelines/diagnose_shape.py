"""What the shape's template can reach, and which training signal holds its normals:
``python -m pipelines.diagnose_shape --dataset data/metallic``.

Per test object, the model's own shape (the template sphere scaled per axis plus bounded, mirror-symmetric
per-vertex offsets; ``Encoder._shape``) is fitted directly to the object's views, no encoder, with the
training's Laplacian weight and one of these signals:

- ``normals``: the rendered normals against the GT mesh's, plus the silhouettes: what the template can represent;
- ``silhouettes``: the soft-silhouette loss alone: what the outlines hold;
- ``image``: the training's image, gradient and silhouette losses against the Cycles views, rendered with the
  GT material and the GT env map's 32-lobe SG fit while an albedo texture is fitted alongside: what shading holds
  when the light is known;
- ``image-from-normals``: the same, starting from the ``normals`` fit (the shape held while the albedo settles,
  for the first third of the steps): whether the image losses keep normals the template can carry;
- ``image-annealed``: ``image`` with the renders' roughness at least 0.7 at the start, lowered to the object's
  own by two thirds of the steps (the ``roughness-anneal`` curriculum): whether blurred reflections first lead
  descent from the sphere to better normals.

The image rows also give the image L1 the fit reached and the GT scene's (GT mesh, texture and material under
the same light) against the same views: where the fit's is lower, the image loss prefers a wrong shape to
the true one. The predicted normals' error is then measured as ``make eval`` measures it (``metrics.normal_error_deg``: per
view, the median angle over the pixels both surfaces cover), median over views and objects. A trained run's
error sits between these rows; docs/experiments.md (entry 14) reads them. With ``--sunny`` each object is fitted
under a map with a sun, and every row also gives the normals' error where the GT surface mirrors the sun (as
``diagnose_light`` measures a run's: ``metrics.normal_errors``), the pixels the light's direction depends on
(entry 18).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset
from dibrpp import Cameras, Renderer
from dibrpp.brdf import Material
from dibrpp.cli_args import Parser, positive_int
from dibrpp.formatting import markdown_table
from dibrpp.io import DataError
from dibrpp.lights import EnvMap, fit_sg_to_envmap
from dibrpp.mesh import laplacian_smoothness, uniform_laplacian

from .evaluation import metrics
from .training.config import TrainConfig
from .model.pixel_normals import normal_loss
from .training.losses import foreground_l1, gradient_loss, hdr_srgb, soft_iou_loss
from .model.encoder import Encoder, ModelConfig

SIGNALS = ("normals", "silhouettes", "image", "image-from-normals", "image-annealed")
ANNEAL_ROUGHNESS = 0.7  # ``image-annealed``: the roughness the fit starts from, lowered to the object's own


def roughness_floor(start: float, iterations: int, iteration: int) -> float:
    """The renders' least roughness at ``iteration`` of the annealed fit: ``start``, lowered linearly to 0 by two
    thirds of its ``iterations``. A blurred reflection changes slowly with the normals, so the shape first fits the
    broad shading and meets the sharp reflection near its basin."""
    return start * max(0.0, 1 - iteration / max(1, 2 * iterations // 3))


def object_views(ds: MultiViewDataset, obj: int, env: int) -> tuple[Cameras, torch.Tensor]:
    """All views of one sample: their cameras and linear RGBA images (V, S, S, 4)."""
    cams = [ds.camera(obj, env, v) for v in range(ds.num_views)]
    cameras = Cameras(torch.stack([m for m, _ in cams]), torch.tensor([f for _, f in cams]), ds.resolution)
    return cameras, torch.stack([ds.view_image(obj, env, v) for v in range(ds.num_views)])


def image_l1(rgb: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
    """The training's image term: foreground L1 in its HDR-aware display space."""
    return foreground_l1(hdr_srgb(rgb), hdr_srgb(images[..., :3]), images[..., 3])


def fit_shape(model: Encoder, signal: str, cameras: Cameras, images: torch.Tensor, gt_normals, material: dict,
              light, steps: int, weights: TrainConfig, start: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, float | None]:
    """The model's shape parameters (1, 3V + 3) fitted to one object's views with ``signal`` from ``start`` (the
    template sphere when None), and for the image signal the image L1 its last step reached."""
    n = len(images)
    raw = (model.shape_head.bias.detach()[None] if start is None else start).clone().requires_grad_(True)
    params = [raw]
    image = signal.startswith("image")
    if image:
        c = model.config
        texture = torch.zeros(1, c.texture_height, c.texture_width, 3, requires_grad=True)  # albedo 0.5
        params.append(texture)
    laplacian = uniform_laplacian(model.faces, model.template_dirs.shape[1])
    renderer = Renderer("sg")
    opt = torch.optim.Adam(params, lr=0.05)
    for step in range(steps):
        if step == 2 * steps // 3:
            for group in opt.param_groups:
                group["lr"] = 0.01
        verts = model._shape(raw)
        meshes = model.template().with_verts(verts.expand(n, -1, -1))
        smooth = weights.w_laplacian * laplacian_smoothness(verts, laplacian) / model.config.template_radius ** 2
        if image:
            albedo = torch.sigmoid(texture).expand(n, -1, -1, -1)
            shading = dict(material)
            if signal == "image-annealed":  # a blurred reflection first: a smoother loss in the normals
                shading["roughness"] = max(shading["roughness"], roughness_floor(ANNEAL_ROUGHNESS, steps, step))
            out = renderer(meshes, cameras, Material(albedo=albedo, wrap_u=True, **shading), light)
            rgb, target = hdr_srgb(out.rgb), hdr_srgb(images[..., :3])
            reached = foreground_l1(rgb, target, images[..., 3])
            loss = weights.w_image * reached + weights.w_gradient * gradient_loss(rgb, target * images[..., 3:])
        else:
            out = renderer.render_normals(meshes, cameras)
            loss = normal_loss(out.image, gt_normals.image) if signal == "normals" else torch.zeros(())
        loss = loss + weights.w_iou * soft_iou_loss(out.silhouette, images[..., 3]) + smooth
        opt.zero_grad()
        loss.backward()
        if start is not None and image and step < steps // 3:
            raw.grad = None  # the albedo settles on the given shape before the shape moves
        opt.step()
    return raw.detach(), float(reached.detach()) if image else None


def sun_direction(ds: MultiViewDataset, env: int) -> torch.Tensor | None:
    """(1, 3) the direction of env map ``env``'s dominant light, or None where it has none (a share of its power
    below ``metrics.SUN_FRACTION``)."""
    direction, share = metrics.dominant_direction(ds.envmap(env)[None])
    return direction if float(share) >= metrics.SUN_FRACTION else None


def fitted_samples(ds: MultiViewDataset, objects: int, sunny: bool) -> list[tuple[int, int]]:
    """(object, env map) of the first ``objects`` test objects, each under its first env map, or with ``sunny``
    under its first map with a sun (objects without one left out)."""
    chosen = {}
    for obj, env in ds.samples:
        if obj not in chosen and (not sunny or sun_direction(ds, env) is not None):
            chosen[obj] = env
    return list(chosen.items())[:objects]


def diagnose(dataset: str, objects: int, steps: int, signals=SIGNALS, sunny: bool = False) -> list[list]:
    ds = MultiViewDataset(dataset, split="test", views_per_item=1)
    model = Encoder(ModelConfig(image_size=ds.resolution))
    weights = TrainConfig()
    samples = fitted_samples(ds, objects, sunny)
    if not samples:
        raise DataError(f"{dataset}: no test objects to fit" + (" under a sunny map" if sunny else ""))
    errors = {s: [] for s in signals}
    within = {s: [] for s in signals}
    at_sun = {s: [] for s in signals}
    reached = {s: [] for s in (*signals, "gt")}
    renderer = Renderer("sg")
    for k, (obj, env) in enumerate(samples):
        cameras, images = object_views(ds, obj, env)
        with torch.no_grad():
            gt = renderer.render_normals(ds.mesh(obj).expand(len(images)), cameras)
        sun = sun_direction(ds, env)
        material = ds.material_params(obj)
        light = None
        if any(s.startswith("image") for s in signals):
            light = fit_sg_to_envmap(EnvMap(ds.envmap(env)[None]), 32)
            with torch.no_grad():  # the GT scene under the same light: where the image loss would sit at the truth
                gt_albedo = ds.texture(obj)[None].expand(len(images), -1, -1, -1)
                out = renderer(ds.mesh(obj).expand(len(images)), cameras, Material(albedo=gt_albedo, **material), light)
                reached["gt"].append(float(image_l1(out.rgb, images)))
        fits = {}
        for signal in signals:
            start = time.time()
            if signal == "image-from-normals" and "normals" not in fits:
                fits["normals"], _ = fit_shape(model, "normals", cameras, images, gt, material, light, steps, weights)
            fits[signal], l1 = fit_shape(model, signal, cameras, images, gt, material, light, steps, weights,
                                         start=fits["normals"] if signal == "image-from-normals" else None)
            verts = model._shape(fits[signal])
            if l1 is not None:
                reached[signal].append(l1)
            with torch.no_grad():
                meshes = model.template().with_verts(verts.expand(len(images), -1, -1))
                pred = renderer.render_normals(meshes, cameras)
                if sun is not None:  # the normals where the GT surface mirrors the sun
                    sun_deg = metrics.normal_errors(meshes, [ds.mesh(obj)] * len(images), cameras, images,
                                                    sun.expand(len(images), 3))[:, 1]
                    at_sun[signal].append(metrics.median(sun_deg))
            deg, share = metrics.normal_error_deg(pred.rgb[..., :3], pred.alpha, gt.rgb[..., :3], gt.alpha)
            errors[signal].append(metrics.median(deg))
            within[signal].append(share.nanmean())
            print(f"object {obj} ({k + 1}/{len(samples)}), {signal}: normals {float(metrics.median(deg)):.1f} deg "
                  f"({time.time() - start:.0f} s)", file=sys.stderr, flush=True)
    mean_l1 = {k: f"{sum(v) / len(v):.3f}" if v else "" for k, v in reached.items()}
    sun_col = {s: f"{float(metrics.median(torch.stack(v))):.1f} ({len(v)})" if v else "" for s, v in at_sun.items()}
    rows = [[s, f"{float(metrics.median(torch.stack(errors[s]))):.1f}", f"{float(torch.stack(within[s]).mean()):.0%}",
             sun_col[s], mean_l1[s]] for s in signals]
    if reached["gt"]:
        gt_at_sun = "0" if at_sun[signals[0]] else ""
        rows.append(["(the GT mesh, texture and material under the same light)", "0", "100%", gt_at_sun, mean_l1["gt"]])
    return rows


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.diagnose_shape", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", required=True, metavar="DIR", help="dataset folder (its test split is used)")
    ap.add_argument("--objects", type=positive_int, default=6, metavar="N", help="test objects to fit (default: 6)")
    ap.add_argument("--steps", type=positive_int, default=300, metavar="N", help="Adam steps per fit (default: 300)")
    ap.add_argument("--signals", default=",".join(SIGNALS), help=f"comma-separated subset of {', '.join(SIGNALS)}")
    ap.add_argument("--sunny", action="store_true",
                    help="fit each object under its first env map with a sun (objects without one left out), so that "
                         "every row also gives the normals where the GT surface mirrors the sun")
    ap.add_argument("--threads", type=positive_int, default=None, metavar="N", help="torch CPU threads")
    args = ap.parse_args(argv)
    signals = tuple(dict.fromkeys(s.strip() for s in args.signals.split(",") if s.strip()))
    if not signals or set(signals) - set(SIGNALS):
        ap.error(f"--signals {args.signals!r}: choose a comma-separated subset of {', '.join(SIGNALS)}")
    if not Path(args.dataset).is_dir():
        ap.error(f"--dataset {args.dataset}: not a folder; render one with `make data-glossy` or `make data-metallic`")
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        rows = diagnose(args.dataset, args.objects, args.steps, signals, sunny=args.sunny)
    except DataError as e:
        ap.error(str(e))
    print(markdown_table(["the template fitted to", "normals: median error (°)", "pixels within 10°",
                         "where the GT surface mirrors the sun (°; sunny samples)", "image L1"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
