"""The networks' step of one single-shot frame before and after issue 31's sessions, interleaved in
one process: ``before``, a weights folder (``--before``: the graph as shipped before, with Acos)
on one session with dynamic sizes (``SingleShotModel.load(fixed_sizes=False)``, every output);
``after``, the shipped weights with the probe's and the frame's graphs (``outputs="frame"``, what
:class:`polrig.app.single_shot.SingleShot` asks) on the device's default sessions (fixed sizes on
CUDA, one dynamic-size session per graph on the CPU). Per frame: the
light-direction probe pass and the frame pass (a stage zero axis other than the training one),
as :meth:`polrig.models.runtime.SingleShotModel.reconstruct` runs them, on a simulated held-out
capture resized to ``--size``. Prints the medians of ``--rounds`` interleaved rounds (after one
warm-up each: the fixed-size sessions are created then) and the two results' largest relative
difference; on CUDA (``--device cuda``) the same for the CUDA provider, plus the CPU-vs-CUDA
parity of the ``after`` path.

    python benchmarks/bench_sessions.py [--before /tmp/oldweights] [--size 612x512] [--rounds 9]
        [--threads T] [--device cpu|cuda] [--training-axis] [--out FILE]

``--before`` folder: ``git show 5cfac96:models/weights/{single_shot.onnx,model.json}`` (the graph
before issue 31; ``benchmarks/gpu_pieces.sh`` writes it to ``.ortpieces/before``); without it
"before" is the shipped graphs on dynamic-size sessions (on CUDA: the fixed sizes' effect alone).
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parent.parent
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

from polrig.models.runtime import SingleShotModel  # noqa: E402


def capture(size: tuple[int, int]):
    import cv2

    from polrig.sim.dataset import make_sample

    s = make_sample(4, seed=31, width=128, height=128, holdout=True)
    h, w = size
    an = np.stack([[cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR) for p in c]
                   for c in s["analyzer"] * s["scale"]]).astype(np.float32)
    mask = cv2.resize(s["mask"].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    return an, s["s_in"], mask


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default=None, help="weights folder of the graph before (dynamic session; "
                    "default: the shipped graph, so only the sessions differ)")
    ap.add_argument("--size", default="612x512", help="analyzer grid HxW (default the colour sensor's superpixel grid)")
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--training-axis", action="store_true",
                    help="the training rig's stage zero axis: one frame pass, no probe")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    h, w = (int(x) for x in args.size.split("x"))
    an, s_in, mask = capture((h, w))
    axis = None if args.training_axis else (1.0, 0.0, 0.0)  # not the training axis: probe + frame pass
    models = {"before": SingleShotModel.load(args.before, threads=args.threads, device=args.device, fixed_sizes=False),
              "after": SingleShotModel.load(threads=args.threads, device=args.device)}
    kw = {"before": {}, "after": {"outputs": "frame"}}
    times = {k: [] for k in models}
    net = {k: [] for k in models}
    results = {}
    for k, m in models.items():  # warm-up: sessions created, arenas grown
        t = time.perf_counter()
        results[k] = m.reconstruct(an, s_in, mask=mask, stage_zero_axis=axis, **kw[k])[0]
        print(f"{k}: first frame {1e3 * (time.perf_counter() - t):.0f} ms", flush=True)
    for _ in range(args.rounds):
        for k, m in models.items():
            t = time.perf_counter()
            _, aux = m.reconstruct(an, s_in, mask=mask, stage_zero_axis=axis, **kw[k])
            times[k].append(time.perf_counter() - t)
            net[k].append(aux["timings_s"]["network"])
    dev = float(np.max(np.abs(results["after"] - results["before"])) / np.max(np.abs(results["before"])))
    passes = ("training axis: one frame pass" if axis is None
              else "another axis: probe + frame pass (two frame passes below 256 px)")
    title = (f"# Networks' step, {h}x{w}x3, {passes}, {models['after'].provider}, "
             f"{models['after'].provider_options}, {args.rounds} interleaved rounds (medians)")
    lines = [title, "", "| path | reconstruct ms | networks ms (probe + frame) |", "|---|---:|---:|"]
    for k in models:
        lines.append(f"| {k} | {1e3 * statistics.median(times[k]):.1f} | {1e3 * statistics.median(net[k]):.1f} |")
    ratios = [a / b for a, b in zip(net["after"], net["before"])]
    lines += ["", (f"networks after/before per round: median {statistics.median(ratios):.3f} "
                   f"(min {min(ratios):.3f}, max {max(ratios):.3f}); max |after - before| / max |before| = {dev:.2e}")]
    if args.device == "cuda":
        cpu = SingleShotModel.load(device="cpu").reconstruct(an, s_in, mask=mask, stage_zero_axis=axis,
                                                             outputs="frame")[0]
        par = float(np.max(np.abs(results["after"] - cpu)) / np.max(np.abs(cpu)))
        lines.append(f"CUDA vs CPU (after): max |cuda - cpu| / max |cpu| = {par:.2e}; notes: "
                     f"{models['after'].device_notes or 'none'}")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        pathlib.Path(args.out).write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
