"""Per-pixel DoFP analyzer model (Powell and Gruev 2013)."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.errors import FormatError
from polrig.sensor.analyzer import AnalyzerModel, layout_name_at, resolve_layout
from polrig.sensor.layouts import IMX250MYR, IMX250MZR


def _ideal_intensity(s: np.ndarray, angle_deg: float) -> np.ndarray:
    t = np.deg2rad(2 * angle_deg)
    return 0.5 * (s[0] + s[1] * np.cos(t) + s[2] * np.sin(t))


def test_ideal_rows_follow_layout_and_conventions():
    m = AnalyzerModel.ideal("imx250mzr", (4, 6))
    r = m.rows()
    assert r.shape == (4, 6, 3)
    # top-left super-pixel [[90, 45], [135, 0]] (docs/conventions.md, layouts.py)
    np.testing.assert_allclose(r[0, 0], [0.5, -0.5, 0.0], atol=1e-15)   # 90
    np.testing.assert_allclose(r[0, 1], [0.5, 0.0, 0.5], atol=1e-15)    # 45
    np.testing.assert_allclose(r[1, 0], [0.5, 0.0, -0.5], atol=1e-15)   # 135
    np.testing.assert_allclose(r[1, 1], [0.5, 0.5, 0.0], atol=1e-15)    # 0


@pytest.mark.parametrize("layout", [IMX250MZR, IMX250MYR])
def test_mosaic_matches_ideal_analyzer_law(layout):
    rng = np.random.default_rng(1)
    h, w = 8, 12
    c = layout.n_colours
    s0 = rng.uniform(1, 2, (c, h, w))
    dolp = rng.uniform(0, 1, (c, h, w))
    a = rng.uniform(0, np.pi, (c, h, w))
    stokes = np.stack([s0, s0 * dolp * np.cos(2 * a), s0 * dolp * np.sin(2 * a)], axis=1)
    m = AnalyzerModel.ideal(layout, (h, w))
    raw = m.mosaic(stokes)
    ang, col = layout.angle_map((h, w)), layout.colour_map((h, w))
    for v in range(h):
        for u in range(w):
            expect = _ideal_intensity(stokes[col[v, u], :, v, u], ang[v, u])
            assert raw[v, u] == pytest.approx(expect, rel=1e-12)


def test_gain_diattenuation_offset_enter_the_model():
    m0 = AnalyzerModel.ideal("imx250mzr", (2, 2))
    m = AnalyzerModel(m0.layout, m0.gain * 2, m0.angle_deg + 10, m0.diattenuation * 0.5,
                      m0.offset_dn + 3)
    s = np.array([2.0, 1.0, 0.5])
    raw = m.mosaic(np.broadcast_to(s[None, :, None, None], (1, 3, 2, 2)))
    t = np.deg2rad(2 * (m0.angle_deg + 10))
    expect = (2 / 2) * (s[0] + 0.5 * (s[1] * np.cos(t) + s[2] * np.sin(t))) + 3
    np.testing.assert_allclose(raw, expect, rtol=1e-12)


def test_crop_shifts_layout_phase():
    m = AnalyzerModel.ideal("imx250myr", (8, 8))
    c = m.crop(1, 2, 4, 5)
    assert c.shape == (5, 4)
    assert c.layout == "imx250myr@1,2"
    np.testing.assert_array_equal(c.angle_deg, m.angle_deg[2:7, 1:5])
    np.testing.assert_array_equal(c.colour_map(), m.colour_map()[2:7, 1:5])
    np.testing.assert_array_equal(resolve_layout(c.layout).angle_map((5, 4)), c.angle_deg)
    assert layout_name_at("imx250mzr@1,1", 1, 1) == "imx250mzr"
    with pytest.raises(ValueError):
        m.crop(6, 0, 4, 4)


def test_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    m0 = AnalyzerModel.ideal("imx250mzr@1,0", (4, 4))
    m = AnalyzerModel(m0.layout, rng.uniform(0.9, 1.1, (4, 4)), m0.angle_deg + 0.3,
                      rng.uniform(0.95, 1, (4, 4)), rng.normal(0, 1, (4, 4)))
    p = tmp_path / "analyzer.npz"
    m.save(p)
    back = AnalyzerModel.load(p)
    assert back.layout == m.layout == "imx250mzr@1,0"
    for name in ("gain", "angle_deg", "diattenuation", "offset_dn"):
        np.testing.assert_array_equal(getattr(back, name), getattr(m, name))
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="bad.npz"):
        AnalyzerModel.load(bad)


def test_rejects_bad_arrays():
    with pytest.raises(ValueError):
        AnalyzerModel("imx250mzr", np.ones((2, 2)), np.zeros((2, 3)), np.ones((2, 2)),
                      np.zeros((2, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        AnalyzerModel("imx250mzr", np.full((2, 2), np.nan), np.zeros((2, 2)), np.ones((2, 2)),
                      np.zeros((2, 2)))
    with pytest.raises(ValueError):
        AnalyzerModel.ideal("imx250mzr", (2, 2)).mosaic(np.zeros((3, 3, 2, 2)))
