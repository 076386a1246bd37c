"""Timing of the N-state reference solve (polrig.reference) and of the realizability tools;
prints a table.

Usage: ``python benchmarks/bench_reference.py [--size 1024] [--colours 3] [--repeat 2]``.
Times are the best of ``repeat`` runs, wall clock and process CPU time (the CPU time is the
robust number on a shared machine). Cases: ideal shared analyzer with all samples valid, the
same with 1% of the samples saturated (per-pattern condition numbers), and per-pixel analyzer
rows (general path) on a quarter of the image; then the realizability tests and the Cloude
filter on the same number of 3x3 blocks as one colour of the image.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from polrig import mueller as mu
from polrig import realizability as rz
from polrig import reference as ref
from polrig.noise import SensorModel
from polrig.stokes import ideal_analyzer_matrix


def best_of(fn, repeat):
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--colours", type=int, default=3)
    ap.add_argument("--states", default="0,45,90,135")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    c, n = args.colours, args.size
    s = mu.polarizer_stokes(np.radians([float(a) for a in args.states.split(",")]))
    sensor = SensorModel()
    truth = np.zeros((c, 3, 3, n, n), np.float32)
    truth[:, 0, 0] = 2000.0
    truth[:, 1, 1] = 800.0
    truth[:, 2, 2] = 600.0
    truth[:, 0, 1] = truth[:, 1, 0] = 300.0
    mean = ref.forward_measurements(truth[..., :64, :64], s)
    mean = np.tile(mean, (1, 1, 1, n // 64, n // 64)).astype(np.float32)
    meas = (mean + rng.normal(size=mean.shape).astype(np.float32) * 10).astype(np.float32)
    var = sensor.variance_dn2(meas, 10_000.0).astype(np.float32)
    valid = rng.random(meas.shape) > 0.01
    q = n // 2
    rows = (ideal_analyzer_matrix()[None, :, :, None, None]
            * (1 + 0.02 * rng.normal(size=(c, 4, 3, q, q)))).astype(np.float32)

    px = c * n * n
    cases = [
        ("ideal analyzer, all valid", px, lambda: ref.solve_reference(s, meas, var)),
        ("ideal analyzer, 1% samples saturated", px, lambda: ref.solve_reference(s, meas, var, valid)),
        ("per-pixel analyzer rows (1/4 image)", c * q * q,
         lambda: ref.solve_reference(s, meas[..., :q, :q], var[..., :q, :q], analyzer_rows=rows)),
    ]
    m3 = np.moveaxis(truth[0], (0, 1), (-2, -1)).astype(np.float64)
    m3 = m3 + rng.normal(size=m3.shape) * 50
    m4 = rz.complete_linear(m3[: n // 4], "zero")
    m3r = rng.normal(size=(n // 64, n, 3, 3))  # mostly non-physical: full search
    cases += [
        ("is_physical_coherency, zero completion (1/4)", m4.shape[0] * n, lambda: rz.is_physical_coherency(m4)),
        ("is_physical_gk, zero completion (1/4)", m4.shape[0] * n, lambda: rz.is_physical_gk(m4)),
        ("is_physical_linear, max-min-eigenvalue (1/16)", (n // 16) * n,
         lambda: rz.is_physical_linear(m3[: n // 16])),
        ("filter_linear, max-min-eigenvalue (1/16)", (n // 16) * n, lambda: rz.filter_linear(m3[: n // 16])),
        ("filter_linear, random blocks (1/64)", (n // 64) * n, lambda: rz.filter_linear(m3r)),
    ]
    print(f"# polrig reference/realizability benchmark, {c} colour(s) x {n} x {n}, "
          f"states {args.states}")
    print(f"{'case':48s} {'pixels':>10s} {'wall s':>8s} {'cpu s':>8s} {'Mpx/s (cpu)':>12s}")
    for name, npx, fn in cases:
        wall, cpu = best_of(fn, args.repeat)
        print(f"{name:48s} {npx:10d} {wall:8.2f} {cpu:8.2f} {npx / cpu / 1e6:12.2f}")


if __name__ == "__main__":
    main()
