"""The direction two polarizer states leave open, predicted from the surface's geometry where
the block is Baek et al.'s diffuse term.

**What two states leave open.** States ``s_a``, ``s_b`` (linear Stokes, ``(3,)``) observe each
row ``m_r`` of the 3x3 block along their plane; the unit normal ``u = s_a x s_b / |.|`` of that
plane is not observed (:func:`unobserved_direction`). The hybrid solve
(:mod:`polrig.solve.hybrid`) takes ``m_r . u`` from the network's prior.

**The diffuse term** (Baek, Jeon, Kim and Kim 2018, *Simultaneous acquisition of polarimetric
SVBRDF and normals*, ACM TOG 37(6) 268, eq. 9; :func:`polrig.optics.pbrdf.linear_rig_mueller`,
``components=("diffuse",)``) is rank one, ``M = k x y^T``: ``x`` the first column of the Fresnel
transmission out of the surface (axis ``n x wo`` in the camera's frame), ``y`` the first row of
the transmission into it (axis ``n x -wi`` in the polarizer stage's frame), both set by the
surface normal ``n``, the view and light directions ``wo``, ``wi`` and the refractive index
``eta``. Where the model selection (:mod:`polrig.solve.model_selection`) chose ``rank_one`` the
two states measure ``x`` (the ratios of ``M (s_a + s_b)``), ``k`` and the incident ratio
``rho = (y . s_b) / (y . s_a)``; ``y . u`` is the one number they miss. With the light and view
directions known (calibration: the light's position, the intrinsics; :class:`DiffuseGeometry`),
``n`` and ``eta`` predict it.

**The fit** (:func:`fit_diffuse_geometry`): per pixel the normal ``n`` (zenith and azimuth about
``wo``), per image one ``eta``, minimising the misfit in the measurement's noise plus a pull
towards a guessed normal,

    w_1 (x_1 - x_hat_1)^2 + w_2 (x_2 - x_hat_2)^2 + w_rho (rho - rho_hat)^2 + g angle(n, n_guess)^2

(``x``, ``rho`` the model's at ``(n, eta)``; ``w`` the inverse variances of the measured ratios,
the delta method on the result's per-element sigma summed over the colours, their covariances
left out (:func:`ratio_weights`); angle in rad). A search, not a descent: the objective has two
branches 180 deg apart in azimuth (``x`` sees the axis, not its sign) and is flat in zenith near
normal exitance. The candidates are a zenith x azimuth grid about ``wo``
(:data:`ZENITH_STEP_DEG`, :data:`AZIMUTH_STEP_DEG`), refined twice by halving around the best;
``eta`` (with the light, where several light fields are given) is the grid value (:data:`ETAS`)
of least total capped cost over a stride sample of the pixels (:data:`ETA_SAMPLE`; cap
:data:`COST_CAP`: pixels the model does not fit must not pick it). The search is compiled
(:mod:`polrig.solve._diffuse_kernel`, shared with the diffuse test's statistic; pixel chunks on
a few threads), the coarse level bounded by the pull (``_diffuse_kernel``, "Bounded by the
pull": the full scan's choices bit for bit): on the 176293 tested pixels of a full mono capture
(2 CPUs, warm) the first pass 2.6 s and the second 0.5 s, where the full scan took 4.3 and 3.6 s
(the previous numpy search, :mod:`polrig.solve._diffuse_numpy`, now the tests' oracle: 250 us a
pixel a pass, 13x slower than the full scan).

:func:`complete_diffuse` fits twice. The first pass pulls towards the network's normal with
:data:`GUESS_WEIGHT`: the two states leave ``n``'s zenith weakly determined where ``x`` is
weakly polarized, and the network's normals are tens of degrees off on shapes it has not seen.
The second pass, at the first's ``eta`` and light, pulls towards the mean of the first pass's
normals over each pixel's 3x3 neighbourhood (:func:`neighbour_mean`) with
:data:`NEIGHBOUR_WEIGHT`: a surface's normal turns by a few degrees from one pixel to the next,
so the neighbours' fits average the noise out of the weakly determined directions, while a
pixel whose data say otherwise (an edge, a crease) keeps its own.

**The completion** (:func:`complete_diffuse`): ``M u = M v (y . u) / (y . v)`` with
``v = s_a + s_b`` and ``y`` the fitted geometry's, per colour, on the ``rank_one`` pixels whose fit
is valid; the block's other directions are kept. Its sigma adds the squared change, per element,
to the selected model's (the model-selection term of :mod:`polrig.solve.model_selection`, Buckland,
Burnham and Augustin 1997: the change's size is what is known of the prediction's error).
Along ``u`` the selected model's sigma is the network prior's, and the change holds the prior's
error there as well, so the sum counts it twice: six of the eight held-out sets have 97.4-97.6 %
of the route's elements within 2 sigma (``benchmarks/results/continuum.md``). Kept anyway,
because the rig's captures need it. A what-if (2026-11-30, not shipped) kept only a share ``g``
of the prior's variance along ``u`` (``1 / (u^T P_r u)``, ``P_r`` the row's prior precision of
:func:`polrig.solve.hybrid.unobserved_precision`). At ``g = 0.7``, where the calibration scenes
pooled cover 95.45 %, the held-out sets came to 93.7-95.8 % (32 samples each). But a capture of
the simulated plastic sphere (512x512 mono, the simulator's hidden errors) fell from 95.9 to
93.1 %, with ``m12`` and ``m22`` from 98.3 and 92.9 % to 83.4 and 83.0 %. (That what-if took the
per-element prior's variance off whole, more than the joint posterior holds along ``u``; taken
off at most each element's own variance, ``g = 0.7`` leaves them at 97.5 and 90.9 % and ``g = 0.3``
at 94.8 and 85.8 %, the six wide sets then at 96.6-96.9 %: ``docs/continuum.md``.) The completion
of rows 1 and 2 errs there by more than the change shows. Dropping the share in row 0 alone, whose
completion the specular term's unfollowed part does not reach (its first row is 0), left
``m01`` and ``m02`` at 88-92 % on the held-out sets and ``m02`` at 78 % on that capture; a
share kept in row 0 alone that such captures bear (0.3: ``m02`` 94-100 %) leaves the sets at
97.1-97.2 %, whose lower block's ``m12`` and ``m21`` err wide as well (2026-12-01). Nor
does the prediction's own spread stand in for that variance (2026-12-01, not shipped): ``m_v``
times the spread of the predicted ratio over the index (+-0.1), the other light field and the
first pass's normal covers 89-93 % of the errors along ``u`` on the held-out sets but 72-87 % on
captures of the spheres (``docs/continuum.md``).

Shapes: images ``(C, 3, 3, H, W)`` as :class:`polrig.solve.reference.ReferenceResult`; directions
``(H, W, 3)`` or ``(3,)`` unit vectors in the camera frame (``docs/conventions.md``): ``view``
surface -> camera, ``light`` surface -> light.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import cv2
import numpy as np

from polrig.optics.pbrdf import linear_rig_mueller, specular_diffuse_blocks
from polrig.solve.chunks import in_chunks
from polrig.solve.reference import ILL_CONDITIONED, ReferenceResult
from polrig.solve.reduced_models import MODELS

__all__ = ["DiffuseGeometry", "geometry_rows", "DiffuseFit", "unobserved_direction", "diffuse_ratios", "specular_block",
           "light_directions", "light_fields",
           "fit_diffuse_geometry", "ratio_weights", "window_sums", "neighbour_mean", "complete_diffuse", "RANK_ONE"]

#: The model selection's code of the rank-one block (Baek's diffuse term).
RANK_ONE = next(m.code for m in MODELS if m.name == "rank_one")
#: The refractive indices searched (one per image).
ETAS = tuple(np.round(np.arange(1.2, 2.01, 0.05), 2))
#: Weight (1/rad^2) of the squared angle from the network's normal in the first pass: a standard
#: deviation of 33 deg. Measured with ``models/continuum/lower_order.py``'s two-state rows on the search
#: scenes (the first 32 of ``search_all_families``, which no reported set holds; PSNR where a model
#: holds, over single-shot, with the second pass): 1 gives +6.83 dB, 3 +7.38, 10 +7.17, 30
#: +6.89; the hybrid with the selection alone +4.75, the one-pass fit with unweighted misfits of
#: before +5.64, the weighted one-pass fit +6.30.
GUESS_WEIGHT = 3.0
#: Weight (1/rad^2) of the squared angle from the neighbours' mean normal in the second pass: a
#: standard deviation of 3.3 deg. The same scenes: without the second pass +6.30 dB, 30 +6.73,
#: 100 +6.95, 300 +7.17, 1000 +7.23, 3000 +7.13 (at a first-pass weight of 10); 300 is the best
#: over all object pixels (+0.89 dB over the selection alone; 1000: +0.88).
NEIGHBOUR_WEIGHT = 300.0
#: Per-pixel cost (chi^2 units) above which a pixel counts as this cap in the choice of ``eta``.
COST_CAP = 16.0
#: Pixels (a stride sample) on which ``eta`` is chosen.
ETA_SAMPLE = 256
#: The coarse grid of normals about the view direction (deg), refined twice by halving.
ZENITH_STEP_DEG, AZIMUTH_STEP_DEG, MAX_ZENITH_DEG = 5.0, 10.0, 85.0
#: Pixels a chunk of the compiled search has at least (a few milliseconds of work each).
_CHUNK_PIXELS = 64


@dataclasses.dataclass(frozen=True)
class DiffuseGeometry:
    """What the rig knows of each pixel's geometry, camera frame.

    ``view``: ``(H, W, 3)`` unit, surface -> camera (the pixel's ray reversed: intrinsics).
    ``light``: ``(3,)`` or ``(H, W, 3)`` unit, surface -> light (the calibrated light position
    seen from the object), or a tuple of such candidates, of which the fit takes per image the
    one of least total cost (e.g. one direction from the object's centre, and the directions at
    the object's depth, :func:`light_directions`: the one holds where the depth varies over the
    image, the other where the light's direction does). ``stage_zero_axis``: ``(3,)`` the polarizer stage's zero axis (the
    incident Stokes frame's x); ``camera_x_axis``: ``(3,)`` the emergent frame's x.
    ``normal_guess``: ``(H, W, 3)`` a normal per pixel (the network's), or None (no pull)."""

    view: np.ndarray
    light: np.ndarray | tuple[np.ndarray, ...]
    stage_zero_axis: np.ndarray
    camera_x_axis: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    normal_guess: np.ndarray | None = None


def geometry_rows(geometry: DiffuseGeometry, y0: int, y1: int) -> DiffuseGeometry:
    """``geometry`` of the image rows ``y0 .. y1``: its per-pixel arrays (``view``, the
    ``(H, W, 3)`` light fields, ``normal_guess``) cut to those rows, the rest as they are."""
    def cut(a):
        return a[y0:y1] if a is not None and np.ndim(a) == 3 else a

    light = tuple(cut(x) for x in geometry.light) if isinstance(geometry.light, tuple) else cut(geometry.light)
    return dataclasses.replace(geometry, view=geometry.view[y0:y1], light=light,
                               normal_guess=cut(geometry.normal_guess))


class DiffuseFit(NamedTuple):
    """:func:`fit_diffuse_geometry`'s result: ``eta`` (float), ``normal`` ``(P, 3)``, ``cost``
    ``(P,)`` (inf where no candidate is valid) and the index of the light candidate taken."""

    eta: float
    normal: np.ndarray
    cost: np.ndarray
    light: int = 0


def unobserved_direction(s_in: np.ndarray) -> np.ndarray | None:
    """The unit vector ``(3,)`` no row of the block is observed along by the states ``s_in``
    ``(N, 3)``, or None when they observe all three directions (or fewer than two): the null
    vector of the states' span when it is a plane (rank 2, relative tolerance 1e-9)."""
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    _, sv, vt = np.linalg.svd(s)
    if len(sv) < 2 or sv[1] <= 1e-9 * sv[0] or (len(sv) == 3 and sv[2] > 1e-9 * sv[0]):
        return None
    return vt[2]


def light_fields(geometry: DiffuseGeometry, ys: np.ndarray, xs: np.ndarray) -> list[np.ndarray]:
    """The geometry's candidate light fields at the pixels ``(ys, xs)``, each ``(P, 3)``."""
    candidates = geometry.light if isinstance(geometry.light, tuple) else (geometry.light,)
    out = []
    for c in (np.asarray(c, np.float64) for c in candidates):
        out.append(np.broadcast_to(c, (len(ys), 3)) if c.ndim == 1 else c[ys, xs])
    return out


def light_directions(light_position: np.ndarray, view: np.ndarray, depth: float = 1.0) -> np.ndarray:
    """Unit vectors surface -> light ``(..., 3)`` for a point light at ``light_position`` ``(3,)``
    (camera frame, the camera at the origin) and the surface at ``depth`` along each pixel's ray
    (the point ``-depth * view``; ``view`` ``(..., 3)`` unit, surface -> camera): the object's
    relief about that depth is left out. Units: ``light_position`` and ``depth`` alike (only
    their ratio matters)."""
    d = np.asarray(light_position, np.float64) + depth * np.asarray(view, np.float64)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def diffuse_ratios(normal, light, view, eta: float, stage_zero_axis, camera_x_axis
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)``, each ``(P, 3)``: the first column and first row of the unit diffuse block at
    ``normal``, ``light``, ``view`` (``(P, 3)``), each over its first element (NaN where the block
    is zero: the normal faces away from the light or the camera)."""
    md = linear_rig_mueller(normal, light, view, kd=1.0, ks=0.0, alpha=0.1, eta=eta, components=("diffuse",),
                            stage_zero_axis=stage_zero_axis, camera_x_axis=camera_x_axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        m00 = np.where(md[:, 0, 0] > 0, md[:, 0, 0], np.nan)[:, None]
        return md[:, :, 0] / m00, md[:, 0, :] / m00


class _Observed(NamedTuple):
    """The measured ratios ``x_hat`` ``(P, 3)`` and ``rho_hat`` ``(P,)`` and the inverse variances
    ``weights`` ``(P, 3)`` of ``x_hat[:, 1]``, ``x_hat[:, 2]`` and ``rho_hat``."""

    x_hat: np.ndarray
    rho_hat: np.ndarray
    weights: np.ndarray


class _Pixels(NamedTuple):
    """What the search reads per pixel (``(P, 3)``; ``guess`` may be None) and per image."""

    view: np.ndarray
    light: np.ndarray
    guess: np.ndarray | None
    guess_weight: float
    stage: np.ndarray
    cam: np.ndarray
    s_a: np.ndarray
    s_b: np.ndarray


def specular_block(light: np.ndarray, view: np.ndarray, eta: float, stage_zero_axis, camera_x_axis) -> np.ndarray:
    """The unit specular block ``(P, 3, 3)`` (``m00 = 1``) of Baek et al.'s specular term at
    each pixel's ``light`` and ``view`` ``(P, 3)`` and refractive index ``eta``, in the rig's
    frames (:func:`polrig.optics.pbrdf.specular_diffuse_blocks`). The term is
    ``F_R(h . wi; eta) D(h) G(wi, wo) / (4 cos theta_o)`` (:mod:`polrig.optics.pbrdf`): the
    Fresnel reflection in the microfacet's plane of incidence, the plane of ``wi`` and ``wo``,
    turned into the incident and emergent frames, so its shape is set by ``light``, ``view``
    and ``eta`` alone; the surface normal and the roughness only scale it (the distribution
    ``D`` and the shadowing ``G``), and it is evaluated at ``n = h``. Zero where the term is not
    defined (``m00`` not positive)."""
    light = np.asarray(light, np.float64).reshape(-1, 3)
    view = np.asarray(view, np.float64).reshape(-1, 3)
    h = light / np.linalg.norm(light, axis=1, keepdims=True) + view / np.linalg.norm(view, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = h / np.linalg.norm(h, axis=1, keepdims=True)
        ms, _ = specular_diffuse_blocks(h, light, view, alpha=1.0, eta=float(eta), stage_zero_axis=stage_zero_axis,
                                        camera_x_axis=camera_x_axis)
        unit = ms / ms[:, :1, :1]
    ok = np.isfinite(unit).all(axis=(1, 2)) & (ms[:, 0, 0] > 0)
    return np.where(ok[:, None, None], unit, 0.0)


def _search_grid(steps_deg: tuple[float, float], refine: int
                 ) -> tuple[tuple[int, int, int], tuple[float, float, float]]:
    """The compiled search's grid (:mod:`polrig.solve._diffuse_kernel`): ``(nz, na, refine)``
    candidates of the coarse zenith x azimuth grid at ``steps_deg`` (zenith 0 to about
    :data:`MAX_ZENITH_DEG`, azimuth round) and its refinements, and ``(dz, da, zmax)`` in rad."""
    nz = int(round(MAX_ZENITH_DEG / steps_deg[0])) + 1
    na = int(round(360.0 / steps_deg[1]))
    return ((nz, na, int(refine)),
            (float(np.deg2rad(steps_deg[0])), float(np.deg2rad(steps_deg[1])), float(np.deg2rad(MAX_ZENITH_DEG))))


def _in_chunks(p: int, work) -> None:
    """``work(sl)`` for slices ``sl`` covering ``range(p)``: :func:`polrig.solve.chunks.in_chunks`
    with chunks of at least :data:`_CHUNK_PIXELS` pixels, four a thread where there are enough
    (the compiled search releases the GIL and its pixels are independent, so the results do not
    depend on the chunking)."""
    in_chunks(p, work, min_pixels=_CHUNK_PIXELS, per_thread=4, name="diffuse-search")


def _search(pix: np.ndarray, eta: float, obs: _Observed, geo: _Pixels, refine: int) -> tuple[np.ndarray, np.ndarray]:
    """Best normal ``(P, 3)`` and its cost ``(P,)`` (inf where no candidate is valid) for the
    pixels ``pix`` at ``eta``: the compiled search
    (:func:`polrig.solve._diffuse_kernel.ratio_search`, chunks on threads, :func:`_in_chunks`)."""
    from polrig.solve import _diffuse_kernel as kern  # numba: imported on first use

    take = lambda a: np.ascontiguousarray(a[pix], np.float64)  # noqa: E731
    view, light, x_hat, rho_hat, weights = (take(a) for a in (geo.view, geo.light, obs.x_hat, obs.rho_hat,
                                                                obs.weights))
    guess = np.zeros_like(view) if geo.guess is None else take(geo.guess)
    stage, cam, s_a, s_b = (np.ascontiguousarray(a, np.float64) for a in (geo.stage, geo.cam, geo.s_a, geo.s_b))
    grid, steps = _search_grid((ZENITH_STEP_DEG, AZIMUTH_STEP_DEG), refine)
    normal, cost = np.empty((len(pix), 3)), np.empty(len(pix))

    def work(sl: slice) -> None:
        kern.ratio_search(view[sl], light[sl], stage, cam, float(eta), grid, steps, x_hat[sl], rho_hat[sl],
                          weights[sl], guess[sl], s_a, s_b, float(geo.guess_weight), geo.guess is not None,
                          cost[sl], normal[sl])

    _in_chunks(len(pix), work)
    return normal, cost


def fit_diffuse_geometry(x_hat: np.ndarray, rho_hat: np.ndarray, weights: np.ndarray, s_a: np.ndarray,
                         s_b: np.ndarray, view: np.ndarray, lights: tuple[np.ndarray, ...], stage_zero_axis,
                         camera_x_axis, normal_guess: np.ndarray | None = None, *,
                         guess_weight: float = GUESS_WEIGHT, etas=ETAS) -> DiffuseFit:
    """Fit the diffuse term's geometry to ``P`` pixels (module docstring, "The fit").

    ``x_hat`` ``(P, 3)``: the measured emergent ratios ``(1, x1, x2)``; ``rho_hat`` ``(P,)``:
    the measured ``(y . s_b) / (y . s_a)``; ``weights`` ``(P, 3)``: the inverse variances of
    ``x1``, ``x2`` and ``rho_hat`` (:func:`ratio_weights`); ``s_a``, ``s_b`` ``(3,)`` the two
    states; ``view`` ``(P, 3)``; ``lights`` candidate light fields, each ``(P, 3)`` or ``(3,)``
    (the one of least total cost is taken, with its ``eta``); ``normal_guess`` ``(P, 3)`` or None,
    pulled towards with ``guess_weight`` (1/rad^2); ``etas`` the indices searched."""
    view = np.asarray(view, np.float64).reshape(-1, 3)
    p = len(view)
    guess = None if normal_guess is None else np.asarray(normal_guess, np.float64).reshape(p, 3)
    fixed = (np.asarray(stage_zero_axis, np.float64), np.asarray(camera_x_axis, np.float64),
             np.asarray(s_a, np.float64), np.asarray(s_b, np.float64))
    geos = [_Pixels(view, np.broadcast_to(np.asarray(li, np.float64), (p, 3)), guess, float(guess_weight),
                    *fixed) for li in lights]
    obs = _Observed(np.asarray(x_hat, np.float64), np.asarray(rho_hat, np.float64),
                    np.asarray(weights, np.float64).reshape(p, 3))
    if p == 0:
        return DiffuseFit(float(etas[0]), np.zeros((0, 3)), np.zeros(0))
    sample = np.arange(0, p, max(1, p // ETA_SAMPLE))[:ETA_SAMPLE]
    totals = [[np.minimum(_search(sample, float(e), obs, geo, refine=2)[1], COST_CAP).sum() for e in etas]
              for geo in geos] if len(geos) * len(etas) > 1 else [[0.0]]
    best_light, best_eta = np.unravel_index(int(np.argmin(totals)), (len(geos), len(etas)))
    eta = float(etas[best_eta])
    normal, cost = _search(np.arange(p), eta, obs, geos[best_light], refine=2)
    return DiffuseFit(eta, normal, cost, int(best_light))


def ratio_weights(total: np.ndarray, variance: np.ndarray, s_a: np.ndarray, s_b: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measured ratios and their inverse variances from blocks summed over the colours.

    ``total`` ``(3, 3, P)``: the blocks; ``variance`` ``(3, 3, P)``: their per-element variances
    (the result's sigma squared, summed over the colours). With ``v = s_a + s_b``:
    ``x_hat = M v / (M v)_0`` ``(P, 3)`` and ``rho_hat = (m_0 . s_b) / (m_0 . s_a)`` ``(P,)``
    (``m_0`` the first row), and ``weights`` ``(P, 3)`` the inverses of ``var x_hat_1``,
    ``var x_hat_2`` and ``var rho_hat`` by the delta method, each element's error independent
    (``var (M v)_r = sum_k var m_rk v_k^2``; ``var (a / b) = (var a + (a / b)^2 var b) / b^2``).
    NaN where ``(M v)_0 <= 0`` (no light the diffuse term can explain); not finite where a
    denominator is 0."""
    v = s_a + s_b
    mv = np.einsum("rkp,k->rp", total, v)
    var_mv = np.einsum("rkp,k->rp", variance, v**2)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_hat = np.where(mv[0] > 0, mv / mv[0], np.nan).T
        m_a, m_b = total[0].T @ s_a, total[0].T @ s_b
        rho_hat = m_b / m_a
        var_x = (var_mv[1:] + x_hat.T[1:] ** 2 * var_mv[0]) / mv[0] ** 2
        var_rho = (variance[0].T @ s_b**2 + rho_hat**2 * (variance[0].T @ s_a**2)) / m_a**2
        weights = 1.0 / np.stack([var_x[0], var_x[1], var_rho], axis=1)
    return x_hat, rho_hat, weights


def window_sums(values: np.ndarray, chosen: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """The sums of ``values`` ``(..., H, W)`` over the ``chosen`` pixels (bool, broadcastable to
    ``values``) in each pixel's ``window`` x ``window`` neighbourhood (itself included; nothing
    beyond the image's edge), plane by plane, and how many pixels each sum holds; both
    ``(..., H, W)`` float64 (``values``' units; a count)."""
    chosen = np.broadcast_to(np.asarray(chosen, bool), np.shape(values))
    r = int(window) // 2

    def box(a: np.ndarray) -> np.ndarray:
        out = np.empty(a.shape)
        for i in np.ndindex(a.shape[:-2]):
            out[i] = cv2.boxFilter(a[i], cv2.CV_64F, (2 * r + 1, 2 * r + 1), normalize=False,
                                   borderType=cv2.BORDER_CONSTANT)
        return out

    return box(np.where(chosen, np.asarray(values, np.float64), 0.0)), box(chosen.astype(np.float64))


def neighbour_mean(normal: np.ndarray, valid: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """The mean unit normal ``(P, 3)`` over each pixel's 3x3 neighbourhood (itself included) of
    the ``valid`` ``(P,)`` normals ``normal`` ``(P, 3)`` at rows ``ys`` and columns ``xs`` of an
    image (:func:`window_sums`, within the box that holds the pixels: nothing outside it is
    valid); a pixel with no valid neighbour, or whose neighbours' normals cancel, keeps its own."""
    if not len(ys):
        return normal
    y0, x0 = ys.min(), xs.min()
    ys, xs = ys - y0, xs - x0
    box = (int(ys.max()) + 1, int(xs.max()) + 1)
    img, chosen = np.zeros((3, *box)), np.zeros(box, bool)
    img[:, ys[valid], xs[valid]] = normal[valid].T
    chosen[ys[valid], xs[valid]] = True
    total, count = window_sums(img, chosen, 3)
    mean = total[:, ys, xs].T
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    ok = (count[0, ys, xs] > 0) & (norm[:, 0] > 1e-9)
    return np.where(ok[:, None], mean / np.where(ok[:, None], norm, 1.0), normal)


def complete_diffuse(result: ReferenceResult, s_in: np.ndarray, geometry: DiffuseGeometry, *,
                     eta: float | None = None, light: int | None = None
                     ) -> tuple[ReferenceResult, np.ndarray, float | None]:
    """Predict the unobserved direction of the ``rank_one`` pixels of ``result`` (a solve of the
    states ``s_in`` ``(2, 3)`` with the model selection, whose ``models`` map says which) from
    the diffuse term's geometry (module docstring). ``eta`` and ``light`` (an index into the
    geometry's candidate light fields), given together: the image's refractive index and light
    as chosen elsewhere (:func:`polrig.solve.diffuse_test.test_diffuse`), not fitted here.
    Returns the new result (arrays copied), the completed pixels ``(C, H, W)`` bool and the
    ``eta`` used (None where nothing was fitted). States that observe every direction (or a
    result without a model map) return ``result`` unchanged."""
    if (eta is None) != (light is None):
        raise ValueError("give eta and light together, or neither")
    s_in = np.asarray(s_in, np.float64).reshape(-1, 3)
    u = unobserved_direction(s_in)
    n_col, _, _, h, w = result.mueller.shape
    none = np.zeros((n_col, h, w), bool)
    if u is None or result.models is None or len(s_in) != 2:
        return result, none, None
    s_a, s_b = s_in
    v = s_a + s_b
    code = result.models.code
    rank_one = (code == RANK_ONE) & ((result.mask & ILL_CONDITIONED) == 0)  # (C, H, W)
    ok_pix = rank_one.any(axis=0)
    ys, xs = np.nonzero(ok_pix)
    if not len(ys):
        return result, none, None
    m = result.mueller.astype(np.float64)[..., ys, xs]  # (C, 3, 3, P)
    total = m.sum(axis=0)  # the colours share the geometry
    variance = (result.sigma.astype(np.float64)[..., ys, xs] ** 2).sum(axis=0)
    x_hat, rho_hat, weights = ratio_weights(total, variance, s_a, s_b)
    good = np.isfinite(x_hat).all(axis=1) & np.isfinite(rho_hat) & np.isfinite(weights).all(axis=1)
    ys, xs, m, x_hat, rho_hat, weights = ys[good], xs[good], m[..., good], x_hat[good], rho_hat[good], weights[good]
    pick = lambda a: None if a is None else np.asarray(a, np.float64).reshape(h, w, 3)[ys, xs]  # noqa: E731
    lights = light_fields(geometry, ys, xs)
    view = pick(geometry.view)
    if eta is not None:
        lights, etas = [lights[light]], (float(eta),)
    else:
        etas = ETAS
    fit = fit_diffuse_geometry(x_hat, rho_hat, weights, s_a, s_b, view, lights, geometry.stage_zero_axis,
                               geometry.camera_x_axis, pick(geometry.normal_guess), etas=etas)
    # the second pass: towards the neighbours' normals, at the first pass's index and light
    smooth = neighbour_mean(fit.normal, np.isfinite(fit.cost), ys, xs)
    second = fit_diffuse_geometry(x_hat, rho_hat, weights, s_a, s_b, view, [lights[fit.light]],
                                  geometry.stage_zero_axis, geometry.camera_x_axis, smooth,
                                  guess_weight=NEIGHBOUR_WEIGHT, etas=(fit.eta,))
    fit = fit._replace(normal=second.normal, cost=np.where(np.isfinite(fit.cost), second.cost, np.inf))
    _, y = diffuse_ratios(fit.normal, np.broadcast_to(lights[fit.light], view.shape), view, fit.eta,
                          geometry.stage_zero_axis, geometry.camera_x_axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (y @ u) / (y @ v)
    done = np.isfinite(ratio) & np.isfinite(fit.cost)
    ys, xs, m, ratio = ys[done], xs[done], m[..., done], ratio[done]
    m_v = np.einsum("crkp,k->crp", m, v)
    m_u = np.einsum("crkp,k->crp", m, u)
    colours = rank_one[:, ys, xs]  # (C, P): the colours the selection gave the rank-one block
    change = np.where(colours[:, None, :], m_v * ratio - m_u, 0.0)
    new = m + change[:, :, None, :] * u[None, None, :, None]
    mueller, sigma = result.mueller.copy(), result.sigma.copy()
    old_sd = sigma[..., ys, xs].astype(np.float64)
    mueller[..., ys, xs] = new
    sigma[..., ys, xs] = np.sqrt(old_sd**2 + (new - m) ** 2)
    completed = none.copy()
    completed[:, ys, xs] = colours
    out = dataclasses.replace(result, mueller=mueller, sigma=sigma)
    return out, completed, fit.eta
