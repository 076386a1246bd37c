"""Emulator of a Thorlabs Elliptec ELL14 rotation mount on a pseudo-terminal.

Speaks the ELLx ASCII protocol (Thorlabs "ELLx modules protocol manual", Elliptec
communication protocol, issue 7+; cross-checked with pylablib ``devices/Thorlabs/elliptec.py``):
host packets ``<addr><cmd>[data]`` with a hex address ``0``-``F`` and lower-case commands,
no terminator; replies ``<addr><CMD><data>\\r\\n`` with upper-case commands. Implemented:
``in`` (-> ``IN`` 30 characters: type, serial, year, firmware, hardware, travel, pulses),
``gs`` (-> ``GS`` 2 hex status), ``gp`` (-> ``PO`` 8 hex, 32-bit two's complement),
``ho<dir>`` and ``ma``/``mr`` (reply ``PO`` when the motion ends, ``GS<code>`` on error),
``st`` (stop), ``gv``/``sv`` (velocity percent), ``go``/``so`` (home offset, ``HO``),
``gj``/``sj`` (jog step, ``GJ``), ``fw``/``bw`` (jog). Status codes: 0 OK, 1 communication
time-out, 2 mechanical time-out, 3 command error or not supported, 4 value out of range,
5 module isolated, 6 module out of isolation, 7 initialising error, 8 thermal error, 9 busy,
10 sensor error, 11 motor error, 12 out of range, 13 over current. An error code is
reported once more by the next ``gs`` (then cleared), as the manual describes.

ELL14: 143360 pulses per revolution (``IN`` travel 0x0168 = 360 deg, pulses 0x00023000),
maximum speed about 430 deg/s.

Faults: see :mod:`polrig.drivers.emulators._pty`; ``bad_status``: the next ``GS`` reply carries a
status that is not two hex digits (``GSQQ``); ``lost_end``: the reply that ends the next
move is lost on the line (other replies, e.g. to ``gs`` during the move, still come). Reply variants a driver must accept (pylablib's
elliptec.py takes a ``GS`` reply to a move as its end): ``end_with_status`` ends moves with
``GS00`` instead of ``PO``; ``stop_reply`` answers ``st`` with ``"PO"`` (default), ``"GS"``
(the status, ``GS00`` once stopped) or ``None`` (no answer).
"""

from __future__ import annotations

import time

from polrig.drivers.emulators._pty import LinearMove, PtyEmulator, run_cli

PULSES_PER_REV = 143360
MAX_SPEED_DEG_S = 430.0
_DATA_LEN = {"in": 0, "gs": 0, "gp": 0, "ho": 1, "ma": 8, "mr": 8, "st": 0, "gv": 0,
             "sv": 2, "go": 0, "so": 8, "gj": 0, "sj": 8, "fw": 0, "bw": 0, "us": 0}


def _hex32(value: int) -> str:
    return f"{value % 2**32:08X}"


def _signed32(text: str) -> int:
    v = int(text, 16)
    return (v + 2**31) % 2**32 - 2**31


class Ell14Emulator(PtyEmulator):
    name = "ell14"
    FAULTS = PtyEmulator.FAULTS + ("bad_status", "lost_end")

    def __init__(self, *, address: int = 0, serial_number: str = "11400123",
                 link=None, speed_factor: float = 1.0):
        super().__init__(link=link, speed_factor=speed_factor)
        self.address = f"{address:X}"
        self.serial_number = serial_number
        self.position_pulses = 0.0
        self.velocity_percent = 100
        self.home_offset = 0
        self.jog_step = PULSES_PER_REV // 360
        self.pending_error = 0  # error code reported by the next gs
        self.move: LinearMove | None = None
        self._move_fails = False
        self.end_with_status = False
        self.stop_reply: str | None = "PO"
        self._buf = bytearray()

    # -- state -----------------------------------------------------------------------------
    @property
    def position_deg(self) -> float:
        with self.lock:
            self.tick(time.monotonic())
            return self.position_pulses * 360.0 / PULSES_PER_REV

    def _speed_pulses_s(self) -> float:
        return (MAX_SPEED_DEG_S * max(self.velocity_percent, 1) / 100.0 * self.speed_factor
                * PULSES_PER_REV / 360.0)

    def _reply(self, cmd: str, data: str) -> None:
        self.send(f"{self.address}{cmd}{data}\r\n".encode("ascii"))

    def _status(self, code: int) -> None:
        self._reply("GS", "QQ" if self.take_fault("bad_status") else f"{code:02X}")

    def _start_move(self, target: float, now: float, kind: str) -> None:
        self.move = LinearMove(self.position_pulses, target, self._speed_pulses_s(), now, kind)
        self._move_fails = self.take_fault("error_mid_move")

    def tick(self, now: float) -> None:
        mv = self.move
        if mv is None:
            return
        if self._move_fails and now >= mv.midpoint_time:
            self.position_pulses = round(mv.position(now))
            self.move = None
            self._move_fails = False
            self.pending_error = 2  # mechanical time-out: the motor stalled
            self._status(2)
            return
        self.position_pulses = mv.position(now)
        if mv.done(now):
            self.move = None
            self.position_pulses = round(mv.target) % PULSES_PER_REV
            if self.take_fault("lost_end"):
                return
            if self.end_with_status:
                self._status(0)
            else:
                self._reply("PO", _hex32(int(self.position_pulses)))

    def on_disconnect(self) -> None:
        if self.move is not None:
            self.position_pulses = round(self.move.position(time.monotonic()))
            self.move = None

    def garble(self, data: bytes) -> bytes:
        # Line noise: the framing (CR LF) survives, the content does not.
        return b"\xfe" + bytes(b | 0x80 for b in data[1:-2]) + data[-2:]

    # -- protocol --------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> None:
        self._buf += data
        while True:
            while self._buf[:1] in (b"\r", b"\n"):
                del self._buf[:1]
            if len(self._buf) < 3:
                return
            addr, cmd = chr(self._buf[0]), self._buf[1:3].decode("ascii", "replace")
            n = _DATA_LEN.get(cmd)
            if n is None:
                # not a command this module knows: drop the packet (up to a terminator or all)
                end = min([i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0],
                          default=len(self._buf))
                del self._buf[: max(end, 3)]
                if addr.upper() == self.address:
                    self._status(3)
                continue
            if cmd == "ho" and len(self._buf) == 3:
                return  # direction digit may still be in flight
            if cmd == "ho" and chr(self._buf[3]) not in "01":
                n = 0  # "ho" without a direction
            if len(self._buf) < 3 + n:
                return
            arg = self._buf[3 : 3 + n].decode("ascii", "replace")
            del self._buf[: 3 + n]
            if addr.upper() != self.address:
                continue  # another module on the bus
            self._execute(cmd, arg, now)

    def _execute(self, cmd: str, arg: str, now: float) -> None:
        busy = self.move is not None
        if cmd == "in":
            self._reply("IN", f"0E{self.serial_number:>8.8}2023{0x17:02X}{0x01:02X}"
                              f"{360:04X}{PULSES_PER_REV:08X}")
        elif cmd == "gs":
            code = self.pending_error or (9 if busy else 0)
            self.pending_error = 0
            self._status(code)
        elif cmd == "gp":
            self._reply("PO", _hex32(round(self.position_pulses)))
        elif cmd == "st":
            if busy:
                self.position_pulses = round(self.move.position(now))
                self.move = None
            if self.stop_reply == "PO":
                self._reply("PO", _hex32(round(self.position_pulses)))
            elif self.stop_reply == "GS":
                self._status(0)
        elif cmd in ("ho", "ma", "mr", "fw", "bw"):
            if busy:
                self._status(9)
                return
            if cmd == "ho":
                # Rotates to the index in the requested direction; ends at the home offset.
                self._start_move(0.0, now, "home")
                return
            if cmd in ("fw", "bw"):
                step = self.jog_step if cmd == "fw" else -self.jog_step
                self._start_move(self.position_pulses + step, now, "jog")
                return
            try:
                value = _signed32(arg)
            except ValueError:
                self._status(3)
                return
            target = value if cmd == "ma" else self.position_pulses + value
            if not (-PULSES_PER_REV < target < 2 * PULSES_PER_REV):
                self.pending_error = 4
                self._status(4)
                return
            self._start_move(float(target), now, cmd)
        elif cmd == "gv":
            self._reply("GV", f"{self.velocity_percent:02X}")
        elif cmd == "sv":
            try:
                v = int(arg, 16)
            except ValueError:
                v = -1
            if not 0 < v <= 100:
                self._status(4)
                return
            self.velocity_percent = v
            self._status(0)
        elif cmd == "go":
            self._reply("HO", _hex32(self.home_offset))
        elif cmd == "so":
            self.home_offset = _signed32(arg)
            self._status(0)
        elif cmd == "gj":
            self._reply("GJ", _hex32(self.jog_step))
        elif cmd == "sj":
            self.jog_step = _signed32(arg)
            self._status(0)
        elif cmd == "us":
            self._status(0)


def main(argv: list[str] | None = None) -> None:
    run_cli(Ell14Emulator, "Emulated Thorlabs ELL14 rotation mount on a pseudo-terminal.",
            argv)


if __name__ == "__main__":
    main()
