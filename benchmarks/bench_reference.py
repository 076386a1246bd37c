"""Speed of the N-state reference solve (polrig.solve.reference) against the previous numpy
implementation (polrig.solve._reference_numpy), the numba compile time, and the realizability tools;
prints tables and writes the solve table into ``benchmarks/results/reference_solve.md`` (its own
section per image size; the rest of the file is left as it is).

Usage: ``python -m benchmarks reference`` or ``python benchmarks/bench_reference.py
[--size 512x612] [--colours 3] [--rounds 3] [--no-numpy] [--no-write]``.

Cases (4 states 0/45/90/135, float32 samples, sensor-model variances, 1 % of the samples
saturated, float32 outputs; "colour pixels" = C x H x W solved per second of wall time):
the ideal shared analyzer; the same with the nominal calibration uncertainty propagated
(analyzer 1 %, 0.5 deg, 0.02; generator 2 deg, 1/ER 0.006); per-pixel analyzer rows
``(C, 4, 3, H, W)`` float32 with the same tolerances. Each case runs in both
implementations, interleaved, ``rounds`` times; the table gives medians of wall and process
CPU time (the CPU time, summed over threads, is the robust number on a shared machine: on an
otherwise idle machine with T cores the wall rate approaches T x "Mpx per CPU-s"; the load
average during the run is printed). The default size is a quarter of a full-sensor superpixel output
(3 x 1024 x 1224), where the numpy path takes tens of seconds per round; ``--size 1024x1224
--no-numpy`` times the full output with the compiled solve alone.

Compile time: ``python -c 'solve once'`` in fresh processes with an empty numba cache
directory (cold: every kernel compiled) and again with the cache it left (warm).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

from polrig.optics import mueller as mu
from polrig.optics import realizability as rz
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import reference as ref
from polrig.solve._reference_numpy import solve_reference_numpy

REPO = pathlib.Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "reference_solve.md"
A_TOL = (0.01, 0.5, 0.02)
G_TOL = (2.0, 0.006)

COLD_START = """
import time
t0 = time.perf_counter()
import numpy as np
from polrig.solve import reference as ref
from polrig.optics import mueller as mu
t1 = time.perf_counter()
s = mu.polarizer_stokes(np.radians([0, 45, 90, 135]))
meas = np.full((4, 3, 4, 16, 16), 100.0, np.float32)
ref.solve_reference(s, meas, np.ones_like(meas), analyzer_tolerance=(0.01, 0.5, 0.02))
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def capture(c: int, h: int, w: int, rng):
    s = mu.polarizer_stokes(np.radians([0.0, 45.0, 90.0, 135.0]))
    truth = np.zeros((c, 3, 3, 64, 64))
    truth[:, 0, 0] = rng.uniform(1000, 3000, (c, 64, 64))
    truth[:, 1, 1] = 800.0
    truth[:, 2, 2] = 600.0
    truth[:, 0, 1] = truth[:, 1, 0] = 300.0
    mean = ref.forward_measurements(truth, s)
    reps = (1, 1, 1, -(-h // 64), -(-w // 64))
    mean = np.tile(mean, reps)[..., :h, :w].astype(np.float32)
    sensor = SensorModel()
    var = sensor.variance_dn2(np.clip(mean, 0, None), 10_000.0).astype(np.float32)
    meas = mean + rng.normal(size=mean.shape).astype(np.float32) * np.sqrt(var)
    valid = rng.random(meas.shape) > 0.01
    rows = (ideal_analyzer_matrix()[None, :, :, None, None]
            * (1 + 0.02 * rng.normal(size=(c, 4, 3, h, w)))).astype(np.float32)
    return s, meas, var, valid, rows


def timed(fn) -> tuple[float, float]:
    t, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t, time.process_time() - c


def compile_times() -> dict[str, tuple[float, float]]:
    """(import s, first solve s) in fresh processes: empty numba cache, then warm."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache,
                   PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        for label in ("cold (empty cache)", "warm (cached)"):
            res = subprocess.run([sys.executable, "-c", COLD_START], env=env, check=True,
                                 capture_output=True, text=True)
            imp, first = (float(v) for v in res.stdout.split())
            out[label] = (imp, first)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="512x612", help="HxW of the solved images")
    ap.add_argument("--colours", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--no-numpy", action="store_true", help="skip the previous implementation")
    ap.add_argument("--no-compile", action="store_true", help="skip the compile-time runs")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args()
    h, w = (int(v) for v in args.size.lower().split("x"))
    c = args.colours
    rng = np.random.default_rng(0)
    s, meas, var, valid, rows = capture(c, h, w, rng)
    px = c * h * w
    cal = dict(analyzer_tolerance=A_TOL, generator_tolerance=G_TOL)
    cases = {
        "ideal analyzer": lambda f, d: f(s, d[0], d[1], d[2]),
        "ideal analyzer + calibration tolerance": lambda f, d: f(s, d[0], d[1], d[2], **cal),
        "per-pixel rows (C,4,3,H,W) + tolerance": lambda f, d: f(s, *d, **cal),
    }
    data = (meas, var, valid, rows)
    impls = {"compiled (numba)": ref.solve_reference}
    if not args.no_numpy:
        impls["previous (numpy)"] = solve_reference_numpy
    strip = tuple(a[..., :8, :] for a in data)
    for run in cases.values():  # compile (or load the cached kernels) on a strip
        run(ref.solve_reference, strip)
    times = {(cn, im): [] for cn in cases for im in impls}
    for _ in range(args.rounds):
        for cn, run in cases.items():
            for im, fn in impls.items():
                times[cn, im].append(timed(lambda: run(fn, data)))
    load = os.getloadavg()
    import polrig.solve._reference_kernel as kern
    head = (f"{c} colours x {h} x {w} ({px / 1e6:.2f} M colour pixels), 4 states, float32 "
            f"samples, 1 % saturated; median of {args.rounds} interleaved rounds; "
            f"{kern.THREADS} threads on {os.cpu_count()} CPUs; load average during the run "
            f"{load[0]:.1f} / {load[1]:.1f}")
    lines = ["| case | implementation | wall s | CPU s | Mpx/s (wall) | Mpx per CPU-s | speed-up |",
             "|---|---|---|---|---|---|---|"]
    for cn in cases:
        base = np.median([t[0] for t in times[cn, "previous (numpy)"]]) if not args.no_numpy \
            else None
        for im in impls:
            wall = float(np.median([t[0] for t in times[cn, im]]))
            cpu = float(np.median([t[1] for t in times[cn, im]]))
            sp = f"{base / wall:.1f}x" if base is not None else "-"
            lines.append(f"| {cn} | {im} | {wall:.3f} | {cpu:.3f} | {px / wall / 1e6:.2f} | "
                         f"{px / cpu / 1e6:.2f} | {sp} |")
    table = "\n".join(lines)
    print(f"# reference solve, {head}\n{table}\n")

    ctable = ""
    if not args.no_compile:
        ct = compile_times()
        ctable = ("| numba cache | import polrig.solve.reference s | first solve s |\n|---|---|---|\n"
                  + "\n".join(f"| {k} | {v[0]:.2f} | {v[1]:.2f} |" for k, v in ct.items()))
        print(f"# first call in a fresh process (load average {os.getloadavg()[0]:.1f})\n"
              f"{ctable}\n")

    # realizability tools on as many 3x3 blocks as one colour of the image
    m3 = rng.normal(size=(h, w, 3, 3)) * 50 + np.diag([2000.0, 800.0, 600.0])
    m4 = rz.complete_linear(m3[: h // 4], "zero")
    m3r = rng.normal(size=(max(1, h // 64), w, 3, 3))  # mostly non-physical: full search
    others = [
        ("is_physical_coherency, zero completion (1/4)", m4.shape[0] * w,
         lambda: rz.is_physical_coherency(m4)),
        ("is_physical_gk, zero completion (1/4)", m4.shape[0] * w, lambda: rz.is_physical_gk(m4)),
        ("is_physical_linear, max-min-eigenvalue (1/16)", (h // 16) * w,
         lambda: rz.is_physical_linear(m3[: h // 16])),
        ("filter_linear, max-min-eigenvalue (1/16)", (h // 16) * w,
         lambda: rz.filter_linear(m3[: h // 16])),
        ("filter_linear, random blocks (1/64)", m3r.shape[0] * w, lambda: rz.filter_linear(m3r)),
    ]
    print(f"# realizability ({h} x {w} blocks per colour)")
    print(f"{'case':48s} {'blocks':>10s} {'wall s':>8s} {'cpu s':>8s} {'Mblocks/s':>10s}")
    for name, n, fn in others:
        res = [timed(fn) for _ in range(args.rounds)]
        wall = float(np.median([r[0] for r in res]))
        cpu = float(np.median([r[1] for r in res]))
        print(f"{name:48s} {n:10d} {wall:8.2f} {cpu:8.2f} {n / wall / 1e6:10.2f}")

    if args.no_write:
        return
    cmd = " ".join(["python benchmarks/bench_reference.py"] + sys.argv[1:])
    # one section per image size, replaced by the next run at that size
    begin = f"<!-- bench_reference {h}x{w}: begin -->"
    end = f"<!-- bench_reference {h}x{w}: end -->"
    section = (f"{begin}\n## Solve speed, {h} x {w}\n\n`{cmd}`: {head}.\n\n{table}\n"
               + (f"\nFirst call in a fresh process (numba compile; cached on disk after the "
                  f"first):\n\n{ctable}\n" if ctable else "") + f"{end}\n")
    text = RESULTS.read_text() if RESULTS.is_file() else "# Reference solve\n"
    if begin in text and end in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end) + 1:]
    else:
        text = text.rstrip("\n") + "\n\n" + section
    RESULTS.write_text(text)


if __name__ == "__main__":
    main()
