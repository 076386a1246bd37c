"""Simulated time for the simulated devices, with an acceleration factor.

``SimClock(speed)`` runs ``speed`` simulated seconds per real second: motion that takes 4.5 s
at ``speed=1`` (the real-time default) takes 4.5 ms of wall time at ``speed=1000``.
``speed=inf`` is a purely virtual clock: time stands still except when a device waits
(:meth:`SimClock.sleep` advances it instantly), which makes tests deterministic and fast.
Thread-safe.
"""

from __future__ import annotations

import math
import threading
import time


class SimClock:
    def __init__(self, speed: float = 1.0) -> None:
        speed = float(speed)
        if not (speed > 0):
            raise ValueError(f"clock speed must be > 0 (inf = virtual), got {speed}")
        self.speed = speed
        self._t0 = time.monotonic()
        self._offset = 0.0
        self._lock = threading.Lock()

    @property
    def virtual(self) -> bool:
        return math.isinf(self.speed)

    def now(self) -> float:
        """Simulated seconds since the clock was made."""
        with self._lock:
            if self.virtual:
                return self._offset
            return self._offset + (time.monotonic() - self._t0) * self.speed

    def sleep(self, duration_s: float) -> None:
        """Let ``duration_s`` simulated seconds pass (real sleep of ``duration_s / speed``)."""
        duration_s = max(0.0, float(duration_s))
        if self.virtual:
            with self._lock:
                self._offset += duration_s
            return
        time.sleep(duration_s / self.speed)

    def advance(self, duration_s: float) -> None:
        """Jump the simulated time forward without sleeping (e.g. exposure on a fast clock)."""
        with self._lock:
            self._offset += max(0.0, float(duration_s))
