"""``run_gui``: what ``polrig gui`` runs (QApplication, rig, main window)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from typing import Any, Iterator

from polrig.app.rig import build_rig, load_rig_config
from polrig.app.session import Interrupted
from polrig.app.single_shot import SingleShot
from polrig.choices import GUI_SIM_SIZE
from polrig.errors import ConfigError, PolrigError

#: Simulated sensor size of the GUI's built-in rig (width x height). Smaller than a real
#: IMX250 (2448x2048): the simulator renders every new pose, which at full size takes
#: seconds; ``polrig gui --sim-size 2448x2048`` gives the full size.
DEFAULT_SIM_SIZE = GUI_SIM_SIZE  # defined in polrig.choices (the command line's start-up vocabulary)


def check_qt_binding(pyside_version: str, python: tuple[int, int]) -> None:
    """Refuse PySide6 6.12.0 on CPython < 3.12: its abi3 build returns ``None`` without
    taking a reference from every void Qt call, so ``None``'s reference count runs down and the
    interpreter aborts ("deallocating None") after some thousand calls (measured here;
    6.11.3 is fine). :class:`polrig.errors.ConfigError` names the fix."""
    if pyside_version == "6.12.0" and tuple(python) < (3, 12):
        raise ConfigError("PySide6 6.12.0 crashes on Python < 3.12 (reference counting of None);"
                          " install another version: pip install 'PySide6-Essentials!=6.12.0'")


#: Debian/Ubuntu package of each shared library that Qt's xcb platform plugin (the X11 window
#: of ``polrig gui``) links and a bare system may lack (Qt for X11 requirements,
#: https://doc.qt.io/qt-6/linux-requirements.html; package names from Debian's packages).
XCB_PACKAGES: dict[str, str] = {
    "libxcb-cursor.so.0": "libxcb-cursor0", "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-image.so.0": "libxcb-image0", "libxcb-keysyms.so.1": "libxcb-keysyms1",
    "libxcb-randr.so.0": "libxcb-randr0", "libxcb-render-util.so.0": "libxcb-render-util0",
    "libxcb-shape.so.0": "libxcb-shape0", "libxcb-xinerama.so.0": "libxcb-xinerama0",
    "libxcb-xkb.so.1": "libxcb-xkb1", "libxkbcommon-x11.so.0": "libxkbcommon-x11-0",
    "libxkbcommon.so.0": "libxkbcommon0", "libxcb-util.so.1": "libxcb-util1",
    "libxcb-xfixes.so.0": "libxcb-xfixes0", "libxcb-sync.so.1": "libxcb-sync1",
    "libxcb-shm.so.0": "libxcb-shm0", "libxcb-render.so.0": "libxcb-render0",
    "libX11-xcb.so.1": "libx11-xcb1", "libxcb.so.1": "libxcb1", "libX11.so.6": "libx11-6",
    "libEGL.so.1": "libegl1", "libGL.so.1": "libgl1", "libOpenGL.so.0": "libopengl0",
    "libfontconfig.so.1": "libfontconfig1", "libfreetype.so.6": "libfreetype6",
    "libdbus-1.so.3": "libdbus-1-3", "libglib-2.0.so.0": "libglib2.0-0",
}


def ldd_missing(ldd_output: str) -> list[str]:
    """The libraries ``ldd`` reports as ``not found``, in order, each once."""
    out: list[str] = []
    for line in ldd_output.splitlines():
        name, _, where = line.strip().partition("=>")
        if where.strip() == "not found" and name.strip() not in out:
            out.append(name.strip())
    return out


def missing_xcb_libraries() -> list[str]:
    """Shared libraries that PySide6's xcb platform plugin needs and the system lacks (``ldd``
    of ``Qt/plugins/platforms/libqxcb.so``); ``[]`` when none are missing or when this cannot
    be checked (not Linux, no ``ldd``, no plugin)."""
    import pathlib
    import shutil
    import subprocess

    if not sys.platform.startswith("linux") or shutil.which("ldd") is None:
        return []
    try:
        import PySide6
    except ImportError:
        return []
    plugin = pathlib.Path(PySide6.__file__).parent / "Qt" / "plugins" / "platforms" / "libqxcb.so"
    if not plugin.is_file():
        return []
    try:
        res = subprocess.run(["ldd", str(plugin)], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return []
    return ldd_missing(res.stdout)


def check_qt_platform(environ=os.environ) -> None:
    """Before Qt starts: with the X11 (xcb) platform, a missing system library aborts the
    process (SIGABRT, exit 134) with Qt's own hint; instead :class:`polrig.errors.PolrigError`
    (exit 1) names the missing libraries and the ``apt-get install`` line that adds them."""
    platform = environ.get("QT_QPA_PLATFORM", "")
    if platform and not platform.startswith("xcb"):
        return  # offscreen, wayland, vnc...: not the xcb plugin
    if not platform and environ.get("WAYLAND_DISPLAY") and not environ.get("DISPLAY"):
        return
    missing = missing_xcb_libraries()
    if missing:
        packages = " ".join(dict.fromkeys(XCB_PACKAGES.get(m, m) for m in missing))
        raise PolrigError(f"Qt's X11 (xcb) platform plugin cannot load: {', '.join(missing)} "
                          f"not found; on Debian/Ubuntu: sudo apt-get install {packages} "
                          f"(README, 'Operator GUI')")


def sim_options(size: str = DEFAULT_SIM_SIZE, clock_speed: float = 1.0) -> dict[str, Any]:
    return {"size": size, "clock_speed": clock_speed}


def model_loader(weights: str | None = None, device: str = "auto", size: str = "auto"):
    """A function opening the single-shot route on ``device`` (``auto``, ``cpu``, ``cuda``:
    :mod:`polrig.models.devices`) with the model in ``weights`` (default: the installed one of
    ``size``, :mod:`polrig.models.sizes`; the
    CLI's message when none is installed): :meth:`polrig.app.single_shot.SingleShot.open`, whose
    model the window's captures share (loaded once per window)."""
    def load() -> SingleShot:
        return SingleShot.open(device, weights, size=size)
    return load


def run_gui(config: str | os.PathLike | None = None, *, sim_size: str = DEFAULT_SIM_SIZE,
            sim_clock_speed: float = 1.0, weights: str | None = None, device: str = "auto",
            settings_file: str | None = None, argv: list[str] | None = None,
            model_size: str = "auto") -> int:
    """Open the rig (simulated unless ``config``) and run the GUI until its window closes."""
    import PySide6
    from PySide6.QtWidgets import QApplication

    from polrig.gui.main_window import MainWindow  # Qt: after the platform checks above
    from polrig.gui.settings import make_settings

    check_qt_binding(PySide6.__version__, sys.version_info[:2])
    check_qt_platform()

    config_data = load_rig_config(config)  # configuration errors before any window opens
    rig = build_rig(config_data, sim_options(sim_size, sim_clock_speed))
    app = QApplication.instance() or QApplication(argv or sys.argv[:1])
    app.setApplicationName("polrig")
    window = MainWindow(rig, make_settings(settings_file), model_loader=model_loader(weights, device, model_size))
    window.show()
    window.start()
    with close_on_signals(window) as received:
        code = int(app.exec())
    if received:
        raise Interrupted(received[0])  # polrig's exit: 130 (SIGINT) / 143 (SIGTERM)
    return code


#: How often the event loop lets Python run its signal handlers, milliseconds.
SIGNAL_CHECK_MS = 100


@contextlib.contextmanager
def close_on_signals(window, signals=(signal.SIGINT, signal.SIGTERM)) -> Iterator[list[int]]:
    """While Qt's event loop runs: SIGINT and SIGTERM close ``window`` as its close button
    does (a running capture is stopped and its session left ``interrupted``; the window
    closes once it has). Yields the list of signals received (the first one decides the
    exit code: :func:`run_gui` raises :class:`polrig.app.session.Interrupted` for it after the
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
