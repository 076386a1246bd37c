"""``polrig move stage|turntable DEG``: move one axis of the rig and report where it is.

A move that does not end within ``--timeout`` is stopped by the driver before the error is
reported; Ctrl-C or SIGTERM while it runs stops the axis before the command exits
(:func:`polrig.acquisition.hal.stopped_when_interrupted`). ``--no-wait`` returns
once the move has started and leaves it running."""

from __future__ import annotations

import argparse
import math

from polrig.cli.commands._device_args import (
    add_config_argument,
    add_timeout_argument,
    identity,
    stop_failed,
)
from polrig.errors import ConfigError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("move", help="move the polarizer stage or the turntable to an angle",
                       description="Move the polarizer stage or the object turntable to an "
                                   "absolute angle in degrees (docs/conventions.md) and print "
                                   "the position the device reports.")
    p.add_argument("device", choices=("stage", "turntable"), help="which axis")
    p.add_argument("angle_deg", type=float, metavar="DEG", help="target angle in degrees")
    add_config_argument(p)
    add_timeout_argument(p, 60.0)
    p.add_argument("--no-wait", action="store_true", help="return once the move has started")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.acquisition.plan import MAX_POSE_DEG, MAX_STATE_DEG
    from polrig.acquisition.hal import stopped_when_interrupted
    from polrig.app.rig import open_device

    if not math.isfinite(args.angle_deg):
        raise ConfigError(f"DEG must be a finite angle, got {args.angle_deg}")
    # the limits `polrig capture` applies to --states and --poses: beyond them a value is a
    # typo that would send the axis on a long move that ends in a timeout
    limit = MAX_STATE_DEG if args.device == "stage" else MAX_POSE_DEG
    if abs(args.angle_deg) > limit:
        raise ConfigError(f"DEG {args.angle_deg:g}: a {args.device} angle must be within "
                          f"+-{limit:g} deg (the limit polrig capture applies)")
    with open_device(args.config, args.device) as dev, \
            stopped_when_interrupted([(args.device, dev)], failed=stop_failed):
        dev.move_to(args.angle_deg, wait=not args.no_wait, timeout_s=args.timeout)
        if args.no_wait:
            print(f"{args.device}: moving to {args.angle_deg:g} deg ({identity(dev.info())})")
        else:
            print(f"{args.device}: at {dev.position_deg():.4f} deg (target {args.angle_deg:g}; "
                  f"{identity(dev.info())})")
    return 0
