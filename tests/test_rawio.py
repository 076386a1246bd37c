"""Raw frame files: lossless PNG/TIFF/.npy with JSON sidecars, atomic writes, clear errors."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

from polrig.errors import FormatError
from polrig.hal import Frame, FrameMeta
from polrig.rawio import (atomic_write_bytes, read_mosaic, read_raw, sidecar_path,
                          write_raw)

META = FrameMeta(frame_id=3, timestamp_s=12.5, exposure_us=800.0, gain_db=1.5,
                 pixel_format="PolarizeMono12p", layout="imx250mzr", bit_depth=12,
                 offset_xy=(2, 1), black_level_dn=60.0, extra={"stage_deg": 45.0})


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff", ".npy"])
@pytest.mark.parametrize("dtype,top", [(np.uint16, 65535), (np.uint8, 255)])
def test_round_trip_is_lossless(tmp_path, suffix, dtype, top):
    rng = np.random.default_rng(0)
    raw = rng.integers(0, top + 1, (17, 23)).astype(dtype)
    raw[0, 0], raw[0, 1] = 0, top
    side = write_raw(tmp_path / f"f{suffix}", Frame(raw, META))
    assert side == sidecar_path(tmp_path / f"f{suffix}") and side.name == f"f{suffix}.json"
    back = read_raw(tmp_path / f"f{suffix}")
    assert back.raw.dtype == dtype
    np.testing.assert_array_equal(back.raw, raw)
    assert back.meta == META
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_png_is_a_plain_16_bit_png(tmp_path):
    raw = np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000
    write_raw(tmp_path / "f.png", Frame(raw, META))
    img = cv2.imread(str(tmp_path / "f.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint16
    np.testing.assert_array_equal(img, raw)
    assert json.loads((tmp_path / "f.png.json").read_text())["bit_depth"] == 12


def test_without_sidecar_metadata_is_synthesised(tmp_path):
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((4, 4), np.uint8))
    fr = read_raw(tmp_path / "x.png", layout="imx250myr")
    assert fr.meta.layout == "imx250myr" and fr.meta.bit_depth == 8
    assert fr.meta.pixel_format == "Mono8"


def test_colour_and_bad_files_are_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(FormatError, match="one channel"):
        read_mosaic(tmp_path / "rgb.png")
    np.save(tmp_path / "f.npy", np.zeros((4, 4), np.float32))
    with pytest.raises(FormatError, match="uint8 or uint16"):
        read_mosaic(tmp_path / "f.npy")
    (tmp_path / "junk.png").write_bytes(b"junk")
    with pytest.raises(FormatError, match="junk.png"):
        read_mosaic(tmp_path / "junk.png")
    (tmp_path / "junk.npy").write_bytes(b"junk")
    with pytest.raises(FormatError, match="junk.npy"):
        read_mosaic(tmp_path / "junk.npy")
    (tmp_path / "junk.json").write_text("{}")
    with pytest.raises(FormatError, match="unsupported"):
        read_mosaic(tmp_path / "junk.json")
    with pytest.raises(FileNotFoundError):
        read_mosaic(tmp_path / "none.png")
    cv2.imwrite(str(tmp_path / "m.png"), np.zeros((4, 4), np.uint8))
    (tmp_path / "m.png.json").write_text("{\"frame_id\": 1}")
    with pytest.raises(FormatError, match="m.png.json"):
        read_raw(tmp_path / "m.png")
    with pytest.raises(FormatError):
        write_raw(tmp_path / "f.jpg", Frame(np.zeros((4, 4), np.uint16), META))


def test_atomic_write_replaces_and_leaves_nothing_on_failure(tmp_path, monkeypatch):
    p = tmp_path / "a.bin"
    atomic_write_bytes(p, b"one")
    atomic_write_bytes(p, b"two")
    assert p.read_bytes() == b"two"
    assert oct(p.stat().st_mode & 0o777) == oct(0o666 & ~_umask())

    def boom(*a, **k):
        raise OSError("disk full")
    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_bytes(p, b"three")
    assert p.read_bytes() == b"two"
    assert [q.name for q in tmp_path.iterdir()] == ["a.bin"]


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m
