"""Experimental design for the hybrid solve: how well a pixel's Mueller block is known, and
which polarizer state to measure next (the adaptive capture, :mod:`polrig.app.adaptive`).

**The posterior in closed form.** The hybrid solve (:mod:`polrig.solve.hybrid`) is linear and
Gaussian: per pixel and colour its posterior precision over ``vec(M)`` (row-major, ``9``) is

    A = P + sum_k kron(R^T W_k R, s_k s_k^T),

``P`` the prior's precision (:func:`prior_precision`: on the unobserved directions of the seen
state only, block diagonal over the rows, :func:`polrig.solve.hybrid.unobserved_precision`, or
with the calibration's joint prior the solve's :func:`polrig.solve.hybrid.joint_precision`),
``R`` the ``(4, 3)`` analyzer rows, ``W_k`` the inverse variances of state ``k``'s used samples
and ``s_k`` its incident Stokes vector (one DoFP frame adds ``D^T W D`` with
``D_j = kron(a_j, s_k)``, which is that Kronecker product: rank 3). The posterior covariance is
``A^-1``. It depends on the data only through the noise variances, so the covariance a
*candidate* state would leave, ``(A + kron(R^T W_c R, s_c s_c^T))^-1``, is known before it is
measured, with its variances predicted from the current estimate by the noise model
(:func:`predicted_variance`).

**The criterion**: Bayesian A-optimality (Chaloner and Verdinelli, "Bayesian experimental
design: a review", Statistical Science 10(3), 1995, section 2.1: minimise the trace of the
posterior covariance, for a linear-Gaussian model the expected posterior loss under squared
error), in the units of the stopping target: each block normalised by its own ``m00`` and
summed over the pixels that do not meet the target yet,

    J(s_c) = sum_{pixels, colours} tr(A_c^-1) / (9 m00^2)       (:func:`a_optimal_scores`).

**The choice** (:func:`choose_next`; the candidates: :func:`next_candidates`, the equiangular
set through the seen state first, then the grid less the states taken). ``J`` ranks the
candidates; what the operator waits for is the time to the target, and states differ in cost
(a 90 deg move takes the simulated stage 3 s more than a 30 deg one). So the capture takes

1. of the states predicted to bring the pose to its target (:func:`predicted_share`: the
   share of the object pixels whose relative sigma the candidate's posterior covariance puts
   at most the target), the one of least hardware time: the pose ends there;
2. else, at the pose's last allowed state, the least ``J``: the pose ends there too, short of
   the target, as well measured as one more state can;
3. else the greatest predicted reduction ``J_now - J(s_c)`` **per second** the state costs:
   its move and its frames, and the decision the stage waits for (:data:`DECISION_S`: a state
   near the last one is cheap to reach but still a state of the budget)
   (:func:`per_second_choice`): the cost-aware
   greedy rule of sequential design (Snoek, Larochelle and Adams, "Practical Bayesian
   optimization of machine learning algorithms", NeurIPS 2012, section 3.2: expected
   improvement per second).

Pixels already at target do not steer the choice (measuring them better does not bring the
stop nearer), and the normalisation by ``m00`` makes a dark pixel's variance count as much as a
bright one's relative to its signal, as the target does (:func:`relative_sigma`). A-optimality
rather than D-optimality (the log-determinant): the target is on element variances, whose sum
the trace is; the determinant rewards shrinking any direction, including ones the target
never looks at separately.

Measured against the least ``J`` alone (its choice before, nearest of equals) on the eight
held-out sets of :mod:`polrig.models.continuum` (16 samples each, 64x64, the same frames): with
up to 8 states (the most a capture allows) about the same number of states (-0.06..+0.13 on
average) in 19..33 % less hardware time per pose (0.05: 6.6..11.9 s against 8.3..16.9 s; 0.03:
9.2..14.8 against 12.2..21.8), -0.10..+0.76 dB matrix PSNR (-0.10..+0.06 on the pixels no state
clipped). Without the decision's time in the cost it saved a few points more (22..37 %) but lost
up to 1.3 dB, and the greatest gain per second for the last state too lost up to 2.6 dB. With up
to 4 states (the default), where the fourth is the last, only rule 1 acts: 0..0.14 s less on
those sets; on ``plastic_metal`` (the capture's 7.5 deg grid) it took 112.5 deg, 7.5 deg away,
where the least ``J`` took 202.5. After the equiangular set the least ``J`` was often a state
beside the seen one, on the far side of the stage (75 deg away).

Everything is per pixel and colour with numpy batches ``(..., 9, 9)``; no device, no file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from polrig.solve.hybrid import (
    joint_precision,
    observed_direction,
    plane_axis,
    unobserved_precision,
)

#: Most pixels the criterion is evaluated on (a regular subsample of the object pixels still
#: above target, every n-th in raster order): about 0.1 s per decision for 24 candidates and 3
#: colours.
DESIGN_PIXELS = 1024
#: What one more state costs beyond its move and frames, as the choice weighs it (s): the decision
#: the stage waits for, 1.2 s with the pose memo at the full colour sensor (``python -m benchmarks
#: adaptive``, its decision table). Without it, the greatest gain per second crept along the grid
#: (7.5 deg moves, each state cheap and of little gain) and spent the budget of states: on
#: ``plastic_metal`` at target 0.03, up to 8 states, 88.7..89.3 % at target against 92.0..92.2 %.
DECISION_S = 1.2
#: The first states of an adaptive pose, as offsets from the seen state's polarizer angle (deg):
#: the equiangular set through it (:func:`next_candidates`).
EQUIANGULAR_OFFSETS_DEG = (0.0, 60.0, 120.0)

__all__ = ["DECISION_S", "DESIGN_PIXELS", "EQUIANGULAR_OFFSETS_DEG", "DesignScores", "a_optimal_next", "a_optimal_scores",
           "choose_next", "data_precision", "next_candidates", "per_second_choice", "predicted_share",
           "predicted_variance", "prior_precision", "relative_sigma", "same_polarizer_state", "share_at_target",
           "state_precision"]


def relative_sigma(sigma: np.ndarray, mueller: np.ndarray, colours: np.ndarray | None = None) -> np.ndarray:
    """How well each pixel's block is known relative to its brightness: the RMS of the nine
    elements' standard deviations over ``m00``, ``sqrt(sum sigma_rc^2 / 9) / m00``, the worst
    (largest) over the colours. ``sigma``, ``mueller``: ``(C, 3, 3, H, W)``; ``colours``
    ``(C, H, W)`` bool, the colours that count per pixel (default all: a colour below the noise
    floor in the frame, all noise, is left out by the callers); returns ``(H, W)`` float64,
    ``inf`` where ``m00 <= 0`` or anything is not finite in a colour that counts, or no colour
    counts.

    Dimensionless: the RMS sigma of the block normalised to ``m00 = 1`` (its elements are the
    diattenuation, polarizance and linear-depolarisation terms in those units, so 0.01 reads
    as "known to about 0.01 per element"), independent of exposure, light level and albedo, as
    a target in DN is not (a DN target is met by bright pixels at once and by dark ones
    never)."""
    m00 = np.asarray(mueller)[:, 0, 0].astype(np.float64)
    rms = np.sqrt(_sum_of_squares(sigma) / 9.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where((m00 > 0) & np.isfinite(m00) & np.isfinite(rms), rms / m00, np.inf)
    if colours is None:
        return np.max(rel, axis=0)
    use = np.asarray(colours, bool)
    return np.where(use.any(axis=0), np.max(np.where(use, rel, 0.0), axis=0), np.inf)


def _sum_of_squares(sigma: np.ndarray) -> np.ndarray:
    """``sum_rc sigma_rc^2`` ``(C, H, W)`` float64 of ``sigma`` ``(C, 3, 3, H, W)``: the nine
    squares added in row-major order, one element plane at a time in float64. These are the
    numbers, bit for bit (tested), of ``np.sum(s * s, axis=(1, 2))`` with ``s`` ``sigma`` in
    float64, which adds the nine planes in that order when they are C-contiguous planes of more
    than one pixel; without its two full-size float64 copies (at the full colour sensor's grid
    about a third of the time). Other inputs (one pixel per plane: numpy then sums the nine
    pairwise; not C-contiguous) take that expression itself."""
    sig = np.asarray(sigma)
    if not sig.flags.c_contiguous or math.prod(sig.shape[3:]) < 2:
        s64 = np.asarray(sig, np.float64)
        return np.sum(s64 * s64, axis=(1, 2))
    total = None
    for r in range(3):
        for c in range(3):
            square = sig[:, r, c].astype(np.float64)
            square *= square
            if total is None:
                total = square
            else:
                total += square
    return total


def share_at_target(rel: np.ndarray, pixels: np.ndarray, target: float) -> tuple[float, np.ndarray]:
    """``(share, met)``: the share of ``pixels`` (``(H, W)`` bool) whose relative sigma ``rel``
    (:func:`relative_sigma`) is at most ``target``, and the met pixels; 0 when there are none."""
    met = np.asarray(pixels, bool) & (np.asarray(rel) <= float(target))
    n = int(np.count_nonzero(pixels))
    return (float(np.count_nonzero(met)) / n if n else 0.0), met


def state_precision(rows: np.ndarray, weights: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The precision one DoFP frame of incident state ``s`` ``(3,)`` adds over ``vec(M)``:
    ``kron(R^T W R, s s^T)`` ``(..., 9, 9)`` for analyzer rows ``rows`` ``(..., 4, 3)`` (or
    ``(4, 3)``) and sample weights ``weights`` ``(..., 4)`` (inverse variances; 0 for an unused
    sample)."""
    r = np.asarray(rows, np.float64)
    w = np.asarray(weights, np.float64)
    rtwr = np.einsum("...ja,...j,...jb->...ab", r, w, r)
    ss = np.outer(s, s)
    return np.einsum("...ab,cd->...acbd", rtwr, ss).reshape(*rtwr.shape[:-2], 9, 9)


def data_precision(rows: np.ndarray, variance: np.ndarray, valid: np.ndarray,
                   s: np.ndarray) -> np.ndarray:
    """:func:`state_precision` of measured samples: ``variance`` ``(..., 4)`` (DN^2), ``valid``
    ``(..., 4)`` bool; a sample that is not valid, or whose variance is not a finite positive
    number, adds nothing."""
    v = np.asarray(variance, np.float64)
    ok = np.asarray(valid, bool) & np.isfinite(v) & (v > 0)
    w = np.where(ok, 1.0 / np.where(ok, v, 1.0), 0.0)
    return state_precision(rows, w, s)


def prior_precision(prior_sigma: np.ndarray, s_seen: np.ndarray,
                    correlation: np.ndarray | None = None) -> np.ndarray:
    """The hybrid solve's prior precision ``(..., 9, 9)`` for per-element sigma ``prior_sigma``
    ``(..., 3, 3)``: block diagonal over the rows, each the unobserved-direction precision of
    the seen state ``s_seen`` (:func:`polrig.solve.hybrid.unobserved_precision`; the seen
    frame's own samples enter through :func:`data_precision`, never twice). With the joint
    prior's ``correlation`` ``(6, 6)`` (the calibration's ``K``, as the solve takes it), its
    precision :func:`polrig.solve.hybrid.joint_precision` where the solve uses it: a seen state
    with an axis and a block whose rows are positive on the plane (every element with a prior);
    elsewhere the per-element blocks, as the solve does."""
    sig = np.asarray(prior_sigma, np.float64)
    blocks = unobserved_precision(sig, s_seen)  # (..., 3 rows, 3, 3)
    out = np.zeros((*sig.shape[:-2], 9, 9))
    for r in range(3):
        out[..., 3 * r:3 * r + 3, 3 * r:3 * r + 3] = blocks[..., r, :, :]
    if correlation is None or plane_axis(observed_direction(s_seen)) is None:
        return out
    joint = joint_precision(blocks, s_seen, correlation)
    return np.where(np.all(np.isfinite(joint), axis=(-2, -1), keepdims=True), joint, out)


def next_candidates(taken_deg: Sequence[float], grid_deg: Sequence[float]) -> list[float]:
    """The polarizer angles (deg, in ``[0, 180)``) the adaptive capture chooses its next state
    among, after the states ``taken_deg`` (stage angles, the seen state first): while fewer than
    three are taken, those of the **equiangular set through the seen state**
    (:data:`EQUIANGULAR_OFFSETS_DEG`) not taken yet; then every angle of ``grid_deg`` not taken
    yet (more frames of a state are the plan's ``frames_per_state``: a state taken again would
    cost no move, and the choice per second, :func:`choose_next`, would repeat it).

    The first three states are nested in the design that is best for three states: with equal
    noise per sample, three fully polarized states determine the block with the least summed
    variance exactly when they are 60 deg apart (``tr (S^T S)^-1 = 5 / 3``, the least possible,
    ``tests/test_state_count_bound.py``), and the set through the seen state is reached with two
    60 deg moves. The greedy A-optimal choice over the whole grid goes to the seen state's
    orthogonal, 90 deg, the best pair, from which no third state completes an equiangular set:
    on the eight held-out sets of :mod:`polrig.models.continuum` (12 samples each, target 0.05)
    it took the same number of states 0.5..2.7 s per pose slower and 0.1..1.7 dB worse in
    matrix PSNR, better only where two states sufficed on the terrains (0.7-0.8 dB: 0/90 is the
    better pair). Which of the two comes first, and the states after the third,
    :func:`choose_next` decides."""
    taken = [float(t) % 180.0 for t in taken_deg]
    if not taken:
        raise ValueError("the seen state comes first: no state taken yet")
    new = lambda angles: [a for a in angles if not any(same_polarizer_state(a, t) for t in taken)]  # noqa: E731
    if len(taken) < len(EQUIANGULAR_OFFSETS_DEG):
        left = new([(taken[0] + o) % 180.0 for o in EQUIANGULAR_OFFSETS_DEG[1:]])
        if left:
            return left
    return new([float(a) % 180.0 for a in grid_deg])


def same_polarizer_state(a: float, b: float, tol_deg: float = 1e-6) -> bool:
    """Whether polarizer angles ``a`` and ``b`` (deg) are one state, within ``tol_deg`` (a linear
    polarizer repeats every 180 deg)."""
    d = (a - b) % 180.0
    return min(d, 180.0 - d) <= tol_deg


def predicted_variance(mueller: np.ndarray, rows: np.ndarray, s: np.ndarray, per_dn: float,
                       offset_dn2: float) -> np.ndarray:
    """The variance ``(..., 4)`` of the four samples a frame of state ``s`` ``(3,)`` would give a
    block ``mueller`` ``(..., 3, 3)`` (the current estimate) under the linear noise model
    ``max(I, 0) * per_dn + offset_dn2`` (:meth:`polrig.sensor.noise.SensorModel.variance_terms`,
    its frame averaging included), ``I_j = a_j^T M s``."""
    m = np.asarray(mueller, np.float64)
    intensity = np.einsum("...ja,...ab,b->...j", np.asarray(rows, np.float64), m, np.asarray(s, np.float64))
    return np.clip(intensity, 0.0, None) * float(per_dn) + float(offset_dn2)


def per_second_choice(j_now: float, j: np.ndarray, cost_s: Sequence[float]) -> int:
    """The index of the candidate of greatest predicted gain per second,
    ``(j_now - j[c]) / cost_s[c]`` (module docstring, *Per second*): ``j_now``, ``j`` ``(K,)``
    the criterion now and after each candidate (:func:`a_optimal_next`), ``cost_s`` ``(K,)`` each
    candidate's hardware time, seconds (:func:`polrig.acquisition.plan.state_time_s`; floored at
    1 ms, so a camera without exposure control and an instant stage still rank). Of equal gains
    per second, the cheapest, then the first."""
    gain = np.maximum(float(j_now) - np.asarray(j, np.float64), 0.0)
    cost = np.maximum(np.asarray(cost_s, np.float64), 1e-3)
    if gain.shape != cost.shape or gain.ndim != 1 or not len(gain):
        raise ValueError(f"one cost per candidate: {gain.shape} criteria, {cost.shape} costs")
    rate = gain / cost
    best = np.flatnonzero(rate >= np.max(rate))
    return int(min(best, key=lambda c: (cost[c], c)))


class DesignScores(NamedTuple):
    """The A-optimal criterion of ``P`` pixel-colour blocks now and after each of ``K``
    candidate states (:func:`a_optimal_scores`): ``criterion`` ``J_now``, ``predicted`` ``(K,)``
    the ``J`` each candidate leaves, ``trace`` ``(K, P)`` each block's posterior covariance trace
    after each candidate (what :func:`predicted_share` reads the stopping rule from)."""

    criterion: float
    predicted: np.ndarray
    trace: np.ndarray


def a_optimal_scores(precision: np.ndarray, m00: np.ndarray, candidates: list[np.ndarray]) -> DesignScores:
    """The A-optimal criterion now and after each candidate state.

    ``precision``: the current posterior precision ``(P, 9, 9)`` of ``P`` pixel-colour blocks;
    ``m00`` ``(P,)`` their current ``m00`` (> 0); ``candidates``: for each candidate state the
    precision its frame would add ``(P, 9, 9)`` (:func:`state_precision` with
    :func:`predicted_variance`). ``J = sum_p tr(cov_p) / (9 m00_p^2)`` (:class:`DesignScores`). A
    block whose precision is singular counts its pseudo-inverse's trace (it adds what its
    determined directions know)."""
    a = np.asarray(precision, np.float64)
    norm = 1.0 / (9.0 * np.asarray(m00, np.float64) ** 2)

    def traces(prec: np.ndarray) -> np.ndarray:
        try:
            return np.trace(np.linalg.inv(prec), axis1=-2, axis2=-1)
        except np.linalg.LinAlgError:
            return np.trace(np.linalg.pinv(prec, hermitian=True), axis1=-2, axis2=-1)

    after = np.array([traces(a + c) for c in candidates]).reshape(len(candidates), len(a))
    return DesignScores(float(np.sum(traces(a) * norm)), np.sum(after * norm, axis=1), after)


def predicted_share(trace: np.ndarray, m00: np.ndarray, colours: np.ndarray, target: float,
                    share_now: float, above_share: float) -> np.ndarray:
    """The share of the object pixels each candidate state is predicted to bring to the target:
    ``share_now`` (those at it already) plus ``above_share`` (those above it, whose design
    pixels these are, as a share of the object) times the share of the design pixels whose
    predicted relative sigma (:func:`relative_sigma`'s, from the posterior covariance the
    candidate leaves) is at most ``target``.

    ``trace`` ``(K, N, C)``: each design pixel and colour's posterior covariance trace after each
    candidate (:attr:`DesignScores.trace`, its blocks in pixel-then-colour order); ``m00``
    ``(N, C)`` the current estimate's (> 0); ``colours`` ``(N, C)`` bool, the colours that count
    (a pixel with none counts as not meeting it). Returns ``(K,)``."""
    tr = np.asarray(trace, np.float64)
    use = np.asarray(colours, bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.sqrt(np.maximum(tr, 0.0) / 9.0) / np.asarray(m00, np.float64)
    rel = np.where(np.isfinite(rel), rel, np.inf)
    worst = np.where(use.any(axis=-1), np.max(np.where(use, rel, 0.0), axis=-1), np.inf)  # (K, N)
    met = np.mean(worst <= float(target), axis=-1) if worst.shape[-1] else np.zeros(len(tr))
    return float(share_now) + float(above_share) * met


def choose_next(scores: DesignScores, cost_s: Sequence[float], share_after: np.ndarray,
                target_share: float, last: bool) -> int:
    """The index of the candidate state to take (module docstring, *The choice*):

    1. of the candidates predicted to bring the pose to its target (``share_after`` ``(K,)``, from
       :func:`predicted_share`, at least ``target_share``), the one of least hardware time
       ``cost_s`` ``(K,)`` (seconds, :func:`polrig.acquisition.plan.state_time_s`): the pose
       ends there;
    2. else, when this is the pose's last allowed state (``last``), the least criterion: the
       pose ends there too, short of its target, as well measured as one more state can;
    3. else the greatest predicted reduction of the criterion per second
       (:func:`per_second_choice`): the way to the target that costs least time.

    Ties: the cheapest, then the first."""
    j = np.asarray(scores.predicted, np.float64)
    cost = np.asarray(cost_s, np.float64)
    share = np.asarray(share_after, np.float64)
    if not (j.shape == cost.shape == share.shape) or j.ndim != 1 or not len(j):
        raise ValueError(f"one cost and share per candidate: {j.shape} criteria, {cost.shape} costs, "
                         f"{share.shape} shares")
    finish = np.flatnonzero(share >= float(target_share))
    if len(finish):
        return int(min(finish, key=lambda c: (cost[c], -share[c], j[c], c)))
    if last:
        return int(min(np.flatnonzero(j <= np.min(j)), key=lambda c: (cost[c], c)))
    return per_second_choice(scores.criterion, j, cost)


def a_optimal_next(prior_sigma: np.ndarray, s_seen: np.ndarray, measured: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                   estimate: np.ndarray, candidates: np.ndarray, per_dn: float, offset_dn2: float,
                   rows: np.ndarray | None = None, correlation: np.ndarray | None = None
                   ) -> DesignScores:
    """The A-optimal criterion now and after each candidate state, for ``P`` design pixels.

    ``prior_sigma`` ``(P, C, 3, 3)`` (the network's sigma), ``s_seen`` ``(3,)`` the seen state;
    ``measured``: per state taken ``(s (3,), variance (P, C, 4), valid (P, C, 4))``; ``estimate``
    ``(P, C, 3, 3)`` the current posterior mean (its ``m00`` normalises, its samples' predicted
    variance weighs each candidate); ``candidates`` ``(K, 3)`` incident states; ``per_dn``,
    ``offset_dn2`` the noise model's linear terms for one state's frames; ``rows`` the ``(4, 3)``
    analyzer rows (default ideal); ``correlation`` the joint prior's ``K`` ``(6, 6)`` where the
    solve uses one (:func:`prior_precision`). Returns :func:`a_optimal_scores`'s
    :class:`DesignScores` (its blocks in pixel-then-colour order: ``trace`` ``(K, P * C)``)."""
    from polrig.sensor.stokes import ideal_analyzer_matrix

    r = ideal_analyzer_matrix() if rows is None else np.asarray(rows, np.float64)
    prec = prior_precision(prior_sigma, s_seen, correlation)
    for s, var, valid in measured:
        prec = prec + data_precision(r, var, valid, s)
    est = np.asarray(estimate, np.float64)
    added = [state_precision(r, 1.0 / predicted_variance(est, r, s_c, per_dn, offset_dn2), s_c).reshape(-1, 9, 9)
             for s_c in np.asarray(candidates, np.float64)]
    return a_optimal_scores(prec.reshape(-1, 9, 9), est[..., 0, 0].reshape(-1), added)
