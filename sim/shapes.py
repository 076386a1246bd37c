"""Analytic shapes with vectorised ray intersection, each in its own local frame (metres).

Every shape answers :meth:`Shape.intersect` for ``N`` rays at once: origins ``o`` and unit
directions ``d`` ``(N, 3)`` give the ray parameter ``t`` ``(N,)`` of the nearest hit with
``t > t_min`` (``inf`` for a miss) and the outward geometric normal ``(N, 3)`` there.
:meth:`Shape.shading_normal` returns the normal used for shading (the geometric one, except for
normal-mapped and height-field surfaces where it follows the surface detail).

Intersections are closed forms (sphere, plane, slab test for the box, quadric plus caps for the
cylinder); height fields and implicit solids (blob, torus) are found by dense marching followed
by bisection of the sign change (Musgrave's height-field ray marching, as in Pharr, Jakob and
Humphreys, *Physically Based Rendering*, 3rd ed., sec. 3.x/4.x on shapes and acceleration).
Misses never raise: NaN or infinite input rays just miss.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Callable

import numpy as np

from polrig.sim.geometry import unit

T_MIN = 1e-6

_ERR = dict(divide="ignore", invalid="ignore", over="ignore")


class Shape(abc.ABC):
    """A surface in its local frame."""

    @abc.abstractmethod
    def intersect(self, o: np.ndarray, d: np.ndarray,
                  t_min: float = T_MIN) -> tuple[np.ndarray, np.ndarray]:
        """``(t (N,), normal (N, 3))`` of the nearest hit beyond ``t_min`` (``t = inf``: miss)."""

    def shading_normal(self, p: np.ndarray, n_geo: np.ndarray) -> np.ndarray:
        """Shading normals at local hit points ``p`` ``(N, 3)`` (default: geometric)."""
        return n_geo

    @property
    def bound_radius_m(self) -> float:
        """Radius of a sphere about the local origin enclosing the shape (``inf``: unbounded);
        the renderer skips rays that miss it."""
        return float("inf")

    def to_json(self) -> dict:
        d = {"type": type(self).__name__}
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            if isinstance(v, (int, float, str)):
                d[f.name] = v
            elif isinstance(v, (tuple, list, np.ndarray)):
                d[f.name] = np.asarray(v).tolist() if np.asarray(v).size <= 16 else \
                    f"array{np.asarray(v).shape}"
        return d


def _clean(o: np.ndarray, d: np.ndarray, t: np.ndarray,
           n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Misses, non-finite hits and rays with non-finite origin or direction get ``t = inf``
    and a zero normal."""
    hit = (np.isfinite(t) & np.isfinite(n).all(axis=1) & np.isfinite(o).all(axis=1)
           & np.isfinite(d).all(axis=1))
    return np.where(hit, t, np.inf), np.where(hit[:, None], n, 0.0)


def _nearest(*cands: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    t = np.full(cands[0][0].shape, np.inf)
    n = np.zeros(cands[0][0].shape + (3,))
    for tc, nc in cands:
        closer = tc < t
        t = np.where(closer, tc, t)
        n = np.where(closer[:, None], nc, n)
    return t, n


@dataclasses.dataclass(frozen=True)
class Sphere(Shape):
    """Sphere of ``radius_m`` centred on the local origin."""

    radius_m: float

    @property
    def bound_radius_m(self) -> float:
        return float(self.radius_m)

    def intersect(self, o, d, t_min=T_MIN):
        with np.errstate(**_ERR):
            b = np.einsum("ij,ij->i", o, d)
            c = np.einsum("ij,ij->i", o, o) - self.radius_m ** 2
            disc = b * b - c
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
            t1, t2 = -b - sq, -b + sq
            t = np.where(t1 > t_min, t1, np.where(t2 > t_min, t2, np.inf))
            t = np.where(np.isfinite(t), t, np.inf)
            n = (o + np.where(np.isfinite(t), t, 0.0)[:, None] * d) / self.radius_m
        return _clean(o, d, t, n)


@dataclasses.dataclass(frozen=True)
class Rectangle(Shape):
    """Two-sided rectangle in the local ``z = 0`` plane, ``|x| <= half_x_m``, ``|y| <= half_y_m``
    (``inf`` half sizes make an infinite plane). Normal ``+z``.

    ``normal_map``: optional ``(h, w, 3)`` tangent-space unit normals over the rectangle
    (row 0 at ``y = +half_y_m``, column 0 at ``x = -half_x_m``), sampled bilinearly for shading.
    """

    half_x_m: float = np.inf
    half_y_m: float = np.inf
    normal_map: np.ndarray | None = None

    @property
    def bound_radius_m(self) -> float:
        return float(np.hypot(self.half_x_m, self.half_y_m))

    def intersect(self, o, d, t_min=T_MIN):
        with np.errstate(**_ERR):
            t = -o[:, 2] / d[:, 2]
            x, y = o[:, 0] + t * d[:, 0], o[:, 1] + t * d[:, 1]
            ok = (t > t_min) & (np.abs(x) <= self.half_x_m) & (np.abs(y) <= self.half_y_m)
        t = np.where(ok, t, np.inf)
        n = np.zeros_like(o)
        n[:, 2] = 1.0
        return _clean(o, d, t, n)

    def shading_normal(self, p, n_geo):
        if self.normal_map is None:
            return n_geo
        nm = np.asarray(self.normal_map, dtype=np.float64)
        h, w = nm.shape[:2]
        u = (p[:, 0] / self.half_x_m * 0.5 + 0.5) * (w - 1)
        v = (0.5 - p[:, 1] / self.half_y_m * 0.5) * (h - 1)
        u0 = np.clip(np.floor(u).astype(np.int64), 0, max(w - 2, 0))
        v0 = np.clip(np.floor(v).astype(np.int64), 0, max(h - 2, 0))
        fu, fv = np.clip(u - u0, 0, 1)[:, None], np.clip(v - v0, 0, 1)[:, None]
        u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
        s = (nm[v0, u0] * (1 - fu) * (1 - fv) + nm[v0, u1] * fu * (1 - fv)
             + nm[v1, u0] * (1 - fu) * fv + nm[v1, u1] * fu * fv)
        return unit(s)


@dataclasses.dataclass(frozen=True)
class Box(Shape):
    """Axis-aligned box centred on the local origin with half sizes ``half_m`` (x, y, z)."""

    half_m: tuple[float, float, float]

    @property
    def bound_radius_m(self) -> float:
        return float(np.linalg.norm(self.half_m))

    def intersect(self, o, d, t_min=T_MIN):
        h = np.asarray(self.half_m, dtype=np.float64)
        with np.errstate(**_ERR):
            inv = 1.0 / d
            t1, t2 = (-h - o) * inv, (h - o) * inv
            t1 = np.where(np.isnan(t1), -np.inf, t1)
            t2 = np.where(np.isnan(t2), np.inf, t2)
            lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
            t_near, t_far = lo.max(axis=1), hi.min(axis=1)
            hit = (t_near <= t_far) & (t_far > t_min)
            entering = t_near > t_min
            t = np.where(hit, np.where(entering, t_near, t_far), np.inf)
            ax = np.where(entering, lo.argmax(axis=1), hi.argmin(axis=1))
        n = np.zeros_like(o)
        p_ax = np.take_along_axis(o + np.where(np.isfinite(t), t, 0.0)[:, None] * d,
                                  ax[:, None], axis=1)[:, 0]
        n[np.arange(len(ax)), ax] = np.sign(p_ax)
        return _clean(o, d, t, n)


@dataclasses.dataclass(frozen=True)
class Cylinder(Shape):
    """Closed cylinder of ``radius_m`` about the local ``z`` axis, ``|z| <= half_height_m``."""

    radius_m: float
    half_height_m: float

    @property
    def bound_radius_m(self) -> float:
        return float(np.hypot(self.radius_m, self.half_height_m))

    def intersect(self, o, d, t_min=T_MIN):
        r, hh = self.radius_m, self.half_height_m
        with np.errstate(**_ERR):
            a = d[:, 0] ** 2 + d[:, 1] ** 2
            b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
            c = o[:, 0] ** 2 + o[:, 1] ** 2 - r * r
            disc = b * b - a * c
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
            side = []
            for sgn in (-1.0, 1.0):
                ts = (-b + sgn * sq) / a
                z = o[:, 2] + ts * d[:, 2]
                ok = (ts > t_min) & (np.abs(z) <= hh)
                ts = np.where(ok, ts, np.inf)
                p = o + np.where(ok, ts, 0.0)[:, None] * d
                ns = np.stack([p[:, 0] / r, p[:, 1] / r, np.zeros_like(ts)], axis=1)
                side.append((ts, ns))
            caps = []
            for zc in (-hh, hh):
                tc = (zc - o[:, 2]) / d[:, 2]
                x, y = o[:, 0] + tc * d[:, 0], o[:, 1] + tc * d[:, 1]
                ok = (tc > t_min) & (x * x + y * y <= r * r)
                nc = np.zeros_like(o)
                nc[:, 2] = np.sign(zc)
                caps.append((np.where(ok, tc, np.inf), nc))
        return _clean(o, d, *_nearest(*side, *caps))


HeightFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class HeightField(Shape):
    """Height field ``z = height(x, y)`` over ``|x| <= half_x_m``, ``|y| <= half_y_m`` (local),
    seen from above (``+z``), with heights within ``[z_min_m, z_max_m]``. It is a surface, not a
    solid: a ray entering the bounding slab below the surface (through a side) misses.

    ``height`` and ``gradient`` are vectorised callables of local ``x, y`` (metres);
    ``gradient`` returns ``(dz/dx, dz/dy)``. ``steps`` marching samples per ray before the
    bisection, enough to not skip a feature narrower than the ray's path through the slab
    divided by ``steps``.
    """

    half_x_m: float
    half_y_m: float
    z_min_m: float
    z_max_m: float
    height: HeightFn
    gradient: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    steps: int = 48
    bisections: int = 24

    @property
    def bound_radius_m(self) -> float:
        return float(np.sqrt(self.half_x_m ** 2 + self.half_y_m ** 2
                             + max(abs(self.z_min_m), abs(self.z_max_m)) ** 2))

    def _slab(self, o, d, t_min):
        box = Box((self.half_x_m, self.half_y_m, 0.5 * (self.z_max_m - self.z_min_m)))
        zc = 0.5 * (self.z_max_m + self.z_min_m)
        oc = o - np.array([0.0, 0.0, zc])
        h = np.asarray(box.half_m)
        with np.errstate(**_ERR):
            t1, t2 = (-h - oc) / d, (h - oc) / d
            t1 = np.where(np.isnan(t1), -np.inf, t1)
            t2 = np.where(np.isnan(t2), np.inf, t2)
            t0 = np.maximum(np.minimum(t1, t2).max(axis=1), t_min)
            t1_ = np.maximum(t1, t2).min(axis=1)
        return t0, t1_, t0 < t1_

    def intersect(self, o, d, t_min=T_MIN):
        t_out = np.full(o.shape[0], np.inf)
        n_out = np.zeros_like(o)
        t0, t1, ok = self._slab(o, d, t_min)
        idx = np.nonzero(ok)[0]
        if idx.size == 0:
            return t_out, n_out
        o_, d_ = o[idx], d[idx]

        def above(p: np.ndarray) -> np.ndarray:  # < 0 below the surface
            return p[..., 2] - self.height(p[..., 0], p[..., 1])

        t_hit, found, starts_below = march_to_surface(above, o_, d_, t0[idx], t1[idx],
                                                      self.steps, self.bisections)
        keep = found & ~starts_below  # entering below the surface: through a side, a miss
        p = o_[keep] + t_hit[keep, None] * d_[keep]
        gx, gy = self.gradient(p[:, 0], p[:, 1])
        t_out[idx[keep]] = t_hit[keep]
        n_out[idx[keep]] = unit(np.stack([-gx, -gy, np.ones_like(gx)], axis=1))
        return _clean(o, d, t_out, n_out)


ImplicitFn = Callable[[np.ndarray], np.ndarray]


def march_to_surface(f: ImplicitFn, o: np.ndarray, d: np.ndarray, t0: np.ndarray,
                     t1: np.ndarray, steps: int, bisections: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First crossing into ``f(p) <= 0`` along rays ``o + t d`` within ``[t0, t1]`` (each
    ``(M,)``): ``steps`` uniform samples, then ``bisections`` halvings of the bracketing step
    (Musgrave's height-field marching generalised to an implicit function, PBRT 3rd ed.).

    ``f`` maps points ``(..., 3)`` to values ``(...)``, negative inside. Returns ``t`` (the
    inside end of the final bracket), ``found`` and ``starts_inside`` (the first sample was
    already inside), each ``(M,)``. A feature thinner than ``(t1 - t0) / steps`` along the ray
    can be skipped.
    """
    rows = np.arange(len(t0))
    s = np.linspace(0.0, 1.0, steps + 1)
    ts = t0[:, None] + (t1 - t0)[:, None] * s[None, :]  # (M, S)
    with np.errstate(**_ERR):
        inside = f(o[:, None, :] + ts[..., None] * d[:, None, :]) <= 0.0
    first = np.argmax(inside, axis=1)
    found = inside[rows, first]
    lo = ts[rows, np.maximum(first - 1, 0)]
    hi = ts[rows, first]
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        with np.errstate(**_ERR):
            go_hi = f(o + mid[:, None] * d) <= 0.0
        hi = np.where(go_hi, mid, hi)
        lo = np.where(go_hi, lo, mid)
    return hi, found, found & (first == 0)


def _bounding_sphere_span(o: np.ndarray, d: np.ndarray, radius_m: float,
                          t_min: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t0, t1, ok)``: the part of each ray beyond ``t_min`` inside the sphere of
    ``radius_m`` about the local origin."""
    with np.errstate(**_ERR):
        b = np.einsum("ij,ij->i", o, d)
        disc = b * b - (np.einsum("ij,ij->i", o, o) - radius_m ** 2)
        sq = np.sqrt(np.where(disc > 0, disc, np.nan))
        t0, t1 = np.maximum(-b - sq, t_min), -b + sq
        ok = np.isfinite(t0) & np.isfinite(t1) & (t0 < t1)
    return t0, t1, ok


class _MarchedSolid(Shape):
    """A closed solid ``f(p) <= 0`` inside its bounding sphere, intersected by
    :func:`march_to_surface`; the normal is the normalised gradient of ``f``. Rays are meant
    to start outside: one starting inside the solid (or with a zero direction) misses."""

    steps: int
    bisections: int

    @abc.abstractmethod
    def inside(self, p: np.ndarray) -> np.ndarray:
        """The implicit function at local points ``(..., 3)``: negative inside (metres)."""

    @abc.abstractmethod
    def outward_gradient(self, p: np.ndarray) -> np.ndarray:
        """Gradient of :meth:`inside` at local points ``(N, 3)`` (not normalised)."""

    def intersect(self, o, d, t_min=T_MIN):
        t_out = np.full(o.shape[0], np.inf)
        n_out = np.zeros_like(o)
        t0, t1, ok = _bounding_sphere_span(o, d, self.bound_radius_m, t_min)
        ok &= np.isfinite(o).all(axis=1) & np.isfinite(d).all(axis=1) & d.any(axis=1)
        idx = np.nonzero(ok)[0]
        if idx.size == 0:
            return t_out, n_out
        t_hit, found, starts_inside = march_to_surface(self.inside, o[idx], d[idx], t0[idx],
                                                       t1[idx], self.steps, self.bisections)
        found &= ~starts_inside
        hit = idx[found]
        t_out[hit] = t_hit[found]
        n_out[hit] = unit(self.outward_gradient(o[hit] + t_out[hit, None] * d[hit]))
        return _clean(o, d, t_out, n_out)


@dataclasses.dataclass(frozen=True)
class Blob(_MarchedSolid):
    """A star-shaped "blobby" solid: along the unit direction ``u`` from its centre its radius
    is ``radius_m * exp(b(u))`` with ``b(u) = sum_k a_k exp((u . c_k - 1) / w_k^2)``: bumps
    (``a_k > 0``) and dents (``a_k < 0``) about unit directions ``c_k`` with angular widths
    ``w_k`` (radians, roughly the Gaussian sigma of the angle from ``c_k``); the exponential
    keeps the radius positive however the dents overlap. Smooth, with convex, concave and
    saddle regions, in the spirit of the blobby shapes of Johnson and Adelson (CVPR 2011) used
    to train shape from shading.

    Implicit function ``f(p) = |p| - r(p / |p|)``; with ``g = grad_u r = r grad_u b`` its
    gradient is ``u - (I - u u^T) g / |p|``.
    """

    radius_m: float
    centres: tuple[tuple[float, float, float], ...]
    widths: tuple[float, ...]
    amplitudes: tuple[float, ...]
    steps: int = 64
    bisections: int = 24

    @property
    def bound_radius_m(self) -> float:
        a = np.asarray(self.amplitudes, float)
        return float(self.radius_m * np.exp(np.clip(a, 0, None).sum()) * 1.001)

    def _radius_and_grad(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = unit(np.asarray(self.centres, float).reshape(-1, 3))
        w2 = np.asarray(self.widths, float) ** 2
        e = np.asarray(self.amplitudes, float) * np.exp((u @ c.T - 1.0) / w2)  # (..., K)
        r = self.radius_m * np.exp(e.sum(axis=-1))
        return r, r[..., None] * ((e / w2) @ c)

    def inside(self, p):
        rho = np.linalg.norm(p, axis=-1)
        r, _ = self._radius_and_grad(p / np.maximum(rho, 1e-300)[..., None])
        return rho - r

    def outward_gradient(self, p):
        rho = np.maximum(np.linalg.norm(p, axis=-1), 1e-300)
        u = p / rho[:, None]
        _, g = self._radius_and_grad(u)
        g_tan = g - np.einsum("ij,ij->i", g, u)[:, None] * u
        return u - g_tan / rho[:, None]


@dataclasses.dataclass(frozen=True)
class Torus(_MarchedSolid):
    """Solid torus about the local ``z`` axis: tube of ``minor_radius_m`` around the circle of
    ``major_radius_m`` in the ``z = 0`` plane. ``f(p) = (rho - R)^2 + z^2 - r^2`` with
    ``rho = hypot(x, y)``; its gradient is ``2 ((rho - R) (x, y) / rho, z)``."""

    major_radius_m: float
    minor_radius_m: float
    steps: int = 64
    bisections: int = 24

    @property
    def bound_radius_m(self) -> float:
        return float((self.major_radius_m + self.minor_radius_m) * 1.001)

    def inside(self, p):
        rho = np.hypot(p[..., 0], p[..., 1])
        return (rho - self.major_radius_m) ** 2 + p[..., 2] ** 2 - self.minor_radius_m ** 2

    def outward_gradient(self, p):
        rho = np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-300)
        k = (rho - self.major_radius_m) / rho
        return np.stack([k * p[:, 0], k * p[:, 1], p[:, 2]], axis=1)


def gaussian_bumps(centres_m: np.ndarray, sigmas_m: np.ndarray,
                   amplitudes_m: np.ndarray) -> tuple[HeightFn, Callable]:
    """Height and gradient callables of a sum of isotropic Gaussian bumps (metres)."""
    c = np.asarray(centres_m, float).reshape(-1, 2)
    s = np.asarray(sigmas_m, float).reshape(-1)
    a = np.asarray(amplitudes_m, float).reshape(-1)

    def height(x, y):
        z = np.zeros(np.broadcast_shapes(np.shape(x), np.shape(y)))
        for (cx, cy), sk, ak in zip(c, s, a):
            z = z + ak * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sk * sk))
        return z

    def gradient(x, y):
        gx = np.zeros(np.broadcast_shapes(np.shape(x), np.shape(y)))
        gy = np.zeros_like(gx)
        for (cx, cy), sk, ak in zip(c, s, a):
            e = ak * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sk * sk)) / (sk * sk)
            gx = gx - e * (x - cx)
            gy = gy - e * (y - cy)
        return gx, gy

    return height, gradient


def wave_normal_map(size: int = 64, cycles: float = 4.0, slope: float = 0.35) -> np.ndarray:
    """A ``(size, size, 3)`` tangent-space normal map of crossed sine waves (unit normals)."""
    g = np.linspace(0, 2 * np.pi * cycles, size)
    gx = slope * np.cos(g)[None, :] * np.ones((size, 1))
    gy = slope * np.cos(g)[:, None] * np.ones((1, size)) * 0.5
    return unit(np.stack([-gx, -gy, np.ones_like(gx)], axis=-1))
