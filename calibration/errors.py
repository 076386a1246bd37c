"""Typed errors of the calibration procedures. Each message names what to change."""

from __future__ import annotations

from polrig.errors import PolrigError


class CalibrationError(PolrigError, ValueError):
    """A calibration input cannot give a result (too few views, degenerate geometry)."""


class BoardNotFound(CalibrationError):
    """The ChArUco board is not (sufficiently) visible in an image."""


class SphereNotFound(CalibrationError):
    """No mirror sphere silhouette could be found in an image."""


class SphereSaturated(CalibrationError):
    """The specular highlight on the mirror sphere is clipped at the sensor's maximum."""


class TooFewAngles(CalibrationError):
    """Too few stage or turntable angles for the fit to be determined."""


#: What the images of a step could not give (the board or sphere not seen or clipped, too few
#: views or angles): a failure while running (``polrig calibrate`` exits 1), not a bad request.
IMAGE_FAILURES = (BoardNotFound, SphereNotFound, SphereSaturated, TooFewAngles)


class SceneTooDark(PolrigError):
    """The scene stays too dark at the longest exposure the procedures can use (light off or
    far too dim): a failure while running (exit 1), not a bad input."""
