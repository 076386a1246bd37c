"""The adaptive capture's criterion (:mod:`polrig.solve.design`) against closed forms: a frame's
precision is the design matrix's ``D^T W D``, the prior's is the hybrid solve's per-row block,
the relative sigma and the A-optimal criterion are what their formulas say, and the criterion
prefers the state that completes a set to one already measured."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve.design import (
    DesignScores,
    a_optimal_scores,
    choose_next,
    data_precision,
    next_candidates,
    per_second_choice,
    predicted_share,
    predicted_variance,
    prior_precision,
    relative_sigma,
    state_precision,
)
from polrig.solve.hybrid import unobserved_precision
from polrig.solve.reference import design_matrix

RNG = np.random.default_rng(3)
R = ideal_analyzer_matrix()


def stokes(deg):
    return polarizer_stokes(np.deg2rad([deg]), intensity=1.0)[0]


@pytest.mark.parametrize("deg", [0.0, 30.0, 112.5])
def test_a_frames_precision_is_its_design_matrix_normal_matrix(deg):
    s = stokes(deg)
    w = RNG.uniform(0.5, 2.0, 4)
    d = design_matrix(s[None], R)  # (4, 9) rows kron(a_j, s)
    np.testing.assert_allclose(state_precision(R, w, s), d.T @ np.diag(w) @ d, atol=1e-12)
    valid = np.array([True, False, True, True])
    var = 1.0 / w
    np.testing.assert_allclose(data_precision(R, var, valid, s), d.T @ np.diag(w * valid) @ d, atol=1e-12)
    assert np.linalg.matrix_rank(state_precision(R, w, s)) == 3  # one frame observes M s only


def test_the_prior_precision_is_the_hybrid_solves_row_blocks():
    sigma = RNG.uniform(0.01, 0.2, (5, 3, 3))
    s = stokes(20.0)
    p = prior_precision(sigma, s)
    blocks = unobserved_precision(sigma, s)
    for r in range(3):
        np.testing.assert_allclose(p[:, 3 * r:3 * r + 3, 3 * r:3 * r + 3], blocks[:, r])
        for q in range(3):
            if q != r:
                assert not p[:, 3 * r:3 * r + 3, 3 * q:3 * q + 3].any()
    # the seen state's own direction is left to its frame: kron(e_r, s) is in the null space
    u = s / np.linalg.norm(s)
    for r in range(3):
        v = np.kron(np.eye(3)[r], u)
        np.testing.assert_allclose(p @ v, 0.0, atol=1e-9)


def test_relative_sigma_is_the_rms_sigma_over_m00_worst_colour():
    m = RNG.uniform(0.1, 1.0, (3, 3, 3, 2, 2))
    sig = RNG.uniform(0.0, 0.05, (3, 3, 3, 2, 2))
    m[1, 0, 0, 0, 1] = -1.0  # a colour with m00 <= 0: never at target
    rel = relative_sigma(sig, m)
    expect = np.sqrt((sig ** 2).mean(axis=(1, 2))) / m[:, 0, 0]
    expect[1, 0, 1] = np.inf
    np.testing.assert_allclose(rel, expect.max(axis=0))
    assert rel[0, 1] == np.inf
    colours = np.ones((3, 2, 2), bool)
    colours[1, 0, 1] = False  # the colour with m00 <= 0 left out there (dark in the frame)
    colours[:, 1, 1] = False  # no colour counts: never at target
    got = relative_sigma(sig, m, colours)
    np.testing.assert_allclose(got[0, 1], expect[[0, 2], 0, 1].max())
    assert got[1, 1] == np.inf
    np.testing.assert_allclose(got[0, 0], rel[0, 0])


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([np.float16, np.float32, np.float64]), st.integers(1, 3), st.integers(1, 6),
       st.integers(1, 7), st.floats(-40, 40), st.integers(0, 2 ** 32 - 1))
def test_relative_sigma_sums_the_squares_as_the_float64_array_sum_bit_for_bit(dtype, c, h, w, exp10, seed):
    """The adaptive decisions are recorded and replayed bit for bit: relative_sigma's plane-wise
    sum of squares gives the numbers of the float64 array sum it replaced, at every magnitude
    (extremes that overflow to inf, underflow, NaN and inf included)."""
    rng = np.random.default_rng(seed)
    with np.errstate(over="ignore"):  # the extremes overflow to inf in the narrow dtypes on purpose
        sig = (rng.standard_normal((c, 3, 3, h, w)) * 10.0 ** exp10).astype(dtype)
    sig.flat[rng.integers(0, sig.size)] = rng.choice([np.inf, np.nan, 0.0, 1e-300])
    m = rng.uniform(-0.2, 1.0, (c, 3, 3, h, w)).astype(dtype)
    with np.errstate(all="ignore"):
        s64 = np.asarray(sig, np.float64)
        rms = np.sqrt(np.sum(s64 * s64, axis=(1, 2)) / 9.0)
        m00 = np.asarray(m, np.float64)[:, 0, 0]
        rel = np.where((m00 > 0) & np.isfinite(m00) & np.isfinite(rms), rms / m00, np.inf)
        got = relative_sigma(sig, m)
    assert got.dtype == np.float64 and np.array_equal(got, np.max(rel, axis=0))


def test_the_criterion_is_the_summed_relative_trace_and_prefers_completing_the_set():
    m00 = np.array([2.0, 0.5])
    s0, s90 = stokes(0.0), stokes(90.0)
    prior = prior_precision(np.full((2, 3, 3), 0.3), s0)
    prec = prior + data_precision(R, np.full((2, 4), 1e-4), np.ones((2, 4), bool), s0)
    j_now = a_optimal_scores(prec, m00, []).criterion
    expect = sum(np.trace(np.linalg.inv(prec[p])) / (9 * m00[p] ** 2) for p in range(2))
    assert j_now == pytest.approx(expect, rel=1e-12)
    mueller = np.tile(np.diag([1.0, 0.4, 0.4]), (2, 1, 1))
    cands = []
    for deg in (0.0, 45.0, 90.0):
        s = stokes(deg)
        var = predicted_variance(mueller, R, s, per_dn=1e-4, offset_dn2=1e-6)
        cands.append(state_precision(R, 1.0 / var, s))
    scores = a_optimal_scores(prec, m00, cands)
    j = scores.predicted
    for k, c in enumerate(cands):  # the blocks' traces it sums
        np.testing.assert_allclose(scores.trace[k], [np.trace(np.linalg.inv(prec[p] + c[p])) for p in range(2)],
                                   rtol=1e-12)
    assert np.all(j < j_now)  # any frame adds information
    assert j[1] < j[0]  # 45 deg observes directions 0 deg (already measured) leaves open
    assert j[2] < j[0]  # 90 deg observes s1 with the other sign: the s0 and s1 columns apart
    np.testing.assert_allclose(predicted_variance(mueller[0], R, s90, 2.0, 3.0),
                               np.clip(R @ mueller[0] @ s90, 0, None) * 2.0 + 3.0)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_designs_posterior_is_the_hybrid_solves_with_the_joint_prior(n):
    """The criterion's covariance under the joint prior, ``(prior_precision(sigma, s0, K) +
    sum_k data_precision)^-1``, has the compiled hybrid solve's sigma (same ``K``) as the square
    roots of its diagonal, to 1e-9; ``K = I`` is the per-element precision (to 1e-9)."""
    from test_hybrid_joint import _case, random_correlation

    from polrig.solve.hybrid import solve_hybrid

    rng, s, _, meas, var, mean, sd = _case(40 + n, n, h=2, w=5)
    k = random_correlation(rng)
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                       prior_correlation=k)
    px = lambda a: np.moveaxis(a, (-2, -1), (0, 1)).reshape(-1, *a.shape[:-2])  # noqa: E731  (P, ...)
    sig = px(sd).reshape(-1, 3, 3)
    prec = prior_precision(sig, s[0], k)
    for j in range(n):
        v = px(var[j]).reshape(-1, 4)  # (P*C, 4)
        prec = prec + data_precision(R, v, np.ones(v.shape, bool), s[j])
    want = np.sqrt(np.diagonal(np.linalg.inv(prec), axis1=-2, axis2=-1))
    np.testing.assert_allclose(px(got.sigma).reshape(-1, 9), want, rtol=1e-9)
    np.testing.assert_allclose(prior_precision(sig, s[0], np.eye(6)), prior_precision(sig, s[0]), rtol=1e-9,
                               atol=1e-9 * np.abs(prior_precision(sig, s[0])).max())


def test_the_first_three_states_are_the_equiangular_set_through_the_seen_one():
    """:func:`next_candidates`: the seen angle +60 and +120 deg (mod 180, whatever stage angle
    took a state), then the grid less the states taken."""
    grid = (0.0, 7.5, 90.0)
    assert next_candidates([0.0], grid) == [60.0, 120.0]
    assert next_candidates([0.0, 120.0], grid) == [60.0]
    assert next_candidates([0.0, -60.0], grid) == [60.0]  # -60 is 120: the same polarizer state
    assert next_candidates([10.0, 250.0], grid) == [130.0]  # 250 is 70 = 10 + 60
    assert next_candidates([0.0, 60.0, 300.0], grid) == [7.5, 90.0]  # 0 taken: not again
    assert next_candidates([0.0, 90.0], grid) == [60.0, 120.0]  # a state off the set: the set still first
    assert next_candidates([0.0, 90.0, 60.0], grid) == [7.5]  # three taken: the grid less them
    assert next_candidates([7.5, 67.5, 307.5], grid) == [0.0, 90.0]  # 307.5 is 127.5
    with pytest.raises(ValueError, match="seen state"):
        next_candidates([], grid)


def test_the_choice_is_the_greatest_gain_per_second_and_of_equal_ones_the_cheapest():
    assert per_second_choice(10.0, np.array([5.0, 8.0]), [4.0, 1.0]) == 1  # 1.25 against 2 per second
    assert per_second_choice(10.0, np.array([5.0, 8.0]), [1.0, 1.0]) == 0  # equal cost: the least criterion
    assert per_second_choice(10.0, np.array([8.0, 6.0]), [1.0, 2.0]) == 0  # equal rates: the cheaper
    assert per_second_choice(10.0, np.array([8.0, 8.0]), [1.0, 1.0]) == 0  # all equal: the first
    assert per_second_choice(10.0, np.array([9.0, 8.0]), [0.0, 0.0]) == 1  # no cost: floored, gains rank
    with pytest.raises(ValueError, match="one cost per candidate"):
        per_second_choice(1.0, np.array([0.5, 0.4]), [1.0])


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 1e6), st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(1e-3, 1e3)), min_size=1, max_size=24))
def test_no_candidate_gains_more_per_second_than_the_one_chosen(j_now, rows):
    frac, cost = (np.array(v) for v in zip(*rows))
    j = j_now * frac  # criteria at most the current one
    c = per_second_choice(j_now, j, cost)
    rate = (j_now - j) / cost
    assert np.all(rate <= rate[c])
    assert np.all(cost[rate == rate[c]] >= cost[c])


def test_the_predicted_share_counts_the_design_pixels_whose_worst_colour_meets_the_target():
    """:func:`predicted_share`: relative sigma ``sqrt(tr / 9) / m00`` per colour, the worst of
    the colours that count, scaled from the design pixels to the pixels above target."""
    m00 = np.array([[1.0, 2.0], [1.0, 1.0], [4.0, 4.0]])  # 3 design pixels, 2 colours
    colours = np.array([[True, True], [True, False], [False, False]])
    # relative sigma 0.1 is tr = 9 * (0.1 m00)^2
    tr = 9 * (np.array([[[0.1, 0.1], [0.1, 0.5]], [[0.1, 0.2], [0.2, 0.2]]])[:, :2] * m00[:2]) ** 2
    tr = np.concatenate([tr, np.zeros((2, 1, 2))], axis=1)  # the third pixel: no colour counts
    got = predicted_share(tr, m00, colours, 0.1 + 1e-12, share_now=0.5, above_share=0.3)
    # candidate 0: pixel 0 meets (0.1, 0.1), pixel 1 meets (0.1; its 0.5 does not count); candidate 1: neither
    np.testing.assert_allclose(got, [0.5 + 0.3 * 2 / 3, 0.5])
    assert predicted_share(np.full((1, 2, 1), np.inf), np.ones((2, 1)), np.ones((2, 1), bool), 1.0, 0.2, 0.8) == [0.2]


def test_the_choice_finishes_cheapest_then_spends_the_last_state_on_accuracy_else_gains_per_second():
    scores = DesignScores(10.0, np.array([4.0, 6.0, 9.0]), np.zeros((3, 1)))
    cost = [3.0, 2.0, 0.5]  # gain per second 2, 2, 2: the cheapest of equal rates
    # 1. some candidates finish the pose: the cheapest of them
    assert choose_next(scores, cost, np.array([0.96, 0.97, 0.90]), 0.95, last=False) == 1
    assert choose_next(scores, cost, np.array([0.96, 0.90, 0.90]), 0.95, last=True) == 0
    # 2. none does, and this is the last state: the least criterion
    assert choose_next(scores, cost, np.array([0.9, 0.9, 0.9]), 0.95, last=True) == 0
    # 3. none does, more may follow: the greatest gain per second
    assert choose_next(scores, cost, np.array([0.9, 0.9, 0.9]), 0.95, last=False) == 2
    assert choose_next(scores, [3.0, 2.0, 5.0], np.array([0.9, 0.9, 0.9]), 0.95, last=False) == 1  # 2 / 3 / 0.2
    with pytest.raises(ValueError, match="one cost and share per candidate"):
        choose_next(scores, cost[:2], np.array([0.9, 0.9, 0.9]), 0.95, last=False)
