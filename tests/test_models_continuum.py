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
    # the adaptive capture at its two targets: between one and four states, a time that grows with them
    for t in continuum.ADAPTIVE_TARGETS:
        a = m[f"adaptive_{t:g}"]
        assert 1 <= a["states"] <= 4 and 0.5 < a["coverage"] <= 1.0
        assert m["single"]["time_s"] <= a["time_s"] <= m["hybrid4"]["time_s"] + 10.0
    assert m["single"]["time_s"] < m["hybrid2"]["time_s"] < m["hybrid4"]["time_s"]
    assert "adaptive 0.05" in text and "acquisition time" in text


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


@pytest.mark.parametrize("argv, needle", [
    (["--sets", "nowhere", "--two", "0,90", "--three", "0,60,120"], "nowhere"),
    (["--two", "0,7"], "offsets"),
    (["--three", "15,60,120"], "the first 0"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    from polrig.models.continuum import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1
