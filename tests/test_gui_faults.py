"""The operator GUI when things go wrong (pytest-qt, offscreen, simulated rig): errors after a
capture started, driver bugs in the status poll and the live view, manual moves (Stop, readouts,
long moves, closing during one), SIGTERM/SIGINT, calibration Cancel, bad settings files, a
capture started during a calibration, long exposures, the capture panel's messages and stale
displays. Helpers and the ``window`` fixture are tests/test_gui.py's."""

from __future__ import annotations

import errno
import json
import os
import signal
import threading
import time

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QEvent, Qt, QTimer  # noqa: E402
from test_gui import close_window, make_window, wait_connected, wait_frames, window  # noqa: E402,F401

pytestmark = [pytest.mark.gui, pytest.mark.timeout(120)]


def messages(w, level: str | None = None) -> list[str]:
    return [t for lvl, t in w.messages.messages if level is None or lvl == level]


def run_capture(qtbot, w, out, poses: str = "0,90", timeout: int = 60000, **fields) -> None:
    cp = w.capture
    cp.poses.setText(poses)
    cp.out.setText(str(out))
    for name, value in fields.items():
        getattr(cp, name).setText(value)
    cp.start()
    qtbot.waitUntil(lambda: not cp.is_running and cp.last_status != "running", timeout=timeout)


# -- 1. an error after the session exists is a stop, reported as polrig capture reports it
@pytest.mark.parametrize("error", ["file-system", "processing"])
def test_error_after_the_session_exists_is_a_resumable_stop(qtbot, window, tmp_path,
                                                            monkeypatch, error):
    import polrig.app.processing
    import polrig.app.session

    out = tmp_path / "session"
    if error == "file-system":  # not a full disk: an I/O error writing capture 2's first file
        real = polrig.app.session.atomic_write_bytes

        def write(path, data):
            if "c001_" in str(path):
                raise OSError(errno.EIO, "Input/output error", str(path))
            real(path, data)
        monkeypatch.setattr(polrig.app.session, "atomic_write_bytes", write)
    else:  # a processing bug in capture 2
        real_process = polrig.app.processing.Processor.process

        def process(self, session, index):
            if index == 1:
                raise RuntimeError("processing bug")
            return real_process(self, session, index)
        monkeypatch.setattr(polrig.app.processing.Processor, "process", process)
    wait_connected(qtbot, window)
    run_capture(qtbot, window, out, "0,90,180")
    cp = window.capture
    assert cp.last_status == "interrupted", cp.eta.text()
    assert "not started" not in cp.eta.text() and "resume to continue" in cp.eta.text()
    err = messages(window, "error")[-1]
    assert err.startswith("capture stopped: ")
    assert ("Input/output error" if error == "file-system" else "RuntimeError: processing bug") in err
    assert "completed captures are intact" in err and "Resume session in folder" in err
    m = json.loads((out / "session.json").read_text())
    assert m["status"] == "interrupted"
    statuses = [c["status"] for c in m["captures"]]
    if error == "file-system":
        assert statuses == ["complete", "failed", "pending"]
    else:  # processing overlaps acquisition: capture 2 keeps its raw frames ("acquired",
        # processed on resume without acquiring it again); capture 3 was being acquired when
        # the error was seen (pending) or was acquired already
        assert statuses[:2] == ["complete", "acquired"] and statuses[2] in ("pending", "acquired")
        assert "RuntimeError: processing bug" in m["captures"][1]["reason"]
    monkeypatch.undo()
    cp.resume()  # the lock was released: the same window resumes it
    qtbot.waitUntil(lambda: cp.last_status == "complete", timeout=60000)
    assert cp.eta.text() == "session complete (3 captures)"  # (11) the whole session, not this run


# -- 2. a driver bug (an exception outside polrig's types) never ends a worker
def test_driver_bug_in_status_poll_and_live_grab_is_a_message(qtbot, window):
    wait_connected(qtbot, window)
    wait_frames(qtbot, window, 3)
    rig = window.rig
    real_status, real_grab = rig.light.status, rig.camera.grab
    calls = {"status": 0, "grab": 0}

    def status():
        calls["status"] += 1
        if calls["status"] == 1:
            raise RuntimeError("driver bug in light.status")
        return real_status()

    def grab(*a, **kw):
        calls["grab"] += 1
        if calls["grab"] == 1:
            raise RuntimeError("driver bug in grab")
        return real_grab(*a, **kw)

    rig.light.status = status
    qtbot.waitUntil(lambda: calls["status"] >= 2, timeout=10000)  # polled again: alive
    assert window.devices.worker.isRunning()
    assert any("RuntimeError: driver bug in light.status" in t for t in messages(window, "error"))
    window.devices.move("stage", 10.0)
    qtbot.waitUntil(lambda: "move stage to 10 deg: done" in messages(window), timeout=10000)
    rig.camera.grab = grab
    qtbot.waitUntil(lambda: calls["grab"] >= 1, timeout=10000)
    wait_frames(qtbot, window, 3)  # the grab thread lives on
    assert any("live view: RuntimeError: driver bug in grab" in t
               for t in messages(window, "error"))
    assert window.live_worker.isRunning()


# -- 3. manual moves: Stop at once, readouts during the motion, long moves
def test_stop_interrupts_a_manual_move_and_readouts_follow_it(qtbot, tmp_path):
    """Stop ends a manual move at once, not at its end (the move lasts 14 s, Stop must be
    done within 5 s); a light setting runs during the motion (the axis is still busy when
    it is done); the readouts follow the axis."""
    w = make_window(qtbot, tmp_path / "gui.ini", clock_speed=5.0)  # turntable 50 deg/s
    try:
        wait_connected(qtbot, w)
        d = w.devices
        qtbot.waitUntil(lambda: "position_deg" in d.last_status.get("turntable", {}),
                        timeout=10000)
        d.turntable.target.setValue(700.0)
        d.turntable.move.click()  # ~14 s
        qtbot.waitUntil(lambda: d.turntable.state.text() == "moving"
                        and 20.0 < float(d.turntable.position.text().split()[0]) < 600.0,
                        timeout=5000)
        d.light_level.setValue(0.5)  # runs during the motion, not after it
        qtbot.waitUntil(lambda: "light level 0.5: done" in messages(w), timeout=5000)
        assert w.rig.turntable.is_busy()
        t0 = time.monotonic()
        d.turntable.stop.click()
        qtbot.waitUntil(lambda: "stop turntable: done" in messages(w), timeout=5000)
        assert time.monotonic() - t0 < 5.0
        assert not w.rig.turntable.is_busy()
        stopped = w.rig.turntable.position_deg()
        assert 20.0 < stopped < 690.0
        assert "move turntable to 700 deg: ended by stop turntable" in messages(w, "warning")
        qtbot.waitUntil(lambda: d.turntable.state.text() == "open"
                        and abs(float(d.turntable.position.text().split()[0]) - stopped) < 1e-3,
                        timeout=3000)
    finally:
        close_window(qtbot, w)


def test_a_long_move_gets_a_timeout_that_fits_it(qtbot, window):
    wait_connected(qtbot, window)
    window.devices.move("turntable", 720.0)  # 72 s at 10 deg/s: beyond the HAL's 30 s
    qtbot.waitUntil(lambda: "move turntable to 720 deg: done" in messages(window), timeout=15000)
    assert not any("did not end" in t for t in messages(window, "error"))
    assert window.rig.turntable.position_deg() == pytest.approx(720.0)
    from polrig.acquisition.hal import motion_timeout_s

    # 1.5 times the trapezoidal profile at the axis's declared speed and acceleration
    assert motion_timeout_s(window.rig.turntable, 720.0) == pytest.approx(
        30.0 + 1.5 * _profile_s(720.0, window.rig.turntable.capabilities))
    assert motion_timeout_s(window.rig.stage, -10.0) == pytest.approx(
        30.0 + 1.5 * _profile_s(10.0, window.rig.stage.capabilities))


def _profile_s(distance_deg: float, caps) -> float:
    """Duration of a trapezoidal move (triangular when too short to reach full speed)."""
    v, a = caps.speed_deg_s, caps.accel_deg_s2
    if distance_deg > v * v / a:
        return distance_deg / v + v / a
    return 2.0 * (distance_deg / a) ** 0.5


# -- 4. SIGTERM and SIGINT close the GUI like its close button, with polrig's exit codes
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_polrig_gui_exits_on_sigterm_and_sigint(qtbot, tmp_path, capsys, signum):
    from PySide6.QtWidgets import QApplication

    from polrig.cli import main
    from polrig.gui.main_window import MainWindow

    out = tmp_path / "session"
    seen = {"t0": time.monotonic()}

    def step():
        if "done" in seen:
            return
        QTimer.singleShot(20, step)  # first: a signal raised in here must not end the checks
        wins = [w for w in QApplication.topLevelWidgets()
                if isinstance(w, MainWindow) and w.isVisible()]
        if not wins:
            return
        w = wins[0]
        if time.monotonic() - seen["t0"] > 30:  # the signal was ignored: end the test
            w.capture.stop()
            w.close()
        elif "killed" not in seen and signum == signal.SIGINT and w.live.frames_shown >= 2:
            seen["killed"] = True
            os.kill(os.getpid(), signum)
        elif "started" not in seen and signum == signal.SIGTERM and all(
                d.is_open for d in w.rig.devices.values()):
            seen["started"] = True
            w.capture.poses.setText("0:360:30")
            w.capture.out.setText(str(out))
            w.capture.start()
        elif "killed" not in seen and any(e.kind == "frame" for e in w.capture.events):
            seen["killed"] = True
            seen["window"] = w
            os.kill(os.getpid(), signum)  # during the capture

    QTimer.singleShot(20, step)
    rc = main(["gui", "--sim-size", "64x64", "--sim-clock-speed", "1000", "--settings",
               str(tmp_path / "gui.ini")])
    seen["done"] = True
    stale = [w for w in QApplication.topLevelWidgets() if isinstance(w, MainWindow)
             and not w.isVisible()]
    err = capsys.readouterr().err
    assert rc == 128 + signum, err
    assert signal.getsignal(signal.SIGINT) is not None
    if signum == signal.SIGTERM:
        assert "polrig: terminated (SIGTERM)" in err
        m = json.loads((out / "session.json").read_text())
        assert m["status"] == "interrupted" and "pending" in [c["status"] for c in m["captures"]]
        assert seen["window"].capture.last_status == "interrupted"
    else:
        assert "polrig: interrupted" in err
    assert (tmp_path / "gui.ini").is_file()  # closed as the close button closes it
    for w in stale:  # polrig gui's window: gone, as when the process ends
        w.deleteLater()
    QApplication.sendPostedEvents(None, QEvent.Type.DeferredDelete)


# -- 5. calibration Cancel
def test_calibration_cancel_stops_at_the_next_device_call_and_saves_nothing(qtbot, window,
                                                                           tmp_path):
    wait_connected(qtbot, window)
    cal = window.calibration
    folder = tmp_path / "cal"
    cal.folder.setText(str(folder))
    cal.steps.setCurrentRow(0)
    real_grab = window.rig.camera.grab
    grabs = {"n": 0, "after_cancel": 0}

    def grab(*a, **kw):  # the operator presses Cancel while the first frame is taken
        if window.locks.owner.get("camera") != "calibration":
            return real_grab(*a, **kw)  # the live view's
        grabs["n"] += 1
        if cal.worker.cancelled.is_set():
            grabs["after_cancel"] += 1
        elif grabs["n"] == 1:
            cal.worker.cancelled.set()
        return real_grab(*a, **kw)

    window.rig.camera.grab = grab
    cal.run_selected()
    qtbot.waitUntil(lambda: not cal.is_running, timeout=30000)
    window.rig.camera.grab = real_grab
    assert grabs == {"n": 1, "after_cancel": 0}
    assert "CANCELLED: nothing was saved" in cal.report_view.toPlainText()
    assert "calibration step intrinsics cancelled; nothing saved" in messages(window, "warning")[-1]
    assert not (folder / "calibration.json").exists()
    qtbot.waitUntil(lambda: not window.live_worker.paused, timeout=10000)
    # the cancel button during a step whose log line comes first: stops there
    cal.run_selected()
    cal.worker.log.connect(lambda _t: cal.worker.cancelled.set(), Qt.ConnectionType.DirectConnection)
    qtbot.waitUntil(lambda: not cal.is_running, timeout=30000)
    assert "CANCELLED" in cal.report_view.toPlainText()
    assert not (folder / "calibration.json").exists()


# -- 6, 7. settings files edited by hand, or that cannot be written
def test_bad_settings_values_are_skipped_and_lists_joined(qtbot, tmp_path, capsys):
    ini = tmp_path / "s.ini"
    ini.write_text("[capture]\nframes=99999999999\nposes=0,90,180\nstates=@Invalid()\n"
                   "exposure=1000,2000\nmode=superfast\ntarget_sigma=nan\ntarget_share=2\n"
                   "[live]\nsaturation_overlay=maybe\n")
    w = make_window(qtbot, ini, start=False)
    cp = w.capture
    assert cp.frames.value() == 1 and cp.mode.currentText() == "reference"
    assert cp.poses.text() == "0,90,180" and cp.exposure.text() == "1000,2000"
    assert cp.states.text() == "" and w.live.overlay.isChecked()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("polrig: warning: settings ")
    assert cp.target_sigma.value() == 0.0 and cp.target_share.value() == 0.95  # the defaults kept
    for key in ("capture/frames", "capture/states", "capture/mode", "capture/target_sigma",
                "capture/target_share", "live/saturation_overlay"):
        assert key in err[0]
    assert "capture/poses" not in err[0]
    assert any("skipped invalid values" in t for t in messages(w, "warning"))
    w.close()
    saved = ini.read_text().splitlines()
    assert 'poses="0,90,180"' in saved and "frames=1" in saved  # as the widgets show them


def test_settings_that_cannot_be_written_are_reported(qtbot, tmp_path, capsys):
    (tmp_path / "a_file").write_text("x")
    ini = tmp_path / "a_file" / "gui.ini"  # its folder is a file: cannot be created
    w = make_window(qtbot, ini, start=False)
    w.capture.poses.setText("0,1")
    w.close()
    err = capsys.readouterr().err
    assert f"polrig: warning: settings could not be saved to {ini}" in err
    assert err.count("could not be saved") == 1


# -- 8. closing during a manual move
def test_closing_during_a_manual_move_stops_the_axis_and_closes_at_once(qtbot, tmp_path):
    """Closing the window during a 14 s move stops the axis and closes within 5 s, without
    waiting for the move's end."""
    w = make_window(qtbot, tmp_path / "gui.ini", clock_speed=5.0)  # 720 deg: ~14 s
    wait_connected(qtbot, w)
    w.devices.move("turntable", 720.0)
    qtbot.waitUntil(lambda: w.rig.turntable.is_busy(), timeout=5000)
    t0 = time.monotonic()
    w.close()
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=10000)
    assert time.monotonic() - t0 < 5.0
    assert not w.devices.worker.isRunning() and not w.live_worker.isRunning()
    # the motion was stopped before the rig closed: the axis's last move is the standstill
    # stop() leaves, short of the target
    move = w.rig.camera.world.turntable_move
    assert move.start_deg == move.target_deg < 720.0


# -- 9. a capture cannot start while a calibration step runs
def test_capture_refused_at_once_while_a_calibration_step_runs(qtbot, window, tmp_path,
                                                               monkeypatch):
    from polrig.calibration import runner

    release = threading.Event()

    def slow_steps(steps, rig, mount, cs, **kw):
        kw["log"]("step running")
        release.wait(20)
        return cs
    monkeypatch.setattr(runner, "run_steps", slow_steps)
    wait_connected(qtbot, window)
    cal = window.calibration
    cal.folder.setText(str(tmp_path / "cal"))
    cal.run_selected()
    qtbot.waitUntil(lambda: "step running" in cal.log_view.toPlainText(), timeout=10000)
    try:
        assert not window.capture_action.isEnabled()
        window.capture.poses.setText("0")
        window.capture.out.setText(str(tmp_path / "s"))
        window.capture_action.trigger()  # Ctrl+R
        window.capture.start()  # and the panel itself
        assert not window.capture.is_running
        assert "capture: cannot start while a calibration step runs" in messages(window, "error")
        assert cal.isEnabled() and cal.cancel_button.isEnabled()
        assert not (tmp_path / "s").exists()
    finally:
        release.set()
    qtbot.waitUntil(lambda: not cal.is_running, timeout=20000)
    assert window.capture_action.isEnabled() and window.capture.blocked_by == ""


# -- 10. grab timeouts follow the exposure
def test_grab_timeout_follows_the_exposure():
    from polrig.acquisition import hal
    from polrig.app.rig import open_rig

    with open_rig(None, size=(32, 24)) as rig:
        cam = rig.camera
        cam.set_exposure_us(5e6)
        readout_s = cam.capabilities.readout_us * 1e-6  # as the camera declares it
        assert readout_s > 0
        assert hal.grab_timeout_s(cam) == pytest.approx(hal.DEFAULT_TIMEOUT_S + 5.0 + readout_s)
        assert hal.grab_timeout_s(cam, 2.0) == pytest.approx(7.0 + readout_s)

    class CannotSay:  # a camera that cannot report its exposure, declaring its readout
        exposure_us = float("nan")
        capabilities = hal.CameraCapabilities(readout_us=20_000.0)
    assert hal.grab_timeout_s(CannotSay(), 2.0) == pytest.approx(2.02)


def test_a_long_exposure_reaches_the_live_view(qtbot, window):
    wait_frames(qtbot, window, 2)
    window.live.exposure.setValue(3_000_000.0)  # 3 s (simulated): beyond the old 2 s timeout
    qtbot.waitUntil(lambda: window.live.last.exposure_us == 3_000_000.0, timeout=15000)
    assert not any("no frame within" in t for t in messages(window, "error"))


def test_a_capture_at_the_longest_exposure_completes(qtbot, window, tmp_path):
    """The camera's longest exposure (10 s + readout: beyond the HAL's 10 s grab timeout),
    accepted by the plan's validation, is acquired (it used to time out on every grab)."""
    wait_connected(qtbot, window)
    out = tmp_path / "session"
    run_capture(qtbot, window, out, "0", exposure="10000000")
    assert window.capture.last_status == "complete", window.capture.eta.text()
    assert json.loads((out / "session.json").read_text())["status"] == "complete"


# -- 11. capture panel messages
def test_a_non_finite_exposure_is_not_called_an_angle():
    from polrig.acquisition.plan import parse_float_list, parse_pose_spec
    from polrig.errors import ConfigError

    with pytest.raises(ConfigError, match=r"invalid --exposure 'nan': 'nan' is not a finite number$"):
        parse_float_list("nan", "--exposure", positive=True)
    with pytest.raises(ConfigError, match=r"'inf' is not a finite angle$"):
        parse_pose_spec("0,inf")


def test_capture_panel_messages(qtbot, window, tmp_path):
    from polrig.app.capture import Progress

    cp = window.capture
    run_capture(qtbot, window, tmp_path / "bad", "0:10:0")  # refused: nothing "started"
    assert cp.last_status == "failed"
    assert not any(t.startswith("capture started") for t in messages(window))
    wait_connected(qtbot, window)
    out = tmp_path / "session"
    cp.poses.setText("0:360:45")
    cp.out.setText(str(out))
    cp.start()
    qtbot.waitUntil(lambda: any(e.kind == "frame" for e in cp.events), timeout=30000)
    assert f"capture started in {out}" in messages(window)
    cp.pause_button.setChecked(True)
    assert cp.eta.text() == "paused"
    ev = cp.events[-1]  # a frame event that was on its way when Pause was pressed
    cp._progress(Progress("frame", 0, ev.n_captures, ev.step + 1, ev.total, 0.0))
    assert cp.eta.text() == "paused"
    cp.pause_button.setChecked(False)
    qtbot.waitUntil(lambda: any(e.kind == "capture-done" for e in cp.events), timeout=30000)
    cp.stop()
    qtbot.waitUntil(lambda: not cp.is_running, timeout=30000)
    assert json.loads((out / "session.json").read_text())["captures"][0]["status"] == "complete"
    cp.resume()
    qtbot.waitUntil(lambda: cp.last_status == "complete", timeout=60000)
    assert f"capture resumed in {out}" in messages(window)
    assert cp.eta.text() == "session complete (8 captures)"


# -- 12. stale displays
def test_live_status_says_when_frames_stop(qtbot, window):
    wait_connected(qtbot, window)
    wait_frames(qtbot, window, 3)
    assert window.fps_label.text().startswith("live ")
    window.rig.faults.inject_fault("camera", "disconnect", after_calls=0)
    qtbot.waitUntil(lambda: window.fps_label.text().startswith("live: no frames"),
                    timeout=10000)
    qtbot.waitUntil(lambda: "camera not connected" in window.fps_label.text(), timeout=10000)
    window.devices.connect_device("camera")
    qtbot.waitUntil(lambda: window.fps_label.text().startswith("live "), timeout=10000)


def test_viewer_clears_the_previous_image_when_a_file_cannot_be_read(qtbot, viewer_panel, tmp_path):
    from polrig.formats.exr import write_mueller_exr
    from test_gui import open_and_wait

    good = tmp_path / "good.exr"
    write_mueller_exr(good, np.ones((3, 3, 3, 8, 8), np.float32))
    bad = tmp_path / "bad.exr"
    bad.write_bytes(good.read_bytes()[:200])
    v = viewer_panel((800, 500))
    assert open_and_wait(qtbot, v, good)
    v._hovered(2, 2)
    assert v.view.image() is not None and v.readout.text() and v.histogram.counts.size
    assert not open_and_wait(qtbot, v, bad)
    assert v.view.image() is None and v.data is None and v.path is None
    assert v.readout.text() == "" and v.histogram.counts.size == 0
    assert "bad.exr" in v.view.placeholder


# -- 13. a limit switch during a capture: stopped, shown with what to do in this window
def test_a_limit_switch_during_a_capture_stops_it_and_says_how_to_home_here(qtbot, window,
                                                                           tmp_path):
    """The turntable's limit switch fires during capture 2 (the simulated rig's injected
    safety fault): the capture stops with the session resumable, nothing homes or moves the
    axis on its own, and the operator is told to home it in this window (the Devices tab):
    ``polrig home turntable``, the command line's advice, cannot reach devices this window
    holds (a real serial port is opened exclusively). Homing from the Devices tab, then
    "Resume session in folder", completes the session."""
    from PySide6.QtCore import Qt

    wait_connected(qtbot, window)
    cp, rig = window.capture, window.rig
    calls = {"home": 0, "move_to": 0}
    real_home, real_move = rig.turntable.home, rig.turntable.move_to
    alarm = threading.Event()

    def home(*a, **kw):
        calls["home"] += alarm.is_set()
        return real_home(*a, **kw)

    def move_to(*a, **kw):
        calls["move_to"] += alarm.is_set()
        return real_move(*a, **kw)
    rig.turntable.home, rig.turntable.move_to = home, move_to

    def on_frame(ev):  # in the capture's thread, before its next step
        if ev.kind == "frame" and ev.capture_index == 1 and not alarm.is_set():
            rig.faults.inject_fault("turntable", "limit", after_calls=0)
            alarm.set()

    def watch(running):
        if running and cp.worker is not None:
            cp.worker.progress.connect(on_frame, Qt.ConnectionType.DirectConnection)
    cp.running.connect(watch)
    out = tmp_path / "session"
    run_capture(qtbot, window, out, "0,90,180")
    assert alarm.is_set() and cp.last_status == "interrupted", cp.eta.text()
    m = json.loads((out / "session.json").read_text())
    assert m["status"] == "interrupted" and "limit switch" in m["status_reason"]
    assert [c["status"] for c in m["captures"]][:2] == ["complete", "complete"]
    qtbot.wait(500)  # the window goes on polling; it never drives the axis
    assert calls == {"home": 0, "move_to": 0}
    shown = [cp.eta.text()] + [t for t in messages(window, "error") if "limit switch" in t]
    assert len(shown) >= 3  # the ETA line, the failed capture, the stop
    for text in shown:
        assert "polrig home" not in text, text
        assert "home the turntable (Devices tab, Home)" in text, text
    assert "Resume session in folder" in messages(window, "error")[-1]
    window.devices.home("turntable")
    qtbot.waitUntil(lambda: "home turntable: done" in messages(window), timeout=10000)
    cp.resume()
    qtbot.waitUntil(lambda: cp.last_status == "complete", timeout=60000)
    assert json.loads((out / "session.json").read_text())["status"] == "complete"


def limit_on_next(rig, method: str) -> None:
    """The stage's next ``method`` call hits a limit switch: the fault is injected in the
    calling thread just before that call, so the Devices tab's status polls (they count as
    device calls too) cannot take it first, as they could, on a loaded machine, between an
    injection made by the test and the call it was meant for."""
    real = getattr(rig.stage, method)

    def first(*a, **kw):
        setattr(rig.stage, method, real)
        rig.faults.inject_fault("stage", "limit", after_calls=0)
        return real(*a, **kw)
    setattr(rig.stage, method, first)


def test_a_device_alarm_in_a_manual_move_says_how_to_home_here(qtbot, window):
    wait_connected(qtbot, window)
    limit_on_next(window.rig, "move_to")
    window.devices.move("stage", 20.0)
    qtbot.waitUntil(lambda: any("limit switch" in t for t in messages(window, "error")),
                    timeout=10000)
    text = next(t for t in messages(window, "error") if "limit switch" in t)
    assert text.startswith("move stage to 20 deg failed: ")
    assert "polrig home" not in text and "home the stage (Devices tab, Home)" in text
    assert "device error 1" in text  # the device's own code stays


def test_a_device_alarm_in_a_calibration_step_says_how_to_home_here(qtbot, window, tmp_path):
    wait_connected(qtbot, window)
    cal = window.calibration
    cal.folder.setText(str(tmp_path / "cal"))
    limit_on_next(window.rig, "home")  # the step homes the stage first
    cal.run_step("dofp")
    qtbot.waitUntil(lambda: not cal.is_running, timeout=30000)
    text = messages(window, "error")[-1]
    assert text.startswith("calibration step dofp failed: ") and "limit switch" in text
    assert "polrig home" not in text and "home the stage (Devices tab, Home)" in text
    assert "home the stage (Devices tab, Home)" in cal.report_view.toPlainText()
