"""Hybrid Mueller solve: any number of polarizer states combined with a Gaussian prior on the
nine elements (the single-shot network's estimate and calibrated sigma), per pixel and colour.

**Model.** As in :mod:`polrig.solve.reference` (conventions, units, masks), each used sample
gives ``I_kj = kron(a_j, s_k) . vec(M) + noise`` with variance ``v_kj``; ``D``, ``W`` the design
and weights of all used samples. The prior is ``vec(M) ~ N(mu, Sigma)`` with
``Sigma = diag(sigma^2)`` (``prior_mean``, ``prior_sigma``, ``(C, 3, 3, H, W)``: the network's
estimate and its calibrated per-element sigma, :mod:`polrig.models.uncertainty`). With a
prior precision ``P`` the posterior is Gaussian with

    (D^T W D + P) vec(M) = D^T W I + P mu,       cov = (D^T W D + P)^-1,

its mean the estimate and ``sqrt(diag cov)`` its ``sigma``. The ``residual`` is the samples'
``chi^2 = sum w r^2`` over their effective degrees of freedom ``n - tr(H)`` with
``H = D cov D^T W`` the hat matrix, ``tr(H) = 9 - tr(cov P)``: for a right noise model and a
calibrated prior ``E chi^2 = n - tr(H)`` exactly (``(I - H)(D P^-1 D^T + W^-1) = W^-1``), so
it is about 1, and it tends to the reference solve's ``chi^2 / (n - 9)`` as ``P -> 0``
(0 below half a degree of freedom). ``P = 0`` gives the reference solve's normal equations exactly: the compiled
kernel of the reference solve (:func:`polrig.solve._reference_kernel.solve_blocks`) adds
``P`` and ``P mu`` and nothing else, so a prior of infinite sigma reproduces
:func:`~polrig.solve.reference.solve_reference` bit for bit (``tests/test_hybrid.py``).

**An observation must never count twice.** The network's estimate is a function of one
frame, the state ``s_0`` it saw (``seen_state``), and that frame's samples are also among
the ones measured. One DoFP frame of ``s_0`` measures exactly ``M s_0``: three numbers per
colour, one per row ``r`` of ``M``, the component of the row ``m_r`` along ``u = s_0 / |s_0|``
(4 analyzers, rank 3). The other six directions, ``m_r`` orthogonal to ``u``, are the ones the
frame leaves unobserved and the network fills in from what it has learned. Write
``vec(M) = O z_o + U z_u`` with ``O = I_3 (x) u`` (observed) and ``U = I_3 (x) V``
(``V`` an orthonormal basis of ``u``'s complement; unobserved). The frame's likelihood
depends on ``z_o`` only (``D_0 U = 0``).

Let ``y_0`` be the seen frame and ``Y`` the other states (independent noise given ``M``).
The posterior of everything is ``p(M | y_0, Y) ∝ p(z_o | y_0) p(z_u | z_o, y_0) p(Y | M)``.

* ``p(z_o | y_0)`` is the frame's own likelihood (a learned prior on ``z_o`` is far wider
  than 4 samples of one pixel determine it): the reference solve's term ``D_0^T W_0 D_0``.
* ``p(z_u | z_o, y_0)`` is what the network adds: the prior's information on the unobserved
  directions, precision ``P = U Sigma_u^-1 U^T`` for the covariance ``Sigma_u`` (6x6) of the
  network's error there. The calibrated sigma is per element, ``sigma_ra^2 = E e_ra^2``, not
  a joint covariance, so ``Sigma_u`` has to be modelled. Because ``U = I (x) V``, it is taken
  block diagonal over the rows, ``Sigma_u = diag_r(V^T Sigma_r V + alpha_r v1 v1^T)`` (in
  ``V``'s coordinates) with ``Sigma_r = diag(sigma_r^2)`` and ``alpha_r = u^T Sigma_r u``:

  - ``V^T Sigma_r V`` is the *marginal* of ``N(mu_r, Sigma_r)`` on the plane ``u^perp``.
    Its precision is the Schur complement of ``Pi_r = diag(1 / sigma_r^2)`` with the ``u``
    direction eliminated, written back in ``M``'s coordinates as

        Pi_r - (Pi_r u)(Pi_r u)^T / (u^T Pi_r u),      (annihilates u, rank 2)

    (proof: it annihilates ``u``, so it equals ``V V^T (.) V V^T``, and ``V^T (.) V`` is the
    Schur complement of ``u^T Pi_r u`` in ``[V u]^T Pi_r [V u]``, the inverse of
    ``V^T Sigma_r V``). Elements without a prior (``pi = 0``) drop out exactly, and written
    element by element it has no cancellation
    (:func:`polrig.solve._reference_kernel.load_prior`).
  - ``alpha_r v1 v1^T`` keeps the row's whole calibrated variance in that plane. The marginal
    alone would throw away the share ``u^T Sigma_r u / tr Sigma_r`` of it (a third, for ``u``
    between the element axes), as if a third of the network's error lay along ``u``; but the
    network reproduces the frame it saw, so its error along ``u`` is small: on the held-out
    terrain set (64x64, first 16 lit samples) 3.5 % of the row's error energy, where the
    diagonal ``Sigma_r`` puts 33 %. With the marginal, the posterior's coverage within 2 sigma
    at the seen state alone fell up to 2.8 points below the network's own.
  - That variance goes onto one axis of the plane, ``v1`` (:func:`plane_axis`): the calibrated
    sigma is per column of the *observed* frame (:mod:`polrig.models.uncertainty`), whose
    columns 0 and 1 (unpolarized light and light along the seen state) span ``u`` and ``v1``,
    and whose column 2 (light at 45 deg to it) is ``v2 = v1 x u``, orthogonal to both and not
    observed at all. An error that the network keeps off ``u`` within columns 0 and 1 lies on
    ``v1``; column 2's has its own calibrated sigma and no share of ``u``'s. (Where ``Sigma_r``
    is diagonal in the observed frame, ``u`` between columns 0 and 1, this puts exactly
    ``sigma_0^2 + sigma_1^2`` on ``v1`` and ``sigma_2^2`` on ``v2``.) The form before spread it
    over the whole plane, ``f_r V^T Sigma_r V`` with ``f_r = tr Sigma_r / (tr Sigma_r -
    u^T Sigma_r u)``, about 1.5: that inflated column 2's variance by ``f_r``, and at two
    states 90 deg apart, which leave column 2 alone unobserved, it over-covered (97.1-97.5 %
    within 2 sigma on the seen-family, compact and dispersive sets). Moved onto ``v1`` (the
    first 24 samples of the eight sets of ``models/continuum/``, 64x64, the calibrated sigma
    of version 3): two states 0.3-1.1 points lower (95.4-97.1 % where ``f_r`` gave 96.0-97.6 %),
    one state -0.2..+0.6, three -0.1..0; matrix PSNR the same at one and two states (within
    0.01 dB) and +0.03..+0.23 dB at three.
    ``solve_hybrid(plane_variance="scalar")`` keeps the ``f_r`` form for that comparison, and
    a seen state without an angle (degree of polarization below :data:`MIN_SEEN_DOP`) uses it:
    there the plane has no axis of its own.
  - **The seen direction's share** (``solve_hybrid(seen_share=...)``, ``kappa_r`` per row,
    default 1): the part of ``alpha_r`` kept, ``kappa_r alpha_r v1 v1^T`` (the scalar form keeps
    ``tr Sigma_r - (1 - kappa_r) alpha_r`` on the plane); ``kappa_r = 0`` is the plain
    marginal. Keeping all of it assumes the network's error along ``u`` is nil, where it is
    2-31 % of a row's error energy (:mod:`polrig.models.coverage_diagnosis`): at the seen state
    alone the posterior then covers about a point more than the single-shot sigma it starts
    from. Fitted per row so that it covers as the single-shot sigma on the calibration scenes,
    the share moves that miss from five held-out sets above the 93-97 % band to the two terrain
    sets below it (:mod:`polrig.models.coverage_diagnosis`; ``docs/continuum.md``, "Against
    issue 33's acceptance, line by line"), so captures keep 1: a sigma that errs wide is the
    safer one.

  So the row's prior precision is the inverse of that covariance written back in ``M``'s
  coordinates: with ``S_r = Pi_r - (Pi_r u)(Pi_r u)^T / (u^T Pi_r u)`` (the marginal's
  precision) and Sherman-Morrison,
  ``P_r = (S_r + alpha_r d_r v2 v2^T) / (1 + alpha_r v1^T S_r v1)``, ``d_r = pi_0 pi_1 pi_2 /
  (u^T Pi_r u)`` the determinant of ``S_r`` on the plane (0 where an element has no prior: then
  ``S_r`` has rank 1 there), every term a sum of positive ones where the row's three elements
  have a prior; ``alpha_r`` is summed over the row's elements that have a prior. The scalar form
  is ``P_r = g_r S_r``, ``g_r = 1 / f_r``.
* ``p(Y | M)`` is the other states' likelihood, unchanged.

So the seen frame enters through its samples and the prior through the six directions that
frame does not observe: the observed part of the network's estimate (the ``u``-component of
each row) is not used, because it *is* the seen frame again, reproduced. Counting the whole
prior as well (``P = Pi``, "naive") counts ``M s_0`` twice; the other way to count it once,
"exclude" (the whole prior, the seen frame's samples dropped), replaces the frame's
per-pixel measurement of ``M s_0`` by the network's reproduction of it, which is worse (its
error along ``u`` is 2.3-2.7 times the frame's noise variance on the first 16 samples of two
held-out sets). Which is right is measured by coverage. ``tests/test_hybrid.py`` simulates a
network that reproduces its frame in the observed directions: there "naive" covers 91-93 %
within 2 sigma, the projection 95.7-96.7 % (1 to 4 states). With the shipped network
(``python -m polrig.models.continuum``, ``benchmarks/results/continuum.md``, eight held-out
sets), "naive" covers 1.8-4.1 points less than the projection at one state, for 0.1-0.5 dB
more matrix PSNR (the network's reproduction of ``M s_0`` is smoothed over its neighbours and
holds a little that the pixel's own frame does not: a calibrated model of that could earn
it without the double count), and "exclude" is 0.3-0.8 dB worse at two states.

Consequences, all tested:

* **Seen state alone**: the estimate is the frame's least-squares ``M s_0`` plus the
  prior's unobserved part, ``m_r = u u^T m_r^(data) + V V^T mu_r`` (the Frobenius error
  splits orthogonally into the two), so it is no worse than the single-shot estimate where
  the frame measures ``M s_0`` better than the network reproduces it.
* **Wide prior** (``sigma -> inf``): ``P -> 0`` and the estimate, sigma, residual and masks
  are the reference solve's (bit for bit at ``inf``, to 1e-9 relative at ``1e8`` times the
  data's sigma).
* **Where the frame is partly used** (saturated or bad samples of the seen state): only the
  directions its *used* samples observe are removed from the prior, ``a_j (x) u`` for each
  used analyzer row ``a_j``: with 3 or 4 used samples that is ``M s_0`` whole, with 1 or 2 a
  smaller subspace (the same Schur complement over it, which couples the rows), with none
  the prior is used whole. So no sample counts twice and none is thrown away, and a wide
  prior tends to the reference solve at every pixel.
* **Where there is no prior** (the network's sigma is 0 outside its object mask, or
  infinite, or its mean is not finite), the pixel is solved from its samples alone, exactly
  as the reference solve does (and masked ``ILL_CONDITIONED`` where they do not determine
  ``M``, e.g. with fewer than 3 states). A NaN or negative sigma, or a non-finite mean with a
  finite sigma, sets ``NONFINITE``.

**Joint prior** (``prior_correlation``, off by default). The calibrated sigma is per element;
the network's errors on the six unobserved directions are not independent across the rows of
``M``. In the coordinates the per-element prior whitens, ``w = Q^T e`` with ``Q`` ``(9, 6)``
block diagonal over the rows, ``Q_r = [v1 v2] L_r`` and ``L_r`` the Cholesky factor of the row's
precision on its plane ``[v1 v2]^T P_r [v1 v2]`` (:func:`unobserved_factor`; ``Q Q^T = P``), a
right per-element prior gives ``w`` unit covariance. The joint prior models it as ``K`` (6x6,
symmetric positive definite; coordinates ``(r, v1), (r, v2)`` row by row), so the covariance
on the plane is ``L^-T K L^-1`` and the precision ``P_joint = Q K^-1 Q^T``
(:func:`joint_precision`; the kernel's :func:`polrig.solve._reference_kernel.correlate_prior`).
``K = I`` is the per-element prior (to rounding: ``tests/test_hybrid_joint.py``, 1e-9). ``K``
with a unit diagonal (a correlation, as fitted: :mod:`polrig.models.uncertainty_fit`
``--joint``) keeps every coordinate's calibrated variance. At the seen state alone the data
observe ``u`` and the prior the plane, orthogonal in every row, so the posterior mean is the
per-element prior's exactly and an element's variance changes only through ``K``'s terms
within a row (``(r, v1)`` with ``(r, v2)``: at most 0.05 as fitted); the rows' coupling acts
from two states on, where a measured direction of one row informs an unmeasured one of
another. It applies where the per-element prior has its block-diagonal form (the seen frame's
samples used whole, a seen state with an axis, all nine elements with a prior); elsewhere the
per-element prior is used as it is. Fitted on the calibration scenes, ``K`` is about ``I`` but
for the lower 2x2 block of the observed frame: ``corr((1, v1), (2, v2)) = +0.66`` and
``corr((1, v2), (2, v1)) = -0.63``, the pattern of a rotation of the linear polarization frame
(an error in the surface's azimuth turns ``m11, m12, m21, m22`` together).

**The open direction's scale** (``solve_hybrid(open_factor=a)``, two states only, default 1).
Two states ``s_a``, ``s_b`` observe each row of ``M`` in their plane; the row's component along
``w = s_a x s_b / |.|`` is the prior's alone (the seen state is one of the two, so ``w`` lies in
its unobserved plane). No innovation of the states checks the prior there
(:mod:`polrig.solve.prior_scale`), and where the network errs more along ``w`` than its sigma
says, so does the posterior: the rig's ``plane`` and its plastic + metal scene at two states
(:mod:`polrig.solve.open_scale` finds ``a`` from the diffuse term's geometry). The factor widens
the prior's standard deviation along ``w`` in every row, covariance ``A C A`` with
``A = I_3 (x) (I + (a - 1) w w^T)``, so its precision becomes ``B P B`` with
``B = A^-1 = I_3 (x) (I + (1/a - 1) w w^T)`` (:func:`stretch_precision`; the kernel's
:func:`polrig.solve._reference_kernel.stretch_prior`, after the joint prior). The samples do
not observe ``w``, so the posterior's variance of each row along ``w`` is ``a^2`` times what it
was (tested), its correlation with the observed directions is kept, and the posterior mean
moves along ``w`` by ``a`` times the regression of the prior's error there on the observed
directions' errors.

Masks and outputs are those of :class:`~polrig.solve.reference.ReferenceResult`, so
:func:`polrig.formats.exr.result_planes` writes them unchanged: ``ILL_CONDITIONED`` for a
pixel with a prior means its posterior is singular to working precision (a Cholesky pivot of
the equilibrated normal matrix at or below 1e-12; fewer samples used than the nine elements less
the prior's directions; an element neither the samples nor the prior inform, its diagonal at
most 1e-12 of the largest) or does not fit the output dtype; for a
pixel without one, the reference solve's rule (its samples' condition number above
``max_condition``). ``pixel_condition`` and ``condition_number`` stay the samples' own
(``inf`` for fewer than 3 states). ``sigma`` is the posterior's (prior and noise; plus the
calibration part with tolerances, ``G = (D^T W D + P)^-1 D^T W``), ``sigma_noise`` the same
without the calibration part. ``n_samples`` counts the samples used.

Frames to result: :func:`polrig.solve.radiometry.reference_from_frames` takes the prior
(``prior_mean``, ``prior_sigma``, ``seen_state``) and solves band by band. The capture and
reconstruct mode ``hybrid`` (``--mode hybrid --states 0,90 [--seen-state 0]``) runs it on a
session's frames with the prior from the single-shot route
(:meth:`polrig.app.processing.Processor.solve`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from polrig.errors import ConfigError
from polrig.solve.reference import (
    DEFAULT_MAX_CONDITION,
    DEFAULT_TILE_PIXELS,
    MIN_SNR,
    PriorInputs,
    ReferenceResult,
    _float_samples,
    _solve_options,
    solve_inputs,
    solve_tiles,
)

__all__ = ["solve_hybrid", "unobserved_precision", "observed_direction", "plane_axis", "unobserved_factor",
           "joint_precision", "open_direction", "stretch_precision", "check_correlation", "JOINT_DIM"]

#: Dimension of the joint prior's correlation: two unobserved directions (``v1``, ``v2``) per
#: row of ``M`` (module docstring, "Joint prior").
JOINT_DIM = 6

#: Degree of polarization of the seen state below which its observed direction has no angle:
#: its unobserved plane has no preferred axis, and the row variance factor is the scalar ``g_r``
#: (module docstring; the single-shot uncertainty's ``P_MIN`` alike).
MIN_SEEN_DOP = 0.05
#: :func:`solve_hybrid`'s ``plane_variance`` choices (module docstring).
PLANE_VARIANCE = ("axis", "scalar")


def observed_direction(s_seen) -> np.ndarray:
    """Unit vector ``u = s / |s|`` of a seen state's Stokes vector ``(3,)``: the direction of
    each Mueller row that one DoFP frame of that state observes (module docstring)."""
    s = np.asarray(s_seen, np.float64).reshape(-1)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or not np.any(s):
        raise ConfigError(f"the seen state must be 3 finite numbers, not all 0, got {s_seen!r}")
    return s / np.linalg.norm(s)


def unobserved_precision(sigma_row: np.ndarray, s_seen=None, seen_share=None) -> np.ndarray:
    """The prior precision block ``P_r`` ``(..., 3, 3)`` of Mueller rows with per-element
    sigma ``sigma_row`` ``(..., 3)``: ``diag(1 / sigma^2)`` (0 where sigma is 0 or inf), and
    with a seen state ``s_seen`` whose frame is used whole, the Schur complement
    ``S_r = Pi_r - (Pi_r u)(Pi_r u)^T / (u^T Pi_r u)`` with the variance along ``u`` moved onto
    the plane's axis :func:`plane_axis`, its share ``seen_share`` ``(3,)`` per row (None: all;
    module docstring). The numpy form of what the compiled kernel does, for tests, analysis and
    the adaptive capture's design."""
    sd = np.asarray(sigma_row, np.float64)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        pi = np.where((sd > 0) & np.isfinite(sd), 1.0 / (sd * sd), 0.0)
    pi = np.where(np.isfinite(pi), pi, 0.0)
    p = pi[..., :, None] * np.eye(3)
    if s_seen is None:
        return p
    u = observed_direction(s_seen)
    kappa = 1.0
    if seen_share is not None:
        if sd.ndim < 2 or sd.shape[-2] != 3:
            raise ValueError(f"seen_share needs the rows of M on sigma_row's axis -2, got shape {sd.shape}")
        kappa = check_seen_share(seen_share)
    pu = pi * u
    c = np.sum(pu * u, axis=-1)[..., None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        var = np.where(pi > 0, 1.0 / np.where(pi > 0, pi, 1.0), 0.0)
        schur = p - pu[..., :, None] * pu[..., None, :] / np.where(c > 0, c, 1.0)
        v1 = plane_axis(u)
        if v1 is None:  # no axis: the scalar row factor
            off = np.sum(var * (1.0 - u * u), axis=-1)
            kept = np.sum(var, axis=-1) if seen_share is None else off + kappa * np.sum(var * u * u, axis=-1)
            g = (off / np.where(kept > 0, kept, 1.0))[..., None, None]
            return np.where(c > 0, g * schur, p)
        # the variance along u, moved onto v1: P = (S + alpha det2 v2 v2^T) / (1 + alpha s11)
        alpha = (kappa * np.sum(var * u * u, axis=-1))[..., None, None]
        v2 = np.cross(v1, u)
        det2 = (np.prod(pi, axis=-1) / np.where(c[..., 0, 0] > 0, c[..., 0, 0], 1.0))[..., None, None]
        s11 = np.einsum("...ab,a,b->...", schur, v1, v1)[..., None, None]
        out = (schur + alpha * det2 * np.outer(v2, v2)) / (1.0 + alpha * s11)
        return np.where(c > 0, out, p)


def plane_axis(u: np.ndarray) -> np.ndarray | None:
    """The unit axis ``v1 = u x v2`` ``(3,)`` of the unobserved plane that lies in the seen
    state's own columns (``v2 = (0, -u_2, u_1) / |.|``, light polarized at 45 deg to the seen
    state, is the other), for a unit seen direction ``u``; None where the seen state's degree
    of polarization is below :data:`MIN_SEEN_DOP` (module docstring)."""
    lin = float(np.hypot(u[1], u[2]))
    if not (lin >= MIN_SEEN_DOP * abs(float(u[0])) and lin > 0):
        return None
    return np.array([lin, -u[0] * u[1] / lin, -u[0] * u[2] / lin])


def unobserved_factor(p_rows: np.ndarray, s_seen) -> np.ndarray:
    """``Q`` ``(..., 9, 6)`` with ``Q Q^T`` the per-element prior's block-diagonal precision
    ``p_rows`` ``(..., 3, 3, 3)`` (:func:`unobserved_precision` with a seen state that has an
    axis; row ``r``'s block ``[r]``): ``Q_r = [v1 v2] L_r``, ``L_r`` the Cholesky factor of
    ``[v1 v2]^T P_r [v1 v2]`` (module docstring, "Joint prior"). ``Q^T e`` is the network's error
    ``e`` ``(..., 9)`` whitened in the unobserved coordinates ``(r, v1), (r, v2)``: unit
    covariance where the per-element prior is right. NaN where a row's block is not positive
    on the plane. :class:`ValueError` for a seen state without an axis."""
    u = observed_direction(s_seen)
    v1 = plane_axis(u)
    if v1 is None:
        raise ValueError("the joint prior needs a seen state with an angle (degree of polarization at least "
                         f"{MIN_SEEN_DOP})")
    basis = np.stack([v1, np.cross(v1, u)], axis=1)  # (3, 2)
    p = np.asarray(p_rows, np.float64)
    g = np.einsum("ai,...rab,bj->...rij", basis, p, basis)
    with np.errstate(invalid="ignore", divide="ignore"):
        l11 = np.sqrt(np.where(g[..., 0, 0] > 0, g[..., 0, 0], np.nan))
        l21 = g[..., 0, 1] / l11
        d = g[..., 1, 1] - l21 * l21
        l22 = np.sqrt(np.where(d > 0, d, np.nan))
    low = np.zeros(g.shape)
    low[..., 0, 0], low[..., 1, 0], low[..., 1, 1] = l11, l21, l22
    rows = np.einsum("ai,...rij->...raj", basis, low)  # (..., 3 rows, 3, 2)
    q = np.zeros(p.shape[:-3] + (9, JOINT_DIM))
    for r in range(3):
        q[..., 3 * r:3 * r + 3, 2 * r:2 * r + 2] = rows[..., r, :, :]
    return q


def joint_precision(p_rows: np.ndarray, s_seen, correlation: np.ndarray) -> np.ndarray:
    """The joint prior's precision ``Q K^-1 Q^T`` ``(..., 9, 9)`` of the per-element prior's
    blocks ``p_rows`` ``(..., 3, 3, 3)`` (:func:`unobserved_factor`) and the whitened
    unobserved error's correlation ``K`` ``(6, 6)`` (module docstring, "Joint prior"); the
    numpy form of :func:`polrig.solve._reference_kernel.correlate_prior`."""
    q = unobserved_factor(p_rows, s_seen)
    kinv = np.linalg.inv(check_correlation(correlation))
    return np.einsum("...ia,ab,...jb->...ij", q, kinv, q)


def open_direction(s_in: np.ndarray) -> np.ndarray:
    """The unit direction ``w = s_a x s_b / |.|`` ``(3,)`` that two states ``s_in`` ``(2, 3)``
    leave open in each row of ``M`` (module docstring, "The open direction's scale");
    :class:`polrig.errors.ConfigError` for another number of states or parallel ones."""
    s = np.asarray(s_in, np.float64).reshape(-1, 3)
    if len(s) != 2:
        raise ConfigError(f"an open direction needs exactly two polarizer states, got {len(s)}")
    w = np.cross(s[0], s[1])
    norm = float(np.linalg.norm(w))
    if not norm > 1e-12 * float(np.linalg.norm(s[0]) * np.linalg.norm(s[1])):
        raise ConfigError("the two states are parallel: they leave two directions of each row open, not one")
    return w / norm


def stretch_precision(p: np.ndarray, w: np.ndarray, factor: float) -> np.ndarray:
    """The prior precision ``p`` ``(..., 9, 9)`` with the standard deviation along the unit ``w``
    ``(3,)`` in every row of ``M`` multiplied by ``factor`` (module docstring, "The open
    direction's scale"): ``B p B``, ``B = I_3 (x) (I + (1/factor - 1) w w^T)``; the numpy form
    of :func:`polrig.solve._reference_kernel.stretch_prior`."""
    b = np.kron(np.eye(3), np.eye(3) + (1.0 / float(factor) - 1.0) * np.outer(w, w))
    return np.einsum("ij,...jk,kl->...il", b, np.asarray(p, np.float64), b)


def check_open_factor(open_factor, n_states: int, seen_state) -> float:
    """``open_factor`` as a float: finite and positive, and other than 1 only with two states
    and a seen state; :class:`polrig.errors.ConfigError` (one line) otherwise."""
    try:
        a = float(open_factor)
    except (TypeError, ValueError):
        raise ConfigError(f"open_factor must be a number, got {open_factor!r}") from None
    if not (np.isfinite(a) and a > 0):
        raise ConfigError(f"open_factor must be finite and positive, got {open_factor!r}")
    if a != 1.0 and (n_states != 2 or seen_state is None):
        raise ConfigError(f"open_factor scales the direction two states leave open: it needs two states "
                          f"and a seen state, got {n_states} state(s)"
                          + ("" if seen_state is not None else " and no seen state"))
    return a


def check_seen_share(seen_share) -> np.ndarray:
    """``seen_share`` as a float64 ``(3,)`` of numbers in ``[0, 1]`` (None: ones, the row's
    whole variance kept); :class:`polrig.errors.ConfigError` (one line) otherwise."""
    if seen_share is None:
        return np.ones(3)
    k = np.asarray(seen_share, np.float64)
    if k.shape != (3,) or not np.all((k >= 0) & (k <= 1)):
        raise ConfigError(f"seen_share must be 3 numbers in [0, 1] (one per row of M), got {seen_share!r}")
    return k


def check_correlation(correlation) -> np.ndarray:
    """``correlation`` as a float64 ``(6, 6)`` symmetric positive definite matrix;
    :class:`polrig.errors.ConfigError` (one line) otherwise."""
    k = np.asarray(correlation, np.float64)
    if k.shape != (JOINT_DIM, JOINT_DIM) or not np.all(np.isfinite(k)):
        raise ConfigError(f"prior_correlation must be a finite {JOINT_DIM}x{JOINT_DIM} matrix, got shape {k.shape}")
    if not np.allclose(k, k.T, rtol=0, atol=1e-9 * max(1.0, float(np.abs(k).max()))):
        raise ConfigError("prior_correlation must be symmetric")
    k = (k + k.T) / 2
    try:
        np.linalg.cholesky(k)
    except np.linalg.LinAlgError:
        raise ConfigError("prior_correlation must be positive definite") from None
    return k


def _prior_array(x, name: str, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{name} must be a real array, got dtype {a.dtype}")
    try:
        a = np.broadcast_to(a, shape)
    except ValueError:
        raise ValueError(f"{name} shape {np.shape(x)} does not broadcast to the solve's "
                         f"(C, 3, 3, H, W) = {shape}") from None
    return _float_samples(a)


def solve_hybrid(s_in: np.ndarray, measured: np.ndarray, variance: np.ndarray,
                 valid: np.ndarray | None = None, analyzer_rows: np.ndarray | None = None, *,
                 prior_mean: np.ndarray, prior_sigma: np.ndarray, seen_state: int | None,
                 plane_variance: str = "axis", prior_correlation: np.ndarray | None = None,
                 seen_share: Sequence[float] | None = None, open_factor: float = 1.0,
                 max_condition: float = DEFAULT_MAX_CONDITION, min_snr: float = MIN_SNR,
                 analyzer_tolerance: Sequence[float] | None = None,
                 generator_tolerance: Sequence[float] | None = None,
                 chunk_pixels: int = DEFAULT_TILE_PIXELS, dtype=np.float32) -> ReferenceResult:
    """Posterior Mueller block per pixel and colour from ``N >= 1`` states and a Gaussian
    prior (module docstring).

    ``s_in``, ``measured``, ``variance``, ``valid``, ``analyzer_rows`` and the keyword options
    as :func:`polrig.solve.reference.solve_reference`, except that any ``N >= 1`` finite
    states are accepted (their ``condition_number`` may be ``inf``; ``max_condition`` applies
    to pixels without a prior only). ``prior_mean``, ``prior_sigma``: ``(C, 3, 3, H, W)`` (or
    broadcastable to it), in the units of the solve (DN per unit incident S0): the
    network's estimate and per-element standard deviation; sigma 0 or ``inf`` is no prior for
    that element. ``seen_state``: index into ``s_in`` of the state whose frame the prior was
    computed from (its samples are in ``measured``), or None when the prior depends on none
    of the measured samples. ``plane_variance``: where the row's prior variance along the seen
    direction goes (module docstring): ``"axis"`` onto the plane's axis :func:`plane_axis`,
    ``"scalar"`` spread over the plane by the factor ``f_r`` (the form before; for the comparison
    in ``models/continuum/``). ``prior_correlation``: the joint prior's ``K`` ``(6, 6)``
    (module docstring, "Joint prior"; :attr:`polrig.models.uncertainty.UncertaintyModel.joint_correlation`),
    applied where the seen frame is used whole, the state has an axis and all nine elements have
    a prior; None (default): the per-element prior. ``seen_share``: per row of ``M``, the share
    ``kappa_r`` of the row's prior variance along the seen direction kept in its unobserved
    plane (module docstring, "The seen direction's share": an analysis option, measured by
    :mod:`polrig.models.coverage_diagnosis`); None (default): all of it. ``open_factor``: at two
    states, the factor on the prior's standard deviation along the direction they leave open
    (module docstring, "The open direction's scale"; :mod:`polrig.solve.open_scale`); 1
    (default): as it is.

    Raises :class:`polrig.errors.ConfigError` for no state, non-finite states, a
    ``seen_state`` that is not an index of ``s_in`` (or a zero state), or a bad option, and
    ``ValueError`` for mismatched shapes; never for bad pixel values (they are masked).
    """
    max_condition, min_snr, dtype, tile = _solve_options(max_condition, min_snr, dtype,
                                                         chunk_pixels)
    if plane_variance not in PLANE_VARIANCE:
        raise ConfigError(f"plane_variance must be one of {', '.join(PLANE_VARIANCE)}, got {plane_variance!r}")
    inputs = solve_inputs(s_in, measured, variance, valid, analyzer_rows, max_condition,
                          analyzer_tolerance, generator_tolerance, check_state_set=False)
    n = len(inputs.s)
    if seen_state is None:
        seen_k, u, axis = -1, np.zeros(3), np.zeros(3)
    else:
        if isinstance(seen_state, bool) or not isinstance(seen_state, (int, np.integer)) \
                or not 0 <= int(seen_state) < n:
            raise ConfigError(f"seen_state must be None or a state index 0..{n - 1}, "
                              f"got {seen_state!r}")
        seen_k = int(seen_state)
        u = observed_direction(inputs.s[seen_k])
        v1 = plane_axis(u) if plane_variance == "axis" else None
        axis = np.zeros(3) if v1 is None else v1
    _, n_col, _, h, w = inputs.meas.shape
    shape = (n_col, 3, 3, h, w)
    kinv = None
    if prior_correlation is not None:
        kinv = np.linalg.inv(check_correlation(prior_correlation))
        kinv = (kinv + kinv.T) / 2
    factor = check_open_factor(open_factor, n, seen_state)
    w_open = open_direction(inputs.s) if factor != 1.0 else np.zeros(3)
    prior = PriorInputs(_prior_array(prior_mean, "prior_mean", shape),
                        _prior_array(prior_sigma, "prior_sigma", shape), u, axis, seen_k,
                        check_seen_share(seen_share), kinv, w_open, factor)
    return solve_tiles(inputs, analyzer_rows, max_condition, min_snr, dtype, tile, prior)
