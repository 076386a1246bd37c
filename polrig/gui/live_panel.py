"""Live view panel: display choice, camera controls, image, cursor readout, histogram.

The panel owns a :class:`polrig.gui.live.LiveWorker`; on ``frame_ready`` it takes the latest
result from the worker's slot (never blocking) and shows it.

The Mueller display on the device route (CUDA) gets the 3x3 grid already reduced to display
size (:meth:`polrig.app.single_shot.SingleShot.live`): the grid, its histogram and a readout
of display-pixel means. ROI statistics and line profiles need every image pixel: once an ROI
or a line is drawn the panel asks the worker for whole frames
(:attr:`polrig.gui.live.LiveSettings.full_mueller`, :meth:`~polrig.app.single_shot.SingleShot.frame`;
slower) and measures those; until one is drawn the ROI summary says so.
"""

from __future__ import annotations

import time

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from polrig.gui import pipeline
from polrig.gui.live import LiveResult, LiveSettings, LiveWorker
from polrig.gui.roi_panel import AolpWheel, RoiTools
from polrig.gui.widgets import (
    HistogramWidget,
    ImageView,
    ReadoutLabel,
    min_snr_box,
    network_binning_box,
    scrolled,
)

DEMOSAIC_METHODS = ("superpixel", "bilinear", "newton")
#: Displays the live view offers: all but the viewer's Mueller layers that need their own
#: controls (parameter map, virtual polarizer).
LIVE_DISPLAYS = tuple(k for k in pipeline.DISPLAYS if k not in ("maps", "polarizer"))
#: Least time between two ROI statistics of live frames (seconds): a table that changes faster
#: cannot be read, and the statistics of a Mueller frame cost a parameter-map computation.
ROI_INTERVAL_S = 0.5


def colour_choices(n_colours: int) -> list[tuple[str, int]]:
    if n_colours == 1:
        return [("Y (mono)", pipeline.LUMINANCE)]
    return [("luminance / RGB", pipeline.LUMINANCE), ("R", 0), ("G", 1), ("B", 2)]


class LivePanel(QWidget):
    """Live camera view. ``status(text)`` carries the frame-rate line for the status bar."""

    status = Signal(str)
    message = Signal(str, str)

    def __init__(self, worker: LiveWorker, n_colours: int = 3, parent=None):
        super().__init__(parent)
        self.worker = worker
        self.frames_shown = 0
        self.paused_text = ""
        self.last: LiveResult | None = None
        self._hover = (-1, -1)

        self.display = QComboBox()
        for key in LIVE_DISPLAYS:
            self.display.addItem(pipeline.DISPLAYS[key], key)
        self.colour = QComboBox()
        for label, value in colour_choices(n_colours):
            self.colour.addItem(label, value)
        self.method = QComboBox()
        self.method.addItems(DEMOSAIC_METHODS)
        self.exposure = QDoubleSpinBox()
        self.exposure.setRange(10.0, 10_000_000.0)
        self.exposure.setDecimals(0)
        self.exposure.setSuffix(" us")
        self.exposure.setKeyboardTracking(False)
        self.gain = QDoubleSpinBox()
        self.gain.setRange(0.0, 48.0)
        self.gain.setSuffix(" dB")
        self.gain.setKeyboardTracking(False)
        self.overlay = QCheckBox("saturation overlay (red)")
        self.overlay.setChecked(True)
        self.mirror_average = QCheckBox("Mueller: mirror-average the network (twice the time)")
        self.resolution = QComboBox()
        self.resolution.addItems(["superpixel", "full"])
        self.resolution.setToolTip("Mueller display: the networks' superpixel grid, or the raw frame's "
                                   "full resolution (the measured detail of the demosaic, bilinear "
                                   "where the demosaic is superpixel)")
        self.binning = network_binning_box("Mueller display")
        self.min_snr = min_snr_box()
        self.pause_button = QPushButton("Pause live")
        self.pause_button.setCheckable(True)

        form = QFormLayout()
        form.addRow("Display", self.display)
        form.addRow("Colour", self.colour)
        form.addRow("Demosaic", self.method)
        form.addRow("Exposure", self.exposure)
        form.addRow("Gain", self.gain)
        form.addRow("Mask below SNR", self.min_snr)
        form.addRow(self.overlay)
        form.addRow(self.mirror_average)
        form.addRow("Mueller resolution", self.resolution)
        form.addRow("Mueller network binning", self.binning)
        form.addRow(self.pause_button)
        self.readout = ReadoutLabel("move the cursor over the image")
        self.histogram = HistogramWidget()
        self.view = ImageView(placeholder="waiting for the camera...")
        self.wheel = AolpWheel(110)
        self.roi = RoiTools(self.view)
        self.roi.message.connect(self.message)
        self._roi_at = 0.0
        side = QVBoxLayout()
        side.addLayout(form)
        side.addWidget(QLabel("Histogram and AoLP colour wheel"))
        row = QHBoxLayout()
        row.addWidget(self.histogram, 1)
        row.addWidget(self.wheel)
        side.addLayout(row)
        side.addWidget(self.readout.area, 1)
        side.addWidget(self.roi, 2)
        side_w = QWidget()
        side_w.setLayout(side)
        side_w.setMinimumWidth(430)
        side_area = scrolled(side_w)  # the controls scroll, the image scales
        side_area.setMinimumWidth(450)
        side_area.setMaximumWidth(540)
        split = QSplitter()
        split.addWidget(self.view)
        split.addWidget(side_area)
        split.setStretchFactor(0, 3)
        lay = QHBoxLayout(self)
        lay.addWidget(split)

        s = worker.settings  # the combos start at the worker's settings
        self.display.setCurrentIndex(max(0, self.display.findData(s.display)))
        self.colour.setCurrentIndex(max(0, self.colour.findData(s.colour)))
        self.method.setCurrentText(s.method)
        self.overlay.setChecked(s.saturation_overlay)
        self.mirror_average.setChecked(s.mirror_average)
        self.resolution.setCurrentText(s.resolution)
        self.binning.setCurrentIndex(max(0, self.binning.findData(s.network_binning)))
        self.min_snr.setValue(s.min_snr)
        self.min_snr.valueChanged.connect(self._settings_changed)
        self.display.currentIndexChanged.connect(self._settings_changed)
        self.colour.currentIndexChanged.connect(self._settings_changed)
        self.method.currentIndexChanged.connect(self._settings_changed)
        self.overlay.toggled.connect(self._settings_changed)
        self.mirror_average.toggled.connect(self._settings_changed)
        self.resolution.currentIndexChanged.connect(self._settings_changed)
        self.binning.currentIndexChanged.connect(self._settings_changed)
        self.exposure.valueChanged.connect(lambda v: self.worker.set_camera(exposure_us=v))
        self.gain.valueChanged.connect(lambda v: self.worker.set_camera(gain_db=v))
        self.pause_button.toggled.connect(self._pause_toggled)
        self.view.hovered.connect(self._hovered)
        self.view.drawn.connect(self._measuring_changed)
        worker.frame_ready.connect(self._take_frame)
        worker.message.connect(self.message)
        worker.stalled.connect(self._stalled)

    # -- settings
    def settings(self) -> LiveSettings:
        return self.worker.settings

    def set_display(self, key: str) -> None:
        self.display.setCurrentIndex(max(0, self.display.findData(key)))

    def set_camera_values(self, exposure_us: float, gain_db: float) -> None:
        """Show the camera's values without sending them back to the camera."""
        for box, v in ((self.exposure, exposure_us), (self.gain, gain_db)):
            box.blockSignals(True)
            box.setValue(v)
            box.blockSignals(False)

    def _settings_changed(self, *_a) -> None:
        s = self.worker.settings
        s.display = self.display.currentData()
        s.colour = self.colour.currentData()
        s.method = self.method.currentText()
        s.saturation_overlay = self.overlay.isChecked()
        s.mirror_average = self.mirror_average.isChecked()
        s.resolution = self.resolution.currentText()
        s.network_binning = int(self.binning.currentData())
        s.min_snr = self.min_snr.value()

    def _measuring_changed(self, *_a) -> None:
        """An ROI or a line drawn: the Mueller display takes whole frames from now on (the
        device route's live grid has display-pixel means only)."""
        self.worker.settings.full_mueller = self.roi.region is not None or self.roi.segment is not None

    def _pause_toggled(self, paused: bool) -> None:
        self.worker.pause(paused)
        self.pause_button.setText("Resume live" if paused else "Pause live")
        self._show_paused("live view paused (Resume live to continue)" if paused else "")

    def _show_paused(self, text: str) -> None:
        """Say on the image and in the status line that the view is paused (the image is the
        last frame, not a live one; the frame rate is not shown); "" when live again."""
        self.paused_text = text
        self.view.set_banner(text.upper().split(" (")[0] if text else "")
        self.status.emit(text if text else "live: resuming...")

    def _stalled(self, reason: str) -> None:
        """Frames stopped coming: the status line says why instead of the last frame rate."""
        if not self.worker.paused:
            self.status.emit(f"live: no frames - {reason}")

    def pause_for(self, reason: str, paused: bool) -> None:
        """Pause/resume for another task (a capture); the button shows why."""
        self.worker.pause(paused or self.pause_button.isChecked())
        self.pause_button.setEnabled(not paused)
        if paused:
            self._show_paused(f"live view paused: {reason} running")
        elif self.pause_button.isChecked():
            self._show_paused("live view paused (Resume live to continue)")
        else:
            self._show_paused("")

    # -- frames
    def _take_frame(self) -> None:
        res = self.worker.slot.take()
        if res is None or self.worker.paused:  # a frame finished as the view paused: dropped
            return
        self.last = res
        self.frames_shown += 1
        self.view.set_image(res.image)
        self.histogram.set_data(*res.hist)
        self.wheel.set_mode(pipeline.AOLP_DOLP_AS.get(res.display, "value"))
        now = time.monotonic()
        self.roi.to_data = lambda pts: pipeline.display_to_data(res.data, res.display, pts,
                                                                res.step)
        self._measuring_changed()
        if pipeline.needs_full_image(res.data, res.display):  # display-pixel means: nothing to measure
            if self.roi.data is not None:  # an older frame's (say, Stokes only): never measured as this one
                self.roi.set_data(None)
            if self.roi.region is None and self.roi.segment is None:
                self.roi.summary.setText("ROI statistics need the whole Mueller image: this grid is "
                                         "rendered at display size on the device; draw an ROI or a "
                                         "line and the live view takes whole frames (slower)")
        elif (now - self._roi_at >= ROI_INTERVAL_S or self.roi.data is None) and not self.roi.busy:
            # a frame's statistics replace the previous frame's once those are shown: a new
            # request while one is computed would drop that one, and with statistics slower
            # than the interval (seconds at the full sensor) the table would never fill
            self._roi_at = now
            self.roi.set_data(res.data)
        if self._hover != (-1, -1):
            self._hovered(*self._hover)
        h, w = pipeline.display_shape(res.data, res.display)
        shape = f"{w}x{h}" + (f" (shown 1:{res.step})" if res.step > 1 else "")
        text = (f"live {res.fps:.1f} fps | frame {res.frame_id} | {shape} "
                f"{pipeline.DISPLAYS[res.display]} | exposure {res.exposure_us:g} us, gain "
                f"{res.gain_db:g} dB | processing {1e3 * res.processing_s:.0f} ms | dropped "
                f"{self.worker.dropped}")
        if res.note:
            text += f" | {res.note}"
        self.status.emit(text)

    def _hovered(self, x: int, y: int) -> None:
        self._hover = (x, y)
        if self.last is None or x < 0:
            return
        self.readout.setText(pipeline.readout(self.last.data, self.last.display, x, y, self.last.step))
