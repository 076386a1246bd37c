"""Parameter maps with sigma (:func:`polrig.optics.parameters.image_maps`, ``polrig analyze``):
time and peak memory, the current implementation against the baseline, in the same run.

The baseline is ``polrig/optics/parameters.py`` at commit :data:`BASELINE_COMMIT` (the sigma
of ``sv1``, ``sv2`` and the decomposition by forward differences: the whole decomposition run
nine more times), read with ``git show`` and imported in place of the current module. Every
measurement runs in its own process, so that one cannot warm or fragment the other's memory:

* **warm in-process**: the process builds the image, calls ``image_maps`` once on a small image
  (imports, first-call costs), then times one ``image_maps(mueller, sigma)`` call. Memory: the
  rise of the process's peak resident set during that call (``VmHWM`` after resetting it to
  the current RSS), i.e. what the call needs beyond its inputs, the float32 output maps included
  (30 float32 planes and one uint8 of ``C x H x W``; the table gives their size).
* **one-shot CLI**: ``polrig analyze RESULT.exr --out MAPS.exr`` (the CLI's ``main`` in a fresh
  interpreter; the baseline module swapped in before the command imports it): wall time of the
  whole process (start, imports, reading and writing the EXRs) and its peak resident set
  (``wait4``).

Implementations: ``baseline``; ``current`` (the default thread count,
:data:`polrig.optics.parameters.DEFAULT_WORKERS`: up to 4, at most the CPUs this process may
use); ``current-1t`` (one thread: the algorithmic gain alone). Rounds are interleaved (each round
runs every implementation, in alternating order) and the table reports medians.

Data: a synthetic Mueller result of the rig's sizes (512x512, and the IMX250's full
2448x2048 in colour, ``C = 3``, and mono, ``C = 1``): an isotropic depolarizer, a linear
retarder and a linear diattenuator whose parameters vary smoothly across the image (the
decomposition's model: every map is defined), about 1000 DN, per-element sigma
``2 + 0.002 m00`` DN and noise drawn with it. The results of the two implementations are
compared on the first size (maps bit for bit; sigma to the baseline's finite-difference
truncation error).

    python -m benchmarks analyze            # everything (long at full size: see --help)
    python benchmarks/bench_analyze.py --sizes 512 --rounds 3 --out benchmarks/results/analyze.md
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
#: The parameters module before the analytic sigma (forward differences through 9 re-runs).
BASELINE_COMMIT = "59af05b"
SIZES = {"512": (512, 512), "full": (2048, 2448)}
IMPLS = ("baseline", "current", "current-1t")


# -- data ---------------------------------------------------------------------------------------
def synthetic_result(c: int, h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(mueller, sigma)`` float32 ``(C, 3, 3, H, W)`` (module docstring). The parameters are
    set on a 128x128 grid and repeated over the image (cheap at full size); the noise is per
    pixel."""
    g = 128
    v, u = np.mgrid[:g, :g] / g
    ret = np.deg2rad(10.0 + 160.0 * u)
    axis = np.deg2rad(180.0 * v)
    dep = 0.6 + 0.35 * (1 - v)
    dmag, dang = 0.3 * u * v, np.pi * (u + v)
    # linear retarder block (retarder_at's), isotropic depolarizer, linear diattenuator
    from polrig.optics import mueller as mu

    r3 = mu.linear_block(mu.retarder_at(axis, ret))
    dvec = np.stack([dmag * np.cos(dang), dmag * np.sin(dang)], -1)
    k = np.sqrt(1 - dmag ** 2)
    md = np.zeros((g, g, 3, 3))
    md[..., 0, 0] = 1.0
    md[..., 0, 1:], md[..., 1:, 0] = dvec, dvec
    outer = dvec[..., :, None] * dvec[..., None, :]
    md[..., 1:, 1:] = k[..., None, None] * np.eye(2) + outer / (1 + k)[..., None, None]
    delta = np.zeros((g, g, 3, 3))
    delta[..., 0, 0] = 1.0
    delta[..., 1, 1] = delta[..., 2, 2] = dep
    blocks = np.moveaxis(1000.0 * (delta @ r3 @ md), (-2, -1), (0, 1))  # (3, 3, g, g)
    rng = np.random.default_rng(seed)
    yy, xx = (np.arange(h) * g) // h, (np.arange(w) * g) // w
    out = np.empty((c, 3, 3, h, w), np.float32)
    sig = np.empty((c, 3, 3, h, w), np.float32)
    for ch in range(c):
        base = (blocks * (0.7 + 0.15 * ch))[:, :, yy][:, :, :, xx].astype(np.float32)
        s = (2.0 + 0.002 * base[0, 0]).astype(np.float32)
        sig[ch] = s
        out[ch] = base + rng.standard_normal(base.shape, dtype=np.float32) * s
    return out, sig


def load_baseline(path: pathlib.Path):
    """Import the baseline module from ``path`` as ``polrig.optics.parameters`` (the CLI's
    ``from polrig.optics import parameters`` then gets it)."""
    import importlib.util

    import polrig.optics

    spec = importlib.util.spec_from_file_location("polrig.optics.parameters", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["polrig.optics.parameters"] = mod
    spec.loader.exec_module(mod)
    polrig.optics.parameters = mod
    return mod


def _impl(name: str, baseline: pathlib.Path):
    if name == "baseline":
        return load_baseline(baseline).image_maps
    from polrig.optics import parameters

    if name == "current-1t":
        return lambda m, s: parameters.image_maps(m, s, workers=1)
    return parameters.image_maps


def _status_mib(key: str) -> float:
    """``VmRSS`` or ``VmHWM`` (peak) of this process from ``/proc/self/status``, MiB."""
    for line in pathlib.Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024.0
    raise KeyError(key)


def _reset_peak() -> float:
    """Reset the kernel's peak-RSS mark (``VmHWM``; ``clear_refs`` 5, Linux 4.0+) to the current
    RSS, which is returned (MiB)."""
    import ctypes
    import gc

    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)  # hand freed heap back: the rise is the call's own
    pathlib.Path("/proc/self/clear_refs").write_text("5")
    return _status_mib("VmRSS")


# -- children -----------------------------------------------------------------------------------
def child_warm(impl: str, c: int, h: int, w: int, baseline: pathlib.Path) -> dict:
    fn = _impl(impl, baseline)
    small = synthetic_result(c, 16, 16, seed=1)
    fn(*small)
    m, s = synthetic_result(c, h, w)
    before = _reset_peak()
    t = time.perf_counter()
    out = fn(m, s)
    seconds = time.perf_counter() - t
    planes = sum(v.nbytes for v in (*out.values.values(), *out.sigma.values())) + out.flags.nbytes
    return {"seconds": seconds, "peak_rise_mib": _status_mib("VmHWM") - before,
            "output_mib": planes / 2 ** 20}


def child_write(c: int, h: int, w: int, path: str) -> dict:
    from polrig.formats.exr import element_planes, write_mueller_exr

    m, s = synthetic_result(c, h, w)
    write_mueller_exr(path, m, extra=element_planes("sigma", s))
    return {"bytes": os.path.getsize(path)}


def child_cli(impl: str, src: str, out: str, baseline: pathlib.Path) -> int:
    if impl == "baseline":
        load_baseline(baseline)
    elif impl == "current-1t":
        from polrig.optics import parameters

        parameters.DEFAULT_WORKERS = 1
    from polrig.cli import main

    return main(["analyze", src, "--out", out])


def child_compare(c: int, h: int, w: int, baseline: pathlib.Path) -> dict:
    from polrig.optics import parameters as cur

    m, s = synthetic_result(c, h, w)
    a = cur.image_maps(m, s)
    b = load_baseline(baseline).image_maps(m, s)
    values_equal = all(np.array_equal(a.values[n], b.values[n], equal_nan=True) for n in cur.MAPS)
    worst, name = 0.0, ""
    rels = []
    for n in cur.MAPS:
        x, y = a.sigma[n].astype(np.float64), b.sigma[n].astype(np.float64)
        ok = np.isfinite(x) & np.isfinite(y) & (y > 0)
        rel = np.abs(x[ok] - y[ok]) / y[ok]
        rels.append(rel)
        if rel.size and rel.max() > worst:
            worst, name = float(rel.max()), n
    allrel = np.concatenate(rels)
    return {"values_bitwise_equal": bool(values_equal),
            "flags_equal": bool(np.array_equal(a.flags, b.flags)),
            "sigma_max_rel": worst, "sigma_max_rel_map": name,
            "sigma_median_rel": float(np.median(allrel)),
            "sigma_p999_rel": float(np.quantile(allrel, 0.999))}


# -- the parent ---------------------------------------------------------------------------------
def _run_child(args: list[str]) -> tuple[dict, float, float]:
    """Run this file with ``args``; ``(its JSON line, wall seconds, peak RSS MiB)``."""
    t = time.perf_counter()
    p = subprocess.Popen([sys.executable, __file__, *args], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t
    out, err = p.stdout.read(), p.stderr.read()
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode:
        raise RuntimeError(f"child {args} failed ({p.returncode}):\n{err[-3000:]}")
    lines = [ln for ln in out.splitlines() if ln.startswith("{")]
    return (json.loads(lines[-1]) if lines else {}), wall, usage.ru_maxrss / 1024.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="512,full", help="512 and/or full (2448x2048)")
    ap.add_argument("--channels", default="1,3", help="colour planes: 1 (mono), 3 (colour)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds at 512x512")
    ap.add_argument("--full-rounds", type=int, default=1,
                    help="interleaved rounds at full size (the baseline takes minutes there)")
    ap.add_argument("--impls", default=",".join(IMPLS), help="implementations at 512x512")
    ap.add_argument("--full-impls", default="baseline,current",
                    help="implementations at full size")
    ap.add_argument("--modes", default="warm,cli", help="warm (in-process) and/or cli (one-shot)")
    ap.add_argument("--out", type=pathlib.Path, default=None, help="write the table (markdown)")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--baseline-file", type=pathlib.Path, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    if a.child:
        kind, rest = a.child[0], a.child[1:]
        if kind == "warm":
            res = child_warm(rest[0], *map(int, rest[1:4]), a.baseline_file)
        elif kind == "write":
            res = child_write(*map(int, rest[:3]), rest[3])
        elif kind == "cli":
            child_cli(rest[0], rest[1], rest[2], a.baseline_file)
            res = {}
        else:
            res = child_compare(*map(int, rest[:3]), a.baseline_file)
        print(json.dumps(res))
        return 0

    modes = [m for m in a.modes.split(",") if m]
    with tempfile.TemporaryDirectory(prefix="bench_analyze_") as tmp:
        tmp = pathlib.Path(tmp)
        base = tmp / "parameters_baseline.py"
        base.write_text(subprocess.run(
            ["git", "show", f"{BASELINE_COMMIT}:polrig/optics/parameters.py"], cwd=REPO,
            check=True, capture_output=True, text=True).stdout)
        bf = ["--baseline-file", str(base)]
        from polrig.optics.parameters import DEFAULT_WORKERS

        machine = (f"Machine: {platform.processor() or platform.machine()}, "
                   f"{len(os.sched_getaffinity(0))} CPUs usable (load average at start "
                   f"{os.getloadavg()[0]:.1f}); current = {DEFAULT_WORKERS} thread(s); "
                   f"baseline = `polrig/optics/parameters.py` at {BASELINE_COMMIT}; "
                   f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.")
        lines = ["# `python -m benchmarks analyze`: parameter maps with sigma", "", machine, ""]
        first = a.sizes.split(",")[0]
        if "baseline" in (a.impls if first == "512" else a.full_impls):
            h, w = SIZES[first]
            cmp, _, _ = _run_child(["--child", "compare", "1", str(h), str(w), *bf])
            equality = (f"Equality at {w}x{h} mono: maps bit for bit "
                        f"{cmp['values_bitwise_equal']}, flags equal {cmp['flags_equal']}; sigma relative to the baseline's: "
                        f"median {cmp['sigma_median_rel']:.1e}, 99.9 % "
                        f"{cmp['sigma_p999_rel']:.1e}, max {cmp['sigma_max_rel']:.1e} "
                        f"({cmp['sigma_max_rel_map']}; the baseline's forward-difference "
                        f"truncation error)")
            lines += [equality, ""]
            print(lines[-2], flush=True)
        header = ("| size | C | mode | rounds | " + " | ".join(f"{i} s" for i in IMPLS)
                  + " | speed-up | " + " | ".join(f"{i} MiB" for i in IMPLS) + " | outputs MiB |")
        lines += [header, "|---" * (4 + 2 * len(IMPLS) + 2) + "|"]
        for size in a.sizes.split(","):
            h, w = SIZES[size]
            rounds = a.rounds if size == "512" else a.full_rounds
            impls = [i for i in (a.impls if size == "512" else a.full_impls).split(",") if i]
            for c in map(int, a.channels.split(",")):
                for mode in modes:
                    src = tmp / f"in_{size}_{c}.exr"
                    if mode == "cli" and not src.exists():
                        _run_child(["--child", "write", str(c), str(h), str(w), str(src)])
                    outputs = ""
                    secs = {i: [] for i in impls}
                    mem = {i: [] for i in impls}
                    for r in range(rounds):
                        for i in (impls if r % 2 == 0 else impls[::-1]):
                            if mode == "warm":
                                res, _, _ = _run_child(["--child", "warm", i, str(c), str(h),
                                                        str(w), *bf])
                                secs[i].append(res["seconds"])
                                mem[i].append(res["peak_rise_mib"])
                                outputs = f"{res['output_mib']:.0f}"
                            else:
                                _, wall, rss = _run_child(["--child", "cli", i, str(src),
                                                           str(tmp / "out.exr"), *bf])
                                secs[i].append(wall)
                                mem[i].append(rss)
                            print(f"{size} C={c} {mode} round {r} {i}: {secs[i][-1]:.2f} s, "
                                  f"{mem[i][-1]:.0f} MiB", flush=True)
                    med = {i: statistics.median(secs[i]) for i in impls}
                    mm = {i: statistics.median(mem[i]) for i in impls}
                    speed = (f"{med['baseline'] / med['current']:.1f}x"
                             if "baseline" in med and "current" in med else "")
                    label = "warm in-process" if mode == "warm" else "one-shot CLI"
                    lines.append(f"| {w}x{h} | {c} | {label} | {rounds} | "
                                 + " | ".join(f"{med[i]:.2f}" if i in med else "" for i in IMPLS)
                                 + f" | {speed} | "
                                 + " | ".join(f"{mm[i]:.0f}" if i in mm else "" for i in IMPLS)
                                 + f" | {outputs} |")
                    print(lines[-1], flush=True)
    note = ("Memory: warm in-process = rise of the peak RSS during the call (beyond the inputs; "
            "includes the float32 outputs); one-shot CLI = the process's peak RSS (inputs, "
            "outputs, EXR buffers, interpreter).")
    lines += ["", note]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out is not None:
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
