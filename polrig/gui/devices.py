"""Devices panel: connect/disconnect, status and position, manual move/home, light level.

Every device call runs in :class:`DeviceWorker` (a ``QThread`` working through a job queue),
holding that device's lock (:class:`polrig.gui.rigaccess.RigLocks`); the UI thread only queues
jobs and shows what comes back. Errors come back as readable messages (the typed
:mod:`polrig.errors` text, which carries the device's own code), never as a frozen window.
"""

from __future__ import annotations

import dataclasses
import queue
from typing import Any, Callable

from PySide6.QtCore import QThread, QTimer, Signal
from PySide6.QtWidgets import (QCheckBox, QDoubleSpinBox, QGridLayout, QGroupBox, QHBoxLayout,
                               QLabel, QPushButton, QVBoxLayout, QWidget)

from polrig.errors import PolrigError
from polrig.gui.rigaccess import DEVICE_KINDS, DeviceBusy, RigLocks


@dataclasses.dataclass
class Job:
    kind: str  # device kind whose lock the job holds
    what: str  # description for messages
    fn: Callable[[], Any]
    poll: bool = False


class DeviceWorker(QThread):
    """Runs device jobs one after another off the UI thread.

    ``done(what, result)``, ``failed(what, message)``; ``polled(status)`` carries the periodic
    status dictionary ``{kind: {"open": bool, "position_deg"/"light": ...}}``.
    """

    done = Signal(str, object)
    failed = Signal(str, str)
    polled = Signal(object)

    def __init__(self, rig, locks: RigLocks, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = locks
        self.jobs: queue.Queue[Job | None] = queue.Queue()
        self._poll_pending = False

    def submit(self, kind: str, what: str, fn: Callable[[], Any]) -> None:
        self.jobs.put(Job(kind, what, fn))

    def request_poll(self) -> None:
        """Queue one status poll unless one is already waiting (polls never pile up)."""
        if not self._poll_pending:
            self._poll_pending = True
            self.jobs.put(Job("", "poll", self._poll, poll=True))

    def stop(self) -> None:
        self.jobs.put(None)

    def run(self) -> None:
        while True:
            job = self.jobs.get()
            if job is None:
                return
            if job.poll:
                self._poll_pending = False
                self.polled.emit(job.fn())
                continue
            try:
                with self.locks.hold(job.kind, timeout_s=2.0, who=job.what):
                    result = job.fn()
            except (PolrigError, OSError, ValueError) as exc:
                self.failed.emit(job.what, str(exc))
            except Exception as exc:  # noqa: BLE001 - a driver bug must not kill the thread
                self.failed.emit(job.what, f"{type(exc).__name__}: {exc}")
            else:
                self.done.emit(job.what, result)

    def _poll(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for kind in DEVICE_KINDS:
            dev = getattr(self.rig, kind)
            st: dict[str, Any] = {"open": bool(dev.is_open)}
            if dev.is_open:
                try:
                    with self.locks.hold(kind, timeout_s=0.05, who="status poll"):
                        if kind in ("stage", "turntable"):
                            st["position_deg"] = float(dev.position_deg())
                            st["busy"] = bool(dev.is_busy())
                        elif kind == "light":
                            st.update(dev.status())
                        else:
                            st["exposure_us"] = float(dev.exposure_us)
                            st["gain_db"] = float(dev.gain_db)
                except DeviceBusy as exc:
                    st["busy_with"] = str(exc)
                except (PolrigError, OSError, ValueError) as exc:
                    st["error"] = str(exc)
            out[kind] = st
        return out


class _AxisBox(QGroupBox):
    def __init__(self, title: str):
        super().__init__(title)
        self.state = QLabel("closed")
        self.position = QLabel("-")
        self.target = QDoubleSpinBox()
        self.target.setRange(-720.0, 720.0)
        self.target.setDecimals(2)
        self.target.setSuffix(" deg")
        self.move = QPushButton("Move")
        self.home = QPushButton("Home")
        self.stop = QPushButton("Stop")
        g = QGridLayout(self)
        g.addWidget(QLabel("State"), 0, 0)
        g.addWidget(self.state, 0, 1, 1, 3)
        g.addWidget(QLabel("Position"), 1, 0)
        g.addWidget(self.position, 1, 1, 1, 3)
        g.addWidget(self.target, 2, 0, 1, 2)
        g.addWidget(self.move, 2, 2)
        g.addWidget(self.home, 3, 1)
        g.addWidget(self.stop, 3, 2)


class DevicesPanel(QWidget):
    """Buttons and readouts for the four devices; ``message(level, text)`` for the log."""

    message = Signal(str, str)
    camera_values = Signal(float, float)  # exposure_us, gain_db as the camera reports them

    def __init__(self, rig, locks: RigLocks, parent=None, poll_ms: int = 500):
        super().__init__(parent)
        self.rig = rig
        self.worker = DeviceWorker(rig, locks, self)
        self.last_status: dict[str, Any] = {}
        self.failures: list[tuple[str, str]] = []
        self._poll_errors: dict[str, str] = {}

        self.conn: dict[str, tuple[QLabel, QPushButton, QPushButton]] = {}
        top = QGroupBox("Connections")
        g = QGridLayout(top)
        for row, kind in enumerate(DEVICE_KINDS):
            lab = QLabel("closed")
            b_on, b_off = QPushButton("Connect"), QPushButton("Disconnect")
            b_on.clicked.connect(lambda _=False, k=kind: self.connect_device(k))
            b_off.clicked.connect(lambda _=False, k=kind: self.disconnect_device(k))
            g.addWidget(QLabel(kind), row, 0)
            g.addWidget(lab, row, 1)
            g.addWidget(b_on, row, 2)
            g.addWidget(b_off, row, 3)
            self.conn[kind] = (lab, b_on, b_off)
        all_on, all_off = QPushButton("Connect all"), QPushButton("Disconnect all")
        all_on.clicked.connect(self.connect_all)
        all_off.clicked.connect(self.disconnect_all)
        g.addWidget(all_on, len(DEVICE_KINDS), 2)
        g.addWidget(all_off, len(DEVICE_KINDS), 3)

        self.stage = _AxisBox("Polarizer stage")
        self.turntable = _AxisBox("Turntable")
        for kind, box in (("stage", self.stage), ("turntable", self.turntable)):
            box.move.clicked.connect(lambda _=False, k=kind, b=box: self.move(k, b.target.value()))
            box.home.clicked.connect(lambda _=False, k=kind: self.home(k))
            box.stop.clicked.connect(lambda _=False, k=kind: self.stop_axis(k))

        self.light_box = QGroupBox("Light")
        self.light_on = QCheckBox("on")
        self.light_level = QDoubleSpinBox()
        self.light_level.setRange(0.0, 1.0)
        self.light_level.setSingleStep(0.05)
        self.light_level.setDecimals(3)
        self.light_level.setKeyboardTracking(False)
        self.light_state = QLabel("-")
        lg = QGridLayout(self.light_box)
        lg.addWidget(self.light_on, 0, 0)
        lg.addWidget(QLabel("Level (0..1)"), 0, 1)
        lg.addWidget(self.light_level, 0, 2)
        lg.addWidget(self.light_state, 1, 0, 1, 3)
        self.light_on.clicked.connect(self.set_light_on)
        self.light_level.valueChanged.connect(self.set_light_level)
        self.camera_state = QLabel("-")
        cam_box = QGroupBox("Camera")
        QVBoxLayout(cam_box).addWidget(self.camera_state)

        axes = QHBoxLayout()
        axes.addWidget(self.stage)
        axes.addWidget(self.turntable)
        lay = QVBoxLayout(self)
        lay.addWidget(top)
        lay.addLayout(axes)
        lay.addWidget(self.light_box)
        lay.addWidget(cam_box)
        lay.addStretch(1)

        self.worker.done.connect(self._done)
        self.worker.failed.connect(self._failed)
        self.worker.polled.connect(self._polled)
        self.timer = QTimer(self)
        self.timer.setInterval(poll_ms)
        self.timer.timeout.connect(self.worker.request_poll)

    def start(self) -> None:
        self.worker.start()
        self.timer.start()
        self.worker.request_poll()

    def shutdown(self, wait_ms: int = 5000) -> bool:
        self.timer.stop()
        self.worker.stop()
        return self.worker.wait(wait_ms)

    # -- actions (queue jobs; results arrive as signals)
    def _dev(self, kind: str):
        return getattr(self.rig, kind)

    def connect_device(self, kind: str) -> None:
        self.worker.submit(kind, f"connect {kind}", self._dev(kind).open)

    def disconnect_device(self, kind: str) -> None:
        self.worker.submit(kind, f"disconnect {kind}", self._dev(kind).close)

    def connect_all(self) -> None:
        for kind in DEVICE_KINDS:
            if not self._dev(kind).is_open:
                self.connect_device(kind)

    def disconnect_all(self) -> None:
        for kind in DEVICE_KINDS:
            self.disconnect_device(kind)

    def move(self, kind: str, angle_deg: float) -> None:
        dev = self._dev(kind)
        self.worker.submit(kind, f"move {kind} to {angle_deg:g} deg",
                           lambda: dev.move_to(angle_deg, wait=True))

    def home(self, kind: str) -> None:
        self.worker.submit(kind, f"home {kind}", self._dev(kind).home)

    def stop_axis(self, kind: str) -> None:
        self.worker.submit(kind, f"stop {kind}", self._dev(kind).stop)

    def set_light_on(self, on: bool) -> None:
        self.worker.submit("light", f"light {'on' if on else 'off'}",
                           lambda: self.rig.light.set_on(bool(on)))

    def set_light_level(self, level: float) -> None:
        self.worker.submit("light", f"light level {level:g}",
                           lambda: self.rig.light.set_level(float(level)))

    # -- results
    def _done(self, what: str, _result: object) -> None:
        self.message.emit("info", f"{what}: done")
        self.worker.request_poll()

    def _failed(self, what: str, text: str) -> None:
        self.failures.append((what, text))
        self.message.emit("error", f"{what} failed: {text}")
        self.worker.request_poll()

    def _polled(self, status: dict[str, Any]) -> None:
        self.last_status = status
        for kind, st in status.items():
            lab = self.conn[kind][0]
            text = "open" if st["open"] else "closed"
            if "error" in st:
                text += f" - {st['error']}"
                if self._poll_errors.get(kind) != st["error"]:  # once per distinct fault
                    self.failures.append((f"{kind} status", st["error"]))
                    self.message.emit("error", f"{kind} status failed: {st['error']}")
            elif "busy_with" in st:
                text += f" - {st['busy_with']}"
            self._poll_errors[kind] = st.get("error", "")
            lab.setText(text)
        for kind, box in (("stage", self.stage), ("turntable", self.turntable)):
            st = status[kind]
            box.state.setText("moving" if st.get("busy") else ("open" if st["open"] else "closed"))
            if "position_deg" in st:
                box.position.setText(f"{st['position_deg']:.3f} deg")
        st = status["light"]
        if "level" in st:
            self.light_state.setText(", ".join(f"{k} {v}" for k, v in st.items() if k != "open"))
            self.light_on.setChecked(bool(st.get("on")))
            self.light_level.blockSignals(True)
            self.light_level.setValue(float(st["level"]))
            self.light_level.blockSignals(False)
        st = status["camera"]
        if "exposure_us" in st:
            self.camera_state.setText(f"open, exposure {st['exposure_us']:g} us, gain "
                                      f"{st['gain_db']:g} dB")
            self.camera_values.emit(st["exposure_us"], st["gain_db"])
        elif not st["open"]:
            self.camera_state.setText("closed")
