"""Capture orchestration over turntable poses: plan, acquire, write, process. No printing.

Used by ``polrig capture`` / ``polrig reconstruct`` and the GUI alike. Progress is reported
through a callback (:class:`Progress` events); pause and stop come in through
:class:`CaptureControl` (``threading.Event`` s). Files go through :mod:`polrig.session`
(atomic, checksummed, raw frames first). Angles in degrees, exposures in microseconds,
conventions as in ``docs/conventions.md``.

Per pose the reference mode (issue 5): turn the turntable, grab dark frames with the light
off (if asked), then for each polarizer state move the stage (waiting for the move to end)
and grab ``K`` frames at each bracket exposure; every raw frame is written to the session as
soon as it arrives. Processing then reads the raw frames back from the session (the same
code path as ``polrig reconstruct``), averages and HDR-merges them, demosaics, solves the
3x3 linear Mueller block per pixel (:mod:`polrig.reference`) and writes the Mueller EXR with
its uncertainty and mask planes (see :mod:`polrig.processing`).

Device faults: a grab that times out is retried (``grab_retries`` times, a timeout loses no
data); a stage or turntable move that times out or faults is retried once after re-homing
(homing is the documented recovery of the ELL14/K10CR1 stages and loses no data); any other
device error, a full disk, any other file-system error or a stop request ends the session
cleanly: the capture in progress is marked ``failed`` (device error, disk full, other
``OSError``) or left ``pending`` (Ctrl-C, SIGTERM, stop), files it wrote are either recorded
with checksums or removed, and the session is ``interrupted`` with the reason. A second
SIGINT/SIGTERM while that clean-up runs is ignored (:class:`polrig.session.SignalGuard`).
``resume`` re-does every capture that is not complete, on the same rig only
(:func:`check_resume_rig`). :func:`run_session` holds the session's lock while it runs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import threading
from typing import Any, Callable

import numpy as np

from polrig.errors import (ConfigError, DeviceDisconnected, DeviceError, DeviceFault, DeviceTimeout,
                           ProtocolError)
from polrig.hal import Frame, grab_timeout_s, motion_timeout_s
from polrig.rawio import encode_mosaic
from polrig.session import (COMPLETE, FAILED, INTERRUPTED, PENDING, RUNNING, SESSION_COMPLETE,
                            Session, SignalGuard, interruption_reason, is_disk_full)

MODES = ("reference", "single-shot")
DEFAULT_STATES_DEG = (0.0, 45.0, 90.0, 135.0)
RAW_SUFFIX = ".png"
#: Largest turntable pose accepted, in degrees either way (100 turns): beyond it a pose is a
#: typo, and its capture folder name (``c000_pose<angle>``) would outgrow the file system's.
MAX_POSE_DEG = 36000.0
#: Largest polarizer stage angle accepted, either way: a linear polarizer repeats every 180 deg,
#: so anything beyond one turn is a typo (and would send the stage on a long, timed-out move).
MAX_STATE_DEG = 360.0


# -- parsing command-line style specs ------------------------------------------------------
def parse_pose_spec(spec: str) -> tuple[float, ...]:
    """Turntable poses in degrees from ``"0,30,60"`` (a list) or ``"START:STOP:STEP"``
    (a range, STOP exclusive like Python's ``range``: ``"0:360:90"`` is 0, 90, 180, 270).

    Raises :class:`ConfigError` naming the spec for anything else (empty, non-numeric,
    non-finite, zero step, a range that is empty).
    """
    text = str(spec).strip()
    bad = f"invalid pose spec {spec!r}"
    if not text:
        raise ConfigError(f"{bad}: give a list like 0,30,60 or a range START:STOP:STEP")
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise ConfigError(f"{bad}: a range is START:STOP:STEP (STOP exclusive), e.g. 0:360:30")
        start, stop, step = (_number(p, bad, "angle") for p in parts)
        if step == 0:
            raise ConfigError(f"{bad}: STEP must not be 0")
        count = math.ceil((stop - start) / step - 1e-9)
        if count <= 0:
            raise ConfigError(f"{bad}: the range is empty (STOP is exclusive)")
        if count > 100000:
            raise ConfigError(f"{bad}: {count} poses is too many")
        return tuple(round(start + i * step, 9) for i in range(count))
    return tuple(_number(p, bad, "angle") for p in text.split(","))


def _number(text: str, bad: str, what: str = "number") -> float:
    """``text`` as a finite float; :class:`ConfigError` ``"{bad}: 'x' is not a finite
    {what}"`` otherwise (``what``: "angle" for poses, "number" for any other value)."""
    try:
        v = float(text.strip())
    except ValueError:
        raise ConfigError(f"{bad}: {text.strip()!r} is not a number") from None
    if not math.isfinite(v):
        raise ConfigError(f"{bad}: {text.strip()!r} is not a finite {what}")
    return v


def parse_float_list(spec: str, name: str, *, positive: bool = False) -> tuple[float, ...]:
    """``"0,45,90"`` -> floats; :class:`ConfigError` naming the option ``name`` otherwise."""
    bad = f"invalid {name} {spec!r}"
    values = tuple(_number(p, bad) for p in str(spec).split(","))
    if positive and any(v <= 0 for v in values):
        raise ConfigError(f"{bad}: values must be > 0")
    return values


# -- the plan -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CapturePlan:
    """What a session acquires at every pose.

    ``exposures_us`` empty means "the camera's current exposure"; more than one is an
    exposure bracket merged to HDR (first entry = reference exposure of the result).
    ``dark_frames`` per exposure, light off, per pose (0 = subtract the camera's black level
    only). ``demosaic`` is the method used for processing (``superpixel`` by default: each
    Mueller pixel then uses four physically measured analyzer values and no interpolated
    ones, so the uncertainty propagated from the noise model is exact; interpolating methods
    correlate neighbouring pixels and mix their Mueller matrices at edges).
    """

    poses_deg: tuple[float, ...]
    mode: str = "reference"
    states_deg: tuple[float, ...] = DEFAULT_STATES_DEG
    frames_per_state: int = 1
    exposures_us: tuple[float, ...] = ()
    dark_frames: int = 0
    demosaic: str = "superpixel"
    grab_retries: int = 3
    #: single-shot: average the network's answers for the capture and its mirror image
    #: (:mod:`models.mirror`)
    mirror_average: bool = False

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not self.poses_deg:
            raise ConfigError("invalid pose spec: no poses")
        for pose in self.poses_deg:
            if not (isinstance(pose, (int, float)) and math.isfinite(pose)
                    and abs(pose) <= MAX_POSE_DEG):
                raise ConfigError(f"invalid pose spec: pose {pose!r} deg is not a finite angle "
                                  f"within +-{MAX_POSE_DEG:g} deg ({MAX_POSE_DEG / 360:g} turns)")
        for state in self.states_deg:
            if not (isinstance(state, (int, float)) and math.isfinite(state)
                    and abs(state) <= MAX_STATE_DEG):
                raise ConfigError(f"--states: {state!r} deg is not a polarizer angle within "
                                  f"+-{MAX_STATE_DEG:g} deg")
        if self.frames_per_state < 1:
            raise ConfigError(f"--frames must be >= 1, got {self.frames_per_state}")
        if self.dark_frames < 0:
            raise ConfigError(f"--dark-frames must be >= 0, got {self.dark_frames}")
        if any(not (e > 0 and math.isfinite(e)) for e in self.exposures_us):
            raise ConfigError(f"--exposure values must be > 0 microseconds, got "
                              f"{self.exposures_us}")
        if self.mirror_average and self.mode != "single-shot":
            raise ConfigError("--mirror-average applies to --mode single-shot only")
        if self.mode == "reference" and len(self.states_deg) < 3:
            raise ConfigError(f"--states: the reference method needs at least 3 polarizer "
                              f"states, got {len(self.states_deg)}")
        object.__setattr__(self, "poses_deg", tuple(float(p) for p in self.poses_deg))
        object.__setattr__(self, "states_deg", tuple(float(s) for s in self.states_deg))
        object.__setattr__(self, "exposures_us", tuple(float(e) for e in self.exposures_us))

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        for k in ("poses_deg", "states_deg", "exposures_us"):
            d[k] = list(d[k])
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "CapturePlan":
        fields = {f.name for f in dataclasses.fields(cls)}
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in fields}
        return cls(**kw)

    def frames_per_pose(self) -> int:
        n_exp = max(1, len(self.exposures_us))
        n_states = len(self.states_deg) if self.mode == "reference" else 1
        return n_exp * (n_states * self.frames_per_state + self.dark_frames)

    def acquired_states_deg(self) -> tuple[float, ...]:
        """Stage angles visited per pose (single-shot uses only the first state)."""
        return self.states_deg if self.mode == "reference" else self.states_deg[:1]


def planned_bytes(plan: CapturePlan, n_poses: int, width: int, height: int,
                  n_colours: int, cell: tuple[int, int] = (1, 1)) -> int:
    """Upper estimate of the disk space ``n_poses`` captures of ``plan`` take: uncompressed
    16-bit raw frames (+ sidecars), the float32 result EXR (9 Mueller + 9 sigma + mask +
    residual planes per colour) at the demosaic's output size (``cell`` = the layout period
    ``(ph, pw)``, which ``superpixel`` divides the size by) and the truth EXR (9 + 1 planes
    per colour) at full size; 5 % and 1 MiB (manifest) on top."""
    raw = plan.frames_per_pose() * (2 * width * height + 4096)
    if plan.demosaic == "superpixel":
        out_px = (height // cell[0]) * (width // cell[1])
    else:
        out_px = width * height
    exr = n_colours * 4 * (20 * out_px + 10 * width * height) + 2 * 65536
    return int(n_poses * (raw + exr) * 1.05) + (1 << 20)


# -- progress and control ---------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Progress:
    """One progress event. ``kind``: ``"frame"`` (a raw frame written), ``"capture-start"``,
    ``"capture-done"`` (``score`` set on the simulated rig), ``"capture-failed"``,
    ``"retry"``, ``"session-done"``. ``step``/``total`` count raw frames of the session."""

    kind: str
    capture_index: int
    n_captures: int
    step: int
    total: int
    pose_deg: float | None = None
    message: str = ""
    score: dict[str, Any] | None = None


ProgressCallback = Callable[[Progress], None]


@dataclasses.dataclass
class CaptureControl:
    """Pause/stop requests from another thread (the GUI). Checked between frames."""

    pause: threading.Event = dataclasses.field(default_factory=threading.Event)
    stop: threading.Event = dataclasses.field(default_factory=threading.Event)
    poll_s: float = 0.05

    def checkpoint(self) -> None:
        """Block while paused; raise :class:`StopRequested` when stop is set."""
        while self.pause.is_set() and not self.stop.is_set():
            self.stop.wait(self.poll_s)
        if self.stop.is_set():
            raise StopRequested("stopped by the operator")


class StopRequested(Exception):
    """Raised inside the capture loop when :attr:`CaptureControl.stop` is set."""


@dataclasses.dataclass
class SessionResult:
    """How a run ended. ``status`` is the session status; ``reason`` why it stopped early."""

    status: str
    completed: list[int]
    failed: list[int]
    reason: str | None = None
    scores: dict[int, dict[str, Any]] = dataclasses.field(default_factory=dict)


# -- device helpers -------------------------------------------------------------------------
def grab_with_retry(camera, retries: int, on_retry: Callable[[str], None] | None = None) -> Frame:
    """``camera.grab()`` with the timeout of the camera's current exposure
    (:func:`polrig.hal.grab_timeout_s`: exposure + readout + margin, so a long exposure does
    not time out by construction); a :class:`DeviceTimeout` is retried up to ``retries``
    times (a timed-out software-triggered grab delivered nothing, so grabbing again loses
    nothing)."""
    for attempt in range(retries + 1):
        try:
            return camera.grab(timeout_s=grab_timeout_s(camera))
        except DeviceTimeout as exc:
            if attempt == retries:
                raise DeviceTimeout(f"grab timed out {retries + 1} times: {exc}") from exc
            if on_retry:
                on_retry(f"camera grab timed out ({exc}); retry {attempt + 1}/{retries}")
    raise AssertionError("unreachable")  # pragma: no cover


def set_with_retry(setter: Callable[[Any], None], value: Any, retries: int,
                   on_retry: Callable[[str], None] | None = None) -> None:
    """Apply a camera setting; a :class:`DeviceTimeout` is retried (setting a value again is
    idempotent, so retrying loses nothing)."""
    for attempt in range(retries + 1):
        try:
            setter(value)
            return
        except DeviceTimeout as exc:
            if attempt == retries:
                raise
            if on_retry:
                on_retry(f"camera setting timed out ({exc}); retry {attempt + 1}/{retries}")


def move_with_rehome(stage, angle_deg: float, what: str,
                     on_retry: Callable[[str], None] | None = None) -> None:
    """Move ``stage`` to ``angle_deg`` and wait, with a timeout that grows with the distance
    (:func:`polrig.hal.motion_timeout_s`; a fixed 30 s failed turntable moves of 300 deg at
    10 deg/s). On a timeout, a device fault or a garbled reply (:class:`ProtocolError`: line
    noise on a serial link leaves the position unknown), home the stage and try once more; a
    second failure is raised. Disconnections are not retried."""
    try:
        stage.move_to(angle_deg, wait=True, timeout_s=_move_timeout_s(stage, angle_deg))
        return
    except DeviceDisconnected:
        raise
    except (DeviceTimeout, DeviceFault, ProtocolError) as exc:
        if on_retry:
            on_retry(f"{what} move to {angle_deg:g} deg failed ({exc}); re-homing and "
                     f"retrying once")
    stage.home()
    stage.move_to(angle_deg, wait=True, timeout_s=motion_timeout_s(stage, angle_deg))


def _move_timeout_s(stage, angle_deg: float) -> float:
    """Timeout of a move from where ``stage`` is now; if its position cannot be read (the move
    then fails or succeeds on its own), as if it had a full turn more to go."""
    try:
        here = float(stage.position_deg())
    except DeviceDisconnected:
        raise
    except (DeviceTimeout, DeviceFault, ProtocolError):
        here = float(angle_deg) + 360.0
    return motion_timeout_s(stage, float(angle_deg) - here)


# -- sessions ------------------------------------------------------------------------------
def frame_geometry(rig) -> tuple[int, int, int, tuple[int, int]]:
    """``(width, height, n_colours, layout period)`` of the rig camera's raw frames."""
    from polrig.analyzer import resolve_layout

    width, height = rig.camera.roi[:2]
    lay = resolve_layout(rig.camera.layout)
    return int(width), int(height), lay.n_colours, tuple(lay.period)


def camera_frames(rig) -> dict[str, Any]:
    """What the rig's camera frames look like (the manifest's ``rig.camera_frames``): size,
    ROI offset (the mosaic phase), layout and colour count. Frames that differ in any of
    these cannot be processed or compared together."""
    from polrig.analyzer import resolve_layout

    width, height, ox, oy = (int(v) for v in rig.camera.roi)
    layout = str(rig.camera.layout)
    return {"width": width, "height": height, "offset_xy": [ox, oy], "layout": layout,
            "colours": int(resolve_layout(layout).n_colours)}


def rig_record(rig) -> dict[str, Any]:
    """The manifest's ``rig`` entry: :func:`describe_rig`, the camera's frame geometry
    (:func:`camera_frames`) and the noise model used for the uncertainty."""
    from polrig.processing import sensor_model_of

    info = describe_rig(rig)
    info["camera_frames"] = camera_frames(rig)
    info["sensor_model"] = _jsonable(dataclasses.asdict(sensor_model_of(rig)))
    return info


def check_rig_for_plan(rig, plan: CapturePlan, *, resume: bool = False) -> None:
    """Refuse (:class:`ConfigError`, one line) a plan this rig's camera cannot acquire, before
    any session file is written: an exposure outside the camera's declared range
    (:attr:`polrig.hal.CameraCapabilities.exposure_range_us`)."""
    if not plan.exposures_us:
        return
    lo, hi = rig.camera.capabilities.exposure_range_us
    for e in plan.exposures_us:
        if not lo <= e <= hi:
            what = ("--resume: the session's plan asks for an exposure of" if resume
                    else "--exposure")
            raise ConfigError(f"{what} {e:g} us; this camera takes [{lo:g}, {hi:g}] us")


def _frames_text(f: dict[str, Any]) -> str:
    off = f.get("offset_xy") or [0, 0]
    where = f"+{off[0]}+{off[1]}" if any(off) else ""
    n = f.get("colours")
    return (f"{f.get('width')}x{f.get('height')}{where} {f.get('layout')}"
            + (f" ({n} colour{'s' if n != 1 else ''})" if n is not None else ""))


def _recorded_camera_frames(session: Session) -> dict[str, Any] | None:
    """:func:`camera_frames` of a session that predates ``rig.camera_frames``: from its first
    recorded raw frame, or ``None`` without one."""
    from polrig.analyzer import resolve_layout
    from polrig.rawio import read_raw

    for cap in session.captures:
        for rec in cap["files"].get("raw", []):
            try:
                frame = read_raw(session.root / rec["path"])
                layout = str(frame.meta.layout)
                return {"width": int(frame.raw.shape[1]), "height": int(frame.raw.shape[0]),
                        "offset_xy": [int(v) for v in frame.meta.offset_xy], "layout": layout,
                        "colours": int(resolve_layout(layout).n_colours)}
            except Exception:  # noqa: BLE001 - a damaged frame: try the next one
                continue
    return None


def rig_differences(stored: dict[str, Any], current: dict[str, Any],
                    stored_frames: dict[str, Any] | None = None) -> list[str]:
    """What makes frames of the rig ``current`` (a :func:`rig_record`) incomparable with those
    a session recorded on ``stored`` (its manifest's ``rig``): simulated or not, the camera
    frames' size, offset and layout, each device's driver, model and serial, the noise model,
    and the simulated world's hidden parameters (scene, seed, sensor...). Settings that do
    not change the frames (a simulated clock's speed) are not compared. One phrase per
    difference (empty: the same rig)."""
    out: list[str] = []
    if bool(stored.get("simulated")) != bool(current.get("simulated")):
        kind = lambda r: "the simulated rig" if r.get("simulated") else "hardware"  # noqa: E731
        out.append(f"captured on {kind(stored)}, this is {kind(current)}")
    sf = stored.get("camera_frames") or stored_frames
    cf = current.get("camera_frames")
    if isinstance(sf, dict) and cf is not None:
        keys = ("width", "height", "offset_xy", "layout", "colours")
        if [sf.get(k) for k in keys] != [cf.get(k) for k in keys]:
            out.append(f"camera frames {_frames_text(sf)}, this camera's {_frames_text(cf)}")
    if stored.get("sensor_model") and stored.get("sensor_model") != current.get("sensor_model"):
        keys = sorted(k for k in set(stored["sensor_model"]) | set(current["sensor_model"] or {})
                      if stored["sensor_model"].get(k) != (current["sensor_model"] or {}).get(k))
        out.append(f"sensor noise model ({', '.join(keys)})")
    sp, cp = stored.get("sim_parameters"), current.get("sim_parameters")
    if (isinstance(sp, dict) and isinstance(cp, dict) and "error" not in sp
            and "error" not in cp and sp != cp):
        keys = sorted(k for k in set(sp) | set(cp) if sp.get(k) != cp.get(k))
        out.append(f"simulated world ({', '.join(keys)})")
    sd, cd = stored.get("devices") or {}, current.get("devices") or {}
    for name in ("camera", "stage", "turntable", "light"):
        a, b = sd.get(name), cd.get(name)
        if not (isinstance(a, dict) and isinstance(b, dict)) or "error" in a or "error" in b:
            continue  # a device that could not describe itself is not compared
        ident = lambda d: " ".join(str(d.get(k)) for k in ("driver", "model", "serial")  # noqa: E731
                                   if d.get(k))
        if ident(a) != ident(b):
            out.append(f"{name} {ident(a)!r}, this rig's {ident(b)!r}")
    return out


def check_resume_rig(session: Session, rig) -> None:
    """Refuse (:class:`ConfigError`, one line) to resume ``session`` on a rig whose frames
    would not be comparable with the ones it holds (:func:`rig_differences`); nothing is
    written. Call before :func:`check_resume_space` and :func:`run_session`."""
    stored = session.manifest.get("rig") or {}
    current = json.loads(json.dumps(rig_record(rig)))  # as the manifest would store it
    frames = None if stored.get("camera_frames") else _recorded_camera_frames(session)
    diffs = rig_differences(stored, current, frames)
    if diffs:
        raise ConfigError(f"--resume: {session.root} was captured on a different rig: "
                          f"{'; '.join(diffs[:4])}; resume it on the rig it was started with "
                          f"(the same --config)")


def create_session(out, rig, plan: CapturePlan, *, calibration_id: str,
                   command_line: list[str] | None = None, write_hook=None) -> Session:
    """A new session for ``plan`` on ``rig`` in ``out`` (disk space checked). The returned
    session holds its lock (:meth:`polrig.session.Session.lock`) until :func:`run_session`
    ends."""
    width, height, colours, cell = frame_geometry(rig)
    need = planned_bytes(plan, len(plan.poses_deg), width, height, colours, cell)
    return Session.create(out, plan=plan.to_json(), rig=rig_record(rig),
                          calibration_id=calibration_id, command_line=command_line,
                          required_bytes=need, write_hook=write_hook)


def check_resume_space(session: Session, rig, n_captures: int) -> None:
    """Check the free disk space for ``n_captures`` more captures of ``session``."""
    from polrig.session import check_free_space

    width, height, colours, cell = frame_geometry(rig)
    plan = CapturePlan.from_json(session.plan)
    check_free_space(session.root,
                     planned_bytes(plan, n_captures, width, height, colours, cell))
    session.log("resumed", remaining=n_captures)


# -- the session run (acquisition) ------------------------------------------------------
def describe_rig(rig) -> dict[str, Any]:
    """What the manifest records about the rig: its config and the devices' identities."""
    out: dict[str, Any] = {"simulated": getattr(rig, "truth", None) is not None}
    cfg = getattr(rig, "config", None)
    if cfg is not None:
        out["config"] = _jsonable(cfg)
    devices = {}
    for name in ("camera", "stage", "turntable", "light"):
        dev = getattr(rig, name, None)
        if dev is None:
            continue
        try:
            devices[name] = _jsonable(dataclasses.asdict(dev.info()))
        except Exception as exc:  # a device that cannot describe itself is still usable
            devices[name] = {"error": str(exc)}
    out["devices"] = devices
    truth = getattr(rig, "truth", None)
    if truth is not None and hasattr(truth, "rig_parameters"):
        try:
            out["sim_parameters"] = _jsonable(truth.rig_parameters())
        except Exception as exc:
            out["sim_parameters"] = {"error": str(exc)}
    return out


def _jsonable(obj: Any) -> Any:
    """A JSON-compatible copy of ``obj`` (arrays to lists, dataclasses to dicts, paths to str)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return _jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist()) if obj.size <= 64 else f"<array {obj.shape} {obj.dtype}>"
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)


def raw_relpath(folder: str, state_index: int, state_deg: float, exposure_index: int,
                frame_index: int) -> str:
    return (f"{folder}/raw/s{state_index:02d}_{state_deg:05.1f}deg_e{exposure_index}"
            f"_f{frame_index:03d}{RAW_SUFFIX}")


def dark_relpath(folder: str, exposure_index: int, frame_index: int) -> str:
    return f"{folder}/dark/e{exposure_index}_f{frame_index:03d}{RAW_SUFFIX}"


def _frame_bytes(frame: Frame) -> tuple[bytes, bytes]:
    image = encode_mosaic(frame.raw, RAW_SUFFIX)
    meta = json.dumps(frame.meta.to_json(), indent=1, sort_keys=True).encode("utf-8")
    return image, meta


def run_session(rig, session: Session, *, processor=None,
                progress: ProgressCallback | None = None,
                control: CaptureControl | None = None) -> SessionResult:
    """Acquire (and process) every capture of ``session`` that is not complete yet.

    ``processor`` (normally :func:`polrig.processing.make_processor`'s result) has
    ``after_acquire(session, index, rig)`` (run while the rig is still at the pose: the
    simulated rig's ground truth) and ``process(session, index) -> score dict or None``
    (turns the capture's raw files into results).

    The session's lock is taken (if this object does not hold it yet; :class:`SessionBusy`
    when another process writes the session) and released when the run ends. In the main
    thread SIGINT and SIGTERM stop the run like Ctrl-C (:class:`polrig.session.SignalGuard`:
    a second signal during the clean-up is ignored). Returns how the run ended; raises
    ``KeyboardInterrupt`` (:class:`polrig.session.Interrupted` for a signal) after leaving
    the session consistent when interrupted, and re-raises a file-system error other than a
    full disk, or an unexpected error, after marking the capture failed and the session
    interrupted.
    """
    session.lock()
    try:
        with SignalGuard() as guard:
            return _run_session(rig, session, processor, progress, control, guard)
    finally:
        session.unlock()


def _run_session(rig, session: Session, processor, progress, control, guard: SignalGuard
                 ) -> SessionResult:
    plan = CapturePlan.from_json(session.plan)
    control = control or CaptureControl()
    todo = session.next_pending()
    n = len(session.captures)
    total = len(todo) * plan.frames_per_pose()
    step = 0
    result = SessionResult(status=RUNNING, completed=[c["index"] for c in session.captures
                                                      if c["status"] == COMPLETE], failed=[])

    def emit(kind: str, index: int, message: str = "", score=None) -> None:
        if progress:
            progress(Progress(kind, index, n, step, total, session.capture(index)["pose_deg"],
                              message, score))

    index = None
    try:
        session.set_status(RUNNING)
        if todo:
            try:
                _prepare_rig(rig, plan)
            except DeviceError as exc:
                with guard.deferred():
                    session.set_status(INTERRUPTED, f"rig preparation failed: {exc}")
                return SessionResult(INTERRUPTED, result.completed, [], str(exc))
        for index in todo:
            try:
                session.restart_capture(index)
                emit("capture-start", index)

                def frame_done(message: str = "") -> None:
                    nonlocal step
                    step += 1
                    emit("frame", index, message)

                _acquire_capture(rig, session, plan, index, control, frame_done,
                                 lambda msg: emit("retry", index, msg))
                score = None
                if processor is not None:
                    processor.after_acquire(session, index, rig)  # truth while at this pose
                    control.checkpoint()
                    score = processor.process(session, index)
                session.complete_capture(index, score)
                result.completed.append(index)
                if score is not None:
                    result.scores[index] = score
                emit("capture-done", index, score=score)
            except (KeyboardInterrupt, StopRequested) as exc:
                reason = (interruption_reason(exc) if isinstance(exc, KeyboardInterrupt)
                          else "stopped by the operator")
                with guard.deferred():
                    _stop_cleanly(session, index, reason, capture_status=PENDING)
                result.status, result.reason = INTERRUPTED, reason
                if isinstance(exc, KeyboardInterrupt):
                    with contextlib.suppress(Exception):  # a progress display must not stop
                        emit("capture-failed", index, reason)  # the interruption
                    raise
                emit("capture-failed", index, reason)
                return result
            except (DeviceError, OSError) as exc:
                if isinstance(exc, OSError) and not is_disk_full(exc):
                    # any other file-system error (permissions, I/O error, a name too long):
                    # leave the session consistent and resumable, then let the caller report it
                    with guard.deferred():
                        _stop_cleanly(session, index, f"{type(exc).__name__}: {exc}",
                                      capture_status=FAILED)
                    raise
                kind = "disk full" if is_disk_full(exc) else type(exc).__name__
                reason = f"{kind}: {exc}"
                with guard.deferred():
                    _stop_cleanly(session, index, reason, capture_status=FAILED)
                result.status, result.reason = INTERRUPTED, reason
                result.failed.append(index)
                emit("capture-failed", index, reason)
                return result
            except Exception as exc:  # a processing bug or bad data: record it, then report it
                with guard.deferred():
                    _stop_cleanly(session, index, f"{type(exc).__name__}: {exc}",
                                  capture_status=FAILED)
                raise
        with guard.deferred():
            session.set_status(SESSION_COMPLETE)
    except KeyboardInterrupt as exc:
        # between captures (rig preparation, the final manifest): the captures are as the
        # manifest on disk says; the session is interrupted unless a capture's clean-up said so
        if session.manifest.get("status") not in (INTERRUPTED, SESSION_COMPLETE):
            with guard.deferred(), contextlib.suppress(Exception):
                if index is None:
                    session.set_status(INTERRUPTED, interruption_reason(exc))
                else:
                    _stop_cleanly(session, index, interruption_reason(exc),
                                  capture_status=PENDING)
        raise
    result.status = SESSION_COMPLETE
    emit("session-done", todo[-1] if todo else 0)
    return result


def interrupted_result(session: Session, exc: BaseException) -> SessionResult:
    """How a run ended that raised ``exc`` after ``session`` was opened: :func:`run_session`
    re-raises a file-system error other than a full disk and an unexpected error (a
    processing bug) after leaving the session ``interrupted``; an error before the run (the
    processor could not be built) leaves it as it was. Either way the session is
    ``interrupted`` with the reason (written here where the run did not), its lock released,
    and the result says so, for the caller to report as any other stop: the completed
    captures are intact and ``--resume`` continues (``polrig capture``, the GUI)."""
    reason = f"{type(exc).__name__}: {exc}"
    if session.manifest.get("status") == INTERRUPTED:
        reason = session.manifest.get("status_reason") or reason
    else:
        with contextlib.suppress(Exception):  # another writer, a failing disk: as it is
            session.lock()
            session.set_status(INTERRUPTED, reason)
    session.unlock()
    done = [c["index"] for c in session.captures if c["status"] == COMPLETE]
    failed = [c["index"] for c in session.captures if c["status"] == FAILED]
    return SessionResult(INTERRUPTED, done, failed, reason)


def _stop_cleanly(session: Session, index: int, reason: str, *, capture_status: str) -> None:
    """Leave the session consistent after a stop: unrecorded files of the capture removed,
    its status set, session ``interrupted`` with ``reason``. Saving may itself fail (a full
    disk): the manifest on disk then still is the last consistent one, which is fine."""
    try:
        session.reload()  # what is on disk is what counts: a failed save may be missing
        session.discard_unrecorded(index)
    except OSError:
        pass
    cap = session.capture(index)
    if cap["status"] == COMPLETE:
        pass  # the interruption came after the capture was complete and saved: keep it
    elif capture_status == FAILED:
        session.fail_capture(index, reason, save=False)
    else:
        cap.update(status=PENDING, reason=reason)
    try:
        session.set_status(INTERRUPTED, reason)
    except OSError:
        pass


def _prepare_rig(rig, plan: CapturePlan) -> None:
    cam = rig.camera
    cam.set_trigger(cam.capabilities.preferred_trigger)
    rig.light.set_on(True)
    rig.stage.home()


def _grab_settled(rig, plan: CapturePlan, settle: bool,
                  on_retry: Callable[[str], None]) -> Frame:
    """One frame exposed entirely after the last change: in free run, after a motion or a
    setting change (``settle``), the camera's declared
    :attr:`~polrig.hal.CameraCapabilities.settle_frames` frames are discarded first."""
    caps = rig.camera.capabilities
    if settle and caps.preferred_trigger == "free":
        for _ in range(caps.settle_frames):
            grab_with_retry(rig.camera, plan.grab_retries, on_retry)
    return grab_with_retry(rig.camera, plan.grab_retries, on_retry)


def _acquire_capture(rig, session: Session, plan: CapturePlan, index: int,
                     control: CaptureControl, frame_done: Callable[[str], None],
                     on_retry: Callable[[str], None]) -> None:
    """Turn to the pose, grab and write every raw frame of capture ``index``."""
    cap = session.capture(index)
    folder = cap["name"]
    control.checkpoint()
    move_with_rehome(rig.turntable, cap["pose_deg"], "turntable", on_retry)
    exposures = plan.exposures_us or (float(rig.camera.exposure_us),)
    changed = [True]  # something moved or changed since the last frame (free-run settling)

    def set_exposure(exposure_us: float) -> None:
        current = float(rig.camera.exposure_us)
        if current != exposure_us and not (math.isnan(current) and math.isnan(exposure_us)):
            set_with_retry(rig.camera.set_exposure_us, exposure_us, plan.grab_retries, on_retry)
            changed[0] = True

    def grab() -> Frame:
        frame = _grab_settled(rig, plan, changed[0], on_retry)
        changed[0] = False
        return frame

    if plan.dark_frames:
        rig.light.set_on(False)
        try:
            for e, exposure_us in enumerate(exposures):
                set_exposure(exposure_us)
                for k in range(plan.dark_frames):
                    control.checkpoint()
                    frame = grab()
                    image, meta = _frame_bytes(frame)
                    session.add_file(index, "dark", dark_relpath(folder, e, k), image,
                                     sidecar=meta, exposure_us=exposure_us, exposure_index=e,
                                     frame=k)
                    frame_done()
        finally:
            rig.light.set_on(True)
            changed[0] = True
    for j, state_deg in enumerate(plan.acquired_states_deg()):
        control.checkpoint()
        move_with_rehome(rig.stage, state_deg, "polarizer stage", on_retry)
        changed[0] = True
        for e, exposure_us in enumerate(exposures):
            set_exposure(exposure_us)
            for k in range(plan.frames_per_state):
                control.checkpoint()
                frame = grab()
                image, meta = _frame_bytes(frame)
                session.add_file(index, "raw", raw_relpath(folder, j, state_deg, e, k), image,
                                 sidecar=meta, state_index=j, state_deg=state_deg,
                                 exposure_us=exposure_us, exposure_index=e, frame=k)
                frame_done()
    set_exposure(exposures[0])  # the reference exposure (the truth is taken at it)
