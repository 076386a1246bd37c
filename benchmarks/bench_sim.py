"""Simulator timings: time per term (intersection, shadow, diffuse, specular, sensor), what
term skipping saves, and the end-to-end ``polrig sim render`` of four polarizer states.

Run: ``.venv/bin/python benchmarks/bench_sim.py [--size 512] [--repeat 3]``. Prints tables of
median wall times (seconds) over ``--repeat`` runs; nothing is asserted. Check ``uptime``
first: on a loaded machine wall times inflate several-fold.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import numpy as np


def _median(fn, repeat: int):
    out, times = None, []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def bench_terms(size: int, repeat: int) -> None:
    from polrig.sim.render import render
    from polrig.sim.scene import make_scene

    terms = ("intersection", "shadow", "specular", "diffuse", "assemble")
    print(f"\nRender terms at {size}x{size} (median of {repeat}; seconds)")
    print(f"{'scene':<16}{'mode':<9}" + "".join(f"{t:>13}" for t in terms)
          + f"{'total':>9}{'lit %':>8}{'spec evals':>12}")
    for name in ("sphere", "diffuse_sphere", "mirror_sphere", "multi", "box", "heightfield"):
        scene = make_scene(name, size, size)
        for skip in (True, False):
            runs = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                r = render(scene, 0.0, skip_terms=skip)
                runs.append((time.perf_counter() - t0, r))
            total = statistics.median(t for t, _ in runs)
            per = {t: statistics.median(r.timings_s[t] for _, r in runs) for t in terms}
            r = runs[-1][1]
            print(f"{name:<16}{'skip' if skip else 'all':<9}"
                  + "".join(f"{per[t]:>13.4f}" for t in terms)
                  + f"{total:>9.3f}{100 * r.counts['lit'] / r.counts['pixels']:>8.1f}"
                  + f"{r.counts['specular_evals']:>12d}")


def bench_sensor(size: int, repeat: int) -> None:
    from polrig.sim import create_sim_rig

    rig = create_sim_rig({"size": (size, size), "clock_speed": float("inf")})
    w = rig.world
    roi = w.full_roi
    w.render_pose(0.0)
    w.radiance_mueller(0.0)
    print(f"\nPer-grab costs at {size}x{size}, pose cached (median of {repeat}; seconds)")
    angles = iter(np.linspace(1, 179, 10 * repeat))
    _, t_state = _median(lambda: w.radiance_state(0.0, next(angles)), repeat)
    s = w.stokes_dn(0.0, 0.0, 20000.0, 0.0, roi)
    _, t_scale = _median(lambda: w.stokes_dn(0.0, 0.0, 20000.0, 0.0, roi), repeat)
    _, t_mosaic = _median(lambda: w.sensor.signal_mosaic(s, roi), repeat)
    sig = w.sensor.signal_mosaic(s, roi)
    rng = np.random.default_rng(0)
    _, t_noise = _median(lambda: w.sensor.expose(sig, exposure_us=20000.0, gain_db=0.0,
                                                 rng=rng), repeat)
    _, t_grab = _median(lambda: rig.camera.grab(), repeat)
    for label, t in (("new polarizer state (S = M S_in)", t_state),
                     ("scale to DN (cached state)", t_scale),
                     ("analyzer mosaic", t_mosaic), ("noise + quantization", t_noise),
                     ("camera.grab (cached state)", t_grab)):
        print(f"  {label:<36}{t:>9.4f}")


def bench_cli(size: int, repeat: int) -> None:
    from polrig.cli import main

    def run():
        with tempfile.TemporaryDirectory() as d:
            main(["sim", "render", "--scene", "sphere", "--size", f"{size}x{size}",
                  "--out", d])

    cpu = []

    def timed_run():
        c0 = time.process_time()
        run()
        cpu.append(time.process_time() - c0)

    _, t = _median(timed_run, repeat)
    print(f"\npolrig sim render sphere {size}x{size}, 4 states + truth files "
          f"(in-process, median of {repeat}): {t:.3f} s wall, "
          f"{statistics.median(cpu):.3f} s CPU (process time; less sensitive to machine load)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    bench_terms(a.size, a.repeat)
    bench_sensor(a.size, a.repeat)
    bench_cli(a.size, a.repeat)


if __name__ == "__main__":
    main()
