"""The prior's scale from the innovations (:mod:`polrig.solve.prior_scale`): it recovers the
scale of a prior whose errors are drawn at a known multiple of its sigma, it takes the seen
frame's measurement for the direction that frame observes, and its quantile equation is
homogeneous in the errors' size."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.solve.hybrid import observed_direction, unobserved_precision
from polrig.solve.prior_scale import (
    MIN_INNOVATIONS,
    SCALE_LIMITS,
    innovation_scale,
    innovations,
    plane_basis,
    prior_scale,
)
from polrig.solve.reference import forward_measurements

SIDE = 40


def _state(theta_deg: float) -> np.ndarray:
    t = np.radians(2 * theta_deg)
    return np.array([1.0, np.cos(t), np.sin(t)])


def _scene(rng, k: float, theta_deg: float = 20.0, offsets=(0, 90), along_u: float = 0.0, noise: float = 1e-4):
    """A prior ``(mean, sigma)`` ``(1, 3, 3, SIDE, SIDE)``, a truth whose rows differ from the mean
    by ``k`` times a draw from the hybrid's plane covariance (and ``along_u`` times sigma along
    the seen direction), and the states' noisy samples."""
    mean = np.zeros((1, 3, 3, SIDE, SIDE))
    mean[0, 0, 0] = 1.0
    mean[0, 1, 1] = mean[0, 2, 2] = 0.3
    mean[0, 0, 1] = 0.1
    sigma = 0.02 * (1.0 + rng.random((1, 3, 3, SIDE, SIDE)))
    states = np.stack([_state(theta_deg + o) for o in offsets])
    u = observed_direction(states[0])
    basis = plane_basis(u)
    rows = np.moveaxis(sigma, 2, -1)  # (1, 3, H, W, 3)
    m2 = np.einsum("ai,...ab,bj->...ij", basis, unobserved_precision(rows, states[0]), basis)
    chol = np.linalg.cholesky(np.linalg.inv(m2))  # the plane's covariance
    z = rng.standard_normal(chol.shape[:-1])
    plane = np.einsum("ai,...i->...a", basis, np.einsum("...ij,...j->...i", chol, z))  # (1, 3, H, W, 3)
    sd_u = np.sqrt(np.sum(rows**2 * u**2, axis=-1))[..., None]  # the prior's sigma along u
    along = along_u * sd_u * rng.standard_normal(rows.shape[:-1] + (1,)) * u
    truth = mean + np.moveaxis(k * plane + along, -1, 2)
    clean = forward_measurements(truth, states)
    var = np.full(clean.shape, noise**2)
    measured = clean + noise * rng.standard_normal(clean.shape)
    return states, measured, var, mean, sigma


@pytest.mark.parametrize("k", [0.4, 1.0, 2.5])
@pytest.mark.parametrize("offsets", [(0, 90), (0, 60, 120), (0, 45, 90, 135)])
def test_the_scale_of_a_prior_drawn_at_k_times_its_sigma_is_k(k, offsets):
    rng = np.random.default_rng(int(10 * k) + len(offsets))
    states, measured, var, mean, sigma = _scene(rng, k, offsets=offsets)
    d, p, n = innovations(states, measured, var, None, mean, sigma, 0)
    assert len(d) == 3 * SIDE * SIDE * (len(offsets) - 1)
    assert innovation_scale(d, p, n) == pytest.approx(k, rel=0.08)
    scale = prior_scale(states, measured, var, None, mean, sigma, 0, shrink=0.5)
    assert scale.factor == pytest.approx(np.sqrt(k), rel=0.05)
    assert scale.raw ** 0.5 == scale.factor and scale.innovations == len(d) and scale.method == "innovations"


def test_the_seen_frame_answers_for_the_direction_it_observes():
    """A network wrong only along the seen direction leaves the other states nothing to find
    beyond noise: the scale goes to its lower limit. Counting the prior there instead (as if the
    frame had not been seen) would find errors of about its sigma. (States 60 and 120 deg from
    the seen one: a state at 90 deg is orthogonal to it and sees nothing along it.)"""
    rng = np.random.default_rng(3)
    states, measured, var, mean, sigma = _scene(rng, 0.0, offsets=(0, 60, 120), along_u=3.0)
    assert innovation_scale(*innovations(states, measured, var, None, mean, sigma, 0)) == pytest.approx(
        SCALE_LIMITS[0], rel=1e-3)


def test_one_state_or_too_few_innovations_leave_the_prior_as_it_is():
    rng = np.random.default_rng(4)
    states, measured, var, mean, sigma = _scene(rng, 2.0)
    assert prior_scale(states[:1], measured[:1], var[:1], None, mean, sigma, 0).factor == 1.0
    d, p, n = innovations(states, measured, var, None, mean, sigma, 0)
    assert innovation_scale(d[: MIN_INNOVATIONS - 1], p[: MIN_INNOVATIONS - 1], n[: MIN_INNOVATIONS - 1]) == 1.0
    # elements without a prior and unusable samples drop out
    sigma_none = sigma.copy()
    sigma_none[0, 1, 2] = np.inf
    valid = np.ones(measured.shape, bool)
    valid[1, 0, 2, :SIDE // 2] = False
    d2, _, _ = innovations(states, measured, var, valid, mean, sigma_none, 0)
    assert len(d2) == 2 * (SIDE * SIDE // 2)  # row 1 gone; half the pixels of rows 0 and 2


def test_only_the_objects_pixels_count_each_as_it_would_alone():
    """Pixels without a prior (off the network's object: no finite positive sigma in any row)
    give nothing and their samples, even NaN, change nothing; every other pixel's values are
    those it gives as a 1x1 image of its own, in the order state, colour, row, pixel in scan order."""
    rng = np.random.default_rng(12)
    states, measured, var, mean, sigma = _scene(rng, 1.3, offsets=(0, 60, 120))
    off = np.zeros((SIDE, SIDE), bool)
    off[:7] = off[:, -5:] = True
    off[20, 3] = True
    sigma = sigma.copy()
    sigma[..., off] = np.where(rng.random((1, 3, 3, off.sum())) < 0.5, 0.0, np.nan)
    messy = measured.copy()
    messy[..., off] = np.nan
    got = innovations(states, messy, var, None, mean, sigma, 0)
    assert all(np.array_equal(a, b) for a, b in zip(got, innovations(states, measured, var, None, mean, sigma, 0)))
    ys, xs = np.nonzero(~off)
    alone = [innovations(states, measured[..., y:y + 1, x:x + 1], var[..., y:y + 1, x:x + 1], None,
                         mean[..., y:y + 1, x:x + 1], sigma[..., y:y + 1, x:x + 1], 0) for y, x in zip(ys, xs)]
    for k in range(3):  # per pixel (state, colour, row) -> (state, colour, row, pixel)
        want = np.stack([a[k].reshape(2, 1, 3) for a in alone], axis=-1).ravel()
        np.testing.assert_allclose(got[k], want, rtol=1e-12, atol=0)
    assert len(got[0]) == 2 * 3 * len(ys)
    # no object at all: nothing to measure the prior against, the prior as it is
    assert all(len(a) == 0 for a in innovations(states, measured, var, None, mean, np.zeros_like(sigma), 0))
    assert prior_scale(states, measured, var, None, mean, np.zeros_like(sigma), 0).factor == 1.0


@settings(max_examples=40, deadline=None)
@given(st.floats(0.3, 3.0), st.floats(1e-6, 1e6), st.integers(0, 2**31 - 1))
def test_the_scale_grows_in_step_with_the_errors(t, unit, seed):
    """With no noise the equation is homogeneous: errors ``t`` times larger need a scale ``t``
    times larger, at any units (tiny or huge sigma)."""
    rng = np.random.default_rng(seed)
    p = unit**2 * rng.uniform(0.1, 10.0, 500)
    d = np.sqrt(p) * rng.standard_t(4, 500) * 0.7
    n = np.zeros(500)
    c = innovation_scale(d, p, n)
    inside = lambda x: SCALE_LIMITS[0] * 1.01 < x < SCALE_LIMITS[1] / 1.01  # noqa: E731
    if not (inside(c) and inside(t * c)):
        return
    assert innovation_scale(t * d, p, n) == pytest.approx(t * c, rel=1e-6)
