"""``polrig evaluate`` (polrig.models.evaluate) end to end on a tiny generated set with the shipped
graphs: every method and metric is present and finite, the tables carry the lit-pixel
realizability columns, and the metric helpers agree with their definitions."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from polrig.models import evaluate as ev  # noqa: E402
from polrig.optics.mueller import polarizer_stokes  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402


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
    assert md.startswith("# Single-shot Mueller reconstruction: evaluation on a held-out set\n")
    assert "Held-out set: " in md and res["holdout"] is True


def test_a_set_of_the_training_families_is_not_called_held_out(result, tmp_path):
    """The report says what the set is, from its manifest: a set made without ``--holdout`` holds
    the training families."""
    res, _ = result
    ev.write_results(dict(res, holdout=False), tmp_path / "t.md")
    md = (tmp_path / "t.md").read_text()
    assert "held-out" not in md.split("\n")[0] and "Held-out set" not in md
    assert "Set of the training families: " in md


def test_forward_l2_of_a_scaled_matrix_is_the_scale_error():
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(3, 3, 3, 8, 8))
    mask = np.ones((8, 8), bool)
    m = ev._sample_metrics((1.1 * truth).astype(np.float32), truth.astype(np.float32), mask,
                           polarizer_stokes(0.3), rng, 50)
    assert m["fwd_l2"] == pytest.approx(0.1, rel=1e-5)


# ----------------------------------------------------------------------------- lit samples, checks

@pytest.fixture(scope="module")
def with_unlit(tmp_path_factory):
    """8 held-out samples of 32x32 (seed 0): sample 5 has its object wholly in shadow."""
    from polrig.models.data import lit_samples, load_dataset

    data = tmp_path_factory.mktemp("unlit") / "data"
    generate_dataset(data, count=8, width=32, seed=0, holdout=True, shard_size=4, progress=False)
    ds = load_dataset(data)
    unlit = [i for i in range(len(ds)) if i not in lit_samples(ds)]
    assert unlit == [5]  # the set this test is about: one unlit sample among lit ones
    return data, ds


def _expected_variance(ds, x: float) -> float:
    """The simulator's own noise (manifest sensor model, EMVA 1288) at clean normalised level ``x``,
    averaged over the lit samples: ``var = x / (g scale) + ((mu_d + sigma_read^2) / g^2 + 1/12) / scale^2``."""
    from polrig.models.data import lit_samples
    from polrig.sensor.noise import SensorModel

    noise = ds.manifest["noise"]
    sm = SensorModel(**noise["sensor_model"])
    g = sm.gain_e_per_dn
    c0 = (float(sm.dark_electrons(noise["exposure_us_for_dark"])) + sm.read_noise_e ** 2) / g ** 2 + 1 / 12
    scale = ds["scale"][lit_samples(ds)].astype(np.float64)
    return float(np.mean(x / (g * scale) + c0 / scale ** 2))


def test_noise_model_leaves_out_unlit_samples_and_matches_the_simulator(with_unlit):
    from polrig.models.data import lit_samples

    _, ds = with_unlit
    a, b = ev.fit_noise_model(ds)
    assert (a, b) == ev.fit_noise_model(ds.subset(lit_samples(ds)))  # the unlit sample changes nothing
    for x in (0.05, 0.2, 0.5):  # before: a = 0.29, thousands of times the sensor's noise
        assert a + b * x == pytest.approx(_expected_variance(ds, x), rel=0.25), x


def test_evaluate_skips_the_unlit_sample(with_unlit):
    data, _ = with_unlit
    res = ev.evaluate(data, limit=6, echo=lambda s: None)  # samples 0..5, the last one unlit
    assert (res["samples"], res["skipped_unlit"]) == (5, 1)


def test_a_set_without_a_lit_sample_is_refused(with_unlit, tmp_path, capsys):
    from polrig.cli import main
    from polrig.models.data import write_dataset

    _, ds = with_unlit
    dark = tmp_path / "dark"
    write_dataset(dark, ds.subset([5]).arrays, ds.manifest)
    assert main(["evaluate", "--data", str(dark), "--out", str(tmp_path / "r.md")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no sample with a lit object pixel" in err and "\n" not in err
    assert not (tmp_path / "r.md").exists() and not (tmp_path / "r.json").exists()


def test_images_off_the_networks_size_multiple_are_refused(with_unlit, tmp_path, capsys):
    from polrig.cli import main
    from polrig.models.data import write_dataset

    _, ds = with_unlit
    crop = {k: (v[..., :28, :28] if v.ndim >= 3 and v.shape[-2:] == (32, 32) else v) for k, v in ds.arrays.items()}
    write_dataset(tmp_path / "odd", crop, ds.manifest)
    assert main(["evaluate", "--data", str(tmp_path / "odd"), "--out", str(tmp_path / "r.md")]) == 2
    assert "multiples of 8" in capsys.readouterr().err


@pytest.mark.parametrize("out, needle", [("folder", "give a Markdown file name"), ("r.json", "ending in .md"),
                                         ("afile/r.md", "is not a folder"), ("r.txt", "ending in .md")])
def test_out_is_checked_before_the_evaluation(with_unlit, tmp_path, capsys, monkeypatch, out, needle):
    from polrig.cli import main

    data, _ = with_unlit
    (tmp_path / "folder").mkdir()
    (tmp_path / "afile").write_text("x")
    monkeypatch.setattr(ev, "evaluate", lambda *a, **k: pytest.fail("evaluated before --out was checked"))
    assert main(["evaluate", "--data", str(data), "--out", str(tmp_path / out)]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err


def test_markdown_and_json_are_two_files_and_the_default_is_not_the_published_table(result, tmp_path):
    from polrig.cli import build_parser

    res, _ = result
    ev.write_results(res, tmp_path / "sub" / "r.md")  # the folder is made at write time
    assert (tmp_path / "sub" / "r.md").read_text().startswith("# Single-shot")
    assert json.loads((tmp_path / "sub" / "r.json").read_text())["samples"] == res["samples"]
    with pytest.raises(ValueError, match=".md"):
        ev.write_results(res, tmp_path / "r.json")
    args = build_parser().parse_args(["evaluate", "--data", "d"])
    assert "benchmarks" not in args.out and args.out.endswith(".md")
