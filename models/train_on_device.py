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
the end ``OUT/summary.json`` and, unless ``export=False``, ``OUT/weights/``. Not supported yet:
``--resume`` of an on-device run, ``--init-from``/``--stages`` (refused, :class:`ConfigError`).
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
from polrig.models.pipnet import PIPNet
from polrig.models.pmmnet import DirectStokesToMM, PMMNet
from polrig.models.scenes_torch import (
    COVERED_FAMILIES,
    SceneGenerator,
    training_tensors,
)
from polrig.models.train import (
    STAGES,
    TrainConfig,
    TrainingError,
    _check_config,
    _check_export_possible,
    _echo_row,
    _run_files,
    _write_log,
    add_initialization,
    direct_step,
    lr_at,
    pipnet_step,
    pmmnet_step,
    save_checkpoint,
    step_with_augmentations,
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
                    echo: Callable[[str], None] = print) -> dict:
    """Train every stage on fresh generated batches (module docstring); returns the summary
    written to ``OUT/summary.json``. ``families`` and ``material_mix``: what the generator draws
    (:data:`polrig.models.scenes_torch.COVERED_FAMILIES`, :data:`polrig.models.scenes_torch.COVERED_MIXES`)."""
    overrides = dict(overrides or {})
    unknown = [k for k in overrides if k not in {f.name for f in dataclasses.fields(TrainConfig)}]
    if unknown:
        raise ConfigError(f"unknown training setting(s) {unknown}")
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
                        dataset=identity, data=ON_DEVICE, init_from=None,
                        generator_state=gen.generator.get_state())

    for stage in STAGES:
        model, opt = models[stage], opts[stage]
        if stage == "pmmnet":
            add_initialization(models["pipnet"].eval(), val)
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
                loss, detail = step(model, t, torch.arange(config.batch_size))
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
               "steps_per_epoch": steps_per_epoch, "stages_trained": list(STAGES), "init_from": None,
               "resolution": [size, size], "train_seconds": times, "generator_seconds": gen_seconds,
               "torch_threads": torch.get_num_threads(), "torch_version": torch.__version__}
    if export:
        from polrig.models.export import export_all

        sample = {k: val[k][:2].cpu() for k in ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")}
        models = {k: m.cpu() for k, m in models.items()}
        extra = {"stage_zero_axis_camera": [float(x) for x in val["stage_zero_axis"][0]],
                 "camera_x_axis_camera": [1.0, 0.0, 0.0],
                 "training": {"samples": samples, "resolution": [size, size], "dataset": identity,
                              "train_seconds": times, "config": summary["config"]}}
        summary["export"] = export_all(models["pipnet"], models["pmmnet"], models["direct"], out / "weights",
                                       sample, extra)
        for name, rec in summary["export"].items():
            echo(f"export {name}: {rec['bytes'] / 1e6:.2f} MB, max |onnx - torch| = {rec['max_abs_diff']:.3g}")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary
