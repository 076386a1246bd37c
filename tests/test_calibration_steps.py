"""The calibration steps' dependency graph (:data:`polrig.calibration.runner.DEPENDS_ON`): which
results a re-run step drops. End to end on the simulated rig: test_calibration_sim.py."""

from __future__ import annotations

from _calibration_sets import small_set

from polrig.calibration import runner


def test_the_dependency_graph_of_the_steps():
    assert runner.dependents("intrinsics") == ["turntable", "light", "stokes", "dofp"]
    assert runner.dependents("turntable") == ["light", "stokes", "dofp"]
    assert runner.dependents("light") == ["stokes", "dofp"]
    assert runner.dependents("stokes") == ["dofp"]
    assert runner.dependents("dofp") == []
    for step, deps in runner.DEPENDS_ON.items():  # only earlier steps
        assert all(runner.STEPS.index(d) < runner.STEPS.index(step) for d in deps)


def test_dropping_the_dofp_step_resets_the_extinction_ratio_it_measured():
    cs = small_set()
    assert runner.drop_results(cs, runner.dependents("stokes")) == ["dofp"]
    g = cs.params["generator"]
    assert g["extinction_ratio"] == float("inf") and g["extinction_ratio_std"] == 0.0
    assert cs.analyzer is None and cs.dofp_maps == {} and not cs.has("dofp")
    assert cs.params["generator"]["zero_offset_deg"] == 1.5
