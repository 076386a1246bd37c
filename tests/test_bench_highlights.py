"""``python -m benchmarks highlights``: the bracket's scene clips at the reference exposure and
nowhere in the bracket, and a tiny run writes its table."""

import numpy as np
import pytest

from polrig.models.runtime import WEIGHTS_DIR


def test_the_scene_clips_only_at_the_reference_exposure():
    from benchmarks import bench_highlights

    _, one, bracket = bench_highlights.states((128, 96), np.random.default_rng(0))
    assert one.excluded.sum() > 0 and not bracket.excluded.any()
    assert np.array_equal(bracket.clipped_reference, one.excluded)


@pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file(), reason="no single-shot model")
def test_a_tiny_run_writes_the_table(tmp_path):
    from benchmarks import bench_highlights

    out = tmp_path / "h.md"
    assert bench_highlights.main(["--size", "64x64", "--rounds", "1", "--out", str(out)]) == 0
    text = out.read_text()
    assert "| bracket 1, 1/16, 1/256 |" in text and "in every exposure of the bracket" in text
