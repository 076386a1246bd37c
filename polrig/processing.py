"""Turn a capture's raw frames into Mueller images (with uncertainty and mask), and score them.

Array level: :mod:`polrig.radiometry` (state radiance, demosaic, solve) and
:mod:`polrig.scoring` (truth on the output grid, score); their names are re-exported here.

Session level: :class:`Processor` (used by :func:`polrig.capture.run_session`) reads a
capture's raw frames back from the session (checksums verified), solves, writes
``mueller.exr`` (Mueller channels plus ``sigma``, ``residual`` and ``mask`` planes), and on the
simulated rig ``truth_mueller.exr`` and a score; :func:`reprocess_session` does the same into
a new revision for ``polrig reconstruct``.

Uncertainty propagation: per raw sample the model variance
(:meth:`polrig.noise.SensorModel.variance_dn2` at the measured mean signal, divided by K;
plus the variance of the subtracted dark mean), HDR-merged by :func:`polrig.reference.merge_hdr`;
the ``superpixel`` demosaic averages ``n`` same-class pixels, so the variance is the mean
variance divided by ``n`` (exact); interpolating demosaics get the interpolated variance
(an approximation: it ignores the correlation the interpolation creates).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import tempfile
from typing import Any, Callable, Sequence

import numpy as np

from polrig.analyzer import AnalyzerModel, resolve_layout
from polrig.demosaic import demosaic_float
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.hal import Frame
from polrig.layouts import MosaicLayout
from polrig.mueller import polarizer_stokes
from polrig.noise import SensorModel
from polrig.radiometry import (StateRadiance, adc_scale, analyzer_stack,  # noqa: F401 (re-exported)
                               reference_from_frames, state_radiance)
from polrig.rawio import read_raw
from polrig.reference import ReferenceResult, reason_names, validate_states
from polrig.scoring import (_psnr_db, format_score, score_against_truth,  # noqa: F401 (re-exported)
                            truth_on_output_grid)
from polrig.session import (COMPLETE, FAILED, PENDING, Session, SignalGuard,
                            interruption_reason, sha256_file)

NOMINAL_CALIBRATION_ID = "nominal"

#: 1-sigma priors of an uncalibrated IMX250MZR/MYR analyzer against the ideal model
#: (``polrig.reference.AnalyzerTolerance``): relative gain 1 % (pixel response non-uniformity of
#: the IMX250 class, about 1 % in EMVA 1288 data sheets of cameras with this sensor),
#: micro-polarizer orientation 0.5 deg (per-pixel scatter plus per-angle bias of wire-grid
#: arrays; measured deviations of a few tenths of a degree, Powell and Gruev, Opt. Express
#: 21(18), 2013), diattenuation 0.02 (extinction ratios of ~100-300 give D = 0.98-0.993).
NOMINAL_ANALYZER_TOLERANCE = (0.01, 0.5, 0.02)
#: 1-sigma priors of an uncalibrated generator (``polrig.reference.GeneratorTolerance``):
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
    nominal ideal polarizer (:func:`polrig.mueller.polarizer_stokes` with intensity 1, so
    ``S0 = 1/2``). ``analyzer`` is a per-pixel analyzer model of the full readout, ``None``
    for the ideal analyzer.

    Geometry for single-shot reconstruction (``None``: not calibrated, the rig's nominal
    geometry is used, :func:`single_shot_geometry`): ``intrinsics`` ``(fx, fy, cx, cy)`` in
    pixels of the full sensor readout (OpenCV pinhole, distortion ignored) and
    ``stage_zero_axis_camera`` ``(x, y, z)``, the polarizer stage's zero axis in the camera
    frame (the ``x`` of the incident Stokes frame, "Stokes reference frames").

    Uncertainty of the calibration itself (1 sigma, propagated into the reported ``sigma`` by
    :func:`polrig.reference.solve_reference`): ``analyzer_tolerance`` ``(gain_rel, angle_deg,
    diattenuation)`` and ``generator_tolerance`` ``(zero_offset_deg, inverse_extinction)``.
    The defaults (zeros) mean an exactly known rig; :func:`nominal_calibration` declares the
    priors of an uncalibrated one, :func:`load_calibration` a calibration set's fitted values.

    ``sensor``: the sensor pixels a calibration set was calibrated on
    (:class:`calibration.calset.SensorGeometry`: layout, calibrated readout area on the
    sensor, sensor size; ``None``: valid for any camera), ``source`` the set's folder. The
    analyzer model covers that area (``sensor.area``); frames must come from the same sensor
    and lie inside it (:func:`check_calibration_fits`).
    """

    id: str
    incident_stokes_fn: Callable[[np.ndarray], np.ndarray] | None = None
    analyzer: AnalyzerModel | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    stage_zero_axis_camera: tuple[float, float, float] | None = None
    analyzer_tolerance: tuple[float, float, float] = (0.0, 0.0, 0.0)
    generator_tolerance: tuple[float, float] = (0.0, 0.0)
    sensor: Any = None
    source: str | None = None

    @property
    def area_offset(self) -> tuple[int, int]:
        """Sensor position ``(x, y)`` of the calibrated area's first pixel (the analyzer
        model's pixel (0, 0)); (0, 0) without a calibrated geometry."""
        area = getattr(self.sensor, "area", None)
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
    """The calibration named by ``--calibration`` (``None``: nominal).

    For a resumed ``session`` the calibration must be the one it was started with.
    """
    if path is None:
        cal = nominal_calibration()
    else:
        p = pathlib.Path(path)
        if not p.exists():
            raise FileNotFoundError(f"--calibration {p}: no such calibration set")
        try:
            from calibration import calibset  # type: ignore[attr-defined]
        except ImportError:
            raise ConfigError(f"--calibration {p}: this polrig cannot read calibration sets "
                              f"yet (no calibration loader installed); omit --calibration to "
                              f"use the nominal model") from None
        cs = calibset.load(p)
        a_tol, g_tol = calibset.tolerances(cs, NOMINAL_ANALYZER_TOLERANCE,
                                           NOMINAL_GENERATOR_TOLERANCE)
        cal = Calibration(cs.id, cs.incident_stokes, getattr(cs, "analyzer", None),
                          *calibration_geometry(cs), analyzer_tolerance=a_tol,
                          generator_tolerance=g_tol, sensor=cs.sensor_geometry(),
                          source=str(p))
    if session is not None and session.manifest.get("calibration_id") != cal.id:
        raise ConfigError(f"--resume: the session was captured with calibration "
                          f"{session.manifest.get('calibration_id')!r}, not {cal.id!r}")
    return cal


def calibration_geometry(cs) -> tuple[tuple[float, float, float, float] | None,
                                      tuple[float, float, float] | None]:
    """``(intrinsics, stage_zero_axis_camera)`` of a calibration set
    (:class:`calibration.calset.CalibrationSet`), each ``None`` where the set lacks the step:
    ``(fx, fy, cx, cy)`` from the camera matrix ``K`` carried from the calibrated readout's
    pixels to the full sensor's (the principal point plus the readout offset of the set's
    ``camera`` section), and the stage zero axis from the generator step, else from the
    turntable axis and the light position (:func:`calibration.rigframes.stage_zero_axis_cam`,
    the rig's definition)."""
    has = getattr(cs, "has", lambda section: False)
    intrinsics = axis = None
    if has("intrinsics"):
        k = np.asarray(cs.intrinsics["K"], np.float64)
        geo = cs.sensor_geometry() if hasattr(cs, "sensor_geometry") else None
        ox, oy = (0, 0) if geo is None or geo.area is None else geo.area[2:]
        intrinsics = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + ox, float(k[1, 2]) + oy)
    if has("generator") and "stage_zero_axis_cam" in cs.params.get("generator", {}):
        axis = np.asarray(cs.stage_zero_axis_cam, np.float64)
    elif has("turntable") and has("light"):
        from calibration.rigframes import stage_zero_axis_cam

        tt = cs.turntable_axis
        axis = stage_zero_axis_cam(cs.light_position_m, tt["point_cam_m"], tt["axis_cam"])
    if axis is not None and not (np.all(np.isfinite(axis)) and np.any(axis)):
        axis = None
    return intrinsics, None if axis is None else tuple(float(v) for v in axis)


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
    from calibration.calset import SensorGeometry

    now = SensorGeometry(None if layout is None else str(layout),
                         None if readout is None else tuple(int(v) for v in readout),
                         None if sensor_size is None else tuple(int(v) for v in sensor_size))
    why = have.mismatch(now, phase=phase)
    if why:
        raise ConfigError(f"--calibration {calibration.source}: calibrated on "
                          f"{have.describe('calibrated area')}; {what}: {now.describe()} "
                          f"({why}); use a set calibrated on this camera ('polrig calibrate "
                          f"all --out DIR' on it)")


def check_calibration_fits_rig(calibration: Calibration, rig) -> None:
    """:func:`check_calibration_fits` for ``rig``'s camera as it reads out now."""
    if calibration.sensor is None:
        return
    from calibration.calset import SensorGeometry

    now = SensorGeometry.of_rig(rig)
    check_calibration_fits(calibration, layout=now.layout, readout=now.area,
                           sensor_size=now.sensor_size, what="this camera")


def session_frame_geometry(session: Session) -> tuple[str | None, tuple[int, int, int, int] | None,
                                                      tuple[int, int] | None]:
    """``(layout, readout, sensor_size)`` of a session's frames, from its manifest
    (``rig.camera_frames``, else its first raw frame; the simulated sensor's size from
    ``rig.sim_parameters``); ``None`` where it does not say."""
    rig = session.manifest.get("rig") or {}
    frames = rig.get("camera_frames")
    if not isinstance(frames, dict):  # a session older than rig.camera_frames
        from polrig.capture import _recorded_camera_frames

        frames = _recorded_camera_frames(session) or {}
    layout = frames.get("layout")
    readout = None
    try:
        off = frames.get("offset_xy") or [0, 0]
        readout = (int(frames["width"]), int(frames["height"]), int(off[0]), int(off[1]))
    except (KeyError, TypeError, ValueError, IndexError):
        readout = None
    size = None
    sensor = ((rig.get("sim_parameters") or {}).get("sensor") or {}) \
        if rig.get("simulated") else {}
    try:
        h, w = sensor["shape"]
        size = (int(w), int(h))
    except (KeyError, TypeError, ValueError):
        size = None
    return (str(layout) if layout else None), readout, size


def single_shot_geometry(calibration: Calibration, rig_config: dict[str, Any] | None,
                         sensor_size: tuple[int, int] | None = None) -> dict[str, Any]:
    """Intrinsics (full-sensor pixels) and stage zero axis (camera frame) for single-shot
    reconstruction: the calibration set's where it has them, else the rig's nominal geometry
    (:func:`polrig.rig.nominal_geometry`: the ``[nominal_geometry]`` table of the rig config, or the
    simulator's design values for a simulated camera). ``None`` values mean "unknown": the
    model then uses its training geometry (``models/weights/model.json``). ``sources`` says
    where each value came from."""
    from polrig.rig import nominal_geometry

    nominal = nominal_geometry(rig_config, sensor_size)
    out: dict[str, Any] = {"sources": {}}
    for key in ("intrinsics", "stage_zero_axis_camera"):
        cal_value = getattr(calibration, key)
        if cal_value is not None:
            out[key], out["sources"][key] = tuple(cal_value), f"calibration {calibration.id}"
        elif nominal[key] is not None:
            out[key], out["sources"][key] = tuple(nominal[key]), nominal["source"]
        else:
            out[key], out["sources"][key] = None, "model training geometry"
    return out


def analyzer_grid_intrinsics(intrinsics: Sequence[float], offset_xy: Sequence[int],
                             raw_shape: tuple[int, int], grid_shape: tuple[int, int]
                             ) -> tuple[float, float, float, float]:
    """Full-sensor pinhole intrinsics ``(fx, fy, cx, cy)`` carried to the demosaiced analyzer
    grid of a readout with ROI offset ``offset_xy`` (pixels) and raw size ``raw_shape``
    ``(H, W)``: the principal point moves by the offset, and a grid ``p`` times coarser (the
    ``superpixel`` demosaic of a ``p x p`` mosaic period) has its pixel ``j`` centred on raw
    ``p j + (p - 1) / 2``, so ``f' = f / p`` and ``c' = (c - offset - (p - 1) / 2) / p``.
    A full-resolution grid (``bilinear``, ``newton``) keeps ``f`` and ``c - offset``."""
    if min(grid_shape[:2]) < 1 or min(raw_shape[:2]) < 1:
        raise ValueError(f"raw mosaic {tuple(raw_shape)} gives an empty analyzer grid "
                         f"{tuple(grid_shape)}: it is smaller than one layout cell")
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    ox, oy = (float(v) for v in offset_xy)
    py = raw_shape[0] / float(grid_shape[0])
    px = raw_shape[1] / float(grid_shape[1])
    return (fx / px, fy / py, (cx - ox - (px - 1) / 2) / px, (cy - oy - (py - 1) / 2) / py)


def single_shot_kwargs(geometry: dict[str, Any], frame: Frame, method: str = "superpixel"
                       ) -> dict[str, Any]:
    """``stage_zero_axis`` and ``intrinsics`` keyword arguments of
    :meth:`models.runtime.SingleShotModel.reconstruct` / :func:`models.runtime.infer_frame` for
    one raw ``frame`` demosaiced with ``method``, from :func:`single_shot_geometry` (the
    intrinsics carried to the analyzer grid by :func:`analyzer_grid_intrinsics`). The GUI's
    live single-shot view and ``polrig infer`` can pass these as processing does."""
    from polrig.demosaic import output_shape

    lay = frame_layout(frame)
    raw_shape = tuple(frame.raw.shape[-2:])
    ph, pw = lay.period
    if raw_shape[0] < ph or raw_shape[1] < pw:  # the demosaic's own one-line refusal
        raise ValueError(f"raw mosaic {raw_shape} is smaller than one {ph}x{pw} layout cell")
    intrinsics = geometry.get("intrinsics")
    if intrinsics is not None:
        intrinsics = analyzer_grid_intrinsics(intrinsics, frame.meta.offset_xy, raw_shape,
                                              output_shape(lay, raw_shape, method))
    return {"stage_zero_axis": geometry.get("stage_zero_axis_camera"), "intrinsics": intrinsics}


def check_plan(plan, calibration: Calibration) -> float | None:
    """Reject a plan that cannot give a result, before any device moves.

    Reference mode: the incident states must determine the Mueller block (at least 3, not
    collinear, condition number below :data:`polrig.reference.DEFAULT_MAX_CONDITION`);
    returns the condition number. Single-shot: a model must be installed.
    """
    if plan.mode == "single-shot":
        single_shot_model()
        return None
    try:
        return validate_states(calibration.incident_stokes(plan.states_deg))
    except ConfigError as exc:
        states = ",".join(f"{a:g}" for a in plan.states_deg)
        raise ConfigError(f"--states {states}: {exc}") from None


def single_shot_model():
    """The installed single-shot model; :class:`ConfigError` (one line) when there is none."""
    try:
        from models.runtime import SingleShotModel  # type: ignore[import-not-found]
    except ImportError:
        raise ConfigError("--mode single-shot: no single-shot model is installed (models.runtime "
                          "is missing); use --mode reference") from None
    try:
        return SingleShotModel.load()
    except (FileNotFoundError, OSError, FormatError) as exc:
        raise ConfigError(f"--mode single-shot: no single-shot model is installed ({exc}); "
                          f"use --mode reference") from None


# -- sensor model ------------------------------------------------------------------------------
def sensor_model_of(rig) -> SensorModel:
    """The noise model of the rig's camera: the simulated rig's own, else the configured one
    (the ``[sensor_model]`` table of the rig config), else the IMX250 defaults."""
    truth = getattr(rig, "truth", None)
    if truth is not None:
        try:
            fields = truth.rig_parameters()["sensor"]["sensor_model"]
            return SensorModel(**fields)
        except (KeyError, TypeError):
            pass
    cfg = getattr(rig, "config", None)
    sm = cfg.get("sensor_model") if isinstance(cfg, dict) else None
    if isinstance(sm, SensorModel):
        return sm
    if isinstance(sm, dict):
        return SensorModel(**sm)
    return SensorModel()


# -- session level -------------------------------------------------------------------------------
def _exr_bytes(writer: Callable[[pathlib.Path], Any]) -> bytes:
    """Bytes of an EXR written by ``writer(path)`` to a scratch folder (the session then writes
    them atomically, checksummed, under their final name)."""
    with tempfile.TemporaryDirectory(prefix="polrig-exr-") as d:
        p = pathlib.Path(d) / "image.exr"
        writer(p)
        return p.read_bytes()


def read_verified_frame(session: Session, record: dict[str, Any]) -> Frame:
    """Read one recorded raw frame after checking its (and its sidecar's) SHA-256."""
    for key, digest in (("path", "sha256"), ("meta_path", "meta_sha256")):
        if key not in record:
            continue
        path = session.root / record[key]
        if not path.is_file():
            raise FileNotFoundError(f"{path}: raw file of the session is missing")
        if sha256_file(path) != record[digest]:
            raise FormatError(f"{path}: SHA-256 does not match the session manifest (changed "
                              f"or corrupt raw data)")
    return read_raw(session.root / record["path"])


@dataclasses.dataclass
class CaptureFrames:
    """Raw frames of one capture grouped for processing."""

    states_deg: list[float]
    exposures_us: list[float]
    frames: list[list[list[Frame]]]  # [state][exposure][k]
    darks: list[list[Frame]]  # [exposure][k]

    @property
    def first(self) -> Frame:
        return self.frames[0][0][0]


def load_capture_frames(session: Session, index: int) -> CaptureFrames:
    """Every raw and dark frame of capture ``index``, checksums verified."""
    files = session.capture(index)["files"]
    raw = files.get("raw", [])
    if not raw:
        raise FormatError(f"capture {index} of {session.root} has no raw frames")
    n_states = 1 + max(r["state_index"] for r in raw)
    n_exp = 1 + max(r["exposure_index"] for r in raw)
    states = [0.0] * n_states
    exposures = [0.0] * n_exp
    frames: list[list[list[tuple[int, Frame]]]] = [[[] for _ in range(n_exp)]
                                                   for _ in range(n_states)]
    for r in raw:
        states[r["state_index"]] = float(r["state_deg"])
        exposures[r["exposure_index"]] = float(r["exposure_us"])
        frames[r["state_index"]][r["exposure_index"]].append((r["frame"],
                                                              read_verified_frame(session, r)))
    darks: list[list[tuple[int, Frame]]] = [[] for _ in range(n_exp)]
    for r in files.get("dark", []):
        darks[r["exposure_index"]].append((r["frame"], read_verified_frame(session, r)))
    for j, per_state in enumerate(frames):
        for e, lst in enumerate(per_state):
            if not lst:
                raise FormatError(f"capture {index}: no frames of state {j} at exposure {e}")
    srt = lambda lst: [f for _, f in sorted(lst, key=lambda t: t[0])]  # noqa: E731
    return CaptureFrames(states, exposures, [[srt(l) for l in s] for s in frames],
                         [srt(l) for l in darks])


def frame_layout(frame: Frame) -> MosaicLayout:
    """Mosaic layout of a frame, phase from its ROI offset."""
    from polrig.analyzer import layout_name_at

    ox, oy = frame.meta.offset_xy
    return resolve_layout(layout_name_at(frame.meta.layout, ox, oy))


def process_reference(cf: CaptureFrames, calibration: Calibration, model: SensorModel,
                      method: str
                      ) -> tuple[ReferenceResult, np.ndarray, MosaicLayout, list[StateRadiance]]:
    """Reference solve of one capture's frames: ``(result, s_in, layout, states)``."""
    first = cf.first
    lay = frame_layout(first)
    scale = adc_scale(model, first.meta.bit_depth)
    adc = lambda f: f.raw.astype(np.float64) * scale if scale != 1 else f.raw  # noqa: E731
    black = float(first.meta.black_level_dn) * scale
    have_darks = any(len(d) for d in cf.darks)
    states = []
    for per_state in cf.frames:
        states.append(state_radiance(
            [[adc(f) for f in lst] for lst in per_state], cf.exposures_us, model,
            black_level_dn=black,
            darks=[[adc(f) for f in d] for d in cf.darks] if have_darks else None))
    analyzer = calibration.analyzer
    if analyzer is not None:  # the frame's readout within the calibrated area
        h, w = first.raw.shape
        ax, ay = calibration.area_offset
        ox, oy = first.meta.offset_xy
        if analyzer.shape != (h, w) or (calibration.sensor is not None and (ox, oy) != (ax, ay)):
            analyzer = analyzer.crop(ox - ax, oy - ay, w, h)
    s_in = calibration.incident_stokes(cf.states_deg)
    result = reference_from_frames(states, s_in, lay, method, analyzer,
                                   analyzer_tolerance=calibration.analyzer_tolerance,
                                   generator_tolerance=calibration.generator_tolerance)
    return result, s_in, lay, states


class Processor:
    """Processing of captures inside a session (see :func:`polrig.capture.run_session`).

    ``mode``/``demosaic`` as in the plan; ``sensor_model`` the camera's noise model;
    ``mirror_average``: single-shot runs the network on the capture and on its mirror image and
    averages (:mod:`models.mirror`; twice the network time, a few per cent lower error).
    """

    def __init__(self, mode: str, demosaic: str, calibration: Calibration,
                 sensor_model: SensorModel, mirror_average: bool = False):
        if mode not in ("reference", "single-shot"):
            raise ConfigError(f"unknown mode {mode!r}; use reference or single-shot")
        if mirror_average and mode != "single-shot":
            raise ConfigError("--mirror-average applies to --mode single-shot only")
        # single-shot: the installed network, or the one-line "no model installed" error
        self.model = single_shot_model() if mode == "single-shot" else None
        self.mode = mode
        self.demosaic = demosaic
        self.mirror_average = bool(mirror_average)
        self.calibration = calibration
        self.sensor_model = sensor_model

    # called by run_session while the rig is still at the pose
    def after_acquire(self, session: Session, index: int, rig) -> None:
        truth = getattr(rig, "truth", None)
        if truth is None:
            return
        gt = truth.ground_truth()
        cap = session.capture(index)
        planes = {"object_mask": np.asarray(gt["mask"], np.float32)}
        meta = {"source": "polrig simulated rig ground truth", "pose_deg": cap["pose_deg"],
                "units": "DN per unit incident S0 (docs/conventions.md)",
                "exposure_us": gt.get("exposure_us"), "gain_db": gt.get("gain_db")}
        from polrig.exr import write_mueller_exr

        data = _exr_bytes(lambda p: write_mueller_exr(p, gt["mueller"], extra=planes,
                                                      metadata=meta))
        session.add_file(index, "truth_mueller", f"{cap['name']}/truth_mueller.exr", data)

    def process(self, session: Session, index: int, revision: str | None = None
                ) -> dict[str, Any] | None:
        """Solve capture ``index`` from its raw files; write the result files (into
        ``revision`` if given); return the score against the truth (simulated rig) or None."""
        from polrig import __version__
        from polrig.exr import colour_planes, element_planes, write_mueller_exr

        cap = session.capture(index)
        cf = load_capture_frames(session, index)
        truth_path = self._verified_truth(session, index)  # damaged truth: refused up front
        geometry = None
        if self.mode == "single-shot":
            rig_info = session.manifest.get("rig", {}) or {}
            config = rig_info.get("config")
            size = ((config or {}).get("sim") or {}).get("size")
            geometry = single_shot_geometry(
                self.calibration, config,
                None if size is not None else (cf.first.raw.shape[1], cf.first.raw.shape[0]))
            result, s_in, lay, states = self.single_shot(cf, geometry)
        else:
            result, s_in, lay, states = process_reference(cf, self.calibration,
                                                          self.sensor_model, self.demosaic)
        extra = element_planes("sigma", result.sigma) | element_planes("sigma_noise", result.sigma_noise)
        extra.update(colour_planes("mask", result.mask.astype(np.float32)))
        extra.update(colour_planes("residual", result.residual))
        meta = {
            "calibration_id": self.calibration.id, "mode": self.mode, "demosaic": self.demosaic,
            "pose_deg": cap["pose_deg"], "states_deg": cf.states_deg,
            "incident_state": np.asarray(s_in).tolist(),
            "exposure_us": cf.exposures_us[0], "exposures_us": cf.exposures_us,
            "frames_per_state": len(cf.frames[0][0]), "dark_frames": len(cf.darks[0]),
            "layout": lay.name, "condition_number": result.condition_number,
            "units": "DN per unit incident S0 at exposure_us (docs/conventions.md)",
            "mask_bits": {str(b): n for b, n in reason_names().items()},
            "analyzer_tolerance": list(self.calibration.analyzer_tolerance),
            "generator_tolerance": list(self.calibration.generator_tolerance),
            "planes": {"sigma.M{rc}": ("standard deviation of M{rc}: sensor noise and "
                                       "calibration uncertainty" if self.mode == "reference" else
                                       "standard deviation of M{rc}: the single-shot model's "
                                       "calibrated error (models/uncertainty.py); inf where clipped"),
                       "sigma_noise.M{rc}": "standard deviation of M{rc} from the sensor "
                                            "noise model alone",
                       "mask": "reason bits, 0 = valid", "residual": "chi^2 per dof"},
            "software": f"polrig {__version__}", "capture": cap["name"],
            "revision": revision or "capture",
        }
        if geometry is not None:
            meta["single_shot_geometry"] = {
                "intrinsics_full_sensor": geometry["intrinsics"],
                "stage_zero_axis_camera": geometry["stage_zero_axis_camera"],
                "sources": geometry["sources"]}
            meta["mirror_average"] = self.mirror_average
        data = _exr_bytes(lambda p: write_mueller_exr(p, result.mueller, extra=extra,
                                                      metadata=meta))
        folder = cap["name"] if revision is None else f"{cap['name']}/{revision}"
        rec = session.add_file(index, "mueller", f"{folder}/mueller.exr", data,
                               revision=revision)
        files = cap["files"] if revision is None else cap["revisions"][revision]["files"]
        files["uncertainty"] = {"part_of": "mueller", "path": rec["path"],
                                "channels": "sigma.M{row}{col}.{colour}, "
                                            "sigma_noise.M{row}{col}.{colour}, "
                                            "residual.{colour}"}
        files["mask"] = {"part_of": "mueller", "path": rec["path"],
                         "channels": "mask.{colour} (reason bits, 0 = valid)"}
        score = self.score(session, index, result, lay, s_in,
                           states if self.mode == "reference" else None, cf.exposures_us[0],
                           truth_path=truth_path)
        if revision is not None:
            cap["revisions"][revision].update(status=COMPLETE, score=score)
        session.save()
        return score

    def single_shot(self, cf: CaptureFrames, geometry: dict[str, Any] | None = None
                    ) -> tuple[ReferenceResult, np.ndarray, MosaicLayout, None]:
        """One state through the installed network (:mod:`models.runtime`): averaged and
        HDR-merged like the reference states, demosaiced, reconstructed. ``sigma`` is the
        model's calibrated uncertainty (:mod:`models.uncertainty`: the network's error
        against the simulator's truth, which sensor noise does not describe; 0 where the graph
        has no calibration), infinite for a colour with a clipped sample (the magnitude of a
        clipped highlight is unknown); ``sigma_noise`` is 0. The mask marks, as the reference solve does,
        ``dark`` pixels: background (outside the network's object mask) and, per colour, pixels
        whose measured ``S0`` is below :data:`polrig.reference.MIN_SNR` noise standard
        deviations (the noise model's variance carried through the demosaic; an object turned
        away from the light is all noise, and the network's relative object mask cannot tell);
        and ``saturated`` pixels, of a colour with an excluded analyzer sample. The network's
        estimate is kept in both.

        ``geometry`` (:func:`single_shot_geometry`; default: from the calibration alone): the
        intrinsics, carried to the analyzer grid (:func:`analyzer_grid_intrinsics`), and the
        stage zero axis the incident state is expressed about; without them the model assumes
        its training rig's, which on another rig puts the result in the wrong incident frame."""
        from polrig.reference import DARK, MIN_SNR, SATURATED

        first = cf.first
        lay = frame_layout(first)
        scale = adc_scale(self.sensor_model, first.meta.bit_depth)
        adc = lambda f: f.raw.astype(np.float64) * scale  # noqa: E731
        state = state_radiance([[adc(f) for f in lst] for lst in cf.frames[0]],
                               cf.exposures_us, self.sensor_model,
                               black_level_dn=float(first.meta.black_level_dn) * scale,
                               darks=[[adc(f) for f in d] for d in cf.darks]
                               if any(len(d) for d in cf.darks) else None)
        measured, variance, valid, _ = analyzer_stack(state, lay, self.demosaic)
        s_in = self.calibration.incident_stokes(cf.states_deg[:1])
        if geometry is None:  # the calibration's geometry only
            geometry = {"intrinsics": self.calibration.intrinsics,
                        "stage_zero_axis_camera": self.calibration.stage_zero_axis_camera}
        mueller, aux = self.model.reconstruct(np.where(valid, measured, np.nan), s_in[0], with_sigma=True,
                                              mirror_average=self.mirror_average,
                                              **single_shot_kwargs(geometry, first, self.demosaic))
        obj = np.asarray(aux["mask"], bool)
        c, h, w = mueller.shape[0], mueller.shape[-2], mueller.shape[-1]
        s0, s0_sigma = 0.5 * measured.sum(axis=1), 0.5 * np.sqrt(variance.sum(axis=1))  # (C, H, W)
        with np.errstate(invalid="ignore"):
            dark = ~obj[None] | ~(s0 >= MIN_SNR * s0_sigma)
        clipped = ~np.all(valid, axis=1) & obj[None]  # (C, H, W)
        mask = (np.where(dark, DARK, 0) | np.where(clipped, SATURATED, 0)).astype(np.uint8)
        zeros = np.zeros((c, h, w), np.float32)
        sigma = np.asarray(aux.get("sigma", np.zeros_like(mueller)), np.float32)
        sigma = np.where(clipped[:, None, None], np.float32(np.inf), sigma)
        result = ReferenceResult(mueller.astype(np.float32), sigma, zeros, mask, float("nan"),
                                 zeros + np.inf, np.zeros((c, h, w), np.uint16),
                                 sigma_noise=np.zeros_like(sigma))
        return result, s_in, lay, None

    @staticmethod
    def _verified_truth(session: Session, index: int) -> pathlib.Path | None:
        """The capture's truth EXR (simulated rig) after checking its SHA-256, or None
        without one; a missing or changed file is a one-line error naming it."""
        rec = session.capture(index)["files"].get("truth_mueller")
        if rec is None:
            return None
        path = session.root / rec["path"]
        if not path.is_file():
            raise FileNotFoundError(f"{path}: truth file of the session is missing")
        if sha256_file(path) != rec["sha256"]:
            raise FormatError(f"{path}: SHA-256 does not match the session manifest (changed "
                              f"or corrupt truth file)")
        return path

    def score(self, session: Session, index: int, result: ReferenceResult,
              layout: MosaicLayout, s_in: np.ndarray,
              states: Sequence[StateRadiance] | None, exposure_us: float,
              truth_path: pathlib.Path | None = None) -> dict[str, Any] | None:
        """Score against the capture's truth file (simulated rig), or None without one.
        ``truth_path``: the truth file already verified by the caller."""
        from polrig.exr import read_mueller_exr

        path = truth_path or self._verified_truth(session, index)
        if path is None:
            return None
        img = read_mueller_exr(path)
        if states is None:  # single-shot: the truth at this resolution, nominal 4-state weights
            t = truth_on_output_grid(img.mueller, layout, self.demosaic,
                                     polarizer_stokes(np.deg2rad([0, 45, 90, 135]), intensity=1),
                                     model=self.sensor_model, exposure_us=exposure_us)
        else:
            t = truth_on_output_grid(img.mueller, layout, self.demosaic, s_in, states)
        obj = img.extra.get("object_mask")
        if obj is not None:  # output pixels whose whole support lies on the object
            support = demosaic_float(np.asarray(obj, np.float32), layout, self.demosaic)
            obj = support.min(axis=(0, 1)) >= 1.0
        return score_against_truth(result, t, obj)


def make_processor(plan, calibration: Calibration, sensor_model: SensorModel) -> Processor:
    return Processor(plan.mode, plan.demosaic, calibration, sensor_model, plan.mirror_average)


def session_sensor_model(session: Session) -> SensorModel:
    """The noise model recorded in a session's manifest (IMX250 defaults if none)."""
    fields = session.manifest.get("rig", {}).get("sensor_model")
    return SensorModel(**fields) if fields else SensorModel()


class ReconstructIncomplete(PolrigError):
    """Some captures of a :func:`reprocess_session` revision failed (damaged or missing
    files); the others were processed. ``revision`` names it, ``failed`` lists
    ``(capture index, reason)``."""

    def __init__(self, session: Session, revision: str, failed: list[tuple[int, str]],
                 attempted: int):
        self.revision, self.failed = revision, failed
        names = "; ".join(f"capture {i} ({session.capture(i)['name']}): {reason}"
                          for i, reason in failed)
        others = "" if len(failed) == attempted else ", the others are complete"
        super().__init__(f"revision {revision}: {len(failed)} of {attempted} capture(s) "
                         f"failed{others}: {names}")


def reprocess_session(session: Session, *, mode: str | None = None, demosaic: str | None = None,
                      mirror_average: bool | None = None, calibration: Calibration | None = None,
                      command_line: list[str] | None = None,
                      progress: Callable[[int, dict[str, Any] | None], None] | None = None,
                      on_failed: Callable[[int, str], None] | None = None) -> str:
    """Re-process every complete capture from its raw frames into a new revision (raw data
    and earlier results untouched). Returns the revision name.

    A capture that cannot be processed (a raw frame missing or changed, a damaged truth file)
    is marked ``failed`` in the revision with its reason (``on_failed(index, reason)`` is
    called) and the others are processed; at the end :class:`ReconstructIncomplete` names
    the failed captures. A full disk stops the revision (the capture is marked failed, the
    error raised). The session's lock is held while it runs (:class:`SessionBusy` if another
    process writes the session; the manifest is re-read under it); SIGINT/SIGTERM leave the
    capture in progress ``pending`` in the revision and raise ``KeyboardInterrupt``."""
    was_locked = session.locked
    session.lock()
    try:
        if not was_locked:
            session.reload()  # under the lock: the manifest no other writer changes any more
        return _reprocess(session, mode, demosaic, mirror_average, calibration, command_line,
                          progress, on_failed)
    finally:
        if not was_locked:
            session.unlock()


def _reprocess(session: Session, mode, demosaic, mirror_average, calibration, command_line,
               progress, on_failed) -> str:
    from polrig.session import is_disk_full

    plan = session.plan
    mode = mode or plan["mode"]
    demosaic = demosaic or plan.get("demosaic", "superpixel")
    if mirror_average is None:  # the session's choice where it was single-shot already
        mirror_average = bool(plan.get("mirror_average", False)) and mode == "single-shot"
    calibration = calibration or nominal_calibration()
    if calibration.sensor is not None:  # before a revision exists: nothing recorded
        layout, readout, size = session_frame_geometry(session)
        check_calibration_fits(calibration, layout=layout, readout=readout, sensor_size=size,
                               what=f"the camera of session {session.root}")
    processor = Processor(mode, demosaic, calibration, session_sensor_model(session), mirror_average)
    done = [c["index"] for c in session.captures if c["status"] == COMPLETE]
    if not done:
        raise ConfigError(f"{session.root}: no complete capture to reconstruct")
    if mode == "reference":  # before a revision exists: an impossible request records nothing
        from polrig.capture import CapturePlan

        acquired = CapturePlan.from_json(plan).acquired_states_deg()
        if len(acquired) < 3:
            raise ConfigError(f"{session.root}: captured in {plan['mode']} mode, {len(acquired)} polarizer "
                              f"state per pose; the reference method needs at least 3 (reconstruct "
                              f"with --mode single-shot, or capture again with --mode reference)")
        validate_states(calibration.incident_stokes(acquired))
    failed: list[tuple[int, str]] = []
    with SignalGuard() as guard:
        name = session.new_revision({"mode": mode, "demosaic": demosaic,
                                     "mirror_average": mirror_average,
                                     "calibration_id": calibration.id}, command_line)
        for index in done:
            session.start_revision(index, name)
            try:
                score = processor.process(session, index, revision=name)
            except Exception as exc:  # this capture's data: record why, go on with the others
                reason = f"{type(exc).__name__}: {exc}"
                with guard.deferred():
                    _mark_revision(session, index, name, FAILED, reason)
                if is_disk_full(exc):
                    raise
                failed.append((index, reason))
                if on_failed:
                    on_failed(index, reason)
                continue
            except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM
                with guard.deferred():
                    _mark_revision(session, index, name, PENDING, interruption_reason(exc))
                raise
            if progress:
                progress(index, score)
    if failed:
        raise ReconstructIncomplete(session, name, failed, len(done))
    return name


def _mark_revision(session: Session, index: int, revision: str, status: str,
                   reason: str) -> None:
    """Set capture ``index``'s entry of ``revision`` to ``status`` with ``reason`` and save
    (best effort). Files it wrote stay recorded: each was written completely and checksummed.
    The manifest on disk is what counts (after a failed save it is the consistent one)."""
    with contextlib.suppress(OSError, FormatError):
        session.reload()
    entry = session.capture(index).setdefault("revisions", {}).setdefault(
        revision, {"status": PENDING, "files": {}, "score": None})
    entry.update(status=status, reason=reason)
    with contextlib.suppress(OSError):
        session.save()
