"""OpenEXR files of Stokes and Mueller images, with polrig metadata in the header.

Channel names follow ``docs/conventions.md`` (Mitsuba 3's ``stokes`` integrator naming):
Stokes ``S{k}.{R,G,B}`` (mono ``S{k}.Y``), Mueller ``M{row}{col}.{R,G,B}`` (mono ``.Y``), all
float32, one scan-line part, ZIP compression or none (``compress``; both lossless: a float32 round
trip is bit-exact, NaN payloads included). Any number of extra ``(H, W)`` planes can ride along under their own
channel names (``mask``, ``dolp.R``, ``sigma.M00.R``, ...); :func:`colour_planes` names the
planes of a ``(C, H, W)`` array. Boolean planes are stored as float32 0/1.

Header attributes: ``polrig:conventions`` (:data:`polrig.conventions.CONVENTIONS_VERSION`),
``polrig:kind`` (``"stokes"`` or ``"mueller"``) and one string attribute ``polrig:<key>`` per
metadata entry holding its JSON encoding (incident state, calibration id, capture info, ...).

Written with the OpenEXR 3.x Python bindings (``OpenEXR.File(header, channels).write``;
reading ``OpenEXR.File(path, separate_channels=True)``; see the OpenEXR "Python bindings"
documentation, openexr.com). Writes are atomic (temporary file in the same folder, fsync,
``os.replace``); a write that fails (full disk, read-only folder) raises :class:`OSError` with
one line naming the file and leaves no temporary file behind. Unreadable, truncated, non-EXR files and missing channels raise
:class:`polrig.errors.FormatError` with one line naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from typing import Any, Mapping

import numpy as np
import OpenEXR

from polrig.conventions import CONVENTIONS_VERSION, MONO, RGB
from polrig.errors import FormatError
from polrig.rawio import check_input_file, temporary_sibling, write_error

PathLike = str | os.PathLike
_PREFIX = "polrig:"


def channel_suffixes(n_colours: int) -> tuple[str, ...]:
    """Channel suffixes of a colour count: ``("Y",)`` for mono, ``("R", "G", "B")`` for 3."""
    if n_colours == 1:
        return MONO
    if n_colours == 3:
        return RGB
    raise ValueError(f"images have 1 (mono) or 3 (RGB) colour planes, got {n_colours}")


def colour_planes(prefix: str, planes: np.ndarray) -> dict[str, np.ndarray]:
    """``{"prefix.R": ..., "prefix.G": ..., "prefix.B": ...}`` (or ``prefix.Y``) of a
    ``(C, H, W)`` array."""
    p = np.asarray(planes)
    if p.ndim != 3:
        raise ValueError(f"{prefix}: expected (C, H, W) planes, got shape {p.shape}")
    return {f"{prefix}.{s}": p[i] for i, s in enumerate(channel_suffixes(p.shape[0]))}


def element_planes(prefix: str, stack: np.ndarray) -> dict[str, np.ndarray]:
    """``{"prefix.M{r}{c}.{colour}": ...}`` of a per-element image stack ``(C, 3, 3, H, W)``
    (e.g. the ``sigma`` planes beside a Mueller image)."""
    out: dict[str, np.ndarray] = {}
    for r in range(3):
        for c in range(3):
            out.update(colour_planes(f"{prefix}.M{r}{c}", stack[:, r, c]))
    return out


def stokes_channels(n_colours: int) -> list[str]:
    return [f"S{k}.{s}" for k in range(3) for s in channel_suffixes(n_colours)]


def mueller_channels(n_colours: int) -> list[str]:
    return [f"M{r}{c}.{s}" for r in range(3) for c in range(3) for s in channel_suffixes(n_colours)]


@dataclasses.dataclass
class ExrImage:
    """What :func:`read_exr` returns: float32 planes by channel name and decoded metadata."""

    path: pathlib.Path
    planes: dict[str, np.ndarray]
    metadata: dict[str, Any]
    kind: str | None
    conventions: str | None

    @property
    def shape(self) -> tuple[int, int]:
        return next(iter(self.planes.values())).shape  # type: ignore[return-value]


@dataclasses.dataclass
class StokesExr:
    stokes: np.ndarray  # (C, 3, H, W)
    extra: dict[str, np.ndarray]
    metadata: dict[str, Any]
    conventions: str | None


@dataclasses.dataclass
class MuellerExr:
    mueller: np.ndarray  # (C, 3, 3, H, W)
    extra: dict[str, np.ndarray]
    metadata: dict[str, Any]
    conventions: str | None


# -- writing ---------------------------------------------------------------------------------
def write_exr(path: PathLike, planes: Mapping[str, np.ndarray], *, kind: str | None = None,
              metadata: Mapping[str, Any] | None = None, compress: bool = True) -> pathlib.Path:
    """Write ``(H, W)`` planes as float32 channels plus polrig header metadata, atomically.
    ``compress``: ZIP (lossless); False writes them uncompressed (float32 images of measured
    data shrink by only about a tenth under ZIP, for about 12 times the writing time)."""
    path = pathlib.Path(path)
    if not planes:
        raise ValueError("an EXR file needs at least one channel")
    chans: dict[str, np.ndarray] = {}
    shape = None
    for name, p in planes.items():
        a = np.asarray(p)
        if a.dtype == bool:
            a = a.astype(np.float32)
        a = np.ascontiguousarray(a, dtype=np.float32)
        if a.ndim != 2:
            raise ValueError(f"channel {name!r}: planes must be 2-D, got shape {a.shape}")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise ValueError(f"channel {name!r} has shape {a.shape}, others {shape}")
        chans[str(name)] = a
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION if compress else OpenEXR.NO_COMPRESSION,
                              "type": OpenEXR.scanlineimage,
                              _PREFIX + "conventions": CONVENTIONS_VERSION}
    if kind:
        header[_PREFIX + "kind"] = kind
    for key, value in (metadata or {}).items():
        try:
            header[_PREFIX + str(key)] = json.dumps(value, sort_keys=True, allow_nan=True,
                                                    default=_json_default)
        except TypeError as exc:
            raise ValueError(f"metadata {key!r} is not JSON-serialisable: {exc}") from None
    tmp = str(temporary_sibling(path))
    try:
        try:
            OpenEXR.File(header, chans).write(tmp)
        except RuntimeError as exc:  # OpenEXR reports I/O failures (full disk, ...) this way
            raise OSError(f"{path}: cannot write the OpenEXR file "
                          f"({_openexr_reason(exc, tmp)})") from None
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and tmp in str(exc):
            raise write_error(path, exc) from None  # name the user's file, not the temporary one
        raise
    return path


def _openexr_reason(exc: RuntimeError, tmp: str) -> str:
    """The operating system's reason in an OpenEXR write error, without the temporary name:
    ``Failed to write pixel data to image file "x.tmp.exr". No space left on device.`` ->
    ``No space left on device``."""
    text = (str(exc).splitlines() or [""])[0]
    quoted = f'"{tmp}"'
    if quoted in text:
        head, _, tail = text.partition(quoted)
        text = tail.strip(" .") or head.strip(" .")
    return text.replace(tmp, "").strip(" .") or type(exc).__name__


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, pathlib.PurePath):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON-serialisable")


def write_stokes_exr(path: PathLike, stokes: np.ndarray, *,
                     extra: Mapping[str, np.ndarray] | None = None,
                     metadata: Mapping[str, Any] | None = None) -> pathlib.Path:
    """Write Stokes images ``(C, 3, H, W)`` as ``S{k}.{R,G,B|Y}`` plus ``extra`` planes."""
    s = np.asarray(stokes)
    if s.ndim != 4 or s.shape[1] != 3:
        raise ValueError(f"Stokes images must have shape (C, 3, H, W), got {s.shape}")
    planes: dict[str, np.ndarray] = {}
    for k in range(3):
        planes.update(colour_planes(f"S{k}", s[:, k]))
    _merge_extra(planes, extra)
    return write_exr(path, planes, kind="stokes", metadata=metadata)


def write_mueller_exr(path: PathLike, mueller: np.ndarray, *,
                      extra: Mapping[str, np.ndarray] | None = None,
                      metadata: Mapping[str, Any] | None = None, compress: bool = True) -> pathlib.Path:
    """Write Mueller images ``(C, 3, 3, H, W)`` as ``M{row}{col}.{R,G,B|Y}`` plus ``extra``.

    Typical ``metadata`` keys: ``incident_state``, ``calibration_id``, ``capture``.
    """
    m = np.asarray(mueller)
    if m.ndim != 5 or m.shape[1:3] != (3, 3):
        raise ValueError(f"Mueller images must have shape (C, 3, 3, H, W), got {m.shape}")
    planes: dict[str, np.ndarray] = {}
    for r in range(3):
        for c in range(3):
            planes.update(colour_planes(f"M{r}{c}", m[:, r, c]))
    _merge_extra(planes, extra)
    return write_exr(path, planes, kind="mueller", metadata=metadata, compress=compress)


def _merge_extra(planes: dict[str, np.ndarray], extra: Mapping[str, np.ndarray] | None) -> None:
    for name, p in (extra or {}).items():
        if name in planes:
            raise ValueError(f"extra plane {name!r} clashes with an image channel")
        planes[name] = p


# -- reading ---------------------------------------------------------------------------------
def read_exr(path: PathLike) -> ExrImage:
    """Read every channel (float32 ``(H, W)``) and the polrig metadata of an EXR file."""
    path = pathlib.Path(path)
    check_input_file(path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"\x76\x2f\x31\x01":  # OpenEXR magic number 20000630, little-endian
        raise FormatError(f"{path}: not an OpenEXR file (bad magic number)")
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        header = f.header()
        chans = f.channels()
        planes = {name: np.asarray(c.pixels) for name, c in chans.items()}
    except (RuntimeError, ValueError, OSError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise FormatError(f"{path}: unreadable or truncated OpenEXR file ({msg})") from None
    if not planes:
        raise FormatError(f"{path}: OpenEXR file has no channels")
    for name, p in planes.items():
        if p.dtype != np.float32:
            planes[name] = p.astype(np.float32)
    metadata: dict[str, Any] = {}
    for key, value in header.items():
        if not key.startswith(_PREFIX) or key in (_PREFIX + "kind", _PREFIX + "conventions"):
            continue
        try:
            metadata[key[len(_PREFIX):]] = json.loads(value)
        except (TypeError, ValueError):
            raise FormatError(f"{path}: header attribute {key!r} is not JSON") from None
    return ExrImage(path, planes, metadata, header.get(_PREFIX + "kind"),
                    header.get(_PREFIX + "conventions"))


def _n_colours(img: ExrImage, first: str) -> int:
    if all(f"{first}.{s}" in img.planes for s in RGB):
        return 3
    if f"{first}.Y" in img.planes:
        return 1
    present = sorted(img.planes)
    raise FormatError(f"{img.path}: missing channels {first}.R/G/B or {first}.Y "
                      f"(has: {', '.join(present[:12])}{' ...' if len(present) > 12 else ''})")


def _require(img: ExrImage, names: list[str]) -> None:
    missing = [n for n in names if n not in img.planes]
    if missing:
        raise FormatError(f"{img.path}: missing channels {', '.join(missing)}")


def read_stokes_exr(path: PathLike) -> StokesExr:
    """Read a Stokes EXR: ``stokes`` ``(C, 3, H, W)`` float32, other channels in ``extra``."""
    img = read_exr(path)
    c = _n_colours(img, "S0")
    names = stokes_channels(c)
    _require(img, names)
    sfx = channel_suffixes(c)
    stokes = np.stack([np.stack([img.planes[f"S{k}.{s}"] for k in range(3)]) for s in sfx])
    extra = {k: v for k, v in img.planes.items() if k not in set(names)}
    return StokesExr(stokes, extra, img.metadata, img.conventions)


def read_mueller_exr(path: PathLike) -> MuellerExr:
    """Read a Mueller EXR: ``mueller`` ``(C, 3, 3, H, W)`` float32, others in ``extra``."""
    img = read_exr(path)
    c = _n_colours(img, "M00")
    names = mueller_channels(c)
    _require(img, names)
    sfx = channel_suffixes(c)
    mueller = np.stack([np.stack([np.stack([img.planes[f"M{r}{q}.{s}"] for q in range(3)])
                                  for r in range(3)]) for s in sfx])
    extra = {k: v for k, v in img.planes.items() if k not in set(names)}
    return MuellerExr(mueller, extra, img.metadata, img.conventions)
