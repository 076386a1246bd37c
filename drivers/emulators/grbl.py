"""Emulator of a GRBL 1.1 controller driving a rotary axis, on a pseudo-terminal.

Protocol: grbl/grbl ``doc/markdown/interface.md`` and ``commands.md`` (GRBL 1.1): lines of
G-code or ``$`` commands answered ``ok`` or ``error:N``; real-time single bytes ``?``
(status report ``<State|MPos:x,y,z,a|FS:feed,speed>``, ``FS`` the real-time feed rate: that
of the running motion, 0 when none runs), ``!`` (feed hold), ``~`` (cycle start / resume),
``0x18`` (soft reset; banner ``Grbl 1.1h ['$' for help]``). ``$H`` homes (``ok`` when the
cycle is done; a ``?`` sent during the cycle is answered only when it ends, with a ``<Home|...>``
report before that ``ok``: commands.md, ``?`` "except during a homing cycle"; grbl
``limits.c`` runs no real-time commands in its homing loop, ``motion_control.c`` runs them
after the cycle), ``$X`` unlocks, ``$I`` prints build info, ``ALARM:N`` is
pushed when an alarm fires. With homing enabled (``$22=1``) the controller starts locked in
the Alarm state, as real GRBL does. Moves queue in a planner (G0 at the axis maximum rate,
G1 at the F feed rate, units per minute), run one after another; ``G90``/``G91`` modes.

Settings (commands.md, "Grbl Settings"): ``$$`` prints every ``$N=value`` line, ``$N=value``
sets one (``error:3`` for a number GRBL does not have, ``error:2`` for a bad value; ``$$``
while a motion runs or is held, and ``$I`` outside Idle and Alarm, are ``error:8``, as
system.c blocks them). The axes' maximum
rates ``$110..$113`` (units/min) limit G0 and G1; their accelerations ``$120..$123``
(units/s^2) are reported but moves here run at constant speed; ``$130..$133`` is the
maximum travel (units). Soft limits (``$20=1``, needs homing ``$22=1``) confine every
axis to the machine travel of a default GRBL 1.1 build, ``[-$13x, 0]`` (settings.c stores
the travel negated; system.c ``system_check_travel_limits`` without
``HOMING_FORCE_SET_ORIGIN``): ``max_travel`` switches them on with that travel.

Faults: see :mod:`polrig.drivers.emulators._pty`; ``error_mid_move`` and ``hard_limit`` trip a
hard limit half way through the next motion (``ALARM:1``, motion aborted, position lost:
re-home); :attr:`obstacle` puts something in the way of one axis (a motion reaching it stops
there with ``ALARM:1``, until it is taken away); ``soft_limit`` makes the next G-code motion a
soft-limit alarm (``ALARM:2``, before any motion, as if its target were beyond the travel);
:meth:`trip_hard_limit` closes a limit switch now, whatever runs (grbl/grbl ``grbl/limits.c``:
the pin-change interrupt kills the motion and raises the hard-limit alarm unless already in
Alarm). With soft limits on, a target outside the travel raises ``ALARM:2`` before any motion,
as GRBL 1.1 does. Both are critical alarms: like grbl/grbl ``grbl/protocol.c``
(``protocol_exec_rt_system``) the controller prints ``ALARM:N`` then ``[MSG:Reset to
continue]`` and then ignores every byte, ``?`` included (the wait loop there has an empty body:
no status report is printed), until a soft reset (0x18); it comes back with the banner and
``[MSG:'$H'|'$X' to unlock]``, locked in the Alarm state: ``<Alarm|...>`` reports, G-code
answered ``error:9``, until ``$H`` (homing) or ``$X`` (unlock). Alarm codes:
``doc/csv/alarm_codes_en_US.csv``.

The controller's input pins (GRBL 1.1 cpu_map: feed hold, cycle start, safety door), as an
operator would use them: :meth:`press_feed_hold` (state ``Hold:0``, the motion suspended),
:meth:`press_cycle_start` (resume), :meth:`set_door` (``Door:1`` while open, ``Door:0`` once
closed; cycle start resumes). ``$10=0`` makes status reports give ``WPos`` instead of
``MPos`` (interface.md; no work offsets here, so the values are the same).
"""

from __future__ import annotations

import re
import time

from polrig.drivers.emulators._pty import LinearMove, PtyEmulator, run_cli

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
AXES = "XYZA"
#: GRBL 1.1 settings of a 4-axis build, with this emulator's power-up values
DEFAULT_SETTINGS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 1, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0,
    32: 0,
    **{100 + i: 250.0 for i in range(len(AXES))},   # steps per unit
    **{110 + i: 3600.0 for i in range(len(AXES))},  # maximum rate, units/min
    **{120 + i: 100.0 for i in range(len(AXES))},   # acceleration, units/s^2
    **{130 + i: 360.0 for i in range(len(AXES))},   # maximum travel, units
}
#: integer-valued settings (printed without decimals, as GRBL does)
_INTEGER_SETTINGS = frozenset({0, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 30, 31, 32})
_WORD = re.compile(r"([A-Z])([-+]?[0-9]*\.?[0-9]*)")


class GrblEmulator(PtyEmulator):
    name = "grbl"
    # "reset": the controller resets (brown-out, DTR pulse) on receiving the next line, which
    # it never executes: the banner comes instead of the line's ``ok``
    # "hard_limit": a limit switch fires half way through the next motion (ALARM:1);
    # "soft_limit": the next G-code motion is a soft-limit alarm (ALARM:2), nothing moves
    FAULTS = PtyEmulator.FAULTS + ("reset", "hard_limit", "soft_limit")

    def __init__(self, *, link=None, speed_factor: float = 1.0, homing_enabled: bool = True,
                 max_rate_per_min: float = 3600.0, accel_per_s2: float = 100.0,
                 homing_s: float = 1.0, max_travel: float | None = None):
        super().__init__(link=link, speed_factor=speed_factor)
        self.settings = dict(DEFAULT_SETTINGS)
        for i in range(len(AXES)):
            self.settings[110 + i] = float(max_rate_per_min)
            self.settings[120 + i] = float(accel_per_s2)
            if max_travel is not None:
                self.settings[130 + i] = float(max_travel)
        self.settings[22] = 1 if homing_enabled else 0
        self.settings[20] = 1 if max_travel is not None else 0
        self.homing_s = homing_s
        self.pos = [0.0] * len(AXES)
        self.state = "Alarm" if homing_enabled else "Idle"
        self.absolute = True
        self.feed_rate = 0.0
        self.motion_mode = 0  # modal G0/G1
        self.queue: list[tuple[list[float], float]] = []  # (target, rate units/min)
        self.move: list[LinearMove] | None = None
        self.move_start_pos: list[float] | None = None
        self.homing_until = 0.0
        self.critical = False  # halted after a hard/soft limit until a soft reset
        # a '?' received during a homing cycle: answered when the cycle ends (limits.c: "No
        # time to run protocol_execute_realtime() in this loop"; commands.md, '?')
        self._report_pending = False
        self._rate = 0.0  # units/min of the motion that runs (the FS: real-time feed rate)
        #: something in the way: (axis letter, position) where a motion closes a limit
        #: switch (ALARM:1), until the operator takes it away (``None``)
        self.obstacle: tuple[str, float] | None = None
        self._fails = False
        self._line = bytearray()

    # -- settings ($$) ----------------------------------------------------------------------
    @property
    def homing_enabled(self) -> bool:
        return bool(self.settings[22])

    @property
    def status_mask(self) -> int:
        """``$10``: bit 0 set reports MPos, clear reports WPos."""
        return int(self.settings[10])

    @property
    def max_rate(self) -> float:
        """The slowest axis maximum rate (units/min) of ``$110..``: the rate of G0 moves."""
        return min(self.settings[110 + i] for i in range(len(AXES)))

    def _settings_lines(self) -> bytes:
        out = []
        for n in sorted(self.settings):
            v = self.settings[n]
            out.append(f"${n}={int(v)}" if n in _INTEGER_SETTINGS else f"${n}={v:.3f}")
        return "".join(line + "\r\n" for line in out).encode()

    def _set_setting(self, cmd: str) -> None:
        key, _, value = cmd.partition("=")
        if not key.isdigit() or int(key) not in self.settings:
            self._error(3)
            return
        try:
            v = float(value)
        except ValueError:
            self._error(2)
            return
        if v < 0 or (int(key) in _INTEGER_SETTINGS and v != int(v)):
            self._error(2)
            return
        self.settings[int(key)] = v
        self._ok()

    def start(self):
        super().start()
        self._banner()
        return self

    def _banner(self) -> None:
        self.send(BANNER)
        if self.state == "Alarm":
            self.send(b"[MSG:'$H'|'$X' to unlock]\r\n")

    def axis_position(self, axis: str = "A") -> float:
        with self.lock:
            self.tick(time.monotonic())
            return self.pos[AXES.index(axis)]

    def garble(self, data: bytes) -> bytes:
        return bytes(b | 0x80 for b in data[:-2]) + data[-2:]

    # -- motion ----------------------------------------------------------------------------
    def _begin_next(self, now: float) -> None:
        if self.move is not None or not self.queue or self.state not in ("Idle", "Run"):
            if self.move is None and not self.queue and self.state == "Run":
                self.state = "Idle"
            return
        target, rate = self.queue.pop(0)
        dist = max(abs(t - p) for t, p in zip(target, self.pos)) or 0.0
        speed = rate / 60.0 * self.speed_factor
        dur = dist / speed if speed > 0 else 0.0
        self.move = [LinearMove(p, t, abs(t - p) / dur if dur else 1.0, now)
                     for p, t in zip(self.pos, target)]
        self._rate = rate
        self.state = "Run"
        self._fails = self.take_fault("error_mid_move") or self.take_fault("hard_limit")

    def tick(self, now: float) -> None:
        if self.state == "Home":
            if now >= self.homing_until:
                self.pos = [0.0] * len(AXES)
                if self._report_pending:  # motion_control.c: realtime runs after the cycle
                    self._report_pending = False
                    self.send(self._status_line())
                self.state = "Idle"
                self.send(b"ok\r\n")
            return
        if self.move is not None and self.state == "Run":
            mid = max(m.midpoint_time for m in self.move)
            if self._fails and now >= mid:
                self.pos = [m.position(now) for m in self.move]
                self._alarm(1)
                return
            new = [m.position(now) for m in self.move]
            if self._hits_obstacle(self.pos, new):
                return
            self.pos = new
            if all(m.done(now) for m in self.move):
                self.move = None
                self._begin_next(now)
                if self.move is None:
                    self.state = "Idle"
        elif self.state in ("Idle", "Run"):
            self._begin_next(now)

    def _hits_obstacle(self, old: list[float], new: list[float]) -> bool:
        """A motion from ``old`` to ``new`` that reaches :attr:`obstacle` stops there with a
        hard-limit alarm (the switch it pushed)."""
        if self.obstacle is None:
            return False
        i, at = AXES.index(self.obstacle[0]), float(self.obstacle[1])
        if old[i] == new[i] or old[i] == at or not min(old[i], new[i]) <= at <= max(old[i], new[i]):
            return False
        self.pos = list(new)
        self.pos[i] = at
        self._alarm(1)
        return True

    def _alarm(self, code: int) -> None:
        self.move, self.queue, self._fails = None, [], False
        self.state = "Alarm"
        self.send(f"ALARM:{code}\r\n".encode())
        if code in (1, 2):  # protocol.c: hard and soft limits halt until reset
            self.critical = True
            self.send(b"[MSG:Reset to continue]\r\n")

    def trip_hard_limit(self) -> None:
        """A limit switch closes now (something in the way): any motion stops at once
        (position lost), ``ALARM:1`` and ``[MSG:Reset to continue]``; nothing if the
        controller is in Alarm already (limits.c)."""
        with self.lock:
            now = time.monotonic()
            self.tick(now)
            if self.critical or self.state == "Alarm":
                return
            if self.move is not None:
                self.pos = [m.position(now) for m in self.move]
            self._alarm(1)

    # -- input pins ------------------------------------------------------------------------
    def press_feed_hold(self) -> None:
        with self.lock:
            self.feed(b"!", time.monotonic())

    def press_cycle_start(self) -> None:
        with self.lock:
            self.feed(b"~", time.monotonic())

    def set_door(self, is_open: bool) -> None:
        """Safety door switch: opening suspends any motion (``Door:1``), closing makes it
        ready to resume (``Door:0``); cycle start then resumes."""
        with self.lock:
            now = time.monotonic()
            self.tick(now)
            if self.critical or self.state in ("Alarm", "Sleep"):
                return
            if is_open:
                self._suspend(now)
                self.state = "Door:1"
            elif self.state.startswith("Door"):
                self.state = "Door:0"

    def _suspend(self, now: float) -> None:
        """Stop the running move where it is and keep the rest queued (resumable)."""
        if self.move is not None:
            self.pos = [m.position(now) for m in self.move]
            rest = [m.target for m in self.move]
            self.queue.insert(0, (rest, self.max_rate))
            self.move = None

    def on_disconnect(self) -> None:
        # GRBL boards are USB-powered through the Arduino: unplugging resets the controller.
        self.tick(time.monotonic())
        self._power_on()

    def _power_on(self) -> None:
        self.move, self.queue, self._line = None, [], bytearray()
        self._report_pending = False
        self.critical = False
        self.state = "Alarm" if self.homing_enabled else "Idle"

    def on_reconnect(self) -> None:
        self._banner()

    # -- input -----------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> None:
        for b in data:
            if self.critical and b != 0x18:
                continue  # halted: everything but a soft reset is ignored (protocol.c)
            if b == ord("?"):
                self._report(now)
            elif b == ord("!"):
                if self.state == "Run" and self.move is not None:
                    self._suspend(now)
                    self.state = "Hold:0"
            elif b == ord("~"):
                if self.state.startswith("Hold") or self.state == "Door:0":
                    self.state = "Idle"
                    self._begin_next(now)
            elif b == 0x18:
                self._soft_reset(now)
            elif b in (ord("\n"), ord("\r")):
                line, self._line = bytes(self._line), bytearray()
                if line.strip():
                    self._execute(line.decode("ascii", "replace").strip().upper(), now)
            else:
                self._line.append(b)

    def _report(self, now: float) -> None:
        self.tick(now)
        if self.state == "Home":  # no report while homing: it comes when the cycle ends
            self._report_pending = True
            return
        self.send(self._status_line())

    def _status_line(self) -> bytes:
        pos = ",".join(f"{p:.3f}" for p in self.pos)
        frame = "MPos" if self.status_mask & 1 else "WPos"  # WPos = MPos - WCO, WCO = 0
        # FS: the real-time feed rate (interface.md), stepper.c st_get_realtime_rate(): the
        # current speed in a motion state, 0 otherwise (a hold here is complete at once)
        rate = self._rate if self.state == "Run" and self.move is not None else 0.0
        return f"<{self.state}|{frame}:{pos}|FS:{rate:.0f},0>\r\n".encode()

    def _soft_reset(self, now: float) -> None:
        self._line = bytearray()
        self._report_pending = False  # a reset clears the pending real-time requests
        self.critical = False
        if self.state == "Run" or self.state == "Home":
            self.pos = [m.position(now) for m in self.move] if self.move else self.pos
            self._alarm(3 if self.state == "Run" else 6)
        else:
            self.move, self.queue = None, []
            # grbl main.c: a reset out of Alarm or Sleep comes back locked in Alarm
            self.state = "Alarm" if self.state in ("Alarm", "Sleep") else "Idle"
        self._banner()

    def _ok(self) -> None:
        self.send(b"ok\r\n")

    def _error(self, code: int) -> None:
        self.send(f"error:{code}\r\n".encode())

    def _execute(self, line: str, now: float) -> None:
        if self.take_fault("reset"):
            self._power_on()
            self._banner()
            return
        if self.state == "Sleep":
            return  # asleep: nothing but a reset is processed
        if line.startswith("$"):
            cmd = line[1:]
            if cmd == "X":
                if self.state == "Alarm":
                    self.state = "Idle"
                    self.send(b"[MSG:Caution: Unlocked]\r\n")
                self._ok()
            elif cmd == "H":
                if not self.homing_enabled:
                    self._error(5)
                elif self.state not in ("Idle", "Alarm"):
                    self._error(8)
                else:
                    self.state = "Home"
                    self.homing_until = now + self.homing_s / self.speed_factor
            elif cmd == "$":
                if self.state in ("Run", "Home") or self.state.startswith("Hold"):
                    self._error(8)  # system.c: blocked during a cycle, takes too long to print
                    return
                self.send(self._settings_lines())
                self._ok()
            elif "=" in cmd and cmd.partition("=")[0].isdigit():
                self._set_setting(cmd)
            elif cmd == "SLP":
                # $SLP: de-energize and sleep; the only way out is a reset (commands.md)
                self.move, self.queue = None, []
                self._ok()
                self.state = "Sleep"
                self.send(b"[MSG:Sleeping]\r\n")
            elif cmd == "I":
                if self.state not in ("Idle", "Alarm"):
                    self._error(8)  # system.c: $I only in Idle or Alarm
                    return
                self.send(b"[VER:1.1h.20190825:ROTARY]\r\n[OPT:V,15,128]\r\n")
                self._ok()
            elif cmd == "":
                self.send(b"[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]\r\n")
                self._ok()
            else:
                self._error(3)
            return
        if self.state == "Alarm":
            self._error(9)
            return
        words = _WORD.findall(line.replace(" ", ""))
        if "".join(l + n for l, n in words) != line.replace(" ", ""):
            self._error(1)
            return
        target = list(self.queue[-1][0]) if self.queue else (
            [m.target for m in self.move] if self.move else list(self.pos))
        motion, has_axis = self.motion_mode, False
        absolute, feed = self.absolute, self.feed_rate
        groups: set[str] = set()
        for letter, num in words:
            try:
                value = float(num)
            except ValueError:
                self._error(2)
                return
            if letter == "G":
                group = "motion" if value in (0, 1) else "distance" if value in (90, 91) else ""
                if group and group in groups:
                    self._error(21)  # two commands of one modal group in a block
                    return
                groups.add(group)
                if value in (0, 1):
                    motion = int(value)
                elif value == 90:
                    absolute = True
                elif value == 91:
                    absolute = False
                elif value == 21:
                    pass
                else:
                    self._error(20)
                    return
            elif letter == "F":
                feed = value
            elif letter in AXES:
                i = AXES.index(letter)
                target[i] = value if absolute else target[i] + value
                has_axis = True
            else:
                self._error(20)
                return
        if motion == 1 and feed <= 0:
            self._error(22)
            return
        self.absolute, self.feed_rate, self.motion_mode = absolute, feed, motion
        if has_axis and self.take_fault("soft_limit"):
            self._alarm(2)  # injected: as if the target were beyond the travel
            return
        if has_axis and self.settings[20]:
            if any(not -self.settings[130 + i] <= t <= 0 for i, t in enumerate(target)):
                # GRBL 1.1: a G-code target beyond the machine travel is a soft-limit alarm
                self._alarm(2)
                return
        if has_axis:
            start = list(self.queue[-1][0]) if self.queue else (
                [m.target for m in self.move] if self.move else list(self.pos))
            moving = [i for i, (a, b) in enumerate(zip(start, target)) if a != b] or [0]
            top = min(self.settings[110 + i] for i in moving)  # each axis's $11x limits
            self.queue.append((target, top if motion == 0 else min(feed, top)))
            self._begin_next(now)
        self._ok()


def main(argv: list[str] | None = None) -> None:
    run_cli(GrblEmulator, "Emulated GRBL 1.1 rotary-axis controller on a pseudo-terminal.",
            argv)


if __name__ == "__main__":
    main()
