"""Live view: a worker ``QThread`` grabs and processes frames, the widget shows the latest one.

Threading: the worker is a two-stage pipeline so that both CPU cores work. Stage 1 (a thread
the worker starts) grabs (holding the camera lock of :class:`polrig.gui.rigaccess.RigLocks`)
and processes (:mod:`polrig.gui.pipeline`: Stokes/DoLP/AoLP, or single-shot Mueller
inference through the one route's live frame, :meth:`polrig.app.single_shot.SingleShot.live`,
with the settings' :class:`polrig.acquisition.plan.SingleShotOptions` and display size:
on the host route (the CPU) that is :meth:`~polrig.app.single_shot.SingleShot.frame`
unchanged; on the device route (CUDA) the 3x3 grid is rendered on the device at display size,
only it comes back, and the light-direction probe runs every few frames. What needs the whole
Mueller image, ROI statistics and profiles, sets :attr:`LiveSettings.full_mueller` and the
next frames go through :meth:`~polrig.app.single_shot.SingleShot.frame`); stage 2 (the ``QThread`` itself) renders the display image of the newest
processed frame and puts it into a :class:`LatestSlot` for the UI. Each hand-over is a
one-item slot: a newer item replaces one not taken yet (that frame is dropped and counted),
so nothing is ever queued without bound, and the UI thread never waits for a device or for
inference; it only takes what is in the slot when ``frame_ready`` fires. Camera settings
(exposure, gain) are handed to the worker and applied between frames.

Neither stage ever ends on an error: a device fault, a processing error or an unexpected
exception (a driver bug) becomes one message per distinct problem and ``stalled(reason)``
(the panel replaces the frame-rate line with it), and the loop tries again. A grab's timeout
follows the exposure (:func:`polrig.acquisition.hal.grab_timeout_s`), so long exposures reach the view.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from typing import Any, Callable

import numpy as np
from PySide6.QtCore import QThread, Signal
from PySide6.QtGui import QImage

from polrig.acquisition.hal import grab_timeout_s
from polrig.acquisition.plan import SingleShotOptions
from polrig.app import processing
from polrig.app.processing import sensor_model_of
from polrig.errors import DeviceDisconnected, PolrigError
from polrig.gui import pipeline
from polrig.gui.qtimage import to_qimage
from polrig.gui.rigaccess import DeviceBusy, RigLocks

#: What a live grab waits beyond the frame's exposure and readout, seconds (short: a camera
#: that stopped delivering shows as a message soon).
LIVE_GRAB_MARGIN_S = 2.0


class LatestSlot:
    """A one-item mailbox between threads: :meth:`put` replaces, :meth:`take` empties."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._item: Any = None
        self.dropped = 0

    def put(self, item: Any) -> bool:
        """Store ``item``; True when the slot was empty (the reader needs a notification),
        False when an unread item was replaced (dropped)."""
        with self._lock:
            was_empty = self._item is None
            if not was_empty:
                self.dropped += 1
            self._item = item
            return was_empty

    def take(self) -> Any:
        with self._lock:
            item, self._item = self._item, None
            return item


@dataclasses.dataclass
class LiveSettings:
    """What the worker computes (changed from the UI thread; read once per frame)."""

    display: str = "aolp_dolp"
    colour: int = pipeline.LUMINANCE
    method: str = "superpixel"
    saturation_overlay: bool = True
    #: Mueller display: average the network's answers for the frame and its mirror image
    #: (:mod:`polrig.models.mirror`; twice the network time)
    mirror_average: bool = False
    #: Mueller display: ``superpixel`` (the networks' grid) or ``full`` (the raw frame's size,
    #: the detail from ``method``, bilinear where that is superpixel:
    #: :meth:`polrig.acquisition.plan.SingleShotOptions.from_settings`)
    resolution: str = "superpixel"
    #: Mueller display: 2 runs the networks on the analyzer grid binned 2x2 (the faster mode:
    #: about half the frame time at full sensor size); 1 on the grid
    network_binning: int = 1
    max_fps: float = 30.0
    #: Longest side of the displayed image in pixels (0: full resolution); see
    #: :func:`polrig.gui.pipeline.display_step`. Processing is always at full resolution.
    max_display_px: int = pipeline.DEFAULT_MAX_DISPLAY_PX
    #: Threads of the strip-parallel Stokes step (0: automatic, see
    #: :func:`polrig.gui.pipeline.stokes_from_raw_strips`; 1: one core call).
    strip_workers: int = 0
    #: DoLP, AoLP and ``m_ij / m00`` are masked where ``S0`` is below this many noise
    #: standard deviations (:data:`polrig.app.preview.DEFAULT_MIN_SNR`; 0: off).
    min_snr: float = pipeline.preview.DEFAULT_MIN_SNR
    #: Mueller display: take whole frames (:meth:`polrig.app.single_shot.SingleShot.frame`)
    #: instead of live ones, whose device route brings back the display-size grid only: set
    #: while the panel measures an ROI or a line profile (they need every image pixel).
    full_mueller: bool = False


@dataclasses.dataclass
class LiveResult:
    """One processed frame, ready for the UI."""

    image: QImage
    data: pipeline.PolarizationData
    display: str
    colour: int
    frame_id: int
    exposure_us: float
    gain_db: float
    hist: tuple[np.ndarray, np.ndarray, str]
    processing_s: float
    fps: float
    note: str = ""
    step: int = 1  # display pixel (x, y) is data pixel (x * step, y * step)


class RateMeter:
    """Events per second over a sliding window of the last ``window_s`` seconds."""

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self.times: deque[float] = deque()

    def tick(self, t: float | None = None) -> None:
        t = time.perf_counter() if t is None else t
        self.times.append(t)
        while self.times and self.times[0] < t - self.window_s:
            self.times.popleft()

    def rate(self) -> float:
        if len(self.times) < 2:
            return 0.0
        span = self.times[-1] - self.times[0]
        return (len(self.times) - 1) / span if span > 0 else 0.0


class LiveWorker(QThread):
    """Grab -> process -> render loop (see the module docstring). ``rig`` is a
    :class:`polrig.app.rig.Rig`; ``model_loader`` returns the single-shot route
    (:class:`polrig.app.single_shot.SingleShot`, :func:`polrig.gui.app.model_loader`: called in
    this thread the first time the Mueller display is chosen, once per window; its exceptions
    become messages)."""

    frame_ready = Signal()
    message = Signal(str, str)  # level, text
    #: frames stopped coming: why (an error's text, "camera not connected"); once per reason
    stalled = Signal(str)

    def __init__(self, rig, locks: RigLocks, settings: LiveSettings | None = None,
                 model_loader: Callable[[], Any] | None = None, parent=None):
        super().__init__(parent)
        self.rig = rig
        self.locks = locks
        self.settings = settings or LiveSettings()
        self.slot = LatestSlot()  # rendered results for the UI thread
        self._processed = LatestSlot()  # processed data for the render stage
        self._processed_ready = threading.Event()
        self.model_loader = model_loader
        self._model: Any = None
        self._model_error: str | None = None
        self._quit = threading.Event()
        self._running = threading.Event()
        self._running.set()
        self._pending: dict[str, float] = {}
        self._pending_lock = threading.Lock()
        self.meter = RateMeter()
        self.frames_processed = 0
        self._last_error = ""
        self._stall_reason = ""
        self._single_shot_geometry: dict | None = None  # computed at first use
        self._model_of_rig: Any = None  # read at first use
        self._mueller_stream = False  # the previous frame was a live Mueller frame

    # -- control from the UI thread
    def stop(self) -> None:
        self._quit.set()
        self._running.set()

    def pause(self, paused: bool) -> None:
        (self._running.clear if paused else self._running.set)()

    @property
    def dropped(self) -> int:
        """Frames dropped at both hand-overs (processed but never rendered, or rendered but
        never shown)."""
        return self._processed.dropped + self.slot.dropped

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    def set_camera(self, **values: float) -> None:
        """Queue camera settings (``exposure_us``, ``gain_db``); the newest value wins."""
        with self._pending_lock:
            self._pending.update(values)

    # -- the loop: stage 1 (grab + process) in a Python thread, stage 2 (render) in this QThread
    def run(self) -> None:
        grabber = threading.Thread(target=self._grab_loop, name="polrig-live-grab", daemon=True)
        grabber.start()
        try:
            while not self._quit.is_set():
                if not self._processed_ready.wait(0.2):
                    continue
                self._processed_ready.clear()
                item = self._processed.take()
                if item is None:
                    continue
                try:
                    result = self._render(*item)
                except Exception as exc:  # noqa: BLE001 - never end the loop: report, go on
                    self._report(exc)
                    continue
                self.frames_processed += 1
                if self.slot.put(result):
                    self.frame_ready.emit()
        finally:
            self._quit.set()
            grabber.join(10.0)

    def _grab_loop(self) -> None:
        while not self._quit.is_set():
            if not self._running.is_set():
                self._running.wait(0.2)
                continue
            t0 = time.perf_counter()
            try:
                item = self._acquire()
            except DeviceBusy:
                self._quit.wait(0.1)
                continue
            except Exception as exc:  # noqa: BLE001 - a driver bug too: report, try again
                self._report(exc)
                self._quit.wait(1.0 if isinstance(exc, DeviceDisconnected) else 0.3)
                continue
            if item is None:
                self._stall("camera not connected")
                self._quit.wait(0.2)
                continue
            self._last_error = ""
            self._stall_reason = ""
            self._processed.put(item)  # an unrendered older frame is dropped
            self._processed_ready.set()
            s = self.settings
            rest = 1.0 / s.max_fps - (time.perf_counter() - t0) if s.max_fps > 0 else 0
            if rest > 0:
                self._quit.wait(rest)

    def _geometry(self) -> dict:
        """Single-shot geometry of this rig (nominal calibration), computed once."""
        if self._single_shot_geometry is None:
            self._single_shot_geometry = processing.single_shot_geometry(
                processing.nominal_calibration(), self.rig.config)
        return self._single_shot_geometry

    def _report(self, exc: BaseException) -> None:
        detail = (str(exc) if isinstance(exc, (PolrigError, OSError, ValueError))
                  else f"{type(exc).__name__}: {exc}")
        text = f"live view: {detail}"
        if text != self._last_error:  # one message per distinct problem, not one per frame
            self._last_error = text
            self.message.emit("error", text)
        self._stall(detail)

    def _stall(self, reason: str) -> None:
        if reason != self._stall_reason:
            self._stall_reason = reason
            self.stalled.emit(reason)

    def _apply_pending(self, cam) -> None:
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        for key, value in pending.items():
            try:
                (cam.set_exposure_us if key == "exposure_us" else cam.set_gain_db)(value)
                self.message.emit("info", f"camera {key.replace('_', ' ')} set to {value:g}")
            except (PolrigError, ValueError) as exc:
                self.message.emit("error", f"camera: cannot set {key}: {exc}")

    def _acquire(self):
        """Stage 1: grab one frame and compute its polarization data (or Mueller image)."""
        cam = self.rig.camera
        s = dataclasses.replace(self.settings)  # one consistent copy for this frame
        with self.locks.hold("camera", timeout_s=0.2, who="live view"):
            if not cam.is_open:
                return None
            self._apply_pending(cam)
            frame = cam.grab(timeout_s=grab_timeout_s(cam, LIVE_GRAB_MARGIN_S))
        t0 = time.perf_counter()
        note = ""
        data = None
        if s.display == "mueller":
            route = self._get_model()
            if route is None:
                note = f"Mueller display unavailable: {self._model_error}"
            else:
                options = SingleShotOptions.from_settings(
                    demosaic=s.method, resolution=s.resolution, network_binning=s.network_binning,
                    mirror_average=s.mirror_average, sigma=False)
                kwargs = {"geometry": self._geometry(), "sensor": self._sensor_model()}
                if s.full_mueller:
                    result = route.frame(frame, self._stage_angle(), options, **kwargs)
                else:
                    if not self._mueller_stream and route.frame_route == "device":
                        route.device_path().restart_live()  # a new live stream probes first
                    result = route.live(frame, self._stage_angle(), options,
                                        max_display_px=s.max_display_px or None, **kwargs)
                data = pipeline.PolarizationData.from_single_shot(result, frame, source="live")
                if result.preview_grid is not None:
                    note = "Mueller grid at display size (on the device; ROI statistics take whole frames)"
        self._mueller_stream = data is not None and not s.full_mueller
        if data is None:
            data = pipeline.process_frame(frame, s.method, workers=s.strip_workers or None,
                                          source="live", model=self._sensor_model())
        return frame.meta, data, note, time.perf_counter() - t0

    def _render(self, meta, data, note: str, process_s: float) -> LiveResult:
        """Stage 2: the display image, histogram and ``QImage`` of processed data."""
        t0 = time.perf_counter()
        s = dataclasses.replace(self.settings)
        shows = data.available()  # a display-size Mueller grid shows only itself
        display = s.display if s.display in shows else ("aolp_dolp" if "aolp_dolp" in shows else shows[-1])
        data.min_snr = s.min_snr
        step = pipeline.display_step(data, display, s.max_display_px)
        rgb = pipeline.render(data, display, s.colour, saturation_overlay=s.saturation_overlay,
                              step=step)
        hist = pipeline.histogram(data, display, s.colour, step=step)
        image = to_qimage(rgb)
        self.meter.tick()
        return LiveResult(image, data, display, s.colour, meta.frame_id, meta.exposure_us,
                          meta.gain_db, hist, process_s + time.perf_counter() - t0,
                          self.meter.rate(), note, step)

    def _sensor_model(self):
        """The camera's noise model (:func:`polrig.app.processing.sensor_model_of`), read once."""
        if self._model_of_rig is None:
            self._model_of_rig = sensor_model_of(self.rig)
        return self._model_of_rig

    def _stage_angle(self) -> float:
        """The polarizer stage angle for single-shot inference (0 if it cannot be read)."""
        try:
            with self.locks.hold("stage", timeout_s=0.2, who="live view"):
                return float(self.rig.stage.position_deg())
        except Exception:  # noqa: BLE001 - any stage problem: angle 0
            return 0.0

    def _get_model(self):
        if self._model is None and self._model_error is None:
            if self.model_loader is None:
                self._model_error = "no single-shot model loader"
            else:
                try:
                    self._model = self.model_loader()
                except Exception as exc:  # noqa: BLE001 - any load problem is a message
                    self._model_error = str(exc)
                    self.message.emit("warning", f"single-shot model: {exc}")
        return self._model
