"""The GUI's live Mueller view on the device route (issue 31, item 4), forced on the CPU
provider (no GPU here): the live worker takes :meth:`polrig.app.single_shot.SingleShot.live`
at the panel's display size, the window shows the grid the device rendered at display size, equal
to the host route's Mueller image reduced to that size (within ``tests/test_device_path.py``'s
``ROUTE_RTOL`` of each element's maximum; the uint8 image within one level), the probe runs on
the stated schedule, the frame rate updates, and an ROI switches the view to whole frames
(:meth:`~polrig.app.single_shot.SingleShot.frame`), whose statistics it shows."""

from __future__ import annotations

import pathlib
import threading

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")
pytest.importorskip("onnxruntime")

import cv2  # noqa: E402
from test_device_path import ROUTE_RTOL  # noqa: E402
from test_gui import close_window, make_window  # noqa: E402

from polrig.app import preview  # noqa: E402
from polrig.app.single_shot import SingleShot  # noqa: E402
from polrig.gui import pipeline  # noqa: E402
from polrig.gui.qtimage import from_qimage  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.gui, pytest.mark.skipif(
    not (REPO / "models" / "weights" / "single_shot.onnx").is_file(), reason="no single-shot model")]
#: The simulated rig: a mono 512x512 sensor, whose 256x256 network grid is large enough for the
#: light-direction probe (:func:`polrig.models.runtime.probe_shape`; smaller grids run twice).
SIM = {"size": "512x512", "sensor": "imx250mzr"}
#: The live panel's display size in this test: three 256-pixel tiles across, shown 1:3 -> 85x85
#: display pixels per element (3.01 image pixels each: partial pixels in the area average).
MAX_DISPLAY_PX = 300


class RecordingRoute(SingleShot):
    """The real device route, recording each live frame: its arguments, its result and whether
    the light-direction probe ran for it (the networks' passes of :class:`DevicePath`)."""

    def __init__(self, model):
        super().__init__(model, "device")
        self.calls: list[dict] = []
        self.passes: list[str] = []
        #: held during a live frame: the test's host-route frames on the same model wait for it
        self.busy = threading.Lock()
        path = self.device_path()
        network = path._network

        def counted(outputs, feed):  # the path's own pass, counted
            self.passes.append(outputs)
            return network(outputs, feed)

        path._network = counted

    def live(self, frame, state_deg, options, **kwargs):
        with self.busy:
            before = len(self.passes)
            result = super().live(frame, state_deg, options, **kwargs)
            self.calls.append({"frame": frame, "state_deg": state_deg, "options": options, "kwargs": kwargs,
                               "result": result, "n": self.device_path()._frames,
                               "probed": "probe" in self.passes[before:]})
        return result


def _host_grid(route: RecordingRoute, call) -> tuple[np.ndarray, np.ndarray]:
    """The host route's whole frame of a recorded live call, each element reduced to the live
    grid's display size by area (``(C, 3, 3, dh, dw)``), and its object mask reduced the same way."""
    kw = call["kwargs"]
    with route.busy:  # not beside the live worker's frame on the same model
        whole = SingleShot(route.model, "host").frame(call["frame"], call["state_deg"], call["options"],
                                                      geometry=kw["geometry"], sensor=kw["sensor"])
    c, dh3, dw3 = call["result"].preview_grid.shape
    dh, dw = dh3 // 3, dw3 // 3
    small = np.stack([[[cv2.resize(whole.mueller[k, r, q], (dw, dh), interpolation=cv2.INTER_AREA)
                        for q in range(3)] for r in range(3)] for k in range(c)])
    inside = cv2.resize(whole.object.astype(np.float32), (dw, dh), interpolation=cv2.INTER_AREA) >= 0.5
    return small, inside


@pytest.mark.slow
def test_the_live_mueller_grid_of_the_device_route_is_the_host_grid_at_display_size(qtbot, tmp_path):
    from polrig.models.runtime import SingleShotModel

    model = SingleShotModel.load(device="cpu", threads=1)
    route = RecordingRoute(model)
    w = make_window(qtbot, tmp_path / "gui.ini", model_loader=lambda: route, **SIM)
    try:
        w.live_worker.settings.max_display_px = MAX_DISPLAY_PX
        # phase 0: a frame of the window's first display (Stokes, whole images) is shown
        qtbot.waitUntil(lambda: w.live.roi.data is not None, timeout=120000)
        assert w.live.roi.data.mueller is None and w.live.roi.data.stokes is not None
        w.live.set_display("mueller")
        route.device_path().probe_every = 1  # phase 1: every live frame probes, as frame() does
        qtbot.waitUntil(lambda: w.live.last is not None and w.live.last.display == "mueller"
                        and w.live.last.data.mueller_preview is not None, timeout=120000)
        res = w.live.last
        call = next(c for c in route.calls if c["frame"].raw is res.data.raw)
        assert call["kwargs"]["max_display_px"] == MAX_DISPLAY_PX
        assert res.data.mueller is None and res.data.stokes is None and res.step == 1
        assert res.data.mueller_preview.shape == (1, 3, 3, 85, 85) and res.data.preview_of == (256, 256)
        assert "display size" in res.note
        # the numbers: the host route's Mueller image reduced to the display size
        small, inside = _host_grid(route, call)
        got = res.data.mueller_preview
        assert float(np.abs(got - small).max()) <= ROUTE_RTOL * float(np.abs(small).max())
        # the picture: the host grid rendered at display size by the same colour maps and masks
        expect = preview.mueller_grid(small, border_px=pipeline.GRID_BORDER_PX, valid=inside)
        shown = from_qimage(res.image)
        assert shown.shape == expect.shape
        assert int(np.abs(shown.astype(int) - expect.astype(int)).max()) <= 1
        # the readout: the display pixel's mean matrix
        b = pipeline.GRID_BORDER_PX
        w.live._hovered(b + 2, b + 2)
        assert "display pixel (u=2, v=2) of 85x85" in w.live.readout.text()

        # phase 2: the live schedule, the probe every third frame, the frame rate updating
        route.device_path().probe_every = 3
        start = len(route.calls)
        first_fps = w.live.last.fps
        qtbot.waitUntil(lambda: len(route.calls) >= start + 8, timeout=180000)
        later = route.calls[start + 1:]  # the first may have started before the change
        assert [c["probed"] for c in later] == [(c["n"] - 1) % 3 == 0 for c in later]
        assert any(c["probed"] for c in later) and not all(c["probed"] for c in later)
        qtbot.waitUntil(lambda: w.live.last.fps > 0 and w.live.last.fps != first_fps, timeout=60000)
        assert "fps" in w.fps_label.text()

        # an ROI needs every image pixel: the live view takes whole frames and measures them
        n_live = len(route.calls)
        w.live.view.set_shape("rect", [(b + 10, b + 10), (b + 40, b + 40)])
        assert w.live_worker.settings.full_mueller
        # what the ROI measures is a frame of this display, not the last one with whole
        # images (phase 0's, Stokes only: its S0, DoLP, AoLP rows were shown as this frame's)
        qtbot.waitUntil(lambda: not w.live.roi.busy, timeout=60000)
        assert w.live.roi.data is None or w.live.roi.data.mueller is not None
        assert w.live.roi.region is not None  # drawn on 85x85 display pixels -> 256x256 image pixels
        qtbot.waitUntil(lambda: w.live.last.data.mueller is not None and bool(w.live.roi.rows), timeout=120000)
        assert w.live.last.data.mueller.shape == (1, 3, 3, 256, 256) and len(route.calls) <= n_live + 1
        first = w.live.roi.rows[0]  # display 10..40 -> image 30.1..120.5: pixel centres 30.5..119.5
        assert first.n_counted + first.n_masked == 90 * 90 and first.quantity == "S0"
        assert {r.quantity for r in w.live.roi.rows} >= {"m01/m00", "m22/m00", "retardance_deg"}
    finally:
        close_window(qtbot, w)
