"""The acquisition engine (polrig.acquisition.engine) on the simulated rig: its fault policy, tested once
here and used by captures and calibration procedures alike; axes moving together; free-run
settle frames; pause/stop at checkpoints; the plan's hardware time against the simulated
rig's own clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from polrig.acquisition import hal
from polrig.acquisition.engine import (
    CaptureControl,
    Executor,
    FaultPolicy,
    FrameGrabbed,
    GuardedRig,
    Retried,
    StopRequested,
)
from polrig.acquisition.plan import (
    Checkpoint,
    FrameTag,
    Grab,
    Home,
    Move,
    SetExposure,
    SetTrigger,
)
from polrig.app import processing
from polrig.app.capture import CapturePlan, create_session, run_session
from polrig.app.rig import open_rig
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
)
from polrig.sim.devices import SimCamera

SIM = {"size": (32, 32), "clock_speed": math.inf, "seed": 3}
EXPECTED = {"fault": DeviceFault, "protocol": ProtocolError, "timeout": DeviceTimeout}


def events_of(executor: Executor) -> list:
    seen: list = []
    executor.subscribe(seen.append)
    return seen


def grab_step(i: int = 0) -> Grab:
    return Grab(FrameTag(0, 0.0, "raw", 0, 20000.0, i, 0, 0.0))


# -- the fault policy ---------------------------------------------------------------------------
def test_a_timed_out_grab_is_retried_then_given_up():
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig, policy=FaultPolicy(grab_retries=2))
        seen = events_of(ex)
        rig.faults.inject_fault("camera", "timeout", after_calls=0)
        ex.execute(grab_step())
        retries = [e for e in seen if isinstance(e, Retried)]
        assert len(retries) == 1 and "camera grab timed out" in retries[0].message
        assert [type(e) for e in seen] == [Retried, FrameGrabbed]
        for k in range(3):  # three timeouts in a row: retries exhausted
            rig.faults.inject_fault("camera", "timeout", after_calls=k)
        with pytest.raises(DeviceTimeout, match="timed out 3 times"):
            ex.execute(grab_step(1))


@pytest.mark.parametrize("kind", ["fault", "protocol", "timeout"])
def test_a_failed_move_is_retried_once_after_homing(kind):
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig)
        seen = events_of(ex)
        rig.faults.inject_fault("stage", kind, after_calls=1)  # position, then move_to
        ex.execute(Move((("stage", 60.0),)))
        assert rig.stage.position_deg() == pytest.approx(60.0)
        assert any("re-homing and retrying once" in e.message for e in seen
                   if isinstance(e, Retried))
        # a second failure (the retried move, after position, move_to, stop and home) is raised
        rig.faults.inject_fault("stage", kind, after_calls=1)
        rig.faults.inject_fault("stage", kind, after_calls=4)
        with pytest.raises(EXPECTED[kind]):
            ex.execute(Move((("stage", 10.0),)))


def test_the_retry_stops_the_axis_before_homing_it():
    """The failed move may still run (an ELL14 answers a home sent then 'busy', GRBL 'Not
    idle'): the recovery stops the axis first, then homes it, then moves again."""
    with open_rig(None, **SIM) as rig:
        calls: list[str] = []
        for name in ("stop", "home", "move_to"):
            real = getattr(rig.stage, name)
            setattr(rig.stage, name, (lambda real, name: lambda *a, **k: (
                calls.append(name), real(*a, **k))[1])(real, name))
        rig.faults.inject_fault("stage", "timeout", after_calls=1)  # position, then move_to
        Executor(rig).execute(Move((("stage", 60.0),)))
        assert calls == ["move_to", "stop", "home", "move_to"]
        assert rig.stage.position_deg() == pytest.approx(60.0)


@pytest.mark.parametrize("kind, when", [("fault", "home"), ("timeout", "home"),
                                        ("protocol", "stop")])
def test_a_recovery_that_fails_reports_the_moves_failure_with_its_reason(kind, when):
    """The home (or the stop before it) fails too: the move's own failure is raised (its
    type, its device), with the recovery's reason; it was lost behind the home's error."""
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig)
        rig.faults.inject_fault("stage", "fault", after_calls=1)  # move_to: code 13
        rig.faults.inject_fault("stage", kind, after_calls={"stop": 2, "home": 3}[when])
        with pytest.raises(DeviceFault) as ei:
            ex.execute(Move((("stage", 60.0),)))
        step = {"stop": "stopping it", "home": "re-homing it"}[when]
        message = str(ei.value)
        assert message.startswith("polarizer stage move to 60 deg failed (")
        assert f"; {step} failed too: " in message and ei.value.code == 13
        assert isinstance(ei.value.__cause__, EXPECTED[kind])
        assert str(ei.value.__cause__) in message


def test_a_safety_fault_while_recovering_is_raised_as_itself():
    with open_rig(None, **SIM) as rig:
        rig.faults.inject_fault("turntable", "timeout", after_calls=1)
        rig.faults.inject_fault("turntable", "limit", after_calls=3)  # the home
        with pytest.raises(DeviceAlarm):
            Executor(rig).execute(Move((("turntable", 30.0),)))


def test_a_disconnection_is_never_retried():
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig)
        seen = events_of(ex)
        rig.faults.inject_fault("turntable", "disconnect", after_calls=1)
        with pytest.raises(DeviceDisconnected):
            ex.execute(Move((("turntable", 30.0), ("stage", 45.0))))
        assert not [e for e in seen if isinstance(e, Retried)]


@pytest.mark.parametrize("when", ["start", "wait"])
def test_a_limit_fault_is_never_retried_nor_re_homed(when):
    """Issue 33 item 5: a limit switch that fired (DeviceAlarm) stops the move: no retry, no
    homing of the axis on its own, nothing more started; the stage already moving in the
    same Move finishes its move first. The alarm names the command that clears it."""
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig)
        seen = events_of(ex)
        homed: list[str] = []
        for name in ("stage", "turntable"):
            real = rig.devices[name].home
            rig.devices[name].home = (lambda real, name: lambda *a, **k: (
                homed.append(name), real(*a, **k)))(real, name)
        # turntable calls: position, move_to, wait
        rig.faults.inject_fault("turntable", "limit",
                                after_calls={"start": 1, "wait": 2}[when])
        with pytest.raises(DeviceAlarm) as ei:
            ex.execute(Move((("stage", 45.0), ("turntable", 30.0))))
        assert ei.value.requires_operator and ei.value.axis == "turntable"
        assert "polrig home turntable" in str(ei.value)
        assert ei.value.command_for("rig.toml") == "polrig home turntable --config rig.toml"
        assert not [e for e in seen if isinstance(e, Retried)]
        assert homed == []
        assert rig.stage.position_deg() == pytest.approx(45.0)  # let finish, not abandoned
        # a plain fault of the same axis keeps its one re-homed retry
        rig.faults.inject_fault("turntable", "fault", after_calls=1)
        ex.execute(Move((("turntable", 30.0),)))
        assert homed == ["turntable"] and rig.turntable.position_deg() == pytest.approx(30.0)


def test_a_limit_fault_is_not_retried_behind_the_hal_either():
    """GuardedRig (calibration procedures): the same policy, the alarm raised at once."""
    with open_rig(None, **SIM) as rig:
        lines: list[str] = []
        guarded = GuardedRig.around(rig, on_retry=lines.append)
        rig.faults.inject_fault("turntable", "limit", after_calls=1)
        with pytest.raises(DeviceAlarm, match="limit switch"):
            guarded.turntable.move_to(60.0)
        assert lines == []


def test_a_limit_fault_stops_the_session_resumably(tmp_path):
    """A capture whose turntable trips a limit on the way to its second pose: the session is
    interrupted with a one-line reason naming the home command, nothing was retried, and a
    resume (the operator having cleared the way) completes."""
    plan = CapturePlan((0.0, 90.0))
    cal = processing.Calibration("ideal")
    with open_rig(None, **SIM) as rig:
        session = create_session(tmp_path / "s", rig, plan, calibration_id=cal.id)
        events: list = []
        # turntable calls of capture 0: position (hardware model), position, move_to, wait;
        # capture 1: position, move_to <- the limit
        rig.faults.inject_fault("turntable", "limit", after_calls=5)
        result = run_session(rig, session, progress=events.append)
        assert result.status == "interrupted" and "\n" not in result.reason
        assert result.reason.startswith("safety stop:")
        assert "`polrig home turntable`" in result.reason
        assert not any(e.kind == "retry" for e in events)
        assert [c["status"] for c in session.captures] == ["complete", "failed"]
        result = run_session(rig, session)
        assert result.status == "complete"


def test_axes_of_one_move_turn_together():
    """Turntable 0 -> 90 deg (10 deg/s, 20 deg/s^2) and stage 0 -> 135 deg (20 deg/s,
    100 deg/s^2) in one Move take as long as the slower of the two, not their sum (the
    simulated clock measures it)."""
    with open_rig(None, **SIM) as rig:
        clock = rig.camera.world.clock
        ex = Executor(rig)
        t_turn = rig.turntable.move_time_s(0.0, 90.0)
        t_stage = rig.stage.move_time_s(0.0, 135.0)
        t0 = clock.now()
        ex.execute(Move((("turntable", 90.0), ("stage", 135.0))))
        assert clock.now() - t0 == pytest.approx(max(t_turn, t_stage), rel=1e-6)
        assert t_turn + t_stage > 1.5 * max(t_turn, t_stage)
        assert rig.turntable.position_deg() == pytest.approx(90.0)
        assert rig.stage.position_deg() == pytest.approx(135.0)


class FreeRunCamera(SimCamera):
    """The simulated camera declaring free run only, with two frames to settle (as a GenICam
    camera without TriggerMode does): what the executor must honour."""

    @property
    def capabilities(self) -> hal.CameraCapabilities:
        return hal.CameraCapabilities(("free",), self.EXPOSURE_RANGE_US, 13000.0, 2)


def test_free_run_discards_the_settle_frames_after_a_move_or_a_setting():
    with open_rig(None, **SIM) as rig:
        rig.camera = FreeRunCamera(rig.camera.world, rig.faults)
        rig.camera.open()
        ex = Executor(rig)
        kept = []
        ex.subscribe(lambda e: kept.append(e.frame.meta.frame_id)
                     if isinstance(e, FrameGrabbed) else None)
        ex.run([SetTrigger(None), Move((("stage", 45.0),)), grab_step(0), grab_step(1),
                SetExposure(20000.0),  # the exposure it has: no change, nothing to settle
                grab_step(2), SetExposure(30000.0), grab_step(3)])
        assert ex.trigger == "free" and rig.camera.trigger == "free"
        # 2 discarded + kept, kept, kept, 2 discarded + kept
        assert kept == [3, 4, 5, 8]


class NoExposureControl(FreeRunCamera):
    """A free-running camera without exposure control (it reports NaN, as the GenICam
    emulator's camera does)."""

    @property
    def exposure_us(self) -> float:
        return float("nan")

    def set_exposure_us(self, exposure_us: float) -> None:
        raise AssertionError("a camera without exposure control is never asked to set it")


def test_a_camera_without_exposure_control_is_never_asked_to_set_it():
    from polrig.acquisition.engine import hardware_model
    from polrig.acquisition.plan import session_steps, step_durations

    with open_rig(None, **SIM) as rig:
        rig.camera = NoExposureControl(rig.camera.world, rig.faults)
        rig.camera.open()
        plan = CapturePlan((0.0,))
        steps = session_steps(plan, [0], (rig.camera.exposure_us,))
        d = step_durations(steps, hardware_model(rig))
        assert all(math.isfinite(v) for v in d) and sum(d) > 0
        kept = []
        ex = Executor(rig)
        ex.subscribe(lambda e: kept.append(e) if isinstance(e, FrameGrabbed) else None)
        ex.run(steps)
        assert len(kept) == 4


def test_a_session_on_a_camera_without_exposure_control_reopens_and_has_results(tmp_path):
    """Frame records store the unknown exposure as null (standard JSON; it used to be NaN,
    which made the manifest invalid: polrig info and --resume refused the session), and
    processing models no dark current for it instead of propagating NaN into every sigma."""
    from polrig.app.session import Session
    from polrig.formats.exr import read_mueller_exr

    plan = CapturePlan((0.0,))
    cal = processing.Calibration("ideal")
    valid = {}
    for name, camera in (("plain", None), ("no-exposure", NoExposureControl)):
        with open_rig(None, **SIM) as rig:
            if camera is not None:
                rig.camera = camera(rig.camera.world, rig.faults)
                rig.camera.open()
            out = tmp_path / name
            session = create_session(out, rig, plan, calibration_id=cal.id)
            proc = processing.make_processor(plan, cal, processing.session_sensor_model(session))
            assert run_session(rig, session, processor=proc).status == "complete"
        s = Session.open(out)  # validates the manifest
        assert s.verify() == []
        m = read_mueller_exr(out / s.capture(0)["files"]["mueller"]["path"])
        masks = [v for k, v in m.extra.items() if k.startswith("mask.")]
        sigmas = [v for k, v in m.extra.items() if k.startswith("sigma.M00.")]
        valid[name] = sum(int((mk == 0).sum()) for mk in masks)
        assert all(np.isfinite(sg[mk == 0]).all() for mk, sg in zip(masks, sigmas))
    assert {r["exposure_us"] for r in s.capture(0)["files"]["raw"]} == {None}
    # the same pixels are valid as with a camera that reports its exposure (20 ms: its dark
    # current is a fraction of an electron); NaN had invalidated every one of them
    assert valid["no-exposure"] > 0 and abs(valid["no-exposure"] - valid["plain"]) <= 2


@pytest.mark.parametrize("during", ["move", "home"])
def test_ctrl_c_while_axes_move_stops_them_before_it_goes_on(during):
    """Ctrl-C or SIGTERM (a ``KeyboardInterrupt``) while the engine waits for a move (or a
    home): every axis it started is stopped before the interruption goes on, so nothing keeps
    turning once ``polrig capture`` has exited (as ``polrig move`` and ``polrig home`` do). The
    axes used to be left moving to their targets."""
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig)
        stopped: list[str] = []
        for name in ("stage", "turntable"):
            axis = rig.devices[name]
            real_stop = axis.stop
            axis.stop = (lambda real, name: lambda: (stopped.append(name), real()))(real_stop, name)

        def ctrl_c(*a, **k):
            raise KeyboardInterrupt

        if during == "move":
            rig.turntable.wait = ctrl_c  # the first axis waited for: the stage is moving too
            with pytest.raises(KeyboardInterrupt):
                ex.execute(Move((("turntable", 90.0), ("stage", 135.0))))
            assert sorted(stopped) == ["stage", "turntable"]
        else:
            ex.execute(Move((("stage", 135.0),)))
            rig.stage._wait = ctrl_c  # the home started, then waited for
            with pytest.raises(KeyboardInterrupt):
                ex.execute(Home("stage"))
            assert stopped == ["stage"]
        assert not rig.turntable.is_busy() and not rig.stage.is_busy()


def test_an_axis_whose_stop_fails_is_named_and_the_others_are_still_stopped():
    """The one route (:func:`polrig.acquisition.hal.stopped_when_interrupted`, which the
    engine's moves and ``polrig move``/``home`` use): the axes the list holds when the
    interruption comes are stopped, each once; a stop that fails is handed to ``failed`` and
    the next axis is still stopped; the interruption goes on."""
    from polrig.acquisition.hal import stopped_when_interrupted
    from polrig.errors import DeviceTimeout

    with open_rig(None, **SIM) as rig:
        stopped, failures = [], []

        def jammed():
            stopped.append("stage")
            raise DeviceTimeout("no reply to the stop", device="stage")
        rig.stage.stop = jammed
        real = rig.turntable.stop
        rig.turntable.stop = lambda: (stopped.append("turntable"), real())
        axes: list = []
        with pytest.raises(KeyboardInterrupt):
            with stopped_when_interrupted(axes, failed=lambda n, e: failures.append((n, str(e)))):
                axes += [("stage", rig.stage), ("turntable", rig.turntable), ("stage", rig.stage)]
                raise KeyboardInterrupt
        assert stopped == ["stage", "turntable"]
        assert failures == [("stage", "stage: no reply to the stop")]


def test_stop_and_pause_at_checkpoints():
    with open_rig(None, **SIM) as rig:
        control = CaptureControl()
        ex = Executor(rig, control=control)
        ex.execute(Checkpoint("capture-start", 0))
        control.stop.set()
        with pytest.raises(StopRequested):
            ex.execute(Checkpoint("capture-start", 1))
        with pytest.raises(StopRequested):  # and before a grab or a move
            ex.execute(grab_step())


# -- the same policy for calibration procedures -------------------------------------------------
def test_calibration_procedures_get_the_capture_fault_policy():
    """A procedure written against the HAL (polrig.calibration.procedures) drives a GuardedRig: a
    camera timeout and a garbled stage reply are recovered exactly as in a capture, and each
    retry is reported."""
    from polrig.calibration import procedures

    with open_rig(None, **SIM) as rig:
        lines = []
        guarded = GuardedRig.around(rig, on_retry=lines.append)
        rig.faults.inject_fault("camera", "timeout", after_calls=0)
        raw, meta = procedures.grab_mean(guarded.camera, 2)
        assert raw.shape == (32, 32) and np.isfinite(raw).all()
        rig.faults.inject_fault("stage", "protocol", after_calls=1)
        procedures._move(guarded.stage, 90.0)  # the procedures' own move helper
        assert rig.stage.position_deg() == pytest.approx(90.0)
        assert any("camera grab timed out" in s for s in lines)
        assert any("re-homing" in s for s in lines)
        control = CaptureControl()
        stopping = GuardedRig.around(rig, control=control)
        control.stop.set()
        with pytest.raises(StopRequested):
            stopping.camera.grab()


# -- hardware time ------------------------------------------------------------------------------
def test_the_plans_hardware_time_is_the_simulated_rigs_clock(tmp_path):
    """The hardware time computed before the run (motion with the axes' declared profiles,
    exposure + readout per frame) is what the simulated rig's clock measures over the run,
    is on the first progress event, and is recorded in the manifest."""
    plan = CapturePlan((0.0, 90.0, 180.0), frames_per_state=2)
    cal = processing.Calibration("ideal")
    events = []
    with open_rig(None, **SIM) as rig:
        clock = rig.camera.world.clock
        session = create_session(tmp_path / "s", rig, plan, calibration_id=cal.id)
        t0 = clock.now()
        result = run_session(rig, session, progress=events.append)
        elapsed = clock.now() - t0
    assert result.status == "complete"
    first = events[0]
    assert first.kind == "capture-start" and first.hardware_s > 0
    assert first.hardware_s == pytest.approx(elapsed, rel=1e-3)
    assert events[-1].hardware_left_s == pytest.approx(0.0, abs=1e-6)
    assert session.manifest["hardware_time_s"] == pytest.approx(first.hardware_s, abs=1e-3)
    # 24 frames of 20 ms + 13 ms; motion: stage 135 deg per pose (serpentine), two 90 deg turns
    frames_s = 24 * 0.033
    assert first.hardware_s > frames_s + 2 * 9.0


# -- a plan continued by decisions (the adaptive capture) ----------------------------------------
def test_extend_continues_the_steps_after_their_events_under_the_same_policy():
    """``extend`` is asked for more steps only once the ones given ran (their frames already
    delivered to the subscribers, so a decision can read them); its steps run under the same
    fault policy (a timed-out grab retried) and StepDone counts on; ``[]`` ends the run."""
    with open_rig(None, **SIM) as rig:
        ex = Executor(rig, policy=FaultPolicy(grab_retries=1))
        seen = events_of(ex)
        asked = []

        def extend():
            frames = sum(isinstance(e, FrameGrabbed) for e in seen)
            asked.append(frames)
            if len(asked) == 1:
                rig.faults.inject_fault("camera", "timeout", after_calls=0)  # the next grab times out once
                return [Move((("stage", 60.0),)), grab_step(1)]
            return []

        ex.run([SetTrigger(None), grab_step(0)], extend)
        assert asked == [1, 2]  # after the first frame, then after the second
        done = [e.index for e in seen if type(e).__name__ == "StepDone"]
        assert done == [0, 1, 2, 3]
        assert sum(isinstance(e, Retried) for e in seen) == 1
        assert rig.stage.position_deg() == pytest.approx(60.0)
