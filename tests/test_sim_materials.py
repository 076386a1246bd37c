"""Materials beyond the Baek 2018 family against closed forms, identities and invariants:
complex-index Fresnel (polrig.optics.mueller), the retarder and partial depolarizer, the optical data
tables, polrig.sim.surface_bsdf and the rendered truth of the material scenes (realizable, equal to
the BSDF at the truth geometry). The Mitsuba 3 oracles are in tests/test_materials_mitsuba.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from polrig.optics import mueller as mu
from polrig.optics import pbrdf
from polrig.optics import realizability as rz
from polrig.sim import surface_bsdf as sb
from polrig.sim.materials import SurfaceMaterial, Texture
from polrig.sim.optical_data import (
    CONDUCTORS,
    SELLMEIER,
    WAVELENGTHS_NM,
    dielectric_rgb,
    sellmeier,
)
from polrig.sim.render import render
from polrig.sim.scene import MATERIAL_SCENES, make_scene

SETTINGS = settings(max_examples=60, deadline=None)
G = np.diag([1.0, -1.0, -1.0, -1.0])
n_st = st.floats(0.05, 5.0)
k_st = st.floats(0.0, 8.0)
cos_st = st.floats(0.0, 1.0)


# --------------------------------------------------------------------------- complex Fresnel
@SETTINGS
@given(n=n_st, k=k_st)
def test_normal_incidence_reflectance_of_a_conductor(n, k):
    r = ((n - 1) ** 2 + k ** 2) / ((n + 1) ** 2 + k ** 2)
    m = mu.specular_reflection(1.0, complex(n, k))
    np.testing.assert_allclose(np.diag(m), [r, r, -r, -r], rtol=1e-12, atol=1e-15)


@SETTINGS
@given(n=n_st, k=k_st, cos_i=cos_st)
@example(n=0.05, k=0.0, cos_i=0.5)  # total internal reflection: Rs = 1 + 4e-16 (found by CI)
def test_complex_fresnel_is_a_non_depolarizing_reflector_with_abeles_relation(n, k, cos_i):
    """``M^T G M = Rs Rp G`` (a Jones matrix ``diag(rs, rp)``), the matrix equals
    ``jones_to_mueller(diag(rs, rp))`` and the amplitudes obey Abeles' relation
    ``rp = rs (rs - cos 2t) / (1 - rs cos 2t)`` for any complex index (F. Abeles, 1950)."""
    eta = complex(n, k)
    if abs(eta - 1) < 1e-6:
        return
    m = mu.specular_reflection(cos_i, eta)
    rs_i, rp_i = mu.fresnel_reflectance(cos_i, eta)
    # reflectances in [0, 1] up to rounding (total internal reflection gives 1 + a few ulp)
    assert np.all(np.isfinite(m)) and 0 <= rp_i <= rs_i + 1e-12 and rs_i <= 1 + 1e-12
    np.testing.assert_allclose(m.T @ G @ m, rs_i * rp_i * G, atol=1e-12)
    rs, rp = mu._fresnel_amplitudes(cos_i, eta)
    np.testing.assert_allclose(mu.jones_to_mueller(np.diag([rs, rp])), m, atol=1e-12)
    c2 = 2 * cos_i ** 2 - 1
    np.testing.assert_allclose(rp * (1 - rs * c2), rs * (rs - c2), atol=1e-12)  # no 0/0 at grazing


@SETTINGS
@given(n=st.floats(1.01, 4.0), cos_i=cos_st)
def test_vanishing_extinction_reduces_to_the_dielectric(n, cos_i):
    for k in (1e-9, 0.0):
        np.testing.assert_allclose(mu.specular_reflection(cos_i, complex(n, k)),
                                   pbrdf.fresnel_reflection_sp(cos_i, n), atol=1e-7)


@pytest.mark.parametrize("metal", list(CONDUCTORS))
def test_conductor_grazing_incidence_and_pseudo_brewster_minimum(metal):
    """At grazing incidence every conductor reflects everything with no retardance
    (``M = diag(1, 1, 1, 1)`` in Mitsuba's signs); Rp has one interior minimum (the
    pseudo-Brewster angle) above 45 deg, and the s-p retardance goes from pi (normal incidence,
    m22 = -R) to 0 (grazing) through pi/2 (the principal angle, m22 = 0) once, beyond the
    pseudo-Brewster angle."""
    for eta in CONDUCTORS[metal]:
        np.testing.assert_allclose(mu.specular_reflection(0.0, eta), np.eye(4), atol=1e-12)
        theta = np.radians(np.linspace(0.0, 89.99, 20000))
        m = mu.specular_reflection(np.cos(theta), eta)
        rp = m[:, 0, 0] - m[:, 0, 1]
        i_min = int(np.argmin(rp))
        assert 0 < i_min < len(theta) - 1 and np.degrees(theta[i_min]) > 45
        assert np.all(np.diff(rp[:i_min]) < 0) and np.all(np.diff(rp[i_min:]) > 0)
        cos_delta = m[:, 2, 2] / np.sqrt((m[:, 0, 0] ** 2 - m[:, 0, 1] ** 2))
        crossings = np.nonzero(np.diff(np.sign(cos_delta)))[0]
        assert len(crossings) == 1 and crossings[0] >= i_min


@pytest.mark.parametrize("n", [1.3, 1.5, 2.4])
def test_pseudo_brewster_angle_tends_to_brewster_as_k_vanishes(n):
    theta = np.radians(np.linspace(30.0, 89.0, 59001))
    for k, tol in ((1e-4, 0.01), (0.05, 1.0)):
        rp = mu.fresnel_reflectance(np.cos(theta), complex(n, k))[1]
        assert np.degrees(theta[np.argmin(rp)]) == pytest.approx(np.degrees(np.arctan(n)), abs=tol)


# --------------------------------------------------------------------------- retarder, depolarizer
angles = st.floats(-2 * np.pi, 2 * np.pi)


@SETTINGS
@given(a=angles, d=angles, e=angles, aolp=angles)
def test_retarder_identities(a, d, e, aolp):
    r = mu.retarder_at(a, d)
    np.testing.assert_allclose(mu.retarder_at(a, 0.0), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(r @ mu.retarder_at(a, e), mu.retarder_at(a, d + e), atol=1e-12)
    np.testing.assert_allclose(r.T @ r, np.eye(4), atol=1e-12)  # orthogonal, m00 = 1
    assert rz.is_physical_coherency(r)
    # half-wave plate: mirrors the polarization angle about the fast axis
    s = np.array([1.0, np.cos(2 * aolp), np.sin(2 * aolp), 0.0])
    out = mu.retarder_at(a, np.pi) @ s
    np.testing.assert_allclose(out, [1, np.cos(2 * (2 * a - aolp)), np.sin(2 * (2 * a - aolp)), 0], atol=1e-12)
    # Jones: a plate turned by a with phase exp(i d) on its slow axis
    c, sn = np.cos(a), np.sin(a)
    rot = np.array([[c, -sn], [sn, c]])
    np.testing.assert_allclose(mu.jones_to_mueller(rot @ np.diag([1, np.exp(1j * d)]) @ rot.T), r, atol=1e-12)


@SETTINGS
@given(p=st.floats(0.0, 1.0))
def test_partial_depolarizer_is_realizable_between_identity_and_depolarizer(p):
    m = mu.partial_depolarizer(p)
    assert rz.is_physical_coherency(m) and rz.is_physical_gk(m)
    np.testing.assert_allclose(m, p * np.eye(4) + (1 - p) * mu.depolarizer(1.0), atol=1e-15)


# --------------------------------------------------------------------------- optical data
def test_sellmeier_glasses_match_their_catalogue_values():
    b, c = SELLMEIER["bk7"]
    nd, nf, nc = sellmeier([587.5618, 486.1327, 656.2725], b, c)
    assert nd == pytest.approx(1.5168, abs=1e-4)  # SCHOTT N-BK7
    assert (nd - 1) / (nf - nc) == pytest.approx(64.17, abs=0.05)
    assert sellmeier(589.3, *SELLMEIER["pmma"]) == pytest.approx(1.4905, abs=5e-4)
    assert sellmeier(589.3, *SELLMEIER["polycarbonate"]) == pytest.approx(1.585, abs=2e-3)
    for name in SELLMEIER:  # normal dispersion: blue is refracted most
        r, g, bl = dielectric_rgb(name)
        assert 1 < r < g < bl


def test_conductor_colours():
    """Gold and copper reflect red more than blue, silver and aluminium are near-white and
    bright, chrome is darker (normal-incidence reflectance per channel)."""
    def r0(name):
        return np.array([((e.real - 1) ** 2 + e.imag ** 2) / ((e.real + 1) ** 2 + e.imag ** 2)
                         for e in CONDUCTORS[name]])
    assert r0("gold")[0] > r0("gold")[2] + 0.3 and r0("copper")[0] > r0("copper")[2] + 0.3
    assert r0("silver").min() > 0.85 and r0("aluminium").min() > 0.85
    assert 0.5 < r0("chrome").max() < 0.7
    assert WAVELENGTHS_NM == (630.0, 532.0, 465.0)


def test_surface_materials_validate():
    gold = CONDUCTORS["gold"]
    for kw, msg in ((dict(eta_rgb=gold, alpha=0.1, kd=(0.1, 0, 0)), "no diffuse"),
                    (dict(eta_rgb=(1.5, 0.9, 1.5), alpha=0.1), "eta must be > 1"),
                    (dict(eta_rgb=(1.5 - 1j, 1.5, 1.5), alpha=0.1), "imaginary part"),
                    (dict(eta_rgb=(1.5, 1.5, 1.5), alpha=0.0), "alpha must be > 0"),
                    (dict(eta_rgb=(1.5, 1.5, 1.5), alpha=0.1, distribution="phong"), "distribution"),
                    (dict(eta_rgb=(1.5, 1.5, 1.5), alpha=0.1, polarized_fraction=1.2), "polarized_fraction"),
                    (dict(eta_rgb=(1.5, 1.5, 1.5), alpha=0.1, alpha_texture=Texture(-0.1, 1)), "textures"),
                    (dict(eta_rgb=(1.5, 1.5, 1.5), alpha=0.1, eta_texture=Texture(-0.6, 0)), "eta texture")):
        with pytest.raises(ValueError, match=msg):
            SurfaceMaterial("bad", **kw)
    with pytest.raises(ValueError, match="kind"):
        Texture(0, 1, kind="spots")


# --------------------------------------------------------------------------- polrig.sim.surface_bsdf
def _directions(rng, p, min_cos=1e-3):
    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)
    n = unit(rng.normal(size=(p, 3)))
    out = []
    for _ in range(2):
        w = unit(rng.normal(size=(p, 3)))
        w = w * np.sign(np.sum(w * n, axis=1))[:, None]
        w = unit(w + n * np.maximum(min_cos - np.sum(w * n, axis=1), 0)[:, None])
        out.append(w)
    return n, out[0], out[1]


def _params(mat, p):
    return mat.parameters(np.zeros((p, 3)))


@SETTINGS
@given(alpha=st.floats(1e-4, 1.5), eta=st.floats(1.01, 3.0), seed=st.integers(0, 2 ** 16),
       distribution=st.sampled_from(["ggx", "beckmann"]))
def test_reduces_to_the_baek_pbrdf_in_the_rig_frames(alpha, eta, seed, distribution):
    rng = np.random.default_rng(seed)
    n, wi, wo = _directions(rng, 64)
    kd = (0.3, 0.6, 0.9)
    mat = SurfaceMaterial("b", (eta,) * 3, alpha, kd=kd, distribution=distribution)
    refs = (np.array([1.0, 0.2, 0.0]), np.array([0.1, 0.0, 1.0]))
    mine = sb.evaluate(n, rng.normal(size=3), wi, wo, _params(mat, 64), distribution=distribution,
                       refs=refs)[..., :3, :3]
    ref = pbrdf.linear_rig_mueller(n, wi, wo, kd=np.tile(kd, (64, 1)), alpha=alpha, eta=eta,
                                   distribution=distribution, stage_zero_axis=refs[0], camera_x_axis=refs[1])
    np.testing.assert_allclose(mine, ref, atol=1e-12 * max(1.0, np.abs(ref).max()))


@SETTINGS
@given(au=st.floats(0.01, 1.0), av=st.floats(0.01, 1.0), seed=st.integers(0, 2 ** 16),
       distribution=st.sampled_from(["ggx", "beckmann"]))
def test_anisotropy_swaps_with_a_quarter_turn_of_the_tangent(au, av, seed, distribution):
    rng = np.random.default_rng(seed)
    n, wi, wo = _directions(rng, 32, 0.05)
    t = rng.normal(size=(32, 3))
    t = t - np.sum(t * n, axis=1)[:, None] * n
    b = np.cross(n, t)
    gold = CONDUCTORS["gold"]
    a = sb.evaluate(n, t, wi, wo, _params(SurfaceMaterial("a", gold, au, av, distribution=distribution), 32),
                    distribution=distribution)
    c = sb.evaluate(n, b, wi, wo, _params(SurfaceMaterial("c", gold, av, au, distribution=distribution), 32),
                    distribution=distribution)
    np.testing.assert_allclose(a, c, atol=1e-10 * max(1.0, np.abs(a).max()))
    iso = sb.evaluate(n, t, wi, wo, _params(SurfaceMaterial("i", gold, au, distribution=distribution), 32),
                      distribution=distribution)
    iso_b = sb.evaluate(n, b, wi, wo, _params(SurfaceMaterial("i", gold, au, distribution=distribution), 32),
                        distribution=distribution)
    np.testing.assert_allclose(iso, iso_b, atol=1e-10 * max(1.0, np.abs(iso).max()))


materials = st.builds(
    lambda metal, eta, alpha, av, kd, p0, d0, axis, conductor: SurfaceMaterial(
        "r", CONDUCTORS[metal] if conductor else eta, alpha, av, kd=(0, 0, 0) if conductor else kd,
        polarized_fraction=p0, retardance_rad=d0, fast_axis_deg=axis),
    metal=st.sampled_from(list(CONDUCTORS)), eta=st.tuples(*[st.floats(1.01, 2.5)] * 3),
    alpha=st.floats(1e-3, 1.0), av=st.none() | st.floats(1e-3, 1.0),
    kd=st.tuples(*[st.floats(0.0, 1.0)] * 3), p0=st.sampled_from([0.0, 0.3, 1.0]) | st.floats(0, 1),
    d0=st.sampled_from([0.0, np.pi, -np.pi / 2]) | st.floats(-7, 7), axis=st.floats(-180, 180),
    conductor=st.booleans())


@SETTINGS
@given(mat=materials, seed=st.integers(0, 2 ** 16), min_cos=st.sampled_from([1e-4, 0.05, 0.5]))
def test_every_material_is_realizable_and_layers_keep_the_unpolarized_response(mat, seed, min_cos):
    """The 4x4 matrices pass the coherency and Givens-Kostinski tests (grazing directions
    included); the film and the depolarizing layer leave ``m00`` (unpolarized in, intensity
    out) unchanged, the depolarizing layer scales the polarizance and the diattenuation by its
    out and in factors and the linear couplings by both, and a film of zero
    retardance or a layer with ``p0 = 1`` changes nothing."""
    rng = np.random.default_rng(seed)
    n, wi, wo = _directions(rng, 48, min_cos)
    t = rng.normal(size=3)
    m = sb.evaluate(n, t, wi, wo, _params(mat, 48), distribution=mat.distribution)
    scale = np.abs(m).max(axis=(-2, -1)) + 1e-300
    flat = (m / scale[..., None, None]).reshape(-1, 4, 4)
    assert rz.is_physical_coherency(flat, rtol=1e-9).all()
    assert rz.is_physical_gk(flat).all()
    import dataclasses
    base = dataclasses.replace(mat, polarized_fraction=1.0, retardance_rad=0.0)
    mb = sb.evaluate(n, t, wi, wo, _params(base, 48), distribution=mat.distribution)
    np.testing.assert_allclose(m[..., 0, 0], mb[..., 0, 0], rtol=1e-9, atol=1e-12 * np.abs(mb).max())
    no_film = dataclasses.replace(mat, retardance_rad=0.0)
    mf = sb.evaluate(n, t, wi, wo, _params(no_film, 48), distribution=mat.distribution)
    p_in = mat.polarized_fraction ** (0.5 / np.sum(n * wi, 1))
    p_out = mat.polarized_fraction ** (0.5 / np.sum(n * wo, 1))
    np.testing.assert_allclose(mu.polarizance(mf), p_out[:, None] * mu.polarizance(mb), atol=1e-9)
    np.testing.assert_allclose(mu.diattenuation(mf), p_in[:, None] * mu.diattenuation(mb), atol=1e-9)
    np.testing.assert_allclose(mf[..., 1:3, 1:3], (p_in * p_out)[:, None, None, None] * mb[..., 1:3, 1:3],
                               atol=1e-12 * np.abs(mb).max())
    if mat.polarized_fraction == 1.0:
        np.testing.assert_allclose(mf, mb, atol=0)


def test_half_wave_film_along_s_at_normal_view_is_an_s_p_swap():
    """A half-wave film over a smooth-ish conductor, looked at along the normal with the light
    along the normal: each pass is a half-wave plate; with its axis along the frame's x
    axis it flips the signs of S2 and S3 (diag(1, 1, -1, -1)), so two passes cancel on the
    base's linear block."""
    n = np.array([[0.0, 0.0, 1.0]])
    mat = SurfaceMaterial("h", CONDUCTORS["aluminium"], 0.2, retardance_rad=np.pi)
    base = SurfaceMaterial("h", CONDUCTORS["aluminium"], 0.2)
    # green channel: retardance exactly pi at normal incidence (no obliquity factor)
    refs = (np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    m = sb.evaluate(n, [1.0, 0.0, 0.0], n, n, _params(mat, 1), refs=refs)[0, 1]
    mb = sb.evaluate(n, [1.0, 0.0, 0.0], n, n, _params(base, 1), refs=refs)[0, 1]
    hwp = np.diag([1.0, 1.0, -1.0, -1.0])
    np.testing.assert_allclose(m, hwp @ mb @ hwp, atol=1e-12)
    np.testing.assert_allclose(m[:3, :3], mb[:3, :3], atol=1e-12)


# --------------------------------------------------------------------------- rendered truth
def _truth_4x4(scene, r):
    """Recompute the 4x4 truth of the lit pixels from the render's own geometry (float64)."""
    cam = scene.camera
    lit = r.lit & np.isin(r.material_index, [k for k, m in enumerate(scene.materials)
                                             if isinstance(m, SurfaceMaterial)])
    to_world = lambda v: v[:, lit].T @ cam.R  # noqa: E731  camera -> world rows
    n, wi, wo = to_world(r.normal), to_world(r.wi), to_world(r.wo)
    p = r.position_m[:, lit].T
    mat_idx = r.material_index[lit]
    out = np.zeros((lit.sum(), 3, 4, 4))
    k = 0
    for ob in scene.objects:
        rot, t = ob.world_pose(scene.turntable, r.turntable_deg)
        for mat in ob.materials:
            sel = mat_idx == k
            k += 1
            if not sel.any():
                continue
            assert isinstance(mat, SurfaceMaterial)
            prm = mat.parameters((p[sel] - t) @ rot)
            out[sel] = sb.evaluate(n[sel], rot @ np.asarray(mat.tangent_axis), wi[sel], wo[sel], prm,
                                   distribution=mat.distribution,
                                   refs=(scene.stage_zero_axis, cam.R[0]))
    return out


@pytest.mark.parametrize("name", MATERIAL_SCENES)
def test_material_scene_truth_is_the_bsdf_at_the_truth_geometry_and_realizable(name, record_property):
    scene = make_scene(name, 48, 48)
    r = render(scene, 33.0)
    surface_lit = np.isin(r.material_index[r.lit],
                          [k for k, m in enumerate(scene.materials) if isinstance(m, SurfaceMaterial)])
    assert r.counts["surface_evals"] == surface_lit.sum() > 50
    m4 = _truth_4x4(scene, r)
    got = np.moveaxis(r.brdf[..., r.lit], -1, 0)[surface_lit]
    np.testing.assert_allclose(got, m4[..., :3, :3], rtol=1e-3, atol=2e-6 * np.abs(m4).max())
    flat = m4.reshape(-1, 4, 4)
    flat = flat[np.abs(flat).max(axis=(1, 2)) > 0]
    flat = flat / np.abs(flat).max(axis=(1, 2))[:, None, None]
    rates = {"4x4 coherency": rz.pass_rate(rz.is_physical_coherency(flat)),
             "4x4 gk": rz.pass_rate(rz.is_physical_gk(flat)),
             # float32 truth of pure (boundary) matrices: the coherency test needs float32's rtol
             "3x3 coherency rtol 1e-6": rz.pass_rate(rz.is_physical_linear(got.reshape(-1, 3, 3), rtol=1e-6)),
             "3x3 gk": rz.pass_rate(rz.is_physical_linear(got.reshape(-1, 3, 3), test="gk"))}
    record_property("realizability", rates)
    assert min(rates.values()) == 1.0, rates


def test_textures_vary_the_truth_parameters_within_one_object():
    r = render(make_scene("textured_blob", 64, 64), 0.0)
    m = r.mask
    assert np.ptp(r.alpha[m]) > 0.1 and np.ptp(r.eta[m]) > 0.1 and np.ptp(r.kd[0][m]) > 0.1
    film = render(make_scene("film_plane", 48, 48), 0.0)
    assert film.counts["lit"] > 50


def test_dispersion_breaks_the_polarization_colour_decoupling():
    """With one index for all colours the diffuse polarization (normalised by m00) is the same
    in every channel; a dispersive plastic makes it differ."""
    r = render(make_scene("dispersive_sphere", 48, 48), 10.0)
    m = np.moveaxis(r.brdf[..., r.lit], -1, 0).astype(np.float64)  # (N, 3, 3, 3)
    pol = np.hypot(m[:, :, 1, 0], m[:, :, 2, 0]) / m[:, :, 0, 0]
    assert np.abs(pol[:, 2] - pol[:, 0]).max() > 1e-3


# --------------------------------------------------------------------------- dataset mixes
def test_cauchy_dielectric_has_the_requested_index_and_abbe_number():
    from polrig.sim.materials import _LINES_NM, cauchy_rgb
    for n_d, v in ((1.5168, 64.17), (1.585, 30.0), (1.7, 20.0)):
        r, g, b = cauchy_rgb(n_d, v)
        assert 1 < r < g < b
        # the two-term form through the three channels, evaluated at the d, F, C lines
        lam = np.array(_LINES_NM)
        a_b = np.polyfit(1 / np.array(WAVELENGTHS_NM) ** 2, [r, g, b], 1)
        nd, nf, nc = np.polyval(a_b, 1 / lam ** 2)
        assert nd == pytest.approx(n_d, abs=1e-9) and (nd - 1) / (nf - nc) == pytest.approx(v, rel=1e-9)
    bk7 = dielectric_rgb("bk7")
    np.testing.assert_allclose(cauchy_rgb(1.5168, 64.17), bk7, atol=2e-4)  # Cauchy ~ Sellmeier


@pytest.mark.parametrize("mix", ["train", "heldout", "conductor", "dispersive", "anisotropic", "film",
                                 "depolarizing"])
def test_material_mixes_keep_the_geometry_and_give_realizable_truth(mix):
    """A mix changes only the material: ``rng`` is consumed as in the default mix, so the
    scene's geometry, light and camera are those of the Baek sample; the truth is realizable."""
    from polrig.sim.materials import MATERIAL_MIXES
    from polrig.sim.scene import FAMILIES, random_scene
    kinds = set()
    for i in range(8):
        rng_base, rng = np.random.default_rng([5, i]), np.random.default_rng([5, i])
        base = random_scene(rng_base, 48, 48, i % len(FAMILIES))
        sc = random_scene(rng, 48, 48, i % len(FAMILIES), material_mix=mix,
                          material_rng=np.random.default_rng([5, i, 2]))
        assert rng.random() == rng_base.random()  # the sample's own stream is untouched
        np.testing.assert_array_equal(sc.light.position_m, base.light.position_m)
        assert [o.shape.to_json() for o in sc.objects] == [o.shape.to_json() for o in base.objects]
        mat = sc.objects[0].materials[0]
        kinds.add(type(mat).__name__)
        r = render(sc, 30.0)
        m = np.moveaxis(r.brdf[..., r.lit], -1, 0).reshape(-1, 3, 3).astype(np.float64)
        m = m[np.abs(m).max(axis=(1, 2)) > 0]
        if len(m):
            assert rz.pass_rate(rz.is_physical_linear(m, rtol=1e-6)) == 1.0
            assert rz.pass_rate(rz.is_physical_linear(m, test="gk")) == 1.0
    assert "SurfaceMaterial" in kinds
    if "baek" not in MATERIAL_MIXES[mix]:
        assert kinds == {"SurfaceMaterial"}
    with pytest.raises(ValueError, match="material_rng"):
        random_scene(np.random.default_rng(0), 48, 48, 0, material_mix=mix)


@pytest.mark.parametrize("kind", ["conductor_aniso", "dispersive", "film", "depolarizing"])
def test_reciprocity_of_the_new_materials(kind):
    """Reversing the path with each physical x axis kept gives ``Q M^T Q`` with
    ``Q = diag(1, 1, -1, 1)`` (Hovenier 1969, as tests/test_pbrdf.py for the Baek model), the
    cosines divided out: holds for complex indices, anisotropy, dispersion, the film (a
    reciprocal retarder seen from the other side) and the depolarizing layer."""
    from polrig.optics import bases as frames
    q = np.diag([1.0, 1.0, -1.0, 1.0])
    mats = {"conductor_aniso": SurfaceMaterial("c", CONDUCTORS["copper"], 0.1, 0.5, distribution="beckmann"),
            "dispersive": SurfaceMaterial("d", dielectric_rgb("polycarbonate"), 0.3, kd=(0.5, 0.3, 0.2)),
            "film": SurfaceMaterial("f", CONDUCTORS["gold"], 0.3, retardance_rad=1.3, fast_axis_deg=25.0),
            "depolarizing": SurfaceMaterial("p", (1.5, 1.5, 1.5), 0.3, kd=(0.4, 0.4, 0.4), polarized_fraction=0.5)}
    mat = mats[kind]
    rng = np.random.default_rng(31)
    n, wi, wo = _directions(rng, 500, 0.02)
    t = rng.normal(size=3)
    prm = _params(mat, 500)
    fwd = sb.evaluate(n, t, wi, wo, prm, distribution=mat.distribution)
    rev = sb.evaluate(n, t, wo, wi, prm, distribution=mat.distribution)
    sb_ = frames.stokes_basis
    rev = frames.rotate_mueller_basis(rev[:, :, None], -wo[:, None, None], sb_(-wo)[:, None, None], sb_(wo)[:, None, None],
                                      wi[:, None, None], sb_(wi)[:, None, None], sb_(-wi)[:, None, None])[:, :, 0]
    cos_i = np.sum(n * wi, 1)[:, None, None, None]
    cos_o = np.sum(n * wo, 1)[:, None, None, None]
    lhs = rev / cos_o
    rhs = q @ np.swapaxes(fwd, -1, -2) @ q / cos_i
    np.testing.assert_allclose(lhs, rhs, atol=1e-10 * np.abs(rhs).max())
