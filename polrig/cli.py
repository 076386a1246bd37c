"""The ``polrig`` console script: a thin shell over polrig's core calls.

Exit codes: 0 success, 1 a failure while running (device fault, processing error),
2 bad input (invalid arguments, config, files), 130 interrupted by Ctrl-C.
Errors print one line ``polrig: error: ...`` on stderr, never a traceback (set
``POLRIG_DEBUG=1`` to see the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from polrig import __version__
from polrig.errors import ConfigError, DeviceError, FormatError, PolrigError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="polrig",
        description="Drive a DoFP polarimetric rig (simulated unless --config names real "
                    "hardware) and turn captures into per-pixel Mueller matrices.")
    parser.add_argument("--version", action="version", version=f"polrig {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    import polrig.commands as commands

    for mod in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if mod.name.startswith("_"):
            continue
        importlib.import_module(f"polrig.commands.{mod.name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("polrig: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (ConfigError, FormatError, FileNotFoundError, FileExistsError, ValueError) as exc:
        if os.environ.get("POLRIG_DEBUG"):
            raise
        print(f"polrig: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (DeviceError, PolrigError, OSError) as exc:
        if os.environ.get("POLRIG_DEBUG"):
            raise
        print(f"polrig: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
