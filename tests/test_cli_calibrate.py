"""``polrig calibrate --out`` is checked before any calibration runs: on hardware a late
failure to write the set loses minutes of work (it used to fail with Errno 17/30 after the
whole procedure)."""

from __future__ import annotations

import os
import time

import pytest

from polrig.cli import main


def _calibrate(out, capsys):
    t0 = time.monotonic()
    rc = main(["calibrate", "intrinsics", "--size", "64x48", "--out", str(out)])
    out_text, err = capsys.readouterr()
    return rc, out_text, err, time.monotonic() - t0


def test_an_existing_file_is_refused_at_once(tmp_path, capsys):
    f = tmp_path / "text.png"
    f.write_text("not a folder")
    rc, out, err, dt = _calibrate(f, capsys)
    assert rc == 2 and out == "" and dt < 5
    assert err == (f"polrig: error: --out {f} exists and is not a folder; give a folder for "
                   f"the calibration set\n")
    rc, _, err, _ = _calibrate(f / "sub", capsys)
    assert rc == 2 and f"{f} is not a folder" in err
    assert f.read_text() == "not a folder"


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into read-only-mode folders")
def test_a_read_only_folder_is_refused_at_once(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        rc, out, err, _ = _calibrate(ro / "cal", capsys)
        assert rc == 2 and out == "" and f"folder {ro} is not writable" in err
        rc, out, err, _ = _calibrate(ro, capsys)
        assert rc == 2 and f"--out folder {ro} is not writable" in err
    finally:
        ro.chmod(0o755)


def test_check_out_folder_on_a_read_only_filesystem(tmp_path, monkeypatch):
    """The same check goes through ``os.access``, which reports a read-only filesystem to
    root too; denied here by hand, since a test cannot mount one."""
    from polrig.commands.calibrate import check_out_folder
    from polrig.errors import ConfigError

    check_out_folder(tmp_path / "a" / "b")  # creatable: no error, and nothing created
    assert list(tmp_path.iterdir()) == []
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: os.fspath(p) != os.fspath(tmp_path)
                        and real(p, mode))
    with pytest.raises(ConfigError, match=f"folder {tmp_path} is not writable"):
        check_out_folder(tmp_path / "a" / "b")
