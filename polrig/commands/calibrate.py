"""``polrig calibrate {intrinsics,turntable,light,stokes,dofp,all} [--config FILE] --out DIR``:
the guided rig calibration procedures (:mod:`calibration.procedures`), stored as a calibration
set folder (:mod:`calibration.calset`) with a report (``report.md`` and PNG plots).

Without ``--config`` the simulated rig is calibrated (virtual clock; ``--size``/``--seed`` pick
its sensor size and hidden parameters) and every result is also compared with the simulator's
hidden truth. On real hardware the procedure asks the operator to mount each target and press
Enter. A single step updates the set already in ``--out`` (a later step needs the earlier ones).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

from polrig.commands._device_args import add_config_argument, positive_float
from polrig.errors import ConfigError

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
                   help="simulated sensor size (simulated rig only; default: the simulated "
                        "rig's, so that captures can use the calibration)")
    p.add_argument("--seed", type=int, default=0, help="simulated rig seed (default 0)")
    p.add_argument("--sensor-diattenuation", type=positive_float, default=None, metavar="D",
                   help="mean micro-polarizer diattenuation of the camera (datasheet), the "
                        "reference of the generator's extinction ratio")
    p.add_argument("--board-png", type=pathlib.Path, default=None, metavar="FILE",
                   help="also write the printable ChArUco board to FILE")
    p.add_argument("--dpi", type=positive_float, default=300.0,
                   help="DPI of --board-png (default 300)")
    p.set_defaults(func=run)


def _mount_for(rig):
    sim_rig = getattr(rig, "sim", None)
    if sim_rig is not None and getattr(rig, "truth", None) is not None:
        from sim import targets

        def mount(name: str, **fixture) -> None:
            targets.mount(sim_rig, name, **fixture)
        return mount, sim_rig

    def ask(name: str, **fixture) -> None:
        where = ", ".join(f"{k}={v}" for k, v in fixture.items()) or "default position"
        input(f"Mount the {name.replace('_', ' ')} ({where}), then press Enter: ")
    return ask, None


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


def run(args: argparse.Namespace) -> int:
    import calibration
    from calibration import runner
    from calibration.calset import CalibrationSet
    from calibration.charuco import write_board_png
    from calibration.report import write_report
    from polrig.rig import open_rig

    out: pathlib.Path = args.out
    check_out_folder(out)
    if args.board_png is not None and args.board_png.is_dir():
        raise ConfigError(f"--board-png {args.board_png} is a directory; give a file name")
    steps = list(runner.STEPS) if args.step == "all" else [args.step]
    opts = runner.Options()
    if args.sensor_diattenuation is not None:
        if not (0.5 < args.sensor_diattenuation <= 1.0):
            raise ValueError(f"--sensor-diattenuation must be in (0.5, 1], got "
                             f"{args.sensor_diattenuation}")
        opts.sensor_diattenuation = float(args.sensor_diattenuation)
    if args.board_png is not None:
        write_board_png(opts.board, args.board_png, args.dpi)
        print(f"board: {args.board_png} ({opts.board.squares_x}x{opts.board.squares_y} squares of "
              f"{opts.board.square_m * 1000:g} mm, print at 100 % and {args.dpi:g} dpi)")
    cs = calibration.load(out) if args.step != "all" and (out / "calibration.json").is_file() \
        else CalibrationSet()
    sim_options = {}
    if args.config is None:
        sim_options = {"seed": args.seed, "clock_speed": float("inf")}
        if args.size is not None:
            sim_options["size"] = args.size
    rig = open_rig(args.config, **sim_options)
    extras: dict = {}
    with rig:
        mount, sim_rig = _mount_for(rig)
        runner.run_steps(steps, rig, mount, cs, options=opts, extras=extras,
                         log=lambda s: print(s, flush=True))
        errors = None
        if sim_rig is not None:
            truth = rig.truth.rig_parameters()
            errors = runner.errors_against_truth(cs, truth, sim_rig.world.sensor.analyzer)
    cid = cs.save(out)
    report = write_report(out, cs, extras, errors)
    if errors:
        print("errors against the simulated rig's hidden truth:")
        print(json.dumps(errors, indent=2, default=float))
    print(f"calibration set {cid} written to {out} (report: {report})", file=sys.stdout)
    return 0
