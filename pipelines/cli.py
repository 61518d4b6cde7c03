"""What the pipelines' command lines share: a parser whose errors are one ``error:`` line (exit status 2) and
whose ``--help`` shows every option's default, and argument types that name what they expect."""
from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

from dibrpp.io import DataError


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
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def finite_float(text: str) -> float:
    return _number(text, float)


def non_negative_float(text: str) -> float:
    value = _number(text, float)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {value}")
    return value


def unit_rgb(text: str) -> tuple[float, float, float]:
    """R,G,B with each value in [0, 1]."""
    try:
        values = tuple(_number(x, float) for x in text.split(","))
    except argparse.ArgumentTypeError:
        values = ()
    if len(values) != 3 or not all(0 <= v <= 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected R,G,B with each value in [0, 1] (e.g. 1,1,1), got {text!r}")
    return values



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
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise DataError(f"{flag} {out}: cannot write into {folder} ({e.strerror}); choose another folder or "
                        "change its permissions") from None
