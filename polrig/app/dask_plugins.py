"""Dask worker plugins of :mod:`polrig.app.cluster`'s local cluster (imported with the
``cluster`` extra only: this module imports ``distributed``)."""

from __future__ import annotations

import signal
import threading

from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["TerminalInterruptIgnored"]


class TerminalInterruptIgnored(WorkerPlugin):
    """Local worker processes ignore SIGINT.

    They share the terminal's process group with the ``polrig`` process, so a Ctrl-C reaches
    them as well, and each printed its ``KeyboardInterrupt`` traceback before ``polrig``'s one
    line. The client's process handles the interrupt alone (the captures not finished stay
    ``pending``), and closing the cluster stops the workers. A worker the nanny restarts gets
    the plugin again."""

    name = "polrig-terminal-interrupt-ignored"

    def setup(self, worker) -> None:
        if threading.current_thread() is threading.main_thread():  # the worker process's event loop
            signal.signal(signal.SIGINT, signal.SIG_IGN)
