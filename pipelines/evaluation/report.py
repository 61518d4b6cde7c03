"""A single self-contained HTML page of the evaluation: the paper-style tables beside the figures.

Images are embedded (data URIs), so ``results/eval/report.html`` can be mailed or archived alone.
"""
from __future__ import annotations

import base64
import html
from pathlib import Path

from dibrpp.formatting import format_number
from dibrpp.io import atomic_path

from .tables import RESULT_KEYS, build_tables, column_headers, read_result, row_cells, split_phrase

# fluid: the page, its figures and its loss curves follow the window; wide tables scroll on their own
STYLE = """body{font-family:sans-serif;margin:1em 2%}h1,h2,h3{margin:.8em 0 .3em}
.scroll{overflow-x:auto;max-width:100%}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}td:first-child,th:first-child{text-align:left}
td:first-child{white-space:nowrap}
img{max-width:100%;height:auto}.missing{color:#a00;white-space:nowrap}
.run{display:flex;flex-wrap:wrap;gap:1em;align-items:flex-start;margin:1em 0}
.run>.figure{flex:1 1 640px;min-width:0}.run>.curve{flex:0 1 480px;min-width:0}ul{margin-top:0}"""
RUN_COLUMNS = (("dataset", "dataset"), ("run", "run"), ("shading", "method"), ("variant", "variant"), ("lobes", "K"),
               ("seed", "seed"), ("iteration", "iterations"), ("image_whole", "Image L1 (whole)"),
               ("image_foreground", "Image L1 (fg)"), ("iou", "2D IoU loss"), ("light_ldr", "Light 1-NCC (LDR)"),
               ("light_hdr", "Light 1-NCC (HDR)"), ("texture", "Tex 1-NCC"), ("chamfer", "Chamfer"),
               ("probe_diffuse", "Diffuse probe"), ("probe_metal", "Metal probe"), ("probe_mirror", "Mirror probe"),
               ("colour_deg", "Colour (°)"), ("direction_deg", "Direction (°)"))
METRICS = tuple(k for k, _ in RUN_COLUMNS[7:])


def _img(path: Path) -> str:
    data = base64.b64encode(path.read_bytes()).decode()
    return f'<img alt="{html.escape(path.name)}" src="data:image/png;base64,{data}">'


def _table_html(tab: dict) -> str:
    head = "<tr><th></th>" + "".join(f"<th>{html.escape(h)}</th>" for h in column_headers()) + "<th></th></tr>"
    rows = []
    for r in tab["rows"]:
        cells = row_cells(r)
        note = f'<td class="missing">{html.escape(r["note"])}</td>' if r["note"] else "<td></td>"
        rows.append(f"<tr><td>{html.escape(r['label'])}</td>" + "".join(f"<td>{c}</td>" for c in cells) + note + "</tr>")
    notes = "".join(f"<p><em>{html.escape(n)}</em></p>" for n in tab["notes"])
    claims = "".join(f"<li>{html.escape(c)}</li>" for c in tab["claims"])
    return (f"<h3>{html.escape(tab['title'])}</h3><div class='scroll'><table>{head}{''.join(rows)}</table></div>"
            f"{notes}<ul>{claims}</ul>")


def evaluated_runs(eval_dir: Path) -> list[tuple[Path, dict]]:
    """(result file, result) of every run evaluated into ``eval_dir``, whatever its dataset is called, variants
    and runs outside the paper's tables included; files that are not an evaluation's result are left out."""
    results = ((path, read_result(path, RESULT_KEYS | {"run"})) for path in sorted(Path(eval_dir).glob("*/*.json")))
    return [(path, r) for path, r in results if r is not None]


def _cell(r: dict, key: str) -> str:
    value = Path(r[key]).name if key == "run" else r.get(key, "")
    if key == "lobes" and r.get("shading") not in ("sg", "sh-sg"):
        value = ""
    if isinstance(value, float):
        value = format_number(value, ".3g" if key in ("colour_deg", "direction_deg") else ".4f")
    return html.escape(str(value))


def _all_runs_html(found: list[tuple[Path, dict]]) -> str:
    head = "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for _, h in RUN_COLUMNS) + "</tr>"
    rows = ["<tr>" + "".join(f"<td>{_cell(r, k)}</td>" for k, _ in RUN_COLUMNS) + "</tr>" for _, r in found]
    return f"<div class='scroll'><table>{head}{''.join(rows)}</table></div>"


def _run_html(path: Path, r: dict) -> str:
    name = Path(r["run"]).name
    figure, failures, curve = path.with_suffix(".png"), path.with_name(f"{path.stem}_failures.png"), Path(r["run"]) / "loss.png"
    metrics = ", ".join(f"{c} {r[c]:.4f}" for c in METRICS if isinstance(r.get(c), (int, float)))
    about = ", ".join(f"{k} {r[k]}" for k in ("shading", "variant", "seed", "split", "trained_on") if r.get(k) not in (None, ""))
    views = f", {r['test_views']} test views" if "test_views" in r else ""
    return (f"<h3>{html.escape(r['dataset'])} / {html.escape(name)}</h3>"
            f"<p>{html.escape(about)}: {html.escape(metrics)} (iteration {r['iteration']}{views})</p>"
            "<div class='run'>" + (f"<div class='figure'>{_img(figure)}</div>" if figure.exists() else "")
            + (f"<div class='curve'>{_img(curve)}</div>" if curve.exists() else "") + "</div>"
            + (f"<div class='run'><div class='figure'>{_img(failures)}</div></div>" if failures.exists() else ""))


def write_report(eval_dir: Path) -> Path:
    """results/eval/report.html: the paper-style tables, a table of every evaluated run, the direction figures
    and each run's figures and (when present) loss curve."""
    found = evaluated_runs(eval_dir)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'>"
             "<meta name='viewport' content='width=device-width, initial-scale=1'><title>dibrpp evaluation</title>"
             f"<style>{STYLE}</style></head><body><h1>dibrpp evaluation</h1>",
             f"<p>{html.escape(split_phrase(r for _, r in found).capitalize()) if found else 'No run evaluated'}. "
             "All metrics: lower is better.</p>", "<h2>Tables</h2>"]
    tables, note = build_tables([r for _, r in found])
    parts += ([f"<p>{html.escape(note)}</p>"] if note else []) + [_table_html(t) for t in tables.values()]
    parts.append(f"<h2>Every evaluated run ({len(found)})</h2>" + _all_runs_html(found))
    directions = sorted(eval_dir.glob("direction_*.png"))  # pipelines.evaluate.write_direction_figures
    if directions:
        parts.append("<h2>Dominant-light direction</h2><div class='run'>"
                     + "".join(f"<div class='curve'>{_img(p)}</div>" for p in directions) + "</div>")
    parts.append("<h2>Runs</h2>")
    parts += [_run_html(path, r) for path, r in sorted(found, key=lambda f: (f[1]["dataset"], Path(f[1]["run"]).name))]
    parts.append("</body></html>")
    path = eval_dir / "report.html"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(parts))
    return path
