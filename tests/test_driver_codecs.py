"""Property tests of the drivers' pure encodings: angle <-> device units, APT and USBTMC
frames (round trips over the whole value ranges, including extremes)."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from polrig.drivers import apt, usbtmc
from polrig.drivers.ell14 import Ell14Stage
from polrig.drivers.k10cr1 import STEPS_PER_DEG

angles = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)


@given(angles, st.floats(min_value=-360, max_value=360, allow_nan=False))
def test_ell14_angle_round_trip_within_half_a_pulse(angle_deg, zero_deg):
    stage = Ell14Stage("/dev/null", zero_offset_deg=zero_deg)
    stage.pulses_per_deg = 143360 / 360
    pulses = stage._to_pulses(angle_deg)
    assert 0 <= pulses < 143360
    back = stage._to_deg(pulses)
    err = (back - angle_deg + 180.0) % 360.0 - 180.0
    assert abs(err) <= 0.5 / stage.pulses_per_deg + 1e-9
    assert 0.0 <= back < 360.0


@given(st.integers(min_value=-2**31, max_value=2**31 - 1))
def test_ell14_hex_is_32bit_twos_complement(value):
    assert Ell14Stage._signed(f"{value % 2**32:08X}") == value


@given(st.integers(0, 0xFFFF), st.integers(0, 255), st.integers(0, 255))
def test_apt_header_only_round_trip(msg_id, p1, p2):
    raw = apt.AptMessage(msg_id, p1, p2).pack()
    assert len(raw) == 6
    assert apt.unpack_header(raw) == (msg_id, p1, p2, apt.USB_UNIT, apt.HOST, False)


@given(st.integers(0, 0xFFFF), st.binary(min_size=1, max_size=255))
def test_apt_data_frame_round_trip(msg_id, data):
    raw = apt.AptMessage(msg_id, data=data).pack()
    mid, p1, p2, dest, src, has_data = apt.unpack_header(raw[:6])
    assert (mid, p1 | p2 << 8, dest, src, has_data) == (msg_id, len(data), apt.USB_UNIT,
                                                       apt.HOST, True)
    assert raw[4] == apt.USB_UNIT | 0x80 and raw[6:] == data


@given(st.floats(min_value=0, max_value=360, exclude_max=True))
def test_k10cr1_steps_resolution(angle_deg):
    steps = round(angle_deg * STEPS_PER_DEG)
    assert abs(steps / STEPS_PER_DEG - angle_deg) <= 0.5 / STEPS_PER_DEG
    struct.pack("<Hi", 1, steps)  # fits the MOT_MOVE_ABSOLUTE int32 field


@given(st.integers(1, 255), st.binary(max_size=300), st.booleans())
def test_usbtmc_frames(tag, payload, eom):
    for frame, msg_id in ((usbtmc.dev_dep_msg_out(tag, payload, eom), usbtmc.DEV_DEP_MSG_OUT),
                          (usbtmc.dev_dep_msg_in(tag, payload, eom), usbtmc.DEV_DEP_MSG_IN)):
        assert len(frame) % 4 == 0 and len(frame) - 12 - len(payload) < 4
        assert usbtmc.parse_header(frame) == (msg_id, tag, ~tag & 0xFF, len(payload), int(eom))
        assert frame[12:12 + len(payload)] == payload
    req = usbtmc.request_dev_dep_msg_in(tag, 1024)
    assert len(req) == 12 and usbtmc.parse_header(req)[:4] == (2, tag, ~tag & 0xFF, 1024)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_angles_rejected_before_any_io(bad):
    stage = Ell14Stage("/dev/null")
    with pytest.raises(ValueError, match="finite"):
        stage.move_to(bad)
