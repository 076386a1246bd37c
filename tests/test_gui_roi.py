"""The viewer's and the live view's analysis tools (issue 34, items 2, 4 and 8; pytest-qt,
offscreen): a drawn ROI's table equals the headless :func:`polrig.app.roi.roi_statistics`, the
line profile and CSV export, the virtual polarizer's sliders against
:func:`polrig.optics.virtual_polarizer.virtual_polarizer_image`, the parameter-maps layer (its
maps computed on a worker thread, a stale result discarded), and
the polarization-camera views (Imin/Imax, signed S1/S2, AoLP with DoLP as saturation or
value, the colour wheel).

The data: a synthetic 40x48 mono Mueller result EXR (a retarder whose axis and retardance vary
across the image, a polarizing corner, noise, sigma and mask planes, a masked block), written by
the core writer: small, fast and with every quantity structured."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QPoint, Qt  # noqa: E402

from polrig.app import preview, roi  # noqa: E402
from polrig.formats.exr import element_planes, write_mueller_exr  # noqa: E402
from polrig.gui import pipeline  # noqa: E402
from polrig.gui.qtimage import from_qimage  # noqa: E402
from polrig.optics import mueller as mu  # noqa: E402
from polrig.optics import parameters as pa  # noqa: E402
from polrig.optics.virtual_polarizer import virtual_polarizer_image  # noqa: E402
from test_gui import open_and_wait  # noqa: E402

pytestmark = pytest.mark.gui
H, W = 40, 48


def roi_done(qtbot, tools) -> None:
    """Wait for the ROI statistics (computed off the UI thread)."""
    qtbot.waitUntil(lambda: not tools.busy, timeout=60000)


@pytest.fixture(scope="module")
def result_exr(tmp_path_factory):
    rng = np.random.default_rng(3)
    v, u = np.mgrid[:H, :W]
    axis = np.deg2rad(170.0 + 25.0 * u / W)  # crosses 180 deg: the circular mean matters
    ret = np.deg2rad(30.0 + 60.0 * v / H)
    m = 900.0 * mu.linear_block(mu.retarder_at(axis, ret))  # (H, W, 3, 3)
    m[:10, :10] = 900.0 * mu.linear_block(mu.polarizer_at(np.deg2rad(20.0)))
    sigma = np.full(m.shape, 3.0)
    m = m + rng.normal(0.0, 1.0, m.shape) * sigma
    img = np.moveaxis(m, (-2, -1), (0, 1))[None].astype(np.float32)  # (1, 3, 3, H, W)
    sig = np.moveaxis(sigma, (-2, -1), (0, 1))[None].astype(np.float32)
    mask = np.zeros((H, W), np.float32)
    mask[20:24, 30:36] = 2  # saturated block
    path = tmp_path_factory.mktemp("roi") / "mueller.exr"
    write_mueller_exr(path, img, extra={**element_planes("sigma", sig), "mask.Y": mask})
    return path


@pytest.fixture
def viewer(qtbot, viewer_panel, result_exr):

    v = viewer_panel((1400, 800))
    v.messages = []
    v.message.connect(lambda lvl, t: v.messages.append((lvl, t)))
    assert open_and_wait(qtbot, v, result_exr)
    return v


def headless(viewer, region):
    d = viewer.data
    inside = roi.roi_mask(region, d.mueller.shape[-2:])
    return roi.roi_statistics(inside, mueller=d.mueller, sigma=d.sigma,
                              valid=pipeline.roi_valid(d))


def drag(qtbot, view, a, b):
    """A left-button drag on the image from image point ``a`` to ``b``."""
    pa_, pb = (view._widget_point(*a).toPoint(), view._widget_point(*b).toPoint())
    qtbot.mousePress(view, Qt.MouseButton.LeftButton, pos=pa_)
    qtbot.mouseMove(view, pos=QPoint((pa_.x() + pb.x()) // 2, (pa_.y() + pb.y()) // 2))
    qtbot.mouseMove(view, pos=pb)
    qtbot.mouseRelease(view, Qt.MouseButton.LeftButton, pos=pb)


def test_drawn_rectangle_table_equals_the_headless_statistics(qtbot, viewer):
    v = viewer
    assert v.data.sigma is not None and v.data.sigma.shape == v.data.mueller.shape
    v.display.setCurrentIndex(v.display.findData("s0"))
    v.roi.tool.setCurrentIndex(v.roi.tool.findData("rect"))
    assert v.view.tool == "rect"
    drag(qtbot, v.view, (26.0, 15.0), (44.0, 33.0))
    region = v.roi.region
    assert isinstance(region, roi.RectROI)
    roi_done(qtbot, v.roi)
    # the mouse lands on whole widget pixels: the drawn corners are within a pixel of the aim
    assert abs(region.x - 26) < 1 and abs(region.y - 15) < 1
    assert abs(region.w - 18) < 1.5 and abs(region.h - 18) < 1.5
    want = headless(v, region)
    assert v.roi.rows == want
    table = v.roi.table_values()
    assert len(table) == len(want) > 20
    for got, r in zip(table, want):
        assert got[1] == r.channel and got[0].startswith(r.quantity)
        assert int(got[6]) == r.n_counted and int(got[7]) == r.n_masked
        for text, val in zip(got[2:6], (r.mean, r.std, r.sem_scatter, r.sem_sigma)):
            assert text == (f"{val:.5g}" if math.isfinite(val) else str(val))
    s0 = next(r for r in want if r.quantity == "S0")
    inside = roi.roi_mask(region, (H, W))
    assert s0.n_counted + s0.n_masked == inside.sum()
    assert s0.n_masked == (inside[20:24, 30:36]).sum() > 0  # the saturated block, counted as masked
    assert f"{s0.n_counted} counted, {s0.n_masked} masked" in v.roi.summary.text()
    # the axis crosses 180 deg inside: its circular mean stays near 180/0, never near 90
    ax = next(r for r in want if r.quantity == "retardance_axis_deg")
    assert min(ax.mean, 90 - ax.mean) < 15


def test_drawn_polygon_and_ellipse_and_the_mueller_grid_tile(qtbot, viewer):
    v = viewer
    v.display.setCurrentIndex(v.display.findData("s0"))
    v.roi.tool.setCurrentIndex(v.roi.tool.findData("poly"))
    pts = [(5.0, 5.0), (30.0, 8.0), (20.0, 30.0)]
    for p in pts:
        qtbot.mouseClick(v.view, Qt.MouseButton.LeftButton, pos=v.view._widget_point(*p).toPoint())
    qtbot.mouseDClick(v.view, Qt.MouseButton.LeftButton,
                      pos=v.view._widget_point(*pts[-1]).toPoint())
    region = v.roi.region
    assert isinstance(region, roi.PolygonROI) and len(region.points) == 3
    roi_done(qtbot, v.roi)
    assert v.roi.rows == headless(v, region)
    v.view.set_shape("ellipse", [(10.0, 12.0), (30.0, 28.0)])
    assert v.roi.region == roi.EllipseROI(20.0, 20.0, 10.0, 8.0)
    roi_done(qtbot, v.roi)
    assert v.roi.rows == headless(v, v.roi.region)
    # on the 3x3 grid, a shape drawn on the m11 tile measures the same pixels
    v.display.setCurrentIndex(v.display.findData("mueller"))
    b = pipeline.GRID_BORDER_PX
    ox, oy = 2 * b + W, 2 * b + H
    v.view.set_shape("rect", [(ox + 4.0, oy + 6.0), (ox + 20.0, oy + 16.0)])
    assert v.roi.region == roi.RectROI(4.0, 6.0, 16.0, 10.0)


def test_line_profile_and_csv_export(qtbot, viewer, tmp_path):
    v = viewer
    v.display.setCurrentIndex(v.display.findData("s0"))
    v.view.set_shape("rect", [(2.0, 2.0), (12.0, 9.0)])
    v.roi.tool.setCurrentIndex(v.roi.tool.findData("line"))
    drag(qtbot, v.view, (3.0, 20.0), (45.0, 20.0))
    seg = v.roi.segment
    assert seg is not None and abs(seg[0] - 3) < 1 and abs(seg[2] - 45) < 1
    roi_done(qtbot, v.roi)
    want = roi.profile_of(seg, mueller=v.data.mueller, sigma=v.data.sigma,
                          valid=pipeline.roi_valid(v.data))  # what polrig stats computes
    whole = roi.line_profile(roi.mueller_quantities(v.data.mueller, v.data.sigma,
                                                    pipeline.roi_valid(v.data)), *seg)
    np.testing.assert_array_equal(v.roi.profile.s, want.s)
    for name in ("S0", "AoLP_deg", "retardance_deg"):
        np.testing.assert_array_equal(v.roi.profile.values[name], want.values[name])
        np.testing.assert_allclose(want.values[name], whole.values[name], rtol=1e-12)
    v.roi.profile_quantity.setCurrentText("retardance_deg")
    np.testing.assert_array_equal(v.roi.plot.values, want.values["retardance_deg"])
    written = v.roi.export_csv(tmp_path / "stats.csv")
    assert [p.name for p in written] == ["stats.csv", "stats_profile.csv"]
    text = (tmp_path / "stats.csv").read_text()
    assert text == roi.stats_csv(v.roi.rows, {"source": str(v.data.source),
                                              "pixel_convention": "pixel (u, v) has its centre at "
                                                                  "(u + 0.5, v + 0.5)",
                                              "roi": v.roi.region.text()})
    rows = list(csv.reader(line for line in (tmp_path / "stats_profile.csv").read_text().splitlines()
                           if not line.startswith("#")))
    assert rows[0][:4] == ["s", "x", "y", "S0.Y"] and len(rows) - 1 == want.s.size


def test_virtual_polarizer_sliders_show_virtual_polarizer_image(qtbot, viewer):
    v = viewer
    v.display.setCurrentIndex(v.display.findData("polarizer"))
    m = v.data.mueller
    white = pipeline.fast_white(0.5 * m[:, 0, 0])
    shown = []
    for inc, ana in ((0, 0), (30, 120), (90, 45)):
        v.incident.setValue(inc)
        v.analyzer.setValue(ana)
        expect = preview.tone_map(virtual_polarizer_image(m, float(inc), float(ana))[0][0],
                                  white=white)
        got = from_qimage(v.view.image())
        np.testing.assert_array_equal(got, expect)
        assert v.incident_label.text().strip() == f"{inc} deg"
        shown.append(got)
    assert not np.array_equal(shown[0], shown[1])  # the sliders change the image
    v._hovered(30, 25)  # the readout: the value under the cursor with its exact sigma
    i, s = virtual_polarizer_image(m, 90.0, 45.0, v.data.sigma)
    assert f"Y {i[0, 25, 30]:.4g} +- {s[0, 25, 30]:.2g}" in v.readout.text()
    v.unpolarized.setChecked(True)
    v.no_analyzer.setChecked(True)
    assert not v.incident.isEnabled() and v.analyzer_label.text() == "none"
    expect = preview.tone_map(virtual_polarizer_image(m, None, None)[0][0], white=white)
    np.testing.assert_array_equal(from_qimage(v.view.image()), expect)
    # unpolarized in, no analyzer out: m00 / 2
    np.testing.assert_allclose(virtual_polarizer_image(m, None, None)[0], 0.5 * m[:, 0, 0], rtol=1e-6)


def _maps_shown(v) -> bool:
    return v.data.maps_ready() and v.view.image() is not None and not v.maps_busy


def test_parameter_maps_layer_shows_the_maps_with_their_colormaps(qtbot, viewer):
    v = viewer
    v.display.setCurrentIndex(v.display.findData("maps"))
    qtbot.waitUntil(lambda: _maps_shown(v), timeout=60000)  # computed on a worker thread
    maps = pa.image_maps(v.data.mueller, v.data.sigma)
    ok = pipeline.shown(v.data)
    for name in ("DL", "retardance_deg", "PL_axis_deg"):
        v.map_name.setCurrentIndex(v.map_name.findData(name))
        got = from_qimage(v.view.image())[:, :W]
        x = maps.values[name][0]
        valid = ok & np.isfinite(x)
        if name == "DL":
            expect = preview.dolp_colormap(x, valid=valid)
        elif name == "retardance_deg":
            expect = preview.dolp_colormap(x / 180.0, valid=valid)
        else:
            expect = preview.aolp_rgb(x, valid=valid)
            assert v.wheel.mode is None  # an angle map: hue only, the wheel says so
        np.testing.assert_array_equal(got, expect)
    v._hovered(40, 30)
    assert (f"PL_axis_deg at (u=40, v=30): Y {maps.values['PL_axis_deg'][0, 30, 40]:.4g} +- "
            f"{maps.sigma['PL_axis_deg'][0, 30, 40]:.2g}") in v.readout.text()
    v.map_name.setCurrentIndex(v.map_name.findData("DL"))
    v.map_sigma.setChecked(True)
    assert "sigma DL" in v.histogram.label
    assert not np.array_equal(from_qimage(v.view.image())[:, :W], expect)


def test_parameter_maps_are_computed_off_the_gui_thread_and_equal_image_maps(qtbot, viewer):
    """The maps layer does not compute on the GUI thread: the view says "computing" until the
    worker's signal delivers the maps, which equal :func:`pa.image_maps` bit for bit."""
    import threading

    from polrig.gui.viewer import COMPUTING_MAPS

    v = viewer
    data = v.data
    threads = []
    compute = data.compute_maps

    def recorded():
        threads.append(threading.get_ident())
        return compute()

    data.compute_maps = recorded
    v._hovered(5, 5)
    v.display.setCurrentIndex(v.display.findData("maps"))
    assert v.maps_busy and not data.maps_ready()
    assert v.view.image() is None and v.view.placeholder == COMPUTING_MAPS
    v._hovered(5, 5)
    assert COMPUTING_MAPS in v.readout.text()  # the readout does not compute them either
    qtbot.waitUntil(lambda: _maps_shown(v), timeout=60000)
    assert threads and threads[0] != threading.get_ident()
    expect = pa.image_maps(data.mueller, data.sigma)
    got = data.maps()
    for name in pa.MAPS:
        np.testing.assert_array_equal(got.values[name], expect.values[name])
        np.testing.assert_array_equal(got.sigma[name], expect.sigma[name])
    np.testing.assert_array_equal(got.flags, expect.flags)
    rgb = pipeline.render(data, "maps", v.colour.currentData(), saturation_overlay=True,
                          options=v.options())
    np.testing.assert_array_equal(from_qimage(v.view.image()), rgb)
    assert len(threads) == 1  # computed once; changing the map only renders
    v.map_name.setCurrentIndex(v.map_name.findData("DL"))
    assert len(threads) == 1 and v.view.image() is not None


def test_a_stale_maps_result_is_discarded_when_the_file_changes(qtbot, viewer, tmp_path):
    """Another file opened while the maps of the first are computed: the first's result is
    dropped (never kept or shown) and the maps of the file shown are computed and shown."""
    import threading

    v = viewer
    first = v.data
    gate, compute = threading.Event(), first.compute_maps
    first.compute_maps = lambda: (gate.wait(30), compute())[1]  # still running when other shows
    v.display.setCurrentIndex(v.display.findData("maps"))
    assert v.maps_busy
    other = tmp_path / "other.exr"
    m = 500.0 * mu.linear_block(mu.retarder_at(np.full((H, W), 0.4), np.full((H, W), 1.1)))
    img = np.moveaxis(m, (-2, -1), (0, 1))[None].astype(np.float32)
    write_mueller_exr(other, img, extra=element_planes("sigma", np.full(img.shape, 2.0, np.float32)))
    assert open_and_wait(qtbot, v, other)  # while the first file's maps worker still runs
    assert v.data is not first and v.maps_busy
    gate.set()
    qtbot.waitUntil(lambda: _maps_shown(v), timeout=60000)
    assert not first.maps_ready()  # the stale result was discarded
    expect = pa.image_maps(v.data.mueller, v.data.sigma)
    np.testing.assert_array_equal(v.data.maps().values["retardance_deg"],
                                  expect.values["retardance_deg"])
    np.testing.assert_allclose(expect.values["retardance_deg"], np.degrees(1.1), rtol=1e-5)
    rgb = pipeline.render(v.data, "maps", v.colour.currentData(), saturation_overlay=True,
                          options=v.options())
    np.testing.assert_array_equal(from_qimage(v.view.image()), rgb)


def test_stokes_views_imin_imax_signed_s1_s2_and_the_wheel(qtbot, viewer_panel, tmp_path):
    """A Stokes EXR in the viewer: Imin + Imax = S0, Imax - Imin = the polarized intensity,
    S1/S2 on the diverging map, the AoLP display's DoLP as value or saturation, and the wheel
    following it."""
    from polrig.formats.exr import write_stokes_exr
    from polrig.sensor.stokes import min_max_intensity

    rng = np.random.default_rng(5)
    s0 = rng.uniform(100, 1000, (1, 24, 32))
    p = rng.uniform(0, 1, s0.shape)
    a = rng.uniform(0, np.pi, s0.shape)
    stokes = np.stack([s0, p * s0 * np.cos(2 * a), p * s0 * np.sin(2 * a)], axis=1).astype(np.float32)
    path = tmp_path / "stokes.exr"
    write_stokes_exr(path, stokes)
    v = viewer_panel()
    assert open_and_wait(qtbot, v, path)
    imin, imax = min_max_intensity(stokes)
    np.testing.assert_allclose(imin + imax, stokes[:, 0], rtol=1e-5)
    np.testing.assert_allclose(imax - imin, np.hypot(stokes[:, 1], stokes[:, 2]), rtol=1e-4, atol=1e-3)
    white = pipeline.fast_white(stokes[:, 0])
    v.display.setCurrentIndex(v.display.findData("imin"))
    np.testing.assert_array_equal(from_qimage(v.view.image()), preview.tone_map(imin, white=white))
    v.display.setCurrentIndex(v.display.findData("s2"))
    vmax = pipeline.fast_white(np.hypot(stokes[0, 1], stokes[0, 2]))
    d = v.data
    np.testing.assert_array_equal(from_qimage(v.view.image()),
                                  preview.diverging(stokes[0, 2], vmax=vmax,
                                                    valid=d.valid[0] & pipeline.shown(d)))
    for display, mode in (("aolp_dolp", "value"), ("aolp_dolp_sat", "saturation"), ("aolp", None)):
        v.display.setCurrentIndex(v.display.findData(display))
        assert v.wheel.mode == mode and v.wheel.isVisible()
        expect = preview.aolp_rgb(d.aolp_deg[0], None if mode is None else d.dolp[0],
                                  dolp_as=mode or "value", valid=d.valid[0] & pipeline.shown(d))
        np.testing.assert_array_equal(from_qimage(v.view.image()), expect)
    np.testing.assert_array_equal(v.wheel.rgb, preview.aolp_wheel(v.wheel.wheel_px, dolp_as=None))
    # ROI statistics of Stokes data: S0, DoLP, AoLP
    v.view.set_shape("rect", [(0.0, 0.0), (32.0, 24.0)])
    roi_done(qtbot, v.roi)
    names = {r.quantity for r in v.roi.rows}
    assert names == {"S0", "DoLP", "AoLP_deg"}
    assert next(r for r in v.roi.rows if r.quantity == "S0").mean == pytest.approx(
        float(stokes[0, 0].mean()), rel=1e-5)


def test_aolp_wheel_hue_is_the_axis_angle():
    w = preview.aolp_wheel(101, dolp_as=None)
    c = 50
    for ang in (10.0, 60.0, 100.0, 150.0):  # opposite directions: one axis, one colour
        t = np.deg2rad(ang)
        for sign in (1, -1):
            x, y = int(round(c + sign * 30 * np.cos(t))), int(round(c - sign * 30 * np.sin(t)))
            hue_rgb = preview.aolp_rgb(np.array([[ang]]))[0, 0].astype(int)
            assert np.abs(w[y, x].astype(int) - hue_rgb).max() <= 40
    assert (w[0, 0] == 255).all()  # outside the disc


def test_live_view_new_displays_and_roi(qtbot, tmp_path):
    from test_gui import close_window, make_window, wait_frames

    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        wait_frames(qtbot, w, 2)
        keys = [w.live.display.itemData(i) for i in range(w.live.display.count())]
        assert {"imin", "imax", "s1", "s2", "aolp_dolp_sat"} <= set(keys)
        assert "maps" not in keys and "polarizer" not in keys
        for display in ("imin", "imax", "s1", "s2", "aolp_dolp_sat"):
            w.live.set_display(display)
            qtbot.waitUntil(lambda d=display: w.live.last is not None and w.live.last.display == d,
                            timeout=20000)
            res = w.live.last
            rgb = from_qimage(res.image)
            expect = pipeline.render(res.data, display, res.colour, saturation_overlay=True,
                                     step=res.step)
            np.testing.assert_array_equal(rgb, expect)
        assert w.live.wheel.mode == "saturation"
        w.live.pause_for("a test", True)  # no newer frame's statistics replace these
        w.live.view.set_shape("rect", [(2.0, 2.0), (10.0, 12.0)])
        res = w.live.last
        w.live.roi.set_data(res.data)
        roi_done(qtbot, w.live.roi)
        assert w.live.roi.data is res.data
        region = w.live.roi.region
        assert region == roi.RectROI(2.0 * res.step, 2.0 * res.step, 8.0 * res.step, 10.0 * res.step)
        inside = roi.roi_mask(region, pipeline.roi_shape(res.data))
        assert w.live.roi.rows == roi.roi_statistics(inside, stokes=res.data.stokes,
                                                     valid=pipeline.roi_valid(res.data),
                                                     snr=res.data.snr)
    finally:
        close_window(qtbot, w)


def test_live_roi_statistics_slower_than_the_frames_still_reach_the_table(qtbot, tmp_path,
                                                                          monkeypatch):
    """Statistics that take longer than the live view's interval between them (seconds at the
    full sensor) are shown, then the next frame's: a new frame's request waits for the one
    being computed instead of superseding it (which left the table empty while frames came)."""
    import time

    from test_gui import close_window, make_window, wait_frames

    from polrig.gui import live_panel

    real = pipeline.roi_statistics
    calls = []

    def slow(*a, **k):
        calls.append(time.monotonic())
        time.sleep(3 * live_panel.ROI_INTERVAL_S)
        return real(*a, **k)
    monkeypatch.setattr(pipeline, "roi_statistics", slow)
    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        wait_frames(qtbot, w, 2)
        w.live.set_display("s1")
        qtbot.waitUntil(lambda: w.live.last is not None and w.live.last.display == "s1",
                        timeout=20000)
        w.live.view.set_shape("rect", [(2.0, 2.0), (10.0, 12.0)])
        shown = w.live.frames_shown
        qtbot.waitUntil(lambda: bool(w.live.roi.rows), timeout=30000)
        assert w.live.frames_shown > shown  # the live view went on meanwhile
        qtbot.waitUntil(lambda: len(calls) >= 2, timeout=30000)  # and the next frame's follow
    finally:
        close_window(qtbot, w)
