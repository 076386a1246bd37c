"""Calibration set files that are damaged, tampered with or badly shaped are refused by
``calibration.load`` with one line naming the file (exit 2 through the CLI); saving replaces a
set without ever leaving a mixed one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _calibration_sets import small_set

from polrig.calibration import calset
from polrig.calibration.calset import CalibrationSet
from polrig.cli import main
from polrig.errors import FormatError


def _one_line_naming(exc_info, path) -> str:
    text = str(exc_info.value)
    assert "\n" not in text and str(path) in text, text
    return text


# ------------------------------------------------------------------------------ id
@pytest.mark.parametrize("how", ["deleted", "empty", "blank", "number"])
def test_a_set_without_its_id_is_refused(tmp_path, how):
    """Deleting or blanking the id used to turn tamper detection off: an edited generator
    offset (30 deg) was applied silently."""
    small_set().save(tmp_path)
    p = tmp_path / "calibration.json"
    doc = json.loads(p.read_text())
    doc["generator"]["zero_offset_deg"] = 30.0
    if how == "deleted":
        del doc["id"]
    else:
        doc["id"] = {"empty": "", "blank": "  ", "number": 5}[how]
    p.write_text(json.dumps(doc))
    with pytest.raises(FormatError) as ei:
        calset.load(tmp_path)
    assert "has no id" in _one_line_naming(ei, p)


def test_the_cli_refuses_a_set_without_id_before_anything_runs(tmp_path, capsys):
    small_set().save(tmp_path / "cal")
    p = tmp_path / "cal" / "calibration.json"
    doc = json.loads(p.read_text())
    doc.pop("id")
    p.write_text(json.dumps(doc))
    rc = main(["capture", "--poses", "0", "--calibration", str(tmp_path / "cal"),
               "--out", str(tmp_path / "s"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and str(p) in err and "no id" in err
    assert not (tmp_path / "s").exists()


# ------------------------------------------------------------------------------ damaged files
@pytest.mark.parametrize("name", ["analyzer.npz", "dofp_maps.npz"])
def test_a_truncated_npz_is_one_line_naming_it(tmp_path, name):
    small_set().save(tmp_path)
    f = tmp_path / name
    f.write_bytes(f.read_bytes()[:100])
    with pytest.raises(FormatError) as ei:  # a zipfile.BadZipFile traceback before
        calset.load(tmp_path)
    _one_line_naming(ei, f)


def test_a_listed_npz_that_is_missing_is_named(tmp_path):
    small_set().save(tmp_path)
    (tmp_path / "analyzer.npz").unlink()
    with pytest.raises(FormatError, match="analyzer.npz: missing") as ei:
        calset.load(tmp_path)
    _one_line_naming(ei, tmp_path / "analyzer.npz")


@pytest.mark.parametrize("version, needle", [
    ("abc", 'expected the integer 1, got "abc"'),  # invalid literal for int() before
    ([1], "expected the integer 1, got [1]"),  # a TypeError traceback before
    (True, "expected the integer 1, got true"),
    (None, "expected the integer 1, got null"),
    (2, "calibration format version 2, expected 1"),
])
def test_a_bad_version_is_one_line(tmp_path, version, needle):
    small_set().save(tmp_path)
    p = tmp_path / "calibration.json"
    doc = json.loads(p.read_text())
    doc["version"] = version
    p.write_text(json.dumps(doc))
    with pytest.raises(FormatError) as ei:
        calset.load(tmp_path)
    assert needle in _one_line_naming(ei, p)


def _edit_intrinsics_k(cs):
    cs.params["intrinsics"]["K"] = [[600.0, 0.0], [0.0, 600.0]]


def _edit_axis(cs):
    cs.params["generator"]["stage_zero_axis_cam"] = [1.0, 0.0]


def _edit_offset(cs):
    cs.params["generator"]["zero_offset_deg"] = "abc"


def _edit_ratio(cs):
    cs.params["generator"]["extinction_ratio"] = 0.5


def _edit_maps(cs):
    cs.dofp_maps = {k: v[:2, :2] for k, v in cs.dofp_maps.items()}


def _edit_light(cs):
    cs.params["light"] = 5


def _edit_nan(cs):
    cs.params["light"]["position_cam_m"] = [0.1, float("nan"), 0.2]


def _edit_image_size(cs):
    cs.params["intrinsics"]["image_size"] = [16, 4]


def _edit_dofp_layout(cs):
    cs.params["dofp"]["layout"] = "imx250mzr"


def _edit_camera_layout(cs):
    cs.params["camera"]["layout"] = "imx250mzr"


def _edit_missing_k(cs):
    del cs.params["intrinsics"]["K"]


@pytest.mark.parametrize("edit, file, needle", [
    (_edit_intrinsics_k, "calibration.json", "intrinsics.K: expected 3x3 finite numbers"),
    (_edit_axis, "calibration.json", "generator.stage_zero_axis_cam: expected 3 finite numbers"),
    (_edit_offset, "calibration.json", 'generator.zero_offset_deg: expected a number, got "abc"'),
    (_edit_ratio, "calibration.json", "generator.extinction_ratio: must be > 1, got 0.5"),
    (_edit_maps, "dofp_maps.npz", "is 2x2 pixels, analyzer.npz (the analyzer model) 8x4"),
    (_edit_light, "calibration.json", "light: expected a JSON object, got 5"),
    (_edit_nan, "calibration.json", "light.position_cam_m: expected 3 finite numbers"),
    (_edit_image_size, "calibration.json", "intrinsics.image_size is 16x4 pixels"),
    (_edit_dofp_layout, "calibration.json", "dofp.layout imx250mzr is not the analyzer"),
    (_edit_camera_layout, "calibration.json", "analyzer.npz layout imx250myr is not the camera's"),
    (_edit_missing_k, "calibration.json", "intrinsics.K: missing"),
])
def test_badly_shaped_sets_are_refused_naming_the_file(tmp_path, edit, file, needle):
    """Sets re-saved with ``CalibrationSet.save`` (so that the id matches) whose values have
    the wrong shape, type or range: refused on load, one line naming the file and the key
    (before: IndexError/TypeError tracebacks, messages without the file, or accepted)."""
    cs = small_set()
    edit(cs)
    cs.save(tmp_path)
    with pytest.raises(FormatError) as ei:
        calset.load(tmp_path)
    assert needle in _one_line_naming(ei, tmp_path / file)


def test_the_cli_refuses_a_badly_shaped_set_in_reference_mode_too(tmp_path, capsys):
    """A 2x2 K used to be an IndexError traceback even in reference mode (the geometry is
    read on load)."""
    cs = small_set()
    _edit_intrinsics_k(cs)
    cs.save(tmp_path / "cal")
    for argv in (["capture", "--poses", "0", "--out", str(tmp_path / "s"), "--no-progress"],
                 ["reconstruct", str(tmp_path / "nothing")]):
        rc = main(argv + ["--calibration", str(tmp_path / "cal")])
        err = capsys.readouterr().err
        if argv[0] == "capture":
            assert rc == 2 and err.count("\n") == 1
            assert f"{tmp_path / 'cal' / 'calibration.json'}: intrinsics.K" in err
    assert not (tmp_path / "s").exists()


def test_a_valid_set_round_trips(tmp_path):
    cs = small_set()
    cid = cs.save(tmp_path)
    back = calset.load(tmp_path)
    assert back.id == cid
    doc = json.loads((tmp_path / "calibration.json").read_text())
    assert doc["files"] == ["analyzer.npz", "dofp_maps.npz"]
    geo = back.sensor_geometry()
    assert (geo.layout, geo.area, geo.sensor_size) == ("imx250myr", (8, 4, 0, 0), (8, 4))


# ------------------------------------------------------------------------------ saving
def _without_pixels(cs: CalibrationSet) -> CalibrationSet:
    cs.analyzer, cs.dofp_maps = None, {}
    cs.params.pop("dofp")
    return cs


def test_saving_a_set_without_pixels_removes_the_old_npz_files(tmp_path):
    small_set().save(tmp_path)
    cs = _without_pixels(calset.load(tmp_path))
    cs.save(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json"]
    back = calset.load(tmp_path)
    assert back.analyzer is None and not back.has("dofp")


def test_npz_files_not_listed_are_not_read(tmp_path):
    """A stale analyzer.npz left next to a set that has none (a save interrupted between
    writing calibration.json and removing it) does not make the set unreadable."""
    _without_pixels(small_set()).save(tmp_path)
    small_set().analyzer.save(tmp_path / "analyzer.npz")
    assert calset.load(tmp_path).analyzer is None


def test_a_failed_save_leaves_the_earlier_set(tmp_path):
    """A write that fails (file size limit, as a full disk) while the new set is written
    leaves the earlier set loadable, unchanged, and no temporary files."""
    from _cli_helpers import run_with_file_size_limit

    small_set().save(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    code = ("import numpy as np\n"
            "from polrig.calibration.calset import CalibrationSet\n"
            "from polrig.sensor.analyzer import AnalyzerModel\n"
            "rng = np.random.default_rng(0)\n"
            "cs = CalibrationSet({'generator': {'zero_offset_deg': 2.0, 'extinction_ratio': 9.0}})\n"
            "g = rng.normal(1, 0.01, (256, 256))\n"
            "cs.analyzer = AnalyzerModel('imx250myr', g, g * 0 + 1, g * 0 + 1, g * 0)\n"
            f"cs.save({str(tmp_path)!r})\n")
    res = run_with_file_size_limit(code, 20000)
    assert res.returncode != 0 and "File too large" in res.stderr
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert calset.load(tmp_path).params["generator"]["zero_offset_deg"] == 1.5
