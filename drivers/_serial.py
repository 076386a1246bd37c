"""Serial-port transport shared by the serial drivers (ELL14, K10CR1, GRBL).

A thin layer over pyserial that turns every transport failure into a typed polrig error and
gives every read a deadline: :class:`polrig.errors.DeviceNotFound` when the port cannot be
opened, :class:`DeviceTimeout` when nothing arrives in time, :class:`ProtocolError` when a
reply starts but never completes (partial reply), :class:`DeviceDisconnected` when the port
goes away (the port is then closed, so it is released to the operating system).

Ports are opened with ``exclusive=True`` (pyserial: ``TIOCEXCL`` plus an advisory ``flock``)
so two programs never talk to one device at once. Reference: pyserial 3.5 API documentation
(``serial.Serial``), https://pyserial.readthedocs.io/en/latest/pyserial_api.html.
"""

from __future__ import annotations

import termios
import time

import serial

from polrig.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout, ProtocolError

# what pyserial lets through when a port vanishes (tcdrain raises termios.error, not OSError)
_LOST = (serial.SerialException, OSError, termios.error)


class SerialLink:
    """One serial port with deadline-bounded reads.

    ``device`` names the device in error messages (e.g. ``"ell14 /dev/ttyUSB0"``).
    """

    def __init__(self, port: str, *, baudrate: int, device: str, rtscts: bool = False,
                 poll_s: float = 0.02):
        self.port = port
        self.baudrate = baudrate
        self.device = device
        self.rtscts = rtscts
        self._poll_s = poll_s
        self._ser: serial.Serial | None = None

    @property
    def is_open(self) -> bool:
        return self._ser is not None and self._ser.is_open

    def open(self) -> None:
        if self.is_open:
            return
        try:
            self._ser = serial.Serial(self.port, self.baudrate, bytesize=8, parity="N",
                                      stopbits=1, rtscts=self.rtscts, timeout=self._poll_s,
                                      write_timeout=2.0, exclusive=True)
        except (*_LOST, ValueError) as exc:
            self._ser = None
            raise DeviceNotFound(f"cannot open serial port {self.port}: {exc}",
                                 device=self.device) from None

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except _LOST:
                pass

    def _require(self) -> serial.Serial:
        if self._ser is None:
            raise DeviceDisconnected("port is not open (open the device again)",
                                     device=self.device)
        return self._ser

    def _lost(self, exc: Exception) -> DeviceDisconnected:
        self.close()
        return DeviceDisconnected(f"serial port {self.port} went away: {exc}", device=self.device)

    def write(self, data: bytes) -> None:
        ser = self._require()
        try:
            ser.write(data)
            ser.flush()
        except serial.SerialTimeoutException:
            raise DeviceTimeout(f"write of {len(data)} bytes did not complete (flow control "
                                "holding the line?)", device=self.device) from None
        except _LOST as exc:
            raise self._lost(exc) from None

    def discard_input(self) -> bytes:
        """Drop (and return) whatever is waiting in the input buffer."""
        ser = self._require()
        try:
            n = ser.in_waiting
            return ser.read(n) if n else b""
        except _LOST as exc:
            raise self._lost(exc) from None

    def in_waiting(self) -> int:
        ser = self._require()
        try:
            return ser.in_waiting
        except _LOST as exc:
            raise self._lost(exc) from None

    def read_exact(self, n: int, timeout_s: float, what: str = "reply") -> bytes:
        """Read exactly ``n`` bytes before ``timeout_s`` runs out."""
        ser = self._require()
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while len(buf) < n:
            if time.monotonic() > deadline:
                self._raise_incomplete(bytes(buf), timeout_s, what)
            try:
                buf += ser.read(n - len(buf))
            except _LOST as exc:
                raise self._lost(exc) from None
        return bytes(buf)

    def read_until(self, terminator: bytes, timeout_s: float, what: str = "reply",
                   max_len: int = 4096) -> bytes:
        """Read up to and including ``terminator``; return the bytes without it."""
        ser = self._require()
        deadline = time.monotonic() + timeout_s
        buf = bytearray()
        while not buf.endswith(terminator):
            if time.monotonic() > deadline:
                self._raise_incomplete(bytes(buf), timeout_s, what)
            if len(buf) > max_len:
                raise ProtocolError(f"{what}: no terminator after {len(buf)} bytes",
                                    device=self.device)
            try:
                chunk = ser.read(1)
            except _LOST as exc:
                raise self._lost(exc) from None
            buf += chunk
        return bytes(buf[: -len(terminator)])

    def _raise_incomplete(self, got: bytes, timeout_s: float, what: str) -> None:
        if got:
            raise ProtocolError(f"{what}: partial reply {got!r} (incomplete after "
                                f"{timeout_s:g} s)", device=self.device)
        raise DeviceTimeout(f"no {what} within {timeout_s:g} s", device=self.device)


class SerialDevice:
    """Life cycle shared by the serial drivers (mixed in before the HAL class).

    ``open`` opens the link, discards stale input, then runs the driver's ``_handshake``
    (identify, enable, reset, ...); if the handshake fails the port is released again before
    the error propagates, so a failed open never leaves the port held.
    """

    _link: SerialLink

    @property
    def is_open(self) -> bool:
        return self._link.is_open

    def open(self) -> None:
        self._link.open()
        try:
            self._link.discard_input()
            self._handshake()
        except BaseException:
            self._link.close()
            raise

    def _handshake(self) -> None:
        raise NotImplementedError


def wrap_deg(angle_deg: float) -> float:
    """``angle_deg`` wrapped into ``[0, 360)`` (``x % 360`` alone returns 360.0 for tiny
    negative ``x``)."""
    w = angle_deg % 360.0
    return 0.0 if w >= 360.0 else w
