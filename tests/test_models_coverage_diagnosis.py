"""``python -m polrig.models.coverage_diagnosis`` end to end on a tiny set: its counts add up
(the what-if at the shipped knee is the per-element table), the error shares are shares, and
bad input is one line, exit 2."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from polrig.models.runtime import WEIGHTS_DIR
from polrig.models.uncertainty import FILE_NAME

needs_weights = pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file()
                                   or not (WEIGHTS_DIR / FILE_NAME).is_file(), reason="no shipped weights")


@needs_weights
def test_tables_and_their_counts(tmp_path):
    from polrig.models import coverage_diagnosis as cd

    out = tmp_path / "res" / "d.md"
    res = cd.run(tmp_path / "sets", out, count=2, sets=["unseen_terrain"], set_count=2, knees_deg=(None, 30.0),
                 echo=lambda *a: None)
    saved = json.loads(out.with_suffix(".json").read_text())
    r = saved["sets"]["unseen_terrain"]
    assert r["samples"] == res["sets"]["unseen_terrain"]["samples"] >= 1
    for m in cd.METHODS:
        per = {k: np.array(v) for k, v in r["per_element"][m].items()}
        shipped = r["what_if"]["shipped"][m]
        assert per["inside"][0].sum() == shipped[0] and per["elements"][0].sum() == shipped[1]
        assert per["inside"].sum() == shipped[2] and per["elements"].sum() == shipped[3]
        assert (per["inside"] <= per["elements"]).all() and per["elements"].min() > 0
        # a knee past the shipped one only widens the first row's sigma: never fewer inside
        grown = r["what_if"]["30"][m]
        assert grown[0] >= shipped[0] and grown[2] >= shipped[2] and grown[1] == shipped[1]
    rows = {k: np.array(v) for k, v in r["rows"].items()}
    assert (0 <= rows["u_error"]).all() and (rows["u_error"] <= rows["error"] * (1 + 1e-12)).all()
    assert (rows["u_sigma"] <= rows["sigma"]).all()
    # the seen direction's share: 1 is the shipped hybrid 1; a smaller share narrows the one-state
    # sigma and leaves its mean, so never more inside; the single-shot's rows are its table's rows
    h1 = np.array(r["per_element"]["hybrid1"]["inside"]).sum(axis=1)
    grid = {float(k): np.array(v) for k, v in r["seen_share"].items()}
    assert np.array_equal(grid[1.0][:, 0], h1) and np.array_equal(grid[1.0][:, 1], grid[0.0][:, 1])
    shares = sorted(grid)
    assert all((grid[a][:, 0] <= grid[b][:, 0]).all() for a, b in zip(shares, shares[1:]))
    assert np.array_equal(np.array(r["single_rows"])[:, 0], np.array(r["per_element"]["single"]["inside"]).sum(axis=1))
    # the prior's scale from the innovations: gamma 0 is the shipped hybrid 2, every gamma scores the same elements
    scaled = {n: {float(g): np.array(v) for g, v in d.items()} for n, d in r["prior_scale"].items()}
    h2 = np.array(r["per_element"]["hybrid2"]["inside"]).sum()
    assert scaled["2"][0.0][0] == h2 and len({v[1] for d in scaled.values() for v in d.values()}) <= 3
    assert all(len(r["raw_scales"][n]) == r["samples"] and min(r["raw_scales"][n]) > 0 for n in scaled)
    # the open direction's what-if: exponent 0 is the two-state hybrid as captures scale it, every
    # exponent scores the same elements, one scale per sample
    from polrig.solve.prior_scale import SHRINK

    opened = {float(g): np.array(v) for g, v in r["open_scale"].items()}
    assert sorted(opened) == sorted(cd.OPEN_EXPONENTS) and len(r["open_scales"]) == r["samples"]
    assert np.array_equal(opened[0.0].sum(axis=0), scaled["2"][SHRINK])
    assert all(np.array_equal(v[:, 1], opened[0.0][:, 1]) for v in opened.values())
    assert min(r["open_scales"]) > 0
    assert "fitted_share" not in saved and "fitted_shrink" not in saved  # no calibration scenes in this run
    assert "fitted_open_exponent" not in saved
    text = out.read_text()
    assert "Within 2 sigma per element" in text and "What-if" in text and "hybrid 2, knee 30" in text
    assert "kappa 0.4" in text and "kappa fitted" not in text
    assert "prior's scale from the innovations" in text and "2 states, gamma 0.5" in text and "gamma fitted" not in text
    assert "open direction's scale from the diffuse completion" in text and "| g 0.5 |" in text


def test_the_open_exponent_is_chosen_by_each_samples_coverage():
    from polrig.models import coverage_diagnosis as cd

    # g 0: pooled 95.5 % but samples at 91 and 100 %; g 1: samples at 95 and 96 % -> 1
    per = {"0.0": [[91, 100], [100, 100]], "1.0": [[95, 100], [96, 100]], "2.0": [[99, 100], [99, 100]]}
    assert cd.fit_open_exponent(per) == 1.0
    assert cd.fit_open_exponent({"0.0": [[95, 100]], "0.5": [[96, 100]]}) == 0.0  # the nearer
    assert cd.fit_open_exponent({"0.5": [[95, 100], [0, 0]], "0.0": [[95, 100]]}) == 0.0  # ties: the smaller g


def test_the_share_is_fitted_where_the_hybrid_covers_as_the_single_shot():
    from polrig.models import coverage_diagnosis as cd

    shares = (1.0, 0.5, 0.0)
    # row 0 covers 90 % at share 0, 94 at 0.5, 98 at 1; the single-shot 96 % -> 0.75; row 1 is
    # below the single-shot's at every share -> 1; row 2 above at every share -> 0
    cov = {1.0: [98, 90, 99], 0.5: [94, 85, 98], 0.0: [90, 80, 97.5]}
    grid = {str(k): [[v[row], 100] for row in range(3)] for k, v in cov.items()}
    single = np.array([[96, 100], [95, 100], [95, 100]])
    assert cd.fit_seen_share(grid, single, shares) == pytest.approx([0.75, 1.0, 0.0])


def test_the_exponent_is_fitted_where_two_states_cover_as_a_gaussian():
    from polrig.models import coverage_diagnosis as cd

    # coverage falls with gamma: 97 % at 0, 96 at 0.5, 94 at 1 -> 95.45 % at 0.6375
    counts = {"0.0": [97, 100], "0.5": [96, 100], "1.0": [94, 100]}
    assert cd.fit_shrink(counts) == pytest.approx(0.5 + 0.5 * 0.55 / 2)
    assert cd.fit_shrink({"0.0": [99, 100], "1.0": [98, 100]}) == 1.0  # never low enough: the grid's end
    assert cd.fit_shrink({"0.0": [95, 100], "0.5": [97, 100], "1.0": [94, 100]}) == 0.0  # not monotone: nearest


@needs_weights
def test_rig_scenes_are_diagnosed_pose_by_pose():
    from polrig.models import continuum as cn
    from polrig.models import coverage_diagnosis as cd

    # two of the poses (each a sample: the rig's six take three times as long)
    res = cd.run(None, None, count=2, sets=[], rig_scenes=["sphere"], knees_deg=(None,), echo=lambda *a: None)
    r = res["sets"]["rig_sphere"]
    assert res["rig"] and 1 <= r["samples"] <= 2 <= len(cn.RIG_POSES_DEG)
    assert "--rig-scenes sphere" in cd.markdown(res) and np.array(r["per_element"]["hybrid2"]["elements"]).min() > 0
    assert "Pooled over the 1 scenes" in cd.markdown(res)


def test_the_pooled_line_is_the_scenes_total_with_its_interval():
    from polrig.models import coverage_diagnosis as cd

    def scene(inside):  # one scene: every element's count alike, 100 elements each
        return {"per_element": {m: {"inside": [[inside] * 3] * 3, "elements": [[100.0] * 3] * 3}
                                for m in cd.METHODS}}

    line = cd.pooled_line({"rig": True, "sets": {"a": scene(90.0), "b": scene(100.0)}})
    # pooled (90 + 100) / 200; the bootstrap of two scenes spans one scene alone to the other alone
    assert "single-shot 95.0 [90.0, 100.0] %" in line and "(scenes 91.0-99.0)" in line


@pytest.mark.parametrize("argv, needle", [(["--sets", "nowhere"], "unknown set(s) nowhere"),
                                          (["--count", "0", "--sets", "unseen_terrain"], "--count and --set-count must be >= 1"),
                                          (["--sets", "unseen_terrain", "--out", "x.txt"], "ending in .md"),
                                          (["--rig-scenes", "moon"], "--rig-scenes: unknown set(s) rig_moon")])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    from polrig.models import coverage_diagnosis as cd

    monkeypatch.chdir(tmp_path)
    assert cd.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1
