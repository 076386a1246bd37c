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

import numpy as np

from polrig.app import preview
from polrig.app.single_shot import SingleShotResult
from polrig.sensor.analyzer import layout_name_at, resolve_layout
from polrig.sensor.frame import Frame
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import (
    StokesImages,
    aolp_deg,
    dolp,
    stokes_from_raw,
    stokes_validity,
)

#: Display modes (key -> label shown in the GUI).
DISPLAYS: dict[str, str] = {
    "raw": "Raw mosaic",
    "s0": "S0 (intensity)",
    "dolp": "DoLP",
    "aolp": "AoLP (hue)",
    "aolp_dolp": "AoLP weighted by DoLP",
    "mueller": "Mueller 3x3",
}
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
    _views: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def n_colours(self) -> int:
        for a in (self.stokes, self.mueller):
            if a is not None:
                return int(a.shape[0])
        return 1

    def available(self) -> list[str]:
        """The display modes this data can show (keys of :data:`DISPLAYS`)."""
        out = []
        if self.raw is not None:
            out.append("raw")
        if self.stokes is not None or self.mueller is not None:
            out.append("s0")
        if self.stokes is not None:
            out += ["dolp", "aolp", "aolp_dolp"]
        if self.mueller is not None:
            out.append("mueller")
        return out

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
        s = np.nan_to_num(np.asarray(stokes, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        valid = stokes_validity(np.asarray(stokes, np.float32))
        flags, snr = preview.exr_masks(planes or {}, s.shape[0], s[:, 0])
        saturated = (flags & preview.SATURATED) > 0
        valid &= flags == 0
        return cls(stokes=s, valid=valid, saturated=saturated, dolp=dolp(s, valid),
                   aolp_deg=aolp_deg(s, valid), source=source, flags=flags, snr=snr)

    @classmethod
    def from_single_shot(cls, result: SingleShotResult, frame: Frame | None = None,
                         source: str = "") -> "PolarizationData":
        """From a single-shot result of a raw frame
        (:meth:`polrig.app.single_shot.SingleShot.frame`): its Mueller image, the measured Stokes
        images on the same grid (the raw size at full resolution) with their masks, the SNR of
        their ``S0`` (the result's, from the camera's noise model) and ``BACKGROUND`` outside the
        networks' object mask; with the ``frame``, its raw mosaic."""
        d = cls.from_stokes(result.stokes, source)
        d.mueller = result.mueller
        if frame is not None:
            d.raw, d.bit_depth = frame.raw, int(frame.meta.bit_depth)
            d.black_level_dn = float(frame.meta.black_level_dn)
        d.snr = result.snr
        d.flags = d.flags | np.where(result.object, 0, preview.BACKGROUND).astype(np.uint8)[None]
        return d

    @classmethod
    def from_mueller(cls, mueller: np.ndarray, source: str = "",
                     planes: dict | None = None) -> "PolarizationData":
        """From a Mueller image ``(C, 3, 3, H, W)``; ``planes`` (the EXR's other planes) give
        its masks and SNR (:func:`polrig.app.preview.exr_masks`)."""
        m = np.asarray(mueller, np.float32)
        flags, snr = preview.exr_masks(planes or {}, m.shape[0], m[:, 0, 0])
        return cls(mueller=m, source=source, flags=flags, snr=snr)


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
    src = data.stokes if data.stokes is not None else data.mueller
    return tuple(src.shape[-2:])  # type: ignore[return-value]


def display_step(data: PolarizationData, display: str, max_px: int) -> int:
    """Decimation step so that the displayed image has at most ``max_px`` pixels on its long
    side (0: no limit); for the Mueller grid, its three tiles side by side (borders and colour
    bar aside). A screen shows no more pixels than it has; the data (and the cursor readout,
    :func:`readout` with the same ``step``) stay at full resolution. At full sensor resolution
    the grid is 7344 pixels wide: rendering it whole took 2.8 s a frame on 16 cores
    (``benchmarks/results/live_mueller_h200.md``), decimated to 1024 a few milliseconds."""
    if max_px <= 0:
        return 1
    long_side = max(display_shape(data, display)) * (3 if display == "mueller" else 1)
    return max(1, -(-long_side // int(max_px)))


def render(data: PolarizationData, display: str, colour: int = LUMINANCE, *,
           saturation_overlay: bool = False, step: int = 1) -> np.ndarray:
    """The uint8 RGB image ``(H, W, 3)`` of ``display`` (a key of :data:`DISPLAYS`).

    S0 of the luminance choice is the RGB composite of a colour sensor; saturated pixels are
    painted :data:`SATURATION_RGB` when ``saturation_overlay`` is set. ``step`` > 1 shows every
    ``step``-th pixel in each direction (see :func:`display_step`; for the Mueller grid, in each
    tile).
    """
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
        return preview.mueller_grid(data.mueller[..., k, k], colour=None if colour == LUMINANCE else
                                    min(colour, data.mueller.shape[0] - 1),
                                    border_px=GRID_BORDER_PX, valid=None if ok is None else ok[k, k])
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
            rgb = preview.aolp_rgb(a, d, valid=valid)
        if saturation_overlay:
            sat = data.saturated[:, k, k].any(axis=0)
    if sat is not None and sat.any():
        rgb[sat] = SATURATION_RGB
    return rgb


def histogram(data: PolarizationData, display: str, colour: int = LUMINANCE,
              bins: int = 64, step: int = 1) -> tuple[np.ndarray, np.ndarray, str]:
    """``(counts, edges, label)`` of the quantity a display shows (valid pixels only):
    raw DN, S0 DN, DoLP in [0, 1] or AoLP in degrees [0, 180). The Mueller grid shows the
    histogram of ``m00``. ``step`` > 1 counts every ``step``-th pixel in each direction."""
    k = slice(None, None, max(1, int(step)))
    if display == "raw":
        x = data.raw[k, k].reshape(-1)
        rng = (0.0, float(2 ** int(data.bit_depth)))
        label = "raw DN"
    elif display in ("s0", "mueller") and (data.stokes is None or display == "mueller"):
        x = _pick(data.mueller[:, 0, 0], colour).reshape(-1)
        x = x[np.isfinite(x) & (x > 0)]
        rng = (0.0, float(x.max()) if x.size else 1.0)
        label = "m00 (DN per unit S0)"
    else:
        s0, d, a, valid = (v[k, k] for v in channel_view(data, colour))
        ok = shown(data, colour)
        if ok is not None and display != "s0":
            valid = valid & ok[k, k]
        q = {"s0": s0, "dolp": d}.get(display, a)
        x = q[valid]
        rng = {"dolp": (0.0, 1.0), "aolp": (0.0, 180.0), "aolp_dolp": (0.0, 180.0)}.get(
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


def readout(data: PolarizationData, display: str, x: int, y: int, step: int = 1) -> str:
    """Text of the values under the cursor at display pixel ``(x, y)`` of an image rendered with
    ``step`` (:func:`render`): Stokes, DoLP, AoLP per colour, and the 3x3 Mueller matrix
    (normalised by ``m00`` too) where there is one."""
    k = max(1, int(step))
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


def _mueller_lines(data: PolarizationData, u: int, v: int) -> str:
    mueller = data.mueller
    out = [f"Mueller at (u={u}, v={v}): m00 in DN per unit S0, then M / m00"]
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
    return {}
