"""K10CR1 driver against the APT emulator on a pseudo-terminal (binary frames)."""

from __future__ import annotations

import time

import pytest
import serial

from polrig.drivers import apt
from polrig.drivers.emulators.k10cr1 import STEPS_PER_DEG, K10cr1Emulator
from polrig.drivers.k10cr1 import K10cr1Stage, K10cr1Turntable
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

pytestmark = pytest.mark.timeout(20)
STEP_DEG = 1 / STEPS_PER_DEG
#: reply timeout of the ``stage`` fixture (s)
REPLY_S = 0.5
#: a motion timeout the tests below must not wait for (s): a wait for it fails their bound
#: of a third of it, which a loaded machine cannot reach by delays alone
LONG_S = 15.0


@pytest.fixture
def emu(tmp_path):
    with K10cr1Emulator(link=tmp_path / "k10cr1", speed_factor=40.0) as e:
        yield e


@pytest.fixture
def stage(emu):
    with K10cr1Stage(emu.port, reply_timeout_s=REPLY_S) as s:
        yield s


def test_binary_frames_survive_the_pty(emu):
    """Every byte value passes unchanged (raw mode: no CR/LF mapping, no XON/XOFF)."""
    payload = bytes(range(256))
    with serial.Serial(emu.port, 115200, rtscts=True, timeout=0.5) as ser:
        emu.write_raw(payload)
        assert ser.read(256) == payload
        ser.write(payload)
        time.sleep(0.1)
    assert bytes(emu.received[-256:]) == payload


def test_identify(stage):
    info = stage.info()
    assert info.model == "K10CR1" and info.serial == "55000123"
    assert info.firmware == "3.0.0"


def test_requires_home_then_moves(stage, emu):
    with pytest.raises(DeviceFault, match="not homed"):
        stage.move_to(45.0)
    stage.home(timeout_s=5)
    assert stage.status_bits() & apt.STATUS_HOMED
    stage.move_to(45.0, timeout_s=5)
    assert abs(emu.position_deg - 45.0) <= STEP_DEG
    assert stage.position_deg() == pytest.approx(45.0, abs=STEP_DEG)
    stage.move_to(100.0, wait=False)
    assert stage.is_busy()
    stage.wait(5)
    assert not stage.is_busy()
    assert emu.position_deg == pytest.approx(100.0, abs=STEP_DEG)
    # the host sent exactly the documented MOT_MOVE_ABSOLUTE frame for 100 deg
    frame = apt.AptMessage(apt.MOT_MOVE_ABSOLUTE,
                           data=(1).to_bytes(2, "little")
                           + round(100 * STEPS_PER_DEG).to_bytes(4, "little", signed=True)).pack()
    assert frame[:6] == bytes([0x53, 0x04, 0x06, 0x00, 0xD0, 0x01])
    assert frame in emu.received


def test_stop(stage, emu):
    stage.home(timeout_s=5)
    emu.speed_factor = 2.0
    stage.move_to(300.0, wait=False)
    time.sleep(0.1)
    stage.stop()
    assert 0 < stage.position_deg() < 300
    assert not stage.is_busy()


def test_no_reply_times_out_and_recovers(stage, emu):
    """A lost reply raises DeviceTimeout naming the configured reply timeout, after asking
    once (no retry), then the next request works."""
    request = apt.AptMessage(apt.MOT_REQ_POSCOUNTER, 1).pack()
    emu.inject("no_reply")
    asked = emu.received.count(request)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.5 s"):
        stage.position_deg()
    assert REPLY_S <= time.monotonic() - t0 < REPLY_S + 2.0  # its deadline, and not hanging
    assert emu.received.count(request) == asked + 1
    assert stage.position_deg() == pytest.approx(0.0)


def test_move_timeout_bounded(stage, emu):
    """A move that cannot end in time raises at its timeout (0.3 s), not when the motion
    ends (18 s at 5 deg/s)."""
    stage.home(timeout_s=5)
    emu.speed_factor = 0.5
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
        stage.move_to(90.0, timeout_s=0.3)
    assert 0.3 <= time.monotonic() - t0 < 3.0
    stage.stop()


@pytest.mark.parametrize("fault", ["garble", "partial"])
def test_bad_frames_are_protocol_errors(stage, emu, fault):
    emu.inject(fault)
    with pytest.raises(ProtocolError):
        stage.status_bits()
    assert stage.status_bits() & apt.STATUS_ENABLED


def test_error_mid_move_needs_rehome(stage, emu):
    stage.home(timeout_s=5)
    emu.inject("error_mid_move")
    with pytest.raises(DeviceFault) as ei:
        stage.move_to(60.0, timeout_s=5)
    assert ei.value.code == 10002 and "Motion error" in ei.value.text
    assert 0 < emu.position_deg < 60
    with pytest.raises(DeviceFault, match="not homed"):
        stage.move_to(60.0)
    stage.home(timeout_s=5)
    stage.move_to(60.0, timeout_s=5)
    assert emu.position_deg == pytest.approx(60.0, abs=STEP_DEG)


def test_disconnect_reconnect(stage, emu):
    stage.home(timeout_s=5)
    emu.disconnect()
    with pytest.raises(DeviceDisconnected):
        stage.position_deg()
    assert not stage.is_open
    emu.reconnect()
    stage.open()
    stage.move_to(10.0, timeout_s=5)
    assert emu.position_deg == pytest.approx(10.0, abs=STEP_DEG)


def test_not_found_and_release(tmp_path, emu):
    with pytest.raises(DeviceNotFound):
        K10cr1Stage(str(tmp_path / "absent")).open()
    st = K10cr1Stage(emu.port)
    st.open()
    st.close()
    with serial.Serial(emu.port, 115200, exclusive=True):
        pass


def test_lost_move_completed(stage, emu):
    """MOT_MOVE_COMPLETED is lost: wait() asks the status bits when nothing comes, sees the
    controller idle and returns (it waited its full timeout and raised DeviceTimeout)."""
    stage.home(timeout_s=5)
    emu.speed_factor = 10.0
    stage.move_to(30.0, wait=False)
    emu.inject("no_reply")  # MOT_MOVE_COMPLETED never arrives
    time.sleep(0.4)  # the move is over
    t0 = time.monotonic()
    stage.wait(timeout_s=LONG_S)
    assert time.monotonic() - t0 < LONG_S / 3  # about 0.35 s: one poll window, then the status
    assert not stage.is_busy()
    assert stage.position_deg() == pytest.approx(30.0, abs=STEP_DEG)
    stage.move_to(40.0, timeout_s=5)
    assert emu.position_deg == pytest.approx(40.0, abs=STEP_DEG)


def test_lost_move_completed_during_move_to(stage, emu):
    """As above, with move_to() waiting: it returns once the status bits say idle, not at its
    timeout."""
    stage.home(timeout_s=5)
    emu.speed_factor = 10.0
    stage.require_homed = False  # no status request before the move
    emu.inject("no_reply")  # the first thing the controller sends: the completion
    t0 = time.monotonic()
    stage.move_to(2.0, timeout_s=LONG_S)  # 0.02 s of motion, then silence
    assert time.monotonic() - t0 < LONG_S / 3
    assert emu.position_deg == pytest.approx(2.0, abs=STEP_DEG)


def test_move_stopped_by_the_controller_is_an_interruption(stage, emu):
    """MOT_MOVE_STOPPED that this driver did not ask for (limit switch, another program):
    DeviceFault with the position (the move counted as done)."""
    stage.home(timeout_s=5)
    emu.inject("stop_mid_move")
    with pytest.raises(DeviceFault, match=r"move interrupted: the controller stopped it at "
                                          r"(2[5-9]|3[0-5])\.\d{4} deg") as ei:
        stage.move_to(60.0, timeout_s=5)
    assert ei.value.code == "MOT_MOVE_STOPPED"
    assert 0 < emu.position_deg < 60
    assert not stage.is_busy()  # reported once
    stage.move_to(60.0, timeout_s=5)
    assert emu.position_deg == pytest.approx(60.0, abs=STEP_DEG)
    emu.inject("stop_mid_move")  # seen by is_busy() when polling a move without wait
    stage.move_to(0.0, wait=False)
    deadline = time.monotonic() + 5
    with pytest.raises(DeviceFault, match="move interrupted"):
        while time.monotonic() < deadline:
            stage.is_busy()
            time.sleep(0.02)


def test_unknown_messages_are_skipped(stage, emu):
    """Well-formed frames with ids the driver does not use (0x0491 with data, 0x0212 header
    only) before a reply are skipped (they aborted the request: 'unknown APT message id')."""
    stage.home(timeout_s=5)
    stage.move_to(20.0, timeout_s=5)
    emu.inject("unsolicited")
    assert stage.position_deg() == pytest.approx(20.0, abs=STEP_DEG)
    emu.inject("unsolicited")  # before MOT_MOVE_COMPLETED
    stage.move_to(25.0, timeout_s=5)
    assert stage.position_deg() == pytest.approx(25.0, abs=STEP_DEG)


def test_request_timeout_names_the_configured_timeout(stage, emu):
    """The reply is lost after a skipped frame: the message names the configured 0.5 s."""
    emu.inject("unsolicited")
    emu.inject("no_reply")
    with pytest.raises(DeviceTimeout, match=r"no APT header within 0\.5 s$"):
        stage.status_bits()
    assert stage.status_bits() & apt.STATUS_ENABLED


# -- capabilities from MOT_GET_VELPARAMS ---------------------------------------------------
def test_capabilities_from_the_velocity_parameters(emu):
    """Maximum velocity and acceleration as the controller reports them (APT units
    converted per the protocol document), read once on open."""
    with K10cr1Stage(emu.port, reply_timeout_s=0.5) as s:
        caps = s.capabilities
        assert caps.speed_deg_s == pytest.approx(10.0, rel=1e-6)
        assert caps.accel_deg_s2 == pytest.approx(10.0, rel=1e-4)
        assert caps.range_deg is None
        # trapezoid: 1 s to full speed (5 deg), 80 deg cruising, 1 s to stop
        assert s.move_time_s(0.0, 90.0) == pytest.approx(10.0, rel=1e-4)
    emu.max_velocity, emu.acceleration = 18322773, 751  # 2.5 deg/s, 0.5 deg/s^2 (APT units)
    with K10cr1Stage(emu.port, reply_timeout_s=0.5) as s:
        assert s.capabilities.speed_deg_s == pytest.approx(2.5, rel=1e-5)
        assert s.capabilities.accel_deg_s2 == pytest.approx(0.5, rel=1e-3)
        assert s.calculate_timeout(90.0, 5.0) == pytest.approx(
            5.0 + 1.5 * (90.0 / 2.5 + 2.5 / 0.5), rel=1e-3)


def test_zero_velocity_parameters_are_a_protocol_error(emu):
    emu.max_velocity = 0
    with pytest.raises(ProtocolError, match="maximum velocity 0"):
        K10cr1Stage(emu.port, reply_timeout_s=0.5).open()


# -- safety: a stop the controller made is the operator's; nothing left moving --------------

def test_a_stop_the_controller_made_is_a_safety_fault_naming_the_home_command(emu):
    """MOT_MOVE_STOPPED nobody asked for (a limit switch that fired): DeviceAlarm, the fault
    the engine never retries nor homes, naming the axis's own home command (the CLI adds the
    rig file)."""
    with K10cr1Turntable(emu.port, reply_timeout_s=REPLY_S) as table:
        table.home(timeout_s=5)
        emu.inject("stop_mid_move")
        with pytest.raises(DeviceAlarm) as ei:
            table.move_to(60.0, timeout_s=5)
    alarm = ei.value
    assert alarm.requires_operator and alarm.axis == "turntable"
    assert alarm.code == "MOT_MOVE_STOPPED" and "turntable move interrupted" in str(alarm)
    assert alarm.command_for("rig.toml") == "polrig home turntable --config rig.toml"
    assert alarm.operator_message("rig.toml").endswith(
        "then run `polrig home turntable --config rig.toml`")


@pytest.mark.parametrize("cls, kind", [(K10cr1Stage, "stage"), (K10cr1Turntable, "turntable")])
def test_not_homed_names_its_own_kind_and_home_command(emu, cls, kind):
    """It said 'stage is not homed (run `polrig home stage`)' for a turntable too, as a
    plain fault the engine re-homed on its own; now, like GRBL's Alarm lock after power-up,
    a DeviceAlarm naming `polrig home KIND`."""
    with cls(emu.port, reply_timeout_s=REPLY_S) as axis:
        with pytest.raises(DeviceAlarm, match=f"{kind} is not homed") as ei:
            axis.move_to(45.0)
    assert ei.value.axis == kind and ei.value.code == "not homed"
    assert ei.value.command_for("r.toml") == f"polrig home {kind} --config r.toml"
    assert emu.position_deg == 0.0


def test_a_move_that_times_out_is_stopped(stage, emu):
    """wait() at its deadline sends MOT_MOVE_STOP before DeviceTimeout: the stage does not
    go on turning after the error (it ran to its target, 18 s later)."""
    stage.home(timeout_s=5)
    emu.speed_factor = 0.5  # 5 deg/s
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s; stopped"):
        stage.move_to(90.0, timeout_s=0.3)
    assert emu.move is None
    here = emu.position_deg
    time.sleep(0.2)
    assert emu.position_deg == here and 0 < here < 90
    assert apt.AptMessage(apt.MOT_MOVE_STOP, 1, 0x01).pack() in emu.received
