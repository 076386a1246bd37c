"""Lower-order models at two states: where a model holds, the selection's false acceptance, and
the diffuse term tested on the two states' samples alone.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from polrig.models.continuum.frames import Frames, lit_pixels, stack_states
from polrig.models.continuum.methods import (
    estimate,
    hybrid_models_result,
    open_factor,
    reference_with_models,
    scaled_sigma,
    score,
)
from polrig.models.continuum.sets import FOUR_STATES


#: "A lower-order model holds" at a pixel (from the hidden truth): in every colour the truth's
#: nearest block of some candidate model (:data:`polrig.solve.reduced_models.MODELS`, Frobenius
#: distance) is within this share of the truth's Frobenius norm.
HOLDS_REL = 0.01


def model_holds(truth: np.ndarray, mask: np.ndarray, rel: float = HOLDS_REL) -> np.ndarray:
    """``(H, W)`` object pixels where a lower-order model holds (:data:`HOLDS_REL`): the least
    relative Frobenius distance of the truth ``(C, 3, 3, H, W)`` from each model (its fit with
    the identity metric, :func:`polrig.solve.reduced_models.fit_model`) at most ``rel`` in
    every colour."""
    from polrig.solve.reduced_models import MODELS, fit_model

    ys, xs = np.nonzero(mask)
    blocks = np.moveaxis(truth[..., ys, xs], -1, 1).reshape(-1, 9).astype(np.float64)  # (C*P, 9)
    eye = np.broadcast_to(np.eye(9), (len(blocks), 9, 9))
    dist = np.full(len(blocks), np.inf)
    for model in MODELS:
        _, q, _ = fit_model(model, blocks, eye)
        dist = np.fmin(dist, np.sqrt(np.clip(q, 0.0, None)))
    ok = (dist <= rel * np.linalg.norm(blocks, axis=1)).reshape(truth.shape[0], -1).all(axis=0)
    out = np.zeros(mask.shape, bool)
    out[ys, xs] = ok
    return out


@functools.lru_cache(maxsize=16)
def _detectable(df: int) -> float:
    from polrig.solve.model_selection import detectable_noncentrality

    return detectable_noncentrality(df)


def detectably_off_every_model(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None
                               ) -> np.ndarray:
    """``(C, H, W)``: the object's unclipped pixels whose truth the selection at ``offsets``
    could tell from every candidate model (:mod:`polrig.solve.model_selection`'s false-acceptance
    definition on the hybrid's posterior system: the noncentrality, each model's fit to the
    truth in the metric ``N'`` of the noise-free samples and the network's prior sigma, at least
    :func:`polrig.solve.model_selection.detectable_noncentrality`)."""
    from polrig.solve import model_selection as ms
    from polrig.solve.reduced_models import MODELS, fit_model
    from polrig.solve.reference import forward_measurements

    s, _, var, valid = stack_states(fr, offsets)
    clean = forward_measurements(fr.truth, s)
    out = np.zeros(fr.use.shape, bool)
    h, w = fr.mask.shape
    for c in range(fr.truth.shape[0]):
        ys, xs = np.nonzero(fr.use[c] & fr.clean & (fr.sigma[c] > 0).all(axis=(0, 1)))
        if not len(ys):
            continue
        rs = ms.row_space_equations(s, clean, var, valid, None, c, ys * w + xs)
        ok = (rs.rank >= ms.MIN_RANK) & (rs.rank < 9) & rs.used[:, :4].all(axis=1)
        truth = fr.truth[c][:, :, ys, xs].reshape(9, -1).T
        sd = fr.sigma[c][:, :, ys, xs].reshape(9, -1).T
        normal, m_post = ms.posterior_system(rs.normal, np.where(ok[:, None], rs.m_hat, 0.0), truth, sd, s[0],
                                             correlation)
        det = ok.copy()
        for model in MODELS:
            _, lam, _ = fit_model(model, m_post, normal)
            det &= lam >= _detectable(9 - model.n_params)
        out[c, ys, xs] = det
    return out


def score_where_models_hold(fr: Frames, mueller: np.ndarray, holds: np.ndarray) -> dict[str, float]:
    """Matrix PSNR over the object pixels where a lower-order model holds (:func:`model_holds`)
    and have no clipped sample (``fr.clean``), and their count (the peak of :func:`score`)."""
    from polrig.models.evaluate import psnr

    sel = holds & fr.clean
    pred = (mueller * fr.mask).astype(np.float32)
    peak = float(np.abs(fr.truth[..., fr.mask]).max())
    return {"psnr_holds": psnr(pred, fr.truth, sel, peak) if sel.any() else float("nan"),
            "holds_pixels": float(sel.sum()), "object_pixels": float((fr.mask & fr.clean).sum())}


def models_rows(fr: Frames, two: Sequence[int], correlation: np.ndarray | None = None,
                keys: Sequence[str] = ("single", "hybrid2", "hybrid2_models", "hybrid2_geometry", "hybrid2_diffuse",
                                       "reference4", "reference4_models"),
                prior_scale: bool = True) -> dict[str, dict[str, float]]:
    """One sample's rows of the lower-order model comparison at the 2-state set ``two``:
    single-shot, hybrid 2 and hybrid 2 with the model selection (:func:`hybrid_with_models`),
    each with :func:`score` and :func:`score_where_models_hold` over the pixels where a model
    holds (:func:`model_holds`) that are lit in every colour (:func:`lit_pixels`: in a shadow a
    model holds trivially, the truth is about 0, the network returns about 0 and one frame's
    noise is all there is: single-shot PSNRs of 90 dB); the selection's row also the share of
    scored colour-pixels given a reduced model, overall and where one holds. The bound they are
    read against: ``reference4``, the four-state reference solve (:data:`FOUR_STATES`, no prior),
    and ``reference4_models``, the same with the selection (:func:`reference_with_models`), scored
    alike. ``hybrid2_geometry``: the selection's result with the diffuse completion
    (:func:`polrig.solve.diffuse_geometry.complete_diffuse`, the frames' ``geometry``; the share of
    scored colour-pixels it completed as ``accepted``; absent without a geometry).
    ``hybrid2_diffuse``: hybrid 2 with the diffuse term where the two states' samples alone accept
    it (:func:`polrig.solve.diffuse_test.complete_tested_diffuse`; no selection), ``accepted`` the
    share of scored colour-pixels, its false acceptance where the samples can tell
    (:func:`detectably_off_diffuse`) and in the prior's metric (:func:`detectably_off_every_model`,
    as the selection's); absent without a geometry.
    ``correlation``: the hybrid's joint prior (None: per element); ``keys``: the rows wanted;
    ``prior_scale``: the hybrid rows' prior sigma scaled as captures scale it (:func:`scaled_sigma`)
    or as calibrated (False; the diffuse row is the capture's route, always scaled)."""
    holds = model_holds(fr.truth, fr.mask) & lit_pixels(fr).all(axis=0)
    rows = {}
    for key, method, offs in (("single", "single", two), ("hybrid2", "hybrid", two),
                              ("reference4", "reference", FOUR_STATES)):
        if key in keys:
            est = estimate(fr, offs, method, correlation, prior_scale=prior_scale)
            rows[key] = score(fr, *est) | score_where_models_hold(fr, est[0], holds)
    if "reference4_models" in keys:
        *est, code = reference_with_models(fr, FOUR_STATES)
        rows["reference4_models"] = score(fr, *est) | score_where_models_hold(fr, est[0], holds)
    if "hybrid2_models" not in keys:
        return rows
    from polrig.solve.diffuse_geometry import complete_diffuse
    from polrig.solve.reference import ILL_CONDITIONED

    r, s = hybrid_models_result(fr, two, correlation, prior_scale)
    code = r.models.code
    est = (r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0)
    sel = fr.use & est[2]
    if "hybrid2_geometry" in keys and fr.geometry is not None:
        g, completed, _ = complete_diffuse(r, s, fr.geometry)
        rows["hybrid2_geometry"] = (score(fr, g.mueller, g.sigma, est[2])
                                    | score_where_models_hold(fr, g.mueller, holds)
                                    | {"accepted": float(completed[sel].mean()) if sel.any() else float("nan")})
    reduced = (code != 0) & (code != 255)
    det = detectably_off_every_model(fr, two, correlation) & sel
    if "hybrid2_diffuse" in keys and fr.geometry is not None:
        rows["hybrid2_diffuse"] = diffuse_row(fr, two, correlation, holds, sel, det)
    rows["hybrid2_models"] = (score(fr, *est) | score_where_models_hold(fr, est[0], holds)
                              | {"accepted": float(reduced[sel].mean()) if sel.any() else float("nan"),
                                 "accepted_holds": float(reduced[sel & holds[None]].mean())
                                 if (sel & holds[None]).any() else float("nan"),
                                 "detectable": float(det.sum()), "falsely_accepted": float(reduced[det].sum())})
    return rows


def _truth_system(fr: Frames, two: Sequence[int], test, ys: np.ndarray, xs: np.ndarray):
    """What the diffuse test ``test`` saw at pixels ``ys``, ``xs``, with the truth's noise-free
    Stokes in place of the measured ones: ``(clean (C, 2, 3, P), information (C, 2, 3, 3, P),
    states (2, 3), view (P, 3), light (P, 3), specular block (P, 3, 3) or None, (stage zero axis,
    camera x axis))`` (the frames' information, the test's light and ``eta``)."""
    from polrig.solve.diffuse_geometry import light_fields, specular_block
    from polrig.solve.diffuse_test import state_stokes

    states = np.stack([fr.states[d] for d in two])
    truth = fr.truth[..., ys, xs]
    clean = np.stack([np.einsum("crkp,k->crp", truth, st) for st in states], axis=1)
    info = np.stack([state_stokes(fr.meas[d], fr.var[d], fr.valid[d])[1][..., ys, xs] for d in two], axis=1)
    g = fr.geometry
    light, view, fixed = light_fields(g, ys, xs)[test.light], g.view[ys, xs], (g.stage_zero_axis, g.camera_x_axis)
    spec = None if test.specular_albedo is None else specular_block(light, view, test.eta, *fixed)
    return clean, info, states, view, light, spec, fixed


def detectably_off_diffuse(fr: Frames, two: Sequence[int], test) -> np.ndarray:
    """``(H, W)``: the pixels the diffuse test ``test`` (:func:`polrig.solve.diffuse_test.test_diffuse`
    of the states ``two``) tested whose truth its samples can tell from the diffuse term: the
    truth's own statistic (noise-free Stokes, the frames' information, the test's ``eta`` and
    light) at least the level's 95 % power point (:mod:`polrig.solve.diffuse_test`, "False
    acceptance"); where the test had the specular term, from both of its models (the diffuse
    term alone and with the specular term), each at its own degrees of freedom. The power point
    is the noncentral chi-square's, which overstates the test's power where the misfit is flat in
    the normal (:func:`diffuse_test_power`)."""
    from polrig.solve.diffuse_test import degrees_of_freedom, diffuse_statistic
    from polrig.solve.model_selection import detectable_noncentrality

    out = np.zeros(fr.mask.shape, bool)
    ys, xs = np.nonzero(test.tested)
    if not len(ys) or test.eta is None:
        return out
    clean, info, states, view, light, spec, fixed = _truth_system(fr, two, test, ys, xs)
    lam, _, _ = diffuse_statistic(clean, info, states, view, light, test.eta, *fixed)
    off = lam >= detectable_noncentrality(test.df, test.alpha)
    if spec is not None:
        lam_s, _, _ = diffuse_statistic(clean, info, states, view, light, test.eta, *fixed, specular=spec)
        off &= lam_s >= detectable_noncentrality(degrees_of_freedom(clean.shape[0], True), test.alpha)
    out[ys, xs] = off
    return out


#: The power at which a truth counts as one the samples can tell from the model (as the selection's
#: noncentral power point, :func:`polrig.solve.model_selection.detectable_noncentrality`).
DETECTABLE_POWER = 0.95
#: Noise draws per pixel of the diffuse test's Monte Carlo power (:func:`diffuse_test_power`).
POWER_DRAWS = 200
#: Pixels x draws per call of the compiled statistic in :func:`diffuse_test_power`.
_POWER_BATCH = 100_000


def diffuse_test_power(fr: Frames, two: Sequence[int], test, ys: np.ndarray, xs: np.ndarray, *,
                       draws: int = POWER_DRAWS, seed: int = 0) -> np.ndarray:
    """``(P,)``: the share of ``draws`` noise draws on which the diffuse test ``test`` rejects at
    the pixels ``ys``, ``xs``: its statistics (:func:`polrig.solve.diffuse_test.diffuse_statistic`,
    at the test's ``eta`` and light, with the specular term where the test had it) and its
    decision (:func:`polrig.solve.diffuse_test.decide`) on the truth's noise-free Stokes of each
    state plus Gaussian noise of the frames' information. Its power where the truth is off the
    model, its level where the truth is on it.

    Why not the noncentrality alone (:func:`detectably_off_diffuse`): ``T`` minimises over the
    normal, and where the misfit is flat in the normal while the residual turns with it, the
    noise's cross term with the residual is absorbed by the choice of normal, so ``T`` falls
    below the noncentral chi-square's. Measured (64 samples of four Baek sets, 200 draws): at
    the pixels past the noncentral 95 % power point the test accepts 12-26 % of the draws, and
    12-28 % of the real samples."""
    from polrig.solve.diffuse_test import decide, diffuse_statistic

    ys, xs = np.asarray(ys), np.asarray(xs)
    if not len(ys) or test.eta is None:
        return np.zeros(len(ys))
    clean, info, states, view, light, spec, fixed = _truth_system(fr, two, test, ys, xs)
    n_col, p = clean.shape[0], len(ys)
    chol = np.linalg.cholesky(np.linalg.inv(np.moveaxis(info, -1, 2)))  # (C, 2, P, 3, 3): the noise's
    rng = np.random.default_rng(seed)
    rejected = np.zeros(p)
    per_call = max(1, _POWER_BATCH // p)
    for start in range(0, int(draws), per_call):
        k = min(per_call, int(draws) - start)
        noise = np.einsum("cjpab,cjpkb->cjakp", chol, rng.standard_normal((n_col, 2, p, k, 3)))
        stokes = (clean[..., None, :] + noise).reshape(n_col, 2, 3, k * p)  # draw-major pixels
        tile = lambda a: np.tile(a, (k,) + (1,) * (a.ndim - 1))  # noqa: E731
        system = (np.tile(info, k), states, tile(view), tile(light), test.eta, *fixed)
        t_d, _, _ = diffuse_statistic(stokes, *system)
        t_s = None if spec is None else diffuse_statistic(stokes, *system, specular=tile(spec))[0]
        accepted, _ = decide(t_d, t_s, n_col, test.alpha)
        rejected += (~accepted).reshape(k, p).sum(axis=0)
    return rejected / int(draws)


def diffuse_row(fr: Frames, two: Sequence[int], correlation, holds: np.ndarray, sel: np.ndarray,
                det_prior: np.ndarray) -> dict[str, float]:
    """:func:`models_rows`' ``hybrid2_diffuse`` row: scores, where a model holds, the accepted
    share of the scored colour-pixels ``sel`` ``(C, H, W)``, and the false acceptance counts where
    the samples can tell: past the noncentral power point (:func:`detectably_off_diffuse`; keys
    ``detectable``, ``falsely_accepted``) and, of those, where the test's Monte Carlo power is at
    least :data:`DETECTABLE_POWER` (:func:`diffuse_test_power`; ``_mc``), and in the prior's
    metric (``det_prior``, :func:`detectably_off_every_model`; ``_prior``)."""
    from polrig.solve.diffuse_test import complete_tested_diffuse
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.reference import ILL_CONDITIONED

    s, meas, var, valid = stack_states(fr, two)
    sigma = scaled_sigma(fr, two)  # as the capture's route (polrig.app.diffuse_route)
    r = solve_hybrid(s, meas, var, valid, prior_mean=fr.prior, prior_sigma=sigma, seen_state=0,
                     dtype=np.float64, prior_correlation=correlation,
                     open_factor=open_factor(fr, two, sigma, correlation))
    g, test, _ = complete_tested_diffuse(r, s, meas, var, valid, fr.geometry, prior=(fr.prior, sigma),
                                         seen_state=0, prior_correlation=correlation, mask=fr.mask, specular=True)
    solved = (r.mask & ILL_CONDITIONED) == 0
    accepted = np.broadcast_to(test.accepted[None], sel.shape)
    specular = accepted & (test.specular_albedo > 0)
    off = detectably_off_diffuse(fr, two, test) & sel.any(axis=0)
    ys, xs = np.nonzero(off)
    strong = np.zeros_like(off)
    strong[ys, xs] = diffuse_test_power(fr, two, test, ys, xs) >= DETECTABLE_POWER
    det = np.broadcast_to(off[None], sel.shape) & sel
    det_mc = np.broadcast_to(strong[None], sel.shape) & sel
    return (score(fr, g.mueller, g.sigma, solved) | score_where_models_hold(fr, g.mueller, holds)
            | {"accepted": float(accepted[sel].mean()) if sel.any() else float("nan"),
               "accepted_holds": float(accepted[sel & holds[None]].mean()) if (sel & holds[None]).any()
               else float("nan"),
               "specular": float(specular[sel].mean()) if sel.any() else float("nan"),
               "detectable": float(det.sum()), "falsely_accepted": float(accepted[det].sum()),
               "detectable_mc": float(det_mc.sum()), "falsely_accepted_mc": float(accepted[det_mc].sum()),
               "detectable_prior": float(det_prior.sum()), "falsely_accepted_prior": float(accepted[det_prior].sum())})


def two_state_bound_db(single_db: float, four_models_db: float) -> float:
    """The matrix PSNR (dB) two states could reach at best where a lower-order model holds,
    from two measured rows: the single-shot estimate (``single_db``) and the four-state
    reference with the selection (``four_models_db``). Half its samples leave an estimate of the
    same model ``10 log10 2`` dB worse (variance inversely proportional to the samples);
    combined with the single-shot one as two independent unbiased estimates (inverse-variance
    weights, the most two such estimates give), the mean squared errors add as reciprocals:
    ``10^(P/10) = 10^(P_single/10) + 10^((P_four - 10 log10 2)/10)`` at the same peak. Ideal on
    both counts (the model known, the errors independent): a bound, not an estimate."""
    half = four_models_db - 10.0 * np.log10(2.0)
    return float(10.0 * np.log10(10.0 ** (single_db / 10.0) + 10.0 ** (half / 10.0)))
