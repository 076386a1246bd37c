"""One bounce of indirect light between the surfaces of a scene (issue 23, item 2).

The direct renderer (:mod:`polrig.sim.render`) lights every surface point by the point light alone.
Concave objects and facing objects also light each other; this module adds the light that
reaches a visible point ``p`` after exactly one reflection at another surface point ``q``
(or another point of the same object):

    L(p -> camera) += integral over the hemisphere at p of
                      M_p(omega -> camera) . M_q(light -> q -> p) I / |light - q|^2  d omega

with ``M`` the polarized BRDF times the cosine of its incident direction (1/sr) evaluated as
full 4x4 Mueller matrices by :mod:`polrig.sim.surface_bsdf` for every material (a Baek-family
:class:`polrig.sim.materials.Material` is the equivalent :class:`SurfaceMaterial`; identical values,
tested), so circular polarization created at ``q`` (a metal) is carried to ``p``. The
intermediate beam ``q -> p`` has one Stokes frame on both sides (``x`` from the fixed
reference :data:`BEAM_REFERENCE`, made perpendicular). The integral is estimated by Monte
Carlo with cosine-weighted directions about the shading normal of ``p`` (pdf ``cos / pi``),
``samples`` per pixel from a seeded generator: the estimate is deterministic for a seed and
is *the* truth of the rendered images (the images are made from it), with Monte Carlo noise
of relative size about ``1 / sqrt(samples)`` in the indirect part only. Sums of realizable
matrices are realizable, so the truth stays realizable.

Why polrig's own renderer rather than Mitsuba 3's polarized path tracer: Mitsuba's emitters
are unpolarized and its ``stokes`` integrator returns Stokes images in its own camera bases,
so the per-pixel Mueller block in the rig frames would need several renders through polarizer
sheets and a basis change per pixel; here the block is exact per path and uses the same
frames and materials as the direct truth. The estimator is checked against a deterministic
quadrature of the same integral over the reflecting surface (tests/test_sim_interreflection.py).
"""

from __future__ import annotations

import numpy as np

from polrig.optics import bases as fr
from polrig.sim import surface_bsdf
from polrig.sim.materials import Material, SurfaceMaterial
from polrig.sim.raycast import SHADOW_EPS_M, light_visibility, surface_hits
from polrig.sim.scene import Scene

#: World reference for the ``x`` axis of the Stokes frame of the beam between two surfaces.
BEAM_REFERENCE = np.array([0.267261, 0.534522, 0.801784])


def as_surface(material: Material | SurfaceMaterial, distribution: str = "ggx") -> SurfaceMaterial:
    """The :class:`SurfaceMaterial` equivalent to a Baek-family ``material`` (same ``eta`` in
    every colour, isotropic, no film or depolarizing layer); surface materials pass through."""
    if isinstance(material, SurfaceMaterial):
        return material
    return SurfaceMaterial(material.name, (material.eta,) * 3, material.alpha, kd=material.kd,
                           ks=material.ks, distribution=distribution)


def evaluate_materials(scene: Scene, turntable_deg: float, mat_index: np.ndarray,
                       p_local: np.ndarray, n: np.ndarray, wi: np.ndarray, wo: np.ndarray,
                       refs: tuple, distribution: str = "ggx") -> np.ndarray:
    """4x4 Mueller matrices times ``cos(theta_i)`` ``(P, 3, 4, 4)`` of the scene's materials at
    ``P`` points (material index into ``scene.materials``, local points for textures, world
    normal and directions), Stokes frames from ``refs`` (:func:`polrig.sim.surface_bsdf.evaluate`)."""
    out = np.zeros((len(n), 3, 4, 4))
    k = 0
    for ob in scene.objects:
        rot, _ = ob.world_pose(scene.turntable, turntable_deg)
        for mat in ob.materials:
            sel = np.nonzero(mat_index == k)[0]
            k += 1
            if not sel.size:
                continue
            sm = as_surface(mat, distribution)
            r_sel = tuple(r if np.ndim(r) == 1 else r[sel] for r in refs)
            out[sel] = surface_bsdf.evaluate(n[sel], rot @ np.asarray(sm.tangent_axis), wi[sel], wo[sel],
                                             sm.parameters(p_local[sel]), distribution=sm.distribution,
                                             refs=r_sel)
    return out


def cosine_directions(ns: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Cosine-weighted unit directions about the normals ``ns`` ``(M, 3)`` from uniform
    ``u1``, ``u2`` ``(M,)`` (Malley's method: ``pdf = cos(theta) / pi``)."""
    t = fr.stokes_basis_unit(ns)
    b = fr.cross(ns, t)
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    z = np.sqrt(np.maximum(1.0 - u1, 0.0))
    return (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b + z[:, None] * ns


def one_bounce(scene: Scene, turntable_deg: float, p: np.ndarray, ng: np.ndarray, ns: np.ndarray,
               wo: np.ndarray, mat_index: np.ndarray, p_local: np.ndarray, *, samples: int,
               seed: int = 0, distribution: str = "ggx") -> np.ndarray:
    """One-bounce indirect radiance Mueller blocks ``(M, 3, 3, 3)`` (colour, row, col; per unit
    radiant intensity of the light, the units of :meth:`polrig.sim.render.RenderResult.radiance_mueller`)
    at ``M`` visible points (world ``p``, normals facing the camera, ``wo`` towards the camera),
    in the rig frames (incident: stage zero axis, emergent: camera ``X``)."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(round(turntable_deg * 1e6)) % (1 << 62)]))
    m = len(p)
    acc = np.zeros((m, 3, 4, 4))
    cam_x = scene.camera.R[0]
    for _ in range(samples):
        omega = cosine_directions(ns, rng.random(m), rng.random(m))
        cos_p = np.einsum("ij,ij->i", ns, omega)
        ok = np.nonzero((np.einsum("ij,ij->i", ng, omega) > 0) & (cos_p > 0))[0]
        hits = surface_hits(scene, turntable_deg, p[ok] + SHADOW_EPS_M * ng[ok], omega[ok])
        wi_q, dist_q, facing, shadowed = light_visibility(scene, turntable_deg, hits.p, hits.ng, hits.ns)
        lit_q = np.nonzero(facing & ~shadowed)[0]
        rows = ok[hits.index[lit_q]]  # the pixels whose sample reaches a lit point q
        if not rows.size:
            continue
        w = omega[rows]
        m_q = evaluate_materials(scene, turntable_deg, hits.mat_index[lit_q], hits.p_local[lit_q],
                                 hits.ns[lit_q], wi_q[lit_q], -w, (scene.stage_zero_axis, BEAM_REFERENCE),
                                 distribution)
        m_p = evaluate_materials(scene, turntable_deg, mat_index[rows], p_local[rows], ns[rows], w,
                                 wo[rows], (BEAM_REFERENCE, cam_x), distribution)
        scale = np.pi / (cos_p[rows] * dist_q[lit_q] ** 2)
        acc[rows] += (m_p @ m_q) * scale[:, None, None, None]
    return acc[..., :3, :3] / samples
