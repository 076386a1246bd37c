"""Parameter maps of a 3x3 linear Mueller block, each with its propagated standard deviation.

Pure array functions: matrices with the matrix axes last, ``(..., 3, 3)`` (``docs/conventions.md``:
rows and columns ``S0, S1, S2``; a measured block is in DN per unit incident ``S0``), float
results of the leading shape ``(...)``; :func:`image_maps` is the plane-first wrapper for
Mueller images ``(C, 3, 3, H, W)``. No loops over pixels; NaN in gives NaN out; a quantity that
a matrix does not define (a normalised map where ``m00 <= 0``, the decomposition where it cannot
be formed) is NaN. Angles are degrees, measured from the Stokes basis ``x`` towards ``y``
(``docs/conventions.md``); an axis angle is reported in ``[0, period)``. The definitions, their
assumptions and what the 3x3 block cannot tell are written up in ``docs/analysis.md``.

Only what the linear block supports (no quantity that needs the unmeasured fourth row and
column, such as the depolarization index or the polarimetric purity, is offered):

* ``m00``: the unpolarized intensity transfer (DN per unit incident ``S0``).
* ``DL``, ``DL_axis_deg``: linear diattenuation ``|(m01, m02)| / m00`` and the incident
  polarization angle of maximum transmission (incident frame);
  ``PL``, ``PL_axis_deg``: linear polarizance ``|(m10, m20)| / m00`` and the AoLP of the light
  that unpolarized illumination leaves (emergent frame). Lu and Chipman, JOSA A 13(5), 1106
  (1996); :func:`polrig.optics.mueller.diattenuation` returns 0 instead of NaN where
  ``m00 <= 0``.
* ``sv1``, ``sv2``: the signed singular values of the lower 2x2 block ``[[m11, m12], [m21,
  m22]] / m00`` (``sv1 >= |sv2|``, ``sv2`` carries the sign of the determinant). With ``m00``,
  ``DL`` and ``PL`` they are invariant under independent rotations of the incident and the
  emergent Stokes bases, ``M -> R(a) M R(b)``: the quantities that do not depend on how either
  frame is oriented.
* ``mmt_b``, ``mmt_t1``, ``mmt_A``, ``mmt_x_deg``: the Mueller matrix transformation (MMT)
  parameters of He et al., on the normalised block ``n = M / m00`` (0-based indices here; the
  papers count from 1): ``b = (n11 + n22) / 2``, ``t1 = sqrt((n11 - n22)^2 + (n12 + n21)^2) / 2``,
  ``A = 2 b t1 / (b^2 + t1^2)`` and the orientation ``x = atan2(n12 + n21, n11 - n22) / 4``
  (reported in ``[0, 90)`` deg). ``b``, ``t1`` and ``A`` are invariant under a common rotation of
  both frames (the sample turned about the beam, ``M -> R(-a) M R(a)``); ``x`` turns with it.
  For a linear retarder of retardance ``d`` and axis ``q``, ``b = (1 + cos d) / 2``,
  ``t1 = (1 - cos d) / 2``, ``x = q`` (mod 90). H. He, N. Zeng, E. Du, Y. Guo, D. Li, R. Liao,
  H. Ma, "A possible quantitative Mueller matrix transformation technique for anisotropic
  scattering media", Photonics Lasers Med. 2(2), 129-137 (2013); W. Sheng et al., "Quantitative
  analysis of 4x4 Mueller matrix transformation parameters for biomedical imaging", Photonics
  6(1), 34 (2019).
* ``retardance_deg``, ``retardance_axis_deg``, ``depolarization``, ``rotation_deg`` and the
  per-pixel ``decomposition_flags``: the 3x3 polar decomposition, :func:`decompose_linear`.

**The 3x3 polar decomposition.** M. K. Swami, S. Manhas, P. Buddhiwant, N. Ghosh, A. Uppal and
P. K. Gupta, "Polar decomposition of 3x3 Mueller matrix: a tool for quantitative tissue
polarimetry", Opt. Express 14(20), 9324-9337 (2006), carry the Lu-Chipman product
``M = M_Delta M_R M_D`` over to the linear block under one assumption: the depolarization of
linearly polarized light does not depend on the orientation of its polarization plane, so the
depolarizer's linear 2x2 block is ``Delta I`` (isotropic). The derivation here is ours, from that
model (we could read only the paper's abstract):

1. ``M_D`` is the linear diattenuator of the first row, ``D = (m01, m02) / m00``:
   ``M_D = m00 [[1, D^T], [D, m_D]]``, ``m_D = k I + (1 - k) D D^T / |D|^2``,
   ``k = sqrt(1 - |D|^2)``, that is ``m_D = k I + D D^T / (1 + k)`` (smooth at ``D = 0``).
   Its inverse exists for ``|D| < 1``: ``M_D^-1 = [[1, -D^T], [-D, m_D]] / (m00 k^2)`` (``D``
   is an eigenvector of ``m_D`` with eigenvalue 1), so the lower 2x2 block of
   ``M' = M M_D^-1`` is ``m' = (n m_D - P D^T) / k^2`` with ``n`` the lower block of
   ``M / m00`` and ``P = (m10, m20) / m00``.
2. ``M' = M_Delta M_R`` with the lower blocks ``m' = Delta A``, where ``A`` is the linear-linear
   block of a retarder. Unlike Lu and Chipman's 3x3 retarder block, ``A`` is not orthogonal: the
   2x2 block of any rotation of the Poincare sphere has singular values ``1`` and
   ``|cos d|`` and determinant ``cos d`` (``d`` the linear retardance of the retarder written as
   a linear retarder followed by a rotator, ``A = Rot(rho) L(d, q)``, Lu and Chipman's and
   Ghosh's convention). Hence ``Delta = s1(m')``, the largest singular value, and
   ``cos d = det(m') / s1^2``, ``d`` in ``[0, 180]`` deg. With ``E = (m'11 + m'22) / 2``,
   ``H = (m'21 - m'12) / 2``, ``F = (m'11 - m'22) / 2``, ``G = (m'12 + m'21) / 2``,
   ``Q = hypot(E, H)`` and ``R = hypot(F, G)``: ``s1 = Q + R``, ``cos d = (Q - R) / (Q + R)``
   (the same as Ghosh's ``d = arccos(sqrt((mR11 + mR22)^2 + (mR21 - mR12)^2) - 1)`` on
   ``A``), the rotation ``rho = atan2(H, E) / 2`` (positive: the polarization plane turned from
   ``x`` towards ``y``; it also holds any rotation between the incident and the emergent frame)
   and the retarder's axis ``q`` (modulo 90 deg: which of the two eigen-axes is fast, the sign
   of ``d``, lives in the unmeasured circular row) from ``L = Rot(-rho) A``:
   ``q = atan2(L12 + L21, L11 - L22) / 4``. ``depolarization = 1 - Delta`` (Lu and Chipman's
   depolarization power restricted to the linear states).

**What the block cannot tell.** The block cannot separate linear retardance from anisotropic
linear depolarization: a retarder of retardance ``d`` at 0 deg and the depolarizer
``diag(1, 1, cos d, cos d)`` have the same block ``diag(1, 1, cos d)`` (both are physical; they
differ in the fourth row and column only). The decomposition reports the isotropic reading
(retardance ``d``, no depolarization); :data:`DECOMP_ASSUMED` marks each pixel whose block is
linearly anisotropic, where that reading rests on the assumption. Where the block is isotropic
(``R = 0``) the reading is "no retardance, depolarization ``1 - Delta``"; a retardance hidden by
an exactly compensating anisotropic depolarizer cannot be excluded there either, but it needs a
coincidence, not a generic sample. Refusals (NaN and :data:`DECOMP_UNDEFINED`): ``m00 <= 0``
or non-finite, ``|D| >= 1`` (no inverse diattenuator), ``m' = 0`` (total depolarization: no
retardance to speak of). :data:`DECOMP_NONPHYSICAL`: ``Delta > 1`` (noise or a non-physical
block; the values are reported, not clipped).

**Uncertainty.** Every ``*_sigma`` result is the first-order (linearised) propagation of
independent per-element standard deviations ``sigma (..., 3, 3)``:
``sigma_f^2 = sum_ij (df / dm_ij)^2 sigma_ij^2`` (a term with a zero derivative is zero even
where ``sigma_ij`` is infinite). Every Jacobian is analytic: closed forms for ``m00``, ``DL``,
``PL``, their axes and the MMT parameters; for the singular values and the decomposition the
chain rule through the 2x2 block, ``m -> n -> m' -> (E, F, G, H) -> map``
(:func:`_chain_sigma`: each of those maps is a closed-form function of ``E, F, G, H``, which
are linear in ``m'``, whose derivatives are written out in :func:`_dq_dn`; the ``m00``
derivative follows from Euler's relation, every map being homogeneous of degree 0 in ``m``).
Until 2026-11-28 these came from forward finite differences, the whole decomposition run nine
more times; the analytic values equal them to the differences' truncation error (median
relative 1e-7) at a fraction of the time (``benchmarks/results/analyze.md``). The tests check
the chain rule against central differences of the maps, and every sigma against the spread of
sampled errors. Linearisation is accurate where a
map is smooth over the error's range: it fails near a map's boundary (``DL``, ``PL``, ``t1`` or
the retardance near 0, where the estimate is biased upwards like a Rician amplitude) and for an
axis whose magnitude is within its noise (its sigma is then large or infinite, which is
honest). ``docs/analysis.md`` reports the coverage measured on a simulated capture.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
from collections.abc import Mapping

import numpy as np

__all__ = [
    "MAPS",
    "ANGLE_PERIOD_DEG",
    "DECOMP_UNDEFINED",
    "DECOMP_ASSUMED",
    "DECOMP_NONPHYSICAL",
    "DECOMPOSITION_FLAGS",
    "DECOMPOSITION_ASSUMPTION",
    "SIGMA_METHOD",
    "linear_diattenuation",
    "linear_polarizance",
    "frame_invariants",
    "mmt_parameters",
    "decompose_linear",
    "decomposition_flags",
    "parameter_maps",
    "parameter_sigmas",
    "resolved",
    "MapSet",
    "image_maps",
    "DEFAULT_WORKERS",
]

#: Every map :func:`parameter_maps` returns, with its meaning and unit (also written into the
#: header of ``polrig analyze``'s EXR).
MAPS: dict[str, str] = {
    "m00": "unpolarized intensity transfer m00 (DN per unit incident S0)",
    "DL": "linear diattenuation |(m01, m02)| / m00",
    "DL_axis_deg": "incident polarization angle of maximum transmission, deg [0, 180), incident frame",
    "PL": "linear polarizance |(m10, m20)| / m00",
    "PL_axis_deg": "AoLP of the light unpolarized illumination leaves, deg [0, 180), emergent frame",
    "sv1": "largest singular value of the lower 2x2 block / m00 (invariant of independent frame rotations)",
    "sv2": "second singular value of the lower 2x2 block / m00, signed as its determinant",
    "mmt_b": "MMT b = (m11 + m22) / 2 / m00 (He et al. 2013; common-rotation invariant)",
    "mmt_t1": "MMT t1 = sqrt((m11 - m22)^2 + (m12 + m21)^2) / 2 / m00 (common-rotation invariant)",
    "mmt_A": "MMT anisotropy A = 2 b t1 / (b^2 + t1^2)",
    "mmt_x_deg": "MMT orientation x = atan2(m12 + m21, m11 - m22) / 4, deg [0, 90)",
    "retardance_deg": "linear retardance of the 3x3 polar decomposition, deg [0, 180] (assumes isotropic linear depolarization)",
    "retardance_axis_deg": "retarder axis of the 3x3 polar decomposition, deg [0, 90) (fast or slow: unknown), incident frame",
    "depolarization": "1 - Delta, linear depolarization of the 3x3 polar decomposition (assumes isotropic linear depolarization)",
    "rotation_deg": "rotation of the 3x3 polar decomposition's retarder (optical rotation and frame rotation), deg (-90, 90]",
}

#: Period of each angle map (its values lie in ``[0, period)``, the rotation in
#: ``(-period/2, period/2]``); differences of these maps are taken modulo the period.
ANGLE_PERIOD_DEG: dict[str, float] = {"DL_axis_deg": 180.0, "PL_axis_deg": 180.0,
                                      "mmt_x_deg": 90.0, "retardance_axis_deg": 90.0,
                                      "rotation_deg": 180.0}

#: Decomposition flag bits (``decomposition_flags``, uint8; 0 = decomposed, isotropic block).
DECOMP_UNDEFINED = 1
DECOMP_ASSUMED = 2
DECOMP_NONPHYSICAL = 4
DECOMPOSITION_FLAGS: dict[int, str] = {
    DECOMP_UNDEFINED: "undefined: m00 <= 0 or non-finite, linear diattenuation >= 1, or total "
                      "depolarization; the decomposition's maps are NaN",
    DECOMP_ASSUMED: "linearly anisotropic block: retardance or anisotropic depolarization, the "
                    "3x3 block cannot tell which (a retarder at 0 deg and the depolarizer "
                    "diag(1, 1, cos d, cos d) have the same block); the values assume isotropic "
                    "linear depolarization (Swami et al. 2006)",
    DECOMP_NONPHYSICAL: "Delta > 1 (depolarization < 0): noise or a non-physical block; values "
                        "reported as computed",
}
#: What the decomposition assumes, in words (written into the output's header).
DECOMPOSITION_ASSUMPTION = (
    "3x3 polar decomposition M = M_Delta M_R M_D of the linear block (Swami et al., Opt. Express "
    "14, 9324, 2006) assuming isotropic linear depolarization (the depolarizer's linear block is "
    "Delta I): the block cannot separate linear retardance from anisotropic linear "
    "depolarization, so retardance_deg, retardance_axis_deg and depolarization hold under that "
    "assumption only; decomposition_flags bit 2 marks the anisotropic pixels where it decides "
    "the answer (docs/analysis.md)")
#: How the ``sigma.*`` maps are computed (written into the output's header).
SIGMA_METHOD = (
    "first-order (linearised) propagation of the per-element sigma planes taken as independent, "
    "with analytic Jacobians (closed forms for m00, DL, PL, their axes and the MMT parameters; "
    "the chain rule through the 2x2 block for sv1, sv2 and the decomposition; infinite where a "
    "map is not differentiable) (docs/analysis.md)")

_DEG = 180.0 / np.pi
_ASSUMED_K = 3.0  # anisotropy significant at this many sigma: DECOMP_ASSUMED
_ANISOTROPY_TOL = 1e-9  # numerical floor of the anisotropy R (normalised block)
_EXCESS_TOL = 1e-9  # numerical floor of Delta - 1


def _blocks(m) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ValueError(f"expected 3x3 linear Mueller blocks of shape (..., 3, 3), got {m.shape}")
    return m


def _wrap(angle_deg: np.ndarray, period: float) -> np.ndarray:
    """``angle`` into ``[0, period)`` (NaN stays NaN)."""
    out = np.mod(angle_deg, period)
    return np.where(out >= period, out - period, out)  # mod can round up to the period


def _normalised(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M / m00, ok)``: ``ok`` where the matrix is finite and ``m00 > 0``; NaN elsewhere."""
    m00 = m[..., 0, 0]
    ok = np.isfinite(m).all(axis=(-2, -1)) & (m00 > 0)
    with np.errstate(all="ignore"):
        n = m / np.where(ok, m00, np.nan)[..., None, None]
    return n, ok


# -- diattenuation and polarizance ------------------------------------------------------------
def linear_diattenuation(m) -> tuple[np.ndarray, np.ndarray]:
    """Linear diattenuation and its axis of ``(..., 3, 3)`` blocks.

    Returns ``(DL, axis_deg)``, each ``(...)``: ``DL = |(m01, m02)| / m00`` (dimensionless, 0 to
    1 for a physical block) and ``axis_deg = atan2(m02, m01) / 2`` in ``[0, 180)``: the incident
    polarization angle (incident frame) that the block transmits most. NaN where ``m00 <= 0`` or
    an element is not finite. Lu and Chipman, JOSA A 13(5), 1106 (1996).
    """
    m = _blocks(m)
    n, ok = _normalised(m)
    with np.errstate(all="ignore"):
        dl = np.where(ok, np.hypot(n[..., 0, 1], n[..., 0, 2]), np.nan)
        axis = np.where(ok, _wrap(0.5 * _DEG * np.arctan2(m[..., 0, 2], m[..., 0, 1]), 180.0),
                        np.nan)
    return dl, axis


def linear_polarizance(m) -> tuple[np.ndarray, np.ndarray]:
    """Linear polarizance and its angle of ``(..., 3, 3)`` blocks: ``(PL, axis_deg)`` with
    ``PL = |(m10, m20)| / m00`` (the DoLP that unpolarized illumination leaves) and
    ``axis_deg = atan2(m20, m10) / 2`` in ``[0, 180)`` (its AoLP, emergent frame). NaN where
    ``m00 <= 0`` or not finite. Lu and Chipman 1996."""
    return linear_diattenuation(np.swapaxes(_blocks(m), -1, -2))


def _magnitude_axis_sigma(m: np.ndarray, s: np.ndarray, a: tuple[int, int],
                          b: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Linearised sigma of ``|(m_a, m_b)| / m00`` and of ``atan2(m_b, m_a) / 2`` (deg)."""
    m00, x, y = m[..., 0, 0], m[..., a[0], a[1]], m[..., b[0], b[1]]
    s00, sx, sy = s[..., 0, 0], s[..., a[0], a[1]], s[..., b[0], b[1]]
    with np.errstate(all="ignore"):
        r = np.hypot(x, y)
        mag = r / m00
        # at r = 0 the magnitude is a cone: every direction has slope 1 / m00
        ux = np.where(r > 0, x / r, np.sqrt(0.5))
        uy = np.where(r > 0, y / r, np.sqrt(0.5))
        sig_mag = _combine([(-mag / m00, s00), (ux / m00, sx), (uy / m00, sy)])
        r2 = r * r
        sig_axis = _combine([(-0.5 * _DEG * y / r2, sx), (0.5 * _DEG * x / r2, sy)])
    ok = np.isfinite(m).all(axis=(-2, -1)) & (m00 > 0)
    return np.where(ok, sig_mag, np.nan), np.where(ok, sig_axis, np.nan)


def _combine(terms) -> np.ndarray:
    """``sqrt(sum (g * s)^2)`` of ``(gradient, sigma)`` pairs; a zero gradient contributes 0 even
    where ``sigma`` is infinite."""
    total = 0.0
    with np.errstate(all="ignore"):
        for g, s in terms:
            term = (g * s) ** 2
            total = total + (term if np.isfinite(s).all() else np.where(g == 0, 0.0, term))
    return np.sqrt(total)


# -- rotation invariants ----------------------------------------------------------------------
def _svd2(a11, a12, a21, a22):
    """Closed-form signed singular values of 2x2 matrices: ``(s1, s2)`` with ``s1 >= |s2|``,
    ``s1 * s2 = det`` (Blinn's ``Q +- R`` form), plus ``(E, F, G, H, Q, R)``."""
    e, f = 0.5 * (a11 + a22), 0.5 * (a11 - a22)
    g, h = 0.5 * (a21 + a12), 0.5 * (a21 - a12)
    q, r = np.hypot(e, h), np.hypot(f, g)
    return q + r, q - r, (e, f, g, h, q, r)


def frame_invariants(m) -> tuple[np.ndarray, np.ndarray]:
    """Signed singular values ``(sv1, sv2)`` of the lower 2x2 block ``[[m11, m12], [m21, m22]]``
    divided by ``m00``, each ``(...)``: ``sv1 >= |sv2|``, ``sv1 * sv2`` the block's determinant.

    Under independent rotations of the incident and emergent bases, ``M -> R(a) M R(b)``
    (``docs/conventions.md``), the lower block is multiplied by rotations on both sides, which
    keeps its singular values and its determinant; with ``m00``, ``DL`` and ``PL`` these are the
    block's invariants of those rotations. Examples: a linear retarder ``(1, cos d)``, an ideal
    polarizer ``(1, 0)``, the depolarizer ``diag(1, a, a)`` ``(a, a)``, a mirror at normal
    incidence ``diag(1, 1, -1)`` ``(1, -1)``. NaN where
    ``m00 <= 0`` or not finite.
    """
    n, ok = _normalised(_blocks(m))
    with np.errstate(all="ignore"):
        s1, s2, _ = _svd2(n[..., 1, 1], n[..., 1, 2], n[..., 2, 1], n[..., 2, 2])
    return np.where(ok, s1, np.nan), np.where(ok, s2, np.nan)


# -- MMT ---------------------------------------------------------------------------------------
def mmt_parameters(m) -> dict[str, np.ndarray]:
    """The Mueller matrix transformation (MMT) parameters of He et al. (2013) on ``M / m00``:
    ``{"mmt_b", "mmt_t1", "mmt_A", "mmt_x_deg"}``, each ``(...)`` (module docstring for the
    formulas and references). ``A`` is NaN where ``b = t1 = 0``; ``x`` is 0 where ``t1 = 0``;
    everything NaN where ``m00 <= 0`` or not finite."""
    n, ok = _normalised(_blocks(m))
    with np.errstate(all="ignore"):
        b = 0.5 * (n[..., 1, 1] + n[..., 2, 2])
        u, v = n[..., 1, 1] - n[..., 2, 2], n[..., 1, 2] + n[..., 2, 1]
        t1 = 0.5 * np.hypot(u, v)
        a = 2 * b * t1 / (b * b + t1 * t1)
        x = _wrap(0.25 * _DEG * np.arctan2(v, u), 90.0)
    nan = np.nan
    return {"mmt_b": np.where(ok, b, nan), "mmt_t1": np.where(ok, t1, nan),
            "mmt_A": np.where(ok, a, nan), "mmt_x_deg": np.where(ok, x, nan)}


def _mmt_sigma(m: np.ndarray, s: np.ndarray) -> dict[str, np.ndarray]:
    """Analytic linearised sigma of :func:`mmt_parameters`."""
    m00 = m[..., 0, 0]
    a11, a12, a21, a22 = m[..., 1, 1], m[..., 1, 2], m[..., 2, 1], m[..., 2, 2]
    s00, s11, s12, s21, s22 = (s[..., 0, 0], s[..., 1, 1], s[..., 1, 2], s[..., 2, 1],
                               s[..., 2, 2])
    with np.errstate(all="ignore"):
        b = 0.5 * (a11 + a22) / m00
        u, v = (a11 - a22) / m00, (a12 + a21) / m00
        r = np.hypot(u, v)
        t1 = 0.5 * r
        # d/dm_ij of b and t1 (t1 = |(u, v)| / 2 is a cone at 0: slope 1/2 in every direction)
        cu = np.where(r > 0, u / r, np.sqrt(0.5))
        cv = np.where(r > 0, v / r, np.sqrt(0.5))
        gb = {"00": -b / m00, "11": 0.5 / m00, "22": 0.5 / m00, "12": 0.0, "21": 0.0}
        gt = {"00": -t1 / m00, "11": 0.5 * cu / m00, "22": -0.5 * cu / m00,
              "12": 0.5 * cv / m00, "21": 0.5 * cv / m00}
        den = b * b + t1 * t1
        da_db = 2 * t1 * (t1 * t1 - b * b) / den ** 2
        da_dt = 2 * b * (b * b - t1 * t1) / den ** 2
        r2 = r * r
        gx = {"11": -0.25 * _DEG * v / r2 / m00, "22": 0.25 * _DEG * v / r2 / m00,
              "12": 0.25 * _DEG * u / r2 / m00, "21": 0.25 * _DEG * u / r2 / m00}
        sig = {"00": s00, "11": s11, "12": s12, "21": s21, "22": s22}
        out = {
            "mmt_b": _combine([(gb[k], sig[k]) for k in gb]),
            "mmt_t1": _combine([(gt[k], sig[k]) for k in gt]),
            "mmt_A": _combine([(da_db * gb[k] + da_dt * gt[k], sig[k]) for k in gb]),
            "mmt_x_deg": _combine([(gx[k], sig[k]) for k in gx]),
        }
    ok = np.isfinite(m).all(axis=(-2, -1)) & (m00 > 0)
    return {k: np.where(ok, v, np.nan) for k, v in out.items()}


# -- the 3x3 polar decomposition ----------------------------------------------------------------
def decompose_linear(m) -> dict[str, np.ndarray]:
    """3x3 polar decomposition ``M = M_Delta M_R M_D`` of ``(..., 3, 3)`` blocks under the
    assumption of isotropic linear depolarization (Swami et al. 2006; the derivation, the
    assumption and what the block cannot tell are in the module docstring).

    Returns ``{"retardance_deg", "retardance_axis_deg", "depolarization", "rotation_deg",
    "decomposition_flags"}``, each ``(...)``: the linear retardance in ``[0, 180]`` deg, the
    retarder's axis in ``[0, 90)`` deg (incident frame; fast or slow axis: the block cannot
    tell), ``1 - Delta`` (``Delta`` the linear depolarization factor, 1 for a
    non-depolarizing block), the rotation that follows the linear retarder in ``(-90, 90]`` deg
    (optical rotation from ``x`` towards ``y``, and any rotation between the incident and the
    emergent frame), and the flag bits (:func:`decomposition_flags` without sigma: numerical
    tolerances only). NaN maps and ``DECOMP_UNDEFINED`` where the decomposition cannot be
    formed.

    The retardance is computed as ``2 atan2(sqrt(R), sqrt(Q))`` (``tan^2(d/2) = R / Q``), which
    keeps the accuracy of ``R`` and ``Q`` where ``arccos((Q - R) / (Q + R))`` loses it; a
    retardance near 0 or 180 deg is still ill-conditioned by nature (``d ~ 2 sqrt(R / Q)``):
    rounding errors ``e`` of the block give errors ``~ sqrt(e)`` there, about 1e-5 deg in
    float64.
    """
    m = _blocks(m)
    out, internal = _decompose(m)
    out["decomposition_flags"] = _flags(internal, None, _ASSUMED_K)
    return out


def _decompose(m: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The four decomposition maps, and the internal quantities of the flags: ``defined``
    (bool), ``anisotropy`` (``R = (s1 - s2) / 2`` of ``m'``, 0 for an isotropic block) and
    ``excess`` (``Delta - 1``)."""
    n, ok = _normalised(m)
    with np.errstate(all="ignore"):
        d1, d2 = n[..., 0, 1], n[..., 0, 2]
        p1, p2 = n[..., 1, 0], n[..., 2, 0]
        dd = d1 * d1 + d2 * d2
        ok = ok & (dd < 1.0)
        k2 = np.where(ok, 1.0 - dd, np.nan)
        k = np.sqrt(k2)
        c = 1.0 / (1.0 + k)
        i11, i12, i22 = k + c * d1 * d1, c * d1 * d2, k + c * d2 * d2  # m_D
        a11, a12, a21, a22 = n[..., 1, 1], n[..., 1, 2], n[..., 2, 1], n[..., 2, 2]
        q11 = (a11 * i11 + a12 * i12 - p1 * d1) / k2  # m' = (n m_D - P D^T) / k^2
        q12 = (a11 * i12 + a12 * i22 - p1 * d2) / k2
        q21 = (a21 * i11 + a22 * i12 - p2 * d1) / k2
        q22 = (a21 * i12 + a22 * i22 - p2 * d2) / k2
        s1, _, (e, f, g, h, q, r) = _svd2(q11, q12, q21, q22)
        ok = ok & (s1 > 0)
        delta = np.where(ok, s1, np.nan)
        retardance = 2.0 * np.arctan2(np.sqrt(r), np.sqrt(q))  # cos d = (Q - R) / (Q + R)
        rho = 0.5 * np.arctan2(h, e)  # radians; atan2(0, 0) = 0 at a half-wave retarder
        cr, sr = np.cos(2 * rho), np.sin(2 * rho)
        # L = Rot(-rho) A with A = m' / Delta: the optical rotation undone (rotator(rho) block)
        l11 = (cr * q11 + sr * q21) / delta
        l12 = (cr * q12 + sr * q22) / delta
        l21 = (-sr * q11 + cr * q21) / delta
        l22 = (-sr * q12 + cr * q22) / delta
        axis = _wrap(0.25 * _DEG * np.arctan2(l12 + l21, l11 - l22), 90.0)
        rot = _DEG * rho
        rot = np.where(rot <= -90.0, rot + 180.0, rot)
    nan = np.nan
    maps = {"retardance_deg": np.where(ok, _DEG * retardance, nan),
            "retardance_axis_deg": np.where(ok, axis, nan),
            "depolarization": np.where(ok, 1.0 - delta, nan),
            "rotation_deg": np.where(ok, rot, nan)}
    internal = {"defined": ok, "anisotropy": np.where(ok, r, nan),
                "excess": np.where(ok, delta - 1.0, nan),
                "parts": _DecompositionParts(n, d1, d2, p1, p2, k, k2, c, i11, i12, i22,
                                             q11, q12, q21, q22, e, f, g, h, q, r)}
    return maps, internal


def _flags(internal: Mapping[str, np.ndarray], sig: Mapping[str, np.ndarray] | None,
           k: float) -> np.ndarray:
    """Flag bits from :func:`_decompose`'s internal quantities and (optionally) their sigma."""
    defined = internal["defined"]
    aniso, excess = internal["anisotropy"], internal["excess"]
    with np.errstate(invalid="ignore"):
        assumed = aniso > _ANISOTROPY_TOL
        nonphysical = excess > _EXCESS_TOL
        if sig is not None:
            sa, se = sig["anisotropy"], sig["excess"]
            assumed = np.where(np.isfinite(sa), aniso > np.maximum(k * sa, _ANISOTROPY_TOL),
                               assumed)
            nonphysical = np.where(np.isfinite(se), excess > np.maximum(k * se, _EXCESS_TOL),
                                   nonphysical)
    flags = np.where(defined, 0, DECOMP_UNDEFINED)
    flags = flags | np.where(defined & assumed, DECOMP_ASSUMED, 0)
    flags = flags | np.where(defined & nonphysical, DECOMP_NONPHYSICAL, 0)
    return flags.astype(np.uint8)


def decomposition_flags(m, sigma=None, *, k: float = _ASSUMED_K) -> np.ndarray:
    """Flag bits (:data:`DECOMPOSITION_FLAGS`, uint8 ``(...)``) of the decomposition of
    ``(..., 3, 3)`` blocks.

    ``DECOMP_UNDEFINED`` where the decomposition cannot be formed. ``DECOMP_ASSUMED`` where the
    block is linearly anisotropic: the anisotropy ``R = (s1 - s2) / 2`` of ``m'`` (module
    docstring; ``R = Delta (1 - cos d) / 2`` in the model) exceeds ``k`` of its linearised
    sigmas (with per-element ``sigma``) and a numerical tolerance of 1e-9. There the split
    between retardance and anisotropic depolarization rests on the assumption. ``R`` is a
    magnitude, so on an isotropic block with noise it exceeds ``k`` sigma with the Rayleigh
    probability ``exp(-k^2 / 2)``: 1.1 % for the default ``k = 3`` (the retardance's own
    linearised sigma would not do: its derivative grows without bound at ``d = 0``).
    ``DECOMP_NONPHYSICAL`` where ``Delta > 1`` by more than ``k`` sigma (and 1e-9).
    """
    m = _blocks(m)
    _, internal = _evaluate(m)
    sig = None
    if sigma is not None:
        s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), m.shape)
        sig = _chain_sigma(m, s, internal["parts"], ("anisotropy", "excess"))
    return _flags(internal, sig, k)


# -- every map at once -------------------------------------------------------------------------
def parameter_maps(m) -> dict[str, np.ndarray]:
    """Every map of :data:`MAPS` (float64 ``(...)``) plus ``decomposition_flags`` (uint8,
    numerical tolerances; :func:`decomposition_flags` with sigma for measured blocks) of
    ``(..., 3, 3)`` blocks."""
    out, internal = _evaluate(_blocks(m))
    out["decomposition_flags"] = _flags(internal, None, _ASSUMED_K)
    return out


def _evaluate(m: np.ndarray):
    """``(maps of MAPS, the decomposition's internal quantities)`` (its intermediates under
    ``"parts"``, :class:`_DecompositionParts`), the decomposition computed once."""
    out: dict[str, np.ndarray] = {"m00": m[..., 0, 0].copy()}
    out["DL"], out["DL_axis_deg"] = linear_diattenuation(m)
    out["PL"], out["PL_axis_deg"] = linear_polarizance(m)
    out["sv1"], out["sv2"] = frame_invariants(m)
    out.update(mmt_parameters(m))
    maps, internal = _decompose(m)
    out.update(maps)
    return out, internal


#: The quantities whose sigma goes through the chain rule of the 2x2 block (:func:`_chain_sigma`).
_CHAIN_NAMES = ("sv1", "sv2", "retardance_deg", "retardance_axis_deg", "depolarization",
                "rotation_deg", "anisotropy", "excess")


@dataclasses.dataclass
class _DecompositionParts:
    """The intermediate planes of :func:`_decompose` (``(...)`` each; names as in the module
    docstring): the normalised block ``n``, ``D = (d1, d2)``, ``P = (p1, p2)``, ``k``,
    ``k^2``, ``c = 1 / (1 + k)``, ``m_D = [[i11, i12], [i12, i22]]``, ``m' = [[q11, q12],
    [q21, q22]]`` and its ``E, F, G, H, Q, R``."""

    n: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    k: np.ndarray
    k2: np.ndarray
    c: np.ndarray
    i11: np.ndarray
    i12: np.ndarray
    i22: np.ndarray
    q11: np.ndarray
    q12: np.ndarray
    q21: np.ndarray
    q22: np.ndarray
    e: np.ndarray
    f: np.ndarray
    g: np.ndarray
    h: np.ndarray
    q: np.ndarray
    r: np.ndarray


def _dq_dn(p: _DecompositionParts) -> dict[tuple[int, int], tuple]:
    """``d(q11, q12, q21, q22) / dn_ij`` of ``m' = (a m_D - P D^T) / k^2`` for the eight
    elements ``(i, j) != (0, 0)`` of the normalised block (``a`` its lower 2x2 block; a 0 entry
    is an exact zero). With ``dk / dD_l = -D_l / k`` and ``dc / dD_l = c^2 D_l / k``:
    ``dm_D / dD_l = -(D_l / k) I + c (e_l D^T + D e_l^T) + (c^2 D_l / k) D D^T`` and
    ``dm' / dD_l = (a dm_D / dD_l - P e_l^T + 2 D_l m') / k^2``."""
    n, d1, d2, p1, p2 = p.n, p.d1, p.d2, p.p1, p.p2
    a11, a12, a21, a22 = n[..., 1, 1], n[..., 1, 2], n[..., 2, 1], n[..., 2, 2]
    inv = 1.0 / p.k2  # NaN where the decomposition is undefined
    out: dict[tuple[int, int], tuple] = {
        (1, 1): (p.i11 * inv, p.i12 * inv, 0.0, 0.0),
        (1, 2): (p.i12 * inv, p.i22 * inv, 0.0, 0.0),
        (2, 1): (0.0, 0.0, p.i11 * inv, p.i12 * inv),
        (2, 2): (0.0, 0.0, p.i12 * inv, p.i22 * inv),
        (1, 0): (-d1 * inv, -d2 * inv, 0.0, 0.0),
        (2, 0): (0.0, 0.0, -d1 * inv, -d2 * inv),
    }
    for col, dl in ((1, d1), (2, d2)):
        w = p.c * p.c * dl / p.k
        j11 = -dl / p.k + w * d1 * d1
        j12 = w * d1 * d2
        j22 = -dl / p.k + w * d2 * d2
        if col == 1:
            j11, j12 = j11 + 2.0 * p.c * d1, j12 + p.c * d2
        else:
            j22, j12 = j22 + 2.0 * p.c * d2, j12 + p.c * d1
        # - P e_l^T: p1, p2 in column l only
        p1_1, p1_2 = (p1, 0.0) if col == 1 else (0.0, p1)
        p2_1, p2_2 = (p2, 0.0) if col == 1 else (0.0, p2)
        out[(0, col)] = ((a11 * j11 + a12 * j12 - p1_1 + 2 * dl * p.q11) * inv,
                         (a11 * j12 + a12 * j22 - p1_2 + 2 * dl * p.q12) * inv,
                         (a21 * j11 + a22 * j12 - p2_1 + 2 * dl * p.q21) * inv,
                         (a21 * j12 + a22 * j22 - p2_2 + 2 * dl * p.q22) * inv)
    return out


def _unit(x: np.ndarray, y: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y) / r``; at ``r = 0`` (a cone point of ``r = |(x, y)|``) the convention of
    :func:`_magnitude_axis_sigma`: every direction has slope 1."""
    with np.errstate(all="ignore"):
        return np.where(r > 0, x / r, np.sqrt(0.5)), np.where(r > 0, y / r, np.sqrt(0.5))


def _accumulate(var: dict, euler: dict, name: str, grad, m_ij, s_ij, s_finite: bool) -> None:
    """Add ``(grad s_ij)^2`` to ``var[name]`` (a zero gradient adds 0 even where ``s_ij`` is
    infinite) and ``m_ij grad`` to ``euler[name]``."""
    term = (grad * s_ij) ** 2 if s_finite else np.where(grad == 0, 0.0, (grad * s_ij) ** 2)
    var[name] = var[name] + term
    euler[name] = euler[name] + m_ij * grad


def _chain_sigma(m: np.ndarray, s: np.ndarray, parts: _DecompositionParts,
                 names: tuple[str, ...] = _CHAIN_NAMES) -> dict[str, np.ndarray]:
    """Analytic linearised sigma of ``names`` (of :data:`_CHAIN_NAMES`) by the chain rule
    ``m -> n -> m' -> (E, F, G, H) -> map``, and for ``sv1``, ``sv2``: ``n``'s lower block
    ``-> (E, F, G, H) -> map`` (:func:`_svd2`).

    In ``E, F, G, H``: ``dQ = (E dE + H dH) / Q``, ``dR = (F dF + G dG) / R`` (at a cone point
    ``Q = 0`` or ``R = 0`` every direction has slope 1, as in :func:`_magnitude_axis_sigma`);
    ``Delta = s1 = Q + R``, ``s2 = Q - R``; the retardance ``2 atan2(sqrt R, sqrt Q)`` has
    ``d = (Q dR - R dQ) / (sqrt(RQ) (Q + R))``; the rotation ``atan2(H, E) / 2`` and the axis
    ``(atan2(G, F) - atan2(H, E)) / 4`` (the axis of ``L = Rot(-rho) A`` in the module
    docstring is the angle of ``(F, G)`` turned by ``-2 rho``) have
    ``d atan2(y, x) = (x dy - y dx) / (x^2 + y^2)``. Every map is homogeneous of degree 0 in
    ``m``, so the ``m00`` derivative follows from the others (Euler):
    ``dX/dm00 = -sum_{ij != 00} m_ij dX/dm_ij / m00``. Where a map is not differentiable (the
    retardance at ``R = 0`` or ``Q = 0``, the axis and rotation where the angle they follow
    has magnitude 0) its sigma is infinite.
    """
    m00 = m[..., 0, 0]
    want = set(names)
    var: dict[str, object] = {name: 0.0 for name in names}
    euler: dict[str, object] = {name: 0.0 for name in names}
    with np.errstate(all="ignore"):
        inv00 = 1.0 / m00
        p = parts
        ue, uh = _unit(p.e, p.h, p.q)
        uf, ug = _unit(p.f, p.g, p.r)
        kr = _DEG / (np.sqrt(p.r * p.q) * (p.q + p.r))
        q2, r2 = p.q * p.q, p.r * p.r
        # the sigma of sv1, sv2 from n's lower block (E', F', G', H')
        if want & {"sv1", "sv2"}:
            n = p.n
            en, hn = 0.5 * (n[..., 1, 1] + n[..., 2, 2]), 0.5 * (n[..., 2, 1] - n[..., 1, 2])
            fn, gn = 0.5 * (n[..., 1, 1] - n[..., 2, 2]), 0.5 * (n[..., 2, 1] + n[..., 1, 2])
            sue, suh = _unit(en, hn, np.hypot(en, hn))
            suf, sug = _unit(fn, gn, np.hypot(fn, gn))
            # d(E', F', G', H') / dn_ij of the lower block: dQ' and dR' per element
            for (i, j), de, df, dg, dh in (((1, 1), 0.5, 0.5, 0.0, 0.0),
                                           ((2, 2), 0.5, -0.5, 0.0, 0.0),
                                           ((1, 2), 0.0, 0.0, 0.5, -0.5),
                                           ((2, 1), 0.0, 0.0, 0.5, 0.5)):
                dq_ = (sue * de + suh * dh) * inv00
                dr_ = (suf * df + sug * dg) * inv00
                fin = bool(np.isfinite(s[..., i, j]).all())
                for name, grad in (("sv1", dq_ + dr_), ("sv2", dq_ - dr_)):
                    if name in want:
                        _accumulate(var, euler, name, grad, m[..., i, j], s[..., i, j], fin)
        decomposition = want - {"sv1", "sv2"}
        if decomposition:
            for (i, j), (d11, d12, d21, d22) in _dq_dn(p).items():
                de, df = 0.5 * (d11 + d22) * inv00, 0.5 * (d11 - d22) * inv00
                dg, dh = 0.5 * (d21 + d12) * inv00, 0.5 * (d21 - d12) * inv00
                dq_, dr_ = ue * de + uh * dh, uf * df + ug * dg
                fin = bool(np.isfinite(s[..., i, j]).all())
                turn = ((p.e * dh - p.h * de) / q2  # d atan2(H, E)
                        if want & {"rotation_deg", "retardance_axis_deg"} else None)
                for name in decomposition:
                    if name == "excess":
                        grad = dq_ + dr_
                    elif name == "depolarization":
                        grad = -(dq_ + dr_)
                    elif name == "anisotropy":
                        grad = dr_
                    elif name == "retardance_deg":
                        grad = kr * (p.q * dr_ - p.r * dq_)
                    elif name == "rotation_deg":
                        grad = 0.5 * _DEG * turn
                    else:  # retardance_axis_deg
                        grad = 0.25 * _DEG * ((p.f * dg - p.g * df) / r2 - turn)
                    _accumulate(var, euler, name, grad, m[..., i, j], s[..., i, j], fin)
        fin00 = bool(np.isfinite(s[..., 0, 0]).all())
        out = {}
        for name in names:
            g00 = -euler[name] * inv00
            term = (g00 * s[..., 0, 0]) ** 2
            out[name] = np.sqrt(var[name] + (term if fin00 else np.where(g00 == 0, 0.0, term)))
        cone_q, cone_r = p.q == 0, p.r == 0
        for name, cone in (("retardance_deg", cone_q | cone_r), ("rotation_deg", cone_q),
                           ("retardance_axis_deg", cone_q | cone_r)):
            if name in out:
                out[name] = np.where(cone, np.inf, out[name])
    return out


def _all_sigmas(m: np.ndarray, s: np.ndarray,
                parts: _DecompositionParts) -> dict[str, np.ndarray]:
    """Sigma of every map and of the flags' internal quantities (``parts``: the intermediates
    of :func:`_decompose` at ``m``)."""
    out: dict[str, np.ndarray] = {"m00": s[..., 0, 0].copy()}
    out["DL"], out["DL_axis_deg"] = _magnitude_axis_sigma(m, s, (0, 1), (0, 2))
    out["PL"], out["PL_axis_deg"] = _magnitude_axis_sigma(m, s, (1, 0), (2, 0))
    out.update(_mmt_sigma(m, s))
    out.update(_chain_sigma(m, s, parts))
    return out


def parameter_sigmas(m, sigma) -> dict[str, np.ndarray]:
    """Linearised standard deviations of every map of :data:`MAPS` (float64 ``(...)``), from the
    independent per-element standard deviations ``sigma (..., 3, 3)`` (same units as ``m``;
    NaN where the map is NaN or a sigma it depends on is NaN). Method: the module docstring."""
    m = _blocks(m)
    s = np.broadcast_to(np.asarray(sigma, dtype=np.float64), m.shape)
    values, internal = _evaluate(m)
    out = _all_sigmas(m, s, internal["parts"])
    return {name: np.where(np.isnan(values[name]), np.nan, out[name]) for name in MAPS}


#: Default of :func:`resolved`: a map's linearised sigma is trusted where the magnitude it rests
#: on is at least this many of its sigmas from its boundary.
RESOLVED_K = 5.0


def resolved(values: Mapping[str, np.ndarray], sigmas: Mapping[str, np.ndarray], *,
             k: float = RESOLVED_K) -> dict[str, np.ndarray]:
    """Where each map is resolved: boolean ``(...)`` by map name, True where the value and its
    sigma are finite and the magnitude the map rests on is at least ``k`` of its sigmas away
    from the boundary where the map stops being smooth. There the linearised sigma is a
    standard deviation (``docs/analysis.md``: the coverage measured on a simulated capture);
    elsewhere the map is biased (a magnitude near 0 is overestimated, like a Rician amplitude)
    or undefined (an axis of a magnitude within its noise), and its sigma is not a confidence
    interval.

    The boundaries: ``m00`` (0), ``DL`` and its axis (``DL = 0``), ``PL`` and its axis,
    ``sv1`` (0), ``sv2`` (``sv1 = +-sv2``: the 2x2 block isotropic or with zero trace part),
    ``mmt_t1``, ``mmt_A`` and ``mmt_x_deg`` (``t1 = 0``), ``mmt_b`` (none: linear in the
    elements), ``retardance_deg`` and its axis (0 and 180 deg), ``depolarization``
    (``Delta = 0``), ``rotation_deg`` (both of the decomposition's). ``values`` and ``sigmas``
    as :func:`parameter_maps` and :func:`parameter_sigmas` return them (or a :class:`MapSet`'s).
    """
    v = {n: np.asarray(values[n], dtype=np.float64) for n in MAPS}
    s = {n: np.asarray(sigmas[n], dtype=np.float64) for n in MAPS}
    with np.errstate(all="ignore"):
        def above(x, sx):
            return x >= k * sx

        ret = np.minimum(v["retardance_deg"], 180.0 - v["retardance_deg"])
        ret_ok = above(ret, s["retardance_deg"])
        dep_ok = above(1.0 - v["depolarization"], s["depolarization"])
        t1_ok = above(v["mmt_t1"], s["mmt_t1"])
        sv_sigma = s["sv1"] + s["sv2"]
        out = {
            "m00": above(v["m00"], s["m00"]),
            "DL": above(v["DL"], s["DL"]), "DL_axis_deg": above(v["DL"], s["DL"]),
            "PL": above(v["PL"], s["PL"]), "PL_axis_deg": above(v["PL"], s["PL"]),
            "sv1": above(v["sv1"], s["sv1"]),
            "sv2": above(np.minimum(v["sv1"] + v["sv2"], v["sv1"] - v["sv2"]), sv_sigma),
            "mmt_b": np.ones(v["mmt_b"].shape, bool), "mmt_t1": t1_ok, "mmt_A": t1_ok,
            "mmt_x_deg": t1_ok,
            "retardance_deg": ret_ok, "retardance_axis_deg": ret_ok,
            "depolarization": dep_ok, "rotation_deg": ret_ok & dep_ok,
        }
    return {n: out[n] & np.isfinite(v[n]) & np.isfinite(s[n]) for n in MAPS}


# -- images -----------------------------------------------------------------------------------
@dataclasses.dataclass
class MapSet:
    """Maps of a Mueller image: ``values`` and ``sigma`` by map name (:data:`MAPS`), float32
    ``(C, H, W)`` (``sigma`` empty without input sigma), ``flags`` the decomposition's uint8
    ``(C, H, W)``."""

    values: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    flags: np.ndarray


#: Default of :func:`image_maps`'s ``workers``: threads over bands (numpy releases the GIL).
DEFAULT_WORKERS = max(1, min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                             else (os.cpu_count() or 1)))


def image_maps(mueller, sigma=None, *, k: float = _ASSUMED_K,
               band_pixels: int = 1 << 14, workers: int | None = None) -> MapSet:
    """Every map of a Mueller image ``(C, 3, 3, H, W)`` (plane-first, ``docs/conventions.md``)
    and, with ``sigma`` of the same shape (the result's ``sigma.M{rc}`` planes), their
    linearised standard deviations; the decomposition flags use them
    (:func:`decomposition_flags` with significance ``k``). Returned as float32.

    Computed in float64 over bands of image rows of about ``band_pixels`` pixels (times
    colours), on ``workers`` threads (default :data:`DEFAULT_WORKERS`): the memory beyond the
    input and the output is that of ``workers`` bands' intermediates (tens of MB), whatever the
    image size. Every pixel's numbers depend on that pixel only and on no reduction, so the
    result is the same to the bit for any band size and thread count."""
    img = np.asarray(mueller)
    if img.ndim != 5 or img.shape[1:3] != (3, 3):
        raise ValueError(f"Mueller images must have shape (C, 3, 3, H, W), got {img.shape}")
    sig = None if sigma is None else np.broadcast_to(np.asarray(sigma), img.shape)
    c, _, _, h, w = img.shape
    values = {name: np.empty((c, h, w), np.float32) for name in MAPS}
    sigmas = {name: np.empty((c, h, w), np.float32) for name in MAPS} if sig is not None else {}
    flags = np.empty((c, h, w), np.uint8)
    rows = max(1, int(band_pixels) // max(1, w * c))

    def band(r0: int) -> None:
        r1 = min(h, r0 + rows)
        mb = np.moveaxis(img[..., r0:r1, :].astype(np.float64), (1, 2), (-2, -1))
        vals, internal = _evaluate(mb)
        sb = None
        if sig is not None:
            sb = _all_sigmas(mb, np.moveaxis(sig[..., r0:r1, :].astype(np.float64),
                                             (1, 2), (-2, -1)), internal["parts"])
            for name in MAPS:
                sigmas[name][:, r0:r1] = np.where(np.isnan(vals[name]), np.nan, sb[name])
        for name in MAPS:
            values[name][:, r0:r1] = vals[name]
        flags[:, r0:r1] = _flags(internal, sb, k)

    starts = range(0, h, rows)
    n_threads = min(len(starts), max(1, int(workers or DEFAULT_WORKERS)))
    if n_threads < 2:
        for r0 in starts:
            band(r0)
    else:
        with concurrent.futures.ThreadPoolExecutor(n_threads,
                                                   thread_name_prefix="polrig-maps") as pool:
            for done in pool.map(band, starts):
                del done  # re-raises a band's exception here
    return MapSet(values, sigmas, flags)
