"""Capture session folders that lose nothing: a ``session.json`` manifest plus checksummed files.

A session is a folder holding everything one capture run produced (schema:
``docs/session-schema.md``). Rules this module enforces:

* Every file is written atomically (temporary file in the same folder, ``fsync``, rename,
  ``fsync`` of the folder: :func:`polrig.atomic.atomic_write_bytes`) and recorded in the
  manifest with its SHA-256 checksum; the manifest itself is rewritten atomically after
  every file, so the manifest on disk always describes files that exist completely.
* A session never overwrites data: :meth:`Session.create` refuses a non-empty folder and
  :meth:`Session.add_file` refuses a path that exists.
* Free disk space is checked against the planned size before a session starts or resumes.
* A capture that did not finish stays ``pending`` (or ``failed`` with a reason);
  :meth:`Session.restart_capture` removes whatever it had written so a resumed session
  re-does it from scratch without duplicating files.
* One writer at a time: a process that writes a session (capture, resume, reconstruct) holds
  an exclusive ``flock`` on ``session.lock`` in the folder (:meth:`Session.lock`); a second
  writer gets :class:`SessionBusy`. Readers (``polrig info``) take no lock.
* The manifest is typed (:mod:`polrig.app.manifest`: one schema version, its plan a
  :class:`polrig.acquisition.plan.CapturePlan`) and checked against its types when it is
  opened (an older version migrated first): a :class:`FormatError` naming the record, never a
  ``KeyError`` later.
* :class:`SignalGuard` turns SIGINT and SIGTERM into :class:`Interrupted` (a
  ``KeyboardInterrupt``) once, and ignores or defers further ones, so the clean-up that
  writes the final manifest is not itself interrupted.

``write_hook`` (a callable ``(path, data) -> None`` run before every write) lets tests
inject write failures such as ``OSError(errno.ENOSPC)`` (a full disk).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import pathlib
import re
import shutil
import signal
import threading
import weakref
from typing import Any, Callable, Iterator

from polrig import __version__
from polrig.acquisition.plan import CapturePlan
from polrig.app import manifest as _schema
from polrig.app.manifest import (  # noqa: F401 (re-exported: the statuses and roles)
    ACQUIRED,
    ACQUISITION_ROLES,
    COMPLETE,
    FAILED,
    INTERRUPTED,
    LIST_ROLES,
    PENDING,
    RUNNING,
    SCHEMA_VERSION,
    ProcessingRecord,
    SESSION_COMPLETE,
    SampleMetadata,
    CaptureRecord,
    RevisionSettings,
    RigRecord,
    SessionManifest,
    default_processing,
    utc_now,
)
from polrig.atomic import atomic_write_bytes
from polrig.errors import FormatError, PolrigError
from polrig.formats import typedjson
from polrig.optics.conventions import CONVENTIONS_VERSION

MANIFEST_NAME = "session.json"
#: Lock file of a session folder: a writer holds an exclusive ``flock`` on it for its whole run
#: (the file stays; its content is the holder's process id, for the error message only).
LOCK_NAME = "session.lock"
#: Where :meth:`Session.set_aside_damaged` moves a capture folder whose raw data is damaged.
DAMAGED_DIR = "damaged"

WriteHook = Callable[[pathlib.Path, bytes], None]


class SessionError(PolrigError):
    """A session folder cannot be used as asked (not enough disk space, inconsistent plan)."""


class SessionBusy(SessionError):
    """Another process is writing the session (it holds the session's lock)."""


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised by :class:`SignalGuard` (and by ``polrig``'s SIGTERM handler)
    as a ``KeyboardInterrupt`` so every Ctrl-C path handles it. ``signum`` is the signal."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def reason(self) -> str:
        """What the session records as the reason it stopped."""
        return interruption_reason(self)


def interruption_reason(exc: BaseException) -> str:
    """``status_reason`` of a session stopped by ``exc`` (a ``KeyboardInterrupt``)."""
    signum = getattr(exc, "signum", signal.SIGINT)
    if signum == signal.SIGINT:
        return "interrupted by the operator (Ctrl-C)"
    return f"terminated by {signal.Signals(signum).name}"


class SignalGuard:
    """Use as ``with SignalGuard() as guard:`` around work that must end in a clean manifest.

    Inside the block (main thread only; elsewhere it does nothing) the first SIGINT or SIGTERM
    raises :class:`Interrupted`; every later one is ignored until the block ends, so the
    clean-up that follows the first is not interrupted by a second (an impatient double
    Ctrl-C). Inside ``with guard.deferred():`` a signal is only recorded and raised when the
    deferred section ends normally (and when the block ends, if still pending). A signal
    whose disposition was "ignore" when the block started stays ignored.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.fired: int | None = None
        self.pending: int | None = None
        self._defer = 0
        self._old: dict[int, Any] = {}

    def __enter__(self) -> "SignalGuard":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                old = signal.getsignal(sig)
                if old is signal.SIG_IGN:
                    continue
                self._old[sig] = old
                signal.signal(sig, self._handler)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        self._old.clear()
        if exc_type is None:
            self._raise_pending()

    def _handler(self, signum: int, frame) -> None:
        if self.fired is not None:
            return  # the first one is being handled: its clean-up must finish
        if self._defer:
            self.pending = self.pending or signum
            return
        self.fired = signum
        raise Interrupted(signum)

    def _raise_pending(self) -> None:
        if self.pending is not None and self.fired is None:
            self.fired, self.pending = self.pending, None
            raise Interrupted(self.fired)

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A section no signal interrupts (writing the final manifest)."""
        self._defer += 1
        try:
            yield
        finally:
            self._defer -= 1
        if not self._defer:
            self._raise_pending()


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike, chunk_bytes: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            h.update(block)
    return h.hexdigest()


def format_bytes(n: float) -> str:
    """Human-readable byte count (``1.5 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n} B"  # pragma: no cover


def check_free_space(folder: str | os.PathLike, required_bytes: int) -> int:
    """Raise :class:`SessionError` unless the file system holding ``folder`` (or its nearest
    existing parent) can be written and has ``required_bytes`` free: a read-only file system
    (a write-protected card), a virtual one (``/proc``) and a folder without write permission
    are each said as such, not as "0 B free". Returns the free byte count."""
    p = pathlib.Path(folder).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    stat = os.statvfs(p) if hasattr(os, "statvfs") else None
    if stat is not None and stat.f_flag & os.ST_RDONLY:  # a write-protected card, a read-only mount
        raise SessionError(f"cannot write the session in {folder}: {p} is on a read-only file "
                           f"system")
    if stat is not None and stat.f_blocks == 0:  # /proc, /sys: no disk behind it
        raise SessionError(f"cannot write the session in {folder}: {p} is on a virtual file "
                           f"system, with no storage behind it")
    if not os.access(p, os.W_OK):
        raise SessionError(f"cannot write the session in {folder}: no permission to write in {p}")
    free = shutil.disk_usage(p).free
    if required_bytes > free:
        raise SessionError(f"not enough disk space for the session in {folder}: it needs about "
                           f"{format_bytes(required_bytes)}, {format_bytes(free)} are free")
    return free


def folder_is_empty(folder: pathlib.Path) -> bool:
    """``folder`` does not exist or holds nothing but a session lock file (left by a session
    whose creation failed after taking the lock) and temporaries of a first manifest that was
    never in place (a crash while the session was being created:
    :func:`is_manifest_temporary`)."""
    folder = pathlib.Path(folder)
    return not folder.exists() or (folder.is_dir() and
                                   all(p.name == LOCK_NAME or is_manifest_temporary(p)
                                       for p in folder.iterdir()))


def is_manifest_temporary(path: pathlib.Path) -> bool:
    """``path`` is a temporary sibling of a session's manifest
    (:func:`polrig.atomic.temporary_sibling` of :data:`MANIFEST_NAME`): a save that a crash
    cut short before its rename, never a manifest."""
    return _MANIFEST_TEMPORARY.fullmatch(pathlib.Path(path).name) is not None


_MANIFEST_TEMPORARY = re.compile(r"\." + re.escape(MANIFEST_NAME) + r"\.[0-9a-f]{12}\.tmp\.json")


class Session:
    """An open session folder and its manifest (``self.manifest``, a
    :class:`polrig.app.manifest.SessionManifest`; :attr:`plan` its plan).

    Create one with :meth:`create` or :meth:`open`; do not build the manifest by hand.
    Paths in the manifest are relative to :attr:`root` and use ``/``.
    """

    def __init__(self, root: pathlib.Path, manifest: SessionManifest,
                 write_hook: WriteHook | None = None):
        self.root = pathlib.Path(root)
        self.manifest = manifest
        #: the schema version of the manifest as it was read from disk (an older one is
        #: migrated in memory; :meth:`save` writes :data:`SCHEMA_VERSION`)
        self.stored_version = SCHEMA_VERSION
        self.write_hook = write_hook
        self._lock_fd: int | None = None
        self._lock_release: Callable[[], Any] | None = None
        #: held while the manifest is changed or saved: a capture's processing (a worker
        #: thread) and the next capture's acquisition write the same manifest
        self.mutex = threading.RLock()

    # -- creation -------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | os.PathLike, *, plan: CapturePlan, rig: RigRecord,
               calibration_id: str, command_line: list[str] | None = None,
               required_bytes: int = 0, write_hook: WriteHook | None = None,
               metadata: SampleMetadata | None = None,
               processing: ProcessingRecord | None = None) -> "Session":
        """Start a new session in ``root`` (created; must not exist or be empty).

        One pending capture is listed per pose of ``plan``. ``rig`` describes the rig
        (:func:`polrig.app.records.rig_record`). ``required_bytes`` is checked against the
        free disk space. ``metadata``: who, why, what (:class:`polrig.app.manifest.SampleMetadata`,
        empty by default). ``processing``: how its captures are processed
        (:class:`polrig.app.manifest.ProcessingRecord`; default ``full`` models and the default
        prior scale). The manifest is checked against its types before anything is written
        (``ValueError`` naming the key).
        """
        root = pathlib.Path(root)
        if root.exists() and not root.is_dir():
            raise FileExistsError(f"{root}: output path exists and is not a folder")
        if not folder_is_empty(root):
            raise _not_empty(root)
        if not isinstance(plan, CapturePlan):
            raise TypeError(f"a session's plan is a CapturePlan, got {type(plan).__name__}")
        check_free_space(root, required_bytes)
        now = utc_now()
        manifest: SessionManifest = {
            "schema_version": SCHEMA_VERSION,
            "software": {"name": "polrig", "version": __version__},
            "conventions_version": CONVENTIONS_VERSION,
            "created": now,
            "updated": now,
            "status": RUNNING,
            "status_reason": None,
            "command_line": list(command_line or []),
            "rig": json.loads(json.dumps(rig)),
            "calibration_id": calibration_id,
            "plan": plan,
            "processing": dict(processing) if processing is not None else default_processing(),
            "metadata": metadata if metadata is not None else SampleMetadata(),
            "planned_bytes": int(required_bytes),
            "hardware_time_s": None,
            "captures": [
                {"index": i, "name": capture_folder_name(i, pose), "pose_deg": float(pose),
                 "status": PENDING, "reason": None, "started": None, "finished": None,
                 "attempts": 0, "files": {}, "score": None, "revisions": {}}
                for i, pose in enumerate(plan.poses_deg)],
            "revisions": [],
            "history": [{"time": now, "event": "created",
                         "command_line": list(command_line or [])}],
        }
        _schema.check_manifest(manifest)  # a programming error, before anything is written
        created = not root.exists()
        root.mkdir(parents=True, exist_ok=True)
        session = cls(root, manifest, write_hook)
        session.lock()  # held until the run ends (Session.unlock) or the object is gone
        try:
            if not folder_is_empty(root):  # another process got here first
                raise _not_empty(root)
            session.save()
        except BaseException:
            if not (root / MANIFEST_NAME).exists():
                with contextlib.suppress(OSError):
                    (root / LOCK_NAME).unlink()
                    if created:
                        root.rmdir()
            session.unlock()
            raise
        return session

    @classmethod
    def open(cls, root: str | os.PathLike, *, write_hook: WriteHook | None = None,
             lock: bool = False) -> "Session":
        """Open an existing session; :class:`FormatError` if ``root`` holds no valid manifest
        (:func:`read_manifest`; a manifest of an older schema version is migrated in memory,
        :attr:`stored_version` says which it was, and the next :meth:`save` writes it in
        this version). ``lock``: open it for writing, taking the session's lock first (:meth:`lock`; :class:`SessionBusy` if another process holds it), so the
        manifest read is the one no other writer changes any more."""
        root = pathlib.Path(root)
        path = root / MANIFEST_NAME
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: no such session folder")
        if not path.is_file():
            raise FormatError(f"{root}: not a polrig session (no {MANIFEST_NAME})")
        session = cls(root, {}, write_hook)
        if lock:
            session.lock()
        try:
            session.manifest, session.stored_version = _read_manifest(path)
        except BaseException:
            session.unlock()
            raise
        return session

    # -- the writer's lock -----------------------------------------------------------------
    def lock(self) -> None:
        """Take the session's exclusive lock (``flock`` on :data:`LOCK_NAME`; no-op if this
        object holds it already). :class:`SessionBusy` (one line, with the holder's process
        id) if another process writes the session. Released by :meth:`unlock`, when this
        object is garbage-collected, or when the process ends (whatever way it ends). Taking
        it removes the temporaries of manifest saves a crash cut short
        (:func:`is_manifest_temporary`)."""
        if self._lock_fd is not None:
            return
        path = self.root / LOCK_NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = ""
            with contextlib.suppress(OSError, ValueError):
                pid = int(os.pread(fd, 32, 0).decode("ascii").strip())
                holder = f" (pid {pid})"
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise SessionBusy(f"{self.root}: the session is being written by another "
                                  f"polrig process{holder}; wait until it ends or stop it, "
                                  f"then try again") from None
            raise
        with contextlib.suppress(OSError):  # who holds it: for the message above only
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._lock_fd = fd
        self._lock_release = weakref.finalize(self, os.close, fd)
        # a save a crash cut short left its temporary (no writer can be writing one now)
        for p in self.root.iterdir():
            if is_manifest_temporary(p):
                with contextlib.suppress(OSError):
                    p.unlink()

    def unlock(self) -> None:
        """Release the lock taken by :meth:`lock` (no-op if not held). The lock file stays
        (removing it would let two processes lock two different files)."""
        if self._lock_release is not None:
            self._lock_release()
        self._lock_fd = self._lock_release = None

    @property
    def locked(self) -> bool:
        """Whether this object holds the session's lock."""
        return self._lock_fd is not None

    # -- manifest -------------------------------------------------------------------------
    def reload(self) -> None:
        """Replace the in-memory manifest by the one on disk (after a failed save the disk
        copy is the consistent one: every file it names exists completely)."""
        with self.mutex:
            self.manifest, self.stored_version = _read_manifest(self.root / MANIFEST_NAME)

    @property
    def captures(self) -> list[CaptureRecord]:
        return self.manifest["captures"]

    @property
    def plan(self) -> CapturePlan:
        """The session's plan, as it was read (or created): the one place it is kept."""
        return self.manifest["plan"]

    def capture(self, index: int) -> CaptureRecord:
        return self.captures[index]

    def states_taken(self, index: int) -> int:
        """How many polarizer states capture ``index`` recorded raw frames of (an adaptive
        pose's: the states its decisions took); 0 before any."""
        return 1 + max((r["state_index"] for r in self.capture(index)["files"].get("raw", [])), default=-1)

    def capture_dir(self, index: int) -> pathlib.Path:
        return self.root / self.capture(index)["name"]

    def save(self) -> None:
        """Rewrite ``session.json`` atomically (goes through ``write_hook`` too)."""
        with self.mutex:
            self.manifest["updated"] = utc_now()
            self._write(self.root / MANIFEST_NAME, _schema.encode_manifest(self.manifest))
            self.stored_version = SCHEMA_VERSION

    def log(self, event: str, **fields: Any) -> None:
        """Append an event to the manifest's ``history`` (saved with the next :meth:`save`)."""
        with self.mutex:
            self.manifest["history"].append({"time": utc_now(), "event": event, **fields})

    def set_status(self, status: str, reason: str | None = None, *, save: bool = True) -> None:
        with self.mutex:
            self.manifest["status"] = status
            self.manifest["status_reason"] = reason
            self.log(f"session {status}", reason=reason)
            if save:
                self.save()

    # -- files ----------------------------------------------------------------------------
    def _write(self, path: pathlib.Path, data: bytes) -> None:
        if self.write_hook is not None:
            self.write_hook(path, data)
        atomic_write_bytes(path, data)

    def relpath(self, path: pathlib.Path) -> str:
        return pathlib.Path(path).relative_to(self.root).as_posix()

    def write_new_file(self, relpath: str, data: bytes) -> dict[str, Any]:
        """Write ``data`` to ``root/relpath`` (never over an existing file); return its
        record ``{"path", "sha256", "bytes"}``. Does not touch the manifest."""
        path = self.root / relpath
        if path.exists():
            raise FileExistsError(f"{path}: refusing to overwrite session data")
        path.parent.mkdir(parents=True, exist_ok=True)
        self._write(path, data)
        return {"path": pathlib.PurePosixPath(relpath).as_posix(), "sha256": sha256_bytes(data),
                "bytes": len(data)}

    def add_file(self, index: int, role: str, relpath: str, data: bytes, *,
                 sidecar: bytes | None = None, revision: str | None = None,
                 **attrs: Any) -> dict[str, Any]:
        """Write one file of capture ``index`` under ``role`` and record it, then save the
        manifest. ``sidecar`` (JSON metadata of a raw frame) is written next to it as
        ``<file>.json`` and recorded in the same entry (``meta_path``, ``meta_sha256``).
        ``revision`` files go to that revision's entry instead of the capture's own.
        ``attrs`` (JSON-compatible) are stored in the entry (state angle, frame index...)."""
        record = self.write_new_file(relpath, data)
        if sidecar is not None:
            side = self.write_new_file(relpath + ".json", sidecar)
            record["meta_path"], record["meta_sha256"] = side["path"], side["sha256"]
        record.update(attrs)
        with self.mutex:
            cap = self.capture(index)
            files = cap["files"] if revision is None else cap["revisions"][revision]["files"]
            if role in LIST_ROLES:
                files.setdefault(role, []).append(record)
            else:
                if role in files:
                    raise FileExistsError(f"capture {index} already has a {role!r} file")
                files[role] = record
            self.save()
        return record

    def iter_file_records(self, capture: dict[str, Any] | None = None
                          ) -> Iterator[tuple[dict[str, Any], str, dict[str, Any]]]:
        """Every ``(capture, role, record)`` of the session (or of one capture), revisions
        included (their role is ``"<revision>/<role>"``). Entries with ``part_of`` (roles
        stored as channels of another role's file) are not files of their own: skipped."""
        caps = self.captures if capture is None else [capture]
        for cap in caps:
            groups = [("", cap["files"])] + [(f"{name}/", rev["files"])
                                             for name, rev in cap["revisions"].items()]
            for prefix, files in groups:
                for role, entry in files.items():
                    for rec in _as_list(entry):
                        if "part_of" in rec:  # a view into another role's file
                            continue
                        yield cap, prefix + role, rec

    def recorded_paths(self, capture: dict[str, Any] | None = None) -> set[str]:
        out: set[str] = set()
        for _, _, rec in self.iter_file_records(capture):
            out.add(rec["path"])
            if "meta_path" in rec:
                out.add(rec["meta_path"])
        return out

    # -- capture life cycle ---------------------------------------------------------------
    def restart_capture(self, index: int) -> None:
        """Prepare capture ``index`` to be captured from scratch: remove its folder (every
        file it wrote, recorded or not), reset its entry to pending, save the manifest.
        Refuses a complete capture."""
        cap = self.capture(index)
        if cap["status"] in (COMPLETE, ACQUIRED):
            raise SessionError(f"capture {index} is {cap['status']}; it is never captured again")
        folder = self.capture_dir(index)
        # forget the records first: the manifest never names a file that is gone
        with self.mutex:
            cap.update(status=PENDING, reason=None, files={}, score=None, revisions={},
                       started=utc_now(), finished=None,
                       attempts=cap["attempts"] + 1)
            cap.pop("adaptive", None)  # an adaptive capture decides again on its new frames
            self.save()
        if folder.exists():
            shutil.rmtree(folder)

    def discard_unrecorded(self, index: int) -> list[str]:
        """Delete files in capture ``index``'s folder that the manifest does not record
        (a file written just before an interruption, temporary files). Returns them."""
        folder = self.capture_dir(index)
        if not folder.exists():
            return []
        keep = self.recorded_paths(self.capture(index))
        removed = []
        for p in sorted(folder.rglob("*")):
            if p.is_file() and self.relpath(p) not in keep:
                p.unlink()
                removed.append(self.relpath(p))
        return removed

    def mark_acquired(self, index: int, reason: str | None = None) -> None:
        """Capture ``index`` has all its raw frames (and truth) recorded; processing them is
        what is left (``reason``: why it is not done, after a failed or interrupted
        processing)."""
        with self.mutex:
            self.capture(index).update(status=ACQUIRED, reason=reason)
            self.save()

    def reset_results(self, index: int) -> list[str]:
        """Forget and delete whatever processing of capture ``index`` recorded (every role
        but :data:`ACQUISITION_ROLES`), so it can be processed again from its raw frames.
        Returns the deleted paths."""
        with self.mutex:
            files = self.capture(index)["files"]
            gone = [role for role in files if role not in ACQUISITION_ROLES]
            paths = [rec["path"] for role in gone
                     for rec in _as_list(files[role])
                     if "part_of" not in rec]
            for role in gone:
                del files[role]
            self.capture(index)["score"] = None
            self.save()
        for rel in paths:
            with contextlib.suppress(FileNotFoundError):
                (self.root / rel).unlink()
        return paths

    def complete_capture(self, index: int, score: dict[str, Any] | None = None) -> None:
        with self.mutex:
            cap = self.capture(index)
            cap.update(status=COMPLETE, reason=None, finished=utc_now(), score=score)
            self.save()

    def fail_capture(self, index: int, reason: str, *, save: bool = True) -> None:
        with self.mutex:
            cap = self.capture(index)
            cap.update(status=FAILED, reason=reason, finished=utc_now())
            if save:
                self.save()

    def next_pending(self) -> list[int]:
        """Indices of the captures that are not complete, in plan order."""
        return [c["index"] for c in self.captures if c["status"] != COMPLETE]

    def acquired(self) -> list[int]:
        """Indices of the captures acquired but not processed, in plan order."""
        return [c["index"] for c in self.captures if c["status"] == ACQUIRED]

    # -- revisions (re-processing) --------------------------------------------------------
    def new_revision(self, settings: dict[str, Any], command_line: list[str] | None = None) -> str:
        """Register a re-processing revision (``rev1``, ``rev2``...) with its ``settings``
        (the fields of :class:`polrig.app.manifest.RevisionSettings` but the name, time and
        command line; ``ValueError`` naming the key if they do not fit) and return its name."""
        name = f"rev{len(self.manifest['revisions']) + 1}"
        entry: RevisionSettings = typedjson.load(RevisionSettings, {
            "name": name, "created": utc_now(), "command_line": list(command_line or []),
            **json.loads(json.dumps(settings))}, context=f"revision {name}: ")
        self.manifest["revisions"].append(entry)
        self.save()
        return name

    def start_revision(self, index: int, revision: str) -> None:
        self.capture(index)["revisions"][revision] = {"status": PENDING, "files": {},
                                                      "score": None, "reason": None}

    # -- checks ---------------------------------------------------------------------------
    def verify(self) -> list[str]:
        """Re-check every recorded file: it exists and its SHA-256 matches. Returns one line
        per problem (empty when the session is intact). Files in capture folders that the
        manifest does not name are reported as well."""
        problems: list[str] = []
        checked: set[str] = set()
        for cap, role, rec in self.iter_file_records():
            for rel, digest in _recorded_pairs(rec):
                if rel in checked:
                    problems.append(f"{rel}: recorded twice")
                    continue
                checked.add(rel)
                problems += self._file_problem(rel, digest, f"capture {cap['index']}, {role}")
        for cap in self.captures:
            folder = self.root / cap["name"]
            if folder.exists():
                for p in sorted(folder.rglob("*")):
                    if p.is_file() and self.relpath(p) not in checked:
                        problems.append(f"{self.relpath(p)}: not recorded in the manifest")
        return problems

    def _file_problem(self, rel: str, digest: str, what: str) -> list[str]:
        """``[]`` if the file ``rel`` exists with SHA-256 ``digest``, else its one line."""
        path = self.root / rel
        if not path.is_file():
            return [f"{rel}: missing ({what})"]
        if sha256_file(path) != digest:
            return [f"{rel}: SHA-256 mismatch ({what})"]
        return []

    def acquisition_problems(self, index: int) -> list[str]:
        """The recorded raw frames, darks and truth of capture ``index``
        (:data:`ACQUISITION_ROLES`, sidecars included) that are missing or changed, one line
        each in :meth:`verify`'s words (empty: they can be processed)."""
        cap = self.capture(index)
        return [line for role in ACQUISITION_ROLES if role in cap["files"]
                for rec in _as_list(cap["files"][role]) if "part_of" not in rec
                for rel, digest in _recorded_pairs(rec)
                for line in self._file_problem(rel, digest, f"capture {index}, {role}")]

    def set_aside_damaged(self, index: int) -> str | None:
        """An acquired capture whose recorded raw data is missing or changed
        (:meth:`acquisition_problems`) cannot be processed, now or ever: its folder is moved,
        whole, to ``damaged/<folder>-<n>`` (nothing deleted), and the capture is pending again,
        so the run acquires it anew at its pose; the history says which files and where they
        went. Returns that reason, or ``None`` (nothing done) when its data verifies."""
        cap = self.capture(index)
        if cap["status"] != ACQUIRED:
            raise SessionError(f"capture {index} is {cap['status']}, not acquired")
        problems = self.acquisition_problems(index)
        if not problems:
            return None
        folder = self.capture_dir(index)
        n = 1
        while (self.root / DAMAGED_DIR / f"{folder.name}-{n}").exists():
            n += 1
        kept = self.root / DAMAGED_DIR / f"{folder.name}-{n}"
        more = f" and {len(problems) - 1} more" if len(problems) > 1 else ""
        reason = (f"its recorded raw data is damaged ({problems[0]}{more}); the capture is "
                  f"acquired again, its old folder kept in {self.relpath(kept)}")
        with self.mutex:  # the records first: the manifest never names a file that is gone
            cap.update(status=PENDING, reason=reason, files={}, score=None, revisions={})
            cap.pop("adaptive", None)
            self.log("capture set aside", capture=index, problems=problems,
                     kept=self.relpath(kept))
            self.save()
        if folder.exists():
            kept.parent.mkdir(exist_ok=True)
            os.replace(folder, kept)
        return reason


def _recorded_pairs(rec: dict[str, Any]) -> list[tuple[str, str]]:
    """A file record's ``(path, sha256)`` pairs: the file, and its sidecar if it has one."""
    pairs = [(rec["path"], rec["sha256"])]
    if "meta_path" in rec:
        pairs.append((rec["meta_path"], rec["meta_sha256"]))
    return pairs


def _as_list(entry: Any) -> list:
    return entry if isinstance(entry, list) else [entry]


def capture_folder_name(index: int, pose_deg: float) -> str:
    """Folder of one capture: ``c003_pose090.0`` (index first, so names sort in plan order)."""
    return f"c{index:03d}_pose{float(pose_deg):05.1f}".replace("-", "m")


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def _not_empty(root: pathlib.Path) -> FileExistsError:
    return FileExistsError(f"{root}: output folder is not empty; choose a new folder, or resume "
                           f"the session in it")


def read_manifest(path: str | os.PathLike) -> SessionManifest:
    """The manifest in ``path`` (``session.json``), migrated from an older schema version if
    it is one and checked against its types (:func:`polrig.app.manifest.parse`);
    :class:`FormatError` (one line naming the file and the record) otherwise."""
    return _read_manifest(path)[0]


def _read_manifest(path: str | os.PathLike) -> tuple[SessionManifest, Any]:
    """:func:`read_manifest` and the schema version the file holds."""
    path = pathlib.Path(path)
    try:
        data = json.loads(path.read_text("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: not valid JSON ({exc})") from None
    return _schema.parse(data, str(path)), data.get("schema_version")
