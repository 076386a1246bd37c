"""Calibration uncertainty in the reported sigma of reference captures (polrig.app.processing,
polrig.solve.reference): the default simulated rig (hidden analyzer errors, stage zero offset, finite
extinction ratio) processed with the nominal calibration is covered by the reported sigma;
result planes; tolerances of calibration sets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from polrig.app import processing
from polrig.app.capture import CapturePlan, create_session, run_session
from polrig.app.rig import open_rig
from polrig.calibration import calibset
from polrig.calibration.calset import CalibrationSet
from polrig.formats.exr import read_mueller_exr
from polrig.sensor.analyzer import AnalyzerModel

POSES = (0.0, 90.0, 180.0, 270.0)


def capture_default_rig(out, calibration, size=128):
    """``polrig capture --poses 0:360:90 --mode reference`` on the default simulated rig (all
    hidden errors at their defaults), small and on an accelerated clock."""
    plan = CapturePlan(POSES)
    with open_rig(None, size=(size, size), clock_speed=math.inf, seed=0) as rig:
        session = create_session(out, rig, plan, calibration_id=calibration.id)
        proc = processing.make_processor(plan, calibration,
                                         processing.session_sensor_model(session))
        result = run_session(rig, session, processor=proc)
    assert result.status == "complete"
    return session, result.scores


@pytest.fixture(scope="module")
def default_rig_nominal(tmp_path_factory):
    return capture_default_rig(tmp_path_factory.mktemp("nominal") / "s",
                               processing.nominal_calibration())


def test_default_rig_with_nominal_calibration_is_within_its_reported_sigma(default_rig_nominal):
    """Per pose about 95 % of the elements lie within 2 reported sigma (3 binomial sd below
    95.45 % allowed; ~14000 elements per pose), and sigma is not inflated beyond that:
    chi^2 per element below 1.1 and above 0.7, fewer than 99 % within 2 sigma."""
    _, scores = default_rig_nominal
    p = 0.9545
    for score in scores.values():
        n = 9 * 3 * score["pixels_compared"]
        assert n > 10000, score
        assert score["within_2sigma"] >= p - 3 * math.sqrt(p * (1 - p) / n), score
        assert score["within_2sigma"] < 0.99, score
        assert 0.7 < score["chi2_per_element"] < 1.1, score
        assert score["mean_sigma"] < 1.3 * score["rmse"], score


def test_noise_only_sigma_does_not_cover_calibration_errors(tmp_path, default_rig_nominal):
    """The same capture processed with an exact calibration (zero tolerances: the noise
    model's sigma alone) claims too much: well under 95 % within 2 sigma, chi^2 > 1.2, same
    estimates."""
    _, exact = capture_default_rig(tmp_path / "s", processing.Calibration("nominal"))
    _, nominal = default_rig_nominal
    for i, score in exact.items():
        assert score["within_2sigma"] < 0.94 and score["chi2_per_element"] > 1.2, score
        assert score["rmse"] == nominal[i]["rmse"]
        assert score["mean_sigma"] < nominal[i]["mean_sigma"]


def test_result_file_has_total_and_noise_sigma_planes(default_rig_nominal):
    session, _ = default_rig_nominal
    cap = session.capture(0)
    got = read_mueller_exr(session.root / cap["files"]["mueller"]["path"])
    assert "sigma_noise" in cap["files"]["uncertainty"]["channels"]
    valid = got.extra["mask.G"] == 0
    for rc in ("00", "12", "21"):
        total, noise = got.extra[f"sigma.M{rc}.G"], got.extra[f"sigma_noise.M{rc}.G"]
        assert np.all(total >= noise) and np.all(noise[valid] > 0)
        assert np.mean(total[valid] > noise[valid]) > 0.9
        assert np.max(total[valid] / noise[valid]) > 1.2
    meta = got.metadata
    assert meta["analyzer_tolerance"] == list(processing.NOMINAL_ANALYZER_TOLERANCE)
    assert meta["generator_tolerance"] == list(processing.NOMINAL_GENERATOR_TOLERANCE)


def test_calibrations_declare_their_tolerances(tmp_path):
    nominal = processing.nominal_calibration()
    assert nominal.analyzer_tolerance == (0.01, 0.5, 0.02)
    assert nominal.generator_tolerance == (2.0, 0.006)
    assert processing.Calibration("x").analyzer_tolerance == (0.0, 0.0, 0.0)
    # a calibration set: fitted uncertainties (median per-pixel maps, offset bound, ER std)
    cs = CalibrationSet(
        params={"generator": {"zero_offset_deg": 1.77, "zero_offset_std_deg": 0.022,
                              "zero_offset_std_bound_deg": 0.1, "extinction_ratio": 800.0,
                              "extinction_ratio_std": 5.0, "stage_zero_axis_cam": [1, 0, 0]},
                "dofp": {"angle_std_deg_median": 0.068, "modulation_std_median": 0.002}},
        analyzer=AnalyzerModel.ideal("imx250mzr", (8, 8)))
    cs.save(tmp_path / "cal")
    cal = processing.load_calibration(tmp_path / "cal")
    assert cal.analyzer_tolerance == (calibset.CALIBRATED_GAIN_TOLERANCE, 0.068, 0.002)
    assert cal.generator_tolerance == pytest.approx((0.1, 5.0 / 800.0**2))
    # steps not run keep the nominal priors
    bare = CalibrationSet(params={"generator": {"zero_offset_deg": 0.0,
                                                "extinction_ratio": float("inf")}})
    a_tol, g_tol = calibset.tolerances(bare, nominal.analyzer_tolerance,
                                       nominal.generator_tolerance)
    assert a_tol == nominal.analyzer_tolerance and g_tol == (2.0, 0.006)
