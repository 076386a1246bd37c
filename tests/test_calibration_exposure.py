"""The procedures' exposure search (:func:`polrig.calibration.procedures.auto_expose`) with the light
off or far too dim: it stops at the longest exposure a grab can wait for and says the scene is
too dark (it used to search up to 10 s, where the camera's grab timed out)."""

from __future__ import annotations

import pytest

from polrig.app.rig import open_rig
from polrig.calibration import procedures
from polrig.calibration.errors import SceneTooDark
from polrig.cli import main


def _sim(light: float):
    return open_rig(None, size="64x48", clock_speed=float("inf"),
                    hidden={"light_intensity_rgb": [light] * 3})


def test_auto_expose_with_the_light_off_is_scene_too_dark():
    with _sim(0.0) as rig:
        with pytest.raises(SceneTooDark, match=r"^scene too dark at the longest usable exposure "
                                               r"5e\+06 us \(the 99.5th percentile reaches "
                                               r"[0-9.]+ % of full scale, 60 % wanted\); is the "
                                               r"light on\?$"):
            procedures.auto_expose(rig.camera)
        assert rig.camera.exposure_us <= procedures.MAX_EXPOSURE_US


def test_auto_expose_in_normal_light_is_unchanged():
    with _sim(1.0) as rig:
        e = procedures.auto_expose(rig.camera, percentile=99.0, target=0.7)
        assert 10 < e < procedures.MAX_EXPOSURE_US


def test_calibrate_with_the_light_off_fails_with_one_clear_line(tmp_path, capsys):
    """A failure while running (exit 1), not a grab timeout; nothing is saved."""
    cfg = tmp_path / "off.toml"
    cfg.write_text('[sim]\nsize = "64x48"\nclock_speed = inf\n'
                   '[sim.hidden]\nlight_intensity_rgb = [0.0, 0.0, 0.0]\n')
    rc = main(["calibrate", "all", "--config", str(cfg), "--out", str(tmp_path / "k")])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1, err
    assert err.startswith("polrig: error: ") and "no frame within" not in err
    assert "scene too dark at the longest usable exposure 5e+06 us (" in err
    assert "is the light on?" in err
    assert not (tmp_path / "k" / "calibration.json").exists()
