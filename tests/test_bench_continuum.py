"""``python -m benchmarks continuum``: the committed table's settings, overridable, end to end."""

import pathlib

import pytest

from polrig.models.runtime import WEIGHTS_DIR


def test_defaults_are_the_committed_tables():
    from benchmarks import bench_continuum

    assert bench_continuum.DEFAULTS[:4] == ["--count", "64", "--search-count", "32"]
    assert bench_continuum.RESULTS.name == "continuum.md"
    assert (bench_continuum.RESULTS.with_suffix(".json")).is_file()
    for defaults in (bench_continuum.JOINT_DEFAULTS, bench_continuum.JOINT_RIG_DEFAULTS):
        assert defaults[0] == "--joint-compare" and pathlib.Path(defaults[-1]).with_suffix(".json").is_file()
    assert bench_continuum.MIN_STATES_DEFAULTS[0] == "--min-states-compare"
    assert pathlib.Path(bench_continuum.MIN_STATES_DEFAULTS[-1]).with_suffix(".json").is_file()


@pytest.mark.skipif(not (WEIGHTS_DIR / "uncertainty.json").is_file(), reason="no calibrated model")
def test_a_tiny_run_writes_the_tables(tmp_path):
    """The benchmark's defaults with the options given winning; the states given, so not
    searched (the search: tests/test_models_continuum.py)."""
    from benchmarks import bench_continuum

    out = tmp_path / "c.md"
    assert bench_continuum.main(["--count", "1", "--search-count", "2", "--sets", "seen_families",
                                 "--two", "0,90", "--three", "0,60,120",
                                 "--out", str(out), "--root", str(tmp_path / "sets")]) == 0
    text = out.read_text()
    assert "--count 1 --search-count 2" in text and "seen families" in text
    assert "hybrid 2 - single" in text and out.with_suffix(".json").is_file()
    assert "the hybrid's prior jointly calibrated" in text  # the shipped calibration holds K


def test_plot_only_redraws_the_committed_plot_from_its_json(tmp_path):
    """``--plot-only [JSON]`` draws the plot beside the JSON from the JSON alone: the committed
    table's 8 sets x 13 methods (single-shot, hybrid 1-4, reference 3/4, the two equal-time
    rows, adaptive at two targets with up to 4 and up to 8 states)."""
    import json
    import shutil

    from benchmarks import bench_continuum
    from polrig.models import continuum

    src = bench_continuum.RESULTS.with_suffix(".json")
    copy = tmp_path / "continuum.json"
    shutil.copy(src, copy)
    assert bench_continuum.main(["--plot-only", str(copy)]) == 0
    assert (tmp_path / "continuum.png").is_file()
    result = json.loads(src.read_text())
    assert len(continuum.trade_points(result)) == 8 * 13
    assert bench_continuum.RIG_RESULTS.with_suffix(".json").is_file()
    assert bench_continuum.RIG_DEFAULTS[:2] == ["--rig-scenes", ",".join(continuum.RIG_SCENES)]
