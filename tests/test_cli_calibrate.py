"""``polrig calibrate --out`` is checked before any calibration runs: on hardware a late
failure to write the set loses minutes of work (it used to fail with Errno 17/30 after the
whole procedure).

"Before any calibration runs" is checked on what happened, not on the clock (a whole
intrinsics or light step at 64x48 takes under 5 s, the bound these tests had): the
intrinsics procedure logs each board it mounts on stdout as it goes, so an empty stdout shows
none was mounted; elsewhere the rigs the real open_rig returns are recorded, and a simulated
rig's clock shows whether anything was exposed or moved (a light step advances it by minutes).
"""

from __future__ import annotations

import os

import pytest
from _calibration_sets import set_calibrated_on

from polrig.cli import main


def _record_rigs(monkeypatch) -> list:
    """The rigs polrig.app.rig.open_rig (the real one) opens from now on."""
    import polrig.app.rig

    rigs: list = []
    real = polrig.app.rig.open_rig

    def recorded(*args, **kwargs):
        rigs.append(real(*args, **kwargs))
        return rigs[-1]
    monkeypatch.setattr(polrig.app.rig, "open_rig", recorded)
    return rigs


def _calibrate(out, capsys):
    rc = main(["calibrate", "intrinsics", "--size", "64x48", "--out", str(out)])
    out_text, err = capsys.readouterr()
    return rc, out_text, err


def test_an_existing_file_is_refused_at_once(tmp_path, capsys):
    f = tmp_path / "text.png"
    f.write_text("not a folder")
    rc, out, err = _calibrate(f, capsys)
    assert rc == 2 and out == ""  # no board mounted: refused before the procedure
    assert err == (f"polrig: error: --out {f} exists and is not a folder; give a folder for "
                   f"the calibration set\n")
    rc, _, err = _calibrate(f / "sub", capsys)
    assert rc == 2 and f"{f} is not a folder" in err
    assert f.read_text() == "not a folder"


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only-mode folders")
def test_a_read_only_folder_is_refused_at_once(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        rc, out, err = _calibrate(ro / "cal", capsys)
        assert rc == 2 and out == "" and f"folder {ro} is not writable" in err
        rc, out, err = _calibrate(ro, capsys)
        assert rc == 2 and f"--out folder {ro} is not writable" in err
    finally:
        ro.chmod(0o755)


def test_check_out_folder_on_a_read_only_filesystem(tmp_path, monkeypatch):
    """The same check goes through ``os.access``, which reports a read-only filesystem to
    root too; denied here by hand, since a test cannot mount one."""
    from polrig.cli.commands.calibrate import check_out_folder
    from polrig.errors import ConfigError

    check_out_folder(tmp_path / "a" / "b")  # creatable: no error, and nothing created
    assert list(tmp_path.iterdir()) == []
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: os.fspath(p) != os.fspath(tmp_path)
                        and real(p, mode))
    with pytest.raises(ConfigError, match=f"folder {tmp_path} is not writable"):
        check_out_folder(tmp_path / "a" / "b")


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("extra", [["--size", "64x48"], ["--seed", "5"],
                                   ["--size", "64x48", "--seed", "5"]])
def test_sim_options_with_a_config_are_refused(tmp_path, capsys, extra):
    """--size/--seed pick the simulated rig used without --config; with --config they used
    to be ignored silently."""
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[sim]\nsize = "64x48"\nclock_speed = inf\n')
    rc = main(["calibrate", "intrinsics", "--config", str(cfg), "--out", str(tmp_path / "c")]
              + extra)
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and err.count("\n") == 1
    assert "only pick the simulated rig used without --config" in err and "[sim] table" in err
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("size, layout, legacy, why", [
    ((320, 240), "imx250myr", False, "(a different sensor size)"),
    ((320, 240), "imx250myr", True, "(a different sensor size)"),
    ((64, 48), "imx250mzr", False, "(layout imx250mzr is not imx250myr)"),
    ((64, 48), "imx250mzr", True, "(layout imx250mzr is not imx250myr)"),
])
def test_a_step_refuses_a_set_of_another_camera_before_acquiring(tmp_path, capsys,
                                                                 monkeypatch, size, layout,
                                                                 legacy, why):
    """``calibrate light --size 64x48`` on a set calibrated at 320x240 used the 320x240
    intrinsics, printed a wrong light position and crashed (on hardware: saved it)."""
    out = tmp_path / "cal"
    before = set_calibrated_on(out, size, layout, legacy=legacy)
    rigs = _record_rigs(monkeypatch)
    rc = main(["calibrate", "light", "--size", "64x48", "--out", str(out)])
    stdout, err = capsys.readouterr()
    assert rc == 2 and stdout == "" and err.count("\n") == 1, err
    assert [r.camera.world.clock.now() for r in rigs] == [0.0]  # nothing exposed or moved
    w, h = size
    assert err.startswith(f"polrig: error: calibration set {out} was calibrated on sensor "
                          f"{w}x{h} {layout}, calibrated readout {w}x{h} at (0, 0); this camera: "
                          f"sensor 64x48 imx250myr, readout 64x48 at (0, 0) {why}")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_an_unknown_target_metal_is_refused_at_once(tmp_path, capsys, monkeypatch):
    """``--mirror-metal`` / ``--sphere-metal`` name a tabulated metal (or ``ideal``); a typo
    is refused in one line before the rig opens, and nothing is written."""
    rigs_opened = _record_rigs(monkeypatch)
    for flag in ("--mirror-metal", "--sphere-metal"):
        rc = main(["calibrate", "dofp", flag, "tin", "--size", "64x48",
                   "--out", str(tmp_path / "cal")])
        out, err = capsys.readouterr()
        assert rc == 2 and out == ""
        assert err == (f"polrig: error: {flag}: unknown mirror metal 'tin'; known: gold, silver, "
                       f"copper, aluminium, chrome, ideal\n")
        assert not (tmp_path / "cal").exists()
    assert rigs_opened == []


def test_a_board_the_images_do_not_show_is_a_failure_while_running(tmp_path, capsys):
    """At 64x48 the board's corners are too small to detect: the images cannot give a result,
    which is a failure while running (exit 1, as a scene too dark is), not a bad argument."""
    rc, out, err = _calibrate(tmp_path / "c", capsys)
    assert rc == 1 and err.count("\n") == 1, err
    assert "needs at least 3 board views" in err and "nothing was saved" in err
