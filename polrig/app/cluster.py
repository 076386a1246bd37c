"""Scale-out on Dask distributed: ``polrig reconstruct`` over many sessions, one task per capture.

Roles (the session's one-writer rule holds):

* **Client** (the ``polrig`` process): takes every session's lock, checks each request
  before anything is recorded (:func:`polrig.app.reconstruct.revision_plan`), creates (or
  continues) each session's revision, submits one :class:`CaptureJob` per capture, and as
  results arrive records them in the manifest (:func:`polrig.app.result_files.record_result`) --
  the only process that writes a ``session.json``.
* **Workers** (:func:`process_job`): open the session read-only from the file system they
  share with the client, read and verify the raw frames themselves (raw data never travels
  through the client), solve (:meth:`polrig.app.processing.Processor.solve`) and write the
  result file under a temporary name in its final folder, then rename it
  (:func:`polrig.app.result_files.write_and_score`, previews included), then score it against
  the simulator's truth if the capture has one; they return the files' records and the score
  (a few hundred bytes).

Faults: a worker that dies mid-task has its task rerun on another worker by Dask (the rerun
writes the same bytes; a temporary file the dead one left is removed by the client when the
batch ends, :func:`discard_leftovers`); a capture whose workers all died (Dask's
``KilledWorker``) is marked ``failed`` with that reason, as is a capture whose data is
damaged (it comes back as a failure with its reason); the batch goes on. A full disk stops
the batch with the captures not recorded ``pending``.
Ctrl-C/SIGTERM cancel the tasks not finished, leave their captures ``pending`` in the
revision and keep the finished ones; running ``polrig reconstruct`` again with the same
settings continues that revision with the captures still pending (:func:`prepare`).

Executors (:class:`Runner`): :class:`SerialRunner` (in-process, the default) and
:class:`DaskRunner` (a ``LocalCluster`` of single-threaded worker processes, or a running
scheduler). ``dask[distributed]`` is the optional ``cluster`` extra
(:func:`require_distributed`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import os
import pathlib
import re
import signal
import threading
import time
import uuid
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence

from polrig.acquisition.plan import ExrChoice
from polrig.app import processing
from polrig.app.reconstruct import mark_revision, revision_plan
from polrig.app.result_files import record_result, write_and_score
from polrig.app.session import (
    FAILED,
    PENDING,
    Session,
    SignalGuard,
    interruption_reason,
    is_disk_full,
)
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.errors import ConfigError, PolrigError

INSTALL_HINT = "pip install 'polrig[cluster]' (or: pip install 'dask[distributed]')"


def require_distributed(option: str):
    """The ``distributed`` module, or :class:`ConfigError` (exit 2) saying how to install
    it when the ``cluster`` extra is missing; ``option`` names what needed it."""
    try:
        import distributed
    except ImportError:
        raise ConfigError(f"{option} needs Dask distributed, which is not installed; install "
                          f"the cluster extra: {INSTALL_HINT}") from None
    return distributed


# -- executors ---------------------------------------------------------------------------------
class Runner(Protocol):
    """Runs ``fn(job)`` for every job and yields ``(job, result)`` as each finishes (any
    order). Leaving the iteration early (an exception, Ctrl-C) cancels what has not run.
    ``lost(job, reason)``, where given, is the result of a job whose worker processes all
    died while running it (:class:`TaskLost` is raised without it)."""

    description: str
    #: A line for the operator before the batch starts, or None (an external scheduler's
    #: address and workers: with none yet, the tasks wait silently for one to join).
    notice: str | None

    def map_unordered(self, fn: Callable[[Any], Any], jobs: Sequence[Any],
                      lost: Callable[[Any, str], Any] | None = None
                      ) -> Iterator[tuple[Any, Any]]: ...

    def close(self) -> None: ...


class SerialRunner:
    """In this process, one job after the other, in order (the default of every command)."""

    description = "serial (this process)"
    notice = None

    def map_unordered(self, fn, jobs, lost=None):
        for job in jobs:  # no worker to lose: ``lost`` is never called
            yield job, fn(job)

    def close(self) -> None:
        pass


class TaskLost(PolrigError):
    """A task whose worker processes all died while running it (Dask's ``KilledWorker``, once
    ``distributed.scheduler.allowed-failures`` reruns are spent); one line."""


class SchedulerLost(PolrigError):
    """The Dask scheduler dropped the batch's tasks mid-batch (it stopped, the network went,
    someone restarted it); one line. What finished is kept; the same command again continues."""


#: Seconds the Dask client and the local cluster each get to close (:meth:`DaskRunner.close`).
CLOSE_TIMEOUT_S = 20.0


class InterruptedSyncFilter(logging.Filter):
    """Drops the one traceback Dask's client logs on a Ctrl-C that arrives before the call it
    waits on has started: ``distributed.utils.sync`` schedules its ``cancel`` callback, which
    reads the call's future before it is assigned (a ``NameError``, logged by Tornado's
    ``tornado.application`` logger on the client's event-loop thread; distributed 2026.8). The
    interrupt itself is handled as every Ctrl-C is (:func:`run_batch`): this only keeps the
    operator's terminal to polrig's one line. Every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, NameError):
            return True
        tb = exc.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        if tb is None:
            return True
        code = tb.tb_frame.f_code
        return not (code.co_name == "cancel"
                    and pathlib.PurePath(code.co_filename).parts[-2:] == ("distributed", "utils.py"))


def filter_interrupted_sync() -> None:
    """Put :class:`InterruptedSyncFilter` on Tornado's ``tornado.application`` logger (once)."""
    log = logging.getLogger("tornado.application")
    if not any(isinstance(f, InterruptedSyncFilter) for f in log.filters):
        log.addFilter(InterruptedSyncFilter())


class DaskRunner:
    """Jobs as Dask tasks (``pure=False``: each runs once per submission; Dask reruns a task
    whose worker died, up to ``distributed.scheduler.allowed-failures`` times). Build it with
    :meth:`local` or :meth:`connect`."""

    def __init__(self, client, cluster=None, description: str = "dask", notice: str | None = None):
        self.client, self.cluster, self.description, self.notice = client, cluster, description, notice
        filter_interrupted_sync()

    @classmethod
    def local(cls, n_workers: int) -> "DaskRunner":
        """A ``LocalCluster`` of ``n_workers`` worker processes with one thread each, on the
        loopback interface (the scheduler's HTTP server too, on a free port: it always starts
        one, and 8787 may be taken); Dask's nanny sets ``OMP_NUM_THREADS`` and friends to 1 in
        each worker (``distributed.nanny.pre-spawn-environ``)."""
        require_distributed("--workers")
        from distributed import Client, LocalCluster

        from polrig.app.dask_plugins import TerminalInterruptIgnored

        if n_workers < 1:
            raise ConfigError(f"--workers {n_workers}: need at least 1")
        cluster = client = None
        try:
            with terminal_interrupt_held():
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1,
                                       processes=True, host="127.0.0.1",
                                       dashboard_address="127.0.0.1:0",
                                       silence_logs=logging.ERROR)
                client = Client(cluster)
                client.register_plugin(TerminalInterruptIgnored())
        except BaseException:  # a Ctrl-C held through the start arrives here, once started
            cls(client, cluster).close()  # what was started (``close`` passes over a None)
            raise
        return cls(client, cluster, f"{n_workers} local worker process(es), 1 thread each")

    @classmethod
    def connect(cls, address: str, timeout: float | str | None = None) -> "DaskRunner":
        """A client of the running scheduler at ``address`` (``tcp://host:8786``);
        :class:`ConfigError` (one line, exit 2) if it cannot be reached within ``timeout``
        (default: Dask's ``distributed.comm.timeouts.connect``)."""
        require_distributed("--scheduler")
        import dask
        from distributed import Client

        timeout = timeout or dask.config.get("distributed.comm.timeouts.connect")
        try:
            client = Client(address, timeout=timeout)
        except (OSError, ValueError, TypeError) as exc:  # TimeoutError is an OSError
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ConfigError(f"--scheduler {address}: cannot reach the Dask scheduler "
                              f"({why}); start it with 'dask scheduler' or check the "
                              f"address") from None
        n = len(client.scheduler_info().get("workers", {}))
        now = (f"{n} worker(s) now" if n else
               "no worker yet: the tasks wait until one joins, e.g. 'dask worker ADDRESS'")
        description = f"scheduler {address} ({now})"
        return cls(client, None, description, notice=f"on {description}")

    def map_unordered(self, fn, jobs, lost=None):
        """:meth:`Runner.map_unordered` as Dask tasks. A task Dask gave up on because its
        workers died (``KilledWorker``) is ``lost(job, reason)``, or :class:`TaskLost`
        without ``lost``; a lost scheduler is :class:`SchedulerLost` (one line each, not
        Dask's traceback)."""
        from distributed import KilledWorker, as_completed
        from distributed.client import FutureCancelledError

        tag = uuid.uuid4().hex[:8]
        futures = {self.client.submit(one_core, fn, job, key=f"{fn.__name__}-{tag}-{i}",
                                      pure=False): job
                   for i, job in enumerate(jobs)}
        try:
            for fut in as_completed(list(futures)):
                job = futures[fut]
                try:
                    result = fut.result()
                except KilledWorker as exc:
                    why = (f"KilledWorker: the worker process running it died "
                           f"{exc.allowed_failures + 1} time(s) (killed, or out of memory?)")
                    if lost is None:
                        raise TaskLost(f"task {fut.key}: {why}") from None
                    result = lost(job, why)
                except FutureCancelledError as exc:  # not ours: we cancel only after leaving
                    raise SchedulerLost(f"the Dask scheduler dropped the batch's tasks "
                                        f"({exc.reason}); what finished is kept: run the "
                                        f"same command again to continue") from None
                yield job, result
        finally:  # early exit: pending tasks are cancelled (finished ones just released)
            with contextlib.suppress(Exception):
                self.client.cancel(list(futures))

    def close(self) -> None:
        """Close the client, then the local cluster, each within :data:`CLOSE_TIMEOUT_S` (a
        Ctrl-C must end the command: a worker busy in a long task can hold Dask's default
        close for minutes; its process is then left to the nanny's own shutdown)."""
        with contextlib.suppress(Exception):
            self.client.close(timeout=CLOSE_TIMEOUT_S)
        if self.cluster is not None:
            with contextlib.suppress(Exception):
                self.cluster.close(timeout=CLOSE_TIMEOUT_S)


@contextlib.contextmanager
def terminal_interrupt_held() -> Iterator[None]:
    """A SIGINT (Ctrl-C) during the block is held, and acted on as the block ends; processes
    started meanwhile never see one.

    For the start of a local cluster: its worker processes share the terminal's process
    group, so a Ctrl-C in the seconds they take to start reached each of them half-started,
    and they and their nannies printed tracebacks ("Nanny failed to start") over
    ``polrig``'s one line. Here SIGINT is blocked in this thread, and a thread or process
    started from it inherits the block (``pthread_sigmask(3)``; ``execve(2)`` keeps the mask),
    so the workers spawned never get it; one delivered meanwhile to a thread that does not
    block it (a numerical library's own threads) is recorded, not raised. As the block ends,
    the previous handler is back and the signal is delivered to it, once the cluster is up
    and can be closed cleanly (about 2 s for a few local workers).

    Main thread with a Python-level SIGINT handler only (elsewhere, or when SIGINT is
    ignored, a plain block). SIGTERM is not held: the nanny stops its worker with it.
    ``multiprocessing``'s resource tracker is started first: starting it unblocks SIGINT in
    the starting thread (CPython ``Lib/multiprocessing/resource_tracker.py``,
    ``ensure_running``), which would lift the block for the threads started after it."""
    handler = signal.getsignal(signal.SIGINT)
    if (not hasattr(signal, "pthread_sigmask") or handler in (signal.SIG_IGN, None)
            or threading.current_thread() is not threading.main_thread()):
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    held: list[int] = []
    signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a pending one reaches ``handler`` here
        if held:
            signal.raise_signal(signal.SIGINT)


def one_core(fn: Callable[[Any], Any], job: Any) -> Any:
    """``fn(job)`` on one core: OpenCV's own thread pool (the demosaics' filters) limited to
    one thread in this worker process, as the nanny limits OpenMP/BLAS
    (``distributed.nanny.pre-spawn-environ``); a task is one core's work."""
    import cv2

    cv2.setNumThreads(1)
    return fn(job)


def open_runner(workers: int | None, scheduler: str | None) -> Runner:
    """The runner that ``--workers N`` / ``--scheduler ADDRESS`` ask for (serial without
    either; both is a :class:`ConfigError`)."""
    if workers is not None and scheduler is not None:
        raise ConfigError("--workers and --scheduler exclude each other")
    if scheduler is not None:
        return DaskRunner.connect(scheduler)
    if workers is not None:
        return DaskRunner.local(workers)
    return SerialRunner()


# -- one capture, on a worker --------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CaptureJob:
    """One task: capture ``index`` of the session in ``root`` (an absolute path the workers
    see too) into ``revision`` with the revision's settings; ``device`` where a single-shot
    network runs on the worker (``auto``, ``cpu``, ``cuda``); ``calibration`` is the
    calibration set's folder (absolute) or ``None`` for the nominal one."""

    root: str
    index: int
    revision: str
    mode: str
    demosaic: str
    mirror_average: bool
    resolution: str
    device: str
    calibration: str | None
    calibration_id: str
    exr_planes: tuple[str, ...]
    exr_uncertainty: str
    exr_compression: str
    #: single-shot network binning (1 or 2: :class:`polrig.app.processing.Processor`)
    network_binning: int = 1
    #: hybrid: the index of the state whose frame the network sees
    seen_state: int = 0
    #: which shipped single-shot model (``auto``, ``small``, ``large``: :mod:`polrig.models.sizes`)
    model_size: str = "auto"
    #: ``full`` or ``auto``: lower-order models per pixel (:mod:`polrig.solve.model_selection`)
    models: str = "full"
    #: hybrid: the prior's scale, ``innovations`` or ``calibrated`` (:class:`polrig.app.processing.Processor`)
    prior_scale: str = DEFAULT_PRIOR_SCALE

    @property
    def exr(self):
        """The result files' format (:class:`polrig.acquisition.plan.ExrChoice`)."""

        return ExrChoice(self.exr_planes, self.exr_uncertainty, self.exr_compression)


@dataclasses.dataclass(frozen=True)
class CaptureOutcome:
    """What a worker sends back: the written files' ``record`` s by role (``mueller`` and its
    previews: ``path``, ``sha256``, ``bytes``) and ``score``, or the ``reason`` it failed
    (``disk_full`` for a full disk); ``seconds`` the time the task took on the worker."""

    record: dict[str, dict[str, Any]] | None
    score: dict[str, Any] | None
    reason: str | None
    disk_full: bool
    seconds: float
    #: a hybrid result's prior model (:class:`polrig.app.manifest.PriorRecord`)
    prior: dict[str, Any] | None = None
    #: a single-shot or hybrid result's network model (:class:`polrig.app.manifest.ModelRecord`)
    model: dict[str, Any] | None = None


_PROCESSORS: dict[tuple, Any] = {}  # per worker process: settings -> Processor


def _processor(job: CaptureJob, session: Session):
    """The worker's :class:`polrig.app.processing.Processor` for ``job`` (made once per settings
    and session noise model: a single-shot network is loaded once per worker)."""

    sensor = processing.session_sensor_model(session)
    key = (job.mode, job.demosaic, job.mirror_average, job.resolution, job.network_binning,
           job.seen_state, job.device, job.model_size, job.calibration, job.calibration_id, repr(sensor), job.exr,
           job.models, job.prior_scale)
    if key not in _PROCESSORS:
        cal = processing.load_calibration(job.calibration)
        if cal.id != job.calibration_id:
            raise ConfigError(f"{job.calibration}: calibration set {cal.id!r} on this worker, "
                              f"the client loaded {job.calibration_id!r} (changed meanwhile?)")
        _PROCESSORS[key] = processing.Processor(job.mode, job.demosaic, cal, sensor,
                                                job.mirror_average, job.resolution, job.device,
                                                job.exr, job.network_binning, job.seen_state,
                                                job.model_size, job.models, prior_scale=job.prior_scale)
    return _PROCESSORS[key]


def process_job(job: CaptureJob) -> CaptureOutcome:
    """The task: solve one capture from its raw files and write its result file. Never
    writes the manifest. A failure (damaged raw data, a full disk...) is returned with its
    reason, not raised, so the client marks that capture and goes on."""
    t0 = time.perf_counter()
    try:
        session = Session.open(job.root)  # read-only: the client holds the lock and writes
        proc = _processor(job, session)
        # a file already there is a result the manifest does not record (the client only
        # submits captures not complete in the revision): the unrecorded output of an attempt
        # that died before the client heard of it, replaced by this one's identical bytes
        out = proc.solve(session, job.index, job.revision)
        prior, model = out.prior, out.model
        record, score = write_and_score(session.root, out, proc.exr, replace=True)
    except Exception as exc:
        return CaptureOutcome(None, None, f"{type(exc).__name__}: {exc}", is_disk_full(exc),
                              time.perf_counter() - t0)
    return CaptureOutcome(record, score, None, False, time.perf_counter() - t0, prior, model)


# -- the client ----------------------------------------------------------------------------------
@dataclasses.dataclass
class SessionBatch:
    """One session's part of a batch: its revision (new or ``continued``), the captures
    submitted and those that ``failed`` (``(index, reason)``); ``device`` where single-shot
    networks run (not a setting of the result)."""

    session: Session
    revision: str
    settings: dict[str, Any]
    todo: list[int]
    device: str = "auto"
    continued: bool = False
    model_size: str = "auto"
    failed: list[tuple[int, str]] = dataclasses.field(default_factory=list)
    finished: int = 0


class BatchIncomplete(PolrigError):
    """Captures of some sessions failed (the others are complete); one line per session in
    :attr:`lines`, the message sums them up."""

    def __init__(self, batches: Sequence[SessionBatch]):
        self.batches = list(batches)
        bad = [b for b in batches if b.failed]
        self.lines = [f"{b.session.root}: revision {b.revision}: {len(b.failed)} of "
                      f"{len(b.todo)} capture(s) failed: " +
                      "; ".join(f"capture {i} ({b.session.capture(i)['name']}): {r}"
                                for i, r in b.failed) for b in bad]
        n = sum(len(b.failed) for b in bad)
        super().__init__(f"{n} capture(s) failed in {len(bad)} of {len(batches)} session(s) "
                         f"(" + ", ".join(f"{b.session.root.name} {b.revision}: "
                                          f"{len(b.failed)}" for b in bad) +
                         "); the others are complete")


def _continuable(session: Session, settings: dict[str, Any], done: list[int]
                 ) -> tuple[str, list[int]] | None:
    """The session's last revision and its captures still to do, when it was made with
    ``settings`` and was interrupted (captures of ``done`` pending or missing in it)."""
    revisions = session.manifest["revisions"]
    if not revisions:
        return None
    last = revisions[-1]
    # a revision made before a setting existed has the value it was made with: models full, the
    # prior's sigma as calibrated
    before = {"models": "full", "prior_scale": "calibrated"}
    if any(last.get(k, before.get(k)) != v for k, v in settings.items()):
        return None
    name = last["name"]
    todo = [i for i in done
            if session.capture(i)["revisions"].get(name, {}).get("status", PENDING) == PENDING]
    return (name, todo) if todo else None


def open_sessions(paths: Iterable[str | os.PathLike]) -> list[Session]:
    """Open every session for writing (each one's lock taken; all released again if one is
    busy or damaged). Duplicates are refused."""
    sessions: list[Session] = []
    seen: set[pathlib.Path] = set()
    try:
        for p in paths:
            real = pathlib.Path(p).resolve()
            if real in seen:
                raise ConfigError(f"{p}: session named twice")
            seen.add(real)
            sessions.append(Session.open(real, lock=True))
    except BaseException:
        for s in sessions:
            s.unlock()
        raise
    return sessions


def prepare(sessions: Sequence[Session], *, mode: str | None = None, demosaic: str | None = None,
            mirror_average: bool | None = None, resolution: str | None = None,
            device: str = "auto", calibration=None,
            command_line: list[str] | None = None,
            exr: dict[str, Any] | None = None,
            network_binning: int | None = None, seen_state: int | None = None,
            model_size: str = "auto", models: str | None = None,
            prior_scale: str | None = None) -> list[SessionBatch]:
    """Check every session's request first (:func:`polrig.app.reconstruct.revision_plan`: nothing
    is recorded if one is impossible), then give each a revision: the last one continued when
    it has the same settings and captures still ``pending`` (an interrupted batch), else a
    new one. Leftover files of earlier attempts in the revision's folders are removed."""

    plans = [revision_plan(s, mode, demosaic, mirror_average, calibration, resolution, device, exr,
                           network_binning, seen_state, model_size, models,
                           prior_scale or DEFAULT_PRIOR_SCALE)
             for s in sessions]
    batches = []
    for s, (settings, _processor_unused, done) in zip(sessions, plans):
        cont = _continuable(s, settings, done)
        if cont is not None:
            name, todo = cont
            s.log("revision continued", revision=name, command_line=list(command_line or []))
        else:
            name, todo = s.new_revision(settings, command_line), list(done)
        for i in todo:
            s.start_revision(i, name)
        s.save()
        batch = SessionBatch(s, name, settings, todo, device, continued=cont is not None,
                             model_size=model_size)
        discard_leftovers(batch)
        batches.append(batch)
    return batches


def jobs_of(batch: SessionBatch, calibration_path: str | None) -> list[CaptureJob]:
    st = batch.settings
    cal = None if calibration_path is None else str(pathlib.Path(calibration_path).resolve())
    return [CaptureJob(str(batch.session.root.resolve()), i, batch.revision, st["mode"],
                       st["demosaic"], bool(st["mirror_average"]), st["resolution"],
                       batch.device, cal, st["calibration_id"], tuple(st["exr_planes"]),
                       st["exr_uncertainty"], st["exr_compression"], st["network_binning"],
                       st.get("seen_state", 0), batch.model_size,
                       st.get("models", "full"), st.get("prior_scale", "calibrated"))
            for i in batch.todo]


def discard_leftovers(batch: SessionBatch) -> list[pathlib.Path]:
    """Remove files in the revision folders of ``batch``'s captures that the manifest does
    not record (temporary files of a worker killed mid-write, a result whose task was
    cancelled after it wrote), and such folders left empty. Returns the files removed."""
    s = batch.session
    recorded = s.recorded_paths()
    removed = []
    for i in batch.todo:
        folder = s.capture_dir(i) / batch.revision
        if not folder.is_dir():
            continue
        for p in sorted(folder.rglob("*"), reverse=True):
            if p.is_file() and s.relpath(p) not in recorded:
                p.unlink()
                removed.append(p)
        for d in sorted((d for d in folder.rglob("*") if d.is_dir()), reverse=True) + [folder]:
            with contextlib.suppress(OSError):
                d.rmdir()  # only empty ones go
    return removed


def run_batch(batches: Sequence[SessionBatch], runner: Runner, *,
              calibration_path: str | None = None,
              on_capture: Callable[[SessionBatch, int, dict | None, str | None], None]
              | None = None) -> None:
    """Run every batch's captures on ``runner`` and record each result as it arrives
    (``on_capture(batch, index, score, reason)`` after each: ``reason`` is ``None`` for
    success). Raises :class:`BatchIncomplete` at the end if captures failed (a capture whose
    workers all died is one); a full disk stops the batch (``OSError`` ``ENOSPC``) and
    Ctrl-C/SIGTERM (``KeyboardInterrupt``) cancel what is not finished: the captures not
    recorded stay ``pending`` with the reason, for the same command to continue them.
    Temporary and unrecorded files in the revisions' folders are removed whatever way it
    ends (after ``runner.close()``, which the caller may not have done: call
    :meth:`Runner.close` first if it should be)."""

    by_key = {}
    jobs: list[CaptureJob] = []
    for b in batches:
        for job in jobs_of(b, calibration_path):
            by_key[(job.root, job.index)] = b
            jobs.append(job)
    try:
        with SignalGuard() as guard:
            try:
                for job, out in runner.map_unordered(process_job, jobs, lost=_lost_outcome):
                    b = by_key[(job.root, job.index)]
                    with guard.deferred():
                        b.finished += 1
                        if out.reason is None:
                            record_result(b.session, job.index, job.revision, out.record,
                                          out.score, job.exr, out.prior, out.model,
                                          job.models != "full")
                        elif out.disk_full:  # the batch stops: this and the unfinished stay
                            # pending, and the same command continues them once there is room
                            _leave_pending(batches, f"batch stopped by a full disk: {out.reason}")
                        else:
                            mark_revision(b.session, job.index, job.revision, FAILED,
                                          out.reason)
                            b.failed.append((job.index, out.reason))
                    if on_capture:
                        on_capture(b, job.index, out.score, out.reason)
                    if out.disk_full:
                        raise OSError(errno.ENOSPC, f"{b.session.root}: disk full while "
                                                    f"writing capture {job.index}'s result "
                                                    f"({out.reason}); free some space, then run "
                                                    f"the same command again to continue")
            except KeyboardInterrupt as exc:
                with guard.deferred():
                    runner.close()  # local workers stop before their leftovers are removed
                    _leave_pending(batches, interruption_reason(exc))
                raise
    finally:
        for b in batches:
            with contextlib.suppress(OSError):
                discard_leftovers(b)
    if any(b.failed for b in batches):
        raise BatchIncomplete(batches)


def _lost_outcome(job: CaptureJob, reason: str) -> CaptureOutcome:
    """A capture whose task Dask gave up on (its workers died): a failure with ``reason``."""
    return CaptureOutcome(None, None, reason, False, 0.0)


def _leave_pending(batches: Sequence[SessionBatch], reason: str) -> None:
    """Give the captures not finished their interruption ``reason`` (status stays
    ``pending``), one manifest save per session."""
    for b in batches:
        s = b.session
        changed = False
        for i in b.todo:
            entry = s.capture(i)["revisions"].get(b.revision)
            if entry is not None and entry.get("status") == PENDING:
                entry["reason"] = reason
                changed = True
        if changed:
            with contextlib.suppress(OSError):
                s.save()


def reconstruct(paths: Sequence[str | os.PathLike], runner: Runner, *, mode=None, demosaic=None,
                mirror_average=None, resolution=None, device: str = "auto", model_size: str = "auto",
                network_binning: int | None = None, seen_state: int | None = None,
                models: str | None = None, prior_scale: str | None = None,
                calibration_path: str | None = None, exr: dict[str, Any] | None = None,
                command_line: list[str] | None = None,
                on_start: Callable[[list[SessionBatch]], None] | None = None,
                on_capture=None) -> list[SessionBatch]:
    """``polrig reconstruct SESSION...`` on ``runner`` (:func:`open_runner`): every session
    opened and locked, checked (:func:`prepare`), its captures run (:func:`run_batch`),
    locks released. ``exr``: the result files' format (fields of
    :class:`polrig.acquisition.plan.ExrChoice`; ``None`` values: each session's). ``on_start(batches)``
    is called once the revisions exist (a progress bar's total). Returns the batches; :class:`BatchIncomplete` if captures failed."""

    calibration = processing.load_calibration(calibration_path)
    sessions = open_sessions(paths)
    try:
        batches = prepare(sessions, mode=mode, demosaic=demosaic, mirror_average=mirror_average,
                          resolution=resolution, device=device, calibration=calibration,
                          network_binning=network_binning, seen_state=seen_state,
                          command_line=command_line, exr=exr, model_size=model_size,
                          models=models, prior_scale=prior_scale)
        if on_start:
            on_start(batches)
        run_batch(batches, runner, calibration_path=calibration_path, on_capture=on_capture)
        return batches
    finally:
        for s in sessions:
            s.unlock()


#: A list file's comment: from a ``#`` at the line's start or after white space to the line's end.
_COMMENT = re.compile(r"(^|\s)#.*$")


def read_session_list(path: str | os.PathLike) -> list[str]:
    """Session folders listed in a text file, one per line; relative paths are relative to the
    list's folder. A ``#`` at the start of a line or after a space or tab starts a comment (a
    ``#`` inside a path, ``runs/a#2``, is part of it); blank lines are skipped."""
    p = pathlib.Path(path)
    try:
        text = p.read_text("utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"--from-list {p}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--from-list {p}: cannot read it ({exc})") from None
    out = []
    for line in text.splitlines():
        line = _COMMENT.sub("", line).strip()
        if not line:
            continue
        q = pathlib.Path(line)
        out.append(str(q if q.is_absolute() else p.parent / q))
    if not out:
        raise ConfigError(f"--from-list {p}: lists no session")
    return out
