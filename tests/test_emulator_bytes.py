"""The emulators answer the documented bytes (checked without the drivers, so a mistake
shared by a driver and its emulator cannot hide)."""

from __future__ import annotations

import struct
import time

import pytest
import serial
import usb.core

from polrig.drivers.emulators.dc2200 import Dc2200Emulator
from polrig.drivers.emulators.ell14 import Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.drivers.emulators.k10cr1 import K10cr1Emulator

pytestmark = pytest.mark.timeout(20)


def lines(ser: serial.Serial, n: int, timeout_s: float = 2.0) -> list[bytes]:
    out = []
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        line = ser.readline()
        if line:
            out.append(line)
    return out


def test_ell14_documented_replies():
    with Ell14Emulator(speed_factor=10) as emu, \
            serial.Serial(emu.port, 9600, timeout=0.2) as ser:
        ser.write(b"0in")
        [info] = lines(ser, 1)
        assert info.endswith(b"\r\n") and info[:3] == b"0IN" and len(info) == 3 + 30 + 2
        assert info[3:5] == b"0E"  # ELL14 = type 14
        assert int(info[21:25], 16) == 360 and int(info[25:33], 16) == 143360
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GS00\r\n"]
        ser.write(b"1gs")  # another address on the bus: silence
        assert lines(ser, 1, 0.3) == []
        ser.write(b"0ma00008C00")  # 35840 pulses = 90 deg; PO comes when the move ends
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GS09\r\n"]  # busy
        assert lines(ser, 1) == [b"0PO00008C00\r\n"]
        ser.write(b"0mrFFFFC400")  # -15360 pulses (two's complement) = -38.57 deg
        assert lines(ser, 1) == [b"0PO00005000\r\n"]
        ser.write(b"0ma00FFFFFF")  # far outside one revolution
        assert lines(ser, 1) == [b"0GS04\r\n"]
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GS04\r\n"]  # the error is repeated once, then cleared
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GS00\r\n"]
        ser.write(b"0xx")
        assert lines(ser, 1) == [b"0GS03\r\n"]


def test_ell14_reply_variants_and_faults():
    with Ell14Emulator(speed_factor=10) as emu, \
            serial.Serial(emu.port, 9600, timeout=0.2) as ser:
        emu.inject("bad_status")
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GSQQ\r\n"]
        emu.end_with_status = True
        ser.write(b"0ma00008C00")
        assert lines(ser, 1) == [b"0GS00\r\n"]
        emu.end_with_status = False
        emu.stop_reply = "GS"
        ser.write(b"0st")
        assert lines(ser, 1) == [b"0GS00\r\n"]
        emu.stop_reply = None
        ser.write(b"0st")
        assert lines(ser, 1, 0.3) == []
        emu.inject("lost_end")
        ser.write(b"0ma00000000")
        ser.write(b"0gs")
        assert lines(ser, 1) == [b"0GS09\r\n"]
        assert lines(ser, 1, 0.5) == []  # the PO that ends the move is lost
        ser.write(b"0gp")
        assert lines(ser, 1) == [b"0PO00000000\r\n"]


def test_k10cr1_documented_frames():
    with K10cr1Emulator(speed_factor=100) as emu, \
            serial.Serial(emu.port, 115200, rtscts=True, timeout=0.5) as ser:
        ser.write(bytes([0x05, 0x00, 0x00, 0x00, 0x50, 0x01]))  # HW_REQ_INFO
        header = ser.read(6)
        assert header == bytes([0x06, 0x00, 84, 0x00, 0x81, 0x50])
        data = ser.read(84)
        assert struct.unpack("<I", data[:4])[0] == 55000123 and data[4:10] == b"K10CR1"
        ser.write(bytes([0x43, 0x04, 0x01, 0x00, 0x50, 0x01]))  # MOT_MOVE_HOME channel 1
        assert ser.read(6) == bytes([0x44, 0x04, 0x01, 0x00, 0x01, 0x50])  # MOVE_HOMED
        steps = round(45 * 409600 / 3)
        ser.write(bytes([0x53, 0x04, 0x06, 0x00, 0xD0, 0x01]) + struct.pack("<Hi", 1, steps))
        assert ser.read(6) == bytes([0x64, 0x04, 14, 0x00, 0x81, 0x50])  # MOVE_COMPLETED
        chan, pos, enc, status = struct.unpack("<HiiI", ser.read(14))
        assert (chan, pos) == (1, steps) and status & (1 << 10) and status & (1 << 31)
        ser.write(bytes([0x29, 0x04, 0x01, 0x00, 0x50, 0x01]))  # MOT_REQ_STATUSBITS
        assert ser.read(6) == bytes([0x2A, 0x04, 6, 0x00, 0x81, 0x50])
        assert struct.unpack("<HI", ser.read(6))[1] & (1 << 10)


def test_k10cr1_stop_mid_move_and_unsolicited_frames():
    with K10cr1Emulator(speed_factor=100, homed=True) as emu, \
            serial.Serial(emu.port, 115200, rtscts=True, timeout=0.5) as ser:
        emu.inject("stop_mid_move")
        steps = round(90 * 409600 / 3)
        ser.write(bytes([0x53, 0x04, 0x06, 0x00, 0xD0, 0x01]) + struct.pack("<Hi", 1, steps))
        assert ser.read(6) == bytes([0x66, 0x04, 14, 0x00, 0x81, 0x50])  # MOVE_STOPPED
        chan, pos, _enc, _status = struct.unpack("<HiiI", ser.read(14))
        assert chan == 1 and 0 < pos < steps
        emu.inject("unsolicited")
        ser.write(bytes([0x11, 0x04, 0x01, 0x00, 0x50, 0x01]))  # MOT_REQ_POSCOUNTER
        assert ser.read(6) == bytes([0x91, 0x04, 14, 0x00, 0x81, 0x50])
        assert struct.unpack("<Hi", ser.read(14)[:6]) == (1, pos)
        assert ser.read(6) == bytes([0x12, 0x02, 0x01, 0x01, 0x01, 0x50])
        assert ser.read(6) == bytes([0x12, 0x04, 6, 0x00, 0x81, 0x50])  # the reply
        assert struct.unpack("<Hi", ser.read(6)) == (1, pos)


def test_grbl_documented_replies():
    with GrblEmulator(speed_factor=50) as emu, serial.Serial(emu.port, 115200, timeout=0.2) as ser:
        ser.write(b"\x18")  # soft reset (opening the port flushed the power-up banner)
        assert lines(ser, 3) == [b"\r\n", b"Grbl 1.1h ['$' for help]\r\n",
                                 b"[MSG:'$H'|'$X' to unlock]\r\n"]
        ser.write(b"?")
        assert lines(ser, 1) == [b"<Alarm|MPos:0.000,0.000,0.000,0.000|FS:0,0>\r\n"]
        ser.write(b"G0 A10\n")
        assert lines(ser, 1) == [b"error:9\r\n"]
        ser.write(b"$X\n")
        assert lines(ser, 2) == [b"[MSG:Caution: Unlocked]\r\n", b"ok\r\n"]
        ser.write(b"G1 A10\n")
        assert lines(ser, 1) == [b"error:22\r\n"]
        ser.write(b"G1 A10 F600\n")
        assert lines(ser, 1) == [b"ok\r\n"]  # planned, not finished
        ser.write(b"?")
        assert lines(ser, 1)[0].startswith(b"<Run|MPos:")
        time.sleep(0.1)
        ser.write(b"?")
        # FS is the real-time feed rate (interface.md): 0 once nothing moves
        assert lines(ser, 1) == [b"<Idle|MPos:0.000,0.000,0.000,10.000|FS:0,0>\r\n"]
        ser.write(b"G91 G0 A-4\n")
        assert lines(ser, 1) == [b"ok\r\n"]
        time.sleep(0.05)
        assert emu.axis_position("A") == pytest.approx(6.0)
        ser.write(b"G38.2 A1\n")
        assert lines(ser, 1) == [b"error:20\r\n"]


def test_grbl_status_report_waits_for_the_end_of_homing():
    """commands.md, `?`: accepted at any time "except during a homing cycle" (grbl limits.c
    runs no real-time command in its homing loop, motion_control.c runs them once the cycle
    ends): a `?` sent while homing is answered after the cycle, `<Home|...>` before the `ok`
    of `$H`; a reset during the cycle drops it (ALARM:6, banner). `FS` is the real-time feed
    rate (interface.md; stepper.c st_get_realtime_rate): that of the motion, 0 when idle."""
    with GrblEmulator(speed_factor=1, homing_s=0.6) as emu, \
            serial.Serial(emu.port, 115200, timeout=0.1) as ser:
        ser.write(b"$H\n")
        time.sleep(0.1)
        ser.write(b"?")
        assert lines(ser, 1, 0.2) == []  # homing: no report yet
        assert lines(ser, 2, 2.0) == [b"<Home|MPos:0.000,0.000,0.000,0.000|FS:0,0>\r\n",
                                      b"ok\r\n"]
        ser.write(b"?")
        assert lines(ser, 1) == [b"<Idle|MPos:0.000,0.000,0.000,0.000|FS:0,0>\r\n"]
        ser.write(b"G1 A2 F600\n")  # 10 units/s: 0.2 s
        assert lines(ser, 1) == [b"ok\r\n"]
        ser.write(b"?")
        [report] = lines(ser, 1)
        assert report.startswith(b"<Run|MPos:") and report.endswith(b"|FS:600,0>\r\n")
        time.sleep(0.4)
        ser.write(b"?")
        assert lines(ser, 1) == [b"<Idle|MPos:0.000,0.000,0.000,2.000|FS:0,0>\r\n"]
        emu.homing_s = 30.0
        ser.write(b"$H\n")
        time.sleep(0.1)
        ser.write(b"?")
        assert lines(ser, 1, 0.2) == []
        ser.write(b"\x18")
        assert lines(ser, 4) == [b"ALARM:6\r\n", b"\r\n", b"Grbl 1.1h ['$' for help]\r\n",
                                 b"[MSG:'$H'|'$X' to unlock]\r\n"]
        assert lines(ser, 1, 0.2) == []  # the reset dropped the report asked during homing


def test_grbl_limit_alarm_blocks_everything_until_reset():
    """grbl/grbl protocol.c protocol_exec_rt_system: after a hard or soft limit the alarm and
    [MSG:Reset to continue] are printed, then everything but 0x18 is ignored, `?` too; the
    reset brings the banner and the Alarm lock."""
    with GrblEmulator(speed_factor=50, max_travel=10.0) as emu, \
            serial.Serial(emu.port, 115200, timeout=0.2) as ser:
        ser.write(b"$X\n")
        assert lines(ser, 2)[-1] == b"ok\r\n"
        ser.write(b"G0 A20\n")
        assert lines(ser, 2) == [b"ALARM:2\r\n", b"[MSG:Reset to continue]\r\n"]
        ser.write(b"?")
        ser.write(b"$X\n")
        assert lines(ser, 1, 0.3) == []
        ser.write(b"\x18")
        assert lines(ser, 3) == [b"\r\n", b"Grbl 1.1h ['$' for help]\r\n",
                                 b"[MSG:'$H'|'$X' to unlock]\r\n"]
        ser.write(b"?")
        assert lines(ser, 1) == [b"<Alarm|MPos:0.000,0.000,0.000,0.000|FS:0,0>\r\n"]


def test_grbl_injected_limits_speak_grbls_bytes():
    """Issue 33 item 5: the emulator trips a hard limit (injected mid-move, an obstacle in
    the way, a switch closed now) and a soft limit on demand, with GRBL 1.1's bytes
    (alarm_codes_en_US.csv, protocol.c, report.c): ALARM:N, [MSG:Reset to continue],
    silence until 0x18, then the banner with [MSG:'$H'|'$X' to unlock], <Alarm|...> and
    error:9 for G-code until $H."""
    halted = [b"[MSG:Reset to continue]\r\n"]
    locked = [b"\r\n", b"Grbl 1.1h ['$' for help]\r\n", b"[MSG:'$H'|'$X' to unlock]\r\n"]
    with GrblEmulator(speed_factor=50) as emu, serial.Serial(emu.port, 115200, timeout=0.2) as ser:
        def unlock_and(line: bytes, alarm: int) -> None:
            ser.write(b"$X\n")
            assert lines(ser, 2)[-1] == b"ok\r\n"
            ser.write(line)
            got = lines(ser, 3)
            assert got == [b"ok\r\n", f"ALARM:{alarm}\r\n".encode()] + halted, got
            ser.write(b"?")
            assert lines(ser, 1, 0.3) == []  # halted: not even a status report
            ser.write(b"\x18")
            assert lines(ser, 3) == locked
            ser.write(b"?")
            assert lines(ser, 1)[0].startswith(b"<Alarm|MPos:")
            ser.write(b"G0 A0\n")
            assert lines(ser, 1) == [b"error:9\r\n"]

        emu.inject("hard_limit")
        unlock_and(b"G0 A90\n", 1)
        assert 0 < emu.axis_position() < 90  # stopped half way, position lost
        emu.obstacle = ("A", 30.0)  # something in the way, between here and -10
        unlock_and(b"G0 A-10\n", 1)
        assert emu.axis_position() == pytest.approx(30.0)  # stopped where it pushed the switch
        ser.write(b"$X\n")
        lines(ser, 2)
        emu.obstacle = None
        ser.write(b"G0 A0\n")
        assert lines(ser, 1) == [b"ok\r\n"]
        time.sleep(0.05)
        emu.obstacle = ("A", 30.0)
        ser.write(b"G0 A60\n")
        assert lines(ser, 3) == [b"ok\r\n", b"ALARM:1\r\n"] + halted
        assert emu.axis_position() == pytest.approx(30.0)
        ser.write(b"\x18")
        assert lines(ser, 3) == locked
        emu.obstacle = None
        emu.inject("soft_limit")
        ser.write(b"$X\n")
        lines(ser, 2)
        ser.write(b"G0 A10\n")  # soft limit: alarm before any motion, no ok
        assert lines(ser, 2) == [b"ALARM:2\r\n"] + halted
        assert emu.axis_position() == pytest.approx(30.0)
        ser.write(b"\x18")
        assert lines(ser, 3) == locked
        ser.write(b"$H\n")
        assert lines(ser, 1) == [b"ok\r\n"]  # homing is the way out
        emu.trip_hard_limit()  # a switch pushed while idle
        assert lines(ser, 2) == [b"ALARM:1\r\n"] + halted


def test_grbl_hold_door_and_wpos_reports():
    with GrblEmulator(speed_factor=1) as emu, serial.Serial(emu.port, 115200, timeout=0.2) as ser:
        ser.write(b"$X\n$10=0\nG0 A90\n")
        assert lines(ser, 4)[-3:] == [b"ok\r\n"] * 3
        time.sleep(0.1)
        emu.press_feed_hold()
        ser.write(b"?")
        [report] = lines(ser, 1)
        assert report.startswith(b"<Hold:0|WPos:0.000,0.000,0.000,") and b"MPos" not in report
        emu.set_door(True)
        ser.write(b"?")
        assert lines(ser, 1)[0].startswith(b"<Door:1|")
        emu.set_door(False)
        ser.write(b"?")
        assert lines(ser, 1)[0].startswith(b"<Door:0|")
        emu.press_cycle_start()
        ser.write(b"?")
        assert lines(ser, 1)[0].startswith(b"<Run|")


def test_dc2200_usbtmc_bytes_through_pyusb():
    emu = Dc2200Emulator()
    dev = usb.core.find(idVendor=0x1313, idProduct=0x80C8, backend=emu)
    assert dev is not None and dev.serial_number == "M00123456" and dev.product == "DC2200"
    dev.set_configuration()
    # DEV_DEP_MSG_OUT, bTag 1, "*IDN?\n" (6 bytes), EOM, padded to 20 bytes
    dev.write(0x02, bytes([1, 1, 0xFE, 0, 6, 0, 0, 0, 1, 0, 0, 0]) + b"*IDN?\n\0\0")
    # REQUEST_DEV_DEP_MSG_IN, bTag 2, up to 256 bytes
    dev.write(0x02, bytes([2, 2, 0xFD, 0, 0, 1, 0, 0, 0, 0, 0, 0]))
    reply = bytes(dev.read(0x81, 512))
    text = b"Thorlabs,DC2200,M00123456,1.2.0\n"
    assert reply[:12] == bytes([2, 2, 0xFD, 0]) + struct.pack("<I", len(text)) + bytes([1, 0, 0, 0])
    assert reply[12:12 + len(text)] == text and len(reply) % 4 == 0
    with pytest.raises(usb.core.USBTimeoutError):  # nothing requested: nothing to read
        dev.read(0x81, 512, timeout=50)
    emu.disconnect()
    with pytest.raises(usb.core.USBError):
        dev.write(0x02, bytes([1, 3, 0xFC, 0, 0, 0, 0, 0, 1, 0, 0, 0]))


@pytest.mark.parametrize("module", ["ell14", "grbl", "k10cr1"])
def test_emulator_help_names_its_own_link(module, capsys, monkeypatch):
    """Each emulator's --help suggests the link path rig-emulated.toml uses for it."""
    import importlib
    import pathlib

    monkeypatch.setenv("COLUMNS", "120")  # argparse wraps help text to the terminal width
    toml = (pathlib.Path(__file__).resolve().parents[1] / "drivers" / "emulators"
            / "rig-emulated.toml").read_text()
    path = f"/tmp/polrig-{module}"
    assert f"--link {path}" in toml
    with pytest.raises(SystemExit):
        importlib.import_module(f"polrig.drivers.emulators.{module}").main(["--help"])
    out = capsys.readouterr().out
    assert path in out and out.count("/tmp/") == 1


# -- the velocity parameters the drivers' capabilities come from --------------------------
def test_ell14_velocity_query():
    """ELLx protocol manual: ``gv`` -> ``GV`` + two hex digits, percent of the maximum
    speed (0x64 = 100 %); ``sv`` sets it (``GS00``), out of 1..100 is ``GS04``."""
    with Ell14Emulator(speed_factor=10) as emu, \
            serial.Serial(emu.port, 9600, timeout=0.2) as ser:
        ser.write(b"0gv")
        assert lines(ser, 1) == [b"0GV64\r\n"]
        ser.write(b"0sv32")
        assert lines(ser, 1) == [b"0GS00\r\n"]
        ser.write(b"0gv")
        assert lines(ser, 1) == [b"0GV32\r\n"]
        ser.write(b"0sv00")
        assert lines(ser, 1) == [b"0GS04\r\n"]
        assert emu.velocity_percent == 50


def test_k10cr1_velocity_parameters_frames():
    """APT MOT_REQ_VELPARAMS 0x0414 (header only, param1 = channel) -> MOT_GET_VELPARAMS
    0x0415 with 14 data bytes <H channel, i min velocity, i acceleration, i max velocity>;
    MOT_SET_VELPARAMS 0x0413 carries the same 14 bytes. Power-up values 10 deg/s and
    10 deg/s^2 in APT units for 409600/3 micro-steps per degree (velocity * 53.68,
    acceleration / 90.9, written out here instead of taken from polrig.drivers.apt)."""
    with K10cr1Emulator(speed_factor=100) as emu, \
            serial.Serial(emu.port, 115200, rtscts=True, timeout=0.5) as ser:
        ser.write(bytes([0x14, 0x04, 0x01, 0x00, 0x50, 0x01]))
        assert ser.read(6) == bytes([0x15, 0x04, 14, 0x00, 0x81, 0x50])
        chan, vmin, accel, vmax = struct.unpack("<Hiii", ser.read(14))
        assert (chan, vmin) == (1, 0)
        assert vmax == 73291093 and accel == 15020  # 10 deg/s, 10 deg/s^2
        ser.write(bytes([0x13, 0x04, 14, 0x00, 0xD0, 0x01])
                  + struct.pack("<Hiii", 1, 0, 7510, 36645547))  # 5 deg/s^2, 5 deg/s
        ser.write(bytes([0x14, 0x04, 0x01, 0x00, 0x50, 0x01]))
        assert ser.read(6) == bytes([0x15, 0x04, 14, 0x00, 0x81, 0x50])
        assert struct.unpack("<Hiii", ser.read(14)) == (1, 0, 7510, 36645547)


def test_grbl_settings_listing():
    """commands.md: ``$$`` prints ``$N=value`` lines then ``ok``; ``$N=value`` sets one
    (``error:3`` for a setting GRBL does not have); ``$$`` is refused during a motion
    (``error:8``, system.c)."""
    with GrblEmulator(speed_factor=1, homing_enabled=False, max_rate_per_min=1200.0,
                      accel_per_s2=30.0) as emu, \
            serial.Serial(emu.port, 115200, timeout=0.2) as ser:
        ser.write(b"$$\n")
        listing = lines(ser, 200, 1.0)
        assert listing[-1] == b"ok\r\n"
        settings = dict(l.strip().decode().lstrip("$").split("=") for l in listing[:-1])
        assert settings["20"] == "0" and settings["22"] == "0" and settings["10"] == "1"
        assert settings["113"] == "1200.000" and settings["123"] == "30.000"
        assert {"110", "111", "112", "130", "131", "132", "133"} <= set(settings)
        ser.write(b"$113=600\n")
        assert lines(ser, 1) == [b"ok\r\n"]
        ser.write(b"$999=1\n")
        assert lines(ser, 1) == [b"error:3\r\n"]
        ser.write(b"$113=fast\n")
        assert lines(ser, 1) == [b"error:2\r\n"]
        ser.write(b"$$\n")
        assert b"$113=600.000\r\n" in lines(ser, 200, 1.0)
        ser.write(b"G0 A100\n")  # 10 s at 600 units/min
        assert lines(ser, 1) == [b"ok\r\n"]
        ser.write(b"$$\n")
        assert lines(ser, 1) == [b"error:8\r\n"]
