"""Highlights a bracket measured: the single-shot estimate where the network's frame clipped
but a shorter exposure of the same polarizer state did not.

The networks are trained on one exposure (``polrig.sim.dataset``: the sensor clips where it
would), so they see a capture's *reference* exposure as that frame shows it, clipped samples
included. Shown an HDR merge instead (values up to hundreds of times the saturation level
at a metal's highlight), they do worse everywhere: on the held-out conductors set, 64x64, 54
samples, matrix PSNR over the object 30.26 dB from the reference exposure against 23.70 dB
from the merge (unseen compact 41.24 against 37.14; ``benchmarks/results/continuum.md``,
"Highlights").

Where the reference exposure clipped a sample, the network's estimate is bounded by the
clipped intensity: at a specular highlight its ``m00`` is low by up to the factor the
highlight exceeds saturation (measured up to 80 on conductors). When a shorter exposure of
the same state measured the pixel, the merge gives its Stokes vector ``S``; the estimate is
then taken as the network's polarimetric *form* at the measured *intensity*:

    M' = M * S_0 / (M s_in)_0,       per pixel and colour,

the one scalar the clipped frame could not give (an assumption, tested by the result: the
form of a clipped pixel's estimate is kept as the network gave it). Its sigma is the calibrated model's (:meth:`polrig.models.uncertainty.UncertaintyModel.sigma`)
evaluated on ``M'`` with the measured ``S`` (the scale feature then follows the measured
intensity), times :data:`SIGMA_FACTOR`, fitted on the uncertainty calibration's scenes (never
on a reported set) so that 95.45 % of these pixels' elements lie within 2 sigma. Elsewhere
the estimate and sigma are unchanged. A pixel clipped in every exposure stays as it was
(``SATURATED``, no error bound). With ``--network-binning 2`` the networks' grid is not the
measured one, and the highlights keep the network's estimate (that mode has no calibrated sigma
either).

The hybrid solve (:mod:`polrig.solve.hybrid`) takes ``M'`` as its prior where the seen state's
merged samples are used: the part of ``M'`` those samples observe (``M s_in``) is dropped from
the prior as for every pixel, so the frame's intensity enters once as data; the rescale
carries it into the prior's unobserved directions as their scale.
"""

from __future__ import annotations

import numpy as np

#: Sigma multiplier at the rescaled highlights: ``q / 2`` for ``q`` the 95.45 % quantile of
#: ``|M' - M_true| / sigma`` over their elements on the uncertainty calibration's scenes (seed
#: 11: 128 samples of all six families, 64 of the held-out families, 64x64; a bracket of 1,
#: 1/16 and 1/256 of the dataset's exposure; 2754 elements; the version-3 sigma, with its light-spread factor):
#: ``python -m polrig.models.continuum --fit-highlights --count 128``.
SIGMA_FACTOR = 1.40


def measured_highlights(mueller: np.ndarray, s_in, stokes: np.ndarray, clipped: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``(M', rescaled)``: the single-shot estimate ``mueller`` ``(C, 3, 3, H, W)`` rescaled to
    the measured intensity (module docstring) where the network's frame clipped (``clipped``
    ``(C, H, W)``) and the merged Stokes images ``stokes`` ``(C, 3, H, W)`` (same units as the
    estimate renders, e.g. DN) measured it; ``rescaled`` ``(C, H, W)`` says where.

    A pixel is rescaled where ``clipped``, ``stokes`` is finite with ``S_0 > 0`` and the
    estimate renders a finite ``(M s_in)_0 > 0``; elsewhere ``M'`` equals ``mueller``.
    ``s_in``: the incident Stokes vector ``(3,)`` the frame was taken under."""
    m = np.asarray(mueller)
    s = np.asarray(s_in, np.float64).reshape(3)
    rendered = np.einsum("ckhw,k->chw", m[:, 0].astype(np.float64), s)
    measured = np.asarray(stokes, np.float64)[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = measured / rendered
        rescaled = (np.asarray(clipped, bool) & np.isfinite(ratio) & (measured > 0) & (rendered > 0)
                    & np.all(np.isfinite(stokes), axis=1))
    factor = np.where(rescaled, ratio, 1.0)[:, None, None]
    return (m * factor).astype(m.dtype, copy=False), rescaled


def highlight_sigma(sigma: np.ndarray, sigma_rescaled: np.ndarray, rescaled: np.ndarray,
                    factor: float = SIGMA_FACTOR) -> np.ndarray:
    """The estimate's sigma ``(C, 3, 3, H, W)``: ``sigma`` where not ``rescaled`` ``(C, H, W)``,
    ``factor * sigma_rescaled`` (the calibrated model's on the rescaled estimate) where it is."""
    return np.where(np.asarray(rescaled, bool)[:, None, None], factor * np.asarray(sigma_rescaled),
                    np.asarray(sigma)).astype(np.asarray(sigma).dtype, copy=False)
