"""One-line errors for the ``python -m polrig.models.*`` tools, with the exit codes of ``polrig``
(README, "CLI"): 2 bad input (arguments, missing or damaged files, a set with nothing to
score), 1 a failure while running, 130 Ctrl-C. ``POLRIG_DEBUG=1`` shows the traceback."""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
from typing import Any, Callable, Sequence

from polrig.errors import exit_code_for


def run_main(prog: str, body: Callable[[], int | None]) -> int:
    """``body()``'s exit code, or the exit code of the error it raised
    (:func:`polrig.errors.exit_code_for`), printed as one line ``PROG: error: ...`` on stderr."""
    try:
        return int(body() or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        code = exit_code_for(exc)
        if code is None or os.environ.get("POLRIG_DEBUG"):
            raise
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return code


def held_out_main(argv: Sequence[str] | None, prog: str, description: str,
                  evaluate_set: Callable[[str, str | None, int | None], dict[str, Any]],
                  markdown: Callable[[list[dict[str, Any]]], str], heading: str) -> int:
    """The command line of a tool that scores held-out sets one by one: ``--data`` sets,
    ``--weights``, ``--limit`` (first N samples of each), ``--out`` (the Markdown table under
    ``heading``, and the numbers as ``.json`` beside it); the table is printed either way."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument("--data", nargs="+", required=True, help="held-out sets (`polrig sim dataset` folders)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--limit", type=int, default=None, help="first N samples of each set")
    ap.add_argument("--out", default=None, help="also write the table (Markdown) and the numbers (.json)")

    def body() -> int:
        results = [evaluate_set(d, args.weights, args.limit) for d in args.data]
        table = markdown(results)
        print(table)
        if args.out:
            out = pathlib.Path(args.out)
            out.write_text(heading + "\n\n" + table + "\n")
            out.with_suffix(".json").write_text(json.dumps(results, indent=1) + "\n")
        return 0

    args = ap.parse_args(argv)
    return run_main(prog, body)
