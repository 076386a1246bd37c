"""Compiled grid search of the diffuse term's normal (numba), for both of its users: the
diffuse test's statistic (:func:`polrig.solve.diffuse_test.diffuse_statistic`) and the
completion's fit (:func:`polrig.solve.diffuse_geometry.fit_diffuse_geometry`).

What is searched is documented there (:mod:`polrig.solve.diffuse_geometry`, "The fit";
:mod:`polrig.solve.diffuse_test`, "The statistic"); this module runs the search for many
pixels, one pixel after the other (``nogil``: the callers run chunks of pixels on a small thread
pool, :func:`polrig.solve.diffuse_geometry._in_chunks`, as :mod:`polrig.solve._reduced_kernel`,
no ``prange``).

**The search** (:func:`_search_pixel`) is :func:`polrig.solve._diffuse_numpy.search_normals`
written out: the frame ``e1``, ``e2`` about the view (``_diffuse_numpy._frame``), the coarse
zenith x azimuth grid (zenith clipped to ``[0, MAX_ZENITH_DEG]``), ``refine`` refinements on the
3x3 grid about the best at halved steps, the same candidate values by the same expressions, in
numpy's order (zenith-major, azimuth-minor), the first of equal least costs kept (numpy's
``argmin``; a non-finite cost counts as inf, so a pixel none of whose candidates is valid gets
cost inf and the first candidate at every level, as there).

**Per candidate** (:func:`_ratios`) the unit diffuse block's ratios ``x = M[:, 0] / m00`` and
``y = M[0, :] / m00`` (:func:`polrig.solve.diffuse_geometry.diffuse_ratios`; the block of
``polrig.optics.pbrdf._diffuse_elements`` is ``p q^T`` with ``p = (a_o, cos 2t_o b_o,
-sin 2t_o b_o)``, ``q = cos_i / pi (a_i, cos 2t_i b_i, -sin 2t_i b_i)``), with the common
factors cancelled: ``x1 = cos 2t_o b_o / a_o`` and so on. ``b / a`` of the Fresnel transmission
(``pbrdf._transmission_ab``) in the closed form of :func:`_polarized`, and the s axis ``n x k``
in a frame ``(x, y = k x x)`` about ``k`` as ``(n . y, -n . x)`` (no cross product; at normal
incidence or exitance, where ``b = 0``, Mitsuba's fallback axis as there): three divisions and
three square roots a candidate instead of some fifteen. The rig frames of ``pbrdf._bases``
(``bases.basis_from_reference_unit``) depend on the pixel alone and are computed once per pixel
(:func:`_setup`). A candidate is invalid (cost inf) where ``n . wi <= 0`` or ``n . wo <= 0``
(the unnormalised vectors, as ``pbrdf._geometry_ok``) or ``m00`` is not positive (``a_i`` or
``a_o`` zero: grazing, total internal reflection).

**One search, two costs**, chosen by an integer (:data:`STATISTIC`, :data:`RATIOS`; numba
compiles each as a literal, the arrays of the other cost are empty placeholders), each from a
flat array of the pixel's constants: the test's profile likelihood ``T`` with the colours'
albedos ``k_c = max(num / den, 0)`` in closed form (:func:`_profile`; the quadratic forms
``x^T Q x``, ``x^T Q S`` as coefficients of ``1, x1, x2, x1^2, x1 x2, x2^2``,
:func:`_prepare_statistic`; ``diffuse_test._profile`` of the oracle) and the completion's
weighted ratio misfit plus the pull to a guessed normal (:func:`_misfit`,
``diffuse_geometry._costs`` of the oracle). The per-candidate helpers are inlined at numba's IR
level (``_inline``), at one site.

**Bounded by the pull.** The completion's cost is a weighted sum of squares (never negative) plus
the pull ``g angle(n, n_guess)^2``, so a candidate whose pull alone exceeds the least cost found
so far cannot be taken; in floating point too, since adding a non-negative number never rounds
below the pull. The coarse level with a pull therefore starts at the candidate nearest the guess
(:func:`_seed`) and at the one the previous pixel of the chunk took (a surface's normal turns
little from one pixel to the next, so the least cost is near its final value from the start)
and, from there on, tests each candidate's cosine to the guess (the candidate
normal and the cosine by the expressions of :func:`_ratios` and :func:`_misfit`) against the
cosine of ``sqrt(best / g)`` widened by ``1e-6`` relative and absolute (:func:`_pull_limit`)
before it computes the ratios. A tie goes to the first candidate in the grid's order, as in the
full scan. The choices, costs and normals are those of the full scan bit for bit (checked on the
176293 tested pixels of a full mono capture of the plastic sphere, both passes and the whole
route's outputs, and the tests' random pixels, ``tests/test_diffuse_kernel.py`` against the
oracle, which scans them all). On that capture (warm, median of 3 interleaved rounds, 2 shared
CPUs) the second pass, whose pull ``NEIGHBOUR_WEIGHT`` keeps the normal within a few degrees of
its neighbours', takes 0.54 s against 3.56 s, the first pass (weak pull, with the choice of
``eta`` and the light) 2.55 s against 4.26 s (2.92 s with the guess's seed alone).

**Oracle** (:mod:`polrig.solve._diffuse_numpy`, the previous numpy implementation,
``tests/test_diffuse_kernel.py``): the candidates are the same numbers; the costs, from the
simplified ratios and sums in another order, agree to rounding (``T`` within ``1e-9 (1 + T)``
where both take the same candidate, measured within ``1e-11``), so a candidate whose cost ties
another's to rounding may flip (on the tests' random pixels 1 of 1200: a pixel whose second
state carries no information, its two branches 180 deg apart equal to ``1e-15``; on 20000
random pixels of each cost none).

**Speed**, measured on 2 shared CPUs (a script, 20000 random pixels, warm, median of 3
interleaved rounds, the callers' two threads): the statistic (``STEPS_DEG`` 10/20,
4 refinements: 198 candidates a pixel, three colours, two states) numpy 145 us a pixel, this
kernel 7.4 us (20x); the completion's search at one ``eta`` (5/10 deg, 2 refinements: 666
candidates, with the pull) numpy 247 us a pixel, this kernel 18.5 us (13x). End to end on a
100x100 diffuse scene over :data:`~polrig.solve.diffuse_geometry.ETAS`: ``test_diffuse`` 185 ->
15 us a pixel, ``complete_diffuse`` (both passes) 691 -> 55 us, the same choices and results.
Compiling both entry points: 11 s cold (the first process after a change of this file), 0.4 s
from numba's on-disk cache.

Determinism: no fastmath, no reductions across pixels (results do not depend on the thread
count or the chunking). ``cache=True`` and ``error_model="numpy"`` as every kernel of
:mod:`polrig.solve` (:func:`polrig.solve._reference_kernel.jit_cached`).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from polrig.solve._reference_kernel import jit_cached

#: the per-candidate helpers: inlined into the search at numba's IR level (as separate functions
#: each call counted references to its array arguments: 1.4x on the completion's search, 1.1x on
#: the statistic); compiled and cached with the entry points that inline them
_inline = njit(inline="always", nogil=True, error_model="numpy")

#: the costs of :func:`_search_pixel`
STATISTIC, RATIOS = 0, 1
#: rows of a pixel's context (:func:`_setup`): the raw view and light, the search frame, the
#: rig's incident and emergent frames, and (inverse lengths of light and view, 0), (cos 2theta,
#: sin 2theta, 0) of the fallback axes ``stokes_basis(-wi)``, ``stokes_basis(wo)`` in the frames
_VIEW, _LIGHT, _E1, _E2, _XI, _YI, _XO, _YO, _INV, _FBI, _FBO = range(11)
_CONTEXT_ROWS = 11


@jit_cached()
def _stokes_basis(k, out):  # pragma: no cover - compiled
    """``polrig.optics.bases.stokes_basis_unit`` of the unit ``k`` ``(3,)`` into ``out``."""
    sign = 1.0 if k[2] >= 0.0 else -1.0
    a = -1.0 / (sign + k[2])
    b = k[0] * k[1] * a
    out[0] = sign * k[0] * k[0] * a + 1.0
    out[1] = sign * b
    out[2] = -sign * k[0]


@jit_cached()
def _basis_from_reference(k, ref, out):  # pragma: no cover - compiled
    """``polrig.optics.bases.basis_from_reference_unit`` of the unit ``k`` and the reference
    ``ref`` (both ``(3,)``) into ``out``."""
    r0, r1, r2 = ref[0], ref[1], ref[2]
    big = max(abs(r0), max(abs(r1), abs(r2)))
    ok_ref = np.isfinite(r0) and np.isfinite(r1) and np.isfinite(r2) and big > 0.0
    if ok_ref:
        r0, r1, r2 = r0 / big, r1 / big, r2 / big
    nr = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    r0, r1, r2 = r0 / nr, r1 / nr, r2 / nr
    rk = r0 * k[0] + r1 * k[1] + r2 * k[2]
    x0, x1, x2 = r0 - rk * k[0], r1 - rk * k[1], r2 - rk * k[2]
    n2 = x0 * x0 + x1 * x1 + x2 * x2
    if not (ok_ref and n2 > 1e-20):
        _stokes_basis(k, out)
        return
    inv = 1.0 / np.sqrt(n2)
    x0, x1, x2 = x0 * inv, x1 * inv, x2 * inv
    if n2 < 1e-4:  # the second Gram-Schmidt pass of references near k
        xk = x0 * k[0] + x1 * k[1] + x2 * k[2]
        x0, x1, x2 = x0 - xk * k[0], x1 - xk * k[1], x2 - xk * k[2]
        nx = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        x0, x1, x2 = x0 / nx, x1 / nx, x2 / nx
    out[0], out[1], out[2] = x0, x1, x2


@jit_cached()
def _cross(a, b, out):  # pragma: no cover - compiled
    """``a x b`` (``(3,)`` each) into ``out``."""
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@jit_cached()
def _rotation(s, x, y):  # pragma: no cover - compiled
    """``(cos 2theta, sin 2theta)`` of ``bases.rotation_cos_sin_2theta_to_frame``: the axis ``s``
    into the frame ``(x, y)`` (each ``(3,)``)."""
    c = s[0] * x[0] + s[1] * x[1] + s[2] * x[2]
    t = s[0] * y[0] + s[1] * y[1] + s[2] * y[2]
    r2 = c * c + t * t
    if np.isfinite(r2) and r2 > 0:
        return (c * c - t * t) / r2, -2.0 * c * t / r2
    return 1.0, 0.0


@jit_cached()
def _setup(view, light, stage, cam, ctx, tmp):  # pragma: no cover - compiled
    """A pixel's context ``ctx`` ``(11, 3)`` (rows as :data:`_VIEW` ...): the search frame of
    ``_diffuse_numpy._frame``, the rig frames of ``pbrdf._bases`` about the unit ``-wi`` and
    ``wo``, the inverse lengths of the light and the view and the fallback axes' rotations
    (``tmp`` ``(3, 3)`` scratch). Returns False where the view or the light is not a finite
    non-zero vector (every candidate invalid)."""
    for c in range(3):
        ctx[_VIEW, c] = view[c]
        ctx[_LIGHT, c] = light[c]
    v = ctx[_VIEW]
    if abs(v[1]) < 0.9:  # the helper axis of _frame: v x (0, 1, 0), else v x (1, 0, 0)
        e0, e1, e2 = v[1] * 0.0 - v[2] * 1.0, v[2] * 0.0 - v[0] * 0.0, v[0] * 1.0 - v[1] * 0.0
    else:
        e0, e1, e2 = v[1] * 0.0 - v[2] * 0.0, v[2] * 1.0 - v[0] * 0.0, v[0] * 0.0 - v[1] * 1.0
    ne = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    ctx[_E1, 0], ctx[_E1, 1], ctx[_E1, 2] = e0 / ne, e1 / ne, e2 / ne
    _cross(v, ctx[_E1], ctx[_E2])
    nl = light[0] * light[0] + light[1] * light[1] + light[2] * light[2]
    nv = view[0] * view[0] + view[1] * view[1] + view[2] * view[2]
    if not (nl > 0.0 and nl < np.inf and nv > 0.0 and nv < np.inf):
        return False
    ctx[_INV, 0], ctx[_INV, 1], ctx[_INV, 2] = 1.0 / np.sqrt(nl), 1.0 / np.sqrt(nv), 0.0
    k_in, wo, fallback = tmp[0], tmp[1], tmp[2]
    for c in range(3):
        k_in[c] = -(light[c] * ctx[_INV, 0])
        wo[c] = view[c] * ctx[_INV, 1]
    _basis_from_reference(k_in, stage, ctx[_XI])
    _cross(k_in, ctx[_XI], ctx[_YI])
    _basis_from_reference(wo, cam, ctx[_XO])
    _cross(wo, ctx[_XO], ctx[_YO])
    _stokes_basis(k_in, fallback)
    ctx[_FBI, 0], ctx[_FBI, 1] = _rotation(fallback, ctx[_XI], ctx[_YI])
    _stokes_basis(wo, fallback)
    ctx[_FBO, 0], ctx[_FBO, 1] = _rotation(fallback, ctx[_XO], ctx[_YO])
    ctx[_FBI, 2], ctx[_FBO, 2] = 0.0, 0.0
    return True


@_inline
def _polarized(cos, eta2):  # pragma: no cover - compiled
    """``b / a`` of the Fresnel transmission at ``cos`` (``pbrdf._transmission_ab``: ``a``, ``b``
    the half sum and difference of ``T_s = 4 c e / d_s^2``, ``T_p = 4 eta^2 c e / d_p^2`` with
    ``c`` the cosine clipped to ``[0, 1]``, ``e = eta cos_t``, ``d_s = c + e``,
    ``d_p = eta^2 c + e``) as numerator and denominator ``(d_p^2 - eta^2 d_s^2,
    d_p^2 + eta^2 d_s^2)``; the denominator is 0 where ``a`` is (grazing, total internal
    reflection)."""
    ci = min(max(cos, 0.0), 1.0)
    ect2 = eta2 - 1.0 + ci * ci
    if not (ci > 0.0 and ect2 > 0.0):
        return 0.0, 0.0
    ect = np.sqrt(ect2)
    ds, dp = ci + ect, eta2 * ci + ect
    dp2, eds2 = dp * dp, eta2 * (ds * ds)
    return dp2 - eds2, dp2 + eds2


@_inline
def _ratios(cz, sz, ca, sa, ctx, eta2, xy):  # pragma: no cover - compiled
    """The unit diffuse block's ratios at the candidate at zenith and azimuth cosines and sines
    ``cz``, ``sz``, ``ca``, ``sa``: ``x`` into ``xy[:3]``, ``y`` into ``xy[3:6]``, the
    candidate normal (unnormalised, as ``_diffuse_numpy._normals``) into ``xy[6:]``. False
    where the candidate is invalid (module docstring)."""
    n0 = cz * ctx[_VIEW, 0] + sz * (ca * ctx[_E1, 0] + sa * ctx[_E2, 0])
    n1 = cz * ctx[_VIEW, 1] + sz * (ca * ctx[_E1, 1] + sa * ctx[_E2, 1])
    n2 = cz * ctx[_VIEW, 2] + sz * (ca * ctx[_E1, 2] + sa * ctx[_E2, 2])
    xy[6], xy[7], xy[8] = n0, n1, n2
    nn = n0 * n0 + n1 * n1 + n2 * n2
    dl = n0 * ctx[_LIGHT, 0] + n1 * ctx[_LIGHT, 1] + n2 * ctx[_LIGHT, 2]
    dv = n0 * ctx[_VIEW, 0] + n1 * ctx[_VIEW, 1] + n2 * ctx[_VIEW, 2]
    if not (nn > 0.0 and nn < np.inf and dl > 0.0 and dv > 0.0):
        return False
    inv_n = 1.0 / np.sqrt(nn)
    bi, ai = _polarized(dl * inv_n * ctx[_INV, 0], eta2)
    bo, ao = _polarized(dv * inv_n * ctx[_INV, 1], eta2)
    if not (ai > 0.0 and ao > 0.0):  # m00 = a_o a_i cos_i / pi
        return False
    xy[0], xy[3] = 1.0, 1.0
    # the s axis n x k in a frame (x, y = k x x) about k: (n . y, -n . x), so that
    # cos 2theta = (c^2 - s^2) / r2 and -sin 2theta = 2 c s / r2; Mitsuba's axis where n || k
    for xr, yr, fb, b, a, o in ((_XI, _YI, _FBI, bi, ai, 4), (_XO, _YO, _FBO, bo, ao, 1)):
        c = n0 * ctx[yr, 0] + n1 * ctx[yr, 1] + n2 * ctx[yr, 2]
        s = -(n0 * ctx[xr, 0] + n1 * ctx[xr, 1] + n2 * ctx[xr, 2])
        r2 = c * c + s * s
        if r2 > 1e-24 * nn:
            t = b / (a * r2)
            xy[o], xy[o + 1] = (c * c - s * s) * t, 2.0 * c * s * t
        else:
            t = b / a
            xy[o], xy[o + 1] = ctx[fb, 0] * t, -ctx[fb, 1] * t
    return True


#: the completion's per-pixel constants in :func:`_search_pixel`'s ``data`` (:func:`_prepare_ratios`)
_XH1, _XH2, _RHO, _W1, _W2, _WRHO, _GUESS, _GW, _USE, _SA, _SB = 0, 1, 2, 3, 4, 5, 6, 9, 10, 11, 14
_RATIO_DATA = 17


@jit_cached()
def _prepare_statistic(p, stokes, info, states, spec, data):  # pragma: no cover - compiled
    """Pixel ``p``'s constants of :func:`_profile` into ``data``: ``sqs[c] = sum_j S^T Q S``
    (``C`` numbers), the states (``3 J``), then per colour and state the six coefficients of
    ``x^T Q x`` in ``1, x1, x2, x1^2, x1 x2, x2^2`` and ``Q S`` (``9 C J``); with the specular
    term (``spec`` ``(P, J, 3)``: its unit block's response ``b_j`` to each state, not empty),
    then per colour ``sum_j b_j^T Q b_j`` and ``sum_j b_j^T Q S`` (``2 C``) and per colour and
    state ``Q b_j`` (``3 C J``)."""
    n_col, n_st = stokes.shape[1], stokes.shape[2]
    for j in range(n_st):
        for a in range(3):
            data[n_col + 3 * j + a] = states[j, a]
    o = n_col + 3 * n_st
    for c in range(n_col):
        acc = 0.0
        for j in range(n_st):
            r = o + 9 * (c * n_st + j)
            data[r] = info[p, c, j, 0, 0]
            data[r + 1] = info[p, c, j, 0, 1] + info[p, c, j, 1, 0]
            data[r + 2] = info[p, c, j, 0, 2] + info[p, c, j, 2, 0]
            data[r + 3] = info[p, c, j, 1, 1]
            data[r + 4] = info[p, c, j, 1, 2] + info[p, c, j, 2, 1]
            data[r + 5] = info[p, c, j, 2, 2]
            for a in range(3):
                qs = (info[p, c, j, a, 0] * stokes[p, c, j, 0] + info[p, c, j, a, 1] * stokes[p, c, j, 1]
                      + info[p, c, j, a, 2] * stokes[p, c, j, 2])
                data[r + 6 + a] = qs
                acc += stokes[p, c, j, a] * qs
        data[c] = acc
    if spec.shape[0] == 0:
        return
    o2 = o + 9 * n_col * n_st
    o3 = o2 + 2 * n_col
    for c in range(n_col):
        bqb, bqs = 0.0, 0.0
        for j in range(n_st):
            r = o3 + 3 * (c * n_st + j)
            for a in range(3):
                qb = (info[p, c, j, a, 0] * spec[p, j, 0] + info[p, c, j, a, 1] * spec[p, j, 1]
                      + info[p, c, j, a, 2] * spec[p, j, 2])
                data[r + a] = qb
                bqb += spec[p, j, a] * qb
                bqs += stokes[p, c, j, a] * qb
        data[o2 + 2 * c], data[o2 + 2 * c + 1] = bqb, bqs


@_inline
def _profile(xy, n_col, n_st, data, k, albedos, specular):  # pragma: no cover - compiled
    """The statistic ``T`` at the ratios ``xy`` (``_diffuse_numpy._profile`` of the oracle) from
    the pixel's constants ``data`` (:func:`_prepare_statistic`); with ``albedos`` the albedos into
    ``k`` (``(C,)``; with the ``specular`` term ``(2 C,)``: the diffuse ones, then the specular
    ones), only for the normal taken (a store per candidate slowed the search)."""
    x1, x2, y1, y2 = xy[1], xy[2], xy[4], xy[5]
    x11, x12, x22 = x1 * x1, x1 * x2, x2 * x2
    o = n_col + 3 * n_st
    o2 = o + 9 * n_col * n_st
    o3 = o2 + 2 * n_col
    t = 0.0
    for c in range(n_col):
        num, den, cross = 0.0, 0.0, 0.0
        for j in range(n_st):
            s = n_col + 3 * j
            g = data[s] + y1 * data[s + 1] + y2 * data[s + 2]  # y . s_j
            r = o + 9 * (c * n_st + j)
            xqx = (data[r] + data[r + 1] * x1 + data[r + 2] * x2 + data[r + 3] * x11 + data[r + 4] * x12
                   + data[r + 5] * x22)
            xqs = data[r + 6] + data[r + 7] * x1 + data[r + 8] * x2
            num += g * xqs
            den += g * g * xqx
            if specular:
                q = o3 + 3 * (c * n_st + j)
                cross += g * (data[q] + x1 * data[q + 1] + x2 * data[q + 2])
        kc = num / den
        if kc < 0.0:  # np.maximum(kc, 0): NaN stays NaN
            kc = 0.0
        tc = data[c] - 2.0 * kc * num + kc * kc * den
        if specular:  # two albedos >= 0: the free optimum, else the better edge
            bqb, bqs = data[o2 + 2 * c], data[o2 + 2 * c + 1]
            ks = 0.0
            det = den * bqb - cross * cross
            kd2 = (bqb * num - cross * bqs) / det
            ks2 = (den * bqs - cross * num) / det
            if det > 0.0 and kd2 >= 0.0 and ks2 >= 0.0:
                kc, ks = kd2, ks2
                tc = data[c] - kd2 * num - ks2 * bqs
            elif bqs > 0.0 and bqb > 0.0 and data[c] - bqs * bqs / bqb < tc:
                kc, ks = 0.0, bqs / bqb
                tc = data[c] - bqs * bqs / bqb
            if albedos:
                k[n_col + c] = ks
        if albedos:
            k[c] = kc
        t += tc
    return t


@jit_cached()
def _prepare_ratios(p, x_hat, rho_hat, weights, guess, s_a, s_b, guess_weight, use_guess, data
                    ):  # pragma: no cover - compiled
    """Pixel ``p``'s constants of :func:`_misfit` into ``data`` (offsets :data:`_XH1` ...)."""
    data[_XH1], data[_XH2], data[_RHO] = x_hat[p, 1], x_hat[p, 2], rho_hat[p]
    for a in range(3):
        data[_W1 + a] = weights[p, a]
        data[_GUESS + a] = guess[p, a] if use_guess else 0.0
        data[_SA + a], data[_SB + a] = s_a[a], s_b[a]
    data[_GW], data[_USE] = guess_weight, 1.0 if use_guess else 0.0


@_inline
def _misfit(xy, data):  # pragma: no cover - compiled
    """The completion's cost at the ratios and candidate normal ``xy`` (``diffuse_geometry._costs``
    of the oracle) from the pixel's constants ``data`` (:func:`_prepare_ratios`)."""
    y1, y2 = xy[4], xy[5]
    rho = (data[_SB] + y1 * data[_SB + 1] + y2 * data[_SB + 2]) / (data[_SA] + y1 * data[_SA + 1] + y2 * data[_SA + 2])
    d1, d2, d3 = xy[1] - data[_XH1], xy[2] - data[_XH2], rho - data[_RHO]
    cost = data[_W1] * (d1 * d1) + data[_W2] * (d2 * d2) + data[_WRHO] * (d3 * d3)
    if data[_USE] != 0.0:
        cos_g = xy[6] * data[_GUESS] + xy[7] * data[_GUESS + 1] + xy[8] * data[_GUESS + 2]
        ang = np.arccos(min(max(cos_g, -1.0), 1.0))
        cost = cost + data[_GW] * (ang * ang)
    return cost


@_inline
def _cost(mode, n_col, n_st, cz, sz, ca, sa, ctx, usable, eta2, data, xy, k, albedos, specular
          ):  # pragma: no cover - compiled
    """The cost ``mode`` at the candidate of zenith and azimuth cosines and sines ``cz``, ``sz``,
    ``ca``, ``sa`` of the pixel of context ``ctx`` (:func:`_setup`) and constants ``data``: inf
    where the candidate is invalid or the cost not finite; with ``albedos`` (:data:`STATISTIC`)
    the albedos into ``k``, NaN where the candidate is invalid."""
    if not (usable and _ratios(cz, sz, ca, sa, ctx, eta2, xy)):
        if albedos:
            for c in range(k.shape[0]):
                k[c] = np.nan
        return np.inf
    if mode == STATISTIC:
        cost = _profile(xy, n_col, n_st, data, k, albedos, specular)
    else:
        cost = _misfit(xy, data)
    return cost if np.isfinite(cost) else np.inf


@_inline
def _seed(ctx, data, nz, na, dz, da):  # pragma: no cover - compiled
    """The flat index ``i na + j`` of the coarse candidate nearest the completion's guessed normal
    (its zenith and azimuth about the view rounded to the grid, whose candidate ``(i, j)`` is at
    zenith ``i dz`` and azimuth ``j da``), or -1 where the guess has no direction."""
    g0, g1, g2 = data[_GUESS], data[_GUESS + 1], data[_GUESS + 2]
    gv = g0 * ctx[_VIEW, 0] + g1 * ctx[_VIEW, 1] + g2 * ctx[_VIEW, 2]
    g_e1 = g0 * ctx[_E1, 0] + g1 * ctx[_E1, 1] + g2 * ctx[_E1, 2]
    g_e2 = g0 * ctx[_E2, 0] + g1 * ctx[_E2, 1] + g2 * ctx[_E2, 2]
    norm = np.sqrt((g0 * g0 + g1 * g1 + g2 * g2) * (ctx[_VIEW, 0] ** 2 + ctx[_VIEW, 1] ** 2 + ctx[_VIEW, 2] ** 2))
    if not (norm > 0.0 and norm < np.inf and np.isfinite(gv + g_e1 + g_e2)):
        return -1
    i = min(max(round(np.arccos(min(max(gv / norm, -1.0), 1.0)) / dz), 0), nz - 1)
    j = round(np.arctan2(g_e2, g_e1) / da) % na
    return i * na + j


@_inline
def _pull_limit(best, guess_weight):  # pragma: no cover - compiled
    """The cosine below which a candidate's pull alone exceeds the cost ``best``: the cosine of
    ``sqrt(best / guess_weight)`` widened by a relative and an absolute ``1e-6`` (rad), far
    beyond the rounding of the arccos, the square and the sum of :func:`_misfit`; ``-inf``
    (nothing is bounded) where that angle reaches pi or ``best`` is not finite."""
    if not best < np.inf:
        return -np.inf
    limit = np.sqrt(best / guess_weight) * (1.0 + 1e-6) + 1e-6
    return np.cos(limit) if limit < np.pi else -np.inf


@jit_cached()
def _search_pixel(mode, n_col, n_st, usable, ctx, eta2, grid, steps, coarse, data, xy, k, normal_out, specular,
                  seeds):  # pragma: no cover - compiled
    """The grid search of one pixel (module docstring; ``grid`` = ``(nz, na, refine)``,
    ``steps`` = ``(dz, da, zmax)`` in rad, ``coarse`` ``(4, max(nz, na))`` the coarse grid's
    zenith cosines, sines, azimuth cosines, sines); the normal into ``normal_out`` ``(3,)``, the
    albedos at it into ``k`` (:data:`STATISTIC`). Returns the least cost. One loop over the
    levels (the coarse grid, the refinements, then for the statistic the normal taken alone, for
    its albedos): one site of the inlined cost, a third of the compile time of one per level.

    The completion's coarse level with a pull (module docstring, "Bounded by the pull") starts
    at the candidate nearest the guess (:func:`_seed`) and at ``seeds[1]`` (the coarse candidate
    the previous pixel took, -1 none; this pixel's is written there), and skips the candidates
    whose pull alone exceeds the least cost so far (:func:`_pull_limit`); a tie is resolved to
    the first candidate in the grid's order, as the full scan resolves it. ``seeds`` ``(2,)``
    int64 scratch."""
    nz, na, refine = grid
    dz, da, zmax = steps
    zb, ab = (nz - 1) * dz / 2, np.pi - da / 2  # the coarse grid's centre
    n_i, n_j, dzl, dal = nz, na, dz, da
    best = np.inf
    bounded = mode == RATIOS and usable and data[_USE] != 0.0 and data[_GW] > 0.0
    for level in range(refine + (2 if mode == STATISTIC else 1)):
        final = level > refine
        if final:  # the normal taken (zb, ab + 0: the same)
            n_i, n_j, dzl, dal = 1, 1, 0.0, 0.0
        elif level > 0:  # 3 x 3 about the best at halved steps
            n_i, n_j, dzl, dal = 3, 3, dz * 2.0 ** -level, da * 2.0 ** -level
        hz, ha = (n_i - 1) / 2, (n_j - 1) / 2
        best_l, ib, jb = np.inf, 0, 0
        seeded = bounded and level == 0
        if seeded:
            seeds[0] = _seed(ctx, data, nz, na, dz, da)
            if seeds[1] == seeds[0]:
                seeds[1] = -1
        cos_limit = -np.inf
        for row in range(-2 if seeded else 0, n_i):  # rows -2, -1: the seeds alone
            for col in range(n_j if row >= 0 else 1):
                if row < 0:
                    if seeds[row + 2] < 0:
                        continue
                    i, j = seeds[row + 2] // n_j, seeds[row + 2] % n_j
                else:
                    i, j = row, col
                if row >= 0 and seeded:
                    if i * n_j + j == seeds[0] or i * n_j + j == seeds[1]:
                        continue
                    # the candidate normal and its cosine to the guess, as _ratios and _misfit
                    ca, sa, cz, sz = coarse[2, j], coarse[3, j], coarse[0, i], coarse[1, i]
                    n0 = cz * ctx[_VIEW, 0] + sz * (ca * ctx[_E1, 0] + sa * ctx[_E2, 0])
                    n1 = cz * ctx[_VIEW, 1] + sz * (ca * ctx[_E1, 1] + sa * ctx[_E2, 1])
                    n2 = cz * ctx[_VIEW, 2] + sz * (ca * ctx[_E1, 2] + sa * ctx[_E2, 2])
                    if n0 * data[_GUESS] + n1 * data[_GUESS + 1] + n2 * data[_GUESS + 2] < cos_limit:
                        continue
                z = min(max(zb + (i - hz) * dzl, 0.0), zmax)
                cz, sz = (coarse[0, i], coarse[1, i]) if level == 0 else (np.cos(z), np.sin(z))
                a = ab + (j - ha) * dal
                ca, sa = (coarse[2, j], coarse[3, j]) if level == 0 else (np.cos(a), np.sin(a))
                cost = _cost(mode, n_col, n_st, cz, sz, ca, sa, ctx, usable, eta2, data, xy, k, final, specular)
                if cost < best_l or (cost == best_l and cost < np.inf and (i, j) < (ib, jb)):
                    best_l, ib, jb = cost, i, j
                    if seeded:
                        cos_limit = _pull_limit(best_l, data[_GW])
        if seeded:
            seeds[1] = ib * n_j + jb if best_l < np.inf else -1
        if not final:
            best = best_l
            zb, ab = min(max(zb + (ib - hz) * dzl, 0.0), zmax), ab + (jb - ha) * dal
    cz, sz, ca, sa = np.cos(zb), np.sin(zb), np.cos(ab), np.sin(ab)
    for c in range(3):
        normal_out[c] = cz * ctx[_VIEW, c] + sz * (ca * ctx[_E1, c] + sa * ctx[_E2, c])
    return best


@jit_cached()
def _search_all(mode, view, light, stage, cam, eta, grid, steps, stat, fit, guess_weight, use_guess,
                cost_out, normal_out, k_out):  # pragma: no cover - compiled
    """:func:`_search_pixel` of every pixel of ``view``, ``light`` ``(P, 3)``; ``stat`` =
    ``(stokes, info, states)`` as :func:`statistic_search` takes them, ``fit`` = ``(x_hat,
    rho_hat, weights, guess, s_a, s_b)`` as :func:`ratio_search` (those of the other cost empty)."""
    stokes, info, states, spec = stat
    x_hat, rho_hat, weights, guess, s_a, s_b = fit
    specular = spec.shape[0] > 0
    nz, na, _ = grid
    dz, da, zmax = steps
    coarse = np.empty((4, max(nz, na)))  # the coarse grid's trigonometry, the same for every pixel
    for i in range(nz):
        z = min(max((nz - 1) * dz / 2 + (i - (nz - 1) / 2) * dz, 0.0), zmax)
        coarse[0, i], coarse[1, i] = np.cos(z), np.sin(z)
    for j in range(na):
        a = np.pi - da / 2 + (j - (na - 1) / 2) * da
        coarse[2, j], coarse[3, j] = np.cos(a), np.sin(a)
    ctx = np.empty((_CONTEXT_ROWS, 3))
    tmp = np.empty((3, 3))
    xy = np.empty(9)
    n_col, n_st = stokes.shape[1], stokes.shape[2]
    data = np.empty(max(_RATIO_DATA, n_col + 3 * n_st + 9 * n_col * n_st + 2 * n_col + 3 * n_col * n_st))
    k = np.empty(k_out.shape[1])
    seeds = np.full(2, -1, np.int64)  # where the search of the completion starts (_search_pixel)
    for p in range(view.shape[0]):
        usable = _setup(view[p], light[p], stage, cam, ctx, tmp)
        if mode == STATISTIC:
            _prepare_statistic(p, stokes, info, states, spec, data)
        else:
            _prepare_ratios(p, x_hat, rho_hat, weights, guess, s_a, s_b, guess_weight, use_guess, data)
        cost_out[p] = _search_pixel(mode, n_col, n_st, usable, ctx, eta * eta, grid, steps, coarse, data, xy, k,
                                    normal_out[p], specular, seeds)
        for c in range(k.shape[0]):
            k_out[p, c] = k[c]


@jit_cached()
def statistic_search(view, light, stage, cam, eta, grid, steps, stokes, info, states, spec, t_out, normal_out,
                     k_out):  # pragma: no cover - compiled
    """The diffuse test's search (:func:`polrig.solve.diffuse_test.diffuse_statistic`) of ``P``
    pixels: ``view``, ``light`` ``(P, 3)``; ``stage``, ``cam`` ``(3,)``; ``grid`` ``(nz, na,
    refine)``, ``steps`` ``(dz, da, zmax)`` (rad); ``stokes`` ``(P, C, J, 3)``, ``info``
    ``(P, C, J, 3, 3)``, ``states`` ``(J, 3)``; ``spec`` ``(P, J, 3)``: the unit specular block's
    response to each state (a second albedo per colour), or ``(0, J, 3)`` for the diffuse term
    alone. Outputs ``t_out`` ``(P,)`` (inf where no candidate is valid), ``normal_out``
    ``(P, 3)``, ``k_out`` ``(P, C)``, with the specular term ``(P, 2 C)`` (the diffuse albedos,
    then the specular; NaN where the normal taken is not valid)."""
    fit = (np.empty((0, 3)), np.empty(0), np.empty((0, 3)), np.empty((0, 3)), np.empty(3), np.empty(3))
    _search_all(STATISTIC, view, light, stage, cam, eta, grid, steps, (stokes, info, states, spec), fit, 0.0,
                False, t_out, normal_out, k_out)


@jit_cached()
def ratio_search(view, light, stage, cam, eta, grid, steps, x_hat, rho_hat, weights, guess, s_a, s_b,
                 guess_weight, use_guess, cost_out, normal_out):  # pragma: no cover - compiled
    """The completion's search (:func:`polrig.solve.diffuse_geometry.fit_diffuse_geometry`) of
    ``P`` pixels: ``view``, ``light``, ``stage``, ``cam``, ``grid``, ``steps`` as
    :func:`statistic_search`; ``x_hat`` ``(P, 3)``, ``rho_hat`` ``(P,)``, ``weights`` ``(P, 3)``,
    ``guess`` ``(P, 3)`` (read only with ``use_guess``), ``s_a``, ``s_b`` ``(3,)``,
    ``guess_weight`` (1/rad^2). Outputs ``cost_out`` ``(P,)`` (inf where no candidate is valid)
    and ``normal_out`` ``(P, 3)``."""
    stat = (np.empty((0, 0, 0, 3)), np.empty((0, 0, 0, 3, 3)), np.empty((0, 3)), np.empty((0, 0, 3)))
    _search_all(RATIOS, view, light, stage, cam, eta, grid, steps, stat, (x_hat, rho_hat, weights, guess, s_a, s_b),
                guess_weight, use_guess, cost_out, normal_out, np.empty((view.shape[0], 0)))
