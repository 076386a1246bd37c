"""models.diagnose on a tiny generated set with freshly exported (untrained) graphs: every rung is
finite, and the true geometry beats PIPNet's untrained guess."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from models.diagnose import RUNGS, diagnose  # noqa: E402
from models.export import export_all  # noqa: E402
from models.pipnet import PIPNet  # noqa: E402
from models.pmmnet import DirectStokesToMM, PMMNet  # noqa: E402
from models.train import _tensors  # noqa: E402
from models.data import load_dataset  # noqa: E402
from sim.dataset import generate_dataset  # noqa: E402


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


def test_shading_pick_takes_the_candidate_whose_lambertian_shading_explains_the_image():
    """Intensity rendered as 0.7 max(n.wi, 0) from a random choice between two candidates:
    the pick recovers that choice wherever the two shadings differ."""
    from models.diagnose import shading_pick

    rng = np.random.default_rng(4)
    plus = rng.normal(size=(3, 12, 12)) + np.array([0, 0, -2.0])[:, None, None]
    plus /= np.linalg.norm(plus, axis=0)
    minus = plus * np.array([-1, -1, 1.0])[:, None, None]  # azimuth turned by 180 deg about the view axis
    wi = np.broadcast_to(np.array([0.5, 0.2, -0.8])[:, None, None] / np.linalg.norm([0.5, 0.2, -0.8]), plus.shape)
    truth = rng.random((12, 12)) < 0.5
    n = np.where(truth[None], plus, minus)
    intensity = 0.7 * np.clip((n * wi).sum(0), 0, None)
    picked = shading_pick(plus, minus, wi, intensity, np.ones((12, 12), bool))
    differ = np.abs(np.clip((plus * wi).sum(0), 0, None) - np.clip((minus * wi).sum(0), 0, None)) > 1e-3
    assert differ.mean() > 0.5
    np.testing.assert_allclose(picked[:, differ], n[:, differ])
