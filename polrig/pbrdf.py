"""Analytic polarimetric BRDF: the microfacet pBRDF of Baek et al. 2018, as in Mitsuba 3's
``pplastic``.

Model (S.-H. Baek, D. S. Jeon, X. Tong, M. H. Kim, "Simultaneous acquisition of polarimetric
SVBRDF and normals", ACM TOG 37(6) 268, SIGGRAPH Asia 2018; implemented by Mitsuba 3,
``src/bsdfs/pplastic.cpp``, whose math and Stokes bases this module follows exactly), for a
light direction ``wi`` (surface -> light), a view direction ``wo`` (surface -> camera) and the
shading normal ``n``, all unit vectors in world coordinates::

    M(wi, wo) = f(wi, wo) cos(theta_i) = ks * Ms + kd * Md

    Ms = F_R(h . wi; eta) D(h) G(wi, wo) / (4 cos theta_o)          (h = normalize(wi + wo))
    Md = T_out(theta_o) . depolarizer . T_in(theta_i) * cos(theta_i) / pi

``F_R`` is the Fresnel reflection Mueller matrix in the microfacet's plane of incidence (s axis
``wi x h``), ``T_in``/``T_out`` the Fresnel transmission matrices at the macro surface (s axes
``n x (-wi)`` and ``n x wo``), each rotated into the returned bases. ``D`` is the GGX
(Trowbridge-Reitz; Walter et al., EGSR 2007) or Beckmann normal distribution, ``G`` the
separable Smith shadowing-masking ``G1(wi) G1(wo)`` (for Beckmann, Walter et al.'s rational
approximation of ``G1``, as Mitsuba uses). ``ks`` is pplastic's ``specular_reflectance``, ``kd``
its ``diffuse_reflectance`` (the depolarizer's value): both scale their term only; pplastic's
``specular_sampling_weight`` affects sampling, never the value. ``T_out`` uses the external
angle, equal to pplastic's internal-angle evaluation with ``1/eta`` by the reciprocity of
Fresnel transmittances. As in Mitsuba's ``MicrofacetDistribution``, ``alpha`` is clamped to at
least ``1e-4``.

Stokes bases of :func:`mueller` (Mitsuba's default bases in world coordinates, i.e. what
Mitsuba's ``SurfaceInteraction3f.to_world_mueller`` gives for ``pplastic.eval``):

* incident: propagation ``k = -wi``, ``x = polrig.frames.stokes_basis(-wi)``;
* outgoing: propagation ``k = wo``, ``x = polrig.frames.stokes_basis(wo)``;
* ``y = k x x`` (``docs/conventions.md``).

:func:`to_rig_frames`, :func:`linear_rig_mueller` and :func:`specular_diffuse_blocks` express
the same matrices in the rig's incident and emergent frames (:mod:`polrig.frames`).
Units: dimensionless BRDF times ``cos(theta_i)``, i.e. 1/sr (``docs/conventions.md``).
Below-horizon ``wi`` or ``wo`` (``n . w <= 0``), and pixels with non-finite or zero-length
vectors or non-finite material parameters, give the zero matrix (see :func:`visible`).

Reciprocity (Stokes bases as above, reversing the path keeps each physical ``x`` axis): with
``Q = diag(1, 1, -1, 1)``, ``M(wo, wi) / cos(theta_o) = Q M(wi, wo)^T Q / cos(theta_i)``
when ``M(wo, wi)`` uses in basis ``x_out`` and out basis ``x_in`` of ``M(wi, wo)``
(Jones-matrix reciprocity, J. W. Hovenier, J. Atmos. Sci. 26, 488, 1969; H. C. van de Hulst,
*Light Scattering by Small Particles*, 1957, sec. 5.32; the ``-1`` on ``S2`` because
``y = k x x`` flips with ``k``). Tested in ``tests/test_pbrdf.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from polrig import frames as _fr

DISTRIBUTIONS = ("ggx", "beckmann")
COMPONENTS = ("specular", "diffuse")
#: Smallest roughness used (Mitsuba 3 ``MicrofacetDistribution`` clamps alpha the same way).
ALPHA_MIN = 1e-4

__all__ = [
    "ALPHA_MIN", "COMPONENTS", "DISTRIBUTIONS", "microfacet_d", "smith_g1", "fresnel_reflection_sp",
    "visible", "mueller", "to_rig_frames", "linear_rig_mueller", "specular_diffuse_blocks",
]


# ----------------------------------------------------------------------------- microfacets

def _check_distribution(distribution: str) -> str:
    d = str(distribution).lower()
    if d not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    return d


def microfacet_d(cos_h, alpha, distribution: str = "ggx") -> np.ndarray:
    """Isotropic normal distribution ``D(h)`` (1/sr) at ``cos_h = n . h``.

    GGX: ``1 / (pi a^2 cos^4 (1 + tan^2 / a^2)^2)``; Beckmann:
    ``exp(-tan^2 / a^2) / (pi a^2 cos^4)`` (Walter et al., "Microfacet models for refraction
    through rough surfaces", EGSR 2007, eqs. 33 and 25). Zero for ``cos_h <= 0`` and, as in
    Mitsuba, where ``D cos_h <= 1e-20``.
    """
    d = _check_distribution(distribution)
    c = np.asarray(cos_h, dtype=np.float64)
    a2 = np.square(np.maximum(np.asarray(alpha, dtype=np.float64), ALPHA_MIN))
    c2 = c * c
    s2 = np.maximum(1.0 - c2, 0.0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if d == "ggx":
            res = 1.0 / (np.pi * a2 * np.square(s2 / a2 + c2))
        else:
            res = np.exp(-s2 / (a2 * c2)) / (np.pi * a2 * c2 * c2)
    ok = (c > 0) & (res * c > 1e-20) & np.isfinite(res)
    return np.where(ok, res, 0.0)


def smith_g1(cos_v, cos_vh, alpha, distribution: str = "ggx") -> np.ndarray:
    """Smith masking ``G1(v, h)`` for a direction at ``cos_v = n . v`` and ``cos_vh = v . h``.

    GGX: ``2 / (1 + sqrt(1 + a^2 tan^2))``; Beckmann: Walter et al. (2007) eq. 27's rational
    approximation with ``b = 1 / (a tan)``: ``(3.535 b + 2.181 b^2) / (1 + 2.276 b + 2.577 b^2)``
    for ``b < 1.6``, else 1 (what Mitsuba 3 evaluates). 1 at normal incidence; 0 when ``v``
    sees the back of the microfacet (``cos_vh cos_v <= 0``).
    """
    d = _check_distribution(distribution)
    cv = np.asarray(cos_v, dtype=np.float64)
    a2 = np.square(np.maximum(np.asarray(alpha, dtype=np.float64), ALPHA_MIN))
    s2 = np.maximum(1.0 - cv * cv, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t2a2 = a2 * s2 / (cv * cv)
        if d == "ggx":
            g = 2.0 / (1.0 + np.sqrt(1.0 + t2a2))
        else:
            b = 1.0 / np.sqrt(t2a2)
            g = np.where(b >= 1.6, 1.0, (3.535 * b + 2.181 * b * b) / (1.0 + 2.276 * b + 2.577 * b * b))
    g = np.where(s2 == 0.0, 1.0, g)
    g = np.where(np.asarray(cos_vh) * cv <= 0.0, 0.0, g)
    return np.where(np.isfinite(g), g, 0.0)


# ----------------------------------------------------------------------------- Fresnel

def _fresnel_rs_rp(cos_i: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Real Fresnel amplitudes ``(r_s, r_p, tir)`` for a real ``eta`` (sign convention of
    :func:`polrig.mueller.specular_reflection`, i.e. Mitsuba's); ``tir`` marks total internal
    reflection (only possible for ``eta < 1``), where the amplitudes are not real."""
    ci = np.clip(cos_i, 0.0, 1.0)
    eta = np.asarray(eta, dtype=np.float64)
    ct2 = 1.0 - (1.0 - ci * ci) / (eta * eta)
    tir = ct2 < 0.0
    ct = np.sqrt(np.maximum(ct2, 0.0))
    ect = eta * ct
    eci = eta * ci
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (ci - ect) / (ci + ect)
        rp = (eci - ct) / (eci + ct)
    return rs, rp, tir


def _fresnel_reflection_abcs(cos_i, eta) -> tuple[np.ndarray, ...]:
    """Elements ``(a, b, c, s)`` of the Fresnel reflection Mueller matrix
    ``[[a, b, 0, 0], [b, a, 0, 0], [0, 0, c, -s], [0, 0, s, c]]`` (s/p bases) for real ``eta``,
    with Mitsuba 3's ``mueller::specular_reflection`` layout: ``c + i s = r_p conj(r_s)``
    (phase ``delta = arg r_p - arg r_s``). Real arithmetic; under total internal reflection
    (``eta < 1``) the amplitudes are complex with ``cos_t = -i sqrt(sin^2/eta^2 - 1)``, the
    branch that reproduces Mitsuba's sign of the retardance."""
    ci = np.asarray(cos_i, dtype=np.float64)
    rs, rp, tir = _fresnel_rs_rp(ci, eta)
    Rs, Rp = rs * rs, rp * rp
    a, b, c = 0.5 * (Rs + Rp), 0.5 * (Rs - Rp), rs * rp
    s = np.zeros(c.shape)
    if np.any(tir):
        shape = c.shape
        tir = np.broadcast_to(tir, shape)
        cit = np.clip(np.broadcast_to(ci, shape)[tir], 0.0, 1.0)
        et = np.broadcast_to(np.asarray(eta, dtype=np.float64), shape)[tir]
        ct = -1j * np.sqrt((1.0 - cit * cit) / (et * et) - 1.0)
        rs_c = (cit - et * ct) / (cit + et * ct)
        rp_c = (et * cit - ct) / (et * cit + ct)
        prod = rp_c * np.conj(rs_c)
        a, b, c = (np.array(np.broadcast_to(x, shape)) for x in (a, b, c))
        Rs_c, Rp_c = np.abs(rs_c) ** 2, np.abs(rp_c) ** 2
        a[tir], b[tir], c[tir], s[tir] = 0.5 * (Rs_c + Rp_c), 0.5 * (Rs_c - Rp_c), prod.real, prod.imag
    return a, b, c, s


def fresnel_reflection_sp(cos_i, eta) -> np.ndarray:
    """Fresnel reflection Mueller matrix ``(..., 4, 4)`` in the s/p bases for a real relative
    index ``eta``, equal to Mitsuba 3's ``mueller::specular_reflection`` (also under total
    internal reflection, ``eta < 1``, where the retardance elements ``m23 = -m32`` appear).
    Same as :func:`polrig.mueller.specular_reflection` for real amplitudes (``eta > 1``)."""
    a, b, c, s = _fresnel_reflection_abcs(cos_i, eta)
    out = np.zeros(a.shape + (4, 4))
    out[..., 0, 0] = out[..., 1, 1] = a
    out[..., 0, 1] = out[..., 1, 0] = b
    out[..., 2, 2] = out[..., 3, 3] = c
    out[..., 3, 2] = s
    out[..., 2, 3] = -s
    return out


def _transmission_ab(cos_i: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray]:
    """``(a, b) = ((Ts + Tp)/2, (Ts - Tp)/2)`` of the Fresnel transmission Mueller matrix
    (:func:`polrig.mueller.specular_transmission`), real ``eta``; zero under TIR."""
    rs, rp, tir = _fresnel_rs_rp(cos_i, eta)
    ts = np.where(tir, 0.0, 1.0 - rs * rs)
    tp = np.where(tir, 0.0, 1.0 - rp * rp)
    return 0.5 * (ts + tp), 0.5 * (ts - tp)


# ----------------------------------------------------------------------------- inputs

def visible(normal, wi, wo) -> np.ndarray:
    """``True`` where the pBRDF is defined: finite non-zero vectors and both ``wi`` and ``wo``
    strictly above the tangent plane of ``normal`` (all ``(..., 3)``, world coordinates)."""
    n, i, o = (_fr.normalize(v) for v in (normal, wi, wo))
    ok = _fr.valid_direction(normal) & _fr.valid_direction(wi) & _fr.valid_direction(wo)
    return ok & (_fr.dot(n, i) > 0) & (_fr.dot(n, o) > 0)


def _components(components: Sequence[str]) -> tuple[bool, bool]:
    if isinstance(components, str):
        components = (components,)
    comps = tuple(str(c).lower() for c in components)
    bad = [c for c in comps if c not in COMPONENTS]
    if bad:
        raise ValueError(f"components must be drawn from {COMPONENTS}, got {bad}")
    return "specular" in comps, "diffuse" in comps


class _Pixels(NamedTuple):
    """Valid pixels gathered into flat, component-major stacks (``P`` pixels)."""

    n: np.ndarray       # (P, 3)
    wi: np.ndarray      # (P, 3)
    wo: np.ndarray      # (P, 3)
    cos_i: np.ndarray   # (P,)
    cos_o: np.ndarray   # (P,)
    batch: tuple        # pixel shape of the result
    flat: np.ndarray | None  # flat indices of the valid pixels, None when all are valid

    @property
    def npix(self) -> int:
        return int(np.prod(self.batch)) if self.flat is None else int(self.flat.size)

    def scalar(self, a) -> np.ndarray:
        """A per-pixel parameter (scalar or broadcastable to ``batch``) at the valid pixels;
        scalars stay scalars."""
        a = np.asarray(a, dtype=np.float64)
        if a.ndim == 0:
            return a
        a = np.broadcast_to(a, self.batch).reshape(-1)
        return a if self.flat is None else a[self.flat]

    def vectors(self, v) -> np.ndarray:
        """``(..., 3)`` vectors at the valid pixels, ``(P, 3)`` (a single ``(3,)`` stays)."""
        v = np.asarray(v, dtype=np.float64)
        if v.ndim == 1:
            return v
        out = _fr._empty_vectors((self.npix, 3))
        for c in range(3):
            comp = np.broadcast_to(v[..., c], self.batch).reshape(-1)
            out[:, c] = comp if self.flat is None else comp[self.flat]
        return out


def _gather(normal, wi, wo, alpha, eta, *, extra_shapes=(), extra_ok=None) -> tuple[_Pixels, np.ndarray, np.ndarray]:
    """Validate and gather the valid pixels. Returns ``(pixels, alpha_v, eta_v)``."""
    vecs = [_fr._as_vectors(v, name) for v, name in ((normal, "normal"), (wi, "wi"), (wo, "wo"))]
    alpha = np.asarray(alpha, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    if np.any(alpha < 0):
        raise ValueError("alpha (microfacet roughness) must be >= 0")
    if np.any(eta <= 0):
        raise ValueError("eta (relative refractive index) must be > 0")
    batch = np.broadcast_shapes(*(v.shape[:-1] for v in vecs), alpha.shape, eta.shape, *extra_shapes)
    n, i, o = (_fr.normalize(v) for v in vecs)
    cos_i = _fr.dot(n, i)
    cos_o = _fr.dot(n, o)
    ok = (_fr.valid_direction(vecs[0]) & _fr.valid_direction(vecs[1]) & _fr.valid_direction(vecs[2])
          & (cos_i > 0) & (cos_o > 0) & np.isfinite(alpha) & np.isfinite(eta))
    if extra_ok is not None:
        ok = ok & extra_ok
    ok = np.broadcast_to(ok, batch).reshape(-1)
    flat = None if ok.all() else np.flatnonzero(ok)
    pix = _Pixels(n, i, o, cos_i, cos_o, batch, flat)
    pix = pix._replace(n=pix.vectors(n), wi=pix.vectors(i), wo=pix.vectors(o))
    pix = pix._replace(cos_i=_fr.dot(pix.n, pix.wi), cos_o=_fr.dot(pix.n, pix.wo))
    return pix, np.maximum(pix.scalar(alpha), ALPHA_MIN), pix.scalar(eta)


# ----------------------------------------------------------------------------- unit terms
# Terms are dictionaries {(row, col): (P,) array} of their non-zero elements.

def _specular_elements(pix: _Pixels, alpha, eta, distribution, x_in, x_out, nmat: int) -> dict:
    """Elements of ``Ms`` (``ks = 1``) in bases ``x_in`` (about ``-wi``), ``x_out`` (about
    ``wo``): ``R(theta_out) F R(theta_in)^T * D G / (4 cos_o)``, written out element-wise."""
    wi, wo = pix.wi, pix.wo
    h = _fr.normalize(wi + wo)
    cos_h = _fr.dot(pix.n, h)
    cos_ih = _fr.dot(wi, h)  # = wo . h
    value = (microfacet_d(cos_h, alpha, distribution)
             * smith_g1(pix.cos_i, cos_ih, alpha, distribution)
             * smith_g1(pix.cos_o, cos_ih, alpha, distribution)) / (4.0 * pix.cos_o)
    a, b, c, s = (x * value for x in _fresnel_reflection_abcs(cos_ih, eta))
    # s axis of the microfacet plane of incidence: h x (-wi) = wi x h (= h x wo: pplastic's
    # s_axis_in and s_axis_out coincide). For wi == wo any axis perpendicular to wi gives the
    # same matrix, the reflection being diag(R, R, -R, -R) there.
    sax = _fr.cross(wi, h)
    bad = _fr.dot(sax, sax) <= 1e-24
    if np.any(bad):
        sax[bad] = _fr.stokes_basis(-wi[bad])
    ci, si = _fr.rotation_cos_sin_2theta(-wi, sax, x_in)
    co, so = _fr.rotation_cos_sin_2theta(wo, sax, x_out)
    cib, sib = ci * b, si * b
    e = {(0, 0): a, (0, 1): cib, (0, 2): -sib, (1, 0): co * b, (2, 0): -so * b}
    ca, sa, cc, sc = ci * a, si * a, ci * c, si * c
    e[1, 1] = co * ca + so * sc
    e[1, 2] = so * cc - co * sa
    e[2, 1] = co * sc - so * ca
    e[2, 2] = co * cc + so * sa
    if nmat == 4:
        e[1, 3] = -so * s
        e[2, 3] = -co * s
        e[3, 1] = si * s
        e[3, 2] = ci * s
        e[3, 3] = c
    return e


def _diffuse_elements(pix: _Pixels, eta, x_in, x_out) -> dict:
    """Elements of ``Md`` (``kd = 1``): the rank-one ``cos_i / pi (R_out t_out)(R_in t_in)^T``
    with ``t = (a, b, 0, 0)`` the first row/column of the Fresnel transmission matrices."""
    wi, wo, n = pix.wi, pix.wo, pix.n
    a_i, b_i = _transmission_ab(pix.cos_i, eta)
    a_o, b_o = _transmission_ab(pix.cos_o, eta)
    s_in = _fr.cross(n, -wi)
    s_out = _fr.cross(n, wo)
    # Normal incidence/exitance: b = 0 there and the axis does not matter.
    bad = _fr.dot(s_in, s_in) <= 1e-24
    if np.any(bad):
        s_in[bad] = _fr.stokes_basis(-wi[bad])
    bad = _fr.dot(s_out, s_out) <= 1e-24
    if np.any(bad):
        s_out[bad] = _fr.stokes_basis(wo[bad])
    ci, si = _fr.rotation_cos_sin_2theta(-wi, s_in, x_in)
    co, so = _fr.rotation_cos_sin_2theta(wo, s_out, x_out)
    scale = pix.cos_i / np.pi
    u = (a_o, co * b_o, -so * b_o)
    v = (scale * a_i, scale * ci * b_i, -scale * si * b_i)
    return {(r, k): u[r] * v[k] for r in range(3) for k in range(3)}


def _terms(pix, alpha, eta, distribution, components, x_in, x_out, nmat):
    want_s, want_d = _components(components)
    es = _specular_elements(pix, alpha, eta, distribution, x_in, x_out, nmat) if want_s else None
    ed = _diffuse_elements(pix, eta, x_in, x_out) if want_d else None
    return es, ed


def _assemble(pix: _Pixels, es, ed, ks, kd, nmat: int, ncolour: int | None) -> np.ndarray:
    """``ks Ms + kd Md`` into a zero-initialised ``batch + ([C,]) + (nmat, nmat)`` array."""
    cshape = () if ncolour is None else (ncolour,)
    out = np.zeros(pix.batch + cshape + (nmat, nmat))
    if pix.flat is not None and pix.flat.size == 0:
        return out
    npix = pix.npix
    sub = out.reshape((-1,) + cshape + (nmat, nmat)) if pix.flat is None else np.zeros((npix,) + cshape + (nmat, nmat))
    ks_v = pix.scalar(ks)
    if ncolour is None:
        kd_v = pix.scalar(kd)
        ks_c = ks_v
    else:
        kd = np.asarray(kd, dtype=np.float64)
        kd_v = np.broadcast_to(kd, pix.batch + cshape).reshape(-1, ncolour)
        kd_v = kd_v if pix.flat is None else kd_v[pix.flat]
        ks_c = ks_v[..., None] if ks_v.ndim else ks_v
    for r in range(nmat):
        for k in range(nmat):
            val = None
            if es is not None and (r, k) in es:
                x = es[r, k] if ncolour is None else es[r, k][:, None]
                val = ks_c * x
            if ed is not None and (r, k) in ed:
                x = ed[r, k] if ncolour is None else ed[r, k][:, None]
                val = kd_v * x if val is None else val + kd_v * x
            if val is not None:
                sub[..., r, k] = val
    if pix.flat is not None:
        out.reshape((-1,) + cshape + (nmat, nmat))[pix.flat] = sub
    return out


def _colour_rule(kd, batch_shapes) -> tuple[tuple, int | None, np.ndarray]:
    """Pixel shape of ``kd``, its colour count (``None`` if no colour axis) and where it is
    finite (all colours)."""
    kd = np.asarray(kd, dtype=np.float64)
    nd = len(np.broadcast_shapes(*batch_shapes))
    if kd.ndim > nd + 1:
        raise ValueError(f"kd has shape {kd.shape}: expected the pixel shape or the pixel shape + (C,)")
    if kd.ndim == nd + 1 and kd.ndim > 0:
        return kd.shape[:-1], kd.shape[-1], np.isfinite(kd).all(axis=-1)
    return kd.shape, None, np.isfinite(kd)


def _evaluate(normal, wi, wo, *, kd, alpha, eta, ks, distribution, components, nmat,
              refs=None) -> np.ndarray:
    distribution = _check_distribution(distribution)
    _components(components)
    shapes = [np.shape(v)[:-1] for v in (normal, wi, wo)] + [np.shape(alpha), np.shape(eta)]
    if refs is not None:
        shapes += [np.shape(r)[:-1] for r in refs]
    kd_shape, ncolour, kd_ok = _colour_rule(kd, shapes)
    ks = np.asarray(ks, dtype=np.float64)
    extra_ok = kd_ok & np.isfinite(ks)
    pix, alpha_v, eta_v = _gather(normal, wi, wo, alpha, eta,
                                  extra_shapes=[kd_shape, ks.shape] + shapes[5:], extra_ok=extra_ok)
    x_in, x_out = _bases(pix, refs)
    es, ed = _terms(pix, alpha_v, eta_v, distribution, components, x_in, x_out, nmat)
    return _assemble(pix, es, ed, ks, kd, nmat, ncolour)


def _bases(pix: _Pixels, refs):
    """Incident and outgoing basis ``x`` at the valid pixels: Mitsuba's defaults when
    ``refs`` is None, else the rig frames from ``(stage_zero_axis, camera_x_axis)``."""
    if refs is None:
        return _fr.stokes_basis(-pix.wi), _fr.stokes_basis(pix.wo)
    stage, cam = (pix.vectors(r) for r in refs)
    return _fr.basis_from_reference(-pix.wi, stage), _fr.basis_from_reference(pix.wo, cam)


def _check_refs(stage_zero_axis, camera_x_axis):
    return (_fr._as_vectors(stage_zero_axis, "stage_zero_axis"),
            _fr._as_vectors(camera_x_axis, "camera_x_axis"))


# ----------------------------------------------------------------------------- public API

def mueller(normal, wi, wo, *, kd, alpha, eta=1.5, ks=1.0, distribution: str = "ggx",
            components: Sequence[str] = COMPONENTS) -> np.ndarray:
    """pBRDF Mueller matrices times ``cos(theta_i)`` (1/sr), ``(..., 4, 4)`` or
    ``(..., C, 4, 4)``.

    Parameters (all broadcast over the pixel axes ``...``):
    ``normal``, ``wi`` (towards the light), ``wo`` (towards the camera): ``(..., 3)`` world
    vectors (normalised here). ``kd``: diffuse albedo, scalar or ``(...)``, or with a trailing
    colour axis ``(..., C)`` (exactly one more axis than the pixel shape; use ``kd[None, :]``
    for one colour everywhere with 1-D pixel arrays), giving ``(..., C, 4, 4)``. ``alpha``:
    GGX/Beckmann roughness (>= 0, clamped to :data:`ALPHA_MIN`). ``eta``: relative refractive
    index (real, > 0). ``ks``: specular scale (pplastic's ``specular_reflectance``), scalar or
    ``(...)``. ``distribution``: ``"ggx"`` or ``"beckmann"``. ``components``: the terms to
    evaluate (others are not computed).

    Bases: incident ``x = stokes_basis(-wi)``, outgoing ``x = stokes_basis(wo)`` (module
    docstring). Invalid pixels (:func:`visible` false, non-finite parameters) are zero.
    """
    return _evaluate(normal, wi, wo, kd=kd, alpha=alpha, eta=eta, ks=ks, distribution=distribution,
                     components=components, nmat=4)


def to_rig_frames(m, wi, wo, *, stage_zero_axis, camera_x_axis) -> np.ndarray:
    """Re-express matrices ``m`` ``(..., [C,] n, n)`` (``n`` = 3 or 4) returned by
    :func:`mueller` (bases ``stokes_basis(-wi)``, ``stokes_basis(wo)``) in the rig's incident
    frame (:func:`polrig.frames.incident_frame` with ``stage_zero_axis``) and emergent frame
    (:func:`polrig.frames.emergent_frame` with ``camera_x_axis``)."""
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] not in (3, 4):
        raise ValueError(f"m must be (..., 3, 3) or (..., 4, 4), got shape {m.shape}")
    stage, cam = _check_refs(stage_zero_axis, camera_x_axis)
    i = _fr.normalize(wi)
    o = _fr.normalize(wo)
    ci, si = _fr.rotation_cos_sin_2theta(-i, _fr.stokes_basis(-i), _fr.basis_from_reference(-i, stage))
    co, so = _fr.rotation_cos_sin_2theta(o, _fr.stokes_basis(o), _fr.basis_from_reference(o, cam))
    vec_nd = max(ci.ndim, co.ndim)
    extra = m.ndim - 2 - vec_nd
    if extra not in (0, 1):
        raise ValueError(f"m of shape {m.shape} does not match directions of pixel shape {ci.shape}")
    if extra == 1:  # colour axis between pixels and matrix
        ci, si, co, so = (a[..., None] for a in (ci, si, co, so))
    return _fr.rotate_rows(_fr.rotate_cols(m, ci, si), co, so)


def linear_rig_mueller(normal, wi, wo, *, kd, alpha, eta=1.5, ks=1.0, distribution: str = "ggx",
                       components: Sequence[str] = COMPONENTS, stage_zero_axis,
                       camera_x_axis) -> np.ndarray:
    """Linear 3x3 block ``(..., [C,] 3, 3)`` of :func:`mueller` in the rig's frames.

    ``S_out = M @ S_in`` with ``S_in`` in the incident frame (``k = -wi``, ``x`` =
    ``stage_zero_axis`` made perpendicular) and ``S_out`` in the emergent frame (``k = wo``,
    ``x`` = ``camera_x_axis`` made perpendicular), ``docs/conventions.md``; both axes are
    ``(3,)`` or per pixel ``(..., 3)``. Other parameters as :func:`mueller`. The simulator's
    truth and the networks' analytic initialisation both use this. Units 1/sr.
    """
    refs = _check_refs(stage_zero_axis, camera_x_axis)
    return _evaluate(normal, wi, wo, kd=kd, alpha=alpha, eta=eta, ks=ks, distribution=distribution,
                     components=components, nmat=3, refs=refs)


def specular_diffuse_blocks(normal, wi, wo, *, alpha, eta=1.5, distribution: str = "ggx",
                            stage_zero_axis, camera_x_axis) -> tuple[np.ndarray, np.ndarray]:
    """Unit specular and diffuse linear blocks ``(Ms, Md)``, each ``(..., 3, 3)``, in the rig's
    frames, so that ``linear_rig_mueller(..., kd=kd, ks=ks) == ks * Ms + kd * Md``
    (``Md`` is the diffuse block for unit albedo ``kd = 1``, ``Ms`` for ``ks = 1``).
    Invalid pixels are zero in both."""
    distribution = _check_distribution(distribution)
    refs = _check_refs(stage_zero_axis, camera_x_axis)
    shapes = [r.shape[:-1] for r in refs]
    pix, alpha_v, eta_v = _gather(normal, wi, wo, alpha, eta, extra_shapes=shapes)
    x_in, x_out = _bases(pix, refs)
    es, ed = _terms(pix, alpha_v, eta_v, distribution, COMPONENTS, x_in, x_out, 3)
    return (_assemble(pix, es, None, 1.0, 0.0, 3, None), _assemble(pix, None, ed, 0.0, 1.0, 3, None))
