"""The compiled grid search of the diffuse term's normal (polrig.solve._diffuse_kernel) against
the previous numpy search (polrig.solve._diffuse_numpy, the oracle), for both costs: the diffuse
test's statistic and the completion's ratio misfit with the pull to a guessed normal. Random
pixels with the extremes: the view along the optical axis and far off it (the search frame's
other helper axis), the light along the view, grazing and behind the surface (every candidate
invalid), the ends of the index grid, states without information."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.optics.pbrdf import linear_rig_mueller
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import _diffuse_numpy as oracle
from polrig.solve import chunks
from polrig.solve import diffuse_geometry as dg
from polrig.solve import diffuse_test as dt

STAGE = np.array([0.0, -1.0, 0.0])
CAM = np.array([1.0, 0.0, 0.0])


def _state(deg: float) -> np.ndarray:
    t = np.deg2rad(2 * deg)
    return np.array([1.0, np.cos(t), np.sin(t)])


STATES = np.stack([_state(0), _state(90)])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _about(axis: np.ndarray, angle_deg: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Unit vectors ``angle_deg`` ``(P,)`` from the unit ``axis`` ``(P, 3)``, random azimuths."""
    helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = _unit(np.cross(axis, helper))
    e2 = np.cross(axis, e1)
    t, f = np.deg2rad(angle_deg)[:, None], rng.uniform(0, 2 * np.pi, (len(axis), 1))
    return np.cos(t) * axis + np.sin(t) * (np.cos(f) * e1 + np.sin(f) * e2)


def _geometry(p: int, rng: np.random.Generator):
    """Views, lights and true normals ``(P, 3)``: most views within 25 deg of the optical axis
    and lights 0-80 deg from them; then the extremes (module docstring)."""
    view = _about(np.tile([0.0, 0.0, 1.0], (p, 1)), rng.uniform(0, 25, p), rng)
    light = _about(view, rng.uniform(0, 80, p), rng)
    view[0] = [0.0, 0.0, 1.0]  # along the optical axis, the light along the view
    light[0] = view[0]
    view[1] = _unit(np.array([0.0, 0.95, 0.3]))  # |view_y| >= 0.9: the frame's other helper
    view[2] = _unit(np.array([0.9, -0.1, 0.2]))  # far off the optical axis
    light[3:6] = -view[3:6]  # behind: no normal faces both
    light[6:9] = _about(view[6:9], np.full(3, 89.5), rng)  # grazing
    light[9:12] = _about(view[9:12], np.full(3, 150.0), rng)  # behind, a few normals still face both
    half = view + light
    half[3:6] = view[3:6]  # the light behind: no half vector
    normal = _unit(_unit(half) + rng.normal(0, 0.2, half.shape))
    return view, light, normal


def _diffuse(normal, light, view, eta):
    """Unit diffuse blocks ``(P, 3, 3)``; a normal facing away from either gives zeros."""
    return linear_rig_mueller(normal, light, view, kd=1.0, ks=0.0, alpha=0.1, eta=eta, components=("diffuse",),
                              stage_zero_axis=STAGE, camera_x_axis=CAM)


def _agree(cost_k, normal_k, cost_n, normal_n) -> np.ndarray:
    """Where the two searches took the same candidate: equal normals and costs to rounding (inf
    where the oracle's is). Returns that mask."""
    same = np.all(np.abs(normal_k - normal_n) <= 1e-9, axis=1)
    assert same.mean() >= 0.99, f"the kernel and numpy took different candidates at {np.flatnonzero(~same)}"
    inf = np.isinf(cost_n[same])
    assert np.array_equal(np.isinf(cost_k[same]), inf)
    a, b = cost_k[same][~inf], cost_n[same][~inf]
    assert np.all(np.abs(a - b) <= 1e-9 * (1 + np.abs(b))), np.max(np.abs(a - b) / (1 + np.abs(b)))
    return same


def _statistic_inputs(p: int, eta: float, rng: np.random.Generator):
    """Three colours' two-state Stokes vectors ``(C, 2, 3, P)`` and information ``(C, 2, 3, 3, P)``:
    half the pixels a diffuse truth's with noise, half arbitrary; a few with no information at
    all or none from one state (then one state's three numbers are all it has)."""
    view, light, normal = _geometry(p, rng)
    md = _diffuse(normal, light, view, eta)  # (P, 3, 3)
    albedo = rng.uniform(0.2, 1.0, (3, p))
    clean = np.einsum("cp,prk,jk->cjrp", albedo, md, STATES)
    wild = rng.normal(0, 0.05, clean.shape) + np.array([0.1, 0.0, 0.0])[None, None, :, None]
    stokes = np.where(np.arange(p) % 2 == 0, clean, wild) + rng.normal(0, 0.002, clean.shape)
    a = ideal_analyzer_matrix()
    w = rng.uniform(0.5, 2.0, (3, 2, 4, p)) * 1e5
    info = np.einsum("ja,cdjp,jb->cdabp", a, w, a)
    info[..., 12:15] = 0.0  # no information: every candidate's statistic is NaN, so inf
    info[:, 1, ..., 15:18] = 0.0  # the second state says nothing
    return stokes, info, view, light


@pytest.mark.parametrize("eta", [1.2, 1.55, 2.0])
def test_statistic_matches_the_numpy_search(eta):
    rng = np.random.default_rng(int(eta * 100))
    stokes, info, view, light = _statistic_inputs(240, eta, rng)
    t_k, n_k, k_k = dt.diffuse_statistic(stokes, info, STATES, view, light, eta, STAGE, CAM)
    t_n, n_n, k_n = oracle.diffuse_statistic_numpy(stokes, info, STATES, view, light, eta, STAGE, CAM)
    same = _agree(t_k, n_k, t_n, n_n)
    assert np.isinf(t_k[3:6]).all() and np.isinf(t_k[12:15]).all()  # behind; no information
    assert np.isfinite(t_k[np.r_[0:3, 6:12, 15:18]]).all()
    assert (np.isnan(k_k) == np.isnan(k_n))[:, same].all()
    fin = same & np.isfinite(k_n).all(axis=0)
    assert np.allclose(k_k[:, fin], k_n[:, fin], rtol=1e-9, atol=1e-12)
    assert np.isnan(k_k[:, 3:6]).all()  # behind: the normal taken is not valid


@pytest.mark.parametrize("eta", [1.3, 1.8])
def test_statistic_with_the_specular_term_matches_the_numpy_search(eta):
    """The second albedo per colour (Baek's specular block, unit ``m00``): the same candidates,
    statistics and both albedos as the numpy search, on pixels with a specular part, without
    one and arbitrary; never above the diffuse term's statistic alone; the albedos >= 0."""
    from polrig.solve.diffuse_geometry import specular_block

    rng = np.random.default_rng(int(eta * 10))
    stokes, info, view, light = _statistic_inputs(240, eta, rng)
    spec = specular_block(light, view, eta, STAGE, CAM)
    # a specular part on every third pixel: up to its diffuse part's size
    add = np.einsum("cp,prk,jk->cjrp", rng.uniform(0.0, 1.0, (3, 240)) * (np.arange(240) % 3 == 0),
                    spec, STATES) * stokes[:, :, :1].clip(0, None)
    stokes = stokes + add
    t_k, n_k, k_k = dt.diffuse_statistic(stokes, info, STATES, view, light, eta, STAGE, CAM, specular=spec)
    t_n, n_n, k_n = oracle.diffuse_statistic_numpy(stokes, info, STATES, view, light, eta, STAGE, CAM, specular=spec)
    same = _agree(t_k, n_k, t_n, n_n)
    assert k_k.shape == (6, 240)
    fin = same & np.isfinite(k_n).all(axis=0)
    assert np.allclose(k_k[:, fin], k_n[:, fin], rtol=1e-8, atol=1e-10)
    assert (k_k[:, fin] >= 0).all()
    t_d, _, _ = dt.diffuse_statistic(stokes, info, STATES, view, light, eta, STAGE, CAM)
    ok = np.isfinite(t_d)
    assert np.all(t_k[ok] <= t_d[ok] + 1e-9 * (1 + t_d[ok]))
    assert (k_k[3:, fin] > 0).any()


def _ratio_inputs(p: int, eta: float, rng: np.random.Generator):
    """The completion's search inputs: views, lights and true normals (:func:`_geometry`), the
    states 30 and 120 deg, and the measured ratios of the noisy diffuse blocks with their weights
    (``dg._Observed``; NaN where no light the diffuse term explains, set to 0.3)."""
    view, light, normal = _geometry(p, rng)
    s_a, s_b = _state(30), _state(120)
    md = _diffuse(normal, light, view, eta) + rng.normal(0, 0.002, (p, 3, 3))
    x_hat, rho_hat, weights = dg.ratio_weights(np.moveaxis(md, 0, -1), np.full((3, 3, p), 1e-4), s_a, s_b)
    x_hat, rho_hat, weights = (np.nan_to_num(a, nan=0.3) for a in (x_hat, rho_hat, weights))
    return view, light, normal, s_a, s_b, dg._Observed(x_hat, rho_hat, weights)


@pytest.mark.parametrize("guess_weight", [None, dg.GUESS_WEIGHT, dg.NEIGHBOUR_WEIGHT])
def test_ratio_search_matches_the_numpy_search(guess_weight):
    """With a pull (the first pass's weak one and the second pass's strong one) the kernel's
    coarse level skips the candidates the pull alone bounds; the numpy search scans them all."""
    with_guess = guess_weight is not None
    rng = np.random.default_rng(7 + with_guess)
    p, eta = 240, 1.5
    view, light, normal, s_a, s_b, obs = _ratio_inputs(p, eta, rng)
    guess = _unit(normal + rng.normal(0, 0.1, normal.shape)) if with_guess else None
    geo = dg._Pixels(view, light, guess, guess_weight or 0.0, STAGE, CAM, s_a, s_b)
    pix = np.arange(p)
    n_k, c_k = dg._search(pix, eta, obs, geo, 2)
    n_n, c_n = oracle.search_ratios_numpy(pix, eta, obs, geo, 2)
    _agree(c_k, n_k, c_n, n_n)
    assert np.isinf(c_k[3:6]).all() and np.isfinite(c_k[np.r_[0:3, 6:12]]).all()
    # a subset in another order: the same per pixel
    sub = rng.permutation(p)[:50]
    n_s, c_s = dg._search(sub, eta, obs, geo, 2)
    assert np.array_equal(n_s, n_k[sub]) and np.array_equal(c_s, c_k[sub])


def test_bounded_scan_takes_the_full_scans_candidate_where_data_and_pull_disagree():
    """Guesses anywhere in the visible hemisphere (most far from the data's normal), at the second
    pass's strong pull and at a pull that just balances the data, and guesses with no direction
    (zero, NaN: nothing bounded; NaN makes every cost inf): the kernel, which skips the coarse
    candidates whose pull alone exceeds its least cost so far, takes the numpy search's
    candidates, which scans them all."""
    rng = np.random.default_rng(17)
    p, eta = 300, 1.5
    view, light, _, s_a, s_b, obs = _ratio_inputs(p, eta, rng)
    guess = _about(view, rng.uniform(0, 88, p), rng)
    guess[12:15] = 0.0
    guess[15:18] = np.nan
    pix = np.arange(p)
    for weight in (dg.NEIGHBOUR_WEIGHT, float(np.median(obs.weights.sum(axis=1))) * 1e-3):
        geo = dg._Pixels(view, light, guess, weight, STAGE, CAM, s_a, s_b)
        n_k, c_k = dg._search(pix, eta, obs, geo, 2)
        n_n, c_n = oracle.search_ratios_numpy(pix, eta, obs, geo, 2)
        _agree(c_k, n_k, c_n, n_n)
        assert np.isinf(c_k[15:18]).all() and np.isfinite(c_k[12:15]).all()


def test_results_do_not_depend_on_threads_or_chunks(monkeypatch):
    rng = np.random.default_rng(21)
    stokes, info, view, light = _statistic_inputs(150, 1.5, rng)
    args = (stokes, info, STATES, view, light, 1.5, STAGE, CAM)
    monkeypatch.setattr(chunks, "THREADS", 1)
    one = dt.diffuse_statistic(*args)
    monkeypatch.setattr(chunks, "THREADS", 3)
    monkeypatch.setattr(dg, "_CHUNK_PIXELS", 7)
    many = dt.diffuse_statistic(*args)
    for a, b in zip(one, many):
        assert np.array_equal(a, b, equal_nan=True)


def test_fit_takes_the_numpy_fits_index_light_and_normals(monkeypatch):
    """The whole fit (``eta`` and the light on the stride sample, then every pixel) with the
    kernel and with the numpy search: the same choice, the same normals to rounding."""
    rng = np.random.default_rng(31)
    p = 90
    view = _about(np.tile([0.0, 0.0, 1.0], (p, 1)), rng.uniform(0, 10, p), rng)
    light = _unit(np.array([0.6, 0.1, 0.8]))
    normal = _unit(_about(np.tile(light, (p, 1)), rng.uniform(10, 40, p), rng) + view)
    s_a, s_b = _state(30), _state(120)
    md = _diffuse(normal, np.broadcast_to(light, view.shape), view, 1.6)
    x_hat, rho_hat, weights = dg.ratio_weights(np.moveaxis(md, 0, -1), np.full((3, 3, p), 1e-5), s_a, s_b)
    wrong = _unit(light + [0.3, 0.0, 0.0])
    args = (x_hat, rho_hat, weights, s_a, s_b, view, (wrong, light), STAGE, CAM, normal)
    fit = dg.fit_diffuse_geometry(*args, etas=(1.4, 1.6, 1.8))
    monkeypatch.setattr(dg, "_search", oracle.search_ratios_numpy)
    ref = dg.fit_diffuse_geometry(*args, etas=(1.4, 1.6, 1.8))
    assert (fit.eta, fit.light) == (ref.eta, ref.light) == (1.6, 1)
    _agree(fit.cost, fit.normal, ref.cost, ref.normal)
