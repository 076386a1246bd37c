"""Throughput of the torch scene generator (polrig.models.scenes_torch) against `polrig sim dataset`'s
per-sample path (polrig.sim.dataset.make_sample), same families (default: the six training
families) and material mix, in samples per second (wall and process CPU time).

``python benchmarks/bench_scenes_torch.py [--device cpu|cuda] [--sizes 64,256] [--batches 8,32]
[--seconds 20] [--threads 2] [--families sphere,box,...] [--materials baek|train] [--no-sim]``
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import time

import torch

from polrig.models.scenes_torch import COVERED_FAMILIES, SceneGenerator
from polrig.sim.dataset import make_sample


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_torch(size: int, batch: int, device: str, seconds: float, families, mix) -> tuple[float, float, int]:
    gen = SceneGenerator(size, seed=0, device=device, families=families, material_mix=mix)
    gen.batch(batch)  # warm-up (allocator, first kernels)
    _sync(device)
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds or n < 2 * batch:
        gen.batch(batch)
        n += batch
    _sync(device)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return n / wall, n / cpu, n


def bench_sim(size: int, seconds: float, families, mix) -> tuple[float, float, int]:
    make_sample(0, seed=0, width=size, height=size, families=families, material_mix=mix)
    n, t0, c0 = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - t0 < seconds or n < 2:
        make_sample(n + 1, seed=0, width=size, height=size, families=families, material_mix=mix)
        n += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return n / wall, n / cpu, n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="64,256")
    ap.add_argument("--batches", default="8,32")
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-sim", action="store_true")
    ap.add_argument("--families", default=",".join(COVERED_FAMILIES))
    ap.add_argument("--materials", default="baek")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"load average {os.getloadavg()}, torch {torch.__version__}, threads {torch.get_num_threads()}, "
          f"device {args.device}")
    fams = tuple(args.families.split(","))
    print(f"families {', '.join(fams)}, materials {args.materials}")
    for size in map(int, args.sizes.split(",")):
        for batch in map(int, args.batches.split(",")):
            w, c, n = bench_torch(size, batch, args.device, args.seconds, fams, args.materials)
            print(f"torch {size}x{size} batch {batch}: {w:.1f} samples/s wall, {c:.1f} per CPU-s ({n} samples)")
        if not args.no_sim:
            w, c, n = bench_sim(size, args.seconds, fams, args.materials)
            print(f"sim   {size}x{size} make_sample: {w:.1f} samples/s wall, {c:.1f} per CPU-s ({n} samples)")


if __name__ == "__main__":
    main()
