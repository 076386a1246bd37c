"""The hybrid solve's cost with the prior calibrated jointly against the per-element prior, at the
full sensor's grids.

:func:`polrig.solve.hybrid.solve_hybrid` of two states (0/90, the seen state 0) on synthetic
realizable Mueller images with shot and read noise and a prior of the shipped calibration's kind
(the truth plus Gaussian errors of a per-element sigma): ``prior_correlation=None`` (per element)
against the shipped ``joint_prior``'s ``K`` (:attr:`polrig.models.uncertainty.UncertaintyModel.joint_correlation`),
in interleaved rounds after one warm-up each (the compiled kernel compiled and cached), warm, in
process, float32 output as captures write it. Time (median) and the peak of numpy's allocations
(``tracemalloc``) per solve; the two results' largest difference on the object relative to its
largest value says the solves differ where the correlation acts.

    python benchmarks/bench_joint_prior.py [--grids 512x612x3,1024x1224x1] [--rounds 3] [--out FILE]

Grids: the colour sensor's superpixel grid (612x512, three colours) and the mono sensor's
(1224x1024, one colour), the grids `polrig capture --mode hybrid` solves at the full sensor.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time
import tracemalloc

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]


def inputs(h: int, w: int, c: int, seed: int = 0) -> dict:
    """Two states' samples ``(2, C, 4, H, W)``, their variance, a prior mean and sigma
    ``(C, 3, 3, H, W)`` (errors of 8 % of m00 on every element)."""
    from polrig.optics import mueller as mu
    from polrig.solve import reference as ref

    rng = np.random.default_rng(seed)
    s = mu.polarizer_stokes(np.radians([0.0, 90.0]), np.inf)
    m00 = rng.uniform(200.0, 2000.0, (c, h, w)).astype(np.float32)
    block = rng.uniform(-0.3, 0.3, (c, 3, 3, h, w)).astype(np.float32)
    block[:, 0, 0] = 1.0
    m = block * m00[:, None, None]
    clean = ref.forward_measurements(m, s)
    var = (4.0 + 0.5 * np.clip(clean, 0, None)).astype(np.float32)
    meas = (clean + rng.normal(size=clean.shape).astype(np.float32) * np.sqrt(var)).astype(np.float32)
    sigma = np.broadcast_to(0.08 * m00[:, None, None], m.shape).astype(np.float32)
    mean = (m + rng.normal(size=m.shape).astype(np.float32) * sigma).astype(np.float32)
    return {"s_in": s, "measured": meas, "variance": var, "prior_mean": mean, "prior_sigma": sigma}


def solve(data: dict, correlation):
    from polrig.solve.hybrid import solve_hybrid

    return solve_hybrid(data["s_in"], data["measured"], data["variance"], prior_mean=data["prior_mean"],
                        prior_sigma=data["prior_sigma"], seen_state=0, prior_correlation=correlation)


def measure(data: dict, correlation) -> tuple[float, float, np.ndarray]:
    tracemalloc.start()
    t = time.perf_counter()
    r = solve(data, correlation)
    seconds = time.perf_counter() - t
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return seconds, peak, r.mueller


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(REPO))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grids", default="512x612x3,1024x1224x1", help="HxWxC, comma-separated")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "joint_prior.md"))
    args = ap.parse_args(argv)
    from polrig.models.runtime import WEIGHTS_DIR
    from polrig.models.uncertainty import load_for_graph

    unc = load_for_graph(WEIGHTS_DIR, "single_shot.onnx")
    k = None if unc is None else unc.joint_correlation
    if k is None:
        print("the shipped calibration holds no joint prior", file=sys.stderr)
        return 1
    rows = []
    for grid in args.grids.split(","):
        h, w, c = (int(v) for v in grid.split("x"))
        data = inputs(h, w, c)
        solve(data, None)  # warm-up: the kernels compiled or loaded from their cache
        solve(data, k)
        times = {"per element": [], "joint": []}
        peaks = {"per element": [], "joint": []}
        results = {}
        for _ in range(args.rounds):
            for name, corr in (("per element", None), ("joint", k)):
                sec, peak, mueller = measure(data, corr)
                times[name].append(sec)
                peaks[name].append(peak)
                results[name] = mueller
        a, b = results["joint"], results["per element"]
        ok = np.isfinite(a) & np.isfinite(b)
        diff = float(np.max(np.abs(a[ok] - b[ok])) / np.max(np.abs(b[ok])))
        rows.append((f"{w}x{h}, {c} colour(s)", *(1e3 * statistics.median(times[n]) for n in times),
                     *(max(peaks[n]) for n in peaks), diff))
        print(f"{grid}: per element {rows[-1][1]:.0f} ms, joint {rows[-1][2]:.0f} ms", flush=True)
    lines = ["# The hybrid solve: the joint prior against the per-element prior", "",
             f"`python benchmarks/bench_joint_prior.py --grids {args.grids} --rounds {args.rounds}`", "",
             f"Two states (0/90, seen state 0), float32 output; medians of {args.rounds} interleaved rounds after "
             "one warm-up each, warm, in process; peak: numpy's allocations during one solve (tracemalloc).", "",
             "| grid | per element (ms) | joint (ms) | peak, per element (MiB) | peak, joint (MiB) | "
             "largest difference / largest value |",
             "|---|---:|---:|---:|---:|---:|"]
    lines += [f"| {g} | {t0:.0f} | {t1:.0f} | {p0:.0f} | {p1:.0f} | {d:.1e} |" for g, t0, t1, p0, p1, d in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    pathlib.Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
