"""Calibration panel: the procedures of :mod:`calibration.procedures`, step by step.

Steps in their order (each uses the results of the earlier ones): intrinsics, turntable axis,
light position, generator (stage zero) offset, DoFP analyzer. A step runs in
:class:`CalibrationWorker` (a ``QThread`` holding every device lock); the procedure's ``log``
lines stream into the panel, and its report (the log, the result's numbers, and the camera's
view at the end of the step as PNG) is shown and, when a report folder is set, written there
as ``<step>.txt`` and ``<step>.png``.

Targets: on the simulated rig the procedure's ``mount(target, **fixture)`` swaps the simulated
target (:func:`sim.targets.mount`); on hardware the panel asks the operator to mount it and
waits for "Target in place".
"""

from __future__ import annotations

import dataclasses
import pathlib
import threading
from typing import Any, Callable

import numpy as np
from PySide6.QtCore import QThread, Signal
from PySide6.QtWidgets import (QDoubleSpinBox, QFormLayout, QHBoxLayout, QLabel, QLineEdit,
                               QListWidget, QPlainTextEdit, QPushButton, QSplitter, QVBoxLayout,
                               QWidget)

from polrig.errors import PolrigError
from polrig.gui.qtimage import to_qimage
from polrig.gui.rigaccess import RigLocks
from polrig.gui.widgets import ImageView

STEPS = (("intrinsics", "Camera intrinsics (ChArUco board)"),
         ("turntable", "Turntable axis (board at several angles)"),
         ("light", "Light position (chrome sphere)"),
         ("generator", "Polarizer stage zero offset (board at grazing light)"),
         ("dofp", "DoFP analyzer per pixel (polished plate)"))


class CalibrationState:
    """Results of the steps run so far (what the next steps need)."""

    def __init__(self) -> None:
        self.results: dict[str, Any] = {}

    def camera(self):
        tt = self.results.get("turntable")
        if tt is not None:
            return tt.K, tt.dist
        intr = self.results.get("intrinsics")
        if intr is not None:
            return intr.result.K, intr.result.dist
        raise PolrigError("run the intrinsics step first")

    def need(self, step: str):
        if step not in self.results:
            raise PolrigError(f"run the {step} step first")
        return self.results[step]


def run_step(step: str, rig, state: CalibrationState, mount: Callable[..., None],
             log: Callable[[str], None], sphere_radius_m: float) -> Any:
    """Run one calibration step with the procedures of :mod:`calibration.procedures`."""
    from calibration import procedures as P

    spec = board_spec(rig)
    if step == "intrinsics":
        return P.run_intrinsics(rig, mount, spec, log=log)
    if step == "turntable":
        intr = state.results.get("intrinsics")
        if intr is None:
            K, dist = state.camera()
            return P.run_turntable(rig, mount, spec, None, K, dist, log=log)
        return P.run_turntable(rig, mount, spec, intr, log=log)
    K, dist = state.camera()
    if step == "light":
        return P.run_light(rig, mount, K, dist, sphere_radius_m, log=log)
    axis = state.need("turntable").axis
    light = state.need("light").position_cam_m
    if step == "generator":
        return P.run_generator_offset(rig, mount, spec, K, dist, axis, light, log=log)
    if step == "dofp":
        off = state.need("generator").zero_offset_deg
        return P.run_dofp(rig, mount, spec, K, dist, axis, light, off, log=log)
    raise ValueError(f"unknown calibration step {step!r}")


def board_spec(rig):
    """The ChArUco board: the simulated one on the simulated rig, else the default spec."""
    if getattr(rig, "sim", None) is not None:
        from sim.targets import board_spec as sim_board

        return sim_board()
    from calibration.charuco import BoardSpec

    return BoardSpec()


def default_sphere_radius_m() -> float:
    try:
        from sim.targets import DEFAULTS

        return float(DEFAULTS["sphere_radius_m"])
    except (ImportError, KeyError):
        return 0.0125


def result_summary(result: Any, depth: int = 0) -> list[str]:
    """Readable lines of a procedure's result dataclass: scalars and small arrays (large
    arrays are summarised by their shape)."""
    lines: list[str] = []
    if not dataclasses.is_dataclass(result):
        return [repr(result)]
    for f in dataclasses.fields(result):
        v = getattr(result, f.name)
        pad = "  " * depth
        if dataclasses.is_dataclass(v):
            lines.append(f"{pad}{f.name}:")
            lines += result_summary(v, depth + 1)
        elif isinstance(v, np.ndarray):
            lines.append(f"{pad}{f.name} = " + (np.array2string(v, precision=5)
                                               if v.size <= 12 else f"<{v.shape} {v.dtype}>"))
        elif isinstance(v, (int, float, str, bool)) or v is None:
            lines.append(f"{pad}{f.name} = {v}")
        elif isinstance(v, (list, tuple)):
            lines.append(f"{pad}{f.name}: {len(v)} items")
    return lines


class CalibrationWorker(QThread):
    """Runs one step. Signals: ``log(text)``, ``mount_request(text)`` (hardware),
    ``step_done(step, result, report_text, rgb)``, ``step_failed(step, message)``."""

    log = Signal(str)
    mount_request = Signal(str)
    step_done = Signal(str, object, str, object)
    step_failed = Signal(str, str)

    def __init__(self, rig, locks: RigLocks, state: CalibrationState, step: str,
                 sphere_radius_m: float, parent=None):
        super().__init__(parent)
        self.rig, self.locks, self.state, self.step = rig, locks, state, step
        self.sphere_radius_m = sphere_radius_m
        self.mounted = threading.Event()
        self.cancelled = threading.Event()
        self.lines: list[str] = []

    def _log(self, text: str) -> None:
        self.lines.append(text)
        self.log.emit(text)

    def _mount(self, target: str, **fixture: Any) -> None:
        what = target + (f" ({', '.join(f'{k}={v}' for k, v in fixture.items())})"
                         if fixture else "")
        if getattr(self.rig, "sim", None) is not None:
            from sim.targets import mount

            mount(self.rig.sim, target, **fixture)
            self._log(f"simulated target mounted: {what}")
            return
        self.mounted.clear()
        self.mount_request.emit(f"Mount the {what}, then press 'Target in place'.")
        while not self.mounted.wait(0.2):
            if self.cancelled.is_set():
                raise PolrigError("calibration cancelled by the operator")

    def run(self) -> None:
        try:
            with self.locks.hold(timeout_s=10.0, who="calibration"):
                result = run_step(self.step, self.rig, self.state, self._mount, self._log,
                                  self.sphere_radius_m)
                rgb = self._camera_view()
        except Exception as exc:  # noqa: BLE001 - calibration errors are typed; report all
            self.step_failed.emit(self.step, f"{type(exc).__name__}: {exc}")
            return
        report = "\n".join([f"step: {self.step}", "", "log:", *self.lines, "", "result:",
                            *result_summary(result)])
        self.step_done.emit(self.step, result, report, rgb)

    def _camera_view(self) -> np.ndarray | None:
        """S0 of one frame at the end of the step (the report picture)."""
        from polrig.gui import pipeline

        try:
            frame = self.rig.camera.grab()
        except PolrigError:
            return None
        return pipeline.render(pipeline.process_frame(frame), "s0")


class CalibrationPanel(QWidget):
    """Step list, run buttons, live log, report text and picture."""

    running = Signal(bool)
    message = Signal(str, str)

    def __init__(self, rig, locks: RigLocks, parent=None):
        super().__init__(parent)
        self.rig, self.locks = rig, locks
        self.state = CalibrationState()
        self.worker: CalibrationWorker | None = None
        self._active = False
        self.reports: dict[str, str] = {}
        self.steps = QListWidget()
        for key, label in STEPS:
            self.steps.addItem(f"{label}")
        self.steps.setCurrentRow(0)
        self.run_button = QPushButton("Run selected step")
        self.run_button.clicked.connect(self.run_selected)
        self.mounted_button = QPushButton("Target in place")
        self.mounted_button.setEnabled(False)
        self.mounted_button.clicked.connect(self._mounted)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self._cancel)
        self.sphere_radius = QDoubleSpinBox()
        self.sphere_radius.setDecimals(5)
        self.sphere_radius.setRange(0.001, 0.5)
        self.sphere_radius.setValue(default_sphere_radius_m())
        self.sphere_radius.setSuffix(" m")
        self.report_dir = QLineEdit()
        self.report_dir.setPlaceholderText("folder for <step>.txt/.png reports (optional)")
        self.prompt = QLabel("")
        self.prompt.setWordWrap(True)
        self.log_view = QPlainTextEdit()
        self.log_view.setReadOnly(True)
        self.report_view = QPlainTextEdit()
        self.report_view.setReadOnly(True)
        self.picture = ImageView(placeholder="report picture")

        form = QFormLayout()
        form.addRow("Chrome sphere radius", self.sphere_radius)
        form.addRow("Report folder", self.report_dir)
        left = QVBoxLayout()
        left.addWidget(QLabel("Steps (in order)"))
        left.addWidget(self.steps)
        left.addLayout(form)
        row = QHBoxLayout()
        for b in (self.run_button, self.mounted_button, self.cancel_button):
            row.addWidget(b)
        left.addLayout(row)
        left.addWidget(self.prompt)
        left.addWidget(QLabel("Log"))
        left.addWidget(self.log_view, 1)
        lw = QWidget()
        lw.setLayout(left)
        right = QSplitter()
        right.setOrientation(right.orientation().Vertical)
        right.addWidget(self.report_view)
        right.addWidget(self.picture)
        split = QSplitter()
        split.addWidget(lw)
        split.addWidget(right)
        QHBoxLayout(self).addWidget(split)

    @property
    def is_running(self) -> bool:
        return self._active

    def run_selected(self) -> None:
        self.run_step(STEPS[max(0, self.steps.currentRow())][0])

    def run_step(self, step: str) -> None:
        if self.is_running:
            self.message.emit("warning", "a calibration step is already running")
            return
        w = CalibrationWorker(self.rig, self.locks, self.state, step,
                              self.sphere_radius.value(), self)
        w.log.connect(self.log_view.appendPlainText)
        w.mount_request.connect(self._mount_request)
        w.step_done.connect(self._done)
        w.step_failed.connect(self._failed)
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
        if self.worker is not None:
            self.worker.cancelled.set()

    def _done(self, step: str, result: object, report: str, rgb: object) -> None:
        self.state.results[step] = result
        self.reports[step] = report
        self.report_view.setPlainText(report)
        if rgb is not None:
            self.picture.set_image(to_qimage(rgb))
        folder = self.report_dir.text().strip()
        if folder:
            self._write_report(pathlib.Path(folder), step, report, rgb)
        self.message.emit("info", f"calibration step {step}: done")
        keys = [k for k, _ in STEPS]
        if keys.index(step) + 1 < len(keys):
            self.steps.setCurrentRow(keys.index(step) + 1)

    def _write_report(self, folder: pathlib.Path, step: str, report: str, rgb) -> None:
        import cv2

        try:
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{step}.txt").write_text(report + "\n", encoding="utf-8")
            if rgb is not None:
                cv2.imwrite(str(folder / f"{step}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        except OSError as exc:
            self.message.emit("error", f"calibration report: {exc}")

    def _failed(self, step: str, text: str) -> None:
        self.report_view.setPlainText(f"step: {step}\n\nFAILED: {text}")
        self.message.emit("error", f"calibration step {step} failed: {text}")
