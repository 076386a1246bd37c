"""Alias of :mod:`polrig.calibration.calset` under the name :mod:`polrig.app.processing` imports
(``polrig.calibration.calibset.load(DIR)``), plus :func:`tolerances`: the 1-sigma uncertainties of a
set that the reference solve propagates into its reported sigma."""

from __future__ import annotations

import math

from polrig.calibration.calset import CalibrationSet, load

__all__ = ["CalibrationSet", "load", "tolerances", "CALIBRATED_GAIN_TOLERANCE"]

#: Relative gain uncertainty of a DoFP-calibrated analyzer: the set stores no fitted gain
#: uncertainty, so the DoFP procedure's acceptance limit is used (0.5 %; measured RMS error on
#: the simulated rig 0.2 %, docs/calibration.md).
CALIBRATED_GAIN_TOLERANCE = 0.005


def _num(section: dict, key: str) -> float | None:
    v = section.get(key)
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v >= 0 else None


def tolerances(cs: CalibrationSet, nominal_analyzer: tuple[float, float, float],
               nominal_generator: tuple[float, float]
               ) -> tuple[tuple[float, float, float], tuple[float, float]]:
    """``(analyzer_tolerance, generator_tolerance)`` of a calibration set, in the form of
    :class:`polrig.app.processing.Calibration`: ``(gain_rel, angle_deg, diattenuation)`` and
    ``(zero_offset_deg, inverse_extinction)``, 1 sigma.

    Analyzer (``dofp`` section): orientation = the median per-pixel ``angle_std_deg``,
    diattenuation = the median ``modulation_std`` (the modulation is ``D_p d`` with generator
    DoLP ``d`` close to 1), gain = :data:`CALIBRATED_GAIN_TOLERANCE`. Generator: zero offset =
    the larger of ``zero_offset_std_deg`` and its bound ``zero_offset_std_bound_deg`` (which
    includes the axis and board pose); ``1/ER`` from ``extinction_ratio_std / ER^2``. A step the
    set lacks keeps the nominal priors (its model is then the nominal one too).
    """
    a_tol = tuple(float(v) for v in nominal_analyzer)
    g_tol = tuple(float(v) for v in nominal_generator)
    dofp = cs.params.get("dofp") if cs.has("dofp") and cs.analyzer is not None else None
    if dofp is not None:
        angle = _num(dofp, "angle_std_deg_median")
        dia = _num(dofp, "modulation_std_median")
        a_tol = (CALIBRATED_GAIN_TOLERANCE,
                 a_tol[1] if angle is None else angle, a_tol[2] if dia is None else dia)
    gen = cs.params.get("generator") if cs.has("generator") else None
    if gen is not None:
        offs = [v for v in (_num(gen, "zero_offset_std_deg"),
                            _num(gen, "zero_offset_std_bound_deg")) if v is not None]
        er, er_std = _num(gen, "extinction_ratio"), _num(gen, "extinction_ratio_std")
        # an infinite (not measured: no DoFP step) extinction ratio keeps the prior
        inv_ext = er_std / er**2 if er is not None and er_std is not None and er > 0 else g_tol[1]
        g_tol = (max(offs) if offs else g_tol[0], inv_ext)
    return a_tol, g_tol
