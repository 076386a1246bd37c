"""Preview images of polarization data: pure functions returning uint8 RGB ``(H, W, 3)`` arrays.

Shared by the CLI (PNG previews) and the GUI. Conventions as in ``docs/conventions.md``:
AoLP in degrees in [0, 180), DoLP in [0, 1]; invalid (masked) pixels are drawn black.

* AoLP as hue, the way the field shows it (e.g. polanalyser's ``applyColorToAoLP``, LUCID
  Arena's ``PolarizedAolp`` colouring): the 180-degree AoLP range maps onto the full hue
  circle (0 deg red, 60 deg green, 120 deg blue), with DoLP as value (default) or saturation.
* DoLP as grey or through an OpenCV colormap; S0 tone-mapped (percentile white point, gamma).
* Mueller elements with a diverging blue-white-red map (colour bar included), and the 3x3
  Mueller grid: ``m00`` tone-mapped, the other elements ``m_ij / m00`` in [-1, 1], each tile
  labelled.
* Legends (DoLP grey bar, AoLP hue bar) appended to the previews.

**Masks.** Every view masks what is not a measurement: a pixel whose signal (``S0`` of a
Stokes image, ``m00`` of a Mueller image) is below ``min_snr`` times its noise standard
deviation (default :data:`DEFAULT_MIN_SNR`, the reference solve's
:data:`polrig.solve.reference.MIN_SNR`) shows background noise as full-scale DoLP or Mueller
speckle, so DoLP, AoLP and ``m_ij / m00`` are drawn black there; so are the pixels a file marks
(saturated, invalid, ill-conditioned, outside the object). The reasons are bit flags
(:data:`MASK_REASONS`, the reference solve's bits plus :data:`BACKGROUND`);
:func:`display_valid` combines them with a signal-to-noise image, and
:func:`exr_masks` reads both from the planes of a Stokes or Mueller EXR.

**Units.** Signal-to-noise from the noise model (:func:`s0_snr`) takes ``S0`` in ADC DN (the
unit of :class:`polrig.sensor.noise.SensorModel`; see ``polrig.app.processing.adc_scale``).
"""

from __future__ import annotations

import pathlib
from collections.abc import Mapping

import cv2
import numpy as np

from polrig.atomic import atomic_write_bytes
from polrig.formats.exr import read_mueller_exr
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import stokes_validity
from polrig.solve.reference import (
    DARK,
    ILL_CONDITIONED,
    MIN_SNR,
    NONFINITE,
    REASONS,
    SATURATED,
)

#: Default signal threshold of every view: ``S0`` (or ``m00``) below this many noise standard
#: deviations is masked (``--min-snr`` of ``polrig stokes``/``infer``; the GUI's "Min SNR").
DEFAULT_MIN_SNR = MIN_SNR
#: Display bit of a pixel outside the object (a single-shot result's object mask,
#: :meth:`polrig.app.single_shot.SingleShotResult.preview_flags`; an older ``polrig infer`` file's
#: ``mask`` plane is 0 there).
BACKGROUND = 16
#: bit -> reason, in bit order: :data:`polrig.solve.reference.REASONS` plus :data:`BACKGROUND`.
MASK_REASONS: dict[int, str] = {**REASONS, BACKGROUND: "background"}

# Diverging map anchors (blue - white - red), sRGB, from ColorBrewer "RdBu" end and mid colours.
_DIVERGING = np.array([[5, 48, 97], [67, 147, 195], [247, 247, 247], [214, 96, 77],
                       [103, 0, 31]], np.float32)


def _mask_black(rgb: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    if valid is not None:
        rgb[~np.asarray(valid, bool)] = 0
    return rgb


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float32)
    return np.clip(np.nan_to_num(x, nan=0.0, posinf=1.0, neginf=0.0), 0, 1)


def aolp_rgb(aolp_deg: np.ndarray, dolp: np.ndarray | None = None, *, dolp_as: str = "value",
             valid: np.ndarray | None = None) -> np.ndarray:
    """AoLP ``(H, W)`` (degrees, [0, 180)) as hue; DoLP (optional) as ``"value"`` or
    ``"saturation"``. Returns uint8 RGB ``(H, W, 3)``."""
    a = np.asarray(aolp_deg, np.float32)
    if a.ndim != 2:
        raise ValueError(f"AoLP image must be 2-D (H, W), got {a.shape}")
    a = np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)
    hue = np.mod(a, 180.0) * (256.0 / 180.0)
    h = np.clip(np.round(hue), 0, 256).astype(np.uint16) % 256
    full = np.full(a.shape, 255, np.uint8)
    if dolp is None:
        s, v = full, full
    else:
        d = np.round(_unit(dolp) * 255).astype(np.uint8)
        if dolp_as == "value":
            s, v = full, d
        elif dolp_as == "saturation":
            s, v = d, full
        else:
            raise ValueError(f"dolp_as must be 'value' or 'saturation', got {dolp_as!r}")
    hsv = np.dstack([h.astype(np.uint8), s, v])
    return _mask_black(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB_FULL), valid)


def dolp_gray(dolp: np.ndarray, *, valid: np.ndarray | None = None) -> np.ndarray:
    """DoLP ``(H, W)`` in [0, 1] as grey levels, uint8 RGB."""
    g = np.round(_unit(dolp) * 255).astype(np.uint8)
    return _mask_black(np.dstack([g, g, g]), valid)


def dolp_colormap(dolp: np.ndarray, *, colormap: int = cv2.COLORMAP_VIRIDIS,
                  valid: np.ndarray | None = None) -> np.ndarray:
    """DoLP ``(H, W)`` in [0, 1] through an OpenCV colormap (default viridis), uint8 RGB."""
    g = np.round(_unit(dolp) * 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(g, colormap), cv2.COLOR_BGR2RGB)
    return _mask_black(rgb, valid)


def tone_map(s0: np.ndarray, *, white_percentile: float = 99.5, gamma: float = 1 / 2.2,
             white: float | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """Linear intensity to uint8 RGB: ``(H, W)`` grey or ``(3, H, W)`` colour planes.

    The white point is ``white`` or the ``white_percentile`` of the finite positive values;
    then ``(x / white) ** gamma``.
    """
    x = np.asarray(s0, np.float32)
    if x.ndim == 3 and x.shape[0] in (1, 3):
        x = np.moveaxis(x, 0, -1)
    elif x.ndim != 2:
        raise ValueError(f"expected (H, W) or (C, H, W) intensities, got {x.shape}")
    x = np.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    if white is None:
        pos = x[x > 0]
        white = float(np.percentile(pos, white_percentile)) if pos.size else 1.0
    y = np.clip(x / max(white, 1e-30), 0, 1) ** gamma
    y = np.round(y * 255).astype(np.uint8)
    if y.ndim == 2:
        y = np.dstack([y, y, y])
    elif y.shape[-1] == 1:
        y = np.repeat(y, 3, axis=-1)
    return _mask_black(np.ascontiguousarray(y), valid)


def diverging(x: np.ndarray, *, vmax: float | None = None,
              valid: np.ndarray | None = None) -> np.ndarray:
    """Signed values ``(H, W)`` with a blue-white-red map over ``[-vmax, vmax]`` (default: the
    largest finite magnitude), uint8 RGB. Blue is negative, white zero, red positive."""
    v = np.asarray(x, np.float32)
    finite = np.isfinite(v)
    if vmax is None:
        vmax = float(np.abs(v[finite]).max()) if finite.any() else 1.0
    vmax = vmax if vmax > 0 else 1.0
    out = np.empty(v.shape + (3,), np.uint8)
    step = max(1, 2 ** 18 // max(1, v.shape[-1])) if v.ndim == 2 else 0
    # in row blocks of (H, W) images: a full-sensor tile's intermediates would be ~400 MB at once
    blocks = [np.s_[y0:y0 + step] for y0 in range(0, v.shape[0], step)] if step else [Ellipsis]
    for b in blocks:
        t = (np.clip(np.where(finite[b], v[b], 0) / vmax, -1, 1) + 1) * 0.5 * (len(_DIVERGING) - 1)
        i = np.minimum(np.floor(t).astype(np.int64), len(_DIVERGING) - 2)
        f = (t - i)[..., None]
        out[b] = np.round(_DIVERGING[i] * (1 - f) + _DIVERGING[i + 1] * f)
    return _mask_black(out, valid)


def _font_scale(height: int) -> float:
    """OpenCV font scale for labels on an image ``height`` pixels tall: readable when the
    image is shown scaled to fit a window (about 1/40 of the height per text line)."""
    return float(np.clip(height / 900.0, 0.4, 3.0))


def _put_label(img: np.ndarray, text: str, org: tuple[int, int], scale: float, *,
               colour=(0, 0, 0), box=None) -> None:
    """Anti-aliased label at ``org`` (bottom-left); ``box`` an RGB behind it (or None)."""
    thick = max(1, int(round(scale * 1.5)))
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    if box is not None:
        x, y = org
        pad = max(1, thick)
        cv2.rectangle(img, (x - pad, y - th - pad), (x + tw + pad, y + base), box, -1)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thick, cv2.LINE_AA)


def colorbar(height: int, *, vmax: float = 1.0, width: int | None = None) -> np.ndarray:
    """A vertical diverging colour bar (``+vmax`` at the top) with three labels, uint8 RGB.

    ``width`` defaults to one that fits the labels at a font scaled with ``height``
    (:func:`_font_scale`), so the labels stay readable when a tall image is shown smaller."""
    scale = _font_scale(height)
    width = int(width or round(40 + 70 * scale))
    ramp = np.linspace(vmax, -vmax, height, dtype=np.float32)[:, None]
    bar = np.full((height, width, 3), 255, np.uint8)
    strip = max(8, width // 3)
    bar[:, :strip] = diverging(np.repeat(ramp, strip, axis=1), vmax=vmax)
    th = int(24 * scale)
    for val, y in ((vmax, th + 2), (0.0, height // 2 + th // 2), (-vmax, height - 4)):
        _put_label(bar, f"{val:+.2g}", (strip + 3, int(np.clip(y, th, height - 2))), scale)
    return bar


def value_bar(height: int, rgb_of, labels: dict[float, str], *, lo: float, hi: float,
              width: int | None = None, title: str = "") -> np.ndarray:
    """A vertical legend: ``rgb_of(values (N, 1))`` -> uint8 RGB ``(N, 1, 3)`` painted from
    ``hi`` (top) to ``lo``; ``labels`` ``{value: text}`` beside it; ``title`` on top."""
    scale = _font_scale(height)
    width = int(width or round(50 + 90 * scale))
    bar = np.full((height, width, 3), 255, np.uint8)
    th = int(24 * scale)
    top = th + 8 if title else 0
    strip = max(8, width // 3)
    ramp = np.linspace(hi, lo, max(1, height - top), dtype=np.float32)[:, None]
    bar[top:, :strip] = np.repeat(rgb_of(ramp), strip, axis=1)
    if title:
        _put_label(bar, title, (2, th + 2), scale * 0.9)
    for val, text in labels.items():
        y = top + (hi - val) / (hi - lo) * (height - top - 1)
        _put_label(bar, text, (strip + 3, int(np.clip(y + th // 2, top + th, height - 2))), scale)
    return bar


def dolp_legend(height: int, *, colormap: int | None = None) -> np.ndarray:
    """Legend of :func:`dolp_gray` (``colormap`` None) or :func:`dolp_colormap`: DoLP 0..1."""
    paint = ((lambda v: dolp_gray(v)) if colormap is None
             else (lambda v: dolp_colormap(v, colormap=colormap)))
    return value_bar(height, paint, {1.0: "1", 0.5: "0.5", 0.0: "0"}, lo=0.0, hi=1.0,
                     title="DoLP")


def aolp_legend(height: int) -> np.ndarray:
    """Legend of :func:`aolp_rgb`: the hue of AoLP 0..180 degrees (full value)."""
    return value_bar(height, lambda v: aolp_rgb(v), {180.0: "180", 135.0: "135", 90.0: "90",
                                                     45.0: "45", 0.0: "0 deg"},
                     lo=0.0, hi=179.9, title="AoLP")


def aolp_wheel(size: int, *, dolp_as: str | None = "value") -> np.ndarray:
    """The colour wheel of :func:`aolp_rgb`, uint8 RGB ``(size, size, 3)``: the direction at
    angle ``a`` from the image's ``+u`` axis towards image up (``docs/conventions.md``) has the
    hue of AoLP ``a`` (mod 180: opposite directions, one axis, one colour), the distance from
    the centre is DoLP 0..1 shown as ``dolp_as`` (``"value"``, ``"saturation"``, or None: hue
    only); white outside the disc, labels at 0, 45, 90 and 135 deg."""
    size = int(size)
    r = (size - 1) / 2.0
    v, u = np.mgrid[:size, :size].astype(np.float32)
    dx, dy = (u - r) / r, (r - v) / r
    a = np.rad2deg(np.arctan2(dy, dx)) % 180.0
    d = np.hypot(dx, dy)
    rgb = aolp_rgb(a, None if dolp_as is None else np.minimum(d, 1.0),
                   dolp_as=dolp_as or "value")
    rgb[d > 1.0] = 255
    scale = max(0.3, size / 400.0)
    for ang in (0, 45, 90, 135):
        t = np.deg2rad(ang)
        x, y = r + 0.78 * r * np.cos(t), r - 0.78 * r * np.sin(t)
        _put_label(rgb, str(ang), (int(x) - int(8 * scale), int(y) + int(6 * scale)), scale,
                   colour=(0, 0, 0), box=(255, 255, 255))
    return rgb


def aolp_key(height: int, *, dolp_as: str | None = "value") -> np.ndarray:
    """The AoLP legend of a preview ``height`` rows tall: the hue bar (:func:`aolp_legend`)
    and the colour wheel (:func:`aolp_wheel`, at most 256 px, at the top, white below)."""
    size = int(min(height, 256))
    wheel = np.full((height, size, 3), 255, np.uint8)
    wheel[:size] = aolp_wheel(size, dolp_as=dolp_as)
    return np.concatenate([aolp_legend(height), wheel], axis=1)


def with_legend(rgb: np.ndarray, legend: np.ndarray) -> np.ndarray:
    """``rgb`` with ``legend`` (same height) appended on the right."""
    return np.ascontiguousarray(np.concatenate([rgb, legend], axis=1))


def upscale(rgb: np.ndarray, min_px: int) -> np.ndarray:
    """``rgb`` enlarged by an integer factor (nearest neighbour, pixels stay pixels) until its
    short side is at least ``min_px`` (a 64x64 superpixel result gets labels that fit)."""
    f = int(np.ceil(min_px / max(1, min(rgb.shape[:2]))))
    return rgb if f <= 1 else np.repeat(np.repeat(rgb, f, axis=0), f, axis=1)


#: Labels of the 3x3 grid tiles (``m00`` itself, the others normalised by it).
GRID_LABELS = tuple(tuple("m00" if r == c == 0 else f"m{r}{c}/m00" for c in range(3))
                    for r in range(3))


def mueller_grid(mueller: np.ndarray, *, colour: int | None = None, border_px: int = 2,
                 valid: np.ndarray | None = None, with_colorbar: bool = True,
                 labels: bool = True, min_tile_px: int = 0) -> np.ndarray:
    """The 3x3 Mueller images as one uint8 RGB image.

    ``mueller``: ``(C, 3, 3, H, W)`` or ``(3, 3, H, W)``; ``colour`` picks a colour plane
    (default: the mean over colours). ``m00`` is tone-mapped grey (black where not finite and
    positive); every other element is shown as ``m_ij / m00`` with :func:`diverging` over
    [-1, 1], black where ``m00 <= 0`` or ``valid`` (``(H, W)`` bool) is False (a masked pixel:
    too little signal, saturated, ...), followed by a colour bar. ``labels`` writes
    :data:`GRID_LABELS` into the tiles' top-left corners (tiles of at least 24 pixels);
    ``min_tile_px`` enlarges small tiles (nearest neighbour) to at least that many pixels.
    """
    m = np.asarray(mueller, np.float32)
    if m.ndim == 5:
        m = m.mean(axis=0) if colour is None else m[colour]
    if m.ndim != 4 or m.shape[:2] != (3, 3):
        raise ValueError(f"expected (C, 3, 3, H, W) or (3, 3, H, W) Mueller images, got "
                         f"{np.asarray(mueller).shape}")
    m00 = m[0, 0]
    positive = np.isfinite(m00) & (m00 > 0)
    ok = positive if valid is None else positive & np.asarray(valid, bool)
    tiles = []
    with np.errstate(all="ignore"):
        for r in range(3):
            row = []
            for c in range(3):
                if r == c == 0:
                    row.append(upscale(tone_map(m00, valid=positive), min_tile_px))
                else:
                    row.append(upscale(diverging(np.where(ok, m[r, c] / m00, 0), vmax=1.0,
                                                 valid=ok), min_tile_px))
            tiles.append(row)
    h, w = tiles[0][0].shape[:2]
    b = border_px
    grid = np.full((3 * h + 4 * b, 3 * w + 4 * b, 3), 255, np.uint8)
    scale = float(np.clip(h / 300.0, 0.35, 3.0))
    for r in range(3):
        for c in range(3):
            y, x = b + r * (h + b), b + c * (w + b)
            grid[y:y + h, x:x + w] = tiles[r][c]
            if labels and min(h, w) >= 24:
                pad = max(2, int(4 * scale))
                _put_label(grid, GRID_LABELS[r][c], (x + pad, y + pad + int(22 * scale)), scale,
                           colour=(255, 255, 255), box=(40, 40, 40))
    if with_colorbar:
        grid = np.concatenate([grid, colorbar(grid.shape[0], vmax=1.0)], axis=1)
    return grid


# -- masks -------------------------------------------------------------------------------------
def s0_snr(s0_adc_dn: np.ndarray, model: SensorModel | None = None,
           exposure_us: float = 0.0) -> np.ndarray:
    """``S0 / sigma(S0)`` per pixel for black-subtracted ``S0`` in ADC DN (any shape).

    Ideal analyzers: ``S0 = (I0 + I45 + I90 + I135) / 2``, so
    ``var(S0) = sum_j var(I_j) / 4``; the noise model's variance is linear in the signal
    (``var(I) = I / g + c``, :meth:`SensorModel.variance_dn2`) and ``sum_j I_j = 2 S0``, hence
    ``var(S0) = var_model(S0 / 2)`` whatever the polarization. Demosaic interpolation averages
    neighbours and lowers the true variance, so this sigma errs on the side of masking.
    Non-finite ``S0`` gives NaN."""
    model = model or SensorModel()
    s0 = np.asarray(s0_adc_dn, np.float32)  # float32 in and out: several times faster than float64
    finite = np.isfinite(s0)
    per_dn, offset = model.variance_terms(exposure_us)
    # var(S0) = var_model(S0 / 2) = max(S0 / 2, 0) per_dn + offset, evaluated in float32
    var = np.maximum(np.where(finite, s0, np.float32(0.0)), np.float32(0.0))
    var *= np.float32(0.5 * per_dn)
    var += np.float32(offset)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = s0 / np.sqrt(var, out=var)
    return np.where(finite, snr, np.float32(np.nan))


def display_valid(flags: np.ndarray | None, snr: np.ndarray | None,
                  min_snr: float = DEFAULT_MIN_SNR) -> np.ndarray | None:
    """True where a pixel is shown: no reason bit set and ``snr >= min_snr``.

    ``flags``: :data:`MASK_REASONS` bits (any shape; None: none set). ``snr``: signal over its
    noise sigma (same shape; None or NaN: unknown). Where the SNR is known it decides
    darkness (the file's :data:`~polrig.solve.reference.DARK` bit, set at another threshold, is
    ignored); where it is unknown the ``DARK`` bit stands. None when both are None."""
    if flags is None and snr is None:
        return None
    dark = _dark(flags, snr, min_snr)
    other = 0 if flags is None else (np.asarray(flags, np.uint8) & np.uint8(~DARK & 0xFF))
    return ~dark & (other == 0)


def _dark(flags, snr, min_snr) -> np.ndarray:
    file_dark = (np.zeros((), bool) if flags is None
                 else (np.asarray(flags, np.uint8) & DARK) > 0)
    if snr is None:
        return np.asarray(file_dark)
    x = np.asarray(snr, np.float32)
    with np.errstate(invalid="ignore"):
        return np.where(np.isnan(x), file_dark, ~(x >= min_snr))


def display_flags(flags: np.ndarray | None, snr: np.ndarray | None,
                  min_snr: float = DEFAULT_MIN_SNR) -> np.ndarray | None:
    """The reason bits a view shows: ``flags`` with ``DARK`` set from ``snr < min_snr`` where
    the SNR is known (see :func:`display_valid`)."""
    if flags is None and snr is None:
        return None
    dark = _dark(flags, snr, min_snr)
    base = (np.zeros(np.shape(snr), np.uint8) if flags is None
            else np.asarray(flags, np.uint8) & np.uint8(~DARK & 0xFF))
    return base | np.where(dark, np.uint8(DARK), np.uint8(0))  # uint8 throughout (no int64 image)


def reason_text(code: int, snr: float | None = None, min_snr: float = DEFAULT_MIN_SNR) -> str:
    """Why a pixel is masked, in words ("" when it is not): e.g. ``"dark (SNR 1.2 < 3)"``,
    ``"saturated"``, ``"background, saturated"``."""
    words = []
    for bit, name in MASK_REASONS.items():
        if int(code) & bit:
            if bit == DARK and snr is not None and np.isfinite(snr):
                name = f"dark (SNR {snr:.1f} < {min_snr:g})"
            words.append(name.replace("_", "-"))
    return ", ".join(words)


def _colour_stack(planes: Mapping[str, np.ndarray], prefix: str, n: int) -> np.ndarray | None:
    names = ("Y",) if n == 1 else ("R", "G", "B")[:n]
    got = [planes.get(f"{prefix}.{s}") for s in names]
    return None if any(g is None for g in got) else np.stack([np.asarray(g) for g in got])


def exr_masks(planes: Mapping[str, np.ndarray], n_colours: int, signal: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray | None]:
    """``(flags, snr)`` ``(C, H, W)`` of a result EXR from its extra planes.

    ``signal`` ``(C, H, W)``: ``S0`` of a Stokes EXR or ``m00`` of a Mueller EXR. Read:
    ``mask.{colour}`` (a reconstruction's reason bits: a session's or ``polrig infer``'s),
    ``mask`` (a ``polrig infer`` file written before the one result writer: 0 = outside the
    object, :data:`BACKGROUND`), ``saturated`` (clipped raw data, ``SATURATED``),
    ``valid`` (a Stokes EXR: 0 = saturated or invalid in some colour; ``NONFINITE`` where no
    ``saturated`` plane says why), and non-finite or non-positive signal (``NONFINITE``).
    The SNR comes from ``snr.{colour}`` planes, else ``signal / sigma_noise.M00.{colour}``
    where that sigma is positive (a reference solve's noise-only sigma), else it is NaN
    (unknown: the file's ``DARK`` bit stands)."""
    sig = np.asarray(signal, np.float32)
    c = n_colours
    flags = np.zeros(sig.shape, np.uint8)
    bits = _colour_stack(planes, "mask", c)
    if bits is not None:
        flags |= np.nan_to_num(bits, nan=NONFINITE).astype(np.uint8)
    elif "mask" in planes:
        flags |= np.where(np.asarray(planes["mask"]) > 0, 0, BACKGROUND).astype(np.uint8)[None]
    sat = np.asarray(planes["saturated"]) > 0 if "saturated" in planes else None
    if sat is not None:
        flags |= np.where(sat, SATURATED, 0).astype(np.uint8)[None]
    if "valid" in planes:
        bad = ~(np.asarray(planes["valid"]) > 0)
        if sat is not None:
            bad &= ~sat
        flags |= np.where(bad, NONFINITE, 0).astype(np.uint8)[None]
    with np.errstate(invalid="ignore"):
        flags |= np.where(np.isfinite(sig) & (sig > 0), 0, NONFINITE).astype(np.uint8)
    snr = _colour_stack(planes, "snr", c)
    if snr is None:
        sigma = _colour_stack(planes, "sigma_noise.M00", c)
        if sigma is not None:
            with np.errstate(all="ignore"):
                snr = np.where(np.isfinite(sigma) & (sigma > 0), sig / sigma, np.nan)
    return flags, None if snr is None else np.asarray(snr, np.float32)


def stokes_exr_masks(stokes: np.ndarray, planes: Mapping[str, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``(stokes, valid, flags, snr)`` of a Stokes EXR's images ``(C, 3, H, W)`` and its other
    ``planes``: the Stokes images with non-finite values set to 0, ``valid`` ``(C, H, W)``
    (:func:`polrig.sensor.stokes.stokes_validity` and no reason bit set), and
    :func:`exr_masks`' ``flags`` and ``snr``. The Viewer and ``polrig stats`` read a Stokes EXR
    through this."""
    raw = np.asarray(stokes, np.float32)
    s = np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
    flags, snr = exr_masks(planes or {}, s.shape[0], s[:, 0])
    valid = stokes_validity(raw) & (flags == 0)
    return s, valid, flags, snr


def mask_summary(flags: np.ndarray | None, snr: np.ndarray | None,
                 min_snr: float = DEFAULT_MIN_SNR) -> str:
    """One phrase for a summary line: ``"masked 1204 of 4096 pixels (dark 1100 below SNR 3,
    saturated 104)"``; a pixel counts once however many colours and reasons it has."""
    f = display_flags(flags, snr, min_snr)
    if f is None:
        return "masked 0 pixels"
    f = np.asarray(f)
    per_pixel = np.bitwise_or.reduce(f, axis=0) if f.ndim == 3 else f
    n, total = int((per_pixel != 0).sum()), per_pixel.size
    parts = []
    for bit, name in MASK_REASONS.items():
        k = int(((per_pixel & bit) > 0).sum())
        if k:
            parts.append(f"{name.replace('_', '-')} {k}" + (f" below SNR {min_snr:g}"
                                                             if bit == DARK else ""))
    return f"masked {n} of {total} pixels" + (f" ({', '.join(parts)})" if parts else "")


# -- result previews ---------------------------------------------------------------------------
#: Shortest side of a preview's tiles (pixels; small results are enlarged, nearest neighbour).
PREVIEW_MIN_PX = 256


def polarizance(mueller: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dolp, aolp_deg)`` ``(C, H, W)`` of a Mueller image ``(C, 3, 3, H, W)``: of its first
    column, the Stokes vector it turns unpolarized light into (polarizance,
    ``sqrt(m10^2 + m20^2) / m00`` and ``atan2(m20, m10) / 2`` in [0, 180) degrees)."""
    m = np.asarray(np.asarray(mueller)[:, :, 0], np.float64)  # the first column only: (C, 3, H, W)
    with np.errstate(all="ignore"):
        d = np.hypot(m[:, 1], m[:, 2]) / m[:, 0]
        a = np.mod(np.degrees(0.5 * np.arctan2(m[:, 2], m[:, 1])), 180.0)
    ok = np.isfinite(d) & (m[:, 0] > 0)
    return (np.where(ok, np.clip(d, 0, 1), 0).astype(np.float32),
            np.where(ok, a, 0).astype(np.float32))


#: Largest preview tile side, pixels: larger results are previewed every ``k``-th pixel
#: (:func:`preview_stride`), so a full-sensor preview costs a fraction of a second, not seconds.
PREVIEW_MAX_PX = 1024


def preview_stride(shape: tuple[int, int], max_px: int = PREVIEW_MAX_PX) -> int:
    """The pixel step ``k`` that brings an ``(H, W)`` image within ``max_px`` on its longer
    side (nearest-neighbour decimation of the previews; 1 for images already that small)."""
    return max(1, -(-max(shape) // int(max_px)))


#: The previews :func:`write_result_previews` writes beside a result, ``<stem><suffix>``: the 3x3
#: grid, the polarizance's DoLP and AoLP.
RESULT_PREVIEW_SUFFIXES = ("_grid.png", "_dolp.png", "_aolp.png")


def write_result_previews(source, out_dir, *, stem: str | None = None,
                          min_snr: float = DEFAULT_MIN_SNR, flags: np.ndarray | None = None,
                          snr: np.ndarray | None = None,
                          max_px: int = PREVIEW_MAX_PX) -> list[pathlib.Path]:
    """PNG previews next to a Mueller result: ``<stem>_grid.png`` (the 3x3 grid, tiles
    labelled, colour bar), ``<stem>_dolp.png`` and ``<stem>_aolp.png`` (polarizance, with
    their legends). Returns the paths written.

    ``source``: a Mueller EXR path (its mask, saturated, sigma and snr planes give the masks,
    :func:`exr_masks`; ``stem`` defaults to the file's), or a Mueller array
    ``(C, 3, 3, H, W)`` with optional ``flags``/``snr`` ``(C, H, W)`` (``stem`` defaults to
    ``"mueller"``). Pixels masked in the green (or only) colour at ``min_snr`` are black.
    Images larger than ``max_px`` on a side are previewed every :func:`preview_stride`-th
    pixel (a full-sensor result in a fraction of a second, tiles of at most ``max_px``).
    Files are replaced atomically (:func:`polrig.atomic.atomic_write_bytes`)."""

    if isinstance(source, (str, pathlib.Path)):
        img = read_mueller_exr(source)
        mueller = img.mueller
        flags, snr = exr_masks(img.extra, mueller.shape[0], mueller[:, 0, 0])
        stem = stem or pathlib.Path(source).stem
    else:
        mueller = np.asarray(source, np.float32)
        if mueller.ndim == 4:
            mueller = mueller[None]
        stem = stem or "mueller"
    if mueller.ndim != 5 or mueller.shape[1:3] != (3, 3):
        raise ValueError(f"expected a (C, 3, 3, H, W) Mueller image, got {mueller.shape}")
    k = preview_stride(mueller.shape[-2:], max_px)
    if k > 1:
        mueller = mueller[..., ::k, ::k]
        flags = None if flags is None else np.asarray(flags)[..., ::k, ::k]
        snr = None if snr is None else np.asarray(snr)[..., ::k, ::k]
    ci = 0 if mueller.shape[0] == 1 else 1  # green: the best-sampled Bayer colour
    valid = display_valid(None if flags is None else np.asarray(flags)[ci],
                          None if snr is None else np.asarray(snr)[ci], min_snr)
    out_dir = pathlib.Path(out_dir)
    grid = mueller_grid(mueller, colour=ci, valid=valid, min_tile_px=PREVIEW_MIN_PX)
    d, a = polarizance(mueller[ci:ci + 1])
    dolp_img = upscale(dolp_gray(d[0], valid=valid), PREVIEW_MIN_PX)
    aolp_img = upscale(aolp_rgb(a[0], d[0], valid=valid), PREVIEW_MIN_PX)
    images = dict(zip((stem + sfx for sfx in RESULT_PREVIEW_SUFFIXES),
                      (grid, with_legend(dolp_img, dolp_legend(dolp_img.shape[0])),
                       with_legend(aolp_img, aolp_legend(aolp_img.shape[0])))))
    written = []
    for name, rgb in images.items():
        path = out_dir / name
        atomic_write_bytes(path, png_bytes(rgb))
        written.append(path)
    return written


def png_bytes(rgb: np.ndarray) -> bytes:
    """uint8 RGB ``(H, W, 3)`` as PNG file bytes."""
    ok, enc = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB image
        raise OSError("could not encode a PNG preview")
    return enc.tobytes()
