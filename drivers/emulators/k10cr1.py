"""Emulator of a Thorlabs K10CR1 rotation stage speaking APT binary frames on a pty.

Protocol: Thorlabs "APT Communications Protocol" (see :mod:`polrig.drivers.apt`). State machine:
position in micro-steps (409600/3 per degree), moves at the maximum velocity of its velocity
parameters (``MOT_SET/REQ/GET_VELPARAMS``, APT units; power-up values 10 deg/s and 10
deg/s^2, the K10CR1's specified maximum speed and Kinesis' default acceleration) times
``speed_factor``, at constant speed (the acceleration is reported, not simulated), homing to 0 with ``MOT_MOVE_HOMED`` at the end, moves
with ``MOT_MOVE_COMPLETED`` carrying position and status bits, ``MOT_MOVE_STOP`` with
``MOT_MOVE_STOPPED``, status bits (moving, homing, homed, motion error, enabled), the channel
enable state (a disabled channel ignores moves and reports an error), ``HW_GET_INFO``.

Faults: see :mod:`polrig.drivers.emulators._pty`. ``error_mid_move`` stops the motor half way,
sets the motion-error bit, clears the homed bit (the position is no longer trusted) and
sends ``HW_RICHRESPONSE`` with an error code and text; the code values are this emulator's
own (the protocol document leaves them device specific). ``garble`` corrupts the header
of the next frame (line noise: every header byte flipped, so neither the id nor the
addresses survive). ``stop_mid_move``: the next move stops half way and the controller
sends ``MOT_MOVE_STOPPED`` with its status, as when a limit switch trips or another client
stops it. ``unsolicited``: the next frame is preceded by two well-formed frames the host
never asked for and a K10CR1 driver does not use (``MOT_GET_DCSTATUSUPDATE`` 0x0491 with 14
data bytes, ``MOD_GET_CHANENABLESTATE`` 0x0212 header only).
"""

from __future__ import annotations

import struct
import time

from polrig.drivers import apt
from polrig.drivers.emulators._pty import LinearMove, PtyEmulator, run_cli

STEPS_PER_DEG = 409600 / 3
MAX_SPEED_DEG_S = 10.0
ACCELERATION_DEG_S2 = 10.0
ERROR_MOTION = (10002, "Motion error: position error exceeded limit, motor stopped")
ERROR_DISABLED = (10001, "Channel is disabled: enable it before moving")


class K10cr1Emulator(PtyEmulator):
    name = "k10cr1"
    FAULTS = PtyEmulator.FAULTS + ("stop_mid_move", "unsolicited")

    def __init__(self, *, serial_number: int = 55000123, link=None, speed_factor: float = 1.0,
                 homed: bool = False):
        super().__init__(link=link, speed_factor=speed_factor)
        self.serial_number = serial_number
        self.position_steps = 0.0
        self.homed = homed
        self.enabled = True
        self.motion_error = False
        self.max_velocity = apt.velocity_to_apt(MAX_SPEED_DEG_S, STEPS_PER_DEG)  # APT units
        self.acceleration = apt.acceleration_to_apt(ACCELERATION_DEG_S2, STEPS_PER_DEG)
        self.move: LinearMove | None = None
        self._move_fails = False
        self._move_stops = False
        self._buf = bytearray()

    @property
    def position_deg(self) -> float:
        with self.lock:
            self.tick(time.monotonic())
            return self.position_steps / STEPS_PER_DEG

    def status_bits(self) -> int:
        bits = apt.STATUS_ENABLED if self.enabled else 0
        if self.homed:
            bits |= apt.STATUS_HOMED
        if self.motion_error:
            bits |= apt.STATUS_MOTION_ERROR
        mv = self.move
        if mv is not None:
            if mv.kind == "home":
                bits |= apt.STATUS_HOMING
            bits |= apt.STATUS_MOVING_FWD if mv.target >= mv.start else apt.STATUS_MOVING_REV
        return bits

    def _msg(self, msg_id: int, *, param1: int = 0, param2: int = 0,
             data: bytes | None = None) -> None:
        self.send(apt.AptMessage(msg_id, param1, param2, data, dest=apt.HOST,
                                 source=apt.USB_UNIT).pack())

    def _status14(self) -> bytes:
        pos = int(round(self.position_steps))
        return struct.pack("<HiiI", 1, pos, pos, self.status_bits())

    def garble(self, data: bytes) -> bytes:
        return bytes(b ^ 0x5A for b in data[:6]) + data[6:]

    def send(self, data: bytes) -> None:
        with self.lock:
            if self.take_fault("unsolicited"):
                pos = int(round(self.position_steps))
                self.write_raw(apt.AptMessage(0x0491, data=struct.pack("<HiiI", 1, pos, 0, 0),
                                              dest=apt.HOST, source=apt.USB_UNIT).pack())
                self.write_raw(apt.AptMessage(0x0212, 1, 0x01, dest=apt.HOST,
                                              source=apt.USB_UNIT).pack())
            super().send(data)

    def _start(self, target: float, now: float, kind: str) -> None:
        if not self.enabled:
            self._msg(apt.HW_RICHRESPONSE, data=struct.pack("<HH64s", apt.MOT_MOVE_ABSOLUTE,
                      ERROR_DISABLED[0], ERROR_DISABLED[1].encode()))
            return
        self.motion_error = False
        speed = (apt.velocity_from_apt(self.max_velocity, STEPS_PER_DEG) * STEPS_PER_DEG
                 * self.speed_factor)
        self.move = LinearMove(self.position_steps, target, speed, now, kind)
        self._move_fails = self.take_fault("error_mid_move")
        self._move_stops = self.take_fault("stop_mid_move")

    def tick(self, now: float) -> None:
        mv = self.move
        if mv is None:
            return
        if self._move_fails and now >= mv.midpoint_time:
            self.position_steps = round(mv.position(now))
            self.move, self._move_fails = None, False
            self.motion_error, self.homed = True, False
            code, text = ERROR_MOTION
            self._msg(apt.HW_RICHRESPONSE,
                      data=struct.pack("<HH64s", apt.MOT_MOVE_ABSOLUTE, code, text.encode()))
            return
        if self._move_stops and now >= mv.midpoint_time:
            self.position_steps = round(mv.position(now))
            self.move, self._move_stops = None, False
            self._msg(apt.MOT_MOVE_STOPPED, data=self._status14())
            return
        self.position_steps = mv.position(now)
        if mv.done(now):
            self.move = None
            self.position_steps = round(mv.target)
            if mv.kind == "home":
                self.homed = True
                self._msg(apt.MOT_MOVE_HOMED, param1=1)
            else:
                self._msg(apt.MOT_MOVE_COMPLETED, data=self._status14())

    def on_disconnect(self) -> None:
        # USB unplugged: the controller keeps its power supply and its state; any motion
        # runs to its end, but the completion message is lost.
        self.tick(time.monotonic())

    def feed(self, data: bytes, now: float) -> None:
        self._buf += data
        while len(self._buf) >= 6:
            msg_id, p1, p2, dest, source, has_data = apt.unpack_header(bytes(self._buf[:6]))
            n = (p1 | p2 << 8) if has_data else 0
            if len(self._buf) < 6 + n:
                return
            payload = bytes(self._buf[6 : 6 + n])
            del self._buf[: 6 + n]
            if dest != apt.USB_UNIT:
                continue
            self._execute(msg_id, p1, p2, payload if has_data else None, now)

    def _execute(self, msg_id: int, p1: int, p2: int, data: bytes | None, now: float) -> None:
        if msg_id == apt.HW_REQ_INFO:
            info = struct.pack("<I8sH4s48s12sHHH", self.serial_number, b"K10CR1", 16,
                               bytes([0, 0, 3, 0]), b"APT Stepper Motor Controller",
                               bytes(12), 1, 0, 1)
            self._msg(apt.HW_GET_INFO, data=info)
        elif msg_id == apt.MOD_SET_CHANENABLESTATE:
            self.enabled = p2 == 0x01
            if not self.enabled and self.move is not None:
                self.position_steps = round(self.move.position(now))
                self.move = None
        elif msg_id == apt.MOT_REQ_STATUSBITS:
            self._msg(apt.MOT_GET_STATUSBITS, data=struct.pack("<HI", 1, self.status_bits()))
        elif msg_id == apt.MOT_REQ_POSCOUNTER:
            self._msg(apt.MOT_GET_POSCOUNTER,
                      data=struct.pack("<Hi", 1, int(round(self.position_steps))))
        elif msg_id == apt.MOT_REQ_VELPARAMS:
            self._msg(apt.MOT_GET_VELPARAMS, data=struct.pack(
                apt.VELPARAMS_FORMAT, 1, 0, self.acceleration, self.max_velocity))
        elif msg_id == apt.MOT_SET_VELPARAMS and data is not None and len(data) == 14:
            _, _, accel, max_vel = struct.unpack(apt.VELPARAMS_FORMAT, data)
            if accel > 0 and max_vel > 0:
                self.acceleration, self.max_velocity = accel, max_vel
        elif msg_id == apt.MOT_MOVE_HOME:
            self._start(0.0, now, "home")
        elif msg_id in (apt.MOT_MOVE_ABSOLUTE, apt.MOT_MOVE_RELATIVE) and data is not None \
                and len(data) == 6:
            _, value = struct.unpack("<Hi", data)
            target = value if msg_id == apt.MOT_MOVE_ABSOLUTE else self.position_steps + value
            self._start(float(target), now, "move")
        elif msg_id == apt.MOT_MOVE_STOP:
            if self.move is not None:
                self.position_steps = round(self.move.position(now))
                self.move = None
            self._msg(apt.MOT_MOVE_STOPPED, data=self._status14())
        # HW_START/STOP_UPDATEMSGS, MOD_IDENTIFY, acknowledgements: nothing to answer


def main(argv: list[str] | None = None) -> None:
    run_cli(K10cr1Emulator, "Emulated Thorlabs K10CR1 (APT protocol) on a pseudo-terminal.",
            argv)


if __name__ == "__main__":
    main()
