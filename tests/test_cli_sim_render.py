"""``polrig sim render``: options checked before the output folder is created, and no
earlier render is ever replaced without ``--overwrite`` (adding a pose to a render of the
same rig stays possible, ``docs/sim.md``)."""

from __future__ import annotations

import json

import pytest

from polrig.cli import main

RENDER = ["sim", "render", "--size", "32x32", "--states", "0", "--no-exr"]


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("args", [["--size", "abc"], ["--size", "63x48"], ["--pose", "nan"],
                                  ["--exposure-us", "-1"], ["--states", "0,nan"],
                                  ["--exposure-us", "5"], ["--exposure-us", "2e7"]])  # outside the camera's range
def test_bad_options_leave_no_folder(tmp_path, capsys, args):
    out = tmp_path / "render"
    try:
        rc = main(["sim", "render", *args, "--out", str(out)])
    except SystemExit as exc:  # argparse: usage error
        rc = exc.code
    assert rc == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].count("error:") == 1
    assert not out.exists()


def test_a_render_is_never_replaced_without_overwrite(tmp_path, capsys):
    out = tmp_path / "render"
    assert main(RENDER + ["--out", str(out)]) == 0
    first = _snapshot(out)
    capsys.readouterr()
    assert main(RENDER + ["--out", str(out)]) == 2  # the same pose again
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pose0000p00_state00.png" in err and "--overwrite" in err
    assert main(RENDER + ["--seed", "5", "--pose", "90", "--out", str(out)]) == 2  # another rig
    assert "another simulated rig" in capsys.readouterr().err
    assert _snapshot(out) == first
    # another pose of the same rig is added (truth.json lists both)
    assert main(RENDER + ["--pose", "90", "--out", str(out)]) == 0
    index = json.loads((out / "truth.json").read_text())
    assert [c["name"] for c in index["captures"]] == ["pose0000p00", "pose0090p00"]
    assert (out / "pose0000p00_state00.png").read_bytes() == first["pose0000p00_state00.png"]
    assert main(RENDER + ["--seed", "5", "--overwrite", "--out", str(out)]) == 0


def test_other_folders_and_files_are_refused(tmp_path, capsys):
    other = tmp_path / "notes"
    other.mkdir()
    (other / "todo.txt").write_text("keep me")
    assert main(RENDER + ["--out", str(other)]) == 2
    assert "not empty and not a 'polrig sim render' folder" in capsys.readouterr().err
    assert [p.name for p in other.iterdir()] == ["todo.txt"]
    (tmp_path / "file").write_text("x")
    assert main(RENDER + ["--out", str(tmp_path / "file")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(RENDER + ["--out", str(empty)]) == 0


def test_the_longest_exposure_the_camera_takes_is_rendered(tmp_path, capsys):
    """Every grab waits its exposure and readout and a margin (``grab_timeout_s``): the camera's
    longest exposure, 10 s, does not time out as a fixed 10 s wait did."""
    out = tmp_path / "long"
    assert main([*RENDER, "--exposure-us", "1e7", "--out", str(out)]) == 0, capsys.readouterr().err
    assert (out / "pose0000p00_state00.png").is_file()
