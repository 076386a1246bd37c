"""Emulator of a Thorlabs DC2200 LED driver as a pyusb backend (``usb.backend.IBackend``).

The DC2200 driver's real pyusb calls (``usb.core.find``, ``set_configuration``,
``Device.write``/``read`` on the bulk endpoints, class control requests, string
descriptors) go through this backend, which answers with the bytes a DC2200 would send:
USBTMC framing (:mod:`polrig.drivers.usbtmc`) around SCPI. Identity: vendor 0x1313 (Thorlabs),
product 0x80C8 (DC2200), USBTMC interface class 0xFE/0x03/0x01 with bulk-OUT 0x02, bulk-IN
0x81 and interrupt-IN 0x83 endpoints.

SCPI subset (DC2200 manual, chapter "Remote control" / SCPI command reference; IEEE 488.2
common commands): ``*IDN?``, ``*RST``, ``*CLS``, ``SYSTem:ERRor[:NEXT]?``,
``SOURce[1]:MODe CB|CC|PWM`` and ``?``, ``SOURce[1]:CBRightness:BRIGhtness <percent>`` and
``?``, ``OUTPut[1]:STATe ON|OFF|1|0`` and ``?``. Long and short mnemonics, case-insensitive.
SCPI error queue with the standard codes (-100 command error, -113 undefined header,
-222 data out of range, -224 illegal parameter value, -241 hardware missing).

Faults: ``no_reply`` (the next response is lost: bulk-IN times out), ``garble`` (wrong
MsgID/bTag), ``partial`` (header announces more bytes than sent, no EOM), ``device_error``
(the LED head is unplugged: output drops and ``OUTPut ON`` fails with -241 until
``led_connected`` is set again), :meth:`disconnect`/:meth:`reconnect` (USB cable).
``error_queue_stuck``: from now on ``SYSTem:ERRor?`` answers -241 "Hardware missing" every
time, the queue never reaching "No error" (a firmware stuck in an error condition; set
``stuck_error = None`` to end it). ``clear_timeout`` / ``clear_stall``: the next USBTMC
INITIATE_CLEAR control request times out (after the request's timeout, as a hung device's)
or stalls (EPIPE, a device that refuses the class request).
"""

from __future__ import annotations

import array
import collections
import errno
import re
import threading
import time
import types

import usb.backend
import usb.core

from polrig.drivers import usbtmc

VENDOR_ID, PRODUCT_ID = 0x1313, 0x80C8
EP_OUT, EP_IN, EP_INT = 0x02, 0x81, 0x83
STRINGS = {1: "Thorlabs", 2: "DC2200", 3: "M00123456"}
FAULTS = ("no_reply", "garble", "partial", "device_error", "error_queue_stuck",
          "clear_timeout", "clear_stall")


def _desc(**fields) -> types.SimpleNamespace:
    return types.SimpleNamespace(**fields)


class Dc2200Emulator(usb.backend.IBackend):
    """One emulated DC2200 on an emulated USB bus."""

    def __init__(self, serial_number: str = "M00123456", firmware: str = "1.2.0"):
        self.serial_number = serial_number
        self.firmware = firmware
        self.lock = threading.RLock()
        self.plugged = True
        self.faults: collections.Counter[str] = collections.Counter()
        self.led_connected = True
        self.stuck_error: tuple[int, str] | None = None
        self.reset_state()
        self._dev = object()
        self._handles: set[int] = set()
        self._out_buf = bytearray()   # SCPI text of the message being received
        self._responses: collections.deque[bytes] = collections.deque()
        self._read_request: tuple[int, int] | None = None
        self.received: list[str] = []  # every SCPI message, for tests

    def reset_state(self) -> None:
        self.mode = "CB"
        self.brightness_percent = 0.0
        self.output_on = False
        self.errors: collections.deque[tuple[int, str]] = collections.deque()

    # -- test controls ---------------------------------------------------------------------
    def inject(self, fault: str, count: int = 1) -> None:
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}; known: {', '.join(FAULTS)}")
        with self.lock:
            self.faults[fault] += count
            if fault == "error_queue_stuck":
                self.faults[fault] = 0
                self.stuck_error = (-241, "Hardware missing")
            if fault == "device_error":
                self.led_connected = False
                if self.output_on:
                    self.output_on = False
                    self.errors.append((-241, "Hardware missing; LED head disconnected"))

    def _take(self, fault: str) -> bool:
        if self.faults[fault] > 0:
            self.faults[fault] -= 1
            return True
        return False

    def disconnect(self) -> None:
        with self.lock:
            self.plugged = False
            self._handles.clear()

    def reconnect(self) -> None:
        with self.lock:
            self.plugged = True
            self._out_buf.clear()
            self._responses.clear()
            self._read_request = None

    def _check(self, handle=None) -> None:
        if not self.plugged or (handle is not None and handle not in self._handles):
            raise usb.core.USBError("No such device (it may have been disconnected)",
                                    error_code=-4, errno=errno.ENODEV)

    # -- descriptors -----------------------------------------------------------------------
    def enumerate_devices(self):
        if self.plugged:
            yield self._dev

    def get_device_descriptor(self, dev):
        return _desc(bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0,
                     bDeviceSubClass=0, bDeviceProtocol=0, bMaxPacketSize0=64,
                     idVendor=VENDOR_ID, idProduct=PRODUCT_ID, bcdDevice=0x0100,
                     iManufacturer=1, iProduct=2, iSerialNumber=3, bNumConfigurations=1,
                     address=7, bus=1, port_number=2, port_numbers=(2,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        return _desc(bLength=9, bDescriptorType=2, wTotalLength=39, bNumInterfaces=1,
                     bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80,
                     bMaxPower=50, extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        if intf != 0 or alt != 0:
            raise IndexError("no such interface")
        return _desc(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
                     bNumEndpoints=3, bInterfaceClass=usbtmc.INTERFACE_CLASS,
                     bInterfaceSubClass=usbtmc.INTERFACE_SUBCLASS, bInterfaceProtocol=1,
                     iInterface=0, extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        addr, attrs = [(EP_OUT, 2), (EP_IN, 2), (EP_INT, 3)][ep]
        return _desc(bLength=7, bDescriptorType=5, bEndpointAddress=addr, bmAttributes=attrs,
                     wMaxPacketSize=512 if attrs == 2 else 8, bInterval=0 if attrs == 2 else 4,
                     bRefresh=0, bSynchAddress=0, extra_descriptors=[])

    # -- device handle ---------------------------------------------------------------------
    def open_device(self, dev):
        with self.lock:
            self._check()
            handle = id(self) ^ int(time.monotonic_ns())
            self._handles.add(handle)
            return handle

    def close_device(self, dev_handle):
        with self.lock:
            self._handles.discard(dev_handle)

    def set_configuration(self, dev_handle, config_value):
        self._check(dev_handle)

    def get_configuration(self, dev_handle):
        self._check(dev_handle)
        return 1

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        self._check(dev_handle)

    def claim_interface(self, dev_handle, intf):
        self._check(dev_handle)

    def release_interface(self, dev_handle, intf):
        pass

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        pass

    def clear_halt(self, dev_handle, ep):
        self._check(dev_handle)

    def reset_device(self, dev_handle):
        self._check(dev_handle)

    # -- control endpoint ------------------------------------------------------------------
    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        if bmRequestType == 0xA1 and bRequest == usbtmc.INITIATE_CLEAR:
            with self.lock:
                self._check(dev_handle)
                hung, stall = self._take("clear_timeout"), self._take("clear_stall")
            if hung:
                time.sleep((timeout or 1000) / 1000.0)
                raise usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                               errno=errno.ETIMEDOUT)
            if stall:
                raise usb.core.USBError("Pipe error", error_code=-9, errno=errno.EPIPE)
        with self.lock:
            self._check(dev_handle)
            reply = b""
            if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR string
                index = wValue & 0xFF
                if index == 0:
                    reply = bytes([4, 3, 0x09, 0x04])
                else:
                    text = STRINGS.get(index, "")
                    if index == 3:
                        text = self.serial_number
                    enc = text.encode("utf-16-le")
                    reply = bytes([2 + len(enc), 3]) + enc
            elif bmRequestType == 0xA1 and bRequest == usbtmc.INITIATE_CLEAR:
                self._out_buf.clear()
                self._responses.clear()
                self._read_request = None
                reply = bytes([usbtmc.STATUS_SUCCESS])
            elif bmRequestType == 0xA1 and bRequest == usbtmc.CHECK_CLEAR_STATUS:
                reply = bytes([usbtmc.STATUS_SUCCESS, 0])
            elif bmRequestType == 0xA1 and bRequest == usbtmc.GET_CAPABILITIES:
                reply = bytes([usbtmc.STATUS_SUCCESS, 0, 0x00, 0x01, 0, 0] + [0] * 18)
            else:
                raise usb.core.USBError("Pipe error", error_code=-9, errno=errno.EPIPE)
            if bmRequestType & 0x80:
                n = min(len(data), len(reply))
                data[:n] = array.array("B", reply[:n])
                return n
            return len(data)

    # -- bulk pipes ------------------------------------------------------------------------
    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        with self.lock:
            self._check(dev_handle)
            raw = bytes(data)
            if ep != EP_OUT or len(raw) < usbtmc.HEADER_LEN:
                raise usb.core.USBError("Pipe error", error_code=-9, errno=errno.EPIPE)
            msg_id, tag, tag_inv, size, attrs = usbtmc.parse_header(raw)
            if tag_inv != (~tag & 0xFF) or tag == 0:
                raise usb.core.USBError("Pipe error (bad bTag)", error_code=-9, errno=errno.EPIPE)
            if msg_id == usbtmc.DEV_DEP_MSG_OUT:
                self._out_buf += raw[usbtmc.HEADER_LEN : usbtmc.HEADER_LEN + size]
                if attrs & 1:
                    text, self._out_buf = self._out_buf.decode("ascii", "replace"), bytearray()
                    self._execute_message(text)
            elif msg_id == usbtmc.REQUEST_DEV_DEP_MSG_IN:
                self._read_request = (tag, size)
            else:
                raise usb.core.USBError("Pipe error (MsgID)", error_code=-9, errno=errno.EPIPE)
            return len(raw)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        deadline = time.monotonic() + (timeout or 1000) / 1000.0
        while True:
            with self.lock:
                self._check(dev_handle)
                if self._read_request is not None and self._responses:
                    tag, max_size = self._read_request
                    self._read_request = None
                    payload = self._responses.popleft()[:max_size]
                    frame = usbtmc.dev_dep_msg_in(tag, payload)
                    if self._take("no_reply"):
                        frame = b""
                    elif self._take("garble"):
                        frame = usbtmc.dev_dep_msg_in(tag ^ 0x5A, payload)
                        frame = bytes([0x7F]) + frame[1:]
                    elif self._take("partial"):
                        frame = frame[: usbtmc.HEADER_LEN + len(payload) // 2]
                        frame = frame[:8] + bytes([0]) + frame[9:]  # no EOM
                    if frame:
                        n = min(len(buff), len(frame))
                        buff[:n] = array.array("B", frame[:n])
                        return n
            if time.monotonic() >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                               errno=errno.ETIMEDOUT)
            time.sleep(0.002)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        time.sleep((timeout or 1000) / 1000.0)
        raise usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                       errno=errno.ETIMEDOUT)

    # -- SCPI ------------------------------------------------------------------------------
    def _execute_message(self, text: str) -> None:
        self.received.append(text)
        for unit in text.strip().split(";"):
            unit = unit.strip()
            if unit:
                self._execute(unit)

    @staticmethod
    def _match(token: str, mnemonic: str) -> bool:
        """SCPI mnemonic match: the short form is the upper-case part of ``mnemonic``."""
        token = token.upper()
        short = "".join(c for c in mnemonic if c.isupper() or c.isdigit())
        return token in (short, mnemonic.upper())

    def _path(self, header: str, *mnemonics: str) -> bool:
        parts = [re.sub(r"1$", "", p) for p in header.strip(":").split(":")]
        optional = [m.startswith("[") for m in mnemonics]
        names = [m.strip("[]") for m in mnemonics]
        i = 0
        for name, opt in zip(names, optional):
            if i < len(parts) and self._match(parts[i], name):
                i += 1
            elif not opt:
                return False
        return i == len(parts)

    def _error(self, code: int, text: str) -> None:
        self.errors.append((code, text))

    def _execute(self, unit: str) -> None:
        header, _, arg = unit.partition(" ")
        arg = arg.strip()
        query = header.endswith("?")
        header = header.rstrip("?")
        h = header.upper()
        if h == "*IDN" and query:
            self._responses.append(
                f"Thorlabs,DC2200,{self.serial_number},{self.firmware}\n".encode())
        elif h == "*RST":
            self.reset_state()
        elif h == "*CLS":
            self.errors.clear()
        elif self._path(header, "SYSTem", "ERRor", "[NEXT]") and query:
            if self.stuck_error is not None:
                code, msg = self.stuck_error
            else:
                code, msg = self.errors.popleft() if self.errors else (0, "No error")
            self._responses.append(f'{code:+d},"{msg}"\n'.encode())
        elif self._path(header, "[SOURce]", "MODe"):
            if query:
                self._responses.append(f"{self.mode}\n".encode())
            elif arg.upper() in ("CB", "CC", "PWM", "PULS", "INT", "TTL", "MOD"):
                self.mode = arg.upper()
            else:
                self._error(-224, "Illegal parameter value")
        elif self._path(header, "[SOURce]", "CBRightness", "BRIGhtness", "[LEVel]",
                        "[IMMediate]", "[AMPLitude]"):
            if query:
                self._responses.append(f"{self.brightness_percent:.6E}\n".encode())
                return
            try:
                value = float(arg)
            except ValueError:
                self._error(-224, "Illegal parameter value")
                return
            if not 0.0 <= value <= 100.0:
                self._error(-222, "Data out of range")
                return
            self.brightness_percent = value
        elif self._path(header, "OUTPut", "[STATe]"):
            if query:
                self._responses.append(b"1\n" if self.output_on else b"0\n")
                return
            if arg.upper() in ("ON", "1"):
                if not self.led_connected:
                    self._error(-241, "Hardware missing; LED head disconnected")
                    return
                self.output_on = True
            elif arg.upper() in ("OFF", "0"):
                self.output_on = False
            else:
                self._error(-224, "Illegal parameter value")
        else:
            self._error(-113, "Undefined header")


_SHARED: Dc2200Emulator | None = None


def get_backend() -> Dc2200Emulator:
    """pyusb backend-module convention (like ``usb.backend.libusb1.get_backend``): a config
    may name ``backend = "polrig.drivers.emulators.dc2200"`` to drive this emulator in-process."""
    global _SHARED
    if _SHARED is None:
        _SHARED = Dc2200Emulator()
    return _SHARED


def main(argv: list[str] | None = None) -> None:
    """A USB backend cannot be shared between processes: say how to use the emulator, and
    prove it answers by asking ``*IDN?`` through the real driver."""
    import argparse

    from polrig.drivers.dc2200 import Dc2200Light

    argparse.ArgumentParser(description="Emulated Thorlabs DC2200 (a pyusb backend). Point a "
                            "rig config at it with [light] driver = \"dc2200\", backend = "
                            "\"polrig.drivers.emulators.dc2200\" (in-process only).").parse_args(argv)
    with Dc2200Light(backend=get_backend()) as light:
        info = light.info()
        print(f"emulated {info.model} serial {info.serial} firmware {info.firmware}; use "
              f'backend = "polrig.drivers.emulators.dc2200" in the [light] table')


if __name__ == "__main__":
    main()
