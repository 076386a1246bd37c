"""``polrig reconstruct SESSION``: re-process a session's raw frames into a new revision.

Raw frames are read (their checksums verified first) and never modified; results go to
``<capture>/<revision>/`` and the manifest records the revision's settings. The session's
lock is held while it runs (a session another process writes is refused, exit 1). A capture
whose files are damaged is marked ``failed`` in the revision with its reason and the others
are processed; the command then exits 1 with one line naming the failed captures (as
``polrig info`` exits 1 on the same damage). A ``--calibration`` set that was not calibrated
on the session's camera (sensor size, layout, or a readout outside its calibrated area) is
refused before a revision exists (exit 2,
:func:`polrig.processing.check_calibration_fits`).
"""

from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct", help="re-process a session's raw frames (new calibration/model/demosaic)",
        description="Re-process every complete capture of a session from its raw frames into "
                    "a new revision (rev1, rev2, ...); raw data is never touched.")
    p.add_argument("session", help="session folder (holds session.json)")
    p.add_argument("--mode", choices=("reference", "single-shot"), default=None,
                   help="reconstruction method (default: the session's)")
    p.add_argument("--demosaic", choices=("superpixel", "bilinear", "newton"), default=None,
                   help="demosaic method (default: the session's)")
    p.add_argument("--mirror-average", action=argparse.BooleanOptionalAction, default=None,
                   help="single-shot: average the network's answers for each frame and its mirror "
                        "image (default: the session's choice)")
    p.add_argument("--resolution", choices=("superpixel", "full"), default=None,
                   help="single-shot output resolution: superpixel or full (the raw frame's; "
                        "default: the session's)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None,
                   help="where the single-shot network runs: auto (default), cpu or cuda (refused "
                        "when unavailable); the provider used is recorded in each result's header")
    p.add_argument("--calibration", help="calibration set folder (default: nominal)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig import processing
    from polrig.commands.capture import command_line, options_named
    from polrig.scoring import format_score
    from polrig.session import Session

    session = Session.open(args.session, lock=True)  # SessionBusy if another process writes it
    try:  # a calibration set that cannot be used: refused, the lock released, nothing written
        with options_named():
            calibration = processing.load_calibration(args.calibration)
    except BaseException:
        session.unlock()
        raise
    progress = on_failed = bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(c["status"] == "complete" for c in session.captures),
                   unit="capture", file=sys.stderr, desc="reconstruct", dynamic_ncols=True)

        def progress(index: int, score) -> None:
            bar.update(1)
            cap = session.capture(index)
            line = f"capture {index + 1} pose {cap['pose_deg']:g} deg: done"
            if score:
                line += " | " + format_score(score)
            tqdm.write(line, file=sys.stdout)

        def on_failed(index: int, reason: str) -> None:
            bar.update(1)
            cap = session.capture(index)
            tqdm.write(f"capture {index + 1} pose {cap['pose_deg']:g} deg: failed ({reason})",
                       file=sys.stdout)
    try:
        with options_named():
            name = processing.reprocess_session(
                session, mode=args.mode, demosaic=args.demosaic,
                mirror_average=args.mirror_average, calibration=calibration,
                command_line=command_line(args, "reconstruct"), progress=progress,
                on_failed=on_failed, resolution=args.resolution, device=args.device or "auto")
    finally:
        if bar is not None:
            bar.close()
        session.unlock()
    print(f"revision {name} written to {session.root}")
    return 0
