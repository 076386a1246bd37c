"""A GRBL 1.1 controller driving the object turntable on one rotary axis (:class:`Turntable`).

Protocol: grbl/grbl ``doc/markdown/interface.md`` and ``doc/markdown/commands.md`` (GRBL
1.1): G-code lines are answered ``ok`` or ``error:N`` (texts from ``doc/csv``, see
:mod:`polrig.drivers.grbl_codes`); real-time single bytes without newline: ``?`` status report
``<State|MPos:...|...>``, ``!`` feed hold, ``~`` resume, ``0x18`` soft reset (answered by the
``Grbl 1.1x ['$' for help]`` banner); ``$H`` homing (``ok`` after the cycle), ``$X`` unlock,
``$I`` build info; ``ALARM:N`` lines are pushed asynchronously. ``ok`` acknowledges that a
motion was *planned*, not finished: completion is seen by polling ``?`` until ``Idle``.

The turntable axis letter (default ``A``) and its position in the ``MPos`` list (``axes``,
default ``"XYZA"``) come from the rig configuration, and ``degrees_per_unit`` converts the
axis units (GRBL's ``$10x`` steps per unit setting decides what one unit is) to degrees.
Stopping uses feed hold then soft reset, which GRBL documents as the way to cancel a motion
without losing position. Angles: degrees, counter-clockwise seen from above
(``polrig.acquisition.hal``).

Positions are what the ``?`` report gives: the machine position (``MPos``, GRBL's default
``$10=1``) or, with ``$10=0``, the work position (``WPos``); interface.md: GRBL reports one
or the other as ``$10`` selects, ``WPos = MPos - WCO``. Moves are ``G90`` targets in the
active work coordinate system, so with a work offset set (``G10``/``G92``) only ``$10=0``
makes the reported position the commanded one; with the default zero offsets both agree.

Alarms (interface.md; ``doc/csv/alarm_codes_en_US.csv``): an ``ALARM:N`` line raises
:class:`polrig.errors.DeviceAlarm` (a :class:`DeviceFault` that needs the operator: the
acquisition engine never retries it nor homes the axis on its own) with the code and text
wherever it is read, also when it arrived unasked between two calls; so do a controller locked
in the Alarm state (``error:9`` for G-code, ``Alarm`` in the ``?`` report, the ``[MSG:'$H'|'$X'
to unlock]`` of a controller that came back from a reset locked). Its message names the alarm,
what it means (:data:`polrig.drivers.grbl_codes.ALARM_MEANINGS`: a hard limit is a limit switch
that fired, something may be in the way) and ``polrig home turntable``, the command that clears
it. After a hard or soft limit (``ALARM:1``/``ALARM:2``) GRBL prints ``[MSG:Reset to
continue]`` and ignores everything, ``?`` included, until a soft reset (grbl/grbl
``grbl/protocol.c`` ``protocol_exec_rt_system``: "Block everything ... until user issues
reset"; the wait loop's body is empty, so no status report is printed either): every call then
raises that alarm at once instead of waiting for a reply that cannot come, and :meth:`home`
(and :meth:`unlock`) soft-reset first.

A motion suspended by a feed hold or an open safety door (states ``Hold`` and ``Door``,
interface.md) has not ended: :meth:`wait` keeps waiting, because GRBL resumes it on cycle
start (``~``) once the operator allows. If it is still suspended at the deadline, the
operator has stopped the machine: the move is cancelled (as below) and a
:class:`polrig.errors.DeviceAlarm` naming the state is raised, so that a capture stops and
is never re-homed and driven on by its engine. A motion that has not ended at :meth:`wait`'s
deadline is stopped (:meth:`stop`: feed hold,
then soft reset, position kept) before :class:`DeviceTimeout` is raised, so it neither keeps
running nor resumes unattended; a homing cycle that runs out of time is aborted by a soft
reset (:meth:`stop` during ``$H``: GRBL ignores a feed hold while homing). A controller that
cannot move at all raises at once: asleep (``Sleep``: only a reset wakes it, locked in Alarm)
a :class:`polrig.errors.DeviceAlarm`, check mode (``Check``) a :class:`DeviceFault`.

Opening never aborts a running motion: a soft reset during a motion stops it and throws an
alarm, the position being lost (commands.md, "Grbl v1.1 Realtime commands", ``0x18``: "If
reset while in motion, Grbl will throw an alarm"; ALARM:3). So :meth:`open` first asks a
``?`` status report, which GRBL answers "at any time, except during a homing cycle and when
critical alarm (hard/soft limit error) is thrown" (same section), and takes a ``Grbl 1.1x``
banner from a board that opening the port reset (DTR) on the way. Only a controller that does
not answer sensibly (nothing, or a garbled line, within ``reply_timeout_s``: halted after a
limit, homing, or not a GRBL at all) is soft-reset, and must then answer with its banner;
so is one asleep or in check mode, where nothing moves (a sleeping GRBL takes nothing but a
reset, commands.md ``$SLP``).
The version comes from the banner or from ``$I`` (``[VER:1.1h...]``). A controller found
moving (``Run``, ``Jog``, ``Home``, ``Hold``, ``Door``) is left alone: ``$I`` and ``$$`` are
refused while it moves (grbl ``system.c``: ``$$`` blocked during a cycle or hold, ``$I`` only
in Idle or Alarm: ``error:8``), so its version is not read and its settings are read when
:attr:`GrblTurntable.capabilities` is first asked (a :class:`DeviceFault` naming the motion if
it still moves then).

Capabilities (:attr:`GrblTurntable.capabilities`, read on open with ``$$``, commands.md
"Grbl Settings"): for the configured axis, number ``k`` of ``axes``, its maximum rate
``$11k`` (units/min; a configured G1 ``rate_per_min`` caps it) and acceleration ``$12k``
(units/s^2), times ``degrees_per_unit``. With soft limits on (``$20=1``) the travel is the
machine window of a default GRBL 1.1 build, ``[-$13k, 0]`` units (settings.c stores the
travel negated, system.c ``system_check_travel_limits`` checks ``max_travel <= target <= 0``
unless the firmware was built with ``HOMING_FORCE_SET_ORIGIN``); without soft limits the
axis turns without limit (``None``). A ``$$`` listing without the axis's settings (a
3-axis build asked for axis A) is a :class:`ProtocolError` naming them.
"""

from __future__ import annotations

import math
import time

from polrig.acquisition.hal import AxisCapabilities, DeviceInfo, Turntable
from polrig.drivers._serial import SerialDevice, SerialLink
from polrig.drivers.grbl_codes import (
    ALARM_MEANINGS,
    ALARMS,
    CRITICAL_ALARMS,
    CRITICAL_MESSAGE,
    ERRORS,
    LOCK_MESSAGE,
    SUBSTATES,
)
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
)

BAUDRATE = 115200
SOFT_RESET = b"\x18"
#: states of a motion that has not ended (interface.md): running, or suspended
_MOVING = ("Run", "Jog", "Home")
_SUSPENDED = ("Hold", "Door")


class GrblTurntable(SerialDevice, Turntable):
    def __init__(self, port: str, *, axis: str = "A", axes: str = "XYZA",
                 degrees_per_unit: float = 1.0, rate_per_min: float | None = None,
                 reply_timeout_s: float = 2.0, poll_s: float = 0.02, kind: str = "turntable"):
        axis, axes = str(axis).upper(), str(axes).upper()
        if len(axis) != 1 or axis not in axes:
            raise ValueError(f"axis {axis!r} is not one of the controller's axes {axes!r}")
        if not degrees_per_unit or degrees_per_unit != degrees_per_unit:
            raise ValueError(f"degrees_per_unit must be a non-zero number, got {degrees_per_unit!r}")
        self.port = port
        self.axis = axis
        self.axes = axes
        self.axis_index = axes.index(axis)
        self.degrees_per_unit = float(degrees_per_unit)
        self.rate_per_min = rate_per_min
        self.reply_timeout_s = float(reply_timeout_s)
        self.poll_s = float(poll_s)
        self.kind = kind
        self._link = SerialLink(port, baudrate=BAUDRATE, device=f"grbl {port}")
        self._info: DeviceInfo | None = None
        self.state = ""
        self.last_alarm: int | str | None = None
        # halted after a critical alarm: GRBL ignores everything but a soft reset
        self.halted = False
        self._homing = False  # a $H cycle this driver started has not ended
        self._banner = ""
        self._caps: AxisCapabilities | None = None

    # -- life cycle ------------------------------------------------------------------------
    def _handshake(self) -> None:
        """Open without aborting a running motion (module docstring): a ``?`` status first,
        a soft reset only when the controller does not answer it sensibly."""
        self._caps, self._banner, self._homing = None, "", False
        report = self._status_on_open()
        if report is not None and report["state"].split(":")[0] in ("Sleep", "Check"):
            # nothing moves here: a sleeping GRBL takes nothing but a reset (commands.md
            # $SLP), check mode refuses $I (error:8); a reset ends both
            report = None
        if report is None:
            self._reset()
            # Opening the port resets many boards (DTR): a boot banner may follow the one
            # just read; it is no news here, so take it without raising.
            time.sleep(0.05)
            self._drain_pending(raise_alarm=False)
            report = self.status()  # checks the axis is in the status report
        state = report["state"].split(":")[0]
        moving = state in _MOVING or state in _SUSPENDED
        lines = [] if moving else self._command("$I")
        build = [l for l in lines if l.startswith("[")]
        if not self._banner:
            version = next((l[5:].split(".", 2) for l in build if l.startswith("[VER:")), None)
            self._banner = (f"Grbl {version[0]}.{version[1]}" if version and len(version) > 1
                            else "Grbl (version not read: it was moving when opened)"
                            if moving else "Grbl")
        self._info = DeviceInfo(kind=self.kind, driver="grbl", model="GRBL",
                                firmware=self._banner, port=self.port,
                                extra={"build": build, "axis": self.axis,
                                       "state_at_open": report["state"]})
        if not moving:
            self._caps = self._axis_capabilities(self.settings())

    def _status_on_open(self) -> dict | None:
        """The first ``?`` report of a controller just opened, or ``None`` when it does not
        answer sensibly within ``reply_timeout_s`` (silent, garbled: it is then reset). A
        banner (a board reset by opening the port) is taken and ``?`` asked again, since the
        first may have reached the boot loader; pushed alarms are recorded."""
        self._link.write(b"?")
        deadline = time.monotonic() + self.reply_timeout_s
        try:
            while True:
                line = self._readline(deadline, "status report", self.reply_timeout_s)
                if line.startswith("<") and line.endswith(">"):
                    return self._parse_status(line)
                if line.startswith("Grbl "):
                    self._banner = line.split("[")[0].strip()
                    self.halted = False
                    self._link.write(b"?")
                    deadline = time.monotonic() + self.reply_timeout_s
                elif line.startswith("ALARM:"):
                    self._alarm(line)
                elif line == CRITICAL_MESSAGE:
                    self.halted = True
                elif line.startswith("<"):
                    return None  # a truncated report: not an answer to go on
        except (DeviceTimeout, ProtocolError):
            return None

    @property
    def capabilities(self) -> AxisCapabilities:
        """Speed, acceleration and travel of the turntable axis from ``$$`` (read on open, or
        here the first time when the controller was moving when opened: GRBL refuses ``$$``
        during a motion, a :class:`DeviceFault` naming it)."""
        if self._caps is None:
            if not self._link.is_open:
                raise DeviceDisconnected("device is not open (open it first)",
                                         device=self._link.device)
            try:
                settings = self.settings()
            except DeviceFault as exc:
                if exc.code != 8 or isinstance(exc, DeviceAlarm):
                    raise
                raise DeviceFault(f"the {self.kind}'s settings ($$) cannot be read while it "
                                  "moves (it was moving when opened): wait for the motion to "
                                  "end or stop it", device=self._link.device, code=8,
                                  text=exc.text) from None
            self._caps = self._axis_capabilities(settings)
        return self._caps

    def settings(self) -> dict[int, float]:
        """``$$``: every ``$N=value`` setting line (GRBL 1.1 prints no comments)."""
        out: dict[int, float] = {}
        for line in self._command("$$"):
            key, sep, value = line.partition("=")
            try:
                if not (sep and key.startswith("$")):
                    raise ValueError
                out[int(key[1:])] = float(value)
            except ValueError:
                self._resync()
                raise ProtocolError(f"malformed settings line {line!r} in the reply to '$$'",
                                    device=self._link.device) from None
        return out

    def _axis_capabilities(self, settings: dict[int, float]) -> AxisCapabilities:
        k = self.axis_index
        keys = {"rate": 110 + k, "accel": 120 + k}
        if settings.get(20):
            keys["travel"] = 130 + k
        missing = [f"${n}" for n in keys.values() if n not in settings]
        if missing:
            raise ProtocolError(f"the controller's settings ($$) have no {', '.join(missing)} "
                                f"for axis {self.axis} (number {k + 1} of the configured axes "
                                f"{self.axes!r}): a build without that axis?",
                                device=self._link.device)
        rate = settings[keys["rate"]]
        if self.rate_per_min:
            rate = min(rate, float(self.rate_per_min))
        dpu = abs(self.degrees_per_unit)
        speed, accel = rate / 60.0 * dpu, settings[keys["accel"]] * dpu
        if not (speed > 0 and accel > 0 and math.isfinite(speed) and math.isfinite(accel)):
            raise ProtocolError(f"axis {self.axis} settings give maximum rate {rate:g} units/min"
                                f" and acceleration {settings[keys['accel']]:g} units/s^2: "
                                "both must be > 0", device=self._link.device)
        travel = None
        if "travel" in keys:
            ends = sorted((-settings[keys["travel"]] * self.degrees_per_unit, 0.0))
            travel = (ends[0], ends[1])
        return AxisCapabilities(speed_deg_s=speed, accel_deg_s2=accel, range_deg=travel)

    def close(self) -> None:
        self._link.close()

    def info(self) -> DeviceInfo:
        if self._info is None:
            raise DeviceDisconnected("device is not open (open it first)",
                                     device=self._link.device)
        return self._info

    # -- protocol --------------------------------------------------------------------------
    def _readline(self, deadline: float, what: str, stated_s: float) -> str:
        """One line that must start before ``deadline`` (time.monotonic); a timeout names
        ``stated_s``, the caller's configured timeout."""
        raw = self._link.read_until(b"\n", max(deadline - time.monotonic(), 0.0), what=what,
                                    stated_s=stated_s).rstrip(b"\r")
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            self._resync()
            raise ProtocolError(f"garbled {what} {raw!r}", device=self._link.device) from None

    def _resync(self) -> None:
        time.sleep(0.05)
        self._link.discard_input()

    def _alarm(self, line: str) -> DeviceFault:
        """Record the alarm of an ``ALARM:N`` line and return its DeviceFault."""
        code = int(line[6:]) if line[6:].strip().isdigit() else line[6:]
        self.state, self.last_alarm = "Alarm", code
        if code in CRITICAL_ALARMS:
            self.halted = True
        return self._alarm_fault()

    def _alarm_fault(self) -> DeviceAlarm:
        """The :class:`DeviceAlarm` of the alarm recorded last (or of the Alarm lock)."""
        code = self.last_alarm if self.last_alarm is not None else "Alarm"
        text = ALARMS.get(code, "controller locked in the Alarm state")
        what = ALARM_MEANINGS.get(code, "locked in the Alarm state (power-up, reset or an "
                                        "earlier alarm): the position is unknown")
        name = f"ALARM:{code}" if code != "Alarm" else "Alarm"
        message = f"{self.kind} stopped by {name}, {what}"
        if self.halted:
            message += "; halted until reset (the home command resets it first)"
        return DeviceAlarm(message, device=self._link.device, code=code, text=text,
                           axis=self.kind)

    def _locked(self, message: str, code: int | str | None = None,
                text: str | None = None) -> DeviceAlarm:
        """A controller found locked (``message`` says how): in the Alarm state, or asleep
        (the state stays ``Sleep``: :meth:`home` resets it first)."""
        if self.state != "Sleep":
            self.state = "Alarm"
        return DeviceAlarm(f"{self.kind} {message}", device=self._link.device, code=code,
                           text=text, axis=self.kind)

    def _reset_seen(self, banner: str, during: str) -> DeviceFault:
        """A ``Grbl 1.1x`` banner nobody asked for: the controller was reset (power, USB
        re-enumeration toggling DTR, the reset button); whatever it was doing is gone."""
        self.halted = False
        self.state = ""
        time.sleep(0.05)
        after = self._link.discard_input()  # the [MSG:...] lines that follow the banner
        message = (f"controller reset during {during} (power, USB or reset button); the "
                   "command was not carried out and any motion was aborted")
        if LOCK_MESSAGE.encode() in after:
            return self._locked(f"stopped: {message}; it came back locked in the Alarm state, "
                                "the position is unknown", code="reset", text=banner.strip())
        return DeviceFault(message, device=self._link.device, code="reset",
                           text=banner.strip())

    def _drain_pending(self, *, raise_alarm: bool = True) -> None:
        """Read what arrived unasked (late replies of a timed-out command, pushed messages)
        so it is not taken for the answer to the next command. An alarm among it is raised
        (``raise_alarm``; always recorded); while the controller is halted after a critical
        alarm the halt is raised, since GRBL would not answer anything but a reset."""
        alarm = banner = None
        locked = False
        if self._link.in_waiting():
            time.sleep(0.01)
            for raw in self._link.discard_input().split(b"\n"):
                line = raw.strip().decode("ascii", "replace")
                if line.startswith("ALARM:"):
                    alarm = self._alarm(line)
                elif line == CRITICAL_MESSAGE:
                    self.halted = True
                elif line.startswith("Grbl "):
                    self.halted = False  # someone reset it: the halt is over
                    self.state, banner, locked = "", line, False
                elif line == LOCK_MESSAGE and banner is not None:
                    locked = True
        if not raise_alarm:
            return
        if alarm is not None:
            raise alarm
        if banner is not None and locked:
            raise self._locked("stopped: the controller was reset (power, USB or reset "
                               "button), any motion was aborted; it came back locked in the "
                               "Alarm state, the position is unknown", code="reset",
                               text=banner)
        if banner is not None:
            raise DeviceFault("controller was reset (power, USB or reset button); any motion "
                              "was aborted", device=self._link.device, code="reset",
                              text=banner)
        if self.halted:
            raise self._alarm_fault()

    def _reset(self) -> None:
        """Soft reset and wait for the banner (proves a GRBL is at the other end)."""
        self._link.write(SOFT_RESET)
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            line = self._readline(deadline, "GRBL banner", self.reply_timeout_s)
            if line.startswith("Grbl "):
                self._banner = line.split("[")[0].strip()
                self.halted = False
                return
            if line.startswith("ALARM:"):
                self._alarm(line)

    def _command(self, line: str, timeout_s: float | None = None) -> list[str]:
        """Send one line; return the lines before ``ok`` (``[...]`` messages, ``$N=value``
        settings); ``error:N``/``ALARM:N`` raise."""
        self._drain_pending()
        self._link.write(line.encode("ascii") + b"\n")
        stated = timeout_s or self.reply_timeout_s
        deadline = time.monotonic() + stated
        out: list[str] = []
        while True:
            reply = self._readline(deadline, f"reply to {line!r}", stated)
            if reply == "ok":
                return out
            if reply.startswith("error:"):
                code_s = reply[6:]
                code = int(code_s) if code_s.isdigit() else code_s
                raise DeviceFault(f"{line!r} rejected", device=self._link.device, code=code,
                                  text=ERRORS.get(code, "unknown error"))
            if reply.startswith("ALARM:"):
                raise self._alarm(reply)
            if reply == CRITICAL_MESSAGE:
                self.halted = True
                raise self._alarm_fault()
            if reply.startswith("Grbl "):
                raise self._reset_seen(reply, repr(line))
            if reply and not reply.startswith(("<", "[", "$")):  # $N=value: a $$ listing
                self._resync()
                raise ProtocolError(f"unexpected reply {reply!r} to {line!r}",
                                    device=self._link.device)
            out.append(reply)

    def status(self) -> dict:
        """One ``?`` status report: ``{"state": ..., "frame": "MPos" or "WPos",
        "positions": [...], "position_deg": ...}`` (``positions`` in the ``axes`` order)."""
        self._drain_pending()
        self._link.write(b"?")
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            line = self._readline(deadline, "status report", self.reply_timeout_s)
            if line.startswith("ALARM:"):
                raise self._alarm(line)
            if line == CRITICAL_MESSAGE:
                self.halted = True
                raise self._alarm_fault()
            if line.startswith("Grbl "):
                raise self._reset_seen(line, "a status request")
            if line.startswith("<") and line.endswith(">"):
                return self._parse_status(line)
            if line.startswith("<"):
                self._resync()
                raise ProtocolError(f"truncated status report {line!r}", device=self._link.device)

    def _parse_status(self, line: str) -> dict:
        fields = line[1:-1].split("|")
        state = fields[0]
        frame, pos = None, None
        for f in fields[1:]:
            if f.startswith(("MPos:", "WPos:")):
                frame = f[:4]
                try:
                    pos = [float(v) for v in f[5:].split(",")]
                except ValueError:
                    pos = None
        if pos is None:
            self._resync()
            raise ProtocolError(f"status report without a position (MPos or WPos): {line!r}",
                                device=self._link.device)
        if len(pos) <= self.axis_index:
            self._resync()
            raise ProtocolError(f"status report has {len(pos)} axes, but axis {self.axis} is "
                                f"number {self.axis_index + 1} of the configured axes "
                                f"{self.axes!r} (set [turntable] axes): {line!r}",
                                device=self._link.device)
        self.state = state
        return {"state": state, "frame": frame, "positions": pos,
                "position_deg": pos[self.axis_index] * self.degrees_per_unit}

    # -- Turntable -------------------------------------------------------------------------
    def position_deg(self) -> float:
        """The axis position from the ``?`` report: machine position (``MPos``, GRBL's
        default ``$10=1``) or work position (``WPos``, ``$10=0``), times
        ``degrees_per_unit``."""
        return self.status()["position_deg"]

    def _motion_state(self) -> tuple[bool, str]:
        """``(motion not ended, state)``; states in which nothing can move raise."""
        st = self.status()["state"]
        base = st.split(":")[0]
        if base == "Alarm":
            raise self._alarm_fault()
        if base == "Sleep":  # only a reset ends it, and GRBL comes back locked in Alarm
            raise self._locked("controller is asleep ($SLP): nothing moves until it is reset",
                               code=st, text="sleep mode")
        if base == "Check":
            raise DeviceFault("controller is in check mode ($C): G-code is checked, nothing "
                              "moves (send $C again to leave it)", device=self._link.device,
                              code=st, text="check mode")
        return base in _MOVING or base in _SUSPENDED, st

    def is_busy(self) -> bool:
        """True while a motion has not ended: running, homing, jogging, or suspended by a
        feed hold or the safety door (it resumes on cycle start)."""
        return self._motion_state()[0]

    def wait(self, timeout_s: float = 30.0) -> None:
        """Block until the motion ends (s); a suspended one (feed hold, safety door) is
        waited for too. At ``timeout_s`` the motion is stopped (:meth:`stop`; a suspended
        one is cancelled, so cycle start cannot resume it unattended) and
        :class:`DeviceTimeout` raised, naming a stop that failed too; a motion still held by
        the operator then is a :class:`DeviceAlarm` (the operator's to clear, never retried)."""
        deadline = time.monotonic() + timeout_s
        while True:
            busy, st = self._motion_state()
            if not busy:
                return
            if time.monotonic() > deadline:
                message = f"motion did not end within {timeout_s:g} s"
                held = st.split(":")[0] in _SUSPENDED
                if held:
                    what = SUBSTATES.get(st, "motion suspended")
                    message += f": it was suspended, state {st} ({what})"
                timeout = self.stopped_after_timeout(message, self._link.device,
                                                     "stopped (the rest of the move cancelled)")
                if held:  # the operator stopped the machine: theirs to clear, never driven on
                    raise DeviceAlarm(f"{self.kind} {timeout}, held by the operator",
                                      device=self._link.device, axis=self.kind) from None
                raise timeout
            time.sleep(self.poll_s)

    def _clear_halt(self) -> None:
        """Read what is pending; after a critical alarm, or in sleep mode, soft-reset: the
        only command GRBL then takes (protocol.c; commands.md ``$SLP``: "the only way to exit
        sleep mode is to reset"). The controller comes back in the Alarm state."""
        self._drain_pending(raise_alarm=False)
        if self.halted or self.state == "Sleep":
            self._reset()

    def home(self, timeout_s: float = 60.0) -> None:
        """``$H``; if it does not finish in ``timeout_s`` (s) the cycle is aborted by
        :meth:`stop` (a soft reset: GRBL then reports ALARM:6, homing failed) so the machine
        never keeps moving unattended. A controller halted by a hard or soft limit is
        soft-reset first."""
        self._clear_halt()
        self._link.discard_input()
        self._homing = True  # left set by an interruption (Ctrl-C): stop() then resets
        try:
            self._command("$H", timeout_s=timeout_s)
        except DeviceTimeout:
            self.stop()
            raise
        except DeviceError:
            self._homing = False
            raise
        self._homing = False
        self.state, self.last_alarm = "Idle", None

    def unlock(self) -> None:
        """``$X`` (soft-resetting first if a hard or soft limit halted the controller)."""
        self._clear_halt()
        self._command("$X")

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None:
        angle_deg = float(angle_deg)
        if angle_deg != angle_deg or abs(angle_deg) == float("inf"):
            raise ValueError(f"turntable angle must be finite, got {angle_deg!r}")
        units = angle_deg / self.degrees_per_unit
        if self.rate_per_min:
            line = f"G90 G1 {self.axis}{units:.4f} F{self.rate_per_min:g}"
        else:
            line = f"G90 G0 {self.axis}{units:.4f}"
        try:
            self._command(line)
        except DeviceFault as exc:
            if exc.code == 9 and not isinstance(exc, DeviceAlarm):
                # G-code locked out: the Alarm state after power-up, a reset or an alarm
                code = self.last_alarm
                what = (f"ALARM:{code}, {ALARM_MEANINGS[code]}" if code in ALARM_MEANINGS
                        else "power-up, a reset or an earlier alarm: the position is unknown")
                raise self._locked(f"is locked in the Alarm state ({what}); the move to "
                                   f"{angle_deg:g} deg was refused", code=9,
                                   text=exc.text) from None
            raise
        if wait:
            self.wait(timeout_s)

    def stop(self) -> None:
        """Feed hold, wait for the hold to complete, then soft reset (position kept). A
        controller halted by a hard or soft limit has stopped already: nothing is sent.
        During a homing cycle this driver started (``$H``, also one interrupted before its
        ``ok``) a soft reset at once: GRBL ignores a feed hold and answers no ``?`` while
        homing (commands.md), and the reset aborts the cycle (ALARM:6, homing failed)."""
        if self._homing:
            self._homing = False
            self._link.write(SOFT_RESET)
            time.sleep(0.05)
            self._drain_pending(raise_alarm=False)
            return
        self._drain_pending(raise_alarm=False)
        if self.halted:
            return
        self._link.write(b"!")
        deadline = time.monotonic() + self.reply_timeout_s
        while self.status()["state"] not in ("Hold:0", "Door:0", "Door:1", "Idle", "Alarm"):
            if time.monotonic() > deadline:
                raise DeviceTimeout("feed hold did not complete", device=self._link.device)
            time.sleep(self.poll_s)
        self._reset()
