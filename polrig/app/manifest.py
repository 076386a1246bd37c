"""The session manifest (``session.json``) as types: one schema version, its reader derived from
the types, and the migration from every older version (``docs/session-schema.md``).

A manifest is a :class:`SessionManifest` (``TypedDict`` s for its JSON objects, so code reads
it with keys a type checker knows) whose ``plan`` is the :class:`polrig.acquisition.plan.CapturePlan`
itself: the plan is written once (:func:`encode`, the plan's own fields) and read back once, as
a ``CapturePlan`` (:func:`parse`), never re-parsed from a dict. Every value is stated: a key
another version left out is filled in by the migration from that version, with the value the
session was written with, never by today's defaults when it is read.

:func:`parse` reads any version this polrig knows: an older manifest is migrated in memory
(:data:`MIGRATIONS`, one function per version, each to the next; the manifest's ``history``
gains a ``schema migrated`` event) and then checked against the types with
:func:`polrig.formats.typedjson.load`, plus the few rules a type cannot say (one capture per
pose, each at its index). A problem is one :class:`polrig.errors.FormatError` line naming the
file and the record: ``session.json: capture 1 (c001_pose090.0): raw file record 2: missing
'sha256' (damaged session manifest)``. A migrated manifest is written in this version by the
next writer that saves it (a capture resumed, a reconstruct); a reader (``polrig info``) writes
nothing.
"""

# No ``from __future__ import annotations`` here: TypedDict reads Required/NotRequired from the
# evaluated annotations (Python 3.11).

import copy
import dataclasses
import datetime as _dt
import json
import math
import re
from typing import Annotated, Any, Callable, Literal, Mapping, NotRequired, TypedDict

from polrig.acquisition.plan import ADAPTIVE_MIN_STATES, MODES, NETWORK_BINNINGS, RESOLUTIONS, CapturePlan
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.errors import ConfigError, FormatError
from polrig.formats.exr import RESULT_PLANES
from polrig.formats.typedjson import (
    FINITE,
    Check,
    Invalid,
    Label,
    encode,
    extra_keys,
    load,
)

#: The version of the manifest this polrig writes (``schema_version``).
SCHEMA_VERSION = 7

# capture status: "acquired" = every raw frame (and the simulated rig's truth) recorded,
# processing not done yet (a resume processes it without acquiring it again)
PENDING, ACQUIRED, COMPLETE, FAILED = "pending", "acquired", "complete", "failed"
# session status
RUNNING, SESSION_COMPLETE, INTERRUPTED = "running", "complete", "interrupted"
CAPTURE_STATUSES = (PENDING, ACQUIRED, COMPLETE, FAILED)
SESSION_STATUSES = (RUNNING, SESSION_COMPLETE, INTERRUPTED)

_SHA256 = re.compile(r"[0-9a-f]{64}")


def safe_relpath(v: str) -> bool:
    """A ``/``-separated path inside the session folder (no absolute path, no ``..``)."""
    if not v or "\\" in v or "\0" in v or v.startswith("/"):
        return False
    return all(part not in ("", ".", "..") for part in v.split("/"))


# -- values with a constraint beyond their type ------------------------------------------------
RelPath = Annotated[str, Check(safe_relpath, "a relative path inside the session")]
FolderName = Annotated[str, Check(lambda v: safe_relpath(v) and "/" not in v, "a folder name")]
Sha256 = Annotated[str, Check(lambda v: bool(_SHA256.fullmatch(v)), "a SHA-256 hex digest")]
Index = Annotated[int, Check(lambda v: v >= 0, "an index >= 0")]
Count = Annotated[int, Check(lambda v: v >= 0, "a count")]
ByteCount = Annotated[int, Check(lambda v: v >= 0, "a byte count")]
Finite = Annotated[float, FINITE]
Factor = Annotated[float, Check(lambda v: math.isfinite(v) and v > 0, "a factor > 0")]
Positive = Annotated[float, Check(lambda v: math.isfinite(v) and v > 0, "a finite number > 0")]
NonNegative = Annotated[float, Check(lambda v: math.isfinite(v) and v >= 0, "a finite number >= 0")]
CaptureStatus = Literal[CAPTURE_STATUSES]
SessionStatus = Literal[SESSION_STATUSES]


# -- who, why, what (issue 34, item 7) -------------------------------------------------------------
#: Keys a user key of :class:`SampleMetadata` may not take: the record's own fields and every key
#: polrig itself writes beside them (a result EXR header's ``polrig:`` entries,
#: :meth:`polrig.app.processing.Processor.solve`, and the attributes of
#: :func:`polrig.app.dataset.open_session`'s dataset). ``tests/test_metadata.py`` checks that a
#: written result header holds no key outside this set and the user's.
RESERVED_METADATA_KEYS = frozenset({
    # the record's fields, and the EXR file's own entries
    "sample", "operator", "note", "user", "metadata", "kind", "conventions",
    # a result header (processing, single-shot, hybrid)
    "calibration_id", "mode", "demosaic", "pose_deg", "states_deg", "incident_state",
    "exposure_us", "exposures_us", "frames_per_state", "dark_frames", "layout",
    "condition_number", "units", "mask_bits", "analyzer_tolerance", "generator_tolerance",
    "planes", "uncertainty_precision", "software", "capture", "revision",
    "single_shot_geometry", "single_shot", "execution_provider", "prior", "seen_state",
    "seen_state_deg", "resolution", "network_binning", "mirror_average", "model",
    "beyond_calibration_fraction", "execution_provider_options", "execution_provider_notes",
    "network_demosaic", "output_demosaic", "prior_model", "model_size", "model_training",
    # a ``polrig infer`` result's header
    "method", "scale_dn", "alpha", "source", "state_deg", "saturation_dn", "adc_dn_per_file_dn",
    # a dataset's attributes
    "schema_version", "conventions_version", "session", "created", "updated", "status", "plan",
    "rig", "command_line", "captures", "path", "captures_without_result",
})
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _metadata_problem(sample: Any, operator: Any, note: Any, user: Any) -> str | None:
    for name, value in (("sample", sample), ("operator", operator), ("note", note)):
        if not isinstance(value, str):
            return f"{name} must be a string, got {type(value).__name__}"
    if not isinstance(user, dict):
        return f"user keys must be an object of strings, got {type(user).__name__}"
    for key, value in user.items():
        if not isinstance(key, str) or not _IDENTIFIER.fullmatch(key):
            return f"metadata key {key!r} is not an identifier (letters, digits, _; not a digit first)"
        if key in RESERVED_METADATA_KEYS or key.startswith("polrig"):
            return f"metadata key {key!r} is one of polrig's own keys; choose another name"
        if not isinstance(value, str):
            return f"metadata key {key!r}: the value must be a string, got {type(value).__name__}"
    return None


class MetadataError(ConfigError):
    """A :class:`SampleMetadata` that is refused (one line; ``field`` is ``"metadata"``)."""

    field = "metadata"


@dataclasses.dataclass(frozen=True)
class SampleMetadata:
    """Who captured what, and why (bluesky's start document is the model): ``sample`` (what is
    on the turntable), ``operator`` (who), ``note`` (why, free text) and ``user`` keys
    (``--md KEY=VALUE``: identifiers, string values, none of :data:`RESERVED_METADATA_KEYS`).
    Empty strings mean "not given". Recorded once in the manifest (``metadata``), copied into
    every result EXR header and shown by ``polrig info``."""

    sample: str = ""
    operator: str = ""
    note: str = ""
    user: dict[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        problem = _metadata_problem(self.sample, self.operator, self.note, self.user)
        if problem:
            raise MetadataError(problem)
        object.__setattr__(self, "user", dict(sorted(self.user.items())))

    def __hash__(self) -> int:
        return hash((self.sample, self.operator, self.note, tuple(self.user.items())))

    @staticmethod
    def parse_user(items) -> dict[str, str]:
        """``KEY=VALUE`` texts (``--md``, the GUI's field) as user keys; a text without ``=``
        or a key given twice is a one-line :class:`MetadataError` (the keys themselves are
        checked when the record is built)."""
        user: dict[str, str] = {}
        for item in items:
            key, eq, value = item.partition("=")
            if not eq:
                raise MetadataError(f"metadata {item!r}: give KEY=VALUE")
            if key.strip() in user:
                raise MetadataError(f"metadata key {key.strip()!r} given twice")
            user[key.strip()] = value.strip()
        return user

    @property
    def empty(self) -> bool:
        return not (self.sample or self.operator or self.note or self.user)

    def fields(self) -> dict[str, str]:
        """Flat: ``sample``, ``operator``, ``note`` (empty strings too) and each user key (a
        dataset's attributes)."""
        return {"sample": self.sample, "operator": self.operator, "note": self.note, **self.user}

    def header(self) -> dict[str, str]:
        """The entries a result EXR header gets: :meth:`fields` that are given (an empty
        record adds none, so a session without metadata writes the files it always did)."""
        return {k: v for k, v in self.fields().items() if v}



def sample_fields(attributes: Mapping[str, Any]) -> dict[str, str]:
    """The sample metadata among flat ``attributes`` (a result header's polrig entries, a
    dataset's attributes): ``sample``, ``operator``, ``note`` where present and every string
    entry that is none of :data:`RESERVED_METADATA_KEYS` (the user keys)."""
    named = {k: str(attributes[k]) for k in ("sample", "operator", "note") if k in attributes}
    return {**named, **{k: v for k, v in sorted(attributes.items())
                        if k not in RESERVED_METADATA_KEYS and not k.startswith("polrig")
                        and isinstance(v, str)}}

# -- files by role ------------------------------------------------------------------------------
class FileRecord(TypedDict):
    """A file of the session: ``path`` relative to the session folder, its SHA-256, its size."""

    path: RelPath
    sha256: Sha256
    bytes: ByteCount


class RawFrameRecord(TypedDict):
    """A raw frame and its JSON sidecar (``meta_path``); ``state_index`` indexes the plan's
    ``states_deg``; ``exposure_us`` null for a camera without exposure control."""

    path: RelPath
    sha256: Sha256
    bytes: ByteCount
    meta_path: RelPath
    meta_sha256: Sha256
    state_index: Index
    state_deg: Finite
    exposure_index: Index
    exposure_us: Finite | None
    frame: Index


class DarkFrameRecord(TypedDict):
    """A dark frame (light off) and its sidecar."""

    path: RelPath
    sha256: Sha256
    bytes: ByteCount
    meta_path: RelPath
    meta_sha256: Sha256
    exposure_index: Index
    exposure_us: Finite | None
    frame: Index


class PlaneView(TypedDict):
    """Planes inside the ``mueller`` file (no file, no checksum of their own)."""

    part_of: Literal["mueller"]
    path: RelPath
    channels: str


def _file(role: str) -> Any:
    return Annotated[FileRecord, Label(f"{role} file record: ")]


class CaptureFiles(TypedDict, total=False):
    """A capture's (or a revision's) files by role; a role is absent until written."""

    raw: Annotated[list[RawFrameRecord], Label(entry=lambda i, v: f"raw file record {i}: ")]
    dark: Annotated[list[DarkFrameRecord], Label(entry=lambda i, v: f"dark file record {i}: ")]
    truth_mueller: _file("truth_mueller")
    mueller: _file("mueller")
    preview_grid: _file("preview_grid")
    preview_dolp: _file("preview_dolp")
    preview_aolp: _file("preview_aolp")
    uncertainty: Annotated[PlaneView, Label("uncertainty view: ")]
    mask: Annotated[PlaneView, Label("mask view: ")]
    #: the model map of a result made with model selection (:mod:`polrig.solve.model_selection`)
    models: Annotated[PlaneView, Label("models view: ")]


#: Roles whose entry is a list of files (one per frame); every other role is one record.
LIST_ROLES = ("raw", "dark")
#: Roles a capture's acquisition writes (raw and dark frames, the simulated rig's truth taken
#: at the pose); every other role is a result of processing them.
ACQUISITION_ROLES = ("raw", "dark", "truth_mueller")
#: Roles that are views into another role's file.
VIEW_ROLES = ("uncertainty", "mask", "models")


# -- captures -----------------------------------------------------------------------------------
@extra_keys
class Score(TypedDict):
    """A result's error against the simulator's truth (:func:`polrig.solve.scoring.score_against_truth`;
    ``rmse`` null: no pixel to score). Its keys belong to the scorer: more are kept as they are."""

    rmse: float | None
    mae: float | None
    psnr_db: float | None
    realizable: float | None
    pixels_compared: int
    pixels_valid: NotRequired[int]
    pixels_total: NotRequired[int]
    mask_counts: NotRequired[dict[str, int]]
    condition_number: NotRequired[float | None]
    within_2sigma: NotRequired[float | None]
    chi2_per_element: NotRequired[float | None]
    mean_sigma: NotRequired[float | None]
    peak_m00: NotRequired[float | None]


class OpenScaleRecord(TypedDict):
    """The factor on a two-state hybrid prior's standard deviation along the direction the
    states leave open (:class:`polrig.solve.open_scale.OpenScale`): the ``factor``, the ``raw``
    estimate, the ``exponent`` it was taken to and the number of accepted ``values`` it rests on
    (0: none, factor 1)."""

    factor: Factor
    raw: Factor
    exponent: Finite
    values: Index


class PriorScaleRecord(TypedDict):
    """The factor a hybrid result's prior sigma was multiplied by
    (:class:`polrig.solve.prior_scale.PriorScale`): ``method`` ``innovations`` (estimated from
    the states after the seen one), ``geometry`` (that, and ``open_direction``) or ``calibrated``
    (factor 1), the ``factor``, the ``raw`` estimate, the exponent ``shrink`` it was taken to,
    and the number of ``innovations``; ``open_direction`` (``geometry`` only): the factor along
    the direction two states leave open."""

    method: Literal["innovations", "geometry", "calibrated"]
    factor: Factor
    raw: Factor
    shrink: Finite
    innovations: Index
    open_direction: NotRequired[Annotated[OpenScaleRecord, Label("open direction: ")]]


class PriorRecord(TypedDict):
    """The prior of a hybrid result (:mod:`polrig.solve.hybrid`): the single-shot model whose
    estimate and calibrated sigma of state ``seen_state``'s frame it is
    (:meth:`polrig.app.single_shot.SingleShot.prior_model`): ``graph`` (file name in the weights
    folder) and its SHA-256, the ``uncertainty.json`` SHA-256 and format version, the
    onnxruntime ``execution_provider`` that ran it, ``mirror_average``; ``seen_state`` (index
    into the plan's states) and its stage angle ``seen_state_deg``; ``joint_prior_version``
    where the prior was calibrated jointly across elements (absent: per element);
    ``sigma_scale`` the factor on its sigma (absent: a result from before it, factor 1)."""

    graph: str
    graph_sha256: Sha256
    uncertainty_sha256: Sha256
    uncertainty_version: int
    execution_provider: str
    mirror_average: bool
    seen_state: Index
    seen_state_deg: Finite
    joint_prior_version: NotRequired[int]
    sigma_scale: NotRequired[Annotated[PriorScaleRecord, Label("sigma scale: ")]]


class ModelRecord(TypedDict):
    """The single-shot model of a single-shot or hybrid result (:mod:`polrig.models.sizes`, read
    from its ``model.json``): ``size`` (``small``, ``large``; None for a weights folder of the
    user's), network ``width``, ``training_hardware`` and ``training_minutes`` (over its whole
    lineage; None where not recorded)."""

    size: str | None
    width: int | None
    training_hardware: str
    training_minutes: float | None


class RevisionResult(TypedDict):
    """A capture's part of a ``polrig reconstruct`` revision (``prior``: hybrid results only;
    ``model``: single-shot and hybrid results)."""

    status: CaptureStatus
    files: Annotated[CaptureFiles, Label("")]
    score: Annotated[Score | None, Label("")]
    reason: str | None
    prior: NotRequired[Annotated[PriorRecord, Label("prior: ")]]
    model: NotRequired[Annotated[ModelRecord, Label("model: ")]]


class AdaptiveDecision(TypedDict):
    """One decision of an adaptive capture (:mod:`polrig.app.adaptive`), made after
    ``states_taken`` states: the share of its ``object_pixels`` (the network's object mask, less
    the ``clipped_pixels`` its frame clips, which have no prior, and the ``dark_pixels``, all noise
    in its frame) that met the target then
    (``share_met``), what it did (``action``: ``take`` the state at stage
    angle ``state_deg``; ``take-min-states`` likewise where the share met the target at fewer
    states than the plan's ``min_states``; or stop: ``stop-target``, ``stop-max-states``,
    ``stop-no-object``) and
    why: the A-optimal criterion (:mod:`polrig.solve.design`, summed relative posterior variance
    over ``design_pixels`` object pixels still above target) now (``criterion``) and predicted
    after the state taken (``predicted_criterion``), and the hardware time that state cost
    (``state_time_s``, its move and frames, seconds, as the choice weighed it:
    :func:`polrig.solve.design.choose_next`; absent in sessions without the rig's ``timing``,
    whose choice was the least criterion); null where no state was chosen."""

    states_taken: Annotated[int, Check(lambda v: v >= 1, "a count >= 1")]
    share_met: Annotated[float, Check(lambda v: 0.0 <= v <= 1.0, "a share in [0, 1]")]
    object_pixels: Count
    clipped_pixels: Count
    dark_pixels: Count
    design_pixels: Count
    criterion: Finite | None
    action: Literal["take", "take-min-states", "stop-target", "stop-max-states", "stop-no-object"]
    state_deg: Finite | None
    predicted_criterion: Finite | None
    state_time_s: NotRequired[Finite | None]
    #: the factor on the prior's sigma of the decision's solve (:class:`PriorScaleRecord`); absent
    #: in decisions made before it (1)
    sigma_scale: NotRequired[Factor]


def describe_decision(decision: AdaptiveDecision) -> str:
    """One line on an adaptive ``decision``: the states taken, the share of the object pixels
    at target, and what it did (``take 60 deg (3.03 s)``, with the hardware time that state
    costs where recorded; ``stop target``...), e.g. ``2 state(s): 97.1 % of 1200 object pixels
    at target; stop target``. The one wording of a decision everywhere:
    the progress event's message (``polrig capture``, the GUI's log and list), ``polrig info``
    and the decisions the GUI shows from a resumed session's manifest."""
    what = (f"take {decision['state_deg']:g} deg" if decision["action"] in ("take", "take-min-states")
            else decision["action"].replace("-", " "))
    if decision["action"] == "take-min-states":  # at target, but fewer states than the plan's least
        what += ", the plan's fewest states not reached"
    if decision.get("state_time_s") is not None:  # what that state costs (sessions with the rig's timing)
        what += f" ({decision['state_time_s']:.2f} s)"
    return (f"{decision['states_taken']} state(s): {100 * decision['share_met']:.1f} % of "
            f"{decision['object_pixels']} object pixels at target; {what}")


def describe_prior_scale(prior: PriorRecord, n_states: int | None = None) -> str:
    """One line on a hybrid result's prior sigma (``polrig info``): ``sigma x 0.71 (innovations,
    48000 values)``, ``sigma as calibrated``; ``sigma as calibrated (no later state to scale it
    by)`` where the scale found nothing to rest on (one state); ``sigma as calibrated (before the
    scale)`` for a result made before it existed; with ``geometry``, ``; along the open direction
    x 1.2 (diffuse geometry, 9000 values)`` after it, or why it is 1: two states with no diffuse
    pixel to check it by, or ``n_states`` (the states the result was solved from, where known)
    other than two, which leave no one direction open."""
    scale = prior.get("sigma_scale")
    if scale is None:
        return "sigma as calibrated (before the scale)"
    if scale["method"] == "calibrated":
        return "sigma as calibrated"
    text = ("sigma as calibrated (no later state to scale it by)" if scale["innovations"] == 0
            else f"sigma x {scale['factor']:.3g} (innovations, {scale['innovations']} values)")
    opened = scale.get("open_direction")
    if opened is None:
        return text
    if opened["values"] > 0:
        return text + f"; along the open direction x {opened['factor']:.3g} (diffuse geometry, {opened['values']} values)"
    if n_states is not None and n_states != 2:
        return text + f"; no one direction left open at {n_states} state{'s' if n_states > 1 else ''}"
    return text + "; along the open direction as that (no diffuse pixel to check it by)"


class CaptureRecord(TypedDict):
    """One pose of the plan: its folder ``name``, status, last attempt, files, score (and
    ``prior``: the hybrid result's prior model, absent in other modes; ``model``: the single-shot
    model of a single-shot or hybrid result, absent for the reference method;
    ``adaptive``: an adaptive capture's decisions, in the order made, absent in other modes)."""

    index: Index
    name: FolderName
    pose_deg: Finite
    status: CaptureStatus
    reason: str | None
    started: str | None
    finished: str | None
    attempts: Count
    files: Annotated[CaptureFiles, Label("")]
    score: Annotated[Score | None, Label("")]
    revisions: Annotated[dict[str, RevisionResult], Label(entry=lambda k, v: f"revision {k!r}: ")]
    prior: NotRequired[Annotated[PriorRecord, Label("prior: ")]]
    model: NotRequired[Annotated[ModelRecord, Label("model: ")]]
    adaptive: NotRequired[Annotated[list[AdaptiveDecision],
                                    Label(entry=lambda i, v: f"adaptive decision {i}: ")]]


# -- the session --------------------------------------------------------------------------------
class ProcessingRecord(TypedDict):
    """How a session's own captures are processed into results, beyond its plan: written when
    the session is created, and a resumed run goes on with it (asking for another is refused),
    so that an interrupted session ends as an uninterrupted one. ``models``: ``full``, ``auto``
    or ``diffuse`` (:mod:`polrig.solve.model_selection`, :mod:`polrig.app.diffuse_route`);
    ``prior_scale``: the hybrid prior's scale (:data:`polrig.solve.prior_scale.METHODS`; in an
    adaptive session it also steers the decisions). A revision records its own
    (:class:`RevisionSettings`)."""

    models: Literal["full", "auto", "diffuse"]
    prior_scale: Literal["innovations", "geometry", "calibrated"]


def default_processing() -> ProcessingRecord:
    """The :class:`ProcessingRecord` of a session whose run asks for nothing: the 3x3 block at
    every pixel and the default prior scale (:data:`polrig.choices.DEFAULT_PRIOR_SCALE`)."""
    return {"models": "full", "prior_scale": DEFAULT_PRIOR_SCALE}


class RevisionSettings(TypedDict):
    """A ``polrig reconstruct`` revision: its name, when and how it was asked for, and the
    settings its results were made with."""

    name: FolderName
    created: str
    command_line: list[str]
    mode: Literal[MODES]
    demosaic: str
    mirror_average: bool
    resolution: Literal[RESOLUTIONS]
    network_binning: Literal[NETWORK_BINNINGS]
    seen_state: Index
    calibration_id: str
    exr_planes: list[str]
    exr_uncertainty: str
    exr_compression: str
    #: ``full``, ``auto`` (lower-order models per pixel, :mod:`polrig.solve.model_selection`) or
    #: ``diffuse`` (two states, :mod:`polrig.app.diffuse_route`); absent in revisions made before
    #: it existed (``full``)
    models: NotRequired[Literal["full", "auto", "diffuse"]]
    #: the hybrid prior's scale (:data:`polrig.solve.prior_scale.METHODS`); absent in revisions
    #: made before it existed (``calibrated``: their sigma was never scaled)
    prior_scale: NotRequired[Literal["innovations", "geometry", "calibrated"]]


class CameraFrames(TypedDict):
    """What the camera's raw frames look like: size, ROI offset (the mosaic phase), layout,
    colours (:func:`polrig.app.records.camera_frames`)."""

    width: int
    height: int
    offset_xy: list[int]
    layout: str
    colours: int


class TimingRecord(TypedDict):
    """The rig's hardware timing as the adaptive capture weighs a state's cost
    (:func:`polrig.app.records.timing_record`): the polarizer stage's declared cruise speed
    (deg/s) and acceleration (deg/s^2, null: full speed at once), the camera's readout per
    frame (us), the frames it discards after a setting change or a move (free run; else 0),
    and the time a decision is taken to cost (s, :data:`polrig.solve.design.DECISION_S`)."""

    stage_speed_deg_s: Positive
    stage_accel_deg_s2: Positive | None
    readout_us: NonNegative
    settle_frames: Count
    decision_s: NonNegative


class RigRecord(TypedDict):
    """The rig a session was captured on (:func:`polrig.app.records.rig_record`): null where a
    session from before a key existed did not record it (``timing``, absent in sessions from
    before it: their adaptive captures chose by the criterion alone, and resume so)."""

    simulated: bool
    config: dict[str, Any] | None
    devices: dict[str, dict[str, Any]]
    sim_parameters: dict[str, Any] | None
    camera_frames: CameraFrames | None
    sensor_model: dict[str, float] | None
    timing: NotRequired[TimingRecord]


class Software(TypedDict):
    name: str
    version: str


@extra_keys
class HistoryEvent(TypedDict):
    """An event (``created``, ``resumed``, ``session interrupted``...) and its details."""

    time: str
    event: str


def _capture_label(i: int, cap: Any) -> str:
    name = cap.get("name") if isinstance(cap, dict) else None
    return f"capture {i}" + (f" ({name})" if isinstance(name, str) else "") + ": "


class SessionManifest(TypedDict):
    """``session.json``, schema version :data:`SCHEMA_VERSION` (``docs/session-schema.md``)."""

    schema_version: Literal[SCHEMA_VERSION]
    software: Software
    conventions_version: str
    created: str
    updated: str
    status: SessionStatus
    status_reason: str | None
    command_line: list[str]
    rig: RigRecord
    calibration_id: str
    plan: CapturePlan
    #: how the captures are processed (:class:`ProcessingRecord`); null in sessions from before
    #: version 7, which did not record it: a resumed one takes what its run asks for, as they did
    processing: Annotated[ProcessingRecord | None, Label("processing: ")]
    #: who, why, what (:class:`SampleMetadata`; empty in sessions from before version 4)
    metadata: Annotated[SampleMetadata, Label("metadata: ")]
    planned_bytes: ByteCount
    #: the plan's hardware time, computed when the first run starts (null until then)
    hardware_time_s: float | None
    captures: Annotated[list[CaptureRecord], Label(entry=_capture_label)]
    revisions: Annotated[list[RevisionSettings], Label(entry=lambda i, v: f"revision entry {i}: ")]
    history: Annotated[list[HistoryEvent], Label(entry=lambda i, v: f"history entry {i}: ")]


# -- writing and reading ------------------------------------------------------------------------
def encode_manifest(manifest: SessionManifest) -> bytes:
    """The bytes of ``session.json`` (the plan as its fields)."""
    return (json.dumps(manifest, indent=1, default=encode) + "\n").encode("utf-8")


def plan_json(plan: CapturePlan) -> dict[str, Any]:
    """The plan as the manifest stores it (every field; lists for tuples)."""
    return json.loads(json.dumps(plan, default=encode))


def read_plan(data: Any, where: str = "plan") -> CapturePlan:
    """A plan as the manifest stores it, read back (:class:`FormatError` naming the key)."""
    try:
        return load(CapturePlan, data, context="")
    except Invalid as exc:
        raise FormatError(f"{where}: {exc}") from None


def check_manifest(manifest: SessionManifest) -> None:
    """Check a manifest built in memory against the types (a new session's, before it is
    written): :class:`polrig.formats.typedjson.Invalid` naming the key if it does not fit."""
    _load(json.loads(encode_manifest(manifest)))


def parse(data: Any, where: str = "session.json") -> SessionManifest:
    """The manifest ``data`` (parsed JSON of any known version) migrated to this version and
    checked against :class:`SessionManifest`; one :class:`FormatError` line otherwise."""
    if not isinstance(data, dict) or "captures" not in data:
        raise FormatError(f"{where}: not a polrig session manifest")
    version = data.get("schema_version")
    if type(version) is not int or (version != SCHEMA_VERSION and version not in MIGRATIONS):
        known = ", ".join(str(v) for v in [*sorted(MIGRATIONS), SCHEMA_VERSION])
        raise FormatError(f"{where}: session schema version {version!r}, this polrig reads "
                          f"versions {known}")
    if version != SCHEMA_VERSION:
        data = copy.deepcopy(data)  # the caller's data stays as it was read
        while data["schema_version"] != SCHEMA_VERSION:
            data = MIGRATIONS[data["schema_version"]](data)
    try:
        return _load(data)
    except Invalid as exc:
        raise FormatError(f"{where}: {exc} (damaged session manifest)") from None


def _load(data: dict[str, Any]) -> SessionManifest:
    manifest = load(SessionManifest, data)
    poses = manifest["plan"].poses_deg
    caps = manifest["captures"]
    if len(caps) != len(poses):
        raise Invalid(f"{len(caps)} captures listed for the {len(poses)} poses of the plan")
    for i, cap in enumerate(caps):
        if cap["index"] != i:
            raise Invalid(f"{_capture_label(i, cap)}'index' is {cap['index']}, but it is entry "
                          f"{i} of the list")
    return manifest


# -- migrations ---------------------------------------------------------------------------------
#: Result files of plans and revisions from before the ``exr_*`` fields existed were written
#: with float32 uncertainty planes and ZIP (today's default is half): the choice they were
#: written with, so that such a session resumes and reprocesses to the same files.
LEGACY_EXR: dict[str, Any] = {"exr_planes": list(RESULT_PLANES), "exr_uncertainty": "float",
                              "exr_compression": "zip"}
#: Plan fields a version-1 plan may lack (written before they existed), as it was captured.
V1_PLAN_DEFAULTS: dict[str, Any] = {"mirror_average": False, "resolution": "superpixel",
                                    "network_binning": 1, **LEGACY_EXR}
#: The same for a version-1 revision's settings.
V1_REVISION_DEFAULTS: dict[str, Any] = {"command_line": [], **V1_PLAN_DEFAULTS}


def migrate_v1(m: dict[str, Any]) -> dict[str, Any]:
    """Version 1 (polrig up to the layered package, docs/session-schema.md of that time) to 2.

    Keys version 1 left out (older sessions, or optional in it) are stated with the value the
    session was written with: the plan's and revisions' ``mirror_average`` (false),
    ``resolution`` (superpixel), ``network_binning`` (1), ``exr_*`` (:data:`LEGACY_EXR`) and
    every other plan field at the value the plan had then; a capture's ``reason``,
    ``started``, ``finished`` (null), ``attempts`` (0), ``score`` (null), ``revisions`` ({});
    a revision result's ``reason`` (null); ``hardware_time_s``, ``rig.camera_frames``,
    ``rig.sensor_model``, ``rig.config``, ``rig.sim_parameters`` (null: not recorded). A
    capture's ``mode`` goes (it is the plan's, stored once); plan keys that are no plan field
    any more go too, named in the ``schema migrated`` history event. Whatever is damaged is
    left for the check that follows to name."""
    m = dict(m, schema_version=2)
    for key, value in (("status_reason", None), ("command_line", []), ("revisions", []),
                       ("history", []), ("hardware_time_s", None)):
        m.setdefault(key, value)
    if isinstance(m.get("conventions_version"), (int, float)) and \
            not isinstance(m.get("conventions_version"), bool):
        m["conventions_version"] = str(m["conventions_version"])
    rig = m.setdefault("rig", {})
    if isinstance(rig, dict):
        rig.setdefault("simulated", False)
        rig.setdefault("devices", {})
        for key in ("config", "sim_parameters", "camera_frames", "sensor_model"):
            rig.setdefault(key, None)
    dropped: dict[str, Any] = {}
    plan = m.get("plan")
    if isinstance(plan, dict):
        fields = {f.name: f for f in dataclasses.fields(CapturePlan)}
        dropped = {k: v for k, v in plan.items() if k not in fields}
        plan = {k: v for k, v in plan.items() if k in fields}
        for key, value in V1_PLAN_DEFAULTS.items():
            if key not in plan or (key.startswith("exr_") and not plan[key]):
                plan[key] = copy.deepcopy(value)
        for name, f in fields.items():  # the oldest plans: the values of their time
            if name not in plan and f.default is not dataclasses.MISSING:
                plan[name] = list(f.default) if isinstance(f.default, tuple) else f.default
        m["plan"] = plan
    for cap in m.get("captures") if isinstance(m.get("captures"), list) else []:
        if not isinstance(cap, dict):
            continue
        cap.pop("mode", None)
        for key, value in (("reason", None), ("started", None), ("finished", None),
                           ("attempts", 0), ("score", None), ("revisions", {})):
            cap.setdefault(key, value)
        _migrate_score_v1(cap)
        for rev in cap["revisions"].values() if isinstance(cap["revisions"], dict) else []:
            if isinstance(rev, dict):
                rev.setdefault("reason", None)
                rev.setdefault("score", None)
                _migrate_score_v1(rev)
    for rev in m["revisions"] if isinstance(m["revisions"], list) else []:
        if isinstance(rev, dict):
            for key, value in V1_REVISION_DEFAULTS.items():
                if key not in rev or (key.startswith("exr_") and not rev[key]):
                    rev[key] = copy.deepcopy(value)
    if isinstance(m["history"], list):
        event: dict[str, Any] = {"time": utc_now(), "event": "schema migrated",
                                 "from_version": 1, "to_version": 2}
        if dropped:
            event["dropped_plan_keys"] = dropped
        m["history"].append(event)
    return m


def _migrate_score_v1(entry: dict[str, Any]) -> None:
    """Version 1 accepted a score with ``rmse`` null ("no pixels to score") and nothing else."""
    score = entry.get("score")
    if isinstance(score, dict) and score.get("rmse") is None:
        for key in ("rmse", "mae", "psnr_db", "realizable"):
            score.setdefault(key, None)
        score.setdefault("pixels_compared", 0)


def utc_now() -> str:
    """Current UTC time as an ISO 8601 string with a ``Z`` suffix (second resolution)."""
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace(
        "+00:00", "Z")


def migrate_v2(m: dict[str, Any]) -> dict[str, Any]:
    """Version 2 to 3 (the hybrid mode): the plan's and every revision's ``seen_state`` (0: the
    only value a version-2 session could mean; it is used by the hybrid mode only, which did
    not exist). A capture's or a revision result's ``prior`` stays absent (no hybrid result).
    Whatever is damaged is left for the check that follows to name."""
    m = dict(m, schema_version=3)
    if isinstance(m.get("plan"), dict):
        m["plan"] = dict(m["plan"])
        m["plan"].setdefault("seen_state", 0)
    if isinstance(m.get("revisions"), list):
        m["revisions"] = [dict(r, seen_state=r.get("seen_state", 0)) if isinstance(r, dict) else r
                          for r in m["revisions"]]
    if isinstance(m.get("history"), list):
        m["history"] = [*m["history"], {"time": utc_now(), "event": "schema migrated",
                                        "from_version": 2, "to_version": 3}]
    return m


def migrate_v3(m: dict[str, Any]) -> dict[str, Any]:
    """Version 3 to 4 (sample metadata, issue 34 item 7): ``metadata`` is the empty
    :class:`SampleMetadata` (a version-3 session recorded none). Whatever is damaged is left for
    the check that follows to name."""
    m = dict(m, schema_version=4)
    m.setdefault("metadata", {"sample": "", "operator": "", "note": "", "user": {}})
    if isinstance(m.get("history"), list):
        m["history"] = [*m["history"], {"time": utc_now(), "event": "schema migrated",
                                        "from_version": 3, "to_version": 4}]
    return m


def migrate_v4(m: dict[str, Any]) -> dict[str, Any]:
    """Version 4 to 5 (the adaptive mode, issue 33 item 2): the plan's ``target_sigma`` (0),
    ``target_share`` (0.95) and ``max_states`` (4), the values of every plan that is not
    adaptive (a version-4 session cannot be). A capture's ``adaptive`` decisions stay absent.
    Whatever is damaged is left for the check that follows to name."""
    m = dict(m, schema_version=5)
    if isinstance(m.get("plan"), dict):
        m["plan"] = {**m["plan"]}
        for key, value in (("target_sigma", 0.0), ("target_share", 0.95), ("max_states", 4)):
            m["plan"].setdefault(key, value)
    if isinstance(m.get("history"), list):
        m["history"] = [*m["history"], {"time": utc_now(), "event": "schema migrated",
                                        "from_version": 4, "to_version": 5}]
    return m


def migrate_v5(m: dict[str, Any]) -> dict[str, Any]:
    """Version 5 to 6 (the adaptive mode's fewest states, ``min_states``): 1 in an adaptive
    plan (a version-5 adaptive pose could stop on its first state, and a resumed session takes
    the same decisions on the same frames), the default
    (:data:`polrig.acquisition.plan.ADAPTIVE_MIN_STATES`) in any other plan, as every plan that
    is not adaptive holds it. Whatever is damaged is left for the check that follows to name."""
    m = dict(m, schema_version=6)
    if isinstance(m.get("plan"), dict):
        m["plan"] = {**m["plan"]}
        m["plan"].setdefault("min_states", 1 if m["plan"].get("mode") == "adaptive" else ADAPTIVE_MIN_STATES)
    if isinstance(m.get("history"), list):
        m["history"] = [*m["history"], {"time": utc_now(), "event": "schema migrated",
                                        "from_version": 5, "to_version": 6}]
    return m


def migrate_v6(m: dict[str, Any]) -> dict[str, Any]:
    """Version 6 to 7 (the session's processing options, ``processing``): null, as a version-6
    session did not record them (its resumed runs take what they ask for, as they did; a
    resumed run's prior scale still follows the results already made,
    :func:`polrig.app.capture_request.resumed_prior_scale`)."""
    m = dict(m, schema_version=7)
    m.setdefault("processing", None)
    if isinstance(m.get("history"), list):
        m["history"] = [*m["history"], {"time": utc_now(), "event": "schema migrated",
                                        "from_version": 6, "to_version": 7}]
    return m


#: Version -> the function that migrates a manifest of that version to the next one.
MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {
    1: migrate_v1, 2: migrate_v2, 3: migrate_v3, 4: migrate_v4, 5: migrate_v5, 6: migrate_v6}
