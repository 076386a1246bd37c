"""The network prior's scale along the direction two states leave open, from the diffuse term's
geometry.

Two polarizer states observe each row ``m_r`` of the 3x3 block in their plane; along
``w = s_a x s_b / |.|`` the hybrid's posterior is the network prior's
(:func:`polrig.solve.hybrid.open_direction`). The states' own check of the prior, the
innovations' scale (:mod:`polrig.solve.prior_scale`), sees only the directions they observe, and
where the network errs more along ``w`` than there, the two-state posterior's sigma is too
small: on the simulated rig's ``plane`` and its plastic + metal scene 91.2 and 90.1 % of the
elements within 2 sigma, the misses in ``m01``, ``m02`` (``docs/continuum.md``, "Against issue
33's acceptance, line by line").

Where the pixel is Baek's diffuse term (with his specular term where significant), the rig's
geometry predicts ``m_r . w`` without the network: the diffuse test on the two states' samples
alone accepts or not, and the completion (:func:`polrig.solve.diffuse_test.complete_tested_diffuse`)
fits each accepted pixel's normal and the image's refractive index to the samples. Here it is
fitted *without* the network's normals as its first guess (``normal_guess=None``): with them,
on rig scenes whose normals the network gets wrong (``box``, ``heightfield``), the completion
leaned on the prior it is to check. The difference of completion and hybrid along ``w``,

    d_r = (m_completed,r - m_hybrid,r) . w,    var d_r ~ f^2 V_r,

against the hybrid's posterior variance ``V_r`` of ``m_r . w`` (:func:`open_variance`: the
samples' normal matrix and the solve's prior precision, per pixel) gives the scale ``f`` at which
95.45 % of the ``|d|`` lie within ``2 f sqrt(V)`` (:func:`polrig.solve.prior_scale.innovation_scale`,
the same quantile rule as the innovations', no noise term: the completion's own error is part of
``d`` and makes ``f`` err wide). The hybrid is then solved again with the prior's standard
deviation along ``w`` times ``max(f, 1) ** EXPONENT`` (``solve_hybrid(open_factor=...)``), where
:data:`EXPONENT` takes the estimate partly, as fitted on the calibration scenes
(:mod:`polrig.models.coverage_diagnosis`, "A what-if of the open direction's scale").

**It widens, never narrows.** The completion and the network's estimate are made from the same
two frames, and the network learned the diffuse term's physics: where they agree, both may be
off together, and their agreement shows less than their disagreement does. Measured
(``coverage_diagnosis``, the solve with the factor at ``f ** 0.75``, 2026-11-30): on the
samples where ``f < 1`` narrowing lowered the matrix PSNR on average on every set, by 0.03 to
1.4 dB (one terrain sample 4.6 dB, the rig's ``plane`` at 60 deg 2.8 dB), while on those where
``f > 1`` widening raised it (by up to 0.46 dB on the conductors). With the floor no set's mean
PSNR falls by more than 0.02 dB, and the exponent fitted on the calibration scenes is the same.

Where fewer than :data:`polrig.solve.prior_scale.MIN_INNOVATIONS` values are accepted (a scene
with no diffuse pixel, or no geometry), the factor is 1 and the record says so.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from polrig.solve.diffuse_geometry import DiffuseGeometry
from polrig.solve.diffuse_test import complete_tested_diffuse
from polrig.solve.hybrid import open_direction
from polrig.solve.model_selection import normal_equations, prior_precision
from polrig.solve.prior_scale import MIN_INNOVATIONS, innovation_scale
from polrig.solve.reference import ReferenceResult

__all__ = ["EXPONENT", "OpenScale", "open_values", "open_variance", "open_scale_of"]

#: Exponent of the raw estimate taken for the factor, ``f ** EXPONENT`` (module docstring):
#: the grid value (0, 0.25, ..., 1.25) whose calibration-scene samples' coverage at two states
#: 0/90 lies nearest 95.45 % in the mean square (``python -m polrig.models.coverage_diagnosis
#: --count 64``, the shipped network and sigma).
EXPONENT = 0.75


@dataclasses.dataclass(frozen=True)
class OpenScale:
    """The factor ``factor`` on the prior's standard deviation along the open direction, the raw
    estimate ``raw`` (``f``), the ``exponent`` it was taken to and the number of accepted
    ``values`` it rests on (0: none, factor 1)."""

    factor: float
    raw: float
    exponent: float
    values: int

    @classmethod
    def none(cls) -> "OpenScale":
        """No estimate: factor 1."""
        return cls(1.0, 1.0, 0.0, 0)

    def record(self) -> dict[str, Any]:
        """The manifest's and the EXR header's record (``open_direction`` of the prior scale's)."""
        return dataclasses.asdict(self)


def open_variance(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray, valid: np.ndarray | None,
                  analyzer_rows, prior_sigma: np.ndarray, seen_state: int, correlation: np.ndarray | None,
                  where: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The hybrid's posterior variance of each row along the unit ``w`` ``(C, 3, H, W)``, at the
    colour-pixels ``where`` ``(C, H, W)`` (0 elsewhere and where the system is singular or a
    prior sigma is not finite and positive): the inverse of ``N + P`` per pixel, ``N`` the samples'
    normal matrix (:func:`polrig.solve.model_selection.normal_equations`) and ``P`` the solve's
    prior precision (:func:`polrig.solve.model_selection.prior_precision`, joint with
    ``correlation``); arguments as :func:`polrig.solve.hybrid.solve_hybrid` takes them."""
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    n_col, h, wd = np.shape(where)
    out = np.zeros((n_col, 3, h, wd))
    sd_all = np.broadcast_to(np.asarray(prior_sigma), (n_col, 3, 3, h, wd))
    e = np.zeros((3, 9))
    for r in range(3):
        e[r, 3 * r:3 * r + 3] = w
    for c in range(n_col):
        pix = np.flatnonzero(np.asarray(where[c]).ravel())
        sd = np.asarray(sd_all[c], np.float64).reshape(9, -1)[:, pix].T  # (P, 9)
        ok = np.all(np.isfinite(sd) & (sd > 0), axis=1)
        if not ok.any():
            continue
        pix = pix[ok]
        total = normal_equations(s, measured, variance, valid, analyzer_rows, c, pix)[0] \
            + prior_precision(sd[ok], s[seen_state], correlation)
        regular = np.linalg.slogdet(total)[0] > 0
        cov = np.linalg.inv(np.where(regular[:, None, None], total, np.eye(9)))
        flat = out[c].reshape(3, -1)
        flat[:, pix] = np.where(regular, np.einsum("ri,pij,rj->rp", e, cov, e), 0.0)
    return out


def open_values(result: ReferenceResult, s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                valid: np.ndarray | None, geometry: DiffuseGeometry, *, prior_mean: np.ndarray,
                prior_sigma: np.ndarray, seen_state: int, prior_correlation: np.ndarray | None = None,
                mask: np.ndarray | None = None, analyzer_rows=None) -> tuple[np.ndarray, np.ndarray]:
    """The differences ``d`` of the completion from the two-state hybrid ``result`` along the open
    direction and their posterior variances ``V`` (module docstring), 1-D over the completed
    colour-pixels x rows with ``V > 0``, in the units of ``measured``. ``geometry``'s normals are
    not used (the completion's first guess is none); ``mask`` ``(H, W)``: the pixels to test (the
    network's object); the other arguments as :func:`polrig.solve.hybrid.solve_hybrid` took them
    for ``result``."""
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    w = open_direction(s)
    blind = dataclasses.replace(geometry, normal_guess=None)
    out, _, completed = complete_tested_diffuse(
        result, s, measured, variance, valid, blind, prior=(prior_mean, prior_sigma), seen_state=seen_state,
        prior_correlation=prior_correlation, mask=mask, analyzer_rows=analyzer_rows, specular=True)
    v = open_variance(s, measured, variance, valid, analyzer_rows, prior_sigma, seen_state, prior_correlation,
                      completed, w)
    d = np.einsum("crkhw,k->crhw", out.mueller.astype(np.float64) - result.mueller.astype(np.float64), w)
    use = completed[:, None] & (v > 0) & np.isfinite(d)
    return d[use], v[use]


def open_scale_of(d: np.ndarray, v: np.ndarray, exponent: float = EXPONENT) -> OpenScale:
    """The :class:`OpenScale` of :func:`open_values`' ``(d, v)`` (pooled over bands or images):
    :func:`polrig.solve.prior_scale.innovation_scale` ``f``, the factor ``max(f, 1) ** exponent``
    (module docstring, "It widens, never narrows"); factor 1 with fewer than
    :data:`polrig.solve.prior_scale.MIN_INNOVATIONS` values."""
    d, v = np.asarray(d, np.float64).ravel(), np.asarray(v, np.float64).ravel()
    n = int(np.count_nonzero(np.isfinite(d) & np.isfinite(v) & (v > 0)))
    if n < MIN_INNOVATIONS:
        return OpenScale(1.0, 1.0, float(exponent), n)
    raw = innovation_scale(d, v, np.zeros_like(v))
    return OpenScale(float(max(raw, 1.0) ** float(exponent)), raw, float(exponent), n)
