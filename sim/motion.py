"""Trapezoidal motion profiles of the simulated rotation stage and turntable.

A move from ``start_deg`` to ``target_deg`` accelerates at ``accel_deg_s2`` up to
``speed_deg_s``, cruises, and decelerates to rest (a triangular profile when the move is too
short to reach full speed), as stepper/servo motion controllers do (e.g. the Thorlabs APT
velocity profile: acceleration, maximum velocity). Times are :class:`polrig.sim.clock.SimClock`
seconds.
"""

from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class Move:
    start_deg: float
    target_deg: float
    t_start_s: float
    speed_deg_s: float
    accel_deg_s2: float

    @property
    def _phases(self) -> tuple[float, float, float]:
        """``(t_acc, t_cruise, peak speed)``."""
        d = abs(self.target_deg - self.start_deg)
        v, a = self.speed_deg_s, self.accel_deg_s2
        if d <= v * v / a:  # triangular
            t_acc = math.sqrt(d / a)
            return t_acc, 0.0, a * t_acc
        return v / a, (d - v * v / a) / v, v

    @property
    def duration_s(self) -> float:
        t_acc, t_cruise, _ = self._phases
        return 2.0 * t_acc + t_cruise

    @property
    def t_end_s(self) -> float:
        return self.t_start_s + self.duration_s

    def position(self, t_s: float) -> float:
        """Angle (degrees) at simulated time ``t_s``."""
        t = t_s - self.t_start_s
        if t <= 0:
            return self.start_deg
        if t >= self.duration_s:
            return self.target_deg
        t_acc, t_cruise, vp = self._phases
        a = self.accel_deg_s2
        if t < t_acc:
            s = 0.5 * a * t * t
        elif t < t_acc + t_cruise:
            s = 0.5 * a * t_acc * t_acc + vp * (t - t_acc)
        else:
            td = self.duration_s - t
            s = abs(self.target_deg - self.start_deg) - 0.5 * a * td * td
        return self.start_deg + math.copysign(s, self.target_deg - self.start_deg)
