"""What ``polrig train`` refuses before it trains or writes anything (one line, exit 2), and
what stops a run while it runs (exit 1): absurd numbers, an --out holding another run or a
file, damaged data and donors, image sizes the networks cannot take, a held-out set, a missing
ONNX exporter, a failed export check. Tiny data and networks; most cases stop before training."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import csv
import json
import shutil
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from polrig.models import train as tr  # noqa: E402
from polrig.models.train import TrainConfig, lr_at, train  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402

TINY = TrainConfig(pipnet_epochs=1, pmmnet_epochs=1, direct_epochs=1, batch_size=2, width=8, val_fraction=0.25)
FAST = ["--epochs", "1", "--width", "8", "--batch-size", "2"]


@pytest.fixture(scope="module")
def data(tiny_train_data):
    return tiny_train_data


@pytest.fixture(scope="module")
def run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run"
    train(data, out, TINY, export=False, echo=lambda s: None)
    return out


def _cli(capsys, *argv) -> tuple[int, str]:
    from polrig.cli import main

    try:
        code = main(["train", *map(str, argv)])
    except SystemExit as exc:  # argparse: usage line + error
        code = exc.code
    err = capsys.readouterr().err.strip()
    return code, err


def _one_line(err: str) -> str:
    assert "Traceback" not in err and "\n" not in err, err
    return err


# ----------------------------------------------------------------------------- numbers

@pytest.mark.parametrize("flag, value", [("--epochs", "0"), ("--epochs", "-1"), ("--pipnet-epochs", "0"),
                                         ("--lr", "inf"), ("--lr", "nan"), ("--lr", "1e9"), ("--lr", "0"),
                                         ("--lr", "-1e-3"), ("--width", "6"), ("--width", "0"),
                                         ("--batch-size", "0"), ("--seed", "-1"), ("--limit", "0"),
                                         ("--threads", "0"), ("--sfp-supervision", "inf"),
                                         ("--decay-start", "nan")])
def test_absurd_numbers_are_usage_errors_naming_the_option(data, tmp_path, capsys, flag, value):
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", flag, value)
    assert code == 2 and flag in err.splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "run").exists()


def test_a_one_epoch_stage_runs_at_the_base_learning_rate():
    cfg = TrainConfig(lr=1e-3, decay_start=0.5, lr_final_fraction=0.05)
    assert lr_at(cfg, 0, 1) == 1e-3  # round(0.5) = 0 used to put it at 5e-5
    assert lr_at(TrainConfig(lr=1e-3, decay_start=0.0), 0, 1) == 1e-3


def test_multi_epoch_schedules_are_unchanged():
    """The published recipes (decay start 0.5 and 0.6, 2..74 epochs) keep their schedules: the
    rule before the one-epoch fix, epoch by epoch."""
    def before(cfg, epoch, epochs):
        start = int(round(cfg.decay_start * epochs))
        if epoch < start or epochs <= start:
            return cfg.lr
        return cfg.lr * (1.0 - (epoch - start + 1) / (epochs - start) * (1.0 - cfg.lr_final_fraction))

    for decay in (0.0, 0.3, 0.5, 0.6, 1.0):
        cfg = TrainConfig(lr=1e-3, decay_start=decay)
        for epochs in range(2, 75):
            assert [lr_at(cfg, e, epochs) for e in range(epochs)] == [before(cfg, e, epochs) for e in range(epochs)]


# ----------------------------------------------------------------------------- --out

def test_an_out_holding_another_run_is_refused(data, run, tmp_path, capsys):
    other = tmp_path / "other"
    shutil.copytree(run, other)
    before = {p.name: p.read_bytes() for p in other.iterdir()}
    code, err = _cli(capsys, "--data", data, "--out", other, "--no-export", *FAST)
    assert code == 2 and "holds another training run" in _one_line(err) and "--overwrite" in err
    assert {p.name: p.read_bytes() for p in other.iterdir()} == before


def test_overwrite_replaces_the_run_and_its_stale_weights(data, run, tmp_path, capsys):
    other = tmp_path / "other"
    shutil.copytree(run, other)
    (other / "weights").mkdir()
    (other / "weights" / "single_shot.onnx").write_bytes(b"an older graph")
    (other / "weights" / "uncertainty.json").write_text("{}")
    code, err = _cli(capsys, "--data", data, "--out", other, "--no-export", "--overwrite", *FAST)
    assert code == 0, err
    assert not (other / "weights" / "single_shot.onnx").exists() and not (other / "weights" / "uncertainty.json").exists()
    rows = list(csv.DictReader((other / "log.csv").open()))
    assert [r["stage"] for r in rows] == ["pipnet", "pmmnet", "direct"]
    code, err = _cli(capsys, "--data", data, "--out", other, "--resume", "--overwrite")
    assert code == 2 and "give one of them" in _one_line(err)


def test_an_out_that_is_a_file_is_one_line(data, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "afile", *FAST)
    assert code == 2 and "is a file, not a folder" in _one_line(err)
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "afile" / "run", *FAST)
    assert code == 2 and "is a file, not a folder" in _one_line(err)


def test_an_unknown_stage_is_named(data, tmp_path, capsys):
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", "--stages", "pipnet,bogus")
    assert code == 2 and "'bogus'" in err.splitlines()[-1]
    from polrig.cli.commands.train import STAGE_NAMES

    assert STAGE_NAMES == tr.STAGES


def test_bad_data_leaves_no_out_folder(tmp_path, capsys):
    code, err = _cli(capsys, "--data", tmp_path / "missing", "--out", tmp_path / "run", *FAST)
    assert code == 2 and "missing" in _one_line(err)
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------- data and donors

def test_a_truncated_shard_is_named(data, tmp_path, capsys):
    bad = tmp_path / "bad"
    shutil.copytree(data, bad)
    blob = (bad / "shard-00001.npz").read_bytes()
    (bad / "shard-00001.npz").write_bytes(blob[: len(blob) // 3])
    code, err = _cli(capsys, "--data", bad, "--out", tmp_path / "run", *FAST)
    assert code == 2 and "shard-00001.npz" in _one_line(err) and not (tmp_path / "run").exists()


@pytest.mark.parametrize("text", ["{not json", "[]"])
def test_a_broken_manifest_is_named(data, tmp_path, capsys, text):
    bad = tmp_path / "bad"
    shutil.copytree(data, bad)
    (bad / "manifest.json").write_text(text)
    code, err = _cli(capsys, "--data", bad, "--out", tmp_path / "run", *FAST)
    assert code == 2 and "manifest.json" in _one_line(err)


@pytest.mark.parametrize("kind", ["json", "npz", "truncated"])
def test_a_donor_that_is_no_checkpoint_is_named(data, run, tmp_path, capsys, kind):
    donor = tmp_path / f"donor.{kind}"
    if kind == "json":
        donor.write_text(json.dumps({"config": {}}))
    elif kind == "npz":
        np.savez(donor, a=np.zeros(3))
    else:
        blob = (run / "checkpoint.pt").read_bytes()
        donor.write_bytes(blob[: len(blob) // 2])
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", "--init-from", donor, "--stages", "pmmnet",
                     "--no-export", *FAST)
    assert code == 2 and str(donor) in _one_line(err) and "not a readable polrig train checkpoint" in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("flags, needle", [(["--width", "12"], "width 8, not 12"),
                                           (["--no-sfp-prior", "--warm-start"], "--sfp-prior")])
def test_a_donor_of_another_architecture_is_refused(data, run, tmp_path, capsys, flags, needle):
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", "--init-from", run / "checkpoint.pt",
                     "--stages", "pmmnet", "--no-export", "--epochs", "1", "--batch-size", "2", *flags)
    assert code == 2 and needle in _one_line(err) and not (tmp_path / "run").exists()


def test_a_size_off_the_networks_multiple_is_refused_before_training(data, tmp_path, capsys):
    from polrig.models.data import load_dataset, write_dataset

    ds = load_dataset(data)
    crop = {k: (v[..., :28, :28] if v.ndim >= 3 and v.shape[-2:] == (32, 32) else v) for k, v in ds.arrays.items()}
    write_dataset(tmp_path / "odd", crop, ds.manifest)
    code, err = _cli(capsys, "--data", tmp_path / "odd", "--out", tmp_path / "run", *FAST)
    assert code == 2 and "multiples of 8" in _one_line(err) and not (tmp_path / "run").exists()


def test_a_held_out_set_is_refused(tmp_path, capsys):
    generate_dataset(tmp_path / "hold", count=2, width=32, seed=0, holdout=True, shard_size=2, progress=False)
    code, err = _cli(capsys, "--data", tmp_path / "hold", "--out", tmp_path / "run", *FAST)
    assert code == 2 and "held-out set" in _one_line(err) and "heightfield" in err
    assert not (tmp_path / "run").exists()


# ----------------------------------------------------------------------------- export

def test_missing_onnx_is_refused_before_training_unless_no_export(data, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "onnx", None)  # import onnx raises ImportError
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", *FAST)
    assert code == 2 and "'onnx' package" in _one_line(err) and "--no-export" in err
    assert not (tmp_path / "run").exists()
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", "--no-export", *FAST)
    assert code == 0, err


@pytest.mark.parametrize("diff, needle", [(float("nan"), "non-finite"), (0.5, "exceeds")])
def test_a_failed_export_check_is_exit_1_and_replaces_nothing(data, tmp_path, capsys, monkeypatch, diff, needle):
    import polrig.models.export as export

    monkeypatch.setattr(export, "compare_with_onnxruntime", lambda *a, **k: diff)
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "run", *FAST)
    assert code == 1 and needle in _one_line(err) and "single_shot.onnx" in err
    assert not any((tmp_path / "run" / "weights").glob("*"))  # no graph, no temporary file
    assert (tmp_path / "run" / "checkpoint.pt").is_file()  # the training is kept


def test_non_finite_weights_are_not_exported(data, tmp_path):
    from polrig.models.export import ExportError, export_all
    from polrig.models.pipnet import PIPNet
    from polrig.models.pmmnet import DirectStokesToMM, PMMNet

    pip = PIPNet(3, 8, True)
    with torch.no_grad():
        next(pip.parameters()).fill_(float("nan"))
    t = tr._tensors(__import__("polrig.models.data", fromlist=["load_dataset"]).load_dataset(data))
    sample = {k: t[k][:1] for k in ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")}
    with pytest.raises(ExportError, match="non-finite weights"):
        export_all(pip, PMMNet(3, 8), DirectStokesToMM(3, 8), tmp_path / "w", sample)
    assert not (tmp_path / "w").exists()
