"""The adaptive capture (issue 33 item 2): each pose starts with the single-shot frame at the
plan's first polarizer state, the network's estimate becomes the prior of the hybrid solve
(:mod:`polrig.solve.hybrid`), and further states are chosen one at a time from the posterior
until the pose is measured well enough.

**The target** (:attr:`polrig.acquisition.plan.CapturePlan.target_sigma`, ``target_share``,
``max_states``): an object pixel meets it when its relative posterior sigma
(:func:`polrig.solve.design.relative_sigma`: the RMS sigma of the nine elements over ``m00``,
the worst colour; dimensionless, the block normalised to ``m00 = 1``) is at most
``target_sigma``. The sigma is the posterior's noise-and-prior part (``sigma_noise``): the
calibration's tolerances add a systematic floor that more states of the same rig do not
lower, so a target below it would never stop. Object pixels are the network's object mask
less the pixels clipped in its frame (the network gives them no prior: infinite sigma; they
need an exposure bracket, not more states, and are counted apart, ``clipped_pixels``; with a
bracket, ``--exposure T,T/16,...``, those a shorter exposure measured have a prior,
:mod:`polrig.models.highlights`, and count as object pixels) and the
pixels dark in every colour of its frame (``S0`` below :data:`polrig.solve.reference.MIN_SNR`
noise sigmas, the route's ``DARK`` bit: turned away from the light, all noise; ``dark_pixels``);
a colour dark at a pixel does not count in its relative sigma. A pixel without a finite
posterior does not meet the target. A pose stops when
the share of its object pixels meeting the target reaches ``target_share`` with at least
``min_states`` states taken, or at ``max_states`` states. **Why a least number of states**
(:data:`polrig.acquisition.plan.ADAPTIVE_MIN_STATES`, two by default): at one state the posterior
sigma is the network's calibrated sigma alone, which nothing the network did not see has checked;
a second state checks the prior's scale (the innovations', :mod:`polrig.solve.prior_scale`,
and along the direction two states leave open, :mod:`polrig.solve.open_scale`). A pose at target
on fewer states takes the next one (``take-min-states``), designed for all its object pixels.

**The choice** (:func:`evaluate`; :mod:`polrig.solve.design`): the Bayesian A-optimal
criterion (the summed relative posterior variance over the object pixels still above target,
predicted in closed form, under the prior the solve uses: the calibration's joint prior where
it holds one) for each candidate of :func:`polrig.solve.design.next_candidates`: for the
second and third states the two others of the equiangular set through the first (its angle
+60 and +120 deg), then :data:`CANDIDATES_DEG` less the states taken, each at the nearer of its
two stage angles (a linear polarizer repeats every 180 deg). It is evaluated on at most
:data:`polrig.solve.design.DESIGN_PIXELS` of those pixels (every n-th in raster order:
deterministic), with the ideal analyzer's rows and the noise model's variance at the current
estimate. Each candidate's hardware time (its move and frames,
:func:`polrig.acquisition.plan.state_time_s`) is timed by the rig's timing the session
recorded (``rig.timing``, :func:`timing_model`), with the decision's own time the stage waits
for (``rig.timing.decision_s``), and :func:`polrig.solve.design.choose_next`
takes the cheapest state predicted to bring the pose to its target; else, at the last allowed
state, the least criterion; else the greatest predicted reduction per second. A session
recorded before the rig's timing was (no ``rig.timing``) chooses as it did then: the least
criterion, of equal ones the nearest.

**How a decision enters the plan.** Plans are frozen data and the engine knows no session
(:mod:`polrig.acquisition.engine`): :class:`AdaptiveSchedule` hands the executor one piece at a
time (a pose's start and first state; then each chosen state; then the pose's end) through
:meth:`polrig.acquisition.engine.Executor.run`'s ``extend``, which the executor calls when the
steps it has run out. Each piece is steps of :mod:`polrig.acquisition.plan`
(:func:`~polrig.acquisition.plan.pose_head_steps`, :func:`~polrig.acquisition.plan.state_steps`,
:func:`~polrig.acquisition.plan.pose_tail_steps`), run under the engine's one fault policy; a pose
that took states ``S`` ran exactly :func:`~polrig.acquisition.plan.adaptive_pose_steps` of ``S``.

**Reproducible.** A decision reads the pose's frames back from the session (checksums
verified, :func:`polrig.app.sessionio.load_capture_frames`) after the session writer has
written them, so it is a function of the recorded frames alone: :func:`replay_decisions`
recomputes a pose's decisions from its files, and a resumed session (which acquires an
interrupted pose from scratch) takes the same decisions on the same frames. Each decision is
recorded in the pose's manifest entry (``adaptive``: :class:`polrig.app.manifest.AdaptiveDecision`).

**Fast.** Within a pose, only the newest state's frames are new: a run's decisions share a
:class:`PoseMemo` (:func:`polrig.app.capture.run_session` keeps one), which holds the pose's
frames already decoded, their state radiances and the network's answer on the first state,
each keyed by the SHA-256 of the files it comes from (every file is still verified on each
read), and forgets them at the pose's last decision. A decision then costs the new state's frames and radiance, the hybrid solve of all
states, and the criterion (on the design pixels; only the samples' variances are demosaiced
for it, not the signal). The record is identical with and without the memo (every reused
value is that of the same computation on the same bytes; tested), so replay and resume stay
exact. Measured with ``python -m benchmarks adaptive`` (its decision table).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from typing import Any

import numpy as np

from polrig.acquisition.hal import AxisCapabilities
from polrig.acquisition.plan import (
    ADAPTIVE_CANDIDATE_STEP_DEG,
    CapturePlan,
    HardwareModel,
    Step,
    adaptive_forecast_states,
    adaptive_pose_steps,
    nearest_stage_angle,
    pose_head_steps,
    pose_tail_steps,
    state_steps,
    state_time_s,
)
from polrig.app.processing import (
    Processor,
    capture_state_radiance,
    noise_exposures_us,
    process_reference,
    state_key,
)
from polrig.app.session import Session
from polrig.app.sessionio import CaptureFrames, load_capture_frames
from polrig.sensor.frame import Frame
from polrig.solve.design import (
    DESIGN_PIXELS,
    a_optimal_next,
    choose_next,
    next_candidates,
    predicted_share,
    relative_sigma,
    share_at_target,
)
from polrig.solve.radiometry import StateRadiance, analyzer_variance
from polrig.solve.reference import DARK

#: Candidate polarizer angles, deg: ``[0, 180)`` in steps of
#: :data:`polrig.acquisition.plan.ADAPTIVE_CANDIDATE_STEP_DEG`.
CANDIDATES_DEG = tuple(float(a) for a in np.arange(0.0, 180.0, ADAPTIVE_CANDIDATE_STEP_DEG))
#: What a decision does (the manifest's ``action``): ``TAKE_MIN`` takes a state although the
#: target holds, the pose having fewer than the plan's ``min_states``.
TAKE, TAKE_MIN, STOP_TARGET, STOP_MAX, STOP_NO_OBJECT = (
    "take", "take-min-states", "stop-target", "stop-max-states", "stop-no-object")
#: The actions that take a state.
TAKES = (TAKE, TAKE_MIN)


@dataclasses.dataclass
class PoseMemo:
    """What the decisions of one capture share (module docstring, *Fast*): the frames read
    (by :func:`polrig.app.sessionio.frame_key`), the state radiances (by
    :func:`polrig.app.processing.state_key`) and the network's answer on the seen state (by
    that key and its incident state). Every entry is keyed by the checksums of the files it
    comes from, so a decision that uses it is the decision a fresh process takes on the same
    files. For one session and one processor; :meth:`of_capture` forgets a capture's entries
    when the next capture begins (only one pose's are held)."""

    index: int | None = None
    frames: dict[str, Frame] = dataclasses.field(default_factory=dict)
    radiances: dict[Hashable, StateRadiance] = dataclasses.field(default_factory=dict)
    networks: dict[Hashable, Any] = dataclasses.field(default_factory=dict)

    def of_capture(self, index: int) -> PoseMemo:
        """This memo for capture ``index``: emptied if it held another capture's entries."""
        if index != self.index:
            self.clear()
            self.index = index
        return self

    def clear(self) -> None:
        """Forget every entry (a pose's last decision: its arrays are not held while the next
        pose is acquired and this one processed)."""
        self.index = None
        self.frames.clear()
        self.radiances.clear()
        self.networks.clear()


class _Clock:
    """Adds the seconds spent in ``with clock(part):`` to ``timings[part]`` (no-op without)."""

    def __init__(self, timings: dict[str, float] | None):
        self.timings = timings

    @contextlib.contextmanager
    def __call__(self, part: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            if self.timings is not None:
                self.timings[part] = self.timings.get(part, 0.0) + time.perf_counter() - t


def evaluate(cf: CaptureFrames, plan: CapturePlan, processor: Processor,
             geometry: dict[str, Any] | None, memo: PoseMemo | None = None,
             timings: dict[str, float] | None = None, timing: Mapping[str, Any] | None = None
             ) -> dict[str, Any]:
    """The decision after the states of ``cf`` (a pose's frames so far, first state first):
    an :class:`polrig.app.manifest.AdaptiveDecision` record (``states_taken``, ``share_met``,
    ``object_pixels``, ``clipped_pixels``, ``dark_pixels``, ``design_pixels``, ``criterion``, ``action``, ``state_deg``,
    ``predicted_criterion``, ``state_time_s`` with ``timing``, and ``sigma_scale``, the factor on
    the prior's sigma: :attr:`polrig.app.processing.Processor.prior_scale`). See the module
    docstring.

    ``timing``: the rig's :class:`polrig.app.manifest.TimingRecord` (the session's
    ``rig.timing``), which times the candidates for :func:`polrig.solve.design.choose_next`;
    without it (a session from before it) the least criterion is taken.

    ``memo``: the state radiances and the network's answer of earlier decisions of the same
    pose (:class:`PoseMemo`), reused where their files' checksums match; the record is
    identical with and without it. ``timings`` (if given) gets the seconds of each part added:
    ``radiance``, ``network``, ``solve`` (the hybrid solve), ``criterion``."""
    clock = _Clock(timings)

    def radiance(k: int) -> StateRadiance:
        key = None if memo is None else state_key(cf, k)
        if key is None:
            return capture_state_radiance(cf, k, processor.sensor_model)
        if key not in memo.radiances:
            memo.radiances[key] = capture_state_radiance(cf, k, processor.sensor_model)
        return memo.radiances[key]

    with clock("radiance"):
        states = [radiance(k) for k in range(len(cf.frames))]
    keep: dict[str, Any] = {}
    header: dict[str, Any] = {}
    network = processor.prior_function(cf, geometry, header, keep,
                                       None if memo is None else memo.networks)

    def prior(states_: list[StateRadiance], s_in_: np.ndarray) -> dict[str, Any]:
        with clock("network"):
            return network(states_, s_in_)

    t, network_s = time.perf_counter(), (timings or {}).get("network", 0.0)
    result, s_in, lay, states = process_reference(cf, processor.calibration, processor.sensor_model,
                                                  processor.demosaic, np.float32, prior, states=states)
    if timings is not None:  # the solve: all of it but the network
        network_s = timings.get("network", 0.0) - network_s
        timings["solve"] = timings.get("solve", 0.0) + time.perf_counter() - t - network_s
    solved = keep["prior"]  # the design's prior is the solve's: its sigma scaled, its correlation
    with clock("criterion"):
        record = _decide(cf, plan, processor, result, s_in, lay, states, keep["net"], solved["prior_sigma"],
                         solved.get("prior_correlation"), timing)
    return record | {"sigma_scale": header["sigma_scale"]["factor"]}


def timing_model(timing: Mapping[str, Any]) -> HardwareModel:
    """The :class:`polrig.acquisition.plan.HardwareModel` of a recorded
    :class:`polrig.app.manifest.TimingRecord`: the polarizer stage's moves and the frames' readout
    and settle frames (the stage's position and the camera's exposure are set per candidate
    by :func:`polrig.acquisition.plan.state_time_s`)."""
    accel = timing["stage_accel_deg_s2"]
    stage = AxisCapabilities(float(timing["stage_speed_deg_s"]), math.inf if accel is None else float(accel))

    def move_time_s(axis: str, from_deg: float, to_deg: float) -> float:
        if axis != "stage":
            raise ValueError(f"the recorded timing has the polarizer stage's motion only, not the {axis}'s")
        return stage.move_time_s(float(to_deg) - float(from_deg))

    return HardwareModel(move_time_s, float(timing["readout_us"]), int(timing["settle_frames"]),
                         {"stage": 0.0}, math.nan)


def _decide(cf: CaptureFrames, plan: CapturePlan, processor: Processor, result, s_in: np.ndarray,
            lay, states: list[StateRadiance], net, prior_sigma: np.ndarray,
            net_correlation: np.ndarray | None = None,
            timing: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:func:`evaluate`'s record from the hybrid solve's ``result`` of the states ``states``
    (incident ``s_in``, layout ``lay``), the network's answer ``net`` on the first, the prior's
    sigma and joint correlation the solve used (``prior_sigma`` ``(C, 3, 3, H, W)``, the network's
    scaled by :attr:`polrig.app.processing.Processor.prior_scale`; correlation None: the
    per-element prior) and the rig's ``timing``."""
    sigma = result.sigma_noise if result.sigma_noise is not None else result.sigma
    lit = (np.asarray(net.mask) & DARK) == 0  # (C, H, W): colours above the seen frame's noise floor
    rel = relative_sigma(sigma, result.mueller, lit)
    prior_sigma = np.asarray(prior_sigma)
    net_object = np.asarray(net.object, bool)
    clipped = net_object & ~np.all(np.isfinite(prior_sigma), axis=(0, 1, 2))
    dark = net_object & ~clipped & ~lit.any(axis=0)
    obj = net_object & ~clipped & ~dark
    share, met = share_at_target(rel, obj, plan.target_sigma)  # rel is inf without a finite answer
    n_obj = int(obj.sum())
    n = len(cf.states_deg)
    record: dict[str, Any] = {"states_taken": n, "share_met": share, "object_pixels": n_obj,
                              "clipped_pixels": int(clipped.sum()), "dark_pixels": int(dark.sum()),
                              "design_pixels": 0,
                              "criterion": None, "action": TAKE,
                              "state_deg": None, "predicted_criterion": None}
    if n_obj == 0:
        return record | {"action": STOP_NO_OBJECT}
    if share >= plan.target_share and n >= plan.min_states:
        return record | {"action": STOP_TARGET}
    if n >= plan.max_states:
        return record | {"action": STOP_MAX}
    m00 = np.asarray(result.mueller)[:, 0, 0].astype(np.float64)
    above = obj & np.all((m00 > 0) & np.isfinite(m00), axis=0)  # (all colours: it normalises)
    at_target = 0.0  # the share the design pixels leave out, met already
    if share >= plan.target_share:  # at target on fewer states than the plan's least: one more,
        record["action"] = TAKE_MIN  # designed for every object pixel
    else:  # designed for the object pixels above target
        above &= ~met
        at_target = share
    ys, xs = np.nonzero(above)
    if len(ys) == 0:  # the pixels above target are all dark or masked: nothing to design for
        return record | {"action": STOP_TARGET}
    stride = max(1, math.ceil(len(ys) / DESIGN_PIXELS))
    ys, xs = ys[::stride], xs[::stride]
    pixels = lambda a: np.moveaxis(np.asarray(a)[..., ys, xs], -1, 0)
    measured = []
    for k, st in enumerate(states):
        var, ok = analyzer_variance(st, lay, processor.demosaic)
        measured.append((s_in[k], pixels(var), pixels(ok)))
    per_dn, offset = processor.sensor_model.variance_terms(noise_exposures_us(cf)[0], plan.frames_per_state)
    candidates = next_candidates(cf.states_deg, CANDIDATES_DEG)
    estimate = pixels(result.mueller).astype(np.float64)  # (N, C, 3, 3)
    scores = a_optimal_next(pixels(prior_sigma).astype(np.float64), s_in[0], measured, estimate,
                            processor.calibration.incident_stokes(candidates), float(per_dn), float(offset),
                            correlation=net_correlation)
    j = scores.predicted
    here = cf.states_deg[-1]
    angles = [nearest_stage_angle(a, here) for a in candidates]
    if timing is None:  # a session from before the rig's timing: the least criterion, of equal ones the nearest
        best = min(np.flatnonzero(j <= np.min(j)), key=lambda c: (abs(angles[c] - here), c))
        return record | {"design_pixels": len(ys), "criterion": scores.criterion,
                         "state_deg": angles[best], "predicted_criterion": float(j[best])}
    model = timing_model(timing)
    hardware = [state_time_s(plan, cf.exposures_us, here, a, model) for a in angles]
    cost = [t + float(timing["decision_s"]) for t in hardware]  # and the decision the stage waits for
    share_after = predicted_share(scores.trace.reshape(len(angles), *estimate.shape[:2]), estimate[..., 0, 0],
                                  pixels(lit), plan.target_sigma, at_target, int(above.sum()) / n_obj)
    best = choose_next(scores, cost, share_after, plan.target_share, last=n + 1 >= plan.max_states)
    return record | {"design_pixels": len(ys), "criterion": scores.criterion, "state_deg": angles[best],
                     "predicted_criterion": float(j[best]), "state_time_s": hardware[best]}


def truncated(cf: CaptureFrames, n: int) -> CaptureFrames:
    """``cf`` with its first ``n`` states only (the pose as it was after ``n`` states)."""
    return dataclasses.replace(cf, states_deg=list(cf.states_deg[:n]), frames=list(cf.frames[:n]),
                               checksums=list(cf.checksums[:n]))


def decide(session: Session, index: int, processor: Processor, memo: PoseMemo | None = None,
           timings: dict[str, float] | None = None) -> dict[str, Any]:
    """Capture ``index``'s decision after the states it has recorded so far (read back from the
    session), appended to its manifest entry (``adaptive``) and saved. ``memo``: what earlier
    decisions of the run computed (:class:`PoseMemo`; the same decision without it);
    ``timings``: as :func:`evaluate`'s, with ``read`` (the frames read back, verified)."""
    memo = None if memo is None else memo.of_capture(index)
    with _Clock(timings)("read"):
        cf = load_capture_frames(session, index, None if memo is None else memo.frames)
    record = evaluate(cf, session.plan, processor, processor.network_geometry(session, cf), memo, timings,
                      timing=session.manifest["rig"].get("timing"))
    if memo is not None and record["action"] not in TAKES:  # the pose's last decision
        memo.clear()
    with session.mutex:
        session.capture(index).setdefault("adaptive", []).append(record)
        session.save()
    return record


def replay_decisions(session: Session, index: int, processor: Processor,
                     memo: PoseMemo | None = None) -> list[dict[str, Any]]:
    """Capture ``index``'s decisions recomputed from its recorded frames (after 1, 2, ...
    states): equal to its manifest's ``adaptive`` records when they are reproducible
    (``memo`` as :func:`evaluate`'s: the same records with or without it)."""
    memo = None if memo is None else memo.of_capture(index)
    cf = load_capture_frames(session, index, None if memo is None else memo.frames)
    geometry = processor.network_geometry(session, cf)
    timing = session.manifest["rig"].get("timing")
    return [evaluate(truncated(cf, n), session.plan, processor, geometry, memo, timing=timing)
            for n in range(1, len(cf.states_deg) + 1)]


class AdaptiveSchedule:
    """The device steps of the adaptive captures ``captures`` of ``plan``, handed out a piece
    at a time as the decisions are made (module docstring). ``decide(index)`` returns a
    capture's next decision (:func:`decide`) once the frames of its last state are written.

    :meth:`start` gives the first piece; :meth:`extend` (the executor's ``extend``) the next
    one, ``[]`` when every capture is done. :meth:`forecast` is the steps still expected after
    those handed out so far (the current capture at its :func:`adaptive_forecast_states`, the
    captures after it at theirs), for the hardware time and ETA."""

    def __init__(self, plan: CapturePlan, captures: Sequence[int], exposures_us: Sequence[float],
                 decide: Callable[[int], dict[str, Any]]):
        self.plan, self.captures = plan, list(captures)
        self.exposures = [float(e) for e in exposures_us]
        self.decide = decide
        self.position = -1  # index into captures of the capture under way
        self.taken: list[float] = []  # its states so far
        self.handed = 0  # its steps handed out so far
        self.ended = True  # its tail was handed out

    def start(self) -> list[Step]:
        return self._next_capture()

    def _next_capture(self) -> list[Step]:
        self.position += 1
        if self.position >= len(self.captures):
            return []
        first = float(self.plan.states_deg[0])
        i = self.captures[self.position]
        self.taken, self.ended = [first], False
        steps = (pose_head_steps(self.plan, i, self.exposures, first)
                 + state_steps(self.plan, i, self.exposures, 0, first, move=False))
        self.handed = len(steps)
        return steps

    def extend(self) -> list[Step]:
        if self.ended:
            return self._next_capture()
        i = self.captures[self.position]
        decision = self.decide(i)
        if decision["action"] in TAKES:
            state = float(decision["state_deg"])
            steps = state_steps(self.plan, i, self.exposures, len(self.taken), state)
            self.taken.append(state)
        else:
            steps = pose_tail_steps(i, self.exposures)
            self.ended = True
        self.handed += len(steps)
        return steps

    def forecast(self) -> list[Step]:
        """The steps still expected after those handed out."""
        out: list[Step] = []
        if 0 <= self.position < len(self.captures) and not self.ended:
            i = self.captures[self.position]
            out += adaptive_pose_steps(self.plan, i, self.exposures,
                                       adaptive_forecast_states(self.plan, self.taken))[self.handed:]
        for i in self.captures[max(0, self.position + 1):]:
            out += adaptive_pose_steps(self.plan, i, self.exposures,
                                       adaptive_forecast_states(self.plan, []))
        return out
