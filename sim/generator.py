"""Polarization state generator of the simulated rig: the point light behind a linear polarizer
on the rotation stage.

The polarizer's transmission axis sits at ``stage_angle_deg + stage_zero_offset_deg`` from the
incident frame's ``x`` axis (the stage zero axis, ``docs/conventions.md``), turned from ``x``
towards ``y``; ``stage_zero_offset_deg`` (the mounting error of the polarizer on the stage) and
``extinction_ratio`` (major / minor intensity transmittance) are hidden parameters of the
simulated rig that calibration must find.

Normalisation (``docs/conventions.md``, "Radiometric units"): :meth:`Generator.incident_stokes`
is the Stokes vector of *unit* unpolarized light after the polarizer
(:func:`polrig.optics.mueller.polarizer_stokes` with ``intensity=1``, so ``S0 = (1 + 1/ER) / 2``);
the light's radiant intensity and colour (:meth:`polrig.sim.geometry.PointLight.radiant_intensity_rgb`)
are part of the image-plane Mueller matrix, not of ``S_in``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.optics.mueller import polarizer_stokes


@dataclasses.dataclass(frozen=True)
class Generator:
    """Hidden parameters of the polarizer in front of the light."""

    stage_zero_offset_deg: float = 1.7
    extinction_ratio: float = 800.0

    def __post_init__(self) -> None:
        if not (self.extinction_ratio > 1.0):
            raise ValueError(f"extinction ratio must be > 1 (inf = ideal), got "
                             f"{self.extinction_ratio}")

    def polarizer_angle_deg(self, stage_angle_deg) -> np.ndarray:
        """True transmission-axis angle (degrees, incident frame) at a stage reading."""
        return np.asarray(stage_angle_deg, dtype=np.float64) + self.stage_zero_offset_deg

    def incident_stokes(self, stage_angle_deg) -> np.ndarray:
        """Normalised incident linear Stokes ``(..., 3)`` at stage angle(s) ``stage_angle_deg``."""
        ang = np.deg2rad(self.polarizer_angle_deg(stage_angle_deg))
        return polarizer_stokes(ang, self.extinction_ratio, np.ones(np.shape(ang)))

    def to_json(self) -> dict:
        return {"stage_zero_offset_deg": self.stage_zero_offset_deg,
                "extinction_ratio": self.extinction_ratio}
