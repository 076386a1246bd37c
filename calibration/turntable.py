"""Turntable axis in camera coordinates from board poses at several turntable angles.

A board fixed on the turntable has pose ``(R_i, t_i)`` (board -> camera) at turntable angle
``a_i``. The relative motion ``R_i R_0^T`` is a rotation about the turntable axis ``w``, so
``(R_i R_0^T - I) w = 0`` for every view: ``w`` is the right singular vector of the stacked
``R_i R_0^T - I`` with the smallest singular value (its sign makes the rotations right-handed
for increasing turntable angle, :class:`polrig.hal.Turntable`). A point ``c`` on the axis
satisfies ``(I - R_rel) c = t_i - R_rel t_0``, solved by linear least squares together with
``w . c = w . mean(t_i)`` (the point of the axis nearest to the board origins).

Reference: R. Y. Tsai and R. K. Lenz, "A new technique for fully autonomous and efficient 3D
robotics hand/eye calibration", IEEE Trans. Robot. Autom. 5(3), 1989 (rotation axis from
relative motions); Rodrigues' formula.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from calibration.errors import TooFewAngles


def rotation_angle_deg(R: np.ndarray, axis: np.ndarray) -> float:
    """Signed rotation angle (degrees) of rotation matrix ``R`` about unit ``axis``."""
    s = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) @ axis
    c = 0.5 * (np.trace(R) - 1.0)
    return float(np.degrees(np.arctan2(s, c)))


@dataclasses.dataclass(frozen=True)
class TurntableAxisResult:
    """The turntable axis in camera coordinates.

    ``axis_cam`` unit vector (the turntable's "up", right-handed for increasing angles),
    ``point_cam_m`` the axis point nearest to the board origins, ``axis_std_deg`` the
    one-sigma angular uncertainty of the direction, ``point_std_m`` per coordinate;
    ``angle_scale`` the fitted ratio measured/commanded rotation (1 for a true encoder),
    ``zero_angle_deg`` the measured rotation at commanded angle 0 (the turntable's zero
    relative to the first view), ``angle_residuals_deg`` measured minus fitted rotation per view,
    ``zero_direction_cam`` the unit vector from the axis towards the board origin at
    turntable angle 0 (perpendicular to the axis).
    """

    axis_cam: np.ndarray
    point_cam_m: np.ndarray
    axis_std_deg: float
    point_std_m: np.ndarray
    angle_scale: float
    zero_angle_deg: float
    angle_residuals_deg: np.ndarray
    zero_direction_cam: np.ndarray
    circle_residual_rms_m: float

    def to_json(self) -> dict:
        return {"axis_cam": self.axis_cam.tolist(), "point_cam_m": self.point_cam_m.tolist(),
                "axis_std_deg": self.axis_std_deg, "point_std_m": self.point_std_m.tolist(),
                "angle_scale": self.angle_scale, "zero_angle_deg": self.zero_angle_deg,
                "angle_residuals_deg": self.angle_residuals_deg.tolist(),
                "zero_direction_cam": self.zero_direction_cam.tolist(),
                "circle_residual_rms_m": self.circle_residual_rms_m}


def fit_turntable_axis(rotations: np.ndarray, translations_m: np.ndarray,
                       turntable_angles_deg: np.ndarray) -> TurntableAxisResult:
    """Fit the axis from board poses ``rotations`` ``(N, 3, 3)``, ``translations_m`` ``(N, 3)``
    (board -> camera) taken at ``turntable_angles_deg`` ``(N,)``.

    Needs at least 3 views spanning at least 20 degrees; raises :class:`TooFewAngles`
    otherwise.
    """
    Rs = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    ts = np.asarray(translations_m, dtype=np.float64).reshape(-1, 3)
    ang = np.asarray(turntable_angles_deg, dtype=np.float64).reshape(-1)
    n = len(Rs)
    if n != len(ts) or n != len(ang):
        raise ValueError(f"need one pose per angle: {len(Rs)} rotations, {len(ts)} "
                         f"translations, {len(ang)} angles")
    if n < 3 or np.ptp(ang) < 20.0:
        raise TooFewAngles(f"turntable axis needs 3+ board views spanning 20+ degrees, got {n} "
                           f"views over {np.ptp(ang) if n else 0:.1f} deg; add turntable angles")
    if not (np.all(np.isfinite(Rs)) and np.all(np.isfinite(ts)) and np.all(np.isfinite(ang))):
        raise ValueError("board poses and turntable angles must be finite")
    i0 = int(np.argmin(np.abs(ang)))
    R0, t0 = Rs[i0], ts[i0]
    rel = Rs @ R0.T  # (N, 3, 3)
    A = (rel - np.eye(3)).reshape(-1, 3)
    _, sv, vt = np.linalg.svd(A)
    w = vt[-1]
    dang = ang - ang[i0]
    meas = np.array([rotation_angle_deg(r, w) for r in rel])
    if np.sum(meas * dang) < 0:
        w = -w
        meas = -meas
    # angular uncertainty of w: residual scale over the curvature of the stacked system
    dof = max(A.shape[0] - 2, 1)
    sigma2 = sv[-1] ** 2 / dof
    axis_std_deg = float(np.degrees(np.sqrt(sigma2 / sv[-2] ** 2 + sigma2 / sv[-3] ** 2)))
    # measured rotation versus commanded: scale and zero
    X = np.stack([dang, np.ones(n)], axis=1)
    coef, *_ = np.linalg.lstsq(X, meas, rcond=None)
    ang_res = meas - X @ coef
    # a point on the axis
    M = np.concatenate([(np.eye(3) - rel).reshape(-1, 3), w[None]], axis=0)
    rhs = np.concatenate([(ts - rel @ t0).reshape(-1), [w @ ts.mean(0)]])
    c, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    r = M @ c - rhs
    dof_c = max(M.shape[0] - 3, 1)
    cov_c = (r @ r / dof_c) * np.linalg.pinv(M.T @ M)
    # circle residual: distance of board origins from the axis should be constant
    d = ts - c
    radial = np.linalg.norm(d - np.outer(d @ w, w), axis=1)
    z = t0 - c
    z = z - (z @ w) * w
    zn = np.linalg.norm(z)
    return TurntableAxisResult(
        axis_cam=w, point_cam_m=c, axis_std_deg=axis_std_deg,
        point_std_m=np.sqrt(np.clip(np.diag(cov_c), 0, None)),
        angle_scale=float(coef[0]),
        zero_angle_deg=float(coef[1] - coef[0] * ang[i0]),
        angle_residuals_deg=ang_res,
        zero_direction_cam=z / zn if zn > 0 else z,
        circle_residual_rms_m=float(np.std(radial)))


def axis_angle_error_deg(axis_a: np.ndarray, axis_b: np.ndarray) -> float:
    """Angle in degrees between two directions (sign-sensitive: opposite axes give 180)."""
    a = np.asarray(axis_a, float) / np.linalg.norm(axis_a)
    b = np.asarray(axis_b, float) / np.linalg.norm(axis_b)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))
