"""Two polarizer states: the diffuse term tested on the samples alone, without the network's
prior.

**Why.** At two states the model selection (:mod:`polrig.solve.model_selection`, "At any rank")
tests its candidates on the hybrid's posterior system: along the direction ``u`` the two states
leave open, the network's prior decides. The network's estimate leans toward lower-order blocks
the truth is not, so that test's level is only as good as the network's calibration (false
acceptance 1.3-21.9 % per held-out set, ``benchmarks/results/continuum_models.md``). The
completion at two states (:func:`polrig.solve.diffuse_geometry.complete_diffuse`) needs one
model, Baek's diffuse term with the rig's geometry, and this module tests that model on what the
two frames measure and nothing else.

**The statistic** (:func:`diffuse_statistic`). State ``j``'s frame measures, per colour ``c``,
the Stokes vector ``S_cj = M_c s_j``: its four analyzer samples give the weighted least-squares
estimate and its information ``Q_cj = A^T W A`` (``A`` the analyzer rows, ``W`` the inverse
variances of the noise model; :func:`state_stokes`). The diffuse term predicts
``S_cj = k_c (y . s_j) x`` (``x``, ``y`` the unit diffuse block's first column and row at the
normal ``n``, :func:`polrig.solve.diffuse_geometry.diffuse_ratios`; ``eta`` and the light per
image; ``k_c >= 0`` the colour's albedo times the shading). Against the unconstrained block,
whose nine elements per colour reproduce the six measured numbers exactly, the likelihood-ratio
statistic is

    T = min_{n, k >= 0} sum_cj (S_cj - k_c (y . s_j) x)^T Q_cj (S_cj - k_c (y . s_j) x),

``chi^2`` with ``6 C - (2 + C)`` degrees of freedom where the model holds (Wilks 1938; 13 for three
colours, 3 for one; :func:`degrees_of_freedom`). ``k_c`` is in closed form at each candidate
normal (a weighted projection, clipped at 0), the normal a grid search (the completion's, on
:data:`STEPS_DEG` refined :data:`REFINE` times, to steps of 0.6 deg of zenith and 1.25 deg of
azimuth; finer steps moved the held-out seen families' median ``T`` by 0.1-0.3, acceptance by
0.4 points at most), compiled (:mod:`polrig.solve._diffuse_kernel`, pixel chunks on a few
threads: about 7 us a pixel on 2 CPUs, some 2.5 s for a full 612x512 image; the previous numpy
search, :mod:`polrig.solve._diffuse_numpy`, now the tests' oracle: 145 us, 20x slower). A pixel
is accepted where ``T`` is at most the level-``alpha`` critical value (:func:`test_diffuse`).

**eta and the light**, one per image: of the refractive indices
(:data:`polrig.solve.diffuse_geometry.ETAS`) and the geometry's candidate light fields, the pair
of least total statistic over a stride sample of the pixels (:data:`ETA_SAMPLE`), each pixel's
capped at :data:`CAP_QUANTILE`'s critical value so that the pixels the model does not explain
do not choose them; every other index first, then the best one's neighbours (the total is
smooth in ``eta``). The completion (:func:`complete_tested_diffuse`) fits its normals at the same
pair.

**The specular term** (``specular=True``; captures with ``--models diffuse`` use it). Baek's
specular term ``k_s,c B`` adds to the diffuse one; its unit block ``B``
(:func:`polrig.solve.diffuse_geometry.specular_block`) is set by the light, the view and
``eta`` alone (the normal and the roughness scale it), so it brings one more albedo per colour
and nothing to search: ``T_s`` minimises over both albedos ``>= 0`` (the two-albedo least
squares in closed form in the same compiled search, else the better edge), ``chi^2(4 C - 2)``
where the model holds. The term is taken where it explains significantly more than the diffuse
term alone, ``T - T_s`` beyond ``chi^2(C)``'s critical value at :data:`SPECULAR_LEVEL` (a
likelihood ratio of nested models), and that pixel is then accepted where ``T_s`` is at most
``chi^2(4 C - 2)``'s critical value; elsewhere the specular albedo is 0 and the diffuse term's
test decides as without it. Where the term is taken, the completion
(:func:`complete_tested_diffuse`) subtracts it from the samples, the prior and the hybrid's
estimate, estimates and completes the diffuse rest as without it and adds it back, its sigma
with the albedo's least-squares variance times ``(B - B[:, 0] B[0, :] / B[0, 0])^2``: an error
of the albedo shifts the rest by a multiple of ``B``, whose first row and column the rank-one
estimate keeps (measured) and whose other elements it predicts from them. (With the whole block,
``B^2``, 95.5-97.6 % of the held-out sets' elements were within 2 sigma, six sets above 97; with
the open direction's part alone, 91 % on the tests' synthetic diffuse + specular truth.) Why: the dielectric scenes the
rig is for (Baek's plastic) have a specular part at almost every pixel, and two states cannot
tell a weak one from noise: the diffuse term alone was accepted with it and its rank-one
estimate carried it as a bias (captures of the simulated plastic sphere: ``m11`` and ``m22`` 36
rms against 20-25 for the plain hybrid). Measured on the held-out sets:
``benchmarks/results/continuum_models.md``, "The diffuse term, with the specular term where
significant".

**The specular term not taken.** Where the term does not pass its test, the diffuse term alone
is estimated, but a weak specular part is still there: Baek's plastic has one at almost every
pixel, and two states tell it from noise only where it is strong. Whatever of it the rank-one
estimate cannot follow, ``k_u (B - B[:, 0] B[0, :] / B[0, 0])`` with ``k_u`` the albedo the
two-albedo fit gave there, is then a bias of the estimate (``m11`` low and ``m22`` high on the
plastic sphere: mean error -1.3 and +1.5 sigma on those pixels, 83 and 78 % within 2 sigma). Its
square is added to the sigma's: the model-selection term of the chosen model against the larger
one (Buckland, Burnham and Augustin 1997), as the selection does for its candidates. On captures
of the plastic sphere (0/90, the simulator's hidden errors) the object's ``m11`` and ``m22``
go from 89.0 and 87.9 % within 2 sigma to 93.2 and 93.4 % (512x512 mono) and from 92.0
and 90.2 % to 94.6 and 93.7 % (the full colour sensor), the estimate unchanged. (Taking the term
wherever its albedo fits above 0 mends those captures as well and raises their PSNR by 0.2-0.3
dB, but costs the 64x64 held-out sets 0.1-0.6 dB.)

**False acceptance**: accepting is wrong only where the samples can tell, where the test rejects
the truth's samples with probability at least 0.95. The model selection at four states takes
the noncentral chi-square's power point for that (the truth's own statistic, ``T`` of the
noise-free ``S``, at least :func:`polrig.solve.model_selection.detectable_noncentrality`). Here
it overstates the power: ``T`` minimises over the normal, and where the misfit is flat in the
normal while the residual turns with it, the choice of normal absorbs the noise's cross term
with the residual, so ``T`` falls below the noncentral chi-square. The benchmark therefore
measures the power by Monte Carlo, the test's statistics and decision (:func:`decide`) on noise
drawn about the truth (``models/continuum/lower_order.py``, ``diffuse_test_power``), at the pixels past the
noncentral power point. What the two states cannot tell,
a truth off the diffuse term along ``u`` alone, no test on them can; there the completion's error
is the truth's distance from the diffuse term along ``u``, and the benchmark reports that too
(``models/continuum/``: the PSNR over every object pixel, and the false acceptance in the
prior's metric). Measured: ``benchmarks/results/continuum_models.md``.

Shapes: Stokes images ``(C, 3, H, W)``, per-pixel arrays flattened to ``P`` pixels where noted;
directions unit vectors in the camera frame as :mod:`polrig.solve.diffuse_geometry`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve.chunks import mask_box
from polrig.solve.diffuse_geometry import (
    ETAS,
    RANK_ONE,
    DiffuseGeometry,
    _in_chunks,
    _search_grid,
    complete_diffuse,
    diffuse_ratios,
    light_fields,
    specular_block,
    unobserved_direction,
    window_sums,
)
from polrig.solve.model_selection import (
    SelectionOptions,
    chi2_critical,
    chi2_sf,
    select_models,
)
from polrig.solve.reference import ReferenceResult, forward_measurements

__all__ = ["state_stokes", "degrees_of_freedom", "diffuse_statistic", "DiffuseTest", "decide", "test_diffuse",
           "neighbour_bias", "complete_tested_diffuse",
           "specular_term"]

#: The normal's coarse grid (zenith, azimuth steps in deg) and its refinements (each halves the
#: steps): 0.6 deg of zenith and 1.25 deg of azimuth at the end.
STEPS_DEG, REFINE = (10.0, 20.0), 4
#: Pixels (a stride sample) on which ``eta`` and the light are chosen.
ETA_SAMPLE = 256
#: Each sampled pixel's statistic counts at most the critical value at this level in the choice of
#: ``eta`` and the light.
CAP_QUANTILE = 1e-3
#: Level of the likelihood-ratio test of the specular term against the diffuse term alone
#: (``chi^2(C)``): below it the specular albedo is taken as 0.
SPECULAR_LEVEL = 0.05
#: Side (output pixels) of the square neighbourhood over which :func:`neighbour_bias` averages
#: the deviation from the full estimate: the bias turns slowly over it (with the whole deviation,
#: before the observed part alone, 3, 5 and 7 gave 95.3-95.9, 95.6-96.4 and 95.7-96.6 % of the
#: accepted pixels' elements within 2 sigma on captures of the plastic sphere).
POOL_WINDOW = 5


def state_stokes(measured: np.ndarray, variance: np.ndarray, valid: np.ndarray | None = None,
                 analyzer_rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One state's Stokes images from its analyzer samples, by weighted least squares.

    ``measured``, ``variance`` ``(C, 4, H, W)`` (the reference solve's units; analyzers 0, 45, 90,
    135 deg), ``valid`` ``(C, 4, H, W)`` bool or None (all); ``analyzer_rows`` ``(4, 3)`` shared,
    ``(C, 4, 3, H, W)`` per pixel (a calibrated analyzer on the output grid, as
    :func:`polrig.solve.reference.solve_reference` takes it) or None (ideal,
    :func:`polrig.sensor.stokes.ideal_analyzer_matrix`). Returns the Stokes estimate
    ``(C, 3, H, W)``, its information ``A^T W A`` ``(C, 3, 3, H, W)`` (the inverse of its
    covariance) and ``ok`` ``(C, H, W)``: where all four samples are used (finite, positive
    variance, valid); the estimate is NaN elsewhere."""
    y = np.asarray(measured, np.float64)
    v = np.asarray(variance, np.float64)
    a = ideal_analyzer_matrix() if analyzer_rows is None else np.asarray(analyzer_rows, np.float64)
    if a.shape == (4, 3):
        a = a[None, :, :, None, None]
    elif a.shape != y.shape[:2] + (3,) + y.shape[2:]:
        raise ValueError(f"analyzer_rows must be (4, 3) or {y.shape[:2] + (3,) + y.shape[2:]}, got {a.shape}")
    used = np.isfinite(y) & np.isfinite(v) & (v > 0)
    if valid is not None:
        used &= np.asarray(valid, bool)
    ok = used.all(axis=1)
    w = np.where(used, 1.0 / np.where(used, v, 1.0), 0.0)
    a = np.broadcast_to(a, y.shape[:2] + (3,) + y.shape[2:])
    info = np.einsum("cjahw,cjhw,cjbhw->cabhw", a, w, a)
    rhs = np.einsum("cjahw,cjhw->cahw", a, w * np.where(used, y, 0.0))
    system = np.where(ok[..., None, None], np.moveaxis(info, (1, 2), (-2, -1)), np.eye(3))
    s = np.moveaxis(np.linalg.solve(system, np.moveaxis(rhs, 1, -1)[..., None])[..., 0], -1, 1)
    return np.where(ok[:, None], s, np.nan), info, ok


def degrees_of_freedom(n_colours: int, specular: bool = False) -> int:
    """``6 C - (2 + C)``: two states' six numbers per colour less the normal and the colours'
    albedos; with the specular term ``6 C - (2 + 2 C)`` (a second albedo per colour)."""
    return (4 if specular else 5) * int(n_colours) - 2


def diffuse_statistic(stokes: np.ndarray, information: np.ndarray, states: np.ndarray, view: np.ndarray,
                      light: np.ndarray, eta: float, stage_zero_axis, camera_x_axis,
                      specular: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``T`` of ``P`` pixels (module docstring), the normal that attains it and the albedos.

    ``stokes`` ``(C, J, 3, P)`` and ``information`` ``(C, J, 3, 3, P)``: each state's
    (:func:`state_stokes`); ``states`` ``(J, 3)``; ``view``, ``light`` ``(P, 3)``; ``eta`` the
    refractive index; ``specular`` ``(P, 3, 3)``: the unit specular block of each pixel
    (:func:`polrig.solve.diffuse_geometry.specular_block`, with a second albedo per colour), or
    None (the diffuse term alone). Returns ``T`` ``(P,)`` (inf where no candidate normal is
    valid), the normal ``(P, 3)`` and ``k`` ``(C, P)``, with the specular term ``(2 C, P)`` (the
    diffuse albedos, then the specular). The compiled search
    (:func:`polrig.solve._diffuse_kernel.statistic_search`, pixel chunks on threads)."""
    from polrig.solve import _diffuse_kernel as kern  # numba: imported on first use

    states = np.ascontiguousarray(np.asarray(states, np.float64).reshape(-1, 3))
    view = np.ascontiguousarray(np.asarray(view, np.float64).reshape(-1, 3))
    light = np.array(np.broadcast_to(np.asarray(light, np.float64), view.shape), order="C")  # one kernel type
    stage, cam = (np.ascontiguousarray(a, np.float64) for a in (stage_zero_axis, camera_x_axis))
    stokes = np.ascontiguousarray(np.moveaxis(np.asarray(stokes, np.float64), -1, 0))  # (P, C, J, 3)
    info = np.ascontiguousarray(np.moveaxis(np.asarray(information, np.float64), -1, 0))  # (P, C, J, 3, 3)
    p, n_col = len(view), stokes.shape[1]
    spec = (np.empty((0, len(states), 3)) if specular is None
            else np.ascontiguousarray(np.einsum("pab,jb->pja", np.asarray(specular, np.float64), states)))
    grid, steps = _search_grid(STEPS_DEG, REFINE)
    t, normal, k = np.empty(p), np.empty((p, 3)), np.empty((p, n_col * (1 if specular is None else 2)))

    def work(sl: slice) -> None:
        kern.statistic_search(view[sl], light[sl], stage, cam, float(eta), grid, steps, stokes[sl], info[sl], states,
                              spec[sl] if len(spec) else spec, t[sl], normal[sl], k[sl])

    _in_chunks(p, work)
    return t, normal, np.ascontiguousarray(k.T)


class DiffuseTest(NamedTuple):
    """:func:`test_diffuse`'s result. ``accepted`` ``(H, W)`` bool; ``statistic``, ``p_value``
    ``(H, W)`` (NaN where not tested); ``tested`` ``(H, W)``; ``normal`` ``(H, W, 3)`` (0 where not
    tested); ``albedo`` ``(C, H, W)``; ``df``, ``alpha``; ``eta`` and ``light`` (the index of the
    geometry's candidate light field) chosen for the image (None where nothing was tested);
    ``specular_albedo`` ``(C, H, W)``, the specular term's weight against its unit block
    (:func:`polrig.solve.diffuse_geometry.specular_block`; 0 where the term is not significant),
    and ``specular_sigma`` its standard deviation (the least squares' at the normal taken), and
    ``specular_unused`` ``(C, H, W)`` the albedo the two-albedo fit gave where the term was *not*
    significant (0 where it was, or where untested: module docstring, "The specular term not
    taken"); each None where the test had no specular term."""

    accepted: np.ndarray
    statistic: np.ndarray
    p_value: np.ndarray
    tested: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    df: int
    alpha: float
    eta: float | None
    light: int | None
    specular_albedo: np.ndarray | None = None
    specular_sigma: np.ndarray | None = None
    specular_unused: np.ndarray | None = None


def decide(t_diffuse: np.ndarray, t_specular: np.ndarray | None, n_colours: int, alpha: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """The test's decision from its statistics (module docstring): ``(accepted, significant)``,
    each shaped as ``t_diffuse``. ``t_diffuse``: ``T`` of the diffuse term alone; ``t_specular``:
    ``T_s`` with the specular term, or None (the diffuse term alone is tested). The specular
    term is significant where ``T - T_s`` is beyond ``chi^2(C)``'s critical value at
    :data:`SPECULAR_LEVEL`; a pixel is accepted where the model so chosen is within the
    level-``alpha`` critical value of its degrees of freedom (:func:`degrees_of_freedom`)."""
    t_diffuse = np.asarray(t_diffuse, np.float64)
    accept_diffuse = t_diffuse <= chi2_critical(degrees_of_freedom(n_colours), float(alpha))
    if t_specular is None:
        return accept_diffuse, np.zeros(t_diffuse.shape, bool)
    t_specular = np.asarray(t_specular, np.float64)
    with np.errstate(invalid="ignore"):  # both infinite (no valid normal): not significant
        significant = (t_diffuse - t_specular) > chi2_critical(int(n_colours), SPECULAR_LEVEL)
    accept_specular = t_specular <= chi2_critical(degrees_of_freedom(n_colours, True), float(alpha))
    return np.where(significant, accept_specular, accept_diffuse), significant


def _choose(n_lights: int, n_etas: int, total) -> tuple[int, int]:
    """``(light, eta)`` indices of least ``total(light, eta)``: every other index first, then
    the neighbours of the best (the total is smooth in ``eta``: half the evaluations)."""
    if n_lights * n_etas == 1:
        return 0, 0
    seen: dict[tuple[int, int], float] = {}

    def at(li: int, e: int) -> float:
        if (li, e) not in seen:
            seen[li, e] = total(li, e)
        return seen[li, e]

    coarse = sorted(set(range(0, n_etas, 2)) | {n_etas - 1})
    li, e = min(((li, e) for li in range(n_lights) for e in coarse), key=lambda k: at(*k))
    return min(((li, f) for f in (e - 1, e, e + 1) if 0 <= f < n_etas), key=lambda k: at(*k))


def test_diffuse(states: np.ndarray, measured: np.ndarray, variance: np.ndarray, valid: np.ndarray | None,
                 geometry: DiffuseGeometry, *, mask: np.ndarray | None = None, alpha: float = 0.05,
                 analyzer_rows: np.ndarray | None = None, etas=ETAS, specular: bool = False) -> DiffuseTest:
    """Test the diffuse term at every pixel of two states' frames (module docstring).

    ``states`` ``(2, 3)``; ``measured``, ``variance`` ``(2, C, 4, H, W)``, ``valid`` the same
    (bool) or None, as :func:`polrig.solve.reference.solve_reference` takes them;
    ``geometry``: what the rig knows of the pixels' geometry; ``mask`` ``(H, W)``: the pixels to
    test (default all), of which those with all samples of both states in every colour used are
    tested; ``alpha`` the level; ``analyzer_rows`` as :func:`state_stokes`; ``etas`` the indices
    searched; ``specular``: the model is the diffuse term plus Baek's specular term (module
    docstring, "The specular term")."""
    states = np.asarray(states, np.float64).reshape(-1, 3)
    if len(states) != 2:
        raise ValueError(f"the diffuse test takes two states, got {len(states)}")
    if not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    measured = np.asarray(measured)
    n_col, h, w = measured.shape[1], measured.shape[-2], measured.shape[-1]
    # the Stokes estimates of the masked pixels only (as a (P, 1) image): the whole image's
    # float64 information would cost memory and time for nothing at the full sensor
    ys, xs = np.nonzero(np.ones((h, w), bool) if mask is None else np.asarray(mask, bool))
    rows = analyzer_rows
    if rows is not None and np.ndim(rows) == 5:
        rows = np.asarray(rows)[..., ys, xs][..., None]
    per_state = [state_stokes(np.asarray(measured[j])[..., ys, xs][..., None],
                              np.asarray(variance[j])[..., ys, xs][..., None],
                              None if valid is None else np.asarray(valid[j])[..., ys, xs][..., None], rows)
                 for j in range(2)]
    used = np.all([ok.all(axis=0)[:, 0] for _, _, ok in per_state], axis=0)  # (P,)
    tested = np.zeros((h, w), bool)
    tested[ys[used], xs[used]] = True
    df, df_fit = degrees_of_freedom(n_col), degrees_of_freedom(n_col, specular)
    ys, xs = ys[used], xs[used]
    nan_img = np.full((h, w), np.nan)
    if not len(ys):
        return DiffuseTest(np.zeros((h, w), bool), nan_img, nan_img.copy(), tested, np.zeros((h, w, 3)),
                           np.zeros((n_col, h, w)), df, float(alpha), None, None,
                           np.zeros((n_col, h, w)) if specular else None)
    stokes = np.stack([s[..., used, 0] for s, _, _ in per_state], axis=1)  # (C, 2, 3, P)
    info = np.stack([q[..., used, 0] for _, q, _ in per_state], axis=1)  # (C, 2, 3, 3, P)
    view = np.asarray(geometry.view, np.float64)[ys, xs]
    lights = light_fields(geometry, ys, xs)
    fixed = (geometry.stage_zero_axis, geometry.camera_x_axis)
    sample = np.arange(0, len(ys), max(1, len(ys) // ETA_SAMPLE))[:ETA_SAMPLE]
    cap = chi2_critical(df_fit, CAP_QUANTILE)

    def spec(li: int, e: int, pix) -> np.ndarray | None:
        return specular_block(lights[li][pix], view[pix], float(etas[e]), *fixed) if specular else None

    def total(li: int, e: int) -> float:
        return float(np.minimum(diffuse_statistic(stokes[..., sample], info[..., sample], states, view[sample],
                                                  lights[li][sample], float(etas[e]), *fixed,
                                                  specular=spec(li, e, sample))[0], cap).sum())

    best_light, best_eta = _choose(len(lights), len(etas), total)
    eta = float(etas[best_eta])
    block = spec(best_light, best_eta, slice(None))
    t, normal, k = diffuse_statistic(stokes, info, states, view, lights[best_light], eta, *fixed, specular=block)
    p = chi2_sf(t, df_fit)
    if not specular:
        accept, _ = decide(t, None, n_col, alpha)
    else:  # the specular term only where it explains significantly more than the diffuse alone
        t_d, normal_d, k_d = diffuse_statistic(stokes, info, states, view, lights[best_light], eta, *fixed)
        accept, significant = decide(t_d, t, n_col, alpha)  # the model chosen, tested against the free block
        normal = np.where(significant[:, None], normal, normal_d)
        unused = np.where(significant, 0.0, k[n_col:])
        k = np.concatenate([np.where(significant, k[:n_col], k_d), np.where(significant, k[n_col:], 0.0)])
        p = np.where(significant, p, chi2_sf(t_d, df))
        t = np.where(significant, t, t_d)
        ks_sd = np.where(significant, np.sqrt(_specular_variance(
            info, states, normal, lights[best_light], view, eta, fixed, block)), 0.0)
    statistic, p_value = nan_img.copy(), nan_img.copy()
    statistic[ys, xs], p_value[ys, xs] = t, p
    accepted = np.zeros((h, w), bool)
    accepted[ys, xs] = accept
    normals = np.zeros((h, w, 3))
    normals[ys, xs] = normal
    albedo = np.zeros((n_col, h, w))
    albedo[:, ys, xs] = k[:n_col]
    specular_albedo = specular_sigma = specular_unused = None
    if specular:
        specular_albedo, specular_sigma = np.zeros((n_col, h, w)), np.zeros((n_col, h, w))
        specular_albedo[:, ys, xs], specular_sigma[:, ys, xs] = k[n_col:], ks_sd
        specular_unused = np.zeros((n_col, h, w))
        specular_unused[:, ys, xs] = unused
    return DiffuseTest(accepted, statistic, p_value, tested, normals, albedo, df, float(alpha), eta, int(best_light),
                       specular_albedo, specular_sigma, specular_unused)


def _specular_variance(info: np.ndarray, states: np.ndarray, normal: np.ndarray, light: np.ndarray,
                       view: np.ndarray, eta: float, fixed, block: np.ndarray) -> np.ndarray:
    """The variance ``(C, P)`` of the specular albedo's least squares at the ``normal`` ``(P, 3)``
    taken: the ``[1, 1]`` element of the inverse of the two albedos' information
    ``sum_j [a_j b_j]^T Q_j [a_j b_j]`` (``a_j = (y . s_j) x`` the diffuse term's response,
    ``b_j`` the unit specular block's ``block`` ``(P, 3, 3)``; ``info`` ``(C, J, 3, 3, P)``)."""
    x, y = diffuse_ratios(normal, light, view, eta, *fixed)
    a = np.einsum("pj,pr->jrp", y @ states.T, x)  # (J, 3, P)
    b = np.einsum("prk,jk->jrp", block, states)
    gaa = np.einsum("jrp,cjrsp,jsp->cp", a, info, a)
    gab = np.einsum("jrp,cjrsp,jsp->cp", a, info, b)
    gbb = np.einsum("jrp,cjrsp,jsp->cp", b, info, b)
    with np.errstate(divide="ignore", invalid="ignore"):
        var = gaa / (gaa * gbb - gab**2)
    return np.where(np.isfinite(var) & (var > 0), var, 0.0)


def neighbour_bias(deviation: np.ndarray, chosen: np.ndarray, window: int = POOL_WINDOW) -> np.ndarray:
    """The model's bias as the neighbours see it: per plane, the mean of ``deviation`` over the
    ``chosen`` pixels in the ``window`` x ``window`` neighbourhood (itself included; clipped at
    the image's edge), where ``chosen``; 0 elsewhere.

    ``deviation`` ``(..., H, W)`` (e.g. one element of one colour, or ``(C, 3, 3, H, W)``): the
    reduced estimate less the full one; ``chosen`` bool, broadcastable to it (``(H, W)``, or
    ``(C, 1, 1, H, W)``). Returns the shape of ``deviation``, float64 (its units).

    Why: the truth may sit off an accepted model by a bias the test cannot detect (the model
    selection's term, :mod:`polrig.solve.model_selection`, "The model's bias in the sigma"). One
    pixel's deviation holds that bias and the two estimates' noise together; where it is small
    by chance, so is the sigma (on captures of the simulator's plastic sphere, 512x512 mono,
    whose weak specular term adds about 1.4 % of ``m00`` to ``m11`` and ``m22``, which no
    rank-one block holds: 75 % of the accepted pixels' ``m11`` within 2 sigma). The bias is set
    by the surface's geometry and keeps its sign from one pixel to the next, the noise does not,
    so the neighbours' mean holds the bias with the noise's variance divided by their number.

    Measured (:func:`complete_tested_diffuse`, which floors the pixel's squared deviation at the
    square of this mean over the directions the states observe; accepted pixels' elements
    within 2 sigma on those captures, with and without the simulator's hidden errors; the
    object's on the eight held-out sets of ``benchmarks/results/continuum_models.md``):

    ============================================  ===========  ==============
    model term                                    captures     held-out sets
    ============================================  ===========  ==============
    each pixel's own squared deviation            91.9-92.4 %  94.6-96.1 %
    the neighbours' mean of the squared deviation 97.3-97.9 %  95.9-97.7 %
    the square of the neighbours' mean deviation  95.6-96.4 %  95.2-97.2 %
    the same, observed directions only (used)     94.4-95.0 %  95.1-96.8 %
    ============================================  ===========  ==============

    The mean of the squares holds the whole noise of the difference besides the bias: too wide.
    Along the direction the states leave open the full estimate is the network's prior, whose
    own errors keep their sign over neighbours as well, so there the mean measures the prior,
    not the model (the compact held-out sets went above 97 %); the completed element's own
    bias stays uncovered there (``m22`` within 2 sigma on 79-81 % of the capture's accepted
    pixels)."""
    total, count = window_sums(deviation, chosen, window)
    return np.where(chosen, total / np.maximum(count, 1.0), 0.0)


def complete_tested_diffuse(result: ReferenceResult, states: np.ndarray, measured: np.ndarray,
                            variance: np.ndarray, valid: np.ndarray | None, geometry: DiffuseGeometry, *,
                            prior: tuple[np.ndarray, np.ndarray], seen_state: int = 0,
                            prior_correlation: np.ndarray | None = None, alpha: float = 0.05,
                            mask: np.ndarray | None = None, analyzer_rows: np.ndarray | None = None,
                            specular: bool = False) -> tuple[ReferenceResult, DiffuseTest, np.ndarray]:
    """Two states' hybrid solve ``result`` with the diffuse term where the samples alone accept it.

    :func:`test_diffuse` decides; at the accepted pixels the block is estimated under the
    rank-one model on the hybrid's posterior system (:func:`polrig.solve.model_selection.select_models`
    with ``decided``: the same fit, covariance and model-selection term in the sigma as the
    selection's), and the direction the states leave open is predicted from the geometry
    (:func:`polrig.solve.diffuse_geometry.complete_diffuse`). At those pixels the sigma's model
    term (the squared difference from ``result``, the selection's and the completion's) is at
    least the square of the accepted neighbours' mean difference in the directions the states
    observe (:func:`neighbour_bias`; along the open direction ``result`` is the network's prior,
    whose errors are no measure of the model's). ``prior``, ``seen_state``,
    ``prior_correlation``: the hybrid solve's; ``analyzer_rows``: the samples' analyzer rows, as
    :func:`polrig.solve.reference.solve_reference` takes them (None: ideal); ``specular``: with
    Baek's specular term where significant (module docstring, "The specular term": it is taken
    off before the rank-one estimate and the completion and put back after; where it was fitted
    but not taken, what it would have added enters the sigma: "The specular term not taken").
    Returns the result (its ``models`` map: ``rank_one``
    where accepted, ``full`` where tested and not), the test and the completed pixels
    ``(C, H, W)``."""
    states = np.asarray(states, np.float64).reshape(-1, 3)
    test = test_diffuse(states, measured, variance, valid, geometry, mask=mask, alpha=alpha,
                        analyzer_rows=analyzer_rows, specular=specular)
    spec, base = None, result
    if test.specular_albedo is not None and test.eta is not None:
        # the specular term fitted by the test, taken off the samples, the prior and the hybrid's
        # estimate: the rank-one estimate and the completion see the diffuse term alone
        ys, xs, unit = spec = specular_term(test, geometry)
        values = test.specular_albedo[:, None, None, ys, xs] * unit[None]
        measured = np.array(measured)
        measured[..., ys, xs] -= _samples_of(values, states, analyzer_rows, ys, xs).astype(measured.dtype)
        mean = np.array(np.broadcast_to(prior[0], result.mueller.shape))
        mean[..., ys, xs] -= values.astype(mean.dtype)
        prior = (mean, prior[1])
        mueller = result.mueller.copy()
        mueller[..., ys, xs] -= values.astype(mueller.dtype)
        base = dataclasses.replace(result, mueller=mueller)
    chosen, _ = select_models(states, measured, variance, valid, analyzer_rows, base,
                              SelectionOptions(alpha=alpha, models=("rank_one",)), prior=prior,
                              seen_state=seen_state, prior_correlation=prior_correlation,
                              decided=test.accepted[None])
    if test.eta is None:
        return chosen, test, np.zeros(chosen.mask.shape, bool)
    out, completed, _ = complete_diffuse(chosen, states, geometry, eta=test.eta, light=test.light)
    if spec is not None:
        mueller = out.mueller.copy()
        mueller[..., ys, xs] += values.astype(mueller.dtype)
        out = dataclasses.replace(out, mueller=mueller, sigma=_with_specular_terms(out.sigma, test, *spec))
    return dataclasses.replace(out, sigma=_floor_at_neighbour_bias(out, result, states)), test, completed


def _with_specular_terms(sigma: np.ndarray, test: DiffuseTest, ys: np.ndarray, xs: np.ndarray,
                         unit: np.ndarray) -> np.ndarray:
    """``sigma`` ``(C, 3, 3, H, W)`` with, at the accepted pixels ``ys``, ``xs``, what the specular
    term leaves where the rank-one estimate cannot follow it, ``B - B[:, 0] B[0, :] / B[0, 0]``
    (``unit`` ``(3, 3, P)`` the unit blocks ``B`` there, :func:`specular_term`), added in
    quadrature: times the albedo's standard deviation where the term was taken (an error ``d`` of
    the albedo shifts the rest by ``-d B``, whose first row and column the rank-one fit keeps, as
    they are measured, and whose other elements it predicts from them), and times the albedo
    fitted where it was not taken (the bias of leaving it out: module docstring, "The specular
    term not taken"); each colour's pixel has one or the other."""
    with np.errstate(divide="ignore", invalid="ignore"):
        follow = unit[:, :1] * unit[:1, :] / unit[:1, :1]
    beyond = np.where(unit[:1, :1] > 0, unit - follow, 0.0)  # (3, 3, P)
    scale2 = test.specular_sigma[:, ys, xs] ** 2 + test.specular_unused[:, ys, xs] ** 2  # (C, P)
    out = sigma.copy()
    out[..., ys, xs] = np.sqrt(sigma[..., ys, xs].astype(np.float64) ** 2
                               + scale2[:, None, None] * beyond[None] ** 2).astype(sigma.dtype)
    return out


def specular_term(test: DiffuseTest, geometry: DiffuseGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit specular block (:func:`polrig.solve.diffuse_geometry.specular_block`, at the
    test's light and index) at the test's accepted pixels: their rows and columns ``(P,)`` and
    the blocks ``(3, 3, P)`` float64; the term is ``test.specular_albedo`` there times them."""
    ys, xs = np.nonzero(test.accepted)
    if test.specular_albedo is None or not len(ys):
        return ys, xs, np.zeros((3, 3, len(ys)))
    block = specular_block(light_fields(geometry, ys, xs)[test.light], np.asarray(geometry.view, np.float64)[ys, xs],
                           test.eta, geometry.stage_zero_axis, geometry.camera_x_axis)  # (P, 3, 3)
    return ys, xs, np.moveaxis(block, 0, -1)


def _samples_of(blocks: np.ndarray, states: np.ndarray, analyzer_rows, ys: np.ndarray, xs: np.ndarray
                ) -> np.ndarray:
    """The analyzer samples ``(J, C, 4, P)`` that blocks ``(C, 3, 3, P)`` at the pixels ``ys``,
    ``xs`` give under the ``states`` ``(J, 3)``: :func:`polrig.solve.reference.forward_measurements`
    of the pixels as a ``(P, 1)`` image (``analyzer_rows`` as :func:`state_stokes`, per pixel
    ``(C, 4, 3, H, W)`` read at those pixels; None ideal)."""
    rows = analyzer_rows
    if rows is not None and np.ndim(rows) > 2:
        rows = np.asarray(rows)[..., ys, xs][..., None]
    return forward_measurements(blocks[..., None], states, rows)[..., 0]


def _floor_at_neighbour_bias(out: ReferenceResult, full: ReferenceResult, states: np.ndarray) -> np.ndarray:
    """``out``'s sigma with, at its ``rank_one`` pixels, the squared deviation from ``full``
    floored at the square of :func:`neighbour_bias` of the deviation's part in the directions the
    ``states`` observe (along the open direction ``full`` is the network's prior, whose own
    errors keep their sign over neighbours too: no measure of the model's bias). One row of one
    colour at a time (a few ``(H, W)`` planes: the full sensor's nine planes in float64 would
    cost some 0.5 GB), within the box that holds the colour's ``rank_one`` pixels (outside it
    nothing is chosen: no pixel there is floored, and none adds to a window's sums). Returns
    ``(C, 3, 3, H, W)`` of ``out.sigma``'s dtype."""
    u = unobserved_direction(states)
    u = np.zeros(3) if u is None else u  # states that leave no one direction open: all of it
    sigma = out.sigma.copy()
    for c in range(out.mueller.shape[0]):
        chosen = np.asarray(out.models.code[c]) == RANK_ONE
        box = mask_box(chosen)
        if box is None:
            continue
        chosen = chosen[box]
        for r in range(3):
            dev = np.where(chosen, out.mueller[c, r][(slice(None), *box)].astype(np.float64)
                           - full.mueller[c, r][(slice(None), *box)].astype(np.float64), 0.0)
            observed = dev - np.einsum("k...,k->...", dev, u)[None] * u[:, None, None]
            extra = np.maximum(neighbour_bias(observed, chosen) ** 2 - dev**2, 0.0)
            sig = sigma[c, r][(slice(None), *box)]
            sigma[c, r][(slice(None), *box)] = np.sqrt(sig.astype(np.float64) ** 2 + extra)
    return sigma

