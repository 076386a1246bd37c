"""Unattended training of the single-shot networks within a wall-clock budget (issue 22, item 4).

``python -m models.paper_scale --out DIR [--budget-min 8] [--size 256] [--width W]``

One run, in order, each phase inside its share of the budget:

1. **Data** (:data:`DATA_SHARE` of the budget): ``polrig sim dataset`` in one process per CPU
   core (``--jobs``), each its own seed, merged into one training set; two held-out sets as in
   ``models/MODEL_CARD.md``: unseen shapes (``--holdout``) and new scenes of the training shapes
   (another seed). The number of training samples comes from the time one sample took to
   generate (a probe), unless ``--train-samples`` gives it.
2. **Training** (:data:`TRAIN_SHARE`): PIPNet, then PMMNet, then the direct Stokes->MM baseline
   (:func:`models.train.train`). The two stages of the method share their time as the paper's
   40 + 20 epochs do (2:1) and the baseline gets as much as the two together (the ablation is
   fair when it had the same budget). Epochs per stage are the paper's schedule scaled to the
   budget: measured seconds per sample-epoch of each stage (a one-epoch probe on a batch of the
   data) times the training samples, at least one epoch each.
3. **Export and check** (inside :func:`models.train.train`: ONNX, onnxruntime against PyTorch),
   then **evaluation** of the new graphs and of the shipped ones on both held-out sets
   (:func:`models.evaluate.evaluate`) and the verdict: ship only if the new graphs beat the
   shipped ones' matrix PSNR on every held-out set.

``OUT`` holds only what is worth bringing back (checked below :data:`MAX_OUT_BYTES`):
``weights/`` (graphs, ``model.json``), ``log.csv``, ``summary.json`` (the training run),
``eval_<set>.md/.json`` (new and shipped), ``run.json`` (hardware, budget, phase times, data
seeds and counts, verdict). Datasets, probe runs and the checkpoint stay in ``--work`` (a
temporary folder by default, removed at the end).

Device: PyTorch trains on the CUDA GPU where it sees one (:attr:`models.train.TrainConfig.device`;
the data generation and the evaluation stay on the CPU cores), else on the CPU; ``run.json``
records which, with the hardware. The CUDA path has not run on a GPU yet (none was available to
this work): it is tested on the CPU only. The width defaults to :data:`DEFAULT_WIDTH`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence

#: Shares of the budget: data generation, training (the rest: export, evaluation, margin).
DATA_SHARE = 0.3
TRAIN_SHARE = 0.55
#: Training-time ratios of the stages (PIPNet : PMMNet as the paper's 40 : 20 epochs; the direct
#: baseline as much as both).
STAGE_SHARES = {"pipnet": 2 / 6, "pmmnet": 1 / 6, "direct": 3 / 6}
DEFAULT_WIDTH = 16
#: The output folder must stay small enough to bring back from a lent machine.
MAX_OUT_BYTES = 16 * 2**20
HOLDOUT_SETS = {"unseen_shapes": True, "new_scenes": False}  # name -> --holdout
#: Seeds: the training parts take ``seed * 1000 + part``; the held-out sets their own.
HOLDOUT_SEEDS = {"unseen_shapes": 900_001, "new_scenes": 900_002}


def _sim_dataset(out: pathlib.Path, count: int, size: int, seed: int, holdout: bool) -> subprocess.Popen:
    """``polrig sim dataset`` in a child process (its own CPU core)."""
    argv = [sys.executable, "-m", "polrig.cli", "sim", "dataset", "--count", str(count), "--size", str(size),
            "--seed", str(seed), "--quiet", "--out", str(out)] + (["--holdout"] if holdout else [])
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait(procs: Sequence[subprocess.Popen]) -> None:
    for p in procs:
        _, err = p.communicate()
        if p.returncode:
            last = (err or "").strip().splitlines()[-1:] or [f"exit status {p.returncode}"]
            raise RuntimeError(f"polrig sim dataset failed: {last[0]}")


def _merge(parts: Sequence[pathlib.Path], out: pathlib.Path) -> int:
    """One dataset folder from ``parts`` (same size and families, different seeds): samples
    concatenated, the first part's manifest with the parts' seeds and the total count."""
    import numpy as np

    from models.data import load_dataset, write_dataset

    sets = [load_dataset(p) for p in parts]
    arrays = {k: np.concatenate([s.arrays[k] for s in sets]) for k in sets[0].arrays}
    manifest = dict(sets[0].manifest, merged_seeds=[s.manifest.get("seed") for s in sets])
    write_dataset(out, arrays, manifest)
    return int(arrays["analyzer"].shape[0])


def generate_data(work: pathlib.Path, *, size: int, seconds: float, jobs: int, seed: int,
                  train_samples: int | None, holdout_samples: int, echo=print) -> dict:
    """Phase 1 (module docstring): the training set ``work/train`` and the held-out sets
    ``work/<name>``; returns counts, seeds and seconds."""
    t0 = time.perf_counter()
    probe = work / "probe-sample"
    _wait([_sim_dataset(probe, 1, size, seed * 1000 + 999, False)])
    per_sample = max(time.perf_counter() - t0, 1e-3)  # a whole process: an upper bound per sample
    held = [(name, _sim_dataset(work / name, holdout_samples, size, HOLDOUT_SEEDS[name] + seed, flag))
            for name, flag in HOLDOUT_SETS.items()]
    if train_samples is None:
        left = max(seconds - (time.perf_counter() - t0), 0.0)
        train_samples = max(jobs, int(jobs * left / per_sample) - 2 * holdout_samples)
    counts = [train_samples // jobs + (k < train_samples % jobs) for k in range(jobs)]
    parts = [(work / f"train-part{k}", _sim_dataset(work / f"train-part{k}", c, size, seed * 1000 + k, False))
             for k, c in enumerate(counts) if c]
    _wait([p for _, p in parts] + [p for _, p in held])
    n = _merge([d for d, _ in parts], work / "train")
    for d, _ in parts:
        shutil.rmtree(d)
    echo(f"data: {n} training samples at {size}x{size} in {len(parts)} processes, "
         f"{holdout_samples} per held-out set, {time.perf_counter() - t0:.1f} s")
    return {"train_samples": n, "holdout_samples": holdout_samples, "size": size, "jobs": jobs,
            "train_seeds": [seed * 1000 + k for k in range(len(parts))],
            "holdout_seeds": {k: v + seed for k, v in HOLDOUT_SEEDS.items()},
            "seconds_per_sample_probe": per_sample, "seconds": time.perf_counter() - t0}


def plan_epochs(stage_seconds: dict[str, float], probe_samples: int, samples: int, seconds: float) -> dict[str, int]:
    """Epochs per stage that fit ``seconds`` of training on ``samples`` samples, from one probe
    epoch per stage on ``probe_samples`` samples that took ``stage_seconds`` (shares
    :data:`STAGE_SHARES`; at least one epoch each)."""
    epochs = {}
    for stage, share in STAGE_SHARES.items():
        per_sample_epoch = max(stage_seconds[stage], 1e-6) / max(probe_samples, 1)
        epochs[stage] = max(1, int(share * seconds / (per_sample_epoch * samples)))
    return epochs


def train_in_budget(work: pathlib.Path, *, seconds: float, width: int, seed: int, epochs: int | None = None,
                    echo=print) -> dict:
    """Phase 2 (module docstring): probe, plan, train, export into ``work/run``. ``epochs``:
    that many epochs of every stage instead of the planned ones (no probe)."""
    from models.train import TrainConfig, train

    t0 = time.perf_counter()
    base = TrainConfig(width=width, seed=seed, threads=max(1, os.cpu_count() or 1), device=training_device())
    n = _count(work / "train")
    probe_seconds = None
    if epochs is None:
        probe_n = base.batch_size
        probe = train(work / "train", work / "probe-run", TrainConfig(**{**base.__dict__, "limit": probe_n,
                                                                         "pipnet_epochs": 1, "pmmnet_epochs": 1,
                                                                         "direct_epochs": 1}),
                      export=False, echo=lambda s: None)
        probe_seconds = probe["train_seconds"]
        left = max(seconds - (time.perf_counter() - t0), 0.0)
        plan = plan_epochs(probe_seconds, min(probe_n, n), n, left)
        echo(f"training plan for {left:.0f} s on {n} samples: " + ", ".join(f"{k} {v} epoch(s)" for k, v in plan.items()))
    else:
        plan = dict.fromkeys(STAGE_SHARES, epochs)
    epochs = plan
    config = TrainConfig(**{**base.__dict__, "pipnet_epochs": epochs["pipnet"], "pmmnet_epochs": epochs["pmmnet"],
                            "direct_epochs": epochs["direct"]})
    summary = train(work / "train", work / "run", config, echo=lambda s: None)
    return {"epochs": epochs, "probe_train_seconds": probe_seconds, "summary": summary,
            "seconds": time.perf_counter() - t0}


def _count(folder: pathlib.Path) -> int:
    return int(json.loads((folder / "manifest.json").read_text())["count"])


def evaluate_against_shipped(work: pathlib.Path, weights: pathlib.Path, out: pathlib.Path, echo=print) -> dict:
    """Phase 3: both held-out sets scored with the new and the shipped graphs; the tables go to
    ``out/eval_<set>_<new|shipped>.md`` (+ ``.json``). ``ship`` is True only if the new graphs'
    matrix PSNR beats the shipped ones' on every set."""
    from models.evaluate import evaluate, write_results
    from models.runtime import WEIGHTS_DIR

    scores, ship = {}, True
    for name in HOLDOUT_SETS:
        scores[name] = {}
        for which, wd in (("new", weights), ("shipped", WEIGHTS_DIR)):
            result = evaluate(work / name, wd, echo=lambda s: None)
            write_results(result, out / f"eval_{name}_{which}.md")
            scores[name][which] = result["methods"]["full"]["matrix_psnr"]
        ship &= scores[name]["new"] > scores[name]["shipped"]
        echo(f"{name}: matrix PSNR new {scores[name]['new']:.2f} dB, shipped {scores[name]['shipped']:.2f} dB")
    return {"matrix_psnr_db": scores, "ship": bool(ship)}


def training_device() -> str:
    """``cuda`` where PyTorch sees a CUDA GPU, else ``cpu`` (:attr:`models.train.TrainConfig.device`)."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def hardware() -> dict:
    """What ran it: CPU, cores, and the GPU torch sees (if any)."""
    import torch

    info = {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_cores": os.cpu_count(), "torch": torch.__version__, "training_device": training_device()}
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def folder_bytes(folder: pathlib.Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def run(out: pathlib.Path, *, budget_s: float, size: int, width: int, jobs: int, seed: int,
        train_samples: int | None, holdout_samples: int, epochs: int | None = None,
        work: pathlib.Path | None = None, echo=print) -> dict:
    """The whole run (module docstring); returns ``run.json``'s content."""
    from polrig.argcheck import check_output_folder

    out = check_output_folder(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty (a run writes into an empty folder)")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="paper-scale-", dir=work) as tmp:
        w = pathlib.Path(tmp)
        data = generate_data(w, size=size, seconds=DATA_SHARE * budget_s, jobs=jobs, seed=seed,
                             train_samples=train_samples, holdout_samples=holdout_samples, echo=echo)
        left = budget_s - (time.perf_counter() - t0)
        training = train_in_budget(w, seconds=max(TRAIN_SHARE / (1 - DATA_SHARE) * left, 0.0), width=width,
                                   seed=seed, epochs=epochs, echo=echo)
        out.mkdir(parents=True, exist_ok=True)
        shutil.copytree(w / "run" / "weights", out / "weights")
        for name in ("log.csv", "summary.json"):
            shutil.copy2(w / "run" / name, out / name)
        t_eval = time.perf_counter()
        verdict = evaluate_against_shipped(w, out / "weights", out, echo=echo)
        eval_s = time.perf_counter() - t_eval
    record = {"budget_s": budget_s, "total_s": time.perf_counter() - t0, "hardware": hardware(),
              "data": data, "training": {k: v for k, v in training.items() if k != "summary"},
              "width": width, "seed": seed, "eval_s": eval_s, **verdict}
    (out / "run.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
    size_b = folder_bytes(out)
    if size_b > MAX_OUT_BYTES:
        raise RuntimeError(f"{out} holds {size_b / 2**20:.1f} MiB, over the {MAX_OUT_BYTES / 2**20:.0f} MiB "
                           f"that can be brought back (a smaller --width)")
    over = record["total_s"] > budget_s
    echo(f"wrote {out} ({size_b / 2**20:.2f} MiB) in {record['total_s']:.0f} s of a {budget_s:.0f} s budget"
         f"{' (OVER BUDGET: the fixed costs exceed it)' if over else ''}; ship: {'yes' if verdict['ship'] else 'no'}")
    return record


def main(argv: Sequence[str] | None = None) -> int:
    from models._cli import run_main
    from polrig.argcheck import int_range, positive_float

    ap = argparse.ArgumentParser(prog="python -m models.paper_scale", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output folder (new or empty)")
    ap.add_argument("--budget-min", type=positive_float, default=8.0, help="wall-clock budget in minutes (default 8)")
    ap.add_argument("--size", type=int_range(16, 4096), default=256, help="image side, a multiple of 8 (default 256)")
    ap.add_argument("--width", type=int_range(4, 1024), default=DEFAULT_WIDTH,
                    help=f"network width, a multiple of 4 (default {DEFAULT_WIDTH})")
    ap.add_argument("--jobs", type=int_range(1, 1024), default=os.cpu_count() or 1,
                    help="data generation processes (default: the CPU cores)")
    ap.add_argument("--train-samples", type=int_range(1, 10**7), default=None,
                    help="training samples (default: as many as the data share of the budget makes)")
    ap.add_argument("--holdout-samples", type=int_range(1, 10**6), default=32, help="samples per held-out set (default 32)")
    ap.add_argument("--epochs", type=int_range(1, 10**5), default=None,
                    help="epochs of every stage instead of the budget's plan (no timing probe)")
    ap.add_argument("--seed", type=int_range(0, 10**6), default=0)
    ap.add_argument("--work", default=None, help="folder for the datasets and checkpoints (default: a temporary one)")
    args = ap.parse_args(argv)

    def body() -> int:
        from polrig.errors import ConfigError

        if args.size % 8:
            raise ConfigError(f"--size {args.size}: must be a multiple of 8 (the networks' size multiple)")
        if args.width % 4:
            raise ConfigError(f"--width {args.width}: must be a multiple of 4 (the attention heads split the channels)")
        run(pathlib.Path(args.out), budget_s=60.0 * args.budget_min, size=args.size, width=args.width,
            jobs=args.jobs, seed=args.seed, train_samples=args.train_samples, holdout_samples=args.holdout_samples,
            epochs=args.epochs,
            work=None if args.work is None else pathlib.Path(args.work))
        return 0

    return run_main(ap.prog, body)


if __name__ == "__main__":
    sys.exit(main())
