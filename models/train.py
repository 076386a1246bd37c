"""Train PIPNet, then PMMNet (and the direct Stokes->MM baseline), then export ONNX.

``polrig train --data DIR --out DIR`` calls :func:`train`. Stages run in order
``pipnet -> pmmnet -> direct``; each uses Adam with a constant learning rate for the first
``decay_start`` fraction of its epochs and a linear decay to ``lr_final_fraction`` after
(the paper: 40 + 20 epochs, linear decay in the later half; a one-epoch stage runs at the
base rate, :func:`lr_at`). After every epoch the models, optimizers, progress, the numpy and
torch random states, the log rows and the dataset's identity are written atomically to
``OUT/checkpoint.pt``, then ``OUT/log.csv`` (one row per epoch) is rewritten from those rows;
``resume=True`` continues from the checkpoint and reproduces the uninterrupted run exactly.
``OUT/summary.json`` records the run. At the end the graphs are exported with
:func:`polrig.models.export.export_all` into ``OUT/weights`` and checked against PyTorch with
onnxruntime (a failed check is an error and replaces nothing).

PMMNet trains on the PIPNet-pBRDF initialization of the frozen stage-1 network (computed
once per sample, PIPNet in eval mode), exactly what it sees at inference; with
``init_perturb_fraction`` > 0 a fraction of its samples see that initialization evaluated on a
perturbed geometry instead (:func:`perturbed_geometry`, :func:`geometry_toward_view`), so that
it learns how far to trust an initialization whose geometry is wrong, as PIPNet's is on shapes
it has not seen.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import json
import math
import os
import pathlib
import time
from typing import Callable

import numpy as np
import torch

from polrig.atomic import atomic_write_bytes, atomic_write_text
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.formats.argcheck import check_output_folder
from polrig.models import mirror
from polrig.models.lineage import hardware_line, run_entries
from polrig.models.lineage import totals as lineage_totals
from polrig.models.data import (
    Dataset,
    check_network_size,
    dataset_identity,
    load_dataset,
    read_manifest,
)
from polrig.models.pbrdf_torch import image_blocks
from polrig.models.pipnet import PIPNet, pipnet_loss
from polrig.models.pmmnet import DirectStokesToMM, PMMNet, SingleShotNet, mueller_loss

STAGES = ("pipnet", "pmmnet", "direct")
#: What each stage's network is called on (``_pick`` keys).
STAGE_INPUTS = {"pipnet": ("analyzer", "mask", "s_in", "wo"),
                "pmmnet": ("analyzer", "mask", "s_in", "ms_init", "md_init", "kd_init"),
                "direct": ("analyzer", "mask", "s_in", "wo")}
#: Training samples whose statistics set the batch norms of a network recovered from ONNX.
RECALIBRATION_SAMPLES = 256
#: Stages that read the raw images and must infer the geometry themselves; ``crop_fraction``
#: windows their training samples (PMMNet refines an initialization of the whole image).
CROPPED_STAGES = ("pipnet", "direct")


@dataclasses.dataclass
class TrainConfig:
    pipnet_epochs: int = 12
    pmmnet_epochs: int = 8
    direct_epochs: int = 8
    batch_size: int = 16
    lr: float = 1e-3
    decay_start: float = 0.5
    lr_final_fraction: float = 0.05
    width: int = 16
    #: PIPNet with the shape-from-polarization normal prior (polrig.models.pipnet, an addition to the paper)
    sfp_prior: bool = True
    #: Fraction of PIPNet and direct-baseline training samples shown through a random window
    #: (:func:`window_crop`; the same augmentation for both, so the ablation stays fair)
    crop_fraction: float = 0.7
    #: Weight of the direct supervision of the SfP prior's pick and trust
    #: (:func:`polrig.models.pipnet.sfp_supervision_loss`; 0: the paper's loss only)
    sfp_supervision: float = 0.0
    #: Fraction of PMMNet training samples whose initialization is evaluated on PIPNet's
    #: geometry perturbed by :func:`perturbed_geometry` or :func:`geometry_toward_view`
    #: (0: the paper's recipe)
    init_perturb_fraction: float = 0.5
    #: Largest common rotation of the perturbed normals and light (deg)
    init_perturb_deg: float = 40.0
    #: Largest further rotation of the perturbed light alone (deg)
    init_perturb_light_deg: float = 30.0
    #: Largest pull of the perturbed normals and light towards the view direction
    #: (:func:`geometry_toward_view`; half of the perturbed samples get it, the other half the
    #: rotation; 0: all get the rotation)
    init_perturb_toward_view: float = 0.7
    #: Fraction of the training samples of every stage shown as their left-right mirror image
    #: (:mod:`polrig.models.mirror`: an exact symmetry of the physics; 0: none)
    mirror_fraction: float = 0.0
    threads: int = 2
    #: Where PyTorch trains: "cpu" or "cuda" (the dataset, the networks and the optimizers live
    #: there; random draws stay on the CPU's generators, so a run's augmentations do not depend
    #: on the device; the export runs on CPU copies). On CUDA a resumed run is not bit-identical
    #: to an uninterrupted one (cuDNN's kernels are not deterministic).
    device: str = "cpu"
    #: Mixed precision of the networks' forward passes: "none" (float32) or "bf16" (bfloat16
    #: autocast, :class:`Autocast`; the pBRDF initialization and the losses stay float32)
    autocast: str = "none"
    seed: int = 0
    val_fraction: float = 0.05
    limit: int | None = None


def _tensors(ds: Dataset) -> dict[str, torch.Tensor]:
    a = ds.arrays
    t = {k: torch.from_numpy(np.ascontiguousarray(a[k])) for k in
         ("analyzer", "normal", "kd", "wi", "wo", "alpha", "s_in", "mueller", "stage_zero_axis")}
    t["mask"] = torch.from_numpy(a["mask"])[:, None]
    return t


def _config_of(checkpoint: dict) -> dict:
    """A checkpoint's configuration; checkpoints from before the SfP prior, the window crops and
    the perturbed initializations existed were trained without them."""
    return {"sfp_prior": False, "crop_fraction": 0.0, "sfp_supervision": 0.0, "init_perturb_fraction": 0.0,
            "init_perturb_toward_view": 0.0, **checkpoint["config"]}


def window_crop(mask: torch.Tensor, fraction: float, generator: torch.Generator,
                min_side: float = 0.25, max_side: float = 0.75) -> torch.Tensor:
    """Random windows ``(B, 1, H, W)`` in {0, 1}: for a ``fraction`` of the samples a rectangle
    with sides uniform in ``[min_side, max_side]`` of the image at a uniform position, else
    the whole image. Training on windowed objects (inputs and loss mask cut to the window)
    hides silhouettes, so geometry has to come from local shading and polarization rather than
    from the outline of a training shape (an augmentation, not in the paper)."""
    b, _, h, w = mask.shape
    out = torch.ones_like(mask)
    if fraction <= 0.0:
        return out
    pick = torch.rand(b, generator=generator) < fraction
    sides = torch.rand(b, 2, generator=generator) * (max_side - min_side) + min_side
    corner = torch.rand(b, 2, generator=generator)
    rows = torch.arange(h, dtype=mask.dtype, device=mask.device)
    cols = torch.arange(w, dtype=mask.dtype, device=mask.device)
    for i in torch.nonzero(pick)[:, 0].tolist():
        hh, ww = max(1, int(sides[i, 0] * h)), max(1, int(sides[i, 1] * w))
        r0, c0 = int(corner[i, 0] * (h - hh + 1)), int(corner[i, 1] * (w - ww + 1))
        out[i, 0] = ((rows >= r0) & (rows < r0 + hh)).to(mask.dtype)[:, None] * ((cols >= c0) & (cols < c0 + ww)).to(mask.dtype)[None]
    return out


#: Smooth per-pixel normal noise of :func:`perturbed_geometry`: Gaussian vectors on a
#: ``PERTURB_GRID`` x ``PERTURB_GRID`` grid, bilinearly upsampled, times up to ``PERTURB_NOISE``.
PERTURB_GRID = 8
PERTURB_NOISE = 0.4


def rotation_matrices(axis: torch.Tensor, angle_rad: torch.Tensor) -> torch.Tensor:
    """Right-handed rotations ``(B, 3, 3)`` by ``angle_rad`` ``(B,)`` about unit ``axis``
    ``(B, 3)`` (Rodrigues' formula ``I + sin(a) K + (1 - cos(a)) K^2``)."""
    x, y, z = axis.unbind(1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], 1).reshape(-1, 3, 3)
    s, c = torch.sin(angle_rad)[:, None, None], torch.cos(angle_rad)[:, None, None]
    return torch.eye(3, dtype=axis.dtype) + s * k + (1.0 - c) * (k @ k)


def perturbed_geometry(normal: torch.Tensor, wi: torch.Tensor, generator: torch.Generator,
                       rotation_deg: float, light_deg: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A wrong but plausible geometry ``(normal, wi)`` (B, 3, H, W) from a predicted one: both
    turned by one random rotation (angle uniform in ``[0, rotation_deg]`` about a uniform random
    axis), which keeps them consistent with each other as PIPNet's are on unseen shapes (its
    normals about 39 deg and its light 27 deg off, ``polrig.models.diagnose``), then the normals bent
    by smooth per-pixel noise (:data:`PERTURB_NOISE`) and the light turned by a further
    rotation of up to ``light_deg``. An augmentation for PMMNet's training (not in the paper)."""
    b, _, h, w = normal.shape

    def random_rotations(max_deg: float) -> torch.Tensor:
        axis = torch.nn.functional.normalize(torch.randn(b, 3, generator=generator, dtype=normal.dtype), dim=1)
        angle = torch.rand(b, generator=generator, dtype=normal.dtype) * np.deg2rad(max_deg)
        return rotation_matrices(axis, angle).to(normal.device)

    turn = random_rotations(rotation_deg)
    n = torch.einsum("bij,bjhw->bihw", turn, normal)
    noise = torch.nn.functional.interpolate(
        torch.randn(b, 3, PERTURB_GRID, PERTURB_GRID, generator=generator, dtype=normal.dtype).to(normal.device),
        size=(h, w), mode="bilinear", align_corners=False)
    n = n + noise * PERTURB_NOISE * torch.rand(b, 1, 1, 1, generator=generator, dtype=normal.dtype).to(normal.device)
    light = torch.einsum("bij,bjhw->bihw", random_rotations(light_deg) @ turn, wi)
    return (torch.nn.functional.normalize(n, dim=1, eps=1e-6),
            torch.nn.functional.normalize(light, dim=1, eps=1e-6))


def geometry_toward_view(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, generator: torch.Generator,
                         max_pull: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals and light ``(B, 3, H, W)`` pulled towards the view directions ``wo`` by one random
    fraction ``t`` per image, uniform in ``[0, max_pull]``: ``normalize(v + t (wo - v))``. This
    is the error PIPNet makes on shapes it has not seen: its normals and its light both lie too
    close to the camera (on heightfields, mean normal z about -0.7 where the truth is -0.4).
    An augmentation for PMMNet's training (not in the paper)."""
    t = torch.rand(normal.shape[0], 1, 1, 1, generator=generator, dtype=normal.dtype).to(normal.device) * max_pull
    pull = lambda v: torch.nn.functional.normalize(v + t * (wo - v), dim=1, eps=1e-6)  # noqa: E731
    return pull(normal), pull(wi)


def lr_at(config: TrainConfig, epoch: int, epochs: int) -> float:
    """Constant, then linear decay from ``decay_start * epochs`` (rounded half to even) to
    ``lr_final_fraction`` at the last epoch. A one-epoch stage has nothing to decay from and
    runs at the base learning rate (``round(0.5)`` is 0, which used to put its only epoch at
    the final fraction)."""
    if epochs <= 1:
        return config.lr
    start = int(round(config.decay_start * epochs))
    if epoch < start or epochs <= start:
        return config.lr
    frac = (epoch - start + 1) / (epochs - start)
    return config.lr * (1.0 - frac * (1.0 - config.lr_final_fraction))


def _batches(n: int, batch: int, rng: np.random.Generator | None):
    order = rng.permutation(n) if rng is not None else np.arange(n)
    for i in range(0, n, batch):
        yield torch.from_numpy(order[i:i + batch])


#: How each training tensor maps to its sample's mirror image (:mod:`polrig.models.mirror`).
MIRROR_OF = {"analyzer": mirror.analyzer, "mask": mirror.image, "s_in": mirror.stokes,
             "stage_zero_axis": mirror.vectors, "kd": mirror.image, "kd_init": mirror.image,
             "wo": mirror.vector_image, "normal": mirror.vector_image, "wi": mirror.vector_image,
             "pip_normal": mirror.vector_image, "pip_wi": mirror.vector_image,
             "mueller": mirror.mueller_image, "ms_init": mirror.mueller_image, "md_init": mirror.mueller_image,
             "alpha": mirror.scalar, "pip_alpha": mirror.scalar}


def _pick(t: dict[str, torch.Tensor], idx: torch.Tensor, keys, mirrored: torch.Tensor | None = None
          ) -> list[torch.Tensor]:
    """``t[k][idx]`` for each key; the samples flagged in ``mirrored`` (bool, per ``idx``) as
    their mirror image (:data:`MIRROR_OF`)."""
    out = [t[k][idx.to(t[k].device)] for k in keys]
    if mirrored is None or not bool(mirrored.any()):
        return out
    for x, k in zip(out, keys):
        flip = mirrored.to(x.device)
        x[flip] = MIRROR_OF[k](x[flip])  # x is a copy (advanced indexing)
    return out


def mirror_flags(n: int, mirroring: tuple[float, torch.Generator] | None) -> torch.Tensor | None:
    """Which of ``n`` samples to show mirrored: ``mirroring = (fraction, generator)``."""
    if mirroring is None:
        return None
    fraction, gen = mirroring
    return torch.rand(n, generator=gen) < fraction


def _windowed(analyzer: torch.Tensor, mask: torch.Tensor, crop: tuple[float, torch.Generator] | None):
    """Analyzer images and mask cut to :func:`window_crop` windows (unchanged without ``crop``)."""
    if crop is None:
        return analyzer, mask
    window = window_crop(mask, *crop)
    return analyzer * window[:, None], mask * window


def pipnet_step(model: PIPNet, t, idx, crop: tuple[float, torch.Generator] | None = None,
                sfp_weight: float = 0.0, mirroring: tuple[float, torch.Generator] | None = None):
    a, m, s, wo, n, kd, wi, al = _pick(t, idx, ("analyzer", "mask", "s_in", "wo", "normal", "kd", "wi", "alpha"),
                                       mirror_flags(len(idx), mirroring))
    a, m = _windowed(a, m, crop)
    return pipnet_loss(model(a, m, s, wo), n, kd, wi, al, m, sfp_weight)


def pmmnet_step(model: PMMNet, t, idx, perturb: tuple[float, float, float, float, torch.Generator] | None = None,
                mirroring: tuple[float, torch.Generator] | None = None):
    """``perturb``: ``(fraction, rotation_deg, light_deg, toward_view, generator)``: that
    fraction of the samples gets its initialization from a perturbed copy of PIPNet's geometry,
    half of it from :func:`perturbed_geometry` and half from :func:`geometry_toward_view` (all
    from the former when ``toward_view`` is 0). ``mirroring``: ``(fraction, generator)`` of the
    samples shown as their mirror image, initialization included (the pBRDF is mirror-symmetric)."""
    flip = mirror_flags(len(idx), mirroring)
    a, m, s, ms, md, kd, mu = _pick(t, idx, ("analyzer", "mask", "s_in", "ms_init", "md_init", "kd_init", "mueller"),
                                    flip)
    if perturb is not None:
        fraction, rotation_deg, light_deg, toward_view, gen = perturb
        u = torch.rand(len(idx), generator=gen)
        split = fraction / 2 if toward_view > 0 else fraction
        ms, md = ms.clone(), md.clone()
        for sel, turned in ((torch.nonzero(u < split)[:, 0], True), (torch.nonzero((u >= split) & (u < fraction))[:, 0], False)):
            if not len(sel):
                continue
            n, wi, wo, alpha, axis = _pick(t, idx[sel], ("pip_normal", "pip_wi", "wo", "pip_alpha", "stage_zero_axis"),
                                           None if flip is None else flip[sel])
            n, wi = (perturbed_geometry(n, wi, gen, rotation_deg, light_deg) if turned
                     else geometry_toward_view(n, wi, wo, gen, toward_view))
            with torch.no_grad():
                ms_p, md_p = image_blocks(n, wi, wo, alpha, axis)
            sel = sel.to(m.device)
            ms[sel], md[sel] = ms_p * m[sel][:, None], md_p * m[sel][:, None]
    return mueller_loss(model(a, m, s, ms, md, kd)["mueller"], mu, m)


def direct_step(model: DirectStokesToMM, t, idx, crop: tuple[float, torch.Generator] | None = None,
                mirroring: tuple[float, torch.Generator] | None = None):
    a, m, s, wo, mu = _pick(t, idx, ("analyzer", "mask", "s_in", "wo", "mueller"), mirror_flags(len(idx), mirroring))
    a, m = _windowed(a, m, crop)
    return mueller_loss(model(a, m, s, wo), mu, m)


@torch.no_grad()
def add_initialization(pipnet: PIPNet, t: dict[str, torch.Tensor], batch: int = 32) -> None:
    """Add ``ms_init``, ``md_init`` (N,3,3,H,W) and ``kd_init`` (N,C,H,W) from PIPNet, and its
    geometry ``pip_normal``, ``pip_wi`` (N,3,H,W), ``pip_alpha`` (N,)."""
    net = SingleShotNet(pipnet, PMMNet(pipnet.colours, 8)).eval()
    parts: dict[str, list[torch.Tensor]] = {k: [] for k in ("ms_init", "md_init", "kd_init", "pip_normal",
                                                           "pip_wi", "pip_alpha")}
    for idx in _batches(len(t["analyzer"]), batch, None):
        p, s_blk, d_blk = net.initialization(*_pick(t, idx, ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")))
        for k, v in (("ms_init", s_blk), ("md_init", d_blk), ("kd_init", p["kd"]), ("pip_normal", p["normal"]),
                     ("pip_wi", p["wi"]), ("pip_alpha", p["alpha"])):
            parts[k].append(v)
    t.update({k: torch.cat(v) for k, v in parts.items()})


AUTOCAST_MODES = ("none", "bf16")


class Autocast:
    """A network whose forward pass runs under bfloat16 autocast on ``device_type`` and returns
    float32 outputs (a tensor, or a dict of them), so that the losses computed from them, and the
    pBRDF (which runs outside the networks, :func:`add_initialization`), stay float32: autocast
    only where it is safe, the convolutions and attention. Everything else (``train()``,
    ``eval()``, parameters) is the network's own."""

    def __init__(self, model: torch.nn.Module, device_type: str):
        self.model, self.device_type = model, device_type

    def __call__(self, *args):
        with torch.autocast(self.device_type, dtype=torch.bfloat16):
            out = self.model(*args)
        if isinstance(out, dict):
            return {k: v.float() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in out.items()}
        return out.float()

    def __getattr__(self, name):
        return getattr(self.model, name)


def with_precision(model: torch.nn.Module, config: "TrainConfig"):
    """``model`` as the training steps call it: itself, or under :class:`Autocast` (``config.autocast``)."""
    return Autocast(model, torch.device(config.device).type) if config.autocast == "bf16" else model


#: Configuration fields a continued run (``continue_from``) does not take from its checkpoint:
#: the epochs of this run, and the machine's settings.
NOT_CONTINUED = ("pipnet_epochs", "pmmnet_epochs", "direct_epochs", "threads", "device", "limit", "autocast",
                 "batch_size", "seed")


def continued_config(donor: dict, overrides: dict, source) -> TrainConfig:
    """The configuration of a run continuing ``donor``: its recipe and architecture (not
    :data:`NOT_CONTINUED`), ``overrides`` on top; another width or SfP prior is one line."""
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    recipe = {k: v for k, v in _config_of(donor).items() if k in fields and k not in NOT_CONTINUED}
    for k in ("width", "sfp_prior"):
        if k in overrides and k in recipe and overrides[k] != recipe[k]:
            raise ConfigError(f"--continue-from {source}: its networks have {k} {recipe[k]}, not {overrides[k]} "
                              f"(a continued run keeps the architecture)")
    return dataclasses.replace(TrainConfig(**recipe), **overrides)


#: Columns of ``OUT/log.csv`` (one row per finished epoch).
LOG_FIELDS = ("stage", "epoch", "lr", "train_loss", "val_loss", "epoch_s", "details")
#: Files of a run in ``OUT`` (and the graphs :func:`polrig.models.export.export_all` writes into
#: ``OUT/weights``, plus a calibration of them): what ``--overwrite`` removes first.
RUN_FILES = ("checkpoint.pt", "log.csv", "summary.json")
WEIGHT_FILES = ("single_shot.onnx", "direct.onnx", "model.json", "uncertainty.json")
CHECKPOINT_FORMAT = "polrig-train-checkpoint"
#: Configuration fields a resumed run cannot change: the networks' architecture and the samples
#: (and their train/validation split) it trains on.
FIXED_ON_RESUME = ("width", "sfp_prior", "seed", "limit", "val_fraction")


class TrainingError(PolrigError):
    """Training cannot go on (a non-finite loss): a failure while running (exit 1)."""


def _echo_row(echo: Callable[[str], None], row: dict) -> None:
    echo(f"{row['stage']:7s} epoch {row['epoch']:3d}  lr {row['lr']:.2e}  "
         f"train {row['train_loss']:.5f}  val {row['val_loss']:.5f}  {row['epoch_s']:.1f}s")


def _write_log(path: pathlib.Path, rows: list[dict]) -> None:
    """``log.csv`` holding exactly ``rows`` (written whole and atomically, so it always matches
    the checkpoint it was written after)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(LOG_FIELDS), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(path, buf.getvalue())


def _legacy_log_rows(path: pathlib.Path, stage: str, epoch: int) -> list[dict]:
    """The rows of an existing ``log.csv`` that a checkpoint without its own log (written
    before checkpoints carried it) covers: epochs before ``(stage, epoch)``, each once."""
    if not path.is_file():
        return []
    end = (STAGES.index(stage), epoch)
    rows: dict[tuple[int, int], dict] = {}
    try:
        with path.open(newline="") as f:
            for r in csv.DictReader(f):
                try:
                    key = (STAGES.index(r["stage"]), int(r["epoch"]))
                except (KeyError, ValueError, TypeError):
                    continue
                if key < end:
                    rows[key] = {k: r.get(k) for k in LOG_FIELDS}
    except (OSError, UnicodeDecodeError, csv.Error):
        return []
    return [rows[k] for k in sorted(rows)]


def _reason(exc: BaseException) -> str:
    text = (str(exc) or type(exc).__name__).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    return line if len(line) <= 160 else line[:157] + "..."


def load_checkpoint(path: str | pathlib.Path, *, for_resume: bool = False) -> dict:
    """A ``polrig train`` checkpoint (``OUT/checkpoint.pt``): :class:`FileNotFoundError` when
    it is missing, :class:`FormatError` naming the file when it cannot be read (truncated,
    another kind of file) or holds no networks; ``for_resume`` also needs the progress and
    optimizer states a resumed run continues from."""
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    if path.is_dir():
        raise FormatError(f"{path} is a folder, not a checkpoint file")
    try:
        state = torch.load(path, weights_only=False, map_location="cpu")
    except Exception as exc:  # truncated zip, a JSON or .npz file, pickle errors: all one message
        raise FormatError(f"{path}: not a readable polrig train checkpoint (truncated or another kind of "
                          f"file: {_reason(exc)})") from exc
    need = ("config", "models") + (("stage", "epoch", "optimizers", "times") if for_resume else ())
    if not isinstance(state, dict) or any(k not in state for k in need) or not isinstance(state["models"], dict) \
            or not isinstance(state["config"], dict):
        raise FormatError(f"{path}: not a polrig train checkpoint (no {'progress or ' if for_resume else ''}"
                          f"networks in it)")
    missing = [k for k in STAGES if k not in state["models"]]
    if missing:
        raise FormatError(f"{path}: checkpoint has no {', '.join(missing)} network")
    if for_resume and state["stage"] not in STAGES:
        raise FormatError(f"{path}: checkpoint names an unknown stage {state['stage']!r}")
    return state


def _load_donor(init_from: str | pathlib.Path) -> dict:
    """The networks to start from: a checkpoint, or a weights folder recovered from its ONNX
    graphs (:mod:`polrig.models.recover`); one-line errors naming the file."""
    path = pathlib.Path(init_from)
    if path.is_dir():
        from polrig.models.recover import checkpoint_from_weights

        try:
            return checkpoint_from_weights(path)
        except (FormatError, FileNotFoundError):
            raise
        except Exception as exc:  # a damaged model.json or graph
            raise FormatError(f"--init-from {path}: cannot recover the networks from its weights "
                              f"(model.json, single_shot.onnx, direct.onnx): {_reason(exc)}") from exc
    if not path.exists():
        raise FileNotFoundError(f"--init-from {path} not found (a checkpoint.pt or a weights folder)")
    return load_checkpoint(path)


def continue_checkpoint(donor: dict, opts: dict, source, echo: Callable[[str], None]) -> bool:
    """Load ``donor``'s optimizer states into ``opts`` (one per network) where it holds them:
    True; else a note that the optimizers start fresh: False. A checkpoint stored compactly
    (:func:`polrig.models.continuation.compact`: moments in bfloat16) loads the same way (Adam casts
    its state to the parameters' dtype)."""
    saved = donor.get("optimizers")
    if not saved:
        why = donor.get("optimizer_note") or "it holds none"
        echo(f"note: --continue-from {source}: no optimizer state ({why}); the optimizers start fresh")
        return False
    try:
        for k, opt in opts.items():
            opt.load_state_dict(saved[k])
    except (KeyError, ValueError, RuntimeError) as exc:
        raise ConfigError(f"--continue-from {source}: its optimizer states do not fit these networks: "
                          f"{_reason(exc)}") from exc
    steps = {k: int(max((float(st["step"]) for st in o.state.values() if "step" in st), default=0))
             for k, o in opts.items()}
    echo(f"continuing from {source}: weights and optimizer states (steps so far: "
         + ", ".join(f"{k} {v}" for k, v in steps.items()) + ")")
    return True


def _check_config(config: TrainConfig, stages: tuple[str, ...], epochs: dict[str, int]) -> None:
    """:class:`ConfigError` naming the first field no training can use."""
    def bad(name: str, value, what: str):
        return ConfigError(f"{name.replace('_', '-')} must be {what}, got {value!r}")

    def is_int(v) -> bool:
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    for k in STAGES:
        v = epochs[k]
        if k in stages and not (is_int(v) and v >= 1):
            raise bad(f"{k}_epochs", v, f"an integer >= 1 (the {k} stage is trained)")
        if not (is_int(v) and v >= 0):
            raise bad(f"{k}_epochs", v, "an integer >= 0")
    for name, low in (("batch_size", 1), ("threads", 1), ("seed", 0)):
        v = getattr(config, name)
        if not (is_int(v) and v >= low):
            raise bad(name, v, f"an integer >= {low}")
    if not (is_int(config.width) and config.width >= 4 and config.width % 4 == 0):
        raise bad("width", config.width, "a multiple of 4, >= 4 (the attention heads split the channels)")
    if config.limit is not None and not (is_int(config.limit) and config.limit >= 1):
        raise bad("limit", config.limit, "an integer >= 1")
    if config.autocast not in AUTOCAST_MODES:
        raise bad("autocast", config.autocast, " or ".join(AUTOCAST_MODES))
    if config.device not in ("cpu", "cuda"):
        raise bad("device", config.device, "cpu or cuda")
    if config.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device cuda: PyTorch sees no CUDA GPU here (torch.cuda.is_available() is False); "
                          "train with device cpu")
    for name, low, high in (("lr", 0.0, 1.0), ("decay_start", 0.0, 1.0), ("lr_final_fraction", 0.0, 1.0),
                            ("crop_fraction", 0.0, 1.0), ("sfp_supervision", 0.0, math.inf),
                            ("init_perturb_fraction", 0.0, 1.0), ("init_perturb_deg", 0.0, 180.0),
                            ("init_perturb_light_deg", 0.0, 180.0), ("init_perturb_toward_view", 0.0, 1.0),
                            ("mirror_fraction", 0.0, 1.0), ("val_fraction", 0.0, 0.5)):
        v = getattr(config, name)
        if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v) and low <= v <= high):
            raise bad(name, v, f"a finite number >= {low:g}" if high == math.inf else f"a number in [{low:g}, {high:g}]")


def _check_export_possible() -> None:
    """:class:`ConfigError` before any training when the ONNX export could not run."""
    for module, why in (("onnx", "the ONNX exporter"), ("onnxruntime", "the export check")):
        try:
            __import__(module)
        except ImportError:
            raise ConfigError(f"exporting the networks needs the '{module}' package ({why}; pip install "
                              f"polrig[train]); install it or pass --no-export") from None


def _run_files(out: pathlib.Path) -> list[pathlib.Path]:
    """What of an earlier run lies in ``out``."""
    found = [out / f for f in RUN_FILES if os.path.lexists(out / f)]
    found += [out / "weights" / f for f in WEIGHT_FILES if os.path.lexists(out / "weights" / f)]
    return found


def _run_epoch(model, step, t, idx_all, batch, opt, rng, where: str = "") -> tuple[float, dict[str, float]]:
    model.train()
    total, parts, count = 0.0, {}, 0
    for k_batch, b in enumerate(_batches(len(idx_all), batch, rng)):
        idx = idx_all[b]
        loss, detail = step(model, t, idx)
        value = float(loss.detach())
        if not math.isfinite(value):  # before the step: the weights stay finite
            raise TrainingError(f"{where}: the training loss is {value} at batch {k_batch + 1}; training stopped "
                                f"(the checkpoint of the last finished epoch is kept); lower --lr")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        k = len(idx)
        total += value * k
        count += k
        for name, v in detail.items():
            parts[name] = parts.get(name, 0.0) + v * k
    return total / max(count, 1), {k: v / max(count, 1) for k, v in parts.items()}


@torch.no_grad()
def _evaluate(model, step, t, idx_all, batch) -> float:
    model.eval()
    total, count = 0.0, 0
    for b in _batches(len(idx_all), batch, None):
        loss, _ = step(model, t, idx_all[b])
        total += float(loss) * len(b)
        count += len(b)
    return total / max(count, 1)



def step_with_augmentations(stage: str, config: TrainConfig, rng: np.random.Generator):
    """The step function of ``stage`` with this epoch's augmentations bound: crops, mirroring,
    the shape-from-polarization supervision and the initialization's perturbation, each
    random one with a torch generator seeded from ``rng`` in this order (so a resumed run
    draws the same). :func:`train` and :func:`polrig.models.train_on_device.train_on_device`
    both build their steps here."""
    steps = {"pipnet": pipnet_step, "pmmnet": pmmnet_step, "direct": direct_step}
    step = steps[stage]
    if stage in CROPPED_STAGES and config.crop_fraction > 0:
        gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
        step = functools.partial(step, crop=(config.crop_fraction, gen))
    if config.mirror_fraction > 0:
        gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
        step = functools.partial(step, mirroring=(config.mirror_fraction, gen))
    if stage == "pipnet" and config.sfp_supervision > 0:
        step = functools.partial(step, sfp_weight=config.sfp_supervision)
    if stage == "pmmnet" and config.init_perturb_fraction > 0:
        gen = torch.Generator().manual_seed(int(rng.integers(2**31)))
        step = functools.partial(step, perturb=(config.init_perturb_fraction, config.init_perturb_deg,
                                                config.init_perturb_light_deg, config.init_perturb_toward_view, gen))
    return step


def save_checkpoint(path: pathlib.Path, *, config, epochs: dict, stage: str, epoch: int, stages,
                    models: dict, opts: dict, times: dict, rng: np.random.Generator, recalibrate: list,
                    rows: list, dataset, data: str, init_from: str | None,
                    lineage_before: list | None = None, lineage: list | None = None, **extra) -> None:
    """Write a training checkpoint (:data:`CHECKPOINT_FORMAT`, version 2) atomically: the run's
    config with each stage's epochs, where it stands (``stage``, ``epoch``), every network's and
    optimizer's state, the seconds spent per stage, both random generators' states, the log rows
    so far, and what it trains on (``dataset`` identity, ``data``); ``lineage_before`` (the runs
    before this one, which a resumed run starts from again) and ``lineage`` (those plus this run's
    entries so far) with its ``totals`` (:mod:`polrig.models.lineage`). ``extra`` holds what one kind
    of run adds (the on-device generator's state); :func:`train` and
    :func:`polrig.models.train_on_device.train_on_device` both write through here."""
    blob = io.BytesIO()
    torch.save({"format": CHECKPOINT_FORMAT, "version": 2,
                "config": dict(dataclasses.asdict(config), **{f"{k}_epochs": v for k, v in epochs.items()}),
                "stage": stage, "epoch": epoch, "stages": list(stages),
                "models": {k: m.state_dict() for k, m in models.items()},
                "optimizers": {k: o.state_dict() for k, o in opts.items()},
                "times": dict(times), "rng_state": rng.bit_generator.state,
                "torch_rng_state": torch.get_rng_state(), **extra, "recalibrate": recalibrate,
                "log": list(rows), "dataset": dataset, "data": data, "init_from": init_from,
                "lineage_before": list(lineage_before or []), "lineage": list(lineage or []),
                "totals": lineage_totals(lineage or [])}, blob)
    atomic_write_bytes(path, blob.getvalue())


def train(data_dir: str | pathlib.Path, out_dir: str | pathlib.Path, config: TrainConfig | None = None,
          *, resume: bool = False, export: bool = True, overrides: dict | None = None,
          init_from: str | pathlib.Path | None = None, stages: tuple[str, ...] | None = None,
          warm_start: bool = False, overwrite: bool = False, echo: Callable[[str], None] = print,
          plan_stage: Callable[[str, list[dict]], int] | None = None,
          continue_from: str | pathlib.Path | None = None) -> dict:
    """Train all stages on ``data_dir``, write checkpoints/logs/ONNX into ``out_dir``.

    ``overrides`` (field -> value) are applied on top of ``config`` or, when resuming, on top
    of the checkpoint's configuration (e.g. more epochs for the stage the checkpoint is in).
    ``init_from`` (a checkpoint of another run, or a weights folder such as ``models/weights``,
    whose networks are recovered from its ONNX graphs by :mod:`polrig.models.recover`) with ``stages``
    (default: all) retrains only those stages from scratch and takes the other networks (and
    their training times and epochs) from it, e.g. a new PMMNet on a trained PIPNet; with
    ``warm_start`` the trained stages start from the donor's weights instead (fine-tuning with a
    fresh optimizer and learning-rate schedule; the batch norms of recovered networks first get
    the statistics of the training data, :func:`polrig.models.recover.recalibrate_batchnorm`). Returns
    the summary dict also written to ``OUT/summary.json``.

    Everything is checked before anything is written or trained: a folder holding another run
    is refused unless ``resume`` (continue it) or ``overwrite`` (its files are removed first);
    ``resume`` needs ``OUT/checkpoint.pt`` and the same dataset (manifest identity,
    :func:`polrig.models.data.dataset_identity`), architecture, seed and samples, and cannot change the
    epochs of a finished stage; a held-out set (``polrig sim dataset --holdout``) is refused;
    image sides must be multiples of the networks' size multiple; the export needs ``onnx`` and
    ``onnxruntime``.

    Every epoch ends with the checkpoint written atomically (models, optimizers, the numpy and
    torch random states, the log rows, the dataset identity), then ``log.csv`` rewritten from
    those rows, so an interruption at any point loses at most the epoch in progress and a
    resumed run reproduces the straight run's log rows and weights exactly. A non-finite
    training loss stops the run with :class:`TrainingError`.

    ``plan_stage(stage, log_rows)``, where given, sets the epochs of each stage that starts from
    its first epoch (a resumed run's unfinished stage keeps its own): it is called just before
    that stage's first epoch (after PMMNet's initialization, so the time that took has passed)
    with the log rows so far (``epoch_s`` of every finished epoch), and returns an integer >= 1
    that replaces the configured epochs (the checkpoints and the summary record it). A caller
    with a wall-clock budget plans each stage from what the earlier ones really took
    (:mod:`polrig.models.paper_scale`).

    ``continue_from`` (a checkpoint, e.g. a shipped size's committed ``checkpoint.pt``) goes on
    training every network of it: its weights and, where it holds them, its optimizers' states
    (Adam's moments and step counters; else fresh optimizers, said in one note), with a fresh
    learning-rate schedule of this run's epochs (:func:`continue_checkpoint`).

    Lineage: every checkpoint and the exported ``model.json`` carry the runs before (the
    donor's or the continued checkpoint's ``lineage``) plus one entry per network this run
    trained, and their ``totals`` (epochs, optimizer steps, seconds; :mod:`polrig.models.lineage`)."""
    if continue_from is not None:
        given = [f for f, v in (("--init-from", init_from), ("--warm-start", warm_start), ("--resume", resume),
                                ("--stages", stages is not None and set(stages) != set(STAGES))) if v]
        if given:
            raise ConfigError(f"--continue-from goes on with every network of its checkpoint: not with "
                              f"{', '.join(given)}")
        init_from, warm_start, stages = continue_from, True, None
    if warm_start and init_from is None:
        raise ValueError("warm_start needs init_from (the checkpoint to start from)")
    if resume and overwrite:
        raise ConfigError("--resume continues the run in --out and --overwrite replaces it: give one of them")
    if stages is not None:
        stages = tuple(stages)
        bad = [s for s in stages if s not in STAGES]
        if bad or not stages:
            raise ConfigError(f"unknown stage(s) {', '.join(map(repr, bad)) or 'none given'}; stages are "
                              f"{', '.join(STAGES)}")
    overrides = dict(overrides or {})
    unknown = [k for k in overrides if k not in {f.name for f in dataclasses.fields(TrainConfig)}]
    if unknown:
        raise ConfigError(f"unknown training setting(s) {unknown}")
    out = pathlib.Path(out_dir)
    check_output_folder(out)
    ckpt_path = out / "checkpoint.pt"
    state = None
    if resume:
        if not ckpt_path.is_file():
            raise ConfigError(f"--resume: no checkpoint.pt in {out} (nothing to continue; start a new run "
                              f"without --resume)")
        state = load_checkpoint(ckpt_path, for_resume=True)
        ck_stages = tuple(state.get("stages", STAGES))
        if stages is not None and set(stages) != set(ck_stages):
            raise ConfigError(f"--resume: the run in {out} trains {', '.join(ck_stages)}, not "
                              f"{', '.join(stages)} (drop --stages)")
        stages = ck_stages
        base = TrainConfig(**{k: v for k, v in _config_of(state).items()
                              if k in {f.name for f in dataclasses.fields(TrainConfig)}})
        changed = [k for k in FIXED_ON_RESUME if k in overrides and overrides[k] != getattr(base, k)]
        if changed:
            k = changed[0]
            show = (lambda v: f"--{'' if v else 'no-'}sfp-prior") if k == "sfp_prior" else \
                (lambda v: f"--{k.replace('_', '-')} {v}")
            raise ConfigError(f"--resume: {show(overrides[k])} differs from the run's {show(getattr(base, k))} "
                              f"(a resumed run keeps its networks' architecture and its samples; start a new "
                              f"run for another)")
        start_stage, start_epoch = STAGES.index(state["stage"]), int(state["epoch"])
        for si, k in enumerate(STAGES):
            key = f"{k}_epochs"
            if key not in overrides or overrides[key] == getattr(base, key):
                continue
            if k not in stages:  # taken from the donor: its epochs are the donor's
                overrides.pop(key)
            elif si < start_stage:
                raise ConfigError(f"--resume: the {k} stage is finished ({getattr(base, key)} epochs); its epochs "
                                  f"cannot change (train it again in a new run: --init-from {ckpt_path} "
                                  f"--warm-start --stages {k})")
            elif si == start_stage and overrides[key] < start_epoch:
                raise ConfigError(f"--resume: the {k} stage has trained {start_epoch} epochs already; "
                                  f"--{k}-epochs {overrides[key]} would record fewer")
        config = dataclasses.replace(base, **overrides)
    else:
        stages = STAGES if stages is None else stages
        if set(stages) != set(STAGES) and init_from is None:
            raise ConfigError(f"training a subset of the stages ({', '.join(stages)}) needs --init-from "
                              f"CHECKPOINT (or a weights folder) for the others")
        found = _run_files(out)
        if found and not overwrite:
            raise FileExistsError(f"--out {out} holds another training run ({found[0].name}); continue it with "
                                  f"--resume, replace it with --overwrite, or choose another folder")
    if export:
        _check_export_possible()
    donor, recalibrate, continued_optimizer = None, set(), False
    if state is None:
        if init_from is not None:
            donor = _load_donor(init_from)
            if continue_from is not None and config is None:  # its recipe, this run's epochs
                config = continued_config(donor, overrides, continue_from)
            elif config is None:  # same architecture and settings as the run the networks come from
                config = TrainConfig(**{k: v for k, v in _config_of(donor).items()
                                        if k in {f.name for f in dataclasses.fields(TrainConfig)}})
        config = dataclasses.replace(config or TrainConfig(), **overrides)
        if donor is not None:
            dc = _config_of(donor)
            loaded = [k for k in STAGES if k not in stages or warm_start]
            if "width" in dc and dc["width"] != config.width:
                raise ConfigError(f"--init-from {init_from}: its networks have width {dc['width']}, not "
                                  f"{config.width} (give --width {dc['width']})")
            if "pipnet" in loaded and bool(dc.get("sfp_prior", False)) != bool(config.sfp_prior):
                raise ConfigError(f"--init-from {init_from}: its PIPNet was trained "
                                  f"{'with' if dc.get('sfp_prior') else 'without'} the SfP prior "
                                  f"(give {'--sfp-prior' if dc.get('sfp_prior') else '--no-sfp-prior'})")
    epochs = {"pipnet": config.pipnet_epochs, "pmmnet": config.pmmnet_epochs, "direct": config.direct_epochs}
    if donor is not None:
        for k in STAGES:
            if k not in stages:
                epochs[k] = int(donor["config"].get(f"{k}_epochs", 0))
    _check_config(config, stages, epochs)

    # -- the data (still nothing written)
    t0 = time.time()
    manifest = read_manifest(data_dir)
    if manifest.get("holdout"):
        raise ConfigError(f"{data_dir} is a held-out set (polrig sim dataset --holdout: families "
                          f"{', '.join(manifest.get('families_present') or manifest.get('holdout_families') or [])}); "
                          f"those families are the acceptance test set of polrig evaluate, and a model trained "
                          f"on them would be scored on its own training shapes: train on a set made without --holdout")
    identity = dataset_identity(manifest)
    if state is not None and state.get("dataset") is not None and state["dataset"] != identity:
        diff = [k for k in {**state["dataset"], **identity} if identity.get(k) != state["dataset"].get(k)]
        raise ConfigError(f"--resume: {data_dir} is not the dataset the run in {out} trains on "
                          f"({', '.join(diff)} differ; it trained on {state.get('data', 'another folder')})")
    ds = load_dataset(data_dir, config.limit)
    check_network_size(ds, data_dir)
    device = torch.device(config.device)
    t = {k: v.to(device) for k, v in _tensors(ds).items()}
    n = len(ds)
    colours = ds["analyzer"].shape[1]
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    perm = rng.permutation(n)
    n_val = max(1, int(round(config.val_fraction * n))) if n > 1 else 0
    val_idx, train_idx = torch.from_numpy(perm[:n_val]), torch.from_numpy(perm[n_val:] if n > 1 else perm)

    models = {"pipnet": PIPNet(colours, config.width, config.sfp_prior), "pmmnet": PMMNet(colours, config.width),
              "direct": DirectStokesToMM(colours, config.width)}
    models = {k: m.to(device) for k, m in models.items()}  # before the optimizers see the parameters
    steps = {"pipnet": pipnet_step, "pmmnet": pmmnet_step, "direct": direct_step}
    opts = {k: torch.optim.Adam(m.parameters(), lr=config.lr) for k, m in models.items()}
    times = {k: 0.0 for k in STAGES}
    start_stage, start_epoch = 0, 0
    rows: list[dict] = []
    try:
        if donor is not None:
            for k in STAGES:
                if k not in stages or warm_start:
                    models[k].load_state_dict(donor["models"][k])
                if k not in stages:
                    times[k] = float((donor.get("times") or {}).get(k, 0.0))
            if warm_start and donor.get("recovered_from_onnx"):
                recalibrate = set(stages)
            if continue_from is not None:
                continued_optimizer = continue_checkpoint(donor, opts, continue_from, echo)
        if state is not None:
            for k in STAGES:
                models[k].load_state_dict(state["models"][k])
                opts[k].load_state_dict(state["optimizers"][k])
    except (RuntimeError, KeyError, ValueError) as exc:
        src = ckpt_path if state is not None else init_from
        raise ConfigError(f"{src}: its networks do not fit the ones configured here (width {config.width}, "
                          f"sfp_prior {config.sfp_prior}, {colours} colours): {_reason(exc)}") from exc
    if donor is not None:
        echo(f"networks {[k for k in STAGES if k not in stages]} taken from {init_from}")
        if warm_start:
            echo(f"networks {list(stages)} warm-started from {init_from}")
    if state is not None:
        times = {k: float(v) for k, v in state["times"].items()}
        start_stage, start_epoch = STAGES.index(state["stage"]), int(state["epoch"])
        recalibrate = set(state.get("recalibrate", ()))
        if "rng_state" in state:
            rng.bit_generator.state = state["rng_state"]
        else:  # a checkpoint of an older polrig: its stream goes on from a stored seed
            rng = np.random.default_rng(state["rng_seed"])
            echo("note: a checkpoint without random states (older polrig): the rest of the run is not "
                 "bit-identical to an uninterrupted one")
        if "torch_rng_state" in state:
            torch.set_rng_state(state["torch_rng_state"])
        rows = list(state["log"]) if "log" in state else _legacy_log_rows(out / "log.csv", state["stage"],
                                                                            start_epoch)
        if init_from is not None:
            echo(f"note: --init-from {init_from} ignored: the run resumes with the networks of its checkpoint")
        echo(f"resuming from {ckpt_path}: stage {state['stage']} epoch {state['epoch']}")

    # -- from here on OUT is written
    out.mkdir(parents=True, exist_ok=True)
    if overwrite:
        for f in _run_files(out):
            f.unlink()
    if state is not None:
        if state.get("dataset") is None:
            echo(f"note: {ckpt_path} does not record its dataset (older polrig); make sure --data is the set "
                 f"it trained on")
        _write_log(out / "log.csv", rows)  # exactly the rows of the epochs the checkpoint holds
    echo(f"data: {n} samples of {ds.shape[0]}x{ds.shape[1]} ({len(train_idx)} train, {n_val} val), "
         f"loaded in {time.time() - t0:.1f}s")

    if state is not None:
        before = list(state.get("lineage_before") or [])
        start_kind, optimizer_kind = state.get("start_kind", "scratch"), state.get("optimizer_kind", "fresh")
    else:
        before = list((donor or {}).get("lineage") or [])
        start_kind = "continued" if continue_from is not None else "warm" if warm_start else "scratch"
        optimizer_kind = "continued" if continued_optimizer else "fresh"
    per_epoch = -(-len(train_idx) // config.batch_size)

    def lineage() -> list[dict]:
        """The runs before this one and this run's entries so far (:mod:`polrig.models.lineage`)."""
        return before + run_entries([r for r in rows if r["stage"] in stages], run=str(out), start=start_kind,
                                    steps_per_epoch={k: per_epoch for k in STAGES}, data=str(data_dir),
                                    device=config.device, hardware=hardware_line(config.device),
                                    optimizer=optimizer_kind)

    def save(stage: str, epoch: int) -> None:
        save_checkpoint(ckpt_path, config=config, epochs=epochs, stage=stage, epoch=epoch, stages=stages,
                        models=models, opts=opts, times=times, rng=rng, recalibrate=sorted(recalibrate),
                        rows=rows, dataset=identity, data=str(data_dir),
                        init_from=None if init_from is None else str(init_from),
                        lineage_before=before, lineage=lineage(), start_kind=start_kind,
                        optimizer_kind=optimizer_kind, size=(donor or state or {}).get("size"))

    saved = [(state["stage"], int(state["epoch"]))] if state is not None else []
    try:
        for si, stage in enumerate(STAGES):
            if si < start_stage or stage not in stages:
                continue
            first = start_epoch if si == start_stage else 0
            if first >= epochs[stage]:
                continue
            if stage == "pmmnet":
                t_init = time.time()
                add_initialization(models["pipnet"].eval(), t)
                echo(f"pmmnet: PIPNet-pBRDF initialization of {n} samples in {time.time() - t_init:.1f}s")
            model, opt = models[stage], opts[stage]
            if stage in recalibrate and first == 0:  # batch norms of a network recovered from ONNX (polrig.models.recover)
                from polrig.models.recover import recalibrate_batchnorm

                calib = train_idx[:RECALIBRATION_SAMPLES]
                recalibrate_batchnorm(model, [lambda i=calib[b]: model(*_pick(t, i, STAGE_INPUTS[stage]))
                                              for b in _batches(len(calib), config.batch_size, None)])
                echo(f"{stage}: batch-norm statistics of the recovered network set on {len(calib)} samples")
            recalibrate.discard(stage)
            if plan_stage is not None and first == 0:
                planned = plan_stage(stage, list(rows))
                if isinstance(planned, bool) or not isinstance(planned, (int, np.integer)) or planned < 1:
                    raise ValueError(f"plan_stage returned {planned!r} epochs for {stage} (an integer >= 1 expected)")
                epochs[stage] = int(planned)
            for epoch in range(first, epochs[stage]):
                lr = lr_at(config, epoch, epochs[stage])
                for g in opt.param_groups:
                    g["lr"] = lr
                te = time.time()
                train_step = step_with_augmentations(stage, config, rng)
                where = f"{stage} epoch {epoch} (lr {lr:.3g})"
                train_loss, detail = _run_epoch(with_precision(model, config), train_step, t, train_idx,
                                                config.batch_size, opt, rng, where)
                val_loss = _evaluate(model, steps[stage], t, val_idx, config.batch_size) if n_val else float("nan")
                if n_val and not math.isfinite(val_loss):
                    raise TrainingError(f"{where}: the validation loss is {val_loss}; training stopped (the "
                                        f"checkpoint of the last finished epoch is kept); lower --lr")
                dt = time.time() - te
                times[stage] += dt
                row = {"stage": stage, "epoch": epoch, "lr": lr, "train_loss": train_loss,
                       "val_loss": val_loss, "epoch_s": dt, "details": json.dumps(detail)}
                rows.append(row)
                save(stage, epoch + 1)  # the checkpoint first (atomic), then the log that matches it
                saved[:] = [(stage, epoch + 1)]
                _write_log(out / "log.csv", rows)
                _echo_row(echo, row)
    except KeyboardInterrupt:
        if saved and saved[0][1] > 0:
            echo(f"interrupted: {ckpt_path} holds the run through {saved[0][0]} epoch {saved[0][1] - 1}; "
                 f"continue with --resume")
        elif saved:
            echo(f"interrupted: {ckpt_path} holds the run up to the start of the {saved[0][0]} stage; "
                 f"continue with --resume")
        else:
            echo("interrupted before the first epoch finished: nothing saved")
        raise

    summary = {"config": dataclasses.asdict(dataclasses.replace(config, **{f"{k}_epochs": v
                                                                         for k, v in epochs.items()})),
               "data": str(data_dir), "dataset": identity, "samples": n,
               "stages_trained": list(stages), "init_from": None if init_from is None else str(init_from),
               "resolution": list(ds.shape), "train_seconds": times,
               "torch_threads": torch.get_num_threads(), "torch_version": torch.__version__}
    if state is not None and state.get("init_from"):
        summary["init_from"] = state["init_from"]
    summary["lineage"] = lineage()
    if export:
        from polrig.models.export import export_all

        pick = (val_idx[:2] if n_val else train_idx[:2]).to(device)
        sample = {k: t[k][pick].cpu() for k in ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")}
        models = {k: m.cpu() for k, m in models.items()}  # the export and its check run on the CPU
        frames = ds.manifest.get("frames", {})
        extra = {"stage_zero_axis_camera": [float(x) for x in t["stage_zero_axis"][0]],
                 "camera_x_axis_camera": frames.get("camera_x_axis_camera", [1.0, 0.0, 0.0]),
                 "training": {"samples": n, "resolution": list(ds.shape),
                              "dataset": {k: ds.manifest.get(k) for k in
                                          ("format", "version", "seed", "holdout", "families_present",
                                           "intrinsics", "normalisation")},
                              "train_seconds": times, "config": summary["config"],
                              "hardware": hardware_line(config.device), "lineage": summary["lineage"],
                              "totals": lineage_totals(summary["lineage"])}}
        size = (donor or state or {}).get("size")
        if size is not None:  # a continued size stays that size
            extra["size"] = size
        summary["export"] = export_all(models["pipnet"], models["pmmnet"], models["direct"],
                                       out / "weights", sample, extra)
        for name, rec in summary["export"].items():
            echo(f"export {name}: {rec['bytes'] / 1e6:.2f} MB, max |onnx - torch| = {rec['max_abs_diff']:.3g}")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2))
    return summary
