"""Random directions for the oracle tests (shared by the Mitsuba comparisons)."""

from __future__ import annotations

import numpy as np

#: Smallest cosine to the normal a sampled direction may have (grazing directions excluded,
#: where both sides' float32 rounding dominates).
MIN_COS = 0.05


def random_unit(rng: np.random.Generator, around: np.ndarray | None = None,
                min_cos: float = MIN_COS) -> np.ndarray:
    """A uniformly random unit 3-vector; with ``around`` (a unit vector), one in its
    hemisphere at least ``min_cos`` from the horizon."""
    while True:
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        if around is None:
            return v
        c = v @ around
        if c < 0:
            v, c = -v, -c
        if c >= min_cos:
            return v
