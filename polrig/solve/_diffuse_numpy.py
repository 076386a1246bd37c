"""The previous, pure-numpy grid search of the diffuse term's normal (batched over chunks of
pixels and their candidates), kept as the oracle that the compiled search
(:mod:`polrig.solve._diffuse_kernel`) of :func:`polrig.solve.diffuse_test.diffuse_statistic` and
:func:`polrig.solve.diffuse_geometry.fit_diffuse_geometry` is tested against
(``tests/test_diffuse_kernel.py``). Same grid, candidates, costs and tie rule as the kernel;
about 30-40x slower. Not used by the application.
"""

from __future__ import annotations

import numpy as np

from polrig.solve.diffuse_geometry import (
    AZIMUTH_STEP_DEG,
    MAX_ZENITH_DEG,
    ZENITH_STEP_DEG,
    _Observed,
    _Pixels,
    diffuse_ratios,
)
from polrig.solve.diffuse_test import REFINE, STEPS_DEG

__all__ = ["search_normals", "search_ratios_numpy", "diffuse_statistic_numpy"]

#: Pixels per chunk of the search (memory: chunk x candidates x 9 doubles).
_CHUNK = 128


def _normals(z: np.ndarray, a: np.ndarray, view: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """Unit normals ``(P, K, 3)`` at zenith ``z`` and azimuth ``a`` ``(P, K)`` (rad) about each
    pixel's ``view`` in its frame ``e1``, ``e2`` (``(P, 3)``)."""
    return (np.cos(z)[..., None] * view[:, None] + np.sin(z)[..., None]
            * (np.cos(a)[..., None] * e1[:, None] + np.sin(a)[..., None] * e2[:, None]))


def _frame(view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors ``(P, 3)`` completing ``view`` to an orthonormal frame."""
    helper = np.where(np.abs(view[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(view, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(view, e1)


def _grid(z0: np.ndarray, a0: np.ndarray, dz: float, da: float, nz: int, na: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (zenith, azimuth) ``(P, nz * na)`` around ``(z0, a0)`` ``(P,)`` (rad)."""
    oz = (np.arange(nz) - (nz - 1) / 2) * dz
    oa = (np.arange(na) - (na - 1) / 2) * da
    z = z0[:, None, None] + oz[None, :, None]
    a = a0[:, None, None] + oa[None, None, :]
    z, a = np.broadcast_arrays(z, a)
    return np.clip(z, 0.0, np.deg2rad(MAX_ZENITH_DEG)).reshape(len(z0), -1), a.reshape(len(z0), -1)


def search_normals(view: np.ndarray, cost, refine: int = 2,
                   steps_deg: tuple[float, float] = (ZENITH_STEP_DEG, AZIMUTH_STEP_DEG)
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The least-cost unit normal ``(P, 3)`` of each pixel and its cost ``(P,)``: a zenith x
    azimuth grid about the pixel's ``view`` ``(P, 3)`` (``steps_deg``, default
    :data:`~polrig.solve.diffuse_geometry.ZENITH_STEP_DEG`,
    :data:`~polrig.solve.diffuse_geometry.AZIMUTH_STEP_DEG`; zenith up to
    :data:`~polrig.solve.diffuse_geometry.MAX_ZENITH_DEG`), refined ``refine`` times by halving
    the steps around the best (:mod:`polrig.solve.diffuse_geometry`, "The fit").
    ``cost(normals, pix)``: the cost ``(p, K)`` of the candidate normals ``(p, K, 3)`` of the
    pixels ``pix`` (indices into ``view``, a chunk of :data:`_CHUNK`), inf where a candidate is
    not valid."""
    view = np.asarray(view, np.float64).reshape(-1, 3)
    e1, e2 = _frame(view)
    dz, da = np.deg2rad(steps_deg[0]), np.deg2rad(steps_deg[1])
    nz = int(round(MAX_ZENITH_DEG / steps_deg[0])) + 1
    na = int(round(360.0 / steps_deg[1]))
    normals, costs = np.zeros((len(view), 3)), np.full(len(view), np.inf)
    for c0 in range(0, len(view), _CHUNK):
        sub = np.arange(c0, min(len(view), c0 + _CHUNK))
        rows = np.arange(len(sub))
        # the coarse grid: zenith 0..MAX_ZENITH_DEG, azimuth 0..360 - step
        z, a = _grid(np.full(len(sub), (nz - 1) * dz / 2), np.full(len(sub), np.pi - da / 2), dz, da, nz, na)
        for level in range(refine + 1):
            cost_k = cost(_normals(z, a, view[sub], e1[sub], e2[sub]), sub)
            cost_k = np.where(np.isfinite(cost_k), cost_k, np.inf)
            j = np.argmin(cost_k, axis=1)
            zb, ab = z[rows, j], a[rows, j]
            if level < refine:
                step = 2.0 ** -(level + 1)
                z, a = _grid(zb, ab, dz * step, da * step, 3, 3)
        costs[sub] = cost_k[rows, j]
        normals[sub] = _normals(zb[:, None], ab[:, None], view[sub], e1[sub], e2[sub])[:, 0]
    return normals, costs


def _costs(normals: np.ndarray, pix, eta: float, obs: _Observed, geo: _Pixels) -> np.ndarray:
    """Cost ``(P, K)`` of the candidate normals ``(P, K, 3)`` of the pixels ``pix``
    (:mod:`polrig.solve.diffuse_geometry`, "The fit")."""
    view, light, guess = geo.view[pix], geo.light[pix], None if geo.guess is None else geo.guess[pix]
    p, k = normals.shape[:2]
    n = normals.reshape(-1, 3)
    rep = lambda v: np.repeat(v, k, axis=0)  # noqa: E731
    x, y = diffuse_ratios(n, rep(light), rep(view), eta, geo.stage, geo.cam)
    x_hat, rho_hat, wt = obs.x_hat[pix], obs.rho_hat[pix], obs.weights[pix]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = (y @ geo.s_b) / (y @ geo.s_a)
    cost = (rep(wt[:, 0]) * (x[:, 1] - rep(x_hat[:, 1])) ** 2 + rep(wt[:, 1]) * (x[:, 2] - rep(x_hat[:, 2])) ** 2
            + rep(wt[:, 2]) * (rho - rep(rho_hat)) ** 2).reshape(p, k)
    if guess is not None:
        ang = np.arccos(np.clip(np.einsum("pkj,pj->pk", normals, guess), -1.0, 1.0))
        cost = cost + geo.guess_weight * ang**2
    return np.where(np.isfinite(cost), cost, np.inf)


def search_ratios_numpy(pix: np.ndarray, eta: float, obs: _Observed, geo: _Pixels, refine: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The previous ``diffuse_geometry._search`` (same arguments and results): best normal
    ``(P, 3)`` and its cost ``(P,)`` for the pixels ``pix`` at ``eta``."""
    return search_normals(geo.view[pix], lambda n, sub: _costs(n, pix[sub], eta, obs, geo), refine)


def _profile(stokes: np.ndarray, info: np.ndarray, x: np.ndarray, g: np.ndarray, spec: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """``(T, k)`` of candidates: ``stokes`` ``(C, J, 3, p)``, ``info`` ``(C, J, 3, 3, p)``, ``x``
    ``(p, K, 3)``, ``g = y . s_j`` ``(p, K, J)``; ``T`` ``(p, K)`` minimised over ``k >= 0``,
    ``k`` ``(C, p, K)``. With ``spec`` ``(p, J, 3)`` (the unit specular block's response to each
    state) a second albedo per colour, ``k`` ``(2 C, p, K)`` (diffuse, then specular): the
    free least squares where both are >= 0, else the better of the two edges."""
    xqx = np.einsum("pka,cjabp,pkb->cjpk", x, info, x)
    xqs = np.einsum("pka,cjabp,cjbp->cjpk", x, info, stokes)
    sqs = np.einsum("cjap,cjabp,cjbp->cp", stokes, info, stokes)
    gj = np.moveaxis(g, -1, 0)[None]  # (1, J, p, K)
    num, den = (gj * xqs).sum(axis=1), (gj**2 * xqx).sum(axis=1)  # (C, p, K)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.maximum(num / den, 0.0)
    t = sqs[..., None] - 2.0 * k * num + k**2 * den
    if spec is None:
        return t.sum(axis=0), k
    bqb = np.einsum("pja,cjabp,pjb->cp", spec, info, spec)[..., None]
    bqs = np.einsum("pja,cjabp,cjbp->cp", spec, info, stokes)[..., None]
    cross = (gj * np.einsum("pka,cjabp,pjb->cjpk", x, info, spec)).sum(axis=1)
    det = den * bqb - cross**2
    with np.errstate(divide="ignore", invalid="ignore"):
        kd2, ks2 = (bqb * num - cross * bqs) / det, (den * bqs - cross * num) / det
        t_spec = sqs[..., None] - bqs**2 / bqb
    free = (det > 0) & (kd2 >= 0) & (ks2 >= 0)
    edge = ~free & (bqs > 0) & (bqb > 0) & (t_spec < t)
    ks = np.where(free, ks2, np.where(edge, bqs / np.where(bqb > 0, bqb, 1.0), 0.0))
    k = np.where(free, kd2, np.where(edge, 0.0, k))
    t = np.where(free, sqs[..., None] - kd2 * num - ks2 * bqs, np.where(edge, t_spec, t))
    return t.sum(axis=0), np.concatenate([k, ks])


def diffuse_statistic_numpy(stokes: np.ndarray, information: np.ndarray, states: np.ndarray, view: np.ndarray,
                            light: np.ndarray, eta: float, stage_zero_axis, camera_x_axis,
                            specular: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The previous :func:`polrig.solve.diffuse_test.diffuse_statistic` (same arguments and
    results)."""
    states = np.asarray(states, np.float64).reshape(-1, 3)
    view = np.asarray(view, np.float64).reshape(-1, 3)
    light = np.broadcast_to(np.asarray(light, np.float64), view.shape)
    stage, cam = np.asarray(stage_zero_axis, np.float64), np.asarray(camera_x_axis, np.float64)
    spec = None if specular is None else np.einsum("pab,jb->pja", np.asarray(specular, np.float64), states)

    def candidates(normals: np.ndarray, pix: np.ndarray):
        p, k = normals.shape[:2]
        rep = lambda v: np.repeat(v, k, axis=0)  # noqa: E731
        x, y = diffuse_ratios(normals.reshape(-1, 3), rep(light[pix]), rep(view[pix]), eta, stage, cam)
        return _profile(stokes[..., pix], information[..., pix], x.reshape(p, k, 3), (y @ states.T).reshape(p, k, -1),
                        None if spec is None else spec[pix])

    normal, t = search_normals(view, lambda n, pix: candidates(n, pix)[0], refine=REFINE, steps_deg=STEPS_DEG)
    _, k = candidates(normal[:, None], np.arange(len(view)))
    return t, normal, k[:, :, 0]
