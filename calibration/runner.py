"""Run calibration steps in order, record them in a :class:`CalibrationSet`, and score them
against a simulator's hidden truth when one is given.

Steps: ``intrinsics``, ``turntable``, ``light``, ``stokes`` (generator zero offset), ``dofp``
(analyzer model and the generator's extinction ratio); ``all`` runs them in that order. A step
reads what earlier steps stored in the set (``polrig calibrate light`` needs the intrinsics) and
raises :class:`CalibrationError` naming the missing step otherwise.

Which results a step's result was computed from is :data:`DEPENDS_ON` (the one place that
says it): when a step runs again on a set, the results of the steps that depend on it
(:func:`dependents`) are dropped from the set, with one log line, because they were computed
from the result it replaces. A step refuses a set calibrated on another camera readout
(:func:`check_set_fits_camera`) before it moves anything. Every step records the camera it
ran on in the set's ``camera`` section (:class:`polrig.calibration.calset.SensorGeometry`).

Truth (simulated rig only): a plain dict as :meth:`polrig.sim.truth.SimTruth.rig_parameters` returns
it, plus optionally the true per-pixel :class:`polrig.sensor.analyzer.AnalyzerModel`. Errors are
reported in the calibration's own frames (camera frame; the stage zero axis defined from the
calibrated turntable axis, :mod:`polrig.calibration.rigframes`): the hidden zero offset is converted
into that frame before comparing.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from polrig.acquisition.engine import CaptureControl, GuardedRig
from polrig.calibration import procedures as pr
from polrig.calibration import turntable as tt
from polrig.calibration.calset import CalibrationSet, SensorGeometry
from polrig.calibration.charuco import BoardSpec
from polrig.calibration.errors import CalibrationError
from polrig.calibration.mirror import (
    DEFAULT_MIRROR_METAL,
    DEFAULT_SPHERE_METAL,
    MirrorMetal,
)
from polrig.optics import bases as fr
from polrig.sensor.analyzer import AnalyzerModel

STEPS = ("intrinsics", "turntable", "light", "stokes", "dofp")
#: The steps that turn the polarizer stage (its angles are measured from its home).
STAGE_STEPS = ("light", "stokes", "dofp")

#: The steps whose results each step's result is computed from (where the set has them):
#: ``turntable`` refines the intrinsics (bundle adjustment), ``light`` uses the intrinsics
#: (as ``turntable`` left them), ``stokes`` the geometry (intrinsics, turntable axis, fixture
#: poses) and the light, ``dofp`` all of that and the generator's zero offset. Re-running a
#: step drops the results of every step that depends on it, directly or not
#: (:func:`dependents`). Which steps a step *needs* is separate: ``light`` needs only the
#: intrinsics, ``stokes`` and ``dofp`` need the turntable and light (and ``dofp`` the stokes
#: step); a missing one is named by :class:`CalibrationError`.
DEPENDS_ON: dict[str, tuple[str, ...]] = {
    "intrinsics": (),
    "turntable": ("intrinsics",),
    "light": ("intrinsics", "turntable"),
    "stokes": ("intrinsics", "turntable", "light"),
    "dofp": ("intrinsics", "turntable", "light", "stokes"),
}
#: The sections of ``calibration.json`` each step writes (``dofp`` also ``analyzer.npz``,
#: ``dofp_maps.npz`` and the generator's extinction ratio; ``turntable`` also refines the
#: ``intrinsics`` section).
STEP_SECTIONS: dict[str, tuple[str, ...]] = {
    "intrinsics": ("intrinsics",), "turntable": ("turntable", "fixtures"),
    "light": ("light",), "stokes": ("generator",), "dofp": ("dofp",)}
_N_RADIAL = {"none": 0, "k1": 1, "k1k2": 2, "full": 2}


@dataclasses.dataclass
class Options:
    """Targets and settings of a calibration run (defaults: the simulated targets)."""

    board: BoardSpec = dataclasses.field(default_factory=lambda: BoardSpec(8, 6, 0.025, 0.018))
    sphere_radius_m: float = 0.03
    #: the light calibration ball's metal (its colour, :func:`polrig.calibration.procedures.run_light`)
    sphere_metal: MirrorMetal = dataclasses.field(
        default_factory=lambda: MirrorMetal.named(DEFAULT_SPHERE_METAL))
    sensor_diattenuation: float = pr.DEFAULT_SENSOR_DIATTENUATION
    #: radial distortion model: "none", "k1" (default: the rig's lens covers about 25 deg, where
    #: k2 is not determined by the board views and only adds noise), "k1k2", "full"
    distortion: str = "k1"
    stage_angles_deg: tuple[float, ...] = pr.STAGE_ANGLES_DEG
    dofp_frames_per_angle: int = 6
    #: the DoFP plate's metal (complex index per colour; :mod:`polrig.calibration.mirror`): its
    #: diattenuation and retardance enter the states the analyzer is fitted to
    mirror: MirrorMetal = dataclasses.field(
        default_factory=lambda: MirrorMetal.named(DEFAULT_MIRROR_METAL))


def _geometry(cs: CalibrationSet) -> tt.JointRigResult:
    intr = cs.intrinsics
    ax = cs.turntable_axis
    fixtures = cs._section("fixtures")
    axis_std = float(ax.get("axis_std_deg", 0.0))
    axis = tt.TurntableAxisResult(ax["axis_cam"], ax["point_cam_m"], axis_std,
                                  np.asarray(ax.get("point_std_m", [0, 0, 0]), float), 1.0, 0.0,
                                  np.zeros(0), np.zeros(3), 0.0)
    poses = tuple((np.asarray(f["R"], float), np.asarray(f["t_m"], float))
                  for f in fixtures["poses"])
    rot_std = tuple(float(f.get("rotation_std_deg", axis_std)) for f in fixtures["poses"])
    return tt.JointRigResult(intr["K"], intr["dist"],
                             np.asarray(intr.get("std_fx_fy_cx_cy_px", [0.0] * 4), float),
                             axis, float(intr.get("rms_px", 0.0)), np.zeros((0, 2)), poses, rot_std)


def dependents(step: str) -> list[str]:
    """The steps whose results are computed from ``step``'s, directly or not (in
    :data:`STEPS` order)."""
    out: set[str] = set()
    frontier = {step}
    while frontier:
        new = {s for s, deps in DEPENDS_ON.items() if frontier & set(deps)} - out
        out |= new
        frontier = new
    return [s for s in STEPS if s in out]


def drop_results(cs: CalibrationSet, steps) -> list[str]:
    """Remove the results of ``steps`` from ``cs``; returns the steps that had results."""
    dropped = []
    for step in steps:
        had = any(cs.has(k) for k in STEP_SECTIONS[step]) or (
            step == "dofp" and (cs.analyzer is not None or bool(cs.dofp_maps)))
        for k in STEP_SECTIONS[step]:
            cs.params.pop(k, None)
        if step == "dofp":
            cs.analyzer = None
            cs.dofp_maps = {}
            g = cs.params.get("generator")
            if isinstance(g, dict):  # the extinction ratio is the DoFP step's result
                g.update(extinction_ratio=float("inf"), extinction_ratio_std=0.0)
                g.pop("extinction_ratio_reference", None)
        if had:
            dropped.append(step)
    return dropped


def check_set_fits_camera(cs: CalibrationSet, rig, name: str = "the calibration set") -> None:
    """Refuse (:class:`CalibrationError`, one line) to add a step to ``cs`` when ``rig``'s
    camera is not the readout the set was calibrated on (another sensor size, layout or ROI):
    the new step's result would be combined with results of another camera. Nothing moves
    before this check."""
    have = cs.sensor_geometry()
    if have is None:
        return
    now = SensorGeometry.of_rig(rig)
    why = have.mismatch(now, exact=True)
    if why:
        raise CalibrationError(
            f"{name} was calibrated on {have.describe('calibrated readout')}; this camera: "
            f"{now.describe()} ({why}); calibrate this camera into a new folder "
            f"('polrig calibrate all --out NEW_DIR')")


def run_steps(steps, rig, mount: Callable[..., None], cs: CalibrationSet, *,
              options: Options | None = None, log: Callable[[str], None] = print,
              extras: dict[str, Any] | None = None,
              on_step_done: Callable[[str], None] | None = None,
              set_name: str = "the calibration set",
              control: CaptureControl | None = None) -> CalibrationSet:
    """Run ``steps`` (names from :data:`STEPS`, in the given order) and store the results in
    ``cs``. ``extras`` (optional dict) receives the raw results for reports.

    The procedures drive ``rig`` through :class:`polrig.acquisition.engine.GuardedRig`: every grab,
    camera setting, light switch and move goes through the same fault policy as a capture
    (:class:`polrig.acquisition.engine.Executor`: retried grab timeouts, one re-homed retry per move
    but none after a safety fault such as a limit switch, timeouts from the declared
    capabilities, free-run settle frames; each retry is a ``log`` line), and ``control`` (a
    :class:`polrig.acquisition.engine.CaptureControl`) pauses or stops them before a grab or a
    move (:class:`polrig.acquisition.engine.StopRequested`).

    Before anything moves, a set calibrated on another camera readout is refused
    (:func:`check_set_fits_camera`, ``set_name`` names it). After each step, the results of
    the steps that depend on it (:data:`DEPENDS_ON`) are dropped from ``cs`` (one log line)
    and ``on_step_done(step)`` is called (the command saves the set there, so an
    interruption keeps the steps that finished). A step that fails changes nothing in
    ``cs``."""
    o = options or Options()
    extras = {} if extras is None else extras
    steps = list(steps)
    for step in steps:
        if step not in STEPS:
            raise ValueError(f"unknown calibration step {step!r}; one of {', '.join(STEPS)}, all")
    check_set_fits_camera(cs, rig, set_name)
    camera = SensorGeometry.of_rig(rig).to_json()
    rig = GuardedRig.around(rig, control=control, on_retry=lambda m: log(f"retry: {m}"))
    if any(step in STAGE_STEPS for step in steps):
        # the polarizer stage's zero is where its angles are measured from: homed first, as a
        # capture's setup homes it (polrig.acquisition.plan.setup_steps); a stage in a safety
        # fault is not homed (DeviceAlarm: the operator's to clear)
        rig.stage.home()
        log("stage: homed")
    for i, step in enumerate(steps):
        later = steps[i + 1:]

        def invalidate() -> None:
            """Drop the results computed from the one this step replaces."""
            dropped = drop_results(cs, dependents(step))
            for d in dropped:
                extras.pop(d, None)
            if dropped:
                again = [d for d in dropped if d not in later]
                log(f"{step}: dropped the set's {', '.join(dropped)} result"
                    f"{'s' if len(dropped) > 1 else ''} (computed from its earlier {step} "
                    f"result)" + (f"; run {'them' if len(again) > 1 else 'it'} again, from "
                                  f"'polrig calibrate {again[0]}'" if again else ""))
            cs.params["camera"] = dict(camera)

        if step == "intrinsics":
            ir = pr.run_intrinsics(rig, mount, o.board, distortion=o.distortion, log=log)
            r = ir.result
            invalidate()
            cs.params["intrinsics"] = {**r.to_json(), "method": "zhang", "views": len(ir.views),
                                       "skipped_views": ir.skipped, "board": o.board.to_json()}
            extras["intrinsics"] = ir
        elif step == "turntable":
            ir = extras.get("intrinsics")
            if ir is None:
                intr = cs.intrinsics
                jr = pr.run_turntable(rig, mount, o.board, None, intr["K"], intr["dist"],
                                      distortion=_N_RADIAL[o.distortion], log=log)
            else:
                jr = pr.run_turntable(rig, mount, o.board, ir, distortion=_N_RADIAL[o.distortion],
                                      log=log)
            invalidate()
            w, h = rig.camera.roi[:2]
            cs.params["intrinsics"] = {
                **cs.params.get("intrinsics", {}), "K": jr.K.tolist(), "dist": jr.dist.tolist(),
                "image_size": [w, h], "std_fx_fy_cx_cy_px": jr.std_fx_fy_cx_cy.tolist(),
                "std_dist": jr.std_dist.tolist(),
                "rms_px": jr.rms_px, "method": "joint bundle adjustment with the turntable",
                "board": o.board.to_json()}
            cs.params["turntable"] = jr.axis.to_json()
            cs.params["fixtures"] = {"mounts": [dict(m) for m in pr.INTRINSIC_MOUNTS],
                                     "poses": [{"R": R.tolist(), "t_m": t.tolist(),
                                                "rotation_std_deg": sd}
                                               for (R, t), sd in zip(jr.mount_poses,
                                                                     jr.mount_rotation_std_deg)]}
            extras["turntable"] = jr
        elif step == "light":
            intr = cs.intrinsics
            lf = pr.run_light(rig, mount, intr["K"], intr["dist"], o.sphere_radius_m,
                              intrinsics_std_px=intr.get("std_fx_fy_cx_cy_px"),
                              dist_std=intr.get("std_dist"), sphere_metal=o.sphere_metal,
                              log=log)
            invalidate()
            cs.params["light"] = {**lf.to_json(), "sphere_radius_m": o.sphere_radius_m,
                                  "sphere_metal": o.sphere_metal.to_json()}
            extras["light"] = lf
        elif step == "stokes":
            geo = _geometry(cs)
            off = pr.run_generator_offset(rig, mount, o.board, geo, cs.light_position_m,
                                          stage_angles_deg=o.stage_angles_deg,
                                          light_cov_m2=cs.params["light"].get("covariance_m2"),
                                          log=log)
            invalidate()  # drops the DoFP step's results, fitted with the earlier offset
            cs.params["generator"] = {
                "zero_offset_deg": off.zero_offset_deg,
                "zero_offset_std_deg": off.zero_offset_std_deg,
                "zero_offset_std_bound_deg": off.zero_offset_std_bound_deg,
                "extinction_ratio": float("inf"),  # measured by the dofp step
                "extinction_ratio_std": 0.0,
                "stage_zero_axis_cam": off.stage_zero_axis_cam.tolist(),
                "offset_method": "grazing-incidence Fresnel transmission into the matte board",
                "offset_turntable_deg": off.turntable_deg, "offset_incidence_deg":
                    off.incidence_deg, "offset_pixels": off.pixels}
            extras["stokes"] = off
        elif step == "dofp":
            geo = _geometry(cs)
            gen = cs.generator
            dr = pr.run_dofp(rig, mount, geo, cs.light_position_m, gen.zero_offset_deg,
                             stage_angles_deg=o.stage_angles_deg,
                             frames_per_angle=o.dofp_frames_per_angle,
                             sensor_diattenuation=o.sensor_diattenuation, mirror=o.mirror,
                             log=log)
            invalidate()
            cs.analyzer = dr.analyzer
            f = dr.fit
            cs.dofp_maps = {"dark_dn": dr.dark_dn.astype(np.float32),
                            "flat_scale": f.scale.astype(np.float32),
                            "angle_std_deg": f.angle_std_deg.astype(np.float32),
                            "modulation_std": f.modulation_std.astype(np.float32),
                            "residual_rms_dn": f.residual_rms_dn.astype(np.float32),
                            "valid": f.valid}
            g = cs.params["generator"]
            g.update({"extinction_ratio": dr.generator.extinction_ratio,
                      "extinction_ratio_std": dr.generator.extinction_ratio_std,
                      "extinction_ratio_reference": f"mean micro-polarizer diattenuation "
                                                    f"{o.sensor_diattenuation}"})
            v = f.valid
            cs.params["dofp"] = {
                "layout": dr.analyzer.layout, "shape": list(dr.analyzer.shape),
                "valid_fraction": float(v.mean()), "turntable_deg": dr.turntable_deg,
                "exposure_us": dr.exposure_us,
                "angle_std_deg_median": float(np.median(f.angle_std_deg[v])),
                "modulation_std_median": float(np.median(f.modulation_std[v])),
                "residual_rms_dn_median": float(np.median(f.residual_rms_dn[v])),
                "sensor_diattenuation_reference": o.sensor_diattenuation,
                "mirror": o.mirror.to_json(), "mirror_incidence_deg": dr.mirror_incidence_deg,
                "stage_angles_deg": list(o.stage_angles_deg),
                "frames_per_angle": o.dofp_frames_per_angle}
            extras["dofp"] = dr
        if step == "intrinsics" and "turntable" not in later:
            log("intrinsics: these are Zhang's start values; 'polrig calibrate turntable' "
                "refines them (joint bundle adjustment with the turntable axis)")
        if on_step_done is not None:
            on_step_done(step)
    return cs


# ------------------------------------------------------------------------------- truth
def truth_in_camera(truth: dict[str, Any]) -> dict[str, Any]:
    """The hidden rig parameters converted into the camera frame."""
    cam = truth["camera"]
    R, t = np.asarray(cam["R"], float), np.asarray(cam["t_m"], float)
    L = R @ np.asarray(truth["light_position_m"], float) + t
    target = R @ np.asarray(truth["illumination_target_m"], float) + t
    tt_ = truth["turntable"]
    return {"fx": cam["fx"], "fy": cam["fy"], "cx": cam["cx"], "cy": cam["cy"],
            "light_cam_m": L, "axis_cam": R @ np.asarray(tt_["axis"], float),
            "axis_point_cam_m": R @ np.asarray(tt_["point_m"], float) + t,
            "stage_zero_axis_cam": R @ np.asarray(truth["stage_zero_axis"], float),
            "target_cam_m": target,
            "zero_offset_deg": float(truth["generator"]["stage_zero_offset_deg"]),
            "extinction_ratio": float(truth["generator"]["extinction_ratio"])}


def errors_against_truth(cs: CalibrationSet, truth: dict[str, Any],
                         analyzer_truth: AnalyzerModel | None = None) -> dict[str, Any]:
    """Errors of every calibrated quantity present in ``cs`` against the hidden truth."""
    t = truth_in_camera(truth)
    out: dict[str, Any] = {}
    if cs.has("intrinsics"):
        K = cs.intrinsics["K"]
        out["intrinsics"] = {"fx_rel_error": K[0, 0] / t["fx"] - 1, "fy_rel_error": K[1, 1] / t["fy"] - 1,
                             "cx_error_px": K[0, 2] - t["cx"], "cy_error_px": K[1, 2] - t["cy"]}
    if cs.has("turntable"):
        a = cs.turntable_axis
        d = a["point_cam_m"] - t["axis_point_cam_m"]
        w = t["axis_cam"]
        out["turntable"] = {"axis_error_deg": tt.axis_angle_error_deg(a["axis_cam"], w),
                            "point_error_perp_m": float(np.linalg.norm(d - (d @ w) * w))}
    if cs.has("light"):
        L = cs.light_position_m
        e = L - t["light_cam_m"]
        dist = np.linalg.norm(t["light_cam_m"] - t["axis_point_cam_m"])
        out["light"] = {"error_m": e.tolist(), "error_norm_m": float(np.linalg.norm(e)),
                        "illumination_distance_m": float(dist),
                        "rel_error_of_illumination_distance": float(np.linalg.norm(e) / dist),
                        "camera_distance_m": float(np.linalg.norm(t["light_cam_m"]))}
    if cs.has("generator"):
        g = cs.params["generator"]
        zero = np.asarray(g["stage_zero_axis_cam"], float)
        k = t["target_cam_m"] - t["light_cam_m"]
        k = k / np.linalg.norm(k)
        xm = fr.basis_from_reference(k, zero)
        xt = fr.basis_from_reference(k, t["stage_zero_axis_cam"])
        frame_deg = float(np.degrees(fr.rotation_angle(k, xm, xt)))
        truth_off = t["zero_offset_deg"] + frame_deg
        out["generator"] = {"zero_offset_truth_in_calibration_frame_deg": truth_off,
                            "zero_axis_frame_rotation_deg": frame_deg,
                            "zero_offset_error_deg": float(g["zero_offset_deg"]) - truth_off}
        er = float(g["extinction_ratio"])
        if np.isfinite(er):
            out["generator"]["extinction_ratio_rel_error"] = er / t["extinction_ratio"] - 1
    if cs.analyzer is not None and analyzer_truth is not None:
        a, b = cs.analyzer, analyzer_truth
        v = cs.dofp_maps.get("valid", np.ones(a.shape, bool)).astype(bool)
        ea = (a.angle_deg - b.angle_deg)[v]
        eg = (a.gain / b.gain - 1)[v]
        ed = (a.diattenuation - b.diattenuation)[v]
        ideal = AnalyzerModel.ideal(b.layout, b.shape)
        out["dofp"] = {"angle_rms_error_deg": float(np.sqrt(np.mean(ea ** 2))),
                       "angle_mean_error_deg": float(ea.mean()),
                       "gain_rms_rel_error": float(np.sqrt(np.mean(eg ** 2))),
                       "diattenuation_rms_error": float(np.sqrt(np.mean(ed ** 2))),
                       "ideal_model_angle_rms_error_deg":
                           float(np.sqrt(np.mean((ideal.angle_deg - b.angle_deg)[v] ** 2))),
                       "ideal_model_gain_rms_rel_error":
                           float(np.sqrt(np.mean((1.0 / b.gain - 1)[v] ** 2)))}
    return out
