"""The faster single-shot mode, network binning 2 (issue 22), in sessions: ``polrig capture
--network-binning 2`` and ``polrig reconstruct --network-binning`` end to end on the simulated
rig, the plan field and revision setting, refusals with the reference method, and sessions
from before the field existed resuming to the same files."""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest

from polrig.acquisition.plan import PlanError
from polrig.app import processing, reconstruct
from polrig.app.capture import (
    CaptureControl,
    CapturePlan,
    CaptureRequest,
    create_session,
    run_session,
)
from polrig.app.rig import open_rig
from polrig.app.session import COMPLETE, PENDING, Session
from polrig.cli import main
from polrig.formats.exr import read_mueller_exr

REPO = pathlib.Path(__file__).resolve().parents[1]
MODEL_INSTALLED = (REPO / "models" / "weights" / "single_shot.onnx").is_file()
needs_model = pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")


def sim_config(path: pathlib.Path, size: str = "128x128") -> pathlib.Path:
    path.write_text(f'[sim]\nsize = "{size}"\nclock_speed = inf\nseed = 3\n')
    return path


def result(root: pathlib.Path, index: int = 0, revision: str | None = None):
    s = Session.open(root)
    cap = s.capture(index)
    files = cap["files"] if revision is None else cap["revisions"][revision]["files"]
    return read_mueller_exr(root / files["mueller"]["path"])


@needs_model
def test_capture_and_reconstruct_with_network_binning_2(tmp_path, capsys):
    """``capture --network-binning 2``: the plan records it; the result is on the same grid as
    the default's, finite inside the object, close to it and to the truth (scored within 3 dB
    of the default), with NaN sigma planes, the header saying why and recording the binning.
    ``reconstruct --network-binning 2`` of a binning-1 session records the setting in a new
    revision and gives the binned capture's image bit for bit (same raw frames: the simulator
    is seeded); ``--network-binning 1`` back gives the default capture's, sigma included."""
    cfg = sim_config(tmp_path / "rig.toml")
    one, two = tmp_path / "one", tmp_path / "two"
    for out, extra in ((one, []), (two, ["--network-binning", "2"])):
        assert main(["capture", "--poses", "0", "--mode", "single-shot", *extra, "--device", "cpu",
                     "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    s1, s2 = Session.open(one), Session.open(two)
    assert s1.plan.network_binning == 1 and s2.plan.network_binning == 2
    assert "--network-binning" in s2.manifest["command_line"]
    a, b = result(one), result(two)
    assert a.mueller.shape == b.mueller.shape == (3, 3, 3, 32, 32)
    # binning 1 is the header's default (no key: such a result is byte-identical to one written
    # before the option existed); 2 is recorded
    assert "network_binning" not in a.metadata and b.metadata["network_binning"] == 2
    assert b.metadata["resolution"] == "superpixel" and b.metadata["beyond_calibration_fraction"] is None
    assert "NaN" in b.metadata["planes"]["sigma.M{rc}"] and "binning 2" in b.metadata["planes"]["sigma.M{rc}"]
    assert all(np.all(np.isnan(b.extra[f"sigma.M{r}{c}.{k}"])) for r in range(3) for c in range(3) for k in "RGB")
    assert not np.any(np.isnan(a.extra["sigma.M00.G"]))  # the default keeps its calibrated sigma (inf: clipped)
    obj = (a.extra["mask.G"] == 0) & (b.extra["mask.G"] == 0)
    assert obj.sum() > 150
    assert np.all(np.isfinite(b.mueller[..., obj]))
    assert not np.array_equal(b.mueller[..., obj], a.mueller[..., obj])  # a quarter of the network work
    # ... and as close to the truth (on the same pixels): within 3 dB, the MAE within half again
    sa, sb = s1.captures[0]["score"], s2.captures[0]["score"]
    assert sb["within_2sigma"] is None  # no sigma to judge
    assert abs(sb["pixels_compared"] - sa["pixels_compared"]) < 0.05 * sa["pixels_compared"]
    assert sb["psnr_db"] > 25 and sb["psnr_db"] > sa["psnr_db"] - 3.0, (sa, sb)
    assert sb["mae"] < 1.5 * sa["mae"] and sb["realizable"] > 0.9, (sa, sb)
    capsys.readouterr()
    assert main(["reconstruct", str(one), "--network-binning", "2", "--no-progress"]) == 0
    s1 = Session.open(one)
    assert [(r["name"], r["network_binning"]) for r in s1.manifest["revisions"]] == [("rev1", 2)]
    assert s1.capture(0)["revisions"]["rev1"]["status"] == COMPLETE
    rev1 = result(one, revision="rev1")
    assert rev1.metadata["network_binning"] == 2
    np.testing.assert_array_equal(rev1.mueller, b.mueller)
    # the binned session reconstructs with its own binning by default, and back to 1 on request
    assert main(["reconstruct", str(two), "--no-progress"]) == 0
    assert main(["reconstruct", str(two), "--network-binning", "1", "--no-progress"]) == 0
    s2 = Session.open(two)
    assert [r["network_binning"] for r in s2.manifest["revisions"]] == [2, 1]
    np.testing.assert_array_equal(result(two, revision="rev1").mueller, b.mueller)
    back = result(two, revision="rev2")
    np.testing.assert_array_equal(back.mueller, a.mueller)
    np.testing.assert_array_equal(back.extra["sigma.M00.G"], a.extra["sigma.M00.G"])
    assert s1.verify() == [] and s2.verify() == []


@needs_model
def test_binning_composes_with_full_resolution(tmp_path):
    """``--resolution full --network-binning 2``: binned networks, lifted to the analyzer grid,
    then to the raw grid (as ``polrig infer``): the raw frame's size, NaN sigma, both reasons in
    the header, scored on the raw grid."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "full"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--resolution", "full",
                 "--network-binning", "2", "--device", "cpu", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    r = result(out)
    assert r.mueller.shape == (3, 3, 3, 128, 128)
    md = r.metadata
    assert (md["resolution"], md["network_binning"], md["output_demosaic"]) == ("full", 2, "bilinear")
    assert "full resolution" in md["planes"]["sigma.M{rc}"] and "binning 2" in md["planes"]["sigma.M{rc}"]
    assert np.all(np.isnan(r.extra["sigma.M11.R"]))
    valid = r.extra["mask.G"] == 0
    assert valid.sum() > 32 * 32 and np.all(np.isfinite(r.mueller[..., valid]))
    score = Session.open(out).captures[0]["score"]
    assert score["pixels_compared"] > 32 * 32 and score["psnr_db"] > 25


@needs_model
def test_binning_with_the_reference_method_is_refused_in_one_line(tmp_path, capsys):
    """``--network-binning 2`` with the reference method (capture, reconstruct) and the
    :class:`Processor` itself: one line naming the option (exit 2), nothing written; a resume
    that asks for another binning than the session's is refused too."""
    cfg = sim_config(tmp_path / "rig.toml", "64x64")
    out = tmp_path / "ref"
    capsys.readouterr()
    assert main(["capture", "--poses", "0", "--network-binning", "2", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--network-binning 2: network binning applies to the single-shot" in err, err
    assert not out.exists()
    ss = tmp_path / "ss"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--config", str(cfg),
                 "--out", str(ss), "--no-progress"]) == 0
    before = (ss / "session.json").read_bytes()
    capsys.readouterr()
    assert main(["reconstruct", str(ss), "--mode", "reference", "--network-binning", "2",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--network-binning 2" in err and "single-shot" in err, err
    assert main(["capture", "--out", str(ss), "--resume", "--network-binning", "2",
                 "--config", str(cfg), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--network-binning" in err and "network_binning=1" in err, err
    assert (ss / "session.json").read_bytes() == before
    with pytest.raises(PlanError, match="network binning 2: network binning applies") as e:
        processing.Processor("reference", "superpixel", processing.Calibration("ideal"),
                             processing.session_sensor_model(Session.open(ss)), network_binning=2)
    assert e.value.field == "network_binning"
    with pytest.raises(PlanError, match="network binning 4: must be one of 1, 2"):
        processing.Processor("single-shot", "superpixel", processing.Calibration("ideal"),
                             processing.session_sensor_model(Session.open(ss)), network_binning=4)


def _sim_rig():
    return open_rig(None, size=(128, 128), sensor="imx250myr", clock_speed=math.inf, seed=3)


def _content(root: pathlib.Path) -> list:
    """Per capture its pose, status and every file's path and checksum (sidecars hold clock
    timestamps: their presence only)."""
    s = Session.open(root)
    return [(c["pose_deg"], c["status"], sorted((role, r["path"], r["sha256"], r.get("meta_path"))
                                                 for _, role, r in s.iter_file_records(c)))
            for c in s.captures]


@needs_model
def test_a_session_from_before_the_field_resumes_to_identical_results(tmp_path):
    """A single-shot session whose plan has no ``network_binning`` (written before it existed),
    stopped after its first pose and resumed as ``polrig capture --resume`` does (the request's
    plan from the session, :func:`polrig.app.processing.make_processor`), is the same files as an
    uninterrupted session of today: it runs with binning 1."""
    from polrig.app import capture

    cal = processing.load_calibration(None)
    plan = CapturePlan((0.0, 90.0), mode="single-shot")
    ref = tmp_path / "ref"
    with _sim_rig() as rig:
        s = create_session(ref, rig, plan, calibration_id=cal.id)
        proc = processing.make_processor(plan, cal, processing.session_sensor_model(s), "cpu")
        assert run_session(rig, s, processor=proc).status == COMPLETE
    old = tmp_path / "old"
    control = CaptureControl()

    def stop_after_first(ev):
        if ev.kind == "capture-acquired" and ev.capture_index == 0:
            control.stop.set()

    with _sim_rig() as rig:
        s = create_session(old, rig, plan, calibration_id=cal.id)
        proc = processing.make_processor(plan, cal, processing.session_sensor_model(s), "cpu")
        run_session(rig, s, processor=proc, progress=stop_after_first, control=control)
    assert [c["status"] for c in Session.open(old).captures] == [COMPLETE, PENDING]
    manifest = json.loads((old / "session.json").read_text())
    manifest["schema_version"] = 1  # as a session from before the field
    del manifest["plan"]["network_binning"]
    (old / "session.json").write_text(json.dumps(manifest, indent=2))
    assert Session.open(old).plan.network_binning == 1  # migrated: the value it was captured with
    request = CaptureRequest(out=old, resume=True, device="cpu")
    run = capture.run_capture(request, command_line=["polrig", "capture", "--resume"],
                              rig=_sim_rig)
    assert run.status == COMPLETE
    assert _content(old) == _content(ref)
    stored = json.loads((old / "session.json").read_text())  # written in this version, stated
    assert stored["schema_version"] == 7 and stored["plan"]["network_binning"] == 1
    assert [h["from_version"] for h in stored["history"] if h["event"] == "schema migrated"] == [1, 2, 3, 4, 5, 6]
    # and a reconstruct of it defaults to binning 1 too, recorded with the revision
    s = Session.open(old)
    s.lock()
    try:
        name = reconstruct.reprocess_session(s, device="cpu")
    finally:
        s.unlock()
    s = Session.open(old)
    assert s.manifest["revisions"][0]["network_binning"] == 1
    np.testing.assert_array_equal(result(old, 1, name).mueller, result(ref, 1).mueller)


@needs_model
def test_cluster_jobs_carry_the_binning_and_old_revisions_continue(tmp_path):
    """:mod:`polrig.app.cluster`: a job carries the revision's binning and the worker's processor is
    keyed by it (two binnings, two processors); ``reconstruct --workers 2 --network-binning 2`` is
    byte for byte the serial :func:`polrig.app.reconstruct.reprocess_session`; an interrupted revision
    written before the setting existed (no ``network_binning``) is continued by a binning-1
    request, not by a binning-2 one."""
    import shutil

    from polrig.app import cluster

    cfg = sim_config(tmp_path / "rig.toml")
    src = tmp_path / "src"
    assert main(["capture", "--poses", "0,90", "--mode", "single-shot", "--device", "cpu",
                 "--config", str(cfg), "--out", str(src), "--no-progress"]) == 0
    # the worker's side, in process: the job of each binning and its processor
    sessions = cluster.open_sessions([shutil.copytree(src, tmp_path / "jobs")])
    try:
        jobs = {}
        for binning in (1, 2):
            [batch] = cluster.prepare(sessions, network_binning=binning, device="cpu")
            assert batch.settings["network_binning"] == binning
            jobs[binning] = cluster.jobs_of(batch, None)[0]
            assert jobs[binning].network_binning == binning
        procs = {b: cluster._processor(job, sessions[0]) for b, job in jobs.items()}
        assert procs[1] is not procs[2]
        assert (procs[1].network_binning, procs[2].network_binning) == (1, 2)
        assert cluster._processor(jobs[2], sessions[0]) is procs[2]  # made once per settings
        # rev2 (binning 2) is pending: a binning-1 request makes a new revision ...
        [batch] = cluster.prepare(sessions, network_binning=1, device="cpu")
        assert (batch.revision, batch.continued) == ("rev3", False)
        # ... but one written before the setting existed (schema version 1) is binning 1:
        # continued
        s = sessions[0]
        m = json.loads((s.root / "session.json").read_text())
        m["schema_version"] = 1
        del m["revisions"][-1]["network_binning"]
        (s.root / "session.json").write_text(json.dumps(m))
        s.reload()
        assert s.manifest["revisions"][-1]["network_binning"] == 1
        [batch] = cluster.prepare(sessions, network_binning=None, device="cpu")
        assert (batch.revision, batch.continued) == ("rev3", True)
        [batch] = cluster.prepare(sessions, network_binning=2, device="cpu")
        assert (batch.revision, batch.continued) == ("rev4", False)
    finally:
        for s in sessions:
            s.unlock()
    pytest.importorskip("distributed")
    serial, dist = shutil.copytree(src, tmp_path / "serial"), shutil.copytree(src, tmp_path / "dist")
    reconstruct.reprocess_session(Session.open(serial), network_binning=2, device="cpu")
    assert main(["reconstruct", str(dist), "--workers", "2", "--network-binning", "2", "--device", "cpu",
                 "--no-progress"]) == 0
    for d in (serial, dist):
        s = Session.open(d)
        assert s.manifest["revisions"][0]["network_binning"] == 2 and s.verify() == []
    for i in range(2):
        a, b = result(serial, i, "rev1"), result(dist, i, "rev1")
        assert a.metadata["network_binning"] == b.metadata["network_binning"] == 2
        path = Session.open(dist).capture(i)["revisions"]["rev1"]["files"]["mueller"]["path"]
        assert (serial / path).read_bytes() == (dist / path).read_bytes()
