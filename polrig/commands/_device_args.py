"""Arguments, argument types and path checks shared by the commands (the single-device
operator commands move, home, light, snap, devices use the ``--config``/``--timeout``
arguments; every command may use the argparse ``type=`` helpers and the output checks).

The ``type=`` helpers reject what no command can use (NaN, infinities, negative or zero
values, a zero vector) while argparse parses the command line, so a bad number is an exit-2
usage error naming the option before anything is read, opened or computed.
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
from typing import Callable, Iterable

from polrig.errors import ConfigError
from polrig.hal import DeviceInfo


def add_config_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=pathlib.Path, default=None, metavar="FILE",
                   help="rig configuration TOML (default: the simulated rig)")


def add_timeout_argument(p: argparse.ArgumentParser, default_s: float) -> None:
    p.add_argument("--timeout", type=positive_float, default=default_s, metavar="S",
                   help=f"give up after S seconds (> 0; default {default_s:g})")


def identity(info: DeviceInfo) -> str:
    """``ELL14 serial 11400123, firmware 23 on /dev/ttyUSB0`` (what the device says)."""
    parts = [info.model or info.driver]
    if info.serial:
        parts.append(f"serial {info.serial}")
    if info.firmware:
        parts.append(f"firmware {info.firmware}")
    text = ", ".join(parts)
    return f"{text} on {info.port}" if info.port else text


# -- argparse type= helpers ------------------------------------------------------------------
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
    configuration's axes, :func:`polrig.config.axis_problem`)."""
    from polrig.config import axis_problem

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


def refuse_existing(paths: Iterable[pathlib.Path], flag: str = "--out",
                    what: str = "file") -> None:
    """:class:`FileExistsError` naming the first of ``paths`` that exists (raw data is never
    replaced without ``--overwrite``)."""
    for p in paths:
        if os.path.lexists(p):
            raise FileExistsError(f"{flag}: {p} already exists ({what}); choose another name "
                                  f"or pass --overwrite")
