"""Capture sessions over turntable poses: plan -> executor -> sinks, processing overlapped with
acquisition. No printing.

:func:`run_capture` is the one capture call: ``polrig capture`` and the GUI build a
:class:`CaptureRequest` and present its events (:class:`SessionOpened`, :class:`Progress`);
it validates the request (:func:`prepare_capture`), opens the rig, builds the processor,
creates or resumes the session (:func:`open_session`), runs it (:func:`run_session`) and turns
any stop once the session exists into a resumable result (:func:`interrupted_result`). The
request and its checks live in :mod:`polrig.app.capture_request`; this module re-exports
:class:`CaptureRequest`, :class:`PreparedCapture`, :func:`prepare_capture` and
:func:`open_session` as the capture's one public face.
``tests/test_architecture.py`` fails if a shell takes those steps itself.

:func:`run_session` turns the session's plan into device steps (:mod:`polrig.acquisition.plan`), runs
them with one :class:`polrig.acquisition.engine.Executor` (its fault policy: retries, re-homing,
timeouts from the hardware's declared capabilities) and subscribes to its events:

* the **session writer** writes every raw frame, atomically and checksummed, the moment it
  is grabbed (:meth:`polrig.app.session.Session.add_file`), before anything processes it;
* at a capture's "capture-acquired" checkpoint (the rig still at its pose) the simulated rig's
  truth is recorded (``processor.after_acquire``) and the capture is marked ``acquired``;
* the **processing worker** (one thread: numpy and the solver release the GIL) processes
  capture ``k`` while capture ``k + 1`` is acquired; at most one capture is processed and one
  acquired at a time (by default a capture is handed to the worker once the previous one's
  processing has ended: ``max_queued``), so memory stays bounded;
* **progress** (:class:`Progress` events, with the plan's remaining hardware time for an
  ETA from the first event) goes to the caller's callback, always from the calling thread.

A safety fault (:class:`polrig.errors.DeviceAlarm`: a limit switch fired, a soft limit, a
turntable locked in its alarm state) stops the run like any device fault, with a reason that
names the command the operator runs once the cause is cleared (``polrig home turntable
--config RIG``); the engine never homes the axis on its own, and ``--resume`` continues.

Interruptions (Ctrl-C, SIGTERM, a stop request, a device fault, a full disk, another
file-system error, a processing error) end the run cleanly: processing already under way is
let finish (its capture becomes ``complete``, or stays ``acquired`` with the reason if it
failed), a capture acquired but not processed yet stays ``acquired``, the capture being
acquired is left ``pending`` (a stop, a signal) or marked ``failed`` (device or file-system
error) with its unrecorded files removed, and the session is ``interrupted`` with the
reason. :func:`run_session` on it again (``--resume``) processes the ``acquired`` captures
without acquiring them again and acquires the others from scratch; since raw file names and
processing are indexed by the plan's state index, and the simulated camera's noise is keyed
by pose, state and repeat, the result is identical to an uninterrupted run. A second
SIGINT/SIGTERM during the clean-up is ignored (:class:`polrig.app.session.SignalGuard`).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import pathlib
from typing import Any, Callable, Sequence

from polrig.acquisition.engine import (
    CaptureControl,
    CheckpointReached,
    Executor,
    FaultPolicy,
    FrameGrabbed,
    Retried,
    StepDone,
    StopRequested,
    hardware_model,
)
from polrig.acquisition.plan import (  # noqa: F401 (CapturePlan: re-exported)
    CapturePlan,
    Grab,
    capture_steps,
    setup_steps,
    step_durations,
)
from polrig.app.adaptive import AdaptiveSchedule, PoseMemo
from polrig.app.adaptive import decide as adaptive_decide
from polrig.app.capture_request import (  # noqa: F401 (CaptureRequest, PreparedCapture: re-exported)
    CaptureRequest,
    PreparedCapture,
    open_session,
    prepare_capture,
)
from polrig.app.manifest import AdaptiveDecision, describe_decision
from polrig.app.processing import make_processor
from polrig.app.records import sensor_model_of, session_sensor_model
from polrig.app.session import (
    ACQUIRED,
    ACQUISITION_ROLES,
    COMPLETE,
    FAILED,
    INTERRUPTED,
    PENDING,
    RUNNING,
    SESSION_COMPLETE,
    Session,
    SignalGuard,
    interruption_reason,
    is_disk_full,
)
from polrig.app.sessionio import (  # noqa: F401 (check_resume_space, create_session: re-exported)
    check_resume_space,
    create_session,
    dark_relpath,
    frame_bytes,
    manifest_exposure_us,
    raw_relpath,
)
from polrig.errors import DeviceAlarm, DeviceError

__all__ = ["CaptureControl", "CaptureEvent", "CapturePlan", "CaptureRequest", "PreparedCapture",
           "Progress", "RecordedDecision", "SessionOpened", "SessionResult", "StopRequested",
           "check_resume_space", "create_session", "interrupted_result", "kept_decisions",
           "open_session", "prepare_capture", "run_capture", "run_session"]


# -- progress -----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Progress:
    """One progress event. ``kind``: ``"capture-start"``, ``"frame"`` (a raw frame written),
    ``"retry"``, ``"capture-acquired"`` (every frame of the capture written; it is handed to
    processing), ``"capture-done"`` (processed; ``score`` set on the simulated rig),
    ``"capture-failed"``, ``"session-done"``, ``"decision"`` (an adaptive capture's decision,
    ``message`` says it; its hardware time and ``total`` are already revised by it).
    ``step``/``total`` count the raw frames this run acquires. ``hardware_s``: the plan's hardware time for this run (motion, exposure,
    readout; :func:`polrig.acquisition.plan.step_durations`), known before the first frame;
    ``hardware_left_s`` what is left of it. ``result``: of ``"capture-done"``, the capture's
    result file (``mueller.exr``; ``None`` without processing)."""

    kind: str
    capture_index: int
    n_captures: int
    step: int
    total: int
    pose_deg: float | None = None
    message: str = ""
    score: dict[str, Any] | None = None
    hardware_s: float = 0.0
    hardware_left_s: float = 0.0
    result: pathlib.Path | None = None


ProgressCallback = Callable[[Progress], None]


@dataclasses.dataclass(frozen=True)
class RecordedDecision:
    """An adaptive decision a session holds from an earlier run: capture ``capture_index``
    (at ``pose_deg``) took ``decision`` (:class:`polrig.app.manifest.AdaptiveDecision`)."""

    capture_index: int
    pose_deg: float
    decision: AdaptiveDecision

    def describe(self) -> str:
        """The decision in the words of its progress event
        (:func:`polrig.app.manifest.describe_decision`)."""
        return describe_decision(self.decision)


def kept_decisions(session: Session) -> tuple[RecordedDecision, ...]:
    """The adaptive decisions ``session`` holds for the captures a run of it keeps: those
    complete or acquired (processed, not acquired again), in plan order, each capture's in the
    order made. Every other capture is acquired from scratch
    (:meth:`polrig.app.session.Session.restart_capture` forgets its decisions) and decides
    again, in that run's ``"decision"`` events, as does an acquired capture whose raw data no
    longer verifies (the run sets it aside: :meth:`polrig.app.session.Session.set_aside_damaged`).
    Empty for a new session or another mode."""
    return tuple(RecordedDecision(c["index"], c["pose_deg"], d) for c in session.captures
                 if c.get("adaptive") and (c["status"] == COMPLETE or (
                     c["status"] == ACQUIRED and not session.acquisition_problems(c["index"])))
                 for d in c["adaptive"])


@dataclasses.dataclass(frozen=True)
class SessionOpened:
    """The session of a :func:`run_capture` exists (``resumed``: an existing one continues)
    and its run starts: the request was valid, the rig is open and fits it, nothing was
    refused. Every way the run ends from here is a :class:`SessionResult` (or Ctrl-C).
    ``decisions``: a resumed adaptive session's decisions the run keeps
    (:func:`kept_decisions`), read before the run changes anything; the run's own come as
    ``"decision"`` events."""

    root: pathlib.Path
    resumed: bool
    n_captures: int
    decisions: tuple[RecordedDecision, ...] = ()


#: What :func:`run_capture` tells its ``events`` callback, in the calling thread.
CaptureEvent = SessionOpened | Progress
#: Where :func:`run_capture` gets its rig: a callable returning a context manager that yields
#: an open :class:`polrig.app.rig.Rig` (and closes or releases it at the end).
RigSource = Callable[[], contextlib.AbstractContextManager[Any]]


@dataclasses.dataclass
class SessionResult:
    """How a run ended. ``status`` is the session status; ``reason`` why it stopped early."""

    status: str
    completed: list[int]
    failed: list[int]
    reason: str | None = None
    scores: dict[int, dict[str, Any]] = dataclasses.field(default_factory=dict)


# -- the one capture call -----------------------------------------------------------------------
def run_capture(request: CaptureRequest, *, command_line: Sequence[str],
                rig: RigSource | None = None,
                events: Callable[[CaptureEvent], None] | None = None,
                control: CaptureControl | None = None, reraise: bool = False) -> SessionResult:
    """Run ``request`` end to end: the one capture call of every shell (``polrig capture``,
    the GUI's capture panel), which only build the request and present the events.

    1. :func:`prepare_capture`: the request is validated before any device opens or any file
       is written (on ``resume`` the session is opened and its lock taken);
    2. the rig: ``rig()`` (default :func:`polrig.app.rig.open_rig` of ``request.config``), a
       context manager held for the whole run (the GUI's yields its open rig under its device
       locks);
    3. the processor (:func:`polrig.app.processing.make_processor` of the plan, the calibration,
       the noise model the session records or will record, on ``request.device``);
    4. :func:`open_session`: the rig must fit the plan and the calibration (on ``resume``: be
       the rig the session was captured on; the disk space for what is left), then the
       session is created or continued, and :class:`SessionOpened` is sent;
    5. :func:`run_session` with ``events`` (its :class:`Progress`) and ``control`` (pause,
       stop);
    6. any error once the session exists (a file-system error, a processing error) leaves it
       ``interrupted`` and resumable and comes back as that result with the reason
       (:func:`interrupted_result`; ``reraise`` raises it instead, for a debugging run);
       device faults, a full disk and a stop are results anyway. The session's lock is
       released whatever way the call ends.

    Before :class:`SessionOpened` a refusal is raised and nothing is written
    (:class:`polrig.acquisition.plan.PlanError` naming the request's field,
    ``FileNotFoundError``, ``FileExistsError``, :class:`polrig.errors.ConfigError`,
    :class:`polrig.app.session.SessionBusy`, a device error while the rig opens). Ctrl-C and
    SIGTERM (main thread) are raised as ``KeyboardInterrupt`` after the session is left
    consistent and resumable. ``command_line`` is what the manifest records as the command.
    """
    prepared = prepare_capture(request)
    session: Session | None = None
    try:
        with (rig or _configured_rig(request.config))() as opened:
            sensor = (session_sensor_model(prepared.resume_session)
                      if prepared.resume_session is not None else sensor_model_of(opened))
            processor = make_processor(prepared.plan, prepared.calibration, sensor,
                                       device=request.device, model_size=request.model_size,
                                       models=prepared.models, prior_scale=prepared.prior_scale)
            session = open_session(prepared, opened, list(command_line))
            try:
                if events is not None:
                    events(SessionOpened(session.root, prepared.resume_session is not None,
                                         len(session.captures), kept_decisions(session)))
                return run_session(opened, session, processor=processor, progress=events,
                                   control=control)
            except Exception as exc:  # the session exists: a stop to report
                if reraise:
                    raise
                return interrupted_result(session, exc)
    finally:  # whatever way it ends (a refusal before the run too), the lock goes
        for held in (session, prepared.resume_session):
            if held is not None:
                held.unlock()


def _configured_rig(config: pathlib.Path | None) -> RigSource:
    """The rig of ``config`` (the simulated rig without one), opened when the run starts."""

    def source():
        # looked up at call time: tests replace polrig.app.rig.open_rig
        from polrig.app import rig as rigs

        return rigs.open_rig(config)

    return source


class _ProcessingFailed(Exception):
    """Internal: processing capture ``index`` raised ``error`` (in the worker)."""

    def __init__(self, index: int, error: BaseException):
        super().__init__(f"{type(error).__name__}: {error}")
        self.index, self.error = index, error


# -- the run ------------------------------------------------------------------------------------
def run_session(rig, session: Session, *, processor=None,
                progress: ProgressCallback | None = None,
                control: CaptureControl | None = None,
                max_queued: int = 1) -> SessionResult:
    """Acquire and process every capture of ``session`` that is not complete yet.

    ``processor`` (normally :func:`polrig.app.processing.make_processor`'s result) has
    ``after_acquire(session, index, rig)`` (run while the rig is still at the pose: the
    simulated rig's ground truth) and ``process(session, index) -> score dict or None`` (run
    in the worker thread); without one, an acquired capture is complete.

    ``max_queued``: how many acquired captures may wait for or be in processing while the
    next one is acquired (one worker thread processes them in order; a capture is loaded from
    its files when its processing starts, so only that one is in memory). With the default 1
    a capture is handed over once the previous one's processing has ended.

    The session's lock is taken (if this object does not hold it yet; :class:`SessionBusy`
    when another process writes the session) and released when the run ends. In the main
    thread SIGINT and SIGTERM stop the run like Ctrl-C. Returns how the run ended; raises
    ``KeyboardInterrupt`` (:class:`polrig.app.session.Interrupted` for a signal) after leaving
    the session consistent when interrupted, and re-raises a file-system error other than a
    full disk, or an unexpected error (a processing error included), after leaving the
    session interrupted.
    """
    if session.plan.mode == "adaptive" and processor is None:
        raise ValueError("the adaptive mode decides from the network's prior: it needs a processor")
    session.lock()
    try:
        with SignalGuard() as guard:
            return _Run(rig, session, processor, progress, control, guard, max_queued).run()
    finally:
        session.unlock()


class _Run:
    """One :func:`run_session` call: the executor, its subscribers and the worker."""

    def __init__(self, rig, session: Session, processor, progress, control,
                 guard: SignalGuard, max_queued: int = 1):
        if int(max_queued) < 1:
            raise ValueError(f"max_queued must be >= 1, got {max_queued!r}")
        self.max_queued = int(max_queued)
        self.rig, self.session, self.processor = rig, session, processor
        self.progress, self.guard = progress, guard
        self.control = control or CaptureControl()
        self.plan = session.plan
        self.n = len(session.captures)
        #: acquired captures whose raw data no longer verifies: acquired again (their reason)
        self.set_aside = {i: reason for i in session.acquired()
                          if (reason := session.set_aside_damaged(i)) is not None}
        self.to_process = session.acquired()
        self.to_acquire = [i for i in session.next_pending() if i not in self.to_process]
        self.total = len(self.to_acquire) * self.plan.frames_per_pose()
        self.step = 0
        self.current: int | None = None  # the capture being acquired
        self.jobs: list[tuple[int, concurrent.futures.Future]] = []
        self.pool: concurrent.futures.ThreadPoolExecutor | None = None
        self.durations: list[float] = []
        self.hardware_s = self.hardware_left_s = 0.0
        #: the adaptive decision made in the current :meth:`extend`, reported once its steps are counted
        self.decided: dict[str, Any] | None = None
        self.result = SessionResult(RUNNING, [c["index"] for c in session.captures
                                              if c["status"] == COMPLETE], [])

    # -- progress
    def emit(self, kind: str, index: int, message: str = "", score=None,
             result: pathlib.Path | None = None) -> None:
        if self.progress:
            self.progress(Progress(kind, index, self.n, self.step, self.total,
                                   self.session.capture(index)["pose_deg"], message, score,
                                   self.hardware_s, self.hardware_left_s, result))

    # -- the executor's subscribers
    def on_event(self, ev) -> None:
        if isinstance(ev, FrameGrabbed):
            self.write_frame(ev)
        elif isinstance(ev, StepDone):
            self.hardware_left_s = max(0.0, self.hardware_left_s - self.durations[ev.index])
            self.collect(block=False)
        elif isinstance(ev, Retried):
            self.emit("retry", self.current if self.current is not None else 0, ev.message)
        elif isinstance(ev, CheckpointReached):
            index = ev.checkpoint.capture
            if ev.checkpoint.label == "capture-start":
                self.collect(block=False)
                self.session.restart_capture(index)
                self.current = index
                self.emit("capture-start", index)
            elif ev.checkpoint.label == "capture-acquired":
                self.acquired(index)

    def write_frame(self, ev: FrameGrabbed) -> None:
        """The session writer: every frame to disk, checksummed, as it arrives."""
        tag = ev.tag
        cap = self.session.capture(tag.capture)
        image, meta = frame_bytes(ev.frame)
        if tag.role == "dark":
            self.session.add_file(tag.capture, "dark",
                                  dark_relpath(cap["name"], tag.exposure_index, tag.frame),
                                  image, sidecar=meta,
                                  exposure_us=manifest_exposure_us(tag.exposure_us),
                                  exposure_index=tag.exposure_index, frame=tag.frame)
        else:
            self.session.add_file(tag.capture, "raw",
                                  raw_relpath(cap["name"], tag.state_index, tag.state_deg,
                                              tag.exposure_index, tag.frame),
                                  image, sidecar=meta, state_index=tag.state_index,
                                  state_deg=tag.state_deg,
                                  exposure_us=manifest_exposure_us(tag.exposure_us),
                                  exposure_index=tag.exposure_index, frame=tag.frame)
        self.step += 1
        self.emit("frame", tag.capture)

    def acquired(self, index: int) -> None:
        """Every frame of ``index`` is written and the rig is still at its pose: its truth
        (simulated rig), then it is handed to processing."""
        if self.processor is not None:
            self.processor.after_acquire(self.session, index, self.rig)
        self.session.mark_acquired(index)
        self.current = None
        self.emit("capture-acquired", index)
        self.submit(index)

    # -- the processing worker
    def submit(self, index: int) -> None:
        """Hand ``index`` to the worker once the previous capture's processing has ended
        (one capture processed while the next is acquired)."""
        if self.processor is None:
            self.session.complete_capture(index, None)
            self.finished(index, None)
            return
        self.collect(block=True, keep=self.max_queued - 1)
        if self.pool is None:
            self.pool = concurrent.futures.ThreadPoolExecutor(1, "polrig-processing")
        self.jobs.append((index, self.pool.submit(self.process, index)))

    def process(self, index: int) -> dict[str, Any] | None:
        """In the worker: process ``index`` from its raw files and mark it complete."""
        session = self.session
        if set(session.capture(index)["files"]) - set(ACQUISITION_ROLES):
            session.reset_results(index)  # an earlier, interrupted processing's files
        session.discard_unrecorded(index)  # a write a crash cut short (its temporary sibling)
        score = self.processor.process(session, index)
        session.complete_capture(index, score)
        return score

    def collect(self, *, block: bool, keep: int = 0) -> None:
        """Report the captures whose processing ended (when ``block``, wait until at most
        ``keep`` remain); a processing error is raised as :class:`_ProcessingFailed` (the
        capture stays ``acquired`` with the reason)."""
        while len(self.jobs) > keep and (block or self.jobs[0][1].done()):
            index, job = self.jobs[0]  # popped once it ended: a signal may cut the wait short
            try:
                score = job.result()
            except Exception as exc:  # noqa: BLE001 - reported below, in this thread
                self.jobs.pop(0)
                # best effort: on a full disk the manifest on disk says "acquired" already
                with self.guard.deferred(), contextlib.suppress(OSError):
                    self.session.mark_acquired(index, f"processing failed: "
                                                      f"{type(exc).__name__}: {exc}")
                raise _ProcessingFailed(index, exc) from exc
            self.jobs.pop(0)
            self.finished(index, score)

    def finished(self, index: int, score) -> None:
        self.result.completed.append(index)
        if score is not None:
            self.result.scores[index] = score
        with self.session.mutex:  # the worker may be recording the next capture's files
            rec = self.session.capture(index)["files"].get("mueller")
        self.emit("capture-done", index, score=score,
                  result=None if rec is None else self.session.root / rec["path"])

    def drain(self) -> BaseException | None:
        """After an interruption: let the processing under way end, report it; the first
        processing error, if any, is returned."""
        error = None
        while self.jobs:
            try:
                self.collect(block=True)
            except _ProcessingFailed as exc:
                error = error or exc
            except KeyboardInterrupt:  # pragma: no cover - signals are deferred here
                continue
        return error

    # -- the adaptive mode: the plan continues by decisions (polrig.app.adaptive)
    def extend(self) -> list:
        """The executor's ``extend``: the schedule's next steps, with their hardware time; the
        forecast of what is left (hardware time, ETA, frames) follows the decision, which is
        reported after it (its ``"decision"`` event carries the revised forecast)."""
        new = self.schedule.extend()
        self.account(new)
        record, self.decided = self.decided, None
        if record is not None:
            self.decision(record)
        return new

    def account(self, new: list) -> None:
        """Add ``new`` (steps handed to the executor) to the run's hardware time and revise the
        forecast of the steps still to come (:meth:`polrig.app.adaptive.AdaptiveSchedule.forecast`):
        ``hardware_s`` is the time of the steps handed out plus that forecast, ``hardware_left_s``
        keeps the time already run."""
        done_s = self.hardware_s - self.hardware_left_s
        forecast = self.schedule.forecast()
        durations = step_durations(self.handed + new + forecast, self.hardware)
        n = len(self.handed)
        self.durations += durations[n:n + len(new)]  # StepDone indices: the body's steps in turn
        self.handed += new
        self.hardware_s = sum(durations)
        self.hardware_left_s = max(0.0, self.hardware_s - done_s)
        self.total = sum(isinstance(s, Grab) for s in self.handed[len(self.setup):] + forecast)

    # -- the run
    def run(self) -> SessionResult:
        session, plan = self.session, self.plan
        try:
            session.set_status(RUNNING)
            for index, reason in self.set_aside.items():
                self.emit("retry", index, f"capture {index + 1}/{self.n}: {reason}")
            setup, body = [], []
            extend = None
            if self.to_acquire and plan.mode == "adaptive":
                exposures = plan.exposures_us or (float(self.rig.camera.exposure_us),)
                self.setup = setup = setup_steps()
                self.hardware = hardware_model(self.rig)
                memo = PoseMemo()  # what a pose's decisions share (frames, radiances, the network's answer)
                self.schedule = AdaptiveSchedule(
                    plan, self.to_acquire, exposures,
                    lambda i: self.keep_decision(adaptive_decide(session, i, self.processor, memo)))
                self.handed, self.durations = list(setup), []
                body = self.schedule.start()
                self.account(body)
                setup_s = step_durations(setup, self.hardware)
                extend = self.extend
            elif self.to_acquire:
                exposures = plan.exposures_us or (float(self.rig.camera.exposure_us),)
                setup = setup_steps()
                body = [step for i in self.to_acquire
                        for step in capture_steps(plan, i, exposures)]
                durations = step_durations(setup + body, hardware_model(self.rig))
                self.hardware_s = self.hardware_left_s = sum(durations)
                setup_s, self.durations = durations[:len(setup)], durations[len(setup):]
            with session.mutex:
                if session.manifest["hardware_time_s"] is None:  # the first run's estimate
                    session.manifest["hardware_time_s"] = round(self.hardware_s, 3)
                session.log("run planned", to_acquire=self.to_acquire,
                            to_process=self.to_process,
                            hardware_time_s=round(self.hardware_s, 3))
            executor = Executor(self.rig, policy=FaultPolicy(plan.grab_retries),
                                control=self.control, subscribers=[self.on_event])
            for index in self.to_process:  # acquired before: processed, not acquired again
                self.submit(index)
            if body:
                try:
                    for step, seconds in zip(setup, setup_s):
                        executor.execute(step)
                        self.hardware_left_s -= seconds
                except DeviceError as exc:
                    alarm = isinstance(exc, DeviceAlarm)
                    reason = ("rig preparation failed: "
                              + (self.device_reason(exc) if alarm else str(exc)))
                    error = self.drain()
                    with self.guard.deferred():
                        session.set_status(INTERRUPTED, reason)
                    if error is not None:
                        raise error.error
                    return SessionResult(INTERRUPTED, self.result.completed, [],
                                         reason if alarm else str(exc),
                                         self.result.scores)
                executor.run(body, extend)  # StepDone indices count from 0 again: self.durations
            self.collect(block=True)
            with self.guard.deferred():
                session.set_status(SESSION_COMPLETE)
        except (KeyboardInterrupt, StopRequested) as exc:
            reason = (interruption_reason(exc) if isinstance(exc, KeyboardInterrupt)
                      else "stopped by the operator")
            self.stop(reason, PENDING)
            self.report_failed()
            if isinstance(exc, KeyboardInterrupt):
                raise
            return self.result
        except _ProcessingFailed as exc:
            if is_disk_full(exc.error):  # as when acquiring: a result, not an error
                self.stop(f"disk full: {exc.error}", FAILED)
                self.report_failed()
                return self.result
            self.stop(str(exc), PENDING)
            raise exc.error from None
        except (DeviceError, OSError) as exc:
            if isinstance(exc, OSError) and not is_disk_full(exc):
                # any other file-system error (permissions, I/O error, a name too long):
                # leave the session consistent and resumable, then let the caller report it
                self.stop(f"{type(exc).__name__}: {exc}", FAILED)
                raise
            self.stop(self.device_reason(exc), FAILED)
            self.report_failed()
            return self.result
        except Exception as exc:  # a bug or bad data while acquiring: record it, report it
            self.stop(f"{type(exc).__name__}: {exc}", FAILED)
            raise
        finally:
            if self.pool is not None:
                self.pool.shutdown(wait=True)
        self.result.status = SESSION_COMPLETE
        last = self.to_acquire[-1] if self.to_acquire else (self.to_process or [0])[-1]
        self.emit("session-done", last)
        return self.result

    def keep_decision(self, record: dict[str, Any]) -> dict[str, Any]:
        """The schedule's ``decide``: keep the decision for :meth:`extend` to report, return it."""
        self.decided = record
        return record

    def decision(self, record: dict[str, Any]) -> dict[str, Any]:
        """Report an adaptive decision (a ``"decision"`` progress event) and return it."""
        index = self.current if self.current is not None else 0
        self.emit("decision", index, describe_decision(record))
        return record

    def device_reason(self, exc: BaseException) -> str:
        """One line on why a device or the disk stopped the run. A safety fault
        (:class:`polrig.errors.DeviceAlarm`: a limit switch fired, an alarm) names the command
        that clears it, with this rig's file (``polrig home turntable --config RIG``): the
        engine never homes such an axis on its own, the operator does, then resumes."""
        if isinstance(exc, DeviceAlarm):
            return f"safety stop: {exc.operator_message(getattr(self.rig, 'source', None))}"
        kind = "disk full" if is_disk_full(exc) else type(exc).__name__
        return f"{kind}: {exc}"

    def stop(self, reason: str, capture_status: str) -> None:
        """Leave the session consistent after an interruption: processing under way ends
        (signals deferred meanwhile), the capture being acquired is left ``capture_status``
        (``pending`` or ``failed``) without unrecorded files, the session ``interrupted``."""
        with self.guard.deferred():
            error = self.drain()  # another capture's processing may fail meanwhile: say so
            if error is not None:
                reason = f"{reason}; processing of capture {error.index} failed too ({error})"
            index = self.current
            if index is not None:
                _stop_cleanly(self.session, index, reason, capture_status=capture_status)
                if capture_status == FAILED:
                    self.result.failed.append(index)
            else:
                with contextlib.suppress(OSError):
                    self.session.set_status(INTERRUPTED, reason)
            self.result.status, self.result.reason = INTERRUPTED, reason

    def report_failed(self) -> None:
        """The "capture-failed" event of a run that ends with a result (not re-raised)."""
        if self.current is not None:
            with contextlib.suppress(Exception):  # a progress display must not stop the stop
                self.emit("capture-failed", self.current, self.result.reason or "")


def interrupted_result(session: Session, exc: BaseException) -> SessionResult:
    """How a run ended that raised ``exc`` after ``session`` was opened: :func:`run_session`
    re-raises a file-system error other than a full disk and an unexpected error (a
    processing error) after leaving the session ``interrupted``; an error before the run (the
    processor could not be built) leaves it as it was. Either way the session is
    ``interrupted`` with the reason (written here where the run did not), its lock released,
    and the result says so, for the caller to report as any other stop: the completed
    captures are intact and a resume continues (``polrig capture``, the GUI)."""
    reason = f"{type(exc).__name__}: {exc}"
    if session.manifest["status"] == INTERRUPTED:
        reason = session.manifest["status_reason"] or reason
    else:
        with contextlib.suppress(Exception):  # another writer, a failing disk: as it is
            session.lock()
            session.set_status(INTERRUPTED, reason)
    session.unlock()
    done = [c["index"] for c in session.captures if c["status"] == COMPLETE]
    failed = [c["index"] for c in session.captures if c["status"] == FAILED]
    return SessionResult(INTERRUPTED, done, failed, reason)


def _stop_cleanly(session: Session, index: int, reason: str, *, capture_status: str) -> None:
    """Leave the session consistent after a stop: unrecorded files of capture ``index``
    removed, its status set (unless it got complete or acquired meanwhile), session
    ``interrupted`` with ``reason``. Saving may itself fail (a full disk): the manifest on
    disk then still is the last consistent one, which is fine."""
    try:
        session.reload()  # what is on disk is what counts: a failed save may be missing
        session.discard_unrecorded(index)
    except OSError:
        pass
    cap = session.capture(index)
    if cap["status"] in (COMPLETE, ACQUIRED):
        pass  # the interruption came after it was saved as such: keep it
    elif capture_status == FAILED:
        session.fail_capture(index, reason, save=False)
    else:
        cap.update(status=PENDING, reason=reason)
    try:
        session.set_status(INTERRUPTED, reason)
    except OSError:
        pass
