"""Display pipeline of the GUI, free of Qt: raw frames, Stokes and Mueller images -> uint8 RGB.

Everything the live view, the viewer and the benchmark show goes through here, and all the
numbers come from the core: :func:`polrig.sensor.stokes.stokes_from_raw` (demosaic, Stokes, masks,
DoLP, AoLP), the single-shot route's results (:class:`polrig.app.single_shot.SingleShotResult`,
:meth:`PolarizationData.from_single_shot`) and the colour maps
of :mod:`polrig.app.preview`. Conventions (AoLP in degrees in [0, 180), DoLP in [0, 1], arrays
plane-first) are those of ``docs/conventions.md``.

Masks (:mod:`polrig.app.preview`, "Masks"): every display hides DoLP, AoLP and ``m_ij / m00``
where the data's reason bits say so (saturated, invalid, outside the object, ...) or its
signal is below ``min_snr`` noise standard deviations; the readout says why a pixel is masked.

The only additions are for speed and interaction: :func:`stokes_from_raw_strips` runs the
superpixel pipeline on horizontal strips in threads (superpixel output pixels depend only on
their own layout cell, so the result is identical to one call), a sub-sampled white point
for tone mapping, the cursor readout and histograms.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
from typing import Any

import cv2
import numpy as np

from polrig.app import preview, roi
from polrig.app.single_shot import SingleShotResult
from polrig.formats.exr import element_stack
from polrig.gui import geometry_layer
from polrig.optics import parameters
from polrig.optics.virtual_polarizer import virtual_polarizer_image
from polrig.sensor.analyzer import layout_name_at, resolve_layout
from polrig.sensor.frame import Frame
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import (
    StokesImages,
    aolp_deg,
    dolp,
    min_max_intensity,
    stokes_from_raw,
)

#: Display modes (key -> label shown in the GUI).
DISPLAYS: dict[str, str] = {
    "raw": "Raw mosaic",
    "s0": "S0 (intensity)",
    "dolp": "DoLP",
    "aolp": "AoLP (hue)",
    "aolp_dolp": "AoLP weighted by DoLP",
    "aolp_dolp_sat": "AoLP, DoLP as saturation",
    "imin": "Imin (glare-reduced)",
    "imax": "Imax",
    "s1": "S1 (signed)",
    "s2": "S2 (signed)",
    "mueller": "Mueller 3x3",
    "maps": "Parameter map",
    "polarizer": "Virtual polarizer",
    "geometry": "Geometry (normals, albedo)",
}
#: Displays of Stokes data (a live frame, a Stokes EXR) beyond S0.
STOKES_DISPLAYS = ("dolp", "aolp", "aolp_dolp", "aolp_dolp_sat", "imin", "imax", "s1", "s2")
#: Displays of a Mueller image beyond S0 (m00).
MUELLER_DISPLAYS = ("mueller", "maps", "polarizer")
#: How each AoLP display shows DoLP (:func:`polrig.app.preview.aolp_rgb`'s ``dolp_as``; None:
#: hue only): the colour wheel beside the image follows it.
AOLP_DOLP_AS = {"aolp": None, "aolp_dolp": "value", "aolp_dolp_sat": "saturation"}


@dataclasses.dataclass
class ViewOptions:
    """What the Mueller displays show beyond their key: the parameter map (a name of
    :data:`polrig.optics.parameters.MAPS`) or its sigma, and the virtual polarizer's incident
    linear state and analyzer angle in degrees (None: unpolarized light / no analyzer)."""

    map_name: str = "retardance_deg"
    map_sigma: bool = False
    incident_deg: float | None = 0.0
    analyzer_deg: float | None = 0.0
    #: what the geometry layer shows (a key of
    #: :meth:`polrig.gui.geometry_layer.GeometryPlanes.choices`)
    geometry: str = geometry_layer.NETWORK_NORMAL
#: Colour choice "luminance": the mean over the colour channels (a mono sensor has one channel).
LUMINANCE = -1
SATURATION_RGB = (255, 0, 0)
#: Longest side of a live image on screen (pixels; :func:`display_step`), the live view's default.
DEFAULT_MAX_DISPLAY_PX = 1024
#: Border between the tiles of :func:`polrig.app.preview.mueller_grid` (pixels).
GRID_BORDER_PX = 2


@dataclasses.dataclass
class PolarizationData:
    """What a display renders. Any field may be ``None`` when the source lacks it (a Mueller
    EXR has no raw frame, a Stokes EXR no Mueller matrix).

    ``stokes`` ``(C, 3, H, W)`` DN; ``valid``/``saturated``/``dolp``/``aolp_deg`` ``(C, H, W)``;
    ``mueller`` ``(C, 3, 3, H', W')`` (DN per unit incident S0); ``raw`` ``(H_raw, W_raw)``
    with its ``bit_depth`` and ``black_level_dn``. ``flags`` (reason bits,
    :data:`polrig.app.preview.MASK_REASONS`) and ``snr`` (signal over its noise sigma, NaN where
    unknown) ``(C, H, W)`` at the output resolution, and ``min_snr`` decide what is masked
    (:func:`shown`).
    """

    stokes: np.ndarray | None = None
    valid: np.ndarray | None = None
    saturated: np.ndarray | None = None
    dolp: np.ndarray | None = None
    aolp_deg: np.ndarray | None = None
    mueller: np.ndarray | None = None
    raw: np.ndarray | None = None
    bit_depth: int = 16
    black_level_dn: float = 0.0
    source: str = ""
    flags: np.ndarray | None = None
    snr: np.ndarray | None = None
    min_snr: float = preview.DEFAULT_MIN_SNR
    #: per-element standard deviations of ``mueller`` ``(C, 3, 3, H', W')`` (a result's
    #: ``sigma`` planes), or None
    sigma: np.ndarray | None = None
    #: the file's normals, albedo, roughness, light direction
    #: (:func:`polrig.gui.geometry_layer.geometry_from_planes`), or None
    geometry: geometry_layer.GeometryPlanes | None = None
    #: The Mueller image already reduced to display size ``(C, 3, 3, dh, dw)`` (each element
    #: area-averaged: the device route's live grid, :attr:`SingleShotResult.preview_grid`), or
    #: None. Such data has no ``mueller`` and no Stokes images: it shows the Mueller grid
    #: (:func:`render`, step 1), its histogram and a readout of the display pixels' means;
    #: ROI statistics need the whole image (:func:`needs_full_image`). ``flags`` are then on
    #: the display grid (``BACKGROUND`` where less than half a display pixel is object).
    mueller_preview: np.ndarray | None = None
    #: ``(H, W)`` of the Mueller image ``mueller_preview`` was reduced from.
    preview_of: tuple[int, int] | None = None
    _views: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def n_colours(self) -> int:
        for a in (self.stokes, self.mueller, self.mueller_preview):
            if a is not None:
                return int(a.shape[0])
        return 1 if self.geometry is None else self.geometry.n_colours

    def available(self) -> list[str]:
        """The display modes this data can show (keys of :data:`DISPLAYS`)."""
        out = []
        if self.raw is not None:
            out.append("raw")
        if self.stokes is not None or self.mueller is not None:
            out.append("s0")
        if self.stokes is not None:
            out += list(STOKES_DISPLAYS)
        if self.mueller is not None:
            out += list(MUELLER_DISPLAYS)
        elif self.mueller_preview is not None:
            out.append("mueller")
        if self.geometry is not None:
            out.append("geometry")
        return out

    def maps(self) -> parameters.MapSet:
        """The parameter maps of ``mueller`` with their sigma (from ``sigma``), computed once
        (here, unless :meth:`set_maps` gave them: the viewer computes them on a worker thread,
        :class:`polrig.gui.viewer.MapsWorker`)."""
        if not self.maps_ready():
            self.set_maps(self.compute_maps())
        return self._views["maps"]

    def maps_ready(self) -> bool:
        """True when :meth:`maps` returns without computing."""
        return "maps" in self._views

    def compute_maps(self) -> parameters.MapSet:
        """:func:`polrig.optics.parameters.image_maps` of ``mueller`` and ``sigma``, not kept
        (it only reads the data: safe on a worker thread while the GUI thread shows it)."""
        return parameters.image_maps(self.mueller, self.sigma)

    def set_maps(self, maps: parameters.MapSet) -> None:
        """Keep the maps :meth:`compute_maps` returned (on the thread that shows the data)."""
        self._views["maps"] = maps

    def min_max(self) -> tuple[np.ndarray, np.ndarray]:
        """``(Imin, Imax)`` ``(C, H, W)`` of ``stokes``
        (:func:`polrig.sensor.stokes.min_max_intensity`), computed once."""
        if "min_max" not in self._views:
            self._views["min_max"] = min_max_intensity(self.stokes, self.valid)
        return self._views["min_max"]

    def polarizer(self, incident_deg: float | None, analyzer_deg: float | None) -> np.ndarray:
        """:func:`polrig.optics.virtual_polarizer.virtual_polarizer_image` of ``mueller``:
        ``(C, H, W)`` float32 in the units of ``mueller``."""
        return virtual_polarizer_image(self.mueller, incident_deg, analyzer_deg)[0]

    @classmethod
    def from_stokes_images(cls, s: StokesImages, frame: Frame | None = None,
                           source: str = "", model: SensorModel | None = None) -> "PolarizationData":
        """From :func:`polrig.sensor.stokes.stokes_from_raw`'s result; with the ``frame``, the SNR of
        ``S0`` from the noise ``model`` (default: the IMX250 model) in the ADC's DN."""
        d = cls(stokes=s.stokes, valid=s.valid, saturated=s.saturated, dolp=s.dolp,
                aolp_deg=s.aolp_deg, source=source)
        d.flags = (np.where(s.saturated, preview.SATURATED, 0)
                   | np.where(~s.valid & ~s.saturated, preview.DARK, 0)).astype(np.uint8)
        if frame is not None:
            d.raw, d.bit_depth = frame.raw, int(frame.meta.bit_depth)
            d.black_level_dn = float(frame.meta.black_level_dn)
            d.snr = frame_snr(s.stokes[:, 0], frame, model)
        return d

    @classmethod
    def from_stokes(cls, stokes: np.ndarray, source: str = "",
                    planes: dict | None = None) -> "PolarizationData":
        """From Stokes images ``(C, 3, H, W)`` (e.g. a Stokes EXR): masks, DoLP and AoLP by
        :mod:`polrig.sensor.stokes`; ``planes`` (the EXR's other planes: ``valid``, ``saturated``,
        ``snr.*``) add the file's masks (:func:`polrig.app.preview.exr_masks`)."""
        s, valid, flags, snr = preview.stokes_exr_masks(stokes, planes)
        saturated = (flags & preview.SATURATED) > 0
        return cls(stokes=s, valid=valid, saturated=saturated, dolp=dolp(s, valid),
                   aolp_deg=aolp_deg(s, valid), source=source, flags=flags, snr=snr)

    @classmethod
    def from_single_shot(cls, result: SingleShotResult, frame: Frame | None = None,
                         source: str = "") -> "PolarizationData":
        """From a single-shot result of a raw frame
        (:meth:`polrig.app.single_shot.SingleShot.frame`): its Mueller image, the measured Stokes
        images on the same grid (the raw size at full resolution) with their masks, the SNR of
        their ``S0`` (the result's, from the camera's noise model) and ``BACKGROUND`` outside the
        networks' object mask; with the ``frame``, its raw mosaic.

        A live result of the device route (:meth:`polrig.app.single_shot.SingleShot.live`: only
        its display-size grid came back, :attr:`SingleShotResult.preview_grid`) gives the grid
        as ``mueller_preview`` and the object mask reduced to it, nothing else."""
        if result.preview_grid is not None:
            return cls._from_preview_grid(result, frame, source)
        d = cls.from_stokes(result.stokes, source)
        d.mueller = result.mueller
        if frame is not None:
            d.raw, d.bit_depth = frame.raw, int(frame.meta.bit_depth)
            d.black_level_dn = float(frame.meta.black_level_dn)
        d.snr = result.snr
        d.flags = d.flags | np.where(result.object, 0, preview.BACKGROUND).astype(np.uint8)[None]
        return d

    @classmethod
    def _from_preview_grid(cls, result: SingleShotResult, frame: Frame | None,
                           source: str) -> "PolarizationData":
        """:meth:`from_single_shot` of a result carrying only ``preview_grid`` ``(C, 3 dh, 3 dw)``
        (the nine elements laid out as the matrix) -> ``mueller_preview`` ``(C, 3, 3, dh, dw)``;
        ``BACKGROUND`` where the networks' object mask covers less than half of a display pixel
        (its area fraction, OpenCV's ``INTER_AREA`` as the grid's own reduction)."""
        g = np.asarray(result.preview_grid, np.float32)
        c, dh, dw = g.shape[0], g.shape[1] // 3, g.shape[2] // 3
        grid = g.reshape(c, 3, dh, 3, dw).transpose(0, 1, 3, 2, 4)
        inside = cv2.resize(np.asarray(result.object, np.float32), (dw, dh), interpolation=cv2.INTER_AREA)
        flags = np.where(inside >= 0.5, 0, preview.BACKGROUND).astype(np.uint8)[None].repeat(c, axis=0)
        d = cls(mueller_preview=grid, preview_of=tuple(int(v) for v in result.object.shape[-2:]),
                source=source, flags=flags)
        if frame is not None:
            d.raw, d.bit_depth = frame.raw, int(frame.meta.bit_depth)
            d.black_level_dn = float(frame.meta.black_level_dn)
        return d

    @classmethod
    def from_mueller(cls, mueller: np.ndarray, source: str = "",
                     planes: dict | None = None) -> "PolarizationData":
        """From a Mueller image ``(C, 3, 3, H, W)``; ``planes`` (the EXR's other planes) give
        its masks and SNR (:func:`polrig.app.preview.exr_masks`)."""
        m = np.asarray(mueller, np.float32)
        flags, snr = preview.exr_masks(planes or {}, m.shape[0], m[:, 0, 0])
        return cls(mueller=m, source=source, flags=flags, snr=snr,
                   sigma=element_stack("sigma", planes or {}, m.shape[0]))


def frame_snr(s0: np.ndarray, frame: Frame, model: SensorModel | None = None) -> np.ndarray:
    """``S0 / sigma(S0)`` ``(C, H, W)`` of black-subtracted ``S0`` in the frame's DN
    (converted to the ADC's DN of ``model`` first, :func:`polrig.app.processing.adc_scale`)."""
    model = model or SensorModel()
    to_adc = 2.0 ** (int(model.bit_depth) - int(frame.meta.bit_depth))
    return preview.s0_snr(np.asarray(s0, np.float64) * to_adc, model, frame.meta.exposure_us)


def shown(data: PolarizationData, colour: int = LUMINANCE) -> np.ndarray | None:
    """``(H, W)`` True where ``colour`` (the luminance: every colour) is shown, i.e. not masked
    (:func:`polrig.app.preview.display_valid` at ``data.min_snr``); None without masks."""
    v = preview.display_valid(data.flags, data.snr, data.min_snr)
    if v is None:
        return None
    if colour == LUMINANCE or v.shape[0] == 1:
        return v.all(axis=0)
    return v[min(colour, v.shape[0] - 1)]


def mask_reason(data: PolarizationData, c: int, v: int, u: int) -> str:
    """Why colour ``c`` of output pixel ``(u, v)`` is masked, in words ("" when it is not)."""
    if data.flags is None and data.snr is None:
        return ""
    flags = None if data.flags is None else data.flags[c, v, u]
    snr = None if data.snr is None else data.snr[c, v, u]
    code = preview.display_flags(flags, snr, data.min_snr)
    return preview.reason_text(int(code), None if snr is None else float(snr), data.min_snr)


# -- processing a raw frame --------------------------------------------------------------------
def frame_layout(frame: Frame) -> str:
    """The layout name of a frame at its ROI offset (the mosaic phase)."""
    ox, oy = frame.meta.offset_xy
    return layout_name_at(frame.meta.layout, int(ox), int(oy))


def stokes_from_raw_strips(raw: np.ndarray, layout: str, method: str = "superpixel", *,
                           black_level_dn: float = 0.0, bit_depth: int | None = None,
                           workers: int | None = None) -> StokesImages:
    """:func:`polrig.sensor.stokes.stokes_from_raw` (ideal analyzers), the superpixel method split
    into horizontal strips computed in ``workers`` threads (numpy and OpenCV release the GIL).

    Superpixel output pixels depend on their own layout cell only, so cutting at cell
    boundaries gives exactly the numbers of one call. Other methods go to the core in one
    call (its bilinear path is strip-parallel already).
    """
    lay = resolve_layout(layout)
    workers = workers or min(4, os.cpu_count() or 1)
    ph = lay.period[0]
    n_cells = raw.shape[0] // ph
    if method != "superpixel" or workers < 2 or n_cells < 2 * workers:
        return stokes_from_raw(raw, lay, method, black_level_dn=black_level_dn,
                               bit_depth=bit_depth)
    bounds = [round(i * n_cells / workers) * ph for i in range(workers + 1)]

    def part(i: int) -> StokesImages:
        return stokes_from_raw(raw[bounds[i]:bounds[i + 1]], lay, method,
                               black_level_dn=black_level_dn, bit_depth=bit_depth)

    with _pool(workers) as pool:
        parts = list(pool.map(part, range(workers)))
    cat = lambda name, axis: np.concatenate([getattr(p, name) for p in parts], axis=axis)  # noqa: E731
    return StokesImages(cat("stokes", 2), cat("valid", 1), cat("saturated", 1), cat("dolp", 1),
                        cat("aolp_deg", 1), sum(p.dolp_overshoot for p in parts), lay.name,
                        method)


_POOLS: dict[int, concurrent.futures.ThreadPoolExecutor] = {}


class _pool:
    """A shared thread pool per size (creating threads per frame costs more than it saves)."""

    def __init__(self, workers: int):
        self.workers = workers

    def __enter__(self) -> concurrent.futures.ThreadPoolExecutor:
        if self.workers not in _POOLS:
            _POOLS[self.workers] = concurrent.futures.ThreadPoolExecutor(
                self.workers, thread_name_prefix="polrig-strips")
        return _POOLS[self.workers]

    def __exit__(self, *exc) -> None:
        return None


def process_frame(frame: Frame, method: str = "superpixel", *, workers: int | None = None,
                  source: str = "", model: SensorModel | None = None) -> PolarizationData:
    """Raw frame -> :class:`PolarizationData` (Stokes, masks, DoLP, AoLP; ideal analyzers;
    the SNR from the noise ``model``, default the IMX250 one)."""
    s = stokes_from_raw_strips(frame.raw, frame_layout(frame), method,
                               black_level_dn=frame.meta.black_level_dn,
                               bit_depth=frame.meta.bit_depth, workers=workers)
    return PolarizationData.from_stokes_images(s, frame, source, model)


# -- rendering -----------------------------------------------------------------------------------
def fast_white(x: np.ndarray, percentile: float = 99.5, max_samples: int = 1 << 16) -> float:
    """White point for :func:`polrig.app.preview.tone_map`: the ``percentile`` of the finite
    positive values of a regular sub-sample of ``x`` (at most about ``max_samples`` values; a
    display needs no exact percentile of millions of pixels)."""
    flat = np.asarray(x).reshape(-1)
    step = max(1, flat.size // max_samples)
    sub = flat[::step]
    sub = sub[np.isfinite(sub) & (sub > 0)]
    return float(np.percentile(sub, percentile)) if sub.size else 1.0


def _pick(planes: np.ndarray, colour: int) -> np.ndarray:
    """``(C, H, W)`` -> ``(H, W)``: channel ``colour`` or the mean (:data:`LUMINANCE`)."""
    if colour == LUMINANCE or planes.shape[0] == 1:
        return planes[0] if planes.shape[0] == 1 else planes.mean(axis=0)
    return planes[min(colour, planes.shape[0] - 1)]


def channel_view(data: PolarizationData, colour: int) -> tuple[np.ndarray, np.ndarray,
                                                                np.ndarray, np.ndarray]:
    """``(s0, dolp, aolp_deg, valid)`` ``(H, W)`` of one colour, or of the luminance (the
    mean Stokes vector over colours, DoLP/AoLP recomputed from it by :mod:`polrig.sensor.stokes`)."""
    if data.stokes is None:
        raise ValueError("no Stokes images in this data")
    if colour != LUMINANCE or data.stokes.shape[0] == 1:
        c = 0 if data.stokes.shape[0] == 1 else min(colour, data.stokes.shape[0] - 1)
        return data.stokes[c, 0], data.dolp[c], data.aolp_deg[c], data.valid[c]
    if "luminance" not in data._views:  # computed once per data (render + histogram)
        mean = data.stokes.mean(axis=0, keepdims=True)
        valid = data.valid.all(axis=0, keepdims=True)
        data._views["luminance"] = (mean[0, 0], dolp(mean, valid)[0], aolp_deg(mean, valid)[0],
                                    valid[0])
    return data._views["luminance"]


def display_shape(data: PolarizationData, display: str) -> tuple[int, int]:
    """``(H, W)`` of the full-resolution image of ``display`` (before any decimation)."""
    if display == "raw":
        return tuple(data.raw.shape)  # type: ignore[return-value]
    if data.stokes is None and data.mueller is None and data.preview_of is not None:
        return data.preview_of
    if display == "geometry" or (data.stokes is None and data.mueller is None):
        return data.geometry.shape
    src = data.stokes if data.stokes is not None else data.mueller
    return tuple(src.shape[-2:])  # type: ignore[return-value]


def needs_full_image(data: PolarizationData, display: str) -> bool:
    """True where ``display`` of ``data`` shows a display-size Mueller grid only
    (``mueller_preview``): ROI statistics and profiles need the whole Mueller image (the live
    view then takes whole frames, :attr:`polrig.gui.live.LiveSettings.full_mueller`)."""
    return display == "mueller" and data.mueller is None and data.mueller_preview is not None


def display_step(data: PolarizationData, display: str, max_px: int) -> int:
    """Decimation step so that the displayed image has at most ``max_px`` pixels on its long
    side (0: no limit); for the Mueller grid, its three tiles side by side (borders and colour
    bar aside). A screen shows no more pixels than it has; the data (and the cursor readout,
    :func:`readout` with the same ``step``) stay at full resolution. At full sensor resolution
    the grid is 7344 pixels wide: rendering it whole took 2.8 s a frame on 16 cores
    (``benchmarks/results/live_mueller_h200.md``), decimated to 1024 a few milliseconds."""
    if max_px <= 0 or needs_full_image(data, display):  # a display-size grid: shown as it is
        return 1
    long_side = max(display_shape(data, display)) * (3 if display == "mueller" else 1)
    return max(1, -(-long_side // int(max_px)))


def render(data: PolarizationData, display: str, colour: int = LUMINANCE, *,
           saturation_overlay: bool = False, step: int = 1,
           options: ViewOptions | None = None) -> np.ndarray:
    """The uint8 RGB image ``(H, W, 3)`` of ``display`` (a key of :data:`DISPLAYS`).

    S0 of the luminance choice is the RGB composite of a colour sensor; saturated pixels are
    painted :data:`SATURATION_RGB` when ``saturation_overlay`` is set. ``step`` > 1 shows every
    ``step``-th pixel in each direction (see :func:`display_step`; for the Mueller grid, in each
    tile). ``options``: the parameter map and the virtual polarizer's angles
    (:class:`ViewOptions`; default its defaults).
    """
    options = options or ViewOptions()
    if display not in data.available():
        raise ValueError(f"{DISPLAYS.get(display, display)} is not available for this data")
    sat = None
    k = slice(None, None, max(1, int(step)))
    if display == "raw":
        raw = data.raw[k, k]
        full = float(2 ** int(data.bit_depth) - 1)
        g = np.empty(raw.shape, np.uint8)
        np.copyto(g, np.clip(raw * np.float32(255.0 / full), 0, 255), casting="unsafe")
        rgb = np.repeat(g[:, :, None], 3, axis=2)
        if saturation_overlay:
            sat = raw >= full
    elif display == "mueller":
        ok = shown(data, colour)
        m = data.mueller[..., k, k] if data.mueller is not None else data.mueller_preview
        return preview.mueller_grid(m, colour=None if colour == LUMINANCE else min(colour, m.shape[0] - 1),
                                    border_px=GRID_BORDER_PX, valid=None if ok is None else ok[k, k])
    elif display == "maps":
        return render_map(data, options.map_name, colour, sigma=options.map_sigma, step=step)
    elif display == "geometry":
        return geometry_layer.render(data.geometry, options.geometry, colour, step)
    elif display == "polarizer":
        i = data.polarizer(options.incident_deg, options.analyzer_deg)[:, k, k]
        white_of = 0.5 * data.mueller[:, 0, 0, k, k]  # the unpolarized, analyzer-free scale
        if colour == LUMINANCE:
            rgb = preview.tone_map(i, white=fast_white(white_of))
        else:
            c = min(colour, i.shape[0] - 1)
            rgb = preview.tone_map(i[c], white=fast_white(white_of[c]))
    elif display in ("imin", "imax"):
        imin, imax = data.min_max()
        planes = imin if display == "imin" else imax
        pick = slice(None) if colour == LUMINANCE else [min(colour, planes.shape[0] - 1)]
        white = fast_white(data.stokes[pick, 0][:, k, k])  # S0's scale: Imin looks darker
        rgb = preview.tone_map(planes[pick][:, k, k], white=white)
        if saturation_overlay:
            sat = data.saturated[:, k, k].any(axis=0)
    elif display in ("s1", "s2"):
        x = _pick(data.stokes[:, 1 if display == "s1" else 2], colour)[k, k]
        lin = np.hypot(_pick(data.stokes[:, 1], colour)[k, k], _pick(data.stokes[:, 2], colour)[k, k])
        valid = channel_view(data, colour)[3][k, k]
        ok = shown(data, colour)
        if ok is not None:
            valid = valid & ok[k, k]
        rgb = preview.diverging(x, vmax=fast_white(lin), valid=valid)
        if saturation_overlay:
            sat = data.saturated[:, k, k].any(axis=0)
    elif display == "s0" and data.stokes is None:  # Mueller only: m00
        m00 = _pick(data.mueller[:, 0, 0], colour)[k, k]
        rgb = preview.tone_map(m00, white=fast_white(m00))
    elif display == "s0":
        planes = data.stokes[:, 0] if colour == LUMINANCE else data.stokes[[min(
            colour, data.stokes.shape[0] - 1)], 0]
        planes = planes[:, k, k]
        rgb = preview.tone_map(planes, white=fast_white(planes))
        if saturation_overlay:
            sat = data.saturated[:, k, k].any(axis=0)
    else:
        _, d, a, valid = (v[k, k] for v in channel_view(data, colour))
        ok = shown(data, colour)
        if ok is not None:
            valid = valid & ok[k, k]
        if display == "dolp":
            rgb = preview.dolp_colormap(d, valid=valid)
        elif display == "aolp":
            rgb = preview.aolp_rgb(a, valid=valid)
        else:
            rgb = preview.aolp_rgb(a, d, dolp_as=AOLP_DOLP_AS[display], valid=valid)
        if saturation_overlay:
            sat = data.saturated[:, k, k].any(axis=0)
    if sat is not None and sat.any():
        rgb[sat] = SATURATION_RGB
    return rgb


#: Least height (pixels) of a map image that gets its colour bar (a readable bar is about 90
#: pixels wide whatever the image's size).
MAP_LEGEND_MIN_PX = 128
#: Maps shown on a viridis scale over [0, 1] (the others: angles as hue, m00 tone-mapped,
#: the signed ones diverging over [-1, 1], the retardance over [0, 180] deg).
_UNIT_MAPS = ("DL", "PL", "sv1", "mmt_t1", "depolarization")
#: The maps with a sign, in -1..1 (docs/analysis.md; ``mmt_b`` < 0 where the block turns the
#: light's frame by more than 45 deg): on the diverging map, where 0..1 showed them as 0.
SIGNED_MAPS = ("sv2", "mmt_b", "mmt_A")


def map_plane(data: PolarizationData, name: str, colour: int = LUMINANCE, *,
              sigma: bool = False) -> tuple[np.ndarray, str]:
    """``(plane (H, W), channel name)`` of parameter map ``name`` (or its sigma) of one colour;
    the luminance choice shows green for a colour image (an angle has no mean of its colours;
    green is the best-sampled colour of a Bayer sensor)."""
    ms = data.maps()
    stack = ms.sigma.get(name) if sigma else ms.values[name]
    if stack is None:
        raise ValueError("this result has no sigma planes")
    n = stack.shape[0]
    c = (1 if n == 3 else 0) if colour == LUMINANCE else min(colour, n - 1)
    return stack[c], _colour_names(n)[c]


def render_map(data: PolarizationData, name: str, colour: int = LUMINANCE, *,
               sigma: bool = False, step: int = 1) -> np.ndarray:
    """Parameter map ``name`` (:data:`polrig.optics.parameters.MAPS`) of the Mueller image, or
    its sigma (grey, tone-mapped), as uint8 RGB with its colour bar on the right when the image
    is at least :data:`MAP_LEGEND_MIN_PX` tall (an angle map has none: the colour wheel beside
    the image is its key; the histogram gives the range of any); masked and NaN pixels black."""
    k = slice(None, None, max(1, int(step)))
    v, ch = map_plane(data, name, colour, sigma=sigma)
    v = v[k, k]
    ok = np.isfinite(v)
    shown_ok = shown(data, colour)
    if shown_ok is not None and shown_ok.shape == data.mueller.shape[-2:]:
        ok &= shown_ok[k, k]
    title = f"{'sigma ' if sigma else ''}{name} {ch}"
    h = v.shape[0]
    if sigma or name == "m00":
        white = fast_white(np.where(ok, v, 0))
        rgb = preview.tone_map(v, white=white, valid=ok)
        bar = preview.value_bar(h, lambda x: preview.tone_map(x, white=white, gamma=1 / 2.2),
                                {white: f"{white:.3g}", 0.0: "0"}, lo=0.0, hi=white, title=title)
    elif name in parameters.ANGLE_PERIOD_DEG:
        period = parameters.ANGLE_PERIOD_DEG[name]
        return preview.aolp_rgb(np.mod(v, period) * (180.0 / period), valid=ok)
    elif name in SIGNED_MAPS:
        rgb = preview.diverging(v, vmax=1.0, valid=ok)
        bar = preview.value_bar(h, lambda x: preview.diverging(x[:, 0], vmax=1.0)[:, None],
                                {1.0: "+1", 0.0: "0", -1.0: "-1"}, lo=-1.0, hi=1.0, title=title)
    else:
        top = 180.0 if name == "retardance_deg" else 1.0
        rgb = preview.dolp_colormap(v / top, valid=ok)
        bar = preview.value_bar(h, lambda x: preview.dolp_colormap(x / top),
                                {top: f"{top:g}", top / 2: f"{top / 2:g}", 0.0: "0"},
                                lo=0.0, hi=top, title=title)
    return preview.with_legend(rgb, bar) if h >= MAP_LEGEND_MIN_PX else rgb


def roi_valid(data: PolarizationData) -> np.ndarray | None:
    """``(C, H, W)`` the pixels ROI statistics count by the data's masks (reason bits and the
    signal threshold ``min_snr``, :func:`polrig.app.preview.display_valid`; for Stokes data
    also its own validity); None: no mask."""
    v = preview.display_valid(data.flags, data.snr, data.min_snr)
    if data.mueller is not None:
        return v if v is None or v.shape[-2:] == data.mueller.shape[-2:] else None
    return data.valid if v is None else v & data.valid


def roi_shape(data: PolarizationData) -> tuple[int, int]:
    """``(H, W)`` of the grid ROI statistics use: the Mueller image's, else the Stokes'."""
    src = data.mueller if data.mueller is not None else data.stokes
    return tuple(src.shape[-2:])  # type: ignore[return-value]


def roi_statistics(data: PolarizationData, inside: np.ndarray) -> list[roi.RoiRow]:
    """:func:`polrig.app.roi.roi_statistics` of the data (its Mueller image and sigma where it
    has one, else its Stokes images and SNR) over ``inside`` ``(H, W)``, counting the pixels
    :func:`roi_valid` leaves."""
    if data.mueller is not None:
        return roi.roi_statistics(inside, mueller=data.mueller, sigma=data.sigma,
                                  valid=roi_valid(data))
    return roi.roi_statistics(inside, stokes=data.stokes, valid=roi_valid(data), snr=data.snr)


def roi_profile(data: PolarizationData, segment: tuple[float, float, float, float]
                ) -> roi.Profile:
    """:func:`polrig.app.roi.profile_of` the data along ``segment`` (data pixels), with the
    quantities and masks of :func:`roi_statistics`."""
    if data.mueller is not None:
        return roi.profile_of(segment, mueller=data.mueller, sigma=data.sigma,
                              valid=roi_valid(data))
    return roi.profile_of(segment, stokes=data.stokes, valid=roi_valid(data), snr=data.snr)


def histogram(data: PolarizationData, display: str, colour: int = LUMINANCE,
              bins: int = 64, step: int = 1, options: ViewOptions | None = None
              ) -> tuple[np.ndarray, np.ndarray, str]:
    """``(counts, edges, label)`` of the quantity a display shows (valid pixels only):
    raw DN, S0 DN, DoLP in [0, 1] or AoLP in degrees [0, 180). The Mueller grid shows the
    histogram of ``m00``. ``step`` > 1 counts every ``step``-th pixel in each direction."""
    k = slice(None, None, max(1, int(step)))
    options = options or ViewOptions()
    if display == "geometry":
        x, rng, label = geometry_layer.histogram_values(data.geometry, options.geometry, colour)
        counts, edges = np.histogram(x, bins=bins, range=rng)
        return counts, edges, label
    if display == "raw":
        x = data.raw[k, k].reshape(-1)
        rng = (0.0, float(2 ** int(data.bit_depth)))
        label = "raw DN"
    elif display in ("maps", "polarizer", "imin", "imax", "s1", "s2"):
        if display == "maps":
            v, ch = map_plane(data, options.map_name, colour, sigma=options.map_sigma)
            label = f"{'sigma ' if options.map_sigma else ''}{options.map_name} {ch}"
        elif display == "polarizer":
            v = _pick(data.polarizer(options.incident_deg, options.analyzer_deg), colour)
            label = "virtual polarizer (DN)"
        elif display in ("imin", "imax"):
            v = _pick(data.min_max()[display == "imax"], colour)
            label = f"{display.capitalize()} (DN)"
        else:
            v = _pick(data.stokes[:, 1 if display == "s1" else 2], colour)
            label = f"{display.upper()} (DN)"
        x = np.asarray(v)[k, k]
        ok = shown(data, colour) if display in ("maps", "polarizer") else None
        x = x[ok[k, k]] if ok is not None and ok.shape == np.shape(v) else x.reshape(-1)
        x = x[np.isfinite(x)]
        lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 1.0)
        if display in ("s1", "s2"):
            lo, hi = -max(abs(lo), abs(hi), 1e-30), max(abs(lo), abs(hi), 1e-30)
        rng = (min(lo, 0.0) if display != "maps" else lo, hi if hi > lo else lo + 1.0)
    elif display in ("s0", "mueller") and (data.stokes is None or display == "mueller"):
        m = data.mueller if data.mueller is not None else data.mueller_preview
        x = _pick(m[:, 0, 0], colour).reshape(-1)
        x = x[np.isfinite(x) & (x > 0)]
        rng = (0.0, float(x.max()) if x.size else 1.0)
        label = "m00 (DN per unit S0)" + (" display-pixel means" if data.mueller is None else "")
    else:
        s0, d, a, valid = (v[k, k] for v in channel_view(data, colour))
        ok = shown(data, colour)
        if ok is not None and display != "s0":
            valid = valid & ok[k, k]
        q = {"s0": s0, "dolp": d}.get(display, a)
        x = q[valid]
        rng = {"dolp": (0.0, 1.0), "aolp": (0.0, 180.0), "aolp_dolp": (0.0, 180.0),
               "aolp_dolp_sat": (0.0, 180.0)}.get(
            display, (0.0, float(x.max()) if x.size and x.max() > 0 else 1.0))
        label = {"s0": "S0 (DN)", "dolp": "DoLP"}.get(display, "AoLP (deg)")
    counts, edges = np.histogram(x, bins=bins, range=rng)
    return counts, edges, label


def grid_to_pixel(x: int, y: int, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """A pixel ``(x, y)`` of :func:`polrig.app.preview.mueller_grid`'s image -> ``(row, col, u, v)``
    of the element tile and the image pixel in it (``None`` on a border or the colour bar)."""
    h, w = shape
    b = GRID_BORDER_PX
    c, u = divmod(x - b, w + b)
    r, v = divmod(y - b, h + b)
    if not (0 <= r < 3 and 0 <= c < 3 and 0 <= u < w and 0 <= v < h):
        return None
    return r, c, u, v


def display_to_data(data: PolarizationData, display: str, points: list, step: int = 1) -> list:
    """Points drawn on a display image rendered with ``step`` -> the data's pixel coordinates
    (floats): times ``step``; on the Mueller grid, relative to the tile of the first point (a
    shape drawn on any element tile measures the same pixels)."""
    k = max(1, int(step))
    pts = [(float(x), float(y)) for x, y in points]
    ky = kx = float(k)
    if needs_full_image(data, display) and data.preview_of is not None:  # tiles of display-pixel means
        th, tw = data.mueller_preview.shape[-2:]
        ky, kx = data.preview_of[0] / th, data.preview_of[1] / tw
    elif display == "mueller" and data.mueller is not None:
        h, w = data.mueller.shape[-2:]
        th, tw = -(-h // k), -(-w // k)
    if display == "mueller" and (data.mueller is not None or data.mueller_preview is not None) and pts:
        hit = grid_to_pixel(int(pts[0][0]), int(pts[0][1]), (th, tw))
        if hit is not None:
            r, c = hit[0], hit[1]
            ox, oy = GRID_BORDER_PX + c * (tw + GRID_BORDER_PX), GRID_BORDER_PX + r * (th + GRID_BORDER_PX)
            pts = [(x - ox, y - oy) for x, y in pts]
    return [(x * kx, y * ky) for x, y in pts]


def layer_readout(data: PolarizationData, display: str, options: ViewOptions, x: int, y: int
                  ) -> str:
    """The value of the parameter map (with its sigma) or of the virtual polarizer (with its
    exact sigma) under the cursor at image pixel ``(x, y)``, per colour; "" for other displays
    or outside the image; the geometry layer's readout
    (:func:`polrig.gui.geometry_layer.readout`)."""
    if display == "geometry" and data.geometry is not None:
        return geometry_layer.readout(data.geometry, options.geometry, x, y)
    if data.mueller is None or display not in ("maps", "polarizer"):
        return ""
    h, w = data.mueller.shape[-2:]
    if not (0 <= y < h and 0 <= x < w):
        return ""
    names = _colour_names(data.mueller.shape[0])
    if display == "maps":
        ms = data.maps()
        val = ms.values[options.map_name][:, y, x]
        sig = ms.sigma.get(options.map_name)
        parts = [f"{n} {v:.4g}" + (f" +- {sig[c, y, x]:.2g}" if sig is not None else "")
                 for c, (n, v) in enumerate(zip(names, val))]
        return f"{options.map_name} at (u={x}, v={y}): " + ", ".join(parts)
    i, s = virtual_polarizer_image(data.mueller[..., y:y + 1, x:x + 1], options.incident_deg,
                                   options.analyzer_deg,
                                   None if data.sigma is None else data.sigma[..., y:y + 1, x:x + 1])
    inc = "unpolarized" if options.incident_deg is None else f"{options.incident_deg:g} deg"
    ana = "none" if options.analyzer_deg is None else f"{options.analyzer_deg:g} deg"
    parts = [f"{n} {i[c, 0, 0]:.4g}" + (f" +- {s[c, 0, 0]:.2g}" if s is not None else "")
             for c, n in enumerate(names)]
    return f"virtual polarizer (in {inc}, analyzer {ana}) DN: " + ", ".join(parts)


def readout(data: PolarizationData, display: str, x: int, y: int, step: int = 1) -> str:
    """Text of the values under the cursor at display pixel ``(x, y)`` of an image rendered with
    ``step`` (:func:`render`): Stokes, DoLP, AoLP per colour, and the 3x3 Mueller matrix
    (normalised by ``m00`` too) where there is one."""
    k = max(1, int(step))
    if needs_full_image(data, display):
        hit = grid_to_pixel(x, y, data.mueller_preview.shape[-2:])
        if hit is None:
            return ""
        th, tw = data.mueller_preview.shape[-2:]
        return _mueller_lines(data, hit[2], hit[3], data.mueller_preview,
                              f"Mueller, display pixel (u={hit[2]}, v={hit[3]}) of {tw}x{th}: the mean over "
                              f"its {data.preview_of[1] / tw:.3g}x{data.preview_of[0] / th:.3g} image pixels")
    if display == "mueller" and data.mueller is not None:
        h, w = data.mueller.shape[-2:]
        hit = grid_to_pixel(x, y, (-(-h // k), -(-w // k)))  # the decimated tiles' shape
        if hit is None:
            return ""
        u, v = hit[2] * k, hit[3] * k
    elif k > 1:
        return readout(data, display, x * k, y * k)
    elif display == "raw" and data.raw is not None:
        if not (0 <= y < data.raw.shape[0] and 0 <= x < data.raw.shape[1]):
            return ""
        lines = [f"raw ({x}, {y}): {int(data.raw[y, x])} DN"]
        if data.stokes is not None:  # the output pixel this raw pixel belongs to
            hs, ws = data.stokes.shape[-2:]
            u, v = x * ws // data.raw.shape[1], y * hs // data.raw.shape[0]
            lines.append(_stokes_lines(data, u, v))
        return "\n".join(lines)
    else:
        u, v = x, y
    lines = []
    if data.stokes is not None:
        hs, ws = data.stokes.shape[-2:]
        if 0 <= v < hs and 0 <= u < ws:
            lines.append(_stokes_lines(data, u, v))
    if data.mueller is not None:
        hm, wm = data.mueller.shape[-2:]
        if 0 <= v < hm and 0 <= u < wm:
            lines.append(_mueller_lines(data, u, v))
    return "\n".join(lines)


def _colour_names(n: int) -> tuple[str, ...]:
    return ("Y",) if n == 1 else ("R", "G", "B")[:n]


def _stokes_lines(data: PolarizationData, u: int, v: int) -> str:
    out = [f"pixel (u={u}, v={v})"]
    for c, name in enumerate(_colour_names(data.stokes.shape[0])):
        s = data.stokes[c, :, v, u]
        why = mask_reason(data, c, v, u)
        if not why and not data.valid[c, v, u]:
            why = "saturated" if data.saturated[c, v, u] else "invalid"
        out.append(f"{name}: S=({s[0]:.1f}, {s[1]:.1f}, {s[2]:.1f}) DN")
        out.append(f"   DoLP {data.dolp[c, v, u]:.3f}  AoLP {data.aolp_deg[c, v, u]:.1f} deg")
        if why:
            out.append(f"   MASKED: {why}")
    return "\n".join(out)


def _mueller_lines(data: PolarizationData, u: int, v: int, mueller: np.ndarray | None = None,
                   where: str = "") -> str:
    """The matrix of ``mueller`` (default ``data.mueller``) at ``(u, v)`` with its mask reason."""
    mueller = data.mueller if mueller is None else mueller
    out = [f"{where or f'Mueller at (u={u}, v={v})'}: m00 in DN per unit S0, then M / m00"]
    same_grid = data.flags is not None and data.flags.shape[-2:] == mueller.shape[-2:]
    for c, name in enumerate(_colour_names(mueller.shape[0])):
        m = mueller[c, :, :, v, u]
        m00 = float(m[0, 0])
        out.append(f"{name}: m00 = {m00:.4g}")
        why = mask_reason(data, c, v, u) if same_grid else ""
        if why:
            out.append(f"   MASKED: {why}")
            continue
        if not (m00 > 0 and np.isfinite(m).all()):
            out.append("   (no valid matrix here)")
            continue
        for r in range(3):
            out.append("   " + "  ".join(f"{m[r, q] / m00:+.3f}" for q in range(3)))
    return "\n".join(out)


def summary(data: PolarizationData) -> dict[str, Any]:
    """Small numbers for the status line: image size and the fraction of valid pixels."""
    if data.stokes is not None:
        return {"size": tuple(int(v) for v in data.stokes.shape[-1:-3:-1]),
                "valid_fraction": float(data.valid.mean()),
                "saturated_fraction": float(data.saturated.mean())}
    if data.mueller is not None:
        return {"size": tuple(int(v) for v in data.mueller.shape[-1:-3:-1])}
    if data.preview_of is not None:
        return {"size": data.preview_of[::-1]}
    return {}
