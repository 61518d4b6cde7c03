"""A single self-contained HTML page of the evaluation: the paper-style tables beside the figures.

Images are embedded (data URIs), so ``results/eval/report.html`` can be mailed or archived alone.
"""
from __future__ import annotations

import base64
import html
from pathlib import Path

from dibrpp.io import atomic_path

from .tables import COLUMNS, HEADER, LIGHT_COLUMNS, LIGHT_HEADER, build_tables, load_results, row_cells

STYLE = """body{font-family:sans-serif;margin:2em;max-width:1500px}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}td:first-child,th:first-child{text-align:left}
.missing{color:#a00}.run{display:flex;gap:1em;align-items:flex-start;margin:1em 0}.run img{max-width:900px}
.curve img{max-width:480px}ul{margin-top:0}"""


def _img(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}">'


def _table_html(tab: dict) -> str:
    head = ("<tr><th></th>" + "".join(f"<th>{h} ours</th><th>{h} paper</th>" for h in HEADER)
            + "".join(f"<th>{html.escape(h)}</th>" for h in LIGHT_HEADER) + "<th></th></tr>")
    rows = []
    for r in tab["rows"]:
        cells = row_cells(r)
        note = f'<td class="missing">{html.escape(r["note"])}</td>' if r["note"] else "<td></td>"
        rows.append(f"<tr><td>{html.escape(r['label'])}</td>" + "".join(f"<td>{c}</td>" for c in cells) + note + "</tr>")
    claims = "".join(f"<li>{html.escape(c)}</li>" for c in tab["claims"])
    return f"<h3>{html.escape(tab['title'])}</h3><table>{head}{''.join(rows)}</table><ul>{claims}</ul>"


def write_report(eval_dir: Path) -> Path:
    """results/eval/report.html from the per-run metrics, figures and (when present) loss curves."""
    results = load_results(eval_dir)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>dibrpp evaluation</title>"
             f"<style>{STYLE}</style></head><body><h1>dibrpp evaluation</h1>",
             "<p>Test split: unseen objects under unseen environment maps. All metrics: lower is better.</p>",
             "<h2>Tables</h2>"]
    parts += [_table_html(t) for t in build_tables(results).values()]
    directions = sorted(eval_dir.glob("direction_*.png"))  # pipelines.evaluate.write_direction_figures
    if directions:
        parts.append("<h2>Dominant-light direction</h2><div class='run'>" + "".join(_img(p) for p in directions) + "</div>")
    parts.append("<h2>Runs</h2>")
    for key in sorted(results):
        r = results[key]
        figure = eval_dir / r["dataset"] / f"{Path(r['run']).name}.png"
        failures = figure.with_name(f"{Path(r['run']).name}_failures.png")
        curve = Path(r["run"]) / "loss.png"
        metrics = ", ".join(f"{c} {r[c]:.4f}" for c in (*COLUMNS, "chamfer", *LIGHT_COLUMNS) if c in r)
        parts.append(f"<h3>{html.escape(r['dataset'])} / {html.escape(Path(r['run']).name)}</h3>"
                     f"<p>{html.escape(metrics)} (iteration {r['iteration']}, {r['test_views']} test views)</p>"
                     "<div class='run'>" + (_img(figure) if figure.exists() else "")
                     + (f"<div class='curve'>{_img(curve)}</div>" if curve.exists() else "") + "</div>"
                     + (f"<div class='run'>{_img(failures)}</div>" if failures.exists() else ""))
    parts.append("</body></html>")
    path = eval_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(parts))
    return path
