"""The device route (issue 31, items 3-4: :mod:`polrig.models.device_graphs`,
:mod:`polrig.models.device_path`) through the CPU provider against today's numpy steps.

Per step the tolerance is stated where it is not bitwise (relative to the output's largest
magnitude): the graphs add and multiply in the numpy step's order where the step is elementwise,
so those are bitwise; filters and resampling (OpenCV vs onnxruntime kernels) sum in another
order: within a few float32 roundings (``STEP_RTOL``). The whole route equals ``polrig infer``'s
result (the host route) within ``ROUTE_RTOL`` for superpixel and full resolution, colour and
mono; the object mask, the reason bits and the scale are equal."""

from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("onnxruntime")

from polrig.models import device_graphs as dg  # noqa: E402
from polrig.models import runtime as rt  # noqa: E402
from polrig.models.device_path import (  # noqa: E402
    DevicePath,
    bilinear_inputs,
    scale_from_tail,
    superpixel_cells,
    tail_count,
)
from polrig.sensor.layouts import IMX250MYR, IMX250MZR  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parents[1]
HAS_WEIGHTS = (REPO / "models" / "weights" / "single_shot.onnx").is_file()
needs_model = pytest.mark.skipif(not HAS_WEIGHTS, reason="no single-shot model in models/weights")
#: Filters and resampling: onnxruntime's kernels against OpenCV's (another summation order).
STEP_RTOL = 2e-6
#: The whole route (its inputs to the networks differ by the steps' roundings at most).
ROUTE_RTOL = 1e-5
LAYOUTS = {"colour": IMX250MYR, "mono": IMX250MZR}


class _CpuModel:
    """What :class:`DevicePath` reads of a model to run the graphs alone (no networks)."""

    provider = "CPUExecutionProvider"
    _session_options = {"intra_op_num_threads": "1"}


@pytest.fixture(scope="module")
def path():
    return DevicePath(_CpuModel())


def _raw(shape, seed, bits=12):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 2 ** bits, size=shape).astype(np.uint16)


def _close(a, b, rtol=STEP_RTOL):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    np.testing.assert_array_equal(a[np.isinf(b)], b[np.isinf(b)])  # inf where the other has it
    ok = np.isfinite(b)
    scale = max(float(np.max(np.abs(b[ok]), initial=0.0)), 1e-30)
    assert float(np.max(np.abs(a[ok] - b[ok]), initial=0.0)) <= rtol * scale


# -- the shipped files ------------------------------------------------------------------------------
def test_the_shipped_graphs_are_what_the_builder_makes(tmp_path):
    """The files in models/weights/device are this module's graphs as they are now (re-made by
    ``python -m polrig.models.device_graphs``) and graphs.json names them."""
    made = dg.build_all(tmp_path)
    shipped = json.loads((dg.GRAPH_DIR / dg.MANIFEST).read_text())
    assert shipped["sha256"] == made["sha256"] and shipped["opset"] == dg.OPSET
    for name, sha in made["sha256"].items():
        assert hashlib.sha256((dg.GRAPH_DIR / name).read_bytes()).hexdigest() == sha


# -- per step -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["colour", "mono"])
@pytest.mark.parametrize("to_adc", [1.0, 0.25])
def test_superpixel_equals_the_numpy_demosaic_bitwise(path, kind, to_adc):
    from polrig.sensor.demosaic import demosaic
    from polrig.sensor.stokes import saturation_mask

    lay = LAYOUTS[kind]
    raw = _raw((37, 50), 1)  # partial last cells are dropped
    raw[3:6, 8:12] = 4095
    x = raw.astype(np.float64) * to_adc if to_adc != 1 else raw
    black, sat = 64.0 * to_adc, 4095.0 * to_adc
    out = path.numpy("superpixel", {"raw": raw, "to_adc": [to_adc], "black": [black], "saturation": [sat],
                                    "cells": superpixel_cells(lay)})
    np.testing.assert_array_equal(out["analyzer"], demosaic(x, lay, "superpixel", black_level_dn=black))
    want = saturation_mask(x, lay, "superpixel", sat)
    np.testing.assert_array_equal(np.broadcast_to(out["clipped"], want.shape), want)


@pytest.mark.parametrize("kind", ["colour", "mono"])
def test_bilinear_equals_the_numpy_demosaic_with_clipped_samples_nan(path, kind):
    """The route's full-resolution demosaic: black removed, clipped samples NaN, the normalised
    tent; NaN exactly where the numpy step has it."""
    from polrig.sensor.demosaic import demosaic_float, preprocess

    lay = LAYOUTS[kind]
    raw = _raw((40, 52), 2)
    raw[10:12, 20:23] = 4095
    x = preprocess(raw.astype(np.float64), black_level_dn=64.0)
    x[raw >= 4095.0] = np.nan
    want = demosaic_float(x, lay, "bilinear")
    out = path.numpy("bilinear", {"raw": raw, "to_adc": [1.0], "black": [64.0], "saturation": [4095.0],
                                  **bilinear_inputs(lay)})["analyzer"]
    _close(out, want)


def test_stokes_equals_the_solver_bitwise_nan_included(path):
    from polrig.sensor.stokes import stokes_from_analyzers

    a = np.random.default_rng(3).normal(100, 50, (3, 4, 9, 11)).astype(np.float32)
    a[0, 1, 2, 3] = np.nan  # a 45-deg sample: S0 and S2 NaN, S1 not (the solver skips zero weights)
    a[2, 0, 4, 4] = np.inf
    np.testing.assert_array_equal(path.numpy("stokes", {"analyzer": a})["stokes"], stokes_from_analyzers(a))


def test_snr_and_clipped_equal_the_preview_rule_bitwise(path):
    from polrig.app.preview import s0_snr
    from polrig.sensor.noise import SensorModel

    s = np.random.default_rng(4).normal(200, 300, (3, 3, 8, 10)).astype(np.float32)
    s[1, 2, 3, 3] = np.nan
    s[0, 0, 1, 1] = np.nan
    model = SensorModel()
    per_dn, offset = model.variance_terms(5000.0)
    out = path.numpy("s0_snr", {"stokes": s, "half_per_dn": [np.float32(0.5 * per_dn)], "offset": [offset]})
    np.testing.assert_array_equal(out["snr"], s0_snr(s[:, 0], model, 5000.0))
    np.testing.assert_array_equal(out["clipped"], ~np.all(np.isfinite(s), axis=1))


@pytest.mark.parametrize("colours", [1, 3])
def test_the_mask_statistic_equals_default_masks_s0_bitwise(path, colours):
    a = np.random.default_rng(5).gamma(2.0, 300.0, (colours, 4, 20, 30)).astype(np.float32)
    s0 = path.numpy("s0_mean", {"analyzer": a})["s0"]
    np.testing.assert_array_equal(s0, np.mean(rt.stokes_s0(a), axis=0))
    np.testing.assert_array_equal(rt.mask_from_s0(s0), rt.default_mask(a))


@settings(max_examples=25, deadline=None)
@given(h=st.integers(1, 140), w=st.integers(1, 140), colours=st.sampled_from([1, 3]),
       seed=st.integers(0, 2 ** 16), ties=st.booleans(), reps=st.sampled_from([1, 3]))
def test_the_scale_from_the_devices_tail_equals_default_scale_exactly(h, w, colours, seed, ties, reps):
    """Small and large samples (numpy's float32 interpolation below MIN_SIZE, the tail's float64
    above), ties, a mono frame's values repeated to the networks' colours."""
    path = _path_for_hypothesis()
    rng = np.random.default_rng(seed)
    a = rng.gamma(2.0, 500.0, (colours, 4, h, w)).astype(np.float32)
    if ties:
        a = np.round(a / 50) * 50
    mask = rng.random((h, w)) < 0.7
    wide = np.repeat(a, reps, axis=0)
    n = int(mask.sum()) * colours * reps * 4
    need = tail_count(n)
    got = 1.0
    if n:
        tail = path.numpy("scale_tail", {"analyzer": a, "mask": mask.astype(np.float32),
                                         "k": np.array([-(-need // reps)], np.int64)})["tail"]
        got = scale_from_tail(np.repeat(tail, reps)[:need], n)
    assert got == rt.default_scale(wide, mask)


_HYP_PATH: list = []


def _path_for_hypothesis() -> DevicePath:
    if not _HYP_PATH:
        _HYP_PATH.append(DevicePath(_CpuModel()))
    return _HYP_PATH[0]


def test_the_network_input_equals_reconstructs_bitwise(path):
    a = np.random.default_rng(6).gamma(2.0, 300.0, (1, 4, 13, 21)).astype(np.float32)
    mask = a[0, 0] > 400
    sc = 1234.567
    out = path.numpy("network_input", {"analyzer": a, "colours": np.array([3, 4, 13, 21], np.int64),
                                       "scale": [sc], "mask": mask.astype(np.float32),
                                       "pads": np.array([3, 3], np.int64)})
    an = np.repeat(a, 3, axis=0) / sc
    np.testing.assert_array_equal(out["net_analyzer"][0], np.pad(an, [(0, 0), (0, 0), (0, 3), (0, 3)], mode="edge"))
    np.testing.assert_array_equal(out["net_mask"][0, 0], np.pad(mask.astype(np.float32), [(0, 3), (0, 3)]))


@pytest.mark.parametrize("shape, small", [((256, 320), (128, 160)), ((616, 512), (152, 128))])
def test_the_probes_reduction_equals_reduce_inputs(path, shape, small):
    """Integer and fractional area factors (the full colour sensor's 616x512 grid -> 152x128)."""
    rng = np.random.default_rng(7)
    a = rng.gamma(2.0, 0.3, (1, 3, 4) + shape).astype(np.float32)
    m = (rng.random((1, 1) + shape) < 0.5).astype(np.float32)
    m[..., : shape[0] // 2, :] = 1.0
    wo = rt.view_directions(shape)[None]
    out = path.numpy("reduce", {"net_analyzer": a, "net_mask": m, "wo": wo,
                                "area_y": dg.area_matrix(shape[0], small[0]),
                                "area_x": dg.area_matrix(shape[1], small[1]).T.copy()})
    want = rt.reduce_inputs(a, m, wo, small)
    _close(out["probe_analyzer"], want[0])
    _close(out["probe_wo"], want[2])
    # the mask's threshold at one half: equal except where the reduced value is within rounding of it
    np.testing.assert_array_equal(out["probe_mask"], want[1])


def test_the_masked_mean_equals_mean_direction(path):
    wi = rt.view_directions((40, 50))[None]
    m = np.zeros((1, 1, 40, 50), np.float32)
    m[..., 5:30, 10:45] = 1
    mean = path.numpy("masked_mean", {"wi": wi, "mask": m})["mean"]
    _close(mean / np.linalg.norm(mean), rt.mean_direction(wi, m))


@pytest.mark.parametrize("mono", [False, True])
def test_post_equals_the_rotation_and_scaling_of_run_rig_frame_and_reconstruct(path, mono):
    """Crop, ``M R(theta)`` per pixel from the network's ``wi``, the mono colour mean, DN:
    bitwise for a colour sensor, within the mean's rounding (``sum / 3`` against ``sum * 1/3``)
    for a mono one."""
    rng = np.random.default_rng(8)
    hp, wp, h, w = 24, 32, 21, 30
    mu = rng.normal(0, 0.3, (1, 3, 3, 3, hp, wp)).astype(np.float32)
    wi = rng.normal(0, 1, (1, 3, hp, wp)).astype(np.float32)
    wi[:, 2] -= 2.0
    wi[0, :, 0, 0] = 0.0  # a degenerate direction: theta = 0
    axis, model_axis = np.array([[0.3, -0.9, 0.3]]), np.array([0.0, -1.0, 0.0])
    mask = rng.random((h, w)) < 0.8
    sc = 2500.25
    a, b = (v / np.linalg.norm(v) for v in (axis.reshape(3), model_axis))
    axes = np.stack([a, b, np.cross(a, b), [float(np.sum(a * b)), 0, 0]]).astype(np.float32)
    mix = np.full((1, 3), 1 / 3, np.float32) if mono else np.eye(3, dtype=np.float32)
    out = path.numpy("post", {"mueller": mu, "wi": wi, "size": np.array([h, w], np.int64), "axes": axes,
                              "colour_mix": mix, "mask": mask.astype(np.float32), "scale": [sc]})["mueller_dn"]
    cp, sp = rt.incident_rotation(wi, axis, model_axis, vector_axis=1)
    want = rt.rotate_incident_columns(mu, cp.reshape(1, 1, hp, wp), sp.reshape(1, 1, hp, wp))[0, ..., :h, :w]
    if mono:
        want = want.mean(axis=0, keepdims=True)
    want = np.multiply(want, (sc * mask).astype(np.float32), dtype=np.float32)
    if mono:
        _close(out, want, 1e-6)
    else:
        np.testing.assert_array_equal(out, want)


@pytest.mark.parametrize("kind, raw_shape", [("colour", (98, 130)), ("mono", (96, 128))])
def test_lift_equals_the_full_resolution_lift(path, kind, raw_shape):
    """Partial last cells (edge repeated), the object's edge band, a clipped sample's NaN."""
    from polrig.models.full_resolution import lift

    lay = LAYOUTS[kind]
    ph, pw = lay.period
    c = lay.n_colours
    h, w = raw_shape[0] // ph, raw_shape[1] // pw
    rng = np.random.default_rng(9)
    mask = np.zeros((h, w), bool)
    mask[3: h - 4, 5: w - 3] = True
    mu = (rng.normal(0, 100, (c, 3, 3, h, w)) * mask).astype(np.float32)
    s = rng.normal(500, 100, (c, 3, h, w)).astype(np.float32)
    sf = rng.normal(500, 100, (c, 3) + raw_shape).astype(np.float32)
    sf[0, 1, 30, 40] = np.nan
    s_in = np.array([1.0, 0.5, -0.2], np.float32)
    coef = s_in.astype(np.float64)
    out = path.numpy("lift", {"mueller": mu, "mask": mask.astype(np.float32), "stokes": s, "stokes_full": sf,
                              "coef": (coef / (coef @ coef)).astype(np.float32),
                              "grid": np.array([h * ph, w * pw], np.int64),
                              "pads": np.array([raw_shape[0] - h * ph, raw_shape[1] - w * pw], np.int64)})
    want, inside = lift(mu, mask, s, sf, s_in, (ph, pw))
    np.testing.assert_array_equal(out["inside"], inside)
    _close(out["mueller_full"], want)


def test_the_grid_preview_is_the_elements_area_reduced_in_matrix_order(path):
    import cv2

    mu = np.random.default_rng(10).normal(0, 1, (3, 3, 3, 48, 64)).astype(np.float32)
    grid = path.numpy("grid_preview", {"mueller": mu, "area_y": dg.area_matrix(48, 20),
                                       "area_x": dg.area_matrix(64, 30).T.copy()})["grid"]
    assert grid.shape == (3, 60, 90)
    for r in range(3):
        for k in range(3):
            for c in range(3):
                _close(grid[c, 20 * r: 20 * r + 20, 30 * k: 30 * k + 30],
                       cv2.resize(mu[c, r, k], (30, 20), interpolation=cv2.INTER_AREA))


# -- the whole route -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Simulated frames: a 128x96 colour one with a clipped block, a 512x512 mono one (its
    256x256 network grid runs the light-direction probe)."""
    from polrig.cli import main
    from polrig.formats.rawio import read_raw, write_raw

    out = {}
    for kind, sensor, size in (("colour", "imx250myr", "128x96"), ("mono", "imx250mzr", "512x512")):
        d = tmp_path_factory.mktemp(kind)
        assert main(["sim", "render", "--size", size, "--states", "0", "--no-exr", "--sensor", sensor,
                     "--out", str(d)]) == 0
        f = read_raw(next(d.glob("*_state00.png")))
        if kind == "colour":
            raw = f.raw.copy()
            raw[40:48, 56:72] = 2 ** f.meta.bit_depth - 1
            f = type(f)(raw, f.meta)
            write_raw(d / "clipped.png", f)
        out[kind] = (f, d)
    return out


@needs_model
@pytest.mark.parametrize("kind", ["colour", "mono"])
@pytest.mark.parametrize("resolution", ["superpixel", "full"])
def test_the_device_route_equals_the_host_route(frames, kind, resolution):
    """Off the training axis (the input rotation, the refinement and, on the mono 256x256 grid,
    the probe run), with the calibrated sigma at superpixel resolution."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    model = SingleShotModel.load(device="cpu")
    host, device = SingleShot(model, "host"), SingleShot(model, "device")
    assert SingleShot(model).frame_route == "host"  # the CPU's declared route
    f = frames[kind][0]
    opts = SingleShotOptions(resolution)
    axis = (0.3, -0.9, 0.3)
    a = host.frame(f, 30.0, opts, stage_zero_axis=axis)
    b = device.frame(f, 30.0, opts, stage_zero_axis=axis)
    assert b.timings_s.keys() >= {"upload", "pre", "statistics", "network", "post", "copy_back"}
    assert a.scale == b.scale and a.incident_rotation_deg == pytest.approx(b.incident_rotation_deg, abs=1e-4)
    np.testing.assert_array_equal(a.object, b.object)
    np.testing.assert_array_equal(a.mask, b.mask)
    _close(b.mueller, a.mueller, ROUTE_RTOL)
    _close(b.snr, a.snr, 1e-6)
    _close(b.stokes, a.stokes, STEP_RTOL)  # what the displays read (polrig.gui.pipeline)
    from polrig.gui.pipeline import PolarizationData

    shown_a, shown_b = PolarizationData.from_single_shot(a, f), PolarizationData.from_single_shot(b, f)
    np.testing.assert_array_equal(shown_b.flags, shown_a.flags)
    if resolution == "superpixel":
        _close(b.sigma, a.sigma, 1e-4)


@needs_model
@pytest.mark.parametrize("kind", ["colour", "mono"])
def test_the_device_route_equals_polrig_infers_file(frames, tmp_path, kind):
    """``polrig infer`` (the CPU's host route) and the device route on the same raw file,
    superpixel and full resolution (the colour frame with a clipped block)."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.calibrations import nominal_calibration, single_shot_geometry
    from polrig.app.rig import load_rig_config
    from polrig.app.single_shot import SingleShot
    from polrig.cli import main
    from polrig.cli.commands._units import config_sensor_model
    from polrig.formats.exr import read_mueller_exr
    from polrig.models.runtime import SingleShotModel

    f, d = frames[kind]
    src = d / "clipped.png" if kind == "colour" else next(d.glob("*_state00.png"))
    for resolution in ("superpixel", "full"):
        out = tmp_path / f"{resolution}.exr"
        assert main(["infer", str(src), "--state-deg", "0", "--device", "cpu",
                     "--resolution", resolution, "--out", str(out)]) == 0
        exr = read_mueller_exr(out)
        config = load_rig_config(None)
        r = SingleShot(SingleShotModel.load(device="cpu"), "device").frame(
            f, 0.0, SingleShotOptions(resolution, sigma=False), sensor=config_sensor_model(config),
            geometry=single_shot_geometry(nominal_calibration(), config))
        _close(r.mueller, exr.mueller, ROUTE_RTOL)
        planes = sorted(k for k in exr.extra if k.startswith("mask"))
        assert len(planes) == r.mask.shape[0]
        for k, name in enumerate(["mask.R", "mask.G", "mask.B"] if kind == "colour" else planes):
            np.testing.assert_array_equal(exr.extra[name], r.mask[k])


@needs_model
def test_the_device_route_declines_what_it_does_not_cover_in_one_line():
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.models.runtime import SingleShotModel

    p = DevicePath(SingleShotModel.load(device="cpu"))
    assert p.supports(SingleShotOptions(), (512, 612)) == ""
    assert p.supports(SingleShotOptions("full"), (512, 612)) == ""
    for opts, text in ((SingleShotOptions(network_binning=2), "binning"),
                       (SingleShotOptions(mirror_average=True), "mirror"),
                       (SingleShotOptions("superpixel", "bilinear"), "bilinear network input"),
                       (SingleShotOptions("full", "newton"), "newton detail"),
                       (SingleShotOptions(geometry=True), "geometry")):
        why = p.supports(opts, (512, 612))
        assert text in why and "\n" not in why
    assert "1.5 Mpx" in p.supports(SingleShotOptions(), (2048, 2448))


def test_a_capture_refused_at_the_first_bound_run_falls_back_to_the_plain_session():
    """:meth:`polrig.models.runtime._Runner.run_device` (the networks on device buffers): where the
    CUDA-graph session's first run fails, the plain session runs the same bound buffers, and the
    outputs are kept for the next frame (the same objects)."""
    import onnxruntime as ort

    from polrig.models.runtime import _Runner

    plain = ort.InferenceSession(str(dg.GRAPH_DIR / "masked_mean.onnx"), providers=["CPUExecutionProvider"])

    class RefusesCapture:
        def __init__(self, s):
            self._s = s

        def run_with_iobinding(self, binding, run_options=None):
            raise RuntimeError("graph capture failed")

        def __getattr__(self, name):
            return getattr(self._s, name)

    refused = []
    runner = _Runner(RefusesCapture(plain), cuda_graph=True, fallback=lambda exc: refused.append(exc) or plain)
    wi = rt.view_directions((6, 7))[None]
    m = np.ones((1, 1, 6, 7), np.float32)
    feed = {"wi": ort.OrtValue.ortvalue_from_numpy(wi), "mask": ort.OrtValue.ortvalue_from_numpy(m)}
    out = runner.run_device(feed, "cpu")
    assert len(refused) == 1 and runner.cuda_graph is False and runner.session is plain
    np.testing.assert_array_equal(out["mean"].numpy(), plain.run(None, {"wi": wi, "mask": m})[0])
    assert runner.run_device(feed, "cpu")["mean"] is out["mean"]


@needs_model
def test_the_live_grid_is_the_frames_mueller_image_at_display_size_and_probes_every_nth_frame(frames, monkeypatch):
    """The device route's live frame: the nine elements area-averaged to a long side of a third
    of the display, laid out as the matrix, the only image copied back; the probe (on the mono
    256x256 grid) on every ``probe_every``-th frame only. The host route's live frame is its frame."""
    import cv2

    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    f = frames["mono"][0]
    opts = SingleShotOptions(sigma=False)
    axis = {"stage_zero_axis_camera": (0.3, -0.9, 0.3)}
    model = SingleShotModel.load(device="cpu")
    route = SingleShot(model, "device")
    path = route.device_path()
    passes = []
    real = DevicePath._network
    monkeypatch.setattr(DevicePath, "_network", lambda self, outputs, feed: passes.append(outputs)
                        or real(self, outputs, feed))
    path.probe_every = 3
    grids = [route.live(f, 30.0, opts, max_display_px=96, geometry=axis) for _ in range(4)]
    assert passes == ["probe", "frame", "frame", "frame", "probe", "frame"]
    whole = route.frame(f, 30.0, opts, geometry=axis)  # probes: what the first live frame showed
    grid = grids[0].preview_grid
    assert grid.shape == (1, 96, 96) and not np.any(grids[0].mask & 2)
    for r in range(3):
        for k in range(3):
            _close(grid[0, 32 * r: 32 * r + 32, 32 * k: 32 * k + 32],
                   cv2.resize(whole.mueller[0, r, k], (32, 32), interpolation=cv2.INTER_AREA), 1e-5)
    host = SingleShot(model, "host")
    np.testing.assert_array_equal(host.live(f, 30.0, opts, max_display_px=96, geometry=axis).mueller,
                                  host.frame(f, 30.0, opts, geometry=axis).mueller)


@pytest.mark.parametrize("case", ["sphere", "ties", "small_object", "nan", "dark", "small_image"])
def test_the_object_mask_from_the_devices_order_statistics_equals_mask_from_s0(path, case):
    """The 1st/99th percentiles and the differences' median from ``TopK`` on the device, the
    threshold applied there; the host rule where it needs the whole image (a small image, a
    non-finite value, fewer than 1 % lit): the same mask and count in every case."""
    rng = np.random.default_rng(11)
    h, w = (40, 50) if case == "small_image" else (256, 300)
    v, u = np.mgrid[0:h, 0:w]
    radius = 4 if case == "small_object" else 0.4 * min(h, w)
    s0 = np.where((u - w / 2) ** 2 + (v - h / 2) ** 2 < radius ** 2, 1500.0, 40.0) + rng.normal(0, 3, (h, w))
    if case == "ties":
        s0 = np.round(s0 / 20) * 20
    if case == "dark":
        s0 = rng.normal(0, 3, (h, w))
    s0 = s0.astype(np.float32)
    if case == "nan":
        s0[5, 7] = np.nan
    mask, count = path._object_mask(path.upload("test_s0", s0), (h, w))
    got = (mask if isinstance(mask, np.ndarray) else mask.numpy()) > 0.5
    want = rt.mask_from_s0(s0)
    np.testing.assert_array_equal(got, want)
    assert count == int(want.sum())
    assert isinstance(mask, np.ndarray) == (case in ("small_object", "dark", "nan", "small_image"))  # on the host


def test_a_refused_pinned_buffer_uploads_from_pageable_memory_and_says_so_once(capsys):
    """The CUDA path's pinned upload where onnxruntime has no pinned allocator (this CPU build
    refuses the ``cuda_pinned`` device): the mosaic goes up as it is, one note, not asked again."""
    import onnxruntime as ort

    notes = []

    class Model(_CpuModel):
        def _note(self, line):
            notes.append(line)

    path = DevicePath(Model())
    raw = _raw((8, 10), 12)
    path.device, pinned_device = "cuda", True  # the pinned branch of a CUDA path
    try:
        ort.OrtValue.ortvalue_from_shape_and_type((1,), np.uint16, "cuda_pinned", 0)
    except Exception:
        pinned_device = False
    if pinned_device:
        pytest.skip("this onnxruntime has pinned memory: nothing refused")
    path.upload = lambda name, a: ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(a))  # host buffers here
    for _ in range(2):
        np.testing.assert_array_equal(path._upload_raw(raw).numpy(), raw)
    assert path._pinned is False and len(notes) == 1 and "pageable" in notes[0]


@needs_model
@pytest.mark.parametrize("resolution", ["superpixel", "full"])
def test_the_device_route_takes_a_roi_at_an_odd_offset_and_partial_cells(frames, resolution):
    """A 94x122 crop of the colour frame at ROI offset (3, 1): the layout's phase moves, the last
    partial cells are dropped (superpixel) or edge-repeated (the lift), 8-bit raw data."""
    import dataclasses

    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    f = frames["colour"][0]
    raw = (f.raw[1:95, 3:125] >> 4).astype(np.uint8)
    meta = dataclasses.replace(f.meta, offset_xy=(3, 1), bit_depth=8,
                               black_level_dn=float(f.meta.black_level_dn) / 16)
    crop = type(f)(raw, meta)
    model = SingleShotModel.load(device="cpu")
    opts = SingleShotOptions(resolution, sigma=False)
    a = SingleShot(model, "host").frame(crop, 45.0, opts)
    b = SingleShot(model, "device").frame(crop, 45.0, opts)
    np.testing.assert_array_equal(a.mask, b.mask)
    _close(b.mueller, a.mueller, ROUTE_RTOL)


@needs_model
def test_a_result_keeps_its_arrays_when_the_next_frame_runs_on_the_cpu_provider(frames):
    """On the CPU provider the persistent buffers are host memory, and ``OrtValue.numpy()`` is a
    view of them: the results copy what they return, so the next frame (another mosaic) leaves a
    result's Mueller image, planes and live grid as they were."""
    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app.single_shot import SingleShot
    from polrig.models.runtime import SingleShotModel

    f = frames["colour"][0]
    other = type(f)(np.ascontiguousarray(f.raw[::-1]), f.meta)  # the scene upside down
    opts = SingleShotOptions(sigma=False)
    route = SingleShot(SingleShotModel.load(device="cpu"), "device")
    first = route.frame(f, 30.0, opts)
    kept = {k: np.array(getattr(first, k)) for k in ("mueller", "stokes", "snr", "mask", "object")}
    live = route.live(f, 30.0, opts, max_display_px=48)
    grid = np.array(live.preview_grid)
    second = route.frame(other, 30.0, opts)
    route.live(other, 30.0, opts, max_display_px=48)
    assert not np.array_equal(second.mueller, kept["mueller"])  # the buffers did change
    for k, v in kept.items():
        np.testing.assert_array_equal(getattr(first, k), v)
    np.testing.assert_array_equal(live.preview_grid, grid)
