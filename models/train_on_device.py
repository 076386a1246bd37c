"""Training on scenes made on the training device (issue 32, item 1): ``polrig train --data
on-device --size N [--steps-per-epoch K]``.

The stages, losses, augmentations, learning-rate schedule and export are those of
:func:`polrig.models.train.train`; the data are not a folder but :class:`polrig.models.scenes_torch.SceneGenerator`
on the training device: every optimizer step draws a fresh batch of ``batch_size`` scenes (no
disk, no worker pool, no sample seen twice), an epoch is ``steps_per_epoch`` steps, and the
validation loss is measured on one fixed set of ``val_samples`` scenes drawn from another seed.
PMMNet's PIPNet-pBRDF initialization (:func:`polrig.models.train.add_initialization`) is made per batch.

Each epoch writes ``OUT/checkpoint.pt`` (the networks, optimizers and log, in the format of
:func:`polrig.models.train.train`: usable as ``--init-from`` of a dataset run), ``OUT/log.csv``;
the end ``OUT/summary.json`` and, unless ``export=False``, ``OUT/weights/``.

``continue_from`` (``--continue-from``: a checkpoint, or a shipped size's committed one,
:mod:`polrig.models.continuation`) goes on training its networks, with its optimizers' states where
it holds them (else fresh ones, said in a note), its recipe and architecture, and a fresh
learning-rate schedule of this run's epochs; networks recovered from ONNX graphs first get the
batch-norm statistics of generated batches. The lineage of every run is carried into the
checkpoints and ``model.json`` (:mod:`polrig.models.lineage`). ``plan_stage(stage, rows)`` sets
each stage's epochs when it starts, as in :func:`polrig.models.train.train` (the GPU lease,
:mod:`polrig.models.lease`, plans them from its budget). Not supported yet: ``--resume`` of an
on-device run, ``--init-from``/``--stages`` (refused, :class:`ConfigError`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time
from typing import Callable

import numpy as np
import torch

from polrig.atomic import atomic_write_text
from polrig.errors import ConfigError
from polrig.formats.argcheck import check_output_folder
from polrig.models.lineage import hardware_line, run_entries
from polrig.models.lineage import totals as lineage_totals
from polrig.models.pipnet import PIPNet
from polrig.models.pmmnet import DirectStokesToMM, PMMNet
from polrig.models.scenes_torch import (
    COVERED_FAMILIES,
    SceneGenerator,
    training_tensors,
)
from polrig.models.train import (
    RECALIBRATION_SAMPLES,
    STAGE_INPUTS,
    STAGES,
    TrainConfig,
    TrainingError,
    _check_config,
    _check_export_possible,
    _echo_row,
    _load_donor,
    _pick,
    _reason,
    _run_files,
    _write_log,
    add_initialization,
    continue_checkpoint,
    continued_config,
    direct_step,
    lr_at,
    pipnet_step,
    pmmnet_step,
    save_checkpoint,
    step_with_augmentations,
    with_precision,
)

#: What ``--data`` names to train on the generator instead of a dataset folder.
ON_DEVICE = "on-device"


def generator_identity(size: int, seed: int, families, material_mix: str) -> dict:
    """What the checkpoint and summary record as the run's data."""
    return {"generator": "polrig.models.scenes_torch.SceneGenerator", "width": size, "height": size,
            "seed": seed, "families_present": list(families), "material_mix": material_mix,
            "stage_zero_axes": "random"}


def train_on_device(out_dir: str | pathlib.Path, config: TrainConfig | None = None, *, size: int = 64,
                    steps_per_epoch: int = 64, val_samples: int = 32, overrides: dict | None = None,
                    families=COVERED_FAMILIES, material_mix: str = "baek", export: bool = True, overwrite: bool = False,
                    echo: Callable[[str], None] = print, continue_from: str | pathlib.Path | None = None,
                    plan_stage: Callable[[str, list[dict]], int] | None = None, extra_meta: dict | None = None) -> dict:
    """Train every stage on fresh generated batches (module docstring); returns the summary
    written to ``OUT/summary.json``. ``families`` and ``material_mix``: what the generator draws
    (:data:`polrig.models.scenes_torch.COVERED_FAMILIES`, :data:`polrig.models.scenes_torch.COVERED_MIXES`).
    ``extra_meta``: further ``model.json`` entries of the export (the lease's ``size``)."""
    overrides = dict(overrides or {})
    unknown = [k for k in overrides if k not in {f.name for f in dataclasses.fields(TrainConfig)}]
    if unknown:
        raise ConfigError(f"unknown training setting(s) {unknown}")
    donor = None
    if continue_from is not None:
        donor = _load_donor(continue_from)  # a missing or damaged file: one line naming it
        if config is None:
            config = continued_config(donor, overrides, continue_from)
            overrides.setdefault("seed", len(donor.get("lineage") or []))  # scenes no earlier run drew
    config = dataclasses.replace(config or TrainConfig(), **overrides)
    epochs = {"pipnet": config.pipnet_epochs, "pmmnet": config.pmmnet_epochs, "direct": config.direct_epochs}
    _check_config(config, STAGES, epochs)
    for name, value in (("steps per epoch", steps_per_epoch), ("validation samples", val_samples)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
    out = pathlib.Path(out_dir)
    check_output_folder(out)
    found = _run_files(out)
    if found and not overwrite:
        raise FileExistsError(f"--out {out} holds another training run ({found[0].name}); replace it with "
                              f"--overwrite or choose another folder (an on-device run cannot be resumed yet)")
    if export:
        _check_export_possible()
    device = torch.device(config.device)
    gen = SceneGenerator(size, seed=config.seed, device=device, families=families,
                         material_mix=material_mix)  # checks the size, families and mix
    val_gen = SceneGenerator(size, seed=config.seed + 1_000_003, device=device, families=families,
                             material_mix=material_mix)
    identity = generator_identity(size, config.seed, gen.families, gen.material_mix)
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    val = training_tensors(val_gen.batch(val_samples))
    val_idx = torch.arange(val_samples)
    models = {"pipnet": PIPNet(3, config.width, config.sfp_prior), "pmmnet": PMMNet(3, config.width),
              "direct": DirectStokesToMM(3, config.width)}
    models = {k: m.to(device) for k, m in models.items()}
    plain = {"pipnet": pipnet_step, "pmmnet": pmmnet_step, "direct": direct_step}
    opts = {k: torch.optim.Adam(m.parameters(), lr=config.lr) for k, m in models.items()}
    continued_optimizer, recalibrate = False, set()
    if donor is not None:
        try:
            for k in STAGES:
                models[k].load_state_dict(donor["models"][k])
        except (RuntimeError, KeyError, ValueError) as exc:
            raise ConfigError(f"--continue-from {continue_from}: its networks do not fit the ones configured "
                              f"here (width {config.width}, sfp_prior {config.sfp_prior}): {_reason(exc)}") from exc
        continued_optimizer = continue_checkpoint(donor, opts, continue_from, echo)
        if donor.get("recovered_from_onnx"):
            recalibrate = set(STAGES)
    before = list((donor or {}).get("lineage") or [])
    start_kind = "continued" if donor is not None else "scratch"
    model_size = (extra_meta or {}).get("size", (donor or {}).get("size"))

    def lineage() -> list[dict]:
        return before + run_entries(rows, run=str(out), start=start_kind,
                                    steps_per_epoch={k: steps_per_epoch for k in STAGES},
                                    data=f"{ON_DEVICE} {size}x{size}",
                                    device=config.device, hardware=hardware_line(config.device),
                                    optimizer="continued" if continued_optimizer else "fresh")

    times = {k: 0.0 for k in STAGES}
    gen_seconds = {k: 0.0 for k in STAGES}
    rows: list[dict] = []
    ckpt_path = out / "checkpoint.pt"
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        for f in _run_files(out):
            f.unlink()
    echo(f"data: on-device generator, {size}x{size}, families {', '.join(gen.families)}, materials {material_mix}, "
         f"{config.batch_size} fresh samples per step, {steps_per_epoch} steps per epoch, {val_samples} val")

    def save(stage: str, epoch: int) -> None:
        save_checkpoint(ckpt_path, config=config, epochs=epochs, stage=stage, epoch=epoch, stages=STAGES,
                        models=models, opts=opts, times=times, rng=rng, recalibrate=[], rows=rows,
                        dataset=identity, data=ON_DEVICE, init_from=None if continue_from is None else str(continue_from),
                        generator_state=gen.generator.get_state(), lineage_before=before, lineage=lineage(),
                        start_kind=start_kind, size=model_size)

    for stage in STAGES:
        model, opt = models[stage], opts[stage]
        if stage == "pmmnet":
            add_initialization(models["pipnet"].eval(), val)
        if stage in recalibrate:  # batch norms of a network recovered from ONNX (polrig.models.recover)
            _recalibrate(stage, models, gen, config)
            echo(f"{stage}: batch-norm statistics of the recovered network set on {RECALIBRATION_SAMPLES} "
                 f"generated samples")
        if plan_stage is not None:
            planned = plan_stage(stage, list(rows))
            if isinstance(planned, bool) or not isinstance(planned, (int, np.integer)) or planned < 1:
                raise ValueError(f"plan_stage returned {planned!r} epochs for {stage} (an integer >= 1 expected)")
            epochs[stage] = int(planned)
        forward = with_precision(model, config)
        for epoch in range(epochs[stage]):
            lr = lr_at(config, epoch, epochs[stage])
            for g in opt.param_groups:
                g["lr"] = lr
            te = time.time()
            step = step_with_augmentations(stage, config, rng)
            where = f"{stage} epoch {epoch} (lr {lr:.3g})"
            total, parts = 0.0, {}
            for k_step in range(steps_per_epoch):
                tg = time.time()
                t = training_tensors(gen.batch(config.batch_size))
                if stage == "pmmnet":
                    add_initialization(models["pipnet"].eval(), t, batch=config.batch_size)
                gen_seconds[stage] += time.time() - tg
                model.train()
                loss, detail = step(forward, t, torch.arange(config.batch_size))
                value = float(loss.detach())
                if not math.isfinite(value):
                    raise TrainingError(f"{where}: the training loss is {value} at step {k_step + 1}; training "
                                        f"stopped (the checkpoint of the last finished epoch is kept); lower --lr")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += value
                for name, v in detail.items():
                    parts[name] = parts.get(name, 0.0) + v
            model.eval()
            with torch.no_grad():
                val_loss = float(plain[stage](model, val, val_idx)[0])
            if not math.isfinite(val_loss):
                raise TrainingError(f"{where}: the validation loss is {val_loss}; training stopped; lower --lr")
            dt = time.time() - te
            times[stage] += dt
            row = {"stage": stage, "epoch": epoch, "lr": lr, "train_loss": total / steps_per_epoch,
                   "val_loss": val_loss, "epoch_s": dt,
                   "details": json.dumps({k: v / steps_per_epoch for k, v in parts.items()})}
            rows.append(row)
            save(stage, epoch + 1)
            _write_log(out / "log.csv", rows)
            _echo_row(echo, row)

    samples = {k: epochs[k] * steps_per_epoch * config.batch_size for k in STAGES}
    summary = {"config": dataclasses.asdict(dataclasses.replace(config, **{f"{k}_epochs": v
                                                                         for k, v in epochs.items()})),
               "data": ON_DEVICE, "dataset": identity, "samples_drawn": samples, "val_samples": val_samples,
               "steps_per_epoch": steps_per_epoch, "stages_trained": list(STAGES),
               "resolution": [size, size], "train_seconds": times, "generator_seconds": gen_seconds,
               "torch_threads": torch.get_num_threads(), "torch_version": torch.__version__,
               "init_from": None if continue_from is None else str(continue_from), "lineage": lineage()}
    if export:
        from polrig.models.export import export_all

        sample = {k: val[k][:2].cpu() for k in ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")}
        models = {k: m.cpu() for k, m in models.items()}
        extra = {"stage_zero_axis_camera": [float(x) for x in val["stage_zero_axis"][0]],
                 "camera_x_axis_camera": [1.0, 0.0, 0.0],
                 "training": {"samples": samples, "resolution": [size, size], "dataset": identity,
                              "train_seconds": times, "config": summary["config"],
                              "hardware": hardware_line(config.device), "lineage": summary["lineage"],
                              "totals": lineage_totals(summary["lineage"])}}
        extra.update(extra_meta or {})
        if model_size is not None:
            extra["size"] = model_size
        summary["export"] = export_all(models["pipnet"], models["pmmnet"], models["direct"], out / "weights",
                                       sample, extra)
        for name, rec in summary["export"].items():
            echo(f"export {name}: {rec['bytes'] / 1e6:.2f} MB, max |onnx - torch| = {rec['max_abs_diff']:.3g}")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary


def _recalibrate(stage: str, models: dict, gen: SceneGenerator, config: TrainConfig) -> None:
    """Give the batch norms of ``models[stage]`` (recovered from ONNX) the statistics of
    :data:`polrig.models.train.RECALIBRATION_SAMPLES` generated samples, keeping its function
    (:func:`polrig.models.recover.recalibrate_batchnorm`)."""
    from polrig.models.recover import recalibrate_batchnorm

    model = models[stage]

    def one_batch():
        t = training_tensors(gen.batch(config.batch_size))
        if stage == "pmmnet":
            add_initialization(models["pipnet"].eval(), t, batch=config.batch_size)
        return model(*_pick(t, torch.arange(config.batch_size), STAGE_INPUTS[stage]))

    recalibrate_batchnorm(model, [one_batch] * max(1, RECALIBRATION_SAMPLES // config.batch_size))
