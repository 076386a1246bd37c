"""USBTMC framing (USB Test and Measurement Class 1.0, USB-IF 2003), shared by the DC2200
driver.

Bulk-OUT messages start with a 12-byte header: ``MsgID``, ``bTag`` (1..255),
``bTagInverse`` (``~bTag & 0xFF``), reserved 0, then for ``DEV_DEP_MSG_OUT`` (MsgID 1) the
transfer size (``<I``), ``bmTransferAttributes`` (bit 0 = EOM) and 3 reserved bytes; for
``REQUEST_DEV_DEP_MSG_IN`` (MsgID 2) the maximum transfer size (``<I``), attributes (bit 1 =
TermChar enabled), the TermChar and 2 reserved bytes. The device answers on Bulk-IN with
``DEV_DEP_MSG_IN`` (MsgID 2): the same 12-byte header with the actual transfer size and EOM.
Every transfer is padded with zeros to a multiple of 4 bytes (spec section 3.2).
Class control requests (section 4.2.1): INITIATE_CLEAR (5) and CHECK_CLEAR_STATUS (6) clear
both bulk pipes; STATUS_SUCCESS 0x01, STATUS_PENDING 0x02.
"""

from __future__ import annotations

import struct

DEV_DEP_MSG_OUT = 1
REQUEST_DEV_DEP_MSG_IN = 2
DEV_DEP_MSG_IN = 2
INITIATE_CLEAR = 5
CHECK_CLEAR_STATUS = 6
GET_CAPABILITIES = 7
STATUS_SUCCESS = 0x01
STATUS_PENDING = 0x02
INTERFACE_CLASS, INTERFACE_SUBCLASS = 0xFE, 0x03
HEADER_LEN = 12


def pad4(data: bytes) -> bytes:
    return data + b"\0" * (-len(data) % 4)


def dev_dep_msg_out(tag: int, payload: bytes, eom: bool = True) -> bytes:
    header = struct.pack("<BBBBIB3x", DEV_DEP_MSG_OUT, tag, ~tag & 0xFF, 0, len(payload),
                         1 if eom else 0)
    return pad4(header + payload)


def request_dev_dep_msg_in(tag: int, max_size: int) -> bytes:
    return struct.pack("<BBBBIBB2x", REQUEST_DEV_DEP_MSG_IN, tag, ~tag & 0xFF, 0, max_size, 0, 0)


def dev_dep_msg_in(tag: int, payload: bytes, eom: bool = True) -> bytes:
    header = struct.pack("<BBBBIB3x", DEV_DEP_MSG_IN, tag, ~tag & 0xFF, 0, len(payload),
                         1 if eom else 0)
    return pad4(header + payload)


def parse_header(data: bytes) -> tuple[int, int, int, int, int]:
    """``(msg_id, tag, tag_inverse, transfer_size, attributes)`` of a 12-byte header."""
    msg_id, tag, tag_inv, _, size, attrs = struct.unpack("<BBBBIB3x", data[:HEADER_LEN])
    return msg_id, tag, tag_inv, size, attrs
