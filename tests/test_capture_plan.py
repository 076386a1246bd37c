"""Capture plan parsing and validation (no devices)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from polrig.acquisition.plan import (
    CapturePlan,
    Checkpoint,
    Grab,
    HardwareModel,
    Home,
    Move,
    PlanError,
    SetExposure,
    SetLight,
    SetTrigger,
    capture_steps,
    parse_float_list,
    parse_pose_spec,
    planned_bytes,
    session_steps,
    step_durations,
)
from polrig.app.manifest import migrate_v1, plan_json, read_plan
from polrig.errors import ConfigError, FormatError


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
    assert parse_float_list("0,45,90", "states") == (0.0, 45.0, 90.0)
    with pytest.raises(PlanError, match="invalid exposures '100,-1': values must be > 0") as e:
        parse_float_list("100,-1", "exposures", positive=True, field="exposures_us")
    assert e.value.field == "exposures_us"


def test_plan_validation_and_json_round_trip():
    p = CapturePlan((0, 90), states_deg=(0, 60, 120), frames_per_state=4, exposures_us=(1000, 4000),
                    dark_frames=2)
    assert read_plan(plan_json(p)) == p
    assert p.frames_per_pose() == 2 * (3 * 4 + 2)
    # errors name the plan field (for the command line to name its option), not a flag
    for kw, field, text in [({"states_deg": (0, 90)}, "states_deg", "at least 3"),
                            ({"frames_per_state": 0}, "frames_per_state", "frames per state"),
                            ({"mode": "magic"}, "mode", "capture mode must be one of"),
                            ({"dark_frames": -1}, "dark_frames", "dark frames must be >= 0"),
                            ({"mirror_average": True}, "mirror_average", "network's methods only"),
                            ({"resolution": "full"}, "resolution", "only the single-shot method"),
                            ({"resolution": "half"}, "resolution", "superpixel, full")]:
        with pytest.raises(PlanError, match=text) as e:
            CapturePlan((0,), **kw)
        assert e.value.field == field and "--" not in str(e.value)
    assert issubclass(PlanError, ConfigError)
    # absurd angles are refused before anything is written (a pose of 1e308 deg made a
    # capture folder name too long for the file system once the session existed)
    with pytest.raises(ConfigError, match="invalid pose spec: pose 1e\\+308 deg"):
        CapturePlan((0, 1e308))
    with pytest.raises(PlanError, match="polarizer state 400 deg: not a polarizer angle") as e:
        CapturePlan((0,), states_deg=(0, 45, 90, 400))
    assert (e.value.field, e.value.subject) == ("states_deg", "400 deg")
    assert CapturePlan((-36000, 36000), states_deg=(-360, 0, 90, 360)).poses_deg[0] == -36000.0
    # single-shot needs one state only
    assert CapturePlan((0,), mode="single-shot", states_deg=(0,)).frames_per_pose() == 1


def test_single_shot_resolution_is_planned_and_older_plans_read_as_superpixel():
    full = CapturePlan((0,), mode="single-shot", resolution="full")
    assert read_plan(plan_json(full)) == full and plan_json(full)["resolution"] == "full"
    old = plan_json(CapturePlan((0,), mode="single-shot"))
    del old["resolution"]  # a session written before the field existed (schema version 1)
    assert read_plan(migrate_v1({"plan": old, "captures": []})["plan"]).resolution == "superpixel"
    with pytest.raises(FormatError, match="plan: missing 'resolution'"):  # version 2 states it
        read_plan(old)
    # the result EXR of a full-resolution plan is at the raw size: 16 times the 4x4-cell grid's
    sp = CapturePlan((0,), mode="single-shot")
    assert planned_bytes(full, 1, 64, 64, 3, (4, 4)) > planned_bytes(sp, 1, 64, 64, 3, (4, 4))
    assert (planned_bytes(full, 1, 64, 64, 3, (4, 4))
            == planned_bytes(CapturePlan((0,), mode="single-shot", demosaic="bilinear"), 1, 64, 64, 3, (4, 4)))


def test_network_binning_is_planned_checked_and_older_plans_read_as_1():
    """``network_binning`` (issue 22's faster single-shot mode): the options' values are the
    command line's, it round-trips, a plan without it (a session from before it existed) reads back
    as 1, bad values and the reference method are one-line errors naming the field, and the
    result file's size does not change (the output grid is ``resolution``'s either way)."""
    from polrig.acquisition.plan import NETWORK_BINNINGS
    from polrig.cli import (
        build_parser,  # the options' choices are the plan's (not imported there)
    )

    sub = next(a for a in build_parser()._actions if a.choices and "capture" in a.choices).choices
    for command in ("capture", "reconstruct"):
        [opt] = [a for a in sub[command]._actions if "--network-binning" in a.option_strings]
        assert tuple(opt.choices) == NETWORK_BINNINGS and opt.default is None
    binned = CapturePlan((0,), mode="single-shot", network_binning=2)
    assert read_plan(plan_json(binned)) == binned and plan_json(binned)["network_binning"] == 2
    old = plan_json(CapturePlan((0,), mode="single-shot"))
    del old["network_binning"]  # a session written before the field existed (schema version 1)
    assert read_plan(migrate_v1({"plan": old, "captures": []})["plan"]).network_binning == 1
    for kw, text in [({"network_binning": 2}, "network binning 2: network binning applies to the "
                                              "single-shot method only"),
                     ({"mode": "single-shot", "network_binning": 3}, "network binning 3: must be one of 1, 2"),
                     ({"mode": "single-shot", "network_binning": True}, "must be one of 1, 2"),
                     ({"mode": "single-shot", "network_binning": "2"}, "network binning '2': must be one of")]:
        with pytest.raises(PlanError, match=text) as e:
            CapturePlan((0,), **kw)
        assert e.value.field == "network_binning" and "\n" not in str(e.value)
    assert CapturePlan((0,), network_binning=1).network_binning == 1  # 1 is every mode's
    for res in ("superpixel", "full"):
        one = CapturePlan((0,), mode="single-shot", resolution=res)
        two = CapturePlan((0,), mode="single-shot", resolution=res, network_binning=2)
        assert planned_bytes(two, 2, 64, 64, 3, (4, 4)) == planned_bytes(one, 2, 64, 64, 3, (4, 4))


def test_planned_bytes_grows_with_everything():
    p = CapturePlan((0, 90))
    base = planned_bytes(p, 2, 64, 64, 1)
    assert planned_bytes(p, 4, 64, 64, 1) > base
    assert planned_bytes(p, 2, 128, 128, 1) > base
    assert planned_bytes(p, 2, 64, 64, 3) > base
    assert base > 2 * 4 * 64 * 64 * 2  # at least the raw frames
    assert planned_bytes(p, 2, 64, 64, 1, (2, 2)) < base  # superpixel results are smaller


# -- the plan as a list of device steps (no rig) -------------------------------------------------
def grabs(steps):
    return [s.tag for s in steps if isinstance(s, Grab)]


def test_a_pose_is_a_list_of_steps_with_the_turntable_and_stage_moving_together():
    plan = CapturePlan((0.0, 90.0), frames_per_state=2, exposures_us=(1000.0, 4000.0),
                       dark_frames=1)
    steps = capture_steps(plan, 0, plan.exposures_us)
    assert steps[0] == Checkpoint("capture-start", 0)
    assert steps[1] == Move((("turntable", 0.0), ("stage", 0.0)))  # one move, both axes
    assert steps[2] == SetLight(False) and SetLight(True) in steps
    assert steps[-2:] == [SetExposure(1000.0), Checkpoint("capture-acquired", 0)]
    # three stage moves for four states: the first state was reached with the turntable
    assert [s for s in steps if isinstance(s, Move)][1:] == [
        Move((("stage", a),)) for a in (45.0, 90.0, 135.0)]
    tags = grabs(steps)
    assert len(tags) == plan.frames_per_pose() == 2 * (4 * 2 + 1)
    assert [(t.exposure_index, t.frame) for t in tags if t.role == "dark"] == [(0, 0), (1, 0)]
    raw = [(t.state_index, t.state_deg, t.exposure_index, t.frame) for t in tags if t.role == "raw"]
    assert raw[:4] == [(0, 0.0, 0, 0), (0, 0.0, 0, 1), (0, 0.0, 1, 0), (0, 0.0, 1, 1)]
    assert len(set(raw)) == len(raw) == 16
    assert all(t.capture == 0 and t.pose_deg == 0.0 for t in tags)


def test_state_order_is_serpentine_and_frames_keep_the_plans_state_index():
    """Pose k visits 0, 45, 90, 135, pose k + 1 135, 90, 45, 0: the stage never travels back
    idle, and the frames of a state carry its index in the plan whatever the order."""
    plan = CapturePlan((0.0, 90.0, 180.0))
    steps = session_steps(plan, [0, 1, 2], (20000.0,))
    assert steps[:3] == [SetTrigger(None), SetLight(True), Home("stage")]
    stage_path = [dict(s.targets)["stage"] for s in steps if isinstance(s, Move)]
    assert stage_path == [0, 45, 90, 135, 135, 90, 45, 0, 0, 45, 90, 135]
    turns = [dict(s.targets)["turntable"] for s in steps
             if isinstance(s, Move) and "turntable" in dict(s.targets)]
    assert turns == [0.0, 90.0, 180.0]
    order = [(t.capture, t.state_index, t.state_deg) for t in grabs(steps)]
    assert order[4:8] == [(1, 3, 135.0), (1, 2, 90.0), (1, 1, 45.0), (1, 0, 0.0)]
    # the same tags as plan order, whatever the order: files and results do not depend on it
    assert sorted(order) == sorted((c, j, a) for c in range(3) for j, a in enumerate(plan.states_deg))
    # a resumed odd pose keeps its own order (it depends on the pose, not on what is left)
    assert grabs(capture_steps(plan, 1, (20000.0,))) == grabs(steps)[4:8]


def test_single_shot_visits_one_state():
    plan = CapturePlan((0.0, 90.0), mode="single-shot", states_deg=(30.0,))
    steps = session_steps(plan, [0, 1], (1000.0,))
    assert [(t.state_index, t.state_deg) for t in grabs(steps)] == [(0, 30.0), (0, 30.0)]
    assert not [s for s in steps if isinstance(s, Move) and len(s.targets) == 1]


def _model(settle=0, readout_us=10000.0):
    speeds = {"stage": 20.0, "turntable": 10.0}
    return HardwareModel(lambda a, f, t: abs(t - f) / speeds[a], readout_us, settle,
                         {"stage": 0.0, "turntable": 0.0}, 20000.0)


def test_hardware_time_is_motion_plus_exposure_plus_readout_with_overlapped_axes():
    """Closed form for two poses of four states at constant speed (stage 20 deg/s, turntable
    10 deg/s): the stage sweeps 135 deg per pose (serpentine: never back), the turntable's
    90 deg turn hides the stage's move to the first state; each frame 20 ms + 10 ms."""
    plan = CapturePlan((0.0, 90.0))
    steps = session_steps(plan, [0, 1], (20000.0,))
    d = step_durations(steps, _model())
    assert len(d) == len(steps)
    motion = 135 / 20 + 90 / 10 + 135 / 20  # pose 0 sweep, the turn (stage stays), pose 1 sweep
    assert sum(d) == pytest.approx(motion + 8 * 0.030)
    # plan order at every pose would add the stage's 135 deg return each time (but the first)
    moves = [s for s in steps if isinstance(s, Move)]
    assert max(d[steps.index(m)] for m in moves if len(m.targets) == 2) == pytest.approx(9.0)
    # free run: settle frames after every move or setting change, none between repeats
    free = step_durations(session_steps(CapturePlan((0.0,), frames_per_state=3), [0], (20000.0,)),
                          _model(settle=2))
    frames = [t for t in free if 0 < t < 1]
    assert frames.count(pytest.approx(0.090)) == 4 and frames.count(pytest.approx(0.030)) == 8


@pytest.mark.parametrize("frames, bracket, settle", [(1, (1000.0,), 0), (3, (1000.0, 62.5), 2)])
def test_a_states_time_is_its_move_and_its_frames(frames, bracket, settle):
    """:func:`polrig.acquisition.plan.state_time_s`: the stage's move from where it stands, then
    ``frames`` frames per exposure of the bracket, each exposure plus readout, and the settle
    frames after the move and after each exposure change (free run) - the camera starts at the
    bracket's last exposure, where the state before left it."""
    from polrig.acquisition.hal import AxisCapabilities
    from polrig.acquisition.plan import HardwareModel, state_time_s

    axis = AxisCapabilities(20.0, 50.0)
    model = HardwareModel(lambda a, f, t: axis.move_time_s(t - f), 500.0, settle, {"stage": 0.0}, float("nan"))
    plan = CapturePlan((0.0,), frames_per_state=frames)
    frame_s = [(e + 500.0) * 1e-6 for e in bracket]
    # the move unsettles; each exposure's first frame discards the settle frames (a change or the move)
    expected = axis.move_time_s(75.0) + sum((frames + settle) * f for f in frame_s)
    assert state_time_s(plan, bracket, 45.0, 120.0, model) == pytest.approx(expected, rel=1e-12)
    assert state_time_s(plan, bracket, 120.0, 45.0, model) == pytest.approx(expected, rel=1e-12)  # either way
