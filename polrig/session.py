"""Capture session folders that lose nothing: a ``session.json`` manifest plus checksummed files.

A session is a folder holding everything one capture run produced (schema:
``docs/session-schema.md``). Rules this module enforces:

* Every file is written atomically (temporary file in the same folder, ``fsync``, rename,
  ``fsync`` of the folder: :func:`polrig.rawio.atomic_write_bytes`) and recorded in the
  manifest with its SHA-256 checksum; the manifest itself is rewritten atomically after
  every file, so the manifest on disk always describes files that exist completely.
* A session never overwrites data: :meth:`Session.create` refuses a non-empty folder and
  :meth:`Session.add_file` refuses a path that exists.
* Free disk space is checked against the planned size before a session starts or resumes.
* A capture that did not finish stays ``pending`` (or ``failed`` with a reason);
  :meth:`Session.restart_capture` removes whatever it had written so a resumed session
  re-does it from scratch without duplicating files.

``write_hook`` (a callable ``(path, data) -> None`` run before every write) lets tests
inject write failures such as ``OSError(errno.ENOSPC)`` (a full disk).
"""

from __future__ import annotations

import copy
import datetime as _dt
import errno
import hashlib
import json
import os
import pathlib
import shutil
from typing import Any, Callable, Iterator

from polrig import __version__
from polrig.conventions import CONVENTIONS_VERSION
from polrig.errors import FormatError, PolrigError
from polrig.rawio import atomic_write_bytes

SCHEMA_VERSION = 1
MANIFEST_NAME = "session.json"

# capture status
PENDING, COMPLETE, FAILED = "pending", "complete", "failed"
# session status
RUNNING, SESSION_COMPLETE, INTERRUPTED = "running", "complete", "interrupted"

#: Roles whose manifest entry is a list of files (one per frame); every other role is one file.
LIST_ROLES = ("raw", "dark")

WriteHook = Callable[[pathlib.Path, bytes], None]


class SessionError(PolrigError):
    """A session folder cannot be used as asked (not enough disk space, inconsistent plan)."""


def utc_now() -> str:
    """Current UTC time as an ISO 8601 string with a ``Z`` suffix (second resolution)."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat().replace(
        "+00:00", "Z")


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
    existing parent) has ``required_bytes`` free. Returns the free byte count."""
    p = pathlib.Path(folder).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    free = shutil.disk_usage(p).free
    if required_bytes > free:
        raise SessionError(f"not enough disk space for the session in {folder}: it needs about "
                           f"{format_bytes(required_bytes)}, {format_bytes(free)} are free")
    return free


def folder_is_empty(folder: pathlib.Path) -> bool:
    return not folder.exists() or (folder.is_dir() and not any(folder.iterdir()))


class Session:
    """An open session folder and its manifest (a JSON-compatible dict, ``self.manifest``).

    Create one with :meth:`create` or :meth:`open`; do not build the manifest by hand.
    Paths in the manifest are relative to :attr:`root` and use ``/``.
    """

    def __init__(self, root: pathlib.Path, manifest: dict[str, Any],
                 write_hook: WriteHook | None = None):
        self.root = pathlib.Path(root)
        self.manifest = manifest
        self.write_hook = write_hook

    # -- creation -------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | os.PathLike, *, plan: dict[str, Any], rig: dict[str, Any],
               calibration_id: str, command_line: list[str] | None = None,
               required_bytes: int = 0, write_hook: WriteHook | None = None) -> "Session":
        """Start a new session in ``root`` (created; must not exist or be empty).

        ``plan`` must hold ``poses_deg`` and ``mode`` (plus whatever else the capture plan
        records); one pending capture is listed per pose. ``rig`` describes the rig
        (config, devices). ``required_bytes`` is checked against the free disk space.
        """
        root = pathlib.Path(root)
        if root.exists() and not root.is_dir():
            raise FileExistsError(f"{root}: output path exists and is not a folder")
        if not folder_is_empty(root):
            raise FileExistsError(f"{root}: output folder is not empty; pass --resume to "
                                  f"continue the session in it, or choose a new folder")
        if "poses_deg" not in plan or "mode" not in plan:
            raise ValueError("a session plan needs 'poses_deg' and 'mode'")
        check_free_space(root, required_bytes)
        now = utc_now()
        manifest: dict[str, Any] = {
            "schema_version": SCHEMA_VERSION,
            "software": {"name": "polrig", "version": __version__},
            "conventions_version": CONVENTIONS_VERSION,
            "created": now,
            "updated": now,
            "status": RUNNING,
            "status_reason": None,
            "command_line": list(command_line or []),
            "rig": copy.deepcopy(rig),
            "calibration_id": calibration_id,
            "plan": copy.deepcopy(plan),
            "planned_bytes": int(required_bytes),
            "captures": [
                {"index": i, "name": capture_folder_name(i, pose), "pose_deg": float(pose),
                 "mode": plan["mode"], "status": PENDING, "reason": None, "started": None,
                 "finished": None, "attempts": 0, "files": {}, "score": None,
                 "revisions": {}}
                for i, pose in enumerate(plan["poses_deg"])],
            "revisions": [],
            "history": [{"time": now, "event": "created",
                         "command_line": list(command_line or [])}],
        }
        root.mkdir(parents=True, exist_ok=True)
        session = cls(root, manifest, write_hook)
        session.save()
        return session

    @classmethod
    def open(cls, root: str | os.PathLike, *, write_hook: WriteHook | None = None) -> "Session":
        """Open an existing session; :class:`FormatError` if ``root`` holds no valid manifest."""
        root = pathlib.Path(root)
        path = root / MANIFEST_NAME
        if not root.is_dir():
            raise FileNotFoundError(f"{root}: no such session folder")
        if not path.is_file():
            raise FormatError(f"{root}: not a polrig session (no {MANIFEST_NAME})")
        try:
            manifest = json.loads(path.read_text("utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise FormatError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(manifest, dict) or "captures" not in manifest:
            raise FormatError(f"{path}: not a polrig session manifest")
        version = manifest.get("schema_version")
        if version != SCHEMA_VERSION:
            raise FormatError(f"{path}: session schema version {version!r}, this polrig "
                              f"reads version {SCHEMA_VERSION}")
        return cls(root, manifest, write_hook)

    # -- manifest -------------------------------------------------------------------------
    def reload(self) -> None:
        """Replace the in-memory manifest by the one on disk (after a failed save the disk
        copy is the consistent one: every file it names exists completely)."""
        self.manifest = Session.open(self.root).manifest

    @property
    def captures(self) -> list[dict[str, Any]]:
        return self.manifest["captures"]

    @property
    def plan(self) -> dict[str, Any]:
        return self.manifest["plan"]

    def capture(self, index: int) -> dict[str, Any]:
        return self.captures[index]

    def capture_dir(self, index: int) -> pathlib.Path:
        return self.root / self.capture(index)["name"]

    def save(self) -> None:
        """Rewrite ``session.json`` atomically (goes through ``write_hook`` too)."""
        self.manifest["updated"] = utc_now()
        data = (json.dumps(self.manifest, indent=1, sort_keys=False) + "\n").encode("utf-8")
        self._write(self.root / MANIFEST_NAME, data)

    def log(self, event: str, **fields: Any) -> None:
        """Append an event to the manifest's ``history`` (saved with the next :meth:`save`)."""
        self.manifest.setdefault("history", []).append({"time": utc_now(), "event": event,
                                                        **fields})

    def set_status(self, status: str, reason: str | None = None, *, save: bool = True) -> None:
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
                                             for name, rev in cap.get("revisions", {}).items()]
            for prefix, files in groups:
                for role, entry in files.items():
                    for rec in entry if isinstance(entry, list) else [entry]:
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
        if cap["status"] == COMPLETE:
            raise SessionError(f"capture {index} is complete; it is never captured again")
        folder = self.capture_dir(index)
        # forget the records first: the manifest never names a file that is gone
        cap.update(status=PENDING, reason=None, files={}, score=None, revisions={},
                   started=utc_now(), finished=None, attempts=int(cap.get("attempts", 0)) + 1)
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

    def complete_capture(self, index: int, score: dict[str, Any] | None = None) -> None:
        cap = self.capture(index)
        cap.update(status=COMPLETE, reason=None, finished=utc_now(), score=score)
        self.save()

    def fail_capture(self, index: int, reason: str, *, save: bool = True) -> None:
        cap = self.capture(index)
        cap.update(status=FAILED, reason=reason, finished=utc_now())
        if save:
            self.save()

    def next_pending(self) -> list[int]:
        """Indices of the captures that are not complete, in plan order."""
        return [c["index"] for c in self.captures if c["status"] != COMPLETE]

    # -- revisions (re-processing) --------------------------------------------------------
    def new_revision(self, settings: dict[str, Any], command_line: list[str] | None = None) -> str:
        """Register a re-processing revision (``rev1``, ``rev2``...) and return its name."""
        n = len(self.manifest.setdefault("revisions", [])) + 1
        name = f"rev{n}"
        self.manifest["revisions"].append({"name": name, "created": utc_now(),
                                           "command_line": list(command_line or []),
                                           **copy.deepcopy(settings)})
        self.save()
        return name

    def start_revision(self, index: int, revision: str) -> None:
        cap = self.capture(index)
        cap.setdefault("revisions", {})[revision] = {"status": PENDING, "files": {},
                                                    "score": None}

    # -- checks ---------------------------------------------------------------------------
    def verify(self) -> list[str]:
        """Re-check every recorded file: it exists and its SHA-256 matches. Returns one line
        per problem (empty when the session is intact). Files in capture folders that the
        manifest does not name are reported as well."""
        problems: list[str] = []
        checked: set[str] = set()
        for cap, role, rec in self.iter_file_records():
            pairs = [(rec["path"], rec["sha256"])]
            if "meta_path" in rec:
                pairs.append((rec["meta_path"], rec["meta_sha256"]))
            for rel, digest in pairs:
                if rel in checked:
                    problems.append(f"{rel}: recorded twice")
                    continue
                checked.add(rel)
                path = self.root / rel
                if not path.is_file():
                    problems.append(f"{rel}: missing (capture {cap['index']}, {role})")
                elif sha256_file(path) != digest:
                    problems.append(f"{rel}: SHA-256 mismatch (capture {cap['index']}, {role})")
        for cap in self.captures:
            folder = self.root / cap["name"]
            if folder.exists():
                for p in sorted(folder.rglob("*")):
                    if p.is_file() and self.relpath(p) not in checked:
                        problems.append(f"{self.relpath(p)}: not recorded in the manifest")
        return problems


def capture_folder_name(index: int, pose_deg: float) -> str:
    """Folder of one capture: ``c003_pose090.0`` (index first, so names sort in plan order)."""
    return f"c{index:03d}_pose{float(pose_deg):05.1f}".replace("-", "m")


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)
