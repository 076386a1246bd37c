"""``python -m polrig.models.continuum``: single-shot, hybrid and reference from one state to
four on held-out sets, end to end on tiny sets; the rendered states; one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polrig.models.runtime import WEIGHTS_DIR
from polrig.models.uncertainty import FILE_NAME
from polrig.optics.mueller import polarizer_stokes

needs_weights = pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file()
                                   or not (WEIGHTS_DIR / FILE_NAME).is_file(), reason="no shipped weights")


def test_rotated_state_is_the_turned_polarizer():
    from polrig.models.continuum import rotated_state

    s = polarizer_stokes(np.radians(17.0), 400.0, 0.8)
    for d in (0, 15, 60, 135):
        assert np.allclose(rotated_state(s, d), polarizer_stokes(np.radians(17.0 + d), 400.0, 0.8), atol=1e-12)


@needs_weights
def test_tables_search_and_the_hybrid_limits(tmp_path):
    from polrig.models import continuum

    out = tmp_path / "res" / "c.md"
    res = continuum.run(tmp_path / "sets", out, count=2, search_count=1, sets=["seen_families"], echo=lambda *a: None)
    saved = json.loads(out.with_suffix(".json").read_text())
    assert saved["offsets"]["four"] == [0, 45, 90, 135]
    two, three = saved["offsets"]["two"], saved["offsets"]["three"]
    assert two[0] == three[0] == 0 and len(saved["search"]["three"]) == 55
    assert saved["search"]["two"]["/".join(map(str, two))] == max(saved["search"]["two"].values())
    m = res["sets"]["seen_families"]["methods"]
    assert res["sets"]["seen_families"]["samples"] >= 1
    # the seen state alone moves only the frame's directions; four states beat the network
    assert m["hybrid1"]["matrix_psnr"] >= m["single"]["matrix_psnr"] - 0.5
    assert m["hybrid4"]["matrix_psnr"] > m["single"]["matrix_psnr"] + 5
    assert m["exclude1"] == m["single"]
    for k in ("single", "hybrid1", "hybrid2", "hybrid3", "hybrid4", "reference3", "reference4"):
        assert 0.5 < m[k]["coverage"] <= 1.0 and m[k]["fwd_l2"] > 0
    text = out.read_text()
    assert "hybrid 2 (0/" in text and "Within 2 sigma" in text and "equal time" in text
    # the adaptive capture at its two targets: between the capture's fewest states (2) and four, a time
    # that grows with them
    assert saved["adaptive_min_states"] == 2 and "with at least 2 states taken" in text
    for t in continuum.ADAPTIVE_TARGETS:
        a = m[f"adaptive_{t:g}"]
        assert 2 <= a["states"] <= 4 and 0.5 < a["coverage"] <= 1.0
        assert m["single"]["time_s"] <= a["time_s"] <= m["hybrid4"]["time_s"] + 10.0
        more = m[f"adaptive_{t:g}_max{continuum.ADAPTIVE_MORE_STATES}"]  # up to 8 states
        assert a["states"] <= more["states"] <= continuum.ADAPTIVE_MORE_STATES and 0.5 < more["coverage"] <= 1.0
    assert m["single"]["time_s"] < m["hybrid2"]["time_s"] < m["hybrid4"]["time_s"]
    assert "adaptive 0.05" in text and "adaptive 0.05, <= 8 states" in text and "acquisition time" in text
    # the bracketed rows: the bracket's short frames cost little time; the highlights table is written
    assert m["hybrid2"]["time_s"] < m["hybrid2_bracket"]["time_s"] < m["hybrid2"]["time_s"] + 0.2
    assert m["hybrid2_bracket"]["states"] == 2 and 0.5 < m["hybrid2_bracket"]["coverage"] <= 1.0
    assert "Highlights: an exposure bracket" in text
    # every coverage figure carries its scene-bootstrap interval, which holds it
    for k in ("single", "hybrid1", "hybrid4"):
        low, high = m[k]["coverage_interval"]
        assert low <= m[k]["coverage"] <= high
    assert "how sure each figure is" in text
    # the prior's sigma as calibrated beside the captures' scaled one: the same states and time,
    # another sigma from two states on
    assert "**The prior's scale**" in text
    for n in (2, 3, 4):
        a, b = m[f"hybrid{n}_calibrated"], m[f"hybrid{n}"]
        assert (a["states"], a["time_s"]) == (b["states"], b["time_s"]) and 0.5 < a["coverage"] <= 1.0
        assert a["coverage"] != b["coverage"] or a["matrix_psnr"] != b["matrix_psnr"]


def test_acquisition_time_is_the_plans_hardware_time():
    """One frame of exposure plus readout per state, and the stage's trapezoidal moves: 0 -> 90
    at 20 deg/s and 100 deg/s^2 takes 90 / 20 + 20 / 100 s; a move to 165 deg goes to -15."""
    from polrig.models import continuum
    from polrig.sim.dataset import DATASET_EXPOSURE_US

    frame = (DATASET_EXPOSURE_US + continuum.SIM_READOUT_US) * 1e-6
    assert continuum.acquisition_time_s([0]) == pytest.approx(frame)
    assert continuum.acquisition_time_s([0, 90]) == pytest.approx(2 * frame + 90 / 20 + 20 / 100)
    assert continuum.acquisition_time_s([0, 165]) == continuum.acquisition_time_s([0, 15])
    assert continuum.acquisition_time_s([0, 90], 3) == pytest.approx(6 * frame + 90 / 20 + 20 / 100)


@needs_weights
def test_frames_are_the_sensor_models(tmp_path):
    """Rendered states clip where the sensor does and carry its variance; averaging k frames
    divides it by k."""
    from polrig.models import continuum
    from polrig.models.data import load_dataset
    from polrig.sensor.noise import SensorModel
    from polrig.sim.dataset import generate_dataset

    data = tmp_path / "d"
    generate_dataset(data, count=1, width=64, seed=3, progress=False)
    ds = load_dataset(data)
    sensor = SensorModel(**ds.manifest["noise"]["sensor_model"])
    prior = (np.zeros_like(ds["mueller"][0], np.float64),) * 2
    one = continuum.sample_frames(ds, 0, prior, sensor, np.random.default_rng(0), offsets=(0, 90))
    four = continuum.sample_frames(ds, 0, prior, sensor, np.random.default_rng(0), offsets=(0, 90),
                                   frames_per_state=4)
    assert np.array_equal(one.meas[0], ds["analyzer"][0].astype(np.float64))  # the network's own frame
    assert np.allclose(four.var[90], sensor.variance_dn2(four.meas[90] * float(ds["scale"][0]), 10000.0, 4)
                       / float(ds["scale"][0]) ** 2)
    sat = sensor.saturation_dn / float(ds["scale"][0])
    assert not np.any(one.valid[90] & (one.meas[90] >= sat))
    # a bracket (on a conductor, whose highlights clip): the reference exposure's clipping stays
    # the scoring's; its merge measures the clipped samples too
    generate_dataset(tmp_path / "m", count=1, width=64, seed=3, progress=False, material_mix="conductor")
    ds = load_dataset(tmp_path / "m")
    one = continuum.sample_frames(ds, 0, prior, sensor, np.random.default_rng(0), offsets=(0, 90))
    br = continuum.sample_frames(ds, 0, prior, sensor, np.random.default_rng(0), offsets=(0, 90),
                                 bracket=continuum.BRACKET)
    assert np.array_equal(br.use, one.use) and np.array_equal(br.clean, one.clean)
    for d in (0, 90):
        assert br.valid[d].sum() >= one.valid[d].sum()
        newly = br.valid[d] & ~one.valid[d]  # clipped at the reference exposure, measured shorter
        assert newly.any() and np.all(br.meas[d][newly] >= 0.9 * sat)
    # the seen state's reference frame is the dataset's in both: where it measured, the merge
    # (inverse-variance weighted with far noisier short frames) stays within its noise
    both = one.valid[0] & br.valid[0]
    assert np.all(np.abs(br.meas[0][both] - one.meas[0][both]) <= 3 * np.sqrt(one.var[0][both]))


@pytest.mark.parametrize("argv, needle", [
    (["--sets", "nowhere", "--two", "0,90", "--three", "0,60,120"], "nowhere"),
    (["--two", "0,7"], "offsets"),
    (["--three", "15,60,120"], "the first 0"),
    (["--size", "128"], "--size goes with --rig-scenes"),
    (["--rig-scenes", "sphere,nowhere"], "nowhere"),
    (["--rig-scenes", "sphere", "--size", "60"], "multiple of 8"),
    (["--rig-scenes", "sphere", "--rig-poses", "a"], "--rig-poses"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    from polrig.models.continuum import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1


def _small_result(adaptive=("0.05",)) -> dict:
    """A results JSON of two sets with every trade method (distinct values per set and method)."""
    from polrig.models.continuum import TRADE_METHODS

    keys = [k for k, _, _ in TRADE_METHODS] + [f"adaptive_{t}" for t in adaptive] + ["naive1"]
    sets = {}
    for j, name in enumerate(("conductors", "rig_sphere")):
        sets[name] = {"samples": 3, "methods": {
            k: {"matrix_psnr": 30.0 + i + 0.5 * j, "fwd_l2": 0.01 * (i + 1) + 0.001 * j, "states": 1 + i % 4,
                "time_s": 0.02 + i + 0.1 * j, "coverage": 0.95, "matrix_psnr_unclipped": 40.0}
            for i, k in enumerate(keys)}}
    return {"size": 64, "sets": sets}


def test_trade_points_map_the_json_and_the_plot_draws_each(tmp_path):
    """One point per set and trade method (the seen state's variants left out), with the JSON's
    numbers; the figure draws each of them once per panel and a median per method; the PNG is
    written from the JSON alone."""
    import matplotlib.image

    from polrig.models import continuum

    result = _small_result(("0.03_max8", "0.05", "0.03"))
    pts = continuum.trade_points(result)
    n_methods = len(continuum.TRADE_METHODS) + 3
    assert len(pts) == 2 * n_methods and not any(p["method"] == "naive1" for p in pts)
    # the looser target first, the larger budget of states after
    assert [p["method"] for p in pts[-3:]] == ["adaptive_0.05", "adaptive_0.03", "adaptive_0.03_max8"]
    assert [p["label"] for p in pts[-3:]] == ["adaptive 0.05", "adaptive 0.03", "adaptive 0.03, <= 8 states"]
    for p in pts:
        m = result["sets"][p["set"]]["methods"][p["method"]]
        assert (p["time_s"], p["matrix_psnr"], p["fwd_l2"], p["states"]) == \
            (m["time_s"], m["matrix_psnr"], m["fwd_l2"], m["states"])
    fig, _ = continuum.trade_figure(result)
    for ax in fig.axes:
        scattered = sum(len(c.get_offsets()) for c in ax.collections if c.get_offsets().ndim == 2
                        and type(c).__name__ == "PathCollection")
        assert scattered == len(pts)
        assert len(ax.containers) == n_methods  # one median with its range per method
    path = tmp_path / "r.json"
    path.write_text(json.dumps(result))
    png = continuum.plot_from_json(path)
    assert png == tmp_path / "r.png"
    img = matplotlib.image.imread(png)
    assert img.shape[0] > 300 and img.shape[1] > 600 and img[..., :3].std() > 0.05


def test_trade_medians_and_ranges_over_the_sets():
    from polrig.models import continuum

    fig, _ = continuum.trade_figure(_small_result())
    ax = fig.axes[0]
    single = ax.containers[0].lines[0]  # the first method's median: single-shot
    assert single.get_xdata()[0] == pytest.approx(0.07) and single.get_ydata()[0] == pytest.approx(30.25)


def test_plot_only_cli_and_its_bad_input(tmp_path, capsys):
    from polrig.models.continuum import main

    good = tmp_path / "good.json"
    good.write_text(json.dumps(_small_result()))
    assert main(["--plot-only", str(good)]) == 0 and (tmp_path / "good.png").is_file()
    bad = tmp_path / "bad.json"
    bad.write_text('{"sets": {"x": {"methods": {}}}}')
    assert main(["--plot-only", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "not a continuum results JSON" in err and err.count("\n") == 1
    assert main(["--plot-only", str(tmp_path / "none.json")]) == 2


def test_rig_set_is_the_default_rigs_scene_at_its_size():
    """The rig's analyzer grid is its 512x512 colour sensor over the 4x4 mosaic; a rig set's
    frames are the truth seen through its polarizer state plus the sensor model's noise (chi^2
    per unclipped value near 1), one pose per sample."""
    from polrig.models import continuum
    from polrig.sensor.noise import SensorModel
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.sim.world import ideal_analyzer_images

    assert continuum.rig_size() == 128
    ds = continuum.rig_set("box", 32, (0.0, 135.0), seed=3)
    assert len(ds) == 2 and ds.shape == (32, 32) and ds["mueller"].shape == (2, 3, 3, 3, 32, 32)
    assert not np.array_equal(ds["mask"][0], ds["mask"][1])  # the box turned
    sensor = SensorModel(**ds.manifest["noise"]["sensor_model"])
    for i in range(2):
        scale = float(ds["scale"][i])
        clean = ideal_analyzer_images(np.einsum("cijhw,j->cihw", ds["mueller"][i].astype(np.float64),
                                                ds["s_in"][i].astype(np.float64))) * scale
        meas = ds["analyzer"][i].astype(np.float64) * scale
        ok = (ds["mask"][i] > 0)[None, None] & (meas < sensor.saturation_dn - 100)
        chi2 = ((meas - clean) ** 2 / sensor.variance_dn2(np.clip(clean, 0, None), DATASET_EXPOSURE_US, 1))[ok]
        assert ok.sum() > 100 and 0.7 < chi2.mean() < 1.4


def test_joint_compare_tables_each_prior(tmp_path):
    """``--joint-compare`` on 1 sample: every prior of JOINT_PRIORS at 1-4 states and the
    two-state test; at one state the joint prior's mean is the per-element prior's (the data
    and the prior are orthogonal there), so its PSNR is the same to 0.01 dB."""
    from polrig.models import continuum
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    net = SingleShotModel.load(WEIGHTS_DIR)
    if net.uncertainty is None or net.uncertainty.joint_correlation is None:
        pytest.skip("no joint prior in the shipped calibration")
    out = tmp_path / "j.md"
    res = continuum.joint_compare(tmp_path / "sets", out, count=1, sets=["seen_families"], echo=lambda *a: None)
    m = res["sets"]["seen_families"]["methods"]
    for p in continuum.JOINT_PRIORS:
        for n in range(1, 5):
            assert 0.5 < m[f"{p}_hybrid{n}"]["coverage"] <= 1.0
        assert "false_acceptance" in m[f"{p}_models"]
    assert abs(m["joint_hybrid1"]["matrix_psnr"] - m["diagonal_hybrid1"]["matrix_psnr"]) < 0.01
    text = out.read_text()
    assert "False acceptance of the two-state model test" in text and "joint_scaled" in text


@needs_weights
def test_the_adaptive_rows_stop_as_captures_do_from_the_fewest_states_on():
    """At a target every pixel meets on the network's frame, the rule takes a second state (one of
    the equiangular set's others, the cheaper) and stops, as the capture does by default; with
    ``min_states`` 1 it stops on the network's frame."""
    from polrig.models import continuum
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    net = SingleShotModel.load(WEIGHTS_DIR)
    ds = continuum.rig_set("sphere", 32, (0.0,))
    (_, sensor, i, prior), *_ = continuum.set_samples(ds, net)
    fr = continuum.sample_frames(ds, i, prior, sensor, np.random.default_rng(0), offsets=(0, 60, 120))
    first, second = continuum.adaptive(fr, 1.0)[-1]
    assert first == 0 and second in (60, 120)
    assert continuum.adaptive(fr, 1.0, min_states=1)[-1] == [0]


@needs_weights
def test_min_states_compare_takes_at_least_that_many_states(tmp_path, capsys):
    """``--min-states-compare``: each pose takes at least the given number of states (2: the
    capture's default, then 3), never more than the capture allows; at a target every pixel
    meets at once (1.0) it takes exactly that many. The tables say which is which; a bad scene
    is one line."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES
    from polrig.models.continuum import ADAPTIVE_MAX_STATES, main

    out = tmp_path / "m.md"
    assert main(["--min-states-compare", "--rig-scenes", "box", "--rig-poses", "0,90", "--size", "32",
                 "--targets", "1,0.05", "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    assert res["min_states"] == [ADAPTIVE_MIN_STATES, 3] and res["targets"] == [1.0, 0.05]
    m = res["scenes"]["box"]["methods"]
    assert res["scenes"]["box"]["samples"] == 2
    for k in res["min_states"]:
        row = m[f"0.05_min{k}"]
        assert k <= row["states"] <= ADAPTIVE_MAX_STATES and 0.0 < row["coverage"] <= 1.0 and row["time_s"] > 0
        assert m[f"1_min{k}"]["states"] == k
    assert m["0.05_min3"]["time_s"] >= m["0.05_min2"]["time_s"]
    text = out.read_text()
    assert "at least 2 states / at least 3 states" in text and "| box | 2 |" in text
    capsys.readouterr()
    assert main(["--min-states-compare", "--rig-scenes", "nosuch", "--size", "32"]) == 2
    err = capsys.readouterr().err
    assert "nosuch" in err and err.count("\n") == 1
