"""The shipped single-shot graphs (issue 31 item 1): no ``Acos``, the frame path's and the probe's
graphs with fewer outputs, each within its tolerance of the graph shipped before
(``tests/data/single_shot_reference.npz``: its outputs on two held-out samples, written by
``python -m polrig.models.reship --reference``), the uncertainty calibration still this graph's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polrig.models.runtime import WEIGHTS_DIR

ort = pytest.importorskip("onnxruntime")

REFERENCE = WEIGHTS_DIR.parent.parent / "tests" / "data" / "single_shot_reference.npz"
GRAPHS = ("single_shot.onnx", "single_shot_frame.onnx", "single_shot_probe.onnx")
#: As polrig.models.reship.TOLERANCE (that module imports nothing heavy, but keep the numbers visible).
TOLERANCE = {"mueller": 1e-5, "kd": 1e-5, "alpha": 1e-5, "mueller_init": 5e-5, "normal": 5e-5, "wi": 5e-5}
#: The reference outputs were recorded on the machine that re-shipped the graphs; onnxruntime's
#: CPU kernels round float32 differently on other processors (the instruction set decides the
#: kernel), so this test, which runs anywhere, allows the re-shipping's tolerance twice: the
#: same graph on an AVX2-only AMD EPYC reads ``mueller`` 1.04e-5 and ``mueller_init`` 4.4e-5 off
#: the recorded outputs, identically with onnxruntime 1.22, 1.26, 1.31 and 1.32 and with 1 or 2
#: threads.
ANOTHER_CPU = 2.0


def _run(sess, feed: dict) -> dict:
    """The session's outputs by name (the probe's graph has no ``stage_zero_axis`` input: unused)."""
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, {i.name: feed[i.name] for i in sess.get_inputs()})))


def _reference() -> list[tuple[dict, dict]]:
    with np.load(REFERENCE) as z:
        cases = sorted({k.split("/")[0] for k in z.files})
        return [({k.split("/")[2]: z[k] for k in z.files if k.startswith(f"{c}/in/")},
                 {k.split("/")[2]: z[k] for k in z.files if k.startswith(f"{c}/out/")}) for c in cases]


def test_reference_is_small_and_the_tolerances_are_reships():
    from polrig.models import reship

    assert REFERENCE.stat().st_size < 2_000_000
    assert reship.TOLERANCE == TOLERANCE


@pytest.mark.parametrize("graph", GRAPHS)
def test_graph_has_no_acos_and_the_outputs_model_json_names(graph):
    onnx = pytest.importorskip("onnx")
    g = onnx.load(str(WEIGHTS_DIR / graph)).graph
    ops = {n.op_type for n in g.node}
    assert "Acos" not in ops
    meta = json.loads((WEIGHTS_DIR / "model.json").read_text())
    assert [o.name for o in g.output] == meta["graph_outputs"][graph]


@pytest.mark.parametrize("graph", GRAPHS)
def test_graph_matches_the_previously_shipped_one(graph):
    sess = ort.InferenceSession(str(WEIGHTS_DIR / graph), providers=["CPUExecutionProvider"])
    for feed, ref in _reference():
        out = _run(sess, feed)
        assert set(out) <= set(ref)
        for k, v in out.items():
            dev = float(np.max(np.abs(v - ref[k])) / np.max(np.abs(ref[k])))
            assert dev <= ANOTHER_CPU * TOLERANCE[k], (graph, k, dev)


def test_frame_and_probe_graphs_compute_the_full_graphs_outputs():
    """The same function: the smaller graphs' outputs equal the full graph's to float32 rounding."""
    feed, _ = _reference()[0]
    full = ort.InferenceSession(str(WEIGHTS_DIR / "single_shot.onnx"), providers=["CPUExecutionProvider"])
    want = _run(full, feed)
    for graph in GRAPHS[1:]:
        sess = ort.InferenceSession(str(WEIGHTS_DIR / graph), providers=["CPUExecutionProvider"])
        for name, v in _run(sess, feed).items():
            assert np.max(np.abs(v - want[name])) <= 1e-5 * np.max(np.abs(want[name])), (graph, name)


def test_uncertainty_calibration_is_the_shipped_graphs():
    from polrig.models.uncertainty import calibration_for_graph

    model, why = calibration_for_graph(WEIGHTS_DIR, "single_shot.onnx")
    assert model is not None, why


def test_zenith_cos_sin_are_the_acos_forms_and_train_with_finite_gradients():
    torch = pytest.importorskip("torch")
    from polrig.models.pipnet import PIPNet, diffuse_zenith, diffuse_zenith_cos_sin

    dolp = torch.cat([torch.linspace(-0.1, 0.6, 2001, dtype=torch.float64), torch.tensor([0.0, 1.0, 2.0],
                                                                                         dtype=torch.float64)])
    c, s = diffuse_zenith_cos_sin(dolp)
    z = diffuse_zenith(dolp)
    assert torch.allclose(c, torch.cos(z), atol=1e-12) and torch.allclose(s, torch.sin(z), atol=1e-12)
    assert (s >= 0).all() and torch.allclose(c * c + s * s, torch.ones_like(c))
    # a training step through the prior: unpolarized pixels (q = 1) and a fully polarized one
    torch.manual_seed(0)
    net = PIPNet(colours=3, width=4, sfp_prior=True)
    analyzer = torch.full((1, 3, 4, 16, 16), 0.5)
    analyzer[..., :8, :] = torch.tensor([1.0, 0.5, 0.0, 0.5])[None, None, :, None, None]
    wo = torch.zeros(1, 3, 16, 16)
    wo[:, 2] = -1.0
    out = net(analyzer, torch.ones(1, 1, 16, 16), torch.tensor([[1.0, 0.5, 0.0]]), wo)
    loss = sum(v.float().pow(2).mean() for v in out.values())
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
