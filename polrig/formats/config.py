"""Rig configuration: a TOML file with one table per device, validated before anything opens.

Example (``docs``: issue 4 and ``polrig devices``)::

    [camera]
    driver = "genicam"
    cti = "/opt/producer.cti"
    serial = "223400123"
    layout = "imx250mzr"

    [stage]
    driver = "ell14"
    port = "/dev/ttyUSB0"
    address = 0

    [turntable]
    driver = "grbl"
    port = "/dev/ttyACM0"
    axis = "A"

    [light]
    driver = "dc2200"

Device tables are ``camera``, ``stage``, ``turntable`` and ``light``; a device left out is
the simulated one. Optional tables: ``[sim]`` (options of the simulated rig, checked by
:mod:`polrig.sim.options`), ``[sensor_model]`` (fields of :class:`polrig.sensor.noise.SensorModel` for a
real camera) and ``[nominal_geometry]`` (the rig's nominal geometry for single-shot processing, and
the light's and the object's positions for the diffuse test of ``--models diffuse``, when no
calibration set gives them, :data:`GEOMETRY_KEYS`)::

    [nominal_geometry]
    intrinsics = [6120.0, 6120.0, 1223.5, 1023.5]   # fx, fy, cx, cy: pixels of the full sensor
    stage_zero_axis_camera = [0.92, -0.10, 0.38]    # polarizer zero axis, camera frame
    light_position_camera_m = [0.31, -0.18, 0.12]   # the point light, camera frame, metres
    object_point_camera_m = [0.0, 0.0, 0.5]         # the object's centre (on the turntable axis)
 Each device table names its ``driver``; the keys a driver accepts, their
types, defaults and meaning are its *schema*, supplied by the driver registry
(:data:`polrig.app.rig.DRIVERS`): this module only knows how to check a table against a schema.
Every problem is a :class:`polrig.errors.ConfigError` with a one-line message naming the
file, the table and the key.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any, Callable, Mapping

from polrig.choices import DEVICE_KINDS
from polrig.errors import ConfigError
from polrig.sensor.noise import SensorModel

EXTRA_TABLES = ("sim", "sensor_model", "nominal_geometry")
#: Keys of the ``[nominal_geometry]`` table: ``intrinsics`` ``[fx, fy, cx, cy]`` (pixels of the full
#: sensor readout, OpenCV pinhole, ``docs/conventions.md`` "Image coordinates") and
#: ``stage_zero_axis_camera`` ``[x, y, z]`` (the polarizer stage's zero axis in the camera frame,
#: any length but not zero; "Stokes reference frames"), ``light_position_camera_m`` and
#: ``object_point_camera_m`` ``[x, y, z]`` (the point light and the object's centre on the turntable
#: axis, camera frame, metres: the diffuse test's light directions,
#: :mod:`polrig.app.diffuse_route`). All optional.
GEOMETRY_KEYS = {"intrinsics": 4, "stage_zero_axis_camera": 3, "light_position_camera_m": 3,
                 "object_point_camera_m": 3}

_TYPE_NAMES = {str: "a string", int: "an integer", float: "a number", bool: "true or false",
               list: "a list"}


@dataclasses.dataclass(frozen=True)
class Field:
    """One key of a driver's schema.

    ``type`` is ``str``, ``int``, ``float`` (integers accepted), ``bool`` or ``list`` (with
    ``item_type`` and optionally ``length``); ``types`` allows alternatives (e.g. a string or
    a list of strings). ``choices`` restricts values; ``check`` returns an error text or None.
    """

    type: type
    required: bool = False
    default: Any = None
    doc: str = ""
    item_type: type | None = None
    length: int | None = None
    choices: tuple[Any, ...] | None = None
    alternatives: tuple["Field", ...] = ()
    check: Any = None  # Callable[[Any], str | None]

    def describe_type(self) -> str:
        names = [self._one_type_name()] + [a._one_type_name() for a in self.alternatives]
        return " or ".join(names)

    def _one_type_name(self) -> str:
        if self.type is list:
            item = _TYPE_NAMES.get(self.item_type, "values").replace("a ", "").replace("an ", "")
            n = f"{self.length} " if self.length else ""
            return f"a list of {n}{item}s"
        return _TYPE_NAMES[self.type]

    def coerce(self, value: Any) -> Any:
        """The checked value (ints become floats for float fields); ``ValueError`` if wrong."""
        for f in (self, *self.alternatives):
            ok, v = f._coerce_one(value)
            if ok:
                return v
        raise ValueError(f"expected {self.describe_type()}, got {_show(value)}")

    def _coerce_one(self, value: Any) -> tuple[bool, Any]:
        t = self.type
        if t is bool:
            return isinstance(value, bool), value
        if t is int:
            return isinstance(value, int) and not isinstance(value, bool), value
        if t is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            return ok, float(value) if ok else value
        if t is str:
            return isinstance(value, str), value
        if t is list:
            if not isinstance(value, list):
                return False, value
            if self.length is not None and len(value) != self.length:
                return False, value
            item = Field(self.item_type) if self.item_type else None
            out = []
            for v in value:
                if item is not None:
                    ok, v = item._coerce_one(v)
                    if not ok:
                        return False, value
                out.append(v)
            return True, out
        return isinstance(value, t), value


@dataclasses.dataclass(frozen=True)
class DriverSpec:
    """A driver: its name, the device kinds it can be and the class for each, its schema, and
    ``check``: a check of the whole table once every key has its value (keys that must agree
    with each other), returning ``(key, problem)`` or None."""

    name: str
    classes: Mapping[str, str]  # kind -> "module:Class" ("" for the simulated devices)
    schema: Mapping[str, Field]
    doc: str = ""
    check: Callable[[Mapping[str, Any]], tuple[str, str] | None] | None = None

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(self.classes)


class RigConfig(dict):
    """Validated tables: ``{"camera": {"driver": ..., key: value, ...}, ...}`` with defaults
    filled in for every device kind (``{"driver": "sim"}`` where a table was left out).
    ``source`` is the file it came from (``None`` for the built-in simulated rig)."""

    source: Path | None = None

    def driver(self, kind: str) -> str:
        return self[kind]["driver"]

    @property
    def sensor_model(self) -> dict[str, Any] | None:
        return self.get("sensor_model")


#: ``(table, where) -> None``: checks the ``[sim]`` table (:func:`validate_config`).
SimTableCheck = Callable[[dict[str, Any], str], None]


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _closest(word: str, options: list[str]) -> str:
    import difflib

    near = difflib.get_close_matches(word, options, n=1)
    return f" (did you mean {near[0]!r}?)" if near else ""


def validate_config(data: Mapping[str, Any], registry: Mapping[str, DriverSpec], *,
                    source: str | Path | None = None,
                    sim_check: SimTableCheck | None = None) -> RigConfig:
    """Check parsed TOML ``data`` against the driver ``registry``; return a :class:`RigConfig`.

    ``sim_check(table, where)``: the simulated rig's own option parser for the ``[sim]``
    table (supplied by :mod:`polrig.app.rig`, which may import ``sim``; this core module does
    not), raising :class:`ConfigError` messages that start with ``where``."""
    where = f"{source}: " if source else ""
    out = RigConfig()
    out.source = Path(source) if source else None
    known_tables = sorted((*DEVICE_KINDS, *EXTRA_TABLES))
    for table in data:
        if table not in known_tables:
            raise ConfigError(f"{where}[{table}]: unknown table{_closest(table, known_tables)}; "
                              f"known: {', '.join(known_tables)}")
        if not isinstance(data[table], Mapping):
            raise ConfigError(f"{where}{table}: expected a table [{table}], got {_show(data[table])}")
    for kind in DEVICE_KINDS:
        table = dict(data.get(kind, {"driver": "sim"}))
        name = table.get("driver")
        known = sorted(n for n, s in registry.items() if kind in s.kinds)
        if name is None:
            raise ConfigError(f"{where}[{kind}] driver: missing; choose one of {', '.join(known)}")
        if not isinstance(name, str):
            raise ConfigError(f"{where}[{kind}] driver: expected a string, got {_show(name)}")
        spec = registry.get(name)
        if spec is None:
            raise ConfigError(f"{where}[{kind}] driver: unknown driver {name!r}"
                              f"{_closest(name, known)}; known for {kind}: {', '.join(known)}")
        if kind not in spec.kinds:
            raise ConfigError(f"{where}[{kind}] driver: {name!r} drives a "
                              f"{' or '.join(spec.kinds)}, not the {kind}; known for {kind}: "
                              f"{', '.join(known)}")
        clean: dict[str, Any] = {"driver": name}
        for key, value in table.items():
            if key == "driver":
                continue
            field = spec.schema.get(key)
            if field is None:
                keys = sorted(spec.schema)
                raise ConfigError(f"{where}[{kind}] {key}: unknown key for driver {name!r}"
                                  f"{_closest(key, keys)}; known: {', '.join(keys) or 'none'}")
            try:
                value = field.coerce(value)
            except ValueError as exc:
                raise ConfigError(f"{where}[{kind}] {key}: {exc}") from None
            if field.choices is not None and value not in field.choices:
                raise ConfigError(f"{where}[{kind}] {key}: {_show(value)} is not one of "
                                  f"{', '.join(map(str, field.choices))}")
            if field.check is not None:
                problem = field.check(value)
                if problem:
                    raise ConfigError(f"{where}[{kind}] {key}: {problem}")
            clean[key] = value
        for key, field in spec.schema.items():
            if key in clean:
                continue
            if field.required:
                raise ConfigError(f"{where}[{kind}] {key}: missing (driver {name!r} needs it: "
                                  f"{field.doc or field.describe_type()})")
            clean[key] = field.default
        if spec.check is not None:
            problem = spec.check(clean)
            if problem is not None:
                raise ConfigError(f"{where}[{kind}] {problem[0]}: {problem[1]}")
        out[kind] = clean
    for extra in EXTRA_TABLES:
        if extra in data:
            out[extra] = dict(data[extra])
    if "sensor_model" in out:
        out["sensor_model"] = _check_sensor_model(out["sensor_model"], where)
    if "sim" in out and sim_check is not None:
        sim_check(out["sim"], f"{where}[sim] ")
    if "nominal_geometry" in out:
        out["nominal_geometry"] = _check_geometry(out["nominal_geometry"], where)
    return out


def _check_geometry(table: dict[str, Any], where: str) -> dict[str, list[float]]:
    """The ``[nominal_geometry]`` table as lists of floats (see :data:`GEOMETRY_KEYS`)."""
    import math

    clean: dict[str, list[float]] = {}
    for key, value in table.items():
        if key not in GEOMETRY_KEYS:
            names = list(GEOMETRY_KEYS)
            raise ConfigError(f"{where}[nominal_geometry] {key}: unknown key{_closest(key, names)}; "
                              f"known: {', '.join(names)}")
        n = GEOMETRY_KEYS[key]
        if (not isinstance(value, list) or len(value) != n
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise ConfigError(f"{where}[nominal_geometry] {key}: must be a list of {n} numbers, got "
                              f"{_show(value)}")
        vals = [float(v) for v in value]
        if not all(math.isfinite(v) for v in vals):
            raise ConfigError(f"{where}[nominal_geometry] {key}: values must be finite, got {_show(value)}")
        if key == "intrinsics" and not (vals[0] > 0 and vals[1] > 0):
            raise ConfigError(f"{where}[nominal_geometry] intrinsics: focal lengths fx, fy must be > 0, "
                              f"got {_show(value)}")
        if key == "stage_zero_axis_camera":
            problem = axis_problem(vals)
            if problem:
                raise ConfigError(f"{where}[nominal_geometry] stage_zero_axis_camera: {problem}")
        clean[key] = vals
    return clean


def axis_problem(values: Any) -> str | None:
    """Why ``values`` is not a usable axis direction (three finite numbers, not all zero; the
    vector's length does not matter), or ``None``. Shared by the rig configuration and the
    command-line options (``polrig infer --stage-zero-axis``)."""
    import math

    try:
        vals = [float(v) for v in values]
    except (TypeError, ValueError):
        return "must be three numbers x, y, z"
    if len(vals) != 3:
        return "must be three numbers x, y, z"
    if not all(math.isfinite(v) for v in vals):
        return "values must be finite"
    if not any(vals):
        return "must not be zero"
    return None


#: Types of the :class:`polrig.sensor.noise.SensorModel` fields a table may set (``gain_e_per_dn``
#: may also be ``None``: derived from the full well).
_SENSOR_MODEL_TYPES = {"full_well_e": float, "read_noise_e": float, "bit_depth": int,
                       "gain_e_per_dn": float, "dark_current_e_per_s": float,
                       "black_level_dn": float, "quantum_efficiency": float}


def check_sensor_model(table: Any, where: str = "") -> dict[str, Any]:
    """Check a table of :class:`polrig.sensor.noise.SensorModel` fields (the rig configuration's
    ``[sensor_model]``, the simulated rig's ``sensor_model`` option): known keys, each of its
    type, then the model's own range checks. Returns the table with ints made floats where
    the field is a float. :class:`ConfigError` messages start with ``where`` plus the key
    (``where`` e.g. ``"rig.toml: [sensor_model] "``)."""

    if not isinstance(table, Mapping):
        raise ConfigError(f"{where.rstrip(' .')}: expected a table of sensor model fields, got "
                          f"{_show(table)}")
    names = [f.name for f in dataclasses.fields(SensorModel)]
    clean: dict[str, Any] = {}
    for key, value in table.items():
        if key not in names:
            raise ConfigError(f"{where}{key}: unknown key{_closest(str(key), names)}; "
                              f"known: {', '.join(names)}")
        kind = _SENSOR_MODEL_TYPES.get(key, float)
        if value is None and key == "gain_e_per_dn":  # unset: derived from the full well
            clean[key] = None
            continue
        try:
            clean[key] = Field(kind).coerce(value)
        except ValueError as exc:
            raise ConfigError(f"{where}{key}: {exc}") from None
    try:
        SensorModel(**clean)
    except (TypeError, ValueError) as exc:
        text = str(exc)
        key = next((k for k in names if text.startswith(k)), None)
        if key is not None:  # the model's message starts with the field it is about
            raise ConfigError(f"{where}{key}: {text[len(key):].strip()}") from None
        raise ConfigError(f"{where.rstrip(' .')}: {text}") from None
    return clean


def _check_sensor_model(table: dict[str, Any], where: str) -> dict[str, Any]:
    return check_sensor_model(table, f"{where}[sensor_model] ")


def load_config(path: str | Path, registry: Mapping[str, DriverSpec], *,
                sim_check: SimTableCheck | None = None) -> RigConfig:
    """Read and validate a rig TOML file (``sim_check``: see :func:`validate_config`)."""
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: rig configuration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read rig configuration ({exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return validate_config(data, registry, source=path, sim_check=sim_check)
