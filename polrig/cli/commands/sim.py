"""``polrig sim``: render simulated captures with their ground truth, and training datasets.

``polrig sim render --scene NAME [--size WxH] [--states 0,45,90,135] [--pose DEG] [--seed N]
--out DIR`` grabs one raw DoFP frame per polarizer state from the simulated rig (lossless
16-bit PNG + JSON sidecar, :func:`polrig.formats.rawio.write_raw`) and writes the ground truth next to
them (``truth.json``, ``truth_<name>.npz``, ``truth_<name>_mueller.exr``; ``docs/sim.md``).

``polrig sim dataset --count N --size 256 --seed S --out DIR [--holdout] [--materials MIX]
[--indirect-samples N]`` writes a sharded, resumable training set
(:func:`polrig.sim.dataset.generate_dataset`; material mixes :data:`polrig.sim.materials.MATERIAL_MIXES`).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

from polrig.choices import MATERIAL_MIXES, SCENES
from polrig.formats.argcheck import finite_float, int_range, positive_float


def _states(text: str) -> list[float]:
    try:
        states = [float(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"states must be comma-separated degrees, got {text!r}")
    if not all(math.isfinite(s) for s in states):
        raise argparse.ArgumentTypeError(f"states must be finite angles, got {text!r}")
    if not states:
        raise argparse.ArgumentTypeError("give at least one polarizer state")
    return states


def _seed(text: str) -> int:
    """A dataset seed: an integer >= 0 (numpy's seed sequences take no negative numbers)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def _names(text: str) -> list[str]:
    """Comma-separated names (validated where used, with the allowed ones in the error)."""
    return [s.strip() for s in text.split(",") if s.strip()]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="simulated captures with ground truth, training datasets",
                       description="Render simulated DoFP captures with their ground truth, "
                                   "or write a training dataset of randomized scenes.")
    ss = p.add_subparsers(dest="sim_command", metavar="SUBCOMMAND")

    r = ss.add_parser("render", help="raw frames of polarizer states + ground truth",
                      description="Grab one raw frame per polarizer state from the simulated "
                                  "rig and write the ground truth (docs/sim.md).")
    r.add_argument("--scene", default="sphere", choices=SCENES, help="scene (default sphere)")
    r.add_argument("--size", default="512x512", help="sensor WxH in pixels (default 512x512)")
    r.add_argument("--states", type=_states, default=[0.0, 45.0, 90.0, 135.0],
                   help="polarizer stage angles in degrees, comma-separated (default 0,45,90,135)")
    r.add_argument("--pose", type=finite_float, default=0.0, help="turntable angle, degrees")
    r.add_argument("--seed", type=int, default=0, help="noise and hidden-parameter seed")
    r.add_argument("--sensor", default="imx250myr", choices=("imx250myr", "imx250mzr"))
    r.add_argument("--exposure-us", type=positive_float, default=20000.0,
                   help="exposure time in microseconds (default 20000)")
    r.add_argument("--no-noise", action="store_true", help="noise-free frames (rounded means)")
    r.add_argument("--no-exr", action="store_true", help="skip the truth Mueller EXR")
    r.add_argument("--out", required=True,
                   help="output folder: new, empty, or an earlier render of the same simulated "
                        "rig (scene, size, seed, sensor, noise) to add this pose to")
    r.add_argument("--overwrite", action="store_true",
                   help="replace this pose's frames and truth if --out already has them, or "
                        "the rig recorded in --out if it is another one")
    r.set_defaults(func=run_render)

    d = ss.add_parser("dataset", help="sharded, resumable training set of random scenes",
                      description="Write a training set of randomized scenes (docs/sim.md, "
                                  "'Dataset'). Re-running the same command resumes.")
    d.add_argument("--count", type=int_range(1, 10**9), required=True, help="number of samples")
    d.add_argument("--size", type=int_range(8, 4096), default=256,
                   help="image side in pixels, a multiple of 8 (the networks' size multiple; default 256)")
    d.add_argument("--seed", type=_seed, default=0, help="dataset seed, >= 0 (default 0)")
    d.add_argument("--shard-size", type=int_range(1, 10**6), default=16, help="samples per shard (default 16)")
    d.add_argument("--holdout", action="store_true",
                   help="generate the held-out shape families instead of the training ones")
    d.add_argument("--families", type=_names, default=None,
                   help="comma-separated shape families to draw from (default: every training "
                        "family, or every held-out one with --holdout); the shipped model's "
                        "version-1 training set used sphere,box,cylinder,multi")
    d.add_argument("--stage-zero-axes", default="random", choices=("random", "camera-up"),
                   help="polarizer stage zero axis per sample: drawn at random (default), or the "
                        "camera's up direction for every sample (version-1 sets such as the "
                        "shipped model's training set)")
    d.add_argument("--materials", default="baek", choices=tuple(MATERIAL_MIXES), metavar="MIX",
                   help="material mix (docs/sim.md, 'Material mixes'): baek (default: the Baek "
                        "2018 dielectric pBRDF of the networks' initialization, datasets as "
                        "before); train (40%% baek, 20%% each conductor, dispersive, anisotropic: "
                        "the training mix); heldout (50%% each film, depolarizing: kinds the "
                        "training mix leaves out); or one kind alone: conductor (gold, silver, "
                        "copper, aluminium, chrome, complex index per colour), dispersive (Cauchy "
                        "dispersion, Abbe number 20-65), anisotropic (two roughnesses, GGX or "
                        "Beckmann), film (textured retarding film over the base), depolarizing "
                        "(polarized fraction 0.3-0.9, kd/alpha/eta textures). A sample's geometry, "
                        "light and pose are the same in every mix")
    d.add_argument("--indirect-samples", type=int_range(0, 4096), default=0, metavar="N",
                   help="one bounce of interreflected light with N Monte Carlo samples per pixel "
                        "in the images and the truth (default 0: direct light only)")
    d.add_argument("--no-compress", action="store_true", help="store shards uncompressed")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--out", required=True, help="output folder")
    where = d.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int_range(1, 1024), metavar="N",
                       help="make shards as tasks on a local Dask cluster of N single-threaded "
                            "worker processes (pip install 'polrig[cluster]')")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="make shards as tasks on the workers of a running Dask scheduler "
                            "(tcp://host:8786); --out must be at the same path on every worker")
    d.set_defaults(func=run_dataset)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_render(args: argparse.Namespace) -> int:
    from polrig.acquisition.hal import grab_timeout_s
    from polrig.formats.argcheck import check_output_folder
    from polrig.formats.rawio import write_raw
    from polrig.sim.devices import create_sim_rig
    from polrig.sim.truth import write_truth

    t0 = time.perf_counter()
    out = check_output_folder(args.out)
    # every option is checked (create_sim_rig) before anything is written
    rig = create_sim_rig({"scene": args.scene, "size": args.size, "seed": args.seed,
                          "sensor": args.sensor, "noise": not args.no_noise,
                          "clock_speed": float("inf"), "exposure_us": args.exposure_us,
                          "open": False})
    pose_name = f"pose{args.pose:07.2f}".replace(".", "p").replace("-", "m")
    names = [f"{pose_name}_state{k:02d}.png" for k in range(len(args.states))]
    if not args.overwrite:
        _refuse_to_replace(out, names, pose_name, rig.truth.rig_parameters())
    rig.camera.capabilities.check_exposure(args.exposure_us)  # before anything is written (exit 2)
    out.mkdir(parents=True, exist_ok=True)
    with rig:
        rig.camera.set_pixel_format("Mono16")
        rig.turntable.move_to(args.pose, timeout_s=3600.0)
        frames = []
        for angle, name in zip(args.states, names):
            rig.stage.move_to(angle, timeout_s=3600.0)
            frame = rig.camera.grab(timeout_s=grab_timeout_s(rig.camera))  # as every grab: exposure + readout + margin
            write_raw(out / name, frame)
            frames.append({"file": name, "stage_deg": angle,
                           "incident_stokes": rig.truth.incident_stokes(angle).tolist()})
        truth = rig.truth.ground_truth()
        files = write_truth(out, pose_name, truth, rig.truth.rig_parameters(),
                            capture={"frames": frames}, exr=not args.no_exr)
    dt = time.perf_counter() - t0
    w, h = rig.camera.roi[:2]
    print(f"polrig sim render: {args.scene} {w}x{h}, {len(frames)} state(s), pose "
          f"{args.pose:g} deg -> {out} ({', '.join(files.values())}) in {dt:.2f} s")
    return 0


def _refuse_to_replace(out: pathlib.Path, frame_names: list[str], pose_name: str,
                       rig_parameters: dict) -> None:
    """:class:`FileExistsError` (exit 2) unless rendering into ``out`` loses nothing: ``out``
    is missing or empty, or it is an earlier render (``truth.json``) of the same simulated rig
    without this pose's files (then this pose is added to it, ``docs/sim.md``)."""
    if not out.is_dir() or not any(out.iterdir()):
        return
    index_path = out / "truth.json"
    if not index_path.is_file():
        raise FileExistsError(f"--out {out} is not empty and not a 'polrig sim render' folder; "
                              f"choose a new or empty folder")
    from polrig.sim.truth import _json_default

    for name in [*frame_names, *(f + ".json" for f in frame_names), f"truth_{pose_name}.npz",
                 f"truth_{pose_name}_mueller.exr"]:
        if (out / name).exists():
            raise FileExistsError(f"--out {out} already holds {name} (this pose's capture); "
                                  f"choose another folder or pass --overwrite")
    try:
        recorded = json.loads(index_path.read_text()).get("rig")
    except (OSError, ValueError, AttributeError):
        recorded = None
    ours = json.loads(json.dumps(rig_parameters, default=_json_default))
    if json.dumps(recorded, sort_keys=True) != json.dumps(ours, sort_keys=True):
        raise FileExistsError(f"--out {out} holds a render of another simulated rig (scene, "
                              f"size, seed, sensor or noise differ); choose another folder or "
                              f"pass --overwrite")


def run_dataset(args: argparse.Namespace) -> int:
    from polrig.app.cluster import open_runner
    from polrig.sim.dataset import generate_dataset

    t0 = time.perf_counter()
    runner = open_runner(args.workers, args.scheduler)  # unreachable: exit 2, nothing written
    if runner.notice:  # an external scheduler: where the work goes, and whether it waits
        print(f"polrig sim dataset: {runner.notice}", file=sys.stderr)
    try:
        res = generate_dataset(args.out, count=args.count, width=args.size, seed=args.seed,
                               holdout=args.holdout, shard_size=args.shard_size,
                               compress=not args.no_compress, progress=not args.quiet,
                               stage_zero_axes=args.stage_zero_axes, families=args.families,
                               material_mix=args.materials,
                               indirect_samples=args.indirect_samples,
                               runner=None if args.workers is None and args.scheduler is None
                               else runner.map_unordered)
    finally:
        runner.close()
    print(f"polrig sim dataset: {res['written']} shard(s) written, {res['skipped']} already "
          f"complete -> {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0
