"""The shipped model sizes: a user's trade between speed and accuracy (issue 32, item 3).

A model size is a named, shipped weights folder (graphs, ``model.json``, ``uncertainty.json``):

=========  ==========================  =====================================================
size       folder                      what it is for
=========  ==========================  =====================================================
``small``  ``models/weights/``         the networks trained on CPUs (width 16): CPUs, the live view
``large``  ``models/weights/large/``   a wider pair trained on a GPU lease (``benchmarks/gpu_train.sh``)
=========  ==========================  =====================================================

The small size stays where the shipped weights always were, so every path, tool and test that
names ``models/weights`` keeps meaning the small model. A size is *shipped* when its folder
holds ``single_shot.onnx`` and ``model.json``.

Choosing (:func:`choose_size`): ``small`` and ``large`` name one; ``auto`` (the default of
``polrig infer``, capture, reconstruct and the GUI) takes ``large`` where the networks will run on
CUDA and it is shipped, else ``small``: on a CPU the default is always the small one. Asking
for a size that is not shipped is one line (:class:`ModelSizeUnavailable`) saying how to get it.

What a result records of its model (:func:`model_record`: the EXR header's ``model_size`` and
``model_training``, the session manifest's ``model`` per result) is read from ``model.json``:
``size``, and its ``training`` entry's ``hardware`` and lineage seconds. Weights exported before
sizes existed (no ``size`` key) are the folder's size, and the small model's hardware is its
model card's (:data:`LEGACY_HARDWARE`).

No torch, no onnxruntime: the runtime, the route and the shells all read sizes from here.
"""

from __future__ import annotations

import json
import pathlib
from typing import Any

from polrig.errors import ConfigError

#: The folder of the shipped weights (the small size's).
WEIGHTS_ROOT = pathlib.Path(__file__).resolve().parent / "weights"
#: Size name -> its shipped weights folder.
SIZE_FOLDERS = {"small": WEIGHTS_ROOT, "large": WEIGHTS_ROOT / "large"}
SIZES = tuple(SIZE_FOLDERS)
#: What ``--model-size`` accepts.
CHOICES = ("auto", *SIZES)
#: What makes a size shipped.
SHIPPED_FILES = ("single_shot.onnx", "model.json")
#: How the small networks shipped before sizes existed were trained (models/MODEL_CARD.md).
LEGACY_HARDWARE = "CPU, 2 cores (the shipped runs of issues 7-12)"
#: How to get a size that is not shipped (one line of :class:`ModelSizeUnavailable`).
HOW_TO_TRAIN = {"large": "it is trained on a GPU lease by benchmarks/gpu_train.sh (polrig.models.lease)",
                "small": "reinstall polrig, or train one with polrig train"}


class ModelSizeUnavailable(ConfigError):
    """A model size asked for by name is not shipped with this installation."""


def size_folder(size: str) -> pathlib.Path:
    """The weights folder of ``size`` (``small`` or ``large``; :class:`ConfigError` otherwise)."""
    if size not in SIZE_FOLDERS:
        raise ConfigError(f"--model-size {size!r}: must be one of {', '.join(CHOICES)}")
    return SIZE_FOLDERS[size]


def is_shipped(size: str) -> bool:
    """Whether ``size``'s folder holds its graph and description."""
    folder = size_folder(size)
    return all((folder / f).is_file() for f in SHIPPED_FILES)


def shipped_sizes() -> tuple[str, ...]:
    return tuple(s for s in SIZES if is_shipped(s))


def choose_size(requested: str, on_cuda: bool) -> str:
    """The size to load for ``requested`` (:data:`CHOICES`) when the networks run on CUDA
    (``on_cuda``) or not (module docstring). A named size that is not shipped:
    :class:`ModelSizeUnavailable`, one line naming how to get it."""
    if requested == "auto":
        return "large" if on_cuda and is_shipped("large") else "small"
    folder = size_folder(requested)
    if not is_shipped(requested):
        raise ModelSizeUnavailable(
            f"--model-size {requested}: the {requested} model is not shipped yet ({folder} holds no "
            f"{' / '.join(SHIPPED_FILES)}); {HOW_TO_TRAIN[requested]}; use --model-size "
            f"{'small' if requested != 'small' else 'auto'} meanwhile")
    return requested


def read_meta(folder: str | pathlib.Path) -> dict[str, Any]:
    """``model.json`` of a weights folder ({} where absent or unreadable: the runtime reports those)."""
    try:
        meta = json.loads((pathlib.Path(folder) / "model.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return meta if isinstance(meta, dict) else {}


def size_of(folder: str | pathlib.Path, meta: dict[str, Any] | None = None) -> str | None:
    """The size a weights folder holds: ``model.json``'s ``size``, else the shipped folder's
    name it is (None: a folder of the user's own, without a recorded size)."""
    meta = read_meta(folder) if meta is None else meta
    if isinstance(meta.get("size"), str):
        return meta["size"]
    resolved = pathlib.Path(folder).resolve()
    return next((s for s, f in SIZE_FOLDERS.items() if f.resolve() == resolved), None)


def training_seconds(training: dict[str, Any]) -> float:
    """Seconds the networks were trained, over every run: the lineage's ``seconds`` where it
    has them (every run it went through), else the last run's ``train_seconds``."""
    lineage = training.get("lineage") or []
    if lineage:
        return float(sum(float(r.get("seconds") or 0.0) for r in lineage))
    return float(sum(float(v) for v in (training.get("train_seconds") or {}).values()))


def model_record(folder: str | pathlib.Path, meta: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a result records of the model that made it: ``size`` (None for an unsized folder of
    the user's), ``width``, ``training_hardware`` and ``training_minutes`` (over the whole
    lineage), from ``model.json``."""
    meta = read_meta(folder) if meta is None else meta
    training = meta.get("training") or {}
    size = size_of(folder, meta)
    hardware = training.get("hardware")
    if not hardware and size == "small" and meta.get("size") is None:
        hardware = LEGACY_HARDWARE
    seconds = training_seconds(training)
    return {"size": size, "width": meta.get("width"),
            "training_hardware": hardware or "not recorded",
            "training_minutes": round(seconds / 60.0, 1) if seconds else None}
