"""Rig calibration: camera intrinsics, turntable axis, light position, generator (incident
Stokes states), DoFP analyzer; calibration set files. See ``docs/calibration.md``.

``calibration.load(DIR)`` reads a calibration set (:class:`polrig.calibration.calset.CalibrationSet`).
"""

from polrig.calibration.calset import CalibrationSet, load

__all__ = ["CalibrationSet", "load"]
