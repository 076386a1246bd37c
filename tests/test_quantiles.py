"""polrig.solve.quantiles.tail_percentile against np.percentile (the definition it claims)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.solve.quantiles import MIN_SIZE, tail_percentile

QS = (0.0, 0.5, 1.0, 5.0, 9.99, 10.0, 50.0, 90.0, 99.0, 99.5, 99.99, 100.0)


def _data(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    if kind == "normal":
        return rng.normal(size=n).astype(np.float32)
    if kind == "ties":  # few distinct values: the thresholds land on long runs of ties
        return rng.integers(0, 5, n).astype(np.float32)
    if kind == "sorted":  # strided samples of ordered data are not random
        return np.sort(rng.exponential(size=n)).astype(np.float32)
    if kind == "reversed":
        return np.sort(rng.exponential(size=n))[::-1].copy()
    if kind == "spike":  # a tail of one huge value repeated (clipped highlights)
        v = rng.uniform(0, 1, n)
        v[rng.random(n) < 0.02] = 4095.0
        return v
    if kind == "constant":
        return np.full(n, 7.25, np.float32)
    raise AssertionError(kind)


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from(["normal", "ties", "sorted", "reversed", "spike", "constant"]),
       extra=st.integers(0, 3 * MIN_SIZE), q=st.one_of(st.sampled_from(QS), st.floats(0.0, 100.0)),
       seed=st.integers(0, 2**31))
def test_equals_numpy_percentile(kind, extra, q, seed):
    v = _data(kind, MIN_SIZE + extra, np.random.default_rng(seed))
    want = float(np.percentile(v, q))
    got = tail_percentile(v, q)
    assert got == pytest.approx(want, rel=1e-6, abs=1e-30)
    assert float(v.min()) <= got <= float(v.max())


def test_small_and_middle_go_to_numpy():
    rng = np.random.default_rng(1)
    small = rng.normal(size=100)
    assert tail_percentile(small, 99.5) == np.percentile(small, 99.5)
    big = rng.normal(size=2 * MIN_SIZE)
    assert tail_percentile(big, 50.0) == np.percentile(big, 50.0)


def test_any_shape_and_empty():
    v = np.random.default_rng(2).uniform(size=(3, 4, 200, 100)).astype(np.float32)
    assert tail_percentile(v, 99.5) == pytest.approx(float(np.percentile(v, 99.5)), rel=1e-6)
    with pytest.raises(ValueError, match="empty"):
        tail_percentile(np.zeros(0), 99.0)
