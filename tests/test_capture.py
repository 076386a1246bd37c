"""Capture sessions on the simulated rig (in-process API): accuracy against the ground truth,
device faults, Ctrl-C, stop requests, a full disk, resume, re-processing."""

from __future__ import annotations

import errno
import math
import pathlib

import numpy as np
import pytest

from polrig.app import processing, reconstruct
from polrig.app.capture import CaptureControl, CapturePlan, create_session, run_session
from polrig.app.rig import open_rig
from polrig.app.session import COMPLETE, FAILED, INTERRUPTED, PENDING, Session, SessionError
from polrig.formats.exr import read_mueller_exr
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import AnalyzerModel, resolve_layout
from polrig.sensor.demosaic import demosaic
from polrig.solve.reference import solve_reference

IDEAL = {"stage_zero_offset_deg": 0.0, "extinction_ratio": 1e12, "ideal_analyzer": True}
#: the ideal rig, exactly known (zero calibration tolerances): its reported sigma is the
#: sensor noise model's alone, which these tests check against the truth
EXACT = processing.Calibration("ideal")


def sim_rig(size=64, *, noise=True, scene="plane", seed=5, **kw):
    """The simulated rig as ``polrig capture`` opens it (:func:`polrig.app.rig.open_rig`);
    ``rig.faults`` injects faults, ``rig.camera.world`` is the simulated world (its clock)."""
    opts = {"size": (size, size), "sensor": "imx250mzr", "clock_speed": math.inf,
            "seed": seed, "scene": scene, "noise": noise, "hidden": dict(IDEAL), **kw}
    return open_rig(None, **opts)


def start(rig, out: pathlib.Path, plan: CapturePlan, **kw) -> tuple[Session, processing.Processor]:
    cal = EXACT
    processing.check_plan(plan, cal)
    session = create_session(out, rig, plan, calibration_id=cal.id, **kw)
    return session, processing.make_processor(plan, cal, processing.session_sensor_model(session))


def resume(rig, out: pathlib.Path, **kw):
    session = Session.open(out)
    proc = processing.make_processor(session.plan, EXACT,
                                     processing.session_sensor_model(session))
    return session, run_session(rig, session, processor=proc, **kw)


def content(session: Session) -> list:
    """What must be identical between two runs: per capture its pose, status and every file's
    path and checksum (image and result files; frame sidecars hold clock timestamps and
    frame counters, so only their presence is compared)."""
    out = []
    for cap in session.captures:
        files = []
        for _, role, rec in session.iter_file_records(cap):
            files.append((role, rec["path"], rec["sha256"], rec.get("meta_path")))
        out.append((cap["pose_deg"], cap["status"], sorted(files)))
    return out


POSES4 = (0.0, 90.0, 180.0, 270.0)


@pytest.fixture(scope="module")
def reference_session(tmp_path_factory):
    """Uninterrupted session (sensor noise on: the simulator keys noise by pose, state and
    repeat index, so an interrupted and resumed session must reproduce it bit for bit), the
    yardstick for the interruption tests."""
    out = tmp_path_factory.mktemp("ref") / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan(POSES4))
        result = run_session(rig, session, processor=proc)
    assert result.status == "complete"
    return Session.open(out)


def test_uninterrupted_session_is_complete_and_verified(reference_session):
    s = reference_session
    assert s.manifest["status"] == "complete"
    assert [c["status"] for c in s.captures] == [COMPLETE] * 4
    for cap in s.captures:
        assert len(cap["files"]["raw"]) == 4
        assert {"mueller", "uncertainty", "mask", "truth_mueller"} <= set(cap["files"])
    assert s.verify() == []


def test_noise_free_capture_is_the_exact_estimate_of_the_truth(tmp_path):
    """Noise off: the simulated camera delivers the rounded mean (12-bit ADC codes). The
    pipeline's Mueller image (frames -> files -> averaging -> demosaic -> solve -> EXR) equals,
    to 1e-4 of the peak m00, the estimate computed here straight from the per-pixel ground
    truth: forward model through the IMX250MZR mosaic with the nominal states, the same
    rounding to ADC codes, superpixel demosaic, weighted solve. Where the truth is uniform over
    a cell, that estimate is the truth up to the 12-bit quantization."""
    states = (0.0, 45.0, 90.0, 135.0)
    with sim_rig(noise=False) as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan((30.0,), states_deg=states))
        assert run_session(rig, session, processor=proc).status == "complete"
        truth = rig.truth.ground_truth()["mueller"].astype(np.float64)
        exposure_us = rig.camera.exposure_us
    model = processing.session_sensor_model(session)
    cap = session.capture(0)
    got = read_mueller_exr(tmp_path / "s" / cap["files"]["mueller"]["path"])
    h, w = truth.shape[-2:]
    lay = resolve_layout("imx250mzr")
    s_in = polarizer_stokes(np.deg2rad(states), intensity=1.0)
    ideal = AnalyzerModel.ideal(lay, (h, w))
    offset = model.black_level_dn + model.dark_electrons(exposure_us) / model.gain_e_per_dn
    codes = [np.clip(np.rint(ideal.mosaic(np.einsum("cijhw,j->cihw", truth, s)) + offset), 0,
                     model.max_code_dn) for s in s_in]
    measured = np.stack([demosaic(c - offset, lay, "superpixel") for c in codes]).astype(float)
    variance = model.variance_dn2(measured, exposure_us)
    expected = solve_reference(s_in, measured, variance).mueller.astype(np.float64)
    valid = got.extra["mask.Y"] == 0
    peak = expected[0, 0, 0][valid].max()
    assert valid.sum() > 100
    err = np.abs(got.mueller - expected)[:, :, :, valid]
    assert err.max() <= 1e-4 * peak, err.max() / peak
    # without the rounding it is processing.truth_on_output_grid (what scores compare with),
    # and that is the truth where the truth does not vary over a cell
    t = processing.truth_on_output_grid(truth, lay, "superpixel", s_in, model=model,
                                        exposure_us=exposure_us)
    assert np.abs(t - expected)[:, :, :, valid].max() <= 2e-3 * peak
    blocks = truth.reshape(1, 3, 3, h // 2, 2, w // 2, 2)
    flat = (blocks.max(axis=(4, 6)) == blocks.min(axis=(4, 6))).all(axis=(1, 2))
    assert flat.any()
    assert np.allclose(t[:, :, :, flat[0]], blocks.mean(axis=(4, 6))[:, :, :, flat[0]],
                       rtol=1e-9, atol=1e-6 * peak)


def test_noisy_mueller_matches_truth_within_reported_sigma(tmp_path):
    """With the sensor noise on, per pose the errors against the truth follow the reported
    sigma: the fraction of valid elements within 2 sigma is 95.45% (Gaussian errors, sigma
    right) within 3 binomial standard deviations of the sample (about 0.9% for ~500 pixels x 9
    elements), and chi^2 per element is 1 within 4 of its standard errors plus 3%."""
    with sim_rig(scene="box") as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan(POSES4))
        result = run_session(rig, session, processor=proc)
    assert result.status == "complete"
    assert sorted(result.scores) == [0, 1, 2, 3]
    p = 0.9545
    for score in result.scores.values():
        n = 9 * score["pixels_compared"]
        assert n > 3000
        assert score["within_2sigma"] >= p - 3 * math.sqrt(p * (1 - p) / n), score
        assert abs(score["chi2_per_element"] - 1) <= 4 * math.sqrt(2 / n) + 0.03, score
        assert score["realizable"] > 0.9, score


def test_ctrl_c_mid_capture_then_resume_gives_identical_session(tmp_path, reference_session):
    out = tmp_path / "s"
    frames = []

    def progress(ev):
        if ev.kind == "frame":
            frames.append(ev)
            if len(frames) == 6:  # second capture, second state
                raise KeyboardInterrupt

    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan(POSES4))
        with pytest.raises(KeyboardInterrupt):
            run_session(rig, session, processor=proc, progress=progress)
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert [c["status"] for c in s.captures] == [COMPLETE, PENDING, PENDING, PENDING]
    assert len(s.capture(1)["files"]["raw"]) == 2  # complete and checksummed, nothing else
    assert s.verify() == []
    with sim_rig() as rig:
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert s2.verify() == []
    assert content(s2) == content(reference_session)
    assert s2.capture(1)["attempts"] == 2


# axis calls: position_deg (the plan's hardware time), [stage: home], then per move
# position_deg (the move's timeout), move_to (wait=False: the turntable and the stage start
# together), wait. Stage call 4 is the wait of the first move (with the turntable), call 6 the
# second state's move_to; turntable call 2 is the first move's start, call 3 its wait.
@pytest.mark.parametrize("device, kind, after", [("camera", "timeout", 5), ("stage", "fault", 6),
                                                  ("turntable", "timeout", 2),
                                                  ("turntable", "fault", 3),
                                                  ("stage", "protocol", 4)])
def test_safe_faults_are_retried(tmp_path, reference_session, device, kind, after):
    events = []
    with sim_rig() as rig:
        rig.faults.inject_fault(device, kind, after_calls=after)
        session, proc = start(rig, tmp_path / "s", CapturePlan(POSES4))
        result = run_session(rig, session, processor=proc, progress=events.append)
    assert result.status == "complete"
    assert any(e.kind == "retry" for e in events)
    assert content(session) == content(reference_session)


def test_a_long_turntable_move_gets_a_timeout_for_its_distance(tmp_path):
    """0 -> 300 deg at the simulated turntable's 10 deg/s takes over 30 s: the move's timeout
    grows with the distance (it failed twice against a fixed 30 s, re-homing in between)."""
    events = []
    with sim_rig() as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan((0.0, 300.0)))
        result = run_session(rig, session, processor=proc, progress=events.append)
    assert result.status == "complete"
    assert not any(e.kind == "retry" for e in events)


def test_unrecoverable_fault_stops_cleanly_then_resumes(tmp_path, reference_session):
    out = tmp_path / "s"
    with sim_rig() as rig:
        rig.faults.inject_fault("camera", "disconnect", after_calls=9)
        session, proc = start(rig, out, CapturePlan(POSES4))
        result = run_session(rig, session, processor=proc)
    assert result.status == INTERRUPTED and "DeviceDisconnected" in result.reason
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert "DeviceDisconnected" in s.manifest["status_reason"]
    failed = [c for c in s.captures if c["status"] == FAILED]
    assert len(failed) == 1 and "connection lost" in failed[0]["reason"]
    assert s.captures[0]["status"] == COMPLETE
    assert s.verify() == []
    with sim_rig() as rig:  # reconnected
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert content(s2) == content(reference_session)


def test_disk_full_stops_cleanly_then_resumes(tmp_path, reference_session):
    out = tmp_path / "s"
    full = []

    def progress(ev):  # the disk fills up once capture 0 is complete
        if ev.kind == "capture-done" and ev.capture_index == 0:
            full.append(True)

    def hook(path, data):
        if full:  # from then on every write fails (capture 1's frames or its processing)
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan(POSES4), write_hook=hook)
        result = run_session(rig, session, processor=proc, progress=progress)
    assert result.status == INTERRUPTED and result.reason.startswith("disk full")
    s = Session.open(out)  # the manifest on disk is the last consistent one
    assert s.verify() == []
    assert not list(out.rglob("*.tmp"))
    assert s.captures[0]["status"] == COMPLETE
    with sim_rig() as rig:  # space freed: no hook
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert content(s2) == content(reference_session)


def test_stop_request_leaves_capture_pending(tmp_path):
    """A stop requested once capture 0 is acquired (its processing under way in the
    background) takes effect at the next checkpoint: capture 0's processing ends (complete),
    capture 1 never starts."""
    control = CaptureControl()

    def progress(ev):
        if ev.kind == "capture-acquired" and ev.capture_index == 0:
            control.stop.set()

    with sim_rig() as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan((0.0, 90.0)))
        result = run_session(rig, session, processor=proc, progress=progress, control=control)
    assert result.status == INTERRUPTED and result.reason == "stopped by the operator"
    assert [c["status"] for c in session.captures] == [COMPLETE, PENDING]
    assert session.verify() == []


def test_reprocess_writes_a_revision_and_never_touches_raw(tmp_path):
    out = tmp_path / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan((0.0,)))
        run_session(rig, session, processor=proc)
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != "session.json"}
    name = reconstruct.reprocess_session(Session.open(out), demosaic="bilinear")
    s = Session.open(out)
    assert name == "rev1" and s.manifest["revisions"][0]["demosaic"] == "bilinear"
    rev = s.capture(0)["revisions"]["rev1"]
    assert rev["status"] == COMPLETE and rev["score"]["pixels_valid"] > 0
    full = read_mueller_exr(out / rev["files"]["mueller"]["path"]).mueller
    assert full.shape[-2:] == (64, 64)
    assert all(p.read_bytes() == data for p, data in before.items())
    assert s.verify() == []


def test_tampered_raw_frame_is_refused_by_reprocessing(tmp_path):
    out = tmp_path / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan((0.0,)))
        run_session(rig, session, processor=proc)
    raw = out / session.capture(0)["files"]["raw"][0]["path"]
    raw.write_bytes(raw.read_bytes()[:-10])
    with pytest.raises(reconstruct.ReconstructIncomplete, match="capture 0 .*SHA-256"):
        reconstruct.reprocess_session(Session.open(out))
    rev = Session.open(out).capture(0)["revisions"]["rev1"]
    assert rev["status"] == FAILED and "SHA-256" in rev["reason"] and rev["files"] == {}


def test_dark_frames_and_hdr_bracket_keep_errors_within_sigma(tmp_path):
    """Dark frames (light off) are recorded per exposure and subtracted; a two-exposure bracket
    is merged to HDR at the first (reference) exposure. Errors against the truth still follow
    the reported sigma, and the bracket lowers the error."""
    plan = CapturePlan((0.0,), frames_per_state=2, exposures_us=(20000.0, 80000.0),
                       dark_frames=2)
    with sim_rig(scene="box") as rig:
        session, proc = start(rig, tmp_path / "s", plan)
        result = run_session(rig, session, processor=proc)
        assert rig.light.status()["on"]  # back on after the dark frames
    assert result.status == "complete"
    files = session.capture(0)["files"]
    assert len(files["dark"]) == 4 and len(files["raw"]) == 16
    from polrig.formats.rawio import read_raw

    dark = read_raw(session.root / files["dark"][0]["path"])
    assert dark.raw.mean() < 40  # black level 16 DN + read noise: the light was off
    score = result.scores[0]
    n = 9 * score["pixels_compared"]
    assert n > 3000
    assert score["within_2sigma"] >= 0.9545 - 3 * math.sqrt(0.9545 * 0.0455 / n), score
    assert abs(score["chi2_per_element"] - 1) <= 4 * math.sqrt(2 / n) + 0.05, score
    with sim_rig(scene="box") as rig:
        single, proc = start(rig, tmp_path / "single", CapturePlan((0.0,), frames_per_state=2))
        plain = run_session(rig, single, processor=proc).scores[0]
    assert score["mean_sigma"] < plain["mean_sigma"]


def test_pause_blocks_between_frames_until_released(tmp_path):
    """The GUI's pause: the capture thread waits at the next frame boundary while paused
    and carries on, losing nothing, when the pause is released from another thread."""
    import threading
    import time

    control = CaptureControl(poll_s=0.01)
    seen = []

    def progress(ev):
        if ev.kind == "frame":
            seen.append(time.monotonic())
            if len(seen) == 2:
                control.pause.set()
                threading.Timer(0.3, control.pause.clear).start()

    with sim_rig() as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan((0.0,)))
        result = run_session(rig, session, processor=proc, progress=progress, control=control)
    assert result.status == "complete" and len(seen) == 4
    assert seen[2] - seen[1] >= 0.25  # the third frame waited for the release
    assert session.verify() == []


def test_colour_sensor_capture_has_rgb_mueller(tmp_path):
    with sim_rig(sensor="imx250myr", scene="box") as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan((0.0,)))
        result = run_session(rig, session, processor=proc)
    assert result.status == "complete"
    got = read_mueller_exr(tmp_path / "s" / session.capture(0)["files"]["mueller"]["path"])
    assert got.mueller.shape == (3, 3, 3, 16, 16)  # 4x4 colour cell -> quarter resolution
    assert {"sigma.M00.R", "sigma.M22.B", "mask.G", "residual.R"} <= set(got.extra)
    assert result.scores[0]["pixels_compared"] > 20


def test_other_file_system_error_stops_cleanly_then_resumes(tmp_path, reference_session):
    """An OSError that is not a full disk (an I/O error here; a name too long, a permission
    taken away) is re-raised for the caller to report, after the same clean-up as a device
    error: the capture failed with the reason, the session interrupted, nothing unrecorded
    left; resume completes it. (It used to skip the clean-up: status stayed "running".)"""
    out = tmp_path / "s"
    raw_1 = []

    def hook(path, data):  # capture 1's second raw frame (capture 0 acquired, maybe processing)
        if "c001_pose090.0/raw/" in path.as_posix() and path.suffix == ".png":
            raw_1.append(path)
            if len(raw_1) == 2:
                raise OSError(errno.EIO, "Input/output error", str(path))

    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan(POSES4), write_hook=hook)
        with pytest.raises(OSError) as info:
            run_session(rig, session, processor=proc)
    assert info.value.errno == errno.EIO
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert s.manifest["status_reason"].startswith("OSError:")
    assert [c["status"] for c in s.captures] == [COMPLETE, FAILED, PENDING, PENDING]
    assert "Input/output error" in s.capture(1)["reason"]
    assert s.verify() == [] and not list(out.rglob("*.tmp"))
    with sim_rig() as rig:
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert content(s2) == content(reference_session)


def test_resume_refuses_a_rig_whose_frames_differ(tmp_path):
    """The rig a session resumes on must give comparable frames: same camera geometry and
    layout, devices, noise model and simulated world; a different clock speed is fine."""
    from polrig.app.records import check_resume_rig
    from polrig.errors import ConfigError

    out = tmp_path / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan((0.0, 90.0)))
    session.unlock()
    s = Session.open(out)
    assert s.manifest["rig"]["camera_frames"] == {"width": 64, "height": 64, "offset_xy": [0, 0],
                                                  "layout": "imx250mzr", "colours": 1}
    with sim_rig(clock_speed=50.0) as rig:
        check_resume_rig(s, rig)  # the same rig, a slower clock
    for kw, expected in [({"size": 128}, "camera frames 64x64 imx250mzr (1 colour), this "
                                         "camera's 128x128 imx250mzr (1 colour)"),
                         ({"sensor": "imx250myr"}, "imx250myr (3 colours)"),
                         ({"seed": 6}, "simulated world"),
                         ({"scene": "box"}, "simulated world (scene)")]:
        with sim_rig(**kw) as rig:
            with pytest.raises(ConfigError, match=" was captured on a different rig: ") as info:
                check_resume_rig(s, rig)
        assert expected in str(info.value), (kw, str(info.value))
    # a session from before rig.camera_frames: the geometry comes from its recorded raw frames
    with sim_rig() as rig:
        run_session(rig, s, processor=None)
    s.manifest["rig"]["camera_frames"] = None  # as a migrated version-1 manifest says
    with sim_rig(size=32) as rig:
        with pytest.raises(ConfigError, match="camera frames 64x64 imx250mzr"):
            check_resume_rig(s, rig)


def test_a_world_recorded_on_another_processor_is_the_same_world():
    """The simulated world's recorded numbers are compared to float rounding: a session started
    on one machine resumes on another whose processor rounds the last bits differently (as the
    version-1 test data's stage axis does on an AVX2-only AMD EPYC), and a real change of a
    value, a key, a length or a type is still a different world."""
    import json

    from polrig.app.records import rig_differences, same_values

    world = {"seed": 11, "scene": {"name": "box", "stage_zero_axis": [0.9193993908515852,
                                                                     0.39331567487433816,
                                                                     0.002745906021358964]},
             "noise": True, "exposure_us": 5000.0}
    elsewhere = json.loads(json.dumps(world))
    elsewhere["scene"]["stage_zero_axis"][2] = 0.002745906021358971
    assert same_values(world, elsewhere)
    rig = {"simulated": True, "sim_parameters": world}
    assert rig_differences(rig, {"simulated": True, "sim_parameters": elsewhere}) == []
    changed = json.loads(json.dumps(world))
    changed["scene"]["stage_zero_axis"][2] *= 1 + 1e-6
    assert rig_differences(rig, {"simulated": True, "sim_parameters": changed}) == [
        "simulated world (scene)"]
    assert not same_values(world, {**world, "seed": 12})
    assert not same_values(world, {**world, "noise": 1.0})  # a bool is not a number here
    assert not same_values(world, {**world, "extra": 0})
    assert not same_values([0.0, 1.0], [0.0])
    assert not same_values(0.0, 1e-9)
    assert same_values(0.0, 1e-13)


def test_exposure_outside_the_cameras_range_is_refused_before_a_session_exists(tmp_path):
    from polrig.acquisition.plan import PlanError
    from polrig.app.records import check_rig_for_plan

    with sim_rig() as rig:  # the range the camera declares (CameraCapabilities), not a probe
        check_rig_for_plan(rig, CapturePlan((0.0,), exposures_us=(1000.0, 4000.0)))
        with pytest.raises(PlanError, match=r"exposure 1e\+12 us: outside the camera's range "
                                            r"\[10, 1e\+07\] us") as info:
            check_rig_for_plan(rig, CapturePlan((0.0,), exposures_us=(1000.0, 1e12)))
    assert info.value.field == "exposures_us"


def test_run_session_refuses_a_session_another_writer_holds(tmp_path):
    from polrig.app.session import SessionBusy

    out = tmp_path / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan((0.0,)))
        session.unlock()
        other = Session.open(out, lock=True)  # another writer (flock: per open file)
        before = (out / "session.json").read_bytes()
        with pytest.raises(SessionBusy):
            run_session(rig, Session.open(out), processor=proc)
        assert (out / "session.json").read_bytes() == before
        other.unlock()
        assert run_session(rig, Session.open(out), processor=proc).status == "complete"


def test_reprocess_goes_on_past_damaged_captures_and_names_them(tmp_path, reference_session):
    """A deleted raw frame (capture 1) and a changed truth file (capture 2): both are marked
    failed in the revision with their reason, captures 0 and 3 are processed, and the error
    at the end names the failed ones. (It used to stop at capture 1, leaving 2 and 3 out.)"""
    import shutil

    out = tmp_path / "s"
    shutil.copytree(reference_session.root, out)
    s = Session.open(out)
    (out / s.capture(1)["files"]["raw"][2]["path"]).unlink()
    truth = out / s.capture(2)["files"]["truth_mueller"]["path"]
    truth.write_bytes(truth.read_bytes() + b"\0")
    failures = []
    with pytest.raises(reconstruct.ReconstructIncomplete) as info:
        reconstruct.reprocess_session(s, on_failed=lambda i, r: failures.append(i))
    message = str(info.value)
    assert message.startswith("revision rev1: 2 of 4 capture(s) failed, the others are complete")
    assert "capture 1 (c001_pose090.0): FileNotFoundError" in message
    assert "capture 2 (c002_pose180.0): FormatError" in message and "truth" in message
    assert info.value.failed[0][0] == 1 and failures == [1, 2]
    revs = [c["revisions"]["rev1"] for c in Session.open(out).captures]
    assert [r["status"] for r in revs] == [COMPLETE, FAILED, FAILED, COMPLETE]
    assert "missing" in revs[1]["reason"] and "SHA-256" in revs[2]["reason"]
    assert revs[2]["files"] == {}  # refused before writing anything
    assert revs[3]["score"]["pixels_valid"] > 0
    problems = Session.open(out).verify()
    assert len(problems) == 2 and all("c001" in p or "c002" in p for p in problems)


def test_a_second_sigint_during_the_clean_up_does_not_cut_it_short(tmp_path):
    """A real SIGINT stops the run; a second one arriving while the clean-up writes the final
    manifest is ignored, so the manifest on disk says "interrupted" (it used to stay
    "running": the second KeyboardInterrupt aborted the write)."""
    import os
    import signal
    import time

    def deliver(signum):  # the Python handler runs at the next bytecode boundaries
        os.kill(os.getpid(), signum)
        time.sleep(0.02)

    def progress(ev):
        if ev.kind == "frame" and ev.step == 6:  # second capture, second state
            deliver(signal.SIGINT)

    def hook(path, data):
        if path.name == "session.json" and b'"status": "interrupted"' in data:
            deliver(signal.SIGINT)  # while the clean-up writes the final manifest

    out = tmp_path / "s"
    with sim_rig() as rig:
        session, proc = start(rig, out, CapturePlan(POSES4), write_hook=hook)
        with pytest.raises(KeyboardInterrupt):
            run_session(rig, session, processor=proc, progress=progress)
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert s.manifest["status_reason"] == "interrupted by the operator (Ctrl-C)"
    assert [c["status"] for c in s.captures] == [COMPLETE, PENDING, PENDING, PENDING]
    assert s.verify() == []


class _SignalDuringProcessing(processing.Processor):
    """The real processor; while processing capture 1 it waits until capture 2 is acquired
    (the run is then waiting for capture 1's processing before handing capture 2 over) and
    sends this process SIGINT, as an operator's Ctrl-C at that moment would."""

    acquired_2 = None

    def process(self, session, index, revision=None):
        import os
        import signal

        if index == 1:
            assert self.acquired_2.wait(60), "capture 2 was never acquired"
            os.kill(os.getpid(), signal.SIGINT)
        return super().process(session, index, revision)


def test_sigint_while_a_pose_is_processed_in_the_background_then_resume(tmp_path,
                                                                         reference_session):
    """Processing overlaps acquisition: SIGINT arrives while capture 1 is processed in the
    worker and capture 2 is acquired. Capture 1's processing ends (complete), capture 2 stays
    "acquired", capture 3 was never started. The resume processes capture 2 without
    acquiring it again (same raw files, sidecars included, one attempt, only capture 3's
    frames grabbed) and the session is identical to an uninterrupted one."""
    import threading

    out = tmp_path / "s"
    acquired_2 = threading.Event()

    def progress(ev):
        if ev.kind == "capture-acquired" and ev.capture_index == 2:
            acquired_2.set()

    with sim_rig() as rig:
        plan = CapturePlan(POSES4)
        session = create_session(out, rig, plan, calibration_id=EXACT.id)
        proc = _SignalDuringProcessing(plan.mode, plan.demosaic, EXACT,
                                       processing.session_sensor_model(session))
        proc.acquired_2 = acquired_2
        with pytest.raises(KeyboardInterrupt):
            run_session(rig, session, processor=proc, progress=progress)
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert s.manifest["status_reason"] == "interrupted by the operator (Ctrl-C)"
    assert [c["status"] for c in s.captures] == [COMPLETE, COMPLETE, "acquired", PENDING]
    assert set(s.capture(2)["files"]) == {"raw", "truth_mueller"}  # no result, nothing partial
    assert s.verify() == []
    raw_2 = s.capture(2)["files"]["raw"]
    frames = []
    with sim_rig() as rig:
        s2, result = resume(rig, out, progress=lambda ev: frames.append(ev)
                            if ev.kind == "frame" else None)
    assert result.status == "complete" and sorted(result.completed) == [0, 1, 2, 3]
    assert {ev.capture_index for ev in frames} == {3} and len(frames) == 4  # capture 3 only
    assert s2.capture(2)["files"]["raw"] == raw_2 and s2.capture(2)["attempts"] == 1
    assert s2.verify() == []
    assert content(s2) == content(reference_session)


def _processing_fails_at_capture_1(out: pathlib.Path) -> Session:
    """A four-pose session whose processing of capture 1 raises ``RuntimeError("solver blew
    up")`` in the worker: the run ends with it (raised here as pytest expects) and the session is
    returned as left on disk."""

    class Failing(processing.Processor):
        def process(self, session, index, revision=None):
            if index == 1:
                raise RuntimeError("solver blew up")
            return super().process(session, index, revision)

    with sim_rig() as rig:
        plan = CapturePlan(POSES4)
        session = create_session(out, rig, plan, calibration_id=EXACT.id)
        proc = Failing(plan.mode, plan.demosaic, EXACT, processing.session_sensor_model(session))
        with pytest.raises(RuntimeError, match="solver blew up"):
            run_session(rig, session, processor=proc)
    return Session.open(out)


def test_processing_error_leaves_the_capture_acquired_and_resume_processes_it(tmp_path,
                                                                              reference_session):
    """A processing error (in the worker) ends the run like before (session interrupted,
    the error raised for the caller to report), but the capture keeps its raw frames as
    "acquired" with the reason; the resume processes it without acquiring it again."""
    out = tmp_path / "s"
    s = _processing_fails_at_capture_1(out)
    assert s.manifest["status"] == INTERRUPTED and "RuntimeError" in s.manifest["status_reason"]
    assert s.capture(1)["status"] == "acquired"
    assert "processing failed: RuntimeError: solver blew up" == s.capture(1)["reason"]
    assert s.verify() == []
    with sim_rig() as rig:
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert s2.capture(1)["attempts"] == 1
    assert content(s2) == content(reference_session)


def test_a_write_a_crash_cut_short_in_an_acquired_capture_is_gone_after_the_resume(tmp_path, reference_session):
    """A crash (SIGKILL: no clean-up runs) while an acquired capture's result was being written
    leaves the atomic write's temporary sibling in its folder, recorded nowhere. The resume
    processes the capture again and deletes that leftover: the session verifies clean and equals
    an uninterrupted one."""
    from polrig.atomic import temporary_sibling

    out = tmp_path / "s"
    s = _processing_fails_at_capture_1(out)  # capture 1 left "acquired", as a crash leaves it
    assert s.capture(1)["status"] == "acquired"
    leftover = temporary_sibling(s.capture_dir(1) / "mueller.exr")
    leftover.write_bytes(b"\x76\x2f\x31\x01 half an EXR")
    assert s.verify() == [f"{s.relpath(leftover)}: not recorded in the manifest"]
    with sim_rig() as rig:
        s2, result = resume(rig, out)
    assert result.status == "complete"
    assert not leftover.exists()
    assert s2.verify() == []
    assert content(s2) == content(reference_session)


@pytest.mark.parametrize("damage", ["changed", "missing"])
def test_an_acquired_capture_whose_raw_data_is_damaged_is_set_aside_and_acquired_again(
        tmp_path, reference_session, damage, capsys):
    """An acquired capture whose recorded raw frame changed or went missing can never be
    processed: each resume used to process it first, fail on the checksum and stop, so the
    session never went on (the captures after it never acquired). Now the resume moves its
    folder, whole, to ``damaged/`` (nothing deleted), says so (a ``retry`` event and the
    history) and acquires it again at its pose: the session completes, equal to an
    uninterrupted one (the simulated rig gives the same frames)."""
    out = tmp_path / "s"
    s = _processing_fails_at_capture_1(out)
    assert [c["status"] for c in s.captures] == [COMPLETE, "acquired", PENDING, PENDING]
    raw = s.capture(1)["files"]["raw"][3]["path"]
    if damage == "changed":
        data = bytearray((out / raw).read_bytes())
        data[len(data) // 2] ^= 0xFF
        (out / raw).write_bytes(bytes(data))
    else:
        (out / raw).unlink()
    before = sorted(p.relative_to(out / s.capture(1)["name"])
                    for p in s.capture_dir(1).rglob("*"))
    events = []
    with sim_rig() as rig:
        s2, result = resume(rig, out, progress=events.append)
    assert result.status == "complete"
    problem = f"{raw}: {'SHA-256 mismatch' if damage == 'changed' else 'missing'} (capture 1, raw)"
    retries = [e.message for e in events if e.kind == "retry"]
    assert retries == [f"capture 2/4: its recorded raw data is damaged ({problem}); the capture "
                       f"is acquired again, its old folder kept in damaged/c001_pose090.0-1"]
    kept = out / "damaged" / "c001_pose090.0-1"
    assert sorted(p.relative_to(kept) for p in kept.rglob("*")) == before  # nothing lost
    event = [h for h in s2.manifest["history"] if h["event"] == "capture set aside"]
    assert [(h["capture"], h["problems"], h["kept"]) for h in event] == [
        (1, [problem], "damaged/c001_pose090.0-1")]
    assert s2.verify() == []
    assert content(s2) == content(reference_session)
    with pytest.raises(SessionError, match="capture 1 is complete, not acquired"):
        s2.set_aside_damaged(1)
    # polrig info says so under the capture
    from polrig.cli import main

    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert (f"set aside ({event[0]['time']}): {problem}; acquired again, the old folder kept in "
            f"damaged/c001_pose090.0-1") in info


def test_a_deeper_processing_queue_gives_the_same_session(tmp_path, reference_session):
    """``max_queued=3``: acquisition runs ahead of processing (captures wait, in order, for
    the one worker); the session is the same as with the default hand-over."""
    events = []
    with sim_rig() as rig:
        session, proc = start(rig, tmp_path / "s", CapturePlan(POSES4))
        result = run_session(rig, session, processor=proc, max_queued=3,
                             progress=events.append)
    assert result.status == "complete"
    done = [e.capture_index for e in events if e.kind == "capture-done"]
    assert done == [0, 1, 2, 3]
    assert content(session) == content(reference_session)
    with pytest.raises(ValueError, match="max_queued"):
        run_session(rig, session, max_queued=0)


def test_run_capture_takes_a_request_end_to_end(tmp_path):
    """The one capture call: its first event says the session exists, the rest are the run's
    progress (a done capture names its result file); a stop is a result; a refusal before the
    session exists is raised and leaves the session's lock free; a resume continues it."""
    from polrig.acquisition.plan import PlanError
    from polrig.app.capture import CaptureRequest, SessionOpened, run_capture

    out = tmp_path / "s"
    control = CaptureControl()
    events = []

    def on(ev):
        events.append(ev)
        if isinstance(ev, SessionOpened):
            assert (out / "session.json").is_file()  # it exists when it is said to
        elif ev.kind == "capture-acquired" and ev.capture_index == 0:
            control.stop.set()

    request = CaptureRequest(out=out, poses_deg=(0.0, 90.0))
    result = run_capture(request, command_line=["test"], rig=sim_rig, events=on, control=control)
    assert events[0] == SessionOpened(out, False, 2)
    assert all(not isinstance(e, SessionOpened) for e in events[1:])
    assert result.status == INTERRUPTED and result.reason == "stopped by the operator"
    [done] = [e for e in events if getattr(e, "kind", "") == "capture-done"]
    assert done.result == out / "c000_pose000.0" / "mueller.exr" and done.result.is_file()
    before = (out / "session.json").read_bytes()
    with pytest.raises(PlanError, match="planned with poses_deg"):
        run_capture(CaptureRequest(out=out, poses_deg=(0.0,), resume=True), command_line=["x"],
                    rig=sim_rig)
    assert (out / "session.json").read_bytes() == before
    Session.open(out, lock=True).unlock()  # not held by the refused call
    events.clear()
    result = run_capture(CaptureRequest(out=out, resume=True), command_line=["test", "--resume"],
                         rig=sim_rig, events=events.append)
    assert events[0] == SessionOpened(out, True, 2) and result.status == "complete"
    assert [c["status"] for c in Session.open(out).captures] == [COMPLETE, COMPLETE]
