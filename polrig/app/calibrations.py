"""What processing needs from a calibration set, and the geometry it implies.

:class:`Calibration` (incident states, per-pixel analyzer model, intrinsics, stage zero
axis, the calibration's own uncertainty); :func:`load_calibration` reads a calibration set
folder (``None``: the nominal rig, :func:`nominal_calibration`);
:func:`check_calibration_fits` refuses frames a set was not calibrated for;
:func:`single_shot_geometry` gives the single-shot route (:mod:`polrig.app.single_shot`) the
rig geometry; :func:`check_plan` refuses a plan that cannot give a result.

Errors name the problem and the calibration set, never a command-line option:
:class:`polrig.acquisition.plan.PlanError` carries the field (``"calibration"``, ``"states_deg"``,
``"mode"``) for the command line to name its option.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from typing import Any, Callable, Sequence

import numpy as np

from polrig.acquisition.plan import NETWORK_MODES, PlanError
from polrig.app.rig import nominal_geometry
from polrig.app.session import Session
from polrig.app.single_shot import SingleShot
from polrig.calibration.calset import SensorGeometry
from polrig.calibration.rigframes import stage_zero_axis_cam
from polrig.errors import ConfigError
from polrig.formats.config import GEOMETRY_KEYS
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import AnalyzerModel, frame_layout  # noqa: F401 (frame_layout re-exported)
from polrig.solve.hybrid import open_direction
from polrig.solve.reference import condition_number, validate_states

NOMINAL_CALIBRATION_ID = "nominal"

#: 1-sigma priors of an uncalibrated IMX250MZR/MYR analyzer against the ideal model
#: (``polrig.solve.reference.AnalyzerTolerance``): relative gain 1 % (pixel response non-uniformity of
#: the IMX250 class, about 1 % in EMVA 1288 data sheets of cameras with this sensor),
#: micro-polarizer orientation 0.5 deg (per-pixel scatter plus per-angle bias of wire-grid
#: arrays; measured deviations of a few tenths of a degree, Powell and Gruev, Opt. Express
#: 21(18), 2013), diattenuation 0.02 (extinction ratios of ~100-300 give D = 0.98-0.993).
NOMINAL_ANALYZER_TOLERANCE = (0.01, 0.5, 0.02)
#: 1-sigma priors of an uncalibrated generator (``polrig.solve.reference.GeneratorTolerance``):
#: stage zero offset 2 deg (a polarizer mounted in its rotation mount by the index mark),
#: inverse extinction ratio 0.006 (a film polarizer specified ER >= 100: 1/ER in [0, 0.01],
#: RMS deviation from the nominal 0 about 0.006).
NOMINAL_GENERATOR_TOLERANCE = (2.0, 0.006)


# -- calibration -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Calibration:
    """What processing needs from a calibration set.

    ``incident_stokes_fn`` maps stage angles (deg, ``(N,)``) to normalised incident linear
    Stokes vectors ``(N, 3)`` (``docs/conventions.md``, "Radiometric units"); ``None`` is the
    nominal ideal polarizer (:func:`polrig.optics.mueller.polarizer_stokes` with intensity 1, so
    ``S0 = 1/2``). ``analyzer`` is a per-pixel analyzer model of the full readout, ``None``
    for the ideal analyzer.

    Geometry for single-shot reconstruction (``None``: not calibrated, the rig's nominal
    geometry is used, :func:`single_shot_geometry`): ``intrinsics`` ``(fx, fy, cx, cy)`` in
    pixels of the full sensor readout (OpenCV pinhole, distortion ignored) and
    ``stage_zero_axis_camera`` ``(x, y, z)``, the polarizer stage's zero axis in the camera
    frame (the ``x`` of the incident Stokes frame, "Stokes reference frames"). For the diffuse
    test (``--models diffuse``, :mod:`polrig.app.diffuse_route`): ``light_position_camera_m``, the
    point light, and ``object_point_camera_m``, the object's centre (the turntable axis point
    nearest the camera's optical axis), both ``(x, y, z)`` in the camera frame, metres
    (:func:`calibration_light_geometry`).

    Uncertainty of the calibration itself (1 sigma, propagated into the reported ``sigma`` by
    :func:`polrig.solve.reference.solve_reference`): ``analyzer_tolerance`` ``(gain_rel, angle_deg,
    diattenuation)`` and ``generator_tolerance`` ``(zero_offset_deg, inverse_extinction)``.
    The defaults (zeros) mean an exactly known rig; :func:`nominal_calibration` declares the
    priors of an uncalibrated one, :func:`load_calibration` a calibration set's fitted values.

    ``sensor``: the sensor pixels a calibration set was calibrated on
    (:class:`polrig.calibration.calset.SensorGeometry`: layout, calibrated readout area on the
    sensor, sensor size; ``None``: valid for any camera), ``source`` the set's folder. The
    analyzer model covers that area (``sensor.area``); frames must come from the same sensor
    and lie inside it (:func:`check_calibration_fits`).
    """

    id: str
    incident_stokes_fn: Callable[[np.ndarray], np.ndarray] | None = None
    analyzer: AnalyzerModel | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    stage_zero_axis_camera: tuple[float, float, float] | None = None
    light_position_camera_m: tuple[float, float, float] | None = None
    object_point_camera_m: tuple[float, float, float] | None = None
    analyzer_tolerance: tuple[float, float, float] = (0.0, 0.0, 0.0)
    generator_tolerance: tuple[float, float] = (0.0, 0.0)
    sensor: Any = None
    source: str | None = None

    @property
    def area_offset(self) -> tuple[int, int]:
        """Sensor position ``(x, y)`` of the calibrated area's first pixel (the analyzer
        model's pixel (0, 0)); (0, 0) without a calibrated geometry."""
        area = None if self.sensor is None else self.sensor.area
        return (0, 0) if area is None else (int(area[2]), int(area[3]))

    def incident_stokes(self, states_deg: Sequence[float]) -> np.ndarray:
        a = np.asarray(states_deg, dtype=np.float64)
        if self.incident_stokes_fn is None:
            return polarizer_stokes(np.deg2rad(a), intensity=1.0)
        return np.asarray(self.incident_stokes_fn(a), dtype=np.float64).reshape(len(a), 3)


def nominal_calibration() -> Calibration:
    """Ideal polarizer and ideal analyzer, with the priors of an uncalibrated rig
    (:data:`NOMINAL_ANALYZER_TOLERANCE`, :data:`NOMINAL_GENERATOR_TOLERANCE`)."""
    return Calibration(NOMINAL_CALIBRATION_ID, analyzer_tolerance=NOMINAL_ANALYZER_TOLERANCE,
                       generator_tolerance=NOMINAL_GENERATOR_TOLERANCE)


def load_calibration(path: str | os.PathLike | None, *, session: Session | None = None
                     ) -> Calibration:
    """The calibration set in folder ``path`` (``None``: the nominal calibration).

    For a resumed ``session`` the calibration must be the one it was started with.
    """
    if path is None:
        cal = nominal_calibration()
    else:
        p = pathlib.Path(path)
        if not p.exists():
            raise FileNotFoundError(f"calibration set {p}: no such folder")
        try:
            from polrig.calibration import calibset  # type: ignore[attr-defined]
        except ImportError:
            raise PlanError("calibration", "this polrig cannot read calibration sets yet (no "
                                           "calibration loader installed); use the nominal "
                                           "model", subject=str(p), what="calibration set") from None
        cs = calibset.load(p)
        a_tol, g_tol = calibset.tolerances(cs, NOMINAL_ANALYZER_TOLERANCE,
                                           NOMINAL_GENERATOR_TOLERANCE)
        cal = Calibration(cs.id, cs.incident_stokes, cs.analyzer,
                          *calibration_geometry(cs), *calibration_light_geometry(cs), analyzer_tolerance=a_tol,
                          generator_tolerance=g_tol, sensor=cs.sensor_geometry(),
                          source=str(p))
    if session is not None and session.manifest.get("calibration_id") != cal.id:
        raise PlanError("calibration", f"the session was captured with calibration "
                                       f"{session.manifest.get('calibration_id')!r}, not "
                                       f"{cal.id!r}")
    return cal


def calibration_geometry(cs) -> tuple[tuple[float, float, float, float] | None,
                                      tuple[float, float, float] | None]:
    """``(intrinsics, stage_zero_axis_camera)`` of a calibration set
    (:class:`polrig.calibration.calset.CalibrationSet`), each ``None`` where the set lacks the step:
    ``(fx, fy, cx, cy)`` from the camera matrix ``K`` carried from the calibrated readout's
    pixels to the full sensor's (the principal point plus the readout offset of the set's
    ``camera`` section), and the stage zero axis from the generator step, else from the
    turntable axis and the light position (:func:`polrig.calibration.rigframes.stage_zero_axis_cam`,
    the rig's definition)."""
    has = cs.has
    intrinsics = axis = None
    if has("intrinsics"):
        k = np.asarray(cs.intrinsics["K"], np.float64)
        geo = cs.sensor_geometry()
        ox, oy = (0, 0) if geo is None or geo.area is None else geo.area[2:]
        intrinsics = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + ox, float(k[1, 2]) + oy)
    if has("generator") and "stage_zero_axis_cam" in cs.params.get("generator", {}):
        axis = np.asarray(cs.stage_zero_axis_cam, np.float64)
    elif has("turntable") and has("light"):
        tt = cs.turntable_axis
        axis = stage_zero_axis_cam(cs.light_position_m, tt["point_cam_m"], tt["axis_cam"])
    if axis is not None and not (np.all(np.isfinite(axis)) and np.any(axis)):
        axis = None
    return intrinsics, None if axis is None else tuple(float(v) for v in axis)


def calibration_light_geometry(cs) -> tuple[tuple[float, float, float] | None,
                                            tuple[float, float, float] | None]:
    """``(light_position_camera_m, object_point_camera_m)`` of a calibration set, each ``None``
    where the set lacks the step: the light step's point light, and the point of the turntable
    axis nearest the camera's optical axis (the ray ``s (0, 0, 1)``; the object sits on the axis
    in the middle of the picture), camera frame, metres."""
    light = point = None
    if cs.has("light"):
        light = np.asarray(cs.light_position_m, np.float64)
    if cs.has("turntable"):
        tt = cs.turntable_axis
        point = axis_point_nearest_optical_axis(tt["point_cam_m"], tt["axis_cam"])
    return tuple((None if v is None or not np.all(np.isfinite(v)) else tuple(float(x) for x in v))
                 for v in (light, point))


def axis_point_nearest_optical_axis(point: Sequence[float], axis: Sequence[float]) -> np.ndarray:
    """The point ``(3,)`` of the line ``point + t axis`` (camera frame) nearest the camera's
    optical axis ``s (0, 0, 1)``: the common perpendicular's foot; ``point`` itself where the
    two are parallel."""
    p, a = np.asarray(point, np.float64), np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    b = a @ z
    den = 1.0 - b * b
    if den < 1e-12:
        return p
    t = (b * (p @ z) - p @ a) / den
    return p + t * a


def check_calibration_fits(calibration: Calibration, *, layout: str | None,
                           readout: Sequence[int] | None,
                           sensor_size: Sequence[int] | None = None,
                           what: str = "the camera", phase: bool = True) -> None:
    """Refuse (:class:`ConfigError`, one line naming the calibration folder and both
    geometries) frames that a calibration set was not calibrated for: another mosaic layout
    (mono/colour, or another mosaic phase when ``phase``), another sensor size (where both
    are known) or a readout ``(width, height, offset_x, offset_y)`` not inside the calibrated
    area. A readout (ROI) inside the calibrated area is accepted: the analyzer model is
    cropped to it and the intrinsics carried by its offset. The nominal calibration, and a set
    with no camera-dependent step, fit every camera. ``capture`` checks before any device
    moves or any session exists, ``reconstruct`` before a revision exists, ``infer`` before
    the network runs."""
    have = calibration.sensor
    if have is None:
        return

    now = SensorGeometry(None if layout is None else str(layout),
                         None if readout is None else tuple(int(v) for v in readout),
                         None if sensor_size is None else tuple(int(v) for v in sensor_size))
    why = have.mismatch(now, phase=phase)
    if why:
        raise PlanError("calibration", f"calibrated on {have.describe('calibrated area')}; "
                                       f"{what}: {now.describe()} ({why}); use a set "
                                       f"calibrated on this camera ('polrig calibrate all "
                                       f"--out DIR' on it)", subject=str(calibration.source),
                        what="calibration set")


def check_calibration_fits_rig(calibration: Calibration, rig) -> None:
    """:func:`check_calibration_fits` for ``rig``'s camera as it reads out now."""
    if calibration.sensor is None:
        return

    now = SensorGeometry.of_rig(rig)
    check_calibration_fits(calibration, layout=now.layout, readout=now.area,
                           sensor_size=now.sensor_size, what="this camera")


def single_shot_geometry(calibration: Calibration, rig_config: dict[str, Any] | None,
                         sensor_size: tuple[int, int] | None = None) -> dict[str, Any]:
    """Intrinsics (full-sensor pixels) and stage zero axis (camera frame) for single-shot
    reconstruction, and the light's and the object's positions (camera frame, metres) for the
    diffuse test (:data:`polrig.formats.config.GEOMETRY_KEYS`): the calibration set's where it has them, else the rig's nominal geometry
    (:func:`polrig.app.rig.nominal_geometry`: the ``[nominal_geometry]`` table of the rig config, or the
    simulator's design values for a simulated camera). ``None`` values mean "unknown": the
    model then uses its training geometry (``models/weights/model.json``). ``sources`` says
    where each value came from."""

    nominal = nominal_geometry(rig_config, sensor_size)
    out: dict[str, Any] = {"sources": {}}
    for key in GEOMETRY_KEYS:
        cal_value = getattr(calibration, key)
        if cal_value is not None:
            out[key], out["sources"][key] = tuple(cal_value), f"calibration {calibration.id}"
        elif nominal[key] is not None:
            out[key], out["sources"][key] = tuple(nominal[key]), nominal["source"]
        else:
            out[key], out["sources"][key] = None, "model training geometry"
    return out


def check_plan(plan, calibration: Calibration, device: str = "auto", model_size: str = "auto") -> float | None:
    """Reject a plan that cannot give a result, before any device moves.

    Reference mode: the incident states must determine the Mueller block (at least 3, not
    collinear, condition number below :data:`polrig.solve.reference.DEFAULT_MAX_CONDITION`);
    returns the condition number. Single-shot: a model must be installed and open on
    ``device`` (:meth:`polrig.app.single_shot.SingleShot.open`: the loaded model the capture's
    processing then gets, not a second load, of ``model_size``; :class:`polrig.acquisition.plan.PlanError`
    of ``mode`` when there is none, :class:`polrig.models.sizes.ModelSizeUnavailable` for a size not shipped, :class:`polrig.models.devices.DeviceUnavailable` for a forced ``cuda``
    that cannot run). Hybrid: the same, and the model must have a calibrated uncertainty (its
    sigma is the prior's); any number of states from 1 (they need not determine the block:
    the prior fills in what they leave out), but two must be two polarizer states, not one
    twice (0 and 180 deg: their incident states are parallel and leave no one direction open
    for the prior's scale there, :func:`polrig.solve.hybrid.open_direction`; more frames of a
    state are ``frames_per_state``); returns the state set's condition number, which may be
    infinite (fewer than 3 states, or collinear ones). Adaptive: as hybrid, of its first state
    (it chooses the others as it goes).
    """
    if plan.mode in NETWORK_MODES:
        route = SingleShot.open(device, size=model_size)
        if plan.mode == "single-shot":
            return None
        route.check_sigma()
        s_in = calibration.incident_stokes(plan.states_deg)
        if plan.mode == "hybrid" and len(plan.states_deg) == 2:
            try:
                open_direction(s_in)
            except ConfigError:
                states = ",".join(f"{a:g}" for a in plan.states_deg)
                raise PlanError("states_deg", "the two are one polarizer state (parallel incident states); give "
                                              "two angles apart, e.g. 0,90, or one state with more frames "
                                              "(--frames)", subject=states, what="polarizer states") from None
        return state_set_condition(s_in)
    try:
        return validate_states(calibration.incident_stokes(plan.states_deg))
    except ConfigError as exc:
        states = ",".join(f"{a:g}" for a in plan.states_deg)
        raise PlanError("states_deg", str(exc), subject=states,
                        what="polarizer states") from None


def state_set_condition(s_in) -> float:
    """The condition number of incident states ``(N, 3)`` as the reference solve defines it
    (:func:`polrig.solve.reference.condition_number` of the ideal-analyzer design), ``inf``
    where they do not determine the block (fewer than 3, collinear): what a hybrid plan reports."""
    return float(condition_number(np.asarray(s_in, np.float64).reshape(-1, 3)))
