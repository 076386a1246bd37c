"""Devices panel: connect/disconnect, status and position, manual move/home, light level.

Every device call runs in :class:`DeviceWorker` (a ``QThread`` working through a job queue),
holding that device's lock (:class:`polrig.gui.rigaccess.RigLocks`); the UI thread only queues
jobs and shows what comes back. Errors come back as readable messages (the typed
:mod:`polrig.errors` text, which carries the device's own code), never as a frozen window; an
unexpected exception (a driver bug) in a job or in the status poll is a message too, and the
worker keeps running.

A manual move is started without waiting (``move_to(wait=False)``) and then followed by the
worker between jobs (``is_busy`` and ``position_deg`` every :attr:`DeviceWorker.MOTION_POLL_S`),
so the readouts move with the axis, other jobs (the light, the other axis) run during the
motion, Stop runs at once (it goes before every queued job) and the timeout grows with the
distance and the axis's speed (:func:`polrig.acquisition.hal.motion_timeout_s`; when it runs out the axis
is stopped). Homing has no non-blocking form in the HAL: it occupies the worker until it ends.
"""

from __future__ import annotations

import collections
import dataclasses
import queue
import re
import time
from typing import Any, Callable

from PySide6.QtCore import QThread, QTimer, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QDoubleSpinBox,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from polrig.acquisition.hal import motion_timeout_s
from polrig.errors import PolrigError
from polrig.gui.rigaccess import DEVICE_KINDS, DeviceBusy, RigLocks


def error_text(exc: BaseException) -> str:
    """One line for a device call's exception: the typed polrig text as it is (a safety
    fault's advice in this window's words: :func:`window_advice`), anything else (a driver
    bug) with its type."""
    if isinstance(exc, (PolrigError, OSError, ValueError)):
        return window_advice(str(exc))
    return f"{type(exc).__name__}: {exc}"


#: What a safety fault (:class:`polrig.errors.DeviceAlarm`, its text and
#: ``operator_message``) tells the command line's operator to run once the cause is cleared.
_HOME_COMMAND = re.compile(r"then run `polrig home (\w+)(?: --config [^`]*)?`")


def window_advice(text: str) -> str:
    """``text`` with a safety fault's "then run `polrig home AXIS [--config RIG]`" said as
    this window does it: "then home the AXIS (Devices tab, Home)". The command cannot reach
    the devices while the window holds them (a serial port is opened exclusively; on the
    simulated rig it would home another rig); the window never homes an axis on its own."""
    return _HOME_COMMAND.sub(lambda m: f"then home the {m.group(1)} (Devices tab, Home)", text)


@dataclasses.dataclass
class Job:
    kind: str  # device kind whose lock the job holds
    what: str  # description for messages
    fn: Callable[[], Any]
    poll: bool = False
    #: ``fn`` starts a motion and returns its timeout in seconds; the worker follows it
    motion: bool = False
    #: the job ends a motion of its axis in progress (stop, home, disconnect)
    ends_motion: bool = False


@dataclasses.dataclass
class Motion:
    """A move the worker follows until the axis is idle."""

    kind: str
    what: str
    timeout_s: float
    deadline: float  # time.monotonic()


_WAKE = Job("", "wake", lambda: None)


class DeviceWorker(QThread):
    """Runs device jobs one after another off the UI thread and follows the motions they
    start.

    ``done(what, result)``, ``failed(what, message)``, ``notice(level, text)``;
    ``polled(status)`` carries the periodic status dictionary ``{kind: {"open": bool,
    "position_deg"/"light": ...}}``; ``motion(kind, {"position_deg", "busy"})`` the position
    of a moving axis. ``current`` is the job running now (``None`` when idle).
    """

    done = Signal(str, object)
    failed = Signal(str, str)
    notice = Signal(str, str)
    polled = Signal(object)
    motion = Signal(str, object)

    #: How often a moving axis is asked where it is, seconds.
    MOTION_POLL_S = 0.1

    def __init__(self, rig, locks: RigLocks, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = locks
        self.jobs: queue.Queue[Job | None] = queue.Queue()
        self._urgent: collections.deque[Job] = collections.deque()
        self._poll_pending = False
        self.motions: dict[str, Motion] = {}  # worker thread only
        self.current: str | None = None
        self._next_follow = 0.0

    def submit(self, kind: str, what: str, fn: Callable[[], Any], *, motion: bool = False,
               ends_motion: bool = False) -> None:
        self.jobs.put(Job(kind, what, fn, motion=motion, ends_motion=ends_motion))

    def submit_urgent(self, kind: str, what: str, fn: Callable[[], Any]) -> None:
        """Run ``fn`` before every job waiting in the queue (Stop); it ends the axis's
        motion."""
        self._urgent.append(Job(kind, what, fn, ends_motion=True))
        self.jobs.put(_WAKE)

    def request_poll(self) -> None:
        """Queue one status poll unless one is already waiting (polls never pile up)."""
        if not self._poll_pending:
            self._poll_pending = True
            self.jobs.put(Job("", "poll", self._poll, poll=True))

    def stop(self, drop_queued: bool = False) -> None:
        """End the thread after the job in progress (and the urgent ones); ``drop_queued``:
        forget the jobs still waiting (closing the window). Axes still moving are stopped."""
        if drop_queued:
            try:
                while True:
                    self.jobs.get_nowait()
            except queue.Empty:
                pass
        self.jobs.put(None)

    # -- the thread
    def run(self) -> None:
        try:
            while True:
                job = self._next_job()
                if job is None:
                    return
                if job is not _WAKE:
                    self._run_job(job)
                if self.motions and time.monotonic() >= self._next_follow:
                    self._follow_motions()
        finally:
            self._stop_motions()  # never leave an axis moving unattended

    def _next_job(self) -> Job | None:
        if self._urgent:
            return self._urgent.popleft()
        if not self.motions:
            return self.jobs.get()
        wait = max(0.0, self._next_follow - time.monotonic())
        try:
            return self.jobs.get(timeout=wait)
        except queue.Empty:
            return _WAKE

    def _run_job(self, job: Job) -> None:
        if job.poll:
            self._poll_pending = False
            try:
                status = job.fn()
            except Exception as exc:  # noqa: BLE001 - a poll must never end the thread
                self.failed.emit("status poll", error_text(exc))
                return
            self.polled.emit(status)
            return
        self.current = job.what
        try:
            with self.locks.hold(job.kind, timeout_s=2.0, who=job.what):
                result = job.fn()
        except Exception as exc:  # noqa: BLE001 - a driver bug must not kill the thread
            self.failed.emit(job.what, error_text(exc))  # a motion goes on being followed
        else:
            if job.motion:
                old = self.motions.pop(job.kind, None)
                if old is not None:
                    self.notice.emit("warning", f"{old.what}: replaced by {job.what}")
                timeout = float(result)
                self.motions[job.kind] = Motion(job.kind, job.what, timeout,
                                                time.monotonic() + timeout)
                self._next_follow = 0.0
                self.notice.emit("info", f"{job.what}: moving")
            else:
                if job.ends_motion:
                    self._end_motion(job.kind, job.what)
                self.done.emit(job.what, result)
        finally:
            self.current = None

    def _end_motion(self, kind: str, by: str) -> None:
        m = self.motions.pop(kind, None)
        if m is not None:
            self.notice.emit("warning", f"{m.what}: ended by {by}")

    def _follow_motions(self) -> None:
        """Ask each moving axis where it is; report the end of its motion, or stop it when
        its timeout has run out."""
        self._next_follow = time.monotonic() + self.MOTION_POLL_S
        for kind, m in list(self.motions.items()):
            dev = getattr(self.rig, kind)
            try:
                with self.locks.hold(kind, timeout_s=0.05, who=m.what):
                    busy = bool(dev.is_busy())
                    pos = float(dev.position_deg())
            except DeviceBusy:
                continue
            except Exception as exc:  # noqa: BLE001 - the motion ends with a message
                self.motions.pop(kind, None)
                self.failed.emit(m.what, error_text(exc))
                continue
            self.motion.emit(kind, {"open": True, "position_deg": pos, "busy": busy})
            if not busy:
                self.motions.pop(kind, None)
                self.done.emit(m.what, pos)
            elif time.monotonic() > m.deadline:
                self.motions.pop(kind, None)
                why = f"motion did not end within {m.timeout_s:.0f} s (at {pos:.3f} deg)"
                try:
                    with self.locks.hold(kind, timeout_s=2.0, who=m.what):
                        dev.stop()
                    why += "; the axis was stopped"
                except Exception as exc:  # noqa: BLE001
                    why += f"; stopping it failed: {error_text(exc)}"
                self.failed.emit(m.what, why)

    def _stop_motions(self) -> None:
        for kind, m in list(self.motions.items()):
            try:
                with self.locks.hold(kind, timeout_s=2.0, who="closing"):
                    getattr(self.rig, kind).stop()
            except Exception:  # noqa: BLE001 - closing: nothing more to do
                pass
        self.motions.clear()

    def _poll(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for kind in DEVICE_KINDS:
            dev = getattr(self.rig, kind)
            st: dict[str, Any] = {"open": False}
            try:
                st["open"] = bool(dev.is_open)
                if st["open"]:
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
            except Exception as exc:  # noqa: BLE001 - a driver bug is a status, not a crash
                st["error"] = error_text(exc)
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
        self.worker.notice.connect(self.message)
        self.worker.polled.connect(self._polled)
        self.worker.motion.connect(self._axis_update)
        self.timer = QTimer(self)
        self.timer.setInterval(poll_ms)
        self.timer.timeout.connect(self.worker.request_poll)

    def start(self) -> None:
        self.worker.start()
        self.timer.start()
        self.worker.request_poll()

    def begin_shutdown(self) -> None:
        """Stop polling, forget queued jobs, stop moving axes and end the worker (after the
        job in progress, if any: a homing runs to its end). Does not wait."""
        self.timer.stop()
        self.worker.stop(drop_queued=True)

    def shutdown(self, wait_ms: int = 5000) -> bool:
        if self.worker.isRunning():
            self.begin_shutdown()
        else:
            self.timer.stop()
        return self.worker.wait(wait_ms)

    # -- actions (queue jobs; results arrive as signals)
    def _dev(self, kind: str):
        return getattr(self.rig, kind)

    def connect_device(self, kind: str) -> None:
        self.worker.submit(kind, f"connect {kind}", self._dev(kind).open)

    def disconnect_device(self, kind: str) -> None:
        self.worker.submit(kind, f"disconnect {kind}", self._dev(kind).close, ends_motion=True)

    def connect_all(self) -> None:
        for kind in DEVICE_KINDS:
            if not self._dev(kind).is_open:
                self.connect_device(kind)

    def disconnect_all(self) -> None:
        for kind in DEVICE_KINDS:
            self.disconnect_device(kind)

    def move(self, kind: str, angle_deg: float) -> None:
        """Start a move (not waiting for it: the worker follows it, see the module)."""
        dev = self._dev(kind)
        angle_deg = float(angle_deg)

        def start() -> float:
            here = float(dev.position_deg())
            dev.move_to(angle_deg, wait=False)
            return motion_timeout_s(dev, angle_deg - here)

        self.worker.submit(kind, f"move {kind} to {angle_deg:g} deg", start, motion=True)

    def home(self, kind: str) -> None:
        self.worker.submit(kind, f"home {kind}", self._dev(kind).home, ends_motion=True)

    def stop_axis(self, kind: str) -> None:
        """Stop the axis now: before any job waiting in the queue (a motion in progress does
        not occupy the worker; a homing does, until it ends)."""
        self.worker.submit_urgent(kind, f"stop {kind}", self._dev(kind).stop)

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

    def _axis_update(self, kind: str, st: dict[str, Any]) -> None:
        """An axis's state and position (from the status poll or a followed motion)."""
        box = self.stage if kind == "stage" else self.turntable
        box.state.setText("moving" if st.get("busy") else ("open" if st["open"] else "closed"))
        if "position_deg" in st:
            box.position.setText(f"{st['position_deg']:.3f} deg")

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
        for kind in ("stage", "turntable"):
            self._axis_update(kind, status[kind])
        st = status["light"]
        if "level" in st:
            self.light_state.setText(light_words(st))
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


def light_words(status: dict[str, Any]) -> str:
    """The light's polled status in words: ``"on, level 0.500"`` (booleans as on/off, never
    ``"on True"``)."""
    parts = []
    for key, value in status.items():
        if key == "open":
            continue
        if key == "on":
            parts.insert(0, "on" if value else "off")
        elif isinstance(value, bool):
            parts.append(f"{key.replace('_', ' ')} {'yes' if value else 'no'}")
        elif isinstance(value, float):
            parts.append(f"{key.replace('_', ' ')} {value:.3f}")
        else:
            parts.append(f"{key.replace('_', ' ')} {value}")
    return ", ".join(parts)
