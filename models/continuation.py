"""Committed training checkpoints: training continues across sessions (issue 32, item 4).

Each shipped model size (:mod:`polrig.models.sizes`) may have a ``checkpoint.pt`` beside its
weights (``models/weights/checkpoint.pt`` for the small one, ``models/weights/large/checkpoint.pt``)
that a later GPU lease or CPU session continues from instead of starting over::

    polrig train --data on-device --continue-from small --out runs/next ...
    polrig train --data DIR --continue-from models/weights/checkpoint.pt --out runs/next ...

It holds the networks' weights, the optimizers' states where the run that made it kept them,
the training configuration (architecture, recipe), the ``lineage`` of every run and its
``totals`` (:mod:`polrig.models.lineage`), and the ``size``. It must stay under
:data:`MAX_COMMIT_BYTES` (a lease brings back at most 16 MiB per file, and it is committed):
:func:`compact` stores Adam's moments in bfloat16 where the float32 file would be larger (the
second moment's range needs bfloat16's exponent, float16 would underflow it), then the weights
too if still needed, and records what it did in ``storage``. Only training code reads it (torch):
the wheel does not ship it (``pyproject.toml`` package data).

The small model's checkpoint was made from its shipped ONNX graphs (:func:`from_weights`): the
runs that trained it kept no optimizer state, so a run continuing from it starts its optimizers
fresh and says so, and first gives the batch norms of the recovered networks the statistics of
its own data (:func:`polrig.models.recover.recalibrate_batchnorm`). A checkpoint of a training
run (:func:`from_run`, what the lease commits) keeps its optimizers.

    python -m polrig.models.continuation --size small            # from the shipped graphs
    python -m polrig.models.continuation --size large --from-run RUN/checkpoint.pt
"""

from __future__ import annotations

import argparse
import io
import pathlib
from typing import Sequence

import torch

from polrig.atomic import atomic_write_bytes
from polrig.errors import ConfigError
from polrig.models import sizes
from polrig.models.lineage import totals as lineage_totals
from polrig.models.train import CHECKPOINT_FORMAT, load_checkpoint

CHECKPOINT_NAME = "checkpoint.pt"
#: A committed checkpoint's largest size: under the 16 MiB a lease brings back per file.
MAX_COMMIT_BYTES = 16 * 2**20 - 64 * 2**10
#: What a continued run needs of a run's checkpoint (the rest, random states and log rows, stays behind).
KEEP = ("format", "version", "config", "models", "optimizers", "times", "lineage", "totals", "size",
        "recovered_from_onnx", "optimizer_note", "storage", "dataset", "data")


def shipped_checkpoint(size: str) -> pathlib.Path:
    """Where ``size``'s committed checkpoint lives (beside its weights)."""
    return sizes.size_folder(size) / CHECKPOINT_NAME


def resolve(source: str | pathlib.Path) -> pathlib.Path:
    """``--continue-from``: a size name (its committed checkpoint) or a checkpoint file; a size
    without one is one line (:class:`ConfigError`)."""
    if str(source) in sizes.SIZES:
        path = shipped_checkpoint(str(source))
        if not path.is_file():
            raise ConfigError(f"--continue-from {source}: the {source} model has no committed checkpoint yet "
                              f"({path} missing); {sizes.HOW_TO_TRAIN[str(source)]}")
        return path
    return pathlib.Path(source)


def _nbytes(state: dict) -> int:
    blob = io.BytesIO()
    torch.save(state, blob)
    return blob.getbuffer().nbytes


def _moments_to(optimizers: dict, dtype: torch.dtype) -> dict:
    """Adam state dicts (network -> ``state_dict()``) with ``exp_avg`` and ``exp_avg_sq`` in ``dtype``."""
    moments = ("exp_avg", "exp_avg_sq")
    return {net: {**sd, "state": {i: {k: v.to(dtype) if k in moments else v for k, v in st.items()}
                                  for i, st in sd["state"].items()}}
            for net, sd in optimizers.items()}


def compact(state: dict, limit: int = MAX_COMMIT_BYTES) -> dict:
    """``state`` fit for committing: only :data:`KEEP`; Adam's moments (``exp_avg``,
    ``exp_avg_sq``) in bfloat16 if the file would exceed ``limit``, then the weights too; its
    ``storage`` says which. :class:`ConfigError` if even that exceeds ``limit``."""
    out = {k: v for k, v in state.items() if k in KEEP}
    out["storage"] = {"weights": "float32", "optimizer_moments": "float32"}
    if _nbytes(out) > limit and out.get("optimizers"):
        out["optimizers"] = _moments_to(out["optimizers"], torch.bfloat16)
        out["storage"]["optimizer_moments"] = "bfloat16"
    if _nbytes(out) > limit:
        out["models"] = {k: {n: (t.to(torch.bfloat16) if t.is_floating_point() else t) for n, t in m.items()}
                         for k, m in out["models"].items()}
        out["storage"]["weights"] = "bfloat16"
    size = _nbytes(out)
    if size > limit:
        raise ConfigError(f"the checkpoint takes {size / 2**20:.1f} MiB even in bfloat16, over the "
                          f"{limit / 2**20:.1f} MiB a commit (and a lease's file) may hold: a smaller width")
    return out


def write(state: dict, path: pathlib.Path, limit: int = MAX_COMMIT_BYTES) -> int:
    """:func:`compact` ``state`` and write it atomically to ``path``; returns its bytes."""
    blob = io.BytesIO()
    torch.save(compact(state, limit), blob)
    atomic_write_bytes(path, blob.getvalue())
    return blob.getbuffer().nbytes


def from_weights(size: str) -> dict:
    """The checkpoint of a shipped size made from its ONNX graphs
    (:func:`polrig.models.recover.checkpoint_from_weights`): weights, recipe, lineage; no
    optimizer state (module docstring)."""
    from polrig.models.recover import checkpoint_from_weights

    state = checkpoint_from_weights(sizes.size_folder(size))
    state.update(format=CHECKPOINT_FORMAT, version=2, optimizers=None, size=size,
                 recovered_from_onnx=f"models/weights{'' if size == 'small' else '/' + size}",
                 totals=lineage_totals(state.get("lineage") or []))
    return state


def from_run(path: str | pathlib.Path, size: str) -> dict:
    """The checkpoint of a training run (``OUT/checkpoint.pt``) as ``size``'s committed one."""
    state = load_checkpoint(path)
    return dict(state, size=size, totals=lineage_totals(state.get("lineage") or []))


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.continuation", description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", choices=sizes.SIZES, required=True)
    ap.add_argument("--from-run", default=None, help="a training run's checkpoint.pt (default: from the shipped graphs)")
    ap.add_argument("--out", default=None, help="where to write it (default: the size's committed checkpoint)")
    args = ap.parse_args(argv)

    def body() -> int:
        state = from_run(args.from_run, args.size) if args.from_run else from_weights(args.size)
        out = pathlib.Path(args.out) if args.out else shipped_checkpoint(args.size)
        n = write(state, out)
        print(f"wrote {out}: {n / 2**20:.2f} MiB ({compact(state)['storage']}), "
              f"{len(state.get('lineage') or [])} runs in its lineage, optimizer state "
              f"{'kept' if state.get('optimizers') else 'none'}")
        return 0

    return run_main(ap.prog, body)


if __name__ == "__main__":
    raise SystemExit(main())
