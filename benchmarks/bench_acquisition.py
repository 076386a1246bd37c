"""Speed/accuracy trade of the N-state reference acquisition on the simulated rig.

Sweeps the number of polarizer states N (3, 4, 6, 8, 12, evenly spread over 180 deg), the
frames averaged per state K (1, 4, 16) and exposure bracketing (off, or a second exposure 4x
longer merged to HDR) and runs each as a real one-pose capture session (polrig.app.capture: stage
moves at the simulated stage's speed, exposures and readouts take their time on the simulated
clock; files written as in a real session). Reports

* acquisition time in **simulated seconds** (stage motion, exposure, readout; not wall time),
* Mueller error against the simulator's ground truth (``polrig.app.processing.score_against_truth``
  against the truth as a perfect rig at this resolution sees it): matrix PSNR, mean absolute
  error (DN per unit incident S0), realizability pass rate (coherency test),
* the error the noise model predicts (root-mean-square of the reported sigma) next to the
  measured RMSE: their ratio near 1 shows the error follows the noise model.

The rig is the simulated IMX250MYR colour camera with ideal hidden parameters, processed with
an exact calibration (zero tolerances: a perfectly calibrated rig, so the sweep measures
noise, not calibration, and sigma is the noise model's alone); one extra row runs the default
rig (stage zero offset 1.7 deg, extinction ratio 800, analyzer errors) with the nominal
calibration, whose reported sigma adds the nominal calibration's declared uncertainty
(``polrig.app.processing.NOMINAL_ANALYZER_TOLERANCE``, ``NOMINAL_GENERATOR_TOLERANCE``).

Usage: ``python benchmarks/bench_acquisition.py [--size 256] [--scene sphere]
[--default-row-only]`` (or ``python -m benchmarks acquisition``; ``--default-row-only`` runs
the default-rig row alone and replaces that row in the results file). Prints a markdown table
and writes
``benchmarks/results/reference.md`` and ``benchmarks/results/reference.png`` (matplotlib,
``bench`` extra).
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

from polrig.app import processing  # noqa: E402
from polrig.app.capture import CapturePlan, create_session, run_session  # noqa: E402
from polrig.app.rig import open_rig  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
IDEAL = {"stage_zero_offset_deg": 0.0, "extinction_ratio": 1e12, "ideal_analyzer": True}
EXPOSURE_US = 20000.0


def run_case(n_states: int, k: int, bracket: bool, *, size: int, scene: str, seed: int,
             ideal: bool = True) -> dict:
    states = tuple(round(180.0 * i / n_states, 6) for i in range(n_states))
    exposures = (EXPOSURE_US, 4 * EXPOSURE_US) if bracket else (EXPOSURE_US,)
    plan = CapturePlan((0.0,), states_deg=states, frames_per_state=k, exposures_us=exposures)
    # ideal rig: known exactly (noise-only sigma); default rig: the nominal model and priors
    cal = (processing.Calibration(processing.NOMINAL_CALIBRATION_ID) if ideal
           else processing.nominal_calibration())
    processing.check_plan(plan, cal)
    opts = {"size": (size, size), "clock_speed": math.inf, "seed": seed, "scene": scene,
            "exposure_us": EXPOSURE_US}
    if ideal:
        opts["hidden"] = IDEAL
    with tempfile.TemporaryDirectory() as d, open_rig(None, **opts) as rig:
        clock = rig.camera.world.clock
        session = create_session(pathlib.Path(d) / "s", rig, plan, calibration_id=cal.id)
        proc = processing.make_processor(plan, cal, processing.session_sensor_model(session))
        t0, w0 = clock.now(), time.perf_counter()
        result = run_session(rig, session, processor=proc)
        sim_s, wall_s = clock.now() - t0, time.perf_counter() - w0
    if result.status != "complete":
        raise RuntimeError(f"N={n_states} K={k}: capture {result.status}: {result.reason}")
    score = result.scores[0]
    return {"N": n_states, "K": k, "bracket": bracket, "ideal": ideal, "sim_s": sim_s,
            "wall_s": wall_s, "frames": n_states * k * len(exposures), **score}


def table(rows: list[dict]) -> str:
    head = ("| rig | N | K | bracket | frames | acquisition (sim s) | PSNR (dB) | MAE | RMSE | "
            "predicted (rms sigma) | RMSE / predicted | within 2 sigma | realizable |")
    lines = [head, "|" + "|".join("---" for _ in range(head.count("|") - 1)) + "|"]
    for r in rows:
        lines.append(
            f"| {'ideal' if r['ideal'] else 'default, nominal cal.'} | {r['N']} | {r['K']} | "
            f"{'2 exp' if r['bracket'] else 'off'} | {r['frames']} | {r['sim_s']:.1f} | "
            f"{r['psnr_db']:.1f} | {r['mae']:.2f} | {r['rmse']:.2f} | {r['mean_sigma']:.2f} | "
            f"{r['rmse'] / r['mean_sigma']:.2f} | {100 * r['within_2sigma']:.1f}% | "
            f"{100 * r['realizable']:.1f}% |")
    return "\n".join(lines)


def plot(rows: list[dict], path: pathlib.Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed (bench extra): no plot", file=sys.stderr)
        return False
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.5))
    colours = {1: "tab:blue", 4: "tab:orange", 16: "tab:green"}
    for r in rows:
        if not r["ideal"]:
            continue
        marker = "s" if r["bracket"] else "o"
        ax1.scatter(r["sim_s"], r["psnr_db"], c=colours[r["K"]], marker=marker)
        ax1.annotate(str(r["N"]), (r["sim_s"], r["psnr_db"]), fontsize=7,
                     textcoords="offset points", xytext=(3, 3))
        ax2.scatter(r["mean_sigma"], r["rmse"], c=colours[r["K"]], marker=marker)
    ax1.set_xscale("log")
    ax1.set_xlabel("acquisition time per pose (simulated s)")
    ax1.set_ylabel("Mueller matrix PSNR (dB)")
    ax1.set_title("speed vs accuracy (label: N states)")
    for k, c in colours.items():
        ax1.scatter([], [], c=c, label=f"K = {k}")
    ax1.scatter([], [], c="gray", marker="o", label="no bracket")
    ax1.scatter([], [], c="gray", marker="s", label="2-exposure HDR")
    ax1.legend(fontsize=8)
    lim = max(max(r["rmse"], r["mean_sigma"]) for r in rows if r["ideal"]) * 1.1
    ax2.plot([0, lim], [0, lim], "k--", lw=1, label="measured = predicted")
    ax2.set_xlabel("predicted error: rms reported sigma (DN per unit S0)")
    ax2.set_ylabel("measured RMSE vs truth (DN per unit S0)")
    ax2.set_title("error follows the noise model")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="sensor size in pixels (square)")
    ap.add_argument("--scene", default="sphere")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--states", default="3,4,6,8,12")
    ap.add_argument("--frames", default="1,4,16")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--default-row-only", action="store_true",
                    help="run only the default-rig row and replace it in the results file")
    args = ap.parse_args()
    rows = []
    t0 = time.perf_counter()
    if args.default_row_only:
        row = run_case(4, 1, False, size=args.size, scene=args.scene, seed=args.seed,
                       ideal=False)
        line = table([row]).splitlines()[-1]
        print(line)
        path = RESULTS / "reference.md"
        if args.no_write or not path.is_file():
            return
        lines = path.read_text().splitlines()
        idx = [i for i, s in enumerate(lines) if s.startswith("| default, nominal cal.")]
        if not idx:
            raise SystemExit(f"{path}: no default-rig row to replace; run the full sweep")
        lines[idx[0]] = line
        path.write_text("\n".join(lines) + "\n")
        return
    for n in (int(v) for v in args.states.split(",")):
        for k in (int(v) for v in args.frames.split(",")):
            for bracket in (False, True):
                rows.append(run_case(n, k, bracket, size=args.size, scene=args.scene,
                                     seed=args.seed))
                r = rows[-1]
                print(f"N={n:2d} K={k:2d} bracket={'on ' if bracket else 'off'} "
                      f"{r['sim_s']:7.1f} sim s  PSNR {r['psnr_db']:5.1f} dB  "
                      f"RMSE/predicted {r['rmse'] / r['mean_sigma']:.2f}  "
                      f"({r['wall_s']:.1f} s wall)", file=sys.stderr)
    rows.append(run_case(4, 1, False, size=args.size, scene=args.scene, seed=args.seed,
                         ideal=False))
    md = table(rows)
    print(md)
    if args.no_write:
        return
    header = (f"# Reference acquisition: speed vs accuracy\n\n"
              f"`python benchmarks/bench_acquisition.py --size {args.size} --scene {args.scene}` "
              f"({time.perf_counter() - t0:.0f} s wall). Simulated IMX250MYR colour rig, "
              f"{args.size}x{args.size} sensor, scene `{args.scene}`, one pose, superpixel "
              f"demosaic, exposure {EXPOSURE_US:g} us (bracket: + {4 * EXPOSURE_US:g} us, "
              f"merged at {EXPOSURE_US:g} us). Acquisition time is simulated seconds (stage "
              f"moves at 20 deg/s, exposure + 13 ms readout per frame). Errors in DN per unit "
              f"incident S0 against the truth as a perfect rig at this resolution sees it; "
              f"'predicted' is the rms reported sigma (ideal rig: exact calibration, the noise "
              f"model alone; default rig: noise plus the nominal calibration's declared "
              f"uncertainty). MAE/RMSE over all 9 "
              f"elements of valid object pixels and 3 colours.\n\n")
    RESULTS.mkdir(parents=True, exist_ok=True)
    plotted = plot(rows, RESULTS / "reference.png")
    (RESULTS / "reference.md").write_text(
        header + md + ("\n\n![speed vs accuracy](reference.png)\n" if plotted else "\n"))


if __name__ == "__main__":
    main()
