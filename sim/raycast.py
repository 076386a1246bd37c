"""Ray casting against the analytic shapes of a :class:`polrig.sim.scene.Scene` (world frame, metres):
nearest hits with shading normals and materials, and point-light visibility. Shared by the
direct renderer (:mod:`polrig.sim.render`) and the one-bounce indirect light
(:mod:`polrig.sim.interreflection`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from polrig.sim.geometry import rows_times, unit
from polrig.sim.scene import Scene

#: Offset of shadow-ray origins along the geometric normal (metres).
SHADOW_EPS_M = 1e-5


class Hits(NamedTuple):
    """The rays (of ``N``) that hit a surface, ``M`` of them: ``index`` ``(M,)`` into the rays,
    world points ``p``, unit geometric and shading normals ``ng``, ``ns`` (turned towards the
    ray origin: surfaces are two-sided), ``mat_index`` into ``scene.materials``, object index
    ``obj``, local points ``p_local`` and the ray parameter ``t`` (all ``(M, ...)``)."""

    index: np.ndarray
    p: np.ndarray
    ng: np.ndarray
    ns: np.ndarray
    mat_index: np.ndarray
    obj: np.ndarray
    p_local: np.ndarray
    t: np.ndarray


def _nearest_hit(scene: Scene, turntable_deg: float, o: np.ndarray, d: np.ndarray,
                 t_max: np.ndarray | None = None, any_hit: bool = False):
    """Nearest hit over all objects of rays ``o``, ``d`` ``(N, 3)`` (world). Returns
    ``(t, object index, normal world (N, 3), local point (N, 3))``; with ``any_hit`` only
    whether some object is hit before ``t_max``."""
    n = d.shape[0]
    t_best = np.full(n, np.inf) if t_max is None else np.asarray(t_max, float).copy()
    obj = np.full(n, -1, dtype=np.int64)
    nrm = np.zeros((n, 3))
    p_loc = np.zeros((n, 3))
    for k, ob in enumerate(scene.objects):
        r, t = ob.world_pose(scene.turntable, turntable_deg)
        cand = _bound_candidates(o, d, t, ob.shape.bound_radius_m, t_best)
        if cand is not None and cand.size == 0:
            continue
        oc = o if cand is None else o[cand]
        dc = d if cand is None else d[cand]
        ol = rows_times(oc - t, r)  # R^T (o - t) for row vectors
        dl = rows_times(dc, r)
        th, nh = ob.shape.intersect(ol, dl)
        closer = th < (t_best if cand is None else t_best[cand])
        if not np.any(closer):
            continue
        sel = np.nonzero(closer)[0] if cand is None else cand[closer]
        t_best[sel] = th[closer]
        obj[sel] = k
        if any_hit:
            continue
        nrm[sel] = rows_times(nh[closer], r.T)
        p_loc[sel] = ol[closer] + th[closer, None] * dl[closer]
    return t_best, obj, nrm, p_loc


def _bound_candidates(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float,
                      t_best: np.ndarray) -> np.ndarray | None:
    """Indices of the rays ``o + t d`` (``(N, 3)``, unit ``d``) that come within ``radius`` of
    ``centre`` before ``t_best`` (``None``: all rays, for unbounded shapes)."""
    if not np.isfinite(radius):
        return None
    oc = centre - o
    tca = np.einsum("ij,ij->i", oc, d)
    oc2 = np.einsum("ij,ij->i", oc, oc)
    r2 = radius * radius * (1.0 + 1e-9) + 1e-18
    inside = oc2 <= r2
    near = (oc2 - tca * tca <= r2) & (tca + radius >= 0) & (tca - radius < t_best)
    return np.nonzero(near | inside)[0]


def surface_hits(scene: Scene, turntable_deg: float, o: np.ndarray, d: np.ndarray) -> Hits:
    """Nearest surface hits of rays ``o + t d`` (``(N, 3)``, unit ``d``) with shading normals
    and material indices (:class:`Hits`)."""
    t_hit, obj, n_geo, p_loc = _nearest_hit(scene, turntable_deg, o, d)
    idx = np.nonzero(np.isfinite(t_hit))[0]
    dd = d[idx]
    p = o[idx] + t_hit[idx, None] * dd
    ng = unit(n_geo[idx])
    ns = ng.copy()
    mat_index = np.zeros(idx.size, dtype=np.int64)
    mat_base = np.cumsum([0] + [len(ob.materials) for ob in scene.objects])
    ob_hit = obj[idx]
    pl = p_loc[idx]
    for k, ob in enumerate(scene.objects):
        sel = ob_hit == k
        if not np.any(sel):
            continue
        r, _ = ob.world_pose(scene.turntable, turntable_deg)
        nl = rows_times(ng[sel], r)  # back to local
        ns[sel] = unit(rows_times(ob.shape.shading_normal(pl[sel], nl), r.T))
        mat_index[sel] = mat_base[k] + ob.material_index(pl[sel])
    flip = np.einsum("ij,ij->i", ng, dd) > 0  # two-sided surfaces face the ray origin
    ng[flip] *= -1
    ns[flip] *= -1
    return Hits(idx, p, ng, ns, mat_index, ob_hit, pl, t_hit[idx])


def light_visibility(scene: Scene, turntable_deg: float, p: np.ndarray, ng: np.ndarray,
                     ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(wi, dist, facing, shadowed)`` of surface points ``p`` ``(M, 3)``: unit directions
    to the point light, distances (m), whether both normals face the light, and whether a
    shadow ray finds an occluder before the light."""
    to_light = scene.light.position_m - p
    dist = np.linalg.norm(to_light, axis=1)
    wi = to_light / dist[:, None]
    facing = (np.einsum("ij,ij->i", ng, wi) > 0) & (np.einsum("ij,ij->i", ns, wi) > 0)
    shadowed = np.zeros(len(p), dtype=bool)
    f_idx = np.nonzero(facing)[0]
    if f_idx.size:
        so = p[f_idx] + SHADOW_EPS_M * ng[f_idx]
        ts, _, _, _ = _nearest_hit(scene, turntable_deg, so, wi[f_idx],
                                   t_max=dist[f_idx] - SHADOW_EPS_M, any_hit=True)
        shadowed[f_idx] = np.isfinite(ts) & (ts < dist[f_idx] - SHADOW_EPS_M)
    return wi, dist, facing, shadowed
