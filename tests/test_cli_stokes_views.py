"""``polrig stokes``'s polarization-camera views (issue 34, item 8): Imin/Imax (glare-reduced)
on S0's scale against their closed forms, signed S1/S2 on the diverging map, the AoLP preview's
DoLP as value or saturation with the colour wheel beside it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from polrig.app import preview
from polrig.cli import main

from test_cli_stokes import _polarized_raw


@pytest.mark.parametrize("dolp_as", ["value", "saturation"])
def test_stokes_writes_imin_imax_s1_s2_and_the_wheel(tmp_path, capsys, dolp_as):
    raw = _polarized_raw(aolp_deg=30.0, dolp=0.6, s0=2000.0)
    src = tmp_path / "frame.png"
    src.write_bytes(cv2.imencode(".png", raw)[1].tobytes())
    out = tmp_path / "out.exr"
    assert main(["stokes", str(src), "--layout", "imx250mzr", "--demosaic", "superpixel",
                 "--aolp-dolp", dolp_as, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for k in ("imin", "imax", "s1", "s2"):
        assert f"out_{k}.png" in printed
    rgb = {k: cv2.cvtColor(cv2.imread(str(tmp_path / f"out_{k}.png")), cv2.COLOR_BGR2RGB)
           for k in ("imin", "imax", "s1", "s2", "aolp")}
    h, w = 16, 20
    # uniform S0 with DoLP 0.6: Imin = 0.2 S0, Imax = 0.8 S0, tone-mapped with S0 as white
    for k, frac in (("imin", 0.2), ("imax", 0.8)):
        assert rgb[k].shape == (h, w, 3)
        level = np.round(255 * frac ** (1 / 2.2))
        assert np.abs(rgb[k][2:-2, 2:-2].astype(int) - level).max() <= 2
    # AoLP 30 deg: S1 = 0.6 S0 cos 60 > 0, S2 = 0.6 S0 sin 60 > 0, and |S| is the scale
    vmax = 0.6 * 2000 / 16
    for k, val in (("s1", vmax * 0.5), ("s2", vmax * np.sqrt(3) / 2)):
        img = rgb[k][:, :w]
        expect = preview.diverging(np.array([[val]]), vmax=vmax)[0, 0].astype(int)
        assert np.abs(img[4:-4, 4:-4].astype(int) - expect).max() <= 8
        assert rgb[k].shape[1] > w  # its colour bar
    # the AoLP preview: the image, its hue bar, then the wheel (as tall as the image)
    a = rgb["aolp"]
    key = preview.aolp_key(h, dolp_as=dolp_as)
    assert a.shape == (h, w + key.shape[1], 3)
    np.testing.assert_array_equal(a[:, w:], key)
    np.testing.assert_array_equal(a[:, -h:], preview.aolp_wheel(h, dolp_as=dolp_as))
    centre = a[h // 2, w // 2].astype(int)
    expect = preview.aolp_rgb(np.array([[30.0]]), np.array([[0.6]]), dolp_as=dolp_as)[0, 0]
    assert np.abs(centre - expect.astype(int)).max() <= 12
