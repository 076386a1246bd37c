"""OME-Zarr (OME-NGFF) and OME-TIFF writers of labelled image stacks: what napari and Fiji open.

The unit of writing is an :class:`OmeImage`: one quantity (``mueller``, ``sigma``, ``mask``, ...)
as a ``(T, C, Y, X)`` stack (``T`` the capture, ``C`` labelled channels) or a ``(C, Y, X)``
one, with its channel names and display colours. A file holds several images, all of the
same ``(Y, X)`` size and the same ``T``.

**OME-Zarr** (:func:`write_ome_zarr`), OME-NGFF 0.4 on Zarr format 2 by default
(https://ngff.openmicroscopy.org/0.4/), or 0.5 on Zarr format 3 (``version="0.5"``). 0.4 is
the default because it is what the readers of Fiji (the N5/Zarr plugin, MoBIE, BigDataViewer)
and QuPath read today, and napari's ``napari-ome-zarr`` plugin reads it as well as 0.5; 0.5
needs a Zarr v3 reader. Layout, one image per quantity::

    OUT.zarr/              the first image (the Mueller stack): ``multiscales`` + ``omero`` + ``polrig``
    OUT.zarr/0             its one resolution level, chunks of one (Y, X) plane
    OUT.zarr/sigma/        each further image: an image group of its own (same axes, same scale)
    OUT.zarr/sigma/0

so that napari opened on ``OUT.zarr`` shows the Mueller elements as one layer per channel
(named ``M00.R``, ... from the ``omero`` channel labels; only ``M00.*`` visible at first) and
``OUT.zarr/sigma`` opens the standard deviations the same way. One labelled channel axis per
quantity rather than one axis per Mueller index: NGFF allows one channel axis and at most five
dimensions (``t``, ``c``, then space), and napari and Fiji label channels, not other axes.
Axes: ``t`` (type ``time``: the captures in acquisition order, no unit; their poses are in the
``polrig`` attributes), ``c`` (``channel``), ``y``, ``x`` (``space``, in ``unit`` with scale
``pixel_size`` where the pixel size is known; without a unit and with scale 1 otherwise). Every
level's ``coordinateTransformations`` is one ``scale``.

**OME-TIFF** (:func:`write_ome_tiff`), with tifffile: one OME image (series) per quantity,
axes ``TCYX`` (or ``CYX``), OME-XML ``Channel`` names and ``PhysicalSizeX``/``Y`` with their
unit; Fiji's Bio-Formats importer opens each series as a hyperstack (ImageJ's ``TZCYX`` order,
``Z`` of size 1). The attributes are the image's ``Description`` (JSON) and the sample
metadata a ``MapAnnotation`` (key-value pairs, shown by Fiji's "Show Info" and OMERO).

Both write a capture at a time: :meth:`OmeImage.block` ``(C, Y, X)`` of capture ``t``, every
image's block of one capture before the next (a session opened lazily,
:func:`polrig.app.export.dataset_images`, reads each capture's result file once and holds one
capture). An OME-Zarr takes the blocks as they come, chunk by chunk. An OME-TIFF's series
follow one another in the file, so the first image's planes are written as each capture comes
and the other images' blocks are spilled to a raw file each in a temporary folder beside the
output (removed afterwards: it needs their size in disk space once more), then read back a
plane at a time for their own series. Memory holds one capture, whatever the session's size.
Writers: ``zarr`` (>= 3) and
``tifffile``, the ``export`` extra; without them a one-line error names the extra.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import shutil
import tempfile
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from polrig.atomic import temporary_sibling
from polrig.choices import OME_UNITS

__all__ = ["NGFF_VERSIONS", "OmeImage", "write_ome_tiff", "write_ome_zarr", "channel_colour"]

#: OME-NGFF versions written, and their Zarr format.
NGFF_VERSIONS = {"0.4": 2, "0.5": 3}
#: What the writers need.
MISSING_EXTRA = "OME-Zarr and OME-TIFF export need zarr and tifffile: pip install 'polrig[export]'"
#: Display colour (hex RGB) of a channel by its colour suffix.
_COLOURS = {"R": "FF0000", "G": "00FF00", "B": "0000FF", "Y": "FFFFFF"}
#: Spatial units the writers accept (NGFF names; OME-XML symbols; defined in
#: :mod:`polrig.choices`, the command line's start-up vocabulary).
UNITS = OME_UNITS
#: Largest (Y, X) chunk edge of the OME-Zarr arrays.
CHUNK = 1024
#: Most values per plane the display windows are taken from (an even subsample beyond).
WINDOW_SAMPLES = 65536
#: OME-TIFF deflate level: 1, the fastest (float planes gain little from more; Bio-Formats reads
#: any level).
ZLIB_LEVEL = 1


def channel_colour(name: str) -> str:
    """Display colour of channel ``name`` (``"M01.G"`` -> green) as hex RGB; white if its last
    dot-separated part is no colour name."""
    return _COLOURS.get(name.rsplit(".", 1)[-1], "FFFFFF")


@dataclasses.dataclass(frozen=True)
class OmeImage:
    """One quantity to write: ``data`` ``(T, C, Y, X)`` or ``(C, Y, X)`` (numpy or dask), its
    channel names ``channels`` (``C`` of them), ``name`` (the image's name; its group in an
    OME-Zarr), ``visible`` (channel names shown at first), ``attributes`` (JSON-serialisable,
    this image's own: units, description)."""

    name: str
    data: Any
    channels: tuple[str, ...]
    visible: tuple[str, ...] = ()
    attributes: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        shape = tuple(self.data.shape)
        if len(shape) not in (3, 4):
            raise ValueError(f"image {self.name!r}: expected (T, C, Y, X) or (C, Y, X), got {shape}")
        if shape[-3] != len(self.channels):
            raise ValueError(f"image {self.name!r}: {shape[-3]} channels but "
                             f"{len(self.channels)} names")

    @property
    def axes(self) -> str:
        return "tcyx" if self.data.ndim == 4 else "cyx"

    def planes(self):
        """``((t, c), (Y, X) numpy plane)`` in storage order (``t`` is ``None`` without ``T``)."""
        if self.data.ndim == 3:
            block = np.asarray(self.data)  # one read of a lazy result
            for c in range(block.shape[0]):
                yield (None, c), block[c]
        else:
            for t in range(self.data.shape[0]):
                yield from (((t, c), p) for c, p in enumerate(self.block(t)))

    def block(self, t: int) -> np.ndarray:
        """The ``(C, Y, X)`` stack of capture ``t`` as numpy (one read of a lazy session)."""
        return np.asarray(self.data[t])


def _check(images: Sequence[OmeImage], pixel_size: tuple[float, float] | None, unit: str) -> None:
    if not images:
        raise ValueError("nothing to export: no image")
    first = images[0].data.shape
    for im in images[1:]:
        s = im.data.shape
        if s[-2:] != first[-2:] or im.data.ndim != len(first) or (len(s) == 4 and s[0] != first[0]):
            raise ValueError(f"image {im.name!r} {s} does not match {images[0].name!r} {first}")
    if len({im.name for im in images}) != len(images):
        raise ValueError("image names must differ")
    if pixel_size is not None:
        if len(pixel_size) != 2 or not all(np.isfinite(v) and v > 0 for v in pixel_size):
            raise ValueError(f"pixel size must be two positive numbers (y, x), got {pixel_size}")
        if unit not in UNITS:
            raise ValueError(f"unknown unit {unit!r}; use one of {', '.join(UNITS)}")


def _window(lo: float, hi: float) -> dict[str, float]:
    if not (np.isfinite(lo) and np.isfinite(hi)):
        lo, hi = 0.0, 1.0
    return {"min": lo, "max": hi, "start": lo, "end": hi if hi > lo else lo + 1.0}


def _libraries():
    try:
        import tifffile
        import zarr
    except ImportError:
        raise ModuleNotFoundError(MISSING_EXTRA) from None
    return zarr, tifffile


# -- OME-Zarr ------------------------------------------------------------------------------------
def write_ome_zarr(path: str | os.PathLike, images: Sequence[OmeImage], *,
                   pixel_size: tuple[float, float] | None = None, unit: str = "micrometer",
                   attributes: Mapping[str, Any] | None = None, version: str = "0.4"
                   ) -> pathlib.Path:
    """Write ``images`` as one OME-Zarr (module docstring: layout, axes, why 0.4 by default).

    ``pixel_size`` ``(y, x)`` in ``unit`` (an NGFF spatial unit name, :data:`UNITS`), or
    ``None``: unit-less pixels, scale 1. ``attributes`` (JSON-serialisable) go under the
    root's ``polrig`` key, each image's own under its group's. The store is built beside
    ``path`` and moved into place when complete; an existing Zarr store at ``path`` is
    replaced, anything else there refused (``FileExistsError``)."""
    zarr, _ = _libraries()
    if version not in NGFF_VERSIONS:
        raise ValueError(f"unknown OME-NGFF version {version!r}; use {' or '.join(NGFF_VERSIONS)}")
    _check(images, pixel_size, unit)
    out = pathlib.Path(path)
    if out.exists() and not (out / ".zgroup").is_file() and not (out / "zarr.json").is_file():
        raise FileExistsError(f"{out} exists and is not a Zarr store: not replaced")
    tmp = temporary_sibling(out)
    try:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=NGFF_VERSIONS[version])
        groups = [root if k == 0 else root.create_group(im.name) for k, im in enumerate(images)]
        arrays = [_create_array(g, im, version) for g, im in zip(groups, images)]
        windows = [_Window(len(im.channels)) for im in images]
        # capture by capture, every image: a lazy session's file is read once per capture
        for t in range(images[0].data.shape[0] if images[0].data.ndim == 4 else 1):
            for im, arr, win in zip(images, arrays, windows):
                block = im.block(t) if im.data.ndim == 4 else np.asarray(im.data)
                for c, plane in enumerate(block):  # plane by plane: zarr buffers what it is given
                    arr[(t, c) if im.data.ndim == 4 else c] = plane
                win.add(block)
        for g, im, win in zip(groups, images, windows):
            _write_metadata(g, im, win, pixel_size, unit, version)
        root.attrs.update({"polrig": json.loads(json.dumps(dict(attributes or {}), allow_nan=True,
                                                           default=str))})
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


class _Window:
    """Per channel display range (0.5 and 99.5 percentiles of the finite values, widened over
    the captures) for the ``omero`` channels' ``window``."""

    def __init__(self, n: int):
        self.lo = np.full(n, np.inf)
        self.hi = np.full(n, -np.inf)

    def add(self, block: np.ndarray) -> None:
        for c, plane in enumerate(block):
            finite = plane[np.isfinite(plane)]
            finite = finite[::max(1, finite.size // WINDOW_SAMPLES)]  # a display range: a sample will do
            if finite.size:
                a, b = np.percentile(finite, (0.5, 99.5))
                self.lo[c], self.hi[c] = min(self.lo[c], float(a)), max(self.hi[c], float(b))

    def of(self, c: int) -> dict[str, float]:
        return _window(self.lo[c], self.hi[c])


def _create_array(group, im: OmeImage, version: str):
    shape = tuple(int(s) for s in im.data.shape)
    dtype = np.dtype(im.data.dtype)
    chunks = (1,) * (len(shape) - 2) + (min(shape[-2], CHUNK), min(shape[-1], CHUNK))
    kwargs: dict[str, Any] = {"fill_value": np.nan if dtype.kind == "f" else 0}
    if NGFF_VERSIONS[version] == 2:
        kwargs["chunk_key_encoding"] = {"name": "v2", "separator": "/"}  # NGFF 0.4: "/" separator
    else:
        kwargs["dimension_names"] = list(im.axes)  # NGFF 0.5: the axes' names
    return group.create_array("0", shape=shape, chunks=chunks, dtype=dtype, **kwargs)


def _write_metadata(group, im: OmeImage, window: _Window, pixel_size, unit: str, version: str) -> None:
    space = {"type": "space"}
    if pixel_size is not None:
        space["unit"] = unit
    axes = [{"name": a, "type": {"t": "time", "c": "channel"}.get(a, "space")} | (space if a in "yx" else {})
            for a in im.axes]
    scale = [1.0] * (im.data.ndim - 2) + ([float(v) for v in pixel_size] if pixel_size else [1.0, 1.0])
    multiscale = {"name": im.name, "axes": axes,
                  "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": scale}]}]}
    omero = {"name": im.name, "rdefs": {"model": "color"},
             "channels": [{"label": name, "color": channel_colour(name), "window": window.of(c),
                           "active": (name in im.visible) if im.visible else True}
                          for c, name in enumerate(im.channels)]}
    own = json.loads(json.dumps(dict(im.attributes), allow_nan=True, default=str))
    if version == "0.4":
        multiscale["version"] = "0.4"
        omero["version"] = "0.4"
        group.attrs.update({"multiscales": [multiscale], "omero": omero, "polrig_image": own})
    else:
        group.attrs.update({"ome": {"version": "0.5", "multiscales": [multiscale], "omero": omero},
                            "polrig_image": own})


# -- OME-TIFF ------------------------------------------------------------------------------------
def write_ome_tiff(path: str | os.PathLike, images: Sequence[OmeImage], *,
                   pixel_size: tuple[float, float] | None = None, unit: str = "micrometer",
                   attributes: Mapping[str, Any] | None = None,
                   annotations: Mapping[str, str] | None = None) -> pathlib.Path:
    """Write ``images`` as one OME-TIFF (BigTIFF), one series per image, axes ``TCYX`` or
    ``CYX`` (module docstring), deflate level :data:`ZLIB_LEVEL`. ``pixel_size`` ``(y, x)`` in ``unit`` as
    :func:`write_ome_zarr` (``None``: no physical size written); ``attributes`` (JSON) each
    image's ``Description`` (with the image's own attributes under ``image``),
    ``annotations`` (strings: the sample metadata) each image's ``MapAnnotation``. Written
    atomically (temporary sibling, then renamed)."""
    _, tifffile = _libraries()
    _check(images, pixel_size, unit)
    out = pathlib.Path(path)
    tmp = temporary_sibling(out)
    common = dict(attributes or {})
    try:
        with tifffile.TiffWriter(tmp, bigtiff=True, ome=True) as tw, \
                tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.spill-") as spill, \
                contextlib.closing(_series_planes(images, pathlib.Path(spill))) as series:
            for im, planes in zip(images, series):
                meta: dict[str, Any] = {
                    "axes": im.axes.upper(), "Name": im.name,
                    "Channel": {"Name": list(im.channels)},
                    "Description": json.dumps({**common, "image": dict(im.attributes)},
                                              allow_nan=True, default=str),
                }
                if pixel_size is not None:
                    meta.update(PhysicalSizeY=float(pixel_size[0]), PhysicalSizeX=float(pixel_size[1]),
                                PhysicalSizeYUnit=UNITS[unit], PhysicalSizeXUnit=UNITS[unit])
                if annotations:
                    meta["MapAnnotation"] = {str(k): str(v) for k, v in annotations.items()}
                tw.write(planes, shape=tuple(im.data.shape),
                         dtype=np.dtype(im.data.dtype), photometric="minisblack",
                         compression="zlib", compressionargs={"level": ZLIB_LEVEL}, metadata=meta)
        os.replace(tmp, out)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise
    return out


def _series_planes(images: Sequence[OmeImage], spill: pathlib.Path) -> Iterator[Iterator[np.ndarray]]:
    """Each image's ``(Y, X)`` planes in storage order, one iterator per image, to be consumed
    in turn (an OME-TIFF's series follow one another). Stacks of several captures are read a
    capture at a time, every image's block of it together (a lazy session's result file once
    per capture, :meth:`OmeImage.block`): while the first image's planes are written, the
    other images' blocks of the same capture go to a raw file each in folder ``spill``, read
    back a plane at a time for their own series; memory holds one capture, never the session."""
    first = images[0]
    if first.data.ndim == 3 or first.data.shape[0] == 1 or len(images) == 1:
        yield from (((p for _, p in im.planes())) for im in images)
        return
    files = [open(spill / f"{k}.raw", "w+b") for k in range(1, len(images))]
    try:
        def first_series() -> Iterator[np.ndarray]:
            for t in range(first.data.shape[0]):
                block = first.block(t)
                for im, f in zip(images[1:], files):
                    np.ascontiguousarray(im.block(t)).tofile(f)
                yield from block

        def spilled(im: OmeImage, f) -> Iterator[np.ndarray]:
            f.flush()
            f.seek(0)
            count = int(np.prod(im.data.shape[-2:]))
            for _ in range(im.data.shape[0] * im.data.shape[1]):
                yield np.fromfile(f, np.dtype(im.data.dtype), count).reshape(im.data.shape[-2:])

        yield first_series()
        for im, f in zip(images[1:], files):
            yield spilled(im, f)
    finally:
        for f in files:
            f.close()
