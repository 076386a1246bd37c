"""N-state reference Mueller solve (polrig.solve.reference): exactness, calibrated uncertainty,
masks, state-set checks, frame averaging and HDR merging."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.errors import ConfigError
from polrig.optics import mueller as mu
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import reference as ref


def states(*angles_deg, er=np.inf):
    return mu.polarizer_stokes(np.radians(angles_deg), er)


def physical_mueller_images(rng, c, h, w, scale_dn):
    """Realizable Mueller images (C, 3, 3, H, W): convex sums of 3 random Jones matrices,
    normalised to m00 = scale_dn."""
    j = rng.normal(size=(3, c, h, w, 2, 2)) + 1j * rng.normal(size=(3, c, h, w, 2, 2))
    m = mu.jones_to_mueller(j)
    m = np.einsum("k,k...->...", rng.random(3), m)[..., :3, :3]
    m = m / m[..., :1, :1] * scale_dn
    return np.moveaxis(m, (-2, -1), (1, 2))


# ---------------------------------------------------------------------------- state sets
@pytest.mark.parametrize("angles,expected", [((0, 45, 90, 135), 2.0), ((0, 45, 90), 2 + np.sqrt(2)),
                                             ((0, 60, 120), 2.0)])
def test_condition_numbers_of_state_sets(angles, expected):
    assert ref.condition_number(states(*angles)) == pytest.approx(expected, rel=1e-12)
    assert ref.validate_states(states(*angles)) == pytest.approx(expected, rel=1e-12)
    # scale of the incident states (and partial polarizers' DoLP 1) does not matter
    assert ref.condition_number(3.0 * states(*angles)) == pytest.approx(expected, rel=1e-12)


def test_design_matrix_rows_are_kron():
    s = states(0, 45, 90)
    d = ref.design_matrix(s)
    a = ideal_analyzer_matrix()
    assert d.shape == (12, 9)
    assert np.allclose(d[4 * 2 + 1], np.kron(a[1], s[2]))


def test_bad_state_sets_rejected_with_clear_errors():
    with pytest.raises(ConfigError, match="at least 3"):
        ref.validate_states(states(0, 90))
    with pytest.raises(ValueError, match="collinear"):  # ConfigError is a ValueError
        ref.validate_states(states(0, 90, 180))
    with pytest.raises(ConfigError, match="nearly collinear.*exceeds 50"):
        ref.validate_states(states(0, 1, 2))
    with pytest.raises(ConfigError, match="non-finite"):
        ref.validate_states(np.array([[1.0, np.nan, 0], [1, 0, 0], [1, 0, 1]]))
    with pytest.raises(ConfigError, match=r"\(N, 3\)"):
        ref.validate_states(np.ones((4, 4)))
    assert ref.condition_number(states(0, 90, 180)) == np.inf
    m = np.ones((3, 4, 1, 4, 2, 2))
    with pytest.raises(ConfigError, match="collinear"):
        ref.solve_reference(states(0, 90, 180), m, m)


# ---------------------------------------------------------------------------- exactness
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 12), per_pixel=st.booleans())
def test_noise_free_measurements_recover_m(seed, n, per_pixel):
    rng = np.random.default_rng(seed)
    # random partial polarizers at well-spread angles (condition number stays moderate)
    ang = np.linspace(0, 180, n, endpoint=False) + rng.uniform(-5, 5, n)
    er = np.inf if seed % 3 == 0 else rng.uniform(50, 1e4)  # DoLP 1 and partial polarizers
    s = states(*ang, er=er) * rng.uniform(0.5, 2.0, (n, 1))
    c, h, w = 2, 5, 7
    m = rng.normal(size=(c, 3, 3, h, w)) * 10.0 ** rng.uniform(-3, 4)
    rows = None
    if per_pixel:
        rows = ideal_analyzer_matrix()[None, :, :, None, None] * (1 + 0.05 * rng.normal(size=(c, 4, 3, h, w)))
    meas = ref.forward_measurements(m, s, rows)
    var = rng.uniform(0.5, 2.0, meas.shape)
    res = ref.solve_reference(s, meas, var, analyzer_rows=rows, dtype=np.float64)
    scale = np.abs(m).max()
    assert np.abs(res.mueller - m).max() <= 1e-9 * scale
    assert np.all(res.residual < 1e-12)
    assert np.all((res.mask & ~np.uint8(ref.DARK)) == 0)
    assert np.all(res.n_samples == 4 * n)
    assert res.mueller.shape == res.sigma.shape == (c, 3, 3, h, w)
    assert np.all(res.sigma > 0)


def test_default_output_dtypes_and_chunking():
    rng = np.random.default_rng(1)
    s = states(0, 45, 90, 135)
    m = rng.normal(size=(3, 3, 3, 9, 11)) * 100
    meas = ref.forward_measurements(m, s).astype(np.float32)
    a = ref.solve_reference(s, meas, np.ones_like(meas))
    b = ref.solve_reference(s, meas, np.ones_like(meas), chunk_pixels=7)
    assert a.mueller.dtype == np.float32 and a.mask.dtype == np.uint8
    assert np.array_equal(a.mueller, b.mueller) and np.array_equal(a.mask, b.mask)
    assert np.allclose(a.mueller, m, atol=1e-4 * np.abs(m).max())


# ---------------------------------------------------------------------------- noise
def _capture(sensor, truth, s, rng, exposure_us=10_000.0):
    """Simulate one frame per state: mean DN -> electrons -> raw -> black/dark subtracted."""
    mean_dn = ref.forward_measurements(truth, s)
    raw = sensor.sample_raw(mean_dn * sensor.gain_e_per_dn, rng, exposure_us).astype(np.float64)
    meas = raw - sensor.black_level_dn - sensor.dark_electrons(exposure_us) / sensor.gain_e_per_dn
    var = sensor.variance_dn2(meas, exposure_us)
    return meas, var, raw


def test_sigma_is_calibrated_and_chi2_per_dof_is_one():
    rng = np.random.default_rng(2024)
    sensor = SensorModel(black_level_dn=32)
    s = states(0, 45, 90, 135)  # S0 = 0.5: measured DN = m00 / 2 at most for unpolarized
    truth = physical_mueller_images(rng, 3, 48, 48, scale_dn=3000.0)
    meas, var, _ = _capture(sensor, truth, s, rng)
    res = ref.solve_reference(s, meas, var)
    assert np.all(res.mask == 0)
    z = (res.mueller - truth) / res.sigma
    within = np.mean(np.abs(z) <= 2.0)
    assert within == pytest.approx(0.9545, abs=0.01)
    assert np.std(z) == pytest.approx(1.0, abs=0.03)
    assert np.mean(res.residual) == pytest.approx(1.0, abs=0.05)
    # the N=3 set 0/45/90 is noisier (condition 3.41 vs 2) but equally well calibrated
    s3 = states(0, 45, 90)
    meas3, var3, _ = _capture(sensor, truth, s3, rng)
    res3 = ref.solve_reference(s3, meas3, var3)
    z3 = (res3.mueller - truth) / res3.sigma
    assert np.mean(np.abs(z3) <= 2.0) == pytest.approx(0.9545, abs=0.015)
    assert np.mean(res3.sigma) > np.mean(res.sigma)


def test_saturated_samples_excluded_and_flagged():
    rng = np.random.default_rng(5)
    sensor = SensorModel()
    s = states(0, 45, 90, 135)
    truth = physical_mueller_images(rng, 1, 16, 16, scale_dn=2000.0)
    # a horizontal polarizer-like region: bright under state 0 -> saturates analyzer 0 there
    truth[:, :, :, :8, :8] = (mu.linear_block(mu.polarizer_at(0.0)) * 2.0 * 6000.0)[None, :, :, None, None]
    truth[:, :, :, 12:, 12:] = np.diag([40000.0, 0, 0])[None, :, :, None, None]  # everything saturates
    meas, var, raw = _capture(sensor, truth, s, rng)
    valid = raw - sensor.black_level_dn < sensor.saturation_dn
    assert not valid[:, :, :, :8, :8].all() and not valid[:, :, :, 12:, 12:].any()
    res = ref.solve_reference(s, meas, var, valid)
    partly = res.mask[0, :8, :8]
    assert np.all(partly & ref.SATURATED) and not np.any(partly & ref.ILL_CONDITIONED)
    err = np.abs(res.mueller[0, :, :, :8, :8] - truth[0, :, :, :8, :8]) / res.sigma[0, :, :, :8, :8]
    assert np.mean(err <= 3.0) > 0.97  # still unbiased from the unsaturated samples
    full = res.mask[0, 12:, 12:]
    assert np.all(full == ref.SATURATED | ref.ILL_CONDITIONED)
    assert np.all(res.mueller[0, :, :, 12:, 12:] == 0) and np.all(res.sigma[0, :, :, 12:, 12:] == 0)
    assert np.all(res.mask[0, 8:12, :12] == 0)
    # without the validity mask the clipped samples bias the estimate far beyond sigma
    biased = ref.solve_reference(s, meas, var)
    bias = np.abs(biased.mueller[0, :, :, :8, :8] - truth[0, :, :, :8, :8]) / biased.sigma[0, :, :, :8, :8]
    assert bias.max() > 10
    assert ref.reason_names(int(full[0, 0])) == ("saturated", "ill_conditioned")


def test_dark_pixels_masked():
    rng = np.random.default_rng(6)
    sensor = SensorModel()
    s = states(0, 45, 90, 135)
    truth = physical_mueller_images(rng, 1, 12, 12, scale_dn=1500.0)
    truth[:, :, :, :, :6] = 0.0
    meas, var, _ = _capture(sensor, truth, s, rng)
    res = ref.solve_reference(s, meas, var)
    assert np.all(res.mask[0, :, :6] & ref.DARK)
    assert np.all(res.mask[0, :, 6:] == 0)
    assert np.isfinite(res.mueller).all() and np.isfinite(res.residual).all()
    assert res.reason_counts()["dark"] == 72


def test_nonfinite_samples_and_extremes_give_masks_not_exceptions():
    s = states(0, 45, 90, 135)
    m = np.broadcast_to(np.eye(3)[None, :, :, None, None] * 100.0, (1, 3, 3, 2, 3)).copy()
    meas = ref.forward_measurements(m, s)
    var = np.ones_like(meas)
    meas[1, 0, 2, 0, 0] = np.nan  # one bad sample: solved from the other 15
    meas[:, 0, :, 0, 1] = np.inf  # all bad
    var[2, 0, 1, 1, 0] = 0.0  # non-positive variance
    var[:, 0, :, 1, 1] = -1.0
    meas[:, 0, :, 1, 2] = 0.0  # exactly dark
    res = ref.solve_reference(s, meas, var, dtype=np.float64)
    for arr in (res.mueller, res.sigma, res.residual):
        assert np.isfinite(arr).all()
    assert res.mask[0, 0, 0] == ref.NONFINITE and res.mask[0, 1, 0] == ref.NONFINITE
    assert np.allclose(res.mueller[0, :, :, 0, 0], m[0, :, :, 0, 0])
    assert res.mask[0, 0, 1] == ref.NONFINITE | ref.ILL_CONDITIONED
    assert res.mask[0, 1, 1] == ref.NONFINITE | ref.ILL_CONDITIONED
    assert res.mask[0, 1, 2] == ref.DARK
    assert res.n_samples[0, 0, 0] == 15 and res.n_samples[0, 0, 1] == 0
    assert res.pixel_condition[0, 0, 0] > 2.0 and res.pixel_condition[0, 0, 1] == np.inf
    # the calibration term keeps outputs finite and masks unchanged (0 where unsolved)
    rt = ref.solve_reference(s, meas, var, analyzer_tolerance=A_TOL, generator_tolerance=G_TOL,
                             dtype=np.float64)
    assert np.isfinite(rt.sigma).all() and np.array_equal(rt.mask, res.mask)
    assert np.all(rt.sigma[0, :, :, 0, 1] == 0) and np.all(rt.sigma >= rt.sigma_noise)


def test_shape_errors_are_value_errors():
    s = states(0, 45, 90, 135)
    good = np.ones((4, 1, 4, 2, 2))
    with pytest.raises(ValueError, match="N=4"):
        ref.solve_reference(s, np.ones((3, 1, 4, 2, 2)), np.ones((3, 1, 4, 2, 2)))
    with pytest.raises(ValueError, match="variance shape"):
        ref.solve_reference(s, good, np.ones((4, 1, 4, 2, 3)))
    with pytest.raises(ValueError, match="valid shape"):
        ref.solve_reference(s, good, good, np.ones((4, 1, 4, 1, 2), bool))
    with pytest.raises(ValueError, match="analyzer rows"):
        ref.solve_reference(s, good, good, analyzer_rows=np.ones((4, 3, 5, 5)))


def test_reason_names():
    assert ref.reason_names() == {1: "dark", 2: "saturated", 4: "ill_conditioned", 8: "nonfinite"}
    assert ref.reason_names(0) == ()
    assert ref.reason_names(ref.DARK | ref.NONFINITE) == ("dark", "nonfinite")


# ---------------------------------------------------------------------------- frames, HDR
def test_average_frames_mean_and_variance_of_mean():
    rng = np.random.default_rng(9)
    frames = rng.normal(100.0, 4.0, size=(16, 20000))
    mean, var = ref.average_frames(frames)
    assert np.mean(mean) == pytest.approx(100.0, abs=0.05)
    assert np.mean(var) == pytest.approx(16.0 / 16, rel=0.02)
    frames[3, :10] = 4095
    mean_s, _ = ref.average_frames(frames, saturation_dn=4000)
    assert np.all(mean_s[:10] == 4000) and np.array_equal(mean_s[10:], mean[10:])
    with pytest.raises(ValueError, match="at least 2 frames"):
        ref.average_frames(frames[:1])


def test_merge_hdr_unbiased_calibrated_and_masks_saturation():
    rng = np.random.default_rng(11)
    sensor = SensorModel(black_level_dn=16)
    # radiance in electrons per microsecond, spanning 4 decades
    rate = np.repeat(np.logspace(-3, 1.2, 60), 4000)
    exposures = [100.0, 1000.0, 10000.0]
    brackets = []
    for t in exposures:
        raw = sensor.sample_raw(rate * t, rng, t).astype(np.float64)
        brackets.append((raw - sensor.black_level_dn - sensor.dark_electrons(t) / sensor.gain_e_per_dn, t))
    rad, var, valid = ref.merge_hdr(brackets, sensor.saturation_dn, sensor)
    truth = rate * 10000.0 / sensor.gain_e_per_dn  # DN at the reference (longest) exposure
    assert valid[truth < 0.9 * 10 * sensor.clip_dn].all()  # the shortest exposure still reads them
    z = (rad - truth) / np.sqrt(var)
    assert np.all(np.isfinite(z))
    # the brightest pixels are above the long exposure's clip: merged from the shorter ones
    bright = truth > 2 * sensor.clip_dn
    assert bright.sum() > 1000
    for sel in (bright, ~bright):
        assert np.mean(z[sel]) == pytest.approx(0.0, abs=0.08)
        assert np.std(z[sel]) == pytest.approx(1.0, abs=0.08)
    # pixels saturated in every exposure are invalid, finite, and not counted
    sat = sensor.sample_raw(np.full(10, 1e7), rng, 100.0).astype(np.float64)
    r2, v2, ok2 = ref.merge_hdr([(sat, 100.0), (sat, 1000.0)], sensor.saturation_dn, sensor,
                                reference_exposure_us=100.0)
    assert not ok2.any() and np.isfinite(r2).all() and np.all(v2 == 0)
    with pytest.raises(ValueError, match="exposures"):
        ref.merge_hdr([(sat, -1.0)], sensor.saturation_dn, sensor)
    with pytest.raises(ValueError, match="shape"):
        ref.merge_hdr([(sat, 1.0), (sat[:3], 2.0)], sensor.saturation_dn, sensor)


# ---------------------------------------------------------------------------- calibration sigma
A_TOL = (0.01, 0.5, 0.02)  # relative gain, orientation deg, diattenuation (1 sigma)
G_TOL = (2.0, 0.006)  # stage zero offset deg, 1/ER (1 sigma)


def _sensor_weighted(truth, s, rows=None, exposure_us=10_000.0):
    """Noise-free samples with the sensor model's variances as weights (a weighted solve)."""
    meas = ref.forward_measurements(truth, s, rows)
    return meas, SensorModel().variance_dn2(np.clip(meas, 0, None), exposure_us)


def test_exact_calibration_gives_the_noise_sigma_and_tolerances_change_only_sigma():
    rng = np.random.default_rng(5)
    truth = physical_mueller_images(rng, 2, 9, 11, scale_dn=2000.0)
    s = states(0, 45, 90, 135)
    meas, var = _sensor_weighted(truth, s)
    meas[0, 0, 1, 2, 3] = np.nan  # a pixel with an excluded sample: its own weights
    base = ref.solve_reference(s, meas, var, dtype=np.float64)
    for a_tol, g_tol in ((None, None), ((0, 0, 0), (0, 0)), ((0.0, 0.0, 0.0), None)):
        r = ref.solve_reference(s, meas, var, analyzer_tolerance=a_tol,
                                generator_tolerance=g_tol, dtype=np.float64)
        assert np.array_equal(r.sigma, base.sigma) and r.sigma_noise is r.sigma
    r = ref.solve_reference(s, meas, var, analyzer_tolerance=A_TOL, generator_tolerance=G_TOL,
                            dtype=np.float64)
    assert np.array_equal(r.sigma_noise, base.sigma)
    assert np.array_equal(r.mueller, base.mueller) and np.array_equal(r.mask, base.mask)
    assert np.all(r.sigma >= r.sigma_noise) and np.mean(r.sigma > r.sigma_noise) > 0.9
    with pytest.raises(ConfigError, match="finite and >= 0"):
        ref.solve_reference(s, meas, var, analyzer_tolerance=(0.01, -1, 0))
    with pytest.raises(ConfigError, match="2 numbers"):
        ref.solve_reference(s, meas, var, generator_tolerance=(1.0,))


@pytest.mark.parametrize("per_pixel_rows", [False, True])
def test_calibration_sigma_of_the_unweighted_solve_is_the_closed_form(per_pixel_rows):
    """Equal weights: analyzer errors give dM = A0^+ dA M, generator errors
    dM = M dS^T (S^+)^T (polrig.solve.reference docstring); per-pixel ideal rows take the general
    path and must agree."""
    rng = np.random.default_rng(7)
    m = rng.normal(size=(1, 3, 3, 6, 5))
    s = states(0, 30, 75, 120, 160)
    a0 = ideal_analyzer_matrix()
    rows = np.broadcast_to(a0[:, :, None, None], (4, 3, 6, 5)) if per_pixel_rows else None
    meas = ref.forward_measurements(m, s, rows)
    ones = np.ones_like(meas)
    ra = ref.solve_reference(s, meas, ones, None, rows, analyzer_tolerance=A_TOL, dtype=np.float64)
    rg = ref.solve_reference(s, meas, ones, None, rows, generator_tolerance=G_TOL, dtype=np.float64)
    mm = np.moveaxis(m[0], (0, 1), (-2, -1))  # (H, W, 3, 3)
    t = np.radians([0, 45, 90, 135])
    da_dt = np.stack([0 * t, -np.sin(2 * t), np.cos(2 * t)], 1)  # d a_j / d t (per rad)
    da_dd = 0.5 * np.stack([0 * t, np.cos(2 * t), np.sin(2 * t)], 1)  # d a_j / d D
    proj = lambda d: np.einsum("ja,hwal->hwjl", d, mm) ** 2  # noqa: E731  (d_j . M[:, l])^2
    var_a = np.einsum("ij,hwjl->hwil", np.linalg.pinv(a0) ** 2,
                      A_TOL[0] ** 2 * proj(a0) + np.radians(A_TOL[1]) ** 2 * proj(da_dt)
                      + A_TOL[2] ** 2 * proj(da_dd))
    sp = np.linalg.pinv(s)  # (3, N)
    ds_phi = np.stack([0 * s[:, 0], -2 * s[:, 2], 2 * s[:, 1]], 1)
    ang = 2 * np.radians([0, 30, 75, 120, 160])
    ds_e = 0.5 * np.stack([np.ones(5), -np.cos(ang), -np.sin(ang)], 1)
    var_g = sum((tol * np.einsum("hwab,kb,ck->hwac", mm, d, sp)) ** 2
                for tol, d in ((np.radians(G_TOL[0]), ds_phi), (G_TOL[1], ds_e)))
    for r, var in ((ra, var_a), (rg, var_g)):
        cal = np.sqrt(r.sigma[0] ** 2 - r.sigma_noise[0] ** 2)
        assert np.allclose(np.moveaxis(cal, (0, 1), (-2, -1)), np.sqrt(var),
                           rtol=1e-6, atol=1e-9 * np.abs(m).max())


def _coverage(err, res):
    """Fraction of elements within 2 sigma_cal (noise-free data: the error is calibration's)."""
    cal = np.sqrt(np.clip(res.sigma**2 - res.sigma_noise**2, 0, None))
    assert np.all(res.mask == 0) and np.all(cal > 0)
    return np.mean(np.abs(err) <= 2 * cal)


def test_analyzer_errors_from_the_tolerances_fall_within_2_sigma_cal():
    """Per-pixel analyzer rows drawn from the stated tolerance distributions (independent per
    micro-polarizer), noise off, weighted solve with the ideal rows: 95.45 % of the elements
    lie within 2 sigma_cal (0.9 % is about 3 binomial sd for elements of ~5000 pixels,
    correlated within a pixel)."""
    rng = np.random.default_rng(11)
    c, h, w = 3, 40, 40
    truth = physical_mueller_images(rng, c, h, w, scale_dn=3000.0)
    g = 1 + A_TOL[0] * rng.normal(size=(c, 4, h, w))
    t = (np.radians([0, 45, 90, 135])[None, :, None, None]
         + np.radians(A_TOL[1]) * rng.normal(size=(c, 4, h, w)))
    d = 1 + A_TOL[2] * rng.normal(size=(c, 4, h, w))
    rows = 0.5 * g[:, :, None] * np.stack([np.ones_like(t), d * np.cos(2 * t),
                                           d * np.sin(2 * t)], 2)
    s = states(0, 45, 90, 135) * 1.0
    meas, var = _sensor_weighted(truth, s, rows)
    res = ref.solve_reference(s, meas, var, analyzer_tolerance=A_TOL, dtype=np.float64)
    assert _coverage(res.mueller - truth, res) == pytest.approx(0.9545, abs=0.009)


def test_generator_errors_from_the_tolerances_fall_within_2_sigma_cal():
    """Stage zero offset ~ N(0, 2 deg) and 1/ER = |N(0, 0.006)| drawn per pixel (each pixel an
    independent rig), solved with the nominal ideal polarizer states: 95.45 % within
    2 sigma_cal. Six states, one of them measured twice (weights from the sensor model)."""
    rng = np.random.default_rng(12)
    c, h, w = 2, 50, 50
    truth = physical_mueller_images(rng, c, h, w, scale_dn=3000.0)
    stage = np.array([0, 30, 60, 90, 120, 150])
    phi = np.radians(G_TOL[0]) * rng.normal(size=(c, h, w))
    er = 1 / np.maximum(np.abs(G_TOL[1] * rng.normal(size=(c, h, w))), 1e-12)
    s_true = mu.polarizer_stokes(np.radians(stage)[:, None, None, None] + phi, er)  # (N,C,H,W,3)
    meas = np.einsum("ja,cabhw,kchwb->kcjhw", ideal_analyzer_matrix(), truth, s_true)
    var = SensorModel().variance_dn2(np.clip(meas, 0, None), 10_000.0)
    s = states(*stage)
    res = ref.solve_reference(s, meas, var, generator_tolerance=G_TOL, dtype=np.float64)
    assert _coverage(res.mueller - truth, res) == pytest.approx(0.9545, abs=0.009)
