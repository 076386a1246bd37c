"""Simulated devices implementing :mod:`polrig.acquisition.hal` over one shared :class:`polrig.sim.world.SimWorld`.

* :class:`SimCamera` (:class:`polrig.acquisition.hal.Camera`): a DoFP camera (IMX250MYR colour or
  IMX250MZR mono layout) with ROI (the offset shifts the mosaic phase), exposure, gain,
  trigger mode and the mosaic pixel formats of :mod:`polrig.sensor.pixelformats`.
* :class:`SimStage` (:class:`polrig.acquisition.hal.RotationStage`): the polarizer stage; moving it
  changes the incident Stokes state the camera sees.
* :class:`SimTurntable` (:class:`polrig.acquisition.hal.Turntable`): rotates the objects on it.
* :class:`SimLight` (:class:`polrig.acquisition.hal.Light`): its level scales the image linearly.

Motion and exposures take time on the world's :class:`polrig.sim.clock.SimClock` (trapezoidal
profiles, :mod:`polrig.sim.motion`). :func:`create_sim_rig` builds the whole rig from an options
dict; :meth:`SimRig.inject_fault` makes a later call of one device raise a typed
:mod:`polrig.errors` error, for testing the code that drives the rig.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from typing import Any

import numpy as np

from polrig.acquisition import hal
from polrig.acquisition.hal import DeviceInfo
from polrig.errors import (
    ConfigError,
    DeviceAlarm,
    DeviceDisconnected,
    DeviceFault,
    DeviceTimeout,
    FormatError,
    ProtocolError,
)
from polrig.sensor.frame import Frame, FrameMeta
from polrig.sensor.pixelformats import get_pixel_format
from polrig.sim.motion import Move
from polrig.sim.truth import SimTruth
from polrig.sim.world import SimWorld

FAULT_KINDS = ("timeout", "fault", "disconnect", "protocol", "limit")
DEVICE_KINDS = ("camera", "stage", "turntable", "light")


@dataclasses.dataclass
class _Fault:
    kind: str
    remaining: int


class FaultInjector:
    """Pending faults per device kind; every counted device call consumes one step."""

    def __init__(self) -> None:
        self._pending: dict[str, list[_Fault]] = {k: [] for k in DEVICE_KINDS}
        self._lock = threading.Lock()

    def add(self, device_kind: str, kind: str, after_calls: int) -> None:
        if device_kind not in DEVICE_KINDS:
            raise ValueError(f"device kind must be one of {DEVICE_KINDS}, got {device_kind!r}")
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind must be one of {FAULT_KINDS}, got {kind!r}")
        if int(after_calls) < 0:
            raise ValueError("after_calls must be >= 0")
        with self._lock:
            self._pending[device_kind].append(_Fault(kind, int(after_calls)))

    def inject_fault(self, device_kind: str, kind: str = "timeout", after_calls: int = 0) -> None:
        """:meth:`SimRig.inject_fault` (:class:`polrig.acquisition.hal.FaultInjection`: the
        simulated rig's test-only capability, ``Rig.faults``)."""
        self.add(device_kind, kind, after_calls)

    def step(self, device_kind: str) -> str | None:
        """Count one call; return the fault kind that fires on it, if any."""
        with self._lock:
            fired = None
            for f in list(self._pending[device_kind]):
                if f.remaining == 0 and fired is None:
                    fired = f.kind
                    self._pending[device_kind].remove(f)
                else:
                    f.remaining -= 1
            return fired


class _SimDevice:
    """Life cycle, fault injection and identity shared by the simulated devices."""

    kind = "device"

    def __init__(self, world: SimWorld, faults: FaultInjector, name: str) -> None:
        self._world = world
        self._faults = faults
        self._name = name
        self._open = False

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def world(self) -> SimWorld:
        """The simulated world this device is part of (for the simulator's own tools and
        tests; the rig's callers see the HAL and the rig's declared capabilities only)."""
        return self._world

    def info(self) -> DeviceInfo:
        return DeviceInfo(kind=self.kind, driver="sim", model=self._model(),
                          serial=f"SIM-{self.kind.upper()}-{self._world.seed:04d}",
                          firmware="sim 1", port="sim://")

    def _model(self) -> str:
        return f"simulated {self.kind}"

    def _call(self, op: str) -> None:
        """Check the device is open and fire an injected fault, if one is due."""
        if not self._open:
            raise DeviceDisconnected(f"{op}: device is not open", device=self._name)
        fault = self._faults.step(self.kind)
        if fault is None:
            return
        if fault == "timeout":
            raise DeviceTimeout(f"{op}: no answer (simulated timeout)", device=self._name)
        if fault == "fault":
            raise DeviceFault(f"{op} failed", device=self._name, code=13,
                              text="simulated device fault")
        if fault == "protocol":
            raise ProtocolError(f"{op}: garbled reply (simulated)", device=self._name)
        if fault == "limit":
            raise DeviceAlarm(f"{self.kind} stopped by a limit switch (simulated): something "
                              "may be in the way", device=self._name, code=1,
                              text="simulated hard limit", axis=self.kind)
        self._open = False
        raise DeviceDisconnected(f"{op}: connection lost (simulated)", device=self._name)


# ---------------------------------------------------------------------------------- camera

class SimCamera(_SimDevice, hal.Camera):
    """Simulated DoFP camera. ``readout_us`` is added to the exposure per frame."""

    kind = "camera"
    EXPOSURE_RANGE_US = (10.0, 10_000_000.0)
    GAIN_RANGE_DB = (0.0, 48.0)

    def __init__(self, world: SimWorld, faults: FaultInjector, *, exposure_us: float = 20000.0,
                 readout_us: float = 13000.0, name: str = "sim-camera") -> None:
        super().__init__(world, faults, name)
        h, w = world.sensor.shape
        self._roi = (w, h, 0, 0)
        self._exposure_us = float(exposure_us)
        self._gain_db = 0.0
        self._trigger = "software"
        self._readout_us = float(readout_us)
        self._pixel_format = "Mono12p"
        self._frame_id = 0

    def _model(self) -> str:
        return f"simulated DoFP {self.layout.upper()}"

    # -- settings
    def set_pixel_format(self, name: str) -> None:
        self._call("set_pixel_format")
        fmt = get_pixel_format(name)
        if fmt.kind != "mosaic":
            raise FormatError(f"the simulated camera delivers raw mosaics; {fmt.name} is an "
                              f"angles format")
        if fmt.bayer and self._world.sensor.n_colours != 3:
            raise FormatError(f"{fmt.name} is a colour format; this camera is mono")
        self._pixel_format = fmt.name

    @property
    def pixel_format(self) -> str:
        return self._pixel_format

    def set_roi(self, width: int, height: int, offset_x: int = 0, offset_y: int = 0) -> None:
        self._call("set_roi")
        full_h, full_w = self._world.sensor.shape
        w, h, ox, oy = (int(v) for v in (width, height, offset_x, offset_y))
        if w < 1 or h < 1 or ox < 0 or oy < 0 or ox + w > full_w or oy + h > full_h:
            raise ConfigError(f"ROI {w}x{h}+{ox}+{oy} does not fit the {full_w}x{full_h} sensor")
        self._roi = (w, h, ox, oy)

    @property
    def roi(self) -> tuple[int, int, int, int]:
        return self._roi

    def set_exposure_us(self, exposure_us: float) -> None:
        self._call("set_exposure_us")
        self._exposure_us = self.capabilities.check_exposure(exposure_us)

    @property
    def exposure_us(self) -> float:
        return self._exposure_us

    def set_gain_db(self, gain_db: float) -> None:
        self._call("set_gain_db")
        lo, hi = self.GAIN_RANGE_DB
        g = float(gain_db)
        if not (lo <= g <= hi):
            raise ConfigError(f"gain must be in [{lo:g}, {hi:g}] dB, got {gain_db!r}")
        self._gain_db = g

    @property
    def gain_db(self) -> float:
        return self._gain_db

    def set_trigger(self, mode: str) -> None:
        self._call("set_trigger")
        if mode not in ("software", "free"):
            raise ConfigError(f"trigger mode must be 'software' or 'free', got {mode!r}")
        self._trigger = mode

    @property
    def trigger(self) -> str:
        return self._trigger

    @property
    def capabilities(self) -> hal.CameraCapabilities:
        """Both trigger modes, :attr:`EXPOSURE_RANGE_US`, the configured readout time, the
        simulated sensor's size; a simulated frame is always exposed with the current settings
        (no frame to settle)."""
        h, w = self._world.sensor.shape
        return hal.CameraCapabilities(trigger_modes=("software", "free"),
                                      exposure_range_us=self.EXPOSURE_RANGE_US,
                                      readout_us=self._readout_us, settle_frames=0,
                                      sensor_size=(int(w), int(h)))

    @property
    def layout(self) -> str:
        return self._world.sensor.layout

    # -- acquisition
    def grab(self, timeout_s: float = hal.DEFAULT_TIMEOUT_S) -> Frame:
        self._call("grab")
        clock = self._world.clock
        frame_s = (self._exposure_us + self._readout_us) * 1e-6
        if frame_s > timeout_s:
            clock.sleep(timeout_s)
            raise DeviceTimeout(f"grab: no frame within {timeout_s:g} s (exposure "
                                f"{self._exposure_us:g} us)", device=self._name)
        t_start = clock.now()
        t_mid = t_start + 0.5 * self._exposure_us * 1e-6
        stage = self._world.stage_move.position(t_mid)
        table = self._world.turntable_move.position(t_mid)
        raw = self._expose(table, stage)
        clock.sleep(frame_s)
        fmt = get_pixel_format(self._pixel_format)
        shift = fmt.bits - int(self._world.sensor.model.bit_depth)
        self._frame_id += 1
        w, h, ox, oy = self._roi
        black = self._world.sensor.model.black_level_dn * 2.0 ** shift
        meta = FrameMeta(frame_id=self._frame_id, timestamp_s=clock.now(),
                         exposure_us=self._exposure_us, gain_db=self._gain_db,
                         pixel_format=fmt.name, layout=self.layout, bit_depth=fmt.bits,
                         offset_xy=(ox, oy), black_level_dn=float(black),
                         extra={"sim": {"stage_deg": stage, "turntable_deg": table,
                                        "light_level": self._world.light_level,
                                        "light_on": self._world.light_on,
                                        "noise": self._world.noise}})
        return Frame(raw=raw, meta=meta)

    def _expose(self, turntable_deg: float, stage_deg: float) -> np.ndarray:
        """The raw mosaic ``(h, w)`` of the ROI in the current pixel format's dtype, rendered
        by the world at these axis angles with the current settings and the grab's noise."""
        rng = self._world.grab_rng((turntable_deg, stage_deg, self._exposure_us, self._gain_db,
                                    *self._roi, self._world.light_on,
                                    self._world.light_level))
        raw_adc = self._world.raw(turntable_deg=turntable_deg, stage_deg=stage_deg,
                                  exposure_us=self._exposure_us, gain_db=self._gain_db,
                                  roi=self._roi, rng=rng)
        fmt = get_pixel_format(self._pixel_format)
        # The ADC delivers sensor_model.bit_depth bits; wider formats carry the code shifted
        # left (12-bit ADC, 16-bit format: code << 4), narrower ones rounded to their bits.
        adc_bits = int(self._world.sensor.model.bit_depth)
        shift = fmt.bits - adc_bits
        adc = np.clip(np.rint(raw_adc), 0, 2 ** adc_bits - 1)  # noise off: the rounded mean
        return np.clip(np.rint(adc * 2.0 ** shift), 0, 2 ** fmt.bits - 1).astype(fmt.dtype)


# ----------------------------------------------------------------------- stage, turntable

class _SimAxis(_SimDevice):
    """A motorized rotation axis whose current :class:`Move` lives on the world."""

    _move_attr = ""

    def __init__(self, world: SimWorld, faults: FaultInjector, *, speed_deg_s: float,
                 accel_deg_s2: float, name: str) -> None:
        super().__init__(world, faults, name)
        if not (speed_deg_s > 0 and accel_deg_s2 > 0):
            raise ConfigError(f"{name}: speed and acceleration must be > 0")
        self.speed_deg_s = float(speed_deg_s)
        self.accel_deg_s2 = float(accel_deg_s2)

    @property
    def capabilities(self) -> hal.AxisCapabilities:
        """The configured speed and acceleration; the simulated axes turn without limit."""
        return hal.AxisCapabilities(self.speed_deg_s, self.accel_deg_s2)

    @property
    def _move(self) -> Move:
        return getattr(self._world, self._move_attr)

    def _set_move(self, move: Move) -> None:
        setattr(self._world, self._move_attr, move)

    def _position(self) -> float:
        return self._move.position(self._world.clock.now())

    def home(self, timeout_s: float = 60.0) -> None:
        self._call("home")
        self._start(0.0)
        self._wait(timeout_s)

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None:
        self._call("move_to")
        a = float(angle_deg)
        if not math.isfinite(a):
            raise ValueError(f"{self._name}: target angle must be finite, got {angle_deg!r}")
        self._start(a)
        if wait:
            self._wait(timeout_s)

    def _start(self, target_deg: float) -> None:
        self._world.note_motion(turntable=self._move_attr == "turntable_move")
        now = self._world.clock.now()
        self._set_move(Move(self._move.position(now), target_deg, now, self.speed_deg_s,
                            self.accel_deg_s2))

    def position_deg(self) -> float:
        self._call("position_deg")
        return self._position()

    def is_busy(self) -> bool:
        self._call("is_busy")
        return self._world.clock.now() < self._move.t_end_s

    def wait(self, timeout_s: float = 30.0) -> None:
        self._call("wait")
        self._wait(timeout_s)

    def _wait(self, timeout_s: float) -> None:
        clock = self._world.clock
        remaining = self._move.t_end_s - clock.now()
        if remaining <= 0:
            return
        if remaining > timeout_s:
            clock.sleep(timeout_s)
            now = clock.now()
            p = self._move.position(now)
            self._set_move(Move(p, p, now, self.speed_deg_s, self.accel_deg_s2))  # stopped
            raise DeviceTimeout(f"motion did not end within {timeout_s:g} s; stopped "
                                f"(at {p:.3f} deg)", device=self._name)
        clock.sleep(remaining)

    def stop(self) -> None:
        self._call("stop")
        now = self._world.clock.now()
        p = self._move.position(now)
        self._set_move(Move(p, p, now, self.speed_deg_s, self.accel_deg_s2))


class SimStage(_SimAxis, hal.RotationStage):
    """Polarizer rotation stage (default 20 deg/s, 100 deg/s^2)."""

    kind = "stage"
    _move_attr = "stage_move"

    def __init__(self, world: SimWorld, faults: FaultInjector, *, speed_deg_s: float = 20.0,
                 accel_deg_s2: float = 100.0, name: str = "sim-stage") -> None:
        super().__init__(world, faults, speed_deg_s=speed_deg_s, accel_deg_s2=accel_deg_s2,
                         name=name)


class SimTurntable(_SimAxis, hal.Turntable):
    """Object turntable (default 10 deg/s, 20 deg/s^2)."""

    kind = "turntable"
    _move_attr = "turntable_move"

    def __init__(self, world: SimWorld, faults: FaultInjector, *, speed_deg_s: float = 10.0,
                 accel_deg_s2: float = 20.0, name: str = "sim-turntable") -> None:
        super().__init__(world, faults, speed_deg_s=speed_deg_s, accel_deg_s2=accel_deg_s2,
                         name=name)


# ----------------------------------------------------------------------------------- light

class SimLight(_SimDevice, hal.Light):
    """LED driver: on/off and a level fraction that scales the radiant intensity linearly."""

    kind = "light"
    MAX_CURRENT_MA = 1000.0

    def __init__(self, world: SimWorld, faults: FaultInjector, name: str = "sim-light") -> None:
        super().__init__(world, faults, name)

    def set_on(self, on: bool) -> None:
        self._call("set_on")
        self._world.light_on = bool(on)

    def set_level(self, level: float) -> None:
        self._call("set_level")
        self._world.light_level = hal.check_level(level)

    def status(self) -> dict[str, Any]:
        self._call("status")
        w = self._world
        return {"on": w.light_on, "level": w.light_level,
                "current_ma": self.MAX_CURRENT_MA * w.light_level * (1.0 if w.light_on else 0.0)}


# ------------------------------------------------------------------------------------- rig

class SimRig:
    """The simulated rig: ``camera``, ``stage``, ``turntable``, ``light`` over one ``world``;
    ``truth`` (:class:`polrig.acquisition.hal.RigTruth`) gives the hidden parameters and the
    per-capture ground truth, ``faults`` (:class:`polrig.acquisition.hal.FaultInjection`) makes
    the devices fail on purpose."""

    def __init__(self, world: SimWorld, options: dict[str, Any], *, camera_kw=None,
                 stage_kw=None, turntable_kw=None) -> None:
        self.world = world
        self.options = options
        self.faults = FaultInjector()
        self.camera = SimCamera(world, self.faults, **(camera_kw or {}))
        self.stage = SimStage(world, self.faults, **(stage_kw or {}))
        self.turntable = SimTurntable(world, self.faults, **(turntable_kw or {}))
        self.light = SimLight(world, self.faults)
        self.truth = SimTruth(world, self.camera)

    @property
    def devices(self) -> dict[str, _SimDevice]:
        return {"camera": self.camera, "stage": self.stage, "turntable": self.turntable,
                "light": self.light}

    def open(self) -> "SimRig":
        for d in self.devices.values():
            d.open()
        return self

    def close(self) -> None:
        for d in self.devices.values():
            d.close()

    def __enter__(self) -> "SimRig":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def inject_fault(self, device_kind: str, kind: str = "timeout", after_calls: int = 0) -> None:
        """Make call number ``after_calls + 1`` (counting from now) of the ``device_kind``
        device (``camera``, ``stage``, ``turntable``, ``light``) raise: ``timeout`` ->
        :class:`DeviceTimeout`, ``fault`` -> :class:`DeviceFault` (code 13), ``protocol`` ->
        :class:`ProtocolError`, ``limit`` -> :class:`polrig.errors.DeviceAlarm` (a limit switch
        fired: a safety fault), ``disconnect`` -> :class:`DeviceDisconnected` (and the device
        stays closed until :meth:`open`). Every HAL call except ``open``, ``close``,
        ``info``, ``is_open`` and the camera's read-only properties counts."""
        self.faults.inject_fault(device_kind, kind, after_calls)


def create_sim_rig(options: dict[str, Any] | None = None) -> SimRig:
    """Build (and open) a simulated rig. Options: see :func:`polrig.sim.options.parse_options`."""
    from polrig.sim.options import build_world, parse_options

    opts = parse_options(options)
    world = build_world(opts)
    rig = SimRig(world, opts, camera_kw={"exposure_us": opts["exposure_us"]},
                 stage_kw={"speed_deg_s": opts["stage_speed_deg_s"]},
                 turntable_kw={"speed_deg_s": opts["turntable_speed_deg_s"]})
    if opts["open"]:
        rig.open()
    return rig
