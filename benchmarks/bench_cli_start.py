"""Cold start of the one-shot ``polrig`` commands: a base commit against this checkout.

Every row is a fresh ``python -m polrig ...`` process (one-shot CLI, wall time of the whole
process, cold interpreter, warm file cache): ``--version``, ``--help``, ``infer --help``,
``info SESSION`` on a tiny simulated session (64x64, one pose, reference mode) and ``infer``
on a small simulated frame (``--size``, default 128x128, CPU provider) and, with
``--full-size WxH`` (e.g. 2448x2048, the IMX250MYR's full sensor), on a full colour frame.
Bytecode is cached (``PYTHONPYCACHEPREFIX``, one folder per checkout, filled by the untimed
comparison runs), as an installed package runs: where ``PYTHONDONTWRITEBYTECODE`` is set (this
project's machine) every process would otherwise compile every module it imports (~0.8 s of
a cold ``infer``); ``--no-bytecode-cache`` measures that way. The base commit
(``--base``, default the commit before the import-light parser) runs from a temporary ``git
worktree`` checkout, this checkout from the repository; each is named ``polrig`` by a folder of
links first on PYTHONPATH (as benchmarks/polrig_path.sh does), so neither reaches the other's
modules through the editable install. Rounds interleave base and head (the order alternates
per round); the medians and the per-round ratio's median are reported. The two checkouts'
``--help`` pages (every command and sub-command) and their ``--version``, ``info`` and
``infer --help`` output, and the EXR and preview PNGs every ``infer`` row writes (both from
one copy of this checkout's weights folder, as the EXR header names the model's path), are
compared byte for byte.

    python -m benchmarks cli_start
    python benchmarks/bench_cli_start.py --rounds 7 --base 9c422a5 --out benchmarks/results/cli_start.md
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

REPO = pathlib.Path(__file__).resolve().parent.parent
#: The commit before the import-light parser (branch ``clistart``): the default baseline.
BASELINE = "9c422a5"
#: Top-level folders installed as subpackages of polrig (pyproject.toml package-dir).
SUBPACKAGES = ("models", "sim", "calibration", "drivers")

#: Prints every (sub)command's help page: the before/after comparison of ``--help``.
HELP_PAGES = """
import argparse, polrig.cli
def walk(p, path):
    print("#####", " ".join(path)); p.print_help()
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                walk(sp, path + [name])
walk(polrig.cli.build_parser(), ["polrig"])
"""


def shim(checkout: pathlib.Path, folder: pathlib.Path) -> dict[str, str]:
    """Environment naming ``checkout`` ``polrig``: a folder of links (its ``polrig/*`` and the
    top-level subpackages) first on PYTHONPATH."""
    pkg = folder / "polrig"
    pkg.mkdir(parents=True)
    for f in (checkout / "polrig").iterdir():
        (pkg / f.name).symlink_to(f)
    for d in SUBPACKAGES:
        (pkg / d).symlink_to(checkout / d)
    return {**os.environ, "PYTHONPATH": str(folder), "COLUMNS": "100", "POLRIG_DEBUG": ""}


def cache_bytecode(env: dict[str, str], folder: pathlib.Path) -> dict[str, str]:
    """``env`` with compiled modules written to and read from ``folder``."""
    out = {k: v for k, v in env.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {**out, "PYTHONPYCACHEPREFIX": str(folder)}


def run(env: dict[str, str], args: list[str], cwd: pathlib.Path) -> tuple[float, str]:
    """Wall seconds of one ``python -m polrig ARGS`` process, and its stdout."""
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "polrig", *args], env=env, cwd=cwd,
                         capture_output=True, text=True, timeout=600)
    dt = time.perf_counter() - t
    if out.returncode != 0:
        raise SystemExit(f"polrig {' '.join(args)} failed ({out.returncode}): {out.stderr.strip()}")
    return dt, out.stdout


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default=BASELINE, help=f"base commit (default {BASELINE})")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    ap.add_argument("--size", default="128x128", help="infer frame size WxH (default 128x128)")
    ap.add_argument("--full-size", default="", help="also infer a full frame of this size WxH "
                    "(e.g. 2448x2048; default none)")
    ap.add_argument("--no-bytecode-cache", action="store_true",
                    help="compile every module in every process (PYTHONDONTWRITEBYTECODE as set)")
    ap.add_argument("--out", type=pathlib.Path, default=None, help="also write the table here (.md)")
    args = ap.parse_args(argv)

    tmp = pathlib.Path(tempfile.mkdtemp(prefix="polrig-cli-start-"))
    base_tree = tmp / "base"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(base_tree),
                    args.base], check=True)
    try:
        base_rev = subprocess.run(["git", "-C", str(base_tree), "rev-parse", "--short", "HEAD"],
                                  capture_output=True, text=True, check=True).stdout.strip()
        head_rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                                  capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--", "polrig",
                                *SUBPACKAGES], capture_output=True, text=True).stdout.strip()
        envs = {"base": shim(base_tree, tmp / "shim-base"), "head": shim(REPO, tmp / "shim-head")}
        if not args.no_bytecode_cache:
            envs = {v: cache_bytecode(env, tmp / f"pycache-{v}") for v, env in envs.items()}
        work = tmp / "work"
        work.mkdir()
        for name, env in envs.items():  # each names its own checkout
            where = subprocess.run([sys.executable, "-c", "import polrig.cli, polrig.sim; "
                                    "print(polrig.cli.__file__, polrig.sim.__file__)"],
                                   env=env, cwd=work, capture_output=True, text=True, check=True)
            root = base_tree if name == "base" else REPO
            assert all(str(root) in p for p in map(str, map(lambda s: pathlib.Path(s).resolve(),
                                                            where.stdout.split()))), where.stdout

        # inputs, made by this checkout: a tiny session and a small frame
        cfg = work / "rig.toml"
        cfg.write_text('[sim]\nsize = "64x64"\nsensor = "imx250mzr"\nclock_speed = inf\nseed = 11\n'
                       'scene = "box"\n')
        session = work / "session"
        run(envs["head"], ["capture", "--poses", "0", "--mode", "reference", "--config", str(cfg),
                           "--out", str(session), "--no-progress"], work)
        frames = {}
        for size in filter(None, (args.size, args.full_size)):
            render = work / f"render-{size}"
            run(envs["head"], ["sim", "render", "--size", size, "--states", "0", "--out",
                               str(render), "--no-exr"], work)
            frames[size] = next(p for p in sorted(render.iterdir())
                                if p.suffix in (".png", ".tiff", ".tif", ".npy"))

        rows = {"--version": ["--version"], "--help": ["--help"], "infer --help": ["infer", "--help"],
                "info SESSION (64x64, 1 pose)": ["info", str(session)]}
        for size, frame in frames.items():
            rows[f"infer FRAME ({size}, cpu)"] = ["infer", str(frame), "--state-deg", "0",
                                                  "--device", "cpu", "--out", "{out}"]
        same = {}
        for label in ("--version", "infer --help", "info SESSION (64x64, 1 pose)"):
            outs = [run(envs[v], rows[label], work)[1] for v in ("base", "head")]
            same[label] = outs[0] == outs[1]
        # the files infer writes (no time stamps in them), from one weights folder: the EXR
        # header names the model's path, which differs between the two checkouts
        weights = work / "weights"
        shutil.copytree(REPO / "models" / "weights", weights)
        for label, cmd in rows.items():
            if cmd[0] != "infer" or "--help" in cmd:
                continue
            written = []
            for v in ("base", "head"):
                out = work / f"compare_{v}" / "m.exr"
                out.parent.mkdir()
                run(envs[v], [c.replace("{out}", str(out)) for c in cmd] + ["--weights", str(weights)],
                    work)
                written.append({p.name: p.read_bytes() for p in sorted(out.parent.iterdir())})
                shutil.rmtree(out.parent)
            same[f"{label[:-1]}: EXR + previews)"] = written[0] == written[1] and len(written[0]) == 4
        pages = [subprocess.run([sys.executable, "-c", HELP_PAGES], env=envs[v], cwd=work,
                                capture_output=True, text=True, check=True).stdout
                 for v in ("base", "head")]
        same["every --help page"] = pages[0] == pages[1]
        n_pages = pages[1].count("#####")

        times: dict[str, dict[str, list[float]]] = {r: {"base": [], "head": []} for r in rows}
        for rnd in range(args.rounds):
            order = ("base", "head") if rnd % 2 == 0 else ("head", "base")
            for label, cmd in rows.items():
                for v in order:
                    out = work / f"infer_{v}_{rnd}" / "m.exr"  # a fresh folder: nothing to overwrite
                    out.parent.mkdir()
                    dt, _ = run(envs[v], [c.replace("{out}", str(out)) for c in cmd], work)
                    times[label][v].append(dt)
                    shutil.rmtree(out.parent)
            print(f"round {rnd + 1}/{args.rounds} done", flush=True)

        lines = [f"# `polrig` cold start, one-shot CLI: base {base_rev} vs head {head_rev}"
                 f"{' (+ uncommitted changes)' if dirty else ''}", "",
                 f"Fresh `python -m polrig` processes (wall time, cold interpreter, warm file "
                 f"cache, {'no bytecode cache' if args.no_bytecode_cache else 'cached bytecode'}), "
                 f"{args.rounds} interleaved rounds (order alternating), medians; "
                 f"{platform.machine()}, {os.cpu_count()} CPU(s) visible, Python "
                 f"{platform.python_version()}; `python benchmarks/bench_cli_start.py`.", "",
                 "| command | base median (s) | head median (s) | saved (s) | head/base, median of rounds |",
                 "|---|---|---|---|---|"]
        for label in rows:
            b, h = times[label]["base"], times[label]["head"]
            ratio = statistics.median(hh / bb for hh, bb in zip(h, b))
            lines.append(f"| `polrig {label}` | {statistics.median(b):.2f} | {statistics.median(h):.2f} "
                         f"| {statistics.median(b) - statistics.median(h):.2f} | {ratio:.2f} |")
        lines += ["", "Output compared byte for byte, base against head: " + "; ".join(
            f"{k}{f' ({n_pages} pages)' if k == 'every --help page' else ''}: "
            f"{'identical' if v else 'DIFFERENT'}" for k, v in same.items()) + "."]
        text = "\n".join(lines) + "\n"
        print(text)
        if args.out:
            args.out.write_text(text)
        return 0 if all(same.values()) else 1
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(base_tree)],
                       check=False)
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
