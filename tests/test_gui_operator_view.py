"""What the operator sees (issue 21): the Viewer honours a file's masks and says why a pixel is
masked, the Mueller grid's tiles are labelled, background below the signal threshold is black,
a paused live view says so, the light reads on/off and fixture positions read as words."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

from polrig.app import preview  # noqa: E402
from polrig.cli import main  # noqa: E402
from polrig.gui import pipeline  # noqa: E402
from polrig.gui.qtimage import from_qimage  # noqa: E402

pytestmark = pytest.mark.gui


def _stokes_exr_with_a_saturated_sky(tmp_path):
    """``polrig stokes`` of a 12-bit frame whose top rows are clipped (a saturated sky) and
    whose right half is background noise."""
    from polrig.formats.rawio import write_raw
    from polrig.sensor.frame import Frame, FrameMeta
    from polrig.sensor.noise import SensorModel

    model = SensorModel(black_level_dn=64.0)
    mean = np.full((32, 64), 1500.0)
    mean[:, 32:] = 0.0
    raw = model.sample_raw(mean * model.gain_e_per_dn, np.random.default_rng(2), 1000.0)
    raw[:8] = 4095
    meta = FrameMeta(frame_id=1, timestamp_s=0.0, exposure_us=1000.0, gain_db=0.0,
                     pixel_format="Mono12", layout="imx250mzr", bit_depth=12,
                     black_level_dn=64.0)
    write_raw(tmp_path / "f.png", Frame(raw, meta))
    out = tmp_path / "s.exr"
    assert main(["stokes", str(tmp_path / "f.png"), "--demosaic", "superpixel",
                 "--out", str(out)]) == 0
    return out


def test_viewer_honours_the_valid_plane_and_says_why(qtbot, viewer_panel, tmp_path):
    """A Stokes EXR's ``valid`` plane used to be ignored: the saturated sky read as a valid
    Stokes vector, unflagged. Now the readout says "MASKED: saturated" (or dark, with the SNR)
    and the DoLP display is black there."""
    from test_gui import open_and_wait

    exr = _stokes_exr_with_a_saturated_sky(tmp_path)
    v = viewer_panel(show=False)
    assert open_and_wait(qtbot, v, exr)
    v.display.setCurrentIndex(v.display.findData("dolp"))
    v._hovered(2, 1)  # the sky (output rows 0..3)
    assert "MASKED: saturated" in v.readout.text()
    v._hovered(2, 10)  # the lit object
    assert "MASKED" not in v.readout.text()
    v._hovered(25, 10)  # background noise
    assert "MASKED: dark (SNR" in v.readout.text()
    rgb = from_qimage(v.view.image())
    assert (rgb[:4] == pipeline.SATURATION_RGB).all()  # the sky: the saturation overlay
    assert (rgb[8:, 20:] == 0).all()  # background noise: masked (black)
    v.min_snr.setValue(0.0)  # threshold off: background noise shows again (but the sky not)
    rgb = from_qimage(v.view.image())
    assert rgb[8:, 20:].max() > 0 and (rgb[:4] == pipeline.SATURATION_RGB).all()


def test_viewer_masks_a_single_shot_exrs_background_and_labels_the_tiles(qtbot, viewer_panel, tmp_path):

    m = np.zeros((1, 3, 3, 40, 40), np.float32)
    m[:, 0, 0] = 100.0
    m[:, 1, 1] = 80.0
    planes = {"mask": np.zeros((40, 40), np.float32)}
    planes["mask"][:, :20] = 1.0
    data = pipeline.PolarizationData.from_mueller(m, "x", planes)
    v = viewer_panel(show=False)
    v.set_data(data)
    rgb = from_qimage(v.view.image())
    b, h = pipeline.GRID_BORDER_PX, 40
    tile11 = rgb[b + h + b: b + 2 * h + b, b + h + b: b + 2 * h + b]
    assert (tile11[20:, 25:] == 0).all() and tile11[30:, 5:15].max() > 0  # background black
    plain = preview.mueller_grid(m, border_px=b, labels=False, valid=pipeline.shown(data))
    assert (rgb[:h, :plain.shape[1]] != plain[:h]).any()  # "m00" etc. written on the tiles
    x, y = b + h + b + 30, b + h + b + 20  # tile m11, background pixel (u=30, v=20)
    v._hovered(x, y)
    assert "MASKED: background" in v.readout.text()


def test_a_paused_live_view_says_so(qtbot, tmp_path):
    from test_gui import close_window, make_window, wait_frames

    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        wait_frames(qtbot, w, 3)
        w.live.pause_for("capture", True)
        assert w.live.view.banner.startswith("LIVE VIEW PAUSED")
        assert "paused" in w.fps_label.text() and "fps" not in w.fps_label.text()
        qtbot.wait(300)
        assert "fps" not in w.fps_label.text()  # no frame after the pause brings a stale rate
        w.live.pause_for("capture", False)
        assert w.live.view.banner == ""
        wait_frames(qtbot, w, 2)
        assert "fps" in w.fps_label.text()
    finally:
        close_window(qtbot, w)


def test_light_and_fixture_positions_read_as_words():
    from polrig.calibration.procedures import fixture_words
    from polrig.gui.devices import light_words

    assert light_words({"open": True, "on": True, "level": 0.5}) == "on, level 0.500"
    assert light_words({"open": True, "on": False, "level": 0.0}) == "off, level 0.000"
    assert fixture_words({"distance_m": 0.3, "tilt_deg": 10.0}) == "distance 0.3 m, tilt 10 deg"


def test_calibration_step_list_is_not_clipped(qtbot):
    from polrig.app.rig import build_rig, load_rig_config
    from polrig.gui.calibration_panel import CalibrationPanel
    from polrig.gui.rigaccess import RigLocks

    rig = build_rig(load_rig_config(None), {"size": "32x32"})
    p = CalibrationPanel(rig, RigLocks())
    qtbot.addWidget(p)
    p.resize(900, 500)
    p.show()
    lst = p.steps
    rows = sum(lst.sizeHintForRow(i) for i in range(lst.count()))
    assert lst.height() >= rows


def test_ldd_output_parsing():
    from polrig.gui.app import ldd_missing

    text = ("\tlibQt6XcbQpa.so.6 => /x/libQt6XcbQpa.so.6 (0x1)\n"
            "\tlibxcb-icccm.so.4 => not found\n\tlinux-vdso.so.1 (0x7)\n"
            "\tlibxcb-keysyms.so.1 => not found\n\tlibxcb-icccm.so.4 => not found\n")
    assert ldd_missing(text) == ["libxcb-icccm.so.4", "libxcb-keysyms.so.1"]


def test_missing_qt_system_libraries_are_named_with_their_packages(tmp_path):
    """``polrig gui`` on a system without the xcb plugin's libraries used to abort (exit 134)
    with Qt's hint; now it exits 1 naming the libraries and the apt-get line. Runs where this
    machine lacks one of them (the check is what the command does, not a stand-in)."""
    import os
    import subprocess
    import sys

    from polrig.gui.app import missing_xcb_libraries

    missing = missing_xcb_libraries()
    if not missing:
        pytest.skip("every library of the Qt xcb plugin is installed here")
    env = {k: v for k, v in os.environ.items() if k not in ("QT_QPA_PLATFORM", "WAYLAND_DISPLAY")}
    env["DISPLAY"] = ":99"
    res = subprocess.run([sys.executable, "-m", "polrig", "gui", "--settings",
                          str(tmp_path / "g.ini")], capture_output=True, text=True, env=env,
                         timeout=120)
    assert res.returncode == 1, res.stderr
    assert res.stderr.startswith("polrig: error: Qt's X11 (xcb) platform plugin cannot load: ")
    assert "sudo apt-get install " in res.stderr and missing[0] in res.stderr


def test_a_refused_capture_start_shows_no_frame_count(qtbot, tmp_path):
    """A start refused by the form (a state that is no angle) leaves the bar saying "not
    started", not Qt's default "0 / 100 frames" (issue 21 item 10)."""
    from test_gui import close_window, make_window

    w = make_window(qtbot, tmp_path / "gui.ini")
    try:
        cp = w.capture
        assert "100" not in cp.progress.text()
        cp.out.setText(str(tmp_path / "s"))
        cp.states.setText("0,45,ninety")
        cp.start()
        assert not cp.is_running and cp.last_status == "failed"
        assert cp.progress.text() == "not started" and "100" not in cp.progress.text()
        assert not (tmp_path / "s").exists()
    finally:
        close_window(qtbot, w)
