"""Sessions and result files as lazily loaded ``xarray.Dataset`` s: the Python API's openers
(issue 34, item 5; ``docs/api.md``), re-exported as ``polrig.open_session`` and
``polrig.open_result``.

:func:`open_session` reads the manifest (read only, no lock: like ``polrig info`` it may run
while a capture writes the session) and each result's EXR header, never its pixels: every
capture's planes are one dask chunk, a :func:`dask.delayed` call of the EXR reader
(:func:`polrig.formats.exr.read_mueller_exr`) that reads the whole file once when any of its
variables is computed. The ``mueller`` variable has dims ``(capture, channel, i, j, y, x)``
(``i``, ``j``: the Mueller row and column; ``channel``: the colour names ``R``, ``G``, ``B`` or
``Y``; ``capture``: the turntable pose in degrees, with the capture folder names as the
second coordinate ``capture_id``); ``sigma`` and ``sigma_noise`` have the same dims,
``mask`` (reason bits, 0 = valid) and ``residual`` (chi^2 per dof) drop ``i`` and ``j``; a
variable is absent where the plan's ``exr_planes`` left its planes out. The metadata are
attributes, every value JSON-serialisable: the sample metadata (``sample``, ``operator``,
``note`` and the user keys, flat, :class:`polrig.app.manifest.SampleMetadata`), the plan, the
rig, the calibration id, the session's status and schema version.

Why here, in the app layer: a session is the app layer's (its manifest, its migrations);
``polrig`` (layer 0) re-exports these functions lazily, by a module ``__getattr__`` that
imports this module on first access, so that ``import polrig`` stays light and the layers
stay what they are (``tests/test_architecture.py``: the one declared public face).

xarray and dask are the ``api`` extra (``pip install 'polrig[api]'``): xarray brings pandas,
which nothing else in polrig needs, and dask is otherwise only the ``cluster`` extra's. Without
them the openers raise one line naming the extra.
"""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

import numpy as np

from polrig.app.manifest import plan_json
from polrig.app.session import Session
from polrig.errors import FormatError
from polrig.formats.exr import MuellerRows, channel_suffixes, read_mueller_exr

__all__ = ["open_result", "open_session"]

#: What the openers need, and where it comes from.
MISSING_EXTRA = ("polrig.open_session and polrig.open_result need xarray and dask: "
                 "pip install 'polrig[api]'")
#: Per-element planes (``(channel, i, j, y, x)``) and per-colour planes (``(channel, y, x)``).
ELEMENT_GROUPS = ("sigma", "sigma_noise")
COLOUR_GROUPS = ("mask", "residual")


def _libraries():
    try:
        import dask
        import dask.array as da
        import xarray as xr
    except ImportError:
        raise ModuleNotFoundError(MISSING_EXTRA) from None
    return dask, da, xr


# -- one file ---------------------------------------------------------------------------------------
class _Layout:
    """A result EXR's layout from its header alone: colours, size, which plane groups it
    holds, its metadata."""

    def __init__(self, path: pathlib.Path):
        with MuellerRows(path) as rows:
            c, _, _, h, w = rows.shape
            names = set(rows.channels)
            self.metadata = rows.metadata
        self.path = path
        self.colours = channel_suffixes(c)
        self.shape = (h, w)
        self.groups = [g for g in ELEMENT_GROUPS if all(
            f"{g}.M{r}{q}.{s}" in names for r in range(3) for q in range(3) for s in self.colours)]
        self.groups += [g for g in COLOUR_GROUPS if all(f"{g}.{s}" in names for s in self.colours)]


def _read_planes(path: pathlib.Path, colours: tuple[str, ...], groups: list[str]
                 ) -> dict[str, np.ndarray]:
    """Every variable of one result file, read once (the capture's one dask chunk)."""
    res = read_mueller_exr(path)
    if channel_suffixes(res.mueller.shape[0]) != tuple(colours):
        raise FormatError(f"{path}: colours changed since the session was opened")
    out = {"mueller": res.mueller}
    h, w = res.mueller.shape[-2:]
    for g in groups:  # each plane moved into its group's array: no second copy of the file at once
        if g in ELEMENT_GROUPS:
            out[g] = np.empty((len(colours), 3, 3, h, w), np.float32)
            for k, s in enumerate(colours):
                for r in range(3):
                    for q in range(3):
                        out[g][k, r, q] = res.extra.pop(f"{g}.M{r}{q}.{s}")
        else:
            out[g] = np.empty((len(colours), h, w), np.uint8 if g == "mask" else np.float32)
            for k, s in enumerate(colours):
                out[g][k] = res.extra.pop(f"{g}.{s}")
    return out


def _lazy_variables(layout: _Layout, dask, da) -> dict[str, tuple[tuple[str, ...], Any]]:
    """The file's variables as dask arrays sharing one delayed read."""
    c = len(layout.colours)
    h, w = layout.shape
    read = dask.delayed(_read_planes, pure=True)(layout.path, layout.colours, layout.groups)
    element = (("channel", "i", "j", "y", "x"), (c, 3, 3, h, w))
    colour = (("channel", "y", "x"), (c, h, w))
    out = {}
    for name in ("mueller", *layout.groups):
        dims, shape = element if name in ("mueller", *ELEMENT_GROUPS) else colour
        dtype = np.uint8 if name == "mask" else np.float32
        out[name] = (dims, da.from_delayed(read[name], shape, dtype=dtype))
    return out


def _json_safe(value: Any) -> Any:
    return json.loads(json.dumps(value, allow_nan=True, default=str))


_ATTRS = {
    "mueller": {"long_name": "Mueller matrix element M[i, j] (3x3 linear block)",
                "units": "DN per unit incident S0 at the reference exposure"},
    "sigma": {"long_name": "standard deviation of M[i, j]: sensor noise and calibration"},
    "sigma_noise": {"long_name": "standard deviation of M[i, j] from the sensor noise alone"},
    "mask": {"long_name": "reason bits, 0 = valid (1 dark, 2 saturated, 4 ill-conditioned, "
                          "8 non-finite)"},
    "residual": {"long_name": "chi^2 per degree of freedom of the solve"},
}


def open_result(path: str | os.PathLike):
    """One result EXR (a session's ``mueller.exr``, a ``polrig infer`` output) as an
    ``xarray.Dataset``: ``mueller`` ``(channel, i, j, y, x)`` and the planes the file holds
    (``sigma``, ``sigma_noise`` alike; ``mask``, ``residual`` ``(channel, y, x)``), one lazy
    dask chunk; its header's polrig entries (sample metadata included) as attributes."""
    dask, da, xr = _libraries()
    layout = _Layout(pathlib.Path(path))
    ds = xr.Dataset(_lazy_variables(layout, dask, da),
                    coords={"channel": list(layout.colours), "i": [0, 1, 2], "j": [0, 1, 2]},
                    attrs={**_json_safe(layout.metadata), "path": str(layout.path)})
    for name, attrs in _ATTRS.items():
        if name in ds:
            ds[name].attrs.update(attrs)
    return ds


# -- a session --------------------------------------------------------------------------------------
def open_session(path: str | os.PathLike, revision: str | None = None):
    """The session in folder ``path`` as an ``xarray.Dataset`` (lazy: nothing but the manifest
    and the results' headers is read until a value is computed).

    ``mueller`` has dims ``(capture, channel, i, j, y, x)``; ``sigma``, ``sigma_noise``
    alike, ``mask`` and ``residual`` ``(capture, channel, y, x)``. The ``capture`` coordinate
    is the pose in degrees, ``capture_id`` (on the same dim) the capture's folder name. Only
    captures with a result are included (``attrs["captures_without_result"]`` lists the
    others' names). ``revision``: a ``polrig reconstruct`` revision's results (``"rev1"``)
    instead of the capture's own. Attributes: the sample metadata (flat), ``plan``, ``rig``,
    ``calibration_id``, ``status``, ``schema_version``, ``session`` (the folder)...
    Raises :class:`polrig.errors.FormatError` for a damaged manifest or result file and
    ``KeyError`` for an unknown revision."""
    dask, da, xr = _libraries()
    session = Session.open(path)  # read only: no lock, nothing written
    m = session.manifest
    if revision is not None and revision not in {r["name"] for r in m["revisions"]}:
        known = ", ".join(r["name"] for r in m["revisions"]) or "none"
        raise KeyError(f"{session.root}: no revision {revision!r} (revisions: {known})")
    layouts, poses, ids, missing = [], [], [], []
    for cap in session.captures:
        files = cap["files"] if revision is None else cap["revisions"].get(revision, {}).get("files", {})
        if "mueller" not in files:
            missing.append(cap["name"])
            continue
        layouts.append(_Layout(session.root / files["mueller"]["path"]))
        poses.append(cap["pose_deg"])
        ids.append(cap["name"])
    md = m["metadata"]
    attrs = {
        **md.fields(),
        "session": str(session.root), "revision": revision or "capture",
        "schema_version": m["schema_version"], "conventions_version": m["conventions_version"],
        "created": m["created"], "updated": m["updated"], "status": m["status"],
        "calibration_id": m["calibration_id"], "plan": plan_json(session.plan),
        "rig": _json_safe(m["rig"]), "command_line": list(m["command_line"]),
        "captures_without_result": missing,
    }
    if not layouts:
        return xr.Dataset(coords={"capture": ("capture", np.zeros(0)),
                                  "capture_id": ("capture", np.array([], dtype=str))},
                          attrs=attrs)
    first = layouts[0]
    for lay in layouts[1:]:
        if (lay.colours, lay.shape, lay.groups) != (first.colours, first.shape, first.groups):
            raise FormatError(f"{lay.path}: {lay.shape} {lay.colours} {lay.groups} differs from "
                              f"{first.path}'s {first.shape} {first.colours} {first.groups}")
    per_file = [_lazy_variables(lay, dask, da) for lay in layouts]
    variables = {name: (("capture", *dims), da.stack([v[name][1] for v in per_file]))
                 for name, (dims, _) in per_file[0].items()}
    ds = xr.Dataset(variables,
                    coords={"capture": ("capture", np.asarray(poses, float),
                                        {"long_name": "turntable pose", "units": "deg"}),
                            "capture_id": ("capture", ids),
                            "channel": list(first.colours), "i": [0, 1, 2], "j": [0, 1, 2]},
                    attrs=attrs)
    for name, a in _ATTRS.items():
        if name in ds:
            ds[name].attrs.update(a)
    return ds
