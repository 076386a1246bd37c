"""What an exposure bracket costs the single-shot route (``polrig.app.single_shot.SingleShot.state``,
``models/highlights.py``) at the full colour sensor, warm in process.

``python -m benchmarks highlights [--rounds N] [--size WxH]`` makes one polarizer state of a
synthetic 12-bit colour mosaic (``bench_single_shot.synthetic_raw``'s sphere) with a highlight
up to 40 times the saturation level, as one exposure (the highlight clipped) and as a bracket of
1, 1/16 and 1/256 of it (:func:`polrig.solve.radiometry.state_radiance`), and times the route on
each in interleaved rounds: the bracket adds a second demosaic of the exclusions (what the
reference exposure shows the networks) and the rescale of the measured highlights. Prints the
median seconds and the peak of numpy's allocations (``tracemalloc``; onnxruntime's arena is not
counted) per case and writes ``benchmarks/results/highlights.md``.
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time
import tracemalloc

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
RESULTS = HERE / "results" / "highlights.md"
FULL = (2448, 2048)


def states(shape: tuple[int, int], rng: np.random.Generator):
    """``(frame, one exposure, bracket)``: a raw frame of the scene for the route's layout and
    the state radiance of one exposure and of the bracket 1, 1/16, 1/256."""
    from bench_single_shot import synthetic_raw

    from polrig.sensor.frame import Frame, FrameMeta
    from polrig.sensor.noise import SensorModel
    from polrig.solve.radiometry import state_radiance

    model = SensorModel()
    w, h = shape
    base = synthetic_raw((h, w), rng).astype(np.float64) - 64.0
    v, u = np.mgrid[0:h, 0:w]
    spot = np.exp(-(((u - 0.45 * w) ** 2 + (v - 0.4 * h) ** 2) / (0.03 * min(h, w)) ** 2))
    signal = np.clip(base, 0, None) * (1.0 + 40.0 * spot)  # up to ~40x saturation at the spot
    exposures = [10000.0, 10000.0 / 16, 10000.0 / 256]
    frames = [[np.minimum(np.rint(signal * e / exposures[0] + 64.0), 4095).astype(np.uint16)] for e in exposures]
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=exposures[0], gain_db=0.0, pixel_format="Mono16",
                     layout="imx250myr", bit_depth=12, black_level_dn=64.0)
    frame = Frame(frames[0][0], meta)
    one = state_radiance(frames[:1], exposures[:1], model, black_level_dn=64.0)
    bracket = state_radiance(frames, exposures, model, black_level_dn=64.0)
    return frame, one, bracket


def measure(route, frame, state, options) -> tuple[float, float]:
    """Seconds and peak numpy allocation (MB) of one call of the route on ``state``."""
    from polrig.optics.mueller import polarizer_stokes

    tracemalloc.start()
    t0 = time.perf_counter()
    route.state(state, frame, polarizer_stokes(0.0), options)
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return dt, peak


def main(argv=None) -> int:
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    ap.add_argument("--size", default=f"{FULL[0]}x{FULL[1]}", help="sensor WxH (default the full sensor)")
    ap.add_argument("--out", default=str(RESULTS), help="Markdown file (default benchmarks/results/highlights.md)")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.lower().split("x"))
    frame, one, bracket = states((w, h), np.random.default_rng(0))
    route = SingleShot.open("cpu")
    options = SingleShotOptions(sigma=True)
    cases = {"one exposure (highlight clipped)": one, "bracket 1, 1/16, 1/256": bracket}
    for state in cases.values():  # warm: the model's first pass and the arena
        route.state(state, frame, np.array([1.0, 1.0, 0.0]), options)
    got: dict[str, list[tuple[float, float]]] = {k: [] for k in cases}
    for _ in range(max(1, args.rounds)):
        for name, state in cases.items():
            got[name].append(measure(route, frame, state, options))
    rows = []
    for name, vals in got.items():
        rows.append(f"| {name} | {statistics.median(v[0] for v in vals):.2f} | "
                    f"{statistics.median(v[1] for v in vals):.0f} |")
    base, br = (statistics.median(v[0] for v in vals) for vals in got.values())
    text = (f"# The single-shot route with an exposure bracket\n\n`python -m benchmarks highlights` "
            f"(benchmarks/bench_highlights.py): one state of a synthetic {w}x{h} colour mosaic with a highlight up "
            f"to 40x saturation, `SingleShot.state` with sigma on the CPU provider, warm in process, median of "
            f"{args.rounds} interleaved rounds; {int(one.excluded.sum())} samples clipped at the reference exposure, "
            f"{int(bracket.excluded.sum())} in every exposure of the bracket.\n\n| state radiance | seconds | peak numpy allocation (MB) |\n"
            "|---|---:|---:|\n" + "\n".join(rows) + f"\n\nBracket / one exposure: {br / base:.2f}x time.\n")
    print(text)
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
