"""What every command line of the project shares (dibrpp's own, datagen, the pipelines, studies, benchmarks): a parser
whose errors are one ``error:`` line (exit status 2) and whose ``--help`` shows every option's default, argument
types that name what they expect (and refuse NaN / Inf), and a cheap check of an output folder before the work."""
from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

from .io import DataError


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The module doc as written, and "(default: ...)" after each option that has a default and does not
    already say it."""

    def _get_help_string(self, action):
        text = action.help or ""
        if any(action.default is v for v in (None, False, argparse.SUPPRESS)) or "default" in text.lower():
            return text
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``error: <what is wrong> (see --help)`` and exit status 2."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        self.exit(2, f"error: {message} (see --help)\n")


def _number(text: str, kind) -> float:
    try:
        value = kind(text)
    except ValueError:
        what = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _checked(text: str, kind, ok, what: str):
    value = _number(text, kind)
    if not ok(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {value}")
    return value


def positive_int(text: str) -> int:
    return _checked(text, int, lambda v: v >= 1, "a positive integer")


def non_negative_int(text: str) -> int:
    return _checked(text, int, lambda v: v >= 0, "a non-negative integer")


def int_in(lo: int, hi: int):
    """An argument type: an integer in lo..hi (the error names both bounds)."""
    def parse(text: str) -> int:
        return _checked(text, int, lambda v: lo <= v <= hi, f"an integer in {lo}..{hi}")
    return parse


def finite_float(text: str) -> float:
    return _number(text, float)


def float_in(lo: float, hi: float, open_low: bool = False):
    """An argument type: a number in [lo, hi] (or (lo, hi] with ``open_low``; the error names both bounds)."""
    def parse(text: str) -> float:
        ok = (lambda v: lo < v <= hi) if open_low else (lambda v: lo <= v <= hi)
        return _checked(text, float, ok, f"a number in {'(' if open_low else '['}{lo:g}, {hi:g}]")
    return parse


def non_negative_float(text: str) -> float:
    return _checked(text, float, lambda v: v >= 0, "a number >= 0")


def positive_float(text: str) -> float:
    return _checked(text, float, lambda v: v > 0, "a number > 0")


def unit_fraction(text: str) -> float:
    """A share: a number in [0, 1]."""
    return _checked(text, float, lambda v: 0 <= v <= 1, "a number in [0, 1]")


def _numbers(text: str) -> tuple[float, ...]:
    """Finite numbers separated by commas; () if any is not one."""
    try:
        return tuple(_number(x, float) for x in text.split(","))
    except argparse.ArgumentTypeError:
        return ()


def unit_rgb(text: str) -> tuple[float, float, float]:
    """R,G,B with each value in [0, 1]."""
    values = _numbers(text)
    if len(values) != 3 or not all(0 <= v <= 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected R,G,B with each value in [0, 1] (e.g. 1,1,1), got {text!r}")
    return values


def elevation_list(text: str) -> list[float]:
    """DEG[,DEG...]: camera elevations in degrees, each strictly between -90 and 90."""
    values = list(_numbers(text))
    if not values or not all(-90 < v < 90 for v in values):
        raise argparse.ArgumentTypeError(f"expected elevations in degrees separated by commas, each strictly between "
                                         f"-90 and 90 (e.g. 12,27,42), got {text!r}")
    return values


def check_writable(flag: str, out: Path, folder: Path) -> None:
    """A :class:`DataError` naming ``flag`` and ``out`` unless this process can create a file in ``folder``."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise DataError(f"{flag} {out}: cannot write into folder {folder} ({e.strerror}); choose another folder or "
                        "change its permissions") from None


def check_output_folder(flag: str, out: Path) -> None:
    """``out`` is a folder (made later if missing) that this process can write into; a :class:`DataError` naming
    ``flag`` and the folder otherwise. Cheap: call it before the long work, not after."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{flag} {out}: is a file, not a folder; give a folder for the results (made if missing)")
    folder = out
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise DataError(f"{flag} {out}: {folder} is a file, not a folder; choose another {flag}")
    check_writable(flag, out, folder)
