"""The joint prior of the hybrid solve (polrig.solve.hybrid, "Joint prior"): the network's error on
the six directions the seen frame leaves unobserved, correlated across rows by a 6x6 ``K`` in the
coordinates the per-element prior whitens. Its covariance is symmetric positive definite with
``K`` as its whitened correlation (closed form), ``K = I`` is the per-element solve, the compiled
kernel equals a dense numpy posterior, a wide prior still tends to the reference solve, the
two-state test's statistic has its chi^2 level on data drawn from the model (closed form for the
linear unpolarizing model), and the fit recovers a known ``K``; the calibration file reads an
older file (no ``joint_prior``) as before."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_hybrid import noisy, physical_mueller
from test_model_selection import MODEL, images, noisy_samples

from polrig.errors import ConfigError
from polrig.optics import mueller as mu
from polrig.solve import model_selection as ms
from polrig.solve import reduced_models as rm
from polrig.solve import reference as ref
from polrig.solve.hybrid import (
    JOINT_DIM,
    joint_precision,
    observed_direction,
    plane_axis,
    solve_hybrid,
    unobserved_factor,
    unobserved_precision,
)

S2 = mu.polarizer_stokes(np.radians([20, 110]), np.inf)


def random_correlation(rng, strength=0.8) -> np.ndarray:
    """A random 6x6 correlation matrix, off-diagonal terms up to about ``strength``."""
    a = rng.normal(size=(JOINT_DIM, JOINT_DIM))
    c = strength * (a @ a.T) / JOINT_DIM + (1 - strength) * np.eye(JOINT_DIM)
    d = np.sqrt(np.diag(c))
    return c / d[:, None] / d[None, :]


def rows_of(sd_blocks, s_seen):
    """The per-element prior's row precisions ``(..., 3, 3, 3)`` of sigma blocks ``(..., 3, 3)``."""
    return unobserved_precision(sd_blocks, s_seen)


def joint_error(rng, sd: np.ndarray, s_seen, k: np.ndarray) -> np.ndarray:
    """A network's error drawn from the joint prior's model: nothing along the seen direction,
    ``Q^T e ~ N(0, K)`` on the unobserved directions (``e = Q (Q^T Q)^-1 w``); ``sd``
    ``(C, 3, 3, H, W)``."""
    q = unobserved_factor(rows_of(np.moveaxis(sd, (1, 2), (-2, -1)), s_seen), s_seen)  # (C, H, W, 9, 6)
    w = rng.multivariate_normal(np.zeros(JOINT_DIM), k, size=q.shape[:-2])
    e = np.einsum("...ia,...a->...i", q, np.linalg.solve(np.swapaxes(q, -1, -2) @ q, w[..., None])[..., 0])
    c, h, wd = sd.shape[0], sd.shape[3], sd.shape[4]
    return np.moveaxis(e.reshape(c, h, wd, 3, 3), (-2, -1), (1, 2))


# --------------------------------------------------------------- the covariance itself
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), angle=st.floats(0.0, 180.0), log_scale=st.floats(-6.0, 6.0),
       spread=st.floats(0.0, 3.0))
def test_the_joint_covariance_is_spd_with_k_as_its_whitened_correlation(seed, angle, log_scale, spread):
    """Per pixel the joint precision ``P`` is symmetric, annihilates the seen direction of each
    row, and on the unobserved coordinates ``B = blockdiag(v1, v2)`` its covariance
    ``C = (B^T P B)^-1`` is positive definite and whitens to ``K``: ``L^T C L = K`` with ``L``
    the per-element prior's factor (``B^T Q``); at element sigmas over 12 decades and any angle."""
    rng = np.random.default_rng(seed)
    s = mu.polarizer_stokes(np.radians([angle]), np.inf)[0]
    u = observed_direction(s)
    sd = 10.0**log_scale * np.exp(spread * rng.normal(size=(5, 3, 3)))
    k = random_correlation(rng)
    p = joint_precision(rows_of(sd, s), s, k)
    assert np.allclose(p, np.swapaxes(p, -1, -2), rtol=0, atol=1e-12 * np.abs(p).max())
    for r in range(3):
        assert np.abs(p[:, :, 3 * r:3 * r + 3] @ u).max() <= 1e-9 * np.abs(p).max()
    v1 = plane_axis(u)
    basis = np.kron(np.eye(3), np.stack([v1, np.cross(v1, u)], axis=1))  # (9, 6)
    cov = np.linalg.inv(basis.T @ p @ basis)
    assert (np.linalg.eigvalsh(cov) > 0).all()
    low = basis.T @ unobserved_factor(rows_of(sd, s), s)  # (5, 6, 6) block lower triangular
    assert np.allclose(np.swapaxes(low, -1, -2) @ cov @ low, k, atol=1e-8)


def test_the_identity_factor_reproduces_the_per_element_precision():
    """``Q Q^T`` is the per-element prior's block-diagonal precision."""
    rng = np.random.default_rng(2)
    s = S2[0]
    sd = np.exp(rng.normal(size=(50, 3, 3)))
    rows = rows_of(sd, s)
    q = unobserved_factor(rows, s)
    diag = np.zeros((50, 9, 9))
    for r in range(3):
        diag[:, 3 * r:3 * r + 3, 3 * r:3 * r + 3] = rows[:, r]
    assert np.allclose(q @ np.swapaxes(q, -1, -2), diag, rtol=0, atol=1e-12 * np.abs(diag).max())
    assert np.allclose(joint_precision(rows, s, np.eye(6)), diag, rtol=0, atol=1e-12 * np.abs(diag).max())


# ------------------------------------------------------------------------- the solve
def _case(seed, n, h=6, w=70):
    rng = np.random.default_rng(seed)
    angles = 20.0 + np.arange(n) * 180.0 / max(n, 1) + rng.uniform(-10, 10, n)
    s = mu.polarizer_stokes(np.radians(angles), np.inf)
    m = physical_mueller(rng, 2, h, w)
    meas, var = noisy(rng, m, s)
    sd = 0.05 * np.abs(m[:, :1, :1]) * np.exp(0.5 * rng.normal(size=m.shape))
    mean = m + sd * rng.normal(size=m.shape)
    return rng, s, m, meas, var, mean, sd


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4), drop=st.booleans())
def test_identity_correlation_is_the_per_element_solve(seed, n, drop):
    """``prior_correlation = I`` equals the per-element solve to 1e-9 (relative), masks and
    counts identical, 1 to 4 states, with some seen samples dropped (those pixels keep the
    per-element prior)."""
    rng, s, m, meas, var, mean, sd = _case(seed, n)
    valid = rng.random(meas.shape) > 0.1 if drop else None
    a = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64)
    b = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                     prior_correlation=np.eye(6))
    assert np.array_equal(a.mask, b.mask) and np.array_equal(a.n_samples, b.n_samples)
    for x, y in ((a.mueller, b.mueller), (a.sigma, b.sigma), (a.residual, b.residual)):
        assert np.abs(x - y).max() <= 1e-9 * max(np.abs(x).max(), 1e-300)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_kernel_equals_a_dense_joint_posterior(n):
    """The compiled kernel with a joint prior against ``(N + P) x = N m + P mu`` in numpy with
    :func:`joint_precision` (every seen sample used), mean and sigma to 1e-9."""
    rng, s, m, meas, var, mean, sd = _case(5 + n, n, h=3, w=9)
    k = random_correlation(rng)
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                       prior_correlation=k)
    design = ref.design_matrix(s)
    for c in range(2):
        for yy in range(3):
            for xx in range(9):
                wt = 1.0 / var[:, c, :, yy, xx].reshape(-1)
                y = meas[:, c, :, yy, xx].reshape(-1)
                p = joint_precision(rows_of(sd[c, :, :, yy, xx], s[0]), s[0], k)
                a = design.T @ (wt[:, None] * design) + p
                x = np.linalg.solve(a, design.T @ (wt * y) + p @ mean[c, :, :, yy, xx].reshape(9))
                sg = np.sqrt(np.diag(np.linalg.inv(a)))
                assert np.allclose(got.mueller[c, :, :, yy, xx].reshape(9), x, rtol=1e-9, atol=1e-9 * np.abs(x).max())
                assert np.allclose(got.sigma[c, :, :, yy, xx].reshape(9), sg, rtol=1e-9)


def test_a_wide_joint_prior_tends_to_the_reference_solve():
    """As the prior widens the joint solve is the reference solve: bit for bit at infinite
    sigma, to 1e-9 relative at 1e8 times the data's sigma (four states)."""
    rng, s, m, meas, var, mean, sd = _case(9, 4)
    k = random_correlation(rng)
    r = ref.solve_reference(s, meas, var, dtype=np.float64)
    inf = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=np.inf, seen_state=0, dtype=np.float64,
                       prior_correlation=k)
    assert np.array_equal(inf.mueller, r.mueller) and np.array_equal(inf.sigma, r.sigma)
    assert np.array_equal(inf.residual, r.residual) and np.array_equal(inf.mask, r.mask)
    wide = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=1e8 * r.sigma, seen_state=0, dtype=np.float64,
                        prior_correlation=k)
    for x, y in ((wide.mueller, r.mueller), (wide.sigma, r.sigma)):
        assert np.abs(x - y).max() <= 1e-9 * np.abs(y).max()


def test_bad_correlations_are_one_line_errors():
    rng, s, m, meas, var, mean, sd = _case(1, 2, h=2, w=3)
    for bad, what in ((np.eye(5), "6x6"), (np.eye(6) + np.triu(np.ones((6, 6)), 1) * 0.1, "symmetric"),
                      (np.ones((6, 6)), "positive definite"), (np.full((6, 6), np.nan), "finite")):
        with pytest.raises(ConfigError, match=what):
            solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, prior_correlation=bad)


# ------------------------------------------------------------------ the test's level
def test_the_two_state_statistic_has_its_chi2_level_with_the_joint_prior():
    """Closed form: truth of the linear unpolarizing model, samples at two states, the prior's
    error drawn from the joint model with a strongly correlated ``K``: on the joint posterior
    system the statistic is exactly chi^2(8) (mean 8, 5 % above the alpha = 0.05 critical value;
    binomial 4-sigma bounds over 2000 pixels), while the per-element system, which ignores the
    correlation, is not (its level is measured off the 5 %). At this seed: joint 4.8 %, mean 7.96;
    per element 7.8 %."""
    rng = np.random.default_rng(21)
    h, w = 40, 50
    truth = images(rm.random_blocks(rng, "unpolarizing", h * w, 3000.0), h, w)
    sd = np.broadcast_to(150.0, truth.shape)
    k = np.eye(6)  # the three rows' v2 errors (what two states leave unobserved) move together
    for a, b in ((1, 3), (3, 5), (1, 5)):
        k[a, b] = k[b, a] = 0.95
    mean = truth + joint_error(rng, np.asarray(sd, float), S2[0], k)
    meas, var = noisy_samples(rng, truth, S2)
    rs = ms.row_space_equations(S2, meas, var, None, None, 0, np.arange(h * w))
    mu_, sd_ = mean[0].reshape(9, -1).T, np.asarray(sd)[0].reshape(9, -1).T
    crit = ms.chi2_critical(8, 0.05)
    rates = {}
    for name, corr in (("joint", k), ("diagonal", None)):
        normal, m_post = ms.posterior_system(rs.normal, rs.m_hat, mu_, sd_, S2[0], corr)
        _, q, _ = rm.fit_model(MODEL["unpolarizing"], m_post, normal)
        rates[name] = (float(np.mean(q > crit)), float(np.mean(q)))
    bound = 4 * np.sqrt(0.05 * 0.95 / (h * w))
    assert abs(rates["joint"][0] - 0.05) <= bound, rates
    assert abs(rates["joint"][1] - 8.0) <= 4 * np.sqrt(16.0 / (h * w)), rates
    assert abs(rates["diagonal"][0] - 0.05) > bound, rates


def test_selection_with_the_joint_prior_equals_its_numpy_system():
    """``select_models(prior_correlation=K)`` at two states tests on ``posterior_system(..., K)``:
    the statistic it writes equals the one from that system (largest-p rule)."""
    rng = np.random.default_rng(4)
    h, w = 6, 8
    truth = images(rm.random_blocks(rng, "retarder", h * w, 3000.0), h, w)
    sd = np.full(truth.shape, 150.0)
    k = random_correlation(rng)
    mean = truth + joint_error(rng, sd, S2[0], k)
    meas, var = noisy_samples(rng, truth, S2)
    post = solve_hybrid(S2, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                        prior_correlation=k)
    _, maps = ms.select_models(S2, meas, var, None, None, post, prior=(mean, sd), seen_state=0,
                               prior_correlation=k)
    rs = ms.row_space_equations(S2, meas, var, None, None, 0, np.arange(h * w))
    normal, m_post = ms.posterior_system(rs.normal, rs.m_hat, mean[0].reshape(9, -1).T, sd[0].reshape(9, -1).T,
                                         S2[0], k)
    assert np.allclose(m_post.T.reshape(3, 3, h, w), post.mueller[0], rtol=1e-7, atol=1e-6)
    best = np.full(h * w, -1.0)
    for model in rm.MODELS:
        _, q, _ = rm.fit_model(model, m_post, normal)
        best = np.fmax(best, ms.chi2_sf(np.clip(q, 0, None), 9 - model.n_params))
    chosen = maps.code[0].ravel() != 0
    assert np.allclose(maps.p_value[0].ravel()[chosen], best[chosen], rtol=1e-5)


# ------------------------------------------------------------------------- the fit
def test_the_fit_recovers_a_known_correlation_and_is_spd():
    """:func:`polrig.models.uncertainty_fit.fit_joint` on Student-t (heavy-tailed) errors with a
    known correlation: within 0.03 of it, unit diagonal, positive definite."""
    from polrig.models.uncertainty_fit import fit_joint

    rng = np.random.default_rng(8)
    k = random_correlation(rng)
    z = rng.multivariate_normal(np.zeros(6), k, size=40000)
    w = z / np.sqrt(rng.chisquare(4, size=(40000, 1)) / 4)  # multivariate t, 4 dof: same correlation
    got = np.asarray(fit_joint(w)["correlation"])
    assert np.abs(got - k).max() <= 0.03
    assert np.allclose(np.diag(got), 1.0) and np.linalg.eigvalsh(got).min() > 0


def test_a_calibration_without_the_joint_prior_reads_as_before(tmp_path):
    """A version-3 file without ``joint_prior`` (every file before it) reads with no joint
    prior; the shipped one round-trips it; a broken entry is a ValueError naming the key."""
    from polrig.models.runtime import WEIGHTS_DIR
    from polrig.models.uncertainty import FILE_NAME, JOINT_KEY, UncertaintyModel

    path = WEIGHTS_DIR / FILE_NAME
    if not path.is_file():
        pytest.skip("no shipped calibration")
    data = json.loads(path.read_text())
    old = {key: v for key, v in data.items() if key != JOINT_KEY}
    assert UncertaintyModel.from_json(old).joint is None
    assert UncertaintyModel.from_json(old).joint_correlation is None
    if JOINT_KEY in data:
        model = UncertaintyModel.from_json(data)
        assert np.allclose(UncertaintyModel.from_json(model.to_json()).joint_correlation, model.joint_correlation)
    for bad in ({"version": 99, "correlation": np.eye(6).tolist()}, {"version": 1, "correlation": np.ones((6, 6)).tolist()}):
        with pytest.raises(ValueError, match=JOINT_KEY):
            UncertaintyModel.from_json(old | {JOINT_KEY: bad})


def test_the_fit_entry_recovers_k_from_errors_drawn_from_the_joint_model():
    """Round trip of ``uncertainty_fit``'s joint step: samples whose network error is drawn from
    the joint model (``K`` known, the per-element sigma a model's own) -> :func:`joint_whitened`
    -> :func:`fit_joint` gives ``K`` back within 0.03 (states at several angles)."""
    from polrig.models.uncertainty import UncertaintyModel
    from polrig.models.uncertainty_fit import Sample, fit_joint, joint_whitened

    rng = np.random.default_rng(12)
    coef = np.zeros((3, 3, 4))
    coef[..., 0] = 0.02 + 0.04 * rng.random((3, 3))  # sigma' = a * scale, per observed-frame element
    model = UncertaintyModel(coef)
    k = random_correlation(rng)
    samples = []
    for angle in (0.0, 30.0, 75.0, 140.0):
        s = mu.polarizer_stokes(np.radians([angle]), np.inf)[0]
        truth = physical_mueller(rng, 1, 60, 60)
        mask = np.ones((60, 60), bool)
        stokes = np.einsum("crkhw,k->crhw", truth, s)
        sd = model.sigma(truth, s, mask, stokes).astype(np.float64)
        pred = truth + joint_error(rng, sd, s, k)
        # the sigma is the model's at the prediction: draw again at the prediction's own sigma
        sd = model.sigma(pred, s, mask, np.einsum("crkhw,k->crhw", pred, s)).astype(np.float64)
        pred = truth + joint_error(rng, sd, s, k)
        samples.append(Sample(pred, truth, s, mask, np.zeros((1, 60, 60), bool),
                              np.einsum("crkhw,k->crhw", pred, s), 0.1))
    w = joint_whitened(model, samples)
    assert len(w) == 4 * 3600
    got = np.asarray(fit_joint(w)["correlation"])
    assert np.abs(got - k).max() <= 0.05, np.abs(got - k).max()
    assert np.abs(k - np.eye(6)).max() > 0.3  # a K far from the per-element prior


def test_an_unpolarized_seen_state_keeps_the_per_element_prior():
    """A seen state without an angle has no plane axis: the kernel and ``posterior_system`` both
    keep the per-element prior there, bit for bit in the solve."""
    rng, s, m, meas, var, mean, sd = _case(3, 2, h=3, w=8)
    s = s.copy()
    s[0] = [1.0, 0.01, 0.0]  # degree of polarization 0.01, below MIN_SEEN_DOP
    a = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64)
    b = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64,
                     prior_correlation=random_correlation(rng))
    assert np.array_equal(a.mueller, b.mueller) and np.array_equal(a.sigma, b.sigma)
    normal = np.tile(np.eye(9), (4, 1, 1))
    mh, mn, sg = rng.normal(size=(4, 9)), rng.normal(size=(4, 9)), np.exp(rng.normal(size=(4, 9)))
    x = ms.posterior_system(normal, mh, mn, sg, s[0])
    y = ms.posterior_system(normal, mh, mn, sg, s[0], random_correlation(rng))
    assert np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1])
