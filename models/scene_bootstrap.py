"""How sure a set's coverage figure is: the scene bootstrap.

A set's coverage within 2 sigma (:func:`polrig.models.continuum.score`) pools the elements of all
its samples, ``sum(inside) / sum(elements)``. Its elements are not independent draws: one scene's
network errors share the scene's light, shape and materials, so they cover or miss together, and
how much a figure from ``n`` scenes would move with other scenes of the same kind is set by how
much coverage varies *between* scenes, not by the number of pixels.

:func:`coverage_interval` resamples whole samples (scenes) with replacement and recomputes the
pooled ratio: the percentile interval of that statistic (Efron and Tibshirani, *An Introduction
to the Bootstrap*, 1993, ch. 13; resampling the clusters, not the units within them, is the
cluster bootstrap of Davison and Hinkley, *Bootstrap Methods and their Application*, 1997,
sec. 3.8). :func:`scene_spread` gives the spread of the per-sample coverage itself: what one
scene's figure may be.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Resamples per interval: with 2000 the 5 % and 95 % points move by about 0.02 point (standard
#: deviation over 20 seeds) on 64 synthetic scenes whose coverage spreads by 5 points.
RESAMPLES = 2000


def coverage_interval(inside: Sequence[float], elements: Sequence[float], level: float = 0.9,
                      resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """The percentile scene-bootstrap interval of the pooled coverage ``sum(inside) / sum(elements)``.

    Parameters
    ----------
    inside, elements : sequence of float, length n
        Per sample (scene), the elements within 2 sigma and the elements scored.
    level : float
        The interval's coverage probability, in (0, 1).
    resamples, seed : int
        The number of bootstrap resamples and the seed of their generator (the interval is
        reproducible).

    Returns
    -------
    (low, high) : tuple of float
        Fractions in [0, 1]; ``(nan, nan)`` when no sample scored an element.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    a = np.asarray(inside, float)
    n = np.asarray(elements, float)
    if a.shape != n.shape or a.ndim != 1:
        raise ValueError(f"inside and elements must be 1-D of one length, got {a.shape} and {n.shape}")
    if np.any(a < 0) or np.any(a > n):
        raise ValueError("each sample's inside count must lie in [0, its elements]")
    if a.size == 0 or n.sum() == 0:
        return float("nan"), float("nan")
    pick = np.random.default_rng(seed).integers(0, a.size, size=(resamples, a.size))
    total = n[pick].sum(axis=1)
    ratio = a[pick].sum(axis=1) / np.where(total > 0, total, np.nan)
    tail = 50.0 * (1.0 - level)
    low, high = np.nanpercentile(ratio, [tail, 100.0 - tail])
    return float(low), float(high)


def scene_spread(inside: Sequence[float], elements: Sequence[float], quantiles: tuple[float, float] = (0.1, 0.9)
                 ) -> tuple[float, float]:
    """The ``quantiles`` of the per-sample coverage ``inside / elements`` over the samples that scored
    an element (fractions; ``(nan, nan)`` when none did)."""
    a = np.asarray(inside, float)
    n = np.asarray(elements, float)
    per = a[n > 0] / n[n > 0]
    if per.size == 0:
        return float("nan"), float("nan")
    low, high = np.quantile(per, quantiles)
    return float(low), float(high)
