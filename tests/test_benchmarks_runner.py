"""``python -m benchmarks``: options after one benchmark's name reach that benchmark, and
options with several names are refused in one line."""

from __future__ import annotations

import pytest

from benchmarks.__main__ import main


def test_options_reach_the_one_benchmark_named(capfd):
    assert main(["diffuse_route", "--help"]) == 0
    out = capfd.readouterr().out
    assert "python -m benchmarks diffuse_route" in out and "--rounds" in out


def test_options_with_several_benchmarks_are_refused(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["dofp", "continuum", "--models"])
    assert exc.value.code == 2
    assert "name exactly one" in capsys.readouterr().err


def test_an_unknown_benchmark_is_named():
    with pytest.raises(SystemExit, match="unknown benchmark 'nonesuch'"):
        main(["nonesuch"])
