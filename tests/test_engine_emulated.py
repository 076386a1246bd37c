"""The engine's fault policy (polrig.acquisition.engine) against real drivers and their emulators rather
than the simulated rig's injected faults: GRBL starts locked in its Alarm state (homing
enabled), which the one re-homed retry of a move recovers; a move GRBL refuses again after
the re-home (a soft limit) is raised after that one home; a calibration step driven through
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
from polrig.errors import DeviceFault, DeviceTimeout

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


def test_a_turntable_locked_in_alarm_is_re_homed_once_and_moves(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as grbl:
        assert grbl.state == "Alarm"
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            retries: list[str] = []
            guarded = GuardedRig.around(rig, on_retry=retries.append)
            guarded.turntable.move_to(30.0)
            assert grbl.axis_position("A") == pytest.approx(30.0, abs=1e-3)
            assert len(retries) == 1
            assert "Alarm" in retries[0] and "re-homing and retrying once" in retries[0]
            guarded.turntable.move_to(-20.0)  # homed now: no further retry
            assert grbl.axis_position("A") == pytest.approx(-20.0, abs=1e-3)
            assert len(retries) == 1


def test_a_move_refused_again_after_the_re_home_is_raised(tmp_path):
    # soft limits on: the travel is [-90, 0] deg, a target of +30 deg is a soft-limit alarm
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20, max_travel=90.0) as grbl:
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            rig.turntable.home(timeout_s=10)  # out of the startup alarm
            retries: list[str] = []
            guarded = GuardedRig.around(rig, on_retry=retries.append)
            with pytest.raises(DeviceFault, match="Soft limit"):
                guarded.turntable.move_to(30.0)
            # the soft-limit alarm halts GRBL: the re-home resets and homes it, the same
            # move is refused again and that second refusal is raised
            assert len(retries) == 1 and "Soft limit" in retries[0]
            assert grbl.axis_position("A") == pytest.approx(0.0, abs=1e-3)


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
            asked: list[dict] = []
            lines: list[str] = []

            def mount(target: str, **fixture) -> None:
                assert target == "charuco"
                asked.append(fixture)

            with pytest.raises(ValueError, match="board views"):
                run_steps(["intrinsics"], rig, mount, CalibrationSet(), log=lines.append)
        assert asked == [dict(m) for m in INTRINSIC_MOUNTS]
        retries = [ln for ln in lines if ln.startswith("retry:")]
        assert len(retries) == 1 and "Alarm" in retries[0]  # the startup alarm, re-homed once
        assert sum("board mounted" in ln for ln in lines) == len(INTRINSIC_MOUNTS)
        # fixture positions in words, never a Python dict (issue 21 item 10)
        assert not any("{" in ln for ln in lines if "board mounted" in ln), lines


def test_a_guarded_home_waits_no_longer_than_the_callers_timeout(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=1, homing_s=30.0) as grbl:
        with open_rig(grbl_rig(tmp_path, grbl), size=(32, 24)) as rig:
            guarded = GuardedRig.around(rig)
            with pytest.raises(DeviceTimeout):
                guarded.turntable.home(timeout_s=0.5)  # a 30 s homing cycle
