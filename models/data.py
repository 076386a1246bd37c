"""Load ``polrig sim dataset`` output for training and evaluation.

A dataset folder holds ``manifest.json`` and ``shard-*.npz`` files, each with float32 arrays
over its samples (plane-first, ``docs/conventions.md``): ``analyzer`` (N,C,4,H,W) normalised
analyzer images, ``mask`` (N,H,W), ``normal``/``kd``/``wi``/``wo`` (N,3,H,W) camera frame,
``alpha`` (N,), ``s_in`` (N,3) normalised incident Stokes, ``mueller`` (N,C,3,3,H,W) on the
analyzer's scale, ``family`` (N,), ``scale`` (N,) (DN per normalised unit), ``lit`` (N,H,W)
object pixels that face the light and are not shadowed, ``eta`` (N,) the material's index of
refraction, ``material_kind`` (N,) the index of the material kind in the manifest's
``materials.kinds`` (all optional). The stage zero
axis in the camera frame comes from ``stage_zero_axis`` (N,3) in the shards, or from the
manifest (one axis for the whole set: ``frames.stage_zero_axis_camera`` in the simulator's
manifest, :mod:`polrig.sim.dataset`).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import zipfile
import zlib

import numpy as np

from polrig.errors import ConfigError, FormatError
from polrig.models.size import SIZE_MULTIPLE

#: Arrays every shard must hold.
REQUIRED = ("analyzer", "mask", "normal", "kd", "wi", "wo", "alpha", "s_in", "mueller")
OPTIONAL = ("family", "scale", "stage_zero_axis", "lit", "eta", "material_kind")


@dataclasses.dataclass
class Dataset:
    """All samples of a dataset folder as numpy arrays (float32 unless stated)."""

    arrays: dict[str, np.ndarray]
    manifest: dict

    def __len__(self) -> int:
        return int(self.arrays["analyzer"].shape[0])

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.arrays["analyzer"].shape[-2:])  # type: ignore[return-value]

    def subset(self, index) -> "Dataset":
        if isinstance(index, (list, tuple)):  # sample indices (an empty list included)
            index = np.asarray(index, dtype=np.intp)
        return Dataset({k: v[index] for k, v in self.arrays.items()}, self.manifest)


def _stage_axes(manifest: dict, n: int) -> np.ndarray | None:
    for key in ("stage_zero_axis_camera", "stage_zero_axis"):
        if key in manifest:
            axis = np.asarray(manifest[key], dtype=np.float32).reshape(-1, 3)
            return np.broadcast_to(axis, (n, 3)).copy() if len(axis) == 1 else axis
    for section in ("frames", "rig"):
        sub = manifest.get(section) or {}
        for key in ("stage_zero_axis_camera", "stage_zero_axis"):
            if key in sub:
                return np.broadcast_to(np.asarray(sub[key], np.float32).reshape(3), (n, 3)).copy()
    return None


def read_manifest(folder: str | pathlib.Path) -> dict:
    """``folder/manifest.json`` as a dict. :class:`FileNotFoundError` when it is missing,
    :class:`FormatError` naming the file when it is not a JSON object."""
    manifest_path = pathlib.Path(folder) / "manifest.json"
    if not manifest_path.is_file():
        raise FileNotFoundError(f"{manifest_path} not found (make one with `polrig sim dataset`)")
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise FormatError(f"{manifest_path}: not a readable JSON dataset manifest ({exc})") from None
    if not isinstance(manifest, dict):
        raise FormatError(f"{manifest_path}: not a dataset manifest (a JSON object expected, got "
                          f"{type(manifest).__name__})")
    return manifest


def _check_limit(limit) -> None:
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or limit < 1):
        raise ValueError(f"limit must be an integer >= 1 (or None for every sample), got {limit!r}")


def load_dataset(folder: str | pathlib.Path, limit: int | None = None) -> Dataset:
    """Read every shard of ``folder`` (sorted by name), at most ``limit`` samples (an integer
    >= 1, or None for all).

    Raises :class:`FileNotFoundError` for a missing folder or manifest and :class:`FormatError`
    naming the file for a damaged manifest or shard and the first missing or malformed array."""
    _check_limit(limit)
    folder = pathlib.Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"dataset folder {folder} not found" if not folder.exists()
                                else f"{folder} is not a dataset folder")
    manifest = read_manifest(folder)
    shards = sorted(folder.glob("shard-*.npz"))
    if not shards:
        raise FormatError(f"{folder}: no shard-*.npz files")
    parts: dict[str, list[np.ndarray]] = {}
    total = 0
    for shard in shards:
        try:
            with np.load(shard, allow_pickle=False) as z:
                missing = [k for k in REQUIRED if k not in z.files]
                if missing:
                    raise FormatError(f"{shard}: missing arrays {missing}")
                n = z["analyzer"].shape[0]
                take = n if limit is None else min(n, limit - total)
                for k in REQUIRED + OPTIONAL:
                    if k in z.files:
                        parts.setdefault(k, []).append(np.asarray(z[k][:take]))
                total += take
        except FormatError:
            raise
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as exc:
            raise FormatError(f"{shard}: not a readable dataset shard (truncated or damaged: "
                              f"{str(exc) or type(exc).__name__}); remake it with the same "
                              f"`polrig sim dataset` command") from None
        if limit is not None and total >= limit:
            break
    try:
        arrays = {k: np.concatenate(v, 0) for k, v in parts.items()}
    except ValueError as exc:
        raise FormatError(f"{folder}: shards of different image sizes or layouts ({exc})") from None
    n = arrays["analyzer"].shape[0]
    if "stage_zero_axis" not in arrays:
        axes = _stage_axes(manifest, n)
        if axes is None:
            raise FormatError(f"{folder}: no stage_zero_axis in the shards or the manifest")
        arrays["stage_zero_axis"] = axes
    if arrays["analyzer"].ndim != 5:
        raise FormatError(f"{folder}: analyzer must be (N, C, 4, H, W), got {arrays['analyzer'].shape}")
    for k in ("analyzer", "normal", "kd", "wi", "wo", "alpha", "s_in", "mueller", "stage_zero_axis"):
        arrays[k] = np.ascontiguousarray(arrays[k], dtype=np.float32)
    arrays["mask"] = (np.asarray(arrays["mask"]) > 0).astype(np.float32)
    _check_shapes(arrays, folder)
    return Dataset(arrays, manifest)


def has_lit_object(ds: Dataset, i: int) -> bool:
    """Whether sample ``i`` has a lit object pixel: an object pixel whose true Mueller matrix is
    not zero. Samples without one (the object wholly in shadow, or no object) carry no signal,
    only noise scaled by the 1 DN floor of ``scale``: :mod:`polrig.models.evaluate` does not score
    them, and nothing fitted to a set's signal (its noise model, an uncertainty calibration, the
    geometry diagnosis) may use them. The one rule every consumer shares."""
    mask = ds["mask"][i] > 0
    return bool(mask.any() and np.any(ds["mueller"][i][..., mask]))


def lit_samples(ds: Dataset) -> list[int]:
    """Indices of the samples of ``ds`` with a lit object pixel (:func:`has_lit_object`)."""
    return [i for i in range(len(ds)) if has_lit_object(ds, i)]


def check_network_size(ds: Dataset, folder) -> None:
    """:class:`ConfigError` unless the images' sides are multiples of the networks' size
    multiple (:data:`polrig.models.size.SIZE_MULTIPLE`): the graphs run on whole images without
    padding in training and evaluation."""
    h, w = ds.shape
    if h % SIZE_MULTIPLE or w % SIZE_MULTIPLE:
        raise ConfigError(f"{folder}: images are {w}x{h} pixels; the networks need sides that are "
                          f"multiples of {SIZE_MULTIPLE} (make the set with `polrig sim dataset "
                          f"--size` a multiple of {SIZE_MULTIPLE})")


#: Manifest keys that identify a dataset (two folders with equal values hold the same samples).
IDENTITY_KEYS = ("format", "version", "count", "width", "height", "seed", "holdout", "shard_size",
                 "families_present")


def dataset_identity(manifest: dict) -> dict:
    """What identifies a dataset: :data:`IDENTITY_KEYS` of its manifest, its stage zero axis
    rule (``frames.stage_zero_axes``) and, where not the default, its material mix
    (``materials.mix`` other than ``"baek"``) and interreflections (``transport.indirect_samples``
    > 0); the identity of a set made before those existed is unchanged."""
    ident = {k: manifest.get(k) for k in IDENTITY_KEYS}
    frames = manifest.get("frames")
    ident["stage_zero_axes"] = frames.get("stage_zero_axes") if isinstance(frames, dict) else None
    mats, trans = manifest.get("materials"), manifest.get("transport")
    mix = mats.get("mix", "baek") if isinstance(mats, dict) else "baek"
    indirect = trans.get("indirect_samples", 0) if isinstance(trans, dict) else 0
    if mix != "baek":
        ident["material_mix"] = mix
    if indirect:
        ident["indirect_samples"] = indirect
    return ident


def _check_shapes(a: dict[str, np.ndarray], folder) -> None:
    n, c, four, h, w = a["analyzer"].shape
    expect = {"mask": (n, h, w), "normal": (n, 3, h, w), "kd": (n, c, h, w), "wi": (n, 3, h, w),
              "wo": (n, 3, h, w), "alpha": (n,), "s_in": (n, 3), "mueller": (n, c, 3, 3, h, w),
              "stage_zero_axis": (n, 3)}
    if four != 4:
        raise FormatError(f"{folder}: analyzer must be (N, C, 4, H, W), got {a['analyzer'].shape}")
    for k, shape in expect.items():
        if a[k].shape != shape:
            raise FormatError(f"{folder}: {k} has shape {a[k].shape}, expected {shape}")


def write_dataset(folder: str | pathlib.Path, arrays: dict[str, np.ndarray], manifest: dict,
                  shard_size: int = 256) -> None:
    """Write arrays in the dataset format (used by tests and by :func:`crop_dataset`)."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n = arrays["analyzer"].shape[0]
    for i, start in enumerate(range(0, n, shard_size)):
        np.savez(folder / f"shard-{i:05d}.npz", **{k: v[start:start + shard_size] for k, v in arrays.items()})
    (folder / "manifest.json").write_text(json.dumps(dict(manifest, count=n), indent=2))
