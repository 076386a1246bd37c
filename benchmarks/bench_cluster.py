"""``polrig reconstruct`` throughput on Dask: serial (this process) versus a ``LocalCluster`` of 1
and 2 single-threaded worker processes (:mod:`polrig.app.cluster`), on one simulated session.

Per configuration and round, a fresh copy of the session is reconstructed (reference method,
the session's demosaic) and timed from submission to the last manifest record; the clusters
are started once before the rounds (start-up time reported apart) and warmed with one capture
each. Rounds interleave the configurations (serial, 1, 2 workers, then rotated). Reported:

* captures per second (median and best over rounds), speed-up against 1 worker and serial;
* per-task overhead: the median wall time of an empty task submitted one at a time (Dask's
  round trip), and the per-capture difference between 1 worker and serial (round trip plus
  the worker opening the session and sending its result);
* bytes between client and workers: the pickled task (``CaptureJob``) and result
  (``CaptureOutcome``) per capture, against the raw bytes a capture reads; and the bytes the
  client process itself read during a run (``rchar`` of ``/proc/self/io``: files and
  sockets), which shows that raw data does not travel through the client.

Every configuration's result files are checked to be the same bytes (SHA-256 records).

    python benchmarks/bench_cluster.py [--size 512x512] [--captures 8] [--rounds 3]

Writes ``benchmarks/results/cluster.md``.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import pickle
import platform
import shutil
import statistics
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)
RESULTS = REPO / "benchmarks" / "results" / "cluster.md"


def _rchar() -> int:
    try:
        for line in pathlib.Path("/proc/self/io").read_text().splitlines():
            if line.startswith("rchar:"):
                return int(line.split()[1])
    except OSError:
        pass
    return -1


def make_session(tmp: pathlib.Path, size: str, captures: int) -> pathlib.Path:
    from polrig.cli import main

    cfg = tmp / "rig.toml"
    cfg.write_text(f'[sim]\nsize = "{size}"\nsensor = "imx250mzr"\nclock_speed = inf\n'
                   f'seed = 11\nscene = "box"\nnoise = true\n')
    out = tmp / "archive"
    step = 360.0 / captures
    poses = ",".join(f"{i * step:g}" for i in range(captures))
    if main(["capture", "--poses", poses, "--config", str(cfg), "--out", str(out),
             "--no-progress"]) != 0:
        raise SystemExit("capture failed")
    return out


def records(session_dir: pathlib.Path, revision: str) -> list[tuple[str, str]]:
    from polrig.app.session import Session

    s = Session.open(session_dir)
    return [(c["name"], c["revisions"][revision]["files"]["mueller"]["sha256"])
            for c in s.captures]


def reconstruct_timed(d: pathlib.Path, runner, cpu_now) -> tuple[float, float, int, int]:
    """``cluster.reconstruct`` of session ``d`` on ``runner``: wall seconds, CPU seconds
    (``cpu_now()`` before and after: every thread of the processes doing the work), bytes the
    calling process read (``rchar``), captures."""
    from polrig.app import cluster

    r0, c0, t0 = _rchar(), cpu_now(), time.perf_counter()
    batches = cluster.reconstruct([d], runner)
    dt, cpu, read = time.perf_counter() - t0, cpu_now() - c0, _rchar() - r0
    return dt, cpu, read, len(batches[0].todo)


def serial_child(d: pathlib.Path) -> None:
    """Child-process mode (``--serial-child DIR``): warm the imports with one solve that
    writes nothing, then reconstruct ``DIR`` serially; print the timings as JSON."""
    import json

    from polrig.app import cluster, reconstruct
    from polrig.app.session import Session

    s = Session.open(d)
    _, proc, done = reconstruct.revision_plan(s, None, None, None, None)
    proc.solve(s, done[0], None)
    dt, cpu, read, n = reconstruct_timed(d, cluster.SerialRunner(), time.process_time)
    print(json.dumps({"seconds": dt, "cpu": cpu, "read": read, "n": n}))


def serial_config(threads: int | None):
    """A serial run in a child process (its own BLAS/OpenMP thread count: ``threads`` sets
    ``OMP_NUM_THREADS``/``OPENBLAS_NUM_THREADS``/``MKL_NUM_THREADS``; ``None`` the defaults)."""
    import json
    import subprocess

    def run(d: pathlib.Path):
        env = dict(os.environ, PYTHONPATH=str(REPO))
        if threads is not None:
            env.update({k: str(threads) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                                   "MKL_NUM_THREADS")})
        r = subprocess.run([sys.executable, __file__, "--serial-child", str(d)], env=env,
                           capture_output=True, text=True, check=True)
        o = json.loads(r.stdout.strip().splitlines()[-1])
        return o["seconds"], o["cpu"], o["read"], o["n"]
    return run


def dask_config(runner):
    def cpu_now() -> float:
        return sum(runner.client.run(time.process_time).values())

    return lambda d: reconstruct_timed(d, runner, cpu_now)


def run_once(archive: pathlib.Path, work: pathlib.Path, config, tag: str):
    d = work / tag
    shutil.copytree(archive, d)
    dt, cpu, read, n = config(d)
    rec = records(d, "rev1")
    shutil.rmtree(d)
    return n / dt, dt / n, cpu / n, read, rec


def _peak_rss_bytes() -> int:
    """This process's peak resident memory, ``VmHWM`` of ``/proc/self/status`` (not
    ``ru_maxrss``: Linux carries a forked parent's peak across ``exec`` into it, so a spawned
    worker would report the client's memory)."""
    for line in pathlib.Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return -1


def noop(x):
    return x


def roundtrip_s(runner, n: int = 100) -> float:
    times = []
    for i in range(n):
        t = time.perf_counter()
        runner.client.submit(noop, i, pure=False).result()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serial-child", metavar="DIR", help=argparse.SUPPRESS)
    ap.add_argument("--size", default="512x512", help="sensor WxH (default 512x512; the "
                    "IMX250's full sensor is 2448x2048)")
    ap.add_argument("--captures", type=int, default=8, help="captures in the session")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    if args.serial_child:
        serial_child(pathlib.Path(args.serial_child))
        return 0
    from polrig.app import cluster, reconstruct
    from polrig.app.session import Session, format_bytes

    load0 = os.getloadavg()
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    try:
        t = time.perf_counter()
        archive = make_session(tmp, args.size, args.captures)
        print(f"session: {args.captures} captures at {args.size} in "
              f"{time.perf_counter() - t:.1f} s", flush=True)
        s = Session.open(archive)
        raw_bytes = sum(r["bytes"] for c in s.captures for r in c["files"]["raw"]) / len(s.captures)
        runners = {}
        startup = {}
        for n in (1, 2):
            t = time.perf_counter()
            runners[n] = cluster.DaskRunner.local(n)
            startup[n] = time.perf_counter() - t
        import logging

        logging.getLogger("distributed").setLevel(logging.ERROR)
        rt = roundtrip_s(runners[1])
        # warm-up: imports and first-call costs in every worker process
        for n, r in runners.items():
            warm = tmp / f"warm-{n}"
            shutil.copytree(archive, warm)
            ws = Session.open(warm, lock=True)
            b = cluster.prepare([ws])
            b[0].todo = b[0].todo[:n]
            cluster.run_batch(b, r)
            ws.unlock()
            shutil.rmtree(warm)
        configs = {"serial (default BLAS threads)": serial_config(None),
                   "serial, 1 thread": serial_config(1),
                   "1 worker": dask_config(runners[1]),
                   "2 workers": dask_config(runners[2])}
        names = list(configs)
        rates = {n: [] for n in names}
        per = {n: [] for n in names}
        cpus = {n: [] for n in names}
        reads = {n: [] for n in names}
        ref = None
        for k in range(args.rounds):
            order = names[k % len(names):] + names[:k % len(names)]
            for name in order:
                rate, sec, cpu, read, rec = run_once(archive, tmp, configs[name], f"r{k}")
                if ref is None:
                    ref = rec
                assert rec == ref, f"{name}: result files differ from the first run's"
                rates[name].append(rate)
                per[name].append(sec)
                reads[name].append(read)
                cpus[name].append(cpu)
                print(f"round {k + 1} {name}: {rate:.3f} captures/s ({sec:.2f} s/capture, "
                      f"CPU {cpu:.2f} s/capture, read {read / 1e6:.1f} MB)", flush=True)
        # bytes of one task and one result, as Dask pickles them (the settings a revision of
        # the session's own plan records)
        settings, _, _ = reconstruct.revision_plan(s, None, None, None, None)
        job = cluster.jobs_of(cluster.SessionBatch(s, "rev1", settings, [0]), None)[0]
        import cloudpickle

        wb = tmp / "bytes"
        shutil.copytree(archive, wb)
        bs = Session.open(wb, lock=True)
        bb = cluster.prepare([bs])
        bs.unlock()
        outcome = cluster.process_job(cluster.jobs_of(bb[0], None)[0])
        job_b, out_b = len(cloudpickle.dumps(job)), len(pickle.dumps(outcome))
        rss = {f"{n} worker(s)": sorted(runners[n].client.run(_peak_rss_bytes).values())
               for n in runners}
        for r in runners.values():
            r.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load1 = os.getloadavg()
    med = {n: statistics.median(v) for n, v in rates.items()}
    one = med["1 worker"]
    lines = [
        "# `polrig reconstruct` on Dask: serial vs local single-threaded workers",
        "",
        f"`python benchmarks/bench_cluster.py --size {args.size} --captures {args.captures} "
        f"--rounds {args.rounds}`: one simulated IMX250MZR session, {args.captures} captures "
        f"of {args.size}, reference method (4 states, superpixel), {args.rounds} interleaved "
        f"rounds on a fresh copy each. {platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; load average {load0[0]:.1f} before, {load1[0]:.1f} after "
        f"(the machine is shared with other work: absolute numbers and ratios move with it).",
        "",
        "| configuration | captures/s (median) | best | s/capture (median) | CPU s/capture (median) | vs 1 worker | vs serial | read by the polrig process per run |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    serial = med["serial (default BLAS threads)"]
    for n in names:
        lines.append(f"| {n} | {med[n]:.3f} | {max(rates[n]):.3f} | "
                     f"{statistics.median(per[n]):.2f} | {statistics.median(cpus[n]):.2f} | "
                     f"{med[n] / one:.2f}x | {med[n] / serial:.2f}x | "
                     f"{format_bytes(statistics.median(reads[n]))} |")
    overhead = statistics.median(cpus["1 worker"]) - statistics.median(cpus["serial, 1 thread"])
    lines += [
        "",
        f"- Cluster start-up (not in the rates): 1 worker {startup[1]:.1f} s, 2 workers "
        f"{startup[2]:.1f} s.",
        f"- Per-task overhead: an empty task's round trip {rt * 1e3:.1f} ms (median of 100); "
        f"CPU per capture of 1 worker minus serial (1 thread) {overhead * 1e3:+.0f} ms (the "
        f"worker opening the session manifest, Dask's own threads; wall-clock differences are "
        f"not overhead: the client records one capture while the worker solves the next).",
        f"- Bytes per capture between client and workers: task {job_b} B, result "
        f"{out_b} B; the capture's raw frames are {format_bytes(raw_bytes)}, read by the worker "
        f"from the shared file system. The client's own reads per run (files and sockets, "
        f"`rchar`) are in the table: serial reads every raw frame, the cluster runs read the "
        f"manifest and the small messages.",
        "- CPU s/capture: CPU time of every thread of the processes doing the work (the serial "
        "child process; the Dask worker processes), per capture. Serial runs in a child "
        "process with the default thread counts, or with OMP/OpenBLAS/MKL limited to 1 "
        "thread as Dask's nanny limits its workers.",
        "- Result files: the same SHA-256 in every configuration and round.",
        "- Peak resident memory of each worker process over the whole benchmark (warm-up, "
        "rounds; `VmHWM`): " + "; ".join(f"{n}: " + ", ".join(format_bytes(b) for b in v)
                                            for n, v in rss.items()) +
        " (what a worker needs at this size: workers per node <= memory / this).",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
