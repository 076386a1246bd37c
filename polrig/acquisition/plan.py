"""What a capture session acquires, as data: the :class:`CapturePlan`, the device steps it
yields, and the hardware time those steps take. No device is touched here.

A plan is turned into a flat list of device steps (:func:`capture_steps`): set the trigger,
switch the light, home or move axes (several axes in one :class:`Move` move together), set
the exposure, grab a frame with its :class:`FrameTag`, and :class:`Checkpoint` s where a run
may pause or stop and where a pose is complete. :class:`polrig.acquisition.engine.Executor` runs such a
list on a rig; a test can check a plan by reading the list, with no rig at all.

Motion that wastes nothing: the turntable's move to pose ``k`` and the stage's move to that
pose's first polarizer state are one :class:`Move` (both axes turn at once), and the state
order alternates between poses (serpentine: pose 0 visits the states in plan order, pose 1
in reverse, ...), so the stage never travels back idle. Frames stay tagged with the plan's
state index, so raw file names and results do not depend on the order.

An adaptive plan (``mode="adaptive"``) chooses its states as it goes: its steps are the same
pieces (:func:`pose_head_steps`, :func:`state_steps`, :func:`pose_tail_steps`), handed to the
executor one at a time by the app layer's decisions (:mod:`polrig.app.adaptive`); a pose that took
states ``S`` ran :func:`adaptive_pose_steps` of ``S``, and before the decisions its hardware time is
forecast at :func:`adaptive_forecast_states`.

:func:`step_durations` is the plan's hardware time per step (motion from each axis's
:meth:`polrig.acquisition.hal.RotationStage.move_time_s`, exposure plus readout per frame, discarded
free-run settle frames), computed before a capture starts. Angles in degrees, exposures in
microseconds, times in seconds.

Errors are :class:`PlanError` s naming the plan field (``states_deg``...), never a
command-line flag: the command line maps fields to its options (:mod:`polrig.cli.commands.capture`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Iterable, Sequence, Union

from polrig.choices import NETWORK_BINNINGS
from polrig.errors import ConfigError
from polrig.formats.exr import (
    COMPRESSIONS,
    PLANE_GROUPS,
    RESULT_PLANES,
    UNCERTAINTY_PRECISIONS,
)

#: Capture and processing methods: ``reference`` (N >= 3 polarizer states solved per pixel),
#: ``single-shot`` (the trained network on one state), ``hybrid`` (N >= 1 states solved with the
#: network's estimate of one of them, ``seen_state``, as a Gaussian prior: :mod:`polrig.solve.hybrid`),
#: ``adaptive`` (the hybrid solve of states chosen per pose from the data until the posterior
#: meets a target: :class:`AdaptiveTarget`, :mod:`polrig.app.adaptive`).
MODES = ("reference", "single-shot", "hybrid", "adaptive")
#: The modes that run the single-shot network (the single-shot route, :class:`SingleShotOptions`).
NETWORK_MODES = ("single-shot", "hybrid", "adaptive")
#: The modes whose result is the hybrid posterior (the network's estimate of the seen state as
#: the prior of the solve of every state taken): they need its calibrated sigma.
PRIOR_MODES = ("hybrid", "adaptive")
#: The modes whose plan records one polarizer state per pose.
ONE_STATE_MODES = ("single-shot", "adaptive")
#: Candidate polarizer angles of the adaptive mode: 0 to 180 deg (a linear polarizer repeats
#: every 180 deg) in steps of :data:`ADAPTIVE_CANDIDATE_STEP_DEG`.
ADAPTIVE_CANDIDATE_STEP_DEG = 7.5
#: Most polarizer states the adaptive mode may take per pose (``max_states``): beyond about
#: twice the four of the reference mode more states only average noise, a fixed plan does that.
ADAPTIVE_MAX_STATES = 8
#: Fewest polarizer states an adaptive pose takes before its target may stop it (``min_states``,
#: :attr:`CapturePlan.min_states`). Two: at one state the posterior sigma is the network's
#: calibrated sigma alone, which no frame the network did not see has checked; from the second
#: state on the prior's scale is checked against the data (the innovations' scale,
#: :mod:`polrig.solve.prior_scale`, and the open direction's, :mod:`polrig.solve.open_scale`).
#: Measured (``python -m benchmarks continuum --rig``): a pose of the default rig's ``plane``
#: stopped on the network's frame at 85.3 % of its elements within 2 sigma (the network's sigma
#: there covers 87.8 %), with its second state 96.6 %. 1 lets a pose stop on the network alone.
ADAPTIVE_MIN_STATES = 2
#: The adaptive capture's forecast states (:func:`adaptive_forecast_states`), as offsets from its
#: first state (deg): the equiangular set through it (the capture's first three,
#: :data:`polrig.solve.design.EQUIANGULAR_OFFSETS_DEG`), then its midpoints, then theirs.
FORECAST_OFFSETS_DEG = (0.0, 60.0, 120.0, 90.0, 30.0, 150.0, 15.0, 45.0, 75.0, 105.0, 135.0, 165.0)
DEFAULT_STATES_DEG = (0.0, 45.0, 90.0, 135.0)
#: Largest turntable pose accepted, in degrees either way (100 turns): beyond it a pose is a
#: typo, and its capture folder name (``c000_pose<angle>``) would outgrow the file system's.
MAX_POSE_DEG = 36000.0
#: Largest polarizer stage angle accepted, either way: a linear polarizer repeats every 180 deg,
#: so anything beyond one turn is a typo (and would send the stage on a long, timed-out move).
MAX_STATE_DEG = 360.0
#: The motion axes a plan moves (names of the rig's :class:`polrig.acquisition.hal.RotationStage` s).
AXES = ("stage", "turntable")


MIRROR_SINGLE_SHOT_ONLY = "mirror averaging applies to the network's methods only (single-shot, hybrid, adaptive)"
#: Output resolutions of the single-shot method (:attr:`SingleShotOptions.resolution`): the
#: networks' superpixel grid or the raw frame's own.
RESOLUTIONS = ("superpixel", "full")
FULL_RESOLUTION_SINGLE_SHOT_ONLY = ("only the single-shot method has a full-resolution output (the "
                                    "reference method's resolution is its demosaic: bilinear or "
                                    "newton give the raw frame's size)")
#: Why a full-resolution single-shot output refuses the superpixel demosaic.
FULL_RESOLUTION_NEEDS_DETAIL = ("takes its detail from a full-resolution demosaic (bilinear or newton), "
                                "not superpixel")
NETWORK_BINNING_SINGLE_SHOT_ONLY = ("network binning applies to the single-shot method only (the "
                                    "reference method runs no network)")
#: Why the hybrid method refuses what leaves the network's sigma uncalibrated (NaN): its prior
#: is the network's estimate with that sigma.
HYBRID_NEEDS_SIGMA = ("the hybrid method's prior needs the network's calibrated sigma, which exists on "
                      "the networks' unbinned superpixel grid only")
SEEN_STATE_HYBRID_ONLY = "the seen state applies to the hybrid method only"
ADAPTIVE_ONLY = "applies to the adaptive method only"


class PlanError(ConfigError):
    """A capture plan that cannot be acquired or processed. ``field`` names what it is about
    (a :class:`CapturePlan` field such as ``"states_deg"``, or ``"calibration"``), for
    callers that name their own option for it; ``subject`` the offending value as text
    (``None``: the message says all), ``what`` what that value is. The message reads
    ``"<what> <subject>: <detail>"`` (or ``detail`` alone)."""

    def __init__(self, field: str, detail: str, *, subject: str | None = None, what: str = ""):
        head = " ".join(p for p in (what, subject) if p)
        super().__init__(f"{head}: {detail}" if subject is not None else detail)
        self.field, self.detail, self.subject = field, detail, subject


def check_network_binning(binning: Any, mode: str) -> int:
    """``binning`` as an int when it is one of :data:`NETWORK_BINNINGS` and allowed in ``mode``
    (anything but 1 is single-shot only); a one-line :class:`PlanError` of ``network_binning``
    otherwise (:func:`single_shot_options`, :class:`SingleShotOptions`)."""
    if isinstance(binning, bool) or not isinstance(binning, int) or binning not in NETWORK_BINNINGS:
        raise PlanError("network_binning", f"must be one of {', '.join(map(str, NETWORK_BINNINGS))}",
                        subject=repr(binning), what="network binning")
    if binning != 1 and mode in PRIOR_MODES:
        raise PlanError("network_binning", HYBRID_NEEDS_SIGMA, subject=str(binning),
                        what="network binning")
    if binning != 1 and mode != "single-shot":
        raise PlanError("network_binning", NETWORK_BINNING_SINGLE_SHOT_ONLY, subject=str(binning),
                        what="network binning")
    return int(binning)



#: Why the ``geometry`` planes are refused outside the single-shot method and off its grid.
GEOMETRY_SINGLE_SHOT_ONLY = ("the geometry planes (normal, albedo, roughness, light) are the single-shot "
                             "method's network outputs (mode single-shot)")
GEOMETRY_ON_NETWORK_GRID = ("the geometry planes are written on the networks' own grid only: superpixel "
                            "resolution, network binning 1")

@dataclasses.dataclass(frozen=True)
class SingleShotOptions:
    """How a single-shot result is computed: the one place its option rules live (issue 30).
    :class:`polrig.app.single_shot.SingleShot` takes it; ``polrig infer``, a capture plan
    (:func:`single_shot_options`: capture and ``reconstruct`` processing) and the GUI's live view
    build it. Refusals are one-line :class:`PlanError` s naming the field (``resolution``,
    ``demosaic``, ``network_binning``, ``sigma``), for the command line to name its option.

    ``resolution``: ``superpixel`` (the networks' grid) or ``full`` (the raw frame's: the
    networks' answer on the superpixel grid lifted with the measured detail of ``demosaic``,
    :func:`polrig.models.full_resolution.lift`).
    ``demosaic``: the output grid's demosaic (``None``: the resolution's default). At
    ``superpixel`` resolution it is the networks' input (``superpixel`` by default; ``bilinear``
    or ``newton`` run the networks on the full-resolution demosaic); at ``full`` resolution the
    demosaic whose detail lifts the networks' answer: ``bilinear`` by default or ``newton``, and
    ``superpixel`` is refused (it has no detail to give).
    ``network_binning``: :data:`NETWORK_BINNINGS`. ``mirror_average``: average the networks'
    answers for the frame and its mirror image (:mod:`polrig.models.mirror`).
    ``sigma``: the model's calibrated standard deviations: ``True`` asks for them (refused where
    they are not calibrated: at full resolution or with network binning, :attr:`sigma_calibrated`),
    ``False`` skips them, ``None`` computes them where they are calibrated (a session's result:
    NaN planes elsewhere).
    ``geometry``: also keep the networks' surface normal, diffuse albedo, roughness and light
    direction (the result's ``geometry`` planes; the full graph runs instead of the frame
    graph); on the networks' own grid only, so refused at full resolution and with network
    binning (:data:`GEOMETRY_ON_NETWORK_GRID`)."""

    resolution: str = "superpixel"
    demosaic: str | None = None
    network_binning: int = 1
    mirror_average: bool = False
    sigma: bool | None = None
    geometry: bool = False

    def __post_init__(self) -> None:
        from polrig.sensor.demosaic import METHODS  # (cv2: not at plan import)

        if self.resolution not in RESOLUTIONS:
            raise PlanError("resolution", f"must be one of {', '.join(RESOLUTIONS)}",
                            subject=repr(self.resolution), what="resolution")
        full = self.resolution == "full"
        demosaic = self.demosaic or ("bilinear" if full else "superpixel")
        if demosaic not in METHODS:
            raise PlanError("demosaic", f"must be one of {', '.join(METHODS)}", subject=repr(demosaic),
                            what="demosaic")
        if full and demosaic == "superpixel":
            raise PlanError("resolution", FULL_RESOLUTION_NEEDS_DETAIL, subject="full", what="resolution")
        object.__setattr__(self, "demosaic", demosaic)
        object.__setattr__(self, "network_binning", check_network_binning(self.network_binning, "single-shot"))
        object.__setattr__(self, "mirror_average", bool(self.mirror_average))
        object.__setattr__(self, "geometry", bool(self.geometry))
        if self.geometry and not self.sigma_calibrated:
            raise PlanError("geometry", GEOMETRY_ON_NETWORK_GRID + ", not "
                            + " or ".join(self.uncalibrated_because()))
        if self.sigma and not self.sigma_calibrated:
            raise PlanError("sigma", "the single-shot uncertainty is calibrated on the networks' unbinned "
                                     f"superpixel grid only, not {' or '.join(self.uncalibrated_because())}")

    @classmethod
    def from_settings(cls, *, demosaic: str, resolution: str = "superpixel", network_binning: int = 1,
                      mirror_average: bool = False, sigma: bool | None = None,
                      geometry: bool = False) -> "SingleShotOptions":
        """The options of settings whose ``demosaic`` serves more than the single-shot output (a
        :class:`CapturePlan`'s, also the reference method's; the live view's, also its Stokes
        display's), ``superpixel`` by default: at full resolution that default stands for the
        default detail (``bilinear``) instead of being refused."""
        full_default = resolution == "full" and demosaic == "superpixel"
        return cls(resolution, None if full_default else demosaic, network_binning, mirror_average, sigma,
                   geometry)

    @property
    def network_demosaic(self) -> str:
        """The demosaic of the networks' input: ``superpixel`` at full resolution (the grid they
        were trained on), else :attr:`demosaic`."""
        return "superpixel" if self.resolution == "full" else self.demosaic

    @property
    def sigma_calibrated(self) -> bool:
        """Whether the model's uncertainty is calibrated for this route: on the networks'
        unbinned grid at superpixel resolution only."""
        return self.resolution == "superpixel" and self.network_binning == 1

    @property
    def with_sigma(self) -> bool:
        """Whether the route computes the calibrated sigma (``sigma``, ``None``: where calibrated)."""
        return self.sigma_calibrated if self.sigma is None else bool(self.sigma)

    def uncalibrated_because(self) -> list[str]:
        """Why the uncertainty is not calibrated for this route, in words (empty where it is)."""
        return [why for why, on in (("at full resolution", self.resolution == "full"),
                                    (f"with network binning {self.network_binning}",
                                     self.network_binning > 1)) if on]


def single_shot_options(mode: str, demosaic: str, resolution: str, network_binning: Any,
                        mirror_average: bool, exr_planes: Sequence[str] = ()) -> SingleShotOptions | None:
    """The single-shot options of a plan's (or a revision's) settings, ``None`` for the reference
    method, checked against the mode: mirror averaging, full resolution and network binning are
    single-shot only (one-line :class:`PlanError` s of the field). The hybrid method runs the
    single-shot route for its prior with its calibrated sigma (``sigma=True``): mirror averaging
    applies, full resolution and network binning 2 are refused (the sigma is NaN there,
    :data:`HYBRID_NEEDS_SIGMA`). ``exr_planes``: the result's plane groups; ``geometry`` among
    them (the networks' geometry, :attr:`SingleShotOptions.geometry`) is the single-shot
    method's, on the networks' grid (a :class:`PlanError` of ``exr_planes`` otherwise). Shared by
    :class:`CapturePlan` and :class:`polrig.app.processing.Processor`."""
    if mirror_average and mode not in NETWORK_MODES:
        raise PlanError("mirror_average", MIRROR_SINGLE_SHOT_ONLY)
    if resolution not in RESOLUTIONS:
        raise PlanError("resolution", f"must be one of {', '.join(RESOLUTIONS)}",
                        subject=repr(resolution), what="resolution")
    if resolution == "full" and mode in PRIOR_MODES:
        raise PlanError("resolution", HYBRID_NEEDS_SIGMA, subject="full", what="resolution")
    if resolution == "full" and mode != "single-shot":
        raise PlanError("resolution", FULL_RESOLUTION_SINGLE_SHOT_ONLY, subject="full",
                        what="resolution")
    binning = check_network_binning(network_binning, mode)
    geometry = "geometry" in exr_planes
    if geometry and mode != "single-shot":
        raise PlanError("exr_planes", GEOMETRY_SINGLE_SHOT_ONLY, subject="geometry", what="EXR plane group")
    if geometry and (resolution != "superpixel" or binning != 1):
        raise PlanError("exr_planes", GEOMETRY_ON_NETWORK_GRID, subject="geometry", what="EXR plane group")
    if mode not in NETWORK_MODES:
        return None
    return SingleShotOptions.from_settings(demosaic=demosaic, resolution=resolution,
                                           network_binning=binning, mirror_average=mirror_average,
                                           sigma=True if mode in PRIOR_MODES else None, geometry=geometry)


def check_seen_state(seen_state: Any, mode: str, n_states: int) -> int:
    """``seen_state`` (the index into the plan's states of the frame the hybrid method's prior
    is computed from) as an int: ``0 <= seen_state < n_states`` in the hybrid mode, 0 in the
    others (one-line :class:`PlanError` s of ``seen_state``)."""
    if isinstance(seen_state, bool) or not isinstance(seen_state, int):
        raise PlanError("seen_state", "must be a state index (0, 1, ...)", subject=repr(seen_state),
                        what="seen state")
    if mode != "hybrid":
        if seen_state != 0:
            raise PlanError("seen_state", SEEN_STATE_HYBRID_ONLY, subject=str(seen_state),
                            what="seen state")
        return 0
    if not 0 <= seen_state < n_states:
        raise PlanError("seen_state", f"must index the plan's {n_states} polarizer state(s): "
                                      f"0..{n_states - 1}", subject=str(seen_state), what="seen state")
    return int(seen_state)


def check_adaptive_target(mode: str, target_sigma: Any, target_share: Any, max_states: Any,
                          min_states: Any = ADAPTIVE_MIN_STATES) -> tuple[float, float, int, int]:
    """The adaptive mode's stopping rule ``(target_sigma, target_share, max_states, min_states)``
    checked: in the adaptive mode a relative sigma ``0 < target_sigma <= 1`` (of the normalised
    block, m00 = 1), a share ``0 < target_share <= 1``, ``1 <= max_states <=``
    :data:`ADAPTIVE_MAX_STATES` and ``1 <= min_states <= max_states``; in the others the defaults
    (0, 0.95, 4, :data:`ADAPTIVE_MIN_STATES`). One-line :class:`PlanError` s naming the field (an
    adaptive plan with the default ``target_sigma``, 0, is one that gave none: the error says so)."""
    defaults = (0.0, 0.95, 4, ADAPTIVE_MIN_STATES)
    names = ("target_sigma", "target_share", "max_states", "min_states")
    if mode != "adaptive":
        for name, value, default in zip(names, (target_sigma, target_share, max_states, min_states), defaults):
            if isinstance(value, bool) or value != default:
                raise PlanError(name, ADAPTIVE_ONLY, subject=repr(value), what=name.replace("_", " "))
        return defaults
    if not isinstance(target_sigma, bool) and target_sigma == defaults[0]:  # not given
        raise PlanError("target_sigma", "the adaptive mode stops each pose at a target: give a relative sigma "
                                        "(of the block normalised to m00 = 1) in (0, 1], e.g. 0.05")
    for name, value in (("target_sigma", target_sigma), ("target_share", target_share)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) \
                or not (math.isfinite(value) and 0 < value <= 1):
            what = ("a relative sigma (of the block normalised to m00 = 1) in (0, 1], e.g. 0.01"
                    if name == "target_sigma" else "a share of object pixels in (0, 1], e.g. 0.95")
            raise PlanError(name, f"must be {what}", subject=repr(value), what=name.replace("_", " "))
    if isinstance(max_states, bool) or not isinstance(max_states, int) \
            or not 1 <= max_states <= ADAPTIVE_MAX_STATES:
        raise PlanError("max_states", f"must be a whole number of polarizer states 1..{ADAPTIVE_MAX_STATES}",
                        subject=repr(max_states), what="max states")
    if isinstance(min_states, bool) or not isinstance(min_states, int) or not 1 <= min_states <= max_states:
        raise PlanError("min_states", f"must be a whole number of polarizer states 1..{max_states} (the most "
                                      f"states a pose takes)", subject=repr(min_states), what="min states")
    return float(target_sigma), float(target_share), int(max_states), int(min_states)


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
        raise PlanError("poses_deg", f"{bad}: give a list like 0,30,60 or a range START:STOP:STEP")
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise PlanError("poses_deg", f"{bad}: a range is START:STOP:STEP (STOP exclusive), e.g. 0:360:30")
        start, stop, step = (_number(p, bad, "angle", "poses_deg") for p in parts)
        if step == 0:
            raise PlanError("poses_deg", f"{bad}: STEP must not be 0")
        count = math.ceil((stop - start) / step - 1e-9)
        if count <= 0:
            raise PlanError("poses_deg", f"{bad}: the range is empty (STOP is exclusive)")
        if count > 100000:
            raise PlanError("poses_deg", f"{bad}: {count} poses is too many")
        return tuple(round(start + i * step, 9) for i in range(count))
    return tuple(_number(p, bad, "angle", "poses_deg") for p in text.split(","))


def _number(text: str, bad: str, what: str = "number", field: str = "") -> float:
    """``text`` as a finite float; :class:`PlanError` (of ``field``) ``"{bad}: 'x' is not a
    finite {what}"`` otherwise (``what``: "angle" for poses, "number" for any other value)."""
    try:
        v = float(text.strip())
    except ValueError:
        raise PlanError(field, f"{bad}: {text.strip()!r} is not a number") from None
    if not math.isfinite(v):
        raise PlanError(field, f"{bad}: {text.strip()!r} is not a finite {what}")
    return v


def parse_float_list(spec: str, name: str, *, positive: bool = False,
                     field: str = "") -> tuple[float, ...]:
    """``"0,45,90"`` -> floats; :class:`PlanError` (of ``field``) naming ``name`` (what the
    list is, as the caller calls it) otherwise."""
    bad = f"invalid {name} {spec!r}"
    values = tuple(_number(p, bad, field=field) for p in str(spec).split(","))
    if positive and any(v <= 0 for v in values):
        raise PlanError(field, f"{bad}: values must be > 0")
    return values


# -- the result file's format -----------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ExrChoice:
    """What a result ``mueller.exr`` holds and how it is stored (:func:`polrig.formats.exr.result_planes`,
    :func:`polrig.formats.exr.write_exr`): ``planes`` the plane groups (:data:`polrig.formats.exr.RESULT_PLANES`,
    and on request :data:`polrig.formats.exr.OPTIONAL_PLANES`' ``geometry``, single-shot only;
    ``mueller`` is always written, the groups are kept in that order), ``uncertainty``
    ``"float"`` (float32) or ``"half"`` (float16 ``sigma``, ``sigma_noise``, ``residual`` and
    ``mask``), ``compression`` ``"zip"``, ``"piz"`` or ``"none"``. Bytes per full-sensor colour
    pose of each choice: ``benchmarks/results/pose.md``.

    The default is half-precision uncertainty planes, ZIP: at full sensor a colour bilinear
    result is 0.7 GB instead of 1.6 GB with float32 planes, written faster and solved in less
    memory, and 11 significant bits are ample for a standard deviation. Sessions from before
    these fields existed were written with float32 planes: their manifests say so once
    migrated (:data:`polrig.app.manifest.LEGACY_EXR`), so they resume to the same files."""

    planes: tuple[str, ...] = RESULT_PLANES
    uncertainty: str = "half"
    compression: str = "zip"

    def __post_init__(self) -> None:
        planes = tuple(self.planes)
        unknown = [p for p in planes if p not in PLANE_GROUPS]
        if unknown:
            raise PlanError("exr_planes", f"choose from {', '.join(PLANE_GROUPS)}",
                            subject=", ".join(map(str, unknown)), what="EXR plane group")
        if self.uncertainty not in UNCERTAINTY_PRECISIONS:
            raise PlanError("exr_uncertainty", f"use {' or '.join(UNCERTAINTY_PRECISIONS)}",
                            subject=repr(self.uncertainty), what="uncertainty precision")
        if self.compression not in COMPRESSIONS:
            raise PlanError("exr_compression", f"use one of {', '.join(COMPRESSIONS)}",
                            subject=repr(self.compression), what="EXR compression")
        object.__setattr__(self, "planes", tuple(p for p in PLANE_GROUPS
                                                 if p == "mueller" or p in planes))

    def bytes_per_pixel(self) -> int:
        """Uncompressed bytes per output pixel and colour."""
        unc = 2 if self.uncertainty == "half" else 4
        # geometry: albedo per colour, the normal, light (3 each) and roughness planes per pixel
        # (counted per colour: exact for mono, an upper bound for colour)
        per = {"mueller": 9 * 4, "sigma": 9 * unc, "sigma_noise": 9 * unc, "mask": unc,
               "residual": unc, "geometry": 4 * (1 + 3 + 3 + 1)}
        return sum(per[p] for p in self.planes)


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

    A session's manifest stores the plan as its fields, every one of them, and reads it back
    as a ``CapturePlan`` (:mod:`polrig.app.manifest`).
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
    #: (:mod:`polrig.models.mirror`)
    mirror_average: bool = False
    #: single-shot output resolution: ``superpixel`` (the networks' grid) or ``full`` (the raw
    #: frame's: :func:`polrig.models.full_resolution.lift` with the detail of ``demosaic``, bilinear
    #: where that is ``superpixel``)
    resolution: str = "superpixel"
    #: single-shot network binning (:data:`NETWORK_BINNINGS`): 2 runs the networks on the
    #: analyzer grid binned 2x2 and lifts the answer back (about half the frame time at full
    #: sensor size; no calibrated sigma: NaN planes). The output grid is ``resolution``'s either way
    network_binning: int = 1
    #: the result EXR's plane groups, uncertainty precision and compression (:class:`ExrChoice`)
    exr_planes: tuple[str, ...] = RESULT_PLANES
    exr_uncertainty: str = ExrChoice.uncertainty
    exr_compression: str = ExrChoice.compression
    #: hybrid: the index into ``states_deg`` of the state whose frame the network sees (its
    #: estimate and calibrated sigma are the prior, :mod:`polrig.solve.hybrid`); 0 in other modes
    seen_state: int = 0
    #: adaptive: the target on each object pixel's relative posterior sigma (the RMS of the nine
    #: elements' sigma over its m00, the worst colour: :func:`polrig.solve.design.relative_sigma`),
    #: dimensionless; 0 in other modes
    target_sigma: float = 0.0
    #: adaptive: the share of object pixels that must meet ``target_sigma`` for a pose to stop
    target_share: float = 0.95
    #: adaptive: the most polarizer states a pose takes (the first, the network's, included)
    max_states: int = 4
    #: adaptive: the fewest states a pose takes before its target may stop it
    #: (:data:`ADAPTIVE_MIN_STATES`; 1: a pose may stop on the network's frame alone)
    min_states: int = ADAPTIVE_MIN_STATES

    def __post_init__(self) -> None:
        exr = ExrChoice(self.exr_planes, self.exr_uncertainty, self.exr_compression)
        object.__setattr__(self, "exr_planes", exr.planes)
        if self.mode not in MODES:
            raise PlanError("mode", f"capture mode must be one of {', '.join(MODES)}, got "
                                    f"{self.mode!r}")
        if not self.poses_deg:
            raise PlanError("poses_deg", "invalid pose spec: no poses")
        for pose in self.poses_deg:
            if not (isinstance(pose, (int, float)) and math.isfinite(pose)
                    and abs(pose) <= MAX_POSE_DEG):
                raise PlanError("poses_deg", f"invalid pose spec: pose {pose!r} deg is not a finite angle "
                                  f"within +-{MAX_POSE_DEG:g} deg ({MAX_POSE_DEG / 360:g} turns)")
        for state in self.states_deg:
            if not (isinstance(state, (int, float)) and math.isfinite(state)
                    and abs(state) <= MAX_STATE_DEG):
                raise PlanError("states_deg", f"not a polarizer angle within "
                                              f"+-{MAX_STATE_DEG:g} deg",
                                subject=f"{state:g} deg", what="polarizer state")
        if self.frames_per_state < 1:
            raise PlanError("frames_per_state", f"frames per state must be >= 1, got "
                                                f"{self.frames_per_state}")
        if self.dark_frames < 0:
            raise PlanError("dark_frames", f"dark frames must be >= 0, got {self.dark_frames}")
        if any(not (e > 0 and math.isfinite(e)) for e in self.exposures_us):
            raise PlanError("exposures_us", f"exposures must be > 0 microseconds, got "
                                            f"{self.exposures_us}")
        single_shot_options(self.mode, self.demosaic, self.resolution, self.network_binning,
                            self.mirror_average, exr.planes)
        if self.mode == "reference" and len(self.states_deg) < 3:
            raise PlanError("states_deg", f"the reference method needs at least 3 polarizer "
                                          f"states, got {len(self.states_deg)}")
        if self.mode in NETWORK_MODES and not self.states_deg:
            raise PlanError("states_deg", f"the {self.mode} method needs at least one polarizer state")
        object.__setattr__(self, "seen_state", check_seen_state(self.seen_state, self.mode,
                                                                len(self.states_deg)))
        target = check_adaptive_target(self.mode, self.target_sigma, self.target_share,
                                       self.max_states, self.min_states)
        for name, value in zip(("target_sigma", "target_share", "max_states", "min_states"), target):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "poses_deg", tuple(float(p) for p in self.poses_deg))
        # single-shot captures one state per pose: the plan records the state it captures
        # (older sessions listed the default four; only the first was ever captured)
        # (the adaptive mode likewise records its first state, the network's: it chooses the others)
        states = self.states_deg[:1] if self.mode in ONE_STATE_MODES else self.states_deg
        object.__setattr__(self, "states_deg", tuple(float(s) for s in states))
        object.__setattr__(self, "exposures_us", tuple(float(e) for e in self.exposures_us))

    @property
    def exr(self) -> ExrChoice:
        """The result EXR's format."""
        return ExrChoice(self.exr_planes, self.exr_uncertainty, self.exr_compression)

    def frames_per_pose(self) -> int:
        """Frames per pose (adaptive: the most, at ``max_states``)."""
        n_exp = max(1, len(self.exposures_us))
        n_states = self.max_states if self.mode == "adaptive" else len(self.states_deg)
        return n_exp * (n_states * self.frames_per_state + self.dark_frames)

    def acquired_states_deg(self) -> tuple[float, ...]:
        """Stage angles visited per pose (single-shot: its one state; adaptive: the first state,
        the others are chosen per pose and recorded with it)."""
        return self.states_deg


def planned_bytes(plan: CapturePlan, n_poses: int, width: int, height: int,
                  n_colours: int, cell: tuple[int, int] = (1, 1)) -> int:
    """Upper estimate of the disk space ``n_poses`` captures of ``plan`` take: uncompressed
    16-bit raw frames (+ sidecars), the result EXR uncompressed (its planes at their precision,
    :meth:`ExrChoice.bytes_per_pixel`) at the demosaic's output size (``cell`` = the layout period
    ``(ph, pw)``, which ``superpixel`` divides the size by) and the truth EXR (9 + 1 planes
    per colour) at full size; 5 % and 1 MiB (manifest) on top."""
    raw = plan.frames_per_pose() * (2 * width * height + 4096)
    if plan.demosaic == "superpixel" and plan.resolution != "full":
        out_px = (height // cell[0]) * (width // cell[1])
    else:
        out_px = width * height
    exr = n_colours * (plan.exr.bytes_per_pixel() * out_px + 40 * width * height) + 2 * 65536
    return int(n_poses * (raw + exr) * 1.05) + (1 << 20)


# -- device steps -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class FrameTag:
    """Where a grabbed frame belongs: capture (pose) ``capture`` of the plan at ``pose_deg``;
    ``role`` ``"raw"`` (polarizer state ``state_index`` of the plan's ``states_deg``, at
    ``state_deg``) or ``"dark"`` (light off, no state); exposure ``exposure_index`` of the
    bracket at ``exposure_us``; ``frame`` the repeat index ``0..K-1``."""

    capture: int
    pose_deg: float
    role: str
    exposure_index: int
    exposure_us: float
    frame: int
    state_index: int | None = None
    state_deg: float | None = None


@dataclasses.dataclass(frozen=True)
class SetTrigger:
    """Set the camera's trigger mode; ``None``: its preferred one
    (:attr:`polrig.acquisition.hal.CameraCapabilities.preferred_trigger`)."""

    mode: str | None = None


@dataclasses.dataclass(frozen=True)
class SetLight:
    on: bool


@dataclasses.dataclass(frozen=True)
class Home:
    axis: str


@dataclasses.dataclass(frozen=True)
class Move:
    """Move every axis of ``targets`` (``(axis, angle_deg)`` pairs) to its angle, all at
    once, and wait until all have arrived."""

    targets: tuple[tuple[str, float], ...]

    def __post_init__(self) -> None:
        axes = [a for a, _ in self.targets]
        if not axes or len(set(axes)) != len(axes) or any(a not in AXES for a in axes):
            raise ValueError(f"a move names each of {AXES} at most once, got {axes}")


@dataclasses.dataclass(frozen=True)
class SetExposure:
    exposure_us: float


@dataclasses.dataclass(frozen=True)
class Grab:
    tag: FrameTag


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A point where a run may pause or stop. ``label``: ``"capture-start"`` (before capture
    ``capture`` moves anything) or ``"capture-acquired"`` (every frame of capture ``capture``
    grabbed, the rig still at its pose)."""

    label: str
    capture: int | None = None


Step = Union[SetTrigger, SetLight, Home, Move, SetExposure, Grab, Checkpoint]


def state_order(plan: CapturePlan, capture: int) -> list[int]:
    """Indices into ``plan.acquired_states_deg()`` in the order capture ``capture`` visits
    them: plan order for even captures, reversed for odd ones (serpentine)."""
    order = list(range(len(plan.acquired_states_deg())))
    return order[::-1] if capture % 2 else order


def setup_steps() -> list[Step]:
    """Before the first capture: the camera's preferred trigger, light on, stage homed."""
    return [SetTrigger(None), SetLight(True), Home("stage")]


def capture_steps(plan: CapturePlan, capture: int, exposures_us: Sequence[float]) -> list[Step]:
    """The device steps of capture ``capture`` (pose ``plan.poses_deg[capture]``).

    ``exposures_us``: the bracket to use (``plan.exposures_us``, or the camera's current
    exposure when the plan names none). Order: checkpoint; turntable to the pose and stage to
    the first state together; dark frames per exposure with the light off (if planned); per
    state (serpentine order, :func:`state_order`) a stage move (not for the first state: it is
    there already) and ``K`` frames per exposure; the reference exposure again (the simulated
    rig's truth is taken at it); checkpoint "capture-acquired". Composed of
    :func:`pose_head_steps`, :func:`state_steps` and :func:`pose_tail_steps`, which the
    adaptive mode runs one state at a time (its states are chosen as it goes)."""
    states = plan.acquired_states_deg()
    order = state_order(plan, capture)
    steps = pose_head_steps(plan, capture, exposures_us, states[order[0]])
    for n, j in enumerate(order):
        steps += state_steps(plan, capture, exposures_us, j, states[j], move=n > 0)
    return steps + pose_tail_steps(capture, exposures_us)


def _bracket(exposures_us: Sequence[float]) -> list[float]:
    exposures = [float(e) for e in exposures_us]
    if not exposures:
        raise ValueError("at least one exposure is needed")
    return exposures


def pose_head_steps(plan: CapturePlan, capture: int, exposures_us: Sequence[float],
                    first_state_deg: float) -> list[Step]:
    """The start of capture ``capture``: checkpoint "capture-start"; turntable to the pose and
    stage to ``first_state_deg`` together; the dark frames per exposure with the light off (if
    planned)."""
    pose = float(plan.poses_deg[capture])
    exposures = _bracket(exposures_us)
    steps: list[Step] = [Checkpoint("capture-start", capture),
                         Move((("turntable", pose), ("stage", float(first_state_deg))))]
    if plan.dark_frames:
        steps.append(SetLight(False))
        for e, exposure in enumerate(exposures):
            steps.append(SetExposure(exposure))
            steps += [Grab(FrameTag(capture, pose, "dark", e, exposure, k))
                      for k in range(plan.dark_frames)]
        steps.append(SetLight(True))
    return steps


def state_steps(plan: CapturePlan, capture: int, exposures_us: Sequence[float], state_index: int,
                state_deg: float, *, move: bool = True) -> list[Step]:
    """One polarizer state of capture ``capture``: the stage to ``state_deg`` (when ``move``)
    and ``K`` frames per exposure, tagged with ``state_index``."""
    pose = float(plan.poses_deg[capture])
    state = float(state_deg)
    steps: list[Step] = [Move((("stage", state),))] if move else []
    for e, exposure in enumerate(_bracket(exposures_us)):
        steps.append(SetExposure(exposure))
        steps += [Grab(FrameTag(capture, pose, "raw", e, exposure, k, state_index, state))
                  for k in range(plan.frames_per_state)]
    return steps


def state_time_s(plan: CapturePlan, exposures_us: Sequence[float], here_deg: float,
                 state_deg: float, model: HardwareModel) -> float:
    """The hardware time of one more state of a pose at stage angle ``state_deg`` with the
    stage at ``here_deg`` and the camera at the last exposure of the bracket ``exposures_us``
    (where the state before left it): :func:`step_durations` of its :func:`state_steps` (the
    move and ``plan.frames_per_state`` frames per exposure, settle frames included; the pose
    does not change it), seconds. What the adaptive capture weighs a candidate state with
    (:func:`polrig.solve.design.choose_next`)."""
    at = dataclasses.replace(model, positions_deg={**model.positions_deg, "stage": float(here_deg)},
                             exposure_us=_bracket(exposures_us)[-1])
    return float(sum(step_durations(state_steps(plan, 0, exposures_us, 1, state_deg), at)))


def pose_tail_steps(capture: int, exposures_us: Sequence[float]) -> list[Step]:
    """The end of a capture: the reference exposure again (the simulated rig's truth is taken
    at it) and checkpoint "capture-acquired"."""
    return [SetExposure(_bracket(exposures_us)[0]), Checkpoint("capture-acquired", capture)]


def adaptive_pose_steps(plan: CapturePlan, capture: int, exposures_us: Sequence[float],
                        states_deg: Sequence[float]) -> list[Step]:
    """Every step of an adaptive capture that took ``states_deg`` (in the order taken; the
    first is the plan's): what :func:`pose_head_steps`, one :func:`state_steps` per state and
    :func:`pose_tail_steps` add up to as the decisions are made. Its hardware time
    (:func:`step_durations`) is the capture's."""
    steps = pose_head_steps(plan, capture, exposures_us, states_deg[0])
    for j, state in enumerate(states_deg):
        steps += state_steps(plan, capture, exposures_us, j, state, move=j > 0)
    return steps + pose_tail_steps(capture, exposures_us)


def nearest_stage_angle(polarizer_deg: float, here_deg: float) -> float:
    """The stage angle for polarizer angle ``polarizer_deg`` (a linear polarizer repeats every
    180 deg) nearest to ``here_deg``, within +-:data:`MAX_STATE_DEG`: the adaptive mode's move
    to a chosen state."""
    angle = float(polarizer_deg) + 180.0 * round((float(here_deg) - float(polarizer_deg)) / 180.0)
    while angle > MAX_STATE_DEG:
        angle -= 180.0
    while angle < -MAX_STATE_DEG:
        angle += 180.0
    return angle


def adaptive_forecast_states(plan: CapturePlan, taken_deg: Sequence[float]) -> list[float]:
    """The states an adaptive capture that took ``taken_deg`` so far is forecast to take, for
    its hardware time before the decisions are made: ``taken_deg`` and then, up to
    ``plan.max_states``, the angles of :data:`FORECAST_OFFSETS_DEG` from the first state not
    taken yet: the equiangular set through it, which the capture takes first
    (:func:`polrig.solve.design.next_candidates`), then its midpoints and so on, each pass
    halving the spacing: the most states, at the spacing the capture tends to choose."""
    from polrig.solve.design import same_polarizer_state  # the solve stack only when forecasting

    first = float(plan.states_deg[0])
    taken = [float(t) for t in taken_deg]
    left = [first + o for o in FORECAST_OFFSETS_DEG
            if not any(same_polarizer_state(first + o, t) for t in taken)]
    return taken + left[:max(0, int(plan.max_states) - len(taken))]


def session_steps(plan: CapturePlan, captures: Iterable[int],
                  exposures_us: Sequence[float]) -> list[Step]:
    """:func:`setup_steps` then :func:`capture_steps` of each of ``captures`` in turn."""
    steps = setup_steps()
    for i in captures:
        steps += capture_steps(plan, i, exposures_us)
    return steps


# -- hardware time ------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class HardwareModel:
    """What the hardware time of a list of steps depends on.

    ``move_time_s(axis, from_deg, to_deg)``: one axis's move duration
    (:meth:`polrig.acquisition.hal.RotationStage.move_time_s`); ``readout_us``: per frame on top of its
    exposure; ``settle_frames``: frames discarded after a setting change or a move (free run
    only, else 0); ``positions_deg``: where the axes start; ``exposure_us``: the camera's
    exposure at the start."""

    move_time_s: Callable[[str, float, float], float]
    readout_us: float
    settle_frames: int
    positions_deg: dict[str, float]
    exposure_us: float


def step_durations(steps: Sequence[Step], model: HardwareModel) -> list[float]:
    """Hardware time of each step, seconds: a :class:`Move` lasts as long as its slowest
    axis (the axes move together), :class:`Home` a move to 0, a :class:`Grab` its exposure
    plus readout (and the settle frames it discards in free run after a setting change or a
    move; a NaN exposure, of a camera without exposure control, counts as 0); other steps
    0."""
    pos = dict(model.positions_deg)
    exposure = float(model.exposure_us)
    unsettled = True
    out = []
    for step in steps:
        t = 0.0
        if isinstance(step, Move):
            t = max(model.move_time_s(a, pos.get(a, 0.0), v) for a, v in step.targets)
            pos.update(dict(step.targets))
            unsettled = True
        elif isinstance(step, Home):
            t = model.move_time_s(step.axis, pos.get(step.axis, 0.0), 0.0)
            pos[step.axis] = 0.0
            unsettled = True
        elif isinstance(step, SetExposure):
            new = float(step.exposure_us)
            if new != exposure and not (math.isnan(new) and math.isnan(exposure)):
                exposure, unsettled = new, True
        elif isinstance(step, SetLight):
            unsettled = True
        elif isinstance(step, Grab):
            frames = 1 + (int(model.settle_frames) if unsettled else 0)
            known = exposure if math.isfinite(exposure) else 0.0  # NaN: no exposure control
            t = frames * (known + float(model.readout_us)) * 1e-6
            unsettled = False
        out.append(t)
    return out
