"""Single-shot geometry carried to the analyzer grid (polrig.app.single_shot) on frames too small
for one mosaic cell: one clear error for every caller, never a ZeroDivisionError."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.app.single_shot import analyzer_grid_intrinsics, network_kwargs
from polrig.cli import main
from polrig.sensor.frame import Frame, FrameMeta

GEOMETRY = {"intrinsics": (640.0, 640.0, 127.5, 127.5), "stage_zero_axis_camera": (1.0, 0.0, 0.0)}


def _frame(h: int, w: int, layout: str = "imx250mzr") -> Frame:
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=1000.0, gain_db=0.0,
                     pixel_format="Mono16", layout=layout, bit_depth=16)
    return Frame(np.full((h, w), 1000, np.uint16), meta)


@pytest.mark.parametrize("shape, layout, cell", [((1, 1), "imx250mzr", "2x2"),
                                                 ((1, 8), "imx250mzr", "2x2"),
                                                 ((3, 3), "imx250myr", "4x4")])
@pytest.mark.parametrize("method", ["superpixel", "bilinear"])
def test_frame_smaller_than_a_layout_cell_is_the_demosaic_error(shape, layout, cell, method):
    import re

    message = f"raw mosaic {shape} is smaller than one {cell} layout cell"
    with pytest.raises(ValueError, match=re.escape(message)):
        network_kwargs(GEOMETRY, _frame(*shape, layout), method)


def test_an_empty_analyzer_grid_is_refused_not_divided_by():
    with pytest.raises(ValueError, match="empty analyzer grid"):
        analyzer_grid_intrinsics(GEOMETRY["intrinsics"], (0, 0), (1, 1), (0, 0))
    assert network_kwargs(GEOMETRY, _frame(2, 2))["intrinsics"] is not None


def test_infer_on_a_one_pixel_frame_is_one_line_exit_2(tmp_path, capsys):
    """``polrig infer`` on a 1x1 16-bit PNG: exit 2 and the line ``polrig stokes`` gives on the
    same file (a ZeroDivisionError traceback before)."""
    from polrig.formats.rawio import encode_mosaic

    raw = tmp_path / "one.png"
    raw.write_bytes(encode_mosaic(np.array([[1000]], np.uint16), ".png"))
    rc = main(["infer", str(raw), "--state-deg", "0", "--out", str(tmp_path / "i.exr")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert "raw mosaic (1, 1) is smaller than one 2x2 layout cell" in err
