"""``polrig calibrate {intrinsics,turntable,light,stokes,dofp,all} [--config FILE] --out DIR``:
the guided rig calibration procedures (:mod:`polrig.calibration.procedures`), stored as a calibration
set folder (:mod:`polrig.calibration.calset`) with a report (``report.md`` and PNG plots).

Without ``--config`` the simulated rig is calibrated (virtual clock; ``--size``/``--seed`` pick
its sensor size and hidden parameters; with ``--config`` they are refused: the file's ``[sim]``
table sets them) and every result is also compared with the simulator's hidden truth. On real
hardware the procedure asks the operator to mount each target and press Enter. A single step
updates the set already in ``--out`` (a later step needs the earlier ones; the results of the
steps that depend on it are dropped, :data:`polrig.calibration.runner.DEPENDS_ON`); a set calibrated on
another camera readout is refused before anything moves. The set is saved after every step
that finishes, so Ctrl-C or a failure in a later step keeps the finished ones, and the
one-line message says which are saved and the command that continues.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shlex
import signal
import sys
from typing import TYPE_CHECKING, Callable

from polrig.cli.commands._device_args import add_config_argument
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.formats.argcheck import positive_float

if TYPE_CHECKING:
    from polrig.app.rig import Rig

STEP_CHOICES = ("intrinsics", "turntable", "light", "stokes", "dofp", "all")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate the rig (camera, turntable, light, "
                                         "generator, DoFP analyzer)",
                       description="Run a guided calibration step (or all of them) and write "
                                   "the calibration set (calibration.json, analyzer.npz, "
                                   "dofp_maps.npz) and report.md into --out.")
    p.add_argument("step", choices=STEP_CHOICES, help="which calibration to run")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="DIR",
                   help="calibration set folder (created or updated)")
    add_config_argument(p)
    p.add_argument("--size", default=None, metavar="WxH",
                   help="simulated sensor size (simulated rig without --config only; default: "
                        "the simulated rig's, so that captures can use the calibration)")
    p.add_argument("--seed", type=int, default=None,
                   help="simulated rig seed (simulated rig without --config only; default 0)")
    p.add_argument("--sensor-diattenuation", type=positive_float, default=None, metavar="D",
                   help="mean micro-polarizer diattenuation of the camera (datasheet), the "
                        "reference of the generator's extinction ratio")
    p.add_argument("--mirror-metal", default=None, metavar="METAL",
                   help="metal of the DoFP step's polished plate, whose diattenuation and "
                        "retardance the analyzer fit models: aluminium (default), silver, gold, "
                        "copper, chrome, or ideal (no diattenuation or retardance)")
    p.add_argument("--sphere-metal", default=None, metavar="METAL",
                   help="metal of the light step's mirror ball (its colour on a colour "
                        "sensor): chrome (default), aluminium, silver, gold, copper, ideal")
    p.add_argument("--board-png", type=pathlib.Path, default=None, metavar="FILE",
                   help="also write the printable ChArUco board to FILE")
    p.add_argument("--dpi", type=positive_float, default=300.0,
                   help="DPI of --board-png (default 300)")
    p.set_defaults(func=run)


def _mount_for(rig: Rig) -> Callable[..., None]:
    """How the procedures' targets get mounted: by the simulated rig itself where the rig
    declares its truth (:attr:`polrig.app.rig.Rig.truth`), else by the operator at a prompt."""
    if rig.truth is not None:
        return rig.truth.mount_target

    def ask(name: str, **fixture) -> None:
        where = ", ".join(f"{k}={v}" for k, v in fixture.items()) or "default position"
        input(f"Mount the {name.replace('_', ' ')} ({where}), then press Enter: ")
    return ask


def check_out_folder(out: pathlib.Path, flag: str = "--out") -> None:
    """:class:`ConfigError` (exit 2, one line) unless ``out`` is a folder the calibration set
    can be written into: an existing writable folder, or a new one whose nearest existing
    parent is a writable folder. Checked before any calibration runs (on hardware a late
    failure loses minutes of work)."""
    out = pathlib.Path(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise ConfigError(f"{flag} {out} exists and is not a folder; give a folder for the "
                              f"calibration set")
        if not os.access(out, os.W_OK | os.X_OK):
            raise ConfigError(f"{flag} folder {out} is not writable")
        return
    parent = out.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(f"{flag} {out} cannot be created: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {out} cannot be created: folder {parent} is not writable")


class StepFailed(PolrigError):
    """A calibration step failed while running (exit 1); the message says what is saved."""


class StepRefused(ConfigError):
    """A calibration step refused its input (exit 2); the message says what is saved."""


def _continue_command(args: argparse.Namespace, step: str) -> str:
    """The ``polrig calibrate`` command that runs ``step`` on the same rig into ``--out``."""
    cmd = ["polrig", "calibrate", step]
    if args.config is not None:
        cmd += ["--config", str(args.config)]
    else:
        if args.size is not None:
            cmd += ["--size", str(args.size)]
        if args.seed:
            cmd += ["--seed", str(args.seed)]
    if args.sensor_diattenuation is not None:
        cmd += ["--sensor-diattenuation", f"{args.sensor_diattenuation:g}"]
    for flag, value in (("--mirror-metal", args.mirror_metal), ("--sphere-metal", args.sphere_metal)):
        if value is not None:
            cmd += [flag, value]
    return shlex.join(cmd + ["--out", str(args.out)])


def _saved_text(args, steps: list[str], saved: list[str], saved_id: list[str],
                existed: bool) -> str:
    """What a stopped run left in ``--out`` and how to continue, one clause."""
    out = args.out
    rest = steps[len(saved):]
    if not saved:
        return f"the set in {out} is unchanged" if existed else f"nothing was saved in {out}"
    done = ", ".join(saved)
    text = f"saved step{'s' if len(saved) > 1 else ''} {done} in {out} (set {saved_id[-1]})"
    if rest:
        text += f"; continue with: {_continue_command(args, rest[0])}"
        if len(rest) > 1:
            text += f", then {', '.join(rest[1:])}"
    return text


def _report_saved(out: pathlib.Path, cs, extras: dict, saved_id: str | None) -> None:
    """After a stopped run: the report of the set as saved (best effort: a report that cannot
    be written, or a second Ctrl-C, leaves the saved set as it is)."""
    if saved_id is None or cs.compute_id() != saved_id:
        return
    from polrig.calibration.report import write_report

    try:
        write_report(out, cs, extras, None)
    except BaseException:  # noqa: BLE001 - the set is saved; the report is a convenience
        pass


def run(args: argparse.Namespace) -> int:
    from polrig import calibration
    from polrig.app.rig import open_rig
    from polrig.app.session import SignalGuard
    from polrig.calibration import runner
    from polrig.calibration.calset import CalibrationSet
    from polrig.calibration.charuco import write_board_png
    from polrig.calibration.errors import IMAGE_FAILURES
    from polrig.calibration.report import write_report

    out: pathlib.Path = args.out
    check_out_folder(out)
    if args.config is not None and (args.size is not None or args.seed is not None):
        given = " and ".join(o for o, v in (("--size", args.size), ("--seed", args.seed))
                             if v is not None)
        raise ConfigError(f"{given} only pick the simulated rig used without --config; with "
                          f"--config {args.config} set them in its [sim] table (size = "
                          f"\"WxH\", seed = N)")
    if args.board_png is not None and args.board_png.is_dir():
        raise ConfigError(f"--board-png {args.board_png} is a directory; give a file name")
    steps = list(runner.STEPS) if args.step == "all" else [args.step]
    opts = runner.Options()
    if args.sensor_diattenuation is not None:
        if not (0.5 < args.sensor_diattenuation <= 1.0):
            raise ValueError(f"--sensor-diattenuation must be in (0.5, 1], got "
                             f"{args.sensor_diattenuation}")
        opts.sensor_diattenuation = float(args.sensor_diattenuation)
    from polrig.calibration.mirror import MirrorMetal

    for flag, value, field in (("--mirror-metal", args.mirror_metal, "mirror"),
                               ("--sphere-metal", args.sphere_metal, "sphere_metal")):
        if value is not None:
            try:
                setattr(opts, field, MirrorMetal.named(value))
            except ValueError as exc:
                raise ConfigError(f"{flag}: {exc}") from None
    if args.board_png is not None:
        write_board_png(opts.board, args.board_png, args.dpi)
        print(f"board: {args.board_png} ({opts.board.squares_x}x{opts.board.squares_y} squares of "
              f"{opts.board.square_m * 1000:g} mm, print at 100 % and {args.dpi:g} dpi)")
    existed = (out / "calibration.json").is_file()
    cs = calibration.load(out) if args.step != "all" and existed else CalibrationSet()
    sim_options = {}
    if args.config is None:
        sim_options = {"seed": args.seed or 0, "clock_speed": float("inf")}
        if args.size is not None:
            sim_options["size"] = args.size
    rig = open_rig(args.config, **sim_options)
    extras: dict = {}
    saved: list[str] = []
    saved_id: list[str] = []
    with rig:
        mount = _mount_for(rig)
        name = f"calibration set {out}"
        runner.check_set_fits_camera(cs, rig, name)  # before anything moves
        try:
            with SignalGuard() as guard:
                def save_step(step: str) -> None:
                    with guard.deferred():  # a signal waits until the set is written
                        saved_id.append(cs.save(out))
                    saved.append(step)
                    print(f"{step}: saved in {out} (set {cs.id})", flush=True)

                runner.run_steps(steps, rig, mount, cs, options=opts, extras=extras,
                                 log=lambda s: print(s, flush=True), on_step_done=save_step,
                                 set_name=name)
        except KeyboardInterrupt as exc:
            signum = getattr(exc, "signum", signal.SIGINT)
            what = "interrupted" if signum == signal.SIGINT else \
                f"terminated ({signal.Signals(signum).name})"
            step = steps[min(len(saved), len(steps) - 1)]
            print(f"polrig: {what} during calibration step {step}; "
                  f"{_saved_text(args, steps, saved, saved_id, existed)}", file=sys.stderr)
            _report_saved(out, cs, extras, saved_id[-1] if saved_id else None)
            return 128 + int(signum)
        except Exception as exc:
            if os.environ.get("POLRIG_DEBUG"):
                raise
            _report_saved(out, cs, extras, saved_id[-1] if saved_id else None)
            step = steps[min(len(saved), len(steps) - 1)]
            # the images cannot give a result (a board or sphere not seen, too few views): a
            # failure while running (exit 1), as a scene too dark is (a missing earlier step
            # stays a refusal of the request, exit 2)
            bad_input = isinstance(exc, (ConfigError, FormatError, FileNotFoundError,
                                         FileExistsError, ValueError)) and not isinstance(exc, IMAGE_FAILURES)
            if not bad_input and not isinstance(exc, (PolrigError, OSError)):
                exc = f"{type(exc).__name__}: {exc}"  # an unexpected error: still one line
            cls = StepRefused if bad_input else StepFailed
            raise cls(f"calibration step {step}: {exc}; "
                      f"{_saved_text(args, steps, saved, saved_id, existed)}") from None
        errors = None
        if rig.truth is not None:
            errors = runner.errors_against_truth(cs, rig.truth.rig_parameters(),
                                                 rig.truth.analyzer())
    report = write_report(out, cs, extras, errors)
    if errors:
        print("errors against the simulated rig's hidden truth:")
        print(json.dumps(errors, indent=2, default=float))
    print(f"calibration set {cs.id} written to {out} (report: {report})", file=sys.stdout)
    return 0
