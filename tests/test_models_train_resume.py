"""``polrig train`` runs that stop and go on: a resumed run reproduces the straight run exactly
(log rows and weights), an interruption anywhere in an epoch's bookkeeping loses nothing and
duplicates nothing, the checkpoint is replaced atomically, and what --resume refuses (no or a
damaged checkpoint, another dataset, another architecture, other epochs for a finished stage).
Tiny data (4 scenes of 32x32) and networks (width 8), a fraction of a second per run."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import csv
import dataclasses
import json
import shutil

import pytest

torch = pytest.importorskip("torch")

from polrig.models import train as tr  # noqa: E402
from polrig.models.train import TrainConfig, train  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402

# every random stream of the trainer in use: window crops, mirrored samples, perturbed initializations
TINY = TrainConfig(pipnet_epochs=2, pmmnet_epochs=2, direct_epochs=1, batch_size=2, width=8, val_fraction=0.25,
                   mirror_fraction=0.5)
QUIET = dict(echo=lambda s: None)


@pytest.fixture(scope="module")
def data(tiny_train_data):
    return tiny_train_data


@pytest.fixture(scope="module")
def straight(data, tmp_path_factory):
    run = tmp_path_factory.mktemp("straight") / "run"
    train(data, run, TINY, export=False, **QUIET)
    return run


def _rows(run):
    """Log rows without the wall-clock column."""
    with (run / "log.csv").open(newline="") as f:
        return [{k: v for k, v in r.items() if k != "epoch_s"} for r in csv.DictReader(f)]


def _weights(run):
    return torch.load(run / "checkpoint.pt", weights_only=False)["models"]


def _assert_same_run(a, b):
    assert _rows(a) == _rows(b)
    wa, wb = _weights(a), _weights(b)
    for net in tr.STAGES:
        for k, v in wa[net].items():
            assert torch.equal(v, wb[net][k]), (net, k)


def _stop_after(stage: str, epoch: int):
    """An ``echo`` that interrupts (as Ctrl-C does) once the log line of ``stage`` ``epoch`` is shown."""
    def echo(line: str) -> None:
        if line.startswith(f"{stage:7s} epoch {epoch:3d} "):
            raise KeyboardInterrupt
    return echo


@pytest.mark.parametrize("stage, epoch", [("pipnet", 1), ("pmmnet", 0)], ids=["stage-boundary", "mid-stage"])
def test_an_interrupted_and_resumed_run_is_the_straight_run(data, straight, tmp_path, stage, epoch):
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, echo=_stop_after(stage, epoch))
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert (ckpt["stage"], ckpt["epoch"]) == (stage, epoch + 1)
    train(data, run, resume=True, export=False, **QUIET)
    _assert_same_run(run, straight)


def test_ctrl_c_between_checkpoint_and_log_loses_and_duplicates_nothing(data, straight, tmp_path, monkeypatch):
    run = tmp_path / "run"
    calls = []
    real = tr._write_log

    def write_log(path, rows):
        calls.append(len(rows))
        if len(rows) == 3:  # the checkpoint of pmmnet epoch 0 is written, its log row not yet
            raise KeyboardInterrupt
        real(path, rows)

    monkeypatch.setattr(tr, "_write_log", write_log)
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, **QUIET)
    monkeypatch.setattr(tr, "_write_log", real)
    assert len(_rows(run)) == 2
    train(data, run, resume=True, export=False, **QUIET)
    assert [(r["stage"], r["epoch"]) for r in _rows(run)] == [("pipnet", "0"), ("pipnet", "1"), ("pmmnet", "0"),
                                                             ("pmmnet", "1"), ("direct", "0")]
    _assert_same_run(run, straight)


def test_the_checkpoint_is_replaced_atomically(data, tmp_path, monkeypatch):
    """Ctrl-C while the second checkpoint is written leaves the first one whole (and no temporary file)."""
    import polrig.formats.rawio

    run = tmp_path / "run"
    real_replace = os.replace
    seen = []

    def replace(src, dst):
        if str(dst).endswith("checkpoint.pt"):
            seen.append(dst)
            if len(seen) == 2:
                raise KeyboardInterrupt
        real_replace(src, dst)

    monkeypatch.setattr(polrig.formats.rawio.os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, **QUIET)
    monkeypatch.setattr(polrig.formats.rawio.os, "replace", real_replace)
    ckpt = tr.load_checkpoint(run / "checkpoint.pt", for_resume=True)
    assert (ckpt["stage"], ckpt["epoch"]) == ("pipnet", 1)
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "log.csv"]
    assert len(_rows(run)) == 1


def _cli(capsys, *argv) -> tuple[int, str]:
    from polrig.cli import main

    code = main(["train", *map(str, argv)])
    err = capsys.readouterr().err.strip()
    return code, err


def test_resume_without_a_checkpoint_is_refused(data, tmp_path, capsys):
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "new", "--resume", "--no-export")
    assert code == 2 and "no checkpoint.pt in" in err and str(tmp_path / "new") in err and "\n" not in err
    assert not (tmp_path / "new").exists()
    # a subset of the stages with --resume: the guard is not bypassed (it used to export random networks)
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "new", "--stages", "pmmnet", "--resume")
    assert code == 2 and "no checkpoint.pt" in err and not (tmp_path / "new").exists()
    code, err = _cli(capsys, "--data", data, "--out", tmp_path / "new", "--stages", "pmmnet")
    assert code == 2 and "--init-from" in err and not (tmp_path / "new").exists()


def test_resume_refuses_other_stages(data, straight, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(straight, run)
    code, err = _cli(capsys, "--data", data, "--out", run, "--resume", "--stages", "pmmnet", "--no-export")
    assert code == 2 and "drop --stages" in err


def test_a_damaged_checkpoint_is_one_line(data, straight, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(straight, run)
    blob = (run / "checkpoint.pt").read_bytes()
    (run / "checkpoint.pt").write_bytes(blob[: len(blob) // 2])
    code, err = _cli(capsys, "--data", data, "--out", run, "--resume", "--no-export")
    assert code == 2 and "checkpoint.pt: not a readable polrig train checkpoint" in err and "\n" not in err


def test_resume_on_another_dataset_is_refused(data, straight, tmp_path, capsys):
    other = tmp_path / "other"
    generate_dataset(other, count=4, width=32, seed=1, shard_size=2, progress=False)
    run = tmp_path / "run"
    shutil.copytree(straight, run)
    code, err = _cli(capsys, "--data", other, "--out", run, "--resume", "--no-export")
    assert code == 2 and "not the dataset" in err and "seed" in err


@pytest.mark.parametrize("flag, value, needle", [("--width", "12", "--width 12 differs from the run's --width 8"),
                                                 ("--no-sfp-prior", None, "--no-sfp-prior differs"),
                                                 ("--seed", "3", "--seed 3 differs"),
                                                 ("--pipnet-epochs", "4", "pipnet stage is finished")])
def test_resume_keeps_architecture_samples_and_finished_stages(data, tmp_path, capsys, flag, value, needle):
    run = tmp_path / "run"
    # stopped in the PMMNet stage: PIPNet is finished
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, echo=_stop_after("pmmnet", 0))
    before = (run / "checkpoint.pt").read_bytes()
    code, err = _cli(capsys, "--data", data, "--out", run, "--resume", "--no-export", flag, *([value] if value else []))
    assert code == 2 and needle in err and "\n" not in err
    assert (run / "checkpoint.pt").read_bytes() == before


def test_resume_with_more_epochs_of_the_current_stage_records_what_was_trained(data, tmp_path):
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, echo=_stop_after("pmmnet", 0))
    summary = train(data, run, resume=True, export=False, overrides={"pmmnet_epochs": 3}, **QUIET)
    assert [r["stage"] for r in _rows(run)].count("pmmnet") == 3
    assert summary["config"]["pmmnet_epochs"] == 3 and summary["config"]["pipnet_epochs"] == 2


def test_a_non_finite_loss_stops_the_run(data, tmp_path, capsys, monkeypatch):
    real = tr.pmmnet_step

    def diverging(*a, **k):
        loss, detail = real(*a, **k)
        return loss * float("nan"), detail

    monkeypatch.setattr(tr, "pmmnet_step", diverging)
    run = tmp_path / "run"
    code, err = _cli(capsys, "--data", data, "--out", run, "--pipnet-epochs", "1", "--pmmnet-epochs", "1",
                     "--direct-epochs", "1", "--width", "8", "--batch-size", "2")
    assert code == 1 and "pmmnet epoch 0" in err and "nan" in err and "\n" not in err
    assert not (run / "weights").exists()
    ckpt = tr.load_checkpoint(run / "checkpoint.pt", for_resume=True)  # the finished PIPNet epoch is kept
    assert (ckpt["stage"], ckpt["epoch"]) == ("pipnet", 1) and len(_rows(run)) == 1
    for net in ckpt["models"].values():
        assert all(bool(torch.isfinite(v).all()) for v in net.values() if v.is_floating_point())


def test_config_of_a_run_records_the_epochs_actually_trained_from_a_donor(data, straight, tmp_path):
    summary = train(data, tmp_path / "run", init_from=straight / "checkpoint.pt", stages=("direct",),
                    overrides={"pipnet_epochs": 7, "direct_epochs": 1}, export=False, **QUIET)
    assert summary["config"]["pipnet_epochs"] == TINY.pipnet_epochs  # the donor's, not the ignored override
    assert dataclasses.asdict(TINY)["width"] == summary["config"]["width"]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["stages_trained"] == ["direct"]


def test_a_checkpoint_of_an_older_polrig_still_resumes(data, tmp_path):
    """Without random states, log rows or dataset identity (checkpoints before this format): the
    run goes on from the stored seed, and the log keeps each epoch the checkpoint holds once (the
    old order could leave a row written twice)."""
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train(data, run, TINY, export=False, echo=_stop_after("pmmnet", 0))
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    for key in ("rng_state", "torch_rng_state", "log", "dataset", "recalibrate", "format", "version", "data",
                "init_from"):
        ckpt.pop(key)
    ckpt["rng_seed"] = 5
    torch.save(ckpt, run / "checkpoint.pt")
    lines = (run / "log.csv").read_text().splitlines()
    (run / "log.csv").write_text("\n".join(lines + lines[-1:]) + "\n")  # pmmnet epoch 0 twice
    said = []
    train(data, run, resume=True, export=False, echo=said.append)
    assert any("not bit-identical" in s for s in said) and any("does not record its dataset" in s for s in said)
    assert [(r["stage"], r["epoch"]) for r in _rows(run)] == [("pipnet", "0"), ("pipnet", "1"), ("pmmnet", "0"),
                                                             ("pmmnet", "1"), ("direct", "0")]
