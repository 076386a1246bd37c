"""Pure radiometry of the reference capture: raw frames of each polarizer state -> radiance
mosaics with variance and exclusions -> demosaiced analyzer images -> the reference solve.

* :func:`adc_scale` -- DN of delivered frames -> DN of the ADC the noise model describes.
* :func:`state_radiance` -- K frames (and an exposure bracket) of one polarizer state ->
  black/dark-subtracted mean mosaic in DN at the reference exposure, its variance from the
  sensor noise model, and the samples to exclude (saturated).
* :func:`analyzer_stack` -- demosaic mosaics, variances and exclusions into analyzer images
  ``(C, 4, H', W')``.
* :func:`reference_from_frames` -- all states -> :class:`polrig.reference.ReferenceResult`.

Uncertainty propagation: per raw sample the model variance
(:meth:`polrig.noise.SensorModel.variance_dn2` at the measured mean signal, divided by K;
plus the variance of the subtracted dark mean), HDR-merged by :func:`polrig.reference.merge_hdr`;
the ``superpixel`` demosaic averages ``n`` same-class pixels, so the variance is the mean
variance divided by ``n`` (exact); interpolating demosaics get the interpolated variance
(an approximation: it ignores the correlation the interpolation creates).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from polrig.analyzer import AnalyzerModel, resolve_layout
from polrig.demosaic import class_positions, demosaic_float
from polrig.layouts import MosaicLayout
from polrig.noise import SensorModel
from polrig.reference import ReferenceResult, solve_reference, merge_hdr


def adc_scale(model: SensorModel, bit_depth: int) -> float:
    """Factor from the DN of frames delivered with ``bit_depth`` bits to the DN of the ADC the
    noise model describes (a 12-bit ADC read out as Mono16 delivers values times 16: the
    factor is 1/16). Results are always in ADC DN, whatever the pixel format."""
    return 2.0 ** (int(model.bit_depth) - int(bit_depth))


# -- array level -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class StateRadiance:
    """One state's mosaic ``(H, W)``: ``signal_dn`` (black/dark-subtracted, at the reference
    exposure), ``variance_dn2`` and ``excluded`` (bool, saturated in every exposure)."""

    signal_dn: np.ndarray
    variance_dn2: np.ndarray
    excluded: np.ndarray


def state_radiance(brackets: Sequence[Sequence[np.ndarray]], exposures_us: Sequence[float],
                   model: SensorModel, *, black_level_dn: float = 0.0,
                   darks: Sequence[Sequence[np.ndarray]] | None = None,
                   code_step_dn: float = 1.0) -> StateRadiance:
    """Mean black-subtracted mosaic of one polarizer state.

    ``brackets[e]``: the K raw frames ``(H, W)`` taken at ``exposures_us[e]``; ``darks[e]``:
    dark frames at that exposure (light off) or ``None``/empty (subtract ``black_level_dn``
    only). A sample is excluded when any of its frames reaches the saturation level
    (``black + model.saturation_dn``); several exposures are merged by
    :func:`polrig.reference.merge_hdr` at ``exposures_us[0]`` (the reference exposure).

    ``code_step_dn``: ADC DN per code of the delivered frames (:func:`adc_scale`; 16 for
    Mono8 from a 12-bit ADC). A frame with fewer bits than the ADC clips at its own top code,
    ``(2**bits - 1) * step = 2**adc_bits - step`` DN (4080 for Mono8), which is below the
    ADC's saturation threshold: samples there are saturated too. Its coarser codes add
    rounding variance: ``step**2 / 12`` in all, ``(step**2 - 1) / 12`` beyond the ADC's own
    ``1/12`` the noise model holds (per frame; not carried into an HDR merge, which takes
    the model's variance).
    """
    if len(brackets) != len(exposures_us) or not brackets:
        raise ValueError("one list of frames per exposure is needed")
    step = float(code_step_dn)
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
        return StateRadiance(means[0], variances[0], sats[0])
    # merge_hdr excludes samples >= saturation_dn: mark the saturated ones that way
    marked = [np.where(s, np.inf, m) for m, s in zip(means, sats)]
    radiance, variance, valid = merge_hdr(list(zip(marked, exposures_us)), model.saturation_dn,
                                          model, reference_exposure_us=exposures_us[0],
                                          n_frames=len(brackets[0]))
    return StateRadiance(radiance, variance, ~valid)


def analyzer_stack(state: StateRadiance, layout: MosaicLayout, method: str,
                   analyzer: AnalyzerModel | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Demosaic one state: ``(measured, variance, valid, rows)``, the first three
    ``(C, 4, H', W')`` and ``rows`` ``(C, 4, 3, H', W')`` (``None`` for the ideal analyzer).

    A calibrated ``analyzer`` (of this readout) has its offsets removed from the signal and its
    per-pixel rows carried to the output grid by the same demosaic.
    """
    signal = np.asarray(state.signal_dn, dtype=np.float64)
    rows = None
    if analyzer is not None:
        if analyzer.shape != signal.shape:
            raise ValueError(f"analyzer model {analyzer.shape} does not match frames "
                             f"{signal.shape}")
        signal = signal - analyzer.offset_dn
        r = analyzer.rows()
        rows = np.stack([demosaic_float(r[..., i].astype(np.float32), layout, method)
                         for i in range(3)], axis=2)
    measured = demosaic_float(signal.astype(np.float32), layout, method)
    variance = demosaic_float(np.asarray(state.variance_dn2, np.float32), layout, method)
    if method == "superpixel":
        counts = np.zeros((layout.n_colours, 4), np.float32)
        for (c, k), pos in class_positions(layout).items():
            counts[c, k] = len(pos)
        variance = variance / counts[:, :, None, None]
    bad = demosaic_float(state.excluded.astype(np.float32), layout, method)
    valid = ~(bad > 0)
    return measured, variance, valid, rows


def reference_from_frames(states: Sequence[StateRadiance], s_in: np.ndarray,
                          layout: str | MosaicLayout, method: str = "superpixel",
                          analyzer: AnalyzerModel | None = None, *,
                          analyzer_tolerance: Sequence[float] | None = None,
                          generator_tolerance: Sequence[float] | None = None
                          ) -> ReferenceResult:
    """The reference solve of all states (see :func:`polrig.reference.solve_reference`;
    the tolerances are the calibration's, :class:`Calibration`)."""
    lay = resolve_layout(layout)
    parts = [analyzer_stack(s, lay, method, analyzer) for s in states]
    measured = np.stack([p[0] for p in parts])
    variance = np.stack([p[1] for p in parts])
    valid = np.stack([p[2] for p in parts])
    rows = parts[0][3]
    return solve_reference(s_in, measured, variance, valid, rows,
                           analyzer_tolerance=analyzer_tolerance,
                           generator_tolerance=generator_tolerance)
