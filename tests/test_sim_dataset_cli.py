"""``polrig sim dataset`` refuses what it cannot make, before anything is written: sides off the
networks' size multiple, a negative seed, an --out that is (or lies in) a file, a folder whose
manifest.json is not a dataset manifest. One line each, exit 2."""

from __future__ import annotations

import json

import pytest

from polrig.cli import main
from polrig.sim.dataset import SIZE_MULTIPLE, generate_dataset


def _run(capsys, *argv) -> tuple[int, str]:
    try:
        code = main(["sim", "dataset", "--quiet", *map(str, argv)])
    except SystemExit as exc:  # argparse
        code = exc.code
    return code, capsys.readouterr().err.strip()


def test_the_size_multiple_is_the_networks_one():
    from polrig.models.runtime import SIZE_MULTIPLE as RUNTIME

    assert SIZE_MULTIPLE == RUNTIME


@pytest.mark.parametrize("argv, needle", [(["--size", "33"], "multiples of 8"), (["--size", "9"], "multiples of 8"),
                                          (["--seed", "-1"], "--seed"), (["--count", "0"], "--count"),
                                          (["--shard-size", "0"], "--shard-size")])
def test_bad_numbers_write_nothing(tmp_path, capsys, argv, needle):
    code, err = _run(capsys, "--count", "2", *argv, "--out", tmp_path / "ds")
    assert code == 2 and needle in err.splitlines()[-1] and "Traceback" not in err
    assert not (tmp_path / "ds").exists()


def test_an_out_that_is_or_lies_in_a_file_is_one_line(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile", tmp_path / "afile" / "x"):
        code, err = _run(capsys, "--count", "2", "--size", "32", "--out", out)
        assert code == 2 and "is a file, not a folder" in err and "\n" not in err


@pytest.mark.parametrize("text", ["[]", "{broken", "7"])
def test_a_folder_with_a_foreign_manifest_is_refused(tmp_path, capsys, text):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "manifest.json").write_text(text)
    code, err = _run(capsys, "--count", "2", "--size", "32", "--out", tmp_path / "ds")
    assert code == 2 and str(tmp_path / "ds" / "manifest.json") in err and "\n" not in err
    assert sorted(p.name for p in (tmp_path / "ds").iterdir()) == ["manifest.json"]


def test_a_good_set_is_still_made(tmp_path, capsys):
    code, err = _run(capsys, "--count", "2", "--size", "16", "--seed", "3", "--out", tmp_path / "ds")
    assert code == 0, err
    assert json.loads((tmp_path / "ds" / "manifest.json").read_text())["width"] == 16
    with pytest.raises(ValueError, match="seed"):
        generate_dataset(tmp_path / "api", count=1, width=16, seed=-2, progress=False)
    assert not (tmp_path / "api").exists()
