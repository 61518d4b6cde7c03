"""What ``pipelines.evaluate`` writes beside each run's result: the figures (qualitative rows like the paper's Fig.
O-Q, the direction errors' distribution) and the table of every result with its constant-light references."""
from __future__ import annotations

from pathlib import Path

import torch

from dibrpp.formatting import format_number, markdown_table, pyplot, save_figure, write_csv

# the paper's metrics: image L1 over the whole image (the paper's) and the GT foreground (ours), eq. 9 on LDR maps
# (the paper's, as we read it) and on HDR maps
METRICS = ("image_whole", "image_foreground", "iou", "light_ldr", "light_hdr", "texture", "chamfer")
LIGHT_METRICS = ("probe_diffuse", "probe_metal", "probe_mirror", "colour_deg", "direction_deg")
# a metric and its reference: what a constant env map scores under the same definition
CONSTANT_REFERENCES = tuple(f"{k}_constant" for k in ("light_ldr", "light_hdr", *LIGHT_METRICS))
NOVEL_AZIMUTHS = (90.0, 180.0)  # novel views: the input camera moved this far along its orbit
FIGURE_COLUMNS = ("input", "re-rendering", "albedo (ours)", "albedo (GT)", "light (ours)", "light (GT)",
                  "metal probe (ours)", "metal probe (GT)", *(f"novel view +{a:.0f}°" for a in NOVEL_AZIMUTHS))


def write_figure(rows: list, path: Path, title: str, row_labels: list[str] | None = None) -> None:
    """Qualitative results like the paper's Fig. O-Q: one test view per row."""
    plt = pyplot()
    ratios = [2 if c.startswith("light") else 1 for c in FIGURE_COLUMNS]
    fig, axes = plt.subplots(len(rows), len(FIGURE_COLUMNS), figsize=(2.2 * len(FIGURE_COLUMNS) + 1.2, 1.9 * len(rows)),
                             gridspec_kw=dict(width_ratios=ratios), squeeze=False)
    for i, row in enumerate(rows):
        for j, img in enumerate(row):
            ax = axes[i, j]
            ax.imshow(img.clamp(0, 1).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(FIGURE_COLUMNS[j], fontsize=9)
            if j == 0 and row_labels:
                ax.set_ylabel(row_labels[i], fontsize=8)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=110)


def write_direction_figures(results: list[dict], out: Path) -> list[Path]:
    """``direction_<dataset>.png``: per dataset, the share of test views (those with a dominant light) whose
    dominant-light direction error is at most x degrees, for each default seed-0 run and the constant guess."""
    plt = pyplot()
    written = []
    for dataset in sorted({r["dataset"] for r in results}):
        runs = [r for r in results if r["dataset"] == dataset and not r.get("variant") and r["seed"] == 0
                and r.get("trained_on", dataset) == dataset and r.get("direction_deg_views")]
        if not runs:
            continue
        fig, ax = plt.subplots(figsize=(5.2, 3.6))
        curves = [(f"{r['shading'].upper()} (median {r['direction_deg']:.0f}°)", r["direction_deg_views"], "-")
                  for r in sorted(runs, key=lambda r: r["shading"])]
        const = runs[0]
        curves.append((f"constant: straight above (median {const['direction_deg_constant']:.0f}°)",
                       const["direction_deg_constant_views"], "--"))
        for label, errors, style in curves:
            e = torch.tensor(sorted(errors))
            ax.step(torch.cat([torch.zeros(1), e]).numpy(), torch.arange(len(e) + 1).numpy() / len(e),
                    style, where="post", label=label)
        ax.axvline(30, color="grey", lw=0.8, ls=":")
        ax.set(xlim=(0, 180), ylim=(0, 1), xlabel="dominant-light direction error (°)",
               ylabel="share of views with at most this error",
               title=f"{dataset}: {len(const['direction_deg_views'])} test views with a sun or lamp")
        ax.legend(fontsize=8, loc="lower right")
        written.append(save_figure(fig, out / f"direction_{dataset}.png", dpi=110))
    return written


def dataset_label(r: dict) -> str:
    """The evaluated dataset, and the one the run was trained on where that is another."""
    trained = r.get("trained_on", r["dataset"])
    return r["dataset"] if trained == r["dataset"] else f"{r['dataset']} (trained on {trained})"


def share_with_interval(share: float | None, interval: list | None) -> str:
    """'45 % (29–61)': a share and its 95 % interval in percent; '' where the run has none (no view with a dominant
    light, or evaluated before the intervals were)."""
    if share is None or interval is None or share != share:
        return ""
    return f"{100 * share:.0f} % ({100 * interval[0]:.0f}–{100 * interval[1]:.0f})"


ALL_RUNS_HEADER = ("dataset", "method", "variant", "K", "seed", "iterations", "Image L1 (whole)", "Image L1 (fg)",
                   "2D IoU loss", "Light 1-NCC (LDR)", "Light 1-NCC (HDR)", "Tex 1-NCC", "Chamfer", "diffuse probe",
                   "metal probe", "mirror probe", "colour (°)", "direction (°)", "≤ 25° (95 % interval)", "normal (°)")


def constant_rows(results: list[dict]) -> list[dict]:
    """One reference row per evaluated dataset and split: every light metric of a constant env map, under the
    metric's own name (from the first result that has them)."""
    rows = {}
    for r in results:
        key = (r["dataset"], r.get("split", "test"))
        if key not in rows and "light_ldr_constant" in r:
            rows[key] = {"dataset": r["dataset"], "shading": "constant light", "split": key[1],
                         **{k.removesuffix("_constant"): r.get(k) for k in CONSTANT_REFERENCES}}
    return list(rows.values())


def write_table(results: list[dict], out: Path) -> str:
    """all_runs.md / .csv: every result, then each dataset's constant-light reference row; the CSV also gives each
    light metric's reference beside every run."""
    out.mkdir(parents=True, exist_ok=True)
    cols = ["dataset", "dataset_kind", "trained_on", "split", "shading", "variant", "lobes", "seed", "iteration",
            *METRICS, *LIGHT_METRICS, *CONSTANT_REFERENCES, "direction_within_25", "normal_deg"]
    write_csv(out / "all_runs.csv", results, cols, extrasaction="ignore")

    def cells(r):
        sg = r["shading"] in ("sg", "sh-sg")
        return [dataset_label(r), r["shading"], r.get("variant", ""), r["lobes"] if sg else "", r.get("seed", ""),
                r.get("iteration", ""), *(format_number(r.get(k), ".4f") for k in METRICS),
                *(format_number(r.get(k), ".3g") for k in LIGHT_METRICS),
                share_with_interval(r.get("direction_within_25"), r.get("direction_within_25_ci")),
                format_number(r.get("normal_deg"), ".3g")]

    rows = [cells(r) for r in (*results, *constant_rows(results))]
    text = markdown_table(ALL_RUNS_HEADER, rows, "llllrr" + "r" * (len(METRICS) + len(LIGHT_METRICS) + 2)) + "\n"
    (out / "all_runs.md").write_text(text)
    return text
