"""A command's outputs (:mod:`polrig.formats.outputs`): an output path that is an input is
refused in one line before any work (exit 2), and the files of one run appear all or none,
so a failure (a full disk, a file that may not be replaced) leaves every earlier file as it
was and no temporary behind. ``polrig stokes``, ``analyze`` and ``stats`` here; ``infer`` in
test_cli_infer.py, ``export`` in test_export.py."""

from __future__ import annotations

import errno
import os
import pathlib

import numpy as np
import pytest

from polrig.atomic import write_error
from polrig.cli import main
from polrig.errors import ConfigError
from polrig.formats.exr import read_exr, write_mueller_exr
from polrig.formats.outputs import OutputSet, check_not_input
from polrig.formats.rawio import write_raw
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.frame import Frame, FrameMeta


def snapshot(folder: pathlib.Path) -> dict[str, bytes]:
    """Every file of ``folder`` (hidden ones included) by name, with its bytes."""
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def no_room(path) -> OSError:
    return write_error(path, OSError(errno.ENOSPC, "No space left on device"))


# -- the helper ---------------------------------------------------------------------------------
def test_an_output_set_replaces_every_file_and_leaves_no_temporary(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    with OutputSet() as outs:
        outs.temporary(tmp_path / "a.txt").write_text("new a")
        stem = outs.temporary_stem(tmp_path, "m", ("_x.txt", "_y.txt"))
        for sfx in ("_x.txt", "_y.txt"):
            (tmp_path / f"{stem}{sfx}").write_text(sfx)
        assert snapshot(tmp_path)["a.txt"] == b"old a"  # nothing replaced before the end
    assert snapshot(tmp_path) == {"a.txt": b"new a", "m_x.txt": b"_x.txt", "m_y.txt": b"_y.txt"}
    assert outs.finals == [tmp_path / n for n in ("a.txt", "m_x.txt", "m_y.txt")]


def test_a_failed_write_removes_the_temporaries_and_names_the_final_file(tmp_path):
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    with pytest.raises(OSError) as exc:
        with OutputSet() as outs:
            outs.temporary(tmp_path / "a.txt").write_text("new a")
            raise no_room(outs.temporary(tmp_path / "b.txt"))
    assert str(exc.value) == f"{tmp_path / 'b.txt'}: cannot write (No space left on device)"
    assert exc.value.errno == errno.ENOSPC
    assert snapshot(tmp_path) == {"a.txt": b"old a", "b.txt": b"old b"}


def test_a_rename_that_fails_puts_back_the_files_renamed_before_it(tmp_path):
    """The third file's final name is a folder with a file in it: it cannot be replaced, so the
    first (replaced) is restored and the second (new) removed."""
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "c.txt").mkdir()
    (tmp_path / "c.txt" / "keep").write_text("kept")
    with pytest.raises(OSError, match=f"^{tmp_path / 'c.txt'}: cannot write"):
        with OutputSet() as outs:
            for name in ("a.txt", "b.txt", "c.txt"):
                outs.temporary(tmp_path / name).write_text(f"new {name}")
    assert snapshot(tmp_path) == {"a.txt": b"old a"}
    assert (tmp_path / "c.txt" / "keep").read_text() == "kept"


def test_an_output_that_is_an_input_is_refused_through_links(tmp_path):
    raw = tmp_path / "raw.png"
    raw.write_bytes(b"raw")
    (tmp_path / "sym.png").symlink_to(raw)
    os.link(raw, tmp_path / "hard.png")
    for out in (raw, tmp_path / "sym.png", tmp_path / "hard.png", tmp_path / "." / "raw.png"):
        with pytest.raises(ConfigError) as exc:
            check_not_input([("--out", out)], [None, raw])
        assert str(exc.value).startswith(f"--out {out} is the input {raw};")
    check_not_input([("--out", tmp_path / "other.png")], [raw])  # another file: fine
    with pytest.raises(ConfigError, match="holds the input"):
        check_not_input([("-o", tmp_path)], [raw], replaces_folder=True)


# -- polrig stokes ------------------------------------------------------------------------------
def _raw_frame(path: pathlib.Path, layout: str = "imx250mzr") -> pathlib.Path:
    model = AnalyzerModel.ideal(f"{layout}@0,0", (32, 40))
    s = np.array([2000.0, 600.0, 300.0])
    stokes = np.broadcast_to(s[None, :, None, None], (model.n_colours, 3, 32, 40))
    meta = FrameMeta(frame_id=1, timestamp_s=0.0, exposure_us=1000.0, gain_db=0.0,
                     pixel_format="Mono16", layout=layout, bit_depth=16, black_level_dn=0.0)
    write_raw(path, Frame(np.round(model.mosaic(stokes)).astype(np.uint16), meta))
    return path


def test_stokes_refuses_an_output_that_is_the_raw_frame(tmp_path, capsys):
    """A raw frame named like a preview of ``--out`` (sample_s1.png for sample.exr), directly
    or through a symbolic link: exit 2, one line naming both, the frame untouched."""
    raw = _raw_frame(tmp_path / "sample_s1.png")
    before = snapshot(tmp_path)
    assert main(["stokes", str(raw), "--out", str(tmp_path / "sample.exr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"polrig: error: --out preview {raw} is the input {raw};")
    assert len(err.splitlines()) == 1
    (tmp_path / "v").mkdir()
    (tmp_path / "v" / "x_dolp.png").symlink_to(raw)
    assert main(["stokes", str(raw), "--out", str(tmp_path / "v" / "x.exr")]) == 2
    assert f"--out preview {tmp_path / 'v' / 'x_dolp.png'} is the input {raw};" in capsys.readouterr().err
    assert snapshot(tmp_path) == before and os.listdir(tmp_path / "v") == ["x_dolp.png"]


def test_stokes_writes_its_exr_and_previews_all_or_none(tmp_path, monkeypatch, capsys):
    """The sixth file (OUT_imin.png) cannot be written: the EXR and the previews of the run
    before stay as they were, nothing new, no temporary; one line naming the file, exit 1."""
    import polrig.atomic

    raw = _raw_frame(tmp_path / "frame.png")
    out = tmp_path / "s.exr"
    assert main(["stokes", str(raw), "--out", str(out)]) == 0
    before = snapshot(tmp_path)
    assert len(before) == 9  # frame, sidecar, EXR, six previews
    real = polrig.atomic.atomic_write_bytes

    def full_at_imin(path, data):
        if "_imin" in pathlib.Path(path).name:
            raise no_room(path)
        real(path, data)

    monkeypatch.setattr(polrig.atomic, "atomic_write_bytes", full_at_imin)
    capsys.readouterr()
    assert main(["stokes", str(raw), "--demosaic", "superpixel", "--out", str(out)]) == 1
    assert capsys.readouterr().err == (f"polrig: error: {tmp_path / 's_imin.png'}: cannot write "
                                       f"(No space left on device)\n")
    assert snapshot(tmp_path) == before


def test_stokes_min_snr_help_says_what_0_masks(capsys):
    with pytest.raises(SystemExit):
        main(["stokes", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "0 masks nothing" not in text
    assert "0 masks only clipped pixels and those without signal" in text


# -- polrig analyze -----------------------------------------------------------------------------
def _result(path: pathlib.Path, masked: np.ndarray | None = None, sigma: bool = True) -> pathlib.Path:
    """A 1-colour 8x6 Mueller result: a weak diattenuator (polarizance 0.1), mask planes
    (``masked``: True = mask bit 1) and, with ``sigma``, sigma planes only (no sigma_noise)."""
    h, w = 6, 8
    m = np.zeros((1, 3, 3, h, w), np.float32)
    m[0, 0, 0], m[0, 1, 0], m[0, 0, 1], m[0, 1, 1], m[0, 2, 2] = 100, 10, 10, 100, 99
    extra = {"mask.Y": (np.zeros((h, w)) if masked is None else masked).astype(np.float32)}
    if sigma:
        extra.update({f"sigma.M{r}{c}.Y": np.full((h, w), 0.5, np.float32)
                      for r in range(3) for c in range(3)})
    write_mueller_exr(path, m, extra=extra)
    return path


def test_analyze_refuses_to_write_over_its_source(tmp_path, capsys):
    src = _result(tmp_path / "m.exr")
    (tmp_path / "link.exr").symlink_to(src)
    before = snapshot(tmp_path)
    for out in (src, tmp_path / "link.exr"):
        assert main(["analyze", str(src), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"polrig: error: --out {out} is the input {src};") and err.count("\n") == 1
    assert snapshot(tmp_path) == before


def test_analyze_normals_only_where_the_decomposition_counts(tmp_path, capsys):
    """Masked pixels (the result's mask) have no normal and are not counted: none of a fully
    masked result, the unmasked half of a half-masked one."""
    h, w = 6, 8
    for masked, n in ((np.ones((h, w), bool), 0), (np.arange(w)[None, :].repeat(h, 0) < 4, 24)):
        src = _result(tmp_path / f"m{n}.exr", masked)
        out = tmp_path / f"maps{n}.exr"
        assert main(["analyze", str(src), "--out", str(out), "--normals", "--ior", "1.5"]) == 0
        line = capsys.readouterr().out
        assert f"decomposition of {n} valid pixel-colour(s)" in line
        assert line.rstrip().endswith(f"at {n} pixel-colour(s)")
        planes = read_exr(out).planes
        for name in ("sfp_normal0.X.Y", "sfp_zenith_deg0.Y", "sfp_azimuth_deg.Y"):
            assert np.isnan(planes[name][masked]).all()
            assert np.isfinite(planes[name][~masked]).all()


# -- polrig stats -------------------------------------------------------------------------------
def test_stats_writes_its_csv_and_profile_all_or_none_on_a_full_disk(tmp_path):
    """A real write failure (the process may not write files past a size between the two
    CSVs'): the first CSV is not left new beside a missing profile; the old pair stays."""
    from _cli_helpers import polrig_with_file_size_limit

    src = _result(tmp_path / "m.exr")
    csv_out, prof = tmp_path / "st.csv", tmp_path / "st_profile.csv"
    argv = ["stats", src, "--csv", csv_out, "--profile", "0,0,8,6", "--spacing", "0.05"]
    assert main([str(a) for a in argv]) == 0
    small, big = csv_out.stat().st_size, prof.stat().st_size
    assert small < big
    csv_out.write_text("old stats\n")
    prof.write_text("old profile\n")
    before = snapshot(tmp_path)
    res = polrig_with_file_size_limit(argv, (small + big) // 2)
    assert res.returncode == 1, res.stderr
    assert res.stderr == f"polrig: error: {prof}: cannot write (File too large)\n"
    assert snapshot(tmp_path) == before


def test_stats_refuses_a_csv_that_is_its_source(tmp_path, capsys):
    src = _result(tmp_path / "m.exr")
    (tmp_path / "m.csv").symlink_to(src)
    before = snapshot(tmp_path)
    assert main(["stats", str(src), "--csv", str(tmp_path / "m.csv")]) == 2
    assert capsys.readouterr().err.startswith(
        f"polrig: error: --csv {tmp_path / 'm.csv'} is the input {src};")
    assert snapshot(tmp_path) == before


def test_stats_names_the_sigma_planes_it_did_not_find(tmp_path, capsys):
    src = _result(tmp_path / "m.exr")  # sigma planes, no sigma_noise planes
    assert main(["stats", str(src), "--sigma", "sigma_noise"]) == 0
    assert "sigma none (no sigma_noise.M{rc} planes)" in capsys.readouterr().out
    assert main(["stats", str(src), "--sigma", "none"]) == 0
    assert "(image 8x6, sigma none)" in capsys.readouterr().out
    assert main(["stats", str(src)]) == 0
    assert "(image 8x6, sigma sigma)" in capsys.readouterr().out
    bare = _result(tmp_path / "bare.exr", sigma=False)
    assert main(["stats", str(bare)]) == 0
    assert "sigma none (no sigma.M{rc} planes)" in capsys.readouterr().out
