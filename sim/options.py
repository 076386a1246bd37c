"""Options of the simulated rig (``create_sim_rig(options)``) and the world they build.

Top-level keys (all optional; unknown keys raise :class:`polrig.errors.ConfigError`):

=====================  ===============================================  =====================
key                    meaning                                          default
=====================  ===============================================  =====================
``scene``              a name of :data:`sim.scene.SCENES`               ``"sphere"``
``size``               sensor ``(width, height)`` or ``"WxH"``          ``(512, 512)``
``sensor``             ``"imx250myr"`` (colour) or ``"imx250mzr"``      ``"imx250myr"``
``seed``               seeds the hidden analyzer errors and the noise   ``0``
``noise``              ``False``: noise-free frames (rounded means)     ``True``
``clock_speed``        simulated s per real s (``inf``: virtual clock)  ``1.0``
``exposure_us``        initial camera exposure                          ``20000``
``stage_speed_deg_s``  polarizer stage speed                            ``20``
``turntable_speed_deg_s``  turntable speed                              ``10``
``distribution``       microfacet distribution ``ggx``/``beckmann``     ``"ggx"``
``open``               open the devices on creation                     ``True``
``hidden``             overrides of :data:`HIDDEN_DEFAULTS`             ``{}``
``sensor_model``       overrides of :class:`polrig.noise.SensorModel`   ``{}``
=====================  ===============================================  =====================
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from polrig.analyzer import AnalyzerModel
from polrig.errors import ConfigError
from polrig.layouts import LAYOUTS
from polrig.noise import SensorModel
from sim.clock import SimClock
from sim.generator import Generator
from sim.geometry import TurntableGeometry, rotation_about_axis
from sim.scene import SCENES, make_scene
from sim.sensor import DoFPSensor, random_analyzer
from sim.world import SimWorld

DEFAULTS: dict[str, Any] = {
    "scene": "sphere", "size": (512, 512), "sensor": "imx250myr", "seed": 0, "noise": True,
    "clock_speed": 1.0, "exposure_us": 20000.0, "stage_speed_deg_s": 20.0,
    "turntable_speed_deg_s": 10.0, "distribution": "ggx", "open": True, "hidden": {},
    "sensor_model": {},
}

#: Hidden parameters of the simulated rig (what calibration has to find).
HIDDEN_DEFAULTS: dict[str, Any] = {
    "stage_zero_offset_deg": 1.7,
    "extinction_ratio": 800.0,
    "light_position_m": None,          # None: the scene's default light position
    "light_intensity_rgb": (1.0, 1.0, 1.0),
    "turntable_axis": tuple(rotation_about_axis([1.0, 0.0, 0.0], 0.4) @ [0.0, 0.0, 1.0]),
    "turntable_point_m": (0.0015, -0.001, 0.0),
    "ideal_analyzer": False,
    "analyzer": {},                    # keyword arguments of sim.sensor.random_analyzer
    "photons_per_radiance_us": 2.5,
    "colour_qe": (0.75, 1.0, 0.85),
}

#: Sensor model of the simulated camera unless ``sensor_model`` overrides it.
SENSOR_MODEL_DEFAULTS: dict[str, Any] = {
    "full_well_e": 10500.0, "read_noise_e": 2.3, "bit_depth": 12, "dark_current_e_per_s": 5.0,
    "black_level_dn": 16.0, "quantum_efficiency": 0.65,
}


def parse_size(size: Any) -> tuple[int, int]:
    """``(width, height)`` from ``"WxH"``, ``"N"`` or a pair; :class:`ConfigError` if bad."""
    try:
        if isinstance(size, str):
            parts = size.lower().split("x")
            w, h = (int(parts[0]), int(parts[-1]))
        elif isinstance(size, (int, np.integer)):
            w = h = int(size)
        else:
            w, h = (int(v) for v in size)
    except (ValueError, TypeError):
        raise ConfigError(f"size must be 'WxH' or (width, height), got {size!r}") from None
    if not (4 <= w <= 8192 and 4 <= h <= 8192):
        raise ConfigError(f"size {w}x{h} out of range (4..8192 pixels per side)")
    return w, h


def parse_options(options: dict[str, Any] | None) -> dict[str, Any]:
    """Validated options with defaults filled in (see the module docstring)."""
    options = dict(options or {})
    unknown = set(options) - set(DEFAULTS)
    if unknown:
        raise ConfigError(f"unknown simulated-rig option(s) {sorted(unknown)}; known: "
                          f"{sorted(DEFAULTS)}")
    opts = {**DEFAULTS, **options}
    if opts["scene"] not in SCENES:
        raise ConfigError(f"unknown scene {opts['scene']!r}; known: {', '.join(SCENES)}")
    opts["size"] = parse_size(opts["size"])
    sensor = str(opts["sensor"]).lower()
    if sensor not in LAYOUTS:
        raise ConfigError(f"sensor must be one of {sorted(LAYOUTS)}, got {opts['sensor']!r}")
    opts["sensor"] = sensor
    w, h = opts["size"]
    period = LAYOUTS[sensor].period
    if h % period[0] or w % period[1]:
        raise ConfigError(f"size {w}x{h} must be a multiple of the {sensor} mosaic period "
                          f"{period[1]}x{period[0]}")
    hidden = dict(opts["hidden"] or {})
    bad = set(hidden) - set(HIDDEN_DEFAULTS)
    if bad:
        raise ConfigError(f"unknown hidden parameter(s) {sorted(bad)}; known: "
                          f"{sorted(HIDDEN_DEFAULTS)}")
    opts["hidden"] = {**HIDDEN_DEFAULTS, **hidden}
    sm = dict(opts["sensor_model"] or {})
    bad = set(sm) - {f.name for f in dataclasses.fields(SensorModel)}
    if bad:
        raise ConfigError(f"unknown sensor_model field(s) {sorted(bad)}")
    opts["sensor_model"] = {**SENSOR_MODEL_DEFAULTS, **sm}
    for key in ("clock_speed", "exposure_us", "stage_speed_deg_s", "turntable_speed_deg_s"):
        try:
            opts[key] = float(opts[key])
        except (TypeError, ValueError):
            raise ConfigError(f"{key} must be a number, got {opts[key]!r}") from None
        if not opts[key] > 0 or (key != "clock_speed" and math.isinf(opts[key])):
            raise ConfigError(f"{key} must be > 0, got {opts[key]!r}")
    opts["seed"] = int(opts["seed"])
    opts["noise"] = bool(opts["noise"])
    opts["open"] = bool(opts["open"])
    return opts


def build_sensor(opts: dict[str, Any], rng: np.random.Generator) -> DoFPSensor:
    """The simulated sensor of parsed options (hidden analyzer errors drawn from ``rng``)."""
    w, h = opts["size"]
    hid = opts["hidden"]
    if hid["ideal_analyzer"]:
        analyzer = AnalyzerModel.ideal(opts["sensor"], (h, w))
    else:
        analyzer = random_analyzer(opts["sensor"], (h, w), rng, **hid["analyzer"])
    model = SensorModel(**opts["sensor_model"])
    return DoFPSensor(analyzer, model, colour_qe=tuple(hid["colour_qe"]),
                      photons_per_radiance_us=float(hid["photons_per_radiance_us"]))


def build_world(opts: dict[str, Any]) -> SimWorld:
    """The :class:`SimWorld` of parsed options."""
    w, h = opts["size"]
    hid = opts["hidden"]
    table = TurntableGeometry(np.asarray(hid["turntable_axis"], float),
                              np.asarray(hid["turntable_point_m"], float))
    scene = make_scene(opts["scene"], w, h, light_position_m=hid["light_position_m"],
                       light_intensity_rgb=hid["light_intensity_rgb"], turntable=table)
    rng = np.random.default_rng([opts["seed"], 1])
    sensor = build_sensor(opts, rng)
    gen = Generator(float(hid["stage_zero_offset_deg"]), float(hid["extinction_ratio"]))
    return SimWorld(scene, sensor, gen, clock=SimClock(opts["clock_speed"]), seed=opts["seed"],
                    noise=opts["noise"], distribution=opts["distribution"])
