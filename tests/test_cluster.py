"""``polrig reconstruct`` on Dask distributed (:mod:`polrig.app.cluster`): real worker processes on
the loopback interface, results compared byte for byte with the serial
:func:`polrig.app.reconstruct.reprocess_session`; faults (a SIGKILLed worker, Ctrl-C, damaged raw
data, an unreachable scheduler, the extra not installed) against the manifest on disk."""

from __future__ import annotations

import contextlib
import logging
import os
import pathlib
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("distributed")

from polrig.app import cluster, reconstruct  # noqa: E402
from polrig.app.session import Session  # noqa: E402
from polrig.cli import main  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}


def _capture(tmp: pathlib.Path, name: str, size: str, poses: str) -> pathlib.Path:
    cfg = tmp / f"{name}.toml"
    cfg.write_text(f'[sim]\nsize = "{size}"\nsensor = "imx250mzr"\nclock_speed = inf\n'
                   f'seed = 11\nscene = "box"\nnoise = true\n')
    out = tmp / name
    assert main(["capture", "--poses", poses, "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    return out


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> list[pathlib.Path]:
    """Two small sessions (64x64, 4 and 3 poses): the multi-session archive; read only."""
    tmp = tmp_path_factory.mktemp("archive")
    return [_capture(tmp, "a", "64x64", "0:360:90"), _capture(tmp, "b", "64x64", "45,135,225")]


@pytest.fixture(scope="module")
def slow_session(tmp_path_factory) -> pathlib.Path:
    """A 128x128 session of 6 poses whose bilinear solve takes a good fraction of a second
    per capture: long enough to kill a worker or press Ctrl-C mid-batch; read only."""
    return _capture(tmp_path_factory.mktemp("slow"), "slow", "128x128", "0:360:60")


def _copies(sessions, dest: pathlib.Path) -> list[pathlib.Path]:
    dest.mkdir(parents=True, exist_ok=True)
    out = []
    for s in sessions:
        shutil.copytree(s, dest / s.name)
        out.append(dest / s.name)
    return out


def _serial(sessions, dest: pathlib.Path, **kw) -> list[pathlib.Path]:
    """The serial reference: :func:`polrig.app.reconstruct.reprocess_session` on copies."""
    copies = _copies(sessions, dest)
    for c in copies:
        reconstruct.reprocess_session(Session.open(c), **kw)
    return copies


def _results(session_dir: pathlib.Path, revision: str = "rev1") -> dict:
    """Per capture: revision status, the result's record (path, sha256, bytes), its score
    and the file's bytes."""
    s = Session.open(session_dir)
    out = {}
    for cap in s.captures:
        rev = cap["revisions"][revision]
        rec = rev["files"].get("mueller")
        out[cap["name"]] = (rev["status"], rec and {k: rec[k] for k in ("path", "sha256", "bytes")},
                            rev["score"],
                            rec and (session_dir / rec["path"]).read_bytes())
    return out


def _no_leftovers(session_dir: pathlib.Path) -> None:
    s = Session.open(session_dir)
    assert s.verify() == [], s.verify()  # also: no file the manifest does not record
    assert not [p for p in session_dir.rglob("*.tmp*")]


@pytest.fixture(scope="module")
def archive_serial(archive, tmp_path_factory) -> list[dict]:
    """:func:`_results` of the serial reference of the archive (default demosaic), computed
    once for the tests that compare against it."""
    return [_results(c) for c in _serial(archive, tmp_path_factory.mktemp("archive-serial"))]


@pytest.fixture(scope="module")
def slow_serial(slow_session, tmp_path_factory) -> dict:
    """:func:`_results` of the serial bilinear reference of the slow session, computed once."""
    return _results(_serial([slow_session], tmp_path_factory.mktemp("slow-serial"),
                            demosaic="bilinear")[0])


def test_two_local_workers_are_bit_identical_to_serial(archive, tmp_path, capsys):
    serial = _serial(archive, tmp_path / "serial", demosaic="bilinear")
    dist = _copies(archive, tmp_path / "dist")
    assert main(["reconstruct", *map(str, dist), "--workers", "2", "--demosaic", "bilinear"]) == 0
    out, err = capsys.readouterr()
    assert out.count(": done") == 7 and "a: capture 4/4 pose 270 deg: done" in out
    assert "revision rev1 written to" in out
    assert "7/7" in err and "capture/s" in err  # one bar over both sessions, with its rate
    for s, d in zip(serial, dist):
        assert _results(d) == _results(s)
        assert all(v[0] == "complete" for v in _results(d).values())
        _no_leftovers(d)
        rev = Session.open(d).manifest["revisions"][-1]
        assert rev["demosaic"] == "bilinear" and "--workers" in rev["command_line"]


def test_from_list_and_serial_command_match_the_library(archive, archive_serial, tmp_path):
    dist = _copies(archive, tmp_path / "listed")
    lst = tmp_path / "listed" / "sessions.txt"
    lst.write_text("# the archive\n" + "\n".join(d.name for d in dist) + "\n\n")
    assert main(["reconstruct", "--from-list", str(lst), "--no-progress"]) == 0
    for s, d in zip(archive_serial, dist):
        assert _results(d) == s


def _kill_a_busy_worker(runner: cluster.DaskRunner, killed: list[int], within_s: float = 120) -> None:
    """SIGKILL the first worker process the scheduler says is running a task, 0.15 s into it;
    its pid goes to ``killed``. Run on a thread beside the batch."""
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline and not killed:
        busy = [w for w, keys in runner.client.processing().items() if keys]
        if busy:
            pid = runner.client.run(os.getpid, workers=[busy[0]])[busy[0]]
            time.sleep(0.15)  # into the task
            if runner.client.processing().get(busy[0]):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
        time.sleep(0.02)


def test_a_worker_killed_mid_task_is_rerun_and_the_batch_is_identical(slow_session, slow_serial,
                                                                      tmp_path):
    """SIGKILL of a worker process while the scheduler says it is running a task: Dask reruns
    the task elsewhere; every capture completes with the serial bytes, nothing half-written
    or temporary is left."""
    dist = _copies([slow_session], tmp_path / "dist")[0]
    runner = cluster.DaskRunner.local(2)
    killed: list[int] = []
    t = threading.Thread(target=_kill_a_busy_worker, args=(runner, killed), daemon=True)
    try:
        t.start()
        cluster.reconstruct([dist], runner, demosaic="bilinear")
    finally:
        t.join(timeout=5)
        runner.close()
    assert killed, "no worker was caught running a task"
    assert _results(dist) == slow_serial
    _no_leftovers(dist)


def test_leftover_temporary_files_of_a_dead_worker_are_removed(archive, tmp_path):
    """A worker killed while writing leaves ``.mueller.exr.<id>.tmp.exr`` in the revision
    folder, and one killed after its rename an unrecorded ``mueller.exr``: the client removes
    the first and the rerun replaces the second; the revision ends complete and intact."""
    d = _copies(archive[:1], tmp_path)[0]
    s = Session.open(d, lock=True)
    try:
        batches = cluster.prepare([s], command_line=["test"])
        folder = d / s.capture(0)["name"] / batches[0].revision
        folder.mkdir()
        (folder / ".mueller.exr.0123456789ab.tmp.exr").write_bytes(b"half")
        (folder / "mueller.exr").write_bytes(b"an attempt the client never heard of")
        cluster.run_batch(batches, cluster.SerialRunner())
    finally:
        s.unlock()
    assert sorted(p.name for p in folder.iterdir()) == ["mueller.exr", "mueller_aolp.png",
                                                         "mueller_dolp.png", "mueller_grid.png"]
    assert all(c["revisions"]["rev1"]["status"] == "complete" for c in Session.open(d).captures)
    _no_leftovers(d)


def test_a_worker_that_dies_every_time_fails_its_capture_and_the_batch_goes_on(slow_session,
                                                                              slow_serial,
                                                                              tmp_path):
    """Dask gives a task up once its workers died ``allowed-failures + 1`` times (0 here: one
    SIGKILL): that capture is marked ``failed`` with the reason, in one line, like a damaged
    one, and the others complete with the serial bytes (it was Dask's ``KilledWorker``
    traceback, and the batch stopped)."""
    import dask

    dist = _copies([slow_session], tmp_path / "dist")[0]
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        runner = cluster.DaskRunner.local(2)
    killed: list[int] = []
    t = threading.Thread(target=_kill_a_busy_worker, args=(runner, killed), daemon=True)
    try:
        t.start()
        with pytest.raises(cluster.BatchIncomplete) as info:
            cluster.reconstruct([dist], runner, demosaic="bilinear")
    finally:
        t.join(timeout=5)
        runner.close()
    assert killed, "no worker was caught running a task"
    failed = dict(info.value.batches[0].failed)
    assert failed and len(info.value.lines) == 1 and "\n" not in str(info.value)
    assert set(failed.values()) == {"KilledWorker: the worker process running it died 1 time(s) "
                                    "(killed, or out of memory?)"}
    got = _results(dist)
    for i, (name, want) in enumerate(slow_serial.items()):
        if i in failed:
            assert got[name][0] == "failed" and got[name][1] is None
        else:
            assert got[name] == want
    _no_leftovers(dist)


def test_a_task_whose_workers_all_die_is_one_line_or_its_lost_result():
    """A task that kills its worker process every time it runs (a real SIGKILL), with Dask's
    ``allowed-failures`` 0: without ``lost`` (``sim dataset``'s use) :class:`TaskLost`, one
    line (it was Dask's ``KilledWorker`` traceback); with it, ``lost(job, reason)`` stands for
    the result and the iteration goes on to every job."""
    import dask

    def die_on_odd(job):
        if job % 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return job * 10

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        runner = cluster.DaskRunner.local(1)
    try:
        with pytest.raises(cluster.TaskLost) as info:
            list(runner.map_unordered(die_on_odd, [1]))
        assert str(info.value).endswith(": KilledWorker: the worker process running it died "
                                        "1 time(s) (killed, or out of memory?)")
        got = dict(runner.map_unordered(die_on_odd, [0, 2, 3],
                                        lost=lambda job, why: why.split(":")[0]))
        # every job answers; 0 and 2 may have been waiting on the worker 3 killed: lost too
        assert sorted(got) == [0, 2, 3] and got[3] == "KilledWorker"
        assert all(got[j] in (10 * j, "KilledWorker") for j in (0, 2)), got
    finally:
        runner.close()


def test_a_full_disk_leaves_the_captures_pending_and_the_same_command_continues(
        archive, archive_serial, tmp_path, monkeypatch, capsys):
    """OpenEXR's own error for a full disk (a RuntimeError naming the temporary file and the
    reason in words) while capture 2's result is written: the batch stops in one line, that
    capture and the next stay ``pending`` (not ``failed``, which the same command never
    redoes), and once there is room the same command continues the revision to the
    uninterrupted run's bytes. Before, the capture was marked failed: as a damaged one (the
    EXR's error had no errno) and the batch went on, or, where it was seen as a full disk,
    for good."""
    import OpenEXR

    d = _copies(archive[:1], tmp_path)[0]
    real = OpenEXR.File

    class FullDisk:  # the real binding, but no room for capture 2's result
        def __init__(self, *args, **kw):
            self._file = real(*args, **kw)

        def __getattr__(self, name):
            return getattr(self._file, name)

        def write(self, path):
            if f"{os.sep}c002_" in path:
                raise RuntimeError(f'Failed to write pixel data to image file "{path}". '
                                   f"No space left on device.")
            return self._file.write(path)

    monkeypatch.setattr(OpenEXR, "File", FullDisk)
    assert main(["reconstruct", str(d), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "disk full while writing capture 2's result" in err
    assert "run the same command again to continue" in err
    revs = [c["revisions"]["rev1"] for c in Session.open(d).captures]
    assert [r["status"] for r in revs] == ["complete", "complete", "pending", "pending"]
    assert revs[2]["reason"].startswith("batch stopped by a full disk: OSError: ")
    assert "No space left on device" in revs[2]["reason"]
    _no_leftovers(d)
    monkeypatch.undo()  # room again
    assert main(["reconstruct", str(d), "--no-progress"]) == 0
    assert f"revision rev1 continued in {d}" in capsys.readouterr().out
    assert _results(d) == archive_serial[0]
    _no_leftovers(d)


@pytest.mark.slow
def test_a_scheduler_lost_mid_batch_is_one_line_and_the_same_command_continues(
        slow_session, slow_serial, tmp_path):
    """A running ``dask scheduler`` SIGKILLed after the first capture is recorded: one line
    (it was Dask's ``FutureCancelledError`` traceback), the finished capture kept, the others
    ``pending``; the same request continues the revision to the serial bytes."""
    d = _copies([slow_session], tmp_path / "dist")[0]
    port = _free_port()
    env = {**ENV, "DASK_TEMPORARY_DIRECTORY": str(tmp_path / "scratch")}
    procs = [subprocess.Popen([sys.executable, "-m", "dask", *argv], env=env, cwd=tmp_path,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)
             for argv in (["scheduler", "--host", "127.0.0.1", "--port", str(port),
                           "--dashboard-address", "127.0.0.1:0"],
                          ["worker", f"tcp://127.0.0.1:{port}", "--host", "127.0.0.1",
                           "--dashboard-address", "127.0.0.1:0", "--nthreads", "1"])]
    try:
        deadline = time.monotonic() + 60
        while True:  # the scheduler up, the worker joined
            with contextlib.suppress(Exception):
                runner = cluster.DaskRunner.connect(f"tcp://127.0.0.1:{port}", timeout=2)
                if runner.client.scheduler_info()["workers"]:
                    break
                runner.close()
            assert time.monotonic() < deadline, "the scheduler or its worker did not start"
            time.sleep(0.5)

        def kill_scheduler(batch, index, score, reason):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(procs[0].pid, signal.SIGKILL)

        try:
            with pytest.raises(cluster.SchedulerLost) as info:
                cluster.reconstruct([d], runner, demosaic="bilinear", on_capture=kill_scheduler)
        finally:
            runner.close()
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=20)
    assert "\n" not in str(info.value) and "run the same command again" in str(info.value)
    statuses = [c["revisions"]["rev1"]["status"] for c in Session.open(d).captures]
    assert "complete" in statuses and "pending" in statuses and "failed" not in statuses
    # (the worker may have gone on writing a result meanwhile: the next run removes it)
    batches = cluster.reconstruct([d], cluster.SerialRunner(), demosaic="bilinear")
    assert batches[0].continued and batches[0].revision == "rev1"
    assert _results(d) == slow_serial
    _no_leftovers(d)


def _spawn(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "polrig", *argv], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


#: A Ctrl-C (a real SIGINT) while Dask's client waits on a call its event loop has not started:
#: the loop is kept busy for 2 s, the signal comes at 0.2 s. ``sys.argv[1]`` says whether the
#: client's log filter is on. Prints what reaches the log.
INTERRUPTED_SYNC = """
import asyncio, logging, os, signal, sys, threading, time
logging.basicConfig(level=logging.ERROR, stream=sys.stdout, format="%(name)s %(levelname)s %(message)s")
from distributed.utils import LoopRunner, sync
from polrig.app import cluster
if sys.argv[1] == "filtered":
    cluster.filter_interrupted_sync()
runner = LoopRunner(asynchronous=False)
runner.start()
runner.loop.add_callback(time.sleep, 2.0)
threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
async def waited():
    await asyncio.sleep(30)
try:
    sync(runner.loop, waited)
except KeyboardInterrupt:
    print("interrupted", flush=True)
time.sleep(2.5)
logging.getLogger("tornado.application").error("another error")
runner.stop()
"""


def test_a_ctrl_c_before_the_clients_call_starts_prints_no_traceback():
    """distributed's ``sync`` logs a ``NameError`` traceback when Ctrl-C comes before the call
    it waits on has started (its ``cancel`` reads a future not yet assigned); seen in the Ctrl-C
    test below as a traceback between the progress bar and polrig's one line. The client's
    filter drops that record and no other."""
    def run(mode):
        return subprocess.run([sys.executable, "-c", INTERRUPTED_SYNC, mode], capture_output=True, text=True,
                              timeout=60)

    plain, filtered = run("plain"), run("filtered")
    assert "interrupted" in plain.stdout and "NameError" in plain.stdout, plain.stdout + plain.stderr
    assert "interrupted" in filtered.stdout, filtered.stdout + filtered.stderr
    assert "Traceback" not in filtered.stdout and "NameError" not in filtered.stdout, filtered.stdout
    assert "tornado.application ERROR another error" in filtered.stdout  # the others pass
    cluster.filter_interrupted_sync()
    cluster.filter_interrupted_sync()
    assert sum(isinstance(f, cluster.InterruptedSyncFilter)
               for f in logging.getLogger("tornado.application").filters) == 1


@pytest.mark.slow
def test_ctrl_c_keeps_finished_captures_and_a_rerun_continues(slow_session, slow_serial, tmp_path,
                                                              capsys):
    d = _copies([slow_session], tmp_path / "dist")[0]
    proc = _spawn(["reconstruct", str(d), "--workers", "2", "--demosaic", "bilinear"])
    try:
        line = proc.stdout.readline()  # the first finished capture
        assert ": done" in line, line + proc.stderr.read()
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the local workers get it too
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert err.strip().endswith("polrig: interrupted")
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err  # the workers stay quiet
    revs = [c["revisions"]["rev1"] for c in Session.open(d).captures]
    done = [r for r in revs if r["status"] == "complete"]
    pending = [r for r in revs if r["status"] == "pending"]
    assert done and pending and len(done) + len(pending) == 6
    assert {r["reason"] for r in pending} == {"interrupted by the operator (Ctrl-C)"}
    _no_leftovers(d)
    kept = {k: v for k, v in _results(d).items() if v[0] == "complete"}
    assert main(["reconstruct", str(d), "--workers", "2", "--demosaic", "bilinear",
                 "--no-progress"]) == 0
    assert f"revision rev1 continued in {d}" in capsys.readouterr().out
    s = Session.open(d)
    assert [r["name"] for r in s.manifest["revisions"]] == ["rev1"]
    assert s.manifest["history"][-1]["event"] == "revision continued"
    assert _results(d) == slow_serial
    assert all(_results(d)[k] == v for k, v in kept.items())
    _no_leftovers(d)


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux ``/proc``)."""
    kids = []
    for task in pathlib.Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            kids += [int(k) for k in (task / "children").read_text().split()]
    return kids


def _importing_numpy(pid: int) -> bool:
    """Whether process ``pid`` has loaded numpy's core extension (a worker starting: it
    imports numpy while it unpickles its task, Linux ``/proc``)."""
    with contextlib.suppress(OSError):
        return "_multiarray_umath" in pathlib.Path(f"/proc/{pid}/maps").read_text()
    return False


@pytest.mark.skipif(not pathlib.Path("/proc/self/task").is_dir(), reason="reads Linux /proc")
def test_ctrl_c_while_the_local_workers_start_is_one_line(archive, tmp_path):
    """A terminal's Ctrl-C in the seconds the local workers take to start: the workers share
    the process group, and each printed its ``KeyboardInterrupt`` traceback (the nannies
    "Nanny failed to start", an ``AssertionError`` at exit) over ``polrig``'s one line. Now
    the start holds the signal (:func:`polrig.app.cluster.terminal_interrupt_held`): one
    line, exit 130, nothing written, no process of the command left behind."""
    d = _copies(archive[:1], tmp_path / "dist")[0]
    before = Session.open(d).manifest
    proc = _spawn(["reconstruct", str(d), "--workers", "2", "--demosaic", "bilinear"])
    try:
        deadline = time.monotonic() + 60
        while not any(_importing_numpy(k) for k in _children(proc.pid)):  # a worker starting
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.005)
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the starting workers too
        out, err = proc.communicate(timeout=120)
        deadline = time.monotonic() + 30
        while subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True).stdout:
            assert time.monotonic() < deadline, "a process of the command was left running"
            time.sleep(0.1)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert err.strip() == "polrig: interrupted", err
    assert Session.open(d).manifest == before


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signal masks")
def test_an_interrupt_held_through_a_start_arrives_after_it_and_never_in_its_children():
    """:func:`polrig.app.cluster.terminal_interrupt_held`: a SIGINT inside is raised as the
    block ends, not inside; a thread started inside blocks it, and so does a process started
    by that thread (``/proc/PID/status`` ``SigBlk``, bit 2 = SIGINT); after the block this
    thread's mask and handler are as before."""
    def sigint_blocked(status: str) -> bool:
        mask = int(re.search(r"^SigBlk:\s*([0-9a-f]+)$", status, re.M).group(1), 16)
        return bool(mask >> (signal.SIGINT - 1) & 1)

    seen = {}

    def child() -> None:
        seen["thread"] = sigint_blocked(pathlib.Path(
            f"/proc/self/task/{threading.get_native_id()}/status").read_text())
        seen["process"] = sigint_blocked(subprocess.run(
            [sys.executable, "-c", "print(open('/proc/self/status').read())"],
            capture_output=True, text=True, check=True).stdout)

    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    reached_the_end = False
    with pytest.raises(KeyboardInterrupt):
        with cluster.terminal_interrupt_held():
            os.kill(os.getpid(), signal.SIGINT)
            t = threading.Thread(target=child)
            t.start()
            t.join()
            time.sleep(0.05)  # a signal not held would have been raised by now
            reached_the_end = True
    assert reached_the_end
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    if pathlib.Path("/proc/self/task").is_dir():
        assert seen == {"thread": True, "process": True}
    with cluster.terminal_interrupt_held():  # nothing held: nothing raised
        pass


def test_damaged_captures_are_marked_failed_and_summarised_by_session(archive, tmp_path, capsys):
    a, b = _copies(archive, tmp_path)
    for s, i in ((a, 1), (b, 2)):
        (s / Session.open(s).capture(i)["files"]["raw"][0]["path"]).unlink()
    assert main(["reconstruct", str(a), str(b), "--workers", "2", "--no-progress"]) == 1
    out, err = capsys.readouterr()
    assert len(err.strip().splitlines()) == 1, err
    assert ("polrig: error: 2 capture(s) failed in 2 of 2 session(s) (a rev1: 1, b rev1: 1); "
            "the others are complete") in err
    assert f"{a}: revision rev1: 1 of 4 capture(s) failed: capture 1 (c001_pose090.0): " \
           f"FileNotFoundError" in out
    assert [c["revisions"]["rev1"]["status"] for c in Session.open(a).captures] == [
        "complete", "failed", "complete", "complete"]
    assert "FileNotFoundError" in Session.open(b).capture(2)["revisions"]["rev1"]["reason"]
    # one session: the serial command's own line
    c = _copies(archive[:1], tmp_path / "one")[0]
    (c / Session.open(c).capture(0)["files"]["raw"][0]["path"]).unlink()
    assert main(["reconstruct", str(c), "--workers", "1", "--no-progress"]) == 1
    assert ("polrig: error: revision rev1: 1 of 4 capture(s) failed, the others are complete: "
            "capture 0 (c000_pose000.0): FileNotFoundError") in capsys.readouterr().err


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_scheduler_with_no_worker_is_said_so_before_the_batch_waits(archive, tmp_path, capsys):
    """``--scheduler`` of a cluster no worker has joined yet: Dask waits for one (workers may
    join later, from a job queue), so the command first says where the work goes and that it
    waits, instead of sitting silent at 0/N; it is then stopped like any batch (Ctrl-C)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp", host="127.0.0.1",
                      dashboard_address=None) as empty:
        runner = cluster.open_runner(None, empty.scheduler_address)
        try:
            assert runner.description == (f"scheduler {empty.scheduler_address} (no worker yet: "
                                           "the tasks wait until one joins, e.g. 'dask worker "
                                           "ADDRESS')")
        finally:
            runner.close()
        session = _copies(archive, tmp_path / "c")[0]
        timer = threading.Timer(3.0, lambda: signal.raise_signal(signal.SIGINT))
        timer.start()
        try:
            code = main(["reconstruct", str(session), "--scheduler", empty.scheduler_address,
                         "--no-progress"])
        finally:
            timer.cancel()
    err = capsys.readouterr().err
    assert code == 130
    assert f"polrig reconstruct: on scheduler {empty.scheduler_address} (no worker yet" in err


def test_unreachable_scheduler_is_one_line_exit_2_before_anything_is_written(archive, tmp_path,
                                                                             capsys):
    import dask

    d = _copies(archive[:1], tmp_path)[0]
    before = {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        assert main(["reconstruct", str(d), "--scheduler",
                     f"tcp://127.0.0.1:{_free_port()}"]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1, err
        assert "cannot reach the Dask scheduler" in err
        assert {p: p.read_bytes() for p in d.rglob("*") if p.is_file()} == before
        assert main(["sim", "dataset", "--count", "2", "--size", "16", "--out",
                     str(tmp_path / "data"), "--scheduler", f"127.0.0.1:{_free_port()}"]) == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


@pytest.mark.parametrize("argv", [["reconstruct", "S", "--workers", "2"],
                                  ["reconstruct", "S", "--scheduler", "tcp://127.0.0.1:1"],
                                  ["sim", "dataset", "--count", "2", "--size", "16",
                                   "--out", "D", "--workers", "2"]])
def test_without_the_extra_the_options_say_how_to_install_it(argv, archive, tmp_path):
    """Dask made unimportable in a child process (``sys.modules['distributed'] = None``, as
    when the extra is not installed): exit 2, one line naming the extra; nothing written."""
    d = _copies(archive[:1], tmp_path)[0]
    argv = [str(d) if a == "S" else str(tmp_path / "data") if a == "D" else a for a in argv]
    before = {p: p.stat().st_mtime_ns for p in d.rglob("*")}
    code = ("import sys; sys.modules['distributed'] = None\n"
            f"from polrig.cli import main; sys.exit(main({argv!r}))")
    r = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [
        f"polrig: error: {argv[argv.index('--workers') if '--workers' in argv else argv.index('--scheduler')]}"
        f" needs Dask distributed, which is not installed; install the cluster extra: "
        f"{cluster.INSTALL_HINT}"]
    assert {p: p.stat().st_mtime_ns for p in d.rglob("*")} == before
    assert not (tmp_path / "data").exists()


def _readme_block() -> list[str]:
    """The README's "scheduler and two workers on this machine" command lines."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Scale-out on a cluster (Dask)"):]
    for block in section.split("```bash\n")[1:]:
        body = block.split("```")[0]
        if "dask scheduler --host" in body:
            return [ln for ln in body.splitlines() if ln.strip()]
    raise AssertionError("README: no 'dask scheduler' example in the scale-out section")


@pytest.mark.slow
def test_the_readme_scheduler_and_two_workers_example(archive, archive_serial, tmp_path):
    """The README's lines run as they are written, with real ``dask scheduler`` and
    ``dask worker`` processes on the loopback interface (a free port instead of 8786, the
    archive's two sessions instead of ``runs/demo``): the archive is reprocessed with the
    serial bytes, in bounded time, and every process is stopped afterwards."""
    import shlex

    lines = _readme_block()
    assert lines[0].startswith("dask scheduler") and lines[-1].startswith("kill %1 %2 %3")
    assert sum(ln.startswith("dask worker") for ln in lines) == 2
    dist = _copies(archive, tmp_path / "dist")
    port = str(_free_port())
    env = {**ENV, "DASK_TEMPORARY_DIRECTORY": str(tmp_path / "scratch")}
    background: list[subprocess.Popen] = []
    try:
        for line in lines[:-1]:
            argv = []
            for tok in shlex.split(line.rstrip(" &")):
                tok = tok.replace("8786", port)
                if tok == "runs/demo":
                    argv += [str(d) for d in dist]
                elif tok == "dask":
                    argv += [sys.executable, "-m", "dask"]
                elif tok == "polrig":
                    argv += [sys.executable, "-m", "polrig"]
                else:
                    argv.append(tok)
            # loopback only: every address a process listens on or connects to
            assert all(a.startswith(("127.0.0.1", "tcp://127.0.0.1")) for a in
                       [argv[i + 1] for i, t in enumerate(argv)
                        if t in ("--host", "--dashboard-address", "--scheduler")]
                       + [t for t in argv if t.startswith("tcp://")]), argv
            if line.rstrip().endswith("&"):
                background.append(subprocess.Popen(argv, env=env, cwd=tmp_path,
                                                   stdout=subprocess.DEVNULL,
                                                   stderr=subprocess.DEVNULL,
                                                   start_new_session=True))
            else:
                r = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True,
                                   timeout=240)
                assert r.returncode == 0, r.stderr
                assert r.stdout.count("revision rev1 written to") == 2
    finally:  # the README's 'kill %1 %2 %3', and whatever those processes started
        for p in reversed(background):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(background):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=20)
    for s, d in zip(archive_serial, dist):
        assert _results(d) == s
        _no_leftovers(d)


def test_a_session_list_takes_comments_after_a_path_and_keeps_a_hash_inside_one(tmp_path):
    from polrig.app.cluster import read_session_list

    lst = tmp_path / "l" / "sessions.txt"
    lst.parent.mkdir()
    lst.write_text("# the archive\n../s2   # the second\n  # indented\nruns/a#2\n/abs/s3\t# tab\n\n")
    assert read_session_list(lst) == [str(lst.parent / "../s2"), str(lst.parent / "runs/a#2"), "/abs/s3"]
