"""Raw DoFP frames on disk: lossless 16-bit (or 8-bit) PNG, TIFF or ``.npy`` plus a JSON sidecar.

A raw frame is a single-channel integer mosaic ``(H, W)`` (one value per sensor pixel, DN) and
its :class:`polrig.sensor.frame.FrameMeta`. The sidecar sits next to the image as ``<file>.json``
(``frame.png`` -> ``frame.png.json``). Every write is atomic (temporary file in the same
folder, flush, ``fsync``, ``os.replace``), so a crash never leaves a half-written frame under
the final name. Colour (3- or 4-channel) images are refused: a DoFP raw frame has one value
per pixel.
"""

from __future__ import annotations

import io
import json
import os
import pathlib
from typing import Any

import cv2
import numpy as np

from polrig.atomic import atomic_write_bytes, atomic_write_text
from polrig.errors import FormatError
from polrig.sensor.frame import Frame, FrameMeta
from polrig.sensor.pixelformats import get_pixel_format

PathLike = str | os.PathLike
IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
RAW_SUFFIXES = IMAGE_SUFFIXES + (".npy",)


def sidecar_path(path: PathLike) -> pathlib.Path:
    """Path of the JSON metadata sidecar of a raw frame file (``<file>.json``)."""
    p = pathlib.Path(path)
    return p.with_name(p.name + ".json")


def encode_mosaic(raw: np.ndarray, suffix: str) -> bytes:
    """Bytes of a single-channel integer mosaic in the file format named by ``suffix``."""
    raw = np.asarray(raw)
    check_mosaic(raw, "mosaic")
    suffix = suffix.lower()
    if suffix == ".npy":
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(raw), allow_pickle=False)
        return buf.getvalue()
    if suffix not in IMAGE_SUFFIXES:
        raise FormatError(f"cannot write a raw frame as {suffix!r}; use one of "
                          f"{', '.join(RAW_SUFFIXES)}")
    ok, enc = cv2.imencode(suffix, np.ascontiguousarray(raw))
    if not ok:  # pragma: no cover - OpenCV encodes every uint8/uint16 mono image
        raise FormatError(f"OpenCV could not encode a {raw.dtype} mosaic as {suffix}")
    return enc.tobytes()


def check_mosaic(raw: np.ndarray, what: str) -> None:
    """Raise :class:`FormatError` unless ``raw`` is a 2-D uint8/uint16 mosaic."""
    if raw.ndim != 2:
        raise FormatError(f"{what}: a raw DoFP frame has one channel, got an array of shape "
                          f"{raw.shape} (colour or multi-channel image?)")
    if raw.dtype not in (np.uint8, np.uint16):
        raise FormatError(f"{what}: raw frames are uint8 or uint16, got {raw.dtype}")


def write_raw(path: PathLike, frame: Frame) -> pathlib.Path:
    """Write ``frame.raw`` losslessly (``.png``, ``.tif``/``.tiff`` or ``.npy``, chosen by the
    suffix of ``path``) and its metadata as the JSON sidecar, both atomically. Returns the
    sidecar path."""
    path = pathlib.Path(path)
    data = encode_mosaic(frame.raw, path.suffix)
    side = sidecar_path(path)
    atomic_write_bytes(path, data)
    atomic_write_text(side, json.dumps(frame.meta.to_json(), indent=1, sort_keys=True))
    return side


def read_mosaic(path: PathLike) -> np.ndarray:
    """Read a raw mosaic ``(H, W)`` uint8/uint16 from a PNG, TIFF or ``.npy`` file, unchanged.

    Raises :class:`FormatError` for colour images, other dtypes, unreadable files.
    """
    path = pathlib.Path(path)
    check_input_file(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise FormatError(f"{path}: not a readable .npy array ({exc})") from None
    elif suffix in IMAGE_SUFFIXES:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise FormatError(f"{path}: not a readable {suffix[1:].upper()} image")
    else:
        raise FormatError(f"{path}: unsupported raw file type {suffix!r}; use one of "
                          f"{', '.join(RAW_SUFFIXES)}")
    check_mosaic(raw, str(path))
    return raw


def check_input_file(path: PathLike) -> None:
    """:class:`FileNotFoundError` if ``path`` does not exist, :class:`FormatError` if it is a
    folder or another non-file (both one line naming ``path``)."""
    p = pathlib.Path(path)
    if p.is_file():
        return
    if p.is_dir():
        raise FormatError(f"{p}: is a directory, not a file")
    if p.exists():
        raise FormatError(f"{p}: not a regular file")
    raise FileNotFoundError(f"{p}: no such file")


def check_bit_depth(raw: np.ndarray, bit_depth: int, what: str, *,
                    pixel_format: str | None = None, label: str = "bit_depth",
                    pixel_format_label: str = "pixel_format", exact_dtype: bool = True) -> None:
    """:class:`FormatError` unless the mosaic ``raw`` can be ``bit_depth``-bit data (and, when
    ``pixel_format`` names a known mosaic format, data of that format): no value may exceed
    ``2**bit_depth - 1``, ``uint8`` cannot hold more than 8 bits, and with ``exact_dtype``
    (what polrig's own frames obey, :mod:`polrig.sensor.pixelformats`) 8-bit data comes as ``uint8``
    and wider data as ``uint16``. ``what`` names the file; ``label`` and
    ``pixel_format_label`` say where the claims came from (``"bit_depth in f.png.json"``,
    ``"--bit-depth"``)."""

    dtype = np.dtype(raw.dtype)
    if pixel_format is not None:
        try:
            fmt = get_pixel_format(pixel_format)
        except FormatError:
            fmt = None  # a name polrig cannot decode: nothing to compare the file with
        if fmt is not None and fmt.values_per_pixel == 1 and fmt.dtype != dtype:
            raise FormatError(f"{what}: the file holds {dtype} data, but {pixel_format_label} "
                              f"is {pixel_format!r} ({fmt.dtype} data)")
    bits = int(bit_depth)
    if not 1 <= bits <= 16:
        raise FormatError(f"{what}: {label} must be 1..16 bits, got {bit_depth}")
    need = np.dtype(np.uint8 if bits <= 8 else np.uint16)
    if dtype != need and (exact_dtype or dtype.itemsize < need.itemsize):
        raise FormatError(f"{what}: the file holds {dtype} data, but {label} is {bits} "
                          f"({need} data)")
    top = 2 ** bits - 1
    peak = int(raw.max()) if raw.size else 0
    if peak > top:
        raise FormatError(f"{what}: the file has values up to {peak}, but {label} is {bits} "
                          f"(values up to {top})")


#: Mosaic layout assumed for a raw frame with neither a sidecar nor an explicit layout (mono IMX250MZR).
DEFAULT_LAYOUT = "imx250mzr"


def assumed_layout_note(path: PathLike, layout: str | None) -> str | None:
    """The line a command prints when it must guess a frame's mosaic layout: ``None`` when
    ``layout`` is given or ``path`` has a sidecar, else a note naming :data:`DEFAULT_LAYOUT`
    and the ``--layout`` flag (a colour frame read as mono, or the reverse, demosaics to
    nonsense without any error)."""
    if layout is not None or sidecar_path(path).is_file():
        return None
    return (f"{path} has no sidecar; assuming the {DEFAULT_LAYOUT} mosaic (mono); "
            f"pass --layout (e.g. imx250myr for the colour sensor) if that is wrong")


def read_raw(path: PathLike, *, layout: str = DEFAULT_LAYOUT, **meta_defaults: Any) -> Frame:
    """Read a raw frame and its sidecar metadata.

    Without a sidecar the metadata is synthesised: ``layout`` (default :data:`DEFAULT_LAYOUT`), the
    bit depth of the dtype, ``Mono8``/``Mono16`` pixel format, zero exposure/gain/timestamp;
    ``meta_defaults`` override those fields. A sidecar that is not valid metadata, or that
    contradicts the file (a ``bit_depth``/``pixel_format`` whose dtype or range the data
    cannot have, :func:`check_bit_depth`), raises :class:`FormatError`.
    """
    raw = read_mosaic(path)
    side = sidecar_path(path)
    if side.is_file():
        try:
            doc = json.loads(side.read_text("utf-8"))
        except (ValueError, OSError) as exc:
            raise FormatError(f"{side}: not valid frame metadata JSON ({exc})") from None
        meta = FrameMeta.from_json(doc, source=side)  # FormatError naming the file and key
        check_bit_depth(raw, meta.bit_depth, str(path), pixel_format=meta.pixel_format,
                        label=f"bit_depth in {side.name}",
                        pixel_format_label=f"pixel_format in {side.name}")
    else:
        bits = 8 if raw.dtype == np.uint8 else 16
        fields: dict[str, Any] = dict(frame_id=0, timestamp_s=0.0, exposure_us=0.0, gain_db=0.0,
                                      pixel_format=f"Mono{bits}", layout=layout, bit_depth=bits,
                                      host_timestamp=True)
        fields.update(meta_defaults)
        meta = FrameMeta(**fields)
    return Frame(raw=raw, meta=meta)
