"""Training continues across sessions (issue 32, item 4): the committed checkpoint of the small
model, ``--continue-from`` on both training routes (a dataset on the CPU and ``--data
on-device``), the step counters and lineage that go on rather than restart, and the compact
storage that keeps a larger model's checkpoint under the 16 MiB a lease brings back.
Tiny runs: 32x32 scenes, width 4-8 (the committed small model: width 16), one or two steps."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import json

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from polrig.cli import main  # noqa: E402
from polrig.models import continuation, sizes  # noqa: E402
from polrig.models import train_on_device as tod  # noqa: E402
from polrig.models.train import TrainConfig, load_checkpoint, train  # noqa: E402

QUIET = dict(echo=lambda s: None)
TINY_DEVICE = dict(size=32, steps_per_epoch=2, val_samples=2)


def _tiny(width=4, **kw):
    return TrainConfig(pipnet_epochs=1, pmmnet_epochs=1, direct_epochs=1, batch_size=2, width=width, **kw)


def _adam_steps(ckpt: dict) -> dict[str, set[int]]:
    """Each network's optimizer step counters (one per parameter)."""
    return {k: {int(float(st["step"])) for st in o["state"].values()} for k, o in ckpt["optimizers"].items()}


def test_the_committed_small_checkpoint_is_the_shipped_model():
    path = continuation.shipped_checkpoint("small")
    assert path == sizes.WEIGHTS_ROOT / "checkpoint.pt" and path.stat().st_size < continuation.MAX_COMMIT_BYTES
    ck = load_checkpoint(path)
    meta = json.loads((sizes.WEIGHTS_ROOT / "model.json").read_text())
    assert ck["size"] == "small" and ck["optimizers"] is None and ck["recovered_from_onnx"] == "models/weights"
    assert ck["lineage"] == meta["training"]["lineage"]  # every run that trained it
    assert ck["totals"]["pmmnet"]["epochs"] == meta["training"]["totals"]["pmmnet"]["epochs"]
    assert ck["config"]["width"] == meta["width"] == 16
    # its networks compute the shipped graphs' function: they are those graphs' parameters
    from polrig.models.recover import networks_from_weights

    nets, _ = networks_from_weights(sizes.WEIGHTS_ROOT)
    for k, net in nets.items():
        for name, value in net.state_dict().items():
            assert torch.equal(value, ck["models"][k][name]), (k, name)


def test_continuing_the_small_checkpoint_on_device_goes_on_with_its_networks(tmp_path, monkeypatch):
    """The committed checkpoint holds no optimizer state: the run says so, starts Adam fresh, sets
    the recovered batch norms on generated batches, and adds its runs to the lineage."""
    monkeypatch.setattr(tod, "RECALIBRATION_SAMPLES", 4)  # the statistics of 2 batches: a tiny run
    lines: list[str] = []
    summary = tod.train_on_device(tmp_path / "run", None, overrides=dict(pipnet_epochs=1, pmmnet_epochs=1,
                                                                         direct_epochs=1, batch_size=2),
                                  continue_from=continuation.resolve("small"), export=False, echo=lines.append,
                                  **TINY_DEVICE)
    assert any("no optimizer state" in s and "start fresh" in s for s in lines)
    assert any("batch-norm statistics" in s for s in lines)
    shipped = load_checkpoint(continuation.shipped_checkpoint("small"))
    n = len(shipped["lineage"])
    assert summary["config"]["width"] == 16 and summary["config"]["sfp_prior"] is True  # its architecture
    assert summary["lineage"][:n] == shipped["lineage"]
    new = summary["lineage"][n:]
    assert [e["network"] for e in new] == ["pipnet", "pmmnet", "direct"]
    assert all(e["start"] == "continued" and e["optimizer"] == "fresh" and e["steps"] == 2 for e in new)
    ck = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert ck["totals"]["pmmnet"]["epochs"] == shipped["totals"]["pmmnet"]["epochs"] + 1
    assert ck["size"] == "small" and _adam_steps(ck) == {k: {2} for k in ("pipnet", "pmmnet", "direct")}
    # trained from the shipped weights, not from scratch: PIPNet's convolution kernels moved by about
    # two Adam steps of lr 1e-3 (the batch norms were re-expressed by the recalibration)
    drift = max(float((ck["models"]["pipnet"][k] - v).abs().max())
                for k, v in shipped["models"]["pipnet"].items() if v.ndim == 4)
    assert 0 < drift <= 2.5e-3


def test_a_continued_on_device_run_goes_on_counting_steps(tmp_path):
    """A run's checkpoint, committed (compact), continued: Adam's step counters and the lineage's
    totals go on from the first run's (2 steps per network) to 4; the seed moves on, so the
    second run draws new scenes."""
    first = tod.train_on_device(tmp_path / "a", _tiny(), export=False, **QUIET, **TINY_DEVICE)
    committed = tmp_path / "checkpoint.pt"
    continuation.write(continuation.from_run(tmp_path / "a" / "checkpoint.pt", "small"), committed)
    lines: list[str] = []
    second = tod.train_on_device(tmp_path / "b", None, overrides=dict(pipnet_epochs=1, pmmnet_epochs=1,
                                                                      direct_epochs=1, batch_size=2),
                                 continue_from=committed, export=True, echo=lines.append, **TINY_DEVICE)
    assert any("optimizer states (steps so far: pipnet 2, pmmnet 2, direct 2)" in s for s in lines)
    ck = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert _adam_steps(ck) == {k: {4} for k in ("pipnet", "pmmnet", "direct")}
    assert ck["totals"]["pipnet"] == {"epochs": 2, "steps": 4,
                                      "seconds": pytest.approx(sum(e["seconds"] for e in second["lineage"]
                                                                   if e["network"] == "pipnet"), abs=0.01)}
    assert second["lineage"][:3] == first["lineage"]
    assert [e["start"] for e in second["lineage"]] == ["scratch"] * 3 + ["continued"] * 3
    assert [e["optimizer"] for e in second["lineage"][3:]] == ["continued"] * 3
    assert second["config"]["seed"] == 3 != first["config"]["seed"]
    meta = json.loads((tmp_path / "b" / "weights" / "model.json").read_text())
    assert meta["size"] == "small" and len(meta["training"]["lineage"]) == 6
    assert meta["training"]["totals"]["direct"]["steps"] == 4 and meta["training"]["hardware"].startswith("CPU")
    assert sizes.model_record(tmp_path / "b" / "weights")["training_hardware"].startswith("CPU")


def test_a_continued_dataset_run_goes_on_too(tiny_train_data, tmp_path):
    train(tiny_train_data, tmp_path / "a", _tiny(val_fraction=0.25), export=False, **QUIET)
    second = train(tiny_train_data, tmp_path / "b", None, continue_from=tmp_path / "a" / "checkpoint.pt",
                   overrides=dict(pipnet_epochs=1, pmmnet_epochs=1, direct_epochs=1, batch_size=2), export=False,
                   **QUIET)
    ck = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert _adam_steps(ck) == {k: {4} for k in ("pipnet", "pmmnet", "direct")}  # 3 train samples, batch 2
    assert [e["start"] for e in second["lineage"]] == ["scratch"] * 3 + ["continued"] * 3
    assert ck["totals"]["pmmnet"]["steps"] == 4
    with pytest.raises(Exception, match="--continue-from goes on with every network"):
        train(tiny_train_data, tmp_path / "c", None, continue_from=tmp_path / "a" / "checkpoint.pt",
              stages=("pmmnet",), **QUIET)


def test_compact_storage_fits_the_limit_and_still_continues(tmp_path):
    """Over the limit, Adam's moments go to bfloat16 (then the weights): the file shrinks, records
    it, and a continued run loads it (Adam casts the moments back to float32)."""
    tod.train_on_device(tmp_path / "a", _tiny(width=8), export=False, **QUIET, **TINY_DEVICE)
    state = continuation.from_run(tmp_path / "a" / "checkpoint.pt", "large")
    full = continuation._nbytes(continuation.compact(state))
    small = continuation.compact(state, limit=full - 1)
    assert small["storage"] == {"weights": "float32", "optimizer_moments": "bfloat16"}
    assert continuation._nbytes(small) < full
    assert small["optimizers"]["pipnet"]["state"][0]["exp_avg_sq"].dtype == torch.bfloat16
    tiny = continuation.compact(state, limit=continuation._nbytes(small) - 1)
    assert tiny["storage"]["weights"] == "bfloat16"
    with pytest.raises(Exception, match="even in bfloat16"):
        continuation.compact(state, limit=1000)
    path = tmp_path / "ck.pt"
    torch.save(small, path)
    tod.train_on_device(tmp_path / "b", None, overrides=dict(pipnet_epochs=1, pmmnet_epochs=1, direct_epochs=1,
                                                             batch_size=2),
                        continue_from=path, export=False, **QUIET, **TINY_DEVICE)
    ck = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert ck["optimizers"]["pipnet"]["state"][0]["exp_avg_sq"].dtype == torch.float32
    assert _adam_steps(ck)["pipnet"] == {4} and ck["size"] == "large"


def test_cli_continue_from_a_size_without_a_checkpoint_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "large", tmp_path / "no-large")
    code = main(["train", "--data", "on-device", "--continue-from", "large", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "no committed checkpoint yet" in err[0] and "gpu_train.sh" in err[0]
    assert not (tmp_path / "run").exists()


def test_bf16_autocast_runs_the_networks_in_bfloat16_and_gives_float32(tmp_path):
    """``--autocast bf16`` (the lease's setting on CUDA; CPU autocast here): the convolutions run
    in bfloat16, what the losses read comes back float32, and a run trains to finite losses."""
    from polrig.models.pipnet import PIPNet
    from polrig.models.scenes_torch import SceneGenerator, training_tensors
    from polrig.models.train import Autocast, with_precision

    t = training_tensors(SceneGenerator(32, seed=0).batch(2))
    net = PIPNet(3, 4, True).eval()
    seen: list[torch.dtype] = []
    hooks = [m.register_forward_hook(lambda mod, i, o: seen.append(o.dtype))
             for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    out = Autocast(net, "cpu")(t["analyzer"], t["mask"], t["s_in"], t["wo"])
    for h in hooks:
        h.remove()
    assert seen and set(seen) == {torch.bfloat16}
    assert all(v.dtype == torch.float32 for v in out.values() if torch.is_tensor(v) and v.is_floating_point())
    plain = net(t["analyzer"], t["mask"], t["s_in"], t["wo"])
    assert float((out["normal"] - plain["normal"]).detach().abs().max()) < 0.1  # bfloat16's ~3 significant digits
    assert with_precision(net, _tiny()) is net
    summary = tod.train_on_device(tmp_path / "run", _tiny(autocast="bf16"), export=False, **QUIET, **TINY_DEVICE)
    assert summary["config"]["autocast"] == "bf16"
    rows = (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]
    assert len(rows) == 3 and all("nan" not in r and "inf" not in r for r in rows)
    with pytest.raises(Exception, match="autocast must be none or bf16"):
        tod.train_on_device(tmp_path / "bad", _tiny(autocast="fp8"), export=False, **QUIET, **TINY_DEVICE)
