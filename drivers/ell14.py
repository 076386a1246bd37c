"""Thorlabs Elliptec ELL14 rotation mount as a :class:`polrig.acquisition.hal.RotationStage`.

Protocol: Thorlabs "ELLx modules protocol manual" (Elliptec communication protocol):
RS-232 levels over the interface board's USB bridge, 9600 baud 8N1, no flow control,
multidrop addresses ``0``-``F``. Host packets ``<addr><cmd>[data]`` (lower-case command,
data as 8 upper-case hex digits, 32-bit two's complement), replies
``<addr><CMD><data>\\r\\n``. ``in`` -> ``IN`` (30 characters: type 2, serial 8, year 4,
firmware 2, hardware 2, travel 4 hex, pulses per travel 8 hex); ``gs`` -> ``GS`` (2 hex
status: 0 OK ... 9 busy ... 13 over current); ``gp`` -> ``PO``; ``ho<dir>``, ``ma``, ``mr``
reply ``PO`` when the motion has ended or ``GS<code>`` on error, after which the next
``gs`` repeats and clears the code. Field layout cross-checked with pylablib
``devices/Thorlabs/elliptec.py``. The pulses per degree come from the ``IN`` reply
(143360 pulses / 360 deg for an ELL14), never from a constant.

End of a motion: the ``PO`` reply, or a ``GS`` status reply (pylablib's elliptec.py takes
a ``GS`` answer to a move as its end too): ``GS00`` is a normal end, any other code but busy
is the device's error (:class:`DeviceFault`). ``GS09`` (busy) is the answer to one of this
driver's own ``gs`` polls (the motion goes on) or, when no poll is outstanding, the device's
answer to the move command itself: it refused the move because a motion was still running
(started by another program or an earlier ``polrig move --no-wait``): :class:`DeviceFault`
with code 9, never a success at the old motion's end position. When nothing arrives for a
while, :meth:`wait` asks ``gs`` itself (as :meth:`is_busy` does), so a lost ``PO`` does not
run into the timeout once the device reports it is idle; a motion that does not end within
:meth:`wait`'s timeout is stopped (``st``) before :class:`DeviceTimeout` is raised. ``st``
(stop) is likewise answered by ``PO`` or ``GS``; with no answer at all the device is asked
``gs``. A status that is not two hex digits is a :class:`ProtocolError` naming the reply, as
is an ``IN`` reply whose hex fields do not parse.

Angles: degrees in ``[0, 360)``; see ``docs/conventions.md`` for the stage zero axis
(``zero_offset_deg`` maps the device's home to the rig's zero axis).

Capabilities (:attr:`Ell14Stage.capabilities`, read on open): ``gv`` -> ``GV`` with two hex
digits, the velocity as a percentage of the maximum (ELLx protocol manual, "get velocity";
``sv`` sets it, 1..100 = 0x01..0x64); the ELL14's maximum speed is 430 deg/s (Thorlabs ELL14
specifications, "maximum rotation speed 430 deg/s"), so the axis declares ``430 * gv / 100``
deg/s. The piezo resonant motor reaches its speed at once (no acceleration ramp is
specified or settable): acceleration ``inf``. Travel: continuous rotation (no limits).
"""

from __future__ import annotations

import time

from polrig.acquisition.hal import AxisCapabilities, DeviceInfo, RotationStage
from polrig.drivers._serial import SerialDevice, SerialLink, wrap_deg
from polrig.errors import (
    DeviceDisconnected,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
)

BAUDRATE = 9600
#: ELL14 maximum rotation speed, deg/s (Thorlabs ELL14 specifications); ``gv`` is a
#: percentage of it
MAX_SPEED_DEG_S = 430.0
STATUS_TEXT = {
    0: "OK", 1: "communication time-out", 2: "mechanical time-out",
    3: "command error or not supported", 4: "value out of range", 5: "module isolated",
    6: "module out of isolation", 7: "initialising error", 8: "thermal error", 9: "busy",
    10: "sensor error", 11: "motor error", 12: "out of range", 13: "over current",
}
BUSY = 9
#: silence after which wait() asks ``gs`` whether the motion has ended
POLL_S = 0.25
#: how long an end-of-move ``PO`` may still come after the device reported idle
END_GRACE_S = 0.1
_HEX = frozenset("0123456789ABCDEFabcdef")


class Ell14Stage(SerialDevice, RotationStage):
    """An ELL14 on ``port`` at multidrop ``address`` (0-15).

    ``reply_timeout_s`` bounds every query (the manual allows about 100 ms per reply; a
    generous default covers slow USB bridges).
    """

    def __init__(self, port: str, address: int = 0, *, zero_offset_deg: float = 0.0,
                 reply_timeout_s: float = 1.0, kind: str = "stage"):
        if not 0 <= int(address) <= 15:
            raise ValueError(f"ELL14 address must be 0..15, got {address!r}")
        self.port = port
        self.address = f"{int(address):X}"
        self.zero_offset_deg = float(zero_offset_deg)
        self.reply_timeout_s = float(reply_timeout_s)
        self.kind = kind
        self._link = SerialLink(port, baudrate=BAUDRATE, device=f"ell14 {port}")
        self._info: DeviceInfo | None = None
        self.pulses_per_deg = 0.0
        self._move_pending = False
        self._move_cmd = ""  # the command that started the pending motion (ma, ho)
        self._polls = 0  # this driver's gs polls during the motion whose GS is not read yet
        self._caps: AxisCapabilities | None = None

    # -- life cycle ------------------------------------------------------------------------
    def _handshake(self) -> None:
        self._identify()
        self._caps = AxisCapabilities(speed_deg_s=MAX_SPEED_DEG_S * self.velocity_percent() / 100)

    @property
    def capabilities(self) -> AxisCapabilities:
        """Speed from the device's ``gv`` velocity (read on open), instant acceleration,
        continuous travel."""
        if self._caps is None:
            raise DeviceDisconnected("stage is not open (open it first)", device=self._link.device)
        return self._caps

    def velocity_percent(self) -> int:
        """``gv``: the velocity as a percentage (1..100) of the maximum speed."""
        payload = self._query("gv", "GV")
        if len(payload) != 2 or not set(payload) <= _HEX or not 0 < int(payload, 16) <= 100:
            raise ProtocolError(f"malformed velocity reply {self.address + 'GV' + payload!r} "
                                "(expected two hex digits, 01..64)", device=self._link.device)
        return int(payload, 16)

    def close(self) -> None:
        self._link.close()
        self._move_pending = False

    def info(self) -> DeviceInfo:
        if self._info is None:
            self._identify()
        assert self._info is not None
        return self._info

    def _identify(self) -> None:
        data = self._query("in", "IN")
        if len(data) != 30:
            raise ProtocolError(f"IN reply has {len(data)} characters, expected 30: {data!r}",
                                device=self._link.device)
        fields = {"type": data[0:2], "firmware": data[14:16], "travel": data[18:22],
                  "pulses": data[22:30]}
        bad = [f"{name} {text!r}" for name, text in fields.items()
               if not (text and set(text) <= _HEX)]
        if bad:
            raise ProtocolError(f"malformed IN reply {self.address + 'IN' + data!r}: "
                                f"{', '.join(bad)} not hexadecimal", device=self._link.device)
        dev_type, firmware, travel, pulses = (int(text, 16) for text in fields.values())
        if travel <= 0 or pulses <= 0:
            raise ProtocolError(f"IN reply gives travel {travel} and pulses {pulses}",
                                device=self._link.device)
        self.pulses_per_deg = pulses / travel
        self._info = DeviceInfo(
            kind=self.kind, driver="ell14", model=f"ELL{dev_type}", serial=data[2:10],
            firmware=f"{firmware}", port=self.port,
            extra={"year": data[10:14], "hardware": data[16:18], "travel": travel,
                   "pulses_per_travel": pulses, "address": self.address})

    # -- protocol --------------------------------------------------------------------------
    def _send(self, cmd: str, data: str = "") -> None:
        self._link.write(f"{self.address}{cmd}{data}".encode("ascii"))

    def _read_reply(self, timeout_s: float, stated_s: float | None = None) -> tuple[str, str]:
        raw = self._link.read_until(b"\r\n", timeout_s, what="ELL14 reply", stated_s=stated_s)
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self._resync()
            raise ProtocolError(f"garbled reply {raw!r}", device=self._link.device) from None
        if len(text) < 3 or text[0].upper() != self.address or not text[1:3].isupper():
            self._resync()
            raise ProtocolError(f"garbled reply {raw!r}", device=self._link.device)
        return text[1:3], text[3:]

    def _resync(self) -> None:
        time.sleep(0.05)
        self._link.discard_input()

    def _query(self, cmd: str, expect: str, data: str = "",
               timeout_s: float | None = None) -> str:
        """Send ``cmd`` and return the data of the ``expect`` reply; ``GS`` errors raise."""
        if not self._move_pending:
            self._link.discard_input()  # a late reply to an earlier, timed-out query
        self._send(cmd, data)
        reply, payload = self._read_reply(timeout_s or self.reply_timeout_s)
        if reply == expect:
            return payload
        if reply == "GS":
            self._raise_status(payload, cmd)
        raise ProtocolError(f"{cmd!r} answered {reply}{payload!r}, expected {expect}",
                            device=self._link.device)

    def _status_of(self, payload: str) -> int:
        """The code of a ``GS`` reply: two hex digits (ELLx protocol manual)."""
        if len(payload) != 2 or not set(payload) <= _HEX:
            raise ProtocolError(f"malformed status reply {self.address + 'GS' + payload!r} "
                                "(expected two hex digits)", device=self._link.device)
        return int(payload, 16)

    def _raise_status(self, payload: str, cmd: str) -> None:
        code = self._status_of(payload)
        if code == 0:
            return
        if code != BUSY:
            self._clear_error()
        raise DeviceFault(f"{cmd!r} failed", device=self._link.device, code=code,
                          text=STATUS_TEXT.get(code, "reserved"))

    def _clear_error(self) -> None:
        """The manual: the next ``gs`` repeats the error code and clears it."""
        try:
            self._send("gs")
            self._read_reply(self.reply_timeout_s)
        except (DeviceTimeout, ProtocolError):
            self._link.discard_input()

    def status_code(self) -> int:
        return self._status_of(self._query("gs", "GS"))

    # -- RotationStage ---------------------------------------------------------------------
    def _to_pulses(self, angle_deg: float) -> int:
        """Device position in ``[0, pulses per revolution)``."""
        per_rev = round(360.0 * self.pulses_per_deg)
        return round(wrap_deg(angle_deg + self.zero_offset_deg) * self.pulses_per_deg) % per_rev

    def _to_deg(self, pulses: int) -> float:
        return wrap_deg(pulses / self.pulses_per_deg - self.zero_offset_deg)

    @staticmethod
    def _signed(text: str) -> int:
        v = int(text, 16)
        return (v + 2**31) % 2**32 - 2**31

    def position_deg(self) -> float:
        if self._move_pending:
            self.is_busy()
        payload = self._query("gp", "PO")
        try:
            return self._to_deg(self._signed(payload))
        except ValueError:
            raise ProtocolError(f"malformed position {payload!r}", device=self._link.device) from None

    def home(self, timeout_s: float = 60.0) -> None:
        self._start("ho", "0")
        self.wait(timeout_s)

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None:
        angle_deg = float(angle_deg)
        if angle_deg != angle_deg or angle_deg in (float("inf"), float("-inf")):
            raise ValueError(f"stage angle must be finite, got {angle_deg!r}")
        self._link.in_waiting()  # not open: DeviceDisconnected (before any pulse arithmetic)
        if not self.pulses_per_deg:
            self._identify()
        self._start("ma", f"{self._to_pulses(angle_deg) % 2**32:08X}")
        if wait:
            self.wait(timeout_s)

    def _start(self, cmd: str, data: str) -> None:
        if self._move_pending and self.is_busy():
            raise DeviceFault(f"cannot start {cmd!r} while a motion is running",
                              device=self._link.device, code=BUSY, text=STATUS_TEXT[BUSY])
        if not self.pulses_per_deg:
            self._identify()
        self._link.discard_input()
        self._send(cmd, data)
        self._move_pending, self._move_cmd, self._polls = True, cmd, 0

    def _finish(self, reply: str, payload: str) -> bool:
        """Handle a reply that may end the pending motion; True if it ended it. ``PO`` and
        ``GS00`` end it; ``GS09`` (busy) answers an outstanding ``gs`` poll (the motion goes
        on) or, with none outstanding, the move command: the device refused it
        (DeviceFault, code 9); another ``GS`` code raises DeviceFault."""
        if reply == "PO":
            self._move_pending = False
            return True
        if reply == "GS":
            code = self._status_of(payload)
            if code == BUSY:
                if self._polls > 0:
                    self._polls -= 1
                    return False
                self._move_pending = False
                raise DeviceFault(f"{self._move_cmd!r} refused: the device is busy with a "
                                  "motion still running (another program, or a move started "
                                  "without waiting); stop it or wait for it to end",
                                  device=self._link.device, code=BUSY, text=STATUS_TEXT[BUSY])
            self._polls = max(self._polls - 1, 0)
            self._move_pending = False
            if code != 0:
                self._raise_status(payload, "move")
            return True
        return False

    def wait(self, timeout_s: float = 30.0) -> None:
        """Block until the pending motion ends (s). At ``timeout_s`` the motion is stopped
        (:meth:`stop`) and :class:`DeviceTimeout` raised; a stop that fails too is named in
        it (the mount may still be turning)."""
        deadline = time.monotonic() + timeout_s
        while self._move_pending:
            left = deadline - time.monotonic()
            if left <= 0:
                raise self.stopped_after_timeout(f"motion did not end within {timeout_s:g} s", self._link.device)
            try:
                try:
                    reply, payload = self._read_reply(min(left, POLL_S))
                except DeviceTimeout:
                    try:
                        self.is_busy()  # silence: ask the device (its PO may have been lost)
                    except DeviceTimeout:
                        pass  # no status either: keep waiting until the deadline
                    continue
                self._finish(reply, payload)
            except ProtocolError:
                # A corrupted reply may have been the end of the move: ask the device where
                # it is next time instead of waiting for an end that may have passed.
                self._move_pending = False
                raise

    def is_busy(self) -> bool:
        if not self._move_pending:
            return self.status_code() == BUSY
        self._send("gs")
        self._polls += 1
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            reply, payload = self._read_reply(max(deadline - time.monotonic(), 0.0),
                                              stated_s=self.reply_timeout_s)
            if reply == "GS":
                self._polls = max(self._polls - 1, 0)
                code = self._status_of(payload)
                if code == BUSY:
                    return True
                if code != 0:
                    self._move_pending = False
                    self._raise_status(payload, "move")
                # GS00 while the end-of-move PO has not been read yet: read it
                if self._move_pending:
                    self._read_move_end()
                return False
            self._finish(reply, payload)

    def _read_move_end(self) -> None:
        """The device says it is idle: take its end-of-move reply if it comes (it may have
        been lost on the line, which is not an error once the device reports idle)."""
        try:
            reply, payload = self._read_reply(min(self.reply_timeout_s, END_GRACE_S))
            self._finish(reply, payload)
        except DeviceTimeout:
            pass
        finally:
            self._move_pending = False

    def stop(self) -> None:
        """``st``: the device answers ``PO`` (or a ``GS`` status) once stopped; ``GS09``
        (still decelerating) waits for the next reply, another error code raises
        DeviceFault. With no answer at all, ``gs`` decides: idle is stopped, busy raises
        DeviceTimeout."""
        self._link.discard_input()
        self._send("st")
        deadline = time.monotonic() + self.reply_timeout_s
        try:
            while True:
                try:
                    reply, payload = self._read_reply(max(deadline - time.monotonic(), 0.0),
                                                      stated_s=self.reply_timeout_s)
                except DeviceTimeout:
                    if self._query_status_after_stop() == BUSY:
                        raise DeviceTimeout("the motor still runs after 'st' (no answer "
                                            f"within {self.reply_timeout_s:g} s)",
                                            device=self._link.device) from None
                    break
                if reply == "PO":
                    break
                if reply == "GS":
                    code = self._status_of(payload)
                    if code == 0:
                        break
                    if code != BUSY:
                        self._raise_status(payload, "st")
        finally:
            self._move_pending = False
        self._link.discard_input()

    def _query_status_after_stop(self) -> int:
        self._send("gs")
        reply, payload = self._read_reply(self.reply_timeout_s)
        if reply != "GS":
            raise ProtocolError(f"'gs' answered {reply}{payload!r}", device=self._link.device)
        code = self._status_of(payload)
        if code not in (0, BUSY):
            self._raise_status(payload, "st")
        return code
