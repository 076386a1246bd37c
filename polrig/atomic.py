"""Atomic file writes: a file appears under its final name whole or not at all.

A write goes to a hidden temporary sibling in the same folder, is flushed and ``fsync``-ed, then
``os.replace``-d onto the final name, and the folder is ``fsync``-ed so the rename is durable.
Every layer that writes a file the user keeps (raw frames, EXR, manifests, calibration sets,
weights) goes through here; a failed write names the user's file, never the temporary one.
"""

from __future__ import annotations

import os
import pathlib
import uuid

PathLike = str | os.PathLike


def atomic_write_bytes(path: PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: temp file in the same folder, flush + fsync,
    then ``os.replace``. The temporary file is removed if anything fails."""
    path = pathlib.Path(path)
    tmp = temporary_sibling(path)
    try:
        # os.open with 0o666 honours the umask (tempfile.mkstemp would force 0o600)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                     0o666)
    except OSError as exc:
        raise write_error(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise write_error(path, exc) from None
        raise
    fsync_folder(path.parent)


def fsync_folder(folder: PathLike) -> None:
    """``fsync`` ``folder`` so that the renames made in it are durable (silently skipped where
    the platform or file system cannot)."""
    try:
        dfd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


def write_error(path: PathLike, exc: OSError) -> OSError:
    """``exc`` (a failed write of ``path`` or of its temporary sibling) as one line naming
    ``path``, the file the user asked for, never the internal temporary name; same class and
    ``errno`` (a full disk stays a failure while running, a missing folder a bad path)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    if os.path.isdir(path):
        reason = "is a directory"
    try:
        new = type(exc)(f"{path}: cannot write ({reason})")
    except TypeError:  # an OSError subclass with a constructor of its own
        new = OSError(f"{path}: cannot write ({reason})")
    new.errno = exc.errno
    return new


def temporary_sibling(path: PathLike) -> pathlib.Path:
    """A fresh hidden temporary name in the folder of ``path`` (for atomic replacement)."""
    p = pathlib.Path(path)
    return p.with_name(f".{p.name}.{uuid.uuid4().hex[:12]}.tmp{p.suffix}")


def atomic_write_text(path: PathLike, text: str) -> None:
    """UTF-8 text variant of :func:`atomic_write_bytes`."""
    atomic_write_bytes(path, text.encode("utf-8"))
