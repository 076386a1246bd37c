"""A GRBL 1.1 controller driving the object turntable on one rotary axis (:class:`Turntable`).

Protocol: grbl/grbl ``doc/markdown/interface.md`` and ``doc/markdown/commands.md`` (GRBL
1.1): G-code lines are answered ``ok`` or ``error:N`` (texts from ``doc/csv``, see
:mod:`drivers.grbl_codes`); real-time single bytes without newline: ``?`` status report
``<State|MPos:...|...>``, ``!`` feed hold, ``~`` resume, ``0x18`` soft reset (answered by the
``Grbl 1.1x ['$' for help]`` banner); ``$H`` homing (``ok`` after the cycle), ``$X`` unlock,
``$I`` build info; ``ALARM:N`` lines are pushed asynchronously. ``ok`` acknowledges that a
motion was *planned*, not finished: completion is seen by polling ``?`` until ``Idle``.

The turntable axis letter (default ``A``) and its position in the ``MPos`` list (``axes``,
default ``"XYZA"``) come from the rig configuration, and ``degrees_per_unit`` converts the
axis units (GRBL's ``$10x`` steps per unit setting decides what one unit is) to degrees.
Stopping uses feed hold then soft reset, which GRBL documents as the way to cancel a motion
without losing position. Angles: degrees, counter-clockwise seen from above
(``polrig.hal``).
"""

from __future__ import annotations

import time

from drivers._serial import SerialDevice, SerialLink
from drivers.grbl_codes import ALARMS, ERRORS
from polrig.errors import DeviceFault, DeviceTimeout, ProtocolError
from polrig.hal import DeviceInfo, Turntable

BAUDRATE = 115200
SOFT_RESET = b"\x18"


class GrblTurntable(SerialDevice, Turntable):
    def __init__(self, port: str, *, axis: str = "A", axes: str = "XYZA",
                 degrees_per_unit: float = 1.0, rate_per_min: float | None = None,
                 reply_timeout_s: float = 2.0, poll_s: float = 0.02, kind: str = "turntable"):
        axis = str(axis).upper()
        if len(axis) != 1 or axis not in axes:
            raise ValueError(f"axis {axis!r} is not one of the controller's axes {axes!r}")
        if not degrees_per_unit or degrees_per_unit != degrees_per_unit:
            raise ValueError(f"degrees_per_unit must be a non-zero number, got {degrees_per_unit!r}")
        self.port = port
        self.axis = axis
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

    # -- life cycle ------------------------------------------------------------------------
    def _handshake(self) -> None:
        self._reset()
        lines = self._command("$I")
        self._info = DeviceInfo(kind=self.kind, driver="grbl", model="GRBL",
                                firmware=self._banner, port=self.port,
                                extra={"build": [l for l in lines if l.startswith("[")],
                                       "axis": self.axis})
        self.status()

    def close(self) -> None:
        self._link.close()

    def info(self) -> DeviceInfo:
        if self._info is None:
            raise DeviceFault("device is not open", device=self._link.device)
        return self._info

    # -- protocol --------------------------------------------------------------------------
    def _readline(self, timeout_s: float, what: str) -> str:
        raw = self._link.read_until(b"\n", timeout_s, what=what).rstrip(b"\r")
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            self._resync()
            raise ProtocolError(f"garbled {what} {raw!r}", device=self._link.device) from None

    def _resync(self) -> None:
        time.sleep(0.05)
        self._link.discard_input()

    def _alarm(self, line: str) -> DeviceFault:
        code = int(line[6:]) if line[6:].strip().isdigit() else line[6:]
        self.state, self.last_alarm = "Alarm", code
        return self._alarm_fault()

    def _alarm_fault(self) -> DeviceFault:
        code = self.last_alarm if self.last_alarm is not None else "Alarm"
        return DeviceFault("alarm (home the turntable: polrig home turntable)",
                           device=self._link.device, code=code,
                           text=ALARMS.get(code, "controller locked in the Alarm state"))

    def _drain_pending(self) -> None:
        """Read what arrived unasked (late replies of a timed-out command, pushed messages)
        so it is not taken for the answer to the next command; remember any alarm."""
        if self._link.in_waiting() == 0:
            return
        time.sleep(0.01)
        for raw in self._link.discard_input().split(b"\n"):
            line = raw.strip().decode("ascii", "replace")
            if line.startswith("ALARM:"):
                self._alarm(line)

    def _reset(self) -> None:
        """Soft reset and wait for the banner (proves a GRBL is at the other end)."""
        self._link.write(SOFT_RESET)
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            line = self._readline(max(deadline - time.monotonic(), 0.0), "GRBL banner")
            if line.startswith("Grbl "):
                self._banner = line.split("[")[0].strip()
                return
            if line.startswith("ALARM:"):
                self.state = "Alarm"

    def _command(self, line: str, timeout_s: float | None = None) -> list[str]:
        """Send one line; return the lines before ``ok``; ``error:N``/``ALARM:N`` raise."""
        self._drain_pending()
        self._link.write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + (timeout_s or self.reply_timeout_s)
        out: list[str] = []
        while True:
            reply = self._readline(max(deadline - time.monotonic(), 0.0), f"reply to {line!r}")
            if reply == "ok":
                return out
            if reply.startswith("error:"):
                code_s = reply[6:]
                code = int(code_s) if code_s.isdigit() else code_s
                raise DeviceFault(f"{line!r} rejected", device=self._link.device, code=code,
                                  text=ERRORS.get(code, "unknown error"))
            if reply.startswith("ALARM:"):
                raise self._alarm(reply)
            if reply and not reply.startswith(("<", "[", "Grbl")):
                self._resync()
                raise ProtocolError(f"unexpected reply {reply!r} to {line!r}",
                                    device=self._link.device)
            out.append(reply)

    def status(self) -> dict:
        """One ``?`` status report: ``{"state": ..., "mpos": [...], "position_deg": ...}``."""
        self._drain_pending()
        self._link.write(b"?")
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            line = self._readline(max(deadline - time.monotonic(), 0.0), "status report")
            if line.startswith("ALARM:"):
                raise self._alarm(line)
            if line.startswith("<") and line.endswith(">"):
                return self._parse_status(line)
            if line.startswith("<"):
                self._resync()
                raise ProtocolError(f"truncated status report {line!r}", device=self._link.device)

    def _parse_status(self, line: str) -> dict:
        fields = line[1:-1].split("|")
        state = fields[0]
        mpos = None
        for f in fields[1:]:
            if f.startswith("MPos:"):
                try:
                    mpos = [float(v) for v in f[5:].split(",")]
                except ValueError:
                    mpos = None
        if mpos is None or len(mpos) <= self.axis_index:
            self._resync()
            raise ProtocolError(f"status report without axis {self.axis}: {line!r}",
                                device=self._link.device)
        self.state = state
        return {"state": state, "mpos": mpos,
                "position_deg": mpos[self.axis_index] * self.degrees_per_unit}

    # -- Turntable -------------------------------------------------------------------------
    def position_deg(self) -> float:
        return self.status()["position_deg"]

    def is_busy(self) -> bool:
        st = self.status()["state"]
        if st == "Alarm":
            raise self._alarm_fault()
        return st.split(":")[0] in ("Run", "Jog", "Home") or st == "Hold:1"

    def wait(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.is_busy():
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"motion did not end within {timeout_s:g} s",
                                    device=self._link.device)
            time.sleep(self.poll_s)

    def home(self, timeout_s: float = 60.0) -> None:
        """``$H``; if it does not finish in time the cycle is aborted by a soft reset (GRBL
        then reports ALARM:6, homing failed) so the machine never keeps moving unattended."""
        self._link.discard_input()
        try:
            self._command("$H", timeout_s=timeout_s)
        except DeviceTimeout:
            self._link.write(SOFT_RESET)
            time.sleep(0.05)
            self._drain_pending()
            raise
        self.state, self.last_alarm = "Idle", None

    def unlock(self) -> None:
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
            if exc.code == 9:  # G-code locked out: Alarm state after power-up, reset or limit
                raise DeviceFault("turntable is locked in the Alarm state (run `polrig home "
                                  "turntable`)", device=self._link.device, code=9,
                                  text=exc.text) from None
            raise
        if wait:
            self.wait(timeout_s)

    def stop(self) -> None:
        """Feed hold, wait for the hold to complete, then soft reset (position kept)."""
        self._link.write(b"!")
        deadline = time.monotonic() + self.reply_timeout_s
        while self.status()["state"] not in ("Hold:0", "Idle", "Alarm"):
            if time.monotonic() > deadline:
                raise DeviceTimeout("feed hold did not complete", device=self._link.device)
            time.sleep(self.poll_s)
        self._reset()
