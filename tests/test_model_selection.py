"""Lower-order models of the 3x3 block and their selection by a likelihood-ratio test
(polrig.solve.reduced_models, polrig.solve.model_selection): closed forms, the test's error
rates measured at a fixed seed, extremes, banding, and the ``--models`` round trip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.errors import ConfigError
from polrig.optics import mueller as mu
from polrig.solve import model_selection as ms
from polrig.solve import reduced_models as rm
from polrig.solve import reference as ref

MODEL = {m.name: m for m in rm.MODELS}


def states(*angles_deg):
    return mu.polarizer_stokes(np.radians(angles_deg), np.inf)


S4 = states(0, 45, 90, 135)


def images(blocks: np.ndarray, h: int, w: int) -> np.ndarray:
    """``(P, 9)`` blocks -> one-colour Mueller images ``(1, 3, 3, H, W)``."""
    return blocks.reshape(h, w, 3, 3).transpose(2, 3, 0, 1)[None]


def noisy_samples(rng, truth: np.ndarray, s=S4, read_var=4.0, gain=0.5):
    """Samples with shot and read noise, variance from the same model at the truth."""
    mean = ref.forward_measurements(truth, s)
    var = read_var + np.clip(mean, 0, None) / gain
    return mean + rng.normal(size=mean.shape) * np.sqrt(var), var


def solve_and_select(truth, rng, options=None, s=S4):
    meas, var = noisy_samples(rng, truth, s)
    full = ref.solve_reference(s, meas, var, dtype=np.float64)
    sel, maps = ms.select_models(s, meas, var, None, None, full, options)
    return full, sel, maps, (meas, var)


def normal_of_truth(truth, s=S4, read_var=4.0, gain=0.5):
    """The normal matrices ``(P, 9, 9)`` of the noise model at the truth (noise-free samples)."""
    mean = ref.forward_measurements(truth, s)
    var = read_var + np.clip(mean, 0, None) / gain
    h, w = truth.shape[-2:]
    normal, m_hat, _, _ = ms.normal_equations(s, mean, var, None, None, 0, np.arange(h * w))
    return normal, m_hat


# ------------------------------------------------------------------ closed forms
@pytest.mark.parametrize("name", list(MODEL))
def test_exact_model_blocks_are_fitted_exactly(name):
    """Noise-free samples of a block of the model: the fit is the block and the statistic 0."""
    rng = np.random.default_rng(1)
    truth = images(rm.random_blocks(rng, name, 200, 1000.0), 10, 20)
    normal, m_hat = normal_of_truth(truth)
    m_fit, q, _ = rm.fit_model(MODEL[name], m_hat, normal)
    scale = np.abs(m_hat).max(axis=1, keepdims=True)
    assert np.max(np.abs(m_fit - m_hat) / scale) < 1e-6
    assert np.max(q) < 1e-6


def test_parameters_of_a_diattenuator_a_retarder_and_a_depolarizer_are_recovered():
    """Closed-form elements: an ideal linear diattenuator at 30 deg (D = 0.6), a quarter-wave
    retarder at 10 deg and a partial depolarizer, seen in frames rotated by 20 deg."""
    frame = np.radians(20.0)

    def rig(m4):  # incident frame rotated by `frame`, emergent frame not
        return (m4 @ mu.rotator(-frame))[:3, :3]

    tx, ty = 0.9, 0.9 * (1 - 0.6) / (1 + 0.6)
    diatt = rig(mu.rotated_element(np.radians(30.0), mu.diattenuator(tx, ty)))
    ret = rig(mu.retarder_at(np.radians(10.0), np.pi / 2) * 0.8)
    dep = rig(mu.partial_depolarizer(0.4) * 0.7)
    truth = images(np.stack([diatt.ravel(), ret.ravel(), dep.ravel()]) * 2000.0, 1, 3)
    normal, m_hat = normal_of_truth(truth)
    # diattenuator: D from (a, b), the axis as seen in the incident frame
    fit, q, jac = rm.fit_model(MODEL["diattenuator"], m_hat[:1], normal[:1])
    m = fit.reshape(3, 3)
    d = np.hypot(m[0, 1], m[0, 2]) / m[0, 0]
    assert d == pytest.approx(0.6, abs=1e-9) and q[0] < 1e-8
    # retarder: cos(retardance) = c / a = 0 for a quarter wave
    fit, q, _ = rm.fit_model(MODEL["retarder"], m_hat[1:2], normal[1:2])
    lower = fit.reshape(3, 3)[1:, 1:] / fit[0, 0]
    assert abs(np.linalg.det(lower)) < 1e-9 and q[0] < 1e-8  # singular values (1, cos delta)
    # depolarizer: diag(m00, p, p) in its own frames, p = 0.4
    fit, q, _ = rm.fit_model(MODEL["depolarizer"], m_hat[2:], normal[2:])
    lower = fit.reshape(3, 3)[1:, 1:] / fit[0, 0]
    assert np.linalg.svd(lower, compute_uv=False) == pytest.approx([0.4, 0.4], abs=1e-9)


def test_full_model_data_rejects_every_reduced_model():
    rng = np.random.default_rng(7)
    truth = images(rm.random_blocks(rng, "full", 400, 3000.0), 20, 20)
    full, sel, maps, _ = solve_and_select(truth, rng)
    assert np.all(maps.code == 0)
    np.testing.assert_array_equal(sel.mueller, full.mueller)
    np.testing.assert_array_equal(sel.sigma, full.sigma)


@settings(max_examples=25, deadline=None)
@given(d=st.floats(0.0, 1.0), axis=st.floats(0.0, np.pi), frame=st.floats(0.0, np.pi),
       m00=st.floats(1e-3, 1e4))
def test_diattenuators_up_to_polarizers_are_fitted(d, axis, frame, m00):
    """Noise-free ideal diattenuators, D from 0 to 1 (a polarizer) and m00 over seven decades:
    the fit reproduces the block (D = 1 is regular in the ``u, v`` parametrisation)."""
    u, v = np.sqrt(1 + d), np.sqrt(1 - d)
    block = MODEL["diattenuator"].matrix(np.array([[u, v, 2 * axis, 2 * axis + 2 * frame]])) * m00
    truth = images(block, 1, 1)
    normal, m_hat = normal_of_truth(truth)
    fit, q, _ = rm.fit_model(MODEL["diattenuator"], m_hat, normal)
    assert np.max(np.abs(fit - block)) <= 1e-6 * m00
    assert q[0] <= 1e-6 * max(1.0, np.einsum("pi,pij,pj->p", block, normal, block)[0]) ** 0 + 1e-6


# ------------------------------------------------------------------ the test's error rates
def test_chi2_tail_and_noncentrality_match_scipy():
    stats = pytest.importorskip("scipy.stats")
    x = np.array([0.0, 0.3, 2.0, 9.49, 15.0, 40.0])
    for df in range(1, 9):
        np.testing.assert_allclose(ms.chi2_sf(x, df), stats.chi2.sf(x, df), rtol=1e-9, atol=1e-14)
        assert ms.chi2_critical(df, 0.05) == pytest.approx(stats.chi2.isf(0.05, df), rel=1e-9)
    for df in range(1, 9):
        for x_ in (0.0, 0.5, 9.49, 40.0, 700.0):
            for lam_ in (0.0, 1e-3, 3.0, 18.6, 120.0, 900.0):
                assert ms._ncx2_sf(x_, df, lam_) == pytest.approx(stats.ncx2.sf(x_, df, lam_) if lam_ else
                                                                  stats.chi2.sf(x_, df), rel=1e-8, abs=1e-13)
        lam = ms.detectable_noncentrality(df)
        assert stats.ncx2.sf(stats.chi2.isf(0.05, df), df, lam) == pytest.approx(0.95, abs=1e-6)


@pytest.mark.parametrize("name", ["depolarizer", "diattenuator", "rank_one"])
def test_a_true_model_is_rejected_at_the_tests_level_and_accepting_it_lowers_the_rmse(name):
    """Where a model holds, its test rejects it in about ``alpha`` = 5 % of pixels (Wilks;
    2400 pixels: standard error 0.45 %), and the selected estimate is closer to the truth than
    the full one."""
    rng = np.random.default_rng(11)
    truth = images(rm.random_blocks(rng, name, 2400, 3000.0), 40, 60)
    full, sel, maps, (meas, var) = solve_and_select(
        truth, rng, ms.SelectionOptions(models=(name,)))
    rejected = np.mean(maps.code == 0)
    assert 0.03 <= rejected <= 0.07
    rmse = lambda m: np.sqrt(np.mean((m - truth) ** 2))  # noqa: E731
    assert rmse(sel.mueller) < 0.9 * rmse(full.mueller)
    # the delta-method sigma (sigma_noise) covers the accepted pixels' errors (elements the
    # model fixes are exact: error and sigma 0); sigma adds the selection's term
    # (m_red - m_full)^2, so it covers more, never less: 95.9-99.5 % measured here
    acc = maps.code[0] != 0
    err = np.abs(sel.mueller - truth)[0][:, :, acc]
    within = lambda sd: np.mean(err <= 2 * sd[0][:, :, acc] + 1e-9)  # noqa: E731
    assert within(sel.sigma_noise) == pytest.approx(0.9545, abs=0.02)
    assert np.all(sel.sigma[0][:, :, acc] >= sel.sigma_noise[0][:, :, acc])
    assert within(sel.sigma_noise) <= within(sel.sigma) <= 0.996
    d2 = (sel.mueller - full.mueller)[0][:, :, acc] ** 2
    np.testing.assert_allclose(sel.sigma[0][:, :, acc] ** 2, sel.sigma_noise[0][:, :, acc] ** 2 + d2,
                               rtol=1e-5, atol=1e-6)


def test_false_acceptance_is_at_most_5_percent_where_the_full_model_holds():
    """Truths off every reduced model by a controlled amount (a reduced block plus a random
    full-rank perturbation of 0 to 800 DN, the full solve's sigma being 20-40 DN): among the pixels whose
    truth the samples can tell from every candidate (noncentrality at least
    :func:`detectable_noncentrality`, power 0.95), the share where a reduced model is chosen
    is at most 5 % (measured: 0.7 %). 6000 pixels at seed 5; 2680 qualify (binomial standard
    error 0.4 % at 5 %). Of the pixels given a reduced model, the share whose truth is
    detectably off the chosen one is at most 5 % too."""
    rng = np.random.default_rng(5)
    p = 6000
    names = list(MODEL)
    base = np.concatenate([rm.random_blocks(rng, names[i % len(names)], p // len(names), 3000.0)
                           for i in range(len(names))])
    pert = rm.random_blocks(rng, "full", p, 1.0)
    size = rng.uniform(0.0, 800.0, (p, 1))  # DN: the full solve's sigma is about 20-40 DN
    truth = images(base + size * pert / np.linalg.norm(pert, axis=1, keepdims=True), 60, 100)
    full, sel, maps, _ = solve_and_select(truth, rng)
    normal, m_true = normal_of_truth(truth)
    detectable = np.ones(p, bool)
    code = maps.code.reshape(p)
    chosen_wrong = np.zeros(p, bool)
    for model in rm.MODELS:
        _, lam, _ = rm.fit_model(model, m_true, normal)
        off = lam >= ms.detectable_noncentrality(9 - model.n_params)
        detectable &= off
        chosen_wrong |= (code == model.code) & off
    # and of the pixels given a reduced model, those whose truth is detectably off that model
    assert np.mean(chosen_wrong[code != 0]) <= 0.05
    false_acceptance = np.mean(code[detectable] != 0)
    assert detectable.sum() > 1500 and (~detectable).sum() > 1500
    assert false_acceptance <= 0.05
    # below the detectable distance a reduced model is accepted often, and that is no harm:
    # the RMSE against the truth is not worse than the full solve's
    assert np.mean(code[~detectable] != 0) > 0.3
    rmse = lambda m: np.sqrt(np.mean((m - truth) ** 2))  # noqa: E731
    assert rmse(sel.mueller) <= 1.02 * rmse(full.mueller)
    # and the selected estimate's sigma still covers its errors (93.4 % within 2 sigma measured;
    # 81.0 % with the delta method's sigma_noise alone, which does not hold the model's bias)
    assert np.mean(np.abs(sel.mueller - truth) <= 2 * sel.sigma) >= 0.92


# ------------------------------------------------------------------ extremes, masks
def test_dark_nan_and_masked_pixels():
    """m00 = 0 (no light): the unpolarizing model, finite; a pixel whose samples are all NaN
    or all masked: untested, its result untouched; a pixel with one masked sample: tested."""
    rng = np.random.default_rng(3)
    blocks = rm.random_blocks(rng, "full", 6, 3000.0)
    blocks[0] = 0.0
    truth = images(blocks, 2, 3)
    meas, var = noisy_samples(rng, truth)
    meas[:, :, :, 0, 1] = np.nan
    valid = np.ones(meas.shape, bool)
    valid[:, :, :, 0, 2] = False
    valid[0, 0, 1, 1, 0] = False
    full = ref.solve_reference(S4, meas, var, valid, dtype=np.float64)
    sel, maps = ms.select_models(S4, meas, var, valid, None, full)
    code = maps.code[0]
    assert code[0, 0] == MODEL["unpolarizing"].code
    assert np.isfinite(sel.mueller).all() and np.isfinite(sel.sigma).all()
    for y, x in ((0, 1), (0, 2)):
        assert code[y, x] == ms.UNTESTED and np.isnan(maps.statistic[0, y, x])
        np.testing.assert_array_equal(sel.mueller[..., y, x], full.mueller[..., y, x])
    assert code[1, 0] == 0 and np.isfinite(maps.statistic[0, 1, 0])


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.0, 1e-3, 1.0, 30.0, 3000.0, 6e4]),
       drop=st.floats(0.0, 0.6))
def test_any_scene_gives_finite_results_and_known_codes(seed, scale, drop):
    """Random blocks of every kind from no light to near saturation, random samples masked:
    finite estimates and sigma, codes from the table, untested pixels untouched, a chosen
    model's statistic within its critical value."""
    rng = np.random.default_rng(seed)
    names = ["full", *MODEL]
    blocks = np.concatenate([rm.random_blocks(rng, n, 3, scale) for n in names])
    truth = images(blocks, 3, len(names))
    meas, var = noisy_samples(rng, truth)
    valid = rng.random(meas.shape) >= drop
    full = ref.solve_reference(S4, meas, var, valid, dtype=np.float64)
    sel, maps = ms.select_models(S4, meas, var, valid, None, full)
    assert np.isfinite(sel.mueller).all() and np.isfinite(sel.sigma).all()
    assert set(np.unique(maps.code)) <= {*rm.MODEL_CODES, ms.UNTESTED}
    untested = maps.code == ms.UNTESTED
    np.testing.assert_array_equal(sel.mueller[:, :, :, untested[0]], full.mueller[:, :, :, untested[0]])
    assert np.isnan(maps.statistic[untested]).all()
    for model in rm.MODELS:
        chosen = maps.code == model.code
        assert (maps.statistic[chosen] <= ms.chi2_critical(9 - model.n_params, 0.05) + 1e-6).all()


def test_fewer_than_three_states_are_not_tested():
    rng = np.random.default_rng(4)
    s = states(0, 60)
    truth = images(rm.random_blocks(rng, "unpolarizing", 4, 3000.0), 2, 2)
    meas, var = noisy_samples(rng, truth, s)
    mean = np.zeros((1, 3, 3, 2, 2))
    from polrig.solve.hybrid import solve_hybrid

    post = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=np.full_like(mean, 1e4),
                        seen_state=0)
    sel, maps = ms.select_models(s, meas, var, None, None, post)
    assert np.all(maps.code == ms.UNTESTED)
    np.testing.assert_array_equal(sel.mueller, post.mueller)


def test_options_are_checked_with_one_line():
    with pytest.raises(ConfigError, match="alpha"):
        ms.SelectionOptions(alpha=1.5)
    with pytest.raises(ConfigError, match="models must be some of"):
        ms.SelectionOptions(models=("mirror",))


def test_banded_frames_to_result_equals_one_selection():
    """radiometry.reference_from_frames with model selection: the same maps and estimate
    whatever the banding (pixels are independent)."""
    from polrig.sensor.layouts import get_layout
    from polrig.solve.radiometry import StateRadiance, reference_from_frames

    rng = np.random.default_rng(8)
    lay = get_layout("IMX250MZR")
    h, w = 16, 24
    truth = images(np.concatenate([rm.random_blocks(rng, "rank_one", h * w // 2, 3000.0),
                                   rm.random_blocks(rng, "full", h * w // 2, 3000.0)]), h, w)
    meas, var = noisy_samples(rng, truth)
    # superpixel mosaics: analyzer j of state k at its place in the 2x2 cell
    states_ = []
    for k in range(len(S4)):
        sig = np.zeros((2 * h, 2 * w), np.float32)
        v = np.zeros_like(sig)
        for j, (dy, dx) in enumerate(_analyzer_offsets(lay)):
            sig[dy::2, dx::2] = meas[k, 0, j]
            v[dy::2, dx::2] = var[k, 0, j]
        states_.append(StateRadiance(sig, v, np.zeros(sig.shape, bool)))
    opts = ms.SelectionOptions()
    one = reference_from_frames(states_, S4, lay, model_selection=opts, band_pixels=10 ** 6)
    banded = reference_from_frames(states_, S4, lay, model_selection=opts, band_pixels=3 * w)
    np.testing.assert_array_equal(one.models.code, banded.models.code)
    np.testing.assert_array_equal(one.mueller, banded.mueller)
    assert (one.models.code != 0).mean() > 0.3


def _analyzer_offsets(lay):
    """``(dy, dx)`` of analyzer 0/45/90/135 in the layout's 2x2 cell."""
    order = {a: i for i, a in enumerate((0, 45, 90, 135))}
    out = [None] * 4
    for (dy, dx), ang in np.ndenumerate(lay.angle_deg):
        out[order[int(ang)]] = (dy, dx)
    return out


# ------------------------------------------------------------------ the --models round trip
def test_models_flag_round_trip_capture_and_reconstruct(tmp_path, capsys):
    """``capture --models auto``: the result holds the map and its statistic, the header the
    test and its codes, the manifest a ``models`` view; ``reconstruct`` without the flag is
    the full block (no map, revision setting ``full``), ``--models auto`` records ``auto``;
    ``--models auto`` with the single-shot mode is one line, exit 2, nothing written."""
    from polrig.app.session import Session
    from polrig.cli import main
    from polrig.formats.exr import read_exr

    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "64x64"\nsensor = "imx250mzr"\nclock_speed = inf\nseed = 11\n'
                   'scene = "box"\nnoise = true\n')
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "reference", "--models", "auto",
                 "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    s = Session.open(out)
    files = s.capture(0)["files"]
    assert files["models"]["path"] == files["mueller"]["path"]
    im = read_exr(out / files["mueller"]["path"])
    assert {"model.Y", "model_chi2.Y", "model_p.Y"} <= set(im.planes)
    header = im.metadata["model_selection"]
    assert header["alpha"] == 0.05 and header["codes"]["0"] == "full"
    assert header["codes"]["255"] == "untested"
    code = im.planes["model.Y"]
    assert set(np.unique(code).astype(int)) <= {int(c) for c in header["codes"]}
    assert sum(header["counts"].values()) == code.size
    assert (code != 0).any()

    assert main(["reconstruct", str(out), "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--models", "auto", "--no-progress"]) == 0
    s = Session.open(out)
    assert [r["models"] for r in s.manifest["revisions"]] == ["full", "auto"]
    assert "models" not in s.capture(0)["revisions"]["rev1"]["files"]
    rev2 = s.capture(0)["revisions"]["rev2"]["files"]
    assert "models" in rev2
    np.testing.assert_array_equal(read_exr(out / rev2["mueller"]["path"]).planes["model.Y"], code)
    assert "model.Y" not in read_exr(out / s.capture(0)["revisions"]["rev1"]["files"]["mueller"]["path"]).planes
    assert s.verify() == []
    capsys.readouterr()

    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--models", "auto",
                 "--config", str(cfg), "--out", str(tmp_path / "ss"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("polrig: error: --models")
    assert not (tmp_path / "ss").exists()
