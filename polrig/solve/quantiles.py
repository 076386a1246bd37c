"""Percentiles in the tails of large samples, without sorting the whole sample.

``np.percentile`` partitions the whole array (introselect, ``O(n)`` with a large constant: about
25 ms for the 3.8 million analyzer values of a full colour sensor on one core). A percentile
in a tail (q >= 90 or q <= 10) depends only on the few values beyond it: a strided subsample
gives a threshold that, with a wide margin, leaves the wanted order statistics on the tail's
side; only those values are partitioned. The result is the same order statistics and the same
linear interpolation as ``np.percentile(values, q)`` (the default ``method="linear"``,
Hyndman and Fan's definition 7); where the subsample's threshold misses (a margin too small
for the data's ties or ordering), the whole array is partitioned as before.
"""

from __future__ import annotations

import math

import numpy as np

#: Below this many values the whole array is partitioned (the selection costs more than it saves).
MIN_SIZE = 65536
#: Values drawn (strided) for the threshold.
SAMPLE_SIZE = 16384
#: The threshold leaves this many times the needed count on the tail's side (expected).
MARGIN = 4.0


def tail_percentile(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) of finite ``values`` (any shape,
    flattened) for a tail percentile ``q`` (in percent); other ``q`` and small arrays go to
    ``np.percentile``. Equal to it up to the rounding of the final interpolation (the same
    two order statistics are interpolated)."""
    v = np.asarray(values).reshape(-1)
    n = v.size
    if n == 0:
        raise ValueError("tail_percentile of an empty array")
    q = float(q)
    if n < MIN_SIZE or 10.0 < q < 90.0:
        return float(np.percentile(v, q))
    upper = q >= 90.0
    pos = q / 100.0 * (n - 1)
    lo = int(math.floor(pos))
    frac = pos - lo
    hi = min(lo + 1, n - 1)
    # order statistics lo..hi counted from the tail's end: the tail must hold at least this many
    need = (n - lo) if upper else (hi + 1)
    step = max(1, n // SAMPLE_SIZE)
    sample = np.sort(v[::step])
    share = min(1.0, MARGIN * need / n)  # the tail's expected share of the sample
    if upper:
        t = sample[max(0, int(math.floor((1.0 - share) * (sample.size - 1))))]
        tail = v[v >= t]
        offset = n - tail.size  # values below the tail
        if offset > lo:  # the threshold cut into the wanted statistics: partition everything
            return float(np.percentile(v, q))
    else:
        t = sample[min(sample.size - 1, int(math.ceil(share * (sample.size - 1))))]
        tail = v[v <= t]
        offset = 0
        if tail.size <= hi:
            return float(np.percentile(v, q))
    k_lo, k_hi = lo - offset, hi - offset
    part = np.partition(tail, [k_lo, k_hi] if k_hi != k_lo else [k_lo])
    a, b = float(part[k_lo]), float(part[k_hi])
    # numpy's linear interpolation (numpy.lib._function_base_impl._lerp), in float64
    return b - (b - a) * (1.0 - frac) if frac >= 0.5 else a + (b - a) * frac
