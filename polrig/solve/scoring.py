"""Scoring a reconstruction against the simulator's truth.

* :func:`truth_on_output_grid` -- the truth Mueller image as a perfect rig at the output
  resolution measures it.
* :func:`score_against_truth` -- error of a result against a truth Mueller image.
* :func:`score_on_output_grid` -- both at once, band by band (a full-sensor colour result is
  scored without a second full-size Mueller image).
* :func:`format_score` -- one line for a score.

Cost: the truth on the output grid is the truth itself wherever the truth is uniform over
the output pixel's demosaic support (the noise-free estimate of a uniform Mueller matrix is
that matrix, whatever the weights: the estimator is linear and exact on its own model), so
only the pixels whose support straddles a change of the truth are demosaiced and solved (no
calibration-uncertainty propagation: the truth needs the estimate alone). On a rendered
object these are its edges and, for a curved surface, every pixel whose neighbours see
another normal; the solve of the rest is skipped.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import cv2
import numpy as np

from polrig.formats.exr import MuellerRows
from polrig.optics.realizability import is_physical_linear
from polrig.sensor.analyzer import AnalyzerModel, LayoutLike, resolve_layout
from polrig.sensor.demosaic import (
    demosaic_float,
    output_shape,
    row_bands,
    support_radius,
)
from polrig.sensor.layouts import MosaicLayout
from polrig.sensor.noise import SensorModel
from polrig.solve.radiometry import BAND_PIXELS, StateRadiance, _demosaic_state
from polrig.solve.reference import MuellerEstimate, ReferenceResult, solve_reference

#: A truth Mueller image ``(C, 3, 3, H, W)``: in memory, or a file read band by band.
Truth = np.ndarray | MuellerRows
#: What a score reads of a result: its estimate (the diagnostics are not needed).
Scored = MuellerEstimate | ReferenceResult

#: Output rows per band of :func:`score_against_truth` over full-size arrays.
SCORE_BAND_ROWS = 64
#: Pixels (times colours) up to which the realizability pass rate tests every compared pixel;
#: a larger result tests every k-th one in scan order, at least half this many (the pass rate's
#: binomial standard error stays below 0.4 %): the eigenvalue search of the test (about 13 us
#: a pixel) would cost more than the rest of the score at full sensor.
REALIZABILITY_SAMPLES = 2 ** 15


# -- truth and score ---------------------------------------------------------------------------
def truth_on_output_grid(truth_mueller: Truth, layout: LayoutLike, method: str,
                         s_in: np.ndarray, weights_like: Sequence[StateRadiance] | None = None,
                         model: SensorModel | None = None, exposure_us: float | None = None,
                         *, band_pixels: int = BAND_PIXELS) -> np.ndarray:
    """The truth as a perfect rig at this resolution measures it: the noise-free estimate
    from the per-pixel truth Mueller image ``(C, 3, 3, H, W)`` (each sensor pixel sees its own
    pixel's matrix, ideal analyzers, incident states ``s_in``), demosaiced with ``method`` and
    solved exactly as a capture is processed. Returns ``(C, 3, 3, H', W')`` float32.

    The weights matter where the truth varies inside a pixel's support (the estimate mixes
    the matrices of the pixels it draws on): ``weights_like`` (the capture's own states) gives
    the sample variances and exclusions to use, so that the result is the expectation of that
    capture's estimator; without it the noise model's variance of the noise-free signal at
    ``exposure_us`` is used. Where the truth is uniform over a pixel's support the result is
    the truth itself, whatever the weights (and it is taken as such, without a solve).
    Computed in bands of about ``band_pixels`` truth pixels (times colours); a
    :class:`polrig.formats.exr.MuellerRows` truth is read band by band.
    """
    t = _as_truth(truth_mueller)
    layout = resolve_layout(layout)
    h, w = t.shape[-2:]
    h_out, w_out = output_shape(layout, (h, w), method)
    out = np.empty(t.shape[:3] + (h_out, w_out), np.float32)
    for o0, o1, _, _, band in _truth_bands(t, layout, method, s_in, weights_like, model,
                                           exposure_us, band_pixels):
        out[..., o0:o1, :] = band
    return out


def _as_truth(truth: Truth) -> Truth:
    return truth if isinstance(truth, MuellerRows) else np.asarray(truth)


def _truth_rows(t: Truth, e0: int, e1: int) -> np.ndarray:
    """Truth rows ``e0:e1``, ``(C, 3, 3, e1 - e0, W)``."""
    return t.rows(e0, e1) if isinstance(t, MuellerRows) else t[..., e0:e1, :]


def _truth_bands(t: Truth, layout: MosaicLayout, method: str, s_in: np.ndarray,
                 weights_like: Sequence[StateRadiance] | None, model: SensorModel | None,
                 exposure_us: float | None, band_pixels: int):
    """Yield ``(o0, o1, e0, e1, truth of output rows o0:o1)`` (``e0:e1``: the truth rows it
    comes from, :func:`polrig.sensor.demosaic.row_bands`; see :func:`truth_on_output_grid`)."""
    if weights_like is None and (model is None or exposure_us is None):
        raise ValueError("give weights_like, or model and exposure_us")
    h, w = t.shape[-2:]
    c = layout.n_colours
    if len(t.shape) != 5 or t.shape[:3] != (c, 3, 3):
        raise ValueError(f"truth must have shape ({c}, 3, 3, H, W) for layout {layout.name}, "
                         f"got {t.shape}")
    s = np.asarray(s_in, dtype=np.float64)
    if weights_like is not None and (len(weights_like) != len(s) or any(
            np.shape(st.variance_dn2) != (h, w) for st in weights_like)):
        raise ValueError(f"weights_like must hold {len(s)} states of shape {(h, w)}")
    # bands of about band_pixels truth pixels (times colours): the truth is full resolution
    rows_in = max(1, int(band_pixels) // max(1, w * c))
    band_rows = max(1, rows_in // layout.period[0]) if method == "superpixel" else rows_in
    for o0, o1, e0, e1 in row_bands(layout, (h, w), method, band_rows):
        a = 0 if method == "superpixel" else o0 - e0
        rows = o1 - o0
        tb = _truth_rows(t, e0, e1)
        uniform, value = _uniform_support(tb, layout, method)
        uniform, value = uniform[..., a:a + rows, :], value[..., a:a + rows, :]
        band = value.astype(np.float32)
        todo = ~uniform.all(axis=0)  # (rows, W'): solved, for every colour at once
        if todo.any():
            est = _noise_free_estimate(tb, layout, method, s,
                                       weights_like, model, exposure_us, e0, e1, a, rows, todo)
            band[..., todo] = np.where(uniform[:, None, None][..., todo], band[..., todo], est)
        yield o0, o1, e0, e1, band


def _uniform_support(t: np.ndarray, layout: MosaicLayout, method: str
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``(uniform, value)`` of a truth band ``(C, 3, 3, h, W)``: ``uniform`` ``(C, h', W')``
    where all 9 elements of colour ``c`` are the same finite numbers over the output pixel's
    demosaic support (:func:`polrig.sensor.demosaic.support_radius`), and ``value`` ``(C, 3, 3, h',
    W')`` the truth there (the cell's first pixel for ``superpixel``).

    Per plane a max and a min filter over the support (OpenCV morphology); ``superpixel``
    takes them over the cell (kernel anchored at its top-left pixel) at every cell origin."""
    c = t.shape[0]
    if method == "superpixel":
        ph, pw = layout.period
        hh, ww = t.shape[-2] // ph, t.shape[-1] // pw
        kernel, anchor = np.ones((ph, pw), np.uint8), (0, 0)
        pick = (slice(0, hh * ph, ph), slice(0, ww * pw, pw))
    else:
        ry, rx = support_radius(layout, method)
        kernel, anchor = np.ones((2 * ry + 1, 2 * rx + 1), np.uint8), (rx, ry)
        pick = (slice(None), slice(None))
    uniform = None
    for ci in range(c):
        flat = None
        for i in range(3):
            for j in range(3):
                p = t[ci, i, j]
                if p.dtype not in (np.float32, np.float64):
                    p = p.astype(np.float64)
                same = _flat(p, kernel, anchor)[pick]
                flat = same if flat is None else flat & same
        if uniform is None:
            uniform = np.empty((c,) + flat.shape, bool)
        uniform[ci] = flat
    return uniform, t[(Ellipsis,) + pick]


def _flat(p: np.ndarray, kernel: np.ndarray, anchor: tuple[int, int]) -> np.ndarray:
    """Where plane ``p`` holds one finite value over the ``kernel`` window (bool)."""
    finite = np.isfinite(p)
    ok = None
    if not finite.all():  # a non-finite pixel spoils its neighbourhood
        ok = cv2.erode(finite.view(np.uint8), kernel, anchor=anchor,
                       borderType=cv2.BORDER_REPLICATE).astype(bool)
        p = np.where(finite, p, 0).astype(p.dtype)
    hi = cv2.dilate(p, kernel, anchor=anchor, borderType=cv2.BORDER_REPLICATE)
    lo = cv2.erode(p, kernel, anchor=anchor, borderType=cv2.BORDER_REPLICATE)
    same = hi == lo
    return same if ok is None else same & ok


def _noise_free_estimate(t: np.ndarray, layout: MosaicLayout, method: str, s: np.ndarray,
                         weights_like, model, exposure_us, e0: int, e1: int, a: int, rows: int,
                         todo: np.ndarray) -> np.ndarray:
    """The solve of the noise-free mosaics of truth rows ``e0:e1`` (``t``) at the output
    pixels ``todo`` ``(rows, W')`` of output rows ``a:a + rows`` of the band: ``(C, 3, 3, n)``."""
    shape = t.shape[-2:]
    # each sensor pixel's own colour's matrix, and the ideal analyzer rows (a band starts at
    # the layout's phase: the rows are the cell's, tiled), as AnalyzerModel.mosaic has them
    ph, pw = layout.period
    if layout.n_colours == 1:
        own = t[0]
    else:
        own = np.empty(t.shape[1:], t.dtype)
        for r in range(ph):
            for q in range(pw):
                own[..., r::ph, q::pw] = t[layout.colour[r, q], ..., r::ph, q::pw]
    cell = AnalyzerModel.ideal(layout, (ph, pw)).rows()
    r = np.tile(cell, (-(-shape[0] // ph), -(-shape[1] // pw), 1))[:shape[0], :shape[1]]
    parts = []
    for k, sk in enumerate(s):  # float64 s: the mosaic in float64 whatever the truth's dtype
        st = np.einsum("ijhw,j->ihw", own, sk)
        mosaic = r[..., 0] * st[0] + r[..., 1] * st[1] + r[..., 2] * st[2]
        if weights_like is not None:
            like = weights_like[k]
            var, excl = like.variance_dn2[e0:e1], like.excluded[e0:e1]
        else:
            var, excl = model.variance_dn2(mosaic, exposure_us), np.zeros(mosaic.shape, bool)
        m, v, ok = _demosaic_state(mosaic, var, excl, layout, method)
        parts.append([p[:, :, a:a + rows][:, :, todo] for p in (m, v, ok)])
    meas, var, valid = (np.stack([p[i] for p in parts])[..., None, :] for i in range(3))
    return solve_reference(s, meas, var, valid).mueller[:, :, :, 0]


def score_on_output_grid(result: Scored, truth_mueller: Truth,
                         layout: LayoutLike, method: str, s_in: np.ndarray,
                         weights_like: Sequence[StateRadiance] | None = None,
                         model: SensorModel | None = None, exposure_us: float | None = None,
                         object_mask: np.ndarray | None = None, *,
                         band_pixels: int = BAND_PIXELS) -> dict[str, Any]:
    """:func:`score_against_truth` of ``result`` against :func:`truth_on_output_grid` of the
    full-resolution ``truth_mueller``, band by band (same numbers up to the summation order,
    without the full-size truth on the output grid, and, for a
    :class:`polrig.formats.exr.MuellerRows` truth, without the whole truth in memory).

    ``object_mask`` ``(H, W)`` (full resolution, e.g. the simulator's): the output pixels whose
    whole demosaic support lies on the object are compared.
    """
    t = _as_truth(truth_mueller)
    layout = resolve_layout(layout)
    h, w = t.shape[-2:]
    expect = (layout.n_colours, 3, 3) + output_shape(layout, (h, w), method)
    if np.shape(result.mueller) != expect:
        raise ValueError(f"result {np.shape(result.mueller)} and truth on the output grid "
                         f"{expect} differ in shape")
    obj_full = None if object_mask is None else np.asarray(object_mask, np.float32)
    if obj_full is not None and obj_full.shape != (h, w):
        raise ValueError(f"object mask {obj_full.shape} differs from the truth {(h, w)}")
    sums = _ScoreSums(_realizability_stride(result))
    for o0, o1, e0, e1, band in _truth_bands(t, layout, method, s_in, weights_like, model,
                                             exposure_us, band_pixels):
        obj = None
        if obj_full is not None:
            a = 0 if method == "superpixel" else o0 - e0
            support = demosaic_float(obj_full[e0:e1], layout, method)[..., a:a + o1 - o0, :]
            obj = support.min(axis=(0, 1)) >= 1.0
        sums.add(_rows(result, o0, o1), band, obj)
    return sums.score(result)


def _rows(result: Scored, o0: int, o1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mueller, sigma, valid)`` of output rows ``o0:o1``."""
    return (result.mueller[..., o0:o1, :], result.sigma[..., o0:o1, :],
            result.mask[..., o0:o1, :] == 0)


def _realizability_stride(result: Scored) -> int:
    """Every how many compared pixels the realizability test runs: all of them up to
    :data:`REALIZABILITY_SAMPLES` output pixels, a regular subsample beyond."""
    return max(1, -(-int(np.size(result.mask)) // REALIZABILITY_SAMPLES))


class _ScoreSums:
    """Running sums of :func:`score_against_truth` over bands of rows; the realizability
    test runs on every ``stride``-th compared pixel in scan order."""

    def __init__(self, stride: int = 1) -> None:
        self.stride = max(1, int(stride))
        self.n_tested = 0
        self.n = 0
        self.n_elem_pos = 0
        self.sq = self.ab = self.sig2 = self.chi2 = 0.0
        self.within = self.realizable = 0
        self.peak = 0.0

    def add(self, rows: tuple[np.ndarray, np.ndarray, np.ndarray], truth: np.ndarray,
            object_mask: np.ndarray | None) -> None:

        m_rows, s_rows, valid = rows
        use = valid.copy()
        if object_mask is not None:
            use &= np.asarray(object_mask, bool)[None]
        n = int(use.sum())
        if n == 0:
            return
        m = np.asarray(m_rows).transpose(1, 2, 0, 3, 4)[:, :, use].astype(np.float64)  # (3, 3, n)
        t = np.asarray(truth).transpose(1, 2, 0, 3, 4)[:, :, use].astype(np.float64)
        sig = np.asarray(s_rows).transpose(1, 2, 0, 3, 4)[:, :, use].astype(np.float64)
        err = m - t
        pos = sig > 0
        self.n += n
        self.sq += float(np.sum(err ** 2))
        self.ab += float(np.sum(np.abs(err)))
        self.peak = max(self.peak, float(np.abs(t[0, 0]).max()))
        self.sig2 += float(np.sum(sig ** 2))
        self.n_elem_pos += int(pos.sum())
        self.within += int(np.count_nonzero(np.abs(err[pos]) <= 2 * sig[pos]))
        self.chi2 += float(np.sum((err[pos] / sig[pos]) ** 2))
        pick = (self.n - n + np.arange(n)) % self.stride == 0  # global scan-order stride
        self.n_tested += int(pick.sum())
        self.realizable += int(np.count_nonzero(is_physical_linear(m[:, :, pick].transpose(2, 0, 1))))

    def score(self, result: Scored) -> dict[str, Any]:
        out: dict[str, Any] = {"pixels_compared": self.n,
                               "pixels_valid": int(np.count_nonzero(result.mask == 0)),
                               "pixels_total": int(result.mask.size),
                               "mask_counts": result.reason_counts(),
                               "condition_number": (float(result.condition_number)
                                                    if math.isfinite(result.condition_number)
                                                    else None)}
        keys = ("rmse", "mae", "psnr_db", "within_2sigma", "chi2_per_element", "mean_sigma",
                "peak_m00", "realizable")
        out.update({k: None for k in keys})
        if self.n == 0:
            return out
        n_elem = 9 * self.n
        rmse = math.sqrt(self.sq / n_elem)
        pos = self.n_elem_pos > 0
        out.update(
            rmse=rmse, mae=self.ab / n_elem, psnr_db=_psnr_db(self.peak, rmse),
            within_2sigma=self.within / self.n_elem_pos if pos else None,
            chi2_per_element=self.chi2 / self.n_elem_pos if pos else None,
            mean_sigma=math.sqrt(self.sig2 / n_elem) if pos else None, peak_m00=self.peak,
            realizable=self.realizable / self.n_tested)
        return out


def score_against_truth(result: Scored, truth: np.ndarray,
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
    (:func:`polrig.optics.realizability.is_physical_linear`) of the measured matrices (of every k-th
    compared pixel in scan order when the result has more than :data:`REALIZABILITY_SAMPLES`
    pixels).

    Accumulated over bands of :data:`SCORE_BAND_ROWS` rows in float64 (no full-size float64
    copies).
    """
    m = result.mueller
    if np.shape(m) != np.shape(truth):
        raise ValueError(f"result {np.shape(m)} and truth {np.shape(truth)} differ in shape")
    obj = None if object_mask is None else np.asarray(object_mask, bool)
    sums = _ScoreSums(_realizability_stride(result))
    h = np.shape(m)[-2]
    for o0 in range(0, h, SCORE_BAND_ROWS):
        o1 = min(h, o0 + SCORE_BAND_ROWS)
        sums.add(_rows(result, o0, o1), np.asarray(truth)[..., o0:o1, :],
                 None if obj is None else obj[o0:o1])
    return sums.score(result)


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
