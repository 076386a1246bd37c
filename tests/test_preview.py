"""Preview images: AoLP hue wheel, DoLP grey/colormap, tone map, diverging Mueller grid."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.preview import (aolp_rgb, colorbar, diverging, dolp_colormap, dolp_gray,
                            mueller_grid, tone_map)


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
    assert colorbar(100).shape == (100, 64, 3)


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
