"""Thorlabs APT binary protocol: message ids and frame packing (for the K10CR1 driver).

Source: Thorlabs "APT Communications Protocol" (issue 20+), sections 2 (message header),
HW_* generic messages and MOT_* motor messages; cross-checked with pylablib
``devices/Thorlabs/kinesis.py``. A frame is a 6-byte little-endian header
``<H message id> <B param1> <B param2> <B dest> <B source>``; when a data packet follows,
bytes 2-3 are its length (``<H``) and ``dest`` has bit 7 set. The host is ``0x01``; a
single-channel USB controller such as the K10CR1 is the generic USB unit ``0x50``.
"""

from __future__ import annotations

import dataclasses
import struct

HOST = 0x01
USB_UNIT = 0x50

HW_REQ_INFO = 0x0005
HW_GET_INFO = 0x0006
HW_START_UPDATEMSGS = 0x0011
HW_STOP_UPDATEMSGS = 0x0012
HW_RESPONSE = 0x0080
HW_RICHRESPONSE = 0x0081
MOD_IDENTIFY = 0x0223
MOD_SET_CHANENABLESTATE = 0x0210
MOT_SET_VELPARAMS = 0x0413
MOT_REQ_VELPARAMS = 0x0414
MOT_GET_VELPARAMS = 0x0415
MOT_REQ_POSCOUNTER = 0x0411
MOT_GET_POSCOUNTER = 0x0412
MOT_REQ_STATUSBITS = 0x0429
MOT_GET_STATUSBITS = 0x042A
MOT_MOVE_HOME = 0x0443
MOT_MOVE_HOMED = 0x0444
MOT_MOVE_RELATIVE = 0x0448
MOT_MOVE_ABSOLUTE = 0x0453
MOT_MOVE_COMPLETED = 0x0464
MOT_MOVE_STOP = 0x0465
MOT_MOVE_STOPPED = 0x0466
MOT_GET_STATUSUPDATE = 0x0481
MOT_ACK_DCSTATUSUPDATE = 0x0492

#: data-packet length of every message the host may receive (None: header only)
REPLY_DATA_LEN: dict[int, int | None] = {
    HW_GET_INFO: 84, HW_RESPONSE: None, HW_RICHRESPONSE: 68, MOT_GET_POSCOUNTER: 6,
    MOT_GET_VELPARAMS: 14,
    MOT_GET_STATUSBITS: 6, MOT_MOVE_HOMED: None, MOT_MOVE_COMPLETED: 14,
    MOT_MOVE_STOPPED: 14, MOT_GET_STATUSUPDATE: 14,
}

# status bits of MOT_GET_STATUSBITS (APT protocol, "status bits" table for stepper motors)
STATUS_MOVING_REV = 1 << 4
STATUS_MOVING_FWD = 1 << 5
STATUS_HOMING = 1 << 9
STATUS_HOMED = 1 << 10
STATUS_MOTION_ERROR = 1 << 14
STATUS_ENABLED = 1 << 31
STATUS_MOVING = STATUS_MOVING_REV | STATUS_MOVING_FWD | STATUS_HOMING

#: Velocity parameters (``MOT_SET/REQ/GET_VELPARAMS``, data ``<H channel> <i minimum velocity>
#: <i acceleration> <i maximum velocity>``, 14 bytes) are in the controller's own units. For
#: the Trinamic-based stepper controllers (K10CR1, KST101, BSC20x, ...) the APT protocol's
#: "conversion between position, velocity and acceleration" section gives
#: velocity = micro-steps/s * 53.68 and acceleration = micro-steps/s^2 / 90.9 (QMI's K10CR1
#: driver, tested on the device, uses the same: 7329109 per deg/s and 1502 per deg/s^2 at
#: 409600/3 micro-steps per degree).
VELOCITY_PER_STEP_S = 53.68
ACCELERATION_STEPS_S2_PER_UNIT = 90.9
VELPARAMS_FORMAT = "<Hiii"


def velocity_from_apt(value: int, steps_per_unit: float) -> float:
    """APT velocity units -> real units per second (``steps_per_unit`` micro-steps each)."""
    return value / VELOCITY_PER_STEP_S / steps_per_unit


def acceleration_from_apt(value: int, steps_per_unit: float) -> float:
    """APT acceleration units -> real units per second squared."""
    return value * ACCELERATION_STEPS_S2_PER_UNIT / steps_per_unit


def velocity_to_apt(units_s: float, steps_per_unit: float) -> int:
    return round(units_s * steps_per_unit * VELOCITY_PER_STEP_S)


def acceleration_to_apt(units_s2: float, steps_per_unit: float) -> int:
    return round(units_s2 * steps_per_unit / ACCELERATION_STEPS_S2_PER_UNIT)


@dataclasses.dataclass(frozen=True)
class AptMessage:
    msg_id: int
    param1: int = 0
    param2: int = 0
    data: bytes | None = None
    dest: int = USB_UNIT
    source: int = HOST

    def pack(self) -> bytes:
        if self.data is None:
            return struct.pack("<HBBBB", self.msg_id, self.param1, self.param2, self.dest,
                               self.source)
        return struct.pack("<HHBB", self.msg_id, len(self.data), self.dest | 0x80,
                           self.source) + self.data


def unpack_header(header: bytes) -> tuple[int, int, int, int, int, bool]:
    """``(msg_id, param1, param2, dest, source, has_data)``; for data frames param1 and
    param2 together are the data length (``param1 | param2 << 8``)."""
    msg_id, p1, p2, dest, source = struct.unpack("<HBBBB", header)
    return msg_id, p1, p2, dest & 0x7F, source, bool(dest & 0x80)
