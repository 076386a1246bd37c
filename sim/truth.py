"""Ground truth of the simulated rig and the truth files written next to simulated captures.

:meth:`SimTruth.ground_truth` gives the per-pixel truth for the camera's current ROI, exposure,
gain, the light's level and the turntable's pose; :meth:`SimTruth.rig_parameters` the hidden
parameters calibration has to recover. :func:`write_truth` writes them as ``truth.json`` plus
one ``truth_<name>.npz`` and ``truth_<name>_mueller.exr`` (:mod:`polrig.formats.exr`) per capture; the schema is documented in ``docs/sim.md``.
"""

from __future__ import annotations

import io
import json
import pathlib
import zipfile
from typing import Any, Protocol

import numpy as np

from polrig.atomic import atomic_write_bytes, atomic_write_text
from polrig.formats.exr import colour_planes, read_mueller_exr, write_mueller_exr
from polrig.optics.conventions import CONVENTIONS_VERSION
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sim import targets
from polrig.sim.world import Roi, SimWorld

TRUTH_FORMAT = "polrig-sim-truth"
TRUTH_VERSION = 1

#: Per-pixel arrays of :meth:`SimTruth.ground_truth` and the truth ``.npz`` files.
PIXEL_KEYS = ("mueller", "mask", "lit", "shadow", "normal", "kd", "alpha", "eta", "ks", "wi",
              "wo", "depth_m", "position_m", "object_index", "material_index")


def pose_truth(world: SimWorld, *, turntable_deg: float, roi: Roi, exposure_us: float,
               gain_db: float) -> dict[str, Any]:
    """Per-pixel truth of a ROI at a turntable pose (see :meth:`SimTruth.ground_truth`)."""
    r = world.render_pose(turntable_deg)
    w, h, ox, oy = roi
    sl = (slice(oy, oy + h), slice(ox, ox + w))
    out: dict[str, Any] = {
        "mueller": world.mueller_dn(turntable_deg, exposure_us, gain_db, roi),
        "mask": r.mask[sl], "lit": r.lit[sl], "shadow": r.shadow[sl],
        "normal": r.normal[(...,) + sl], "kd": r.kd[(...,) + sl], "alpha": r.alpha[sl],
        "eta": r.eta[sl], "ks": r.ks[sl], "wi": r.wi[(...,) + sl], "wo": r.wo[(...,) + sl],
        "depth_m": r.depth_m[sl], "position_m": r.position_m[(...,) + sl],
        "object_index": r.object_index[sl], "material_index": r.material_index[sl],
    }
    out = {k: np.ascontiguousarray(v) for k, v in out.items()}
    out.update({"turntable_deg": float(turntable_deg), "roi": tuple(int(v) for v in roi),
                "exposure_us": float(exposure_us), "gain_db": float(gain_db),
                "light_level": float(world.light_level), "light_on": bool(world.light_on)})
    return out


class CameraSettings(Protocol):
    """What the truth needs of the simulated camera: its current readout and settings."""

    roi: Roi
    exposure_us: float
    gain_db: float


class SimTruth:
    """Ground truth of a simulated rig: its ``world`` seen through ``camera``'s current ROI,
    exposure and gain (the :class:`polrig.sim.devices.SimRig` builds it; this module knows
    nothing of the devices). It is the simulated rig's
    :class:`polrig.acquisition.hal.RigTruth`."""

    def __init__(self, world: SimWorld, camera: CameraSettings) -> None:
        self._world = world
        self._camera = camera

    def ground_truth(self, *, turntable_deg: float | None = None) -> dict[str, Any]:
        """Truth for the camera's current ROI, exposure and gain, the light's level and the
        turntable's current angle (or ``turntable_deg``).

        Arrays (``docs/sim.md``, frames and units in ``docs/conventions.md``): ``mueller``
        ``(C, 3, 3, h, w)`` float32 in DN per unit incident S0 in the rig frames; ``mask``,
        ``lit``, ``shadow`` ``(h, w)`` bool; ``normal``, ``wi``, ``wo`` ``(3, h, w)`` unit
        vectors in the camera frame; ``kd`` ``(3, h, w)``; ``alpha``, ``eta``, ``ks``,
        ``depth_m`` ``(h, w)``; ``position_m`` ``(3, h, w)`` world metres; plus the scalars
        ``turntable_deg``, ``roi``, ``exposure_us``, ``gain_db``, ``light_level``, ``light_on``.
        """
        cam = self._camera
        world = self._world
        table = world.turntable_angle_deg() if turntable_deg is None else float(turntable_deg)
        return pose_truth(world, turntable_deg=table, roi=cam.roi, exposure_us=cam.exposure_us,
                          gain_db=cam.gain_db)

    def rig_parameters(self) -> dict[str, Any]:
        """Hidden parameters of the simulated rig, JSON-serialisable."""
        return rig_parameters(self._world)

    def incident_stokes(self, stage_deg: float) -> np.ndarray:
        """True normalised incident Stokes ``(3,)`` at a stage reading."""
        return self._world.generator.incident_stokes(stage_deg)

    def analyzer(self) -> AnalyzerModel:
        """The simulated camera's true per-pixel analyzer (its sensor's)."""
        return self._world.sensor.analyzer

    def mount_target(self, name: str, **fixture: Any) -> None:
        """Swap the simulated target in front of the camera (:func:`polrig.sim.targets.mount`)."""
        targets.mount(self._world, name, **fixture)


def rig_parameters(world: SimWorld) -> dict[str, Any]:
    """Hidden parameters of a :class:`polrig.sim.world.SimWorld` (see ``docs/sim.md``)."""
    sc = world.scene
    return {
        "light_position_m": sc.light.position_m.tolist(),
        "light_intensity_rgb": sc.light.intensity_rgb.tolist(),
        "stage_zero_axis": sc.stage_zero_axis.tolist(),
        "illumination_target_m": sc.illumination_target_m.tolist(),
        "generator": world.generator.to_json(),
        "camera": sc.camera.to_json(),
        "turntable": {"axis": sc.turntable.axis.tolist(),
                      "point_m": sc.turntable.point_m.tolist()},
        "sensor": world.sensor.to_json(),
        "scene": sc.to_json(),
        "distribution": world.distribution,
        "seed": world.seed,
        "noise": world.noise,
        # recorded only when on, so renders of direct light read as before
        **({"indirect_samples": world.indirect_samples} if world.indirect_samples else {}),
    }


def npz_bytes(arrays: dict[str, np.ndarray], compress: bool = True) -> bytes:
    """An ``.npz`` archive (readable by :func:`numpy.load`) in memory; ``compress`` uses
    DEFLATE level 1 (several times faster than :func:`numpy.savez_compressed`'s default and
    nearly as small on images that are mostly background)."""
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", method, compresslevel=1 if compress else None,
                         allowZip64=True) as zf:
        for name, a in arrays.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
    return buf.getvalue()


def write_truth(directory: str | pathlib.Path, name: str, truth: dict[str, Any],
                parameters: dict[str, Any], *, capture: dict[str, Any] | None = None,
                exr: bool = True, compress: bool = True) -> dict[str, str]:
    """Write one capture's truth into ``directory`` (atomically) and register it in
    ``truth.json`` (created or updated; a capture of the same ``name`` is replaced).

    ``truth``: a :meth:`SimTruth.ground_truth` dict; ``parameters``: :func:`rig_parameters`;
    ``capture``: extra JSON metadata of the capture (frames written, incident states).
    Returns the written file names.
    """
    d = pathlib.Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    # The Mueller image goes into the EXR when one is written (not duplicated in the npz).
    arrays = {k: np.asarray(truth[k]) for k in PIXEL_KEYS
              if k in truth and not (exr and k == "mueller")}
    npz_name = f"truth_{name}.npz"
    atomic_write_bytes(d / npz_name, npz_bytes(arrays, compress))
    files["npz"] = npz_name
    if exr:
        files["exr"] = _write_mueller_exr(d, f"truth_{name}_mueller.exr", truth)
    entry = {"name": name, "files": files,
             **{k: truth[k] for k in ("turntable_deg", "exposure_us", "gain_db", "light_level",
                                      "light_on") if k in truth},
             "roi": list(truth.get("roi", ())),
             "shape": list(np.shape(truth["mask"])),
             "channels": int(np.shape(truth["mueller"])[0]),
             **(capture or {})}
    index_path = d / "truth.json"
    index = {"format": TRUTH_FORMAT, "version": TRUTH_VERSION,
             "conventions_version": CONVENTIONS_VERSION, "units": {
                 "mueller": "DN per unit incident S0 (docs/conventions.md, Radiometric units)",
                 "normal": "unit, camera frame", "wi": "unit, towards the light, camera frame",
                 "wo": "unit, towards the camera, camera frame", "depth_m": "m, camera Z",
                 "position_m": "m, world frame"},
             "rig": parameters, "captures": []}
    if index_path.is_file():
        try:
            old = json.loads(index_path.read_text())
            if old.get("format") == TRUTH_FORMAT:
                index["captures"] = [c for c in old.get("captures", []) if c.get("name") != name]
        except (OSError, ValueError):
            pass
    index["captures"].append(entry)
    atomic_write_text(index_path, json.dumps(index, indent=1, default=_json_default))
    files["json"] = "truth.json"
    return files


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _write_mueller_exr(d: pathlib.Path, name: str, truth: dict[str, Any]) -> str:
    """Write the truth Mueller image (``M{row}{col}.{R,G,B|Y}``) with the mask and the
    normals as extra planes (:func:`polrig.formats.exr.write_mueller_exr`)."""

    extra = {"mask": np.asarray(truth["mask"], np.float32)}
    extra.update(colour_planes("normal", np.asarray(truth["normal"], np.float32)))
    meta = {"source": "polrig sim truth", "units": "DN per unit incident S0",
            **{k: truth[k] for k in ("turntable_deg", "exposure_us", "gain_db", "light_level")
               if k in truth}, "roi": list(truth.get("roi", ()))}
    write_mueller_exr(d / name, np.asarray(truth["mueller"], dtype=np.float32), extra=extra,
                      metadata=meta)
    return name


def read_truth(directory: str | pathlib.Path, name: str | None = None) -> tuple[dict, dict]:
    """``(truth.json contents, arrays of capture name)`` (the first capture by default); the
    Mueller image comes from the EXR when the npz does not hold it."""
    d = pathlib.Path(directory)
    index = json.loads((d / "truth.json").read_text())
    caps = index["captures"]
    entry = caps[0] if name is None else next(c for c in caps if c["name"] == name)
    with np.load(d / entry["files"]["npz"], allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    if "mueller" not in arrays:
        arrays["mueller"] = read_mueller_exr(d / entry["files"]["exr"]).mueller
    return index, arrays
