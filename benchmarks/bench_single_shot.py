"""Latency, throughput and memory of the whole single-shot path on this machine, warm and cold.

Path per frame: decode the raw file (16-bit PNG, :func:`polrig.formats.rawio.read_raw`), demosaic,
Stokes, PIPNet -> pBRDF -> PMMNet (one onnxruntime call per pass; the one single-shot route,
:meth:`polrig.app.single_shot.SingleShot.frame`), Mueller EXR (:func:`polrig.formats.exr.write_result_exr`). Raw
frames are IMX250MYR (colour) mosaics of a lit sphere (content matters little for speed); the
full sensor is also timed as a mono IMX250MZR frame (superpixel analyzer images 1224x1024, four
times the colour sensor's).

Cases (issue 22's targets): 512x512 raw -> 512x512 Mueller (``--resolution full``: networks on
the superpixel grid plus the measured detail, :mod:`polrig.models.full_resolution`; and the networks on
the bilinear demosaic, the older route), 512x512 superpixel, full sensor colour superpixel, full
sensor colour full resolution, full sensor mono superpixel; and the faster mode's full-sensor colour
cases (``--network-binning 2``: the networks on the analyzer grid binned 2x2, lifted back with the
grid's measured detail, :func:`polrig.models.full_resolution.reconstruct_binned`). The "lifts" column
is the full-resolution lift plus the binning's lift; "networks" includes the reduced passes of
the light-direction probe (:func:`polrig.models.runtime.probe_shape`).

Columns: **warm**: in process, the model loaded once, median of the runs after one warm-up:
**raw -> Mueller** (the raw frame in memory, as a camera delivers it, to the Mueller image in
memory: the per-frame work issue 22's targets are for) and file to file (plus decoding the raw
file and writing the EXR), with the geometry ``polrig infer`` uses without a
calibration (the default rig's, whose stage zero axis is not the training rig's: two network
passes, as on a real rig); **cold**: the one-shot CLI (``python -m polrig
infer ...`` in a fresh process, what a user types), wall-clock median, with the child's peak
resident memory (``wait4`` rusage). Rounds interleave the cases (warm and cold alternate) so a
busy machine's load spreads over all of them; the table says how many rounds. ``--anatomy``
also times, in fresh processes, where a cold run's time goes: imports, session creation, the
first and a second network pass at the full-sensor mono size; and the one-shot CLI's own steps
for the full colour sensor at full resolution (its functions wrapped where they run: decode,
session, reconstruction, EXR, the previews' S0 SNR and PNGs, the rest). The device each ran on (the
onnxruntime provider, the GPU's name) and the frame route (``host`` on the CPU; ``device`` on CUDA,
the frame kept on the GPU: :data:`polrig.app.single_shot.FRAME_ROUTES`) are printed with the
table; on the device route a second table splits the warm frame into its steps (upload, pre,
statistics, networks, post, copy-back; ``benchmarks/bench_device_route.py`` compares the two
routes on one provider).

Usage: ``python benchmarks/bench_single_shot.py [--rounds N] [--threads T] [--out FILE] [--anatomy]``
(or ``python -m benchmarks single_shot``; default ``--out benchmarks/results/single_shot_speed.md``).

**Model sizes** (issue 32, :mod:`polrig.models.sizes`): every run also writes
``benchmarks/results/single_shot_sizes.md`` (``--sizes-only``: that table alone), one row per
size: its width, training hardware and minutes (``model.json``), its accuracy on the model
card's two held-out sets (the committed evaluation tables, :data:`ACCURACY_FILES`), its warm
raw -> Mueller time here for :data:`SIZE_CASES` (interleaved rounds, medians) and on a GPU (the
committed CUDA measurements, :data:`GPU_RESULTS`). A size not shipped yet reads "waiting for a
GPU lease".

``--rig-scenes sphere,box,...`` instead scores ``polrig capture --mode single-shot`` on the
default simulated rig (256x256 raw, virtual clock, nominal calibration: the simulator's design
geometry), one capture per scene, with processing's own score (``polrig.app.processing``), three
ways: the design stage zero axis (what processing does now), the training rig's axis (camera up,
what processing did before it passed any geometry) and the design axis turned by 90 deg about
the illumination axis (both through ``[nominal_geometry]``); ``--out`` writes that table.
With ``--mirror-average`` the rig scenes are captured with the design geometry with and
without ``--mirror-average`` instead. ``--rig-poses 0:360:45`` captures each scene over those
turntable poses instead of pose 0 only
(one view of a scene says little: the same model differs by several dB from pose to pose);
every column is then the mean matrix PSNR over the poses with a lit truth (an object turned
with its unlit back to the camera has no PSNR, :func:`polrig.app.processing.score_against_truth`),
and a second table gives the design-geometry PSNR per pose.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

from polrig.formats.rawio import read_raw, write_raw  # noqa: E402
from polrig.acquisition.plan import SingleShotOptions  # noqa: E402
from polrig.app.single_shot import SingleShot  # noqa: E402
from polrig.formats.exr import write_result_exr  # noqa: E402
from polrig.models.runtime import (  # noqa: E402
    SingleShotModel,
    physical_cores,
)
from polrig.sensor.frame import Frame, FrameMeta
from polrig.sensor.layouts import get_layout  # noqa: E402

COLOUR, MONO = "imx250myr", "imx250mzr"
FULL = (2048, 2448)
#: (label, raw shape (H, W), layout, infer options): issue 22's cases.
CASES = (
    ("512x512 -> 512x512 (full resolution)", (512, 512), COLOUR, ["--resolution", "full"]),
    ("512x512 -> 512x512 (networks on bilinear)", (512, 512), COLOUR, ["--demosaic", "bilinear"]),
    ("512x512 superpixel (128x128)", (512, 512), COLOUR, []),
    ("full sensor colour superpixel (612x512)", FULL, COLOUR, []),
    ("full sensor colour full resolution (2448x2048)", FULL, COLOUR, ["--resolution", "full"]),
    ("full sensor mono superpixel (1224x1024)", FULL, MONO, []),
    ("full sensor colour superpixel, network binning 2", FULL, COLOUR, ["--network-binning", "2"]),
    ("full sensor colour full resolution, network binning 2", FULL, COLOUR,
     ["--resolution", "full", "--network-binning", "2"]),
)
#: The cases the model sizes table times (a live-view frame and the full colour sensor).
SIZE_CASES = (CASES[2], CASES[3])
#: Each size's committed accuracy tables (``polrig evaluate`` JSON in benchmarks/results) on the
#: model card's held-out sets; the large size's are written when a lease ships it.
ACCURACY_FILES = {"small": {"unseen shapes": "single_shot.json", "new scenes": "single_shot_seen_families.json"},
                  "large": {"unseen shapes": "single_shot_large_unseen_shapes.json",  # polrig.models.lease.ship
                            "new scenes": "single_shot_large_new_scenes.json"}}
#: Each size's committed CUDA measurements (this benchmark's JSON from a lease, ``--device cuda``).
GPU_RESULTS = {"small": "single_shot_cuda_h200.json", "large": "single_shot_large_cuda.json"}
WAITING = "not shipped"
#: Issue 22's CPU targets (ms, per frame: the warm raw -> Mueller column) and the full-sensor peak (MB).
TARGETS_MS = {CASES[0][0]: 150, CASES[3][0]: 300, CASES[4][0]: 3000, CASES[6][0]: 300, CASES[7][0]: 3000}
PEAK_TARGET_MB = 2048


def synthetic_raw(shape: tuple[int, int], rng: np.random.Generator, layout: str = COLOUR) -> np.ndarray:
    """A 12-bit mosaic (``layout``) of a diffuse sphere with a polarized highlight (DN)."""
    h, w = shape
    lay = get_layout(layout)
    angle = np.deg2rad(lay.angle_map(shape))
    v, u = np.mgrid[0:h, 0:w]
    r2 = ((u - w / 2) ** 2 + (v - h / 2) ** 2) / (0.4 * min(h, w)) ** 2
    inside = r2 < 1
    s0 = np.where(inside, 1500 * np.sqrt(np.clip(1 - r2, 0, 1)) + 200, 40.0)
    dolp = np.where(inside, 0.3 * r2, 0.0)
    aolp = np.arctan2(v - h / 2, u - w / 2)
    signal = 0.5 * s0 * (1 + dolp * np.cos(2 * (angle - aolp)))
    noisy = rng.poisson(np.clip(signal, 0, None)) + rng.normal(0, 2.0, shape) + 64
    return np.clip(noisy, 0, 4095).astype(np.uint16)


def write_case_raw(shape, layout: str, path: pathlib.Path, rng) -> pathlib.Path:
    raw = synthetic_raw(shape, rng, layout)
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=10000.0, gain_db=0.0, pixel_format="Mono16",
                     layout=layout, bit_depth=12, black_level_dn=64.0)
    write_raw(path, Frame(raw=raw, meta=meta))
    return path


def _options(argv: list[str]) -> SingleShotOptions:
    """The :class:`SingleShotOptions` of ``polrig infer`` options (the ones CASES use; no sigma,
    as ``infer`` without ``--sigma``: ``sigma=None`` would compute it, a session's default)."""
    opts = dict(zip(argv[::2], argv[1::2]))
    return SingleShotOptions(opts.get("--resolution", "superpixel"), opts.get("--demosaic"),
                             int(opts.get("--network-binning", 1)), sigma=False)


def warm_once(src: pathlib.Path, argv: list[str], route: SingleShot, out: pathlib.Path) -> dict:
    """One in-process frame, decode to EXR, as ``polrig infer`` does it (seconds per step)."""
    c0, t0 = _cpu_s(), time.perf_counter()
    frame = read_raw(src)
    t1 = time.perf_counter()
    result = route.frame(frame, 0.0, _options(argv), geometry=_rig_geometry(), saturation_dn=4095.0)
    t2 = time.perf_counter()
    write_result_exr(out, result, planes=("mueller", "mask"), compression="none")
    t3 = time.perf_counter()
    lift = result.timings_s.get("full_resolution", 0.0) + result.timings_s.get("binning_lift", 0.0)
    mueller = result.mueller
    network = result.timings_s["network"]
    return {**result.timings_s, "network": network, "lift": lift, "decode": t1 - t0, "compute": t2 - t1,
            "exr": t3 - t2,
            "total": t3 - t0, "cpu": _cpu_s() - c0, "net": f"{mueller.shape[-1]}x{mueller.shape[-2]}"}


def _rig_geometry() -> dict:
    """The geometry ``polrig infer`` uses without a calibration (the default rig's nominal
    stage zero axis and intrinsics, :func:`polrig.app.calibrations.single_shot_geometry`), so warm and
    cold runs do the same work: that axis differs from the training rig's, so the runtime makes
    its two passes (the incident-frame refinement, :meth:`SingleShotModel.run_rig_frame`)."""
    from polrig.app import calibrations
    from polrig.app.rig import load_rig_config

    return calibrations.single_shot_geometry(calibrations.load_calibration(None), load_rig_config(None))


def _cpu_s() -> float:
    """CPU seconds (user + system, all threads) this process has used: on a machine shared with
    other jobs the work done, which wall-clock time is not (on an idle machine a frame takes
    between this over the threads used and this)."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


#: ``python -m polrig ARGS`` as a one-shot process that reports its own peak resident memory
#: (``VmHWM`` of its address space: a child's ``wait4`` maximum would include the benchmark
#: process's own peak, which Linux carries through fork and exec).
COLD = """
import sys
from polrig.cli import main
try:
    code = main(sys.argv[1:])
finally:
    hwm = next(line for line in open("/proc/self/status") if line.startswith("VmHWM"))
    print("VMHWM_KB", hwm.split()[1], file=sys.stderr)
sys.exit(code)
"""


def _child_env() -> dict:
    """The environment of a one-shot run: this checkout on the path, and bytecode caching
    as an installed package has it (a development shell's PYTHONDONTWRITEBYTECODE would make
    every cold start compile all of polrig again)."""
    import os

    # this checkout after PYTHONPATH: on a lent machine the links of benchmarks/polrig_path.sh,
    # which name polrig's top-level folders as an install does, must come before its polrig/
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (os.environ.get("PYTHONPATH"), str(REPO)) if p))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def cold_once(src: pathlib.Path, argv: list[str], out: pathlib.Path, device: str = "auto") -> dict:
    """``polrig infer --device DEVICE`` in a fresh process (the CLI's own ``main``, as ``python -m
    polrig.cli`` runs it): wall seconds and the process's peak resident memory."""
    import subprocess

    cmd = [sys.executable, "-c", COLD, "infer", str(src), "--state-deg", "0", "--saturation-dn", "4095",
           "--device", device, "--out", str(out), *argv]
    import resource

    env = _child_env()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    if proc.returncode or not out.is_file():
        raise RuntimeError(f"cold run failed: {' '.join(cmd[3:])}: {proc.stderr.strip()[-300:]}")
    out.unlink()
    kb = next(float(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("VMHWM_KB"))
    return {"wall": wall, "cpu": cpu, "peak_mb": kb / 1024.0}


ANATOMY = """
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import onnxruntime
t1 = time.perf_counter()
import polrig.cli
from polrig.models.runtime import SingleShotModel, view_directions
t2 = time.perf_counter()
m = SingleShotModel.load(threads=THREADS)
t3 = time.perf_counter()
h, w = 1024, 1224
rng = np.random.default_rng(0)
feed = (rng.random((1, 3, 4, h, w), dtype=np.float32), np.ones((1, 1, h, w), np.float32),
        np.array([[0.5, 0.5, 0.0]], np.float32), view_directions((h, w))[None], np.array([[0.0, -1.0, 0.0]], np.float32))
runs = []
for _ in range(3):
    t = time.perf_counter(); m.run_normalised(*feed); runs.append(time.perf_counter() - t)
print(json.dumps({"import numpy+onnxruntime": t1 - t0, "import polrig.cli+polrig.models.runtime": t2 - t1,
                  "session creation": t3 - t2, "first pass": runs[0], "second pass": runs[1], "third pass": runs[2],
                  "peak_mb": float(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1]) / 1024}))
"""


def anatomy(rounds: int, threads: int | None) -> dict[str, float]:
    """Medians over ``rounds`` fresh processes of where a cold run's time goes (ANATOMY)."""
    import json
    import subprocess

    env = _child_env()
    rows = [json.loads(subprocess.run([sys.executable, "-c", ANATOMY.replace("THREADS", repr(threads))],
                                      capture_output=True, text=True, check=True, env=env, cwd=REPO).stdout)
            for _ in range(rounds)]
    return {k: statistics.median(r[k] for r in rows) for k in rows[0]}


#: The one-shot CLI in a fresh process with its steps timed where they run (the CLI's own
#: functions wrapped, nothing re-implemented): CPU seconds (all threads) and wall per step.
COLD_STEPS = """
import json, sys, time
w0, c0 = time.perf_counter(), time.process_time()
steps = {}
def timed(owner, name, label):
    fn = getattr(owner, name)
    def wrapper(*a, **k):
        w, c = time.perf_counter(), time.process_time()
        try:
            return fn(*a, **k)
        finally:
            prev = steps.get(label, (0.0, 0.0))
            steps[label] = (prev[0] + time.process_time() - c, prev[1] + time.perf_counter() - w)
    setattr(owner, name, wrapper)
import numpy, onnxruntime
steps["import numpy+onnxruntime"] = (time.process_time() - c0, time.perf_counter() - w0)
import polrig.models.runtime as rt, polrig.app.preview as pv, polrig.formats.rawio as rio, polrig.cli as cli
import polrig.app.single_shot as ss, polrig.formats.exr as ex
timed(rt.SingleShotModel, "load", "session creation")
timed(rio, "read_raw", "decode")
timed(ss.SingleShot, "frame", "reconstruction")
timed(ex, "write_result_exr", "EXR")
timed(ss, "s0_snr", "S0 SNR (mask, previews)")
timed(pv, "write_result_previews", "previews: PNGs")
cli.main(sys.argv[1:])
total = (time.process_time() - c0, time.perf_counter() - w0)
steps["rest (imports, parser, checks)"] = tuple(t - sum(v[i] for v in steps.values()) for i, t in enumerate(total))
steps["total"] = total
print(json.dumps(steps))
"""


def cold_steps(src: pathlib.Path, argv: list[str], out: pathlib.Path, rounds: int) -> dict[str, tuple[float, float]]:
    """Medians over ``rounds`` fresh processes of :data:`COLD_STEPS`: step -> (CPU s, wall s)."""
    import json
    import subprocess

    rows = []
    for _ in range(rounds):
        cmd = [sys.executable, "-c", COLD_STEPS, "infer", str(src), "--state-deg", "0", "--saturation-dn", "4095",
               "--out", str(out), *argv]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=_child_env(), cwd=REPO)
        if proc.returncode:
            raise RuntimeError(f"cold steps failed: {proc.stderr.strip()[-300:]}")
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return {k: tuple(statistics.median(r[k][i] for r in rows) for i in range(2)) for k in rows[0]}


def gpu_name() -> str | None:
    """The NVIDIA GPU's name as ``nvidia-smi`` reports it (None where there is none)."""
    import shutil
    import subprocess

    if shutil.which("nvidia-smi") is None:
        return None
    proc = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                          capture_output=True, text=True)
    return proc.stdout.strip().splitlines()[0] if proc.returncode == 0 and proc.stdout.strip() else None


def pick_cases(spec: str | None) -> tuple:
    """The CASES a ``--cases`` value names: comma-separated 0-based indices (None: all)."""
    if not spec:
        return CASES
    try:
        picked = [CASES[int(k)] for k in spec.split(",")]
    except (ValueError, IndexError):
        raise SystemExit(f"--cases {spec!r}: comma-separated indices 0..{len(CASES) - 1}") from None
    return tuple(picked)


def speed(rounds: int, threads: int | None, spinning: bool, weights, with_anatomy: bool, device: str = "auto",
          cases: tuple = CASES) -> tuple[str, dict]:
    """The cases table (module docstring) as Markdown, and the measurements it was made from.
    ``device``: where the networks run (``auto``, ``cpu``, ``cuda``; warm and cold alike)."""
    import os

    load_start = os.getloadavg()[0]
    model = SingleShot(SingleShotModel.load(weights, threads=threads, spinning=spinning, device=device))
    rng = np.random.default_rng(0)
    warm: dict[str, list[dict]] = {c[0]: [] for c in cases}
    cold: dict[str, list[dict]] = {c[0]: [] for c in cases}
    with tempfile.TemporaryDirectory() as d:
        tmp = pathlib.Path(d)
        raws = {}
        for label, shape, layout, argv in cases:
            key = (shape, layout)
            if key not in raws:
                raws[key] = write_case_raw(shape, layout, tmp / f"raw_{layout}_{shape[1]}x{shape[0]}.png", rng)
            warm_once(raws[key], argv, model, tmp / "warm.exr")  # warm-up: sessions, plans, caches
        for r in range(rounds):
            for label, shape, layout, argv in cases:
                # a case writes a new file, as a user's run does: the previous case's output is
                # deleted and written back before the clock starts (replacing a full-sensor
                # EXR frees a gigabyte inside the next case's write: 140 ms of a 512x512
                # case's 30 ms EXR write)
                for name in ("warm.exr", "cold.exr"):
                    (tmp / name).unlink(missing_ok=True)
                os.sync()
                warm[label].append(warm_once(raws[(shape, layout)], argv, model, tmp / "warm.exr"))
                cold[label].append(cold_once(raws[(shape, layout)], argv, tmp / "cold.exr", device))
                print(f"round {r + 1}/{rounds} {label}: warm {1e3 * warm[label][-1]['total']:.0f} ms, "
                      f"cold {1e3 * cold[label][-1]['wall']:.0f} ms, {cold[label][-1]['peak_mb']:.0f} MB", flush=True)
        anat = anatomy(rounds, threads) if with_anatomy else None
        label, shape, layout, argv = CASES[4]  # the full colour sensor at full resolution
        if with_anatomy and (shape, layout) not in raws:
            raws[(shape, layout)] = write_case_raw(shape, layout, tmp / "raw_steps.png", rng)
        steps = cold_steps(raws[(shape, layout)], argv + ["--device", device], tmp / "steps.exr",
                           rounds) if with_anatomy else None
    raw = {"provider": model.provider, "gpu": gpu_name() if model.provider == "CUDAExecutionProvider" else None,
           "frame_route": model.frame_route,
           "onnxruntime": __import__("onnxruntime").__version__,
           "threads": threads or physical_cores(), "cores": physical_cores(), "spinning": spinning, "rounds": rounds,
           "warm": warm, "cold": cold, "anatomy": anat, "cold_steps": steps,
           "cold_steps_case": CASES[4][0] if steps else None, "load_average": [load_start, os.getloadavg()[0]]}
    return render(raw), raw


def render(raw: dict) -> str:
    """The Markdown table of :func:`speed`'s measurements ``raw`` (also saved as JSON)."""
    med = lambda rows, k: statistics.median(x.get(k, 0.0) for x in rows)  # noqa: E731
    gpu = f" on {raw['gpu']}" if raw.get("gpu") else ""
    route = f", frame route {raw['frame_route']}" if raw.get("frame_route") else ""
    lines = [f"Device: {raw['provider']}{gpu}{route} (onnxruntime {raw['onnxruntime']}), {raw['threads']} intra-op thread(s), "
             f"spinning {'on' if raw['spinning'] else 'off'}; {raw['cores']} physical core(s). Medians over "
             f"{raw['rounds']} interleaved round(s) after one warm-up; times in ms. Warm: in process; raw -> Mueller: "
             f"the raw frame in memory (as the camera delivers it) to the Mueller image in memory (demosaic, Stokes, "
             f"networks, lifts, output; the per-frame work the targets are set for); file to file: plus decoding "
             f"the raw file (16-bit PNG) and writing the EXR (atomic, fsync); cold: the one-shot "
             f"CLI `polrig infer` in a fresh process (imports, session, first run, EXR). Warm CPU time: user + "
             f"system seconds of all threads per frame (the work done; on a shared machine wall time also holds the "
             f"waiting)."
             + (" Load average (1 min) at the start and the end: {:.1f}, {:.1f} (the machine's other jobs: times grow "
                "with it).".format(*raw["load_average"]) if raw.get("load_average") else ""), "",
             "| case | output | **warm: raw -> Mueller** | warm: file to file | networks | lifts | decode | EXR | "
             "warm CPU time | **cold (CLI)** | cold CPU time | cold peak MB | target |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, w in raw["warm"].items():
        c = raw["cold"][label]
        target = TARGETS_MS.get(label)
        goals = ([f"<= {target} ms"] if target else []) + (["<= 2048 MB"] if label.startswith("full sensor") else [])
        lines.append(f"| {label} | {w[0]['net']} | **{1e3 * med(w, 'compute'):.0f}** | {1e3 * med(w, 'total'):.0f} | "
                     f"{1e3 * med(w, 'network'):.0f} | {1e3 * med(w, 'lift'):.0f} | {1e3 * med(w, 'decode'):.0f} | "
                     f"{1e3 * med(w, 'exr'):.0f} | {1e3 * med(w, 'cpu'):.0f} | "
                     f"**{1e3 * med(c, 'wall'):.0f}** | {1e3 * med(c, 'cpu'):.0f} | {med(c, 'peak_mb'):.0f} | {'; '.join(goals)} |")
    device_rows = {label: w for label, w in raw["warm"].items() if w and "upload" in w[0]}
    if device_rows:  # the device route (issue 31): the frame kept on the provider's device
        steps = ("upload", "pre", "statistics", "network", "post", "copy_back")
        lines += ["", "The device route's steps (warm, raw -> Mueller; `models/device_path.py`), ms:", "",
                  "| case | " + " | ".join(steps) + " |", "|---|" + "---|" * len(steps)]
        lines += [f"| {label} | " + " | ".join(f"{1e3 * med(w, k):.1f}" for k in steps) + " |"
                  for label, w in device_rows.items()]
    anat = raw.get("anatomy")
    if anat:
        lines += ["", f"Where a cold run's time goes (fresh processes, medians of {raw['rounds']}; one network pass "
                  "on 1224x1024x3, the mono full sensor's grid):", "", "| step | ms |", "|---|---|"]
        lines += [f"| {k} | {1e3 * v:.0f} |" for k, v in anat.items() if k != "peak_mb"]
        lines.append(f"| peak memory | {anat['peak_mb']:.0f} MB |")
    steps = raw.get("cold_steps")
    if steps:
        lines += ["", f"Where the one-shot CLI's time goes for the {raw['cold_steps_case']} (fresh processes, medians of "
                  f"{raw['rounds']}; the CLI's own functions timed where they run):", "",
                  "| step | CPU ms | wall ms |", "|---|---|---|"]
        lines += [f"| {k} | {1e3 * v[0]:.0f} | {1e3 * v[1]:.0f} |" for k, v in steps.items()]
    return "\n".join(lines)


RIG_SCENES = "sphere,rough_sphere,checker_sphere,box,multi,heightfield,plane,normalmap"


def size_speed(rounds: int, threads: int | None, device: str) -> dict:
    """Warm raw -> Mueller seconds per shipped size and :data:`SIZE_CASES` case, rounds
    interleaving the sizes (the model loaded once per size)."""
    from polrig.models import sizes

    routes = {s: SingleShot(SingleShotModel.load(sizes.size_folder(s), threads=threads, device=device))
              for s in sizes.shipped_sizes()}
    times: dict[str, dict[str, list[float]]] = {s: {c[0]: [] for c in SIZE_CASES} for s in routes}
    with tempfile.TemporaryDirectory() as d:
        tmp, rng = pathlib.Path(d), np.random.default_rng(0)
        raws = {c[0]: write_case_raw(c[1], c[2], tmp / f"raw{k}.png", rng) for k, c in enumerate(SIZE_CASES)}
        for route in routes.values():
            for label, _, _, argv in SIZE_CASES:
                warm_once(raws[label], argv, route, tmp / "warm.exr")  # warm-up
        for _ in range(rounds):
            for s, route in routes.items():
                for label, _, _, argv in SIZE_CASES:
                    times[s][label].append(warm_once(raws[label], argv, route, tmp / "warm.exr")["compute"])
    provider = next(iter(routes.values())).provider if routes else ""
    return {"rounds": rounds, "provider": provider, "threads": threads or physical_cores(),
            "load_average": os.getloadavg()[0],
            "medians_s": {s: {k: statistics.median(v) for k, v in t.items()} for s, t in times.items()}}


def _committed(name: str) -> dict | None:
    import json

    path = REPO / "benchmarks" / "results" / name
    return json.loads(path.read_text()) if path.is_file() else None


def sizes_table(measured: dict) -> str:
    """The model sizes table (module docstring) from :func:`size_speed`'s ``measured``."""
    from polrig.models import sizes

    cases = [c[0] for c in SIZE_CASES]
    lines = [f"One row per model size (`polrig infer --model-size`, polrig.models.sizes). Accuracy: the full model on the "
             f"model card's held-out sets (matrix PSNR dB / forward Stokes L2). Speed: warm raw -> Mueller, ms, "
             f"medians of {measured['rounds']} interleaved round(s) here ({measured['provider']}, "
             f"{measured['threads']} intra-op thread(s)"
             + (f", load average {measured['load_average']:.1f}: the machine's other jobs slow it" if
                measured.get("load_average") else "")
             + ") and from the committed CUDA measurements (`single_shot_cuda_h200.json` for small).", "",
             "| size | width | trained on | training min | unseen shapes | new scenes | "
             + " | ".join(f"CPU {c}" for c in cases) + " | " + " | ".join(f"GPU {c}" for c in cases) + " |",
             "|---" * (6 + 2 * len(cases)) + "|"]
    for size in sizes.SIZES:
        if not sizes.is_shipped(size):
            lines.append(f"| {size} | | | | " + " | ".join([WAITING] * (2 + 2 * len(cases))) + " |")
            continue
        rec = sizes.model_record(sizes.size_folder(size))
        acc = []
        for name in ACCURACY_FILES[size].values():
            r = _committed(name)
            full = (r or {}).get("methods", {}).get("full")
            acc.append(f"{full['matrix_psnr']:.2f} / {full['fwd_l2']:.4f}" if full else "not measured")
        cpu = [f"{1e3 * measured['medians_s'][size][c]:.0f}" if size in measured["medians_s"] else "" for c in cases]
        gpu_raw = _committed(GPU_RESULTS[size]) or {}
        gpu = []
        for c in cases:
            rows = (gpu_raw.get("warm") or {}).get(c)
            gpu.append(f"{1e3 * statistics.median(x['compute'] for x in rows):.0f}" if rows else "not measured")
        lines.append(f"| {size} | {rec['width']} | {rec['training_hardware'].split('; ')[0]} | "
                     f"{rec['training_minutes']} | {' | '.join(acc)} | {' | '.join(cpu)} | {' | '.join(gpu)} |")
    return "\n".join(lines)


def write_sizes(rounds: int, threads: int | None, device: str) -> str:
    import json

    measured = size_speed(rounds, threads, device)
    table = sizes_table(measured)
    out = REPO / "benchmarks" / "results" / "single_shot_sizes.md"
    out.with_suffix(".json").write_text(json.dumps(measured, indent=1) + "\n")
    out.write_text("# Single-shot model sizes: accuracy and speed\n\n`python benchmarks/bench_single_shot.py "
                   f"--sizes-only --rounds {rounds}`\n\n" + table + "\n")
    print(table)
    print(f"wrote {out}")
    return table


def rig_scene_scores(scenes: list[str], tmp: pathlib.Path, poses: str = "0", mirror: bool = False) -> list[dict]:
    """Processing scores of single-shot captures on the default simulated rig (see module):
    per scene and variant the mean matrix PSNR over the ``poses`` (``polrig capture --poses``
    syntax) whose truth is lit, and the design variant's per-pose PSNRs (``None`` for a dark
    truth) under ``"design_per_pose"``. ``mirror``: the variants are the design geometry
    with and without ``--mirror-average`` instead."""
    import contextlib
    import io

    from polrig.app.session import Session
    from polrig.cli import main as cli
    from polrig.sim.geometry import TurntableGeometry
    from polrig.sim.scene import default_camera, default_light, stage_zero_axis_for

    cam = default_camera(256, 256)
    x0, target = stage_zero_axis_for(default_light(), TurntableGeometry())
    k = cam.R @ (target - default_light().position_m)
    turned = np.cross(k / np.linalg.norm(k), cam.R @ x0).tolist()
    variants = ({"design": ("", []), "mirror": ("", ["--mirror-average"])} if mirror else
                {"design": ("", []),
                 "training_axis": ("[nominal_geometry]\nstage_zero_axis_camera = [0.0, -1.0, 0.0]\n", []),
                 "turned_90": (f"[nominal_geometry]\nstage_zero_axis_camera = {turned}\n", [])})
    rows = []
    for scene in scenes:
        row = {"scene": scene}
        for name, (extra, flags) in variants.items():
            cfg = tmp / f"{scene}-{name}.toml"
            cfg.write_text(f'[sim]\nsize = "256x256"\nclock_speed = inf\nscene = "{scene}"\n{extra}')
            out = tmp / f"{scene}-{name}"
            with contextlib.redirect_stdout(io.StringIO()):
                cli(["capture", "--poses", poses, "--mode", "single-shot", "--config", str(cfg), "--out", str(out),
                     "--no-progress", *flags])
            caps = Session.open(out).captures
            psnr = [c["score"]["psnr_db"] for c in caps]
            row[name] = float(np.mean([p for p in psnr if p is not None]))
            if name == "design":
                row["design_per_pose"] = {c["pose_deg"]: p for c, p in zip(caps, psnr)}
        rows.append(row)
        print(f"{scene:15s} " + ", ".join(f"{k} {row[k]:.2f} dB" for k in variants), flush=True)
    return rows


def rig_mirror_table(rows: list[dict]) -> str:
    lines = ["| scene | one pass | mirror-averaged | gain (dB) |", "|---|---|---|---|"]
    for r in rows + [{"scene": "**mean**", **{k: float(np.mean([r[k] for r in rows])) for k in ("design", "mirror")}}]:
        lines.append(f"| {r['scene']} | {r['design']:.2f} | {r['mirror']:.2f} | {r['mirror'] - r['design']:+.2f} |")
    return "\n".join(lines)


def rig_scene_table(rows: list[dict]) -> str:
    lines = ["| scene | design geometry (now) | training-rig axis (before) | axis turned 90 deg | gain over before |",
             "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['design']:.2f} | {r['training_axis']:.2f} | {r['turned_90']:.2f} | "
                     f"{r['design'] - r['training_axis']:+.2f} |")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in ("design", "training_axis", "turned_90")}
    lines.append(f"| **mean** | **{mean['design']:.2f}** | {mean['training_axis']:.2f} | {mean['turned_90']:.2f} | "
                 f"{mean['design'] - mean['training_axis']:+.2f} |")
    poses = sorted({p for r in rows for p in r["design_per_pose"]})
    if len(poses) > 1:
        lines += ["", "Design geometry per turntable pose (n/a: the truth is dark, the object shows its unlit back):", "",
                  "| scene | " + " | ".join(f"{p:g} deg" for p in poses) + " |", "|---|" + "---|" * len(poses)]
        for r in rows:
            cells = [r["design_per_pose"].get(p) for p in poses]
            lines.append(f"| {r['scene']} | " + " | ".join("n/a" if c is None else f"{c:.2f}" for c in cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds of every case (default 3)")
    ap.add_argument("--anatomy", action="store_true", help="also time a cold run's steps in fresh processes")
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: physical cores)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped models/weights)")
    ap.add_argument("--spinning", action="store_true", help="let onnxruntime worker threads spin")
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                    help="where the networks run, warm and cold (default auto: CUDA where onnxruntime offers it)")
    ap.add_argument("--cases", default=None, help="comma-separated case indices to time (default: all; 0-based, "
                                                   "in the table's order)")
    ap.add_argument("--mirror-average", action="store_true",
                    help="with --rig-scenes: score captures with and without --mirror-average (models/mirror.py) "
                         "instead of the geometry variants")
    ap.add_argument("--out", default=None, help="also write the table to this Markdown file (speed: default "
                                                "benchmarks/results/single_shot_speed.md)")
    ap.add_argument("--rig-scenes", default=None, nargs="?", const=RIG_SCENES,
                    help=f"score single-shot captures of these scenes on the default rig instead (default {RIG_SCENES})")
    ap.add_argument("--rig-poses", default="0",
                    help="turntable poses of the --rig-scenes captures, as polrig capture --poses (default 0)")
    ap.add_argument("--sizes-only", action="store_true",
                    help="only the model sizes table (benchmarks/results/single_shot_sizes.md)")
    args = ap.parse_args(argv)
    if args.sizes_only:
        write_sizes(args.rounds, args.threads, args.device)
        return 0
    if args.rig_scenes:
        with tempfile.TemporaryDirectory() as d:
            rows = rig_scene_scores(args.rig_scenes.split(","), pathlib.Path(d), args.rig_poses,
                                    mirror=args.mirror_average)
        table = rig_mirror_table(rows) if args.mirror_average else rig_scene_table(rows)
        print(table)
        if args.out:
            command = (f"`python benchmarks/bench_single_shot.py --rig-scenes {args.rig_scenes} --rig-poses "
                       f"{args.rig_poses}{' --mirror-average' if args.mirror_average else ''} --out FILE`: ")
            if args.mirror_average:
                head = ("# Single-shot captures on the default simulated rig: one pass against mirror averaging\n\n"
                        + command + "`polrig capture --mode single-shot` with and without `--mirror-average` "
                        "(models/mirror.py), design geometry, otherwise as `single_shot_rig.md`: mean matrix PSNR (dB) "
                        "over the poses with a lit truth.")
            else:
                head = ("# Single-shot captures on the default simulated rig: processing scores\n\n" + command
                        + "`polrig capture --mode single-shot` of each scene (256x256 raw, 64x64 analyzer grid, "
                        f"turntable poses {args.rig_poses}, seed 0, nominal calibration), mean over the poses with a lit "
                        "truth of the matrix PSNR in dB from `polrig.app.processing.score_against_truth` (peak = largest "
                        "true m00 compared; pixels whose support lies on the object; pixels with saturated samples "
                        "excluded, as for the reference mode).")
            pathlib.Path(args.out).write_text(head + "\n\n" + table + "\n")
        return 0
    table, raw = speed(args.rounds, args.threads, args.spinning, args.weights, args.anatomy, args.device,
                       pick_cases(args.cases))
    print(table)
    out = pathlib.Path(args.out) if args.out else REPO / "benchmarks" / "results" / "single_shot_speed.md"
    import json

    out.with_suffix(".json").write_text(json.dumps(raw, indent=1) + "\n")
    out.write_text("# Single-shot inference speed\n\n`python benchmarks/bench_single_shot.py"
                   f"{' --anatomy' if args.anatomy else ''} --rounds {args.rounds}`\n\n" + table + "\n")
    print(f"wrote {out}")
    if args.weights is None and args.cases is None:  # the default run: both sizes too
        write_sizes(args.rounds, args.threads, args.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
