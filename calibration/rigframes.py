"""Rig geometry in camera coordinates for the calibration procedures.

Everything here is in the camera frame (OpenCV, metres; ``docs/conventions.md``): the
calibrated turntable axis is the rig's "up", the light position comes from the mirror-sphere
fit, and the polarizer stage's zero axis is defined (as the simulator and the lab rig define
it) as the horizontal direction perpendicular to the illumination axis:
``x0 = (k x up) / |k x up|`` with ``k`` the illumination direction from the light towards the
turntable axis. Only the horizontal part of ``k`` matters, so any point of the axis serves.
"""

from __future__ import annotations

import numpy as np

from polrig.calibration.light import pixel_rays
from polrig.optics import bases as fr


def stage_zero_axis_cam(light_cam_m: np.ndarray, axis_point_cam_m: np.ndarray,
                        up_cam: np.ndarray) -> np.ndarray:
    """Unit stage zero axis in camera coordinates (see the module docstring)."""
    up = np.asarray(up_cam, float) / np.linalg.norm(up_cam)
    k = np.asarray(axis_point_cam_m, float) - np.asarray(light_cam_m, float)
    x = np.cross(k / np.linalg.norm(k), up)
    n = np.linalg.norm(x)
    if n < 1e-9:
        raise ValueError("the light lies on the turntable axis: the stage zero axis is undefined")
    return x / n


def pixel_rays_grid(K: np.ndarray, dist: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Unit camera rays ``(H, W, 3)`` through every pixel centre."""

    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(np.float64)
    return pixel_rays(pts, K, dist).reshape(h, w, 3)


def intersect_plane(rays: np.ndarray, point_m: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Points ``(..., 3)`` where camera rays (from the origin) meet a plane; NaN where parallel
    or behind the camera."""
    n = np.asarray(normal, float)
    den = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.asarray(point_m, float) @ n) / den
    t = np.where((np.abs(den) > 1e-12) & (t > 0), t, np.nan)
    return rays * t[..., None]


def board_plane(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(point, front normal)`` of a board with pose ``p_cam = R p_board + t``: the board's
    ``z`` points into the board (:mod:`polrig.calibration.charuco`), so the printed side faces
    ``-R[:, 2]``."""
    n = -np.asarray(R, float)[:, 2]
    if n @ np.asarray(t, float) > 0:  # make it face the camera
        n = -n
    return np.asarray(t, float), n


def incident_basis_angle_deg(wi: np.ndarray, zero_axis: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Angle (degrees) of the transverse ``direction`` ``(..., 3)`` in the incident frame of
    light arriving along ``-wi`` (``x`` = the stage zero axis made perpendicular), measured
    from ``x`` towards ``y = k x x`` (``docs/conventions.md``)."""
    f = fr.incident_frame(wi, zero_axis)
    return np.rad2deg(np.arctan2(fr.dot(direction, f.y), fr.dot(direction, f.x)))
