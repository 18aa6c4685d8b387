"""Command-line options checked where they are parsed.

:class:`OptionParser` makes ``argparse``'s usage errors one line and exit 2, like every
other user mistake (:mod:`edges.command`); :func:`number`, :func:`integer` and
:func:`path_text` are ``type=`` functions that refuse ``nan``, ``inf``, values out of
range and empty paths, naming the bound.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable
from typing import Any

from edges.command import one_line


class OptionParser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line, ``PROG: error: MESSAGE (see PROG
    --help)``, exit 2, like every other user mistake (its subcommands' parsers too)."""

    def error(self, message: str) -> Any:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see {self.prog} --help)\n")


def number(
    lo: float | None = None, *, above: bool = False, hi: float | None = None
) -> Callable[[str], float]:
    """An ``argparse`` ``type=``: a finite float >= ``lo`` (> ``lo`` when ``above``), <=
    ``hi``; ``nan``, ``inf`` and values outside are refused naming the bound."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if lo is not None and (v <= lo if above else v < lo):
            raise argparse.ArgumentTypeError(
                f"must be {'>' if above else '>='} {lo:g}, got {text!r}"
            )
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be <= {hi:g}, got {text!r}")
        return v

    parse.__name__ = "number"
    return parse


def integer(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An ``argparse`` ``type=``: an integer in ``lo..hi``."""

    def parse(text: str) -> int:
        if not re.fullmatch(r"\s*[+-]?[0-9]+\s*", text):
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
        v = int(text)
        if v < lo or (hi is not None and v > hi):
            rng = f">= {lo}" if hi is None else f"{lo}-{hi}"
            raise argparse.ArgumentTypeError(f"must be {rng}, got {text!r}")
        return v

    parse.__name__ = "integer"
    return parse


def path_text(text: str) -> str:
    """An ``argparse`` ``type=``: a path, not empty."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return text
