"""The Viewer's geometry layer, free of Qt: surface normals, albedo, roughness and light direction.

A file carries geometry in one of two plane groups (issue 34, item 3):

* the single-shot networks' estimate in a result EXR (``polrig infer --geometry``,
  ``--exr-planes ...,geometry``; :data:`polrig.app.single_shot.GEOMETRY_PLANES`):
  ``geometry.normal.{X,Y,Z}``, ``geometry.light.{X,Y,Z}`` (unit vectors, camera frame),
  ``geometry.albedo.{ch}`` and ``geometry.roughness`` (NaN outside the object);
* shape-from-polarization normals in a maps EXR (``polrig analyze --normals --ior N``;
  :mod:`polrig.optics.shape_from_polarization`): every candidate the ambiguities allow,
  ``sfp_normal{k}.{X,Y,Z}.{ch}``, with ``sfp_zenith_deg{z}.{ch}`` and ``sfp_azimuth_deg.{ch}``
  (the azimuth of candidate 0); the header's ``shape_from_polarization`` names the reflection
  model and the refractive index.

**Normal map.** A normal is shown as the usual RGB normal map, ``(n' + 1) / 2`` scaled to
0..255, of ``n' = (X, -Y, -Z)``: the normal in the viewer's frame (``x`` right, ``y`` up, ``z``
towards the viewer) rather than the OpenCV camera frame the planes use (``Y`` down, ``Z``
forward), so a surface facing the camera is light blue ``(128, 128, 255)``, one tilted right
reddish, one tilted up greenish. Pixels without a normal (NaN: outside the object, or a DoLP
that no surface of the index gives) are black. The albedo is shown as colour (linear,
``(kd) ** (1 / 2.2)`` with white at 1); the roughness and the light direction, one per image
and nearly constant, are in the readout.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from polrig.app import preview
from polrig.formats.exr import channel_suffixes

#: Choice key of the networks' normal and albedo (the shape-from-polarization candidates are
#: ``"sfp0"``, ``"sfp1"``, ...).
NETWORK_NORMAL, NETWORK_ALBEDO = "normal", "albedo"

#: What each candidate of a reflection model is (:class:`polrig.optics.shape_from_polarization.SfpNormals`).
SFP_CANDIDATES = {
    "diffuse": ("azimuth = AoLP", "azimuth = AoLP + 180 deg"),
    "specular": ("below Brewster, azimuth = AoLP + 90 deg", "below Brewster, azimuth = AoLP + 270 deg",
                 "above Brewster, azimuth = AoLP + 90 deg", "above Brewster, azimuth = AoLP + 270 deg"),
}


@dataclasses.dataclass(frozen=True)
class GeometryPlanes:
    """A file's geometry (module docstring), each ``None`` where the file lacks it.

    Networks': ``normal`` and ``light`` ``(3, H, W)`` unit vectors (camera frame), ``albedo``
    ``(C, H, W)``, ``roughness`` ``(H, W)`` (GGX alpha). Shape from polarization:
    ``sfp_normals`` ``(K, 3, C, H, W)`` (candidate, axis, colour), ``sfp_zenith_deg``
    ``(Z, C, H, W)``, ``sfp_azimuth_deg`` ``(C, H, W)`` (of candidate 0, degrees from image
    right towards up), ``sfp_reflection`` (``"diffuse"`` or ``"specular"``) and ``sfp_ior``."""

    normal: np.ndarray | None = None
    light: np.ndarray | None = None
    albedo: np.ndarray | None = None
    roughness: np.ndarray | None = None
    sfp_normals: np.ndarray | None = None
    sfp_zenith_deg: np.ndarray | None = None
    sfp_azimuth_deg: np.ndarray | None = None
    sfp_reflection: str = ""
    sfp_ior: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the planes."""
        for a in (self.normal, self.albedo, self.sfp_normals):
            if a is not None:
                return tuple(a.shape[-2:])  # type: ignore[return-value]
        raise ValueError("no geometry planes")

    @property
    def n_colours(self) -> int:
        """Colour planes of the albedo or of the shape-from-polarization normals (1 without)."""
        if self.sfp_normals is not None:
            return int(self.sfp_normals.shape[2])
        return 1 if self.albedo is None else int(self.albedo.shape[0])

    def choices(self) -> list[tuple[str, str]]:
        """``(key, label)`` of what the layer can show: the networks' normal and albedo, then
        each shape-from-polarization candidate."""
        out = []
        if self.normal is not None:
            out.append((NETWORK_NORMAL, "normal (single-shot networks)"))
        if self.albedo is not None:
            out.append((NETWORK_ALBEDO, "albedo (single-shot networks)"))
        if self.sfp_normals is not None:
            for k in range(self.sfp_normals.shape[0]):
                out.append((f"sfp{k}", f"normal, shape from polarization: {sfp_label(self, k)}"))
        return out


def sfp_label(geo: GeometryPlanes, k: int) -> str:
    """What candidate ``k`` of the shape-from-polarization normals is (e.g. "azimuth = AoLP")."""
    names = SFP_CANDIDATES.get(geo.sfp_reflection, ())
    return f"k = {k}" + (f", {names[k]}" if k < len(names) else "")


def _stack(planes: Mapping[str, np.ndarray], names: list[str]) -> np.ndarray | None:
    got = [planes.get(n) for n in names]
    return None if any(g is None for g in got) else np.stack([np.asarray(g, np.float32) for g in got])


def _colours_of(planes: Mapping[str, np.ndarray], prefix: str) -> tuple[str, ...] | None:
    for n in (3, 1):
        sfx = channel_suffixes(n)
        if all(f"{prefix}.{s}" in planes for s in sfx):
            return sfx
    return None


def geometry_from_planes(planes: Mapping[str, np.ndarray],
                         metadata: Mapping[str, Any] | None = None) -> GeometryPlanes | None:
    """The geometry of an EXR's ``planes`` (and its header ``metadata``, for the
    shape-from-polarization model), or None when it has neither group."""
    normal = _stack(planes, [f"geometry.normal.{a}" for a in "XYZ"])
    light = _stack(planes, [f"geometry.light.{a}" for a in "XYZ"])
    sfx = _colours_of(planes, "geometry.albedo")
    albedo = None if sfx is None else _stack(planes, [f"geometry.albedo.{s}" for s in sfx])
    rough = planes.get("geometry.roughness")
    sfp = sfp_zen = sfp_az = None
    sfx = _colours_of(planes, "sfp_normal0.X")
    if sfx is not None:
        cands, k = [], 0
        while all(f"sfp_normal{k}.{a}.{s}" in planes for a in "XYZ" for s in sfx):
            cands.append(np.stack([_stack(planes, [f"sfp_normal{k}.{a}.{s}" for s in sfx])
                                   for a in "XYZ"]))
            k += 1
        sfp = np.stack(cands)
        zen, z = [], 0
        while all(f"sfp_zenith_deg{z}.{s}" in planes for s in sfx):
            zen.append(_stack(planes, [f"sfp_zenith_deg{z}.{s}" for s in sfx]))
            z += 1
        sfp_zen = np.stack(zen) if zen else None
        sfp_az = _stack(planes, [f"sfp_azimuth_deg.{s}" for s in sfx])
    if all(a is None for a in (normal, light, albedo, rough, sfp)):
        return None
    info = (metadata or {}).get("shape_from_polarization") or {}
    reflection = info.get("reflection") or (
        {2: "diffuse", 4: "specular"}.get(sfp.shape[0], "") if sfp is not None else "")
    ior = info.get("ior")
    return GeometryPlanes(normal, light, albedo, None if rough is None else np.asarray(rough, np.float32),
                          sfp, sfp_zen, sfp_az, reflection, None if ior is None else float(ior))


def _colour_index(n: int, colour: int) -> int:
    """Colour plane of a choice: negative (the luminance) shows green of a colour image (the
    best-sampled colour of a Bayer sensor; a normal has no mean of its colours)."""
    return (1 if n == 3 else 0) if colour < 0 else min(colour, n - 1)


def normal_rgb(normal: np.ndarray) -> np.ndarray:
    """The RGB normal map ``(H, W, 3)`` uint8 of unit normals ``(3, H, W)`` in the camera frame
    (module docstring: ``round(255 (n' + 1) / 2)`` of ``n' = (X, -Y, -Z)``); black where a
    component is not finite."""
    n = np.asarray(normal, np.float64) * np.array([1.0, -1.0, -1.0])[:, None, None]
    ok = np.isfinite(n).all(axis=0)
    rgb = np.rint(np.clip((np.nan_to_num(n) + 1.0) / 2.0, 0.0, 1.0) * 255.0).astype(np.uint8)
    rgb = np.moveaxis(rgb, 0, -1)
    rgb[~ok] = 0
    return np.ascontiguousarray(rgb)


def chosen_normal(geo: GeometryPlanes, choice: str, colour: int = -1) -> np.ndarray:
    """``(3, H, W)``: the networks' normal, or shape-from-polarization candidate ``sfpK`` of
    ``colour`` (:func:`_colour_index`)."""
    if choice == NETWORK_NORMAL and geo.normal is not None:
        return geo.normal
    if choice.startswith("sfp") and geo.sfp_normals is not None:
        k = int(choice[3:])
        if 0 <= k < geo.sfp_normals.shape[0]:
            return geo.sfp_normals[k][:, _colour_index(geo.sfp_normals.shape[2], colour)]
    raise ValueError(f"this file has no geometry {choice!r}")


def _first_choice(geo: GeometryPlanes, choice: str) -> str:
    keys = [k for k, _ in geo.choices()]
    return choice if choice in keys else keys[0]


def render(geo: GeometryPlanes, choice: str, colour: int = -1, step: int = 1) -> np.ndarray:
    """uint8 RGB ``(H, W, 3)`` of ``choice`` (a key of :meth:`GeometryPlanes.choices`; an
    unknown one shows the first): a normal map (:func:`normal_rgb`) or the albedo as colour
    (every colour for the luminance choice, else that colour's grey); every ``step``-th pixel."""
    k = slice(None, None, max(1, int(step)))
    choice = _first_choice(geo, choice)
    if choice == NETWORK_ALBEDO:
        a = geo.albedo[:, k, k]
        ok = np.isfinite(a).all(axis=0)
        planes = a if colour < 0 else a[[_colour_index(a.shape[0], colour)]]
        return preview.tone_map(planes, white=1.0, valid=ok)
    return normal_rgb(chosen_normal(geo, choice, colour)[:, k, k])


def histogram_values(geo: GeometryPlanes, choice: str, colour: int = -1
                     ) -> tuple[np.ndarray, tuple[float, float], str]:
    """``(finite values, range, label)`` the histogram shows: the albedo, or the normal's angle
    to the optical axis in degrees (``arccos(-Z)``, 0 = facing the camera)."""
    choice = _first_choice(geo, choice)
    if choice == NETWORK_ALBEDO:
        a = geo.albedo if colour < 0 else geo.albedo[[_colour_index(geo.albedo.shape[0], colour)]]
        x = a[np.isfinite(a)]
        return x, (0.0, max(1.0, float(x.max()) if x.size else 1.0)), "albedo"
    z = chosen_normal(geo, choice, colour)[2]
    x = np.rad2deg(np.arccos(np.clip(-z[np.isfinite(z)], -1.0, 1.0)))
    return x, (0.0, 180.0), "normal's angle to the optical axis (deg)"


def _vec(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{c:+.3f}" for c in v) + ")"


def readout(geo: GeometryPlanes, choice: str, x: int, y: int) -> str:
    """The geometry at image pixel ``(x, y)``: the networks' normal, light direction (camera
    frame), roughness and albedo per colour; the shape-from-polarization candidate ``choice``
    (or candidate 0) per colour with its zenith and azimuth; "" outside the image."""
    h, w = geo.shape
    if not (0 <= y < h and 0 <= x < w):
        return ""
    lines = [f"geometry at (u={x}, v={y}), camera frame (X right, Y down, Z forward)"]
    if geo.normal is not None or geo.albedo is not None:
        parts = []
        if geo.normal is not None:
            n = geo.normal[:, y, x]
            parts.append(f"normal {_vec(n)}" if np.isfinite(n).all() else "no normal (outside the object)")
        if geo.light is not None and np.isfinite(geo.light[:, y, x]).all():
            parts.append(f"light direction {_vec(geo.light[:, y, x])}")
        if geo.roughness is not None and np.isfinite(geo.roughness[y, x]):
            parts.append(f"roughness alpha {geo.roughness[y, x]:.4g}")
        if geo.albedo is not None and np.isfinite(geo.albedo[:, y, x]).all():
            names = channel_suffixes(geo.albedo.shape[0])
            parts.append("albedo " + ", ".join(f"{s} {v:.4g}" for s, v in zip(names, geo.albedo[:, y, x])))
        lines.append("networks: " + "; ".join(parts))
    if geo.sfp_normals is not None:
        k = int(choice[3:]) if choice.startswith("sfp") and choice[3:].isdigit() else 0
        k = min(k, geo.sfp_normals.shape[0] - 1)
        ior = "" if geo.sfp_ior is None else f", n = {geo.sfp_ior:g}"
        lines.append(f"shape from polarization ({geo.sfp_reflection or 'unknown reflection'}{ior}), "
                     f"candidate {sfp_label(geo, k)}:")
        for c, s in enumerate(channel_suffixes(geo.sfp_normals.shape[2])):
            n = geo.sfp_normals[k, :, c, y, x]
            if not np.isfinite(n).all():
                lines.append(f"{s}: no normal (no surface of this index polarizes so)")
                continue
            text = f"{s}: normal {_vec(n)}"
            if geo.sfp_zenith_deg is not None:
                text += f", zenith {geo.sfp_zenith_deg[min(k // 2, geo.sfp_zenith_deg.shape[0] - 1), c, y, x]:.2f} deg"
            if geo.sfp_azimuth_deg is not None:
                az = np.mod(geo.sfp_azimuth_deg[c, y, x] + 180.0 * (k % 2), 360.0)
                text += f", image azimuth {az:.2f} deg"
            lines.append(text)
    return "\n".join(lines)
