"""The paper-scale training entry point (:mod:`models.paper_scale`, issue 22 item 4) end to end
on the CPU at tiny scale: ``polrig sim dataset`` in two processes, the three stages, the ONNX
export and check, the evaluation against the shipped graphs, one small output folder; and
the budget arithmetic of the epoch plan."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from models import paper_scale  # noqa: E402


def test_plan_epochs_scales_the_paper_schedule_to_the_budget():
    # one probe epoch of 16 samples took 1.6 s per stage: 0.1 s per sample-epoch
    secs = dict.fromkeys(paper_scale.STAGE_SHARES, 1.6)
    plan = paper_scale.plan_epochs(secs, 16, 100, 600.0)
    assert plan == {"pipnet": 20, "pmmnet": 10, "direct": 30}  # 2:1 and the baseline as both together
    assert paper_scale.plan_epochs(secs, 16, 100, 1.0) == dict.fromkeys(paper_scale.STAGE_SHARES, 1)


@pytest.mark.slow
def test_tiny_run_end_to_end(tmp_path, capsys):
    out = tmp_path / "out"
    code = paper_scale.main(["--out", str(out), "--budget-min", "0.5", "--size", "32", "--width", "8",
                             "--jobs", "2", "--train-samples", "6", "--holdout-samples", "3", "--epochs", "1",
                             "--work", str(tmp_path)])
    assert code == 0, capsys.readouterr().err
    names = {p.name for p in out.iterdir()}
    assert {"weights", "log.csv", "summary.json", "run.json", "eval_unseen_shapes_new.md",
            "eval_new_scenes_shipped.json"} <= names
    assert {"single_shot.onnx", "direct.onnx", "model.json"} <= {p.name for p in (out / "weights").iterdir()}
    run = json.loads((out / "run.json").read_text())
    assert run["data"]["train_samples"] == 6 and run["training"]["epochs"] == {"pipnet": 1, "pmmnet": 1, "direct": 1}
    assert run["hardware"]["cpu_cores"] >= 1 and isinstance(run["ship"], bool)
    assert paper_scale.folder_bytes(out) < paper_scale.MAX_OUT_BYTES
    assert not list(tmp_path.glob("paper-scale-*"))  # the work folder is gone
    # the exported graph runs with the runtime
    from models.runtime import SingleShotModel

    assert SingleShotModel.load(out / "weights", threads=1).provider


def test_a_full_output_folder_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "x").write_text("")
    assert paper_scale.main(["--out", str(tmp_path), "--size", "32"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert paper_scale.main(["--out", str(tmp_path / "new"), "--size", "36"]) == 2


def test_training_device_is_checked_before_any_work(tmp_path):
    """``TrainConfig.device``: cpu or cuda; cuda where PyTorch sees no GPU is a one-line
    ConfigError before anything is read or written (the paper-scale run picks cuda only where
    ``torch.cuda.is_available()``)."""
    import torch

    from models.train import TrainConfig, train
    from polrig.errors import ConfigError

    with pytest.raises(ConfigError, match="device must be cpu or cuda"):
        train(tmp_path / "nodata", tmp_path / "out", TrainConfig(device="tpu"), export=False, echo=lambda s: None)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            train(tmp_path / "nodata", tmp_path / "out", TrainConfig(device="cuda"), export=False, echo=lambda s: None)
        assert paper_scale.training_device() == "cpu"
    assert not (tmp_path / "out").exists()
