"""Capture panel: the options of ``polrig capture``, start/pause/stop/resume, progress with
ETA, thumbnails of finished poses and (simulated rig) the score against truth.

The form becomes a typed :class:`polrig.app.capture.CaptureRequest` (as ``polrig capture``'s
options do) and :class:`CaptureWorker` runs it with the call ``polrig capture`` makes,
:func:`polrig.app.capture.run_capture`, in a ``QThread``, on the window's rig with every
device lock held, and shows its events. The ETA comes from the plan's hardware time from the
first event, scaled by the observed pace once frames arrive. In the adaptive mode each
decision (states taken, share of the object pixels at target, what it does next) is logged, put
on the ETA line (its event carries the forecast the decision revised) and listed under "Adaptive
decisions" as it is made. When a resumed adaptive session starts, the list first shows, greyed
and marked "(recorded)", the decisions its earlier runs took for the captures this run keeps
(complete or acquired: :func:`polrig.app.capture.kept_decisions`, read from its
``session.json``); a capture that is acquired again (interrupted, failed) decides again from
scratch, its earlier decisions are dropped and its new ones come live, so none is listed
twice. Pause and stop go through
:class:`polrig.app.capture.CaptureControl`; a stop (or closing the window) leaves the session
``interrupted`` and resumable. Once the session exists, every way a run can end is reported
like ``polrig capture`` reports it: complete, or stopped with the reason (a device fault, a
full disk, any other file-system error, a processing error) and the hint that the completed
captures are intact and "Resume session in folder" continues; only a refusal before the
session exists (bad options, devices not connected, devices busy) is "not started". A finished
pose's thumbnail is read from its result on a thread of its own (about 0.8 s at the full
sensor), so the window never waits for it.
"""

from __future__ import annotations

import contextlib
import pathlib
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Iterator

import numpy as np
from PySide6.QtCore import QSize, Qt, QThread, Signal
from PySide6.QtGui import QIcon, QPalette, QPixmap
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QListWidget,
    QListWidgetItem,
    QProgressBar,
    QPushButton,
    QSpinBox,
    QVBoxLayout,
    QWidget,
)

from polrig.acquisition.plan import (
    ADAPTIVE_MAX_STATES,
    MODES,
    NETWORK_MODES,
    PRIOR_MODES,
    CapturePlan,
    ExrChoice,
    parse_float_list,
    parse_pose_spec,
)
from polrig.app import capture
from polrig.app.capture import (
    CaptureControl,
    CaptureRequest,
    Progress,
    RecordedDecision,
    SessionOpened,
)
from polrig.app.manifest import SampleMetadata
from polrig.app.preview import tone_map
from polrig.choices import DEFAULT_PRIOR_SCALE, MODEL_CHOICES, PRIOR_SCALES
from polrig.errors import PolrigError
from polrig.formats.exr import (
    COMPRESSIONS,
    RESULT_PLANES,
    UNCERTAINTY_PRECISIONS,
    read_mueller_exr,
)
from polrig.gui.devices import window_advice
from polrig.gui.pipeline import fast_white
from polrig.gui.qtimage import to_qimage
from polrig.gui.rigaccess import RigLocks
from polrig.gui.widgets import network_binning_box
from polrig.solve.scoring import format_score

THUMB_PX = 128


def thumbnail_rgb(path: pathlib.Path, size: int = THUMB_PX) -> np.ndarray:
    """A small preview of a capture's Mueller EXR: the tone-mapped ``m00`` (RGB), resized."""
    import cv2

    m00 = read_mueller_exr(path).mueller[:, 0, 0]
    rgb = tone_map(m00, white=fast_white(m00))
    h, w = rgb.shape[:2]
    s = size / max(h, w)
    return cv2.resize(rgb, (max(1, int(w * s)), max(1, int(h * s))),
                      interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)


class CaptureWorker(QThread):
    """Runs one capture session (new or resumed) with :func:`polrig.app.capture.run_capture`.
    Signals: ``progress(Progress)``, ``finished_result(status, reason, result)`` (``result``
    the :class:`polrig.app.capture.SessionResult`; any error once the session exists ends
    here, as an ``interrupted`` result), ``failed(message)`` (a refusal before the session
    exists: bad options, devices not connected or busy; nothing written),
    ``session_ready(opened)`` (the session exists and the run starts: its
    :class:`polrig.app.capture.SessionOpened`)."""

    progress = Signal(object)
    finished_result = Signal(str, str, object)
    failed = Signal(str)
    session_ready = Signal(object)

    def __init__(self, rig, locks: RigLocks, request: CaptureRequest, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = locks
        self.request = request
        self.control = CaptureControl()
        self.result = None

    def run(self) -> None:
        try:
            self._run()
        except (PolrigError, OSError, ValueError) as exc:
            self.failed.emit(str(exc))
        except Exception as exc:  # noqa: BLE001 - report, never kill the GUI
            self.failed.emit(f"{type(exc).__name__}: {exc}")

    def _run(self) -> None:
        result = capture.run_capture(self.request, command_line=["polrig", "gui"],
                                     rig=self._held_rig, events=self._event,
                                     control=self.control)
        self.result = result
        self.finished_result.emit(result.status, result.reason or "", result)

    @contextlib.contextmanager
    def _held_rig(self) -> Iterator[Any]:
        """The window's rig for the run, with every device lock held and every device
        connected (checked once the request is valid, before anything is written)."""
        with self.locks.hold(timeout_s=10.0, who="capture"):
            closed = [k for k, d in self.rig.devices.items() if not d.is_open]
            if closed:
                raise PolrigError(f"not connected: {', '.join(closed)}; connect the "
                                  f"devices (Devices tab) before capturing")
            yield self.rig

    def _event(self, ev) -> None:
        if isinstance(ev, SessionOpened):
            self.session_ready.emit(ev)
        else:
            self.progress.emit(ev)


class CapturePanel(QWidget):
    """Options form, controls, progress, thumbnails. ``running(bool)`` tells the window to
    pause the live view and lock the device controls; ``message(level, text)`` logs."""

    running = Signal(bool)
    message = Signal(str, str)
    #: a finished pose's thumbnail, from the thumbnail thread: run, row, QImage (None: failed),
    #: the warning when it failed
    thumbnail_ready = Signal(int, int, object, str)

    def __init__(self, rig, locks: RigLocks, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = locks
        self.worker: CaptureWorker | None = None
        #: thumbnails are read from the poses' result EXRs here, off the UI thread (about 0.8 s
        #: each at the full sensor); ``_run_id`` tells a run's from those of an earlier one
        self._thumbnailer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="thumbnails")
        self._run_id = 0
        self.thumbnail_ready.connect(self._thumbnail_ready)
        self._active = False
        self.events: list[Progress] = []
        self.scores: dict[int, dict[str, Any]] = {}
        self.last_status = ""
        #: why a capture cannot start now (set by the window while a calibration step runs)
        self.blocked_by = ""
        self._request: CaptureRequest | None = None
        self._t_start = 0.0
        self._step0 = 0

        self.poses = QLineEdit("0:360:90")
        self.poses.setToolTip("turntable poses in degrees: a list 0,30,60 or a range "
                              "START:STOP:STEP with STOP exclusive")
        self.mode = QComboBox()
        self.mode.addItems(list(MODES))
        self.mode.setToolTip("reference: N >= 3 polarizer states solved per pixel; single-shot: the "
                             "trained network on one state; hybrid: N >= 1 states solved with the "
                             "network's estimate of the seen state as a prior; adaptive: the "
                             "network's state, then states chosen from the posterior until the "
                             "target holds")
        self.mirror_average = QCheckBox("Mirror-average the network (single-shot: twice the network time, "
                                        "a few per cent lower error)")
        self.mirror_average.setEnabled(False)
        self.resolution = QComboBox()
        self.resolution.addItems(["superpixel", "full"])
        self.resolution.setToolTip("single-shot output: the networks' superpixel grid, or the raw "
                                   "frame's full resolution (detail from the demosaic, bilinear "
                                   "where it is superpixel; no sigma)")
        self.resolution.setEnabled(False)
        self.binning = network_binning_box("single-shot")
        self.binning.setEnabled(False)
        self.device = QComboBox()
        self.device.addItems(["auto", "cpu", "cuda"])
        self.device.setToolTip("where the single-shot network runs (auto: CUDA where onnxruntime "
                               "offers it); the provider used is recorded in each result")
        self.device.setEnabled(False)
        self.model_size = QComboBox()
        self.model_size.addItems(["auto", "small", "large"])  # polrig.models.sizes.CHOICES
        self.model_size.setToolTip("single-shot model: small (CPU networks), large (trained on a GPU; "
                                   "refused while not shipped) or auto (large on CUDA where shipped); "
                                   "each result records its size, training hardware and minutes")
        self.model_size.setEnabled(False)
        for w in (self.resolution, self.binning):  # hybrid: superpixel, unbinned (calibrated sigma)
            self.mode.currentTextChanged.connect(
                lambda m, w=w: w.setEnabled(m == "single-shot"))
        self.seen_state = QSpinBox()
        self.seen_state.setRange(0, 359)
        self.seen_state.setToolTip("hybrid: index into the states of the one whose frame the network sees")
        self.seen_state.setEnabled(False)
        for w in (self.mirror_average, self.device, self.model_size):
            self.mode.currentTextChanged.connect(
                lambda m, w=w: w.setEnabled(m in NETWORK_MODES))
        self.mode.currentTextChanged.connect(lambda m: self.seen_state.setEnabled(m == "hybrid"))
        self.models = QComboBox()
        self.models.addItems(list(MODEL_CHOICES))
        self.models.setToolTip("full: the 3x3 block at every pixel; auto (reference, hybrid): per pixel "
                               "the lower-order model a likelihood-ratio test accepts; diffuse (hybrid, two "
                               "states): the diffuse term (with the specular term where significant) tested on "
                               "their samples alone and the direction "
                               "they leave open predicted from the rig's geometry. The model map is always "
                               "written")
        self.mode.currentTextChanged.connect(lambda m: self.models.setEnabled(m != "single-shot"))
        self.prior_scale = QComboBox()
        self.prior_scale.addItems(list(PRIOR_SCALES))
        self.prior_scale.setCurrentText(DEFAULT_PRIOR_SCALE)
        self.prior_scale.setToolTip("hybrid, adaptive: innovations scales the network's calibrated sigma per "
                                    "capture by how far the states after the seen one find its estimate off "
                                    "(each result records the factor); geometry does that and, at two states, "
                                    "scales the prior along the direction they leave open by what the diffuse "
                                    "term at the rig's geometry finds; calibrated keeps it as calibrated. "
                                    "A resumed session goes on with its own")
        self.prior_scale.setEnabled(False)
        self.mode.currentTextChanged.connect(lambda m: self.prior_scale.setEnabled(m in PRIOR_MODES))
        # adaptive: the stopping rule (polrig.acquisition.plan.check_adaptive_target checks it)
        self.target_sigma = QDoubleSpinBox()
        self.target_sigma.setDecimals(4)
        self.target_sigma.setRange(0.0, 1.0)
        self.target_sigma.setSingleStep(0.01)
        self.target_sigma.setSpecialValueText("required (e.g. 0.05)")  # shown at 0: not given
        self.target_sigma.setToolTip("adaptive: stop a pose once each object pixel's posterior "
                                     "sigma, RMS of the nine elements over m00, is at most this")
        self.target_share = QDoubleSpinBox()
        self.target_share.setDecimals(3)
        self.target_share.setRange(0.0, 1.0)
        self.target_share.setSingleStep(0.01)
        self.target_share.setValue(CapturePlan.target_share)
        self.target_share.setToolTip("adaptive: the share of the object pixels that must meet the "
                                     "target for a pose to stop")
        self.max_states = QSpinBox()
        self.max_states.setRange(1, ADAPTIVE_MAX_STATES)
        self.max_states.setValue(CapturePlan.max_states)
        self.max_states.setToolTip("adaptive: the most polarizer states a pose takes, the "
                                   "network's first one included")
        self.min_states = QSpinBox()
        self.min_states.setRange(1, ADAPTIVE_MAX_STATES)
        self.min_states.setValue(CapturePlan.min_states)
        self.min_states.setToolTip("adaptive: the fewest polarizer states a pose takes before the "
                                   "target may stop it (2: the network's sigma is checked by a "
                                   "state it did not see; 1: a pose may stop on the network alone)")
        self.max_states.valueChanged.connect(self.min_states.setMaximum)  # never above the most
        # one form row (the panel is tall already), on in the adaptive mode only
        self.adaptive_target = QWidget()
        row = QHBoxLayout(self.adaptive_target)
        row.setContentsMargins(0, 0, 0, 0)
        for label, w in (("relative sigma", self.target_sigma), ("share", self.target_share),
                         ("min states", self.min_states), ("max states", self.max_states)):
            row.addWidget(QLabel(label))
            row.addWidget(w, 1)
        self.adaptive_target.setEnabled(False)
        self.mode.currentTextChanged.connect(
            lambda m: self.adaptive_target.setEnabled(m == "adaptive"))
        self.states = QLineEdit()
        self.states.setPlaceholderText("0,45,90,135")
        self.states.setToolTip("polarizer stage angles in degrees (single-shot and adaptive: the "
                               "one state the network sees, default 0; adaptive chooses the others)")
        self.frames = QSpinBox()
        self.frames.setRange(1, 1000)
        self.exposure = QLineEdit()
        self.exposure.setPlaceholderText("camera's current (us; several = HDR bracket)")
        self.dark_frames = QSpinBox()
        self.dark_frames.setRange(0, 1000)
        self.demosaic = QComboBox()
        self.demosaic.addItems(["superpixel", "bilinear", "newton"])

        self.exr_planes = QLineEdit(",".join(RESULT_PLANES))
        self.exr_planes.setToolTip("plane groups of each result EXR, comma separated (mueller "
                                   "always written)")
        self.exr_uncertainty = QComboBox()
        self.exr_uncertainty.addItems(list(UNCERTAINTY_PRECISIONS))
        self.exr_uncertainty.setCurrentText(ExrChoice().uncertainty)
        self.exr_uncertainty.setToolTip("precision of the sigma, sigma_noise, residual and mask "
                                        "planes: float32, or half (half the bytes)")
        self.exr_compression = QComboBox()
        self.exr_compression.addItems(list(COMPRESSIONS))
        self.exr_compression.setCurrentText(ExrChoice().compression)
        self.calibration = QLineEdit()
        self.calibration.setPlaceholderText("nominal")
        # who, why, what (polrig.app.manifest.SampleMetadata; a resume keeps the stored one)
        self.sample, self.operator, self.note = QLineEdit(), QLineEdit(), QLineEdit()
        self.md = QLineEdit()
        self.md.setPlaceholderText("KEY=VALUE; KEY=VALUE")
        self.md.setToolTip("further metadata keys (identifiers, not polrig's own keys), "
                           "separated by ';'")
        self.out = QLineEdit()
        browse = QPushButton("Browse...")
        browse.clicked.connect(self._browse)
        out_row = QHBoxLayout()
        out_row.addWidget(self.out, 1)
        out_row.addWidget(browse)
        form = QFormLayout()
        form.addRow("Poses (deg)", self.poses)
        form.addRow("Mode", self.mode)
        form.addRow("", self.mirror_average)
        form.addRow("Resolution", self.resolution)
        form.addRow("Network binning", self.binning)
        form.addRow("Network device", self.device)
        form.addRow("Model size", self.model_size)
        form.addRow("Seen state (hybrid)", self.seen_state)
        form.addRow("Models per pixel", self.models)
        form.addRow("Prior scale", self.prior_scale)
        form.addRow("Target (adaptive)", self.adaptive_target)
        form.addRow("States (deg)", self.states)
        form.addRow("Frames per state", self.frames)
        form.addRow("Exposure(s)", self.exposure)
        form.addRow("Dark frames", self.dark_frames)
        form.addRow("Demosaic", self.demosaic)
        form.addRow("Result planes", self.exr_planes)
        form.addRow("Uncertainty precision", self.exr_uncertainty)
        form.addRow("EXR compression", self.exr_compression)
        form.addRow("Calibration set", self.calibration)
        form.addRow("Sample", self.sample)
        form.addRow("Operator", self.operator)
        form.addRow("Note", self.note)
        form.addRow("More metadata", self.md)
        form.addRow("Output folder", out_row)
        opts = QGroupBox("Capture options (as polrig capture)")
        opts.setLayout(form)

        self.start_button = QPushButton("Start capture (Ctrl+R)")
        self.pause_button = QPushButton("Pause")
        self.pause_button.setCheckable(True)
        self.stop_button = QPushButton("Stop (Esc)")
        self.resume_button = QPushButton("Resume session in folder")
        self.start_button.clicked.connect(self.start)
        self.pause_button.toggled.connect(self.set_paused)
        self.stop_button.clicked.connect(self.stop)
        self.resume_button.clicked.connect(self.resume)
        buttons = QHBoxLayout()
        for b in (self.start_button, self.pause_button, self.stop_button, self.resume_button):
            buttons.addWidget(b)
        self.progress = QProgressBar()
        self._progress_idle("no capture yet")
        self.eta = QLabel("idle")
        self.score = QLabel("")
        self.score.setWordWrap(True)
        self.score.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.thumbs = QListWidget()
        self.thumbs.setViewMode(QListWidget.ViewMode.IconMode)
        self.thumbs.setIconSize(QSize(THUMB_PX, THUMB_PX))
        self.thumbs.setFlow(QListWidget.Flow.LeftToRight)
        self.thumbs.setWrapping(False)
        self.thumbs.setFixedHeight(THUMB_PX + 48)
        #: an adaptive capture's decisions, one line each (shown from the first): on a resume
        #: those recorded before for the captures kept, "(recorded)", then those made live
        self.decisions = QListWidget()
        self.decisions.setToolTip("each adaptive decision: the states taken so far, the share of "
                                  "the object pixels at target, and the next state or why it stopped")
        self.decisions.setFixedHeight(THUMB_PX + 48)  # beside the thumbnails, as tall
        self.decisions_box = QWidget()
        box = QVBoxLayout(self.decisions_box)
        box.setContentsMargins(0, 0, 0, 0)
        box.addWidget(QLabel("Adaptive decisions"))
        box.addWidget(self.decisions)
        self.decisions_box.setVisible(False)
        lay = QVBoxLayout(self)
        lay.addWidget(opts)
        lay.addLayout(buttons)
        lay.addWidget(self.progress)
        lay.addWidget(self.eta)
        poses = QVBoxLayout()
        poses.setContentsMargins(0, 0, 0, 0)
        poses.addWidget(QLabel("Finished poses"))
        poses.addWidget(self.thumbs)
        results = QHBoxLayout()  # an adaptive capture's decisions beside its poses
        results.addLayout(poses, 1)
        results.addWidget(self.decisions_box, 1)
        lay.addLayout(results)
        lay.addWidget(self.score)
        lay.addStretch(1)
        self._set_running(False)

    # -- options
    def request(self, resume: bool = False) -> CaptureRequest:
        """The form as a typed request (:class:`polrig.app.capture.CaptureRequest`); on
        ``resume`` only the folder and calibration: the plan is the session's. Raises
        :class:`polrig.acquisition.plan.PlanError` / ``ValueError`` (one line) for a field that does not
        parse."""

        out = self.out.text().strip()
        if not out:
            raise ValueError("choose an output folder for the session")
        calibration = self.calibration.text().strip()
        base = dict(out=pathlib.Path(out), resume=resume,
                    calibration=pathlib.Path(calibration) if calibration else None,
                    device=self.device.currentText(), model_size=self.model_size.currentText())
        if resume:  # the session's own models and prior scale (polrig.app.capture_request.resumed_processing)
            return CaptureRequest(**base)
        base["models"] = self.models.currentText() if self.mode.currentText() != "single-shot" else "full"
        states, exposure = self.states.text().strip(), self.exposure.text().strip()
        mode = self.mode.currentText()
        return CaptureRequest(
            **base, poses_deg=parse_pose_spec(self.poses.text().strip()), mode=mode,
            states_deg=(parse_float_list(states, "polarizer states", field="states_deg")
                        if states else None),
            frames_per_state=self.frames.value(),
            exposures_us=(parse_float_list(exposure, "exposures", positive=True,
                                           field="exposures_us") if exposure else None),
            dark_frames=self.dark_frames.value(), demosaic=self.demosaic.currentText(),
            mirror_average=mode in NETWORK_MODES and self.mirror_average.isChecked(),
            seen_state=self.seen_state.value() if mode == "hybrid" else 0,
            target_sigma=self.target_sigma.value() if mode == "adaptive" else None,
            target_share=self.target_share.value() if mode == "adaptive" else None,
            max_states=self.max_states.value() if mode == "adaptive" else None,
            min_states=self.min_states.value() if mode == "adaptive" else None,
            resolution=self.resolution.currentText() if mode == "single-shot" else "superpixel",
            network_binning=int(self.binning.currentData()) if mode == "single-shot" else 1,
            prior_scale=self.prior_scale.currentText() if mode in PRIOR_MODES else None,
            exr_planes=tuple(p.strip() for p in self.exr_planes.text().split(",") if p.strip()),
            exr_uncertainty=self.exr_uncertainty.currentText(),
            exr_compression=self.exr_compression.currentText(),
            metadata=SampleMetadata(
                sample=self.sample.text().strip(), operator=self.operator.text().strip(),
                note=self.note.text().strip(),
                user=SampleMetadata.parse_user(t for t in self.md.text().split(";") if t.strip())))

    def _browse(self) -> None:
        path = QFileDialog.getExistingDirectory(self, "Session folder", self.out.text())
        if path:
            self.out.setText(path)

    # -- control
    @property
    def is_running(self) -> bool:
        return self._active

    def start(self) -> None:
        self._launch_form(resume=False)

    def resume(self) -> None:
        self._launch_form(resume=True)

    def _launch_form(self, resume: bool) -> None:
        try:
            req = self.request(resume=resume)
        except (PolrigError, ValueError) as exc:  # a field that does not parse: not started
            self._failed(str(exc))
            return
        self._launch(req)

    def _launch(self, req: CaptureRequest) -> None:
        if self.is_running:
            self.message.emit("warning", "a capture is already running")
            return
        if self.blocked_by:
            self.message.emit("error", f"capture: cannot start while {self.blocked_by} runs")
            return
        self._request = req
        self._run_id += 1  # thumbnails still on their way belong to the earlier run
        self.events.clear()
        self.scores.clear()
        self.thumbs.clear()
        self.decisions.clear()
        self.decisions_box.setVisible(False)
        self.score.setText("")
        self._progress_idle("starting...")
        self.eta.setText("starting...")
        self.last_status = "running"
        w = CaptureWorker(self.rig, self.locks, req, self)
        w.progress.connect(self._progress)
        w.finished_result.connect(self._finished)
        w.failed.connect(self._failed)
        w.session_ready.connect(self._session_ready)
        w.finished.connect(lambda: self._set_running(False))
        self.worker = w
        self._t_start, self._step0 = time.monotonic(), 0
        self._set_running(True)
        w.start()

    def _session_ready(self, opened: SessionOpened) -> None:
        for recorded in opened.decisions:  # a resumed adaptive session: what it decided before
            self._recorded_decision(recorded)
        self.message.emit("info", f"capture {'resumed' if opened.resumed else 'started'} in "
                                  f"{opened.root}")

    def set_paused(self, paused: bool) -> None:
        if self.worker is None:
            return
        (self.worker.control.pause.set if paused else self.worker.control.pause.clear)()
        self.pause_button.setText("Continue" if paused else "Pause")
        self.eta.setText("paused" if paused else "continuing...")

    def stop(self) -> None:
        if self.is_running:
            self.worker.control.stop.set()
            self.worker.control.pause.clear()
            self.eta.setText("stopping after the current frame...")
            self.message.emit("info", "capture: stop requested")

    def _set_running(self, running: bool) -> None:
        self._active = running
        self.start_button.setEnabled(not running)
        self.resume_button.setEnabled(not running)
        self.pause_button.setEnabled(running)
        self.stop_button.setEnabled(running)
        if not running:
            self.pause_button.blockSignals(True)
            self.pause_button.setChecked(False)
            self.pause_button.setText("Pause")
            self.pause_button.blockSignals(False)
        self.running.emit(running)

    # -- events from the worker
    def _progress_idle(self, text: str) -> None:
        """The bar when no capture runs: empty, saying why (not a made-up '0 / 100 frames')."""
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat(text)

    def _progress(self, ev: Progress) -> None:
        self.events.append(ev)
        if ev.total:
            self.progress.setFormat("%v / %m frames")
            self.progress.setMaximum(ev.total)
            self.progress.setValue(ev.step)
        if ev.kind == "capture-start" and not self._step0:
            self._t_start, self._step0 = time.monotonic(), max(ev.step, 0)
        if ev.kind == "capture-start" and ev.hardware_s:  # the plan's time, from the first event
            self.eta.setText(f"capture {ev.capture_index + 1}/{ev.n_captures}, pose "
                             f"{ev.pose_deg:g} deg, ETA {_fmt_s(self._eta_s(ev))}")
        control = self.worker.control if self.worker is not None else None
        if ev.kind == "frame" and ev.total and control is not None and (
                control.pause.is_set() or control.stop.is_set()):
            pass  # a frame that was on its way: "paused" / "stopping..." stays on the label
        elif ev.kind == "frame" and ev.total:
            eta = self._eta_s(ev)
            self.eta.setText(f"capture {ev.capture_index + 1}/{ev.n_captures}, pose "
                             f"{ev.pose_deg:g} deg, frame {ev.step}/{ev.total}, ETA "
                             f"{_fmt_s(eta)}")
        elif ev.kind == "decision":
            self._decision(ev, control)
        elif ev.kind == "retry":
            self.message.emit("warning", f"capture: {ev.message}")
        elif ev.kind == "capture-failed":
            self.message.emit(self._stop_level(), f"capture {ev.capture_index + 1} pose "
                                                  f"{ev.pose_deg:g} deg: "
                                                  f"{window_advice(ev.message)}")
        elif ev.kind == "capture-done":
            self._capture_done(ev)

    def _recorded_decision(self, recorded: RecordedDecision) -> None:
        """A decision an earlier run of the resumed session took (a capture the run keeps:
        :func:`polrig.app.capture.kept_decisions`), listed as the live ones are, marked
        "(recorded)" and greyed."""
        item = QListWidgetItem(f"capture {recorded.capture_index + 1}, pose "
                               f"{recorded.pose_deg:g} deg: {recorded.describe()} (recorded)")
        item.setForeground(self.decisions.palette().color(QPalette.ColorRole.PlaceholderText))
        item.setToolTip("taken by an earlier run of this session (its session.json); the run "
                        "keeps this capture")
        self.decisions.addItem(item)
        self.decisions.scrollToBottom()
        self.decisions_box.setVisible(True)

    def _decision(self, ev: Progress, control: CaptureControl | None) -> None:
        """An adaptive decision: logged, listed under "Adaptive decisions" and, unless a pause
        or stop was asked for, on the ETA label with the ETA it revised."""
        where = f"capture {ev.capture_index + 1}, pose {ev.pose_deg:g} deg"
        self.decisions.addItem(f"{where}: {ev.message}")
        self.decisions.scrollToBottom()
        self.decisions_box.setVisible(True)
        if control is None or not (control.pause.is_set() or control.stop.is_set()):
            self.eta.setText(f"capture {ev.capture_index + 1}/{ev.n_captures}, pose "
                             f"{ev.pose_deg:g} deg, {ev.message}, ETA {_fmt_s(self._eta_s(ev))}")
        self.message.emit("info", f"{where}: decision: {ev.message}")

    def _eta_s(self, ev: Progress) -> float:
        """Remaining time: the plan's remaining hardware time (known from the first event),
        scaled by the pace observed so far (processing, a slow host) once frames arrive."""
        done_hw = ev.hardware_s - ev.hardware_left_s
        el = time.monotonic() - self._t_start
        if ev.hardware_s > 0:
            pace = el / done_hw if done_hw > 0 and el > 0 else 1.0
            return ev.hardware_left_s * max(pace, 1.0)
        done = ev.step - self._step0
        return el / done * (ev.total - ev.step) if done > 0 else float("nan")

    def _capture_done(self, ev: Progress) -> None:
        text = f"pose {ev.pose_deg:g} deg"
        if ev.score:
            self.scores[ev.capture_index] = ev.score
            line = format_score(ev.score)
            self.score.setText("\n".join(f"capture {i + 1}: {format_score(s)}"
                                         for i, s in sorted(self.scores.items())))
            self.message.emit("info", f"capture {ev.capture_index + 1} ({text}) done | {line}")
        else:
            self.message.emit("info", f"capture {ev.capture_index + 1} ({text}) done")
        self.thumbs.addItem(QListWidgetItem(text))
        if ev.result is not None:  # its icon comes from the thumbnail thread
            self._thumbnailer.submit(self._make_thumbnail, self._run_id,
                                     self.thumbs.count() - 1, ev.result, ev.pose_deg)

    def _make_thumbnail(self, run: int, row: int, path: pathlib.Path, pose_deg: float) -> None:
        """The thumbnail thread: read and scale one pose's result, hand it to the UI thread."""
        image, warning = None, ""
        try:
            image = to_qimage(thumbnail_rgb(path))
        except (OSError, PolrigError, ValueError) as exc:
            warning = f"thumbnail of pose {pose_deg:g}: {exc}"
        except Exception as exc:  # noqa: BLE001 - a thumbnail must not be lost silently
            warning = f"thumbnail of pose {pose_deg:g}: {type(exc).__name__}: {exc}"
        self.thumbnail_ready.emit(run, row, image, warning)

    def _thumbnail_ready(self, run: int, row: int, image, warning: str) -> None:
        if run != self._run_id:  # a new run started meanwhile: its list was cleared
            return
        item = self.thumbs.item(row)
        if item is None:
            return
        if image is not None:
            item.setIcon(QIcon(QPixmap.fromImage(image)))
        else:
            self.message.emit("warning", warning)

    @property
    def thumbnails_shown(self) -> int:
        """How many finished poses show their thumbnail."""
        return sum(not self.thumbs.item(i).icon().isNull() for i in range(self.thumbs.count()))

    def shutdown(self) -> None:
        """End the thumbnail thread (a thumbnail being made is finished, the others dropped)
        before the panel goes."""
        self._thumbnailer.shutdown(wait=True, cancel_futures=True)

    def _finished(self, status: str, reason: str, result: object) -> None:
        self.last_status = status
        reason = window_advice(reason)  # a safety stop: home the axis here, then resume
        if status == "complete":
            n = len(getattr(result, "completed", ())) or len(self.scores) or self.thumbs.count()
            self.eta.setText(f"session complete ({n} captures)")
            self.message.emit("info", "capture: session complete")
        else:
            self.eta.setText(f"session {status}: {reason} (resume to continue)")
            self.message.emit(self._stop_level(), f"capture stopped: {reason}; completed "
                                                  f"captures are intact, use 'Resume session "
                                                  f"in folder' to continue")

    def _stop_level(self) -> str:
        """Message level of a capture that ended early: ``info`` when the operator asked for
        the stop (Stop, closing the window), ``error`` otherwise."""
        control = self.worker.control if self.worker is not None else None
        return "info" if control is not None and control.stop.is_set() else "error"

    def _failed(self, text: str) -> None:
        self.last_status = "failed"
        text = window_advice(text)
        self.eta.setText(f"not started: {text}")
        if not self.events:  # refused before the first frame: no count to show
            self._progress_idle("not started")
        self.message.emit("error", f"capture: {text}")


def _fmt_s(s: float) -> str:
    if not np.isfinite(s):
        return "--"
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
