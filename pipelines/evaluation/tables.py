"""Paper-style tables (Table 1, C, D, E, F) from the per-run metrics that :mod:`pipelines.evaluate` wrote.

Each table puts the paper's numbers beside ours defined like the paper's (image L1 over the whole image; light
1 - NCC on LDR maps, how we read eq. 9: no public code of the paper computes it), then our own columns (image
L1 over the foreground, eq. 9 on HDR maps, the probe-sphere light metrics), a constant env map's scores as a
reference row, the runs that are missing (with the make target that trains them) and whether each of the
paper's claims holds on our data. A set goes into the tables of its kind as its manifest names it (metallic,
glossy, diffuse), whatever its folder is called; tables without any run are left out, and one line says why.
Written as Markdown, LaTeX and CSV.
"""
from __future__ import annotations

import json
import statistics
from collections import Counter
from pathlib import Path

from dibrpp.formatting import markdown_table, write_csv

PAPER_KINDS = ("metallic", "glossy", "diffuse")  # the paper's sets; a manifest's "dataset" names one of them
COLUMNS = ("image_whole", "iou", "light_ldr", "texture")  # ours, each defined like the paper's column beside it
HEADER = ("Image L1", "2D IoU", "Light", "Tex.")
OURS_HEADER = ("ours, whole", "ours", "ours, LDR", "ours")  # how ours is measured: the whole image, LDR maps
# ours only: the paper has no such column
OWN_COLUMNS = ("image_foreground", "light_hdr", "probe_diffuse", "probe_metal", "probe_mirror", "colour_deg",
               "direction_deg")
OWN_HEADER = ("Image L1 (fg)", "Light (HDR)", "Diffuse probe", "Metal probe", "Mirror probe", "Colour (°)",
              "Direction (°)")
PAIRING_NOTE = ("Ours beside the paper's, defined like it: image L1 over the whole image (sRGB clipped to [0, 1], "
                "on black, mean over pixels and channels); light 1 − NCC (eq. 9) on LDR maps (each map divided by "
                "its mean radiance, clipped to [0, 1]), a guess at the paper's definition, which no public code "
                "gives. Ours only: image L1 over the GT foreground, eq. 9 on HDR maps, the probe metrics.")

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
SPLITS = {"test": "test split: unseen objects under unseen env maps",
          "train": "train split: the objects and env maps the runs trained on", "all": "every sample of the set"}
# what each table needs, for the line that says why it is left out
NEEDS = {"table1": "metallic or glossy runs", "tableC": "diffuse runs", "tableD": "glossy SG, SH-SG or SH runs",
         "tableE": "glossy SG runs", "tableF": "glossy SG runs"}
TABLE_NAMES = {"table1": "1", "tableC": "C", "tableD": "D", "tableE": "E", "tableF": "F"}


def dataset_kind(r: dict) -> str | None:
    """The paper set a result's dataset is one of, as its manifest says (a result that does not record it: its
    folder name); None for any other set."""
    kind = r.get("dataset_kind", r["dataset"])
    return kind if kind in PAPER_KINDS else None


PUBLISHED = "published"  # the variant that is the paper's model as published: its rows sit beside the default's
MODELS = (("", ()), (" as published", (PUBLISHED,)))  # (label, run-key suffix): every claim is judged on both


def run_key(r: dict) -> tuple:
    # K only distinguishes SG-lit runs; MC and SH runs key at the default 32; the published model's keys end in its name
    lobes = r["lobes"] if r["shading"] in ("sg", "sh-sg") else 32
    key = (dataset_kind(r), r["shading"], lobes, r["seed"])
    return key + (PUBLISHED,) if r.get("variant") == PUBLISHED else key


RESULT_KEYS = frozenset({"dataset", "shading", "lobes", "seed", "iteration"})  # of pipelines.evaluate's results
RENAMED = {"image": "image_foreground", "light": "light_hdr", "light_constant": "light_hdr_constant"}  # older files


def read_result(path: Path, keys=RESULT_KEYS) -> dict | None:
    """The result JSON at ``path``, or None for any other file (not JSON, unreadable, or without ``keys``);
    metrics an older result file names otherwise under today's names."""
    try:
        r = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if not isinstance(r, dict) or not keys <= r.keys():
        return None
    return {**{new: r[old] for old, new in RENAMED.items() if old in r and new not in r}, **r}


def load_results(eval_dir: Path) -> list[dict]:
    """Every result under ``eval_dir`` (``<dataset>/<run>.json``); other files there are skipped."""
    return list(filter(None, map(read_result, sorted(Path(eval_dir).glob("*/*.json")))))


def paper_sets(results: list[dict]) -> dict[str, str]:
    """{kind: the dataset folder the tables show for it}: of the sets of one kind, the one named like it, else the
    one with the most runs (the others' runs stay in all_runs.md)."""
    folders: dict[str, Counter] = {}
    for r in results:
        if dataset_kind(r) and not r.get("variant"):
            folders.setdefault(dataset_kind(r), Counter())[r["dataset"]] += 1
    return {kind: kind if kind in count else min(count, key=lambda f: (-count[f], f)) for kind, count in folders.items()}


def paper_results(results: list[dict]) -> dict:
    """{run_key: result} of the default model's, the published model's and Table E's lobe counts' results on the
    sets the tables show (the other variants, ablations of the model, are not paper rows)."""
    sets = paper_sets(results)
    return {run_key(r): r for r in results if is_paper_row(r) and dataset_kind(r)
            and dataset_kind(r) in sets and sets[dataset_kind(r)] == r["dataset"]}


def is_paper_row(r: dict) -> bool:
    """The default (no variant), the published model, and the variants the paper's own tables have (K lobes: their
    registry kind, which evaluate writes into the result as ``variant_kind``)."""
    return r.get("variant", "") in ("", PUBLISHED) or r.get("variant_kind") == "paper"


def format_value(v, spec: str = ".3f") -> str:
    """Table cell: 3 decimals by default, a dash where there is no value (None or NaN); a value too small for the
    decimals (Table F's variances) in scientific notation, not as a zero."""
    if v is None or v != v:
        return "—"
    text = format(v, spec)
    return format(v, ".1e") if v != 0 and float(text) == 0 else text


def split_phrase(results) -> str:
    """What the results were evaluated on, for the tables' titles."""
    splits = sorted({r.get("split", "test") for r in results})
    return SPLITS.get(splits[0], splits[0]) if len(splits) == 1 else f"splits {', '.join(splits)} mixed"


class _Builder:
    """The rows of the tables from the results on the paper's sets."""

    def __init__(self, results: list[dict]):
        self.keyed, self.sets = paper_results(results), paper_sets(results)

    def set_label(self, kind: str) -> str:
        folder = self.sets.get(kind, kind)
        return kind if folder == kind else f"{folder} ({kind})"

    def hint(self, kind: str, target: str) -> str:
        """How to fill a missing row: the make target where the set is the default one."""
        folder = self.sets.get(kind, kind)
        return target if folder == kind else f"no such run on {folder}"

    # a row: label, ours (COLUMNS), paper, own (OWN_COLUMNS), note, iterations; reference: not a run's own row (a
    # constant map, a spread over seeds), so it alone does not make a table worth showing
    def row(self, label: str, key: tuple, target: str) -> dict:
        r = self.keyed.get(key)
        return dict(label=label, ours=None if r is None else tuple(r.get(c) for c in COLUMNS), paper=PAPER.get(key[:4]),
                    own=None if r is None else tuple(r.get(c) for c in OWN_COLUMNS), reference=False,
                    note="" if r else f"missing: {self.hint(key[0], target)}",
                    iterations=None if r is None else r["iteration"])

    def constant_row(self, kind: str) -> list[dict]:
        """Reference row: every metric a constant env map has a score on, under the same definition (from any run
        on the set); its direction is the guess "straight above"."""
        r = next((r for k, r in self.keyed.items() if k[0] == kind and "light_hdr_constant" in r), None)
        if r is None:
            return []
        return [dict(label=f"{self.set_label(kind)} / constant light (reference)",
                     ours=tuple(r.get(f"{c}_constant") for c in COLUMNS), paper=None,
                     own=tuple(r.get(f"{c}_constant") for c in OWN_COLUMNS), reference=True,
                     note="a constant env map (direction: straight above)", iterations=None)]


def build_tables(results: list[dict]) -> tuple[dict[str, dict], str]:
    """({table id: {title, rows, notes, claims}} of the tables that hold a run, and one line saying which sets and
    tables are left out and why ("" where none is)) from every result of an evaluation folder."""
    b = _Builder(results)
    split = split_phrase(b.keyed.values()) if b.keyed else "test split"
    t = {}
    rows = []
    for ds in ("metallic", "glossy"):
        if ds in b.sets:
            rows += [b.row(f"{b.set_label(ds)} / {METHOD_NAMES[m]}", (ds, m, 32, 0), f"make train-{ds}")
                     for m in ("mc", "sg", "sh")] + published_rows(b, ds) + b.constant_row(ds)
    t["table1"] = dict(title=f"Table 1: metallic and glossy surfaces ({split}; lower is better)", rows=rows)
    t["tableC"] = dict(title=f"Table C: {b.set_label('diffuse')} surfaces ({split})", rows=[
        b.row(METHOD_NAMES[m], ("diffuse", m, 32, 0), "make train-diffuse") for m in ("mc", "sg", "sh")]
        + published_rows(b, "diffuse") + b.constant_row("diffuse"))
    glossy = b.set_label("glossy")
    t["tableD"] = dict(title=f"Table D: shading methods on {glossy} surfaces ({split})", rows=[
        b.row(METHOD_NAMES[m], ("glossy", m, 32, 0), target) for m, target in
        (("sg", "make train-glossy"), ("sh-sg", "make train-ablations"), ("sh", "make train-glossy"))]
        + b.constant_row("glossy"))
    t["tableE"] = dict(title=f"Table E: number of SG lobes K ({glossy}; {split})", rows=[
        b.row(f"K = {k}", ("glossy", "sg", k, 0), "make train-glossy" if k == 32 else "make train-ablations")
        for k in (4, 8, 16, 32)] + b.constant_row("glossy"))
    seeds = [b.row(f"DIB-R++ SG, seed {s}", ("glossy", "sg", 32, s), "make train-glossy") for s in (0, 1, 2)]
    published = [b.row(f"DIB-R++ SG as published, seed {s}", ("glossy", "sg", 32, s, PUBLISHED),
                       "make train-published") for s in (0, 1, 2)]
    t["tableF"] = dict(title=f"Table F: training variance over three seeds ({glossy}, SG; {split})",
                       rows=seeds + _spread(seeds) + published + _spread(published, "as published: ")
                       + b.constant_row("glossy"))
    shown = {name: tab for name, tab in t.items() if any(r["ours"] for r in tab["rows"] if not r["reference"])}
    for tab in shown.values():
        tab["notes"], tab["claims"] = [PAIRING_NOTE], []
    _claims(shown, b.keyed)
    return shown, coverage_note(results, b.sets, [name for name in t if name not in shown])


def published_rows(b: "_Builder", kind: str) -> list[dict]:
    """The published model's SG and MC rows of a set (``--variant published``), beside the default's."""
    return [b.row(f"{b.set_label(kind)} / {METHOD_NAMES[m]} as published", (kind, m, 32, 0, PUBLISHED),
                  "make train-published") for m in ("mc", "sg")]


def coverage_note(results: list[dict], sets: dict[str, str], left_out: list[str]) -> str:
    """One line: the sets whose runs are in all_runs.md only (not one of the paper's; or another set of a kind
    whose tables show one set), Table 1's kinds without runs, and the tables left out for want of runs."""
    parts = []
    others = sorted({r["dataset"] for r in results if not dataset_kind(r)})
    if others:
        parts.append(f"{', '.join(others)}: not one of the paper's {', '.join(PAPER_KINDS)} sets (the manifest's "
                     "`dataset`), in all_runs.md only")
    extra = sorted({(r["dataset"], dataset_kind(r)) for r in results
                    if dataset_kind(r) in sets and r["dataset"] != sets[dataset_kind(r)]})
    if extra:
        parts.append(f"{', '.join(f'{f} ({kind}, the tables show {sets[kind]})' for f, kind in extra)}: in "
                     "all_runs.md only")
    if "table1" not in left_out:
        parts += [f"Table 1 without {ds} rows (no {ds} run)" for ds in ("metallic", "glossy") if ds not in sets]
    if left_out:
        parts.append(f"Table{'s' if len(left_out) > 1 else ''} {', '.join(TABLE_NAMES[n] for n in left_out)} left out "
                     f"(no run of theirs here: {'; '.join(dict.fromkeys(NEEDS[n] for n in left_out))})")
    return f"Paper-style tables: {'; '.join(parts)}." if parts else ""


# Table F's summary rows as printed; its "variance" row matches the standard deviation of its three rows.
PAPER_SPREAD = {"mean": (0.025, 0.060, 0.091, 0.142), "variance": None, "std. dev.": (0.000, 0.002, 0.000, 0.001)}


def _spread(seeds: list[dict], prefix: str = "") -> list[dict]:
    got = [r["ours"] for r in seeds if r["ours"] is not None]

    def stat(fn, vals):
        if len(vals) < 2:
            return None
        columns = [[v[i] for v in vals] for i in range(len(COLUMNS))]
        return tuple(fn(c) if None not in c else None for c in columns)  # a column an older result lacks: none

    return [dict(label=prefix + name, ours=stat(fn, got), paper=PAPER_SPREAD[name], own=None, reference=True,
                 note="" if len(got) == 3 else f"over {len(got)} of 3 seeds", iterations=None)
            for name, fn in (("mean", statistics.mean), ("variance", statistics.variance), ("std. dev.", statistics.stdev))]


def _claims(t: dict, results: dict) -> None:
    """The paper's claims, each judged on the metric defined like the paper's (light: eq. 9 on LDR maps), and ours
    on the probes; a claim goes to its table only where that table is shown."""
    def metric(key, col):
        r = results.get(key)
        return None if r is None else r.get(col)

    def claim(table, text, holds):
        if table in t:
            verdict = "cannot be tested yet (runs missing)" if holds is None else ("holds" if holds else "does NOT hold")
            t[table]["claims"].append(f"{text}: {verdict} on our data.")

    def below(a, b):
        return None if a is None or b is None else a < b

    def named(m, label):  # SH is DIB-R's baseline under either model's label
        return METHOD_NAMES[m] + ("" if m == "sh" else label)

    kinds = {k[0] for k in results}
    for label, suffix in MODELS:  # each claim on the default, then on the published model
        for ds in ("metallic", "glossy"):
            if ds not in kinds:
                continue
            sh = metric((ds, "sh", 32, 0), "light_ldr")
            for m in ("sg", "mc"):
                claim("table1", f"{named(m, label)} predicts light better than SH on {ds} surfaces (LDR eq. 9)",
                      below(metric((ds, m, 32, 0) + suffix, "light_ldr"), sh))
        for ds, table in (("metallic", "table1"), ("glossy", "table1"), ("diffuse", "tableC")):
            runs = [r for k, r in results.items() if k[0] == ds and k[1] in ("mc", "sg", "sh")
                    and k[2:] == (32, 0) + suffix]
            for col, metric_name in (("light_ldr", "LDR"), ("light_hdr", "HDR")):
                scored = [r for r in runs if r.get(col) is not None and r.get(f"{col}_constant") is not None]
                if scored:
                    best = min(scored, key=lambda r: r[col])
                    claim(table, f"on {ds} surfaces the best predicted light{label} by eq. 9 on {metric_name} maps "
                          f"({named(best['shading'], label)}, {best[col]:.3f}) beats a constant env map "
                          f"({best[col + '_constant']:.3f})", best[col] < best[col + "_constant"])
        for ds in ("metallic", "glossy"):
            if ds not in kinds:
                continue
            const = next((r["probe_metal_constant"] for k, r in results.items()
                          if k[0] == ds and "probe_metal_constant" in r), None)
            sh = metric((ds, "sh", 32, 0), "probe_metal")
            for m in ("sg", "mc"):
                v = metric((ds, m, 32, 0) + suffix, "probe_metal")
                claim("table1", f"(ours) {named(m, label)}'s light on {ds} lights a rough-metal sphere at least 30 % "
                      "better (si-RMSE) than a constant map" + ("" if None in (v, const) else f" ({v:.3f} vs {const:.3f})"),
                      None if None in (v, const) else v <= 0.7 * const)
                claim("table1", f"(ours) {named(m, label)}'s light on {ds} lights a rough-metal sphere better than SH's",
                      below(v, sh))
        d = [metric(("diffuse", m, 32, 0) + suffix, "light_ldr") for m in ("mc", "sg")] + \
            [metric(("diffuse", "sh", 32, 0), "light_ldr")]
        claim("tableC", f"on diffuse surfaces SH has a better light score than {named('sg', label)} and "
              f"{named('mc', label)} (LDR eq. 9)", None if None in d else d[2] <= min(d[:2]))
        seeds = [results.get(("glossy", "sg", 32, s) + suffix) for s in (0, 1, 2)]
        if all(seeds) and all(r.get(c) is not None for r in seeds for c in COLUMNS):
            spread = max(statistics.stdev([r[c] for r in seeds]) / max(statistics.mean([r[c] for r in seeds]), 1e-12)
                         for c in COLUMNS)
            claim("tableF", f"seeds have little effect{label} (largest relative std. dev. {spread:.1%})", spread < 0.1)
        else:
            claim("tableF", f"seeds have little effect{label}", None)
    sg, shsg, sh = (metric(("glossy", m, 32, 0), "light_ldr") for m in ("sg", "sh-sg", "sh"))
    claim("tableD", "diffuse-only shading with SG light predicts light better than with SH (LDR eq. 9)", below(shsg, sh))
    claim("tableD", "but worse than DIB-R++ SG", below(sg, shsg))
    e = {k: metric(("glossy", "sg", k, 0), "light_ldr") for k in (4, 8, 16, 32)}
    claim("tableE", "fewer lobes give a higher light error (K = 4 worst; LDR eq. 9)",
          None if None in e.values() else e[4] >= max(e[8], e[16], e[32]))


def row_cells(r: dict) -> list[str]:
    """The formatted cells of a table row: (ours, paper) per paper column, then ours per column of our own."""
    cells = []
    for i in range(len(COLUMNS)):
        cells += [format_value(None if r["ours"] is None else r["ours"][i]),
                  format_value(None if r["paper"] is None else r["paper"][i])]
    return cells + [format_value(None if r["own"] is None else r["own"][i], ".1f" if c.endswith("_deg") else ".3f")
                    for i, c in enumerate(OWN_COLUMNS)]


def column_headers() -> list[str]:
    """The header of every cell :func:`row_cells` gives."""
    return [*(f"{h} {who}" for h, ours in zip(HEADER, OURS_HEADER) for who in (ours, "paper")), *OWN_HEADER]


def to_markdown(tab: dict) -> str:
    header = ["", *column_headers(), ""]
    rows = [[r["label"], *row_cells(r), r["note"]] for r in tab["rows"]]
    table = markdown_table(header, rows, "l" + "r" * (2 * len(HEADER) + len(OWN_HEADER)) + "l")
    notes = [f"*{n}*" for n in tab["notes"]]
    return "\n".join([f"**{tab['title']}**", "", table, "", *notes, ""] + [f"- {c}" for c in tab["claims"]]) + "\n"


def to_latex(tab: dict) -> str:
    own = [h.replace("°", "$^\\circ$") for h in OWN_HEADER]
    lines = [r"\begin{tabular}{l" + "rr" * len(HEADER) + "r" * len(OWN_HEADER) + "}", r"\toprule",
             " & " + " & ".join(rf"\multicolumn{{2}}{{c}}{{{h}}}" for h in HEADER) + " & " + " & ".join(own) + r" \\",
             " & " + " & ".join(f"{ours} & paper" for ours in OURS_HEADER) + " & " + " & ".join(["ours"] * len(own)) + r" \\",
             r"\midrule"]
    for r in tab["rows"]:
        cells = row_cells(r)
        lines.append(r["label"].replace("_", r"\_") + " & " + " & ".join(cells).replace("—", "--") + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "".join(f"% {line}\n" for line in (tab["title"], *tab["notes"])) + "\n".join(lines) + "\n"


def write_tables(eval_dir: Path) -> str:
    """tables.md, tables.tex and table<id>.csv of every result under ``eval_dir``; the Markdown, the line on what is
    left out first."""
    tables, note = build_tables(load_results(eval_dir))
    md = "\n".join([*([note, ""] if note else []), *(to_markdown(t) for t in tables.values())])
    (eval_dir / "tables.md").write_text(md)
    (eval_dir / "tables.tex").write_text("\n".join([*([f"% {note}"] if note else []),
                                                    *(to_latex(t) for t in tables.values())]))
    head = ["row", *[f"{c}_ours" for c in COLUMNS], *[f"{c}_paper" for c in COLUMNS], *OWN_COLUMNS, "note"]
    for name in TABLE_NAMES:
        path = eval_dir / f"{name}.csv"
        if name not in tables:  # a table left out leaves no file of an earlier evaluation behind
            path.unlink(missing_ok=True)
            continue
        write_csv(path, [dict(zip(head, [r["label"], *(r["ours"] or [""] * len(COLUMNS)),
                                         *(r["paper"] or [""] * len(COLUMNS)), *(r["own"] or [""] * len(OWN_COLUMNS)),
                                         r["note"]])) for r in tables[name]["rows"]], head)
    return md
