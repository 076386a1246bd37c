"""Compiled per-pixel kernels of :func:`polrig.reference.solve_reference` (numba).

The model, the masks and the calibration-uncertainty propagation are documented in
:mod:`polrig.reference`; this module only evaluates them, one pixel at a time, fused: each
pixel's ``4 N`` samples are read once (float32 or float64, any strides, converted to float64
in registers), and everything else lives in a few hundred bytes of scratch per thread.

Per pixel (analyzer rows ``a_j``, states ``s_k``, weights ``w_kj = 1 / var_kj``, used samples
only):

* ``T_j = sum_k w_kj s_k s_k^T`` (3x3) and ``r_j = sum_k w_kj I_kj s_k``; the normal matrix
  is the Kronecker sum ``D^T W D = sum_j (a_j a_j^T) (x) T_j`` (45 distinct entries from four
  3x3 blocks, ~0.4 kflop) and ``D^T W I = sum_j a_j (x) r_j``;
* equilibration ``d_i = 1 / sqrt(A_ii)``, Cholesky ``L L^T = diag(d) A diag(d)`` (a pivot
  ``<= 1e-12`` makes the pixel ILL_CONDITIONED) and the explicit inverse factor ``L^-1``;
  ``x = d L^-T L^-1 d b`` and ``sigma_noise_i = d_i |(L^-1)_{:, i}|``;
* calibration right-hand sides without forming the 4N-vectors ``e_p``: an analyzer parameter
  of row ``j`` gives ``D^T W e = a_j (x) (T_j M^T da_j)``, a generator one
  ``sum_j a_j (x) sum_k w_kj (a_j . M ds_k) s_k``; each is solved with the same ``L^-1``.

Every pixel is computed by the same sequence of IEEE operations whatever the thread or tile it
falls in (no fastmath, no reductions across pixels), so results are bit-identical for any
thread count and tiling. ``cache=True`` keeps the compiled machine code on disk (numba's cache:
``__pycache__`` next to this file, else the user cache directory, or ``NUMBA_CACHE_DIR``);
where no cache directory is writable the kernels are compiled in memory at each first call.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit, prange

log = logging.getLogger(__name__)

# mask bits, as in polrig.reference (this module must not import it: it is imported from there)
_DARK = 1
_SATURATED = 2
_ILL_CONDITIONED = 4
_NONFINITE = 8
#: smallest pivot of the equilibrated (unit-diagonal) normal matrix that counts as positive
PIVOT_EPS = 1e-12
#: pixels per block of the parallel loop (scratch arrays are allocated once per block)
_BLOCK = 256


def _jit(parallel: bool = False):
    """``numba.njit`` with ``cache=True``, falling back to an uncached kernel (compiled at each
    process's first call) where numba finds no writable cache directory."""
    def deco(fn):
        try:
            return njit(cache=True, nogil=True, parallel=parallel)(fn)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            log.debug("numba cache unavailable for %s (%s); compiling in memory", fn.__name__, exc)
            return njit(cache=False, nogil=True, parallel=parallel)(fn)
    return deco


@_jit(parallel=True)
def sample_patterns(meas, var, valid, has_valid, g0, keys):  # pragma: no cover - compiled
    """Bit patterns of the used samples of pixels ``g0 .. g0 + len(keys)`` (flat index over
    colour, row, column): bit ``r = 4 k + j`` of ``keys[i, r // 64]`` is set when sample
    ``(k, j)`` is valid, finite and has a finite positive variance."""
    n = meas.shape[0]
    height, width = meas.shape[3], meas.shape[4]
    hw = height * width
    for i in prange(keys.shape[0]):
        g = g0 + i
        c = g // hw
        p = g - c * hw
        y = p // width
        x = p - y * width
        for wd in range(keys.shape[1]):
            keys[i, wd] = 0
        for k in range(n):
            for j in range(4):
                m = meas[k, c, j, y, x]
                v = var[k, c, j, y, x]
                if has_valid and not valid[k, c, j, y, x]:
                    continue
                if math.isfinite(m) and math.isfinite(v) and v > 0:
                    r = 4 * k + j
                    keys[i, r >> 6] |= np.int64(1) << np.int64(r & 63)


@_jit()
def _cholesky_inverse(amat, dsc, low, linv):  # pragma: no cover - compiled
    """Equilibrate the lower triangle of ``amat`` (``dsc``: 1 / sqrt(diagonal)), factor it
    (``low``) and invert the factor (``linv``). False when a pivot is not above PIVOT_EPS."""
    for jj in range(9):
        acc = amat[jj, jj] * dsc[jj] * dsc[jj]
        for kk in range(jj):
            acc -= low[jj, kk] * low[jj, kk]
        if not acc > PIVOT_EPS:
            return False
        ljj = math.sqrt(acc)
        low[jj, jj] = ljj
        for ii in range(jj + 1, 9):
            acc = amat[ii, jj] * dsc[ii] * dsc[jj]
            for kk in range(jj):
                acc -= low[ii, kk] * low[jj, kk]
            low[ii, jj] = acc / ljj
    for ii in range(9):
        linv[ii, ii] = 1.0 / low[ii, ii]
        for ll in range(ii):
            acc = 0.0
            for kk in range(ll, ii):
                acc += low[ii, kk] * linv[kk, ll]
            linv[ii, ll] = -acc / low[ii, ii]
    return True


@_jit()
def _apply_inverse(linv, dsc, b, tmp, out):  # pragma: no cover - compiled
    """``out = diag(dsc) L^-T L^-1 diag(dsc) b`` (the solution of the unequilibrated system)."""
    for ii in range(9):
        acc = 0.0
        for ll in range(ii + 1):
            acc += linv[ii, ll] * (b[ll] * dsc[ll])
        tmp[ii] = acc
    for ll in range(9):
        acc = 0.0
        for ii in range(ll, 9):
            acc += linv[ii, ll] * tmp[ii]
        out[ll] = acc * dsc[ll]


@_jit()
def _calibration_variance(s, ds_gen, cal_sd, ok, w, arow, t, x, linv, dsc, e, tmp, z, acc
                          ):  # pragma: no cover - compiled
    """``acc_i = sum_p (G sigma_p e_p)_i^2`` over the 12 analyzer and 2 generator parameters
    (:mod:`polrig.reference`, "Calibration uncertainty"); ``x`` is the estimate vec(M)."""
    n = s.shape[0]
    for ii in range(9):
        acc[ii] = 0.0
    for j in range(4):
        a0, a1, a2 = arow[j, 0], arow[j, 1], arow[j, 2]
        nrm = math.sqrt(a1 * a1 + a2 * a2)
        for q in range(3):
            sd = cal_sd[q]
            if sd == 0.0:
                continue
            if q == 0:  # relative gain: da = a
                d0, d1, d2 = a0, a1, a2
            elif q == 1:  # orientation, per rad
                d0, d1, d2 = 0.0, -2.0 * a2, 2.0 * a1
            elif nrm > 0:  # diattenuation: a_0 (0, cos 2t, sin 2t)
                d0, d1, d2 = 0.0, a0 * (a1 / nrm), a0 * (a2 / nrm)
            else:
                d0, d1, d2 = 0.0, 0.0, 0.0
            # u = M^T da, v = T_j u, e = sd a_j (x) v
            u0 = d0 * x[0] + d1 * x[3] + d2 * x[6]
            u1 = d0 * x[1] + d1 * x[4] + d2 * x[7]
            u2 = d0 * x[2] + d1 * x[5] + d2 * x[8]
            for b in range(3):
                vb = (t[j, b, 0] * u0 + t[j, b, 1] * u1 + t[j, b, 2] * u2) * sd
                e[b] = arow[j, 0] * vb
                e[3 + b] = arow[j, 1] * vb
                e[6 + b] = arow[j, 2] * vb
            _apply_inverse(linv, dsc, e, tmp, z)
            for ii in range(9):
                acc[ii] += z[ii] * z[ii]
    for gq in range(2):
        sd = cal_sd[3 + gq]
        if sd == 0.0:
            continue
        for ii in range(9):
            e[ii] = 0.0
        for j in range(4):
            # h = M^T a_j; e_kj = w_kj (h . ds_k); e += a_j (x) sum_k e_kj s_k
            h0 = arow[j, 0] * x[0] + arow[j, 1] * x[3] + arow[j, 2] * x[6]
            h1 = arow[j, 0] * x[1] + arow[j, 1] * x[4] + arow[j, 2] * x[7]
            h2 = arow[j, 0] * x[2] + arow[j, 1] * x[5] + arow[j, 2] * x[8]
            v0 = 0.0
            v1 = 0.0
            v2 = 0.0
            for k in range(n):
                r = 4 * k + j
                if ok[r]:
                    ekj = w[r] * (h0 * ds_gen[gq, k, 0] + h1 * ds_gen[gq, k, 1]
                                  + h2 * ds_gen[gq, k, 2])
                    v0 += ekj * s[k, 0]
                    v1 += ekj * s[k, 1]
                    v2 += ekj * s[k, 2]
            for a in range(3):
                e[3 * a] += arow[j, a] * v0
                e[3 * a + 1] += arow[j, a] * v1
                e[3 * a + 2] += arow[j, a] * v2
        for ii in range(9):
            e[ii] *= sd
        _apply_inverse(linv, dsc, e, tmp, z)
        for ii in range(9):
            acc[ii] += z[ii] * z[ii]


@_jit(parallel=True)
def solve_pixels(s, ds_gen, meas, var, valid, has_valid, rows, cond, g0, max_condition,
                 min_snr, out_max, cal_sd, with_cal, mueller, sigma, sigma_noise, residual,
                 mask, n_used):  # pragma: no cover - compiled
    """Solve pixels ``g0 .. g0 + len(cond)`` (flat index over colour, row, column) and write
    their outputs.

    ``s`` ``(N, 3)``; ``ds_gen`` ``(2, N, 3)`` the generator state derivatives (zero offset
    per rad, 1/ER); ``meas``, ``var`` ``(N, C, 4, H, W)``; ``valid`` the same shape (read only
    with ``has_valid``); ``rows`` ``(C' , 4, 3, H', W')`` with ``C'``, ``H'``, ``W'`` either the
    image's or 1 (broadcast); ``cond`` the condition number of each pixel's used design;
    ``out_max`` the largest magnitude the output dtype holds; ``cal_sd`` the 5 calibration
    standard deviations (used with ``with_cal``). Outputs ``mueller``, ``sigma``,
    ``sigma_noise`` ``(C, 3, 3, H, W)`` (``sigma_noise`` written only with ``with_cal``),
    ``residual``, ``mask``, ``n_used`` ``(C, H, W)``, zero-initialised by the caller
    (unsolved pixels are not written).
    """
    n = s.shape[0]
    nr = 4 * n
    height, width = meas.shape[3], meas.shape[4]
    hw = height * width
    count = cond.shape[0]
    row_c = rows.shape[0] > 1
    row_y = rows.shape[3] > 1
    row_x = rows.shape[4] > 1
    for blk in prange((count + _BLOCK - 1) // _BLOCK):
        w = np.empty(nr)
        mv = np.empty(nr)
        ok = np.empty(nr, np.bool_)
        arow = np.empty((4, 3))
        t = np.empty((4, 3, 3))
        rj = np.empty((4, 3))
        amat = np.empty((9, 9))
        low = np.empty((9, 9))
        linv = np.empty((9, 9))
        dsc = np.empty(9)
        rhs = np.empty(9)
        x = np.empty(9)
        sn = np.empty(9)
        sg = np.empty(9)
        e = np.empty(9)
        tmp = np.empty(9)
        z = np.empty(9)
        acc = np.empty(9)
        for i in range(blk * _BLOCK, min(count, (blk + 1) * _BLOCK)):
            g = g0 + i
            c = g // hw
            p = g - c * hw
            yy = p // width
            xx = p - yy * width
            # -- samples: used ones, exclusion flags
            flags = 0
            nok = 0
            for k in range(n):
                for j in range(4):
                    r = 4 * k + j
                    m = meas[k, c, j, yy, xx]
                    v = var[k, c, j, yy, xx]
                    given = valid[k, c, j, yy, xx] if has_valid else True
                    good = math.isfinite(m) and math.isfinite(v) and v > 0
                    if not given:
                        flags |= _SATURATED
                    elif not good:
                        flags |= _NONFINITE
                    if given and good:
                        ok[r] = True
                        w[r] = 1.0 / np.float64(v)
                        mv[r] = m
                        nok += 1
                    else:
                        ok[r] = False
                        w[r] = 0.0
                        mv[r] = 0.0
            n_used[c, yy, xx] = min(nok, 65535)
            if not cond[i] <= max_condition:
                mask[c, yy, xx] = flags | _ILL_CONDITIONED
                continue
            # -- normal equations, Kronecker form
            rc = c if row_c else 0
            ry = yy if row_y else 0
            rx = xx if row_x else 0
            for j in range(4):
                for a in range(3):
                    arow[j, a] = rows[rc, j, a, ry, rx]
                t00 = t10 = t11 = t20 = t21 = t22 = 0.0
                r0 = r1 = r2 = 0.0
                for k in range(n):
                    r = 4 * k + j
                    if ok[r]:
                        s0, s1, s2 = s[k, 0], s[k, 1], s[k, 2]
                        wr = w[r]
                        wm = wr * mv[r]
                        r0 += wm * s0
                        r1 += wm * s1
                        r2 += wm * s2
                        w0 = wr * s0
                        w1 = wr * s1
                        w2 = wr * s2
                        t00 += w0 * s0
                        t10 += w1 * s0
                        t11 += w1 * s1
                        t20 += w2 * s0
                        t21 += w2 * s1
                        t22 += w2 * s2
                t[j, 0, 0] = t00
                t[j, 1, 0] = t[j, 0, 1] = t10
                t[j, 1, 1] = t11
                t[j, 2, 0] = t[j, 0, 2] = t20
                t[j, 2, 1] = t[j, 1, 2] = t21
                t[j, 2, 2] = t22
                rj[j, 0] = r0
                rj[j, 1] = r1
                rj[j, 2] = r2
            for ii in range(9):
                ia = ii // 3
                ib = ii - 3 * ia
                for ll in range(ii + 1):
                    la = ll // 3
                    lb = ll - 3 * la
                    sacc = 0.0
                    for j in range(4):
                        sacc += arow[j, ia] * arow[j, la] * t[j, ib, lb]
                    amat[ii, ll] = sacc
                sacc = 0.0
                for j in range(4):
                    sacc += arow[j, ia] * rj[j, ib]
                rhs[ii] = sacc
            for ii in range(9):
                dg = amat[ii, ii]
                dsc[ii] = 1.0 / math.sqrt(dg) if dg > 0 else 1.0
            if not _cholesky_inverse(amat, dsc, low, linv):
                mask[c, yy, xx] = flags | _ILL_CONDITIONED
                continue
            _apply_inverse(linv, dsc, rhs, tmp, x)
            for ll in range(9):
                sacc = 0.0
                for ii in range(ll, 9):
                    sacc += linv[ii, ll] * linv[ii, ll]
                sn[ll] = dsc[ll] * math.sqrt(sacc)
            if with_cal:
                _calibration_variance(s, ds_gen, cal_sd, ok, w, arow, t, x, linv, dsc, e, tmp,
                                      z, acc)
                for ll in range(9):
                    sg[ll] = math.sqrt(sn[ll] * sn[ll] + acc[ll])
            else:
                for ll in range(9):
                    sg[ll] = sn[ll]
            # -- residual chi^2 / dof
            chi2 = 0.0
            for k in range(n):
                s0, s1, s2 = s[k, 0], s[k, 1], s[k, 2]
                ms0 = x[0] * s0 + x[1] * s1 + x[2] * s2
                ms1 = x[3] * s0 + x[4] * s1 + x[5] * s2
                ms2 = x[6] * s0 + x[7] * s1 + x[8] * s2
                for j in range(4):
                    r = 4 * k + j
                    if ok[r]:
                        dv = mv[r] - (arow[j, 0] * ms0 + arow[j, 1] * ms1 + arow[j, 2] * ms2)
                        chi2 += w[r] * dv * dv
            dof = nok - 9
            res = chi2 / dof if dof > 0 else 0.0
            # -- every output finite and representable in the output dtype, else unsolved
            fine = abs(res) <= out_max
            for ll in range(9):
                fine = fine and abs(x[ll]) <= out_max and sg[ll] <= out_max
            if not fine:
                mask[c, yy, xx] = flags | _ILL_CONDITIONED
                continue
            if not x[0] >= min_snr * sg[0]:
                flags |= _DARK
            mask[c, yy, xx] = flags
            residual[c, yy, xx] = res
            for ll in range(9):
                ia = ll // 3
                ib = ll - 3 * ia
                mueller[c, ia, ib, yy, xx] = x[ll]
                sigma[c, ia, ib, yy, xx] = sg[ll]
                if with_cal:
                    sigma_noise[c, ia, ib, yy, xx] = sn[ll]
