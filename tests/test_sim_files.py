"""Truth files, the reference round trip, the dataset shards and the ``polrig sim`` CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polrig.cli import main
from polrig.errors import ConfigError
from polrig.formats.exr import read_mueller_exr
from polrig.formats.rawio import read_raw
from polrig.sensor.noise import SensorModel
from polrig.sim import create_sim_rig
from polrig.sim.dataset import (
    SHARD_ARRAYS,
    families_for,
    generate_dataset,
    load_shard,
    make_sample,
    shard_name,
)
from polrig.sim.scene import FAMILIES, HOLDOUT_FAMILIES
from polrig.sim.truth import read_truth, write_truth
from polrig.sim.world import ideal_analyzer_images
from polrig.solve.reference import forward_measurements, solve_reference

VIRTUAL = float("inf")


def test_reference_solve_recovers_the_truth_from_noise_free_analyzer_images():
    """Noise off: four states through the analyzers, polrig.solve.reference's weighted solve of the
    16 samples per pixel gives the truth Mueller image to 1e-4 relative."""
    rig = create_sim_rig({"scene": "checker_sphere", "size": (64, 48), "noise": False,
                          "clock_speed": VIRTUAL})
    w = rig.world
    states = (0.0, 45.0, 90.0, 135.0)
    s_in = np.stack([rig.truth.incident_stokes(a) for a in states])
    meas = []
    for a in states:
        rig.stage.move_to(a)
        meas.append(w.analyzer_images(w.turntable_angle_deg(), rig.stage.position_deg(),
                                      rig.camera.exposure_us))
    meas = np.stack(meas).astype(np.float64)  # (N, C, 4, H, W)
    model = w.sensor.model
    var = model.variance_dn2(meas, rig.camera.exposure_us)
    res = solve_reference(s_in, meas, var, dtype=np.float64)
    gt = rig.truth.ground_truth()
    t = gt["mueller"].astype(np.float64)
    lit = gt["lit"]
    scale = np.abs(t[..., lit]).max()
    assert np.abs(res.mueller[..., lit] - t[..., lit]).max() / scale < 1e-4
    # and the truth predicts the measurements through the reference forward model
    np.testing.assert_allclose(forward_measurements(t, s_in), meas, rtol=1e-5,
                               atol=1e-6 * np.abs(meas).max())


def test_truth_files_round_trip(tmp_path):
    rig = create_sim_rig({"scene": "multi", "size": (64, 48), "clock_speed": VIRTUAL})
    rig.camera.set_roi(32, 24, 2, 4)
    rig.light.set_level(0.5)
    rig.turntable.move_to(20.0)
    gt = rig.truth.ground_truth()
    files = write_truth(tmp_path, "pose1", gt, rig.truth.rig_parameters(),
                        capture={"frames": ["a.png"]})
    assert set(files) == {"npz", "exr", "json"}
    index, arrays = read_truth(tmp_path, "pose1")
    assert index["format"] == "polrig-sim-truth" and index["version"] == 1
    cap = index["captures"][0]
    assert cap["roi"] == [32, 24, 2, 4] and cap["light_level"] == 0.5
    assert cap["turntable_deg"] == pytest.approx(20.0) and cap["frames"] == ["a.png"]
    for k in ("mueller", "mask", "normal", "kd", "alpha", "wi", "wo"):
        np.testing.assert_array_equal(arrays[k], gt[k])
    exr = read_mueller_exr(tmp_path / files["exr"])
    np.testing.assert_array_equal(exr.mueller, gt["mueller"])
    np.testing.assert_array_equal(exr.extra["mask"], gt["mask"].astype(np.float32))
    rp = index["rig"]
    assert rp["generator"]["stage_zero_offset_deg"] == 1.7
    assert len(rp["light_position_m"]) == 3 and "analyzer_summary" in rp["sensor"]
    assert rp["camera"]["width"] == 64
    # a second capture is added, the same name replaced
    write_truth(tmp_path, "pose2", gt, rp, exr=False)
    write_truth(tmp_path, "pose1", gt, rp, exr=False)
    names = [c["name"] for c in json.loads((tmp_path / "truth.json").read_text())["captures"]]
    assert sorted(names) == ["pose1", "pose2"]


def test_hidden_parameter_overrides_reach_the_truth():
    rig = create_sim_rig({"size": (32, 32), "clock_speed": VIRTUAL,
                          "hidden": {"stage_zero_offset_deg": -4.0, "extinction_ratio": 50.0,
                                     "light_position_m": [0.1, -0.4, 0.3]}})
    p = rig.truth.rig_parameters()
    assert p["generator"] == {"stage_zero_offset_deg": -4.0, "extinction_ratio": 50.0}
    assert p["light_position_m"] == [0.1, -0.4, 0.3]
    s = rig.truth.incident_stokes(10.0)
    assert np.rad2deg(0.5 * np.arctan2(s[2], s[1])) == pytest.approx(6.0)


def test_dataset_sample_is_consistent():
    s = make_sample(3, seed=7, width=48, height=40)
    mask = s["mask"].astype(bool)
    assert mask.any() and s["analyzer"].shape == (3, 4, 40, 48)
    assert s["mueller"].shape == (3, 3, 3, 40, 48) and int(s["family"]) in families_for(False)
    n = s["normal"][:, mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=0), 1.0, atol=1e-5)
    assert (n[2] < 0.05).all()  # normals face the camera (camera frame, Z forward)
    # the analyzer images are the noisy forward model of the truth, same units
    clean = ideal_analyzer_images(np.einsum("cijhw,j->cihw", s["mueller"], s["s_in"]))
    model = SensorModel(full_well_e=10500.0, read_noise_e=2.3, bit_depth=12)
    lin = mask & (clean.max(axis=(0, 1)) * s["scale"] < 0.9 * model.clip_dn)
    resid = (s["analyzer"] - clean)[:, :, lin] * s["scale"]
    sigma = np.sqrt(model.variance_dn2(clean[:, :, lin] * s["scale"], 10000.0))
    assert np.abs(np.mean(resid / sigma)) < 0.1 and 0.8 < np.std(resid / sigma) < 1.2
    # deterministic per index
    s2 = make_sample(3, seed=7, width=48, height=40)
    np.testing.assert_array_equal(s["analyzer"], s2["analyzer"])
    assert 0.0 < np.percentile(s["analyzer"][:, :, mask], 99.5) <= 1.0 + 1e-6


def test_dataset_shards_resume_and_holdout(tmp_path):
    out = tmp_path / "ds"
    r = generate_dataset(out, count=5, width=24, seed=2, shard_size=2, progress=False,
                         max_shards=1)
    assert r == {"written": 1, "skipped": 0}
    first = (out / shard_name(0)).stat().st_mtime_ns
    (out / shard_name(1)).write_bytes(b"PK\x03\x04 truncated")  # a crashed half shard
    r = generate_dataset(out, count=5, width=24, seed=2, shard_size=2, progress=False)
    assert r == {"written": 2, "skipped": 1}
    assert (out / shard_name(0)).stat().st_mtime_ns == first
    man = json.loads((out / "manifest.json").read_text())
    assert man["n_shards"] == 3 and man["count"] == 5 and man["width"] == 24
    shard = load_shard(out / shard_name(2))
    assert set(shard) == set(SHARD_ARRAYS) and len(shard["index"]) == 1
    for k, (shape, dtype) in SHARD_ARRAYS.items():
        assert shard[k].dtype == np.dtype(dtype), k
    assert shard["mueller"].shape == (1, 3, 3, 3, 24, 24)
    # the same samples whichever order the shards were made in
    again = make_sample(4, seed=2, width=24, height=24)
    np.testing.assert_array_equal(shard["analyzer"][0], again["analyzer"])
    with pytest.raises(ConfigError, match="different dataset"):
        generate_dataset(out, count=6, width=24, seed=2, shard_size=2, progress=False)
    hold = tmp_path / "hold"
    generate_dataset(hold, count=4, width=24, seed=2, shard_size=4, progress=False,
                     holdout=True)
    fams = {FAMILIES[f] for f in load_shard(hold / shard_name(0))["family"]}
    assert fams <= set(HOLDOUT_FAMILIES)
    assert json.loads((hold / "manifest.json").read_text())["holdout"] is True


def test_cli_render_writes_frames_and_truth(tmp_path, capsys):
    out = tmp_path / "render"
    rc = main(["sim", "render", "--scene", "box", "--size", "64x48", "--states", "0,60,120",
               "--pose", "15", "--seed", "3", "--out", str(out)])
    assert rc == 0
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 3
    f = read_raw(pngs[1])
    assert f.raw.dtype == np.uint16 and f.raw.shape == (48, 64)
    assert f.meta.pixel_format == "Mono16" and f.meta.extra["sim"]["stage_deg"] == 60.0
    index, arrays = read_truth(out)
    cap = index["captures"][0]
    assert [fr["stage_deg"] for fr in cap["frames"]] == [0.0, 60.0, 120.0]
    assert cap["turntable_deg"] == pytest.approx(15.0)
    assert arrays["mueller"].shape == (3, 3, 3, 48, 64)
    assert "in " in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:  # argparse: usage error, exit code 2
        main(["sim", "render", "--scene", "teapot", "--out", str(out)])
    assert exc.value.code == 2
    assert main(["sim", "render", "--size", "63x48", "--out", str(out)]) == 2  # ConfigError


def test_cli_dataset(tmp_path, capsys):
    out = tmp_path / "ds"
    args = ["sim", "dataset", "--count", "3", "--size", "16", "--seed", "1", "--shard-size",
            "2", "--quiet", "--out", str(out)]
    assert main(args) == 0
    assert main(args) == 0
    assert "0 shard(s) written, 2 already complete" in capsys.readouterr().out


def test_cli_dataset_stage_zero_axes_camera_up(tmp_path):
    """``--stage-zero-axes camera-up`` writes version-1 samples (the shipped model's training
    set): every axis is the camera's up direction made perpendicular to the illumination."""
    out = tmp_path / "ds"
    assert main(["sim", "dataset", "--count", "3", "--size", "16", "--seed", "1", "--quiet",
                 "--stage-zero-axes", "camera-up", "--out", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["frames"]["stage_zero_axes"] == "camera-up"
    with np.load(out / "shard-00000.npz") as z:
        axes = z["stage_zero_axis"]
    assert np.all(axes[:, 1] < -0.8)  # close to -Y (up) in the camera frame


def test_dataset_families_are_a_subset_of_one_side(tmp_path, capsys):
    """``--families`` narrows the families drawn; a held-out family never enters a training set,
    and a folder made with other families is not resumed."""
    assert families_for(False, ["torus", "sphere"]) == (FAMILIES.index("sphere"),
                                                        FAMILIES.index("torus"))
    for bad in (["heightfield"], ["teapot"], []):
        with pytest.raises(ConfigError, match="training families must be"):
            families_for(False, bad)
    with pytest.raises(ConfigError, match="held-out families must be"):
        families_for(True, ["blob"])
    out = tmp_path / "ds"
    args = ["sim", "dataset", "--count", "4", "--size", "24", "--seed", "3", "--shard-size",
            "4", "--quiet", "--families", "blob,torus", "--out", str(out)]
    assert main(args) == 0
    fams = {FAMILIES[f] for f in load_shard(out / shard_name(0))["family"]}
    assert fams <= {"blob", "torus"}
    assert json.loads((out / "manifest.json").read_text())["families_present"] == ["blob", "torus"]
    assert main(args[:-4] + ["--families", "blob", "--out", str(out)]) == 2  # another dataset
    assert "families_present" in capsys.readouterr().err
    assert main(args[:-4] + ["--families", "plane", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()  # rejected before anything was written
