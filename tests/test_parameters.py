"""Parameter maps of the 3x3 linear block (polrig.optics.parameters) against oracles.

Oracles: py-pol (``py_pol``; its licence is unclear, so it is a test dependency only and none of
its code is copied) and usnistgov pySCATMECH (``pySCATMECH``), both on 4x4 matrices built from
polrig's closed-form elements (:mod:`polrig.optics.mueller`) and compared on what the 3x3 block
holds (the decomposition against pySCATMECH's Lu-Chipman decomposition: py-pol 1.3's
``decompose_polar`` does not reproduce its input for these matrices); closed forms of
polarizers, retarders, depolarizers and rotators; hypothesis properties at the extremes
(``m00`` near 0, ``D`` near 1, NaN planes); the linearised sigma against the spread of sampled
errors.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics import mueller as mu
from polrig.optics import parameters as pa
from polrig.optics.realizability import is_physical_coherency

SETTINGS = settings(max_examples=60, deadline=None)
TOL = 1e-6
N_ORACLE = 150


def _py_pol():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pytest.importorskip("py_pol.mueller")


def _scatmech():
    return pytest.importorskip("pySCATMECH.mueller")


# -- random physical matrices from closed forms --------------------------------------------------
def diattenuator(rng, d_max=0.95):
    t, d, ax = rng.uniform(0.1, 2.0), rng.uniform(0.0, d_max), rng.uniform(0, np.pi)
    return mu.rotated_element(ax, mu.diattenuator(t * (1 + d), t * (1 - d)))


def retarder(rng, rotation=True):
    m = mu.retarder_at(rng.uniform(0, np.pi), rng.uniform(0.05, np.pi - 0.05))
    return (mu.rotator(-rng.uniform(-0.7, 0.7)) @ m) if rotation else m


def depolarizer(rng):
    """A physical diagonal depolarizer ``diag(1, a, b, c)``, rotated (rejection sampling)."""
    while True:
        a, b, c = rng.uniform(-1, 1, 3)
        m = np.diag([1.0, a, b, c])
        if is_physical_coherency(m):
            return mu.rotated_element(rng.uniform(0, np.pi), m)


def random_physical(rng):
    """A product of 2 to 4 random diattenuators, retarders (with rotation) and depolarizers,
    in random order: a physical 4x4 Mueller matrix (a product of convex sums of
    Mueller-Jones matrices)."""
    makers = [diattenuator, retarder, depolarizer]
    m = np.eye(4)
    for _ in range(rng.integers(2, 5)):
        m = makers[rng.integers(3)](rng) @ m
    return m


def isotropic_model(rng, rotation: bool):
    """``M = M_Delta M_R M_D`` of the decomposition's model: an isotropic linear depolarizer
    with polarizance ``diag(1, a, a, c)``, a linear retarder (then a rotator), a linear
    diattenuator. Returns ``(M, truth)``."""
    while True:
        a, c = rng.uniform(0.05, 1.0), rng.uniform(0.05, 1.0)
        md = np.diag([1.0, a, a, c])
        md[1:3, 0] = rng.uniform(-0.2, 0.2, 2) * (1 - a)
        if is_physical_coherency(md):
            break
    ax, d = rng.uniform(0, np.pi), rng.uniform(0.05, np.pi - 0.05)
    rho = rng.uniform(-0.7, 0.7) if rotation else 0.0
    t, dd, dax = rng.uniform(0.1, 2.0), rng.uniform(0.0, 0.9), rng.uniform(0, np.pi)
    m = md @ mu.rotator(-rho) @ mu.retarder_at(ax, d) @ mu.rotated_element(
        dax, mu.diattenuator(t * (1 + dd), t * (1 - dd)))
    truth = {"retardance_deg": np.degrees(d), "retardance_axis_deg": np.degrees(ax) % 90,
             "depolarization": 1 - a, "rotation_deg": np.degrees(rho), "DL": dd,
             "DL_axis_deg": np.degrees(dax) % 180}
    return m, truth


def _angle_close(a, b, period, tol=TOL):
    d = np.mod(np.asarray(a) - np.asarray(b) + period / 2, period) - period / 2
    return np.all(np.abs(d) < tol)


# -- oracles ---------------------------------------------------------------------------------------
def test_element_conventions_match_py_pol_and_scatmech():
    """polrig's closed forms are py-pol's matrices (same frame and rotation conventions); the
    3x3 blocks of pySCATMECH's retarder and rotated elements agree once its opposite S3 sign
    and rotate() sign are accounted for (a retarder's linear block does not depend on them)."""
    Mueller, sm = _py_pol().Mueller, _scatmech()
    ax, d = 0.37, 1.1
    r = Mueller("r")
    r.retarder_linear(R=d, azimuth=ax)
    np.testing.assert_allclose(r.M[..., 0] if r.M.ndim == 3 else r.M, mu.retarder_at(ax, d),
                               atol=1e-12)
    dm = Mueller("d")
    dm.diattenuator_linear(p1=1.0, p2=0.5, azimuth=ax)
    np.testing.assert_allclose(dm.M[..., 0] if dm.M.ndim == 3 else dm.M,
                               mu.rotated_element(ax, mu.diattenuator(1.0, 0.25)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(sm.MuellerRetarder(d, ax))[:3, :3],
                               mu.retarder_at(ax, d)[:3, :3], atol=1e-12)
    np.testing.assert_allclose(np.asarray(sm.MuellerRotator(ax)), mu.rotator(ax), atol=1e-12)


@pytest.fixture(scope="module")
def physical_set():
    rng = np.random.default_rng(34)
    ms = np.stack([random_physical(rng) for _ in range(N_ORACLE)])
    assert is_physical_coherency(ms).all()
    return ms


def test_maps_of_random_physical_matrices_equal_py_pol(physical_set):
    Mueller = _py_pol().Mueller
    ms = physical_set
    ours = pa.parameter_maps(ms[:, :3, :3])
    o = Mueller("m")
    o.from_matrix(np.moveaxis(ms, 0, -1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.testing.assert_allclose(ours["m00"], o.parameters.mean_transmission(), atol=TOL)
        np.testing.assert_allclose(ours["DL"], o.parameters.diattenuation_linear(), atol=TOL)
        np.testing.assert_allclose(ours["PL"], o.parameters.polarizance_linear(), atol=TOL)
        dvec = o.parameters.diattenuation_vector()  # (3, N), normalised by m00
        pvec = o.parameters.polarizance_vector()
    assert _angle_close(ours["DL_axis_deg"], np.degrees(0.5 * np.arctan2(dvec[1], dvec[0])), 180)
    assert _angle_close(ours["PL_axis_deg"], np.degrees(0.5 * np.arctan2(pvec[1], pvec[0])), 180)


def test_maps_of_random_physical_matrices_equal_pyscatmech(physical_set):
    sm = _scatmech()
    ours = pa.parameter_maps(physical_set[:, :3, :3])
    for k, m in enumerate(physical_set):
        mm = sm.MuellerMatrix(m)
        assert abs(ours["DL"][k] - mm.linear_diattenuation()) < TOL
        out = sm.StokesVector(m @ [1.0, 0, 0, 0])  # what unpolarized light leaves
        assert abs(ours["PL"][k] - out.DOLP()) < TOL
        assert _angle_close(ours["PL_axis_deg"][k], np.degrees(out.eta()), 180)
        first_row = sm.StokesVector(m[0])  # the diattenuation vector's Stokes angle
        assert _angle_close(ours["DL_axis_deg"][k], np.degrees(first_row.eta()), 180)
        # the reported axis is the incident angle of maximum transmission, m00 (1 + DL)
        t = np.radians(ours["DL_axis_deg"][k])
        s_in = sm.StokesVector([1.0, np.cos(2 * t), np.sin(2 * t), 0.0])
        assert abs((m @ s_in)[0] - m[0, 0] * (1 + ours["DL"][k])) < TOL * (1 + m[0, 0])


def test_singular_values_equal_numpy_and_are_frame_invariant(physical_set):
    Mueller = _py_pol().Mueller
    ms = physical_set
    ours = pa.parameter_maps(ms[:, :3, :3])
    low = ms[:, 1:3, 1:3] / ms[:, :1, :1]
    sv = np.linalg.svd(low, compute_uv=False)
    np.testing.assert_allclose(ours["sv1"], sv[:, 0], atol=TOL)
    np.testing.assert_allclose(ours["sv2"], np.sign(np.linalg.det(low)) * sv[:, 1], atol=TOL)
    rng = np.random.default_rng(5)
    a, b = rng.uniform(0, np.pi, (2, len(ms)))
    turned = mu.rotator(a) @ ms @ mu.rotator(b)  # independent input and output frame rotations
    again = pa.parameter_maps(turned[:, :3, :3])
    for name in ("m00", "DL", "PL", "sv1", "sv2"):
        np.testing.assert_allclose(again[name], ours[name], atol=TOL)
    # a common rotation with py-pol's rotate(): the MMT invariants stay, x turns with the sample
    o = Mueller("m")
    o.from_matrix(np.moveaxis(ms, 0, -1))
    o.rotate(angle=a)
    common = pa.parameter_maps(np.moveaxis(o.M, -1, 0)[:, :3, :3])
    for name in ("mmt_b", "mmt_t1", "mmt_A"):
        np.testing.assert_allclose(common[name], ours[name], atol=TOL)
    ok = ours["mmt_t1"] > 1e-3
    assert _angle_close(common["mmt_x_deg"][ok], ours["mmt_x_deg"][ok] + np.degrees(a[ok]), 90)


def _real(x):
    """py-pol's results as real numbers (some come back complex128 with a zero imaginary part)."""
    x = np.asarray(x)
    assert np.all(np.abs(np.imag(x)) < 1e-9)
    return np.real(x)


def _decomposition_oracles(ms):
    """The 4x4 Lu-Chipman decomposition of pySCATMECH (SCATMECH's C++ ``Lu_Chipman_Decomposition``)
    of each matrix: ``(retardance_deg, retarder azimuth_deg, depolarizer's linear diagonal,
    linear diattenuation)``; the retardance from the retarder's trace, its azimuth from py-pol's
    analysis of that pure retarder (``analysis.retarder``). py-pol 1.3's own
    ``decompose_polar`` is no oracle here: for most of these matrices its factors do not
    multiply back to the matrix (its docstring names erroneous retarders as a known problem)."""
    Mueller, sm = _py_pol().Mueller, _scatmech()
    rets, deps, dls = [], [], []
    for m in ms:
        dep, ret, dia = sm.Lu_Chipman_Decomposition(sm.MuellerMatrix(m))
        assert np.allclose(np.asarray(dep) @ np.asarray(ret) @ np.asarray(dia), m, atol=1e-9)
        rets.append(np.asarray(ret))
        deps.append(np.diag(np.asarray(dep))[1:3])
        dls.append(sm.MuellerMatrix(np.asarray(dia)).linear_diattenuation())
    rets = np.stack(rets)
    r_deg = np.degrees(np.arccos(np.clip(np.trace(rets, axis1=1, axis2=2) / 2 - 1, -1, 1)))
    o = Mueller("r")
    o.from_matrix(np.moveaxis(rets, 0, -1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        az = np.degrees(_real(o.analysis.retarder(angles="azimuth")[1][0]))
    return r_deg, az, np.stack(deps), np.array(dls)


def test_decomposition_equals_4x4_lu_chipman_on_its_model():
    """On matrices of the decomposition's model (isotropic linear depolarizer, linear
    retarder, linear diattenuator) the 3x3 decomposition equals the 4x4 Lu-Chipman
    decomposition (pySCATMECH, the retarder's azimuth by py-pol) and the generating
    parameters."""
    rng = np.random.default_rng(9)
    made = [isotropic_model(rng, rotation=False) for _ in range(N_ORACLE)]
    ms = np.stack([m for m, _ in made])
    ours = pa.parameter_maps(ms[:, :3, :3])
    r_deg, az, dep, dl = _decomposition_oracles(ms)
    np.testing.assert_allclose(ours["retardance_deg"], r_deg, atol=TOL)
    assert _angle_close(ours["retardance_axis_deg"], az, 90)
    np.testing.assert_allclose(ours["depolarization"], 1 - dep[:, 0], atol=TOL)
    np.testing.assert_allclose(ours["depolarization"], 1 - dep[:, 1], atol=TOL)
    np.testing.assert_allclose(ours["DL"], dl, atol=TOL)
    np.testing.assert_allclose(ours["rotation_deg"], 0.0, atol=TOL)
    for name in ("retardance_deg", "depolarization", "DL"):
        np.testing.assert_allclose(ours[name], [t[name] for _, t in made], atol=TOL)
    assert _angle_close(ours["retardance_axis_deg"], [t["retardance_axis_deg"] for _, t in made], 90)
    assert np.all(ours["decomposition_flags"] == pa.DECOMP_ASSUMED)


def test_decomposition_recovers_the_rotation_and_the_linear_retardance():
    """With a rotator after the linear retarder (an elliptical retarder), the linear
    retardance, its axis and the rotation are the generating ones (Ghosh's linear retardance
    of pySCATMECH's 4x4 Lu-Chipman retarder agrees)."""
    rng = np.random.default_rng(10)
    made = [isotropic_model(rng, rotation=True) for _ in range(N_ORACLE)]
    ms = np.stack([m for m, _ in made])
    ours = pa.parameter_maps(ms[:, :3, :3])
    for name in ("retardance_deg", "depolarization", "rotation_deg", "DL"):
        np.testing.assert_allclose(ours[name], [t[name] for _, t in made], atol=TOL)
    assert _angle_close(ours["retardance_axis_deg"], [t["retardance_axis_deg"] for _, t in made], 90)
    assert _angle_close(ours["DL_axis_deg"], [t["DL_axis_deg"] for _, t in made], 180)
    sm = _scatmech()
    for k, m in enumerate(ms):
        ret = np.asarray(sm.Lu_Chipman_Decomposition(sm.MuellerMatrix(m))[1])
        ghosh = np.degrees(np.arccos(np.clip(
            np.hypot(ret[1, 1] + ret[2, 2], ret[2, 1] - ret[1, 2]) - 1, -1, 1)))
        assert abs(ours["retardance_deg"][k] - ghosh) < TOL


# -- closed forms -----------------------------------------------------------------------------
@pytest.mark.parametrize("ax_deg", [0.0, 30.0, 100.0, 179.0])
def test_closed_forms_of_a_partial_polarizer(ax_deg):
    er = 50.0
    m = mu.polarizer_at(np.radians(ax_deg), er)[:3, :3] * 700.0
    p = pa.parameter_maps(m)
    d = (1 - 1 / er) / (1 + 1 / er)
    assert p["m00"] == pytest.approx(700 * 0.5 * (1 + 1 / er))
    assert p["DL"] == pytest.approx(d) and p["PL"] == pytest.approx(d)
    assert _angle_close(p["DL_axis_deg"], ax_deg, 180, 1e-9)
    assert _angle_close(p["PL_axis_deg"], ax_deg, 180, 1e-9)
    # a diattenuator alone: no retardance, no depolarization, no rotation
    # retardance near 0 is ill-conditioned by nature (~ sqrt of rounding errors)
    assert p["retardance_deg"] == pytest.approx(0, abs=1e-4)
    assert p["depolarization"] == pytest.approx(0, abs=1e-12)


def test_an_ideal_polarizer_is_refused_by_the_decomposition():
    p = pa.parameter_maps(mu.polarizer_at(0.3)[:3, :3])
    assert p["DL"] == pytest.approx(1.0) and p["sv1"] == pytest.approx(1.0)
    assert p["sv2"] == pytest.approx(0.0, abs=1e-12)
    for name in ("retardance_deg", "retardance_axis_deg", "depolarization", "rotation_deg"):
        assert np.isnan(p[name])
    assert p["decomposition_flags"] == pa.DECOMP_UNDEFINED


@pytest.mark.parametrize("ax_deg, d_deg", [(0, 30), (20, 90), (75, 150), (135, 60)])
def test_closed_forms_of_a_retarder(ax_deg, d_deg):
    p = pa.parameter_maps(mu.retarder_at(np.radians(ax_deg), np.radians(d_deg))[:3, :3])
    c = np.cos(np.radians(d_deg))
    assert p["DL"] == pytest.approx(0, abs=1e-12) and p["PL"] == pytest.approx(0, abs=1e-12)
    assert (p["sv1"], p["sv2"]) == pytest.approx((1.0, c))
    assert (p["mmt_b"], p["mmt_t1"]) == pytest.approx(((1 + c) / 2, (1 - c) / 2))
    assert _angle_close(p["mmt_x_deg"], ax_deg, 90, 1e-9)
    assert p["retardance_deg"] == pytest.approx(d_deg)
    assert _angle_close(p["retardance_axis_deg"], ax_deg, 90, 1e-9)
    assert p["depolarization"] == pytest.approx(0, abs=1e-12)
    assert p["rotation_deg"] == pytest.approx(0, abs=1e-9)


@pytest.mark.parametrize("a", [1.0, 0.6, 0.1, 0.0])
def test_closed_forms_of_an_isotropic_depolarizer(a):
    p = pa.parameter_maps(mu.partial_depolarizer(a)[:3, :3] * 3.0)
    assert (p["sv1"], p["sv2"]) == pytest.approx((a, a))
    assert p["mmt_b"] == pytest.approx(a) and p["mmt_t1"] == pytest.approx(0)
    if a > 0:
        assert p["depolarization"] == pytest.approx(1 - a)
        assert p["retardance_deg"] == pytest.approx(0, abs=1e-6)
        assert p["decomposition_flags"] == 0
    else:  # the ideal depolarizer: nothing left to decompose
        assert np.isnan(p["retardance_deg"]) and p["decomposition_flags"] == pa.DECOMP_UNDEFINED


def test_closed_forms_of_a_rotator_and_a_mirror():
    rot = pa.parameter_maps(mu.rotator(-np.radians(25.0))[:3, :3])  # optical rotation +25 deg
    assert rot["rotation_deg"] == pytest.approx(25.0) and rot["retardance_deg"] == pytest.approx(0, abs=1e-6)
    assert (rot["sv1"], rot["sv2"]) == pytest.approx((1.0, 1.0))
    mirror = pa.parameter_maps(np.diag([1.0, 1.0, -1.0]))
    assert mirror["retardance_deg"] == pytest.approx(180.0)
    assert (mirror["sv1"], mirror["sv2"]) == pytest.approx((1.0, -1.0))


# -- what the block cannot tell ---------------------------------------------------------------
@pytest.mark.parametrize("d_deg", [20.0, 70.0, 120.0])
def test_a_retarder_and_an_anisotropic_depolarizer_with_the_same_block_are_flagged(d_deg):
    """The refusal case: a retarder at 0 deg and the depolarizer diag(1, 1, cos d, cos d) have
    the same 3x3 block; the 4x4 decompositions tell them apart, the 3x3 one cannot: it gives
    both the same answer (retardance d under the isotropic-depolarization assumption) and flags
    them as resting on that assumption."""
    d = np.radians(d_deg)
    ret = mu.retarder_at(0.0, d)
    dep = np.diag([1.0, 1.0, np.cos(d), np.cos(d)])
    assert is_physical_coherency(dep) and is_physical_coherency(ret)
    np.testing.assert_allclose(ret[:3, :3], dep[:3, :3], atol=1e-15)
    a, b = pa.parameter_maps(ret[:3, :3]), pa.parameter_maps(dep[:3, :3])
    for name in a:
        assert a[name] == b[name] or (np.isnan(a[name]) and np.isnan(b[name]))
    assert a["decomposition_flags"] & pa.DECOMP_ASSUMED
    assert a["retardance_deg"] == pytest.approx(d_deg) and a["depolarization"] == pytest.approx(0)
    # with measured sigma, the flag needs a significant anisotropy
    assert pa.decomposition_flags(ret[:3, :3], np.full((3, 3), 1e-3)) & pa.DECOMP_ASSUMED
    assert pa.decomposition_flags(dep[:3, :3], np.full((3, 3), 1e-3)) & pa.DECOMP_ASSUMED
    # the 4x4 Lu-Chipman decomposition sees the fourth row and tells them apart
    # (d < 90: no retardance; d > 90: Lu-Chipman reads the negative eigenvalues as a
    # half-wave retarder and a depolarizer diag(1, 1, |cos d|, |cos d|))
    r_deg, _, dp, _ = _decomposition_oracles(np.stack([ret, dep]))
    assert r_deg[0] == pytest.approx(d_deg)
    assert r_deg[1] == pytest.approx(0.0 if d_deg < 90 else 180.0, abs=1e-4)  # arccos at +-1
    assert dp[1, 1] == pytest.approx(abs(np.cos(d)))  # the depolarizer's anisotropy
    assert "isotropic linear depolarization" in pa.DECOMPOSITION_ASSUMPTION
    assert "cannot tell" in pa.DECOMPOSITION_FLAGS[pa.DECOMP_ASSUMED]


def test_an_isotropic_block_is_not_flagged_and_noise_alone_is_not_retardance():
    """With noise, an isotropic block is flagged anisotropic with the Rayleigh probability
    exp(-k^2 / 2) (1.1 % at k = 3); a retarder of a few sigma's anisotropy always is."""
    m = mu.partial_depolarizer(0.5)[:3, :3]
    rng = np.random.default_rng(2)
    noisy = m + rng.normal(0, 1e-3, (2000, 3, 3))
    assumed = pa.decomposition_flags(noisy, 1e-3) & pa.DECOMP_ASSUMED
    assert np.mean(assumed > 0) == pytest.approx(np.exp(-4.5), abs=0.008)
    assert np.mean(pa.decomposition_flags(noisy, 1e-3, k=2) > 0) == pytest.approx(np.exp(-2), abs=0.03)
    assert pa.parameter_maps(m)["decomposition_flags"] == 0
    ret = mu.partial_depolarizer(0.5)[:3, :3] @ mu.retarder_at(0.3, 0.3)[:3, :3]
    noisy = ret + rng.normal(0, 1e-3, (200, 3, 3))
    assert np.all(pa.decomposition_flags(noisy, 1e-3) & pa.DECOMP_ASSUMED)


# -- extremes (hypothesis) ----------------------------------------------------------------------
seeds = st.integers(0, 2 ** 32 - 1)


#: Where an angle map is well conditioned (the magnitude that defines it away from 0).
_DEFINED_BY = {"DL_axis_deg": lambda p: p["DL"] > 1e-6, "PL_axis_deg": lambda p: p["PL"] > 1e-6,
               "mmt_x_deg": lambda p: p["mmt_t1"] > 1e-6,
               "retardance_axis_deg": lambda p: 0.01 < p["retardance_deg"] < 179.99,
               "rotation_deg": lambda p: p["retardance_deg"] < 179.99}


@SETTINGS
@given(seed=seeds, scale=st.floats(1e-300, 1e300))
def test_normalised_maps_do_not_depend_on_the_scale_down_to_m00_near_zero(seed, scale):
    """Every normalised map of ``s M`` equals that of ``M`` for ``s`` from 1e-300 to 1e300
    (no overflow, underflow or warning); a retardance near 0 or 180 deg to its conditioning
    (~ sqrt of rounding errors, 1e-4 deg), an angle where the magnitude defining it is not 0."""
    m = random_physical(np.random.default_rng(seed))[:3, :3]
    with np.errstate(all="raise"):
        p, q = pa.parameter_maps(m), pa.parameter_maps(m * scale)
    for name in pa.MAPS:
        if name == "m00":
            assert q[name] == pytest.approx(p[name] * scale, rel=1e-12)
        elif np.isnan(p[name]) or np.isnan(q[name]):
            assert np.isnan(p[name]) and np.isnan(q[name]), name
        elif name in pa.ANGLE_PERIOD_DEG:
            if _DEFINED_BY[name](p):
                assert _angle_close(q[name], p[name], pa.ANGLE_PERIOD_DEG[name], 1e-4), name
        elif name == "retardance_deg":
            assert q[name] == pytest.approx(p[name], abs=1e-4), name
        else:
            assert q[name] == pytest.approx(p[name], rel=1e-9, abs=1e-9), name


@pytest.mark.parametrize("m00", [0.0, -1e-3, -5.0])
def test_m00_at_or_below_zero_gives_nan_maps_and_the_undefined_flag(m00):
    m = np.diag([m00, 0.2, 0.1])
    p = pa.parameter_maps(m)
    assert p["m00"] == m00
    assert all(np.isnan(p[n]) for n in pa.MAPS if n != "m00")
    assert p["decomposition_flags"] == pa.DECOMP_UNDEFINED


@SETTINGS
@given(seed=seeds, eps=st.floats(1e-9, 1e-2))
def test_diattenuation_near_one(seed, eps):
    """``D = 1 - eps``: DL to double precision, the decomposition defined and within the
    conditioning of the inverse diattenuator (error ~ 1e-16 / (1 - D^2))."""
    rng = np.random.default_rng(seed)
    t, ax = rng.uniform(0.1, 2), rng.uniform(0, np.pi)
    d = 1 - eps
    md = mu.rotated_element(ax, mu.diattenuator(t * (1 + d), t * (1 - d)))
    ret_ax, ret_d = rng.uniform(0, np.pi), rng.uniform(0.1, np.pi - 0.1)
    a = rng.uniform(0.2, 1.0)
    m = (mu.partial_depolarizer(a) @ mu.retarder_at(ret_ax, ret_d) @ md)[:3, :3]
    p = pa.parameter_maps(m)
    assert p["DL"] == pytest.approx(d, abs=1e-12)
    assert p["decomposition_flags"] & pa.DECOMP_UNDEFINED == 0
    tol = 1e-12 / eps + 1e-9
    assert p["depolarization"] == pytest.approx(1 - a, abs=tol)
    assert p["retardance_deg"] == pytest.approx(np.degrees(ret_d), abs=1e3 * tol)


def test_diattenuation_at_or_above_one_is_refused():
    for d in (1.0, 1.0 + 1e-9, 1.5):
        m = np.array([[1.0, d, 0.0], [d, 1.0, 0.0], [0.0, 0.0, 0.0]])
        p = pa.parameter_maps(m)
        assert p["DL"] == pytest.approx(d)
        assert np.isnan(p["retardance_deg"]) and p["decomposition_flags"] == pa.DECOMP_UNDEFINED


@SETTINGS
@given(seed=seeds, nan_mask=st.lists(st.booleans(), min_size=9, max_size=9))
def test_nan_planes_give_nan_maps_and_no_warning(seed, nan_mask):
    rng = np.random.default_rng(seed)
    ms = np.stack([random_physical(rng)[:3, :3] for _ in range(4)])
    bad = np.array(nan_mask).reshape(3, 3)
    ms[1][bad] = np.nan  # one pixel with NaN planes
    ms[3] = np.nan  # one all-NaN pixel
    sig = np.full(ms.shape, 0.01)
    sig[2, 0, 1] = np.nan  # a NaN sigma
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vals, sigs = pa.parameter_maps(ms), pa.parameter_sigmas(ms, sig)
        flags = pa.decomposition_flags(ms, sig)
    for name in pa.MAPS:
        assert np.isnan(vals[name][3]) and np.isnan(sigs[name][3])
        assert np.isfinite(vals[name][0]) or name in ("retardance_deg", "retardance_axis_deg",
                                                      "depolarization", "rotation_deg", "mmt_A")
        if bad.any() and not (name == "m00" and not bad[0, 0]):
            assert np.isnan(vals[name][1])
    assert np.isnan(sigs["DL"][2]) and np.isfinite(sigs["PL"][2])
    assert flags[3] == pa.DECOMP_UNDEFINED
    if bad.any():
        assert flags[1] == pa.DECOMP_UNDEFINED


# -- the linearised sigma -----------------------------------------------------------------------
def test_linearised_sigma_equals_the_spread_of_sampled_errors():
    """At a high signal-to-noise ratio each map's linearised sigma is the standard deviation of
    the map over many noisy copies of the block (independent element errors), within the
    sampling error (2000 samples: about 3 %)."""
    rng = np.random.default_rng(4)
    m, _ = isotropic_model(rng, rotation=True)
    m = m[:3, :3] * 1000.0
    sigma = rng.uniform(0.5, 2.0, (3, 3))
    noisy = m + rng.normal(0.0, 1.0, (2000, 3, 3)) * sigma
    lin = pa.parameter_sigmas(m, sigma)
    samples = pa.parameter_maps(noisy)
    for name in pa.MAPS:
        x = samples[name]
        if name in pa.ANGLE_PERIOD_DEG:
            per = pa.ANGLE_PERIOD_DEG[name]
            x = np.mod(x - pa.parameter_maps(m)[name] + per / 2, per) - per / 2
        assert np.std(x) == pytest.approx(lin[name], rel=0.08), name


def test_finite_difference_and_analytic_sigma_agree():
    """The finite-difference Jacobian route gives the analytic sigma of DL (checked through the
    private helper on a map with a closed-form derivative)."""
    rng = np.random.default_rng(8)
    ms = np.stack([random_physical(rng)[:3, :3] for _ in range(80)])
    ms = ms[pa.linear_diattenuation(ms)[0] > 1e-3]  # away from the cone point DL = 0
    sig = rng.uniform(0.001, 0.01, ms.shape)
    analytic = pa.parameter_sigmas(ms, sig)["DL"]
    h = 1e-6 * np.abs(ms).max(axis=(-2, -1))
    var = np.zeros(len(ms))
    for i in range(3):
        for j in range(3):
            up, dn = ms.copy(), ms.copy()
            up[:, i, j] += h
            dn[:, i, j] -= h
            g = (pa.linear_diattenuation(up)[0] - pa.linear_diattenuation(dn)[0]) / (2 * h)
            var += (g * sig[:, i, j]) ** 2
    np.testing.assert_allclose(np.sqrt(var), analytic, rtol=1e-5)


def test_chain_rule_sigma_equals_central_differences_of_the_maps():
    """The analytic chain-rule sigma of sv1, sv2 and the decomposition's maps equals the sigma
    from central differences of :func:`pa.parameter_maps` itself (an independent route: no
    Jacobian code shared), on random physical matrices with noise, away from the points where
    a map is not differentiable (cone points of R, Q, D and sv1 = +-sv2)."""
    rng = np.random.default_rng(12)
    ms = np.stack([random_physical(rng)[:3, :3] for _ in range(300)])
    ms = ms * rng.uniform(0.01, 1e4, (len(ms), 1, 1))
    ms = ms + rng.normal(0, 0.02, ms.shape) * ms[:, :1, :1]
    v = pa.parameter_maps(ms)
    keep = ((v["retardance_deg"] > 5) & (v["retardance_deg"] < 175) & (v["DL"] < 0.9)
            & (v["depolarization"] < 0.9) & (v["mmt_t1"] > 1e-2)
            & (np.abs(np.abs(v["sv2"]) - v["sv1"]) > 1e-2) & (np.abs(v["sv2"]) > 1e-2))
    ms = ms[keep]
    assert len(ms) > 100
    sig = rng.uniform(0.5, 2.0, ms.shape) * 1e-3 * np.abs(ms[:, :1, :1])
    analytic = pa.parameter_sigmas(ms, sig)
    h = 1e-6 * np.abs(ms).max(axis=(-2, -1))
    names = ("sv1", "sv2", "retardance_deg", "retardance_axis_deg", "depolarization",
             "rotation_deg")
    var = {n: np.zeros(len(ms)) for n in names}
    for i in range(3):
        for j in range(3):
            up, dn = ms.copy(), ms.copy()
            up[:, i, j] += h
            dn[:, i, j] -= h
            a, b = pa.parameter_maps(up), pa.parameter_maps(dn)
            for n in names:
                d = a[n] - b[n]
                if n in pa.ANGLE_PERIOD_DEG:
                    per = pa.ANGLE_PERIOD_DEG[n]
                    d = np.mod(d + per / 2, per) - per / 2
                var[n] += (d / (2 * h) * sig[:, i, j]) ** 2
    for n in names:
        np.testing.assert_allclose(analytic[n], np.sqrt(var[n]), rtol=1e-5, err_msg=n)


def test_an_infinite_sigma_does_not_spread_to_maps_that_ignore_the_element():
    m = mu.retarder_at(0.3, 1.0)[:3, :3] * 100 + np.diag([0, 0, 0])
    m[0, 1] = 10.0
    sig = np.full((3, 3), 0.1)
    sig[2, 0] = np.inf
    s = pa.parameter_sigmas(m, sig)
    assert np.isfinite(s["DL"]) and np.isfinite(s["mmt_b"]) and np.isfinite(s["m00"])
    assert np.isinf(s["PL"])


# -- images -----------------------------------------------------------------------------------
def test_image_maps_equal_the_per_pixel_maps_for_any_band():
    rng = np.random.default_rng(3)
    c, h, w = 3, 5, 7
    blocks = np.stack([random_physical(rng)[:3, :3] for _ in range(c * h * w)]) * 500
    img = np.moveaxis(blocks.reshape(c, h, w, 3, 3), (-2, -1), (1, 2)).astype(np.float32)
    sig = np.full(img.shape, 2.0, np.float32)
    a = pa.image_maps(img, sig)
    b = pa.image_maps(img, sig, band_pixels=1)
    ref = pa.parameter_maps(np.moveaxis(img.astype(np.float64), (1, 2), (-2, -1)))
    for name in pa.MAPS:
        np.testing.assert_array_equal(a.values[name], b.values[name])
        np.testing.assert_array_equal(a.sigma[name], b.sigma[name])
        np.testing.assert_allclose(a.values[name], ref[name].astype(np.float32), rtol=1e-6,
                                   equal_nan=True)
        assert a.values[name].shape == (c, h, w) and a.values[name].dtype == np.float32
    np.testing.assert_array_equal(a.flags, b.flags)
    assert pa.image_maps(img).sigma == {}
    with pytest.raises(ValueError, match=r"\(C, 3, 3, H, W\)"):
        pa.image_maps(img[0])


def test_image_maps_are_the_same_bits_for_any_band_and_thread_count():
    """Tiled (bands of rows, any height) and threaded: the same maps, sigma and flags to the
    bit as one band on one thread, with NaN pixels and an infinite sigma in the image."""
    rng = np.random.default_rng(5)
    c, h, w = 3, 23, 11
    blocks = np.stack([random_physical(rng)[:3, :3] for _ in range(c * h * w)]) * 800
    img = np.moveaxis(blocks.reshape(c, h, w, 3, 3), (-2, -1), (1, 2)).astype(np.float32)
    img = img + rng.normal(0, 1.0, img.shape).astype(np.float32)
    img[1, :, :, 4, 5] = np.nan
    sig = rng.uniform(0.5, 2.0, img.shape).astype(np.float32)
    sig[0, 2, 0, 7, 3] = np.inf
    whole = pa.image_maps(img, sig, band_pixels=c * h * w, workers=1)
    for band_pixels, workers in ((c * w, 1), (c * w, 4), (2 * c * w + 1, 3), (1 << 14, 2)):
        got = pa.image_maps(img, sig, band_pixels=band_pixels, workers=workers)
        for name in pa.MAPS:
            np.testing.assert_array_equal(got.values[name], whole.values[name], err_msg=name)
            np.testing.assert_array_equal(got.sigma[name], whole.sigma[name], err_msg=name)
        np.testing.assert_array_equal(got.flags, whole.flags)
    assert np.isnan(whole.values["retardance_deg"][1, 4, 5])
    assert np.isinf(whole.sigma["PL"][0, 7, 3])


def test_resolved_marks_magnitudes_above_k_sigma():
    m = np.stack([mu.retarder_at(0.2, d)[:3, :3] for d in (0.001, 0.5, np.pi - 0.001)])
    v = pa.parameter_maps(m)
    s = pa.parameter_sigmas(m, np.full(m.shape, 1e-3))
    r = pa.resolved(v, s)
    assert list(r["retardance_deg"]) == [False, True, False]
    assert list(r["retardance_axis_deg"]) == [False, True, False]
    assert not r["DL"].any() and not r["DL_axis_deg"].any()  # no diattenuation at all
    assert r["mmt_b"].all() and r["m00"].all()
