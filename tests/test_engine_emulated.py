"""The engine's fault policy (polrig.acquisition.engine) against real drivers and their emulators rather
than the simulated rig's injected faults. A turntable in ALARM is never homed by the engine on
its own (issue 33 item 5): GRBL's startup Alarm lock, a hard limit (a limit switch fired:
something in the way) and a soft limit each stop the move with a
:class:`polrig.errors.DeviceAlarm` naming ``polrig home turntable``, with no retry and no
``$H`` on the wire, until the operator homes it; a calibration step driven through
:class:`polrig.acquisition.engine.GuardedRig` on the emulated rig with the GenTL test producer (no board
in its test pattern) asks the operator for every fixture mount in turn and ends with a
readable error."""

from __future__ import annotations

import textwrap
import types
from pathlib import Path

import pytest
from _genicam import VIKY, viky_camera

from polrig.acquisition.engine import Executor, GuardedRig, Retried
from polrig.app.rig import open_rig
from polrig.calibration.calset import CalibrationSet
from polrig.calibration.procedures import INTRINSIC_MOUNTS
from polrig.calibration.runner import run_steps
from polrig.drivers import apt
from polrig.drivers.ell14 import Ell14Stage
from polrig.drivers.emulators.ell14 import PULSES_PER_REV, Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.drivers.emulators.k10cr1 import STEPS_PER_DEG, K10cr1Emulator
from polrig.drivers.k10cr1 import K10cr1Turntable
from polrig.errors import DeviceAlarm, DeviceTimeout

pytestmark = pytest.mark.timeout(60)


def grbl_rig(tmp_path, grbl, extra: str = "") -> Path:
    """``rig.toml``: the GRBL emulator as turntable plus ``extra``; the rest simulated."""
    path = tmp_path / "rig.toml"
    path.write_text(textwrap.dedent(extra) + textwrap.dedent(f"""
        [turntable]
        driver = "grbl"
        port = "{grbl.port}"
        """))
    return path


def test_a_turntable_locked_in_alarm_is_never_homed_by_the_engine(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as grbl:
        assert grbl.state == "Alarm"  # homing enabled: GRBL starts locked
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            retries: list[str] = []
            guarded = GuardedRig.around(rig, on_retry=retries.append)
            with pytest.raises(DeviceAlarm, match=r"locked in the Alarm state.*"
                                                  r"run `polrig home turntable`") as ei:
                guarded.turntable.move_to(30.0)
            assert ei.value.code == 9 and ei.value.requires_operator
            assert retries == [] and b"$H" not in grbl.received
            assert grbl.state == "Alarm" and grbl.axis_position("A") == 0.0
            rig.turntable.home(timeout_s=10)  # the operator's `polrig home turntable`
            guarded.turntable.move_to(30.0)
            assert grbl.axis_position("A") == pytest.approx(30.0, abs=1e-3)
            assert retries == [] and grbl.received.count(b"$H") == 1


@pytest.mark.parametrize("limit", ["hard", "soft"])
def test_a_limit_stops_the_move_and_is_never_retried(tmp_path, limit):
    """ALARM:1 (a limit switch fired half way) or ALARM:2 (a soft limit: nothing moved):
    raised at once, no retry, no $H; the controller stays halted until the operator's home
    resets and homes it."""
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as grbl:
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            rig.turntable.home(timeout_s=10)  # the operator, before the run
            homes = grbl.received.count(b"$H")
            retries: list[str] = []
            guarded = GuardedRig.around(rig, on_retry=retries.append)
            grbl.inject(f"{limit}_limit")
            with pytest.raises(DeviceAlarm) as ei:
                guarded.turntable.move_to(60.0)
            code = {"hard": 1, "soft": 2}[limit]
            assert ei.value.code == code and f"ALARM:{code}" in str(ei.value)
            assert "polrig home turntable" in str(ei.value)
            if limit == "hard":
                assert "something may be in the way" in str(ei.value)
                assert 0 < grbl.axis_position("A") < 60
            else:
                assert grbl.axis_position("A") == 0.0
            assert retries == [] and grbl.received.count(b"$H") == homes
            assert grbl.critical  # nobody reset it: halted, as the operator will find it
            with pytest.raises(DeviceAlarm):  # later moves too, still without a retry
                guarded.turntable.move_to(10.0)
            assert retries == [] and grbl.received.count(b"$H") == homes
            rig.turntable.home(timeout_s=10)  # the operator: reset, then $H
            guarded.turntable.move_to(60.0)
            assert grbl.axis_position("A") == pytest.approx(60.0, abs=1e-3)


@pytest.mark.skipif(not VIKY.is_file(), reason="genicam test producer viky.cti not installed")
def test_a_calibration_step_on_hardware_asks_for_every_mount_then_fails_readably(tmp_path):
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=8) as ell, \
            GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as grbl:
        path = grbl_rig(tmp_path, grbl, f"""
            {viky_camera()}
            [stage]
            driver = "ell14"
            port = "{ell.port}"
            [light]
            driver = "dc2200"
            backend = "polrig.drivers.emulators.dc2200"
            """)
        with open_rig(path) as rig:
            rig.turntable.home(timeout_s=10)  # the operator: GRBL starts locked in Alarm
            asked: list[dict] = []
            lines: list[str] = []

            def mount(target: str, **fixture) -> None:
                assert target == "charuco"
                asked.append(fixture)

            with pytest.raises(ValueError, match="board views"):
                run_steps(["intrinsics"], rig, mount, CalibrationSet(), log=lines.append)
        assert asked == [dict(m) for m in INTRINSIC_MOUNTS]
        retries = [ln for ln in lines if ln.startswith("retry:")]
        assert retries == []
        assert sum("board mounted" in ln for ln in lines) == len(INTRINSIC_MOUNTS)
        # fixture positions in words, never a Python dict (issue 21 item 10)
        assert not any("{" in ln for ln in lines if "board mounted" in ln), lines


def test_a_guarded_home_waits_no_longer_than_the_callers_timeout(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=1, homing_s=30.0) as grbl:
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            guarded = GuardedRig.around(rig)
            with pytest.raises(DeviceTimeout):
                guarded.turntable.home(timeout_s=0.5)  # a 30 s homing cycle


def axis_rig(**axes) -> types.SimpleNamespace:
    """What the executor needs of a rig to move ``axes`` (name -> driver)."""
    return types.SimpleNamespace(devices=dict(axes), **axes)


def test_a_refused_move_is_stopped_before_the_re_home(tmp_path):
    """The ELL14 still turns (a `polrig move stage 300 --no-wait` before the run): the move
    is refused (GS09), and its one re-homed retry stops the stage first: a home sent while
    it turns is refused 'busy' too, which raised the home's error and lost the move's."""
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=0.02) as ell:  # 8.6 deg/s
        with Ell14Stage(ell.port, reply_timeout_s=0.5) as earlier:
            earlier.move_to(300.0, wait=False)
        ell.speed_factor = 4.0
        with Ell14Stage(ell.port, reply_timeout_s=0.5) as stage:
            retries: list[str] = []
            ex = Executor(axis_rig(stage=stage),
                          subscribers=[lambda e: isinstance(e, Retried) and retries.append(e.message)])
            sent = len(ell.received)
            ex.move({"stage": 170.0})
            assert ell.position_deg == pytest.approx(170.0, abs=360.0 / PULSES_PER_REV)
            assert len(retries) == 1 and "refused: the device is busy" in retries[0]
            wire = bytes(ell.received[sent:])
            assert wire.index(b"0st") < wire.index(b"0ho0")


def test_a_k10cr1_turntable_stopped_by_its_controller_is_never_homed_by_the_engine(tmp_path):
    """A K10CR1 turntable: a never-homed one and a move the controller stopped on its own
    (a limit switch) stop the run with a DeviceAlarm naming `polrig home turntable`; the
    engine sends no MOT_MOVE_HOME (it re-homed and went on)."""
    home = apt.AptMessage(apt.MOT_MOVE_HOME, 1).pack()
    with K10cr1Emulator(link=tmp_path / "k10", speed_factor=40) as k10, \
            K10cr1Turntable(k10.port, reply_timeout_s=0.5) as table:
        retries: list[str] = []
        ex = Executor(axis_rig(turntable=table),
                      subscribers=[lambda e: isinstance(e, Retried) and retries.append(e.message)])
        with pytest.raises(DeviceAlarm, match="turntable is not homed") as ei:
            ex.move({"turntable": 30.0})
        assert ei.value.command == "polrig home turntable"
        assert retries == [] and home not in k10.received and not k10.homed
        table.home(timeout_s=5)  # the operator's `polrig home turntable`
        k10.inject("stop_mid_move")
        with pytest.raises(DeviceAlarm, match="turntable move interrupted") as ei:
            ex.move({"turntable": 90.0})
        assert ei.value.command_for("rig.toml") == "polrig home turntable --config rig.toml"
        assert retries == [] and k10.received.count(home) == 1
        assert 0 < k10.position_deg < 90
        ex.move({"turntable": 90.0})  # after the operator cleared it
        assert k10.position_deg == pytest.approx(90.0, abs=1 / STEPS_PER_DEG)
