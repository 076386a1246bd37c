"""Stokes/Mueller OpenEXR files: bit-exact round trips, metadata, one-line errors."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from polrig.errors import FormatError
from polrig.formats.exr import (
    MuellerRows,
    colour_planes,
    mueller_channels,
    read_exr,
    read_mueller_exr,
    read_stokes_exr,
    write_exr,
    write_mueller_exr,
    write_stokes_exr,
)
from polrig.optics.conventions import CONVENTIONS_VERSION


def _bits(a):
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def _nasty(rng, shape):
    """Random float32 including NaN, +-inf, -0, subnormals and extremes."""
    a = rng.normal(0, 1e3, shape).astype(np.float32)
    flat = a.reshape(-1)
    specials = np.array([np.nan, np.inf, -np.inf, -0.0, 1e-45, 3.4e38, -1e-40], np.float32)
    flat[: specials.size] = specials
    return a


@pytest.mark.parametrize("c", [1, 3])
def test_mueller_round_trip_is_bit_exact(tmp_path, c):
    rng = np.random.default_rng(c)
    m = _nasty(rng, (c, 3, 3, 7, 9))
    mask = rng.random((7, 9)) > 0.5
    sigma = rng.random((c, 7, 9)).astype(np.float32)
    meta = {"incident_state": [[1.0, 0.5, 0.0]], "calibration_id": "cal-2026-11-22",
            "capture": {"exposure_us": 1200.0, "poses": 3}}
    p = write_mueller_exr(tmp_path / "m.exr", m,
                          extra={"mask": mask, **colour_planes("sigma.M00", sigma)},
                          metadata=meta)
    back = read_mueller_exr(p)
    assert back.mueller.shape == m.shape and back.mueller.dtype == np.float32
    np.testing.assert_array_equal(_bits(back.mueller), _bits(m))
    np.testing.assert_array_equal(back.extra["mask"], mask.astype(np.float32))
    np.testing.assert_array_equal(back.extra[f"sigma.M00.{'Y' if c == 1 else 'G'}"],
                                  sigma[0 if c == 1 else 1])
    assert back.metadata == meta
    assert back.conventions == CONVENTIONS_VERSION
    names = set(read_exr(p).planes)
    assert set(mueller_channels(c)) <= names
    assert ("M12.Y" in names) == (c == 1) and ("M12.B" in names) == (c == 3)


@pytest.mark.parametrize("c", [1, 3])
def test_stokes_round_trip_is_bit_exact(tmp_path, c):
    rng = np.random.default_rng(10 + c)
    s = _nasty(rng, (c, 3, 5, 4))
    p = write_stokes_exr(tmp_path / "s.exr", s, extra=colour_planes("dolp", s[:, 1]))
    back = read_stokes_exr(p)
    np.testing.assert_array_equal(_bits(back.stokes), _bits(s))
    assert set(back.extra) == set(colour_planes("dolp", s[:, 1]))
    img = read_exr(p)
    assert img.kind == "stokes" and "S2." + ("Y" if c == 1 else "B") in img.planes


def test_files_are_readable_by_plain_openexr(tmp_path):
    s = np.arange(2 * 3 * 3, dtype=np.float32).reshape(1, 3, 2, 3)
    p = write_stokes_exr(tmp_path / "s.exr", s, metadata={"note": "x"})
    f = OpenEXR.File(str(p), separate_channels=True)
    np.testing.assert_array_equal(f.channels()["S1.Y"].pixels, s[0, 1])
    assert f.header()["polrig:note"] == '"x"'
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def _one_line(exc, path):
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_non_exr_file(tmp_path):
    p = tmp_path / "not.exr"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(FormatError) as e:
        read_stokes_exr(p)
    assert "not an OpenEXR file" in _one_line(e, p)


@pytest.mark.parametrize("keep", [0.001, 0.01, 0.3, 0.6, 0.95, 0.9999])
def test_truncated_file(tmp_path, keep, capfd):
    """A file cut short anywhere (header, offset table, a chunk) is one error line naming it, and
    the OpenEXR library prints nothing of its own (the check runs before it reads)."""
    rng = np.random.default_rng(1)
    p = write_mueller_exr(tmp_path / "m.exr", rng.random((3, 3, 3, 64, 64)).astype(np.float32))
    data = p.read_bytes()
    bad = tmp_path / "trunc.exr"
    bad.write_bytes(data[: int(len(data) * keep)])
    capfd.readouterr()
    with pytest.raises(FormatError) as e:
        read_mueller_exr(bad)
    assert "OpenEXR" in _one_line(e, bad)
    assert capfd.readouterr() == ("", "")  # no library chatter on stdout or stderr


def test_missing_channels(tmp_path):
    m = np.zeros((3, 3, 3, 4, 4), np.float32)
    planes = {f"M{r}{c}.{s}": m[0, r, c] for r in range(3) for c in range(3) for s in "RGB"}
    del planes["M21.G"], planes["M02.B"]
    p = write_exr(tmp_path / "m.exr", planes, kind="mueller")
    with pytest.raises(FormatError) as e:
        read_mueller_exr(p)
    msg = _one_line(e, p)
    assert "M21.G" in msg and "M02.B" in msg
    with pytest.raises(FormatError) as e:
        read_stokes_exr(p)
    assert "S0" in _one_line(e, p)


def test_missing_file_and_bad_arrays(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_exr(tmp_path / "nope.exr")
    with pytest.raises(ValueError):
        write_stokes_exr(tmp_path / "x.exr", np.zeros((2, 3, 4, 4)))
    with pytest.raises(ValueError):
        write_mueller_exr(tmp_path / "x.exr", np.zeros((1, 3, 4, 4, 4)))
    with pytest.raises(ValueError, match="clashes"):
        write_stokes_exr(tmp_path / "x.exr", np.zeros((1, 3, 4, 4)),
                         extra={"S0.Y": np.zeros((4, 4))})
    with pytest.raises(ValueError, match="JSON"):
        write_stokes_exr(tmp_path / "x.exr", np.zeros((1, 3, 4, 4)), metadata={"a": object()})


def test_a_failed_write_is_an_oserror_naming_the_file_and_leaves_nothing(tmp_path):
    """OpenEXR reports I/O failures as RuntimeError naming its temporary file; write_exr
    turns them into one-line OSErrors naming the file asked for (exit 1 in the CLI). The
    failure is real: the child process may not write files over 4 kB (a full disk gives
    "No space left on device" the same way)."""
    from _cli_helpers import run_with_file_size_limit

    out = tmp_path / "s.exr"
    code = ("import numpy as np\nfrom polrig.formats.exr import write_stokes_exr\n"
            "s = np.random.default_rng(0).random((3, 3, 64, 64)).astype(np.float32)\n"
            "try:\n"
            f"    write_stokes_exr({str(out)!r}, s)\n"
            "except OSError as exc:\n"
            "    print(type(exc).__name__, exc)\n")
    res = run_with_file_size_limit(code, 4096)
    assert res.returncode == 0, res.stderr
    assert res.stdout == f"OSError {out}: cannot write the OpenEXR file (File too large)\n"
    assert list(tmp_path.iterdir()) == []


def test_writing_onto_a_folder_names_the_folder(tmp_path):
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(OSError) as ei:
        write_stokes_exr(tmp_path / "d.exr", np.zeros((1, 3, 4, 4), np.float32))
    assert str(ei.value) == f"{tmp_path / 'd.exr'}: cannot write (is a directory)"
    assert [p.name for p in tmp_path.iterdir()] == ["d.exr"]
    with pytest.raises(FormatError, match="is a directory"):
        read_exr(tmp_path / "d.exr")


# -- plane choices: half-precision uncertainty, plane selection, compression --------------------
from polrig.formats.exr import RESULT_PLANES, result_planes  # noqa: E402
from polrig.solve.reference import ReferenceResult  # noqa: E402


def _result(c=3, h=6, w=5, seed=0) -> ReferenceResult:
    rng = np.random.default_rng(seed)
    m = rng.normal(0, 100, (c, 3, 3, h, w)).astype(np.float32)
    sigma = rng.uniform(0.01, 50, m.shape).astype(np.float32)
    sigma[0, 0, 0, 0, 0] = np.inf
    sigma[0, 0, 1, 0, 0] = 1e6  # above the half range: inf in half precision
    mask = rng.integers(0, 64, (c, h, w)).astype(np.uint8)
    res = rng.uniform(0, 3, (c, h, w)).astype(np.float32)
    return ReferenceResult(m, sigma, res, mask, 2.0, np.ones((c, h, w), np.float32),
                           np.full((c, h, w), 16, np.uint16), sigma_noise=0.5 * sigma)


def _channel_types(path) -> dict[str, str]:
    f = OpenEXR.File(str(path), separate_channels=True)
    return {name: ch.pixels.dtype.name for name, ch in f.channels().items()}


@pytest.mark.parametrize("c", [1, 3])
def test_half_uncertainty_planes_are_half_channels_and_read_back_as_float32(tmp_path, c):
    r = _result(c)
    p = write_mueller_exr(tmp_path / "m.exr", r.mueller,
                          extra=result_planes(r, uncertainty="half"))
    types = _channel_types(p)
    sfx = "Y" if c == 1 else "G"
    assert types[f"M01.{sfx}"] == "float32"
    for name in (f"sigma.M01.{sfx}", f"sigma_noise.M22.{sfx}", f"mask.{sfx}", f"residual.{sfx}"):
        assert types[name] == "float16", name
    back = read_mueller_exr(p)
    np.testing.assert_array_equal(_bits(back.mueller), _bits(r.mueller))
    sig = back.extra[f"sigma.M00.{'Y' if c == 1 else 'R'}"]
    assert sig.dtype == np.float32
    np.testing.assert_array_equal(sig, r.sigma[0, 0, 0].astype(np.float16).astype(np.float32))
    assert np.isinf(sig[0, 0]) and np.isinf(back.extra[f"sigma.M01.{'Y' if c == 1 else 'R'}"][0, 0])
    np.testing.assert_array_equal(back.extra[f"mask.{sfx}"], r.mask[c // 2].astype(np.float32))
    rel = np.abs(back.extra[f"residual.{sfx}"] / r.residual[c // 2] - 1)
    assert rel.max() <= 2 ** -11


def test_plane_selection_writes_exactly_the_chosen_groups(tmp_path):
    r = _result(3)
    full = result_planes(r)
    assert all(a.dtype == np.float32 for a in full.values())
    assert {k.split(".")[0] for k in full} == set(RESULT_PLANES) - {"mueller"}
    assert len(full) == 2 * 27 + 3 + 3
    chosen = result_planes(r, planes=("mueller", "mask"))
    assert set(chosen) == {"mask.R", "mask.G", "mask.B"}
    assert result_planes(r, planes=()) == {}
    p = write_mueller_exr(tmp_path / "m.exr", r.mueller, extra=chosen)
    back = read_mueller_exr(p)  # a file without the uncertainty planes still reads
    assert set(back.extra) == set(chosen)
    np.testing.assert_array_equal(back.mueller, r.mueller)
    with pytest.raises(ValueError, match="unknown EXR plane group.*'sigmas'"):
        result_planes(r, planes=("sigmas",))
    with pytest.raises(ValueError, match="unknown uncertainty precision"):
        result_planes(r, uncertainty="double")


@pytest.mark.parametrize("compression", ["zip", "piz", "none"])
def test_every_compression_round_trips_bit_exact(tmp_path, compression):
    r = _result(3, h=17, w=11, seed=4)
    m = _nasty(np.random.default_rng(2), r.mueller.shape)
    extra = result_planes(r, uncertainty="half")
    p = write_mueller_exr(tmp_path / "m.exr", m, extra=extra, compression=compression)
    back = read_mueller_exr(p)
    np.testing.assert_array_equal(_bits(back.mueller), _bits(m))
    for k, v in extra.items():
        np.testing.assert_array_equal(back.extra[k], v.astype(np.float32))
    with pytest.raises(ValueError, match="unknown EXR compression 'lzma'"):
        write_mueller_exr(tmp_path / "x.exr", m, compression="lzma")
    assert not (tmp_path / "x.exr").exists()


@pytest.mark.parametrize("c,uncertainty", [(1, "float"), (3, "half")])
def test_mueller_rows_are_the_rows_of_the_whole_file(tmp_path, c, uncertainty):
    """A band of rows read from the file alone equals those rows of the whole read, at every
    band boundary (bands clipped at the bottom, empty bands), for float and half channels."""
    rng = np.random.default_rng(c)
    m = _nasty(rng, (c, 3, 3, 37, 11))
    obj = rng.random((37, 11)) > 0.5
    half = {"Mhalf.Y": rng.random((37, 11)).astype(np.float16)}
    p = write_mueller_exr(tmp_path / "m.exr", m, extra={"object_mask": obj, **half},
                          metadata={"pose_deg": 30.0}, compression="zip")
    whole = read_mueller_exr(p)
    with MuellerRows(p) as rows:
        assert rows.shape == m.shape and rows.metadata["pose_deg"] == 30.0
        for r0, r1 in [(0, 16), (16, 32), (32, 48), (5, 6), (36, 37), (10, 10)]:
            band = rows.rows(r0, r1)
            assert band.dtype == np.float32
            assert np.array_equal(_bits(band), _bits(whole.mueller[..., r0:r1, :]))
        assert np.array_equal(rows.plane("object_mask"), whole.extra["object_mask"])
        assert np.array_equal(rows.plane("Mhalf.Y"), whole.extra["Mhalf.Y"])
        assert rows.plane("nothing") is None


def test_mueller_rows_one_line_errors(tmp_path):
    bad = tmp_path / "x.exr"
    bad.write_bytes(b"not an exr file at all")
    with pytest.raises(FormatError, match="not an OpenEXR file"):
        MuellerRows(bad)
    p = write_exr(tmp_path / "s.exr", {f"M00.{k}": np.zeros((4, 4), np.float32) for k in "RGB"})
    with pytest.raises(FormatError, match="missing channels M01.R"):
        MuellerRows(p)
    with pytest.raises(FormatError, match="M00.R/G/B or M00.Y"):
        MuellerRows(write_exr(tmp_path / "t.exr", {"S0.Y": np.zeros((4, 4), np.float32)}))


def test_the_rename_of_a_written_exr_is_made_durable(tmp_path, monkeypatch):
    """After the temporary file is renamed onto the result, its folder is fsync-ed (as
    polrig.atomic's writes do), so a power loss after the write cannot take the rename back."""
    import pathlib

    import numpy as np

    from polrig.formats import exr

    synced = []
    monkeypatch.setattr(exr, "fsync_folder", lambda folder: synced.append((folder, sorted(
        p.name for p in pathlib.Path(folder).iterdir()))))
    out = tmp_path / "m.exr"
    exr.write_exr(out, {"Y": np.zeros((2, 3), np.float32)})
    assert synced == [(tmp_path, ["m.exr"])]  # after the rename: only the final name is there
