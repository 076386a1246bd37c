"""Thorlabs K10CR1 motorised rotation stage as a :class:`polrig.acquisition.hal.RotationStage`.

Transport: FTDI USB serial (VID:PID 0403:FAF0), 115200 baud 8N1 with RTS/CTS handshake, as
the Thorlabs "APT Communications Protocol" document prescribes for its USB controllers.
Messages (see :mod:`polrig.drivers.apt`): ``HW_REQ_INFO``/``HW_GET_INFO`` (identity),
``MOD_SET_CHANENABLESTATE`` (enable channel 1), ``MOT_MOVE_HOME``/``MOT_MOVE_HOMED``,
``MOT_MOVE_ABSOLUTE``/``MOT_MOVE_COMPLETED``, ``MOT_MOVE_STOP``/``MOT_MOVE_STOPPED``,
``MOT_REQ_STATUSBITS``/``MOT_GET_STATUSBITS``, ``MOT_REQ_POSCOUNTER``/``MOT_GET_POSCOUNTER``;
``HW_RESPONSE``/``HW_RICHRESPONSE`` report device errors (code and text), raised as
:class:`polrig.errors.DeviceFault`. Scale: 409600/3 micro-steps per degree (K10CR1 with the
default 2048 micro-steps and 66:1 worm gear; pylablib ``kinesis.py`` lists the same value).

The stage must be homed after power-up or a motion error (status bit "homed" clear) before
absolute moves mean anything; ``require_homed`` makes moves refuse until it is, with a
:class:`polrig.errors.DeviceAlarm` naming the axis's own kind (``stage`` or ``turntable``) and
the command that homes it (``polrig home turntable``; the CLI adds ``--config RIG``), as GRBL's
Alarm lock after power-up does: the acquisition engine never homes such an axis on its own
(a capture's setup homes the stage, as it does for every stage driver; a turntable is homed by
the operator).

Frames with a message id this driver does not use are skipped (logged at debug level)
while it waits for the reply it asked for: the header says how many data bytes follow
(dest | 0x80 flags a data packet, APT protocol section 2), so the stream stays in step. A
header that is not addressed to the host (0x01), or announces an implausible data length,
is line noise: :class:`ProtocolError`.

End of a motion: ``MOT_MOVE_COMPLETED`` / ``MOT_MOVE_HOMED``. ``MOT_MOVE_STOPPED`` ends it
too, but unless this driver asked for the stop (:meth:`stop`) the controller stopped the move
on its own (a limit switch, its stop button, another program): a safety fault,
:class:`polrig.errors.DeviceAlarm` (never retried nor homed by the acquisition engine; its
message names the position it stopped at and ``polrig home stage|turntable``). When no message
comes for a while, :meth:`wait` asks the status bits: a controller that no longer moves has
finished, and its end-of-motion message was lost on the line (with the motion-error bit set
that is a :class:`DeviceFault`). A motion that does not end within :meth:`wait`'s timeout is
stopped (``MOT_MOVE_STOP``) before :class:`DeviceTimeout` is raised, so nothing keeps moving
unattended.

Capabilities (:attr:`K10cr1Stage.capabilities`, read on open): ``MOT_REQ_VELPARAMS`` ->
``MOT_GET_VELPARAMS`` (maximum velocity and acceleration in APT units, converted as
:mod:`polrig.drivers.apt` documents: velocity / 53.68, acceleration * 90.9, per micro-step); the
stage turns without limit (``range_deg`` None).
"""

from __future__ import annotations

import logging
import struct
import time

from polrig.acquisition.hal import (
    AxisCapabilities,
    DeviceInfo,
    RotationStage,
    Turntable,
)
from polrig.drivers import apt
from polrig.drivers._serial import SerialDevice, SerialLink, wrap_deg
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
)

BAUDRATE = 115200
STEPS_PER_DEG = 409600 / 3
_END_OF_MOTION = (apt.MOT_MOVE_COMPLETED, apt.MOT_MOVE_HOMED, apt.MOT_MOVE_STOPPED)
#: data length beyond which a header is taken for line noise (the largest APT message a
#: motor controller sends, HW_GET_INFO, has 84 bytes)
MAX_DATA_LEN = 512
#: silence after which wait() asks the status bits whether the motion has ended
POLL_S = 0.25
_log = logging.getLogger(__name__)


class K10cr1Stage(SerialDevice, RotationStage):
    """A K10CR1 on ``port`` (channel 1)."""

    def __init__(self, port: str, *, zero_offset_deg: float = 0.0, require_homed: bool = True,
                 reply_timeout_s: float = 1.0, kind: str = "stage"):
        self.port = port
        self.zero_offset_deg = float(zero_offset_deg)
        self.require_homed = bool(require_homed)
        self.reply_timeout_s = float(reply_timeout_s)
        self.kind = kind
        self._link = SerialLink(port, baudrate=BAUDRATE, rtscts=True, device=f"k10cr1 {port}")
        self._info: DeviceInfo | None = None
        self._pending = False  # a motion whose end-of-motion message has not been read
        self._stopping = False  # stop() is waiting for its MOT_MOVE_STOPPED
        self._interrupted: tuple[int | None] | None = None  # (steps,) of an unasked stop
        self._caps: AxisCapabilities | None = None

    # -- life cycle ------------------------------------------------------------------------
    def _handshake(self) -> None:
        self._send(apt.AptMessage(apt.HW_STOP_UPDATEMSGS))
        self._identify()
        self._send(apt.AptMessage(apt.MOD_SET_CHANENABLESTATE, 1, 0x01))
        speed, accel = self.velocity_params()
        self._caps = AxisCapabilities(speed_deg_s=speed, accel_deg_s2=accel)

    @property
    def capabilities(self) -> AxisCapabilities:
        """Maximum velocity and acceleration from ``MOT_GET_VELPARAMS`` (read on open);
        unlimited travel."""
        if self._caps is None:
            raise DeviceDisconnected(f"{self.kind} is not open (open it first)",
                                     device=self._link.device)
        return self._caps

    def velocity_params(self) -> tuple[float, float]:
        """``(maximum velocity deg/s, acceleration deg/s^2)`` as the controller reports them
        (``MOT_REQ_VELPARAMS``)."""
        data = self._request(apt.AptMessage(apt.MOT_REQ_VELPARAMS, 1), apt.MOT_GET_VELPARAMS)
        _chan, _min_vel, accel, max_vel = struct.unpack(apt.VELPARAMS_FORMAT, data)
        speed = apt.velocity_from_apt(max_vel, STEPS_PER_DEG)
        acceleration = apt.acceleration_from_apt(accel, STEPS_PER_DEG)
        if not (speed > 0 and acceleration > 0):
            raise ProtocolError(f"MOT_GET_VELPARAMS gives maximum velocity {max_vel} and "
                                f"acceleration {accel} (APT units): both must be > 0",
                                device=self._link.device)
        return speed, acceleration

    def close(self) -> None:
        self._pending = False
        self._link.close()

    def info(self) -> DeviceInfo:
        if self._info is None:
            self._identify()
        assert self._info is not None
        return self._info

    def _identify(self) -> None:
        data = self._request(apt.AptMessage(apt.HW_REQ_INFO), apt.HW_GET_INFO)
        serial_no, model, hw_type, fw, notes, _, hw_ver, mod_state, nchan = struct.unpack(
            "<I8sH4s48s12sHHH", data)
        self._info = DeviceInfo(
            kind=self.kind, driver="k10cr1", model=model.rstrip(b"\0").decode("ascii", "replace"),
            serial=str(serial_no), firmware=f"{fw[2]}.{fw[1]}.{fw[0]}", port=self.port,
            extra={"type": hw_type, "notes": notes.rstrip(b"\0").decode("ascii", "replace"),
                   "hardware_version": hw_ver, "channels": nchan})

    # -- framing ---------------------------------------------------------------------------
    def _send(self, msg: apt.AptMessage) -> None:
        self._link.write(msg.pack())

    def _read_message(self, timeout_s: float, stated_s: float | None = None,
                      ) -> tuple[int, int, int, bytes | None]:
        """The next message with an id this driver knows, within ``timeout_s``; frames with
        other ids are skipped. ``stated_s``: the timeout an error message names."""
        stated = timeout_s if stated_s is None else stated_s
        deadline = time.monotonic() + timeout_s
        while True:
            header = self._link.read_exact(6, max(deadline - time.monotonic(), 0.0),
                                           what="APT header", stated_s=stated)
            msg_id, p1, p2, dest, _src, has_data = apt.unpack_header(header)
            n = (p1 | p2 << 8) if has_data else None
            if dest != apt.HOST or (n is not None and n > MAX_DATA_LEN):
                self._resync()
                raise ProtocolError(f"garbled APT frame header {header.hex(' ')} (not "
                                    "addressed to the host, or an implausible data length)",
                                    device=self._link.device)
            data = self._read_data(msg_id, n, stated) if n else None
            if msg_id in apt.REPLY_DATA_LEN:
                break
            _log.debug("%s: skipped APT message 0x%04X (%s data bytes)", self._link.device,
                       msg_id, n or 0)
        expected = apt.REPLY_DATA_LEN[msg_id]
        if n != expected:
            self._resync()
            raise ProtocolError(f"APT message 0x{msg_id:04X} with data length {n}, "
                                f"expected {expected}", device=self._link.device)
        if msg_id in (apt.HW_RESPONSE, apt.HW_RICHRESPONSE):
            self._pending = False
            code, text = None, "error reported (HW_RESPONSE)"
            if data is not None:
                _ident, code, raw = struct.unpack("<HH64s", data)
                text = raw.split(b"\0", 1)[0].decode("ascii", "replace")
            raise DeviceFault("controller reported an error", device=self._link.device,
                              code=code if code is not None else "HW_RESPONSE", text=text)
        return msg_id, p1, p2, data

    def _read_data(self, msg_id: int, n: int, stated_s: float) -> bytes:
        try:
            # the frame has started: its data get the link's inter-byte timeout even when
            # the header came at the very end of the time left
            return self._link.read_exact(n, 0.0, what="APT data", started=True,
                                         stated_s=stated_s)
        except DeviceTimeout:
            self._resync()
            raise ProtocolError(f"partial APT frame: header 0x{msg_id:04X} announced {n} "
                                "data bytes that never came", device=self._link.device) from None

    def _resync(self) -> None:
        time.sleep(0.05)
        self._link.discard_input()

    def _request(self, msg: apt.AptMessage, reply_id: int) -> bytes:
        if not self._pending:
            self._link.discard_input()  # a late reply to an earlier, timed-out request
        self._send(msg)
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            msg_id, _, _, data = self._read_message(max(deadline - time.monotonic(), 0.0),
                                                    stated_s=self.reply_timeout_s)
            if msg_id == reply_id:
                return data or b""
            self._motion_message(msg_id, data)

    def _motion_message(self, msg_id: int, data: bytes | None) -> None:
        """Bookkeeping of an end-of-motion message, wherever it was read."""
        if msg_id not in _END_OF_MOTION or not self._pending:
            return
        self._pending = False
        if msg_id == apt.MOT_MOVE_STOPPED and not self._stopping:
            steps = struct.unpack("<Hi", data[:6])[1] if data and len(data) >= 6 else None
            self._interrupted = (steps,)

    def _raise_interrupted(self) -> None:
        stopped, self._interrupted = self._interrupted, None
        if stopped is None:
            return
        steps = stopped[0]
        where = (f"at {wrap_deg(steps / STEPS_PER_DEG - self.zero_offset_deg):.4f} deg"
                 if steps is not None else "at an unknown position")
        raise DeviceAlarm(f"{self.kind} move interrupted: the controller stopped it {where} "
                          "(a limit switch that fired: something may be in the way; or its "
                          "stop button, or another program)",
                          device=self._link.device, code="MOT_MOVE_STOPPED",
                          text=f"stopped {where} without a stop request", axis=self.kind)

    # -- RotationStage ---------------------------------------------------------------------
    def status_bits(self) -> int:
        data = self._request(apt.AptMessage(apt.MOT_REQ_STATUSBITS, 1), apt.MOT_GET_STATUSBITS)
        return struct.unpack("<HI", data)[1]

    def position_deg(self) -> float:
        data = self._request(apt.AptMessage(apt.MOT_REQ_POSCOUNTER, 1), apt.MOT_GET_POSCOUNTER)
        steps = struct.unpack("<Hi", data)[1]
        return wrap_deg(steps / STEPS_PER_DEG - self.zero_offset_deg)

    def _check_motion(self) -> bool:
        """Ask the status bits whether the pending motion still runs; if it does not, its
        end-of-motion message was lost on the line (it would have come before the status
        reply): take it if it is still on its way, else count the motion as ended."""
        bits = self.status_bits()
        busy = bool(bits & apt.STATUS_MOVING)
        if not busy and self._pending:
            try:
                msg_id, _, _, data = self._read_message(min(self.reply_timeout_s, 0.1))
                self._motion_message(msg_id, data)
            except DeviceTimeout:
                pass
            if self._pending:
                self._pending = False
                _log.info("%s: end-of-motion message lost; the controller reports idle",
                          self._link.device)
                if bits & apt.STATUS_MOTION_ERROR:
                    raise DeviceFault("motion ended with an error", device=self._link.device,
                                      code="motion error",
                                      text="status bit 'motion error' is set")
        return busy

    def is_busy(self) -> bool:
        busy = self._check_motion()
        self._raise_interrupted()
        return busy

    def home(self, timeout_s: float = 60.0) -> None:
        self._link.discard_input()
        self._send(apt.AptMessage(apt.MOT_MOVE_HOME, 1))
        self._pending, self._interrupted = True, None
        self.wait(timeout_s)

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None:
        angle_deg = float(angle_deg)
        if angle_deg != angle_deg or abs(angle_deg) == float("inf"):
            raise ValueError(f"stage angle must be finite, got {angle_deg!r}")
        if self.require_homed and not self.status_bits() & apt.STATUS_HOMED:
            raise DeviceAlarm(f"{self.kind} is not homed (after power-up or a motion error its "
                              f"position is unknown); the move to {angle_deg:g} deg was refused",
                              device=self._link.device, code="not homed",
                              text="status bit 'homed' is clear", axis=self.kind)
        steps = round((wrap_deg(angle_deg) + self.zero_offset_deg) * STEPS_PER_DEG)
        self._send(apt.AptMessage(apt.MOT_MOVE_ABSOLUTE, data=struct.pack("<Hi", 1, steps)))
        self._pending, self._interrupted = True, None
        if wait:
            self.wait(timeout_s)

    def wait(self, timeout_s: float = 30.0) -> None:
        """Block until the pending motion ends (s). At ``timeout_s`` the motion is stopped
        (:meth:`stop`) and :class:`DeviceTimeout` raised; a stop that fails too is named in
        it (the axis may still be moving)."""
        deadline = time.monotonic() + timeout_s
        while self._pending:
            left = deadline - time.monotonic()
            if left <= 0:
                raise self.stopped_after_timeout(f"motion did not end within {timeout_s:g} s", self._link.device)
            try:
                msg_id, _, _, data = self._read_message(min(left, POLL_S))
            except DeviceTimeout:
                try:
                    self._check_motion()  # silence: is it still moving?
                except DeviceTimeout:
                    pass  # the status reply was lost too: keep waiting until the deadline
                continue
            self._motion_message(msg_id, data)
        self._raise_interrupted()

    def stop(self) -> None:
        """``MOT_MOVE_STOP`` (immediate); the ``MOT_MOVE_STOPPED`` it brings is no fault."""
        self._link.discard_input()
        self._stopping = True
        try:
            self._request(apt.AptMessage(apt.MOT_MOVE_STOP, 1, 0x01), apt.MOT_MOVE_STOPPED)
        finally:
            self._stopping = False
        self._pending, self._interrupted = False, None


class K10cr1Turntable(K10cr1Stage, Turntable):
    """A K10CR1 carrying the object: the same driver as a :class:`Turntable`."""

    def __init__(self, port: str, **kw):
        kw.setdefault("kind", "turntable")
        super().__init__(port, **kw)
