"""Arguments and output shared by the commands: the single-device operator commands (move,
home, light, snap, devices) use the ``--config``/``--timeout`` arguments; raw data is never
replaced without ``--overwrite`` (:func:`refuse_existing`); an axis command interrupted by
Ctrl-C or SIGTERM stops its axis (:func:`stopped_when_interrupted`). Argument types and the
other path checks are in :mod:`polrig.formats.argcheck`."""

from __future__ import annotations

import argparse
import contextlib
import os
import pathlib
import sys
from typing import TYPE_CHECKING, Iterable, Iterator

from polrig.errors import PolrigError
from polrig.formats.argcheck import positive_float

if TYPE_CHECKING:
    from polrig.acquisition.hal import DeviceInfo, RotationStage


def add_config_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=pathlib.Path, default=None, metavar="FILE",
                   help="rig configuration TOML (default: the simulated rig)")


def add_timeout_argument(p: argparse.ArgumentParser, default_s: float) -> None:
    p.add_argument("--timeout", type=positive_float, default=default_s, metavar="S",
                   help=f"give up after S seconds (> 0; default {default_s:g})")


@contextlib.contextmanager
def stopped_when_interrupted(axis: RotationStage, name: str) -> Iterator[None]:
    """The body drives ``axis`` (``name``: ``stage`` or ``turntable``); when it is interrupted
    (Ctrl-C, or SIGTERM, which the CLI raises as ``KeyboardInterrupt``) the axis is stopped
    (its driver's ``stop()``) before the interruption goes on, so nothing keeps moving after
    the command has exited. A stop that fails is one line on stderr (the interruption is
    still reported); a second interruption during the stop ends it."""
    try:
        yield
    except KeyboardInterrupt:
        try:
            axis.stop()
        except (PolrigError, OSError) as exc:  # the interruption is the news; say why
            print(f"polrig: could not stop the {name} ({exc}): it may still be moving",
                  file=sys.stderr)
        raise


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
