"""Session folders: atomic checksummed files, no overwrites, disk-space check, verify, restart."""

from __future__ import annotations

import errno
import json
import os
import pathlib

import pytest

from polrig.acquisition.plan import CapturePlan
from polrig.app.manifest import SCHEMA_VERSION
from polrig.app.session import (
    COMPLETE,
    LOCK_NAME,
    MANIFEST_NAME,
    PENDING,
    Interrupted,
    Session,
    SessionBusy,
    SessionError,
    SignalGuard,
    check_free_space,
    folder_is_empty,
    interruption_reason,
    sha256_file,
)
from polrig.errors import FormatError

PLAN = CapturePlan((0.0, 90.0))
#: a rig record (polrig.app.manifest.RigRecord) of a rig that says little about itself
RIG = {"simulated": False, "config": None, "devices": {}, "sim_parameters": None,
       "camera_frames": None, "sensor_model": None}
#: what a raw frame record carries besides its file (docs/session-schema.md)
FRAME = {"state_index": 0, "state_deg": 0.0, "exposure_index": 0, "exposure_us": 1000.0,
         "frame": 0}


def make(tmp_path: pathlib.Path, **kw) -> Session:
    return Session.create(tmp_path / "s", plan=PLAN, rig=RIG, calibration_id="nominal",
                          command_line=["polrig", "capture"], **kw)


def test_create_lists_one_pending_capture_per_pose(tmp_path):
    s = make(tmp_path)
    m = json.loads((s.root / MANIFEST_NAME).read_text())
    assert m["schema_version"] == SCHEMA_VERSION == 7 and m["calibration_id"] == "nominal"
    assert m["plan"]["poses_deg"] == [0.0, 90.0] and m["plan"]["exr_uncertainty"] == "half"
    assert Session.open(s.root).plan == PLAN  # stored once, read back as the CapturePlan
    assert [c["pose_deg"] for c in m["captures"]] == [0.0, 90.0]
    assert all(c["status"] == PENDING for c in m["captures"])
    assert m["conventions_version"] and m["software"]["version"]


def test_refuses_non_empty_folder(tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "keep.txt").write_text("precious")
    with pytest.raises(FileExistsError, match="not empty; choose a new folder, or resume the "
                                              "session in it"):
        make(tmp_path)
    assert (tmp_path / "s" / "keep.txt").read_text() == "precious"


def test_disk_space_check_names_need_and_free(tmp_path):
    with pytest.raises(SessionError, match="needs about .* free"):
        check_free_space(tmp_path / "new" / "deeper", 1 << 62)
    with pytest.raises(SessionError):
        make(tmp_path, required_bytes=1 << 62)
    assert not (tmp_path / "s").exists()


@pytest.mark.skipif(not hasattr(os, "statvfs"), reason="POSIX file system flags")
def test_a_folder_that_cannot_be_written_is_said_so_not_as_no_space(tmp_path, monkeypatch):
    """``--out`` on a read-only file system (a write-protected card) or a virtual one
    (``/proc``) read "needs about 2.7 MiB, 0 B are free"; each is now said as what it is,
    before anything is written."""
    if pathlib.Path("/proc/self").is_dir():
        with pytest.raises(SessionError, match=r"in /proc/new: /proc is on a virtual file system"):
            check_free_space("/proc/new", 1)
    real = os.statvfs

    class ReadOnly:  # the real figures, with the read-only flag a write-protected card has
        def __init__(self, path):
            self._s = real(path)

        def __getattr__(self, name):
            return self._s.f_flag | os.ST_RDONLY if name == "f_flag" else getattr(self._s, name)

    monkeypatch.setattr(os, "statvfs", ReadOnly)
    with pytest.raises(SessionError, match=f"in {tmp_path / 'new'}: {tmp_path} is on a read-only file system"):
        check_free_space(tmp_path / "new", 1)
    with pytest.raises(SessionError, match="read-only file system"):
        make(tmp_path)
    assert not (tmp_path / "s").exists()


def test_files_are_recorded_with_checksums_and_verified(tmp_path):
    s = make(tmp_path)
    s.capture(0)["name"] = "c000"
    rec = s.add_file(0, "raw", "c000/raw/a.png", b"pixels", sidecar=b"{}",
                     **{**FRAME, "state_deg": 45.0})
    s.add_file(0, "mueller", "c000/mueller.exr", b"exr")
    again = Session.open(s.root)
    files = again.capture(0)["files"]
    assert files["raw"][0]["sha256"] == sha256_file(s.root / "c000/raw/a.png")
    assert files["raw"][0]["meta_path"] == "c000/raw/a.png.json"
    assert files["raw"][0]["state_deg"] == 45.0 and rec["bytes"] == 6
    assert again.verify() == []
    (s.root / "c000/raw/a.png").write_bytes(b"pixelz")
    (s.root / "c000/stray.bin").write_bytes(b"?")
    (s.root / "c000/mueller.exr").unlink()
    problems = "\n".join(again.verify())
    assert "a.png: SHA-256 mismatch" in problems
    assert "mueller.exr: missing" in problems
    assert "stray.bin: not recorded" in problems


def test_never_overwrites(tmp_path):
    s = make(tmp_path)
    s.add_file(0, "mueller", "c000/mueller.exr", b"one")
    with pytest.raises(FileExistsError):
        s.add_file(1, "mueller", "c000/mueller.exr", b"two")
    assert (s.root / "c000/mueller.exr").read_bytes() == b"one"


def test_disk_full_leaves_previous_manifest_and_no_partial_file(tmp_path):
    s = make(tmp_path)
    s.add_file(0, "raw", "c000/raw/a.png", b"a", sidecar=b"{}", **FRAME)

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    s.write_hook = full
    with pytest.raises(OSError) as info:
        s.add_file(0, "raw", "c000/raw/b.png", b"b", sidecar=b"{}", **FRAME)
    assert info.value.errno == errno.ENOSPC
    assert not (s.root / "c000/raw/b.png").exists()
    on_disk = Session.open(s.root)
    assert [r["path"] for r in on_disk.capture(0)["files"]["raw"]] == ["c000/raw/a.png"]
    assert on_disk.verify() == []
    assert not [p for p in s.root.rglob("*.tmp")]


def test_restart_removes_partial_capture_and_discard_unrecorded(tmp_path):
    s = make(tmp_path)
    s.capture(0)["name"] = "c000"
    s.add_file(0, "raw", "c000/raw/a.png", b"a", sidecar=b"{}", **FRAME)
    (s.root / "c000/raw/orphan.png").write_bytes(b"o")  # written, crash before recording
    assert s.discard_unrecorded(0) == ["c000/raw/orphan.png"]
    s.restart_capture(0)
    assert not (s.root / "c000").exists()
    assert s.capture(0)["files"] == {} and s.capture(0)["attempts"] == 1
    s.complete_capture(0)
    assert s.capture(0)["status"] == COMPLETE
    with pytest.raises(SessionError):
        s.restart_capture(0)


def test_open_rejects_non_sessions(tmp_path):
    with pytest.raises(FileNotFoundError):
        Session.open(tmp_path / "nope")
    with pytest.raises(FormatError, match="not a polrig session"):
        Session.open(tmp_path)
    (tmp_path / MANIFEST_NAME).write_text("{")
    with pytest.raises(FormatError, match="not valid JSON"):
        Session.open(tmp_path)
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"captures": [], "schema_version": 99}))
    with pytest.raises(FormatError, match="schema version 99"):
        Session.open(tmp_path)


def test_revisions_are_separate_entries(tmp_path):
    s = make(tmp_path)
    s.add_file(0, "mueller", "c000/mueller.exr", b"m0")
    with pytest.raises(ValueError, match="revision rev1: missing 'mirror_average'"):
        s.new_revision({"mode": "reference", "demosaic": "bilinear"})
    name = s.new_revision({"mode": "reference", "demosaic": "bilinear", "mirror_average": False,
                           "resolution": "superpixel", "network_binning": 1, "seen_state": 0,
                           "calibration_id": "nominal", "exr_planes": ["mueller"],
                           "exr_uncertainty": "half", "exr_compression": "zip"})
    s.start_revision(0, name)
    s.add_file(0, "mueller", f"c000/{name}/mueller.exr", b"m1", revision=name)
    roles = [role for _, role, _ in s.iter_file_records()]
    assert roles == ["mueller", "rev1/mueller"]
    assert Session.open(s.root).verify() == []


# -- manifest structure: one validation place, one line naming the record ------------------------
def _damaged(tmp_path, change) -> pathlib.Path:
    s = make(tmp_path)
    s.capture(0)["name"] = "c000"
    s.add_file(0, "raw", "c000/raw/a.png", b"a", sidecar=b"{}", **FRAME)
    m = json.loads((s.root / MANIFEST_NAME).read_text())
    change(m)
    (s.root / MANIFEST_NAME).write_text(json.dumps(m))
    return s.root


@pytest.mark.parametrize("change, message", [
    (lambda m: m["captures"][0]["files"]["raw"][0].pop("sha256"),
     "capture 0 (c000): raw file record 0: missing 'sha256'"),
    (lambda m: m["captures"][0]["files"]["raw"][0].pop("meta_sha256"),
     "raw file record 0: missing 'meta_sha256'"),
    (lambda m: m["captures"][0]["files"]["raw"][0].update(path="../../etc/passwd"),
     "'path' must be a relative path inside the session"),
    (lambda m: m["captures"][0]["files"]["raw"][0].update(state_index="one"),
     "'state_index' must be an index >= 0"),
    (lambda m: m["captures"][0]["files"].update(raw={"path": "x"}),
     "capture 0 (c000): 'raw' must be a list"),
    (lambda m: m["captures"][1].update(name="../outside"), "capture 1 (../outside): 'name' must be a folder name"),
    (lambda m: m["captures"][1].pop("status"), "capture 1 (c001_pose090.0): missing 'status'"),
    (lambda m: m["captures"][1].update(index=7), "'index' is 7, but it is entry 1"),
    (lambda m: m["captures"].pop(), "1 captures listed for the 2 poses"),
    (lambda m: m["plan"].pop("mode"), "plan: missing 'mode'"),
    (lambda m: m["plan"].update(exposures_us=["fast"]), "plan: 'exposures_us' must be a list"),
    (lambda m: m["plan"].update(states_deg=[0, 90]), "plan: the reference method needs at least 3"),
    (lambda m: m["captures"][0]["files"].update(bogus={}), "capture 0 (c000): unknown key 'bogus'"),
    (lambda m: m["captures"][0]["files"]["raw"][0].update(exposure_us="long"),
     "'exposure_us' must be a finite number or null"),
    (lambda m: m["rig"].pop("camera_frames"), "rig: missing 'camera_frames'"),
    (lambda m: m["revisions"].append({"name": "../x"}), "revision entry 0: 'name' must be a folder name"),
    (lambda m: m.pop("software"), "missing 'software'"),
    (lambda m: m.update(status="paused"), "'status' must be one of running, complete, interrupted"),
    (lambda m: m["captures"][0].update(score={"rmse": 1.0}), "capture 0 (c000): missing 'mae'"),
    (lambda m: m["captures"][0]["revisions"].update(rev1={"files": {}}),
     "capture 0 (c000): revision 'rev1': missing 'status'"),
])
def test_structural_damage_is_one_format_error_naming_the_record(tmp_path, change, message):
    root = _damaged(tmp_path, change)
    with pytest.raises(FormatError) as info:
        Session.open(root)
    text = str(info.value)
    assert message in text and "damaged session manifest" in text and "\n" not in text, text


def test_info_and_reconstruct_report_a_record_without_checksum_in_one_line(tmp_path, capsys):
    """`info` and `reconstruct` on a manifest whose raw record lost its "sha256": exit 2 and
    one line naming the record (a KeyError traceback before)."""
    from polrig.cli import main

    root = _damaged(tmp_path, lambda m: m["captures"][0]["files"]["raw"][0].pop("sha256"))
    before = (root / MANIFEST_NAME).read_bytes()
    for argv in (["info", str(root)], ["reconstruct", str(root), "--no-progress"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "raw file record 0: missing 'sha256'" in err, err
    assert (root / MANIFEST_NAME).read_bytes() == before


# -- one writer at a time ---------------------------------------------------------------------------
def test_a_second_writer_is_refused_and_readers_need_no_lock(tmp_path):
    s = make(tmp_path)  # a new session holds its lock
    assert s.locked and (s.root / LOCK_NAME).is_file()
    with pytest.raises(SessionBusy, match=r"being written by another polrig process \(pid \d+\)"):
        Session.open(s.root, lock=True)
    assert Session.open(s.root).captures  # a reader
    s.unlock()
    again = Session.open(s.root, lock=True)
    with pytest.raises(SessionBusy):
        s.lock()
    again.unlock()
    s.lock()
    assert s.locked


def test_the_lock_of_another_process_is_honoured(tmp_path):
    """flock is per process here: a child holding the lock refuses this process, and the lock
    goes when the child ends, however it ends."""
    import subprocess
    import sys

    s = make(tmp_path)
    s.unlock()
    child = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from polrig.app.session import Session; "
        f"s = Session.open({str(s.root)!r}, lock=True); print('locked', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(SessionBusy, match=f"pid {child.pid}"):
            Session.open(s.root, lock=True)
    finally:
        child.kill()
        child.wait()
    Session.open(s.root, lock=True).unlock()


def test_a_lock_file_alone_does_not_make_a_folder_non_empty(tmp_path):
    root = tmp_path / "s"
    root.mkdir()
    (root / LOCK_NAME).write_text("12345\n")  # a creation that failed after locking
    assert folder_is_empty(root)
    s = make(tmp_path)
    assert s.manifest["status"] == "running"


_CRASH_IN_FIRST_SAVE = """
import os, signal, sys
from polrig.acquisition.plan import CapturePlan
from polrig.app.session import Session
os.replace = lambda src, dst: os.kill(os.getpid(), signal.SIGKILL)  # the temporary is whole, not renamed
Session.create(sys.argv[1], plan=CapturePlan((0.0,)), rig={"simulated": False, "config": None, "devices": {},
               "sim_parameters": None, "camera_frames": None, "sensor_model": None}, calibration_id="nominal")
"""


def test_a_crash_while_the_session_is_created_leaves_a_folder_a_new_session_takes(tmp_path):
    """SIGKILL in the first manifest save, before its rename: the folder holds the lock file and
    the manifest's temporary, no session (``--resume`` says so). A new session in it used to be
    refused as "not empty; ... or resume the session in it", which it could not: the folder
    was stuck. It is empty for a new session, whose lock removes the temporary."""
    import signal
    import subprocess
    import sys

    root = tmp_path / "s"
    child = subprocess.run([sys.executable, "-c", _CRASH_IN_FIRST_SAVE, str(root)], capture_output=True, text=True)
    assert child.returncode == -signal.SIGKILL, child.stderr
    left = sorted(p.name for p in root.iterdir())
    assert len(left) == 2 and left[1] == LOCK_NAME and left[0].startswith(f".{MANIFEST_NAME}."), left
    assert folder_is_empty(root)
    s = make(tmp_path)
    assert sorted(p.name for p in root.iterdir()) == sorted([LOCK_NAME, MANIFEST_NAME])
    s.unlock()
    # a save of an existing session cut short likewise: its writer's lock removes the temporary
    stale = root / left[0]
    stale.write_bytes(b'{"schema_ver')
    Session.open(root)  # a reader writes nothing
    assert stale.exists()
    Session.open(root, lock=True).unlock()
    assert not stale.exists() and Session.open(root).verify() == []


def test_create_that_fails_after_locking_leaves_no_folder(tmp_path):
    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    with pytest.raises(OSError):
        make(tmp_path, write_hook=full)
    assert not (tmp_path / "s").exists()


# -- signals: the first stops, the clean-up after it is not interrupted ----------------------------
def test_signal_guard_raises_once_then_ignores_and_defers(tmp_path):
    import os
    import signal
    import time

    def wait_for_signal():  # the handler runs between bytecodes, soon after the kill
        for _ in range(1000):
            time.sleep(0.001)

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as info:
        with SignalGuard():
            os.kill(os.getpid(), signal.SIGTERM)
            wait_for_signal()
    assert info.value.signum == signal.SIGTERM and isinstance(info.value, KeyboardInterrupt)
    assert interruption_reason(info.value) == "terminated by SIGTERM"
    assert signal.getsignal(signal.SIGTERM) is before  # restored
    cleaned = []
    with pytest.raises(Interrupted):
        with SignalGuard():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                wait_for_signal()
            except KeyboardInterrupt:
                os.kill(os.getpid(), signal.SIGINT)  # an impatient second Ctrl-C
                os.kill(os.getpid(), signal.SIGTERM)
                wait_for_signal()
                cleaned.append(True)  # the clean-up ran to its end
                raise
    assert cleaned == [True]
    with SignalGuard() as guard:
        with pytest.raises(Interrupted):
            with guard.deferred():
                os.kill(os.getpid(), signal.SIGINT)
                wait_for_signal()
                cleaned.append("deferred")  # not interrupted inside
    assert cleaned == [True, "deferred"]
