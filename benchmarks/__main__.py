"""Run the benchmarks: ``python -m benchmarks [NAME ...]`` or ``python -m benchmarks NAME [options]``.

Every ``benchmarks/bench_*.py`` runs in turn as its own process (``python benchmarks/bench_x.py``
from the repository root), so one benchmark's memory and thread settings cannot skew the next.
``names`` select a subset (``dofp``, ``bench_dofp`` and ``bench_dofp.py`` all name
``bench_dofp.py``). Options this runner does not know go to the benchmark, when exactly one is
named (``python -m benchmarks continuum --models``; each benchmark's docstring lists its own).
``--list`` prints the available names. The exit status is 1 if any benchmark failed.
"""

from __future__ import annotations

import argparse
import pathlib
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parent


def available() -> dict[str, pathlib.Path]:
    return {p.stem[len("bench_"):]: p for p in sorted(HERE.glob("bench_*.py"))}


def select(names: list[str]) -> list[pathlib.Path]:
    benches = available()
    if not names:
        return list(benches.values())
    chosen = []
    for n in names:
        key = pathlib.Path(n).stem
        key = key[len("bench_"):] if key.startswith("bench_") else key
        if key not in benches:
            raise SystemExit(f"benchmarks: unknown benchmark {n!r}; available: "
                             f"{', '.join(benches)}")
        chosen.append(benches[key])
    return chosen


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0], add_help=False)
    ap.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    ap.add_argument("-h", "--help", action="store_true", help="this help; after one name, that benchmark's")
    args, options = ap.parse_known_args(argv)
    if args.help and len(args.names) != 1:
        ap.print_help()
        return 0
    if args.help:
        options = ["--help", *options]
    if args.list:
        print("\n".join(available()))
        return 0
    chosen = select(args.names)
    if options and len(chosen) != 1:
        ap.error(f"options {' '.join(options)} go to one benchmark: name exactly one")
    failed = []
    for path in chosen:
        print(f"\n=== {path.name} ===", flush=True)
        t = time.perf_counter()
        rc = subprocess.run([sys.executable, str(path), *options], cwd=REPO).returncode
        print(f"=== {path.name}: exit {rc}, {time.perf_counter() - t:.1f} s ===", flush=True)
        if rc:
            failed.append(path.name)
    if failed:
        print(f"benchmarks failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
