"""The hybrid method wired as a capture and reconstruct mode (issue 33 item 1): the plan's rules,
the manifest's ``seen_state`` and ``prior`` records (schema version 3, older sessions migrated),
``polrig capture --mode hybrid`` end to end on a 64x64 simulated rig, ``reconstruct --mode
hybrid`` of a reference session, and the option refusals. The solver's own properties (the
wide-prior limit, coverage) are tested in ``tests/test_hybrid.py``; here the wiring."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import shutil

import numpy as np
import pytest

from polrig.acquisition.plan import CapturePlan, PlanError, single_shot_options
from polrig.app.manifest import SCHEMA_VERSION
from polrig.app.session import MANIFEST_NAME, Session
from polrig.cli import main
from polrig.formats.exr import read_mueller_exr
from polrig.models.uncertainty import VERSION as UNCERTAINTY_VERSION

from test_cli_capture import MODEL_INSTALLED, sim_config

needs_model = pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")


# -- the plan ------------------------------------------------------------------------------------
def test_a_hybrid_plan_takes_any_number_of_states_and_a_seen_state():
    p = CapturePlan((0.0,), mode="hybrid", states_deg=(0.0, 60.0), seen_state=1)
    assert p.states_deg == (0.0, 60.0) and p.seen_state == 1 and p.frames_per_pose() == 2
    assert CapturePlan((0.0,), mode="hybrid", states_deg=(30.0,)).seen_state == 0
    assert CapturePlan((0.0,), mode="hybrid", mirror_average=True).mirror_average is True
    opts = single_shot_options("hybrid", "bilinear", "superpixel", 1, True)
    assert opts.sigma is True and opts.demosaic == "bilinear" and opts.mirror_average  # the prior's route


@pytest.mark.parametrize("kwargs, field, text", [
    ({"resolution": "full"}, "resolution", "calibrated sigma"),
    ({"network_binning": 2}, "network_binning", "calibrated sigma"),
    ({"states_deg": (0.0, 90.0), "seen_state": 2}, "seen_state", "0..1"),
    ({"seen_state": -1}, "seen_state", "0..3"),
    ({"seen_state": True}, "seen_state", "a state index"),
    ({"states_deg": ()}, "states_deg", "at least one polarizer state"),
])
def test_hybrid_plan_refusals_name_the_field(kwargs, field, text):
    with pytest.raises(PlanError) as e:
        CapturePlan((0.0,), mode="hybrid", **kwargs)
    assert e.value.field == field and text in str(e.value)


def test_the_seen_state_is_hybrid_only():
    for mode in ("reference", "single-shot"):
        with pytest.raises(PlanError) as e:
            CapturePlan((0.0,), mode=mode, seen_state=1)
        assert e.value.field == "seen_state" and "hybrid method only" in str(e.value)
    with pytest.raises(PlanError) as e:  # the one place the rules live: the processor's check too
        single_shot_options("hybrid", "superpixel", "full", 1, False)
    assert e.value.field == "resolution"


@needs_model
def test_two_hybrid_states_that_are_one_polarizer_state_are_refused_before_anything_moves(tmp_path, capsys):
    """0 and 180 deg are one polarizer state: no direction is left open for the prior's scale,
    and the solve would fail on every resume; refused in one line naming --states, nothing
    written. Two states apart, however close, are a plan."""
    cfg = sim_config(tmp_path / "rig.toml")
    for states in ("0,180", "45,45"):
        out = tmp_path / f"s{states}"
        rc = main(["capture", "--poses", "0", "--mode", "hybrid", "--states", states, "--config", str(cfg),
                   "--out", str(out), "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1, err
        assert f"--states {states}: the two are one polarizer state" in err and not out.exists(), err
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--states", "0,5", "--config", str(cfg),
                 "--out", str(tmp_path / "close"), "--no-progress"]) == 0


# -- the manifest: version 3, older sessions ---------------------------------------------------------
def test_a_version_2_session_opens_with_seen_state_0(tmp_path):
    """A session written in version 2 (no ``seen_state`` in its plan or revisions) opens,
    migrated in memory (one history event, 2 -> 3), and writes nothing until saved."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--no-progress"]) == 0
    m = json.loads((out / MANIFEST_NAME).read_text())
    assert m["schema_version"] == SCHEMA_VERSION == 7 and m["plan"]["seen_state"] == 0
    del m["metadata"]  # version 4's
    del m["plan"]["seen_state"]
    for rev in m["revisions"]:
        del rev["seen_state"]
    m["schema_version"] = 2
    (out / MANIFEST_NAME).write_text(json.dumps(m))
    before = (out / MANIFEST_NAME).read_bytes()
    s = Session.open(out)
    assert s.stored_version == 2 and s.manifest["schema_version"] == 7
    assert s.plan.seen_state == 0 and s.manifest["revisions"][0]["seen_state"] == 0
    steps = [(h["event"], h["from_version"], h["to_version"]) for h in s.manifest["history"][-5:]]
    assert steps == [("schema migrated", 2, 3), ("schema migrated", 3, 4), ("schema migrated", 4, 5),
                     ("schema migrated", 5, 6), ("schema migrated", 6, 7)]
    assert (out / MANIFEST_NAME).read_bytes() == before and s.verify() == []


def test_a_damaged_prior_record_is_one_line(tmp_path):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / MANIFEST_NAME).read_text())
    m["captures"][0]["prior"] = {"graph": "single_shot.onnx"}
    (out / MANIFEST_NAME).write_text(json.dumps(m))
    with pytest.raises(Exception, match=r"capture 0 \(c000_pose000.0\): prior: missing 'graph_sha256'"):
        Session.open(out)


# -- end to end ------------------------------------------------------------------------------------
@needs_model
def test_hybrid_capture_with_two_states_end_to_end(tmp_path, capsys):
    """``polrig capture --mode hybrid --states 0,60`` on the 64x64 simulated rig: the manifest's
    plan and prior record, the EXR's planes and header, and a score better than single-shot's on
    the same scene (same rig seed, the same frame of state 0 the network sees)."""
    cfg = sim_config(tmp_path / "rig.toml")
    hybrid, single = tmp_path / "hybrid", tmp_path / "single"
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--states", "0,60", "--device", "cpu",
                 "--config", str(cfg), "--out", str(hybrid), "--no-progress"]) == 0
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--device", "cpu",
                 "--config", str(cfg), "--out", str(single), "--no-progress"]) == 0
    s = Session.open(hybrid)
    assert (s.plan.mode, s.plan.states_deg, s.plan.seen_state) == ("hybrid", (0.0, 60.0), 0)
    cap = s.capture(0)
    assert len(cap["files"]["raw"]) == 2 and s.verify() == []
    prior = cap["prior"]
    weights = pathlib.Path(__file__).resolve().parents[1] / "models" / "weights"
    import hashlib

    assert prior["graph"] == "single_shot.onnx"
    assert prior["graph_sha256"] == hashlib.sha256((weights / "single_shot.onnx").read_bytes()).hexdigest()
    assert prior["uncertainty_sha256"] == hashlib.sha256((weights / "uncertainty.json").read_bytes()).hexdigest()
    assert prior["uncertainty_version"] == UNCERTAINTY_VERSION and prior["execution_provider"] == "CPUExecutionProvider"
    assert (prior["mirror_average"], prior["seen_state"], prior["seen_state_deg"]) == (False, 0, 0.0)
    exr = read_mueller_exr(hybrid / cap["files"]["mueller"]["path"])
    meta = exr.metadata
    assert (meta["mode"], meta["seen_state"], meta["seen_state_deg"]) == ("hybrid", 0, 0.0)
    assert meta["prior_model"] == {k: v for k, v in prior.items() if not k.startswith("seen_state")}
    assert meta["condition_number"] == float("inf")  # two states do not determine the block alone
    assert "prior" in meta["planes"]["sigma.M{rc}"] and "effective degree" in meta["planes"]["residual"]
    colours = [k.split(".")[-1] for k in exr.extra if k.startswith("mask.")]
    assert colours and all(f"sigma.M12.{c}" in exr.extra and f"residual.{c}" in exr.extra for c in colours)
    assert not any(k.startswith("beyond_calibration") for k in exr.extra)
    ours, theirs = cap["score"], Session.open(single).capture(0)["score"]
    assert ours["pixels_compared"] > 0.9 * theirs["pixels_compared"]
    # measured: 30.7 dB against 26.5 dB, RMSE 111 against 180
    assert ours["psnr_db"] > theirs["psnr_db"] + 2.0 and ours["rmse"] < theirs["rmse"]
    assert ours["within_2sigma"] > 0.9
    capsys.readouterr()
    assert main(["info", str(hybrid)]) == 0
    assert "plan: mode hybrid (seen state 0: 0 deg), 1 poses, states 0,60 deg" in capsys.readouterr().out


@needs_model
def test_hybrid_with_a_seen_state_mirror_averaging_and_bilinear(tmp_path):
    """The seen state, mirror averaging and the demosaic reach the prior: the record says so and
    the result lies on the bilinear (raw frame's) grid."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--states", "0,60,120", "--seen-state", "1",
                 "--mirror-average", "--demosaic", "bilinear", "--device", "cpu", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    cap = Session.open(out).capture(0)
    assert (cap["prior"]["seen_state"], cap["prior"]["seen_state_deg"], cap["prior"]["mirror_average"]) == (
        1, 60.0, True)
    exr = read_mueller_exr(out / cap["files"]["mueller"]["path"])
    assert exr.mueller.shape[-2:] == (64, 64) and exr.metadata["demosaic"] == "bilinear"
    assert exr.metadata["condition_number"] == pytest.approx(2.0)  # 0/60/120
    assert cap["score"]["within_2sigma"] > 0.9 and cap["score"]["psnr_db"] > 40


@needs_model
def test_reconstruct_a_reference_session_in_hybrid_mode(tmp_path, capsys, monkeypatch):
    """``reconstruct --mode hybrid --seen-state 2`` of a four-state reference session: the
    revision records the seen state and the prior; with the route's sigma made infinite (no
    prior) the revision is the reference result bit for bit, so the frames, states and prior
    reach the solve as they should."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--mode", "hybrid", "--seen-state", "2", "--device", "cpu",
                 "--no-progress"]) == 0
    s = Session.open(out)
    [rev] = s.manifest["revisions"]
    assert (rev["mode"], rev["seen_state"], rev["resolution"], rev["network_binning"]) == (
        "hybrid", 2, "superpixel", 1)
    entry = s.capture(0)["revisions"]["rev1"]
    assert entry["status"] == "complete" and entry["prior"]["seen_state_deg"] == 90.0
    assert entry["score"]["within_2sigma"] > 0.9 and "prior" not in s.capture(0)
    meta = read_mueller_exr(out / entry["files"]["mueller"]["path"]).metadata
    assert meta["seen_state"] == 2 and meta["condition_number"] == pytest.approx(2.0)

    from polrig.app.single_shot import SingleShot

    state = SingleShot.state

    def no_prior(self, *args, **kwargs):
        r = state(self, *args, **kwargs)
        return dataclasses.replace(r, sigma=np.full(r.sigma.shape, np.inf, np.float32))

    monkeypatch.setattr(SingleShot, "state", no_prior)
    assert main(["reconstruct", str(out), "--mode", "hybrid", "--device", "cpu", "--no-progress"]) == 0
    s = Session.open(out)
    wide = read_mueller_exr(out / s.capture(0)["revisions"]["rev2"]["files"]["mueller"]["path"])
    ref = read_mueller_exr(out / s.capture(0)["files"]["mueller"]["path"])
    np.testing.assert_array_equal(wide.mueller, ref.mueller)
    for k in ref.extra:
        np.testing.assert_array_equal(wide.extra[k], ref.extra[k], err_msg=k)


# -- refusals ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, message", [
    (["--mode", "hybrid", "--resolution", "full"], "--resolution full: the hybrid method's prior needs"),
    (["--mode", "hybrid", "--network-binning", "2"], "--network-binning 2: the hybrid method's prior needs"),
    (["--mode", "hybrid", "--states", "0,90", "--seen-state", "2"], "--seen-state 2: must index"),
    (["--mode", "reference", "--seen-state", "1"], "--seen-state 1: the seen state applies to the hybrid"),
    (["--mode", "single-shot", "--seen-state", "1"], "--seen-state 1: the seen state applies to the hybrid"),
])
def test_capture_option_refusals_exit_2_with_one_line(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main(["capture", "--poses", "0", *args, "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert not out.exists()


@needs_model
def test_hybrid_needs_a_calibrated_sigma(tmp_path, capsys, monkeypatch):
    """A graph without its uncertainty calibration: the hybrid capture is refused before
    anything is written (one line naming --mode)."""
    from polrig.models import sizes

    weights = tmp_path / "weights"
    shutil.copytree(sizes.SIZE_FOLDERS["small"], weights,
                    ignore=shutil.ignore_patterns("uncertainty.json", "*.csv", "*.pt", "large"))
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "small", weights)  # the installed (small) model
    out = tmp_path / "out"
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--device", "cpu", "--out", str(out),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--mode hybrid" in err and "calibrated sigma" in err, err
    assert not out.exists()


def test_reconstruct_refusals_record_nothing(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    before = (out / MANIFEST_NAME).read_bytes()
    capsys.readouterr()
    for args, message in ((["--mode", "hybrid", "--seen-state", "4"], "--seen-state 4: must index"),
                          (["--seen-state", "1"], "--seen-state 1: the seen state applies to the hybrid"),
                          (["--mode", "hybrid", "--resolution", "full"], "--resolution full: the hybrid")):
        assert main(["reconstruct", str(out), *args, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and message in err, err
        assert (out / MANIFEST_NAME).read_bytes() == before


def test_the_gui_capture_panel_offers_the_hybrid_mode(qtbot, tmp_path):
    """The capture panel's mode list has ``hybrid``; its request carries the states, the seen
    state and mirror averaging (the network's settings), superpixel and unbinned."""
    pytest.importorskip("PySide6")
    pytest.importorskip("pytestqt")
    from test_gui import close_window, make_window

    w = make_window(qtbot, tmp_path / "gui.ini", start=False)
    cp = w.capture
    modes = [cp.mode.itemText(i) for i in range(cp.mode.count())]
    assert modes == ["reference", "single-shot", "hybrid", "adaptive"]
    assert not cp.seen_state.isEnabled()
    cp.mode.setCurrentText("hybrid")
    assert cp.seen_state.isEnabled() and cp.mirror_average.isEnabled() and not cp.resolution.isEnabled()
    cp.poses.setText("0")
    cp.states.setText("0,60")
    cp.seen_state.setValue(1)
    cp.out.setText(str(tmp_path / "s"))
    request = cp.request()
    assert (request.mode, request.states_deg, request.seen_state) == ("hybrid", (0.0, 60.0), 1)
    assert (request.resolution, request.network_binning) == ("superpixel", 1)
    assert request.plan().seen_state == 1
    # the models per pixel: the CLI's choices, full by default, none for the single-shot mode
    assert [cp.models.itemText(i) for i in range(cp.models.count())] == ["full", "auto", "diffuse"]
    assert request.models == "full" and cp.models.isEnabled()
    cp.models.setCurrentText("diffuse")
    assert cp.request().models == "diffuse"
    # the prior's scale: the CLI's choices, the CLI's default, none outside the prior's modes
    cp.mode.setCurrentText("hybrid")
    assert [cp.prior_scale.itemText(i) for i in range(cp.prior_scale.count())] == ["innovations", "geometry",
                                                                                   "calibrated"]
    assert cp.prior_scale.isEnabled() and cp.request().prior_scale == "geometry"
    cp.prior_scale.setCurrentText("calibrated")
    assert cp.request().prior_scale == "calibrated"
    cp.mode.setCurrentText("single-shot")
    assert not cp.models.isEnabled() and cp.request().models == "full"
    assert not cp.prior_scale.isEnabled() and cp.request().prior_scale is None
    close_window(qtbot, w)


def test_the_hybrid_solve_uses_the_joint_prior_and_records_it(tmp_path, monkeypatch):
    """The shipped calibration holds the prior calibrated jointly: a two-state hybrid capture
    records ``joint_prior_version`` in its prior and solves with the correlation; reconstructed
    with the same calibration without it (a file fitted per element only), the revision records
    none and gives another posterior on the object."""
    from polrig.app import cluster, single_shot
    from polrig.models import uncertainty

    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "hybrid", "--states", "0,90", "--device", "cpu",
                 "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    from_json = uncertainty.UncertaintyModel.from_json.__func__

    def per_element(cls, data):
        return dataclasses.replace(from_json(cls, data), joint=None)

    monkeypatch.setattr(uncertainty.UncertaintyModel, "from_json", classmethod(per_element))
    # the process's loaded routes and processors: made again
    monkeypatch.setattr(single_shot, "_OPEN", {})
    monkeypatch.setattr(cluster, "_PROCESSORS", {})
    assert main(["reconstruct", str(out), "--mode", "hybrid", "--device", "cpu", "--no-progress"]) == 0
    cap = Session.open(out).capture(0)
    joint, plain = cap, cap["revisions"]["rev1"]
    assert joint["prior"]["joint_prior_version"] == uncertainty.JOINT_VERSION
    assert "joint_prior_version" not in plain["prior"]
    a, b = (read_mueller_exr(out / e["files"]["mueller"]["path"]) for e in (joint, plain))
    assert a.metadata["prior_model"]["joint_prior_version"] == uncertainty.JOINT_VERSION
    differ = np.any(np.abs(a.mueller - b.mueller) > 1e-3 * np.nanmax(np.abs(b.mueller)), axis=(1, 2))
    assert differ.mean() > 0.05  # the object's pixels, where the prior acts
    assert joint["score"]["within_2sigma"] > 0.9 and plain["score"]["within_2sigma"] > 0.9
