"""What the pipelines' command lines share: a parser whose errors are one ``error:`` line (exit status 2) and
whose ``--help`` shows every option's default, and argument types that name what they expect. One copy for every
command line of the project: :mod:`dibrpp.cli_args` (dibrpp, datagen and the studies cannot import ``pipelines``)."""
from __future__ import annotations

from dibrpp.cli_args import (HelpFormatter, Parser, check_output_folder, finite_float, non_negative_float,
                             non_negative_int, positive_float, positive_int, unit_rgb)

__all__ = ["HelpFormatter", "Parser", "check_output_folder", "finite_float", "non_negative_float", "non_negative_int",
           "positive_float", "positive_int", "unit_rgb"]
