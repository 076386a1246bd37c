"""Lower-order models from two polarizer states (polrig.solve.model_selection, "At any rank"):
the samples observe six of the block's nine directions and the hybrid's prior completes the
other three. Hidden-truth round trips per model, the test's level and false acceptance measured
at a fixed seed, the numpy oracle, extremes, the >= 3-state path untouched by the prior, and
``polrig capture --mode hybrid --states 0,90 --models auto``, which does not offer it (its pixels
stay untested: the shipped prior's false acceptance exceeds the level)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_cli_capture import MODEL_INSTALLED, sim_config
from test_model_selection import MODEL, S4, images, noisy_samples

from polrig.optics import mueller as mu
from polrig.solve import model_selection as ms
from polrig.solve import reduced_models as rm
from polrig.solve import reference as ref
from polrig.solve.hybrid import solve_hybrid

#: an orthogonal pair in a frame turned by 20 deg (every model has the mirror minimum there)
S2 = mu.polarizer_stokes(np.radians([20, 110]), np.inf)
SCALE = 3000.0
PRIOR_SD = 150.0  # 5 % of the scale: a prior a little better than the shipped network's


def prior_error(rng, sd: np.ndarray, s_seen) -> np.ndarray:
    """A network's error as the hybrid models it (:mod:`polrig.solve.hybrid`): per row, Gaussian
    in the plane the seen frame leaves unobserved with the covariance whose precision is the
    prior's ``P_r`` (:func:`polrig.solve.hybrid.unobserved_precision`); none along the seen
    state (the network reproduces its frame). ``sd`` ``(C, 3, 3, H, W)``."""
    from polrig.solve.hybrid import unobserved_precision

    p_rows = unobserved_precision(np.moveaxis(sd, (1, 2), (-2, -1)), s_seen)  # (C, H, W, 3, 3, 3)
    w, v = np.linalg.eigh(p_rows)
    scale = np.where(w > 1e-12 * w.max(axis=-1, keepdims=True), 1.0 / np.sqrt(np.where(w > 0, w, 1.0)), 0.0)
    z = rng.normal(size=w.shape)
    err = np.einsum("...ij,...j->...i", v, scale * z)  # (C, H, W, row, 3)
    return np.moveaxis(err, (-2, -1), (1, 2))


def two_state_case(rng, truth, *, s=S2, prior_sd=PRIOR_SD, valid=None):
    """Noisy samples of ``truth`` at states ``s``, a prior calibrated in the hybrid's model
    (:func:`prior_error`, sigma ``prior_sd`` per element), the hybrid solve and the selection
    with that prior."""
    meas, var = noisy_samples(rng, truth, s)
    sd = np.broadcast_to(np.asarray(prior_sd, float), truth.shape)
    mean = truth + prior_error(rng, sd, s[0])
    post = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sd, seen_state=0,
                        dtype=np.float64)
    sel, maps = ms.select_models(s, meas, var, valid, None, post, prior=(mean, sd), seen_state=0)
    return post, sel, maps, (meas, var, mean, sd)


def posterior(truth, meas, var, mean, sd, s=S2):
    """The hybrid's posterior system (``N'``, ``m'``) of every pixel (one colour)."""
    h, w = truth.shape[-2:]
    rs = ms.row_space_equations(s, meas, var, None, None, 0, np.arange(h * w))
    assert (rs.rank == 6).all()
    mu_ = mean[0].reshape(9, -1).T
    sd_ = np.broadcast_to(sd, truth.shape)[0].reshape(9, -1).T
    return ms.posterior_system(rs.normal, rs.m_hat, mu_, sd_, s[0])


# ------------------------------------------------------------------ the statistic's level
@pytest.mark.parametrize("name", ["unpolarizing", "depolarizer", "diattenuator", "retarder", "fresnel"])
def test_the_true_models_statistic_has_the_tests_level(name):
    """Truth exactly of the model, sensor noise, a calibrated prior: the model's statistic on
    the completed system exceeds the chi^2(9 - k) critical value at about alpha = 5 % (exact
    for the linear unpolarizing model; the depolarizer, the lower of two subspaces, and the
    nonlinear models to first order). Measured at this seed: 5.3, 4.3, 4.5, 4.7, 4.6 %."""
    rng = np.random.default_rng(11)
    truth = images(rm.random_blocks(rng, name, 2000, SCALE), 40, 50)
    _, _, _, (meas, var, mean, sd) = two_state_case(rng, truth)
    normal, m_c = posterior(truth, meas, var, mean, sd)
    _, q, _ = rm.fit_model(MODEL[name], m_c, normal)
    rate = np.mean(q > ms.chi2_critical(9 - MODEL[name].n_params, 0.05))
    lo, hi = (0.03, 0.07) if name == "unpolarizing" else (0.02, 0.09)
    assert lo <= rate <= hi, rate


# ------------------------------------------------------------------ hidden-truth round trips
@pytest.mark.parametrize("name", [m.name for m in rm.MODELS])
def test_two_state_round_trip_per_model(name):
    """Truth of each model at two states: a reduced model explains about all pixels (the true
    one, or one that nests it or matches it on the samples), the estimate beats the hybrid's
    RMSE and covers the truth within 2 sigma at about 95 %. Measured at this seed, per model
    in MODELS order: reduced 99, 95, 97, 98, 96, 96 %; RMSE 0.58, 0.60, 0.53, 0.72, 0.62, 0.69
    of the hybrid's; within 2 sigma 94.9, 93.0, 91.8, 93.0, 93.4, 94.9 % (the hybrid's 95-96 %)."""
    rng = np.random.default_rng(5)
    truth = images(rm.random_blocks(rng, name, 600, SCALE), 20, 30)
    post, sel, maps, _ = two_state_case(rng, truth)
    code = maps.code[0]
    assert not (code == ms.UNTESTED).any()
    assert np.mean(code != 0) >= 0.9
    rmse = lambda m: np.sqrt(np.mean((m - truth) ** 2))
    assert rmse(sel.mueller) < 0.85 * rmse(post.mueller)
    inside = np.mean(np.abs(sel.mueller - truth) <= 2 * sel.sigma)
    assert 0.88 <= inside <= 0.995, inside
    # the chosen model's statistic is within its critical value
    for model in rm.MODELS:
        chosen = code == model.code
        assert (maps.statistic[0][chosen] <= ms.chi2_critical(9 - model.n_params, 0.05) + 1e-6).all()


def test_false_acceptance_where_the_truth_is_detectably_off_every_model():
    """Full blocks and perturbed model blocks at two states: where the truth's noncentrality
    under the completed design (noise-free samples, prior mean at the truth) is at least the
    detectable one for every candidate, a reduced model is chosen at most 5 % of the time; the
    full-model truths are mostly left full."""
    rng = np.random.default_rng(17)
    p = 2400
    names = [m.name for m in rm.MODELS]
    base = np.concatenate([rm.random_blocks(rng, names[i % 6], p // 6, SCALE) for i in range(6)])
    pert = rm.random_blocks(rng, "full", p)
    blocks = base + rng.uniform(0, 1500, (p, 1)) * pert / np.linalg.norm(pert, axis=1, keepdims=True)
    truth = images(blocks, 40, 60)
    _, _, maps, _ = two_state_case(rng, truth)
    clean = ref.forward_measurements(truth, S2)
    var = 4.0 + np.clip(clean, 0, None) / 0.5
    normal, m_c = posterior(truth, clean, var, truth, PRIOR_SD)
    np.testing.assert_allclose(m_c, truth[0].reshape(9, -1).T, atol=1e-6 * SCALE)
    detectable = np.ones(p, bool)
    for model in rm.MODELS:
        _, lam, _ = rm.fit_model(model, m_c, normal)
        detectable &= lam >= ms.detectable_noncentrality(9 - model.n_params)
    code = maps.code[0].ravel()
    assert detectable.sum() > 500 and (~detectable).sum() > 500
    assert np.mean(code[detectable] != 0) <= 0.05

    full = images(rm.random_blocks(rng, "full", 600, SCALE), 20, 30)
    _, _, maps, _ = two_state_case(rng, full)
    assert np.mean(maps.code == 0) >= 0.9


# ------------------------------------------------------------------ the oracle, the other path
def test_two_state_selection_equals_the_one_with_the_numpy_oracle(monkeypatch):
    """The compiled fits against the numpy oracle on the hybrid's posterior systems: the same
    codes, statistics within 1e-4, estimates and sigma within 1e-6 of the scale."""
    from polrig.solve._reduced_numpy import fit_model_numpy

    rng = np.random.default_rng(23)
    names = ["full", *(m.name for m in rm.MODELS)]
    truth = images(np.concatenate([rm.random_blocks(rng, n, 100, SCALE) for n in names]), 20, 35)
    meas, var = noisy_samples(rng, truth, S2)
    sd = np.full(truth.shape, PRIOR_SD)
    mean = truth + prior_error(rng, sd, S2[0])
    post = solve_hybrid(S2, meas, var, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64)
    sel, maps = ms.select_models(S2, meas, var, None, None, post, prior=(mean, sd), seen_state=0)
    monkeypatch.setattr(ms, "fit_model", fit_model_numpy)
    sel_o, maps_o = ms.select_models(S2, meas, var, None, None, post, prior=(mean, sd), seen_state=0)
    np.testing.assert_array_equal(maps.code, maps_o.code)
    assert 0.3 < np.mean(maps.code != 0) < 0.95
    np.testing.assert_allclose(maps.statistic, maps_o.statistic, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(sel.mueller, sel_o.mueller, rtol=0, atol=1e-6 * SCALE)
    np.testing.assert_allclose(sel.sigma, sel_o.sigma, rtol=0, atol=1e-6 * SCALE)


def test_the_prior_leaves_pixels_the_samples_determine_as_they_were():
    """Four states: the selection with the prior given is the one without it, bit for bit."""
    rng = np.random.default_rng(2)
    names = ["full", *(m.name for m in rm.MODELS)]
    truth = images(np.concatenate([rm.random_blocks(rng, n, 30, SCALE) for n in names]), 10, 21)
    meas, var = noisy_samples(rng, truth, S4)
    full = ref.solve_reference(S4, meas, var, dtype=np.float64)
    a, maps_a = ms.select_models(S4, meas, var, None, None, full)
    b, maps_b = ms.select_models(S4, meas, var, None, None, full,
                                 prior=(truth, np.full(truth.shape, PRIOR_SD)))
    for name in ("mueller", "sigma", "residual", "mask"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("code", "statistic", "p_value"):
        np.testing.assert_array_equal(getattr(maps_a, name), getattr(maps_b, name), err_msg=name)


# ------------------------------------------------------------------ extremes
def test_a_state_set_of_rank_below_six_or_no_prior_is_untested():
    """Two identical states (rank 3), or two states without a prior: untested, untouched."""
    rng = np.random.default_rng(4)
    truth = images(rm.random_blocks(rng, "unpolarizing", 6, SCALE), 2, 3)
    same = mu.polarizer_stokes(np.radians([20, 20]), np.inf)
    post, sel, maps, _ = two_state_case(rng, truth, s=same)
    assert np.all(maps.code == ms.UNTESTED) and np.isnan(maps.statistic).all()
    np.testing.assert_array_equal(sel.mueller, post.mueller)
    post, _, _, (meas, var, _, _) = two_state_case(rng, truth)
    sel, maps = ms.select_models(S2, meas, var, None, None, post)
    assert np.all(maps.code == ms.UNTESTED)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-3, 1.0, 30.0, 3000.0, 6e4]),
       drop=st.floats(0.0, 0.5), prior_kind=st.sampled_from(["calibrated", "zero", "inf", "mixed"]))
def test_any_two_state_scene_gives_finite_results_and_known_codes(seed, scale, drop, prior_kind):
    """No light to near saturation, samples masked at random, priors calibrated, absent (sigma 0
    or inf) or absent at some elements: finite estimates where the hybrid's are, codes from the
    table, untested pixels untouched, a chosen model's statistic within its critical value;
    a pixel without a prior at every element is untested."""
    rng = np.random.default_rng(seed)
    names = ["full", *MODEL]
    truth = images(np.concatenate([rm.random_blocks(rng, n, 3, scale) for n in names]), 3, len(names))
    meas, var = noisy_samples(rng, truth, S2)
    valid = rng.random(meas.shape) >= drop
    sd = np.full(truth.shape, 0.05 * max(scale, 1e-6))
    if prior_kind == "zero":
        sd[:] = 0.0
    elif prior_kind == "inf":
        sd[:] = np.inf
    elif prior_kind == "mixed":
        sd[:, 0, 2] = np.inf
    mean = truth + rng.normal(size=truth.shape) * np.where(np.isfinite(sd), sd, 0.0)
    post = solve_hybrid(S2, meas, var, valid, prior_mean=mean, prior_sigma=sd, seen_state=0,
                        dtype=np.float64)
    sel, maps = ms.select_models(S2, meas, var, valid, None, post, prior=(mean, sd), seen_state=0)
    assert set(np.unique(maps.code)) <= {*rm.MODEL_CODES, ms.UNTESTED}
    untested = maps.code[0] == ms.UNTESTED
    np.testing.assert_array_equal(sel.mueller[0][:, :, untested], post.mueller[0][:, :, untested])
    tested = ~untested
    assert np.isfinite(sel.mueller[0][:, :, tested]).all() and np.isfinite(sel.sigma[0][:, :, tested]).all()
    if prior_kind != "calibrated":
        assert untested.all()
    for model in rm.MODELS:
        chosen = maps.code == model.code
        assert (maps.statistic[chosen] <= ms.chi2_critical(9 - model.n_params, 0.05) + 1e-6).all()


# ------------------------------------------------------------------ the CLI
@pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")
def test_hybrid_two_states_models_auto_is_refused_in_captures_and_revisions(tmp_path, capsys):
    """``polrig capture --mode hybrid --states 0,90 --models auto``, and ``reconstruct`` of a
    two-state session with it: refused in one line naming ``--models`` before anything is
    written, pointing at ``--models diffuse``. Captures do not pass the prior to the selection
    (with the shipped network's prior the two-state test's false acceptance exceeds its level,
    ``polrig.solve.radiometry.reference_from_frames``), so every pixel would stay untested."""
    from polrig.app.session import Session
    from polrig.cli import main

    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    hybrid = ["--mode", "hybrid", "--device", "cpu"]
    rc = main(["capture", "--poses", "0", *hybrid, "--states", "0,90", "--models", "auto", "--config", str(cfg),
               "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and not out.exists(), err
    assert "--models auto: model selection tests the block on the samples alone" in err and "--models diffuse" in err
    assert main(["capture", "--poses", "0", *hybrid, "--states", "0,90", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    before = (out / "session.json").read_bytes()
    capsys.readouterr()
    rc = main(["reconstruct", str(out), *hybrid, "--models", "auto", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--models auto" in err and (out / "session.json").read_bytes() == before, err
    assert Session.open(out).manifest["revisions"] == []


def test_selection_does_not_depend_on_chunks_or_threads(monkeypatch):
    """Both paths (four states, full rank; two states with the prior, on the posterior system)
    in small chunks, one after the other on one thread and side by side on three: the same arrays
    bit for bit (each chunk writes its own pixels)."""
    from polrig.solve import chunks

    rng = np.random.default_rng(29)
    names = ["full", *(m.name for m in rm.MODELS)]
    truth = images(np.concatenate([rm.random_blocks(rng, n, 60, SCALE) for n in names]), 12, 35)
    meas4, var4 = noisy_samples(rng, truth, S4)
    full = ref.solve_reference(S4, meas4, var4, dtype=np.float64)
    meas2, var2 = noisy_samples(rng, truth, S2)
    sd = np.full(truth.shape, PRIOR_SD)
    mean = truth + prior_error(rng, sd, S2[0])
    post = solve_hybrid(S2, meas2, var2, prior_mean=mean, prior_sigma=sd, seen_state=0, dtype=np.float64)
    cases = [((S4, meas4, var4, None, None, full), {}),
             ((S2, meas2, var2, None, None, post), dict(prior=(mean, sd), seen_state=0))]
    for args, kw in cases:
        monkeypatch.setattr(chunks, "THREADS", 1)
        one, maps_one = ms.select_models(*args, chunk_pixels=37, **kw)
        monkeypatch.setattr(chunks, "THREADS", 3)
        many, maps_many = ms.select_models(*args, chunk_pixels=37, **kw)
        assert (maps_one.code != 0).any()
        for a, b in zip((one.mueller, one.sigma, one.sigma_noise, one.residual, one.mask, maps_one.code,
                         maps_one.statistic, maps_one.p_value),
                        (many.mueller, many.sigma, many.sigma_noise, many.residual, many.mask, maps_many.code,
                         maps_many.statistic, maps_many.p_value)):
            np.testing.assert_array_equal(a, b)
