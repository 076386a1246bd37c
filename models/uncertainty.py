"""Calibrated per-element uncertainty of single-shot Mueller images.

One DoFP capture under one incident state ``s_in`` measures only ``M s_in``; the rest of the
matrix comes from the network's learned prior, so its error cannot be propagated from the
sensor noise as :mod:`polrig.reference` does. It is instead *calibrated*: an error model with
a few coefficients is fitted to the shipped network's errors against the simulator's truth on a
calibration set, and its coverage is checked on other held-out sets (``models/MODEL_CARD.md``,
"Uncertainty").

The error model (numpy only: it runs at inference without torch):

* **Observed frame.** The incident Stokes basis is turned about the illumination axis by the
  state's own angle ``theta`` (``s_in = [1, p cos 2 theta, p sin 2 theta]``):
  ``M = M' R(theta)`` with ``R = [[1,0,0],[0,c,s],[0,-s,c]]``, ``c, s = cos 2 theta, sin 2 theta``
  (the rotation of ``docs/conventions.md``), so ``R s_in = [1, p, 0]``. Column 0 of ``M'``
  (its response to unpolarized light, the same as ``M``'s) and column 1 (to light polarized
  along the observed state) are tied by the measurement ``M' [1, p, 0]``; column 2 (light
  polarized at 45 deg to it) is not observed at all. Errors differ by column in this frame,
  not in the rig's.
* **Scale, polarization strength and misfit.** In the observed frame ``sigma'_rk = scale *
  (a_rk + b_rk min(q, 1) + c_rk max(q - 1, 0) + d_rk r)`` with ``scale = max(|m00|, floor *
  m_ref)`` (``m_ref`` the 99th percentile of ``|m00|`` over the object, so dark pixels keep a
  floor), ``q`` the predicted matrix's polarization strength ``||M'[1:, 1:]||_F / |m00|``
  (about 0 where diffuse reflection dominates, up to 1 for a specular pixel: errors of the
  lower-right block grow about tenfold from diffuse to specular pixels) and ``r`` the misfit of
  the one thing measured, ``||M s_in - S|| / (|s_in| scale)`` with ``S`` the measured Stokes
  vector: where the prediction does not reproduce its own observation (the network is unsure of
  the shape, or the pixel is noisy), the rest of the matrix is less certain too (on the held-out
  sets the errors grow about fivefold from the lowest to the highest misfits).
* **Back to the rig's frame.** ``M_rc = sum_k M'_rk R_kc``; with independent errors per
  observed-frame column, ``sigma_rc^2 = sum_k R_kc^2 sigma'_rk^2``. Where the incident state is
  (nearly) unpolarized, ``p < P_MIN``, columns 1 and 2 are both unobserved and get the larger
  of their two sigmas.

* **Mirror averaging** (:mod:`models.mirror`): the average of the answers for the capture
  and its mirror image is scored by the same model, plus the two answers' disagreement
  ``h = |M_plain - M_mirror| / 2`` per element: ``sigma_avg^2 = sigma^2 + (k h)^2``. Where the
  two passes disagree the network is unsure (on the held-out sets coverage fell from 94-99 %
  to 71-83 % in the 1 % of elements that disagree most, measured against ``sigma``).

Calibration (:func:`calibrate`): the coefficients are fitted to the ``COVERAGE`` quantile of
``|error'| / scale`` in bins of ``q`` and, within each, of ``r`` (weighted least squares over
the bins, coefficients kept >= 0), then each element's sigma is rescaled so that exactly
``COVERAGE`` of the calibration errors lie within ``2 sigma``, the fraction a right Gaussian
sigma covers; ``k`` (:func:`calibrate_mirror`) so that the tenth of the mirror-averaged
calibration elements whose disagreement is largest against ``sigma`` is covered as well.
Pixels with a clipped
analyzer sample are left out: a clipped highlight's magnitude is unknown, and
:mod:`polrig.processing` reports infinite sigma there.

``python -m models.uncertainty --data DIR [DIR ...] --write`` runs the shipped graph on
``polrig sim dataset`` folders, calibrates and writes ``models/weights/uncertainty.json`` (with
the SHA-256 of the graph it belongs to); ``--check DIR ...`` prints the coverage on other sets.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import pathlib
import sys
from collections.abc import Iterable, Sequence

import numpy as np

from polrig.errors import ConfigError, FormatError

#: Fraction of errors inside +-2 sigma for a right Gaussian sigma (erf(sqrt 2)).
COVERAGE = 0.9545
#: Degree of polarization of ``s_in`` below which its angle is undefined (unpolarized input).
P_MIN = 0.05
#: Scale floor, as a fraction of the image's 99th-percentile ``|m00|``.
SCALE_FLOOR = 0.01
#: Bins of :func:`calibrate`: quantiles of the polarization strength ``q``, then within each
#: quantiles of the misfit ``r``.
Q_BINS = 12
R_BINS = 6
#: Features of the error model (:func:`_design`).
N_FEATURES = 4
FILE_NAME = "uncertainty.json"
FORMAT = "polrig-single-shot-uncertainty"
#: Version 2 added the misfit feature ``r``; a version-1 file counts as no calibration. The
#: mirror term's ``mirror_disagreement_k`` is optional (absent: 0, no term).
VERSION = 2
#: Fraction of elements, those whose mirror disagreement is largest against ``sigma``, whose
#: coverage :func:`calibrate_mirror` sets.
MIRROR_TOP = 0.1


def observed_frame_rotation(s_in) -> tuple[np.ndarray, float]:
    """``(R, p)``: the Stokes rotation ``R(theta)`` (3, 3) that takes the normalised incident
    state ``s_in = [1, p cos 2 theta, p sin 2 theta]`` to ``[1, p, 0]``, and its degree of
    polarization ``p`` (``R`` is the identity where ``p < P_MIN``)."""
    s = np.asarray(s_in, np.float64).reshape(3)
    s = s / s[0] if s[0] > 0 else s
    p = float(np.hypot(s[1], s[2]))
    if p < P_MIN:
        return np.eye(3), p
    c, sn = s[1] / p, s[2] / p
    return np.array([[1.0, 0.0, 0.0], [0.0, c, sn], [0.0, -sn, c]]), p


def to_observed_frame(mueller: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``M' = M R^T`` for a Mueller image ``(C, 3, 3, H, W)`` (or blocks ``(..., 3, 3, N)``)."""
    return np.einsum("...rkn,jk->...rjn", mueller.reshape(*mueller.shape[:-2], -1), rotation).reshape(mueller.shape)


def features(m_obs: np.ndarray, object_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(scale, q)`` ``(C, H, W)`` of an observed-frame Mueller image ``(C, 3, 3, H, W)``:
    ``scale = max(|m00|, SCALE_FLOOR m_ref)``, ``q = ||M'[1:, 1:]|| / scale`` (module docstring)."""
    m00 = np.abs(m_obs[:, 0, 0])
    inside = m00[:, np.asarray(object_mask, bool)]
    ref = float(np.percentile(inside, 99)) if inside.size else 0.0
    scale = np.maximum(m00, max(SCALE_FLOOR * ref, np.finfo(np.float32).tiny))
    q = np.sqrt(np.sum(m_obs[:, 1:, 1:] ** 2, axis=(1, 2))) / scale
    return scale, q


def misfit(mueller: np.ndarray, s_in, stokes: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``r = ||M s_in - S|| / (|s_in| scale)`` ``(C, H, W)`` of a Mueller image ``(C, 3, 3, H, W)``
    and the measured Stokes images ``S`` ``(C, 3, H, W)`` (same units); non-finite where ``S``
    is."""
    s = np.asarray(s_in, np.float64).reshape(3)
    rendered = np.einsum("crkhw,k->crhw", mueller, s)
    return np.linalg.norm(rendered - stokes, axis=1) / (np.linalg.norm(s) * scale)


def _design(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Feature rows ``[1, min(q,1), max(q - 1, 0), r]`` -> ``(..., N_FEATURES)``."""
    return np.stack([np.ones_like(q), np.minimum(q, 1.0), np.maximum(q - 1.0, 0.0), r], -1)


@dataclasses.dataclass
class UncertaintyModel:
    """Coefficients ``(3, 3, N_FEATURES)``: observed-frame element ``(r, k)``, feature ``j`` (module
    docstring). ``graph_sha256``: the ONNX graph they were calibrated for."""

    coefficients: np.ndarray
    graph_sha256: str = ""
    calibration: dict = dataclasses.field(default_factory=dict)
    #: ``k`` of the mirror-disagreement term (module docstring); 0: none.
    mirror_k: float = 0.0

    def sigma(self, mueller: np.ndarray, s_in, object_mask: np.ndarray, stokes: np.ndarray,
              disagreement: np.ndarray | None = None) -> np.ndarray:
        """Standard deviation ``(C, 3, 3, H, W)`` of each element of a single-shot Mueller
        image ``mueller`` ``(C, 3, 3, H, W)`` (any units: sigma has the same) reconstructed
        under ``s_in`` from a capture whose Stokes images are ``stokes`` ``(C, 3, H, W)`` (same
        units); ``object_mask`` ``(H, W)``: where the object is (outside it sigma is 0, as the
        Mueller image). Non-finite where ``stokes`` is. ``disagreement`` (like ``mueller``): for
        a mirror-averaged image, ``|M_plain - M_mirror| / 2`` (module docstring)."""
        m = np.asarray(mueller, np.float64)
        if np.shape(stokes) != m.shape[:1] + (3,) + m.shape[-2:]:
            raise ValueError(f"stokes must be {m.shape[:1] + (3,) + m.shape[-2:]}, got {np.shape(stokes)}")
        rot, p = observed_frame_rotation(s_in)
        m_obs = to_observed_frame(m, rot)
        scale, q = features(m_obs, object_mask)
        r = misfit(m, s_in, np.asarray(stokes, np.float64), scale)
        sig_obs = scale[:, None, None] * np.einsum("chwj,rkj->crkhw", _design(q, r), self.coefficients)
        if p < P_MIN:  # no observed direction: columns 1 and 2 are alike unobserved
            sig_obs[:, :, 1:] = np.max(sig_obs[:, :, 1:], axis=2, keepdims=True)
        var = np.einsum("crkhw,kj->crjhw", sig_obs**2, rot**2)  # sum_k R_kc^2 sigma'_rk^2
        if disagreement is not None:
            if np.shape(disagreement) != m.shape:
                raise ValueError(f"disagreement must be {m.shape}, got {np.shape(disagreement)}")
            var = var + (self.mirror_k * np.asarray(disagreement, np.float64)) ** 2
        return np.where(np.asarray(object_mask, bool), np.sqrt(var), 0.0).astype(np.float32)

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "graph_sha256": self.graph_sha256,
                "model": "sigma'_rk = scale * (a + b min(q,1) + c max(q-1,0) + d r) in the observed frame "
                         "(models/uncertainty.py)",
                "coverage_target": COVERAGE, "scale_floor": SCALE_FLOOR, "p_min": P_MIN,
                "coefficients": np.round(self.coefficients, 6).tolist(),
                "mirror_disagreement_k": round(float(self.mirror_k), 6), "calibration": self.calibration}

    @classmethod
    def from_json(cls, data: dict) -> "UncertaintyModel":
        if data.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file (format {data.get('format')!r})")
        coef = np.asarray(data["coefficients"], np.float64)
        if coef.shape != (3, 3, N_FEATURES) or not np.all(np.isfinite(coef)) or np.any(coef < 0):
            raise ValueError(f"coefficients must be 3x3x{N_FEATURES} finite numbers >= 0, got shape {coef.shape} "
                             "(an older calibration: run python -m models.uncertainty again)")
        k = float(data.get("mirror_disagreement_k", 0.0))
        if not (np.isfinite(k) and k >= 0):
            raise ValueError(f"mirror_disagreement_k must be a finite number >= 0, got {k}")
        return cls(coef, str(data.get("graph_sha256", "")), dict(data.get("calibration", {})), k)


def graph_sha256(path: str | pathlib.Path) -> str:
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def calibration_for_graph(weights_dir: str | pathlib.Path, graph: str = "single_shot.onnx"
                          ) -> tuple[UncertaintyModel | None, str]:
    """``(model, "")`` when ``weights_dir`` holds a calibration of ``graph`` (same SHA-256, the
    current :data:`VERSION`), else ``(None, why not)``: no file, a file that cannot be read, a
    calibration of an older version, or one that belongs to another graph (a retrained graph has
    no calibrated uncertainty until ``python -m models.uncertainty`` runs)."""
    wd = pathlib.Path(weights_dir)
    path = wd / FILE_NAME
    if not path.is_file():
        return None, f"no {FILE_NAME} in {wd} (this graph has no calibrated uncertainty)"
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict):
            raise ValueError(f"a JSON object expected, got {type(data).__name__}")
        if data.get("format") == FORMAT and data.get("version") != VERSION:
            return None, (f"{path} is a version-{data.get('version')} calibration (this polrig reads version "
                          f"{VERSION})")
        model = UncertaintyModel.from_json(data)
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        return None, f"{path} is not a readable uncertainty calibration ({exc})"
    try:
        mine = graph_sha256(wd / graph)
    except OSError as exc:
        return None, f"cannot read {wd / graph} ({exc.strerror or exc})"
    if model.graph_sha256 != mine:
        return None, (f"{path} belongs to another graph (calibrated for SHA-256 {model.graph_sha256[:12] or 'none'}..., "
                      f"{graph} here is {mine[:12]}...)")
    return model, ""


def load_for_graph(weights_dir: pathlib.Path, graph: str) -> UncertaintyModel | None:
    """The calibration in ``weights_dir`` if it belongs to ``graph`` (same SHA-256) and is of the
    current :data:`VERSION`, else None (:func:`calibration_for_graph` says why)."""
    return calibration_for_graph(weights_dir, graph)[0]


def how_to_calibrate(weights_dir) -> str:
    return (f"calibrate it with: python -m models.uncertainty --weights {weights_dir} --data DIR [DIR ...] "
            f"--write (DIR: polrig sim dataset --holdout sets)")


# ----------------------------------------------------------------------------- calibration

@dataclasses.dataclass
class Sample:
    """One prediction with its truth: ``pred``/``truth`` ``(C, 3, 3, H, W)``, ``s_in`` (3,),
    ``mask`` (H, W) object pixels, ``clipped`` (C, H, W) pixels with a clipped sample,
    ``stokes`` ``(C, 3, H, W)`` the measured Stokes images the prediction was made from;
    ``disagreement`` (like ``pred``) for a mirror-averaged prediction, else None."""

    pred: np.ndarray
    truth: np.ndarray
    s_in: np.ndarray
    mask: np.ndarray
    clipped: np.ndarray
    stokes: np.ndarray
    disagreement: np.ndarray | None = None


def _observed_errors(samples: Iterable[Sample]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pooled ``(|error'| / scale (N, 3, 3), q (N,), r (N,), p (N,))`` over unclipped object pixels."""
    ratios, qs, rs, ps = [], [], [], []
    for s in samples:
        rot, p = observed_frame_rotation(s.s_in)
        pred = np.asarray(s.pred, np.float64)
        pred_obs, truth = to_observed_frame(pred, rot), to_observed_frame(np.asarray(s.truth, np.float64), rot)
        scale, q = features(pred_obs, s.mask)
        r = misfit(pred, s.s_in, np.asarray(s.stokes, np.float64), scale)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & np.isfinite(r)  # (C, H, W)
        err = np.abs(pred_obs - truth) / scale[:, None, None]
        ratios.append(np.moveaxis(err, (1, 2), (-2, -1))[use])
        qs.append(q[use])
        rs.append(r[use])
        ps.append(np.full(int(use.sum()), p))
    return np.concatenate(ratios), np.concatenate(qs), np.concatenate(rs), np.concatenate(ps)


def _quantile_bins(x: np.ndarray, n: int) -> np.ndarray:
    """Index ``0..n-1`` of each value's bin among ``n`` bins of equal count."""
    edges = np.quantile(x, np.linspace(0.0, 1.0, n + 1))
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)


def calibrate(samples: Iterable[Sample]) -> tuple[np.ndarray, dict]:
    """Coefficients ``(3, 3, N_FEATURES)`` (module docstring) and a summary of the fit."""
    ratio, q, r, p = _observed_errors(samples)
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
    x = _design(np.array([np.median(q[i]) for i in bins]), np.array([np.median(r[i]) for i in bins]))
    weight = np.sqrt([float(len(i)) for i in bins])
    design = x * weight[:, None]
    full_design = _design(q, r)
    coef = np.zeros((3, 3, N_FEATURES))
    for row in range(3):
        for k in range(3):
            y = np.array([np.quantile(ratio[i, row, k], COVERAGE) / 2.0 for i in bins])
            coef[row, k] = _nonnegative_lstsq(design, y * weight)
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
        sig = model.sigma(s.pred, s.s_in, s.mask, s.stokes, s.disagreement if mirror_term else None)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & np.all(np.isfinite(sig), axis=(1, 2))
        h = np.zeros_like(sig) if s.disagreement is None else s.disagreement
        for out, x in ((errs, np.abs(np.asarray(s.pred, np.float64) - s.truth)), (sigs, sig), (dis, h)):
            out.append(np.moveaxis(np.asarray(x, np.float64), (1, 2), (-2, -1))[use])
    return np.concatenate(errs), np.concatenate(sigs), np.concatenate(dis)


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


def dataset_samples(data_dir, model, limit: int | None = None, mirror_average: bool = False) -> list[Sample]:
    """Run ``model`` (:class:`models.runtime.SingleShotModel`; mirror-averaged with
    ``mirror_average``) on a ``polrig sim dataset`` folder -> samples with the truth (samples
    without a lit object pixel are skipped, as in :mod:`models.evaluate`). A sample's pixel is
    clipped where an analyzer value reached the sensor's saturation level
    (:attr:`polrig.noise.SensorModel.saturation_dn` of the set's sensor model, as
    :mod:`polrig.processing` flags it)."""
    from models.data import load_dataset
    from models.evaluate import _network_inputs
    from polrig.noise import SensorModel
    from polrig.stokes import stokes_from_analyzers

    from models.data import check_network_size, lit_samples

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
        res = model.run_rig_frame(*_network_inputs(ds, i), mirror_average=mirror_average)
        dn = ds["analyzer"][i] * (ds["scale"][i] if "scale" in ds.arrays else 1.0)
        clipped = dn.max(axis=1) >= sensor.saturation_dn
        out.append(Sample(res["mueller"][0], truth, ds["s_in"][i], mask, clipped,
                          stokes_from_analyzers(ds["analyzer"][i]),
                          res["mueller_disagreement"][0] if mirror_average else None))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m models.uncertainty", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", nargs="*", default=[], help="calibration sets (`polrig sim dataset` folders)")
    ap.add_argument("--check", nargs="*", default=[], help="sets to report the coverage on")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--write", action="store_true", help=f"write {FILE_NAME} into the weights folder")
    args = ap.parse_args(argv)
    return run_main(ap.prog, lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    from models.data import read_manifest
    from models.runtime import WEIGHTS_DIR, SingleShotModel
    from polrig.rawio import atomic_write_text, temporary_sibling

    wd = pathlib.Path(args.weights) if args.weights else WEIGHTS_DIR
    if not wd.is_dir():
        raise FileNotFoundError(f"weights folder {wd} not found")
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
    if args.data:
        cal = [s for d in args.data for s in dataset_samples(d, net)]
        coef, info = calibrate(cal)
        model = UncertaintyModel(coef, graph_sha256(wd / "single_shot.onnx"),
                                 dict(info, sets=[pathlib.Path(d).name for d in args.data], samples=len(cal)))
        model.calibration["coverage"] = coverage(model, cal)
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
