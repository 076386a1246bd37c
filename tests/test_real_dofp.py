"""Real IMX250MZR frames (``tests/data/real-dofp``, see its README.md) end to end."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from polrig.formats.rawio import read_raw
from polrig.sensor import pixelformats as pf
from polrig.sensor.demosaic import METHODS
from polrig.sensor.stokes import stokes_from_raw

FRAMES = ["polanalyser_polarizer_IMX250MZR_raw8.png", "polanalyser_carps_IMX250MZR_raw8.png",
          "polanalyser_fruits_IMX250MZR_raw8.png"]
#: Filter centres in superpixel (half-resolution) coordinates, labels 0, 45, 90, 135 on paper.
FILTERS_ROW = 540
FILTERS_COLS = (188, 500, 812, 1052)


def _region_aolp_dolp(res, row, col, scale, radius=25):
    sl = (0, slice((row - radius) * scale, (row + radius) * scale),
          slice((col - radius) * scale, (col + radius) * scale))
    ok = res.valid[sl]
    assert ok.mean() > 0.9  # the filters are not saturated
    z = np.exp(2j * np.deg2rad(res.aolp_deg[sl][ok].astype(float))).mean()
    return np.rad2deg(np.angle(z)) / 2 % 180, float(np.median(res.dolp[sl][ok]))


@pytest.fixture(scope="module")
def frames(real_dofp_dir):
    return {name: read_raw(real_dofp_dir / name) for name in FRAMES}


@pytest.fixture(scope="module")
def results(frames):
    """Stokes of every frame by every method, computed once for the module."""
    cache = {}

    def get(name, method):
        if (name, method) not in cache:
            frame = frames[name]
            cache[name, method] = stokes_from_raw(frame.raw, frame.meta.layout, method,
                                                  bit_depth=8)
        return cache[name, method]
    return get


@pytest.mark.parametrize("method", METHODS)
def test_frames_decode_and_process_end_to_end(frames, results, method):
    for name, frame in frames.items():
        raw = frame.raw
        assert raw.shape == (2048, 2448) and raw.dtype == np.uint8
        res = results(name, method)
        for arr in (res.stokes, res.dolp, res.aolp_deg):
            assert np.isfinite(arr).all()
        assert res.valid.mean() > 0.8, name
        if method == "superpixel":
            # orthogonal analyzer pairs sum to the same S0 (MANIFEST: within a few DN)
            q = raw.astype(float)
            pair_a = q[0::2, 0::2] + q[1::2, 1::2]  # 90 + 0
            pair_b = q[0::2, 1::2] + q[1::2, 0::2]  # 45 + 135
            assert np.median(np.abs(pair_a - pair_b)[res.valid[0]]) <= 4


def test_saturated_pixels_are_masked(frames, results):
    for name, frame in frames.items():
        raw = frame.raw
        for method in ("superpixel", "bilinear"):
            res = results(name, method)
            sat = raw == 255
            if method == "superpixel":
                sat = sat.reshape(1024, 2, 1224, 2).any(axis=(1, 3))
            assert not (res.valid[0] & sat).any(), (name, method)
            assert (res.dolp[0][sat] == 0).all()
            frac = sat.mean()
            if "polarizer" in name:
                assert frac > 0.1  # MANIFEST: about 13 % saturated pixels
            if "fruits" in name:
                assert res.valid.mean() > 0.999


@pytest.mark.parametrize("method", METHODS)
def test_polarizer_filters_read_aolp_45_degrees_apart(results, method):
    """The four filters labelled 0, 45, 90, 135 (left to right) read AoLP stepping by -45 deg.

    polrig measures angles counter-clockwise as displayed, from image +u (docs/conventions.md;
    the Sony datasheet's analyzer drawings, row 0 = 90, 45 as read out and displayed), which is
    counter-clockwise for an observer looking into the beam, i.e. from the camera at the filter
    sheet. With AoLP = atan2(S2, S1) / 2 the filters read about 83, 44, 175, 135 deg (MANIFEST):
    each label step of +45 is a step of -45 deg (mod 180) in polrig's sense, so the labels'
    angles run clockwise as the camera sees the sheet (and the labels' zero lies near our 83 deg,
    i.e. close to vertical). Swapping the 0/90 analyzers (the old polanalyser bug, a mirror)
    would turn every step into +45; this test pins the sense down.
    """
    res = results("polanalyser_polarizer_IMX250MZR_raw8.png", method)
    scale = 1 if method == "superpixel" else 2
    readings = [_region_aolp_dolp(res, FILTERS_ROW, c, scale) for c in FILTERS_COLS]
    aolp = np.array([a for a, _ in readings])
    steps = (np.diff(aolp) + 90) % 180 - 90
    np.testing.assert_allclose(steps, -45, atol=8)
    assert abs(aolp[0] - 83) < 5
    background = np.median(res.dolp[0][res.valid[0]])
    assert background < 0.1
    for _, d in readings:
        assert d > 0.3 and d > 4 * background


def test_polarizer_frame_through_camera_pixel_formats(frames, results):
    """The real mosaic sent as camera bytes (8-bit and 12-bit packed) decodes to the same
    Stokes images (12-bit: the 8-bit values shifted left by 4, Stokes scale by 16)."""
    raw = frames["polanalyser_polarizer_IMX250MZR_raw8.png"].raw
    h, w = raw.shape
    ref = results("polanalyser_polarizer_IMX250MZR_raw8.png", "superpixel")
    for fmt in ("PolarizeMono8", "Polarized8", "Mono8"):
        dec = pf.decode(pf.encode(raw, fmt), fmt, w, h)
        np.testing.assert_array_equal(dec, raw)
    raw12 = raw.astype(np.uint16) << 4
    for fmt in ("PolarizeMono12p", "Polarized12p", "PolarizeMono12Packed"):
        dec = pf.decode(pf.encode(raw12, fmt), fmt, w, h)
        np.testing.assert_array_equal(dec, raw12)
    res12 = stokes_from_raw(dec, "imx250mzr", "superpixel", saturation_dn=255 << 4)
    np.testing.assert_allclose(res12.stokes, 16 * ref.stokes, rtol=1e-6, atol=1e-3)
    np.testing.assert_array_equal(res12.valid, ref.valid)


@pytest.mark.skipif(not (pathlib.Path(__file__).resolve().parents[1] / "models" / "weights" / "single_shot.onnx").is_file(),
                    reason="no single-shot model in models/weights")
def test_polrig_infer_on_a_real_mono_frame_without_sidecar(real_dofp_dir, tmp_path, capsys):
    """A real IMX250MZR (mono) frame with no sidecar: ``polrig infer`` says which layout it
    assumed, reconstructs the one channel as a grey scene and writes a one-colour Mueller EXR
    at the superpixel resolution (it used to stop at "model expects 3 colour channel(s)")."""
    from polrig.cli import main
    from polrig.formats.exr import read_mueller_exr

    out = tmp_path / "carps.exr"
    assert main(["infer", str(real_dofp_dir / FRAMES[1]), "--state-deg", "0", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "no sidecar; assuming the imx250mzr mosaic" in err and "--layout" in err
    exr = read_mueller_exr(out)
    assert exr.mueller.shape == (1, 3, 3, 1024, 1224) and np.all(np.isfinite(exr.mueller))
    lit = np.any(exr.mueller[0] != 0, axis=(0, 1))  # the networks' object (Mueller 0 outside)
    assert set(exr.extra) == {"mask.Y"}  # the reason bits, as a session's result
    assert lit.mean() > 0.5 and np.all(exr.mueller[0, 0, 0][lit] >= 0)
