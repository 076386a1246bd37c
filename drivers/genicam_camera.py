"""GenICam camera through a GenTL producer (.cti) with harvesters, as a :class:`Camera`.

Sources: harvesters 1.4 documentation (``docs/TUTORIAL.rst``: ``Harvester.add_file``,
``update``, ``device_info_list``, ``create``, ``ImageAcquirer.start/stop``,
``fetch(timeout=...)`` as a context manager that re-queues the buffer on exit) and
``src/harvesters/core.py``; GenICam SFNC 2.x feature names (``PixelFormat``, ``Width``,
``Height``, ``OffsetX``, ``OffsetY``, ``ExposureTime`` [us], ``Gain`` [dB],
``TriggerMode``/``TriggerSource``/``TriggerSoftware``, ``AcquisitionFrameRate``); GenTL
SFNC for buffer info (frame id, timestamp, image offset). Known pitfalls handled here:
``fetch()`` without a timeout can block forever (harvesters issues #348, #375), so every
fetch has one; polarization pixel formats are not decoded by harvesters (#167, #316, #473),
so the payload bytes are copied out of the buffer *before* it is re-queued and decoded by
:mod:`polrig.sensor.pixelformats`.

Features are set through the node map where the camera has them; asking for a missing one
(e.g. ``ExposureTime`` on a simulated producer) raises :class:`DeviceFault` naming it.
The mosaic layout (``layout``, e.g. ``"imx250mzr"``) is configuration: GenICam does not
describe the on-chip polarizer arrangement.

A GenTL producer can be initialised once per process (GenTL standard, ``GCInitLib``: a
second call fails with ``GC_ERR_RESOURCE_IN_USE``, -1004): a second ``Harvester`` on the
same .cti sees no devices at all. So every producer is loaded once and shared, reference
counted, by all cameras and device listings of this process (:class:`_SharedProducer`);
a second camera of the same producer opens, and a listing while a camera is open shows
the devices the producer offered when it was loaded. Before a .cti is handed to the GenTL
loader it is checked to be a shared library with the GenTL entry point ``GCInitLib``: any
other file is refused with :class:`DeviceNotFound` (the loader crashes the process on a
shared library that is not a producer).

Every timeout must be a positive number of seconds: harvesters treats ``fetch(timeout=0)``
or less as "wait forever", so those are refused with ValueError.

Capabilities (:attr:`GenicamCamera.capabilities`, read from the node map on open and again
after every setting this driver changes, so that reading them costs nothing):

- trigger modes: free run always; ``"software"`` when the node map has ``TriggerMode`` and
  ``TriggerSoftware`` (SFNC). A camera without them (the genicam wheel's Viky producer)
  streams in free run only, and :meth:`GenicamCamera.set_trigger` refuses ``"software"``
  with :class:`polrig.errors.ConfigError`.
- exposure range: the ``min``/``max`` of ``ExposureTime`` (SFNC, microseconds), else of
  ``ExposureTimeAbs`` (the pre-SFNC 2.0 GigE name, also microseconds). A camera with
  neither has no exposure control: it declares ``(0, 0)``, so every exposure a plan asks
  for is refused before anything is acquired.
- readout: ``SensorReadoutTime`` (SFNC, microseconds) where the camera has it; else one
  frame period at the frame rate the camera reports (``ResultingFrameRate``, the rate it
  really runs at, else ``AcquisitionFrameRate``, the rate asked for): ``1e6 / fps``
  microseconds. Assumption: with overlapped exposure and readout a frame is delivered at
  most one frame period after its exposure ends (readout and transfer take no longer than
  the period, or the camera could not keep that rate), so the period bounds the readout
  plus transfer; nothing is subtracted for the exposure, which may overlap the previous
  readout entirely. A camera reporting neither: 0.
- sensor size: ``SensorWidth`` x ``SensorHeight`` (SFNC: the sensor's effective pixels), else
  ``WidthMax`` x ``HeightMax`` (SFNC: the largest image, after binning or decimation; polrig
  never bins a DoFP sensor, whose neighbouring pixels carry different analyzers, so the two
  agree); ``None`` for a camera with neither pair (the Viky producer).
- settle frames (free run): 2. When a setting changes (or the rig moves) during free run,
  one frame is being exposed, and began before the change, and the one before it may be
  in readout or transfer and not yet queued on the host (:meth:`GenicamCamera.grab`
  discards only frames already queued). The second frame begun after the change is the
  first one certainly exposed entirely with the new setting and the new scene.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from polrig.acquisition.hal import (
    DEFAULT_TIMEOUT_S,
    Camera,
    CameraCapabilities,
    DeviceInfo,
)
from polrig.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    FormatError,
)
from polrig.sensor import pixelformats
from polrig.sensor.frame import Frame, FrameMeta
from polrig.sensor.layouts import get_layout


def _gentl():
    import genicam.gentl as gentl  # noqa: PLC0415 (heavy import, only when a camera is used)

    return gentl


def _genapi():
    import genicam.genapi as genapi  # noqa: PLC0415

    return genapi


def _check_producer(cti: str) -> None:
    """``cti`` exists and is a shared library exporting ``GCInitLib`` (a GenTL producer)."""
    if not Path(cti).is_file():
        raise DeviceNotFound(f"GenTL producer {cti!r} not found (set [camera] cti to a "
                             "producer .cti file)", device="genicam")
    try:
        lib = ctypes.CDLL(os.path.realpath(cti))
    except OSError as exc:
        raise DeviceNotFound(f"{cti!r} is not a loadable GenTL producer ({exc})",
                             device="genicam") from None
    if not hasattr(lib, "GCInitLib"):
        raise DeviceNotFound(f"{cti!r} is not a GenTL producer (a shared library without the "
                             "GenTL entry point GCInitLib)", device="genicam")


@contextlib.contextmanager
def _sigint_kept() -> Iterator[None]:
    """Keep the process's SIGINT handler across ``Harvester.create``: harvesters installs its
    own (in the main thread), which destroys the image acquirer and swallows the interrupt, so
    an operator's Ctrl-C would no longer stop a capture (harvesters/core.py, ImageAcquirer
    ``__init__`` and ``_SignalHandler``). Ctrl-C is polrig's to handle: the capture leaves the
    session resumable and closes the camera itself."""
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if in_main else None
    try:
        yield
    finally:
        if in_main and previous is not None:
            signal.signal(signal.SIGINT, previous)

class _SharedProducer:
    """One GenTL producer (.cti) loaded in this process, with its own ``Harvester``, shared
    by every user (reference counted): loading it a second time fails (GCInitLib)."""

    _lock = threading.Lock()
    _loaded: dict[str, "_SharedProducer"] = {}

    def __init__(self, path: str, harvester):
        self.path, self.h, self.users = path, harvester, 0

    @classmethod
    def acquire(cls, cti: str) -> "_SharedProducer":
        path = os.path.realpath(cti)
        with cls._lock:
            shared = cls._loaded.get(path)
            if shared is None:
                shared = cls(path, cls._load(cti))
                cls._loaded[path] = shared
            shared.users += 1
            return shared

    @staticmethod
    def _load(cti: str):
        from harvesters.core import Harvester  # noqa: PLC0415

        _check_producer(cti)
        h = Harvester()
        h.add_file(cti)
        try:
            h.update()
        except _gentl().GenericException as exc:
            h.reset()
            raise DeviceNotFound(f"GenTL producer {cti!r} cannot be loaded: {exc}",
                                 device="genicam") from None
        if not getattr(h, "_producers", [None]):  # harvesters logs the failure and goes on
            h.reset()
            raise DeviceNotFound(f"GenTL producer {cti!r} could not be initialised: it is in "
                                 "use elsewhere in this process (a producer can be opened "
                                 "once per process), or it failed to start", device="genicam")
        return h

    def release(self) -> None:
        with self._lock:
            self.users -= 1
            if self.users > 0:
                return
            self._loaded.pop(self.path, None)
        with contextlib.suppress(Exception):
            self.h.reset()

    def forget(self, ia) -> None:
        with contextlib.suppress(Exception):
            self.h.image_acquirers.remove(ia)


def list_gentl_devices(cti_files: list[str]) -> list[DeviceInfo]:
    """Devices the producers offer (``polrig devices``); a missing .cti raises DeviceNotFound.
    A producer a camera of this process holds open lists the devices it offered then."""
    out: list[DeviceInfo] = []
    for cti in cti_files:
        shared = _SharedProducer.acquire(cti)
        try:
            out += [DeviceInfo(kind="camera", driver="genicam", model=d.model or "",
                               serial=d.serial_number or "", port=d.id_ or "",
                               extra={"vendor": d.vendor, "cti": cti_files})
                    for d in shared.h.device_info_list]
        finally:
            shared.release()
    return out


def _check_timeout(timeout_s: float) -> float:
    """A fetch timeout: harvesters waits forever for 0 or less (``fetch(timeout=...)``)."""
    try:
        t = float(timeout_s)
    except (TypeError, ValueError):
        raise ValueError(f"frame timeout must be a number of seconds, got {timeout_s!r}") from None
    if not (t > 0 and math.isfinite(t)):
        raise ValueError(f"frame timeout must be a positive, finite number of seconds, got "
                         f"{timeout_s!r} (0 or less would wait forever)")
    return t


def gentl_paths_from_env() -> list[str]:
    """.cti files in the folders of ``GENICAM_GENTL64_PATH`` (GenTL standard, section 6.1)."""
    out: list[str] = []
    for folder in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if folder and Path(folder).is_dir():
            out += sorted(str(p) for p in Path(folder).glob("*.cti"))
    return out


#: features that change the payload size: the stream is stopped while they are set
_PAYLOAD_FEATURES = frozenset({"PixelFormat", "Width", "Height"})
#: exposure features, SFNC name first (both in microseconds)
_EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")
#: frame-rate features: the rate the camera runs at, then the rate asked for (Hz)
_FRAME_RATE_FEATURES = ("ResultingFrameRate", "AcquisitionFrameRate")
#: free run: frames to discard after a setting change (see the module notes)
FREE_RUN_SETTLE_FRAMES = 2
#: full-sensor size features, (width, height) pairs in order of preference (SFNC names)
_SENSOR_SIZE_FEATURES = (("SensorWidth", "SensorHeight"), ("WidthMax", "HeightMax"))


def exposure_feature(node_map) -> str | None:
    """The node map's exposure feature: ``ExposureTime``, else ``ExposureTimeAbs``; None
    when it has neither."""
    return next((n for n in _EXPOSURE_FEATURES if node_map.has_node(n)), None)


def capabilities_from_node_map(node_map) -> CameraCapabilities:
    """What a GenICam node map (``has_node``/``get_node``, as GenApi's ``NodeMap``) declares,
    by the rules of the module notes. ValueError for a range the camera cannot mean."""
    software = node_map.has_node("TriggerMode") and node_map.has_node("TriggerSoftware")
    exposure = exposure_feature(node_map)
    if exposure is None:
        exposure_range = (0.0, 0.0)  # no exposure control
    else:
        node = node_map.get_node(exposure)
        exposure_range = (float(node.min), float(node.max))
    readout = _float_feature(node_map, "SensorReadoutTime")
    if readout is None or readout < 0:
        rates = (_float_feature(node_map, n) for n in _FRAME_RATE_FEATURES)
        fps = next((r for r in rates if r is not None and r > 0), None)
        readout = 1e6 / fps if fps is not None else 0.0
    return CameraCapabilities(trigger_modes=("software", "free") if software else ("free",),
                              exposure_range_us=exposure_range, readout_us=readout,
                              settle_frames=FREE_RUN_SETTLE_FRAMES,
                              sensor_size=sensor_size_from_node_map(node_map))


def sensor_size_from_node_map(node_map) -> tuple[int, int] | None:
    """``(width, height)`` of the full sensor from ``SensorWidth``/``SensorHeight``, else
    ``WidthMax``/``HeightMax`` (the first pair the node map has and can read as whole
    numbers >= 1); None where it has neither."""
    for width_name, height_name in _SENSOR_SIZE_FEATURES:
        size = (_float_feature(node_map, width_name), _float_feature(node_map, height_name))
        if all(v is not None and v >= 1 and v == int(v) for v in size):
            return int(size[0]), int(size[1])
    return None


def _float_feature(node_map, name: str) -> float | None:
    """The value of a numeric feature, or None where the node map lacks it or cannot read it
    now (a node not readable in the current state)."""
    if not node_map.has_node(name):
        return None
    try:
        value = float(node_map.get_node(name).value)
    except (_genapi().GenericException, TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


class GenicamCamera(Camera):
    """A GenICam camera selected by ``serial`` (or ``index``) from the producer ``cti``.

    Optional settings applied on open: ``pixel_format``, ``roi`` ``(w, h, x, y)``,
    ``exposure_us``, ``gain_db``, ``frame_rate_hz``, ``trigger`` (``"free"`` or
    ``"software"``).
    """

    def __init__(self, cti: str | list[str] | None = None, serial: str | None = None,
                 index: int | None = None,
                 *, layout: str = "imx250mzr", pixel_format: str | None = None,
                 roi: tuple[int, int, int, int] | None = None, exposure_us: float | None = None,
                 gain_db: float | None = None, frame_rate_hz: float | None = None,
                 trigger: str = "free", black_level_dn: float = 0.0, kind: str = "camera"):
        if cti is None:
            cti = gentl_paths_from_env()
        self.cti_files = [cti] if isinstance(cti, (str, os.PathLike)) else list(cti)
        self.cti_files = [os.fspath(c) for c in self.cti_files]
        self.serial = None if serial in (None, "") else str(serial)
        self.index = index
        get_layout(layout)  # validate the name now
        self._layout = layout
        self._settings = dict(pixel_format=pixel_format, roi=roi, exposure_us=exposure_us,
                              gain_db=gain_db, frame_rate_hz=frame_rate_hz)
        self._trigger = trigger
        self.black_level_dn = float(black_level_dn)
        self.kind = kind
        self._producer: _SharedProducer | None = None
        self._ia = None
        self._info: DeviceInfo | None = None
        self._caps: CameraCapabilities | None = None
        self.name = f"genicam {self.serial or self.index or ''}".strip()

    # -- life cycle ------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._ia is not None

    def open(self) -> None:
        if self._ia is not None:
            return
        if not self.cti_files:
            raise DeviceNotFound("no GenTL producer: name a .cti in [camera] cti or set "
                                 "GENICAM_GENTL64_PATH", device=self.name)
        producers: list[_SharedProducer] = []
        try:
            for cti in self.cti_files:
                producers.append(_SharedProducer.acquire(cti))
        except Exception:
            for p in producers:
                p.release()
            raise
        devices = [(p, i, d) for p in producers for i, d in enumerate(p.h.device_info_list)]
        serials = [d.serial_number for _, _, d in devices]
        chosen = None
        try:
            if self.serial is not None:
                if self.serial not in serials:
                    raise DeviceNotFound(f"no camera with serial {self.serial!r}; the producer "
                                         f"offers {serials or 'no devices'}", device=self.name)
                pick = serials.index(self.serial)
            else:
                pick = self.index or 0
                if not 0 <= pick < len(devices):
                    raise DeviceNotFound(f"no camera at index {pick}; the producer offers "
                                         f"{len(devices)} device(s)", device=self.name)
            chosen, local, d = devices[pick]
            try:
                with _sigint_kept():
                    ia = chosen.h.create(local)
            except _gentl().ResourceInUseException:
                raise DeviceNotFound(f"camera serial {d.serial_number!r} is already open (by "
                                     "another camera of this process or another program)",
                                     device=self.name) from None
            except _gentl().GenericException as exc:
                raise DeviceNotFound(f"cannot open camera: {exc}", device=self.name) from None
        except Exception:
            chosen = None
            raise
        finally:
            for p in producers:
                if p is not chosen:
                    p.release()
        self._producer, self._ia = chosen, ia
        self._caps = None
        self._info = DeviceInfo(kind=self.kind, driver="genicam", model=d.model or "",
                                serial=d.serial_number or "", firmware=d.version or "",
                                port=d.id_ or "", extra={"vendor": d.vendor,
                                                         "cti": self.cti_files})
        try:
            s = self._settings
            if s["pixel_format"]:
                self.set_pixel_format(s["pixel_format"])
            if s["roi"]:
                self.set_roi(*s["roi"])
            if s["exposure_us"] is not None:
                self.set_exposure_us(s["exposure_us"])
            if s["gain_db"] is not None:
                self.set_gain_db(s["gain_db"])
            if s["frame_rate_hz"] is not None:
                self.set_frame_rate_hz(s["frame_rate_hz"])
            self.set_trigger(self._trigger)
        except Exception:
            self.close()
            raise

    def close(self) -> None:
        self._caps = None
        ia, self._ia = self._ia, None
        producer, self._producer = self._producer, None
        if ia is not None:
            with contextlib.suppress(Exception):
                ia.stop()
            with contextlib.suppress(Exception):
                ia.destroy()
        if producer is not None:
            if ia is not None:
                producer.forget(ia)
            producer.release()

    def info(self) -> DeviceInfo:
        if self._info is None:
            raise DeviceDisconnected("camera is not open (open it first)", device=self.name)
        return self._info

    # -- node map --------------------------------------------------------------------------
    def _require(self):
        if self._ia is None:
            raise DeviceDisconnected("camera is not open (open it again)", device=self.name)
        if not self._ia.is_valid():
            self.close()
            raise DeviceDisconnected("camera went away", device=self.name)
        return self._ia

    def has_feature(self, name: str) -> bool:
        return bool(self._require().remote_device.node_map.has_node(name))

    def _node(self, name: str):
        nm = self._require().remote_device.node_map
        if not nm.has_node(name):
            raise DeviceFault(f"camera has no {name} feature", device=self.name,
                              code="feature missing", text=name)
        return nm.get_node(name)

    def _set(self, name: str, value: Any) -> None:
        """Set a feature; if the camera locks it while streaming, stop, set and restart.
        Any setting may change what the camera declares (the readout time follows the ROI,
        pixel format and frame rate): the capabilities are read again when next asked."""
        node = self._node(name)
        self._caps = None
        genapi = _genapi()
        ia = self._require()
        if name in _PAYLOAD_FEATURES and ia.is_acquiring():
            ia.stop()  # the stream's buffers were sized for the old payload
        else:
            try:
                node.value = value
                return
            except genapi.AccessException:
                if not ia.is_acquiring():
                    raise DeviceFault(f"{name} is not writable", device=self.name,
                                      code="AccessException", text=name) from None
            except genapi.GenericException as exc:
                raise DeviceFault(f"setting {name} = {value!r} failed", device=self.name,
                                  code=type(exc).__name__, text=str(exc).split(" : ")[0]) from None
            ia.stop()
        try:
            node.value = value
        except genapi.GenericException as exc:
            raise DeviceFault(f"setting {name} = {value!r} failed", device=self.name,
                              code=type(exc).__name__, text=str(exc).split(" : ")[0]) from None
        finally:
            ia.start()

    def _get(self, name: str, default: Any = None) -> Any:
        nm = self._require().remote_device.node_map
        if not nm.has_node(name):
            return default
        return nm.get_node(name).value

    # -- Camera ----------------------------------------------------------------------------
    def set_pixel_format(self, name: str) -> None:
        symbolics = self._node("PixelFormat").symbolics
        if name not in symbolics:
            raise DeviceFault(f"pixel format {name!r} not offered", device=self.name,
                              code="PixelFormat", text=f"camera offers {', '.join(symbolics)}")
        self._set("PixelFormat", name)

    @property
    def pixel_format(self) -> str:
        return str(self._node("PixelFormat").value)

    def set_roi(self, width: int, height: int, offset_x: int = 0, offset_y: int = 0) -> None:
        # Offsets first to 0 so the new size fits, then size, then offsets (SFNC ordering).
        for name in ("OffsetX", "OffsetY"):
            if self.has_feature(name):
                self._set(name, 0)
            elif (offset_x if name == "OffsetX" else offset_y):
                self._node(name)  # raises: a non-zero offset needs the feature
        self._set("Width", int(width))
        self._set("Height", int(height))
        if offset_x:
            self._set("OffsetX", int(offset_x))
        if offset_y:
            self._set("OffsetY", int(offset_y))

    @property
    def roi(self) -> tuple[int, int, int, int]:
        return (int(self._get("Width")), int(self._get("Height")),
                int(self._get("OffsetX", 0)), int(self._get("OffsetY", 0)))

    def _exposure_feature(self) -> str:
        """``ExposureTime``, else ``ExposureTimeAbs``; the SFNC name when it has neither
        (so that setting it names the missing feature)."""
        return exposure_feature(self._require().remote_device.node_map) or _EXPOSURE_FEATURES[0]

    def set_exposure_us(self, exposure_us: float) -> None:
        self._set(self._exposure_feature(), float(exposure_us))

    @property
    def exposure_us(self) -> float:
        return float(self._get(self._exposure_feature(), float("nan")))

    def set_gain_db(self, gain_db: float) -> None:
        self._set("Gain", float(gain_db))

    @property
    def gain_db(self) -> float:
        return float(self._get("Gain", float("nan")))

    def set_frame_rate_hz(self, rate_hz: float) -> None:
        self._set("AcquisitionFrameRate", float(rate_hz))

    # -- capabilities ----------------------------------------------------------------------
    @property
    def capabilities(self) -> CameraCapabilities:
        """What the node map declares (module notes); read once, again after a setting
        changed."""
        if self._caps is None:
            self._caps = self._read_capabilities()
        return self._caps

    def _read_capabilities(self) -> CameraCapabilities:
        try:
            return capabilities_from_node_map(self._require().remote_device.node_map)
        except ValueError as exc:
            raise DeviceFault(f"camera declares impossible capabilities: {exc}",
                              device=self.name, code="capabilities", text=str(exc)) from None

    def set_trigger(self, mode: str) -> None:
        """``"free"`` or ``"software"``, whichever :attr:`capabilities` lists (else
        :class:`ConfigError`). Free run works on a camera without ``TriggerMode``."""
        modes = self.capabilities.trigger_modes
        if mode not in modes:
            missing = (" (the camera has no TriggerMode/TriggerSoftware feature)"
                       if mode == "software" else "")
            raise ConfigError(f"trigger mode {mode!r} is not supported by camera "
                              f"{self.name}{missing}; it supports {', '.join(modes)}")
        if mode == "software":
            self._set("TriggerSelector", "FrameStart") if self.has_feature("TriggerSelector") else None
            self._set("TriggerMode", "On")
            self._set("TriggerSource", "Software")
        elif self.has_feature("TriggerMode"):
            self._set("TriggerMode", "Off")
        self._trigger = mode

    @property
    def trigger(self) -> str:
        return self._trigger

    @property
    def layout(self) -> str:
        return self._layout

    def start(self) -> None:
        ia = self._require()
        if not ia.is_acquiring():
            ia.start()

    def stop(self) -> None:
        ia = self._require()
        if ia.is_acquiring():
            ia.stop()

    def grab(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """One new frame: in free run, frames queued before this call are discarded."""
        timeout_s = _check_timeout(timeout_s)
        ia = self._require()
        self.start()
        if self._trigger == "software":
            self._node("TriggerSoftware").execute()
        else:
            self._drain(ia)
        return self._fetch(ia, timeout_s)

    def frames(self, count: int, timeout_s: float = DEFAULT_TIMEOUT_S) -> Iterator[Frame]:
        """``count`` consecutive frames of the running stream (none discarded)."""
        timeout_s = _check_timeout(timeout_s)
        ia = self._require()
        self.start()
        for _ in range(count):
            if self._trigger == "software":
                self._node("TriggerSoftware").execute()
            yield self._fetch(ia, timeout_s)

    def fetch(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """The next frame of the stream as it is: no start, no trigger, nothing discarded."""
        timeout_s = _check_timeout(timeout_s)
        return self._fetch(self._require(), timeout_s)

    def _drain(self, ia) -> None:
        gentl = _gentl()
        for _ in range(64):
            try:
                buf = ia.try_fetch(timeout=1e-4)
            except gentl.GenericException:
                return
            if buf is None:
                return
            buf.queue()

    def _fetch(self, ia, timeout_s: float) -> Frame:
        gentl = _gentl()
        try:
            with ia.fetch(timeout=timeout_s) as buf:
                frame = self._copy_frame(buf)
        except gentl.TimeoutException:
            raise DeviceTimeout(f"no frame within {timeout_s:g} s", device=self.name) from None
        except (gentl.InvalidHandleException, gentl.NotInitializedException, gentl.IoException,
                gentl.ClosedException) as exc:
            self.close()
            raise DeviceDisconnected(f"camera stream lost: {exc}", device=self.name) from None
        except gentl.GenericException as exc:
            raise DeviceFault("frame acquisition failed", device=self.name,
                              code=type(exc).__name__, text=str(exc)) from None
        return frame

    def _copy_frame(self, buf) -> Frame:
        """Copy the payload out of the GenTL buffer (it is re-queued right after) and decode."""
        module = buf.module
        fmt_name = self.pixel_format
        width, height = int(module.width), int(module.height)
        try:
            fmt = pixelformats.get_pixel_format(fmt_name)
        except FormatError as exc:
            raise FormatError(f"camera pixel format {fmt_name!r} is not a raw mosaic format "
                              f"polrig can decode ({exc})") from None
        try:
            offset = int(module.image_offset)
        except Exception:  # producers may not report it  # noqa: BLE001
            offset = 0
        n = fmt.frame_bytes(width, height)
        payload = np.frombuffer(module.raw_buffer, dtype=np.uint8)  # the buffer, not a copy
        if payload.size < offset + n:
            raise FormatError(f"{fmt_name} {width}x{height} frame needs {n} bytes at offset "
                              f"{offset}; the buffer holds {payload.size}")
        data = payload[offset : offset + n].copy()  # owned by us before the buffer is re-queued
        raw = pixelformats.decode(data, fmt_name, width, height)
        if raw.ndim != 2:
            raise FormatError(f"pixel format {fmt_name!r} delivers angle planes, not a raw "
                              "mosaic; choose a mosaic format (e.g. PolarizeMono12p)")
        try:
            ts, host = module.timestamp_ns * 1e-9, False
        except _gentl().GenericException:
            ts, host = time.time(), True
        _, _, ox, oy = self.roi
        meta = FrameMeta(frame_id=int(module.frame_id), timestamp_s=float(ts),
                         exposure_us=self.exposure_us, gain_db=self.gain_db,
                         pixel_format=fmt_name, layout=self._layout, bit_depth=fmt.bits,
                         offset_xy=(ox, oy), black_level_dn=self.black_level_dn,
                         host_timestamp=host, extra={"serial": self.info().serial})
        return Frame(raw=raw, meta=meta)
