"""Hybrid solve (polrig.solve.hybrid): the prior in the reference kernel's normal equations,
its wide-prior limit (the reference solve), the seen state's treatment (no observation counted
twice), coverage of the posterior sigma on a simulated network, extremes and masks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from polrig.errors import ConfigError
from polrig.formats.exr import result_planes
from polrig.optics import mueller as mu
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import reference as ref
from polrig.solve.hybrid import observed_direction, plane_axis, solve_hybrid, unobserved_precision


def states(*angles_deg, er=np.inf):
    return mu.polarizer_stokes(np.radians(angles_deg), er)


def physical_mueller(rng, c, h, w, m00_lo=200.0, m00_hi=2000.0):
    """Realizable Mueller images (C, 3, 3, H, W) with m00 uniform in DN (convex sums of random
    Jones matrices)."""
    j = rng.normal(size=(3, c, h, w, 2, 2)) + 1j * rng.normal(size=(3, c, h, w, 2, 2))
    m = np.einsum("k,k...->...", rng.random(3), mu.jones_to_mueller(j))[..., :3, :3]
    m = m / m[..., :1, :1] * rng.uniform(m00_lo, m00_hi, (c, h, w))[..., None, None]
    return np.moveaxis(m, (-2, -1), (1, 2))


def noisy(rng, m, s, read_var=4.0, gain=0.5):
    """Samples of ``m`` under states ``s`` with Gaussian noise ``read_var + gain I`` (DN^2),
    and that variance."""
    clean = ref.forward_measurements(m, s)
    var = read_var + gain * np.clip(clean, 0, None)
    return clean + rng.normal(size=clean.shape) * np.sqrt(var), var


# ---------------------------------------------------------------------------- dense oracle
def _keep_variance_in_plane(schur, var_r, u, scalar=False, share=1.0):
    """The row's unobserved-plane precision with its prior variance along ``u``,
    ``alpha = share sum u_a^2 var_a``, added to the plane's axis ``v1`` (``plane_axis``): by the
    explicit covariance ``(V^T S V)^-1 + alpha e1 e1^T`` in the basis ``V = [v1, v2]`` where the
    row's three elements have a prior, else (``S`` of rank 1 on the plane) by Sherman-Morrison,
    ``S / (1 + alpha v1^T S v1)``; the scalar ``g_r`` for a seen
    state without an angle, or with ``scalar``."""
    v1 = None if scalar else plane_axis(u)
    if v1 is None:
        off = np.sum(var_r * (1 - u * u))
        return schur * off / (off + share * np.sum(var_r * u * u))
    alpha = share * float(np.sum(var_r * u * u))
    if np.all(var_r > 0):
        basis = np.stack([v1, np.cross(u, v1)], axis=1)  # (3, 2)
        cov = np.linalg.inv(basis.T @ schur @ basis) + np.diag([alpha, 0.0])
        return basis @ np.linalg.inv(cov) @ basis.T
    return schur / (1.0 + alpha * v1 @ schur @ v1)  # S rank 1: S v1 v1^T S = (v1^T S v1) S


#: The last :func:`dense_posterior` call's condition numbers ``(C, H, W)`` (one-element list).
LAST_CONDITION: list[np.ndarray] = []


def dense_posterior(s, meas, var, valid, mean, sigma, seen, scalar=False, share=(1.0, 1.0, 1.0)):
    """Per pixel with numpy: the prior precision by an explicit Schur complement over the
    span of the used seen samples' design rows (the whole-frame row scaling ``g_r`` where
    they span ``M u`` whole), then the posterior. Returns (x, sd, residual, rank) images;
    :data:`LAST_CONDITION` holds each pixel's condition number of the (Jacobi-scaled)
    posterior precision."""
    n = len(s)
    design = ref.design_matrix(s)
    c_n, h, w = meas.shape[1], meas.shape[3], meas.shape[4]
    x = np.zeros((c_n, 9, h, w))
    sd = np.zeros_like(x)
    res = np.zeros((c_n, h, w))
    rank = np.zeros((c_n, h, w), int)
    cond = np.ones((c_n, h, w))
    LAST_CONDITION[:] = [cond]
    for c in range(c_n):
        for yy in range(h):
            for xx in range(w):
                y = meas[:, c, :, yy, xx].reshape(4 * n)
                v = var[:, c, :, yy, xx].reshape(4 * n)
                ok = np.isfinite(y) & np.isfinite(v) & (v > 0)
                if valid is not None:
                    ok &= valid[:, c, :, yy, xx].reshape(4 * n)
                wt = np.where(ok, 1.0 / np.where(ok, v, 1.0), 0.0)
                yv = np.where(ok, y, 0.0)
                sg = sigma[c, :, :, yy, xx].reshape(9)
                mn = mean[c, :, :, yy, xx].reshape(9)
                use = np.isfinite(mn) & np.isfinite(sg) & (sg > 0)
                pi = np.where(use, 1.0 / np.where(use, sg, 1.0) ** 2, 0.0)
                mn = np.where(use, mn, 0.0)
                p = np.diag(pi)
                if seen is not None:
                    rows = [4 * seen + j for j in range(4) if ok[4 * seen + j]]
                    if rows:
                        q_basis = np.linalg.svd(design[rows], full_matrices=False)[2][:min(len(rows), 3)].T
                        # P - P Q (Q^T P Q)^+ Q^T P = R N N^T R, R = P^1/2 and N an orthonormal basis
                        # of the complement of range(R Q): no difference of large terms (the
                        # form with the difference lost 5e-7 on priors 2e5 apart at condition 1e6)
                        root = np.sqrt(pi)
                        left, sv, _ = np.linalg.svd(root[:, None] * q_basis, full_matrices=True)
                        kept = int(np.sum(sv > 1e-12 * sv.max())) if sv.size and sv.max() > 0 else 0
                        comp = root[:, None] * left[:, kept:]
                        p = comp @ comp.T
                        if len(rows) >= 3:  # a whole observed M u: the row variance along u kept
                            u = observed_direction(s[seen])
                            for r in range(3):
                                blk = slice(3 * r, 3 * r + 3)
                                var_r = np.where(pi[blk] > 0, 1.0 / np.where(pi[blk] > 0, pi[blk], 1.0), 0.0)
                                if var_r.sum() > 0:
                                    p[blk, blk] = _keep_variance_in_plane(p[blk, blk], var_r, u, scalar, share[r])
                a = design.T @ (wt[:, None] * design) + p
                b = design.T @ (wt * yv) + p @ mn
                dg = 1.0 / np.sqrt(np.where(np.diag(a) > 0, np.diag(a), 1.0))
                ev = np.linalg.eigvalsh(a * dg[:, None] * dg[None, :])
                cond[c, yy, xx] = ev[-1] / ev[0] if ev[0] > 0 else np.inf
                # an element the samples and the prior leave (nearly) uninformed: the Jacobi
                # scaling above would hide it, its diagonal against the largest shows it
                spread = np.diag(a).min() / np.diag(a).max() if np.diag(a).max() > 0 else 0.0
                if not (ev[0] > 1e-7 * ev[-1] and spread > 1e-7):  # (nearly) singular: -1, or -2
                    rank[c, yy, xx] = -1 if (ev[0] > 1e-14 * ev[-1] and spread > 1e-14) else -2
                    continue
                sol = np.linalg.solve(a, b)
                cov = np.linalg.inv(a)
                x[c, :, yy, xx] = sol
                sd[c, :, yy, xx] = np.sqrt(np.diag(cov))
                r_k = int(np.linalg.matrix_rank(p, tol=1e-9 * max(np.abs(p).max(), 1e-300)))
                rank[c, yy, xx] = r_k
                chi2 = np.sum(wt * (yv - design @ sol) ** 2)
                dof = int(ok.sum()) - np.trace(design @ cov @ design.T * wt[None, :])
                res[c, yy, xx] = chi2 / dof if dof > 0.5 else 0.0
    return x.reshape(c_n, 3, 3, h, w), sd.reshape(c_n, 3, 3, h, w), res, rank


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4), seen=st.booleans(),
       drop=st.floats(0.0, 0.4))
# cases random runs found: singular posteriors the pivots missed (an exactly singular count, an
# element nothing informs, a Schur complement's rounding), and the partial seen state's prior
# formed as a difference (off by up to 1.6e-5 against a long double solve, now 4e-9 as the oracle)
@example(seed=7060889, n=1, seen=True, drop=0.375)
@example(seed=1596101752, n=1, seen=False, drop=0.12911770922753676)
@example(seed=2380273531, n=2, seen=True, drop=0.25152281854727276)
@example(seed=4294967295, n=2, seen=True, drop=0.25)
@example(seed=145566106, n=2, seen=True, drop=0.2282258391809993)
@example(seed=121178517, n=3, seen=True, drop=0.3869887006197571)
@example(seed=2508105926, n=4, seen=True, drop=0.2437140861613191)
def test_kernel_matches_a_dense_posterior(seed, n, seen, drop):
    """The compiled kernel against a per-pixel numpy posterior, with random states, excluded
    samples (so that 0-4 of the seen state's samples are used), elements without a prior and
    priors of very different widths."""
    _kernel_against_the_oracle(seed, n, seen, drop, "axis")


@pytest.mark.parametrize("seed,n", [(1, 1), (2, 2), (3, 3), (4, 4)])
def test_kernel_matches_a_dense_posterior_with_the_scalar_plane_factor(seed, n):
    """``plane_variance="scalar"`` (the row variance spread over the plane by ``f_r``, the
    comparison of ``models/continuum/``) against the same oracle."""
    _kernel_against_the_oracle(seed, n, True, 0.1, "scalar")


@pytest.mark.parametrize("plane_variance", ["axis", "scalar"])
@pytest.mark.parametrize("seed,n,share", [(5, 1, (0.0, 0.5, 1.0)), (6, 2, (0.3, 0.0, 0.9)), (8, 3, (0.7, 0.2, 0.0))])
def test_kernel_matches_a_dense_posterior_with_a_share_of_the_seen_variance(seed, n, share, plane_variance):
    """``seen_share`` (the part of each row's variance along ``u`` kept in its plane, 0 the plain
    marginal) against the same oracle, a different share per row."""
    _kernel_against_the_oracle(seed, n, True, 0.1, plane_variance, share)


def _kernel_against_the_oracle(seed, n, seen, drop, plane_variance, share=None):
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 180, n)
    s = states(*ang, er=rng.uniform(100, 1e4))
    c, h, w = 1, 3, 5
    m = physical_mueller(rng, c, h, w)
    meas, var = noisy(rng, m, s)
    valid = rng.random(meas.shape) >= drop
    mean = m + rng.normal(size=m.shape) * 30
    sigma = 10.0 ** rng.uniform(0, 3, m.shape)
    sigma[rng.random(m.shape) < 0.1] = np.inf  # no prior for some elements
    k = 0 if seen else None
    got = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sigma, seen_state=k,
                       plane_variance=plane_variance, seen_share=share, dtype=np.float64)
    x, sd, res, rank = dense_posterior(s, meas, var, valid, mean, sigma, k, scalar=plane_variance == "scalar",
                                       share=(1.0, 1.0, 1.0) if share is None else share)
    solved = (got.mask & ref.ILL_CONDITIONED) == 0
    # a pixel without a prior follows the reference solve's rule (its samples' condition); one
    # with a prior is unsolved exactly where its posterior is singular
    assert not solved[rank == -2].any()
    judged = (rank >= 0) & ((rank > 0) | (got.pixel_condition <= ref.DEFAULT_MAX_CONDITION))
    assert np.array_equal(solved[rank != -1], judged[rank != -1])
    solved &= rank >= 0
    # float64 rounding grows with the posterior's condition (up to 1e7 here, where the oracle
    # stops solving): 1e-8, or 100 eps per unit of condition where that is larger
    tol = np.maximum(1e-8, 100 * np.finfo(np.float64).eps * LAST_CONDITION[0])[solved]
    for got_a, want in ((got.mueller, x), (got.sigma, sd)):
        scale = np.abs(want).max(axis=(1, 2), keepdims=True) + 1e-300
        err = np.abs(got_a - want) / scale
        assert np.all(err.transpose(1, 2, 0, 3, 4)[:, :, solved] < tol), err.max()
    assert np.allclose(got.residual[solved], res[solved], rtol=1e-7, atol=1e-9)


# ---------------------------------------------------------------------------- wide-prior limit
@pytest.mark.parametrize("case", ["plain", "tolerances", "per_pixel_rows"])
def test_infinite_prior_is_the_reference_solve_bit_for_bit(case):
    rng = np.random.default_rng(7)
    s = states(0, 45, 90, 135, er=800)
    c, h, w = 2, 6, 70  # two lane blocks per row, a partial one included
    m = physical_mueller(rng, c, h, w)
    meas, var = noisy(rng, m, s)
    valid = rng.random(meas.shape) > 0.08  # excluded samples: some pixels ill-conditioned
    var[0, 0, 1, 2, 3] = np.nan  # NONFINITE
    kw = {}
    if case == "tolerances":
        kw = dict(analyzer_tolerance=(0.01, 0.5, 0.01), generator_tolerance=(0.3, 0.002))
    if case == "per_pixel_rows":
        kw = dict(analyzer_rows=ideal_analyzer_matrix()[None, :, :, None, None]
                  * (1 + 0.03 * rng.normal(size=(c, 4, 3, h, w))))
    want = ref.solve_reference(s, meas, var, valid, **kw)
    for seen in (None, 0, 3):
        got = solve_hybrid(s, meas, var, valid, prior_mean=m, prior_sigma=np.inf, seen_state=seen, **kw)
        for name in ("mueller", "sigma", "sigma_noise", "residual", "mask", "pixel_condition", "n_samples"):
            assert np.array_equal(getattr(got, name), getattr(want, name)), (name, seen)
        assert got.condition_number == want.condition_number
    assert (want.mask & ref.ILL_CONDITIONED).any() and (want.mask & ref.NONFINITE).any()


def test_wide_prior_tends_to_the_reference_solve():
    """At 1e8 times the data's sigma the prior changes nothing beyond 1e-9 (relative to each
    pixel's largest element), with the seen state's samples partly excluded."""
    rng = np.random.default_rng(8)
    s = states(0, 60, 120, er=2000)
    m = physical_mueller(rng, 1, 8, 40)
    meas, var = noisy(rng, m, s)
    valid = rng.random(meas.shape) > 0.05
    want = ref.solve_reference(s, meas, var, valid, dtype=np.float64)
    ok = want.mask & ref.ILL_CONDITIONED == 0
    for seen in (None, 0):
        got = solve_hybrid(s, meas, var, valid, prior_mean=m * 1.1, prior_sigma=1e8 * want.sigma.max(),
                           seen_state=seen, dtype=np.float64)
        assert np.array_equal(got.mask, want.mask)
        scale = np.abs(want.mueller).max(axis=(1, 2))[ok]
        for name in ("mueller", "sigma"):
            err = np.abs(getattr(got, name) - getattr(want, name)).max(axis=(1, 2))[ok] / scale
            assert err.max() < 1e-9, name
        assert np.allclose(got.residual[ok], want.residual[ok], rtol=1e-9)


# ---------------------------------------------------------------------------- simulated network
def simulated_network(rng, m, s0, meas0, var0, tau_rel=0.03, misfit_rel=0.0):
    """A network that saw the frame of ``s0`` (samples ``meas0``, ``var0`` ``(C, 4, H, W)``):
    in each row's observed direction ``u`` it reproduces that frame's weighted least-squares
    ``M u`` (plus an independent misfit of ``misfit_rel m00``), in the unobserved plane it
    errs by independent Gaussians of ``tau_rel m00`` on each of two axes of that plane, and
    its sigma is the exact per-element standard deviation of its error (calibrated)."""
    u = observed_direction(s0)
    v = np.linalg.svd(u[None])[2][1:].T  # (3, 2) orthonormal basis of u's complement
    a = ideal_analyzer_matrix() * np.linalg.norm(s0)  # sample j = a_j . (M u)
    wt = 1.0 / var0  # (C, 4, H, W)
    ata = np.einsum("ja,jb,cjhw->chwab", a, a, wt)
    cov_z = np.linalg.inv(ata)  # (C, H, W, 3, 3): covariance of the frame's M u
    z = np.einsum("chwab,jb,cjhw->chwa", cov_z, a, wt * meas0)
    mm = np.moveaxis(m, (1, 2), (-2, -1))  # (C, H, W, 3, 3)
    m00 = mm[..., 0, 0][..., None]
    tau = tau_rel * m00  # (C, H, W, 1)
    eta = rng.normal(size=mm.shape[:-2] + (3, 2)) * tau[..., None]
    misfit = rng.normal(size=mm.shape[:-2] + (3,)) * misfit_rel * m00
    est = (mm @ v) @ v.T + eta @ v.T + (z + misfit)[..., None] * u
    # exact per-element variance: the plane's two axes, the frame's M u (and the misfit)
    var_el = (tau[..., None] ** 2) * np.sum(v * v, axis=1) \
        + (np.diagonal(cov_z, axis1=-2, axis2=-1) + (misfit_rel * m00) ** 2)[..., None] * u * u
    back = lambda x: np.moveaxis(x, (-2, -1), (1, 2))  # noqa: E731
    return back(est), back(np.sqrt(var_el))


def coverage(est, sd, truth):
    return float(np.mean(np.abs(est - truth) <= 2.0 * sd))


def _simulated_sets(seed, angles, h=32, w=64, **net):
    rng = np.random.default_rng(seed)
    s = states(*angles, er=1000)
    m = physical_mueller(rng, 1, h, w)
    meas, var = noisy(rng, m, s)
    mean, sigma = simulated_network(rng, m, s[0], meas[0], var[0], **net)
    return s, m, meas, var, mean, sigma


@pytest.mark.parametrize("angles", [(10,), (10, 100), (10, 70, 130), (10, 55, 100, 145)])
def test_posterior_sigma_covers_95_percent_on_a_simulated_network(angles):
    s, m, meas, var, mean, sigma = _simulated_sets(11, angles)
    assert 0.945 < coverage(mean, sigma, m) < 0.962  # the network itself is calibrated
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    assert not got.mask.any()
    cov = coverage(got.mueller, got.sigma, m)
    assert 0.93 <= cov <= 0.97, cov


@pytest.mark.parametrize("tau_rel", [0.03, 0.005])
def test_counting_the_seen_frame_twice_is_overconfident(tau_rel):
    """A network that reproduces its frame: counting its whole prior and that frame covers
    less than 2 sigma promises (the frame's noise counted twice); the projected prior keeps
    the promise. Where the network's error in the unobserved plane is as small as the frame's
    noise (0.005) the projection is conservative (the row's whole calibrated variance is kept
    in the plane, module docstring)."""
    s, m, meas, var, mean, sigma = _simulated_sets(12, (10, 100), tau_rel=tau_rel)
    naive = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=None,
                         dtype=np.float64)
    right = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=0,
                         dtype=np.float64)
    cov_naive, cov_right = coverage(naive.mueller, naive.sigma, m), coverage(right.mueller, right.sigma, m)
    assert cov_naive < 0.93 and cov_right >= 0.93, (cov_naive, cov_right)
    if tau_rel >= 0.03:
        assert cov_right <= 0.97


def test_seen_state_alone_is_the_frame_plus_the_priors_unobserved_part():
    s, m, meas, var, mean, sigma = _simulated_sets(13, (25,), misfit_rel=0.01)
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    u = observed_direction(s[0])
    # the frame's own estimate of M u: the same solve with a prior on the plane only
    plane = np.eye(3) - np.outer(u, u)
    est_u = np.einsum("crahw,a->crhw", got.mueller, u)
    want_plane = np.einsum("crahw,ab->crbhw", mean, plane)
    assert np.allclose(np.einsum("crahw,ab->crbhw", got.mueller, plane), want_plane, rtol=0,
                       atol=1e-9 * np.abs(m).max())
    # the u-part is the frame's weighted least squares (the network without its misfit)
    net_nomisfit, _ = simulated_network(np.random.default_rng(0), m, s[0], meas[0], var[0], tau_rel=0.0)
    assert np.allclose(est_u, np.einsum("crahw,a->crhw", net_nomisfit, u), rtol=1e-9, atol=1e-9)
    # and it is no worse than the prior: in expectation, and here on 2048 pixels
    mse = lambda x: float(np.mean((x - m) ** 2))  # noqa: E731
    assert mse(got.mueller) < mse(mean)
    # the network's misfit along u is not in the plane, where its variance is kept: a little
    # conservative (97.3 % here)
    assert 0.93 <= coverage(got.mueller, got.sigma, m) <= 0.98
    assert np.all(got.residual >= 0) and abs(float(np.mean(got.residual)) - 1.0) < 0.1  # chi^2_1


def test_a_calibrated_prior_improves_the_reference_solve():
    s, m, meas, var, mean, sigma = _simulated_sets(14, (10, 70, 130), tau_rel=0.005)
    hyb = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    rs = ref.solve_reference(s, meas, var, dtype=np.float64)
    assert np.mean((hyb.mueller - m) ** 2) < 0.9 * np.mean((rs.mueller - m) ** 2)
    assert np.all(hyb.sigma <= rs.sigma * (1 + 1e-12))


# ---------------------------------------------------------------------------- extremes
def _small(seed=3, angles=(0, 60), h=4, w=6):
    rng = np.random.default_rng(seed)
    s = states(*angles, er=500)
    m = physical_mueller(rng, 1, h, w)
    meas, var = noisy(rng, m, s)
    return rng, s, m, meas, var


def test_a_posterior_singular_by_count_or_by_an_uninformed_element_is_ill_conditioned():
    """The kernel's exact rules for a pixel with a prior, whatever rounding leaves in the
    Cholesky pivots: fewer samples used than the nine elements less the prior's directions
    (one state, two of its samples, no prior on m10: 2 + 8 - 2 < 9), and an element that neither
    the samples nor the prior inform (no prior on m10, only the 45 and 135 deg analyzers, whose
    rows have no S1 part: m1x is seen by no sample). A random case of each came out solved
    with a sigma of 1e19 before."""
    rng, s, m, meas, var = _small(angles=(20,))
    sigma = np.full(m.shape, 20.0)
    sigma[:, 1, 0] = np.inf
    valid = np.zeros(meas.shape, bool)
    valid[:, :, [1, 3]] = True
    for seen in (0, None):
        got = solve_hybrid(s, meas, var, valid, prior_mean=m, prior_sigma=sigma, seen_state=seen,
                           dtype=np.float64)
        assert np.all(got.mask & ref.ILL_CONDITIONED), seen
        assert not got.mueller.any() and not got.sigma.any()
    # with a prior on m10 too, the same samples make a regular posterior
    got = solve_hybrid(s, meas, var, valid, prior_mean=m, prior_sigma=20.0, seen_state=None, dtype=np.float64)
    assert not (got.mask & ref.ILL_CONDITIONED).any()


def test_no_prior_pixels_are_solved_from_their_samples_alone():
    """sigma 0 (the network's background) or inf: the reference solve's rule, i.e. fewer than
    3 states leave such pixels ILL_CONDITIONED with zero outputs."""
    rng, s, m, meas, var = _small()
    sigma = np.full(m.shape, 20.0)
    sigma[..., 0, :3] = 0.0
    sigma[..., 1, :3] = np.inf
    got = solve_hybrid(s, meas, var, prior_mean=m, prior_sigma=sigma, seen_state=0)
    bad = np.zeros(got.mask.shape, bool)
    bad[:, :2, :3] = True
    assert np.array_equal((got.mask & ref.ILL_CONDITIONED) > 0, bad)
    assert not got.mueller[..., bad[0]].any() and not got.sigma[..., bad[0]].any()
    assert np.all(got.sigma[..., ~bad[0]] > 0)
    assert np.all(np.isinf(got.pixel_condition)) and got.condition_number == np.inf


def test_non_finite_prior_values_are_flagged_and_ignored():
    rng, s, m, meas, var = _small(angles=(0, 45, 90))
    mean = m.copy()
    sigma = np.full(m.shape, 5.0)
    mean[0, 1, 1, 0, 0] = np.nan  # mean NaN with a finite sigma
    sigma[0, 2, 2, 0, 1] = np.nan
    sigma[0, 0, 0, 0, 2] = -1.0
    mean[0, 0, 1, 0, 3] = np.inf
    sigma[0, 0, 1, 0, 3] = np.inf  # no prior there: not a fault
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=sigma, seen_state=0)
    flagged = (got.mask[0, 0] & ref.NONFINITE) > 0
    assert flagged.tolist() == [True, True, True, False, False, False]
    assert np.all(np.isfinite(got.mueller)) and not (got.mask & ref.ILL_CONDITIONED).any()


def test_a_tiny_prior_sigma_pins_the_unobserved_part():
    rng, s, m, meas, var = _small(angles=(30,))
    mean = m + 50.0
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=1e-3, seen_state=0, dtype=np.float64)
    u = observed_direction(s[0])
    plane = np.eye(3) - np.outer(u, u)
    assert not got.mask.any()
    assert np.allclose(np.einsum("crahw,ab->crbhw", got.mueller, plane),
                       np.einsum("crahw,ab->crbhw", mean, plane), atol=1e-6)
    assert np.all(got.sigma < 1e3)
    # without the seen frame's treatment the tiny prior simply wins everywhere
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=1e-3, seen_state=None, dtype=np.float64)
    assert np.allclose(got.mueller, mean, atol=1e-6)
    # a prior 1e9 times tighter than the samples leaves the u direction numerically singular
    # (precisions 1e20 apart): unsolved, zeros, never a wrong number with a small sigma
    got = solve_hybrid(s, meas, var, prior_mean=mean, prior_sigma=1e-8, seen_state=0)
    assert np.all(got.mask & ref.ILL_CONDITIONED) and not got.mueller.any() and not got.sigma.any()


def test_masked_seen_samples_hand_their_directions_back_to_the_prior():
    """With every sample of the seen state excluded the prior is used whole (the estimate at
    one state is the prior); with 2 of 4 left the two observed directions come from them."""
    rng, s, m, meas, var = _small(angles=(20,))
    mean = m + rng.normal(size=m.shape) * 20
    sigma = np.full(m.shape, 20.0)
    valid = np.ones(meas.shape, bool)
    valid[0, :, :, 0, :] = False  # row 0: all four excluded
    valid[0, :, :2, 1, :] = False  # row 1: two left
    got = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    assert np.allclose(got.mueller[..., 0, :], mean[..., 0, :], rtol=0, atol=1e-9)
    assert np.allclose(got.sigma[..., 0, :], 20.0)
    assert np.all(got.mask[:, :2] & ref.SATURATED) and not (got.mask & ref.ILL_CONDITIONED).any()
    x, sd, res, rank = dense_posterior(s, meas, var, valid, mean, sigma, 0)
    assert np.allclose(got.mueller, x, rtol=1e-9, atol=1e-9) and np.allclose(got.sigma, sd, rtol=1e-9)
    assert np.all(rank[:, 1] == 7) and np.all(rank[:, 0] == 9) and np.all(rank[:, 2:] == 6)


def test_unobserved_precision_annihilates_the_seen_direction():
    rng = np.random.default_rng(5)
    sd = 10.0 ** rng.uniform(-1, 2, (50, 3))
    s0 = states(33.0, er=300)[0]
    p = unobserved_precision(sd, s0)
    u = observed_direction(s0)
    assert np.abs(p @ u).max() < 1e-12 * np.abs(p).max()
    assert np.all(np.linalg.eigvalsh(p) > -1e-12 * np.abs(p).max())
    # in the plane (basis v1 = plane_axis, v2 = 45 deg light): the marginal covariance of the
    # diagonal prior plus its variance along u on v1, so the row's whole variance is kept
    v1 = plane_axis(u)
    v2 = np.cross(v1, u)
    assert np.allclose(v2, np.array([0.0, -u[2], u[1]]) / np.hypot(u[1], u[2]), atol=1e-12)
    v = np.stack([v1, v2], axis=1)
    for k in range(5):
        cov = np.diag(sd[k] ** 2)
        want = v.T @ cov @ v + np.diag([u @ cov @ u, 0.0])
        assert np.allclose(np.linalg.inv(v.T @ p[k] @ v), want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
        assert np.isclose(np.trace(np.linalg.inv(v.T @ p[k] @ v)), np.sum(sd[k] ** 2), rtol=1e-10)
    assert np.allclose(unobserved_precision(sd), np.einsum("ka,ab->kab", sd ** -2.0, np.eye(3)))
    # a seen state without an angle (unpolarized): no axis, the scalar row factor g_r
    p0 = unobserved_precision(sd, np.array([1.0, 0.0, 0.0]))
    assert plane_axis(np.array([1.0, 0.0, 0.0])) is None
    for k in range(5):
        g = np.sum(sd[k, 1:] ** 2) / np.sum(sd[k] ** 2)
        assert np.allclose(p0[k], g * np.diag([0.0, *sd[k, 1:] ** -2.0]), rtol=1e-10, atol=0)


def test_seen_share_keeps_that_part_of_the_variance_along_u():
    """The numpy form: share 1 is the default bit for bit, share 0 the plain marginal (the Schur
    complement), and in between the plane's covariance holds ``share alpha`` on ``v1``; the
    one-state posterior's sigma falls with the share, its mean does not move; bad shares are one
    line."""
    rng = np.random.default_rng(11)
    sd = 10.0 ** rng.uniform(-1, 2, (40, 3, 3))
    s0 = states(71.0, er=300)[0]
    u = observed_direction(s0)
    assert np.array_equal(unobserved_precision(sd, s0, seen_share=[1.0, 1.0, 1.0]), unobserved_precision(sd, s0))
    pi = sd ** -2.0
    schur = pi[..., :, None] * np.eye(3) - (pi * u)[..., :, None] * (pi * u)[..., None, :] \
        / np.sum(pi * u * u, axis=-1)[..., None, None]
    assert np.allclose(unobserved_precision(sd, s0, seen_share=[0.0, 0.0, 0.0]), schur, rtol=1e-12, atol=0)
    share = np.array([0.25, 0.5, 0.75])
    p = unobserved_precision(sd, s0, seen_share=share)
    v1 = plane_axis(u)
    v = np.stack([v1, np.cross(v1, u)], axis=1)
    for k in range(5):
        for r in range(3):
            cov = np.diag(sd[k, r] ** 2)
            want = v.T @ cov @ v + np.diag([share[r] * (u @ cov @ u), 0.0])
            assert np.allclose(np.linalg.inv(v.T @ p[k, r] @ v), want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    # the solve: one state, every element a prior
    c, h, w = 1, 2, 3
    m = physical_mueller(rng, c, h, w)
    st1 = states(71.0, er=800)
    meas, var = noisy(rng, m, st1)
    mean, sigma = m + rng.normal(size=m.shape) * 20, np.full(m.shape, 30.0)
    kw = dict(prior_mean=mean, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    whole = solve_hybrid(st1, meas, var, **kw)
    assert np.array_equal(solve_hybrid(st1, meas, var, seen_share=[1.0, 1.0, 1.0], **kw).sigma, whole.sigma)
    half = solve_hybrid(st1, meas, var, seen_share=[0.5, 0.5, 0.5], **kw)
    none = solve_hybrid(st1, meas, var, seen_share=[0.0, 0.0, 0.0], **kw)
    assert np.allclose(half.mueller, whole.mueller, rtol=0, atol=1e-9 * np.abs(whole.mueller).max())
    assert np.all(none.sigma <= half.sigma * (1 + 1e-12)) and np.all(half.sigma <= whole.sigma * (1 + 1e-12))
    assert np.any(none.sigma < whole.sigma * 0.99)
    for bad in ([0.5, 0.5], [1.5, 0.0, 0.0], [-0.1, 0.0, 0.0], [np.nan, 0.0, 0.0]):
        with pytest.raises(ConfigError, match="seen_share must be 3 numbers in"):
            solve_hybrid(st1, meas, var, seen_share=bad, **kw)


# ---------------------------------------------------------------------------- properties
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 5), chunk=st.sampled_from([1, 7, 64, 4096]))
def test_results_do_not_depend_on_tiles(seed, n, chunk):
    rng = np.random.default_rng(seed)
    s = states(*rng.uniform(0, 180, n), er=1000)
    m = physical_mueller(rng, 2, 5, 67)
    meas, var = noisy(rng, m, s)
    valid = rng.random(meas.shape) > 0.1
    sigma = np.abs(rng.normal(size=m.shape)) * 50
    kw = dict(prior_mean=m, prior_sigma=sigma, seen_state=int(rng.integers(n)))
    a = solve_hybrid(s, meas, var, valid, chunk_pixels=chunk, **kw)
    b = solve_hybrid(s, meas, var, valid, **kw)
    for name in ("mueller", "sigma", "residual", "mask", "n_samples", "pixel_condition"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 4), k=st.floats(1e-3, 1e3))
def test_prior_and_data_scale_together(seed, n, k):
    """Units: scaling the samples by k, their variance by k^2 and the prior by k scales the
    estimate and sigma by k and leaves the residual and masks unchanged."""
    rng = np.random.default_rng(seed)
    s = states(*rng.uniform(0, 180, n), er=1000)
    m = physical_mueller(rng, 1, 3, 9)
    meas, var = noisy(rng, m, s)
    sigma = np.abs(rng.normal(size=m.shape)) * 40 + 1
    a = solve_hybrid(s, meas, var, prior_mean=m, prior_sigma=sigma, seen_state=0, dtype=np.float64)
    b = solve_hybrid(s, meas * k, var * k * k, prior_mean=m * k, prior_sigma=sigma * k, seen_state=0,
                     dtype=np.float64)
    assert np.array_equal(a.mask, b.mask)
    assert np.allclose(b.mueller, a.mueller * k, rtol=1e-9, atol=1e-12 * k * np.abs(m).max())
    assert np.allclose(b.sigma, a.sigma * k, rtol=1e-9)
    assert np.allclose(b.residual, a.residual, rtol=1e-7, atol=1e-12)


# ---------------------------------------------------------------------------- interface
def test_bad_arguments_are_one_line_errors():
    rng, s, m, meas, var = _small()
    kw = dict(prior_mean=m, prior_sigma=1.0)
    with pytest.raises(ConfigError, match="seen_state"):
        solve_hybrid(s, meas, var, seen_state=2, **kw)
    with pytest.raises(ConfigError, match="seen_state"):
        solve_hybrid(s, meas, var, seen_state=True, **kw)
    with pytest.raises(ConfigError, match="at least 1"):
        solve_hybrid(np.zeros((0, 3)), meas[:0], var[:0], seen_state=None, **kw)
    with pytest.raises(ConfigError, match="not all 0"):
        solve_hybrid(np.zeros((2, 3)), meas, var, seen_state=0, **kw)
    with pytest.raises(ValueError, match="prior_mean"):
        solve_hybrid(s, meas, var, seen_state=0, prior_mean=m[..., :2], prior_sigma=1.0)
    with pytest.raises(ConfigError, match="max_condition"):
        solve_hybrid(s, meas, var, seen_state=0, max_condition=0.5, **kw)
    with pytest.raises(ConfigError, match="plane_variance"):
        solve_hybrid(s, meas, var, seen_state=None, plane_variance="marginal", **kw)


def test_the_result_writes_the_reference_planes():
    rng, s, m, meas, var = _small(angles=(0,))
    got = solve_hybrid(s, meas, var, prior_mean=m, prior_sigma=30.0, seen_state=0,
                       analyzer_tolerance=(0.01, 0.2, 0.0))
    planes = result_planes(got)
    assert {"sigma.M00.Y", "sigma_noise.M22.Y", "mask.Y", "residual.Y"} <= set(planes)
    assert np.all(got.sigma >= got.sigma_noise)


# ---------------------------------------------------------------------------- from frames
@pytest.mark.parametrize("method", ["superpixel", "bilinear"])
def test_frames_in_bands_equal_one_whole_image_solve(method):
    """reference_from_frames with a prior: band by band (each with its rows of the prior) the
    same numbers as one hybrid solve of the whole demosaiced image."""
    from polrig.sensor.layouts import IMX250MYR
    from polrig.solve.radiometry import analyzer_stack, reference_from_frames

    from _state_radiance import noisy_states

    rng = np.random.default_rng(21)
    shape = (40, 48)
    s = states(0, 90, er=700)
    sts = noisy_states(rng, physical_mueller(rng, 3, *shape), s, IMX250MYR)
    parts = [analyzer_stack(st_, IMX250MYR, method) for st_ in sts]
    meas, var, valid = (np.stack([p[i] for p in parts]) for i in range(3))
    mean = rng.normal(size=(3, 3, 3) + meas.shape[-2:]) * 50 + 100
    sigma = np.abs(rng.normal(size=mean.shape)) * 30
    whole = solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sigma, seen_state=0)
    banded = reference_from_frames(sts, s, IMX250MYR, method, band_pixels=300, prior_mean=mean,
                                   prior_sigma=sigma, seen_state=0, workers=2)
    for name in ("mueller", "sigma", "residual", "mask", "pixel_condition", "n_samples"):
        assert np.array_equal(getattr(banded, name), getattr(whole, name)), name
    with pytest.raises(ValueError, match="both"):
        reference_from_frames(sts, s, IMX250MYR, method, prior_mean=mean)
    with pytest.raises(ValueError, match="output grid"):
        reference_from_frames(sts, s, IMX250MYR, method, prior_mean=mean[..., :3, :], prior_sigma=sigma,
                              seen_state=0)
