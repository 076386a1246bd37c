"""DC2200 driver through real pyusb calls into the USBTMC emulator backend."""

from __future__ import annotations

import time

import pytest

from polrig.drivers import usbtmc
from polrig.drivers.dc2200 import Dc2200Light
from polrig.drivers.emulators.dc2200 import Dc2200Emulator
from polrig.errors import (
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

pytestmark = pytest.mark.timeout(20)
#: USB timeout of the ``light`` fixture (s)
TIMEOUT_S = 0.3


@pytest.fixture
def emu():
    return Dc2200Emulator()


@pytest.fixture
def light(emu):
    with Dc2200Light(backend=emu, timeout_s=TIMEOUT_S) as lt:
        yield lt


def test_identity_and_constant_brightness_mode(light, emu):
    info = light.info()
    assert (info.model, info.serial, info.firmware) == ("DC2200", "M00123456", "1.2.0")
    assert emu.mode == "CB"
    assert "SOURCE1:MODE CB\n" in emu.received


def test_on_level_status(light, emu):
    light.set_level(0.25)
    light.set_on(True)
    assert emu.output_on and emu.brightness_percent == pytest.approx(25.0)
    st = light.status()
    assert st["on"] is True and st["level"] == pytest.approx(0.25) and st["mode"] == "CB"
    light.set_on(False)
    assert light.status()["on"] is False
    with pytest.raises(ValueError):
        light.set_level(1.5)
    with pytest.raises(ValueError):
        light.set_level(float("nan"))


def test_usbtmc_frames_are_padded():
    frame = usbtmc.dev_dep_msg_out(7, b"*IDN?\n")
    assert len(frame) % 4 == 0 and frame[:4] == bytes([1, 7, 0xF8, 0])
    assert int.from_bytes(frame[4:8], "little") == 6 and frame[8] == 1


def test_scpi_error_is_device_fault(light, emu):
    with pytest.raises(DeviceFault) as ei:
        light.command("SOURCE1:CBRIGHTNESS:BRIGHTNESS 150")
    assert ei.value.code == -222 and "out of range" in ei.value.text
    light.set_level(0.5)  # queue drained: the next command is clean


def test_select_by_serial(emu):
    with pytest.raises(DeviceNotFound, match="serial X1"):
        Dc2200Light("X1", backend=emu).open()
    with Dc2200Light("M00123456", backend=emu) as lt:
        assert lt.info().serial == "M00123456"


def test_no_reply_times_out_and_recovers(light, emu):
    """A lost response raises DeviceTimeout naming the configured timeout, after one query
    (no retry, no further query of status()), then the device answers again."""
    emu.inject("no_reply")
    n0 = len(emu.received)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"within 0\.3 s"):
        light.status()
    assert TIMEOUT_S <= time.monotonic() - t0 < TIMEOUT_S + 2.0  # its deadline, not hanging
    assert emu.received[n0:] == ["OUTPUT1:STATE?\n"]
    assert light.status()["on"] is False


@pytest.mark.parametrize("fault", ["garble", "partial"])
def test_bad_replies(light, emu, fault):
    emu.inject(fault)
    with pytest.raises(ProtocolError):
        light.status()
    assert light.status()["level"] == 0.0


def test_led_head_lost(light, emu):
    light.set_on(True)
    emu.inject("device_error")
    with pytest.raises(DeviceFault) as ei:
        light.set_on(True)
    assert ei.value.code == -241 and "Hardware missing" in ei.value.text
    assert light.status()["on"] is False
    emu.led_connected = True
    light.set_on(True)
    assert emu.output_on


def test_disconnect_and_reopen(light, emu):
    emu.disconnect()
    with pytest.raises(DeviceDisconnected):
        light.set_on(True)
    assert not light.is_open
    with pytest.raises(DeviceNotFound):
        light.open()
    emu.reconnect()
    light.open()
    light.set_on(True)
    assert emu.output_on
    light.close()
    light.close()


def test_backend_module_name():
    from polrig.drivers.emulators import dc2200 as mod
    with Dc2200Light(backend="polrig.drivers.emulators.dc2200") as lt:
        lt.set_level(0.1)
    assert mod.get_backend().brightness_percent == pytest.approx(10.0)
    with pytest.raises(DeviceNotFound):
        Dc2200Light(backend="no.such.backend").open()


def test_scpi_short_and_long_forms(light, emu):
    light.command("SOUR1:MOD CB")
    light.command("source1:cbrightness:brightness:level:amplitude 12.5")
    assert emu.brightness_percent == pytest.approx(12.5)
    assert light.query("SOURce:CBRightness:BRIGhtness:AMPLitude?").startswith("1.25")
    with pytest.raises(DeviceFault) as ei:
        light.command("SOURCE1:BRIGHTNESS 3")
    assert ei.value.code == -113


def test_error_queue_that_never_empties_is_bounded(emu):
    """SYST:ERR? always answers -241 (it was asked 300,000 times in 5 s, forever): the
    drain stops after 32 reads (polrig.drivers.dc2200.MAX_ERROR_READS) and raises the errors
    read. The drain's other bound, the driver's timeout, is set far out here (the fixture's
    0.3 s could end a drain slowed down by a loaded machine first)."""
    with Dc2200Light(backend=emu, timeout_s=30.0) as light:
        emu.inject("error_queue_stuck")
        n0 = len(emu.received)
        with pytest.raises(DeviceFault, match=r"did not empty after 32 reads .*-241 "
                                              r"'Hardware missing'") as ei:
            light.set_on(True)
        assert ei.value.code == -241 and ei.value.text == "Hardware missing"
        assert len(emu.received) - n0 == 1 + 32  # the setting, then SYST:ERR? 32 times
        emu.stuck_error = None
        light.set_on(True)
        assert emu.output_on


def test_several_queued_errors_are_drained_and_named(light, emu):
    with pytest.raises(DeviceFault, match=r"2 more in the queue: -113 'Undefined header'; "
                                          r"-224 ") as ei:
        light.command("SOURCE1:CBRIGHTNESS:BRIGHTNESS 150;SOURCE1:NOPE 1;SOURCE1:MODE XX")
    assert ei.value.code == -222
    light.set_level(0.5)


@pytest.mark.parametrize("fault, error, words", [
    ("clear_timeout", DeviceTimeout, "no answer within 0.3 s"),
    ("clear_stall", DeviceNotFound, "refused the USBTMC request"),
])
def test_failed_clear_on_open_is_typed(emu, fault, error, words):
    """INITIATE_CLEAR timing out or stalling while opening raised a raw usb.core.USBError
    ('polrig: error: [Errno 110] Operation timed out')."""
    emu.inject(fault)
    lt = Dc2200Light(backend=emu, timeout_s=0.3)
    with pytest.raises(error, match=rf"dc2200: clearing the USBTMC pipes \(INITIATE_CLEAR\): "
                                    rf".*{words}"):
        lt.open()
    assert not lt.is_open
    lt.open()  # the next try works
    assert lt.info().model == "DC2200"
    lt.close()
