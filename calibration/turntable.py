"""Turntable axis in camera coordinates from board poses at several turntable angles.

A board fixed on the turntable has pose ``(R_i, t_i)`` (board -> camera) at turntable angle
``a_i``. The relative motion ``R_i R_0^T`` is a rotation about the turntable axis ``w``, so
``(R_i R_0^T - I) w = 0`` for every view: ``w`` is the right singular vector of the stacked
``R_i R_0^T - I`` with the smallest singular value (its sign makes the rotations right-handed
for increasing turntable angle, :class:`polrig.acquisition.hal.Turntable`). A point ``c`` on the axis
satisfies ``(I - R_rel) c = t_i - R_rel t_0``, solved by linear least squares together with
``w . c = w . mean(t_i)`` (the point of the axis nearest to the board origins).

Reference: R. Y. Tsai and R. K. Lenz, "A new technique for fully autonomous and efficient 3D
robotics hand/eye calibration", IEEE Trans. Robot. Autom. 5(3), 1989 (rotation axis from
relative motions); Rodrigues' formula.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.calibration.charuco import board_pose
from polrig.calibration.errors import TooFewAngles


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


def _rodrigues(v: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(v, float).reshape(3, 1))[0]


def _perp_basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0, 0]) if abs(w[0]) < 0.9 else np.array([0, 1.0, 0])
    u1 = np.cross(w, a)
    u1 /= np.linalg.norm(u1)
    return u1, np.cross(w, u1)


def _axis_rotation(w: np.ndarray, angle_deg: float) -> np.ndarray:
    return _rodrigues(np.deg2rad(angle_deg) * w / np.linalg.norm(w))


def refine_turntable_axis(detections, turntable_angles_deg, K: np.ndarray,
                          dist: np.ndarray | None, initial: TurntableAxisResult,
                          iterations: int = 30) -> TurntableAxisResult:
    """Refine the axis by minimising the reprojection error of every detected board corner
    over all views at once, with the model
    ``p_cam = R_w(a_i) (R_0 X + t_0 - c) + c`` (``R_w(a)`` the rotation by the commanded
    turntable angle ``a`` about the axis ``w`` through ``c``; board pose ``R_0, t_0`` at angle
    0). Gauss-Newton/Levenberg-Marquardt on 10 parameters (axis 2, axis point 2, board pose 6)
    with a numerical Jacobian; the 1-sigma axis uncertainty comes from ``(J^T J)^-1`` scaled
    by the residual variance. This uses all corners of all views, so one badly posed view
    (a near-frontal board) cannot tilt the axis as it can in :func:`fit_turntable_axis`.
    """
    import cv2

    ang = np.asarray(turntable_angles_deg, float).reshape(-1)
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    obj = [d.object_m for d in detections]
    img = np.concatenate([d.corners_px for d in detections])
    w0 = initial.axis_cam / np.linalg.norm(initial.axis_cam)
    u1, u2 = _perp_basis(w0)
    c0 = initial.point_cam_m
    # initial board pose at angle 0 from the first view rotated back
    i0 = int(np.argmin(np.abs(ang)))
    R_i0, t_i0, _ = __import__("polrig.calibration.charuco", fromlist=["board_pose"]).board_pose(
        detections[i0], K, dist)
    Rb = _axis_rotation(w0, -ang[i0])
    R0 = Rb @ R_i0
    t0 = Rb @ (t_i0 - c0) + c0

    def unpack(p):
        w = w0 + p[0] * u1 + p[1] * u2
        w /= np.linalg.norm(w)
        c = c0 + p[2] * u1 + p[3] * u2
        R = _rodrigues(p[4:7]) @ R0
        t = t0 + p[7:10]
        return w, c, R, t

    def residuals(p):
        w, c, R, t = unpack(p)
        out = []
        for o, a in zip(obj, ang):
            Ra = _axis_rotation(w, a)
            pc = (o @ R.T + t - c) @ Ra.T + c
            proj, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), K, dist)
            out.append(proj.reshape(-1, 2))
        return (np.concatenate(out) - img).reshape(-1)

    p = np.zeros(10)
    steps = np.array([1e-6] * 2 + [1e-6] * 2 + [1e-6] * 3 + [1e-6] * 3)
    lam = 1e-3
    r = residuals(p)
    cost = r @ r
    for _ in range(iterations):
        J = np.empty((r.size, 10))
        for k in range(10):
            dp = np.zeros(10)
            dp[k] = steps[k]
            J[:, k] = (residuals(p + dp) - residuals(p - dp)) / (2 * steps[k])
        A = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(8):
            delta = -np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
            r_new = residuals(p + delta)
            c_new = r_new @ r_new
            if c_new < cost:
                p, r, cost = p + delta, r_new, c_new
                lam = max(lam / 3, 1e-9)
                improved = True
                break
            lam *= 5
        if not improved or np.max(np.abs(delta)) < 1e-12:
            break
    J = np.empty((r.size, 10))
    for k in range(10):
        dp = np.zeros(10)
        dp[k] = steps[k]
        J[:, k] = (residuals(p + dp) - residuals(p - dp)) / (2 * steps[k])
    sigma2 = cost / max(r.size - 10, 1)
    cov = sigma2 * np.linalg.pinv(J.T @ J)
    w, c, R, t = unpack(p)
    axis_std = float(np.degrees(np.sqrt(cov[0, 0] + cov[1, 1])))
    point_std = np.sqrt(np.clip(np.array([cov[2, 2], cov[3, 3], 0.0]), 0, None))
    # per-view residual rotation check: measured (PnP) vs model angle
    z = t - c
    z = z - (z @ w) * w
    zn = np.linalg.norm(z)
    return TurntableAxisResult(
        axis_cam=w, point_cam_m=c, axis_std_deg=axis_std, point_std_m=point_std,
        angle_scale=initial.angle_scale, zero_angle_deg=initial.zero_angle_deg,
        angle_residuals_deg=initial.angle_residuals_deg,
        zero_direction_cam=z / zn if zn > 0 else z,
        circle_residual_rms_m=float(np.sqrt(cost / r.size)) * 0 + initial.circle_residual_rms_m)


@dataclasses.dataclass(frozen=True)
class JointRigResult:
    """Intrinsics and turntable axis refined together (:func:`refine_rig`)."""

    K: np.ndarray
    dist: np.ndarray
    std_fx_fy_cx_cy: np.ndarray
    axis: TurntableAxisResult
    rms_px: float
    residuals_px: np.ndarray
    mount_poses: tuple = ()  # per mount index: (R, t) board -> camera at turntable angle 0
    mount_rotation_std_deg: tuple = ()  # per mount: 1-sigma direction of its board normal (deg)
    std_dist: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(5))

    def pose_at(self, mount_index: int, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """Board pose (board -> camera) of a mount at a turntable angle, from the model."""
        R, t = self.mount_poses[mount_index]
        Ra = _axis_rotation(self.axis.axis_cam, angle_deg)
        c = self.axis.point_cam_m
        return Ra @ R, Ra @ (t - c) + c


def refine_rig(views, K: np.ndarray, dist: np.ndarray, axis0: np.ndarray, point0: np.ndarray,
               *, fit_distortion: bool | int = True, iterations: int = 40) -> JointRigResult:
    """Bundle adjustment of the intrinsics and the turntable axis over every board view.

    ``views``: a list of ``(mount_index, turntable_angle_deg, CharucoDetection)``. Each board
    mount ``m`` has one pose ``(R_m, t_m)`` at turntable angle 0; a view at angle ``a`` sees
    ``R_w(a) (R_m X + t_m - c) + c`` (rotation by the commanded angle about the axis ``w``
    through ``c``). Parameters: ``fx, fy, cx, cy`` (+ ``k1`` and ``k2``: ``fit_distortion`` is
    the number of radial terms fitted, ``True`` = 2; the others stay as given), axis direction (2), axis
    point (2), 6 per mount; Levenberg-Marquardt with a numerical Jacobian; 1-sigma
    uncertainties from ``(J^T J)^-1`` scaled by the residual variance. Constraining all views
    of a mount to one rigid rotation about one axis determines the principal point and the
    axis far better than independent per-view poses (Zhang's method) do.
    """
    import cv2

    mounts = sorted({m for m, _, _ in views})
    midx = {m: i for i, m in enumerate(mounts)}
    w0 = np.asarray(axis0, float) / np.linalg.norm(axis0)
    u1, u2 = _perp_basis(w0)
    c0 = np.asarray(point0, float)
    dist = np.zeros(5) if dist is None else np.asarray(dist, float).reshape(-1)[:5]
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    # initial mount poses: PnP of the view nearest angle 0, rotated back to angle 0
    base = []
    for m in mounts:
        mv = [(a, d) for mm, a, d in views if mm == m]
        a, d = min(mv, key=lambda x: abs(x[0]))
        R, t, _ = board_pose(d, K, dist)
        Rb = _axis_rotation(w0, -a)
        base.append((Rb @ R, Rb @ (t - c0) + c0))
    n_dist = 2 if fit_distortion is True else int(fit_distortion)
    if not 0 <= n_dist <= 2:
        raise ValueError(f"fit_distortion must be 0, 1 or 2 radial terms, got {fit_distortion!r}")
    n_in = 4 + n_dist
    npar = n_in + 4 + 6 * len(mounts)
    p_init = np.zeros(npar)
    p_init[:4] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    p_init[4:n_in] = dist[:n_dist]
    obj = [d.object_m for _, _, d in views]
    img = np.concatenate([d.corners_px for _, _, d in views])
    vm = [midx[m] for m, _, _ in views]
    va = [float(a) for _, a, _ in views]

    def unpack(p):
        Kp = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1.0]])
        dp = dist.copy()
        dp[:n_dist] = p[4:n_in]
        q = p[n_in:]
        w = w0 + q[0] * u1 + q[1] * u2
        w = w / np.linalg.norm(w)
        c = c0 + q[2] * u1 + q[3] * u2
        poses = []
        for i, (Rb, tb) in enumerate(base):
            r = q[4 + 6 * i: 7 + 6 * i]
            poses.append((_rodrigues(r) @ Rb, tb + q[7 + 6 * i: 10 + 6 * i]))
        return Kp, dp, w, c, poses

    def residuals(p):
        Kp, dp, w, c, poses = unpack(p)
        out = []
        for o, i, a in zip(obj, vm, va):
            R, t = poses[i]
            Ra = _axis_rotation(w, a)
            pc = (o @ R.T + t - c) @ Ra.T + c
            proj, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), Kp, dp)
            out.append(proj.reshape(-1, 2))
        return (np.concatenate(out) - img).reshape(-1)

    step = np.full(npar, 1e-6)
    step[:4] = 1e-3
    step[4:n_in] = 1e-5

    def jac(p):
        J = np.empty((img.size, npar))
        for k in range(npar):
            dp_ = np.zeros(npar)
            dp_[k] = step[k]
            J[:, k] = (residuals(p + dp_) - residuals(p - dp_)) / (2 * step[k])
        return J

    p = p_init
    r = residuals(p)
    cost = r @ r
    lam = 1e-3
    for _ in range(iterations):
        J = jac(p)
        A, g = J.T @ J, J.T @ r
        improved = False
        for _ in range(10):
            delta = -np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), g)
            r_new = residuals(p + delta)
            if r_new @ r_new < cost:
                p, r, cost = p + delta, r_new, r_new @ r_new
                lam = max(lam / 3, 1e-10)
                improved = True
                break
            lam *= 5
        if not improved or np.max(np.abs(delta / step)) < 1e-4:
            break
    J = jac(p)
    sigma2 = cost / max(r.size - npar, 1)
    cov = sigma2 * np.linalg.pinv(J.T @ J)
    Kp, dp, w, c, poses = unpack(p)
    q0 = n_in
    axis_std = float(np.degrees(np.sqrt(cov[q0, q0] + cov[q0 + 1, q0 + 1])))
    point_std = np.sqrt(np.clip([cov[q0 + 2, q0 + 2], cov[q0 + 3, q0 + 3], 0.0], 0, None))
    R0, t0 = poses[0]
    z = t0 - c
    z = z - (z @ w) * w
    zn = np.linalg.norm(z)
    res2 = r.reshape(-1, 2)
    ax = TurntableAxisResult(axis_cam=w, point_cam_m=c, axis_std_deg=axis_std,
                             point_std_m=point_std, angle_scale=1.0, zero_angle_deg=0.0,
                             angle_residuals_deg=np.zeros(0),
                             zero_direction_cam=z / zn if zn > 0 else z,
                             circle_residual_rms_m=0.0)
    # uncertainty of each mount's board normal: the rotation-vector covariance projected
    # perpendicular to the normal (a rotation about the normal does not move it)
    rot_std = []
    for i in range(len(mounts)):
        c_rot = cov[q0 + 4 + 6 * i: q0 + 7 + 6 * i, q0 + 4 + 6 * i: q0 + 7 + 6 * i]
        n = poses[i][0][:, 2]
        P = np.eye(3) - np.outer(n, n)
        rot_std.append(float(np.degrees(np.sqrt(max(np.trace(P @ c_rot @ P), 0.0)))))
    rot_std = tuple(rot_std)
    std_dist = np.zeros(5)
    std_dist[:n_dist] = np.sqrt(np.clip(np.diag(cov)[4:n_in], 0, None))
    return JointRigResult(Kp, dp, np.sqrt(np.clip(np.diag(cov)[:4], 0, None)), ax,
                          float(np.sqrt(np.mean(np.sum(res2 ** 2, axis=1)))), res2,
                          tuple((poses[midx[m]][0], poses[midx[m]][1]) for m in mounts),
                          rot_std, std_dist)
