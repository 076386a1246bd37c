"""The one single-shot route (issue 30, :mod:`polrig.app.single_shot`): its options' rules in one
place (:class:`polrig.acquisition.plan.SingleShotOptions`), the model loaded once per capture or
window (the plan check and the processing share it), one result with the reference solve's
reason-bit mask, written by the one result writer for ``polrig infer`` and sessions alike."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from polrig.acquisition.plan import (
    CapturePlan,
    PlanError,
    SingleShotOptions,
    single_shot_options,
)

pytest.importorskip("onnxruntime")

REPO = pathlib.Path(__file__).resolve().parents[1]
HAS_WEIGHTS = (REPO / "models" / "weights" / "single_shot.onnx").is_file()
needs_model = pytest.mark.skipif(not HAS_WEIGHTS, reason="no single-shot model in models/weights")


# -- the options ---------------------------------------------------------------------------------
def test_the_options_default_demosaic_follows_the_resolution():
    assert SingleShotOptions().demosaic == "superpixel"
    full = SingleShotOptions("full")
    assert (full.demosaic, full.network_demosaic) == ("bilinear", "superpixel")
    assert SingleShotOptions("full", "newton").demosaic == "newton"
    assert SingleShotOptions("superpixel", "bilinear").network_demosaic == "bilinear"


@pytest.mark.parametrize("kwargs, field, text", [
    ({"resolution": "full", "demosaic": "superpixel"}, "resolution",
     "resolution full: takes its detail from a full-resolution demosaic (bilinear or newton), not superpixel"),
    ({"resolution": "half"}, "resolution", "resolution 'half': must be one of superpixel, full"),
    ({"demosaic": "nearest"}, "demosaic", "demosaic 'nearest': must be one of"),
    ({"network_binning": 4}, "network_binning", "network binning 4: must be one of 1, 2"),
    ({"resolution": "full", "sigma": True}, "sigma", "not at full resolution"),
    ({"network_binning": 2, "sigma": True}, "sigma", "not with network binning 2"),
    ({"resolution": "full", "network_binning": 2, "sigma": True}, "sigma",
     "not at full resolution or with network binning 2"),
])
def test_the_options_refuse_in_one_line_naming_the_field(kwargs, field, text):
    with pytest.raises(PlanError) as e:
        SingleShotOptions(**kwargs)
    assert e.value.field == field and text in str(e.value) and "\n" not in str(e.value)


def test_a_shared_superpixel_demosaic_stands_for_the_default_detail():
    """A plan's (or the live view's) demosaic is also the reference method's (the Stokes
    display's), superpixel by default: at full resolution it means the default detail."""
    o = SingleShotOptions.from_settings(demosaic="superpixel", resolution="full")
    assert o == SingleShotOptions("full", "bilinear")
    assert SingleShotOptions.from_settings(demosaic="newton", resolution="full").demosaic == "newton"
    assert single_shot_options("single-shot", "superpixel", "full", 1, False) == o
    assert single_shot_options("reference", "bilinear", "superpixel", 1, False) is None
    plan = CapturePlan((0.0,), mode="single-shot", resolution="full")  # accepted, as before
    assert plan.demosaic == "superpixel"


def test_sigma_is_computed_where_calibrated_unless_told():
    assert SingleShotOptions().with_sigma and not SingleShotOptions(sigma=False).with_sigma
    assert not SingleShotOptions("full").with_sigma and not SingleShotOptions(network_binning=2).with_sigma
    assert SingleShotOptions(sigma=True).sigma_calibrated
    assert SingleShotOptions("full", network_binning=2).uncalibrated_because() == [
        "at full resolution", "with network binning 2"]


@pytest.mark.parametrize("kwargs, field", [({"mirror_average": True}, "mirror_average"),
                                           ({"resolution": "full"}, "resolution"),
                                           ({"network_binning": 2}, "network_binning")])
def test_single_shot_settings_with_the_reference_method_are_refused(kwargs, field):
    args = {"demosaic": "superpixel", "resolution": "superpixel", "network_binning": 1,
            "mirror_average": False, **kwargs}
    with pytest.raises(PlanError) as e:
        single_shot_options("reference", **args)
    assert e.value.field == field
    with pytest.raises(PlanError) as e:
        CapturePlan((0.0,), **kwargs)
    assert e.value.field == field


# -- the model loads once ------------------------------------------------------------------------
@pytest.fixture
def counted_loads(monkeypatch):
    """Every :meth:`SingleShotModel.load` call, with a fresh set of open routes."""
    from polrig.app import single_shot
    from polrig.models.runtime import SingleShotModel

    monkeypatch.setattr(single_shot, "_OPEN", {})
    calls = []
    real = SingleShotModel.load.__func__

    def load(cls, *args, **kwargs):
        calls.append((args, kwargs))
        return real(cls, *args, **kwargs)

    monkeypatch.setattr(SingleShotModel, "load", classmethod(load))
    return calls


@needs_model
def test_a_capture_loads_the_model_once_for_its_plan_check_and_its_processing(tmp_path, counted_loads):
    from polrig.app import capture, processing
    from polrig.app.capture import CaptureRequest
    from polrig.app.rig import open_rig
    from polrig.app.single_shot import SingleShot

    prepared = capture.prepare_capture(CaptureRequest(out=tmp_path / "s", poses_deg=(0.0,), mode="single-shot",
                                                      device="cpu"))
    assert len(counted_loads) == 1  # the plan check opened it
    with open_rig(None, size=(64, 64), clock_speed=float("inf")) as rig:
        session = capture.open_session(prepared, rig, ["polrig", "capture"])
        try:
            proc = processing.make_processor(prepared.plan, prepared.calibration,
                                             processing.session_sensor_model(session), "cpu")
            assert capture.run_session(rig, session, processor=proc).status == "complete"
        finally:
            session.unlock()
    assert len(counted_loads) == 1  # ... and the processing used that one
    assert proc.single_shot is SingleShot.open("cpu")
    SingleShot.open("auto")  # another device: another session
    assert len(counted_loads) == 2


@needs_model
def test_the_gui_window_and_its_captures_share_one_model(counted_loads):
    from polrig.app import calibrations
    from polrig.gui.app import model_loader

    live = model_loader(device="cpu")()
    calibrations.check_plan(CapturePlan((0.0,), mode="single-shot"), calibrations.nominal_calibration(), "cpu")
    assert model_loader(device="cpu")() is live and len(counted_loads) == 1


def test_a_missing_installed_model_is_a_plan_error_and_a_given_folder_its_own(tmp_path, monkeypatch):
    from polrig.app import single_shot
    from polrig.app.single_shot import SingleShot
    from polrig.models import sizes

    monkeypatch.setattr(single_shot, "_OPEN", {})
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "small", tmp_path / "none")  # the installed (small) model
    with pytest.raises(PlanError, match="no single-shot model is installed") as e:
        SingleShot.open("cpu")
    assert e.value.field == "mode"
    with pytest.raises(FileNotFoundError, match="not found"):
        SingleShot.open("cpu", tmp_path / "elsewhere")
    assert single_shot._OPEN == {}  # nothing kept


# -- one result, one mask meaning, one writer ----------------------------------------------------
@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """A simulated 128x96 colour frame with a block of clipped pixels on the object."""
    from polrig.cli import main
    from polrig.formats.rawio import read_raw, write_raw

    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "128x96", "--states", "0", "--no-exr", "--out", str(out)]) == 0
    f = read_raw(next(out.glob("*_state00.png")))
    raw = f.raw.copy()
    raw[40:48, 56:72] = 2 ** f.meta.bit_depth - 1  # superpixel rows 10-11, columns 14-17
    path = out / "clipped.png"
    write_raw(path, type(f)(raw, f.meta))
    return path


@needs_model
def test_the_frame_route_marks_background_dark_and_clipped_object_pixels_saturated(frame):
    from polrig.app.single_shot import SingleShot
    from polrig.formats.rawio import read_raw
    from polrig.solve.reference import DARK, SATURATED

    f = read_raw(frame)
    route = SingleShot.open("cpu")
    r = route.frame(f, 0.0, SingleShotOptions(sigma=True))
    assert r.mueller.shape == (3, 3, 3, 24, 32) and r.mask.shape == (3, 24, 32) and r.mask.dtype == np.uint8
    assert np.all(r.mask[:, ~r.object] & DARK) and not np.any(r.mueller[..., ~r.object])
    block = np.zeros((24, 32), bool)
    block[10:12, 14:18] = True
    assert (block & r.object).any()
    np.testing.assert_array_equal((r.mask & SATURATED) > 0, np.broadcast_to(block & r.object, r.mask.shape))
    assert np.all(np.isinf(r.sigma[:, :, :, block & r.object]))
    assert np.all(np.isfinite(r.sigma[:, :, :, ~block]))
    assert r.stokes.shape == (3, 3, 24, 32) and r.snr.shape == (3, 24, 32)
    assert r.provider == route.provider and r.beyond_fraction is not None
    full = route.frame(f, 0.0, SingleShotOptions("full"))
    assert full.mueller.shape[-2:] == (96, 128) and full.mask.shape == (3, 96, 128)
    assert np.all(np.isnan(full.sigma)) and "network_demosaic" in full.header(("mueller", "sigma"))


@needs_model
def test_infer_writes_the_routes_result_with_the_session_mask_meaning(frame, tmp_path, capsys):
    """``polrig infer`` writes what the route computes (same Mueller and mask), through the one
    writer, with the planes and mask meaning of a session's single-shot result."""
    from polrig.app.calibrations import nominal_calibration, single_shot_geometry
    from polrig.app.rig import load_rig_config
    from polrig.app.single_shot import SingleShot
    from polrig.cli import main
    from polrig.formats.exr import read_mueller_exr
    from polrig.cli.commands._units import config_sensor_model
    from polrig.formats.rawio import read_raw

    out = tmp_path / "i.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--device", "cpu", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "clipped" in err and "'mask', bit 2: saturated" in err
    exr = read_mueller_exr(out)
    config = load_rig_config(None)  # infer's geometry and noise model without --config
    r = SingleShot.open("cpu").frame(read_raw(frame), 0.0, SingleShotOptions(sigma=False),
                                     sensor=config_sensor_model(config),
                                     geometry=single_shot_geometry(nominal_calibration(), config))
    np.testing.assert_array_equal(exr.mueller, r.mueller)
    assert sorted(k for k in exr.extra) == ["mask.B", "mask.G", "mask.R"]
    for k, c in enumerate("RGB"):
        np.testing.assert_array_equal(exr.extra[f"mask.{c}"], r.mask[k])
    md = exr.metadata
    assert md["planes"] == {"mask": "reason bits, 0 = valid"}
    assert md["mask_bits"] == {"1": "dark", "2": "saturated", "4": "ill_conditioned", "8": "nonfinite"}
    assert md["execution_provider"] == r.provider and md["resolution"] == "superpixel"
