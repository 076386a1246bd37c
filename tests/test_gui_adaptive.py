"""The adaptive mode in the GUI's capture panel (pytest-qt, offscreen): its fields are on in
that mode only and reach the plan through the request ``polrig capture`` builds; a bad target
is the plan's one-line error and starts nothing; a one-pose adaptive capture on the simulated
rig records its decisions in ``session.json`` and the panel shows each one as it is made (log,
ETA label, the "Adaptive decisions" list), the ETA from the forecast the decision revised; a
stopped adaptive session resumed from the panel lists the decisions recorded for the captures it
keeps, marked, then the live ones, none twice."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from test_cli_capture import MODEL_INSTALLED  # noqa: E402
from test_gui import close_window, make_window, wait_connected  # noqa: E402

from polrig.acquisition.plan import ADAPTIVE_MAX_STATES, MODES, NETWORK_MODES  # noqa: E402

pytestmark = pytest.mark.gui
needs_model = pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")


@pytest.fixture
def idle_window(qtbot, tmp_path):
    """The window, devices not connected (the form only)."""
    w = make_window(qtbot, tmp_path / "gui.ini", start=False)
    yield w
    w.close()


def test_the_adaptive_fields_are_on_in_the_adaptive_mode_only(idle_window, tmp_path):
    cp = idle_window.capture
    adaptive_fields = (cp.target_sigma, cp.target_share, cp.max_states, cp.min_states)
    assert [cp.mode.itemText(i) for i in range(cp.mode.count())] == list(MODES)
    assert cp.max_states.maximum() == ADAPTIVE_MAX_STATES and cp.max_states.minimum() == 1
    assert all(w.toolTip() for w in adaptive_fields)
    cp.poses.setText("0,90")
    cp.out.setText(str(tmp_path / "s"))
    for mode in MODES:
        cp.mode.setCurrentText(mode)
        assert [w.isEnabled() for w in adaptive_fields] == [mode == "adaptive"] * 4, mode
        assert cp.device.isEnabled() == cp.model_size.isEnabled() == (mode in NETWORK_MODES)
        if mode != "adaptive":  # the stopping rule is not asked for: the plan's defaults
            req = cp.request()
            assert (req.target_sigma, req.target_share, req.max_states, req.min_states) == (None,) * 4
    cp.target_sigma.setValue(0.03)
    cp.target_share.setValue(0.9)
    cp.max_states.setValue(3)
    cp.states.setText("45")  # the network's state, the pose's first
    plan = cp.request().plan()
    assert (plan.mode, plan.target_sigma, plan.target_share, plan.max_states) == (
        "adaptive", 0.03, 0.9, 3)
    assert plan.states_deg == (45.0,) and plan.frames_per_pose() == 3
    assert plan.min_states == 2  # the default: a stop from the second state on
    cp.max_states.setValue(1)  # the fewest follow the most down, never above it
    assert cp.min_states.value() == 1 and cp.request().plan().min_states == 1
    cp.max_states.setValue(4)
    cp.min_states.setValue(1)
    assert cp.request().plan().min_states == 1
    cp.states.setText("")  # as --states left out: the default's first state
    assert cp.request().plan().states_deg == (0.0,)


@pytest.mark.parametrize("target_sigma, target_share, states, text", [
    (0.0, 0.95, "", "the adaptive mode stops each pose at a target"),  # the spin box says "required"
    (0.05, 0.0, "", "target share 0.0: must be a share of object pixels"),
    (0.05, 0.95, "0,45", "give one state"),
])
def test_a_bad_adaptive_option_is_one_line_and_starts_nothing(qtbot, idle_window, tmp_path,
                                                             target_sigma, target_share, states, text):
    w = idle_window
    cp = w.capture
    cp.poses.setText("0")
    cp.out.setText(str(tmp_path / "s"))
    cp.mode.setCurrentText("adaptive")
    cp.target_sigma.setValue(target_sigma)
    cp.target_share.setValue(target_share)
    cp.states.setText(states)
    if target_sigma == 0:
        assert cp.target_sigma.text() == "required (e.g. 0.05)"
    cp.start()  # the plan is checked before the devices (not connected here) or any file
    qtbot.waitUntil(lambda: cp.last_status == "failed" and not cp.is_running, timeout=10000)
    level, message = w.messages.messages[-1]
    assert level == "error" and text in message and "\n" not in message, message
    assert cp.worker.result is None and not cp.decisions_box.isVisibleTo(cp)
    assert cp.eta.text() == f"not started: {message.removeprefix('capture: ')}"
    assert not (tmp_path / "s").exists()


def adaptive_panel(w, out, poses: str, target: float):
    """``w``'s capture panel set for an adaptive capture of ``poses`` into ``out`` at relative
    sigma ``target``: ``(panel, out)``."""
    cp = w.capture
    cp.poses.setText(poses)
    cp.out.setText(str(out))
    cp.mode.setCurrentText("adaptive")
    cp.target_sigma.setValue(target)
    return cp, out


@needs_model
def test_an_adaptive_capture_shows_each_decision_and_records_them(qtbot, tmp_path):
    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        wait_connected(qtbot, w)
        cp, out = adaptive_panel(w, tmp_path / "session", "0", 0.05)
        cp.target_share.setValue(0.9)
        shown = []  # the ETA label when each decision is logged
        cp.message.connect(lambda level, text: "decision" in text and shown.append(
            (text, cp.eta.text())))
        cp.start()
        qtbot.waitUntil(lambda: cp.last_status == "complete", timeout=120000)
        qtbot.waitUntil(lambda: not cp.is_running, timeout=10000)
        manifest = json.loads((out / "session.json").read_text())
        assert manifest["status"] == "complete"
        assert manifest["plan"]["mode"] == "adaptive" and manifest["plan"]["target_share"] == 0.9
        (capture,) = manifest["captures"]
        decisions = capture["adaptive"]
        assert 1 <= len(decisions) <= 4 and decisions[-1]["action"] != "take"
        assert len(capture["files"]["raw"]) == len(decisions)  # a state per decision, the last stops
        # each decision, as it was made: in the log, on the ETA label, in the list (kept after)
        assert len(shown) == cp.decisions.count() == len(decisions)
        assert cp.decisions_box.isVisibleTo(cp)
        for i, (d, (text, eta)) in enumerate(zip(decisions, shown)):
            what = (f"take {d['state_deg']:g} deg ({d['state_time_s']:.2f} s)" if d["action"] == "take"
                    else d["action"].replace("-", " "))
            said = (f"{d['states_taken']} state(s): {100 * d['share_met']:.1f} % of "
                    f"{d['object_pixels']} object pixels at target; {what}")
            assert text == f"capture 1, pose 0 deg: decision: {said}"
            assert cp.decisions.item(i).text() == f"capture 1, pose 0 deg: {said}"
            assert eta.startswith(f"capture 1/1, pose 0 deg, {said}, ETA ")
        assert shown[-1][1].endswith("ETA 0:00")  # the pose's stop: nothing left
        # each decision's event carries the forecast it revised: the frames after it go on from it
        events = cp.events
        for i, ev in enumerate(events[:-1]):
            if ev.kind == "decision":
                nxt = events[i + 1]
                assert (nxt.hardware_s, nxt.total) == (ev.hardware_s, ev.total), (ev, nxt)
        assert cp.progress.value() == cp.progress.maximum() == len(decisions)
        assert cp.eta.text() == "session complete (1 captures)"
    finally:
        close_window(qtbot, w)


@needs_model
def test_a_resumed_adaptive_session_lists_the_recorded_decisions_then_the_live_ones(
        qtbot, tmp_path, monkeypatch):
    """Two poses, a target no pose meets and at most two states: each pose takes a second
    state, then stops at the most states. The first run is stopped at pose 2's first decision
    (the stop is asked for in the worker thread as the event is sent, so the pose's next move
    never starts): pose 1 complete, pose 2 pending with that decision recorded. Resumed from the
    panel, the list starts, before the run's first event, with pose 1's recorded decisions
    (marked "(recorded)"), not pose 2's, which the run takes again from scratch and lists once,
    live: the list ends as the session's decisions, each once."""
    from polrig.app.manifest import describe_decision
    from polrig.gui.capture_panel import CaptureWorker

    stop_at = {"capture": 1}  # the first run stops at this capture's first decision
    real_event = CaptureWorker._event

    def event(worker, ev):
        if getattr(ev, "kind", "") == "decision" and ev.capture_index == stop_at.get("capture"):
            worker.control.stop.set()
        real_event(worker, ev)

    monkeypatch.setattr(CaptureWorker, "_event", event)
    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        wait_connected(qtbot, w)
        cp, out = adaptive_panel(w, tmp_path / "session", "0,90", 1e-4)  # the spin box's least: no pose meets it
        cp.max_states.setValue(2)
        cp.start()
        qtbot.waitUntil(lambda: cp.last_status == "interrupted" and not cp.is_running,
                        timeout=120000)
        first = json.loads((out / "session.json").read_text())
        assert [c["status"] for c in first["captures"]] == ["complete", "pending"]
        kept, dropped = first["captures"][0]["adaptive"], first["captures"][1]["adaptive"]
        assert [d["action"] for d in kept] == ["take", "stop-max-states"]
        assert [d["action"] for d in dropped] == ["take"]  # recorded, then stopped before its move
        assert cp.decisions.count() == 3 and "(recorded)" not in cp.decisions.item(0).text()

        stop_at.clear()
        at_start = []  # the list when the resumed run's session is ready, and the events by then
        cp.message.connect(lambda level, text: text.startswith("capture resumed in") and at_start.append(
            ([cp.decisions.item(i).text() for i in range(cp.decisions.count())], len(cp.events),
             cp.decisions_box.isVisibleTo(cp))))
        cp.resume()
        qtbot.waitUntil(lambda: cp.last_status == "complete" and not cp.is_running, timeout=120000)
        final = json.loads((out / "session.json").read_text())
        assert final["captures"][0]["adaptive"] == kept  # kept, not taken again
        again = final["captures"][1]["adaptive"]
        assert [d["action"] for d in again] == ["take", "stop-max-states"]
        assert again[0] == dropped[0]  # the same decision on the same frames, listed once below
        recorded = [f"capture 1, pose 0 deg: {describe_decision(d)} (recorded)" for d in kept]
        live = [f"capture 2, pose 90 deg: {describe_decision(d)}" for d in again]
        assert at_start == [(recorded, 0, True)]
        assert [cp.decisions.item(i).text() for i in range(cp.decisions.count())] == recorded + live
        assert [e.message for e in cp.events if e.kind == "decision"] == [
            describe_decision(d) for d in again]
        assert cp.decisions.item(0).toolTip() != cp.decisions.item(len(recorded)).toolTip()
    finally:
        close_window(qtbot, w)
