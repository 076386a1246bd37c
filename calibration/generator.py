"""The polarization state generator model: the light behind a linear polarizer on the stage.

The polarizer's transmission axis is at ``stage_angle_deg + zero_offset_deg`` from the incident
frame's ``x`` axis (the stage zero axis, ``docs/conventions.md``), its extinction ratio is
``extinction_ratio`` (major / minor intensity transmittance). The normalised incident Stokes
vector is that of unit unpolarized light after the polarizer,
:func:`polrig.optics.mueller.polarizer_stokes` with ``intensity=1`` (``S0 = (1 + 1/ER) / 2``;
``docs/conventions.md``, "Radiometric units").

The fit (:func:`fit_generator_from_angles`) takes, for many stage angles, the polarization
angle and degree that a calibrated analyzer measured for light whose basis change from the
incident frame to the camera frame is known (a mirror with a known Mueller matrix, or a direct
view), and solves for the offset and the DoLP ``d = (ER - 1) / (ER + 1)`` of the generator.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.calibration.errors import TooFewAngles
from polrig.optics.mueller import polarizer_stokes


def dolp_from_extinction_ratio(extinction_ratio) -> np.ndarray:
    """DoLP ``(ER - 1) / (ER + 1)`` of unpolarized light after a polarizer of ratio ``ER``."""
    er = np.asarray(extinction_ratio, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.where(np.isinf(er), 1.0, (er - 1.0) / (er + 1.0))


def extinction_ratio_from_dolp(dolp) -> np.ndarray:
    """Inverse of :func:`dolp_from_extinction_ratio` (``inf`` for DoLP >= 1)."""
    d = np.asarray(dolp, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d >= 1.0, np.inf, (1.0 + d) / (1.0 - d))


@dataclasses.dataclass(frozen=True)
class GeneratorModel:
    """Fitted generator: zero offset (degrees) and extinction ratio with 1-sigma uncertainties.

    ``incident_stokes(stage_angle_deg)`` gives the normalised incident linear Stokes vector
    ``(..., 3)`` in the incident frame (``docs/conventions.md``).
    """

    zero_offset_deg: float
    extinction_ratio: float
    zero_offset_std_deg: float = 0.0
    extinction_ratio_std: float = 0.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.zero_offset_deg):
            raise ValueError("generator zero offset must be finite")
        if not (self.extinction_ratio > 1.0):
            raise ValueError(f"extinction ratio must be > 1, got {self.extinction_ratio}")

    @classmethod
    def ideal(cls) -> "GeneratorModel":
        return cls(0.0, np.inf)

    def polarizer_angle_deg(self, stage_angle_deg) -> np.ndarray:
        return np.asarray(stage_angle_deg, dtype=np.float64) + self.zero_offset_deg

    def incident_stokes(self, stage_angle_deg) -> np.ndarray:
        """Normalised incident Stokes ``(..., 3)`` at stage angle(s) in degrees."""
        ang = np.deg2rad(self.polarizer_angle_deg(stage_angle_deg))
        return polarizer_stokes(ang, self.extinction_ratio, np.ones(np.shape(ang)))

    @property
    def dolp(self) -> float:
        return float(dolp_from_extinction_ratio(self.extinction_ratio))

    def to_json(self) -> dict:
        return {"zero_offset_deg": self.zero_offset_deg,
                "zero_offset_std_deg": self.zero_offset_std_deg,
                "extinction_ratio": self.extinction_ratio,
                "extinction_ratio_std": self.extinction_ratio_std}

    @classmethod
    def from_json(cls, d: dict) -> "GeneratorModel":
        return cls(float(d["zero_offset_deg"]), float(d["extinction_ratio"]),
                   float(d.get("zero_offset_std_deg", 0.0)),
                   float(d.get("extinction_ratio_std", 0.0)))


def wrap_deg(angle_deg, period: float = 180.0) -> np.ndarray:
    """Wrap angles to ``[-period/2, period/2)``."""
    a = np.asarray(angle_deg, dtype=np.float64)
    return (a + period / 2) % period - period / 2


def check_stage_angles(stage_angles_deg, minimum: int = 8) -> np.ndarray:
    """Validate a stage-angle sweep: at least ``minimum`` angles covering 90+ degrees of
    polarizer rotation (half a period of the cos 2 theta response); :class:`TooFewAngles`
    names what to add."""
    a = np.asarray(stage_angles_deg, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(a)):
        raise ValueError("stage angles must be finite")
    distinct = np.unique(np.round(wrap_deg(a, 180.0), 6))
    span = 0.0
    if distinct.size >= 2:
        gaps = np.diff(np.concatenate([distinct, distinct[:1] + 180.0]))
        span = 180.0 - gaps.max()
    if distinct.size < minimum or span < 90.0:
        raise TooFewAngles(f"need {minimum}+ distinct stage angles spanning 90+ degrees (mod "
                           f"180), got {distinct.size} spanning {span:.0f} deg; add stage angles, "
                           f"e.g. every 10 deg over 0..180")
    return a


def fit_generator_from_angles(stage_angles_deg: np.ndarray, measured_aolp_deg: np.ndarray,
                              measured_dolp: np.ndarray, frame_sign: np.ndarray,
                              frame_angle_deg: np.ndarray, dolp_scale: np.ndarray,
                              weights: np.ndarray | None = None) -> GeneratorModel:
    """Fit offset and extinction ratio from measured camera-frame AoLP/DoLP.

    For each sample (stage angle ``theta``), the light reaching the camera has AoLP
    ``frame_sign * (theta + offset) + frame_angle_deg`` (``frame_sign`` -1 for a mirror
    reflection, which flips the basis handedness, +1 for a direct view; ``frame_angle_deg``
    the basis rotation from geometry) and DoLP ``dolp_scale * d`` (``dolp_scale`` the
    reference's DoLP transfer, 1 for a direct view or an ideal mirror). All arrays ``(N,)``.
    Returns the model with 1-sigma uncertainties from the scatter of the residuals.
    """
    th = np.asarray(stage_angles_deg, float).reshape(-1)
    n = th.size
    arrays = [np.broadcast_to(np.asarray(x, float), (n,)) for x in
              (measured_aolp_deg, measured_dolp, frame_sign, frame_angle_deg, dolp_scale)]
    aolp, dolp, sign, fang, dscale = arrays
    w = np.ones(n) if weights is None else np.broadcast_to(np.asarray(weights, float), (n,))
    ok = np.isfinite(aolp) & np.isfinite(dolp) & (w > 0) & (dscale > 0)
    if ok.sum() < 3:
        raise TooFewAngles(f"generator fit needs 3+ valid samples, got {int(ok.sum())}; add "
                           "stage angles or raise the light level")
    aolp, dolp, sign, fang, dscale, w, th = (x[ok] for x in (aolp, dolp, sign, fang, dscale, w, th))
    # offset: (aolp - fang) * sign - theta = offset (mod 180); circular weighted mean on 2x
    est = wrap_deg(sign * (aolp - fang) - th, 180.0)
    z = np.sum(w * np.exp(2j * np.deg2rad(est))) / np.sum(w)
    off = float(np.rad2deg(np.angle(z)) / 2)
    res = wrap_deg(est - off, 180.0)
    wn = w / w.sum()
    n_eff = 1.0 / np.sum(wn ** 2)
    off_std = float(np.sqrt(np.sum(wn * res ** 2) / max(n_eff - 1, 1)))
    dd = dolp / dscale
    d = float(np.sum(wn * dd))
    d_std = float(np.sqrt(np.sum(wn * (dd - d) ** 2) / max(n_eff - 1, 1)))
    d_c = min(d, 1.0 - 1e-9)
    er = float(extinction_ratio_from_dolp(d_c))
    er_std = float(2.0 / (1.0 - d_c) ** 2 * d_std)  # dER/dd = 2 / (1 - d)^2
    return GeneratorModel(off, er, off_std, er_std)
