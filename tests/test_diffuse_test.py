"""The diffuse term tested on two states' samples alone (polrig.solve.diffuse_test): the
per-state Stokes estimate against its closed form, the statistic's null distribution on noisy
diffuse pixels rendered by the pBRDF (its level), its power against a specular (Fresnel) block,
the refractive index it chooses, the selection's ``decided`` route, and the completed result
against hidden truth."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.optics.pbrdf import linear_rig_mueller
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import diffuse_geometry as dg
from polrig.solve import diffuse_test as dt
from polrig.solve.model_selection import SelectionOptions, chi2_critical, select_models
from polrig.solve.reference import forward_measurements

STAGE = np.array([0.0, -1.0, 0.0])
CAM = np.array([1.0, 0.0, 0.0])
#: Shot noise in these units: variance = GAIN * intensity + READ (a bright diffuse pixel at about
#: 2000 DN, a few thousand electrons).
GAIN, READ = 1.0, 25.0


def _state(deg: float) -> np.ndarray:
    t = np.deg2rad(2 * deg)
    return np.array([1.0, np.cos(t), np.sin(t)])


STATES = np.stack([_state(0), _state(90)])


def _surface(h: int, w: int, seed: int):
    """A smooth surface seen about the optical axis under one light 40 deg off it: views
    ``(H, W, 3)``, the light ``(3,)`` and normals ``(H, W, 3)`` (zenith 10-55 deg, the azimuth
    turning across the image)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    view = np.stack([0.05 * (xx - 0.5), 0.05 * (yy - 0.5), np.ones_like(xx)], axis=-1)
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    light = np.array([np.sin(np.deg2rad(40)), 0.1, np.cos(np.deg2rad(40))])
    light /= np.linalg.norm(light)
    zen = np.deg2rad(10 + 45 * (0.5 + 0.5 * np.sin(3 * xx + 2 * yy + rng.uniform(0, 6))))
    azi = 2 * np.pi * (xx + 0.5 * yy) + rng.uniform(0, 2 * np.pi)
    normal = np.stack([np.sin(zen) * np.cos(azi), np.sin(zen) * np.sin(azi), np.cos(zen)], axis=-1)
    return view, light, normal


def _blocks(view, light, normal, eta: float, component: str, albedo) -> np.ndarray:
    """``(C, 3, 3, H, W)`` blocks of one pBRDF ``component`` scaled per colour by ``albedo``."""
    h, w = view.shape[:2]
    flat = lambda a: np.broadcast_to(a, (h, w, 3)).reshape(-1, 3)  # noqa: E731
    kw = dict(kd=1.0, ks=0.0) if component == "diffuse" else dict(kd=0.0, ks=1.0)
    m = linear_rig_mueller(flat(normal), flat(light), flat(view), alpha=0.3, eta=eta, components=(component,),
                           stage_zero_axis=STAGE, camera_x_axis=CAM, **kw)  # (P, 3, 3)
    m = np.moveaxis(m, 0, -1).reshape(3, 3, h, w)
    return np.asarray(albedo, np.float64)[:, None, None, None, None] * m[None]


def _frames(truth: np.ndarray, rng: np.random.Generator, peak: float = 2000.0):
    """Noisy analyzer samples of two states ``(2, C, 4, H, W)`` and their variances, the truth
    scaled so its brightest ``m00`` is ``peak``."""
    scale = peak / truth[:, 0, 0].max()
    clean = forward_measurements(truth * scale, STATES)
    var = GAIN * np.clip(clean, 0, None) + READ
    return (clean + rng.normal(size=clean.shape) * np.sqrt(var)) / scale, var / scale**2, scale


def _geometry(view, light, normal=None) -> dg.DiffuseGeometry:
    return dg.DiffuseGeometry(view=view, light=light, stage_zero_axis=STAGE, camera_x_axis=CAM, normal_guess=normal)


def test_state_stokes_is_the_weighted_inverse_of_the_analyzer_rows():
    """Equal variances: the ideal pseudo-inverse; the information is ``A^T A / v``; a sample
    missing (invalid) leaves the pixel out (NaN, ``ok`` False)."""
    rng = np.random.default_rng(0)
    stokes = rng.normal(size=(2, 3, 4, 5)) + np.array([3.0, 0.0, 0.0])[None, :, None, None]
    a = ideal_analyzer_matrix()
    meas = np.einsum("ja,cahw->cjhw", a, stokes)
    var = np.full(meas.shape, 0.04)
    valid = np.ones(meas.shape, bool)
    valid[1, 2, 3, 4] = False
    s, info, ok = dt.state_stokes(meas, var, valid)
    keep = np.broadcast_to(ok[:, None], s.shape)
    assert np.allclose(s[keep], stokes[keep], atol=1e-12)
    assert np.allclose(info[0, ..., 0, 0], a.T @ a / 0.04)
    assert not ok[1, 3, 4] and ok.sum() == ok.size - 1 and np.isnan(s[1, :, 3, 4]).all()
    # unequal variances: the generalized least squares, exact on noise-free samples
    var = rng.uniform(0.01, 1.0, meas.shape)
    s, _, _ = dt.state_stokes(meas, var)
    assert np.allclose(s, stokes, atol=1e-12)


def test_state_stokes_takes_a_calibrated_analyzer_per_pixel():
    """Per-pixel rows ``(C, 4, 3, H, W)`` (a calibrated analyzer: gains, angles and
    diattenuations off the ideal) give, pixel by pixel, the weighted least squares of that
    pixel's own rows; the ideal rows broadcast give the shared rows' result exactly."""
    rng = np.random.default_rng(1)
    c, h, w = 2, 3, 4
    stokes = rng.normal(size=(c, 3, h, w)) + np.array([3.0, 0.0, 0.0])[None, :, None, None]
    ideal = ideal_analyzer_matrix()
    rows = ideal[None, :, :, None, None] * rng.uniform(0.9, 1.1, (c, 4, 1, h, w))
    rows[:, :, 1:] += rng.normal(0, 0.03, (c, 4, 2, h, w))
    meas = np.einsum("cjahw,cahw->cjhw", rows, stokes) + rng.normal(0, 0.01, (c, 4, h, w))
    var = rng.uniform(0.01, 0.1, meas.shape)
    s, info, ok = dt.state_stokes(meas, var, analyzer_rows=rows)
    assert ok.all()
    for ci, y, x in np.ndindex(c, h, w):
        a, wt = rows[ci, :, :, y, x], 1.0 / var[ci, :, y, x]
        q = a.T @ (wt[:, None] * a)
        np.testing.assert_allclose(info[ci, :, :, y, x], q, rtol=1e-12)
        np.testing.assert_allclose(s[ci, :, y, x], np.linalg.solve(q, a.T @ (wt * meas[ci, :, y, x])), rtol=1e-10)
    same = dt.state_stokes(meas, var, analyzer_rows=np.broadcast_to(ideal[None, :, :, None, None], rows.shape))
    for got, want in zip(same, dt.state_stokes(meas, var)):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="analyzer_rows must be"):
        dt.state_stokes(meas, var, analyzer_rows=rows[:, :, :, :1])


def test_degrees_of_freedom():
    assert dt.degrees_of_freedom(3) == 13 and dt.degrees_of_freedom(1) == 3


def _test(truth, view, light, rng, etas=(1.5,), mask=None, peak=2000.0):
    meas, var, _ = _frames(truth, rng, peak)
    return dt.test_diffuse(STATES, meas, var, None, _geometry(view, light), etas=etas, mask=mask)


def test_noise_free_diffuse_pixels_fit_within_the_grid():
    """Noise-free diffuse samples: the statistic is the grid's misfit alone, far below one degree
    of freedom's worth of noise, and the normal it finds is the truth's to about a degree."""
    view, light, normal = _surface(12, 12, seed=1)
    truth = _blocks(view, light, normal, 1.5, "diffuse", [0.9, 0.6, 0.4])
    scale = 2000.0 / truth[:, 0, 0].max()
    clean = forward_measurements(truth * scale, STATES)
    var = GAIN * clean + READ
    res = dt.test_diffuse(STATES, clean / scale, var / scale**2, None, _geometry(view, light), etas=(1.5,))
    assert res.tested.all() and res.accepted.all()
    assert np.nanmax(res.statistic) < 0.5
    angle = np.degrees(np.arccos(np.clip(np.sum(res.normal * normal, axis=-1), -1, 1)))
    assert np.median(angle) < 1.0
    assert np.allclose(res.albedo / res.albedo[:1], np.array([0.9, 0.6, 0.4])[:, None, None] / 0.9, rtol=1e-3)


def test_the_level_holds_on_noisy_diffuse_pixels():
    """Diffuse truth with shot and read noise: the statistic follows chi^2(13), so the test
    rejects about ``alpha`` of the pixels (5 % +- 3) and its mean is about 13."""
    view, light, normal = _surface(24, 24, seed=2)
    truth = _blocks(view, light, normal, 1.6, "diffuse", [1.0, 0.7, 0.5])
    res = _test(truth, view, light, np.random.default_rng(3), etas=(1.6,))
    t = res.statistic[res.tested]
    assert len(t) == 24 * 24
    assert 0.02 <= 1 - res.accepted[res.tested].mean() <= 0.08
    assert 12.0 <= np.mean(t) <= 14.5


def test_the_index_is_chosen_on_the_grid():
    """One refractive index per image, the grid's value of least total statistic, found by the
    coarse-then-fine search: the same as evaluating every index, near the truth's (the total is
    flat in ``eta`` within a few tenths: two states pin the diffuse term's index weakly), and the
    pixels pass at about the level."""
    view, light, normal = _surface(16, 16, seed=4)
    truth = _blocks(view, light, normal, 1.6, "diffuse", [1.0, 0.8, 0.6])
    meas, var, _ = _frames(truth, np.random.default_rng(5), 4000.0)
    geo = _geometry(view, light)
    res = dt.test_diffuse(STATES, meas, var, None, geo, etas=dg.ETAS)
    cap = chi2_critical(13, dt.CAP_QUANTILE)
    totals = [np.nansum(np.minimum(dt.test_diffuse(STATES, meas, var, None, geo, etas=(e,)).statistic, cap))
              for e in dg.ETAS]
    assert res.eta == dg.ETAS[int(np.argmin(totals))]
    assert abs(res.eta - 1.6) <= 0.2 + 1e-9
    assert res.accepted[res.tested].mean() > 0.85


def test_a_specular_block_is_rejected_where_the_samples_can_tell():
    """Fresnel reflection (the specular term: no diffuse geometry explains both states' Stokes
    vectors): where its truth is detectably off the diffuse term (its own noise-free statistic at
    least the level's 95 % power point: the false-acceptance definition), accepted at most 5 % of
    the time; the pixels where the specular lobe has faded into the noise are the others."""
    from polrig.solve.model_selection import detectable_noncentrality

    view, light, normal = _surface(16, 16, seed=6)
    truth = _blocks(view, light, normal, 1.5, "specular", [1.0, 1.0, 1.0])
    meas, var, _ = _frames(truth, np.random.default_rng(7))
    res = dt.test_diffuse(STATES, meas, var, None, _geometry(view, light), etas=(1.5,))
    assert res.tested.all()
    clean = np.stack([np.einsum("crkhw,k->crhw", truth, s) for s in STATES], axis=1)  # (C, 2, 3, H, W)
    info = np.stack([dt.state_stokes(meas[j], var[j])[1] for j in range(2)], axis=1)
    flat = lambda a: a.reshape(a.shape[:-2] + (-1,))  # noqa: E731
    lam, _, _ = dt.diffuse_statistic(flat(clean), flat(info), STATES, view.reshape(-1, 3), light, 1.5, STAGE, CAM)
    detectable = (lam >= detectable_noncentrality(13)).reshape(16, 16)
    assert detectable.mean() > 0.7
    assert res.accepted[detectable].mean() <= 0.05
    assert np.median(res.statistic[detectable]) > 5 * chi2_critical(13, 0.05)


def test_untested_pixels_and_bad_arguments():
    view, light, normal = _surface(6, 6, seed=8)
    truth = _blocks(view, light, normal, 1.5, "diffuse", [1.0, 1.0, 1.0])
    mask = np.zeros((6, 6), bool)
    mask[2:4, 2:5] = True
    res = _test(truth, view, light, np.random.default_rng(9), mask=mask)
    assert (res.tested == mask).all() and np.isnan(res.statistic[~mask]).all() and not res.accepted[~mask].any()
    none = _test(truth, view, light, np.random.default_rng(9), mask=np.zeros((6, 6), bool))
    assert not none.tested.any() and none.eta is None
    meas, var, _ = _frames(truth, np.random.default_rng(1))
    with pytest.raises(ValueError, match="two states"):
        dt.test_diffuse(np.stack([_state(0), _state(60), _state(120)]), meas, var, None, _geometry(view, light))
    with pytest.raises(ValueError, match="alpha"):
        dt.test_diffuse(STATES, meas, var, None, _geometry(view, light), alpha=1.5)


def _hybrid(truth, meas, var, prior_mean, prior_sigma):
    from polrig.solve.hybrid import solve_hybrid

    return solve_hybrid(STATES, meas, var, None, prior_mean=prior_mean, prior_sigma=prior_sigma, seen_state=0,
                        dtype=np.float64)


def _frames_and_prior(truth: np.ndarray, rng: np.random.Generator):
    """:func:`_frames` of ``truth`` and a prior off along the direction the two states leave open
    (a network's error where they do not look), 5 % of the brightest ``m00``: ``meas, var,
    prior, sigma``."""
    meas, var, _ = _frames(truth, rng)
    u = dg.unobserved_direction(STATES)
    err = rng.normal(0, 0.05, truth.shape[:2] + truth.shape[3:]) * truth[:, 0, 0].max()
    prior = truth + err[:, :, None] * u[None, None, :, None, None]
    return meas, var, prior, np.full(truth.shape, 0.05 * truth[:, 0, 0].max())


def _scene(seed: int, h: int = 16, w: int = 16):
    """Diffuse truth, its frames and a prior off along the open direction
    (:func:`_frames_and_prior`)."""
    view, light, normal = _surface(h, w, seed)
    truth = _blocks(view, light, normal, 1.5, "diffuse", [0.9, 0.7, 0.5])
    meas, var, prior, sigma = _frames_and_prior(truth, np.random.default_rng(seed + 100))
    return truth, meas, var, prior, sigma, _geometry(view, light, normal)


def test_decided_takes_the_callers_choice_exactly():
    """``select_models(decided=...)``: the rank-one model where the caller's test accepted (and
    the fit is finite), the full block elsewhere, whatever this module's own statistic says."""
    truth, meas, var, prior, sigma, _ = _scene(seed=10, h=6, w=6)
    r = _hybrid(truth, meas, var, prior, sigma)
    decided = np.zeros((6, 6), bool)
    decided[::2] = True
    out, maps = select_models(STATES, meas, var, None, None, r, SelectionOptions(models=("rank_one",)),
                              prior=(prior, sigma), seen_state=0, decided=decided[None])
    code = maps.code
    from polrig.solve.reduced_models import MODEL_CODES

    rank_one = {v: k for k, v in MODEL_CODES.items()}["rank_one"]
    assert (code[:, decided] == rank_one).mean() > 0.95
    assert (code[:, ~decided] == 0).all()
    assert np.array_equal(out.mueller[:, :, :, ~decided], r.mueller[:, :, :, ~decided])


def test_completion_after_the_test_recovers_the_open_direction():
    """Diffuse truth, a prior off along the direction two states leave open: where the samples
    accept the diffuse term (about 95 % of the pixels), the completed result's error along that
    direction is a fraction of the hybrid's, and the whole block's error falls."""
    truth, meas, var, prior, sigma, geo = _scene(seed=12)
    r = _hybrid(truth, meas, var, prior, sigma)
    out, test, completed = dt.complete_tested_diffuse(r, STATES, meas, var, None, geo, prior=(prior, sigma))
    assert test.accepted.mean() > 0.85
    assert (completed == test.accepted[None]).mean() > 0.95
    u = dg.unobserved_direction(STATES)
    along = lambda m: np.einsum("crk...,k->cr...", m, u)[..., test.accepted]  # noqa: E731
    before = np.sqrt(np.mean((along(r.mueller) - along(truth)) ** 2))
    after = np.sqrt(np.mean((along(out.mueller.astype(np.float64)) - along(truth)) ** 2))
    assert after < before / 3
    assert np.sqrt(np.mean((out.mueller - truth) ** 2)) < np.sqrt(np.mean((r.mueller - truth) ** 2))


def test_neighbour_bias_is_the_chosen_neighbours_mean_deviation():
    """Against a loop over every pixel: the mean deviation over the chosen pixels of the same
    colour in the window (clipped at the edges), 0 where not chosen; a window of one is the
    pixel's own deviation."""
    rng = np.random.default_rng(3)
    dev = rng.normal(size=(2, 3, 3, 9, 11))
    chosen = rng.random((2, 9, 11)) < 0.6
    got = dt.neighbour_bias(dev, chosen[:, None, None], window=5)
    want = np.zeros_like(got)
    for c, y, x in np.ndindex(2, 9, 11):
        if chosen[c, y, x]:
            ys, xs = slice(max(0, y - 2), y + 3), slice(max(0, x - 2), x + 3)
            want[c, :, :, y, x] = dev[c, :, :, ys, xs][..., chosen[c, ys, xs]].mean(axis=-1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    assert dt.neighbour_bias(dev, chosen[:, None, None], window=1) == pytest.approx(np.where(chosen[:, None, None], dev, 0))
    # one plane with its own (H, W) choice: the same numbers as the stack's
    np.testing.assert_array_equal(dt.neighbour_bias(dev[1, 2, 0], chosen[1], window=5), got[1, 2, 0])


def _coverage_with_and_without_neighbours(monkeypatch, bias: float):
    """Diffuse truth with ``m11`` and ``m22`` raised by ``bias`` times ``m00`` (as a weak specular
    reflection adds; no rank-one block holds it), its frames and a prior off along the open
    direction: the share accepted, and of the accepted pixels' elements (all, ``m11``) the share
    within 2 sigma, with the neighbours' bias and with each pixel's own deviation alone."""
    view, light, normal = _surface(24, 24, 21)
    truth = _blocks(view, light, normal, 1.5, "diffuse", [0.9, 0.7, 0.5])
    truth[:, 1, 1] += bias * truth[:, 0, 0]
    truth[:, 2, 2] += bias * truth[:, 0, 0]
    meas, var, prior, sigma = _frames_and_prior(truth, np.random.default_rng(121))
    geo = _geometry(view, light, normal)
    r = _hybrid(truth, meas, var, prior, sigma)

    def within():
        out, test, _ = dt.complete_tested_diffuse(r, STATES, meas, var, None, geo, prior=(prior, sigma))
        ok = (np.abs(out.mueller - truth) <= 2 * out.sigma)[..., test.accepted]
        return test.accepted.mean(), ok.mean(), ok[:, 1, 1].mean()

    accepted, *neighbours = within()
    with monkeypatch.context() as m:
        m.setattr(dt, "neighbour_bias", lambda d, chosen: d)
        _, *alone = within()
    return accepted, neighbours, alone


def test_the_sigma_holds_a_bias_the_test_cannot_detect(monkeypatch):
    """A bias of 1.5 % of ``m00`` in ``m11``: the test still accepts most pixels; with each
    pixel's own deviation alone ``m11`` is within 2 sigma on about 82 % of them, with the
    neighbours' bias as often as a sigma should say."""
    accepted, (_, m11), (_, m11_alone) = _coverage_with_and_without_neighbours(monkeypatch, 0.015)
    assert accepted > 0.85
    assert m11_alone < 0.9
    assert 0.93 <= m11 <= 0.99


def test_the_neighbours_add_nothing_where_the_model_holds(monkeypatch):
    """Exact diffuse truth: the neighbours' mean deviation is noise averaged down, and the
    sigma is as wide as each pixel's own deviation makes it (within half a point)."""
    _, (every, _), (every_alone, _) = _coverage_with_and_without_neighbours(monkeypatch, 0.0)
    assert abs(every - every_alone) < 0.005


def _diffuse_and_specular(seed: int, share: float, h: int = 16, w: int = 16):
    """Diffuse truth plus Baek's specular term at ``share`` of each pixel's diffuse ``m00`` (the
    unit specular block of :func:`polrig.solve.diffuse_geometry.specular_block`, the same share
    in every colour), with its view, light and the specular albedo ``(C, H, W)``."""
    view, light, normal = _surface(h, w, seed)
    diffuse = _blocks(view, light, normal, 1.5, "diffuse", [1.0, 0.7, 0.5])
    unit = dg.specular_block(np.broadcast_to(light, view.shape).reshape(-1, 3), view.reshape(-1, 3), 1.5, STAGE, CAM)
    unit = np.moveaxis(unit, 0, -1).reshape(3, 3, h, w)
    ks = share * diffuse[:, 0, 0]
    return diffuse + ks[:, None, None] * unit[None], view, light, ks


def test_the_specular_block_is_set_by_the_light_view_and_index_alone():
    """Baek's specular block over its ``m00`` is the same at any normal (the normal and the
    roughness only scale it), so the test's unit block, evaluated at the half vector, is the
    pBRDF's at the surface's own normal."""
    view, light, normal = _surface(8, 8, seed=13)
    flat = lambda a: np.broadcast_to(a, (8, 8, 3)).reshape(-1, 3)  # noqa: E731
    spec = _blocks(view, light, normal, 1.7, "specular", [1.0]).reshape(3, 3, -1)
    unit = dg.specular_block(flat(light), flat(view), 1.7, STAGE, CAM)
    lit = spec[0, 0] > 1e-12
    assert lit.mean() > 0.5
    np.testing.assert_allclose(np.moveaxis(spec[..., lit] / spec[0, 0, lit], -1, 0), unit[lit], rtol=1e-9, atol=1e-12)
    assert np.allclose(unit[:, 0, 0], 1.0)


def test_with_the_specular_term_the_level_holds_on_diffuse_pixels():
    """Diffuse truth: with the specular term the test still rejects about ``alpha`` of the
    pixels, and the term is significant on few (its test's level, halved by ``k_s >= 0``)."""
    view, light, normal = _surface(24, 24, seed=2)
    truth = _blocks(view, light, normal, 1.6, "diffuse", [1.0, 0.7, 0.5])
    meas, var, _ = _frames(truth, np.random.default_rng(3))
    res = dt.test_diffuse(STATES, meas, var, None, _geometry(view, light), etas=(1.6,), specular=True)
    assert 0.02 <= 1 - res.accepted[res.tested].mean() <= 0.08
    assert ((res.specular_albedo > 0).any(axis=0) & res.tested).mean() <= 0.08
    assert res.df == 13 and dt.degrees_of_freedom(3, True) == 10


def test_a_diffuse_and_specular_truth_is_accepted_with_its_specular_albedo():
    """Diffuse plus a specular term at 10 % of the diffuse ``m00``: the diffuse term alone is
    rejected almost everywhere; with the specular term the test accepts at about its level, the
    term is significant nearly everywhere and its albedo is the truth's within its noise."""
    truth, view, light, ks = _diffuse_and_specular(14, 0.10)
    meas, var, _ = _frames(truth, np.random.default_rng(15))
    geo = _geometry(view, light)
    alone = dt.test_diffuse(STATES, meas, var, None, geo, etas=(1.5,))
    res = dt.test_diffuse(STATES, meas, var, None, geo, etas=(1.5,), specular=True)
    assert alone.accepted.mean() < 0.3 and alone.specular_albedo is None
    assert res.accepted.mean() > 0.9
    used = (res.specular_albedo > 0).all(axis=0) & res.accepted
    assert used.mean() > 0.75
    z = (res.specular_albedo - ks)[:, used] / res.specular_sigma[:, used]
    assert np.mean(np.abs(z) <= 2) > 0.9 and abs(np.median(z)) < 0.3


def test_the_completion_with_the_specular_term():
    """The same truth, two states and a prior off along the open direction: taking the fitted
    specular term off before the rank-one estimate and the completion, and back after, brings
    the block's error to a fraction of the diffuse route's, with the sigma covering it."""
    truth, view, light, _ = _diffuse_and_specular(16, 0.10)
    meas, var, prior, sigma = _frames_and_prior(truth, np.random.default_rng(17))
    geo = _geometry(view, light)
    r = _hybrid(truth, meas, var, prior, sigma)
    rmse = lambda m: np.sqrt(np.mean((m - truth) ** 2))  # noqa: E731
    alone, _, _ = dt.complete_tested_diffuse(r, STATES, meas, var, None, geo, prior=(prior, sigma))
    out, test, completed = dt.complete_tested_diffuse(r, STATES, meas, var, None, geo, prior=(prior, sigma),
                                                      specular=True)
    assert test.accepted.mean() > 0.9 and completed[:, test.accepted].mean() > 0.9
    assert rmse(out.mueller) < 0.5 * rmse(alone.mueller) and rmse(out.mueller) < 0.5 * rmse(r.mueller)
    inside = np.abs(out.mueller - truth) <= 2 * out.sigma
    assert inside[..., test.accepted].mean() >= 0.93


def test_the_decision_takes_the_specular_term_only_where_significant_and_rejects_what_has_no_fit():
    """:func:`polrig.solve.diffuse_test.decide` against its rule written out: the specular term
    where ``T - T_s`` passes ``chi^2(C)`` at the specular level, then the chosen model's own
    critical value (``chi^2(4C - 2)`` with it, ``chi^2(5C - 2)`` without); a statistic that is
    infinite (no valid normal) or NaN is never accepted, and without ``T_s`` the diffuse term
    alone decides."""
    from polrig.solve.diffuse_test import SPECULAR_LEVEL, decide, degrees_of_freedom
    from polrig.solve.model_selection import chi2_critical

    c = 3
    crit_d, crit_s = chi2_critical(degrees_of_freedom(c), 0.05), chi2_critical(degrees_of_freedom(c, True), 0.05)
    gap = chi2_critical(c, SPECULAR_LEVEL)
    t_d = np.array([crit_d - 1, crit_d + 1, crit_s + gap + 2, crit_s + gap + 2, np.inf, np.nan, np.inf])
    t_s = np.array([crit_d - 1, crit_d + 1 - gap / 2, crit_s - 1, crit_s + 1, np.inf, np.nan, crit_s - 1])
    accepted, significant = decide(t_d, t_s, c, 0.05)
    assert significant.tolist() == [False, False, True, True, False, False, True]
    assert accepted.tolist() == [True, False, True, False, False, False, True]
    alone, none = decide(t_d, None, c, 0.05)
    assert alone.tolist() == [True, False, False, False, False, False, False] and not none.any()


def test_a_specular_term_not_taken_enters_the_sigma(monkeypatch):
    """Diffuse truth plus a weak specular term (3 % of the diffuse ``m00``), too weak for its test
    at two thirds of the pixels: there the diffuse estimate misses it in ``m11`` and ``m22``, and
    the sigma holds that bias only with the term's would-be part added (``specular_unused``, 0
    where it was taken)."""
    truth, view, light, _ = _diffuse_and_specular(23, 0.03, 24, 24)
    meas, var, prior, sigma = _frames_and_prior(truth, np.random.default_rng(24))
    geo = _geometry(view, light)
    r = _hybrid(truth, meas, var, prior, sigma)

    def within():
        out, test, _ = dt.complete_tested_diffuse(r, STATES, meas, var, None, geo, prior=(prior, sigma),
                                                  specular=True)
        where = test.accepted[None] & (test.specular_albedo == 0)  # (C, H, W): the term not taken
        ok = (np.abs(out.mueller - truth) <= 2 * out.sigma).transpose(1, 2, 0, 3, 4)[:, :, where]
        return test, where, out, (ok[1, 1].mean() + ok[2, 2].mean()) / 2

    test, where, out, with_term = within()
    assert where.mean() > 0.5
    assert np.all(test.specular_unused[test.specular_albedo > 0] == 0) and np.all(test.specular_unused >= 0)
    assert (test.specular_unused[where] > 0).mean() > 0.5
    fitted = dt.test_diffuse
    with monkeypatch.context() as m:  # the same test with the term not taken left out of the sigma
        m.setattr(dt, "test_diffuse", lambda *a, **k: (lambda t: t._replace(
            specular_unused=np.zeros_like(t.specular_unused)))(fitted(*a, **k)))
        _, _, plain, without = within()
    assert without < 0.91 and with_term >= max(0.93, without + 0.03)
    np.testing.assert_array_equal(out.mueller, plain.mueller)  # the estimate is the same
