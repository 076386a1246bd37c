"""The simulator's materials beyond the Baek 2018 family (polrig.sim.surface_bsdf) agree with
Mitsuba 3 (test dependency, ``scalar_spectral_polarized``): ``roughconductor`` with a complex
index per colour (isotropic and anisotropic, GGX and Beckmann), ``conductor`` with Mitsuba's
named tabulated metals at the channel wavelengths (the oracle of :mod:`polrig.sim.optical_data`),
``pplastic`` per colour for dispersive dielectrics, and compositions with Mitsuba's
``mueller`` retarder and depolarizer matrices for the thin film and depolarizing layer.

Mitsuba evaluates in float32, so configurations keep ``cos theta >= 0.05`` (as
tests/test_pbrdf_mitsuba.py) and agreement is required to 1e-4 relative to the largest
element.
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")
mi.set_variant("scalar_spectral_polarized")

from _sampling import random_unit as _random_unit  # noqa: E402

from polrig.optics import bases as frames  # noqa: E402
from polrig.sim import surface_bsdf as sb  # noqa: E402
from polrig.sim.materials import SurfaceMaterial  # noqa: E402
from polrig.sim.optical_data import (  # noqa: E402
    CONDUCTORS,
    MITSUBA_NAMES,
    WAVELENGTHS_NM,
    dielectric_rgb,
)

REL_TOL = 1e-4


def _v(v):
    return mi.Vector3f(*[float(x) for x in v])


def _mitsuba_world(bsdf, normal, tangent, wi, wo, wavelengths=(550.0,) * 4):
    """Mitsuba's Mueller matrix for world directions (wi towards the light, wo towards the
    camera) in Mitsuba's world Stokes bases; ``(4, 4, 4)`` (row, col, wavelength)."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    t = tangent - (tangent @ normal) * normal
    t /= np.linalg.norm(t)
    si.sh_frame = mi.Frame3f(_v(t), _v(np.cross(normal, t)), _v(normal))
    si.wi = si.to_local(_v(wo))
    si.wavelengths = list(wavelengths)
    wo_local = si.to_local(_v(wi))
    m = bsdf.eval(mi.BSDFContext(), si, wo_local)
    return np.array(si.to_world_mueller(m, -wo_local, si.wi), dtype=np.float64)


def _mine(material, normal, tangent, wi, wo):
    prm = material.parameters(np.zeros((1, 3)))
    return sb.evaluate(normal[None], tangent, wi[None], wo[None], prm,
                       distribution=material.distribution)[0]  # (3, 4, 4)


def _roughconductor(eta, alpha_u, alpha_v, distribution):
    return mi.load_dict({
        "type": "roughconductor", "distribution": distribution,
        "alpha_u": float(alpha_u), "alpha_v": float(alpha_v),
        "eta": {"type": "spectrum", "value": float(eta.real)},
        "k": {"type": "spectrum", "value": float(eta.imag)},
    })


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
@pytest.mark.parametrize("anisotropic", [False, True])
def test_rough_conductor_with_complex_eta_per_colour_agrees_with_roughconductor(distribution, anisotropic):
    rng = np.random.default_rng(23 + 2 * anisotropic + (distribution == "ggx"))
    worst = 0.0
    names = list(CONDUCTORS)
    for trial in range(40):
        normal = _random_unit(rng)
        tangent = rng.normal(size=3)
        wi, wo = _random_unit(rng, normal), _random_unit(rng, normal)
        au = float(rng.uniform(0.03, 0.8))
        av = float(rng.uniform(0.03, 0.8)) if anisotropic else au
        eta = CONDUCTORS[names[trial % len(names)]]
        mat = SurfaceMaterial("m", eta, au, av, distribution=distribution, tangent_axis=(0, 0, 1))
        mine = _mine(mat, normal, tangent, wi, wo)
        scale = np.abs(mine).max()
        if scale < 1e-6:
            continue
        for c in range(3):
            ref = _mitsuba_world(_roughconductor(eta[c], au, av, distribution), normal, tangent, wi, wo)[..., 0]
            worst = max(worst, np.abs(ref - mine[c]).max() / scale)
    print(f"roughconductor {distribution} anisotropic={anisotropic}: worst rel. error {worst:.2e}")
    assert worst < REL_TOL


def test_retardance_of_a_conductor_appears_in_m22_m23_m32():
    """A conductor reflects with an s-p phase difference: in the s/p bases the lower block is
    ``sqrt(Rs Rp) [[cos d, -sin d], [sin d, cos d]]`` with ``sin d != 0``, unlike a dielectric
    (checked in Mitsuba's own bases against roughconductor above; here its size at 45 deg)."""
    from polrig.optics import mueller as mu

    m = mu.specular_reflection(np.cos(np.radians(60.0)), CONDUCTORS["gold"][1])
    ref = np.array(mi.mueller.specular_reflection(mi.Float(np.cos(np.radians(60.0))),
                                                  mi.Complex2f(*[float(x) for x in (CONDUCTORS["gold"][1].real,
                                                                                     CONDUCTORS["gold"][1].imag)])))
    np.testing.assert_allclose(m, ref.reshape(4, 4), atol=2e-6)
    assert abs(m[2, 3]) > 0.1 and m[2, 3] == pytest.approx(-m[3, 2])


@pytest.mark.parametrize("metal", list(CONDUCTORS))
def test_conductor_table_matches_mitsubas_tabulated_metal_at_the_channel_wavelengths(metal):
    """Smooth ``conductor`` with ``material = Au`` etc. reads the same data files: its
    normal-incidence reflection matrix at 630/532/465 nm must be the closed form of our table,
    ``R = ((n - 1)^2 + k^2) / ((n + 1)^2 + k^2)`` in ``diag(R, R, -R, -R)``."""
    bsdf = mi.load_dict({"type": "conductor", "material": MITSUBA_NAMES[metal]})
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(0, 0, 1)
    si.wavelengths = list(WAVELENGTHS_NM) + [WAVELENGTHS_NM[0]]
    _, w = bsdf.sample(mi.BSDFContext(), si, 0.5, mi.Point2f(0.5, 0.5))
    ref = np.array(w, dtype=np.float64)[..., :3]  # (4, 4, 3)
    for c, eta in enumerate(CONDUCTORS[metal]):
        n, k = eta.real, eta.imag
        r = ((n - 1) ** 2 + k ** 2) / ((n + 1) ** 2 + k ** 2)
        np.testing.assert_allclose(np.diag(ref[..., c]), [r, r, -r, -r], rtol=REL_TOL)


def _pplastic(kd, alpha, eta, distribution):
    return mi.load_dict({
        "type": "pplastic", "distribution": distribution, "alpha": float(alpha),
        "diffuse_reflectance": {"type": "spectrum", "value": float(kd)},
        "int_ior": float(eta), "ext_ior": 1.0,
    })


@pytest.mark.parametrize("glass", ["bk7", "pmma", "polycarbonate"])
def test_dispersive_dielectric_is_pplastic_per_colour(glass):
    rng = np.random.default_rng(hash(glass) % 1000)
    eta = dielectric_rgb(glass)
    kd = (0.6, 0.3, 0.1)
    worst = 0.0
    for _ in range(30):
        normal = _random_unit(rng)
        wi, wo = _random_unit(rng, normal), _random_unit(rng, normal)
        alpha = float(rng.uniform(0.05, 0.6))
        mat = SurfaceMaterial("g", eta, alpha, kd=kd)
        mine = _mine(mat, normal, np.array([0.0, 0.0, 1.0]), wi, wo)
        scale = np.abs(mine).max()
        for c in range(3):
            ref = _mitsuba_world(_pplastic(kd[c], alpha, eta[c], "ggx"), normal, np.array([1.0, 0, 0]), wi, wo)[..., 0]
            worst = max(worst, np.abs(ref - mine[c]).max() / scale)
    print(f"pplastic per colour, {glass}: worst rel. error {worst:.2e}")
    assert worst < REL_TOL


def _mi_matrix(m):
    return np.array(m, dtype=np.float64).reshape(4, 4)


def test_film_and_depolarizing_layer_compose_like_mitsubas_mueller_elements():
    """The layered material equals Mitsuba's base BSDF (roughconductor / pplastic) composed
    with Mitsuba's ``rotated_element(linear_retarder)`` and the partial depolarizer
    ``p I + (1 - p) depolarizer`` on each pass, the fast axis taken at its angle in Mitsuba's
    Stokes bases of each beam."""
    rng = np.random.default_rng(9)
    worst = 0.0
    for trial in range(30):
        normal = _random_unit(rng)
        tangent = rng.normal(size=3)
        wi, wo = _random_unit(rng, normal), _random_unit(rng, normal)
        alpha = float(rng.uniform(0.05, 0.6))
        delta0, axis_deg, p0 = rng.uniform(-3, 3), rng.uniform(0, 180), rng.uniform(0.2, 1.0)
        if trial % 2:
            eta, kd = CONDUCTORS["copper"], (0.0, 0.0, 0.0)
            base = [_roughconductor(e, alpha, alpha, "ggx") for e in eta]
        else:
            eta, kd = dielectric_rgb("pmma"), (0.5, 0.4, 0.3)
            base = [_pplastic(kd[c], alpha, eta[c], "ggx") for c in range(3)]
        mat = SurfaceMaterial("f", eta, alpha, kd=kd, retardance_rad=delta0, fast_axis_deg=axis_deg,
                              polarized_fraction=p0)
        mine = _mine(mat, normal, tangent, wi, wo)
        t = tangent - (tangent @ normal) * normal
        t /= np.linalg.norm(t)
        a = np.radians(axis_deg)
        f = np.cos(a) * t + np.sin(a) * np.cross(normal, t)
        cos_i, cos_o = wi @ normal, wo @ normal
        def depol(cos_theta):
            p = p0 ** (0.5 / cos_theta)
            return p * np.eye(4) + (1 - p) * _mi_matrix(mi.mueller.depolarizer(mi.Float(1.0)))

        def film(k, cos_theta, c):
            x = frames.stokes_basis(k)
            y = np.cross(k, x)
            phi = np.arctan2(f @ y, f @ x)
            delta = delta0 * 532.0 / WAVELENGTHS_NM[c] / np.sqrt(1 - (1 - cos_theta ** 2) / 1.5 ** 2)
            return _mi_matrix(mi.mueller.rotated_element(mi.Float(phi), mi.mueller.linear_retarder(mi.Float(delta))))

        for c in range(3):
            m_base = _mitsuba_world(base[c], normal, tangent, wi, wo)[..., 0]
            ref = film(wo, cos_o, c) @ depol(cos_o) @ m_base @ depol(cos_i) @ film(-wi, cos_i, c)
            worst = max(worst, np.abs(ref - mine[c]).max() / np.abs(mine).max())
    print(f"film + depolarizer over roughconductor/pplastic: worst rel. error {worst:.2e}")
    assert worst < REL_TOL
