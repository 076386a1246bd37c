"""Rig geometry of the simulator: rotations, the pinhole camera, the point light, the turntable.

World frame: right-handed, metres, ``+Z`` up (the turntable axis of the default rig points
up). The camera frame is OpenCV's (``X`` right, ``Y`` down, ``Z`` forward) and a camera pose
is the world->camera map ``p_cam = R @ p_world + t`` (``docs/conventions.md``, "Image
coordinates"). Pixel ``(row v, col u)`` looks along ``K^-1 (u, v, 1)``: pixel centres sit at
integer coordinates, as in OpenCV's ``projectPoints``.

References: R. Hartley and A. Zisserman, *Multiple View Geometry* (2nd ed., 2004), ch. 6
(pinhole camera ``x = K [R | t] X``); OpenCV documentation, "Camera Calibration and 3D
Reconstruction" (camera frame axes); Rodrigues' rotation formula.
"""

from __future__ import annotations

import dataclasses

import numpy as np


def unit(v: np.ndarray, axis: int = -1) -> np.ndarray:
    """``v`` divided by its norm along ``axis`` (zero vectors stay zero, never NaN)."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def rows_times(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``v @ m`` for row vectors ``v`` ``(..., 3)`` and a 3x3 ``m``, by ``einsum`` rather than
    BLAS: for tall, thin products the BLAS thread start-up costs more than the arithmetic
    (7x slower on a busy 2-core machine)."""
    return np.einsum("...j,jk->...k", np.asarray(v, dtype=np.float64), m)


def rotation_about_axis(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """3x3 rotation by ``angle_deg`` about the unit ``axis``, right-handed (Rodrigues)."""
    k = unit(np.asarray(axis, dtype=np.float64))
    if not np.any(k):
        raise ValueError("rotation axis must be a non-zero 3-vector")
    a = np.deg2rad(float(angle_deg))
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)


def look_at(eye_m: np.ndarray, target_m: np.ndarray,
            up: np.ndarray = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World->camera pose ``(R, t)`` of an OpenCV camera at ``eye_m`` looking at ``target_m``
    with the world ``up`` direction appearing as image up (``-Y``)."""
    eye, target = np.asarray(eye_m, float), np.asarray(target_m, float)
    z = unit(target - eye)
    x = unit(np.cross(z, np.asarray(up, float)))
    if not np.any(x):
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    y = np.cross(z, x)
    r = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return r, -r @ eye


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """Pinhole camera: intrinsics in pixels, pose world->camera, sensor size in pixels.

    ``width``/``height`` is the full simulated sensor (the readout a ROI is cut from).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,) metres

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def centre_m(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t

    def to_camera(self, v_world: np.ndarray) -> np.ndarray:
        """Rotate world vectors ``(..., 3)`` into the camera frame (directions, no translation)."""
        return rows_times(v_world, self.R.T)

    def ray_directions(self) -> np.ndarray:
        """Unit world directions ``(H, W, 3)`` of the rays through every pixel centre."""
        u = (np.arange(self.width, dtype=np.float64) - self.cx) / self.fx
        v = (np.arange(self.height, dtype=np.float64) - self.cy) / self.fy
        d = np.empty((self.height, self.width, 3))
        d[..., 0] = u[None, :]
        d[..., 1] = v[:, None]
        d[..., 2] = 1.0
        return unit(rows_times(d, self.R))  # R^T d_cam for every pixel

    def project(self, points_world_m: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``(..., 2)`` = ``(u, v)`` of world points."""
        pc = rows_times(points_world_m, self.R.T) + self.t
        return np.stack([self.fx * pc[..., 0] / pc[..., 2] + self.cx,
                         self.fy * pc[..., 1] / pc[..., 2] + self.cy], axis=-1)

    def to_json(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height,
                "R": self.R.tolist(), "t_m": self.t.tolist()}


@dataclasses.dataclass(frozen=True)
class PointLight:
    """Isotropic point light: position (world, metres), radiant intensity of the unpolarized
    source per colour (arbitrary radiometric unit per steradian, R, G, B) at level 1."""

    position_m: np.ndarray
    intensity_rgb: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", np.asarray(self.position_m, float).reshape(3))
        i = np.asarray(self.intensity_rgb, float).reshape(3)
        if not (np.all(np.isfinite(i)) and np.all(i >= 0)):
            raise ValueError(f"light intensity must be finite and >= 0, got {i}")
        object.__setattr__(self, "intensity_rgb", i)

    def radiant_intensity_rgb(self, level: float = 1.0, on: bool = True) -> np.ndarray:
        """Radiant intensity ``(3,)`` of the unpolarized source at a light ``level`` in [0, 1]."""
        return self.intensity_rgb * (float(level) if on else 0.0)


@dataclasses.dataclass(frozen=True)
class TurntableGeometry:
    """The turntable: unit ``axis`` (world, pointing up) through ``point_m``.

    A turntable angle rotates the objects on it right-handedly about ``axis`` (counter-
    clockwise seen from above, as :class:`polrig.acquisition.hal.Turntable` states).
    """

    axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    point_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "axis", unit(np.asarray(self.axis, float).reshape(3)))
        object.__setattr__(self, "point_m", np.asarray(self.point_m, float).reshape(3))

    def transform(self, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` with ``p_rotated = R @ p + t`` for points carried by the turntable."""
        r = rotation_about_axis(self.axis, angle_deg)
        return r, self.point_m - r @ self.point_m
