"""SerialLink (drivers/_serial.py) read deadlines, with real bytes over a pseudo-terminal.

A reply that has started when the read deadline passes must be allowed to finish (inter-byte
timeout); a reply that stops mid-way is still a partial reply (ProtocolError), and silence is
still a DeviceTimeout at the deadline.

The tests that time these rules use a link with a long inter-byte timeout (:data:`IB`, not
the 0.1 s the baud rates give): the peer's bytes are scheduled 0.15 s or more away from the
instants that decide the outcome, and a wrong rule costs a whole :data:`IB` more, so a loaded
machine, which delays threads by tens of milliseconds, cannot turn a pass into a fail or the
reverse.
"""

from __future__ import annotations

import time

import pytest

from polrig.drivers._serial import MIN_INTER_BYTE_S, SerialLink
from polrig.drivers.emulators._pty import PtyEmulator
from polrig.errors import DeviceTimeout, ProtocolError

pytestmark = pytest.mark.timeout(20)
T = 0.3  # read timeout used by these tests
IB = 0.5  # inter-byte timeout of the ``patient_link`` fixture (s)


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


@pytest.fixture
def patient_link(peer):
    """A link whose started replies may pause :data:`IB` between bytes (the baud rate then
    plays no part: a pty has no line rate)."""
    lk = SerialLink(peer.port, baudrate=9600, device="test link", inter_byte_s=IB)
    lk.open()
    yield lk
    lk.close()


def test_inter_byte_timeout_from_baud_rate():
    assert SerialLink("x", baudrate=115200, device="d").inter_byte_s == MIN_INTER_BYTE_S
    assert SerialLink("x", baudrate=300, device="d").inter_byte_s == pytest.approx(64 * 10 / 300)
    assert SerialLink("x", baudrate=9600, device="d", inter_byte_s=0.2).inter_byte_s == 0.2


def test_reply_straddling_the_deadline_completes(peer, patient_link):
    """First byte before the deadline, the rest after it: the whole line (the old loop
    reported ``partial reply b'0'``, the audit's ELL14 failure), returned when it is complete,
    without waiting out an inter-byte timeout after it."""
    peer.play([(T - 0.15, b"0"), (T + 0.15, b"PO00008C00\r\n")])
    t0 = time.monotonic()
    assert patient_link.read_until(b"\r\n", T, what="ELL14 reply") == b"0PO00008C00"
    assert time.monotonic() - t0 < T + 0.15 + IB / 2


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


def test_binary_frame_straddling_the_deadline_completes(peer, patient_link):
    """read_exact (APT frames) gets the same grace."""
    frame = bytes([0x64, 0x04, 14, 0x00, 0x81, 0x50])
    peer.play([(T - 0.15, frame[:2]), (T + 0.15, frame[2:])])
    assert patient_link.read_exact(6, T, what="APT header") == frame


def test_reply_that_stops_midway_is_still_a_partial_reply(peer, patient_link):
    """Bytes that stopped more than the inter-byte timeout before the deadline: the partial
    reply is reported at the deadline, with no grace after it."""
    deadline = 0.8  # the bytes stop 0.75 s before it, more than IB
    peer.play([(0.05, b"0PO00")])
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"ELL14 reply: partial reply b'0PO00' "
                                            r"\(incomplete after 0.8 s\)"):
        patient_link.read_until(b"\r\n", deadline, what="ELL14 reply")
    assert deadline <= time.monotonic() - t0 < deadline + IB / 2


def test_reply_that_stops_midway_after_the_deadline(peer, patient_link):
    """Started before the deadline, then nothing: the error comes one inter-byte timeout
    after the last byte (0.1 + IB s), past the deadline, and does not wait on."""
    peer.play([(0.1, b"0P")])
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"partial reply b'0P' \(incomplete after 0.3 s\)"):
        patient_link.read_until(b"\r\n", T, what="ELL14 reply")
    assert 0.1 + IB - 0.01 <= time.monotonic() - t0 < 0.1 + IB + 0.5
    peer.play([(0.1, b"\x64\x04")])
    with pytest.raises(ProtocolError, match=r"APT header: partial reply"):
        patient_link.read_exact(6, T, what="APT header")


def test_silence_is_a_timeout_at_the_deadline(peer, patient_link):
    """Nothing comes: DeviceTimeout at the deadline, not extended by the inter-byte
    timeout (which would make it T + IB)."""
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"no ELL14 reply within 0.3 s"):
        patient_link.read_until(b"\r\n", T, what="ELL14 reply")
    assert T <= time.monotonic() - t0 < T + IB / 2
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"no APT header within 0.3 s"):
        patient_link.read_exact(6, T, what="APT header")
    assert T <= time.monotonic() - t0 < T + IB / 2


def test_frame_data_after_a_late_header_complete(peer, patient_link):
    """K10CR1: the header of an APT frame came at the very end of the time left; the data
    that follow it continue the same reply (``started=True``), not a new one with no time."""
    peer.play([(0.03, bytes(14))])
    assert patient_link.read_exact(14, 0.0, what="APT data", started=True) == bytes(14)
    with pytest.raises(DeviceTimeout, match="no APT data within 0 s"):  # nothing follows
        patient_link.read_exact(14, 0.0, what="APT data", started=True)


def test_bytes_waiting_at_the_deadline_are_read(peer, link):
    """A reply already in the input buffer arrived in time, even if the read starts with no
    time left (GRBL reads the lines of one answer against one deadline)."""
    peer.play([(0.0, b"[MSG:Caution: Unlocked]\r\nok\r\n")])
    time.sleep(0.1)
    assert link.read_until(b"\n", 0.5) == b"[MSG:Caution: Unlocked]\r"
    assert link.read_until(b"\n", 0.0) == b"ok\r"
    with pytest.raises(DeviceTimeout):
        link.read_until(b"\n", 0.0)
