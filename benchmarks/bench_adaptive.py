"""The adaptive capture against the fixed four-state capture on a scene that mixes plastic and a
metal (issue 33 item 2): ``python -m benchmarks adaptive``.

Sessions of the simulated rig's ``plastic_metal`` scene (a sphere, half red plastic, half
aluminium; used for fitting nothing), ideal hidden rig and its exact calibration, sensor noise
on, through the in-process capture (:func:`polrig.app.capture.run_session`):

* ``adaptive`` at each target (``--targets``; ``max_states`` 4, share 0.95);
* ``hybrid4``: the fixed four states 0/45/90/135 with the same prior and solve (the comparison
  that isolates the choice of states);
* ``reference4``: the fixed four states, reference solve (no network).

Per mode: polarizer states per pose (mean), the share of object pixels at each target
(:func:`polrig.app.adaptive.evaluate` on the capture's frames: the same definition for every
mode that has the prior), matrix PSNR against the truth (the session score), and the
acquisition time: the plan's hardware time after the decisions (simulated stage and turntable
motion, exposure and readout: :func:`polrig.acquisition.plan.step_durations`), summed over the
poses, with the part spent at the poses (:func:`time_at_poses_s`), and the wall time of the session (acquisition, decisions, processing) on this machine.
Writes ``benchmarks/results/adaptive.md`` (and ``.json``).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import tempfile
import time

import numpy as np

from polrig.acquisition.engine import hardware_model
from polrig.acquisition.plan import (
    CapturePlan,
    Move,
    adaptive_pose_steps,
    capture_steps,
    setup_steps,
    step_durations,
)
from polrig.app import processing
from polrig.app.adaptive import evaluate
from polrig.app.capture import create_session, run_session
from polrig.app.rig import open_rig
from polrig.app.session import Session
from polrig.app.sessionio import load_capture_frames

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "adaptive.md"
IDEAL = {"stage_zero_offset_deg": 0.0, "extinction_ratio": 1e12, "ideal_analyzer": True}
EXACT = processing.Calibration("ideal")


def rig(size: int, seed: int):
    return open_rig(None, size=(size, size), sensor="imx250mzr", clock_speed=math.inf, seed=seed,
                    scene="plastic_metal", noise=True, hidden=dict(IDEAL))


def time_at_poses_s(session: Session, model) -> float:
    """The hardware time ``session`` spent at its poses: every step after a pose's first move
    (the turntable to the pose, the stage to the first state with it, overlapped) up to its
    end: the stage's moves between states and the frames, all poses (the steps the plan ran:
    the fixed plan's, or each adaptive pose's for the states it took)."""
    plan = session.plan
    exposures = (float(session.capture(0)["files"]["raw"][0]["exposure_us"]),)
    steps = setup_steps()
    for cap in session.captures:
        if plan.mode == "adaptive":
            taken = [plan.states_deg[0]] + [d["state_deg"] for d in cap["adaptive"][:-1]]
            steps += adaptive_pose_steps(plan, cap["index"], exposures, taken)
        else:
            steps += capture_steps(plan, cap["index"], exposures)
    durations = step_durations(steps, model)
    return float(sum(d for step, d in zip(steps[3:], durations[3:])  # after the setup
                     if not (isinstance(step, Move) and any(a == "turntable" for a, _ in step.targets))))


def capture(out: pathlib.Path, plan: CapturePlan, size: int, seed: int) -> dict:
    events = []
    t = time.perf_counter()
    with rig(size, seed) as r:
        model = hardware_model(r)
        session = create_session(out, r, plan, calibration_id=EXACT.id)
        proc = processing.make_processor(plan, EXACT, processing.session_sensor_model(session))
        result = run_session(r, session, processor=proc, progress=events.append)
    wall = time.perf_counter() - t
    if result.status != "complete":
        raise RuntimeError(f"{out}: {result.status} {result.reason}")
    s = Session.open(out)
    return {"session": s, "processor": proc, "hardware_s": events[-1].hardware_s, "wall_s": wall,
            "at_poses_s": time_at_poses_s(s, model),
            "states": [len({r["state_index"] for r in c["files"]["raw"]}) for c in s.captures],
            "psnr_db": [c["score"]["psnr_db"] for c in s.captures]}


def shares(run: dict, targets: list[float]) -> dict[float, float]:
    """The share of object pixels at each target of every pose's final posterior (the hybrid
    solve of all its states; mean over the poses)."""
    s, proc = run["session"], run["processor"]
    out = {}
    for target in targets:
        plan = CapturePlan(s.plan.poses_deg, mode="adaptive", states_deg=(0.0,), target_sigma=target,
                           max_states=8)
        vals = []
        for cap in s.captures:
            cf = load_capture_frames(s, cap["index"])
            vals.append(evaluate(cf, plan, proc, proc.network_geometry(s, cf))["share_met"])
        out[target] = float(np.mean(vals))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/bench_adaptive.py", description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128, help="sensor size, square (default 128)")
    ap.add_argument("--poses", default="0,90,180,270", help="turntable poses (default 0,90,180,270)")
    ap.add_argument("--targets", default="0.1,0.05,0.03", help="relative sigma targets (default 0.1,0.05,0.03)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args(argv)
    poses = tuple(float(p) for p in args.poses.split(","))
    targets = [float(t) for t in args.targets.split(",")]
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        plans = {f"adaptive {t:g}": CapturePlan(poses, mode="adaptive", states_deg=(0.0,), target_sigma=t,
                                                max_states=4) for t in targets}
        plans["hybrid4"] = CapturePlan(poses, mode="hybrid", states_deg=(0.0, 45.0, 90.0, 135.0))
        plans["reference4"] = CapturePlan(poses)
        # warm-up (the solver's compiled kernel, the network's session): not timed
        capture(tmp / "warm-up", CapturePlan(poses[:1], mode="adaptive", states_deg=(0.0,),
                                              target_sigma=targets[-1], max_states=2), args.size, args.seed)
        for name, plan in plans.items():
            run = capture(tmp / name.replace(" ", "_"), plan, args.size, args.seed)
            row = {k: run[k] for k in ("hardware_s", "at_poses_s", "wall_s", "states", "psnr_db")}
            if plan.mode != "reference":
                row["share"] = shares(run, targets)
            if plan.mode == "adaptive":
                row["decisions"] = [c["adaptive"] for c in run["session"].captures]
            rows[name] = row
            print(name, {k: v for k, v in row.items() if k != "decisions"}, flush=True)
    out = pathlib.Path(args.out)
    out.with_suffix(".json").write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1,
                                                   default=str) + "\n")
    lines = [
        "# Adaptive capture against the fixed four-state capture (issue 33 item 2)",
        "",
        (f"`python -m benchmarks adaptive` (`benchmarks/bench_adaptive.py --size {args.size} --poses "
        f"{args.poses} --targets {args.targets} --seed {args.seed}`): simulated rig, scene "
        f"`plastic_metal` (half red plastic, half aluminium; fitted to nothing), {args.size}x{args.size} "
        "mono sensor, ideal hidden rig with its exact calibration, sensor noise on, one frame per "
        "state. Acquisition time: the hardware time after the decisions (simulated stage and "
        "turntable motion, exposure, readout), all poses; of which at the poses: after each pose's "
        "first move (the turntable's, with the stage's to the first state), the stage's moves between "
        "states and the frames; wall: the whole session on this machine "
        "(acquisition, network, decisions, processing; 2 shared CPUs; after an untimed warm-up). Share at target: object "
        "pixels (the network's object mask less the pixels its frame clips or leaves dark in every colour) whose relative "
         "posterior sigma (RMS of the nine elements over m00) is at most the target, mean over poses."),
        "",
        "| capture | states per pose (mean; per pose) | "
        + " | ".join(f"share at {t:g}" for t in targets)
        + " | matrix PSNR dB (mean) | acquisition time s | of which at the poses s | wall s |",
        "|---|---|" + "---|" * len(targets) + "---|---|---|---|",
    ]
    for name, row in rows.items():
        share = row.get("share", {})
        lines.append(f"| {name} | {np.mean(row['states']):.2f} ({', '.join(map(str, row['states']))}) | "
                     + " | ".join(f"{100 * share[t]:.1f} %" if t in share else "-" for t in targets)
                     + f" | {np.mean(row['psnr_db']):.2f} | {row['hardware_s']:.2f} | {row['at_poses_s']:.2f}"
                     f" | {row['wall_s']:.1f} |")
    lines += ["", "Decisions (per pose: states taken, share at target after them, action):", ""]
    for name, row in rows.items():
        for i, decisions in enumerate(row.get("decisions", [])):
            text = "; ".join(f"{d['states_taken']}: {100 * d['share_met']:.1f} % -> "
                             + (f"take {d['state_deg']:g} deg" if d["action"] == "take" else d["action"])
                             for d in decisions)
            lines.append(f"- {name}, pose {i}: {text}")
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
