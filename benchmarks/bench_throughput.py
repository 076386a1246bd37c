"""Full-sensor throughput: per-pose processing time and peak memory, and a turntable session's
wall time against the rig's own hardware time (issue 20, item 9).

Two tables, both at the IMX250's full 2448 x 2048 sensor, 4 polarizer states, K = 1 frame per
state, nominal calibration:

1. **Per-pose processing** (``polrig reconstruct`` of one capture: raw frames read back and
   checksummed, radiometry, demosaic, reference solve with sigma, residual and mask, the
   Mueller EXR written, the score against the simulator's truth) for the colour IMX250MYR and
   the mono IMX250MZR with each demosaic (superpixel, bilinear, newton). Each case runs in a
   fresh child process (``--case``), so its peak resident memory (``VmHWM``) is its own;
   cases are interleaved over ``--rounds`` rounds and the medians reported, next to the time
   the same capture takes the hardware (motion, exposure, readout). One row more is the same
   processing without the truth score, so the score's own cost shows.
2. **A 12-pose turntable session** with the simulated rig's realistic motion (the clock at
   real time: the turntable at 10 deg/s, the stage at 20 deg/s, 20 ms exposure, 13 ms
   readout) whose camera replays frames rendered beforehand (:class:`polrig.sim.replay.ReplayCamera`:
   the simulator's rendering is not counted as hardware). Wall time is compared with the
   plan's hardware time (``hardware_time_s`` of the session manifest) for the engine
   (processing of pose k overlapped with the acquisition of pose k + 1, serpentine state
   order, turntable and stage moving together) and for the best alternative without overlap
   (acquire every pose, then ``polrig reconstruct`` the session). Targets (issue 20): wall /
   hardware <= 1.1 with the superpixel demosaic, <= 1.5 with bilinear.

Everything runs in process except where a child is named; these are warm figures of the
library calls (each per-pose child loads the compiled solver with a few-pixel solve before
its clock starts, as every pose after a session's first finds it), not one-shot CLI runs
(``polrig capture`` adds about a second of start-up).

Usage: ``python benchmarks/bench_throughput.py [--rounds 3] [--poses 12] [--skip-session]
[--skip-pose]`` (or ``python -m benchmarks throughput``). Writes
``benchmarks/results/throughput.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

RESULTS = REPO / "benchmarks" / "results"
SIZE = (2448, 2048)
STATES = (0.0, 45.0, 90.0, 135.0)
EXPOSURE_US = 20000.0
SENSORS = {"colour": "imx250myr", "mono": "imx250mzr"}
METHODS = ("superpixel", "bilinear", "newton")
#: The EXR choice of the timed rows (README "CLI": --exr-uncertainty half --exr-compression
#: none): half-float uncertainty planes, no compression. The default (half, ZIP) is timed in its
#: own rows: ZIP of full-resolution planes costs about half as much as the processing.
FAST_EXR = {"uncertainty": "half", "compression": "none"}
DEFAULT_EXR: dict = {}
EXR_CHOICES = {"fast": FAST_EXR, "default": DEFAULT_EXR}


def peak_rss_mb() -> float:
    """This process's peak resident set size (``VmHWM``), MiB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _size() -> tuple[int, int]:
    """``(W, H)``: the full sensor unless ``POLRIG_BENCH_SIZE=WxH`` (a quick trial run)."""
    spec = os.environ.get("POLRIG_BENCH_SIZE")
    return tuple(int(v) for v in spec.split("x")) if spec else SIZE


def _sim_options(sensor: str, clock_speed: float) -> dict:
    return {"size": _size(), "sensor": sensor, "clock_speed": clock_speed, "seed": 7,
            "scene": "sphere", "exposure_us": EXPOSURE_US}


def replay_rig(sensor: str, clock_speed: float):
    """The simulated rig at full sensor with a :class:`ReplayCamera` that has recorded one
    frame per polarizer state (rendered now, before any timing) and no truth provider (a
    real rig has none; the truth would be rendered at every pose)."""
    from polrig.app.rig import open_rig
    from polrig.sim.replay import ReplayCamera

    rig = open_rig(None, **_sim_options(sensor, clock_speed))
    cam = ReplayCamera(rig.camera.world, rig.faults, exposure_us=EXPOSURE_US)
    cam.open()
    cam.record(STATES)
    return dataclasses.replace(rig, camera=cam, truth=None)


# -- table 1: per-pose processing ----------------------------------------------------------------
def make_capture(folder: pathlib.Path, sensor: str, exr: dict) -> pathlib.Path:
    """A one-pose reference session at full sensor on the (rendering) simulated rig, with its
    truth recorded (compressed as the EXR choice ``exr`` says, as a capture with that choice
    writes it); processed once with the superpixel demosaic."""
    from polrig.app import capture
    from polrig.app.rig import open_rig

    req = capture.CaptureRequest(out=folder, poses_deg=(0.0,), mode="reference",
                                 states_deg=STATES, frames_per_state=1,
                                 exr_compression=exr.get("compression", "zip"))
    result = capture.run_capture(req, command_line=["bench_throughput"],
                                 rig=lambda: open_rig(None, **_sim_options(sensor, math.inf)))
    if result.status != "complete":
        raise RuntimeError(f"setup capture {result.status}: {result.reason}")
    return folder


def warm_up() -> None:
    """Import the solver and load its compiled kernel from the cache with a solve of a few
    pixels, as any pose after a session's first finds them (a per-process cost of about
    0.3-0.5 s, not a per-pose one)."""
    import numpy as np

    from polrig.optics.mueller import polarizer_stokes
    from polrig.solve.reference import solve_reference

    s = polarizer_stokes(np.deg2rad(STATES), intensity=1)
    meas = np.ones((len(STATES), 1, 4, 2, 2))
    solve_reference(s, meas, meas, np.ones(meas.shape, bool))


def run_case(session_dir: pathlib.Path, method: str, score: bool, exr: dict) -> dict:
    """One reconstruct of the session's capture (in this process); wall seconds and bytes of
    the Mueller EXR."""
    from polrig.app import reconstruct
    from polrig.app.session import Session

    warm_up()
    session = Session.open(session_dir, lock=True)
    try:
        if not score:  # a copy of the session without its truth file record: nothing to score
            session.captures[0]["files"].pop("truth_mueller", None)
        t0 = time.perf_counter()
        revision = reconstruct.reprocess_session(session, demosaic=method, exr=exr)
        wall = time.perf_counter() - t0
        files = session.captures[0]["revisions"][revision]["files"]
        size = (session.root / files["mueller"]["path"]).stat().st_size
    finally:
        session.unlock()
    return {"wall_s": wall, "exr_bytes": size, "peak_mb": peak_rss_mb()}


def pose_hardware_s(n_poses: int = 12) -> float:
    """Hardware time per pose of the session table's plan on the simulated rig (``n_poses``
    poses over a turn, serpentine states, turntable and stage moving together, exposure and
    readout): the plan's whole hardware time divided by its poses."""
    from polrig.acquisition.engine import hardware_model
    from polrig.acquisition.plan import CapturePlan, session_steps, step_durations
    from polrig.app.rig import open_rig

    with open_rig(None, **_sim_options("imx250myr", math.inf)) as rig:  # nothing is rendered
        plan = CapturePlan(tuple(360.0 * i / n_poses for i in range(n_poses)), states_deg=STATES)
        steps = session_steps(plan, range(n_poses), (EXPOSURE_US,))
        return float(sum(step_durations(steps, hardware_model(rig)))) / n_poses


def pose_table(rounds: int) -> str:
    fast, default = "fast", "default"
    cases = ([(lay, m, True, fast) for lay in SENSORS for m in METHODS]
             + [("colour", m, False, fast) for m in ("superpixel", "bilinear")]
             + [("colour", m, True, default) for m in ("superpixel", "bilinear")])
    runs: dict[tuple, list[dict]] = {c: [] for c in cases}
    with tempfile.TemporaryDirectory(prefix="polrig-bench-") as tmp:
        sessions = {}
        for lay, choice in [(lay, fast) for lay in SENSORS] + [("colour", default)]:
            t0 = time.perf_counter()
            sessions[lay, choice] = make_capture(pathlib.Path(tmp) / f"{lay}-{choice}",
                                                 SENSORS[lay], EXR_CHOICES[choice])
            print(f"  setup {lay} {choice}: {time.perf_counter() - t0:.1f} s", flush=True)
        # the unscored rows reprocess a copy whose manifest loses its truth record
        noscore = shutil.copytree(sessions["colour", fast], pathlib.Path(tmp) / "colour-noscore")
        for r in range(rounds):
            for lay, method, score, choice in cases:
                out = subprocess.run(
                    [sys.executable, __file__, "--case",
                     str(sessions[lay, choice] if score else noscore), method,
                     "score" if score else "noscore", choice],
                    cwd=REPO, capture_output=True, text=True, check=True)
                res = json.loads(out.stdout.strip().splitlines()[-1])
                runs[(lay, method, score, choice)].append(res)
                print(f"  round {r + 1}: {lay:6s} {method:10s} {'score' if score else 'no score'}"
                      f" {choice:7s} {res['wall_s']:6.2f} s {res['peak_mb']:7.0f} MiB", flush=True)
    hw = pose_hardware_s()
    lines = [f"Hardware time per pose (the session table's 12-pose plan: 30 deg turns, 4 serpentine "
             f"states, 20 ms exposure, 13 ms readout): {hw:.2f} s.", "",
             "EXR choice 'fast': half-float uncertainty planes, no compression "
             "(`--exr-uncertainty half --exr-compression none`); 'default': the plan's default "
             "(half-float uncertainty planes, ZIP).", "",
             "| sensor | demosaic | score | EXR | processing per pose (s) | / hardware | peak memory "
             "(MiB) | Mueller EXR (MB) |", "|---|---|---|---|---|---|---|---|"]
    for (lay, method, score, choice), rs in runs.items():
        wall = statistics.median(x["wall_s"] for x in rs)
        peak = statistics.median(x["peak_mb"] for x in rs)
        mb = rs[-1]["exr_bytes"] / 1e6
        lines.append(f"| {lay} | {method} | {'yes' if score else 'no'} | {choice} | {wall:.2f} | "
                     f"{wall / hw:.2f} | {peak:.0f} | {mb:.0f} |")
    return "\n".join(lines)


# -- table 2: a turntable session ----------------------------------------------------------------
def run_session_case(method: str, overlapped: bool, n_poses: int, clock_speed: float,
                     exr: dict) -> dict:
    from polrig.app import capture, processing, reconstruct

    with tempfile.TemporaryDirectory(prefix="polrig-bench-") as tmp:
        out = pathlib.Path(tmp) / "s"
        poses = tuple(360.0 * i / n_poses for i in range(n_poses))
        req = capture.CaptureRequest(out=out, poses_deg=poses, mode="reference",
                                     states_deg=STATES, frames_per_state=1, demosaic=method,
                                     exr_uncertainty=exr.get("uncertainty"),
                                     exr_compression=exr.get("compression"))
        prepared = capture.prepare_capture(req)
        rig = replay_rig("imx250myr", clock_speed)
        try:
            session = capture.open_session(prepared, rig, ["bench_throughput"])
            proc = processing.make_processor(prepared.plan, prepared.calibration,
                                             processing.session_sensor_model(session))
            clock = rig.camera.world.clock
            t0, c0 = time.perf_counter(), clock.now()
            result = capture.run_session(rig, session, processor=proc if overlapped else None)
            if not overlapped:
                reconstruct.reprocess_session(session, demosaic=method, exr=exr)
            wall = time.perf_counter() - t0
            sim_s = clock.now() - c0
        finally:
            rig.close()
        if result.status != "complete":
            raise RuntimeError(f"session {result.status}: {result.reason}")
        hardware = float(session.manifest["hardware_time_s"] or float("nan"))
    return {"wall_s": wall, "hardware_s": hardware, "clock_s": sim_s / clock_speed,
            "peak_mb": peak_rss_mb()}


def session_table(n_poses: int, clock_speed: float,
                  methods: tuple[str, ...] = ("superpixel", "bilinear"),
                  exr_choice: str = "fast") -> str:
    w, h = _size()
    lines = [f"{n_poses} poses over 360 deg, colour IMX250MYR {w}x{h}, 4 states, K = 1, "
             f"simulated motion at {clock_speed:g}x real time (hardware time in wall seconds), "
             f"frames replayed; EXR choice '{exr_choice}' (see above).", "",
             "| demosaic | processing | wall (s) | hardware (s) | wall / hardware | target |",
             "|---|---|---|---|---|---|"]
    targets = {"superpixel": 1.1, "bilinear": 1.5}
    for method in methods:
        for overlapped in (True, False):
            out = subprocess.run(
                [sys.executable, __file__, "--session-case", method,
                 "overlap" if overlapped else "after", str(n_poses), str(clock_speed),
                 exr_choice],
                cwd=REPO, capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            hardware_wall_s = res["hardware_s"] / clock_speed  # the clock runs faster
            ratio = res["wall_s"] / hardware_wall_s
            label = ("overlapped (engine)" if overlapped
                     else "after acquisition (reconstruct)")
            print(f"  {method:10s} {label:32s} wall {res['wall_s']:.1f} s hardware "
                  f"{hardware_wall_s:.1f} s ratio {ratio:.2f}", flush=True)
            lines.append(f"| {method} | {label} | {res['wall_s']:.1f} | {hardware_wall_s:.1f} "
                         f"| {ratio:.2f} | {'<= %.1f' % targets[method] if overlapped else ''} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--clock-speed", type=float, default=1.0)
    ap.add_argument("--skip-session", action="store_true")
    ap.add_argument("--skip-pose", action="store_true")
    ap.add_argument("--methods", default="superpixel,bilinear",
                    help="demosaic methods of the session table (comma-separated)")
    ap.add_argument("--out", default="throughput.md", help="results file name in benchmarks/results")
    ap.add_argument("--size", help="WxH instead of the full 2448x2048 sensor (a quick trial)")
    ap.add_argument("--exr", choices=("fast", "default"), default="fast",
                    help="EXR choice of the session table (default: fast)")
    ap.add_argument("--case", nargs=4, metavar=("SESSION", "METHOD", "SCORE", "EXR"),
                    help=argparse.SUPPRESS)
    ap.add_argument("--session-case", nargs=5, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.size:
        os.environ["POLRIG_BENCH_SIZE"] = args.size  # the child processes inherit it
    if args.case:
        session, method, score, choice = args.case
        exr = FAST_EXR if choice == "fast" else DEFAULT_EXR
        print(json.dumps(run_case(pathlib.Path(session), method, score == "score", exr)))
        return 0
    if args.session_case:
        method, mode, n, speed, choice = args.session_case
        exr = FAST_EXR if choice == "fast" else DEFAULT_EXR
        print(json.dumps(run_session_case(method, mode == "overlap", int(n), float(speed), exr)))
        return 0
    w, h = _size()
    head = (f"Sensor {w}x{h}. Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}; medians over {args.rounds} interleaved rounds "
            f"(per-pose table); one run each (session table).")
    parts = ["# Full-sensor throughput", "", head, ""]
    if not args.skip_pose:
        print("per-pose processing:", flush=True)
        parts += ["## Per-pose processing", "", pose_table(args.rounds), ""]
    if not args.skip_session:
        print("turntable session:", flush=True)
        parts += ["## Turntable session", "", session_table(args.poses, args.clock_speed,
                                                          tuple(args.methods.split(",")),
                                                          args.exr), ""]
    text = "\n".join(parts)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
