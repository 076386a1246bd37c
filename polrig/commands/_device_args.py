"""Arguments and output shared by the single-device operator commands (move, home, light,
snap, devices)."""

from __future__ import annotations

import argparse
import pathlib

from polrig.hal import DeviceInfo


def add_config_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=pathlib.Path, default=None, metavar="FILE",
                   help="rig configuration TOML (default: the simulated rig)")


def add_timeout_argument(p: argparse.ArgumentParser, default_s: float) -> None:
    p.add_argument("--timeout", type=float, default=default_s, metavar="S",
                   help=f"give up after S seconds (default {default_s:g})")


def identity(info: DeviceInfo) -> str:
    """``ELL14 serial 11400123, firmware 23 on /dev/ttyUSB0`` (what the device says)."""
    parts = [info.model or info.driver]
    if info.serial:
        parts.append(f"serial {info.serial}")
    if info.firmware:
        parts.append(f"firmware {info.firmware}")
    text = ", ".join(parts)
    return f"{text} on {info.port}" if info.port else text
