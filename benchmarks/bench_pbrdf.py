"""Timing of polrig.optics.pbrdf on image-sized pixel stacks; prints a table.

Usage: ``python benchmarks/bench_pbrdf.py [--size 512] [--repeat 5]``. Times are the best of
``repeat`` runs (wall clock and process CPU time, float64). Scenes: ``lit`` has every pixel valid (normals facing a
camera on +Z, light and view above the horizon), ``mixed`` has random normals so that about
a quarter of the pixels are valid (invalid pixels cost only the gather/scatter).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from polrig.optics import pbrdf


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene(kind: str, size: int, rng: np.random.Generator):
    shape = (size, size, 3)
    if kind == "lit":
        normal = _unit(rng.normal(size=shape) * [0.3, 0.3, 0.0] + [0, 0, 1])
        wi = _unit(rng.normal(size=shape) * [0.3, 0.3, 0.0] + [0.3, 0, 1])
        wo = _unit(rng.normal(size=shape) * [0.1, 0.1, 0.0] + [0, 0, 1])
    else:
        normal, wi, wo = (_unit(rng.normal(size=shape)) for _ in range(3))
    return normal, wi, wo


def best_of(fn, repeat):
    """Best wall-clock and best CPU (process) time in seconds; the CPU time is the robust one
    on a shared machine (numpy's element-wise work here is single-threaded)."""
    wall, cpu = [], []
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    n = args.size
    alpha = rng.uniform(0.05, 0.6, size=(n, n))
    kd_rgb = rng.uniform(size=(n, n, 3))
    axes = dict(stage_zero_axis=np.array([0.0, 1.0, 0.0]), camera_x_axis=np.array([1.0, 0.0, 0.0]))
    print(f"polrig.optics.pbrdf, {n}x{n} pixels, float64, best of {args.repeat}")
    a, b = rng.random(n * n), rng.random(n * n)
    ref = best_of(lambda: a * b, 50)[0]
    print(f"machine reference: one {n}x{n} float64 multiply takes {1e6 * ref:.0f} us "
          "(about 70 us on an idle machine of this project; scale the table by it under load)")
    print(f"{'scene':6} {'valid':>6}  {'call':44} {'wall ms':>8} {'cpu ms':>8}")
    for kind in ("lit", "mixed"):
        normal, wi, wo = scene(kind, n, rng)
        frac = pbrdf.visible(normal, wi, wo).mean()
        cases = [
            ("mueller 4x4 mono, specular", lambda: pbrdf.mueller(normal, wi, wo, kd=0.5, alpha=alpha,
                                                                  components=("specular",))),
            ("mueller 4x4 mono, diffuse", lambda: pbrdf.mueller(normal, wi, wo, kd=0.5, alpha=alpha,
                                                                 components=("diffuse",))),
            ("mueller 4x4 RGB, both", lambda: pbrdf.mueller(normal, wi, wo, kd=kd_rgb, alpha=alpha)),
            ("linear_rig_mueller mono, specular", lambda: pbrdf.linear_rig_mueller(
                normal, wi, wo, kd=0.5, alpha=alpha, components=("specular",), **axes)),
            ("linear_rig_mueller mono, diffuse", lambda: pbrdf.linear_rig_mueller(
                normal, wi, wo, kd=0.5, alpha=alpha, components=("diffuse",), **axes)),
            ("linear_rig_mueller RGB, both", lambda: pbrdf.linear_rig_mueller(
                normal, wi, wo, kd=kd_rgb, alpha=alpha, **axes)),
            ("specular_diffuse_blocks", lambda: pbrdf.specular_diffuse_blocks(normal, wi, wo, alpha=alpha, **axes)),
        ]
        for name, fn in cases:
            wall, cpu = best_of(fn, args.repeat)
            print(f"{kind:6} {frac:6.2f}  {name:44} {1e3 * wall:8.1f} {1e3 * cpu:8.1f}")


if __name__ == "__main__":
    main()
