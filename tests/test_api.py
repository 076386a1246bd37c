"""The Python API (issue 34, item 5; ``docs/api.md``): the page's worked example runs as written
(its ``python`` code blocks in order, in an empty folder), and the openers' details: dims,
coordinates, laziness (one dask chunk per capture), sample metadata as attributes, a revision,
an older session, the one-line error without the ``api`` extra."""

from __future__ import annotations

import json
import pathlib
import re
import sys

import numpy as np
import pytest

import polrig
from polrig.app.manifest import RESERVED_METADATA_KEYS, SCHEMA_VERSION
from polrig.app.session import MANIFEST_NAME
from polrig.cli import main
from polrig.formats.exr import read_mueller_exr

from test_cli_capture import sim_config

REPO = pathlib.Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "api.md"


def code_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_the_docs_example_runs(tmp_path, monkeypatch, capsys):
    blocks = code_blocks(DOC.read_text("utf-8"))
    assert len(blocks) >= 3
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "docs_api_example"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"{DOC}:block{i}", "exec"), namespace)
    printed = capsys.readouterr().out
    assert "pose 90 deg done" in printed and "median depolarization index" in printed


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    cfg = sim_config(tmp / "rig.toml", noise=False)
    out = tmp / "run"
    assert main(["capture", "--poses", "0,45,90", "--config", str(cfg), "--out", str(out),
                 "--no-progress", "--sample", "box", "--md", "lot=7",
                 "--exr-planes", "mueller,sigma,mask"]) == 0
    return out


def test_open_session_is_lazy_one_chunk_per_capture_and_the_files_values(session):
    ds = polrig.open_session(session)
    assert ds.mueller.dims == ("capture", "channel", "i", "j", "y", "x")
    assert ds.mask.dims == ("capture", "channel", "y", "x")
    assert set(ds.data_vars) == {"mueller", "sigma", "mask"}  # the plan's planes only
    assert list(ds.capture.values) == [0.0, 45.0, 90.0] and list(ds.channel.values) == ["Y"]  # mono sensor
    assert list(ds.capture_id.values) == ["c000_pose000.0", "c001_pose045.0", "c002_pose090.0"]
    assert ds.mueller.data.numblocks == (3, 1, 1, 1, 1, 1)  # one chunk per capture
    assert ds.mueller.shape[-2:] == (32, 32) and ds.mask.dtype == np.uint8
    # the values are the file's, element (i, j) = M{i}{j}
    f = read_mueller_exr(session / "c001_pose045.0" / "mueller.exr")
    np.testing.assert_array_equal(ds.mueller.sel(capture=45.0).values, f.mueller)
    np.testing.assert_array_equal(ds.sigma.sel(capture=45.0, channel="Y", i=1, j=2).values,
                                  f.extra["sigma.M12.Y"])
    np.testing.assert_array_equal(ds.mask.sel(capture=45.0, channel="Y").values,
                                  f.extra["mask.Y"].astype(np.uint8))
    a = ds.attrs
    assert (a["sample"], a["operator"], a["note"], a["lot"]) == ("box", "", "", "7")
    assert a["plan"]["poses_deg"] == [0.0, 45.0, 90.0] and a["schema_version"] == SCHEMA_VERSION
    json.dumps(a)  # every attribute JSON-serialisable
    assert set(a) - {"lot"} <= RESERVED_METADATA_KEYS  # a user key never overwrites one of polrig's
    assert a["captures_without_result"] == []


def test_open_result_and_a_revision(session, tmp_path):
    one = polrig.open_result(session / "c000_pose000.0" / "mueller.exr")
    assert one.mueller.dims == ("channel", "i", "j", "y", "x")
    assert one.attrs["sample"] == "box" and one.attrs["pose_deg"] == 0.0
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(session, copy)
    assert main(["reconstruct", str(copy), "--no-progress"]) == 0
    rev = polrig.open_session(copy, revision="rev1")
    assert rev.attrs["revision"] == "rev1" and rev.sizes["capture"] == 3
    with pytest.raises(KeyError, match="no revision 'rev9'"):
        polrig.open_session(copy, revision="rev9")


def test_an_older_session_and_one_without_results_open(session, tmp_path):
    import shutil

    old = tmp_path / "old"
    shutil.copytree(session, old)
    m = json.loads((old / MANIFEST_NAME).read_text())
    del m["metadata"]
    m["schema_version"] = 3
    m["captures"][2]["files"] = {k: v for k, v in m["captures"][2]["files"].items()
                                 if k in ("raw", "dark", "truth_mueller")}
    m["captures"][2]["status"] = "acquired"
    (old / MANIFEST_NAME).write_text(json.dumps(m))
    ds = polrig.open_session(old)
    assert ds.sizes["capture"] == 2 and ds.attrs["captures_without_result"] == ["c002_pose090.0"]
    assert ds.attrs["sample"] == "" and ds.attrs["schema_version"] == SCHEMA_VERSION


def test_without_the_extra_the_openers_name_it(monkeypatch, session):
    monkeypatch.setitem(sys.modules, "xarray", None)
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'polrig\[api\]'"):
        polrig.open_session(session)


def test_pixels_are_read_when_computed_once_per_capture(session, monkeypatch):
    """Opening reads headers only; computing a capture's variables reads its file once."""
    import dask

    from polrig.app import dataset

    reads = []
    real = dataset.read_mueller_exr
    monkeypatch.setattr(dataset, "read_mueller_exr", lambda p: reads.append(p) or real(p))
    ds = polrig.open_session(session)
    assert reads == []
    one = ds.sel(capture=90.0)
    dask.compute(one.mueller.data, one.sigma.data, one.mask.data, scheduler="sync")
    assert [p.parent.name for p in reads] == ["c002_pose090.0"]
