"""Realizability tests and Cloude filtering (polrig.optics.realizability)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polrig.optics import mueller as mu
from polrig.optics import realizability as rz

SETTINGS = settings(max_examples=50, deadline=None)
finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False, allow_subnormal=False)
# batches of Jones matrices: (k, 2, 2) complex
jones_batch = st.integers(1, 6).flatmap(
    lambda k: arrays(np.float64, (2, k, 2, 2), elements=finite).map(lambda a: a[0] + 1j * a[1]))


def _convex_sum(jones: np.ndarray, weights: np.ndarray) -> np.ndarray:
    return np.einsum("k,kij->ij", weights, mu.jones_to_mueller(jones))


def _scatmech_hermitian(m: np.ndarray) -> np.ndarray:
    """Reference construction: usnistgov pySCATMECH mueller.py ``MuellerToHermitian`` (formula
    transcribed as a fact; its eigenvalues are twice those of Cloude's coherency matrix)."""
    h = np.zeros((4, 4), complex)
    h[0, 0] = (m[0, 0] + m[1, 1] + m[0, 1] + m[1, 0]) / 2
    h[0, 1] = complex(m[0, 2] + m[1, 2], m[0, 3] + m[1, 3]) / 2
    h[0, 2] = complex(m[2, 0] + m[2, 1], -m[3, 0] - m[3, 1]) / 2
    h[0, 3] = complex(m[2, 2] + m[3, 3], m[2, 3] - m[3, 2]) / 2
    h[1, 1] = (m[0, 0] - m[1, 1] - m[0, 1] + m[1, 0]) / 2
    h[1, 2] = complex(m[2, 2] - m[3, 3], -m[2, 3] - m[3, 2]) / 2
    h[1, 3] = complex(m[2, 0] - m[2, 1], -m[3, 0] + m[3, 1]) / 2
    h[2, 2] = (m[0, 0] - m[1, 1] + m[0, 1] - m[1, 0]) / 2
    h[2, 3] = complex(m[0, 2] - m[1, 2], m[0, 3] - m[1, 3]) / 2
    h[3, 3] = (m[0, 0] + m[1, 1] - m[0, 1] - m[1, 0]) / 2
    return np.triu(h) + np.triu(h, 1).conj().T


@SETTINGS
@given(m=arrays(np.float64, (4, 4), elements=finite))
def test_coherency_matches_pyscatmech_reference(m):
    ours = rz.coherency_eigenvalues(m)
    ref = np.linalg.eigvalsh(_scatmech_hermitian(m)) / 2
    assert np.allclose(ours, ref, atol=1e-9 * (1 + np.abs(m).max()))
    h = rz.coherency_matrix(m)
    assert np.allclose(h, np.conj(np.swapaxes(h, -1, -2)))
    assert np.trace(h).real == pytest.approx(m[0, 0], abs=1e-12 * (1 + np.abs(m).max()))
    assert np.allclose(rz.mueller_from_coherency(h), m, atol=1e-12 * (1 + np.abs(m).max()))


@SETTINGS
@given(j=jones_batch)
def test_pure_matrices_pass_both_tests_and_are_rank_one(j):
    m = mu.jones_to_mueller(j)
    assert rz.is_physical_gk(m).all()
    assert rz.is_physical_coherency(m).all()
    ev = rz.coherency_eigenvalues(m)
    scale = 1 + m[..., 0, 0]
    assert np.allclose(ev[..., :3] / scale[..., None], 0, atol=1e-9)
    assert np.allclose(ev[..., 3], m[..., 0, 0], rtol=1e-9, atol=1e-12)


@SETTINGS
@given(j=jones_batch, data=st.data())
def test_convex_sums_are_realizable_and_unchanged_by_filter(j, data):
    # Weights are 0 or at least 1e-12: a weight near the subnormal range (hypothesis found
    # 5e-324) rounds the sum to a matrix of a few ulps that is no longer the physical one.
    w = data.draw(arrays(np.float64, j.shape[:1],
                         elements=st.one_of(st.just(0.0), st.floats(1e-12, 1))))
    m = _convex_sum(j, w)
    assert rz.is_physical_coherency(m) and rz.is_physical_gk(m)
    assert np.allclose(rz.cloude_filter(m), m, atol=1e-9 * (1 + np.abs(m).max()))
    # blocks of realizable matrices are realizable under the max-min-eigenvalue completion
    m3 = mu.linear_block(m)
    assert rz.is_physical_linear(m3)
    assert np.allclose(rz.filter_linear(m3), m3, atol=1e-9 * (1 + np.abs(m).max()))


def test_products_and_sums_of_elements_unchanged():
    theta = np.linspace(0, np.pi, 7)
    elems = [
        mu.polarizer_at(theta[:, None], 300.0),
        mu.rotated_element(theta[:, None], mu.linear_retarder(1.1)),
        mu.specular_reflection(np.cos(np.radians(60.0)), 1.5) * np.ones((7, 1, 1, 1)),
        mu.specular_transmission(np.cos(np.radians(30.0)), 1.5) * np.ones((7, 1, 1, 1)),
        mu.depolarizer(0.4) * np.ones((7, 1, 1, 1)),
    ]
    prod = elems[0] @ elems[1] @ elems[2] @ elems[3]
    mix = 0.3 * prod + 0.5 * elems[4] + 0.2 * mu.rotated_element(0.3, elems[2])
    for m in (prod, mix, mu.identity((3,)), mu.diattenuator(1.0, 0.0)):
        assert rz.is_physical_coherency(m).all() and rz.is_physical_gk(m).all()
        assert np.allclose(rz.cloude_filter(m), m, atol=1e-9)


@SETTINGS
@given(m=arrays(np.float64, (8, 4, 4), elements=finite))
def test_filter_returns_realizable_and_is_idempotent(m):
    f = rz.cloude_filter(m)
    assert rz.is_physical_coherency(f).all()
    assert rz.is_physical_gk(f).all()
    assert np.allclose(rz.cloude_filter(f), f, atol=1e-9 * (1 + np.abs(m).max()))
    # Cloude-realizable implies Stokes-Stokes
    psd = rz.is_physical_coherency(m)
    assert (rz.is_physical_gk(m) | ~psd).all()
    # scale invariance of both tests for positive scales
    gk = rz.is_physical_gk(m)
    for s in (1e-6, 1e6):
        assert np.array_equal(rz.is_physical_coherency(s * m), psd)
        assert np.array_equal(rz.is_physical_gk(s * m), gk)


def test_known_verdicts():
    mirror_s3 = np.diag([1.0, 1.0, 1.0, -1.0])  # Stokes-Stokes, but not a sum of Jones matrices
    assert rz.is_physical_gk(mirror_s3) and not rz.is_physical_coherency(mirror_s3)
    amplifier = np.diag([1.0, 1.2, 0.0, 0.0])  # turns (1, 1, 0, 0) into DoP 1.2
    assert not rz.is_physical_gk(amplifier) and not rz.is_physical_coherency(amplifier)
    assert not rz.is_physical_gk(-np.eye(4)) and not rz.is_physical_coherency(-np.eye(4))
    assert rz.is_physical_gk(np.zeros((4, 4))) and rz.is_physical_coherency(np.zeros((4, 4)))
    assert rz.is_physical_gk(mu.depolarizer(2.0)) and rz.is_physical_coherency(mu.depolarizer(2.0))
    ev = rz.coherency_eigenvalues(mirror_s3)
    assert ev[0] == pytest.approx(-0.5)


def test_linear_block_completions():
    ident = np.eye(3)
    # zero padding makes the identity diag(1, 1, 1, 0): coherency eigenvalue -1/4
    assert rz.coherency_eigenvalues(rz.complete_linear(ident, "zero"))[0] == pytest.approx(-0.25)
    assert not rz.is_physical_linear(ident, completion="zero")
    assert rz.optimal_m33(ident) == pytest.approx(1.0, abs=1e-8)
    assert rz.is_physical_linear(ident) and rz.is_physical_linear(ident, test="gk")
    # linear retarder: the block is realizable with m33 = cos(d)
    d = np.linspace(0.0, np.pi, 9)
    m3 = mu.linear_block(mu.linear_retarder(d))
    assert np.allclose(rz.optimal_m33(m3), np.cos(d), atol=1e-7)
    with pytest.raises(ValueError, match="completion"):
        rz.complete_linear(ident, "bogus")
    with pytest.raises(ValueError, match="test"):
        rz.is_physical_linear(ident, test="bogus")


@SETTINGS
@given(m3=arrays(np.float64, (6, 3, 3), elements=finite))
def test_filter_linear_returns_realizable_blocks(m3):
    f = rz.filter_linear(m3)
    assert f.shape == m3.shape and np.isfinite(f).all()
    assert rz.is_physical_linear(f, rtol=1e-8).all()
    # the optimal completion is at least as realizable as zero padding
    ev_opt = rz.coherency_eigenvalues(rz.complete_linear(m3))[..., 0]
    ev_zero = rz.coherency_eigenvalues(rz.complete_linear(m3, "zero"))[..., 0]
    assert (ev_opt >= ev_zero - 1e-9 * (1 + np.abs(m3).max())).all()


def test_filter_linear_refuses_the_zero_completion():
    """Filtering under m33 = 0 would Cloude-filter to a matrix with m33 != 0 and then drop it:
    the identity came back as diag(1.25, 0.75, 0.75), not realizable under that completion."""
    assert rz.filter_linear(np.eye(3)) == pytest.approx(np.eye(3))
    with pytest.raises(ValueError, match="max_min_eigenvalue"):
        rz.filter_linear(np.eye(3), completion="zero")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nonfinite_input_gives_false_and_finite_output(bad):
    m = np.stack([np.eye(4), np.eye(4)])
    m[1, 2, 1] = bad
    assert rz.is_physical_gk(m).tolist() == [True, False]
    assert rz.is_physical_coherency(m).tolist() == [True, False]
    f = rz.cloude_filter(m)
    assert np.isfinite(f).all() and np.array_equal(f[1], np.zeros((4, 4)))
    m3 = m[:, :3, :3]
    assert rz.is_physical_linear(m3).tolist() == [True, False]
    assert rz.is_physical_linear(m3, test="gk").tolist() == [True, False]
    assert np.isfinite(rz.filter_linear(m3)).all()
    assert np.isnan(rz.coherency_eigenvalues(m)[1]).all()


def test_image_shaped_input_and_pass_rate():
    rng = np.random.default_rng(3)
    j = rng.normal(size=(2, 5, 7, 2, 2)) + 1j * rng.normal(size=(2, 5, 7, 2, 2))
    m = mu.jones_to_mueller(j)
    m[0, 0, 0] = np.diag([1.0, 1.2, 0, 0])
    ok = rz.is_physical_coherency(m)
    assert ok.shape == (2, 5, 7)
    assert rz.pass_rate(ok) == pytest.approx(69 / 70)
    valid = np.ones((2, 5, 7), bool)
    valid[0, 0, 0] = False
    assert rz.pass_rate(ok, valid) == 1.0
    assert np.isnan(rz.pass_rate(ok, np.zeros_like(valid)))
    with pytest.raises(ValueError, match="4, 4"):
        rz.is_physical_gk(np.eye(3))


def test_linear_test_shortcuts_agree_with_full_search():
    rng = np.random.default_rng(12)
    j = rng.normal(size=(2000, 3, 2, 2)) + 1j * rng.normal(size=(2000, 3, 2, 2))
    phys = np.einsum("pk,pkij->pij", rng.random((2000, 3)), mu.jones_to_mueller(j))[:, :3, :3]
    noisy = phys + 0.03 * rng.normal(size=phys.shape) * phys[:, :1, :1]
    for m3 in (phys, noisy, rng.normal(size=(500, 3, 3))):
        fast = rz.is_physical_linear(m3)
        full = rz.is_physical_coherency(rz.complete_linear(m3))
        assert np.array_equal(fast, full)
        f = rz.filter_linear(m3)
        assert np.array_equal(f[fast], m3[fast])
        assert rz.is_physical_linear(f, rtol=1e-8).all()
    assert 0.5 < rz.pass_rate(rz.is_physical_linear(noisy)) < 1.0
