"""``python -m polrig.models.continuum``'s lower-order model comparison at two states
(``models_rows``, ``--models-only``): where a model holds from the hidden truth, and the
comparison end to end on a tiny set."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_models_continuum import needs_weights

from polrig.solve import reduced_models as rm


def test_model_holds_is_the_truths_distance_from_the_nearest_model():
    """Exact blocks of every model hold; full random blocks do not; a model block moved off by
    half a per cent holds, by two per cent not (relative Frobenius, every colour); off the
    object nothing."""
    from polrig.models.continuum import HOLDS_REL, model_holds

    rng = np.random.default_rng(0)
    names = [m.name for m in rm.MODELS]
    exact = np.concatenate([rm.random_blocks(rng, n, 4, 2.0) for n in names])  # (24, 9)
    full = rm.random_blocks(rng, "full", 24, 2.0)
    full_dist = np.full(24, np.inf)
    for model in rm.MODELS:
        _, q, _ = rm.fit_model(model, full, np.broadcast_to(np.eye(9), (24, 9, 9)))
        full_dist = np.fmin(full_dist, np.sqrt(q))
    far = full_dist > 2 * HOLDS_REL * np.linalg.norm(full, axis=1)
    direction = rng.normal(size=exact.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    # moved along a random direction: the distance to the model is at most the step
    near = exact + 0.5 * HOLDS_REL * np.linalg.norm(exact, axis=1, keepdims=True) * direction
    blocks = np.stack([exact, full, near])  # (3, 24, 9): three rows of the image
    truth = np.broadcast_to(blocks.reshape(3, 24, 3, 3).transpose(2, 3, 0, 1), (3, 3, 3, 3, 24))
    mask = np.ones((3, 24), bool)
    mask[0, 0] = False
    holds = model_holds(np.ascontiguousarray(truth), mask)
    assert holds[0, 1:].all() and not holds[0, 0]
    assert not holds[1, far].any() and far.sum() >= 12
    assert holds[2].all()


@needs_weights
def test_models_only_run_writes_its_table(tmp_path):
    """``--models-only`` on a tiny set: the three methods' rows, the share where a model holds,
    the table and its JSON; the selection gives a reduced model somewhere and keeps its sigma
    finite."""
    from polrig.models.continuum import main

    out = tmp_path / "m.md"
    assert main(["--models-only", "--count", "2", "--sets", "seen_families", "--root", str(tmp_path / "sets"),
                 "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    assert res["offsets"]["two"] == [0, 90]
    m = res["sets"]["seen_families"]["methods"]
    assert set(m) == {"holds_single", "holds_hybrid2", "hybrid2_models", "hybrid2_geometry", "hybrid2_diffuse",
                      "holds_reference4", "reference4_models"}
    # the four-state bound: more samples than two states, so a better estimate where a model holds
    assert m["reference4_models"]["states"] == 4 and m["holds_reference4"]["time_s"] > m["hybrid2_models"]["time_s"]
    assert m["reference4_models"]["psnr_holds"] > m["holds_hybrid2"]["psnr_holds"]
    sel = m["hybrid2_models"]
    assert 0 < sel["holds_share"] <= 1 and 0 < sel["accepted"] <= 1 and 0.5 < sel["coverage"] <= 1
    assert np.isfinite(sel["matrix_psnr"]) and np.isfinite(m["holds_hybrid2"]["psnr_holds"])
    assert m["holds_single"]["matrix_psnr"] < m["holds_hybrid2"]["matrix_psnr"]
    # the diffuse completion changes some of the rank-one pixels and keeps its sigma finite
    geo = m["hybrid2_geometry"]
    assert 0 < geo["accepted"] <= sel["accepted"] and 0.5 < geo["coverage"] <= 1 and np.isfinite(geo["psnr_holds"])
    # the diffuse term (with the specular term where significant) tested on the samples alone:
    # accepted somewhere, the specular term on some of those, its sigma finite, both false
    # acceptances counted (the samples' own and the prior's metric)
    dif = m["hybrid2_diffuse"]
    assert 0 < dif["accepted"] <= 1 and 0.5 < dif["coverage"] <= 1 and np.isfinite(dif["psnr_holds"])
    assert 0 < dif["specular"] <= dif["accepted"]
    assert dif["detectable_share"] >= dif["detectable_mc_share"] >= 0 and dif["detectable_prior_share"] >= 0
    text = out.read_text()
    assert "tested on the two states' samples alone" in text and "with the specular term" in text
    assert "Lower-order models at two states (0/90)" in text and "hybrid 2 + models, holds" in text
    assert "reference 4 / + models, holds" in text and "+ geometry, holds" in text
    assert "--models-only --count 2" in text


def test_the_benchmarks_models_defaults_are_the_committed_table():
    from benchmarks import bench_continuum

    assert bench_continuum.MODELS_DEFAULTS[:3] == ["--models-only", "--count", "64"]
    assert bench_continuum.MODELS_RESULTS.with_suffix(".json").is_file()


def test_detectably_off_every_model_on_a_synthetic_frame():
    """Blocks exactly of a model are never detectably off every model; random full blocks with
    precise samples and a tight prior are (the noncentrality on the hybrid's posterior system);
    pixels without a prior are left out."""
    from polrig.models.continuum import Frames, detectably_off_every_model, rotated_state

    rng = np.random.default_rng(3)
    h, w = 4, 10
    names = [m.name for m in rm.MODELS]
    exact = np.concatenate([rm.random_blocks(rng, n, 4, 1.0) for n in names])[:w * h // 2]
    full = rm.random_blocks(rng, "full", w * h // 2, 1.0)
    truth = np.concatenate([exact, full]).reshape(h, w, 3, 3).transpose(2, 3, 0, 1)[None]
    s0 = np.array([1.0, 0.6, 0.8]) / 2
    states = {0: s0, 90: rotated_state(s0, 90)}
    from polrig.solve.reference import forward_measurements

    meas = forward_measurements(truth, np.stack([states[0], states[90]]))
    var = np.full(meas.shape[1:], 1e-6)
    sigma = np.full(truth.shape, 0.01)
    sigma[..., 3, 9] = 0.0  # no prior at one pixel
    ones = np.ones((h, w), bool)
    fr = Frames(truth, ones, ones[None], ones, truth, sigma, states, {0: meas[0], 90: meas[1]},
                {0: var, 90: var}, {0: np.ones(var.shape, bool), 90: np.ones(var.shape, bool)})
    det = detectably_off_every_model(fr, (0, 90))[0]
    assert not det[:h // 2].any()
    assert det[h // 2:].mean() > 0.9 and not det[3, 9]


def test_two_state_bound_is_the_inverse_variance_combination():
    """Two equal independent estimates give 3.01 dB more than either; a four-state estimate
    halved to two states loses 3.01 dB; a far worse single-shot adds almost nothing."""
    from polrig.models.continuum import two_state_bound_db

    db3 = 10 * np.log10(2)
    assert two_state_bound_db(40.0, 40.0 + db3) == pytest.approx(40.0 + db3, abs=1e-9)
    assert two_state_bound_db(0.0, 50.0) == pytest.approx(50.0 - db3, abs=1e-4)
    assert two_state_bound_db(50.0, 0.0) == pytest.approx(50.0, abs=1e-4)


def test_detectably_off_diffuse_on_a_synthetic_frame():
    """The diffuse test's false-acceptance denominators: diffuse truth (Baek's term at the frame's
    own geometry) is never detectably off it, and the test's Monte Carlo rejection rate there is
    its level; a bright specular (Fresnel) truth mostly is, and the test rejects it on almost
    every noise draw there, in the noise of the frames' samples."""
    from polrig.models.continuum import Frames, detectably_off_diffuse, diffuse_test_power, rotated_state
    from polrig.optics.pbrdf import linear_rig_mueller
    from polrig.solve.diffuse_geometry import DiffuseGeometry
    from polrig.solve.diffuse_test import test_diffuse
    from polrig.solve.reference import forward_measurements

    h, w = 6, 8
    yy, xx = np.mgrid[0:h, 0:w] / w
    view = np.stack([0.05 * xx, 0.05 * yy, np.ones_like(xx)], axis=-1)
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    light = np.array([0.6, 0.1, 0.8]) / np.linalg.norm([0.6, 0.1, 0.8])
    zen, azi = np.deg2rad(15 + 30 * xx), 2 * np.pi * (xx + yy)
    normal = np.stack([np.sin(zen) * np.cos(azi), np.sin(zen) * np.sin(azi), np.cos(zen)], axis=-1)
    stage, cam = np.array([0.0, -1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    s0 = np.array([1.0, 1.0, 0.0])
    states = {0: s0, 90: rotated_state(s0, 90)}
    geo = DiffuseGeometry(view=view, light=light, stage_zero_axis=stage, camera_x_axis=cam)
    for component, detectable in (("diffuse", False), ("specular", True)):
        kw = {"kd": 1.0, "ks": 0.0} if component == "diffuse" else {"kd": 0.0, "ks": 1.0}
        m = linear_rig_mueller(normal.reshape(-1, 3), np.broadcast_to(light, (h * w, 3)), view.reshape(-1, 3),
                               alpha=0.3, eta=1.5, components=(component,), stage_zero_axis=stage,
                               camera_x_axis=cam, **kw)
        truth = np.moveaxis(m, 0, -1).reshape(3, 3, h, w)[None].repeat(3, axis=0)
        truth = truth / truth[:, 0, 0].max()
        meas = forward_measurements(truth, np.stack([states[0], states[90]]))
        var = np.clip(meas, 0, None) / 2000 + 1e-5  # shot noise at 2000 DN for the brightest m00
        ones = np.ones((h, w), bool)
        fr = Frames(truth, ones, ones[None].repeat(3, 0), ones, truth, np.full(truth.shape, 0.01), states,
                    {0: meas[0], 90: meas[1]}, {0: var[0], 90: var[1]},
                    {0: np.ones(var.shape[1:], bool), 90: np.ones(var.shape[1:], bool)}, geometry=geo)
        test = test_diffuse(np.stack([states[0], states[90]]), meas, var, None, geo, etas=(1.5,))
        det = detectably_off_diffuse(fr, (0, 90), test)
        rejected = diffuse_test_power(fr, (0, 90), test, *np.nonzero(ones), draws=100)
        if detectable:
            assert det.mean() > 0.9 and not test.accepted[det].any()
            assert rejected.reshape(h, w)[det].mean() > 0.95
        else:
            assert not det.any() and test.accepted.all()
            assert 0.0 < rejected.mean() < 0.12  # the level, 0.05, within the grid search's and the draws' spread
