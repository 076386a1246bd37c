"""Scoring a result against the simulator's truth (polrig.app.processing.score_against_truth)."""

from __future__ import annotations

import math

import numpy as np

from polrig.app.processing import format_score, score_against_truth
from polrig.solve.reference import ReferenceResult


def _result(mueller: np.ndarray, sigma: float = 0.1) -> ReferenceResult:
    c, h, w = mueller.shape[0], mueller.shape[-2], mueller.shape[-1]
    zeros = np.zeros((c, h, w), np.float32)
    return ReferenceResult(mueller.astype(np.float32), np.full_like(mueller, sigma, np.float32), zeros,
                           np.zeros((c, h, w), np.uint8), 1.0, zeros + 1.0, np.full((c, h, w), 4, np.uint16))


def _depolarizer(value: float, shape=(3, 3, 3, 4, 5)) -> np.ndarray:
    m = np.zeros(shape)
    m[:, 0, 0] = value
    return m


def test_psnr_is_peak_over_rmse():
    truth = _depolarizer(2.0)
    result = _result(truth + 0.02)
    score = score_against_truth(result, truth)
    assert math.isclose(score["rmse"], 0.02, rel_tol=1e-5)
    assert math.isclose(score["psnr_db"], 20 * math.log10(2.0 / 0.02), rel_tol=1e-5)
    assert score["pixels_compared"] == 3 * 4 * 5
    assert "PSNR 40.0 dB" in format_score(score)


def test_exact_result_scores_inf():
    truth = _depolarizer(2.0)
    score = score_against_truth(_result(truth), truth)
    assert score["psnr_db"] == float("inf") and score["rmse"] == 0.0
    assert "PSNR inf" in format_score(score)


def test_dark_truth_has_no_psnr_but_keeps_the_error():
    """An object turned so that only its unlit back faces the camera: every compared truth
    pixel is 0. The PSNR has no peak; the score must say so, not raise (a turntable capture
    used to abort here)."""
    truth = _depolarizer(0.0)
    score = score_against_truth(_result(truth + 0.05), truth)
    assert score["psnr_db"] is None
    assert math.isclose(score["rmse"], 0.05, rel_tol=1e-5)
    line = format_score(score)
    assert "PSNR n/a" in line and "RMSE 0.05" in line


def test_object_mask_limits_the_pixels():
    truth = _depolarizer(1.0)
    obj = np.zeros((4, 5), bool)
    obj[1:3, 1:4] = True
    score = score_against_truth(_result(truth), truth, obj)
    assert score["pixels_compared"] == 3 * 6
    empty = score_against_truth(_result(truth), truth, np.zeros((4, 5), bool))
    assert empty["pixels_compared"] == 0 and empty["psnr_db"] is None
    assert format_score(empty) == "no pixels to score"


# -- truth on the output grid and banded scoring ------------------------------------------------
import pytest  # noqa: E402

from polrig.optics.mueller import polarizer_stokes  # noqa: E402
from polrig.sensor.analyzer import AnalyzerModel  # noqa: E402
from polrig.sensor.demosaic import METHODS, demosaic_float  # noqa: E402
from polrig.sensor.layouts import IMX250MYR, IMX250MZR  # noqa: E402
from polrig.sensor.noise import SensorModel  # noqa: E402
from polrig.solve.radiometry import StateRadiance, reference_from_frames  # noqa: E402
from polrig.solve.scoring import score_on_output_grid, truth_on_output_grid  # noqa: E402

S_IN = polarizer_stokes(np.deg2rad([0, 45, 90, 135]), intensity=1.0)


def _scene(c: int, h: int = 45, w: int = 56) -> np.ndarray:
    """Uniform background, a uniform block, and a region whose matrix varies pixel by pixel."""
    t = np.empty((c, 3, 3, h, w))
    t[...] = (600 * np.array([[1, 0.1, 0], [0.1, 0.8, 0.05], [0, -0.05, 0.7]]))[None, :, :, None, None]
    t[..., 6:22, 4:20] *= 1.7
    u = np.arange(w)[None, :]
    t[..., 30:, 22:] *= 1 + 0.02 * u[:, 22:] + 0.01 * np.arange(h - 30)[:, None]
    return t


def _capture(t, layout, rng, model=SensorModel(), exposure_us=1000.0):
    """Noisy states of a truth image, some samples excluded (the capture's own weights)."""
    ideal = AnalyzerModel.ideal(layout, t.shape[-2:])
    out = []
    for s in S_IN:
        mosaic = ideal.mosaic(np.einsum("cijhw,j->cihw", t, s))
        var = model.variance_dn2(mosaic, exposure_us)
        out.append(StateRadiance((mosaic + rng.standard_normal(mosaic.shape) * np.sqrt(var)),
                                 var, rng.random(mosaic.shape) < 0.02))
    return out


def _definition(t, layout, method, weights_like):
    """truth_on_output_grid's meaning, computed literally: the noise-free mosaics with the
    capture's weights, demosaiced and solved like a capture."""
    ideal = AnalyzerModel.ideal(layout, t.shape[-2:])
    states = [StateRadiance(ideal.mosaic(np.einsum("cijhw,j->cihw", t, s)), like.variance_dn2,
                            like.excluded) for s, like in zip(S_IN, weights_like)]
    return reference_from_frames(states, S_IN, layout, method)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR.shifted(1, 2)])
def test_truth_on_output_grid_is_the_noise_free_estimate(layout, method):
    """The cheap truth (uniform support -> the truth itself, the rest solved) equals the
    literal definition wherever that solve is valid; it is the truth exactly on uniform
    supports, and the solved pixels are the definition's (to rounding: the solve of a subset of
    pixels may round differently in the last bits)."""
    rng = np.random.default_rng(5)
    t = _scene(layout.n_colours)
    like = _capture(t, layout, rng)
    got = truth_on_output_grid(t, layout, method, S_IN, like, band_pixels=300)
    ref = _definition(t, layout, method, like)
    assert got.shape == ref.mueller.shape and got.dtype == np.float32
    peak = np.abs(t).max()
    ok = np.broadcast_to(ref.valid[:, None, None], got.shape)
    assert np.abs(got - ref.mueller)[ok].max() <= 1e-6 * peak
    # uniform over the support: the truth itself (first pixel of the cell for superpixel)
    on_grid = t[..., ::layout.period[0], ::layout.period[1]] if method == "superpixel" else t
    on_grid = on_grid[..., :got.shape[-2], :got.shape[-1]]
    ph, pw = layout.period if method == "superpixel" else (1, 1)
    rows, cols = np.arange(got.shape[-2]), np.arange(got.shape[-1])
    far = ((rows * ph + ph - 1 <= 16)[:, None]  # 14 px or more from any change of the truth
           & (cols * pw >= 34)[None, :])
    assert far.sum() >= 8
    np.testing.assert_array_equal(got[..., far], on_grid[..., far].astype(np.float32))
    # where the truth varies inside the support the estimate mixes matrices: not the truth
    mixed = np.abs(got - on_grid).max(axis=(0, 1, 2)) > 1e-3 * peak
    assert mixed.any()
    sel = mixed & ref.valid.all(axis=0)
    np.testing.assert_allclose(got[..., sel], ref.mueller[..., sel], rtol=0, atol=1e-9 * peak)


def test_truth_on_output_grid_with_the_noise_model_weights():
    model = SensorModel()
    t = _scene(1)
    got = truth_on_output_grid(t, IMX250MZR, "bilinear", S_IN, model=model, exposure_us=800.0)
    ideal = AnalyzerModel.ideal(IMX250MZR, t.shape[-2:])
    mosaics = [ideal.mosaic(np.einsum("cijhw,j->cihw", t, s)) for s in S_IN]
    states = [StateRadiance(m, model.variance_dn2(m, 800.0), np.zeros(m.shape, bool))
              for m in mosaics]
    ref = reference_from_frames(states, S_IN, IMX250MZR, "bilinear").mueller
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6 * np.abs(t).max())
    with pytest.raises(ValueError, match="give weights_like, or model and exposure_us"):
        truth_on_output_grid(t, IMX250MZR, "bilinear", S_IN)
    with pytest.raises(ValueError, match=r"truth must have shape \(3, 3, 3, H, W\)"):
        truth_on_output_grid(t, IMX250MYR, "bilinear", S_IN, model=model, exposure_us=800.0)


@pytest.mark.parametrize("method", METHODS)
def test_score_on_output_grid_equals_the_two_step_score(method):
    """Band by band against the full-resolution truth = truth_on_output_grid, then
    score_against_truth over the output pixels whose support lies on the object."""
    layout = IMX250MYR
    rng = np.random.default_rng(9)
    t = _scene(3)
    like = _capture(t, layout, rng)
    result = reference_from_frames(like, S_IN, layout, method,
                                   analyzer_tolerance=(0.01, 0.5, 0.02))
    obj = np.ones(t.shape[-2:], np.float32)
    obj[:5] = 0
    obj[:, -7:] = 0
    support = demosaic_float(obj, layout, method).min(axis=(0, 1)) >= 1.0
    two_step = score_against_truth(result, truth_on_output_grid(t, layout, method, S_IN, like),
                                   support)
    banded = score_on_output_grid(result, t, layout, method, S_IN, like, object_mask=obj,
                                  band_pixels=400)
    assert two_step["pixels_compared"] > 100
    assert banded.keys() == two_step.keys()
    for key, value in two_step.items():
        if isinstance(value, float):
            assert math.isclose(banded[key], value, rel_tol=1e-12), key
        else:
            assert banded[key] == value, key


def test_banded_score_sums_match_the_closed_form():
    """More rows than one band: errors of 0.1 and 0.3 on alternate rows, sigma 0.1: half the
    elements within 2 sigma, chi^2 per element (1 + 9) / 2, RMSE sqrt((0.01 + 0.09) / 2)."""
    h = 3 * 64 + 5
    truth = _depolarizer(2.0, shape=(1, 3, 3, h, 4))
    err = np.where(np.arange(h) % 2 == 0, 0.1, 0.3)[:, None]
    score = score_against_truth(_result(truth + err, sigma=0.1), truth)
    assert score["pixels_compared"] == h * 4
    frac_even = np.mean(np.arange(h) % 2 == 0)
    assert math.isclose(score["within_2sigma"], frac_even, rel_tol=1e-9)
    assert math.isclose(score["chi2_per_element"], frac_even * 1 + (1 - frac_even) * 9,
                        rel_tol=1e-5)
    assert math.isclose(score["rmse"], math.sqrt(frac_even * 0.01 + (1 - frac_even) * 0.09),
                        rel_tol=1e-6)
    assert math.isclose(score["mean_sigma"], 0.1, rel_tol=1e-6)


def test_realizability_of_a_large_result_is_a_regular_subsample(monkeypatch):
    """Beyond REALIZABILITY_SAMPLES pixels every k-th compared pixel is tested: a pattern of
    one non-physical matrix in three keeps its pass rate of 2/3 under a stride of 2."""
    import polrig.solve.scoring as scoring

    h, w = 9, 10
    truth = _depolarizer(1.0, shape=(1, 3, 3, h, w))
    bad = (np.arange(h * w).reshape(h, w) % 3) == 0
    m = truth.copy()
    m[0, 1, 1][bad] = 5.0  # |m11| > m00: not a Mueller matrix
    full = score_against_truth(_result(m), truth)
    monkeypatch.setattr(scoring, "REALIZABILITY_SAMPLES", h * w // 2)
    sampled = score_against_truth(_result(m), truth)
    assert math.isclose(full["realizable"], 2 / 3)
    assert math.isclose(sampled["realizable"], 2 / 3, abs_tol=1 / 45)
    assert sampled["rmse"] == full["rmse"]


@pytest.mark.parametrize("method", METHODS)
def test_a_non_finite_truth_pixel_is_never_taken_as_uniform(method):
    """A NaN in the truth makes its neighbourhood non-uniform: those pixels go through the
    solve (as the definition does), and are not replaced by a finite neighbour's matrix."""
    layout = IMX250MZR
    t = _scene(1)
    t[0, 1, 1, 8, 40] = np.nan
    rng = np.random.default_rng(2)
    like = _capture(np.nan_to_num(t), layout, rng)
    got = truth_on_output_grid(t, layout, method, S_IN, like)
    ref = _definition(t, layout, method, like)
    y, x = (4, 20) if method == "superpixel" else (8, 40)
    np.testing.assert_allclose(got[..., y, x], ref.mueller[..., y, x], rtol=0,
                               atol=1e-9 * np.nanmax(t))
    assert not ref.valid[0, y, x]  # the solve flags the non-finite sample
