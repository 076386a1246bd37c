"""``polrig --version`` and ``python -m polrig --version``: the same line, the package's version,
which is also the installed distribution's."""

from __future__ import annotations

import importlib.metadata
import pathlib
import subprocess
import sys

import pytest

import polrig


@pytest.mark.parametrize("how", ["console script", "python -m"])
def test_version(how):
    if how == "python -m":
        argv = [sys.executable, "-m", "polrig", "--version"]
    else:
        script = pathlib.Path(sys.executable).with_name("polrig")
        assert script.is_file(), f"no console script next to {sys.executable} (pip install -e .)"
        argv = [str(script), "--version"]
    out = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout == f"polrig {polrig.__version__}\n" and out.stderr == ""
    assert polrig.__version__ == importlib.metadata.version("polrig")
