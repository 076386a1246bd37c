"""N-state reference Mueller solve: per pixel and colour, the 3x3 linear block from all
``N x 4`` analyzer measurements, with uncertainty, residual, condition numbers and masks.

Measurement model (``docs/conventions.md``: Stokes, analyzer order 0/45/90/135 deg, units):
for polarizer state ``k`` with incident linear Stokes vector ``s_k`` (normalised units, section
"Radiometric units") and analyzer ``j`` with row ``a_j`` (ideal: ``[1, cos 2t, sin 2t] / 2``),
the black-subtracted intensity is

    I_kj = a_j^T M s_k = kron(a_j, s_k) . vec(M)        (vec row-major: m00, m01, ..., m22)

so all ``4 N`` samples of a pixel give a linear system ``D vec(M) = I`` with the design matrix
``D`` of rows ``kron(a_j, s_k)`` (:func:`design_matrix`). It is solved by weighted least squares
with weights ``w = 1 / variance`` per sample: ``vec(M) = (D^T W D)^-1 D^T W I``, covariance
``(D^T W D)^-1`` (whose diagonal gives :attr:`ReferenceResult.sigma`) and
``chi^2 / dof = sum w r^2 / (n - 9)`` (:attr:`ReferenceResult.residual`; about 1 when the noise
model is right).

**Why measurements, not Stokes images.** Solving from the ``N`` Stokes images (one 3x4 pseudo-
inverse per state, then ``N`` (S_in, S_out) pairs) would weight the states equally although
their analyzer samples differ in variance by orders of magnitude (shot noise follows the
signal, so a crossed state is far less noisy than a parallel one), would ignore the correlation
that the Stokes inversion introduces between ``S0, S1, S2``, and would have to discard a whole
state whenever one of its four analyzer samples is saturated. Working on the ``4 N`` samples
weights each by its own variance and drops saturated or bad samples individually; the other
samples of the same state still count.

**How it is solved, and why so** (:mod:`polrig.solve._reference_kernel`). Per pixel the normal
equations have the Kronecker structure ``D^T W D = sum_j (a_j a_j^T) (x) T_j`` with
``T_j = sum_k w_kj s_k s_k^T``, so they cost about 0.4 kflop to form; an equilibrated Cholesky
factorisation, the inverse factor, the residual and (with calibration tolerances) the 14
calibration right-hand sides add about 2 kflop, from about 200 bytes of samples. The work is
compiled with numba and fused: a tile of image rows is read once (float32 or float64 samples
in place, never copied or upcast as a whole array), converted to float64 in blocks of 64
neighbouring pixels laid out lanes-last, and every step runs as SIMD loops over the lanes;
tiles run on a thread pool (the kernels release the GIL). Memory beyond the outputs is a few
MB of tile buffers per thread. On this project's 2-core machine that is 15-20x faster than
the previous numpy implementation (chunked, with a batched Cholesky in pixels-last layout;
kept as :mod:`polrig.solve._reference_numpy`, the tests' oracle and the benchmark's baseline);
``python -m benchmarks reference`` gives the numbers.

numba earns its place as a dependency: numpy alone cannot fuse the per-pixel 9x9 algebra
(each step becomes a pass over memory, about 40 of them), and a fixed pseudo-inverse that
would reduce the solve to a matrix product throws information away: with the sensor's shot
noise, the unweighted solve of 4 states 0/45/90/135 has 1.1-1.4x the variance of the weighted
one for random physical samples (median 1.10) and 1.5-3x for polarizer-like samples
(measured over 2000 samples of each), i.e. that many more frames for the same precision,
besides being unable to drop saturated samples without per-pattern inverses. The compiled
kernels are cached on disk (numba ``cache=True``: the first call on a machine compiles them,
about 10 s; later processes load them in well under a second; without a writable cache
directory they are compiled in each process). The compute kernel has one signature (float64
buffers), so other input or output dtypes only add the small load and store kernels.
Results are bit-identical for any thread count and tile size.

Masks (:data:`DARK`, :data:`SATURATED`, :data:`ILL_CONDITIONED`, :data:`NONFINITE` bit flags,
uint8 ``(C, H, W)``, names via :func:`reason_names`): a pixel with ``mask == 0`` is good.
``SATURATED`` and ``NONFINITE`` mean that samples were excluded (invalid in the given mask, or
non-finite value/variance, or variance <= 0); the pixel is still solved from the rest when they
determine ``M`` well. ``ILL_CONDITIONED`` means the remaining samples do not (condition number
of the remaining design above ``max_condition``, fewer than 9 samples, or a normal matrix that
is not positive definite to working precision), or that the estimate, its sigma or the
residual is not finite or does not fit the output dtype (e.g. beyond float32's 3.4e38): its
Mueller matrix, sigma and residual are 0 (finite, never NaN or inf). ``DARK`` means ``m00``
is below ``min_snr`` times its own standard deviation; the estimate is kept.

**Calibration uncertainty** (:func:`solve_reference` ``analyzer_tolerance`` /
``generator_tolerance``). The solve assumes analyzer rows ``A0`` and incident states ``S``; the
real ones differ by calibration errors that are the *same* for every sample of a capture, so
their effect on ``M`` does not average out with frames and is not in ``(D^T W D)^-1``. To first
order, true samples ``I = (D + dD) vec(M)`` give the estimate
``vec(M_hat) = G I = vec(M) + G dD vec(M)`` with ``G = (D^T W D)^-1 D^T W``; a calibration
parameter ``p`` with sample sensitivity ``e_p = (dD/dp) vec(M)`` (a ``4N`` vector) moves the
estimate by ``dvec(M)/dp = G e_p``, i.e. one more right-hand side ``D^T W e_p`` of the same
normal equations. Parameters are independent, so
``sigma_cal^2 = sum_p sigma_p^2 (G e_p)^2`` per element, evaluated at the estimated ``M``;
because each ``e_p`` spans all states at once, the full correlation of a calibration error
across states (and across the four analyzers for the generator) is kept. The reported
``sigma`` is ``sqrt(sigma_noise^2 + sigma_cal^2)``; ``sigma_noise`` keeps the noise part.

* Analyzer ``j`` (row ``a_j = g_j/2 [1, D_j cos 2t_j, D_j sin 2t_j]``): relative gain
  (``da/dg = a``), orientation (``da/dt = [0, -2 a_2, 2 a_1]`` per rad) and diattenuation
  (``da/dD = a_0 [0, cos 2t, sin 2t]``), independent per micro-polarizer class, 12 parameters;
  ``e[k, j'] = delta_jj' (da_j . M s_k)``. For the unweighted solve (``W = I``, all samples) this
  is exactly ``dM = A0^+ dA M`` (``D = A0 (x) S`` and ``G = A0^+ (x) S^+``, ``S^+ S = I``), hence
  ``var(dM_il) = sum_j (A0^+_ij)^2 [s_g^2 (a_j . M_:l)^2 + s_t^2 (a_j' . M_:l)^2 +
  s_D^2 (da_j/dD . M_:l)^2]``. The per-pixel tolerance is applied to each demosaiced row
  without dividing by the number of averaged sensor pixels: part of a real sensor's error
  (per-angle orientation bias, mean diattenuation) is common to all of them.
* Generator: stage zero offset ``phi`` (rotates every state, ``ds/dphi = [0, -2 s_2, 2 s_1]``
  per rad) and inverse extinction ratio ``e = 1/ER`` (``s = [(1 + e), (1 - e) u] / 2`` for a
  polarizer with unit transmission axis ``u = (cos 2theta, sin 2theta)``, so
  ``ds/de = [1, -u] / 2``); ``e[k, j] = a_j . M ds_k``. Unweighted this is
  ``dM = M dS^T (S^+)^T`` (``A0^+ A0 = I``).

This is linear propagation about the assumed values (first-order Taylor series, GUM,
JCGM 100:2008, section 5.1); second-order terms are neglected, which at tolerances of degrees
and percent keeps the coverage of ``2 sigma`` near 95 % (checked in
``tests/test_reference.py`` with errors drawn from the tolerances). The 14 extra right-hand
sides (solved with the explicit inverse: an analyzer parameter of row ``j`` through
``A^-1 (a_j (x) I_3)``, shared by its three parameters) make the solve about 1.7x slower; an
exact calibration (zero tolerances) skips them.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from polrig.choices import MIN_SNR
from polrig.errors import ConfigError
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import ideal_analyzer_matrix

__all__ = [
    "DARK", "SATURATED", "ILL_CONDITIONED", "NONFINITE", "REASONS", "reason_names",
    "DEFAULT_MAX_CONDITION",
    "ReferenceResult", "AnalyzerTolerance", "GeneratorTolerance",
    "design_matrix", "condition_number", "validate_states",
    "forward_measurements", "solve_reference", "average_frames", "merge_hdr",
]

DARK = 1  #: m00 below ``min_snr`` standard deviations (estimate kept)
SATURATED = 2  #: some samples excluded by the validity mask (saturated or bad)
ILL_CONDITIONED = 4  #: remaining samples do not determine M (estimate set to 0)
NONFINITE = 8  #: some samples had a non-finite value or a non-finite/non-positive variance

#: bit -> name, in bit order
REASONS: dict[int, str] = {DARK: "dark", SATURATED: "saturated",
                           ILL_CONDITIONED: "ill_conditioned", NONFINITE: "nonfinite"}

#: default limit on the condition number of a state set and of a pixel's remaining design
#: (0/45/90/135 and 0/60/120 give 2, 0/45/90 3.4, 0/30/60 8.8, 0/10/20 96)
DEFAULT_MAX_CONDITION = 50.0


def reason_names(code: int | None = None) -> dict[int, str] | tuple[str, ...]:
    """Without argument: the ``{bit: name}`` table. With a mask value: the names of its set
    bits in bit order, e.g. ``reason_names(6) == ("saturated", "ill_conditioned")``."""
    if code is None:
        return dict(REASONS)
    code = int(code)
    return tuple(name for bit, name in REASONS.items() if code & bit)


class AnalyzerTolerance(NamedTuple):
    """1-sigma uncertainty of the analyzer rows the solve assumes, per micro-polarizer class:
    relative gain (``0.01`` = 1 %), orientation in degrees, diattenuation (absolute)."""

    gain_rel: float = 0.0
    angle_deg: float = 0.0
    diattenuation: float = 0.0


class GeneratorTolerance(NamedTuple):
    """1-sigma uncertainty of the incident states the solve assumes: stage zero offset in
    degrees (common to all states) and inverse extinction ratio ``1/ER`` of the polarizer."""

    zero_offset_deg: float = 0.0
    inverse_extinction: float = 0.0


def _tolerance(value, cls, what: str):
    if value is None:
        return cls()
    try:
        vals = [float(v) for v in value]
        if len(vals) != len(cls._fields):
            raise ValueError
        tol = cls(*vals)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} tolerance must be {len(cls._fields)} numbers "
                          f"{cls._fields}, got {value!r}") from None
    if not all(np.isfinite(v) and v >= 0 for v in tol):
        raise ConfigError(f"{what} tolerance must be finite and >= 0, got {tuple(tol)}")
    return tol


def reason_counts(mask: np.ndarray) -> dict[str, int]:
    """Number of pixels (over colours) of a reason-bit ``mask`` with each bit set."""
    return {name: int(np.count_nonzero(mask & bit)) for bit, name in REASONS.items()}


@dataclass(frozen=True, eq=False)
class MuellerEstimate:
    """The estimate of a result without its diagnostics: ``mueller`` and ``sigma``
    ``(C, 3, 3, H, W)``, ``mask`` ``(C, H, W)`` reason bits and the state set's
    ``condition_number`` (:class:`ReferenceResult`), all a score against a truth reads
    (:mod:`polrig.solve.scoring`). Scoring after the result file is written keeps only this, so
    that the diagnostic planes (``sigma_noise``, ``residual``, ``pixel_condition``,
    ``n_samples``: about 0.4 GB of a full-sensor colour result at full resolution) are
    released first."""

    mueller: np.ndarray
    sigma: np.ndarray
    mask: np.ndarray
    condition_number: float

    def reason_counts(self) -> dict[str, int]:
        """Number of pixels (over colours) with each reason bit set."""
        return reason_counts(self.mask)


@dataclass(frozen=True, eq=False)
class ReferenceResult:
    """Output of :func:`solve_reference` (image stacks plane-first, ``docs/conventions.md``).

    ``mueller``: ``(C, 3, 3, H, W)`` float32, DN per unit incident S0.
    ``sigma``: ``(C, 3, 3, H, W)`` float32 standard deviation of each element:
    ``sqrt(sigma_noise^2 + sigma_cal^2)``, the noise part and the calibration part (module
    docstring; 0 for an exact calibration).
    ``sigma_noise``: the noise part alone, from the covariance ``(D^T W D)^-1`` (noise model,
    not scaled by the residual); the same array as ``sigma`` when not given.
    ``residual``: ``(C, H, W)`` float32 ``chi^2 / dof`` (0 where ``dof <= 0`` or unsolved).
    ``mask``: ``(C, H, W)`` uint8 reason bits (0 = good), see :func:`reason_names`.
    ``condition_number``: of the full design of the state set (all samples).
    ``pixel_condition``: ``(C, H, W)`` float32 condition number of the design of the samples
    actually used at each pixel (``inf`` where fewer than 9 or rank deficient). With per-pixel
    analyzer rows it is computed with the ideal analyzer rows (one value per sample pattern,
    which keeps it cheap; a calibrated analyzer differs from the ideal by a few percent), and
    systems that are singular to working precision are caught by the Cholesky pivots instead.
    ``n_samples``: ``(C, H, W)`` uint16 number of samples used.
    ``models``: with model selection only (:mod:`polrig.solve.model_selection`), the
    :class:`~polrig.solve.model_selection.ModelMaps` of the model chosen per pixel; None else.
    """

    mueller: np.ndarray
    sigma: np.ndarray
    residual: np.ndarray
    mask: np.ndarray
    condition_number: float
    pixel_condition: np.ndarray
    n_samples: np.ndarray
    sigma_noise: np.ndarray | None = None
    models: object | None = None

    def __post_init__(self) -> None:
        if self.sigma_noise is None:
            object.__setattr__(self, "sigma_noise", self.sigma)

    @property
    def valid(self) -> np.ndarray:
        """``(C, H, W)`` bool, ``mask == 0``."""
        return self.mask == 0

    def reason_counts(self) -> dict[str, int]:
        """Number of pixels (over colours) with each reason bit set."""
        return reason_counts(self.mask)

    def estimate(self) -> MuellerEstimate:
        """The estimate part (the same arrays, not copies): :class:`MuellerEstimate`."""
        return MuellerEstimate(self.mueller, self.sigma, self.mask, self.condition_number)


# ---------------------------------------------------------------------------- design
def _states(s_in: np.ndarray) -> np.ndarray:
    s = np.asarray(s_in, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ConfigError(f"incident states must be an (N, 3) array of linear Stokes vectors, got shape {s.shape}")
    if not np.isfinite(s).all():
        raise ConfigError("incident states contain non-finite values")
    return s


def _shared_rows(analyzer_rows: np.ndarray | None) -> np.ndarray:
    if analyzer_rows is None:
        return ideal_analyzer_matrix()
    a = np.asarray(analyzer_rows, dtype=np.float64)
    if a.shape != (4, 3):
        raise ValueError(f"shared analyzer rows must have shape (4, 3), got {a.shape}")
    return a


def design_matrix(s_in: np.ndarray, analyzer_rows: np.ndarray | None = None) -> np.ndarray:
    """``(4 N, 9)`` design matrix, row ``4 k + j`` = ``kron(a_j, s_k)`` (ideal analyzer rows
    when ``analyzer_rows`` is None; else one shared ``(4, 3)`` set)."""
    s = _states(s_in)
    a = _shared_rows(analyzer_rows)
    return np.einsum("ja,kb->kjab", a, s).reshape(len(s) * 4, 9)


def _cond_from_singular(sv: np.ndarray) -> float:
    if sv.size == 0 or not np.isfinite(sv).all() or sv[-1] <= 1e-12 * sv[0]:
        return float("inf")
    return float(sv[0] / sv[-1])


def condition_number(s_in: np.ndarray, analyzer_rows: np.ndarray | None = None) -> float:
    """2-norm condition number of the full ``4 N x 9`` design (``inf`` when rank deficient).

    With ideal analyzers the polarizer states 0/45/90/135 deg give 2.0, 0/60/120 give 2.0,
    0/45/90 give 3.41 (``2 + sqrt 2``), 0/30/60 give 8.8 and 0/10/20 give 96.
    """
    d = design_matrix(s_in, analyzer_rows)
    if len(d) < 9:
        return float("inf")
    return _cond_from_singular(np.linalg.svd(d, compute_uv=False))


def _max_condition(value) -> float:
    """``max_condition`` as a float >= 1 (``inf``: no limit), else a one-line ConfigError."""
    try:
        limit = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"max_condition must be a number, got {value!r}") from None
    if not limit >= 1.0:  # NaN fails too
        raise ConfigError(f"max_condition must be >= 1 (a condition number is at least 1; inf: "
                          f"no limit), got {value!r}")
    return limit


def validate_states(s_in: np.ndarray, max_condition: float = DEFAULT_MAX_CONDITION,
                    analyzer_rows: np.ndarray | None = None) -> float:
    """Check a polarizer state set; return its condition number.

    Raises :class:`polrig.errors.ConfigError` (a ``ValueError``) with one clear line for fewer
    than 3 states, non-finite states, collinear states (rank < 3), a condition number above
    ``max_condition``, or a ``max_condition`` that is not a number >= 1 (``inf``: no limit).
    """
    max_condition = _max_condition(max_condition)
    s = _states(s_in)
    if len(s) < 3:
        raise ConfigError(f"need at least 3 polarizer states, got {len(s)}")
    cond = condition_number(s, analyzer_rows)
    if not np.isfinite(cond):
        raise ConfigError("polarizer states are collinear (their Stokes vectors span fewer than 3 "
                          "dimensions); the Mueller matrix is not determined")
    if cond > max_condition:
        raise ConfigError(f"polarizer states are nearly collinear: condition number {cond:.3g} "
                          f"exceeds {max_condition:g}")
    return cond


def forward_measurements(mueller: np.ndarray, s_in: np.ndarray,
                         analyzer_rows: np.ndarray | None = None) -> np.ndarray:
    """Noise-free analyzer images ``(N, C, 4, H, W)`` of Mueller images ``(C, 3, 3, H, W)``:
    ``I_kj = a_j^T M s_k`` (the model :func:`solve_reference` inverts). ``analyzer_rows`` as
    in :func:`solve_reference`."""
    s = _states(s_in)
    m = np.asarray(mueller, dtype=np.float64)
    if m.ndim != 5 or m.shape[1:3] != (3, 3):
        raise ValueError(f"Mueller images must have shape (C, 3, 3, H, W), got {m.shape}")
    a = _analyzer_planes(analyzer_rows, m.shape[0], m.shape[-2:])
    ms = np.einsum("cabhw,kb->kcahw", m, s)  # M s_k: (N, C, 3, H, W)
    return np.einsum("cjahw,kcahw->kcjhw", a, ms)


def _analyzer_planes(analyzer_rows, n_col: int, hw: tuple[int, int]) -> np.ndarray:
    """Analyzer rows as a broadcast ``(C, 4, 3, H, W)`` view (no copy)."""
    if analyzer_rows is None:
        a = ideal_analyzer_matrix()
    else:
        a = np.asarray(analyzer_rows, dtype=np.float64)
    if a.shape == (4, 3):
        a = a[None, :, :, None, None]
    elif a.ndim == 4 and a.shape[:2] == (4, 3):
        a = a[None]
    elif not (a.ndim == 5 and a.shape[1:3] == (4, 3)):
        raise ValueError(f"analyzer rows must have shape (4, 3), (4, 3, H, W) or (C, 4, 3, H, W), got {a.shape}")
    try:
        return np.broadcast_to(a, (n_col, 4, 3) + tuple(hw))
    except ValueError:
        raise ValueError(f"analyzer rows {a.shape} do not match images of {n_col} colours and "
                         f"size {tuple(hw)}") from None


class SolveInputs(NamedTuple):
    """The checked inputs of a reference solve (:func:`solve_inputs`)."""

    cal_sd: np.ndarray  # (5,) 1-sigma of analyzer gain, angle (rad), D; generator angle (rad), 1/ER
    with_cal: bool  # any of them > 0
    shared: bool  # one analyzer for every pixel (rows None or (4, 3))
    cond_all: float  # condition number of the whole state set
    s: np.ndarray  # (N, 3) incident states
    meas: np.ndarray  # (N, C, 4, H, W)
    var: np.ndarray
    valid: np.ndarray
    a_shared: np.ndarray  # (4, 3) the shared analyzer rows (ideal ones with per-pixel rows)


def solve_inputs(s_in, measured, variance, valid, analyzer_rows, max_condition,
                 analyzer_tolerance, generator_tolerance, *,
                 check_state_set: bool = True) -> SolveInputs:
    """Check and normalise the arguments of :func:`solve_reference` (and of its numpy oracle,
    :mod:`polrig.solve._reference_numpy`): tolerances, state set (its condition number against
    ``max_condition``), sample arrays (:func:`check_samples`), shared analyzer rows. Raises as
    :func:`solve_reference` documents. ``check_state_set=False`` (the hybrid solve, whose
    prior may complete any state set): at least one finite state, its condition number
    reported as it is (``inf`` for fewer than 3 states)."""
    a_tol = _tolerance(analyzer_tolerance, AnalyzerTolerance, "analyzer")
    g_tol = _tolerance(generator_tolerance, GeneratorTolerance, "generator")
    cal_sd = np.array([a_tol.gain_rel, np.deg2rad(a_tol.angle_deg), a_tol.diattenuation,
                       np.deg2rad(g_tol.zero_offset_deg), g_tol.inverse_extinction])
    shared = analyzer_rows is None or np.ndim(analyzer_rows) == 2
    if check_state_set:
        cond_all = validate_states(s_in, max_condition, analyzer_rows if shared else None)
    else:
        _max_condition(max_condition)
        if len(_states(s_in)) < 1:
            raise ConfigError("need at least 1 polarizer state, got 0")
        cond_all = condition_number(s_in, analyzer_rows if shared else None)
    s = _states(s_in)
    meas, var, valid = check_samples(len(s), measured, variance, valid)
    a_shared = _shared_rows(analyzer_rows) if shared else ideal_analyzer_matrix()
    return SolveInputs(cal_sd, bool(np.any(cal_sd > 0)), shared, cond_all, s, meas, var, valid,
                       a_shared)


def check_samples(n_states: int, measured, variance, valid=None):
    """``(measured, variance, valid)`` as arrays after checking their shapes: ``measured``
    ``(N, C, 4, H, W)`` with ``N = n_states``, ``variance`` and ``valid`` (optional, bool) the
    same shape; ``ValueError`` naming the mismatch otherwise. No copy of float input."""
    meas = np.asarray(measured)
    if meas.ndim != 5 or meas.shape[0] != n_states or meas.shape[2] != 4:
        raise ValueError(f"measured must have shape (N={n_states}, C, 4, H, W), got {meas.shape}")
    var = np.asarray(variance)
    if var.shape != meas.shape:
        raise ValueError(f"variance shape {var.shape} differs from measured {meas.shape}")
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != meas.shape:
            raise ValueError(f"valid shape {valid.shape} differs from measured {meas.shape}")
    return meas, var, valid


# ---------------------------------------------------------------------------- solve
#: pixels per tile of the solve (rounded to whole rows): big enough to amortise the per-tile
#: Python work, small enough for the tile buffers to stay in L2 (measured: 1024 px 1.5x,
#: 16384 px 1.05x, 65536 px 1.15x the CPU time of 4096 px)
DEFAULT_TILE_PIXELS = 4096


def _solve_options(max_condition, min_snr, dtype, chunk_pixels
                   ) -> tuple[float, float, np.dtype, int]:
    """Check the scalar options of :func:`solve_reference` (one-line ConfigError each)."""
    max_condition = _max_condition(max_condition)
    try:
        min_snr = float(min_snr)
    except (TypeError, ValueError):
        raise ConfigError(f"min_snr must be a number, got {min_snr!r}") from None
    if not (np.isfinite(min_snr) and min_snr >= 0):
        raise ConfigError(f"min_snr must be finite and >= 0, got {min_snr!r}")
    try:
        out = np.dtype(dtype)
    except TypeError:
        raise ConfigError(f"dtype must be float32 or float64, got {dtype!r}") from None
    if out not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise ConfigError(f"dtype must be float32 or float64, got {out}")
    try:
        chunk = int(chunk_pixels)
    except (TypeError, ValueError):
        raise ConfigError(f"chunk_pixels must be a positive integer, got {chunk_pixels!r}") from None
    if chunk < 1:
        raise ConfigError(f"chunk_pixels must be a positive integer, got {chunk_pixels!r}")
    return max_condition, min_snr, out, chunk


def _float_samples(x: np.ndarray) -> np.ndarray:
    """float32 and float64 samples as they are (no copy); others as float64. (The tile driver
    copies a small strided array once, :func:`_kernel_input`.)"""
    return x if x.dtype in (np.float32, np.float64) else x.astype(np.float64)


def solve_reference(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                    valid: np.ndarray | None = None, analyzer_rows: np.ndarray | None = None, *,
                    max_condition: float = DEFAULT_MAX_CONDITION, min_snr: float = MIN_SNR,
                    analyzer_tolerance: Sequence[float] | None = None,
                    generator_tolerance: Sequence[float] | None = None,
                    chunk_pixels: int = DEFAULT_TILE_PIXELS, dtype=np.float32) -> ReferenceResult:
    """Per-pixel, per-colour weighted least-squares 3x3 Mueller block (see module docstring).

    ``s_in``: ``(N, 3)`` incident linear Stokes vectors, normalised units, N >= 3.
    ``measured``: ``(N, C, 4, H, W)`` black-subtracted analyzer images in DN (averaged over
    frames and/or HDR-merged, analyzer offsets removed). ``variance``: the same shape, the
    variance of each sample (e.g. :meth:`polrig.sensor.noise.SensorModel.variance_dn2`, or from
    :func:`average_frames` / :func:`merge_hdr`). float32 and float64 inputs are read as they
    are (never copied or upcast as a whole); other dtypes are converted to float64.
    ``valid``: optional bool of the same shape, ``False`` for saturated or bad samples.
    ``analyzer_rows``: None (ideal), one shared ``(4, 3)`` set, or per pixel ``(4, 3, H, W)`` /
    ``(C, 4, 3, H, W)`` (e.g. demosaiced rows of a calibrated analyzer model).
    ``max_condition``: per-pixel limit (>= 1, ``inf`` for none) on the condition number of the
    design of the samples used. ``min_snr``: ``m00 / sigma(m00)`` below it is ``DARK``
    (finite, >= 0).

    ``analyzer_tolerance`` (:class:`AnalyzerTolerance`: relative gain, orientation in deg,
    diattenuation) and ``generator_tolerance`` (:class:`GeneratorTolerance`: stage zero offset
    in deg, ``1/ER``): 1-sigma uncertainty of ``analyzer_rows`` and ``s_in``, propagated into
    ``sigma`` (module docstring); ``None`` or zeros: exact, ``sigma`` is the noise part alone.

    ``chunk_pixels``: pixels per tile, rounded to whole image rows (the memory beyond the
    outputs is about 600 bytes per pixel of a tile and thread: float64 tile buffers; the
    default keeps them in the CPU's L2 cache). ``dtype``: float32 (the conventions) or
    float64, of the ``mueller``, ``sigma`` and ``residual`` outputs; a pixel whose estimate,
    sigma or residual does not fit it (float32 overflow) is ``ILL_CONDITIONED`` with zero
    outputs.

    Results are bit-identical for any ``chunk_pixels`` and thread count (each pixel is solved
    by one fixed sequence of float64 operations, :mod:`polrig.solve._reference_kernel`). Tiles run
    on ``polrig.solve._reference_kernel.THREADS`` threads (``NUMBA_NUM_THREADS``, default the
    CPUs this process may use).

    Raises :class:`polrig.errors.ConfigError` for a bad state set (fewer than 3, collinear,
    condition number above ``max_condition``) or a bad option (``max_condition``,
    ``min_snr``, ``dtype``, ``chunk_pixels``, tolerances) and ``ValueError`` for mismatched
    shapes; never for bad pixel values (they are masked).
    """
    max_condition, min_snr, dtype, tile = _solve_options(max_condition, min_snr, dtype,
                                                         chunk_pixels)
    inputs = solve_inputs(s_in, measured, variance, valid, analyzer_rows, max_condition,
                          analyzer_tolerance, generator_tolerance)
    return solve_tiles(inputs, analyzer_rows, max_condition, min_snr, dtype, tile)


class PriorInputs(NamedTuple):
    """A Gaussian prior on the nine elements for :func:`solve_tiles` (checked by
    :mod:`polrig.solve.hybrid`): ``mean`` and ``sigma`` ``(C, 3, 3, H, W)`` float32 or float64
    (broadcast views allowed; :func:`_kernel_input`), ``seen_dir`` ``(3,)`` the
    unit Stokes vector of the state whose samples the prior already holds, ``seen_axis``
    ``(3,)`` the axis of its unobserved
    plane that the row variance along ``seen_dir`` moves onto (all 0: the scalar row factor;
    :func:`polrig.solve.hybrid.plane_axis`) and ``seen_k`` that state's index (-1: none)."""

    mean: np.ndarray
    sigma: np.ndarray
    seen_dir: np.ndarray
    seen_axis: np.ndarray
    seen_k: int
    #: ``(3,)`` per row of ``M``, the share of the row's prior variance along ``seen_dir`` that
    #: is kept in its unobserved plane (:mod:`polrig.solve.hybrid`, "The seen direction's share")
    seen_share: np.ndarray
    #: ``(6, 6)`` inverse of the joint prior's correlation in the whitened unobserved
    #: coordinates (:mod:`polrig.solve.hybrid`, "Joint prior"), or None: the per-element prior
    joint_inverse: np.ndarray | None = None
    #: ``(3,)`` the unit direction two states leave open in each row, and the factor on the
    #: prior's standard deviation along it (:mod:`polrig.solve.hybrid`, "The open direction's
    #: scale"); factor 1: as it is
    open_dir: np.ndarray = np.zeros(3)
    open_factor: float = 1.0


def solve_tiles(inputs: SolveInputs, analyzer_rows, max_condition: float, min_snr: float,
                dtype: np.dtype, tile: int, prior: PriorInputs | None = None) -> ReferenceResult:
    """The tile driver of :func:`solve_reference` on checked inputs (:func:`solve_inputs`,
    :func:`_solve_options`); with ``prior``, the hybrid solve of :mod:`polrig.solve.hybrid`
    (the same kernels with the prior's precision in the normal equations; a pixel with a
    prior is not masked for its samples' condition number, only where the posterior is
    singular)."""
    (cal_sd, with_cal, shared, cond_all, s, meas, var, valid, a_shared) = inputs
    n = len(s)
    _, n_col, _, h, w = meas.shape
    pixel_rows = None
    if not shared:
        _analyzer_planes(analyzer_rows, n_col, (h, w))  # checks the shape
        a = np.asarray(analyzer_rows)
        pixel_rows = _float_samples(a if a.ndim == 5 else a[None])

    mueller = np.zeros((n_col, 3, 3, h, w), dtype)
    sigma = np.zeros_like(mueller)
    sigma_noise = np.zeros_like(mueller) if with_cal else sigma
    residual = np.zeros((n_col, h, w), dtype)
    mask = np.zeros((n_col, h, w), np.uint8)
    pix_cond = np.zeros((n_col, h, w), np.float32)
    n_used = np.zeros((n_col, h, w), np.uint16)
    if n_col * h * w:
        from polrig.solve import (
            _reference_kernel as kern,  # numba: imported on first use
        )

        run = _TileRun(kern, s, _float_samples(meas), _float_samples(var), valid, a_shared,
                       pixel_rows, cond_all, max_condition, min_snr,
                       float(np.finfo(dtype).max), cal_sd, with_cal,
                       (mueller, sigma, sigma_noise, residual, mask, pix_cond, n_used), prior)
        rows_per_tile = max(1, tile // w)
        tiles = [(c, y0, min(h, y0 + rows_per_tile))
                 for c in range(n_col) for y0 in range(0, h, rows_per_tile)]
        n_threads = min(len(tiles), kern.THREADS)
        if n_threads > 1:
            with ThreadPoolExecutor(n_threads, thread_name_prefix="reference-solve") as pool:
                futures = [pool.submit(run, t) for t in tiles]
                try:
                    for f in futures:
                        f.result()
                except BaseException:  # an error or Ctrl-C: do not solve the remaining tiles
                    for f in futures:
                        f.cancel()
                    raise
        else:
            for t in tiles:
                run(t)
    return ReferenceResult(mueller, sigma, residual, mask, cond_all, pix_cond, n_used,
                           sigma_noise if with_cal else None)


#: the largest strided input :func:`_kernel_input` copies (bytes)
KERNEL_COPY_LIMIT = 32 * 2**20


def _kernel_input(x: np.ndarray) -> np.ndarray:
    """``x`` read-only and, up to :data:`KERNEL_COPY_LIMIT` bytes, C-contiguous: itself (a
    read-only view) where it is C-contiguous or larger than that, else a copy.

    numba compiles one machine-code version of a kernel per argument type, and an array's
    type holds its layout and writability. Callers pass contiguous arrays, row bands and
    read-only broadcasts, so each kernel was compiled, and cached, once per mix (solve_blocks
    21-25 s each on this project's 2-core machine, 2026-11-30). The bands and broadcast priors
    of the capture paths are a few MiB: copied, they run on the contiguous arrays' version. A
    strided full-sensor array is not copied (its samples alone are 230 MiB in colour: copying
    samples and variances raised the solve's peak from 304 to 762 MiB); it gets its own
    version, compiled once. Typing every input as any-strides ("A") instead, with no copy,
    made the full-sensor solve 20-35 % slower (``python -m benchmarks reference``)."""
    if not x.flags.c_contiguous and x.nbytes <= KERNEL_COPY_LIMIT:
        x = np.ascontiguousarray(x)
    if x.flags.writeable:
        x = x.view()
        x.flags.writeable = False
    return x


class _TileRun:
    """Solve one tile (rows ``y0 .. y1`` of colour ``c``) into the output images: load the
    samples into block-major float64 buffers (one set per thread, reused), solve, store,
    then mask the pixels whose used design is too ill-conditioned (:class:`_PatternConditions`).
    Called from several threads at once: tiles write disjoint parts of the outputs."""

    def __init__(self, kern, s, meas, var, valid, a_shared, pixel_rows, cond_all,
                 max_condition, min_snr, out_max, cal_sd, with_cal, outputs,
                 prior: PriorInputs | None = None) -> None:
        self.kern = kern
        self.s = _kernel_input(s)
        self.ds_gen = _generator_derivatives(s)
        self.meas, self.var = _kernel_input(meas), _kernel_input(var)
        self.has_valid = valid is not None
        self.valid = _kernel_input(valid if self.has_valid else np.ones((1,) * 5, bool))
        self.per_pixel = pixel_rows is not None
        self.rows = _kernel_input(pixel_rows if self.per_pixel else np.zeros((1,) * 5))
        lanes = kern.LANES
        self.shared_arow = np.repeat(a_shared.reshape(1, 4, 3, 1), lanes, -1)
        # condition numbers with the shared (for per-pixel rows: the ideal) analyzer
        self.patterns = _PatternConditions(design_matrix(s, a_shared), cond_all)
        self.max_condition, self.min_snr, self.out_max = max_condition, min_snr, out_max
        self.cal_sd, self.with_cal = cal_sd, with_cal
        self.outputs = outputs
        self.prior = None if prior is None else prior._replace(mean=_kernel_input(prior.mean),
                                                                sigma=_kernel_input(prior.sigma))
        self.local = threading.local()

    def _buffers(self, n_blocks: int) -> dict[str, np.ndarray]:
        """This thread's tile buffers, at least ``n_blocks`` blocks (zeroed when allocated:
        lanes past a row's end are never written and must keep weight 0)."""
        buf = getattr(self.local, "buf", None)
        if buf is None or len(buf["w"]) < n_blocks:
            lanes, nr = self.kern.LANES, 4 * len(self.s)
            buf = {"w": np.zeros((n_blocks, nr, lanes)), "mv": np.zeros((n_blocks, nr, lanes)),
                   "flags": np.zeros((n_blocks, lanes), np.int64),
                   "nok": np.zeros((n_blocks, lanes), np.int64),
                   "arow": np.zeros((n_blocks if self.per_pixel else 0, 4, 3, lanes)),
                   "keys": np.zeros((self.patterns.n_words, n_blocks * lanes), np.int64),
                   "x": np.zeros((n_blocks, 9, lanes)), "sg": np.zeros((n_blocks, 9, lanes)),
                   "sn": np.zeros((n_blocks, 9, lanes)), "res": np.zeros((n_blocks, lanes))}
            pb = n_blocks if self.prior is not None else 0  # the prior's buffers, else empty
            buf.update(pa=np.zeros((pb, 9, 9, lanes)), pm=np.zeros((pb, 9, lanes)),
                       prank=np.zeros((pb, lanes), np.int64))
            self.local.buf = buf
        return {k: v[:, :n_blocks * self.kern.LANES] if k == "keys" else v[:n_blocks]
                for k, v in buf.items()}

    def __call__(self, tile: tuple[int, int, int]) -> None:
        c, y0, y1 = tile
        kern = self.kern
        lanes = kern.LANES
        mueller, sigma, sigma_noise, residual, mask, pix_cond, n_used = self.outputs
        width = mueller.shape[-1]
        per_row = -(-width // lanes)
        b = self._buffers((y1 - y0) * per_row)
        arow = b["arow"] if self.per_pixel else self.shared_arow
        partial = kern.load_tile(self.meas, self.var, self.valid, self.has_valid, self.rows,
                                 self.per_pixel, c, y0, y1, b["w"], b["mv"], b["flags"], arow)
        prior = self.prior
        if prior is not None:  # polrig.solve.hybrid
            kern.load_prior(prior.mean, prior.sigma, c, y0, y1, prior.seen_dir, prior.seen_axis, prior.seen_k,
                            prior.seen_share, b["w"], b["flags"], arow, self.per_pixel, b["pa"], b["pm"],
                            b["prank"])
            if prior.joint_inverse is not None:
                kern.correlate_prior(b["pa"], b["prank"], b["w"], prior.seen_k, prior.seen_dir, prior.seen_axis,
                                     prior.joint_inverse)
            if prior.open_factor != 1.0:
                kern.stretch_prior(b["pa"], b["prank"], prior.open_dir, 1.0 / prior.open_factor - 1.0)
        kern.solve_blocks(self.s, self.ds_gen, b["w"], b["mv"], arow, self.per_pixel,
                          b["flags"], lanes, self.min_snr, self.out_max, self.cal_sd,
                          self.with_cal, prior is not None, b["pa"], b["pm"], b["prank"],
                          b["x"], b["sg"], b["sn"], b["res"], b["nok"], b["keys"])
        kern.store_tile(c, y0, y1, b["x"], b["sg"], b["sn"], b["res"], b["flags"], b["nok"],
                        self.with_cal, mueller, sigma, sigma_noise, residual, mask, n_used)
        if prior is None and not partial:  # every pixel uses all its samples
            pix_cond[c, y0:y1] = self.patterns.cond_all
            return
        keys = b["keys"].reshape(-1, y1 - y0, per_row * lanes)[:, :, :width].reshape(
            -1, (y1 - y0) * width).T
        cond = self.patterns.conditions(keys)
        pix_cond[c, y0:y1] = cond.reshape(y1 - y0, width)
        too_ill = ~(cond <= self.max_condition)
        if prior is not None:  # a pixel with a prior is judged by its posterior (pivots) alone
            too_ill &= (b["prank"].reshape(y1 - y0, per_row * lanes)[:, :width] == 0).ravel()
        unsolved = np.flatnonzero(too_ill)
        if unsolved.size:  # too few or too ill-conditioned samples: zeros, ILL_CONDITIONED
            yy, xx = np.divmod(unsolved, width)
            yy += y0
            mask[c, yy, xx] = mask[c, yy, xx] & ~np.uint8(DARK) | ILL_CONDITIONED
            for arr in (mueller, sigma, sigma_noise):
                arr[c, :, :, yy, xx] = 0
            residual[c, yy, xx] = 0


def _generator_derivatives(s: np.ndarray) -> np.ndarray:
    """``(2, N, 3)`` derivatives of the incident states: stage zero offset (per rad,
    ``[0, -2 s_2, 2 s_1]``) and inverse extinction ratio (``[1, -u] / 2``, module docstring)."""
    ds = np.zeros((2,) + s.shape)
    ds[0, :, 1] = -2.0 * s[:, 2]
    ds[0, :, 2] = 2.0 * s[:, 1]
    xy = s[:, 1:3]
    norm = np.sqrt(np.einsum("ki,ki->k", xy, xy))[:, None]
    ds[1, :, 0] = 0.5
    ds[1, :, 1:] = -0.5 * np.where(norm > 0, xy / np.where(norm > 0, norm, 1.0), 0.0)
    return ds


class _PatternConditions:
    """Condition number of each pixel's used design from its sample pattern (bit ``4 k + j``
    set: sample used; :func:`polrig.solve._reference_kernel.load_tile`). All samples used:
    the state set's; any other pattern: the SVD of its rows of the shared design (for
    per-pixel analyzer rows: the ideal analyzer's), computed once per pattern and cached; fewer
    than 9 samples: ``inf``."""

    def __init__(self, design: np.ndarray, cond_all: float) -> None:
        self.design = design
        self.cond_all = cond_all
        n_rows = len(design)
        self.n_words = (n_rows + 63) // 64
        full = np.zeros(self.n_words, np.uint64)
        for r in range(n_rows):
            full[r >> 6] |= np.uint64(1) << np.uint64(r & 63)
        self.full = full.view(np.int64)
        self.cache: dict[bytes, float] = {}

    def _pattern(self, key: np.ndarray) -> float:
        kb = key.tobytes()
        if kb not in self.cache:
            words = key.view(np.uint64)
            used = [r for r in range(len(self.design)) if (int(words[r >> 6]) >> (r & 63)) & 1]
            rows = self.design[used]
            self.cache[kb] = (_cond_from_singular(np.linalg.svd(rows, compute_uv=False))
                              if len(rows) >= 9 else float("inf"))
        return self.cache[kb]

    def conditions(self, keys: np.ndarray) -> np.ndarray:
        """``(P,)`` float64 condition numbers of pixels with pattern keys ``(P, n_words)``."""
        cond = np.full(len(keys), self.cond_all)
        partial = np.flatnonzero((keys != self.full).any(axis=1))
        if partial.size:
            if self.n_words == 1:
                uniq, inverse = np.unique(keys[partial, 0], return_inverse=True)
                uniq = uniq[:, None]
            else:
                uniq, inverse = np.unique(keys[partial], axis=0, return_inverse=True)
            vals = np.array([self._pattern(np.ascontiguousarray(k)) for k in uniq])
            cond[partial] = vals[inverse.ravel()]
        return cond


# ---------------------------------------------------------------------------- frames, HDR
def average_frames(frames: np.ndarray, saturation_dn: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``K >= 2`` frames (axis 0) and the empirical variance of that mean
    (sample variance with ``ddof=1`` divided by ``K``), both float64.

    With ``saturation_dn``, a sample where any frame reached it is reported at
    ``saturation_dn`` exactly, so the usual ``>= saturation_dn`` test (e.g. in
    :func:`merge_hdr`) still excludes it after averaging. Note that an empirical variance
    from a few frames is itself noisy (relative error ``sqrt(2 / (K - 1))``); a model variance
    (:meth:`polrig.sensor.noise.SensorModel.variance_dn2` with ``n_frames=K``) is usually the better
    weight.
    """
    f = np.asarray(frames, dtype=np.float64)
    if f.ndim < 1 or f.shape[0] < 2:
        raise ValueError(f"need at least 2 frames along axis 0 to estimate a variance, got shape {f.shape}")
    k = f.shape[0]
    mean = f.mean(axis=0)
    variance = f.var(axis=0, ddof=1) / k
    if saturation_dn is not None:
        sat = (f >= saturation_dn).any(axis=0)
        mean = np.where(sat, float(saturation_dn), mean)
    return mean, variance


def merge_hdr(brackets: Sequence[tuple[np.ndarray, float]], saturation_dn: float,
              sensor_model: SensorModel, *, reference_exposure_us: float | None = None,
              n_frames: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge an exposure bracket into one image at ``reference_exposure_us``.

    ``brackets``: ``[(image, exposure_us), ...]``, images of one shape in black-subtracted DN
    (each the mean of ``n_frames`` frames). A sample is used where it is finite and below
    ``saturation_dn`` (e.g. ``sensor_model.saturation_dn``). Each used sample is scaled to the
    reference exposure (default: the longest) by ``r = t_ref / t``; the samples are combined
    with inverse-variance weights, the variance of each being the model variance
    ``r^2 var(x_hat, t)`` at the *predicted* signal ``x_hat = y0 / r`` (``y0``: the estimate of
    the longest usable exposure) rather than at the measured one, which would bias the merge
    low (noise-correlated weights). Returns ``(radiance, variance, valid)``: radiance in DN at
    the reference exposure, its variance (``1 / sum w``), and ``valid`` (some exposure
    usable). Where no exposure is usable, radiance is the shortest exposure's value scaled
    (a lower bound), variance 0 and ``valid`` False (finite outputs; exclude by ``valid``).
    """
    if len(brackets) < 1:
        raise ValueError("merge_hdr needs at least one (image, exposure_us) pair")
    images = [np.asarray(im, dtype=np.float64) for im, _ in brackets]
    exps = np.array([float(e) for _, e in brackets])
    if not (np.isfinite(exps).all() and (exps > 0).all()):
        raise ValueError(f"exposures must be positive and finite, got {exps.tolist()}")
    shape = images[0].shape
    if any(im.shape != shape for im in images):
        raise ValueError(f"bracket images differ in shape: {[im.shape for im in images]}")
    t_ref = float(exps.max() if reference_exposure_us is None else reference_exposure_us)
    order = np.argsort(exps)[::-1]  # longest first
    scaled = [images[i] * (t_ref / exps[i]) for i in range(len(images))]
    usable = [np.isfinite(im) & (im < saturation_dn) for im in images]

    y0 = np.zeros(shape)
    have = np.zeros(shape, bool)
    for i in order:
        take = usable[i] & ~have
        y0 = np.where(take, scaled[i], y0)
        have |= take
    wsum = np.zeros(shape)
    ysum = np.zeros(shape)
    for i in range(len(images)):
        r = t_ref / exps[i]
        v = sensor_model.variance_dn2(np.clip(y0, 0.0, None) / r, exps[i], n_frames) * r**2
        wt = np.where(usable[i], 1.0 / v, 0.0)
        wsum += wt
        ysum += wt * np.where(usable[i], scaled[i], 0.0)
    valid = wsum > 0
    shortest = int(np.argmin(exps))
    fallback = np.where(np.isfinite(scaled[shortest]), scaled[shortest], 0.0)
    radiance = np.where(valid, ysum / np.where(valid, wsum, 1.0), fallback)
    variance = np.where(valid, 1.0 / np.where(valid, wsum, 1.0), 0.0)
    return radiance, variance, valid
