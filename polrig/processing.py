"""Turn a capture's raw frames into Mueller images (with uncertainty and mask), and score them.

Array level (pure functions, ``docs/conventions.md`` layouts and units):

* :func:`state_radiance` -- K frames (and an exposure bracket) of one polarizer state ->
  black/dark-subtracted mean mosaic in DN at the reference exposure, its variance from the
  sensor noise model, and the samples to exclude (saturated).
* :func:`analyzer_stack` -- demosaic mosaics, variances and exclusions into analyzer images
  ``(C, 4, H', W')``.
* :func:`reference_from_frames` -- all states -> :class:`polrig.reference.ReferenceResult`.
* :func:`score_against_truth` -- error of a result against a truth Mueller image.

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
import math
import os
import pathlib
import tempfile
from typing import Any, Callable, Sequence

import numpy as np

from polrig.analyzer import AnalyzerModel, resolve_layout
from polrig.demosaic import class_positions, demosaic_float
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.hal import Frame
from polrig.layouts import MosaicLayout
from polrig.mueller import polarizer_stokes
from polrig.noise import SensorModel
from polrig.rawio import read_raw
from polrig.reference import (ReferenceResult, reason_names, solve_reference,
                              validate_states, merge_hdr)
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


def adc_scale(model: SensorModel, bit_depth: int) -> float:
    """Factor from the DN of frames delivered with ``bit_depth`` bits to the DN of the ADC the
    noise model describes (a 12-bit ADC read out as Mono16 delivers values times 16: the
    factor is 1/16). Results are always in ADC DN, whatever the pixel format."""
    return 2.0 ** (int(model.bit_depth) - int(bit_depth))


# -- array level -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class StateRadiance:
    """One state's mosaic ``(H, W)``: ``signal_dn`` (black/dark-subtracted, at the reference
    exposure), ``variance_dn2`` and ``excluded`` (bool, saturated in every exposure)."""

    signal_dn: np.ndarray
    variance_dn2: np.ndarray
    excluded: np.ndarray


def state_radiance(brackets: Sequence[Sequence[np.ndarray]], exposures_us: Sequence[float],
                   model: SensorModel, *, black_level_dn: float = 0.0,
                   darks: Sequence[Sequence[np.ndarray]] | None = None) -> StateRadiance:
    """Mean black-subtracted mosaic of one polarizer state.

    ``brackets[e]``: the K raw frames ``(H, W)`` taken at ``exposures_us[e]``; ``darks[e]``:
    dark frames at that exposure (light off) or ``None``/empty (subtract ``black_level_dn``
    only). A sample is excluded when any of its frames reaches the saturation level
    (``black + model.saturation_dn``); several exposures are merged by
    :func:`polrig.reference.merge_hdr` at ``exposures_us[0]`` (the reference exposure).
    """
    if len(brackets) != len(exposures_us) or not brackets:
        raise ValueError("one list of frames per exposure is needed")
    sat_raw = black_level_dn + model.saturation_dn
    means, variances, sats = [], [], []
    for e, frames in enumerate(brackets):
        f = np.asarray(frames, dtype=np.float64)
        k = f.shape[0]
        mean = f.mean(axis=0)
        sat = (f >= sat_raw).any(axis=0)
        dark_list = darks[e] if darks else None
        if dark_list is not None and len(dark_list):
            d = np.asarray(dark_list, dtype=np.float64)
            offset = d.mean(axis=0)
            dark_var = model.variance_dn2(0.0, exposures_us[e], d.shape[0])
            signal = mean - offset
            # the dark mean already holds the mean dark signal: the photo-signal is what is left
            var = model.variance_dn2(signal, exposures_us[e], k) + dark_var
        else:
            dark_dn = model.dark_electrons(exposures_us[e]) / model.gain_e_per_dn
            signal = mean - black_level_dn - dark_dn
            var = model.variance_dn2(signal, exposures_us[e], k)
        means.append(signal)
        variances.append(var)
        sats.append(sat)
    if len(brackets) == 1:
        return StateRadiance(means[0], variances[0], sats[0])
    # merge_hdr excludes samples >= saturation_dn: mark the saturated ones that way
    marked = [np.where(s, np.inf, m) for m, s in zip(means, sats)]
    radiance, variance, valid = merge_hdr(list(zip(marked, exposures_us)), model.saturation_dn,
                                          model, reference_exposure_us=exposures_us[0],
                                          n_frames=len(brackets[0]))
    return StateRadiance(radiance, variance, ~valid)


def analyzer_stack(state: StateRadiance, layout: MosaicLayout, method: str,
                   analyzer: AnalyzerModel | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Demosaic one state: ``(measured, variance, valid, rows)``, the first three
    ``(C, 4, H', W')`` and ``rows`` ``(C, 4, 3, H', W')`` (``None`` for the ideal analyzer).

    A calibrated ``analyzer`` (of this readout) has its offsets removed from the signal and its
    per-pixel rows carried to the output grid by the same demosaic.
    """
    signal = np.asarray(state.signal_dn, dtype=np.float64)
    rows = None
    if analyzer is not None:
        if analyzer.shape != signal.shape:
            raise ValueError(f"analyzer model {analyzer.shape} does not match frames "
                             f"{signal.shape}")
        signal = signal - analyzer.offset_dn
        r = analyzer.rows()
        rows = np.stack([demosaic_float(r[..., i].astype(np.float32), layout, method)
                         for i in range(3)], axis=2)
    measured = demosaic_float(signal.astype(np.float32), layout, method)
    variance = demosaic_float(np.asarray(state.variance_dn2, np.float32), layout, method)
    if method == "superpixel":
        counts = np.zeros((layout.n_colours, 4), np.float32)
        for (c, k), pos in class_positions(layout).items():
            counts[c, k] = len(pos)
        variance = variance / counts[:, :, None, None]
    bad = demosaic_float(state.excluded.astype(np.float32), layout, method)
    valid = ~(bad > 0)
    return measured, variance, valid, rows


def reference_from_frames(states: Sequence[StateRadiance], s_in: np.ndarray,
                          layout: str | MosaicLayout, method: str = "superpixel",
                          analyzer: AnalyzerModel | None = None, *,
                          analyzer_tolerance: Sequence[float] | None = None,
                          generator_tolerance: Sequence[float] | None = None
                          ) -> ReferenceResult:
    """The reference solve of all states (see :func:`polrig.reference.solve_reference`;
    the tolerances are the calibration's, :class:`Calibration`)."""
    lay = resolve_layout(layout)
    parts = [analyzer_stack(s, lay, method, analyzer) for s in states]
    measured = np.stack([p[0] for p in parts])
    variance = np.stack([p[1] for p in parts])
    valid = np.stack([p[2] for p in parts])
    rows = parts[0][3]
    return solve_reference(s_in, measured, variance, valid, rows,
                           analyzer_tolerance=analyzer_tolerance,
                           generator_tolerance=generator_tolerance)


# -- truth and score ---------------------------------------------------------------------------
def truth_on_output_grid(truth_mueller: np.ndarray, layout: MosaicLayout, method: str,
                         s_in: np.ndarray, weights_like: Sequence[StateRadiance] | None = None,
                         model: SensorModel | None = None, exposure_us: float | None = None
                         ) -> np.ndarray:
    """The truth as a perfect rig at this resolution measures it: the noise-free estimate
    from the per-pixel truth Mueller image ``(C, 3, 3, H, W)`` (each sensor pixel sees its own
    pixel's matrix, ideal analyzers, incident states ``s_in``), demosaiced with ``method`` and
    solved exactly as a capture is processed. Returns ``(C, 3, 3, H', W')``.

    The weights matter where the truth varies inside a pixel's support (the estimate mixes
    the matrices of the pixels it draws on): ``weights_like`` (the capture's own states) gives
    the sample variances and exclusions to use, so that the result is the expectation of that
    capture's estimator; without it the noise model's variance of the noise-free signal at
    ``exposure_us`` is used. Where the truth is uniform over a pixel's support the result is
    the truth itself, whatever the weights.
    """
    t = np.asarray(truth_mueller, dtype=np.float64)
    h, w = t.shape[-2:]
    ideal = AnalyzerModel.ideal(layout, (h, w))
    states = []
    for k, s in enumerate(np.asarray(s_in, dtype=np.float64)):
        mosaic = ideal.mosaic(np.einsum("cijhw,j->cihw", t, s))
        if weights_like is not None:
            like = weights_like[k]
            states.append(StateRadiance(mosaic, like.variance_dn2, like.excluded))
        else:
            if model is None or exposure_us is None:
                raise ValueError("give weights_like, or model and exposure_us")
            states.append(StateRadiance(mosaic, model.variance_dn2(mosaic, exposure_us),
                                        np.zeros(mosaic.shape, bool)))
    return reference_from_frames(states, s_in, layout, method).mueller


def score_against_truth(result: ReferenceResult, truth: np.ndarray,
                        object_mask: np.ndarray | None = None) -> dict[str, Any]:
    """Error of ``result`` against ``truth`` ``(C, 3, 3, H, W)`` on the same grid (normally
    :func:`truth_on_output_grid`) over the pixels valid in the result (mask 0) and inside
    ``object_mask`` ``(H, W)`` if given.

    ``rmse``/``mae`` (DN per unit S0) over the 9 elements; ``psnr_db`` = 20 log10(peak / rmse)
    with ``peak`` the largest truth ``m00`` compared (``|m_ij| <= m00`` for a physical matrix:
    the matrix PSNR in the units of the data; ``inf`` for an exact result, ``None`` where the
    truth is dark over every compared pixel, e.g. an object turned so that only its unlit back
    faces the camera: the PSNR has no peak then, and ``rmse`` still says how far from 0 the
    result is); ``within_2sigma``: fraction of elements with
    ``|error| <= 2 sigma`` (0.954 for Gaussian errors when sigma is right);
    ``chi2_per_element``: mean ``(error / sigma)^2`` (1 when sigma is right); ``mean_sigma``:
    root-mean-square reported sigma (noise and calibration), the predicted error (comparable with
    ``rmse``); ``realizable``: pass rate of the coherency test
    (:func:`polrig.realizability.is_physical_linear`) of the measured matrices.
    """
    from polrig.realizability import is_physical_linear

    m = np.asarray(result.mueller, np.float64)
    s = np.asarray(result.sigma, np.float64)
    t = np.asarray(truth, np.float64)
    if m.shape != t.shape:
        raise ValueError(f"result {m.shape} and truth {t.shape} differ in shape")
    use = result.valid.copy()
    if object_mask is not None:
        use &= np.asarray(object_mask, bool)[None]
    n = int(use.sum())
    out: dict[str, Any] = {"pixels_compared": n,
                           "pixels_valid": int(result.valid.sum()),
                           "pixels_total": int(result.valid.size),
                           "mask_counts": result.reason_counts(),
                           "condition_number": (float(result.condition_number)
                                                if math.isfinite(result.condition_number)
                                                else None)}
    keys = ("rmse", "mae", "psnr_db", "within_2sigma", "chi2_per_element", "mean_sigma",
            "peak_m00", "realizable")
    out.update({k: None for k in keys})
    if n == 0:
        return out
    err = (m - t).transpose(1, 2, 0, 3, 4)[:, :, use]  # (3, 3, n)
    sig = s.transpose(1, 2, 0, 3, 4)[:, :, use]
    peak = float(np.abs(t[:, 0, 0][use]).max())
    rmse = float(np.sqrt(np.mean(err**2)))
    pos = sig > 0
    mats = m.transpose(0, 3, 4, 1, 2)[use]  # (n, 3, 3)
    out.update(
        rmse=rmse, mae=float(np.mean(np.abs(err))),
        psnr_db=_psnr_db(peak, rmse),
        within_2sigma=float(np.mean(np.abs(err[pos]) <= 2 * sig[pos])) if pos.any() else None,
        chi2_per_element=float(np.mean((err[pos] / sig[pos]) ** 2)) if pos.any() else None,
        mean_sigma=float(np.sqrt(np.mean(sig**2))) if pos.any() else None, peak_m00=peak,
        realizable=float(np.mean(is_physical_linear(mats))))
    return out


def _psnr_db(peak: float, rmse: float) -> float | None:
    """``20 log10(peak / rmse)``; ``inf`` when ``rmse`` is 0, ``None`` when ``peak`` is 0."""
    if peak <= 0.0:
        return None
    return float(20 * math.log10(peak / rmse)) if rmse > 0 else float("inf")


def format_score(score: dict[str, Any]) -> str:
    """One line for a score dict (``polrig capture`` and ``polrig info``)."""
    if not score or score.get("rmse") is None:
        return "no pixels to score"
    psnr = score["psnr_db"]
    parts = [f"RMSE {score['rmse']:.4g}", f"MAE {score['mae']:.4g}",
             "PSNR n/a (dark truth)" if psnr is None else f"PSNR {psnr:.1f} dB" if math.isfinite(psnr) else "PSNR inf"]
    if score.get("mean_sigma") is not None:
        parts.append(f"mean sigma {score['mean_sigma']:.4g}")
    if score.get("within_2sigma") is not None:
        parts.append(f"{100 * score['within_2sigma']:.1f}% within 2 sigma")
    parts.append(f"realizable {100 * score['realizable']:.1f}%")
    parts.append(f"{score['pixels_compared']} px")
    return ", ".join(parts)


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


@dataclasses.dataclass(frozen=True)
class CaptureResult:
    """One capture solved by :meth:`Processor.solve`: ``relpath`` (inside the session,
    ``<capture>/mueller.exr`` or ``<capture>/<revision>/mueller.exr``), ``data`` the EXR's
    bytes, ``score`` against the simulator's truth (``None`` without a truth file)."""

    relpath: str
    data: bytes
    score: dict[str, Any] | None


def record_result(session: Session, index: int, revision: str | None, record: dict[str, Any],
                  score: dict[str, Any] | None) -> None:
    """Record capture ``index``'s written ``mueller.exr`` (``record``: ``path``, ``sha256``,
    ``bytes``, as :meth:`Session.write_new_file` returns) with its ``uncertainty`` and ``mask``
    views, and in ``revision`` (if given) its score and status ``complete``; save the manifest.
    The one place a result enters a manifest: the serial :meth:`Processor.process` and the
    client of :mod:`polrig.cluster` (whose workers write the files) both call it."""
    cap = session.capture(index)
    files = cap["files"] if revision is None else cap["revisions"][revision]["files"]
    if "mueller" in files:
        raise FileExistsError(f"capture {index} already has a 'mueller' file")
    files["mueller"] = dict(record)
    files["uncertainty"] = {"part_of": "mueller", "path": record["path"],
                            "channels": "sigma.M{row}{col}.{colour}, "
                                        "sigma_noise.M{row}{col}.{colour}, "
                                        "residual.{colour}"}
    files["mask"] = {"part_of": "mueller", "path": record["path"],
                     "channels": "mask.{colour} (reason bits, 0 = valid)"}
    if revision is not None:
        cap["revisions"][revision].update(status=COMPLETE, score=score)
    session.save()


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
        ``revision`` if given); return the score against the truth (simulated rig) or None.
        :meth:`solve` and :func:`record_result`, with the file written in between."""
        out = self.solve(session, index, revision)
        rec = session.write_new_file(out.relpath, out.data)
        record_result(session, index, revision, rec, out.score)
        return out.score

    def solve(self, session: Session, index: int, revision: str | None = None
              ) -> "CaptureResult":
        """Capture ``index`` solved from its raw files (checksums verified), as the bytes of
        its ``mueller.exr`` (for ``revision`` if given) and its score; writes nothing, so a
        worker of :mod:`polrig.cluster` can run it on a session another process writes."""
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
        score = self.score(session, index, result, lay, s_in,
                           states if self.mode == "reference" else None, cf.exposures_us[0],
                           truth_path=truth_path)
        return CaptureResult(f"{folder}/mueller.exr", data, score)

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


def revision_plan(session: Session, mode: str | None, demosaic: str | None,
                  mirror_average: bool | None, calibration: Calibration | None
                  ) -> tuple[dict[str, Any], Processor, list[int]]:
    """What a new revision of ``session`` records and needs, checked before it exists (an
    impossible request records nothing): ``(settings, processor, captures)`` -- the
    revision's settings (``mode``, ``demosaic``, ``mirror_average``, ``calibration_id``;
    ``None`` arguments take the session's), its :class:`Processor` and the indices of the
    complete captures to process. Shared by :func:`reprocess_session` and
    :mod:`polrig.cluster`."""
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
    return ({"mode": mode, "demosaic": demosaic, "mirror_average": mirror_average,
             "calibration_id": calibration.id}, processor, done)


def _reprocess(session: Session, mode, demosaic, mirror_average, calibration, command_line,
               progress, on_failed) -> str:
    from polrig.session import is_disk_full

    settings, processor, done = revision_plan(session, mode, demosaic, mirror_average,
                                              calibration)
    failed: list[tuple[int, str]] = []
    with SignalGuard() as guard:
        name = session.new_revision(settings, command_line)
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
