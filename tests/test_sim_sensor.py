"""Simulated generator and DoFP sensor: incident states, radiometry, noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.noise import SensorModel
from polrig.sim import create_sim_rig
from polrig.sim.generator import Generator
from polrig.sim.sensor import DoFPSensor, gain_factor, random_analyzer

VIRTUAL = float("inf")


@pytest.mark.parametrize("er", [2.0, 50.0, 800.0, np.inf])
@pytest.mark.parametrize("offset", [0.0, 1.7, -13.0])
def test_incident_state_of_a_leaky_offset_polarizer(er, offset):
    gen = Generator(offset, er)
    theta = np.array([0.0, 30.0, 45.0, 90.0, 135.0, 400.0])
    s = gen.incident_stokes(theta)
    minor = 0.0 if np.isinf(er) else 1.0 / er
    np.testing.assert_allclose(s[:, 0], 0.5 * (1 + minor))
    dolp = np.hypot(s[:, 1], s[:, 2]) / s[:, 0]
    np.testing.assert_allclose(dolp, (1 - minor) / (1 + minor))
    aolp = np.rad2deg(0.5 * np.arctan2(s[:, 2], s[:, 1])) % 180
    np.testing.assert_allclose(aolp, (theta + offset) % 180, atol=1e-9)


def test_generator_rejects_impossible_extinction():
    with pytest.raises(ValueError, match="extinction"):
        Generator(0.0, 0.5)


def _flat_sensor(bit_depth=12, black=64.0, shape=(256, 256), layout="imx250mzr"):
    model = SensorModel(bit_depth=bit_depth, black_level_dn=black, dark_current_e_per_s=50.0)
    return DoFPSensor(AnalyzerModel.ideal(layout, shape), model)


@pytest.mark.parametrize("gain_db", [0.0, 6.0])
def test_noise_mean_and_variance_follow_the_photon_transfer_model(gain_db):
    sensor = _flat_sensor()
    rng = np.random.default_rng(5)
    exposure = 100000.0
    model = sensor.gained_model(gain_db)
    for signal in (0.0, 5.0, 80.0, 900.0, 2500.0):
        sig = np.full(sensor.shape, signal)
        raw = sensor.expose(sig, exposure_us=exposure, gain_db=gain_db, rng=rng)
        assert raw.dtype == np.uint16
        mean_expected = model.black_level_dn + signal + model.dark_electrons(exposure) / model.gain_e_per_dn
        var_expected = model.variance_dn2(signal, exposure)
        n = raw.size
        assert abs(raw.mean() - mean_expected) < 5 * np.sqrt(var_expected / n) + 0.02
        assert raw.var() == pytest.approx(var_expected, rel=5 * np.sqrt(2 / n) + 0.01)
        exact = sensor.expose(sig, exposure_us=exposure, gain_db=gain_db, rng=None, noise=False)
        np.testing.assert_allclose(exact, mean_expected)
    # gain: 6 dB doubles the DN per electron
    assert gain_factor(6.0) == pytest.approx(1.9953, rel=1e-4)


def test_saturation_and_8_bit_quantization():
    sensor = _flat_sensor(bit_depth=8, black=2.0, shape=(64, 64))
    model = sensor.model
    rng = np.random.default_rng(1)
    raw = sensor.expose(np.full(sensor.shape, 1e6), exposure_us=1000.0, gain_db=0.0, rng=rng)
    assert raw.max() <= 255 and (raw >= 250).all()
    exact = sensor.expose(np.full(sensor.shape, 1e6), exposure_us=1000.0, gain_db=0.0, rng=None,
                          noise=False)
    np.testing.assert_allclose(exact, min(model.black_level_dn + model.full_well_e / model.gain_e_per_dn,
                                          model.max_code_dn))
    mid = sensor.expose(np.full(sensor.shape, 100.3), exposure_us=1000.0, gain_db=0.0, rng=rng)
    assert np.all(mid == np.round(mid))  # integer codes
    with pytest.raises(ValueError, match="rng"):
        sensor.expose(np.zeros(sensor.shape), exposure_us=1.0, gain_db=0.0, rng=None)


def test_frames_are_reproducible_by_seed_and_differ_across_seeds():
    def frames(seed):
        rig = create_sim_rig({"size": (64, 48), "seed": seed, "clock_speed": VIRTUAL})
        return rig.camera.grab().raw, rig.world.sensor.analyzer.angle_deg

    a, ang_a = frames(3)
    b, ang_b = frames(3)
    c, ang_c = frames(4)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ang_a, ang_b)
    assert (a != c).mean() > 0.1
    assert not np.array_equal(ang_a, ang_c)


def test_noise_free_raw_is_the_analyzer_forward_model_of_the_truth():
    rig = create_sim_rig({"size": (64, 48), "noise": False, "clock_speed": VIRTUAL})
    w = rig.world
    roi = w.full_roi
    stage = 30.0
    s_in = w.generator.incident_stokes(stage)
    truth = rig.truth.ground_truth()["mueller"]  # (C, 3, 3, H, W)
    stokes = np.einsum("cijhw,j->cihw", truth.astype(np.float64), s_in)
    model = w.sensor.model
    exp_us = rig.camera.exposure_us
    expected = (model.black_level_dn + model.dark_electrons(exp_us) / model.gain_e_per_dn
                + w.sensor.analyzer.mosaic(stokes))
    got = w.raw(turntable_deg=0.0, stage_deg=stage, exposure_us=exp_us, gain_db=0.0, roi=roi)
    lin = expected < model.clip_dn
    np.testing.assert_allclose(got[lin], expected[lin], rtol=1e-5)
    # the hidden analyzer is not ideal: an ideal one reads differently
    ideal = AnalyzerModel.ideal(w.sensor.layout, w.sensor.shape).mosaic(stokes)
    assert np.abs(ideal - w.sensor.analyzer.mosaic(stokes)).max() > 1.0


def test_random_analyzer_statistics():
    rng = np.random.default_rng(0)
    a = random_analyzer("imx250myr", (128, 128), rng, angle_sigma_deg=0.5, angle_bias_deg=0.0,
                        diattenuation_mean=0.97, diattenuation_sigma=0.01, gain_sigma=0.02)
    err = a.angle_deg - AnalyzerModel.ideal("imx250myr", (128, 128)).angle_deg
    assert err.std() == pytest.approx(0.5, rel=0.05)
    assert a.diattenuation.mean() == pytest.approx(0.97, abs=0.002)
    assert a.gain.std() == pytest.approx(0.02, rel=0.05)
    assert a.diattenuation.max() <= 1.0
