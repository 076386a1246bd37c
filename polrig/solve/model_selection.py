"""Model only what the scene requires: per pixel and colour, a likelihood-ratio test of each
lower-order model of the 3x3 block (:mod:`polrig.solve.reduced_models`) against the full
block, and, where one explains the samples within their noise, the estimate under it.

**The test** (Wilks 1938; for a model linear in its parameters it is exact). The samples
``I_kj`` of the reference solve have the variances ``v_kj`` of its noise model
(:mod:`polrig.solve.reference`), so ``chi^2(m) = sum w (I - D m)^2`` is their
``-2 log``-likelihood up to a constant. A model with ``k`` parameters nested in the nine of
the full block has the likelihood-ratio statistic

    Lambda = min chi^2(model) - min chi^2(full) = min_theta (m(theta) - m_hat)^T N (m(theta) - m_hat)

(``N = D^T W D``, ``m_hat`` the full block's weighted least-squares estimate), distributed
``chi^2(9 - k)`` when the model holds (exactly for a linear model; to first order for the
nonlinear ones). The model is *accepted* where ``p = P(chi^2(9 - k) > Lambda) > alpha``
(default ``alpha = 0.05``: a pixel where the model holds is rejected 5 % of the time). Of the
accepted models the one with the fewest parameters is chosen (ties: the larger ``p``). Why a
test and not an information criterion: the noise model is known (the residual of the full
solve is about 1, ``benchmarks/results/reference.md``), so ``Lambda`` has a known distribution
and ``alpha`` is an error rate one can state and check; AIC amounts to the same test with a
level that changes with ``9 - k`` (0.09 at 4 degrees of freedom, 0.04 at 8) and BIC to one
whose level falls with the number of samples, neither an error rate chosen for the purpose.

**False acceptance** (what ``tests/test_model_selection.py`` and ``python -m benchmarks
model_selection`` measure). Where the full block holds, accepting a reduced model is wrong
only where the samples can tell: the truth's distance from the model in the noise metric,
the noncentrality ``lambda = min_theta (m(theta) - m_true)^T N (m(theta) - m_true)``, is at
least :func:`detectable_noncentrality` (the ``lambda`` at which the level-``alpha`` test rejects
with probability 0.95: 18.6 at 4 degrees of freedom, ``alpha = 0.05``). A pixel whose truth is
detectably off *every* candidate counts in the denominator; it is a false acceptance when any
reduced model is chosen. Below that distance a reduced model may be accepted and is not an
error: its bias is then comparable to the noise it removes (the benchmark reports the RMSE
against the truth with and without selection on the scenes where the full block holds).

**The estimate under the chosen model** replaces the full one: the block ``m(theta_hat)``, its
noise sigma by the delta method (:func:`polrig.solve.reduced_models.block_covariance`), the
calibration part of the full result's sigma kept as it is (``sigma^2 = sigma_noise_red^2 +
sigma^2 - sigma_noise^2`` of the full result: a conservative choice, the model's projection
would shrink it too), the residual ``(chi^2_full + Lambda) / (n - k)`` and the ``DARK`` bit
re-evaluated. With a prior (the hybrid solve) the test and the reduced estimate use the
samples alone; the prior enters only the pixels left full.

**Which pixels are tested**: those the samples alone determine (not ``ILL_CONDITIONED``, the
used samples' condition number at most ``max_condition``, at least 9 finite samples; with
fewer than three states, none). The others are coded :data:`UNTESTED` with a NaN statistic.

Never silent: nothing here runs unless asked (``polrig reconstruct --models auto``,
``polrig capture --models auto``); the result then always carries the maps
(:class:`ModelMaps`: ``model.{colour}`` codes, ``model_chi2.{colour}`` the statistic,
``model_p.{colour}`` its p-value, :func:`model_planes`) and the header records the test.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from polrig.errors import ConfigError
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve.reduced_models import MODEL_CODES, MODELS, block_covariance, fit_model
from polrig.solve.reference import (
    DARK,
    DEFAULT_MAX_CONDITION,
    ILL_CONDITIONED,
    MIN_SNR,
    ReferenceResult,
)

__all__ = ["UNTESTED", "SelectionOptions", "ModelMaps", "select_models", "chi2_sf",
           "chi2_critical", "detectable_noncentrality", "model_planes", "selection_header",
           "normal_equations", "MODEL_CHOICES", "MODEL_PLANES"]

#: Model map code of a pixel that was not tested (its samples do not determine the block).
UNTESTED = 255

#: The ``--models`` choices: ``full`` (no selection, the default) and ``auto``.
MODEL_CHOICES = ("full", "auto")


@dataclass(frozen=True)
class SelectionOptions:
    """``alpha``: the test's level (0 < alpha < 1). ``models``: names of the candidates
    (:data:`polrig.solve.reduced_models.MODELS`). ``iterations``: Levenberg-Marquardt steps per
    start. ``max_condition``: a pixel is tested only where its samples' condition number is at
    most this."""

    alpha: float = 0.05
    models: tuple[str, ...] = tuple(m.name for m in MODELS)
    iterations: int = 12
    max_condition: float = DEFAULT_MAX_CONDITION

    def __post_init__(self) -> None:
        if not (0.0 < float(self.alpha) < 1.0):
            raise ConfigError(f"model selection alpha must be in (0, 1), got {self.alpha!r}")
        known = {m.name for m in MODELS}
        unknown = [m for m in self.models if m not in known]
        if unknown or not self.models:
            raise ConfigError(f"model selection models must be some of {', '.join(sorted(known))}; "
                              f"got {', '.join(map(repr, self.models)) or 'none'}")
        if int(self.iterations) < 1:
            raise ConfigError(f"model selection iterations must be >= 1, got {self.iterations!r}")


@dataclass(frozen=True, eq=False)
class ModelMaps:
    """Per pixel and colour ``(C, H, W)``: ``code`` uint8 (:data:`MODEL_CODES`, ``0`` full,
    :data:`UNTESTED`), ``statistic`` float32 (``Lambda`` of the chosen model; for ``full`` of
    the candidate with the largest p-value; NaN untested), ``p_value`` float32 (its p-value)."""

    code: np.ndarray
    statistic: np.ndarray
    p_value: np.ndarray
    options: SelectionOptions = field(default_factory=SelectionOptions)

    def counts(self) -> dict[str, int]:
        """Pixels (over colours) per model name (``untested`` included)."""
        names = {**MODEL_CODES, UNTESTED: "untested"}
        return {names[c]: int(np.count_nonzero(self.code == c)) for c in names}


# ----------------------------------------------------------------------- chi-square tail
_ERFC = np.frompyfunc(math.erfc, 1, 1)


def chi2_sf(x: np.ndarray, df: int) -> np.ndarray:
    """``P(chi^2(df) > x)`` for integer ``df >= 1``, vectorised (the regularised upper
    incomplete gamma ``Q(df/2, x/2)`` by its recursion ``Q(s + 1, y) = Q(s, y) + y^s e^-y /
    Gamma(s + 1)`` from ``Q(1, y) = e^-y`` or ``Q(1/2, y) = erfc(sqrt y)``). NaN stays NaN;
    ``x <= 0`` gives 1."""
    x = np.asarray(x, dtype=np.float64)
    y = np.clip(x, 0.0, None) / 2.0
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        if df % 2:
            q = np.asarray(_ERFC(np.sqrt(np.where(np.isfinite(y), y, 0.0))), dtype=np.float64)
            s = 0.5
        else:
            q = np.exp(-y)
            s = 1.0
        log_y = np.log(np.where(y > 0, y, 1.0))
        while s < df / 2.0:
            q = q + np.where(y > 0, np.exp(s * log_y - y - math.lgamma(s + 1.0)), 0.0)
            s += 1.0
    q = np.where(np.isinf(x), 0.0, q)
    return np.where(np.isnan(x), np.nan, np.clip(q, 0.0, 1.0))


@lru_cache(maxsize=64)
def chi2_critical(df: int, alpha: float) -> float:
    """The ``1 - alpha`` quantile of ``chi^2(df)`` (bisection on :func:`chi2_sf`; cached: 200
    bisection steps cost about 10 ms, once per model and call of :func:`select_models`, i.e.
    per row band of a full-sensor solve)."""
    lo, hi = 0.0, 10.0 * df + 100.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_sf(np.array(mid), df) > alpha:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _ncx2_sf(x: float, df: int, lam: float) -> float:
    """``P(chi^2(df, lam) > x)``: the noncentral chi-square as a Poisson(``lam / 2``) mixture
    of central ones with ``df + 2 j`` degrees of freedom."""
    total, j = 0.0, 0
    half = lam / 2.0
    while True:
        wj = math.exp(-half + j * math.log(half) - math.lgamma(j + 1)) if half > 0 else float(j == 0)
        total += wj * float(chi2_sf(np.array(x), df + 2 * j))
        if j > half and wj < 1e-14:
            return total
        j += 1


def detectable_noncentrality(df: int, alpha: float = 0.05, power: float = 0.95) -> float:
    """The noncentrality ``lambda`` at which the level-``alpha`` test with ``df`` degrees of
    freedom rejects with probability ``power``: a truth at least that far from a model (in
    the noise metric) is one the samples can tell from it (module docstring)."""
    crit = chi2_critical(df, alpha)
    lo, hi = 0.0, 1000.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if _ncx2_sf(crit, df, mid) < power:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# ----------------------------------------------------------------------- normal equations
def _pixel_design(s: np.ndarray, analyzer_rows, c: int, pix: np.ndarray, hw: tuple[int, int]):
    """Design rows ``(P, 4 N, 9)`` or shared ``(4 N, 9)`` of pixels ``pix`` (flat indices) of
    colour ``c``."""
    if analyzer_rows is None or np.ndim(analyzer_rows) == 2:
        a = ideal_analyzer_matrix() if analyzer_rows is None else np.asarray(analyzer_rows, float)
        return np.einsum("ja,kb->kjab", a, s).reshape(len(s) * 4, 9)
    a = np.asarray(analyzer_rows, dtype=np.float64)
    a = a[c] if a.ndim == 5 else a
    a = a.reshape(4, 3, hw[0] * hw[1])[..., pix]
    return np.einsum("jap,kb->pkjab", a, s).reshape(len(pix), len(s) * 4, 9)


def normal_equations(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                     valid: np.ndarray | None, analyzer_rows, c: int, pix: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The reference solve's weighted least squares for pixels ``pix`` (flat indices into
    ``(H, W)``) of colour ``c``, in float64: the normal matrix ``N = D^T W D`` ``(P, 9, 9)``,
    the estimate ``m_hat`` ``(P, 9)`` (NaN where ``N`` is singular), ``chi^2`` of ``m_hat``
    ``(P,)`` and the number of samples used ``(P,)``. Arguments as
    :func:`polrig.solve.reference.solve_reference` (samples used: finite, positive variance,
    ``valid``)."""
    s = np.asarray(s_in, dtype=np.float64)
    n = len(s)
    h, w = measured.shape[-2:]

    def take(arr):
        return np.moveaxis(np.asarray(arr[:, c]).reshape(n * 4, h * w)[:, pix], 0, -1).astype(np.float64)

    meas, var = take(measured), take(variance)
    ok = np.isfinite(meas) & np.isfinite(var) & (var > 0)
    if valid is not None:
        ok &= take(valid).astype(bool)
    wgt = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
    y = np.where(ok, meas, 0.0)
    d = _pixel_design(s, analyzer_rows, c, pix, (h, w))
    if d.ndim == 2:
        normal = (wgt[:, None, :] * d.T) @ d
        rhs = (wgt * y) @ d
    else:
        normal = (np.swapaxes(d, 1, 2) * wgt[:, None, :]) @ d
        rhs = np.einsum("pr,pri->pi", wgt * y, d)
    scale = 1.0 / np.sqrt(np.where(np.einsum("pii->pi", normal) > 0,
                                   np.einsum("pii->pi", normal), 1.0))
    eq = normal * scale[:, :, None] * scale[:, None, :]
    with np.errstate(all="ignore"):
        sv = np.linalg.svd(eq, compute_uv=False)
        regular = sv[:, -1] > 1e-12 * sv[:, 0]
        safe = np.where(regular[:, None, None], eq, np.eye(9))
        m_hat = np.linalg.solve(safe, (rhs * scale)[..., None])[..., 0] * scale
        m_hat = np.where(regular[:, None], m_hat, np.nan)
        pred = m_hat @ d.T if d.ndim == 2 else np.einsum("pri,pi->pr", d, m_hat)
        chi2 = np.einsum("pr,pr->p", wgt, np.where(ok, y - pred, 0.0) ** 2)
    return normal, m_hat, chi2, ok.sum(axis=1)


# ----------------------------------------------------------------------- selection
def select_models(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                  valid: np.ndarray | None, analyzer_rows, result: ReferenceResult,
                  options: SelectionOptions | None = None, *, chunk_pixels: int = 16384
                  ) -> tuple[ReferenceResult, ModelMaps]:
    """Test the candidate models at every pixel and colour of ``result`` (the reference or
    hybrid solve of the same samples: ``s_in``, ``measured``, ``variance``, ``valid``,
    ``analyzer_rows`` as :func:`polrig.solve.reference.solve_reference`) and estimate under the
    chosen one (module docstring). Returns a new result (arrays copied; the same dtypes) and
    the :class:`ModelMaps`."""
    opts = options or SelectionOptions()
    models = sorted((m for m in MODELS if m.name in opts.models), key=lambda m: m.n_params)
    crit = {m.code: chi2_critical(9 - m.n_params, opts.alpha) for m in models}
    n_col, h, w = result.mask.shape
    mueller, sigma = result.mueller.copy(), result.sigma.copy()
    with_cal = result.sigma_noise is not result.sigma
    sigma_noise = result.sigma_noise.copy() if with_cal else sigma
    residual, mask = result.residual.copy(), result.mask.copy()
    code = np.full((n_col, h, w), UNTESTED, np.uint8)
    stat = np.full((n_col, h, w), np.nan, np.float32)
    pval = np.full((n_col, h, w), np.nan, np.float32)
    flat = lambda a: a.reshape(a.shape[:-2] + (h * w,))  # noqa: E731
    for c in range(n_col):
        testable = ((result.mask[c] & ILL_CONDITIONED) == 0) & (
            result.pixel_condition[c] <= opts.max_condition)
        idx = np.flatnonzero(testable.ravel())
        for p0 in range(0, idx.size, max(1, int(chunk_pixels))):
            pix = idx[p0:p0 + chunk_pixels]
            normal, m_hat, chi2_full, n_ok = normal_equations(
                s_in, measured, variance, valid, analyzer_rows, c, pix)
            good = np.isfinite(m_hat).all(axis=1) & (n_ok >= 9)
            best = np.zeros(len(pix), np.int64)  # chosen code, 0 full
            best_k = np.full(len(pix), 10)
            best_p = np.full(len(pix), -1.0)
            best_q = np.full(len(pix), np.nan)
            top_p, top_q = np.full(len(pix), -1.0), np.full(len(pix), np.nan)
            fits = {}
            m0 = np.where(good[:, None], m_hat, 0.0)
            for model in models:  # fewest parameters first
                # a pixel that accepted a model with fewer parameters cannot choose this one:
                # fit only the others (the statistic of the skipped ones is not needed)
                need = np.flatnonzero(good & (best_k >= model.n_params))
                m_fit = np.full((len(pix), 9), np.nan)
                q = np.full(len(pix), np.nan)
                jac = np.zeros((len(pix), 9, model.n_params))
                if need.size:
                    m_fit[need], q[need], jac[need] = fit_model(
                        model, m0[need], normal[need], iterations=opts.iterations)
                q = np.where(good, np.clip(q, 0.0, None), np.nan)
                p = chi2_sf(q, 9 - model.n_params)
                fits[model.code] = (m_fit, jac, q, model.n_params)
                ok_p = np.where(np.isfinite(p), p, -1.0)
                higher = ok_p > top_p
                top_p, top_q = np.where(higher, ok_p, top_p), np.where(higher, q, top_q)
                accept = (q <= crit[model.code]) & np.isfinite(m_fit).all(axis=1)
                choose = accept & ((model.n_params < best_k)
                                   | ((model.n_params == best_k) & (ok_p > best_p)))
                best = np.where(choose, model.code, best)
                best_k = np.where(choose, model.n_params, best_k)
                best_p = np.where(choose, ok_p, best_p)
                best_q = np.where(choose, q, best_q)
            chosen = best > 0
            yy, xx = np.divmod(pix, w)
            code[c, yy, xx] = np.where(good, best, UNTESTED)
            stat[c, yy, xx] = np.where(good, np.where(chosen, best_q, top_q), np.nan)
            pval[c, yy, xx] = np.where(good, np.where(chosen, best_p, top_p), np.nan)
            for model_code, (m_fit, jac, q, k) in fits.items():
                sel = np.flatnonzero(best == model_code)
                if not sel.size:
                    continue
                py, px = yy[sel], xx[sel]
                cov = block_covariance(jac[sel], normal[sel])
                sd_noise = np.sqrt(np.clip(np.einsum("pii->pi", cov), 0.0, None))
                full_sg = flat(result.sigma[c])[:, :, pix[sel]].reshape(9, -1).T.astype(np.float64)
                full_sn = flat(result.sigma_noise[c])[:, :, pix[sel]].reshape(9, -1).T.astype(np.float64)
                sd = np.sqrt(sd_noise**2 + np.clip(full_sg**2 - full_sn**2, 0.0, None))
                mueller[c, :, :, py, px] = m_fit[sel].reshape(-1, 3, 3)
                sigma[c, :, :, py, px] = sd.reshape(-1, 3, 3)
                if with_cal:
                    sigma_noise[c, :, :, py, px] = sd_noise.reshape(-1, 3, 3)
                dof = n_ok[sel] - k
                residual[c, py, px] = np.where(dof > 0, (chi2_full[sel] + q[sel]) / np.maximum(dof, 1), 0.0)
                with np.errstate(invalid="ignore"):
                    dark = ~(m_fit[sel, 0] >= MIN_SNR * sd[:, 0])
                mask[c, py, px] = np.where(dark, mask[c, py, px] | DARK,
                                           mask[c, py, px] & ~np.uint8(DARK))
    maps = ModelMaps(code, stat, pval, opts)
    return ReferenceResult(mueller, sigma, residual, mask, result.condition_number,
                           result.pixel_condition, result.n_samples,
                           sigma_noise if with_cal else None, maps), maps


# ----------------------------------------------------------------------- files
#: What the model planes mean (a result header's ``planes`` entries).
MODEL_PLANES = {
    "model": "lower-order model chosen per pixel (codes in model_selection.codes; 0 full, "
             "255 untested)",
    "model_chi2": "likelihood-ratio statistic of the chosen model against the full block "
                  "(full: of the candidate with the largest p-value)",
    "model_p": "its p-value, P(chi^2(9 - k) > model_chi2)"}

def model_planes(maps: ModelMaps, colours: Sequence[str]) -> dict[str, np.ndarray]:
    """The EXR planes of the maps (:func:`polrig.formats.exr.colour_planes` naming):
    ``model.{colour}`` (codes, exact in float32), ``model_chi2.{colour}``, ``model_p.{colour}``."""
    out = {}
    for ci, col in enumerate(colours):
        out[f"model.{col}"] = maps.code[ci].astype(np.float32)
        out[f"model_chi2.{col}"] = maps.statistic[ci]
        out[f"model_p.{col}"] = maps.p_value[ci]
    return out


def selection_header(maps: ModelMaps) -> dict[str, object]:
    """Header entries recording the selection: the test, its level, the candidates, the
    code table and the pixel counts per model."""
    return {"model_selection": {
        "test": "likelihood ratio vs the full 3x3 block, chi^2(9 - k) (polrig.solve.model_selection)",
        "alpha": float(maps.options.alpha),
        "models": list(maps.options.models),
        "codes": {str(k): v for k, v in {**MODEL_CODES, UNTESTED: "untested"}.items()},
        "counts": maps.counts(),
    }}
