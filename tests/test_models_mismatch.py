"""``python -m polrig.models.mismatch``: the evaluation tables plus the sigma checks on a set with
materials outside the Baek family, end to end on a tiny set; one-line errors."""

from __future__ import annotations

import json

import pytest

from polrig.models.runtime import WEIGHTS_DIR
from polrig.models.uncertainty import FILE_NAME

pytestmark = pytest.mark.skipif(not (WEIGHTS_DIR / "single_shot.onnx").is_file()
                                or not (WEIGHTS_DIR / FILE_NAME).is_file(), reason="no shipped weights")


def test_tables_coverage_per_kind_and_sigma_only(tmp_path, capsys):
    from polrig.models import mismatch
    from polrig.sim.dataset import generate_dataset

    data = tmp_path / "mix"
    generate_dataset(data, count=6, width=64, seed=31, material_mix="heldout", progress=False)
    out = tmp_path / "res" / "mm.md"
    res = mismatch.run(data, out, limit=6)
    saved = json.loads(out.with_suffix(".json").read_text())
    assert saved["samples"] == res["samples"] >= 1
    sig = saved["sigma"]
    assert 0.0 < sig["plain"]["within_2sigma"] <= 1.0 and 0.0 < sig["mirror_averaged"]["within_2sigma"] <= 1.0
    assert set(sig["per_kind"]) <= {"film", "depolarizing"}
    assert sum(k["samples"] for k in sig["per_kind"].values()) == res["samples"]
    assert float(sig["misfit"]["0.5"]) <= float(sig["misfit"]["0.99"])
    assert 0.0 <= sig["beyond_calibration_misfit"] <= 1.0
    assert saved["truth_realizability"]["gk_lit"] == pytest.approx(1.0, abs=0.02)  # the truth is physical
    text = out.read_text()
    assert "materials `heldout`" in text and "within 2 sigma" in text and "| Full model" in text
    # the sigma checks again on the same tables; refused on another set
    again = mismatch.run(data, out, sigma_only=True)
    assert again["methods"] == saved["methods"] and again["sigma"]["plain"] == sig["plain"]
    other = tmp_path / "other"
    generate_dataset(other, count=2, width=64, seed=32, progress=False)
    from polrig.errors import ConfigError
    with pytest.raises(ConfigError, match="another set"):
        mismatch.run(other, out, sigma_only=True)
    row = mismatch.summary_table({"mix": saved}).splitlines()[-1]
    assert row.startswith("| mix | ") and f"{saved['methods']['full']['fwd_l2']:.3f}" in row


@pytest.mark.parametrize("argv, needle", [
    (["--data", "nowhere", "--out", "x.md"], "nowhere"),
    (["--summary", "no-equals-sign"], "LABEL=PATH"),
    (["--summary", "a=missing.json"], "missing.json"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    from polrig.models.mismatch import main

    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1
