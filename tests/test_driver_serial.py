"""SerialLink (drivers/_serial.py) read deadlines, with real bytes over a pseudo-terminal.

A reply that has started when the read deadline passes must be allowed to finish (inter-byte
timeout); a reply that stops mid-way is still a partial reply (ProtocolError), and silence is
still a DeviceTimeout at the deadline.
"""

from __future__ import annotations

import time

import pytest

from polrig.drivers._serial import MIN_INTER_BYTE_S, SerialLink
from polrig.drivers.emulators._pty import PtyEmulator
from polrig.errors import DeviceTimeout, ProtocolError

pytestmark = pytest.mark.timeout(20)
T = 0.3  # read timeout used by these tests


class ScriptedPeer(PtyEmulator):
    """The far end of the line: writes given bytes at given times, ignores what it gets."""

    name = "peer"

    def __init__(self):
        super().__init__()
        self._script: list[tuple[float, bytes]] = []

    def play(self, script: list[tuple[float, bytes]]) -> None:
        """``script``: (seconds from now, bytes) pairs."""
        t0 = time.monotonic()
        with self.lock:
            self._script = sorted((t0 + dt, data) for dt, data in script)

    def feed(self, data: bytes, now: float) -> None:
        pass

    def tick(self, now: float) -> None:
        while self._script and self._script[0][0] <= now:
            self.write_raw(self._script.pop(0)[1])


@pytest.fixture
def peer():
    with ScriptedPeer() as p:
        yield p


@pytest.fixture(params=[9600, 115200])
def link(peer, request):
    lk = SerialLink(peer.port, baudrate=request.param, device="test link")
    lk.open()
    yield lk
    lk.close()


def test_inter_byte_timeout_from_baud_rate():
    assert SerialLink("x", baudrate=115200, device="d").inter_byte_s == MIN_INTER_BYTE_S
    assert SerialLink("x", baudrate=300, device="d").inter_byte_s == pytest.approx(64 * 10 / 300)
    assert SerialLink("x", baudrate=9600, device="d", inter_byte_s=0.2).inter_byte_s == 0.2


def test_reply_straddling_the_deadline_completes(peer, link):
    """First byte just before the deadline, the rest shortly after it: the whole line (the
    old loop reported ``partial reply b'0'``, the audit's ELL14 failure)."""
    peer.play([(T - 0.01, b"0"), (T + 0.04, b"PO00008C00\r\n")])
    t0 = time.monotonic()
    assert link.read_until(b"\r\n", T, what="ELL14 reply") == b"0PO00008C00"
    assert time.monotonic() - t0 < T + 0.04 + MIN_INTER_BYTE_S


def test_reply_arriving_at_the_deadline_is_never_cut(peer, link):
    """Whole replies written around the deadline (as the emulators write them): each read
    either times out with nothing or returns the full line, never a partial reply."""
    for k in range(-4, 5):
        link.discard_input()
        peer.play([(0.1 + k * 0.004, b"0PO00000000\r\n")])
        try:
            assert link.read_until(b"\r\n", 0.1, what="ELL14 reply") == b"0PO00000000"
        except DeviceTimeout:
            assert link.read_until(b"\r\n", 0.5, what="ELL14 reply") == b"0PO00000000"


def test_binary_frame_straddling_the_deadline_completes(peer, link):
    """read_exact (APT frames) gets the same grace."""
    frame = bytes([0x64, 0x04, 14, 0x00, 0x81, 0x50])
    peer.play([(T - 0.01, frame[:2]), (T + 0.04, frame[2:])])
    assert link.read_exact(6, T, what="APT header") == frame


def test_reply_that_stops_midway_is_still_a_partial_reply(peer, link):
    peer.play([(0.05, b"0PO00")])
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"ELL14 reply: partial reply b'0PO00' "
                                            r"\(incomplete after 0.3 s\)"):
        link.read_until(b"\r\n", T, what="ELL14 reply")
    assert T <= time.monotonic() - t0 < T + 0.1  # at the deadline: the bytes stopped long ago


def test_reply_that_stops_midway_after_the_deadline(peer, link):
    """Started just before the deadline, then nothing: the error comes one inter-byte
    timeout after the last byte, not later."""
    peer.play([(T - 0.01, b"0P")])
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"partial reply b'0P' \(incomplete after 0.3 s\)"):
        link.read_until(b"\r\n", T, what="ELL14 reply")
    assert time.monotonic() - t0 < T + link.inter_byte_s + 0.1
    peer.play([(T - 0.01, b"\x64\x04")])
    with pytest.raises(ProtocolError, match=r"APT header: partial reply"):
        link.read_exact(6, T, what="APT header")


def test_silence_is_a_timeout_at_the_deadline(peer, link):
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"no ELL14 reply within 0.3 s"):
        link.read_until(b"\r\n", T, what="ELL14 reply")
    with pytest.raises(DeviceTimeout, match=r"no APT header within 0.3 s"):
        link.read_exact(6, T, what="APT header")
    assert time.monotonic() - t0 < 2 * (T + 0.05)  # not extended by the inter-byte timeout


def test_frame_data_after_a_late_header_complete(peer, link):
    """K10CR1: the header of an APT frame came at the very end of the time left; the data
    that follow it continue the same reply (``started=True``), not a new one with no time."""
    peer.play([(0.03, bytes(14))])
    assert link.read_exact(14, 0.0, what="APT data", started=True) == bytes(14)
    with pytest.raises(DeviceTimeout, match="no APT data within 0 s"):  # nothing follows
        link.read_exact(14, 0.0, what="APT data", started=True)


def test_bytes_waiting_at_the_deadline_are_read(peer, link):
    """A reply already in the input buffer arrived in time, even if the read starts with no
    time left (GRBL reads the lines of one answer against one deadline)."""
    peer.play([(0.0, b"[MSG:Caution: Unlocked]\r\nok\r\n")])
    time.sleep(0.1)
    assert link.read_until(b"\n", 0.5) == b"[MSG:Caution: Unlocked]\r"
    assert link.read_until(b"\n", 0.0) == b"ok\r"
    with pytest.raises(DeviceTimeout):
        link.read_until(b"\n", 0.0)
