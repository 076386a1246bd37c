"""``polrig sim dataset --workers N``: shards made as Dask tasks on local worker processes are
the serial run's bytes (same seed), and a re-run resumes with the missing shards only."""

from __future__ import annotations

import pytest

pytest.importorskip("distributed")

from polrig.cli import main  # noqa: E402


def _shards(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.glob("shard-*.npz"))}


def test_two_workers_write_the_serial_shards_and_resume(tmp_path, capsys):
    common = ["sim", "dataset", "--count", "6", "--size", "16", "--seed", "5", "--shard-size",
              "2", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "serial")]) == 0
    assert main([*common, "--out", str(tmp_path / "dist"), "--workers", "2"]) == 0
    serial, dist = _shards(tmp_path / "serial"), _shards(tmp_path / "dist")
    assert len(serial) == 3 and dist == serial
    assert ((tmp_path / "dist" / "manifest.json").read_bytes()
            == (tmp_path / "serial" / "manifest.json").read_bytes())
    (tmp_path / "dist" / "shard-00001.npz").unlink()
    (tmp_path / "dist" / ".shard-00002.npz.0123456789ab.tmp.npz").write_bytes(b"half")
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "dist"), "--workers", "2"]) == 0
    assert "1 shard(s) written, 2 already complete" in capsys.readouterr().out
    assert _shards(tmp_path / "dist") == serial
    assert sorted(p.name for p in (tmp_path / "dist").iterdir()) == [
        "manifest.json", "shard-00000.npz", "shard-00001.npz", "shard-00002.npz"]


def test_workers_pass_the_material_mix_and_interreflections(tmp_path):
    """``--materials`` and ``--indirect-samples`` reach the workers: the same bytes as serial."""
    common = ["sim", "dataset", "--count", "4", "--size", "16", "--seed", "8", "--shard-size",
              "2", "--quiet", "--materials", "train", "--indirect-samples", "2"]
    assert main([*common, "--out", str(tmp_path / "serial")]) == 0
    assert main([*common, "--out", str(tmp_path / "dist"), "--workers", "2"]) == 0
    serial, dist = _shards(tmp_path / "serial"), _shards(tmp_path / "dist")
    assert len(serial) == 2 and dist == serial
    assert ((tmp_path / "dist" / "manifest.json").read_bytes()
            == (tmp_path / "serial" / "manifest.json").read_bytes())
    plain = tmp_path / "plain"
    assert main([*common[:-4], "--out", str(plain)]) == 0
    assert _shards(plain) != serial  # the options changed the samples
