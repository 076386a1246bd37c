"""Rig calibration: camera intrinsics, turntable axis, light position, generator (incident
Stokes states), DoFP analyzer; calibration set files. See ``docs/calibration.md``.

``calibration.load(DIR)`` reads a calibration set (:class:`calibration.calset.CalibrationSet`).
"""

from calibration.calset import CalibrationSet, load

__all__ = ["CalibrationSet", "load"]
