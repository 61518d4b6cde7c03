"""Whether a run's light has a sky over a ground: ``python -m pipelines.diagnose_sky --runs RUN [RUN ...] [--dataset DIR]``.

The light beyond the sun, measured. On the test views whose GT map has a sky brighter and bluer than its ground
(outdoor light), each run's predicted light (world frame) and the GT map are each split at the horizon, leaving out
the sun and its glow (diagnose_light's): how much brighter the sky is than the ground (the ratio of their mean
luminances) and how much bluer (the difference of their blue chromaticities, b / (r + g + b)), medians over the
views, and the share of views where the predicted sky is as much brighter and bluer as makes a sky
(``metrics.has_sky``: at least 1.25 times as bright, 0.01 bluer), as every selected GT map is, and the share where it
is as much brighter and at least half as much bluer as its GT's sky is than its ground (the light's target), also
counted over the views under the dataset's outdoor maps (its manifest's ``env_kind``), the target's own count. A
constant map has neither (ratio 1, difference 0): its row is the reference.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

from datagen.reader import MultiViewDataset, collate
from dibrpp.cli_args import Parser, positive_int
from dibrpp.formatting import markdown_table
from dibrpp.io import DataError

from .evaluation import metrics
from .model.model_input import encoder_input
from .scoring import strided_views
from .training.runs import check_image_size, load_run, run_folder


@torch.no_grad()
def diagnose(run: Path, stride: int = 3, dataset: str | None = None) -> dict:
    """The sky against the ground of ``run``'s predicted light and of the GT maps on the test views with a sky of
    its dataset (or of ``dataset``)."""
    loaded = load_run(run)
    ds = MultiViewDataset(dataset or loaded.config.dataset, split="test", views_per_item=1)
    check_image_size(run, loaded.model.config.image_size, ds)
    views = strided_views(ds, stride)
    kinds = ds.manifest.get("env_kind", [])
    pred, gt, outdoor = [], [], []
    for start in range(0, len(views), 16):
        b = collate([ds[i] for i in views[start:start + 16]])
        rgba, cams, env = b["image"][:, 0], b["cameras"], b["envmap"]
        gt_ratio, gt_bluer = metrics.sky_contrast(env)
        kind_outdoor = torch.tensor([kinds[int(i)] == "outdoor" if kinds else False for i in b["envmap_index"]])
        chosen = metrics.has_sky(gt_ratio, gt_bluer) | kind_outdoor
        if not chosen.any():
            continue
        light = loaded.model(encoder_input(rgba[chosen]), cams[chosen]).light(cams.world_to_camera[chosen])
        pred.append(torch.stack(metrics.sky_contrast(light.to_envmap(env.shape[1], env.shape[2]).image), 1))
        gt.append(torch.stack([gt_ratio[chosen], gt_bluer[chosen]], 1))
        outdoor.append(kind_outdoor[chosen])
    if not pred:
        raise DataError(f"{run}: no test view of {ds.root} has a sky brighter and bluer than its ground")
    pred, gt, outdoor = torch.cat(pred), torch.cat(gt), torch.cat(outdoor)
    like_gt = metrics.has_sky_like_gt(pred[:, 0], pred[:, 1], gt[:, 1])
    sky = metrics.has_sky(gt[:, 0], gt[:, 1])  # the views whose GT map has a sky
    pred, gt, like_outdoor = pred[sky], gt[sky], like_gt[outdoor]
    return {"views": len(pred), "ratio": float(metrics.median(pred[:, 0])), "ratio_gt": float(metrics.median(gt[:, 0])),
            "bluer": float(metrics.median(pred[:, 1])), "bluer_gt": float(metrics.median(gt[:, 1])),
            "brighter_share": float((pred[:, 0] >= metrics.SKY_BRIGHTER).float().mean()),
            "bluer_share": float((pred[:, 1] >= metrics.SKY_BLUER).float().mean()),
            "sky_share": float(metrics.has_sky(pred[:, 0], pred[:, 1]).float().mean()),
            "like_gt_share": float(like_gt[sky].float().mean()),
            "outdoor_views": int(outdoor.sum()),
            "like_gt_outdoor": float(like_outdoor.float().mean()) if len(like_outdoor) else float("nan")}


HEADER = ["run", "test views with a sky", "sky / ground luminance, median (GT)", "sky − ground blue, median (GT)",
          f"sky ≥ {metrics.SKY_BRIGHTER}× ground", f"sky ≥ {metrics.SKY_BLUER} bluer", "both (a sky over a ground)",
          f"≥ {metrics.SKY_BRIGHTER}× and half the GT's blue", "… of the views under outdoor maps"]


def row(name: str, r: dict) -> list[str]:
    return [name, str(r["views"]), f"{r['ratio']:.2f} ({r['ratio_gt']:.2f})", f"{r['bluer']:+.3f} ({r['bluer_gt']:+.3f})",
            f"{100 * r['brighter_share']:.0f} %", f"{100 * r['bluer_share']:.0f} %", f"{100 * r['sky_share']:.0f} %",
            f"{100 * r['like_gt_share']:.0f} %", f"{100 * r['like_gt_outdoor']:.0f} % of {r['outdoor_views']}"]


def main(argv=None) -> int:
    ap = Parser(prog="python -m pipelines.diagnose_sky", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, nargs="+", metavar="DIR", help="run folders")
    ap.add_argument("--view-stride", type=positive_int, default=3, metavar="N",
                    help="every N-th test view of each object, as make eval (default: 3)")
    ap.add_argument("--dataset", metavar="DIR",
                    help="the test views of this dataset instead of each run's own (e.g. make data-glossy-elevations)")
    args = ap.parse_args(argv)
    try:
        if args.dataset:  # a missing or broken --dataset: said before any run is loaded
            MultiViewDataset(args.dataset, split="test", views_per_item=1)
        results = [(str(run), diagnose(run_folder(Path(run)), args.view_stride, args.dataset)) for run in args.runs]
    except DataError as e:
        ap.error(str(e))
    first = results[0][1]
    constant = {**first, "ratio": 1.0, "bluer": 0.0, "brighter_share": 0.0, "bluer_share": 0.0, "sky_share": 0.0,
                "like_gt_share": 0.0, "like_gt_outdoor": 0.0}
    print(markdown_table(HEADER, [row(name, r) for name, r in results] +
                         [row(f"a constant map (the reference; GT of {results[0][0]})", constant)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
