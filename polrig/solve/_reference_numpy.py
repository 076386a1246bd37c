"""The previous, pure-numpy reference solve (chunked, batched Cholesky in pixels-last
layout), kept as the oracle that :func:`polrig.solve.reference.solve_reference` is tested against
(``tests/test_reference_numerics.py``) and as the baseline of ``python -m benchmarks
reference``. Same model, semantics and outputs as :func:`polrig.solve.reference.solve_reference`
(see its module docstring), except for the argument checks and output-range masking that
were added there; about 0.4 Mpx/s on two cores. Not used by the application.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from polrig.solve.reference import (
    DARK,
    DEFAULT_MAX_CONDITION,
    ILL_CONDITIONED,
    MIN_SNR,
    NONFINITE,
    SATURATED,
    ReferenceResult,
    _analyzer_planes,
    _cond_from_singular,
    solve_inputs,
)

__all__ = ["solve_reference_numpy"]


def solve_reference_numpy(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                          valid: np.ndarray | None = None,
                          analyzer_rows: np.ndarray | None = None, *,
                          max_condition: float = DEFAULT_MAX_CONDITION, min_snr: float = MIN_SNR,
                          analyzer_tolerance: Sequence[float] | None = None,
                          generator_tolerance: Sequence[float] | None = None,
                          chunk_pixels: int = 4096, dtype=np.float32) -> ReferenceResult:
    """The previous implementation of :func:`polrig.solve.reference.solve_reference` (same
    arguments and results)."""
    (cal_sd, with_cal, shared, cond_all, s, meas, var, valid,
     a_shared) = solve_inputs(s_in, measured, variance, valid, analyzer_rows, max_condition,
                              analyzer_tolerance, generator_tolerance)
    cal_sd = cal_sd if with_cal else None
    n = len(s)
    _, n_col, _, h, w = meas.shape
    a_planes = _analyzer_planes(analyzer_rows, n_col, (h, w))

    mueller = np.zeros((n_col, 3, 3, h, w), dtype)
    sigma = np.zeros_like(mueller)
    sigma_noise = sigma if cal_sd is None else np.zeros_like(mueller)
    residual = np.zeros((n_col, h, w), dtype)
    mask = np.zeros((n_col, h, w), np.uint8)
    pix_cond = np.zeros((n_col, h, w), np.float32)
    n_used = np.zeros((n_col, h, w), np.uint16)

    hw = h * w
    chunk = max(1, int(chunk_pixels))
    pattern_cache: dict[bytes, float] = {}
    for c in range(n_col):
        m_c = meas[:, c].reshape(n, 4, hw)
        v_c = var[:, c].reshape(n, 4, hw)
        ok_c = None if valid is None else valid[:, c].reshape(n, 4, hw)
        a_c = None if shared else a_planes[c].reshape(4, 3, hw)
        for p0 in range(0, hw, chunk):
            sl = slice(p0, min(p0 + chunk, hw))
            res = _solve_chunk(
                s,
                np.moveaxis(m_c[..., sl], -1, 0).astype(np.float64),
                np.moveaxis(v_c[..., sl], -1, 0).astype(np.float64),
                None if ok_c is None else np.moveaxis(ok_c[..., sl], -1, 0),
                a_shared, None if a_c is None else np.moveaxis(a_c[..., sl], -1, 0),
                max_condition, min_snr, pattern_cache, cond_all, cal_sd)
            mm, sg, sn, rs, mk, pc, nu = res
            mueller.reshape(n_col, 3, 3, hw)[c, :, :, sl] = np.moveaxis(mm, 0, -1)
            sigma.reshape(n_col, 3, 3, hw)[c, :, :, sl] = np.moveaxis(sg, 0, -1)
            if cal_sd is not None:
                sigma_noise.reshape(n_col, 3, 3, hw)[c, :, :, sl] = np.moveaxis(sn, 0, -1)
            residual.reshape(n_col, hw)[c, sl] = rs
            mask.reshape(n_col, hw)[c, sl] = mk
            pix_cond.reshape(n_col, hw)[c, sl] = pc
            n_used.reshape(n_col, hw)[c, sl] = nu
    return ReferenceResult(mueller, sigma, residual, mask, cond_all, pix_cond, n_used,
                           sigma_noise)


def _solve_chunk(s, meas, var, valid, a_shared, a_pix, max_condition, min_snr, pattern_cache,
                 cond_all, cal_sd=None):
    """Solve ``P`` pixels. meas/var/valid: ``(P, N, 4)``; a_pix: ``(P, 4, 3)`` or None (then
    ``a_shared`` ``(4, 3)`` is the analyzer; with ``a_pix`` it only serves the condition
    numbers). ``cal_sd``: None or the 5 calibration standard deviations (gain, analyzer angle
    rad, diattenuation, zero offset rad, 1/ER). Returns ``(M, sigma, sigma_noise, residual,
    flags, condition, n_used)``."""
    p, n, _ = meas.shape
    meas = meas.reshape(p, n * 4)
    var = var.reshape(p, n * 4)
    good = np.isfinite(meas) & np.isfinite(var) & (var > 0)
    given = np.ones_like(good) if valid is None else valid.reshape(p, n * 4)
    ok = good & given
    flags = np.where((given & ~good).any(axis=1), NONFINITE, 0).astype(np.uint8)
    flags |= np.where((~given).any(axis=1), SATURATED, 0).astype(np.uint8)
    n_ok = ok.sum(axis=1)
    wgt = np.where(ok, 1.0 / np.where(ok, var, 1.0), 0.0)
    wi = wgt * np.where(ok, meas, 0.0)

    d = np.einsum("ja,kb->kjab", a_shared, s).reshape(n * 4, 9)  # design, row 4k + j
    if a_pix is None:
        dd = np.einsum("ri,rj->rij", d, d)[:, _TRIL[0], _TRIL[1]]  # (4N, 45)
        # (einsum, not BLAS: multithreaded GEMM on these thin matrices is several times slower)
        nm = np.einsum("rq,pr->qp", dd, wgt)  # (45, P) lower triangle of D^T W D
        rhs = np.einsum("ri,pr->ip", d, wi)  # (9, P)
    else:
        dpix = np.einsum("pja,kb->pkjab", a_pix, s).reshape(p, n * 4, 9)
        # Kronecker structure: D^T W D = sum_j (a_j a_j^T) (x) (sum_k w_kj s_k s_k^T)
        sj = np.einsum("pkj,kq->pjq", wgt.reshape(p, n, 4), np.einsum("kb,kd->kbd", s, s).reshape(n, 9))
        aa = np.einsum("pja,pjc->pjac", a_pix, a_pix).reshape(p, 4, 9)
        nm = np.einsum("pjr,pjq->rqp", aa, sj)  # [(a, c), (b, d), P]
        nm = nm.reshape(3, 3, 3, 3, p).transpose(0, 2, 1, 3, 4).reshape(81, p)[_TRIL_FLAT]
        rhs = np.einsum("pr,pri->ip", wi, dpix)
    # per-pixel condition number of the design of the samples used, with the shared (or, for
    # per-pixel rows, the ideal) analyzer: all samples -> the state set's; every other sample
    # pattern is computed once and cached
    cond = np.full(p, cond_all)
    partial = ~ok.all(axis=1)
    if partial.any():
        keys, inverse = np.unique(np.packbits(ok[partial], axis=1), axis=0, return_inverse=True)
        vals = np.empty(len(keys))
        for i, key in enumerate(keys):
            kb = key.tobytes()
            if kb not in pattern_cache:
                rows = d[np.unpackbits(key)[: n * 4].astype(bool)]
                pattern_cache[kb] = (_cond_from_singular(np.linalg.svd(rows, compute_uv=False))
                                     if len(rows) >= 9 else float("inf"))
            vals[i] = pattern_cache[kb]
        cond[partial] = vals[inverse.ravel()]
    cond = np.where(n_ok >= 9, cond, np.inf)
    solvable = cond <= max_condition

    # equilibrate (weights span decades), then batched Cholesky in structure-of-arrays layout
    diag = nm[_TRIL_DIAG]
    dscale = np.where(solvable & (diag > 0), 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0)), 1.0)
    nm = nm * dscale[_TRIL[0]] * dscale[_TRIL[1]]
    nm[:, ~solvable] = _EYE_TRIL[:, None]
    x, inv, bad = _cholesky_solve(_from_tril(nm), np.where(solvable, rhs * dscale, 0.0))
    solvable &= ~bad
    x = x * dscale
    sig = dscale * np.sqrt(np.clip(np.einsum("kip,kip->ip", inv, inv), 0.0, None))
    sig_noise = sig
    if cal_sd is not None:
        sens = _calibration_rhs(s, a_shared if a_pix is None else a_pix,
                                wgt.reshape(p, n, 4), x, cal_sd)  # (P, Q, 9)
        # G e_p = (D^T W D)^-1 D^T W e_p with the equilibrated factor: S L^-T L^-1 S rhs
        lin = np.moveaxis(inv, -1, 0)  # (P, 9, 9) L^-1
        sc = dscale.T[:, None, :]
        dm = (((sens * sc) @ np.swapaxes(lin, 1, 2)) @ lin) * sc
        sig = np.sqrt(sig_noise**2 + np.einsum("pqi,pqi->ip", dm, dm))

    if a_pix is None:
        pred = x.T @ d.T  # (P, 4N)
    else:
        pred = np.einsum("pri,ip->pr", dpix, x)
    r = np.where(ok, np.where(ok, meas, 0.0) - pred, 0.0)
    chi2 = np.einsum("pr,pr->p", wgt * r, r)
    dof = n_ok - 9
    resid = np.where(solvable & (dof > 0), chi2 / np.maximum(dof, 1), 0.0)
    finite = np.isfinite(x).all(axis=0) & np.isfinite(sig).all(axis=0) & np.isfinite(resid)
    solvable &= finite
    flags |= np.where(solvable, 0, ILL_CONDITIONED).astype(np.uint8)
    with np.errstate(invalid="ignore"):
        dark = solvable & ~(x[0] >= min_snr * sig[0])
    flags |= np.where(dark, DARK, 0).astype(np.uint8)
    x = np.where(solvable, x, 0.0)
    sig = np.where(solvable, sig, 0.0)
    sig_noise = np.where(solvable, sig_noise, 0.0)
    resid = np.where(solvable, resid, 0.0)
    return (x.T.reshape(p, 3, 3), sig.T.reshape(p, 3, 3), sig_noise.T.reshape(p, 3, 3), resid,
            flags, cond, np.minimum(n_ok, 65535))


def _unit_xy(v: np.ndarray) -> np.ndarray:
    """``(v_1, v_2) / |(v_1, v_2)|`` of vectors ``(..., 3)`` (0 where that part is 0)."""
    xy = v[..., 1:3]
    norm = np.sqrt(np.einsum("...i,...i->...", xy, xy))[..., None]
    return np.where(norm > 0, xy / np.where(norm > 0, norm, 1.0), 0.0)


def _calibration_rhs(s, a_rows, wgt, x, cal_sd):
    """Right-hand sides ``sigma_p D^T W e_p`` ``(P, Q, 9)`` of the ``Q = 14`` calibration
    parameters (module docstring): (gain, angle, diattenuation) x 4 analyzers, then zero
    offset and ``1/ER``. ``s`` ``(N, 3)``, ``a_rows`` shared ``(4, 3)`` or ``(P, 4, 3)``,
    ``wgt`` ``(P, N, 4)``, ``x`` ``(9, P)`` the estimate, ``cal_sd`` the 5 standard deviations."""
    p = x.shape[1]
    n = s.shape[0]
    m = np.ascontiguousarray(np.moveaxis(x.reshape(3, 3, p), -1, 0))  # (P, 3, 3)
    a = a_rows if a_rows.ndim == 3 else a_rows[None]
    # analyzer row derivatives, row 4 q + j: relative gain, angle (rad), diattenuation
    da = np.zeros(a.shape[:-2] + (3, 4, 3))
    da[..., 0, :, :] = a
    da[..., 1, :, 1] = -2.0 * a[..., 2]
    da[..., 1, :, 2] = 2.0 * a[..., 1]
    da[..., 2, :, 1:] = a[..., :1] * _unit_xy(a)
    da = da.reshape(a.shape[:-2] + (12, 3))
    w_t = wgt.transpose(0, 2, 1)  # (P, 4, N)
    we = (da @ m @ s.T) * np.tile(w_t, (1, 3, 1))  # w e: da_j . M s_k on analyzer j only
    out = np.empty((p, 14, 3, 3))
    # D^T W e = kron(a_j, sum_k w e s_k): outer products a_j (x) (we @ s)
    out[:, :12] = (np.tile(a, (1, 3, 1))[..., :, None]
                   @ ((we @ s) * np.repeat(cal_sd[:3], 4)[:, None])[..., None, :])
    # generator state derivatives (2, N, 3): zero offset (rad), 1/ER
    ds = np.zeros((2,) + s.shape)
    ds[0, :, 1] = -2.0 * s[:, 2]
    ds[0, :, 2] = 2.0 * s[:, 1]
    ds[1, :, 0] = 0.5
    ds[1, :, 1:] = -0.5 * _unit_xy(s)
    e_g = (a @ m @ ds.reshape(2 * n, 3).T).reshape(p, 4, 2, n)  # a_j . M ds_gk
    at = np.swapaxes(a, -1, -2)  # (P or 1, 3, 4)
    for g in range(2):
        out[:, 12 + g] = (at @ (e_g[:, :, g] * w_t) @ s) * cal_sd[3 + g]
    return out.reshape(p, 14, 9)


_TRIL = np.tril_indices(9)
_TRIL_DIAG = np.flatnonzero(_TRIL[0] == _TRIL[1])
_TRIL_FLAT = _TRIL[0] * 9 + _TRIL[1]
_EYE_TRIL = (_TRIL[0] == _TRIL[1]).astype(np.float64)


def _from_tril(t: np.ndarray) -> np.ndarray:
    """``(45, P)`` lower-triangle entries -> ``(9, 9, P)`` with the lower triangle filled
    (all that :func:`_cholesky_solve` reads)."""
    out = np.zeros((9, 9, t.shape[1]))
    out[_TRIL[0], _TRIL[1]] = t
    return out


def _cholesky_solve(a: np.ndarray, b: np.ndarray, eps: float = 1e-12):
    """Batched Cholesky solve in structure-of-arrays layout (pixels last, which keeps every
    operation a long vector operation; faster than ``numpy.linalg`` on many 9x9 systems).

    ``a``: ``(n, n, P)`` symmetric positive definite (equilibrated: unit diagonal), ``b``:
    ``(n, P)``. Returns ``x = a^-1 b`` ``(n, P)``, the inverse ``L^-1`` ``(n, n, P)`` of the
    Cholesky factor (``a^-1 = L^-T L^-1``; ``diag(a^-1)`` is ``sum_k (L^-1)_ki^2``) and ``bad``
    ``(P,)``, true where a pivot fell below ``eps`` (not positive definite to working precision;
    those results are meaningless and must be masked).
    """
    n, _, p = a.shape
    low = np.zeros_like(a)
    bad = np.zeros(p, bool)
    for j in range(n):
        piv = a[j, j] - np.einsum("kp,kp->p", low[j, :j], low[j, :j]) if j else a[j, j].copy()
        bad |= ~(piv > eps)
        low[j, j] = np.sqrt(np.where(bad, 1.0, piv))
        if j + 1 < n:
            acc = a[j + 1:, j] - np.einsum("ikp,kp->ip", low[j + 1:, :j], low[j, :j]) if j else a[j + 1:, j]
            low[j + 1:, j] = acc / low[j, j]
    y = np.empty_like(b)
    for i in range(n):
        y[i] = (b[i] - np.einsum("kp,kp->p", low[i, :i], y[:i])) / low[i, i]
    x = np.empty_like(b)
    for i in range(n - 1, -1, -1):
        x[i] = (y[i] - np.einsum("kp,kp->p", low[i + 1:, i], x[i + 1:])) / low[i, i]
    inv = np.zeros_like(a)  # inverse of the Cholesky factor, lower triangular
    for i in range(n):
        inv[i, i] = 1.0 / low[i, i]
        if i:
            inv[i, :i] = -np.einsum("kp,kjp->jp", low[i, :i], inv[:i, :i]) / low[i, i]
    return x, inv, bad


