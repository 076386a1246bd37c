"""The operator GUI on the simulated rig (pytest-qt, offscreen): live frames, displays and
readout, a two-pose reference capture, a device fault while the UI stays responsive, closing
during a capture (then resuming with the core API), settings, shortcuts, the viewer."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestqt = pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt, QTimer  # noqa: E402

from polrig.app.rig import build_rig, load_rig_config  # noqa: E402
from polrig.gui import pipeline  # noqa: E402
from polrig.gui.latency import EventLoopProbe  # noqa: E402
from polrig.gui.main_window import MainWindow  # noqa: E402
from polrig.gui.qtimage import from_qimage  # noqa: E402
from polrig.gui.settings import make_settings  # noqa: E402

pytestmark = pytest.mark.gui
SIM = {"size": "64x64", "clock_speed": 1000.0}


def make_window(qtbot, settings_path, start: bool = True, model_loader=None, **sim) -> MainWindow:
    rig = build_rig(load_rig_config(None), {**SIM, **sim})
    w = MainWindow(rig, make_settings(settings_path), live_max_fps=40.0, poll_ms=150,
                   model_loader=model_loader)
    qtbot.addWidget(w)
    w.show()
    if start:
        w.start()
    return w


def close_window(qtbot, w: MainWindow) -> None:
    if w.capture.is_running:
        w.capture.stop()
        qtbot.waitUntil(lambda: not w.capture.is_running, timeout=30000)
    w.close()
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=30000)
    assert not w.live_worker.isRunning() and not w.devices.worker.isRunning()


@pytest.fixture
def window(qtbot, tmp_path):
    w = make_window(qtbot, tmp_path / "gui.ini")
    yield w
    if w.isVisible():
        close_window(qtbot, w)


def open_and_wait(qtbot, viewer, path, kind: str = "exr", timeout: int = 60000) -> bool:
    """Open ``path`` in ``viewer`` and wait until it is shown (True) or its error is reported
    (False): the viewer loads files off the UI thread."""
    with qtbot.waitSignal(viewer.loaded, timeout=timeout) as blocker:
        assert viewer.open_file(path, kind)
    return blocker.args[0]


def wait_loaded(qtbot, viewer, timeout: int = 60000) -> None:
    """Wait for the viewer's latest load (a session's first entry, an entry chosen)."""
    qtbot.waitUntil(lambda: not viewer.loading, timeout=timeout)


def wait_connected(qtbot, w: MainWindow, timeout: int = 20000) -> None:
    qtbot.waitUntil(lambda: all(d.is_open for d in w.rig.devices.values()), timeout=timeout)


def wait_frames(qtbot, w: MainWindow, n: int, timeout: int = 20000) -> None:
    start = w.live.frames_shown
    qtbot.waitUntil(lambda: w.live.frames_shown >= start + n, timeout=timeout)


def test_window_opens_and_live_frames_arrive(qtbot, window):
    wait_frames(qtbot, window, 10)
    res = window.live.last
    rgb = from_qimage(res.image)
    assert rgb.shape == (16, 16, 3) and rgb.std() > 0  # 64x64 colour mosaic, superpixel
    assert window.live_worker.frames_processed >= window.live.frames_shown
    assert "fps" in window.fps_label.text()
    qtbot.waitUntil(lambda: window.live.last.fps > 1.0, timeout=10000)
    qtbot.waitUntil(lambda: all(s["open"] for s in window.devices.last_status.values()),
                    timeout=10000)
    print(f"\nlive: {window.live.frames_shown} frames shown, {res.fps:.1f} fps, "
          f"{window.live_worker.dropped} dropped")


@pytest.mark.parametrize("display", ["raw", "s0", "dolp", "aolp", "aolp_dolp"])
def test_live_displays_readout_histogram(qtbot, window, display):
    window.live.set_display(display)
    qtbot.waitUntil(lambda: window.live.last is not None and window.live.last.display == display,
                    timeout=10000)
    res = window.live.last
    img = from_qimage(res.image)
    want = (64, 64) if display == "raw" else (16, 16)
    assert img.shape[:2] == want
    counts, edges, label = res.hist
    assert counts.sum() > 0 and np.all(np.diff(edges) > 0) and label
    window.live._hovered(8, 8)
    text = window.live.readout.text()
    assert ("raw (8, 8)" in text) if display == "raw" else ("pixel (u=8, v=8)" in text)
    assert "DoLP" in text and "AoLP" in text


def test_exposure_control_reaches_the_camera(qtbot, window):
    wait_frames(qtbot, window, 2)
    window.live.exposure.setValue(5000.0)
    qtbot.waitUntil(lambda: window.live.last.exposure_us == 5000.0, timeout=10000)
    window.live.method.setCurrentText("bilinear")
    qtbot.waitUntil(lambda: window.live.last.image.width() == 64, timeout=10000)


def test_mueller_display_without_a_model_is_a_message_not_a_crash(qtbot, window):
    window.live.set_display("mueller")
    qtbot.waitUntil(lambda: window.live.last is not None and (
        window.live.last.display == "mueller" or "unavailable" in window.live.last.note),
        timeout=60000)
    res = window.live.last
    if res.display == "mueller":  # a model is installed: the 3x3 grid with its colour bar
        assert res.image.width() > 3 * 16
        window.live._hovered(4, 4)
        assert "Mueller" in window.live.readout.text()
    else:
        assert "single-shot" in res.note and "unavailable" in window.fps_label.text()
        assert res.display == "aolp_dolp"  # still showing live frames


@pytest.fixture(scope="module")
def untrained_model_dir(tmp_path_factory):
    """A real single-shot ONNX graph exported from freshly initialised (untrained) networks:
    it exercises the live Mueller path end to end (its numbers are not a reconstruction)."""
    torch = pytest.importorskip("torch")
    from polrig.models.export import export_all
    from polrig.models.pipnet import PIPNet
    from polrig.models.pmmnet import DirectStokesToMM, PMMNet

    torch.manual_seed(0)
    wo = torch.zeros(1, 3, 16, 16)
    wo[:, 2] = -1.0
    sample = {"analyzer": torch.rand(1, 3, 4, 16, 16), "mask": torch.ones(1, 1, 16, 16),
              "s_in": torch.tensor([[0.5, 0.5, 0.0]]), "wo": wo,
              "stage_zero_axis": torch.tensor([[0.0, -1.0, 0.0]])}
    out = tmp_path_factory.mktemp("untrained")
    export_all(PIPNet(3, 4), PMMNet(3, 4, 2), DirectStokesToMM(3, 4), out, sample)
    return out


@pytest.mark.slow
def test_live_mueller_grid_with_a_model(qtbot, tmp_path, untrained_model_dir):
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    w = make_window(qtbot, tmp_path / "gui.ini",
                    model_loader=lambda: SingleShot(SingleShotModel.load(untrained_model_dir, threads=1)))
    try:
        w.live.set_display("mueller")
        qtbot.waitUntil(lambda: w.live.last is not None and w.live.last.display == "mueller",
                        timeout=60000)
        res = w.live.last
        assert res.data.mueller.shape == (3, 3, 3, 16, 16)
        grid = from_qimage(res.image)
        b = pipeline.GRID_BORDER_PX
        assert grid.shape[0] == 3 * 16 + 4 * b and grid.shape[1] > 3 * 16 + 4 * b  # + colour bar
        w.live.colour.setCurrentIndex(w.live.colour.findData(1))  # green only
        qtbot.waitUntil(lambda: w.live.last.colour == 1 and w.live.last.display == "mueller",
                        timeout=30000)
        w.live._hovered(b + 8, b + 8)
        text = w.live.readout.text()
        assert "Mueller at (u=8, v=8)" in text and "G:" in text
        # mirror averaging (polrig.models.mirror) reaches the worker and the live frames keep coming
        w.live.mirror_average.setChecked(True)
        assert w.live_worker.settings.mirror_average
        before = w.live.last
        qtbot.waitUntil(lambda: w.live.last is not before and w.live.last.display == "mueller", timeout=30000)
        assert np.all(np.isfinite(w.live.last.data.mueller))
        # full resolution (polrig.models.full_resolution): the grid of the sensor's own 64x64 pixels
        w.live.resolution.setCurrentText("full")
        assert w.live_worker.settings.resolution == "full"
        qtbot.waitUntil(lambda: w.live.last.display == "mueller"
                        and w.live.last.data.mueller.shape[-2:] == (64, 64), timeout=30000)
        assert from_qimage(w.live.last.image).shape[0] == 3 * 64 + 4 * b
        # the faster mode: the networks on the 16x16 grid binned to 8x8, the answer lifted back
        w.live.binning.setCurrentIndex(w.live.binning.findData(2))
        assert w.live_worker.settings.network_binning == 2
        before = w.live.last
        qtbot.waitUntil(lambda: w.live.last is not before and w.live.last.display == "mueller"
                        and w.live_worker.settings.network_binning == 2, timeout=30000)
        assert w.live.last.data.mueller.shape[-2:] == (64, 64)
        assert np.all(np.isfinite(w.live.last.data.mueller))
    finally:
        close_window(qtbot, w)


def test_two_pose_reference_capture_completes(qtbot, window, tmp_path):
    wait_frames(qtbot, window, 2)
    out = tmp_path / "session"
    cp = window.capture
    cp.poses.setText("0,90")
    cp.out.setText(str(out))
    paused = []
    cp.running.connect(lambda r: paused.append((r, window.live_worker.paused)))
    window.show_panel(cp)
    window.activateWindow()
    window.capture_action.trigger()  # what Ctrl+R triggers
    qtbot.waitUntil(lambda: cp.last_status == "complete", timeout=60000)
    qtbot.waitUntil(lambda: not cp.is_running, timeout=10000)
    assert paused[0] == (True, True)  # the live view paused for the capture...
    assert not window.live_worker.paused  # ...and runs again after it
    qtbot.waitUntil(lambda: cp.thumbnails_shown == 2, timeout=10000)  # made off the UI thread
    assert cp.thumbs.count() == 2
    assert cp.progress.value() == cp.progress.maximum() == 8  # 2 poses x 4 states
    assert set(cp.scores) == {0, 1} and all(s["rmse"] > 0 for s in cp.scores.values())
    assert "RMSE" in cp.score.text()
    manifest = json.loads((out / "session.json").read_text())
    assert manifest["status"] == "complete"
    assert [c["status"] for c in manifest["captures"]] == ["complete", "complete"]
    assert manifest["plan"]["poses_deg"] == [0.0, 90.0]
    wait_frames(qtbot, window, 2)  # live again


def test_finished_pose_thumbnails_are_made_off_the_ui_thread(qtbot, window, tmp_path,
                                                            monkeypatch):
    """A finished pose's thumbnail reads its Mueller EXR (about 0.8 s at the full sensor's
    1224x1024 superpixel grid): made on the UI thread it froze the window once per pose. Here
    each one takes 1 s; the event loop must never wait for it, and the icons still arrive."""
    import threading
    import time

    from polrig.gui import capture_panel

    real, threads = capture_panel.thumbnail_rgb, []

    def slow_thumbnail(path, *a, **kw):
        threads.append(threading.current_thread())
        time.sleep(1.0)
        return real(path, *a, **kw)
    monkeypatch.setattr(capture_panel, "thumbnail_rgb", slow_thumbnail)
    wait_connected(qtbot, window)
    cp = window.capture
    cp.poses.setText("0,90")
    cp.out.setText(str(tmp_path / "session"))
    probe = EventLoopProbe(10).start()
    cp.start()
    qtbot.waitUntil(lambda: cp.last_status == "complete" and not cp.is_running, timeout=60000)
    qtbot.waitUntil(lambda: cp.thumbnails_shown == 2, timeout=10000)
    probe.stop()
    assert len(threads) == 2 and threading.main_thread() not in threads
    assert probe.max_latency_s < 0.5, probe.max_latency_s
    assert [cp.thumbs.item(i).text() for i in range(2)] == ["pose 0 deg", "pose 90 deg"]


def test_a_thumbnail_of_an_earlier_run_is_not_put_on_a_new_one(qtbot, window, tmp_path):
    """A thumbnail that arrives after a new capture started (its run's list was cleared)
    is dropped, not put on the new run's pose of the same row."""
    cp = window.capture
    cp.thumbs.addItem("pose 0 deg")
    cp._thumbnail_ready(cp._run_id - 1, 0, None, "thumbnail of pose 0: stale")
    assert cp.thumbs.item(0).icon().isNull()
    assert not any("stale" in t for _, t in window.messages.messages)


def test_capture_needs_connected_devices(qtbot, tmp_path):
    w = make_window(qtbot, tmp_path / "gui.ini", start=False)  # nothing connected
    w.devices.start()
    try:
        w.capture.poses.setText("0")
        w.capture.out.setText(str(tmp_path / "s"))
        w.capture.start()
        qtbot.waitUntil(lambda: w.capture.last_status == "failed", timeout=20000)
        assert "not connected: camera, stage, turntable, light" in w.messages.messages[-1][1]
        assert not (tmp_path / "s").exists()  # refused before any file is written
    finally:
        close_window(qtbot, w)


def test_capture_form_asks_for_the_result_exr_format(qtbot, window, tmp_path):
    """The form's result planes, precision and compression reach the typed request and the
    plan it makes; an unknown plane group is a one-line plan error naming the field."""
    cp = window.capture
    cp.poses.setText("0")
    cp.out.setText(str(tmp_path / "s"))
    from polrig.acquisition.plan import ExrChoice

    assert cp.request().plan().exr == ExrChoice()  # the defaults, as the CLI's
    assert cp.request().plan().exr_planes == ("mueller", "sigma", "sigma_noise", "mask",
                                              "residual")
    cp.exr_planes.setText("sigma, mask")
    cp.exr_uncertainty.setCurrentText("float")
    assert cp.request().plan().exr_uncertainty == "float"
    cp.exr_uncertainty.setCurrentText("half")
    cp.exr_compression.setCurrentText("none")
    plan = cp.request().plan()
    assert (plan.exr_planes, plan.exr_uncertainty, plan.exr_compression) == (
        ("mueller", "sigma", "mask"), "half", "none")
    cp.exr_planes.setText("sigma,dolp")
    from polrig.acquisition.plan import PlanError
    with pytest.raises(PlanError, match="dolp") as info:
        cp.request().plan()
    assert info.value.field == "exr_planes"


def test_capture_form_asks_for_the_sample_metadata(qtbot, window, tmp_path):
    """The form's sample, operator, note and further keys reach the typed request as the
    :class:`polrig.app.manifest.SampleMetadata` ``polrig capture --sample ...`` gives; a resume
    keeps the session's (``None``); a bad key is one line."""
    from polrig.app.manifest import MetadataError, SampleMetadata

    cp = window.capture
    cp.poses.setText("0")
    cp.out.setText(str(tmp_path / "s"))
    assert cp.request().metadata == SampleMetadata()
    cp.sample.setText("gold ball")
    cp.operator.setText("ada")
    cp.note.setText("why")
    cp.md.setText("lot=42; batch_id = x7")
    assert cp.request().metadata == SampleMetadata(sample="gold ball", operator="ada", note="why",
                                                   user={"lot": "42", "batch_id": "x7"})
    assert cp.request(resume=True).metadata is None
    cp.md.setText("mode=x")
    with pytest.raises(MetadataError, match="one of polrig's own keys"):
        cp.request()


def test_bad_capture_options_are_a_message(qtbot, window, tmp_path):
    window.capture.poses.setText("0:10:0")
    window.capture.out.setText(str(tmp_path / "s"))
    window.capture.start()
    qtbot.waitUntil(lambda: window.capture.last_status == "failed", timeout=10000)
    assert "STEP must not be 0" in window.messages.messages[-1][1]
    assert not (tmp_path / "s").exists()


def test_device_fault_shows_a_message_and_the_ui_stays_responsive(qtbot, window):
    qtbot.waitUntil(lambda: window.devices.last_status.get("stage", {}).get("open", False),
                    timeout=10000)
    wait_frames(qtbot, window, 2)
    probe = EventLoopProbe(10).start()
    frames_before = window.live.frames_shown
    faults = window.rig.faults
    faults.inject_fault("stage", "fault", after_calls=0)
    faults.inject_fault("camera", "timeout", after_calls=0)
    window.devices.move("turntable", 8000.0)  # 800 s simulated = 0.8 s of a busy device
    window.devices.move("stage", 30.0)
    qtbot.waitUntil(lambda: any("simulated device fault" in t for lvl, t in
                                window.messages.messages if lvl == "error"), timeout=20000)
    qtbot.waitUntil(lambda: any("simulated timeout" in t for _, t in window.messages.messages),
                    timeout=20000)
    qtbot.waitUntil(lambda: "turntable" in " ".join(t for _, t in window.messages.messages[-20:])
                    and window.devices.last_status["turntable"].get("position_deg", 0) > 7999,
                    timeout=20000)
    wait_frames(qtbot, window, 3)  # the live view recovered from the camera timeout
    probe.stop()
    latency = probe.max_latency_s
    text = [t for lvl, t in window.messages.messages if lvl == "error"]
    assert any("device error 13" in t for t in text)  # the device's own code, readable
    assert "simulated" in window.statusBar().currentMessage() or text
    assert window.live.frames_shown > frames_before
    print(f"\nevent-loop latency during the fault: max {1e3 * latency:.1f} ms over "
          f"{len(probe.gaps_s)} ticks (median interval {1e3 * np.median(probe.gaps_s):.1f} ms)")
    assert latency < 0.5  # never frozen (the UI thread never waits on a device)


def test_closing_during_capture_leaves_a_resumable_session(qtbot, tmp_path):
    from polrig.app import capture, processing
    from polrig.app.session import Session

    w = make_window(qtbot, tmp_path / "gui.ini")
    out = tmp_path / "session"
    wait_connected(qtbot, w)
    w.capture.poses.setText("0:360:45")
    w.capture.out.setText(str(out))
    w.capture.start()
    qtbot.waitUntil(lambda: any(e.kind == "frame" for e in w.capture.events), timeout=30000)
    w.close()  # asks the capture to stop, closes when it has
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=30000)
    assert not w.capture.is_running and not w.live_worker.isRunning()
    session = Session.open(out)
    assert session.manifest["status"] == "interrupted"
    pending = session.next_pending()
    assert pending and session.verify() == []
    # resume with the core API, as `polrig capture --resume` does
    with build_rig(load_rig_config(None), SIM).open() as rig:
        plan = session.plan
        cal = processing.load_calibration(None, session=session)
        capture.check_resume_space(session, rig, len(pending))
        proc = processing.make_processor(plan, cal, processing.session_sensor_model(session))
        result = capture.run_session(rig, session, processor=proc)
    assert result.status == "complete"
    assert all(c["status"] == "complete" for c in Session.open(out).captures)
    assert Session.open(out).verify() == []


def test_stop_shortcut_stops_a_capture(qtbot, window, tmp_path):
    out = tmp_path / "session"
    wait_connected(qtbot, window)
    window.capture.poses.setText("0:360:60")
    window.capture.out.setText(str(out))
    window.capture.start()
    qtbot.waitUntil(lambda: any(e.kind == "frame" for e in window.capture.events),
                    timeout=30000)
    window.activateWindow()
    window.setFocus()
    qtbot.keyClick(window, Qt.Key.Key_Escape)
    if window.capture.is_running and not window.capture.worker.control.stop.is_set():
        window.stop_action.trigger()  # no focus on the offscreen platform: the same action
    qtbot.waitUntil(lambda: not window.capture.is_running, timeout=30000)
    assert json.loads((out / "session.json").read_text())["status"] == "interrupted"
    assert window.capture.last_status == "interrupted"
    # the operator's own stop is news, not an error
    stop_lines = [(lvl, t) for lvl, t in window.messages.messages if "stopped by the operator" in t]
    assert stop_lines and all(lvl == "info" for lvl, _ in stop_lines), stop_lines
    keys = {s.toString() for s in window.stop_action.shortcuts()}
    assert keys == {"Esc", "Ctrl+."}
    assert window.capture_action.shortcut().toString() == "Ctrl+R"
    # resume from the panel, pausing and continuing on the way
    done_before = sum(e.kind == "capture-done" for e in window.capture.events)
    window.capture.resume_button.click()
    qtbot.waitUntil(lambda: window.capture.is_running, timeout=10000)
    window.capture.pause_button.setChecked(True)
    assert window.capture.worker.control.pause.is_set()
    assert window.capture.eta.text() == "paused"
    window.capture.pause_button.setChecked(False)
    qtbot.waitUntil(lambda: window.capture.last_status == "complete", timeout=60000)
    manifest = json.loads((out / "session.json").read_text())
    assert manifest["status"] == "complete" and len(manifest["captures"]) == 6
    assert all(c["status"] == "complete" for c in manifest["captures"])
    assert any("resumed" == h["event"] for h in manifest["history"])
    assert done_before < 6


def test_settings_are_remembered(qtbot, tmp_path):
    ini = tmp_path / "gui.ini"
    w = make_window(qtbot, ini, start=False)
    w.live.set_display("dolp")
    w.capture.poses.setText("0:180:30")
    w.capture.frames.setValue(3)
    w.capture.mode.setCurrentText("single-shot")
    w.capture.mirror_average.setChecked(True)
    w.capture.out.setText(str(tmp_path / "x"))
    w.live.colour.setCurrentIndex(2)
    w.live.mirror_average.setChecked(True)
    w.capture.resolution.setCurrentText("full")
    w.capture.device.setCurrentText("cpu")
    w.capture.binning.setCurrentIndex(w.capture.binning.findData(2))
    w.live.resolution.setCurrentText("full")
    w.live.binning.setCurrentIndex(w.live.binning.findData(2))
    w.capture.target_sigma.setValue(0.03)
    w.capture.target_share.setValue(0.9)
    w.capture.max_states.setValue(6)
    w.capture.seen_state.setValue(2)
    w.capture.prior_scale.setCurrentText("calibrated")
    w.capture.exr_planes.setText("sigma,mask")
    w.capture.exr_uncertainty.setCurrentText("float")
    w.capture.exr_compression.setCurrentText("none")
    w.capture.operator.setText("A. Lab")
    w.capture.sample.setText("tile 7")
    w.live.min_snr.setValue(7.5)
    w.close()
    assert ini.is_file()
    w2 = make_window(qtbot, ini, start=False)
    c2 = w2.capture
    assert (c2.seen_state.value(), c2.prior_scale.currentText(), c2.exr_planes.text(),
            c2.exr_uncertainty.currentText(), c2.exr_compression.currentText()) \
        == (2, "calibrated", "sigma,mask", "float", "none")
    assert c2.operator.text() == "A. Lab" and c2.sample.text() == ""  # the sample is one capture's
    assert w2.live.min_snr.value() == 7.5 and w2.live_worker.settings.min_snr == 7.5
    assert (w2.capture.target_sigma.value(), w2.capture.target_share.value(), w2.capture.max_states.value()) \
        == (0.03, 0.9, 6)
    assert w2.live.display.currentData() == "dolp"
    assert w2.live_worker.settings.display == "dolp"
    assert w2.capture.poses.text() == "0:180:30" and w2.capture.frames.value() == 3
    assert w2.capture.mode.currentText() == "single-shot"
    assert w2.capture.mirror_average.isEnabled() and w2.capture.mirror_average.isChecked()
    assert w2.capture.request().mirror_average
    assert w2.capture.resolution.isEnabled() and w2.capture.request().resolution == "full"
    assert w2.capture.request().device == "cpu"
    assert w2.capture.binning.isEnabled() and w2.capture.request().network_binning == 2
    assert w2.capture.request().plan().network_binning == 2
    # the reference method runs no network: the combo is off and the request asks for 1
    w2.capture.mode.setCurrentText("reference")
    assert not w2.capture.binning.isEnabled() and w2.capture.request().network_binning == 1
    w2.capture.mode.setCurrentText("single-shot")
    assert w2.live_worker.settings.resolution == "full"
    assert w2.live_worker.settings.network_binning == 2
    assert w2.capture.out.text() == str(tmp_path / "x")
    assert w2.live.colour.currentIndex() == 2
    assert w2.live.mirror_average.isChecked() and w2.live_worker.settings.mirror_average
    w2.close()


def test_viewer_browses_a_session_and_exrs(qtbot, viewer_panel, tmp_path):
    from polrig.acquisition.plan import CapturePlan
    from polrig.app import capture, processing
    from polrig.app.manifest import SampleMetadata
    from polrig.formats.exr import write_stokes_exr

    out = tmp_path / "session"
    with build_rig(load_rig_config(None), SIM).open() as rig:
        plan = CapturePlan(poses_deg=(0.0,))
        cal = processing.load_calibration(None)
        md = SampleMetadata(sample="box", operator="ada", user={"lot": "7"})
        s = capture.create_session(out, rig, plan, calibration_id=cal.id, metadata=md)
        proc = processing.make_processor(plan, cal, processing.session_sensor_model(s))
        assert capture.run_session(rig, s, processor=proc).status == "complete"
        frame = rig.camera.grab()
    v = viewer_panel((900, 600))
    messages = []
    v.message.connect(lambda lvl, t: messages.append((lvl, t)))
    assert v.open_session(out)
    wait_loaded(qtbot, v)
    assert v.metadata.text() == "sample: box\noperator: ada\nlot: 7"  # the sample metadata
    labels = [v.entries.item(i).text() for i in range(v.entries.count())]
    assert any("mueller.exr" in t for t in labels) and any("truth_mueller" in t for t in labels)
    assert sum("raw" in t for t in labels) == 4
    assert v.display.currentData() == "mueller"
    grid = from_qimage(v.view.image())
    assert grid.shape[0] == 3 * 16 + 4 * pipeline.GRID_BORDER_PX and grid.std() > 0
    v._hovered(pipeline.GRID_BORDER_PX + 8, pipeline.GRID_BORDER_PX + 8)
    assert "Mueller at (u=8, v=8)" in v.readout.text()
    raw_row = next(i for i, t in enumerate(labels) if "raw" in t)
    v.entries.setCurrentRow(raw_row)
    wait_loaded(qtbot, v)
    assert v.data.raw is not None and "dolp" in v.data.available()
    v.display.setCurrentIndex(v.display.findData("aolp"))
    assert from_qimage(v.view.image()).shape == (16, 16, 3)
    stokes_path = tmp_path / "stokes.exr"
    write_stokes_exr(stokes_path, pipeline.process_frame(frame).stokes)
    assert open_and_wait(qtbot, v, stokes_path)
    assert v.data.mueller is None and v.data.stokes.shape == (3, 3, 16, 16)
    assert not open_and_wait(qtbot, v, tmp_path / "missing.exr")
    assert messages[-1][0] == "error" and "missing.exr" in messages[-1][1]


def _small_mueller_exr(path, value: float = 100.0):
    from polrig.formats.exr import write_mueller_exr

    m = np.zeros((1, 3, 3, 12, 16), np.float32)
    m[:, 0, 0] = value
    m[:, 1, 1] = 0.5 * value
    write_mueller_exr(path, m)
    return path


def _slow_reader(monkeypatch, delay_s: float = 1.0, slow: str = ""):
    """The viewer's EXR reader, ``delay_s`` slower (for files whose name contains ``slow``);
    returns the list of the threads it ran on."""
    import threading
    import time

    from polrig.gui import viewer

    real, threads = viewer.load_exr, []

    def slow_load(path, *a, **kw):
        threads.append(threading.current_thread())
        if slow in str(path):
            time.sleep(delay_s)
        return real(path, *a, **kw)
    monkeypatch.setattr(viewer, "load_exr", slow_load)
    return threads


def test_viewer_loads_a_file_off_the_ui_thread(qtbot, viewer_panel, tmp_path, monkeypatch):
    """Reading and rendering a full colour sensor's Mueller result takes seconds (2.2-2.7 s
    to read, 2.2 s to render at 1224x1024x3): done on the UI thread it froze the window. Here
    the read takes 1 s; the event loop must never wait for it, and the file is shown."""
    import threading


    threads = _slow_reader(monkeypatch)
    path = _small_mueller_exr(tmp_path / "m.exr")
    v = viewer_panel()
    probe = EventLoopProbe(10).start()
    started = v.open_file(path)
    qtbot.waitUntil(lambda: v.data is not None and not getattr(v, "loading", False), timeout=20000)
    probe.stop()
    assert started and v.path == path and v.view.image() is not None
    assert len(threads) == 1 and threads[0] is not threading.main_thread()
    assert probe.max_latency_s < 0.5, probe.max_latency_s
    assert v.display.currentData() == "mueller" and v.histogram.counts.size


def test_viewer_never_shows_a_load_that_a_newer_one_superseded(qtbot, viewer_panel, tmp_path, monkeypatch):
    """The operator opens B while A is still loading: A is dropped, B is shown."""

    threads = _slow_reader(monkeypatch, 1.0, slow="slow_a")
    a = _small_mueller_exr(tmp_path / "slow_a.exr", 100.0)
    b = _small_mueller_exr(tmp_path / "b.exr", 300.0)
    v = viewer_panel()
    shown, ends = [], []
    real_set_data = v.set_data
    v.set_data = lambda data: (shown.append(data.source), real_set_data(data))
    v.loaded.connect(ends.append)
    assert v.open_file(a)
    qtbot.waitUntil(lambda: len(threads) == 1, timeout=10000)  # A is being read
    assert v.open_file(b) and v.loading
    qtbot.waitUntil(lambda: not v.loading, timeout=20000)
    qtbot.wait(1200)  # A's read has ended meanwhile at the latest
    assert shown == [str(b)] and ends == [True] and v.path == b
    assert float(np.nanmax(v.data.mueller[:, 0, 0])) == 300.0


def test_closing_the_window_while_a_file_loads_shuts_down_cleanly(qtbot, tmp_path, monkeypatch):
    _slow_reader(monkeypatch, 1.5)
    w = make_window(qtbot, tmp_path / "gui.ini")
    wait_connected(qtbot, w)
    assert w.viewer.open_file(_small_mueller_exr(tmp_path / "m.exr"))
    assert w.viewer.loading
    close_window(qtbot, w)
    for pool in (w.viewer._loader, w.viewer.roi._worker, w.live.roi._worker):  # all ended
        assert not any(t.is_alive() for t in pool._threads)
    qtbot.wait(100)
    assert w.viewer.data is None and not w.viewer.loading  # never shown once closed
    assert not w.viewer.open_file(tmp_path / "m.exr")  # nothing starts after the shutdown


def test_viewer_roi_statistics_are_computed_off_the_ui_thread(qtbot, viewer_panel, tmp_path, monkeypatch):
    """A region's statistics take seconds at the full sensor (1.8 s for an ellipse, 5-6 s for
    a large rectangle on a 1224x1024x3 result): here 1 s each; the window never waits."""
    import threading
    import time

    from polrig.app import roi
    from polrig.gui import pipeline as pl

    real, threads = pl.roi_statistics, []

    def slow_statistics(*a, **kw):
        threads.append(threading.current_thread())
        time.sleep(1.0)
        return real(*a, **kw)
    monkeypatch.setattr(pl, "roi_statistics", slow_statistics)
    v = viewer_panel()
    v.set_data(pipeline.PolarizationData.from_mueller(
        np.full((1, 3, 3, 12, 16), 10.0, np.float32), "x"))
    probe = EventLoopProbe(10).start()
    v.roi.set_region(roi.RectROI(2.0, 2.0, 8.0, 6.0))
    qtbot.waitUntil(lambda: bool(v.roi.rows), timeout=20000)
    probe.stop()
    assert threads and threading.main_thread() not in threads
    assert probe.max_latency_s < 0.5, probe.max_latency_s
    assert v.roi.rows[0].n_counted == 48 and "48 counted" in v.roi.summary.text()


#: A Mueller result larger than the viewer redraws at once (viewer.SYNC_REDRAW_MAX_PX, 128x128)
LARGE_HW = (136, 144)


def _slow_render(monkeypatch, delay_s: float = 1.0):
    """pipeline.render, ``delay_s`` slower; returns the list of ``(thread, display, colour,
    options, min_snr)`` of its calls."""
    import threading
    import time

    real, calls = pipeline.render, []

    def slow_render(data, display, colour=pipeline.LUMINANCE, **kw):
        calls.append((threading.current_thread(), display, colour, kw.get("options"),
                      data.min_snr))
        time.sleep(delay_s)
        return real(data, display, colour, **kw)
    monkeypatch.setattr(pipeline, "render", slow_render)
    return calls


def _large_viewer(qtbot, tmp_path, v, display: str = "polarizer"):
    """Viewer ``v`` (shown) made to show a LARGE_HW Mueller result with ``display``, waited
    for."""
    from polrig.formats.exr import write_mueller_exr

    h, w = LARGE_HW
    m = np.zeros((1, 3, 3, h, w), np.float32)
    m[:, 0, 0] = np.linspace(50.0, 400.0, h * w, dtype=np.float32).reshape(h, w)
    m[:, 0, 1] = 0.4 * m[:, 0, 0]
    m[:, 1, 0] = 0.3 * m[:, 0, 0]
    m[:, 1, 1] = 0.5 * m[:, 0, 0]
    path = write_mueller_exr(tmp_path / "large.exr", m)
    assert open_and_wait(qtbot, v, path)
    v.display.setCurrentIndex(v.display.findData(display))
    qtbot.waitUntil(lambda: not getattr(v, "drawing", False), timeout=20000)
    return v


def _record_shown(v) -> list:
    shown, real = [], v.view.set_image
    v.view.set_image = lambda img: (shown.append(img), real(img))
    return shown


def test_viewer_redraws_a_large_image_off_the_ui_thread_latest_wins(qtbot, viewer_panel, tmp_path,
                                                                   monkeypatch):
    """Redrawing a full colour sensor's 3x3 Mueller grid after a change of the display took
    1.1-1.5 s on the UI thread, a dragged slider froze the window for seconds. Here each
    redraw takes 1 s more; four quick changes: the event loop never waits for them, at most
    two redraws run (the one in progress, then one with the newest settings) and only the
    newest settings' image is shown."""
    import threading

    from polrig.gui import viewer as viewer_module
    from polrig.gui.qtimage import to_qimage

    assert LARGE_HW[0] * LARGE_HW[1] > getattr(viewer_module, "SYNC_REDRAW_MAX_PX", 0)
    v = _large_viewer(qtbot, tmp_path, viewer_panel())
    real_render = pipeline.render
    calls = _slow_render(monkeypatch)
    shown = _record_shown(v)
    drawn = []
    if hasattr(v, "drawn"):
        v.drawn.connect(lambda: drawn.append(1))
    probe = EventLoopProbe(10).start()
    v.incident.setValue(10)
    qtbot.wait(50)
    v.incident.setValue(20)
    qtbot.wait(50)
    v.min_snr.setValue(5.0)
    qtbot.wait(50)
    v.incident.setValue(40)
    assert v.incident_label.text().strip() == "40 deg"  # the controls answer at once
    qtbot.waitUntil(lambda: bool(shown) and not getattr(v, "drawing", False), timeout=20000)
    qtbot.wait(300)
    probe.stop()
    assert probe.max_latency_s < 0.5, probe.max_latency_s
    assert 1 <= len(calls) <= 2, [c[1:] for c in calls]
    assert threading.main_thread() not in [c[0] for c in calls]
    assert calls[-1][3].incident_deg == 40.0 and calls[-1][4] == 5.0  # the newest settings
    v.data.min_snr = 5.0
    want = real_render(v.data, "polarizer", pipeline.LUMINANCE, saturation_overlay=True,
                       options=v.options())
    assert len(shown) == 1 and len(drawn) == 1  # the superseded redraw is never shown
    np.testing.assert_array_equal(from_qimage(shown[0]), from_qimage(to_qimage(want)))
    assert v.view.image() is shown[0] and v.view.banner == ""


def test_viewer_redraws_a_small_image_at_once(qtbot, viewer_panel, tmp_path, monkeypatch):
    """A small image (the tests' files, a 256x256 sensor's result) is redrawn on the UI
    thread when the setting changes: it takes milliseconds."""
    import threading


    v = viewer_panel()
    assert open_and_wait(qtbot, v, _small_mueller_exr(tmp_path / "m.exr"))
    calls = _slow_render(monkeypatch, 0.0)
    v.display.setCurrentIndex(v.display.findData("polarizer"))
    assert not v.drawing and [c[0] for c in calls] == [threading.main_thread()]
    v.incident.setValue(30)
    assert not v.drawing and len(calls) == 2 and calls[-1][3].incident_deg == 30.0


def test_a_change_while_a_file_loads_draws_the_file_not_the_earlier_one(qtbot, viewer_panel, tmp_path,
                                                                        monkeypatch):
    """The operator opens another file, then moves a slider while it loads: the file still
    shown is not redrawn (the new one comes with the newest settings); here the new file cannot
    be read, the view is cleared, and nothing of the earlier file comes back."""
    v = _large_viewer(qtbot, tmp_path, viewer_panel())
    threads = _slow_reader(monkeypatch, 1.0, slow="missing")
    calls = _slow_render(monkeypatch, 0.2)
    shown = _record_shown(v)
    assert v.open_file(tmp_path / "missing.exr")
    qtbot.waitUntil(lambda: len(threads) == 1, timeout=10000)  # being read
    v.incident.setValue(30)
    assert v.loading and not v.drawing
    qtbot.waitUntil(lambda: not v.loading and not v.drawing, timeout=20000)
    qtbot.wait(500)
    assert v.data is None and [img for img in shown if img is not None] == [] and not calls


def test_a_file_loaded_while_the_settings_change_is_shown_with_the_newest(qtbot, viewer_panel, tmp_path,
                                                                          monkeypatch):
    import shutil

    from polrig.gui.qtimage import to_qimage

    v = _large_viewer(qtbot, tmp_path, viewer_panel())
    second = shutil.copy(tmp_path / "large.exr", tmp_path / "slow_second.exr")
    threads = _slow_reader(monkeypatch, 1.0, slow="slow_second")
    assert v.open_file(second)
    qtbot.waitUntil(lambda: len(threads) == 1, timeout=10000)  # being read
    v.incident.setValue(50)
    v.analyzer.setValue(10)
    qtbot.waitUntil(lambda: not v.loading and not v.drawing, timeout=20000)
    assert str(v.path) == str(second) and v.data.source == str(second)
    want = pipeline.render(v.data, "polarizer", pipeline.LUMINANCE, saturation_overlay=True,
                           options=v.options())
    assert v.options().incident_deg == 50.0 and v.options().analyzer_deg == 10.0
    np.testing.assert_array_equal(from_qimage(v.view.image()), from_qimage(to_qimage(want)))


def test_closing_the_window_while_a_redraw_runs_shuts_down_cleanly(qtbot, tmp_path, monkeypatch):
    w = make_window(qtbot, tmp_path / "gui.ini")
    wait_connected(qtbot, w)
    v = _large_viewer(qtbot, tmp_path, w.viewer)
    calls = _slow_render(monkeypatch, 1.5)
    shown = _record_shown(v)
    v.incident.setValue(30)
    redraws = lambda: [c for c in calls if c[1] == "polarizer"]  # not the live view's  # noqa: E731
    qtbot.waitUntil(lambda: bool(redraws()), timeout=10000)  # the redraw runs
    assert v.drawing
    close_window(qtbot, w)
    for pool in (v._loader, v.roi._worker, w.live.roi._worker):  # all ended
        assert not any(t.is_alive() for t in pool._threads)
    qtbot.wait(100)
    assert shown == [] and not v.drawing  # never shown once closed
    assert len(redraws()) == 1


def test_calibration_step_out_of_order_is_a_readable_failure(qtbot, window, tmp_path):
    # the devices open on their own thread: a step started before they are open fails on the
    # camera (DeviceDisconnected), not on the missing intrinsics this test is about
    wait_connected(qtbot, window)
    cal = window.calibration
    cal.run_selected()
    assert "choose a calibration set folder" in window.messages.messages[-1][1]
    cal.folder.setText(str(tmp_path / "cal"))
    cal.steps.setCurrentRow(2)  # light position needs the intrinsics first
    cal.run_selected()
    qtbot.waitUntil(lambda: not cal.is_running, timeout=20000)
    assert "run 'polrig calibrate intrinsics'" in cal.report_view.toPlainText()
    assert any("calibration step light failed" in t for _, t in window.messages.messages)
    wait_frames(qtbot, window, 2)  # live view resumed


def test_polrig_gui_command(qtbot, tmp_path, capsys):
    from PySide6.QtWidgets import QApplication

    from polrig.cli import main

    assert main(["gui", "--config", str(tmp_path / "missing.toml")]) == 2
    assert main(["gui", "--sim-size", "big"]) == 2
    assert "size must be" in capsys.readouterr().err
    seen = {}

    def close_when_live():
        wins = [w for w in QApplication.topLevelWidgets()
                if isinstance(w, MainWindow) and w.isVisible()]  # not another test's
        if wins and wins[0].live.frames_shown >= 3:
            seen["frames"] = wins[0].live.frames_shown
            wins[0].close()
        else:
            QTimer.singleShot(50, close_when_live)

    QTimer.singleShot(50, close_when_live)
    ini = tmp_path / "gui.ini"
    assert main(["gui", "--sim-size", "64x64", "--sim-clock-speed", "1000",
                 "--settings", str(ini)]) == 0
    assert seen["frames"] >= 3 and ini.is_file()


def test_qt_binding_check():
    from polrig.errors import ConfigError
    from polrig.gui.app import check_qt_binding

    check_qt_binding("6.11.3", (3, 11))
    check_qt_binding("6.12.0", (3, 12))
    with pytest.raises(ConfigError, match="PySide6 6.12.0"):
        check_qt_binding("6.12.0", (3, 11))


def test_the_window_fits_a_1080p_screen_and_tall_panels_scroll(qtbot, tmp_path):
    """Every panel sits in a scroll area: the window's least size is what the tab bar, menus
    and the messages need, not the tallest panel's (the capture panel alone is about 1000 px),
    so the default 1280x860 window fits a 1920x1080 screen; each panel is brought to the front
    by its page, and one taller than the room scrolls."""
    w = make_window(qtbot, tmp_path / "s.ini", start=False)
    try:
        least = w.minimumSizeHint()
        assert least.width() <= 1280 and least.height() <= 860, least
        assert w.height() <= 1080
        for panel in (w.live, w.devices, w.capture, w.calibration, w.viewer):
            w.show_panel(panel)
            assert w.tabs.currentWidget() is w.pages[panel] and w.pages[panel].widget() is panel
        for panel in (w.live, w.viewer):  # an image beside its controls: the image scales, the controls scroll
            assert panel.minimumSizeHint().height() < 400, panel
        w.show_panel(w.capture)
        w.resize(1280, 700)
        qtbot.waitUntil(lambda: w.pages[w.capture].verticalScrollBar().maximum() > 0, timeout=5000)
    finally:
        close_window(qtbot, w)
