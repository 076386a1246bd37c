"""One-line errors for the ``python -m models.*`` tools, with the exit codes of ``polrig``
(README, "CLI"): 2 bad input (arguments, missing or damaged files, a set with nothing to
score), 1 a failure while running, 130 Ctrl-C. ``POLRIG_DEBUG=1`` shows the traceback."""

from __future__ import annotations

import os
import sys
from typing import Callable

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
