"""The main window: tabs for live view, devices, capture, calibration and the viewer; a
dialog-free message area; the live frame rate in the status bar; settings and shortcuts.

Device access is arbitrated by one :class:`polrig.gui.rigaccess.RigLocks`: while a capture or
a calibration step runs, the live view is paused and the manual device controls are disabled
(the task holds every device lock); while a calibration step runs a capture cannot start
(Ctrl+R is disabled, the panel refuses at once) and the other way round. Closing the window
during a capture asks the capture to stop (the session is left ``interrupted`` and resumable)
and closes once it has; closing during a manual move stops the axes and closes at once
(during a homing, once it has ended). Settings values the widgets cannot take are skipped and
named, and a settings file that cannot be read or written is reported (a message and a line
on stderr).
"""

from __future__ import annotations

import sys
from typing import Any, Callable

from PySide6.QtCore import QByteArray, Qt
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QDockWidget, QLabel, QMainWindow, QScrollArea, QTabWidget, QWidget

from polrig.gui import settings as st
from polrig.gui.calibration_panel import CalibrationPanel
from polrig.gui.capture_panel import CapturePanel
from polrig.gui.devices import DevicesPanel
from polrig.gui.live import LiveSettings, LiveWorker
from polrig.gui.live_panel import LivePanel
from polrig.gui.rigaccess import RigLocks
from polrig.gui.viewer import ViewerPanel
from polrig.gui.widgets import MessageArea, scrolled
from polrig.sensor.analyzer import resolve_layout

STOP_KEYS = ("Esc", "Ctrl+.")
CAPTURE_KEY = "Ctrl+R"


def _n_colours(rig) -> int:
    try:
        return resolve_layout(rig.camera.layout).n_colours
    except Exception:  # noqa: BLE001 - a closed real camera may not know its layout yet
        return 3


class MainWindow(QMainWindow):
    """``MainWindow(rig, settings)``: ``rig`` from :func:`polrig.app.rig.build_rig` (opened by the
    window's devices worker), ``settings`` a ``QSettings``. Call :meth:`start` after showing."""

    def __init__(self, rig, settings, *, model_loader: Callable[[], Any] | None = None,
                 live_max_fps: float = 30.0, poll_ms: int = 500, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = RigLocks()
        self.qsettings = settings
        self._closing = False
        self._settings_saved = False
        self._close_when_devices_end = False
        self.setWindowTitle(f"polrig - {rig.source or 'simulated rig'}")

        self.live_worker = LiveWorker(rig, self.locks, LiveSettings(max_fps=live_max_fps),
                                      model_loader)
        self.live = LivePanel(self.live_worker, _n_colours(rig))
        self.devices = DevicesPanel(rig, self.locks, poll_ms=poll_ms)
        self.capture = CapturePanel(rig, self.locks)
        self.calibration = CalibrationPanel(rig, self.locks)
        self.viewer = ViewerPanel()
        self.tabs = QTabWidget()
        #: each panel's page: the panel in a scroll area (:func:`polrig.gui.widgets.scrolled`): the
        #: window opens at 1280x860 and fits a 1080p screen (its least height was 1149 px before)
        self.pages: dict[QWidget, QScrollArea] = {}
        for w, name in ((self.live, "Live"), (self.devices, "Devices"),
                        (self.capture, "Capture"), (self.calibration, "Calibration"),
                        (self.viewer, "Viewer")):
            self.pages[w] = scrolled(w)
            self.tabs.addTab(self.pages[w], name)
        self.setCentralWidget(self.tabs)

        self.messages = MessageArea()
        dock = QDockWidget("Messages")
        dock.setObjectName("messages")
        dock.setWidget(self.messages)
        dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable)
        self.addDockWidget(Qt.DockWidgetArea.BottomDockWidgetArea, dock)
        self.fps_label = QLabel("live: -")
        self.statusBar().addPermanentWidget(self.fps_label)

        for panel in (self.live, self.devices, self.capture, self.calibration, self.viewer):
            panel.message.connect(self.show_message)
        self.live.status.connect(self.fps_label.setText)
        self.devices.camera_values.connect(self._camera_values)
        self.capture.running.connect(lambda r: self._task_running("capture", r))
        self.calibration.running.connect(lambda r: self._task_running("calibration", r))

        self.capture_action = QAction("Start capture", self)
        self.capture_action.setShortcut(QKeySequence(CAPTURE_KEY))
        self.capture_action.triggered.connect(self.capture.start)
        self.stop_action = QAction("Stop capture", self)
        self.stop_action.setShortcuts([QKeySequence(k) for k in STOP_KEYS])
        self.stop_action.triggered.connect(self.capture.stop)
        for a in (self.capture_action, self.stop_action):
            a.setShortcutContext(Qt.ShortcutContext.WindowShortcut)
            self.addAction(a)
        menu = self.menuBar().addMenu("&Capture")
        menu.addAction(self.capture_action)
        menu.addAction(self.stop_action)

        self.binder = st.SettingsBinder(settings)
        self._bind_settings()
        bad = self.binder.restore()
        problem = st.settings_problem(settings, "read")  # known once something was read
        if problem:
            self._settings_warning(problem)
        elif bad:
            self._settings_warning(
                f"settings {settings.fileName()}: skipped invalid value{'s' if len(bad) > 1 else ''}"
                f" of {', '.join(bad)} (the defaults are used)")
        geo = settings.value("window/geometry")
        if isinstance(geo, QByteArray):
            self.restoreGeometry(geo)
        else:
            self.resize(1280, 860)

    def _bind_settings(self) -> None:
        b, lp, cp = self.binder, self.live, self.capture
        b.bind("live/display", st.combo_binding(lp.display))
        b.bind("live/colour", st.combo_binding(lp.colour))
        b.bind("live/demosaic", st.combo_binding(lp.method))
        b.bind("live/saturation_overlay", st.bool_binding(lp.overlay))
        b.bind("live/mirror_average", st.bool_binding(lp.mirror_average))
        b.bind("live/resolution", st.combo_binding(lp.resolution))
        b.bind("live/network_binning", st.combo_binding(lp.binning))
        b.bind("live/min_snr", st.float_binding(lp.min_snr))
        for key, w in (("poses", cp.poses), ("states", cp.states), ("exposure", cp.exposure),
                       ("calibration", cp.calibration), ("out", cp.out)):
            b.bind(f"capture/{key}", st.text_binding(w))
        b.bind("capture/mode", st.combo_binding(cp.mode))
        b.bind("capture/mirror_average", st.bool_binding(cp.mirror_average))
        b.bind("capture/resolution", st.combo_binding(cp.resolution))
        b.bind("capture/network_binning", st.combo_binding(cp.binning))
        b.bind("capture/device", st.combo_binding(cp.device))
        b.bind("capture/model_size", st.combo_binding(cp.model_size))
        b.bind("capture/models", st.combo_binding(cp.models))
        b.bind("capture/demosaic", st.combo_binding(cp.demosaic))
        b.bind("capture/frames", st.int_binding(cp.frames))
        b.bind("capture/dark_frames", st.int_binding(cp.dark_frames))
        b.bind("capture/target_sigma", st.float_binding(cp.target_sigma))
        b.bind("capture/target_share", st.float_binding(cp.target_share))
        b.bind("capture/max_states", st.int_binding(cp.max_states))
        b.bind("capture/min_states", st.int_binding(cp.min_states))
        b.bind("capture/seen_state", st.int_binding(cp.seen_state))
        b.bind("capture/prior_scale", st.combo_binding(cp.prior_scale))
        b.bind("capture/exr_planes", st.text_binding(cp.exr_planes))
        b.bind("capture/exr_uncertainty", st.combo_binding(cp.exr_uncertainty))
        b.bind("capture/exr_compression", st.combo_binding(cp.exr_compression))
        # the operator is the same from one capture to the next; the sample, the note and the
        # further keys describe one capture, so each new one starts without them
        b.bind("capture/operator", st.text_binding(cp.operator))
        b.bind("calibration/folder", st.text_binding(self.calibration.folder))
        b.bind("window/tab", (self.tabs.currentIndex, lambda v: self.tabs.setCurrentIndex(int(v))))

    def show_panel(self, panel: QWidget) -> None:
        """Bring ``panel`` (one of the window's panels: ``live``, ``devices``, ``capture``,
        ``calibration``, ``viewer``) to the front."""
        self.tabs.setCurrentWidget(self.pages[panel])

    # -- life cycle
    def start(self) -> None:
        """Start the workers and connect every device (off the UI thread)."""
        self.devices.start()
        self.devices.connect_all()
        self.live_worker.start()

    def show_message(self, level: str, text: str) -> None:
        self.messages.add(level, text)
        # elided to the room left of the live line (permanent): the two never overlap; the
        # whole text is in the messages dock
        bar = self.statusBar()
        room = max(80, bar.width() - self.fps_label.sizeHint().width() - 40)
        short = bar.fontMetrics().elidedText(text, Qt.TextElideMode.ElideRight, room)
        bar.showMessage(short, 15000 if level == "error" else 5000)

    def _settings_warning(self, text: str) -> None:
        """A settings problem: in the messages and once on stderr (it may concern a file the
        operator edited; the window may be closing)."""
        self.show_message("warning", text)
        try:
            print(f"polrig: warning: {text}", file=sys.stderr, flush=True)
        except (OSError, ValueError):
            pass

    def _camera_values(self, exposure_us: float, gain_db: float) -> None:
        if not (self.live.exposure.hasFocus() or self.live.gain.hasFocus()):
            self.live.set_camera_values(exposure_us, gain_db)

    def _task_running(self, task: str, running: bool) -> None:
        busy = running or self.capture.is_running or self.calibration.is_running
        self.live.pause_for(task, busy)
        self.devices.setEnabled(not busy)
        calibrating, capturing = self.calibration.is_running, self.capture.is_running
        self.capture.setEnabled(not calibrating)
        self.capture.blocked_by = "a calibration step" if calibrating else ""
        self.capture_action.setEnabled(not calibrating)
        self.calibration.setEnabled(not capturing)
        self.calibration.blocked_by = "a capture" if capturing else ""
        if not busy and self._closing:
            self.close()

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt naming
        if self.capture.is_running or self.calibration.is_running:
            self._closing = True
            self.capture.stop()
            if self.calibration.worker is not None:
                self.calibration.worker.cancelled.set()
            self.show_message("info", "closing once the running task has stopped...")
            event.ignore()
            return
        if not self._settings_saved:
            self._settings_saved = True
            self.binder.save()
            self.qsettings.setValue("window/geometry", self.saveGeometry())
            self.qsettings.sync()
            problem = st.settings_problem(self.qsettings, "saved")
            if problem:
                self._settings_warning(problem)
        self.live_worker.stop()
        dw = self.devices.worker
        self.devices.begin_shutdown()  # moving axes are stopped, queued jobs dropped
        if dw.isRunning() and not dw.wait(200):  # a blocking call (a homing) in progress
            self._closing = True
            self.show_message("info", f"closing once '{dw.current or 'a device call'}' has "
                                      f"ended...")
            if not self._close_when_devices_end:
                self._close_when_devices_end = True
                dw.finished.connect(self.close)
            event.ignore()
            return
        self.shutdown()
        event.accept()

    def shutdown(self) -> None:
        """Stop the workers and close the rig (idempotent). Waits for a device call in
        progress to end (the longest HAL timeout is a 60 s homing) so that no thread is
        destroyed while it runs."""
        self.live_worker.stop()
        self.live_worker.wait(15000)
        self.devices.shutdown(wait_ms=65000)
        self.viewer.shutdown()
        self.live.roi.shutdown()
        self.capture.shutdown()
        self.rig.close()
