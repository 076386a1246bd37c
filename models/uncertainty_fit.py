"""The fitting tool of the single-shot uncertainty (:mod:`polrig.models.uncertainty`, whose module
docstring describes the error model; that module is the runtime part).

Calibration (:func:`calibrate`): a first fit without the light-spread factor gives each
calibration image the factor its sigma would need (:func:`needed_factors`); the factor's knee,
where it stops growing, is fitted to those, its low limit and reference are quantiles of the
images' spread (:func:`spread_limits`); then the errors are divided by the factor and the
coefficients are fitted to the ``COVERAGE`` quantile of
``|error'| / scale`` in bins of ``q`` and, within each, of ``r`` (weighted least squares over
the bins, coefficients kept >= 0), then each element's sigma is rescaled so that exactly
``COVERAGE`` of the calibration errors lie within ``2 sigma``, the fraction a right Gaussian
sigma covers; ``k`` (:func:`calibrate_mirror`) so that the tenth of the mirror-averaged
calibration elements whose disagreement is largest against ``sigma`` is covered as well.
Pixels with a clipped
analyzer sample are left out: a clipped highlight's magnitude is unknown, and
:mod:`polrig.app.processing` reports infinite sigma there.

``python -m polrig.models.uncertainty_fit --data DIR [DIR ...] --write`` runs the shipped graph on
``polrig sim dataset`` folders, calibrates and writes ``models/weights/uncertainty.json`` (with
the SHA-256 of the graph it belongs to); ``--check DIR ...`` prints the coverage on other sets.
``--data DIR [DIR ...] --joint --write`` fits only the joint prior on top of the calibration in the
file (:func:`joint_whitened`, :func:`fit_joint`; :mod:`polrig.solve.hybrid`, "Joint prior") and
adds it as ``joint_prior``, everything else in the file as it is; a refit of the per-element
sigma writes the file without it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
from collections.abc import Iterable, Sequence

import numpy as np

from polrig.errors import ConfigError, FormatError
from polrig.models.uncertainty import (
    COVERAGE,
    FILE_NAME,
    JOINT_KEY,
    JOINT_VERSION,
    N_FEATURES,
    P_MIN,
    SPREAD_QUANTILES,
    UncertaintyModel,
    calibration_for_graph,
    feature_rows,
    features,
    graph_sha256,
    how_to_calibrate,
    light_spread,
    misfit,
    observed_frame_rotation,
    to_observed_frame,
)

#: Bins of :func:`calibrate`: quantiles of the polarization strength ``q``, then within each
#: quantiles of the misfit ``r``.
Q_BINS = 12
R_BINS = 6
#: Fraction of elements, those whose mirror disagreement is largest against ``sigma``, whose
#: coverage :func:`calibrate_mirror` sets.
MIRROR_TOP = 0.1


@dataclasses.dataclass
class Sample:
    """One prediction with its truth: ``pred``/``truth`` ``(C, 3, 3, H, W)``, ``s_in`` (3,),
    ``mask`` (H, W) object pixels, ``clipped`` (C, H, W) pixels with a clipped sample,
    ``stokes`` ``(C, 3, H, W)`` the measured Stokes images the prediction was made from;
    ``light_spread`` the network's light spread over the object (rad,
    :func:`polrig.models.uncertainty.light_spread`);
    ``disagreement`` (like ``pred``) for a mirror-averaged prediction, else None."""

    pred: np.ndarray
    truth: np.ndarray
    s_in: np.ndarray
    mask: np.ndarray
    clipped: np.ndarray
    stokes: np.ndarray
    light_spread: float
    disagreement: np.ndarray | None = None


def needed_factors(model: UncertaintyModel, samples: Sequence[Sample]) -> np.ndarray:
    """Per sample, the factor its sigma (``model``'s) would need for ``COVERAGE`` of its own
    elements within 2 sigma: the ``COVERAGE`` quantile of ``|error| / (2 sigma)`` ``(n,)`` (NaN
    for a sample without a scored element)."""
    out = []
    for s in samples:
        e, g, _ = _pooled(model, [s], mirror_term=False)
        ratio = (e / np.maximum(g, 1e-30)).ravel()
        out.append(float(np.quantile(ratio, COVERAGE)) / 2.0 if ratio.size else np.nan)
    return np.asarray(out)


def spread_limits(samples: Sequence[Sample], plain: UncertaintyModel) -> dict[str, float]:
    """The light-spread factor's ``{"low", "reference", "high"}`` (rad) from the calibration
    ``samples`` and their fit without the factor, ``plain``: ``low`` and ``reference`` the
    :data:`~polrig.models.uncertainty.SPREAD_QUANTILES` of the samples' spreads; ``high``, where
    the factor stops growing, the knee ``omega_c`` of ``n = k min(max(omega, low), omega_c)``
    fitted to the samples' :func:`needed_factors` ``n`` by least squares in ``log n`` (``log k``
    in closed form, ``omega_c`` among the samples' spreads from the reference up to the
    ``SPREAD_QUANTILES["high"]`` quantile)."""
    w = np.array([s.light_spread for s in samples], np.float64)
    need = needed_factors(plain, samples)
    ok = np.isfinite(w) & (w > 0) & np.isfinite(need) & (need > 0)
    if ok.sum() < 3:
        raise ValueError(f"too few calibration samples with a finite light spread and a scored element "
                         f"({int(ok.sum())})")
    w, log_need = w[ok], np.log(need[ok])
    out = {k: float(np.quantile(w, q)) for k, q in SPREAD_QUANTILES.items()}
    w_low = np.maximum(w, out["low"])
    best, best_res = out["high"], np.inf
    for knee in np.unique(np.concatenate([w[(w >= out["reference"]) & (w <= out["high"])], [out["high"]]])):
        x = np.log(np.minimum(w_low, knee))
        res = float(np.sum((log_need - x - np.mean(log_need - x)) ** 2))
        if res < best_res - 1e-12:
            best, best_res = float(knee), res
    out["high"] = best
    return out


def _observed_errors(samples: Iterable[Sample], spread: UncertaintyModel | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pooled ``(|error'| / (t scale) (N, 3, 3), q (N,), r (N,), p (N,))`` over unclipped object
    pixels, ``t`` the light-spread factor of ``spread`` (1 without)."""
    ratios, qs, rs, ps = [], [], [], []
    for s in samples:
        t = 1.0 if spread is None else spread.spread_factor(s.light_spread)
        rot, p = observed_frame_rotation(s.s_in)
        pred = np.asarray(s.pred, np.float64)
        pred_obs, truth = to_observed_frame(pred, rot), to_observed_frame(np.asarray(s.truth, np.float64), rot)
        scale, q = features(pred_obs, s.mask)
        r = misfit(pred, s.s_in, np.asarray(s.stokes, np.float64), scale)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & np.isfinite(r)  # (C, H, W)
        err = np.abs(pred_obs - truth) / (t * scale[:, None, None])
        ratios.append(np.moveaxis(err, (1, 2), (-2, -1))[use])
        qs.append(q[use])
        rs.append(r[use])
        ps.append(np.full(int(use.sum()), p))
    return np.concatenate(ratios), np.concatenate(qs), np.concatenate(rs), np.concatenate(ps)


def _quantile_bins(x: np.ndarray, n: int) -> np.ndarray:
    """Index ``0..n-1`` of each value's bin among ``n`` bins of equal count."""
    edges = np.quantile(x, np.linspace(0.0, 1.0, n + 1))
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)


def calibrate(samples: Sequence[Sample]) -> tuple[np.ndarray, dict, dict]:
    """Coefficients ``(3, 3, N_FEATURES)``, the light-spread factor's limits
    (:func:`spread_limits`, from a first fit without the factor) and a summary of the fit
    (module docstring)."""
    plain, _ = _fit_coefficients(samples, None)
    limits = spread_limits(samples, UncertaintyModel(plain))
    coef, info = _fit_coefficients(samples, UncertaintyModel(np.zeros((3, 3, N_FEATURES)), spread=limits))
    return coef, limits, info


def _fit_coefficients(samples: Sequence[Sample], spread: UncertaintyModel | None) -> tuple[np.ndarray, dict]:
    """The binned fit of :func:`calibrate` on the errors divided by ``spread``'s light factor."""
    ratio, q, r, p = _observed_errors(samples, spread)
    polarized = p >= P_MIN
    ratio, q, r = ratio[polarized], q[polarized], r[polarized]
    n_bins = Q_BINS * R_BINS
    if len(q) < 100 * n_bins:
        raise ValueError(f"too few calibration pixels ({len(q)}) for {n_bins} bins")
    which = np.empty(len(q), np.int64)
    q_bin = _quantile_bins(q, Q_BINS)
    for b in range(Q_BINS):
        sel = np.flatnonzero(q_bin == b)
        which[sel] = b * R_BINS + _quantile_bins(r[sel], R_BINS)
    bins = [np.flatnonzero(which == b) for b in range(n_bins)]
    bins = [i for i in bins if len(i)]
    x = feature_rows(np.array([np.median(q[i]) for i in bins]), np.array([np.median(r[i]) for i in bins]))
    weight = np.sqrt([float(len(i)) for i in bins])
    weighted = x * weight[:, None]
    full_design = feature_rows(q, r)
    coef = np.zeros((3, 3, N_FEATURES))
    for row in range(3):
        for k in range(3):
            y = np.array([np.quantile(ratio[i, row, k], COVERAGE) / 2.0 for i in bins])
            coef[row, k] = _nonnegative_lstsq(weighted, y * weight)
            # exact coverage on the calibration pixels
            sig = full_design @ coef[row, k]
            coef[row, k] *= np.quantile(ratio[:, row, k] / np.maximum(sig, 1e-12), COVERAGE) / 2.0
    return coef, {"pixels": int(len(q)), "q_bins": Q_BINS, "r_bins": R_BINS}


def _nonnegative_lstsq(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least squares with every coefficient >= 0, by trying each active set (a few unknowns)."""
    best, best_res = np.zeros(a.shape[1]), np.inf
    n = a.shape[1]
    for subset in range(1, 2**n):
        cols = [j for j in range(n) if subset >> j & 1]
        sol, *_ = np.linalg.lstsq(a[:, cols], b, rcond=None)
        if np.any(sol < 0):
            continue
        full = np.zeros(n)
        full[cols] = sol
        res = float(np.sum((a @ full - b) ** 2))
        if res < best_res:
            best, best_res = full, res
    return best


def _pooled(model: UncertaintyModel, samples: Iterable[Sample], mirror_term: bool = True
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pooled ``|error|``, ``sigma`` (with the mirror term where a sample has a disagreement,
    unless ``mirror_term`` is False) and disagreement (0 where none) ``(N, 3, 3)``, rig frame,
    over unclipped object pixels of ``samples`` with a finite sigma."""
    errs, sigs, dis = [], [], []
    for s in samples:
        sig = model.sigma(s.pred, s.s_in, s.mask, s.stokes, s.disagreement if mirror_term else None,
                          s.light_spread)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & np.all(np.isfinite(sig), axis=(1, 2))
        h = np.zeros_like(sig) if s.disagreement is None else s.disagreement
        for out, x in ((errs, np.abs(np.asarray(s.pred, np.float64) - s.truth)), (sigs, sig), (dis, h)):
            out.append(np.moveaxis(np.asarray(x, np.float64), (1, 2), (-2, -1))[use])
    return np.concatenate(errs), np.concatenate(sigs), np.concatenate(dis)


#: Quantiles of the misfit ``r`` recorded with a calibration (``calibration["misfit_quantiles"]``;
#: :data:`polrig.models.uncertainty.MISFIT_LIMIT_QUANTILE` is the one that flags a pixel).
MISFIT_QUANTILES = (0.5, 0.9, 0.99)


def misfit_values(samples: Iterable[Sample]) -> np.ndarray:
    """The misfit ``r`` of every unclipped object pixel and colour of ``samples`` ``(N,)``
    (finite values only; :func:`polrig.models.uncertainty.misfit`)."""
    return _observed_errors(samples)[2]


def misfit_quantiles(samples: Iterable[Sample]) -> dict[str, float]:
    """``{str(quantile): r}`` over :data:`MISFIT_QUANTILES`."""
    r = misfit_values(samples)
    return {str(q): float(np.quantile(r, q)) for q in MISFIT_QUANTILES}


def calibrate_mirror(model: UncertaintyModel, samples: Iterable[Sample]) -> float:
    """``k`` of ``sigma_avg^2 = sigma^2 + (k h)^2`` (module docstring): the smallest ``k`` for
    which ``COVERAGE`` of the :data:`MIRROR_TOP` elements with the largest ``h / sigma`` lie
    within ``2 sigma_avg``, on mirror-averaged ``samples`` (bisection; 0 if already covered)."""
    e, g, h = _pooled(model, samples, mirror_term=False)
    ratio = h / np.maximum(g, 1e-30)
    top = ratio >= np.quantile(ratio, 1.0 - MIRROR_TOP)
    e, g, h = e[top], g[top], h[top]
    covered = lambda k: float(np.mean(e <= 2.0 * np.sqrt(g**2 + (k * h) ** 2)))  # noqa: E731
    if covered(0.0) >= COVERAGE:
        return 0.0
    lo, hi = 0.0, 1.0
    while covered(hi) < COVERAGE:
        lo, hi = hi, 2.0 * hi
        if hi > 1e3:
            raise ValueError("the mirror disagreement does not explain the errors (k > 1000)")
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if covered(mid) >= COVERAGE else (mid, hi)
    return hi


def coverage(model: UncertaintyModel, samples: Iterable[Sample]) -> dict[str, float]:
    """In the rig's frame: fraction of elements within ``2 sigma`` (all, and per element), the
    RMS error over the RMS sigma, over unclipped object pixels of ``samples`` (with the mirror
    term for mirror-averaged samples)."""
    e_all, g_all, _ = _pooled(model, samples)
    inside_all = e_all <= 2.0 * g_all
    return {"within_2sigma": float(inside_all.mean()),
            "within_2sigma_per_element": np.round(inside_all.mean(0), 3).tolist(),
            "rms_error_over_rms_sigma": float(np.sqrt(np.mean(e_all**2) / np.mean(g_all.astype(np.float64) ** 2))),
            "pixels": int(len(e_all))}


def joint_whitened(model: UncertaintyModel, samples: Iterable[Sample]) -> np.ndarray:
    """The network's errors whitened in the hybrid's unobserved coordinates, ``w = Q^T (M_net -
    M_true)`` ``(N, 6)`` (:func:`polrig.solve.hybrid.unobserved_factor` of the per-element
    prior's precision, ``model``'s sigma with the seen state the sample's own), pooled over the
    unclipped object pixels (and colours) whose sigma is positive at all nine elements; samples
    whose state has no angle are left out (the joint prior does not apply there). Unit
    covariance where the per-element prior is right (:mod:`polrig.models.uncertainty`, "Joint
    prior")."""
    from polrig.solve.hybrid import observed_direction, plane_axis, unobserved_factor, unobserved_precision

    out = []
    for s in samples:
        if plane_axis(observed_direction(s.s_in)) is None:
            continue
        pred = np.asarray(s.pred, np.float64)
        sd = model.sigma(pred, s.s_in, s.mask, s.stokes, s.disagreement, light_spread=s.light_spread)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & (sd > 0).all(axis=(1, 2)) \
            & np.isfinite(sd).all(axis=(1, 2))
        sig = np.moveaxis(sd, (1, 2), (-2, -1))[use].astype(np.float64)  # (n, 3, 3)
        err = np.moveaxis(pred - np.asarray(s.truth, np.float64), (1, 2), (-2, -1))[use].reshape(-1, 9)
        q = unobserved_factor(unobserved_precision(sig, s.s_in), s.s_in)  # (n, 9, 6)
        w = np.einsum("nia,ni->na", q, err)
        out.append(w[np.isfinite(w).all(axis=1)])
    return np.concatenate(out) if out else np.zeros((0, 6))


def fit_joint(w: np.ndarray) -> dict:
    """The joint prior's correlation ``K`` ``(6, 6)`` of whitened errors ``w`` ``(N, 6)``
    (:func:`joint_whitened`): Spearman's rank correlation ``rho_s`` of each pair, taken to the
    Pearson correlation of a Gaussian pair, ``2 sin(pi rho_s / 6)`` (Kruskal 1958, J. Am. Stat.
    Assoc. 53, 814), robust to the errors' heavy tails that would dominate a moment estimate;
    then made positive definite (eigenvalues at least :data:`JOINT_MIN_EIGENVALUE`, unit
    diagonal again). Also records, per coordinate, the ``COVERAGE`` quantile of ``|w| / 2``,
    the scale the per-element sigma has in those coordinates (1 for a calibrated one; not
    applied: ``K`` keeps the per-element calibration's scale)."""
    w = np.asarray(w, np.float64)
    if w.ndim != 2 or w.shape[1] != 6 or len(w) < 10:
        raise ValueError(f"too few whitened errors to fit the joint prior ({w.shape})")
    ranks = np.argsort(np.argsort(w, axis=0), axis=0).astype(np.float64)
    rho_s = np.corrcoef(ranks, rowvar=False)
    k = 2.0 * np.sin(np.pi * rho_s / 6.0)
    np.fill_diagonal(k, 1.0)
    val, vec = np.linalg.eigh((k + k.T) / 2)
    k = (vec * np.maximum(val, JOINT_MIN_EIGENVALUE)) @ vec.T
    d = np.sqrt(np.diag(k))
    k = k / d[:, None] / d[None, :]
    k = (k + k.T) / 2
    scale = np.quantile(np.abs(w), COVERAGE, axis=0) / 2.0
    return {"correlation": np.round(k, 6).tolist(), "elements": int(len(w)),
            "coverage_scale": np.round(scale, 4).tolist()}


#: What the joint prior's entry describes (``joint_prior.model`` in the file).
JOINT_MODEL = ("prior precision on the seen state's unobserved directions Q K^-1 Q^T, Q the per-element prior's "
               "factor (polrig.solve.hybrid.unobserved_factor), K this correlation of the whitened errors, "
               "coordinates (row 0, v1), (row 0, v2), (row 1, v1), ...")
#: Least eigenvalue of the fitted joint correlation (:func:`fit_joint`).
JOINT_MIN_EIGENVALUE = 0.02


def dataset_samples(data_dir, model, limit: int | None = None, mirror_average: bool = False) -> list[Sample]:
    """Run ``model`` (:class:`polrig.models.runtime.SingleShotModel`; mirror-averaged with
    ``mirror_average``) on a ``polrig sim dataset`` folder -> samples with the truth (samples
    without a lit object pixel are skipped, as in :mod:`polrig.models.evaluate`). A sample's pixel is
    clipped where an analyzer value reached the sensor's saturation level
    (:attr:`polrig.sensor.noise.SensorModel.saturation_dn` of the set's sensor model, as
    :mod:`polrig.app.processing` flags it)."""
    from polrig.models.data import check_network_size, lit_samples, load_dataset
    from polrig.models.evaluate import network_inputs
    from polrig.sensor.noise import SensorModel
    from polrig.sensor.stokes import stokes_from_analyzers

    ds = load_dataset(data_dir, limit)
    check_network_size(ds, data_dir)
    try:
        sensor = SensorModel(**ds.manifest["noise"]["sensor_model"]) if "noise" in ds.manifest else SensorModel()
    except (TypeError, ValueError, KeyError) as exc:
        raise FormatError(f"{data_dir}/manifest.json: no usable noise.sensor_model ({exc})") from None
    lit = lit_samples(ds)
    if not lit:
        raise ConfigError(f"{data_dir}: no sample with a lit object pixel ({len(ds)} sample(s), nothing to "
                          f"calibrate or check on)")
    out = []
    for i in lit:
        mask = ds["mask"][i] > 0
        truth = ds["mueller"][i]
        res = model.run_rig_frame(*network_inputs(ds, i), mirror_average=mirror_average)
        dn = ds["analyzer"][i] * (ds["scale"][i] if "scale" in ds.arrays else 1.0)
        clipped = dn.max(axis=1) >= sensor.saturation_dn
        out.append(Sample(res["mueller"][0], truth, ds["s_in"][i], mask, clipped,
                          stokes_from_analyzers(ds["analyzer"][i]), light_spread(res["wi"][0], mask),
                          res["mueller_disagreement"][0] if mirror_average else None))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.uncertainty_fit", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="*", default=[], help="calibration sets (`polrig sim dataset` folders)")
    ap.add_argument("--check", nargs="*", default=[], help="sets to report the coverage on")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--write", action="store_true", help=f"write {FILE_NAME} into the weights folder")
    ap.add_argument("--joint", action="store_true",
                    help="fit only the joint prior (the correlation of the errors the hybrid solve's prior leaves "
                         f"unobserved) on --data, on top of the calibration in {FILE_NAME}, which is not refitted")
    args = ap.parse_args(argv)
    return run_main(ap.prog, lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    from polrig.atomic import atomic_write_text, temporary_sibling
    from polrig.models.data import read_manifest
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    wd = pathlib.Path(args.weights) if args.weights else WEIGHTS_DIR
    if not wd.is_dir():
        raise FileNotFoundError(f"weights folder {wd} not found")
    if args.joint and not args.data:
        raise ConfigError("--joint needs --data (the calibration sets)")
    for d in (*args.data, *args.check):  # every set, before the first is run
        read_manifest(d)
    if args.write:
        if not args.data and not args.check:
            raise ConfigError("--write needs --data (to calibrate) or --check (to record the coverage)")
        try:  # the weights folder takes the file: found out now, not after the calibration
            probe = temporary_sibling(wd / FILE_NAME)
            probe.open("x").close()
            probe.unlink()
        except OSError as exc:
            raise ConfigError(f"--write: cannot write in {wd} ({exc.strerror or exc})") from None
    net = SingleShotModel.load(wd)
    if args.joint:
        model, why = calibration_for_graph(wd, "single_shot.onnx")
        if model is None:
            raise ConfigError(f"{why}; {how_to_calibrate(wd)}")
        cal = [s for d in args.data for s in dataset_samples(d, net)]
        model.joint = {"version": JOINT_VERSION, **fit_joint(joint_whitened(model, cal)),
                       "sets": [pathlib.Path(d).name for d in args.data], "samples": len(cal),
                       "model": JOINT_MODEL}
        print(json.dumps(model.joint, indent=1))
        if args.write:
            data = json.loads((wd / FILE_NAME).read_text())  # everything else as it is (checks included)
            data[JOINT_KEY] = model.joint
            atomic_write_text(wd / FILE_NAME, json.dumps(data, indent=1) + "\n")
        return 0
    if args.data:
        cal = [s for d in args.data for s in dataset_samples(d, net)]
        coef, limits, info = calibrate(cal)
        model = UncertaintyModel(coef, graph_sha256(wd / "single_shot.onnx"),
                                 dict(info, sets=[pathlib.Path(d).name for d in args.data], samples=len(cal)),
                                 spread=limits)
        model.calibration["coverage"] = coverage(model, cal)
        model.calibration["misfit_quantiles"] = misfit_quantiles(cal)
        mirrored = [s for d in args.data for s in dataset_samples(d, net, mirror_average=True)]
        model.mirror_k = calibrate_mirror(model, mirrored)
        model.calibration["coverage_mirror_averaged"] = coverage(model, mirrored)
        print(json.dumps(model.to_json(), indent=1))
        if args.write:
            atomic_write_text(wd / FILE_NAME, json.dumps(model.to_json(), indent=1) + "\n")
    else:
        model, why = calibration_for_graph(wd, "single_shot.onnx")
        if model is None:
            raise ConfigError(f"{why}; {how_to_calibrate(wd)}")
    checks = {}
    for d in args.check:
        for suffix, mirror_average in (("", False), (" mirror-averaged", True)):
            checks[pathlib.Path(d).name + suffix] = c = coverage(model, dataset_samples(d, net, mirror_average=mirror_average))
            print(f"{pathlib.Path(d).name}{suffix}: within 2 sigma {c['within_2sigma']:.3f}, "
                  f"per element {c['within_2sigma_per_element']}, RMS error / RMS sigma "
                  f"{c['rms_error_over_rms_sigma']:.2f}, {c['pixels']} values")
    if args.write and checks:
        data = json.loads((wd / FILE_NAME).read_text())  # the calibration just written or checked above
        data["checks"] = checks
        atomic_write_text(wd / FILE_NAME, json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
