"""GRBL turntable driver against the GRBL 1.1 emulator on a pseudo-terminal."""

from __future__ import annotations

import time

import pytest
import serial

from drivers.emulators.grbl import GrblEmulator
from drivers.grbl import GrblTurntable
from polrig.errors import DeviceDisconnected, DeviceFault, DeviceNotFound, DeviceTimeout, ProtocolError

pytestmark = pytest.mark.timeout(20)


@pytest.fixture
def emu(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20.0) as e:
        yield e


@pytest.fixture
def table(emu):
    with GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        yield t


def test_starts_locked_homes_and_moves(table, emu):
    assert table.info().firmware.startswith("Grbl 1.1")
    with pytest.raises(DeviceFault) as ei:
        table.move_to(45.0)
    assert ei.value.code == 9  # G-code locked out in alarm
    table.home(timeout_s=5)
    table.move_to(45.0, timeout_s=5)
    assert emu.axis_position("A") == pytest.approx(45.0, abs=1e-3)
    assert table.position_deg() == pytest.approx(45.0, abs=1e-3)
    assert b"G90 G0 A45.0000\n" in emu.received
    table.move_to(-30.0, wait=False)
    assert table.is_busy()
    table.wait(5)
    assert table.position_deg() == pytest.approx(-30.0, abs=1e-3)


def test_axis_and_scale_from_config(emu):
    with GrblTurntable(emu.port, axis="z", degrees_per_unit=2.0, reply_timeout_s=0.5) as t:
        t.unlock()
        t.move_to(90.0, timeout_s=5)
        assert emu.axis_position("Z") == pytest.approx(45.0, abs=1e-3)
        assert t.position_deg() == pytest.approx(90.0, abs=1e-3)
    with pytest.raises(ValueError):
        GrblTurntable(emu.port, axis="Q")


def test_feed_hold_stop_keeps_position(table, emu):
    table.home(timeout_s=5)
    emu.speed_factor = 1.0
    table.move_to(180.0, wait=False)
    time.sleep(0.2)
    table.stop()
    pos = table.position_deg()
    assert 0 < pos < 180
    assert not table.is_busy()
    table.move_to(10.0, timeout_s=10)  # no alarm: reset during hold keeps position


def test_reset_while_moving_raises_alarm(table, emu):
    table.home(timeout_s=5)
    emu.speed_factor = 1.0
    table.move_to(180.0, wait=False)
    time.sleep(0.05)
    table._link.write(b"\x18")
    time.sleep(0.05)
    with pytest.raises(DeviceFault) as ei:
        table.wait(2)
    assert ei.value.code == 3


def test_error_mid_move_alarm_then_rehome(table, emu):
    table.home(timeout_s=5)
    emu.inject("error_mid_move")
    with pytest.raises(DeviceFault) as ei:
        table.move_to(90.0, timeout_s=5)
    assert ei.value.code == 1 and "Hard limit" in ei.value.text
    assert 0 < emu.axis_position() < 90
    with pytest.raises(DeviceFault):
        table.move_to(90.0)
    table.home(timeout_s=5)
    table.move_to(90.0, timeout_s=5)
    assert emu.axis_position() == pytest.approx(90.0, abs=1e-3)


def test_gcode_error_is_typed(table):
    with pytest.raises(DeviceFault) as ei:
        table._command("G38.2 A1")
    assert ei.value.code == 9 or ei.value.code == 20
    table.unlock()
    with pytest.raises(DeviceFault) as ei:
        table._command("G1 A10")  # no feed rate set
    assert ei.value.code == 22 and "feed" in ei.value.text.lower()


def test_no_reply_timeout_and_recovery(table, emu):
    emu.inject("no_reply")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        table.position_deg()
    assert time.monotonic() - t0 < 1.0
    assert table.position_deg() == pytest.approx(0.0)


@pytest.mark.parametrize("fault", ["garble", "partial"])
def test_bad_replies(table, emu, fault):
    emu.inject(fault)
    with pytest.raises(ProtocolError):
        table.position_deg()
    assert table.position_deg() == pytest.approx(0.0)


def test_disconnect_resets_controller(table, emu):
    table.home(timeout_s=5)
    table.move_to(20.0, timeout_s=5)
    emu.disconnect()
    with pytest.raises(DeviceDisconnected):
        table.position_deg()
    assert not table.is_open
    emu.reconnect()
    table.open()
    with pytest.raises(DeviceFault):
        table.move_to(30.0)  # USB unplug reset the board: locked until homed
    table.home(timeout_s=5)
    table.move_to(30.0, timeout_s=5)
    assert emu.axis_position() == pytest.approx(30.0, abs=1e-3)


def test_not_a_grbl_and_release(tmp_path, emu):
    with pytest.raises(DeviceNotFound):
        GrblTurntable(str(tmp_path / "absent")).open()
    emu.inject("no_reply", count=1)  # the banner never comes
    t = GrblTurntable(emu.port, reply_timeout_s=0.3)
    with pytest.raises(DeviceTimeout):
        t.open()
    assert not t.is_open
    with serial.Serial(emu.port, 115200, exclusive=True):
        pass


def test_soft_limit_alarm(tmp_path):
    with GrblEmulator(link=tmp_path / "g", speed_factor=20, soft_limits=(-360.0, 360.0)) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        t.home(timeout_s=5)
        with pytest.raises(DeviceFault) as ei:
            t.move_to(400.0)
        assert ei.value.code == 2 and "Soft limit" in ei.value.text
        assert emu.axis_position() == 0.0
        t.home(timeout_s=5)
        t.move_to(-90.0, timeout_s=5)
        assert emu.axis_position() == pytest.approx(-90.0)


def test_lost_ok_does_not_shift_later_replies(table, emu):
    table.home(timeout_s=5)
    emu.inject("no_reply")  # the 'ok' of the next line is lost; the move still runs
    with pytest.raises(DeviceTimeout):
        table.move_to(10.0)
    table.wait(5)
    assert table.position_deg() == pytest.approx(10.0, abs=1e-3)
    table.move_to(20.0, timeout_s=5)
    assert emu.axis_position() == pytest.approx(20.0, abs=1e-3)


def test_home_timeout_aborts_the_cycle(tmp_path):
    with GrblEmulator(link=tmp_path / "g", speed_factor=1.0, homing_s=5.0) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            t.home(timeout_s=0.3)
        assert time.monotonic() - t0 < 1.0
        assert emu.state == "Alarm"  # reset during homing: ALARM:6, nothing moves
        with pytest.raises(DeviceFault) as ei:
            t.wait(1)
        assert ei.value.code == 6
        emu.homing_s = 0.05
        t.home(timeout_s=5)
        assert not t.is_busy()
