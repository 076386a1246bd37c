"""``polrig train --data DIR --out DIR``: train the single-shot networks (needs the ``train``
extra, i.e. PyTorch) on ``polrig sim dataset`` output and export ONNX into ``OUT/weights``.

Thin shell over :func:`models.train.train` (stages, schedule, logs and checkpoints are
documented there).
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train PIPNet + PMMNet (and the direct baseline), export ONNX",
                       description="Train PIPNet, then PMMNet, then the direct Stokes->MM baseline on "
                                   "a simulated dataset; checkpoints every epoch (resume with "
                                   "--resume), logs OUT/log.csv, exports OUT/weights/*.onnx and "
                                   "checks them against PyTorch with onnxruntime.")
    p.add_argument("--data", required=True, help="dataset folder written by `polrig sim dataset`")
    p.add_argument("--out", required=True, help="output folder (checkpoint, logs, weights/)")
    p.add_argument("--epochs", type=int, default=None,
                   help="epochs of every stage (overrides the per-stage defaults)")
    p.add_argument("--pipnet-epochs", type=int, default=None)
    p.add_argument("--pmmnet-epochs", type=int, default=None)
    p.add_argument("--direct-epochs", type=int, default=None)
    p.add_argument("--batch-size", type=int, default=None)
    p.add_argument("--lr", type=float, default=None, help="initial Adam learning rate")
    p.add_argument("--width", type=int, default=None, help="backbone width (channels at 1/2 resolution)")
    p.add_argument("--decay-start", type=float, default=None,
                   help="fraction of each stage's epochs at the initial learning rate before the linear decay")
    p.add_argument("--sfp-prior", action=argparse.BooleanOptionalAction, default=None,
                   help="PIPNet with the shape-from-polarization normal prior (default on for new runs)")
    p.add_argument("--crop-fraction", type=float, default=None,
                   help="fraction of PIPNet and direct-baseline training samples seen through a random window "
                        "(hides silhouettes; default 0.7 for new runs)")
    p.add_argument("--sfp-supervision", type=float, default=None,
                   help="weight of the direct supervision of the SfP prior's candidate pick and trust "
                        "(models.pipnet.sfp_supervision_loss; default 0, the paper's loss only)")
    p.add_argument("--init-perturb-fraction", type=float, default=None,
                   help="fraction of PMMNet training samples whose initialization is computed on a randomly "
                        "turned PIPNet geometry (models.train.perturbed_geometry; default 0.5 for new runs, 0 is the "
                        "paper's recipe)")
    p.add_argument("--init-perturb-deg", type=float, default=None,
                   help="largest common rotation of the perturbed normals and light (deg, default 40)")
    p.add_argument("--init-perturb-light-deg", type=float, default=None,
                   help="largest further rotation of the perturbed light alone (deg, default 30)")
    p.add_argument("--init-perturb-toward-view", type=float, default=None,
                   help="largest pull of the perturbed normals and light towards the view direction "
                        "(models.train.geometry_toward_view; half of the perturbed samples; default 0.7, "
                        "0: all perturbed samples are turned)")
    p.add_argument("--mirror-fraction", type=float, default=None,
                   help="fraction of every stage's training samples shown as their left-right mirror image "
                        "(models/mirror.py; default 0)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default 2)")
    p.add_argument("--limit", type=int, default=None, help="use at most this many samples")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument("--stages", default="pipnet,pmmnet,direct",
                   help="stages to train (comma separated, default all); with --init-from the "
                        "others are taken from that checkpoint")
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
        from models.train import train
    except ImportError as exc:  # torch missing
        raise ValueError(f"training needs the 'train' extra (pip install polrig[train]): {exc}") from exc

    overrides = {}
    if args.epochs is not None:
        overrides.update(pipnet_epochs=args.epochs, pmmnet_epochs=args.epochs, direct_epochs=args.epochs)
    if args.sfp_prior is not None:
        overrides["sfp_prior"] = args.sfp_prior
    # Bounded settings: (name, lowest, highest, unit shown in the message).
    for name, low, high, unit in (("crop_fraction", 0.0, 1.0, ""), ("sfp_supervision", 0.0, float("inf"), ""),
                                  ("init_perturb_fraction", 0.0, 1.0, ""), ("init_perturb_deg", 0.0, 180.0, " deg"),
                                  ("init_perturb_light_deg", 0.0, 180.0, " deg"),
                                  ("init_perturb_toward_view", 0.0, 1.0, ""), ("decay_start", 0.0, 1.0, ""),
                                  ("mirror_fraction", 0.0, 1.0, "")):
        value = getattr(args, name)
        if value is not None:
            if not low <= value <= high:
                bounds = f">= {low:g}" if high == float("inf") else f"in [{low:g}, {high:g}]"
                raise ValueError(f"--{name.replace('_', '-')} must be {bounds}{unit}, got {value}")
            overrides[name] = value
    for name in ("pipnet_epochs", "pmmnet_epochs", "direct_epochs", "batch_size", "lr", "width",
                 "threads", "limit", "seed"):
        value = getattr(args, name)
        if value is not None:
            if value < 0 or (name in ("batch_size", "width", "threads", "limit") and value < 1):
                raise ValueError(f"--{name.replace('_', '-')} out of range: {value}")
            overrides[name] = value
    stages = tuple(x.strip() for x in args.stages.split(",") if x.strip())
    if args.init_from is None and set(stages) != {"pipnet", "pmmnet", "direct"} and not args.resume:
        raise ValueError("training a subset of the stages needs --init-from CHECKPOINT (or a weights folder) "
                         "for the others")
    train(args.data, args.out, None, resume=args.resume, export=not args.no_export,
          overrides=overrides, init_from=args.init_from, stages=stages,
          warm_start=args.warm_start)
    return 0
