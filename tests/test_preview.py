"""Preview images: AoLP hue wheel, DoLP grey/colormap, tone map, diverging Mueller grid."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.app.preview import (
    BACKGROUND,
    DARK,
    SATURATED,
    aolp_rgb,
    colorbar,
    display_valid,
    diverging,
    dolp_colormap,
    dolp_gray,
    exr_masks,
    mask_summary,
    mueller_grid,
    polarizance,
    reason_text,
    s0_snr,
    tone_map,
    write_result_previews,
)
from polrig.sensor.noise import SensorModel


def test_aolp_hue_wheel_and_dolp_value():
    a = np.array([[0.0, 60.0, 120.0, 179.99]])
    rgb = aolp_rgb(a)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    # 8-bit hue (256 steps over 180 deg AoLP) quantises to within a few levels
    np.testing.assert_allclose(rgb[0, 0], [255, 0, 0], atol=8)   # 0 deg red
    np.testing.assert_allclose(rgb[0, 1], [0, 255, 0], atol=8)   # 60 deg green
    np.testing.assert_allclose(rgb[0, 2], [0, 0, 255], atol=8)   # 120 deg blue
    assert rgb[0, 3, 0] == 255  # wraps back to red
    dark = aolp_rgb(a, np.zeros_like(a))
    assert dark.max() == 0
    pale = aolp_rgb(a, np.zeros_like(a), dolp_as="saturation")
    assert (pale == 255).all()
    masked = aolp_rgb(a, np.ones_like(a), valid=np.array([[True, False, True, True]]))
    assert masked[0, 1].max() == 0 and masked[0, 0].max() == 255
    nan = aolp_rgb(np.array([[np.nan]]), np.array([[np.inf]]))
    assert nan.shape == (1, 1, 3)


def test_dolp_and_tone_map():
    d = np.array([[0.0, 0.5, 1.0, 2.0, np.nan]])
    g = dolp_gray(d)
    np.testing.assert_array_equal(g[0, :, 0], [0, 128, 255, 255, 0])
    assert dolp_colormap(d).shape == (1, 5, 3)
    t = tone_map(np.array([[0.0, 1.0, 4.0]]), white=4.0, gamma=0.5)
    np.testing.assert_array_equal(t[0, :, 0], [0, 128, 255])
    assert tone_map(np.ones((3, 2, 2))).shape == (2, 2, 3)


def test_diverging_is_blue_white_red():
    rgb = diverging(np.array([[-1.0, 0.0, 1.0]]), vmax=1.0)
    assert rgb[0, 0, 2] > rgb[0, 0, 0]          # negative: blue
    assert (rgb[0, 1] > 240).all()               # zero: white
    assert rgb[0, 2, 0] > rgb[0, 2, 2]           # positive: red
    assert colorbar(100, width=64).shape == (100, 64, 3)


def test_diverging_maps_a_large_image_pixel_by_pixel_across_its_row_blocks():
    """A full-sensor-sized tile is mapped in row blocks (memory); every row gets the map's own
    colours: -1 blue end, 0 white centre, +1 red end, NaN masked by ``valid``."""
    h, w = 700, 2448  # more than two blocks of 2^18 pixels
    x = np.zeros((h, w), np.float32)
    x[:, 0], x[:, 1], x[::7, 2] = -1.0, 1.0, np.nan
    rgb = diverging(x, vmax=1.0, valid=np.isfinite(x))
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8
    assert (rgb[:, 0] == [5, 48, 97]).all() and (rgb[:, 1] == [103, 0, 31]).all()
    assert (rgb[:, 3:] == 247).all() and (rgb[::7, 2] == 0).all() and (rgb[1::7, 2] == 247).all()


@pytest.mark.parametrize("shape", [(3, 3, 8, 10), (3, 3, 3, 8, 10)])
def test_mueller_grid_layout(shape):
    m = np.zeros(shape, np.float32)
    m[..., 0, 0, :, :] = 2.0
    m[..., 1, 1, :, :] = 2.0      # m11 / m00 = +1 -> red
    m[..., 2, 2, :, :] = -2.0     # m22 / m00 = -1 -> blue
    img = mueller_grid(m, border_px=2)
    h, w = 8, 10
    assert img.shape[0] == 3 * h + 8 and img.shape[1] >= 3 * w + 8
    tile = lambda r, c: img[2 + r * (h + 2): 2 + r * (h + 2) + h, 2 + c * (w + 2): 2 + c * (w + 2) + w]
    assert tile(1, 1)[..., 0].mean() > tile(1, 1)[..., 2].mean()
    assert tile(2, 2)[..., 2].mean() > tile(2, 2)[..., 0].mean()
    assert (tile(0, 1) > 240).all()  # zero elements are white
    with pytest.raises(ValueError):
        mueller_grid(np.zeros((4, 4, 2, 2)))


def test_s0_snr_matches_the_noise_of_simulated_frames():
    """``s0_snr``'s sigma is the spread of S0 over many noisy frames of the same scene, for
    any polarization (var(S0) = var_model(S0 / 2) for ideal analyzers)."""
    model = SensorModel()
    rng = np.random.default_rng(1)
    for s0, dolp, aolp in ((40.0, 0.0, 0.0), (400.0, 0.9, 30.0), (3000.0, 0.5, 100.0)):
        t = np.deg2rad(2 * aolp)
        i = np.array([s0 / 2 * (1 + dolp * np.cos(t - 2 * np.deg2rad(a))) for a in (0, 45, 90, 135)])
        samples = np.stack([model.sample_raw(np.full(20000, x * model.gain_e_per_dn), rng, 0.0)
                            for x in i]).astype(np.float64)
        s0_hat = samples.sum(axis=0) / 2
        want = s0 / s0_hat.std()
        got = float(s0_snr(np.array([s0]), model)[0])
        assert abs(got / want - 1) < 0.03, (s0, got, want)


def test_display_valid_uses_the_snr_where_known_and_the_files_dark_bit_elsewhere():
    flags = np.array([DARK, 0, SATURATED, DARK, BACKGROUND], np.uint8)
    snr = np.array([10.0, 1.0, 10.0, np.nan, 10.0], np.float32)
    np.testing.assert_array_equal(display_valid(flags, snr, 3.0), [True, False, False, False, False])
    np.testing.assert_array_equal(display_valid(flags, snr, 0.5), [True, True, False, False, False])
    assert display_valid(None, None) is None
    assert reason_text(DARK | SATURATED, 1.24, 3) == "dark (SNR 1.2 < 3), saturated"
    assert reason_text(BACKGROUND) == "background" and reason_text(0) == ""
    assert mask_summary(flags[None], snr[None], 3.0) == \
        "masked 4 of 5 pixels (dark 2 below SNR 3, saturated 1, background 1)"


def test_exr_masks_read_every_kind_of_result():
    sig = np.array([[[100.0, 100.0, 0.0, 100.0]]], np.float32)  # (1, 1, 4)
    single = {"mask": np.array([[1, 1, 1, 0]], np.float32),
              "saturated": np.array([[0, 1, 0, 0]], np.float32)}
    flags, snr = exr_masks(single, 1, sig)
    assert snr is None
    assert flags.tolist() == [[[0, SATURATED, 8, BACKGROUND]]]  # m00 = 0: nonfinite
    session = {"mask.Y": np.array([[0, 4, 1, 0]], np.float32),
               "sigma_noise.M00.Y": np.array([[10, 10, 10, 50]], np.float32)}
    flags, snr = exr_masks(session, 1, sig)
    np.testing.assert_allclose(snr[0, 0, [0, 1, 3]], [10, 10, 2])
    np.testing.assert_array_equal(display_valid(flags, snr, 3.0), [[[True, False, False, False]]])
    stokes = {"valid": np.array([[1, 0, 0, 1]], np.float32),
              "saturated": np.array([[0, 1, 0, 0]], np.float32),
              "snr.Y": np.array([[20, 20, 0, 2]], np.float32)}
    flags, snr = exr_masks(stokes, 1, sig)
    np.testing.assert_array_equal(display_valid(flags, snr, 3.0), [[[True, False, False, False]]])


def test_mueller_grid_masks_only_the_normalised_tiles_and_labels_them():
    h = w = 40
    m = np.zeros((3, 3, h, w), np.float32)
    m[0, 0] = 100.0
    m[1, 1] = 100.0
    valid = np.ones((h, w), bool)
    valid[:, 20:] = False
    img = mueller_grid(m, valid=valid, border_px=2, with_colorbar=False)
    tile = lambda r, c: img[2 + r * (h + 2): 2 + r * (h + 2) + h, 2 + c * (w + 2): 2 + c * (w + 2) + w]
    assert (tile(1, 1)[20:, 20:] == 0).all() and tile(1, 1)[20:, :20].max(axis=-1).min() > 0  # masked: black
    assert tile(0, 0)[20:, 20:].min() > 0  # m00 itself is intensity: shown
    plain = mueller_grid(m, valid=valid, border_px=2, with_colorbar=False, labels=False)
    assert (img[:20, :30] != plain[:20, :30]).any()  # "m00" written into the corner
    big = mueller_grid(m, min_tile_px=256, with_colorbar=False)
    assert big.shape[0] >= 3 * 256


def test_polarizance_and_result_previews(tmp_path):
    import cv2

    m = np.zeros((3, 3, 3, 16, 16), np.float32)
    m[:, 0, 0] = 100.0
    m[:, 1, 0] = 50.0 * np.cos(np.deg2rad(60))  # DoLP 0.5 at AoLP 30 deg
    m[:, 2, 0] = 50.0 * np.sin(np.deg2rad(60))
    d, a = polarizance(m)
    np.testing.assert_allclose(d, 0.5, atol=1e-6)
    np.testing.assert_allclose(a, 30.0, atol=1e-4)
    snr = np.full((3, 16, 16), 10.0, np.float32)
    snr[:, :, 8:] = 1.0
    paths = write_result_previews(m, tmp_path, stem="r", snr=snr)
    assert [p.name for p in paths] == ["r_grid.png", "r_dolp.png", "r_aolp.png"]
    dolp = cv2.imread(str(tmp_path / "r_dolp.png"))
    assert dolp.shape[0] == 256 and dolp.shape[1] > 256  # enlarged 16x, legend on the right
    assert (dolp[:, 128:256] == 0).all() and (dolp[:, :128] > 100).all()


def test_large_results_are_previewed_every_kth_pixel(tmp_path):
    """A result larger than ``max_px`` is previewed from every k-th pixel, exactly as the
    decimated arrays are (the same PNG bytes), flags and snr decimated with it."""
    from polrig.app.preview import preview_stride, write_result_previews

    rng = np.random.default_rng(5)
    m = rng.uniform(-1, 1, (3, 3, 3, 250, 180)).astype(np.float32)
    m[:, 0, 0] = rng.uniform(0.5, 1.0, (3, 250, 180))
    flags = (rng.random((3, 250, 180)) < 0.1).astype(np.uint8)
    snr = rng.uniform(0, 50, (3, 250, 180)).astype(np.float32)
    assert preview_stride((250, 180), 100) == 3 and preview_stride((100, 100), 100) == 1
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    big = write_result_previews(m, tmp_path / "a", flags=flags, snr=snr, max_px=100)
    small = write_result_previews(m[..., ::3, ::3], tmp_path / "b", flags=flags[..., ::3, ::3],
                                  snr=snr[..., ::3, ::3], max_px=100)
    assert [p.name for p in big] == [p.name for p in small]
    for p, q in zip(big, small):
        assert p.read_bytes() == q.read_bytes()
