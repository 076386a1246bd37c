"""polrig.optics.pbrdf agrees with Mitsuba 3's ``pplastic`` (Baek et al. 2018) in the same Stokes bases.

Mitsuba (test dependency, variant ``scalar_spectral_polarized``) evaluates ``bsdf.eval`` in the
shading frame with ``si.wi`` towards the camera and ``wo`` towards the light (radiance mode);
the returned Mueller matrix follows the *actual light propagation*: from
``stokes_basis(-wo_light)`` to ``stokes_basis(wi_camera)`` (pplastic.cpp comment "light arrives
along -wo_hat and leaves along +wi_hat"); ``si.to_world_mueller(M, -wo, si.wi)`` moves it to
world bases, which is what ``polrig.optics.pbrdf.mueller`` returns. Mitsuba computes in float32, so
configurations are kept at ``cos theta >= 0.05`` where float32 is well conditioned (closer to
grazing, its internal-angle refraction loses digits; polrig evaluates in float64).
"""

from __future__ import annotations

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")
mi.set_variant("scalar_spectral_polarized")

from _sampling import random_unit as _random_unit  # noqa: E402

from polrig.optics import bases as frames  # noqa: E402
from polrig.optics import pbrdf

REL_TOL = 1e-4


def _mi_vec(v):
    return mi.Vector3f(*[float(x) for x in v])


def _np(m):
    a = np.array(m, dtype=np.float64)
    if a.ndim == 3:  # spectral: (4, 4, wavelengths) -- spectrally flat, take the first
        assert np.allclose(a, a[..., :1], rtol=1e-6, atol=1e-12)
        a = a[..., 0]
    return a


def _mitsuba_world(bsdf, normal, wi, wo, component=None):
    """pplastic's Mueller matrix for world directions, in Mitsuba's world Stokes bases."""
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(_mi_vec(normal))
    si.wi = si.to_local(_mi_vec(wo))  # Mitsuba's wi: towards the camera
    si.wavelengths = [550.0] * 4
    ctx = mi.BSDFContext()
    if component is not None:
        ctx.component = component
    wo_local = si.to_local(_mi_vec(wi))  # Mitsuba's wo: towards the light
    m_local = bsdf.eval(ctx, si, wo_local)
    return _np(si.to_world_mueller(m_local, -wo_local, si.wi))


def _pplastic(kd, ks, alpha, eta, distribution):
    return mi.load_dict({
        "type": "pplastic",
        "diffuse_reflectance": {"type": "spectrum", "value": float(kd)},
        "specular_reflectance": {"type": "spectrum", "value": float(ks)},
        "alpha": float(alpha), "distribution": distribution,
        "int_ior": float(eta), "ext_ior": 1.0,
    })


@pytest.mark.parametrize("distribution", ["ggx", "beckmann"])
def test_agrees_with_pplastic_on_random_configurations(distribution):
    rng = np.random.default_rng(20181204 if distribution == "ggx" else 7)
    worst = {"specular": 0.0, "diffuse": 0.0, "total": 0.0}
    for _ in range(150):
        normal = _random_unit(rng)
        wi, wo = _random_unit(rng, normal), _random_unit(rng, normal)
        kd, ks = rng.uniform(0, 1), rng.uniform(0.1, 1)
        alpha, eta = rng.uniform(0.02, 1.0), rng.uniform(1.1, 2.5)
        bsdf = _pplastic(kd, ks, alpha, eta, distribution)
        for comp, idx in (("specular", 0), ("diffuse", 1), ("total", None)):
            ref = _mitsuba_world(bsdf, normal, wi, wo, idx)
            comps = pbrdf.COMPONENTS if comp == "total" else (comp,)
            mine = pbrdf.mueller(normal, wi, wo, kd=kd, ks=ks, alpha=alpha, eta=eta,
                                 distribution=distribution, components=comps)
            scale = np.abs(mine).max()
            if scale == 0:  # e.g. kd = 0 for diffuse: Mitsuba must agree
                assert np.abs(ref).max() == 0
                continue
            worst[comp] = max(worst[comp], np.abs(ref - mine).max() / scale)
    print(f"pplastic {distribution}: worst |M_mitsuba - M_polrig|_max / |M|_max = {worst}")
    assert max(worst.values()) < REL_TOL, worst


def test_importance_mode_gives_the_same_physical_matrix():
    """Mitsuba's adjoint (importance) mode swaps the roles of si.wi and wo, but the Mueller
    matrix still maps light travelling towards the surface to light leaving it."""
    rng = np.random.default_rng(11)
    normal = np.array([0.0, 0.0, 1.0])
    wi, wo = _random_unit(rng, normal), _random_unit(rng, normal)
    bsdf = _pplastic(0.4, 1.0, 0.3, 1.5, "ggx")
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(_mi_vec(normal))
    si.wi = _mi_vec(wi)  # importance: si.wi is the light side
    si.wavelengths = [550.0] * 4
    m = _np(bsdf.eval(mi.BSDFContext(mi.TransportMode.Importance), si, _mi_vec(wo)))
    mine = pbrdf.mueller(normal, wi, wo, kd=0.4, alpha=0.3)
    # Importance mode scales by cos(theta) of Mitsuba's wo (the camera side here).
    mine_imp = mine / wi[2] * wo[2]
    np.testing.assert_allclose(m, mine_imp, atol=REL_TOL * np.abs(mine_imp).max())


def test_stokes_basis_and_rotations_match_mitsuba():
    rng = np.random.default_rng(5)
    for _ in range(200):
        k = rng.normal(size=3)
        k /= np.linalg.norm(k)
        np.testing.assert_allclose(frames.stokes_basis(k), np.array(mi.mueller.stokes_basis(_mi_vec(k))), atol=2e-6)
        a, b = frames.frame(k, rng.normal(size=3)).x, frames.frame(k, rng.normal(size=3)).x
        k2 = rng.normal(size=3)
        k2 /= np.linalg.norm(k2)
        c, d = frames.frame(k2, rng.normal(size=3)).x, frames.frame(k2, rng.normal(size=3)).x
        m = rng.normal(size=(4, 4))
        ref = np.array(mi.mueller.rotate_mueller_basis(mi.Matrix4f(m.tolist()), _mi_vec(k), _mi_vec(a), _mi_vec(b),
                                                       _mi_vec(k2), _mi_vec(c), _mi_vec(d)))
        mine = frames.rotate_mueller_basis(m, k, a, b, k2, c, d)
        np.testing.assert_allclose(mine, ref, atol=5e-5 * np.abs(m).max())


@pytest.mark.parametrize("eta", [1.5, 1.0 / 1.5, 1.33, 2.4])
def test_fresnel_reflection_matches_mitsuba_including_tir(eta):
    for cos_i in np.linspace(0.0, 1.0, 41):
        ref = _np(mi.mueller.specular_reflection(float(cos_i), float(eta)))
        mine = pbrdf.fresnel_reflection_sp(cos_i, eta)
        np.testing.assert_allclose(mine, ref, atol=2e-6)
