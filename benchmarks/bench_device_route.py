"""The single-shot frame's device route against its host route, per step, per provider (issue 31).

Per case (raw size, colour or mono, superpixel or full resolution) and provider, in interleaved
rounds after one warm-up, warm in process, the raw frame in memory to the result in memory:

* **host route**: :meth:`polrig.app.single_shot.SingleShot.frame` with the numpy and OpenCV
  steps around the networks (the CPU's declared route, ``FRAME_ROUTES``);
* **device route**: the same call with the steps as ONNX graphs on the provider's device
  (:mod:`polrig.models.device_path`), its time split into ``upload`` (the raw mosaic),
  ``pre`` (demosaic, Stokes, network inputs), ``statistics`` (the mask's S0 down and the
  scale's tail), ``networks`` (probe, frame pass, refinement), ``post`` (rotation, DN, the
  full-resolution lift, SNR) and ``copy_back`` (the result's arrays to the host);
* the two routes' largest Mueller difference relative to the host route's largest value;
* the live view's frame (:meth:`~polrig.app.single_shot.SingleShot.live`, the grid at a long
  side of 1024 px on the device route; :meth:`frame` on the host route), ms and fps, Qt's
  colour mapping and display not included;
* with ``cpu`` and ``cuda`` both listed: the device route's CUDA-vs-CPU parity per output
  (the issue's target: within 1e-4 of each output's maximum, TF32 off).

``--live-frames N`` (N >= 2) also measures the live view's probe schedule on the simulated
rig: N frames of a mono 512x512 sphere turning on the turntable (5 degrees a frame; the
networks' 256x256 grid runs the light-direction probe), the device route's live grid
(:meth:`~polrig.app.single_shot.SingleShot.live`) with the probe on every frame and on every
``LIVE_PROBE_EVERY``-th frame: the ms per frame, the input rotation's largest change, the
Mueller image's change relative to its maximum, and the matrix PSNR against the hidden truth
(averaged over the superpixel cells, on the cells wholly on the object).

The GPU's name is printed (``nvidia-smi``).

    python benchmarks/bench_device_route.py [--devices cpu,cuda] [--sizes 256x256] [--rounds 3]
        [--resolutions superpixel,full] [--layouts colour,mono] [--live-frames 8] [--out FILE]
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

from benchmarks.bench_single_shot import COLOUR, MONO, _rig_geometry, gpu_name, synthetic_raw  # noqa: E402
from polrig.sensor.frame import Frame, FrameMeta  # noqa: E402

STEPS = ("upload", "pre", "statistics", "network", "post", "copy_back")
LAYOUT_NAMES = {"colour": COLOUR, "mono": MONO}


def make_frame(shape, layout: str, seed: int = 0) -> Frame:
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=10000.0, gain_db=0.0, pixel_format="Mono16",
                     layout=layout, bit_depth=12, black_level_dn=64.0)
    return Frame(raw=synthetic_raw(shape, np.random.default_rng(seed), layout), meta=meta)


def _rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    peak = float(np.max(np.abs(b[ok]), initial=0.0)) or 1.0
    return float(np.max(np.abs(a[ok] - b[ok]), initial=0.0)) / peak


def routes(device: str, cases, rounds: int, geometry: dict) -> tuple[list[dict], dict]:
    """Timings per case on ``device`` and the device route's results (for the parity)."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    model = SingleShotModel.load(device=device)
    host, dev = SingleShot(model, "host"), SingleShot(model, "device")
    rows, results = [], {}
    for label, frame, resolution in cases:
        opts = SingleShotOptions(resolution, sigma=False)
        a = host.frame(frame, 0.0, opts, geometry=geometry)
        b = dev.frame(frame, 0.0, opts, geometry=geometry)  # warm-ups: sessions, plans, buffers
        dev.live(frame, 0.0, opts, max_display_px=1024, geometry=geometry)
        row = {"device": device, "provider": model.provider, "case": label, "host": [], "device_route": [], "live": [],
               "steps": {k: [] for k in STEPS}, "host_vs_device": _rel(b.mueller, a.mueller)}
        results[label] = {"mueller": b.mueller, "snr": b.snr}
        rows.append(row)
    for _ in range(rounds):
        for row, (label, frame, resolution) in zip(rows, cases):
            opts = SingleShotOptions(resolution, sigma=False)
            t0 = time.perf_counter()
            host.frame(frame, 0.0, opts, geometry=geometry)
            t1 = time.perf_counter()
            r = dev.frame(frame, 0.0, opts, geometry=geometry)
            t2 = time.perf_counter()
            dev.live(frame, 0.0, opts, max_display_px=1024, geometry=geometry)
            row["live"].append(time.perf_counter() - t2)
            row["host"].append(t1 - t0)
            row["device_route"].append(t2 - t1)
            for k in STEPS:
                row["steps"][k].append(r.timings_s.get(k, 0.0))
    return rows, results


def live_probe(device: str, n_frames: int, tmp: pathlib.Path) -> list[dict]:
    """The live grid with the probe on every frame and every LIVE_PROBE_EVERY-th (module docstring)."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.calibrations import load_calibration, single_shot_geometry
    from polrig.app.rig import load_rig_config
    from polrig.app.single_shot import SingleShot
    from polrig.cli import main as cli
    from polrig.formats.rawio import read_raw
    from polrig.models import device_path
    from polrig.models.full_resolution import bin_cells
    from polrig.models.runtime import SingleShotModel
    from polrig.solve.scoring import score_against_truth

    shots = []
    for k in range(n_frames):
        out = tmp / "live"
        cli(["sim", "render", "--size", "512x512", "--states", "0", "--no-exr", "--sensor", MONO, "--pose",
             str(5 * k), "--out", str(out)])
        raw = sorted(out.glob(f"pose{5 * k:04d}*_state00.png"))[0]
        truth = dict(np.load(sorted(out.glob(f"truth_pose{5 * k:04d}*.npz"))[0]))
        shots.append((read_raw(raw), truth))
    geometry = single_shot_geometry(load_calibration(None), load_rig_config(None))
    opts = SingleShotOptions(sigma=False)
    rows, reference = [], []
    for every in (1, device_path.LIVE_PROBE_EVERY):
        route = SingleShot(SingleShotModel.load(device=device), "device")
        route.device_path().probe_every = every
        route.live(shots[0][0], 0.0, opts, max_display_px=1024, geometry=geometry)  # warm-up
        times, rot, diff, psnr = [], [], [], []
        route.device_path().restart_live()
        for frame, _ in shots:  # the grid, as the live view shows it
            t0 = time.perf_counter()
            route.live(frame, 0.0, opts, max_display_px=1024, geometry=geometry)
            times.append(time.perf_counter() - t0)
        route.device_path().restart_live()
        for k, (frame, truth) in enumerate(shots):  # the same schedule's whole Mueller image
            r = route.live(frame, 0.0, opts, max_display_px=None, geometry=geometry)
            if every == 1:
                reference.append(r)
            else:
                rot.append(abs(r.incident_rotation_deg - reference[k].incident_rotation_deg))
                diff.append(_rel(r.mueller, reference[k].mueller))
            # the truth averaged over the 2x2 cells of the superpixel grid, on the cells wholly on the object
            score = score_against_truth(r.estimate(), bin_cells(truth["mueller"], 2),
                                        bin_cells(truth["mask"].astype(np.float32), 2) > 0.999)
            psnr.append(score["psnr_db"])
        rows.append({"every": every, "ms": 1e3 * statistics.median(times),
                     "rotation_deg": max(rot) if rot else 0.0, "mueller_rel": max(diff) if diff else 0.0,
                     "psnr_db": float(np.mean([p for p in psnr if p is not None]))})
    return rows


def render(rows: list[dict], parity: dict, live: list[dict], gpu: str | None, rounds: int) -> str:
    med = lambda xs: 1e3 * statistics.median(xs)  # noqa: E731
    lines = [f"GPU: {gpu or 'none'}. Medians over {rounds} interleaved round(s) after one warm-up, warm in "
             "process, the raw frame in memory to the result in memory; ms.", "",
             "| provider | case | host route | device route | " + " | ".join(STEPS)
             + " | live grid (fps) | device vs host |",
             "|---|---|---|---|" + "---|" * len(STEPS) + "---|---|"]
    for r in rows:
        lines.append(f"| {r['provider']} | {r['case']} | {med(r['host']):.1f} | **{med(r['device_route']):.1f}** | "
                     + " | ".join(f"{med(r['steps'][k]):.1f}" for k in STEPS)
                     + f" | {med(r['live']):.1f} ({1e3 / med(r['live']):.1f}) | {r['host_vs_device']:.1e} |")
    if parity:
        lines += ["", "Device route, CUDA against the CPU provider (largest difference over the output's largest "
                  "value; target <= 1e-4 with TF32 off):", "", "| case | mueller | snr |", "|---|---|---|"]
        lines += [f"| {k} | {v['mueller']:.1e} | {v['snr']:.1e} |" for k, v in parity.items()]
    if live:
        lines += ["", "Live grid on the simulated rig (mono 512x512 sphere turning 5 deg a frame, the probe on "
                  "every frame or every N-th): ms per frame, the input rotation's and the Mueller image's largest "
                  "change against probing every frame, matrix PSNR against the hidden truth:", "",
                  "| probe every | ms / frame | rotation change (deg) | Mueller change | PSNR (dB) |",
                  "|---|---|---|---|---|"]
        lines += [f"| {r['every']} | {r['ms']:.0f} | {r['rotation_deg']:.3f} | {r['mueller_rel']:.1e} | "
                  f"{r['psnr_db']:.2f} |" for r in live]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", default="cpu", help="comma-separated: cpu, cuda (default cpu)")
    ap.add_argument("--sizes", default="256x256", help="raw WxH list, comma-separated (default 256x256)")
    ap.add_argument("--layouts", default="colour,mono")
    ap.add_argument("--resolutions", default="superpixel,full")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--live-frames", type=int, default=0, help="also the live probe schedule over N frames")
    ap.add_argument("--out", default=None, help="also write the table to this Markdown file")
    args = ap.parse_args(argv)
    geometry = _rig_geometry()
    cases = []
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.lower().split("x"))
        for layout in args.layouts.split(","):
            frame = make_frame((h, w), LAYOUT_NAMES[layout])
            for res in args.resolutions.split(","):
                cases.append((f"{w}x{h} {layout} {res}", frame, res))
    devices = args.devices.split(",")
    rows, results = [], {}
    for device in devices:
        r, results[device] = routes(device, cases, args.rounds, geometry)
        rows += r
        # the table so far, in the log: a run cut short by its time limit still leaves its rows
        print(render(rows, {}, [], gpu_name() if device == "cuda" else None, args.rounds), flush=True)
    parity = {}
    if "cpu" in results and "cuda" in results:
        parity = {k: {o: _rel(results["cuda"][k][o], results["cpu"][k][o]) for o in ("mueller", "snr")}
                  for k in results["cpu"]}
    live = []
    if args.live_frames >= 2:
        with tempfile.TemporaryDirectory() as d:
            live = live_probe(devices[0], args.live_frames, pathlib.Path(d))
    text = render(rows, parity, live, gpu_name() if "cuda" in devices else None, args.rounds)
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text("# Single-shot device route against the host route\n\n`python "
                                          f"benchmarks/bench_device_route.py {' '.join(argv or sys.argv[1:])}`\n\n"
                                          + text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
