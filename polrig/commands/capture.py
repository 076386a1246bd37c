"""``polrig capture``: reference (or single-shot) captures over turntable poses into a session.

Thin shell over :mod:`polrig.capture` (acquisition), :mod:`polrig.processing` (results) and
:mod:`polrig.session` (files). Bad input (pose spec, states, output folder, config) is
rejected before any device is opened or any file is written; what needs the opened rig (the
camera's exposure range, on ``--resume`` the same rig as the session's) is checked before
any file is written. A session being written by another process is refused (its lock).
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys

from polrig.errors import ConfigError

POSES_HELP = ("turntable poses in degrees: a list 0,30,60 or a range START:STOP:STEP with STOP "
              "exclusive (0:360:90 = 0, 90, 180, 270)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "capture", help="capture Mueller images over turntable poses into a session folder",
        description="Capture over turntable poses into a session folder (simulated rig unless "
                    "--config names real hardware). Every raw frame is kept; each pose gets a "
                    "Mueller EXR with uncertainty and mask planes. --poses: " + POSES_HELP + ". "
                    "Interrupted sessions (Ctrl-C, device fault, full disk) continue with "
                    "--out DIR --resume.")
    p.add_argument("--poses", help=POSES_HELP + " (required unless --resume)")
    p.add_argument("--mode", choices=("reference", "single-shot"), default=None,
                   help="reference: N polarizer states per pose (default); single-shot: the "
                        "trained network")
    p.add_argument("--mirror-average", action="store_true", default=None,
                   help="single-shot: also run the network on each frame's left-right mirror image "
                        "and average the two answers (a few per cent lower error, twice the network "
                        "time; models/MODEL_CARD.md, 'Mirror averaging')")
    p.add_argument("--states", help="polarizer stage angles in degrees (default 0,45,90,135; "
                                    "at least 3 non-collinear states for the reference method)")
    p.add_argument("--frames", type=int, default=None, help="frames averaged per state (default 1)")
    p.add_argument("--exposure", help="exposure time(s) in microseconds; several (comma "
                                      "separated) form an HDR bracket, the first is the "
                                      "reference exposure (default: the camera's current one)")
    p.add_argument("--dark-frames", type=int, default=None,
                   help="dark frames (light off) per pose and exposure (default 0: subtract "
                        "the camera's black level only)")
    p.add_argument("--demosaic", choices=("superpixel", "bilinear", "newton"), default=None,
                   help="demosaic method for processing (default superpixel: no interpolated "
                        "values, exact propagated uncertainty)")
    p.add_argument("--config", help="rig configuration TOML (default: the simulated rig)")
    p.add_argument("--calibration", help="calibration set folder (default: nominal ideal "
                                         "polarizer and analyzer, calibration id 'nominal')")
    p.add_argument("--out", required=True, help="session folder (must be new or empty)")
    p.add_argument("--resume", action="store_true",
                   help="continue the session in --out where it stopped")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def build_plan(args: argparse.Namespace):
    """The :class:`CapturePlan` the arguments ask for (defaults filled in)."""
    from polrig.capture import DEFAULT_STATES_DEG, CapturePlan, parse_float_list, parse_pose_spec

    if not args.poses:
        raise ConfigError("--poses is required (e.g. --poses 0:360:90)")
    return CapturePlan(
        poses_deg=parse_pose_spec(args.poses),
        mode=args.mode or "reference",
        states_deg=(parse_float_list(args.states, "--states") if args.states
                    else DEFAULT_STATES_DEG),
        frames_per_state=1 if args.frames is None else args.frames,
        exposures_us=(parse_float_list(args.exposure, "--exposure", positive=True)
                      if args.exposure else ()),
        dark_frames=0 if args.dark_frames is None else args.dark_frames,
        demosaic=args.demosaic or "superpixel",
        mirror_average=bool(args.mirror_average))


def check_resume_args(args: argparse.Namespace, stored) -> None:
    """On ``--resume`` the plan comes from the manifest; options that contradict it are
    refused (a resumed session must be the same session)."""
    from polrig.capture import parse_float_list, parse_pose_spec

    given = {
        "poses_deg": parse_pose_spec(args.poses) if args.poses else None,
        "mode": args.mode,
        "states_deg": parse_float_list(args.states, "--states") if args.states else None,
        "frames_per_state": args.frames,
        "exposures_us": (parse_float_list(args.exposure, "--exposure", positive=True)
                         if args.exposure else None),
        "dark_frames": args.dark_frames,
        "demosaic": args.demosaic,
        "mirror_average": args.mirror_average,
    }
    for key, value in given.items():
        if value is not None and value != getattr(stored, key):
            raise ConfigError(f"--resume: the session was planned with {key}="
                              f"{getattr(stored, key)!r}, the command line asks for {value!r}")


def command_line(args: argparse.Namespace, command: str = "capture") -> list[str]:
    """The command as the manifest records it, rebuilt from the parsed options (so that it
    is the same whether polrig ran as a console script or in-process)."""
    out = ["polrig", command]
    for key, value in vars(args).items():
        if key in ("func", "command", "session") or value is None or value is False:
            continue
        out.append("--" + key.replace("_", "-"))
        if value is not True:
            out.append(str(value))
    if getattr(args, "session", None):
        out.append(str(args.session))
    return out


@dataclasses.dataclass
class PreparedCapture:
    """A validated capture request: nothing opened, nothing written yet."""

    out: pathlib.Path
    plan: object  # polrig.capture.CapturePlan
    calibration: object  # polrig.processing.Calibration
    resume_session: object | None  # the polrig.session.Session to continue, or None


def prepare_capture(args: argparse.Namespace) -> PreparedCapture:
    """Validate a capture request before any device opens or any file is written.

    ``args`` holds the ``polrig capture`` options (the GUI's capture panel builds the same
    namespace). Raises ``FileNotFoundError``/``FileExistsError``/:class:`ConfigError` with
    one-line messages naming the option.
    """
    from polrig import capture, processing
    from polrig.session import Session, folder_is_empty

    out = pathlib.Path(args.out)
    if getattr(args, "config", None) and not pathlib.Path(args.config).is_file():
        raise FileNotFoundError(f"--config {args.config}: no such file")
    session = None
    if args.resume:
        if not (out / "session.json").is_file():
            raise FileNotFoundError(f"--resume: {out} holds no session to resume")
        # opened for writing: its lock first (SessionBusy if another process writes it), so
        # the manifest read here is the one this run continues
        session = Session.open(out, lock=True)
        try:
            plan = capture.CapturePlan.from_json(session.plan)
            check_resume_args(args, plan)
            calibration = processing.load_calibration(args.calibration, session=session)
            processing.check_plan(plan, calibration)  # states conditioning, single-shot model
        except BaseException:
            session.unlock()
            raise
    else:
        plan = build_plan(args)
        if out.exists() and not out.is_dir():
            raise FileExistsError(f"--out {out}: exists and is not a folder")
        if not folder_is_empty(out):
            raise FileExistsError(f"--out {out}: folder is not empty; pass --resume to continue "
                                  f"the session in it, or choose a new folder")
        calibration = processing.load_calibration(args.calibration)
        processing.check_plan(plan, calibration)  # states conditioning, single-shot model
    return PreparedCapture(out, plan, calibration, session)


def open_session(prepared: PreparedCapture, rig, command_line: list[str]):
    """The session to run on ``rig``: the resumed one (after checking that ``rig`` is the
    rig it was captured on and the free disk space for what is left) or a new one created in
    ``prepared.out``. The calibration set must have been calibrated on this camera (same
    sensor and layout, the readout inside the calibrated area,
    :func:`polrig.processing.check_calibration_fits_rig`) and the plan is checked against the
    rig's camera (:func:`polrig.capture.check_rig_for_plan`), both before any device moves; a
    refusal writes nothing. The session returned holds its lock until
    :func:`polrig.capture.run_session` ends."""
    from polrig import capture, processing

    if prepared.resume_session is not None:
        session = prepared.resume_session
        try:
            session.lock()  # no-op when prepare_capture took it
            capture.check_resume_rig(session, rig)
            processing.check_calibration_fits_rig(prepared.calibration, rig)
            capture.check_rig_for_plan(rig, prepared.plan, resume=True)
            capture.check_resume_space(session, rig, len(session.next_pending()))
        except BaseException:
            session.unlock()
            raise
        session.log("resume command", command_line=command_line)
        return session
    processing.check_calibration_fits_rig(prepared.calibration, rig)
    capture.check_rig_for_plan(rig, prepared.plan)
    return capture.create_session(prepared.out, rig, prepared.plan,
                                  calibration_id=prepared.calibration.id,
                                  command_line=command_line)


def run(args: argparse.Namespace) -> int:
    import os

    from polrig import capture, processing
    from polrig.rig import open_rig

    prepared = prepare_capture(args)
    plan, calibration, out = prepared.plan, prepared.calibration, prepared.out
    with open_rig(args.config) as rig:
        session = open_session(prepared, rig, command_line(args))
        try:
            processor = processing.make_processor(plan, calibration,
                                                  processing.session_sensor_model(session))
        except BaseException:
            session.unlock()
            raise
        bar = _ProgressPrinter(enabled=not args.no_progress)
        try:
            result = capture.run_session(rig, session, processor=processor,
                                         progress=bar)
        except Exception as exc:
            # run_session handles device faults and a full disk itself; anything else raised
            # once the session exists (another file-system error, a processing error) leaves
            # it interrupted and resumable: say so, with the way to continue (as the GUI does)
            if os.environ.get("POLRIG_DEBUG"):
                raise
            result = capture.interrupted_result(session, exc)
        finally:
            bar.close()
    if result.status != "complete":
        print(f"polrig: error: capture stopped ({result.reason}); completed captures are "
              f"intact, continue with: polrig capture --out {out} --resume", file=sys.stderr)
        return 1
    print(f"session complete: {len(result.completed)} captures in {out}")
    return 0


class _ProgressPrinter:
    """tqdm bar on stderr (frames, with ETA) and one score line per capture on stdout."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bar = None

    def __call__(self, ev) -> None:
        from tqdm import tqdm

        if self.bar is None and self.enabled and ev.total:
            self.bar = tqdm(total=ev.total, unit="frame", file=sys.stderr, dynamic_ncols=True,
                            desc="capture")
        if ev.kind == "frame" and self.bar is not None:
            self.bar.update(ev.step - self.bar.n)
            self.bar.set_postfix_str(f"pose {ev.pose_deg:g} deg", refresh=False)
        elif ev.kind == "retry":
            self._write(f"retry: {ev.message}", sys.stderr)
        elif ev.kind == "capture-done":
            line = f"capture {ev.capture_index + 1}/{ev.n_captures} pose {ev.pose_deg:g} deg: done"
            if ev.score:
                from polrig.processing import format_score

                line += " | " + format_score(ev.score)
            self._write(line, sys.stdout)
        elif ev.kind == "capture-failed":
            self._write(f"capture {ev.capture_index + 1}/{ev.n_captures} pose "
                        f"{ev.pose_deg:g} deg: {ev.message}", sys.stderr)

    def _write(self, line: str, stream) -> None:
        if self.bar is not None:
            from tqdm import tqdm

            tqdm.write(line, file=stream)
        else:
            print(line, file=stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
