"""Serial-port transport shared by the serial drivers (ELL14, K10CR1, GRBL).

A thin layer over pyserial that turns every transport failure into a typed polrig error and
gives every read a deadline: :class:`polrig.errors.DeviceNotFound` when the port cannot be
opened, :class:`DeviceTimeout` when nothing arrives in time, :class:`ProtocolError` when a
reply starts but never completes (partial reply), :class:`DeviceDisconnected` when the port
goes away (the port is then closed, so it is released to the operating system).

A reply that has started when the deadline passes is not cut off: it may go on as long as
its bytes keep coming, each within an inter-byte timeout of the previous one (64 character
times at the line rate, at least 0.1 s: a USB bridge delivers a reply in chunks up to its
latency timer, 16 ms on FTDI chips, apart). Only a reply that stops mid-way for longer is a
partial reply. Without this grace a reply whose first byte arrived just before the deadline
was reported as partial although the rest was already in the buffer. Likewise bytes already
waiting in the input buffer when the deadline passes arrived in time: they are read, not
reported missing.

Ports are opened with ``exclusive=True`` (pyserial: ``TIOCEXCL`` plus an advisory ``flock``)
so two programs never talk to one device at once. Reference: pyserial 3.5 API documentation
(``serial.Serial``), https://pyserial.readthedocs.io/en/latest/pyserial_api.html.
"""

from __future__ import annotations

import termios
import time

import serial

from polrig.errors import (
    DeviceDisconnected,
    DeviceNotFound,
    DeviceTimeout,
    ProtocolError,
)

# what pyserial lets through when a port vanishes (tcdrain raises termios.error, not OSError)
_LOST = (serial.SerialException, OSError, termios.error)

# Inter-byte timeout of a reply that has started: this many character times (10 bits each,
# 8N1) at the line rate, and never less than MIN_INTER_BYTE_S.
INTER_BYTE_CHARS = 64
MIN_INTER_BYTE_S = 0.1


class _ReplyClock:
    """Deadline of one read: ``timeout_s`` for the reply to start; once bytes have come, the
    read only expires after the deadline *and* ``inter_byte_s`` without a new byte.
    ``started``: the reply began before this read (e.g. the data after a frame header)."""

    def __init__(self, timeout_s: float, inter_byte_s: float, started: bool = False):
        now = time.monotonic()
        self.deadline = now + timeout_s
        self.inter_byte_s = inter_byte_s
        self.last_byte: float | None = now if started else None

    def got(self, n: int) -> None:
        if n:
            self.last_byte = time.monotonic()

    def expired(self) -> bool:
        now = time.monotonic()
        if now <= self.deadline:
            return False
        return self.last_byte is None or now - self.last_byte > self.inter_byte_s


class SerialLink:
    """One serial port with deadline-bounded reads.

    ``device`` names the device in error messages (e.g. ``"ell14 /dev/ttyUSB0"``).
    """

    def __init__(self, port: str, *, baudrate: int, device: str, rtscts: bool = False,
                 poll_s: float = 0.02, inter_byte_s: float | None = None):
        self.port = port
        self.baudrate = baudrate
        self.device = device
        self.rtscts = rtscts
        self._poll_s = poll_s
        # how long a started reply may pause between bytes once the deadline has passed
        self.inter_byte_s = (float(inter_byte_s) if inter_byte_s is not None
                             else max(MIN_INTER_BYTE_S, INTER_BYTE_CHARS * 10.0 / baudrate))
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
            raise DeviceDisconnected("port is not open (open the device first)",
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

    def read_exact(self, n: int, timeout_s: float, what: str = "reply", *,
                   started: bool = False, stated_s: float | None = None) -> bytes:
        """Read exactly ``n`` bytes: they must start before ``timeout_s`` runs out, and a
        reply that has started may finish within the inter-byte timeout after that.
        ``started=True``: these bytes continue a reply already under way (the data after a
        frame header), so they get the inter-byte timeout even when ``timeout_s`` is spent.
        ``stated_s``: the timeout error messages name (default ``timeout_s``); a caller that
        reads several messages against one deadline passes its configured timeout, so the
        message does not show the few milliseconds that were left."""
        ser = self._require()
        clock = _ReplyClock(timeout_s, self.inter_byte_s, started)
        buf = bytearray()
        shown = timeout_s if stated_s is None else stated_s
        while len(buf) < n:
            self._read_step(ser, clock, buf, n - len(buf), shown, what)
        return bytes(buf)

    def read_until(self, terminator: bytes, timeout_s: float, what: str = "reply",
                   max_len: int = 4096, *, stated_s: float | None = None) -> bytes:
        """Read up to and including ``terminator``; return the bytes without it. The reply
        must start before ``timeout_s`` runs out (the inter-byte timeout lets a started one
        finish). ``stated_s``: the timeout error messages name (see :meth:`read_exact`)."""
        ser = self._require()
        clock = _ReplyClock(timeout_s, self.inter_byte_s)
        buf = bytearray()
        shown = timeout_s if stated_s is None else stated_s
        while not buf.endswith(terminator):
            if len(buf) > max_len:
                raise ProtocolError(f"{what}: no terminator after {len(buf)} bytes",
                                    device=self.device)
            self._read_step(ser, clock, buf, 1, shown, what)  # never past the terminator
        return bytes(buf[: -len(terminator)])

    def _read_step(self, ser: serial.Serial, clock: _ReplyClock, buf: bytearray, size: int,
                   timeout_s: float, what: str) -> None:
        """One step of a deadline-bounded read: append up to ``size`` bytes to ``buf`` (the
        port's read blocks at most ``poll_s``), or raise once ``clock`` has expired and
        nothing is waiting in the input buffer (bytes already there arrived in time)."""
        try:
            if clock.expired() and not ser.in_waiting:
                self._raise_incomplete(bytes(buf), timeout_s, what)
            chunk = ser.read(size)
        except _LOST as exc:
            raise self._lost(exc) from None
        clock.got(len(chunk))
        buf += chunk

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
