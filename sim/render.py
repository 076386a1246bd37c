"""Vectorised ray casting of a :class:`polrig.sim.scene.Scene` into per-pixel ground truth.

One camera ray per pixel centre (:meth:`polrig.sim.geometry.PinholeCamera.ray_directions`), nearest
analytic hit over all objects (:mod:`polrig.sim.shapes`), one shadow ray per lit pixel towards the
point light against the same shapes, then the pBRDF (:func:`polrig.optics.pbrdf.linear_rig_mueller`)
in the rig's Stokes frames (incident ``x`` = the stage zero axis, emergent ``x`` = the camera
``X`` axis; ``docs/conventions.md``). Only the terms a pixel needs are evaluated: nothing
outside the mask or in shadow, no specular term for ``ks = 0`` materials, no diffuse term for
``kd = 0``; the specular term is colour independent and evaluated once, the diffuse one for
unit albedo and scaled per colour (``M_c = ks Ms + kd_c Md``, the decomposition of
:func:`polrig.optics.pbrdf.specular_diffuse_blocks`).

Radiometry (``docs/conventions.md``, "Radiometric units"): ``brdf`` is the pBRDF times
``cos(theta_i)`` (1/sr) and ``inv_r2`` the inverse-square falloff ``1 / |light - p|^2``
(1/m^2); the radiance leaving a pixel's surface point towards the camera, per unit radiant
intensity of the light and per unit normalised incident Stokes, is ``brdf * inv_r2``
(:meth:`RenderResult.radiance_mueller`). :mod:`polrig.sim.world` turns it into DN.

Materials outside the Baek family (:class:`polrig.sim.materials.SurfaceMaterial`: conductors,
dispersive dielectrics, anisotropic roughness, films, depolarizing layers, textures) are
evaluated per colour by :func:`polrig.sim.surface_bsdf.evaluate` (4x4, then the linear block);
Baek-family pixels take the path above unchanged. ``indirect_samples > 0`` adds one bounce of
interreflected light (:mod:`polrig.sim.interreflection`) to :meth:`RenderResult.radiance_mueller`
and :meth:`RenderResult.radiance_state`; ``brdf`` stays the direct term. Ray casting is
:mod:`polrig.sim.raycast`.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np

from polrig.optics.pbrdf import linear_rig_mueller
from polrig.sim import surface_bsdf
from polrig.sim.footprint import footprint_albedo
from polrig.sim.geometry import rows_times, unit
from polrig.sim.interreflection import one_bounce
from polrig.sim.materials import SurfaceMaterial
from polrig.sim.raycast import light_visibility, surface_hits
from polrig.sim.scene import Scene


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
    indirect_index: np.ndarray | None = None  # (K,) flat pixel indices with indirect light
    indirect: np.ndarray | None = None        # (K, 3, 3, 3) float32 indirect radiance Mueller

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

    def _add_indirect(self, img: np.ndarray, values: np.ndarray | None) -> np.ndarray:
        """``img`` ``(*k, H, W)`` plus indirect ``values`` ``(K, *k)`` at their pixels."""
        if self.indirect_index is None or values is None:
            return img
        h, w = self.shape
        flat = img.reshape(img.shape[:-2] + (h * w,))
        flat[..., self.indirect_index] += np.moveaxis(values, 0, -1).astype(np.float32)
        return flat.reshape(img.shape)

    def radiance_mueller(self) -> np.ndarray:
        """``brdf * inv_r2`` (plus the one-bounce indirect light when rendered with
        ``indirect_samples``) ``(3, 3, 3, H, W)`` float32: emergent radiance per unit radiant
        intensity of the light and per unit normalised incident Stokes."""
        return self._add_indirect(self._scatter(self.brdf_lit * self.inv_r2_lit[:, None, None, None]),
                                  self.indirect)

    def radiance_state(self, s_in: np.ndarray) -> np.ndarray:
        """Emergent radiance Stokes image ``(3, 3, H, W)`` float32 (colour, S0..S2) per unit
        radiant intensity for incident Stokes ``s_in`` ``(3,)``: ``S = M s_in`` evaluated on
        the lit pixels only (27 multiply-adds each)."""
        s = np.asarray(s_in, dtype=np.float32)
        m = self.brdf_lit
        out = (m[..., 0] * s[0] + m[..., 1] * s[1] + m[..., 2] * s[2]) * self.inv_r2_lit[:, None, None]
        ind = None if self.indirect is None else self.indirect @ s
        return self._add_indirect(self._scatter(out), ind)


def render(scene: Scene, turntable_deg: float = 0.0, *, distribution: str = "ggx",
           skip_terms: bool = True, indirect_samples: int = 0, indirect_seed: int = 0) -> RenderResult:
    """Ray-cast ``scene`` with its objects turned to ``turntable_deg``.

    ``indirect_samples > 0`` adds one bounce of indirect light between the surfaces
    (:func:`polrig.sim.interreflection.one_bounce`, that many Monte Carlo samples per visible pixel,
    seeded by ``indirect_seed`` and the pose) to every visible pixel, lit or in shadow; the
    default 0 renders direct light only, exactly as before.

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
    hits = surface_hits(scene, turntable_deg, o_all, d_all)
    idx, p, ng, ns, mat_index, ob_hit = hits.index, hits.p, hits.ng, hits.ns, hits.mat_index, hits.obj
    p_loc = hits.p_local
    wo = -d_all[idx]
    tim["intersection"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    wi, dist, facing, shadowed = light_visibility(scene, turntable_deg, p, ng, ns)
    lit = facing & ~shadowed
    tim["shadow"] = time.perf_counter() - t0

    mats = scene.materials
    kd_tab = np.array([m.kd for m in mats])
    al_tab = np.array([m.alpha for m in mats])
    eta_tab = np.array([m.eta for m in mats])
    ks_tab = np.array([m.ks for m in mats])
    kd = footprint_albedo(scene, turntable_deg, hits, kd_tab[mat_index])
    alpha, eta, ks = al_tab[mat_index], eta_tab[mat_index], ks_tab[mat_index]
    surface = _surface_parameters(scene, turntable_deg, mat_index, p_loc, kd, alpha, eta, ks)
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
    ind_index = ind_values = None
    if indirect_samples > 0:
        t0 = time.perf_counter()
        ind = one_bounce(scene, turntable_deg, p, ng, ns, wo, mat_index, p_loc,
                         samples=int(indirect_samples), seed=indirect_seed, distribution=distribution)
        keep = np.nonzero(np.abs(ind).max(axis=(1, 2, 3)) > 0)[0]
        ind_index, ind_values = idx[keep], ind[keep].astype(np.float32)
        tim["indirect"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_pix = h * w

    def image(values: np.ndarray, fill=0.0, dtype=np.float32) -> np.ndarray:
        out = np.full((n_pix,) + values.shape[1:], fill, dtype=dtype)
        out[idx] = values
        return np.moveaxis(out.reshape((h, w) + values.shape[1:]),
                           (0, 1), (-2, -1)) if values.ndim > 1 else out.reshape(h, w)

    to_cam = cam.R.T  # row vectors: v_cam = v_world @ R^T
    mask = np.zeros(n_pix, bool)
    mask[idx] = True
    mask = mask.reshape(h, w)
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
                "surface_evals": n_surface,
                "indirect_pixels": 0 if ind_index is None else int(ind_index.size)},
        indirect_index=ind_index, indirect=ind_values)
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
