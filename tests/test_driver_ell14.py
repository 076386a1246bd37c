"""ELL14 driver against the ELL14 emulator on a pseudo-terminal (real ASCII bytes)."""

from __future__ import annotations

import time

import pytest
import serial

from polrig.drivers import ell14
from polrig.drivers.ell14 import Ell14Stage
from polrig.drivers.emulators.ell14 import PULSES_PER_REV, Ell14Emulator
from polrig.errors import (
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

pytestmark = pytest.mark.timeout(20)
PULSE_DEG = 360.0 / PULSES_PER_REV
#: reply timeout of the ``stage`` fixture (s)
REPLY_S = 0.5
#: a motion timeout the tests below must not wait for (s): a wait for it fails their bound
#: of a third of it, which a loaded machine cannot reach by delays alone
LONG_S = 15.0


@pytest.fixture
def emu(tmp_path):
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=4.0) as e:
        yield e


@pytest.fixture
def stage(emu):
    with Ell14Stage(emu.port, reply_timeout_s=REPLY_S) as s:
        yield s


def assert_released(port: str) -> None:
    """Another program can open the port exclusively: the driver let go of it."""
    with serial.Serial(port, 9600, timeout=0.1, exclusive=True):
        pass


def test_identify_and_pulses_from_in_reply(stage):
    info = stage.info()
    assert info.model == "ELL14" and info.serial == "11400123"
    assert stage.pulses_per_deg == pytest.approx(143360 / 360)


def test_move_home_position_busy(stage, emu):
    stage.move_to(45.0)
    assert abs(emu.position_deg - 45.0) <= PULSE_DEG
    assert stage.position_deg() == pytest.approx(45.0, abs=PULSE_DEG)
    stage.move_to(350.0, wait=False)
    assert stage.is_busy()
    stage.wait(5.0)
    assert not stage.is_busy()
    assert stage.position_deg() == pytest.approx(350.0, abs=PULSE_DEG)
    stage.move_to(-10.0)  # wraps into [0, 360)
    assert stage.position_deg() == pytest.approx(350.0, abs=PULSE_DEG)
    stage.home()
    assert emu.position_deg == pytest.approx(0.0, abs=PULSE_DEG)
    assert b"0ho0" in emu.received


def test_stop_mid_move(stage, emu):
    emu.speed_factor = 0.2
    stage.move_to(300.0, wait=False)
    time.sleep(0.1)
    stage.stop()
    pos = stage.position_deg()
    assert 0 < pos < 300
    assert not stage.is_busy()


def test_no_reply_times_out_then_recovers(stage, emu):
    """A lost reply raises DeviceTimeout naming the configured reply timeout, after asking
    once (no retry), then the next query works."""
    emu.inject("no_reply")
    asked = emu.received.count(b"0gp")
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.5 s"):
        stage.position_deg()
    assert REPLY_S <= time.monotonic() - t0 < REPLY_S + 2.0  # its deadline, and not hanging
    assert emu.received.count(b"0gp") == asked + 1
    assert stage.position_deg() == pytest.approx(0.0, abs=PULSE_DEG)


def test_move_timeout_is_bounded(stage, emu):
    """A move that cannot end in time raises at its timeout (0.3 s), not when the motion
    ends (8.4 s at 21.5 deg/s)."""
    emu.speed_factor = 0.05
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
        stage.move_to(180.0, timeout_s=0.3)
    assert 0.3 <= time.monotonic() - t0 < 3.0
    stage.stop()
    stage.move_to(10.0)


@pytest.mark.parametrize("fault", ["garble", "partial"])
def test_bad_replies_are_protocol_errors(stage, emu, fault):
    emu.inject(fault)
    with pytest.raises(ProtocolError):
        stage.position_deg()
    stage.move_to(20.0)
    assert stage.position_deg() == pytest.approx(20.0, abs=PULSE_DEG)


def test_garbled_end_of_move(stage, emu):
    stage.move_to(5.0)
    emu.inject("garble")
    with pytest.raises(ProtocolError):
        stage.move_to(30.0)
    assert stage.position_deg() == pytest.approx(30.0, abs=PULSE_DEG)


def test_device_error_mid_move(stage, emu):
    emu.inject("error_mid_move")
    with pytest.raises(DeviceFault) as ei:
        stage.move_to(90.0, timeout_s=5)
    assert ei.value.code == 2 and "mechanical" in ei.value.text
    assert 0 < emu.position_deg < 90
    assert emu.pending_error == 0  # the driver read and cleared the error
    stage.move_to(90.0)
    assert emu.position_deg == pytest.approx(90.0, abs=PULSE_DEG)


def test_disconnect_then_reconnect(stage, emu):
    stage.move_to(15.0)
    emu.disconnect()
    with pytest.raises(DeviceDisconnected):
        stage.position_deg()
    assert not stage.is_open
    emu.reconnect()
    stage.open()
    assert stage.position_deg() == pytest.approx(15.0, abs=PULSE_DEG)


def test_port_released_on_close_and_exclusive_while_open(emu):
    st = Ell14Stage(emu.port)
    st.open()
    with pytest.raises(serial.SerialException):
        serial.Serial(emu.port, 9600, exclusive=True)
    st.close()
    st.close()  # twice is fine
    assert_released(emu.port)


def test_missing_port_and_silent_device(tmp_path, emu):
    with pytest.raises(DeviceNotFound):
        Ell14Stage(str(tmp_path / "nope")).open()
    emu.inject("no_reply")
    st = Ell14Stage(emu.port, address=3, reply_timeout_s=0.3)  # nobody answers at address 3
    with pytest.raises(DeviceTimeout):
        st.open()
    assert not st.is_open
    assert_released(emu.port)


def test_lost_end_of_move_reply(stage, emu):
    """The PO that ends the move is lost: wait() asks `gs` when nothing comes, sees the
    device idle and returns (it ran into its timeout)."""
    emu.inject("no_reply")  # the PO that ends the move never arrives
    t0 = time.monotonic()
    stage.move_to(60.0, timeout_s=LONG_S)
    assert time.monotonic() - t0 < LONG_S / 3  # about 0.35 s: one poll window, then `gs`
    assert emu.received.count(b"0gs") >= 1
    assert emu.position_deg == pytest.approx(60.0, abs=PULSE_DEG)
    assert not stage.is_busy()
    stage.move_to(70.0)
    assert emu.position_deg == pytest.approx(70.0, abs=PULSE_DEG)


def test_lost_end_of_a_long_move(stage, emu):
    """`gs` polls during the move answer busy; the move is over once one answers GS00
    (not before the motion has ended, and not at the move's timeout)."""
    emu.speed_factor = 0.5  # 215 deg/s: 100 deg in about 0.47 s
    emu.inject("lost_end")
    t0 = time.monotonic()
    stage.move_to(100.0, timeout_s=LONG_S)
    assert 0.45 < time.monotonic() - t0 < LONG_S / 3
    assert emu.position_deg == pytest.approx(100.0, abs=PULSE_DEG)
    assert emu.received.count(b"0gs") >= 2


@pytest.mark.parametrize("call", ["move", "is_busy", "status_code"])
def test_malformed_status_is_a_protocol_error(stage, emu, call):
    """A GS reply whose status is not two hex digits: ProtocolError naming the reply (an
    untyped ValueError from int(..., 16) reached the CLI)."""
    if call == "move":
        emu.end_with_status = True  # the move ends with a GS reply, which comes malformed
        emu.inject("bad_status")
        with pytest.raises(ProtocolError, match=r"malformed status reply '0GSQQ'"):
            stage.move_to(30.0, timeout_s=2)
        emu.end_with_status = False
    elif call == "is_busy":
        emu.speed_factor = 0.2
        stage.move_to(90.0, wait=False)
        emu.inject("bad_status")
        with pytest.raises(ProtocolError, match="'0GSQQ'"):
            stage.is_busy()
        stage.wait(5)
    else:
        emu.inject("bad_status")
        with pytest.raises(ProtocolError, match="'0GSQQ'"):
            stage.status_code()
    assert stage.status_code() == 0


def test_move_ended_by_a_status_reply(stage, emu, monkeypatch):
    """GS00 answering `ma` ends the move: the driver does not ask `gs`, which it does only
    after a silent poll window (GS00 was ignored and the move timed out)."""
    monkeypatch.setattr(ell14, "POLL_S", LONG_S)  # no silent window a loaded machine can reach
    emu.end_with_status = True
    asked = emu.received.count(b"0gs")
    stage.move_to(45.0, timeout_s=LONG_S)
    assert emu.received.count(b"0gs") == asked  # ended by the reply, not by asking
    assert stage.position_deg() == pytest.approx(45.0, abs=PULSE_DEG)
    stage.move_to(10.0, wait=False)
    stage.wait(2)
    assert not stage.is_busy()


@pytest.mark.parametrize("reply", ["GS", None])
def test_stop_answered_by_status_or_nothing(stage, emu, reply):
    """`st` answered GS00, or not at all: stop() succeeds once the device reports idle (it
    raised DeviceTimeout unless the answer was PO). GS00 ends it at once, without asking
    `gs`; with no answer the reply timeout runs out and `gs` is asked once."""
    emu.stop_reply = reply
    emu.speed_factor = 0.2
    stage.move_to(300.0, wait=False)
    time.sleep(0.1)
    if reply:
        stage.reply_timeout_s = LONG_S  # waiting for it would break the bound below
    asked = emu.received.count(b"0gs")
    t0 = time.monotonic()
    stage.stop()
    dt = time.monotonic() - t0
    stage.reply_timeout_s = REPLY_S
    if reply:
        assert dt < LONG_S / 3 and emu.received.count(b"0gs") == asked
    else:
        assert REPLY_S <= dt < REPLY_S + 2.0 and emu.received.count(b"0gs") == asked + 1
    pos = stage.position_deg()
    assert 0 < pos < 300
    assert not stage.is_busy()
    stage.move_to(20.0, timeout_s=5)


def test_move_before_open_is_not_open_error(emu):
    """move_to() on a stage never opened: DeviceDisconnected (it was ZeroDivisionError)."""
    st = Ell14Stage(emu.port)
    for call in (lambda: st.move_to(5.0), lambda: st.move_to(5.0, wait=False), st.home,
                 st.stop, st.is_busy, st.position_deg):
        with pytest.raises(DeviceDisconnected, match="not open"):
            call()


class SplitReplyEll14(Ell14Emulator):
    """An ELL14 whose end-of-move reply straddles the driver's 0.25 s polling window: the
    first byte comes just before the window ends, the rest 50 ms later (as a USB bridge can
    deliver it)."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self._script: list[tuple[float, bytes]] = []

    def _execute(self, cmd: str, arg: str, now: float) -> None:
        if cmd != "ma":
            return super()._execute(cmd, arg, now)
        self.position_pulses = float(int(arg, 16))
        reply = f"{self.address}PO{arg}\r\n".encode("ascii")
        self._script = [(now + 0.235, reply[:1]), (now + 0.285, reply[1:])]

    def tick(self, now: float) -> None:
        while self._script and self._script[0][0] <= now:
            self.write_raw(self._script.pop(0)[1])


def test_end_of_move_reply_straddling_the_poll_window(tmp_path):
    """The audit's failure: `polrig move stage 45` against the emulator at speed 0.1 ended
    with ``partial reply b'0' (incomplete after 0.25 s)``."""
    with SplitReplyEll14(link=tmp_path / "ell14") as emu, \
            Ell14Stage(emu.port, reply_timeout_s=0.5) as stage:
        for angle in (45.0, 90.0, 10.0):
            stage.move_to(angle, timeout_s=5)
            assert stage.position_deg() == pytest.approx(angle, abs=PULSE_DEG)


def test_end_of_move_reply_that_stops_midway(stage, emu):
    """A reply that really stops half way is still a ProtocolError (then the device is
    asked where it is), raised once the reply stops, not at the move's timeout."""
    emu.inject("partial")
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"partial reply b'0PO0"):
        stage.move_to(40.0, timeout_s=LONG_S)
    assert time.monotonic() - t0 < LONG_S / 3
    assert stage.position_deg() == pytest.approx(40.0, abs=PULSE_DEG)


# -- capabilities from the device's velocity (gv) ----------------------------------------
@pytest.mark.parametrize("percent", [100, 25])
def test_capabilities_from_the_velocity_setting(emu, percent):
    """The speed is the ``gv`` percentage of the ELL14's 430 deg/s, read on open; the piezo
    motor has no acceleration ramp; the mount turns without limit."""
    emu.velocity_percent = percent
    with Ell14Stage(emu.port, reply_timeout_s=0.5) as s:
        caps = s.capabilities
        assert caps.speed_deg_s == pytest.approx(430.0 * percent / 100)
        assert caps.accel_deg_s2 == float("inf") and caps.range_deg is None
        assert s.move_time_s(10.0, 100.0) == pytest.approx(90.0 / caps.speed_deg_s)
        n = emu.received.count(b"0gv")
        assert s.capabilities is caps and emu.received.count(b"0gv") == n  # cached


def test_capabilities_need_an_open_stage(emu):
    with pytest.raises(DeviceDisconnected, match="not open"):
        Ell14Stage(emu.port).capabilities


# -- a refused move, a malformed identity, nothing left moving ------------------------------

def test_a_move_refused_as_busy_is_an_error_not_a_success(emu):
    """`polrig move stage 100 --no-wait`, then `polrig move stage 20` while it still turns:
    the ELL14 answers the second 'ma' with GS09 (busy: refused). That was taken for 'still
    moving' and the first move's end reported as success at 100 deg."""
    emu.speed_factor = 0.05  # 21.5 deg/s
    with Ell14Stage(emu.port, reply_timeout_s=REPLY_S) as first:
        first.move_to(100.0, wait=False)
    with Ell14Stage(emu.port, reply_timeout_s=REPLY_S) as second:
        with pytest.raises(DeviceFault, match="'ma' refused: the device is busy") as ei:
            second.move_to(20.0, timeout_s=LONG_S)
        assert ei.value.code == ell14.BUSY
        assert emu.move is not None  # the first move goes on, untouched
        second.stop()
        emu.speed_factor = 4.0
        second.move_to(20.0, timeout_s=5)  # a poll's GS09 is still 'moving'
        assert second.position_deg() == pytest.approx(20.0, abs=PULSE_DEG)


def test_polls_answered_busy_mean_still_moving(stage, emu):
    emu.speed_factor = 0.2  # 86 deg/s: 2 s
    stage.move_to(170.0, wait=False)
    assert stage.is_busy() and stage.is_busy()
    stage.wait(LONG_S)
    assert stage.position_deg() == pytest.approx(170.0, abs=PULSE_DEG)


@pytest.mark.parametrize("field, at", [("firmware", slice(14, 16)), ("travel", slice(18, 22)),
                                       ("type", slice(0, 2))])
def test_a_malformed_in_reply_is_a_protocol_error_naming_the_device(tmp_path, field, at):
    """A non-hex firmware field raised a bare ValueError (outside the IN parse's error
    handling): now every hex field is checked, a ProtocolError naming the device."""

    class BadIn(Ell14Emulator):
        def _reply(self, cmd, data):
            if cmd == "IN":
                data = data[:at.start] + "Z" * (at.stop - at.start) + data[at.stop:]
            super()._reply(cmd, data)

    with BadIn(link=tmp_path / "ell") as emu:
        st = Ell14Stage(emu.port, reply_timeout_s=REPLY_S)
        with pytest.raises(ProtocolError, match=f"ell14 {emu.port}: malformed IN reply.*{field}"):
            st.open()
        assert not st.is_open


def test_a_move_that_times_out_is_stopped(stage, emu):
    """wait() at its deadline sends 'st' before DeviceTimeout: the mount does not go on
    turning after the error."""
    emu.speed_factor = 0.05
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s; stopped"):
        stage.move_to(180.0, timeout_s=0.3)
    assert emu.move is None and b"0st" in emu.received
    here = emu.position_deg
    time.sleep(0.2)
    assert emu.position_deg == here and 0 < here < 180
