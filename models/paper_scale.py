"""Unattended training of the single-shot networks within a wall-clock budget (issue 22, item 4).

``python -m polrig.models.paper_scale --out DIR [--budget-min 8] [--size 256] [--width W] [--data-share F]``

One run, in order, each phase planned inside the budget ``B``:

1. **Data** (``--data-share``, default :data:`DATA_SHARE` of ``B``): ``polrig sim dataset
   --no-compress`` in one process per CPU core (``--jobs``), each its own seed, making samples
   until the data share is up (then stopped; the shards they finished are kept: each is
   written whole and renamed into place), unless ``--train-samples`` gives the count; their
   shards moved into one training set (no copy: :func:`merge_parts`). Two held-out sets as in
   ``models/MODEL_CARD.md``, unseen shapes (``--holdout``) and new scenes of the training shapes
   (another seed), are made alongside, whole.
2. **Training** (what the data left, less the evaluation's reserve :data:`EVAL_SHARE` of ``B``
   and the final margin :func:`margin_seconds`): PIPNet, then PMMNet, then the direct
   Stokes->MM baseline (:func:`polrig.models.train.train`). The stages share the time as
   :data:`STAGE_SHARES`: PIPNet : PMMNet as the paper's 40 : 20 epochs (2:1), the baseline as
   much as both (the ablation is fair when it had the same time). A probe first trains every
   stage :data:`PROBE_EPOCHS` epochs on :data:`PROBE_BATCHES` batches and keeps the fastest
   epoch after the first (:func:`probe_epoch_seconds`): the first epoch pays the warm-up (CUDA
   context, first kernels, allocator; 0.85 s of a one-batch PIPNet epoch on the H200 below,
   where a warm epoch of 57 batches took 1 s). Each stage's epochs are then chosen when it starts
   (:class:`StagePlanner`, the ``plan_stage`` hook of :func:`polrig.models.train.train`): its share of
   the time really left (the shares of it and the stages after it), divided by its estimated
   epoch (the probe's seconds per sample-epoch times the samples, plus the checkpoint and log
   written after every epoch, times how much longer the finished stages took than so
   estimated, if they did), so whatever a stage did not use goes to the next ones and an
   underestimate is corrected at the next stage. :data:`EXPORT_RESERVE_S` is kept for the
   export. Where the time cannot give every stage :data:`MIN_EPOCHS` on all the samples, the
   first samples that fit are used (a data share too large for the machine, e.g. training on
   the CPU).
3. **Export and check** (inside :func:`polrig.models.train.train`: ONNX, onnxruntime against PyTorch),
   then **evaluation** (until ``B`` less the margin) of the new graphs and of the shipped ones
   on both held-out sets (:func:`evaluate_against_shipped`) and the verdict: ship only if the
   new graphs beat the shipped ones' matrix PSNR of the full method on every held-out set. Only
   :data:`EVAL_METHODS` are scored (the verdict's full model, and the baseline the run trains):
   the other rows of ``polrig evaluate`` do not depend on the graphs, or are mirror variants.
   Every set gets an equal part of the time left; the new graphs score samples in order until
   their half of it is spent (at least :data:`MIN_EVAL_SAMPLES` scored), and the shipped ones
   score exactly the same samples.

How the shares were chosen. The first GPU run (NVIDIA H200, 16 CPU cores, torch 2.11+cu130,
``--budget-min 7.5 --size 256``, width 16, with the planner before this one) made 905 training
samples in 109 s (at most 0.12 s of wall time per sample on 16 processes: its data phase also
decompressed and rewrote the parts into one set, which moving uncompressed shards now avoids,
and its sample count came from a one-sample probe that counted a process's start-up as a
sample's cost, which stopping the processes at the share's end now avoids);
a warm epoch on those samples took 1.0 s for PIPNet, 1.9 s for PMMNet and 0.75 s for the
baseline (1.1, 2.1 and 0.83 ms per sample-epoch; ``log.csv``); the evaluation of all seven
methods took 244 s (1.9 s per sample and graph set, 32 samples, two sets, new and shipped).
With a data share ``D`` and ``T`` of the budget ``B`` for the epochs, the samples are
``D B / 0.12 s`` and PIPNet's epochs ``(T B / 3) / (samples x 1.1 ms)`` = ``36 T / D``: the
paper's 40 PIPNet epochs need ``T`` about ``1.1 D`` (PMMNet then gets ``9.5 T / D`` epochs, its
epochs costing twice PIPNet's). The evaluation keeps :data:`EVAL_SHARE` = 0.15 (the verdict's
two methods cost a quarter of the seven: 0.27 against 1.05 s per sample at 256x256 here, two
busy cores, so about 0.5 s on the H200's cores, 64 s for 32 samples, two sets, both graph sets),
the margin 0.02, and the probe, the loading and the export about 0.07 (30 s of 450), so
``D + T`` = 0.76 and :data:`DATA_SHARE` is 0.35 (``T / D`` = 1.2: about 40 PIPNet epochs on
about 1300 samples in a 7.5 min budget). Beyond the paper's epochs more data is worth more than
more epochs: the run above trained 905 samples for one PIPNet epoch while 60% of its training
time went unused. Where training is slower per sample relative to the cores making data (CPU
training, a slower GPU), a smaller ``--data-share`` keeps the epochs up.

``OUT`` holds only what is worth bringing back (checked below :data:`MAX_OUT_BYTES`):
``weights/`` (graphs, ``model.json``), ``log.csv``, ``summary.json`` (the training run),
``eval_<set>_<new|shipped>.md/.json``, ``run.json`` (hardware, budget, shares, phase times, the
data processes stopped, the training probe, each stage's plan and wall time, the samples
evaluated, the verdict). Datasets,
probe runs and the checkpoint stay in ``--work`` (a temporary folder by default, removed at the
end). The training set lives uncompressed on disk and whole in memory (and on the GPU): about
13 MB per sample at 256x256 on disk, 21 MB in training with PMMNet's initialization; samples
beyond what the memory holds are not used (:func:`samples_that_fit_memory`: about 2600 on an
80 GB GPU). The disk must hold them (about 17 GB for 1300 samples).

Device: PyTorch trains on the CUDA GPU where it sees one (:attr:`polrig.models.train.TrainConfig.device`;
the data generation and the evaluation stay on the CPU cores), else on the CPU; ``run.json``
records which, with the hardware. The width defaults to :data:`DEFAULT_WIDTH`.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import pathlib
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence

#: Share of the budget for the data (``--data-share``; module docstring: how it was chosen).
DATA_SHARE = 0.35
#: Share of the budget kept for the evaluation when the training is planned (the evaluation
#: itself uses whatever is left until the margin).
EVAL_SHARE = 0.15
#: Final margin (writing ``run.json``, removing the work folder): this share of the budget, at
#: least :data:`MIN_MARGIN_S` seconds.
MARGIN_SHARE = 0.02
MIN_MARGIN_S = 2.0
#: Seconds kept after the last epoch for the export and its onnxruntime check (CPU).
EXPORT_RESERVE_S = 10.0
#: Training-time ratios of the stages (PIPNet : PMMNet as the paper's 40 : 20 epochs; the direct
#: baseline as much as both), in the order :func:`polrig.models.train.train` runs them.
STAGE_SHARES = {"pipnet": 2 / 6, "pmmnet": 1 / 6, "direct": 3 / 6}
#: The fewest epochs a stage is planned on all the training samples: a tenth of the paper's 40 +
#: 20 (the baseline as PMMNet), so that the learning rate decays (polrig.models.train.lr_at) and the
#: samples are seen more than once. Where the budget cannot give them, the training uses the
#: first samples that fit (:func:`samples_that_fit`; the data share was too large for the machine).
MIN_EPOCHS = {"pipnet": 4, "pmmnet": 2, "direct": 2}
#: :func:`samples_that_fit` plans the fewest epochs in this share of the time left, the rest kept
#: for the loading, PMMNet's initialization and the estimates' errors.
FIT_SHARE = 0.8
#: Memory a training sample takes where it trains (and on the host while it loads), as a multiple
#: of its bytes in an uncompressed shard: its arrays plus PMMNet's initialization (half as much
#: again at 256x256: 27 planes on 52); and the share of the free memory the training set may fill
#: (the rest: activations, the allocator, the loading's copies). More samples than fit are not used.
SAMPLE_MEMORY_FACTOR = 1.6
MEMORY_SHARE = 0.6
#: The training probe: this many epochs of every stage on this many batches; the fastest epoch
#: after the first is its time (the first pays the warm-up; the fastest is the one another job
#: on the machine disturbed least).
PROBE_EPOCHS = 3
PROBE_BATCHES = 4
#: Without ``--train-samples`` each data process is asked for this many samples and stopped at
#: the data share's end; shards of this many samples (a stop loses at most one shard's work).
OPEN_COUNT = 100_000
OPEN_SHARD_SIZE = 2
#: What the verdict's evaluation scores (:func:`polrig.models.evaluate.evaluate` methods), and the
#: fewest scored samples per held-out set whatever the time left.
EVAL_METHODS = ("full", "direct")
MIN_EVAL_SAMPLES = 8
DEFAULT_WIDTH = 16
#: The output folder must stay small enough to bring back from a lent machine.
MAX_OUT_BYTES = 16 * 2**20
HOLDOUT_SETS = {"unseen_shapes": True, "new_scenes": False}  # name -> --holdout
#: Seeds: the training parts take ``seed * 1000 + part``; the held-out sets their own.
HOLDOUT_SEEDS = {"unseen_shapes": 900_001, "new_scenes": 900_002}

Clock = Callable[[], float]


# ----------------------------------------------------------------------------- phase 1: data

def _sim_dataset(out: pathlib.Path, count: int, size: int, seed: int, holdout: bool,
                 shard_size: int = 16) -> subprocess.Popen:
    """``polrig sim dataset`` (uncompressed shards) in a child process (its own CPU core)."""
    argv = [sys.executable, "-m", "polrig", "sim", "dataset", "--count", str(count), "--size", str(size),
            "--seed", str(seed), "--shard-size", str(shard_size), "--no-compress", "--quiet",
            "--out", str(out)] + (["--holdout"] if holdout else [])
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait(procs: Sequence[subprocess.Popen], deadline: float | None = None,
          clock: Clock = time.perf_counter) -> int:
    """Wait for every process, or until ``deadline`` (a ``clock`` value), when the ones still
    running are stopped (their finished shards stay: each is written whole and renamed into
    place). Returns how many were stopped. :class:`RuntimeError` with the last line of the first
    failure's stderr."""
    while deadline is not None and any(p.poll() is None for p in procs) and clock() < deadline:
        time.sleep(0.02)
    stopped = [p for p in procs if p.poll() is None] if deadline is not None else []
    for p in stopped:
        p.terminate()
    failures = []
    for p in procs:  # every one waited for before any error
        _, err = p.communicate()
        if p.returncode and p not in stopped:
            failures.append((err or "").strip().splitlines()[-1:] or [f"exit status {p.returncode}"])
    if failures:
        raise RuntimeError(f"polrig sim dataset failed: {failures[0][0]}")
    return len(stopped)


def shard_samples(path: pathlib.Path) -> int:
    """Samples in a dataset shard, from its ``analyzer`` array's header (nothing else read)."""
    import zipfile

    import numpy as np

    with zipfile.ZipFile(path) as z, z.open("analyzer.npy") as f:
        major, _ = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
        return int(read(f)[0][0])


def merge_parts(parts: Sequence[pathlib.Path], out: pathlib.Path) -> int:
    """One dataset folder ``out`` from ``parts`` (``polrig sim dataset`` folders of the same size,
    different seeds, each possibly stopped before its count): the shard files they hold moved
    (not copied) into ``out`` as ``shard-PPP-SSSSS.npz``, so :func:`polrig.models.data.load_dataset`
    (shards sorted by name) reads the parts' samples in order; the manifest is the first part's
    with the samples there are, the new shard names, the union of the families present and the
    parts' seeds. Parts with no manifest (stopped while starting) hold nothing. Returns the count."""
    from polrig.models.data import read_manifest

    out.mkdir(parents=True, exist_ok=True)
    parts = [p for p in parts if (p / "manifest.json").is_file()]
    manifests = [read_manifest(p) for p in parts]
    names: list[str] = []
    count = 0
    for k, part in enumerate(parts):
        for j, shard in enumerate(sorted(part.glob("shard-*.npz"))):
            names.append(f"shard-{k:03d}-{j:05d}.npz")
            count += shard_samples(shard)
            shard.rename(out / names[-1])
    families: list = []
    for m in manifests:
        families += [f for f in m.get("families_present") or [] if f not in families]
    manifest = dict(manifests[0] if manifests else {}, count=count, n_shards=len(names), shards=names,
                    merged_seeds=[m.get("seed") for m in manifests])
    if families:
        manifest["families_present"] = families
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return count


def generate_data(work: pathlib.Path, *, size: int, seconds: float, jobs: int, seed: int,
                  train_samples: int | None, holdout_samples: int, echo=print,
                  clock: Clock = time.perf_counter) -> dict:
    """Phase 1 (module docstring): the training set ``work/train`` and the held-out sets
    ``work/<name>``; returns counts, seeds and seconds. Without ``train_samples`` every process
    makes samples until ``seconds`` are up (shards of :data:`OPEN_SHARD_SIZE`)."""
    t0 = clock()
    held = [_sim_dataset(work / name, holdout_samples, size, HOLDOUT_SEEDS[name] + seed, flag)
            for name, flag in HOLDOUT_SETS.items()]
    if train_samples is None:
        counts, shard_size, deadline = [OPEN_COUNT] * jobs, OPEN_SHARD_SIZE, t0 + seconds
    else:
        counts = [train_samples // jobs + (k < train_samples % jobs) for k in range(jobs)]
        shard_size, deadline = 16, None
    parts = [(work / f"train-part{k}", seed * 1000 + k, c) for k, c in enumerate(counts) if c]
    try:
        stopped = _wait([_sim_dataset(d, c, size, s, False, shard_size) for d, s, c in parts], deadline, clock)
    except BaseException:
        _wait(held, clock(), clock)  # stop the held-out sets too
        raise
    made_s = clock() - t0
    _wait(held)
    n = merge_parts([d for d, _, _ in parts], work / "train")
    for d, _, _ in parts:
        if d.exists():  # a process stopped while starting made none
            shutil.rmtree(d)
    if n < 1:
        raise RuntimeError(f"no training sample made in {made_s:.1f} s (a larger --budget-min or --data-share)")
    seconds_taken = clock() - t0
    echo(f"data: {n} training samples at {size}x{size} in {len(parts)} processes in {made_s:.1f} s"
         f"{f' ({stopped} stopped at the data share)' if stopped else ''}, {holdout_samples} per held-out set; "
         f"{seconds_taken:.1f} s")
    return {"train_samples": n, "holdout_samples": holdout_samples, "size": size, "jobs": jobs,
            "train_seeds": [s for _, s, _ in parts], "holdout_seeds": {k: v + seed for k, v in HOLDOUT_SEEDS.items()},
            "stopped_at_share": stopped, "train_seconds": made_s, "seconds": seconds_taken}


# ----------------------------------------------------------------------------- phase 2: training

def plan_epochs(stage_seconds: Mapping[str, float], probe_samples: int, samples: int, seconds: float) -> dict[str, int]:
    """Epochs per stage that fit ``seconds`` of training on ``samples`` samples, where one epoch
    of a stage on ``probe_samples`` samples takes ``stage_seconds[stage]``: each stage of
    ``stage_seconds`` (all of them, or the ones still to run) gets its :data:`STAGE_SHARES`
    share, renormalised over the stages given, at least one epoch."""
    total = sum(STAGE_SHARES[k] for k in stage_seconds)
    epochs = {}
    for stage, secs in stage_seconds.items():
        per_epoch = max(secs, 1e-9) / max(probe_samples, 1) * samples
        epochs[stage] = max(1, int(STAGE_SHARES[stage] / total * seconds / per_epoch))
    return epochs


def estimate_correction(epoch_estimates: Mapping[str, float], finished: Sequence[tuple[str, int, float]]) -> float:
    """How much longer the ``finished`` stages (``(stage, epochs, wall seconds)``: from the
    stage's start to the next one's, checkpoints included, and the next stage's preparation
    such as PMMNet's initialization) took than their epochs at ``epoch_estimates[stage]``
    seconds: the ratio of the sums, 1 with none, kept within [1, 4]. Never below 1: a stage
    that ran faster than estimated leaves its time to the next ones anyway, and its error need
    not be the next stage's (a probe epoch slowed by another job on the machine made one stage
    look ten times slower than it was, and the next one, estimated right, then overran); one
    that ran slower makes the next ones planned as cautiously, up to 4 times."""
    est = sum(epochs * epoch_estimates[stage] for stage, epochs, _ in finished)
    real = sum(wall for _, _, wall in finished)
    return 1.0 if est <= 0 else min(max(real / est, 1.0), 4.0)


class StagePlanner:
    """The ``plan_stage`` hook of :func:`polrig.models.train.train` for epochs that must end by
    ``deadline`` (a ``clock`` value). An epoch of a stage is estimated at
    ``sample_epoch_s[stage] * samples + epoch_overhead_s`` (the probe's warm compute, and the
    checkpoint and log written after every epoch), times :func:`estimate_correction` of the
    stages finished so far (their wall time against their estimate). A stage starting gets its
    :data:`STAGE_SHARES` share of the time left, renormalised over it and the stages after it
    (:func:`plan_epochs`). ``decisions`` records each plan (for ``run.json``)."""

    def __init__(self, sample_epoch_s: Mapping[str, float], samples: int, deadline: float, *,
                 epoch_overhead_s: float = 0.0, clock: Clock = time.perf_counter, echo=lambda s: None):
        self.epoch_s = {k: float(v) * samples + epoch_overhead_s for k, v in sample_epoch_s.items()}
        self.deadline, self.clock, self.echo = deadline, clock, echo
        self.decisions: list[dict] = []
        self._started: float | None = None

    def initial(self) -> dict[str, int]:
        """The whole plan as it stands before any stage ran."""
        return plan_epochs(self.epoch_s, 1, 1, max(self.deadline - self.clock(), 0.0))

    def finished(self, now: float) -> list[tuple[str, int, float]]:
        """``(stage, epochs, wall seconds)`` of the stages planned so far, the last one ending
        at ``now``."""
        starts = [d["at"] for d in self.decisions] + [now]
        return [(d["stage"], d["epochs"], starts[k + 1] - starts[k]) for k, d in enumerate(self.decisions)]

    def __call__(self, stage: str, rows: Sequence[Mapping] = ()) -> int:
        now = self.clock()
        order = list(STAGE_SHARES)
        left = {k: self.epoch_s[k] for k in order[order.index(stage):]}
        correction = estimate_correction(self.epoch_s, self.finished(now))
        seconds = max(self.deadline - now, 0.0)
        epochs = plan_epochs({k: v * correction for k, v in left.items()}, 1, 1, seconds)[stage]
        self.decisions.append({"stage": stage, "at": now, "seconds_left": seconds, "correction": correction,
                               "epoch_s_estimate": left[stage] * correction, "epochs": epochs})
        self.echo(f"training {stage}: {epochs} epoch(s) of ~{left[stage] * correction:.2f} s, "
                  f"{seconds:.0f} s left for it and {len(left) - 1} stage(s) after it")
        return epochs


def samples_that_fit(sample_epoch_s: Mapping[str, float], epoch_overhead_s: float, seconds: float,
                     min_epochs: Mapping[str, int] = MIN_EPOCHS) -> int:
    """The most samples on which every stage gets its ``min_epochs`` within its
    :data:`STAGE_SHARES` share of ``seconds``, an epoch taking ``sample_epoch_s[stage]`` per
    sample plus ``epoch_overhead_s`` (at least 0)."""
    fit = min((STAGE_SHARES[k] * seconds / min_epochs[k] - epoch_overhead_s) / max(sample_epoch_s[k], 1e-12)
              for k in STAGE_SHARES)
    return max(int(fit), 0)


def samples_that_fit_memory(sample_bytes: float, free_bytes: float) -> int:
    """The most training samples of ``sample_bytes`` each (uncompressed on disk) that fit in
    ``free_bytes`` of memory (:data:`SAMPLE_MEMORY_FACTOR`, :data:`MEMORY_SHARE`)."""
    return max(int(MEMORY_SHARE * free_bytes / (SAMPLE_MEMORY_FACTOR * max(sample_bytes, 1.0))), 0)


def available_memory(device: str) -> int:
    """Bytes the training set can use: half the host's available memory (``MemAvailable``:
    loading holds the shards and their concatenation at once), and on ``cuda`` at most the
    GPU's free memory."""
    host = None
    try:
        for line in pathlib.Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                host = int(line.split()[1]) * 1024
    except OSError:
        pass
    if host is None:
        host = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    free = host // 2
    if device == "cuda":
        import torch

        free = min(free, int(torch.cuda.mem_get_info()[0]))
    return free


def probe_epoch_seconds(work: pathlib.Path, base, samples: int,
                        clock: Clock = time.perf_counter) -> tuple[dict[str, float], float, int]:
    """``(seconds per sample-epoch of each stage, seconds per epoch besides, probe samples)``:
    every stage trained :data:`PROBE_EPOCHS` epochs on the first ``min(samples, PROBE_BATCHES *
    batch_size)`` samples (no export); the compute is the fastest epoch's ``epoch_s`` after the
    first (which pays the warm-up) per sample, the rest what the last stage's wall time holds
    beyond its epochs' ``epoch_s`` (checkpoint and log after every epoch), per epoch."""
    from polrig.models.train import train

    n = min(samples, PROBE_BATCHES * base.batch_size)
    config = dataclasses.replace(base, limit=n, pipnet_epochs=PROBE_EPOCHS, pmmnet_epochs=PROBE_EPOCHS,
                                 direct_epochs=PROBE_EPOCHS)
    starts: dict[str, float] = {}

    def hook(stage: str, rows) -> int:
        starts[stage] = clock()
        return PROBE_EPOCHS

    train(work / "train", work / "probe-run", config, export=False, echo=lambda s: None, plan_stage=hook)
    ended = clock()
    last_stage = list(STAGE_SHARES)[-1]
    with (work / "probe-run" / "log.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    warm = {k: min(float(r["epoch_s"]) for r in rows if r["stage"] == k and int(r["epoch"]) > 0) for k in STAGE_SHARES}
    compute = sum(float(r["epoch_s"]) for r in rows if r["stage"] == last_stage)
    overhead = max(ended - starts[last_stage] - compute, 0.0) / PROBE_EPOCHS
    return {k: warm[k] / n for k in STAGE_SHARES}, overhead, n


def train_in_budget(work: pathlib.Path, *, seconds: float, width: int, seed: int, epochs: int | None = None,
                    echo=print, clock: Clock = time.perf_counter) -> dict:
    """Phase 2 (module docstring): probe, train with a :class:`StagePlanner` (epochs ending
    :data:`EXPORT_RESERVE_S` before ``seconds`` are up), export into ``work/run``. ``epochs``:
    that many epochs of every stage instead (no probe, no plan). Returns the epochs, the probe,
    the samples used (the first ones, fewer than made where :func:`samples_that_fit_memory` or
    :func:`samples_that_fit` say so), the plan (each
    stage's decision and its wall seconds, the last one's with the export) and the seconds
    taken."""
    from polrig.models.train import TrainConfig, train

    t0 = clock()
    base = TrainConfig(width=width, seed=seed, threads=max(1, os.cpu_count() or 1), device=training_device())
    n = _count(work / "train")
    record: dict = {"probe": None, "plan": None}
    fit = samples_that_fit_memory(folder_bytes(work / "train") / max(n, 1), available_memory(base.device))
    base, n = _first_samples(base, n, fit, f"the training set does not fit in the {base.device}'s memory", echo)
    planner = None
    if epochs is None:
        sample_epoch_s, overhead, probe_n = probe_epoch_seconds(work, base, n, clock)
        deadline = t0 + seconds - EXPORT_RESERVE_S
        fit = samples_that_fit(sample_epoch_s, overhead, FIT_SHARE * (deadline - clock()))
        base, n = _first_samples(base, n, fit, f"too many samples for {', '.join(f'{v} {k}' for k, v in MIN_EPOCHS.items())} "
                                 f"epochs in the budget (a smaller --data-share fits this machine)", echo)
        planner = StagePlanner(sample_epoch_s, n, deadline, epoch_overhead_s=overhead, clock=clock, echo=echo)
        first = planner.initial()
        record["probe"] = {"samples": probe_n, "epochs": PROBE_EPOCHS, "seconds": clock() - t0,
                           "seconds_per_sample_epoch": sample_epoch_s, "epoch_overhead_s": overhead}
        echo(f"training: {planner.deadline - clock():.0f} s for the epochs on {n} samples; probe (warm epoch): "
             + ", ".join(f"{k} {1e3 * v:.2f} ms" for k, v in sample_epoch_s.items())
             + f" per sample-epoch, {1e3 * overhead:.0f} ms per epoch besides; plan "
             + ", ".join(f"{k} {v}" for k, v in first.items()) + " epochs (each stage re-planned when it starts)")
        config = dataclasses.replace(base, **{f"{k}_epochs": v for k, v in first.items()})
    else:
        config = dataclasses.replace(base, **{f"{k}_epochs": epochs for k in STAGE_SHARES})
    record["samples_used"] = n
    summary = train(work / "train", work / "run", config, echo=lambda s: None, plan_stage=planner)
    done = {k: int(summary["config"][f"{k}_epochs"]) for k in STAGE_SHARES}
    if planner is not None:
        end = clock()
        record["plan"] = [dict({k: v for k, v in d.items() if k != "at"}, wall_s=wall)
                          for d, (_, _, wall) in zip(planner.decisions, planner.finished(end))]
        late = end - (t0 + seconds)
        echo(f"training: done with the export {abs(late):.1f} s {'after' if late > 0 else 'before'} its end")
    return {"epochs": done, **record, "epoch_seconds": summary["train_seconds"], "summary": summary,
            "seconds": clock() - t0}


def _first_samples(base, n: int, fit: int, why: str, echo) -> tuple:
    """``(config, samples)``: ``base`` training on the first ``fit`` of ``n`` samples (at least a
    batch, or all where fewer) where ``fit < n``, else as it is."""
    if fit >= n:
        return base, n
    use = max(fit, min(n, base.batch_size))
    echo(f"training: {why}; the first {use} of {n} samples are used")
    return dataclasses.replace(base, limit=use), use


def _count(folder: pathlib.Path) -> int:
    return int(json.loads((folder / "manifest.json").read_text())["count"])


# ----------------------------------------------------------------------------- phase 3: verdict

def evaluation_deadline(now: float, end: float, sets_left: int) -> float:
    """When the new graphs stop starting samples of the next held-out set: each set left gets
    an equal part of the time until ``end``, half for the new graphs and half for the shipped
    ones on the same samples (no later than ``now`` where the time is up)."""
    return now + max(end - now, 0.0) / max(sets_left, 1) / 2


def evaluate_against_shipped(work: pathlib.Path, weights: pathlib.Path, out: pathlib.Path, *,
                             end: float | None = None, clock: Clock = time.perf_counter, echo=print) -> dict:
    """Phase 3: both held-out sets scored with the new and the shipped graphs
    (:data:`EVAL_METHODS`), within ``end`` (a ``clock`` value; None: every sample) as
    :func:`evaluation_deadline` shares it, at least :data:`MIN_EVAL_SAMPLES` samples each; the
    tables go to ``out/eval_<set>_<new|shipped>.md`` (+ ``.json``). ``ship`` is True only if
    the new graphs' matrix PSNR of the full method beats the shipped ones' on every set."""
    from polrig.models.evaluate import evaluate, write_results
    from polrig.models.runtime import WEIGHTS_DIR

    scores, samples, ship = {}, {}, True
    for k, name in enumerate(HOLDOUT_SETS):
        deadline = None if end is None else evaluation_deadline(clock(), end, len(HOLDOUT_SETS) - k)
        new = evaluate(work / name, weights, methods=EVAL_METHODS, deadline=deadline,
                       min_samples=MIN_EVAL_SAMPLES, echo=lambda s: None)
        shipped = evaluate(work / name, WEIGHTS_DIR, methods=EVAL_METHODS, limit=new["samples_visited"],
                           echo=lambda s: None)
        for which, result in (("new", new), ("shipped", shipped)):
            write_results(result, out / f"eval_{name}_{which}.md")
        scores[name] = {w: r["methods"]["full"]["matrix_psnr"] for w, r in (("new", new), ("shipped", shipped))}
        samples[name] = {"scored": new["samples"], "visited": new["samples_visited"], "of": _count(work / name)}
        ship &= scores[name]["new"] > scores[name]["shipped"]
        echo(f"{name}: matrix PSNR new {scores[name]['new']:.2f} dB, shipped {scores[name]['shipped']:.2f} dB "
             f"({new['samples']} samples scored of the first {new['samples_visited']} of {samples[name]['of']})")
    return {"matrix_psnr_db": scores, "eval_samples": samples, "ship": bool(ship)}


# ----------------------------------------------------------------------------- the run

def training_device() -> str:
    """``cuda`` where PyTorch sees a CUDA GPU, else ``cpu`` (:attr:`polrig.models.train.TrainConfig.device`)."""
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


def margin_seconds(budget_s: float) -> float:
    """The final margin of a run of ``budget_s`` seconds (:data:`MARGIN_SHARE`, :data:`MIN_MARGIN_S`)."""
    return max(MARGIN_SHARE * budget_s, MIN_MARGIN_S)


def check_data_share(share: float) -> float:
    """``share`` if the data can have it (0 < share and the evaluation's and the margin's shares
    still fit), else :class:`polrig.errors.ConfigError`."""
    from polrig.errors import ConfigError

    top = 1.0 - EVAL_SHARE - MARGIN_SHARE
    if not 0.0 < share < top:
        raise ConfigError(f"--data-share {share:g}: must be above 0 and below {top:g} (the evaluation keeps "
                          f"{EVAL_SHARE:g} of the budget and the margin {MARGIN_SHARE:g})")
    return share


def run(out: pathlib.Path, *, budget_s: float, size: int, width: int, jobs: int, seed: int,
        train_samples: int | None, holdout_samples: int, epochs: int | None = None,
        work: pathlib.Path | None = None, data_share: float = DATA_SHARE, echo=print) -> dict:
    """The whole run (module docstring); returns ``run.json``'s content."""
    from polrig.formats.argcheck import check_output_folder

    check_data_share(data_share)
    out = check_output_folder(out)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty (a run writes into an empty folder)")
    t0 = time.perf_counter()
    end = t0 + budget_s - margin_seconds(budget_s)
    with tempfile.TemporaryDirectory(prefix="paper-scale-", dir=work) as tmp:
        w = pathlib.Path(tmp)
        data = generate_data(w, size=size, seconds=data_share * budget_s, jobs=jobs, seed=seed,
                             train_samples=train_samples, holdout_samples=holdout_samples, echo=echo)
        training = train_in_budget(w, seconds=max(end - EVAL_SHARE * budget_s - time.perf_counter(), 0.0),
                                   width=width, seed=seed, epochs=epochs, echo=echo)
        out.mkdir(parents=True, exist_ok=True)
        shutil.copytree(w / "run" / "weights", out / "weights")
        for name in ("log.csv", "summary.json"):
            shutil.copy2(w / "run" / name, out / name)
        t_eval = time.perf_counter()
        verdict = evaluate_against_shipped(w, out / "weights", out, end=end, echo=echo)
        eval_s = time.perf_counter() - t_eval
    record = {"budget_s": budget_s, "total_s": time.perf_counter() - t0, "hardware": hardware(),
              "shares": {"data": data_share, "eval": EVAL_SHARE, "margin_s": margin_seconds(budget_s),
                         "export_reserve_s": EXPORT_RESERVE_S, "stages": STAGE_SHARES},
              "data": data, "training": {k: v for k, v in training.items() if k != "summary"},
              "width": width, "seed": seed, "eval_s": eval_s, "eval_methods": list(EVAL_METHODS), **verdict}
    (out / "run.json").write_text(json.dumps(record, indent=2, default=str) + "\n")
    size_b = folder_bytes(out)
    if size_b > MAX_OUT_BYTES:
        raise RuntimeError(f"{out} holds {size_b / 2**20:.1f} MiB, over the {MAX_OUT_BYTES / 2**20:.0f} MiB "
                           f"that can be brought back (a smaller --width)")
    over = record["total_s"] > budget_s
    echo(f"wrote {out} ({size_b / 2**20:.2f} MiB) in {record['total_s']:.0f} s of a {budget_s:.0f} s budget "
         f"(data {data['seconds']:.0f} s, training {training['seconds']:.0f} s, evaluation {eval_s:.0f} s)"
         f"{' (OVER BUDGET: the fixed costs exceed it)' if over else ''}; ship: {'yes' if verdict['ship'] else 'no'}")
    return record


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.formats.argcheck import int_range, positive_float
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.paper_scale", description=__doc__.split("\n\n")[0])
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
    ap.add_argument("--data-share", type=positive_float, default=DATA_SHARE,
                    help=f"share of the budget for making the data (default {DATA_SHARE:g})")
    ap.add_argument("--seed", type=int_range(0, 10**6), default=0)
    ap.add_argument("--work", default=None, help="folder for the datasets and checkpoints (default: a temporary one)")
    args = ap.parse_args(argv)

    def body() -> int:
        from polrig.errors import ConfigError

        if args.size % 8:
            raise ConfigError(f"--size {args.size}: must be a multiple of 8 (the networks' size multiple)")
        if args.width % 4:
            raise ConfigError(f"--width {args.width}: must be a multiple of 4 (the attention heads split the channels)")
        check_data_share(args.data_share)
        run(pathlib.Path(args.out), budget_s=60.0 * args.budget_min, size=args.size, width=args.width,
            jobs=args.jobs, seed=args.seed, train_samples=args.train_samples, holdout_samples=args.holdout_samples,
            epochs=args.epochs, data_share=args.data_share,
            work=None if args.work is None else pathlib.Path(args.work))
        return 0

    return run_main(ap.prog, body)


if __name__ == "__main__":
    sys.exit(main())
