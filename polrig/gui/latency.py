"""Event-loop latency probe: how late a periodic Qt timer fires while the UI is busy.

A :class:`QTimer` at ``interval_ms`` records the time between its ticks; the worst lateness
(``max gap - interval``) is how long the UI thread could not process events. Used by the GUI
tests (a device fault must not freeze the window) and by ``benchmarks/bench_gui.py``.
"""

from __future__ import annotations

from PySide6.QtCore import QElapsedTimer, QTimer


class EventLoopProbe:
    """Start with :meth:`start`, stop with :meth:`stop`; read :attr:`max_latency_s`."""

    def __init__(self, interval_ms: int = 10) -> None:
        self.interval_s = interval_ms * 1e-3
        self.gaps_s: list[float] = []
        self._clock = QElapsedTimer()
        self._last_ns = 0
        self._timer = QTimer()
        self._timer.setInterval(interval_ms)
        self._timer.timeout.connect(self._tick)

    def _tick(self) -> None:
        now = self._clock.nsecsElapsed()
        self.gaps_s.append((now - self._last_ns) * 1e-9)
        self._last_ns = now

    def start(self) -> "EventLoopProbe":
        self._clock.start()
        self._last_ns = self._clock.nsecsElapsed()
        self._timer.start()
        return self

    def stop(self) -> None:
        self._timer.stop()

    @property
    def max_latency_s(self) -> float:
        """Worst delay beyond the timer interval (NaN before the first tick)."""
        return max(self.gaps_s) - self.interval_s if self.gaps_s else float("nan")
