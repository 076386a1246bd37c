"""``polrig capture`` / ``reconstruct`` / ``info`` end to end on the simulated rig."""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from polrig.app.session import Session
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.cli import main

REPO = pathlib.Path(__file__).resolve().parents[1]
MODEL_INSTALLED = (REPO / "models" / "weights" / "single_shot.onnx").is_file()


def sim_config(path: pathlib.Path, *, noise: bool = True, clock_speed: str = "inf",
               scene: str = "box", ideal: bool = True) -> pathlib.Path:
    hidden = ("\n[sim.hidden]\nstage_zero_offset_deg = 0.0\nextinction_ratio = 1e12\n"
              "ideal_analyzer = true\n") if ideal else ""
    path.write_text(f'[sim]\nsize = "64x64"\nsensor = "imx250mzr"\nclock_speed = {clock_speed}\n'
                    f'seed = 11\nscene = "{scene}"\nnoise = {str(noise).lower()}\n{hidden}')
    return path


def test_capture_completes_with_scores_then_info_and_reconstruct(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    rc = main(["capture", "--poses", "0:360:90", "--mode", "reference", "--config", str(cfg),
               "--out", str(out), "--no-progress"])
    printed = capsys.readouterr().out
    assert rc == 0
    assert printed.count("within 2 sigma") == 4 and "session complete: 4 captures" in printed
    s = Session.open(out)
    assert [c["pose_deg"] for c in s.captures] == [0.0, 90.0, 180.0, 270.0]
    assert all(c["status"] == "complete" for c in s.captures)
    assert s.manifest["calibration_id"] == "nominal"
    assert s.manifest["command_line"] == ["polrig", "capture", "--poses", "0:360:90", "--mode",
                                          "reference", "--config", str(cfg), "--out", str(out),
                                          "--no-progress"]
    assert s.manifest["rig"]["simulated"] is True
    for cap in s.captures:
        assert cap["score"]["within_2sigma"] > 0.9
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    # 40 frame, sidecar, truth and result files, and 3 previews per capture
    assert "4 complete" in info and "checksums: all 52 files verified" in info
    assert main(["reconstruct", str(out), "--demosaic", "bilinear", "--no-progress"]) == 0
    s = Session.open(out)
    assert s.manifest["revisions"][0]["name"] == "rev1"
    assert all(c["revisions"]["rev1"]["status"] == "complete" for c in s.captures)
    assert s.verify() == []
    # a changed raw frame is found by info
    raw = out / s.capture(2)["files"]["raw"][1]["path"]
    raw.write_bytes(raw.read_bytes() + b"\0")
    assert main(["info", str(out)]) == 1
    assert "SHA-256 mismatch" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--poses", "0:360"], "invalid pose spec"),
    (["--poses", "zero,90"], "invalid pose spec"),
    (["--poses", "0", "--states", "0,90"], "at least 3"),
    (["--poses", "0", "--states", "0,180,360"], "collinear"),
    (["--poses", "0", "--states", "0,5,10"], "condition number"),
    (["--poses", "0", "--frames", "0"], "--frames"),
    (["--poses", "0", "--exposure", "-5"], "--exposure"),
    # checked before the session is created (they used to leave a session.json behind)
    (["--poses", "0", "--exposure", "1e12"], "--exposure 1e+12 us: outside the camera's range [10, 1e+07] us"),
    (["--poses", "0", "--exposure", "1000,5"], "--exposure 5 us: outside the camera's range"),
    (["--poses", "1e308,1e308"], "invalid pose spec: pose 1e+308 deg is not a finite angle"),
    (["--poses", "0,40000"], "within +-36000 deg"),
    (["--poses", "0", "--states", "0,45,90,1e300"], "--states 1e+300 deg: not a polarizer angle"),
    (["--poses", "0", "--config", "/nonexistent/rig.toml"], "no such file"),
    (["--poses", "0", "--mode", "single-shot"], "single-shot"),
    # single-shot captures one state: several are refused, not recorded as if captured
    (["--poses", "0", "--mode", "single-shot", "--states", "0,45"],
     "--states: the single-shot method captures one polarizer state per pose"),
    (["--poses", "0", "--mirror-average"], "--mirror-average: mirror averaging applies to the network's methods only"),
    (["--poses", "0", "--prior-scale", "calibrated"], "--prior-scale calibrated: applies to the hybrid and adaptive"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, monkeypatch, args, message):
    if "single-shot" in args:  # no model installed: point the runtime at an empty folder
        from polrig.models import sizes

        monkeypatch.setitem(sizes.SIZE_FOLDERS, "small", tmp_path / "no-weights")
    out = tmp_path / "out"
    rc = main(["capture", *args, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and message in err, err
    assert not out.exists()  # nothing was created


def test_non_empty_output_without_resume_exits_2(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.exr").write_bytes(b"data")
    rc = main(["capture", "--poses", "0", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "not empty" in err and "--resume" in err
    assert len(err.strip().splitlines()) == 1
    assert (out / "precious.exr").read_bytes() == b"data"


def test_resume_refuses_a_different_plan(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                 "--resume", "--no-progress"]) == 2
    assert "planned with poses_deg" in capsys.readouterr().err
    # nothing left to do: resume is a no-op that succeeds
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0


def spawn_capture(cfg: pathlib.Path, out: pathlib.Path, poses: str = "0:360:90",
                  *extra: str) -> subprocess.Popen:
    """``polrig capture`` in a child process, its output unbuffered, after its first capture
    is done (the first stdout line is read and checked). A shell without job control starts
    background jobs with SIGINT ignored, and an ignored SIGINT is inherited: the child gets
    the default disposition so Python installs its Ctrl-C handler however the test runner was
    started."""
    proc = subprocess.Popen([sys.executable, "-m", "polrig", "capture", "--poses", poses,
                             "--config", str(cfg), "--out", str(out), "--no-progress", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=REPO,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    line = proc.stdout.readline()
    if not ("capture 1/" in line and "done" in line):
        proc.kill()
        raise AssertionError(line + proc.communicate(timeout=60)[1])
    return proc


def content(root: pathlib.Path) -> list:
    s = Session.open(root)
    return [(c["pose_deg"], c["status"],
             sorted((role, r["path"], r["sha256"]) for _, role, r in s.iter_file_records(c)))
            for c in s.captures]


@pytest.mark.skipif(not pathlib.Path("/proc/self/maps").is_file(), reason="reads Linux /proc")
def test_ctrl_c_while_the_commands_load_is_one_line(tmp_path):
    """A Ctrl-C in the first few hundred milliseconds, while the commands' modules load
    (numpy, the session code), printed Python's ``KeyboardInterrupt`` traceback: only the
    command's own run was guarded. Sent here as numpy's core extension is being loaded."""
    cfg = sim_config(tmp_path / "rig.toml")
    proc = subprocess.Popen([sys.executable, "-m", "polrig", "capture", "--poses", "0:360:90",
                             "--config", str(cfg), "--out", str(tmp_path / "s"), "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    maps = pathlib.Path(f"/proc/{proc.pid}/maps")
    deadline = time.monotonic() + 60
    while proc.poll() is None and time.monotonic() < deadline:
        with contextlib.suppress(OSError):
            if "_multiarray_umath" in maps.read_text():
                break
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "polrig: interrupted", err


@pytest.mark.slow
def test_sigint_mid_session_then_resume_equals_uninterrupted(tmp_path):
    """SIGINT to a running ``polrig capture`` after its first capture, then ``--resume``:
    the session has the same captures and files (checksums) as an uninterrupted run, with the
    sensor noise on (the simulator keys noise by pose, state and repeat index)."""
    cfg = sim_config(tmp_path / "rig.toml", noise=True, clock_speed="40")  # ~0.5 s/capture
    poses = "0:360:90"
    ref = tmp_path / "ref"
    assert main(["capture", "--poses", poses, "--config", str(sim_config(tmp_path / "fast.toml",
                 noise=True)), "--out", str(ref), "--no-progress"]) == 0
    out = tmp_path / "run"
    proc = spawn_capture(cfg, out, poses)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    s = Session.open(out)
    assert s.manifest["status"] == "interrupted"
    statuses = [c["status"] for c in s.captures]
    assert statuses[0] == "complete" and "pending" in statuses
    assert s.verify() == []
    assert main(["capture", "--config", str(tmp_path / "fast.toml"), "--out", str(out),
                 "--resume", "--no-progress"]) == 0
    assert content(out) == content(ref)
    assert Session.open(out).verify() == []
    history = [h["event"] for h in Session.open(out).manifest["history"]]
    assert "resumed" in history


def test_injected_fault_stops_cleanly_and_cli_resumes(tmp_path, capsys, monkeypatch):
    """A device that disconnects mid-session: exit 1 with the reason, the manifest names it,
    ``--resume`` completes the session with the same content as an uninterrupted run."""
    import polrig.app.rig

    cfg = sim_config(tmp_path / "rig.toml", noise=True)
    ref = tmp_path / "ref"
    assert main(["capture", "--poses", "0,90,180", "--config", str(cfg), "--out", str(ref),
                 "--no-progress"]) == 0
    real_open = polrig.app.rig.open_rig

    def faulty_open(*a, **kw):
        rig = real_open(*a, **kw)
        # stage calls: position (hardware time), home, then per move position, move_to, wait;
        # call 15 starts capture 1's first move (with the turntable)
        rig.faults.inject_fault("stage", "disconnect", after_calls=15)
        return rig

    monkeypatch.setattr(polrig.app.rig, "open_rig", faulty_open)
    out = tmp_path / "run"
    capsys.readouterr()
    rc = main(["capture", "--poses", "0,90,180", "--config", str(cfg), "--out", str(out),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and "--resume" in err and "DeviceDisconnected" in err
    m = json.loads((out / "session.json").read_text())
    assert m["status"] == "interrupted" and "connection lost" in m["status_reason"]
    assert [c["status"] for c in m["captures"]].count("failed") == 1
    monkeypatch.setattr(polrig.app.rig, "open_rig", real_open)
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0
    assert content(out) == content(ref)


def test_a_resumed_session_goes_on_with_its_models_and_refuses_others(tmp_path, capsys, monkeypatch):
    """The session records how its captures are processed (``--models``, ``--prior-scale``):
    interrupted by a device fault in its second capture, ``--resume`` without the options ends
    with the content of an uninterrupted run (every result with its model map), and asking
    for other models is refused in one line naming the option, before anything moves."""
    import polrig.app.rig

    cfg = sim_config(tmp_path / "rig.toml", noise=True)
    args = ["--poses", "0,90,180", "--models", "auto", "--config", str(cfg)]
    ref = tmp_path / "ref"
    assert main(["capture", *args, "--out", str(ref), "--no-progress"]) == 0
    real_open = polrig.app.rig.open_rig

    def faulty_open(*a, **kw):
        rig = real_open(*a, **kw)
        rig.faults.inject_fault("stage", "disconnect", after_calls=15)  # in capture 1 (as above)
        return rig

    monkeypatch.setattr(polrig.app.rig, "open_rig", faulty_open)
    out = tmp_path / "run"
    assert main(["capture", *args, "--out", str(out), "--no-progress"]) == 1
    monkeypatch.setattr(polrig.app.rig, "open_rig", real_open)
    s = Session.open(out)
    assert s.manifest["processing"] == {"models": "auto", "prior_scale": DEFAULT_PRIOR_SCALE}
    assert [c["status"] for c in s.captures].count("complete") == 1
    capsys.readouterr()
    assert main(["info", str(out), "--no-verify"]) == 0
    assert "  processing: models auto (a resume goes on with these)\n" in capsys.readouterr().out
    before = (out / "session.json").read_bytes()
    for option, why in ((["--models", "full"], "leave it out"), (["--prior-scale", "geometry"], "hybrid and adaptive")):
        rc = main(["capture", "--config", str(cfg), "--out", str(out), "--resume", *option, "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and len(err.strip().splitlines()) == 1 and option[0] in err and why in err, err
        assert (out / "session.json").read_bytes() == before
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume", "--no-progress"]) == 0
    assert content(out) == content(ref)
    assert all("models" in c["files"] for c in Session.open(out).captures)  # each result's model map


@pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")
def test_single_shot_capture_with_the_installed_model(tmp_path, capsys):
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "128x128"\nclock_speed = inf\nseed = 3\n')
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0,180", "--mode", "single-shot", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    s = Session.open(out)
    assert s.plan.states_deg == (0.0,)  # the plan records the one state captured
    for cap in s.captures:
        assert len(cap["files"]["raw"]) == 1  # one state, one frame
        assert cap["score"]["pixels_compared"] > 0 and cap["score"]["psnr_db"] > 20
    assert s.verify() == []
    # one state per pose cannot be reconstructed by the reference method: one line, no revision
    before = (out / "session.json").read_bytes()
    capsys.readouterr()
    assert main(["reconstruct", str(out), "--mode", "reference", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "captured in single-shot mode" in err and "the single-shot method" in err and len(err.strip().splitlines()) == 1
    assert (out / "session.json").read_bytes() == before


@pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")
def test_single_shot_mirror_average_is_planned_recorded_and_reprocessable(tmp_path, capsys):
    """``--mirror-average`` reaches the plan and the processing (polrig.models.mirror), a resumed
    session keeps it, and ``reconstruct --no-mirror-average`` writes a revision without it."""
    from polrig.formats.exr import read_mueller_exr

    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "128x128"\nclock_speed = inf\nseed = 3\n')
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--mirror-average", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 0
    s = Session.open(out)
    assert s.plan.mirror_average is True and s.captures[0]["score"]["psnr_db"] > 20
    capsys.readouterr()
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--config", str(cfg), "--out", str(out),
                 "--resume", "--no-progress"]) == 0  # the stored plan holds, nothing left to do
    assert main(["reconstruct", str(out), "--no-mirror-average", "--no-progress"]) == 0
    s = Session.open(out)
    rev = s.capture(0)["revisions"]["rev1"]
    assert [r["mirror_average"] for r in s.manifest["revisions"] if r["name"] == "rev1"] == [False]
    mirrored = read_mueller_exr(out / s.capture(0)["files"]["mueller"]["path"]).mueller
    single = read_mueller_exr(out / rev["files"]["mueller"]["path"]).mueller
    assert np.all(np.isfinite(mirrored)) and np.all(np.isfinite(single))
    assert not np.allclose(mirrored, single)
    # a wrong mirror transform scores far worse; here the average is 4.4 dB better (38.1 against 33.7)
    assert s.captures[0]["score"]["psnr_db"] > rev["score"]["psnr_db"] - 1.0


@pytest.mark.slow
def test_crash_mid_session_then_resume_equals_uninterrupted(tmp_path):
    """SIGKILL (a crash: no clean-up runs) after the first capture, then ``--resume``: the
    manifest on disk was consistent, and the resumed session equals an uninterrupted one."""
    cfg = sim_config(tmp_path / "rig.toml", noise=True, clock_speed="40")
    fast = sim_config(tmp_path / "fast.toml", noise=True)
    ref = tmp_path / "ref"
    assert main(["capture", "--poses", "0:360:90", "--config", str(fast), "--out", str(ref),
                 "--no-progress"]) == 0
    out = tmp_path / "run"
    proc = spawn_capture(cfg, out)
    proc.kill()
    proc.communicate(timeout=60)
    s = Session.open(out)  # readable: the manifest is only ever replaced atomically
    assert s.manifest["status"] == "running"  # nobody got to say otherwise
    assert s.captures[0]["status"] == "complete"
    problems = s.verify()
    assert all("not recorded" in p for p in problems)  # at most orphans of the open capture
    assert main(["capture", "--config", str(fast), "--out", str(out), "--resume",
                 "--no-progress"]) == 0
    assert content(out) == content(ref)
    assert Session.open(out).verify() == []


def test_info_and_reconstruct_reject_non_sessions(tmp_path, capsys):
    assert main(["info", str(tmp_path)]) == 2
    assert "not a polrig session" in capsys.readouterr().err
    assert main(["reconstruct", str(tmp_path / "missing"), "--no-progress"]) == 2
    assert "no such session folder" in capsys.readouterr().err


def test_calibration_without_a_loader_is_a_clear_error(tmp_path, capsys):
    cal = tmp_path / "cal"
    cal.mkdir()
    rc = main(["capture", "--poses", "0", "--calibration", str(cal), "--out",
               str(tmp_path / "out"), "--no-progress"])
    err = capsys.readouterr().err
    try:
        from polrig.calibration import calibset  # noqa: F401
    except ImportError:
        assert rc == 2 and "--calibration" in err and len(err.strip().splitlines()) == 1
    else:  # pragma: no cover - a loader exists: an empty folder is not a calibration set
        assert rc == 2


def test_reconstruct_refuses_mirror_average_with_the_reference_method(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    before = (out / "session.json").read_bytes()
    capsys.readouterr()
    assert main(["reconstruct", str(out), "--mirror-average", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--mirror-average: mirror averaging applies to the network's methods only" in err and len(err.strip().splitlines()) == 1
    assert (out / "session.json").read_bytes() == before  # no revision recorded


def interrupted_session(tmp_path, monkeypatch, cfg: pathlib.Path, poses: str = "0,90,180"
                        ) -> pathlib.Path:
    """A session left interrupted by a stage that disconnects during its second capture."""
    import polrig.app.rig

    real_open = polrig.app.rig.open_rig

    def faulty_open(*a, **kw):
        rig = real_open(*a, **kw)
        # stage calls: position (hardware time), home, then per move position, move_to, wait;
        # call 15 starts capture 1's first move (with the turntable)
        rig.faults.inject_fault("stage", "disconnect", after_calls=15)
        return rig

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(polrig.app.rig, "open_rig", faulty_open)
        assert main(["capture", "--poses", poses, "--config", str(cfg), "--out", str(out),
                     "--no-progress"]) == 1
    s = Session.open(out)
    assert s.manifest["status"] == "interrupted"
    assert [c["status"] for c in s.captures][:2] == ["complete", "failed"]
    return out


def test_resume_on_a_different_rig_exits_2_and_writes_nothing(tmp_path, capsys, monkeypatch):
    """A session captured with 64x64 mono frames cannot continue on a 128x128 colour rig: one
    line naming the difference, exit 2, the session untouched (captures 1-2 used to be
    captured with the other rig's frames and the manifest kept naming the first)."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = interrupted_session(tmp_path, monkeypatch, cfg)
    other = tmp_path / "other.toml"
    other.write_text(cfg.read_text().replace('"64x64"', '"128x128"').replace("imx250mzr", "imx250myr"))
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(["capture", "--config", str(other), "--out", str(out), "--resume",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert ("was captured on a different rig: camera frames 64x64 imx250mzr (1 colour), this "
            "camera's 128x128 imx250myr (3 colours)") in err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0


def test_other_file_system_error_exits_1_with_the_resume_hint(tmp_path, capsys, monkeypatch):
    """An OSError other than a full disk mid-capture: one line with the reason and the resume
    command, exit 1; the session says why it stopped (it used to stay "running")."""
    import errno

    import polrig.app.session

    cfg = sim_config(tmp_path / "rig.toml")
    real_write = polrig.app.session.atomic_write_bytes
    calls = []

    def failing_write(path, data):
        calls.append(path)
        if len(calls) == 16:  # capture 1 of 2, before its result
            raise OSError(errno.EACCES, "Permission denied", str(path))
        real_write(path, data)

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(polrig.app.session, "atomic_write_bytes", failing_write)
        rc = main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                   "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1, err
    assert "Permission denied" in err and f"polrig capture --out {out} --resume" in err
    m = json.loads((out / "session.json").read_text())
    assert m["status"] == "interrupted" and "PermissionError" in m["status_reason"]
    assert [c["status"] for c in m["captures"]].count("failed") == 1
    assert Session.open(out).verify() == []
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0


def test_processing_error_mid_capture_exits_1_with_the_resume_hint(tmp_path, capsys, monkeypatch):
    """A processing error (not a device fault, not a file-system error) once the session
    exists: one line with the reason and the resume command, exit 1, the session interrupted
    (it used to be a traceback), and the resume completes it."""
    import polrig.app.processing

    cfg = sim_config(tmp_path / "rig.toml")
    real = polrig.app.processing.Processor.process
    calls = []

    def failing(self, session, index, revision=None):
        calls.append(index)
        if len(calls) == 2:
            raise RuntimeError("solver blew up")
        return real(self, session, index, revision)

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        m.setattr(polrig.app.processing.Processor, "process", failing)
        rc = main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                   "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1, err
    assert "solver blew up" in err and f"polrig capture --out {out} --resume" in err
    m = json.loads((out / "session.json").read_text())
    assert m["status"] == "interrupted" and "RuntimeError" in m["status_reason"]
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0


@pytest.mark.slow
def test_second_writer_is_refused_and_sigterm_stops_like_ctrl_c(tmp_path, capsys):
    """While one ``polrig capture`` writes a session, a second ``--resume`` and a
    ``reconstruct`` are refused with one line (exit 1) and change nothing; SIGTERM then stops
    the capture as Ctrl-C does (exit 143, session interrupted, resumable)."""
    cfg = sim_config(tmp_path / "rig.toml", clock_speed="40")  # ~0.5 s/capture
    fast = sim_config(tmp_path / "fast.toml")
    out = tmp_path / "run"
    proc = spawn_capture(cfg, out)
    try:
        for argv in (["capture", "--config", str(fast), "--out", str(out), "--resume",
                      "--no-progress"], ["reconstruct", str(out), "--no-progress"]):
            assert main(argv) == 1
            err = capsys.readouterr().err
            assert len(err.strip().splitlines()) == 1, err
            assert f"being written by another polrig process (pid {proc.pid})" in err
        assert not (out / "c000_pose000.0" / "rev1").exists()
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip().endswith("polrig: terminated (SIGTERM)")
    s = Session.open(out)
    assert s.manifest["status"] == "interrupted"
    assert s.manifest["status_reason"] == "terminated by SIGTERM"
    assert s.captures[0]["status"] == "complete" and "pending" in [c["status"] for c in s.captures]
    assert s.verify() == [] and s.manifest["revisions"] == []
    assert main(["capture", "--config", str(fast), "--out", str(out), "--resume",
                 "--no-progress"]) == 0


@pytest.mark.slow
def test_a_burst_of_sigints_still_leaves_the_session_interrupted(tmp_path):
    """SIGINTs every 0.5 ms (an impatient operator, a supervisor repeating its signal): the
    first stops the capture, the later ones do not interrupt its clean-up, so the session is
    interrupted and intact, and resume completes it (the clean-up used to be cut short, the
    session left "running"). The process ends by SIGINT (shell status 130) either way."""
    import time

    cfg = sim_config(tmp_path / "rig.toml", clock_speed="40")
    out = tmp_path / "run"
    proc = spawn_capture(cfg, out)
    for _ in range(200):
        if proc.poll() is not None:
            break
        os.kill(proc.pid, signal.SIGINT)
        time.sleep(0.0005)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (130, -signal.SIGINT), err
    s = Session.open(out)
    assert s.manifest["status"] == "interrupted", s.manifest["history"]
    assert s.manifest["status_reason"] == "interrupted by the operator (Ctrl-C)"
    assert s.verify() == []
    assert main(["capture", "--config", str(sim_config(tmp_path / "fast.toml")), "--out",
                 str(out), "--resume", "--no-progress"]) == 0


def test_reconstruct_goes_on_past_a_damaged_capture_and_exits_1(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0,90,180", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    (out / Session.open(out).capture(1)["files"]["raw"][0]["path"]).unlink()
    capsys.readouterr()
    assert main(["reconstruct", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert ("polrig: error: revision rev1: 1 of 3 capture(s) failed, the others are complete: "
            "capture 1 (c001_pose090.0): FileNotFoundError") in err
    assert [c["revisions"]["rev1"]["status"] for c in Session.open(out).captures] == [
        "complete", "failed", "complete"]
    assert main(["info", str(out)]) == 1
    assert "rev1: failed  (FileNotFoundError" in capsys.readouterr().out


def test_info_into_a_closed_pipe_exits_quietly(tmp_path):
    """``polrig info DIR | head``: the reader goes away; no "Broken pipe" error line, the exit
    status of a process that SIGPIPE ended (141)."""
    cfg = sim_config(tmp_path / "rig.toml")
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0:360:30", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    r, w = os.pipe()
    os.close(r)  # the reader is gone before polrig writes
    proc = subprocess.run([sys.executable, "-m", "polrig", "info", str(out)], stdout=w,
                          stderr=subprocess.PIPE, text=True, cwd=REPO, timeout=60)
    os.close(w)
    assert proc.returncode == 141 and proc.stderr == "", proc.stderr


@pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")
def test_single_shot_full_resolution_capture_and_reconstruct(tmp_path, capsys):
    """``--resolution full`` (issue 22 item 1): the plan records it, the Mueller EXR has the raw
    frame's size with a score against the truth on that grid, sigma NaN (not calibrated there)
    and the provider and resolution in its header; ``reconstruct --resolution superpixel``
    writes the networks' grid, whose cells the full-resolution image averages back to."""
    from polrig.formats.exr import read_mueller_exr

    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "128x128"\nclock_speed = inf\nseed = 3\n')
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--resolution", "full",
                 "--device", "cpu", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    s = Session.open(out)
    assert s.plan.resolution == "full"
    score = s.captures[0]["score"]
    assert score["psnr_db"] > 25 and score["within_2sigma"] is None  # no sigma to judge
    full = read_mueller_exr(out / s.capture(0)["files"]["mueller"]["path"])
    assert full.mueller.shape == (3, 3, 3, 128, 128)
    md = full.metadata
    assert md["resolution"] == "full" and md["execution_provider"] == "CPUExecutionProvider"
    assert md["output_demosaic"] == "bilinear" and "NaN" in md["planes"]["sigma.M{rc}"]
    assert np.all(np.isnan(full.extra["sigma.M00.R"]))
    valid = full.extra["mask.G"] == 0
    assert score["pixels_compared"] > 32 * 32  # scored on the raw grid (superpixel: 529 of 32x32)
    assert np.all(np.isfinite(full.mueller[..., valid]))
    capsys.readouterr()
    assert main(["reconstruct", str(out), "--resolution", "superpixel", "--no-progress"]) == 0
    s = Session.open(out)
    assert [r["resolution"] for r in s.manifest["revisions"]] == ["superpixel"]
    sp = read_mueller_exr(out / s.capture(0)["revisions"]["rev1"]["files"]["mueller"]["path"])
    assert sp.mueller.shape == (3, 3, 3, 32, 32) and sp.metadata["resolution"] == "superpixel"
    # the lifted image averaged over each 4x4 cell is close to the networks' answer on the grid
    cells = full.mueller.reshape(3, 3, 3, 32, 4, 32, 4).mean(axis=(-3, -1))
    obj = (sp.extra["mask.G"] == 0) & valid.reshape(32, 4, 32, 4).all(axis=(1, 3))
    err = np.abs(cells - sp.mueller)[..., obj].mean() / np.abs(sp.mueller[..., obj]).mean()
    assert obj.sum() > 100 and err < 0.25, err
    # and back to full resolution from the raw frames: the same image as the capture's
    assert main(["reconstruct", str(out), "--resolution", "full", "--no-progress"]) == 0
    s = Session.open(out)
    again = read_mueller_exr(out / s.capture(0)["revisions"]["rev2"]["files"]["mueller"]["path"])
    np.testing.assert_array_equal(again.mueller, full.mueller)


@pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")
def test_full_resolution_with_the_reference_method_or_an_absent_cuda_is_refused(tmp_path, capsys):
    """``--resolution full`` with the reference method, and ``--device cuda`` where onnxruntime
    has no CUDA: one line naming the option, exit 2, nothing written (no session folder, no
    revision)."""
    import onnxruntime as ort

    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "64x64"\nclock_speed = inf\nseed = 3\n')
    out = tmp_path / "ref"
    capsys.readouterr()
    assert main(["capture", "--poses", "0", "--resolution", "full", "--config", str(cfg),
                 "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--resolution full" in err and "single-shot" in err
    assert not out.exists()
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        assert main(["capture", "--poses", "0", "--mode", "single-shot", "--device", "cuda",
                     "--config", str(cfg), "--out", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--device cuda" in err
        assert not out.exists()
    ss = tmp_path / "ss"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--config", str(cfg),
                 "--out", str(ss), "--no-progress"]) == 0
    before = (ss / "session.json").read_bytes()
    capsys.readouterr()
    assert main(["reconstruct", str(ss), "--mode", "reference", "--resolution", "full",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--resolution full" in err
    assert (ss / "session.json").read_bytes() == before


@pytest.mark.parametrize("argv, usage", [
    (["capture", "--poses", "0", "--out", "x", "--bogus"], "usage: polrig capture "),
    (["info", "--bogus", "x"], "usage: polrig info "),
    (["--bogus"], "usage: polrig "),
])
def test_a_mistyped_option_prints_its_commands_usage_line(argv, usage, tmp_path, capsys, monkeypatch):
    """As the README says: the error in one line, the usage line of the command it belongs to
    above it; exit 2, nothing written."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(usage), err
    assert err.strip().splitlines()[-1].endswith("error: unrecognized arguments: --bogus"), err
    assert list(tmp_path.iterdir()) == []
