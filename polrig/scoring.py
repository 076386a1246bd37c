"""Scoring a reconstruction against the simulator's truth.

* :func:`truth_on_output_grid` -- the truth Mueller image as a perfect rig at the output
  resolution measures it.
* :func:`score_against_truth` -- error of a result against a truth Mueller image.
* :func:`format_score` -- one line for a score.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from polrig.analyzer import AnalyzerModel
from polrig.layouts import MosaicLayout
from polrig.noise import SensorModel
from polrig.radiometry import StateRadiance, reference_from_frames
from polrig.reference import ReferenceResult


# -- truth and score ---------------------------------------------------------------------------
def truth_on_output_grid(truth_mueller: np.ndarray, layout: MosaicLayout, method: str,
                         s_in: np.ndarray, weights_like: Sequence[StateRadiance] | None = None,
                         model: SensorModel | None = None, exposure_us: float | None = None
                         ) -> np.ndarray:
    """The truth as a perfect rig at this resolution measures it: the noise-free estimate
    from the per-pixel truth Mueller image ``(C, 3, 3, H, W)`` (each sensor pixel sees its own
    pixel's matrix, ideal analyzers, incident states ``s_in``), demosaiced with ``method`` and
    solved exactly as a capture is processed. Returns ``(C, 3, 3, H', W')``.

    The weights matter where the truth varies inside a pixel's support (the estimate mixes
    the matrices of the pixels it draws on): ``weights_like`` (the capture's own states) gives
    the sample variances and exclusions to use, so that the result is the expectation of that
    capture's estimator; without it the noise model's variance of the noise-free signal at
    ``exposure_us`` is used. Where the truth is uniform over a pixel's support the result is
    the truth itself, whatever the weights.
    """
    t = np.asarray(truth_mueller, dtype=np.float64)
    h, w = t.shape[-2:]
    ideal = AnalyzerModel.ideal(layout, (h, w))
    states = []
    for k, s in enumerate(np.asarray(s_in, dtype=np.float64)):
        mosaic = ideal.mosaic(np.einsum("cijhw,j->cihw", t, s))
        if weights_like is not None:
            like = weights_like[k]
            states.append(StateRadiance(mosaic, like.variance_dn2, like.excluded))
        else:
            if model is None or exposure_us is None:
                raise ValueError("give weights_like, or model and exposure_us")
            states.append(StateRadiance(mosaic, model.variance_dn2(mosaic, exposure_us),
                                        np.zeros(mosaic.shape, bool)))
    return reference_from_frames(states, s_in, layout, method).mueller


def score_against_truth(result: ReferenceResult, truth: np.ndarray,
                        object_mask: np.ndarray | None = None) -> dict[str, Any]:
    """Error of ``result`` against ``truth`` ``(C, 3, 3, H, W)`` on the same grid (normally
    :func:`truth_on_output_grid`) over the pixels valid in the result (mask 0) and inside
    ``object_mask`` ``(H, W)`` if given.

    ``rmse``/``mae`` (DN per unit S0) over the 9 elements; ``psnr_db`` = 20 log10(peak / rmse)
    with ``peak`` the largest truth ``m00`` compared (``|m_ij| <= m00`` for a physical matrix:
    the matrix PSNR in the units of the data; ``inf`` for an exact result, ``None`` where the
    truth is dark over every compared pixel, e.g. an object turned so that only its unlit back
    faces the camera: the PSNR has no peak then, and ``rmse`` still says how far from 0 the
    result is); ``within_2sigma``: fraction of elements with
    ``|error| <= 2 sigma`` (0.954 for Gaussian errors when sigma is right);
    ``chi2_per_element``: mean ``(error / sigma)^2`` (1 when sigma is right); ``mean_sigma``:
    root-mean-square reported sigma (noise and calibration), the predicted error (comparable with
    ``rmse``); ``realizable``: pass rate of the coherency test
    (:func:`polrig.realizability.is_physical_linear`) of the measured matrices.
    """
    from polrig.realizability import is_physical_linear

    m = np.asarray(result.mueller, np.float64)
    s = np.asarray(result.sigma, np.float64)
    t = np.asarray(truth, np.float64)
    if m.shape != t.shape:
        raise ValueError(f"result {m.shape} and truth {t.shape} differ in shape")
    use = result.valid.copy()
    if object_mask is not None:
        use &= np.asarray(object_mask, bool)[None]
    n = int(use.sum())
    out: dict[str, Any] = {"pixels_compared": n,
                           "pixels_valid": int(result.valid.sum()),
                           "pixels_total": int(result.valid.size),
                           "mask_counts": result.reason_counts(),
                           "condition_number": (float(result.condition_number)
                                                if math.isfinite(result.condition_number)
                                                else None)}
    keys = ("rmse", "mae", "psnr_db", "within_2sigma", "chi2_per_element", "mean_sigma",
            "peak_m00", "realizable")
    out.update({k: None for k in keys})
    if n == 0:
        return out
    err = (m - t).transpose(1, 2, 0, 3, 4)[:, :, use]  # (3, 3, n)
    sig = s.transpose(1, 2, 0, 3, 4)[:, :, use]
    peak = float(np.abs(t[:, 0, 0][use]).max())
    rmse = float(np.sqrt(np.mean(err**2)))
    pos = sig > 0
    mats = m.transpose(0, 3, 4, 1, 2)[use]  # (n, 3, 3)
    out.update(
        rmse=rmse, mae=float(np.mean(np.abs(err))),
        psnr_db=_psnr_db(peak, rmse),
        within_2sigma=float(np.mean(np.abs(err[pos]) <= 2 * sig[pos])) if pos.any() else None,
        chi2_per_element=float(np.mean((err[pos] / sig[pos]) ** 2)) if pos.any() else None,
        mean_sigma=float(np.sqrt(np.mean(sig**2))) if pos.any() else None, peak_m00=peak,
        realizable=float(np.mean(is_physical_linear(mats))))
    return out


def _psnr_db(peak: float, rmse: float) -> float | None:
    """``20 log10(peak / rmse)``; ``inf`` when ``rmse`` is 0, ``None`` when ``peak`` is 0."""
    if peak <= 0.0:
        return None
    return float(20 * math.log10(peak / rmse)) if rmse > 0 else float("inf")


def format_score(score: dict[str, Any]) -> str:
    """One line for a score dict (``polrig capture`` and ``polrig info``)."""
    if not score or score.get("rmse") is None:
        return "no pixels to score"
    psnr = score["psnr_db"]
    parts = [f"RMSE {score['rmse']:.4g}", f"MAE {score['mae']:.4g}",
             "PSNR n/a (dark truth)" if psnr is None else f"PSNR {psnr:.1f} dB" if math.isfinite(psnr) else "PSNR inf"]
    if score.get("mean_sigma") is not None:
        parts.append(f"mean sigma {score['mean_sigma']:.4g}")
    if score.get("within_2sigma") is not None:
        parts.append(f"{100 * score['within_2sigma']:.1f}% within 2 sigma")
    parts.append(f"realizable {100 * score['realizable']:.1f}%")
    parts.append(f"{score['pixels_compared']} px")
    return ", ".join(parts)
