"""``polrig reconstruct SESSION... | --from-list FILE``: re-process sessions' raw frames into new revisions.

Raw frames are read (their checksums verified first) and never modified; results go to
``<capture>/<revision>/`` and the manifest records the revision's settings. Every session's
lock is held while it runs (a session another process writes is refused, exit 1). A capture
whose files are damaged is marked ``failed`` in the revision with its reason and the others
are processed; the command then exits 1 with one line naming the failed captures (as
``polrig info`` exits 1 on the same damage). A ``--calibration`` set that was not calibrated
on a session's camera (sensor size, layout, or a readout outside its calibrated area) is
refused before any revision exists (exit 2,
:func:`polrig.app.processing.check_calibration_fits`).

Serial in this process by default; ``--workers N`` runs one task per capture on a local Dask
cluster of N single-threaded worker processes, ``--scheduler ADDRESS`` on a running Dask
scheduler's workers (:mod:`polrig.app.cluster`; the ``cluster`` extra). The results are the
same bytes either way. After Ctrl-C, running the same command again continues the
interrupted revisions with the captures still pending.
"""

from __future__ import annotations

import argparse
import sys

from polrig.choices import DEFAULT_PRIOR_SCALE, DEMOSAIC_METHODS
from polrig.formats.argcheck import int_range


def register(sub: argparse._SubParsersAction) -> None:
    from polrig.cli.commands.capture import (
        add_binning_option,
        add_exr_options,
        add_model_size_option,
        add_models_option,
        add_prior_scale_option,
        add_seen_state_option,
    )

    p = sub.add_parser(
        "reconstruct", help="re-process sessions' raw frames (new calibration/model/demosaic)",
        description="Re-process every complete capture of one or more sessions from their raw "
                    "frames into a new revision each (rev1, rev2, ...); raw data is never "
                    "touched. Serial by default; --workers/--scheduler run one Dask task per "
                    "capture (pip install 'polrig[cluster]').")
    p.add_argument("sessions", nargs="*", metavar="SESSION",
                   help="session folder(s) (each holds session.json)")
    p.add_argument("--from-list", metavar="FILE",
                   help="text file listing session folders, one per line (# comments)")
    p.add_argument("--mode", choices=("reference", "single-shot", "hybrid"), default=None,
                   help="reconstruction method (default: each session's); hybrid works on any "
                        "session with at least one polarizer state")
    add_seen_state_option(p, "default: the session's where it stays hybrid, else 0")
    add_prior_scale_option(p, f"default {DEFAULT_PRIOR_SCALE}")
    p.add_argument("--demosaic", choices=DEMOSAIC_METHODS, default=None,
                   help="demosaic method (default: each session's)")
    p.add_argument("--mirror-average", action=argparse.BooleanOptionalAction, default=None,
                   help="single-shot, hybrid: average the network's answers for each frame and its mirror "
                        "image (default: the session's choice)")
    p.add_argument("--resolution", choices=("superpixel", "full"), default=None,
                   help="single-shot output resolution: superpixel or full (the raw frame's; "
                        "default: the session's)")
    add_binning_option(p, "default: the session's where it stays single-shot, else 1")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None,
                   help="where the single-shot network runs: auto (default), cpu or cuda (refused "
                        "when unavailable); the provider used is recorded in each result's header")
    add_model_size_option(p)
    add_exr_options(p, "default: the session's", "default: the session's",
                    "default: the session's")
    add_models_option(p)
    p.add_argument("--calibration", help="calibration set folder (default: nominal)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_range(1, 1024), metavar="N",
                       help="run on a local Dask cluster of N single-threaded worker processes")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on the workers of a running Dask scheduler "
                            "(tcp://host:8786); the session folders must be at the same "
                            "path on every worker")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _command_line(args: argparse.Namespace, paths: list[str]) -> list[str]:
    from polrig.cli.commands.capture import command_line

    ns = argparse.Namespace(**{k: v for k, v in vars(args).items()
                               if k not in ("sessions", "no_progress")})
    return command_line(ns, "reconstruct") + list(paths)


def run(args: argparse.Namespace) -> int:
    from polrig.app import cluster, reconstruct
    from polrig.cli.commands.capture import exr_planes_option, options_named
    from polrig.errors import ConfigError
    from polrig.solve.scoring import format_score

    paths = list(args.sessions)
    if args.from_list:
        paths += cluster.read_session_list(args.from_list)
    if not paths:
        raise ConfigError("name at least one SESSION folder or --from-list FILE")
    # the executor first: an unreachable scheduler or a missing extra stops before anything
    # is opened or written
    runner = cluster.open_runner(args.workers, args.scheduler)
    if runner.notice:  # an external scheduler: where the work goes, and whether it waits
        print(f"polrig reconstruct: {runner.notice}", file=sys.stderr)
    bar = None
    many = len(paths) > 1

    def on_start(batches) -> None:
        nonlocal bar
        if args.no_progress:
            return
        from tqdm import tqdm

        bar = tqdm(total=sum(len(b.todo) for b in batches), unit="capture", file=sys.stderr,
                   desc="reconstruct", dynamic_ncols=True)

    def on_capture(batch, index: int, score, reason) -> None:
        if bar is None:
            return
        from tqdm import tqdm

        bar.update(1)
        cap = batch.session.capture(index)
        where = f"{batch.session.root.name}: " if many else ""
        # a count, as the capture command's progress (``2/4``); the failure summary names the
        # capture as the session does (its index from 0 and its folder: ``capture 1 (c001_...)``)
        line = f"{where}capture {index + 1}/{len(batch.session.captures)} pose {cap['pose_deg']:g} deg: "
        if reason is None:
            line += "done" + (" | " + format_score(score) if score else "")
        else:
            line += f"failed ({reason})"
        tqdm.write(line, file=sys.stdout)

    try:
        with options_named():  # a plan error names its option (--mode, --mirror-average...)
            batches = cluster.reconstruct(
                paths, runner, mode=args.mode, demosaic=args.demosaic,
                mirror_average=args.mirror_average, resolution=args.resolution,
                network_binning=args.network_binning, seen_state=args.seen_state,
                models=args.models, prior_scale=args.prior_scale, device=args.device or "auto", model_size=args.model_size or "auto", calibration_path=args.calibration,
                exr={"planes": exr_planes_option(args.exr_planes),
                     "uncertainty": args.exr_uncertainty, "compression": args.exr_compression},
                command_line=_command_line(args, paths), on_start=on_start,
                on_capture=on_capture)
    except cluster.BatchIncomplete as exc:
        _close(bar, runner)
        if len(paths) == 1:  # one session: the serial command's own one-line error
            b = next(b for b in exc.batches if b.failed)
            raise reconstruct.ReconstructIncomplete(b.session, b.revision, b.failed,
                                                   len(b.todo)) from None
        for line in exc.lines:
            print(line, file=sys.stdout)
        raise
    finally:
        _close(bar, runner)
    for b in batches:
        verb = "continued in" if b.continued else "written to"
        print(f"revision {b.revision} {verb} {b.session.root}")
    return 0


def _close(bar, runner) -> None:
    if bar is not None:
        bar.close()
    runner.close()
