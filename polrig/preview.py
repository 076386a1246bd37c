"""Preview images of polarization data: pure functions returning uint8 RGB ``(H, W, 3)`` arrays.

Shared by the CLI (PNG previews) and the GUI. Conventions as in ``docs/conventions.md``:
AoLP in degrees in [0, 180), DoLP in [0, 1]; invalid (masked) pixels are drawn black.

* AoLP as hue, the way the field shows it (e.g. polanalyser's ``applyColorToAoLP``, LUCID
  Arena's ``PolarizedAolp`` colouring): the 180-degree AoLP range maps onto the full hue
  circle (0 deg red, 60 deg green, 120 deg blue), with DoLP as value (default) or saturation.
* DoLP as grey or through an OpenCV colormap; S0 tone-mapped (percentile white point, gamma).
* Mueller elements with a diverging blue-white-red map (colour bar included), and the 3x3
  Mueller grid: ``m00`` tone-mapped, the other elements ``m_ij / m00`` in [-1, 1].
"""

from __future__ import annotations

import cv2
import numpy as np

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
    t = (np.clip(np.where(finite, v, 0) / vmax, -1, 1) + 1) * 0.5 * (len(_DIVERGING) - 1)
    i = np.minimum(np.floor(t).astype(np.int64), len(_DIVERGING) - 2)
    f = (t - i)[..., None]
    rgb = _DIVERGING[i] * (1 - f) + _DIVERGING[i + 1] * f
    return _mask_black(np.round(rgb).astype(np.uint8), valid)


def colorbar(height: int, *, vmax: float = 1.0, width: int = 64) -> np.ndarray:
    """A vertical diverging colour bar (``+vmax`` at the top) with three labels, uint8 RGB."""
    ramp = np.linspace(vmax, -vmax, height, dtype=np.float32)[:, None]
    bar = np.full((height, width, 3), 255, np.uint8)
    strip = max(8, width // 3)
    bar[:, :strip] = diverging(np.repeat(ramp, strip, axis=1), vmax=vmax)
    scale = max(0.3, min(0.5, height / 400))
    for val, y in ((vmax, 12), (0.0, height // 2 + 4), (-vmax, height - 4)):
        cv2.putText(bar, f"{val:+.2g}", (strip + 2, int(np.clip(y, 10, height - 2))),
                    cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return bar


def mueller_grid(mueller: np.ndarray, *, colour: int | None = None, border_px: int = 2,
                 valid: np.ndarray | None = None, with_colorbar: bool = True) -> np.ndarray:
    """The 3x3 Mueller images as one uint8 RGB image.

    ``mueller``: ``(C, 3, 3, H, W)`` or ``(3, 3, H, W)``; ``colour`` picks a colour plane
    (default: the mean over colours). ``m00`` is tone-mapped grey; every other element is shown
    as ``m_ij / m00`` with :func:`diverging` over [-1, 1] (pixels with ``m00 <= 0`` black),
    followed by a colour bar.
    """
    m = np.asarray(mueller, np.float32)
    if m.ndim == 5:
        m = m.mean(axis=0) if colour is None else m[colour]
    if m.ndim != 4 or m.shape[:2] != (3, 3):
        raise ValueError(f"expected (C, 3, 3, H, W) or (3, 3, H, W) Mueller images, got "
                         f"{np.asarray(mueller).shape}")
    h, w = m.shape[2:]
    m00 = m[0, 0]
    ok = np.isfinite(m00) & (m00 > 0)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    tiles = []
    with np.errstate(all="ignore"):
        for r in range(3):
            row = []
            for c in range(3):
                if r == c == 0:
                    row.append(tone_map(m00, valid=ok))
                else:
                    row.append(diverging(np.where(ok, m[r, c] / m00, 0), vmax=1.0, valid=ok))
            tiles.append(row)
    b = border_px
    grid = np.full((3 * h + 4 * b, 3 * w + 4 * b, 3), 255, np.uint8)
    for r in range(3):
        for c in range(3):
            y, x = b + r * (h + b), b + c * (w + b)
            grid[y:y + h, x:x + w] = tiles[r][c]
    if with_colorbar:
        grid = np.concatenate([grid, colorbar(grid.shape[0], vmax=1.0)], axis=1)
    return grid
