"""Sessions with fixed input sizes (issue 31 item 2): one per graph and input size, created once and
kept; the frame path's and the probe's smaller graphs; the same numbers as the one dynamic-size
session; CUDA graphs refused by onnxruntime (at session creation or at the first run) leave the
path running without them, say so once on stderr and in the provider options a result records.
The CUDA side is played by a CPU session that reports itself as CUDA (no GPU here)."""

from __future__ import annotations

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from polrig.models import devices  # noqa: E402
from polrig.models.runtime import MAX_SESSIONS, WEIGHTS_DIR, SingleShotModel  # noqa: E402


@pytest.fixture(scope="module")
def capture():
    from polrig.sim.dataset import make_sample

    s = make_sample(5, seed=778, width=64, height=64, holdout=True)
    return s["analyzer"] * s["scale"], s["s_in"], s["mask"].astype(bool)


def test_fixed_size_sessions_are_made_once_and_give_the_dynamic_sessions_numbers(capture):
    analyzer, s_in, mask = capture
    fixed = SingleShotModel.load(threads=1, fixed_sizes=True)
    dynamic = SingleShotModel.load(threads=1, fixed_sizes=False)
    axis = (1.0, 0.0, 0.0)  # another axis than the training one: probe + frame pass at 256x256
    big = np.repeat(np.repeat(analyzer, 4, axis=-1), 4, axis=-2)
    big_mask = np.repeat(np.repeat(mask, 4, axis=-1), 4, axis=-2)
    for outputs in ("all", "frame"):
        got, aux = fixed.reconstruct(big, s_in, mask=big_mask, stage_zero_axis=axis, outputs=outputs)
        want, want_aux = dynamic.reconstruct(big, s_in, mask=big_mask, stage_zero_axis=axis)
        assert np.max(np.abs(got - want)) <= 1e-5 * np.max(np.abs(want))
        assert abs(aux["incident_rotation_deg"] - want_aux["incident_rotation_deg"]) < 1e-3
        assert ("normal" in aux) == (outputs == "all") and aux["wi"].shape == (3, 256, 256)
    keys = set(fixed._runners)
    assert keys == {("single_shot_probe.onnx", (1, 128, 128), "host"), ("single_shot.onnx", (1, 256, 256), "host"),
                    ("single_shot_frame.onnx", (1, 256, 256), "host")}
    runners = dict(fixed._runners)
    fixed.reconstruct(big, s_in, mask=big_mask, stage_zero_axis=axis, outputs="frame")
    assert all(fixed._runners[k] is runners[k] for k in keys)  # created once per size
    assert fixed.provider_options == {"intra_op_num_threads": "1", "fixed_sizes": "1"}
    # without fixed sizes: one dynamic session per graph run; model.session (not optimised)
    # only names the graph and never runs
    assert set(dynamic._runners) == {("single_shot_probe.onnx", None, "host"), ("single_shot.onnx", None, "host")}
    assert all(r.session is not dynamic.session for r in dynamic._runners.values())
    assert dynamic.provider_options["fixed_sizes"] == "0"
    # the CPU's default: dynamic sizes (more memory for no measured speed when fixed)
    assert not SingleShotModel.load(threads=1).fixed_sizes


def test_sessions_are_bounded_least_recently_used_first(capture):
    analyzer, s_in, mask = capture
    model = SingleShotModel.load(threads=1, fixed_sizes=True)
    analyzer = np.repeat(np.repeat(analyzer, 2, axis=-1), 2, axis=-2)  # 128x128: room for the sizes
    mask = np.repeat(np.repeat(mask, 2, axis=-1), 2, axis=-2)
    for n in range(MAX_SESSIONS + 1):
        size = 16 + 8 * n
        model.reconstruct(analyzer[..., :size, :size], s_in, mask=mask[:size, :size])
    assert len(model._runners) == MAX_SESSIONS
    assert ("single_shot.onnx", (1, 16, 16), "host") not in model._runners


class _ReportsCuda:
    """A CPU session that says it runs on CUDA with the options it was given."""

    def __init__(self, session, options: dict[str, str]):
        self._s, self._options = session, options

    def get_providers(self):
        return [devices.CUDA, devices.CPU]

    def get_provider_options(self):
        return {devices.CUDA: dict(self._options, device_id="0"), devices.CPU: {}}

    def __getattr__(self, name):
        return getattr(self._s, name)


def _cuda_model(refuse_at_creation: bool) -> tuple[SingleShotModel, list]:
    opened = []

    def opener(path, sizes, cuda_graph=False):
        opened.append((path.name, sizes, cuda_graph))
        if cuda_graph and refuse_at_creation:
            raise RuntimeError("[ONNXRuntimeError] : 1 : FAIL : This session cannot use the graph capture "
                               "feature as requested by the user as all compute graph nodes have not been "
                               "partitioned to the CUDA EP.")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        for k, n in zip(("batch", "height", "width"), sizes):
            opts.add_free_dimension_override_by_name(k, n)
        sess = ort.InferenceSession(str(path), opts, providers=[devices.CPU])
        asked = dict(devices.CUDA_OPTIONS, **(devices.CUDA_GRAPH_OPTION if cuda_graph else {}))
        return _ReportsCuda(sess, asked)

    base = ort.InferenceSession(str(WEIGHTS_DIR / "single_shot.onnx"), providers=[devices.CPU])
    import json

    meta = json.loads((WEIGHTS_DIR / "model.json").read_text())
    model = SingleShotModel(_ReportsCuda(base, dict(devices.CUDA_OPTIONS)), meta, WEIGHTS_DIR, opener=opener,
                            session_options={"intra_op_num_threads": "1", "fixed_sizes": "1"})
    return model, opened


@pytest.mark.parametrize("refuse_at_creation", [True, False])
def test_refused_cuda_graphs_run_without_and_say_so(capture, capsys, refuse_at_creation):
    """Refused when the session is created, or (a CPU-only onnxruntime has no "cuda" device for
    the bound buffers) at the first run: either way the run's numbers are the plain session's, one
    line on stderr, ``enable_cuda_graph=0`` in the options a result records, and the other sizes
    do not ask again."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot

    analyzer, s_in, mask = capture
    model, opened = _cuda_model(refuse_at_creation)
    assert model.provider == devices.CUDA
    got, aux = model.reconstruct(analyzer, s_in, mask=mask, outputs="frame")
    want, _ = SingleShotModel.load(threads=1).reconstruct(analyzer, s_in, mask=mask)
    assert np.max(np.abs(got - want)) <= 1e-5 * np.max(np.abs(want))
    assert opened[0] == ("single_shot_frame.onnx", (1, 64, 64), True)
    assert opened[1] == ("single_shot_frame.onnx", (1, 64, 64), False)
    err = capsys.readouterr().err
    assert err.count("polrig: cuda: onnxruntime refused enable_cuda_graph=1 (") == 1
    assert len(model.device_notes) == 1 and "running without" in model.device_notes[0]
    assert aux["provider_options"] == {"intra_op_num_threads": "1", "fixed_sizes": "1",
                                       **{k: v for k, v in devices.CUDA_OPTIONS.items()}, "enable_cuda_graph": "0"}
    model.reconstruct(analyzer[..., :32, :32], s_in, mask=mask[:32, :32], outputs="frame")
    assert opened[2] == ("single_shot_frame.onnx", (1, 32, 32), False)  # not asked again
    assert capsys.readouterr().err == ""
    # the route records the options and the refusal in the result's header
    route = SingleShot(model)
    net = route._network(analyzer, s_in, SingleShotOptions(), {})
    result = route._result(net.mueller, net.object, np.zeros((3, 64, 64), bool), np.zeros((3, 64, 64), bool), net,
                           SingleShotOptions())
    header = result.header(["mueller"])
    assert header["execution_provider"] == devices.CUDA
    assert header["execution_provider_options"]["enable_cuda_graph"] == "0"
    assert header["execution_provider_options"]["use_tf32"] == "0"
    assert header["execution_provider_notes"] == model.device_notes


def test_accepted_cuda_graphs_bind_fixed_buffers(capture, monkeypatch):
    """Where onnxruntime takes ``enable_cuda_graph`` the run goes through I/O binding (here the
    binding fails for want of a GPU, which is the refusal path above); the plain path keeps the
    CPU's arena options."""
    model, _ = _cuda_model(refuse_at_creation=False)
    analyzer, s_in, mask = capture
    calls = []
    from polrig.models import runtime

    real = runtime._Runner._run_bound

    def spy(self, feed):
        calls.append(sorted(feed))
        return real(self, feed)

    monkeypatch.setattr(runtime._Runner, "_run_bound", spy)
    model.reconstruct(analyzer, s_in, mask=mask, outputs="frame")
    assert calls == [["analyzer", "mask", "s_in", "stage_zero_axis", "wo"]]


def test_smaller_graphs_only_beside_the_full_graph_they_were_exported_with(tmp_path, capture):
    """A folder whose full graph was replaced alone (its SHA-256 is not the one model.json names
    beside the smaller graphs) runs everything on the full graph; the shipped folder's match."""
    import json
    import shutil

    analyzer, s_in, mask = capture
    shipped = SingleShotModel.load(threads=1)
    assert shipped._companions() == {"single_shot_frame.onnx", "single_shot_probe.onnx"}
    wd = tmp_path / "w"
    shutil.copytree(WEIGHTS_DIR, wd)
    meta = json.loads((wd / "model.json").read_text())
    meta["graph_sha256"]["single_shot.onnx"] = "0" * 64  # another full graph than the smaller ones'
    (wd / "model.json").write_text(json.dumps(meta))
    model = SingleShotModel.load(wd, threads=1, fixed_sizes=True)
    assert model._companions() == set()
    big = np.repeat(np.repeat(analyzer, 4, axis=-1), 4, axis=-2)
    model.reconstruct(big, s_in, mask=np.repeat(np.repeat(mask, 4, axis=-1), 4, axis=-2),
                      stage_zero_axis=(1.0, 0.0, 0.0), outputs="frame")
    assert {k[0] for k in model._runners} == {"single_shot.onnx"}
    with pytest.raises(ValueError, match="outputs must be"):
        model.reconstruct(analyzer, s_in, mask=mask, outputs="some")


def _add_one_session(path):
    """A real session of ``y = x + 1`` on a ``(1, 4)`` float32 input."""
    import onnx
    from onnx import TensorProto, helper

    if not path.exists():
        one = helper.make_tensor("one", TensorProto.FLOAT, [1], [1.0])
        graph = helper.make_graph([helper.make_node("Add", ["x", "one"], ["y"])], "add_one",
                                  [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
                                  [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4])], [one])
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
    return ort.InferenceSession(str(path), providers=[devices.CPU])


def test_a_captured_graph_serves_only_the_buffers_it_was_captured_with(tmp_path):
    """A CUDA graph replays at the addresses it was captured with, whatever is bound later (on an
    H200 a device-route frame after a host-route frame came back as zeros). So a run with other
    buffers than the capturing run's takes a fresh session; the same buffers keep it. Played on
    the CPU with real bindings: the reopenings are counted, and every result is checked."""
    from polrig.models.runtime import _Runner

    path = tmp_path / "add_one.onnx"
    reopened = []

    def reopen():
        reopened.append(1)
        return _add_one_session(path)

    runner = _Runner(_add_one_session(path), cuda_graph=True, fallback=None, reopen=reopen, device="cpu")
    rng = np.random.default_rng(3)
    a, b = (rng.normal(size=(1, 4)).astype(np.float32) for _ in range(2))
    np.testing.assert_array_equal(runner.run({"x": a})["y"], a + 1)
    np.testing.assert_array_equal(runner.run({"x": b})["y"], b + 1)  # its own buffers, refilled
    assert reopened == []
    v1 = ort.OrtValue.ortvalue_from_numpy(a, "cpu", 0)
    v2 = ort.OrtValue.ortvalue_from_numpy(b, "cpu", 0)
    for value, want, count in ((v1, a, 1), (v1, a, 1), (v2, b, 2), (v2, b, 2)):
        np.testing.assert_array_equal(runner.run_device({"x": value}, "cpu")["y"].numpy(), want + 1)
        assert len(reopened) == count
    np.testing.assert_array_equal(runner.run({"x": a})["y"], a + 1)  # back to the host's buffers
    assert len(reopened) == 3
    # without CUDA graphs nothing is captured, and no buffers are owned
    plain = _Runner(_add_one_session(path), device="cpu")
    plain.run({"x": a})
    np.testing.assert_array_equal(plain.run_device({"x": v2}, "cpu")["y"].numpy(), b + 1)


def test_host_and_device_routes_keep_their_own_sessions(capture):
    """One model serving both routes (the device route hands some options to the host route)
    gives each its own fixed-size session, so each keeps its own CUDA graph."""
    from benchmarks.bench_single_shot import COLOUR, synthetic_raw
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.sensor.frame import Frame, FrameMeta

    model = SingleShotModel.load(threads=1, fixed_sizes=True)
    meta = FrameMeta(frame_id=0, timestamp_s=0.0, exposure_us=10000.0, gain_db=0.0, pixel_format="Mono16",
                     layout=COLOUR, bit_depth=12, black_level_dn=64.0)
    frame = Frame(raw=synthetic_raw((128, 128), np.random.default_rng(0), COLOUR), meta=meta)
    opts = SingleShotOptions(sigma=False)
    a = SingleShot(model, "host").frame(frame, 0.0, opts).mueller
    b = SingleShot(model, "device").frame(frame, 0.0, opts).mueller
    assert {k[2] for k in model._runners} == {"host", "device"}
    ok = np.isfinite(a) & np.isfinite(b)
    assert np.max(np.abs(a[ok] - b[ok])) <= 1e-5 * np.max(np.abs(a[ok]))
