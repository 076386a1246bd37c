"""Helpers of the command-line tests: a real write failure without root or a full disk.

A child process whose files may not grow past ``limit_bytes`` (``RLIMIT_FSIZE``, with
``SIGXFSZ`` ignored) gets ``EFBIG`` ("File too large") from the operating system on the first
write past the limit, just as a full disk gives ``ENOSPC``: the same code paths fail.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

_PRELUDE = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, ({n}, {n}))\n")


def run_with_file_size_limit(code: str, limit_bytes: int, *, cwd=None,
                             timeout: float = 120) -> subprocess.CompletedProcess:
    """Run Python ``code`` in a child process whose files cannot exceed ``limit_bytes``."""
    pytest.importorskip("resource")
    return subprocess.run([sys.executable, "-c", _PRELUDE.format(n=int(limit_bytes)) + code],
                          capture_output=True, text=True, cwd=cwd, timeout=timeout)


def polrig_with_file_size_limit(argv: list[str], limit_bytes: int, **kw) -> subprocess.CompletedProcess:
    """``polrig ARGV`` (the real entry point, :func:`polrig.cli.main`) under the limit."""
    code = f"from polrig.cli import main\nsys.exit(main({[str(a) for a in argv]!r}))\n"
    return run_with_file_size_limit(code, limit_bytes, **kw)
