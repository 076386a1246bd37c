"""The open direction's scale of the hybrid solve (polrig.solve.hybrid, "The open direction's
scale"): at two states the prior's standard deviation along the direction ``w = s_a x s_b`` they
leave open is multiplied by ``a``. The compiled kernel equals a dense numpy posterior with
:func:`stretch_precision` (per-element and joint prior), the posterior's variance of each row along
``w`` is ``a^2`` times the unscaled one (the samples do not see ``w``) while the observed
directions' posterior mean and variance stay put where the prior is per element, ``a = 1`` is
the solve as it was bit for bit, and bad factors are one-line errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_hybrid_joint import _case, random_correlation, rows_of

from polrig.errors import ConfigError
from polrig.solve import reference as ref
from polrig.solve.hybrid import (
    joint_precision,
    open_direction,
    solve_hybrid,
    stretch_precision,
    unobserved_precision,
)


def _dense(s, meas, var, mean, p_of, c, yy, xx):
    """The dense posterior ``(N + P)^-1`` and its mean at one pixel, ``P = p_of(c, yy, xx)``."""
    design = ref.design_matrix(s)
    wt = 1.0 / var[:, c, :, yy, xx].reshape(-1)
    y = meas[:, c, :, yy, xx].reshape(-1)
    p = p_of(c, yy, xx)
    a = design.T @ (wt[:, None] * design) + p
    cov = np.linalg.inv(a)
    return cov @ (design.T @ (wt * y) + p @ mean[c, :, :, yy, xx].reshape(9)), cov


@pytest.mark.parametrize("joint", [False, True])
@pytest.mark.parametrize("factor", [0.3, 2.5])
def test_the_kernel_equals_a_dense_stretched_posterior(joint, factor):
    """The kernel with ``open_factor`` against numpy with :func:`stretch_precision` of the
    per-element or joint precision: mean and sigma to 1e-9."""
    rng, s, m, meas, var, mean, sd = _case(11, 2, h=3, w=9)
    k = random_correlation(rng) if joint else None
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                       prior_correlation=k, open_factor=factor)
    w = open_direction(s)

    def p_of(c, yy, xx):
        rows = rows_of(sd[c, :, :, yy, xx], s[0])
        p = joint_precision(rows, s[0], k) if joint else _block_diagonal(rows)
        return stretch_precision(p, w, factor)

    for c in range(2):
        for yy in range(3):
            for xx in range(9):
                x, cov = _dense(s, meas, var, mean, p_of, c, yy, xx)
                assert np.allclose(got.mueller[c, :, :, yy, xx].reshape(9), x, rtol=1e-9, atol=1e-9 * np.abs(x).max())
                assert np.allclose(got.sigma[c, :, :, yy, xx].reshape(9), np.sqrt(np.diag(cov)), rtol=1e-9)


def _block_diagonal(rows: np.ndarray) -> np.ndarray:
    p = np.zeros((9, 9))
    for r in range(3):
        p[3 * r:3 * r + 3, 3 * r:3 * r + 3] = rows[r]
    return p


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), log_factor=st.floats(-3.0, 3.0), joint=st.booleans())
def test_the_open_directions_posterior_variance_scales_by_the_factor_squared(seed, log_factor, joint):
    """Two states leave ``w`` unobserved in every row: its posterior variance is ``a^2`` times the
    unscaled solve's, for factors from 0.05 to 20 and any seen angle (dense numpy, from the
    kernel's own prior); with the per-element prior (rows independent, ``w`` orthogonal to the
    observed plane within each row) the observed directions' posterior is unchanged."""
    rng, s, m, meas, var, mean, sd = _case(seed, 2, h=1, w=2)
    a = float(np.exp(log_factor))
    k = random_correlation(rng) if joint else None
    w = open_direction(s)
    e = [np.kron(np.eye(3)[r], w) for r in range(3)]
    seen = s[0] / np.linalg.norm(s[0])
    for xx in range(2):
        rows = rows_of(sd[0, :, :, 0, xx], s[0])
        p = joint_precision(rows, s[0], k) if joint else _block_diagonal(rows)
        if not np.all(np.isfinite(p)):
            continue
        x1, c1 = _dense(s, meas, var, mean, lambda *_: p, 0, 0, xx)
        xa, ca = _dense(s, meas, var, mean, lambda *_: stretch_precision(p, w, a), 0, 0, xx)
        for r in range(3):
            assert np.isclose(e[r] @ ca @ e[r], a * a * (e[r] @ c1 @ e[r]), rtol=1e-7)
            if not joint:
                o = np.kron(np.eye(3)[r], seen)
                assert np.isclose(o @ ca @ o, o @ c1 @ o, rtol=1e-7)
                assert np.isclose(o @ xa, o @ x1, rtol=1e-7, atol=1e-9 * np.abs(x1).max())


@pytest.mark.parametrize("joint", [False, True])
def test_factor_one_is_the_solve_as_it_was(joint):
    rng, s, m, meas, var, mean, sd = _case(3, 2)
    k = random_correlation(rng) if joint else None
    a = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, prior_correlation=k)
    b = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, prior_correlation=k,
                     open_factor=1.0)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert x is None and y is None or np.array_equal(x, y)


def test_the_open_direction_is_orthogonal_to_both_states():
    _, s, *_ = _case(4, 2)
    w = open_direction(s)
    assert np.isclose(np.linalg.norm(w), 1.0) and np.allclose(s @ w, 0.0, atol=1e-12)
    p = unobserved_precision(np.ones(3), s[0])
    assert np.allclose(stretch_precision(np.kron(np.eye(3), p), w, 1.0), np.kron(np.eye(3), p))


@pytest.mark.parametrize("n, factor, seen, match", [
    (2, 0.0, 0, "finite and positive"), (2, np.nan, 0, "finite and positive"), (2, "x", 0, "a number"),
    (3, 2.0, 0, "two states"), (2, 2.0, None, "no seen state")])
def test_bad_open_factors_are_one_line_errors(n, factor, seen, match):
    rng, s, m, meas, var, mean, sd = _case(1, n, h=2, w=3)
    with pytest.raises(ConfigError, match=match) as err:
        solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=seen, open_factor=factor)
    assert "\n" not in str(err.value)


def test_parallel_states_have_no_single_open_direction():
    _, s, *_ = _case(1, 2)
    with pytest.raises(ConfigError, match="parallel"):
        open_direction(np.stack([s[0], 2 * s[0]]))
