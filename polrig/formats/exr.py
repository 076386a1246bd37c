"""OpenEXR files of Stokes and Mueller images, with polrig metadata in the header.

Channel names follow ``docs/conventions.md`` (Mitsuba 3's ``stokes`` integrator naming):
Stokes ``S{k}.{R,G,B}`` (mono ``S{k}.Y``), Mueller ``M{row}{col}.{R,G,B}`` (mono ``.Y``), all
float32, one scan-line part, ZIP compression by default (lossless: a float32 round trip is
bit-exact, NaN payloads included; ``compression="none"`` writes faster and larger files,
``"piz"`` is OpenEXR's wavelet coder). Any number of extra ``(H, W)`` planes can ride along
under their own channel names (``mask``, ``dolp.R``, ``sigma.M00.R``, ...);
:func:`colour_planes` names the planes of a ``(C, H, W)`` array. Boolean planes are stored as
float32 0/1; a float16 plane is stored as an OpenEXR ``HALF`` channel (the readers return
every channel as float32 either way).

A reconstruction's planes (:func:`result_planes`, written by :func:`write_result_exr`, the one
writer of result files): the Mueller channels always; ``sigma``,
``sigma_noise``, ``mask`` and ``residual`` by choice (:data:`RESULT_PLANES`), the uncertainty
planes in float32 or half precision (``uncertainty="half"``: 11 significant bits, ample for a
standard deviation; values above 65504 become ``inf``). Bytes per full-sensor colour pose:
``benchmarks/bench_pose.py``.

Header attributes: ``polrig:conventions`` (:data:`polrig.optics.conventions.CONVENTIONS_VERSION`),
``polrig:kind`` (``"stokes"`` or ``"mueller"``) and one string attribute ``polrig:<key>`` per
metadata entry holding its JSON encoding (incident state, calibration id, capture info, ...).

Written with the OpenEXR 3.x Python bindings (``OpenEXR.File(header, channels).write``;
reading ``OpenEXR.File(path, separate_channels=True)``; see the OpenEXR "Python bindings"
documentation, openexr.com). OpenEXR compresses and decompresses a file's line blocks on
its process-wide thread pool; polrig sizes that pool to the CPUs this process may use
(:func:`use_all_cores`, called by every reader and writer here) unless the application has
already sized it (about 2x faster ZIP writes and reads of a full-sensor result on 2 cores).
:class:`MuellerRows` reads a Mueller file a band of scan lines at a time (OpenEXR's classic
``InputFile`` API with ``scanLine1``/``scanLine2``, which the 3.x bindings keep), so that a
full-sensor truth is scored without ever being whole in memory. Writes are atomic (temporary file in the same folder, fsync,
``os.replace``); a write that fails (full disk, read-only folder) raises :class:`OSError` with
one line naming the file and leaves no temporary file behind. Unreadable, truncated, non-EXR files and missing channels raise
:class:`polrig.errors.FormatError` with one line naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import pathlib
from typing import Any, Collection, Mapping, Protocol, Sequence

import numpy as np
import OpenEXR

from polrig.atomic import fsync_folder, temporary_sibling, write_error
from polrig.choices import OPTIONAL_PLANES, PLANE_GROUPS, RESULT_PLANES
from polrig.errors import FormatError
from polrig.formats.rawio import check_input_file
from polrig.optics.conventions import CONVENTIONS_VERSION, MONO, RGB

PathLike = str | os.PathLike
_PREFIX = "polrig:"

#: Compression choices of :func:`write_exr` (OpenEXR's names, lower case).
COMPRESSIONS = {"zip": OpenEXR.ZIP_COMPRESSION, "piz": OpenEXR.PIZ_COMPRESSION,
                "none": OpenEXR.NO_COMPRESSION}
#: Precision choices of the uncertainty planes (``sigma``, ``sigma_noise``, ``residual``).
UNCERTAINTY_PRECISIONS = {"float": np.float32, "half": np.float16}


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


def element_stack(prefix: str, planes: Mapping[str, np.ndarray], n_colours: int
                  ) -> np.ndarray | None:
    """The inverse of :func:`element_planes`: ``(C, 3, 3, H, W)`` float32 of the
    ``prefix.M{r}{c}.{colour}`` planes, or None when any of them is missing."""
    names = [[[f"{prefix}.M{r}{c}.{s}" for c in range(3)] for r in range(3)]
             for s in channel_suffixes(n_colours)]
    if any(n not in planes for per in names for row in per for n in row):
        return None
    return np.stack([np.stack([np.stack([np.asarray(planes[n], np.float32) for n in row])
                               for row in per]) for per in names])


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


def use_all_cores() -> None:
    """Size OpenEXR's process-wide thread pool to this process's CPUs (its affinity mask),
    unless it already has threads (the application's choice wins)."""
    if OpenEXR.global_thread_count() == 0:
        OpenEXR.set_global_thread_count(len(os.sched_getaffinity(0)) if hasattr(
            os, "sched_getaffinity") else (os.cpu_count() or 1))


# -- writing ---------------------------------------------------------------------------------
def write_exr(path: PathLike, planes: Mapping[str, np.ndarray], *, kind: str | None = None,
              metadata: Mapping[str, Any] | None = None,
              compression: str = "zip") -> pathlib.Path:
    """Write ``(H, W)`` planes as float32 channels (float16 planes as ``HALF`` channels) plus
    polrig header metadata, atomically. ``compression``: one of :data:`COMPRESSIONS`."""
    path = pathlib.Path(path)
    if not planes:
        raise ValueError("an EXR file needs at least one channel")
    if compression not in COMPRESSIONS:
        raise ValueError(f"unknown EXR compression {compression!r}; use one of "
                         f"{', '.join(COMPRESSIONS)}")
    chans: dict[str, np.ndarray] = {}
    shape = None
    for name, p in planes.items():
        a = np.asarray(p)
        if a.dtype == bool:
            a = a.astype(np.float32)
        a = np.ascontiguousarray(a, dtype=np.float16 if a.dtype == np.float16 else np.float32)
        if a.ndim != 2:
            raise ValueError(f"channel {name!r}: planes must be 2-D, got shape {a.shape}")
        if shape is None:
            shape = a.shape
        elif a.shape != shape:
            raise ValueError(f"channel {name!r} has shape {a.shape}, others {shape}")
        chans[str(name)] = a
    header: dict[str, Any] = {"compression": COMPRESSIONS[compression],
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
    use_all_cores()
    tmp = str(temporary_sibling(path))
    try:
        try:
            OpenEXR.File(header, chans).write(tmp)
        except RuntimeError as exc:  # OpenEXR reports I/O failures (full disk, ...) this way
            reason = _openexr_reason(exc, tmp)
            err = OSError(f"{path}: cannot write the OpenEXR file ({reason})")
            err.errno = _ERRNO_OF_REASON.get(reason)  # a full disk stays ENOSPC
            raise err from None
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and tmp in str(exc):
            raise write_error(path, exc) from None  # name the user's file, not the temporary one
        raise
    fsync_folder(path.parent)  # the rename too, as polrig.atomic's writes
    return path


#: The operating system's error texts (``os.strerror``) -> their ``errno``: OpenEXR's error
#: names the reason in words only.
_ERRNO_OF_REASON = {os.strerror(e): e for e in errno.errorcode}


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
                      metadata: Mapping[str, Any] | None = None,
                      compression: str = "zip") -> pathlib.Path:
    """Write Mueller images ``(C, 3, 3, H, W)`` as ``M{row}{col}.{R,G,B|Y}`` plus ``extra``
    (e.g. :func:`result_planes`).

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
    return write_exr(path, planes, kind="mueller", metadata=metadata, compression=compression)


class ResultArrays(Protocol):
    """What :func:`result_planes` and :func:`write_result_exr` read of a reconstruction (the
    reference solve's :class:`polrig.solve.reference.ReferenceResult` or a single-shot
    :class:`polrig.app.single_shot.SingleShotResult`): ``mueller``, ``sigma`` and ``sigma_noise``
    ``(C, 3, 3, H, W)``, ``mask`` (reason bits of :func:`polrig.solve.reference.reason_names`,
    0 = valid) and ``residual`` ``(C, H, W)``."""

    mueller: np.ndarray
    sigma: np.ndarray
    sigma_noise: np.ndarray
    mask: np.ndarray
    residual: np.ndarray


def result_planes(result: ResultArrays, *, planes: Sequence[str] = RESULT_PLANES,
                  uncertainty: str = "float") -> dict[str, np.ndarray]:
    """The extra planes of a reconstruction's Mueller EXR (the Mueller channels themselves go
    through :func:`write_mueller_exr`): of the groups in ``planes`` (:data:`RESULT_PLANES`;
    ``"mueller"`` may be named and is always written), ``sigma.M{rc}.{colour}`` and
    ``sigma_noise.M{rc}.{colour}`` (standard deviations), ``mask.{colour}`` (reason bits) and
    ``residual.{colour}`` (chi^2 per dof). ``uncertainty``: ``"float"`` (float32) or ``"half"``
    (float16 ``sigma``, ``sigma_noise``, ``residual`` and ``mask``; the reason bits are small
    integers, exact in half precision). No copy is made of planes already in that precision.
    The :data:`OPTIONAL_PLANES` groups may be named; their method writes them (``extra``).
    """
    unknown = [p for p in planes if p not in PLANE_GROUPS]
    if unknown:
        raise ValueError(f"unknown EXR plane group(s) {', '.join(map(repr, unknown))}; choose "
                         f"from {', '.join(PLANE_GROUPS)}")
    if uncertainty not in UNCERTAINTY_PRECISIONS:
        raise ValueError(f"unknown uncertainty precision {uncertainty!r}; use "
                         f"{' or '.join(UNCERTAINTY_PRECISIONS)}")
    dtype = UNCERTAINTY_PRECISIONS[uncertainty]
    as_dtype = lambda a: np.asarray(a).astype(dtype, copy=False)  # noqa: E731
    out: dict[str, np.ndarray] = {}
    with np.errstate(over="ignore"):  # a sigma above the half range is inf: unbounded
        if "sigma" in planes:
            out.update(element_planes("sigma", as_dtype(result.sigma)))
        if "sigma_noise" in planes:
            out.update(element_planes("sigma_noise", as_dtype(result.sigma_noise)))
        if "mask" in planes:
            out.update(colour_planes("mask", as_dtype(result.mask)))
        if "residual" in planes:
            out.update(colour_planes("residual", as_dtype(result.residual)))
    return out


def write_result_exr(path: PathLike, result: ResultArrays, *, planes: Sequence[str] = RESULT_PLANES,
                     uncertainty: str = "float", compression: str = "zip",
                     extra: Mapping[str, np.ndarray] | None = None,
                     metadata: Mapping[str, Any] | None = None) -> pathlib.Path:
    """The one writer of a reconstruction's Mueller EXR (a session's ``mueller.exr``, a
    ``polrig infer`` result): the Mueller channels, the plane groups ``planes`` of
    :func:`result_planes` in ``uncertainty`` precision (its ``mask.{colour}`` planes are reason
    bits, 0 = valid, whatever the method), the ``extra`` planes and the header ``metadata``,
    atomically (:func:`write_mueller_exr`)."""
    return write_mueller_exr(path, result.mueller,
                             extra={**result_planes(result, planes=planes, uncertainty=uncertainty),
                                    **(extra or {})},
                             metadata=metadata, compression=compression)


def _merge_extra(planes: dict[str, np.ndarray], extra: Mapping[str, np.ndarray] | None) -> None:
    for name, p in (extra or {}).items():
        if name in planes:
            raise ValueError(f"extra plane {name!r} clashes with an image channel")
        planes[name] = p


# -- reading ---------------------------------------------------------------------------------
def read_exr(path: PathLike) -> ExrImage:
    """Read every channel (float32 ``(H, W)``) and the polrig metadata of an EXR file."""
    path = _checked_exr(path)
    use_all_cores()
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        header = f.header()
        chans = f.channels()
        planes = {name: np.asarray(c.pixels) for name, c in chans.items()}
    except (RuntimeError, ValueError, OSError) as exc:
        raise _unreadable(path, exc) from None
    if not planes:
        raise FormatError(f"{path}: OpenEXR file has no channels")
    for name, p in planes.items():
        if p.dtype != np.float32:
            planes[name] = p.astype(np.float32)
    return ExrImage(path, planes, _metadata(path, header), header.get(_PREFIX + "kind"),
                    header.get(_PREFIX + "conventions"))


def _checked_exr(path: PathLike) -> pathlib.Path:
    """``path`` after checking that it is a readable file with OpenEXR's magic number and, for a
    single-part scan-line file, that its chunks lie within it (:func:`_truncation`): a truncated
    file is refused in one line here, before the OpenEXR library prints its own warnings."""
    path = pathlib.Path(path)
    check_input_file(path)
    with open(path, "rb") as f:
        if f.read(4) != b"\x76\x2f\x31\x01":  # OpenEXR magic number 20000630, little-endian
            raise FormatError(f"{path}: not an OpenEXR file (bad magic number)")
        problem = _truncation(f, path.stat().st_size)
    if problem:
        raise FormatError(f"{path}: unreadable or truncated OpenEXR file ({problem})")
    return path


#: Scan lines per chunk of each compression (the header's ``compression`` byte: NONE, RLE,
#: ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA, DWAB; "OpenEXR File Layout", "Line Offset Table").
_LINES_PER_CHUNK = (1, 1, 1, 16, 32, 16, 32, 32, 32, 256)


def _truncation(f, size: int) -> str | None:
    """Why a single-part scan-line OpenEXR file (``f`` open after its magic number, ``size``
    bytes) is cut short, or None: its header, then its line-offset table (one 64-bit offset per
    chunk of the data window's scan lines), then each chunk (a 32-bit line number, a 32-bit byte
    count, the data) must lie within the file. Tiled, deep and multi-part files, and headers this
    check does not know, are left to the library (None). The layout: "OpenEXR File Layout",
    https://openexr.com/en/latest/OpenEXRFileLayout.html."""
    import struct

    head = f.read(4)
    if len(head) < 4:
        return "no version field"
    if struct.unpack("<I", head)[0] & ((1 << 9) | (1 << 11) | (1 << 12)):  # tiled, deep, multi-part
        return None
    attrs = {}
    while True:
        name = _read_cstring(f)
        if name is None:
            return "its header ends early"
        if name == b"":  # the header's closing null byte
            break
        kind, count = _read_cstring(f), f.read(4)
        if kind is None or len(count) < 4:
            return "its header ends early"
        n = struct.unpack("<i", count)[0]
        value = f.read(n) if n >= 0 else b""
        if n < 0 or len(value) < n:
            return "its header ends early"
        attrs[name] = value
    window, compression = attrs.get(b"dataWindow", b""), attrs.get(b"compression", b"")
    if len(window) != 16 or len(compression) != 1 or compression[0] >= len(_LINES_PER_CHUNK):
        return None
    _, y_min, _, y_max = struct.unpack("<4i", window)
    chunks = max(0, (y_max - y_min) // _LINES_PER_CHUNK[compression[0]] + 1)
    table = f.read(8 * chunks)
    if len(table) < 8 * chunks:
        return "its line-offset table ends early"
    for (offset,) in struct.iter_unpack("<Q", table):
        f.seek(offset)
        chunk = f.read(8)
        if len(chunk) < 8 or offset + 8 + struct.unpack("<ii", chunk)[1] > size:
            return "a chunk ends beyond the file's end"
    return None


def _read_cstring(f, limit: int = 256) -> bytes | None:
    """A null-terminated string of at most ``limit`` bytes from ``f`` (without the null), or None
    where the file ends first or it is longer."""
    out = bytearray()
    while len(out) <= limit:
        c = f.read(1)
        if not c:
            return None
        if c == b"\0":
            return bytes(out)
        out += c
    return None


def _metadata(path: pathlib.Path, header: Mapping[str, Any]) -> dict[str, Any]:
    """The polrig metadata entries of a header, JSON-decoded."""
    metadata: dict[str, Any] = {}
    for key, value in header.items():
        if not key.startswith(_PREFIX) or key in (_PREFIX + "kind", _PREFIX + "conventions"):
            continue
        try:
            metadata[key[len(_PREFIX):]] = json.loads(value)
        except (TypeError, ValueError):
            raise FormatError(f"{path}: header attribute {key!r} is not JSON") from None
    return metadata


def _unreadable(path: pathlib.Path, exc: Exception, what: str = "unreadable or truncated OpenEXR file"
                ) -> FormatError:
    """The one-line error of an OpenEXR read that failed: ``PATH: WHAT (first line of exc)``."""
    msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return FormatError(f"{path}: {what} ({msg})")


def _n_colours(path: pathlib.Path, channels: Collection[str], first: str) -> int:
    """1 (mono, ``FIRST.Y``) or 3 (``FIRST.R/G/B``) colours of a file's ``channels``."""
    if all(f"{first}.{s}" in channels for s in RGB):
        return 3
    if f"{first}.Y" in channels:
        return 1
    present = sorted(channels)
    raise FormatError(f"{path}: missing channels {first}.R/G/B or {first}.Y "
                      f"(has: {', '.join(present[:12])}{' ...' if len(present) > 12 else ''})")


def _require(path: pathlib.Path, channels: Collection[str], names: list[str]) -> None:
    missing = [n for n in names if n not in channels]
    if missing:
        raise FormatError(f"{path}: missing channels {', '.join(missing)}")


def read_stokes_exr(path: PathLike) -> StokesExr:
    """Read a Stokes EXR: ``stokes`` ``(C, 3, H, W)`` float32, other channels in ``extra``."""
    return stokes_exr(read_exr(path))


def stokes_exr(img: ExrImage) -> StokesExr:
    """:func:`read_stokes_exr` of a file already read whole (:func:`read_exr`)."""
    c = _n_colours(img.path, img.planes, "S0")
    names = stokes_channels(c)
    _require(img.path, img.planes, names)
    sfx = channel_suffixes(c)
    stokes = np.stack([np.stack([img.planes[f"S{k}.{s}"] for k in range(3)]) for s in sfx])
    extra = {k: v for k, v in img.planes.items() if k not in set(names)}
    return StokesExr(stokes, extra, img.metadata, img.conventions)


def read_mueller_exr(path: PathLike) -> MuellerExr:
    """Read a Mueller EXR: ``mueller`` ``(C, 3, 3, H, W)`` float32, others in ``extra``
    (whatever optional planes the file has: ``sigma``, ``mask``, ... may be absent)."""
    return mueller_exr(read_exr(path))


def mueller_exr(img: ExrImage) -> MuellerExr:
    """:func:`read_mueller_exr` of a file already read whole (:func:`read_exr`); the Mueller
    planes are moved out of ``img.planes``, the rest become ``extra``."""
    c = _n_colours(img.path, img.planes, "M00")
    names = mueller_channels(c)
    _require(img.path, img.planes, names)
    sfx = channel_suffixes(c)
    mueller = np.empty((c, 3, 3) + img.shape, np.float32)
    for i, s in enumerate(sfx):  # moved plane by plane: no second full-size copy at once
        for r in range(3):
            for q in range(3):
                mueller[i, r, q] = img.planes.pop(f"M{r}{q}.{s}")
    return MuellerExr(mueller, img.planes, img.metadata, img.conventions)


class MuellerRows:
    """A Mueller EXR opened for reading a band of rows at a time: ``rows(r0, r1)`` is
    ``mueller[..., r0:r1, :]`` of :func:`read_mueller_exr` (``(C, 3, 3, r1 - r0, W)``
    float32, the same numbers) decoded from those scan lines only, so a full-sensor file
    (0.54 GB of float32 in colour) is never whole in memory. ``shape`` is the whole image's
    ``(C, 3, 3, H, W)``; :meth:`plane` reads one other channel whole. A context manager;
    unreadable files and missing channels raise :class:`polrig.errors.FormatError` naming
    the file, like :func:`read_mueller_exr`."""

    def __init__(self, path: PathLike) -> None:
        self.path = _checked_exr(path)
        use_all_cores()
        try:
            self._file = OpenEXR.InputFile(str(self.path))
            header = self._file.header()
        except (RuntimeError, ValueError, OSError) as exc:
            raise _unreadable(self.path, exc) from None
        try:
            self._channels = dict(header["channels"])
            box = header["dataWindow"]
            w, h = box.max.x - box.min.x + 1, box.max.y - box.min.y + 1
            self.metadata = _metadata(self.path, header)
            c = _n_colours(self.path, self._channels, "M00")
            _require(self.path, self._channels, mueller_channels(c))
        except BaseException:
            self._file.close()
            raise
        self.shape: tuple[int, int, int, int, int] = (c, 3, 3, h, w)
        #: every channel's name in the file (its header: no pixel read)
        self.channels: tuple[str, ...] = tuple(self._channels)
        self._names = [f"M{r}{q}.{s}" for s in channel_suffixes(c) for r in range(3)
                       for q in range(3)]

    def _decode(self, raw: bytes, name: str, rows: int) -> np.ndarray:
        kind = str(self._channels[name].type)
        dtype = np.float16 if "HALF" in kind else np.uint32 if "UINT" in kind else np.float32
        return np.frombuffer(raw, dtype).reshape(rows, self.shape[-1]).astype(np.float32,
                                                                             copy=False)

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` (clipped to the image) of every Mueller element, ``(C, 3, 3, n, W)``."""
        h = self.shape[3]
        r0, r1 = max(0, int(r0)), min(h, int(r1))
        out = np.empty(self.shape[:3] + (max(0, r1 - r0), self.shape[4]), np.float32)
        if r1 <= r0:
            return out
        try:
            raws = self._file.channels(self._names, scanLine1=r0, scanLine2=r1 - 1)
        except (RuntimeError, ValueError, OSError) as exc:
            raise _unreadable(self.path, exc, f"unreadable rows {r0}-{r1 - 1}") from None
        flat = out.reshape((-1,) + out.shape[3:])
        for k, (raw, name) in enumerate(zip(raws, self._names)):
            flat[k] = self._decode(raw, name, r1 - r0)
        return out

    def plane(self, name: str) -> np.ndarray | None:
        """Channel ``name`` whole ``(H, W)`` float32, or None if the file has none."""
        if name not in self._channels:
            return None
        try:
            raw = self._file.channel(name)
        except (RuntimeError, ValueError, OSError) as exc:
            raise _unreadable(self.path, exc, f"unreadable channel {name}") from None
        return self._decode(raw, name, self.shape[3]).copy()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "MuellerRows":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
