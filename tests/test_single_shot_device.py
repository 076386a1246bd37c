"""Where the single-shot networks run (issue 22, item 3) and the full-resolution path (item 1),
on a CPU-only machine: the provider selection and fallback rules of :mod:`polrig.models.devices` against
the real ``onnxruntime.get_available_providers()`` and real sessions, ``polrig infer --device``
and ``--resolution full`` end to end, and :mod:`polrig.models.full_resolution` against closed forms
(upsampling of a linear ramp is exact, the lifted image reproduces the full-resolution
measurement up to the network's own misfit, the support of a clipped sample)."""

from __future__ import annotations

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from polrig.models import devices  # noqa: E402
from polrig.models.full_resolution import lift, upsample  # noqa: E402
from polrig.models.runtime import WEIGHTS_DIR  # noqa: E402

HAS_CUDA = devices.CUDA in ort.get_available_providers()
HAS_WEIGHTS = (WEIGHTS_DIR / "single_shot.onnx").is_file()


# -- provider selection ------------------------------------------------------------------------
@pytest.mark.parametrize("device, available, gpus, expected", [
    ("auto", [devices.CPU], 1, [devices.CPU]),
    ("auto", ["AzureExecutionProvider", devices.CPU], 1, [devices.CPU]),
    ("auto", [devices.CUDA, devices.CPU], 1, [devices.CUDA, devices.CPU]),
    ("auto", ["TensorrtExecutionProvider", devices.CUDA, devices.CPU], 2, [devices.CUDA, devices.CPU]),
    # the gpu extra on a machine without an NVIDIA device: auto stays on the CPU
    ("auto", [devices.CUDA, devices.CPU], 0, [devices.CPU]),
    ("cpu", [devices.CUDA, devices.CPU], 1, [devices.CPU]),
    ("cuda", [devices.CUDA, devices.CPU], 1, [devices.CUDA, devices.CPU]),
    # a forced cuda is tried (check_session refuses it if it does not start)
    ("cuda", [devices.CUDA, devices.CPU], 0, [devices.CUDA, devices.CPU]),
])
def test_choose_providers(device, available, gpus, expected):
    assert devices.choose_providers(device, available, gpus) == expected


def test_cuda_device_count_is_a_number_without_a_gpu_too():
    n = devices.cuda_device_count()
    assert isinstance(n, int) and n >= 0
    # what auto decides on this machine follows the count
    assert devices.choose_providers("auto", [devices.CUDA, devices.CPU])[0] == (devices.CUDA if n else devices.CPU)


def test_accepted_options_report_refusals_in_one_line_each():
    """The CUDA-graph refusal path, fed what onnxruntime reports (no GPU needed)."""
    want = {"enable_cuda_graph": "1"}
    assert devices.accepted_options(want, {"enable_cuda_graph": "1", "device_id": "0"}) == (want, [])
    options, notes = devices.accepted_options(want, {"enable_cuda_graph": "0"})
    assert options == {"enable_cuda_graph": "0"} and notes == ["onnxruntime runs enable_cuda_graph=0 (asked 1)"]
    options, notes = devices.accepted_options(
        want, None, error="[ONNXRuntimeError] : 1 : FAIL : This session cannot use the graph capture feature as "
                          "requested by the user as all compute graph nodes have not been partitioned to the CUDA EP.\nmore")
    assert options == {} and len(notes) == 1 and "\n" not in notes[0]
    assert notes[0].startswith("onnxruntime refused enable_cuda_graph=1 (") and notes[0].endswith("running without")
    assert devices.accepted_options(want, None)[1] == ["the provider did not start: none of its options apply"]
    # an option the provider does not report keeps the asked value
    assert devices.accepted_options({"use_tf32": "0"}, {}) == ({"use_tf32": "0"}, [])


def test_forced_cuda_without_cuda_is_one_line_usage_error():
    from polrig.errors import EXIT_USAGE, exit_code_for

    with pytest.raises(devices.DeviceUnavailable) as err:
        devices.choose_providers("cuda", [devices.CPU])
    assert "\n" not in str(err.value) and "--device cpu" in str(err.value)
    assert exit_code_for(err.value) == EXIT_USAGE
    with pytest.raises(ValueError, match="device must be one of"):
        devices.choose_providers("gpu", [devices.CPU])


def test_a_forced_cuda_session_that_fell_back_to_the_cpu_is_refused_auto_accepts_it():
    requested = [devices.CUDA, devices.CPU]
    assert devices.check_session("cuda", requested, [devices.CUDA, devices.CPU]) == devices.CUDA
    with pytest.raises(devices.DeviceUnavailable, match="did not start"):
        devices.check_session("cuda", requested, [devices.CPU])
    assert devices.check_session("auto", requested, [devices.CPU]) == devices.CPU


def test_session_providers_give_cuda_heuristic_convolution_search_and_the_cpu_nothing():
    """CUDA sessions ask cuDNN's heuristics for convolution algorithms (no benchmarking run at
    each new input shape), TF32 off, CUDA graphs where asked; the CPU provider gets no options,
    and the order is kept."""
    assert devices.session_providers([devices.CUDA, devices.CPU]) == [
        (devices.CUDA, {"cudnn_conv_algo_search": "HEURISTIC", "use_tf32": "0"}), (devices.CPU, {})]
    assert devices.session_providers([devices.CUDA], cuda_graph=True) == [
        (devices.CUDA, {"cudnn_conv_algo_search": "HEURISTIC", "use_tf32": "0", "enable_cuda_graph": "1"})]
    assert devices.session_providers([devices.CPU]) == [(devices.CPU, {})]
    # a fresh dict each time: a caller's edit cannot change the next session's options
    devices.session_providers([devices.CUDA])[0][1]["x"] = "1"
    assert devices.session_providers([devices.CUDA])[0][1] == devices.CUDA_OPTIONS


def test_loading_cuda_libraries_reports_on_stderr_and_needs_nothing_from_an_older_onnxruntime(capsys):
    """onnxruntime-gpu's ``preload_dlls`` is called with CUDA and cuDNN (not MSVC) and what it
    prints lands on stderr, not in a command's output; an onnxruntime without it is left alone."""
    import types

    calls = []

    def preload_dlls(**kw):
        calls.append(kw)
        print("Failed to load libcudart.so.13: not found")

    devices.load_cuda_libraries(types.SimpleNamespace(preload_dlls=preload_dlls))
    out, err = capsys.readouterr()
    assert calls == [{"cuda": True, "cudnn": True, "msvc": False}]
    assert out == "" and "libcudart" in err
    devices.load_cuda_libraries(types.SimpleNamespace())  # onnxruntime < 1.21: nothing to do
    assert capsys.readouterr() == ("", "")


def test_this_onnxruntime_auto_choice_opens_a_real_session():
    """The automatic choice on this machine's real onnxruntime gives a session whose first
    provider is the one chosen (CUDA on a GPU machine with the gpu extra, else the CPU)."""
    if not HAS_WEIGHTS:
        pytest.skip("no shipped graph")
    from polrig.models.runtime import SingleShotModel

    model = SingleShotModel.load(device="auto", threads=1)
    assert model.provider == devices.choose_providers("auto", ort.get_available_providers())[0]
    assert model.provider == model.session.get_providers()[0]
    assert SingleShotModel.load(device="cpu", threads=1).provider == devices.CPU
    if not HAS_CUDA:
        with pytest.raises(devices.DeviceUnavailable):
            SingleShotModel.load(device="cuda")


# -- full resolution -------------------------------------------------------------------------
@pytest.mark.parametrize("period", [(2, 2), (4, 4)])
def test_upsampling_a_ramp_at_cell_centres_is_exact(period):
    """A plane linear in the raw coordinates, sampled at the superpixel cell centres
    (``p i + (p - 1) / 2``), comes back exactly inside the frame (bilinear reproduces linear
    functions; the outermost half cells are extrapolated as edge values)."""
    ph, pw = period
    h, w = 6, 7
    yc, xc = ph * np.arange(h) + (ph - 1) / 2, pw * np.arange(w) + (pw - 1) / 2
    plane = (0.3 * yc[:, None] - 0.7 * xc[None, :] + 5).astype(np.float32)
    shape = (h * ph + 1, w * pw + 1)  # a partial last cell too
    up = upsample(plane, period, shape)
    y, x = np.arange(shape[0]), np.arange(shape[1])
    truth = 0.3 * y[:, None] - 0.7 * x[None, :] + 5
    inner = (slice(ph // 2 + (ph - 1) // 2, (h - 1) * ph + 1), slice(pw // 2 + (pw - 1) // 2, (w - 1) * pw + 1))
    np.testing.assert_allclose(up[inner], truth[inner], atol=1e-4)
    assert up.shape == shape


@pytest.mark.parametrize("period, mask_kind", [((2, 2), "inner"), ((4, 4), "inner"), ((2, 2), "random"),
                                               ((4, 4), "random")])
def test_lift_reproduces_the_full_resolution_measurement_and_keeps_the_prior(period, mask_kind):
    """``M_full s_in = up(M s_in) + S_full - up(S)``: where the network reproduces its
    observation on the grid (``M s_in = S``) the lifted image reproduces the full-resolution
    measurement exactly; the part of the matrix orthogonal to ``s_in`` is the upsampled grid
    answer, normalised by the upsampled mask (along a ragged object edge too); the background
    is 0."""
    rng = np.random.default_rng(1)
    (h, w) = (8, 10)
    shape = (period[0] * h + 1, period[1] * w + 1)  # with a partial last cell
    s_in = np.array([0.5, 0.3, -0.2])
    mask = np.zeros((h, w), bool)
    mask[1:-1, 1:-1] = True
    if mask_kind == "random":
        mask = rng.random((h, w)) < 0.6
    m = rng.normal(size=(1, 3, 3, h, w)).astype(np.float32) * mask
    s_grid = np.einsum("crkhw,k->crhw", m, s_in).astype(np.float32)  # consistent: no misfit
    s_full = rng.normal(size=(1, 3) + shape).astype(np.float32)
    s_full[0, 0, 0, 0] = np.nan  # a clipped sample's support: no detail there
    out, inside = lift(m, mask, s_grid, s_full, s_in, period)
    assert out.shape == (1, 3, 3) + shape and out.dtype == np.float32
    assert not out[..., ~inside].any()
    rendered = np.einsum("crkhw,k->crhw", out, s_in)
    ok = inside & np.isfinite(s_full[0, 0])
    np.testing.assert_allclose(rendered[..., ok], s_full[..., ok], atol=1e-4)
    # orthogonal to s_in: the grid answer, upsampled
    v = np.cross(s_in, [0.0, 0.0, 1.0])
    norm = upsample(mask.astype(np.float32), period, shape)
    grid = np.einsum("crkhw,k->crhw", m, v)
    expected = upsample(grid, period, shape) / np.where(inside, norm, 1.0)
    np.testing.assert_allclose(np.einsum("crkhw,k->crhw", out, v)[..., inside], expected[..., inside], atol=1e-4)


def test_nan_support_of_clipped_samples_is_the_clipped_indicator_support():
    """Full resolution marks clipped pixels by NaN propagation through the demosaic; it must
    be the support the superpixel path computes from the clipped indicator."""
    from polrig.sensor.analyzer import resolve_layout
    from polrig.sensor.demosaic import demosaic_float

    rng = np.random.default_rng(2)
    for name in ("imx250myr", "imx250mzr"):
        lay = resolve_layout(name)
        x = rng.uniform(10, 100, (32, 40)).astype(np.float32)
        clipped = rng.random(x.shape) < 0.01
        via_nan = ~np.all(np.isfinite(demosaic_float(np.where(clipped, np.nan, x).astype(np.float32), lay,
                                                     "bilinear")), axis=(0, 1))
        via_indicator = demosaic_float(clipped.astype(np.float32), lay, "bilinear").max(axis=(0, 1)) > 0
        np.testing.assert_array_equal(via_nan, via_indicator)


# -- polrig infer ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    from polrig.cli import main

    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "128x96", "--states", "0", "--no-exr", "--out", str(out)]) == 0
    return next(out.glob("*_state00.png"))


@pytest.mark.skipif(not HAS_WEIGHTS, reason="no shipped graph")
def test_infer_records_the_provider_and_full_resolution_is_the_raw_size(frame, tmp_path, capsys):
    from polrig.cli import main
    from polrig.formats.exr import read_mueller_exr

    sp, full = tmp_path / "sp.exr", tmp_path / "full.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--device", "cpu", "--out", str(sp)]) == 0
    assert "networks ran on CPUExecutionProvider" in capsys.readouterr().out
    assert main(["infer", str(frame), "--state-deg", "0", "--resolution", "full", "--out", str(full)]) == 0
    a, b = read_mueller_exr(sp), read_mueller_exr(full)
    assert a.metadata["execution_provider"] == devices.CPU or HAS_CUDA
    assert b.mueller.shape[-2:] == (96, 128) and a.mueller.shape[-2:] == (24, 32)  # colour 4x4 cells
    assert b.metadata["resolution"] == "full" and b.metadata["demosaic"] == "bilinear"
    # the lifted image averaged back over the cells is close to the grid answer (on valid pixels:
    # the mask planes are reason bits, 0 = valid, as in a session's result)
    cells = b.mueller.reshape(*b.mueller.shape[:3], 24, 4, 32, 4).mean(axis=(-3, -1))
    obj = (a.extra["mask.G"] == 0) & (b.extra["mask.G"].reshape(24, 4, 32, 4).max(axis=(1, 3)) == 0)
    err = np.abs(cells - a.mueller)[..., obj].mean() / np.abs(a.mueller[..., obj]).mean()
    assert err < 0.25, err


@pytest.mark.parametrize("argv, needle", [
    (["--device", "cuda"], "--device cuda"),
    (["--resolution", "full", "--demosaic", "superpixel"], "--resolution full"),
    (["--resolution", "full", "--sigma"], "--sigma"),
])
def test_infer_refuses_what_cannot_run_in_one_line(frame, tmp_path, capsys, argv, needle):
    from polrig.cli import main

    if argv[:2] == ["--device", "cuda"] and HAS_CUDA:
        pytest.skip("CUDA is available here")
    out = tmp_path / "x.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err and not out.exists()


@pytest.mark.parametrize("compression", ["none", "zip"])
def test_result_exr_round_trips_bit_exactly_compressed_or_not(tmp_path, compression):
    """A single-shot result through the one result writer (:func:`polrig.formats.exr.write_result_exr`;
    ``polrig infer`` writes uncompressed, a session ZIP by default): both lossless, its mask the
    reason bits, its header the route's."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShotResult
    from polrig.formats.exr import read_mueller_exr, write_result_exr
    from polrig.solve.reference import DARK

    rng = np.random.default_rng(3)
    m = rng.normal(size=(3, 3, 3, 8, 12)).astype(np.float32)
    m[0, 1, 2, 3, 4] = np.nan
    obj = rng.random((8, 12)) > 0.3
    mask = np.broadcast_to(np.where(obj, 0, DARK).astype(np.uint8), (3, 8, 12))
    zeros = np.zeros((3, 8, 12), np.float32)
    result = SingleShotResult(m, np.abs(m), np.zeros_like(m), mask, zeros, obj, SingleShotOptions(),
                              provider=devices.CPU)
    planes = ("mueller", "mask")
    path = write_result_exr(tmp_path / "m.exr", result, planes=planes, compression=compression,
                            metadata=result.header(planes))
    back = read_mueller_exr(path)
    np.testing.assert_array_equal(back.mueller, m)
    for k, c in enumerate("RGB"):
        np.testing.assert_array_equal(back.extra[f"mask.{c}"], mask[k])
    assert not any(p.startswith("sigma") for p in back.extra)
    assert back.metadata["execution_provider"] == devices.CPU
    assert back.metadata["planes"] == {"mask": "reason bits, 0 = valid"}


def test_the_accuracy_tool_samples_a_mosaic_the_superpixel_demosaic_inverts():
    """:func:`polrig.models.evaluate_full_resolution.mosaic` keeps each pixel's own (colour, angle)
    image: analyzer images constant per cell come back exactly from the superpixel demosaic,
    and :func:`cell_mean` is that demosaic's averaging."""
    from polrig.models.evaluate_full_resolution import cell_mean, mosaic
    from polrig.sensor.analyzer import resolve_layout
    from polrig.sensor.demosaic import demosaic_float

    lay = resolve_layout("imx250myr")
    rng = np.random.default_rng(5)
    cells = rng.uniform(0, 1, (3, 4, 6, 5)).astype(np.float32)
    analyzer = np.repeat(np.repeat(cells, 4, axis=-2), 4, axis=-1)  # (3, 4, 24, 20)
    np.testing.assert_allclose(demosaic_float(mosaic(analyzer, lay), lay, "superpixel"), cells, atol=1e-6)
    np.testing.assert_allclose(cell_mean(analyzer, (4, 4)), cells, atol=1e-6)
