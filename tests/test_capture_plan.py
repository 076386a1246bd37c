"""Capture plan parsing and validation (no devices)."""

from __future__ import annotations

import pytest
from hypothesis import given, strategies as st

from polrig.capture import CapturePlan, parse_float_list, parse_pose_spec, planned_bytes
from polrig.errors import ConfigError


def test_range_is_stop_exclusive():
    assert parse_pose_spec("0:360:90") == (0.0, 90.0, 180.0, 270.0)
    assert parse_pose_spec("0:360:30")[-1] == 330.0
    assert parse_pose_spec("10:0:-5") == (10.0, 5.0)
    assert parse_pose_spec("0:1:0.25") == (0.0, 0.25, 0.5, 0.75)


def test_list_and_single():
    assert parse_pose_spec("0,30, 60") == (0.0, 30.0, 60.0)
    assert parse_pose_spec("45") == (45.0,)
    assert parse_pose_spec("-30") == (-30.0,)


@pytest.mark.parametrize("spec", ["", "a", "0:360", "0:360:0", "0:360:-10", "0,,30", "nan",
                                  "0:inf:1", "1:2:3:4", "0:10:1e-9"])
def test_bad_pose_specs_name_the_spec(spec):
    with pytest.raises(ConfigError, match="invalid pose spec"):
        parse_pose_spec(spec)


@given(start=st.integers(-720, 720), count=st.integers(1, 50), step=st.integers(1, 90))
def test_range_count_matches_python_range(start, count, step):
    stop = start + count * step
    assert parse_pose_spec(f"{start}:{stop}:{step}") == tuple(
        float(v) for v in range(start, stop, step))


def test_float_list():
    assert parse_float_list("0,45,90", "--states") == (0.0, 45.0, 90.0)
    with pytest.raises(ConfigError, match="--exposure"):
        parse_float_list("100,-1", "--exposure", positive=True)


def test_plan_validation_and_json_round_trip():
    p = CapturePlan((0, 90), states_deg=(0, 60, 120), frames_per_state=4, exposures_us=(1000, 4000),
                    dark_frames=2)
    assert CapturePlan.from_json(p.to_json()) == p
    assert p.frames_per_pose() == 2 * (3 * 4 + 2)
    with pytest.raises(ConfigError, match="at least 3"):
        CapturePlan((0,), states_deg=(0, 90))
    with pytest.raises(ConfigError, match="--frames"):
        CapturePlan((0,), frames_per_state=0)
    with pytest.raises(ConfigError, match="--mode"):
        CapturePlan((0,), mode="magic")
    # absurd angles are refused before anything is written (a pose of 1e308 deg made a
    # capture folder name too long for the file system once the session existed)
    with pytest.raises(ConfigError, match="invalid pose spec: pose 1e\\+308 deg"):
        CapturePlan((0, 1e308))
    with pytest.raises(ConfigError, match="--states: 400"):
        CapturePlan((0,), states_deg=(0, 45, 90, 400))
    assert CapturePlan((-36000, 36000), states_deg=(-360, 0, 90, 360)).poses_deg[0] == -36000.0
    # single-shot needs one state only
    assert CapturePlan((0,), mode="single-shot", states_deg=(0,)).frames_per_pose() == 1


def test_planned_bytes_grows_with_everything():
    p = CapturePlan((0, 90))
    base = planned_bytes(p, 2, 64, 64, 1)
    assert planned_bytes(p, 4, 64, 64, 1) > base
    assert planned_bytes(p, 2, 128, 128, 1) > base
    assert planned_bytes(p, 2, 64, 64, 3) > base
    assert base > 2 * 4 * 64 * 64 * 2  # at least the raw frames
    assert planned_bytes(p, 2, 64, 64, 1, (2, 2)) < base  # superpixel results are smaller
