"""Noisy state radiances of a known Mueller scene, for the tests of the band-by-band solve and
the prior's scale (shared by ``test_radiometry_tiled``, ``test_hybrid`` and
``test_prior_scale_capture``)."""

from __future__ import annotations

import numpy as np

from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.noise import SensorModel
from polrig.solve.radiometry import StateRadiance


def noisy_states(rng: np.random.Generator, mueller: np.ndarray, s_in: np.ndarray, layout,
                 excluded_share: float = 0.03, exposure_us: float = 1000.0) -> list[StateRadiance]:
    """One :class:`StateRadiance` per incident state ``s_in`` ``(N, 3)`` of the scene ``mueller``
    ``(C, 3, 3, H, W)`` (DN per unit S0) through the ideal analyzer of ``layout``: the mosaic, the
    sensor model's variance at ``exposure_us`` and its Gaussian noise, ``excluded_share`` of the
    samples excluded at random."""
    shape = mueller.shape[-2:]
    ideal, model = AnalyzerModel.ideal(layout, shape), SensorModel()
    out = []
    for s in s_in:
        mosaic = ideal.mosaic(np.einsum("cijhw,j->cihw", mueller, s))
        var = model.variance_dn2(mosaic, exposure_us)
        out.append(StateRadiance((mosaic + rng.standard_normal(shape) * np.sqrt(var)).astype(np.float32),
                                 var.astype(np.float32), rng.random(shape) < excluded_share))
    return out
