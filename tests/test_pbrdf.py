"""polrig.optics.pbrdf against closed forms, reciprocity, energy bounds, frame invariance and
realizability (the Mitsuba comparison is in test_pbrdf_mitsuba.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polrig.optics import bases as frames
from polrig.optics import mueller as mu
from polrig.optics import pbrdf, realizability

Z = np.array([0.0, 0.0, 1.0])
Q = np.diag([1.0, 1.0, -1.0, 1.0])


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_config(rng, n, min_cos=1e-3):
    """Random normals and directions above their horizon (cos >= min_cos)."""
    normal = _unit(rng.normal(size=(n, 3)))

    def above():
        v = _unit(rng.normal(size=(n, 3)))
        c = frames.dot(v, normal)
        v = np.where((c < 0)[:, None], -v, v)
        c = np.abs(c)
        lift = np.maximum(min_cos - c, 0.0)  # push near-horizon samples up
        return _unit(v + (lift * 2)[:, None] * normal)

    return normal, above(), above()


def _dolp_unpolarized(m):
    return np.hypot(m[..., 1, 0], m[..., 2, 0]) / m[..., 0, 0]


def _in_plane(theta, phi=0.0):
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


# ----------------------------------------------------------------------------- closed forms

@pytest.mark.parametrize("alpha", [1e-3, 0.05, 0.4])
@pytest.mark.parametrize("distribution", pbrdf.DISTRIBUTIONS)
def test_brewster_specular_is_fully_s_polarized(alpha, distribution):
    eta = 1.5
    tb = np.arctan(eta)
    wi, wo = _in_plane(tb, 0.0), _in_plane(tb, np.pi)
    m = pbrdf.mueller(Z, wi, wo, kd=0.0, alpha=alpha, eta=eta, distribution=distribution,
                      components=("specular",))
    np.testing.assert_allclose(_dolp_unpolarized(m), 1.0, atol=1e-12)
    # Upper 2x2 in the s/p bases is Rs/2 = 0.0739645 (Mitsuba test_mueller.py) times D G / (4 cos_o)
    value = (pbrdf.microfacet_d(1.0, alpha, distribution)
             * pbrdf.smith_g1(np.cos(tb), np.cos(tb), alpha, distribution) ** 2 / (4 * np.cos(tb)))
    s_axis = np.array([0.0, 1.0, 0.0])  # perpendicular to the plane of incidence (x-z)
    m_s = pbrdf.linear_rig_mueller(Z, wi, wo, kd=0.0, alpha=alpha, eta=eta, distribution=distribution,
                                   stage_zero_axis=s_axis, camera_x_axis=s_axis)
    np.testing.assert_allclose(m_s[:2, :2] / value, np.full((2, 2), 0.0739645), rtol=2e-6)
    np.testing.assert_allclose(m_s[2] / value, 0.0, atol=1e-14)
    np.testing.assert_allclose(m_s[:, 2] / value, 0.0, atol=1e-14)


@pytest.mark.parametrize("eta", [1.33, 1.5, 2.0])
def test_normal_incidence_closed_forms(eta):
    r = ((eta - 1) / (eta + 1)) ** 2
    alpha, kd = 0.2, 0.7
    x = np.array([1.0, 0.0, 0.0])
    ms, md = pbrdf.specular_diffuse_blocks(Z, Z, Z, alpha=alpha, eta=eta, stage_zero_axis=x, camera_x_axis=x)
    value = pbrdf.microfacet_d(1.0, alpha) / 4.0  # G = 1 at normal incidence
    # Same physical x on both sides, k reversed: mirror reflection diag(R, R, -R).
    np.testing.assert_allclose(ms, value * np.diag([r, r, -r]), atol=1e-15)
    np.testing.assert_allclose(md, np.diag([(1 - r) ** 2 / np.pi, 0, 0]), atol=1e-15)
    full = pbrdf.mueller(Z, Z, Z, kd=kd, alpha=alpha, eta=eta)
    np.testing.assert_allclose(full[0, 0], value * r + kd * (1 - r) ** 2 / np.pi, rtol=1e-14)
    np.testing.assert_allclose(full[3, 3], -value * r, rtol=1e-14)


def _atkinson_diffuse_dolp(eta, theta):
    """Atkinson & Hancock, "Recovery of surface orientation from diffuse polarization", IEEE
    TIP 15(6), 1653-1664, 2006: DoLP of diffuse reflection at emission angle theta."""
    s2 = np.sin(theta) ** 2
    num = (eta - 1 / eta) ** 2 * s2
    den = 2 + 2 * eta**2 - (eta + 1 / eta) ** 2 * s2 + 4 * np.cos(theta) * np.sqrt(eta**2 - s2)
    return num / den


@pytest.mark.parametrize("eta", [1.3, 1.5, 1.8])
def test_diffuse_dolp_matches_atkinson_hancock(eta):
    rng = np.random.default_rng(1)
    th_o = np.linspace(0.0, np.radians(89.5), 60)
    wo = np.stack([np.sin(th_o), np.zeros_like(th_o), np.cos(th_o)], axis=-1)
    wi = _unit(rng.normal(size=(60, 3)) * [1, 1, 0] + [0, 0, 0.5])  # any lit direction
    m = pbrdf.mueller(Z, wi, wo, kd=0.8, alpha=0.3, eta=eta, components=("diffuse",))
    np.testing.assert_allclose(_dolp_unpolarized(m), _atkinson_diffuse_dolp(eta, th_o), rtol=1e-10, atol=1e-15)
    # Orientation: diffuse light is polarized in the plane of emission (p), i.e. S1 < 0 in the
    # basis whose x is the s axis n x wo (90 deg from specular's s polarization).
    s_out = np.cross(Z, wo[1:])
    lin = pbrdf.linear_rig_mueller(Z, wi[1:], wo[1:], kd=0.8, alpha=0.3, eta=eta, components=("diffuse",),
                                   stage_zero_axis=[1.0, 0, 0], camera_x_axis=s_out)
    assert np.all(lin[:, 1, 0] < 0)
    np.testing.assert_allclose(lin[:, 2, 0], 0.0, atol=1e-15)


def test_specular_polarization_is_s_in_the_microfacet_plane():
    rng = np.random.default_rng(2)
    normal, wi, wo = _random_config(rng, 500)
    h = _unit(wi + wo)
    s = np.cross(wi, h)
    m = pbrdf.linear_rig_mueller(normal, wi, wo, kd=0.0, alpha=0.3, components=("specular",),
                                 stage_zero_axis=s, camera_x_axis=s)
    ok = pbrdf.visible(normal, wi, wo) & (np.linalg.norm(s, axis=-1) > 1e-3)
    assert np.all(m[ok, 1, 0] >= 0)  # Rs >= Rp: reflected light is s-polarized
    np.testing.assert_allclose(m[ok, 2, 0], 0.0, atol=1e-13 * np.abs(m[ok]).max())


# ----------------------------------------------------------------------------- reciprocity

@pytest.mark.parametrize("distribution", pbrdf.DISTRIBUTIONS)
def test_reciprocity(distribution):
    """BRDF reciprocity for Mueller matrices (Hovenier 1969; van de Hulst 1957, 5.32): reversing
    the path with each physical x axis kept gives Q M^T Q, Q = diag(1, 1, -1, 1); the minus
    sign because y = k x x flips with k. M carries cos(theta_i), so divide it out."""
    rng = np.random.default_rng(3)
    normal, wi, wo = _random_config(rng, 2000)
    kw = dict(kd=0.6, alpha=rng.uniform(0.02, 1.0, 2000), eta=rng.uniform(1.1, 2.5, 2000),
              distribution=distribution)
    fwd = pbrdf.mueller(normal, wi, wo, **kw)  # bases stokes_basis(-wi) -> stokes_basis(wo)
    rev = pbrdf.mueller(normal, wo, wi, **kw)  # bases stokes_basis(-wo) -> stokes_basis(wi)
    # reversed path: incident x = forward's outgoing x, outgoing x = forward's incident x
    rev = frames.rotate_mueller_basis(rev, -wo, frames.stokes_basis(-wo), frames.stokes_basis(wo),
                                      wi, frames.stokes_basis(wi), frames.stokes_basis(-wi))
    cos_i = frames.dot(normal, wi)[:, None, None]
    cos_o = frames.dot(normal, wo)[:, None, None]
    lhs = rev / cos_o
    rhs = Q @ np.swapaxes(fwd, -1, -2) @ Q / cos_i
    scale = np.abs(lhs).max(axis=(-1, -2), keepdims=True)
    np.testing.assert_allclose(lhs / scale, rhs / scale, atol=1e-12)
    # and the relation is not trivially satisfied: without Q it fails
    assert np.abs(lhs - np.swapaxes(fwd, -1, -2) / cos_i).max() > 1e-3 * scale.max()


# ----------------------------------------------------------------------------- energy

def _sample_half_vectors(rng, n, alpha, distribution):
    """Microfacet normals with pdf D(h) cos(theta_h) (Walter et al. 2007, eqs. 28, 35)."""
    u1, u2 = rng.random(n), rng.random(n)
    tan2 = alpha**2 * u1 / (1 - u1) if distribution == "ggx" else -alpha**2 * np.log1p(-u1)
    cos_t = 1 / np.sqrt(1 + tan2)
    sin_t = np.sqrt(np.maximum(1 - cos_t**2, 0))
    phi = 2 * np.pi * u2
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=-1)


@pytest.mark.parametrize("distribution", pbrdf.DISTRIBUTIONS)
def test_hemispherical_reflectance_at_most_one(distribution):
    """Monte Carlo (fixed seed): rho(wo) = int m00(wi, wo) dw_i (the albedo, by reciprocity)
    stays <= 1 for kd = ks = 1 over roughness, index and view angle. Diffuse term: cosine-
    weighted light directions; specular term: light directions reflected about microfacet
    normals drawn from D(h) cos(theta_h) (pdf D cos_h / (4 |wo.h|))."""
    rng = np.random.default_rng(4)
    n = 100_000
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    wi_cos = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u1, 0))], axis=-1)
    pdf_cos = wi_cos[:, 2] / np.pi
    results = []
    for alpha in (0.05, 0.3, 1.0):
        h = _sample_half_vectors(rng, n, alpha, distribution)
        pdf_h = pbrdf.microfacet_d(h[:, 2], alpha, distribution) * h[:, 2]
        for eta in (1.2, 1.5, 2.5):
            for th_o in np.radians([0.0, 45.0, 80.0]):
                wo = _in_plane(th_o, 0.3)
                kw = dict(kd=1.0, alpha=alpha, eta=eta, distribution=distribution)
                wd = pbrdf.mueller(Z, wi_cos, wo, components=("diffuse",), **kw)[:, 0, 0] / pdf_cos
                woh = h @ wo
                wi_s = 2 * woh[:, None] * h - wo
                ms = pbrdf.mueller(Z, wi_s, wo, components=("specular",), **kw)[:, 0, 0]
                ws = np.where(ms > 0, ms / np.where(pdf_h > 0, pdf_h, 1) * 4 * np.abs(woh), 0.0)
                est = wd.mean() + ws.mean()
                se = np.hypot(wd.std(), ws.std()) / np.sqrt(n)
                results.append((round(alpha, 3), eta, round(float(np.degrees(th_o))), round(float(est), 4),
                                round(float(se), 5)))
                assert est + 3 * se <= 1.0, results[-1]
                assert est > 0.3  # not vacuous
    print("hemispherical reflectance (alpha, eta, theta_o deg, estimate, s.e.):", results)
    # diffuse alone has a closed form: T(theta_o) int T(theta_i) cos/pi dw_i, T = 1 - R
    wo = _in_plane(0.7)
    md = pbrdf.mueller(Z, wi_cos, wo, kd=1.0, alpha=0.3, eta=1.5, components=("diffuse",))[:, 0, 0]
    rs, rp = mu.fresnel_reflectance(np.cos(0.7), 1.5)
    mu_t = np.linspace(0, 1, 20001)[1:]
    rs_i, rp_i = mu.fresnel_reflectance(mu_t, 1.5)
    hemi_t = np.trapezoid(2 * mu_t * (1 - 0.5 * (rs_i + rp_i)), mu_t)
    np.testing.assert_allclose((md / pdf_cos).mean(), (1 - 0.5 * (rs + rp)) * hemi_t, rtol=2e-3)


# ----------------------------------------------------------------------------- rig frames

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (4, 3), elements=finite), arrays(np.float64, (4, 3), elements=finite),
       st.integers(0, 2**31 - 1), st.floats(0, np.pi))
def test_rig_frames_give_consistent_physical_outputs(ref_a, ref_b, seed, pol_angle):
    """The same physical scene seen through two choices of stage zero axis / camera X axis gives
    the same physical output polarization for the same physical input polarization."""
    rng = np.random.default_rng(seed)
    normal, wi, wo = _random_config(rng, 64, min_cos=0.02)
    kd = rng.uniform(0, 1, size=(64, 3))
    alpha = rng.uniform(0.02, 1.0, size=64)
    sa, ca, sb, cb = ref_a[0], ref_a[1], ref_b[0], ref_b[1]
    la = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, alpha=alpha, stage_zero_axis=sa, camera_x_axis=ca)
    lb = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, alpha=alpha, stage_zero_axis=sb, camera_x_axis=cb)
    assert np.all(np.isfinite(la)) and np.all(np.isfinite(lb))
    fa_in, fb_in = frames.incident_frame(wi, sa), frames.incident_frame(wi, sb)
    fa_out, fb_out = frames.emergent_frame(wo, ca), frames.emergent_frame(wo, cb)
    # physical field direction of the incident linear polarization, expressed in both frames
    e = np.cos(pol_angle) * fa_in.x + np.sin(pol_angle) * fa_in.y
    psi_b = np.arctan2(frames.dot(e, fb_in.y), frames.dot(e, fb_in.x))
    s_in_a = mu.polarizer_stokes(np.full(64, pol_angle))
    s_in_b = mu.polarizer_stokes(psi_b)
    out_a = np.einsum("pcij,pj->pci", la, s_in_a)
    out_b = np.einsum("pcij,pj->pci", lb, s_in_b)
    r = frames.rotate_stokes_basis(fa_out.k, fa_out.x, fb_out.x)[:, None, :3, :3]
    scale = np.abs(out_a).max() + 1e-300
    np.testing.assert_allclose(np.einsum("pcij,pcj->pci", r, out_a) / scale, out_b / scale, atol=1e-12)
    # intensity and DoLP do not depend on the frames at all
    np.testing.assert_allclose(out_a[..., 0], out_b[..., 0], rtol=1e-12, atol=1e-300)


def test_to_rig_frames_matches_direct_evaluation_and_blocks_combine():
    rng = np.random.default_rng(6)
    normal, wi, wo = _random_config(rng, 3000)
    kd = rng.uniform(0, 1, size=(3000, 3))
    ks = rng.uniform(0, 1, size=3000)
    alpha = rng.uniform(0.02, 1.0, size=3000)
    stage = _unit(rng.normal(size=(3000, 3)))
    cam = np.array([1.0, 0.0, 0.0])
    m4 = pbrdf.mueller(normal, wi, wo, kd=kd, ks=ks, alpha=alpha)
    assert m4.shape == (3000, 3, 4, 4)
    via = pbrdf.to_rig_frames(m4, wi, wo, stage_zero_axis=stage, camera_x_axis=cam)
    direct = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, ks=ks, alpha=alpha, stage_zero_axis=stage,
                                      camera_x_axis=cam)
    assert direct.shape == (3000, 3, 3, 3)
    np.testing.assert_allclose(via[..., :3, :3], direct, atol=1e-13 * np.abs(direct).max())
    ms, md = pbrdf.specular_diffuse_blocks(normal, wi, wo, alpha=alpha, stage_zero_axis=stage, camera_x_axis=cam)
    combo = ks[:, None, None, None] * ms[:, None] + kd[..., None, None] * md[:, None]
    np.testing.assert_allclose(combo, direct, atol=1e-15)
    # every colour plane equals the scalar-kd evaluation
    for c in range(3):
        single = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd[:, c], ks=ks, alpha=alpha,
                                          stage_zero_axis=stage, camera_x_axis=cam)
        np.testing.assert_allclose(direct[:, c], single, atol=1e-16)
    # the 3x3 block of a rotated 4x4 equals rotating the 3x3 block (no m3x leakage into 0..2)
    np.testing.assert_allclose(pbrdf.to_rig_frames(m4[..., :3, :3], wi, wo, stage_zero_axis=stage, camera_x_axis=cam),
                               direct, atol=1e-13 * np.abs(direct).max())


def test_components_are_additive_and_selective():
    rng = np.random.default_rng(7)
    normal, wi, wo = _random_config(rng, 500)
    kw = dict(kd=0.5, alpha=0.2, eta=1.6)
    both = pbrdf.mueller(normal, wi, wo, **kw)
    spec = pbrdf.mueller(normal, wi, wo, components=("specular",), **kw)
    diff = pbrdf.mueller(normal, wi, wo, components="diffuse", **kw)
    np.testing.assert_allclose(both, spec + diff, atol=1e-16)
    assert np.all(diff[..., 3, :] == 0) and np.all(diff[..., :, 3] == 0)  # rank-one, linear only
    assert np.abs(spec[..., 3, 3]).max() > 0
    assert np.all(pbrdf.mueller(normal, wi, wo, components=(), **kw) == 0)


# ----------------------------------------------------------------------------- robustness

def test_below_horizon_degenerate_and_nonfinite_inputs_give_zero():
    wi = np.array([[0.3, 0, 0.9], [0.3, 0, -0.1], [0.3, 0, 0.9], [0, 0, 0], [np.nan, 0, 1], [0.3, 0, 0.9],
                   [0.3, 0, 0.9], [0.3, 0, 0.9], [0.0, 0.0, 1.0]])
    wo = np.array([[-0.2, 0.1, 0.9], [-0.2, 0.1, 0.9], [-0.2, 0.1, -0.9], [-0.2, 0.1, 0.9], [-0.2, 0.1, 0.9],
                   [np.inf, 0, 1], [-0.2, 0.1, 0.9], [-0.2, 0.1, 0.9], [1.0, 0.0, 0.0]])
    alpha = np.array([0.2, 0.2, 0.2, 0.2, 0.2, 0.2, np.nan, 0.2, 0.2])
    kd = np.array([[0.5, 0.5, 0.5]] * 7 + [[np.nan, 0.5, 0.5]] + [[0.5, 0.5, 0.5]])
    with np.errstate(divide="raise", invalid="raise", over="raise"):  # nothing may warn on the way
        m = pbrdf.mueller(Z, wi, wo, kd=kd, alpha=alpha)
        lin = pbrdf.linear_rig_mueller(Z, wi, wo, kd=kd, alpha=alpha, stage_zero_axis=[0, 0, 1.0],
                                       camera_x_axis=[1.0, 0, 0])
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(lin))
    assert np.abs(m[0]).max() > 0 and np.abs(lin[0]).max() > 0
    assert np.all(m[1:] == 0) and np.all(lin[1:] == 0)
    np.testing.assert_array_equal(pbrdf.visible(Z, wi, wo), [True, False, False, False, False, False, True, True, False])


def test_grazing_and_extreme_parameters_stay_finite():
    rng = np.random.default_rng(8)
    normal, wi, wo = _random_config(rng, 4000, min_cos=1e-9)
    for alpha in (0.0, 1e-6, 1e-4, 5.0):
        for eta in (1.0001, 1.0, 0.6, 10.0):
            for dist in pbrdf.DISTRIBUTIONS:
                m = pbrdf.mueller(normal, wi, wo, kd=1.0, alpha=alpha, eta=eta, distribution=dist)
                assert np.all(np.isfinite(m))
                assert np.all(m[..., 0, 0] >= 0)
    # retro-reflection wi == wo at oblique angles (degenerate microfacet plane)
    w = _unit([[0.5, 0.2, 0.8]])
    m = pbrdf.mueller(Z, w, w, kd=0.3, alpha=0.3)
    assert np.all(np.isfinite(m)) and m[0, 0, 0] > 0


def test_bad_arguments_raise_one_line_errors():
    with pytest.raises(ValueError, match="distribution"):
        pbrdf.mueller(Z, Z, Z, kd=0.5, alpha=0.2, distribution="phong")
    with pytest.raises(ValueError, match="components"):
        pbrdf.mueller(Z, Z, Z, kd=0.5, alpha=0.2, components=("sheen",))
    with pytest.raises(ValueError, match="alpha"):
        pbrdf.mueller(Z, Z, Z, kd=0.5, alpha=-0.1)
    with pytest.raises(ValueError, match="eta"):
        pbrdf.mueller(Z, Z, Z, kd=0.5, alpha=0.1, eta=0.0)
    with pytest.raises(ValueError, match="kd"):
        pbrdf.mueller(np.tile(Z, (5, 1)), Z, Z, kd=np.ones((5, 3, 2)), alpha=0.1)
    with pytest.raises(ValueError, match="albedo"):  # a negative albedo makes m00 < 0
        pbrdf.mueller(Z, Z, Z, kd=-1.0, alpha=0.1)
    with pytest.raises(ValueError, match="albedo"):
        pbrdf.mueller(Z, Z, Z, kd=[[0.5, -0.1, 0.2]], alpha=0.1, ks=1.0)
    with pytest.raises(ValueError, match="albedo"):
        pbrdf.mueller(Z, Z, Z, kd=0.5, alpha=0.1, ks=-0.5)
    with pytest.raises(ValueError, match="length 3"):
        pbrdf.mueller(np.zeros((5, 2)), Z, Z, kd=0.5, alpha=0.1)
    with pytest.raises(ValueError, match="stage_zero_axis"):
        pbrdf.linear_rig_mueller(Z, Z, Z, kd=0.5, alpha=0.1, stage_zero_axis=[1.0, 0], camera_x_axis=[1.0, 0, 0])


def test_image_shaped_inputs_and_colour_axis():
    rng = np.random.default_rng(9)
    h, w = 6, 5
    normal, wi, wo = (a.reshape(h, w, 3) for a in _random_config(rng, h * w))
    kd = rng.uniform(size=(h, w, 3))
    out = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, alpha=0.3, stage_zero_axis=[0, 1.0, 0],
                                   camera_x_axis=[1.0, 0, 0])
    assert out.shape == (h, w, 3, 3, 3)
    mono = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd[..., 1], alpha=0.3, stage_zero_axis=[0, 1.0, 0],
                                    camera_x_axis=[1.0, 0, 0])
    assert mono.shape == (h, w, 3, 3)
    np.testing.assert_allclose(out[..., 1, :, :], mono, atol=1e-16)
    # a single colour for all pixels: one extra axis
    one = pbrdf.mueller(normal, wi, wo, kd=np.array([[[0.2, 0.5, 0.9]]]), alpha=0.3)
    assert one.shape == (h, w, 3, 4, 4)


# ----------------------------------------------------------------------------- realizability

def test_pbrdf_matrices_are_physically_realizable():
    """Each term is a (sum of) physical Mueller matrices: the specular one is Mueller-Jones
    (Fresnel reflection and rotations), the diffuse one a transmission-depolarizer-transmission
    cascade. The full 4x4 matrices must pass the Cloude coherency test everywhere; the rig's
    3x3 blocks pass with the 'max_min_eigenvalue' completion (the true m33 is admissible).
    The zero-padded completion (m33 = 0) is reported, not required (Gil et al. 2025)."""
    rng = np.random.default_rng(10)
    n = 4000
    normal, wi, wo = _random_config(rng, n)
    kd = rng.uniform(0, 1, size=(n, 3))
    ks = rng.uniform(0, 1, size=n)
    alpha = rng.uniform(0.01, 1.0, size=n)
    eta = rng.uniform(1.05, 2.5, size=n)
    m4 = pbrdf.mueller(normal, wi, wo, kd=kd, ks=ks, alpha=alpha, eta=eta)
    rate4 = realizability.pass_rate(realizability.is_physical_coherency(m4))
    lin = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, ks=ks, alpha=alpha, eta=eta,
                                   stage_zero_axis=_unit(rng.normal(size=(n, 3))), camera_x_axis=[1.0, 0, 0])
    rate3 = realizability.pass_rate(realizability.is_physical_linear(lin))
    rate3_zero = realizability.pass_rate(realizability.is_physical_linear(lin, completion="zero"))
    gk4 = realizability.pass_rate(realizability.is_physical_gk(m4))
    print(f"pBRDF realizability pass rates: coherency 4x4 {rate4:.4f}, GK 4x4 {gk4:.4f}, "
          f"3x3 max-min-eig completion {rate3:.4f}, 3x3 zero completion {rate3_zero:.4f}")
    assert rate4 == 1.0
    assert gk4 == 1.0
    assert rate3 == 1.0


wild = st.one_of(st.floats(-1e6, 1e6, allow_nan=False), st.just(0.0), st.just(np.nan), st.just(np.inf),
                 st.just(-np.inf), st.just(1e-300), st.just(1e300))


@settings(max_examples=150, deadline=None)
@given(arrays(np.float64, (6, 3), elements=wild), arrays(np.float64, (6, 3), elements=wild),
       arrays(np.float64, (6, 3), elements=wild),
       arrays(np.float64, (6,), elements=st.one_of(st.floats(0, 10), st.just(np.nan))),
       st.floats(0.05, 20), st.sampled_from(pbrdf.DISTRIBUTIONS))
def test_property_finite_and_diattenuation_polarizance_bounded(normal, wi, wo, alpha, eta, distribution):
    """Any input (NaN, inf, zero, huge, grazing) gives finite matrices, zero outside
    :func:`visible`, and m00 >= |(m01, m02, m03)|, m00 >= |(m10, m20, m30)| (diattenuation and
    polarizance at most 1, as for every physical Mueller matrix)."""
    with np.errstate(divide="raise", invalid="raise", over="raise", under="ignore"):
        m = pbrdf.mueller(normal, wi, wo, kd=0.7, alpha=alpha, eta=eta, distribution=distribution)
        lin = pbrdf.linear_rig_mueller(normal, wi, wo, kd=0.7, alpha=alpha, eta=eta, distribution=distribution,
                                       stage_zero_axis=[0.0, 1.0, 0.0], camera_x_axis=wi)
    assert np.all(np.isfinite(m)) and np.all(np.isfinite(lin))
    vis = pbrdf.visible(normal, wi, wo) & np.isfinite(alpha)
    assert np.all(m[~vis] == 0) and np.all(lin[~vis] == 0)
    tol = 1e-12 * np.abs(m).max(axis=(-1, -2))
    assert np.all(m[..., 0, 0] >= 0)
    assert np.all(np.linalg.norm(m[..., 0, 1:], axis=-1) <= m[..., 0, 0] + tol)
    assert np.all(np.linalg.norm(m[..., 1:, 0], axis=-1) <= m[..., 0, 0] + tol)
    np.testing.assert_allclose(lin[..., 0, 0], m[..., 0, 0], rtol=1e-12, atol=0)


def test_chunked_evaluation_matches_piecewise_evaluation():
    """More pixels than one internal chunk (pbrdf.CHUNK), valid and invalid interleaved: the
    result equals evaluating small slices separately (no chunk-boundary or gather errors)."""
    rng = np.random.default_rng(12)
    n = 2 * pbrdf.CHUNK + 1234
    normal, wi, wo = (_unit(rng.normal(size=(n, 3))) for _ in range(3))  # ~1/4 valid
    kd = rng.uniform(size=(n, 3))
    alpha = rng.uniform(0.02, 1.0, size=n)
    stage = _unit(rng.normal(size=(n, 3)))
    kw = dict(stage_zero_axis=stage, camera_x_axis=[1.0, 0, 0])
    whole = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, alpha=alpha, **kw)
    parts = [pbrdf.linear_rig_mueller(normal[s], wi[s], wo[s], kd=kd[s], alpha=alpha[s],
                                      stage_zero_axis=stage[s], camera_x_axis=[1.0, 0, 0])
             for s in (slice(a, a + 777) for a in range(0, n, 777))]
    np.testing.assert_array_equal(whole, np.concatenate(parts))
    vis = pbrdf.visible(normal, wi, wo)
    assert 0.1 < vis.mean() < 0.5
    assert np.all(whole[~vis] == 0) and np.all(np.abs(whole[vis]).max(axis=(-1, -2, -3)) > 0)
    # all-valid stacks take the slice path: same values as the indexed path
    v = np.flatnonzero(vis)
    np.testing.assert_array_equal(
        pbrdf.linear_rig_mueller(normal[v], wi[v], wo[v], kd=kd[v], alpha=alpha[v], stage_zero_axis=stage[v],
                                 camera_x_axis=[1.0, 0, 0]), whole[v])
