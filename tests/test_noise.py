"""Sensor noise model against the EMVA 1288 photon transfer specification (polrig.sensor.noise)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polrig.errors import ConfigError
from polrig.sensor.noise import SensorModel


def test_defaults_and_derived_constants():
    s = SensorModel()
    assert s.max_code_dn == 4095
    assert s.gain_e_per_dn == pytest.approx(10500 / 4095)
    assert s.clip_dn == pytest.approx(4095.0)
    assert s.read_noise_dn == pytest.approx(2.3 / (10500 / 4095))
    assert s.saturation_dn == pytest.approx(s.clip_dn - 5 * s.read_noise_dn - 1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.read_noise_e = 1.0  # type: ignore[misc]
    # an explicit gain wins; a black level lowers the clip level
    t = SensorModel(gain_e_per_dn=1.0, black_level_dn=64)
    assert t.gain_e_per_dn == 1.0 and t.clip_dn == 4095 - 64


@pytest.mark.parametrize("kwargs", [dict(bit_depth=0), dict(bit_depth=17), dict(full_well_e=-1),
                                    dict(read_noise_e=np.nan), dict(gain_e_per_dn=0.0),
                                    dict(quantum_efficiency=1.5), dict(black_level_dn=5000),
                                    # every sample, even a dark one, would count as saturated:
                                    dict(bit_depth=1), dict(full_well_e=10, read_noise_e=50)])
def test_invalid_parameters_raise_config_error(kwargs):
    with pytest.raises(ConfigError):
        SensorModel(**kwargs)


@pytest.mark.parametrize("mean_e", [0.0, 3.0, 50.0, 800.0, 5000.0, 9500.0])
def test_photon_transfer_curve(mean_e):
    """Mean and variance of sampled frames match mu_y and var_y of EMVA 1288 (black level 64
    keeps the dark end unclipped)."""
    s = SensorModel(black_level_dn=64, dark_current_e_per_s=200.0)
    exposure_us = 50_000.0  # 10 dark electrons
    n = 200_000
    raw = s.sample_raw(np.full(n, mean_e), np.random.default_rng(42), exposure_us).astype(np.float64)
    mean_pred = s.mean_dn(mean_e, exposure_us)
    signal_dn = mean_e / s.gain_e_per_dn
    var_pred = s.variance_dn2(signal_dn, exposure_us)
    # standard errors of the sample mean and variance (Gaussian approximation, generous 5 sigma)
    assert raw.mean() == pytest.approx(mean_pred, abs=5 * np.sqrt(var_pred / n) + 1e-3)
    assert raw.var(ddof=1) == pytest.approx(var_pred, rel=5 * np.sqrt(2.0 / n) + 0.01)


def test_variance_terms_and_frame_averaging():
    s = SensorModel(dark_current_e_per_s=0.0)
    g = s.gain_e_per_dn
    assert s.variance_dn2(0.0, 0.0) == pytest.approx((2.3 / g) ** 2 + 1 / 12)
    assert s.variance_dn2(1000.0, 0.0) == pytest.approx(1000 / g + (2.3 / g) ** 2 + 1 / 12)
    assert s.variance_dn2(1000.0, 0.0, n_frames=4) == pytest.approx(s.variance_dn2(1000.0, 0.0) / 4)
    # negative (noisy) signals count as zero signal; arrays broadcast
    v = s.variance_dn2(np.array([-5.0, 0.0, 10.0]), np.array([1e3, 1e3, 1e3]))
    assert v[0] == v[1] < v[2]
    assert SensorModel(dark_current_e_per_s=1e3).variance_dn2(0.0, 1e6) > s.variance_dn2(0.0, 1e6)


def test_saturation_clips_at_top_code_and_is_detected():
    s = SensorModel()
    rng = np.random.default_rng(0)
    raw = s.sample_raw(np.full(10_000, 3 * s.full_well_e), rng, 1000.0)
    assert raw.max() == s.max_code_dn
    assert (raw >= s.saturation_dn).all()
    # just at the full well half of the samples hit the clip; all are flagged
    at_well = s.sample_raw(np.full(10_000, s.full_well_e), rng, 1000.0)
    assert (at_well >= s.saturation_dn).mean() > 0.45
    # well below saturation nothing is flagged
    low = s.sample_raw(np.full(10_000, 0.8 * s.full_well_e), rng, 1000.0)
    assert not (low >= s.saturation_dn).any()
    # with a black level the ADC clips before the full well
    b = SensorModel(black_level_dn=200)
    assert b.sample_raw(np.array([b.full_well_e]), rng, 0.0)[0] == b.max_code_dn
    assert b.clip_dn == 4095 - 200


def test_reproducible_by_seed_and_shapes():
    s = SensorModel()
    mean = np.linspace(0, 8000, 64 * 48).reshape(64, 48)
    a = s.sample_raw(mean, np.random.default_rng(7), 10_000.0)
    b = s.sample_raw(mean, np.random.default_rng(7), 10_000.0)
    c = s.sample_raw(mean, np.random.default_rng(8), 10_000.0)
    assert a.dtype == np.uint16 and a.shape == (64, 48)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_bad_sampling_input_raises():
    s = SensorModel()
    rng = np.random.default_rng(0)
    for bad in (np.array([np.nan]), np.array([np.inf]), np.array([-1.0])):
        with pytest.raises(ValueError, match="mean_electrons"):
            s.sample_raw(bad, rng, 100.0)
    with pytest.raises(ValueError, match="exposure_us"):
        s.sample_raw(np.array([1.0]), rng, -5.0)


def test_electrons_from_photons():
    assert SensorModel(quantum_efficiency=0.5).electrons_from_photons(np.array([10.0]))[0] == 5.0
