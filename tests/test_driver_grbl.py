"""GRBL turntable driver against the GRBL 1.1 emulator on a pseudo-terminal."""

from __future__ import annotations

import _thread
import threading
import time

import pytest
import serial

from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.drivers.grbl import GrblTurntable
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

pytestmark = pytest.mark.timeout(20)
#: reply timeout of the ``table`` fixture (s)
REPLY_S = 0.5
#: a timeout the tests below must not wait for (s): a wait for it fails their bound of a
#: third of it, which a loaded machine cannot reach by delays alone
LONG_S = 15.0


@pytest.fixture
def emu(tmp_path):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20.0) as e:
        yield e


@pytest.fixture
def table(emu):
    with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
        yield t


def test_starts_locked_homes_and_moves(table, emu):
    assert table.info().firmware.startswith("Grbl 1.1")
    with pytest.raises(DeviceAlarm) as ei:
        table.move_to(45.0)
    assert ei.value.code == 9  # G-code locked out in alarm
    assert ei.value.requires_operator and ei.value.axis == "turntable"
    assert "run `polrig home turntable`" in str(ei.value)
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
    with pytest.raises(DeviceAlarm) as ei:
        table.move_to(90.0, timeout_s=5)
    assert ei.value.code == 1 and "Hard limit" in ei.value.text
    assert "limit switch fired, something may be in the way" in str(ei.value)
    assert ei.value.command_for("rig.toml") == "polrig home turntable --config rig.toml"
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
    """A lost status report raises DeviceTimeout naming the configured reply timeout, after
    asking once (no retry), then the next request works."""
    emu.inject("no_reply")
    asked = emu.received.count(b"?")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.5 s"):
        table.position_deg()
    assert REPLY_S <= time.monotonic() - t0 < REPLY_S + 2.0  # its deadline, and not hanging
    assert emu.received.count(b"?") == asked + 1
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
    emu.inject("no_reply", count=2)  # no status report, then no banner after the reset
    t = GrblTurntable(emu.port, reply_timeout_s=0.3)
    with pytest.raises(DeviceTimeout):
        t.open()
    assert not t.is_open
    with serial.Serial(emu.port, 115200, exclusive=True):
        pass


def test_soft_limit_alarm(tmp_path):
    with GrblEmulator(link=tmp_path / "g", speed_factor=20, max_travel=720.0) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        t.home(timeout_s=5)
        with pytest.raises(DeviceAlarm) as ei:
            t.move_to(400.0)
        assert ei.value.code == 2 and "Soft limit" in ei.value.text
        assert "ALARM:2, soft limit" in str(ei.value)
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
    """home() raises at its timeout (0.3 s), not when the homing cycle ends (15 s), and
    aborts the cycle by a soft reset."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=1.0, homing_s=LONG_S) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
            t.home(timeout_s=0.3)
        assert 0.3 <= time.monotonic() - t0 < LONG_S / 3
        assert emu.state == "Alarm"  # reset during homing: ALARM:6, nothing moves
        with pytest.raises(DeviceFault) as ei:
            t.wait(1)
        assert ei.value.code == 6
        emu.homing_s = 0.05
        t.home(timeout_s=5)
        assert not t.is_busy()


# -- alarms that halt the controller (grbl/grbl protocol.c: hard and soft limits) ---------

def test_hard_limit_halts_until_reset_then_home_resets_first(table, emu):
    """After ALARM:1 GRBL prints [MSG:Reset to continue] and ignores everything, `?` too,
    until 0x18: every call raises the alarm at once (it timed out as 'no status report'),
    and home() soft-resets before $H (it timed out waiting for $H)."""
    table.home(timeout_s=5)
    emu.inject("error_mid_move")
    with pytest.raises(DeviceFault) as ei:
        table.move_to(90.0, timeout_s=5)
    assert ei.value.code == 1 and "reset" in str(ei.value)
    assert emu.critical
    sent = len(emu.received)
    for call in (table.position_deg, table.is_busy, lambda: table.move_to(10.0)):
        with pytest.raises(DeviceFault) as ei:
            call()
        assert ei.value.code == 1 and "halted until reset" in str(ei.value)
    assert len(emu.received) == sent  # nothing asked, so no reply awaited from it
    t0 = time.monotonic()
    table.home(timeout_s=LONG_S)
    assert time.monotonic() - t0 < LONG_S / 3  # $H was answered: it was not ignored
    after = bytes(emu.received[sent:])
    assert after.index(b"\x18") < after.index(b"$H\n")  # soft reset first
    assert not emu.critical and emu.state == "Idle"
    table.move_to(90.0, timeout_s=5)
    assert emu.axis_position() == pytest.approx(90.0, abs=1e-3)


def test_alarm_that_arrived_between_calls_is_raised(table, emu):
    """The alarm came while nobody was reading: the next call raises it (it was recorded,
    then the `?` went unanswered: DeviceTimeout)."""
    table.home(timeout_s=5)
    emu.inject("error_mid_move")
    table.move_to(90.0, wait=False)
    deadline = time.monotonic() + 3
    while emu.state != "Alarm" and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    with pytest.raises(DeviceFault) as ei:
        table.position_deg()
    assert ei.value.code == 1 and "Hard limit" in ei.value.text


def test_soft_limit_halts_until_reset(tmp_path):
    with GrblEmulator(link=tmp_path / "g", speed_factor=20, max_travel=720.0) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        t.home(timeout_s=5)
        with pytest.raises(DeviceFault) as ei:
            t.move_to(400.0)
        assert ei.value.code == 2
        sent = len(emu.received)
        with pytest.raises(DeviceFault) as ei:
            t.position_deg()
        assert ei.value.code == 2 and len(emu.received) == sent  # no `?` awaited: none sent
        t.unlock()  # soft reset first, then $X: the soft limit kept the position
        assert t.position_deg() == pytest.approx(0.0)
        t.move_to(-90.0, timeout_s=5)


# -- suspended motions (interface.md states Hold and Door) --------------------------------

def test_feed_hold_suspends_the_move_it_does_not_end_it(table, emu):
    """A feed hold pressed on the controller: wait() does not report the move done (it
    returned at once with the axis paused); the move ends after cycle start. A wait that
    reaches its deadline while the move is held times out naming Hold:0 and cancels the
    move (feed hold, soft reset: position kept), so a later cycle start cannot resume it
    with nobody waiting for it."""
    table.home(timeout_s=5)
    emu.speed_factor = 4.0  # 240 deg/s
    table.move_to(180.0, wait=False)
    time.sleep(0.15)
    emu.press_feed_hold()
    assert emu.state == "Hold:0"
    assert table.is_busy()  # held: not done
    emu.press_cycle_start()
    table.wait(5)
    assert table.position_deg() == pytest.approx(180.0, abs=1e-3)
    table.move_to(0.0, wait=False)
    time.sleep(0.15)
    emu.press_feed_hold()
    t0 = time.monotonic()
    with pytest.raises(DeviceAlarm, match=r"Hold:0 \(feed hold complete.*; stopped.*held by the operator") as e:
        table.wait(0.3)  # the operator stopped it: a safety fault, never retried by the engine
    assert e.value.axis == "turntable" and e.value.command == "polrig home turntable"
    assert 0.3 <= time.monotonic() - t0 < 0.3 + 2.0  # waited its deadline, not forever
    assert not table.is_busy() and emu.state == "Idle"
    held = table.position_deg()
    assert 0 < held < 180
    emu.press_cycle_start()  # nothing left to resume
    time.sleep(0.1)
    assert emu.axis_position() == pytest.approx(held, abs=1e-3) and emu.state == "Idle"


def test_open_safety_door_suspends_the_move(table, emu):
    table.home(timeout_s=5)
    emu.speed_factor = 4.0
    table.move_to(200.0, wait=False)
    time.sleep(0.15)
    emu.set_door(True)
    assert table.is_busy()  # suspended, not done
    emu.set_door(False)
    assert emu.state == "Door:0" and table.is_busy()
    emu.press_cycle_start()
    table.move_to(200.0, timeout_s=5)  # waits for the resumed move, then this one
    assert emu.axis_position() == pytest.approx(200.0, abs=1e-3)
    table.move_to(0.0, wait=False)
    time.sleep(0.15)
    emu.set_door(True)
    with pytest.raises(DeviceAlarm, match=r"Door:1 \(safety door ajar.*; stopped"):
        table.wait(0.3)
    assert not table.is_busy()  # cancelled: closing the door and cycle start move nothing
    held = emu.axis_position()
    emu.set_door(False)
    emu.press_cycle_start()
    time.sleep(0.1)
    assert emu.axis_position() == pytest.approx(held, abs=1e-3)


def test_sleeping_controller_is_a_fault(table, emu):
    table.home(timeout_s=5)
    table._command("$SLP")
    with pytest.raises(DeviceFault, match=r"asleep"):
        table.is_busy()
    sent = len(emu.received)
    t0 = time.monotonic()
    table.home(timeout_s=LONG_S)  # only a reset ends sleep mode: home() resets first
    assert time.monotonic() - t0 < LONG_S / 3  # $H was answered: it was not ignored
    after = bytes(emu.received[sent:])
    assert after.index(b"\x18") < after.index(b"$H\n")
    assert not table.is_busy()


# -- texts and reports ---------------------------------------------------------------------

def test_error_texts_follow_the_grbl_csv(table):
    """grbl/grbl doc/csv/error_codes_en_US.csv: 21 is the modal group violation (24 said
    so), and every code 1-17, 20-38 has its text (12-14, 17, 21, 23, 25-32, 34-38 printed
    'unknown error')."""
    from polrig.drivers.grbl_codes import ERRORS
    assert sorted(ERRORS) == list(range(1, 18)) + list(range(20, 39))
    assert ERRORS[21] == "Modal group violation"
    assert ERRORS[24].startswith("Invalid gcode ID:24")
    assert ERRORS[13] == "Check Door" and ERRORS[12] == "Step rate > 30kHz"
    table.unlock()
    with pytest.raises(DeviceFault) as ei:
        table._command("G0 G1 A1")  # two motion commands in one block
    assert ei.value.code == 21 and ei.value.text == "Modal group violation"


def test_work_position_reports(table, emu):
    """$10=0: GRBL reports WPos instead of MPos (was 'status report without axis A')."""
    table.unlock()
    table._command("$10=0")
    table.move_to(30.0, timeout_s=5)
    st = table.status()
    assert st["frame"] == "WPos" and st["position_deg"] == pytest.approx(30.0, abs=1e-3)
    table._command("$10=1")
    assert table.status()["frame"] == "MPos"


def test_three_axis_report_names_the_axes_setting(tmp_path):
    with GrblEmulator(link=tmp_path / "g") as emu:
        t = GrblTurntable(emu.port, axis="B", axes="XYZAB", reply_timeout_s=0.5)
        with pytest.raises(ProtocolError, match=r"has 4 axes, but axis B is number 5 of "
                                                r"the configured axes 'XYZAB'"):
            t.open()
        t.close()


def test_controller_reset_during_a_command(table, emu):
    """The banner comes instead of 'ok' (brown-out, DTR): said so at once (it was a plain
    'no reply' timeout)."""
    table.home(timeout_s=5)
    emu.inject("reset")
    table.reply_timeout_s = LONG_S  # a wait for the 'ok' would break the bound below
    t0 = time.monotonic()
    with pytest.raises(DeviceFault, match="controller reset during 'G90 G0 A10.0000'"):
        table.move_to(10.0)
    assert time.monotonic() - t0 < LONG_S / 3
    table.reply_timeout_s = REPLY_S
    with pytest.raises(DeviceAlarm, match="Alarm"):
        table.move_to(10.0)  # came back locked (homing enabled)
    table.home(timeout_s=5)
    table.move_to(10.0, timeout_s=5)


class LostOkGrbl(GrblEmulator):
    """$X is answered by its message line, and the 'ok' after it is lost on the line."""

    def _execute(self, line: str, now: float) -> None:
        if line == "$X":
            self.send(b"[MSG:Caution: Unlocked]\r\n")
            return
        super()._execute(line, now)


def test_timeouts_name_the_configured_timeout(tmp_path):
    """The second line of an answer is read against what is left of the deadline; the
    message names the configured timeout (it said 'within 0.49... s')."""
    with LostOkGrbl(link=tmp_path / "g") as emu:
        t = GrblTurntable(emu.port, reply_timeout_s=0.5)
        t.open()
        time.sleep(0.05)
        with pytest.raises(DeviceTimeout, match=r"no reply to '\$X' within 0\.5 s$"):
            t.unlock()
        t.close()
        emu.inject("no_reply", count=2)  # the status report, then the banner of the reset
        with pytest.raises(DeviceTimeout, match=r"no GRBL banner within 0\.5 s$"):
            t.open()


# -- capabilities from the settings ($$) ---------------------------------------------------
def test_capabilities_from_the_axis_settings(tmp_path):
    """$113 (units/min) and $123 (units/s^2) of axis A, times degrees_per_unit; no soft
    limits: no travel limit. Read once, on open."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=20, max_rate_per_min=1800.0,
                      accel_per_s2=40.0) as emu:
        emu.settings[112] = 60.0  # another axis's rate does not matter
        with GrblTurntable(emu.port, reply_timeout_s=0.5, degrees_per_unit=2.0) as t:
            caps = t.capabilities
            assert caps.speed_deg_s == pytest.approx(1800.0 / 60 * 2.0)
            assert caps.accel_deg_s2 == pytest.approx(80.0) and caps.range_deg is None
            n = emu.received.count(b"$$\n")
            assert n == 1 and t.capabilities is caps and emu.received.count(b"$$\n") == 1
        with GrblTurntable(emu.port, reply_timeout_s=0.5, rate_per_min=600.0) as t:
            assert t.capabilities.speed_deg_s == pytest.approx(10.0)  # the G1 feed caps it


def test_declared_travel_is_where_the_soft_limits_are(tmp_path):
    """With soft limits ($20=1) the declared range is GRBL's machine window [-$13k, 0]:
    the controller moves to both ends and raises the soft-limit alarm just beyond."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=50, max_travel=90.0) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=0.5, poll_s=0.01) as t:
        lo, hi = t.capabilities.range_deg
        assert (lo, hi) == (-90.0, 0.0)
        t.home(timeout_s=5)
        t.move_to(lo, timeout_s=5)
        t.move_to(hi, timeout_s=5)
        with pytest.raises(DeviceFault) as ei:
            t.move_to(hi + 1.0)
        assert ei.value.code == 2
        t.home(timeout_s=5)
        with pytest.raises(DeviceFault) as ei:
            t.move_to(lo - 1.0)
        assert ei.value.code == 2


def test_a_build_without_the_axis_settings(tmp_path):
    """A listing without the axis's $11k/$12k (a 3-axis build asked for axis A) is refused
    on open, naming the settings; the port is released."""
    with GrblEmulator(link=tmp_path / "g") as emu:
        for n in (113, 123, 133):
            del emu.settings[n]
        t = GrblTurntable(emu.port, reply_timeout_s=0.5)
        with pytest.raises(ProtocolError, match=r"no \$113, \$123 for axis A"):
            t.open()
        assert not t.is_open
        with serial.Serial(emu.port, 115200, exclusive=True):
            pass


# -- motion is never left running, nor aborted by opening (issue: audit C) -----------------

def test_opening_does_not_abort_a_running_move(emu):
    """`polrig move turntable 180 --no-wait`, then another command opens the port: the open
    asks '?' (answered at any time) and sends no soft reset, which would abort the move with
    ALARM:3 and lose the position; the version and settings GRBL refuses during a motion
    (error:8) are read later, and the move ends where it was sent."""
    with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
        t.home(timeout_s=5)
        emu.speed_factor = 1.0  # 60 deg/s: 3 s to 180 deg
        t.move_to(180.0, wait=False)
    time.sleep(0.1)
    sent = len(emu.received)
    with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
        assert b"\x18" not in emu.received[sent:]
        assert emu.state == "Run"
        assert t.info().extra["state_at_open"].startswith("Run")
        assert t.is_busy()
        with pytest.raises(DeviceFault, match="cannot be read while it moves") as ei:
            t.capabilities
        assert ei.value.code == 8 and not isinstance(ei.value, DeviceAlarm)
        t.wait(10)
        assert t.position_deg() == pytest.approx(180.0, abs=1e-3)
        assert t.capabilities.speed_deg_s == pytest.approx(60.0)  # read once idle
    assert emu.state == "Idle"


def test_opening_resets_a_controller_that_does_not_answer(tmp_path):
    """A controller halted by a limit ignores '?': the open soft-resets it (as before), and it
    comes back locked in the Alarm state."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=20) as emu:
        with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
            t.home(timeout_s=5)
            emu.trip_hard_limit()
        assert emu.critical
        with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
            assert not emu.critical and emu.state == "Alarm"
            assert t.info().firmware.startswith("Grbl 1.1")
            with pytest.raises(DeviceAlarm):
                t.move_to(10.0)


def test_opening_during_a_homing_cycle_resets_it(tmp_path):
    """GRBL answers no '?' during a homing cycle (commands.md, '?'): a controller found homing
    (a '$H' of another program) is silent, so the open soft-resets it like any silent
    controller; the cycle aborts with ALARM:6 and the controller comes back locked in the
    Alarm state, and moves are refused until it is homed."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=1, homing_s=30.0) as emu:
        with emu.lock:
            emu.feed(b"$H\n", time.monotonic())
        assert emu.state == "Home"
        with GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
            assert b"\x18" in emu.received and emu.state == "Alarm"
            assert t.info().extra["state_at_open"] == "Alarm" and t.last_alarm == 6
            with pytest.raises(DeviceAlarm, match="ALARM:6"):
                t.move_to(10.0)


def test_lower_case_axes_from_the_config(emu):
    with GrblTurntable(emu.port, axis="a", axes="xyza", reply_timeout_s=REPLY_S) as t:
        assert t.axes == "XYZA" and t.axis_index == 3


def test_a_move_that_times_out_is_stopped(table, emu):
    """wait() at its deadline stops the axis (feed hold, soft reset: position kept) before
    DeviceTimeout is raised: nothing keeps turning after the error."""
    table.home(timeout_s=5)
    emu.speed_factor = 1.0  # 60 deg/s
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s; stopped"):
        table.move_to(300.0, timeout_s=0.3)
    assert emu.state == "Idle"
    here = emu.axis_position()
    time.sleep(0.2)
    assert emu.axis_position() == pytest.approx(here, abs=1e-6) and 0 < here < 300
    table.move_to(0.0, timeout_s=10)  # no alarm: the position was kept


def test_a_homing_cycle_interrupted_is_aborted_by_stop(tmp_path):
    """Ctrl-C while home() waits for the 'ok' of $H, then stop() (what `polrig home` does):
    a soft reset at once (GRBL ignores a feed hold and '?' while homing), the cycle aborted."""
    with GrblEmulator(link=tmp_path / "g", speed_factor=1, homing_s=30.0) as emu, \
            GrblTurntable(emu.port, reply_timeout_s=REPLY_S, poll_s=0.01) as t:
        timer = threading.Timer(0.3, _thread.interrupt_main)
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            t.home(timeout_s=LONG_S)
        timer.join()
        assert emu.state == "Home"
        t.stop()
        assert emu.state == "Alarm" and b"!" not in emu.received  # ALARM:6, homing aborted
