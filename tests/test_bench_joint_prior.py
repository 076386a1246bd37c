"""benchmarks/bench_joint_prior.py: a tiny run writes its table, with the two priors' solves
differing on the object (the correlation reaches the kernel)."""

from __future__ import annotations

import pathlib
import re
import sys

REPO = pathlib.Path(__file__).resolve().parents[1]


def test_a_tiny_run_writes_the_table(tmp_path):
    sys.path.insert(0, str(REPO))
    from benchmarks.bench_joint_prior import main

    out = tmp_path / "joint.md"
    assert main(["--grids", "16x24x3", "--rounds", "1", "--out", str(out)]) == 0
    row = [line for line in out.read_text().splitlines() if line.startswith("| 24x16, 3 colour(s)")]
    assert len(row) == 1
    cells = [c.strip() for c in row[0].strip("|").split("|")]
    assert all(float(c) > 0 for c in cells[1:5])
    assert re.fullmatch(r"\d\.\de[+-]\d\d", cells[5]) and 1e-4 < float(cells[5]) < 10
