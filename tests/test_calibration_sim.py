"""End-to-end calibration of the simulated rig, scored against its hidden truth.

One module fixture runs every procedure once (320x240 colour sensor, default noise, virtual
clock); the tests check the acceptance limits of issue 6 and what the procedures print.
"""

from __future__ import annotations

import numpy as np
import pytest

from polrig import calibration
from polrig.app.rig import open_rig
from polrig.calibration import evaluate, procedures, runner
from polrig.calibration.calset import CalibrationSet
from polrig.calibration.errors import TooFewAngles
from polrig.calibration.report import write_report
from polrig.cli import main as polrig_main

pytestmark = pytest.mark.slow

SIM = {"size": "320x240", "seed": 0, "clock_speed": float("inf")}


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    rig = open_rig(None, **SIM)
    rig.open()

    def mount(name, **kw):
        rig.truth.mount_target(name, **kw)

    cs, extras, lines = CalibrationSet(), {}, []
    runner.run_steps(runner.STEPS, rig, mount, cs, extras=extras, log=lines.append)
    print("\n".join(lines))
    errors = runner.errors_against_truth(cs, rig.truth.rig_parameters(),
                                         rig.truth.analyzer())
    out = tmp_path_factory.mktemp("calset")
    cs.save(out)
    write_report(out, cs, extras, errors)
    yield rig, mount, cs, errors, lines, out
    rig.close()


def test_intrinsics_within_half_a_percent(calibrated):
    _, _, cs, e, lines, _ = calibrated
    assert abs(e["intrinsics"]["fx_rel_error"]) < 0.005
    assert abs(e["intrinsics"]["fy_rel_error"]) < 0.005
    std = cs.params["intrinsics"]["std_fx_fy_cx_cy_px"]
    assert 0 < std[0] < 0.005 * cs.intrinsics["K"][0, 0]
    assert any(l.startswith("turntable:") and "fx=" in l and "±" in l for l in lines)


def test_turntable_axis_within_0p2_deg(calibrated):
    _, _, cs, e, _, _ = calibrated
    assert e["turntable"]["axis_error_deg"] < 0.2
    assert 0 < cs.params["turntable"]["axis_std_deg"] < 0.2
    assert e["turntable"]["point_error_perp_m"] < 0.005


def test_light_position_within_1_percent(calibrated):
    _, _, cs, e, lines, _ = calibrated
    le = e["light"]
    assert le["rel_error_of_illumination_distance"] < 0.01
    # the reported uncertainty (residual scatter, intrinsics and the sphere model's Type B
    # term, docs/calibration.md) covers the error within 3 sigma per axis
    std = np.asarray(cs.params["light"]["std_m"])
    assert np.all(np.abs(le["error_m"]) < 3 * std)
    assert any(l.startswith("light:") and "±" in l for l in lines)
    # the uncertainty assures the 1 % here (2 sigma 0.55-0.75 % over 8 turntable placements),
    # and bounds the error
    acc = cs.params["light"]["acceptance"]
    assert acc["assured"] and le["error_norm_m"] < acc["two_sigma_m"]
    assert abs(acc["distance_m"] / le["illumination_distance_m"] - 1) < 0.05
    assert not any("acceptance is not assured" in l for l in lines)


def test_the_stage_is_homed_before_a_step_turns_it(calibrated):
    """Its angles are measured from its home, as in a capture's setup (a K10CR1 that was never
    homed would otherwise stop the light step)."""
    lines = calibrated[4]
    homed = lines.index("stage: homed")
    assert homed < min(i for i, l in enumerate(lines) if l.startswith("light:"))


def test_generator_offset_and_extinction_ratio(calibrated):
    _, _, cs, e, lines, _ = calibrated
    g = e["generator"]
    assert abs(g["zero_offset_error_deg"]) < 0.1
    assert abs(g["extinction_ratio_rel_error"]) < 0.10
    gen = cs.generator
    assert 0 < gen.zero_offset_std_deg < 0.1 and gen.extinction_ratio_std > 0
    assert any(l.startswith("generator offset:") and "±" in l for l in lines)
    # incident states for any stage angle, normalised: S0 = (1 + 1/ER) / 2
    s = cs.incident_stokes([0.0, 45.0, 90.0])
    assert s.shape == (3, 3)
    np.testing.assert_allclose(s[:, 0], 0.5 * (1 + 1 / gen.extinction_ratio))


def test_dofp_orientation_gain_and_better_than_nominal(calibrated):
    _, _, cs, e, _, _ = calibrated
    d = e["dofp"]
    assert d["angle_rms_error_deg"] < 0.2
    assert d["gain_rms_rel_error"] < 0.005
    assert d["angle_rms_error_deg"] < d["ideal_model_angle_rms_error_deg"] / 3
    assert d["gain_rms_rel_error"] < d["ideal_model_gain_rms_rel_error"] / 3
    assert cs.dofp_maps["valid"].mean() > 0.95
    # the targets' metals the calibration modelled are recorded (polrig.calibration.mirror)
    assert cs.params["dofp"]["mirror"]["name"] == "aluminium"
    assert 5.0 < cs.params["dofp"]["mirror_incidence_deg"] < 20.0
    assert cs.params["light"]["sphere_metal"]["name"] == "chrome"


def test_calibration_set_files_and_report(calibrated):
    _, _, cs, _, _, out = calibrated
    back = calibration.load(out)
    assert back.id == cs.id
    np.testing.assert_array_equal(back.analyzer_model.angle_deg, cs.analyzer.angle_deg)
    np.testing.assert_allclose(back.light_position_m, cs.light_position_m)
    np.testing.assert_allclose(back.turntable_axis["axis_cam"], cs.turntable_axis["axis_cam"])
    report = (out / "report.md").read_text()
    assert cs.id in report and "hidden truth" in report
    for png in ("dofp_angle_error.png", "dofp_gain.png", "dofp_diattenuation.png",
                "geometry_residuals.png", "light_rays.png", "offset_histogram.png"):
        assert (out / png).stat().st_size > 100
    assert "skipped" not in report  # residual plots on a default install (issue 21 item 10)


def test_calibrated_reference_acquisition_is_3x_more_accurate(calibrated):
    rig, mount, cs, _, _, _ = calibrated
    mount("mirror_plate", **procedures.INTRINSIC_MOUNTS[0])
    rig.turntable.move_to(cs.params["dofp"]["turntable_deg"])
    procedures.auto_expose(rig.camera, percentile=99.9, target=0.45)
    gt = rig.truth.ground_truth()
    truth = evaluate.truth_on_superpixel_grid(gt["mueller"], rig.camera.layout)
    mask = evaluate.uniform_cells(gt["mueller"], gt["lit"], rig.camera.layout)
    assert mask.sum() > 300
    res = evaluate.compare_models(rig, cs, truth, mask)
    print(res)
    assert res["calibrated"] * 3 <= res["ideal"]


def test_degenerate_inputs_name_what_to_change(calibrated):
    rig, mount, cs, _, _, _ = calibrated
    mount("white_plate")  # no board in view
    with pytest.raises(ValueError, match="board views"):
        procedures.run_intrinsics(rig, mount, runner.Options().board,
                                  mounts=({"tilt_deg": 20.0},), angles_deg=(0.0, 10.0))
    geo = runner._geometry(cs)
    with pytest.raises(TooFewAngles, match="add stage angles"):
        procedures.run_generator_offset(rig, mount, runner.Options().board, geo,
                                        cs.light_position_m, stage_angles_deg=(0, 30, 60))


def test_cli_step_without_prerequisites_fails_cleanly(tmp_path, capsys):
    rc = polrig_main(["calibrate", "light", "--out", str(tmp_path / "new"), "--size", "64x48"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "polrig: error:" in err and "calibrate intrinsics" in err


def test_rerunning_a_step_drops_the_results_computed_from_it(calibrated, tmp_path, capsys):
    """Re-running ``stokes`` used to keep the analyzer fitted with the old zero offset, and
    re-running ``intrinsics`` kept the turntable, light, generator and DoFP results computed
    from the bundle-adjusted intrinsics it replaced (with Zhang start values)."""
    import shutil

    _, _, cs, _, _, out = calibrated
    ri = tmp_path / "ri"
    shutil.copytree(out, ri)
    capsys.readouterr()
    assert polrig_main(["calibrate", "stokes", "--size", "320x240", "--out", str(ri)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert ("stokes: dropped the set's dofp result (computed from its earlier stokes result); "
            "run it again, from 'polrig calibrate dofp'") in printed
    back = calibration.load(ri)
    assert not back.has("dofp") and back.analyzer is None and not back.dofp_maps
    assert back.generator.extinction_ratio == np.inf  # the DoFP step's, dropped with it
    assert sorted(p.name for p in ri.glob("*.npz")) == []
    assert back.params["turntable"] == cs.params["turntable"]  # not downstream: kept
    assert polrig_main(["calibrate", "intrinsics", "--size", "320x240", "--out", str(ri)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert ("intrinsics: dropped the set's turntable, light, stokes results (computed from its "
            "earlier intrinsics result); run them again, from 'polrig calibrate turntable'"
            ) in printed
    assert any(line.startswith("intrinsics: these are Zhang's start values") for line in printed)
    back = calibration.load(ri)
    assert [k for k in back.params if k in calibration.calset.SECTIONS] == ["camera", "intrinsics"]
    assert back.params["intrinsics"]["method"] == "zhang"


def test_an_interrupted_or_failed_run_keeps_the_finished_steps(tmp_path, capsys, monkeypatch):
    """Ctrl-C (or a failure) in a later step of ``calibrate all`` used to save nothing."""
    from polrig.errors import DeviceFault

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    def stalled(*a, **k):
        raise DeviceFault("stalled", device="turntable")

    out = tmp_path / "k"
    argv = ["calibrate", "all", "--size", "256x192", "--out", str(out)]
    monkeypatch.setattr(procedures, "run_turntable", interrupted)
    assert polrig_main(argv) == 130
    captured = capsys.readouterr()
    cid = calibration.load(out).id
    assert captured.err == (f"polrig: interrupted during calibration step turntable; saved step "
                            f"intrinsics in {out} (set {cid}); continue with: polrig calibrate "
                            f"turntable --size 256x192 --out {out}, then light, stokes, dofp\n")
    assert f"intrinsics: saved in {out} (set {cid})" in captured.out
    assert calibration.load(out).has("intrinsics")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(procedures, "run_turntable", stalled)
    assert polrig_main(["calibrate", "turntable", "--size", "256x192", "--out", str(out)]) == 1
    assert capsys.readouterr().err == (f"polrig: error: calibration step turntable: turntable: "
                                       f"stalled; the set in {out} is unchanged\n")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    out2 = tmp_path / "k2"
    assert polrig_main(argv[:-1] + [str(out2)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"polrig: error: calibration step turntable: turntable: stalled; saved "
                          f"step intrinsics in {out2} (set ")
    assert err.endswith(f"continue with: polrig calibrate turntable --size 256x192 --out {out2}, "
                        f"then light, stokes, dofp\n")
