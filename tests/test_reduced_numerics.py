"""The compiled Levenberg-Marquardt of the lower-order models (polrig.solve.reduced_models.fit_model,
polrig.solve._reduced_kernel) against the previous numpy implementation
(polrig.solve._reduced_numpy, the oracle): the compiled model forms, the fits, the whole
selection; determinism across threads and chunks; a normal matrix that is not positive definite."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.optics import mueller as mu
from polrig.solve import _reduced_kernel as kern
from polrig.solve import chunks
from polrig.solve import model_selection as ms
from polrig.solve import reduced_models as rm
from polrig.solve import reference as ref
from polrig.solve._reduced_numpy import fit_model_numpy

S4 = mu.polarizer_stokes(np.radians([0, 45, 90, 135]), np.inf)
NONLINEAR = [m for m in rm.MODELS if not m.linear]


def noisy_normal_equations(rng, blocks: np.ndarray, s=S4):
    """Normal matrices and full estimates ``(P, 9, 9)``, ``(P, 9)`` of noisy samples of
    ``blocks`` ``(P, 9)`` (shot and read noise, variance from the same model)."""
    p = len(blocks)
    truth = blocks.reshape(1, p, 3, 3).transpose(2, 3, 0, 1)[None]
    mean = ref.forward_measurements(truth, s)
    var = 4.0 + np.clip(mean, 0, None) / 0.5
    meas = mean + rng.normal(size=mean.shape) * np.sqrt(var)
    normal, m_hat, _, _ = ms.normal_equations(s, meas, var, None, None, 0, np.arange(p))
    return normal, m_hat


def mixed_blocks(rng, p_each: int, scale: float) -> np.ndarray:
    """Blocks of every model and of the full block."""
    return np.concatenate([rm.random_blocks(rng, name, p_each, scale)
                           for name in ["full", *(m.name for m in rm.MODELS)]])


@pytest.mark.parametrize("model", NONLINEAR, ids=lambda m: m.name)
def test_compiled_model_forms_equal_the_numpy_ones(model):
    """The kernel's block and Jacobian (written out per model) against the numpy forms that
    define the models, at random parameters including zero amplitudes."""
    rng = np.random.default_rng(0)
    theta = rng.uniform(-3.0, 3.0, (200, model.n_params))
    theta[:20, :2] = 0.0
    want_m, want_j = model.matrix(theta), model.jacobian(theta)
    m, jac, j5 = np.empty(9), np.empty((9, model.n_params)), np.empty((9, 5))
    for p in range(len(theta)):
        kern._matrix(model.code, theta[p], m)
        kern._jacobian(model.code, theta[p], jac, j5)
        np.testing.assert_allclose(m, want_m[p], rtol=0, atol=1e-14)
        np.testing.assert_allclose(jac, want_j[p], rtol=0, atol=1e-14)


@pytest.mark.parametrize("scale", [1e-3, 30.0, 3000.0, 6e4])
@pytest.mark.parametrize("model", NONLINEAR, ids=lambda m: m.name)
def test_fit_equals_the_numpy_oracle(model, scale):
    """Noisy samples of blocks of every kind, from no light to near saturation: the
    statistic ``q`` agrees within ``1e-6 (1 + q)`` (measured: at most 4e-8) and, where the
    model could be accepted (``q < 100``, beyond every critical value), the fitted block
    within ``1e-8`` in the noise metric ``(m - m_o)^T N (m - m_o)`` (1e-4 sigma; measured: at
    most 2e-10). (Where the fit's minimum is degenerate, e.g. a noise-free isotropic block
    under an axis model, the two may return different minimisers of equal ``q``.)"""
    rng = np.random.default_rng(int(scale * 1000) % 2**32)
    normal, m_hat = noisy_normal_equations(rng, mixed_blocks(rng, 40, scale))
    m, q, jac = rm.fit_model(model, m_hat, normal)
    m_o, q_o, jac_o = fit_model_numpy(model, m_hat, normal)
    assert np.isfinite(q).all() and np.isfinite(q_o).all()
    assert np.max(np.abs(q - q_o) / (1.0 + q_o)) <= 1e-6
    close = q_o < 100.0
    assert close.sum() >= 40
    d = (m - m_o)[close]
    assert np.max(np.einsum("pi,pij,pj->p", d, normal[close], d)) <= 1e-8
    assert jac.shape == jac_o.shape == (len(m_hat), 9, model.n_params)


def test_selection_equals_the_one_with_the_numpy_oracle(monkeypatch):
    """The whole selection on a mixed scene (every model, the full block, off-model
    perturbations of 0 to 800 DN): the same codes, statistics within 1e-5 (float32 maps),
    the estimate and sigma within 1e-6 of each pixel's m00."""
    rng = np.random.default_rng(21)
    names = [m.name for m in rm.MODELS]
    p = 3000
    base = np.concatenate([rm.random_blocks(rng, names[i % 6], p // 6, 3000.0) for i in range(6)])
    pert = rm.random_blocks(rng, "full", p)
    blocks = base + rng.uniform(0, 800, (p, 1)) * pert / np.linalg.norm(pert, axis=1, keepdims=True)
    truth = blocks.reshape(50, 60, 3, 3).transpose(2, 3, 0, 1)[None]
    mean = ref.forward_measurements(truth, S4)
    var = 4.0 + np.clip(mean, 0, None) / 0.5
    meas = mean + rng.normal(size=mean.shape) * np.sqrt(var)
    full = ref.solve_reference(S4, meas, var, dtype=np.float64)
    sel, maps = ms.select_models(S4, meas, var, None, None, full)
    monkeypatch.setattr(ms, "fit_model", fit_model_numpy)
    sel_o, maps_o = ms.select_models(S4, meas, var, None, None, full)
    np.testing.assert_array_equal(maps.code, maps_o.code)
    assert 0.2 < np.mean(maps.code != 0) < 0.8
    np.testing.assert_allclose(maps.statistic, maps_o.statistic, rtol=1e-5, atol=1e-5)
    m00 = np.abs(full.mueller[:, :1, :1])
    for name in ("mueller", "sigma"):
        diff = np.abs(getattr(sel, name) - getattr(sel_o, name)) / m00
        assert np.max(diff) <= 1e-6, name


def test_fits_do_not_depend_on_the_threads_or_the_chunking(monkeypatch):
    """One thread, or chunks of 7 pixels on 3 threads: the same bits."""
    rng = np.random.default_rng(3)
    normal, m_hat = noisy_normal_equations(rng, mixed_blocks(rng, 30, 3000.0))
    results = []
    for threads, chunk in ((1, 256), (3, 7)):
        monkeypatch.setattr(chunks, "THREADS", threads)
        monkeypatch.setattr(rm, "_CHUNK_PIXELS", chunk)
        results.append([rm.fit_model(m, m_hat, normal) for m in NONLINEAR])
    for a, b in zip(*results):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_a_normal_matrix_that_is_not_positive_definite_fails_the_fit_only_there():
    """A zero and a NaN normal matrix: NaN block and statistic for those pixels (the
    selection tests only pixels with a regular normal matrix), the others fitted."""
    rng = np.random.default_rng(4)
    normal, m_hat = noisy_normal_equations(rng, rm.random_blocks(rng, "fresnel", 4, 3000.0))
    normal[1] = 0.0
    normal[2, 0, 0] = np.nan
    for model in NONLINEAR:
        m, q, _ = rm.fit_model(model, m_hat, normal)
        assert np.isnan(q[1:3]).all() and np.isnan(m[1:3]).all()
        assert np.isfinite(q[[0, 3]]).all() and np.isfinite(m[[0, 3]]).all()
