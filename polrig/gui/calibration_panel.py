"""Calibration panel: the steps of ``polrig calibrate``, one at a time, with their reports.

The same core as the CLI: :func:`polrig.calibration.runner.run_steps` runs a step (in its order
intrinsics, turntable, light, stokes, dofp; a later step reads what the earlier ones stored in
the :class:`polrig.calibration.calset.CalibrationSet`), the set is saved into the chosen folder
(:meth:`CalibrationSet.save`) and :func:`polrig.calibration.report.write_report` writes
``report.md`` and its PNG plots there; on the simulated rig the result is also scored against
the simulator's hidden truth (:func:`polrig.calibration.runner.errors_against_truth`). A step runs in
:class:`CalibrationWorker` (a ``QThread`` holding every device lock); the procedure's log lines
stream into the panel, the report's text and PNGs are shown when it is done.

Targets: on the simulated rig the procedure's ``mount(target, **fixture)`` swaps the simulated
target (the rig's declared truth, :meth:`polrig.acquisition.hal.RigTruth.mount_target`, as
``polrig calibrate`` does); on hardware the panel asks the operator to mount it and waits for
"Target in place" (the CLI waits for Enter).

The procedures run through the same executor as a capture (:func:`polrig.calibration.runner.run_steps`
drives the rig through :class:`polrig.acquisition.engine.GuardedRig`: the capture's fault policy, retries
logged). Cancel stops the step at its next grab or move (the worker's cancel event is the
executor's stop request, :class:`polrig.acquisition.engine.CaptureControl`), log line or target mount
(:class:`CalibrationCancelled` from its callbacks); nothing new is saved and the panel reports
"cancelled". A device call already running (a turntable move, a grab) ends first.
"""

from __future__ import annotations

import pathlib
import threading
from typing import TYPE_CHECKING, Any, Callable

from PySide6.QtCore import Qt, QThread, Signal
from PySide6.QtGui import QImage
from PySide6.QtWidgets import (
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QListWidget,
    QListWidgetItem,
    QPlainTextEdit,
    QPushButton,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from polrig import calibration
from polrig.acquisition.engine import CaptureControl, StopRequested
from polrig.calibration import runner
from polrig.calibration.procedures import fixture_words  # noqa: F401 (re-exported)
from polrig.calibration.report import write_report
from polrig.calibration.runner import STEPS
from polrig.errors import PolrigError
from polrig.gui.devices import window_advice
from polrig.gui.rigaccess import RigLocks
from polrig.gui.widgets import ImageView

if TYPE_CHECKING:
    from polrig.app.rig import Rig

STEP_LABELS = {"intrinsics": "Camera intrinsics (ChArUco board)",
               "turntable": "Turntable axis (board at several angles)",
               "light": "Light position (chrome sphere)",
               "stokes": "Polarizer stage zero offset (board at grazing light)",
               "dofp": "DoFP analyzer per pixel + extinction ratio (polished plate)",
               "all": "All steps in order"}


def step_names() -> tuple[str, ...]:
    """The steps of :data:`polrig.calibration.runner.STEPS` and ``all``."""

    return tuple(STEPS) + ("all",)


class CalibrationCancelled(PolrigError):
    """The operator cancelled the calibration step."""


def simulated_mount(rig: Rig) -> Callable[..., None] | None:
    """The simulated rig's target swap where the rig declares its truth (every device
    simulated, :attr:`polrig.app.rig.Rig.truth`), else ``None``."""
    return None if rig.truth is None else rig.truth.mount_target


class CalibrationWorker(QThread):
    """Runs one step (or ``all``) into ``calset`` and writes the set and its report into
    ``folder``. Signals: ``log(text)``, ``mount_request(text)`` (hardware),
    ``step_done(step, report_path)``, ``step_failed(step, message)``, ``step_cancelled(step)``
    (nothing saved)."""

    log = Signal(str)
    mount_request = Signal(str)
    step_done = Signal(str, str)
    step_failed = Signal(str, str)
    step_cancelled = Signal(str)

    def __init__(self, rig, locks: RigLocks, calset, extras: dict, step: str,
                 folder: pathlib.Path, parent=None):
        super().__init__(parent)
        self.rig, self.locks, self.calset, self.extras = rig, locks, calset, extras
        self.step, self.folder = step, folder
        self.mounted = threading.Event()
        self.cancelled = threading.Event()

    def check_cancelled(self) -> None:
        """Raise :class:`CalibrationCancelled` once :attr:`cancelled` is set."""
        if self.cancelled.is_set():
            raise CalibrationCancelled("calibration cancelled by the operator")

    def _log(self, text: str) -> None:
        self.log.emit(text)
        self.check_cancelled()

    def _ask_mount(self, target: str, **fixture: Any) -> None:
        where = fixture_words(fixture) or "default position"
        self.mounted.clear()
        self.mount_request.emit(f"Mount the {target.replace('_', ' ')} ({where}), then press "
                                f"'Target in place'.")
        while not self.mounted.wait(0.2):
            self.check_cancelled()

    def run(self) -> None:
        steps = list(runner.STEPS) if self.step == "all" else [self.step]
        check = self.check_cancelled
        try:
            with self.locks.hold(timeout_s=10.0, who="calibration"):
                sim_mount = simulated_mount(self.rig)

                def mount(target: str, **fixture: Any) -> None:
                    check()
                    (sim_mount or self._ask_mount)(target, **fixture)

                runner.run_steps(steps, self.rig, mount, self.calset, extras=self.extras,
                                 log=self._log, control=CaptureControl(stop=self.cancelled))
                check()
                errors = None
                if self.rig.truth is not None:
                    errors = runner.errors_against_truth(
                        self.calset, self.rig.truth.rig_parameters(),
                        self.rig.truth.analyzer())
            check()  # the last moment a cancel keeps the folder as it was
            self.calset.save(self.folder)
            report = write_report(self.folder, self.calset, self.extras, errors)
        except (CalibrationCancelled, StopRequested):
            self.step_cancelled.emit(self.step)
            return
        except Exception as exc:  # noqa: BLE001 - calibration errors are typed; report all
            self.step_failed.emit(self.step, f"{type(exc).__name__}: {exc}")
            return
        self.step_done.emit(self.step, str(report))


class CalibrationPanel(QWidget):
    """Calibration set folder, step list, run buttons, live log, report text and PNGs."""

    running = Signal(bool)
    message = Signal(str, str)

    def __init__(self, rig, locks: RigLocks, parent=None):
        super().__init__(parent)
        self.rig, self.locks = rig, locks
        self.calset = None
        self.extras: dict = {}
        self._loaded_from: pathlib.Path | None = None
        self.worker: CalibrationWorker | None = None
        self._active = False
        #: why a step cannot start now (set by the window while a capture runs)
        self.blocked_by = ""
        self.report_path: pathlib.Path | None = None
        self.steps = QListWidget()
        for key in step_names():
            item = QListWidgetItem(f"{key}: {STEP_LABELS.get(key, key)}")
            item.setData(Qt.ItemDataRole.UserRole, key)
            self.steps.addItem(item)
        self.steps.setCurrentRow(0)
        # every step visible without scrolling (the list used to be clipped)
        rows = self.steps.count()
        self.steps.setMinimumHeight(self.steps.sizeHintForRow(0) * rows
                                    + 2 * self.steps.frameWidth() + 4)
        self.folder = QLineEdit()
        self.folder.setPlaceholderText("calibration set folder (created or updated)")
        self.run_button = QPushButton("Run selected step")
        self.run_button.clicked.connect(self.run_selected)
        self.mounted_button = QPushButton("Target in place")
        self.mounted_button.setEnabled(False)
        self.mounted_button.clicked.connect(self._mounted)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self._cancel)
        self.prompt = QLabel("")
        self.prompt.setWordWrap(True)
        self.log_view = QPlainTextEdit()
        self.log_view.setReadOnly(True)
        self.report_view = QPlainTextEdit()
        self.report_view.setReadOnly(True)
        self.pngs = QListWidget()
        self.pngs.currentItemChanged.connect(self._png_chosen)
        self.picture = ImageView(placeholder="report plots appear here")

        form = QFormLayout()
        form.addRow("Calibration set", self.folder)
        left = QVBoxLayout()
        left.addLayout(form)
        left.addWidget(QLabel("Steps (in order; a step needs the earlier ones)"))
        left.addWidget(self.steps)
        row = QHBoxLayout()
        for b in (self.run_button, self.mounted_button, self.cancel_button):
            row.addWidget(b)
        left.addLayout(row)
        left.addWidget(self.prompt)
        left.addWidget(QLabel("Log"))
        left.addWidget(self.log_view, 1)
        lw = QWidget()
        lw.setLayout(left)
        pics = QSplitter()
        pics.addWidget(self.pngs)
        pics.addWidget(self.picture)
        pics.setStretchFactor(1, 3)
        right = QSplitter(Qt.Orientation.Vertical)
        right.addWidget(self.report_view)
        right.addWidget(pics)
        split = QSplitter()
        split.addWidget(lw)
        split.addWidget(right)
        split.setStretchFactor(1, 2)
        QHBoxLayout(self).addWidget(split)

    @property
    def is_running(self) -> bool:
        return self._active

    def run_selected(self) -> None:
        item = self.steps.currentItem() or self.steps.item(0)
        self.run_step(item.data(Qt.ItemDataRole.UserRole))

    def _calibration_set(self, folder: pathlib.Path):
        """The set in ``folder`` (loaded once; a new one if the folder holds none)."""

        if self.calset is None or self._loaded_from != folder:
            self.extras = {}
            self.calset = (calibration.load(folder) if (folder / "calibration.json").is_file()
                           else calibration.CalibrationSet())
            self._loaded_from = folder
        return self.calset

    def run_step(self, step: str) -> None:
        if self.is_running:
            self.message.emit("warning", "a calibration step is already running")
            return
        if self.blocked_by:
            self.message.emit("error", f"calibration: cannot start while {self.blocked_by} runs")
            return
        text = self.folder.text().strip()
        if not text:
            self.message.emit("error", "calibration: choose a calibration set folder first")
            return
        folder = pathlib.Path(text)
        try:
            calset = self._calibration_set(folder)
        except (PolrigError, OSError, ValueError) as exc:
            self.message.emit("error", f"calibration: {folder}: {exc}")
            return
        w = CalibrationWorker(self.rig, self.locks, calset, self.extras, step, folder, self)
        w.log.connect(self.log_view.appendPlainText)
        w.mount_request.connect(self._mount_request)
        w.step_done.connect(self._done)
        w.step_failed.connect(self._failed)
        w.step_cancelled.connect(self._cancelled)
        w.finished.connect(lambda: self._set_running(False))
        self.worker = w
        self._set_running(True)
        self.log_view.appendPlainText(f"--- {step} ---")
        w.start()

    def _set_running(self, running: bool) -> None:
        self._active = running
        self.run_button.setEnabled(not running)
        self.cancel_button.setEnabled(running)
        if not running:
            self.mounted_button.setEnabled(False)
            self.prompt.setText("")
        self.running.emit(running)

    def _mount_request(self, text: str) -> None:
        self.prompt.setText(text)
        self.mounted_button.setEnabled(True)
        self.message.emit("info", f"calibration: {text}")

    def _mounted(self) -> None:
        if self.worker is not None:
            self.mounted_button.setEnabled(False)
            self.prompt.setText("")
            self.worker.mounted.set()

    def _cancel(self) -> None:
        if self.worker is not None and self.is_running:
            self.worker.cancelled.set()
            self.cancel_button.setEnabled(False)
            self.prompt.setText("cancelling at the next device call...")

    def _cancelled(self, step: str) -> None:
        folder = self._loaded_from
        self.report_view.setPlainText(f"step: {step}\n\nCANCELLED: nothing was saved; the "
                                      f"calibration set in {folder} is as it was")
        self.message.emit("warning", f"calibration step {step} cancelled; nothing saved in "
                                     f"{folder}")
        self.calset = None  # the folder's set is what counts: reloaded by the next step
        self._loaded_from = None

    def _done(self, step: str, report: str) -> None:
        self.report_path = pathlib.Path(report)
        self.report_view.setPlainText(self.report_path.read_text(encoding="utf-8"))
        self.pngs.clear()
        for png in sorted(self.report_path.parent.glob("*.png")):
            self.pngs.addItem(png.name)
        if self.pngs.count():
            self.pngs.setCurrentRow(0)
        self.message.emit("info", f"calibration step {step}: done (set {self.calset.id}, "
                                  f"report {report})")
        keys = step_names()
        i = keys.index(step)
        if i + 2 < len(keys):  # the next step (never jumps onto "all")
            self.steps.setCurrentRow(i + 1)

    def _png_chosen(self, item, _prev=None) -> None:
        if item is not None and self.report_path is not None:
            img = QImage(str(self.report_path.parent / item.text()))
            self.picture.set_image(None if img.isNull() else img)

    def _failed(self, step: str, text: str) -> None:
        text = window_advice(text)  # a safety fault: home the axis in this window
        self.report_view.setPlainText(f"step: {step}\n\nFAILED: {text}")
        self.message.emit("error", f"calibration step {step} failed: {text}")
