"""Thorlabs DC2200 LED driver as the rig's point light (:class:`polrig.acquisition.hal.Light`).

Transport: USB-TMC through pyusb (no VISA): vendor 0x1313, product 0x80C8, the USBTMC
interface (class 0xFE, subclass 0x03) with one bulk-OUT and one bulk-IN endpoint. Framing
per the USB-IF "USB Test and Measurement Class Specification" 1.0 (see
:mod:`polrig.drivers.usbtmc`): commands go out as ``DEV_DEP_MSG_OUT``; a query is followed by
``REQUEST_DEV_DEP_MSG_IN`` and a bulk-IN read of ``DEV_DEP_MSG_IN`` (header checked: MsgID,
bTag and its inverse, transfer size, EOM). After a timeout or a malformed reply the pipes are
cleared with INITIATE_CLEAR / CHECK_CLEAR_STATUS and a CLEAR_FEATURE(ENDPOINT_HALT) on
bulk-OUT, as the spec's section 4.2.1.6 prescribes, so the next command works.

SCPI (Thorlabs DC2200 operation manual, SCPI command reference; IEEE 488.2; ``*IDN?``,
``SOURCE1:MODE`` and ``OUTPUT1:STATE`` as in Thorlabs' own example
``Current_And_Temperature_Controller_Examples``, ``Python/DC2200 LED Controllers/DC2200 with
PyVISA.py``, which does not use the constant-brightness mode; ``SOURCE1:MODE CB`` and
``SOURCE1:CBRIGHTNESS:BRIGHTNESS`` as independent public DC2200 control code sends them, the
long forms of ``SOURce1:MODe CB`` and ``SOURce1:CBRightness:BRIGhtness``; not checked against
the manual's own pages here): ``*IDN?``,
``*CLS``, ``SOURCE1:MODE CB`` (constant brightness), ``SOURCE1:CBRIGHTNESS:BRIGHTNESS
<percent>``, ``OUTPUT1:STATE ON|OFF``; after every setting the error queue is read with
``SYST:ERR?`` and a non-zero entry raises :class:`polrig.errors.DeviceFault` with the
device's code and text. ``level`` in [0, 1] maps to brightness percent = 100 * level.
The queue is then drained so the next command starts clean, but never without bound: an
IEEE 488.2 / SCPI error queue is finite (SCPI-1999 vol. 2, ``SYSTem:ERRor[:NEXT]?``: a
first-in first-out queue of fixed size whose last entry becomes -350 "Queue overflow" when
it is full), so a device that still answers errors after :data:`MAX_ERROR_READS` reads, or
after the driver's timeout, is reported with the errors read instead of being asked
forever.

Control requests that fail while opening (INITIATE_CLEAR / CHECK_CLEAR_STATUS time out or
stall) are typed too: a timeout is :class:`DeviceTimeout`, a stall (the device does not
take the USBTMC class request) :class:`DeviceNotFound`, a vanished device
:class:`DeviceDisconnected`.

``backend`` may be a pyusb backend object or the name of a module with ``get_backend()``
(pyusb's convention, e.g. ``"usb.backend.libusb1"`` or the emulator
``"polrig.drivers.emulators.dc2200"``); ``None`` lets pyusb pick libusb.
"""

from __future__ import annotations

import errno
import importlib
import time
from typing import Any

import usb.core
import usb.util

from polrig.acquisition.hal import DeviceInfo, Light, check_level
from polrig.drivers import usbtmc
from polrig.errors import (
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

VENDOR_ID, PRODUCT_ID = 0x1313, 0x80C8
#: most ``SYST:ERR?`` reads after a setting (the first error included)
MAX_ERROR_READS = 32


def resolve_backend(backend: Any):
    if backend is None or not isinstance(backend, str):
        return backend
    try:
        module = importlib.import_module(backend)
    except ImportError as exc:
        raise DeviceNotFound(f"pyusb backend module {backend!r} cannot be imported: {exc}",
                             device="dc2200") from None
    get_backend = getattr(module, "get_backend", None)
    if not callable(get_backend):
        raise DeviceNotFound(f"{backend!r} is no pyusb backend module (it has no get_backend(); "
                             f"e.g. usb.backend.libusb1)", device="dc2200")
    be = get_backend()
    if be is None:
        raise DeviceNotFound(f"pyusb backend {backend!r} is not available on this system",
                             device="dc2200")
    return be


class Dc2200Light(Light):
    """A DC2200 selected by USB serial number (``None``: the only one attached)."""

    def __init__(self, serial: str | None = None, *, backend: Any = None,
                 timeout_s: float = 1.0, kind: str = "light"):
        self.serial = serial or None
        self.backend_spec = backend
        self.timeout_s = float(timeout_s)
        self.kind = kind
        self._dev: usb.core.Device | None = None
        self._ep_out = self._ep_in = None
        self._intf = 0
        self._tag = 0
        self._info: DeviceInfo | None = None
        self.name = f"dc2200 {serial}" if serial else "dc2200"

    # -- life cycle ------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._dev is not None

    def open(self) -> None:
        if self._dev is not None:
            return
        backend = resolve_backend(self.backend_spec)
        try:
            found = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID,
                                       backend=backend))
        except usb.core.NoBackendError:
            raise DeviceNotFound("no pyusb backend (install libusb)", device=self.name) from None
        except usb.core.USBError as exc:
            raise DeviceNotFound(f"USB enumeration failed: {exc}", device=self.name) from None
        if self.serial:
            found = [d for d in found if self._serial_of(d) == self.serial]
        if not found:
            what = f"serial {self.serial}" if self.serial else "any serial"
            raise DeviceNotFound(f"no DC2200 (USB {VENDOR_ID:04x}:{PRODUCT_ID:04x}, {what}) "
                                 "attached", device=self.name)
        if len(found) > 1:
            raise DeviceNotFound(f"{len(found)} DC2200 attached: name one by serial in the "
                                 "config", device=self.name)
        dev = found[0]
        try:
            try:
                if dev.is_kernel_driver_active(0):  # e.g. the Linux usbtmc module holds it
                    dev.detach_kernel_driver(0)
            except NotImplementedError:  # backends without kernel-driver control
                pass
            dev.set_configuration()
            intf = usb.util.find_descriptor(dev.get_active_configuration(),
                                            bInterfaceClass=usbtmc.INTERFACE_CLASS,
                                            bInterfaceSubClass=usbtmc.INTERFACE_SUBCLASS)
            if intf is None:
                raise DeviceNotFound("device has no USBTMC interface", device=self.name)
            usb.util.claim_interface(dev, intf)
            bulk = [e for e in intf if usb.util.endpoint_type(e.bmAttributes)
                    == usb.util.ENDPOINT_TYPE_BULK]
            self._ep_out = next(e for e in bulk if usb.util.endpoint_direction(
                e.bEndpointAddress) == usb.util.ENDPOINT_OUT)
            self._ep_in = next(e for e in bulk if usb.util.endpoint_direction(
                e.bEndpointAddress) == usb.util.ENDPOINT_IN)
            self._intf = intf.bInterfaceNumber
        except usb.core.USBError as exc:
            usb.util.dispose_resources(dev)
            raise DeviceNotFound(f"cannot configure the USB device: {exc}", device=self.name) from None
        self._dev = dev
        try:
            try:
                self._clear()
            except usb.core.USBError as exc:
                raise self._control_error(exc, "clearing the USBTMC pipes (INITIATE_CLEAR)") \
                    from None
            idn = self.query("*IDN?")
            parts = [p.strip() for p in idn.split(",")]
            if len(parts) < 4 or "DC2200" not in parts[1]:
                raise ProtocolError(f"unexpected *IDN? answer {idn!r}", device=self.name)
            self._info = DeviceInfo(kind=self.kind, driver="dc2200", model=parts[1],
                                    serial=parts[2], firmware=parts[3],
                                    port=f"usb {dev.bus}:{dev.address}",
                                    extra={"manufacturer": parts[0]})
            self.command("*CLS")
            self.command("SOURCE1:MODE CB")
        except Exception:
            self.close()
            raise

    @staticmethod
    def _serial_of(dev) -> str | None:
        try:
            return dev.serial_number
        except (usb.core.USBError, ValueError):
            return None

    def close(self) -> None:
        dev, self._dev = self._dev, None
        if dev is not None:
            try:
                usb.util.release_interface(dev, self._intf)
            except (usb.core.USBError, ValueError):
                pass
            usb.util.dispose_resources(dev)

    def info(self) -> DeviceInfo:
        if self._info is None:
            raise DeviceDisconnected("device is not open (open it first)", device=self.name)
        return self._info

    # -- USBTMC ----------------------------------------------------------------------------
    def _next_tag(self) -> int:
        self._tag = self._tag % 255 + 1
        return self._tag

    def _usb_error(self, exc: usb.core.USBError, what: str) -> Exception:
        if isinstance(exc, usb.core.USBTimeoutError) or exc.errno == errno.ETIMEDOUT:
            self._recover()
            return DeviceTimeout(f"{what}: no answer within {self.timeout_s:g} s", device=self.name)
        if exc.errno in (errno.ENODEV, errno.EIO) or exc.backend_error_code == -4:
            self.close()
            return DeviceDisconnected(f"{what}: USB device went away ({exc})", device=self.name)
        self._recover()
        return ProtocolError(f"{what}: USB transfer failed ({exc})", device=self.name)

    def _control_error(self, exc: usb.core.USBError, what: str) -> Exception:
        """A class control request failed while opening: typed, and never retried (a
        recovery would send the same request again)."""
        if isinstance(exc, usb.core.USBTimeoutError) or exc.errno == errno.ETIMEDOUT:
            return DeviceTimeout(f"{what}: no answer within {self.timeout_s:g} s (device hung? "
                                 "unplug it and plug it in again)", device=self.name)
        if exc.errno in (errno.ENODEV, errno.EIO) or exc.backend_error_code == -4:
            return DeviceDisconnected(f"{what}: USB device went away ({exc})", device=self.name)
        return DeviceNotFound(f"{what}: the device refused the USBTMC request ({exc}); it "
                              "does not work as a USBTMC instrument", device=self.name)

    def _require(self) -> usb.core.Device:
        if self._dev is None:
            raise DeviceDisconnected("device is not open (open it again)", device=self.name)
        return self._dev

    def _write(self, text: str) -> None:
        dev = self._require()
        frame = usbtmc.dev_dep_msg_out(self._next_tag(), text.encode("ascii") + b"\n")
        try:
            dev.write(self._ep_out.bEndpointAddress, frame, timeout=int(self.timeout_s * 1000))
        except usb.core.USBError as exc:
            raise self._usb_error(exc, f"sending {text!r}") from None

    def _read(self, what: str, max_size: int = 1024) -> str:
        dev = self._require()
        tag = self._next_tag()
        ms = int(self.timeout_s * 1000)
        try:
            dev.write(self._ep_out.bEndpointAddress, usbtmc.request_dev_dep_msg_in(tag, max_size),
                      timeout=ms)
            raw = bytes(dev.read(self._ep_in.bEndpointAddress,
                                 max_size + usbtmc.HEADER_LEN + 3, timeout=ms))
        except usb.core.USBError as exc:
            raise self._usb_error(exc, what) from None
        if len(raw) < usbtmc.HEADER_LEN:
            self._recover()
            raise ProtocolError(f"{what}: {len(raw)}-byte USBTMC transfer", device=self.name)
        msg_id, rtag, rtag_inv, size, attrs = usbtmc.parse_header(raw)
        if msg_id != usbtmc.DEV_DEP_MSG_IN or rtag != tag or rtag_inv != (~tag & 0xFF):
            self._recover()
            raise ProtocolError(f"{what}: bad USBTMC header {raw[:12].hex(' ')} (expected "
                                f"DEV_DEP_MSG_IN with bTag {tag})", device=self.name)
        payload = raw[usbtmc.HEADER_LEN : usbtmc.HEADER_LEN + size]
        if len(payload) < size or not attrs & 1:
            self._recover()
            raise ProtocolError(f"{what}: partial reply, {len(payload)} of {size} bytes"
                                f"{'' if attrs & 1 else ', no end of message'}", device=self.name)
        return payload.decode("ascii", "replace").strip()

    def _clear(self) -> None:
        """USBTMC INITIATE_CLEAR + CHECK_CLEAR_STATUS, then clear the bulk-OUT halt."""
        dev = self._require()
        ms = int(self.timeout_s * 1000)
        status = dev.ctrl_transfer(0xA1, usbtmc.INITIATE_CLEAR, 0, self._intf, 1, timeout=ms)
        if status[0] == usbtmc.STATUS_SUCCESS:
            for _ in range(50):
                check = dev.ctrl_transfer(0xA1, usbtmc.CHECK_CLEAR_STATUS, 0, self._intf, 2,
                                          timeout=ms)
                if check[0] != usbtmc.STATUS_PENDING:
                    break
        dev.clear_halt(self._ep_out.bEndpointAddress)

    def _recover(self) -> None:
        try:
            self._clear()
        except (usb.core.USBError, DeviceDisconnected):
            pass

    # -- SCPI ------------------------------------------------------------------------------
    def query(self, text: str) -> str:
        self._write(text)
        return self._read(f"reply to {text!r}")

    def command(self, text: str) -> None:
        """Send a setting, then read the error queue; a device error raises DeviceFault."""
        self._write(text)
        self.check_error(text)

    def _next_error(self) -> tuple[int, str]:
        """One ``SYST:ERR?`` entry: ``(code, text)``; code 0 is "No error"."""
        answer = self.query("SYST:ERR?")
        code_s, _, msg = answer.partition(",")
        try:
            code = int(code_s)
        except ValueError:
            raise ProtocolError(f"malformed SYST:ERR? answer {answer!r}", device=self.name) from None
        return code, msg.strip().strip('"')

    def check_error(self, context: str = "") -> None:
        """Read the error queue; an error raises DeviceFault with the first entry's code and
        text. The rest of the queue is drained (at most :data:`MAX_ERROR_READS` reads and
        ``timeout_s``; see the module docstring) so the next command starts clean."""
        code, text = self._next_error()
        if code == 0:
            return
        errors = [(code, text)]
        deadline = time.monotonic() + self.timeout_s
        while True:
            if len(errors) >= MAX_ERROR_READS or time.monotonic() > deadline:
                shown = "; ".join(f"{c} {t!r}" for c, t in dict.fromkeys(errors))
                raise DeviceFault(f"{context!r} failed, and the error queue did not empty "
                                  f"after {len(errors)} reads of SYST:ERR? (errors read: "
                                  f"{shown}); is the device stuck in an error state?",
                                  device=self.name, code=code, text=text)
            more = self._next_error()
            if more[0] == 0:
                break
            errors.append(more)
        extra = (f"; {len(errors) - 1} more in the queue: "
                 + "; ".join(f"{c} {t!r}" for c, t in errors[1:])) if len(errors) > 1 else ""
        raise DeviceFault((f"{context!r} failed" if context else "device error") + extra,
                          device=self.name, code=code, text=text)

    # -- Light -----------------------------------------------------------------------------
    def set_on(self, on: bool) -> None:
        self.command(f"OUTPUT1:STATE {'ON' if on else 'OFF'}")

    def set_level(self, level: float) -> None:
        level = check_level(level)
        self.command(f"SOURCE1:CBRIGHTNESS:BRIGHTNESS {100.0 * level:.4f}")

    def status(self) -> dict[str, Any]:
        on = self.query("OUTPUT1:STATE?")
        brightness = self.query("SOURCE1:CBRIGHTNESS:BRIGHTNESS?")
        mode = self.query("SOURCE1:MODE?")
        try:
            level = float(brightness) / 100.0
        except ValueError:
            raise ProtocolError(f"malformed brightness {brightness!r}", device=self.name) from None
        return {"on": on.strip() in ("1", "ON"), "level": level, "mode": mode,
                "brightness_percent": float(brightness)}
