"""The network prior's scale, per image, from the states measured after the seen one.

The hybrid solve (:mod:`polrig.solve.hybrid`) takes the network's calibrated sigma as its
prior. That sigma is calibrated over many scenes, not for this one: on one scene the network's
errors may be smaller than the sigma (the simulated rig's spheres: 98 % within 2 sigma at two
states) or larger (its `plane`: 90 %). Every state measured after the seen one shows how large
they are here, in the directions it observes: its Stokes vector ``S_j = M s_j`` is predicted by
the seen frame and the prior alone, and the prediction's error is the network's error there,
plus noise. This module finds the scale ``c`` of the prior's sigma under which those
predictions' errors lie within 2 of their predicted standard deviation as often as a right
Gaussian's do (95.45 %): the empirical Bayes estimate of a prior's scale from the marginal
distribution of the data (Casella, "An introduction to empirical Bayes data analysis",
The American Statistician 39, 1985), in the quantile form the sigma itself is calibrated in
(:mod:`polrig.models.uncertainty`), which heavy tails do not sway as a variance would.

**The prediction.** With ``u = s_0 / |s_0|`` the seen state's direction, each row ``m_r`` of
``M`` is known along ``u`` from the seen frame's Stokes (``m_r . u = S_0r / |s_0|``, its noise
from the frame's own samples) and in the plane ``u`` leaves open it is the prior's, with the
covariance the hybrid solve gives it: the pseudo-inverse of
:func:`polrig.solve.hybrid.unobserved_precision` (the row's marginal; the joint prior's
correlation across rows, :mod:`polrig.solve.hybrid`, "Joint prior", leaves each row's marginal
as it is and is not used here). So, per state ``j`` after the seen one, row ``r``, pixel and
colour,

    S_jr = m_prior,r . s_j + (s_j . u) (S_0r / |s_0| - m_prior,r . u) + e,
    var e = c^2 s_j^T C_r s_j + N_jr,

``C_r`` the plane's prior covariance and ``N_jr`` the noise of ``S_jr`` and of the seen
frame's term. The observed directions' scale is taken for the whole prior: the open direction
at two states (column 2 of the seen frame, light at 45 deg to the seen state) is no part of
any innovation, so :data:`SHRINK` takes the estimate partly (``c ** SHRINK``), as fitted on
the calibration scenes (:mod:`polrig.models.coverage_diagnosis`, "A what-if of the prior's scale
from the innovations"; what it does to every set: ``docs/continuum.md``, "Against issue 33's
acceptance, line by line").

Captures take it (``--prior-scale innovations``, and ``geometry``, which at two states adds the
open direction's own scale from the diffuse term's geometry, :mod:`polrig.solve.open_scale`;
``calibrated`` keeps the sigma as calibrated): :func:`polrig.solve.radiometry.prior_scale_from_frames`
estimates it from an even sample of the output rows before the band-by-band solve, and each
hybrid result records it (:class:`PriorScale`, the manifest's ``prior`` record and the EXR
header).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from polrig.choices import PRIOR_SCALES
from polrig.solve.diffuse_test import state_stokes
from polrig.solve.hybrid import observed_direction, plane_axis, unobserved_precision

#: Share of errors within 2 standard deviations for a right Gaussian (erf(sqrt 2)).
COVERAGE = 0.9545
#: Fewest usable innovations (pixel x colour x row x state) for an estimate; fewer: scale 1.
MIN_INNOVATIONS = 30
#: Range the raw estimate ``c`` is kept in.
SCALE_LIMITS = (0.1, 10.0)
#: Exponent of the raw estimate taken for the prior's scale, ``c ** SHRINK`` (module docstring):
#: where two states 0/90 cover 95.45 % of the calibration scenes' elements (their 48 lit samples
#: of ``python -m polrig.models.coverage_diagnosis --count 64``, the shipped network and sigma).
SHRINK = 0.84
#: The choices of a capture's prior scale: ``innovations`` (this module's), ``geometry`` (this
#: module's and :mod:`polrig.solve.open_scale`'s) or ``calibrated`` (the sigma as calibrated,
#: factor 1); defined in :mod:`polrig.choices`.
METHODS = PRIOR_SCALES


@dataclasses.dataclass(frozen=True)
class PriorScale:
    """The factor ``factor`` the prior's calibrated sigma is multiplied by, how it was found
    (``method``, :data:`METHODS`), the raw estimate ``raw`` (:func:`innovation_scale`), the
    exponent ``shrink`` it was taken to and the number of ``innovations`` it rests on (0: one
    state, or the calibrated sigma)."""

    method: str
    factor: float
    raw: float
    shrink: float
    innovations: int

    @classmethod
    def calibrated(cls) -> "PriorScale":
        """The sigma as calibrated: factor 1."""
        return cls("calibrated", 1.0, 1.0, 0.0, 0)

    def record(self) -> dict[str, Any]:
        """The manifest's and the EXR header's record (:class:`polrig.app.manifest.PriorScaleRecord`)."""
        return dataclasses.asdict(self)


def scale_of(d: np.ndarray, p: np.ndarray, n: np.ndarray, shrink: float = SHRINK) -> PriorScale:
    """The :class:`PriorScale` of :func:`innovations`' ``(d, p, n)``: :func:`innovation_scale`
    to the power ``shrink``."""
    raw = innovation_scale(d, p, n)
    return PriorScale("innovations", float(raw ** float(shrink)), raw, float(shrink), int(np.count_nonzero(_usable(d, p, n))))


def plane_basis(u: np.ndarray) -> np.ndarray:
    """An orthonormal basis ``(3, 2)`` of the plane orthogonal to the unit ``u`` ``(3,)``:
    ``[v1, v2]`` of :func:`polrig.solve.hybrid.plane_axis` where the seen state has an axis,
    else any."""
    v1 = plane_axis(u)
    if v1 is None:
        pick = np.eye(3)[int(np.argmin(np.abs(u)))]
        v1 = pick - (pick @ u) * u
        v1 /= np.linalg.norm(v1)
    return np.stack([v1, np.cross(v1, u)], axis=1)


def innovations(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray, valid: np.ndarray | None,
                prior_mean: np.ndarray, prior_sigma: np.ndarray, seen_state: int = 0,
                analyzer_rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The states after the seen one, predicted from the seen frame and the prior (module
    docstring): ``(d, p, n)``, each a 1-D array over the usable pixel x colour x row x state
    values: the prediction's error ``d`` (measured Stokes less predicted), the prior's part of
    its variance ``p`` (at scale 1) and the noise's ``n``, in the units of ``measured``.

    ``s_in`` ``(N, 3)``, ``measured``, ``variance`` ``(N, C, 4, H, W)``, ``valid`` as
    :func:`polrig.solve.hybrid.solve_hybrid` takes them (``analyzer_rows`` shared ``(4, 3)``,
    per pixel ``(C, 4, 3, H, W)``, or None: ideal); ``prior_mean``, ``prior_sigma``
    ``(C, 3, 3, H, W)``. Usable: all four samples of the seen frame and of the state used, every
    element of the row with a finite positive prior sigma. Only the pixels where some row of
    some colour has such a sigma (the network's object) are computed, gathered in scan order:
    the values and their order are those of the whole image, at the object's share of the cost."""
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    sigma = np.asarray(prior_sigma)
    usable_row = np.all(np.isfinite(sigma) & (sigma > 0), axis=2)  # (C, 3, H, W)
    ys, xs = np.nonzero(usable_row.any(axis=(0, 1)))
    pick = lambda a: None if a is None else np.asarray(a)[..., ys, xs][..., None]  # noqa: E731  (..., P, 1)
    measured, variance, valid, prior_mean, prior_sigma, usable_row = (
        pick(a) for a in (measured, variance, valid, prior_mean, sigma, usable_row))
    if analyzer_rows is not None and np.ndim(analyzer_rows) == 5:
        analyzer_rows = pick(analyzer_rows)
    # from here on the images are the object's pixels as a (P, 1) image: H, W below are P, 1
    u = observed_direction(s[seen_state])
    norm0 = float(np.linalg.norm(s[seen_state]))
    basis = plane_basis(u)  # (3, 2)
    mean = np.asarray(prior_mean, np.float64)
    sd = np.moveaxis(np.asarray(prior_sigma, np.float64), 2, -1)  # (C, 3, H, W, 3): rows' sigma
    prec = unobserved_precision(np.where(usable_row[..., None], sd, 1.0), s[seen_state])  # (C, 3, H, W, 3, 3)
    m2 = np.einsum("ai,...ab,bj->...ij", basis, prec, basis)  # the plane's precision (..., 2, 2)
    det = np.linalg.det(m2)
    usable_row &= np.isfinite(det) & (det > 0)
    cov = np.linalg.inv(np.where(usable_row[..., None, None], m2, np.eye(2)))  # the plane's prior covariance
    seen, seen_info, seen_ok = state_stokes(measured[seen_state], variance[seen_state],
                                            None if valid is None else valid[seen_state], analyzer_rows)
    seen_var = _diagonal_of_inverse(seen_info)  # (C, 3, H, W)
    along_u = seen / norm0 - np.einsum("crkhw,k->crhw", mean, u)
    d, p, n = [], [], []
    for j in range(len(s)):
        if j == seen_state:
            continue
        stokes, info, ok = state_stokes(measured[j], variance[j], None if valid is None else valid[j], analyzer_rows)
        su = float(s[j] @ u)
        w = basis.T @ s[j]  # (2,)
        pred = np.einsum("crkhw,k->crhw", mean, s[j]) + su * along_u
        use = usable_row & (ok & seen_ok)[:, None] & np.isfinite(stokes) & np.isfinite(pred)
        d.append((stokes - pred)[use])
        p.append(np.einsum("i,...ij,j->...", w, cov, w)[use])
        # the seen frame's noise along u; a state orthogonal to u (su = 0) takes none of it
        seen_part = su * su * seen_var if su else np.where(np.isfinite(seen_var), 0.0, np.inf)
        n.append((_diagonal_of_inverse(info) + seen_part / norm0**2)[use])
    if not d:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(d), np.concatenate(p), np.concatenate(n)


def _diagonal_of_inverse(info: np.ndarray) -> np.ndarray:
    """The diagonal ``(C, 3, H, W)`` of the inverse of the information ``(C, 3, 3, H, W)``
    (a Stokes estimate's variances); inf where it is singular."""
    a = np.moveaxis(info, (1, 2), (-2, -1))
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = np.linalg.det(a) > 0
        inv = np.linalg.inv(np.where(ok[..., None, None], a, np.eye(3)))
    diag = np.where(ok[..., None], np.diagonal(inv, axis1=-2, axis2=-1), np.inf)
    return np.moveaxis(diag, -1, 1)


def _usable(d: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Which of :func:`innovations`' values an estimate uses: finite, prior variance > 0."""
    d, p, n = (np.asarray(a, np.float64).ravel() for a in (d, p, n))
    return np.isfinite(d) & np.isfinite(p) & np.isfinite(n) & (p > 0) & (n >= 0)


def innovation_scale(d: np.ndarray, p: np.ndarray, n: np.ndarray, coverage: float = COVERAGE) -> float:
    """The raw scale ``c`` (module docstring) of :func:`innovations`' ``(d, p, n)``: where the
    share of ``|d| <= 2 sqrt(c^2 p + n)`` is ``coverage``, by bisection in ``log c`` within
    :data:`SCALE_LIMITS` (the share grows with ``c``); 1.0 with fewer than
    :data:`MIN_INNOVATIONS` finite values."""
    d, p, n = (np.asarray(a, np.float64).ravel() for a in (d, p, n))
    keep = _usable(d, p, n)
    if np.count_nonzero(keep) < MIN_INNOVATIONS:
        return 1.0
    d2, p, n = (d[keep] / 2.0) ** 2, p[keep], n[keep]
    lo, hi = np.log(SCALE_LIMITS[0]), np.log(SCALE_LIMITS[1])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if np.mean(d2 <= np.exp(2 * mid) * p + n) < coverage:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def prior_scale(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray, valid: np.ndarray | None,
                prior_mean: np.ndarray, prior_sigma: np.ndarray, seen_state: int = 0,
                analyzer_rows: np.ndarray | None = None, shrink: float = SHRINK) -> PriorScale:
    """The :class:`PriorScale` of one image (:func:`scale_of` of its :func:`innovations`;
    factor 1 with one state). Arguments as :func:`innovations`."""
    if np.asarray(s_in).reshape(-1, 3).shape[0] < 2:
        return scale_of(np.zeros(0), np.zeros(0), np.zeros(0), shrink)
    return scale_of(*innovations(s_in, measured, variance, valid, prior_mean, prior_sigma, seen_state,
                                 analyzer_rows), shrink)
