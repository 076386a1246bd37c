"""Polarized BRDF of :class:`polrig.sim.materials.SurfaceMaterial`: conductors, dispersive
dielectrics, anisotropic GGX/Beckmann roughness, partial depolarization and a thin retarding
film, per colour channel, as full 4x4 Mueller matrices times ``cos(theta_i)`` (1/sr).

Model, for ``wi`` (surface -> light), ``wo`` (surface -> camera), shading normal ``n`` and the
surface tangent ``t`` (bitangent ``b = n x t``), per colour ``c``::

    M_c = R_out . P_out . (ks Ms_c + kd_c Md_c) . P_in . R_in

* ``Ms_c = F(h . wi; eta_c) D(h) G(wi, wo) / (4 cos theta_o)``: the microfacet specular term
  of :mod:`polrig.optics.pbrdf` with the complex-index Fresnel matrix
  :func:`polrig.optics.mueller.specular_reflection` (conductors put retardance into ``m22, m23, m32,
  m33``; Mitsuba 3 ``roughconductor``), the anisotropic GGX or Beckmann ``D`` and the separable
  Smith ``G`` with projected roughness ``(alpha_u^2 v_t^2 + alpha_v^2 v_b^2) / v_n^2``
  (Heitz, "Understanding the masking-shadowing function", JCGT 3(2), 2014; Walter et al.,
  EGSR 2007; Mitsuba 3 ``MicrofacetDistribution``, whose Beckmann ``G1`` approximation is used).
* ``Md_c = T_out(theta_o; eta_c) . depolarizer . T_in(theta_i; eta_c) cos(theta_i) / pi``: the
  Baek 2018 diffuse term (dielectrics only) with the index of the channel, so that the
  polarization of the diffuse light now depends on colour (dispersion).
* ``P_in``, ``P_out = diag(1, p, p, p)`` (:func:`polrig.optics.mueller.partial_depolarizer`) with
  ``p = p0 ** (1 / (2 cos theta))`` for the pass in (``theta_i``) and out (``theta_o``): a
  depolarizing layer crossed twice whose polarization memory decays with the path length
  through it (phenomenological); the linear-to-linear elements are scaled by
  ``p0 ** ((1 / cos theta_i + 1 / cos theta_o) / 2)``, the polarizance and diattenuation by
  the out and in factors. One factor per pass keeps the BRDF reciprocal (tested).
* ``R_in``, ``R_out``: a thin birefringent film over the surface, index matched (no Fresnel
  term of its own), fast axis ``f = cos(a) t + sin(a) b`` in the surface plane; each pass is
  the linear retarder :func:`polrig.optics.mueller.retarder_at` with the fast axis at the angle of
  ``f`` in the beam's Stokes frame and retardance ``delta0 (532 nm / lambda_c) / cos theta_t``
  (``cos theta_t`` inside the film of index :data:`polrig.sim.materials.FILM_INDEX`; constant
  birefringence; R. A. Chipman, W. S. T. Lam, G. Young, *Polarized Light and Optical Systems*,
  CRC 2018, ch. 20 on retarders, to first order in the film's obliquity).

With one real ``eta`` for every colour, isotropic roughness, ``p0 = 1`` and no film this is
exactly :func:`polrig.optics.pbrdf.mueller` (tested). Every factor is a realizable Mueller matrix and
sums and products of realizable matrices are realizable, so the truth is realizable.

Stokes bases: incident ``k = -wi``, outgoing ``k = wo``; ``x`` is Mitsuba's default
``stokes_basis(k)`` (``refs = None``, as :func:`polrig.optics.pbrdf.mueller`) or the rig frames from
``refs = (stage_zero_axis, camera_x_axis)`` (as :func:`polrig.optics.pbrdf.linear_rig_mueller`).
Invalid geometry (``wi`` or ``wo`` at or below the horizon) gives zero matrices.
"""

from __future__ import annotations

import numpy as np

from polrig.optics import bases as fr
from polrig.optics import mueller as mu
from polrig.optics.pbrdf import ALPHA_MIN, DISTRIBUTIONS, smith_g1_of_a2t2
from polrig.sim.materials import FILM_INDEX
from polrig.sim.optical_data import WAVELENGTHS_NM

#: Wavelength at which a film's ``retardance_rad`` is given (nm).
RETARDANCE_REFERENCE_NM = 532.0
#: Pixels per chunk (bounds the temporaries: 3 colours x 16 elements x CHUNK doubles).
CHUNK = 8192

PARAM_KEYS = ("eta", "kd", "alpha_u", "alpha_v", "ks", "polarized_fraction", "retardance_rad",
              "fast_axis_rad")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def tangent_frame(n: np.ndarray, t_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangent ``t`` (``t_ref`` projected on the plane of ``n``) and bitangent ``b = n x t``,
    ``(P, 3)`` each; where ``t_ref`` is parallel to ``n`` the tangent is Mitsuba's
    ``stokes_basis(n)``."""
    t_ref = np.broadcast_to(t_ref, n.shape)
    t = t_ref - fr.dot(t_ref, n)[:, None] * n
    length = np.linalg.norm(t, axis=1)
    bad = length < 1e-6  # reference within ~1e-6 rad of the normal: no defined tangent
    if np.any(bad):
        t[bad] = fr.stokes_basis_unit(n[bad])
        length[bad] = 1.0
    t = t / length[:, None]
    return t, fr.cross(n, t)


def microfacet_d(h_local: np.ndarray, alpha_u, alpha_v, distribution: str = "ggx") -> np.ndarray:
    """Anisotropic normal distribution ``D(h)`` (1/sr) for a microfacet normal in the local
    frame ``(t, b, n)`` ``(P, 3)``. GGX: ``1 / (pi au av (x^2/au^2 + y^2/av^2 + z^2)^2)``;
    Beckmann: ``exp(-(x^2/au^2 + y^2/av^2) / z^2) / (pi au av z^4)``. Zero for ``z <= 0`` and
    where ``D z <= 1e-20`` (as Mitsuba 3)."""
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    au = np.maximum(np.asarray(alpha_u, float), ALPHA_MIN)
    av = np.maximum(np.asarray(alpha_v, float), ALPHA_MIN)
    x, y, z = h_local[:, 0], h_local[:, 1], h_local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if distribution == "ggx":
            res = 1.0 / (np.pi * au * av * np.square(np.square(x / au) + np.square(y / av) + z * z))
        else:
            res = np.exp(-(np.square(x / au) + np.square(y / av)) / (z * z)) / (np.pi * au * av * z ** 4)
    return np.where((z > 0) & np.isfinite(res) & (res * z > 1e-20), res, 0.0)


def smith_g1(v_local: np.ndarray, h_local: np.ndarray, alpha_u, alpha_v,
             distribution: str = "ggx") -> np.ndarray:
    """Smith masking ``G1(v, h)`` with the projected roughness (Heitz 2014) for local ``v`` and
    ``h`` ``(P, 3)``: GGX ``2 / (1 + sqrt(1 + a2t2))``, Beckmann Walter et al.'s rational
    approximation; 1 where ``a2t2 = 0``, 0 where ``(v . h) v_z <= 0``."""
    au = np.maximum(np.asarray(alpha_u, float), ALPHA_MIN)
    av = np.maximum(np.asarray(alpha_v, float), ALPHA_MIN)
    xy = np.square(au * v_local[:, 0]) + np.square(av * v_local[:, 1])
    vz = v_local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        g = smith_g1_of_a2t2(xy / (vz * vz), distribution)
    g = np.where(xy == 0.0, 1.0, g)
    g = np.where(fr.dot(v_local, h_local) * vz <= 0.0, 0.0, g)
    return np.where(np.isfinite(g), g, 0.0)


def _to_frames(m: np.ndarray, s_in, s_out, frame_in, frame_out) -> np.ndarray:
    """``m`` ``(P, 4, 4)`` from bases ``x = s_in`` / ``s_out`` to the target frames."""
    ci, si = fr.rotation_cos_sin_2theta_to_frame(s_in, *frame_in)
    co, so = fr.rotation_cos_sin_2theta_to_frame(s_out, *frame_out)
    return fr.rotate_rows(fr.rotate_cols(m, ci, si), co, so)


def _axis_or(axis: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``axis`` where it is non-degenerate, else ``fallback`` (both ``(P, 3)``)."""
    bad = fr.dot(axis, axis) <= 1e-24
    if np.any(bad):
        axis = axis.copy()
        axis[bad] = fallback[bad]
    return axis


def _film_pass(f: np.ndarray, frame, cos_theta: np.ndarray, delta0: np.ndarray) -> np.ndarray:
    """Retarder of one pass through the film ``(P, 3, 4, 4)`` (colour axis): fast axis ``f``
    at its angle in the beam frame, retardance scaled by wavelength and obliquity."""
    phi = np.arctan2(fr.dot(f, frame[1]), fr.dot(f, frame[0]))
    cos_t = np.sqrt(1.0 - (1.0 - cos_theta ** 2) / FILM_INDEX ** 2)
    scale = RETARDANCE_REFERENCE_NM / np.asarray(WAVELENGTHS_NM)  # (3,)
    delta = delta0[:, None] * scale[None, :] / cos_t[:, None]
    return mu.retarder_at(phi[:, None], delta)


def _chunk(n, t_ref, wi, wo, prm, distribution, refs) -> np.ndarray:
    p = len(n)
    out = np.zeros((p, 3, 4, 4))
    cos_i, cos_o = fr.dot(n, wi), fr.dot(n, wo)
    ok = (cos_i > 0) & (cos_o > 0)
    if not np.any(ok):
        return out
    if not np.all(ok):
        refs_ok = None if refs is None else tuple(r if r.ndim == 1 else r[ok] for r in refs)
        sub = _chunk(n[ok], t_ref if t_ref.ndim == 1 else t_ref[ok], wi[ok], wo[ok],
                     {k: v[ok] for k, v in prm.items()}, distribution, refs_ok)
        out[ok] = sub
        return out
    k_in = -wi
    if refs is None:
        x_in, x_out = fr.stokes_basis_unit(k_in), fr.stokes_basis_unit(wo)
    else:
        x_in = fr.basis_from_reference_unit(k_in, refs[0])
        x_out = fr.basis_from_reference_unit(wo, refs[1])
    frame_in, frame_out = (x_in, fr.cross(k_in, x_in)), (x_out, fr.cross(wo, x_out))
    t, b = tangent_frame(n, t_ref)
    eta, ks, kd = prm["eta"], prm["ks"], prm["kd"]
    if np.any(ks > 0):
        h = _unit(wi + wo)
        loc = lambda v: np.stack([fr.dot(v, t), fr.dot(v, b), fr.dot(v, n)], -1)  # noqa: E731
        h_l, i_l, o_l = loc(h), loc(wi), loc(wo)
        au, av = prm["alpha_u"], prm["alpha_v"]
        w = ks * microfacet_d(h_l, au, av, distribution) * smith_g1(i_l, h_l, au, av, distribution) \
            * smith_g1(o_l, h_l, au, av, distribution) / (4.0 * cos_o)
        s = _axis_or(fr.cross(wi, h), x_in)  # perpendicular to the microfacet's plane of incidence
        cos_ih = fr.dot(wi, h)
        for c in range(3):
            f = mu.specular_reflection(cos_ih, eta[:, c])
            out[:, c] += _to_frames(f, s, s, frame_in, frame_out) * w[:, None, None]
    if np.any(kd > 0):
        s_in = _axis_or(fr.cross(n, -wi), x_in)
        s_out = _axis_or(fr.cross(n, wo), x_out)
        for c in range(3):
            t_in = mu.specular_transmission(cos_i, eta[:, c].real)
            t_out = mu.specular_transmission(cos_o, eta[:, c].real)
            md = t_out[:, :, 0, None] * t_in[:, None, 0, :] * (cos_i / np.pi)[:, None, None]
            out[:, c] += _to_frames(md, s_in, s_out, frame_in, frame_out) * kd[:, c, None, None]
    p0 = prm["polarized_fraction"]
    if np.any(p0 < 1):
        out[:, :, 1:, :] *= (p0 ** (0.5 / cos_o))[:, None, None, None]
        out[:, :, :, 1:] *= (p0 ** (0.5 / cos_i))[:, None, None, None]
    d0 = prm["retardance_rad"]
    if np.any(d0 != 0):
        a = prm["fast_axis_rad"]
        f = np.cos(a)[:, None] * t + np.sin(a)[:, None] * b
        out = _film_pass(f, frame_out, cos_o, d0) @ out @ _film_pass(f, frame_in, cos_i, d0)
    return out


def evaluate(normal, tangent_ref, wi, wo, params: dict[str, np.ndarray], *,
             distribution: str = "ggx", refs: tuple | None = None) -> np.ndarray:
    """Mueller matrices times ``cos(theta_i)`` ``(P, 3, 4, 4)`` (pixel, colour R G B, row, col;
    1/sr) of ``P`` surface points.

    ``normal``, ``wi``, ``wo``: ``(P, 3)`` world vectors (normalised here); ``tangent_ref``:
    ``(3,)`` or ``(P, 3)`` tangent reference (projected on the surface); ``params``: the
    per-point arrays of :meth:`polrig.sim.materials.SurfaceMaterial.parameters` (``P`` rows);
    ``refs``: ``None`` for Mitsuba's default Stokes bases or ``(stage_zero_axis,
    camera_x_axis)`` for the rig frames (module docstring), each ``(3,)`` or ``(P, 3)``.
    """
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    missing = [k for k in PARAM_KEYS if k not in params]
    if missing:
        raise ValueError(f"params lack {', '.join(missing)}")
    n = fr.normalize(np.atleast_2d(np.asarray(normal, float)))
    wi = fr.normalize(np.broadcast_to(np.asarray(wi, float), n.shape))
    wo = fr.normalize(np.broadcast_to(np.asarray(wo, float), n.shape))
    t_ref = np.asarray(tangent_ref, float)
    prm = {k: np.broadcast_to(np.asarray(params[k]), (len(n),) + np.shape(params[k])[1:])
           for k in PARAM_KEYS}
    prm["eta"] = prm["eta"].astype(complex)
    if refs is not None:
        refs = tuple(np.asarray(r, float) for r in refs)
    out = np.zeros((len(n), 3, 4, 4))
    for lo in range(0, len(n), CHUNK):
        sl = slice(lo, lo + CHUNK)
        refs_c = None if refs is None else tuple(r if r.ndim == 1 else r[sl] for r in refs)
        out[sl] = _chunk(n[sl], t_ref if t_ref.ndim == 1 else t_ref[sl], wi[sl], wo[sl],
                         {k: v[sl] for k, v in prm.items()}, distribution, refs_c)
    return out
