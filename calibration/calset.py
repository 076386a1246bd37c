"""Calibration set files: one folder with human-readable parameters and per-pixel maps.

Layout of a calibration set folder (format ``polrig-calibration``, version 1):

* ``calibration.json``: every fitted parameter with its 1-sigma uncertainty, in the units and
  frames of ``docs/conventions.md`` (camera frame, metres, degrees), sections ``intrinsics``,
  ``turntable``, ``fixtures``, ``light``, ``generator``, ``dofp``, each optional (a step that
  has not run is absent), plus ``id``, ``created_utc`` and ``polrig_version``;
* ``analyzer.npz``: the per-pixel :class:`polrig.analyzer.AnalyzerModel` (``AnalyzerModel.save``);
* ``dofp_maps.npz``: per-pixel maps of the DoFP fit (``dark_dn``, ``flat_scale``,
  ``angle_std_deg``, ``modulation_std``, ``residual_rms_dn``, ``valid``).

The ``id`` is the first 16 hex digits of the SHA-256 of the canonical JSON parameters (without
``id``/``created_utc``) and of the bytes of the ``.npz`` files: it changes whenever any
calibrated value changes, and captures record it (``calibration_id``) in their metadata.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import io
import json
import pathlib
from typing import Any

import numpy as np

from calibration.errors import CalibrationError
from calibration.generator import GeneratorModel
from polrig.analyzer import AnalyzerModel
from polrig.errors import FormatError

FORMAT = "polrig-calibration"
VERSION = 1
SECTIONS = ("intrinsics", "turntable", "fixtures", "light", "generator", "dofp")


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
        """``{"K": (3, 3), "dist": (5,), "image_size": (w, h), ...}`` (pixels)."""
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
        """Write the set into ``directory`` (created if needed, files replaced atomically);
        returns the id."""
        from polrig import __version__
        from polrig.conventions import CONVENTIONS_VERSION
        from polrig.rawio import atomic_write_bytes, atomic_write_text

        d = pathlib.Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        self.id = self.compute_id()
        doc = {"format": FORMAT, "version": VERSION, "id": self.id,
               "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(
                   timespec="seconds"),
               "polrig_version": __version__, "conventions_version": CONVENTIONS_VERSION,
               "frames": "camera frame (OpenCV: X right, Y down, Z forward), metres, degrees; "
                         "see docs/conventions.md and docs/calibration.md",
               **{k: self.params[k] for k in SECTIONS if k in self.params}}
        for k, v in self.params.items():
            if k not in SECTIONS and k not in doc:
                doc[k] = v
        if self.analyzer is not None:
            self.analyzer.save(d / "analyzer.npz")
        if self.dofp_maps:
            atomic_write_bytes(d / "dofp_maps.npz", _npz_bytes(self.dofp_maps))
        atomic_write_text(d / "calibration.json", json.dumps(_jsonable(doc), indent=2) + "\n")
        return self.id


_STEP_OF = {"intrinsics": "intrinsics", "turntable": "turntable", "fixtures": "turntable",
            "light": "light", "generator": "stokes", "dofp": "dofp"}


def _finite(x: Any) -> Any:
    if isinstance(x, str) and x in ("inf", "-inf", "nan"):
        return float(x)
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite(v) for v in x]
    return x


def load(directory: str | pathlib.Path) -> CalibrationSet:
    """Read a calibration set folder; :class:`polrig.errors.FormatError` if it is not one."""
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
    if int(doc.get("version", -1)) != VERSION:
        raise FormatError(f"{path}: calibration format version {doc.get('version')}, "
                          f"expected {VERSION}")
    params = _finite({k: v for k, v in doc.items()
                      if k not in ("format", "version", "id")})
    analyzer = AnalyzerModel.load(d / "analyzer.npz") if (d / "analyzer.npz").is_file() else None
    maps: dict[str, np.ndarray] = {}
    if (d / "dofp_maps.npz").is_file():
        try:
            with np.load(d / "dofp_maps.npz", allow_pickle=False) as z:
                maps = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise FormatError(f"{d / 'dofp_maps.npz'}: not readable ({exc})") from None
    cs = CalibrationSet(params, analyzer, maps, str(doc.get("id", "")))
    if cs.id and cs.id != cs.compute_id():
        raise FormatError(f"{path}: content does not match its id {cs.id} (files edited or "
                          f"mixed from different calibrations)")
    return cs
