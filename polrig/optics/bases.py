"""Stokes reference frames (bases) and basis changes, vectorised over ``(..., 3)`` vectors.

Convention (``docs/conventions.md``, "Stokes reference frames"): a Stokes vector travels along
``k`` and is measured against an ``x`` axis perpendicular to ``k``; ``y = k x x`` so that
``(x, y, k)`` is right-handed. This is Mitsuba 3's convention (``mueller::stokes_basis``,
``mueller::rotate_stokes_basis``, ``mueller::rotate_mueller_basis`` in
``include/mitsuba/render/mueller.h``), so matrices expressed in the same bases agree with
Mitsuba's.

The rig's frames (per pixel):

* :func:`incident_frame`: ``k = -wi`` (from the light towards the surface), ``x`` = the
  polarizer stage's zero axis made perpendicular to ``k``.
* :func:`emergent_frame`: ``k = wo`` (from the surface towards the camera), ``x`` = the
  camera ``X`` axis made perpendicular to ``k``.

Degenerate references (``x_ref`` parallel to ``k``, zero or non-finite) fall back to Mitsuba's
default basis :func:`stokes_basis` of ``k``; nothing here returns NaN for finite non-zero ``k``.
A zero or non-finite ``k`` is replaced by ``(0, 0, 1)`` (finite frame, no NaN propagation);
callers mask such pixels with :func:`valid_direction`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Below this squared length a vector made perpendicular to ``k`` counts as degenerate.
_DEGENERATE_SQ = 1e-20


class StokesFrame(NamedTuple):
    """A Stokes basis: unit ``x`` axis, ``y = k x x`` and propagation direction ``k``, each
    ``(..., 3)``."""

    x: np.ndarray
    y: np.ndarray
    k: np.ndarray


def _as_vectors(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have a trailing axis of length 3 (x, y, z), got shape {a.shape}")
    return a


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of ``(..., 3)`` arrays (broadcasting)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _empty_vectors(shape: tuple[int, ...]) -> np.ndarray:
    """Uninitialised ``shape`` (= ``(..., 3)``) array stored component-major, so that
    ``v[..., 0]`` etc. are contiguous (fast component access for large pixel stacks)."""
    return np.moveaxis(np.empty((3,) + tuple(shape[:-1])), 0, -1)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(..., 3)`` arrays (broadcasting; faster than ``np.cross``
    for large stacks)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    out = _empty_vectors(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def valid_direction(v) -> np.ndarray:
    """``True`` where ``v`` ``(..., 3)`` is finite and of non-zero length."""
    v = _as_vectors(v, "v")
    n2 = dot(v, v)
    return np.isfinite(n2) & (n2 > 0)


def unit_and_valid(v) -> tuple[np.ndarray, np.ndarray]:
    """``(normalize(v), valid_direction(v))`` in one pass (one length computation)."""
    v = _as_vectors(v, "v")
    n2 = dot(v, v)
    ok = np.isfinite(n2) & (n2 > 0)
    inv = 1.0 / np.sqrt(np.where(ok, n2, 1.0))
    out = _empty_vectors(v.shape)
    for c in range(3):
        out[..., c] = v[..., c] * inv
    if not ok.all():
        out[~ok] = (0.0, 0.0, 1.0)
    return out, ok


def unit_fast(v: np.ndarray) -> np.ndarray:
    """``v / |v|`` for ``(..., 3)`` vectors already known to be finite and non-zero (no checks;
    component-major result). Use :func:`normalize` for arbitrary input."""
    inv = 1.0 / np.sqrt(dot(v, v))
    out = _empty_vectors(v.shape)
    for c in range(3):
        np.multiply(v[..., c], inv, out=out[..., c])
    return out


def normalize(v) -> np.ndarray:
    """Unit vectors along ``v`` ``(..., 3)``; zero or non-finite vectors become ``(0, 0, 1)``
    (mask them with :func:`valid_direction`)."""
    return unit_and_valid(v)[0]


def stokes_basis(k) -> np.ndarray:
    """Mitsuba 3's default Stokes basis ``x`` for propagation direction ``k`` ``(..., 3)``.

    ``x`` is the first vector of ``coordinate_system(k)`` (Duff et al., "Building an
    Orthonormal Basis, Revisited", JCGT 6(1), 2017), exactly as Mitsuba's
    ``mueller::stokes_basis``. It is continuous except across ``k_z = 0`` where the branch
    changes (``k_z >= 0`` takes the ``+`` branch). ``k`` is normalised first.
    """
    return stokes_basis_unit(normalize(k))


def stokes_basis_unit(n: np.ndarray) -> np.ndarray:
    """:func:`stokes_basis` for an already unit direction ``n`` (skips normalising)."""
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    x = _empty_vectors(n.shape)
    x[..., 0] = sign * nx * nx * a + 1.0
    x[..., 1] = sign * b
    x[..., 2] = -sign * nx
    return x


def basis_from_reference(k, x_ref) -> np.ndarray:
    """Stokes basis ``x`` for direction ``k``: ``x_ref`` made perpendicular to ``k`` and
    normalised (Gram-Schmidt). Both ``(..., 3)``, broadcast.

    Where ``x_ref`` is (nearly) parallel to ``k``, zero or non-finite, falls back to
    :func:`stokes_basis` of ``k``.
    """
    return basis_from_reference_unit(normalize(k), x_ref)


def basis_from_reference_unit(k: np.ndarray, x_ref) -> np.ndarray:
    """:func:`basis_from_reference` for an already unit ``k`` (skips normalising ``k``)."""
    r = _as_vectors(x_ref, "x_ref")
    shape = np.broadcast_shapes(k.shape, r.shape)
    with np.errstate(invalid="ignore", over="ignore"):
        big = np.abs(r).max(axis=-1)  # scale first: no underflow/overflow in |r|^2
        ok_ref = np.isfinite(big) & (big > 0)
        r = r / np.where(ok_ref, big, 1.0)[..., None]
        r = r / np.sqrt(dot(r, r))[..., None]
    rk = dot(r, k)
    x = _empty_vectors(shape)
    for c in range(3):
        x[..., c] = r[..., c] - rk * k[..., c]
    n2 = dot(x, x)
    ok = ok_ref & (n2 > _DEGENERATE_SQ)
    inv = 1.0 / np.sqrt(np.where(ok, n2, 1.0))
    for c in range(3):
        x[..., c] *= inv
    # References within ~0.6 deg of k lose digits to cancellation: a second Gram-Schmidt pass
    # there keeps x exactly perpendicular to k.
    near = np.broadcast_to(ok & (n2 < 1e-4), shape[:-1])
    if np.any(near):
        kn = np.broadcast_to(k, shape)[near]
        xn = x[near]
        xn = xn - dot(xn, kn)[..., None] * kn
        x[near] = xn / np.sqrt(dot(xn, xn))[..., None]
    if not np.all(ok):
        ok = np.broadcast_to(ok, shape[:-1])
        x[~ok] = stokes_basis_unit(np.broadcast_to(k, shape)[~ok])
    return x


def frame(k, x_ref) -> StokesFrame:
    """Right-handed orthonormal :class:`StokesFrame` for direction ``k`` with ``x`` from
    ``x_ref`` (:func:`basis_from_reference`), ``y = k x x``."""
    k = normalize(k)
    x = basis_from_reference(k, x_ref)
    k = np.broadcast_to(k, x.shape)
    return StokesFrame(x, cross(k, x), k)


def incident_frame(wi, stage_zero_axis) -> StokesFrame:
    """The rig's incident (illumination) frame per pixel.

    ``wi`` ``(..., 3)`` points from the surface towards the light; ``k = -wi`` is the
    propagation direction of the illumination. ``x`` is ``stage_zero_axis`` (3D unit vector of
    the polarizer stage's zero axis, world coordinates) made perpendicular to ``k``; a stage
    angle turns the polarizer from ``x`` towards ``y`` (``docs/conventions.md``).
    """
    return frame(-_as_vectors(wi, "wi"), stage_zero_axis)


def emergent_frame(wo, camera_x_axis) -> StokesFrame:
    """The rig's emergent (camera) frame per pixel.

    ``wo`` ``(..., 3)`` points from the surface towards the camera (``k = wo``); ``x`` is the
    camera ``X`` axis (image ``+u``, world coordinates) made perpendicular to ``k``, so that
    for the central ray ``y`` is image up (``docs/conventions.md``).
    """
    return frame(wo, camera_x_axis)


def rotation_cos_sin_2theta(forward, basis_current, basis_target) -> tuple[np.ndarray, np.ndarray]:
    """``(cos 2theta, sin 2theta)`` of the signed angle ``theta`` that turns
    ``basis_current`` into ``basis_target`` about ``forward`` (positive from ``x`` towards
    ``y = forward x x``), as in Mitsuba's ``mueller::rotate_stokes_basis``.

    Uses ``theta = atan2(|cur x tgt|, cur . tgt)`` with the sign of ``forward . (cur x tgt)``
    (Mitsuba: ``unit_angle`` and that sign) without trigonometric calls; neither ``forward``
    nor the bases need be normalised (the bases must be perpendicular to ``forward``). A zero
    current or target basis gives ``theta = 0``.
    """
    f = _as_vectors(forward, "forward")
    cur = _as_vectors(basis_current, "basis_current")
    tgt = _as_vectors(basis_target, "basis_target")
    c = dot(cur, tgt)
    cr = cross(cur, tgt)
    s = np.copysign(np.sqrt(dot(cr, cr)), dot(f, cr))
    r2 = c * c + s * s
    ok = np.isfinite(r2) & (r2 > 0)
    r2 = np.where(ok, r2, 1.0)
    cos2 = np.where(ok, (c * c - s * s) / r2, 1.0)
    sin2 = np.where(ok, 2.0 * c * s / r2, 0.0)
    return cos2, sin2


def rotation_cos_sin_2theta_to_frame(basis_current, x_target, y_target) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`rotation_cos_sin_2theta` with the target given as a full frame
    ``(x_target, y_target = k x x_target)`` (unit vectors): ``basis_current`` (any non-zero
    length, perpendicular to ``k``) lies at ``phi = atan2(cur . y, cur . x)`` in the target
    frame and the rotation is ``theta = -phi``. Two dot products and no cross product: the fast
    path when several bases are rotated into one frame. A zero or non-finite current basis
    gives ``theta = 0``."""
    c = dot(basis_current, x_target)
    s = dot(basis_current, y_target)
    cc, ss = c * c, s * s
    r2 = cc + ss
    ok = np.isfinite(r2) & (r2 > 0)
    if ok.all():
        inv = 1.0 / r2
        return (cc - ss) * inv, -2.0 * c * s * inv
    inv = 1.0 / np.where(ok, r2, 1.0)
    return np.where(ok, (cc - ss) * inv, 1.0), np.where(ok, -2.0 * c * s * inv, 0.0)


def rotation_angle(forward, basis_current, basis_target) -> np.ndarray:
    """Signed angle (radians, in ``(-pi, pi]``) from ``basis_current`` to ``basis_target``
    about ``forward`` (Mitsuba's ``rotate_stokes_basis`` angle)."""
    f = _as_vectors(forward, "forward")
    cur = _as_vectors(basis_current, "basis_current")
    tgt = _as_vectors(basis_target, "basis_target")
    cr = cross(cur, tgt)
    return np.arctan2(np.copysign(np.sqrt(dot(cr, cr)), dot(f, cr)), dot(cur, tgt))


def _rotator_cs(cos2: np.ndarray, sin2: np.ndarray) -> np.ndarray:
    """Rotator (``polrig.optics.mueller.rotator``) built from ``cos 2theta``, ``sin 2theta``."""
    out = np.zeros(np.shape(cos2) + (4, 4))
    out[..., 0, 0] = 1.0
    out[..., 3, 3] = 1.0
    out[..., 1, 1] = cos2
    out[..., 2, 2] = cos2
    out[..., 1, 2] = sin2
    out[..., 2, 1] = -sin2
    return out


def rotate_stokes_basis(forward, basis_current, basis_target) -> np.ndarray:
    """Mueller matrix ``(..., 4, 4)`` that re-expresses a Stokes vector travelling along
    ``forward`` from ``basis_current`` to ``basis_target`` (Mitsuba's
    ``mueller::rotate_stokes_basis``): ``S_target = R @ S_current``."""
    return _rotator_cs(*rotation_cos_sin_2theta(forward, basis_current, basis_target))


def rotate_rows(m: np.ndarray, cos2: np.ndarray, sin2: np.ndarray) -> np.ndarray:
    """``R(theta) @ m`` for ``m`` ``(..., n, k)`` with ``n >= 3`` (rows 1, 2 mix), without
    building ``R``; ``cos2``/``sin2`` broadcast against ``m.shape[:-2]``."""
    out = np.array(m, dtype=np.result_type(m, np.float64), copy=True)
    c, s = np.asarray(cos2)[..., None], np.asarray(sin2)[..., None]
    r1, r2 = m[..., 1, :], m[..., 2, :]
    out[..., 1, :] = c * r1 + s * r2
    out[..., 2, :] = c * r2 - s * r1
    return out


def rotate_cols(m: np.ndarray, cos2: np.ndarray, sin2: np.ndarray) -> np.ndarray:
    """``m @ R(theta)^T`` for ``m`` ``(..., k, n)`` with ``n >= 3`` (columns 1, 2 mix)."""
    out = np.array(m, dtype=np.result_type(m, np.float64), copy=True)
    c, s = np.asarray(cos2)[..., None], np.asarray(sin2)[..., None]
    c1, c2 = m[..., :, 1], m[..., :, 2]
    out[..., :, 1] = c * c1 + s * c2
    out[..., :, 2] = c * c2 - s * c1
    return out


def rotate_mueller_basis(m, in_forward, in_basis_current, in_basis_target,
                         out_forward, out_basis_current, out_basis_target) -> np.ndarray:
    """Re-express ``m`` ``(..., n, n)`` (``n`` = 3 or 4) operating from ``in_basis_current``
    to ``out_basis_current`` as a matrix from ``in_basis_target`` to ``out_basis_target``:
    ``R_out @ m @ R_in^T`` (Mitsuba's ``mueller::rotate_mueller_basis``).

    ``m`` may carry extra axes between the pixel axes and the matrix axes only if the vectors
    broadcast against ``m.shape[:-2]`` (e.g. insert a colour axis with ``[..., None, :]``).
    """
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] not in (3, 4):
        raise ValueError(f"m must be (..., 3, 3) or (..., 4, 4), got shape {m.shape}")
    ci, si = rotation_cos_sin_2theta(in_forward, in_basis_current, in_basis_target)
    co, so = rotation_cos_sin_2theta(out_forward, out_basis_current, out_basis_target)
    return rotate_rows(rotate_cols(m, ci, si), co, so)
