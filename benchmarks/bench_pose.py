"""Per-pose processing at full sensor: time and peak memory of each step, and EXR bytes.

Usage: ``python benchmarks/bench_pose.py [--size 2448x2048] [--layouts colour,mono]
[--methods superpixel,bilinear,newton] [--rounds 1] [--no-score] [--exr-choices]``
(or ``python -m benchmarks pose``). Writes the markdown tables to
``benchmarks/results/pose.md``.

One pose of a reference capture: 4 polarizer states (0, 45, 90, 135 deg), K = 1 frame each,
12-bit frames with a black level, nominal calibration (ideal analyzer, the nominal analyzer
and generator tolerances propagated into sigma). The scene is a synthetic Mueller image at
full resolution: a uniform background and a disk covering about a third of the frame whose
nine elements vary smoothly from pixel to pixel (a curved object: its truth differs between
neighbouring pixels almost everywhere on the disk, the worst case of the truth scoring);
frames are its ideal-analyzer mosaics with the sensor model's noise.

Each configuration (layout x demosaic) runs in a fresh process that loads the raw frames (and,
for the scoring, the truth) and then does what ``polrig.app.processing`` does per pose:

* ``radiance``: :func:`polrig.solve.radiometry.state_radiance` of the 4 states;
* ``solve``: :func:`polrig.solve.radiometry.reference_from_frames` (band-tiled demosaic and
  :func:`polrig.solve.reference.solve_reference`); the time inside ``solve_reference`` is given
  apart (``of which solve_reference``), since the solver itself is being replaced;
* ``exr``: :func:`polrig.formats.exr.write_mueller_exr` of the result with all planes (float32);
* ``score``: :func:`polrig.solve.scoring.score_on_output_grid` against the truth.

Peak memory is the process's peak resident set (``VmHWM`` of ``/proc/self/status``, Linux;
not ``ru_maxrss``, which Linux carries over ``exec`` from the parent), which includes the interpreter and libraries (about 100 MB), the raw frames and, for the scoring
run, the full-resolution truth (as the processor holds it). ``processing`` rows are a process
that never loads the truth; ``with score`` rows are a second process that does everything.

``--exr-choices`` also writes the full-sensor colour result (bilinear and superpixel) with each
plane choice (all planes float32 / half-float uncertainty / Mueller + mask only) and each
compression, and reports bytes and write time.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

RESULTS = REPO / "benchmarks" / "results" / "pose.md"
STATES_DEG = (0.0, 45.0, 90.0, 135.0)
EXPOSURE_US = 10000.0
BLACK_DN = 64.0
LAYOUTS = {"colour": "imx250myr", "mono": "imx250mzr"}
METHODS = ("superpixel", "bilinear", "newton")
#: nominal calibration tolerances (polrig.app.processing.NOMINAL_*_TOLERANCE)
ANALYZER_TOL = (0.01, 0.5, 0.02)
GENERATOR_TOL = (2.0, 0.006)


def scene(layout_name: str, h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(truth (C, 3, 3, H, W) float32, object mask (H, W) float32)``: background and a
    smoothly varying disk (DN per unit incident S0)."""
    from polrig.sensor.analyzer import resolve_layout

    c = resolve_layout(layout_name).n_colours
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    cy, cx, r = 0.5 * h, 0.5 * w, 0.35 * min(h, w)
    rho2 = ((v - cy) ** 2 + (u - cx) ** 2) / r**2
    disk = rho2 < 1.0
    t = np.zeros((c, 3, 3, h, w), np.float32)
    for ci in range(c):
        bg = np.array([[1200, 60, 0], [60, 900, 0], [0, 0, 800]], np.float32) * (1 + 0.1 * ci)
        t[ci] = bg[:, :, None, None]
        shade = np.sqrt(np.clip(1 - rho2, 0, 1)) * (2000 + 300 * ci)  # Lambertian-like
        nu, nv = (u - cx) / r, (v - cy) / r
        m = [[shade, 0.3 * shade * nu, 0.3 * shade * nv],
             [0.3 * shade * nu, 0.8 * shade, 0.1 * shade * nu * nv],
             [0.3 * shade * nv, -0.1 * shade * nu * nv, 0.75 * shade]]
        for i in range(3):
            for j in range(3):
                t[ci, i, j][disk] = m[i][j][disk]
    return t, disk.astype(np.float32)


def make_frames(truth: np.ndarray, layout_name: str, seed: int = 1) -> np.ndarray:
    """``(4, H, W)`` uint16 raw frames (12-bit, black level) of the 4 states."""
    from polrig.optics.mueller import polarizer_stokes
    from polrig.sensor.analyzer import AnalyzerModel
    from polrig.sensor.noise import SensorModel

    model = SensorModel()
    rng = np.random.default_rng(seed)
    h, w = truth.shape[-2:]
    ideal = AnalyzerModel.ideal(layout_name, (h, w))
    frames = []
    for s in polarizer_stokes(np.deg2rad(STATES_DEG), intensity=1.0):
        stokes = np.einsum("cijhw,j->cihw", truth, s.astype(np.float32))
        mosaic = ideal.mosaic(stokes)
        var = model.variance_dn2(mosaic, EXPOSURE_US)
        raw = mosaic + BLACK_DN + model.dark_electrons(EXPOSURE_US) / model.gain_e_per_dn
        raw += rng.standard_normal(raw.shape) * np.sqrt(var)
        frames.append(np.clip(np.rint(raw), 0, model.max_code_dn).astype(np.uint16))
    return np.stack(frames)


def run_pose(data: pathlib.Path, layout_name: str, method: str, score: bool,
             planes: tuple[str, ...], uncertainty: str, compression: str) -> dict:
    """The per-pose work in this process; returns timings (s), peak RSS (MB), EXR bytes."""
    from polrig.formats.exr import result_planes, write_mueller_exr
    from polrig.optics.mueller import polarizer_stokes
    from polrig.sensor.analyzer import resolve_layout
    from polrig.sensor.noise import SensorModel
    from polrig.solve import radiometry

    solve_s = [0.0]
    inner = radiometry.solve_reference

    def timed_solve(*a, **k):  # instrumentation: the solver's own share of the time
        t0 = time.perf_counter()
        try:
            return inner(*a, **k)
        finally:
            solve_s[0] += time.perf_counter() - t0

    radiometry.solve_reference = timed_solve
    model = SensorModel()
    frames = np.load(data / f"{layout_name}_frames.npy")
    lay = resolve_layout(layout_name)
    s_in = polarizer_stokes(np.deg2rad(STATES_DEG), intensity=1.0)
    out: dict = {}
    t0 = time.perf_counter()
    states = [radiometry.state_radiance([[f]], [EXPOSURE_US], model, black_level_dn=BLACK_DN)
              for f in frames]
    t1 = time.perf_counter()
    result = radiometry.reference_from_frames(
        states, s_in, lay, method, analyzer_tolerance=ANALYZER_TOL,
        generator_tolerance=GENERATOR_TOL,
        uncertainty_dtype=np.float16 if uncertainty == "half" else np.float32)
    t2 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="polrig-bench-") as d:
        p = pathlib.Path(d) / "mueller.exr"
        write_mueller_exr(p, result.mueller,
                          extra=result_planes(result, planes=planes, uncertainty=uncertainty),
                          compression=compression)
        out["exr_bytes"] = p.stat().st_size
    t3 = time.perf_counter()
    out.update(radiance_s=t1 - t0, solve_total_s=t2 - t1, solve_reference_s=solve_s[0],
               exr_s=t3 - t2)
    if score:
        from polrig.solve.scoring import score_on_output_grid

        truth = np.load(data / f"{layout_name}_truth.npy")
        obj = np.load(data / f"{layout_name}_object.npy")
        t4 = time.perf_counter()
        sc = score_on_output_grid(result, truth, lay, method, s_in, states, object_mask=obj)
        out["score_s"] = time.perf_counter() - t4
        out["rmse"], out["within_2sigma"] = sc["rmse"], sc["within_2sigma"]
    out["peak_rss_mb"] = peak_rss_mb()
    return out


EXR_CHOICES = (("all planes, float32", RESULT_GROUPS := ("mueller", "sigma", "sigma_noise",
                                                          "mask", "residual"), "float"),
               ("all planes, half uncertainty", RESULT_GROUPS, "half"),
               ("mueller + sigma + mask, half", ("mueller", "sigma", "mask"), "half"),
               ("mueller + mask", ("mueller", "mask"), "float"))


def run_exr_choices(data: pathlib.Path, layout_name: str, method: str) -> list[dict]:
    """One solve, then the EXR written with each plane choice and compression."""
    from polrig.formats.exr import result_planes, write_mueller_exr
    from polrig.optics.mueller import polarizer_stokes
    from polrig.sensor.noise import SensorModel
    from polrig.solve import radiometry

    frames = np.load(data / f"{layout_name}_frames.npy")
    states = [radiometry.state_radiance([[f]], [EXPOSURE_US], SensorModel(),
                                        black_level_dn=BLACK_DN) for f in frames]
    result = radiometry.reference_from_frames(
        states, polarizer_stokes(np.deg2rad(STATES_DEG), intensity=1.0), layout_name, method,
        analyzer_tolerance=ANALYZER_TOL, generator_tolerance=GENERATOR_TOL)
    out = []
    with tempfile.TemporaryDirectory(prefix="polrig-bench-") as d:
        for label, planes, unc in EXR_CHOICES:
            for comp in ("zip", "piz", "none"):
                p = pathlib.Path(d) / "mueller.exr"
                t0 = time.perf_counter()
                write_mueller_exr(p, result.mueller, compression=comp,
                                  extra=result_planes(result, planes=planes, uncertainty=unc))
                out.append(dict(label=label, compression=comp, exr_bytes=p.stat().st_size,
                                exr_s=time.perf_counter() - t0))
                p.unlink()
    return out


def peak_rss_mb() -> float:
    """This process's peak resident set in MB (``VmHWM``; ``ru_maxrss`` where there is no
    ``/proc``)."""
    try:
        for line in pathlib.Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(args: list[str]) -> dict:
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--child", json.dumps(args)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if r.returncode:
        raise SystemExit(f"bench_pose child failed: {r.stderr.strip().splitlines()[-1:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="2448x2048", help="WxH of the sensor (default full)")
    ap.add_argument("--layouts", default="colour,mono")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--rounds", type=int, default=1, help="processes per configuration "
                    "(median reported)")
    ap.add_argument("--no-score", action="store_true", help="skip the runs with scoring")
    ap.add_argument("--uncertainty", choices=("float", "half", "both"), default="both",
                    help="uncertainty planes of the runs (both: float32 for every row, half for "
                         "colour bilinear as well)")
    ap.add_argument("--exr-choices", action="store_true",
                    help="also report EXR bytes/time per plane choice and compression")
    ap.add_argument("--results", type=pathlib.Path, default=RESULTS,
                    help=f"markdown file to write (default {RESULTS.relative_to(REPO)})")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ns = ap.parse_args(argv)
    if ns.child:
        a = json.loads(ns.child)
        if a[0] == "exr":
            print(json.dumps(run_exr_choices(pathlib.Path(a[1]), a[2], a[3])))
        else:
            print(json.dumps(run_pose(pathlib.Path(a[0]), a[1], a[2], a[3], tuple(a[4]), a[5],
                                      a[6])))
        return 0
    w, h = (int(x) for x in ns.size.lower().split("x"))
    layouts = [LAYOUTS[k] for k in ns.layouts.split(",")]
    methods = ns.methods.split(",")
    all_planes = ["mueller", "sigma", "sigma_noise", "mask", "residual"]
    rows, exr_rows = [], []
    with tempfile.TemporaryDirectory(prefix="polrig-bench-data-") as d:
        data = pathlib.Path(d)
        for lay in layouts:
            truth, obj = scene(lay, h, w)
            np.save(data / f"{lay}_truth.npy", truth)
            np.save(data / f"{lay}_object.npy", obj)
            np.save(data / f"{lay}_frames.npy", make_frames(truth, lay))
            del truth, obj
        configs = [(lay, method, unc) for unc in ("float", "half") for lay in layouts
                   for method in methods if ns.uncertainty in (unc, "both")
                   and (unc == "float" or ns.uncertainty == "half"
                        or (lay, method) == (LAYOUTS["colour"], "bilinear"))]
        for lay, method, unc in configs:
            for score in ([False] if ns.no_score else [False, True]):
                runs = [child([d, lay, method, score, all_planes, unc, "zip"])
                        for _ in range(max(1, ns.rounds))]
                med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
                rows.append((lay, method, unc, score, med))
                print(lay, method, unc, "with score" if score else "processing",
                      json.dumps({k: round(v, 3) for k, v in med.items()}), flush=True)
        if ns.exr_choices and LAYOUTS["colour"] in layouts:
            for method in ("bilinear", "superpixel"):
                for r in child(["exr", d, LAYOUTS["colour"], method]):
                    exr_rows.append((LAYOUTS["colour"], method, r))
                    print(method, json.dumps(r), flush=True)
    write_tables(rows, exr_rows, (w, h), ns.rounds, ns.results)
    return 0


def write_tables(rows, exr_rows, size, rounds, path: pathlib.Path = RESULTS) -> None:
    lines = [f"# Per-pose processing at {size[0]}x{size[1]}",
             "",
             f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
             f"{platform.node()}, {os.cpu_count()} CPUs, {platform.python_version()}; median "
             f"of {rounds} process(es) per row. 4 states, K = 1, nominal calibration, EXR with "
             f"all planes (ZIP), uncertainty planes in float32 or half. Times in s; peak = "
             f"peak RSS (VmHWM) of the process in MB.",
             "",
             "| layout | demosaic | uncertainty | run | radiance | demosaic + solve (tiled) | of which "
             "solve_reference | EXR write | EXR MB | score | total | peak MB |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for lay, method, unc, score, r in rows:
        total = r["radiance_s"] + r["solve_total_s"] + r["exr_s"] + r.get("score_s", 0.0)
        score_s = f"{r['score_s']:.2f}" if score else "-"
        lines.append(
            f"| {lay} | {method} | {unc} | {'with score' if score else 'processing'} | "
            f"{r['radiance_s']:.2f} | {r['solve_total_s']:.2f} | {r['solve_reference_s']:.2f} | "
            f"{r['exr_s']:.2f} | {r['exr_bytes'] / 1e6:.0f} | {score_s} | {total:.2f} | "
            f"{r['peak_rss_mb']:.0f} |")
    if exr_rows:
        lines += ["", "## EXR bytes per pose by plane choice (one result, written each way)", "",
                  "| layout | demosaic | planes | compression | bytes | MB | write s |",
                  "|---|---|---|---|---|---|---|"]
        for lay, method, r in exr_rows:
            lines.append(f"| {lay} | {method} | {r['label']} | {r['compression']} | "
                         f"{r['exr_bytes']} | {r['exr_bytes'] / 1e6:.0f} | {r['exr_s']:.2f} |")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    sys.exit(main())
