"""Hardware abstraction layer: the interfaces every camera, stage, light and turntable obeys.

Real drivers (``drivers/``) and simulated devices (``sim/``) implement these classes; callers
receive them from :func:`polrig.rig.open_rig` (chosen by configuration) and never test which
kind they hold. Every blocking call takes ``timeout_s`` and raises
:class:`polrig.errors.DeviceTimeout` when it runs out; device-reported errors raise
:class:`polrig.errors.DeviceFault` with the device's own code and text.

Angles are degrees. A stage angle of 0 is the polarizer stage's zero axis (the ``x`` axis of
the incident Stokes frame, see ``docs/conventions.md``); positive angles turn the polarizer
counter-clockwise as seen from the object looking at the light. Turntable angles are positive
counter-clockwise seen from above (right-handed about the turntable axis, which points up).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from typing import Any

import numpy as np

from polrig.errors import FormatError

DEFAULT_TIMEOUT_S = 10.0
#: Timeout of a motion (move or home) whose length is unknown, seconds (the HAL's default).
DEFAULT_MOTION_TIMEOUT_S = 30.0
#: Speed assumed for an axis that does not say how fast it turns (no ``speed_deg_s``
#: attribute), deg/s: below the slowest stage polrig drives (K10CR1 default 10 deg/s), so a
#: timeout derived from it is never too short.
ASSUMED_AXIS_SPEED_DEG_S = 5.0


def grab_timeout_s(camera, margin_s: float = DEFAULT_TIMEOUT_S) -> float:
    """Timeout of one :meth:`Camera.grab` at the camera's current exposure: the exposure, the
    readout (``readout_us`` where the camera declares it) and ``margin_s`` on top (transfer,
    triggering, a slow host). The one place every grab's timeout comes from (captures,
    the live view), so that a long exposure never times out by construction. A camera that
    cannot report its exposure (NaN, an error) gets ``margin_s`` alone."""
    try:
        exposure_us = float(camera.exposure_us)
    except Exception:  # noqa: BLE001 - a camera that cannot say: the margin alone
        exposure_us = 0.0
    readout_us = getattr(camera, "readout_us", 0.0)
    frame_us = sum(v for v in (exposure_us, readout_us)
                   if isinstance(v, (int, float)) and math.isfinite(v) and v > 0)
    return float(margin_s) + frame_us * 1e-6


def motion_timeout_s(axis, distance_deg: float,
                     margin_s: float = DEFAULT_MOTION_TIMEOUT_S) -> float:
    """Timeout of a move of ``distance_deg`` on ``axis``: the time the move takes at the
    axis's speed (``speed_deg_s`` where it declares one, else
    :data:`ASSUMED_AXIS_SPEED_DEG_S`), 1.5 times for acceleration, plus ``margin_s``."""
    speed = getattr(axis, "speed_deg_s", None)
    if not (isinstance(speed, (int, float)) and math.isfinite(speed) and speed > 0):
        speed = ASSUMED_AXIS_SPEED_DEG_S
    distance = abs(float(distance_deg))
    if not math.isfinite(distance):
        distance = 0.0
    return float(margin_s) + 1.5 * distance / float(speed)


@dataclasses.dataclass(frozen=True)
class FrameMeta:
    """Metadata of one raw frame, as the camera reported it.

    ``layout`` names a :mod:`polrig.layouts` mosaic layout and ``offset_xy`` the ROI offset
    (pixels) that sets its phase. ``bit_depth`` is the number of significant bits of the
    raw values (8, 10, 12, 16). ``timestamp_s`` is the device clock (or host clock when the
    device has none, flagged by ``host_timestamp``).
    """

    frame_id: int
    timestamp_s: float
    exposure_us: float
    gain_db: float
    pixel_format: str
    layout: str
    bit_depth: int
    offset_xy: tuple[int, int] = (0, 0)
    black_level_dn: float = 0.0
    host_timestamp: bool = False
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["offset_xy"] = list(self.offset_xy)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], *, source: Any = None) -> "FrameMeta":
        """The metadata of a JSON object (a raw frame's sidecar), every field type-checked.

        Raises :class:`polrig.errors.FormatError` with one line naming ``source`` (the file
        it came from, if given) and the key: missing or unknown keys, wrong types (``null``,
        strings for numbers, booleans for integers), ``bit_depth`` outside 1..16, a negative,
        non-finite or saturating ``black_level_dn``, a negative ``offset_xy``. Timestamps,
        exposure and gain may be NaN (a camera that does not report them).
        """
        where = f"{source}: " if source is not None else ""

        def bad(key: str, problem: str) -> FormatError:
            return FormatError(f"{where}{key}: {problem}")

        if not isinstance(d, dict):
            raise FormatError(f"{where}frame metadata must be a JSON object, got {_show(d)}")
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise bad(unknown[0], f"unknown frame metadata key; known: {', '.join(names)}")
        required = [f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        missing = [k for k in required if k not in d]
        if missing:
            raise bad(missing[0], "missing from the frame metadata")
        out: dict[str, Any] = {}
        for key in ("frame_id", "bit_depth"):
            v = d[key]
            if not (isinstance(v, int) and not isinstance(v, bool)):
                raise bad(key, f"expected an integer, got {_show(v)}")
            out[key] = v
        if not 1 <= out["bit_depth"] <= 16:
            raise bad("bit_depth", f"must be 1..16 bits (raw frames are 8 or 16-bit "
                                   f"integers), got {out['bit_depth']}")
        for key in ("timestamp_s", "exposure_us", "gain_db", "black_level_dn"):
            if key not in d:
                continue
            v = d[key]
            if not (isinstance(v, (int, float)) and not isinstance(v, bool)):
                raise bad(key, f"expected a number, got {_show(v)}")
            out[key] = float(v)
        black = out.get("black_level_dn", 0.0)
        top = 2 ** out["bit_depth"] - 1
        if not (math.isfinite(black) and 0 <= black < top):
            raise bad("black_level_dn", f"must be a finite number in [0, {top}) for "
                                        f"{out['bit_depth']}-bit data, got {black!r}")
        for key in ("pixel_format", "layout"):
            if not isinstance(d[key], str):
                raise bad(key, f"expected a string, got {_show(d[key])}")
            out[key] = d[key]
        if "offset_xy" in d:
            v = d["offset_xy"]
            if not (isinstance(v, (list, tuple)) and len(v) == 2
                    and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in v)):
                raise bad("offset_xy", f"expected two integers >= 0 [x, y], got {_show(v)}")
            out["offset_xy"] = (int(v[0]), int(v[1]))
        if "host_timestamp" in d:
            if not isinstance(d["host_timestamp"], bool):
                raise bad("host_timestamp", f"expected true or false, got {_show(d['host_timestamp'])}")
            out["host_timestamp"] = d["host_timestamp"]
        if "extra" in d:
            if not isinstance(d["extra"], dict):
                raise bad("extra", f"expected a JSON object, got {_show(d['extra'])}")
            out["extra"] = d["extra"]
        return cls(**out)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


@dataclasses.dataclass(frozen=True)
class Frame:
    """A raw mosaic (``uint16`` or ``uint8``, shape ``(H, W)``, one value per sensor pixel)."""

    raw: np.ndarray
    meta: FrameMeta


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

    @abc.abstractmethod
    def set_trigger(self, mode: str) -> None:
        """``"software"`` (one frame per :meth:`grab`) or ``"free"`` (free run)."""

    @property
    @abc.abstractmethod
    def layout(self) -> str:
        """Name of the mosaic layout at ROI offset (0, 0), see :mod:`polrig.layouts`."""

    @abc.abstractmethod
    def grab(self, timeout_s: float = DEFAULT_TIMEOUT_S) -> Frame:
        """Acquire one frame (software-triggering it if in software mode).

        The returned ``raw`` array is owned by the caller (copied out of any driver buffer).
        """


class RotationStage(Device):
    """A motorized rotation stage carrying the illumination polarizer (angles in degrees)."""

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
        """Block until motion ends; :class:`DeviceTimeout` if it does not end in time."""

    @abc.abstractmethod
    def stop(self) -> None: ...


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
