"""Command-line argument types and output-path checks shared by every command line: ``polrig``'s
commands and the ``python -m polrig.models.*`` tools (a core module, so that the tools below the app
layer need not import it).

The ``type=`` helpers reject what no command can use (NaN, infinities, negative or zero
values, a zero vector) while argparse parses the command line, so a bad number is an exit-2
usage error naming the option before anything is read, opened or computed. The path checks
run before any work and create nothing.
"""

from __future__ import annotations

import argparse
import math
import pathlib
from typing import Callable

from polrig.errors import ConfigError


def finite_float(text: str) -> float:
    """A finite number (``nan``, ``inf`` refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    """An argparse type: an integer in ``lo..hi``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in {lo}..{hi}, got {text!r}")
        return value
    return parse


def axis_vector(text: str) -> tuple[float, float, float]:
    """``x,y,z``: three finite numbers, not all zero (a direction; the same rule as the rig
    configuration's axes, :func:`polrig.formats.config.axis_problem`)."""
    from polrig.formats.config import axis_problem  # here: config needs NumPy, parser start-up does not

    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated numbers x,y,z, got "
                                         f"{text!r}")
    problem = axis_problem(parts)
    if problem:
        raise argparse.ArgumentTypeError(f"{problem}, got {text!r}")
    return tuple(parts)  # type: ignore[return-value]


# -- output paths ----------------------------------------------------------------------------
def check_output_file(path: pathlib.Path, flag: str = "--out") -> pathlib.Path:
    """:class:`ConfigError` (one line naming ``path``) unless ``path`` can be written as a file:
    it is not a folder and its folder exists. Call before any work."""
    path = pathlib.Path(path)
    if path.is_dir():
        raise ConfigError(f"{flag} {path} is a directory; give a file name")
    parent = path.parent
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist"
        raise ConfigError(f"{flag} folder {parent} {what}")
    return path


def check_output_folder(out: str | pathlib.Path, flag: str = "--out") -> pathlib.Path:
    """``out`` as a folder path that can be made: refuses (``ConfigError``, one line naming
    ``flag``) a file at ``out`` or a file where one of its parent folders would be. Creates
    nothing; call before any work."""
    out = pathlib.Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{flag} {out} is a file, not a folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(f"{flag} {out}: {parent} is a file, not a folder")
            break
    return out
