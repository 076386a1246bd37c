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

**Decision time** (``--decision-sizes``, ``--rounds``; issue 33 item 2 follow-up): what one
decision costs while the stage waits, at each size (``512``: 512x512; ``full``: the sensor's
2448x2048; colour sensor, IMX250MYR), broken down into its parts (:func:`polrig.app.adaptive.decide`'s
``timings``: frames read back and verified, state radiances, the network, the hybrid solve,
the criterion), with and without the :class:`polrig.app.adaptive.PoseMemo` a run keeps (frames,
radiances and the network's answer reused within the pose). One adaptive pose is captured at
target 1e-6 (so every pose takes ``max_states`` 4 states, and three decisions design a next
state), then its four decisions are taken again from its files, as the run took them (after
1, 2, 3, 4 states), both ways in turn each round; the records must equal the run's (else the
benchmark fails). Medians over the rounds; peak memory: the largest traced (``tracemalloc``:
numpy and Python; not the ONNX runtime's arena) during a pose's decisions, memo included.

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
import tracemalloc

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
from polrig.app.adaptive import PoseMemo, decide, evaluate
from polrig.app.capture import create_session, run_session
from polrig.app.rig import open_rig
from polrig.app.session import Session
from polrig.app.sessionio import load_capture_frames

RESULTS = pathlib.Path(__file__).resolve().parent / "results" / "adaptive.md"
#: The decision time of the code before the pose memo (commit 9c422a5), measured apart (its
#: ``how``); shown beside the decision-time table when present.
BEFORE = RESULTS.with_name("adaptive_before.json")
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


#: Sizes of the decision-time table: name -> (width, height).
DECISION_SIZES = {"64": (64, 64), "512": (512, 512), "full": (2448, 2048)}  # 64: the test's
#: The parts of a decision (:func:`polrig.app.adaptive.decide`'s ``timings``).
PARTS = ("read", "radiance", "network", "solve", "criterion")


def pose_decisions(session: Session, proc, records: list[dict], memo: PoseMemo | None
                   ) -> tuple[list[dict], dict[str, float]]:
    """Capture 0's decisions retaken from its files as the run took them (after 1, 2, ...
    states: the manifest shows the states recorded by then), with ``memo`` (or none); returns
    the records and the seconds per part, summed over the decisions."""
    cap = session.capture(0)
    timings: dict[str, float] = {}
    out = []
    n_states = 1 + max(r["state_index"] for r in records)
    try:
        for n in range(1, n_states + 1):
            cap["files"]["raw"] = [r for r in records if r["state_index"] < n]
            cap["adaptive"] = []
            t = time.perf_counter()
            out.append(decide(session, 0, proc, memo, timings))
            timings["total"] = timings.get("total", 0.0) + time.perf_counter() - t
    finally:
        cap["files"]["raw"] = records
    return out, timings


def decision_profile(name: str, tmp: pathlib.Path, rounds: int, seed: int) -> dict:
    """The decision-time rows of size ``name`` (module docstring)."""
    width, height = DECISION_SIZES[name]
    plan = CapturePlan((0.0,), mode="adaptive", states_deg=(0.0,), target_sigma=1e-6, max_states=4)
    t = time.perf_counter()
    with open_rig(None, size=(width, height), sensor="imx250myr", clock_speed=math.inf, seed=seed,
                  scene="plastic_metal", noise=True, hidden=dict(IDEAL)) as r:
        session = create_session(tmp, r, plan, calibration_id=EXACT.id)
        proc = processing.make_processor(plan, EXACT, processing.session_sensor_model(session))
        result = run_session(r, session, processor=proc)
    if result.status != "complete":
        raise RuntimeError(f"{tmp}: {result.status} {result.reason}")
    print(f"decisions {name}: captured in {time.perf_counter() - t:.1f} s", flush=True)
    session = Session.open(tmp)
    recorded = session.capture(0)["adaptive"]
    records = list(session.capture(0)["files"]["raw"])
    runs: dict[str, list[dict[str, float]]] = {"uncached": [], "cached": []}
    for i in range(rounds):
        order = ("uncached", "cached") if i % 2 == 0 else ("cached", "uncached")
        for path in order:
            decisions, timings = pose_decisions(session, proc, records,
                                                PoseMemo() if path == "cached" else None)
            if decisions != recorded:
                raise RuntimeError(f"{name}, {path}: decisions {decisions} differ from the run's {recorded}")
            runs[path].append(timings)
            print(f"decisions {name} {path} round {i}: "
                  + ", ".join(f"{k} {v:.3f}" for k, v in timings.items()), flush=True)
    peaks = {}
    for path in runs:  # untimed: tracing slows Python code down
        tracemalloc.start()
        pose_decisions(session, proc, records, PoseMemo() if path == "cached" else None)
        peaks[path] = tracemalloc.get_traced_memory()[1] / 2 ** 20
        tracemalloc.stop()
    return {path: {"decisions": len(recorded), "peak_mib": peaks[path],
                   **{k: float(np.median([t.get(k, 0.0) for t in rs])) for k in (*PARTS, "total")},
                   "rounds": rs}
            for path, rs in runs.items()} | {"width": width, "height": height, "n_rounds": rounds,
                                             "states": [d["state_deg"] for d in recorded[:-1]]}


def decision_lines(profile: dict[str, dict]) -> list[str]:
    """The decision-time table of :func:`decision_profile`'s rows."""
    lines = [
        "## Decision time",
        "",
        ("One adaptive pose of `plastic_metal` on the colour sensor (IMX250MYR), target 1e-6 so it "
         "takes 4 states; its 4 decisions (after 1..4 states; 3 design the next state, the 4th "
         "stops at max states) taken again from its files as the run took them, without and with "
         "the pose memo, alternating rounds (how many: beside the size), medians; warm in process (after the capture "
         "that recorded them); 2 shared CPUs. Seconds per pose (all 4 decisions) by part; per "
         "decision: the pose's total / 4. Peak: tracemalloc's (numpy and Python, not the ONNX "
         "runtime's arena) during the pose's decisions. Both ways give the run's records exactly. "
         f"Before: {BEFORE.name} (how it was measured is in it; both ways of this code replay "
         "its recorded decisions exactly)."),
        "",
        "| size | path | read s | radiance s | network s | solve s | criterion s | pose total s | per decision s | peak MiB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    before = json.loads(BEFORE.read_text()) if BEFORE.is_file() else {"rows": {}}
    for name, prof in profile.items():
        if name in before["rows"]:
            old = before["rows"][name]
            lines.append(f"| {old['width']}x{old['height']} ({len(old['totals_s'])} rounds) | before "
                         f"({before['commit']}, {old.get('label', 'run apart')}) | - | - | - | - | - | {old['median_s']:.2f} | "
                         f"{old['median_s'] / old['decisions']:.2f} | {old['peak_mib']:.0f} |")
            if "this_code_with_memo_median_s" in old:  # the same alternation's rounds of this code
                lines.append(f"| {old['width']}x{old['height']} ({len(old['this_code_with_memo_totals_s'])} rounds) | "
                             f"cached ({old['label']}) | - | - | - | - | - | "
                             f"{old['this_code_with_memo_median_s']:.2f} | "
                             f"{old['this_code_with_memo_median_s'] / old['decisions']:.2f} | - |")
        for path in ("uncached", "cached"):
            row = prof[path]
            lines.append(f"| {prof['width']}x{prof['height']} ({prof['n_rounds']} rounds) | {path} | "
                         + " | ".join(f"{row[k]:.3f}" for k in PARTS)
                         + f" | {row['total']:.2f} | {row['total'] / row['decisions']:.2f} | {row['peak_mib']:.0f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/bench_adaptive.py", description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128, help="sensor size, square (default 128)")
    ap.add_argument("--poses", default="0,90,180,270", help="turntable poses (default 0,90,180,270)")
    ap.add_argument("--targets", default="0.1,0.05,0.03", help="relative sigma targets (default 0.1,0.05,0.03)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--decision-sizes", default="512,full",
                    help=f"sizes of the decision-time table ({', '.join(DECISION_SIZES)}; '' for none)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the decision-time table (default 3)")
    ap.add_argument("--decisions-only", action="store_true",
                    help="the decision-time table only (not the session table)")
    args = ap.parse_args(argv)
    decision_sizes = [n for n in args.decision_sizes.split(",") if n]
    for n in decision_sizes:
        if n not in DECISION_SIZES:
            ap.error(f"--decision-sizes: unknown size {n!r}; use {', '.join(DECISION_SIZES)}")
    poses = tuple(float(p) for p in args.poses.split(","))
    targets = [float(t) for t in args.targets.split(",")]
    rows: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        if not args.decisions_only:
            rows = session_rows(tmp, poses, targets, args.size, args.seed)
        profile = {n: decision_profile(n, tmp / f"decisions_{n}", args.rounds, args.seed)
                   for n in decision_sizes}
    out = pathlib.Path(args.out)
    before = json.loads(out.with_suffix(".json").read_text()) if out.with_suffix(".json").is_file() else {}
    if args.decisions_only:  # the session table as it was
        rows, run_args = before.get("rows", {}), before.get("args", vars(args))
        text = out.read_text().split("\n## Decision time")[0] if out.is_file() else ""
        lines = text.rstrip("\n").split("\n") if text else []
    else:
        run_args = vars(args)
        lines = session_lines(args, targets, rows)
    profile = {**before.get("decision_time", {}), **profile}  # sizes not run this time: as they were
    out.with_suffix(".json").write_text(json.dumps({"args": run_args, "rows": rows,
                                                    "decision_time": profile}, indent=1,
                                                   default=str) + "\n")
    if profile:
        lines += [""] + decision_lines(profile)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


def session_rows(tmp: pathlib.Path, poses: tuple[float, ...], targets: list[float], size: int,
                 seed: int) -> dict[str, dict]:
    """The session table's rows (module docstring)."""
    rows = {}
    plans = {f"adaptive {t:g}": CapturePlan(poses, mode="adaptive", states_deg=(0.0,), target_sigma=t,
                                            max_states=4) for t in targets}
    plans["hybrid4"] = CapturePlan(poses, mode="hybrid", states_deg=(0.0, 45.0, 90.0, 135.0))
    plans["reference4"] = CapturePlan(poses)
    # warm-up (the solver's compiled kernel, the network's session): not timed
    capture(tmp / "warm-up", CapturePlan(poses[:1], mode="adaptive", states_deg=(0.0,),
                                          target_sigma=targets[-1], max_states=2), size, seed)
    for name, plan in plans.items():
        run = capture(tmp / name.replace(" ", "_"), plan, size, seed)
        row = {k: run[k] for k in ("hardware_s", "at_poses_s", "wall_s", "states", "psnr_db")}
        if plan.mode != "reference":
            row["share"] = shares(run, targets)
        if plan.mode == "adaptive":
            row["decisions"] = [c["adaptive"] for c in run["session"].captures]
        rows[name] = row
        print(name, {k: v for k, v in row.items() if k != "decisions"}, flush=True)
    return rows


def session_lines(args, targets: list[float], rows: dict[str, dict]) -> list[str]:
    """The session table (module docstring) as markdown lines."""
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
    return lines


if __name__ == "__main__":
    sys.exit(main())
