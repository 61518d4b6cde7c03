"""What one view can tell of its light: ``python -m pipelines.light_ceiling --dataset data/glossy-128``.

The ceiling of any model that reads its light off one view. On test views of a dataset, a free SG light (32 lobes,
every axis, sharpness and colour its own) is fitted to each view apart by the training's image loss, rendered
through everything else the model predicts taken from the GT: the mesh, the albedo texture and the material. No
learning and no prior: what is left between this light and the GT map is what the image does not hold (or the SG
renderer's difference from Cycles). A model's light can come closer only through a prior over maps.

Scored as ``make eval`` scores a prediction, beside a constant map on the same views: eq. 9 on LDR maps, the three
probes, the dominant direction (sunny views). docs/experiments.md entry 2 measured it at 64 x 64 on 8 training
views; docs/scale.md reads it along the input's resolution.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from tqdm import tqdm

from datagen.reader import MultiViewDataset, collate
from dibrpp import Material, Renderer
from dibrpp.cli_args import Parser, check_output_folder, int_in, positive_int
from dibrpp.display import display_image, tonemap_envmap
from dibrpp.formatting import markdown_table, pyplot, save_figure
from dibrpp.io import DataError, atomic_path
from dibrpp.lights import EnvMap, SGLight

from .evaluation import metrics
from .model.light_probe import fibonacci_axes
from .scoring import strided_views
from .training.losses import foreground_l1, image_space

LOBES = 32
INITIAL_SHARPNESS = 11.0  # the trained runs' shared sky sharpness (docs/experiments.md, "what the light's form can reach")
INITIAL_RADIANCE = 0.5  # a grey dome: the datasets' maps are normalised to a mean radiance of about 1
LEARNING_RATE = 0.05
METRICS = ("light_ldr", "probe_metal", "probe_mirror", "probe_diffuse")


class FreeSGLight(torch.nn.Module):
    """An SG light in the world frame, every lobe free: axes, log sharpness, log RGB amplitude."""

    def __init__(self, lobes: int = LOBES):
        super().__init__()
        self.axis = torch.nn.Parameter(fibonacci_axes(lobes)[None])
        self.log_sharpness = torch.nn.Parameter(torch.full((1, lobes), INITIAL_SHARPNESS).log())
        self.log_amplitude = torch.nn.Parameter(torch.full((1, lobes, 3), INITIAL_RADIANCE).log())

    def forward(self) -> SGLight:
        return SGLight(self.axis, self.log_sharpness.exp(), self.log_amplitude.exp())


def fit_view(renderer: Renderer, mesh, camera, material: Material, rgba: torch.Tensor, steps: int) -> SGLight:
    """The SG light that best re-renders one view (``rgba`` (1, H, W, 4), linear) through the GT mesh and
    material, by the training's foreground L1 in its image space."""
    light = FreeSGLight()
    opt = torch.optim.Adam(light.parameters(), lr=LEARNING_RATE)
    frags = renderer.rasterize(mesh, camera)  # the surface is fixed: rasterised once
    target = image_space(rgba[..., :3])
    for _ in range(steps):
        opt.zero_grad()
        loss = foreground_l1(image_space(renderer(mesh, camera, material, light(), frags).rgb), target, rgba[..., 3])
        loss.backward()
        opt.step()
    with torch.no_grad():
        return light()


def ceiling(dataset: str, split: str = "test", stride: int = 24, steps: int = 1000, max_views: int | None = None,
            figure_views: int = 4) -> tuple[dict, dict, list]:
    """({metric: (V,)} of the fitted lights, {metric: (V,)} of a constant map, figure rows (input, GT map, fitted
    light) of the first ``figure_views`` views) on every ``stride``-th view of each ``split`` sample (the first
    ``max_views`` of them)."""
    ds = MultiViewDataset(dataset, split=split, views_per_item=1)
    views = strided_views(ds, stride)[:max_views]
    renderer = Renderer("sg", compile=True)  # the training renderer's fused SG shading
    fitted, constant, rows = {}, {}, []
    for n, i in enumerate(tqdm(views, desc=f"fitting {Path(dataset).name}", unit="view", file=sys.stderr)):
        b = collate([ds[i]])
        rgba, cams, env = b["image"][:, 0], b["cameras"], b["envmap"]
        obj = int(b["object"][0])
        # the scalars as tensors: as Python floats torch.compile specialises on each object's values and recompiles
        material = Material(albedo=ds.texture(obj)[None],
                            **{k: torch.tensor([v]) for k, v in ds.material_params(obj).items()})
        light = fit_view(renderer, ds.mesh(obj), cams, material, rgba, steps)
        scene = metrics.ProbeScene(cams.world_to_camera)
        with torch.no_grad():
            table = light.to_envmap(env.shape[1], env.shape[2]).image
            scores = {**metrics.light_metrics(light, EnvMap(env), scene), **metrics.envmap_losses(table, env),
                      **sky_scores(table, env)}
            reference = metrics.constant_light_references(env, scene)
        for k, v in scores.items():
            fitted.setdefault(k, []).append(v)
        for k, v in reference.items():
            constant.setdefault(k.removesuffix("_constant"), []).append(v)
        if n < figure_views:
            rows.append([display_image(rgba[0, ..., :3]), tonemap_envmap(env[0]), tonemap_envmap(table[0])])
    return {k: torch.cat(v) for k, v in fitted.items()}, {k: torch.cat(v) for k, v in constant.items()}, rows


def sky_scores(table: torch.Tensor, env: torch.Tensor) -> dict:
    """(B,) diagnose_sky's two tests of the light ``table`` where the GT map ``env`` has a sky over a ground (NaN
    elsewhere): a sky over a ground (metrics.has_sky), and one at least half as much bluer as the GT's."""
    gt_ratio, gt_bluer = metrics.sky_contrast(env)
    ratio, bluer = metrics.sky_contrast(table)
    nan = torch.full_like(ratio, float("nan"))
    outdoor = metrics.has_sky(gt_ratio, gt_bluer)
    return {"sky": torch.where(outdoor, metrics.has_sky(ratio, bluer).float(), nan),
            "sky_like_gt": torch.where(outdoor, metrics.has_sky_like_gt(ratio, bluer, gt_bluer).float(), nan)}


def summary(fitted: dict, constant: dict) -> list[list[str]]:
    """Table rows: each light metric's mean (the direction's median and share within 25 degrees over sunny views)
    for the fitted lights and for a constant map, and their ratio."""
    rows = []
    for k in METRICS:
        f, c = float(fitted[k].mean()), float(constant[k].mean())
        rows.append([k, f"{f:.3f}", f"{c:.3f}", f"{f / c:.2f}×"])
    sunny = ~fitted["direction_deg"].isnan()
    if sunny.any():
        f, c = fitted["direction_deg"][sunny], constant["direction_deg"][sunny]
        rows.append([f"direction_deg, median (≤ 25°), {int(sunny.sum())} sunny views",
                     f"{metrics.median(f):.1f} ({100 * (f <= 25).float().mean():.0f} %)",
                     f"{metrics.median(c):.1f} ({100 * (c <= 25).float().mean():.0f} %)", ""])
    outdoor = ~fitted["sky"].isnan()
    if outdoor.any():
        for k, what in (("sky", "a sky over a ground"), ("sky_like_gt", "… with half its GT's blue")):
            rows.append([f"{what}, {int(outdoor.sum())} views with one",
                         f"{100 * fitted[k][outdoor].mean():.0f} %", "0 %", ""])
    return rows


def draw(rows: list, path: Path) -> Path:
    """The input view, the GT map and the light fitted to the view, a row each."""
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 3, figsize=(7.5, 1.6 * len(rows)), squeeze=False)
    for r, images in enumerate(rows):
        for c, (image, title) in enumerate(zip(images, ("input view", "GT map", "SG fitted to the view"))):
            axes[r, c].imshow(image.clamp(0, 1).numpy())
            axes[r, c].set_axis_off()
            if r == 0:
                axes[r, c].set_title(title, fontsize=9)
    return save_figure(fig, path)


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.light_ceiling", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", required=True, metavar="DIR", help="a dataset folder (datagen's layout)")
    ap.add_argument("--out", default="results/light-ceiling", metavar="DIR",
                    help="where the table (<dataset>.md) and the figure of the first views (<dataset>.png) go")
    ap.add_argument("--split", choices=("test", "train"), default="test", help="the views to fit")
    ap.add_argument("--view-stride", type=positive_int, default=24, metavar="N",
                    help="every N-th view of each sample (24: one view a sample)")
    ap.add_argument("--max-views", type=positive_int, metavar="N",
                    help="fit only the first N of those views (default: all; a view at 128 x 128 takes ~10 s on 2 cores)")
    ap.add_argument("--steps", type=int_in(1, 20000), default=1000, metavar="N", help="Adam steps a view")
    args = ap.parse_args(argv)
    out, name = Path(args.out), Path(args.dataset).name
    try:
        check_output_folder("--out", out)
        MultiViewDataset(args.dataset, split=args.split, views_per_item=1)  # a missing or broken set: said first
        fitted, constant, rows = ceiling(args.dataset, args.split, args.view_stride, args.steps, args.max_views)
    except DataError as e:
        ap.error(str(e))
    table = markdown_table([f"{args.split} views of {args.dataset} ({len(fitted['light_ldr'])}; {args.steps} steps)",
                            "SG fitted to the view", "constant map", "× constant"], summary(fitted, constant))
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / f"{name}.md") as tmp:
        tmp.write_text(table + "\n")
    print(table)
    print(f"written: {out / f'{name}.md'}, {draw(rows, out / f'{name}.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
