"""``polrig light on|off [--level FRACTION]``: switch the point light and report its status."""

from __future__ import annotations

import argparse

from polrig.cli.commands._device_args import add_config_argument, identity


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("light", help="switch the point light on or off, set its level",
                       description="Switch the LED light on or off (optionally setting its "
                                   "level, a fraction of full brightness in [0, 1]) and print "
                                   "the status the driver reports.")
    p.add_argument("state", choices=("on", "off"))
    p.add_argument("--level", type=float, default=None, metavar="FRACTION",
                   help="brightness as a fraction in [0, 1]")
    add_config_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.acquisition.hal import check_level
    from polrig.app.rig import open_device

    level = None if args.level is None else check_level(args.level)  # before opening anything
    with open_device(args.config, "light") as light:
        if level is not None:
            light.set_level(level)
        light.set_on(args.state == "on")
        st = light.status()
        extra = ", ".join(f"{k} {v}" for k, v in st.items() if k not in ("on", "level"))
        print(f"light: {'on' if st['on'] else 'off'}, level {st['level']:.3f}"
              + (f", {extra}" if extra else "") + f" ({identity(light.info())})")
    return 0
