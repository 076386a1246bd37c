"""The ``polrig`` console script: a thin shell over polrig's core calls.

Exit codes: 0 success, 1 a failure while running (device fault, processing error, a session
another process is writing), 2 bad input (invalid arguments, config, files), 130 interrupted
by Ctrl-C (SIGINT), 143 terminated by SIGTERM (handled as Ctrl-C is: a capture leaves its
session ``interrupted`` and resumable), 141 when the reader of the output went away (a broken
pipe, ``polrig info DIR | head``: no message, as ``cat`` and friends do).
Errors print one line ``polrig: error: ...`` on stderr, never a traceback (set
``POLRIG_DEBUG=1`` to see the traceback).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import pkgutil
import signal
import sys
import threading

from polrig import __version__
from polrig.errors import EXIT_USAGE, DeviceAlarm, exit_code_for

EXIT_OK, EXIT_INTERRUPTED = 0, 130  # failure 1 and usage 2: polrig.errors.exit_code_for
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # 141


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="polrig",
        description="Drive a DoFP polarimetric rig (simulated unless --config names real "
                    "hardware) and turn captures into per-pixel Mueller matrices.")
    parser.add_argument("--version", action="version", version=f"polrig {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    import polrig.cli.commands as commands

    for mod in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if mod.name.startswith("_"):
            continue
        importlib.import_module(f"polrig.cli.commands.{mod.name}").register(sub)
    return parser


def command_parser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser:
    """The sub-command ``name``'s own parser (``parser`` itself where there is none), whose usage
    line an error about that command's options prints."""
    for action in parser._actions:  # argparse keeps its sub-command parsers only here
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    return parser


def main(argv: list[str] | None = None) -> int:
    """``polrig ARGS``: the exit status. Ctrl-C (SIGTERM too, once the command runs) is one line
    and 130 (143) wherever it comes, the commands' modules loading included."""
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        if signum == signal.SIGINT:
            _error_line("polrig: interrupted")
            return EXIT_INTERRUPTED
        _error_line(f"polrig: terminated ({signal.Signals(signum).name})")
        return 128 + signum


def _main(argv: list[str] | None) -> int:
    parser = build_parser()  # imports every command's module: about a second on a cold start
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the command's usage line above the error, not the top level's
        command_parser(parser, getattr(args, "command", None)).error(
            f"unrecognized arguments: {' '.join(unknown)}")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    with _sigterm_as_interrupt():
        try:
            code = int(args.func(args) or 0)
            sys.stdout.flush()  # a closed pipe shows here, not at interpreter exit
            return code
        except BrokenPipeError:
            return _broken_pipe()
        except Exception as exc:
            code = exit_code_for(exc)
            if code is None or os.environ.get("POLRIG_DEBUG"):
                raise
            if isinstance(exc, DeviceAlarm):  # the command that clears it, with this rig
                _error_line(f"polrig: error: {exc.operator_message(getattr(args, 'config', None))}")
                return code
            _error_line(f"polrig: error: {exc}")
            return code


def _error_line(line: str) -> None:
    with contextlib.suppress(OSError, ValueError):  # stderr gone too: nothing to tell
        print(line, file=sys.stderr)


def _broken_pipe() -> int:
    """The reader of stdout went away: exit quietly (141, as a process killed by SIGPIPE
    does). stdout is pointed at /dev/null so that the interpreter's final flush of what is
    still buffered does not fail a second time."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    return EXIT_BROKEN_PIPE


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises :class:`polrig.app.session.Interrupted` (a ``KeyboardInterrupt``) so every
    command stops on it as on Ctrl-C; restored afterwards (``main`` also runs in-process).
    Not where SIGTERM is ignored or outside the main thread."""
    from polrig.app.session import Interrupted

    def handler(signum, frame):
        raise Interrupted(signum)

    old = None
    if threading.current_thread() is threading.main_thread():
        old = signal.getsignal(signal.SIGTERM)
        if old is signal.SIG_IGN:
            old = None
        else:
            signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
