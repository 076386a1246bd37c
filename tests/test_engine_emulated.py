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
from pathlib import Path

import pytest
from _genicam import VIKY, viky_camera

from polrig.acquisition.engine import GuardedRig
from polrig.app.rig import open_rig
from polrig.calibration.calset import CalibrationSet
from polrig.calibration.procedures import INTRINSIC_MOUNTS
from polrig.calibration.runner import run_steps
from polrig.drivers.emulators.ell14 import Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
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
