"""The command line, ``python -m polrig.models.continuum``.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from polrig.models.continuum.report import plot_from_json
from polrig.models.continuum.run import fit_highlight_factor, joint_compare, min_states_compare, run
from polrig.models.continuum.sets import (
    ADAPTIVE_TARGETS,
    OFFSETS_DEG,
    RIG_POSES_DEG,
    RIG_SCENES,
    RIG_THREE,
    RIG_TWO,
    SETS,
)


def _offsets(text: str | None, n: int) -> tuple[int, ...] | None:
    from polrig.errors import ConfigError

    if text is None:
        return None
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"give {n} comma-separated offsets in degrees, got {text!r}") from None
    if len(vals) != n or vals[0] != 0 or any(v not in OFFSETS_DEG for v in vals):
        raise ConfigError(f"give {n} offsets from {OFFSETS_DEG}, the first 0, got {text!r}")
    return vals


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.continuum", description=sys.modules[__package__].__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=16, help="samples per held-out set (default 16)")
    ap.add_argument("--search-count", type=int, default=16,
                    help="samples of the state search's all-family set (half as many of its held-out families)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated, of: {', '.join(SETS)}")
    ap.add_argument("--root", default="runs/continuum", help="where the sets are generated (default runs/continuum)")
    ap.add_argument("--out", default=None, help="Markdown file for the tables (the numbers go next to it as .json)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--seed", type=int, default=0, help="noise seed of the rendered states' frames")
    ap.add_argument("--two", default=None, help="the 2-state offsets instead of searching, e.g. 0,90")
    ap.add_argument("--three", default=None, help="the 3-state offsets instead of searching, e.g. 0,60,120")
    ap.add_argument("--targets", default=",".join(f"{t:g}" for t in ADAPTIVE_TARGETS),
                    help="the adaptive capture's relative sigma targets, comma separated (default "
                         + ",".join(f"{t:g}" for t in ADAPTIVE_TARGETS) + ")")
    ap.add_argument("--rig-scenes", default=None, nargs="?", const=",".join(RIG_SCENES),
                    help="score the default rig's named scenes at its size instead of the held-out sets "
                         f"(default {','.join(RIG_SCENES)}; states --two/--three default "
                         f"{','.join(map(str, RIG_TWO))} and {','.join(map(str, RIG_THREE))}, not searched)")
    ap.add_argument("--rig-poses", default=",".join(f"{p:g}" for p in RIG_POSES_DEG),
                    help="turntable angles (deg) of --rig-scenes, one sample each (default "
                         + ",".join(f"{p:g}" for p in RIG_POSES_DEG) + ")")
    ap.add_argument("--size", type=int, default=None,
                    help="image side of --rig-scenes (default: the rig's analyzer grid, 128)")
    ap.add_argument("--models-only", action="store_true",
                    help="only the lower-order model comparison at two states (--two, default "
                         + ",".join(map(str, RIG_TWO)) + "): single-shot, hybrid 2, hybrid 2 + models")
    ap.add_argument("--plot-only", metavar="JSON", default=None,
                    help="only draw the accuracy-against-time plot of a results JSON (written next to it as .png)")
    ap.add_argument("--fit-highlights", action="store_true",
                    help="only fit the sigma factor at the highlights a bracket measured "
                         "(polrig.models.highlights.SIGMA_FACTOR) on the calibration scenes, --count samples")
    ap.add_argument("--joint-compare", action="store_true",
                    help="only the per-element prior against the joint one (uncertainty.json's joint_prior): the "
                         "two-state model test's false acceptance, coverage and PSNR at 1 to 4 states")
    ap.add_argument("--min-states-compare", action="store_true",
                    help="only the adaptive capture at the capture's least number of states before a pose may stop "
                         "and at 3, on --rig-scenes (default all) at each of --targets")
    args = ap.parse_args(argv)
    if args.min_states_compare:
        scenes = RIG_SCENES if args.rig_scenes is None else tuple(n for n in args.rig_scenes.split(",") if n)
        return run_main(ap.prog, lambda: (min_states_compare(args.out, scenes=scenes, poses=_poses(args.rig_poses),
                                                             size=args.size, targets=_targets(args.targets),
                                                             seed=args.seed, weights_dir=args.weights), 0)[1])
    if args.joint_compare:
        return run_main(ap.prog, lambda: (joint_compare(args.root, args.out, count=args.count,
                                                        sets=[s for s in args.sets.split(",") if s], seed=args.seed,
                                                        weights_dir=args.weights, two=_offsets(args.two, 2),
                                                        three=_offsets(args.three, 3),
                                                        rig_scenes=None if args.rig_scenes is None else
                                                        [n for n in args.rig_scenes.split(",") if n],
                                                        rig_poses=_poses(args.rig_poses), size=args.size), 0)[1])
    if args.fit_highlights:
        from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

        return run_main(ap.prog, lambda: fit_highlight_factor(
            args.root, SingleShotModel.load(args.weights or WEIGHTS_DIR), count=args.count, seed=args.seed) and 0)
    if args.plot_only is not None:
        return run_main(ap.prog, lambda: print(plot_from_json(args.plot_only)) or 0)
    return run_main(ap.prog, lambda: (run(args.root, args.out, count=args.count, search_count=args.search_count,
                                          sets=[s for s in args.sets.split(",") if s], seed=args.seed,
                                          weights_dir=args.weights, two=_offsets(args.two, 2),
                                          three=_offsets(args.three, 3), targets=_targets(args.targets),
                                          rig_scenes=None if args.rig_scenes is None else
                                          [n for n in args.rig_scenes.split(",") if n],
                                          rig_poses=_poses(args.rig_poses), size=args.size,
                                          only_models=args.models_only), 0)[1])


def _poses(text: str) -> tuple[float, ...]:
    from polrig.errors import ConfigError

    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"--rig-poses: give turntable angles in degrees, comma separated, got {text!r}") from None


def _targets(text: str) -> tuple[float, ...]:
    from polrig.errors import ConfigError

    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--targets: give relative sigmas in (0, 1], comma separated, got {text!r}") from None
    if not vals or not all(0 < v <= 1 for v in vals):
        raise ConfigError(f"--targets: give relative sigmas in (0, 1], comma separated, got {text!r}")
    return vals
