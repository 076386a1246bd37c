"""Frame rate of the GUI's live Mueller view at full sensor size, on each device the networks
can run on, without Qt.

Per frame, what the live worker's processing stage does for the "Mueller 3x3" display
(:mod:`polrig.gui.live`): the one single-shot route's whole frame,
:meth:`polrig.app.single_shot.SingleShot.frame` (demosaic, Stokes, the single-shot networks, the
planes; on the host route this is the worker's :meth:`~polrig.app.single_shot.SingleShot.live`,
and on any route what it takes while an ROI is drawn) with the default rig's nominal
geometry, and :meth:`polrig.gui.pipeline.PolarizationData.from_single_shot`, then :func:`polrig.gui.pipeline.render` of the Mueller grid decimated to the live
view's display size (``--max-display-px``, default 1024; 0 renders the whole grid, as the view
did before 2026-11-26). Qt's part (QImage onto
the view) is left out: ``benchmarks/bench_gui.py`` measures it with the Stokes displays, and it
is the same for every device. Frames are 2448x2048 IMX250MYR mosaics of a lit sphere
(:func:`benchmarks.bench_single_shot.synthetic_raw`), a new one each frame.

Columns: per device and resolution, the median milliseconds of the inference and of the grid
render over ``--frames`` frames after two warm-ups, and the frames per second they allow
(1 / their sum; the live worker overlaps the render with the next frame's processing, so this
is the lower bound). Devices: ``cpu`` and, where this onnxruntime offers it, ``cuda``; the
GPU's name is printed. Where the route runs its frames on the device (CUDA, issue 31) two
more rows time its live frame, :meth:`polrig.app.single_shot.SingleShot.live` as the worker
calls it: the grid rendered on the device at display size and the light-direction probe every 8
frames, then the colour mapping of that small grid (``render`` at step 1). Issue 22's target: >= 20 fps at full sensor with the Mueller grid on one
H100-class GPU.

    python benchmarks/bench_live_mueller.py [--frames 10] [--devices cpu,cuda] [--out FILE]
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

from benchmarks.bench_single_shot import COLOUR, FULL, gpu_name, synthetic_raw  # noqa: E402
from polrig.models import devices  # noqa: E402
from polrig.sensor.frame import Frame, FrameMeta

#: (output resolution, network binning) rows: the live view's Mueller choices.
VARIANTS = (("superpixel", 1), ("superpixel", 2), ("full", 1))
TARGET_FPS = 20.0


def frames(n: int, rng: np.random.Generator) -> list[Frame]:
    """``n`` different full-sensor colour frames (12-bit, black level 64 DN)."""
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=10000.0, gain_db=0.0, pixel_format="Mono16",
                     layout=COLOUR, bit_depth=12, black_level_dn=64.0)
    return [Frame(raw=synthetic_raw(FULL, rng, COLOUR), meta=meta) for _ in range(n)]


def run(device: str, resolution: str, binning: int, shots: list[Frame], geometry: dict, max_px: int,
        grid_on_device: bool = False) -> dict:
    """Median seconds of inference and grid render over ``shots`` (two warm-ups first); the grid
    decimated as the live view shows it (long side ``max_px``, :func:`polrig.gui.pipeline.display_step`).
    ``grid_on_device``: the device route's live frame instead
    (:meth:`polrig.app.single_shot.SingleShot.live`: the grid rendered on the device at display
    size, the probe every few frames; the render column is then the colour mapping of that
    display-size grid, as the live worker does it)."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.gui import pipeline

    model = SingleShot.open(device)
    options = SingleShotOptions.from_settings(demosaic="superpixel", resolution=resolution,
                                              network_binning=binning, sigma=False)
    infer, render = [], []
    for k, frame in enumerate([shots[0], shots[1 % len(shots)], *shots]):
        t0 = time.perf_counter()
        if grid_on_device:
            data = pipeline.PolarizationData.from_single_shot(
                model.live(frame, 0.0, options, max_display_px=max_px or None, geometry=geometry), frame)
            t1 = time.perf_counter()
            pipeline.render(data, "mueller", step=pipeline.display_step(data, "mueller", max_px))
            t2 = time.perf_counter()
        else:
            data = pipeline.PolarizationData.from_single_shot(
                model.frame(frame, 0.0, options, geometry=geometry), frame)
            t1 = time.perf_counter()
            pipeline.render(data, "mueller", step=pipeline.display_step(data, "mueller", max_px))
            t2 = time.perf_counter()
        if k >= 2:
            infer.append(t1 - t0)
            render.append(t2 - t1)
    i, r = statistics.median(infer), statistics.median(render)
    return {"device": device, "provider": model.provider, "resolution": resolution, "binning": binning,
            "path": "grid on the device" if grid_on_device else f"{model.frame_route} route, grid on the host",
            "infer_s": i, "render_s": r, "fps": 1.0 / (i + r), "frames": len(infer), "max_px": max_px}


def table(rows: list[dict], gpu: str | None) -> str:
    lines = [f"GPU: {gpu or 'none'}. Grid long side: {rows[0]['max_px'] or 'whole'} px. Medians over "
             f"{rows[0]['frames']} full-sensor colour frames after two warm-ups, warm in process; Qt's display "
             "step not included.", "",
             "| device (provider) | path | resolution | network binning | inference ms | Mueller grid render ms | fps "
             "| target |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        goal = f">= {TARGET_FPS:.0f} fps (GPU)" if r["device"] == "cuda" else ""
        lines.append(f"| {r['device']} ({r['provider']}) | {r.get('path', '')} | {r['resolution']} | {r.get('binning', 1)} | "
                     f"{1e3 * r['infer_s']:.0f} | "
                     f"{1e3 * r['render_s']:.0f} | {r['fps']:.1f} | {goal} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import onnxruntime as ort

    from polrig.app import calibrations
    from polrig.app.rig import load_rig_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10, help="timed frames per row (default 10)")
    ap.add_argument("--devices", default=None,
                    help="comma-separated devices (default: cpu, and cuda where onnxruntime offers it)")
    ap.add_argument("--max-display-px", type=int, default=None,
                    help="long side of the shown grid (default: the live view's; 0: the whole grid)")
    ap.add_argument("--out", default=None, help="also write the table to this Markdown file")
    args = ap.parse_args(argv)
    if args.max_display_px is None:
        from polrig.gui.pipeline import DEFAULT_MAX_DISPLAY_PX

        args.max_display_px = DEFAULT_MAX_DISPLAY_PX
    have_cuda = devices.CUDA in ort.get_available_providers()
    chosen = args.devices.split(",") if args.devices else (["cpu", "cuda"] if have_cuda else ["cpu"])
    geometry = calibrations.single_shot_geometry(calibrations.load_calibration(None), load_rig_config(None))
    shots = frames(max(args.frames, 2), np.random.default_rng(0))
    rows = []
    for device in chosen:
        for resolution, binning in VARIANTS:
            rows.append(run(device, resolution, binning, shots, geometry, args.max_display_px))
            print(f"{device} {resolution} binning {binning}: {rows[-1]['fps']:.1f} fps", flush=True)
        from polrig.app.single_shot import SingleShot

        if SingleShot.open(device).frame_route == "device":  # issue 31: the grid rendered on the device
            for resolution in ("superpixel", "full"):
                rows.append(run(device, resolution, 1, shots, geometry, args.max_display_px, grid_on_device=True))
                print(f"{device} {resolution} grid on the device: {rows[-1]['fps']:.1f} fps", flush=True)
    import os

    text = (table(rows, gpu_name() if "cuda" in chosen else None)
            + f"\n\n{os.cpu_count()} CPU core(s); load average (1 min) at the end: {os.getloadavg()[0]:.1f}.")
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text("# Live Mueller view at full sensor size\n\n`python "
                                          "benchmarks/bench_live_mueller.py`\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
