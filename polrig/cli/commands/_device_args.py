"""Arguments and output shared by the commands: the single-device operator commands (move,
home, light, snap, devices) use the ``--config``/``--timeout`` arguments; raw data is never
replaced without ``--overwrite`` (:func:`refuse_existing`); an axis command interrupted by
Ctrl-C or SIGTERM stops its axis (:func:`polrig.acquisition.hal.stopped_when_interrupted`,
with :func:`stop_failed`). Argument types and the
other path checks are in :mod:`polrig.formats.argcheck`."""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
from typing import TYPE_CHECKING, Iterable

from polrig.formats.argcheck import positive_float

if TYPE_CHECKING:
    from polrig.acquisition.hal import DeviceInfo


def add_config_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=pathlib.Path, default=None, metavar="FILE",
                   help="rig configuration TOML (default: the simulated rig)")


def add_timeout_argument(p: argparse.ArgumentParser, default_s: float) -> None:
    p.add_argument("--timeout", type=positive_float, default=default_s, metavar="S",
                   help=f"give up after S seconds (> 0; default {default_s:g})")


def stop_failed(name: str, exc: BaseException) -> None:
    """One line on stderr when stopping an interrupted axis failed
    (:func:`polrig.acquisition.hal.stopped_when_interrupted`'s ``failed``): the interruption
    is still reported, and the operator learns the axis may still be moving."""
    print(f"polrig: could not stop the {name} ({exc}): it may still be moving", file=sys.stderr)


def identity(info: DeviceInfo) -> str:
    """``ELL14 serial 11400123, firmware 23 on /dev/ttyUSB0`` (what the device says)."""
    parts = [info.model or info.driver]
    if info.serial:
        parts.append(f"serial {info.serial}")
    if info.firmware:
        parts.append(f"firmware {info.firmware}")
    text = ", ".join(parts)
    return f"{text} on {info.port}" if info.port else text


def refuse_existing(paths: Iterable[pathlib.Path], flag: str = "--out",
                    what: str = "file") -> None:
    """:class:`FileExistsError` naming the first of ``paths`` that exists (raw data is never
    replaced without ``--overwrite``)."""
    for p in paths:
        if os.path.lexists(p):
            raise FileExistsError(f"{flag}: {p} already exists ({what}); choose another name "
                                  f"or pass --overwrite")
