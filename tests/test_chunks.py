"""polrig.solve.chunks: the box that holds a mask's pixels (the chunks themselves are tested with
their kernels: tests/test_diffuse_kernel.py, tests/test_reduced_numerics.py,
tests/test_model_selection_two_states.py)."""

from __future__ import annotations

import numpy as np

from polrig.solve.chunks import mask_box


def test_mask_box_holds_every_pixel_of_the_mask():
    assert mask_box(np.zeros((4, 5), bool)) is None
    m = np.zeros((6, 9), bool)
    m[2, 7] = m[4, 3] = True
    assert mask_box(m) == (slice(2, 5), slice(3, 8))
    assert m[mask_box(m)].sum() == m.sum()
    assert mask_box(np.ones((3, 2), bool)) == (slice(0, 3), slice(0, 2))
