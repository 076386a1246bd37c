"""Decode (and encode) raw camera buffers of DoFP polarization cameras.

harvesters/GenTL hands over the payload bytes of a frame but cannot decode the vendor
polarization pixel formats, so polrig decodes every supported format here from the bytes.

Two kinds of format:

* **mosaic** formats carry one value per sensor pixel: the decoder returns the raw mosaic
  ``(H, W)`` (``uint8`` for 8-bit formats, ``uint16`` otherwise, values right-aligned, i.e.
  ``0 .. 2**bits - 1``). The polarization mosaic formats (Lucid ``PolarizeMono*``, FLIR
  ``Polarized*``/``BayerRGPolarized*``) have exactly the byte layout of the mono format of the
  same bit depth; only the name tells that the pixels sit behind micro-polarizers.
* **angles** formats (Lucid ``PolarizedAngles_0d_45d_90d_135d_*``) carry, per output pixel
  (one 2x2 polarizer block, so ``Width``/``Height`` are half the sensor's), the four analyzer
  values 0, 45, 90, 135 deg side by side (a 4-channel pixel, like RGBa). The decoder returns
  ``(4, H, W)`` planes in that analyzer order; for the ``_BayerRG*`` variants the planes carry
  an RGGB Bayer mosaic over the block grid. :func:`angle_planes_to_analyzers` turns them into
  analyzer images ``(C, 4, H', W')`` (``docs/conventions.md``).

Packing (all little-endian; 16-bit containers hold the value in the low bits):

* ``*8``: one byte per value; ``*12``/``*16``: one little-endian 16-bit word per value.
* PFNC ``p`` formats (``Mono10p``, ``Mono12p``, ...): a continuous LSB-first bit stream, e.g.
  ``Mono12p``: 2 pixels in 3 bytes, byte0 = p0[7:0], byte1 = p1[3:0] << 4 | p0[11:8],
  byte2 = p1[11:4]; ``Mono10p``: 4 pixels in 5 bytes. No padding at line ends.
* GigE Vision legacy ``Packed`` (``Mono12Packed``): 2 pixels in 3 bytes, byte0 = p0[11:4],
  byte1 = p1[3:0] << 4 | p0[3:0], byte2 = p1[11:4].

Buffers are whole frames without line padding (GenICam ``PaddingX = 0``, the default of the
supported cameras); a buffer of any other length raises :class:`FormatError` naming the format
and the expected and actual sizes.

Sources: GenICam Pixel Format Naming Convention (PFNC) 2.x, section "Packed formats" and the
PFNC.h value list (codes ``0x01080001`` Mono8 ... ``0x010C0047`` Mono12p); GigE Vision 2.x
specification, pixel format appendix (``GVSP_Mono12Packed`` ``0x010C0006``); FLIR Blackfly S
BFS-U3-51S5P technical reference, "ImageFormatControl" (Mono12p vs Mono12Packed byte
diagrams); LUCID Arena SDK ``PFNC.h``/pixel format list (``LUCID_PolarizeMono8`` ``0x81080001``,
``LUCID_PolarizedAngles_0d_45d_90d_135d_Mono8`` ``0x8220000F``, ...) and the Arena
"Polarization, Angles" example (four angle channels side by side per pixel). FLIR Spinnaker
enumerates ``Polarized8/10p/12p/16`` and ``BayerRGPolarized8/10p/12p/16`` by name; their
values are not PFNC codes and are not listed here (``pfnc = None``).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from polrig.errors import FormatError

Buffer = bytes | bytearray | memoryview | np.ndarray


@dataclasses.dataclass(frozen=True)
class PixelFormat:
    """One pixel format: its name, PFNC/vendor code, bit depth and byte packing.

    ``packing`` is ``"u8"``, ``"u16"``, ``"p"`` (PFNC LSB-first bit stream) or ``"packed"``
    (GigE Vision legacy 12-bit). ``values_per_pixel`` is 1 for mosaic formats and 4 for the
    angle formats. ``layout`` is the default mosaic layout name of a sensor delivering it
    (``imx250mzr`` mono, ``imx250myr`` colour).
    """

    name: str
    pfnc: int | None
    bits: int
    packing: str
    values_per_pixel: int = 1
    bayer: bool = False
    polarized: bool = True

    @property
    def kind(self) -> str:
        return "angles" if self.values_per_pixel == 4 else "mosaic"

    @property
    def layout(self) -> str:
        return "imx250myr" if self.bayer else "imx250mzr"

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bits <= 8 else np.uint16)

    def frame_bytes(self, width: int, height: int) -> int:
        """Number of payload bytes of a ``width x height`` frame (pixels as the camera counts
        them: sensor pixels for mosaic formats, 2x2 blocks for angle formats)."""
        n = width * height * self.values_per_pixel
        if self.packing == "u8":
            return n
        if self.packing == "u16":
            return 2 * n
        return -(-n * self.bits // 8)

    def decode(self, data: Buffer, width: int, height: int) -> np.ndarray:
        """Decode a frame buffer: ``(H, W)`` mosaic, or ``(4, H, W)`` angle planes."""
        if width <= 0 or height <= 0:
            raise FormatError(f"{self.name}: frame size {width}x{height} is not positive")
        buf = np.frombuffer(_as_bytes(data), dtype=np.uint8)
        expect = self.frame_bytes(width, height)
        if buf.size != expect:
            raise FormatError(f"{self.name}: a {width}x{height} frame needs {expect} bytes, "
                              f"got {buf.size}")
        n = width * height * self.values_per_pixel
        values = _UNPACK[self.packing](buf, n, self.bits)
        if self.values_per_pixel == 1:
            return values.reshape(height, width)
        return np.ascontiguousarray(values.reshape(height, width, 4).transpose(2, 0, 1))

    def encode(self, image: np.ndarray) -> bytes:
        """Inverse of :meth:`decode` (for tests, simulators and emulated cameras)."""
        a = np.asarray(image)
        if self.values_per_pixel == 4:
            if a.ndim != 3 or a.shape[0] != 4:
                raise FormatError(f"{self.name}: expected (4, H, W) angle planes, got {a.shape}")
            a = a.transpose(1, 2, 0)
        elif a.ndim != 2:
            raise FormatError(f"{self.name}: expected an (H, W) mosaic, got {a.shape}")
        if not np.issubdtype(a.dtype, np.integer):
            raise FormatError(f"{self.name}: values must be integers, got {a.dtype}")
        flat = a.reshape(-1).astype(np.int64)
        if flat.size and (flat.min() < 0 or flat.max() >= (1 << self.bits)):
            raise FormatError(f"{self.name}: values must lie in [0, {(1 << self.bits) - 1}]")
        return _PACK[self.packing](flat, self.bits)


def _as_bytes(data: Buffer) -> memoryview | bytes:
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).view(np.uint8).reshape(-1).data
    return data


def _unpack_u8(buf: np.ndarray, n: int, bits: int) -> np.ndarray:
    return buf.copy()


def _unpack_u16(buf: np.ndarray, n: int, bits: int) -> np.ndarray:
    return buf.view("<u2").astype(np.uint16)


def _groups(bits: int) -> tuple[int, int]:
    """(pixels, bytes) of the smallest whole-byte group of ``bits``-bit values."""
    g = np.lcm(bits, 8)
    return int(g // bits), int(g // 8)


def _unpack_p(buf: np.ndarray, n: int, bits: int) -> np.ndarray:
    px, nb = _groups(bits)
    n_groups = -(-n // px)
    if buf.size < n_groups * nb:
        buf = np.concatenate([buf, np.zeros(n_groups * nb - buf.size, np.uint8)])
    g = buf.reshape(n_groups, nb)
    word = np.zeros(n_groups, np.uint64)
    for k in range(nb):
        word |= g[:, k].astype(np.uint64) << np.uint64(8 * k)
    mask = np.uint64((1 << bits) - 1)
    out = np.empty((n_groups, px), np.uint16)
    for i in range(px):
        out[:, i] = (word >> np.uint64(i * bits)) & mask
    return out.reshape(-1)[:n]


def _pack_p(flat: np.ndarray, bits: int) -> bytes:
    px, nb = _groups(bits)
    n = flat.size
    n_groups = -(-n // px)
    v = np.zeros(n_groups * px, np.uint64)
    v[:n] = flat
    v = v.reshape(n_groups, px)
    word = np.zeros(n_groups, np.uint64)
    for i in range(px):
        word |= v[:, i] << np.uint64(i * bits)
    out = np.empty((n_groups, nb), np.uint8)
    for k in range(nb):
        out[:, k] = (word >> np.uint64(8 * k)) & np.uint64(0xFF)
    return out.reshape(-1)[: -(-n * bits // 8)].tobytes()


def _unpack_packed12(buf: np.ndarray, n: int, bits: int) -> np.ndarray:
    n_groups = -(-n // 2)
    if buf.size < n_groups * 3:
        buf = np.concatenate([buf, np.zeros(n_groups * 3 - buf.size, np.uint8)])
    g = buf.reshape(n_groups, 3).astype(np.uint16)
    out = np.empty((n_groups, 2), np.uint16)
    out[:, 0] = (g[:, 0] << 4) | (g[:, 1] & 0x0F)
    out[:, 1] = (g[:, 2] << 4) | (g[:, 1] >> 4)
    return out.reshape(-1)[:n]


def _pack_packed12(flat: np.ndarray, bits: int) -> bytes:
    n = flat.size
    v = np.zeros(-(-n // 2) * 2, np.int64)
    v[:n] = flat
    p0, p1 = v[0::2], v[1::2]
    out = np.stack([p0 >> 4, ((p1 & 0x0F) << 4) | (p0 & 0x0F), p1 >> 4], axis=1).astype(np.uint8)
    return out.reshape(-1)[: -(-n * 12 // 8)].tobytes()


_UNPACK: dict[str, Callable[[np.ndarray, int, int], np.ndarray]] = {
    "u8": _unpack_u8, "u16": _unpack_u16, "p": _unpack_p, "packed": _unpack_packed12}
_PACK: dict[str, Callable[[np.ndarray, int], bytes]] = {
    "u8": lambda f, b: f.astype(np.uint8).tobytes(),
    "u16": lambda f, b: f.astype("<u2").tobytes(),
    "p": _pack_p, "packed": _pack_packed12}


def _fmt(name: str, pfnc: int | None, bits: int, packing: str, **kw) -> PixelFormat:
    return PixelFormat(name, pfnc, bits, packing, **kw)


_FORMATS = [
    # PFNC / GigE Vision mono formats (layout decided by the camera, not the format)
    _fmt("Mono8", 0x01080001, 8, "u8", polarized=False),
    _fmt("Mono10", 0x01100003, 10, "u16", polarized=False),
    _fmt("Mono10p", 0x010A0046, 10, "p", polarized=False),
    _fmt("Mono12", 0x01100005, 12, "u16", polarized=False),
    _fmt("Mono12p", 0x010C0047, 12, "p", polarized=False),
    _fmt("Mono12Packed", 0x010C0006, 12, "packed", polarized=False),
    _fmt("Mono16", 0x01100007, 16, "u16", polarized=False),
    # LUCID Arena polarization mosaics (same bytes as the mono formats)
    _fmt("PolarizeMono8", 0x81080001, 8, "u8"),
    _fmt("PolarizeMono12p", 0x810C0047, 12, "p"),
    _fmt("PolarizeMono12Packed", 0x810C0006, 12, "packed"),
    _fmt("PolarizeMono12", 0x81100008, 12, "u16"),
    _fmt("PolarizeMono16", 0x81100007, 16, "u16"),
    # LUCID Arena angle formats: 4 analyzer values per 2x2 block
    _fmt("PolarizedAngles_0d_45d_90d_135d_Mono8", 0x8220000F, 8, "u8", values_per_pixel=4),
    _fmt("PolarizedAngles_0d_45d_90d_135d_Mono12p", 0x8230001F, 12, "p", values_per_pixel=4),
    _fmt("PolarizedAngles_0d_45d_90d_135d_Mono16", 0x8240002F, 16, "u16", values_per_pixel=4),
    _fmt("PolarizedAngles_0d_45d_90d_135d_BayerRG8", 0x8220020F, 8, "u8", values_per_pixel=4,
         bayer=True),
    _fmt("PolarizedAngles_0d_45d_90d_135d_BayerRG12p", 0x8230021F, 12, "p", values_per_pixel=4,
         bayer=True),
    # FLIR Spinnaker polarization mosaics
    _fmt("Polarized8", None, 8, "u8"),
    _fmt("Polarized10p", None, 10, "p"),
    _fmt("Polarized12p", None, 12, "p"),
    _fmt("Polarized16", None, 16, "u16"),
    _fmt("BayerRGPolarized8", None, 8, "u8", bayer=True),
    _fmt("BayerRGPolarized10p", None, 10, "p", bayer=True),
    _fmt("BayerRGPolarized12p", None, 12, "p", bayer=True),
    _fmt("BayerRGPolarized16", None, 16, "u16", bayer=True),
]

#: Every supported pixel format by name.
PIXEL_FORMATS: dict[str, PixelFormat] = {f.name: f for f in _FORMATS}
_BY_LOWER = {k.lower(): v for k, v in PIXEL_FORMATS.items()}
_BY_CODE = {f.pfnc: f for f in _FORMATS if f.pfnc is not None}


def get_pixel_format(name_or_code: str | int) -> PixelFormat:
    """Look a format up by name (case-insensitive) or PFNC/vendor code."""
    if isinstance(name_or_code, (int, np.integer)):
        fmt = _BY_CODE.get(int(name_or_code))
        if fmt is None:
            raise FormatError(f"unsupported pixel format code 0x{int(name_or_code):08X}")
        return fmt
    fmt = _BY_LOWER.get(str(name_or_code).lower())
    if fmt is None:
        raise FormatError(f"unsupported pixel format {name_or_code!r}; supported: "
                          f"{', '.join(PIXEL_FORMATS)}")
    return fmt


def decode(data: Buffer, pixel_format: str | int, width: int, height: int) -> np.ndarray:
    """Decode a frame buffer of ``pixel_format`` (see :meth:`PixelFormat.decode`)."""
    return get_pixel_format(pixel_format).decode(data, width, height)


def encode(image: np.ndarray, pixel_format: str | int) -> bytes:
    """Encode a mosaic / angle planes into the bytes of ``pixel_format``."""
    return get_pixel_format(pixel_format).encode(image)


def angle_planes_to_analyzers(planes: np.ndarray, *, bayer: bool) -> np.ndarray:
    """Analyzer images ``(C, 4, H', W')`` float32 from decoded angle-format planes ``(4, H, W)``.

    Mono (``bayer=False``): ``C = 1``, ``H' = H``, ``W' = W`` (the planes as they are).
    Bayer RG (``bayer=True``): the block grid carries an RGGB mosaic (R at (0, 0), G at (0, 1)
    and (1, 0), B at (1, 1)); each 2x2 Bayer cell gives one output pixel with R, the mean of the
    two G, and B (``C = 3``, ``H' = H // 2``, ``W' = W // 2``; an odd last row/column is
    dropped).
    """
    p = np.asarray(planes, dtype=np.float32)
    if p.ndim != 3 or p.shape[0] != 4:
        raise FormatError(f"angle planes must have shape (4, H, W), got {p.shape}")
    if not bayer:
        return p[None].copy()
    h, w = (p.shape[1] // 2) * 2, (p.shape[2] // 2) * 2
    if h == 0 or w == 0:
        raise FormatError(f"Bayer angle planes of shape {p.shape} are smaller than one 2x2 cell")
    p = p[:, :h, :w]
    r = p[:, 0::2, 0::2]
    g = 0.5 * (p[:, 0::2, 1::2] + p[:, 1::2, 0::2])
    b = p[:, 1::2, 1::2]
    return np.stack([r, g, b], axis=0)
