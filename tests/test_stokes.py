"""Stokes from DoFP data: round trips, calibrated analyzers, DoLP/AoLP closed forms, masks."""

from __future__ import annotations

import numpy as np
import pytest
from _dofp_scenes import cell_constant, smooth_stokes
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.demosaic import METHODS
from polrig.sensor.layouts import IMX250MYR, IMX250MZR, get_layout
from polrig.sensor.stokes import (
    StokesSolver,
    aolp_deg,
    dolp,
    dolp_with_overshoot,
    ideal_inverse,
    polarized_split,
    saturation_mask,
    stokes_from_analyzers,
    stokes_from_raw,
    stokes_validity,
)

ALL_PHASES = {"imx250mzr": [(x, y) for y in range(2) for x in range(2)],
              "imx250myr": [(x, y) for y in range(4) for x in range(4)]}


def _random_stokes(rng, c, shape, dolp_max=1.0):
    s0 = rng.uniform(0.1, 4000, (c,) + shape)
    d = rng.uniform(0, dolp_max, (c,) + shape)
    a = rng.uniform(0, np.pi, (c,) + shape)
    return np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)], axis=1)


def test_ideal_inverse_is_the_textbook_formula():
    np.testing.assert_array_equal(ideal_inverse(), [[0.5, 0.5, 0.5, 0.5], [1, 0, -1, 0],
                                                    [0, 1, 0, -1]])


@pytest.mark.parametrize("name", ["imx250mzr", "imx250myr"])
def test_superpixel_round_trip_every_phase(name):
    """Acceptance: Stokes of a mosaic synthesised from known Stokes images comes back to 1e-6
    relative (superpixel, float input) for both layouts and every ROI phase."""
    rng = np.random.default_rng(7)
    for ox, oy in ALL_PHASES[name]:
        layout = get_layout(name, ox, oy)
        small = _random_stokes(rng, layout.n_colours, (6, 7))
        full = cell_constant(small, layout.period)
        raw = AnalyzerModel.ideal(layout, full.shape[-2:]).mosaic(full)
        res = stokes_from_raw(raw, layout, "superpixel")
        err = np.abs(res.stokes - small) / small[:, :1]
        assert err.max() < 1e-6, (ox, oy, err.max())
        assert res.valid.all() and res.dolp_overshoot <= small.size  # DoLP=1 may round over


@pytest.mark.parametrize("name", ["imx250mzr", "imx250myr"])
def test_round_trip_through_a_cropped_model(name):
    """A model cropped at an ROI offset carries the phase: same Stokes as the shifted layout."""
    rng = np.random.default_rng(8)
    big = AnalyzerModel.ideal(name, (32, 32))
    for ox, oy in [(1, 0), (3, 2), (2, 1)]:
        crop = big.crop(ox, oy, 16, 16)
        small = _random_stokes(rng, crop.n_colours, (16 // crop.mosaic_layout.period[0],
                                                     16 // crop.mosaic_layout.period[1]))
        full = cell_constant(small, crop.mosaic_layout.period)
        res = stokes_from_raw(crop.mosaic(full), crop.layout, "superpixel")
        np.testing.assert_allclose(res.stokes, small, rtol=1e-6, atol=1e-6 * small[:, 0].max())


def _perturbed_model(layout, shape, seed):
    rng = np.random.default_rng(seed)
    ideal = AnalyzerModel.ideal(layout, shape)
    return AnalyzerModel(ideal.layout, rng.uniform(0.8, 1.2, shape),
                         ideal.angle_deg + rng.normal(0, 3, shape),
                         rng.uniform(0.85, 1.0, shape), rng.normal(0, 5, shape))


@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR, get_layout("imx250myr", 1, 3)])
def test_calibrated_analyzer_recovers_stokes(layout):
    rng = np.random.default_rng(9)
    ph, pw = layout.period
    model = _perturbed_model(layout, (8 * ph, 6 * pw), seed=10)
    small = _random_stokes(rng, layout.n_colours, (8, 6))
    raw = model.mosaic(cell_constant(small, layout.period))
    got = stokes_from_raw(raw, layout, "superpixel", analyzer=model).stokes
    np.testing.assert_allclose(got, small, atol=2e-6 * small[:, 0].max())
    naive = stokes_from_raw(raw, layout, "superpixel").stokes
    assert np.abs(naive - small).max() > 100 * np.abs(got - small).max()


@pytest.mark.parametrize("method,tol", [("bilinear", 2e-3), ("newton", 2e-3)])
def test_calibrated_full_resolution_on_uniform_light(method, tol):
    """Exact for bilinear (linear: the model's rows go through the same interpolation) and for
    Newton (the mosaic is made ideal before its data-dependent interpolation)."""
    layout = IMX250MZR
    model = _perturbed_model(layout, (16, 20), seed=11)
    s = np.array([1000.0, 300.0, -200.0])
    raw = model.mosaic(np.broadcast_to(s[None, :, None, None], (1, 3, 16, 20)))
    solver = StokesSolver(model, method)
    got = stokes_from_raw(raw, layout, method, analyzer=solver).stokes
    np.testing.assert_allclose(got[0].reshape(3, -1).T, np.broadcast_to(s, (320, 3)),
                               atol=tol)
    naive = stokes_from_raw(raw, layout, method).stokes
    assert np.abs(naive[0].reshape(3, -1).T - s).max() > 10 * tol


def test_solver_rejects_wrong_grid_and_singular_models():
    model = AnalyzerModel.ideal("imx250mzr", (8, 8))
    solver = StokesSolver(model, "superpixel")
    assert solver.grid_shape == (4, 4)
    with pytest.raises(ValueError, match="do not match"):
        solver.solve(np.zeros((1, 4, 5, 5)))
    dead = AnalyzerModel(model.layout, model.gain, model.angle_deg,
                         np.zeros((8, 8)), model.offset_dn)  # no polarizers at all
    with pytest.raises(ValueError, match="singular"):
        StokesSolver(dead, "superpixel")
    with pytest.raises(ValueError, match="shape"):
        stokes_from_analyzers(np.zeros((1, 3, 4, 4)))
    with pytest.raises(ValueError, match="layout"):
        stokes_from_raw(np.zeros((8, 8)), "imx250mzr@1,0", "superpixel", analyzer=model)
    with pytest.raises(ValueError, match="built for"):
        stokes_from_raw(np.zeros((8, 8)), "imx250mzr", "bilinear", analyzer=solver)


def test_solver_refuses_ill_conditioned_analyzers_and_accepts_weak_ones():
    """Analyzer angles 0/1/2/3 deg instead of 0/45/90/135 are not singular, but the solve
    amplifies 1 DN of noise into a DoLP of 0.4 on unpolarized light: refused with the
    condition number, not returned as Stokes images. Weak polarizers (D = 0.1) are kept."""
    ideal = AnalyzerModel.ideal("imx250mzr", (8, 8))
    squeezed = ideal.angle_deg.copy()
    for nominal, angle in zip((0, 45, 90, 135), (0, 1, 2, 3)):
        squeezed[ideal.angle_deg == nominal] = angle
    bad = AnalyzerModel(ideal.layout, ideal.gain, squeezed, ideal.diattenuation, ideal.offset_dn)
    with pytest.raises(ValueError, match="ill-conditioned at 16 output pixels"):
        StokesSolver(bad, "superpixel")
    weak = AnalyzerModel(ideal.layout, ideal.gain, ideal.angle_deg, np.full((8, 8), 0.1), ideal.offset_dn)
    s = np.array([1000.0, 30.0, -20.0])
    raw = np.einsum("hwk,k->hw", weak.rows(), s).astype(np.float32)
    got = stokes_from_raw(raw, "imx250mzr", "superpixel", analyzer=weak, bit_depth=16).stokes
    np.testing.assert_allclose(got[0, :, 1, 1], s, rtol=1e-4)


def test_dolp_aolp_closed_forms():
    aolp_true = np.array([0.0, 10.0, 45.0, 89.9, 90.0, 135.0, 179.9])
    d_true = np.linspace(0.05, 1.0, aolp_true.size)
    t = np.deg2rad(2 * aolp_true)
    s = np.stack([np.full_like(t, 10.0), 10 * d_true * np.cos(t), 10 * d_true * np.sin(t)])
    s = s[None, :, None, :].astype(np.float32)
    got_a = aolp_deg(s)[0, 0]
    diff = (got_a - aolp_true + 90) % 180 - 90
    assert np.abs(diff).max() < 0.01
    assert got_a.min() >= 0 and got_a.max() < 180
    np.testing.assert_allclose(dolp(s)[0, 0], d_true, atol=1e-6)


def test_aolp_follows_the_analyzer_law():
    """Light polarized at psi is brightest behind the analyzer at psi (conventions.md)."""
    for psi in (0, 30, 45, 100, 135):
        t = np.deg2rad(2 * psi)
        s = np.array([2.0, 2 * np.cos(t), 2 * np.sin(t)])
        analyzers = 0.5 * (s[0] + s[1] * np.cos(np.deg2rad([0, 90, 180, 270]))
                           + s[2] * np.sin(np.deg2rad([0, 90, 180, 270])))
        st_ = stokes_from_analyzers(analyzers[None, :, None, None])
        assert aolp_deg(st_)[0, 0, 0] == pytest.approx(psi % 180, abs=0.01)


def test_overshoot_is_clipped_and_counted():
    s = np.array([[[[1.0, 1.0, 1.0]], [[1.2, 0.5, 0.0]], [[0.0, 0.0, 0.9]]]], np.float32)
    d, n = dolp_with_overshoot(s)
    assert n == 1
    np.testing.assert_allclose(d[0, 0], [1.0, 0.5, 0.9], atol=1e-6)


def test_dolp_stays_in_range_whatever_valid_mask_is_passed():
    """A caller's mask (here: everything valid) that lets through S0 <= 0 or NaN still gives a
    DoLP in [0, 1], 0 there (it used to return NaN for S = 0 and -0.5 for S0 = -1)."""
    s = np.array([[[[0.0, -1.0, np.nan, 2.0]], [[0.0, 0.5, 0.1, 1.0]], [[0.0, 0.0, 0.0, 0.0]]]], np.float32)
    d = dolp(s, np.ones((1, 1, 4), bool))
    np.testing.assert_array_equal(d[0, 0], [0.0, 0.0, 0.0, 0.5])


def test_polarized_split_adds_up():
    s = smooth_stokes(1, (6, 6), seed=2).astype(np.float32)
    unpol, pol = polarized_split(s)
    np.testing.assert_allclose(unpol + pol, s[:, 0], rtol=1e-6)
    np.testing.assert_allclose(pol, np.hypot(s[:, 1], s[:, 2]), rtol=1e-5)


def test_saturation_mask_covers_the_support():
    raw = np.full((20, 20), 100, np.uint16)
    raw[9, 10] = 4095
    for method, r in [("bilinear", 1), ("newton", 10)]:
        m = saturation_mask(raw, IMX250MZR, method, 4095)[0]
        assert m[9, 10] and m[max(9 - r, 0), 10] and m[9, min(10 + r, 19)]
        assert m.sum() <= (2 * r + 1) ** 2
    sp = saturation_mask(raw, IMX250MZR, "superpixel", 4095)[0]
    assert sp.shape == (10, 10) and sp[4, 5] and sp.sum() == 1
    res = stokes_from_raw(raw, IMX250MZR, "superpixel", bit_depth=12)
    assert not res.valid[0, 4, 5] and res.saturated[0, 4, 5] and res.valid.sum() == 99
    assert res.dolp[0, 4, 5] == 0 and res.aolp_deg[0, 4, 5] == 0


_special = st.sampled_from([0.0, -1.0, np.nan, np.inf, -np.inf, 4095.0, 1e30, 1e-30])


@settings(max_examples=60, deadline=None)
@given(method=st.sampled_from(METHODS), layout_name=st.sampled_from(["imx250mzr", "imx250myr"]),
       values=st.lists(st.tuples(st.integers(0, 15), st.integers(0, 15), _special),
                       max_size=12),
       dolp_level=st.sampled_from([0.0, 1.0, 0.5]), seed=st.integers(0, 2**16))
def test_extremes_give_masks_and_finite_outputs(method, layout_name, values, dolp_level, seed):
    """S0 = 0, DoLP 0 and 1, saturated, NaN/inf input: masks and finite outputs, no
    exceptions."""
    rng = np.random.default_rng(seed)
    layout = get_layout(layout_name)
    c = layout.n_colours
    s0 = rng.uniform(0, 3000, (c, 16, 16))
    a = rng.uniform(0, np.pi, (c, 16, 16))
    stokes = np.stack([s0, s0 * dolp_level * np.cos(2 * a), s0 * dolp_level * np.sin(2 * a)], 1)
    raw = AnalyzerModel.ideal(layout, (16, 16)).mosaic(stokes)
    final = {(v, u): x for v, u, x in values}  # the last write to a pixel wins
    for (v, u), x in final.items():
        raw[v, u] = x
    with np.errstate(all="raise"):  # nothing may warn deep inside numpy either
        res = stokes_from_raw(raw, layout, method, saturation_dn=4095.0)
    for arr in (res.stokes, res.dolp, res.aolp_deg):
        assert np.isfinite(arr).all()
    assert ((res.dolp >= 0) & (res.dolp <= 1)).all()
    assert ((res.aolp_deg >= 0) & (res.aolp_deg < 180)).all()
    assert not (res.valid & (res.stokes[:, 0] <= 0)).any()
    assert not (res.valid & res.saturated).any()
    assert (res.dolp[~res.valid] == 0).all()
    colour = layout.colour_map((16, 16))
    ph, pw = layout.period
    for (v, u), x in final.items():
        if not np.isfinite(x) or x >= 4095:
            # the output pixels fed by that sensor pixel are masked: in its own colour for a
            # non-finite value, in all colours for saturation (a conservative mask)
            chans = slice(None) if x >= 4095 else colour[v, u]
            at = (v // ph, u // pw) if method == "superpixel" else (v, u)
            assert not res.valid[(chans,) + at].any()


def test_validity_of_raw_stokes():
    s = np.array([[[[1.0, 0.0, -1.0, np.nan]], [[0, 0, 0, 0]], [[0, np.inf, 0, 0]]]])
    np.testing.assert_array_equal(stokes_validity(s)[0, 0], [True, False, False, False])


@pytest.mark.parametrize("phase", [(0, 0), (1, 1)])
def test_strip_wise_bilinear_equals_whole_image_computation(monkeypatch, phase):
    """The cache-friendly strip path gives the whole-image numbers (strip seams included)."""
    import polrig.sensor.stokes as stokes_mod

    layout = IMX250MZR.shifted(*phase)
    rng = np.random.default_rng(13)
    raw = rng.uniform(0, 4095, (37, 30))
    raw[[3, 18, 19, 36], [5, 7, 29, 0]] = 4095.0  # saturated, some on strip seams
    raw[10, 10] = np.nan
    monkeypatch.setattr(stokes_mod, "STRIP_PIXELS", 4 * 30)  # 4-row strips
    res = stokes_from_raw(raw, layout, "bilinear", saturation_dn=4095.0, black_level_dn=10)
    a = __import__("polrig.sensor.demosaic", fromlist=["demosaic"]).demosaic(
        raw, layout, "bilinear", black_level_dn=10)
    s = stokes_from_analyzers(a)
    finite = np.isfinite(s).all(axis=1)
    s[~np.isfinite(s)] = 0
    s[:, 0][~finite] = 0
    sat = saturation_mask(raw, layout, "bilinear", 4095.0)
    valid = stokes_validity(s, sat)
    assert np.isfinite(res.stokes).all()
    # (invalid pixels may differ: both paths zero what is non-finite, a NaN reaches more planes
    # through the weighted mosaic than through the per-class planes)
    np.testing.assert_allclose(np.where(valid[:, None], res.stokes, 0),
                               np.where(valid[:, None], s, 0), rtol=1e-6, atol=1e-3)
    np.testing.assert_array_equal(res.saturated, sat)
    np.testing.assert_array_equal(res.valid, valid)
    np.testing.assert_allclose(res.dolp, dolp(s, valid), atol=1e-6)
    np.testing.assert_allclose(res.aolp_deg, aolp_deg(s, valid), atol=1e-3)


@pytest.mark.parametrize("shape", [(1, 3, 0, 5), (0, 3, 4, 4), (2, 3, 4, 0), (0, 3, 0, 0)])
def test_images_without_pixels_give_empty_results(shape):
    """OpenCV returns None for empty planes: DoLP, AoLP and the polarized split return empty
    float32 arrays of shape (C, H, W) instead (issue 20, item 8)."""
    s = np.zeros(shape, np.float32)
    out_shape = shape[:1] + shape[2:]
    d, n_over = dolp_with_overshoot(s)
    assert d.shape == out_shape and d.dtype == np.float32 and n_over == 0
    for arr in (dolp(s), aolp_deg(s), *polarized_split(s),
                dolp(s, np.zeros(out_shape, bool)), aolp_deg(s, np.zeros(out_shape, bool))):
        assert arr.shape == out_shape and arr.dtype == np.float32
