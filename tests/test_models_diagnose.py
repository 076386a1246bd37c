"""polrig.models.diagnose on a tiny generated set with freshly exported (untrained) graphs: every rung is
finite, and the true geometry beats PIPNet's untrained guess."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from polrig.models.data import load_dataset  # noqa: E402
from polrig.models.diagnose import RUNGS, diagnose  # noqa: E402
from polrig.models.export import export_all  # noqa: E402
from polrig.models.pipnet import PIPNet  # noqa: E402
from polrig.models.pmmnet import DirectStokesToMM, PMMNet  # noqa: E402
from polrig.models.train import _tensors  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402


def test_diagnose_ladder_on_a_tiny_set(tmp_path):
    data = tmp_path / "data"
    generate_dataset(data, count=3, width=32, seed=3, shard_size=3, progress=False)
    t = _tensors(load_dataset(data))
    torch.manual_seed(0)
    sample = {k: t[k][:1] for k in ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")}
    export_all(PIPNet(3, 4, True).eval(), PMMNet(3, 4, 2).eval(), DirectStokesToMM(3, 4).eval(), tmp_path / "w", sample)
    lines = []
    result = diagnose(data, tmp_path / "w", echo=lines.append)
    rows = result["all"]
    assert rows["samples"] >= 1 and "| all |" in lines[0]
    for key in (*RUNGS, "full", "direct", "normal_err_deg", "fit_light_true_n_err_deg", "sfp_oracle_err_deg",
                "sfp_shading_err_deg"):
        assert np.isfinite(rows[key]), key
    assert rows["true_n+true_wi"] < rows["pip_n+pip_wi"]


