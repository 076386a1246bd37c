"""Alias of :mod:`calibration.calset` under the name :mod:`polrig.processing` imports
(``calibration.calibset.load(DIR)``)."""

from calibration.calset import CalibrationSet, load

__all__ = ["CalibrationSet", "load"]
