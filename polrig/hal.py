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
from typing import Any

import numpy as np

DEFAULT_TIMEOUT_S = 10.0


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
    def from_json(cls, d: dict[str, Any]) -> "FrameMeta":
        d = dict(d)
        d["offset_xy"] = tuple(d.get("offset_xy", (0, 0)))
        return cls(**d)


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
