"""A calibration set is applied only to frames of the camera it was calibrated on.

``capture``, ``reconstruct`` and ``infer`` refuse a set of another sensor size or layout, or
one that does not cover the frames' readout, up front (exit 2, one line naming the set and
both geometries; no session, no revision, nothing moved). A readout (ROI) inside the
calibrated area is accepted: the analyzer model is cropped to it and the intrinsics carried
by its offset. (They used to crop a 320x240 analyzer to a 128x128 sensor, apply a colour set
to a mono sensor, or find a too small set only after acquiring.)
"""

from __future__ import annotations

import contextlib
import json
import pathlib

import numpy as np
import pytest
from _calibration_sets import set_calibrated_on

from polrig.app import processing
from polrig.app.session import Session
from polrig.cli import main
from polrig.sensor.analyzer import AnalyzerModel


def rig_toml(path: pathlib.Path, size: str = "64x48", sensor: str = "imx250myr") -> pathlib.Path:
    path.write_text(f'[sim]\nsize = "{size}"\nsensor = "{sensor}"\nclock_speed = inf\n'
                    f'scene = "box"\n')
    return path


def _capture(tmp_path, cfg, cal, *extra) -> list[str]:
    return ["capture", "--poses", "0", "--config", str(cfg), "--calibration", str(cal),
            "--out", str(tmp_path / "s"), "--no-progress", *extra]


@pytest.mark.parametrize("set_size, set_layout, legacy, camera_size, camera_layout, why", [
    ((96, 72), "imx250myr", False, "64x48", "imx250myr", "a different sensor size"),
    ((96, 72), "imx250myr", True, "64x48", "imx250myr", "a different sensor size"),
    ((64, 48), "imx250myr", False, "64x48", "imx250mzr", "layout imx250myr is not imx250mzr"),
    ((64, 48), "imx250myr", True, "64x48", "imx250mzr", "layout imx250myr is not imx250mzr"),
    ((32, 24), "imx250myr", False, "64x48", "imx250myr", "a different sensor size"),
])
def test_capture_refuses_a_set_of_another_camera_before_anything(
        tmp_path, capsys, set_size, set_layout, legacy, camera_size, camera_layout, why):
    cal = tmp_path / "cal"
    set_calibrated_on(cal, set_size, set_layout, legacy=legacy)
    cfg = rig_toml(tmp_path / "rig.toml", camera_size, camera_layout)
    rc = main(_capture(tmp_path, cfg, cal))
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    w, h = set_size
    cw, ch = camera_size.split("x")
    assert err == (f"polrig: error: --calibration {cal}: calibrated on sensor {w}x{h} "
                   f"{set_layout}, calibrated area {w}x{h} at (0, 0); this camera: sensor "
                   f"{cw}x{ch} {camera_layout}, readout {cw}x{ch} at (0, 0) ({why}); use a set "
                   f"calibrated on this camera ('polrig calibrate all --out DIR' on it)\n")
    assert not (tmp_path / "s").exists()  # no session, nothing acquired


def test_single_shot_capture_refuses_it_too(tmp_path, capsys):
    """Single-shot capture used to record the 320x240 set's intrinsics for a 128x128 sensor."""
    pytest.importorskip("onnxruntime")
    cal = tmp_path / "cal"
    set_calibrated_on(cal, (96, 72))
    rc = main(_capture(tmp_path, rig_toml(tmp_path / "rig.toml"), cal, "--mode", "single-shot"))
    err = capsys.readouterr().err
    assert rc == 2 and "a different sensor size" in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()


def test_the_same_camera_is_accepted(tmp_path, capsys):
    cal = tmp_path / "cal"
    set_calibrated_on(cal, (64, 48))
    assert main(_capture(tmp_path, rig_toml(tmp_path / "rig.toml"), cal)) == 0
    s = Session.open(tmp_path / "s")
    assert s.manifest["calibration_id"] == json.loads((cal / "calibration.json").read_text())["id"]


def _request(tmp_path, cal):
    """The request ``polrig capture --poses 0 --calibration CAL --out S`` makes."""
    from polrig.cli import build_parser
    from polrig.cli.commands.capture import build_request

    # the command's own parser: every option the command reads has its default
    ns = build_parser().parse_args(["capture", "--out", str(tmp_path / "s"), "--poses", "0",
                                    "--calibration", str(cal)])
    return build_request(ns)


def _rig_with_roi(config: pathlib.Path, roi: tuple[int, int, int, int]):
    """A rig source for :func:`polrig.app.capture.run_capture`: the rig of ``config`` with its
    camera's readout set to ``roi`` (width, height, x, y)."""
    from polrig.app.rig import open_rig

    @contextlib.contextmanager
    def source():
        with open_rig(config) as rig:
            rig.camera.set_roi(*roi)
            yield rig

    return source


def test_a_readout_inside_the_calibrated_area_is_accepted_and_cropped(tmp_path):
    """A set calibrated on the whole 64x48 sensor serves a 32x24 ROI at (8, 4): the session
    is captured and processed with the analyzer model cropped to the ROI."""
    from polrig.app import capture

    cal = tmp_path / "cal"
    rng = np.random.default_rng(2)
    ideal = AnalyzerModel.ideal("imx250myr", (48, 64))
    analyzer = AnalyzerModel("imx250myr", rng.normal(1, 0.01, (48, 64)), ideal.angle_deg,
                             ideal.diattenuation, ideal.offset_dn)
    set_calibrated_on(cal, (64, 48), analyzer=analyzer)
    result = capture.run_capture(_request(tmp_path, cal), command_line=["polrig", "capture"],
                                 rig=_rig_with_roi(rig_toml(tmp_path / "rig.toml"), (32, 24, 8, 4)))
    assert result.status == "complete"
    session = Session.open(tmp_path / "s")
    cf = processing.load_capture_frames(session, 0)
    assert cf.first.raw.shape == (24, 32) and tuple(cf.first.meta.offset_xy) == (8, 4)
    # the calibrated analyzer cropped to the ROI: the same solve as with the crop given
    calibration = processing.load_calibration(cal)
    crop = processing.Calibration(calibration.id, calibration.incident_stokes_fn,
                                  analyzer.crop(8, 4, 32, 24))
    model = processing.session_sensor_model(session)
    got = processing.process_reference(cf, calibration, model, "superpixel")[0]
    want = processing.process_reference(cf, crop, model, "superpixel")[0]
    np.testing.assert_array_equal(got.mueller, want.mueller)


def test_a_set_calibrated_on_a_roi_serves_only_readouts_inside_it(tmp_path, capsys):
    """A set calibrated on the 32x24 readout at (16, 8) of a 64x48 sensor: its intrinsics
    are carried to full-sensor pixels, a readout inside it is accepted (analyzer cropped at
    the offset relative to the calibrated area), one reaching outside is refused."""
    from polrig.app import capture
    from polrig.app.rig import open_rig
    from polrig.errors import ConfigError

    cal = tmp_path / "cal"
    rng = np.random.default_rng(3)
    ideal = AnalyzerModel.ideal("imx250myr", (24, 32))
    analyzer = AnalyzerModel("imx250myr", rng.normal(1, 0.01, (24, 32)), ideal.angle_deg,
                             ideal.diattenuation, ideal.offset_dn)
    set_calibrated_on(cal, (64, 48), readout=(32, 24, 16, 8), analyzer=analyzer)
    cal_obj = processing.load_calibration(cal)
    assert cal_obj.intrinsics == (600.0, 600.0, 16.0 + 16, 12.0 + 8)  # full-sensor pixels
    assert cal_obj.area_offset == (16, 8)
    config = rig_toml(tmp_path / "rig.toml")
    with open_rig(config) as rig:
        rig.camera.set_roi(16, 8, 24, 12)  # inside the calibrated area
        processing.check_calibration_fits_rig(cal_obj, rig)
    # the sensor's corner, outside it: refused before the session exists
    with pytest.raises(ConfigError, match=r"readout 32x24 at \(0, 0\) \(the readout is not "
                                          r"inside the calibrated area\)"):
        capture.run_capture(_request(tmp_path, cal), command_line=["polrig", "capture"],
                            rig=_rig_with_roi(config, (32, 24, 0, 0)))
    assert not (tmp_path / "s").exists()
    # the analyzer of a readout at (24, 12) is the calibrated one at (8, 4)
    from polrig.sensor.frame import Frame, FrameMeta

    meta = FrameMeta(0, 0.0, 1000.0, 0.0, "BayerRG16", "imx250myr", 16, offset_xy=(24, 12))
    frames = [[[Frame(np.full((8, 16), 2000 + 100 * i, np.uint16), meta)]] for i in range(4)]
    cf = processing.CaptureFrames([0.0, 45.0, 90.0, 135.0], [1000.0], frames, [[]])
    crop = processing.Calibration(cal_obj.id, cal_obj.incident_stokes_fn, analyzer.crop(8, 4, 16, 8))
    model = processing.SensorModel()
    got = processing.process_reference(cf, cal_obj, model, "superpixel")[0]
    want = processing.process_reference(cf, crop, model, "superpixel")[0]
    np.testing.assert_array_equal(got.mueller, want.mueller)


# ------------------------------------------------------------------------------ reconstruct
def test_reconstruct_refuses_a_set_too_small_before_any_revision(tmp_path, capsys):
    """It used to record a failed revision rev1 and exit 1."""
    cfg = rig_toml(tmp_path / "rig.toml")
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(tmp_path / "s"),
                 "--no-progress"]) == 0
    manifest = (tmp_path / "s" / "session.json").read_bytes()
    set_calibrated_on(tmp_path / "small", (32, 24))
    set_calibrated_on(tmp_path / "mono", (64, 48), "imx250mzr", legacy=True)
    capsys.readouterr()
    for cal, why in (("small", "a different sensor size"),
                     ("mono", "layout imx250mzr is not imx250myr")):
        rc = main(["reconstruct", str(tmp_path / "s"), "--calibration", str(tmp_path / cal),
                   "--no-progress"])
        out, err = capsys.readouterr()
        assert rc == 2 and err.count("\n") == 1, err
        assert err.startswith(f"polrig: error: --calibration {tmp_path / cal}: calibrated on ")
        assert f"the camera of session {tmp_path / 's'}: sensor 64x48 imx250myr, readout 64x48 " \
               f"at (0, 0) ({why})" in err
        assert (tmp_path / "s" / "session.json").read_bytes() == manifest  # no revision
    set_calibrated_on(tmp_path / "good", (64, 48))
    assert main(["reconstruct", str(tmp_path / "s"), "--calibration", str(tmp_path / "good"),
                 "--no-progress"]) == 0
    assert Session.open(tmp_path / "s").manifest["revisions"][0]["name"] == "rev1"
