"""Demosaicing: output sizes, exactness where the method is exact, accuracy ordering."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from _dofp_scenes import analyzer_truth, cell_constant, smooth_stokes

from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.demosaic import (
    METHODS,
    demosaic,
    demosaic_combined,
    demosaic_float,
    output_shape,
    row_bands,
    support_radius,
)
from polrig.sensor.layouts import IMX250MYR, IMX250MZR, MosaicLayout, get_layout
from polrig.sensor.stokes import ideal_inverse

PHASES = [(0, 0), (1, 0), (0, 1), (1, 1), (2, 3), (3, 2)]


def _raw(layout, stokes):
    return AnalyzerModel.ideal(layout, stokes.shape[-2:]).mosaic(stokes)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR])
def test_output_shape_and_dtype(layout, method):
    raw = np.zeros((18, 22), np.uint16)
    out = demosaic(raw, layout, method)
    ph, pw = layout.period
    expect = (18 // ph, 22 // pw) if method == "superpixel" else (18, 22)
    assert out.shape == (layout.n_colours, 4) + expect
    assert output_shape(layout, raw.shape, method) == expect
    assert out.dtype == np.float32


@pytest.mark.parametrize("phase", PHASES)
@pytest.mark.parametrize("base", [IMX250MZR, IMX250MYR])
def test_superpixel_is_exact_on_cell_constant_scenes(base, phase):
    layout = base.shifted(*phase)
    small = smooth_stokes(layout.n_colours, (5, 6), freq=1.0, seed=3)
    stokes = cell_constant(small, layout.period)
    out = demosaic(_raw(layout, stokes), layout, "superpixel")
    np.testing.assert_allclose(out, analyzer_truth(small), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("phase", PHASES[:4])
def test_bilinear_reproduces_affine_scenes_in_the_interior(phase):
    layout = IMX250MZR.shifted(*phase)
    v, u = np.mgrid[0:20, 0:24].astype(float)
    s0 = 3 + 0.05 * u + 0.03 * v
    stokes = np.stack([s0, 0.02 * u - 0.01 * v, 0.5 - 0.01 * u])[None]
    out = demosaic(_raw(layout, stokes), layout, "bilinear")
    np.testing.assert_allclose(out[..., 2:-2, 2:-2], analyzer_truth(stokes)[..., 2:-2, 2:-2],
                               atol=2e-5)


@pytest.mark.parametrize("phase", PHASES[:4])
def test_newton_is_exact_on_unpolarized_cubic_scenes(phase):
    """Li et al.'s kernel is a cubic Newton interpolation plus the polarization-difference
    correction, whose second differences cancel for a shared signal: exact for cubics."""
    layout = IMX250MZR.shifted(*phase)
    v, u = np.mgrid[0:40, 0:44].astype(float) / 40
    s0 = 2 + u ** 3 - 0.5 * v ** 3 + 0.7 * u * v - u ** 2
    stokes = np.stack([s0, 0 * s0, 0 * s0])[None]
    out = demosaic(_raw(layout, stokes), layout, "newton")
    err = np.abs(out - analyzer_truth(stokes))[..., 11:-11, 11:-11].max()
    bil = demosaic(_raw(layout, stokes), layout, "bilinear")
    err_bil = np.abs(bil - analyzer_truth(stokes))[..., 11:-11, 11:-11].max()
    assert err < 1e-5 < err_bil


def _psnr(est, truth):
    mse = np.mean((est - truth) ** 2)
    return 10 * np.log10(np.ptp(truth) ** 2 / mse)


def _superpixel_upsampled(raw, layout):
    sp = demosaic(raw, layout, "superpixel")
    h, w = raw.shape
    return np.stack([[cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR) for p in c]
                     for c in sp])


@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR, get_layout("imx250myr", 1, 2)])
def test_interpolating_methods_beat_upsampled_superpixel(layout):
    stokes = smooth_stokes(layout.n_colours, (96, 128), freq=0.25, seed=1)
    raw = _raw(layout, stokes)
    truth = analyzer_truth(stokes)
    crop = (Ellipsis, slice(12, -12), slice(12, -12))
    p_sp = _psnr(_superpixel_upsampled(raw, layout)[crop], truth[crop])
    p_bil = _psnr(demosaic(raw, layout, "bilinear")[crop], truth[crop])
    p_new = _psnr(demosaic(raw, layout, "newton")[crop], truth[crop])
    assert p_bil > p_sp + 1 and p_new > p_sp + 1, (p_sp, p_bil, p_new)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("layout", [IMX250MZR, get_layout("imx250mzr", 1, 1), IMX250MYR])
def test_combined_equals_demosaic_then_combination(layout, method):
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 100, (24, 28)).astype(np.float32)
    w = ideal_inverse()
    a = demosaic(x, layout, method)
    expect = np.einsum("jk,ckhw->cjhw", w, a)
    np.testing.assert_allclose(demosaic_combined(x, layout, method, w), expect, atol=2e-4)


def test_colour_bilinear_combined_one_colour_at_a_time_is_bitwise_the_full_route():
    """The colour layout's combined bilinear route (one colour's analyzer images at a time) gives
    exactly the Stokes of the full analyzer stack, clipped (NaN) samples' support included:
    the full-resolution single-shot path marks clipped pixels by that NaN propagation."""
    from polrig.sensor.stokes import stokes_from_analyzers

    rng = np.random.default_rng(7)
    x = rng.uniform(0, 100, (40, 48)).astype(np.float32)
    x[rng.random(x.shape) < 0.01] = np.nan
    got = demosaic_combined(x, IMX250MYR, "bilinear", ideal_inverse())
    want = stokes_from_analyzers(demosaic_float(x, IMX250MYR, "bilinear"))
    assert np.isnan(want).any()
    np.testing.assert_array_equal(got, want)


def test_black_level_and_dark_are_removed():
    rng = np.random.default_rng(5)
    raw = rng.integers(100, 4000, (8, 8)).astype(np.uint16)
    dark = rng.uniform(0, 20, (8, 8)).astype(np.float32)
    a = demosaic(raw, IMX250MZR, "superpixel", black_level_dn=64, dark=dark)
    b = demosaic(raw.astype(np.float32) - dark - 64, IMX250MZR, "superpixel")
    np.testing.assert_allclose(a, b, atol=1e-3)
    with pytest.raises(ValueError, match="dark frame"):
        demosaic(raw, IMX250MZR, "bilinear", dark=np.zeros((4, 4)))


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match="unknown demosaic method"):
        demosaic(np.zeros((4, 4)), IMX250MZR, "cubic")
    with pytest.raises(ValueError, match="smaller than one"):
        demosaic(np.zeros((2, 3)), IMX250MYR, "bilinear")
    with pytest.raises(ValueError, match="2-D"):
        demosaic(np.zeros((4, 4, 3)), IMX250MZR)
    strip = MosaicLayout("strip", np.array([[0, 45, 90, 135]]), np.zeros((1, 4), int), ("Y",))
    assert demosaic(np.ones((4, 8)), strip, "bilinear").shape == (1, 4, 4, 8)
    with pytest.raises(ValueError, match="2x2-periodic"):
        demosaic(np.ones((4, 8)), strip, "newton")


@pytest.mark.parametrize("method,radius", [("bilinear", 1), ("newton", 10)])
def test_non_finite_input_stays_local(method, radius):
    raw = np.full((40, 40), 100.0)
    raw[20, 21] = np.nan
    out = demosaic(raw, IMX250MZR, method)
    bad = ~np.isfinite(out).all(axis=(0, 1))
    rows, cols = np.nonzero(bad)
    assert bad[20, 21]
    assert rows.min() >= 20 - radius and rows.max() <= 20 + radius
    assert cols.min() >= 21 - radius and cols.max() <= 21 + radius


def _newton_reference(img: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """Per-pixel loops written from Li et al. 2019 (Eqs. 14-17 and the edge classifier with
    tau = 5.8), interior pixels only; a slow, independent statement of the method."""
    m, n = img.shape
    o = lambda i, j: cell[i % 2, j % 2]  # noqa: E731  analyzer index at a pixel
    t = [1 / 16, -1 / 4, 7 / 16, 1 / 2, 7 / 16, -1 / 4, 1 / 16]
    r = np.repeat(img[None].astype(float), 4, axis=0)
    y1, y2 = img.astype(float).copy(), img.astype(float).copy()
    rng = lambda size: range(3, size - 3)  # noqa: E731
    for i in rng(m):
        for j in rng(n):
            r[o(i, j + 1), i, j] = sum(t[k + 3] * img[i, j + k] for k in range(-3, 4))
            r[o(i + 1, j), i, j] = sum(t[k + 3] * img[i + k, j] for k in range(-3, 4))
            y1[i, j] = sum(t[k + 3] * img[i + k, j + k] for k in range(-3, 4))
            y2[i, j] = sum(t[k + 3] * img[i + k, j - k] for k in range(-3, 4))

    def fuse(e1, e2, i, j, g1, g2):
        p1 = sum(abs(e1[i + k, j + l] - img[i + k, j + l]) for k in (-2, 0, 2) for l in (-2, 0, 2))
        p2 = sum(abs(e2[i + k, j + l] - img[i + k, j + l]) for k in (-2, 0, 2) for l in (-2, 0, 2))
        if p1 > 5.8 * p2:
            return e2[i, j]
        if p2 > 5.8 * p1:
            return e1[i, j]
        w1, w2 = 1 / (g1 + 1e-12), 1 / (g2 + 1e-12)
        return (w1 * e1[i, j] + w2 * e2[i, j]) / (w1 + w2)

    def grad(i, j, di, dj):
        return (abs(img[i - di, j - dj] - img[i + di, j + dj])
                + abs(2 * img[i, j] - img[i - 2 * di, j - 2 * dj] - img[i + 2 * di, j + 2 * dj]))

    for i in range(5, m - 5):
        for j in range(5, n - 5):
            r[o(i + 1, j + 1), i, j] = fuse(y1, y2, i, j, grad(i, j, 1, 1), grad(i, j, 1, -1))
    rr = r.copy()
    xx1, xx2, yy1, yy2 = (img.astype(float).copy() for _ in range(4))
    for i in range(8, m - 8):
        for j in range(8, n - 8):
            b, c = o(i, j + 1), o(i + 1, j)
            xx1[i, j] = r[b, i, j]
            xx2[i, j] = sum(t[k + 3] * (img[i + k, j] if k % 2 == 0 else r[b, i + k, j])
                            for k in range(-3, 4))
            yy1[i, j] = r[c, i, j]
            yy2[i, j] = sum(t[k + 3] * (img[i, j + k] if k % 2 == 0 else r[c, i, j + k])
                            for k in range(-3, 4))
    for i in range(10, m - 10):
        for j in range(10, n - 10):
            gh, gv = grad(i, j, 0, 1), grad(i, j, 1, 0)
            rr[o(i, j + 1), i, j] = fuse(xx1, xx2, i, j, gh, gv)
            rr[o(i + 1, j), i, j] = fuse(yy2, yy1, i, j, gh, gv)
    return rr


@pytest.mark.parametrize("phase", [(0, 0), (1, 1)])
def test_newton_matches_a_per_pixel_statement_of_the_paper(phase):
    layout = IMX250MZR.shifted(*phase)
    rng = np.random.default_rng(12)
    stokes = smooth_stokes(1, (28, 30), freq=0.4, seed=5)
    raw = _raw(layout, stokes) + rng.normal(0, 0.02, (28, 30))  # texture + noise: both branches
    raw[14:, :] += 0.8  # an edge
    idx = {a: i for i, a in enumerate((0, 45, 90, 135))}
    cell = np.vectorize(idx.__getitem__)(layout.angle_deg)
    ref = _newton_reference(raw.astype(np.float32).astype(float), cell)
    got = demosaic(raw, layout, "newton")[0]
    np.testing.assert_allclose(got[:, 10:-10, 10:-10], ref[:, 10:-10, 10:-10], atol=2e-4)


def test_newton_strips_equal_the_whole_image(monkeypatch):
    import polrig.sensor.demosaic as dm

    rng = np.random.default_rng(21)
    for layout in (IMX250MZR.shifted(1, 0), IMX250MYR.shifted(0, 3)):
        stokes = smooth_stokes(layout.n_colours, (90, 40), freq=0.3, seed=2)
        raw = _raw(layout, stokes) + rng.normal(0, 0.01, (90, 40))
        raw[45:, 10:] += 0.5  # an edge across strip seams
        whole = demosaic(raw, layout, "newton")  # 90 rows: a single strip
        monkeypatch.setattr(dm, "NEWTON_STRIP_PIXELS", 8 * 40)  # 8-row strips
        strips = demosaic(raw, layout, "newton")
        monkeypatch.undo()
        np.testing.assert_array_equal(strips, whole)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("layout", [IMX250MZR, get_layout("imx250mzr", 1, 1), IMX250MYR,
                                    get_layout("imx250myr", 3, 2)])
@pytest.mark.parametrize("height", [4, 37, 64])
def test_row_bands_reproduce_the_whole_demosaic_bit_for_bit(layout, method, height):
    """Bands of every size: each band's rows, demosaiced from its halo-extended mosaic rows,
    are the whole image's rows exactly (the halo covers the method's support; bands start on
    a period boundary, so each sees the layout at its own phase)."""
    rng = np.random.default_rng(height)
    x = rng.uniform(0, 4000, (height, 30)).astype(np.float32)
    x[height // 2, 7] = np.nan  # non-finite input spreads the same way in bands
    whole = demosaic_float(x, layout, method)
    ph = layout.period[0]
    for band_rows in (1, 2, 5, 9, 1000):
        bands = row_bands(layout, x.shape, method, band_rows)
        covered = np.concatenate([np.arange(o0, o1) for o0, o1, _, _ in bands])
        np.testing.assert_array_equal(covered, np.arange(whole.shape[2]))
        for o0, o1, e0, e1 in bands:
            assert e0 % ph == 0 and 0 <= e0 and e1 <= height
            part = demosaic_float(x[e0:e1], layout, method)
            a = 0 if method == "superpixel" else o0 - e0
            np.testing.assert_array_equal(part[:, :, a:a + o1 - o0], whole[:, :, o0:o1])


@pytest.mark.parametrize("method", ["bilinear", "newton"])
@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR])
def test_support_radius_bounds_the_reach_of_one_pixel(layout, method):
    """A change of one raw pixel changes the output only within the support radius (the
    bound the truth scoring relies on to call a pixel's support uniform)."""
    ry, rx = support_radius(layout, method)
    rng = np.random.default_rng(1)
    x = rng.uniform(100, 200, (64, 64)).astype(np.float32)
    y = x.copy()
    y[31, 30] += 1000
    diff = (demosaic_float(x, layout, method) != demosaic_float(y, layout, method)).any(axis=(0, 1))
    rows, cols = np.nonzero(diff)
    assert diff[31, 30]
    assert rows.min() >= 31 - ry and rows.max() <= 31 + ry
    assert cols.min() >= 30 - rx and cols.max() <= 30 + rx
    assert support_radius(layout, "superpixel") == (0, 0)
