"""The scale study's figures and tables (``pipelines.scale_study report``): each axis's curves, its light row and
its markdown table, from rows of evaluated points ({"value", "test", "train", "minutes"})."""
from __future__ import annotations

from pathlib import Path

from dibrpp.formatting import format_number, markdown_table, pyplot, save_figure

from .summary import CONSTANT_REFERENCES

BASE_LABEL = "glossy; base: 64², 1500 its, 80 cars, 32 maps"
AXIS_LABELS = {"resolution": "input resolution (pixels a side)", "iterations": "training iterations",
               "cars": "training cars", "maps": "training env maps"}

# what each axis's figure plots: (key, title); a light metric's constant-map score is drawn beside it
CURVES = [("image_whole", "image L1, whole image"), ("image_foreground", "image L1, foreground"),
          ("iou", "2D IoU loss"), ("texture", "texture 1-NCC"), ("normal_deg", "normal error (deg)"),
          ("light_ldr", "light 1-NCC, LDR maps"), ("light_hdr", "light 1-NCC, HDR maps"),
          ("probe_diffuse", "diffuse probe si-RMSE"), ("probe_metal", "rough-metal probe si-RMSE"),
          ("probe_mirror", "mirror probe si-RMSE"), ("direction_deg", "sun direction, median (deg)"),
          ("minutes", "training wall time (min, 2 cores)")]


def plot_axis(axis: str, rows: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(3, 4, figsize=(15, 9.5))
    xs = [r["value"] for r in rows]
    for ax, (key, title) in zip(axes.flat, CURVES):
        if key == "minutes":
            ax.plot(xs, [r["minutes"] or float("nan") for r in rows], "o-", color="k")
        else:
            ax.plot(xs, [r["test"][key] for r in rows], "o-", label="test split")
            ax.plot(xs, [r["train"][key] if r["train"] else float("nan") for r in rows], "x--", label="train split")
            if f"{key}_constant" in CONSTANT_REFERENCES:
                ax.plot(xs, [r["test"][f"{key}_constant"] for r in rows], ":", color="grey", label="constant map (test)")
        ax.set_xscale("log", base=2)
        ax.set_xticks(xs, [str(x) for x in xs])
        ax.minorticks_off()
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes.flat[5].legend(fontsize=8)
    fig.supxlabel(AXIS_LABELS[axis])
    fig.suptitle(f"The default SG model along {AXIS_LABELS[axis]} ({BASE_LABEL})")
    save_figure(fig, path, dpi=90)


def plot_light_row(axis: str, rows: list[dict], lights: list, path: Path) -> None:
    """The GT map and each point's predicted light (:func:`predicted_lights` of each row's run), one test view per
    row."""
    gt = lights[0][1]
    plt = pyplot()
    fig, axes = plt.subplots(len(gt), len(rows) + 1, figsize=(2.6 * (len(rows) + 1), 1.45 * len(gt)), squeeze=False)
    for i in range(len(gt)):
        for j, img in enumerate([gt[i], *(pred[i] for pred, _ in lights)]):
            ax = axes[i, j]
            ax.imshow(img.clamp(0, 1).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title("GT" if j == 0 else f"{rows[j - 1]['value']}", fontsize=9)
    fig.suptitle(f"Predicted light along {AXIS_LABELS[axis]} (test views; tone-mapped equirect, up at the top)",
                 fontsize=10)
    save_figure(fig, path, dpi=100)


TABLE_KEYS = ("image_whole", "iou", "texture", "normal_deg", "light_ldr", "probe_metal", "probe_mirror", "direction_deg")
TRAIN_KEYS = ("image_whole", "light_ldr", "probe_metal")
TITLES = dict(CURVES)


def cell(r: dict | None, key: str) -> str:
    """A metric, with its ratio to the constant map's score where it has one."""
    if not r:
        return "—"
    ratio = f" ({r[key] / r[key + '_constant']:.2f}×)" if key + "_constant" in r else ""
    return format_number(r[key], ".3g") + ratio


def table(axis: str, rows: list[dict]) -> str:
    """Each point's test metrics, a few train-split ones, its training time."""
    head = [AXIS_LABELS[axis], *(TITLES[k] for k in TABLE_KEYS), *(f"train: {TITLES[k]}" for k in TRAIN_KEYS),
            "training (min)"]
    body = [[str(r["value"]), *(cell(r["test"], k) for k in TABLE_KEYS), *(cell(r["train"], k) for k in TRAIN_KEYS),
             format_number(r["minutes"], ".1f")] for r in rows]
    return markdown_table(head, body)
