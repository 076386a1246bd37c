"""Highlights a bracket measured (:mod:`polrig.models.highlights`): the network sees the
reference exposure as trained, and where that frame clipped but a shorter exposure did not,
its estimate takes the measured intensity and a calibrated sigma."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.models.highlights import SIGMA_FACTOR, highlight_sigma, measured_highlights
from polrig.sensor.noise import SensorModel
from polrig.solve.radiometry import StateRadiance, state_radiance

REPO = pathlib.Path(__file__).resolve().parents[1]
HAS_WEIGHTS = (REPO / "models" / "weights" / "single_shot.onnx").is_file()


def _image(rng, c=2, h=3, w=4):
    m = rng.uniform(-0.3, 0.3, (c, 3, 3, h, w))
    m[:, 0, 0] = rng.uniform(0.5, 2.0, (c, h, w))
    return m


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), gain=st.floats(1e-3, 1e4), angle=st.floats(0, np.pi),
       dolp=st.floats(0.0, 1.0))
def test_a_measured_highlight_renders_the_measured_intensity_and_keeps_its_form(seed, gain, angle, dolp):
    rng = np.random.default_rng(seed)
    m = _image(rng)
    s_in = np.array([1.0, dolp * np.cos(2 * angle), dolp * np.sin(2 * angle)])
    truth = gain * m  # the same form, `gain` times as bright
    stokes = np.einsum("crkhw,k->crhw", truth, s_in)
    clipped = rng.random((2, 3, 4)) < 0.5
    out, rescaled = measured_highlights(m, s_in, stokes, clipped)
    np.testing.assert_array_equal(rescaled, clipped)  # rendered S0 of m is > 0 everywhere here
    sel = clipped[:, None, None] & np.ones((1, 3, 3, 1, 1), bool)
    np.testing.assert_allclose(out[sel], truth[sel], rtol=1e-9)
    np.testing.assert_array_equal(out[~sel], m[~sel])
    rendered = np.einsum("ckhw,k->chw", out[:, 0], s_in)
    np.testing.assert_allclose(rendered[clipped], stokes[:, 0][clipped], rtol=1e-9)


def test_an_unmeasured_or_unlit_highlight_is_left_as_the_network_gave_it():
    rng = np.random.default_rng(1)
    m = _image(rng, 1, 1, 4)
    s_in = np.array([1.0, 1.0, 0.0])
    stokes = np.einsum("crkhw,k->crhw", 3 * m, s_in)
    stokes[0, 1, 0, 0] = np.nan  # no exposure measured it
    stokes[0, 0, 0, 1] = 0.0  # measured dark
    m[0, 0, :, 0, 2] = [1.0, -1.0, 0.0]  # renders S0 = 0 under s_in
    stokes[0, 0, 0, 2] = 1.0
    out, rescaled = measured_highlights(m, s_in, stokes, np.ones((1, 1, 4), bool))
    assert rescaled.tolist() == [[[False, False, False, True]]]
    np.testing.assert_array_equal(out[..., :3], m[..., :3])
    out, rescaled = measured_highlights(m, s_in, stokes, np.zeros((1, 1, 4), bool))
    assert not rescaled.any() and np.array_equal(out, m)


def test_the_highlight_sigma_scales_only_the_rescaled_pixels():
    sigma = np.full((1, 3, 3, 1, 2), 0.1, np.float32)
    other = np.full_like(sigma, 2.0)
    out = highlight_sigma(sigma, other, np.array([[[True, False]]]))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[..., 0], 2.0 * SIGMA_FACTOR)
    np.testing.assert_allclose(out[..., 1], 0.1)
    assert 1.0 <= SIGMA_FACTOR <= 2.0  # fitted on the calibration scenes: a modest widening


def test_a_bracket_records_what_its_reference_exposure_clipped():
    model = SensorModel()
    rng = np.random.default_rng(3)
    signal = rng.uniform(100, 3 * model.saturation_dn, (8, 8))
    exposures = [4000.0, 1000.0, 250.0]
    frames = [[np.minimum(signal * e / exposures[0], model.max_code_dn)] for e in exposures]
    st_ = state_radiance(frames, exposures, model)
    clipped_ref = signal >= model.saturation_dn
    np.testing.assert_array_equal(st_.clipped_reference, clipped_ref)
    np.testing.assert_array_equal(st_.reference_exclusions(), clipped_ref)
    assert not st_.excluded.any()  # the shortest exposure measured every sample
    one = state_radiance(frames[:1], exposures[:1], model)
    assert one.clipped_reference is None and np.array_equal(one.reference_exclusions(), one.excluded)


@pytest.mark.skipif(not HAS_WEIGHTS, reason="no single-shot model in models/weights")
def test_the_state_route_sees_the_reference_exposure_and_takes_the_measured_highlights(tmp_path):
    """The same radiance, once as one exposure whose block clipped (excluded: one analyzer
    sample of each colour; a pixel with no sample left leaves the networks' object) and once
    as a bracket whose reference exposure clipped it but a shorter one measured it: the
    networks see the same input, so every other pixel is identical; the block becomes the
    network's form at the measured intensity with a finite sigma instead of SATURATED."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.cli import main
    from polrig.formats.rawio import read_raw
    from polrig.optics.mueller import polarizer_stokes
    from polrig.solve.reference import SATURATED

    assert main(["sim", "render", "--size", "128x96", "--states", "0", "--no-exr", "--out", str(tmp_path)]) == 0
    f = read_raw(next(tmp_path.glob("*_state00.png")))
    signal = f.raw.astype(np.float64) - float(f.meta.black_level_dn)
    block = np.zeros(signal.shape, bool)
    block[40:48:2, 56:72:2] = True  # one analyzer of each colour in superpixel rows 10-11, columns 14-17
    signal[block] *= 8.0  # a highlight eight times as bright as the frame showed there
    variance = np.maximum(signal, 1.0)
    s_in = polarizer_stokes(0.0)
    route = SingleShot.open("cpu")
    options = SingleShotOptions(sigma=True)
    one = route.state(StateRadiance(signal, variance, block), f, s_in, options)
    hdr = route.state(StateRadiance(signal, variance, np.zeros_like(block), block), f, s_in, options)
    cells = np.zeros(one.mask.shape[-2:], bool)
    cells[10:12, 14:18] = True
    inside = cells & one.object
    assert inside.any()
    np.testing.assert_array_equal(hdr.mueller[..., ~cells], one.mueller[..., ~cells])
    np.testing.assert_array_equal(hdr.sigma[..., ~cells], one.sigma[..., ~cells])
    assert np.all(one.mask[:, inside] & SATURATED) and not np.any(hdr.mask[:, inside] & SATURATED)
    assert np.all(np.isinf(one.sigma[..., inside])) and np.all(np.isfinite(hdr.sigma[..., inside]))
    # the highlight renders the measured intensity: S0 of the superpixel radiance
    from polrig.sensor.analyzer import frame_layout
    from polrig.sensor.stokes import stokes_from_analyzers
    from polrig.solve.radiometry import analyzer_stack

    measured = analyzer_stack(StateRadiance(signal, variance, np.zeros_like(block)), frame_layout(f), "superpixel")[0]
    s0 = stokes_from_analyzers(measured)[:, 0][:, inside]
    rendered = np.einsum("ckn,k->cn", hdr.mueller[:, 0][:, :, inside].astype(np.float64), s_in)
    np.testing.assert_allclose(rendered, s0, rtol=1e-4)
