"""``polrig train --data DIR --out DIR``: train the single-shot networks (needs the ``train``
extra, i.e. PyTorch) on ``polrig sim dataset`` output and export ONNX into ``OUT/weights``.

Thin shell over :func:`polrig.models.train.train` (stages, schedule, logs and checkpoints are
documented there).
"""

from __future__ import annotations

import argparse
import math

from polrig.formats.argcheck import finite_float, int_range, positive_float

STAGE_NAMES = ("pipnet", "pmmnet", "direct")  # polrig.models.train.STAGES (not imported: torch is optional)
_EPOCHS = int_range(1, 100_000)


def _stages(text: str) -> tuple[str, ...]:
    stages = tuple(x.strip() for x in text.split(",") if x.strip())
    bad = [s for s in stages if s not in STAGE_NAMES]
    if bad or not stages:
        raise argparse.ArgumentTypeError(f"unknown stage(s) {', '.join(map(repr, bad)) or 'none given'}; "
                                         f"stages are {', '.join(STAGE_NAMES)}")
    return stages


def _learning_rate(text: str) -> float:
    """Adam's initial learning rate: a finite number in (0, 1] (above 1 every step moves each
    weight by about 1 or more: the losses go to NaN)."""
    value = positive_float(text)
    if value > 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text!r}")
    return value


def _width(text: str) -> int:
    value = int_range(4, 1024)(text)
    if value % 4:
        raise argparse.ArgumentTypeError(f"must be a multiple of 4 (the attention heads split the channels), "
                                         f"got {text!r}")
    return value


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train PIPNet + PMMNet (and the direct baseline), export ONNX",
                       description="Train PIPNet, then PMMNet, then the direct Stokes->MM baseline on "
                                   "a simulated dataset; checkpoints every epoch (resume with "
                                   "--resume), logs OUT/log.csv, exports OUT/weights/*.onnx and "
                                   "checks them against PyTorch with onnxruntime.")
    p.add_argument("--data", required=True, help="dataset folder written by `polrig sim dataset`, or "
                   "'on-device': fresh scenes of its training distribution made by PyTorch on the training "
                   "device at every step (polrig.models.scenes_torch; no disk)")
    p.add_argument("--size", type=int_range(8, 4096), default=None,
                   help="with --data on-device: image side, a multiple of 8 (default 64)")
    p.add_argument("--steps-per-epoch", type=int_range(1, 10**7), default=None,
                   help="with --data on-device: optimizer steps (fresh batches) per epoch (default 64)")
    p.add_argument("--val-samples", type=int_range(1, 10**6), default=None,
                   help="with --data on-device: scenes of the fixed validation set (default 32)")
    p.add_argument("--out", required=True, help="output folder (checkpoint, logs, weights/); a folder holding "
                   "another run is refused unless --resume or --overwrite")
    p.add_argument("--epochs", type=_EPOCHS, default=None,
                   help="epochs of every stage, >= 1 (overrides the per-stage defaults)")
    p.add_argument("--pipnet-epochs", type=_EPOCHS, default=None, help="PIPNet epochs, >= 1 (default 12)")
    p.add_argument("--pmmnet-epochs", type=_EPOCHS, default=None, help="PMMNet epochs, >= 1 (default 8)")
    p.add_argument("--direct-epochs", type=_EPOCHS, default=None, help="direct-baseline epochs, >= 1 (default 8)")
    p.add_argument("--batch-size", type=int_range(1, 100_000), default=None, help="samples per step (default 16)")
    p.add_argument("--lr", type=_learning_rate, default=None,
                   help="initial Adam learning rate, in (0, 1] (default 1e-3)")
    p.add_argument("--width", type=_width, default=None,
                   help="backbone width (channels at 1/2 resolution), a multiple of 4 (default 16)")
    p.add_argument("--decay-start", type=finite_float, default=None,
                   help="fraction of each stage's epochs at the initial learning rate before the linear decay")
    p.add_argument("--sfp-prior", action=argparse.BooleanOptionalAction, default=None,
                   help="PIPNet with the shape-from-polarization normal prior (default on for new runs)")
    p.add_argument("--crop-fraction", type=finite_float, default=None,
                   help="fraction of PIPNet and direct-baseline training samples seen through a random window "
                        "(hides silhouettes; default 0.7 for new runs)")
    p.add_argument("--sfp-supervision", type=finite_float, default=None,
                   help="weight of the direct supervision of the SfP prior's candidate pick and trust "
                        "(polrig.models.pipnet.sfp_supervision_loss; default 0, the paper's loss only)")
    p.add_argument("--init-perturb-fraction", type=finite_float, default=None,
                   help="fraction of PMMNet training samples whose initialization is computed on a randomly "
                        "turned PIPNet geometry (polrig.models.train.perturbed_geometry; default 0.5 for new runs, 0 is the "
                        "paper's recipe)")
    p.add_argument("--init-perturb-deg", type=finite_float, default=None,
                   help="largest common rotation of the perturbed normals and light (deg, default 40)")
    p.add_argument("--init-perturb-light-deg", type=finite_float, default=None,
                   help="largest further rotation of the perturbed light alone (deg, default 30)")
    p.add_argument("--init-perturb-toward-view", type=finite_float, default=None,
                   help="largest pull of the perturbed normals and light towards the view direction "
                        "(polrig.models.train.geometry_toward_view; half of the perturbed samples; default 0.7, "
                        "0: all perturbed samples are turned)")
    p.add_argument("--mirror-fraction", type=finite_float, default=None,
                   help="fraction of every stage's training samples shown as their left-right mirror image "
                        "(models/mirror.py; default 0)")
    p.add_argument("--threads", type=int_range(1, 1024), default=None, help="torch threads (default 2)")
    p.add_argument("--limit", type=int_range(1, 10**9), default=None, help="use at most this many samples")
    p.add_argument("--seed", type=int_range(0, 2**32 - 1), default=None,
                   help="seed of the initialization, the validation split and the sample order (default 0)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in OUT from OUT/checkpoint.pt (same --data; refused when there is "
                        "no checkpoint); per-stage epochs may grow for the stage in progress and the ones after it")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a run already in OUT (its checkpoint, log, summary and weights are removed first)")
    p.add_argument("--stages", type=_stages, default=None,
                   help="stages to train (comma separated from pipnet, pmmnet, direct; default all); with "
                        "--init-from the others are taken from that checkpoint")
    p.add_argument("--init-from", default=None, help="checkpoint.pt of another run, or a weights folder "
                   "(e.g. models/weights: the shipped networks, recovered from their ONNX graphs), to take the "
                   "networks of the stages not trained from")
    p.add_argument("--warm-start", action="store_true", help="with --init-from: start the trained "
                   "stages from that checkpoint's weights too (fine-tuning, fresh schedule)")
    p.add_argument("--no-export", action="store_true", help="skip the ONNX export")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os

    # OpenMP threads that spin while waiting collapse throughput on a shared, oversubscribed
    # CPU (measured here: 5 s instead of 0.5 s per step); passive waiting must be set before
    # torch starts its thread pool.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        from polrig.models.train import train
    except ImportError as exc:  # torch missing
        raise ValueError(f"training needs the 'train' extra (pip install polrig[train]): {exc}") from exc

    overrides = {}
    if args.epochs is not None:
        overrides.update(pipnet_epochs=args.epochs, pmmnet_epochs=args.epochs, direct_epochs=args.epochs)
    if args.sfp_prior is not None:
        overrides["sfp_prior"] = args.sfp_prior
    # Bounded settings: (name, lowest, highest, unit shown in the message).
    for name, low, high, unit in (("crop_fraction", 0.0, 1.0, ""), ("sfp_supervision", 0.0, math.inf, ""),
                                  ("init_perturb_fraction", 0.0, 1.0, ""), ("init_perturb_deg", 0.0, 180.0, " deg"),
                                  ("init_perturb_light_deg", 0.0, 180.0, " deg"),
                                  ("init_perturb_toward_view", 0.0, 1.0, ""), ("decay_start", 0.0, 1.0, ""),
                                  ("mirror_fraction", 0.0, 1.0, "")):
        value = getattr(args, name)
        if value is not None:
            if not low <= value <= high:
                bounds = f">= {low:g}" if high == math.inf else f"in [{low:g}, {high:g}]"
                raise ValueError(f"--{name.replace('_', '-')} must be {bounds}{unit}, got {value}")
            overrides[name] = value
    # ranges checked by argparse (the type= helpers above)
    for name in ("pipnet_epochs", "pmmnet_epochs", "direct_epochs", "batch_size", "lr", "width",
                 "threads", "limit", "seed"):
        value = getattr(args, name)
        if value is not None:
            overrides[name] = value
    on_device_args = {k: getattr(args, k) for k in ("size", "steps_per_epoch", "val_samples")
                      if getattr(args, k) is not None}
    if args.data == "on-device":
        from polrig.models.train_on_device import train_on_device

        refused = [flag for flag, given in (("--resume", args.resume), ("--init-from", args.init_from),
                                            ("--stages", args.stages), ("--limit", args.limit)) if given]
        if refused:
            raise ValueError(f"--data on-device: {', '.join(refused)} not supported with on-device scenes")
        train_on_device(args.out, None, overrides=overrides, export=not args.no_export,
                        overwrite=args.overwrite, **on_device_args)
        return 0
    if on_device_args:
        raise ValueError(f"--{next(iter(on_device_args)).replace('_', '-')} needs --data on-device")
    train(args.data, args.out, None, resume=args.resume, export=not args.no_export,
          overrides=overrides, init_from=args.init_from, stages=args.stages,
          warm_start=args.warm_start, overwrite=args.overwrite)
    return 0
