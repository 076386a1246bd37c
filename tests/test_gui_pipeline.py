"""The GUI's display pipeline (no widgets): strip-parallel Stokes equal the core's, displays
render finite uint8 images with the saturation overlay where the core says saturated, the
readout shows the core's numbers, the latest-frame slot never holds more than one frame."""

from __future__ import annotations

import pathlib
import threading

import numpy as np
import pytest

from polrig.gui import pipeline
from polrig.gui.live import LatestSlot, RateMeter
from polrig.sensor.frame import Frame, FrameMeta
from polrig.sensor.stokes import stokes_from_raw

REPO = pathlib.Path(__file__).resolve().parents[1]


def _frame(raw: np.ndarray, layout: str, bit_depth: int = 12, black: float = 16.0) -> Frame:
    return Frame(raw, FrameMeta(7, 0.0, 1000.0, 0.0, "Mono12p", layout, bit_depth, (0, 0), black))


@pytest.mark.parametrize("layout", ["imx250myr", "imx250mzr"])
@pytest.mark.parametrize("shape", [(8, 8), (24, 40), (100, 64), (4, 4)])
@pytest.mark.parametrize("workers", [2, 3, 4])
def test_strips_equal_one_core_call(layout, shape, workers):
    rng = np.random.default_rng(sum(shape) + workers)
    raw = rng.integers(0, 4096, shape).astype(np.uint16)
    raw[0, :3] = 4095  # saturated samples
    if layout == "imx250myr" and shape[0] % 4:
        pytest.skip("colour layout needs multiples of 4")
    ref = stokes_from_raw(raw, layout, "superpixel", black_level_dn=16.0, bit_depth=12)
    got = pipeline.stokes_from_raw_strips(raw, layout, "superpixel", black_level_dn=16.0,
                                          bit_depth=12, workers=workers)
    for name in ("stokes", "valid", "saturated", "dolp", "aolp_deg"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    assert got.dolp_overshoot == ref.dolp_overshoot


def test_non_superpixel_methods_go_to_the_core_unchanged():
    raw = np.random.default_rng(1).integers(0, 4096, (32, 32)).astype(np.uint16)
    for method in ("bilinear", "newton"):
        ref = stokes_from_raw(raw, "imx250mzr", method, bit_depth=12)
        got = pipeline.stokes_from_raw_strips(raw, "imx250mzr", method, bit_depth=12, workers=2)
        np.testing.assert_array_equal(got.stokes, ref.stokes)


@pytest.mark.parametrize("fill", ["dark", "saturated", "noise", "zero"])
@pytest.mark.parametrize("layout", ["imx250myr", "imx250mzr"])
def test_every_display_renders_uint8_with_the_saturation_overlay(fill, layout):
    rng = np.random.default_rng(3)
    raw = {"dark": np.full((32, 32), 16), "saturated": np.full((32, 32), 4095),
           "noise": rng.integers(0, 4096, (32, 32)), "zero": np.zeros((32, 32))}[fill]
    data = pipeline.process_frame(_frame(raw.astype(np.uint16), layout))
    for display in data.available():
        for colour in (pipeline.LUMINANCE, 0, 2):
            rgb = pipeline.render(data, display, colour, saturation_overlay=True)
            assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
            counts, edges, _ = pipeline.histogram(data, display, colour)
            assert np.all(np.isfinite(edges)) and counts.sum() >= 0
            if fill == "saturated" and display != "raw":
                assert np.all(rgb == pipeline.SATURATION_RGB)  # every pixel saturated
            if fill == "saturated" and display == "raw":
                assert np.all(rgb == pipeline.SATURATION_RGB)


def test_readout_shows_the_core_numbers():
    rng = np.random.default_rng(5)
    raw = rng.integers(200, 3000, (16, 16)).astype(np.uint16)
    frame = _frame(raw, "imx250mzr")
    data = pipeline.process_frame(frame)
    ref = stokes_from_raw(raw, "imx250mzr", "superpixel", black_level_dn=16.0, bit_depth=12)
    text = pipeline.readout(data, "dolp", 3, 2)
    s = ref.stokes[0, :, 2, 3]
    assert f"S=({s[0]:.1f}, {s[1]:.1f}, {s[2]:.1f})" in text
    assert f"DoLP {ref.dolp[0, 2, 3]:.3f}" in text and f"AoLP {ref.aolp_deg[0, 2, 3]:.1f}" in text
    assert pipeline.readout(data, "dolp", 100, 100) == ""  # outside: nothing, no exception


def test_mueller_grid_coordinates_and_readout():
    m = np.zeros((1, 3, 3, 10, 12), np.float32)
    m[0, 0, 0] = 2.0
    m[0, 1, 2, 4, 5] = -1.0
    data = pipeline.PolarizationData.from_mueller(m)
    grid = pipeline.render(data, "mueller")
    b = pipeline.GRID_BORDER_PX
    x, y = b + 2 * (12 + b) + 5, b + 1 * (10 + b) + 4  # element m12, pixel (u=5, v=4)
    assert pipeline.grid_to_pixel(x, y, (10, 12)) == (1, 2, 5, 4)
    assert pipeline.grid_to_pixel(0, 0, (10, 12)) is None
    assert np.array_equal(grid[y, x], pipeline.preview.diverging(np.array([[-0.5]]), vmax=1.0)[0, 0])
    text = pipeline.readout(data, "mueller", x, y)
    assert "Mueller at (u=5, v=4)" in text and "-0.500" in text
    assert pipeline.render(data, "s0").shape == (10, 12, 3)  # m00 for a Mueller-only source
    with pytest.raises(ValueError, match="not available"):
        pipeline.render(data, "dolp")


def test_decimated_mueller_grid_keeps_the_readout_on_the_data_pixel():
    """A large Mueller image is shown decimated (every step-th pixel of each tile) so the grid
    fits the display, and the cursor readout of a decimated tile pixel names the data pixel it
    shows, at full resolution."""
    h, w = 40, 60
    m = np.zeros((1, 3, 3, h, w), np.float32)
    m[0, 0, 0] = 2.0
    m[0, 1, 2] = np.arange(w, dtype=np.float32)[None, :] / w - 0.5  # m12/m00 varies along u
    data = pipeline.PolarizationData.from_mueller(m)
    step = pipeline.display_step(data, "mueller", 60)  # three tiles of 60 px in 60 px: 1 in 3
    assert step == 3
    assert pipeline.display_step(data, "mueller", 0) == 1
    grid = pipeline.render(data, "mueller", step=step)
    full = pipeline.render(data, "mueller")
    th, tw = -(-h // step), -(-w // step)
    b = pipeline.GRID_BORDER_PX
    assert grid.shape[0] == 3 * th + 4 * b and full.shape[0] == 3 * h + 4 * b
    u_dec, v_dec = 7, 5
    x, y = b + 2 * (tw + b) + u_dec, b + 1 * (th + b) + v_dec  # element m12 of the decimated grid
    xf, yf = b + 2 * (w + b) + u_dec * step, b + 1 * (h + b) + v_dec * step  # the same data pixel, whole grid
    assert np.array_equal(grid[y, x], full[yf, xf])
    text = pipeline.readout(data, "mueller", x, y, step)
    assert f"Mueller at (u={u_dec * step}, v={v_dec * step})" in text
    assert text == pipeline.readout(data, "mueller", xf, yf)


def test_latest_slot_holds_one_item_and_counts_drops():
    slot = LatestSlot()
    assert slot.put(1) is True and slot.put(2) is False and slot.put(3) is False
    assert slot.dropped == 2 and slot.take() == 3 and slot.take() is None

    def writer():
        for i in range(10000):
            slot.put(i)

    threads = [threading.Thread(target=writer) for _ in range(3)]
    for t in threads:
        t.start()
    taken = []
    while any(t.is_alive() for t in threads):
        v = slot.take()
        if v is not None:
            taken.append(v)
    for t in threads:
        t.join()
    rest = slot.take()
    total = len(taken) + (rest is not None) + slot.dropped
    assert total == 30000 + 2  # every put was taken, is still there, or was dropped (+2 above)


def test_rate_meter():
    m = RateMeter(window_s=10.0)
    for k in range(11):
        m.tick(100.0 + 0.05 * k)
    assert m.rate() == pytest.approx(20.0)


@pytest.mark.skipif(not (REPO / "models" / "weights" / "single_shot.onnx").is_file(),
                    reason="no single-shot model in models/weights")
def test_live_mueller_grid_at_full_resolution_has_the_sensor_size():
    """The live view's single-shot Mueller grid (issue 22 item 1): at ``full`` resolution the
    Mueller image, its Stokes images and masks have the simulated sensor's size (the networks'
    grid is a quarter of it per axis on the colour sensor), the grid renders 3x3 of them, and
    the detail keeps the networks' cell averages. Through the one single-shot route with the
    live view's options (:meth:`polrig.acquisition.plan.SingleShotOptions.from_settings`: its
    superpixel demosaic stands for the default detail at full resolution)."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.calibrations import nominal_calibration, single_shot_geometry
    from polrig.app.rig import build_rig, load_rig_config
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    rig = build_rig(load_rig_config(None), {"size": "128x96", "clock_speed": 1000.0})
    rig.open()
    try:
        frame = rig.camera.grab(timeout_s=10.0)
    finally:
        rig.close()
    route = SingleShot(SingleShotModel.load(threads=1, device="cpu"))
    geometry = single_shot_geometry(nominal_calibration(), rig.config)

    def live(resolution: str) -> pipeline.PolarizationData:
        options = SingleShotOptions.from_settings(demosaic="superpixel", resolution=resolution, sigma=False)
        return pipeline.PolarizationData.from_single_shot(
            route.frame(frame, 0.0, options, geometry=geometry), frame, "live")

    sp, full = live("superpixel"), live("full")
    assert sp.mueller.shape == (3, 3, 3, 24, 32)
    assert full.mueller.shape == (3, 3, 3, 96, 128) and full.stokes.shape[-2:] == (96, 128)
    assert full.snr.shape[-2:] == (96, 128) and full.flags.shape[-2:] == (96, 128)
    grid = pipeline.render(full, "mueller")
    b = pipeline.GRID_BORDER_PX
    assert grid.shape[0] == 3 * 96 + 4 * b and grid.shape[1] > 3 * 128 + 4 * b  # + colour bar
    obj = (full.flags[0] & pipeline.preview.BACKGROUND) == 0
    cells = obj.reshape(24, 4, 32, 4).all(axis=(1, 3))
    assert cells.sum() > 10
    avg = full.mueller.reshape(3, 3, 3, 24, 4, 32, 4).mean(axis=(-3, -1))
    err = np.abs(avg - sp.mueller)[..., cells].mean() / np.abs(sp.mueller[..., cells]).mean()
    assert err < 0.25, err


def test_a_display_size_mueller_grid_shows_as_the_matrix_and_maps_rois_to_image_pixels():
    """A live result carrying only the device's display-size grid (``preview_grid``
    ``(C, 3 dh, 3 dw)``, laid out as the matrix): the data holds it as ``(C, 3, 3, dh, dw)``,
    masks display pixels less than half object, shows only the grid (at step 1, rendered as the
    whole-image grid would be from the same means), reads out its means, reports that ROI
    statistics need the whole image, and maps a point drawn on any tile to image pixels."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app import preview
    from polrig.app.single_shot import SingleShotResult

    rng = np.random.default_rng(3)
    small = rng.uniform(-1, 1, (1, 3, 3, 4, 6)).astype(np.float32)
    small[:, 0, 0] = rng.uniform(1, 2, (4, 6))
    grid = small.transpose(0, 1, 3, 2, 4).reshape(1, 12, 18)  # the grid_preview graph's layout
    obj = np.zeros((8, 12), bool)
    obj[:, :5] = True  # display columns 0-1 object, column 2 (image 4-5) half: 4 of 4 rows x 1/2
    z = np.zeros((1, 3, 3, 8, 12), np.float32)
    res = SingleShotResult(z, z, z, np.zeros((1, 8, 12), np.uint8), np.zeros((1, 8, 12)), obj,
                           SingleShotOptions(sigma=False), preview_grid=grid)
    d = pipeline.PolarizationData.from_single_shot(res, source="live")
    np.testing.assert_array_equal(d.mueller_preview, small)
    assert d.mueller is None and d.preview_of == (8, 12) and d.available() == ["mueller"]
    inside = d.flags[0] == 0
    assert inside[:, :3].all() and not inside[:, 3:].any()  # column 2 exactly half object: shown
    assert pipeline.needs_full_image(d, "mueller") and pipeline.display_step(d, "mueller", 4) == 1
    np.testing.assert_array_equal(
        pipeline.render(d, "mueller"),
        preview.mueller_grid(small, border_px=pipeline.GRID_BORDER_PX, valid=inside))
    b = pipeline.GRID_BORDER_PX
    text = pipeline.readout(d, "mueller", b + (6 + b) + 1, b + 2)  # tile m01, display pixel (1, 2)
    assert "display pixel (u=1, v=2) of 6x4" in text and f"m00 = {small[0, 0, 0, 2, 1]:.4g}" in text
    # a rectangle drawn on tile m12 (row 1, column 2): tile-relative, two image pixels per display pixel
    ox, oy = b + 2 * (6 + b), b + (4 + b)
    assert pipeline.display_to_data(d, "mueller", [(ox + 1, oy + 1), (ox + 3, oy + 2)]) == [(2.0, 2.0), (6.0, 4.0)]
    assert pipeline.summary(d) == {"size": (12, 8)}


@pytest.mark.parametrize("name, negative", [("mmt_b", (-0.8, -0.2)), ("mmt_A", (-0.8, -0.2)),
                                            ("sv2", (0.8, -0.2))])
def test_signed_parameter_maps_show_their_sign(name, negative):
    """``mmt_b`` and ``mmt_A`` lie in -1..1 (docs/analysis.md; ``b`` < 0 where the block turns
    the light's frame by more than 45 deg, e.g. optical rotation): their map shows the sign on
    the diverging map as ``sv2``'s does; on the 0..1 map a negative value looked like 0."""
    from polrig.optics import parameters as pa

    h, w = 4, 3
    m = np.zeros((1, 3, 3, h, w), np.float32)
    m[0, 0, 0] = 100.0
    for col, (n11, n22) in enumerate((negative, (0.0, 0.0), (0.8, 0.2))):  # diagonal blocks
        m[0, 1, 1, :, col], m[0, 2, 2, :, col] = 100.0 * n11, 100.0 * n22
    data = pipeline.PolarizationData.from_mueller(m)
    v = pa.image_maps(m, None).values[name][0]
    assert v[0, 0] < -0.1 and v[0, 2] > 0.1  # negative, positive (and zero: column 1)
    got = pipeline.render_map(data, name, 0)
    np.testing.assert_array_equal(got, pipeline.preview.diverging(v, vmax=1.0,
                                                                  valid=np.isfinite(v)))
    assert not np.array_equal(got[0, 0], pipeline.preview.diverging(np.zeros((1, 1)), vmax=1.0)[0, 0])
