"""Every reader of Mueller EXRs (the GUI viewer, the capture panel's thumbnail, polrig.sim.truth's
reader path through read_mueller_exr) loads files written with any plane choice: half-float
uncertainty planes, only some optional planes, or the Mueller channels alone."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.formats.exr import (
    RESULT_PLANES,
    read_mueller_exr,
    result_planes,
    write_mueller_exr,
)
from polrig.solve.reference import ReferenceResult

CHOICES = [(RESULT_PLANES, "float"), (RESULT_PLANES, "half"), (("mueller", "mask"), "half"),
           (("mueller",), "float")]


def _result(c: int = 3, h: int = 12, w: int = 16) -> ReferenceResult:
    rng = np.random.default_rng(0)
    m = rng.normal(0, 50, (c, 3, 3, h, w)).astype(np.float32)
    m[:, 0, 0] = rng.uniform(100, 2000, (c, h, w))
    zeros = np.zeros((c, h, w), np.float32)
    return ReferenceResult(m, np.abs(m) * 0.01 + 1, zeros + 1, np.zeros((c, h, w), np.uint8),
                           2.0, zeros + 2, np.full((c, h, w), 16, np.uint16))


@pytest.mark.parametrize("planes,uncertainty", CHOICES)
def test_viewer_and_thumbnail_load_every_plane_choice(tmp_path, planes, uncertainty):
    from polrig.gui.capture_panel import thumbnail_rgb
    from polrig.gui.viewer import load_exr

    r = _result()
    p = write_mueller_exr(tmp_path / "m.exr", r.mueller,
                          extra=result_planes(r, planes=planes, uncertainty=uncertainty))
    data = load_exr(p)
    np.testing.assert_array_equal(data.mueller, r.mueller)
    thumb = thumbnail_rgb(p, size=32)
    assert thumb.ndim == 3 and thumb.shape[2] == 3 and thumb.std() > 0
    back = read_mueller_exr(p)
    assert all(v.dtype == np.float32 for v in back.extra.values())
    assert {k.split(".")[0] for k in back.extra} == set(planes) - {"mueller"}
