"""Linear Stokes images from DoFP analyzer images, DoLP, AoLP, masks.

Conventions (Stokes definition, angle sense, AoLP range, array layouts) are those of
``docs/conventions.md``: analyzer images ``(C, 4, H, W)`` in analyzer order 0, 45, 90, 135 deg,
Stokes images ``(C, 3, H, W)`` float32 in DN (black level removed).

Analyzer models:

* **ideal**: ``I(t) = (S0 + S1 cos 2t + S2 sin 2t) / 2``; its pseudo-inverse gives
  ``S0 = (I0 + I45 + I90 + I135) / 2``, ``S1 = I0 - I90``, ``S2 = I45 - I135``.
* **calibrated per pixel** (:class:`polrig.sensor.analyzer.AnalyzerModel`, Powell and Gruev, Opt.
  Express 21(18):21039, 2013): each output pixel has its own 4x3 analyzer matrix; the model's
  per-sensor-pixel rows and offsets are carried to the output grid by the same linear
  demosaicing as the data (``bilinear`` stands in for ``newton``, whose edge-directed weights
  are data dependent), and the per-pixel least-squares pseudo-inverses ``(A^T A)^-1 A^T`` are
  computed once in :class:`StokesSolver`.

Speed: the ideal-analyzer ``bilinear`` path of :func:`stokes_from_raw` runs in cache-sized
strips of rows on a thread pool (same numbers as the whole-image computation; see
``benchmarks/bench_dofp.py``).

Masks: a pixel is **valid** when all its Stokes values are finite, ``S0 > 0`` and no
contributing sensor pixel is saturated. Outputs are always finite: non-finite Stokes values
are set to 0, DoLP and AoLP are 0 where invalid. DoLP is clipped to 1 only where noise pushes it
over and the number of such pixels is reported.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os

import cv2
import numpy as np

from polrig.sensor.analyzer import (
    AnalyzerModel,
    LayoutLike,
    layout_name_at,
    resolve_layout,
)
from polrig.sensor.demosaic import (
    METHODS,
    NEWTON_RADIUS,
    BilinearCombiner,
    demosaic_combined,
    demosaic_float,
    output_shape,
    preprocess,
)
from polrig.sensor.layouts import ANALYZER_ANGLES_DEG, MosaicLayout


def ideal_analyzer_matrix() -> np.ndarray:
    """``(4, 3)`` rows ``[1, cos 2t, sin 2t] / 2`` for t = 0, 45, 90, 135 deg."""
    t = np.deg2rad(2 * np.asarray(ANALYZER_ANGLES_DEG, float))
    return 0.5 * np.stack([np.ones(4), np.cos(t), np.sin(t)], axis=1)


def ideal_inverse() -> np.ndarray:
    """``(3, 4)`` pseudo-inverse of :func:`ideal_analyzer_matrix` (rounded: exact 0, 1/2, 1)."""
    return _IDEAL_INVERSE.copy()


_IDEAL_INVERSE = np.round(np.linalg.pinv(ideal_analyzer_matrix()), 12)

#: Largest condition number of a calibrated pixel's analyzer matrix (upper bound, see
#: :func:`_pixel_pseudo_inverse`) that a :class:`StokesSolver` accepts. Ideal analyzers give
#: 1.9; diattenuation ``D`` with ideal angles gives about ``2.4 / D``, so 50 admits ``D >= 0.05``
#: (real micro-polarizers: 0.95-0.99) and refuses near-degenerate angle sets, where a 1 DN
#: noise would already move DoLP by tens of percent.
MAX_ANALYZER_CONDITION = 50.0


class StokesSolver:
    """Analyzer images -> Stokes images, with per-pixel pseudo-inverses computed once.

    ``StokesSolver()`` is the ideal analyzer (any image size). ``StokesSolver(model, method)``
    uses a calibrated :class:`AnalyzerModel` of the readout and the demosaic ``method`` that
    produced the analyzer images; it only accepts analyzer images of that readout's output grid.
    Reuse one solver for every frame of a readout.
    """

    def __init__(self, analyzer: AnalyzerModel | None = None, method: str = "superpixel"):
        if method not in METHODS:
            raise ValueError(f"unknown demosaic method {method!r}; use one of {METHODS}")
        self.method = method
        self.model = analyzer
        self.inverse = ideal_inverse().astype(np.float32)  # (3, 4)
        self.pixel_inverse: np.ndarray | None = None  # (C, 3, 4, H', W')
        self.offset: np.ndarray | None = None  # (C, 4, H', W')
        self._bilinear: StokesSolver | None = None  # calibrated newton: pre-correction
        if analyzer is not None:
            self._build(analyzer, method)

    @property
    def is_ideal(self) -> bool:
        """True when :meth:`solve` applies the ideal inverse (no calibration, or a calibrated
        ``newton`` solver whose calibration acts in :meth:`prepare_mosaic`)."""
        return self.pixel_inverse is None

    @property
    def grid_shape(self) -> tuple[int, int] | None:
        """``(H', W')`` of the analyzer images a calibrated solver accepts (None: any)."""
        return None if self.pixel_inverse is None else self.pixel_inverse.shape[-2:]

    def _build(self, model: AnalyzerModel, method: str) -> None:
        layout = model.mosaic_layout
        if method == "newton":
            # Newton's edge-directed weights are data dependent, so the calibration cannot be
            # carried through them. Instead the mosaic is made ideal before demosaicing
            # (prepare_mosaic): offset removed and each pixel's deviation from the ideal
            # analyzer, (rows - ideal rows) . S, subtracted with S from the calibrated
            # bilinear solve. Exact for locally uniform light, second order elsewhere.
            self._bilinear = StokesSolver(model, "bilinear")
            ideal = AnalyzerModel.ideal(layout, model.shape)
            self._delta_rows = (model.rows() - ideal.rows()).astype(np.float32)  # (H, W, 3)
            self._colour_map = model.colour_map()
            return
        rows = model.rows()  # (H, W, 3)
        # effective analyzer rows on the output grid: a[j] is (C, 4, H', W')
        a = [demosaic_float(np.ascontiguousarray(rows[..., j], np.float32), layout, method)
             for j in range(3)]
        c, _, h, w = a[0].shape
        pinv = np.empty((c, 3, 4, h, w), np.float32)
        step = max(1, 2 ** 18 // max(w, 1))
        for y0 in range(0, h, step):
            sl = (slice(None), slice(None), slice(y0, y0 + step))
            pinv[..., y0:y0 + step, :] = _pixel_pseudo_inverse([aj[sl] for aj in a])
        self.pixel_inverse = pinv
        self.offset = demosaic_float(model.offset_dn.astype(np.float32), layout, method)

    def prepare_mosaic(self, x: np.ndarray) -> np.ndarray:
        """The pre-processed float32 mosaic as this solver's demosaic step expects it:
        unchanged, except for a calibrated ``newton`` solver, which returns the mosaic an ideal
        sensor would have recorded (see :meth:`_build`)."""
        if self._bilinear is None:
            return x
        if x.shape != self._delta_rows.shape[:2]:
            raise ValueError(f"raw mosaic {x.shape} does not match the calibrated model "
                             f"{self._delta_rows.shape[:2]}")
        model = self.model
        s = self._bilinear.solve(demosaic_float(x, model.mosaic_layout, "bilinear"))
        if s.shape[0] == 1:
            own = s[0]
        else:
            own = np.take_along_axis(s, self._colour_map[None, None], axis=0)[0]
        out = x - model.offset_dn.astype(np.float32)
        for j in range(3):
            out -= self._delta_rows[..., j] * own[j]
        return out

    def solve(self, analyzers: np.ndarray) -> np.ndarray:
        """Stokes images ``(C, 3, H', W')`` float32 of analyzer images ``(C, 4, H', W')``.

        No masking here (see :func:`stokes_from_analyzers` / :func:`stokes_from_raw`).
        """
        a = np.asarray(analyzers)
        if a.ndim != 4 or a.shape[1] != 4:
            raise ValueError(f"analyzer images must have shape (C, 4, H, W), got {a.shape}")
        a = a.astype(np.float32, copy=False)
        with np.errstate(all="ignore"):
            return self._solve(a)

    def _solve(self, a: np.ndarray) -> np.ndarray:
        c = a.shape[0]
        out = np.empty((c, 3) + a.shape[2:], np.float32)
        if self.pixel_inverse is None:
            p = self.inverse
            for ci in range(c):
                for j in range(3):
                    acc = out[ci, j]
                    np.multiply(a[ci, 0], p[j, 0], out=acc)
                    for k in range(1, 4):
                        if p[j, k]:
                            acc += p[j, k] * a[ci, k]
            return out
        if a.shape[0] != self.pixel_inverse.shape[0] or a.shape[2:] != self.grid_shape:
            raise ValueError(f"analyzer images {a.shape} do not match the calibrated model's "
                             f"grid {(self.pixel_inverse.shape[0], 4) + self.grid_shape}")
        d = a - self.offset
        p = self.pixel_inverse
        for j in range(3):
            np.sum(p[:, j] * d, axis=1, out=out[:, j])
        return out


def _pixel_pseudo_inverse(a: list[np.ndarray]) -> np.ndarray:
    """Per-pixel ``(A^T A)^-1 A^T`` of 4x3 matrices given as planes ``a[j][:, k]`` (row k,
    column j), computed in float64 with the adjugate of the 3x3 normal matrix.

    Returns ``(C, 3, 4, h, w)``; raises ``ValueError`` where a matrix is singular or so
    ill-conditioned that noise would swamp the Stokes vector: the condition number of ``A``,
    bounded above by ``sqrt(||N||_F ||N^-1||_F)`` (``N = A^T A``, at most ``sqrt(3)`` times the
    2-norm value), must not exceed :data:`MAX_ANALYZER_CONDITION` (ideal analyzers: 1.9)."""
    A = np.stack(a, axis=2).astype(np.float64)  # (C, 4, 3, h, w): A[:, k, j]
    n = np.einsum("ckihw,ckjhw->cijhw", A, A)  # normal matrix (C, 3, 3, h, w)
    adj = np.empty_like(n)
    for i in range(3):
        for j in range(3):
            r = [x for x in range(3) if x != j]
            q = [x for x in range(3) if x != i]
            minor = n[:, r[0], q[0]] * n[:, r[1], q[1]] - n[:, r[0], q[1]] * n[:, r[1], q[0]]
            adj[:, i, j] = minor if (i + j) % 2 == 0 else -minor
    det = np.einsum("cjhw,cjhw->chw", n[:, 0], adj[:, :, 0])
    scale = (np.trace(n, axis1=1, axis2=2) / 3) ** 3
    bad = ~(np.abs(det) > 1e-9 * scale)
    if bad.any():
        raise ValueError(f"analyzer model is singular at {int(bad.sum())} output pixels "
                         f"(diattenuation or analyzer angles degenerate)")
    frob = lambda x: np.sqrt(np.einsum("cijhw,cijhw->chw", x, x))  # noqa: E731
    with np.errstate(all="ignore"):
        cond = np.sqrt(frob(n) * frob(adj) / np.abs(det))
    ill = ~(cond <= MAX_ANALYZER_CONDITION)
    if ill.any():
        raise ValueError(f"analyzer model is ill-conditioned at {int(ill.sum())} output pixels "
                         f"(condition number up to {np.nanmax(np.where(ill, cond, np.nan)):.3g}, limit "
                         f"{MAX_ANALYZER_CONDITION:g}: diattenuation too low or analyzer angles nearly degenerate)")
    inv = adj / det[:, None, None]
    return np.einsum("cijhw,ckjhw->cikhw", inv, A).astype(np.float32)


def stokes_from_analyzers(analyzers: np.ndarray,
                          analyzer: AnalyzerModel | StokesSolver | None = None, *,
                          method: str = "superpixel") -> np.ndarray:
    """Stokes images ``(C, 3, H, W)`` from analyzer images ``(C, 4, H, W)``.

    ``analyzer``: ``None`` (ideal), a calibrated :class:`AnalyzerModel` (with the demosaic
    ``method`` used for the analyzer images) or a prepared :class:`StokesSolver`. No masks or
    clipping here; see :func:`stokes_validity`, :func:`finite_stokes`.
    """
    solver = analyzer if isinstance(analyzer, StokesSolver) else StokesSolver(analyzer, method)
    return solver.solve(analyzers)


# -- masks and derived quantities ---------------------------------------------------------------
def stokes_validity(stokes: np.ndarray, saturated: np.ndarray | None = None,
                    *, check_finite: bool = True) -> np.ndarray:
    """Valid-pixel mask ``(C, H, W)``: finite Stokes, ``S0 > 0``, not saturated."""
    s = np.asarray(stokes)
    valid = s[:, 0] > 0  # NaN compares False
    if check_finite:
        valid &= np.isfinite(s).all(axis=1)
    if saturated is not None:
        valid &= ~np.asarray(saturated, bool)
    return valid


def finite_stokes(stokes: np.ndarray) -> np.ndarray:
    """A float32 copy of ``stokes`` with every non-finite value replaced by 0."""
    s = np.array(stokes, dtype=np.float32)
    s[~np.isfinite(s)] = 0
    return s


def _planes(x: np.ndarray) -> np.ndarray:
    """(C, H, W) -> (C*H, W) contiguous float32 for OpenCV's 2-D element-wise calls."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    return x.reshape(-1, x.shape[-1])


def _empty_result(s: np.ndarray) -> np.ndarray | None:
    """Zeros ``(C, H, W)`` float32 for Stokes images ``(C, 3, H, W)`` without pixels (OpenCV's
    element-wise calls return None for empty input), else None."""
    return np.zeros(s.shape[:1] + s.shape[2:], np.float32) if s[:, 0].size == 0 else None


def dolp_with_overshoot(stokes: np.ndarray, valid: np.ndarray | None = None
                        ) -> tuple[np.ndarray, int]:
    """DoLP ``sqrt(S1^2 + S2^2) / S0`` ``(C, H, W)`` float32 in [0, 1] and the number of valid
    pixels where noise pushed it above 1 (clipped to 1 there). 0 where invalid, and also where
    a caller's ``valid`` lets through a pixel with ``S0 <= 0`` or a non-finite value (negative
    or NaN quotients), so the range holds whatever mask is passed. Images without pixels
    (``C``, ``H`` or ``W`` = 0) give an empty array of that shape."""
    s = np.asarray(stokes, dtype=np.float32)
    empty = _empty_result(s)
    if empty is not None:
        return empty, 0
    if valid is None:
        valid = stokes_validity(s)
    mag = cv2.magnitude(_planes(s[:, 1]), _planes(s[:, 2]))
    return _dolp_from_magnitude(mag, s[:, 0], valid)


def _dolp_from_magnitude(mag: np.ndarray, s0: np.ndarray, valid: np.ndarray
                         ) -> tuple[np.ndarray, int]:
    d = mag.reshape(s0.shape)
    with np.errstate(all="ignore"):
        np.divide(d, s0, out=d)
    np.copyto(d, 0, where=~valid)
    np.fmax(d, 0, out=d)  # NaN and negative quotients -> 0 (fmax ignores NaN)
    over = d > 1
    n_over = int(np.count_nonzero(over))
    if n_over:
        d[over] = 1
    return d, n_over


def dolp(stokes: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """DoLP in [0, 1] (``docs/conventions.md``), 0 where invalid (:func:`dolp_with_overshoot`)."""
    return dolp_with_overshoot(stokes, valid)[0]


def aolp_deg(stokes: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """AoLP ``atan2(S2, S1) / 2`` in degrees in [0, 180) ``(C, H, W)`` float32, 0 where invalid.

    Computed with ``cv2.phase`` (absolute error below 0.01 deg, measured against ``arctan2``).
    Images without pixels give an empty array of that shape.
    """
    s = np.asarray(stokes, dtype=np.float32)
    empty = _empty_result(s)
    if empty is not None:
        return empty
    if valid is None:
        valid = stokes_validity(s)
    shape = s.shape[:1] + s.shape[2:]
    with np.errstate(all="ignore"):
        a = cv2.phase(_planes(s[:, 1]), _planes(s[:, 2]), angleInDegrees=True).reshape(shape)
    a *= np.float32(0.5)
    np.copyto(a, 0, where=~valid)
    a[~(a < 180)] = 0  # phase() may return exactly 360 deg; NaN never survives
    return a


def polarized_split(stokes: np.ndarray, valid: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(unpolarized, polarized)`` intensities ``(C, H, W)``: polarized = DoLP * S0 (DoLP
    clipped to [0, 1]), unpolarized = S0 - polarized; both 0 where invalid (empty arrays for
    images without pixels)."""
    s = np.asarray(stokes, dtype=np.float32)
    if valid is None:
        valid = stokes_validity(s)
    d = dolp(s, valid)
    s0 = np.where(valid, s[:, 0], 0).astype(np.float32)
    pol = d * s0
    return s0 - pol, pol


def min_max_intensity(stokes: np.ndarray, valid: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(Imin, Imax)`` ``(C, H, W)``: the intensities an ideal linear analyzer passes across and
    along the AoLP, ``(S0 -+ sqrt(S1^2 + S2^2)) / 2`` (DoLP clipped to [0, 1]), from
    :func:`polarized_split`: ``Imin = unpolarized / 2`` (the glare-reduced image: the polarized
    part, e.g. specular glare off a dielectric, removed), ``Imax = Imin + polarized``; 0 where
    invalid."""
    unpolarized, polarized = polarized_split(stokes, valid)
    imin = np.float32(0.5) * unpolarized
    return imin, imin + polarized


def saturation_mask(raw: np.ndarray, layout: LayoutLike, method: str,
                    saturation_dn: float) -> np.ndarray:
    """``(C, H', W')`` bool: some sensor pixel that contributes to the output pixel reads at or
    above ``saturation_dn`` (conservative: the method's whole support, all colours)."""
    lay = resolve_layout(layout)
    raw = np.asarray(raw)
    sat = raw >= saturation_dn
    return _saturation_mask(sat, lay, method)


def _saturation_mask(sat: np.ndarray, lay: MosaicLayout, method: str) -> np.ndarray:
    ph, pw = lay.period
    h, w = output_shape(lay, sat.shape, method)
    if method == "superpixel":
        m = sat[0 : h * ph : ph, 0 : w * pw : pw].copy()
        for r in range(ph):
            for q in range(pw):
                if r or q:
                    m |= sat[r : h * ph : ph, q : w * pw : pw]
    else:
        sat = sat.view(np.uint8)
        ry, rx = ph - 1, pw - 1  # bilinear: the tent's support
        if method == "newton":  # 7-tap filters, 5x5 gradients and windows, two stages
            ry, rx = NEWTON_RADIUS + (ry if lay.is_colour else 0), \
                NEWTON_RADIUS + (rx if lay.is_colour else 0)
        k = np.ones((2 * ry + 1, 2 * rx + 1), np.uint8)
        m = cv2.dilate(sat, k, borderType=cv2.BORDER_REFLECT_101).view(bool)
    return m[None] if lay.n_colours == 1 else np.repeat(m[None], lay.n_colours, axis=0)


def default_saturation_dn(raw: np.ndarray, bit_depth: int | None = None) -> float:
    """Saturation level of a raw mosaic: ``2**bit_depth - 1``, else the dtype's maximum for
    integers, else +inf (float input has no saturation level unless given)."""
    if bit_depth:
        return float(2 ** int(bit_depth) - 1)
    dt = np.asarray(raw).dtype
    if np.issubdtype(dt, np.integer):
        return float(np.iinfo(dt).max)
    return float("inf")


@dataclasses.dataclass(frozen=True)
class StokesImages:
    """Everything :func:`stokes_from_raw` computes for one frame (arrays plane-first).

    ``stokes`` ``(C, 3, H, W)`` float32 finite; ``valid``, ``saturated`` ``(C, H, W)`` bool;
    ``dolp`` in [0, 1] and ``aolp_deg`` in [0, 180) ``(C, H, W)`` float32, 0 where invalid;
    ``dolp_overshoot`` the number of valid pixels whose DoLP was clipped to 1.
    """

    stokes: np.ndarray
    valid: np.ndarray
    saturated: np.ndarray
    dolp: np.ndarray
    aolp_deg: np.ndarray
    dolp_overshoot: int
    layout: str
    method: str


def stokes_from_raw(raw: np.ndarray, layout: LayoutLike, method: str = "superpixel", *,
                    black_level_dn: float = 0.0, dark: np.ndarray | None = None,
                    analyzer: AnalyzerModel | StokesSolver | None = None,
                    saturation_dn: float | None = None,
                    bit_depth: int | None = None) -> StokesImages:
    """Raw mosaic ``(H, W)`` -> :class:`StokesImages` (demosaic, Stokes, masks, DoLP, AoLP).

    ``saturation_dn`` defaults to :func:`default_saturation_dn` (``2**bit_depth - 1``). The raw
    values are compared with it before black-level/dark removal. ``analyzer``: ``None`` for the
    ideal model, or a calibrated model / solver of this readout (see :class:`StokesSolver`).
    """
    with np.errstate(all="ignore"):  # non-finite input is expected: it ends up masked
        return _stokes_from_raw(raw, layout, method, black_level_dn, dark, analyzer,
                                saturation_dn, bit_depth)


def _saturation_level(raw, saturation_dn, bit_depth) -> float:
    return default_saturation_dn(raw, bit_depth) if saturation_dn is None else saturation_dn


def _stokes_from_raw(raw, layout, method, black_level_dn, dark, analyzer, saturation_dn,
                     bit_depth) -> StokesImages:
    lay = resolve_layout(layout)
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(f"raw mosaic must be 2-D (H, W), got shape {raw.shape}")
    if dark is not None and np.shape(dark) != raw.shape:
        raise ValueError(f"dark frame shape {np.shape(dark)} differs from raw {raw.shape}")
    ph, pw = lay.period
    if raw.shape[0] < ph or raw.shape[1] < pw:
        raise ValueError(f"raw mosaic {raw.shape} is smaller than one {ph}x{pw} layout cell")
    if method not in METHODS:
        raise ValueError(f"unknown demosaic method {method!r}; use one of {', '.join(METHODS)}")
    if method == "bilinear" and analyzer is None:
        comb = BilinearCombiner(lay, raw.shape, ideal_inverse())
        if comb.supported:
            return _bilinear_in_strips(raw, lay, comb, black_level_dn, dark,
                                       _saturation_level(raw, saturation_dn, bit_depth))
    x = preprocess(raw, black_level_dn=black_level_dn, dark=dark)
    solver = analyzer
    if isinstance(analyzer, AnalyzerModel):
        solver = StokesSolver(analyzer, method)
    if solver is not None and solver.model is not None:
        if layout_name_at(solver.model.layout, 0, 0) != layout_name_at(lay, 0, 0):
            raise ValueError(f"the analyzer model is for layout {solver.model.layout}, the "
                             f"frame is {lay.name}")
    if solver is not None:
        if solver.method != method and solver.model is not None:
            raise ValueError(f"the Stokes solver was built for {solver.method!r} demosaicing, "
                             f"not {method!r}")
        x = solver.prepare_mosaic(x)
    if solver is None or solver.is_ideal:
        stokes = demosaic_combined(x, lay, method, ideal_inverse())
    else:
        stokes = solver.solve(demosaic_float(x, lay, method))
    check_finite = not (np.issubdtype(raw.dtype, np.integer) and
                        (dark is None or np.isfinite(dark).all())
                        and np.isfinite(black_level_dn))
    if check_finite and not np.isfinite(stokes).all():
        finite = np.isfinite(stokes).all(axis=1)
        stokes[~np.isfinite(stokes)] = 0
        stokes[:, 0][~finite] = 0  # a pixel with any non-finite Stokes value is invalid
    sat_level = _saturation_level(raw, saturation_dn, bit_depth)
    valid = stokes[:, 0] > 0
    sat = raw >= sat_level if np.isfinite(sat_level) else None
    if sat is not None and sat.any():
        saturated = _saturation_mask(sat, lay, method)
        valid &= ~saturated
    else:
        saturated = np.zeros(valid.shape, bool)
    mag, ang = cv2.cartToPolar(_planes(stokes[:, 1]), _planes(stokes[:, 2]),
                               angleInDegrees=True)
    d, n_over = _dolp_from_magnitude(mag, stokes[:, 0], valid)
    a = ang.reshape(valid.shape)
    a *= np.float32(0.5)
    np.copyto(a, 0, where=~valid)
    a[~(a < 180)] = 0
    return StokesImages(stokes, valid, saturated, d, a, n_over, lay.name, method)


_BELOW_180 = float(np.nextafter(np.float32(180), np.float32(0)))

#: Rows per strip of the strip-wise bilinear path (2**18 pixels, 107 rows of a 2448-wide frame):
#: the working set of one strip stays in the CPU caches.
STRIP_PIXELS = 2 ** 18


def _bilinear_in_strips(raw: np.ndarray, lay: MosaicLayout, comb, black_level_dn: float,
                        dark: np.ndarray | None, sat_level: float) -> StokesImages:
    """The ideal-analyzer bilinear pipeline computed strip by strip: the same numbers as the
    whole-image path, with far less memory traffic (every intermediate of a strip stays in
    cache). Outputs as :func:`stokes_from_raw`."""
    h, w = raw.shape
    c = lay.n_colours
    stokes = np.empty((c, 3, h, w), np.float32)
    valid = np.empty((c, h, w), bool)
    saturated = np.zeros((c, h, w), bool)
    dl = np.empty((c, h, w), np.float32)
    al = np.empty((c, h, w), np.float32)
    check_finite = not (np.issubdtype(raw.dtype, np.integer) and
                        (dark is None or np.isfinite(dark).all())
                        and np.isfinite(black_level_dn))
    halo = comb.halo
    ph = lay.period[0]
    step = max(ph, STRIP_PIXELS // max(w, 1) // ph * ph)  # whole cells: one row phase
    sat_kernel = np.ones((2 * halo + 1, 2 * halo + 1), np.uint8)

    def one_strip(y0: int) -> int:
        """Rows ``y0 .. y0 + step`` of every output; returns the DoLP overshoot count."""
        n_over = 0
        with np.errstate(all="ignore"):  # per thread: non-finite input ends up masked
            y1 = min(h, y0 + step)
            e0, e1 = max(0, y0 - halo), min(h, y1 + halo)
            xs = preprocess(raw[e0:e1], black_level_dn=black_level_dn,
                            dark=None if dark is None else dark[e0:e1])
            s = comb.strip(xs, e0)[:, :, y0 - e0:y1 - e0]
            if check_finite and not np.isfinite(s).all():
                bad = ~np.isfinite(s)
                s[bad] = 0
                s[:, 0][bad.any(axis=1)] = 0  # a pixel with any non-finite value is invalid
            stokes[:, :, y0:y1] = s
            v = valid[:, y0:y1]
            np.greater(s[:, 0], 0, out=v)
            if np.isfinite(sat_level):
                sat = raw[e0:e1] >= sat_level
                if sat.any():
                    m = cv2.dilate(sat.view(np.uint8), sat_kernel,
                                   borderType=cv2.BORDER_REFLECT_101).view(bool)
                    m = m[y0 - e0:y1 - e0]
                    saturated[:, y0:y1] = m
                    v &= ~m
            for ci in range(c):
                d, a, inv = dl[ci, y0:y1], al[ci, y0:y1], ~v[ci]
                cv2.cartToPolar(s[ci, 1], s[ci, 2], magnitude=d, angle=a,
                                angleInDegrees=True)
                np.divide(d, s[ci, 0], out=d)  # inf/NaN where S0 <= 0: overwritten next
                np.copyto(d, 0, where=inv)
                k = int(np.count_nonzero(d > 1))
                if k:
                    cv2.threshold(d, 1.0, 1.0, cv2.THRESH_TRUNC, dst=d)
                    n_over += k
                a *= np.float32(0.5)
                np.copyto(a, 0, where=inv)
                # cartToPolar may return exactly 360 deg: AoLP 180 is AoLP 0
                cv2.threshold(a, _BELOW_180, 0.0, cv2.THRESH_TOZERO_INV, dst=a)
        return n_over

    starts = range(0, h, step)
    workers = min(len(starts), os.cpu_count() or 1)
    if workers > 1:  # strips write disjoint rows; numpy and OpenCV release the GIL
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            n_over = sum(pool.map(one_strip, starts))
    else:
        n_over = sum(map(one_strip, starts))
    return StokesImages(stokes, valid, saturated, dl, al, n_over, lay.name, "bilinear")
