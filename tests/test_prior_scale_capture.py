"""The prior's scale from the innovations in the capture path (issue 33, coverage): the banded
estimate from the frames agrees with the definition on the whole image and samples the bands
evenly; a hybrid capture records the factor in its manifest and EXR header, a reconstruct with
the same choice gives the identical result and ``--prior-scale calibrated`` the unscaled one; a
resumed session goes on with the scale its results were made with. The estimator's own
properties are tested in ``tests/test_prior_scale.py``."""

from __future__ import annotations

import types

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.acquisition.plan import PlanError
from polrig.app.capture_request import resumed_prior_scale
from polrig.app.cluster import _continuable
from polrig.app.session import Session
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.cli import main
from polrig.formats.exr import read_mueller_exr
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.demosaic import output_shape
from polrig.sensor.layouts import IMX250MYR, IMX250MZR
from polrig.solve.prior_scale import SHRINK, innovations, prior_scale
from polrig.solve.radiometry import analyzer_stack, prior_scale_from_frames

from _state_radiance import noisy_states
from test_cli_capture import MODEL_INSTALLED, sim_config

needs_model = pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")


def _frames(rng, shape, layout, states_deg, method):
    """Noisy mosaics of a smooth random Mueller scene under the polarizer ``states_deg``, a few
    samples excluded, and a prior ``(mean, sigma)`` on the output grid off by about its sigma."""
    h, w = shape
    c = layout.n_colours
    v, u = np.mgrid[0:h, 0:w]
    m = np.zeros((c, 3, 3, h, w))
    for ci in range(c):
        base = rng.uniform(-0.3, 0.3, (3, 3)) + np.diag([1.0, 0.7, 0.6])
        m[ci] = 800 * base[:, :, None, None] * (1 + 0.2 * np.sin(0.3 * u + 0.2 * v + ci))
    s_in = polarizer_stokes(np.deg2rad(states_deg), intensity=1.0)
    states = noisy_states(rng, m, s_in, layout, excluded_share=0.02)
    ho, wo = output_shape(layout, shape, method)
    sigma = 20.0 * (1.0 + rng.random((c, 3, 3, ho, wo)))
    mean = 800 * np.diag([1.0, 0.7, 0.6])[None, :, :, None, None] + sigma * rng.standard_normal(sigma.shape)
    sigma[:, 2, 1, : ho // 3] = np.inf  # elements without a prior drop out
    sigma[..., ho // 2:, : wo // 3] = 0.0  # pixels off the network's object: none of their rows has one
    return states, s_in, mean, sigma


def _calibrated(rng, layout, shape):
    return AnalyzerModel(layout.name, 1 + 0.01 * rng.standard_normal(shape),
                         layout.angle_map(shape) + 0.5 * rng.standard_normal(shape),
                         np.clip(0.98 + 0.01 * rng.standard_normal(shape), 0, 1), rng.normal(0, 2, shape))


@settings(max_examples=10, deadline=None)
@given(colour=st.booleans(), method=st.sampled_from(("superpixel", "bilinear")), h=st.integers(8, 40),
       w=st.integers(8, 24), band_rows=st.integers(1, 12), calibrated=st.booleans(), seed=st.integers(0, 99))
def test_the_banded_scale_is_the_scale_of_the_whole_image(colour, method, h, w, band_rows, calibrated, seed):
    """With every band sampled, the frames' scale is :func:`polrig.solve.prior_scale.prior_scale` of
    the states demosaiced whole, exactly, whatever the banding, layout, demosaic and analyzer."""
    rng = np.random.default_rng(seed)
    layout = IMX250MYR if colour else IMX250MZR
    shape = (2 * (h // 2), 2 * (w // 2)) if colour else (h, w)
    states, s_in, mean, sigma = _frames(rng, shape, layout, [0, 60, 120], method)
    analyzer = _calibrated(rng, layout, shape) if calibrated else None
    got = prior_scale_from_frames(states, s_in, layout, method, analyzer, mean, sigma, 1, band_rows=band_rows,
                                  sample_pixels=10**9)
    parts = [analyzer_stack(s, layout, method, analyzer) for s in states]
    want = prior_scale(s_in, *(np.stack([p[i] for p in parts]) for i in range(3)), mean, sigma, 1, parts[0][3])
    assert got == want
    assert got.method == "innovations" and got.shrink == SHRINK and got.factor == got.raw ** SHRINK


def test_a_large_image_is_sampled_in_even_bands_and_one_state_has_no_scale():
    """Above ``sample_pixels`` every ``k``-th band is taken: the innovations are those of the
    sampled rows alone, spread over the whole image, and the factor is close to the whole
    image's. One state: factor 1, nothing measured."""
    rng = np.random.default_rng(7)
    shape, layout = (96, 64), IMX250MZR  # output 48 x 32
    states, s_in, mean, sigma = _frames(rng, shape, layout, [0, 90], "superpixel")
    whole = prior_scale_from_frames(states, s_in, layout, "superpixel", None, mean, sigma, 0, band_rows=2,
                                    sample_pixels=10**9)
    part = prior_scale_from_frames(states, s_in, layout, "superpixel", None, mean, sigma, 0, band_rows=2,
                                   sample_pixels=48 * 32 // 4)
    # bands of 2 output rows; every 4th band: rows 0-1, 8-9, ..., 40-41
    rows = np.concatenate([np.arange(r, r + 2) for r in range(0, 48, 8)])
    parts = [analyzer_stack(s, layout, "superpixel") for s in states]
    stack = [np.stack([p[i] for p in parts])[..., rows, :] for i in range(3)]
    d, _, _ = innovations(s_in, *stack, mean[..., rows, :], sigma[..., rows, :], 0)
    assert part.innovations == len(d) and whole.innovations > 3.5 * part.innovations
    assert part.factor == pytest.approx(whole.factor, rel=0.15)
    one = prior_scale_from_frames(states[:1], s_in[:1], layout, "superpixel", None, mean, sigma, 0)
    assert (one.factor, one.innovations) == (1.0, 0)


def _captures(*methods):
    return types.SimpleNamespace(captures=[{"index": i} | ({} if m is None else {"prior": (
        {} if m == "before" else {"sigma_scale": {"method": m}})}) for i, m in enumerate(methods)])


def test_a_resumed_session_goes_on_with_the_scale_its_results_were_made_with():
    """A session whose hybrid results were made with one scale goes on with it (a result from
    before the scale existed was made with the calibrated sigma); another is refused in one line
    naming the option's field; a session without a hybrid result yet takes what is asked."""
    assert resumed_prior_scale(_captures("calibrated", None), None) == "calibrated"
    assert resumed_prior_scale(_captures("before"), None) == "calibrated"
    assert resumed_prior_scale(_captures("innovations"), "innovations") == "innovations"
    assert resumed_prior_scale(_captures(None, None), None) == DEFAULT_PRIOR_SCALE
    assert resumed_prior_scale(_captures(None), "calibrated") == "calibrated"
    with pytest.raises(PlanError) as err:
        resumed_prior_scale(_captures("before"), "innovations")
    assert err.value.field == "prior_scale" and "'calibrated'" in str(err.value)
    with pytest.raises(PlanError, match="unknown choice"):
        resumed_prior_scale(_captures(None), "sometimes")


def test_a_resumed_session_takes_the_processing_it_recorded_even_before_its_first_result():
    """A version-7 session records its models and prior scale when it is created: a resume
    goes on with them though no result exists yet (an adaptive session's decisions follow the
    scale), and refuses others; a version-6 one recorded none (migrated to null) and resumes as
    it did."""
    from polrig.app.capture_request import resumed_processing
    from polrig.app.manifest import migrate_v6

    recorded = types.SimpleNamespace(manifest={"processing": {"models": "diffuse", "prior_scale": "calibrated"}},
                                     captures=[{"index": 0}])
    assert resumed_processing(recorded, None, None) == ("diffuse", "calibrated")
    assert resumed_processing(recorded, "diffuse", "calibrated") == ("diffuse", "calibrated")
    for asked in ({"models": "full"}, {"prior_scale": "geometry"}):
        with pytest.raises(PlanError) as err:
            resumed_processing(recorded, asked.get("models"), asked.get("prior_scale"))
        assert err.value.field == next(iter(asked)), err.value
    old = migrate_v6({"schema_version": 6, "history": []})
    assert old["schema_version"] == 7 and old["processing"] is None
    assert old["history"][-1]["from_version"] == 6 and old["history"][-1]["to_version"] == 7
    unrecorded = types.SimpleNamespace(manifest=old, captures=_captures("innovations").captures)
    assert resumed_processing(unrecorded, None, None) == ("full", "innovations")
    assert resumed_processing(unrecorded, "auto", None) == ("auto", "innovations")


def test_info_words_each_kind_of_scale():
    from polrig.app.manifest import describe_prior_scale

    scaled = {"method": "innovations", "factor": 0.713, "raw": 0.669, "shrink": SHRINK, "innovations": 4800}
    assert describe_prior_scale({"sigma_scale": scaled}) == "sigma x 0.713 (innovations, 4800 values)"
    one_state = dict(scaled, factor=1.0, raw=1.0, innovations=0)
    assert describe_prior_scale({"sigma_scale": one_state}) == "sigma as calibrated (no later state to scale it by)"
    assert describe_prior_scale({"sigma_scale": dict(scaled, method="calibrated")}) == "sigma as calibrated"
    assert describe_prior_scale({}) == "sigma as calibrated (before the scale)"


def test_an_interrupted_revision_from_before_the_scale_is_not_continued_with_it():
    """A revision made before the setting existed was made with the calibrated sigma: continued
    only by a request for that."""
    last = {"name": "rev1", "mode": "hybrid", "models": "full"}
    session = types.SimpleNamespace(manifest={"revisions": [last]},
                                    capture=lambda i: {"revisions": {"rev1": {"status": "pending"}}})
    assert _continuable(session, {"mode": "hybrid", "prior_scale": "innovations"}, [0]) is None
    assert _continuable(session, {"mode": "hybrid", "prior_scale": "calibrated"}, [0]) == ("rev1", [0])


@needs_model
def test_a_hybrid_capture_records_its_scale_and_reconstructs_to_the_same_result(tmp_path, capsys):
    """``polrig capture --mode hybrid --states 0,90 --prior-scale innovations`` records the factor
    (manifest and header);
    ``reconstruct`` with the same choice reproduces the result bit for bit; ``--prior-scale
    calibrated`` records factor 1 and another posterior sigma where the prior acts; asking a
    resumed session for another scale exits 2 with one line."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--states", "0,90", "--device", "cpu",
                 "--prior-scale", "innovations", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--mode", "hybrid", "--prior-scale", "innovations", "--device", "cpu",
                 "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--mode", "hybrid", "--prior-scale", "calibrated", "--device", "cpu",
                 "--no-progress"]) == 0
    s = Session.open(out)
    cap = s.capture(0)
    scale = cap["prior"]["sigma_scale"]
    assert scale["method"] == "innovations" and scale["innovations"] > 1000
    assert scale["factor"] == pytest.approx(scale["raw"] ** SHRINK) and scale["factor"] != 1.0
    assert [r["prior_scale"] for r in s.manifest["revisions"]] == ["innovations", "calibrated"]
    same, plain = cap["revisions"]["rev1"], cap["revisions"]["rev2"]
    assert same["prior"]["sigma_scale"] == scale
    assert plain["prior"]["sigma_scale"] == {"method": "calibrated", "factor": 1.0, "raw": 1.0, "shrink": 0.0,
                                             "innovations": 0}
    a, b, c = (read_mueller_exr(out / e["files"]["mueller"]["path"]) for e in (cap, same, plain))
    assert a.metadata["prior_model"]["sigma_scale"] == scale
    _assert_same_result(a, b)
    # the open column at two states is the prior's: its sigma follows the factor there
    assert _open_column_ratio(a, c) == pytest.approx(scale["factor"], rel=0.1)
    capsys.readouterr()
    assert main(["info", str(out), "--no-verify"]) == 0
    text = capsys.readouterr().out
    assert f"prior: sigma x {scale['factor']:.3g} (innovations, {scale['innovations']} values)" in text
    assert "rev2: complete" in text and "prior: sigma as calibrated" in text
    rc = main(["capture", "--resume", "--prior-scale", "calibrated", "--config", str(cfg), "--out", str(out),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--prior-scale" in err, err


def test_info_words_the_open_directions_scale():
    from polrig.app.manifest import describe_prior_scale

    scaled = {"method": "geometry", "factor": 0.713, "raw": 0.669, "shrink": SHRINK, "innovations": 4800,
              "open_direction": {"factor": 1.21, "raw": 1.29, "exponent": 0.75, "values": 900}}
    assert describe_prior_scale({"sigma_scale": scaled}) == (
        "sigma x 0.713 (innovations, 4800 values); along the open direction x 1.21 (diffuse geometry, 900 values)")
    none = dict(scaled, open_direction={"factor": 1.0, "raw": 1.0, "exponent": 0.0, "values": 0})
    assert describe_prior_scale({"sigma_scale": none}).endswith("along the open direction as that (no diffuse "
                                                                 "pixel to check it by)")
    assert describe_prior_scale({"sigma_scale": none}, 2).endswith("(no diffuse pixel to check it by)")
    for n in (1, 3, 4):  # no open direction to check: said so, not "no diffuse pixel"
        assert describe_prior_scale({"sigma_scale": none}, n).endswith(
            f"; no one direction left open at {n} state{'s' if n > 1 else ''}")


@needs_model
def test_the_geometry_scale_widens_the_open_column_by_its_recorded_factor(tmp_path):
    """``--prior-scale geometry`` at two states 0/90 (seen state 0: the open direction is the
    third column of M) on the simulated rig's plane: the record holds the innovations' factor and
    the open direction's, resting on values the diffuse test accepted; ``reconstruct`` with
    ``innovations`` keeps the same innovations' factor, and the third column's posterior sigma
    is the open factor times that revision's where the prior alone sets it; ``geometry`` again
    reproduces the capture bit for bit."""
    cfg = sim_config(tmp_path / "rig.toml", scene="plane")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "120", "--mode", "hybrid", "--states", "0,90", "--device", "cpu",
                 "--prior-scale", "geometry", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    for scale in ("innovations", "geometry"):
        assert main(["reconstruct", str(out), "--mode", "hybrid", "--prior-scale", scale, "--device", "cpu",
                     "--no-progress"]) == 0
    cap = Session.open(out).capture(0)
    scale = cap["prior"]["sigma_scale"]
    opened = scale["open_direction"]
    assert scale["method"] == "geometry" and opened["values"] >= 30 and opened["exponent"] == 0.75
    assert opened["factor"] == pytest.approx(opened["raw"] ** 0.75) and opened["factor"] > 1.1
    plain, again = cap["revisions"]["rev1"], cap["revisions"]["rev2"]
    assert plain["prior"]["sigma_scale"] == {k: v for k, v in scale.items() if k != "open_direction"} | {
        "method": "innovations"}
    a, b, c = (read_mueller_exr(out / e["files"]["mueller"]["path"]) for e in (cap, plain, again))
    assert a.metadata["prior_model"]["sigma_scale"] == scale
    _assert_same_result(a, c)
    assert _open_column_ratio(a, b) == pytest.approx(opened["factor"], rel=0.05)


def _assert_same_result(a, b) -> None:
    """Two read EXR results hold the same Mueller matrix and extra planes, bit for bit."""
    np.testing.assert_array_equal(a.mueller, b.mueller)
    for k in a.extra:
        np.testing.assert_array_equal(a.extra[k], b.extra[k], err_msg=k)


def _open_column_ratio(a, b) -> float:
    """The median ratio of two results' posterior sigma of M02 (the third column: the one states
    0/90 leave open with seen state 0) where both have one (more than 100 pixels)."""
    key = next(k for k in a.extra if k.startswith("sigma.M02"))
    acts = np.isfinite(a.extra[key]) & (a.extra[key] > 0) & (b.extra[key] > 0)
    assert acts.sum() > 100
    return float(np.median(a.extra[key][acts] / b.extra[key][acts]))


@needs_model
def test_without_the_rigs_geometry_or_two_states_the_open_factor_is_one():
    """``Processor.open_scale`` gives factor 1 with no values, never an error, where the light or
    the object point is not known (a real rig's configuration without them) and at a number of
    states other than two; its record says so (``values`` 0)."""
    from polrig.acquisition.plan import CapturePlan
    from polrig.app import processing
    from polrig.app.diffuse_route import GEOMETRY_NEEDED
    from polrig.sensor.noise import SensorModel
    from polrig.solve.open_scale import OpenScale

    plan = CapturePlan((0.0,), mode="hybrid", states_deg=(0.0, 90.0))
    proc = processing.make_processor(plan, processing.Calibration("ideal"), SensorModel())
    assert proc.prior_scale == DEFAULT_PRIOR_SCALE == "geometry"
    two = polarizer_stokes(np.deg2rad([0.0, 90.0]), intensity=1.0)
    partial = dict.fromkeys(GEOMETRY_NEEDED, (1.0, 0.0, 0.0)) | {"light_position_camera_m": None}
    for states, geometry in ((two, None), (two, partial), (two[:1], dict.fromkeys(GEOMETRY_NEEDED, 1.0))):
        got = proc.open_scale(list(states), states, None, geometry, None, {})
        assert got == OpenScale.none() and got.record()["values"] == 0
