"""Region-of-interest statistics and line profiles of Stokes and Mueller images (issue 34, item 4).

Headless and array-level: the GUI's ROI tools (:mod:`polrig.gui.roi_panel`) and
``polrig stats`` both call :func:`roi_statistics` and :func:`line_profile`, so a drawn ROI and
the command line give the same numbers.

**Pixel convention.** Image pixel ``(u, v)`` (column, row) covers ``[u, u + 1) x [v, v + 1)``
in image coordinates ``(x, y)``; its centre is ``(u + 0.5, v + 0.5)``. A pixel belongs to an
ROI when its centre does: a rectangle ``x, y, w, h`` holds the centres with
``x <= cx < x + w`` and ``y <= cy < y + h`` (``rect:10,20,5,4`` is columns 10..14, rows
20..23), an ellipse ``cx, cy, rx, ry`` those with ``((cx' - cx) / rx)^2 + ((cy' - cy) / ry)^2
<= 1``, a polygon those inside by the even-odd rule (a centre exactly on an edge may fall on
either side).

**Line profiles.** Samples every ``spacing`` pixels (default 1) of arc length from ``(x0, y0)``
to ``(x1, y1)`` (the end point included when the length is a multiple of the spacing),
bilinear between the four nearest pixel centres; a sample outside the image, or with a masked
or NaN neighbour of non-zero weight, is NaN. Axial angles (AoLP and the axis maps) are
interpolated as the unit vectors of twice the angle, never as numbers (so 179 and 1 deg
give 0, not 90).

**Statistics** per quantity and colour over the ROI's counted pixels (inside, valid, finite):

* linear quantities: mean, standard deviation (``ddof = 1``), and two standard errors of the
  mean: ``sem_scatter = std / sqrt(n)`` from the pixels' scatter (texture included), and
  ``sem_sigma = sqrt(sum sigma_i^2) / n`` from the pixels' own sigma planes (independent pixels;
  NaN without sigma planes; infinite or NaN when a counted pixel's sigma is: an axis whose
  magnitude is within its noise has no sigma to speak of). The first also holds the sample's
  texture; the second only the measurement noise (and calibration) that the sigma planes hold.
  Which pixels count does not depend on the sigma planes.
* axial angles (period ``p``: AoLP and ``DL``/``PL``/retarder axes 180 deg, the MMT
  orientation 90 deg): the angles are mapped onto the circle, ``phi = 2 pi a / p``, and
  summarised by the mean resultant vector ``R e^{i mu}`` (Mardia and Jupp, *Directional
  Statistics*, Wiley 2000, sections 2.2-2.3, and section 9.1 on axial data: "double the
  angle"); the mean is ``mu p / (2 pi)`` in the quantity's range and the spread is the circular
  standard deviation ``sqrt(-2 ln R) p / (2 pi)`` (their eq. 2.3.11). ``sem_scatter`` is
  Fisher's circular standard error ``sqrt((1 - rho2) / (2 n R^2)) p / (2 pi)`` with ``rho2`` the
  mean of ``cos 2 (phi_i - mu)`` (N. I. Fisher, *Statistical Analysis of Circular Data*,
  Cambridge 1993, eq. 4.21); ``sem_sigma`` is the first-order propagation of the pixels'
  sigmas through ``mu``: ``sqrt(sum (cos(phi_i - mu) sigma_i)^2) / (n R)``.

Quantities: of a Stokes image ``S0``, ``DoLP``, ``AoLP_deg`` (:mod:`polrig.sensor.stokes`), with
the sigma of ``S0`` where the signal-to-noise is known; of a Mueller image ``S0``, ``DoLP`` and
``AoLP_deg`` of the light that unpolarized illumination leaves (``m00``, ``PL`` and
``PL_axis_deg``: the first column of ``M``), every ``m_ij / m00`` and every other map of
:mod:`polrig.optics.parameters`, each with its linearised sigma from the result's ``sigma``
planes. Maps are computed on the ROI's bounding box only.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from polrig.errors import ConfigError
from polrig.optics import parameters as pa
from polrig.sensor.stokes import aolp_deg, dolp, stokes_validity
from polrig.solve.chunks import mask_box

__all__ = [
    "RectROI", "EllipseROI", "PolygonROI", "ROI", "parse_roi", "parse_segment", "roi_mask",
    "Quantities", "stokes_quantities", "mueller_quantities", "RoiRow", "roi_statistics",
    "statistics_of", "Profile", "line_profile", "profile_of", "stats_csv", "profile_csv", "STATS_COLUMNS",
]


# -- geometry ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class RectROI:
    """Axis-aligned rectangle: corner ``(x, y)``, size ``w x h`` (image pixels)."""

    x: float
    y: float
    w: float
    h: float

    def bounds(self) -> tuple[float, float, float, float]:
        return self.x, self.y, self.x + self.w, self.y + self.h

    def contains(self, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        return (cx >= self.x) & (cx < self.x + self.w) & (cy >= self.y) & (cy < self.y + self.h)

    def text(self) -> str:
        return f"rect:{self.x:g},{self.y:g},{self.w:g},{self.h:g}"


@dataclasses.dataclass(frozen=True)
class EllipseROI:
    """Axis-aligned ellipse: centre ``(cx, cy)``, semi-axes ``rx``, ``ry`` (image pixels)."""

    cx: float
    cy: float
    rx: float
    ry: float

    def bounds(self) -> tuple[float, float, float, float]:
        return self.cx - self.rx, self.cy - self.ry, self.cx + self.rx, self.cy + self.ry

    def contains(self, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        return ((cx - self.cx) / self.rx) ** 2 + ((cy - self.cy) / self.ry) ** 2 <= 1.0

    def text(self) -> str:
        return f"ellipse:{self.cx:g},{self.cy:g},{self.rx:g},{self.ry:g}"


@dataclasses.dataclass(frozen=True)
class PolygonROI:
    """Closed polygon through ``points`` ``((x, y), ...)`` (at least three; even-odd rule)."""

    points: tuple[tuple[float, float], ...]

    def bounds(self) -> tuple[float, float, float, float]:
        xs, ys = zip(*self.points)
        return min(xs), min(ys), max(xs), max(ys)

    def contains(self, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        inside = np.zeros(np.broadcast(cx, cy).shape, bool)
        pts = self.points
        for (xa, ya), (xb, yb) in zip(pts, pts[1:] + pts[:1]):
            if ya == yb:
                continue  # a horizontal edge crosses no horizontal ray
            straddles = (ya > cy) != (yb > cy)
            x_cross = xa + (cy - ya) * (xb - xa) / (yb - ya)
            inside ^= straddles & (cx < x_cross)
        return inside

    def text(self) -> str:
        return "poly:" + ",".join(f"{x:g},{y:g}" for x, y in self.points)


ROI = RectROI | EllipseROI | PolygonROI


def roi_mask(roi: ROI, shape: tuple[int, int]) -> np.ndarray:
    """Boolean ``(H, W)``: True for the pixels whose centre lies in ``roi`` (module docstring)."""
    h, w = (int(v) for v in shape)
    cy = np.arange(h, dtype=np.float64)[:, None] + 0.5
    cx = np.arange(w, dtype=np.float64)[None, :] + 0.5
    return np.broadcast_to(roi.contains(cx, cy), (h, w)).copy()


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def _numbers(text: str, what: str) -> list[float]:
    parts = [p.strip() for p in text.split(",")]
    if not all(re.fullmatch(_NUMBER, p) for p in parts):
        raise ConfigError(f"{what}: expected comma-separated numbers, got {text!r}")
    return [float(p) for p in parts]


def parse_roi(text: str, what: str = "--roi") -> ROI:
    """``rect:x,y,w,h``, ``ellipse:cx,cy,rx,ry`` or ``poly:x1,y1,x2,y2,...`` (image pixels);
    :class:`polrig.errors.ConfigError` naming ``what`` for anything else."""
    kind, sep, rest = text.partition(":")
    kind = kind.strip().lower()
    if not sep or kind not in ("rect", "ellipse", "poly"):
        raise ConfigError(f"{what}: expected rect:x,y,w,h, ellipse:cx,cy,rx,ry or "
                          f"poly:x1,y1,x2,y2,..., got {text!r}")
    v = _numbers(rest, what)
    if kind == "poly":
        if len(v) < 6 or len(v) % 2:
            raise ConfigError(f"{what}: a polygon needs at least three x,y points, got {text!r}")
        return PolygonROI(tuple(zip(v[0::2], v[1::2])))
    if len(v) != 4:
        raise ConfigError(f"{what}: {kind} takes four numbers, got {len(v)} in {text!r}")
    if v[2] <= 0 or v[3] <= 0:
        raise ConfigError(f"{what}: {kind} size must be positive, got {text!r}")
    return RectROI(*v) if kind == "rect" else EllipseROI(*v)


def parse_segment(text: str, what: str = "--profile") -> tuple[float, float, float, float]:
    """``x0,y0,x1,y1`` (image pixels) of a line profile."""
    v = _numbers(text, what)
    if len(v) != 4:
        raise ConfigError(f"{what}: expected x0,y0,x1,y1, got {text!r}")
    return v[0], v[1], v[2], v[3]


# -- quantities -------------------------------------------------------------------------------
@dataclasses.dataclass
class Quantities:
    """What statistics are taken of: ``values`` and ``sigma`` by name, ``(C, H, W)`` float
    (a name absent from ``sigma`` has no per-pixel sigma); ``valid`` ``(C, H, W)`` bool (False:
    masked by the data's reason bits or signal threshold); ``periods`` the axial angles' periods
    in degrees and ``lows`` the lower end of their range (0, or ``-p/2`` for the rotation);
    ``channels`` the colour names; ``notes`` a short description per name."""

    values: dict[str, np.ndarray]
    sigma: dict[str, np.ndarray]
    valid: np.ndarray
    periods: dict[str, float]
    lows: dict[str, float]
    channels: tuple[str, ...]
    notes: dict[str, str]


def _channels(n: int) -> tuple[str, ...]:
    return ("Y",) if n == 1 else ("R", "G", "B")[:n]


def stokes_quantities(stokes: np.ndarray, valid: np.ndarray | None = None,
                      snr: np.ndarray | None = None) -> Quantities:
    """``S0``, ``DoLP``, ``AoLP_deg`` of Stokes images ``(C, 3, H, W)``; ``valid`` ``(C, H, W)``
    (default :func:`polrig.sensor.stokes.stokes_validity`) marks the counted pixels; with
    ``snr`` (``S0`` over its noise sigma), ``sigma(S0) = S0 / snr``."""
    s = np.asarray(stokes, np.float32)
    ok = stokes_validity(s) if valid is None else (np.asarray(valid, bool) & stokes_validity(s))
    values = {"S0": s[:, 0].astype(np.float64), "DoLP": dolp(s, ok).astype(np.float64),
              "AoLP_deg": aolp_deg(s, ok).astype(np.float64)}
    sigma = {}
    if snr is not None:
        with np.errstate(all="ignore"):
            sigma["S0"] = np.abs(values["S0"] / np.asarray(snr, np.float64))
    return Quantities(values, sigma, ok, {"AoLP_deg": 180.0}, {"AoLP_deg": 0.0},
                      _channels(s.shape[0]),
                      {"S0": "S0 (DN)", "DoLP": "degree of linear polarization",
                       "AoLP_deg": "angle of linear polarization, deg [0, 180)"})


#: Names of the Mueller quantities that are S0, DoLP and AoLP of the emerging light under
#: unpolarized illumination.
MUELLER_ALIASES = {"S0": "m00", "DoLP": "PL", "AoLP_deg": "PL_axis_deg"}


def mueller_quantities(mueller: np.ndarray, sigma: np.ndarray | None = None,
                       valid: np.ndarray | None = None) -> Quantities:
    """Of Mueller images ``(C, 3, 3, H, W)`` with per-element ``sigma`` (same shape, or None):
    ``S0``, ``DoLP``, ``AoLP_deg`` (:data:`MUELLER_ALIASES`), ``m{ij}/m00`` for the eight
    normalised elements and every other map of :data:`polrig.optics.parameters.MAPS`, each with
    its linearised sigma (:func:`polrig.optics.parameters.image_maps`; ``m_ij / m00``:
    ``sigma^2 = (sigma_ij / m00)^2 + (m_ij sigma_00 / m00^2)^2``). ``valid`` ``(C, H, W)``
    (e.g. the result's ``mask == 0``) marks the counted pixels."""
    m = np.asarray(mueller)
    if m.ndim != 5 or m.shape[1:3] != (3, 3):
        raise ValueError(f"Mueller images must have shape (C, 3, 3, H, W), got {m.shape}")
    maps = pa.image_maps(m, sigma)
    m00 = m[:, 0, 0].astype(np.float64)
    rename = {v: k for k, v in MUELLER_ALIASES.items()}
    values: dict[str, np.ndarray] = {}
    sig: dict[str, np.ndarray] = {}
    notes: dict[str, str] = {}
    for alias, name in MUELLER_ALIASES.items():
        values[alias] = maps.values[name].astype(np.float64)
        notes[alias] = f"{name}: {pa.MAPS[name]}"
    with np.errstate(all="ignore"):
        pos = np.where(m00 > 0, m00, np.nan)
        for r in range(3):
            for c in range(3):
                if r == c == 0:
                    continue
                name = f"m{r}{c}/m00"
                values[name] = m[:, r, c].astype(np.float64) / pos
                notes[name] = f"normalised Mueller element m{r}{c} / m00"
                if sigma is not None:
                    s = np.broadcast_to(np.asarray(sigma), m.shape)
                    sig[name] = np.hypot(s[:, r, c] / pos, values[name] * s[:, 0, 0] / pos)
    for name, note in pa.MAPS.items():
        if name not in rename:
            values[name] = maps.values[name].astype(np.float64)
            notes[name] = note
    for name, s in maps.sigma.items():
        sig[rename.get(name, name)] = s.astype(np.float64)
    periods = {rename.get(n, n): p for n, p in pa.ANGLE_PERIOD_DEG.items()}
    lows = {n: (-p / 2 if n == "rotation_deg" else 0.0) for n, p in periods.items()}
    ok = np.isfinite(m).all(axis=(1, 2)) & (m00 > 0)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    return Quantities(values, sig, ok, periods, lows, _channels(m.shape[0]), notes)


# -- statistics ---------------------------------------------------------------------------------
#: CSV columns of :func:`stats_csv`, in order.
STATS_COLUMNS = ("quantity", "channel", "kind", "mean", "std", "sem_scatter", "sem_sigma",
                 "n_counted", "n_masked")


@dataclasses.dataclass(frozen=True)
class RoiRow:
    """One quantity of one colour over an ROI. ``kind``: ``"linear"`` or ``"axial/P"`` (an angle
    of period ``P`` deg: ``mean`` is the circular mean, ``std`` the circular standard
    deviation); ``n_counted`` pixels inside, valid and finite, ``n_masked`` the other pixels
    inside. Statistics of fewer than one (two for ``std``) pixel are NaN."""

    quantity: str
    channel: str
    kind: str
    mean: float
    std: float
    sem_scatter: float
    sem_sigma: float
    n_counted: int
    n_masked: int

    def as_tuple(self) -> tuple:
        return tuple(getattr(self, k) for k in STATS_COLUMNS)


def _linear(x: np.ndarray, s: np.ndarray | None) -> tuple[float, float, float, float]:
    n = x.size
    if n == 0:
        return (math.nan,) * 4
    mean = float(x.mean())
    std = float(x.std(ddof=1)) if n > 1 else math.nan
    sem = std / math.sqrt(n) if n > 1 else math.nan
    sem_sigma = float(np.sqrt(np.sum(s ** 2)) / n) if s is not None else math.nan
    return mean, std, sem, sem_sigma


def _axial(x: np.ndarray, s: np.ndarray | None, period: float, low: float
           ) -> tuple[float, float, float, float]:
    n = x.size
    if n == 0:
        return (math.nan,) * 4
    k = 2.0 * math.pi / period  # axial data: the angle times 360 / period on the circle
    phi = x * k
    c, sn = float(np.cos(phi).mean()), float(np.sin(phi).mean())
    r = math.hypot(c, sn)
    if r < 1e-12:  # no mean direction (e.g. uniform around the circle)
        return math.nan, math.inf, math.nan, math.nan
    mu = math.atan2(sn, c)
    mean = (mu / k - low) % period + low
    std = math.sqrt(max(0.0, -2.0 * math.log(min(r, 1.0)))) / k
    rho2 = float(np.cos(2.0 * (phi - mu)).mean())
    sem = math.sqrt(max(0.0, 1.0 - rho2) / (2.0 * n * r * r)) / k if n > 1 else math.nan
    sem_sigma = math.nan
    if s is not None:
        sem_sigma = float(np.sqrt(np.sum((np.cos(phi - mu) * s) ** 2)) / (n * r))
    return mean, std, sem, sem_sigma


def statistics_of(q: Quantities, inside: np.ndarray,
                  names: Sequence[str] | None = None) -> list[RoiRow]:
    """Rows of :class:`RoiRow` (quantity by quantity, colour by colour) of the pixels where
    ``inside`` ``(H, W)`` is True."""
    inside = np.asarray(inside, bool)
    rows = []
    for name in (names or list(q.values)):
        vals = q.values[name]
        sig = q.sigma.get(name)
        for ci, ch in enumerate(q.channels):
            v = vals[ci][inside]
            ok = q.valid[ci][inside] & np.isfinite(v)
            x = v[ok]
            s = None if sig is None else sig[ci][inside][ok]
            if name in q.periods:
                kind = f"axial/{q.periods[name]:g}"
                stats = _axial(x, s, q.periods[name], q.lows.get(name, 0.0))
            else:
                kind = "linear"
                stats = _linear(x, s)
            rows.append(RoiRow(name, ch, kind, *stats, int(ok.sum()), int(ok.size - ok.sum())))
    return rows


def roi_statistics(inside: np.ndarray, *, mueller: np.ndarray | None = None,
                   sigma: np.ndarray | None = None, stokes: np.ndarray | None = None,
                   valid: np.ndarray | None = None, snr: np.ndarray | None = None
                   ) -> list[RoiRow]:
    """Statistics over the ROI ``inside`` ``(H, W)`` (:func:`roi_mask`) of a Mueller image
    (:func:`mueller_quantities` of ``mueller``, ``sigma``) or, without one, of Stokes images
    (:func:`stokes_quantities` of ``stokes``, ``snr``); ``valid`` ``(C, H, W)`` the data's own
    mask (True = use). The quantities are computed on the ROI's bounding box only."""
    inside = np.asarray(inside, bool)
    src = mueller if mueller is not None else stokes
    if src is None:
        raise ValueError("roi_statistics needs a Mueller or a Stokes image")
    if inside.shape != np.shape(src)[-2:]:
        raise ValueError(f"ROI mask {inside.shape} does not match the image {np.shape(src)[-2:]}")
    box = mask_box(inside)
    if box is None:
        box = (slice(0, 1), slice(0, 1))
        inside = np.zeros((1, 1), bool)
    else:
        inside = inside[box]
    crop = lambda a: None if a is None else np.asarray(a)[..., box[0], box[1]]  # noqa: E731
    if mueller is not None:
        q = mueller_quantities(crop(mueller), crop(sigma), crop(valid))
    else:
        q = stokes_quantities(crop(stokes), crop(valid), crop(snr))
    return statistics_of(q, inside)


# -- line profiles ------------------------------------------------------------------------------
@dataclasses.dataclass
class Profile:
    """A line profile: arc length ``s`` from the start, sample positions ``x``, ``y`` (image
    pixels), ``values`` by quantity name ``(C, N)`` and the colour ``channels``."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    values: dict[str, np.ndarray]
    channels: tuple[str, ...]


def sample_positions(x0: float, y0: float, x1: float, y1: float, spacing: float = 1.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(s, x, y)``: samples every ``spacing`` pixels of arc length from ``(x0, y0)`` towards
    ``(x1, y1)``, the end included when the length is a multiple of the spacing (a zero-length
    segment: one sample)."""
    if not spacing > 0:
        raise ValueError(f"profile spacing must be positive, got {spacing}")
    length = math.hypot(x1 - x0, y1 - y0)
    n = int(math.floor(length / spacing + 1e-9)) + 1
    s = np.arange(n, dtype=np.float64) * spacing
    t = s / length if length > 0 else np.zeros(1)
    return s, x0 + t * (x1 - x0), y0 + t * (y1 - y0)


def _bilinear(planes: np.ndarray, ok: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``planes`` ``(C, H, W)`` at image points ``(x, y)`` (pixel centres at ``+0.5``) ->
    ``(C, N)``; NaN outside the image or where a neighbour of non-zero weight is not ``ok``."""
    c, h, w = planes.shape
    inside = (x >= 0) & (x <= w) & (y >= 0) & (y <= h)
    fx = np.clip(x - 0.5, 0, w - 1)
    fy = np.clip(y - 0.5, 0, h - 1)
    ix, iy = np.minimum(np.floor(fx).astype(int), max(w - 2, 0)), np.minimum(
        np.floor(fy).astype(int), max(h - 2, 0))
    tx, ty = fx - ix, fy - iy
    out = np.zeros((c, x.size))
    bad = np.zeros((c, x.size), bool)
    for dy, wy in ((0, 1 - ty), (1, ty)):
        for dx, wx in ((0, 1 - tx), (1, tx)):
            wgt = wx * wy
            yy, xx = np.minimum(iy + dy, h - 1), np.minimum(ix + dx, w - 1)
            v = planes[:, yy, xx]
            use = wgt > 0
            bad |= use & ~(ok[:, yy, xx] & np.isfinite(v))
            out += np.where(use, np.nan_to_num(v) * wgt, 0.0)
    out[bad | ~inside] = np.nan
    return out


def line_profile(q: Quantities, x0: float, y0: float, x1: float, y1: float,
                 spacing: float = 1.0, names: Sequence[str] | None = None) -> Profile:
    """The profile of quantities ``q`` along the segment (module docstring: sampling,
    bilinear, axial angles through twice the angle)."""
    s, x, y = sample_positions(x0, y0, x1, y1, spacing)
    values = {}
    for name in (names or list(q.values)):
        v = q.values[name]
        if name in q.periods:
            k = 2.0 * np.pi / q.periods[name]
            cs = _bilinear(np.cos(v * k), q.valid, x, y)
            sn = _bilinear(np.sin(v * k), q.valid, x, y)
            low = q.lows.get(name, 0.0)
            values[name] = (np.arctan2(sn, cs) / k - low) % q.periods[name] + low
        else:
            values[name] = _bilinear(v, q.valid, x, y)
    return Profile(s, x, y, values, q.channels)


def profile_of(segment: tuple[float, float, float, float], *, mueller: np.ndarray | None = None,
               sigma: np.ndarray | None = None, stokes: np.ndarray | None = None,
               valid: np.ndarray | None = None, snr: np.ndarray | None = None,
               spacing: float = 1.0) -> Profile:
    """:func:`line_profile` of a Mueller image (:func:`mueller_quantities`) or, without one, of
    Stokes images (:func:`stokes_quantities`), the arguments as :func:`roi_statistics`'s; the
    quantities are computed on the segment's bounding box (and the pixels next to it) only,
    with the same values as on the whole image."""
    src = mueller if mueller is not None else stokes
    if src is None:
        raise ValueError("profile_of needs a Mueller or a Stokes image")
    h, w = np.shape(src)[-2:]
    x0, y0, x1, y1 = segment
    c0 = int(np.clip(math.floor(min(x0, x1) - 0.5), 0, w - 1))
    c1 = int(np.clip(math.floor(max(x0, x1) + 0.5), 0, w - 1)) + 1
    r0 = int(np.clip(math.floor(min(y0, y1) - 0.5), 0, h - 1))
    r1 = int(np.clip(math.floor(max(y0, y1) + 0.5), 0, h - 1)) + 1
    crop = lambda a: None if a is None else np.asarray(a)[..., r0:r1, c0:c1]  # noqa: E731
    if mueller is not None:
        q = mueller_quantities(crop(mueller), crop(sigma), crop(valid))
    else:
        q = stokes_quantities(crop(stokes), crop(valid), crop(snr))
    p = line_profile(q, x0 - c0, y0 - r0, x1 - c0, y1 - r0, spacing)
    outside = ~((p.x + c0 >= 0) & (p.x + c0 <= w) & (p.y + r0 >= 0) & (p.y + r0 <= h))
    for v in p.values.values():
        v[:, outside] = np.nan  # outside the image, not merely outside the crop
    return Profile(p.s, p.x + c0, p.y + r0, p.values, p.channels)


# -- CSV ------------------------------------------------------------------------------------------
def _cell(v) -> str:
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    return str(v)


def _csv_text(header: Mapping[str, str] | None, columns: Sequence[str],
              rows: Iterable[Sequence]) -> str:
    """``# key: value`` comment lines of ``header``, one line of ``columns``, the ``rows``."""
    buf = io.StringIO()
    for k, v in (header or {}).items():
        buf.write(f"# {k}: {v}\n")
    wr = csv.writer(buf, lineterminator="\n")
    wr.writerow(columns)
    wr.writerows(rows)
    return buf.getvalue()


def stats_csv(rows: Sequence[RoiRow] | Mapping[str, Sequence[RoiRow]],
              header: Mapping[str, str] | None = None) -> str:
    """CSV text of statistics rows (:data:`STATS_COLUMNS`), preceded by ``# key: value``
    comment lines of ``header`` (e.g. the source and the ROI). Full float precision.

    ``rows`` by capture name (a session's captures) give one table with a first column
    ``capture`` naming each row's capture, under one header line."""
    if isinstance(rows, Mapping):
        return _csv_text(header, ("capture",) + STATS_COLUMNS,
                         ([name] + [_cell(v) for v in r.as_tuple()]
                          for name, part in rows.items() for r in part))
    return _csv_text(header, STATS_COLUMNS, ([_cell(v) for v in r.as_tuple()] for r in rows))


def profile_csv(p: Profile | Mapping[str, Profile], header: Mapping[str, str] | None = None) -> str:
    """CSV text of a profile: ``s, x, y`` then one column per quantity and colour
    (``NAME.CH``), preceded by ``# key: value`` comment lines of ``header``.

    Profiles by capture name (a session's captures, each with the same quantities and colours,
    else ``ValueError``) give one table with a first column ``capture``."""
    parts = p if isinstance(p, Mapping) else {None: p}
    first = next(iter(parts.values()))
    cols = [(n, ci, f"{n}.{ch}") for n in first.values for ci, ch in enumerate(first.channels)]
    for name, q in parts.items():
        if list(q.values) != list(first.values) or q.channels != first.channels:
            raise ValueError(f"profile of {name}: quantities or colours differ from the first's")

    def rows():
        for name, q in parts.items():
            for i in range(q.s.size):
                yield (([name] if isinstance(p, Mapping) else [])
                       + [_cell(float(q.s[i])), _cell(float(q.x[i])), _cell(float(q.y[i]))]
                       + [_cell(float(q.values[n][ci, i])) for n, ci, _ in cols])

    lead = ["capture"] if isinstance(p, Mapping) else []
    return _csv_text(header, lead + ["s", "x", "y"] + [c[2] for c in cols], rows())
