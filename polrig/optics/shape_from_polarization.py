"""Surface normals from the polarization of reflected light (shape from polarization).

Unpolarized light reflected by a dielectric leaves partially linearly polarized; its degree
(DoLP) fixes the zenith angle ``theta`` between the normal and the viewing direction for a
known refractive index ``n``, and its angle (AoLP) the normal's azimuth in the image, up to the
ambiguities below. From a Mueller result the state that unpolarized illumination leaves is the
linear polarizance, ``DoLP = |(m10, m20)| / m00`` and ``AoLP = atan2(m20, m10) / 2``
(:func:`polrig.optics.parameters.linear_polarizance`), so the normal needs no separate
unpolarized capture.

Two reflection models (Atkinson and Hancock, "Recovery of surface orientation from diffuse
polarization", IEEE Trans. Image Process. 15(6):1653-1664, 2006, eqs. for rho_s and rho_d;
Miyazaki et al., "Polarization-based inverse rendering from a single view", ICCV 2003):

* **diffuse** (light scattered below the surface and refracted out, the Fresnel transmission's
  polarization)::

      rho_d = (n - 1/n)^2 sin^2 t / (2 + 2 n^2 - (n + 1/n)^2 sin^2 t + 4 cos t sqrt(n^2 - sin^2 t))

  which rises monotonically from 0 at ``t = 0`` to its value at grazing exit, so the zenith
  is unique; the polarization is parallel to the plane of emittance: the normal's image
  azimuth is the AoLP **or the AoLP + 180 deg** (the pi ambiguity: a DoLP and AoLP cannot tell
  a surface tilted left from one tilted right the same amount).
* **specular** (Fresnel reflection)::

      rho_s = 2 sin^2 t cos t sqrt(n^2 - sin^2 t) / (n^2 - sin^2 t - n^2 sin^2 t + 2 sin^4 t)

  which is 1 at Brewster's angle ``atan n`` and falls on both sides: **two zeniths** for
  every DoLP below 1 (one below, one above Brewster's angle); the polarization is
  perpendicular to the plane of incidence: the azimuth is the AoLP + 90 deg, or + 270 deg.

Which model holds is a property of the pixel that the DoLP and AoLP alone cannot tell (a
specular highlight on a plastic is specular, most of a matte object diffuse): the caller
states it. Both assume a single bounce and a smooth, non-birefringent dielectric of index
``n`` (metals and retarding films do not follow these curves).

Frames (``docs/conventions.md``): the AoLP is in the emergent (camera) Stokes frame, measured
from image right towards image up; the normals are unit vectors in the OpenCV camera frame
(``X`` right, ``Y`` down, ``Z`` forward), pointing out of the surface (towards the camera:
``n . view > 0``). The viewing direction ``view`` (from the surface to the camera) is per pixel
where given (a pinhole camera's rays) and ``(0, 0, -1)`` otherwise (orthographic); the Stokes
frame's ``x`` is the camera ``X`` made perpendicular to ``view``, its ``y = view x x`` (image up
for the central ray).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.optics.parameters import linear_polarizance

__all__ = ["REFLECTIONS", "SfpNormals", "angle_between_deg", "diffuse_dolp", "diffuse_zenith",
           "normals_from_mueller", "normals_from_polarization", "specular_dolp", "specular_zeniths",
           "view_directions"]

#: The reflection models.
REFLECTIONS = ("diffuse", "specular")
#: Samples of the zenith in [0, 90] deg of the inversions' tables (0.0015 deg apart).
_TABLE = np.linspace(0.0, np.pi / 2, 60001)


def _check_ior(ior: float) -> float:
    ior = float(ior)
    if not (np.isfinite(ior) and ior > 1.0):
        raise ValueError(f"refractive index must be a finite number > 1, got {ior}")
    return ior


def diffuse_dolp(zenith_rad, ior: float) -> np.ndarray:
    """DoLP of diffuse reflection leaving a dielectric of index ``ior`` at zenith ``zenith_rad``
    (radians, 0 to pi/2; any shape): Atkinson and Hancock 2006, rho_d (module docstring)."""
    n = _check_ior(ior)
    s2 = np.sin(np.asarray(zenith_rad, np.float64)) ** 2
    c = np.cos(np.asarray(zenith_rad, np.float64))
    return ((n - 1 / n) ** 2 * s2
            / (2 + 2 * n * n - (n + 1 / n) ** 2 * s2 + 4 * c * np.sqrt(n * n - s2)))


def specular_dolp(zenith_rad, ior: float) -> np.ndarray:
    """DoLP of specular (Fresnel) reflection of unpolarized light at zenith ``zenith_rad``
    (radians) off a dielectric of index ``ior``: Atkinson and Hancock 2006, rho_s; 1 at
    Brewster's angle ``arctan(ior)``."""
    n = _check_ior(ior)
    s2 = np.sin(np.asarray(zenith_rad, np.float64)) ** 2
    c = np.cos(np.asarray(zenith_rad, np.float64))
    return 2 * s2 * c * np.sqrt(n * n - s2) / (n * n - s2 - n * n * s2 + 2 * s2 * s2)


def diffuse_zenith(dolp, ior: float) -> np.ndarray:
    """The zenith (radians) whose diffuse DoLP is ``dolp`` (any shape): unique (rho_d is
    monotonic); NaN where ``dolp`` is not finite, negative, or beyond the grazing value
    ``rho_d(pi/2)`` (no diffuse surface of this index polarizes that much)."""
    table = diffuse_dolp(_TABLE, ior)
    d = np.asarray(dolp, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d >= 0) & (d <= table[-1])
    return np.where(ok, np.interp(np.where(ok, d, 0.0), table, _TABLE), np.nan)


def specular_zeniths(dolp, ior: float) -> tuple[np.ndarray, np.ndarray]:
    """The two zeniths (radians) whose specular DoLP is ``dolp``: ``(below, above)`` Brewster's
    angle (equal at DoLP 1); NaN where ``dolp`` is not finite or outside [0, 1]."""
    n = _check_ior(ior)
    brewster = np.arctan(n)
    d = np.asarray(dolp, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(d) & (d >= 0) & (d <= 1)
    d0 = np.where(ok, d, 0.0)
    lo = _TABLE[_TABLE <= brewster]
    hi = _TABLE[_TABLE >= brewster][::-1]  # increasing DoLP from grazing to Brewster
    below = np.interp(d0, specular_dolp(lo, n), lo)
    above = np.interp(d0, specular_dolp(hi, n), hi)
    return np.where(ok, below, np.nan), np.where(ok, above, np.nan)


@dataclasses.dataclass(frozen=True)
class SfpNormals:
    """The normals a DoLP and AoLP allow (module docstring), for input shape ``S``.

    ``normals`` ``(K, 3, *S)``: every candidate, unit vectors in the camera frame (NaN where
    the DoLP allows none); diffuse ``K = 2`` (azimuth ``a``, ``a + 180``), specular ``K = 4``
    (zenith below Brewster with ``a``, ``a + 180``, then above Brewster with both).
    ``zenith_deg`` ``(Z, *S)`` (``Z`` = 1 diffuse, 2 specular: below, above Brewster);
    ``azimuth_deg`` ``(*S)`` in ``[0, 180)``, the image azimuth of ``normals[0]`` (measured
    from image right towards image up, in the pixel's Stokes frame); ``reflection``, ``ior``."""

    normals: np.ndarray
    zenith_deg: np.ndarray
    azimuth_deg: np.ndarray
    reflection: str
    ior: float

    @property
    def normal(self) -> np.ndarray:
        """``(3, *S)``: the first candidate (diffuse: azimuth = AoLP; specular: below Brewster)."""
        return self.normals[0]


def _view_frame(view, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel ``(x, y, k)``, each ``(3, *shape)``: the emergent Stokes frame."""
    if view is None:
        k = np.broadcast_to(np.array([0.0, 0.0, -1.0]).reshape((3,) + (1,) * len(shape)), (3, *shape))
    else:
        k = np.asarray(view, np.float64)
        if k.shape[:1] != (3,) or np.broadcast_shapes(k.shape[1:], shape) != shape:
            raise ValueError(f"view must have shape (3, ...) broadcastable to {(3, *shape)}, "
                             f"got {k.shape}")
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.broadcast_to(k / np.linalg.norm(k, axis=0), (3, *shape))
    cam_x = np.array([1.0, 0.0, 0.0]).reshape((3,) + (1,) * len(shape))
    x = cam_x - np.sum(cam_x * k, axis=0) * k
    with np.errstate(invalid="ignore", divide="ignore"):
        x = x / np.linalg.norm(x, axis=0)
    y = np.cross(k, x, axis=0)
    return x, y, k


def normals_from_polarization(dolp, aolp_deg, ior: float, reflection: str = "diffuse",
                              view=None) -> SfpNormals:
    """Candidate surface normals from the DoLP and AoLP of light reflected under unpolarized
    illumination (module docstring: formulas, ambiguities, frames).

    ``dolp`` and ``aolp_deg`` (degrees, emergent frame) of shape ``S`` (e.g. ``(C, H, W)`` or
    ``(H, W)``); ``ior`` the refractive index (> 1), ``reflection`` ``"diffuse"`` or
    ``"specular"``; ``view`` ``(3, *S)`` unit vectors from the surface to the camera (camera
    frame), ``None`` for the orthographic ``(0, 0, -1)``. Returns :class:`SfpNormals`."""
    if reflection not in REFLECTIONS:
        raise ValueError(f"unknown reflection {reflection!r}; use {' or '.join(REFLECTIONS)}")
    d = np.asarray(dolp, np.float64)
    a = np.asarray(aolp_deg, np.float64)
    if d.shape != a.shape:
        raise ValueError(f"dolp {d.shape} and aolp {a.shape} differ in shape")
    x, y, k = _view_frame(view, d.shape)
    if reflection == "diffuse":
        zeniths = diffuse_zenith(d, ior)[None]
        azimuth = np.mod(a, 180.0)
    else:
        zeniths = np.stack(specular_zeniths(d, ior))
        azimuth = np.mod(a + 90.0, 180.0)
    azimuth = np.where(np.isfinite(a), azimuth, np.nan)
    cands = []
    for theta in zeniths:
        for flip in (0.0, np.pi):
            phi = np.deg2rad(azimuth) + flip
            cands.append(np.sin(theta) * (np.cos(phi) * x + np.sin(phi) * y) + np.cos(theta) * k)
    return SfpNormals(np.stack(cands).astype(np.float32), np.rad2deg(zeniths).astype(np.float32),
                      azimuth.astype(np.float32), reflection, float(ior))


def view_directions(intrinsics, shape: tuple[int, int]) -> np.ndarray:
    """``(3, H, W)`` unit vectors from the surface seen at each pixel to a pinhole camera of
    intrinsics ``(fx, fy, cx, cy)`` (pixels of this ``(H, W)`` grid; OpenCV, pixel centres at
    integer coordinates): ``-normalise(((u - cx) / fx, (v - cy) / fy, 1))``, camera frame."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    if not (fx > 0 and fy > 0 and np.isfinite([fx, fy, cx, cy]).all()):
        raise ValueError(f"intrinsics must be finite with fx, fy > 0, got {tuple(intrinsics)}")
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)])
    return -ray / np.linalg.norm(ray, axis=0)


def normals_from_mueller(mueller, ior: float, reflection: str = "diffuse", view=None) -> SfpNormals:
    """:func:`normals_from_polarization` of a Mueller image ``(C, 3, 3, H, W)`` (any unit):
    the DoLP and AoLP that unpolarized illumination leaves, its linear polarizance
    (:func:`polrig.optics.parameters.linear_polarizance`), per colour; ``S = (C, H, W)``.
    ``view`` ``(3, H, W)`` (e.g. :func:`view_directions`) or ``None`` (orthographic)."""
    m = np.asarray(mueller)
    if m.ndim != 5 or m.shape[1:3] != (3, 3):
        raise ValueError(f"expected a Mueller image (C, 3, 3, H, W), got shape {m.shape}")
    dolp, aolp = linear_polarizance(np.moveaxis(m, (1, 2), (-2, -1)))
    if view is not None:
        view = np.asarray(view)[:, None]  # the same rays for every colour
    return normals_from_polarization(dolp, aolp, ior, reflection, view)


def angle_between_deg(a, b) -> np.ndarray:
    """Angle in degrees between unit vectors ``a`` and ``b`` of shape ``(3, *S)`` (NaN where
    either is NaN): the angular error of a normal."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.sum(a * b, axis=0) / (np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0))
    return np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0)))
