"""Two model sizes, a user's trade (issue 32, item 3): ``polrig.models.sizes``.

The small size is the shipped ``models/weights`` as before; a large size lives in
``models/weights/large`` once a GPU lease ships it. ``--model-size auto`` (the default) takes
the small one on a CPU; asking for a size not shipped is one line naming the lease script; the
size, training hardware and minutes are recorded in every result header and in the manifest.
Where a large model is needed, the tests ship one of their own: a copy of the small graphs whose
``model.json`` says ``large`` (the same files under another name; what is checked is the choice
and the record, not the accuracy)."""

from __future__ import annotations

import fnmatch
import json
import pathlib
import shutil
import tomllib

import pytest

from polrig.cli import main
from polrig.formats.exr import read_exr
from polrig.models import sizes

from test_cli_capture import MODEL_INSTALLED, sim_config

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture
def large_shipped(tmp_path, monkeypatch):
    """A large model shipped in a folder of the test's: the small graphs, ``model.json`` saying
    ``large``, trained 8 minutes on an H200 (as a lease would record it)."""
    folder = tmp_path / "large"
    shutil.copytree(sizes.WEIGHTS_ROOT, folder, ignore=shutil.ignore_patterns("large", "*.pt", "*.csv"))
    meta = json.loads((folder / "model.json").read_text())
    meta["size"] = "large"
    meta["training"] = {"hardware": "NVIDIA H200 (test)", "lineage": [{"network": "pipnet", "seconds": 480.0}]}
    (folder / "model.json").write_text(json.dumps(meta))
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "large", folder)
    return folder


@pytest.fixture
def large_missing(tmp_path, monkeypatch):
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "large", tmp_path / "no-large")


# -- the choice ------------------------------------------------------------------------------------
def test_auto_takes_small_on_a_cpu_and_large_on_cuda_only_where_shipped(large_missing):
    assert sizes.choose_size("auto", on_cuda=False) == "small"
    assert sizes.choose_size("auto", on_cuda=True) == "small"  # large not shipped
    assert sizes.choose_size("small", on_cuda=True) == "small"
    assert sizes.shipped_sizes() == ("small",)


def test_auto_takes_large_on_cuda_when_shipped(large_shipped):
    assert sizes.choose_size("auto", on_cuda=True) == "large"
    assert sizes.choose_size("auto", on_cuda=False) == "small"
    assert sizes.choose_size("large", on_cuda=False) == "large"  # asked for by name: also on a CPU
    assert sizes.shipped_sizes() == ("small", "large")


def test_a_size_not_shipped_is_one_line_naming_the_lease(large_missing):
    with pytest.raises(sizes.ModelSizeUnavailable) as exc:
        sizes.choose_size("large", on_cuda=True)
    text = str(exc.value)
    assert "\n" not in text and "not shipped yet" in text and "benchmarks/gpu_train.sh" in text
    with pytest.raises(sizes.ConfigError, match="must be one of auto, small, large"):
        sizes.size_folder("huge")


def test_the_record_comes_from_model_json(large_shipped, tmp_path):
    small = sizes.model_record(sizes.WEIGHTS_ROOT)
    meta = json.loads((sizes.WEIGHTS_ROOT / "model.json").read_text())
    lineage_s = sum(r["seconds"] for r in meta["training"]["lineage"])
    assert small == {"size": "small", "width": meta["width"], "training_hardware": meta["training"]["hardware"],
                     "training_minutes": round(lineage_s / 60, 1)}
    assert 100 < small["training_minutes"] < 120  # the model card's "just under two hours"
    assert sizes.model_record(large_shipped) == {"size": "large", "width": meta["width"],
                                                 "training_hardware": "NVIDIA H200 (test)",
                                                 "training_minutes": 8.0}
    # a folder of the user's, exported without a size or hardware: recorded as unknown
    own = tmp_path / "own"
    own.mkdir()
    (own / "model.json").write_text(json.dumps({"width": 8, "training": {"train_seconds": {"pipnet": 30.0,
                                                                                          "pmmnet": 30.0}}}))
    assert sizes.model_record(own) == {"size": None, "width": 8, "training_hardware": "not recorded",
                                       "training_minutes": 1.0}


def test_package_data_ships_every_size_and_no_checkpoint():
    """The wheel's patterns (``pyproject.toml``) take each size's graphs and JSON files, and not
    a training checkpoint (``tests/test_wheel.py`` checks the built wheel itself)."""
    patterns = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["polrig.models"]
    for size, folder in {"small": REPO / "models" / "weights", "large": REPO / "models" / "weights" / "large"}.items():
        rel = folder.relative_to(REPO / "models").as_posix()
        for name in ("single_shot.onnx", "single_shot_frame.onnx", "model.json", "uncertainty.json"):
            assert any(fnmatch.fnmatchcase(f"{rel}/{name}", p) for p in patterns), (size, name)
        assert not any(fnmatch.fnmatchcase(f"{rel}/checkpoint.pt", p) for p in patterns)


# -- the route and the shells ----------------------------------------------------------------------
def test_the_route_opens_the_size_asked_for(large_shipped):
    from polrig.app.single_shot import SingleShot

    small = SingleShot.open("cpu")
    assert small.model.weights_dir == sizes.WEIGHTS_ROOT and small.model_header()["model_size"] == "small"
    large = SingleShot.open("cpu", size="large")
    assert large.model.weights_dir == large_shipped
    assert large.model_header() == {"model_size": "large", "model_training": {
        "width": 16, "training_hardware": "NVIDIA H200 (test)", "training_minutes": 8.0}}
    assert SingleShot.open("cpu", size="auto") is small  # a CPU: the small one, the same loaded object


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "64x64", "--states", "0", "--no-exr", "--out", str(out)]) == 0
    return next(out.glob("*_state00.png"))


def test_infer_records_the_size_and_refuses_one_not_shipped(frame, tmp_path, capsys, large_missing):
    out = tmp_path / "m.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(out), "--device", "cpu"]) == 0
    meta = read_exr(out).metadata
    assert meta["model_size"] == "small"
    assert meta["model_training"] == {k: v for k, v in sizes.model_record(sizes.WEIGHTS_ROOT).items() if k != "size"}
    capsys.readouterr()
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(tmp_path / "l.exr"),
                 "--model-size", "large"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the large model is not shipped yet" in err[0] and "gpu_train.sh" in err[0]
    assert not (tmp_path / "l.exr").exists()


@pytest.mark.skipif(not MODEL_INSTALLED, reason="single-shot model not installed")
def test_capture_and_reconstruct_record_the_model_in_header_and_manifest(tmp_path, large_shipped):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--states", "0", "--config", str(cfg),
                 "--out", str(out), "--no-progress", "--device", "cpu"]) == 0
    manifest = json.loads((out / "session.json").read_text())
    cap = manifest["captures"][0]
    assert cap["model"]["size"] == "small" and cap["model"]["training_minutes"] > 100
    assert read_exr(out / cap["name"] / "mueller.exr").metadata["model_size"] == "small"
    # the same session reconstructed with the large model: the revision's result says so
    assert main(["reconstruct", str(out), "--model-size", "large", "--device", "cpu", "--no-progress"]) == 0
    manifest = json.loads((out / "session.json").read_text())
    (name, rev), = manifest["captures"][0]["revisions"].items()
    assert rev["model"] == {"size": "large", "width": 16, "training_hardware": "NVIDIA H200 (test)",
                            "training_minutes": 8.0}
    meta = read_exr(out / rev["files"]["mueller"]["path"]).metadata
    assert meta["model_size"] == "large" and meta["model_training"]["training_hardware"] == "NVIDIA H200 (test)"


@pytest.mark.skipif(not MODEL_INSTALLED, reason="single-shot model not installed")
def test_capture_of_a_size_not_shipped_is_refused_before_anything_is_written(tmp_path, capsys, large_missing):
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--states", "0", "--out", str(out),
                 "--no-progress", "--model-size", "large"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not shipped yet" in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_a_reference_capture_records_no_model(tmp_path):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--states", "0,60,120", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    cap = json.loads((out / "session.json").read_text())["captures"][0]
    assert "model" not in cap
    assert "model_size" not in read_exr(out / cap["name"] / "mueller.exr").metadata


# -- the benchmark's table -------------------------------------------------------------------------
def test_the_benchmark_shows_both_sizes_and_waits_for_the_large_one(large_missing):
    from benchmarks.bench_single_shot import SIZE_CASES, WAITING, sizes_table

    measured = {"rounds": 1, "provider": "CPUExecutionProvider", "threads": 2,
                "medians_s": {"small": {c[0]: 0.05 for c in SIZE_CASES}}}
    rows = {line.split("|")[1].strip(): line for line in sizes_table(measured).splitlines() if line.startswith("| ")}
    assert "37.26 / 0.1073" in rows["small"] and "| 50 | 50 |" in rows["small"]  # committed accuracy, measured speed
    assert rows["large"].count(WAITING) == 6


def test_the_benchmark_times_a_shipped_large_size(large_shipped, monkeypatch):
    """Every shipped size is timed and tabled: here the table's live-view frame (512x512) and a
    256x256 mono frame instead of its full colour sensor (2448x2048, about 9 s of the test's
    model runs; what is checked does not depend on the frame's size)."""
    from benchmarks import bench_single_shot as bench

    assert len(bench.SIZE_CASES) == 2
    assert bench.SIZE_CASES[0][1] == (512, 512) and bench.SIZE_CASES[1][1] == bench.FULL
    monkeypatch.setattr(bench, "SIZE_CASES", (bench.SIZE_CASES[0],
                                              ("256x256 mono superpixel (128x128)", (256, 256), bench.MONO, [])))
    measured = bench.size_speed(1, 1, "cpu")
    assert set(measured["medians_s"]) == {"small", "large"}
    assert all(set(t) == {c[0] for c in bench.SIZE_CASES} and all(v > 0 for v in t.values())
               for t in measured["medians_s"].values())
    large = next(line for line in bench.sizes_table(measured).splitlines() if line.startswith("| large"))
    assert "NVIDIA H200 (test)" in large and "| 8.0 |" in large and "not measured" in large  # no accuracy yet


def test_auto_asks_onnxruntime_for_cuda_only_where_a_large_model_is_shipped(large_shipped, monkeypatch):
    import onnxruntime as ort

    from polrig.app import single_shot
    from polrig.models import devices

    monkeypatch.setattr(ort, "get_available_providers", lambda: [devices.CUDA, devices.CPU])
    monkeypatch.setattr(devices, "cuda_device_count", lambda: 1)
    assert single_shot._runs_on_cuda("auto") and single_shot._runs_on_cuda("cuda")
    assert not single_shot._runs_on_cuda("cpu")
    monkeypatch.setattr(devices, "cuda_device_count", lambda: 0)  # the gpu extra, no GPU: the CPU runs it
    assert not single_shot._runs_on_cuda("auto")
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "large", large_shipped / "gone")
    monkeypatch.setattr(ort, "get_available_providers", lambda: pytest.fail("asked without a large model"))
    assert not single_shot._runs_on_cuda("auto")
