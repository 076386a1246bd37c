"""Compiled Levenberg-Marquardt of the nonlinear lower-order models
(:func:`polrig.solve.reduced_models.fit_model`; numba).

The models, their parametrisations and the fit are documented in
:mod:`polrig.solve.reduced_models`; this module runs the fit of one model for many pixels, one
pixel after the other, every start point of a pixel in turn; the caller runs chunks of pixels
on threads (``nogil``; as :mod:`polrig.solve._reference_kernel`, no ``prange``: the selection
runs on several row bands' threads at once, which numba's parallel layers do not all allow). The per-pixel
algebra is small (``9 x 9`` normal matrix, ``k <= 5`` parameters) and written out: the block
``m(theta)`` and its Jacobian per model (:func:`_matrix`, :func:`_jacobian`, the same
expressions as the numpy forms of :mod:`polrig.solve.reduced_models`). The quadratic form is
whitened once per pixel: with the Cholesky factor ``N = L L^T``, ``z = L^T (m(theta) - m_hat)``,
``q = |z|^2``, ``J_w = L^T J``, ``A = J_w^T J_w`` and ``g = J_w^T z`` (about half the
arithmetic of forming ``N J``, and ``q`` never negative by rounding); the damped normal
equations ``(A + lambda diag A + eps I) delta = -g`` (``eps`` the ridge of
``reduced_models._ridge``) are solved by Gaussian elimination with partial pivoting. A pixel
whose ``N`` has a non-positive Cholesky pivot (not positive definite to working precision;
the selection never tests such a pixel, its ``m_hat`` being NaN) gets NaN ``q`` and block.

The iteration, the acceptance of a step, Marquardt's damping update and the stopping rule are
those of the previous numpy implementation (:mod:`polrig.solve._reduced_numpy`, the tests'
oracle, ``tests/test_reduced_numerics.py``); a pixel stops as soon as its own rule says so
(the numpy version iterated on the shrinking set of pixels still moving, which is the same
thing). Sums run in a different order than numpy's batched ``matmul`` and LAPACK's ``gesv``,
so the results agree to rounding, not bit for bit: ``q`` within ``1e-6 (1 + q)``, and where the
model could be accepted the block within ``1e-8`` in the noise metric, the same model codes
(``tests/test_reduced_numerics.py``; where the minimum is degenerate, e.g. an isotropic block
under an axis model, the two may return different minimisers of equal ``q``).

Determinism: no fastmath, no reductions across pixels (results do not depend on the thread
count or the chunking). ``cache=True`` as in :mod:`polrig.solve._reference_kernel` (uncached where numba finds
no writable cache directory). ``error_model="numpy"``: a zero pivot gives inf/NaN, whose trial
step is then rejected (``q_t < q`` is false for NaN), as the oracle's ridge makes it.
"""

from __future__ import annotations

import numpy as np

from polrig.solve._reference_kernel import jit_cached

#: model codes with a compiled fit (:data:`polrig.solve.reduced_models.MODELS`)
DIATTENUATOR, RETARDER, FRESNEL, RANK_ONE = 3, 4, 5, 6


@jit_cached()
def _block(a, b, c, ci, si, co, so, out, col):  # pragma: no cover - compiled
    """``R(po) F(a, b, c) R(pi)^T`` row-major into ``out[:, col]`` (``out`` ``(9, n)``), the
    expressions of ``reduced_models._axis_form``'s ``block``."""
    out[0, col] = a
    out[1, col] = b * ci
    out[2, col] = -b * si
    out[3, col] = b * co
    out[4, col] = co * ci * a + so * si * c
    out[5, col] = -co * si * a + so * ci * c
    out[6, col] = -b * so
    out[7, col] = -so * ci * a + co * si * c
    out[8, col] = so * si * a + co * ci * c


@jit_cached()
def _axis_parameters(code, t):  # pragma: no cover - compiled
    """``(a, b, c, pi, po)`` of an axis-form model's parameters ``t``."""
    if code == DIATTENUATOR:
        u, v = t[0], t[1]
        return (u * u + v * v) / 2, (u * u - v * v) / 2, u * v, t[2], t[3]
    if code == RETARDER:
        return t[0], 0.0, t[1], t[2], t[3]
    return t[0], t[1], t[2], t[3], t[4]


@jit_cached()
def _matrix(code, t, m):  # pragma: no cover - compiled
    """The block ``m(theta)`` ``(9,)`` of model ``code`` at ``t`` ``(k,)``, into ``m``."""
    if code == RANK_ONE:
        for r in range(3):
            m[3 * r] = t[r] * 1.0
            m[3 * r + 1] = t[r] * t[3]
            m[3 * r + 2] = t[r] * t[4]
        return
    a, b, c, pi, po = _axis_parameters(code, t)
    out = m.reshape((9, 1))
    _block(a, b, c, np.cos(pi), np.sin(pi), np.cos(po), np.sin(po), out, 0)


@jit_cached()
def _jacobian(code, t, jac, j5):  # pragma: no cover - compiled
    """``d m / d theta`` ``(9, k)`` of model ``code`` at ``t`` into ``jac`` (``j5`` ``(9, 5)``
    scratch: the axis form's derivatives in ``(a, b, c, pi, po)``)."""
    if code == RANK_ONE:
        for i in range(9):
            for q in range(5):
                jac[i, q] = 0.0
        for r in range(3):
            for s in range(3):
                jac[3 * r + s, r] = 1.0 if s == 0 else t[2 + s]
            jac[3 * r + 1, 3] = t[r]
            jac[3 * r + 2, 4] = t[r]
        return
    a, b, c, pi, po = _axis_parameters(code, t)
    ci, si, co, so = np.cos(pi), np.sin(pi), np.cos(po), np.sin(po)
    _block(1.0, 0.0, 0.0, ci, si, co, so, j5, 0)
    _block(0.0, 1.0, 0.0, ci, si, co, so, j5, 1)
    _block(0.0, 0.0, 1.0, ci, si, co, so, j5, 2)
    _block(a, b, c, -si, ci, co, so, j5, 3)
    _block(a, b, c, ci, si, -so, co, j5, 4)
    j5[0, 3] = 0.0
    j5[0, 4] = 0.0
    j5[3, 3] = 0.0
    j5[6, 3] = 0.0
    j5[1, 4] = 0.0
    j5[2, 4] = 0.0
    if code == FRESNEL:
        for i in range(9):
            for q in range(5):
                jac[i, q] = j5[i, q]
    elif code == RETARDER:
        for i in range(9):
            jac[i, 0] = j5[i, 0]
            jac[i, 1] = j5[i, 2]
            jac[i, 2] = j5[i, 3]
            jac[i, 3] = j5[i, 4]
    else:  # DIATTENUATOR: chain rule through (a, b, c) = ((u^2 + v^2) / 2, (u^2 - v^2) / 2, u v)
        u, v = t[0], t[1]
        for i in range(9):
            jac[i, 0] = j5[i, 0] * u + j5[i, 1] * u + j5[i, 2] * v
            jac[i, 1] = j5[i, 0] * v - j5[i, 1] * v + j5[i, 2] * u
            jac[i, 2] = j5[i, 3]
            jac[i, 3] = j5[i, 4]


@jit_cached()
def _cholesky_upper(normal, u):  # pragma: no cover - compiled
    """``u = L^T`` ``(9, 9)`` with ``L L^T = N`` (the upper triangle of ``u`` written). Returns
    False where a pivot is not positive (``N`` not positive definite to working precision)."""
    for j in range(9):
        acc = normal[j, j]
        for i in range(j):
            acc -= u[i, j] * u[i, j]
        if not acc > 0.0:
            return False
        d = np.sqrt(acc)
        u[j, j] = d
        for c in range(j + 1, 9):
            acc = normal[j, c]
            for i in range(j):
                acc -= u[i, j] * u[i, c]
            u[j, c] = acc / d
    return True


@jit_cached()
def _whitened_residual(m, m_hat, u, z):  # pragma: no cover - compiled
    """``z = L^T (m - m_hat)`` into ``z``; returns ``q = |z|^2 = (m - m_hat)^T N (m - m_hat)``."""
    q = 0.0
    for i in range(9):
        acc = 0.0
        for j in range(i, 9):
            acc += u[i, j] * (m[j] - m_hat[j])
        z[i] = acc
        q += acc * acc
    return q


@jit_cached()
def _solve_in_place(a, x, k):  # pragma: no cover - compiled
    """Solve ``a x = b`` (``a`` ``(k, k)``, ``x`` holds ``b``) by Gaussian elimination with
    partial pivoting; ``a`` and ``x`` are overwritten (``x`` with the solution)."""
    for col in range(k):
        piv = col
        big = abs(a[col, col])
        for r in range(col + 1, k):
            if abs(a[r, col]) > big:
                big = abs(a[r, col])
                piv = r
        if piv != col:
            for cc in range(k):
                tmp = a[col, cc]
                a[col, cc] = a[piv, cc]
                a[piv, cc] = tmp
            tmp = x[col]
            x[col] = x[piv]
            x[piv] = tmp
        for r in range(col + 1, k):
            f = a[r, col] / a[col, col]
            for cc in range(col + 1, k):
                a[r, cc] -= f * a[col, cc]
            x[r] -= f * x[col]
    for col in range(k - 1, -1, -1):
        acc = x[col]
        for cc in range(col + 1, k):
            acc -= a[col, cc] * x[cc]
        x[col] = acc / a[col, col]


@jit_cached()
def _lm_pixel(code, m_hat, u, theta, iterations, m, step, jac, j5, jw, damp, trial, m_t, z,
              z_t):  # pragma: no cover - compiled
    """Levenberg-Marquardt of one pixel from ``theta`` (``(k,)``, updated in place) on
    ``q = |L^T (m(theta) - m_hat)|^2`` (``u = L^T``); ``m`` receives the block at the end.
    Returns ``q``. The rest are scratch arrays."""
    k = theta.shape[0]
    _matrix(code, theta, m)
    q = _whitened_residual(m, m_hat, u, z)
    lam = 1e-3
    for _ in range(iterations):
        _jacobian(code, theta, jac, j5)
        for i in range(9):  # J_w = L^T J
            for a in range(k):
                acc = 0.0
                for j in range(i, 9):
                    acc += u[i, j] * jac[j, a]
                jw[i, a] = acc
        for a in range(k):  # A = J_w^T J_w (symmetric), -g = -J_w^T z
            acc = 0.0
            for i in range(9):
                acc += jw[i, a] * z[i]
            step[a] = -acc
            for b in range(a, k):
                acc = 0.0
                for i in range(9):
                    acc += jw[i, a] * jw[i, b]
                damp[a, b] = acc
                damp[b, a] = acc
        tr = 0.0
        for a in range(k):  # Marquardt's damping, then reduced_models._ridge
            damp[a, a] = damp[a, a] + lam * damp[a, a]
            tr += damp[a, a]
        eps = 1e-13 * abs(tr) / k + 1e-300
        for a in range(k):
            damp[a, a] += eps
        _solve_in_place(damp, step, k)
        for a in range(k):
            trial[a] = theta[a] + step[a]
        _matrix(code, trial, m_t)
        q_t = _whitened_residual(m_t, m_hat, u, z_t)
        better = q_t < q  # NaN never is
        if better:
            gain = q - q_t
            for a in range(k):
                theta[a] = trial[a]
            for i in range(9):
                m[i] = m_t[i]
                z[i] = z_t[i]
            q = q_t
            lam = min(max(lam * 0.3, 1e-9), 1e9)
            if not gain > 1e-6 * (q + 1.0):
                break
        else:
            lam = min(max(lam * 10.0, 1e-9), 1e9)
            if not lam < 1e9:
                break
    return q


@jit_cached()
def fit_nonlinear(code, m_hat, normal, starts, iterations, theta_out, m_out, q_out
                  ):  # pragma: no cover - compiled
    """Fit model ``code`` to ``P`` pixels from each of ``S`` start points, keeping per pixel
    the start with the lowest ``q`` (the first on ties; NaN never wins).

    ``m_hat`` ``(P, 9)``, ``normal`` ``(P, 9, 9)``, ``starts`` ``(P, S, k)`` float64 (finite);
    outputs ``theta_out`` ``(P, k)``, ``m_out`` ``(P, 9)``, ``q_out`` ``(P,)``: the start's
    parameters, NaN ``m`` and ``q`` where ``N`` is not positive definite (the fit failed)."""
    n_pix, n_start, k = starts.shape
    for p in range(n_pix):
        u = np.empty((9, 9))
        theta = np.empty(k)
        m = np.empty(9)
        step = np.empty(k)
        jac = np.empty((9, k))
        j5 = np.empty((9, 5))
        jw = np.empty((9, k))
        damp = np.empty((k, k))
        trial = np.empty(k)
        m_t = np.empty(9)
        z = np.empty(9)
        z_t = np.empty(9)
        if not _cholesky_upper(normal[p], u):
            for a in range(k):
                theta_out[p, a] = starts[p, 0, a]
            for i in range(9):
                m_out[p, i] = np.nan
            q_out[p] = np.nan
            continue
        for s in range(n_start):
            for a in range(k):
                theta[a] = starts[p, s, a]
            q = _lm_pixel(code, m_hat[p], u, theta, iterations, m, step, jac, j5, jw, damp,
                          trial, m_t, z, z_t)
            if s == 0 or q < q_out[p]:
                q_out[p] = q
                for a in range(k):
                    theta_out[p, a] = theta[a]
                for i in range(9):
                    m_out[p, i] = m[i]
