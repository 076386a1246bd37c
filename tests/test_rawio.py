"""Raw frame files: lossless PNG/TIFF/.npy with JSON sidecars, atomic writes, clear errors."""

from __future__ import annotations

import dataclasses
import json
import os

import cv2
import numpy as np
import pytest

from polrig.atomic import atomic_write_bytes
from polrig.errors import FormatError
from polrig.formats.rawio import read_mosaic, read_raw, sidecar_path, write_raw
from polrig.sensor.frame import Frame, FrameMeta

META = FrameMeta(frame_id=3, timestamp_s=12.5, exposure_us=800.0, gain_db=1.5,
                 pixel_format="PolarizeMono12p", layout="imx250mzr", bit_depth=12,
                 offset_xy=(2, 1), black_level_dn=60.0, extra={"stage_deg": 45.0})


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff", ".npy"])
@pytest.mark.parametrize("dtype,top", [(np.uint16, 65535), (np.uint8, 255)])
def test_round_trip_is_lossless(tmp_path, suffix, dtype, top):
    rng = np.random.default_rng(0)
    raw = rng.integers(0, top + 1, (17, 23)).astype(dtype)
    raw[0, 0], raw[0, 1] = 0, top
    bits = 8 if dtype == np.uint8 else 16
    meta = dataclasses.replace(META, bit_depth=bits, pixel_format=f"PolarizeMono{bits}")
    side = write_raw(tmp_path / f"f{suffix}", Frame(raw, meta))
    assert side == sidecar_path(tmp_path / f"f{suffix}") and side.name == f"f{suffix}.json"
    back = read_raw(tmp_path / f"f{suffix}")
    assert back.raw.dtype == dtype
    np.testing.assert_array_equal(back.raw, raw)
    assert back.meta == meta
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


@pytest.mark.parametrize("key,value,needle", [
    ("black_level_dn", None, "black_level_dn: expected a number, got None"),
    ("black_level_dn", "x", "black_level_dn: expected a number, got 'x'"),
    ("black_level_dn", float("nan"), "black_level_dn: must be a finite number in [0, 4095)"),
    ("black_level_dn", 4095, "black_level_dn: must be a finite number in [0, 4095)"),
    ("black_level_dn", -1, "black_level_dn: must be a finite number"),
    ("bit_depth", "twelve", "bit_depth: expected an integer, got 'twelve'"),
    ("bit_depth", 12.0, "bit_depth: expected an integer, got 12.0"),
    ("bit_depth", True, "bit_depth: expected an integer, got True"),
    ("bit_depth", 0, "bit_depth: must be 1..16 bits"),
    ("bit_depth", 40, "bit_depth: must be 1..16 bits"),
    ("frame_id", None, "frame_id: expected an integer"),
    ("exposure_us", "fast", "exposure_us: expected a number"),
    ("pixel_format", 12, "pixel_format: expected a string"),
    ("layout", None, "layout: expected a string"),
    ("offset_xy", [1], "offset_xy: expected two integers >= 0"),
    ("offset_xy", [-2, 0], "offset_xy: expected two integers >= 0"),
    ("host_timestamp", "no", "host_timestamp: expected true or false"),
    ("extra", [1], "extra: expected a JSON object"),
    ("speed", 3, "speed: unknown frame metadata key"),
])
def test_sidecar_fields_are_type_checked_naming_file_and_key(tmp_path, key, value, needle):
    """A sidecar with the wrong type in one field is a one-line FormatError naming the sidecar
    and the key (``null`` black levels used to reach numpy as a TypeError traceback)."""
    raw = np.full((4, 4), 100, np.uint16)
    write_raw(tmp_path / "f.png", Frame(raw, META))
    doc = json.loads((tmp_path / "f.png.json").read_text())
    doc[key] = value
    (tmp_path / "f.png.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError) as ei:
        read_raw(tmp_path / "f.png")
    msg = str(ei.value)
    assert msg.startswith(f"{tmp_path / 'f.png.json'}: ") and needle in msg and "\n" not in msg


def test_missing_sidecar_key_and_nan_exposure(tmp_path):
    raw = np.full((4, 4), 100, np.uint16)
    write_raw(tmp_path / "f.png", Frame(raw, META))
    doc = json.loads((tmp_path / "f.png.json").read_text())
    doc["exposure_us"] = float("nan")  # a camera that does not report it: allowed
    (tmp_path / "f.png.json").write_text(json.dumps(doc))
    assert np.isnan(read_raw(tmp_path / "f.png").meta.exposure_us)
    del doc["layout"]
    (tmp_path / "f.png.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match=r"f\.png\.json: layout: missing"):
        read_raw(tmp_path / "f.png")


@pytest.mark.parametrize("raw,fields,needle", [
    (np.full((4, 4), 200, np.uint8), dict(pixel_format="Mono16", bit_depth=16, black_level_dn=256.0),
     "uint8 data, but pixel_format in f.png.json is 'Mono16' (uint16 data)"),
    (np.full((4, 4), 200, np.uint8), dict(pixel_format="Sensor12", bit_depth=12),
     "uint8 data, but bit_depth in f.png.json is 12 (uint16 data)"),
    (np.full((4, 4), 3000, np.uint16), dict(pixel_format="Mono8", bit_depth=8, black_level_dn=0.0),
     "uint16 data, but pixel_format in f.png.json is 'Mono8' (uint8 data)"),
    (np.full((4, 4), 3000, np.uint16), dict(pixel_format="Sensor8", bit_depth=8, black_level_dn=0.0),
     "uint16 data, but bit_depth in f.png.json is 8 (uint8 data)"),
    (np.full((4, 4), 5000, np.uint16), dict(pixel_format="Mono12", bit_depth=12),
     "values up to 5000, but bit_depth in f.png.json is 12 (values up to 4095)"),
])
def test_a_sidecar_contradicting_the_data_is_refused(tmp_path, raw, fields, needle):
    """8-bit data under a 16-bit sidecar (or the reverse) used to be read, and processed with
    every pixel saturated or below the black level."""
    meta = dataclasses.replace(META, **fields)
    write_raw(tmp_path / "f.png", Frame(raw, meta))
    with pytest.raises(FormatError) as ei:
        read_raw(tmp_path / "f.png")
    msg = str(ei.value)
    assert msg.startswith(f"{tmp_path / 'f.png'}: the file ") and needle in msg and "\n" not in msg


def test_a_folder_is_not_a_raw_frame(tmp_path):
    (tmp_path / "adir.png").mkdir()
    with pytest.raises(FormatError, match=r"adir\.png: is a directory"):
        read_raw(tmp_path / "adir.png")


def test_atomic_write_errors_name_the_file_not_the_temporary(tmp_path):
    (tmp_path / "d.bin").mkdir()
    with pytest.raises(OSError) as ei:
        atomic_write_bytes(tmp_path / "d.bin", b"x")
    assert str(ei.value) == f"{tmp_path / 'd.bin'}: cannot write (is a directory)"
    with pytest.raises(FileNotFoundError, match="nowhere"):
        atomic_write_bytes(tmp_path / "nowhere" / "f.bin", b"x")
    assert [p.name for p in tmp_path.iterdir()] == ["d.bin"]
