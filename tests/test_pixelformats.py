"""Pixel format decoding: byte layouts from the PFNC / GigE Vision documents, round trips."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.errors import FormatError
from polrig.sensor import pixelformats as pf


def test_mono12p_byte_layout_matches_pfnc():
    # p0 = 0xABC, p1 = 0x123 -> LSB-first stream: 0xBC, (0x3 << 4) | 0xA, 0x12
    data = bytes([0xBC, 0x3A, 0x12])
    np.testing.assert_array_equal(pf.decode(data, "Mono12p", 2, 1), [[0xABC, 0x123]])
    assert pf.encode(np.array([[0xABC, 0x123]], np.uint16), "Mono12p") == data


def test_mono12packed_byte_layout_matches_gige_vision():
    # byte0 = p0[11:4], byte1 = p1[3:0] << 4 | p0[3:0], byte2 = p1[11:4]
    data = bytes([0xAB, 0x3C, 0x12])
    np.testing.assert_array_equal(pf.decode(data, "Mono12Packed", 2, 1), [[0xABC, 0x123]])
    assert pf.encode(np.array([[0xABC, 0x123]], np.uint16), "Mono12Packed") == data


def test_mono10p_byte_layout_matches_pfnc():
    vals = [0x3FF, 0x001, 0x200, 0x155]
    word = sum(v << (10 * i) for i, v in enumerate(vals))
    data = word.to_bytes(5, "little")
    np.testing.assert_array_equal(pf.decode(data, "Mono10p", 4, 1), [vals])


def test_mono16_is_little_endian():
    np.testing.assert_array_equal(pf.decode(b"\x34\x12\xff\x0f", "Mono16", 2, 1),
                                  [[0x1234, 0x0FFF]])


def test_polarization_formats_share_the_mono_byte_layout():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 4096, (6, 10), dtype=np.uint16)
    for mono, pol in [("Mono12p", "PolarizeMono12p"), ("Mono12p", "Polarized12p"),
                      ("Mono12Packed", "PolarizeMono12Packed"), ("Mono16", "BayerRGPolarized16"),
                      ("Mono10p", "Polarized10p")]:
        src = img >> (12 - pf.get_pixel_format(mono).bits) if "10" in mono else img
        assert pf.encode(src, mono) == pf.encode(src, pol)


@pytest.mark.parametrize("name", list(pf.PIXEL_FORMATS))
def test_round_trip_every_format(name):
    fmt = pf.get_pixel_format(name)
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    h, w = 6, 7  # odd pixel count exercises partial packing groups
    shape = (4, h, w) if fmt.kind == "angles" else (h, w)
    img = rng.integers(0, 1 << fmt.bits, shape).astype(fmt.dtype)
    img.flat[0] = (1 << fmt.bits) - 1  # full scale
    data = fmt.encode(img)
    assert len(data) == fmt.frame_bytes(w, h)
    back = fmt.decode(data, w, h)
    assert back.dtype == fmt.dtype
    np.testing.assert_array_equal(back, img)


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(list(pf.PIXEL_FORMATS)), st.integers(1, 9), st.integers(1, 9),
       st.integers(0, 2**31 - 1))
def test_round_trip_property(name, w, h, seed):
    fmt = pf.get_pixel_format(name)
    shape = (4, h, w) if fmt.kind == "angles" else (h, w)
    img = np.random.default_rng(seed).integers(0, 1 << fmt.bits, shape).astype(fmt.dtype)
    np.testing.assert_array_equal(fmt.decode(fmt.encode(img), w, h), img)


@pytest.mark.parametrize("name", ["Mono8", "Mono12p", "Mono12Packed", "PolarizeMono16",
                                  "PolarizedAngles_0d_45d_90d_135d_Mono12p"])
def test_bad_length_names_format_and_sizes(name):
    fmt = pf.get_pixel_format(name)
    need = fmt.frame_bytes(8, 4)
    with pytest.raises(FormatError) as e:
        fmt.decode(bytes(need - 1), 8, 4)
    msg = str(e.value)
    assert name in msg and str(need) in msg and str(need - 1) in msg and "\n" not in msg


def test_unknown_format_and_code():
    with pytest.raises(FormatError, match="RGB8"):
        pf.get_pixel_format("RGB8")
    with pytest.raises(FormatError, match="0x12345678"):
        pf.get_pixel_format(0x12345678)
    assert pf.get_pixel_format(0x810C0047).name == "PolarizeMono12p"
    assert pf.get_pixel_format("mono12P").name == "Mono12p"


def test_encode_rejects_out_of_range():
    with pytest.raises(FormatError):
        pf.encode(np.array([[4096]], np.uint16), "Mono12p")


def test_angle_planes_mono_and_bayer():
    rng = np.random.default_rng(3)
    planes = rng.integers(0, 256, (4, 4, 6), dtype=np.uint8)
    data = pf.encode(planes, "PolarizedAngles_0d_45d_90d_135d_Mono8")
    # four angle values side by side per pixel
    assert data[:4] == bytes(planes[:, 0, 0])
    a = pf.angle_planes_to_analyzers(pf.decode(data, "PolarizedAngles_0d_45d_90d_135d_Mono8",
                                               6, 4), bayer=False)
    assert a.shape == (1, 4, 4, 6)
    np.testing.assert_array_equal(a[0], planes)
    b = pf.angle_planes_to_analyzers(planes, bayer=True)
    assert b.shape == (3, 4, 2, 3)
    np.testing.assert_array_equal(b[0], planes[:, 0::2, 0::2])
    np.testing.assert_allclose(b[1], (planes[:, 0::2, 1::2] + planes[:, 1::2, 0::2].astype(float)) / 2)
    np.testing.assert_array_equal(b[2], planes[:, 1::2, 1::2])
