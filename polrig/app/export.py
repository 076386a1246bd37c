"""Export a session or a result EXR to OME-Zarr or OME-TIFF (issue 34, item 6): the files napari
and Fiji open. ``polrig export`` and :func:`export` (``polrig.export``) are this one route.

The source is read through the Python API's openers (:func:`polrig.app.dataset.open_session`,
:func:`~polrig.app.dataset.open_result`: lazily, one capture at a time), and each of its
variables becomes one image (:class:`polrig.formats.ome.OmeImage`) with a labelled channel axis:

===============  ==========================  ========================================
image            channels                    from
===============  ==========================  ========================================
``mueller``      ``M{i}{j}.{colour}``        the 3x3 Mueller block, element-major
``sigma``        ``sigma.M{i}{j}.{colour}``  its standard deviation (noise + calibration)
``sigma_noise``  ``sigma_noise.M{i}{j}...``  its standard deviation from the noise alone
``mask``         ``mask.{colour}``           reason bits (uint8), 0 = valid
``residual``     ``residual.{colour}``       chi^2 per degree of freedom
===============  ==========================  ========================================

(only the variables the source holds). A session's captures are the ``T`` axis, in capture
order; their poses and folder names are in the attributes (``captures``). The attributes are
the dataset's (sample metadata, plan, rig, calibration id, ... :mod:`polrig.app.dataset`), and
the sample metadata (:func:`polrig.app.manifest.sample_fields`) also an OME-TIFF
``MapAnnotation``.

Pixel size: the output pixel's size in the object, which needs the distance to the sample.
It is the caller's ``pixel_size`` (e.g. a scale bar's measure), or, from the calibration set the
source was captured with (``calibration``: its ``intrinsics`` and ``turntable`` steps),
:func:`pixel_size_at_turntable_axis`: the size at the depth where the turntable axis crosses
the optical axis (closest approach), ``depth / f`` times the output grid's binning of sensor
pixels (the layout period for a ``superpixel`` result, 1 otherwise). Without either the export
states unit-less pixels (scale 1, no unit; ``attributes["pixel_size"]`` says so).
"""

from __future__ import annotations

import dataclasses
import errno
import os
import pathlib
from typing import Any

import numpy as np

from polrig.app.manifest import sample_fields
from polrig.atomic import write_error
from polrig.formats.ome import NGFF_VERSIONS, UNITS, OmeImage, write_ome_tiff, write_ome_zarr

__all__ = ["FORMATS", "export", "dataset_images"]

#: Export formats and their writers' file-name endings.
FORMATS = {"ome-zarr": ".zarr", "ome-tiff": ".ome.tif"}
_ELEMENT = ("mueller", "sigma", "sigma_noise")
_ORDER = ("mueller", "sigma", "sigma_noise", "mask", "residual")


def _channel_names(name: str, ds) -> tuple[str, ...]:
    colours = [str(c) for c in ds.channel.values]
    if name in _ELEMENT:
        prefix = "" if name == "mueller" else f"{name}."
        return tuple(f"{prefix}M{i}{j}.{s}" for i in range(3) for j in range(3) for s in colours)
    return tuple(f"{name}.{s}" for s in colours)


class _Captures:
    """A dataset's variables as the images' ``(C, Y, X)`` blocks, a capture at a time:
    ``blocks(t)`` computes every variable of capture ``t`` together (one read of its result
    file, shared through the dataset's one dask chunk per capture; ``t`` is ``None`` for a
    dataset without captures) and keeps that capture only, so that memory holds one capture's
    planes (and one variable's reordered copy while it is made) whatever the session's size."""

    def __init__(self, variables: dict[str, Any]):
        self._variables = variables  # dask (T, ..., y, x) or (..., y, x), image-major dims
        self._t: object = object()
        self._blocks: dict[str, np.ndarray] = {}

    def blocks(self, t: int | None) -> dict[str, np.ndarray]:
        if t != self._t:
            import dask

            self._blocks, self._t = {}, None  # the previous capture goes before the next comes
            names = list(self._variables)
            computed = dict(zip(names, dask.compute(*(_one_chunk(self._variables[n] if t is None
                                                                 else self._variables[n][t])
                                                      for n in names))))
            for n in names:  # (..., y, x) -> (C, y, x), C-contiguous; one variable copied at a time
                a = computed.pop(n)
                self._blocks[n] = np.ascontiguousarray(a).reshape((-1,) + a.shape[-2:])
                del a
            self._t = t
        return self._blocks


def _one_chunk(array):
    """A one-chunk dask array as the delayed value of that chunk: computed, it is the chunk
    itself, not the copy that computing the array makes (dask copies a single chunk), and, the
    graph left unoptimised, the chunks of one capture share its one read (an optimised graph
    per delayed value would inline the read into each)."""
    (chunk,) = array.to_delayed(optimize_graph=False).ravel()
    return chunk


class _OneCaptureAtATime:
    """A session variable as ``(T, C, Y, X)`` whose ``[t]`` is its block of capture ``t``
    (:class:`_Captures`: every variable of that capture read together)."""

    def __init__(self, captures: _Captures, name: str, shape: tuple[int, ...], dtype):
        self._captures, self._name = captures, name
        self.shape, self.dtype, self.ndim = shape, np.dtype(dtype), len(shape)

    def __getitem__(self, t: int) -> np.ndarray:
        return self._captures.blocks(int(t))[self._name]


def dataset_images(ds) -> list[OmeImage]:
    """The images of an opened session or result (module docstring's table): each variable's
    ``(capture, channel, i, j, y, x)`` (or ``(capture, channel, y, x)``) as ``(T, C, Y, X)``,
    element-major channels (``M00.R``, ``M00.G``, ``M00.B``, ``M01.R``, ...); without a
    ``capture`` dim ``(C, Y, X)``, read at once (one result file); a session's are read a
    capture at a time, all its variables together (:class:`_Captures`)."""
    labels, variables = {}, {}
    for name in _ORDER:
        if name not in ds:
            continue
        var = ds[name]
        lead = ("capture",) if "capture" in var.dims else ()
        channels = _channel_names(name, ds)
        if name in _ELEMENT:  # (..., i, j, channel, y, x) -> (..., 9 C, y, x), element-major
            variables[name] = var.transpose(*lead, "i", "j", "channel", "y", "x").data
            visible = tuple(c for c in channels if c.split(".")[-2] == "M00")
        else:
            variables[name] = var.transpose(*lead, "channel", "y", "x").data
            visible = channels
        labels[name] = (channels, visible, dict(var.attrs))
    captures = _Captures(variables)
    if "capture" not in ds.dims:  # one result: one read
        return [OmeImage(n, b, *labels[n]) for n, b in captures.blocks(None).items()]
    images = []
    for name, v in variables.items():  # each capture's file read once for all its variables
        shape = (v.shape[0], len(labels[name][0])) + v.shape[-2:]
        images.append(OmeImage(name, _OneCaptureAtATime(captures, name, shape, v.dtype), *labels[name]))
    return images


def pixel_size_at_turntable_axis(calibration: str | os.PathLike, attrs: dict[str, Any]
                                 ) -> tuple[float, float]:
    """``(y, x)`` size in micrometres of an output pixel of the source with attributes
    ``attrs`` (an opened session's or result's), in the object at the turntable axis, from the
    calibration set in folder ``calibration``: ``depth / (fy, fx) * binning`` with ``depth`` the
    camera-frame Z of the axis point closest to the optical axis (distortion ignored).
    ``ValueError`` (one line) for a set without the ``intrinsics`` or ``turntable`` step, of
    another calibration id than the source's, or an axis along the optical axis."""
    import numpy as np

    from polrig.calibration import calset
    from polrig.sensor.layouts import get_layout

    cs = calset.load(calibration)
    missing = [step for step in ("intrinsics", "turntable") if not cs.has(step)]
    if missing:
        raise ValueError(f"calibration set {calibration}: no {' or '.join(missing)} step for a pixel size")
    own = attrs.get("calibration_id")
    if own is not None and own != cs.id:
        raise ValueError(f"calibration set {calibration} is {cs.id!r}; the source was captured "
                         f"with {own!r}")
    k = cs.intrinsics["K"]
    tt = cs.turntable_axis
    a = tt["axis_cam"] / np.linalg.norm(tt["axis_cam"])
    p0 = tt["point_cam_m"]
    ez = np.array([0.0, 0.0, 1.0])
    # closest approach of the lines p0 + s a and t ez: solve for s, t
    b = float(a @ ez)
    if 1.0 - b * b < 1e-9:
        raise ValueError(f"calibration set {calibration}: the turntable axis runs along the optical axis")
    d = p0
    s_ = (b * float(ez @ d) - float(a @ d)) / (1.0 - b * b)
    depth = float((p0 + s_ * a)[2])
    plan = attrs.get("plan") or {}
    demosaic = plan.get("demosaic", attrs.get("demosaic"))
    resolution = plan.get("resolution", attrs.get("resolution", "superpixel"))
    # the result header's layout, else the sensor the set was calibrated on (the frames' own)
    layout = attrs.get("layout") or cs.params.get("camera", {}).get("layout")
    binned = demosaic == "superpixel" and resolution != "full"
    if binned and not layout:
        raise ValueError(f"calibration set {calibration}: no sensor layout to size a superpixel by")
    period = get_layout(layout).period if binned else (1, 1)
    return (depth / float(k[1, 1]) * period[0] * 1e6, depth / float(k[0, 0]) * period[1] * 1e6)


def export(source: str | os.PathLike, out: str | os.PathLike, format: str = "ome-zarr", *,
           pixel_size: tuple[float, float] | None = None, unit: str = "micrometer",
           revision: str | None = None, version: str = "0.4",
           calibration: str | os.PathLike | None = None) -> pathlib.Path:
    """Export the session folder or result EXR ``source`` to ``out`` in ``format``
    (:data:`FORMATS`: ``"ome-zarr"``, OME-NGFF ``version`` 0.4 (default) or 0.5; ``"ome-tiff"``).

    ``pixel_size`` ``(y, x)`` in ``unit`` (:data:`polrig.formats.ome.UNITS`), ``None`` for
    unit-less pixels (module docstring); ``calibration``: the calibration set folder the
    pixel size is computed from instead (:func:`pixel_size_at_turntable_axis`, micrometres);
    ``revision`` a session revision's results. Returns
    the written path. Raises ``ValueError`` for an unknown format, version or unit, the
    openers' errors (:class:`polrig.errors.FormatError`, ``KeyError`` for an unknown
    revision), and an ``OSError`` naming ``out`` where the disk is full."""
    from polrig.app.dataset import open_result, open_session

    if format not in FORMATS:
        raise ValueError(f"unknown export format {format!r}; use {' or '.join(FORMATS)}")
    if version not in NGFF_VERSIONS:
        raise ValueError(f"unknown OME-NGFF version {version!r}; use {' or '.join(NGFF_VERSIONS)}")
    if unit not in UNITS:
        raise ValueError(f"unknown unit {unit!r}; use one of {', '.join(UNITS)}")
    src = pathlib.Path(source)
    ds = open_session(src, revision=revision) if src.is_dir() else open_result(src)
    if not ds.data_vars:
        raise ValueError(f"{src}: no capture has a result to export")
    if calibration is not None:
        if pixel_size is not None:
            raise ValueError("give a pixel size or a calibration set, not both")
        pixel_size, unit = pixel_size_at_turntable_axis(calibration, dict(ds.attrs)), "micrometer"
    attrs = _attributes(ds, pixel_size, unit)
    if calibration is not None:
        attrs["pixel_size"]["from"] = (f"calibration set {calibration}: at the turntable axis "
                                       "(its closest approach to the optical axis)")
    images = dataset_images(ds)
    try:
        if format == "ome-zarr":
            return write_ome_zarr(out, images, pixel_size=pixel_size, unit=unit, attributes=attrs,
                                  version=version)
        return write_ome_tiff(out, images, pixel_size=pixel_size, unit=unit, attributes=attrs,
                              annotations=sample_fields(ds.attrs))
    except OSError as exc:
        if exc.errno in NO_ROOM:  # tifffile's and zarr's own lines name no file, or a temporary
            raise write_error(out, exc) from None
        raise


#: The errors of a write that ran out of room (a full disk, a file-size limit, a quota): the
#: error then names the output the user asked for.
NO_ROOM = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}


def _attributes(ds, pixel_size, unit: str) -> dict[str, Any]:
    attrs: dict[str, Any] = dict(ds.attrs)
    attrs["sample_metadata"] = sample_fields(ds.attrs)
    if "capture" in ds.dims:
        attrs["captures"] = [{"capture_id": str(i), "pose_deg": float(p)}
                             for i, p in zip(ds.capture_id.values, ds.capture.values)]
        attrs["t_axis"] = "the captures, in capture order (not a time: see captures' pose_deg)"
    attrs["pixel_size"] = ({"y": pixel_size[0], "x": pixel_size[1], "unit": unit} if pixel_size
                           else "not known: unit-less pixels (scale 1)")
    return attrs

