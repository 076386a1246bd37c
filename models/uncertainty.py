"""Calibrated per-element uncertainty of single-shot Mueller images.

One DoFP capture under one incident state ``s_in`` measures only ``M s_in``; the rest of the
matrix comes from the network's learned prior, so its error cannot be propagated from the
sensor noise as :mod:`polrig.solve.reference` does. It is instead *calibrated*: an error model with
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
* **The network's certainty of the light.** The whole image's sigma is multiplied by
  ``t = clip(omega, omega_lo, omega_hi) / omega_ref``, with ``omega`` the angular spread of the
  network's own per-pixel light direction ``wi`` over the object (:func:`light_spread`):
  ``omega = sqrt(2 (1 - Rbar))`` with ``Rbar`` the length of the mean of the unit vectors ``wi``,
  the spherical variance ``1 - Rbar`` of directional statistics (Mardia and Jupp, *Directional
  Statistics*, 2000, sec. 9.2.1) as an angle (about the RMS angle to the mean for small
  spreads). The rig's light is one lamp, whose direction varies over a 64x64 object by 2-6 deg;
  where the network's estimates of it scatter more, it is unsure of the light, which sets the
  unobserved columns through the surface's reflectance. No pixel feature separates the shapes
  the network gets wrong from those it gets right (on the calibration sets the held-out
  families' coverage was 4-6 points below the others' in every quantile bin of ``q``, ``r``,
  the measured DoLP, the shading, the distance to the silhouette, the local gradient of the
  prediction or of the measured polarization, or the predicted normal's angle to the view); nor
  do two per-image features measured later (the eight held-out sets of
  ``models/continuum/``, 48-64 samples each, single-shot: the per-image factor each image would
  need has a Spearman correlation of 0.5 with the mirror passes' mean disagreement over sigma,
  but the best factor of that form, fitted on the reported sets themselves, still leaves the
  sets 92.8-97.1 % apart; the angle between the network's mean light direction and the
  calibrated one is 6-9 deg on most sets, 19 on the conductors and 28 on the terrains, yet
  coverage is not monotone in it: 96.9 % below 5 deg, 91.3 % at 15-20 deg, 96.0 % at 30-45
  deg). The light's spread is per image: median 5.9 deg on the training families' calibration scenes,
  8.9 deg on the held-out families' (Spearman correlation with the factor an image's own sigma
  would need, 0.44 over the calibration images). ``omega_lo`` and ``omega_ref`` are the 1 % and
  50 % quantiles of the calibration images' spread; ``omega_hi`` is where the factor stops
  growing, fitted to what the calibration images need (:mod:`polrig.models.uncertainty_fit`):
  it lands at the median, 7.7 deg, so the factor narrows the sigma of images whose light the
  network is sure of and leaves the others' as fitted. (Growing on to the calibration's 99th
  percentile, 22.9 deg, brought the held-out families to 95 % but made the sigma 2-3 times too
  wide on the default rig's scenes, where the network's light scatters by 14-35 deg with
  errors no larger: 99.5-100 % within 2 sigma, ``models/MODEL_CARD.md``, "Uncertainty".)
* **Back to the rig's frame.** ``M_rc = sum_k M'_rk R_kc``; with independent errors per
  observed-frame column, ``sigma_rc^2 = sum_k R_kc^2 sigma'_rk^2``. Where the incident state is
  (nearly) unpolarized, ``p < P_MIN``, columns 1 and 2 are both unobserved and get the larger
  of their two sigmas.

* **Mirror averaging** (:mod:`polrig.models.mirror`): the average of the answers for the capture
  and its mirror image is scored by the same model, plus the two answers' disagreement
  ``h = |M_plain - M_mirror| / 2`` per element: ``sigma_avg^2 = sigma^2 + (k h)^2``. Where the
  two passes disagree the network is unsure (on the held-out sets coverage fell from 94-99 %
  to 71-83 % in the 1 % of elements that disagree most, measured against ``sigma``).

* **Joint prior** (optional, the file's ``joint_prior``, version :data:`JOINT_VERSION`): the
  sigma is per element, but the hybrid solve uses the network's estimate as a prior on the six
  directions its frame leaves unobserved, whose errors are correlated across the rows of ``M``.
  ``joint_prior.correlation`` is the 6x6 correlation ``K`` of the errors in the coordinates the
  per-element prior whitens (:mod:`polrig.solve.hybrid`, "Joint prior"), fitted on the
  calibration scenes by ``python -m polrig.models.uncertainty_fit --data ... --joint --write``
  (Spearman's rank correlation taken to Pearson's, robust to heavy tails). It leaves every
  element's sigma as it is. A file without it (every version-3 file before it) reads as
  before, with no joint prior; a refit of the per-element sigma writes the file without it
  (``K`` belongs to that sigma's whitening), so the joint prior is fitted again after it.

The coefficients are fitted by :mod:`polrig.models.uncertainty_fit` (``python -m polrig.models.uncertainty_fit``,
the fitting tool: it runs the graph on simulated sets, so it imports the evaluation code; this
module is the runtime part and imports nothing from evaluation or training).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib

import numpy as np

from polrig.solve.chunks import mask_box

#: Fraction of errors inside +-2 sigma for a right Gaussian sigma (erf(sqrt 2)).
COVERAGE = 0.9545
#: Degree of polarization of ``s_in`` below which its angle is undefined (unpolarized input).
P_MIN = 0.05
#: Scale floor, as a fraction of the image's 99th-percentile ``|m00|``.
SCALE_FLOOR = 0.01
#: Quantile of the calibration sets' misfit ``r`` beyond which a pixel is outside the
#: calibration (:meth:`UncertaintyModel.beyond_calibration`); a key of
#: ``calibration["misfit_quantiles"]``.
MISFIT_LIMIT_QUANTILE = "0.99"
#: Features of the error model (:func:`feature_rows`).
N_FEATURES = 4
FILE_NAME = "uncertainty.json"
FORMAT = "polrig-single-shot-uncertainty"
#: Version 2 added the misfit feature ``r``, version 3 the light-spread factor (``light_spread``:
#: its reference and limits); an older file counts as no calibration (one line says so, and how
#: to calibrate). The mirror term's ``mirror_disagreement_k`` is optional (absent: 0, no term).
VERSION = 3
#: Key of the optional joint prior in the file (module docstring, "Joint prior"), and the
#: version of its entry: a file without it (every version-3 file before) reads as before.
JOINT_KEY = "joint_prior"
JOINT_VERSION = 1
#: Quantiles of the calibration images' light spread that bound it below (``low``) and divide it
#: (``reference``), and up to which the knee ``high`` is searched (``light_spread`` in the file).
SPREAD_QUANTILES = {"low": 0.01, "reference": 0.5, "high": 0.99}


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


def _features_and_misfit(mueller: np.ndarray, s_in, object_mask: np.ndarray, stokes: np.ndarray):
    """``(box, R, p, scale, q, r)`` of a Mueller image ``mueller`` ``(C, 3, 3, H, W)`` under
    ``s_in`` with the measured Stokes images ``stokes`` ``(C, 3, H, W)``, within ``box``, the
    rows and columns that hold the object (:func:`polrig.solve.chunks.mask_box`: every value is
    per pixel, the scale's reference the object's own); None where there is no object."""
    shape = np.shape(mueller)
    if np.shape(stokes) != shape[:1] + (3,) + shape[-2:]:
        raise ValueError(f"stokes must be {shape[:1] + (3,) + shape[-2:]}, got {np.shape(stokes)}")
    mask = np.asarray(object_mask, bool)
    box = mask_box(mask)
    if box is None:
        return None
    m = np.asarray(np.asarray(mueller)[..., box[0], box[1]], np.float64)
    rot, p = observed_frame_rotation(s_in)
    scale, q = features(to_observed_frame(m, rot), mask[box])
    stokes = np.asarray(np.asarray(stokes)[..., box[0], box[1]], np.float64)
    return box, rot, p, scale, q, misfit(m, s_in, stokes, scale)


def light_spread(wi: np.ndarray, object_mask: np.ndarray) -> float:
    """Angular spread ``omega = sqrt(2 (1 - Rbar))`` (rad) of the unit light directions ``wi``
    ``(3, H, W)`` over ``object_mask`` ``(H, W)``, ``Rbar`` the length of their mean (module
    docstring); NaN for an empty mask. 0 where every direction is the same, ``sqrt 2`` where they
    cancel; about the RMS angle to the mean direction for small spreads."""
    w = np.asarray(wi, np.float64)
    m = np.asarray(object_mask, bool)
    if w.shape[:1] != (3,) or w.shape[1:] != m.shape:
        raise ValueError(f"wi must be (3, H, W) with the mask's (H, W) = {m.shape}, got {w.shape}")
    if not m.any():
        return float("nan")
    n = np.linalg.norm(w, axis=0)
    return spread_of_mean((w[:, m] / np.where(n[m] > 0, n[m], 1.0)).mean(axis=1))


def spread_of_mean(mean) -> float:
    """``sqrt(2 (1 - Rbar))`` (rad) of the mean ``(3,)`` of unit directions, ``Rbar`` its length
    (:func:`light_spread`; the device route's masked mean gives it without the images)."""
    rbar = float(np.linalg.norm(np.asarray(mean, np.float64).reshape(3)))
    return float(np.sqrt(2.0 * max(0.0, 1.0 - rbar)))


def feature_rows(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Feature rows ``[1, min(q,1), max(q - 1, 0), r]`` -> ``(..., N_FEATURES)``."""
    return np.stack([np.ones_like(q), np.minimum(q, 1.0), np.maximum(q - 1.0, 0.0), r], -1)


#: Fraction of an object's pixels (flagged in any colour) beyond the calibration's misfit range
#: above which a reconstruction warns that its sigma may be too small. Measured with
#: ``polrig infer --sigma`` on the default simulated rig at 256x256 and 512x512: plastic spheres
#: (``sphere``, ``rough_sphere``, ``diffuse_sphere``) 4-14 %, ``chrome_sphere`` 43-51 %,
#: ``gold_sphere`` 90-95 % (1 % per colour by construction on the calibration sets).
BEYOND_WARN_FRACTION = 0.25


@dataclasses.dataclass
class UncertaintyModel:
    """Coefficients ``(3, 3, N_FEATURES)``: observed-frame element ``(r, k)``, feature ``j`` (module
    docstring). ``graph_sha256``: the ONNX graph they were calibrated for."""

    coefficients: np.ndarray
    graph_sha256: str = ""
    calibration: dict = dataclasses.field(default_factory=dict)
    #: ``k`` of the mirror-disagreement term (module docstring); 0: none.
    mirror_k: float = 0.0
    #: ``{"low", "reference", "high"}`` (rad) of the light-spread factor (module docstring;
    #: :data:`SPREAD_QUANTILES`), or None: no factor (a model made in code, e.g. in a test).
    spread: dict | None = None
    #: The joint prior (module docstring, "Joint prior"): ``{"version", "correlation" (6, 6),
    #: ...}`` as :mod:`polrig.models.uncertainty_fit` fits it (``--joint``), or None: none fitted.
    joint: dict | None = None

    @property
    def joint_correlation(self) -> np.ndarray | None:
        """The joint prior's ``K`` ``(6, 6)`` (:func:`polrig.solve.hybrid.solve_hybrid`'s
        ``prior_correlation``), or None where the calibration has none."""
        return None if self.joint is None else np.asarray(self.joint["correlation"], np.float64)

    def spread_factor(self, light_spread: float | None) -> float:
        """``clip(omega, low, high) / reference`` (module docstring); 1 for a model without the
        factor. :class:`ValueError` when the model has it and ``light_spread`` is not a finite
        number >= 0."""
        if self.spread is None:
            return 1.0
        if light_spread is None or not np.isfinite(light_spread) or light_spread < 0:
            raise ValueError(f"this calibration needs the network's light spread (a finite angle >= 0, rad), "
                             f"got {light_spread!r}")
        return float(np.clip(light_spread, self.spread["low"], self.spread["high"]) / self.spread["reference"])

    def sigma(self, mueller: np.ndarray, s_in, object_mask: np.ndarray, stokes: np.ndarray,
              disagreement: np.ndarray | None = None, light_spread: float | None = None) -> np.ndarray:
        """Standard deviation ``(C, 3, 3, H, W)`` of each element of a single-shot Mueller
        image ``mueller`` ``(C, 3, 3, H, W)`` (any units: sigma has the same) reconstructed
        under ``s_in`` from a capture whose Stokes images are ``stokes`` ``(C, 3, H, W)`` (same
        units); ``object_mask`` ``(H, W)``: where the object is (outside it sigma is 0, as the
        Mueller image). Non-finite where ``stokes`` is. ``disagreement`` (like ``mueller``): for
        a mirror-averaged image, ``|M_plain - M_mirror| / 2`` (module docstring).
        ``light_spread``: :func:`light_spread` of the network's light directions over the
        object (needed where the calibration has the factor, :meth:`spread_factor`). Computed
        within the box that holds the object (every value is per pixel, the scale's reference
        the object's own), zero around it."""
        t = self.spread_factor(light_spread)
        mask = np.asarray(object_mask, bool)
        shape = np.shape(mueller)
        if disagreement is not None and np.shape(disagreement) != shape:
            raise ValueError(f"disagreement must be {shape}, got {np.shape(disagreement)}")
        out = np.zeros(shape, np.float32)
        found = _features_and_misfit(mueller, s_in, mask, stokes)
        if found is None:
            return out
        box, rot, p, scale, q, r = found
        sig_obs = (t * scale)[:, None, None] * np.einsum("chwj,rkj->crkhw", feature_rows(q, r), self.coefficients)
        if p < P_MIN:  # no observed direction: columns 1 and 2 are alike unobserved
            sig_obs[:, :, 1:] = np.max(sig_obs[:, :, 1:], axis=2, keepdims=True)
        var = np.einsum("crkhw,kj->crjhw", sig_obs**2, rot**2)  # sum_k R_kc^2 sigma'_rk^2
        if disagreement is not None:
            var = var + (self.mirror_k * np.asarray(np.asarray(disagreement)[..., box[0], box[1]], np.float64)) ** 2
        out[..., box[0], box[1]] = np.where(mask[box], np.sqrt(var), 0.0)
        return out

    @property
    def misfit_limit(self) -> float | None:
        """The :data:`MISFIT_LIMIT_QUANTILE` quantile of the misfit ``r`` over the calibration
        sets' pixels (``calibration["misfit_quantiles"]``, recorded by
        :mod:`polrig.models.uncertainty_fit`), or None where the calibration does not record it."""
        q = self.calibration.get("misfit_quantiles")
        try:
            value = float(q[MISFIT_LIMIT_QUANTILE])
        except (TypeError, KeyError, ValueError):
            return None
        return value if np.isfinite(value) and value > 0 else None

    @staticmethod
    def beyond_fraction(beyond: np.ndarray, object_mask: np.ndarray) -> float:
        """Fraction of the object's pixels flagged by :meth:`beyond_calibration` in any
        colour (0 for an empty object)."""
        obj = np.asarray(object_mask, bool)
        n = int(obj.sum())
        return float(np.count_nonzero(np.any(beyond, axis=0) & obj)) / n if n else 0.0

    def beyond_calibration(self, mueller: np.ndarray, s_in, object_mask: np.ndarray,
                           stokes: np.ndarray) -> np.ndarray | None:
        """``(C, H, W)`` bool: object pixels whose misfit ``r`` exceeds :attr:`misfit_limit`
        (arguments as :meth:`sigma`), None where the calibration records no limit. Such a
        capture is outside what the sigma was calibrated on: on conductors, which the
        networks never saw, 41 % of the pixels are, against 1 % by construction on the
        calibration sets (``models/MODEL_CARD.md``, "Mismatched materials and
        interreflections"), and the sigma of some elements covers 86 % instead of 95 %."""
        limit = self.misfit_limit
        if limit is None:
            return None
        mask = np.asarray(object_mask, bool)
        beyond = np.zeros(np.shape(mueller)[:1] + np.shape(mueller)[-2:], bool)
        found = _features_and_misfit(mueller, s_in, mask, stokes)
        if found is not None:
            box, r = found[0], found[-1]
            beyond[..., box[0], box[1]] = mask[box][None] & ~(r <= limit)  # non-finite r counts as beyond
        return beyond

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "graph_sha256": self.graph_sha256,
                "model": "sigma'_rk = scale * clip(omega, low, high) / reference * (a + b min(q,1) + c max(q-1,0) "
                         "+ d r) in the observed frame, omega the network's light spread (models/uncertainty.py)",
                "coverage_target": COVERAGE, "scale_floor": SCALE_FLOOR, "p_min": P_MIN,
                "coefficients": np.round(self.coefficients, 6).tolist(),
                "mirror_disagreement_k": round(float(self.mirror_k), 6), "light_spread": self.spread,
                "calibration": self.calibration} | ({} if self.joint is None else {JOINT_KEY: self.joint})

    @classmethod
    def from_json(cls, data: dict) -> "UncertaintyModel":
        if data.get("format") != FORMAT:
            raise ValueError(f"not a {FORMAT} file (format {data.get('format')!r})")
        coef = np.asarray(data["coefficients"], np.float64)
        if coef.shape != (3, 3, N_FEATURES) or not np.all(np.isfinite(coef)) or np.any(coef < 0):
            raise ValueError(f"coefficients must be 3x3x{N_FEATURES} finite numbers >= 0, got shape {coef.shape} "
                             "(an older calibration: run python -m polrig.models.uncertainty_fit again)")
        k = float(data.get("mirror_disagreement_k", 0.0))
        if not (np.isfinite(k) and k >= 0):
            raise ValueError(f"mirror_disagreement_k must be a finite number >= 0, got {k}")
        spread = data.get("light_spread")
        try:
            spread = {key: float(spread[key]) for key in SPREAD_QUANTILES}
        except (TypeError, KeyError, ValueError):
            raise ValueError(f"light_spread must hold {', '.join(SPREAD_QUANTILES)} (an older calibration: run "
                             "python -m polrig.models.uncertainty_fit again)") from None
        if not (np.all(np.isfinite(list(spread.values())))
                and 0 < spread["low"] <= spread["reference"] <= spread["high"]):
            raise ValueError(f"light_spread must be finite with 0 < low <= reference <= high, got {spread}")
        return cls(coef, str(data.get("graph_sha256", "")), dict(data.get("calibration", {})), k, spread,
                   _read_joint(data.get(JOINT_KEY)))


def _read_joint(joint) -> dict | None:
    """The file's :data:`JOINT_KEY` entry checked (None where absent: a calibration without the
    joint prior, as every file before it); :class:`ValueError` for one this polrig cannot use."""
    if joint is None:
        return None
    from polrig.errors import ConfigError
    from polrig.solve.hybrid import check_correlation

    if not isinstance(joint, dict) or joint.get("version") != JOINT_VERSION:
        raise ValueError(f"{JOINT_KEY} must be a version-{JOINT_VERSION} object, got "
                         f"{joint.get('version') if isinstance(joint, dict) else type(joint).__name__!r}")
    try:
        check_correlation(joint.get("correlation"))
    except ConfigError as exc:
        raise ValueError(f"{JOINT_KEY}: {exc}") from None
    return dict(joint)


def graph_sha256(path: str | pathlib.Path) -> str:
    return hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def calibration_for_graph(weights_dir: str | pathlib.Path, graph: str = "single_shot.onnx"
                          ) -> tuple[UncertaintyModel | None, str]:
    """``(model, "")`` when ``weights_dir`` holds a calibration of ``graph`` (same SHA-256, the
    current :data:`VERSION`), else ``(None, why not)``: no file, a file that cannot be read, a
    calibration of an older version, or one that belongs to another graph (a retrained graph has
    no calibrated uncertainty until ``python -m polrig.models.uncertainty_fit`` runs)."""
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
    return (f"calibrate it with: python -m polrig.models.uncertainty_fit --weights {weights_dir} --data DIR [DIR ...] "
            f"--write (DIR: polrig sim dataset --holdout sets)")
