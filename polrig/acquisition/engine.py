"""The acquisition engine: one :class:`Executor` runs device steps (:mod:`polrig.acquisition.plan`) on a
rig with one fault policy and tells its subscribers what happened through typed events.

Split as in bluesky (plans are data, a run engine executes them) and pymmcore-plus (an MDA
runner drives an engine that owns the device calls): a plan never touches a device; the
executor never knows what a session or a result is; the session writer, the processor and
the progress display are subscribers (:mod:`polrig.app.capture`).

Fault policy (:class:`FaultPolicy`, the one place it lives; captures and calibration
procedures use it alike, the latter through :class:`GuardedRig`):

* a grab that times out is retried ``grab_retries`` times (a timed-out software-triggered
  grab delivered nothing: grabbing again loses nothing); its timeout is the camera's current
  exposure plus readout plus a margin (:func:`polrig.acquisition.hal.grab_timeout_s`);
* a camera setting or light switch that times out is retried as often (setting a value
  again is idempotent);
* a move that times out, faults or gets a garbled reply (:class:`ProtocolError`: line noise
  leaves the position unknown) is retried once after stopping and homing the axis (homing is
  the documented recovery of the ELL14/K10CR1 stages and loses no data; the stop comes first
  because a home sent while the axis still runs is refused, ELL14 ``busy``, GRBL ``Not
  idle``); a second failure is raised; if the stop or the home fails, the move's failure is
  raised with the recovery's reason (an error of the move failure's type; a safety fault or a
  disconnection met on the way is raised as itself); a disconnection is never retried. Each
  move's timeout comes from its axis's
  :meth:`polrig.acquisition.hal.RotationStage.calculate_timeout` for the distance it has to go;
* a safety fault (:class:`polrig.errors.DeviceAlarm`: a limit switch fired, a soft limit, a
  controller locked in its alarm state, issue 33 item 5) is never retried and the axis is
  never homed on its own: a limit switch that fired means something may be in the way. The
  other axes of the move are let finish (nothing is left moving unattended), nothing else
  is started, and the alarm is raised; its message names the command that clears it
  (``polrig home turntable``), which the operator runs once the cause is cleared;
* axes named in one :class:`polrig.acquisition.plan.Move` are started together (``wait=False``) and then
  waited on, each with its own timeout;
* in free run (a camera without software trigger) the first
  :attr:`polrig.acquisition.hal.CameraCapabilities.settle_frames` frames after a setting change, a light
  switch or a move are discarded: they may have been exposed before it.

Pause and stop: :class:`CaptureControl` is checked at every :class:`polrig.acquisition.plan.Checkpoint`,
before every move and before every grab (:class:`StopRequested` ends the run there).
"""

from __future__ import annotations

import dataclasses
import math
import threading
from typing import Any, Callable, Iterable, Sequence, Union

from polrig.acquisition.hal import (
    Camera,
    CameraCapabilities,
    Light,
    RigTruth,
    RotationStage,
    grab_timeout_s,
    motion_timeout_s,
    stopped_when_interrupted,
)
from polrig.acquisition.plan import (
    Checkpoint,
    FrameTag,
    Grab,
    HardwareModel,
    Home,
    Move,
    SetExposure,
    SetLight,
    SetTrigger,
    Step,
)
from polrig.errors import (
    DeviceAlarm,
    DeviceDisconnected,
    DeviceError,
    DeviceFault,
    DeviceTimeout,
    ProtocolError,
)
from polrig.sensor.frame import Frame

#: Errors after which a move is retried once, after homing the axis (but never a
#: :class:`DeviceAlarm`, a safety fault, nor a :class:`DeviceDisconnected`).
MOVE_RECOVERABLE = (DeviceTimeout, DeviceFault, ProtocolError)
#: Errors never retried: they stop the run and are reported.
NEVER_RETRIED = (DeviceDisconnected, DeviceAlarm)


# -- control ------------------------------------------------------------------------------------
class StopRequested(Exception):
    """Raised by :meth:`CaptureControl.checkpoint` when a stop was requested."""


@dataclasses.dataclass
class CaptureControl:
    """Pause/stop requests from another thread (the GUI), honoured at checkpoints."""

    pause: threading.Event = dataclasses.field(default_factory=threading.Event)
    stop: threading.Event = dataclasses.field(default_factory=threading.Event)
    poll_s: float = 0.05

    def checkpoint(self) -> None:
        """Block while paused; raise :class:`StopRequested` when stop is set."""
        while self.pause.is_set() and not self.stop.is_set():
            self.stop.wait(self.poll_s)
        if self.stop.is_set():
            raise StopRequested("stopped by the operator")


# -- events -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FrameGrabbed:
    """A kept frame (settle frames are not reported) and where it belongs."""

    tag: FrameTag
    frame: Frame


@dataclasses.dataclass(frozen=True)
class Retried:
    """A device call failed and is being retried (the policy's message says how)."""

    message: str


@dataclasses.dataclass(frozen=True)
class CheckpointReached:
    checkpoint: Checkpoint


@dataclasses.dataclass(frozen=True)
class StepDone:
    """Step ``index`` of the list given to :meth:`Executor.run` is done."""

    index: int
    step: Step


Event = Union[FrameGrabbed, Retried, CheckpointReached, StepDone]
Subscriber = Callable[[Event], None]


# -- the policy ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FaultPolicy:
    """How often a timed-out grab or setting is retried (a move is retried once, after
    homing)."""

    grab_retries: int = 3

    def __post_init__(self) -> None:
        if int(self.grab_retries) < 0:
            raise ValueError(f"grab_retries must be >= 0, got {self.grab_retries!r}")


class Executor:
    """Runs steps on ``rig`` (its ``camera``, ``stage``, ``turntable``, ``light``) under
    ``policy``; every event goes to each subscriber in turn, in the calling thread (an
    exception in a subscriber ends the run: a failed write stops the capture)."""

    def __init__(self, rig, *, policy: FaultPolicy = FaultPolicy(),
                 control: CaptureControl | None = None,
                 subscribers: Iterable[Subscriber] = ()):
        self.rig = rig
        self.policy = policy
        self.control = control or CaptureControl()
        self.subscribers: list[Subscriber] = list(subscribers)
        self.trigger: str | None = None  # the mode this executor set (None: not set yet)
        self._unsettled = True

    # -- running steps
    def subscribe(self, subscriber: Subscriber) -> None:
        self.subscribers.append(subscriber)

    def emit(self, event: Event) -> None:
        for subscriber in self.subscribers:
            subscriber(event)

    def run(self, steps: Iterable[Step],
            extend: Callable[[], Sequence[Step]] | None = None) -> None:
        """Execute ``steps`` in order, emitting :class:`StepDone` after each (``index`` counts
        every step of this call).

        ``extend``: where the plan continues by a decision on the data (the adaptive capture,
        :mod:`polrig.app.adaptive`): called whenever the steps run out (after the last one's
        events, so a subscriber has written its frames), it returns the next steps, ``[]`` to
        end. The executor knows nothing of the decision; each step it gets runs under the one
        fault policy like any other."""
        index = 0
        pending: Iterable[Step] = steps
        while True:
            for step in pending:
                self.execute(step)
                self.emit(StepDone(index, step))
                index += 1
            if extend is None:
                return
            pending = list(extend())
            if not pending:
                return

    def execute(self, step: Step) -> None:
        """Execute one step under the fault policy."""
        if isinstance(step, Checkpoint):
            self.control.checkpoint()
            self.emit(CheckpointReached(step))
        elif isinstance(step, Grab):
            self.control.checkpoint()
            self.emit(FrameGrabbed(step.tag, self.grab()))
        elif isinstance(step, Move):
            self.control.checkpoint()
            self.move(dict(step.targets))
        elif isinstance(step, SetExposure):
            self.set_exposure(step.exposure_us)
        elif isinstance(step, SetLight):
            self.set_light(step.on)
        elif isinstance(step, Home):
            self.home(step.axis)
        elif isinstance(step, SetTrigger):
            self.set_trigger(step.mode)
        else:  # pragma: no cover - a new step type without its handler
            raise TypeError(f"unknown step {step!r}")

    # -- device operations under the policy (also used by GuardedRig)
    def retried(self, what: str, call: Callable[[], Any]) -> Any:
        """``call()``, a :class:`DeviceTimeout` retried ``grab_retries`` times."""
        retries = int(self.policy.grab_retries)
        for attempt in range(retries + 1):
            try:
                return call()
            except DeviceTimeout as exc:
                if attempt == retries:
                    raise DeviceTimeout(f"{what} timed out {retries + 1} times: {exc}") from exc
                self.emit(Retried(f"{what} timed out ({exc}); retry {attempt + 1}/{retries}"))
        raise AssertionError("unreachable")  # pragma: no cover

    def grab(self) -> Frame:
        """One kept frame, after discarding the free-run settle frames where due."""
        camera: Camera = self.rig.camera
        if self.trigger == "free" and self._unsettled:
            for _ in range(int(camera.capabilities.settle_frames)):
                self._grab_once(camera)
        frame = self._grab_once(camera)
        self._unsettled = False
        return frame

    def _grab_once(self, camera: Camera) -> Frame:
        return self.retried("camera grab", lambda: camera.grab(timeout_s=grab_timeout_s(camera)))

    def set_exposure(self, exposure_us: float) -> None:
        """Set the exposure (nothing when it is set already: no settle frames needed; a
        camera without exposure control reports NaN, and NaN asked of it is no change)."""
        camera: Camera = self.rig.camera
        current, target = float(camera.exposure_us), float(exposure_us)
        if current == target or (math.isnan(current) and math.isnan(target)):
            return
        self.retried("camera setting", lambda: camera.set_exposure_us(float(exposure_us)))
        self._unsettled = True

    def set_camera(self, what: str, call: Callable[[], Any]) -> Any:
        """Any other camera setting (``call`` applies it): retried, then frames settle."""
        out = self.retried(what, call)
        self._unsettled = True
        return out

    def set_trigger(self, mode: str | None = None) -> None:
        """The trigger mode ``mode`` (``None``: the camera's preferred one)."""
        camera: Camera = self.rig.camera
        caps: CameraCapabilities = camera.capabilities
        chosen = caps.preferred_trigger if mode is None else mode
        self.retried("camera setting", lambda: camera.set_trigger(chosen))
        self.trigger = chosen
        self._unsettled = True

    def set_light(self, on: bool) -> None:
        light: Light = self.rig.light
        self.retried("light switch", lambda: light.set_on(bool(on)))
        self._unsettled = True

    def axis(self, name: str) -> RotationStage:
        """The rig's axis called ``name`` (``"stage"`` or ``"turntable"``)."""
        return self.rig.devices[name]

    def home(self, name: str, timeout_s: float | None = None) -> None:
        """Home axis ``name`` (within ``timeout_s``; ``None``: the axis's default). Ctrl-C or
        SIGTERM meanwhile stops the axis before it goes on (:func:`polrig.acquisition.hal.stopped_when_interrupted`)."""
        axis = self.axis(name)
        with stopped_when_interrupted([(name, axis)]):
            if timeout_s is None:
                axis.home()
            else:
                axis.home(timeout_s=float(timeout_s))
        self._unsettled = True

    def move(self, targets: dict[str, float]) -> None:
        """Move every axis of ``targets`` (name -> angle, deg) at once and wait for all; an
        axis whose move fails recoverably is stopped, homed and moved once more on its own
        (:meth:`_recover`). A safety fault (:class:`DeviceAlarm`) of any axis starts nothing
        more, waits for the axes already moving and is raised, with no retry and no
        homing. Ctrl-C or SIGTERM (a ``KeyboardInterrupt``) meanwhile stops every axis the move
        started before it goes on, so nothing keeps turning once the run has ended
        (:func:`polrig.acquisition.hal.stopped_when_interrupted`)."""
        begun: list[tuple[str, RotationStage]] = []
        with stopped_when_interrupted(begun):
            self._move(targets, begun)

    def _move(self, targets: dict[str, float], begun: list[tuple[str, RotationStage]]) -> None:
        """:meth:`move`; ``begun`` gets each axis, with its name, as its move is started."""
        failed: dict[str, Exception] = {}
        started = []
        alarm: DeviceAlarm | None = None
        self._unsettled = True
        for name, angle in targets.items():
            axis = self.axis(name)
            try:
                timeout_s = self._timeout_from_here(axis, angle)
                begun.append((name, axis))
                axis.move_to(float(angle), wait=False, timeout_s=timeout_s)
                started.append((name, axis, timeout_s))
            except DeviceDisconnected:
                self._let_finish(started)
                raise
            except DeviceAlarm as exc:
                alarm = exc
                break
            except MOVE_RECOVERABLE as exc:
                failed[name] = exc
        if alarm is not None:
            self._let_finish(started)
            raise alarm
        for name, axis, timeout_s in started:
            try:
                axis.wait(timeout_s)
            except DeviceDisconnected:
                raise
            except DeviceAlarm as exc:
                alarm = alarm or exc
            except MOVE_RECOVERABLE as exc:
                failed[name] = exc
        if alarm is not None:
            raise alarm
        for name in targets:
            if name in failed:
                angle = float(targets[name])
                self.emit(Retried(f"{_AXIS_NAMES.get(name, name)} move to {angle:g} deg failed "
                                  f"({failed[name]}); re-homing and retrying once"))
                axis = self.axis(name)
                self._recover(name, axis, angle, failed[name])
                axis.move_to(angle, wait=True, timeout_s=motion_timeout_s(axis, angle))

    @staticmethod
    def _recover(name: str, axis: RotationStage, angle_deg: float, failure: Exception) -> None:
        """Stop ``axis`` (its failed move may still run: a home sent then is refused) and home
        it. If either fails, ``failure`` (the move's) is raised with the recovery's reason,
        as an error of its own type; a safety fault or a disconnection is raised as itself."""
        step = "stopping it"
        try:
            axis.stop()
            step = "re-homing it"
            axis.home()
        except NEVER_RETRIED:
            raise
        except MOVE_RECOVERABLE as exc:
            what = f"{_AXIS_NAMES.get(name, name)} move to {angle_deg:g} deg"
            raise _with_reason(failure, f"{what} failed ({failure}); {step} failed too: "
                                        f"{exc}") from exc

    @staticmethod
    def _let_finish(started: list) -> None:
        """Wait for the axes already moving before a stop is raised (their own errors are
        not the news: the stop is)."""
        for _name, axis, timeout_s in started:
            try:
                axis.wait(timeout_s)
            except DeviceError:
                pass

    @staticmethod
    def _timeout_from_here(axis: RotationStage, angle_deg: float) -> float:
        """Timeout of a move from where ``axis`` is now; if its position cannot be read (the
        move then fails or succeeds on its own), as if it had a full turn more to go; a
        safety fault or a disconnection is raised."""
        try:
            here = float(axis.position_deg())
        except NEVER_RETRIED:
            raise
        except MOVE_RECOVERABLE:
            here = float(angle_deg) + 360.0
        return motion_timeout_s(axis, float(angle_deg) - here)


_AXIS_NAMES = {"stage": "polarizer stage", "turntable": "turntable"}


def _with_reason(failure: Exception, message: str) -> Exception:
    """An error of ``failure``'s type saying ``message``, with its device, code and text."""
    try:
        err = type(failure)(message)
    except TypeError:  # a subclass with another signature: the nearest common type
        err = DeviceFault(message)
    for attr in ("device", "code", "text"):
        if hasattr(failure, attr):
            setattr(err, attr, getattr(failure, attr))
    return err


def hardware_model(rig) -> HardwareModel:
    """The :class:`polrig.acquisition.plan.HardwareModel` of ``rig`` as it is now: its axes' declared
    motion, the camera's readout, exposure and (in free run) settle frames, the axes'
    positions (0 where one cannot be read)."""
    axes: dict[str, RotationStage] = {"stage": rig.stage, "turntable": rig.turntable}
    positions = {}
    for name, axis in axes.items():
        try:
            positions[name] = float(axis.position_deg())
        except (DeviceTimeout, DeviceFault, ProtocolError):
            positions[name] = 0.0
    caps = rig.camera.capabilities
    return HardwareModel(lambda a, f, t: axes[a].move_time_s(f, t), caps.readout_us, settle_frames(caps),
                         positions, float(rig.camera.exposure_us))


def settle_frames(caps: CameraCapabilities) -> int:
    """The frames a camera of capabilities ``caps`` discards after a setting change or a move:
    its declared settle frames in free run (its preferred trigger), none when triggered."""
    return int(caps.settle_frames) if caps.preferred_trigger == "free" else 0


# -- calibration procedures: the same policy behind the HAL interfaces ----------------------
class GuardedCamera(Camera):
    """``camera`` with every grab and setting going through ``executor``'s policy (retries,
    free-run settle frames). Used by :class:`GuardedRig`. Anything a driver offers beyond the
    HAL is the wrapped camera's own (read through unchanged)."""

    def __init__(self, camera: Camera, executor: Executor):
        self._camera, self._executor = camera, executor

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._camera, name)

    def open(self) -> None:
        self._camera.open()

    def close(self) -> None:
        self._camera.close()

    def info(self):
        return self._camera.info()

    @property
    def is_open(self) -> bool:
        return self._camera.is_open

    def set_pixel_format(self, name: str) -> None:
        self._executor.set_camera("camera setting", lambda: self._camera.set_pixel_format(name))

    @property
    def pixel_format(self) -> str:
        return self._camera.pixel_format

    def set_roi(self, width: int, height: int, offset_x: int = 0, offset_y: int = 0) -> None:
        self._executor.set_camera("camera setting", lambda: self._camera.set_roi(
            width, height, offset_x, offset_y))

    @property
    def roi(self) -> tuple[int, int, int, int]:
        return self._camera.roi

    def set_exposure_us(self, exposure_us: float) -> None:
        self._executor.set_exposure(exposure_us)

    @property
    def exposure_us(self) -> float:
        return self._camera.exposure_us

    def set_gain_db(self, gain_db: float) -> None:
        self._executor.set_camera("camera setting", lambda: self._camera.set_gain_db(gain_db))

    @property
    def gain_db(self) -> float:
        return self._camera.gain_db

    @property
    def capabilities(self) -> CameraCapabilities:
        return self._camera.capabilities

    def set_trigger(self, mode: str) -> None:
        self._executor.set_trigger(mode)

    @property
    def layout(self) -> str:
        return self._camera.layout

    def grab(self, timeout_s: float | None = None) -> Frame:
        """A frame under the policy (the timeout is the policy's, from the exposure)."""
        self._executor.control.checkpoint()
        return self._executor.grab()


class GuardedAxis(RotationStage):
    """A stage or turntable whose moves go through ``executor``'s policy (timeout from the
    distance, one re-homed retry, never one after a safety fault). Used by
    :class:`GuardedRig`."""

    def __init__(self, name: str, axis: RotationStage, executor: Executor):
        self._name, self._axis, self._executor = name, axis, executor

    def open(self) -> None:
        self._axis.open()

    def close(self) -> None:
        self._axis.close()

    def info(self):
        return self._axis.info()

    @property
    def is_open(self) -> bool:
        return self._axis.is_open

    @property
    def capabilities(self):
        return self._axis.capabilities

    def move_time_s(self, from_deg: float, to_deg: float) -> float:
        return self._axis.move_time_s(from_deg, to_deg)

    def calculate_timeout(self, distance_deg: float, margin_s: float = 30.0) -> float:
        return self._axis.calculate_timeout(distance_deg, margin_s)

    def home(self, timeout_s: float = 60.0) -> None:
        self._executor.home(self._name, timeout_s)

    def move_to(self, angle_deg: float, *, wait: bool = True, timeout_s: float = 30.0) -> None:
        """Under the policy; ``wait=False`` starts the move only (no retry: nothing waits
        for it to fail)."""
        if not wait:
            self._axis.move_to(angle_deg, wait=False, timeout_s=timeout_s)
            return
        self._executor.control.checkpoint()
        self._executor.move({self._name: float(angle_deg)})

    def position_deg(self) -> float:
        return self._axis.position_deg()

    def is_busy(self) -> bool:
        return self._axis.is_busy()

    def wait(self, timeout_s: float = 30.0) -> None:
        self._axis.wait(timeout_s)

    def stop(self) -> None:
        self._axis.stop()


class GuardedLight(Light):
    """A light whose switching goes through ``executor``'s policy. Used by
    :class:`GuardedRig`."""

    def __init__(self, light: Light, executor: Executor):
        self._light, self._executor = light, executor

    def open(self) -> None:
        self._light.open()

    def close(self) -> None:
        self._light.close()

    def info(self):
        return self._light.info()

    @property
    def is_open(self) -> bool:
        return self._light.is_open

    def set_on(self, on: bool) -> None:
        self._executor.set_light(on)

    def set_level(self, level: float) -> None:
        self._executor.retried("light setting", lambda: self._light.set_level(level))

    def status(self) -> dict[str, Any]:
        return self._light.status()


@dataclasses.dataclass
class GuardedRig:
    """A rig facade for procedures written against the HAL (the calibration procedures):
    the same four devices, every grab, setting and move going through one
    :class:`Executor`'s fault policy, and pause/stop honoured before grabs and moves.
    ``truth`` (the declared :class:`polrig.acquisition.hal.RigTruth` or ``None``), ``config`` and
    ``source`` are the wrapped rig's. Build with
    :meth:`around` (``rig``: a :class:`polrig.app.rig.Rig`); the camera is put in its preferred
    trigger mode."""

    camera: GuardedCamera
    stage: GuardedAxis
    turntable: GuardedAxis
    light: GuardedLight
    executor: Executor
    truth: RigTruth | None = None
    config: Any = None
    source: Any = None

    @property
    def devices(self) -> dict[str, Any]:
        return {"camera": self.camera, "stage": self.stage, "turntable": self.turntable,
                "light": self.light}

    @classmethod
    def around(cls, rig, *, policy: FaultPolicy = FaultPolicy(),
               control: CaptureControl | None = None,
               on_retry: Callable[[str], None] | None = None) -> "GuardedRig":
        executor = Executor(rig, policy=policy, control=control)
        if on_retry is not None:
            executor.subscribe(lambda ev: on_retry(ev.message) if isinstance(ev, Retried)
                               else None)
        executor.set_trigger(None)
        return cls(GuardedCamera(rig.camera, executor),
                   GuardedAxis("stage", rig.stage, executor),
                   GuardedAxis("turntable", rig.turntable, executor),
                   GuardedLight(rig.light, executor), executor,
                   truth=rig.truth, config=rig.config, source=rig.source)
