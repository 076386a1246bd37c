"""The adaptive capture (issue 33 item 2) on a 64x64 simulated rig of the ``plastic_metal``
scene: the plan's rules (one-line PlanErrors naming the field), decisions that stop at the
target and at the most states, decisions reproducible from the recorded frames, the hardware
time and ETA following the decisions, and an interrupted session that resumes to the identical
result. The criterion's algebra is tested in ``tests/test_design.py``."""

from __future__ import annotations

import itertools
import json
import shutil

import pytest
from test_capture import content, resume, sim_rig, start
from test_cli_capture import MODEL_INSTALLED

from polrig.acquisition.engine import hardware_model
from polrig.acquisition.plan import (
    ADAPTIVE_MIN_STATES,
    CapturePlan,
    PlanError,
    adaptive_pose_steps,
    setup_steps,
    step_durations,
)
from polrig.app.adaptive import STOP_MAX, STOP_TARGET, TAKE, TAKE_MIN, PoseMemo, replay_decisions
from polrig.app.capture import (
    CaptureRequest,
    RecordedDecision,
    kept_decisions,
    run_session,
)
from polrig.app.manifest import describe_decision
from polrig.app.session import COMPLETE, INTERRUPTED, MANIFEST_NAME, PENDING, Session
from polrig.app.sessionio import load_capture_frames
from polrig.cli import main
from polrig.errors import FormatError

needs_model = pytest.mark.skipif(not MODEL_INSTALLED, reason="no single-shot model in models/weights")

SCENE = "plastic_metal"
POSES = (0.0, 90.0)


def adaptive(target: float = 0.05, max_states: int = 4, poses=POSES, **kw) -> CapturePlan:
    return CapturePlan(poses, mode="adaptive", states_deg=(0.0,), target_sigma=target,
                       max_states=max_states, **kw)


# -- the plan ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, field, text", [
    ({"target_sigma": 0.0}, "target_sigma", "relative sigma"),
    ({"target_sigma": float("nan")}, "target_sigma", "relative sigma"),
    ({"target_sigma": 2.0}, "target_sigma", "(0, 1]"),
    ({"target_sigma": 0.01, "target_share": 0.0}, "target_share", "share of object pixels"),
    ({"target_sigma": 0.01, "target_share": 1.5}, "target_share", "share of object pixels"),
    ({"target_sigma": 0.01, "max_states": 0}, "max_states", "1..8"),
    ({"target_sigma": 0.01, "max_states": 9}, "max_states", "1..8"),
    ({"target_sigma": 0.01, "max_states": True}, "max_states", "1..8"),
    ({"target_sigma": 0.01, "min_states": 0}, "min_states", "1..4"),
    ({"target_sigma": 0.01, "min_states": 5}, "min_states", "1..4"),
    ({"target_sigma": 0.01, "max_states": 3, "min_states": 4}, "min_states", "1..3"),
    ({"target_sigma": 0.01, "min_states": 2.0}, "min_states", "whole number"),
    ({"target_sigma": 0.01, "resolution": "full"}, "resolution", "calibrated sigma"),
    ({"target_sigma": 0.01, "network_binning": 2}, "network_binning", "calibrated sigma"),
])
def test_adaptive_plan_refusals_name_the_field(kwargs, field, text):
    with pytest.raises(PlanError) as e:
        CapturePlan((0.0,), mode="adaptive", **kwargs)
    assert e.value.field == field and text in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("field, value", [("target_sigma", 0.01), ("target_share", 0.5),
                                          ("max_states", 3), ("min_states", 1)])
def test_the_stopping_rule_is_adaptive_only(field, value):
    for mode in ("reference", "hybrid"):
        with pytest.raises(PlanError) as e:
            CapturePlan((0.0,), mode=mode, **{field: value})
        assert e.value.field == field and "adaptive method only" in str(e.value)


def test_an_adaptive_plan_records_its_first_state_and_counts_the_most_frames():
    p = adaptive(0.02, 3, frames_per_state=2, dark_frames=1)
    assert p.states_deg == (0.0,) and p.seen_state == 0
    assert p.frames_per_pose() == 3 * 2 + 1  # the most: max_states states of K frames, the darks
    with pytest.raises(PlanError) as e:  # several states given: the method chooses them
        CaptureRequest(out=".", poses_deg=(0.0,), mode="adaptive", states_deg=(0.0, 45.0),
                       target_sigma=0.01).plan()
    assert e.value.field == "states_deg"


def test_the_fewest_states_default_to_two_and_follow_a_smaller_most():
    """A pose stops on its target from its second state on (the network's sigma checked by a
    frame it did not see), unless the plan says 1; a request for at most one state, the fewest
    not given, asks for one, not for a refusal."""
    assert adaptive().min_states == ADAPTIVE_MIN_STATES == 2
    assert adaptive(min_states=1).min_states == 1
    assert CapturePlan((0.0,)).min_states == 2  # every other plan holds the default
    req = lambda **kw: CaptureRequest(out=".", poses_deg=(0.0,), mode="adaptive", target_sigma=0.01, **kw).plan()
    assert req(max_states=1).min_states == 1 and req(max_states=3).min_states == 2
    with pytest.raises(PlanError) as e:  # both given: the fewest above the most is refused
        req(max_states=1, min_states=2)
    assert e.value.field == "min_states"


def test_a_version_5_session_reads_with_the_fewest_states_it_ran_with():
    """Version 5 had no ``min_states``: its adaptive poses could stop on the first state, and a
    resumed one must decide as it did (1); any other plan holds the default."""
    from polrig.app.manifest import migrate_v5

    for mode, least in (("adaptive", 1), ("reference", ADAPTIVE_MIN_STATES)):
        m = migrate_v5({"schema_version": 5, "plan": {"mode": mode}, "history": []})
        assert m["schema_version"] == 6 and m["plan"]["min_states"] == least
        assert m["history"][-1] | {"time": None} == {"time": None, "event": "schema migrated",
                                                     "from_version": 5, "to_version": 6}


def test_the_command_line_names_the_option(tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["capture", "--poses", "0", "--mode", "adaptive", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--target-sigma" in err, err
    assert "give a relative sigma" in err and "--target-sigma 0.0" not in err, err  # none given, not "0.0"
    rc = main(["capture", "--poses", "0", "--mode", "adaptive", "--target-sigma", "1.5", "--out", str(out),
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--target-sigma 1.5: must be a relative sigma" in err and not out.exists(), err
    rc = main(["capture", "--poses", "0", "--mode", "adaptive", "--target-sigma", "0.01",
               "--max-states", "12", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--max-states 12" in err and not out.exists(), err
    rc = main(["capture", "--poses", "0", "--mode", "adaptive", "--target-sigma", "0.01",
               "--min-states", "0", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "--min-states 0" in err and not out.exists(), err


# -- sessions -----------------------------------------------------------------------------------------
def run(tmp, plan: CapturePlan, **kw):
    events = []
    with sim_rig(scene=SCENE) as rig:
        model = hardware_model(rig)
        session, proc = start(rig, tmp, plan)
        result = run_session(rig, session, processor=proc, progress=events.append, **kw)
    return Session.open(tmp), proc, result, events, model


@pytest.fixture(scope="module")
def adaptive_run(tmp_path_factory):
    """Uninterrupted two-pose adaptive session (sensor noise keyed by pose, stage angle and
    repeat: a resumed session must reproduce it), the yardstick of the tests below."""
    return run(tmp_path_factory.mktemp("adaptive") / "s", adaptive())


@needs_model
def test_each_pose_records_the_states_it_took_and_why(adaptive_run):
    session, _, result, _, _ = adaptive_run
    assert result.status == "complete"
    for cap in session.captures:
        decisions = cap["adaptive"]
        assert [d["states_taken"] for d in decisions] == list(range(1, len(decisions) + 1))
        assert all(d["action"] == TAKE for d in decisions[:-1])
        assert decisions[-1]["action"] in (STOP_TARGET, STOP_MAX)
        taken = [0.0] + [d["state_deg"] for d in decisions[:-1]]
        raw = sorted((r["state_index"], r["state_deg"]) for r in cap["files"]["raw"])
        assert raw == list(enumerate(taken))  # the files are the states the decisions took
        # the second and third states are the equiangular set through the seen one (polrig.solve.design)
        second_third = [t % 180.0 for t in taken[1:3]]
        assert set(second_third) <= {60.0, 120.0} and len(set(second_third)) == len(second_third), taken
        for d in decisions[:-1]:  # the chosen state was predicted to lower the criterion
            assert d["predicted_criterion"] < d["criterion"] and d["design_pixels"] > 0
        assert cap["prior"]["seen_state"] == 0 and cap["score"]["psnr_db"] > 30
        # the prior's scale: none at the network's state alone; the result's is its last decision's
        assert decisions[0]["sigma_scale"] == 1.0 and all(d["sigma_scale"] > 0 for d in decisions)
        assert cap["prior"]["sigma_scale"]["factor"] == decisions[-1]["sigma_scale"]
        scale = cap["prior"]["sigma_scale"]  # the default: with the open direction's at two states
        assert scale["method"] == "geometry" and (decisions[-1]["states_taken"] == 2
                                                  or scale["open_direction"]["values"] == 0)


@needs_model
def test_info_shows_the_target_and_the_decisions(adaptive_run, capsys):
    session = adaptive_run[0]
    assert main(["info", str(session.root), "--no-verify"]) == 0
    out = capsys.readouterr().out
    assert "mode adaptive (target relative sigma 0.05 on 95 % of the object pixels, 2 to 4 states" in out
    lines = [line.strip() for line in out.splitlines()]
    # each decision on a line of its own, in the words of its progress event, in the order made
    decisions = [line.removeprefix("decision: ") for line in lines if line.startswith("decision: ")]
    assert decisions == [describe_decision(d) for c in session.captures for d in c["adaptive"]]
    assert sum(line.startswith("1 state(s): ") for line in decisions) == len(session.captures)


@needs_model
def test_on_plastic_and_metal_the_target_holds_with_fewer_states_than_the_fixed_four(adaptive_run):
    """Issue 33's acceptance at CI size (64x64, two poses; the measurement at 128x128 and
    512x512 is ``python -m benchmarks adaptive``): every pose stops at the target, on at least
    95 % of its object pixels, with fewer than four states on average."""
    session = adaptive_run[0]
    last = [c["adaptive"][-1] for c in session.captures]
    assert all(d["action"] == STOP_TARGET and d["share_met"] >= 0.95 for d in last), last
    assert sum(d["states_taken"] for d in last) / len(last) < 4


@needs_model
def test_decisions_are_reproducible_from_the_recorded_frames(adaptive_run):
    session, proc, _, _, _ = adaptive_run
    for cap in session.captures:
        assert replay_decisions(session, cap["index"], proc) == cap["adaptive"]


@needs_model
def test_the_pose_memo_gives_identical_decisions_with_one_network_pass_per_pose(adaptive_run, monkeypatch):
    """The memo a run keeps (frames, state radiances, the network's answer; keyed by the files'
    checksums) changes no decision: the records with it, without it and as recorded (by the run,
    which used one) are equal, and with it the network runs once per pose, each state's
    radiance is computed once."""
    session, proc, _, _, _ = adaptive_run
    calls = []
    network = proc.single_shot.state
    monkeypatch.setattr(proc.single_shot, "state", lambda *a, **k: calls.append(1) or network(*a, **k))
    memo = PoseMemo()
    for cap in session.captures:
        n = len(cap["adaptive"])
        calls.clear()
        uncached = replay_decisions(session, cap["index"], proc)
        assert len(calls) == n  # without the memo: the network on every decision
        calls.clear()
        cached = replay_decisions(session, cap["index"], proc, memo)
        assert len(calls) == 1 and len(memo.networks) == 1 and len(memo.radiances) == n
        assert memo.index == cap["index"] and len(memo.frames) == len(cap["files"]["raw"])
        assert cached == uncached == cap["adaptive"]
        calls.clear()  # a second pass finds everything in the memo
        assert replay_decisions(session, cap["index"], proc, memo) == cap["adaptive"] and calls == []


@needs_model
def test_frames_in_the_memo_are_still_verified(adaptive_run, tmp_path):
    """A frame the memo holds is not decoded again, but its file is verified on every read: a
    file changed since is refused (one line naming it), not served from the memo."""
    session, proc, _, _, _ = adaptive_run
    shutil.copytree(session.root, tmp_path / "s")
    s = Session.open(tmp_path / "s")
    memo = PoseMemo().of_capture(0)
    replay_decisions(s, 0, proc, memo)
    raw = s.capture(0)["files"]["raw"][-1]
    path = s.root / raw["path"]
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError) as e:
        load_capture_frames(s, 0, memo.frames)
    assert str(path) in str(e.value) and "SHA-256" in str(e.value) and "\n" not in str(e.value)


@needs_model
def test_hardware_time_and_eta_follow_the_decisions(adaptive_run):
    """The steps run are exactly each pose's steps for the states it took: the final hardware
    time is theirs; on the way the time done never goes back and what is left ends at 0."""
    session, _, _, events, model = adaptive_run
    plan = session.plan
    exposures = (float(session.capture(0)["files"]["raw"][0]["exposure_us"]),)
    steps = setup_steps()
    for cap in session.captures:
        taken = [0.0] + [d["state_deg"] for d in cap["adaptive"][:-1]]
        steps += adaptive_pose_steps(plan, cap["index"], exposures, taken)
    expected = sum(step_durations(steps, model))
    last = events[-1]
    assert last.kind == "session-done"
    assert last.hardware_s == pytest.approx(expected, rel=1e-12) and last.hardware_left_s == 0.0
    done = [e.hardware_s - e.hardware_left_s for e in events]
    assert all(b >= a - 1e-9 for a, b in itertools.pairwise(done))
    assert last.step == last.total == sum(len(c["files"]["raw"]) for c in session.captures)
    # a decision event per recorded decision, in its words (polrig.app.manifest.describe_decision)
    assert [(e.capture_index, e.message) for e in events if e.kind == "decision"] == [
        (c["index"], describe_decision(d)) for c in session.captures for d in c["adaptive"]]


@needs_model
def test_the_reference_method_reconstructs_each_pose_of_three_states_or_more(adaptive_run, tmp_path, capsys):
    """An adaptive session's poses took the states their decisions chose: ``reconstruct --mode
    reference`` solves each of at least 3 states, and one of fewer fails with its reason while
    the others go on; where no pose took 3 it is refused in one line, nothing recorded."""
    out = tmp_path / "s"
    shutil.copytree(adaptive_run[0].root, out, ignore=shutil.ignore_patterns("session.lock"))
    taken = [Session.open(out).states_taken(i) for i in range(len(POSES))]
    assert taken == [len(c["adaptive"]) for c in adaptive_run[0].captures]
    rc = main(["reconstruct", str(out), "--mode", "reference", "--no-progress"])
    err = capsys.readouterr().err
    if max(taken) < 3:
        assert rc == 2 and "at most" in err and "reconstruct with the hybrid method" in err, err
        return
    assert rc == (0 if min(taken) >= 3 else 1), err
    for n, cap in zip(taken, Session.open(out).captures):
        result = cap["revisions"]["rev1"]
        assert result["status"] == ("complete" if n >= 3 else "failed"), result
        assert n >= 3 or "need at least 3 polarizer states" in result["reason"]


def interrupted_at_frame(out, plan: CapturePlan, n: int) -> None:
    """Start ``plan`` in ``out`` and interrupt it (Ctrl-C) at its ``n``-th frame."""
    frames = []

    def progress(ev):
        if ev.kind == "frame":
            frames.append(ev)
            if len(frames) == n:
                raise KeyboardInterrupt

    with sim_rig(scene=SCENE) as rig:
        session, proc = start(rig, out, plan)
        with pytest.raises(KeyboardInterrupt):
            run_session(rig, session, processor=proc, progress=progress)


def resumes_to(out, reference: Session) -> None:
    """Resume ``out``: complete, verified, and identical to ``reference`` in files and decisions."""
    with sim_rig(scene=SCENE) as rig:
        s2, result = resume(rig, out)
    assert result.status == "complete" and s2.verify() == []
    assert content(s2) == content(reference)
    assert [c["adaptive"] for c in s2.captures] == [c["adaptive"] for c in reference.captures]


@needs_model
def test_an_interrupted_adaptive_session_resumes_to_the_identical_result(tmp_path, adaptive_run, capsys):
    from polrig.app.capture import SessionOpened
    from polrig.cli.commands.capture import _ProgressPrinter

    reference = adaptive_run[0]
    out = tmp_path / "s"
    interrupted_at_frame(out, adaptive(), len(reference.capture(0)["files"]["raw"]) + 2)  # pose 1, state 2
    s = Session.open(out)
    assert s.manifest["status"] == INTERRUPTED
    assert [c["status"] for c in s.captures] == [COMPLETE, PENDING]
    assert len(s.capture(1)["adaptive"]) == 1  # its first decision was recorded
    # a resume keeps the complete pose's decisions; the pending one decides again from scratch
    assert kept_decisions(s) == tuple(RecordedDecision(0, POSES[0], d) for d in s.capture(0)["adaptive"])
    # the command line prints them as the resumed run starts, as the GUI lists them
    _ProgressPrinter(enabled=False)(SessionOpened(out, True, 2, kept_decisions(s)))
    assert capsys.readouterr().out.splitlines() == [f"capture 1/2 pose {POSES[0]:g} deg: {describe_decision(d)} (recorded)"
                                                    for d in s.capture(0)["adaptive"]]
    resumes_to(out, reference)


@needs_model
def test_an_acquired_pose_whose_raw_data_is_damaged_keeps_no_recorded_decision(tmp_path, adaptive_run):
    """A resume keeps an acquired pose's decisions, except where its recorded raw data no
    longer verifies: the run sets that pose aside and acquires it again, deciding anew, so its
    old decisions are not listed as kept ("(recorded)")."""
    out = tmp_path / "s"
    shutil.copytree(adaptive_run[0].root, out)
    s = Session.open(out)
    s.capture(1)["status"] = "acquired"  # as a run stopped before processing it leaves it
    assert [k.capture_index for k in kept_decisions(s)] == [0] * len(s.capture(0)["adaptive"]) + \
        [1] * len(s.capture(1)["adaptive"])
    raw = out / s.capture(1)["files"]["raw"][0]["path"]
    raw.write_bytes(raw.read_bytes()[:-1])
    assert [k.capture_index for k in kept_decisions(s)] == [0] * len(s.capture(0)["adaptive"])


@needs_model
def test_an_interrupted_version_5_session_resumes_stopping_where_it_did(tmp_path):
    """A session written by schema version 5 (no ``min_states``: a pose could stop on the
    network's frame) and interrupted, then resumed by this polrig: the pending pose decides as
    version 5 did, and the session equals an uninterrupted one run with ``min_states`` 1."""
    plan = adaptive(1.0, min_states=1)
    reference = run(tmp_path / "reference", plan)[0]
    assert [len(c["adaptive"]) for c in reference.captures] == [1, 1]  # each pose stopped on its first state
    out = tmp_path / "s"
    interrupted_at_frame(out, plan, 2)  # pose 1's first frame
    m = json.loads((out / MANIFEST_NAME).read_text())
    del m["plan"]["min_states"]
    m["schema_version"] = 5
    (out / MANIFEST_NAME).write_text(json.dumps(m))
    assert Session.open(out).stored_version == 5 and Session.open(out).plan.min_states == 1
    resumes_to(out, reference)


@needs_model
def test_a_loose_target_stops_at_the_fewest_states_and_a_tight_one_at_max_states(tmp_path):
    """At target on the network's frame, a pose takes its second state (``take-min-states``,
    the cheapest: the nearer of the equiangular set's two others) and stops; with ``min_states``
    1 it stops on the network's frame."""
    session, _, result, _, _ = run(tmp_path / "loose", adaptive(1.0, poses=(0.0,)))
    assert result.status == "complete"
    first, last = session.capture(0)["adaptive"]
    assert first["action"] == TAKE_MIN and first["share_met"] >= 0.95 and first["state_deg"] == 60.0
    assert "the plan's fewest states not reached" in describe_decision(first)
    assert last["action"] == STOP_TARGET and last["states_taken"] == 2
    assert len(session.capture(0)["files"]["raw"]) == 2
    session, _, result, _, _ = run(tmp_path / "one", adaptive(1.0, poses=(0.0,), min_states=1))
    (only,) = session.capture(0)["adaptive"]
    assert only["action"] == STOP_TARGET and only["share_met"] >= 0.95 and only["states_taken"] == 1
    assert len(session.capture(0)["files"]["raw"]) == 1
    session, _, result, _, _ = run(tmp_path / "tight", adaptive(1e-6, max_states=2, poses=(0.0,)))
    decisions = session.capture(0)["adaptive"]
    assert [d["action"] for d in decisions] == [TAKE, STOP_MAX]
    assert decisions[-1]["share_met"] < 0.95 and len(session.capture(0)["files"]["raw"]) == 2


@needs_model
def test_a_limit_on_a_chosen_states_move_stops_safely_then_resumes_to_the_same_result(tmp_path, adaptive_run):
    """The steps a decision appends run under the engine's one fault policy: a limit switch
    on the stage's move to the first chosen state stops the session (no retry, no homing, the
    reason names the home command), the pose is failed with its partial frames gone, and a
    resume captures it again to the uninterrupted session's files and decisions."""
    reference = adaptive_run[0]
    out = tmp_path / "s"
    events = []
    with sim_rig(scene=SCENE) as rig:
        def progress(ev):
            events.append(ev)
            if ev.kind == "decision" and sum(e.kind == "decision" for e in events) == 1:
                rig.faults.inject_fault("stage", "limit", after_calls=0)  # the next stage call

        session, proc = start(rig, out, adaptive())
        result = run_session(rig, session, processor=proc, progress=progress)
    assert result.status == INTERRUPTED and result.reason.startswith("safety stop:")
    assert "`polrig home stage`" in result.reason and "\n" not in result.reason
    assert not any(e.kind == "retry" for e in events)
    s = Session.open(out)
    assert [c["status"] for c in s.captures] == ["failed", PENDING] and s.verify() == []
    resumes_to(out, reference)


@needs_model
def test_past_the_equiangular_set_states_are_chosen_per_second_and_the_last_for_accuracy(tmp_path):
    """A target no pose reaches takes ``max_states`` (5) states. The fourth is chosen by its
    predicted reduction of the criterion per second of hardware time, timed by the rig's timing
    the session recorded; the fifth, the last allowed, by the least criterion
    (:func:`polrig.solve.design.choose_next`). Replayed without that record (a session from
    before it) the same frames choose by the least criterion alone: the equiangular set's two
    states (one 60 deg move each) and the last state agree, and where the fourth differs, the
    per-second choice costs less time and predicts no lower criterion (the least criterion has
    the greatest gain, so a greater gain per second must cost less)."""
    from polrig.acquisition.plan import state_time_s
    from polrig.app.adaptive import timing_model

    out = tmp_path / "tight"
    session, proc, result, _, _ = run(out, adaptive(1e-6, max_states=5, poses=(0.0,)))
    assert result.status == "complete"
    with sim_rig(scene=SCENE) as rig:
        caps = rig.stage.capabilities
    timing = session.manifest["rig"]["timing"]
    assert timing["stage_speed_deg_s"] == caps.speed_deg_s
    decisions = session.capture(0)["adaptive"]
    assert [d["action"] for d in decisions] == [TAKE] * 4 + [STOP_MAX]
    exposures = load_capture_frames(session, 0).exposures_us
    here, seen = 0.0, []
    for d in decisions[:-1]:  # each records the hardware time of the state it took, a new state
        assert d["state_time_s"] == state_time_s(session.plan, exposures, here, d["state_deg"], timing_model(timing))
        assert all((d["state_deg"] - t) % 180.0 not in (0.0,) for t in [0.0, *seen])
        here = d["state_deg"]
        seen.append(here)
    legacy = tmp_path / "legacy"
    shutil.copytree(out, legacy)
    old = Session.open(legacy)
    del old.manifest["rig"]["timing"]
    old.save()
    replayed = replay_decisions(Session.open(legacy), 0, proc)
    assert all("state_time_s" not in d for d in replayed)
    assert [d["state_deg"] % 180.0 for d in replayed[:2]] == [d["state_deg"] % 180.0 for d in decisions[:2]]
    assert replayed[3]["state_deg"] % 180.0 == decisions[3]["state_deg"] % 180.0  # the last: least criterion
    fourth, least = decisions[2], replayed[2]
    if least["state_deg"] % 180.0 != fourth["state_deg"] % 180.0:
        least_s = state_time_s(session.plan, exposures, decisions[1]["state_deg"], least["state_deg"],
                               timing_model(timing))
        assert fourth["state_time_s"] < least_s
        assert fourth["predicted_criterion"] >= least["predicted_criterion"]


def test_the_forecast_is_the_equiangular_set_then_its_midpoints():
    """The hardware-time forecast (:func:`polrig.acquisition.plan.adaptive_forecast_states`): the
    states taken, then the equiangular set through the first not taken yet, then its midpoints,
    up to ``max_states``; a state taken at an equivalent stage angle counts as taken."""
    from polrig.acquisition.plan import adaptive_forecast_states

    plan = adaptive(max_states=5)
    assert adaptive_forecast_states(plan, []) == [0.0, 60.0, 120.0, 90.0, 30.0]
    assert adaptive_forecast_states(plan, [0.0, 300.0]) == [0.0, 300.0, 60.0, 90.0, 30.0]  # 300 is 120
    assert adaptive_forecast_states(adaptive(max_states=2), [0.0, 60.0, 120.0]) == [0.0, 60.0, 120.0]
