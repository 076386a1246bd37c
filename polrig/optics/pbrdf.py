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

* incident: propagation ``k = -wi``, ``x = polrig.optics.bases.stokes_basis(-wi)``;
* outgoing: propagation ``k = wo``, ``x = polrig.optics.bases.stokes_basis(wo)``;
* ``y = k x x`` (``docs/conventions.md``).

:func:`to_rig_frames`, :func:`linear_rig_mueller` and :func:`specular_diffuse_blocks` express
the same matrices in the rig's incident and emergent frames (:mod:`polrig.optics.bases`).
Units: dimensionless BRDF times ``cos(theta_i)``, i.e. 1/sr (``docs/conventions.md``).
Below-horizon ``wi`` or ``wo`` (``n . w <= 0``), and pixels with non-finite or zero-length
vectors or non-finite material parameters, give the zero matrix (see :func:`visible`).

Reciprocity (Stokes bases as above, reversing the path keeps each physical ``x`` axis): with
``Q = diag(1, 1, -1, 1)``, ``M(wo, wi) / cos(theta_o) = Q M(wi, wo)^T Q / cos(theta_i)``
when ``M(wo, wi)`` uses in basis ``x_out`` and out basis ``x_in`` of ``M(wi, wo)``.
Derivation: for a reciprocal interaction the Jones matrix of the reversed path is the
transpose in fixed Cartesian axes (Saxon, Phys. Rev. 100, 1771, 1955); keeping ``x`` while
``k`` reverses flips ``y = k x x``, so ``J' = P J^T P`` with ``P = diag(1, -1) = sigma_1``.
With ``m_ij = tr(sigma_i J sigma_j J^H) / 2``, conjugation by ``sigma_1`` flips the signs of
``sigma_2, sigma_3`` (``(1, 1, -1, -1)``) and transposition those of ``sigma_3^T = -sigma_3``
(``(1, 1, 1, -1)``): together ``Q``. Depolarizing sums of such matrices inherit it. This is the
Mueller reciprocity relation of J. W. Hovenier, J. Atmos. Sci. 26, 488 (1969) and H. C. van de
Hulst, *Light Scattering by Small Particles* (1957), sec. 5.32. ``M`` carries ``cos(theta_i)``,
hence the cosines. Tested in ``tests/test_pbrdf.py``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from polrig.optics import bases as _fr

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


def smith_g1_of_a2t2(a2t2: np.ndarray, distribution: str) -> np.ndarray:
    """Smith ``G1`` as a function of ``a^2 tan^2`` of the direction (the squared roughness
    projected on its azimuth for an anisotropic surface, Heitz 2014): GGX
    ``2 / (1 + sqrt(1 + a2t2))``, Beckmann Walter et al.'s rational approximation with
    ``b = 1 / sqrt(a2t2)`` (see :func:`smith_g1`). ``inf``/``nan`` where ``a2t2`` is 0 or
    undefined: the callers decide those cases."""
    a2t2 = np.asarray(a2t2, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if distribution == "ggx":
            return 2.0 / (1.0 + np.sqrt(1.0 + a2t2))
        b = 1.0 / np.sqrt(a2t2)
        return np.where(b >= 1.6, 1.0, (3.535 * b + 2.181 * b * b) / (1.0 + 2.276 * b + 2.577 * b * b))


def smith_g1(cos_v, cos_vh, alpha, distribution: str = "ggx") -> np.ndarray:
    """Smith masking ``G1(v, h)`` for a direction at ``cos_v = n . v`` and ``cos_vh = v . h``.

    GGX: ``2 / (1 + sqrt(1 + a^2 tan^2))`` (Walter et al. 2007, eq. 34); Beckmann: the
    rational approximation of Walter et al. (2007) eq. 27 with ``b = 1 / (a tan)``:
    ``(3.535 b + 2.181 b^2) / (1 + 2.276 b + 2.577 b^2)`` for ``b < 1.6``, else 1 (what
    Mitsuba 3 evaluates; within 0.35 % of the exact erf form). 1 at normal incidence; 0 when ``v``
    sees the back of the microfacet (``cos_vh cos_v <= 0``).
    """
    d = _check_distribution(distribution)
    cv = np.asarray(cos_v, dtype=np.float64)
    a2 = np.square(np.maximum(np.asarray(alpha, dtype=np.float64), ALPHA_MIN))
    s2 = np.maximum(1.0 - cv * cv, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = smith_g1_of_a2t2(a2 * s2 / (cv * cv), d)
    g = np.where(s2 == 0.0, 1.0, g)
    g = np.where(np.asarray(cos_vh) * cv <= 0.0, 0.0, g)
    return np.where(np.isfinite(g), g, 0.0)


# ----------------------------------------------------------------------------- Fresnel

def _fresnel_rs_rp(cos_i: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Real Fresnel amplitudes ``(r_s, r_p, tir)`` for a real ``eta`` (sign convention of
    :func:`polrig.optics.mueller.specular_reflection`, i.e. Mitsuba's); ``tir`` marks total internal
    reflection (only possible for ``eta < 1``), where the amplitudes are not real.

    Same cancellation-free form as :func:`polrig.optics.mueller._fresnel_amplitudes`
    (``eta cos_t = sqrt(eta^2 - 1 + cos_i^2)``, ``r_p`` multiplied through by ``eta``); an
    index-matched interface (``eta = 1``) reflects nothing, also at exactly grazing incidence."""
    ci = np.clip(cos_i, 0.0, 1.0)
    eta = np.asarray(eta, dtype=np.float64)
    ect2 = eta * eta - 1.0 + ci * ci  # (eta cos_t)^2
    tir = ect2 < 0.0
    ect = np.sqrt(np.maximum(ect2, 0.0))
    e2ci = eta * eta * ci
    den_s, den_p = ci + ect, e2ci + ect
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = np.where(den_s == 0, 0.0, (ci - ect) / den_s)
        rp = np.where(den_p == 0, 0.0, (e2ci - ect) / den_p)
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
    Equal to the general complex-amplitude :func:`polrig.optics.mueller.specular_reflection` (tested);
    this real-index form is the fast path evaluated per pixel."""
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
    (:func:`polrig.optics.mueller.specular_transmission`), real ``eta``; zero under TIR."""
    rs, rp, tir = _fresnel_rs_rp(cos_i, eta)
    ts = np.where(tir, 0.0, 1.0 - rs * rs)
    tp = np.where(tir, 0.0, 1.0 - rp * rp)
    return 0.5 * (ts + tp), 0.5 * (ts - tp)


# ----------------------------------------------------------------------------- inputs

def _geometry_ok(n: np.ndarray, i: np.ndarray, o: np.ndarray) -> np.ndarray:
    """Finite non-zero vectors (``|v|^2`` finite and positive) with ``wi`` and ``wo`` strictly
    above the horizon; uses the signs of unnormalised dot products."""
    good = True
    for v in (n, i, o):
        n2 = _fr.dot(v, v)
        good = good & np.isfinite(n2) & (n2 > 0)
    return good & (_fr.dot(n, i) > 0) & (_fr.dot(n, o) > 0)


def visible(normal, wi, wo) -> np.ndarray:
    """``True`` where the pBRDF is defined: finite non-zero vectors and both ``wi`` and ``wo``
    strictly above the tangent plane of ``normal`` (all ``(..., 3)``, world coordinates).
    Material parameters are not checked here (non-finite ones also give zero matrices)."""
    vecs = [_fr._as_vectors(v, name) for v, name in ((normal, "normal"), (wi, "wi"), (wo, "wo"))]
    return np.broadcast_to(_geometry_ok(*vecs), np.broadcast_shapes(*(v.shape[:-1] for v in vecs)))


def _components(components: Sequence[str]) -> tuple[bool, bool]:
    if isinstance(components, str):
        components = (components,)
    comps = tuple(str(c).lower() for c in components)
    bad = [c for c in comps if c not in COMPONENTS]
    if bad:
        raise ValueError(f"components must be drawn from {COMPONENTS}, got {bad}")
    return "specular" in comps, "diffuse" in comps


class _Pixels(NamedTuple):
    """One chunk of valid pixels, flat and component-major (``P`` pixels). Per-pixel material
    parameters are ``(P,)`` or scalars; reference axes ``(P, 3)``, ``(3,)`` or None."""

    n: np.ndarray        # (P, 3) unit normals
    wi: np.ndarray       # (P, 3) unit directions to the light
    wo: np.ndarray       # (P, 3) unit directions to the camera
    cos_i: np.ndarray    # (P,)
    cos_o: np.ndarray    # (P,)
    alpha: np.ndarray    # (P,) or scalar, clamped to ALPHA_MIN
    eta: np.ndarray      # (P,) or scalar
    refs: tuple | None   # (stage_zero_axis, camera_x_axis) or None for Mitsuba's default bases


#: Pixels per chunk: keeps every temporary (~64 kB) in cache and out of the page-fault path of
#: large allocations; the Python overhead per chunk is well under a millisecond.
CHUNK = 8192


def _flat(a, batch: tuple, trailing: int) -> np.ndarray:
    """``a`` with its pixel axes flattened to one, ``(N,) + trailing axes``; arrays without pixel
    axes (scalars, a single vector) are returned as they are."""
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == trailing:
        return a
    tail = a.shape[a.ndim - trailing:] if trailing else ()
    return np.broadcast_to(a, batch + tail).reshape((-1,) + tail)


def _take(a: np.ndarray, trailing: int, rows) -> np.ndarray:
    """Rows ``rows`` (a slice or flat indices) of a flattened per-pixel array; constants pass."""
    return a if a.ndim == trailing else a[rows]


class _Inputs(NamedTuple):
    """Validated inputs, pixel axes flattened (see :func:`_flat`)."""

    batch: tuple
    normal: np.ndarray
    wi: np.ndarray
    wo: np.ndarray
    alpha: np.ndarray
    eta: np.ndarray
    ks: np.ndarray
    kd: np.ndarray          # (N,), (N, C), scalar or (C,)
    ncolour: int | None
    refs: tuple | None


def _prepare(normal, wi, wo, *, alpha, eta, ks=1.0, kd=0.0, refs=None) -> _Inputs:
    """Check arguments (one-line ``ValueError``s) and flatten the pixel axes."""
    vecs = [_fr._as_vectors(v, name) for v, name in ((normal, "normal"), (wi, "wi"), (wo, "wo"))]
    alpha = np.asarray(alpha, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    ks = np.asarray(ks, dtype=np.float64)
    kd = np.asarray(kd, dtype=np.float64)
    if np.any(alpha < 0):
        raise ValueError("alpha (microfacet roughness) must be >= 0")
    if np.any(eta <= 0):
        raise ValueError("eta (relative refractive index) must be > 0")
    if np.any(ks < 0) or np.any(kd < 0):
        raise ValueError("ks and kd (specular and diffuse albedo) must be >= 0")
    shapes = [v.shape[:-1] for v in vecs] + [alpha.shape, eta.shape, ks.shape]
    if refs is not None:
        refs = (_fr._as_vectors(refs[0], "stage_zero_axis"), _fr._as_vectors(refs[1], "camera_x_axis"))
        shapes += [r.shape[:-1] for r in refs]
    try:
        nd = len(np.broadcast_shapes(*shapes))
        ncolour = kd.shape[-1] if kd.ndim == nd + 1 and kd.ndim > 0 else None
        if kd.ndim > nd + 1:
            raise ValueError(f"kd has shape {kd.shape}: expected the pixel shape or the pixel shape + (C,)")
        batch = np.broadcast_shapes(*shapes, kd.shape[:-1] if ncolour else kd.shape)
    except ValueError as exc:
        if str(exc).startswith("kd has shape"):
            raise
        raise ValueError(f"pixel shapes do not broadcast: {exc}") from None
    ct = 1 if ncolour else 0
    return _Inputs(batch, *(_flat(v, batch, 1) for v in vecs), _flat(alpha, batch, 0), _flat(eta, batch, 0),
                   _flat(ks, batch, 0), _flat(kd, batch, ct), ncolour,
                   None if refs is None else tuple(_flat(r, batch, 1) for r in refs))


def _valid_rows(inp: _Inputs, extra_ok: bool) -> np.ndarray | None:
    """Flat indices of the valid pixels (None when all are): finite non-zero vectors, ``wi`` and
    ``wo`` above the horizon (signs of unnormalised dot products), finite ``alpha``/``eta``
    and, when ``extra_ok``, finite ``ks``/``kd``. Computed in chunks (small temporaries)."""
    total = int(np.prod(inp.batch))
    ct = 1 if inp.ncolour else 0
    ok = np.empty(total, dtype=bool)
    for start in range(0, total, 4 * CHUNK):
        sl = slice(start, min(total, start + 4 * CHUNK))
        good = _geometry_ok(*(_take(v, 1, sl) for v in (inp.normal, inp.wi, inp.wo)))
        good = good & np.isfinite(_take(inp.alpha, 0, sl)) & np.isfinite(_take(inp.eta, 0, sl))
        if extra_ok:
            kd = _take(inp.kd, ct, sl)
            good = good & np.isfinite(_take(inp.ks, 0, sl)) & (np.isfinite(kd).all(axis=-1) if ct else np.isfinite(kd))
        ok[sl] = good
    return None if ok.all() else np.flatnonzero(ok)


def _chunks(inp: _Inputs, extra_ok: bool):
    """Yield ``(rows, pixels)`` for chunks of :data:`CHUNK` valid pixels: ``rows`` (a slice or
    flat indices into the flattened pixels) and the gathered, normalised :class:`_Pixels`."""
    flat = _valid_rows(inp, extra_ok)
    count = int(np.prod(inp.batch)) if flat is None else flat.size
    for start in range(0, count, CHUNK):
        stop = min(count, start + CHUNK)
        rows = slice(start, stop) if flat is None else flat[start:stop]
        m = stop - start
        # validated by _valid_rows: finite and non-zero
        n, i, o = (np.broadcast_to(_fr.unit_fast(_take(v, 1, rows)), (m, 3)) for v in (inp.normal, inp.wi, inp.wo))
        alpha, eta = _take(inp.alpha, 0, rows), _take(inp.eta, 0, rows)
        refs = None if inp.refs is None else tuple(_take(r, 1, rows) for r in inp.refs)
        yield rows, _Pixels(n, i, o, _fr.dot(n, i), _fr.dot(n, o), np.maximum(alpha, ALPHA_MIN), eta, refs)


# ----------------------------------------------------------------------------- unit terms
# Terms are dictionaries {(row, col): (P,) array} of their non-zero elements.

def _specular_elements(pix: _Pixels, distribution, frame_in, frame_out, nmat: int) -> dict:
    """Elements of ``Ms`` (``ks = 1``) in bases ``x_in`` (about ``-wi``), ``x_out`` (about
    ``wo``): ``R(theta_out) F R(theta_in)^T * D G / (4 cos_o)``, written out element-wise."""
    wi, wo, alpha, eta = pix.wi, pix.wo, pix.alpha, pix.eta
    h = _fr.unit_fast(wi + wo)  # wi + wo != 0: both above the horizon
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
        sax[bad] = _fr.stokes_basis_unit(-wi[bad])
    ci, si = _fr.rotation_cos_sin_2theta_to_frame(sax, *frame_in)
    co, so = _fr.rotation_cos_sin_2theta_to_frame(sax, *frame_out)
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


def _diffuse_elements(pix: _Pixels, frame_in, frame_out) -> dict:
    """Elements of ``Md`` (``kd = 1``): the rank-one ``cos_i / pi (R_out t_out)(R_in t_in)^T``
    with ``t = (a, b, 0, 0)`` the first row/column of the Fresnel transmission matrices."""
    wi, wo, n, eta = pix.wi, pix.wo, pix.n, pix.eta
    a_i, b_i = _transmission_ab(pix.cos_i, eta)
    a_o, b_o = _transmission_ab(pix.cos_o, eta)
    s_in = _fr.cross(n, -wi)
    s_out = _fr.cross(n, wo)
    # Normal incidence/exitance: b = 0 there and the axis does not matter.
    bad = _fr.dot(s_in, s_in) <= 1e-24
    if np.any(bad):
        s_in[bad] = _fr.stokes_basis_unit(-wi[bad])
    bad = _fr.dot(s_out, s_out) <= 1e-24
    if np.any(bad):
        s_out[bad] = _fr.stokes_basis_unit(wo[bad])
    ci, si = _fr.rotation_cos_sin_2theta_to_frame(s_in, *frame_in)
    co, so = _fr.rotation_cos_sin_2theta_to_frame(s_out, *frame_out)
    scale = pix.cos_i / np.pi
    u = (a_o, co * b_o, -so * b_o)
    v = (scale * a_i, scale * ci * b_i, -scale * si * b_i)
    return {(r, k): u[r] * v[k] for r in range(3) for k in range(3)}


def _bases(pix: _Pixels):
    """Incident and outgoing frames ``((x_in, y_in), (x_out, y_out))``: Mitsuba's default
    bases when ``pix.refs`` is None, else the rig frames from ``(stage_zero_axis,
    camera_x_axis)``; ``y = k x x`` with ``k = -wi`` and ``k = wo``."""
    k_in = -pix.wi
    if pix.refs is None:
        x_in, x_out = _fr.stokes_basis_unit(k_in), _fr.stokes_basis_unit(pix.wo)
    else:
        x_in = _fr.basis_from_reference_unit(k_in, pix.refs[0])
        x_out = _fr.basis_from_reference_unit(pix.wo, pix.refs[1])
    return (x_in, _fr.cross(k_in, x_in)), (x_out, _fr.cross(pix.wo, x_out))


def _new_planes(batch: tuple, ncolour: int | None, nmat: int) -> tuple[np.ndarray, np.ndarray]:
    """Zero output stored plane-first (memory order ``([C,] row, col, pixels)``, the image
    layout of ``docs/conventions.md``): returns ``(flat planes ([C,] n, n, N), matrix-last view
    batch + ([C,]) + (n, n))``; each element is written contiguously and ``np.moveaxis`` back
    to the image layout is free."""
    cshape = () if ncolour is None else (ncolour,)
    planes = np.zeros(cshape + (nmat, nmat) + batch)
    lead = len(cshape) + 2
    view = np.moveaxis(planes, tuple(range(lead)), tuple(range(-lead, 0)))
    return planes.reshape(cshape + (nmat, nmat, -1)), view


def _write(planes, cols, es, ed, ks, kd, nmat: int) -> None:
    """``planes[..., r, k, cols] = ks es[r, k] + kd ed[r, k]`` for one chunk of valid pixels;
    ``kd`` is scalar, ``(P,)`` or ``(C, P)``."""
    unit_ks = ks.ndim == 0 and ks == 1.0
    for r in range(nmat):
        for k in range(nmat):
            val = None
            if es is not None and (r, k) in es:
                val = es[r, k] if unit_ks else ks * es[r, k]
            if ed is not None and (r, k) in ed:
                val = kd * ed[r, k] if val is None else val + kd * ed[r, k]
            if val is not None:
                planes[..., r, k, cols] = val


def _evaluate(normal, wi, wo, *, kd, alpha, eta, ks, distribution, components, nmat, refs=None) -> np.ndarray:
    distribution = _check_distribution(distribution)
    want_s, want_d = _components(components)
    inp = _prepare(normal, wi, wo, alpha=alpha, eta=eta, ks=ks, kd=kd, refs=refs)
    planes, out = _new_planes(inp.batch, inp.ncolour, nmat)
    if not (want_s or want_d):
        return out
    ct = 1 if inp.ncolour else 0
    for rows, pix in _chunks(inp, extra_ok=True):
        frame_in, frame_out = _bases(pix)
        es = _specular_elements(pix, distribution, frame_in, frame_out, nmat) if want_s else None
        ed = _diffuse_elements(pix, frame_in, frame_out) if want_d else None
        kd_c = _take(inp.kd, ct, rows)
        if ct and kd_c.ndim == 2:
            kd_c = kd_c.T  # (C, P)
        elif ct:
            kd_c = kd_c[:, None]  # one colour for all pixels: (C, 1)
        _write(planes, rows, es, ed, _take(inp.ks, 0, rows), kd_c, nmat)
    return out


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
    frame (:func:`polrig.optics.bases.incident_frame` with ``stage_zero_axis``) and emergent frame
    (:func:`polrig.optics.bases.emergent_frame` with ``camera_x_axis``)."""
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-1] != m.shape[-2] or m.shape[-1] not in (3, 4):
        raise ValueError(f"m must be (..., 3, 3) or (..., 4, 4), got shape {m.shape}")
    stage = _fr._as_vectors(stage_zero_axis, "stage_zero_axis")
    cam = _fr._as_vectors(camera_x_axis, "camera_x_axis")
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
    return _evaluate(normal, wi, wo, kd=kd, alpha=alpha, eta=eta, ks=ks, distribution=distribution,
                     components=components, nmat=3, refs=(stage_zero_axis, camera_x_axis))


def specular_diffuse_blocks(normal, wi, wo, *, alpha, eta=1.5, distribution: str = "ggx",
                            stage_zero_axis, camera_x_axis) -> tuple[np.ndarray, np.ndarray]:
    """Unit specular and diffuse linear blocks ``(Ms, Md)``, each ``(..., 3, 3)``, in the rig's
    frames, so that ``linear_rig_mueller(..., kd=kd, ks=ks) == ks * Ms + kd * Md``
    (``Md`` is the diffuse block for unit albedo ``kd = 1``, ``Ms`` for ``ks = 1``).
    Invalid pixels are zero in both."""
    distribution = _check_distribution(distribution)
    inp = _prepare(normal, wi, wo, alpha=alpha, eta=eta, refs=(stage_zero_axis, camera_x_axis))
    (ms_planes, ms), (md_planes, md) = _new_planes(inp.batch, None, 3), _new_planes(inp.batch, None, 3)
    one = np.float64(1.0)
    for rows, pix in _chunks(inp, extra_ok=False):
        frame_in, frame_out = _bases(pix)
        _write(ms_planes, rows, _specular_elements(pix, distribution, frame_in, frame_out, 3), None, one, one, 3)
        _write(md_planes, rows, None, _diffuse_elements(pix, frame_in, frame_out), one, one, 3)
    return ms, md
