"""``polrig evaluate`` (models.evaluate) end to end on a tiny generated set with the shipped
graphs: every method and metric is present and finite, the tables carry the lit-pixel
realizability columns, and the metric helpers agree with their definitions."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from models import evaluate as ev  # noqa: E402
from polrig.mueller import polarizer_stokes  # noqa: E402
from sim.dataset import generate_dataset  # noqa: E402


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    data = tmp_path_factory.mktemp("eval") / "data"
    generate_dataset(data, count=4, width=32, seed=11, holdout=True, shard_size=4, progress=False)
    return ev.evaluate(data, echo=lambda s: None), data


def test_every_method_and_metric_is_finite(result):
    res, _ = result
    assert set(res["methods"]) == set(ev.METHODS) and res["samples"] >= 1
    for name, metrics in res["methods"].items():
        for key in ("matrix_psnr", "render_psnr", "fwd_l2", "gk_before", "psd_after", "gk_lit"):
            assert np.isfinite(metrics[key]) or key == "gk_lit", (name, key)
    assert res["methods"]["reference4"]["fwd_l2"] < res["methods"]["pipnet_pbrdf"]["fwd_l2"]


def test_tables_and_json(result, tmp_path):
    res, _ = result
    ev.write_results(res, tmp_path / "t.md")
    md = (tmp_path / "t.md").read_text()
    assert "GK pass (lit)" in md and md.count("| Full model (PIPNet") == 2 and md.count("mirror-averaged") == 4
    assert json.loads((tmp_path / "t.json").read_text())["samples"] == res["samples"]


def test_forward_l2_of_a_scaled_matrix_is_the_scale_error():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(3, 3, 3, 8, 8))
    mask = np.ones((8, 8), bool)
    m = ev._sample_metrics((1.1 * truth).astype(np.float32), truth.astype(np.float32), mask,
                           polarizer_stokes(0.3), rng, 50)
    assert m["fwd_l2"] == pytest.approx(0.1, rel=1e-5)
