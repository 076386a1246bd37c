"""Options of the simulated rig (``create_sim_rig(options)``) and the world they build.

Top-level keys (all optional). :func:`parse_options` checks every value, nested ones too
(``hidden.extinction_ratio``, ``sensor_model.full_well_e``), for type and range, and is the
one place that does: a rig configuration's ``[sim]`` table goes through it when the
configuration is validated (:func:`polrig.formats.config.validate_config`). Unknown keys and bad
values raise :class:`polrig.errors.ConfigError` naming the key:

=====================  ===============================================  =====================
key                    meaning                                          default
=====================  ===============================================  =====================
``scene``              a name of :data:`polrig.sim.scene.SCENES`               ``"sphere"``
``size``               sensor ``(width, height)`` or ``"WxH"``          ``(512, 512)``
``sensor``             ``"imx250myr"`` (colour) or ``"imx250mzr"``      ``"imx250myr"``
``seed``               seeds the hidden analyzer errors and the noise   ``0``
``noise``              ``False``: noise-free frames (rounded means)     ``True``
``clock_speed``        simulated s per real s (``inf``: virtual clock)  ``1.0``
``exposure_us``        initial camera exposure                          ``20000``
``stage_speed_deg_s``  polarizer stage speed                            ``20``
``turntable_speed_deg_s``  turntable speed                              ``10``
``distribution``       microfacet distribution ``ggx``/``beckmann``     ``"ggx"``
``indirect_samples``   Monte Carlo samples per pixel of one bounce of   ``0``
                       interreflected light (:mod:`polrig.sim.interreflection`;
                       0: direct light only)
``open``               open the devices on creation                     ``True``
``hidden``             overrides of :data:`HIDDEN_DEFAULTS`             ``{}``
``sensor_model``       overrides of :class:`polrig.sensor.noise.SensorModel`   ``{}``
=====================  ===============================================  =====================
"""

from __future__ import annotations

import inspect
import math
from typing import Any, Mapping

import numpy as np

from polrig.errors import ConfigError
from polrig.formats.config import check_sensor_model
from polrig.optics.pbrdf import DISTRIBUTIONS
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.layouts import LAYOUTS
from polrig.sensor.noise import SensorModel
from polrig.sim.clock import SimClock
from polrig.sim.generator import Generator
from polrig.sim.geometry import TurntableGeometry, rotation_about_axis
from polrig.sim.scene import SCENES, make_scene
from polrig.sim.sensor import DoFPSensor, random_analyzer
from polrig.sim.world import SimWorld

DEFAULTS: dict[str, Any] = {
    "scene": "sphere", "size": (512, 512), "sensor": "imx250myr", "seed": 0, "noise": True,
    "clock_speed": 1.0, "exposure_us": 20000.0, "stage_speed_deg_s": 20.0,
    "turntable_speed_deg_s": 10.0, "distribution": "ggx", "indirect_samples": 0, "open": True,
    "hidden": {},
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
    "analyzer": {},                    # keyword arguments of polrig.sim.sensor.random_analyzer
    "photons_per_radiance_us": 2.5,
    "colour_qe": (0.75, 1.0, 0.85),
}

#: Sensor model of the simulated camera unless ``sensor_model`` overrides it.
SENSOR_MODEL_DEFAULTS: dict[str, Any] = {
    "full_well_e": 10500.0, "read_noise_e": 2.3, "bit_depth": 12, "dark_current_e_per_s": 5.0,
    "black_level_dn": 16.0, "quantum_efficiency": 0.65,
}


def parse_size(size: Any, *, where: str = "") -> tuple[int, int]:
    """``(width, height)`` from ``"WxH"``, ``"N"`` or a pair; :class:`ConfigError` if bad."""
    try:
        if isinstance(size, bool):
            raise TypeError
        if isinstance(size, str):
            parts = size.lower().split("x")
            if len(parts) > 2:
                raise ValueError
            w, h = (int(parts[0]), int(parts[-1]))
        elif isinstance(size, (int, np.integer)):
            w = h = int(size)
        else:
            vals = list(size)
            if len(vals) != 2 or not all(isinstance(v, (int, np.integer)) and
                                         not isinstance(v, bool) for v in vals):
                raise ValueError
            w, h = (int(v) for v in vals)
    except (ValueError, TypeError):
        raise ConfigError(f"{where}size must be 'WxH' or (width, height), got "
                          f"{_show(size)}") from None
    if not (4 <= w <= 8192 and 4 <= h <= 8192):
        raise ConfigError(f"{where}size {w}x{h} out of range (4..8192 pixels per side)")
    return w, h


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _number(where: str, key: str, value: Any, *, low: float | None = None,
            low_open: bool = False, allow_inf: bool = False) -> float:
    """``value`` as a float, or :class:`ConfigError` ``"{where}{key}: ..."``."""
    if not _is_number(value):
        raise ConfigError(f"{where}{key}: expected a number, got {_show(value)}")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(f"{where}{key}: must be a finite number, got {_show(value)}")
    if low is not None and (v <= low if low_open else v < low):
        raise ConfigError(f"{where}{key}: must be {'>' if low_open else '>='} {low:g}, got "
                          f"{_show(value)}")
    return v


def _numbers(where: str, key: str, value: Any, n: int, *, low: float | None = None,
             low_open: bool = False) -> tuple[float, ...]:
    """``n`` finite numbers (a list or tuple), or :class:`ConfigError` naming the key."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if not (isinstance(value, (list, tuple)) and len(value) == n and all(map(_is_number, value))):
        raise ConfigError(f"{where}{key}: expected a list of {n} numbers, got {_show(value)}")
    return tuple(_number(where, key, v, low=low, low_open=low_open) for v in value)


def _bool(where: str, key: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{where}{key}: expected true or false, got {_show(value)}")
    return bool(value)


def _table(where: str, key: str, value: Any) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}{key}: expected a table of overrides, got {_show(value)}")
    return dict(value)


def _analyzer_kwargs(where: str, value: Any) -> dict[str, float]:
    """Keyword arguments of :func:`polrig.sim.sensor.random_analyzer` (all numbers >= 0)."""
    table = _table(where, "hidden.analyzer", value)
    params = inspect.signature(random_analyzer).parameters
    known = sorted(k for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY)
    out = {}
    for k, v in table.items():
        if k not in known:
            raise ConfigError(f"{where}hidden.analyzer.{k}: unknown key; known: "
                              f"{', '.join(known)}")
        out[k] = _number(where, f"hidden.analyzer.{k}", v, low=0.0)
    return out


def _parse_hidden(where: str, value: Any) -> dict[str, Any]:
    """:data:`HIDDEN_DEFAULTS` with the overrides in ``value``, every one type-checked."""
    hidden = _table(where, "hidden", value)
    bad = sorted(set(hidden) - set(HIDDEN_DEFAULTS))
    if bad:
        raise ConfigError(f"{where}hidden.{bad[0]}: unknown hidden parameter; known: "
                          f"{', '.join(sorted(HIDDEN_DEFAULTS))}")
    out = dict(HIDDEN_DEFAULTS)
    k = "hidden."
    for key, v in hidden.items():
        if key == "stage_zero_offset_deg":
            out[key] = _number(where, k + key, v)
        elif key == "extinction_ratio":
            out[key] = _number(where, k + key, v, low=1.0, low_open=True, allow_inf=True)
        elif key == "light_position_m":
            out[key] = None if v is None else _numbers(where, k + key, v, 3)
        elif key == "light_intensity_rgb":
            out[key] = _numbers(where, k + key, v, 3, low=0.0)
        elif key == "turntable_axis":
            axis = _numbers(where, k + key, v, 3)
            if not any(axis):
                raise ConfigError(f"{where}{k}{key}: must not be zero")
            out[key] = axis
        elif key == "turntable_point_m":
            out[key] = _numbers(where, k + key, v, 3)
        elif key == "ideal_analyzer":
            out[key] = _bool(where, k + key, v)
        elif key == "analyzer":
            out[key] = _analyzer_kwargs(where, v)
        elif key == "photons_per_radiance_us":
            out[key] = _number(where, k + key, v, low=0.0, low_open=True)
        elif key == "colour_qe":
            out[key] = _numbers(where, k + key, v, 3, low=0.0, low_open=True)
    return out


def parse_options(options: Mapping[str, Any] | None, *, where: str = "") -> dict[str, Any]:
    """Validated options with defaults filled in (see the module docstring).

    Every value is type- and range-checked here, the one place the simulated rig's options
    are checked (the rig configuration's ``[sim]`` table comes through here too); a bad one is
    a :class:`ConfigError` whose message starts with ``where`` (e.g. ``"rig.toml: [sim] "``)
    and the key (``hidden.extinction_ratio``)."""
    if options is not None and not isinstance(options, Mapping):
        raise ConfigError(f"{where.rstrip() or 'simulated-rig options'}: expected a table, got "
                          f"{_show(options)}")
    options = dict(options or {})
    unknown = sorted(set(options) - set(DEFAULTS))
    if unknown:
        raise ConfigError(f"{where}{unknown[0]}: unknown simulated-rig option; known: "
                          f"{', '.join(sorted(DEFAULTS))}")
    opts = {**DEFAULTS, **options}
    if not isinstance(opts["scene"], str) or opts["scene"] not in SCENES:
        raise ConfigError(f"{where}scene: unknown scene {_show(opts['scene'])}; known: "
                          f"{', '.join(SCENES)}")
    opts["size"] = parse_size(opts["size"], where=where)
    sensor = str(opts["sensor"]).lower() if isinstance(opts["sensor"], str) else None
    if sensor not in LAYOUTS:
        raise ConfigError(f"{where}sensor: must be one of {', '.join(sorted(LAYOUTS))}, got "
                          f"{_show(opts['sensor'])}")
    opts["sensor"] = sensor
    w, h = opts["size"]
    period = LAYOUTS[sensor].period
    if h % period[0] or w % period[1]:
        raise ConfigError(f"{where}size: {w}x{h} must be a multiple of the {sensor} mosaic "
                          f"period {period[1]}x{period[0]}")
    opts["hidden"] = _parse_hidden(where, opts["hidden"])
    sm = check_sensor_model(_table(where, "sensor_model", opts["sensor_model"]),
                            f"{where}sensor_model.")
    opts["sensor_model"] = {**SENSOR_MODEL_DEFAULTS, **sm}
    check_sensor_model(opts["sensor_model"], f"{where}sensor_model.")  # with the defaults
    for key in ("clock_speed", "exposure_us", "stage_speed_deg_s", "turntable_speed_deg_s"):
        opts[key] = _number(where, key, opts[key], low=0.0, low_open=True,
                            allow_inf=key == "clock_speed")
    seed = opts["seed"]
    if not (isinstance(seed, (int, np.integer)) and not isinstance(seed, bool) and seed >= 0):
        raise ConfigError(f"{where}seed: expected an integer >= 0, got {_show(seed)}")
    opts["seed"] = int(seed)
    dist = opts["distribution"]
    if not (isinstance(dist, str) and dist.lower() in DISTRIBUTIONS):
        raise ConfigError(f"{where}distribution: must be one of {', '.join(DISTRIBUTIONS)}, got "
                          f"{_show(dist)}")
    opts["distribution"] = dist.lower()
    n = opts["indirect_samples"]
    if not (isinstance(n, (int, np.integer)) and not isinstance(n, bool) and 0 <= n <= 4096):
        raise ConfigError(f"{where}indirect_samples: expected an integer in 0..4096, got {_show(n)}")
    opts["indirect_samples"] = int(n)
    opts["noise"] = _bool(where, "noise", opts["noise"])
    opts["open"] = _bool(where, "open", opts["open"])
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
                    noise=opts["noise"], distribution=opts["distribution"],
                    indirect_samples=opts["indirect_samples"])
