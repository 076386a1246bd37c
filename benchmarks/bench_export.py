"""``polrig export`` at full-sensor size: a synthetic result EXR and a small session of such
results, exported to OME-Zarr (NGFF 0.4 and 0.5) and OME-TIFF, against the I/O floor.

Data (written once, with the project's own writers: :func:`polrig.formats.exr.write_result_exr`
in a session made by :class:`polrig.app.session.Session`): a colour superpixel result of a
2448x2048 sensor (``--size 1024x1224``), every plane group (3x3 Mueller, ``sigma``,
``sigma_noise`` per element and colour, ``mask`` and ``residual`` per colour: 87 planes,
0.44 GB of float32), smooth fields plus noise, ZIP; the session holds ``--captures`` poses of it.

Cases, per round in turn (interleaved rounds, medians):

* ``export`` to ``ome-zarr`` 0.4, ``ome-zarr`` 0.5 and ``ome-tiff`` of the result and of the session;
* the floor, ``floor-zarr`` / ``floor-tiff``: each result file read once
  (:func:`polrig.formats.exr.read_mueller_exr`) and its arrays written without any OME metadata,
  display windows or channel reordering, with the same codecs (a plain Zarr array per
  quantity, zarr's default compressor, chunks of one (Y, X) plane of at most 1024x1024; plain
  BigTIFF pages, deflate level 1, capture-major): what any export of these bytes must do.

each timed twice: warm in-process (the library call, after one warm-up) and one-shot CLI (a fresh
``python -c`` running ``polrig.cli.main`` or the floor, reporting its peak resident memory
``VmHWM``).

    python -m benchmarks export            # or python benchmarks/bench_export.py
        [--size 1024x1224] [--colours 3] [--captures 2] [--rounds 3] [--only session] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parent.parent
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

RESULTS = REPO / "benchmarks" / "results" / "export.md"

#: A one-shot run: ``polrig.cli.main(ARGS)`` or the floor, then the process's peak resident memory.
ONE_SHOT = """
import sys
sys.path.insert(0, sys.argv[1])
import bench_export as b
try:
    code = b.one_shot(sys.argv[2:])
finally:
    hwm = next(line for line in open("/proc/self/status") if line.startswith("VmHWM"))
    print("VMHWM_KB", hwm.split()[1], file=sys.stderr)
sys.exit(code)
"""


class SyntheticResult:
    """A reconstruction's arrays (:class:`polrig.formats.exr.ResultArrays`) at ``(H, W)``:
    smooth Mueller fields with noise, their standard deviations, reason bits, residuals."""

    def __init__(self, colours: int, h: int, w: int, seed: int = 34):
        rng = np.random.default_rng(seed)
        y, x = np.mgrid[0:h, 0:w].astype(np.float32)
        base = (0.5 + 0.3 * np.sin(x / 97.0) * np.cos(y / 61.0)).astype(np.float32)
        scale = rng.uniform(-1, 1, (colours, 3, 3, 1, 1)).astype(np.float32)
        scale[:, 0, 0] = 1.0
        self.mueller = scale * base + rng.normal(0, 1e-3, (colours, 3, 3, h, w)).astype(np.float32)
        self.sigma = np.abs(rng.normal(1e-3, 2e-4, (colours, 3, 3, h, w))).astype(np.float32)
        self.sigma_noise = (0.9 * self.sigma).astype(np.float32)
        self.mask = (rng.random((colours, h, w)) < 0.02).astype(np.uint8) * 2
        self.residual = rng.chisquare(4, (colours, h, w)).astype(np.float32) / 4


def make_data(folder: pathlib.Path, colours: int, h: int, w: int, captures: int) -> tuple[pathlib.Path, pathlib.Path]:
    """``(result EXR, session folder)`` in ``folder``."""
    from polrig.acquisition.plan import CapturePlan
    from polrig.app.manifest import SampleMetadata
    from polrig.app.session import Session
    from polrig.formats.exr import write_result_exr

    result = folder / "mueller.exr"
    write_result_exr(result, SyntheticResult(colours, h, w), metadata={"calibration_id": "nominal"})
    data = result.read_bytes()
    rig = {"simulated": False, "config": None, "devices": {}, "sim_parameters": None,
           "camera_frames": None, "sensor_model": None}
    poses = tuple(360.0 * i / captures for i in range(captures))
    s = Session.create(folder / "session", plan=CapturePlan(poses), rig=rig, calibration_id="nominal",
                       command_line=["bench_export"], metadata=SampleMetadata("synthetic", "bench"))
    for cap in s.captures:
        s.add_file(cap["index"], "mueller", f"{cap['name']}/mueller.exr", data)
        s.complete_capture(cap["index"])
    s.unlock()
    return result, folder / "session"


# -- the floor ----------------------------------------------------------------------------------
def _sources(src: pathlib.Path) -> list[pathlib.Path]:
    if src.is_file():
        return [src]
    from polrig.app.session import Session

    s = Session.open(src)
    return [s.root / c["files"]["mueller"]["path"] for c in s.captures]


def _quantities(path: pathlib.Path) -> dict[str, np.ndarray]:
    """One read of a result file: each quantity as ``(planes, Y, X)`` in the file's order."""
    from polrig.formats.exr import read_mueller_exr

    r = read_mueller_exr(path)
    out = {"mueller": r.mueller.reshape((-1,) + r.mueller.shape[-2:])}
    for group in ("sigma", "sigma_noise", "mask", "residual"):
        names = sorted(k for k in r.extra if k.startswith(group + "."))
        if names:
            dtype = np.uint8 if group == "mask" else np.float32
            out[group] = np.stack([r.extra.pop(k) for k in names]).astype(dtype, copy=False)
    return out


def floor_zarr(src: pathlib.Path, out: pathlib.Path) -> None:
    """Each file read once; each quantity a plain Zarr (format 2) array ``(T, C, Y, X)``."""
    import zarr

    paths = _sources(src)
    root = zarr.open_group(str(out), mode="w", zarr_format=2)
    arrays: dict = {}
    for t, p in enumerate(paths):
        for name, a in _quantities(p).items():
            if name not in arrays:
                arrays[name] = root.create_array(name, shape=(len(paths),) + a.shape, dtype=a.dtype,
                                                 chunks=(1, 1, min(a.shape[1], 1024), min(a.shape[2], 1024)))
            arrays[name][t] = a


def floor_tiff(src: pathlib.Path, out: pathlib.Path) -> None:
    """Each file read once; its planes as BigTIFF pages, deflate level 1, no OME metadata."""
    import tifffile

    with tifffile.TiffWriter(out, bigtiff=True) as tw:
        for p in _sources(src):
            for a in _quantities(p).values():
                tw.write(a, photometric="minisblack", compression="zlib", compressionargs={"level": 1},
                         metadata=None)


# -- the cases ----------------------------------------------------------------------------------
CASES = {  # name: (format, NGFF version)
    "ome-zarr 0.4": ("ome-zarr", "0.4"), "ome-zarr 0.5": ("ome-zarr", "0.5"),
    "ome-tiff": ("ome-tiff", None), "floor-zarr": ("floor-zarr", None), "floor-tiff": ("floor-tiff", None),
}


def run_case(case: str, src: pathlib.Path, out: pathlib.Path) -> None:
    fmt, version = CASES[case]
    if fmt == "floor-zarr":
        floor_zarr(src, out)
    elif fmt == "floor-tiff":
        floor_tiff(src, out)
    else:
        import polrig

        polrig.export(src, out, fmt, version=version or "0.4")


def one_shot(argv: list[str]) -> int:
    """The one-shot process's work: ``CASE SRC OUT``; the exports through the CLI."""
    case, src, out = argv
    fmt, version = CASES[case]
    if fmt.startswith("floor"):
        run_case(case, pathlib.Path(src), pathlib.Path(out))
        return 0
    from polrig.cli import main

    return main(["export", src, "--format", fmt, "-o", out] + (["--ngff", version] if version else []))


def _out_path(tmp: pathlib.Path, case: str) -> pathlib.Path:
    return tmp / ("out.zarr" if "zarr" in case else "out.ome.tif")


def _clear(p: pathlib.Path) -> None:
    if p.is_dir():
        shutil.rmtree(p)
    elif p.exists():
        p.unlink()


def time_warm(case: str, src: pathlib.Path, tmp: pathlib.Path) -> float:
    out = _out_path(tmp, case)
    _clear(out)
    t = time.perf_counter()
    run_case(case, src, out)
    dt = time.perf_counter() - t
    _clear(out)
    return dt


def time_one_shot(case: str, src: pathlib.Path, tmp: pathlib.Path) -> tuple[float, float]:
    """Wall seconds and peak resident MB of a fresh process."""
    out = _out_path(tmp, case)
    _clear(out)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (os.environ.get("PYTHONPATH"), str(REPO)) if p))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", ONE_SHOT, str(REPO / "benchmarks"), case, str(src), str(out)],
                       capture_output=True, text=True, env=env, cwd=REPO)
    dt = time.perf_counter() - t
    if r.returncode:
        raise SystemExit(f"{case} {src.name}: exit {r.returncode}\n{r.stderr[-2000:]}")
    hwm = next(int(line.split()[1]) for line in r.stderr.splitlines() if line.startswith("VMHWM_KB"))
    _clear(out)
    return dt, hwm / 1024


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1024x1224", help="result grid HxW (default: the superpixel grid of a "
                    "2448x2048 sensor)")
    ap.add_argument("--colours", type=int, default=3, choices=(1, 3))
    ap.add_argument("--captures", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--only", choices=("result", "session"), default=None)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated subset of " + ", ".join(CASES))
    ap.add_argument("--no-one-shot", action="store_true", help="warm in-process only")
    ap.add_argument("--out", default=None, help=f"write the table here (e.g. {RESULTS.relative_to(REPO)})")
    args = ap.parse_args(argv)
    h, w = (int(v) for v in args.size.split("x"))
    cases = args.cases.split(",")
    with tempfile.TemporaryDirectory(prefix="polrig-bench-export-") as d:
        tmp = pathlib.Path(d)
        t = time.perf_counter()
        result, session = make_data(tmp, args.colours, h, w, args.captures)
        mb = result.stat().st_size / 2**20
        print(f"data: {h}x{w}x{args.colours} result, {mb:.0f} MB EXR; session of {args.captures} "
              f"({time.perf_counter() - t:.1f} s)", flush=True)
        sources = {"result": result, "session": session}
        if args.only:
            sources = {args.only: sources[args.only]}
        for name, src in sources.items():  # warm-up: imports, zarr/tifffile first use
            run_case(cases[0], src, _out_path(tmp, cases[0]))
            _clear(_out_path(tmp, cases[0]))
        warm: dict = {}
        shot: dict = {}
        for r in range(args.rounds):
            for name, src in sources.items():
                for case in cases:
                    key = (name, case)
                    warm.setdefault(key, []).append(time_warm(case, src, tmp))
                    if not args.no_one_shot:
                        shot.setdefault(key, []).append(time_one_shot(case, src, tmp))
                    print(f"round {r}: {name} {case}: warm {warm[key][-1]:.2f} s"
                          + (f", one-shot {shot[key][-1][0]:.2f} s, {shot[key][-1][1]:.0f} MB"
                             if shot else ""), flush=True)
    raw_gb = args.colours * 29 * h * w * 4 / 1e9
    lines = [f"# `polrig export`, {h}x{w} colour={args.colours} result with every plane group "
             f"({args.colours * 29} planes, {raw_gb:.2f} GB raw per capture; EXR {mb:.0f} MB), session of "
             f"{args.captures} captures; {args.rounds} interleaved rounds, medians",
             "", f"Machine: {os.cpu_count()} CPUs (shared), {sys.platform}; "
             f"`python -m benchmarks export --size {args.size} --captures {args.captures} --rounds {args.rounds}`.",
             "", "| source | case | warm in-process s | one-shot CLI s | one-shot peak RSS MB |",
             "|---|---|---:|---:|---:|"]
    for (name, case), ts in warm.items():
        s = shot.get((name, case))
        lines.append(f"| {name} | {case} | {statistics.median(ts):.2f} | "
                     + (f"{statistics.median(x[0] for x in s):.2f} | {statistics.median(x[1] for x in s):.0f} |"
                        if s else "- | - |"))
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text)
    print(json.dumps({f"{k[0]}/{k[1]}": statistics.median(v) for k, v in warm.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
