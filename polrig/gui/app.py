"""``run_gui``: what ``polrig gui`` runs (QApplication, rig, main window)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Any, Iterator

#: Simulated sensor size of the GUI's built-in rig (width x height). Smaller than a real
#: IMX250 (2448x2048): the simulator renders every new pose, which at full size takes
#: seconds; ``polrig gui --sim-size 2448x2048`` gives the full size.
DEFAULT_SIM_SIZE = "512x512"


def check_qt_binding(pyside_version: str, python: tuple[int, int]) -> None:
    """Refuse PySide6 6.12.0 on CPython < 3.12: its abi3 build returns ``None`` without
    taking a reference from every void Qt call, so ``None``'s reference count runs down and the
    interpreter aborts ("deallocating None") after some thousand calls (measured here;
    6.11.3 is fine). :class:`polrig.errors.ConfigError` names the fix."""
    if pyside_version == "6.12.0" and tuple(python) < (3, 12):
        from polrig.errors import ConfigError

        raise ConfigError("PySide6 6.12.0 crashes on Python < 3.12 (reference counting of None);"
                          " install another version: pip install 'PySide6-Essentials!=6.12.0'")


def sim_options(size: str = DEFAULT_SIM_SIZE, clock_speed: float = 1.0) -> dict[str, Any]:
    return {"size": size, "clock_speed": clock_speed}


def model_loader(weights: str | None = None):
    """A function loading the single-shot model (the CLI's message when none is installed)."""
    def load():
        from polrig import processing

        if weights is None:
            return processing.single_shot_model()
        from models.runtime import SingleShotModel

        return SingleShotModel.load(weights)
    return load


def run_gui(config: str | os.PathLike | None = None, *, sim_size: str = DEFAULT_SIM_SIZE,
            sim_clock_speed: float = 1.0, weights: str | None = None,
            settings_file: str | None = None, argv: list[str] | None = None) -> int:
    """Open the rig (simulated unless ``config``) and run the GUI until its window closes."""
    import PySide6
    from PySide6.QtWidgets import QApplication

    check_qt_binding(PySide6.__version__, sys.version_info[:2])
    from polrig.gui.main_window import MainWindow
    from polrig.gui.settings import make_settings
    from polrig.rig import build_rig, load_rig_config

    config_data = load_rig_config(config)  # configuration errors before any window opens
    rig = build_rig(config_data, sim_options(sim_size, sim_clock_speed))
    app = QApplication.instance() or QApplication(argv or sys.argv[:1])
    app.setApplicationName("polrig")
    window = MainWindow(rig, make_settings(settings_file), model_loader=model_loader(weights))
    window.show()
    window.start()
    with close_on_signals(window) as received:
        code = int(app.exec())
    if received:
        from polrig.session import Interrupted

        raise Interrupted(received[0])  # polrig's exit: 130 (SIGINT) / 143 (SIGTERM)
    return code


#: How often the event loop lets Python run its signal handlers, milliseconds.
SIGNAL_CHECK_MS = 100


@contextlib.contextmanager
def close_on_signals(window, signals=(signal.SIGINT, signal.SIGTERM)) -> Iterator[list[int]]:
    """While Qt's event loop runs: SIGINT and SIGTERM close ``window`` as its close button
    does (a running capture is stopped and its session left ``interrupted``; the window
    closes once it has). Yields the list of signals received (the first one decides the
    exit code: :func:`run_gui` raises :class:`polrig.session.Interrupted` for it after the
    window closed). A repeated signal does not cut the clean-up short.

    The usual Qt approach: the Python handler only records the signal; a timer
    (:data:`SIGNAL_CHECK_MS`) lets the interpreter run while Qt's C++ loop waits, and posts
    the close to the event loop. Only in the main thread, and not for a signal that is
    ignored (``SIG_IGN``). The previous handlers are restored afterwards."""
    from PySide6.QtCore import QTimer

    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return
    closing = [False]

    def handler(signum, _frame) -> None:
        received.append(int(signum))

    def check() -> None:
        if received and not closing[0]:
            closing[0] = True
            window.close()

    old = {}
    for sig in signals:
        prev = signal.getsignal(sig)
        if prev is signal.SIG_IGN:
            continue
        old[sig] = prev
        signal.signal(sig, handler)
    timer = QTimer()
    timer.setInterval(SIGNAL_CHECK_MS)
    timer.timeout.connect(check)
    timer.start()
    try:
        yield received
    finally:
        timer.stop()
        for sig, prev in old.items():
            signal.signal(sig, prev if prev is not None else signal.SIG_DFL)
