"""The GPU lease's entry point (issue 32, items 2, 5 and 6): one unattended run that trains a
model size on scenes made on the GPU within one wall-clock budget, and ships it or not.

``python -m polrig.models.lease --out DIR [--model-size large] [--budget-min 8] [--dry]``
(on a lent machine through ``benchmarks/gpu_train.sh``).

One budget ``B`` covers everything, in this order:

1. **Held-out and calibration sets** (:data:`SETS`: the model card's acceptance sets, the
   mismatched-material and interreflection sets, and a calibration set) are made by
   ``polrig sim dataset`` in one process each on the CPU cores, while the GPU trains; the
   shipped weights are evaluated on them in a thread as soon as they exist.
2. **Training** (:func:`polrig.models.train_on_device.train_on_device`: fresh scenes on the
   training device at every step, no disk): a probe (:data:`PROBE_STEPS` steps of every stage,
   twice: the first pays CUDA's warm-up and cuDNN's searches) times a step of each stage, then
   PIPNet, PMMNet and the direct baseline train with :class:`polrig.models.paper_scale.StagePlanner`
   (the shares :data:`polrig.models.paper_scale.STAGE_SHARES`: PIPNet : PMMNet 2 : 1 as the paper's
   40 : 20 epochs, the baseline as long as both, so the ablation is fair) until
   :data:`TRAIN_SHARE` of the budget is spent. bf16 autocast on CUDA
   (:class:`polrig.models.train.Autocast`: the convolutions and attention; the pBRDF and the losses
   stay float32). The run continues the size's committed checkpoint where there is one
   (:mod:`polrig.models.continuation`), else starts from scratch with the size's :data:`PROFILES`.
3. **Export and ONNX check** (inside the training: onnxruntime against PyTorch).
4. **Evaluation** of the new graphs on every set (what is left until the margin), against the
   shipped weights of the same size (the small ones where the size was never shipped), and the
   **shipping rule**: ship only if the new graphs' matrix PSNR of the full method beats the
   baseline's on every set. Where it ships, the calibrated sigma is refitted on the calibration
   set and its coverage re-measured on every set (:mod:`polrig.models.uncertainty_fit`).

``OUT`` holds what comes back (every file under :data:`MAX_FILE_BYTES`): ``weights/`` (graphs,
``model.json`` with ``size``, hardware and lineage, ``uncertainty.json`` where it ships),
``checkpoint.pt`` (the committed form, :func:`polrig.models.continuation.compact`), ``log.csv``,
``summary.json``, ``eval_<set>_<new|baseline>.md``, ``sigma_fit.log``, ``run.json`` (hardware, budget, phases,
plan, scores, verdict). ``--ship FOLDER`` (:func:`ship`) ships what ``benchmarks/gpu_train.sh``
brought back where the rule passed.

``--dry``: the same run at tiny scale on the CPU (32x32 scenes, width 4, two scenes per set, a
budget of seconds; the sigma refitted whatever the verdict, so that every step runs): what the
test suite runs, end to end.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import dataclasses
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Sequence

#: The sets made for the verdict and the sigma (``polrig sim dataset`` arguments besides count,
#: size, seed): the model card's held-out sets, the mismatched materials, the interreflections;
#: ``calibration`` is the sigma's calibration set (not a verdict set).
TRAIN_FAMILIES = "sphere,box,cylinder,multi"
SETS = {
    "unseen_shapes": (2, ["--holdout"]),
    "new_scenes": (5, ["--families", TRAIN_FAMILIES]),
    "unseen_compact": (7, ["--families", "blob,torus"]),
    "mm_heldout": (5, ["--families", TRAIN_FAMILIES, "--materials", "heldout"]),
    "mm_conductor": (5, ["--families", TRAIN_FAMILIES, "--materials", "conductor"]),
    "mm_dispersive": (5, ["--families", TRAIN_FAMILIES, "--materials", "dispersive"]),
    "indirect_terrain": (2, ["--holdout", "--indirect-samples", "32"]),
    "indirect_compact": (7, ["--families", "blob,torus", "--indirect-samples", "32"]),
    "calibration": (11, ["--families", TRAIN_FAMILIES + ",blob,torus"]),
}
CALIBRATION_SET = "calibration"
#: Networks and batches per size for a run from scratch (a continued run keeps its checkpoint's
#: architecture). The large width is the widest whose checkpoint keeps everything in float32
#: under 16 MiB (measured: width 32, 1.08 M parameters over the three networks, 12.6 MiB with
#: Adam's moments; width 48, 2.4 M, would need bfloat16 weights and moments, 13.9 MiB, and lose
#: the weights' precision from lease to lease); its batch and scene size are meant to fill an H200
#: far better than the CPU recipe (not yet run on a GPU: the first lease's run.json will say).
PROFILES = {
    "large": {"width": 32, "batch_size": 32, "image": 128, "steps_per_epoch": 32, "val_samples": 64},
    "small": {"width": 16, "batch_size": 16, "image": 64, "steps_per_epoch": 64, "val_samples": 32},
    "dry": {"width": 4, "batch_size": 2, "image": 32, "steps_per_epoch": 2, "val_samples": 2},
}
#: Share of the budget for the training's epochs (the rest: the export, the evaluation, the
#: sigma refit and the margin); the probe comes out of it.
TRAIN_SHARE = 0.62
PROBE_STEPS = 3
MARGIN_SHARE = 0.02
#: The samples per set, the evaluation's image size (the model card's sets are 64x64), and the
#: fewest samples each set is scored on whatever the time.
SET_SAMPLES, EVAL_SIZE, MIN_EVAL_SAMPLES = 32, 64, 4
#: A dry run's sets (count, image side): two tiny scenes, but enough polarized pixels for the
#: sigma's fit (:func:`polrig.models.uncertainty_fit.calibrate`: 100 per bin).
DRY_SETS = {"default": (2, 32), CALIBRATION_SET: (5, 64)}
#: Largest file the device tool brings back.
MAX_FILE_BYTES = 16 * 2**20


@dataclasses.dataclass
class Phase:
    """Seconds of a phase (``run.json``)."""

    name: str
    seconds: float = 0.0


def make_sets(work: pathlib.Path, names: Sequence[str], count: int, size: int, dry: bool = False
              ) -> list[subprocess.Popen]:
    """Start ``polrig sim dataset`` for each set of ``names`` (one process each, CPU); ``dry``:
    :data:`DRY_SETS`' counts and sizes instead."""
    procs = []
    for name in names:
        seed, extra = SETS[name]
        if dry:
            count, size = DRY_SETS.get(name, DRY_SETS["default"])
        argv = [sys.executable, "-m", "polrig", "sim", "dataset", "--count", str(count), "--size", str(size),
                "--seed", str(seed), "--quiet", "--out", str(work / name), *extra]
        procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    return procs


def wait_sets(procs: Sequence[subprocess.Popen]) -> None:
    for p in procs:
        _, err = p.communicate()
        if p.returncode:
            raise RuntimeError(f"polrig sim dataset failed: {(err or '').strip().splitlines()[-1:]}")


def baseline_weights(size: str) -> tuple[str, pathlib.Path]:
    """The weights the new ones must beat: the shipped ones of ``size``, else the small ones."""
    from polrig.models import sizes

    chosen = size if sizes.is_shipped(size) else "small"
    return chosen, sizes.size_folder(chosen)


def score(data: pathlib.Path, weights: pathlib.Path, out_md: pathlib.Path, *, limit: int | None = None,
          deadline: float | None = None) -> dict:
    """The verdict's numbers on one set (:func:`polrig.models.evaluate.evaluate`, full model and
    direct baseline), its table written to ``out_md``."""
    from polrig.models.evaluate import evaluate, write_results

    r = evaluate(data, weights, methods=("full", "direct"), limit=limit, deadline=deadline,
                 min_samples=MIN_EVAL_SAMPLES, echo=lambda s: None)
    write_results(r, out_md)
    full, direct = r["methods"]["full"], r["methods"]["direct"]
    return {"matrix_psnr": full["matrix_psnr"], "fwd_l2": full["fwd_l2"], "direct_fwd_l2": direct["fwd_l2"],
            "samples": r["samples"], "visited": r["samples_visited"]}


def probe_step_seconds(work: pathlib.Path, base: dict, overrides: dict, continue_from) -> dict[str, float]:
    """Seconds of one optimizer step per stage, warm: every stage trained 2 epochs of
    :data:`PROBE_STEPS` steps (no export) with a one-scene validation set; the second epoch's
    time per step (the first pays the warm-up). The real epochs' validation pass is planned
    apart (:func:`validation_seconds`)."""
    from polrig.models.train_on_device import train_on_device

    train_on_device(work / "probe", None, overrides=dict(overrides, pipnet_epochs=2, pmmnet_epochs=2,
                                                                 direct_epochs=2),
                            size=base["image"], steps_per_epoch=PROBE_STEPS, val_samples=1,
                            continue_from=continue_from, export=False, echo=lambda s: None)
    rows = _log_rows(work / "probe" / "log.csv")
    return {k: min(float(r["epoch_s"]) for r in rows if r["stage"] == k and int(r["epoch"]) == 1) / PROBE_STEPS
            for k in ("pipnet", "pmmnet", "direct")}


def validation_seconds(step_s: dict[str, float], val_samples: int, batch_size: int) -> float:
    """An epoch's validation pass, estimated: forward passes over ``val_samples`` scenes, a third
    of a training step's time per batch (forward only, no optimizer) for the slowest stage."""
    return max(step_s.values()) * val_samples / batch_size / 3.0


def _log_rows(path: pathlib.Path) -> list[dict]:
    import csv

    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def run(out: pathlib.Path, *, size: str = "large", budget_s: float = 480.0, dry: bool = False,
        sets: Sequence[str] = tuple(SETS), set_samples: int = SET_SAMPLES, eval_size: int = EVAL_SIZE,
        work: pathlib.Path | None = None, echo=print) -> dict:
    """The whole lease (module docstring); returns ``run.json``'s content."""
    import torch

    from polrig.formats.argcheck import check_output_folder
    from polrig.models import continuation, sizes
    from polrig.models.lineage import hardware_line
    from polrig.models.paper_scale import StagePlanner
    from polrig.models.train_on_device import train_on_device

    sizes.size_folder(size)  # a known size
    out = check_output_folder(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty (a lease writes into an empty folder)")
    t0 = time.perf_counter()
    end = t0 + budget_s * (1 - MARGIN_SHARE)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    profile = PROFILES["dry" if dry else size]
    ckpt = continuation.shipped_checkpoint(size)
    continue_from = ckpt if ckpt.is_file() and not dry else None
    overrides = {"batch_size": profile["batch_size"], "device": device, "threads": max(1, (os.cpu_count() or 2) // 2),
                 "autocast": "bf16" if device == "cuda" else "none"}
    if continue_from is None:
        overrides["width"] = profile["width"]
    sets = [s for s in sets if s in SETS]
    verdict_sets = [s for s in sets if s != CALIBRATION_SET]
    base_size, base_dir = baseline_weights(size)
    record: dict = {"size": size, "dry": dry, "budget_s": budget_s, "hardware": hardware_line(device),
                    "device": device, "profile": profile, "continued_from": None if continue_from is None else
                    str(continue_from), "baseline": base_size, "sets": list(sets)}
    echo(f"lease: {size} model, {budget_s:.0f} s budget on {record['hardware']}; "
         f"{'continuing ' + str(continue_from) if continue_from else 'from scratch, width ' + str(profile['width'])}; "
         f"baseline: the shipped {base_size} weights")
    with tempfile.TemporaryDirectory(prefix="lease-", dir=work) as tmp:
        w = pathlib.Path(tmp)
        procs = make_sets(w, sets, set_samples, eval_size, dry)
        pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)

        def baseline_scores() -> dict:  # on the CPU cores while the GPU trains
            wait_sets(procs)
            return {s: score(w / s, base_dir, out / f"eval_{s}_baseline.md") for s in verdict_sets}

        out.mkdir(parents=True, exist_ok=True)
        baseline = pool.submit(baseline_scores)
        t_probe = time.perf_counter()
        step_s = probe_step_seconds(w, profile, overrides, continue_from)
        train_end = t0 + TRAIN_SHARE * budget_s
        planner = StagePlanner(step_s, profile["steps_per_epoch"], train_end, clock=time.perf_counter, echo=echo,
                               epoch_overhead_s=validation_seconds(step_s, profile["val_samples"],
                                                                   profile["batch_size"]))
        echo(f"probe: {time.perf_counter() - t_probe:.1f} s; a warm step "
             + ", ".join(f"{k} {1e3 * v:.0f} ms" for k, v in step_s.items()))
        t_train = time.perf_counter()
        summary = train_on_device(w / "run", None, overrides=overrides, size=profile["image"],
                                  steps_per_epoch=profile["steps_per_epoch"], val_samples=profile["val_samples"],
                                  continue_from=continue_from, plan_stage=planner, echo=echo,
                                  extra_meta={"size": size})
        record["training"] = {"seconds": time.perf_counter() - t_train, "probe_step_s": step_s,
                              "plan": [{k: v for k, v in d.items() if k != "at"} for d in planner.decisions],
                              "epochs": {k: summary["config"][f"{k}_epochs"] for k in step_s},
                              "samples_drawn": summary["samples_drawn"], "autocast": overrides["autocast"]}
        shutil.copytree(w / "run" / "weights", out / "weights")
        for name in ("log.csv", "summary.json"):
            shutil.copy2(w / "run" / name, out / name)
        record["checkpoint_bytes"] = continuation.write(continuation.from_run(w / "run" / "checkpoint.pt", size),
                                                        out / "checkpoint.pt")
        # evaluation: the new graphs on the samples the baseline scored, each set an equal part of the time left
        t_eval = time.perf_counter()
        base = baseline.result()
        pool.shutdown()
        new, ship = {}, True
        for k, s in enumerate(verdict_sets):
            deadline = time.perf_counter() + max(end - time.perf_counter(), 0.0) * 0.7 / (len(verdict_sets) - k)
            new[s] = score(w / s, out / "weights", out / f"eval_{s}_new.md", limit=base[s]["visited"],
                           deadline=deadline)
            better = new[s]["matrix_psnr"] > base[s]["matrix_psnr"]
            ship &= better
            echo(f"{s}: matrix PSNR new {new[s]['matrix_psnr']:.2f} dB, baseline {base[s]['matrix_psnr']:.2f} dB, "
                 f"forward L2 {new[s]['fwd_l2']:.4f} / {base[s]['fwd_l2']:.4f} ({new[s]['samples']} samples)"
                 f"{'' if better else ': not better'}")
        record.update(scores={"new": new, "baseline": base}, ship=bool(ship), eval_s=time.perf_counter() - t_eval)
        if (ship or dry) and CALIBRATION_SET in sets:  # the sigma refitted, its coverage on every set
            from polrig.models import uncertainty_fit

            t_sigma = time.perf_counter()
            with (out / "sigma_fit.log").open("w") as log, contextlib.redirect_stdout(log):
                code = uncertainty_fit.main(["--weights", str(out / "weights"), "--data", str(w / CALIBRATION_SET),
                                             "--check", *[str(w / s) for s in verdict_sets], "--write"])
            if code:
                raise RuntimeError(f"the sigma's refit failed (python -m polrig.models.uncertainty_fit, exit {code})")
            checks = json.loads((out / "weights" / "uncertainty.json").read_text()).get("checks", {})
            record["sigma"] = {"seconds": time.perf_counter() - t_sigma,
                               "within_2sigma": {k: v["within_2sigma"] for k, v in checks.items()}}
    record["total_s"] = time.perf_counter() - t0
    record["over_budget"] = record["total_s"] > budget_s  # a dry run's fixed costs exceed its seconds
    (out / "run.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
    big = [p for p in out.rglob("*") if p.is_file() and p.stat().st_size > MAX_FILE_BYTES]
    if big:
        raise RuntimeError(f"{big[0]} is over the {MAX_FILE_BYTES / 2**20:.0f} MiB a lease brings back")
    where = f"models/weights{'' if size == 'small' else '/' + size}/"
    echo(f"lease: {record['total_s']:.0f} s of {budget_s:.0f} s; ship: {'yes' if record['ship'] else 'no'}"
         + (f" (copy {out}/weights/* and {out}/checkpoint.pt into {where})" if record["ship"] and not dry else
            " (a dry run: tiny networks, never shipped)" if dry else " (the shipped weights stay)"))
    return record


#: Where :func:`ship` puts the new weights' evaluation tables (``benchmarks/results`` of the checkout).
RESULTS_DIR = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "results"


def ship(folder: pathlib.Path, results: pathlib.Path = RESULTS_DIR) -> list[pathlib.Path]:
    """Ship what a lease brought back (``benchmarks/gpu_train.sh``'s ``$OUT``: ``run.json``,
    ``weights.tar``, ``checkpoint.pt``, ``tables.tar.gz``) where its ``run.json`` says the
    shipping rule passed: the graphs, ``model.json`` and ``uncertainty.json`` and the checkpoint
    into the size's folder (:mod:`polrig.models.sizes`), each set's evaluation of the new weights
    into ``results/single_shot_<size>_<set>.json`` (+ ``.md``; ``python -m benchmarks
    single_shot`` reads the held-out ones). A run that did not pass, a dry run, or a folder
    missing a file: :class:`polrig.errors.ConfigError`, nothing copied. Returns the files written."""
    import tarfile

    from polrig.errors import ConfigError
    from polrig.models import sizes

    folder = pathlib.Path(folder)
    missing = [n for n in ("run.json", "weights.tar", "checkpoint.pt", "tables.tar.gz") if not (folder / n).is_file()]
    if missing:
        raise ConfigError(f"--ship {folder}: no {', '.join(missing)} (what benchmarks/gpu_train.sh brings back)")
    run_record = json.loads((folder / "run.json").read_text())
    if run_record.get("dry") or not run_record.get("ship"):
        why = "a dry run" if run_record.get("dry") else "the new weights did not beat the shipped ones on every set"
        raise ConfigError(f"--ship {folder}: not shipped ({why}; run.json)")
    size = run_record["size"]
    dest = sizes.size_folder(size)
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        with tarfile.open(folder / "weights.tar") as t:
            t.extractall(tmp, filter="data")
        with tarfile.open(folder / "tables.tar.gz") as t:
            t.extractall(tmp / "tables", filter="data")
        meta = json.loads((tmp / "weights" / "model.json").read_text())
        if meta.get("size") != size or not (tmp / "weights" / "single_shot.onnx").is_file():
            raise ConfigError(f"--ship {folder}: weights.tar does not hold the {size} model run.json names")
        dest.mkdir(parents=True, exist_ok=True)
        for f in sorted((tmp / "weights").iterdir()):
            shutil.copy2(f, dest / f.name)
            written.append(dest / f.name)
        shutil.copy2(folder / "checkpoint.pt", dest / "checkpoint.pt")
        written.append(dest / "checkpoint.pt")
        for f in sorted((tmp / "tables").glob("eval_*_new.*")):
            name = f.name[len("eval_"):-len("_new" + f.suffix)]
            target = results / f"single_shot_{size}_{name}{f.suffix}"
            shutil.copy2(f, target)
            written.append(target)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.formats.argcheck import int_range, positive_float
    from polrig.models._cli import run_main
    from polrig.models.sizes import SIZES

    ap = argparse.ArgumentParser(prog="python -m polrig.models.lease", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="output folder (new or empty): what the lease brings back")
    ap.add_argument("--ship", default=None, metavar="FOLDER",
                    help="instead of a run: ship what benchmarks/gpu_train.sh brought back into FOLDER, where its "
                         "run.json says the shipping rule passed")
    ap.add_argument("--model-size", choices=SIZES, default="large", help="the size trained (default large)")
    ap.add_argument("--budget-min", type=positive_float, default=8.0, help="wall-clock budget in minutes (default 8)")
    ap.add_argument("--sets", default=",".join(SETS), help="sets made and scored (default all: " + ", ".join(SETS) + ")")
    ap.add_argument("--set-samples", type=int_range(1, 10**5), default=SET_SAMPLES, help="samples per set")
    ap.add_argument("--dry", action="store_true", help="tiny scale on the CPU (the test suite's run)")
    ap.add_argument("--work", default=None, help="folder for the sets and the run (default: a temporary one)")
    args = ap.parse_args(argv)

    def body() -> int:
        from polrig.errors import ConfigError

        if args.ship is not None:
            for f in ship(pathlib.Path(args.ship)):
                print(f"shipped {f}")
            return 0
        if args.out is None:
            raise ConfigError("--out is required (or --ship FOLDER)")
        sets = [s.strip() for s in args.sets.split(",") if s.strip()]
        bad = [s for s in sets if s not in SETS]
        if bad or not sets:
            raise ConfigError(f"--sets: unknown set(s) {bad or 'none given'}; sets are {', '.join(SETS)}")
        run(pathlib.Path(args.out), size=args.model_size, budget_s=60.0 * args.budget_min, dry=args.dry, sets=sets,
            set_samples=args.set_samples, work=None if args.work is None else pathlib.Path(args.work))
        return 0

    return run_main(ap.prog, body)


if __name__ == "__main__":
    sys.exit(main())
