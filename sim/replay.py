"""A simulated camera that replays frames rendered beforehand.

:class:`ReplayCamera` behaves as :class:`polrig.sim.devices.SimCamera` in every respect the rig sees
(settings, trigger, timing on the world's clock: exposure plus readout per frame, the axes'
positions at mid-exposure), but its frames are not rendered at grab time: they are rendered
once by :meth:`ReplayCamera.record` (one raw mosaic per polarizer state) and each grab returns
a copy of the recording nearest to the stage's angle at mid-exposure, whatever the turntable
angle. That is what a real camera costs the host: a frame arrives after exposure and readout,
with no CPU spent making it. Benchmarks use it to time a full-sensor session against the
rig's own hardware time (``python -m benchmarks throughput``) without counting the
simulator's rendering as hardware.
"""

from __future__ import annotations

import numpy as np

from polrig.errors import ConfigError
from polrig.sim.devices import SimCamera


class ReplayCamera(SimCamera):
    """A :class:`SimCamera` whose grabs replay recorded frames (see the module docstring)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self._recorded: dict[float, np.ndarray] = {}
        self._recorded_settings: tuple | None = None

    def _settings(self) -> tuple:
        return (self._exposure_us, self._gain_db, self._roi, self._pixel_format)

    def record(self, stage_angles_deg, turntable_deg: float = 0.0) -> None:
        """Render one raw mosaic per stage angle at ``turntable_deg`` with the current
        settings (exposure, gain, ROI, pixel format) and keep them for replay."""
        self._recorded = {float(a): self._render(turntable_deg, float(a))
                          for a in stage_angles_deg}
        self._recorded_settings = self._settings()

    def _render(self, turntable_deg: float, stage_deg: float) -> np.ndarray:
        return super()._expose(turntable_deg, stage_deg)

    def _expose(self, turntable_deg: float, stage_deg: float) -> np.ndarray:
        if not self._recorded:
            raise ConfigError("replay camera: nothing recorded; call record() first")
        if self._settings() != self._recorded_settings:
            raise ConfigError(f"replay camera: frames were recorded with exposure, gain, ROI "
                              f"and format {self._recorded_settings}, the camera is now set to "
                              f"{self._settings()}")
        angles = np.array(list(self._recorded))
        # polarizer states repeat every 180 deg
        dist = np.abs((angles - stage_deg + 90.0) % 180.0 - 90.0)
        return self._recorded[float(angles[int(np.argmin(dist))])].copy()
