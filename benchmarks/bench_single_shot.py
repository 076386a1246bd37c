"""Latency and throughput of the whole single-shot path on this machine.

Path per frame: decode the raw file (16-bit PNG, :func:`polrig.rawio.read_raw`), demosaic,
Stokes, PIPNet -> pBRDF -> PMMNet (one onnxruntime call, :func:`models.runtime.infer_frame`),
Mueller EXR (:func:`models.runtime.write_result_exr`). Raw frames are IMX250MYR (colour)
mosaics of a lit sphere rendered with the pBRDF (content matters little for speed, the mask does
for nothing: every pixel runs through the networks); the full sensor is also timed as a mono
IMX250MZR frame ("mono" rows), whose superpixel analyzer images are half the raw size per
axis (1224x1024), four times the colour sensor's.

Sizes are **raw sensor sizes** (256x256, 512x512, full 2448x2048). With the default
``superpixel`` demosaic the colour sensor's native analyzer images are a quarter of that per
axis (64x64, 128x128, 612x512); with ``bilinear`` the network runs at the raw size (the full
sensor then exceeds the runtime's ``max_pixels`` and is resized, see :mod:`models.runtime`).

Usage: ``python benchmarks/bench_single_shot.py [--repeat N] [--threads T] [--out FILE]``
(or ``python -m benchmarks single_shot``; default ``--out benchmarks/results/single_shot_speed.md``).
The superpixel sizes are also timed mirror-averaged (:mod:`models.mirror`: the networks run on
the frame and on its mirror image), the slower, more accurate alternative.

``--rig-scenes sphere,box,...`` instead scores ``polrig capture --mode single-shot`` on the
default simulated rig (256x256 raw, virtual clock, nominal calibration: the simulator's design
geometry), one capture per scene, with processing's own score (``polrig.processing``), three
ways: the design stage zero axis (what processing does now), the training rig's axis (camera up,
what processing did before it passed any geometry) and the design axis turned by 90 deg about
the illumination axis (both through ``[nominal_geometry]``); ``--out`` writes that table.
With ``--mirror-average`` the rig scenes are captured with the design geometry with and
without ``--mirror-average`` instead. ``--rig-poses 0:360:45`` captures each scene over those
turntable poses instead of pose 0 only
(one view of a scene says little: the same model differs by several dB from pose to pose);
every column is then the mean matrix PSNR over the poses with a lit truth (an object turned
with its unlit back to the camera has no PSNR, :func:`polrig.processing.score_against_truth`),
and a second table gives the design-geometry PSNR per pose.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from models.runtime import SingleShotModel, infer_frame, physical_cores, write_result_exr  # noqa: E402
from polrig.hal import Frame, FrameMeta  # noqa: E402
from polrig.layouts import get_layout  # noqa: E402
from polrig.rawio import read_raw, write_raw  # noqa: E402

SIZES = ((256, 256), (512, 512), (2048, 2448))
COLOUR, MONO = "imx250myr", "imx250mzr"
#: Mono sensor rows (the IMX250MZR of ``../shared/data/real-dofp``): its superpixel analyzer
#: images are half the raw size per axis, four times the colour sensor's pixels.
MONO_SIZES = ((2048, 2448),)


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


def bench(size, method, model, repeat, tmp: pathlib.Path, rng, mirror_average: bool = False,
          layout: str = COLOUR) -> dict:
    raw = synthetic_raw(size, rng, layout)
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=10000.0, gain_db=0.0, pixel_format="Mono16",
                     layout=layout, bit_depth=12, black_level_dn=64.0)
    src = tmp / f"raw_{size[0]}x{size[1]}.png"
    write_raw(src, Frame(raw=raw, meta=meta))
    out = tmp / "out.exr"
    rows = []
    for i in range(repeat + 1):  # the first run warms up caches and the session
        t0 = time.perf_counter()
        frame = read_raw(src)
        t1 = time.perf_counter()
        mueller, aux = infer_frame(frame.raw, frame.meta.layout, 0.0, model, demosaic_method=method,
                                   black_level_dn=frame.meta.black_level_dn, mirror_average=mirror_average)
        t2 = time.perf_counter()
        write_result_exr(out, mueller, aux)
        t3 = time.perf_counter()
        if i:
            tt = aux["timings_s"]
            rows.append({"decode": t1 - t0, "demosaic": tt["demosaic"], "stokes": tt["stokes"],
                         "prepare": tt["prepare"], "network": tt["network"], "finish": tt["finish"],
                         "exr": t3 - t2, "total": t3 - t0})
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    label = f"{method}, mirror-averaged" if mirror_average else method
    sensor = " mono" if layout == MONO else ""
    return {"raw": f"{size[1]}x{size[0]}{sensor}", "method": label, "net": f"{mueller.shape[-1]}x{mueller.shape[-2]}",
            **med, "fps": 1.0 / med["total"]}


RIG_SCENES = "sphere,rough_sphere,checker_sphere,box,multi,heightfield,plane,normalmap"


def rig_scene_scores(scenes: list[str], tmp: pathlib.Path, poses: str = "0", mirror: bool = False) -> list[dict]:
    """Processing scores of single-shot captures on the default simulated rig (see module):
    per scene and variant the mean matrix PSNR over the ``poses`` (``polrig capture --poses``
    syntax) whose truth is lit, and the design variant's per-pose PSNRs (``None`` for a dark
    truth) under ``"design_per_pose"``. ``mirror``: the variants are the design geometry
    with and without ``--mirror-average`` instead."""
    import contextlib
    import io

    from polrig.cli import main as cli
    from polrig.session import Session
    from sim.geometry import TurntableGeometry
    from sim.scene import default_camera, default_light, stage_zero_axis_for

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
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (default: physical cores)")
    ap.add_argument("--methods", default="superpixel,bilinear")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped models/weights)")
    ap.add_argument("--spinning", action="store_true", help="let onnxruntime worker threads spin")
    ap.add_argument("--mirror-average", action="store_true",
                    help="with --rig-scenes: score captures with and without --mirror-average (models/mirror.py) "
                         "instead of the geometry variants")
    ap.add_argument("--out", default=None, help="also write the table to this Markdown file (speed: default "
                                                "benchmarks/results/single_shot_speed.md)")
    ap.add_argument("--rig-scenes", default=None, nargs="?", const=RIG_SCENES,
                    help=f"score single-shot captures of these scenes on the default rig instead (default {RIG_SCENES})")
    ap.add_argument("--rig-poses", default="0",
                    help="turntable poses of the --rig-scenes captures, as polrig capture --poses (default 0)")
    args = ap.parse_args(argv)
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
                        "truth of the matrix PSNR in dB from `polrig.processing.score_against_truth` (peak = largest "
                        "true m00 compared; pixels whose support lies on the object; pixels with saturated samples "
                        "excluded, as for the reference mode).")
            pathlib.Path(args.out).write_text(head + "\n\n" + table + "\n")
        return 0
    model = SingleShotModel.load(args.weights, threads=args.threads, spinning=args.spinning)
    rng = np.random.default_rng(0)
    results = []
    with tempfile.TemporaryDirectory() as d:
        for method in args.methods.split(","):
            passes = (False, True) if method == "superpixel" else (False,)  # mirror averaging off / on
            jobs = [(size, COLOUR, mirror) for size in SIZES for mirror in passes]
            if method == "superpixel":
                jobs += [(size, MONO, mirror) for size in MONO_SIZES for mirror in passes]
            for size, layout, mirror_average in jobs:
                all_repeats = size[0] * size[1] <= 512 * 512 or method == "superpixel"  # the slow bilinear sizes get half
                reps = args.repeat if all_repeats else max(2, args.repeat // 2)
                results.append(bench(size, method, model, reps, pathlib.Path(d), rng, mirror_average, layout))
                r = results[-1]
                print(f"{r['raw']:>10s} {r['method']:10s} net {r['net']:>9s}  total {1e3 * r['total']:7.1f} ms",
                      flush=True)
    threads = args.threads or physical_cores()
    lines = [f"onnxruntime intra-op threads: {threads}, spinning {'on' if args.spinning else 'off'}; median of the runs after one warm-up; times in ms.", "",
             "| raw size | demosaic | network size | decode | demosaic | Stokes | prepare | networks + pBRDF | finish | EXR | **total** | frames/s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['raw']} | {r['method']} | {r['net']} | " + " | ".join(
            f"{1e3 * r[k]:.1f}" for k in ("decode", "demosaic", "stokes", "prepare", "network", "finish", "exr"))
            + f" | **{1e3 * r['total']:.1f}** | {r['fps']:.1f} |")
    table = "\n".join(lines)
    print(table)
    out = pathlib.Path(args.out) if args.out else REPO / "benchmarks" / "results" / "single_shot_speed.md"
    out.write_text("# Single-shot inference speed\n\n" + table + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
