"""A capture's request, checked before anything opens, and the session it opens.

:class:`CaptureRequest` is what ``polrig capture`` and the GUI ask for, typed (``None``: not
given). :func:`prepare_capture` validates it before any device opens or any file is written
(a new session's plan, folder and calibration; a resumed session's lock, plan, metadata,
calibration and processing options) and gives a :class:`PreparedCapture`;
:func:`open_session` then checks it against the open rig and creates the session or reopens
the resumed one. :func:`polrig.app.capture.run_capture` takes these steps in this order; no
shell takes them itself (``tests/test_architecture.py``).

Refusals are one-line :class:`polrig.acquisition.plan.PlanError` s naming the field (or
``FileNotFoundError``/``FileExistsError``), raised before anything is written.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

from polrig.acquisition.plan import ADAPTIVE_MIN_STATES, PRIOR_MODES, CapturePlan, ExrChoice, PlanError
from polrig.app.calibrations import (
    Calibration,
    check_calibration_fits_rig,
    check_plan,
    load_calibration,
    single_shot_geometry,
)
from polrig.app.diffuse_route import check_diffuse_states, check_geometry
from polrig.app.manifest import ProcessingRecord, SampleMetadata
from polrig.app.processing import check_prior_scale
from polrig.app.records import check_resume_rig, check_rig_for_plan
from polrig.app.rig import load_rig_config
from polrig.app.session import MANIFEST_NAME, Session, folder_is_empty
from polrig.app.sessionio import check_resume_space, create_session
from polrig.choices import DEFAULT_PRIOR_SCALE, MODEL_CHOICES

__all__ = ["CaptureRequest", "PreparedCapture", "check_model_choice", "check_models",
           "check_prior_scale_applies", "open_session", "prepare_capture", "resumed_prior_scale",
           "resumed_processing"]


@dataclasses.dataclass(frozen=True)
class CaptureRequest:
    """What a capture is asked to do, typed (``polrig capture`` builds it from its options,
    the GUI from its form). ``None`` means "not given": the default for a new session, the
    session's own value on ``resume`` (where a value that contradicts the session's plan is
    refused). Angles in degrees, exposures in microseconds."""

    out: pathlib.Path
    poses_deg: tuple[float, ...] | None = None
    mode: str | None = None
    states_deg: tuple[float, ...] | None = None
    frames_per_state: int | None = None
    exposures_us: tuple[float, ...] | None = None
    dark_frames: int | None = None
    demosaic: str | None = None
    mirror_average: bool | None = None
    resolution: str | None = None
    #: single-shot network binning (1 or 2: :attr:`polrig.acquisition.plan.CapturePlan.network_binning`)
    network_binning: int | None = None
    #: hybrid: the index into the states of the frame the network sees
    #: (:attr:`polrig.acquisition.plan.CapturePlan.seen_state`)
    seen_state: int | None = None
    #: adaptive: the stopping rule (:attr:`polrig.acquisition.plan.CapturePlan.target_sigma`,
    #: ``target_share``, ``max_states``, ``min_states``; ``min_states`` not given and a
    #: ``max_states`` below its default: ``max_states``)
    target_sigma: float | None = None
    target_share: float | None = None
    max_states: int | None = None
    min_states: int | None = None
    #: the result EXR's plane groups, uncertainty precision and compression
    #: (:class:`polrig.acquisition.plan.ExrChoice`)
    exr_planes: tuple[str, ...] | None = None
    exr_uncertainty: str | None = None
    exr_compression: str | None = None
    config: pathlib.Path | None = None
    calibration: pathlib.Path | None = None
    resume: bool = False
    #: where the single-shot network runs (``auto``, ``cpu``, ``cuda``: :mod:`polrig.models.devices`):
    #: a run option, not part of the plan (a resumed session may run on another device); the
    #: provider used is recorded in each result's header
    device: str = "auto"
    #: which shipped single-shot model (``auto``, ``small``, ``large``: :mod:`polrig.models.sizes`):
    #: a run option like ``device``; each result records its size, training hardware and minutes
    model_size: str = "auto"
    #: ``full``, ``auto`` or ``diffuse``: lower-order models per pixel (:mod:`polrig.solve.model_selection`,
    #: :mod:`polrig.app.diffuse_route`; reference and hybrid modes): a processing option, not
    #: part of the plan, recorded in the session (:class:`polrig.app.manifest.ProcessingRecord`)
    #: and in each result (its ``models`` view in the manifest, the header's
    #: ``model_selection``); ``None``: ``full`` for a new session, on ``resume`` the session's
    #: (another one is refused there: one session's results are made one way)
    models: str | None = None
    #: the hybrid prior's scale, ``innovations``, ``geometry`` or ``calibrated``
    #: (:class:`polrig.app.processing.Processor`): a processing option recorded like ``models``;
    #: ``None``: :data:`polrig.choices.DEFAULT_PRIOR_SCALE` for a new session, on ``resume`` the
    #: session's (another one is refused there)
    prior_scale: str | None = None
    #: who, why, what (:class:`polrig.app.manifest.SampleMetadata`): recorded in the manifest
    #: and every result header; ``None``: empty for a new session, the stored one on ``resume``
    #: (a different one is refused there)
    metadata: SampleMetadata | None = None

    def plan_fields(self) -> dict[str, Any]:
        """The :class:`polrig.acquisition.plan.CapturePlan` fields this request gives (not ``None``)."""
        names = ("poses_deg", "mode", "states_deg", "frames_per_state", "exposures_us",
                 "dark_frames", "demosaic", "mirror_average", "resolution", "network_binning",
                 "seen_state", "target_sigma", "target_share", "max_states", "min_states", "exr_planes",
                 "exr_uncertainty", "exr_compression")
        fields = {k: getattr(self, k) for k in names if getattr(self, k) is not None}
        if self.min_states is None and isinstance(self.max_states, int) and not isinstance(self.max_states, bool) \
                and 1 <= self.max_states < ADAPTIVE_MIN_STATES and fields.get("mode") == "adaptive":
            fields["min_states"] = self.max_states  # fewer states asked for than the default least
        if "exr_planes" in fields:  # as the plan holds them (mueller always, in order)
            fields["exr_planes"] = ExrChoice(planes=fields["exr_planes"]).planes
        return fields

    def plan(self) -> CapturePlan:
        """The plan of a new session: the given fields, defaults for the others."""
        fields = self.plan_fields()
        if "poses_deg" not in fields:
            raise PlanError("poses_deg", "no poses given (e.g. 0:360:90)")
        if fields.get("mode") == "single-shot" and len(fields.get("states_deg", ())) > 1:
            raise PlanError("states_deg", "the single-shot method captures one polarizer "
                                          "state per pose; give one state (e.g. 0)")
        if fields.get("mode") == "adaptive" and len(fields.get("states_deg", ())) > 1:
            raise PlanError("states_deg", "the adaptive method starts each pose at one polarizer "
                                          "state (the network's) and chooses the others; give one "
                                          "state (e.g. 0)")
        return CapturePlan(**fields)


@dataclasses.dataclass
class PreparedCapture:
    """A validated :class:`CaptureRequest`: nothing opened, nothing written yet."""

    out: pathlib.Path
    plan: CapturePlan
    calibration: Calibration
    resume_session: Session | None  # the session to continue, or None
    #: a new session's metadata (a resumed one keeps its own)
    metadata: SampleMetadata = dataclasses.field(default_factory=SampleMetadata)
    #: the hybrid prior's scale (:attr:`CaptureRequest.prior_scale`, resolved)
    prior_scale: str = DEFAULT_PRIOR_SCALE
    #: lower-order models per pixel (:attr:`CaptureRequest.models`, resolved)
    models: str = "full"

    def processing(self) -> ProcessingRecord:
        """What a new session records of how its captures are processed."""
        return {"models": self.models, "prior_scale": self.prior_scale}


def prepare_capture(request: CaptureRequest) -> PreparedCapture:
    """Validate ``request`` before any device opens or any file is written.

    A new session: its plan, an output folder that is new or empty, the calibration set, a
    plan that can give a result (:func:`polrig.app.calibrations.check_plan`). A resumed one: the
    session is opened for writing (its lock taken: :class:`polrig.app.session.SessionBusy` if
    another process writes it), the request must not contradict its plan, the calibration
    must be the one it was captured with. Raises ``FileNotFoundError``/``FileExistsError``
    or :class:`polrig.acquisition.plan.PlanError` (one line; ``field`` says what it is about).
    """
    out = pathlib.Path(request.out)
    if request.config is not None and not pathlib.Path(request.config).is_file():
        raise FileNotFoundError(f"rig configuration {request.config}: no such file")
    session = None
    if request.resume:
        if not (out / MANIFEST_NAME).is_file():
            raise FileNotFoundError(f"{out} holds no session to resume")
        # opened for writing: its lock first, so the manifest read is the one this run continues
        session = Session.open(out, lock=True)
        try:
            plan = session.plan
            for key, value in request.plan_fields().items():
                if value != getattr(plan, key):
                    raise PlanError(key, f"the session was planned with {key}="
                                         f"{getattr(plan, key)!r}, this run asks for {value!r}")
            stored = session.manifest["metadata"]
            if request.metadata is not None and request.metadata != stored:
                raise PlanError("metadata", f"the session was captured with metadata "
                                            f"{_metadata_text(stored)}, this run asks for "
                                            f"{_metadata_text(request.metadata)}; leave the "
                                            f"metadata out to keep the stored one")
            calibration = load_calibration(request.calibration, session=session)
            check_plan(plan, calibration, request.device, request.model_size)  # states conditioning, single-shot model
            check_prior_scale_applies(plan, request.prior_scale)
            models, prior_scale = resumed_processing(session, request.models, request.prior_scale)
            check_models(models, plan, calibration, request.config)
        except BaseException:
            session.unlock()
            raise
    else:
        plan = request.plan()
        if out.exists() and not out.is_dir():
            raise PlanError("out", "exists and is not a folder", subject=str(out),
                            what="output")
        if not folder_is_empty(out):
            raise PlanError("out", "folder is not empty; choose a new folder, or resume the "
                                   "session in it", subject=str(out), what="output")
        calibration = load_calibration(request.calibration)
        check_plan(plan, calibration, request.device, request.model_size)  # states conditioning, single-shot model
        models = check_model_choice(request.models or "full")
        check_models(models, plan, calibration, request.config)
        check_prior_scale_applies(plan, request.prior_scale)
        prior_scale = check_prior_scale(request.prior_scale or DEFAULT_PRIOR_SCALE)
    return PreparedCapture(out, plan, calibration, session,
                           request.metadata if request.metadata is not None else SampleMetadata(),
                           prior_scale, models)


def resumed_processing(session: Session, models: str | None, prior_scale: str | None) -> tuple[str, str]:
    """``(models, prior_scale)`` a resumed ``session`` goes on with: those it recorded when it
    was created (:class:`polrig.app.manifest.ProcessingRecord`). Asking for another is a
    one-line :class:`PlanError` of the option. A session from before version 7 recorded none:
    ``models`` as asked (default ``full``) and the prior scale of :func:`resumed_prior_scale`."""
    stored = session.manifest.get("processing")
    if stored is None:
        return check_model_choice(models or "full"), resumed_prior_scale(session, prior_scale)
    for field, asked, option in (("models", models, "--models"), ("prior_scale", prior_scale, "--prior-scale")):
        if asked is not None and asked != stored[field]:
            raise PlanError(field, f"the session's captures are processed with {field}={stored[field]!r}, this run "
                                   f"asks for {asked!r}; leave it out to go on with {stored[field]!r}, or "
                                   f"reconstruct the session with another")
    return stored["models"], stored["prior_scale"]


def resumed_prior_scale(session: Session, asked: str | None) -> str:
    """The prior scale a resumed ``session`` goes on with: the one its hybrid results were made
    with (their prior records' ``sigma_scale``; a result from before it: ``calibrated``), else
    ``asked`` or :data:`polrig.choices.DEFAULT_PRIOR_SCALE`. Asking for another is a one-line :class:`PlanError` of
    ``prior_scale``: one session's results are made one way."""
    made = [c["prior"].get("sigma_scale", {"method": "calibrated"})["method"]
            for c in session.captures if "prior" in c]
    if not made:
        return check_prior_scale(asked or DEFAULT_PRIOR_SCALE)
    if asked is not None and asked != made[0]:
        raise PlanError("prior_scale", f"the session's results were made with the prior scale {made[0]!r}, "
                                       f"this run asks for {asked!r}; leave it out to go on with {made[0]!r}, "
                                       f"or reconstruct the session with another")
    return made[0]


def check_prior_scale_applies(plan: CapturePlan, prior_scale: str | None) -> None:
    """A prior scale asked for (not None) in a plan without the network's prior (reference,
    single-shot) is a one-line :class:`PlanError` of ``prior_scale``, as the adaptive mode's
    options are outside it: it would be recorded and do nothing."""
    if prior_scale is not None and plan.mode not in PRIOR_MODES:
        raise PlanError("prior_scale", "applies to the hybrid and adaptive methods only (the network's "
                                       "estimate as a prior)", subject=prior_scale, what="prior scale")


def check_model_choice(models: str) -> str:
    """``models`` when it is one of :data:`polrig.choices.MODEL_CHOICES`, else a one-line
    :class:`PlanError` of ``models``."""
    if models not in MODEL_CHOICES:
        raise PlanError("models", f"must be one of {', '.join(MODEL_CHOICES)}", subject=repr(models), what="models")
    return models


def check_models(models: str, plan: CapturePlan, calibration: Calibration, config=None) -> None:
    """``models`` ``diffuse``: a hybrid plan at two states, and the rig's geometry known (the
    calibration's or the rig configuration's ``config``; :mod:`polrig.app.diffuse_route`),
    one-line :class:`PlanError` s of ``models`` before any device opens."""
    if models == "diffuse":
        check_diffuse_states(plan.mode, len(plan.states_deg))
        check_geometry(single_shot_geometry(calibration, load_rig_config(config)))


def open_session(prepared: PreparedCapture, rig, command_line: list[str]) -> Session:
    """The session to run on ``rig``: the resumed one (after checking that ``rig`` is the
    rig it was captured on, :func:`polrig.app.records.check_resume_rig`, and the free disk space
    for what is left) or a new one created in ``prepared.out``. The calibration set must fit
    the camera (:func:`polrig.app.calibrations.check_calibration_fits_rig`) and the plan's
    exposures its range (:func:`polrig.app.records.check_rig_for_plan`), both before any device
    moves; a refusal writes nothing. The session returned holds its lock until
    :func:`run_session` ends."""
    if prepared.resume_session is not None:
        session = prepared.resume_session
        try:
            session.lock()  # no-op when prepare_capture took it
            check_resume_rig(session, rig)
            check_calibration_fits_rig(prepared.calibration, rig)
            check_rig_for_plan(rig, prepared.plan)
            check_resume_space(session, rig, len(session.next_pending()))
        except BaseException:
            session.unlock()
            raise
        session.log("resume command", command_line=command_line)
        return session
    check_calibration_fits_rig(prepared.calibration, rig)
    check_rig_for_plan(rig, prepared.plan)
    return create_session(prepared.out, rig, prepared.plan,
                          calibration_id=prepared.calibration.id, command_line=command_line,
                          metadata=prepared.metadata, processing=prepared.processing())


def _metadata_text(md: SampleMetadata) -> str:
    return "{" + ", ".join(f"{k}={v!r}" for k, v in md.header().items()) + "}"
