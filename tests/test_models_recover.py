"""polrig.models.recover: the shipped ONNX graphs turned back into PyTorch networks compute what the
graphs compute, batch-norm recalibration keeps that function, and a graph of another
architecture is refused with a clear error."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from polrig.errors import FormatError  # noqa: E402
from polrig.models.data import load_dataset  # noqa: E402
from polrig.models.export import INPUTS, compare_with_onnxruntime  # noqa: E402
from polrig.models.pmmnet import DirectStokesToMM, SingleShotNet  # noqa: E402
from polrig.models.recover import (  # noqa: E402
    load_onnx_into,
    networks_from_weights,
    recalibrate_batchnorm,
)
from polrig.models.runtime import WEIGHTS_DIR  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    data = tmp_path_factory.mktemp("recover") / "data"
    generate_dataset(data, count=2, width=32, seed=4, shard_size=2, progress=False)
    ds = load_dataset(data)
    i = int(np.argmax([(m > 0).sum() for m in ds["mask"]]))
    arrays = (ds["analyzer"][i][None], ds["mask"][i][None, None], ds["s_in"][i][None], ds["wo"][i][None],
              ds["stage_zero_axis"][i][None])
    return {k: torch.from_numpy(np.ascontiguousarray(a)).float() for k, a in zip(INPUTS, arrays)}


def test_shipped_graphs_recover_to_the_function_they_compute(sample):
    nets, meta = networks_from_weights(WEIGHTS_DIR)
    single = SingleShotNet(nets["pipnet"], nets["pmmnet"]).eval()
    with torch.no_grad():
        out = single(*(sample[k] for k in INPUTS))
    scale = max(1.0, float(out[0].abs().max()))
    # every output of the composite graph (mueller, init, normal, kd, wi, alpha), float32 rounding only
    assert compare_with_onnxruntime(single, WEIGHTS_DIR / "single_shot.onnx", sample) <= 1e-4 * scale
    assert compare_with_onnxruntime(nets["direct"], WEIGHTS_DIR / "direct.onnx", sample) <= 1e-4 * scale
    assert meta["training"]["config"]["sfp_prior"] is True and nets["pipnet"].sfp_prior


def test_recalibrated_batch_norm_keeps_the_eval_function_and_matches_batch_statistics(sample):
    nets, _ = networks_from_weights(WEIGHTS_DIR)
    direct = nets["direct"]
    gen = torch.Generator().manual_seed(0)
    batch = {k: v.repeat(4, *([1] * (v.dim() - 1))) for k, v in sample.items()}
    batch["analyzer"] = batch["analyzer"] * (0.5 + torch.rand(4, 1, 1, 1, 1, generator=gen))
    args = [batch[k] for k in INPUTS]
    with torch.no_grad():
        before = direct(*args)
    bn = next(m for m in direct.modules() if isinstance(m, torch.nn.BatchNorm2d))
    assert torch.all(bn.running_mean == 0)  # recovered: identity plus bias
    recalibrate_batchnorm(direct, [lambda: direct(*args)])
    assert not torch.all(bn.running_mean == 0)
    with torch.no_grad():
        after_eval = direct(*args)
        direct.train()
        after_train = direct(*args)  # batch statistics == the statistics it was set to
        direct.eval()
    tol = 1e-4 * float(before.abs().max())
    assert float((after_eval - before).abs().max()) <= tol
    assert float((after_train - before).abs().max()) <= 10 * tol


def test_a_graph_of_another_architecture_is_refused_in_one_line(tmp_path):
    with pytest.raises(FormatError, match="direct.onnx"):
        load_onnx_into(DirectStokesToMM(3, 8), WEIGHTS_DIR / "direct.onnx", 3)
    with pytest.raises(FileNotFoundError, match="model.json"):
        networks_from_weights(tmp_path)
    # model.json saying another width than the graphs hold
    for name in ("single_shot.onnx", "direct.onnx"):
        (tmp_path / name).write_bytes((WEIGHTS_DIR / name).read_bytes())
    meta = json.loads((WEIGHTS_DIR / "model.json").read_text())
    (tmp_path / "model.json").write_text(json.dumps(dict(meta, width=8)))
    with pytest.raises(FormatError):
        networks_from_weights(tmp_path)
