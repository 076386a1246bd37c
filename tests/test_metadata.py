"""Sample metadata (issue 34, item 7): ``--sample``, ``--operator``, ``--note``, ``--md KEY=VALUE``
on ``polrig capture`` (and the GUI's fields, the same :class:`SampleMetadata` in the request),
recorded in ``session.json`` (schema version 4; older sessions migrate to empty metadata),
copied into every result EXR header (capture and reconstruct), shown by ``polrig info``; a
``--resume`` keeps the stored metadata and refuses a different one (one line, exit 2)."""

from __future__ import annotations

import json

import pytest

from polrig.app.manifest import (
    RESERVED_METADATA_KEYS,
    SCHEMA_VERSION,
    MetadataError,
    SampleMetadata,
)
from polrig.app.session import MANIFEST_NAME, Session
from polrig.cli import main
from polrig.formats.exr import read_exr

from test_cli_capture import MODEL_INSTALLED, sim_config

MD = ["--sample", "gold ball #3", "--operator", "ada", "--note", "after re-polishing",
      "--md", "lot=42", "--md", "batch_id=x7"]


# -- the record ------------------------------------------------------------------------------------
def test_the_record_checks_its_values():
    md = SampleMetadata(sample="s", operator="o", note="n", user={"z": "1", "a": "2"})
    assert list(md.user) == ["a", "z"] and md.header() == {
        "sample": "s", "operator": "o", "note": "n", "a": "2", "z": "1"}
    assert SampleMetadata().empty and SampleMetadata().header() == {}
    assert SampleMetadata() == SampleMetadata(user={}) and hash(md) == hash(
        SampleMetadata(sample="s", operator="o", note="n", user={"a": "2", "z": "1"}))
    for bad, text in ((dict(sample=3), "sample must be a string"),
                      (dict(user={"1a": "x"}), "'1a' is not an identifier"),
                      (dict(user={"a-b": "x"}), "'a-b' is not an identifier"),
                      (dict(user={"mode": "x"}), "'mode' is one of polrig's own keys"),
                      (dict(user={"polrig_x": "x"}), "'polrig_x' is one of polrig's own keys"),
                      (dict(user={"k": 1}), "'k': the value must be a string")):
        with pytest.raises(MetadataError, match=text):
            SampleMetadata(**bad)
    assert SampleMetadata.parse_user(["a=1", " b = two words "]) == {"a": "1", "b": "two words"}
    with pytest.raises(MetadataError, match="give KEY=VALUE"):
        SampleMetadata.parse_user(["a"])
    with pytest.raises(MetadataError, match="given twice"):
        SampleMetadata.parse_user(["a=1", "a=2"])


# -- a capture with metadata -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("md")
    cfg = sim_config(tmp / "rig.toml", noise=False)
    out = tmp / "run"
    assert main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                 "--no-progress", *MD]) == 0
    return cfg, out


def test_the_manifest_records_it(captured):
    _, out = captured
    stored = json.loads((out / MANIFEST_NAME).read_text())
    assert stored["schema_version"] == SCHEMA_VERSION == 7
    line = " ".join(stored["command_line"])
    assert "--sample gold ball #3" in line and "--md lot=42 --md batch_id=x7" in line
    assert stored["metadata"] == {"sample": "gold ball #3", "operator": "ada",
                                  "note": "after re-polishing",
                                  "user": {"batch_id": "x7", "lot": "42"}}
    assert Session.open(out).manifest["metadata"] == SampleMetadata(
        sample="gold ball #3", operator="ada", note="after re-polishing",
        user={"lot": "42", "batch_id": "x7"})


def test_every_result_header_has_it_and_no_key_of_its_own_clashes(captured, tmp_path):
    cfg, out = captured
    want = {"sample": "gold ball #3", "operator": "ada", "note": "after re-polishing",
            "lot": "42", "batch_id": "x7"}
    for cap in ("c000_pose000.0", "c001_pose090.0"):
        meta = read_exr(out / cap / "mueller.exr").metadata
        assert {k: meta[k] for k in want} == want
        # polrig's own header keys are all reserved: a user key can never overwrite one
        assert set(meta) - set(want) <= RESERVED_METADATA_KEYS, set(meta) - RESERVED_METADATA_KEYS


@pytest.mark.skipif(not MODEL_INSTALLED, reason="single-shot model not installed")
@pytest.mark.parametrize("mode, states", [("single-shot", "0"), ("hybrid", "0,60")])
def test_network_modes_headers_have_no_key_a_user_key_could_take(tmp_path, mode, states):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", mode, "--states", states, "--config",
                 str(cfg), "--out", str(out), "--no-progress", "--device", "cpu",
                 "--md", "lot=42"]) == 0
    meta = read_exr(out / "c000_pose000.0" / "mueller.exr").metadata
    assert meta["lot"] == "42"
    assert set(meta) - {"lot"} <= RESERVED_METADATA_KEYS, set(meta) - RESERVED_METADATA_KEYS


def test_info_shows_it(captured, capsys):
    _, out = captured
    assert main(["info", str(out), "--no-verify"]) == 0
    assert ("metadata: sample: gold ball #3; operator: ada; note: after re-polishing; "
            "batch_id: x7; lot: 42") in capsys.readouterr().out


def test_reconstruct_copies_it_into_the_revision(captured, tmp_path):
    import shutil

    _, out = captured
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "session.lock").unlink(missing_ok=True)
    assert main(["reconstruct", str(copy), "--no-progress"]) == 0
    meta = read_exr(copy / "c000_pose000.0" / "rev1" / "mueller.exr").metadata
    assert meta["sample"] == "gold ball #3" and meta["lot"] == "42"


def test_a_resume_keeps_it_and_refuses_another(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out),
                 "--no-progress", *MD]) == 0
    before = (out / MANIFEST_NAME).read_bytes()
    capsys.readouterr()
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress", "--sample", "another"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the session was captured with metadata" in err[0], err
    assert "--sample/--operator/--note/--md" in err[0]
    assert (out / MANIFEST_NAME).read_bytes() == before
    # the same metadata again, or none: kept
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress", *MD]) == 0
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--no-progress"]) == 0
    assert Session.open(out).manifest["metadata"].sample == "gold ball #3"


@pytest.mark.parametrize("args, text", [
    (["--md", "mode=x"], "--md: metadata key 'mode' is one of polrig's own keys"),
    (["--md", "lot"], "--md: metadata 'lot': give KEY=VALUE"),
    (["--md", "2x=1"], "--md: metadata key '2x' is not an identifier"),
])
def test_bad_metadata_is_one_line_and_writes_nothing(tmp_path, capsys, args, text):
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--out", str(out), "--no-progress", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and text in err[0], err
    assert not out.exists()


# -- older sessions --------------------------------------------------------------------------------
def test_a_version_3_session_opens_with_empty_metadata(captured, tmp_path, capsys):
    """A manifest of version 3 (no ``metadata``) migrates in memory to empty metadata (one
    history event, 3 -> 4), writes nothing, and ``polrig info`` shows no metadata line."""
    import shutil

    _, out = captured
    old = tmp_path / "old"
    shutil.copytree(out, old)
    m = json.loads((old / MANIFEST_NAME).read_text())
    del m["metadata"]
    m["schema_version"] = 3
    (old / MANIFEST_NAME).write_text(json.dumps(m))
    before = (old / MANIFEST_NAME).read_bytes()
    s = Session.open(old)
    assert s.stored_version == 3 and s.manifest["schema_version"] == 7
    assert s.manifest["metadata"] == SampleMetadata()
    last = s.manifest["history"][-4]
    assert (last["event"], last["from_version"], last["to_version"]) == ("schema migrated", 3, 4)
    assert main(["info", str(old), "--no-verify"]) == 0
    printed = capsys.readouterr().out
    assert "schema: version 3, read as version 7" in printed and "metadata:" not in printed
    assert (old / MANIFEST_NAME).read_bytes() == before


def test_a_damaged_metadata_record_is_one_line(captured, tmp_path):
    import shutil

    from polrig.errors import FormatError

    _, out = captured
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    m = json.loads((bad / MANIFEST_NAME).read_text())
    m["metadata"]["user"]["mode"] = "x"
    (bad / MANIFEST_NAME).write_text(json.dumps(m))
    with pytest.raises(FormatError, match=r"metadata: metadata key 'mode' is one of polrig's own"):
        Session.open(bad)


def test_a_distributed_reconstruct_copies_it_too(captured, tmp_path):
    """The workers of ``polrig reconstruct --workers`` build the header in the same place
    (:meth:`polrig.app.processing.Processor.solve` on the session they read)."""
    import shutil

    pytest.importorskip("distributed")
    _, out = captured
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "session.lock").unlink(missing_ok=True)
    assert main(["reconstruct", str(copy), "--workers", "1", "--no-progress"]) == 0
    for cap in ("c000_pose000.0", "c001_pose090.0"):
        meta = read_exr(copy / cap / "rev1" / "mueller.exr").metadata
        assert (meta["operator"], meta["batch_id"]) == ("ada", "x7")
