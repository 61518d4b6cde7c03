"""Paper-style tables (Table 1, C, D, E, F) from the per-run metrics that :mod:`pipelines.evaluate` wrote.

Each table puts the paper's numbers beside ours where the supplementary gives them, marks runs that
are missing (with the make target that trains them) and states whether each of the paper's claims
holds on our data. Written as Markdown, LaTeX and CSV.
"""
from __future__ import annotations

import json
import statistics
from pathlib import Path

from dibrpp.formatting import markdown_table, write_csv

COLUMNS = ("image", "iou", "light", "texture")  # the paper's columns: ours beside the paper's
HEADER = ("Image", "2D IoU", "Light", "Tex.")
# Light by what it does to surfaces (pipelines.metrics.light_metrics); ours only, the paper has no such column.
LIGHT_COLUMNS = ("probe_diffuse", "probe_metal", "probe_mirror", "colour_deg", "direction_deg")
LIGHT_HEADER = ("Diffuse probe", "Metal probe", "Mirror probe", "Colour (°)", "Direction (°)")

# The paper's numbers (supplementary Tables C-F; Table 1's glossy SG / SH rows are Table D's).
PAPER = {
    ("glossy", "sg", 32, 0): (0.024, 0.057, 0.091, 0.140),
    ("glossy", "sh", 32, 0): (0.024, 0.062, 0.131, 0.152),
    ("glossy", "sh-sg", 32, 0): (0.023, 0.063, 0.098, 0.147),
    ("glossy", "sg", 4, 0): (0.025, 0.067, 0.118, 0.147),
    ("glossy", "sg", 8, 0): (0.025, 0.063, 0.093, 0.145),
    ("glossy", "sg", 16, 0): (0.024, 0.063, 0.092, 0.143),
    ("glossy", "sg", 32, 1): (0.025, 0.061, 0.092, 0.143),
    ("glossy", "sg", 32, 2): (0.025, 0.062, 0.091, 0.143),
    ("diffuse", "mc", 32, 0): (0.030, 0.032, 0.109, 0.039),
    ("diffuse", "sg", 32, 0): (0.032, 0.032, 0.122, 0.040),
    ("diffuse", "sh", 32, 0): (0.030, 0.035, 0.101, 0.043),
}
METHOD_NAMES = {"mc": "DIB-R++ MC", "sg": "DIB-R++ SG", "sh": "DIB-R (SH)", "sh-sg": "DIB-R with SG light"}


def run_key(r: dict) -> tuple:
    # K only distinguishes SG-lit runs; MC and SH runs key at the default 32
    lobes = r["lobes"] if r["shading"] in ("sg", "sh-sg") else 32
    return (r["dataset"], r["shading"], lobes, r["seed"])


RESULT_KEYS = frozenset({"dataset", "shading", "lobes", "seed", "iteration"})  # of pipelines.evaluate's results


def read_result(path: Path, keys=RESULT_KEYS) -> dict | None:
    """The result JSON at ``path``, or None for any other file (not JSON, unreadable, or without ``keys``)."""
    try:
        r = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return r if isinstance(r, dict) and keys <= r.keys() else None


def load_results(eval_dir: Path) -> dict:
    """{run_key: result} of the default-model results under ``eval_dir``; other files there are skipped."""
    out = {}
    for r in filter(None, map(read_result, sorted(Path(eval_dir).glob("*/*.json")))):
        if not r.get("variant"):  # ablations of the model (pipelines.evaluate.run_variant) are not paper rows
            out[run_key(r)] = r
    return out


def format_value(v, spec: str = ".3f") -> str:
    """Table cell: 3 decimals by default, a dash where there is no value (None or NaN)."""
    return "—" if v is None or v != v else format(v, spec)


def _row(label: str, key: tuple, results: dict, missing_hint: str) -> dict:
    r = results.get(key)
    return dict(label=label, ours=None if r is None else tuple(r[c] for c in COLUMNS), paper=PAPER.get(key),
                light=None if r is None else tuple(r.get(c) for c in LIGHT_COLUMNS),
                note="" if r else f"missing: {missing_hint}", iterations=None if r is None else r["iteration"])


def _constant_light_row(ds: str, results: dict) -> list[dict]:
    """Reference row: the light metrics of a constant env map on the dataset's test views (from any run);
    its direction is the guess "straight above"."""
    r = next((r for r in results.values() if r["dataset"] == ds and "light_constant" in r), None)
    if r is None:
        return []
    return [dict(label=f"{ds} / constant light (reference)", ours=(None, None, r["light_constant"], None), paper=None,
                 light=tuple(r.get(f"{c}_constant") for c in LIGHT_COLUMNS),
                 note="a constant env map (direction: straight above)", iterations=None)]


def build_tables(results: dict) -> dict[str, dict]:
    """{table id: {title, rows, claims}} for every table, whether or not its runs exist."""
    t = {}
    rows = []
    for ds in ("metallic", "glossy"):
        for m in ("mc", "sg", "sh"):
            rows.append(_row(f"{ds} / {METHOD_NAMES[m]}", (ds, m, 32, 0), results, f"make train-{ds}"))
        rows += _constant_light_row(ds, results)
    t["table1"] = dict(title="Table 1: metallic and glossy surfaces (test split; lower is better)", rows=rows)
    t["tableC"] = dict(title="Table C: diffuse surfaces", rows=[
        _row(METHOD_NAMES[m], ("diffuse", m, 32, 0), results, "make train-diffuse") for m in ("mc", "sg", "sh")]
        + _constant_light_row("diffuse", results))
    t["tableD"] = dict(title="Table D: shading methods on glossy surfaces", rows=[
        _row(METHOD_NAMES[m], ("glossy", m, 32, 0), results, hint) for m, hint in
        (("sg", "make train-glossy"), ("sh-sg", "make train-ablations"), ("sh", "make train-glossy"))])
    t["tableE"] = dict(title="Table E: number of SG lobes K (glossy)", rows=[
        _row(f"K = {k}", ("glossy", "sg", k, 0), results, "make train-glossy" if k == 32 else "make train-ablations")
        for k in (4, 8, 16, 32)])
    seeds = [_row(f"DIB-R++ SG, seed {s}", ("glossy", "sg", 32, s), results, "make train-glossy") for s in (0, 1, 2)]
    t["tableF"] = dict(title="Table F: training variance over three seeds (glossy, SG)", rows=seeds + _spread(seeds))
    for tab in t.values():
        tab["claims"] = []
    _claims(t, results)
    return t


# Table F's summary rows as printed; its "variance" row matches the standard deviation of its three rows.
PAPER_SPREAD = {"mean": (0.025, 0.060, 0.091, 0.142), "variance": None, "std. dev.": (0.000, 0.002, 0.000, 0.001)}


def _spread(seeds: list[dict]) -> list[dict]:
    got = [r["ours"] for r in seeds if r["ours"] is not None]

    def stat(fn, vals):
        return tuple(fn([v[i] for v in vals]) for i in range(len(COLUMNS))) if len(vals) >= 2 else None

    return [dict(label=name, ours=stat(fn, got), paper=PAPER_SPREAD[name], light=None, note="" if len(got) == 3 else
                 f"over {len(got)} of 3 seeds", iterations=None)
            for name, fn in (("mean", statistics.mean), ("variance", statistics.variance), ("std. dev.", statistics.stdev))]


def _claims(t: dict, results: dict) -> None:
    def metric(key, col):
        r = results.get(key)
        return None if r is None else r.get(col)

    def claim(table, text, holds):
        verdict = "cannot be tested yet (runs missing)" if holds is None else ("holds" if holds else "does NOT hold")
        t[table]["claims"].append(f"{text}: {verdict} on our data.")

    for ds in ("metallic", "glossy"):
        sh = metric((ds, "sh", 32, 0), "light")
        for m in ("sg", "mc"):
            v = metric((ds, m, 32, 0), "light")
            claim("table1", f"{METHOD_NAMES[m]} predicts light better than SH on {ds} surfaces",
                  None if v is None or sh is None else v < sh)
    for ds, table in (("metallic", "table1"), ("glossy", "table1"), ("diffuse", "tableC")):
        runs = [r for r in results.values() if r["dataset"] == ds and "light_constant" in r and r["seed"] == 0
                and r["shading"] in ("mc", "sg", "sh") and run_key(r)[2] == 32]
        if runs:
            best = min(runs, key=lambda r: r["light"])
            claim(table, f"on {ds} surfaces the best predicted light ({METHOD_NAMES[best['shading']]}, "
                  f"{best['light']:.3f}) beats a constant env map ({best['light_constant']:.3f})",
                  best["light"] < best["light_constant"])
    for ds in ("metallic", "glossy"):
        const = next((r["probe_metal_constant"] for r in results.values()
                      if r["dataset"] == ds and "probe_metal_constant" in r), None)
        sh = metric((ds, "sh", 32, 0), "probe_metal")
        for m in ("sg", "mc"):
            v = metric((ds, m, 32, 0), "probe_metal")
            claim("table1", f"(ours) {METHOD_NAMES[m]}'s light on {ds} lights a rough-metal sphere at least 30 % better "
                  "(si-RMSE) than a constant map" + ("" if None in (v, const) else f" ({v:.3f} vs {const:.3f})"),
                  None if None in (v, const) else v <= 0.7 * const)
            claim("table1", f"(ours) {METHOD_NAMES[m]}'s light on {ds} lights a rough-metal sphere better than SH's",
                  None if None in (v, sh) else v < sh)
    d = [metric(("diffuse", m, 32, 0), "light") for m in ("mc", "sg", "sh")]
    claim("tableC", "on diffuse surfaces SH has the best light score", None if None in d else d[2] <= min(d[:2]))
    sg, shsg, sh = (metric(("glossy", m, 32, 0), "light") for m in ("sg", "sh-sg", "sh"))
    claim("tableD", "diffuse-only shading with SG light predicts light better than with SH",
          None if None in (shsg, sh) else shsg < sh)
    claim("tableD", "but worse than DIB-R++ SG", None if None in (sg, shsg) else sg < shsg)
    e = {k: metric(("glossy", "sg", k, 0), "light") for k in (4, 8, 16, 32)}
    claim("tableE", "fewer lobes give a higher light error (K = 4 worst)",
          None if None in e.values() else e[4] >= max(e[8], e[16], e[32]))
    seeds = [results.get(("glossy", "sg", 32, s)) for s in (0, 1, 2)]
    if all(seeds):
        spread = max(statistics.stdev([r[c] for r in seeds]) / max(statistics.mean([r[c] for r in seeds]), 1e-12)
                     for c in COLUMNS)
        claim("tableF", f"seeds have little effect (largest relative std. dev. {spread:.1%})", spread < 0.1)
    else:
        claim("tableF", "seeds have little effect", None)


def row_cells(r: dict) -> list[str]:
    """The formatted cells of a table row: (ours, paper) per paper column, then ours per light column."""
    cells = []
    for i in range(len(COLUMNS)):
        cells += [format_value(None if r["ours"] is None else r["ours"][i]),
                  format_value(None if r["paper"] is None else r["paper"][i])]
    return cells + [format_value(None if r["light"] is None else r["light"][i], ".1f" if c.endswith("_deg") else ".3f")
                    for i, c in enumerate(LIGHT_COLUMNS)]


def to_markdown(tab: dict) -> str:
    header = ["", *(f"{h} {who}" for h in HEADER for who in ("ours", "paper")), *LIGHT_HEADER, ""]
    rows = [[r["label"], *row_cells(r), r["note"]] for r in tab["rows"]]
    table = markdown_table(header, rows, "l" + "r" * (2 * len(HEADER) + len(LIGHT_HEADER)) + "l")
    return "\n".join([f"**{tab['title']}**", "", table, ""] + [f"- {c}" for c in tab["claims"]]) + "\n"


def to_latex(tab: dict) -> str:
    light = [h.replace("°", "$^\\circ$") for h in LIGHT_HEADER]
    lines = [r"\begin{tabular}{l" + "rr" * len(HEADER) + "r" * len(LIGHT_HEADER) + "}", r"\toprule",
             " & " + " & ".join(rf"\multicolumn{{2}}{{c}}{{{h}}}" for h in HEADER) + " & " + " & ".join(light) + r" \\",
             " & " + " & ".join(["ours & paper"] * len(HEADER)) + " & " + " & ".join(["ours"] * len(light)) + r" \\",
             r"\midrule"]
    for r in tab["rows"]:
        cells = row_cells(r)
        lines.append(r["label"].replace("_", r"\_") + " & " + " & ".join(cells).replace("—", "--") + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return f"% {tab['title']}\n" + "\n".join(lines) + "\n"


def write_tables(eval_dir: Path) -> str:
    tables = build_tables(load_results(eval_dir))
    md = "\n".join(to_markdown(t) for t in tables.values())
    (eval_dir / "tables.md").write_text(md)
    (eval_dir / "tables.tex").write_text("\n".join(to_latex(t) for t in tables.values()))
    for name, tab in tables.items():
        head = ["row", *[f"{c}_ours" for c in COLUMNS], *[f"{c}_paper" for c in COLUMNS], *LIGHT_COLUMNS, "note"]
        write_csv(eval_dir / f"{name}.csv", [dict(zip(head, [r["label"], *(r["ours"] or [""] * len(COLUMNS)),
                                                             *(r["paper"] or [""] * len(COLUMNS)),
                                                             *(r["light"] or [""] * len(LIGHT_COLUMNS)), r["note"]]))
                                             for r in tab["rows"]], head)
    return md
