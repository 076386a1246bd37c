"""Demosaic a DoFP raw mosaic into analyzer images ``(C, 4, H', W')`` (float32, DN).

Analyzer order is 0, 45, 90, 135 deg and angles follow ``docs/conventions.md``. The mosaic
layout is data (:class:`polrig.sensor.layouts.MosaicLayout`, any ROI phase): every method works on
the layout's ``(colour, angle)`` pixel classes, never on a hard-coded pattern.

Methods (speed/accuracy choice):

``superpixel``
    No interpolation. Each period cell of the layout (2x2 mono, 4x4 colour) gives one output
    pixel whose analyzer value is the mean of the cell's pixels of that colour and angle.
    Output size ``H' = H // ph``, ``W' = W // pw`` (a partial last cell is dropped): half
    resolution for the 2x2 mono cell, a quarter for the 4x4 colour cell.
``bilinear``
    Full resolution (``H' = H``, ``W' = W``). Each class plane is interpolated by normalised
    convolution with a separable tent of half-width equal to the layout period; for a
    rectangular class lattice (every mono class, R and B of the colour sensor) this is exactly
    bilinear interpolation on that lattice; G of the colour sensor (two samples per 4x4 cell)
    gets the tent-weighted mean of its neighbours.
``newton``
    Full resolution. Newton polynomial interpolation with the polarization difference model and
    edge classifier of N. Li, Y. Zhao, Q. Pan, S. G. Kong, "Demosaicking DoFP images using
    Newton's polynomial interpolation and polarization difference model", Opt. Express
    27(2):1376-1391 (2019): stage one estimates the horizontal and vertical neighbours' channels
    with the 1-D kernel ``[1/16, -1/4, 7/16, 1/2, 7/16, -1/4, 1/16]`` (their Eqs. 14-17: a
    cubic Newton interpolation of the other channel plus the own channel's second difference)
    and the diagonal channel along both diagonals, fused by the edge classifier (threshold
    ``tau = 5.8`` on the ratio of the summed polarization differences over the 3x3 same-channel
    neighbourhood, as in the authors' published MATLAB implementation; otherwise weighted by the
    inverse directional gradients); stage two re-estimates the horizontal/vertical channels
    along the other axis from the stage-one diagonal plane and fuses them the same way. It needs
    an angle pattern of period 2x2 (the Sony layouts at any phase). For a colour layout the
    Bayer step comes first: each colour's mosaic is completed at every pixel, keeping that
    pixel's analyzer angle, by the ``bilinear`` interpolation of the same colour-and-angle
    samples; then the polarization step (Newton) runs per colour.

Pre-processing: ``black_level_dn`` (scalar) and ``dark`` (a dark frame ``(H, W)`` in DN,
already black-level free or not: it is simply subtracted) are removed before interpolation.
Non-finite input values stay non-finite in the outputs that use them (local support only);
:mod:`polrig.sensor.stokes` masks them.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading

import cv2
import numpy as np

from polrig.choices import DEMOSAIC_METHODS
from polrig.sensor.layouts import ANALYZER_ANGLES_DEG, MosaicLayout

METHODS = DEMOSAIC_METHODS  # defined in polrig.choices (the command line's start-up vocabulary)
_BORDER = cv2.BORDER_REFLECT_101

#: Newton 1-D kernel taps at offsets -3..3 (Li et al. 2019, Eqs. 14-17 simplified).
NEWTON_TAPS = np.array([1 / 16, -1 / 4, 7 / 16, 1 / 2, 7 / 16, -1 / 4, 1 / 16], np.float32)
NEWTON_TAU = 5.8


def preprocess(raw: np.ndarray, *, black_level_dn: float = 0.0,
               dark: np.ndarray | None = None) -> np.ndarray:
    """The raw mosaic as float32 DN with black level and dark frame removed (a new array)."""
    raw = _mosaic(raw)
    with np.errstate(over="ignore", invalid="ignore"):
        x = raw.astype(np.float32, copy=True)
    if dark is not None:
        dark = np.asarray(dark, dtype=np.float32)
        if dark.shape != raw.shape:
            raise ValueError(f"dark frame shape {dark.shape} differs from raw {raw.shape}")
        x -= dark
    if black_level_dn:
        x -= np.float32(black_level_dn)
    return x


def _mosaic(raw) -> np.ndarray:
    """``raw`` as an array, ValueError unless it is 2-D ``(H, W)``."""
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"raw mosaic must be 2-D (H, W), got shape {raw.shape}")
    return raw


def output_shape(layout: MosaicLayout, shape: tuple[int, int], method: str) -> tuple[int, int]:
    """Spatial size ``(H', W')`` of :func:`demosaic`'s output for a raw of ``shape``."""
    _check_method(method)
    if method == "superpixel":
        ph, pw = layout.period
        return shape[0] // ph, shape[1] // pw
    return tuple(shape)  # type: ignore[return-value]


def check_mosaic_shape(layout: MosaicLayout, shape: tuple[int, int]) -> None:
    """``ValueError`` unless a raw mosaic of ``shape`` holds at least one layout cell."""
    ph, pw = layout.period
    if len(shape) != 2 or shape[0] < ph or shape[1] < pw:
        raise ValueError(f"raw mosaic {tuple(shape)} is smaller than one {ph}x{pw} layout cell")


def support_radius(layout: MosaicLayout, method: str) -> tuple[int, int]:
    """``(rows, cols)``: how far (in raw pixels) the full-resolution output at a pixel reaches
    into the mosaic (``0`` for ``superpixel``, whose output pixel is exactly its cell).

    ``bilinear``: the tent of half-width equal to the period reaches ``period - 1``;
    ``newton``: :data:`NEWTON_RADIUS`, plus the ``bilinear`` Bayer step of a colour layout.
    """
    _check_method(method)
    ph, pw = layout.period
    if method == "superpixel":
        return 0, 0
    if method == "bilinear":
        return ph - 1, pw - 1
    bayer = (ph - 1, pw - 1) if layout.n_colours > 1 else (0, 0)
    return NEWTON_RADIUS + bayer[0], NEWTON_RADIUS + bayer[1]


def halo_rows(layout: MosaicLayout, method: str) -> int:
    """Rows of context a band of full-resolution output rows needs above and below it for
    :func:`demosaic_float` of the band to equal the rows of the whole image's demosaic: the
    row :func:`support_radius` rounded up to a whole number of layout periods (a band that
    starts on a period boundary sees the layout at its own phase). 0 for ``superpixel``."""
    r = support_radius(layout, method)[0]
    ph = layout.period[0]
    return -(-r // ph) * ph


def row_bands(layout: MosaicLayout, shape: tuple[int, int], method: str, band_rows: int
              ) -> list[tuple[int, int, int, int]]:
    """Row bands for demosaicing a mosaic of ``shape`` piecewise: ``(o0, o1, e0, e1)`` with
    output rows ``o0:o1`` (of :func:`output_shape`) computed exactly from the mosaic rows
    ``e0:e1`` -- they are rows ``o0 - e0 // ph : ...`` (``superpixel``, ``ph`` the layout's row
    period) or ``o0 - e0 : o1 - e0`` (full-resolution methods) of ``demosaic_float(x[e0:e1])``.

    ``band_rows``: output rows per band (rounded up to a whole number of periods for the
    full-resolution methods, so that every band starts at the layout's phase).
    """
    check_mosaic_shape(layout, shape)
    ph = layout.period[0]
    h_out = output_shape(layout, shape, method)[0]
    step = max(1, int(band_rows))
    if method == "superpixel":
        return [(o0, min(h_out, o0 + step), o0 * ph, min(h_out, o0 + step) * ph)
                for o0 in range(0, h_out, step)]
    step = -(-step // ph) * ph
    halo = halo_rows(layout, method)
    return [(o0, min(h_out, o0 + step), max(0, o0 - halo), min(h_out, o0 + step + halo))
            for o0 in range(0, h_out, step)]


def demosaic(raw: np.ndarray, layout: MosaicLayout, method: str = "superpixel", *,
             black_level_dn: float = 0.0, dark: np.ndarray | None = None) -> np.ndarray:
    """Analyzer images ``(C, 4, H', W')`` float32 (DN) of a raw mosaic ``(H, W)``.

    See the module docstring for the methods and output sizes (:func:`output_shape`).
    """
    _check_method(method)
    if method == "superpixel" and dark is None:
        # a cell's mean is taken straight from the raw samples and the black level removed from
        # the mean: no float copy of the whole mosaic (the same numbers for integer raw data)
        raw = _mosaic(raw)
        check_mosaic_shape(layout, raw.shape)
        with np.errstate(all="ignore"):
            return _superpixel(raw, layout, black_level_dn)
    x = preprocess(raw, black_level_dn=black_level_dn, dark=dark)
    return demosaic_float(x, layout, method)


def demosaic_float(x: np.ndarray, layout: MosaicLayout, method: str) -> np.ndarray:
    """:func:`demosaic` of an already pre-processed float32 mosaic (no copy of ``x`` made
    where avoidable; ``x`` is not modified)."""
    _check_method(method)
    check_mosaic_shape(layout, x.shape)
    if x.dtype != np.float32:
        x = x.astype(np.float32)
    with np.errstate(all="ignore"):  # non-finite input is expected and masked downstream
        if method == "superpixel":
            return _superpixel(x, layout)
        if method == "bilinear":
            return _bilinear(x, layout)
        return _newton(x, layout)


def _check_method(method: str) -> None:
    if method not in METHODS:
        raise ValueError(f"unknown demosaic method {method!r}; use one of {', '.join(METHODS)}")


def class_positions(layout: MosaicLayout) -> dict[tuple[int, int], list[tuple[int, int]]]:
    """Cell positions ``(row, col)`` of every ``(colour, angle index)`` class."""
    out: dict[tuple[int, int], list[tuple[int, int]]] = {}
    ph, pw = layout.period
    for c in range(layout.n_colours):
        for k, ang in enumerate(ANALYZER_ANGLES_DEG):
            out[(c, k)] = [(r, q) for r in range(ph) for q in range(pw)
                           if layout.angle_deg[r, q] == ang and layout.colour[r, q] == c]
    return out


# -- superpixel --------------------------------------------------------------------------------
def _superpixel(x: np.ndarray, layout: MosaicLayout, black_level_dn: float = 0.0) -> np.ndarray:
    """Cell means ``(C, 4, H / ph, W / pw)`` float32 of a mosaic ``x`` (any real dtype) minus
    ``black_level_dn``."""
    ph, pw = layout.period
    h, w = x.shape[0] // ph, x.shape[1] // pw
    xc = x[: h * ph, : w * pw]
    out = np.empty((layout.n_colours, 4, h, w), np.float32)
    for (c, k), pos in class_positions(layout).items():
        r, q = pos[0]
        np.copyto(out[c, k], xc[r::ph, q::pw], casting="unsafe")
        for r, q in pos[1:]:
            out[c, k] += xc[r::ph, q::pw]
        if len(pos) > 1:
            out[c, k] *= np.float32(1.0 / len(pos))
    if black_level_dn:
        out -= np.float32(black_level_dn)
    return out


# -- bilinear (normalised convolution) ---------------------------------------------------------
def _tent(period: int) -> np.ndarray:
    k = np.arange(-period + 1, period)
    return (1.0 - np.abs(k) / period).astype(np.float32)


_PLAN_CACHE: dict[tuple, tuple] = {}
_PLAN_LOCK = threading.Lock()
#: Plans kept: a frame stream reuses one shape; a banded image has three (first, middle, last
#: band) per layout.
_PLAN_CACHE_SIZE = 4


def _bilinear_plan(layout: MosaicLayout, shape: tuple[int, int]):
    """Per class: the cell positions and the normalisation, ``None`` when it is exactly 1:
    for a separable class lattice ``((rows, factors (k, 1)), (cols, factors (1, m)))`` (the
    rows and columns whose factor differs from 1: the borders), otherwise
    ``((slice(None), plane),)``, a full plane.
    Memoised per layout pattern and image shape (the last few: a frame stream reuses one)."""
    key = (layout.angle_deg.tobytes(), layout.colour.tobytes(), layout.period,
           layout.n_colours, tuple(shape))
    with _PLAN_LOCK:  # bands of one image are demosaiced on several threads
        plan = _PLAN_CACHE.get(key)
    if plan is None:
        plan = _make_bilinear_plan(layout, tuple(shape))
        with _PLAN_LOCK:
            while len(_PLAN_CACHE) >= _PLAN_CACHE_SIZE:  # colour plans hold full-size planes
                _PLAN_CACHE.pop(next(iter(_PLAN_CACHE)))
            _PLAN_CACHE[key] = plan
    return plan


def _make_bilinear_plan(layout: MosaicLayout, shape: tuple[int, int]):
    ph, pw = layout.period
    ky, kx = _tent(ph), _tent(pw)
    h, w = shape
    plan = {}
    for cls, pos in class_positions(layout).items():
        rows = sorted({r for r, _ in pos})
        cols = sorted({q for _, q in pos})
        if len(pos) == len(rows) * len(cols):  # separable lattice: rows x cols
            mr = np.isin(np.arange(h) % ph, rows).astype(np.float32)[:, None]
            mc = np.isin(np.arange(w) % pw, cols).astype(np.float32)[None, :]
            dr = cv2.filter2D(mr, -1, ky[:, None], borderType=_BORDER)[:, 0]
            dc = cv2.filter2D(mc, -1, kx[None, :], borderType=_BORDER)[0]
            norm = None
            if not (np.allclose(dr, 1, atol=1e-6) and np.allclose(dc, 1, atol=1e-6)):
                # only the rows and columns whose factor is not exactly 1 (the borders)
                rn, cn = (1.0 / dr).astype(np.float32), (1.0 / dc).astype(np.float32)
                ri, ci = np.flatnonzero(rn != 1), np.flatnonzero(cn != 1)
                norm = ((ri, rn[ri][:, None]), (ci, cn[ci][None, :]))
        else:
            m = np.zeros((h, w), np.float32)
            for r, q in pos:
                m[r::ph, q::pw] = 1
            d = cv2.sepFilter2D(m, -1, kx, ky, borderType=_BORDER)
            norm = ((slice(None), (1.0 / d).astype(np.float32)),)
        plan[cls] = (pos, norm)
    return ky, kx, plan


def _bilinear(x: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    out = np.empty((layout.n_colours, 4) + x.shape, np.float32)
    sparse = np.empty_like(x)
    for c in range(layout.n_colours):
        _bilinear_colour(x, layout, c, out[c], sparse)
    return out


def _bilinear_colour(x: np.ndarray, layout: MosaicLayout, colour: int, dst: np.ndarray,
                     sparse: np.ndarray) -> None:
    """The four analyzer images of one colour ``(4, H, W)`` into ``dst`` (``sparse``: an
    ``(H, W)`` float32 scratch plane)."""
    ph, pw = layout.period
    ky, kx, plan = _bilinear_plan(layout, x.shape)
    for (c, k), (pos, norm) in plan.items():
        if c != colour:
            continue
        sparse.fill(0)
        for r, q in pos:
            sparse[r::ph, q::pw] = x[r::ph, q::pw]
        cv2.sepFilter2D(sparse, -1, kx, ky, dst=dst[k], borderType=_BORDER)
        if norm is not None:
            (ri, rn), *cols = norm
            dst[k][ri] *= rn
            for ci, cn in cols:
                dst[k][:, ci] *= cn


# -- fixed linear combinations of the analyzer images ------------------------------------------
def demosaic_combined(x: np.ndarray, layout: MosaicLayout, method: str,
                      weights: np.ndarray) -> np.ndarray:
    """``sum_k weights[j, k] * A[c, k]`` for the analyzer images ``A = demosaic_float(x, ...)``,
    shape ``(C, J, H', W')`` float32.

    For ``bilinear`` on a layout whose class normalisation is exactly 1 (every mono layout) the
    combination is taken on the mosaic before the (linear) interpolation, one filter per output
    plane instead of one per analyzer: the same numbers, computed faster. Used by
    :mod:`polrig.sensor.stokes` for the ideal analyzer (``weights`` = its 3x4 pseudo-inverse).
    """
    w = np.asarray(weights, dtype=np.float32)
    if w.ndim != 2 or w.shape[1] != 4:
        raise ValueError(f"weights must have shape (J, 4), got {w.shape}")
    if x.dtype != np.float32:
        x = x.astype(np.float32)
    if method == "bilinear":
        ky, kx, plan = _bilinear_plan(layout, x.shape)
        if all(norm is None for _, norm in plan.values()):
            return _bilinear_combined(x, layout, w, ky, kx, plan)
        check_mosaic_shape(layout, x.shape)
        # one colour's analyzer images at a time (a colour full sensor: 80 MB of scratch, not
        # 240 MB of analyzer images), combined as _combine does
        out = np.empty((layout.n_colours, w.shape[0]) + x.shape, np.float32)
        scratch, sparse = np.empty((4,) + x.shape, np.float32), np.empty_like(x)
        with np.errstate(all="ignore"):
            for c in range(layout.n_colours):
                _bilinear_colour(x, layout, c, scratch, sparse)
                _combine_colour(scratch, w, out[c])
        return out
    a = demosaic_float(x, layout, method)
    with np.errstate(all="ignore"):
        return _combine(a, w)


def _combine(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    out = np.empty((a.shape[0], w.shape[0]) + a.shape[2:], np.float32)
    for c in range(a.shape[0]):
        _combine_colour(a[c], w, out[c])
    return out


def _combine_colour(a: np.ndarray, w: np.ndarray, out: np.ndarray) -> None:
    """``out[j] = sum_k w[j, k] a[k]`` for one colour's analyzer images ``a`` ``(4, H, W)``
    (in this order, float32; zero weights after the first skipped, as
    :meth:`polrig.sensor.stokes.StokesSolver.solve` does for the ideal analyzer)."""
    for j in range(w.shape[0]):
        acc = out[j]
        np.multiply(a[0], w[j, 0], out=acc)
        for k in range(1, 4):
            if w[j, k]:
                acc += w[j, k] * a[k]


def _bilinear_combined(x, layout, w, ky, kx, plan) -> np.ndarray:
    return BilinearCombiner(layout, x.shape, w).strip(x, 0)


class BilinearCombiner:
    """Bilinear demosaicing followed by a fixed per-colour linear combination ``weights``
    ``(J, 4)`` of the analyzer images, computable strip by strip (cache-friendly).

    Only for layouts whose bilinear normalisation is exactly 1 (``supported``): then each
    output plane is one separable filter of the mosaic times a periodic weight plane. A strip
    ``x[e0:e1]`` gives exact outputs for rows ``e0 + halo .. e1 - halo`` (and up to the image
    border where ``e0 == 0`` or ``e1 == H``).
    """

    def __init__(self, layout: MosaicLayout, shape: tuple[int, int], weights: np.ndarray):
        self.layout = layout
        self.shape = tuple(shape)
        w = np.asarray(weights, np.float32)
        self.n_out = w.shape[0]
        self.ky, self.kx, plan = _bilinear_plan(layout, self.shape)
        self.halo = (len(self.ky) - 1) // 2
        self.supported = all(norm is None for _, norm in plan.values())
        ph, pw = layout.period
        self.terms: list[list[tuple[float | None, np.ndarray | None]]] = []
        for c in range(layout.n_colours):
            row = []
            for j in range(self.n_out):
                cell = np.zeros((ph, pw), np.float32)  # weight of every cell position
                for (cc, k), (pos, _) in plan.items():
                    if cc == c:
                        for r, q in pos:
                            cell[r, q] = w[j, k]
                if np.all(cell == cell.flat[0]):  # uniform weight: folded into the kernel
                    row.append((float(cell.flat[0]), None))
                else:
                    row.append((None, cell))
            self.terms.append(row)
        self._weights: dict[tuple, np.ndarray] = {}  # tiled cells by (c, j, row phase, rows)

    def _weight_rows(self, c: int, j: int, cell: np.ndarray, e0: int, rows: int,
                     width: int) -> np.ndarray:
        """``cell`` tiled over mosaic rows ``e0 .. e0 + rows`` (memoised per row phase)."""
        ph, pw = cell.shape
        key = (c, j, e0 % ph, rows, width)
        plane = self._weights.get(key)
        if plane is None:
            rolled = np.roll(cell, -(e0 % ph), axis=0)
            plane = np.ascontiguousarray(
                np.tile(rolled, (-(-rows // ph), -(-width // pw)))[:rows, :width])
            self._weights[key] = plane
        return plane

    def strip(self, x: np.ndarray, e0: int) -> np.ndarray:
        """``(C, J, rows, W)`` float32 for the mosaic rows ``x = mosaic[e0:e0 + rows]``."""
        rows = x.shape[0]
        out = np.empty((self.layout.n_colours, self.n_out, rows, x.shape[1]), np.float32)
        tmp = None
        for c, row in enumerate(self.terms):
            for j, (scale, cell) in enumerate(row):
                if cell is None:
                    cv2.sepFilter2D(x, -1, self.kx * np.float32(scale), self.ky,
                                    dst=out[c, j], borderType=_BORDER)
                else:
                    plane = self._weight_rows(c, j, cell, e0, rows, x.shape[1])
                    tmp = np.multiply(x, plane, out=tmp)
                    cv2.sepFilter2D(tmp, -1, self.kx, self.ky, dst=out[c, j],
                                    borderType=_BORDER)
        return out


# -- Newton polynomial interpolation (Li et al. 2019) -----------------------------------------
def _newton(x: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    ph, pw = layout.period
    angle_cell = layout.angle_deg[:2, :2]
    if (ph % 2 or pw % 2 or not np.array_equal(np.tile(angle_cell, (ph // 2, pw // 2)),
                                                layout.angle_deg)
            or sorted(angle_cell.ravel()) != sorted(ANALYZER_ANGLES_DEG)):
        raise ValueError(f"newton demosaicing needs a 2x2-periodic analyzer pattern with all four "
                         f"angles; layout {layout.name} has {layout.angle_deg.tolist()}")
    kidx = {a: i for i, a in enumerate(ANALYZER_ANGLES_DEG)}
    cell = np.vectorize(kidx.__getitem__)(angle_cell)  # analyzer index per 2x2 position
    if layout.n_colours == 1:
        return _newton_in_strips(x, cell)[None]
    # Bayer step: per colour, a full mosaic keeping each pixel's analyzer angle.
    bil = _bilinear(x, layout)
    out = np.empty_like(bil)
    for c in range(layout.n_colours):
        mc = np.empty_like(x)
        for r in range(2):
            for q in range(2):
                mc[r::2, q::2] = bil[c, cell[r, q], r::2, q::2]
        out[c] = _newton_in_strips(mc, cell)
    return out


def _f2d(img: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Correlation with a kernel whose centre is offset (0, 0) (``cv2.filter2D`` semantics)."""
    return cv2.filter2D(img, -1, kernel, borderType=_BORDER)


def _sep(img: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    return cv2.sepFilter2D(img, -1, kx, ky, borderType=_BORDER)


@functools.lru_cache(maxsize=1)
def _newton_kernels():
    t = NEWTON_TAPS
    odd = t.copy()
    odd[1::2] = 0  # offsets -3, -1, 1, 3 (indices 0, 2, 4, 6) keep; even offsets zero
    even = t - odd
    one = np.ones(1, np.float32)
    diag1 = np.diag(t).astype(np.float32)              # offsets (k, k)
    diag2 = np.fliplr(np.diag(t)).astype(np.float32)   # offsets (k, -k)
    step2 = np.array([1, 0, 1, 0, 1], np.float32)      # 3x3 samples at step 2
    return dict(t=t, odd=odd, even=even, one=one, diag1=diag1, diag2=diag2, step2=step2)


def _grad(img: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``|I(p - d) - I(p + d)| + |2 I(p) - I(p - 2d) - I(p + 2d)|`` for direction ``d``."""
    k1 = np.zeros((5, 5), np.float32)
    k1[2 - dy, 2 - dx], k1[2 + dy, 2 + dx] = 1, -1
    k2 = np.zeros((5, 5), np.float32)
    k2[2, 2] = 2
    k2[2 - 2 * dy, 2 - 2 * dx] = k2[2 + 2 * dy, 2 + 2 * dx] = -1
    return np.abs(_f2d(img, k1)) + np.abs(_f2d(img, k2))


def _fuse(x: np.ndarray, est1: np.ndarray, est2: np.ndarray, g1: np.ndarray,
          g2: np.ndarray) -> np.ndarray:
    """Edge-classifier fusion of two directional estimates (Li et al. 2019, Sec. 3.3)."""
    k = _newton_kernels()["step2"]
    pha1 = _sep(np.abs(est1 - x), k, k)
    pha2 = _sep(np.abs(est2 - x), k, k)
    eps = np.float32(1e-12)
    # weights 1/(g + eps): (w1 e1 + w2 e2) / (w1 + w2) = ((g2+eps) e1 + (g1+eps) e2) / (g1+g2+2eps)
    fused = ((g2 + eps) * est1 + (g1 + eps) * est2) / (g1 + g2 + 2 * eps)
    tau = np.float32(NEWTON_TAU)
    fused = np.where(pha1 > tau * pha2, est2, fused)
    fused = np.where(pha2 > tau * pha1, est1, fused)
    return fused.astype(np.float32, copy=False)


#: Support radius of :func:`_newton_mono` in pixels: stage one 3, its fusion windows +2 (the
#: diagonal plane has radius 5), stage two 3 more on that plane (8), its fusion windows +2.
NEWTON_RADIUS = 10
#: Pixels per strip of :func:`_newton_in_strips` (about 107 rows of a 2448-wide frame: the
#: 2 x 10-row halo costs 19 %).
NEWTON_STRIP_PIXELS = 2 ** 18


def _newton_in_strips(x: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """:func:`_newton_mono` computed in strips of rows with a halo of :data:`NEWTON_RADIUS`
    on a thread pool: identical numbers, cache-sized working sets, both cores busy."""
    h, w = x.shape
    step = max(2, NEWTON_STRIP_PIXELS // max(w, 1) // 2 * 2)  # even: strips keep the phase
    halo = NEWTON_RADIUS  # even as well
    if h <= step + 2 * halo:
        return _newton_mono(x, cell)
    out = np.empty((4, h, w), np.float32)

    def one_strip(y0: int) -> None:
        y1 = min(h, y0 + step)
        e0, e1 = max(0, y0 - halo), min(h, y1 + halo)
        with np.errstate(all="ignore"):
            out[:, y0:y1] = _newton_mono(x[e0:e1], cell)[:, y0 - e0:y1 - e0]

    starts = range(0, h, step)
    workers = min(len(starts), os.cpu_count() or 1)
    if workers > 1:  # strips write disjoint rows; numpy and OpenCV release the GIL
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            list(pool.map(one_strip, starts))
    else:
        for y0 in starts:
            one_strip(y0)
    return out


def _newton_mono(x: np.ndarray, cell: np.ndarray) -> np.ndarray:
    """Newton demosaicing of a 2x2-periodic mosaic; ``cell[r, q]`` is the analyzer index at
    2x2 position ``(r, q)``. Returns ``(4, H, W)``."""
    k = _newton_kernels()
    # stage one
    hor = _sep(x, k["t"], k["one"])     # channel of the right/left neighbour
    ver = _sep(x, k["one"], k["t"])     # channel of the lower/upper neighbour
    dg1 = _f2d(x, k["diag1"])
    dg2 = _f2d(x, k["diag2"])
    diag = _fuse(x, dg1, dg2, _grad(x, 1, 1), _grad(x, 1, -1))
    del dg1, dg2
    # stage two: the other axis, through the stage-one diagonal plane
    x_even_v = _sep(x, k["one"], k["even"])
    x_even_h = _sep(x, k["even"], k["one"])
    hor2 = _sep(diag, k["one"], k["odd"]) + x_even_v   # horizontal channel, vertical estimate
    ver2 = _sep(diag, k["odd"], k["one"]) + x_even_h   # vertical channel, horizontal estimate
    gh, gv = _grad(x, 0, 1), _grad(x, 1, 0)
    hor = _fuse(x, hor, hor2, gh, gv)
    ver = _fuse(x, ver2, ver, gh, gv)
    del hor2, ver2, x_even_h, x_even_v
    out = np.empty((4,) + x.shape, np.float32)
    for r in range(2):
        for q in range(2):
            sl = (slice(r, None, 2), slice(q, None, 2))
            out[(cell[r, q],) + sl] = x[sl]
            out[(cell[r, 1 - q],) + sl] = hor[sl]
            out[(cell[1 - r, q],) + sl] = ver[sl]
            out[(cell[1 - r, 1 - q],) + sl] = diag[sl]
    return out
