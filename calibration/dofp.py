"""DoFP analyzer calibration: per-pixel gain, orientation and diattenuation.

Model (Powell and Gruev, "Calibration methods for division-of-focal-plane polarimeters", Opt.
Express 21(18):21039, 2013; :mod:`polrig.sensor.analyzer`): sensor pixel ``p`` reads
``I_p = a_p . S_p + o_p`` with ``a_p = g_p / 2 [1, D_p cos 2 t_p, D_p sin 2 t_p]``. Under a
stage sweep the Stokes vector at pixel ``p`` is known up to a scalar radiance ``r_p``:
``S_p(theta_k) = r_p M_p S_in(theta_k)`` (``M_p`` the normalised Mueller matrix of the light
path, e.g. an ideal mirror in the rig frames, ``S_in`` the generator model). The offset comes
from a dark frame (light off); then ``v_p = r_p a_p`` is a per-pixel linear least-squares
problem with the ``K x 3`` design matrix ``X_p = [M_p S_in(theta_k)]_k``. From ``v_p``:
``t_p = atan2(v_2, v_1) / 2``, ``D_p = |v_12| / v_0``, ``g_p r_p = 2 v_0``. The radiance ``r_p``
is smooth over the image (a broad specular lobe), the gain is not: the gain is ``2 v_0``
divided by a smooth (low-order polynomial) fit per colour channel, i.e. relative to the mean
gain of that channel (flat-field normalisation).

Angles in degrees (``docs/conventions.md``); image arrays ``(H, W)`` over the sensor readout.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.calibration.errors import TooFewAngles
from polrig.sensor.analyzer import AnalyzerModel, resolve_layout


@dataclasses.dataclass(frozen=True)
class DofpFit:
    """Per-pixel result of :func:`fit_analyzer_rows` (``(H, W)`` arrays unless stated).

    ``rows`` ``(H, W, 3)`` = ``r_p a_p``; ``angle_deg``, ``modulation`` (= ``D_p`` times the
    generator DoLP assumed in ``S_in``), ``scale`` (= ``g_p r_p``), 1-sigma ``angle_std_deg``
    and ``modulation_std``, RMS fit residual ``residual_rms_dn``, ``valid`` mask.
    """

    rows: np.ndarray
    angle_deg: np.ndarray
    modulation: np.ndarray
    scale: np.ndarray
    angle_std_deg: np.ndarray
    modulation_std: np.ndarray
    residual_rms_dn: np.ndarray
    valid: np.ndarray


def fit_analyzer_rows(frames_dn: np.ndarray, states: np.ndarray,
                      min_signal_dn: float = 20.0) -> DofpFit:
    """Per-pixel least squares ``frames_dn[k, p] = v_p . states[k, :, p]``.

    ``frames_dn``: ``(K, H, W)`` dark-subtracted frames; ``states``: ``(K, 3, H, W)`` the
    (relative) Stokes vectors reaching each pixel, or ``(K, 3)`` for one state per frame for
    all pixels. Needs ``K >= 4``. Pixels with a mean signal below ``min_signal_dn`` or a
    singular system are invalid (their outputs are finite: angle from the nominal layout is not
    known here, so they get 0 and ``valid`` False).
    """
    y = np.asarray(frames_dn, dtype=np.float64)
    if y.ndim != 3:
        raise ValueError(f"frames must be (K, H, W), got shape {y.shape}")
    k, h, w = y.shape
    if k < 4:
        raise TooFewAngles(f"DoFP calibration needs 4+ stage angles, got {k}; add stage angles")
    s = np.asarray(states, dtype=np.float64)
    if s.shape == (k, 3):
        s = np.broadcast_to(s[:, :, None, None], (k, 3, h, w))
    if s.shape != (k, 3, h, w):
        raise ValueError(f"states must be (K, 3) or (K, 3, H, W) = {(k, 3, h, w)}, got {s.shape}")
    yf = np.where(np.isfinite(y), y, 0.0)
    sf = np.where(np.isfinite(s), s, 0.0)
    A = np.einsum("kihw,kjhw->hwij", sf, sf)  # (H, W, 3, 3)
    b = np.einsum("kihw,khw->hwi", sf, yf)
    det = np.linalg.det(A)
    tr = np.trace(A, axis1=-2, axis2=-1)
    ok = np.isfinite(det) & (np.abs(det) > 1e-12 * np.maximum(tr, 1e-300) ** 3)
    A_safe = np.where(ok[..., None, None], A, np.eye(3))
    Ainv = np.linalg.inv(A_safe)
    v = np.einsum("hwij,hwj->hwi", Ainv, np.where(ok[..., None], b, 0.0))
    pred = np.einsum("kihw,hwi->khw", sf, v)
    res = yf - pred
    dof = max(k - 3, 1)
    sigma2 = np.sum(res ** 2, axis=0) / dof
    cov = sigma2[..., None, None] * Ainv
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    amp = np.hypot(v1, v2)
    mean_sig = np.mean(yf, axis=0)
    valid = ok & (mean_sig >= min_signal_dn) & (v0 > 0) & np.isfinite(amp)
    v0s = np.where(valid, v0, 1.0)
    ang = np.rad2deg(0.5 * np.arctan2(v2, v1)) % 180.0
    # error propagation
    with np.errstate(divide="ignore", invalid="ignore"):
        amp_s = np.where(amp > 0, amp, 1.0)
        # d(angle)/d(v1, v2) = 0.5 (-v2, v1) / amp^2 (radians)
        g1, g2 = -0.5 * v2 / amp_s ** 2, 0.5 * v1 / amp_s ** 2
        var_ang = g1 ** 2 * cov[..., 1, 1] + g2 ** 2 * cov[..., 2, 2] + 2 * g1 * g2 * cov[..., 1, 2]
        mod = amp / v0s
        # modulation m = amp / v0
        h1, h2, h0 = v1 / (amp_s * v0s), v2 / (amp_s * v0s), -amp / v0s ** 2
        var_mod = (h0 ** 2 * cov[..., 0, 0] + h1 ** 2 * cov[..., 1, 1] + h2 ** 2 * cov[..., 2, 2]
                   + 2 * h0 * h1 * cov[..., 0, 1] + 2 * h0 * h2 * cov[..., 0, 2]
                   + 2 * h1 * h2 * cov[..., 1, 2])
    z = np.zeros((h, w))
    return DofpFit(
        rows=np.where(valid[..., None], v, 0.0),
        angle_deg=np.where(valid, ang, 0.0),
        modulation=np.where(valid, mod, 0.0),
        scale=np.where(valid, 2.0 * v0, 0.0),
        angle_std_deg=np.where(valid, np.rad2deg(np.sqrt(np.clip(var_ang, 0, None))), z),
        modulation_std=np.where(valid, np.sqrt(np.clip(var_mod, 0, None)), z),
        residual_rms_dn=np.where(valid, np.sqrt(np.mean(res ** 2, axis=0)), z),
        valid=valid)


def _poly_terms(u: np.ndarray, v: np.ndarray, degree: int) -> np.ndarray:
    return np.stack([u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)],
                    axis=-1)


def smooth_field(values: np.ndarray, mask: np.ndarray, degree: int = 4) -> np.ndarray:
    """Least-squares 2-D polynomial of total ``degree`` through ``values`` at ``mask``,
    evaluated everywhere (pixel coordinates scaled to [-1, 1])."""
    h, w = values.shape
    vv, uu = np.mgrid[0:h, 0:w]
    u = 2.0 * uu / max(w - 1, 1) - 1.0
    v = 2.0 * vv / max(h - 1, 1) - 1.0
    T = _poly_terms(u, v, degree)
    m = mask & np.isfinite(values)
    if m.sum() < T.shape[-1] * 4:
        raise ValueError("too few valid pixels for the flat-field fit; raise the light level")
    coef, *_ = np.linalg.lstsq(T[m], values[m], rcond=None)
    return T @ coef


def relative_gain(scale: np.ndarray, valid: np.ndarray, layout, degree: int = 4) -> np.ndarray:
    """Per-pixel gain ``g_p`` from ``scale = g_p r_p`` with a smooth radiance ``r_p``: the scale
    divided by a smooth fit per colour channel (``layout`` gives the colour of each pixel).
    Invalid pixels get gain 1."""
    lay = resolve_layout(layout)
    cmap = lay.colour_map(scale.shape)
    gain = np.ones(scale.shape)
    for c in range(lay.n_colours):
        m = valid & (cmap == c)
        # fit on a log scale so the multiplicative gain separates from the smooth radiance;
        # only the colour's own pixels enter, the field is evaluated everywhere
        logs = np.log(np.where(m, scale, 1.0))
        field = smooth_field(logs, m, degree)
        gain = np.where(cmap == c, np.where(valid, scale / np.exp(field), 1.0), gain)
    return gain


def analyzer_model_from_fit(fit: DofpFit, layout, generator_dolp: float, offset_dn: np.ndarray,
                            degree: int = 4) -> AnalyzerModel:
    """An :class:`AnalyzerModel` from a per-pixel fit: angles, diattenuation
    ``modulation / generator_dolp`` (clipped to [0, 1]), gains from :func:`relative_gain`,
    offsets ``offset_dn``. Invalid pixels keep the layout's nominal values."""
    lay = resolve_layout(layout)
    nominal = AnalyzerModel.ideal(lay, fit.valid.shape)
    ang = np.where(fit.valid, fit.angle_deg, nominal.angle_deg)
    # keep each angle near its nominal value (the fit's angle is modulo 180)
    ang = nominal.angle_deg + ((ang - nominal.angle_deg + 90.0) % 180.0 - 90.0)
    dia = np.where(fit.valid, np.clip(fit.modulation / generator_dolp, 0.0, 1.0), 1.0)
    gain = relative_gain(fit.scale, fit.valid, lay, degree)
    return AnalyzerModel(lay.name, gain, ang, dia, np.asarray(offset_dn, float))
