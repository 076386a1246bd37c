"""The scene bootstrap of a set's coverage (:mod:`polrig.models.scene_bootstrap`): against the
binomial closed form where scenes are alike, wider where they differ, reproducible, and one-line
errors for bad counts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.models.scene_bootstrap import coverage_interval, scene_spread


def test_alike_scenes_give_the_binomial_interval():
    # n scenes of m independent elements each, coverage p: the pooled ratio's sd is sqrt(p(1-p)/(n m))
    rng = np.random.default_rng(3)
    n, m, p = 400, 50, 0.95
    inside = rng.binomial(m, p, size=n).astype(float)
    low, high = coverage_interval(inside, np.full(n, float(m)), level=0.9)
    sd = np.sqrt(p * (1 - p) / (n * m))
    assert (high - low) == pytest.approx(2 * 1.6449 * sd, rel=0.15)
    assert low < inside.sum() / (n * m) < high


def test_scenes_that_differ_widen_it_beyond_the_pixel_count():
    # the same element count, but half the scenes cover 99 % and half 91 %: a cluster effect
    rng = np.random.default_rng(4)
    n, m = 64, 4096
    per_scene = np.where(rng.random(n) < 0.5, 0.99, 0.91)
    inside = np.round(per_scene * m)
    low, high = coverage_interval(inside, np.full(n, float(m)))
    pixel_sd = np.sqrt(0.95 * 0.05 / (n * m))
    scene_sd = per_scene.std() / np.sqrt(n)
    assert high - low > 10 * 2 * 1.6449 * pixel_sd
    assert (high - low) == pytest.approx(2 * 1.6449 * scene_sd, rel=0.25)
    assert scene_spread(inside, np.full(n, float(m))) == pytest.approx((0.91, 0.99), abs=1e-3)


def test_it_is_reproducible_and_narrows_with_level():
    inside, elements = [90.0, 95.0, 99.0, 80.0], [100.0, 100.0, 100.0, 100.0]
    assert coverage_interval(inside, elements, seed=1) == coverage_interval(inside, elements, seed=1)
    wide, narrow = coverage_interval(inside, elements, 0.9), coverage_interval(inside, elements, 0.5)
    assert wide[0] <= narrow[0] <= narrow[1] <= wide[1]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 10_000)), min_size=1, max_size=40))
def test_the_interval_lies_within_the_samples_own_extremes(pairs):
    # the extremes included: a scene with no elements, all covered, none covered
    elements = np.array([max(a, b) for a, b in pairs], float)
    inside = np.array([min(a, b) for a, b in pairs], float)
    low, high = coverage_interval(inside, elements, resamples=200)
    if elements.sum() == 0:
        assert np.isnan(low) and np.isnan(high)
        return
    per = inside[elements > 0] / elements[elements > 0]
    assert per.min() - 1e-12 <= low <= high <= per.max() + 1e-12


@pytest.mark.parametrize("inside, elements, level, needle", [
    ([1.0, 2.0], [1.0], 0.9, "one length"),
    ([3.0], [2.0], 0.9, "inside count"),
    ([-1.0], [2.0], 0.9, "inside count"),
    ([1.0], [2.0], 1.0, "level"),
])
def test_bad_counts_say_so(inside, elements, level, needle):
    with pytest.raises(ValueError, match=needle):
        coverage_interval(inside, elements, level)
