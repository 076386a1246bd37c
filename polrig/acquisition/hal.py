"""Hardware abstraction layer: the interfaces every camera, stage, light and turntable obeys.

Real drivers (``drivers/``) and simulated devices (``sim/``) implement these classes; callers
receive them from :func:`polrig.app.rig.open_rig` (chosen by configuration) and never test which
kind they hold. Every blocking call takes ``timeout_s`` and raises
:class:`polrig.errors.DeviceTimeout` when it runs out; device-reported errors raise
:class:`polrig.errors.DeviceFault` with the device's own code and text.

Optional capabilities of a whole rig are declared here too, as protocols a rig's attribute is
typed with (``None`` where the rig lacks them): :class:`RigTruth`, the simulator's hidden truth,
and :class:`FaultInjection`, the simulated devices' made-to-order failures (for tests). Callers
compare the attribute with ``None``; nothing asks an object which attributes it happens to have.

Angles are degrees. A stage angle of 0 is the polarizer stage's zero axis (the ``x`` axis of
the incident Stokes frame, see ``docs/conventions.md``); positive angles turn the polarizer
counter-clockwise as seen from the object looking at the light. Turntable angles are positive
counter-clockwise seen from above (right-handed about the turntable axis, which points up).
"""

from __future__ import annotations

import abc
import contextlib
import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from polrig.errors import (
    ConfigError,
    DeviceAlarm,
    DeviceDisconnected,
    DeviceError,
    DeviceTimeout,
    PolrigError,
)
from polrig.sensor.frame import Frame

if TYPE_CHECKING:
    import numpy as np

    from polrig.sensor.analyzer import AnalyzerModel

DEFAULT_TIMEOUT_S = 10.0
#: Timeout of a motion (move or home) whose length is unknown, seconds (the HAL's default).
DEFAULT_MOTION_TIMEOUT_S = 30.0


def grab_timeout_s(camera: "Camera", margin_s: float = DEFAULT_TIMEOUT_S) -> float:
    """Timeout of one :meth:`Camera.grab` at the camera's current exposure: the exposure, the
    readout (:attr:`CameraCapabilities.readout_us`) and ``margin_s`` on top (transfer,
    triggering, a slow host). The one place every grab's timeout comes from (captures,
    the live view), so that a long exposure never times out by construction. A camera that
    cannot report its exposure (NaN, an error) gets ``margin_s`` alone."""
    try:
        exposure_us = float(camera.exposure_us)
    except Exception:  # noqa: BLE001 - a camera that cannot say: the margin alone
        exposure_us = 0.0
    try:
        readout_us = float(camera.capabilities.readout_us)
    except Exception:  # noqa: BLE001 - a closed or failing camera: the exposure alone
        readout_us = 0.0
    frame_us = sum(v for v in (exposure_us, readout_us) if math.isfinite(v) and v > 0)
    return float(margin_s) + frame_us * 1e-6


def motion_timeout_s(axis: "RotationStage", distance_deg: float,
                     margin_s: float = DEFAULT_MOTION_TIMEOUT_S) -> float:
    """Timeout of a move of ``distance_deg`` on ``axis``: the axis's own
    :meth:`RotationStage.calculate_timeout` hook (by default 1.5 times the profile's duration
    at the declared :class:`AxisCapabilities`, plus ``margin_s``)."""
    distance = abs(float(distance_deg))
    if not math.isfinite(distance):
        distance = 0.0
    return axis.calculate_timeout(distance, margin_s)


#: Trigger modes a :class:`Camera` may support (:attr:`CameraCapabilities.trigger_modes`).
TRIGGER_MODES = ("software", "free")


@dataclasses.dataclass(frozen=True)
class CameraCapabilities:
    """What a camera declares about itself, read from the device where it reports it
    (GenICam node ranges, ``SensorReadoutTime`` or the frame rate), never probed by callers.

    ``trigger_modes``: the acquisition modes it supports, a subset of ``("software",
    "free")``: ``"software"`` exposes one frame per :meth:`Camera.grab`; ``"free"`` (free run)
    streams frames, and a frame taken right after a setting change may still be exposed with
    the old setting. ``exposure_range_us``: ``(min, max)`` exposure in microseconds.
    ``readout_us``: time from the end of an exposure until the frame is delivered
    (readout plus transfer) at the current ROI and pixel format, microseconds (0 where the
    device does not say). ``settle_frames``: in free run, how many frames after a setting
    change to discard before a frame is certainly exposed with the new setting (one in
    flight plus one being read out on typical sensors). ``sensor_size``: ``(width, height)``
    of the full sensor in pixels (the largest ROI at offset (0, 0)), ``None`` where the
    device does not say.
    """

    trigger_modes: tuple[str, ...] = ("software", "free")
    exposure_range_us: tuple[float, float] = (1.0, 10_000_000.0)
    readout_us: float = 0.0
    settle_frames: int = 2
    sensor_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        modes = tuple(self.trigger_modes)
        if not modes or any(m not in TRIGGER_MODES for m in modes):
            raise ValueError(f"trigger modes must be a non-empty subset of {TRIGGER_MODES}, "
                             f"got {modes!r}")
        lo, hi = (float(v) for v in self.exposure_range_us)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise ValueError(f"exposure range must be 0 <= min <= max, got {self.exposure_range_us!r}")
        if not (math.isfinite(self.readout_us) and self.readout_us >= 0):
            raise ValueError(f"readout time must be finite and >= 0 us, got {self.readout_us!r}")
        if int(self.settle_frames) < 0:
            raise ValueError(f"settle_frames must be >= 0, got {self.settle_frames!r}")
        if self.sensor_size is not None:
            size = tuple(self.sensor_size)
            if len(size) != 2 or any(isinstance(v, bool) or int(v) != v or int(v) < 1
                                     for v in size):
                raise ValueError(f"sensor size must be (width, height) in whole pixels >= 1, "
                                 f"got {self.sensor_size!r}")
            object.__setattr__(self, "sensor_size", (int(size[0]), int(size[1])))
        object.__setattr__(self, "trigger_modes", modes)
        object.__setattr__(self, "exposure_range_us", (lo, hi))

    @property
    def preferred_trigger(self) -> str:
        """``"software"`` where supported (one exposure per grab), else free run."""
        return "software" if "software" in self.trigger_modes else "free"

    def check_exposure(self, exposure_us: float) -> float:
        """``exposure_us`` as a float, or :class:`polrig.errors.ConfigError` naming the
        camera's range."""
        e = float(exposure_us)
        lo, hi = self.exposure_range_us
        if not (math.isfinite(e) and lo <= e <= hi):
            raise ConfigError(f"exposure {exposure_us!r} us is outside the camera's range "
                              f"[{lo:g}, {hi:g}] us")
        return e


@dataclasses.dataclass(frozen=True)
class AxisCapabilities:
    """What a rotation axis declares about its motion, from the controller's own velocity
    parameters where it reports them (ELL14 ``gv``, K10CR1 ``MGMSG_MOT_REQ_VELPARAMS``, GRBL
    ``$110..$113`` / ``$120..$123``).

    ``speed_deg_s``: cruise (maximum) speed, deg/s. ``accel_deg_s2``: acceleration, deg/s^2
    (``inf`` for a move that reaches full speed at once). ``range_deg``: ``(min, max)``
    travel, or ``None`` for an axis that turns without limit.
    """

    speed_deg_s: float
    accel_deg_s2: float = math.inf
    range_deg: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speed_deg_s) and self.speed_deg_s > 0):
            raise ValueError(f"axis speed must be finite and > 0 deg/s, got {self.speed_deg_s!r}")
        if not (self.accel_deg_s2 > 0):
            raise ValueError(f"axis acceleration must be > 0 deg/s^2, got {self.accel_deg_s2!r}")

    def move_time_s(self, distance_deg: float) -> float:
        """Duration of a move of ``distance_deg`` with a trapezoidal velocity profile
        (triangular when the move is too short to reach full speed), seconds."""
        d = abs(float(distance_deg))
        v, a = float(self.speed_deg_s), float(self.accel_deg_s2)
        if not math.isfinite(a):
            return d / v
        if d <= v * v / a:
            return 2.0 * math.sqrt(d / a)
        return d / v + v / a


@dataclasses.dataclass(frozen=True)
class DeviceInfo:
    """What a device says about itself (for ``polrig devices`` and session manifests)."""

    kind: str  # "camera" | "stage" | "turntable" | "light"
    driver: str
    model: str = ""
    serial: str = ""
    firmware: str = ""
    port: str = ""
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)


class Device(abc.ABC):
    """Common life cycle: ``open``/``close`` and use as a context manager."""

    @abc.abstractmethod
    def open(self) -> None:
        """Connect; raise :class:`DeviceNotFound` if the device cannot be reached."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the transport. Safe to call twice and after a fault."""

    @abc.abstractmethod
    def info(self) -> DeviceInfo:
        """Identity of the open device."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool: ...

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Camera(Device):
    """A DoFP polarization camera delivering raw mosaics."""

    @abc.abstractmethod
    def set_pixel_format(self, name: str) -> None: ...

    @property
    @abc.abstractmethod
    def pixel_format(self) -> str: ...

    @abc.abstractmethod
    def set_roi(self, width: int, height: int, offset_x: int = 0, offset_y: int = 0) -> None:
        """Sensor region of interest in pixels. The offset shifts the mosaic phase."""

    @property
    @abc.abstractmethod
    def roi(self) -> tuple[int, int, int, int]:
        """``(width, height, offset_x, offset_y)`` in pixels."""

    @abc.abstractmethod
    def set_exposure_us(self, exposure_us: float) -> None: ...

    @property
    @abc.abstractmethod
    def exposure_us(self) -> float: ...

    @abc.abstractmethod
    def set_gain_db(self, gain_db: float) -> None: ...

    @property
    @abc.abstractmethod
    def gain_db(self) -> float: ...

    @property
    @abc.abstractmethod
    def capabilities(self) -> CameraCapabilities:
        """What this camera supports, as the open device reports it (trigger modes, exposure
        range, readout time at the current ROI and pixel format)."""

    @abc.abstractmethod
    def set_trigger(self, mode: str) -> None:
        """``"software"`` (one frame per :meth:`grab`) or ``"free"`` (free run); only a mode
        in :attr:`capabilities` ``.trigger_modes`` (else :class:`polrig.errors.ConfigError`)."""

    @property
    @abc.abstractmethod
    def layout(self) -> str:
        """Name of the mosaic layout at ROI offset (0, 0), see :mod:`polrig.sensor.layouts`."""

    @abc.abstractmethod
    def grab(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """Acquire one frame (software-triggering it if in software mode).

        The returned ``raw`` array is owned by the caller (copied out of any driver buffer).
        """


class RotationStage(Device):
    """A motorized rotation stage carrying the illumination polarizer (angles in degrees)."""

    @property
    @abc.abstractmethod
    def capabilities(self) -> AxisCapabilities:
        """Speed, acceleration and travel of this axis, as its controller reports them."""

    def move_time_s(self, from_deg: float, to_deg: float) -> float:
        """Time a move from ``from_deg`` to ``to_deg`` takes, seconds (from
        :attr:`capabilities`; a device with another profile overrides it)."""
        return self.capabilities.move_time_s(float(to_deg) - float(from_deg))

    def calculate_timeout(self, distance_deg: float,
                          margin_s: float = DEFAULT_MOTION_TIMEOUT_S) -> float:
        """Timeout for a move of ``distance_deg``: 1.5 times its duration (a slow start, a
        loaded axis) plus ``margin_s``. The hook a device overrides when it knows better
        (as ophyd-async's movables do)."""
        return float(margin_s) + 1.5 * self.capabilities.move_time_s(distance_deg)

    @abc.abstractmethod
    def home(self, timeout_s: float = 60.0) -> None: ...

    @abc.abstractmethod
    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None: ...

    @abc.abstractmethod
    def position_deg(self) -> float: ...

    @abc.abstractmethod
    def is_busy(self) -> bool: ...

    @abc.abstractmethod
    def wait(self, timeout_s: float = 30.0) -> None:
        """Block until motion ends. A motion that does not end within ``timeout_s`` (s) is
        stopped (:meth:`stop`) before :class:`DeviceTimeout` is raised, so nothing keeps
        moving after the error (the message says when the stop failed too)."""

    @abc.abstractmethod
    def stop(self) -> None: ...

    def stopped_after_timeout(self, message: str, device: str | None = None,
                              stopped: str = "stopped") -> DeviceTimeout:
        """What :meth:`wait` raises when a motion did not end in time, after stopping it
        (:meth:`stop`): a :class:`DeviceTimeout` of ``message`` (why) and ``stopped`` (what the
        stop did), or naming a stop that failed too, so that the operator knows the axis may
        still be moving. A safety fault or a disconnection met while stopping is raised as
        itself. ``device`` names the device in the error. The one place every driver's
        timeout stops its axis."""
        try:
            self.stop()
        except (DeviceAlarm, DeviceDisconnected):
            raise
        except DeviceError as exc:
            return DeviceTimeout(f"{message}; stopping it failed too ({exc}): it may still be moving",
                                 device=device)
        return DeviceTimeout(f"{message}; {stopped}", device=device)


@contextlib.contextmanager
def stopped_when_interrupted(axes: Iterable[tuple[str, RotationStage]],
                             failed: Callable[[str, BaseException], None] | None = None
                             ) -> Iterator[None]:
    """The body drives ``axes`` (``(name, axis)`` pairs; a list may grow while the body runs,
    the pairs it holds when the interruption comes count). When the body is interrupted
    (Ctrl-C, or SIGTERM, which polrig raises as ``KeyboardInterrupt``) each axis is stopped
    (its driver's :meth:`RotationStage.stop`) before the interruption goes on, so nothing
    keeps moving after the run has ended. A stop that fails is ``failed(name, exc)`` (default:
    passed over, the interruption is the news) and the other axes are still stopped. The one
    place the CLI's ``move``/``home`` and the engine's moves and homing stop on an interruption."""
    try:
        yield
    except KeyboardInterrupt:
        for name, axis in dict(list(axes)).items():
            try:
                axis.stop()
            except (PolrigError, OSError) as exc:
                if failed is not None:
                    failed(name, exc)
        raise


class Turntable(RotationStage):
    """The object turntable: same motion interface as a rotation stage (degrees)."""


class Light(Device):
    """The point light source (an LED driver). ``level`` is a fraction in [0, 1]."""

    @abc.abstractmethod
    def set_on(self, on: bool) -> None: ...

    @abc.abstractmethod
    def set_level(self, level: float) -> None: ...

    @abc.abstractmethod
    def status(self) -> dict[str, Any]:
        """At least ``{"on": bool, "level": float}``, plus whatever the device reports."""


def check_level(level: float) -> float:
    """Validate a light level fraction; raise ``ValueError`` naming the allowed range."""
    level = float(level)
    if not (0.0 <= level <= 1.0) or level != level:
        raise ValueError(f"light level must be a fraction in [0, 1], got {level!r}")
    return level


# -- optional capabilities of a rig -------------------------------------------------------------
@runtime_checkable
class RigTruth(Protocol):
    """The hidden truth of a simulated rig: what the rig really is, which calibration and
    processing estimate, and the hand that puts calibration targets in front of the camera
    (on hardware an operator does that).

    A rig declares it as an optional capability (:attr:`polrig.app.rig.Rig.truth`, typed
    ``RigTruth | None``): present on the all-simulated rig, ``None`` on hardware and on a rig
    that mixes real and simulated devices (the simulated world no longer describes the real
    ones). :class:`polrig.sim.truth.SimTruth` implements it."""

    def ground_truth(self, *, turntable_deg: float | None = None) -> dict[str, Any]:
        """Per-pixel truth for the camera's current ROI, exposure and gain at the turntable's
        current angle (or ``turntable_deg``): ``mueller`` ``(C, 3, 3, h, w)`` in DN per unit
        incident S0, ``mask`` and the other arrays of ``docs/sim.md``."""

    def rig_parameters(self) -> dict[str, Any]:
        """The hidden rig parameters, JSON-serialisable (``docs/sim.md``, "Hidden parameters")."""

    def incident_stokes(self, stage_deg: float) -> "np.ndarray":
        """The true normalised incident Stokes vector ``(3,)`` at a stage reading."""

    def analyzer(self) -> "AnalyzerModel":
        """The camera's true per-pixel micro-polarizer analyzer (what the DoFP step fits)."""

    def mount_target(self, name: str, **fixture: Any) -> None:
        """Put calibration target ``name`` (``charuco``, ``chrome_sphere``, ``mirror_plate``,
        ...) in front of the camera at ``fixture`` (the procedures' ``mount`` callback)."""


@runtime_checkable
class FaultInjection(Protocol):
    """Failures made to order, for testing the code that drives a rig: a simulated rig's
    devices raise them (:class:`polrig.sim.devices.FaultInjector`). An optional, test-only
    capability of a rig (:attr:`polrig.app.rig.Rig.faults`, ``None`` on hardware)."""

    def inject_fault(self, device_kind: str, kind: str = "timeout",
                     after_calls: int = 0) -> None:
        """Make call number ``after_calls + 1`` from now of the ``device_kind`` device
        (``camera``, ``stage``, ``turntable``, ``light``) raise: ``timeout``
        (:class:`polrig.errors.DeviceTimeout`), ``fault`` (:class:`polrig.errors.DeviceFault`),
        ``protocol`` (:class:`polrig.errors.ProtocolError`), ``limit``
        (:class:`polrig.errors.DeviceAlarm`, a limit switch that fired) or ``disconnect``
        (:class:`polrig.errors.DeviceDisconnected`)."""
