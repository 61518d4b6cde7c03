"""Output helpers shared by the pipelines, benchmarks and studies: Markdown tables, CSV files, figures.

One way to write each kind of result, so every table and figure looks and is written alike:

- :func:`format_number`: a number with a format spec, a placeholder for a missing value;
- :func:`markdown_table`: a GitHub Markdown table from a header and rows of cells;
- :func:`write_csv`: rows of dicts as a CSV file (written atomically);
- :func:`pyplot` and :func:`save_figure`: matplotlib on the Agg backend (no display needed) and an atomic
  PNG write that closes the figure.
"""
from __future__ import annotations

import csv
import numbers
from pathlib import Path
from typing import Iterable, Sequence

from .io import atomic_path

MISSING = "—"  # what a table shows where a value is missing
ALIGN_RULES = {"l": "---", "r": "---:", "c": ":---:"}  # "l" is Markdown's default (left in every renderer)


def format_number(value, spec: str, missing: str = MISSING) -> str:
    """``format(value, spec)`` for a real number (int, float, numpy scalar; not bool); ``missing`` for anything
    else (None, an empty cell, a status string)."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return format(value, spec)
    return missing


def markdown_table(header: Sequence, rows: Iterable[Sequence], align: str | Sequence[str] = "l",
                   float_spec: str | None = None) -> str:
    """A Markdown table: ``| a | b |`` lines, the rule line after the header, no trailing newline.

    ``align``: one letter for every column or one per column (a string like ``"llrr"`` or a list):
    ``l`` (the rule ``---``), ``r`` (``---:``) or ``c`` (``:---:``). Cells are written with ``str``, except
    floats when ``float_spec`` is given (``format(v, float_spec)``); format other numbers before passing them
    (:func:`format_number`)."""
    header = list(header)
    letters = list(align) if len(align) == len(header) else list(align) * len(header) if len(align) == 1 else None
    if letters is None or any(a not in ALIGN_RULES for a in letters):
        raise ValueError(f"align {align!r}: give one of l, r, c for all {len(header)} columns or one per column")

    def cell(v) -> str:
        return format(v, float_spec) if float_spec and isinstance(v, float) else str(v)

    def line(cells) -> str:
        return "| " + " | ".join(cell(c) for c in cells) + " |"

    lines = [line(header), "|" + "|".join(ALIGN_RULES[a] for a in letters) + "|"]
    for r in rows:
        r = list(r)
        if len(r) != len(header):
            raise ValueError(f"a row of {len(r)} cells in a table of {len(header)} columns: {r}")
        lines.append(line(r))
    return "\n".join(lines)


def write_csv(path, rows: Iterable[dict], fieldnames: Sequence[str] | None = None, extrasaction: str = "raise") -> Path:
    """Rows of dicts as a CSV file with a header (``fieldnames``: the first row's keys by default); missing keys
    are empty cells, extra keys raise unless ``extrasaction="ignore"``. Atomic: a reader never sees half a file."""
    rows = list(rows)
    fieldnames = list(fieldnames if fieldnames is not None else (rows[0] if rows else []))
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fieldnames, extrasaction=extrasaction)
            w.writeheader()
            w.writerows(rows)
    return path


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (renders to files; needs no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 100, tight: bool = True) -> Path:
    """Write ``fig`` to ``path`` (format from the suffix, PNG by default) atomically, then close it.
    ``tight``: ``fig.tight_layout()`` first, as every figure of the project does."""
    plt = pyplot()
    path = Path(path)
    try:
        if tight:
            fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return path
