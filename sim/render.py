"""Vectorised ray casting of a :class:`sim.scene.Scene` into per-pixel ground truth.

One camera ray per pixel centre (:meth:`sim.geometry.PinholeCamera.ray_directions`), nearest
analytic hit over all objects (:mod:`sim.shapes`), one shadow ray per lit pixel towards the
point light against the same shapes, then the pBRDF (:func:`polrig.pbrdf.linear_rig_mueller`)
in the rig's Stokes frames (incident ``x`` = the stage zero axis, emergent ``x`` = the camera
``X`` axis; ``docs/conventions.md``). Only the terms a pixel needs are evaluated: nothing
outside the mask or in shadow, no specular term for ``ks = 0`` materials, no diffuse term for
``kd = 0``; the specular term is colour independent and evaluated once, the diffuse one for
unit albedo and scaled per colour (``M_c = ks Ms + kd_c Md``, the decomposition of
:func:`polrig.pbrdf.specular_diffuse_blocks`).

Radiometry (``docs/conventions.md``, "Radiometric units"): ``brdf`` is the pBRDF times
``cos(theta_i)`` (1/sr) and ``inv_r2`` the inverse-square falloff ``1 / |light - p|^2``
(1/m^2); the radiance leaving a pixel's surface point towards the camera, per unit radiant
intensity of the light and per unit normalised incident Stokes, is ``brdf * inv_r2``
(:meth:`RenderResult.radiance_mueller`). :mod:`sim.world` turns it into DN.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np

from polrig.pbrdf import linear_rig_mueller
from sim import surface_bsdf
from sim.geometry import rows_times, unit
from sim.materials import SurfaceMaterial
from sim.scene import Scene

#: Offset of shadow-ray origins along the geometric normal (metres).
SHADOW_EPS_M = 1e-5


@dataclasses.dataclass
class RenderResult:
    """Per-pixel ground truth of one pose over the full simulated sensor ``(H, W)``.

    Image stacks are plane-first (``docs/conventions.md``). Directions are unit vectors in the
    **camera frame** (OpenCV); zero outside the mask. The pBRDF is stored for the lit pixels
    only (``brdf_lit``); :attr:`brdf` is the ``(3, 3, 3, H, W)`` image (colour R, G, B, row,
    col, v, u) in the rig frames, 1/sr, zero outside lit pixels.
    """

    turntable_deg: float
    mask: np.ndarray          # (H, W) bool: a surface is hit
    lit: np.ndarray           # (H, W) bool: hit, facing the light, not in shadow
    shadow: np.ndarray        # (H, W) bool: hit, facing the light, occluded
    object_index: np.ndarray  # (H, W) int16, -1 = background
    material_index: np.ndarray  # (H, W) int16 into scene.materials, -1 = background
    normal: np.ndarray        # (3, H, W) shading normal, camera frame
    wi: np.ndarray            # (3, H, W) towards the light, camera frame
    wo: np.ndarray            # (3, H, W) towards the camera, camera frame
    position_m: np.ndarray    # (3, H, W) world frame, metres
    depth_m: np.ndarray       # (H, W) camera Z, metres (0 outside the mask)
    kd: np.ndarray            # (3, H, W)
    alpha: np.ndarray         # (H, W)
    eta: np.ndarray           # (H, W)
    ks: np.ndarray            # (H, W)
    inv_r2: np.ndarray        # (H, W) 1/m^2
    lit_index: np.ndarray     # (N,) flat pixel indices (row-major) of the lit pixels
    brdf_lit: np.ndarray      # (N, 3, 3, 3) float32, 1/sr: colour, row, col per lit pixel
    inv_r2_lit: np.ndarray    # (N,) float32 1/m^2 at the lit pixels
    timings_s: dict[str, float]
    counts: dict[str, int]

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape  # type: ignore[return-value]

    def _scatter(self, values: np.ndarray) -> np.ndarray:
        """Lit-pixel values ``(N, *k)`` as a zero-filled plane-first image ``(*k, H, W)``."""
        h, w = self.shape
        k = values.shape[1:]
        out = np.zeros(k + (h * w,), dtype=np.float32)
        out[..., self.lit_index] = np.moveaxis(values, 0, -1)
        return out.reshape(k + (h, w))

    @functools.cached_property
    def brdf(self) -> np.ndarray:
        """pBRDF times cos ``(3, 3, 3, H, W)`` float32 (1/sr), zero where not lit."""
        return self._scatter(self.brdf_lit)

    def radiance_mueller(self) -> np.ndarray:
        """``brdf * inv_r2`` ``(3, 3, 3, H, W)`` float32: emergent radiance per unit radiant
        intensity of the light and per unit normalised incident Stokes."""
        return self._scatter(self.brdf_lit * self.inv_r2_lit[:, None, None, None])

    def radiance_state(self, s_in: np.ndarray) -> np.ndarray:
        """Emergent radiance Stokes image ``(3, 3, H, W)`` float32 (colour, S0..S2) per unit
        radiant intensity for incident Stokes ``s_in`` ``(3,)``: ``S = M s_in`` evaluated on
        the lit pixels only (27 multiply-adds each)."""
        s = np.asarray(s_in, dtype=np.float32)
        m = self.brdf_lit
        out = (m[..., 0] * s[0] + m[..., 1] * s[1] + m[..., 2] * s[2]) * self.inv_r2_lit[:, None, None]
        return self._scatter(out)


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


def render(scene: Scene, turntable_deg: float = 0.0, *, distribution: str = "ggx",
           skip_terms: bool = True) -> RenderResult:
    """Ray-cast ``scene`` with its objects turned to ``turntable_deg``.

    ``skip_terms=False`` evaluates both pBRDF terms on every pixel (mask or not, lit or not)
    and is only there to measure what skipping saves (``benchmarks/bench_sim.py``); the result
    is identical on lit pixels.
    """
    tim: dict[str, float] = {}
    cam = scene.camera
    h, w = cam.height, cam.width
    t0 = time.perf_counter()
    d_all = cam.ray_directions().reshape(-1, 3)
    origin = cam.centre_m
    o_all = np.broadcast_to(origin, d_all.shape)
    t_hit, obj, n_geo, p_loc = _nearest_hit(scene, turntable_deg, o_all, d_all)
    hit = np.isfinite(t_hit)
    idx = np.nonzero(hit)[0]
    d = d_all[idx]
    p = origin + t_hit[idx, None] * d
    wo = -d
    ng = unit(n_geo[idx])
    # shading normals and materials per object
    ns = ng.copy()
    mat_index = np.zeros(idx.size, dtype=np.int64)
    mat_base = np.cumsum([0] + [len(o.materials) for o in scene.objects])
    ob_hit = obj[idx]
    for k, ob in enumerate(scene.objects):
        sel = ob_hit == k
        if not np.any(sel):
            continue
        r, _ = ob.world_pose(scene.turntable, turntable_deg)
        nl = rows_times(ng[sel], r)  # back to local
        ns[sel] = unit(rows_times(ob.shape.shading_normal(p_loc[idx][sel], nl), r.T))
        mat_index[sel] = mat_base[k] + ob.material_index(p_loc[idx][sel])
    flip = np.einsum("ij,ij->i", ng, wo) < 0  # two-sided surfaces face the camera
    ng[flip] *= -1
    ns[flip] *= -1
    tim["intersection"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    to_light = scene.light.position_m - p
    dist = np.linalg.norm(to_light, axis=1)
    wi = to_light / dist[:, None]
    facing = (np.einsum("ij,ij->i", ng, wi) > 0) & (np.einsum("ij,ij->i", ns, wi) > 0)
    shadowed = np.zeros(idx.size, dtype=bool)
    f_idx = np.nonzero(facing)[0]
    if f_idx.size:
        so = p[f_idx] + SHADOW_EPS_M * ng[f_idx]
        ts, _, _, _ = _nearest_hit(scene, turntable_deg, so, wi[f_idx],
                                   t_max=dist[f_idx] - SHADOW_EPS_M, any_hit=True)
        shadowed[f_idx] = np.isfinite(ts) & (ts < dist[f_idx] - SHADOW_EPS_M)
    lit = facing & ~shadowed
    tim["shadow"] = time.perf_counter() - t0

    mats = scene.materials
    kd_tab = np.array([m.kd for m in mats])
    al_tab = np.array([m.alpha for m in mats])
    eta_tab = np.array([m.eta for m in mats])
    ks_tab = np.array([m.ks for m in mats])
    kd = kd_tab[mat_index]
    alpha, eta, ks = al_tab[mat_index], eta_tab[mat_index], ks_tab[mat_index]
    surface = _surface_parameters(scene, turntable_deg, mat_index, p_loc[idx], kd, alpha, eta, ks)
    baek = ~np.isin(mat_index, list(surface))  # pixels of the Baek-family Material

    zero_axis = scene.stage_zero_axis
    cam_x = cam.R[0]
    lit_sel = np.nonzero(lit)[0]  # positions in the hit arrays of the lit pixels
    brdf_px = np.zeros((lit_sel.size, 3, 3, 3))
    if skip_terms:
        spec_sel = np.nonzero((ks[lit_sel] > 0) & baek[lit_sel])[0]  # positions in lit_sel
        diff_sel = np.nonzero((kd[lit_sel].max(axis=1) > 0) & baek[lit_sel])[0]
    else:  # the brute-force reference for the benchmark: every term on every pixel
        spec_sel = diff_sel = None
        ns_f, wi_f, wo_f = _full_directions(cam, d_all, idx, ns, wi, wo, scene)
        at_lit = idx[lit_sel]  # flat pixel index of the lit pixels

    def term(component: str, sel: np.ndarray | None) -> np.ndarray:
        """Unit specular (ks = 1) or diffuse (kd = 1) block at the lit positions ``sel``, or
        over the whole image (no skipping) then picked at the lit pixels."""
        kw = dict(kd=1.0 if component == "diffuse" else 0.0,
                  ks=1.0 if component == "specular" else 0.0, distribution=distribution,
                  components=(component,), stage_zero_axis=zero_axis, camera_x_axis=cam_x)
        if sel is not None:
            q = lit_sel[sel]
            return linear_rig_mueller(ns[q], wi[q], wo[q], alpha=alpha[q], eta=eta[q], **kw)
        m = linear_rig_mueller(ns_f, wi_f, wo_f, alpha=_full(0.5, idx, alpha, h * w),
                               eta=_full(1.5, idx, eta, h * w), **kw)
        return m[at_lit]

    t0 = time.perf_counter()
    if spec_sel is None or spec_sel.size:
        ms = term("specular", spec_sel)
        q = slice(None) if spec_sel is None else spec_sel
        brdf_px[q] += (ks[lit_sel][q, None, None] * ms)[:, None]
    tim["specular"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    if diff_sel is None or diff_sel.size:
        md = term("diffuse", diff_sel)
        q = slice(None) if diff_sel is None else diff_sel
        brdf_px[q] += kd[lit_sel][q, :, None, None] * md[:, None]
    tim["diffuse"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    n_surface = 0
    for k, (prm, t_ref, micro) in surface.items():
        q = np.nonzero(mat_index[lit_sel] == k)[0]  # positions in lit_sel
        if not q.size:
            continue
        sel = np.searchsorted(prm["hit_positions"], lit_sel[q])
        pl = lit_sel[q]
        m = surface_bsdf.evaluate(ns[pl], t_ref, wi[pl], wo[pl],
                                  {key: v[sel] for key, v in prm.items() if key != "hit_positions"},
                                  distribution=micro, refs=(zero_axis, cam_x))
        brdf_px[q] = m[..., :3, :3]
        n_surface += q.size
    tim["surface"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_pix = h * w

    def image(values: np.ndarray, fill=0.0, dtype=np.float32) -> np.ndarray:
        out = np.full((n_pix,) + values.shape[1:], fill, dtype=dtype)
        out[idx] = values
        return np.moveaxis(out.reshape((h, w) + values.shape[1:]),
                           (0, 1), (-2, -1)) if values.ndim > 1 else out.reshape(h, w)

    to_cam = cam.R.T  # row vectors: v_cam = v_world @ R^T
    mask = hit.reshape(h, w)
    p_cam_z = rows_times(p, to_cam)[:, 2] + cam.t[2]
    res = RenderResult(
        turntable_deg=float(turntable_deg), mask=mask,
        lit=image(lit, False, bool), shadow=image(facing & shadowed, False, bool),
        object_index=image(ob_hit, -1, np.int16), material_index=image(mat_index, -1, np.int16),
        normal=image(rows_times(ns, to_cam)), wi=image(rows_times(wi, to_cam)),
        wo=image(rows_times(wo, to_cam)),
        position_m=image(p), depth_m=image(p_cam_z), kd=image(kd), alpha=image(alpha),
        eta=image(eta), ks=image(ks), inv_r2=image(1.0 / dist ** 2),
        lit_index=idx[lit_sel], brdf_lit=brdf_px.astype(np.float32),
        inv_r2_lit=(1.0 / dist[lit_sel] ** 2).astype(np.float32),
        timings_s=tim,
        counts={"pixels": n_pix, "hit": int(idx.size), "lit": int(lit.sum()),
                "shadowed": int((facing & shadowed).sum()),
                "specular_evals": int(n_pix if spec_sel is None else spec_sel.size),
                "diffuse_evals": int(n_pix if diff_sel is None else diff_sel.size),
                "surface_evals": n_surface})
    tim["assemble"] = time.perf_counter() - t0
    return res


def _surface_parameters(scene: Scene, turntable_deg: float, mat_index: np.ndarray,
                        p_local: np.ndarray, kd: np.ndarray, alpha: np.ndarray, eta: np.ndarray,
                        ks: np.ndarray) -> dict[int, tuple[dict, np.ndarray, str]]:
    """Per-point parameters of the hit pixels of every :class:`SurfaceMaterial` (textures
    evaluated at the local points ``p_local`` ``(N, 3)``), keyed by material index:
    ``(params incl. "hit_positions", world tangent reference (3,), distribution)``. Writes the
    nominal per-pixel truth (``kd``, ``alpha`` along the tangent, real green ``eta``, ``ks``)
    into the given arrays in place."""
    out = {}
    k = 0
    for ob in scene.objects:
        r, _ = ob.world_pose(scene.turntable, turntable_deg)
        for mat in ob.materials:
            if isinstance(mat, SurfaceMaterial):
                pos = np.nonzero(mat_index == k)[0]
                prm = mat.parameters(p_local[pos])
                kd[pos], alpha[pos], ks[pos] = prm["kd"], prm["alpha_u"], prm["ks"]
                eta[pos] = prm["eta"][:, 1].real
                prm["hit_positions"] = pos
                out[k] = (prm, r @ np.asarray(mat.tangent_axis), mat.distribution)
            k += 1
    return out


def _full(fill: float, idx: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``values`` at pixels ``idx`` of a flat image of ``n`` pixels, ``fill`` elsewhere."""
    out = np.full(n, fill)
    out[idx] = values
    return out


def _full_directions(cam, d_all, idx, ns, wi, wo, scene):
    """Per-pixel vectors over the whole image for the no-skipping benchmark path (background
    pixels get a plausible geometry so the pBRDF does full work on them)."""
    ns_f = -d_all.copy()
    wo_f = -d_all.copy()
    wi_f = unit(scene.light.position_m - (cam.centre_m + 0.5 * d_all))
    ns_f[idx], wi_f[idx], wo_f[idx] = ns, wi, wo
    return ns_f, wi_f, wo_f
