"""A capture's files inside a session: where raw and dark frames go and how they are encoded
(:func:`raw_relpath`, :func:`frame_bytes`), reading them back with their checksums verified
(:func:`load_capture_frames`), and creating a session for a plan on a rig with its disk
space checked (:func:`create_session`).

Raw frame names carry the plan's state index (``s01_045.0deg_e0_f000.png``), never the order
they were grabbed in, so a session's files do not depend on the order of acquisition.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, MutableMapping

from polrig.acquisition.plan import CapturePlan, planned_bytes
from polrig.app.manifest import DarkFrameRecord, RawFrameRecord
from polrig.app.records import frame_geometry, rig_record
from polrig.app.session import Session, check_free_space, sha256_file
from polrig.errors import FormatError
from polrig.formats.rawio import encode_mosaic, read_raw
from polrig.sensor.frame import Frame

RAW_SUFFIX = ".png"


def raw_relpath(folder: str, state_index: int, state_deg: float, exposure_index: int,
                frame_index: int) -> str:
    return (f"{folder}/raw/s{state_index:02d}_{state_deg:05.1f}deg_e{exposure_index}"
            f"_f{frame_index:03d}{RAW_SUFFIX}")


def dark_relpath(folder: str, exposure_index: int, frame_index: int) -> str:
    return f"{folder}/dark/e{exposure_index}_f{frame_index:03d}{RAW_SUFFIX}"


def frame_bytes(frame: Frame) -> tuple[bytes, bytes]:
    """A raw frame as the session stores it: the encoded mosaic and its JSON sidecar."""
    image = encode_mosaic(frame.raw, RAW_SUFFIX)
    meta = json.dumps(frame.meta.to_json(), indent=1, sort_keys=True).encode("utf-8")
    return image, meta


def create_session(out, rig, plan: CapturePlan, *, calibration_id: str,
                   command_line: list[str] | None = None, write_hook=None,
                   metadata=None, processing=None) -> Session:
    """A new session for ``plan`` on ``rig`` in ``out`` (disk space checked; ``metadata``: its
    :class:`polrig.app.manifest.SampleMetadata`, empty by default; ``processing``: how its
    captures are processed, :class:`polrig.app.manifest.ProcessingRecord`). The returned
    session holds its lock (:meth:`polrig.app.session.Session.lock`) until :func:`run_session`
    ends."""
    width, height, colours, cell = frame_geometry(rig)
    need = planned_bytes(plan, len(plan.poses_deg), width, height, colours, cell)
    return Session.create(out, plan=plan, rig=rig_record(rig),
                          calibration_id=calibration_id, command_line=command_line,
                          required_bytes=need, write_hook=write_hook, metadata=metadata,
                          processing=processing)


def check_resume_space(session: Session, rig, n_captures: int) -> None:
    """Check the free disk space for ``n_captures`` more captures of ``session``."""
    width, height, colours, cell = frame_geometry(rig)
    check_free_space(session.root,
                     planned_bytes(session.plan, n_captures, width, height, colours, cell))
    session.log("resumed", remaining=n_captures)


def read_verified_frame(session: Session, record: RawFrameRecord | DarkFrameRecord,
                        known: Mapping[str, Frame] | None = None) -> Frame:
    """Read one recorded raw frame after checking its (and its sidecar's) SHA-256.

    ``known``: frames already read, by the SHA-256 of their file: a file whose checksum (as
    verified now) is there is not decoded again; its frame was read from identical bytes,
    sidecar included (the key is both checksums, :func:`frame_key`)."""
    for key, digest in (("path", "sha256"), ("meta_path", "meta_sha256")):
        path = session.root / record[key]
        if not path.is_file():
            raise FileNotFoundError(f"{path}: raw file of the session is missing")
        if sha256_file(path) != record[digest]:
            raise FormatError(f"{path}: SHA-256 does not match the session manifest (changed "
                              f"or corrupt raw data)")
    if known is not None and frame_key(record) in known:
        return known[frame_key(record)]
    return read_raw(session.root / record["path"])


def frame_key(record: RawFrameRecord | DarkFrameRecord) -> str:
    """A frame file's identity: its image's and its sidecar's SHA-256 (``image:sidecar``)."""
    return f"{record['sha256']}:{record['meta_sha256']}"


@dataclasses.dataclass
class CaptureFrames:
    """Raw frames of one capture grouped for processing."""

    states_deg: list[float]
    exposures_us: list[float]
    frames: list[list[list[Frame]]]  # [state][exposure][k]
    darks: list[list[Frame]]  # [exposure][k]
    #: per state, the SHA-256 of its frame files in the order of ``frames[state]`` (exposure,
    #: then repeat), as verified when read; empty where the frames did not come from files
    checksums: list[tuple[str, ...]] = dataclasses.field(default_factory=list)
    #: the dark frames' SHA-256 in the order of ``darks``
    dark_checksums: tuple[str, ...] = ()

    @property
    def first(self) -> Frame:
        return self.frames[0][0][0]


def recorded_exposure_us(record: RawFrameRecord | DarkFrameRecord) -> float:
    """A frame record's exposure in microseconds; NaN where it is unknown (``null``: a camera
    without exposure control)."""
    value = record["exposure_us"]
    return float("nan") if value is None else float(value)


def manifest_exposure_us(exposure_us: float) -> float | None:
    """An exposure as a frame record stores it: ``None`` (JSON ``null``) when the camera does
    not report one (NaN), so the manifest stays standard JSON."""
    e = float(exposure_us)
    return e if math.isfinite(e) else None


def load_capture_frames(session: Session, index: int,
                        known: MutableMapping[str, Frame] | None = None) -> CaptureFrames:
    """Every raw and dark frame of capture ``index``, checksums verified.

    ``known`` (frames by :func:`frame_key`): frames already read are taken from it rather than
    decoded again (their files are still verified), and the frames read are added to it."""
    files = session.capture(index)["files"]
    raw = files.get("raw", [])
    if not raw:
        raise FormatError(f"capture {index} of {session.root} has no raw frames")
    n_states = 1 + max(r["state_index"] for r in raw)
    n_exp = 1 + max(r["exposure_index"] for r in raw)
    states = [0.0] * n_states
    exposures = [0.0] * n_exp
    frames: list[list[list[tuple[int, Frame, str]]]] = [[[] for _ in range(n_exp)]
                                                        for _ in range(n_states)]

    def read(r) -> tuple[int, Frame, str]:
        frame = read_verified_frame(session, r, known)
        if known is not None:
            known[frame_key(r)] = frame
        return r["frame"], frame, frame_key(r)

    for r in raw:
        states[r["state_index"]] = float(r["state_deg"])
        exposures[r["exposure_index"]] = recorded_exposure_us(r)
        frames[r["state_index"]][r["exposure_index"]].append(read(r))
    darks: list[list[tuple[int, Frame, str]]] = [[] for _ in range(n_exp)]
    for r in files.get("dark", []):
        darks[r["exposure_index"]].append(read(r))
    for j, per_state in enumerate(frames):
        for e, lst in enumerate(per_state):
            if not lst:
                raise FormatError(f"capture {index}: no frames of state {j} at exposure {e}")
    srt = lambda lst: sorted(lst, key=lambda t: t[0])  # noqa: E731
    return CaptureFrames(states, exposures,
                         [[[f for _, f, _ in srt(l)] for l in s] for s in frames],
                         [[f for _, f, _ in srt(l)] for l in darks],
                         [tuple(k for l in s for _, _, k in srt(l)) for s in frames],
                         tuple(k for l in darks for _, _, k in srt(l)))
