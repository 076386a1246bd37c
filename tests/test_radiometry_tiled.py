"""Band-tiled radiometry (polrig.solve.radiometry): the banded state radiance and reference solve
give the same numbers as the whole image at once, for every layout, phase, demosaic method
and band boundary; half-precision uncertainty planes; bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.demosaic import METHODS
from polrig.sensor.layouts import IMX250MYR, IMX250MZR
from polrig.sensor.noise import SensorModel
from polrig.solve.radiometry import (
    StateRadiance,
    analyzer_stack,
    analyzer_variance,
    reference_from_frames,
    state_radiance,
)
from polrig.solve.reference import solve_reference

from _state_radiance import noisy_states

S_IN = polarizer_stokes(np.deg2rad([0, 45, 90, 135]), intensity=1.0)
FIELDS = ("mueller", "sigma", "sigma_noise", "residual", "mask", "pixel_condition", "n_samples")
TOL = dict(analyzer_tolerance=(0.01, 0.5, 0.02), generator_tolerance=(2.0, 0.006))


def _whole_image(states, layout, method, analyzer=None, **kw):
    """The definition: every state demosaiced whole, one solve of the whole image."""
    parts = [analyzer_stack(s, layout, method, analyzer) for s in states]
    return solve_reference(S_IN, *(np.stack([p[i] for p in parts]) for i in range(3)),
                           parts[0][3], **kw)


def _states(rng, shape, layout):
    """Noisy mosaics of a random smooth Mueller scene, some samples excluded."""
    h, w = shape
    c = layout.n_colours
    m = np.zeros((c, 3, 3, h, w))
    v, u = np.mgrid[0:h, 0:w]
    for ci in range(c):
        base = rng.uniform(-0.3, 0.3, (3, 3)) + np.diag([1.0, 0.7, 0.6])
        m[ci] = 800 * base[:, :, None, None] * (1 + 0.2 * np.sin(0.3 * u + 0.2 * v + ci))
    return noisy_states(rng, m, S_IN, layout)


def _calibrated(rng, layout, shape):
    h, w = shape
    return AnalyzerModel(layout.name, 1 + 0.01 * rng.standard_normal(shape),
                         layout.angle_map(shape) + 0.5 * rng.standard_normal(shape),
                         np.clip(0.98 + 0.01 * rng.standard_normal(shape), 0, 1),
                         rng.normal(0, 2, shape))


def _assert_identical(a, b):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.condition_number == b.condition_number


@settings(max_examples=12)
@given(colour=st.booleans(), phase=st.tuples(st.integers(0, 3), st.integers(0, 3)),
       method=st.sampled_from(METHODS), h=st.integers(4, 41), w=st.integers(4, 23),
       band_pixels=st.integers(1, 700), calibrated=st.booleans(), seed=st.integers(0, 99))
def test_banded_solve_is_bit_identical_to_the_whole_image(colour, phase, method, h, w,
                                                          band_pixels, calibrated, seed):
    """Any size (odd included), any band size down to one row per band: each output row is
    demosaiced from the same mosaic rows as in the whole image, and solved alone."""
    layout = (IMX250MYR if colour else IMX250MZR).shifted(*phase)
    rng = np.random.default_rng(seed)
    states = _states(rng, (h, w), layout)
    analyzer = _calibrated(rng, layout, (h, w)) if calibrated else None
    banded = reference_from_frames(states, S_IN, layout, method, analyzer,
                                   band_pixels=band_pixels, **TOL)
    _assert_identical(banded, _whole_image(states, layout, method, analyzer, **TOL))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR.shifted(1, 2)])
def test_band_boundaries_at_every_row_offset(layout, method):
    """Bands of 1..5 periods on a frame whose height is not a multiple of the period, with
    and without the calibration-uncertainty propagation (shared sigma or not)."""
    rng = np.random.default_rng(7)
    h, w = 4 * 9 + 3, 14
    states = _states(rng, (h, w), layout)
    for kw in (TOL, {}):
        whole = _whole_image(states, layout, method, **kw)
        w_out = whole.mueller.shape[-1] * layout.n_colours
        for rows in (1, 2, 3, 5):
            banded = reference_from_frames(states, S_IN, layout, method,
                                           band_pixels=rows * w_out, **kw)
            _assert_identical(banded, whole)
            assert (banded.sigma_noise is banded.sigma) == (not kw)


@pytest.mark.parametrize("method", METHODS)
def test_threads_change_nothing(method):
    """Bands on 1, 2 or 5 threads (demosaics side by side, solves serialised)."""
    rng = np.random.default_rng(21)
    layout = IMX250MYR.shifted(2, 1)
    states = _states(rng, (50, 22), layout)
    analyzer = _calibrated(rng, layout, (50, 22))
    runs = [reference_from_frames(states, S_IN, layout, method, analyzer, band_pixels=150,
                                  workers=k, **TOL) for k in (1, 2, 5)]
    for r in runs[1:]:
        _assert_identical(r, runs[0])


def test_half_precision_uncertainty_planes():
    rng = np.random.default_rng(3)
    states = _states(rng, (24, 20), IMX250MYR)
    full = reference_from_frames(states, S_IN, IMX250MYR, "bilinear", **TOL)
    half = reference_from_frames(states, S_IN, IMX250MYR, "bilinear", uncertainty_dtype="float16",
                                 **TOL)
    np.testing.assert_array_equal(half.mueller, full.mueller)
    np.testing.assert_array_equal(half.mask, full.mask)
    for name in ("sigma", "sigma_noise", "residual"):
        assert getattr(half, name).dtype == np.float16
        np.testing.assert_array_equal(getattr(half, name), getattr(full, name).astype(np.float16))
    ok = np.broadcast_to(full.valid[:, None, None], full.sigma.shape) & (full.sigma > 0)
    rel = np.abs(half.sigma[ok].astype(np.float64) / full.sigma[ok] - 1)
    assert ok.sum() > 1000 and rel.max() <= 2 ** -11


@pytest.mark.parametrize("band_rows", [1, 3, 7, 10**6])
def test_state_radiance_bands_change_nothing(band_rows):
    """HDR bracket with darks and saturated samples: float32 of the float64 computation,
    whatever the band height."""
    rng = np.random.default_rng(11)
    model = SensorModel(black_level_dn=64.0)
    shape = (13, 9)
    exposures = [4000.0, 1000.0]
    light = rng.uniform(0, 5000, shape)
    light[::4, ::3] = 30000  # saturated in both exposures
    brackets = [[np.clip(np.rint(64 + light * e / 4000 + rng.normal(0, 3, shape)), 0, 4095)
                 .astype(np.uint16) for _ in range(3)] for e in exposures]
    darks = [[np.clip(np.rint(64 + rng.normal(0, 3, shape)), 0, 4095).astype(np.uint16)
              for _ in range(2)] for _ in exposures]
    got = state_radiance(brackets, exposures, model, black_level_dn=64.0, darks=darks,
                         band_rows=band_rows)
    ref = state_radiance(brackets, exposures, model, black_level_dn=64.0, darks=darks,
                         band_rows=shape[0])
    assert got.signal_dn.dtype == np.float32 and got.variance_dn2.dtype == np.float32
    assert got.excluded.any() and not got.excluded.all()
    for a, b in zip((got.signal_dn, got.variance_dn2, got.excluded),
                    (ref.signal_dn, ref.variance_dn2, ref.excluded)):
        np.testing.assert_array_equal(a, b)
    # one exposure, no darks: the closed form (mean - black - dark signal, model variance / K)
    one = state_radiance(brackets[:1], exposures[:1], model, black_level_dn=64.0,
                         band_rows=band_rows)
    mean = np.mean(np.asarray(brackets[0], np.float64), axis=0)
    signal = mean - 64.0 - model.dark_electrons(4000.0) / model.gain_e_per_dn
    np.testing.assert_array_equal(one.signal_dn, signal.astype(np.float32))
    np.testing.assert_array_equal(one.variance_dn2,
                                  model.variance_dn2(signal, 4000.0, 3).astype(np.float32))


def test_bad_input_is_a_clear_error():
    rng = np.random.default_rng(0)
    states = _states(rng, (8, 8), IMX250MZR)
    with pytest.raises(ValueError, match="uncertainty_dtype must be float32 or float16"):
        reference_from_frames(states, S_IN, IMX250MZR, uncertainty_dtype=np.int16)
    odd = StateRadiance(np.zeros((8, 6)), np.zeros((8, 6)), np.zeros((8, 6), bool))
    with pytest.raises(ValueError, match="differ in shape"):
        reference_from_frames(states[:3] + [odd], S_IN, IMX250MZR)
    with pytest.raises(ValueError, match="does not match frames"):
        reference_from_frames(states, S_IN, IMX250MZR,
                              analyzer=AnalyzerModel.ideal(IMX250MZR, (8, 6)))
    with pytest.raises(ValueError, match="smaller than one 2x2 layout cell"):
        tiny = StateRadiance(np.zeros((1, 8)), np.zeros((1, 8)), np.zeros((1, 8), bool))
        reference_from_frames([tiny] * 4, S_IN, IMX250MZR)
    with pytest.raises(ValueError, match="of one shape"):
        state_radiance([[np.zeros((4, 4)), np.zeros((4, 5))]], [100.0], SensorModel())


@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR])
@pytest.mark.parametrize("method", METHODS)
def test_analyzer_variance_is_analyzer_stacks_noise_half_bit_for_bit(layout, method):
    """The adaptive criterion's weights (analyzer_variance) are analyzer_stack's variance and
    validity, identical, with and without excluded samples."""
    rng = np.random.default_rng(7)
    for state in _states(rng, (24, 32), layout)[:2] + [
            StateRadiance(rng.uniform(1, 9, (24, 32)).astype(np.float32),
                          rng.uniform(1, 9, (24, 32)).astype(np.float32), np.zeros((24, 32), bool))]:
        _, var, valid, _ = analyzer_stack(state, layout, method)
        var2, valid2 = analyzer_variance(state, layout, method)
        assert var2.dtype == var.dtype and np.array_equal(var2, var) and np.array_equal(valid2, valid)
