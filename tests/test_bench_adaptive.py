"""``python -m benchmarks adaptive``: a tiny run writes its table (one pose, 64x64)."""

import pytest

from polrig.models.runtime import WEIGHTS_DIR


@pytest.mark.skipif(not (WEIGHTS_DIR / "uncertainty.json").is_file(), reason="no calibrated model")
def test_a_tiny_run_writes_the_table(tmp_path):
    from benchmarks import bench_adaptive

    out = tmp_path / "a.md"
    # the decision-time table at 64x64, one round (its default sizes, 512 and the full sensor, are
    # minutes: the benchmark's, not the suite's)
    assert bench_adaptive.main(["--size", "64", "--poses", "0", "--targets", "0.05", "--out", str(out),
                                "--decision-sizes", "64", "--rounds", "1"]) == 0
    text = out.read_text()
    assert "| adaptive 0.05 |" in text and "| hybrid4 | 4.00 (4) |" in text and "| reference4 |" in text
    assert "share at 0.05" in text and "acquisition time s" in text and out.with_suffix(".json").is_file()
    assert "## Decision time" in text
