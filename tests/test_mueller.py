"""Mueller algebra against closed forms, invariants and round trips (polrig.optics.mueller)."""

from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polrig.optics import mueller as mu
from polrig.optics import pbrdf

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
angles = st.floats(-2 * np.pi, 2 * np.pi, allow_nan=False)
SETTINGS = settings(max_examples=60, deadline=None)


def _linear_state(aolp, dolp, s0=1.0):
    return np.stack([s0 * np.ones_like(aolp), s0 * dolp * np.cos(2 * aolp), s0 * dolp * np.sin(2 * aolp)], -1)


# --------------------------------------------------------------------------- estimate_linear
@SETTINGS
@given(m=arrays(np.float64, (3, 3), elements=finite),
       aolp=arrays(np.float64, st.integers(3, 12), elements=st.floats(0, np.pi)),
       data=st.data())
def test_estimate_linear_recovers_m(m, aolp, data):
    dolp = data.draw(arrays(np.float64, aolp.shape, elements=st.floats(0, 1)))
    s_in = _linear_state(aolp, dolp)
    sv = np.linalg.svd(s_in, compute_uv=False)
    assume(sv[-1] > 1e-3 * sv[0])
    s_out = s_in @ m.T
    est, cond = mu.estimate_linear(s_in, s_out)
    assert cond == pytest.approx(sv[0] / sv[-1])
    assert np.allclose(est, m, atol=1e-9 * cond * (1 + np.abs(m).max()))
    # weighted solve gives the same answer for consistent data, broadcast over pixels
    w = np.linspace(0.5, 2.0, len(aolp))
    est_w, _ = mu.estimate_linear(s_in, np.broadcast_to(s_out, (2,) + s_out.shape), np.broadcast_to(w, (2, len(w))))
    assert np.allclose(est_w, m, atol=1e-8 * cond * (1 + np.abs(m).max()))


def test_estimate_linear_condition_numbers_and_errors():
    s4 = mu.polarizer_stokes(np.radians([0, 45, 90, 135]))
    _, cond = mu.estimate_linear(s4, s4)
    # s_in^T s_in = diag(1, 1/2, 1/2): the 3-state-vector condition number is sqrt(2)
    assert cond == pytest.approx(np.sqrt(2.0))
    # collinear: 0, 90 and their unpolarized average span only (S0, S1)
    bad = np.array([[0.5, 0.5, 0.0], [0.5, -0.5, 0.0], [1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="collinear"):
        mu.estimate_linear(bad, bad)
    with pytest.raises(ValueError, match="at least 3"):
        mu.estimate_linear(s4[:2], s4[:2])
    # weights that zero all but two states leave M undetermined at that pixel: refused, not a
    # least-squares answer off by more than the matrix itself (weights 1e-17 included)
    m = np.array([[1.0, 0.2, -0.1], [0.3, 0.5, 0.1], [0.0, -0.2, 0.4]])
    s_out = np.broadcast_to(s4 @ m.T, (3, 4, 3))
    for w in ([1, 1, 0, 0], [1, 1, 1e-17, 0], [1, 0, 1, 0]):
        weights = np.array([[1, 1, 1, 1], w, [2, 1, 1, 2]], float)
        with pytest.raises(ValueError, match="1 of 3 pixel"):
            mu.estimate_linear(s4, s_out, weights)
    for w in ([1, np.nan, 1, 1], [1, -1, 1, 1], [1, np.inf, 1, 1]):
        with pytest.raises(ValueError, match="finite and >= 0"):
            mu.estimate_linear(s4, s_out[0], np.array(w))
    est, _ = mu.estimate_linear(s4, s_out, np.array([[1, 1, 1, 1], [1, 1, 1, 0], [2, 1, 1, 2]], float))
    np.testing.assert_allclose(est, np.broadcast_to(m, (3, 3, 3)), atol=1e-12)


# --------------------------------------------------------------------------- element closed forms
def test_polarizer_extinction_ratio_must_be_at_least_one():
    """ER < 1 would make the minor axis transmit more than the major one (a polarizer along
    the other axis, mislabelled), ER 0 a division by zero: refused in one line."""
    np.testing.assert_allclose(mu.polarizer_stokes(0.3, 1.0), [1.0, 0.0, 0.0], atol=1e-15)
    for er in (0.0, 0.5, -3.0, np.nan, [2.0, 0.9]):
        with pytest.raises(ValueError, match="extinction_ratio must be >= 1"):
            mu.polarizer_stokes(np.zeros(np.shape(er)), er)


@SETTINGS
@given(theta=angles, phi=angles, s0=st.floats(1e-6, 1e6))
def test_polarizer_malus_law(theta, phi, s0):
    s_in = np.array([s0, s0 * np.cos(2 * phi), s0 * np.sin(2 * phi), 0.0])
    out = mu.apply(mu.polarizer_at(theta), s_in)
    assert out[0] == pytest.approx(s0 * np.cos(theta - phi) ** 2, abs=1e-12 * s0)
    # the output is fully polarized along theta
    assert np.allclose(out, out[0] * np.array([1, np.cos(2 * theta), np.sin(2 * theta), 0]), atol=1e-12 * s0)


@SETTINGS
@given(theta=angles, er=st.floats(1.0, 1e6))
def test_polarizer_matches_jones_projector(theta, er):
    """Independent check of the rotation sign: a polarizer at theta is the Jones matrix that
    passes the field along (cos theta, sin theta) (angle from x towards y)."""
    c, s = np.cos(theta), np.sin(theta)
    r = np.array([[c, -s], [s, c]])
    j = r @ np.diag([1.0, 1.0 / np.sqrt(er)]) @ r.T
    assert np.allclose(mu.polarizer_at(theta, er), mu.jones_to_mueller(j), atol=1e-12)


@SETTINGS
@given(a=angles, b=angles)
def test_rotator_composition(a, b):
    assert np.allclose(mu.rotator(a) @ mu.rotator(b), mu.rotator(a + b), atol=1e-12)
    assert np.allclose(mu.rotator(a) @ mu.rotator(-a), np.eye(4), atol=1e-12)
    assert np.allclose(mu.rotator(np.pi), np.eye(4), atol=1e-12)
    # a rotated element composes: rotating by a then b is rotating by a + b
    m = mu.linear_retarder(0.7)
    assert np.allclose(mu.rotated_element(a, mu.rotated_element(b, m)), mu.rotated_element(a + b, m), atol=1e-12)


@SETTINGS
@given(theta=angles)
def test_half_wave_plate_mirrors_aolp(theta):
    hwp = mu.rotated_element(theta, mu.linear_retarder(np.pi))
    s_in = np.array([1.0, 1.0, 0.0, 0.0])  # horizontal
    assert np.allclose(mu.apply(hwp, s_in), [1, np.cos(4 * theta), np.sin(4 * theta), 0], atol=1e-12)


def test_quarter_wave_plate_makes_circular():
    qwp = mu.rotated_element(np.pi / 4, mu.linear_retarder(np.pi / 2))
    out = mu.apply(qwp, np.array([1.0, 1.0, 0.0, 0.0]))
    assert np.allclose(np.abs(out), [1, 0, 0, 1], atol=1e-12)
    # retarder leaves its own axes alone
    assert np.allclose(mu.apply(mu.linear_retarder(0.3), np.array([1.0, 1.0, 0, 0])), [1, 1, 0, 0])


@SETTINGS
@given(eta=st.floats(1.01, 4.0))
def test_fresnel_closed_forms(eta):
    rs, rp = mu.fresnel_reflectance(np.cos(np.arctan(eta)), eta)
    assert rp == pytest.approx(0.0, abs=1e-14)  # Brewster
    r0 = ((eta - 1) / (eta + 1)) ** 2
    assert np.allclose(mu.fresnel_reflectance(1.0, eta), (r0, r0))
    # energy: T + R = 1 for s and p (a and b of the two matrices add to 1 and 0)
    cos_i = np.linspace(0.0, 1.0, 33)
    r, t = mu.specular_reflection(cos_i, eta), mu.specular_transmission(cos_i, eta)
    assert np.allclose(r[..., 0, 0] + t[..., 0, 0], 1.0)
    assert np.allclose(r[..., 0, 1] + t[..., 0, 1], 0.0)
    # grazing incidence reflects everything, the Mueller matrix stays finite
    assert np.isfinite(r).all() and r[0, 0, 0] == pytest.approx(1.0)


def _fresnel_reference(cos_i: float, eta: float) -> tuple[float, float]:
    """``(Rs, Rp)`` in 60-digit decimal arithmetic (no cancellation to worry about)."""
    if eta == 1.0:
        return 0.0, 0.0  # no interface
    with localcontext() as ctx:
        ctx.prec = 60
        ci, n = Decimal(cos_i), Decimal(eta)
        ect = (n * n - 1 + ci * ci).sqrt()  # eta cos_t, Snell's law
        rs = (ci - ect) / (ci + ect)
        rp = (n * n * ci - ect) / (n * n * ci + ect)
        return float(rs * rs), float(rp * rp)


@pytest.mark.parametrize("eta", [1.0, 1.0 + 1e-12, 1.0 + 1e-6, 1.0001, 1.5])
def test_fresnel_near_grazing_for_eta_near_one_has_no_cancellation(eta):
    """An index-matched interface reflects nothing, also at exactly grazing incidence, and an
    interface with ``eta`` just above 1 reflects what the closed form says near grazing: the
    textbook ``cos_t = sqrt(1 - sin^2 / eta^2)`` loses every digit there (it gave R = 1 for
    eta = 1 at cos_i = 1e-9, and NaN at cos_i = 0)."""
    cos_i = np.array([1e-12, 1e-9, 1e-6, 1e-3, 0.3, 1.0] + ([0.0] if eta == 1.0 else []))
    want = np.array([_fresnel_reference(c, eta) for c in cos_i])  # (n, 2)
    got = np.stack(mu.fresnel_reflectance(cos_i, eta), -1)
    fast = pbrdf.fresnel_reflection_sp(cos_i, eta)
    fast_rs_rp = np.stack([fast[:, 0, 0] + fast[:, 0, 1], fast[:, 0, 0] - fast[:, 0, 1]], -1)
    for g in (got, fast_rs_rp):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, want, rtol=1e-9, atol=1e-15)
    t = mu.specular_transmission(cos_i, eta)
    np.testing.assert_allclose(t[:, 0, 0], 1.0 - want.mean(-1), rtol=1e-9, atol=1e-15)


def test_fresnel_mitsuba_brewster_value():
    """Mitsuba 3 src/render/tests/test_mueller.py: eta 1.5 at Brewster's angle."""
    m = mu.specular_reflection(np.cos(np.arctan(1.5)), 1.5)
    assert np.allclose(m[:2, :2], 0.0739645, atol=1e-7)
    assert np.allclose(m[2:, :2], 0) and np.allclose(m[:2, 2:], 0)


def test_normal_incidence_flips_handedness():
    m = mu.specular_reflection(1.0, 1.5)
    assert np.allclose(np.diag(m), [0.04, 0.04, -0.04, -0.04])


# --------------------------------------------------------------------------- Jones, diattenuation
jones = arrays(np.float64, (2, 2, 2), elements=finite).map(lambda a: a[0] + 1j * a[1])


@SETTINGS
@given(j1=jones, j2=jones)
def test_jones_to_mueller_is_a_homomorphism(j1, j2):
    m12 = mu.jones_to_mueller(j1 @ j2)
    assert np.allclose(m12, mu.jones_to_mueller(j1) @ mu.jones_to_mueller(j2),
                       atol=1e-9 * (1 + np.abs(m12).max()))
    # non-depolarizing: M^T G M = |det J|^2 G (the 2x2 determinant written out: LAPACK's LU
    # gives NaN for a subnormal pivot such as [[0, 1], [2.2e-309, 0]], which Hypothesis found)
    g = np.diag([1.0, -1, -1, -1])
    m1 = mu.jones_to_mueller(j1)
    det = j1[0, 0] * j1[1, 1] - j1[0, 1] * j1[1, 0]
    assert np.allclose(m1.T @ g @ m1, abs(det) ** 2 * g, atol=1e-9 * (1 + np.abs(m1).max()) ** 2)


def test_diattenuation_and_polarizance():
    assert mu.diattenuation(mu.polarizer_at(0.4)) == pytest.approx(1.0)
    assert mu.polarizance(mu.polarizer_at(0.4)) == pytest.approx(1.0)
    assert mu.diattenuation(mu.depolarizer(0.3)) == 0.0
    assert mu.diattenuation(mu.diattenuator(0.8, 0.2)) == pytest.approx(0.6)
    assert mu.diattenuation(mu.linear_block(mu.diattenuator(0.8, 0.2))) == pytest.approx(0.6)
    bad = np.array([np.full((4, 4), np.nan), np.zeros((4, 4))])
    assert np.array_equal(mu.diattenuation(bad), [0.0, 0.0])


@pytest.mark.parametrize("eta", [1.5, 0.6, 0.7, 0.2 + 3j, 1.3 + 0.5j])
def test_specular_reflection_matches_mitsuba_including_retardance(eta):
    """Conductors and total internal reflection have complex amplitudes: the retardance
    elements m23 = -m32 must carry Mitsuba 3's sign (mueller::specular_reflection)."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_spectral_polarized")
    for cos_i in (0.05, 0.3, 0.5, 0.9, 1.0):
        e = mi.Complex2f(eta.real, eta.imag) if isinstance(eta, complex) else float(eta)
        ref = np.array(mi.mueller.specular_reflection(mi.Float(cos_i), e)).reshape(4, 4)
        np.testing.assert_allclose(mu.specular_reflection(cos_i, eta), ref, atol=2e-6)


def test_specular_reflection_agrees_with_the_pbrdf_fast_path():
    from polrig.optics import pbrdf

    cos_i = np.linspace(0.0, 1.0, 41)
    for eta in (0.5, 0.8, 1.33, 1.5, 2.4):
        np.testing.assert_allclose(mu.specular_reflection(cos_i, eta),
                                   pbrdf.fresnel_reflection_sp(cos_i, eta), atol=1e-12)


@pytest.mark.parametrize("angle, phase", [(0.0, 0.7), (0.4, 0.7), (-1.1, np.pi), (2.0, np.pi / 2), (0.3, 0.0)])
def test_retarder_matches_mitsuba_and_composes_with_fresnel_in_one_convention(angle, phase):
    """``retarder_at`` is Mitsuba 3's ``rotated_element(a, linear_retarder(d))`` (Goldstein
    eq. 6.43: the S3 sign of docs/conventions.md), and ``jones_to_mueller`` maps the Jones
    matrices of a retarder and of a Fresnel reflector onto ``linear_retarder`` and
    ``specular_reflection`` alike, so that films over metals compose in one convention."""
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_spectral_polarized")
    ref = np.array(mi.mueller.rotated_element(mi.Float(angle), mi.mueller.linear_retarder(mi.Float(phase))))
    np.testing.assert_allclose(mu.retarder_at(angle, phase), ref.reshape(4, 4), atol=2e-6)
    np.testing.assert_allclose(mu.jones_to_mueller(np.diag([1.0, np.exp(1j * phase)])), mu.linear_retarder(phase),
                               atol=1e-12)
    for eta in (0.2 + 3j, 1.5, 0.6):
        rs, rp = mu._fresnel_amplitudes(0.4, eta)
        np.testing.assert_allclose(mu.jones_to_mueller(np.diag([rs, rp])), mu.specular_reflection(0.4, eta),
                                   atol=1e-12)
