"""Calibration set files: one folder with human-readable parameters and per-pixel maps.

Layout of a calibration set folder (format ``polrig-calibration``, version 1):

* ``calibration.json``: every fitted parameter with its 1-sigma uncertainty, in the units and
  frames of ``docs/conventions.md`` (camera frame, metres, degrees), sections ``camera``,
  ``intrinsics``, ``turntable``, ``fixtures``, ``light``, ``generator``, ``dofp``, each
  optional (a step that has not run is absent), plus ``id``, ``created_utc``,
  ``polrig_version`` and ``files`` (the ``.npz`` files that belong to the set);
* ``analyzer.npz``: the per-pixel :class:`polrig.sensor.analyzer.AnalyzerModel` (``AnalyzerModel.save``);
* ``dofp_maps.npz``: per-pixel maps of the DoFP fit (``dark_dn``, ``flat_scale``,
  ``angle_std_deg``, ``modulation_std``, ``residual_rms_dn``, ``valid``).

``camera`` records the camera the set was calibrated on: its mosaic ``layout`` (at ROI offset
0, 0), the ``readout`` ROI ``[width, height, offset_x, offset_y]`` every step used (the
intrinsics' pixel coordinates and the analyzer model's pixels are those of this readout) and
the full ``sensor_size`` ``[width, height]`` where the camera declares it
(:attr:`polrig.acquisition.hal.CameraCapabilities.sensor_size`; else ``null``). Sets
written before this section existed were calibrated on the full sensor at offset 0, 0 (what
the processing has always assumed): their geometry is the analyzer's or the intrinsics'
image size (:meth:`CalibrationSet.sensor_geometry`).

The ``id`` is the first 16 hex digits of the SHA-256 of the canonical JSON parameters (without
``id``/``created_utc``) and of the per-pixel arrays: it changes whenever any calibrated value
changes, and captures record it (``calibration_id``) in their metadata. :func:`load` refuses a
set without an id, whose content does not match it, or whose values do not have the types,
shapes and ranges of :func:`validate` (one :class:`polrig.errors.FormatError` line naming the
file).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import io
import json
import math
import os
import pathlib
from typing import Any

import numpy as np

from polrig import __version__
from polrig.atomic import atomic_write_bytes, fsync_folder, temporary_sibling
from polrig.calibration.errors import CalibrationError
from polrig.calibration.generator import GeneratorModel
from polrig.calibration.mirror import MirrorMetal
from polrig.errors import FormatError
from polrig.optics.conventions import CONVENTIONS_VERSION
from polrig.sensor.analyzer import AnalyzerModel, layout_name_at, resolve_layout

FORMAT = "polrig-calibration"
VERSION = 1
SECTIONS = ("camera", "intrinsics", "turntable", "fixtures", "light", "generator", "dofp")
ANALYZER_FILE = "analyzer.npz"
MAPS_FILE = "dofp_maps.npz"
NPZ_FILES = (ANALYZER_FILE, MAPS_FILE)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# ------------------------------------------------------------------------ sensor geometry
def _base(layout: str) -> str:
    return str(layout).split("@")[0].lower()


@dataclasses.dataclass(frozen=True)
class SensorGeometry:
    """Which sensor pixels a calibration covers, or a camera reads out.

    ``layout``: the sensor's mosaic layout at ROI offset (0, 0) (``None``: not known);
    ``area``: ``(width, height, offset_x, offset_y)`` of the readout on the sensor (``None``:
    not known); ``sensor_size``: ``(width, height)`` of the full sensor (``None``: the camera
    does not report it)."""

    layout: str | None = None
    area: tuple[int, int, int, int] | None = None
    sensor_size: tuple[int, int] | None = None

    @classmethod
    def of_rig(cls, rig) -> "SensorGeometry":
        """The geometry of ``rig``'s camera as it reads out now: layout, ROI and the sensor
        size where the camera declares it
        (:attr:`polrig.acquisition.hal.CameraCapabilities.sensor_size`)."""
        cam = rig.camera
        w, h, ox, oy = (int(v) for v in cam.roi)
        return cls(layout_name_at(str(cam.layout), 0, 0), (w, h, ox, oy),
                   cam.capabilities.sensor_size)

    def to_json(self) -> dict[str, Any]:
        return {"layout": self.layout, "readout": None if self.area is None else list(self.area),
                "sensor_size": None if self.sensor_size is None else list(self.sensor_size)}

    def describe(self, area_word: str = "readout") -> str:
        """``"sensor 320x240 imx250myr, readout 160x120 at (16, 8)"`` (unknown parts left
        out)."""
        text = "sensor"
        if self.sensor_size is not None:
            text += f" {self.sensor_size[0]}x{self.sensor_size[1]}"
        text += f" {self.layout}" if self.layout else " of unknown layout"
        if self.area is not None:
            w, h, ox, oy = self.area
            text += f", {area_word} {w}x{h} at ({ox}, {oy})"
        return text

    def mismatch(self, other: "SensorGeometry", *, exact: bool = False,
                 phase: bool = True) -> str | None:
        """Why frames of ``other`` (a camera's readout) cannot use a calibration of ``self``
        (``None``: they can). Different layouts (mono/colour, or the mosaic phase when
        ``phase``), different known sensor sizes, or a readout outside the calibrated area
        (``exact``: not the calibrated area itself) are refused."""
        if self.layout and other.layout:
            if _base(self.layout) != _base(other.layout):
                return f"layout {_base(self.layout)} is not {_base(other.layout)}"
            if phase and layout_name_at(self.layout, 0, 0) != layout_name_at(other.layout, 0, 0):
                return f"mosaic phase {self.layout} is not {other.layout}"
        if self.sensor_size and other.sensor_size and \
                tuple(self.sensor_size) != tuple(other.sensor_size):
            return "a different sensor size"
        if self.area and other.area:
            w, h, ox, oy = other.area
            aw, ah, ax, ay = self.area
            if exact:
                if tuple(self.area) != tuple(other.area):
                    return "a different readout"
            elif not (ox >= ax and oy >= ay and ox + w <= ax + aw and oy + h <= ay + ah):
                return "the readout is not inside the calibrated area"
        return None


@dataclasses.dataclass
class CalibrationSet:
    """A rig calibration (see the module docstring); ``params`` holds the JSON sections."""

    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    analyzer: AnalyzerModel | None = None
    dofp_maps: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    id: str = ""

    # -- accessors ----------------------------------------------------------------------
    def _section(self, name: str) -> dict[str, Any]:
        if name not in self.params:
            raise CalibrationError(f"calibration set has no '{name}' section; run "
                                   f"'polrig calibrate {_STEP_OF.get(name, name)}'")
        return self.params[name]

    @property
    def intrinsics(self) -> dict[str, Any]:
        """``{"K": (3, 3), "dist": (5,), "image_size": (w, h), ...}`` (pixels of the
        calibrated readout, ``camera.readout``)."""
        s = self._section("intrinsics")
        return {**s, "K": np.asarray(s["K"], float), "dist": np.asarray(s["dist"], float)}

    @property
    def turntable_axis(self) -> dict[str, Any]:
        """``{"axis_cam": (3,), "point_cam_m": (3,), "axis_std_deg": float, ...}``."""
        s = self._section("turntable")
        return {**s, "axis_cam": np.asarray(s["axis_cam"], float),
                "point_cam_m": np.asarray(s["point_cam_m"], float)}

    @property
    def light_position_m(self) -> np.ndarray:
        """Light position in the camera frame (metres)."""
        return np.asarray(self._section("light")["position_cam_m"], float)

    @property
    def generator(self) -> GeneratorModel:
        return GeneratorModel.from_json(self._section("generator"))

    @property
    def stage_zero_axis_cam(self) -> np.ndarray:
        return np.asarray(self._section("generator")["stage_zero_axis_cam"], float)

    def incident_stokes(self, stage_angle_deg) -> np.ndarray:
        """Normalised incident linear Stokes ``(..., 3)`` at stage angle(s) (degrees), in the
        incident frame whose ``x`` is :attr:`stage_zero_axis_cam` (``docs/conventions.md``)."""
        return self.generator.incident_stokes(stage_angle_deg)

    @property
    def analyzer_model(self) -> AnalyzerModel:
        if self.analyzer is None:
            raise CalibrationError("calibration set has no DoFP analyzer model; run "
                                   "'polrig calibrate dofp'")
        return self.analyzer

    def has(self, section: str) -> bool:
        return section in self.params

    def sensor_geometry(self) -> SensorGeometry | None:
        """The sensor pixels this set was calibrated on (``None``: the set has no step that
        depends on them). From the ``camera`` section; for a set written before it existed,
        the analyzer's (else the intrinsics') size and layout at offset (0, 0) on a sensor of
        that size (what processing has always assumed)."""
        cam = self.params.get("camera")
        if isinstance(cam, dict) and cam.get("readout") is not None:
            size = cam.get("sensor_size")
            return SensorGeometry(cam.get("layout"), tuple(int(v) for v in cam["readout"]),
                                  None if size is None else (int(size[0]), int(size[1])))
        size = None
        layout = None
        if self.analyzer is not None:
            h, w = self.analyzer.shape
            size, layout = (w, h), self.analyzer.layout
        elif isinstance(self.params.get("intrinsics"), dict) and \
                self.params["intrinsics"].get("image_size") is not None:
            w, h = (int(v) for v in self.params["intrinsics"]["image_size"])
            size = (w, h)
        if isinstance(self.params.get("dofp"), dict) and layout is None:
            layout = self.params["dofp"].get("layout")
        if size is None:
            return None if layout is None else SensorGeometry(layout)
        return SensorGeometry(layout, (size[0], size[1], 0, 0), size)

    # -- files ----------------------------------------------------------------------------
    def compute_id(self) -> str:
        h = hashlib.sha256()
        body = {k: v for k, v in self.params.items() if k in SECTIONS}
        h.update(json.dumps(_jsonable(body), sort_keys=True, separators=(",", ":")).encode())
        if self.analyzer is not None:
            for name in ("gain", "angle_deg", "diattenuation", "offset_dn"):
                h.update(np.ascontiguousarray(getattr(self.analyzer, name)).tobytes())
            h.update(self.analyzer.layout.encode())
        for k in sorted(self.dofp_maps):
            h.update(k.encode())
            h.update(np.ascontiguousarray(self.dofp_maps[k]).tobytes())
        return h.hexdigest()[:16]

    def save(self, directory: str | pathlib.Path) -> str:
        """Write the set into ``directory`` (created if needed); returns the id.

        Every file is first written completely under a temporary name, then the ``.npz``
        files and last ``calibration.json`` are renamed into place, so a failed write
        (full disk) leaves the earlier set as it was. ``.npz`` files of an earlier set that
        this one does not have are removed afterwards (``calibration.json`` lists the files
        of the set, ``files``, and :func:`load` reads only those)."""

        d = pathlib.Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.id = self.compute_id()
        files = ([ANALYZER_FILE] if self.analyzer is not None else []) + \
                ([MAPS_FILE] if self.dofp_maps else [])
        doc = {"format": FORMAT, "version": VERSION, "id": self.id,
               "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(
                   timespec="seconds"),
               "polrig_version": __version__, "conventions_version": CONVENTIONS_VERSION,
               "frames": "camera frame (OpenCV: X right, Y down, Z forward), metres, degrees; "
                         "see docs/conventions.md and docs/calibration.md",
               "files": files,
               **{k: self.params[k] for k in SECTIONS if k in self.params}}
        for k, v in self.params.items():
            if k not in SECTIONS and k not in doc:
                doc[k] = v
        staged: list[tuple[pathlib.Path, pathlib.Path]] = []
        try:
            if self.analyzer is not None:
                tmp = temporary_sibling(d / ANALYZER_FILE)
                staged.append((tmp, d / ANALYZER_FILE))
                self.analyzer.save(tmp)
            if self.dofp_maps:
                tmp = temporary_sibling(d / MAPS_FILE)
                staged.append((tmp, d / MAPS_FILE))
                atomic_write_bytes(tmp, _npz_bytes(self.dofp_maps))
            tmp = temporary_sibling(d / "calibration.json")
            staged.append((tmp, d / "calibration.json"))
            atomic_write_bytes(tmp, (json.dumps(_jsonable(doc), indent=2) + "\n").encode())
            for tmp, final in staged:  # the .npz files first, calibration.json last
                os.replace(tmp, final)
            fsync_folder(d)  # the renames are durable
        finally:
            for tmp, _ in staged:
                if tmp.exists():
                    tmp.unlink()
        for name in NPZ_FILES:  # files of an earlier set that this one does not have
            if name not in files and (d / name).exists():
                try:
                    (d / name).unlink()
                except OSError:
                    pass  # not listed in calibration.json: load() does not read it
        return self.id


_STEP_OF = {"camera": "intrinsics", "intrinsics": "intrinsics", "turntable": "turntable",
            "fixtures": "turntable", "light": "light", "generator": "stokes", "dofp": "dofp"}


def _finite(x: Any) -> Any:
    if isinstance(x, str) and x in ("inf", "-inf", "nan"):
        return float(x)
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


# ------------------------------------------------------------------------------ validation
class _Invalid(Exception):
    """One problem of a set, ``where: problem``, in ``file`` of the set folder (made a
    :class:`FormatError` naming the file)."""

    def __init__(self, message: str, file: str = "calibration.json"):
        super().__init__(message)
        self.file = file


def _show(v: Any) -> str:
    text = json.dumps(_jsonable(v)) if not isinstance(v, np.ndarray) else f"array {v.shape}"
    return text if len(text) <= 60 else text[:57] + "..."


def _number(v: Any, where: str, *, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, finite: bool = True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Invalid(f"{where}: expected a number, got {_show(v)}")
    x = float(v)
    if math.isnan(x) or (finite and not math.isfinite(x)):
        raise _Invalid(f"{where}: expected a finite number, got {_show(v)}")
    if lo is not None and (x < lo or (lo_open and x == lo)):
        raise _Invalid(f"{where}: must be {'>' if lo_open else '>='} {lo:g}, got {x:g}")
    if hi is not None and x > hi:
        raise _Invalid(f"{where}: must be <= {hi:g}, got {x:g}")
    return x


def _integer(v: Any, where: str, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise _Invalid(f"{where}: expected an integer, got {_show(v)}")
    if v < lo:
        raise _Invalid(f"{where}: must be >= {lo}, got {v}")
    return v


def _array(v: Any, where: str, shape: tuple[int | None, ...], *, lo: float | None = None,
           nonzero: bool = False) -> np.ndarray:
    """A list (of lists) of finite numbers of ``shape`` (``None``: any length)."""
    want = "x".join("N" if n is None else str(n) for n in shape)

    def bad() -> _Invalid:
        return _Invalid(f"{where}: expected {want} finite numbers, got {_show(v)}")

    def check(x: Any, depth: int) -> None:
        if depth == len(shape):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                raise bad()
            return
        if not isinstance(x, list) or (shape[depth] is not None and len(x) != shape[depth]):
            raise bad()
        for y in x:
            check(y, depth + 1)

    check(v, 0)
    a = np.asarray(v, dtype=np.float64).reshape(-1) if shape == (None,) else \
        np.asarray(v, dtype=np.float64)
    if lo is not None and a.size and a.min() < lo:
        raise _Invalid(f"{where}: values must be >= {lo:g}, got {_show(v)}")
    if nonzero and not np.any(a):
        raise _Invalid(f"{where}: must not be zero")
    return a


def _dict(v: Any, where: str) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise _Invalid(f"{where}: expected a JSON object, got {_show(v)}")
    return v


def _required(s: dict[str, Any], section: str, key: str) -> Any:
    if key not in s:
        raise _Invalid(f"{section}.{key}: missing")
    return s[key]


def _layout(v: Any, where: str) -> str:
    if not isinstance(v, str):
        raise _Invalid(f"{where}: expected a layout name, got {_show(v)}")
    try:
        return resolve_layout(v).name
    except ValueError as exc:
        raise _Invalid(f"{where}: {exc}") from None


def _size(v: Any, where: str) -> tuple[int, int]:
    if not (isinstance(v, list) and len(v) == 2):
        raise _Invalid(f"{where}: expected [width, height], got {_show(v)}")
    return _integer(v[0], where, 1), _integer(v[1], where, 1)


def _validate_params(p: dict[str, Any]) -> None:
    """Types, shapes and ranges of every section present in ``p`` (after ``_finite``)."""
    for name in SECTIONS:
        if name in p:
            _dict(p[name], name)
    if "camera" in p:
        c = p["camera"]
        _layout(_required(c, "camera", "layout"), "camera.layout")
        r = _required(c, "camera", "readout")
        if not (isinstance(r, list) and len(r) == 4):
            raise _Invalid(f"camera.readout: expected [width, height, offset_x, offset_y], got "
                           f"{_show(r)}")
        w, h = (_integer(x, "camera.readout", 1) for x in r[:2])
        ox, oy = (_integer(x, "camera.readout", 0) for x in r[2:])
        if c.get("sensor_size") is not None:
            sw, sh = _size(c["sensor_size"], "camera.sensor_size")
            if ox + w > sw or oy + h > sh:
                raise _Invalid(f"camera.readout {w}x{h} at ({ox}, {oy}) is not inside the "
                               f"{sw}x{sh} camera.sensor_size")
    if "intrinsics" in p:
        s = p["intrinsics"]
        K = _array(_required(s, "intrinsics", "K"), "intrinsics.K", (3, 3))
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise _Invalid(f"intrinsics.K: focal lengths fx, fy must be > 0, got "
                           f"{K[0, 0]:g}, {K[1, 1]:g}")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
            raise _Invalid(f"intrinsics.K: not a camera matrix [[fx, s, cx], [0, fy, cy], "
                           f"[0, 0, 1]], got {_show(s['K'])}")
        dist = _array(_required(s, "intrinsics", "dist"), "intrinsics.dist", (None,))
        if dist.size not in (4, 5, 8, 12, 14):
            raise _Invalid(f"intrinsics.dist: expected 4, 5, 8, 12 or 14 distortion "
                           f"coefficients, got {dist.size}")
        if "std_fx_fy_cx_cy_px" in s:
            _array(s["std_fx_fy_cx_cy_px"], "intrinsics.std_fx_fy_cx_cy_px", (4,), lo=0.0)
        if "std_dist" in s:
            _array(s["std_dist"], "intrinsics.std_dist", (None,), lo=0.0)
        if "rms_px" in s:
            _number(s["rms_px"], "intrinsics.rms_px", lo=0.0)
        if s.get("image_size") is not None:
            _size(s["image_size"], "intrinsics.image_size")
    if "turntable" in p:
        s = p["turntable"]
        _array(_required(s, "turntable", "axis_cam"), "turntable.axis_cam", (3,), nonzero=True)
        _array(_required(s, "turntable", "point_cam_m"), "turntable.point_cam_m", (3,))
        if "axis_std_deg" in s:
            _number(s["axis_std_deg"], "turntable.axis_std_deg", lo=0.0)
        if "point_std_m" in s:
            _array(s["point_std_m"], "turntable.point_std_m", (3,), lo=0.0)
    if "fixtures" in p:
        poses = _required(p["fixtures"], "fixtures", "poses")
        if not isinstance(poses, list):
            raise _Invalid(f"fixtures.poses: expected a list, got {_show(poses)}")
        for i, f in enumerate(poses):
            f = _dict(f, f"fixtures.poses[{i}]")
            _array(_required(f, f"fixtures.poses[{i}]", "R"), f"fixtures.poses[{i}].R", (3, 3))
            _array(_required(f, f"fixtures.poses[{i}]", "t_m"), f"fixtures.poses[{i}].t_m", (3,))
            if "rotation_std_deg" in f:
                _number(f["rotation_std_deg"], f"fixtures.poses[{i}].rotation_std_deg", lo=0.0)
    if "light" in p:
        s = p["light"]
        _array(_required(s, "light", "position_cam_m"), "light.position_cam_m", (3,))
        if "std_m" in s:
            _array(s["std_m"], "light.std_m", (3,), lo=0.0)
        if "covariance_m2" in s:
            _array(s["covariance_m2"], "light.covariance_m2", (3, 3))
    if "generator" in p:
        s = p["generator"]
        _number(_required(s, "generator", "zero_offset_deg"), "generator.zero_offset_deg",
                lo=-180.0, hi=180.0)
        _number(_required(s, "generator", "extinction_ratio"), "generator.extinction_ratio",
                lo=1.0, lo_open=True, finite=False)
        for key in ("zero_offset_std_deg", "zero_offset_std_bound_deg", "extinction_ratio_std"):
            if key in s:
                _number(s[key], f"generator.{key}", lo=0.0)
        if "stage_zero_axis_cam" in s:
            _array(s["stage_zero_axis_cam"], "generator.stage_zero_axis_cam", (3,),
                   nonzero=True)
    if "dofp" in p:
        s = p["dofp"]
        if "layout" in s:
            _layout(s["layout"], "dofp.layout")
        if "shape" in s:
            v = s["shape"]
            if not (isinstance(v, list) and len(v) == 2):
                raise _Invalid(f"dofp.shape: expected [height, width], got {_show(v)}")
            _integer(v[0], "dofp.shape", 1), _integer(v[1], "dofp.shape", 1)
        if "valid_fraction" in s:
            _number(s["valid_fraction"], "dofp.valid_fraction", lo=0.0, hi=1.0)
        for key in ("angle_std_deg_median", "modulation_std_median", "residual_rms_dn_median"):
            if key in s:
                _number(s[key], f"dofp.{key}", lo=0.0)
        if "sensor_diattenuation_reference" in s:
            _number(s["sensor_diattenuation_reference"], "dofp.sensor_diattenuation_reference",
                    lo=0.0, hi=1.0, lo_open=True)
        if "mirror" in s:
            try:
                MirrorMetal.from_json(_dict(s["mirror"], "dofp.mirror"))
            except (KeyError, TypeError, ValueError) as exc:
                raise _Invalid(f"dofp.mirror: expected {{\"name\": ..., \"eta_rgb\": [[n, k] x 3] "
                               f"or null}}, got {_show(s['mirror'])} ({exc})") from None


def _validate_pixels(cs: CalibrationSet) -> None:
    """The per-pixel files against each other and against the JSON sections."""
    p = cs.params
    a = cs.analyzer
    sizes: list[tuple[str, str, tuple[int, int]]] = []  # (file, what, (h, w))
    if a is not None:
        sizes.append((ANALYZER_FILE, "the analyzer model", a.shape))
    if "camera" in p:
        w, h = p["camera"]["readout"][:2]
        sizes.append(("calibration.json", "camera.readout", (h, w)))
    if isinstance(p.get("intrinsics"), dict) and p["intrinsics"].get("image_size") is not None:
        w, h = p["intrinsics"]["image_size"]
        sizes.append(("calibration.json", "intrinsics.image_size", (h, w)))
    if "dofp" in p and "shape" in p["dofp"]:
        sizes.append(("calibration.json", "dofp.shape", tuple(p["dofp"]["shape"])))
    for k, m in cs.dofp_maps.items():
        if m.ndim != 2 or not (np.issubdtype(m.dtype, np.number) or m.dtype == bool):
            raise _Invalid(f"map {k!r} must be a 2-D numeric image, got {m.dtype} "
                           f"{m.shape}", MAPS_FILE)
        sizes.append((MAPS_FILE, f"map {k!r}", m.shape))
    for file, what, shape in sizes[1:]:
        ref_file, ref_what, ref = sizes[0]
        if tuple(shape) != tuple(ref):
            ref_text = ref_what if ref_file in (file, "calibration.json") else \
                f"{ref_file} ({ref_what})"
            raise _Invalid(f"{what} is {shape[1]}x{shape[0]} pixels, {ref_text} "
                           f"{ref[1]}x{ref[0]}: files mixed from different calibrations", file)
    if a is not None and "dofp" in p and "layout" in p["dofp"] and \
            layout_name_at(p["dofp"]["layout"], 0, 0) != a.layout:
        raise _Invalid(f"dofp.layout {p['dofp']['layout']} is not the analyzer model's "
                       f"{a.layout}")
    if a is not None and "camera" in p:
        _, _, ox, oy = p["camera"]["readout"]
        want = layout_name_at(p["camera"]["layout"], ox, oy)
        if a.layout != want:
            raise _Invalid(f"analyzer.npz layout {a.layout} is not the camera's {want} "
                           f"(camera.layout {p['camera']['layout']} at its readout offset)")
    valid = cs.dofp_maps.get("valid")
    if valid is not None and valid.dtype != bool and not np.isin(valid, (0, 1)).all():
        raise _Invalid("map 'valid' must hold only 0/1 (false/true)", MAPS_FILE)


def validate(cs: CalibrationSet, directory: str | pathlib.Path = ".") -> None:
    """Refuse (:class:`FormatError`, one line naming the file) a set whose sections, values or
    per-pixel files do not have the types, shapes and ranges the procedures write."""
    try:
        _validate_params(cs.params)
        _validate_pixels(cs)
    except _Invalid as exc:
        raise FormatError(f"{pathlib.Path(directory) / exc.file}: {exc}") from None


def _read_npz_file(path: pathlib.Path, reader):
    try:
        return reader(path)
    except FileNotFoundError:
        raise FormatError(f"{path}: missing (calibration.json lists it)") from None
    except FormatError:
        raise
    except Exception as exc:  # noqa: BLE001 - a damaged zip, bad arrays, ...: one line
        raise FormatError(f"{path}: not readable ({type(exc).__name__}: {exc})") from None


def _read_maps(path: pathlib.Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        if not hasattr(z, "files"):
            raise ValueError("not an .npz archive")
        return {k: z[k] for k in z.files}


def load(directory: str | pathlib.Path) -> CalibrationSet:
    """Read a calibration set folder; :class:`polrig.errors.FormatError` (one line naming the
    file) if it is not one: unreadable or damaged files, a missing or empty id, content that
    does not match the id, values of the wrong type, shape or range (:func:`validate`)."""
    d = pathlib.Path(directory)
    path = d / "calibration.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no calibration set here (run 'polrig calibrate all "
                                f"--out {d}')")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise FormatError(f"{path}: not a {FORMAT} file")
    version = doc.get("version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise FormatError(f"{path}: version: expected the integer {VERSION}, got "
                          f"{_show(version) if 'version' in doc else 'nothing'}")
    if version != VERSION:
        raise FormatError(f"{path}: calibration format version {version}, expected {VERSION}")
    cid = doc.get("id")
    if not isinstance(cid, str) or not cid.strip():
        raise FormatError(f"{path}: the set has no id (the checksum of its content), so it "
                          f"cannot be verified; calibrate again ('polrig calibrate all --out "
                          f"{d}')")
    files = doc.get("files")
    if files is None:  # written before the list existed: the files that are there
        files = [n for n in NPZ_FILES if (d / n).is_file()]
    elif not (isinstance(files, list) and all(f in NPZ_FILES for f in files)):
        raise FormatError(f"{path}: files: expected a list of {', '.join(NPZ_FILES)}, got "
                          f"{_show(files)}")
    params = _finite({k: v for k, v in doc.items()
                      if k not in ("format", "version", "id", "files")})
    analyzer = (_read_npz_file(d / ANALYZER_FILE, AnalyzerModel.load)
                if ANALYZER_FILE in files else None)
    maps = _read_npz_file(d / MAPS_FILE, _read_maps) if MAPS_FILE in files else {}
    cs = CalibrationSet(params, analyzer, maps, cid)
    if cs.id != cs.compute_id():
        raise FormatError(f"{path}: content does not match its id {cs.id} (files edited or "
                          f"mixed from different calibrations)")
    validate(cs, d)
    return cs
