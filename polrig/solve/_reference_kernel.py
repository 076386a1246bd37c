"""Compiled kernels of :func:`polrig.solve.reference.solve_reference` (numba).

The model, the masks and the calibration-uncertainty propagation are documented in
:mod:`polrig.solve.reference`; this module evaluates them for one tile of image rows at a time, in
three kernels the caller runs in turn on a thread (they release the GIL):

* :func:`load_tile` reads the tile's samples once (float32 or float64, any strides; the only
  kernel, with :func:`store_tile`, that is compiled again for other input dtypes) into
  block-major float64 buffers: blocks of :data:`LANES` neighbouring pixels of one row,
  laid out lanes-last;
* :func:`solve_blocks` does all the arithmetic on those buffers. Every loop runs over the
  lanes, so it compiles to SIMD code (the per-pixel 9x9 algebra is too small and too
  sequential to vectorise by itself: a scalar per-pixel version of this kernel was 2-3x
  slower). Its signature is fixed (float64 buffers): it is compiled once, whatever the input
  and output dtypes. The lane count is a run-time argument: with a constant trip count LLVM
  unrolls every loop, which multiplied the compile time and defeated the vectoriser;
* :func:`store_tile` writes the results into the output images (float32 or float64).

Per pixel (analyzer rows ``a_j``, states ``s_k``, weights ``w_kj = 1 / var_kj``, 0 for
excluded samples):

* ``T_j = sum_k w_kj s_k s_k^T`` (3x3) and ``r_j = sum_k w_kj I_kj s_k``; the normal matrix
  is the Kronecker sum ``D^T W D = sum_j (a_j a_j^T) (x) T_j`` (45 distinct entries from four
  3x3 blocks) and ``D^T W I = sum_j a_j (x) r_j``;
* equilibration ``d_i = 1 / sqrt(A_ii)``, Cholesky ``L L^T = diag(d) A diag(d)`` (a pivot
  ``<= 1e-12`` makes the pixel ILL_CONDITIONED; with a prior also fewer samples used than the
  nine elements less the prior's rank, a diagonal ``A_ii <= 1e-12 max A_jj``, or an inverse
  diagonal of the equilibrated matrix above ``1e12``: singular, whatever the pivots show), the
  inverse factor ``L^-1``;
  ``x = d L^-T L^-1 d b`` and ``sigma_noise_i = d_i |(L^-1)_{:, i}|``;
* with calibration tolerances, the explicit ``A^-1`` and the 14 calibration right-hand sides
  without forming the 4N-vectors ``e_p``: an analyzer parameter of row ``j`` gives
  ``D^T W e = a_j (x) (T_j M^T da_j)``, solved as ``P_j (T_j M^T da_j)`` with
  ``P_j = A^-1 (a_j (x) I_3)`` shared by the row's three parameters; a generator parameter
  gives ``sum_j a_j (x) sum_k w_kj (a_j . M ds_k) s_k``.

Determinism: no fastmath (IEEE semantics: SIMD and scalar code give the same bits), no
reductions across pixels, and the estimate and noise sigma are computed by the same
operations with and without the calibration term; results are bit-identical for any thread
count and tile size. ``cache=True`` keeps the machine code on disk (numba's cache:
``__pycache__`` next to this file, else the user cache directory, or ``NUMBA_CACHE_DIR``);
where none is writable the kernels are compiled at each process's first call.
``error_model="numpy"``: a division by zero gives inf/NaN (masked afterwards) instead of a
branch and an exception, which SIMD code cannot have.
"""

from __future__ import annotations

import logging
import os

import numba
import numpy as np
from numba import njit

log = logging.getLogger(__name__)

# mask bits, as in polrig.solve.reference (which imports this module, not the other way round)
_DARK = 1
_SATURATED = 2
_ILL_CONDITIONED = 4
_NONFINITE = 8
#: smallest pivot of the equilibrated (unit-diagonal) normal matrix that counts as positive
PIVOT_EPS = 1e-12
#: largest diagonal element of the inverse of the equilibrated normal matrix of a pixel with a
#: prior (:mod:`polrig.solve.hybrid`): beyond it (its smallest eigenvalue is then below about
#: 1e-13) the posterior counts as singular, also where no single Cholesky pivot is that small
INVERSE_DIAG_MAX = 1.0 / PIVOT_EPS
#: pixels of one row solved together (the SIMD width of every loop; a partial block at the
#: end of a row is padded with copies of its last pixel, which are not written)
LANES = 64


def jit_cached():
    """``numba.njit`` (nogil: the caller runs tiles or pixel chunks on threads) with
    ``cache=True``, falling back to an uncached kernel (compiled at each process's first call)
    where numba finds no writable cache directory. The decorator of every compiled kernel of
    :mod:`polrig.solve` (this one's and :mod:`polrig.solve._reduced_kernel`'s)."""
    opts = dict(nogil=True, error_model="numpy")

    def deco(fn):
        try:
            return njit(cache=True, **opts)(fn)
        except RuntimeError as exc:  # "cannot cache function ...: no locator available"
            log.debug("numba cache unavailable for %s (%s); compiling in memory", fn.__name__, exc)
            return njit(cache=False, **opts)(fn)
    return deco


#: threads the solve runs tiles on: numba's setting (NUMBA_NUM_THREADS, default the CPU
#: count), at most the CPUs this process may run on
THREADS = max(1, min(int(numba.config.NUMBA_NUM_THREADS), len(os.sched_getaffinity(0))
                     if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


@jit_cached()
def load_tile(meas, var, valid, has_valid, rows, per_pixel_rows, c, y0, y1, w, mv, flags, arow
              ):  # pragma: no cover - compiled
    """Read image rows ``y0 .. y1`` of colour ``c`` into block-major float64 buffers: each
    image row is ``ceil(W / LANES)`` blocks, column ``x`` is lane ``x % LANES`` of the row's
    block ``x // LANES``; lanes past the row's end keep weight 0 (the caller zeroes them
    once). ``w`` ``(B, 4N, LANES)`` the weights ``1 / var`` (0 for an excluded sample), ``mv``
    the values (0 when excluded), ``flags`` ``(B, LANES)`` SATURATED / NONFINITE exclusion
    bits; with ``per_pixel_rows`` also ``arow`` ``(B, 4, 3, LANES)`` from ``rows``
    ``(C', 4, 3, H', W')`` (``C'``, ``H'``, ``W'`` the image's or 1). ``meas``, ``var``,
    ``valid``: ``(N, C, 4, H, W)`` (``valid`` read only with ``has_valid``). Returns the
    number of pixels with an excluded sample (0: every pixel uses all its samples)."""
    n = meas.shape[0]
    width = meas.shape[4]
    nbr = (width + LANES - 1) // LANES
    rc = c if rows.shape[0] > 1 else 0
    partial = 0
    for yy in range(y0, y1):
        ry = yy if rows.shape[3] > 1 else 0
        for xb in range(nbr):
            b = (yy - y0) * nbr + xb
            x0 = xb * LANES
            nb = min(LANES, width - x0)
            for q in range(nb):
                flags[b, q] = 0
            for k in range(n):
                for j in range(4):
                    r = 4 * k + j
                    for q in range(nb):
                        xx = x0 + q
                        m = np.float64(meas[k, c, j, yy, xx])
                        v = np.float64(var[k, c, j, yy, xx])
                        given = valid[k, c, j, yy, xx] if has_valid else True
                        good = (abs(m) < np.inf) & (abs(v) < np.inf) & (v > 0)
                        use = given & good
                        w[b, r, q] = 1.0 / v if use else 0.0
                        mv[b, r, q] = m if use else 0.0
                        flags[b, q] |= ((0 if given else _SATURATED)
                                        | (_NONFINITE if given & (not good) else 0))
            for q in range(nb):
                partial += 1 if flags[b, q] != 0 else 0
            if per_pixel_rows:
                for j in range(4):
                    for a in range(3):
                        for q in range(nb):
                            rx = x0 + q if rows.shape[4] > 1 else 0
                            arow[b, j, a, q] = rows[rc, j, a, ry, rx]
    return partial


@jit_cached()
def store_tile(c, y0, y1, x, sg, sn, res, flags, nok, with_cal, mueller, sigma, sigma_noise,
               residual, mask, n_used):  # pragma: no cover - compiled
    """Write a tile's block-major results (:func:`solve_blocks`, layout of
    :func:`load_tile`) into the output images, rows ``y0 .. y1`` of colour ``c`` (converted
    to the outputs' dtype)."""
    width = mueller.shape[4]
    nbr = (width + LANES - 1) // LANES
    for yy in range(y0, y1):
        for xb in range(nbr):
            b = (yy - y0) * nbr + xb
            x0 = xb * LANES
            nb = min(LANES, width - x0)
            for ll in range(9):
                ia = ll // 3
                ib = ll - 3 * ia
                for q in range(nb):
                    mueller[c, ia, ib, yy, x0 + q] = x[b, ll, q]
                for q in range(nb):
                    sigma[c, ia, ib, yy, x0 + q] = sg[b, ll, q]
                if with_cal:
                    for q in range(nb):
                        sigma_noise[c, ia, ib, yy, x0 + q] = sn[b, ll, q]
            for q in range(nb):
                residual[c, yy, x0 + q] = res[b, q]
                mask[c, yy, x0 + q] = flags[b, q]
                n_used[c, yy, x0 + q] = min(nok[b, q], 65535)


@jit_cached()
def _normal_equations(s, w, mv, arow, per_pixel_rows, t, rj, amat, rhs
                      ):  # pragma: no cover - compiled
    """``T_j``, ``r_j``, then the lower triangle of ``D^T W D`` and ``D^T W I`` per lane
    (``arow`` ``(4, 3, L)``: the same in every lane unless ``per_pixel_rows``)."""
    d9, nl = rhs.shape
    n = s.shape[0]
    t[...] = 0.0
    rj[...] = 0.0
    for j in range(4):
        for k in range(n):
            r = 4 * k + j
            s0, s1, s2 = s[k, 0], s[k, 1], s[k, 2]
            for q in range(nl):
                wr = w[r, q]
                wm = wr * mv[r, q]
                rj[j, 0, q] += wm * s0
                rj[j, 1, q] += wm * s1
                rj[j, 2, q] += wm * s2
                t[j, 0, 0, q] += wr * s0 * s0
                t[j, 1, 0, q] += wr * s1 * s0
                t[j, 1, 1, q] += wr * s1 * s1
                t[j, 2, 0, q] += wr * s2 * s0
                t[j, 2, 1, q] += wr * s2 * s1
                t[j, 2, 2, q] += wr * s2 * s2
        for b in range(3):
            for d in range(b):
                for q in range(nl):
                    t[j, d, b, q] = t[j, b, d, q]
    for ii in range(d9):
        ia = ii // 3
        ib = ii - 3 * ia
        for ll in range(ii + 1):
            la = ll // 3
            lb = ll - 3 * la
            if per_pixel_rows:
                for q in range(nl):
                    amat[ii, ll, q] = (arow[0, ia, q] * arow[0, la, q] * t[0, ib, lb, q]
                                       + arow[1, ia, q] * arow[1, la, q] * t[1, ib, lb, q]
                                       + arow[2, ia, q] * arow[2, la, q] * t[2, ib, lb, q]
                                       + arow[3, ia, q] * arow[3, la, q] * t[3, ib, lb, q])
            else:  # the same products, with the lane-independent factors hoisted
                c0 = arow[0, ia, 0] * arow[0, la, 0]
                c1 = arow[1, ia, 0] * arow[1, la, 0]
                c2 = arow[2, ia, 0] * arow[2, la, 0]
                c3 = arow[3, ia, 0] * arow[3, la, 0]
                for q in range(nl):
                    amat[ii, ll, q] = (c0 * t[0, ib, lb, q] + c1 * t[1, ib, lb, q]
                                       + c2 * t[2, ib, lb, q] + c3 * t[3, ib, lb, q])
        for q in range(nl):
            rhs[ii, q] = (arow[0, ia, q] * rj[0, ib, q] + arow[1, ia, q] * rj[1, ib, q]
                          + arow[2, ia, q] * rj[2, ib, q] + arow[3, ia, q] * rj[3, ib, q])


@jit_cached()
def _factor(amat, dsc, low, rl, bad):  # pragma: no cover - compiled
    """Per lane: equilibration ``dsc = 1 / sqrt(diag A)`` of the normal matrix ``A`` (lower
    triangle in ``amat``, used as scratch afterwards), the Cholesky factor of the
    equilibrated matrix and then its inverse ``L^-1`` in ``low`` (``rl``: the reciprocal
    diagonal of ``L``). ``bad`` where a pivot is not above PIVOT_EPS (that lane's results are
    meaningless)."""
    d9, nl = dsc.shape
    for ii in range(d9):
        for q in range(nl):
            dg = amat[ii, ii, q]
            dsc[ii, q] = 1.0 / np.sqrt(dg) if dg > 0 else 1.0
    for q in range(nl):
        bad[q] = False
    for jj in range(d9):
        for q in range(nl):
            rl[jj, q] = amat[jj, jj, q] * dsc[jj, q] * dsc[jj, q]  # the pivot, accumulated
        for kk in range(jj):
            for q in range(nl):
                rl[jj, q] -= low[jj, kk, q] * low[jj, kk, q]
        for q in range(nl):
            piv = rl[jj, q]
            fine = piv > PIVOT_EPS
            bad[q] |= not fine
            ljj = np.sqrt(piv) if fine else 1.0
            low[jj, jj, q] = ljj
            rl[jj, q] = 1.0 / ljj
        for ii in range(jj + 1, d9):
            for q in range(nl):
                low[ii, jj, q] = amat[ii, jj, q] * dsc[ii, q] * dsc[jj, q]
            for kk in range(jj):
                for q in range(nl):
                    low[ii, jj, q] -= low[ii, kk, q] * low[jj, kk, q]
            for q in range(nl):
                low[ii, jj, q] *= rl[jj, q]
    # L^-1 in place, row by row (row ii needs rows < ii of L^-1 and row ii of L)
    for ii in range(d9):
        for ll in range(ii):
            for q in range(nl):
                amat[0, ll, q] = low[ii, ll, q] * low[ll, ll, q]  # scratch: L_il (L^-1)_ll
            for kk in range(ll + 1, ii):
                for q in range(nl):
                    amat[0, ll, q] += low[ii, kk, q] * low[kk, ll, q]
        for ll in range(ii):
            for q in range(nl):
                low[ii, ll, q] = -amat[0, ll, q] * rl[ii, q]
        for q in range(nl):
            low[ii, ii, q] = rl[ii, q]


@jit_cached()
def _inverse(low, dsc, amat):  # pragma: no cover - compiled
    """Per lane, the full symmetric ``A^-1 = diag(dsc) L^-T L^-1 diag(dsc)`` into ``amat``
    (``low``: ``L^-1``)."""
    d9, nl = dsc.shape
    for ii in range(d9):
        for ll in range(ii + 1):
            for q in range(nl):
                amat[ii, ll, q] = low[ii, ii, q] * low[ii, ll, q]
            for kk in range(ii + 1, d9):
                for q in range(nl):
                    amat[ii, ll, q] += low[kk, ii, q] * low[kk, ll, q]
            for q in range(nl):
                amat[ii, ll, q] *= dsc[ii, q] * dsc[ll, q]
                amat[ll, ii, q] = amat[ii, ll, q]


@jit_cached()
def _triangular_solve(linv, dsc, b, tmp, out):  # pragma: no cover - compiled
    """``out = diag(dsc) L^-T L^-1 diag(dsc) b`` per lane, with the inverse factor."""
    d9, nl = b.shape
    for ii in range(d9):
        for q in range(nl):
            tmp[ii, q] = 0.0
        for ll in range(ii + 1):
            for q in range(nl):
                tmp[ii, q] += linv[ii, ll, q] * (b[ll, q] * dsc[ll, q])
    for ll in range(d9):
        for q in range(nl):
            out[ll, q] = 0.0
        for ii in range(ll, d9):
            for q in range(nl):
                out[ll, q] += linv[ii, ll, q] * tmp[ii, q]
        for q in range(nl):
            out[ll, q] *= dsc[ll, q]


@jit_cached()
def _calibration_variance(s, ds_gen, cal_sd, w, arow, per_pixel_rows, t, x, ainv, pj, e, z, u,
                          acc):  # pragma: no cover - compiled
    """``acc_i = sum_p (G sigma_p e_p)_i^2`` per lane over the 12 analyzer and 2 generator
    parameters (:mod:`polrig.solve.reference`, "Calibration uncertainty"); ``x`` the estimate,
    ``ainv`` the full ``A^-1``. An analyzer parameter of row ``j`` has
    ``G e = A^-1 (a_j (x) T_j M^T da) = P_j T_j M^T da`` with ``P_j = A^-1 (a_j (x) I_3)``."""
    d9, nl = x.shape
    n = s.shape[0]
    acc[...] = 0.0
    sg_gain, sg_ang, sg_dia = cal_sd[0], cal_sd[1], cal_sd[2]
    for j in range(4):
        if sg_gain == 0.0 and sg_ang == 0.0 and sg_dia == 0.0:
            break
        c0, c1, c2 = arow[j, 0, 0], arow[j, 1, 0], arow[j, 2, 0]
        for ii in range(d9):
            for b in range(3):
                if per_pixel_rows:
                    for q in range(nl):
                        pj[ii, b, q] = (ainv[ii, b, q] * arow[j, 0, q]
                                        + ainv[ii, 3 + b, q] * arow[j, 1, q]
                                        + ainv[ii, 6 + b, q] * arow[j, 2, q])
                else:  # the same products, lane-independent factors hoisted
                    for q in range(nl):
                        pj[ii, b, q] = (ainv[ii, b, q] * c0 + ainv[ii, 3 + b, q] * c1
                                        + ainv[ii, 6 + b, q] * c2)
        # e[3 p + b] = sd_p (T_j M^T da_p)_b for gain, orientation (per rad), diattenuation
        for q in range(nl):
            a0, a1, a2 = arow[j, 0, q], arow[j, 1, q], arow[j, 2, q]
            nrm = np.sqrt(a1 * a1 + a2 * a2)
            f = a0 / nrm if nrm > 0 else 0.0
            # M^T a (gain) and M^T (0, c, s) for the orientation (0, -2 a2, 2 a1) and the
            # diattenuation f (0, a1, a2) derivatives
            g0 = a0 * x[0, q] + a1 * x[3, q] + a2 * x[6, q]
            g1 = a0 * x[1, q] + a1 * x[4, q] + a2 * x[7, q]
            g2 = a0 * x[2, q] + a1 * x[5, q] + a2 * x[8, q]
            o0 = 2.0 * (a1 * x[6, q] - a2 * x[3, q])
            o1 = 2.0 * (a1 * x[7, q] - a2 * x[4, q])
            o2 = 2.0 * (a1 * x[8, q] - a2 * x[5, q])
            h0 = f * (a1 * x[3, q] + a2 * x[6, q])
            h1 = f * (a1 * x[4, q] + a2 * x[7, q])
            h2 = f * (a1 * x[5, q] + a2 * x[8, q])
            for b in range(3):
                tb0, tb1, tb2 = t[j, b, 0, q], t[j, b, 1, q], t[j, b, 2, q]
                e[b, q] = (tb0 * g0 + tb1 * g1 + tb2 * g2) * sg_gain
                e[3 + b, q] = (tb0 * o0 + tb1 * o1 + tb2 * o2) * sg_ang
                e[6 + b, q] = (tb0 * h0 + tb1 * h1 + tb2 * h2) * sg_dia
        for ii in range(d9):
            for q in range(nl):
                p0, p1, p2 = pj[ii, 0, q], pj[ii, 1, q], pj[ii, 2, q]
                z0 = p0 * e[0, q] + p1 * e[1, q] + p2 * e[2, q]
                z1 = p0 * e[3, q] + p1 * e[4, q] + p2 * e[5, q]
                z2 = p0 * e[6, q] + p1 * e[7, q] + p2 * e[8, q]
                acc[ii, q] += z0 * z0 + z1 * z1 + z2 * z2
    sg_zero, sg_er = cal_sd[3], cal_sd[4]
    if sg_zero == 0.0 and sg_er == 0.0:
        return
    # right-hand sides of the stage zero offset (e) and 1/ER (z), both at once
    for ii in range(d9):
        for q in range(nl):
            e[ii, q] = 0.0
            z[ii, q] = 0.0
    for j in range(4):
        for q in range(nl):  # u = M^T a_j; v, v' = sum_k w_kj (u . ds_k) sd s_k
            u[0, q] = arow[j, 0, q] * x[0, q] + arow[j, 1, q] * x[3, q] + arow[j, 2, q] * x[6, q]
            u[1, q] = arow[j, 0, q] * x[1, q] + arow[j, 1, q] * x[4, q] + arow[j, 2, q] * x[7, q]
            u[2, q] = arow[j, 0, q] * x[2, q] + arow[j, 1, q] * x[5, q] + arow[j, 2, q] * x[8, q]
            for b in range(3, 9):
                u[b, q] = 0.0
        for k in range(n):
            r = 4 * k + j
            f0, f1, f2 = (ds_gen[0, k, 0] * sg_zero, ds_gen[0, k, 1] * sg_zero,
                          ds_gen[0, k, 2] * sg_zero)
            h0, h1, h2 = ds_gen[1, k, 0] * sg_er, ds_gen[1, k, 1] * sg_er, ds_gen[1, k, 2] * sg_er
            s0, s1, s2 = s[k, 0], s[k, 1], s[k, 2]
            for q in range(nl):
                wr = w[r, q]
                ez = wr * (u[0, q] * f0 + u[1, q] * f1 + u[2, q] * f2)
                ee = wr * (u[0, q] * h0 + u[1, q] * h1 + u[2, q] * h2)
                u[3, q] += ez * s0
                u[4, q] += ez * s1
                u[5, q] += ez * s2
                u[6, q] += ee * s0
                u[7, q] += ee * s1
                u[8, q] += ee * s2
        for a in range(3):  # += a_j (x) v
            for q in range(nl):
                aj = arow[j, a, q]
                e[3 * a, q] += aj * u[3, q]
                e[3 * a + 1, q] += aj * u[4, q]
                e[3 * a + 2, q] += aj * u[5, q]
                z[3 * a, q] += aj * u[6, q]
                z[3 * a + 1, q] += aj * u[7, q]
                z[3 * a + 2, q] += aj * u[8, q]
    for ii in range(d9):  # acc += (A^-1 e)^2 + (A^-1 z)^2
        for q in range(nl):
            ge = 0.0
            gz = 0.0
            for ll in range(9):
                ge += ainv[ii, ll, q] * e[ll, q]
                gz += ainv[ii, ll, q] * z[ll, q]
            acc[ii, q] += ge * ge + gz * gz


@jit_cached()
def _add_prior(pa, pm, amat, rhs):  # pragma: no cover - compiled
    """``A += P`` (lower triangle) and ``b += P mu`` per lane (``pa`` ``(9, 9, L)`` the full
    symmetric ``P``, ``pm`` ``(9, L)``)."""
    d9, nl = rhs.shape
    for ii in range(d9):
        for ll in range(ii + 1):
            for q in range(nl):
                amat[ii, ll, q] += pa[ii, ll, q]
        for ll in range(d9):
            for q in range(nl):
                rhs[ii, q] += pa[ii, ll, q] * pm[ll, q]


@jit_cached()
def load_prior(mean, sigma, c, y0, y1, seen_dir, seen_axis, seen_k, seen_share, w, flags, arow, per_pixel_rows,
               pa, pm, prank):  # pragma: no cover - compiled
    """The prior of rows ``y0 .. y1`` of colour ``c`` into block-major buffers (layout of
    :func:`load_tile`, which must have filled ``w``, ``flags`` and, with ``per_pixel_rows``,
    ``arow`` first), as :mod:`polrig.solve.hybrid` derives it.

    ``mean``, ``sigma`` ``(C, 3, 3, H, W)`` (any float dtype and strides). An element's prior
    is used where its mean is finite and its precision ``pi = 1 / sigma^2`` is finite and
    positive; ``sigma`` 0, ``+inf`` or so large that ``pi`` underflows means no prior for that
    element; a NaN or negative sigma, a non-finite mean with a usable sigma, or a ``pi``
    beyond float64 set NONFINITE in ``flags``.

    ``seen_k >= 0``: the prior is a function of the frame of state ``seen_k``, whose unit
    Stokes direction is ``seen_dir`` (``u``). Its used samples ``j`` (``w > 0``) observe the
    directions ``a_j (x) u`` of ``vec(M)``; the prior's information on those is removed
    (a Schur complement): ``P = Pi - T K T^T`` with ``Pi = diag(pi)``, ``T`` ``(9, 3)`` the
    block columns ``t_r = Pi_r u`` (row ``r`` of ``M``), ``K = B (B^T C B)^+ B^T`` over the
    span ``B`` of the used analyzer rows and ``C = diag(u^T Pi_r u)``. With 3 or more used
    samples (they observe ``M s`` whole) ``K = C^+`` and ``P`` is block diagonal,
    the Schur complement ``S_r = Pi_r - t_r t_r^T / c_r`` (evaluated without cancellation,
    ``S_aa = pi_a sum_{k != a} pi_k u_k^2 / c_r``) with the row's prior variance along ``u``,
    ``alpha_r = seen_share_r sum u_a^2 sigma_a^2`` over its used elements (``seen_share`` ``(3,)``:
    the part of it kept per row, 1 all of it; :mod:`polrig.solve.hybrid`, "The seen direction's
    share"), moved onto the plane's axis ``v1``
    ``seen_axis`` (:func:`polrig.solve.hybrid.plane_axis`): ``P_r = (S_r + alpha_r det_r v2 v2^T) /
    (1 + alpha_r v1^T S_r v1)`` with ``v2 = v1 x u`` and ``det_r`` the determinant of ``S_r`` on
    the plane (``pi_0 pi_1 pi_2 / c_r``; 0 where an element has no prior); with ``seen_axis`` all 0 (a seen state without an angle) the
    scalar ``P_r = g_r S_r`` with
    ``g_r = sum (1 - u_a^2) sigma_a^2 / (sum (1 - u_a^2) sigma_a^2 + seen_share_r sum u_a^2 sigma_a^2)``.
    Either way the row's prior variance (all of it at ``seen_share`` 1) stays in its unobserved
    plane; with 1 or 2 the plain Schur complement of the general form,
    computed as ``R (I - E E^T) R`` (``R = Pi^1/2``, ``E`` an orthonormal basis of ``R B``, Gram-Schmidt
    twice): no inverse of ``B^T Pi B``, which can be nearly singular.
    ``seen_k < 0``: ``P = Pi``.

    Writes ``pa`` ``(B, 9, 9, L)`` (the full symmetric ``P``), ``pm`` ``(B, 9, L)`` (the mean,
    0 where unused) and ``prank`` ``(B, L)``: the number of directions ``P`` informs (0: no
    prior at this pixel, which is then solved from its samples alone)."""
    width = mean.shape[4]
    nbr = (width + LANES - 1) // LANES
    pi = np.empty(9)
    tt = np.empty(9)
    cc = np.empty(3)
    u2 = np.empty(3)
    rp = np.empty(9)
    zz = np.empty((2, 9))
    nz = np.empty(2)
    used = np.empty(4, np.int64)
    srow = np.empty((3, 3))
    sv = np.empty(3)
    for a in range(3):
        u2[a] = seen_dir[a] * seen_dir[a]
    directional = seen_axis[0] * seen_axis[0] + seen_axis[1] * seen_axis[1] + seen_axis[2] * seen_axis[2] > 0
    # v2 = v1 x u: the plane's other axis (light at 45 deg to the seen state)
    sv[0] = seen_axis[1] * seen_dir[2] - seen_axis[2] * seen_dir[1]
    sv[1] = seen_axis[2] * seen_dir[0] - seen_axis[0] * seen_dir[2]
    sv[2] = seen_axis[0] * seen_dir[1] - seen_axis[1] * seen_dir[0]
    for yy in range(y0, y1):
        for xb in range(nbr):
            b = (yy - y0) * nbr + xb
            x0 = xb * LANES
            nb = min(LANES, width - x0)
            ab = arow[b if per_pixel_rows else 0]
            for q in range(nb):
                xx = x0 + q
                nuse = 0
                fault = False
                for r in range(3):
                    for a in range(3):
                        m = np.float64(mean[c, r, a, yy, xx])
                        sd = np.float64(sigma[c, r, a, yy, xx])
                        p = 1.0 / (sd * sd) if sd > 0 else 0.0  # 0 for sd 0, inf or NaN
                        fine = abs(m) < np.inf
                        use = fine & (p > 0) & (p < np.inf)
                        fault |= (not (sd >= 0)) | (p == np.inf) | ((p > 0) & (not fine))
                        pi[3 * r + a] = p if use else 0.0
                        pm[b, 3 * r + a, q] = m if use else 0.0
                        nuse += 1 if use else 0
                flags[b, q] |= _NONFINITE if fault else 0
                for ii in range(9):
                    for ll in range(9):
                        pa[b, ii, ll, q] = 0.0
                    pa[b, ii, ii, q] = pi[ii]
                nseen = 0
                if seen_k >= 0:
                    for j in range(4):
                        if w[b, 4 * seen_k + j, q] > 0:
                            used[nseen] = j
                            nseen += 1
                for r in range(3):
                    cc[r] = 0.0
                    for a in range(3):
                        tt[3 * r + a] = pi[3 * r + a] * seen_dir[a]
                        cc[r] += pi[3 * r + a] * u2[a]
                rank = nuse
                if nseen >= 3:  # M u observed whole: per row, without cancellation
                    for r in range(3):
                        cr = cc[r]
                        if cr > 0:
                            rank -= 1
                            if directional:  # the variance along u moved onto v1
                                # P = (S + alpha det2 v2 v2^T) / (1 + alpha s11) (module
                                # docstring), every term without cancellation where the row's
                                # three elements have a prior: det2 = pi0 pi1 pi2 / c (the
                                # plane's precision determinant), s11 = v1^T S v1 = det2 v2^T
                                # Sigma v2; with one missing, det2 = 0 and S has rank 1
                                alpha = 0.0
                                nrow = 0
                                for a in range(3):
                                    if pi[3 * r + a] > 0:
                                        alpha += u2[a] / pi[3 * r + a]
                                        nrow += 1
                                alpha *= seen_share[r]
                                for a in range(3):
                                    a1, a2 = (a + 1) % 3, (a + 2) % 3
                                    srow[a, a] = pi[3 * r + a] * (
                                        (pi[3 * r + a1] * u2[a1] + pi[3 * r + a2] * u2[a2]) / cr)
                                    for bb in range(a):
                                        srow[a, bb] = -tt[3 * r + a] * tt[3 * r + bb] / cr
                                        srow[bb, a] = srow[a, bb]
                                if nrow == 3:
                                    det2 = pi[3 * r] * pi[3 * r + 1] * pi[3 * r + 2] / cr
                                    s11 = (sv[0] * sv[0] * pi[3 * r + 1] * pi[3 * r + 2]
                                           + sv[1] * sv[1] * pi[3 * r + 2] * pi[3 * r]
                                           + sv[2] * sv[2] * pi[3 * r] * pi[3 * r + 1]) / cr
                                else:
                                    det2 = 0.0
                                    s11 = 0.0
                                    for a in range(3):
                                        for bb in range(3):
                                            s11 += seen_axis[a] * srow[a, bb] * seen_axis[bb]
                                inv = 1.0 / (1.0 + alpha * s11)
                                for a in range(3):
                                    for bb in range(a + 1):
                                        v = (srow[a, bb] + alpha * det2 * sv[a] * sv[bb]) * inv
                                        pa[b, 3 * r + a, 3 * r + bb, q] = v
                                        pa[b, 3 * r + bb, 3 * r + a, q] = v
                                continue
                            # g: the share of the row's prior variance off u over the variance
                            # kept in the unobserved plane (its share seen_share[r] along u too)
                            num = 0.0
                            den = 0.0
                            for a in range(3):
                                if pi[3 * r + a] > 0:
                                    num += (1.0 - u2[a]) / pi[3 * r + a]
                                    den += 1.0 / pi[3 * r + a]
                            kept = den if seen_share[r] == 1.0 else num + seen_share[r] * (den - num)
                            g = num / kept if kept > 0 else 0.0
                            for a in range(3):
                                a1, a2 = (a + 1) % 3, (a + 2) % 3
                                pa[b, 3 * r + a, 3 * r + a, q] = g * pi[3 * r + a] * (
                                    (pi[3 * r + a1] * u2[a1] + pi[3 * r + a2] * u2[a2]) / cr)
                                for bb in range(a):
                                    v = -g * tt[3 * r + a] * tt[3 * r + bb] / cr
                                    pa[b, 3 * r + a, 3 * r + bb, q] = v
                                    pa[b, 3 * r + bb, 3 * r + a, q] = v
                elif nseen >= 1:  # part of M u observed: P = R (I - E E^T) R
                    # (R = Pi^1/2, E an orthonormal basis of R B, B the used samples' directions
                    # a_j (x) u): the Schur complement Pi - Pi B (B^T Pi B)^+ B^T Pi with no
                    # inverse of B^T Pi B, which can be nearly singular (row precisions 1e4
                    # apart: it lost 4e-5 of P that way); Gram-Schmidt twice
                    for ii in range(9):
                        rp[ii] = np.sqrt(pi[ii])
                    for k in range(nseen):
                        nz[k] = 0.0
                        for ii in range(9):
                            zz[k, ii] = rp[ii] * ab[used[k], ii // 3, q] * seen_dir[ii % 3]
                            nz[k] += zz[k, ii] * zz[k, ii]
                    # the first direction: the longer vector; the second: the other, less its
                    # part along the first, kept where the Gram determinant |z_a|^2 |z_b'|^2 is
                    # above 1e-12 tr^2 (the rank rule of B^T Pi B, tr its trace)
                    first = 1 if nseen == 2 and nz[1] > nz[0] else 0
                    na = nz[first]
                    tr = nz[0] + nz[1] if nseen == 2 else nz[0]
                    nvec = 0
                    if na > 0:
                        rank -= 1
                        nvec = 1
                        inv = 1.0 / np.sqrt(na)
                        for ii in range(9):
                            zz[first, ii] *= inv
                        if nseen == 2:
                            other = 1 - first
                            for _ in range(2):
                                dot = 0.0
                                for ii in range(9):
                                    dot += zz[first, ii] * zz[other, ii]
                                for ii in range(9):
                                    zz[other, ii] -= dot * zz[first, ii]
                            nb = 0.0
                            for ii in range(9):
                                nb += zz[other, ii] * zz[other, ii]
                            if na * nb > 1e-12 * tr * tr:
                                rank -= 1
                                nvec = 2
                                inv = 1.0 / np.sqrt(nb)
                                for ii in range(9):
                                    zz[other, ii] *= inv
                    for ii in range(9):
                        for ll in range(9):
                            proj = 0.0
                            if nvec >= 1:
                                proj += zz[first, ii] * zz[first, ll]
                            if nvec == 2:
                                proj += zz[1 - first, ii] * zz[1 - first, ll]
                            pa[b, ii, ll, q] -= rp[ii] * rp[ll] * proj
                prank[b, q] = rank


@jit_cached()
def correlate_prior(pa, prank, w, seen_k, seen_dir, seen_axis, kinv):  # pragma: no cover - compiled
    """The joint prior of :mod:`polrig.solve.hybrid` ("Joint prior"): where :func:`load_prior`
    wrote the block-diagonal precision of a whole seen frame and a prior at all nine elements
    (``prank == 6``, at least 3 of the seen state's samples used, a seen state with an axis),
    replace it by ``P = Q K^-1 Q^T`` with ``Q`` ``(9, 6)`` block diagonal over the rows,
    ``Q_r = [v1 v2] L_r`` and ``L_r`` the Cholesky factor of ``[v1 v2]^T P_r [v1 v2]`` (so
    ``Q Q^T`` is the block-diagonal ``P``: ``K = I`` changes nothing but rounding). ``kinv``
    ``(6, 6)``: the inverse of the whitened unobserved error's correlation ``K`` (coordinates
    row-major, ``(r, v1), (r, v2)``). Other lanes are left as they are."""
    nb, _, _, nl = pa.shape
    v2 = np.empty(3)
    v2[0] = seen_axis[1] * seen_dir[2] - seen_axis[2] * seen_dir[1]
    v2[1] = seen_axis[2] * seen_dir[0] - seen_axis[0] * seen_dir[2]
    v2[2] = seen_axis[0] * seen_dir[1] - seen_axis[1] * seen_dir[0]
    qf = np.zeros((9, 6))
    tmp = np.empty((9, 6))
    for b in range(nb):
        for q in range(nl):
            if prank[b, q] != 6 or seen_k < 0:
                continue
            nseen = 0
            for j in range(4):
                if w[b, 4 * seen_k + j, q] > 0:
                    nseen += 1
            if nseen < 3:
                continue
            ok = True
            for r in range(3):
                g11 = 0.0
                g12 = 0.0
                g22 = 0.0
                for a in range(3):
                    for bb in range(3):
                        p = pa[b, 3 * r + a, 3 * r + bb, q]
                        g11 += seen_axis[a] * p * seen_axis[bb]
                        g12 += seen_axis[a] * p * v2[bb]
                        g22 += v2[a] * p * v2[bb]
                if not g11 > 0:
                    ok = False
                    break
                l11 = np.sqrt(g11)
                l21 = g12 / l11
                d = g22 - l21 * l21
                if not d > 0:
                    ok = False
                    break
                l22 = np.sqrt(d)
                for a in range(3):
                    qf[3 * r + a, 2 * r] = seen_axis[a] * l11 + v2[a] * l21
                    qf[3 * r + a, 2 * r + 1] = v2[a] * l22
            if not ok:
                continue
            for ii in range(9):  # tmp = Q K^-1 (Q block diagonal: row ii lives in block ii // 3)
                r = ii // 3
                for jj in range(6):
                    tmp[ii, jj] = qf[ii, 2 * r] * kinv[2 * r, jj] + qf[ii, 2 * r + 1] * kinv[2 * r + 1, jj]
            for ii in range(9):
                for ll in range(ii + 1):
                    r2 = ll // 3
                    v = tmp[ii, 2 * r2] * qf[ll, 2 * r2] + tmp[ii, 2 * r2 + 1] * qf[ll, 2 * r2 + 1]
                    pa[b, ii, ll, q] = v
                    pa[b, ll, ii, q] = v


@jit_cached()
def stretch_prior(pa, prank, open_dir, beta):  # pragma: no cover - compiled
    """The prior's spread along ``open_dir`` (``w`` ``(3,)``, unit) in every row of ``M``
    widened (:mod:`polrig.solve.hybrid`, "The open direction's scale"): ``P <- B P B`` with
    ``B = I_3 (x) (I + beta w w^T)`` on the lanes with a prior (``prank > 0``), ``beta = 1/a - 1``
    for the factor ``a`` on the prior's standard deviation along ``w`` (covariance ``A C A``,
    ``A = I_3 (x) (I + (a - 1) w w^T)``, whose inverse is ``B``). Other lanes are left as they are;
    the prior's mean term ``P mu`` is formed afterwards from the result (:func:`_add_prior`)."""
    nb, _, _, nl = pa.shape
    tmp = np.empty((9, 9))
    for b in range(nb):
        for q in range(nl):
            if prank[b, q] == 0:
                continue
            for r in range(3):  # tmp = B P: each row block r of P gets beta w (w . its rows)
                for ll in range(9):
                    d = (open_dir[0] * pa[b, 3 * r, ll, q] + open_dir[1] * pa[b, 3 * r + 1, ll, q]
                         + open_dir[2] * pa[b, 3 * r + 2, ll, q])
                    for a in range(3):
                        tmp[3 * r + a, ll] = pa[b, 3 * r + a, ll, q] + beta * open_dir[a] * d
            for ii in range(9):  # P = tmp B
                for r in range(3):
                    d = (tmp[ii, 3 * r] * open_dir[0] + tmp[ii, 3 * r + 1] * open_dir[1]
                         + tmp[ii, 3 * r + 2] * open_dir[2])
                    for a in range(3):
                        pa[b, ii, 3 * r + a, q] = tmp[ii, 3 * r + a] + beta * open_dir[a] * d


@jit_cached()
def solve_blocks(s, ds_gen, w, mv, arow, per_pixel_rows, flags, lanes, min_snr, out_max, cal_sd,
                 with_cal, with_prior, pa, pm, prank, x_out, sg_out, sn_out, res_out, nok, keys
                 ):  # pragma: no cover - compiled
    """Solve the blocks of a tile loaded by :func:`load_tile` as if every pixel's used samples
    determined M (the caller masks those whose used design is too ill-conditioned).

    ``s`` ``(N, 3)``; ``ds_gen`` ``(2, N, 3)`` the generator state derivatives (zero offset
    per rad, 1/ER); ``arow`` ``(B, 4, 3, L)`` with ``per_pixel_rows``, else ``(1, 4, 3, L)``
    the same rows in every lane;
    ``lanes`` = ``L`` (passed at run time: a constant trip count makes LLVM unroll every loop,
    which multiplies the compile time and defeats the vectoriser); ``out_max`` the largest
    magnitude the output dtype holds; ``cal_sd`` the 5 calibration standard deviations (used
    with ``with_cal``). Writes ``x_out``, ``sg_out``, ``sn_out`` ``(B, 9, L)`` (estimate,
    total and noise sigma), ``res_out`` ``(B, L)``, ``flags`` (DARK, ILL_CONDITIONED added),
    ``nok`` ``(B, L)`` the number of used samples and ``keys`` ``(words, B * L)`` their bit
    patterns (bit ``r = 4 k + j`` of word ``r // 64``);
    an unsolved pixel (singular, or an output not finite or beyond ``out_max``) gets zeros.
    All arrays float64 (int64 ``nok``, ``flags``): one compiled variant serves every input and
    output dtype.

    ``with_prior`` (:mod:`polrig.solve.hybrid`): a Gaussian prior on the nine elements from
    :func:`load_prior`, ``pa`` ``(B, 9, 9, L)`` its precision, ``pm`` ``(B, 9, L)`` its mean
    (0 where unused), ``prank`` ``(B, L)`` the number of directions it informs. It adds ``P`` to
    the normal matrix and ``P mu`` to the right-hand side; the residual is the samples'
    ``chi^2`` over their effective degrees of freedom ``n - tr(H) = n - 9 + tr(A^-1 P)`` (``H``
    the hat matrix; 0 below half a degree of freedom), and a pixel with a prior is
    also unsolved where a diagonal element of its equilibrated inverse exceeds
    :data:`INVERSE_DIAG_MAX`; without it (or with a zero precision and rank) every operation
    is the reference solve's.
    """
    n = s.shape[0]
    nl = lanes
    d9 = 9 if lanes > 0 else 0  # a run-time bound, as ``lanes``
    bad = np.empty(nl, np.bool_)
    fine = np.empty(nl, np.bool_)
    t = np.empty((4, 3, 3, nl))
    rj = np.empty((4, 3, nl))
    amat = np.empty((d9, d9, nl))
    low = np.empty((d9, d9, nl))
    pj = np.empty((d9, 3, nl))
    vec = np.empty((8, d9, nl))
    dsc, rl, rhs, e, z, acc, u, chi2 = (vec[0], vec[1], vec[2], vec[3], vec[4], vec[5],
                                        vec[6], vec[7])
    for blk in range(w.shape[0]):
        wb = w[blk]
        mb = mv[blk]
        ab = arow[blk if per_pixel_rows else 0]
        x = x_out[blk]
        sn = sn_out[blk]
        sg = sg_out[blk]
        for q in range(nl):
            nok[blk, q] = 0
        for wd in range(keys.shape[0]):
            for q in range(nl):
                keys[wd, blk * nl + q] = 0
        for r in range(4 * n):
            wd = r >> 6
            bit = np.int64(1) << np.int64(r & 63)
            for q in range(nl):
                use = wb[r, q] > 0
                nok[blk, q] += 1 if use else 0
                keys[wd, blk * nl + q] |= bit if use else 0
        _normal_equations(s, wb, mb, ab, per_pixel_rows, t, rj, amat, rhs)
        if with_prior:
            _add_prior(pa[blk], pm[blk], amat, rhs)
        if with_prior:  # the largest and smallest diagonal of A (acc: scratch until the sigma)
            for q in range(nl):
                acc[0, q] = 0.0
                acc[1, q] = np.inf
            for ii in range(d9):
                for q in range(nl):
                    acc[0, q] = max(acc[0, q], amat[ii, ii, q])
                    acc[1, q] = min(acc[1, q], amat[ii, ii, q])
        _factor(amat, dsc, low, rl, bad)
        if with_prior:  # singular whatever rounding leaves in the pivots of the equilibrated matrix:
            for q in range(nl):
                # fewer samples used than the nine elements less the prior's directions (exactly),
                # or an element that neither the samples nor the prior inform to working precision
                # (its diagonal at most PIVOT_EPS of the largest: equilibration would hide it)
                bad[q] |= (prank[blk, q] > 0) & ((nok[blk, q] + prank[blk, q] < d9)
                                                  | (not acc[1, q] > PIVOT_EPS * acc[0, q]))
        # estimate and noise sigma: the same operations with and without the calibration term
        _triangular_solve(low, dsc, rhs, e, x)
        for ll in range(d9):
            for q in range(nl):
                acc[ll, q] = 0.0
            for ii in range(ll, d9):
                for q in range(nl):
                    acc[ll, q] += low[ii, ll, q] * low[ii, ll, q]
            for q in range(nl):
                sn[ll, q] = dsc[ll, q] * np.sqrt(acc[ll, q])
            if with_prior:  # (A_eq^-1)_ll: a singular posterior need not show in one pivot
                for q in range(nl):
                    bad[q] |= (prank[blk, q] > 0) & (not acc[ll, q] <= INVERSE_DIAG_MAX)
        if with_cal or with_prior:
            _inverse(low, dsc, amat)
        if with_prior:  # tr(A^-1 P) in chi2[1]: the directions the prior determines
            for q in range(nl):
                chi2[1, q] = 0.0
            for ii in range(d9):
                for ll in range(d9):
                    for q in range(nl):
                        chi2[1, q] += amat[ii, ll, q] * pa[blk, ll, ii, q]
        if with_cal:
            _calibration_variance(s, ds_gen, cal_sd, wb, ab, per_pixel_rows, t, x, amat, pj, e,
                                  z, u, acc)
            for ll in range(d9):
                for q in range(nl):
                    sg[ll, q] = np.sqrt(sn[ll, q] * sn[ll, q] + acc[ll, q])
        else:
            for ll in range(d9):
                for q in range(nl):
                    sg[ll, q] = sn[ll, q]
        # residual chi^2 / dof (excluded samples have w = 0) in chi2[0]
        for q in range(nl):
            chi2[0, q] = 0.0
        for k in range(n):
            s0, s1, s2 = s[k, 0], s[k, 1], s[k, 2]
            for q in range(nl):
                u[0, q] = x[0, q] * s0 + x[1, q] * s1 + x[2, q] * s2
                u[1, q] = x[3, q] * s0 + x[4, q] * s1 + x[5, q] * s2
                u[2, q] = x[6, q] * s0 + x[7, q] * s1 + x[8, q] * s2
            for j in range(4):
                r = 4 * k + j
                for q in range(nl):
                    dv = mb[r, q] - (ab[j, 0, q] * u[0, q] + ab[j, 1, q] * u[1, q]
                                     + ab[j, 2, q] * u[2, q])
                    wr = wb[r, q]
                    chi2[0, q] += wr * dv * dv if wr > 0 else 0.0
        # solved, finite and representable in the output dtype: else unsolved (zeros)
        for q in range(nl):
            if with_prior:  # n - tr(H), H = D A^-1 D^T W the hat matrix: n - 9 + tr(A^-1 P)
                dof = nok[blk, q] - 9 + chi2[1, q]
                res = chi2[0, q] / dof if dof > 0.5 else 0.0
            else:
                dof = nok[blk, q] - 9
                res = chi2[0, q] / dof if dof > 0 else 0.0
            chi2[0, q] = res
            fine[q] = (not bad[q]) & (abs(res) <= out_max)
        for ll in range(d9):
            for q in range(nl):
                fine[q] &= (abs(x[ll, q]) <= out_max) & (sg[ll, q] <= out_max)
        for q in range(nl):
            ok = fine[q]
            dark = not x[0, q] >= min_snr * sg[0, q]
            flags[blk, q] |= (_DARK if dark else 0) if ok else _ILL_CONDITIONED
            res_out[blk, q] = chi2[0, q] if ok else 0.0
        for ll in range(d9):
            for q in range(nl):
                ok = fine[q]
                x[ll, q] = x[ll, q] if ok else 0.0
                sg[ll, q] = sg[ll, q] if ok else 0.0
                sn[ll, q] = sn[ll, q] if ok else 0.0
