"""Pure radiometry of the reference capture: raw frames of each polarizer state -> radiance
mosaics with variance and exclusions -> demosaiced analyzer images -> the reference solve.

* :func:`adc_scale` -- DN of delivered frames -> DN of the ADC the noise model describes.
* :func:`state_radiance` -- K frames (and an exposure bracket) of one polarizer state ->
  black/dark-subtracted mean mosaic in DN at the reference exposure, its variance from the
  sensor noise model, and the samples to exclude (saturated).
* :func:`analyzer_stack` -- demosaic mosaics, variances and exclusions into analyzer images
  ``(C, 4, H', W')``.
* :func:`reference_from_frames` -- all states -> :class:`polrig.solve.reference.ReferenceResult`
  (with a prior from the single-shot network: the hybrid solve, :mod:`polrig.solve.hybrid`).

Uncertainty propagation: per raw sample the model variance
(:meth:`polrig.sensor.noise.SensorModel.variance_dn2` at the measured mean signal, divided by K;
plus the variance of the subtracted dark mean), HDR-merged by :func:`polrig.solve.reference.merge_hdr`;
the ``superpixel`` demosaic averages ``n`` same-class pixels, so the variance is the mean
variance divided by ``n`` (exact); interpolating demosaics get the interpolated variance
(an approximation: it ignores the correlation the interpolation creates).

Memory and precision (full sensor, 2448x2048): every step works in row bands.
:func:`state_radiance` computes in float64 band by band and stores float32 (the demosaic works
in float32 anyway); :func:`reference_from_frames` demosaics each band of output rows from the
mosaic rows it needs (:func:`polrig.sensor.demosaic.row_bands`, halo per method) and solves it, so the
working set is a few tens of MB whatever the frame size, and the result is the same as one
solve of the whole image (bit-identical, ``tests/test_radiometry_tiled.py``). The result's
uncertainty planes may be kept in half precision (``uncertainty_dtype``).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import threading
from typing import Sequence

import numpy as np

from polrig.sensor.analyzer import AnalyzerModel, resolve_layout
from polrig.sensor.demosaic import (
    class_positions,
    demosaic_float,
    output_shape,
    row_bands,
)
from polrig.sensor.layouts import MosaicLayout
from polrig.sensor.noise import SensorModel
from polrig.solve.diffuse_geometry import DiffuseGeometry, geometry_rows
from polrig.solve.hybrid import solve_hybrid
from polrig.solve.model_selection import ModelMaps, SelectionOptions, select_models
from polrig.solve.open_scale import OpenScale, open_scale_of, open_values
from polrig.solve.prior_scale import PriorScale, innovations, scale_of
from polrig.solve.reference import ReferenceResult, merge_hdr, solve_reference


def adc_scale(model: SensorModel, bit_depth: int) -> float:
    """Factor from the DN of frames delivered with ``bit_depth`` bits to the DN of the ADC the
    noise model describes (a 12-bit ADC read out as Mono16 delivers values times 16: the
    factor is 1/16). Results are always in ADC DN, whatever the pixel format."""
    return 2.0 ** (int(model.bit_depth) - int(bit_depth))


# -- array level -------------------------------------------------------------------------------
#: Output pixels (times colours) per band of :func:`reference_from_frames` (2^18: 32 rows of a
#: full-resolution colour 2448-wide frame; about 35 MB of solve input for 4 states).
BAND_PIXELS = 2 ** 18
#: Raw rows per band of :func:`state_radiance` (its float64 temporaries stay small).
STATE_BAND_ROWS = 256
#: Default band threads of :func:`reference_from_frames` (the CPU count, at most 4: the
#: demosaic and the solve release the GIL; memory grows by one band per thread).
WORKERS = min(4, os.cpu_count() or 1)
_SOLVE_LOCK = threading.Lock()
#: Dtypes the uncertainty planes (``sigma``, ``sigma_noise``, ``residual``) may be kept in.
UNCERTAINTY_DTYPES = (np.float32, np.float16)


@dataclasses.dataclass(frozen=True)
class StateRadiance:
    """One state's mosaic ``(H, W)``: ``signal_dn`` (black/dark-subtracted, at the reference
    exposure), ``variance_dn2`` and ``excluded`` (bool, saturated in every exposure).
    :func:`state_radiance` gives float32 signal and variance; any float dtype is accepted.

    ``clipped_reference`` (bool): saturated at the reference exposure (what its frame alone
    shows; the single-shot networks see that, :meth:`polrig.app.single_shot.SingleShot.state`);
    ``None`` means the same as ``excluded`` (one exposure)."""

    signal_dn: np.ndarray
    variance_dn2: np.ndarray
    excluded: np.ndarray
    clipped_reference: np.ndarray | None = None

    def reference_exclusions(self) -> np.ndarray:
        """The samples the reference exposure's frame clipped (``excluded`` without a bracket)."""
        return self.excluded if self.clipped_reference is None else self.clipped_reference


def state_radiance(brackets: Sequence[Sequence[np.ndarray]], exposures_us: Sequence[float],
                   model: SensorModel, *, black_level_dn: float = 0.0,
                   darks: Sequence[Sequence[np.ndarray]] | None = None,
                   code_step_dn: float = 1.0,
                   band_rows: int = STATE_BAND_ROWS) -> StateRadiance:
    """Mean black-subtracted mosaic of one polarizer state.

    ``brackets[e]``: the K raw frames ``(H, W)`` taken at ``exposures_us[e]``; ``darks[e]``:
    dark frames at that exposure (light off) or ``None``/empty (subtract ``black_level_dn``
    only). A sample is excluded when any of its frames reaches the saturation level
    (``black + model.saturation_dn``); several exposures are merged by
    :func:`polrig.solve.reference.merge_hdr` at ``exposures_us[0]`` (the reference exposure).

    ``code_step_dn``: ADC DN per code of the delivered frames (:func:`adc_scale`; 16 for
    Mono8 from a 12-bit ADC). A frame with fewer bits than the ADC clips at its own top code,
    ``(2**bits - 1) * step = 2**adc_bits - step`` DN (4080 for Mono8), which is below the
    ADC's saturation threshold: samples there are saturated too. Its coarser codes add
    rounding variance: ``step**2 / 12`` in all, ``(step**2 - 1) / 12`` beyond the ADC's own
    ``1/12`` the noise model holds (per frame; not carried into an HDR merge, which takes
    the model's variance).

    Computed in float64, ``band_rows`` raw rows at a time (every step is per pixel, so the
    bands change nothing), stored as float32 signal and variance.
    """
    if len(brackets) != len(exposures_us) or not brackets:
        raise ValueError("one list of frames per exposure is needed")
    frames = [[np.asarray(f) for f in lst] for lst in brackets]
    dark_frames = ([[np.asarray(d) for d in (lst or ())] for lst in darks] if darks else None)
    shapes = {f.shape for lst in frames + (dark_frames or []) for f in lst}
    if not frames[0] or len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"frames of one state must be 2-D and of one shape, got "
                         f"{sorted(shapes)}")
    h, w = next(iter(shapes))
    signal = np.empty((h, w), np.float32)
    variance = np.empty((h, w), np.float32)
    excluded = np.empty((h, w), bool)
    clipped = np.empty((h, w), bool) if len(frames) > 1 else None
    step = max(1, int(band_rows))
    for r0 in range(0, h, step):
        sl = slice(r0, min(h, r0 + step))
        s, v, x, c = _state_radiance_rows(
            [[f[sl] for f in lst] for lst in frames], exposures_us, model, black_level_dn,
            None if dark_frames is None else [[d[sl] for d in lst] for lst in dark_frames],
            float(code_step_dn))
        signal[sl], variance[sl], excluded[sl] = s, v, x
        if clipped is not None:
            clipped[sl] = c
    return StateRadiance(signal, variance, excluded, clipped)


def _state_radiance_rows(brackets, exposures_us, model: SensorModel, black_level_dn: float,
                         darks, step: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`state_radiance` of some rows, float64 ``(signal, variance, excluded,
    clipped_reference)``."""
    sat_raw = min(black_level_dn + model.saturation_dn, model.max_code_dn + 1.0 - step)
    requantization = max(step * step - 1.0, 0.0) / 12.0
    means, variances, sats = [], [], []
    for e, frames in enumerate(brackets):
        f = np.asarray(frames, dtype=np.float64)
        k = f.shape[0]
        mean = f.mean(axis=0)
        sat = (f >= sat_raw).any(axis=0)
        dark_list = darks[e] if darks else None
        if dark_list is not None and len(dark_list):
            d = np.asarray(dark_list, dtype=np.float64)
            offset = d.mean(axis=0)
            dark_var = model.variance_dn2(0.0, exposures_us[e], d.shape[0])
            signal = mean - offset
            # the dark mean already holds the mean dark signal: the photo-signal is what is left
            var = (model.variance_dn2(signal, exposures_us[e], k) + dark_var
                   + requantization / k + requantization / d.shape[0])
        else:
            dark_dn = model.dark_electrons(exposures_us[e]) / model.gain_e_per_dn
            signal = mean - black_level_dn - dark_dn
            var = model.variance_dn2(signal, exposures_us[e], k) + requantization / k
        means.append(signal)
        variances.append(var)
        sats.append(sat)
    if len(brackets) == 1:
        return means[0], variances[0], sats[0], sats[0]
    # merge_hdr excludes samples >= saturation_dn: mark the saturated ones that way
    marked = [np.where(s, np.inf, m) for m, s in zip(means, sats)]
    radiance, variance, valid = merge_hdr(list(zip(marked, exposures_us)), model.saturation_dn,
                                          model, reference_exposure_us=exposures_us[0],
                                          n_frames=len(brackets[0]))
    return radiance, variance, ~valid, sats[0]


def _superpixel_counts(layout: MosaicLayout) -> np.ndarray:
    """``(C, 4, 1, 1)`` float32: pixels per cell of each (colour, analyzer) class."""
    counts = np.zeros((layout.n_colours, 4), np.float32)
    for (c, k), pos in class_positions(layout).items():
        counts[c, k] = len(pos)
    return counts[:, :, None, None]


def _demosaic_state(signal: np.ndarray, variance: np.ndarray, excluded: np.ndarray,
                    layout: MosaicLayout, method: str, offset_dn: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(measured, variance, valid)`` ``(C, 4, H', W')`` of one state's mosaic (or rows of
    it), analyzer offsets ``offset_dn`` (same shape, DN) removed first."""
    if offset_dn is not None:
        signal = np.asarray(signal, np.float64) - offset_dn
    measured = demosaic_float(np.asarray(signal, np.float32), layout, method)
    return (measured, *_demosaic_variance(variance, excluded, layout, method))


def _demosaic_variance(variance: np.ndarray, excluded: np.ndarray, layout: MosaicLayout,
                       method: str) -> tuple[np.ndarray, np.ndarray]:
    """``(variance, valid)`` ``(C, 4, H', W')`` of one state's mosaic (or rows of it): the
    noise half of :func:`_demosaic_state`."""
    var = demosaic_float(np.asarray(variance, np.float32), layout, method)
    if method == "superpixel":
        var /= _superpixel_counts(layout)
    excluded = np.asarray(excluded)
    if not excluded.any():  # nothing to spread: every output sample is valid
        return var, np.ones(var.shape, bool)
    bad = demosaic_float(excluded.astype(np.float32), layout, method)
    return var, ~(bad > 0)


def analyzer_variance(state: StateRadiance, layout: MosaicLayout, method: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The ``variance`` and ``valid`` of :func:`analyzer_stack` alone (``(C, 4, H', W')``,
    identical values), without demosaicing the signal: what the samples' weights need."""
    return _demosaic_variance(state.variance_dn2, state.excluded, layout, method)


def _demosaic_rows(rows: np.ndarray, layout: MosaicLayout, method: str) -> np.ndarray:
    """Per-pixel analyzer rows ``(H, W, 3)`` -> ``(C, 4, 3, H', W')`` by the same demosaic."""
    return np.stack([demosaic_float(rows[..., i].astype(np.float32), layout, method)
                     for i in range(3)], axis=2)


def analyzer_stack(state: StateRadiance, layout: MosaicLayout, method: str,
                   analyzer: AnalyzerModel | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Demosaic one state: ``(measured, variance, valid, rows)``, the first three
    ``(C, 4, H', W')`` and ``rows`` ``(C, 4, 3, H', W')`` (``None`` for the ideal analyzer).

    A calibrated ``analyzer`` (of this readout) has its offsets removed from the signal and its
    per-pixel rows carried to the output grid by the same demosaic.
    """
    signal = np.asarray(state.signal_dn)
    rows = None
    offset = None
    if analyzer is not None:
        _check_analyzer(analyzer, signal.shape)
        offset = analyzer.offset_dn
        rows = _demosaic_rows(analyzer.rows(), layout, method)
    measured, variance, valid = _demosaic_state(signal, state.variance_dn2, state.excluded,
                                                layout, method, offset)
    return measured, variance, valid, rows


def _check_analyzer(analyzer: AnalyzerModel, shape: tuple[int, ...]) -> None:
    if analyzer.shape != tuple(shape):
        raise ValueError(f"analyzer model {analyzer.shape} does not match frames {tuple(shape)}")


def _band_samples(states: Sequence[StateRadiance], band: tuple[int, int, int, int],
                  lay: MosaicLayout, method: str, analyzer: AnalyzerModel | None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(measured, variance, valid, rows)`` of every state on the output rows ``o0:o1`` of
    ``band`` ``(o0, o1, e0, e1)`` (:func:`polrig.sensor.demosaic.row_bands`: demosaiced from the
    mosaic rows ``e0:e1``): the first three ``(N, C, 4, o1 - o0, W')``, ``rows`` the analyzer's
    ``(C, 4, 3, o1 - o0, W')`` (None: ideal)."""
    o0, o1, e0, e1 = band
    width = np.shape(states[0].signal_dn)[1]
    a = 0 if method == "superpixel" else o0 - e0
    rows = o1 - o0
    offset = a_rows = None
    if analyzer is not None:
        part = analyzer.crop(0, e0, width, e1 - e0)
        offset = part.offset_dn
        a_rows = _demosaic_rows(part.rows(), lay, method)[..., a:a + rows, :]
    meas = var = valid = None
    for k, st in enumerate(states):
        m, v, ok = _demosaic_state(st.signal_dn[e0:e1], st.variance_dn2[e0:e1],
                                   st.excluded[e0:e1], lay, method, offset)
        if meas is None:
            meas = np.empty((len(states), *m.shape[:2], rows, m.shape[-1]), np.float32)
            var, valid = np.empty_like(meas), np.empty(meas.shape, bool)
        meas[k], var[k], valid[k] = (p[:, :, a:a + rows] for p in (m, v, ok))
    return meas, var, valid, a_rows


#: Output pixels (times colours) :func:`prior_scale_from_frames` samples at most (2^16: one band
#: of :data:`SCALE_BAND_ROWS` rows in 15 of a full-sensor colour superpixel result, in 20 of a
#: mono one; the quantile it solves for then rests on about 200 000 innovations per further
#: state; 64x64 and the rig's 128x128 analyzer grid are taken whole).
SCALE_SAMPLE_PIXELS = 2 ** 16
#: Output rows per band of :func:`prior_scale_from_frames`' sample (every ``k``-th such band).
SCALE_BAND_ROWS = 4


def prior_scale_from_frames(states: Sequence[StateRadiance], s_in: np.ndarray,
                            layout: str | MosaicLayout, method: str, analyzer: AnalyzerModel | None,
                            prior_mean: np.ndarray, prior_sigma: np.ndarray, seen_state: int, *,
                            band_rows: int = SCALE_BAND_ROWS,
                            sample_pixels: int = SCALE_SAMPLE_PIXELS) -> PriorScale:
    """The network prior's scale for the hybrid solve of these frames
    (:func:`polrig.solve.prior_scale.scale_of`, :mod:`polrig.solve.prior_scale`): from the
    innovations of an even sample of the output rows, bands of ``band_rows`` rows
    (:func:`polrig.sensor.demosaic.row_bands`, every ``k``-th, ``k`` the least that keeps at most
    ``sample_pixels`` output pixels times colours; all of them in a smaller image), demosaiced as
    :func:`reference_from_frames` demosaics them (per-pixel values do not depend on the banding).
    Arguments as :func:`reference_from_frames` (``prior_mean``, ``prior_sigma`` on the output
    grid or broadcastable to it). One state: factor 1 (nothing to measure the prior against)."""
    lay = resolve_layout(layout)
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    if len(states) < 2:
        return scale_of(np.zeros(0), np.zeros(0), np.zeros(0))
    shape = np.shape(states[0].signal_dn)
    if analyzer is not None:
        _check_analyzer(analyzer, shape)
    c = lay.n_colours
    h_out, w_out = output_shape(lay, shape, method)
    bands = row_bands(lay, shape, method, max(1, int(band_rows)))
    step = max(1, -(-h_out * w_out * c // max(1, int(sample_pixels))))
    mean, sigma = (np.broadcast_to(np.asarray(a), (c, 3, 3, h_out, w_out)) for a in (prior_mean, prior_sigma))
    parts = []
    for band in bands[::step]:
        o0, o1 = band[:2]
        meas, var, valid, rows = _band_samples(states, band, lay, method, analyzer)
        parts.append(innovations(s, meas, var, valid, mean[..., o0:o1, :], sigma[..., o0:o1, :], seen_state, rows))
    return scale_of(*(np.concatenate(a) for a in zip(*parts)))


#: Output rows per band of :func:`open_scale_from_frames`' sample: the diffuse completion's second
#: pass looks at each pixel's 3x3 neighbours, whom a band's first and last rows lack in part.
OPEN_BAND_ROWS = 8
#: Object pixels times colours :func:`open_scale_from_frames` samples at most: the test and the
#: completion cost about 75 us a colour-pixel (2 CPUs), so 2^16 took 4.6 s of a full mono
#: capture (``python -m benchmarks open_scale``); a quarter of that keeps the quantile's own
#: spread small (some 40 000 values) for a quarter of the time. The rig's 128x128 grid and the
#: 64x64 sets are taken whole.
OPEN_SAMPLE_PIXELS = 2 ** 14


def open_scale_from_frames(states: Sequence[StateRadiance], s_in: np.ndarray,
                           layout: str | MosaicLayout, method: str, analyzer: AnalyzerModel | None,
                           prior_mean: np.ndarray, prior_sigma: np.ndarray, seen_state: int,
                           prior_correlation: np.ndarray | None, geometry: DiffuseGeometry, mask: np.ndarray, *,
                           band_rows: int = OPEN_BAND_ROWS, sample_pixels: int = OPEN_SAMPLE_PIXELS) -> OpenScale:
    """The factor on the prior's standard deviation along the direction two states leave open
    (:mod:`polrig.solve.open_scale`) for the hybrid solve of these frames: on an even sample of
    the bands of ``band_rows`` output rows that hold some of ``mask`` (every ``k``-th, ``k`` the
    least that keeps at most ``sample_pixels`` of its pixels times colours; all of them on a
    smaller object), each solved as :func:`reference_from_frames` solves it (in float64) and
    tested and completed there (:func:`polrig.solve.open_scale.open_values`), the values pooled
    (:func:`polrig.solve.open_scale.open_scale_of`). ``prior_*``, ``seen_state``: the hybrid's
    (the sigma already scaled by :func:`prior_scale_from_frames`); ``geometry``: the output
    grid's (:class:`polrig.solve.diffuse_geometry.DiffuseGeometry`; its normals are not used);
    ``mask`` ``(H, W)``: the pixels to test (the network's object). Not two states: factor 1."""
    lay = resolve_layout(layout)
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    if len(states) != 2:
        return OpenScale.none()
    shape = np.shape(states[0].signal_dn)
    if analyzer is not None:
        _check_analyzer(analyzer, shape)
    c = lay.n_colours
    h_out, w_out = output_shape(lay, shape, method)
    mask = np.broadcast_to(np.asarray(mask, bool), (h_out, w_out))
    bands = [b for b in row_bands(lay, shape, method, max(1, int(band_rows))) if mask[b[0]:b[1]].any()]
    step = max(1, -(-int(mask.sum()) * c // max(1, int(sample_pixels))))
    mean, sigma = (np.broadcast_to(np.asarray(a), (c, 3, 3, h_out, w_out)) for a in (prior_mean, prior_sigma))
    d, v = [], []
    for band in bands[::step]:
        o0, o1 = band[:2]
        meas, var, valid, rows = _band_samples(states, band, lay, method, analyzer)
        prior = dict(prior_mean=mean[..., o0:o1, :], prior_sigma=sigma[..., o0:o1, :], seen_state=seen_state,
                     prior_correlation=prior_correlation)
        with _SOLVE_LOCK:
            res = solve_hybrid(s, meas, var, valid, rows, dtype=np.float64, **prior)
        part = open_values(res, s, meas, var, valid, geometry_rows(geometry, o0, o1), mask=mask[o0:o1],
                           analyzer_rows=rows, **prior)
        d.append(part[0])
        v.append(part[1])
    if not d:
        return open_scale_of(np.zeros(0), np.zeros(0))
    return open_scale_of(np.concatenate(d), np.concatenate(v))


def reference_from_frames(states: Sequence[StateRadiance], s_in: np.ndarray,
                          layout: str | MosaicLayout, method: str = "superpixel",
                          analyzer: AnalyzerModel | None = None, *,
                          analyzer_tolerance: Sequence[float] | None = None,
                          generator_tolerance: Sequence[float] | None = None,
                          band_pixels: int = BAND_PIXELS,
                          uncertainty_dtype: type | np.dtype | str = np.float32,
                          workers: int | None = None, prior_mean: np.ndarray | None = None,
                          prior_sigma: np.ndarray | None = None,
                          seen_state: int | None = None,
                          prior_correlation: np.ndarray | None = None, open_factor: float = 1.0,
                          model_selection: SelectionOptions | None = None) -> ReferenceResult:
    """The reference solve of all states (see :func:`polrig.solve.reference.solve_reference`;
    the tolerances are the calibration's, :class:`polrig.app.processing.Calibration`).

    With ``prior_mean`` and ``prior_sigma`` (``(C, 3, 3, H', W')`` on the output grid, or
    broadcastable to it: the single-shot network's estimate and calibrated sigma of state
    ``seen_state``'s frame), the hybrid solve instead
    (:func:`polrig.solve.hybrid.solve_hybrid`, any number of states), each band with its rows
    of the prior; ``prior_correlation`` ``(6, 6)``: the prior calibrated jointly
    (:mod:`polrig.solve.hybrid`, "Joint prior"; None: per element); ``open_factor``: at two
    states, the factor on the prior's standard deviation along the direction they leave open
    (:func:`open_scale_from_frames`; 1: as it is).

    With ``model_selection``, each band's result then goes through
    :func:`polrig.solve.model_selection.select_models` on the same samples (lower-order models
    where they explain them; off by default): the result's ``models`` holds the maps. Only
    the pixels the samples determine are tested: the prior is not passed to the selection, so
    two states leave every pixel ``UNTESTED``. The test at two states on the hybrid's posterior
    system (:func:`~polrig.solve.model_selection.select_models` with ``prior``) exists and is
    measured (``python -m polrig.models.continuum --models-only``), but with the shipped
    network's prior its false acceptance is 1-22 % per held-out set, above the 5 % its level
    promises (1.3-21.9 % with the prior calibrated jointly, ``python -m polrig.models.continuum
    --joint-compare``), so captures do not offer it.

    Solved in bands of about ``band_pixels`` output pixels (times colours): each band is
    demosaiced from the mosaic rows it needs (:func:`polrig.sensor.demosaic.row_bands`) and solved on
    its own; per-pixel results do not depend on the banding. ``uncertainty_dtype``
    (``float32`` or ``float16``): of the result's ``sigma``, ``sigma_noise`` and ``residual``
    (half precision, 11 significant bits, halves their memory and file size; ``mueller`` stays
    float32; values above 65504 become ``inf``). ``workers``: bands in flight on threads
    (default :data:`WORKERS`; 1: sequential): band demosaics overlap each other and the solve
    of another band, the :func:`~polrig.solve.reference.solve_reference` calls are serialised; the
    result does not depend on it.
    """
    lay = resolve_layout(layout)
    unc = np.dtype(uncertainty_dtype)
    if unc not in [np.dtype(d) for d in UNCERTAINTY_DTYPES]:
        raise ValueError(f"uncertainty_dtype must be float32 or float16, got {unc}")
    if not states:
        raise ValueError("no polarizer states to solve")
    shape = np.shape(states[0].signal_dn)
    for st in states:
        for a in (st.signal_dn, st.variance_dn2, st.excluded):
            if np.shape(a) != shape:
                raise ValueError(f"state mosaics differ in shape: {np.shape(a)} and {shape}")
    if analyzer is not None:
        _check_analyzer(analyzer, shape)
    c = lay.n_colours
    h_out, w_out = output_shape(lay, shape, method)
    if (prior_mean is None) != (prior_sigma is None):
        raise ValueError("give both prior_mean and prior_sigma, or neither")
    if prior_mean is not None:
        try:
            prior_mean, prior_sigma = (np.broadcast_to(np.asarray(a), (c, 3, 3, h_out, w_out))
                                       for a in (prior_mean, prior_sigma))
        except ValueError:
            raise ValueError(f"prior shapes {np.shape(prior_mean)}, {np.shape(prior_sigma)} do not "
                             f"broadcast to the output grid {(c, 3, 3, h_out, w_out)}") from None
    band_rows = max(1, int(band_pixels) // max(1, w_out * c))
    bands = row_bands(lay, shape, method, band_rows)

    def solve_band(band: tuple[int, int, int, int]) -> ReferenceResult:
        o0, o1 = band[:2]
        meas, var, valid, a_rows = _band_samples(states, band, lay, method, analyzer)
        with _SOLVE_LOCK:  # one solve at a time: the solver may run threads of its own
            if prior_mean is not None:
                res = solve_hybrid(s_in, meas, var, valid, a_rows,
                                   prior_mean=prior_mean[..., o0:o1, :],
                                   prior_sigma=prior_sigma[..., o0:o1, :], seen_state=seen_state,
                                   prior_correlation=prior_correlation, open_factor=open_factor,
                                   analyzer_tolerance=analyzer_tolerance,
                                   generator_tolerance=generator_tolerance)
            else:
                res = solve_reference(s_in, meas, var, valid, a_rows,
                                      analyzer_tolerance=analyzer_tolerance,
                                      generator_tolerance=generator_tolerance)
        if model_selection is not None:  # numpy: releases the GIL in its large operations
            res = select_models(s_in, meas, var, valid, a_rows, res, model_selection)[0]
        return res

    # the first band alone (it raises for a bad state set before any other work, and gives
    # the result's layout); the others on a few threads: their demosaics run side by side
    # (OpenCV and numpy release the GIL) and beside the solve of another band, the solves one
    # after the other (solve_reference already spreads one band's tiles over the CPUs on its
    # own thread pool: two solves at once would only oversubscribe them); each band stores
    # its own rows as soon as it is solved: at most ``workers`` bands in flight
    first = solve_band(bands[0])
    cond = first.condition_number
    shared_sigma = first.sigma_noise is first.sigma
    out = _allocate(first, (h_out, w_out), unc, shared_sigma)

    maps = None
    if model_selection is not None:
        maps = ModelMaps(*(np.empty(first.mask.shape[:-2] + (h_out, w_out), a.dtype) for a in (
            first.models.code, first.models.statistic, first.models.p_value)), model_selection)

    def store(band: tuple[int, int, int, int], res: ReferenceResult) -> None:
        with np.errstate(over="ignore"):  # above the half range: inf
            for name, arr in out.items():
                arr[..., band[0]:band[1], :] = getattr(res, name)
        if maps is not None:
            for name in ("code", "statistic", "p_value"):
                getattr(maps, name)[..., band[0]:band[1], :] = getattr(res.models, name)

    store(bands[0], first)
    rest = bands[1:]
    n_workers = max(1, min(len(rest), int(WORKERS if workers is None else workers)))
    if n_workers == 1:
        for band in rest:
            store(band, solve_band(band))
    else:
        with concurrent.futures.ThreadPoolExecutor(n_workers) as pool:
            list(pool.map(lambda band: store(band, solve_band(band)), rest))
    return ReferenceResult(out["mueller"], out["sigma"], out["residual"], out["mask"], cond,
                           out["pixel_condition"], out["n_samples"],
                           None if shared_sigma else out["sigma_noise"], maps)


def _allocate(band: ReferenceResult, hw: tuple[int, int], unc: np.dtype, shared_sigma: bool
              ) -> dict[str, np.ndarray]:
    """Full-size result arrays shaped and typed like a band's (uncertainty planes ``unc``)."""
    names = ["mueller", "sigma", "residual", "mask", "pixel_condition", "n_samples"]
    if not shared_sigma:
        names.append("sigma_noise")
    out = {}
    for name in names:
        a = getattr(band, name)
        dtype = unc if name in ("sigma", "sigma_noise", "residual") else a.dtype
        out[name] = np.empty(a.shape[:-2] + hw, dtype)
    return out
