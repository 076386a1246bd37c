"""The virtual polarizer (polrig.optics.virtual_polarizer): closed forms, py-pol as the oracle,
sigma, NaN handling."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics import mueller as mu
from polrig.optics.virtual_polarizer import (
    analyzer_row,
    incident_stokes,
    virtual_polarizer,
    virtual_polarizer_image,
)

angles = st.floats(-360, 360, allow_nan=False)


@settings(max_examples=50, deadline=None)
@given(psi=angles, theta=angles, a=st.floats(0, 1))
def test_malus_law_through_a_depolarizer(psi, theta, a):
    """Identity scaled by m00 and an isotropic depolarizer: I = m00 (1 + a cos 2(theta - psi)) / 4
    (incident S0 = 1/2, analyzer (1 + ...) / 2)."""
    m = 800.0 * mu.partial_depolarizer(a)[:3, :3]
    i, _ = virtual_polarizer(m, psi, theta)
    assert i == pytest.approx(800.0 * (1 + a * np.cos(np.radians(2 * (theta - psi)))) / 4)


def test_unpolarized_and_no_analyzer():
    rng = np.random.default_rng(1)
    m = rng.uniform(-1, 1, (3, 3)) + np.diag([3.0, 0, 0])
    # unpolarized light: the mean over polarizer angles; no analyzer: the total S0
    mean = np.mean([virtual_polarizer(m, p, 30.0)[0] for p in np.arange(0, 180, 1.0)])
    assert virtual_polarizer(m, None, 30.0)[0] == pytest.approx(mean)
    assert virtual_polarizer(m, 10.0, None)[0] == pytest.approx(
        virtual_polarizer(m, 10.0, 10.0)[0] + virtual_polarizer(m, 10.0, 100.0)[0])
    assert virtual_polarizer(m, None, None)[0] == pytest.approx(0.5 * m[0, 0])
    np.testing.assert_allclose(analyzer_row(None), [1, 0, 0])
    np.testing.assert_allclose(incident_stokes(None), [0.5, 0, 0])
    np.testing.assert_allclose(incident_stokes(0.0), mu.polarizer_stokes(0.0))  # the rig's states
    np.testing.assert_allclose(analyzer_row(45.0), [0.5, 0, 0.5], atol=1e-15)


def test_equals_py_pol_on_random_physical_matrices():
    """The image equals py-pol's chain: linear light at psi (intensity 1/2) through M, then an
    ideal linear polarizer at theta, intensity of the result (4x4, compared for S3-free input)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pp_m = pytest.importorskip("py_pol.mueller")
        pp_s = pytest.importorskip("py_pol.stokes")
    from test_parameters import random_physical

    rng = np.random.default_rng(7)
    for _ in range(40):
        m4 = random_physical(rng) * rng.uniform(1, 1000)
        psi, theta = rng.uniform(0, 180, 2)
        with warnings.catch_warnings():  # py-pol warns about its own Stokes conversions
            warnings.simplefilter("ignore")
            s = pp_s.Stokes("s")
            s.linear_light(azimuth=np.radians(psi), intensity=0.5)
            sample, analyzer = pp_m.Mueller("m"), pp_m.Mueller("a")
            sample.from_matrix(m4)
            analyzer.diattenuator_perfect(azimuth=np.radians(theta))
            ref = float(np.real((analyzer * (sample * s)).parameters.intensity()))
        ours, _ = virtual_polarizer(m4[:3, :3], psi, theta)
        assert ours == pytest.approx(ref, rel=1e-9, abs=1e-9 * abs(m4[0, 0]))


def test_sigma_is_the_linear_propagation_and_nan_only_where_used():
    m = mu.retarder_at(0.3, 1.0)[:3, :3] * 100
    sig = np.arange(1.0, 10.0).reshape(3, 3)
    i, s = virtual_polarizer(m, 0.0, 45.0, sig)
    w = np.outer(analyzer_row(45.0), incident_stokes(0.0))
    assert s == pytest.approx(np.sqrt(np.sum((w * sig) ** 2)))
    bad = m.copy()
    bad[2, 2] = np.nan  # used by (0 deg in, 45 deg analyzer)? w[2, 2] = 0.5 * sin 90 * sin 0 = 0
    i2, _ = virtual_polarizer(bad, 0.0, 45.0)
    assert i2 == pytest.approx(i)
    assert np.isnan(virtual_polarizer(bad, 45.0, 45.0)[0])


def test_image_function_matches_the_per_pixel_one():
    rng = np.random.default_rng(2)
    img = rng.uniform(-1, 1, (3, 3, 3, 4, 5)).astype(np.float32) + 5 * np.eye(3)[None, :, :, None, None]
    sig = np.full(img.shape, 0.5, np.float32)
    i, s = virtual_polarizer_image(img, 20.0, 70.0, sig)
    ref, rs = virtual_polarizer(np.moveaxis(img, (1, 2), (-2, -1)), 20.0, 70.0, np.full((3, 3), 0.5))
    np.testing.assert_allclose(i, ref, rtol=1e-6)
    np.testing.assert_allclose(s, rs, rtol=1e-6)
    assert i.shape == (3, 4, 5) and i.dtype == np.float32
    assert virtual_polarizer_image(img, None, None)[1] is None
    with pytest.raises(ValueError, match="scalar"):
        virtual_polarizer_image(img, [0.0, 1.0], 0.0)
