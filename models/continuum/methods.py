"""The estimators compared (single-shot, hybrid, reference), the adaptive capture's rule, the
simulated rig's acquisition time and the metrics of one sample.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from polrig.models.continuum.frames import Frames, lit_pixels, stack_states
from polrig.models.continuum.sets import (
    ADAPTIVE_MAX_STATES,
    ADAPTIVE_SHARE,
    OFFSETS_DEG,
    SIM_READOUT_US,
    SIM_STAGE_ACCEL_DEG_S2,
)
from polrig.models.scene_bootstrap import coverage_interval, scene_spread


def marginal_sigma(fr: Frames) -> np.ndarray:
    """Prior sigma that makes the hybrid solve with ``plane_variance="scalar"`` use the plain
    marginal on the unobserved plane (``sigma sqrt(g_r)``: the Schur complement scales with the
    precision, ``g_r`` does not)."""
    from polrig.solve.hybrid import observed_direction

    u2 = observed_direction(fr.states[0]) ** 2
    v = fr.sigma**2
    tot = v.sum(axis=2, keepdims=True)
    g = np.where(tot > 0, np.einsum("crahw,a->crhw", v, 1.0 - u2)[:, :, None] / np.where(tot > 0, tot, 1.0), 1.0)
    return fr.sigma * np.sqrt(g)


def scaled_sigma(fr: Frames, offsets: Sequence[int]) -> np.ndarray:
    """The prior's sigma as captures take it for the states ``offsets`` (the seen state first):
    ``fr.sigma`` times the factor of :func:`polrig.solve.prior_scale.prior_scale` (1 at one state),
    as :func:`polrig.solve.radiometry.prior_scale_from_frames` finds it on a capture's frames."""
    from polrig.solve.prior_scale import prior_scale

    factor = prior_scale(*stack_states(fr, offsets), fr.prior, fr.sigma, 0).factor
    return fr.sigma if factor == 1.0 else fr.sigma * factor


def open_factor(fr: Frames, offsets: Sequence[int], sigma: np.ndarray, correlation: np.ndarray | None = None
                ) -> float:
    """The factor on the hybrid prior's standard deviation along the direction two states leave
    open, as captures with :data:`polrig.choices.DEFAULT_PRIOR_SCALE` find it (``geometry``:
    :mod:`polrig.solve.open_scale` on the whole frame, the network's object, the prior's sigma
    ``sigma`` as scaled by :func:`scaled_sigma`); 1 at another number of states, without the
    frame's geometry, or with another default."""
    from polrig.choices import DEFAULT_PRIOR_SCALE
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.open_scale import open_scale_of, open_values

    if DEFAULT_PRIOR_SCALE != "geometry" or len(offsets) != 2 or fr.geometry is None:
        return 1.0
    s, meas, var, valid = stack_states(fr, offsets)
    prior = dict(prior_mean=fr.prior, prior_sigma=sigma, seen_state=0, prior_correlation=correlation)
    r = solve_hybrid(s, meas, var, valid, dtype=np.float64, **prior)
    return open_scale_of(*open_values(r, s, meas, var, valid, fr.geometry, mask=fr.mask, **prior)).factor


def estimate(fr: Frames, offsets: Sequence[int], method: str, correlation: np.ndarray | None = None,
             seen_share: Sequence[float] | None = None, prior_scale: bool = True):
    """``(mueller, sigma, solved)`` of ``method`` (``single``, ``hybrid``, ``reference`` or a
    :data:`VARIANTS` name) from the frames at ``offsets`` (the seen state first); ``correlation``:
    the hybrid's joint prior (:func:`polrig.solve.hybrid.solve_hybrid`'s ``prior_correlation``;
    None the per-element prior); ``seen_share``: the hybrid's (``solve_hybrid``'s; None: the
    row's whole variance along the seen direction kept); ``prior_scale``: the hybrid's prior
    sigma scaled as captures scale it (:func:`scaled_sigma` and, at two states, :func:`open_factor`;
    the default) or as calibrated (False; the :data:`VARIANTS` study the calibrated sigma)."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.reference import ILL_CONDITIONED, solve_reference

    if method == "single":
        return fr.prior, fr.sigma, np.ones(fr.use.shape, bool)
    s, meas, var, valid = stack_states(fr, offsets)
    kw = dict(prior_mean=fr.prior, dtype=np.float64)
    if method == "hybrid":
        sigma = scaled_sigma(fr, offsets) if prior_scale else fr.sigma
        factor = open_factor(fr, offsets, sigma, correlation) if prior_scale else 1.0
        r = solve_hybrid(s, meas, var, valid, prior_sigma=sigma, seen_state=0, prior_correlation=correlation,
                         seen_share=seen_share, open_factor=factor, **kw)
    elif method == "marginal":
        r = solve_hybrid(s, meas, var, valid, prior_sigma=marginal_sigma(fr), seen_state=0, plane_variance="scalar",
                         **kw)
    elif method == "naive":
        r = solve_hybrid(s, meas, var, valid, prior_sigma=fr.sigma, seen_state=None, **kw)
    elif method == "exclude":
        if len(offsets) == 1:
            return fr.prior, fr.sigma, np.ones(fr.use.shape, bool)
        r = solve_hybrid(s[1:], meas[1:], var[1:], valid[1:], prior_sigma=fr.sigma, seen_state=None, **kw)
    elif method == "reference":
        r = solve_reference(s, meas, var, valid, dtype=np.float64, max_condition=np.inf)
    elif method == "hybrid_models":
        return hybrid_with_models(fr, offsets, correlation)[:3]
    else:
        raise ValueError(method)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0


def hybrid_models_result(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None,
                         prior_scale: bool = True):
    """The hybrid solve of ``offsets`` then the lower-order model selection
    (:func:`polrig.solve.model_selection.select_models` with the network as the prior: at two
    states it tests on the hybrid's posterior system, samples and prior): the
    :class:`polrig.solve.reference.ReferenceResult` (its ``models`` the maps) and the states
    ``(N, 3)``; the prior's sigma scaled as captures scale it (:func:`scaled_sigma`) or, with
    ``prior_scale`` False, as calibrated."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.model_selection import select_models

    s, meas, var, valid = stack_states(fr, offsets)
    sigma = scaled_sigma(fr, offsets) if prior_scale else fr.sigma
    r = solve_hybrid(s, meas, var, valid, prior_mean=fr.prior, prior_sigma=sigma, seen_state=0,
                     dtype=np.float64, prior_correlation=correlation)
    r, _ = select_models(s, meas, var, valid, None, r, prior=(fr.prior, sigma), seen_state=0,
                         prior_correlation=correlation)
    return r, s


def hybrid_with_models(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None):
    """:func:`hybrid_models_result` as ``(mueller, sigma, solved, model codes (C, H, W))``."""
    from polrig.solve.reference import ILL_CONDITIONED

    r, _ = hybrid_models_result(fr, offsets, correlation)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0, r.models.code


def reference_with_models(fr: Frames, offsets: Sequence[int]):
    """The reference solve of ``offsets`` (no prior) then the lower-order model selection
    (:func:`polrig.solve.model_selection.select_models`, the samples alone):
    ``(mueller, sigma, solved, model codes (C, H, W))``. At four states it is the bound the
    two-state rows are read against: the same candidates fitted to twice the samples."""
    from polrig.solve.model_selection import select_models
    from polrig.solve.reference import ILL_CONDITIONED, solve_reference

    s, meas, var, valid = stack_states(fr, offsets)
    r = solve_reference(s, meas, var, valid, dtype=np.float64, max_condition=np.inf)
    r, maps = select_models(s, meas, var, valid, None, r)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0, maps.code


#: The priors of the joint comparison (:func:`joint_priors`): the per-element prior, the joint
#: one (the fitted correlation ``K``) and the joint one with the whitened errors' scale measured
#: on the calibration scenes (``S K S``, ``S`` the file's ``coverage_scale``).
JOINT_PRIORS = ("diagonal", "joint", "joint_scaled")


def joint_priors(uncertainty) -> dict[str, np.ndarray | None]:
    """:data:`JOINT_PRIORS` -> the hybrid's ``prior_correlation`` of an
    :class:`polrig.models.uncertainty.UncertaintyModel` with a joint prior."""
    k = uncertainty.joint_correlation
    scale = np.asarray(uncertainty.joint["coverage_scale"], np.float64)
    return dict(zip(JOINT_PRIORS, (None, k, scale[:, None] * k * scale[None, :])))


def acquisition_time_s(offsets: Sequence[float], frames_per_state: int = 1, bracket: Sequence[float] = ()) -> float:
    """The simulated rig's hardware time of one pose that takes the states ``offsets`` (deg from
    the seen state, in that order; the stage starts at the first, each move to the nearer of the
    two equivalent angles: :func:`polrig.acquisition.plan.nearest_stage_angle`): the stage's
    trapezoidal moves (:mod:`polrig.sim.motion`, the simulated rig's speed and acceleration) and
    ``frames_per_state`` frames of the dataset's exposure plus readout per state, and as many
    again at each ``bracket`` fraction of it
    (:func:`polrig.acquisition.plan.step_durations` of
    :func:`polrig.acquisition.plan.adaptive_pose_steps`: the plan's own hardware time)."""
    from polrig.acquisition.plan import CapturePlan, adaptive_pose_steps, step_durations
    from polrig.sim.dataset import DATASET_EXPOSURE_US

    plan = CapturePlan((0.0,), frames_per_state=int(frames_per_state))
    exposures = [DATASET_EXPOSURE_US] + [DATASET_EXPOSURE_US * float(f) for f in bracket]
    return float(sum(step_durations(adaptive_pose_steps(plan, 0, exposures, stage_angles(offsets)),
                                    sim_hardware_model())))


def stage_angles(offsets: Sequence[float]) -> list[float]:
    """The stage angles of a pose that takes the states ``offsets`` in that order: the first as
    given, each next at the nearer of its two equivalent angles
    (:func:`polrig.acquisition.plan.nearest_stage_angle`)."""
    from polrig.acquisition.plan import nearest_stage_angle

    angles = [float(offsets[0])]
    for d in offsets[1:]:
        angles.append(nearest_stage_angle(d, angles[-1]))
    return angles


def sim_hardware_model():
    """The simulated rig's :class:`polrig.acquisition.plan.HardwareModel` at the sets' exposure:
    trapezoidal moves (:mod:`polrig.sim.motion`, the simulated rig's default speeds and
    :data:`SIM_STAGE_ACCEL_DEG_S2`), :data:`SIM_READOUT_US` per frame, no settle frames, both
    axes at 0."""
    from polrig.acquisition.plan import HardwareModel
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.sim.motion import Move
    from polrig.sim.options import DEFAULTS

    speed = {"stage": DEFAULTS["stage_speed_deg_s"], "turntable": DEFAULTS["turntable_speed_deg_s"]}
    return HardwareModel(lambda a, f, t: Move(f, t, 0.0, speed[a], SIM_STAGE_ACCEL_DEG_S2).duration_s
                         if f != t else 0.0, SIM_READOUT_US, 0, {"stage": 0.0, "turntable": 0.0},
                         DATASET_EXPOSURE_US)


def adaptive(fr: Frames, target: float, *, share: float = ADAPTIVE_SHARE,
             max_states: int = ADAPTIVE_MAX_STATES, min_states: int | None = None,
             correlation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """The adaptive capture on one sample (:mod:`polrig.app.adaptive`'s rule and criterion on
    the sample's frames): from the seen state, while less than ``share`` of the object pixels
    (those whose seen frame is not clipped and has some colour above its noise floor, ``S0`` at
    least :data:`polrig.solve.reference.MIN_SNR` sigmas; the colours below it do not count) have
    a relative posterior sigma at most ``target``, or fewer than ``min_states`` states are taken
    (default the capture's, :data:`polrig.acquisition.plan.ADAPTIVE_MIN_STATES`; designed then for
    every object pixel), and fewer than ``max_states`` states are taken, the A-optimal next offset
    (:func:`polrig.solve.design.a_optimal_next`, under the joint prior ``correlation`` where
    given) among the candidates of :func:`polrig.solve.design.next_candidates` not taken yet
    (the equiangular set through the seen state first, then the 15 deg offsets; one frame each
    exists), chosen as the capture chooses (:func:`polrig.solve.design.choose_next`, timed by
    :func:`sim_hardware_model` and :data:`polrig.solve.design.DECISION_S`; the time reported is
    the hardware time alone, as for every method). Returns the hybrid estimate of the states taken (``estimate``'s three arrays, with
    the joint prior ``correlation`` where given, as the capture's) and the offsets taken, in
    order."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES, CapturePlan, nearest_stage_angle, state_time_s
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.solve.design import (
        DECISION_S,
        DESIGN_PIXELS,
        a_optimal_next,
        choose_next,
        next_candidates,
        predicted_share,
        relative_sigma,
        share_at_target,
    )

    # the capture's object pixels: the seen frame not clipped, some colour above its noise floor
    lit = lit_pixels(fr)
    obj = fr.use.all(axis=0) & lit.any(axis=0)
    plan, exposures, model = CapturePlan((0.0,)), [DATASET_EXPOSURE_US], sim_hardware_model()
    taken = [0]
    while True:
        prior_sigma = scaled_sigma(fr, taken)  # the solve's and the design's, as the capture's
        mueller, sigma, solved = estimate(fr, taken, "hybrid", correlation)  # prior_sigma and, at two, the open factor
        got, met = share_at_target(relative_sigma(sigma, mueller, lit), obj, target)
        least = len(taken) >= (ADAPTIVE_MIN_STATES if min_states is None else min_states)
        if (got >= share and least) or len(taken) >= max_states:
            return mueller, sigma, solved, taken
        m00 = mueller[:, 0, 0]
        above = obj & np.all((m00 > 0) & np.isfinite(m00), axis=0)
        at_target = 0.0  # as the capture: below its least states, designed for every object pixel
        if got < share:
            above &= ~met
            at_target = got
        ys, xs = np.nonzero(above)
        if len(ys) == 0:
            return mueller, sigma, solved, taken
        stride = max(1, -(-len(ys) // DESIGN_PIXELS))
        ys, xs = ys[::stride], xs[::stride]
        px = lambda a: np.moveaxis(np.asarray(a, np.float64)[..., ys, xs], -1, 0)  # noqa: E731
        cands = [int(round(a)) for a in next_candidates(taken, OFFSETS_DEG)]
        scores = a_optimal_next(px(prior_sigma), fr.states[0], [(fr.states[d], px(fr.var[d]), px(fr.valid[d]) > 0)
                                                            for d in taken],
                                px(mueller), np.stack([fr.states[d] for d in cands]), *fr.noise_terms,
                                correlation=correlation)
        # the capture's choice (polrig.app.adaptive): the cheapest state predicted to finish, else at the
        # last state the least criterion, else the greatest reduction per second of hardware time
        here = stage_angles(taken)[-1]
        cost = [state_time_s(plan, exposures, here, nearest_stage_angle(c, here), model) + DECISION_S for c in cands]
        m = px(mueller)
        after = predicted_share(scores.trace.reshape(len(cands), *m.shape[:2]), m[..., 0, 0], px(lit) > 0,
                                target, at_target, int(above.sum()) / int(obj.sum()))
        taken.append(cands[choose_next(scores, cost, after, share, last=len(taken) + 1 >= max_states)])


def score(fr: Frames, mueller: np.ndarray, sigma: np.ndarray, solved: np.ndarray,
          clean: np.ndarray | None = None, cover: np.ndarray | None = None) -> dict[str, float]:
    """Matrix PSNR (over the object, and over its pixels unclipped in every state: ``clean``,
    default ``fr.clean``), forward L2 and the counts of elements within 2 sigma (module
    docstring; over ``cover`` ``(C, H, W)`` instead of the pixels whose seen frame is not
    clipped, if given)."""
    from polrig.models.evaluate import forward_l2, psnr

    clean = fr.clean if clean is None else clean
    pred = (mueller * fr.mask).astype(np.float32)
    peak = float(np.abs(fr.truth[..., fr.mask]).max())
    sel = (fr.use if cover is None else cover) & solved
    inside = (np.abs(mueller - fr.truth) <= 2.0 * sigma).transpose(1, 2, 0, 3, 4)[:, :, sel]
    return {"matrix_psnr": psnr(pred, fr.truth, fr.mask, peak),
            "matrix_psnr_unclipped": psnr(pred, fr.truth, clean, peak) if clean.any() else float("nan"),
            "fwd_l2": forward_l2(pred, fr.truth, fr.mask),
            "inside": float(inside.sum()), "elements": float(inside.size)}


def mean_rows(rows: list[dict[str, float]]) -> dict[str, float]:
    """One method's metrics over a set: the mean of each sample's (:func:`score`'s) metrics,
    coverage pooled over the elements with its interval over the samples, and the shares and
    false-acceptance rates pooled over what each counts."""
    keys = ("matrix_psnr", "matrix_psnr_unclipped", "fwd_l2", "states", "time_s", "psnr_holds", "accepted",
            "accepted_holds", "specular")
    out = {k: float(np.nanmean([r[k] for r in rows])) for k in keys if rows and k in rows[0]}
    n = sum(r["elements"] for r in rows)
    out["coverage"] = sum(r["inside"] for r in rows) / n if n else float("nan")
    if rows:
        inside, elements = [r["inside"] for r in rows], [r["elements"] for r in rows]
        out["coverage_interval"] = list(coverage_interval(inside, elements))
        out["coverage_scenes"] = list(scene_spread(inside, elements))
    if rows and "hl_elements" in rows[0]:
        n = sum(r["hl_elements"] for r in rows)
        out["coverage_highlights"] = sum(r["hl_inside"] for r in rows) / n if n else float("nan")
        out["highlight_elements"] = float(n)
    for metric in ("", "_mc", "_prior"):  # the false acceptance in each metric a row counts
        if rows and f"detectable{metric}" in rows[0]:
            det = sum(r[f"detectable{metric}"] for r in rows)
            out[f"false_acceptance{metric}"] = (sum(r[f"falsely_accepted{metric}"] for r in rows) / det if det
                                                else float("nan"))
            out[f"detectable{metric}_share"] = det / n * 9 if n else float("nan")
    if rows and "holds_pixels" in rows[0]:
        total = sum(r["object_pixels"] for r in rows)
        out["holds_share"] = sum(r["holds_pixels"] for r in rows) / total if total else float("nan")
    return out
