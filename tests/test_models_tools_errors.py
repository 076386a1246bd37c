"""The model tools on bad input: ``polrig infer --sigma`` without a calibration of its graph,
``python -m polrig.models.uncertainty_fit`` and ``python -m polrig.models.diagnose`` with missing folders, sets
without a lit sample, absurd limits, damaged or foreign calibration files and unwritable
outputs. One line naming the problem, exit 2, before the work."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from polrig.cli import main  # noqa: E402
from polrig.models.runtime import WEIGHTS_DIR  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """A simulated 128x64 colour frame with its sidecar."""
    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "128x64", "--states", "0", "--no-exr", "--out", str(out)]) == 0
    return next(out.glob("*_state00.png"))


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    """A held-out set of 8 scenes (sample 5 unlit) and one of that unlit sample alone."""
    from polrig.models.data import load_dataset, write_dataset

    root = tmp_path_factory.mktemp("sets")
    generate_dataset(root / "lit", count=8, width=32, seed=0, holdout=True, shard_size=4, progress=False)
    ds = load_dataset(root / "lit")
    write_dataset(root / "dark", ds.subset([5]).arrays, ds.manifest)
    return root / "lit", root / "dark"


def _weights(tmp_path, calibration: str | None):
    """A copy of the shipped graphs with ``calibration``: "none", "broken", "other" (another
    graph's), or "same" (the shipped file)."""
    wd = tmp_path / "w"
    wd.mkdir()
    for name in ("single_shot.onnx", "direct.onnx", "model.json"):
        shutil.copy(WEIGHTS_DIR / name, wd / name)
    if calibration == "broken":
        (wd / "uncertainty.json").write_text("{bad")
    elif calibration == "other":
        data = json.loads((WEIGHTS_DIR / "uncertainty.json").read_text())
        data["graph_sha256"] = "0" * 64
        (wd / "uncertainty.json").write_text(json.dumps(data))
    elif calibration == "same":
        shutil.copy(WEIGHTS_DIR / "uncertainty.json", wd / "uncertainty.json")
    return wd


@pytest.mark.parametrize("calibration, needle", [("none", "no uncertainty.json in"),
                                                 ("broken", "not a readable uncertainty calibration"),
                                                 ("other", "belongs to another graph")])
def test_infer_sigma_without_a_calibration_of_the_graph_is_refused(frame, tmp_path, capsys, calibration, needle):
    wd = _weights(tmp_path, calibration)
    argv = ["infer", str(frame), "--state-deg", "0", "--weights", str(wd)]
    capsys.readouterr()
    assert main(argv + ["--sigma", "--out", str(tmp_path / "s.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "python -m polrig.models.uncertainty_fit" in err and "\n" not in err
    assert not (tmp_path / "s.exr").exists()
    assert main(argv + ["--out", str(tmp_path / "plain.exr")]) == 0  # without --sigma nothing is missing


def _tool(module: str, capsys, *argv) -> tuple[int, str]:
    import importlib

    try:
        code = importlib.import_module(f"models.{module}").main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    return code, capsys.readouterr().err.strip()


@pytest.mark.parametrize("case", ["no-weights", "no-data", "dark", "dark-check", "limit-0", "limit-negative",
                                  "json-nodir", "joint-no-data"])
def test_diagnose_and_uncertainty_bad_input_is_one_line(sets, tmp_path, capsys, case):
    lit, dark = sets
    module, argv, needle = {
        "no-weights": ("uncertainty_fit", ["--weights", tmp_path / "nowhere", "--check", lit], "nowhere not found"),
        "no-data": ("diagnose", ["--data", tmp_path / "nowhere"], "nowhere not found"),
        "dark": ("diagnose", ["--data", dark], "no sample with a lit object pixel"),
        "dark-check": ("uncertainty_fit", ["--check", dark], "no sample with a lit object pixel"),
        "limit-0": ("diagnose", ["--data", lit, "--limit", "0"], "--limit"),
        "limit-negative": ("diagnose", ["--data", lit, "--limit", "-1"], "--limit"),
        "json-nodir": ("diagnose", ["--data", lit, "--json", tmp_path / "nodir" / "x.json"], "nodir"),
        "joint-no-data": ("uncertainty_fit", ["--joint", "--check", lit], "--joint needs --data"),
    }[case]
    code, err = _tool(module, capsys, *argv)
    assert code == 2 and needle in err.splitlines()[-1] and "Traceback" not in err


def test_a_limit_is_the_first_samples_or_refused():
    from polrig.models.data import load_dataset

    with pytest.raises(ValueError, match="limit"):
        load_dataset(".", -1)  # a negative slice used to drop the last sample silently


@pytest.mark.parametrize("calibration, needle", [("broken", "not a readable uncertainty calibration"),
                                                 ("other", "belongs to another graph"),
                                                 ("none", "no uncertainty.json")])
def test_uncertainty_says_why_a_calibration_does_not_apply(sets, tmp_path, capsys, calibration, needle):
    lit, _ = sets
    wd = _weights(tmp_path, calibration)
    code, err = _tool("uncertainty_fit", capsys, "--weights", wd, "--check", lit)
    assert code == 2 and needle in err and "--write" in err and "\n" not in err


def test_uncertainty_checks_a_matching_calibration_and_diagnose_skips_the_unlit_sample(sets, tmp_path, capsys):
    from polrig.models.diagnose import diagnose

    lit, _ = sets
    wd = _weights(tmp_path, "same")
    code, err = _tool("uncertainty_fit", capsys, "--weights", wd, "--check", lit)
    assert code == 0, err
    result = diagnose(lit, wd, echo=lambda s: None)
    assert result["all"]["samples"] == 7 and np.isfinite(result["all"]["full"])
