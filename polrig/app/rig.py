"""The rig: which driver runs each device (the registry), and :func:`open_rig`.

Configuration picks the classes (see :mod:`polrig.formats.config`); callers receive HAL objects and
never ask whether a device is real or simulated. Drivers: ``genicam`` (camera),
``ell14`` (stage), ``k10cr1`` (stage or turntable), ``grbl`` (turntable), ``dc2200`` (light)
and ``sim`` (any device: all ``sim`` devices share one simulated world,
:func:`polrig.sim.devices.create_sim_rig`, whose options come from the ``[sim]`` table and from
``open_rig(**sim_options)``).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from pathlib import Path
from typing import Any

from polrig.acquisition.hal import (
    Camera,
    Device,
    FaultInjection,
    Light,
    RigTruth,
    RotationStage,
    Turntable,
)
from polrig.formats.config import (
    DEVICE_KINDS,
    GEOMETRY_KEYS,
    DriverSpec,
    Field,
    RigConfig,
    load_config,
    validate_config,
)
from polrig.sensor.layouts import LAYOUTS
from polrig.sim.geometry import TurntableGeometry
from polrig.sim.options import DEFAULTS, parse_options, parse_size
from polrig.sim.scene import default_camera, default_light, stage_zero_axis_for


def _address_ok(v: int) -> str | None:
    return None if 0 <= v <= 15 else f"{v} is not a multidrop address 0..15"


def _positive(v: float) -> str | None:
    return None if v > 0 and v == v and v != float("inf") else f"{v!r} must be a positive number"


def _finite(v: float) -> str | None:
    return None if math.isfinite(v) else f"{v!r} must be a finite angle"


def _axis_ok(v: str) -> str | None:
    return None if len(v) == 1 and v.upper() in "XYZABC" else f"{v!r} is not an axis letter X Y Z A B C"


def _axes_ok(v: str) -> str | None:
    letters = v.upper()
    if not letters or any(a not in "XYZABC" for a in letters) or len(set(letters)) != len(letters):
        return f"{v!r} is not a list of distinct axis letters X Y Z A B C (e.g. XYZA)"
    return None


def _grbl_axis_listed(table) -> tuple[str, str] | None:
    """The turntable's axis is one of the status report's axes."""
    if table["axis"].upper() not in table["axes"].upper():
        return "axis", f"{table['axis']!r} is not one of the controller's axes {table['axes']!r} (the key axes)"
    return None


def _module_name(v: str) -> str | None:
    """A dotted Python module name (what ``importlib`` can be asked for; whether it imports and is
    a pyusb backend is found when the device opens)."""
    if v and all(part.isidentifier() for part in v.split(".")):
        return None
    return f"{v!r} is not a module name (e.g. usb.backend.libusb1)"


_TIMEOUT = Field(float, default=1.0, doc="seconds to wait for each reply", check=_positive)
_ZERO = Field(float, default=0.0, doc="device angle (deg) of the rig's zero axis", check=_finite)
_PORT = Field(str, required=True, doc="serial port, e.g. /dev/ttyUSB0 or /dev/serial/by-id/...")

DRIVERS: dict[str, DriverSpec] = {
    "genicam": DriverSpec(
        "genicam", {"camera": "polrig.drivers.genicam_camera:GenicamCamera"}, {
            "cti": Field(str, doc="GenTL producer .cti (default: GENICAM_GENTL64_PATH)",
                         alternatives=(Field(list, item_type=str),)),
            "serial": Field(str, doc="camera serial number (as the producer lists it)"),
            "index": Field(int, doc="device index when no serial is given"),
            "layout": Field(str, default="imx250mzr", choices=tuple(sorted(LAYOUTS)),
                            doc="mosaic layout of the sensor"),
            "pixel_format": Field(str, doc="GenICam PixelFormat to set, e.g. PolarizeMono12p"),
            "roi": Field(list, item_type=int, length=4, doc="[width, height, offset_x, offset_y]"),
            "exposure_us": Field(float, check=_positive, doc="ExposureTime in microseconds"),
            "gain_db": Field(float, doc="Gain in dB"),
            "frame_rate_hz": Field(float, check=_positive, doc="AcquisitionFrameRate"),
            "trigger": Field(str, default="free", choices=("free", "software")),
            "black_level_dn": Field(float, default=0.0, doc="black level of the raw values"),
        }, "GenICam camera through a GenTL producer (harvesters)"),
    "ell14": DriverSpec(
        "ell14", {"stage": "polrig.drivers.ell14:Ell14Stage"}, {
            "port": _PORT,
            "address": Field(int, default=0, check=_address_ok, doc="multidrop address 0..15"),
            "zero_offset_deg": _ZERO, "reply_timeout_s": _TIMEOUT,
        }, "Thorlabs Elliptec ELL14 rotation mount (ASCII, 9600 8N1)"),
    "k10cr1": DriverSpec(
        "k10cr1", {"stage": "polrig.drivers.k10cr1:K10cr1Stage",
                   "turntable": "polrig.drivers.k10cr1:K10cr1Turntable"}, {
            "port": _PORT, "zero_offset_deg": _ZERO, "reply_timeout_s": _TIMEOUT,
            "require_homed": Field(bool, default=True, doc="refuse moves until homed"),
        }, "Thorlabs K10CR1 rotation stage (APT binary protocol, 115200 RTS/CTS)"),
    "grbl": DriverSpec(
        "grbl", {"turntable": "polrig.drivers.grbl:GrblTurntable"}, {
            "port": _PORT,
            "axis": Field(str, default="A", check=_axis_ok, doc="axis letter of the turntable"),
            "axes": Field(str, default="XYZA", check=_axes_ok,
                          doc="axis letters in the order of the status report's MPos/WPos list"),
            "degrees_per_unit": Field(float, default=1.0, check=_positive,
                                      doc="degrees per GRBL axis unit"),
            "rate_per_min": Field(float, check=_positive,
                                  doc="G1 feed rate in units/min (default: G0 rapid)"),
            "reply_timeout_s": Field(float, default=2.0, check=_positive),
        }, "GRBL 1.1 controller, one rotary axis", check=_grbl_axis_listed),
    "dc2200": DriverSpec(
        "dc2200", {"light": "polrig.drivers.dc2200:Dc2200Light"}, {
            "serial": Field(str, doc="USB serial number (default: the only DC2200)"),
            "backend": Field(str, check=_module_name,
                             doc="pyusb backend module, e.g. usb.backend.libusb1 (default: pyusb's choice)"),
            "timeout_s": _TIMEOUT,
        }, "Thorlabs DC2200 LED driver (SCPI over USB-TMC via pyusb)"),
    "sim": DriverSpec(
        "sim", {kind: "" for kind in DEVICE_KINDS}, {},
        "simulated device in the shared simulated world (options: [sim] table)"),
}

_HAL = {"camera": Camera, "stage": RotationStage, "turntable": Turntable, "light": Light}


def _import_class(path: str) -> type:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def driver_kwargs(table: dict[str, Any]) -> dict[str, Any]:
    """Constructor keywords from a validated table (unset optional keys left out)."""
    kw = {k: v for k, v in table.items() if k != "driver" and v is not None}
    if "roi" in kw:
        kw["roi"] = tuple(kw["roi"])
    return kw


@dataclasses.dataclass
class Rig:
    """The four devices of the rig, opened and closed together, and the rig's optional
    capabilities, declared (typed, ``None`` where the rig lacks them) rather than probed:

    * ``truth`` (:class:`polrig.acquisition.hal.RigTruth`): the simulator's hidden truth and its
      calibration-target swap, when every device is simulated (a mixed rig has none: the
      simulated world no longer matches reality); ``None`` on hardware.
    * ``faults`` (:class:`polrig.acquisition.hal.FaultInjection`): failures made to order in
      the simulated devices, for tests; present when any device is simulated.

    ``config`` is the validated configuration, ``source`` its file (``None``: the built-in
    simulated rig).
    """

    camera: Camera
    stage: RotationStage
    turntable: Turntable
    light: Light
    truth: RigTruth | None = None
    config: RigConfig = dataclasses.field(default_factory=RigConfig)
    source: Path | None = None
    faults: FaultInjection | None = None

    @property
    def devices(self) -> dict[str, Device]:
        return {"camera": self.camera, "stage": self.stage, "turntable": self.turntable,
                "light": self.light}

    def open(self) -> "Rig":
        """Open every device not open yet; on failure close what was opened and re-raise."""
        opened = []
        try:
            for dev in self.devices.values():
                if not dev.is_open:
                    dev.open()
                    opened.append(dev)
        except BaseException:
            for dev in reversed(opened):
                dev.close()
            raise
        return self

    def close(self) -> None:
        for dev in self.devices.values():
            try:
                dev.close()
            except Exception:  # noqa: BLE001 - closing must reach every device
                pass

    def __enter__(self) -> "Rig":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def describe(self) -> str:
        """One line per device: kind, driver, and what the device reports (or its settings)."""
        lines = [f"rig: {self.source or 'built-in simulated rig'}"]
        for kind, dev in self.devices.items():
            driver = self.config.get(kind, {}).get("driver", "sim")
            if dev.is_open:
                try:
                    i = dev.info()
                    parts = [p for p in (i.model, f"serial {i.serial}" if i.serial else "",
                                         f"firmware {i.firmware}" if i.firmware else "",
                                         f"on {i.port}" if i.port else "") if p]
                    state = ", ".join(parts) or "open"
                except Exception as exc:  # noqa: BLE001 - report, don't fail
                    state = f"open, info failed: {exc}"
            else:
                settings = {k: v for k, v in self.config.get(kind, {}).items()
                            if k != "driver" and v is not None}
                state = "closed" + (f" ({', '.join(f'{k}={v}' for k, v in settings.items())})"
                                    if settings else "")
            lines.append(f"  {kind:<10} {driver:<8} {state}")
        return "\n".join(lines)


def _make_device(kind: str, table: dict[str, Any], sim_rig_factory) -> Device:
    if table["driver"] == "sim":
        return getattr(sim_rig_factory(), kind)
    cls = _import_class(DRIVERS[table["driver"]].classes[kind])
    dev = cls(**driver_kwargs(table), kind=kind)
    if not isinstance(dev, _HAL[kind]):  # pragma: no cover - registry bug
        raise TypeError(f"{cls.__name__} is not a {_HAL[kind].__name__}")
    return dev


def _sim_factory(config: RigConfig, sim_options: dict[str, Any] | None):
    """A function returning the one shared simulated rig, created on first use."""
    made: list[Any] = []

    def factory():
        if not made:
            # imported here, where a simulated device is made: the simulated devices, their
            # truth and targets are ~50-90 ms of a cold `polrig infer`, which only reads the
            # rig's configuration and nominal geometry (benchmarks/results/cli_start.md)
            from polrig.sim.devices import create_sim_rig

            made.append(create_sim_rig({**config.get("sim", {}), **(sim_options or {}),
                                        "open": False}))
        return made[0]

    factory.made = made  # type: ignore[attr-defined]
    return factory


def build_rig(config: RigConfig, sim_options: dict[str, Any] | None = None) -> Rig:
    """Instantiate (not open) the configured devices; ``sim`` ones share one simulated rig."""
    factory = _sim_factory(config, sim_options)
    devices = {kind: _make_device(kind, config[kind], factory) for kind in DEVICE_KINDS}
    sim_rig = factory.made[0] if factory.made else None
    all_sim = all(config[k]["driver"] == "sim" for k in DEVICE_KINDS)
    return Rig(**devices, truth=sim_rig.truth if (sim_rig is not None and all_sim) else None,
               config=config, source=config.source,
               faults=sim_rig.faults if sim_rig is not None else None)


def open_device(config_path: str | Path | None, kind: str, **sim_options: Any) -> Device:
    """Open just one device of the configured rig (for single-device commands such as
    ``polrig move stage``); use it as a context manager."""
    if kind not in DEVICE_KINDS:
        raise ValueError(f"device kind must be one of {', '.join(DEVICE_KINDS)}, got {kind!r}")
    config = load_rig_config(config_path)
    dev = _make_device(kind, config[kind], _sim_factory(config, sim_options))
    dev.open()
    return dev


def check_sim_table(table: dict[str, Any], where: str) -> None:
    """The ``[sim]`` table through the simulated rig's own option parser (the one place its
    options are checked), so errors name the table and key before anything runs."""

    parse_options(table, where=where)


def load_rig_config(config_path: str | Path | None) -> RigConfig:
    """The validated configuration (the all-simulated one when ``config_path`` is None)."""
    if config_path is None:
        return validate_config({}, DRIVERS, sim_check=check_sim_table)
    return load_config(config_path, DRIVERS, sim_check=check_sim_table)


def open_rig(config_path: str | Path | None = None, **sim_options: Any) -> Rig:
    """Validate the configuration, build the devices and open them all.

    With no ``config_path`` the simulated rig is used; ``sim_options`` go to
    :func:`polrig.sim.devices.create_sim_rig`. Use the result as a context manager (or call
    :meth:`Rig.close`). Configuration errors are raised before any device is opened.
    """
    rig = build_rig(load_rig_config(config_path), sim_options)
    return rig.open()


# -- nominal geometry (single-shot processing without a calibration set) --------------------
def nominal_geometry(config: dict[str, Any] | None,
                     sensor_size: tuple[int, int] | None = None) -> dict[str, Any]:
    """The rig's nominal camera intrinsics and stage zero axis, for single-shot processing when
    no calibration set provides them (:func:`polrig.app.processing.single_shot_geometry`).

    ``config``: a validated rig configuration (or the ``config`` a session manifest records).
    Its ``[nominal_geometry]`` table wins (:data:`polrig.formats.config.GEOMETRY_KEYS`). Otherwise, for a rig
    whose camera is simulated, the simulator's *design* values (never its hidden, perturbed
    ones): the default camera of :func:`polrig.sim.scene.default_camera` (``fx = fy = 2.5 min(W, H)``,
    principal point at the centre) for a sensor of ``sensor_size`` ``(W, H)`` (default: the
    ``[sim]`` table's ``size``, else :data:`polrig.sim.options.DEFAULTS`), and the stage zero axis of
    :func:`polrig.sim.scene.stage_zero_axis_for` for the default light and a vertical turntable
    through the origin, in the camera frame, and that light's position and the object's centre
    (the turntable axis at the object's height), camera frame. A real rig without
    ``[nominal_geometry]`` has none.

    Returns ``{"intrinsics": (fx, fy, cx, cy) | None`` (pixels of the full sensor),
    ``"stage_zero_axis_camera": (x, y, z) | None, "light_position_camera_m": (x, y, z) | None,
    "object_point_camera_m": (x, y, z) | None, "source": str}`` (metres).
    """
    cfg = dict(config or {})
    geo = dict(cfg.get("nominal_geometry") or {})
    out: dict[str, Any] = {key: None for key in GEOMETRY_KEYS} | {"source": "none"}
    camera = cfg.get("camera") or {}
    if camera.get("driver", "sim") == "sim":
        import numpy as np

        if sensor_size is None:
            sensor_size = parse_size((cfg.get("sim") or {}).get("size", DEFAULTS["size"]))
        w, h = (int(v) for v in sensor_size)
        cam = default_camera(w, h)
        light = default_light()
        axis_world, target_world = stage_zero_axis_for(light, TurntableGeometry())
        to_camera = lambda p: tuple(float(v) for v in np.asarray(cam.R) @ p + np.asarray(cam.t))  # noqa: E731
        out.update(intrinsics=(cam.fx, cam.fy, cam.cx, cam.cy),
                   stage_zero_axis_camera=tuple(float(v) for v in np.asarray(cam.R) @ axis_world),
                   light_position_camera_m=to_camera(light.position_m),
                   object_point_camera_m=to_camera(target_world),
                   source="simulator design geometry")
    if geo:
        for key in GEOMETRY_KEYS:
            if key in geo:
                out[key] = tuple(float(v) for v in geo[key])
        out["source"] = "[nominal_geometry] table" if out["source"] == "none" else \
            "[nominal_geometry] table over the simulator design geometry"
    return out
