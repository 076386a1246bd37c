"""One lock per device of the rig, so that calls from the GUI's worker threads never overlap.

The live worker holds ``camera`` for each grab, the devices worker holds the device it drives,
a capture holds all four for the whole session. Locks are taken with a timeout: a thread that
cannot get a device in time gets :class:`DeviceBusy` (a readable message) instead of waiting,
so no thread waits on another one indefinitely. The UI thread never takes these locks.
"""

from __future__ import annotations

import contextlib
import threading
from typing import Iterator

from polrig.errors import PolrigError

DEVICE_KINDS = ("camera", "stage", "turntable", "light")


class DeviceBusy(PolrigError):
    """The device is in use by another part of the GUI (a capture, a calibration step)."""


class RigLocks:
    """Re-entrant locks per device kind (``camera``, ``stage``, ``turntable``, ``light``)."""

    def __init__(self) -> None:
        self._locks = {k: threading.RLock() for k in DEVICE_KINDS}
        self.owner: dict[str, str] = {}

    @contextlib.contextmanager
    def hold(self, *kinds: str, timeout_s: float = 1.0, who: str = "") -> Iterator[None]:
        """Hold the locks of ``kinds`` (all devices when none are named); raise
        :class:`DeviceBusy` naming the holder if one is not free within ``timeout_s``."""
        kinds = kinds or DEVICE_KINDS
        taken = []
        try:
            for k in kinds:
                if not self._locks[k].acquire(timeout=timeout_s):
                    holder = self.owner.get(k) or "another task"
                    raise DeviceBusy(f"{k} is busy ({holder})")
                taken.append(k)
                self.owner.setdefault(k, who)
            yield
        finally:
            for k in reversed(taken):
                if self.owner.get(k) == who:
                    self.owner.pop(k, None)
                self._locks[k].release()
