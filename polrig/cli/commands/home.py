"""``polrig home stage|turntable``: run the device's homing cycle and report the position.

The operator's command after a safety stop (:class:`polrig.errors.DeviceAlarm`: a limit switch
fired, a soft limit, GRBL locked in its Alarm state): the capture engine never homes an axis in
that state on its own, its stop message names this command. For GRBL it soft-resets a
controller halted by a hard or soft limit, then homes it (``$H``). A homing cycle that does not
end within ``--timeout`` is stopped by the driver; Ctrl-C or SIGTERM stops it too
(:func:`polrig.acquisition.hal.stopped_when_interrupted`; GRBL: a soft reset, the
only way to abort ``$H``)."""

from __future__ import annotations

import argparse

from polrig.cli.commands._device_args import (
    add_config_argument,
    add_timeout_argument,
    identity,
    stop_failed,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("home", help="home the polarizer stage or the turntable",
                       description="Run the homing cycle of the polarizer stage or the object "
                                   "turntable (needed after power-up, a motion error or an "
                                   "alarm: a capture stopped by a limit switch names this "
                                   "command; clear whatever is in the way first) and print the "
                                   "position the device reports.")
    p.add_argument("device", choices=("stage", "turntable"), help="which axis")
    add_config_argument(p)
    add_timeout_argument(p, 120.0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.acquisition.hal import stopped_when_interrupted
    from polrig.app.rig import open_device

    with open_device(args.config, args.device) as dev, \
            stopped_when_interrupted([(args.device, dev)], failed=stop_failed):
        dev.home(timeout_s=args.timeout)
        print(f"{args.device}: homed, at {dev.position_deg():.4f} deg ({identity(dev.info())})")
    return 0
