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
model_selection`` measure; at two states ``tests/test_model_selection_two_states.py``, with
``N'`` for ``N``). Where the full block holds, accepting a reduced model is wrong
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
would shrink it too), plus the model's bias, the residual ``(chi^2_full + Lambda) / (n - k)``
and the ``DARK`` bit re-evaluated.

*The model's bias in the sigma.* An accepted model is only not detectably wrong: the truth
may sit off it by up to the test's power point, a bias the delta method's sigma does not hold.
So the chosen model's ``sigma^2`` adds, per element, the squared difference ``(m_red -
m_full)^2`` of the two estimates: the model-selection term of Buckland, Burnham and Augustin
(1997, *Biometrics* 53, 603; a model's variance plus its estimate's squared distance from the
reference one), the full block, unbiased under every candidate, as the reference.
``sigma_noise`` (the sensor noise alone) does not. Measured (``python -m benchmarks
model_selection``, 4 states; elements within 2 sigma, full -> selected): without the term
72-86 % on the held-out sets and 81 % on the synthetic off-model truths; with it 93.6-96.2 % and
93.5 %, at the price of 96.3-98.9 % where a model holds exactly (synthetic truths of each model).
Two sharper estimates of the bias were measured and left, because the held-out sets' pixels
sit near the test's power point, where a single pixel's ``d`` cannot tell bias from noise: the
positive part of the unbiased estimate ``d^2 - (v_full - v_red)`` (``Var(d) = v_full - v_red``
where the model holds, Hausman 1978, *Econometrica* 46, 1251, Lemma 2.1): 70 % on the off-model
truths, 89.8 % on one held-out set; and ``d^2`` shrunk by ``max(0, 1 - (9 - k) / Lambda)``: 73 %.
The RMSE is the estimate's and does not change.

**Which pixels are tested**: those the samples alone determine (not ``ILL_CONDITIONED``, the
used samples' condition number at most ``max_condition``, at least 9 finite samples); with the
hybrid solve's prior (``prior``, ``seen_state``) also those whose samples observe 6 to 8 of the
nine directions (below); the others are coded :data:`UNTESTED` with a NaN statistic.

**At any rank: two states with the prior.** Two states observe ``M s_a`` and ``M s_b`` (each
DoFP frame three numbers per colour): the design ``D`` has rank ``r = 6``, ``N`` is singular
and its null space, the block's response to the incident direction ``n = s_a x s_b``, is not
seen by the samples (:func:`row_space_equations`: rank, condition within the row space, a
least-squares solution ``m_hat``; ``chi^2(m) = chi^2(m_hat) + (m - m_hat)^T N (m - m_hat)``
still holds exactly, for any least-squares ``m_hat``).

*Samples alone* the statistic would be ``Lambda_s = min q`` on that singular ``N``, ``chi^2(r -
k)`` where the model's parameters are identifiable from the samples (its Jacobian projected on
``D``'s row space of rank ``k``). That route was built and measured, and dropped: on an
orthogonal pair (``0/90``, the best two-state set) every candidate has a second minimum ``M H``
of the same ``q`` (``H`` the reflection that fixes ``s_a`` and ``s_b``; every model is closed
under it), a retarder and a depolarizer reproduce the same observed columns, a five-parameter
model keeps one degree of freedom, and ``rank_one`` is identifiable from no pair of states (the
diattenuation along ``n`` is unobserved). On synthetic truths of each model (20x20, a 5 % prior)
its estimate's RMSE was 1.5-4.2 times the hybrid's where it accepted a model that agreed on the
samples and not off them.

*With the prior* (the route). The hybrid solve (:mod:`polrig.solve.hybrid`) counts the
network's estimate ``mu`` as Gaussian information of precision ``P`` on the directions the
seen frame leaves unobserved (:func:`polrig.solve.hybrid.unobserved_precision`, block diagonal
over the rows). Its ``-2 log`` posterior of a block is

    chi^2(m) + (m - mu)^T P (m - mu) = const + (m - m')^T N' (m - m'),
    N' = N + P,   m' = N'^-1 (N m_hat + P mu)

(:func:`posterior_system`; ``N'`` is regular and ``m'`` is the hybrid's posterior mean). So the
likelihood ratio of a model against the full block, with the prior counted as the observations
it stands for, is ``Lambda = min_theta (m(theta) - m')^T N' (m(theta) - m')``: the statistic
above with ``(N', m')`` for ``(N, m_hat)``, ``chi^2(9 - k)`` where the model holds and the prior
is calibrated in the hybrid's model (exact for a linear model: ``m' - m_true ~ N(0, N'^-1)``;
Wilks' first order otherwise). It runs on the same fits, kernel and critical values, and every
model is identifiable (``N'`` regular): what the samples leave open, the mirror minimum
included, the prior decides (the fits start from ``m'``). Measured level on truths of each
model with a prior calibrated that way: 4.3-5.3 % (``tests/test_model_selection_two_states.py``).
Against the prior's marginal on ``N``'s null space alone (the samples completed where they see
nothing), the hybrid's ``P`` also weighs the prior on the second state's directions: 0.2-0.8 dB
more PSNR where a model holds (3 held-out sets x 16 samples).

Of the accepted models at these pixels the one with the largest p-value is chosen, not the
fewest parameters (the rule at rank 9, kept there bit for bit): with the shipped network's
prior, the fewest-parameter rule accepted the unpolarizing model on faintly polarized diffuse
pixels whose bias then exceeded the noise it removed (unseen terrain, 4 samples: 41.65 against
41.81 dB over the object, 79 against 87 % within 2 sigma). The estimate's covariance is the
delta method's with ``N'`` (prior included), the residual ``(chi^2_samples + Lambda) / (n -
k)``. Tested where the rank is 6 to 8 (:data:`MIN_RANK`: one state's three directions leave
only the unpolarizing model), the row space's condition number at most ``max_condition``, the
prior finite and positive at all nine elements, and the seen frame's four samples used (the
prior's projection assumes it whole). The level on real scenes is that of the prior's
calibration: ``python -m polrig.models.continuum --models-only`` measures it on the held-out sets
(``benchmarks/results/continuum_models.md``, the shipped network's joint prior): false
acceptance 1.3 % on the terrains but 7-22 % elsewhere (the network's errors are not calibrated
in the hybrid's model), +4.1..+12.1 dB over single-shot where a model holds, and 92.4-94.7 % of
the elements within 2 sigma (80-84 % before the selection term above). No single level fixes
it: at a level of 0.2 instead of 0.05 the seen families' false acceptance falls to 4.4 % and
unseen compact's to 1.5 %, the films + depolarizing layers' stays at 33 % (12 % at 0.7, where
a model that holds is accepted on 71 % of its pixels; 16 samples each, per-element prior).
Because that false acceptance exceeds the level, captures and ``polrig reconstruct`` do not
pass the prior here
(:func:`polrig.solve.radiometry.reference_from_frames`): with two states their pixels stay
``UNTESTED``; this route serves the benchmark. The prior calibrated jointly
(``prior_correlation``, :mod:`polrig.solve.hybrid` "Joint prior") gives the test its level on
data drawn from that model (``tests/test_hybrid_joint.py``) but not on the network's errors:
1.3-21.9 % per held-out set (``python -m polrig.models.continuum --joint-compare``,
``benchmarks/results/continuum_joint.md``), where the network's estimate itself leans toward a
lower-order block that the truth is not. The one model the two-state completion needs, the
diffuse term, is tested on the samples alone instead by :mod:`polrig.solve.diffuse_test`, whose
decision this module takes as given (``decided``) to estimate under ``rank_one``.

Never silent: nothing here runs unless asked (``polrig reconstruct --models auto``,
``polrig capture --models auto``); the result then always carries the maps
(:class:`ModelMaps`: ``model.{colour}`` codes, ``model_chi2.{colour}`` the statistic,
``model_p.{colour}`` its p-value, :func:`model_planes`) and the header records the test.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from polrig.choices import MODEL_CHOICES as _MODEL_CHOICES
from polrig.errors import ConfigError
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve.chunks import in_chunks
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
           "normal_equations", "row_space_equations", "RowSpace", "posterior_system", "MIN_RANK",
           "MODEL_CHOICES", "MODEL_PLANES"]

#: Model map code of a pixel that was not tested (its samples do not determine the block).
UNTESTED = 255

#: The ``--models`` choices: ``full`` (no selection, the default), ``auto`` (this module) and
#: ``diffuse`` (two states: :mod:`polrig.solve.diffuse_test`), from :mod:`polrig.choices`.
MODEL_CHOICES = _MODEL_CHOICES


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
    of central ones with ``df + 2 j`` degrees of freedom, all ``j`` at once: their tails follow
    from ``chi2_sf(x, df)`` by the recursion of :func:`chi2_sf`, ``Q(s + 1, y) = Q(s, y) + y^s
    e^-y / Gamma(s + 1)``, summed cumulatively. The Poisson weights are kept out to ``lam / 2 +
    12 sqrt(lam / 2) + 40`` (the mass beyond is below 1e-15)."""
    half, y, s0 = lam / 2.0, max(float(x), 0.0) / 2.0, df / 2.0
    n = int(half + 12.0 * math.sqrt(half) + 40.0)
    j = np.arange(n, dtype=np.float64)
    log_factorial = np.concatenate([[0.0], np.cumsum(np.log(j[1:]))])  # lgamma(j + 1)
    if half > 0:
        weights = np.exp(-half + j * math.log(half) - log_factorial)
    else:
        weights = (j == 0).astype(np.float64)
    tails = np.full(n, float(chi2_sf(np.array(x, np.float64), df)))
    if y > 0 and n > 1:
        # lgamma(s0 + j + 1) for j = 0 .. n - 2, by lgamma(s + 1) = lgamma(s) + log s
        log_gamma = math.lgamma(s0 + 1.0) + np.concatenate([[0.0], np.cumsum(np.log(s0 + j[1:-1]))])
        tails[1:] += np.cumsum(np.exp((s0 + j[:-1]) * math.log(y) - y - log_gamma))
    return float(np.sum(weights * np.clip(tails, 0.0, 1.0)))


@lru_cache(maxsize=64)
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
    normal, rhs, d, wgt, y, ok = _weighted_system(s_in, measured, variance, valid, analyzer_rows, c, pix)
    scale, eq = _equilibrated(normal)
    with np.errstate(all="ignore"):
        sv = np.linalg.svd(eq, compute_uv=False)
        regular = sv[:, -1] > 1e-12 * sv[:, 0]
        safe = np.where(regular[:, None, None], eq, np.eye(9))
        m_hat = np.linalg.solve(safe, (rhs * scale)[..., None])[..., 0] * scale
        m_hat = np.where(regular[:, None], m_hat, np.nan)
    return normal, m_hat, _chi2(m_hat, d, wgt, y, ok), ok.sum(axis=1)


def _weighted_system(s_in, measured, variance, valid, analyzer_rows, c: int, pix: np.ndarray):
    """``(N, D^T W y, D, w, y, used)`` of pixels ``pix`` of colour ``c`` (float64; ``D``
    shared ``(4 n, 9)`` or per pixel ``(P, 4 n, 9)``; ``w``, ``y``, ``used`` ``(P, 4 n)``)."""
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
    return normal, rhs, d, wgt, y, ok


def _equilibrated(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(S, S N S)``: Jacobi scaling ``S = diag(N)^-1/2`` (1 where the diagonal is 0)."""
    scale = 1.0 / np.sqrt(np.where(np.einsum("pii->pi", normal) > 0,
                                   np.einsum("pii->pi", normal), 1.0))
    return scale, normal * scale[:, :, None] * scale[:, None, :]


def _chi2(m_hat, d, wgt, y, ok) -> np.ndarray:
    """``sum w (y - D m_hat)^2`` over the used samples ``(P,)``."""
    with np.errstate(all="ignore"):
        pred = m_hat @ d.T if d.ndim == 2 else np.einsum("pri,pi->pr", d, m_hat)
        return np.einsum("pr,pr->p", wgt, np.where(ok, y - pred, 0.0) ** 2)


@dataclass(frozen=True, eq=False)
class RowSpace:
    """The samples' weighted least squares of ``P`` pixels at any rank of the design
    (:func:`row_space_equations`), float64: ``normal`` ``(P, 9, 9)`` ``N = D^T W D``;
    ``m_hat`` ``(P, 9)`` a least-squares solution (the pseudo-inverse's, in the equilibrated
    coordinates); ``chi2`` ``(P,)`` its ``chi^2``; ``n_used`` ``(P,)``; ``rank`` ``(P,)``
    ``r = rank N``; ``condition`` ``(P,)`` the equilibrated design's condition number within
    its row space; ``used`` ``(P, 4 n)`` which samples are used; ``null`` ``(P, 9, 9)`` an orthonormal basis of ``N``'s null space in its first ``9 - r``
    columns (zeros after)."""

    normal: np.ndarray
    m_hat: np.ndarray
    chi2: np.ndarray
    n_used: np.ndarray
    rank: np.ndarray
    condition: np.ndarray
    used: np.ndarray


#: relative eigenvalue of the equilibrated normal matrix below which a direction counts as
#: unobserved (a singular value of the design 1e-6 of its largest)
RANK_TOLERANCE = 1e-12


def row_space_equations(s_in, measured, variance, valid, analyzer_rows, c: int,
                        pix: np.ndarray) -> RowSpace:
    """:func:`normal_equations` for a design of any rank (module docstring, "At any rank"):
    the eigendecomposition of the equilibrated ``S N S = V w V^T`` gives the rank (eigenvalues
    above :data:`RANK_TOLERANCE` of the largest) and ``m_hat = S V w^+ V^T S D^T W y``."""
    normal, rhs, d, wgt, y, ok = _weighted_system(s_in, measured, variance, valid, analyzer_rows, c, pix)
    scale, eq = _equilibrated(normal)
    with np.errstate(all="ignore"):
        w_eig, v = np.linalg.eigh(eq)  # ascending
        top = w_eig[:, -1:]
        kept = w_eig > RANK_TOLERANCE * np.where(top > 0, top, np.inf)
        rank = kept.sum(axis=1)
        inv_w = np.where(kept, 1.0 / np.where(kept, w_eig, 1.0), 0.0)
        m_hat = scale * np.einsum("pij,pj,pkj,pk->pi", v, inv_w, v, rhs * scale)
        smallest = np.where(kept, w_eig, np.inf).min(axis=1)
        condition = np.sqrt(top[:, 0] / smallest)
    return RowSpace(normal, m_hat, _chi2(m_hat, d, wgt, y, ok), ok.sum(axis=1), rank, condition, ok)


# ----------------------------------------------------------------------- selection
@dataclass
class _Outputs:
    """The arrays :func:`select_models` writes (copies of the result's) and the result."""

    result: ReferenceResult
    mueller: np.ndarray
    sigma: np.ndarray
    sigma_noise: np.ndarray
    residual: np.ndarray
    mask: np.ndarray

    def write(self, c: int, pix: np.ndarray, w: int, m_fit: np.ndarray, cov: np.ndarray,
              chi2_full: np.ndarray, q: np.ndarray, n_ok: np.ndarray, k: int) -> None:
        """The estimate under a chosen model at pixels ``pix`` (flat) of colour ``c``: block
        ``m_fit`` ``(P, 9)``, its noise covariance ``cov`` ``(P, 9, 9)``, the calibration part
        of the full result's sigma kept, the model's estimated bias added to ``sigma`` (module
        docstring), residual ``(chi2_full + q) / (n_ok - k)``, ``DARK``
        re-evaluated (module docstring)."""
        py, px = np.divmod(pix, w)
        flat = lambda a: a.reshape(a.shape[:-2] + (-1,))  # noqa: E731
        sd_noise = np.sqrt(np.clip(np.einsum("pii->pi", cov), 0.0, None))
        full_sg = flat(self.result.sigma[c])[:, :, pix].reshape(9, -1).T.astype(np.float64)
        full_sn = flat(self.result.sigma_noise[c])[:, :, pix].reshape(9, -1).T.astype(np.float64)
        full_m = flat(self.result.mueller[c])[:, :, pix].reshape(9, -1).T.astype(np.float64)
        bias2 = (m_fit - full_m) ** 2  # the model-selection term (module docstring)
        bias2 = np.where(np.isfinite(bias2), bias2, 0.0)
        sd = np.sqrt(sd_noise**2 + np.clip(full_sg**2 - full_sn**2, 0.0, None) + bias2)
        self.mueller[c, :, :, py, px] = m_fit.reshape(-1, 3, 3)
        self.sigma[c, :, :, py, px] = sd.reshape(-1, 3, 3)
        self.sigma_noise[c, :, :, py, px] = sd_noise.reshape(-1, 3, 3)
        dof = n_ok - k
        self.residual[c, py, px] = np.where(dof > 0, (chi2_full + q) / np.maximum(dof, 1), 0.0)
        with np.errstate(invalid="ignore"):
            dark = ~(m_fit[:, 0] >= MIN_SNR * sd[:, 0])
        self.mask[c, py, px] = np.where(dark, self.mask[c, py, px] | DARK,
                                        self.mask[c, py, px] & ~np.uint8(DARK))


def select_models(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                  valid: np.ndarray | None, analyzer_rows, result: ReferenceResult,
                  options: SelectionOptions | None = None, *, chunk_pixels: int = 16384,
                  prior: tuple[np.ndarray, np.ndarray] | None = None, seen_state: int | None = None,
                  prior_correlation: np.ndarray | None = None, decided: np.ndarray | None = None
                  ) -> tuple[ReferenceResult, ModelMaps]:
    """Test the candidate models at every pixel and colour of ``result`` (the reference or
    hybrid solve of the same samples: ``s_in``, ``measured``, ``variance``, ``valid``,
    ``analyzer_rows`` as :func:`polrig.solve.reference.solve_reference`) and estimate under the
    chosen one (module docstring). Returns a new result (arrays copied; the same dtypes) and
    the :class:`ModelMaps`.

    ``prior``: ``(mean, sigma)``, ``(C, 3, 3, H, W)`` (or broadcastable), and ``seen_state``:
    the hybrid solve's prior and seen state (:func:`polrig.solve.hybrid.solve_hybrid`). With
    them, the pixels whose samples observe only some of the block's directions (rank 6 to 8:
    two states, or three with samples missing) are tested too, on the hybrid's posterior
    system (module docstring, "At any rank"); without them those stay :data:`UNTESTED`. A pixel
    the samples alone determine is tested as without a prior. ``prior_correlation``: the joint
    prior's ``K`` (:func:`polrig.solve.hybrid.solve_hybrid`'s; None: the per-element prior).

    ``decided`` ``(C, H, W)`` bool: the caller's own test decided, and this module only
    estimates: a candidate counts as accepted exactly where ``decided`` holds (and its fit is
    finite), whatever its statistic (which the maps hold there), e.g. the diffuse term tested on
    two states' samples alone (:mod:`polrig.solve.diffuse_test`) with ``options.models =
    ("rank_one",)``. Elsewhere nothing is fitted: the full block as given, code ``0`` (where not
    ill-conditioned), no statistic.

    ``chunk_pixels``: the most pixels a chunk's systems hold (its memory); the chunks run side by
    side on the CPUs (:func:`_in_pixel_chunks`), and the results do not depend on the threads."""
    opts = options or SelectionOptions()
    models = sorted((m for m in MODELS if m.name in opts.models), key=lambda m: m.n_params)
    crit = {m.code: chi2_critical(9 - m.n_params, opts.alpha) for m in models}
    n_col, h, w = result.mask.shape
    # the model's term enters sigma and not sigma_noise: the result keeps both (a copy of the
    # noise sigma where the input had one sigma)
    out = _Outputs(result, result.mueller.copy(), result.sigma.copy(), result.sigma_noise.copy(),
                   result.residual.copy(), result.mask.copy())
    code = np.full((n_col, h, w), UNTESTED, np.uint8)
    stat = np.full((n_col, h, w), np.nan, np.float32)
    pval = np.full((n_col, h, w), np.nan, np.float32)
    if prior is not None:
        prior = tuple(np.broadcast_to(np.asarray(a), (n_col, 3, 3, h, w)) for a in prior)
    if decided is not None:
        decided = np.broadcast_to(np.asarray(decided, bool), (n_col, h, w))
    for c in range(n_col):
        solved = (result.mask[c] & ILL_CONDITIONED) == 0
        if decided is not None:  # the caller's test rejected: the full block, nothing to fit
            code[c][solved & ~decided[c]] = 0
            solved = solved & decided[c]
        testable = solved & (result.pixel_condition[c] <= opts.max_condition)

        def full_rank(pix: np.ndarray, c: int = c) -> None:
            normal, m_hat, chi2_full, n_ok = normal_equations(
                s_in, measured, variance, valid, analyzer_rows, c, pix)
            good = np.isfinite(m_hat).all(axis=1) & (n_ok >= 9)
            _test_and_write(models, crit, opts, c, pix, w, normal, m_hat, chi2_full, n_ok, good,
                            out, code, stat, pval, decided=None if decided is None else decided[c].ravel()[pix])

        def row_space(pix: np.ndarray, c: int = c) -> None:
            _select_row_space(s_in, measured, variance, valid, analyzer_rows, c, pix, w, models,
                              crit, opts, prior, out, code, stat, pval, seen_state, prior_correlation,
                              None if decided is None else decided[c].ravel()[pix])

        _in_pixel_chunks(np.flatnonzero(testable.ravel()), chunk_pixels, full_rank)
        if prior is not None:
            _in_pixel_chunks(np.flatnonzero((~testable & solved).ravel()), chunk_pixels, row_space)
    maps = ModelMaps(code, stat, pval, opts)
    return ReferenceResult(out.mueller, out.sigma, out.residual, out.mask, result.condition_number,
                           result.pixel_condition, result.n_samples, out.sigma_noise, maps), maps


def _in_pixel_chunks(idx: np.ndarray, chunk_pixels: int, work: Callable[[np.ndarray], None]) -> None:
    """``work(pix)`` for the consecutive chunks ``pix`` of at most ``chunk_pixels`` of the flat
    pixel indices ``idx``, the chunks side by side on the CPUs (:func:`polrig.solve.chunks.in_chunks`;
    each chunk writes its own pixels and is computed as alone, so the results do not depend on
    the threads)."""
    size = max(1, int(chunk_pixels))
    n_chunks = -(-idx.size // size)

    def run(sl: slice) -> None:
        for i in range(sl.start, sl.stop):
            work(idx[i * size:(i + 1) * size])

    if n_chunks:
        in_chunks(n_chunks, run, min_pixels=1, name="model-selection")


def _test_and_write(models, crit, opts: SelectionOptions, c: int, pix: np.ndarray, w: int,
                    normal: np.ndarray, m_hat: np.ndarray, chi2_full: np.ndarray, n_ok: np.ndarray,
                    good: np.ndarray, out: _Outputs, code, stat, pval, prefer_p: bool = False,
                    decided: np.ndarray | None = None) -> None:
    """The test against the full block of the full-rank system ``(normal, m_hat)`` at pixels
    ``pix`` (flat) of colour ``c`` where ``good``, the maps and the estimate written. Of the
    accepted models the one with the fewest parameters (ties: the larger p-value), or with
    ``prefer_p`` the one with the largest p-value (module docstring, "At any rank").
    ``decided`` ``(P,)``: accepted there and only there (:func:`select_models`)."""
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
        need = np.flatnonzero(good & ((best_k >= model.n_params) | prefer_p))
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
        accept = ((q <= crit[model.code]) if decided is None else decided) & np.isfinite(m_fit).all(axis=1)
        if prefer_p:
            choose = accept & (ok_p > best_p)
        else:
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
        if sel.size:
            out.write(c, pix[sel], w, m_fit[sel], block_covariance(jac[sel], normal[sel]),
                      chi2_full[sel], q[sel], n_ok[sel], k)


#: the least rank of the samples' design at which a pixel is tested on the hybrid's posterior
#: system (two states' six directions; one state's three are left untested)
MIN_RANK = 6
def _select_row_space(s_in, measured, variance, valid, analyzer_rows, c: int, pix: np.ndarray,
                      w: int, models, crit, opts: SelectionOptions, prior, out: _Outputs, code,
                      stat, pval, seen_state=None, correlation=None, decided: np.ndarray | None = None) -> None:
    """The test and the estimate at pixels ``pix`` of colour ``c`` whose samples leave some
    of the block's directions unobserved (module docstring, "At any rank"); ``decided``
    ``(P,)`` as :func:`_test_and_write`'s."""
    rs = row_space_equations(s_in, measured, variance, valid, analyzer_rows, c, pix)
    yy, xx = np.divmod(pix, w)
    take = lambda a: np.asarray(a[c])[:, :, yy, xx].reshape(9, -1).T.astype(np.float64)  # noqa: E731
    mean, sd = take(prior[0]), take(prior[1])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        precision = np.where((sd > 0) & np.isfinite(sd) & np.isfinite(mean), 1.0 / (sd * sd), 0.0)
    precision = np.where(np.isfinite(precision), precision, 0.0)
    mean = np.where(precision > 0, mean, 0.0)
    good = (np.isfinite(rs.m_hat).all(axis=1) & (rs.rank >= MIN_RANK) & (rs.rank < 9)
            & (rs.condition <= opts.max_condition) & (rs.n_used >= rs.rank))
    g = good & (precision > 0).all(axis=1)
    s_seen = None
    if seen_state is not None:  # the prior's projection assumes the seen frame used whole
        s_seen = np.asarray(s_in, np.float64)[seen_state]
        g &= rs.used[:, 4 * seen_state:4 * seen_state + 4].all(axis=1)
    g = np.flatnonzero(g)
    if not g.size:
        return
    normal, m_post = posterior_system(rs.normal[g], rs.m_hat[g], mean[g], 1.0 / np.sqrt(precision[g]), s_seen,
                                      correlation)
    _test_and_write(models, crit, opts, c, pix[g], w, normal, m_post, rs.chi2[g], rs.n_used[g],
                    np.ones(g.size, bool), out, code, stat, pval, prefer_p=True,
                    decided=None if decided is None else decided[g])


def prior_precision(sigma: np.ndarray, s_seen=None, correlation: np.ndarray | None = None) -> np.ndarray:
    """The hybrid solve's prior precision ``(P, 9, 9)`` float64 of ``P`` pixels whose prior sigma is
    ``sigma`` ``(P, 9)`` (positive and finite): :func:`polrig.solve.hybrid.unobserved_precision`
    per row with the seen state ``s_seen``'s frame used whole, block diagonal over the rows, or,
    as the kernel takes it, joint with ``correlation`` (:func:`polrig.solve.hybrid.joint_precision`)
    where given and ``s_seen`` has an axis."""
    from polrig.solve.hybrid import joint_precision, observed_direction, plane_axis, unobserved_precision

    rows = unobserved_precision(np.asarray(sigma, np.float64).reshape(-1, 3, 3), s_seen)  # (P, row, 3, 3)
    if correlation is not None and s_seen is not None and plane_axis(observed_direction(s_seen)) is not None:
        return joint_precision(rows, s_seen, correlation)
    prec = np.zeros((len(rows), 9, 9))
    for r in range(3):
        prec[:, 3 * r:3 * r + 3, 3 * r:3 * r + 3] = rows[:, r]
    return prec


def posterior_system(normal: np.ndarray, m_hat: np.ndarray, mean: np.ndarray, sigma: np.ndarray,
                     s_seen=None, correlation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The hybrid solve's posterior system of ``P`` pixels (module docstring, "At any rank"):
    ``N' = N + P`` ``(P, 9, 9)`` and the posterior mean ``m' = N'^-1 (N m_hat + P mu)``
    ``(P, 9)``, float64, with the hybrid's prior precision ``P``
    (:func:`polrig.solve.hybrid.unobserved_precision`, block diagonal over the rows; the seen
    state ``s_seen``'s frame used whole). ``normal``, ``m_hat``: the samples' (any rank);
    ``mean``, ``sigma`` ``(P, 9)``: the prior's, sigma positive and finite. ``correlation``: the
    joint prior's ``K`` (:func:`polrig.solve.hybrid.joint_precision`; used where ``s_seen`` has
    an axis, as the hybrid solve does), None the per-element prior."""
    prec = prior_precision(sigma, s_seen, correlation)
    total = normal + prec
    rhs = np.einsum("pij,pj->pi", normal, m_hat) + np.einsum("pij,pj->pi", prec, mean)
    return total, np.linalg.solve(total, rhs[..., None])[..., 0]


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
        "test": "likelihood ratio vs the full 3x3 block, chi^2(9 - k) (polrig.solve.model_selection; "
                "with fewer than 9 observed directions, on the hybrid's posterior system)",
        "alpha": float(maps.options.alpha),
        "models": list(maps.options.models),
        "codes": {str(k): v for k, v in {**MODEL_CODES, UNTESTED: "untested"}.items()},
        "counts": maps.counts(),
    }}
