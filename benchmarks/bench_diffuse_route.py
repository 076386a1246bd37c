"""Two-state captures with ``--models diffuse`` (``polrig.app.diffuse_route``) against the plain
hybrid of the same frames: accuracy on captures of the simulated rig, and the solve's time at the
full colour sensor.

``python -m benchmarks diffuse_route [--rounds N] [--skip-full]``:

* **Accuracy** (one-shot captures): the simulator's diffuse sphere, hybrid 0/90, mono at 64x64,
  128x128 and 256x256 and colour at 256x256, with the superpixel and the bilinear demosaic. Each
  session is captured with ``--models diffuse`` and reconstructed without it (the same frames and
  the same network), both scored against the hidden truth (``polrig.solve.scoring``: matrix PSNR
  over the object); also the share of the object pixels the test accepts.
* **Speed** (warm, in process): one full-sensor capture (2448x2048, colour and mono, the default
  plastic sphere, the simulator's hidden errors, nominal calibration), then
  :meth:`polrig.app.processing.Processor.solve` of it with ``models`` ``full`` and ``diffuse`` in
  ``--rounds`` interleaved rounds (median), after one warm-up each (numba's compile,
  onnxruntime's session); one more solve each under ``tracemalloc`` for the peak of numpy's
  allocations (onnxruntime's arena not counted); and the two results' scores.

Prints the tables and writes ``benchmarks/results/diffuse_route.md``. About 6 min on 2 CPUs.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import pathlib
import statistics
import sys
import tempfile
import time
import tracemalloc

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "results" / "diffuse_route.md"
#: (sensor, size) of the accuracy rows
CASES = (("imx250mzr", "64x64"), ("imx250mzr", "128x128"), ("imx250mzr", "256x256"), ("imx250mzr", "512x512"),
         ("imx250myr", "256x256"))
DEMOSAICS = ("superpixel", "bilinear")


def config(path: pathlib.Path, sensor: str, size: str, scene: str, hidden: bool) -> pathlib.Path:
    """A simulated rig: ``hidden`` False sets the stage's zero offset, the polarizer's extinction and
    the analyzer ideal (as the CI test), True keeps the simulator's hidden errors."""
    ideal = "" if hidden else ("\n[sim.hidden]\nstage_zero_offset_deg = 0.0\nextinction_ratio = 1e12\n"
                               "ideal_analyzer = true\n")
    path.write_text(f'[sim]\nsize = "{size}"\nsensor = "{sensor}"\nclock_speed = inf\nseed = 11\n'
                    f'scene = "{scene}"\nnoise = true\n{ideal}')
    return path


def cli(*args: str) -> None:
    """``polrig`` with ``args``, its output swallowed; a failure raises."""
    from polrig.cli import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(list(args))
    if rc != 0:
        raise RuntimeError(f"polrig {' '.join(args)}: exit {rc}")


def capture(root: pathlib.Path, cfg: pathlib.Path, demosaic: str) -> dict:
    """Capture with ``--models diffuse``, reconstruct without: both scores and the test's record."""
    from polrig.app.session import Session
    from polrig.formats.exr import read_exr

    cli("capture", "--poses", "0", "--mode", "hybrid", "--states", "0,90", "--models", "diffuse", "--demosaic",
        demosaic, "--device", "cpu", "--config", str(cfg), "--out", str(root), "--no-progress")
    cli("reconstruct", str(root), "--device", "cpu", "--no-progress")
    cap = Session.open(root).capture(0)
    test = read_exr(root / cap["files"]["mueller"]["path"]).metadata["diffuse_test"]
    return {"diffuse": cap["score"], "plain": cap["revisions"]["rev1"]["score"], "test": test}


def accuracy(tmp: pathlib.Path) -> list[str]:
    rows = ["| sensor, size | demosaic | plain hybrid 2 (dB) | --models diffuse (dB) | difference | accepted / tested "
            "| within 2 sigma, plain / diffuse |", "|---|---|---:|---:|---:|---:|---:|"]
    for sensor, size in CASES:
        for demosaic in DEMOSAICS:
            name = f"{sensor}_{size}_{demosaic}"
            out = capture(tmp / name, config(tmp / f"{name}.toml", sensor, size, "diffuse_sphere", False), demosaic)
            d, p, t = out["diffuse"], out["plain"], out["test"]
            rows.append(f"| {sensor} {size} | {demosaic} | {p['psnr_db']:.2f} | {d['psnr_db']:.2f} | "
                        f"{d['psnr_db'] - p['psnr_db']:+.2f} | {t['pixels_accepted']} / {t['pixels_tested']} | "
                        f"{100 * p['within_2sigma']:.1f} / {100 * d['within_2sigma']:.1f} % |")
            print(rows[-1], flush=True)
    return rows


def speed(tmp: pathlib.Path, rounds: int) -> list[str]:
    from polrig.app.processing import load_calibration, make_processor, session_sensor_model
    from polrig.app.result_files import write_and_score
    from polrig.app.session import Session

    rows = ["| sensor | models | solve of a pose, median (s) | rounds (s) | peak of numpy's allocations | "
            "matrix PSNR (dB) | within 2 sigma | tested / accepted object pixels |",
            "|---|---|---:|---|---:|---:|---:|---:|"]
    for sensor in ("imx250myr", "imx250mzr"):
        root = tmp / f"full_{sensor}"
        cli("capture", "--poses", "0", "--mode", "hybrid", "--states", "0,90", "--device", "cpu", "--config",
            str(config(tmp / f"full_{sensor}.toml", sensor, "2448x2048", "sphere", True)), "--out", str(root),
            "--no-progress")
        session = Session.open(root)
        procs = {m: make_processor(session.plan, load_calibration(None), session_sensor_model(session),
                                   device="cpu", models=m) for m in ("full", "diffuse")}
        outs = {m: pr.solve(session, 0) for m, pr in procs.items()}  # warm-up
        times: dict[str, list[float]] = {m: [] for m in procs}
        for _ in range(rounds):
            for m, pr in procs.items():
                t = time.perf_counter()
                pr.solve(session, 0)
                times[m].append(time.perf_counter() - t)
        peaks = {}
        for m, pr in procs.items():  # apart from the timed rounds: tracing slows numpy's allocations
            tracemalloc.start()
            pr.solve(session, 0)
            peaks[m] = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        for m, out in outs.items():
            test = out.metadata.get("diffuse_test")
            (root / f"bench_{m}").mkdir()
            _, score = write_and_score(root, dataclasses.replace(out, relpath=f"bench_{m}/mueller.exr"),
                                       procs[m].exr)
            rows.append(f"| {sensor} | {m} | {statistics.median(times[m]):.2f} | "
                        f"{', '.join(f'{x:.2f}' for x in times[m])} | {peaks[m] / 2**20:.0f} MiB | "
                        f"{score['psnr_db']:.2f} | {100 * score['within_2sigma']:.1f} % | "
                        + ("" if test is None else f"{test['pixels_tested']} / {test['pixels_accepted']}") + " |")
            print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks diffuse_route", description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of the speed table (default 3)")
    ap.add_argument("--skip-full", action="store_true", help="leave out the full-sensor speed table")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        acc = accuracy(tmp)
        spd = [] if args.skip_full else speed(tmp, args.rounds)
    text = ["# Two-state captures: --models diffuse against the plain hybrid", "",
            f"`python -m benchmarks diffuse_route` (one run, {time.perf_counter() - t0:.0f} s on 2 shared CPUs). Hybrid 0/90; scores against the simulator's "
            "hidden truth; the plain hybrid is the same session reconstructed without the flag.", "",
            "**Accuracy on captures of the simulator's diffuse sphere** (one-shot; the stage's zero offset "
            "and the analyzer ideal, as the CI test):", "", *acc]
    if spd:
        text += ["", "**Speed at the full sensor** (2448x2048, the default plastic sphere, the simulator's "
                 "hidden errors, nominal calibration; `Processor.solve` of one pose, warm in process, "
                 f"{args.rounds} interleaved rounds):", "", *spd]
    RESULTS.write_text("\n".join(text) + "\n")
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
