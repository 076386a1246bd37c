"""Pseudo-terminal plumbing shared by the serial device emulators.

An emulator owns the master side of a pty (``os.openpty``) and serves it from a thread; a
driver opens the slave path (or a symlink to it, like ``/dev/serial/by-id/...``) with
pyserial exactly as it would open ``/dev/ttyUSB0``. The slave is put in raw mode
(``tty.setraw``: no echo, no CR/LF translation, no flow-control characters, 8-bit clean) so
binary APT frames pass unchanged.

Fault injection (counted, consumed in order of use) on everything the device sends:

- ``"no_reply"``: the next reply is dropped;
- ``"garble"``: the next reply is corrupted (subclasses decide how, keeping framing plausible);
- ``"partial"``: only the first half of the next reply is sent;
- ``"error_mid_move"``: the next move stops half way with the device's own error (subclass);
- :meth:`PtyEmulator.disconnect` closes the pty as a pulled cable would; :meth:`reconnect`
  opens a new one and re-points the link.
"""

from __future__ import annotations

import argparse
import collections
import os
import select
import threading
import time
import traceback
import tty


class PtyEmulator:
    """Base class: subclasses implement :meth:`feed` (bytes from the host) and :meth:`tick`."""

    name = "device"
    FAULTS = ("no_reply", "garble", "partial", "error_mid_move")

    def __init__(self, *, link: str | os.PathLike | None = None, speed_factor: float = 1.0):
        self.link = os.fspath(link) if link else None
        self.speed_factor = float(speed_factor)
        self.lock = threading.RLock()
        self._faults: collections.Counter[str] = collections.Counter()
        self._master: int | None = None
        self._slave: int | None = None
        self.pty_path = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.received = bytearray()  # everything the host sent (for tests and debugging)

    # -- life cycle ------------------------------------------------------------------------
    @property
    def port(self) -> str:
        """The path a driver opens: the link if one was asked for, else the pty slave."""
        return self.link or self.pty_path

    @property
    def connected(self) -> bool:
        return self._master is not None

    def start(self) -> "PtyEmulator":
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"{self.name}-emulator",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_pty()
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def disconnect(self) -> None:
        """Pull the cable: the host side sees EIO on its next read or write."""
        with self.lock:
            self._close_pty()
            self.on_disconnect()

    def reconnect(self) -> None:
        """Plug the cable back in (a new pty; the link, if any, points at it)."""
        with self.lock:
            if self._master is None:
                self._open_pty()
                self.on_reconnect()

    def inject(self, fault: str, count: int = 1) -> None:
        if fault not in self.FAULTS:
            raise ValueError(f"unknown fault {fault!r}; known: {', '.join(self.FAULTS)}")
        with self.lock:
            self._faults[fault] += count

    def take_fault(self, fault: str) -> bool:
        """Consume one pending ``fault``; True if there was one."""
        with self.lock:
            if self._faults[fault] > 0:
                self._faults[fault] -= 1
                return True
            return False

    # -- hooks for subclasses --------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> None:
        raise NotImplementedError

    def tick(self, now: float) -> None:
        """Called every few milliseconds: finish motions, emit unsolicited messages."""

    def garble(self, data: bytes) -> bytes:
        return bytes(b ^ 0x5A for b in data)

    def on_disconnect(self) -> None:
        """Device state change when the cable is pulled (default: none)."""

    def on_reconnect(self) -> None:
        """Device state change when plugged back in (default: none)."""

    # -- output ----------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        """Send bytes to the host, applying any pending reply fault."""
        with self.lock:
            if self.take_fault("no_reply"):
                return
            if self.take_fault("garble"):
                data = self.garble(data)
            elif self.take_fault("partial"):
                data = data[: max(1, len(data) // 2)]
            self.write_raw(data)

    def write_raw(self, data: bytes) -> None:
        with self.lock:
            if self._master is None:
                return
            try:
                os.write(self._master, data)
            except OSError:
                pass

    # -- internals -------------------------------------------------------------------------
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self._master, self._slave = master, slave
        self.pty_path = os.ttyname(slave)
        if self.link:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.pty_path, tmp)
            os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def _serve(self) -> None:
        while not self._stop.is_set():
            master = self._master
            data = b""
            if master is not None:
                try:
                    ready, _, _ = select.select([master], [], [], 0.002)
                    if ready:
                        data = os.read(master, 4096)
                except (OSError, ValueError):
                    data = b""
            else:
                time.sleep(0.005)
            now = time.monotonic()
            with self.lock:
                try:
                    if data:
                        self.received += data
                        self.feed(data, now)
                    self.tick(now)
                except Exception:  # an emulator bug must show, not silently kill the device
                    traceback.print_exc()


def run_cli(factory, description: str, argv: list[str] | None = None) -> None:
    """``python -m polrig.drivers.emulators.<device> [--link PATH] [--speed-factor F]``.

    Prints the pty path (and link) and serves until Ctrl-C.
    """
    parser = argparse.ArgumentParser(description=description)
    name = getattr(factory, "name", "device")  # example path as in rig-emulated.toml
    parser.add_argument("--link", help=f"make this symlink to the pty, e.g. /tmp/polrig-{name}")
    parser.add_argument("--speed-factor", type=float, default=1.0,
                        help="multiply the device's motion speed (default 1: real speed)")
    args = parser.parse_args(argv)
    emu = factory(link=args.link, speed_factor=args.speed_factor)
    emu.start()
    print(emu.pty_path + (f" (link {emu.link})" if emu.link else ""), flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        emu.stop()


class LinearMove:
    """A constant-speed move from ``start`` to ``target`` (device units) starting at ``t0``."""

    def __init__(self, start: float, target: float, speed: float, t0: float, kind: str = "move"):
        self.start, self.target, self.t0, self.kind = float(start), float(target), t0, kind
        self.duration = abs(self.target - self.start) / speed if speed > 0 else 0.0

    def position(self, now: float) -> float:
        if self.duration <= 0 or now >= self.t0 + self.duration:
            return self.target
        frac = (now - self.t0) / self.duration
        return self.start + frac * (self.target - self.start)

    def done(self, now: float) -> bool:
        return now >= self.t0 + self.duration

    @property
    def midpoint_time(self) -> float:
        return self.t0 + self.duration / 2
