"""One pass of the shipped single-shot networks, per device and setting: what the hardware does
with this network, apart from the rest of the frame.

Why: on an NVIDIA H200 (2026-11-26, ``benchmarks/results/single_shot_cuda_h200.md``) the CUDA
provider took 1.1 s of a full-sensor superpixel frame's networks, against 0.29 s on the same
machine's 16 CPU cores, and a repeated 1224x1024x3 pass 0.24 s. This separates the suspects the
next GPU lease can settle in one call: cuDNN's algorithm search (each
``cudnn_conv_algo_search``), the alternation of the light-direction probe's and the frame's
input shapes (:func:`polrig.models.runtime.probe_shape`), host <-> device copies (onnxruntime's I/O
binding with inputs and outputs kept on the GPU), and onnxruntime itself (the same networks in
PyTorch, recovered from the graph by :func:`polrig.models.recover.networks_from_weights`, on the same
device: the best alternative in the same run).

Rows, each on the full colour sensor's superpixel grid (``--size``, default 612x512 padded to
616x512) with random normalised inputs:

* ``onnxruntime <provider> [<search>]``: the first pass at the frame's shape, then the median
  over ``--rounds`` of a frame pass alternating with a probe pass (as every real frame does),
  and the probe pass's median; on CUDA also ``io binding``: the frame's pass with inputs and
  outputs on the GPU (no copies).
* ``pytorch <device>``: the recovered ``SingleShotNet`` in ``inference_mode`` (float32; on CUDA
  with ``cudnn.benchmark`` on, which the first pass pays for).

The table says which device and GPU ran it. CPU-only machines print the CPU rows (onnxruntime
and PyTorch, both with this machine's threads). ``--profile`` adds onnxruntime's own per-operator
totals of one frame pass for the first provider listed.

    python benchmarks/bench_network_pass.py [--size 612x512] [--rounds 10] [--devices cpu,cuda]
        [--no-torch] [--profile] [--out FILE]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parent.parent
sys.path.append(str(REPO))  # after PYTHONPATH: a lent machine names polrig by links (polrig_path.sh)

from benchmarks.bench_single_shot import gpu_name  # noqa: E402
from polrig.models import devices  # noqa: E402
from polrig.models.runtime import (  # noqa: E402
    WEIGHTS_DIR,
    physical_cores,
    probe_shape,
    view_directions,
)
from polrig.models.size import SIZE_MULTIPLE  # noqa: E402

#: cuDNN algorithm searches onnxruntime's CUDA provider offers (``cudnn_conv_algo_search``).
CUDA_SEARCHES = ("HEURISTIC", "DEFAULT", "EXHAUSTIVE")


def feeds(shape: tuple[int, int], colours: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Plausible normalised inputs of the graph at ``shape`` (rounded up to the size multiple)."""
    h, w = (-(-n // SIZE_MULTIPLE) * SIZE_MULTIPLE for n in shape)
    rng = np.random.default_rng(seed)
    analyzer = rng.uniform(0.05, 1.0, (1, colours, 4, h, w)).astype(np.float32)
    return {"analyzer": analyzer, "mask": np.ones((1, 1, h, w), np.float32),
            "s_in": np.array([[0.5, 0.45, 0.1]], np.float32), "wo": view_directions((h, w))[None],
            "stage_zero_axis": np.array([[0.0, -1.0, 0.0]], np.float32)}


def ort_session(provider: str, options: dict, threads: int, profile_dir: str | None = None):
    import onnxruntime as ort

    if provider not in ort.get_available_providers():
        raise RuntimeError(f"this onnxruntime offers no {provider} (it offers {', '.join(ort.get_available_providers())})")
    if provider == devices.CUDA:
        devices.load_cuda_libraries(ort)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile_dir:
        opts.enable_profiling = True
        opts.profile_file_prefix = os.path.join(profile_dir, "pass")
    sess = ort.InferenceSession(str(WEIGHTS_DIR / "single_shot.onnx"), opts, providers=[(provider, options)])
    if sess.get_providers()[0] != provider:
        raise RuntimeError(f"{provider} did not start (the session runs on {sess.get_providers()[0]})")
    return sess


def _timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def ort_row(provider: str, options: dict, frame: dict, probe: dict, rounds: int, threads: int) -> dict:
    """First pass, alternating frame/probe medians and, on CUDA, the I/O-bound frame pass (s)."""
    sess = ort_session(provider, options, threads)
    first = _timed(lambda: sess.run(None, frame))
    frame_t, probe_t = [], []
    for _ in range(rounds):
        probe_t.append(_timed(lambda: sess.run(None, probe)))
        frame_t.append(_timed(lambda: sess.run(None, frame)))
    row = {"first": first, "frame": statistics.median(frame_t), "probe": statistics.median(probe_t)}
    if provider == devices.CUDA:
        import onnxruntime as ort

        binding = sess.io_binding()
        for name, value in frame.items():
            binding.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(value, "cuda", 0))
        for out in sess.get_outputs():
            binding.bind_output(out.name, "cuda", 0)
        sess.run_with_iobinding(binding)
        bound = []
        for _ in range(rounds):
            bound.append(_timed(lambda: sess.run_with_iobinding(binding)))
        row["bound"] = statistics.median(bound)
    return row


def torch_row(device: str, frame: dict, probe: dict, rounds: int, threads: int) -> dict:
    import torch

    from polrig.models.pmmnet import SingleShotNet
    from polrig.models.recover import networks_from_weights

    torch.set_num_threads(threads)
    nets, _ = networks_from_weights(WEIGHTS_DIR)
    net = SingleShotNet(nets["pipnet"], nets["pmmnet"]).eval().to(device)
    if device == "cuda":
        torch.backends.cudnn.benchmark = True
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    as_t = lambda f: [torch.from_numpy(f[k]).to(device) for k in  # noqa: E731
                      ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")]
    tf, tp = as_t(frame), as_t(probe)

    def run(inputs):
        with torch.inference_mode():
            net(*inputs)
        sync()

    first = _timed(lambda: run(tf))
    frame_t, probe_t = [], []
    for _ in range(rounds):
        probe_t.append(_timed(lambda: run(tp)))
        frame_t.append(_timed(lambda: run(tf)))
    return {"first": first, "frame": statistics.median(frame_t), "probe": statistics.median(probe_t)}


def op_profile(provider: str, options: dict, frame: dict, threads: int) -> list[tuple[str, float, int]]:
    """onnxruntime's per-operator kernel totals (op type, ms, nodes) of one warm frame pass."""
    with tempfile.TemporaryDirectory() as d:
        sess = ort_session(provider, options, threads, profile_dir=d)
        sess.run(None, frame)
        sess.run(None, frame)
        events = json.loads(pathlib.Path(sess.end_profiling()).read_text())
    runs = [e for e in events if e.get("name") == "model_run"]
    last = runs[-1]
    ms, count = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time") and e["ts"] >= last["ts"]:
            op = e.get("args", {}).get("op_name", "?")
            ms[op] += e["dur"] / 1000.0
            count[op] += 1
    return [(op, t, count[op]) for op, t in ms.most_common()]


def render(rows: list[tuple[str, dict]], shape: tuple[int, int], probe_hw: tuple[int, int], colours: int,
           rounds: int, threads: int, profile: list | None) -> str:
    gpu = gpu_name()
    lines = [f"One pass of the single-shot networks at {shape[1]}x{shape[0]}x{colours} (the frame) and "
             f"{probe_hw[1]}x{probe_hw[0]}x{colours} (the light-direction probe), alternating as in a frame; "
             f"medians of {rounds} rounds after the first pass, warm, in process, ms. CPU threads: {threads} "
             f"({physical_cores()} physical cores). GPU: {gpu or 'none'}.", "",
             "| runtime | device | setting | first pass | frame pass | probe pass | frame pass, I/O on the GPU |",
             "|---|---|---|---:|---:|---:|---:|"]
    for label, r in rows:
        runtime, device, setting = label.split("|")
        bound = f"{1e3 * r['bound']:.1f}" if "bound" in r else ""
        if "error" in r:
            lines.append(f"| {runtime} | {device} | {setting} | {r['error']} | | | |")
            continue
        lines.append(f"| {runtime} | {device} | {setting} | {1e3 * r['first']:.1f} | {1e3 * r['frame']:.1f} | "
                     f"{1e3 * r['probe']:.1f} | {bound} |")
    if profile:
        lines += ["", "onnxruntime's kernel time per operator type, one warm frame pass:", "",
                  "| operator | ms | nodes |", "|---|---:|---:|"]
        lines += [f"| {op} | {t:.2f} | {n} |" for op, t, n in profile[:20]]
    return "\n".join(lines)


def main(argv=None) -> int:
    import onnxruntime as ort

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="612x512", help="the frame's network grid WxH (default: the full colour "
                    "sensor's superpixel grid)")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--devices", default=None, help="cpu,cuda (default: every one this onnxruntime offers)")
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: the physical cores)")
    ap.add_argument("--no-torch", action="store_true", help="leave out the PyTorch rows")
    ap.add_argument("--profile", action="store_true", help="per-operator totals of the first device's pass")
    ap.add_argument("--out", default=None, help="also write the table to this Markdown file")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    threads = args.threads or physical_cores()
    colours = int(json.loads((WEIGHTS_DIR / "model.json").read_text()).get("colours", 3))
    frame = feeds((h, w), colours)
    probe_hw = probe_shape(frame["mask"].shape[-2:]) or frame["mask"].shape[-2:]
    probe = feeds(probe_hw, colours, seed=1)
    available = ort.get_available_providers()
    wanted = args.devices.split(",") if args.devices else [d for d, p in devices.DEVICES.items() if p in available]
    rows: list[tuple[str, dict]] = []
    for device in wanted:
        provider = devices.DEVICES[device]
        settings = [(s, {"cudnn_conv_algo_search": s}) for s in CUDA_SEARCHES] if device == "cuda" else [("", {})]
        for setting, options in settings:
            try:
                rows.append((f"onnxruntime|{device}|{setting}", ort_row(provider, options, frame, probe, args.rounds,
                                                                       threads)))
            except Exception as exc:  # a provider that fails to start is a result of this benchmark
                rows.append((f"onnxruntime|{device}|{setting}", {"error": str(exc).splitlines()[0][:120]}))
            print(f"{rows[-1][0]}: {rows[-1][1]}", flush=True)
        if not args.no_torch:
            try:
                rows.append((f"pytorch|{device}|cudnn.benchmark" if device == "cuda" else f"pytorch|{device}|",
                             torch_row(device, frame, probe, args.rounds, threads)))
            except Exception as exc:
                rows.append((f"pytorch|{device}|", {"error": str(exc).splitlines()[0][:120]}))
            print(f"{rows[-1][0]}: {rows[-1][1]}", flush=True)
    profile = None
    if args.profile and wanted:
        provider = devices.DEVICES[wanted[0]]
        profile = op_profile(provider, dict(devices.CUDA_OPTIONS) if provider == devices.CUDA else {}, frame, threads)
    table = render(rows, frame["mask"].shape[-2:], probe_hw, colours, args.rounds, threads, profile)
    print(table)
    if args.out:
        pathlib.Path(args.out).write_text("# One pass of the single-shot networks\n\n"
                                          f"`python benchmarks/bench_network_pass.py {' '.join(argv or sys.argv[1:])}`"
                                          "\n\n" + table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
