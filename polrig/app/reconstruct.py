"""A new revision of a session from its raw frames (``polrig reconstruct``): what the revision
records and needs, checked before it exists (:func:`revision_plan`, shared with
:mod:`polrig.app.cluster`), and the serial run over its captures (:func:`reprocess_session`)."""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, Callable, Mapping

from polrig.acquisition.plan import NETWORK_MODES, check_seen_state
from polrig.app.calibrations import (
    Calibration,
    check_calibration_fits,
    nominal_calibration,
    single_shot_geometry,
)
from polrig.app.diffuse_route import check_geometry
from polrig.app.processing import Processor
from polrig.app.records import session_frame_geometry, session_sensor_model
from polrig.app.session import (
    COMPLETE,
    FAILED,
    PENDING,
    Session,
    SignalGuard,
    interruption_reason,
    is_disk_full,
)
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.solve.reference import validate_states


class ReconstructIncomplete(PolrigError):
    """Some captures of a :func:`reprocess_session` revision failed (damaged or missing
    files); the others were processed. ``revision`` names it, ``failed`` lists
    ``(capture index, reason)``."""

    def __init__(self, session: Session, revision: str, failed: list[tuple[int, str]],
                 attempted: int):
        self.revision, self.failed = revision, failed
        names = "; ".join(f"capture {i} ({session.capture(i)['name']}): {reason}"
                          for i, reason in failed)
        others = "" if len(failed) == attempted else ", the others are complete"
        super().__init__(f"revision {revision}: {len(failed)} of {attempted} capture(s) "
                         f"failed{others}: {names}")


def reprocess_session(session: Session, *, mode: str | None = None, demosaic: str | None = None,
                      mirror_average: bool | None = None, calibration: Calibration | None = None,
                      command_line: list[str] | None = None,
                      progress: Callable[[int, dict[str, Any] | None], None] | None = None,
                      on_failed: Callable[[int, str], None] | None = None,
                      resolution: str | None = None, device: str = "auto",
                      exr: Mapping[str, Any] | None = None,
                      network_binning: int | None = None, seen_state: int | None = None,
                      model_size: str = "auto", models: str | None = None,
                      prior_scale: str = DEFAULT_PRIOR_SCALE) -> str:
    """Re-process every complete capture from its raw frames into a new revision (raw data
    and earlier results untouched). Returns the revision name.

    ``mode`` ``hybrid`` works on any session with at least one polarizer state: ``seen_state``
    (index into the session's states; default: the session's where it was hybrid, else 0) names
    the frame the network sees.

    ``resolution`` (single-shot output grid, :class:`polrig.app.processing.Processor`; default: the session's where it
    stays single-shot, else ``superpixel``) and ``network_binning`` (single-shot, 1 or 2; default:
    the session's where it stays single-shot, else 1) are recorded with the revision; ``device``
    (where the network runs) is not a setting of the result: the provider used is in its header;
    nor is ``model_size`` (which shipped model, :mod:`polrig.models.sizes`): its results record it.
    ``exr``: the result files' format, fields of :class:`polrig.acquisition.plan.ExrChoice` (``planes``,
    ``uncertainty``, ``compression``) overriding the session plan's; recorded with the
    revision. ``models``: ``full`` (default: never applied silently) or ``auto``
    (:class:`polrig.app.processing.Processor`), recorded with the revision; so is ``prior_scale`` (hybrid:
    ``innovations`` or ``calibrated``, :class:`polrig.app.processing.Processor`).

    A capture that cannot be processed (a raw frame missing or changed, a damaged truth file)
    is marked ``failed`` in the revision with its reason (``on_failed(index, reason)`` is
    called) and the others are processed; at the end :class:`ReconstructIncomplete` names
    the failed captures. A full disk stops the revision (the capture is marked failed, the
    error raised). The session's lock is held while it runs (:class:`polrig.app.session.SessionBusy` if another
    process writes the session; the manifest is re-read under it); SIGINT/SIGTERM leave the
    capture in progress ``pending`` in the revision and raise ``KeyboardInterrupt``."""
    was_locked = session.locked
    session.lock()
    try:
        if not was_locked:
            session.reload()  # under the lock: the manifest no other writer changes any more
        return _reprocess(session, mode, demosaic, mirror_average, calibration, command_line,
                          progress, on_failed, resolution, device, exr, network_binning, seen_state,
                          model_size, models, prior_scale)
    finally:
        if not was_locked:
            session.unlock()


def revision_plan(session: Session, mode: str | None, demosaic: str | None,
                  mirror_average: bool | None, calibration: Calibration | None,
                  resolution: str | None = None, device: str = "auto",
                  exr: Mapping[str, Any] | None = None, network_binning: int | None = None,
                  seen_state: int | None = None, model_size: str = "auto",
                  models: str | None = None, prior_scale: str = DEFAULT_PRIOR_SCALE
                  ) -> tuple[dict[str, Any], Processor, list[int]]:
    """What a new revision of ``session`` records and needs, checked before it exists (an
    impossible request records nothing): ``(settings, processor, captures)`` -- the
    revision's settings (``mode``, ``demosaic``, ``mirror_average``, ``resolution``,
    ``network_binning``, ``seen_state``, ``calibration_id``, ``exr_planes``, ``exr_uncertainty``,
    ``exr_compression``, ``models``, ``prior_scale``; ``None`` arguments, and the :class:`polrig.acquisition.plan.ExrChoice` fields ``exr`` does not name or gives as ``None``,
    take the session's), its :class:`polrig.app.processing.Processor` (on
    ``device``) and the indices of the complete captures to process. Shared by
    :func:`reprocess_session` and :mod:`polrig.app.cluster`."""
    plan = session.plan
    mode = mode or plan.mode
    demosaic = demosaic or plan.demosaic
    if mirror_average is None:  # the session's choice where it ran the network already
        mirror_average = plan.mirror_average and mode in NETWORK_MODES and plan.mode in NETWORK_MODES
    if seen_state is None:  # the session's where it stays hybrid
        seen_state = plan.seen_state if mode == "hybrid" and plan.mode == "hybrid" else 0
    if mode == "adaptive" and plan.mode != "adaptive":
        raise ConfigError(f"{session.root}: captured in {plan.mode} mode; the adaptive method chooses "
                          f"its states while capturing (reconstruct with the hybrid method)")
    acquired = plan.acquired_states_deg()
    check_seen_state(seen_state, mode, len(acquired))
    if resolution is None:  # the session's where it stays single-shot
        resolution = plan.resolution if mode == "single-shot" else "superpixel"
    if network_binning is None:  # the session's where it stays single-shot
        network_binning = plan.network_binning if mode == "single-shot" else 1
    choice = dataclasses.replace(plan.exr,
                                 **{k: v for k, v in (exr or {}).items() if v is not None})
    calibration = calibration or nominal_calibration()
    if calibration.sensor is not None:  # before a revision exists: nothing recorded
        layout, readout, size = session_frame_geometry(session)
        check_calibration_fits(calibration, layout=layout, readout=readout, sensor_size=size,
                               what=f"the camera of session {session.root}")
    if models is None:  # off unless asked: never applied silently
        models = "full"
    processor = Processor(mode, demosaic, calibration, session_sensor_model(session), mirror_average,
                          resolution, device, choice, network_binning, seen_state, model_size,
                          models, len(acquired), prior_scale)
    if models == "diffuse":  # before a revision exists
        check_geometry(single_shot_geometry(calibration, (session.manifest.get("rig") or {}).get("config")))
    done = [c["index"] for c in session.captures if c["status"] == COMPLETE]
    if not done:
        raise ConfigError(f"{session.root}: no complete capture to reconstruct")
    if mode == "reference" and plan.mode == "adaptive":
        # each pose took the states its decisions chose: solved per capture, those of fewer than
        # 3 states fail with their reason and the others go on (before a revision exists: a
        # session where no pose took 3 records nothing)
        most = max(session.states_taken(i) for i in done)
        if most < 3:
            raise ConfigError(f"{session.root}: captured in adaptive mode, at most {most} polarizer "
                              f"state(s) per pose; the reference method needs at least 3 "
                              f"(reconstruct with the hybrid method)")
    elif mode == "reference":  # before a revision exists: an impossible request records nothing
        if len(acquired) < 3:
            raise ConfigError(f"{session.root}: captured in {plan.mode} mode, "
                              f"{len(acquired)} polarizer state per pose; the reference method "
                              f"needs at least 3 (reconstruct with the single-shot method, or "
                              f"capture again with the reference method)")
        validate_states(calibration.incident_stokes(acquired))
    return ({"mode": mode, "demosaic": demosaic, "mirror_average": mirror_average,
             "resolution": resolution, "network_binning": processor.network_binning,
             "seen_state": processor.seen_state, "calibration_id": calibration.id,
             "exr_planes": list(choice.planes), "exr_uncertainty": choice.uncertainty,
             "exr_compression": choice.compression, "models": processor.models,
             "prior_scale": processor.prior_scale}, processor, done)


def _reprocess(session: Session, mode, demosaic, mirror_average, calibration, command_line,
               progress, on_failed, resolution=None, device="auto", exr=None,
               network_binning=None, seen_state=None, model_size="auto", models=None,
               prior_scale=DEFAULT_PRIOR_SCALE) -> str:
    settings, processor, done = revision_plan(session, mode, demosaic, mirror_average,
                                              calibration, resolution, device, exr, network_binning,
                                              seen_state, model_size, models, prior_scale)
    failed: list[tuple[int, str]] = []
    with SignalGuard() as guard:
        name = session.new_revision(settings, command_line)
        for index in done:
            session.start_revision(index, name)
            try:
                score = processor.process(session, index, revision=name)
            except Exception as exc:  # this capture's data: record why, go on with the others
                reason = f"{type(exc).__name__}: {exc}"
                with guard.deferred():
                    mark_revision(session, index, name, FAILED, reason)
                if is_disk_full(exc):
                    raise
                failed.append((index, reason))
                if on_failed:
                    on_failed(index, reason)
                continue
            except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM
                with guard.deferred():
                    mark_revision(session, index, name, PENDING, interruption_reason(exc))
                raise
            if progress:
                progress(index, score)
    if failed:
        raise ReconstructIncomplete(session, name, failed, len(done))
    return name


def mark_revision(session: Session, index: int, revision: str, status: str,
                   reason: str) -> None:
    """Set capture ``index``'s entry of ``revision`` to ``status`` with ``reason`` and save
    (best effort). Files it wrote stay recorded: each was written completely and checksummed.
    The manifest on disk is what counts (after a failed save it is the consistent one)."""
    with contextlib.suppress(OSError, FormatError):
        session.reload()
    entry = session.capture(index)["revisions"].setdefault(
        revision, {"status": PENDING, "files": {}, "score": None, "reason": None})
    entry.update(status=status, reason=reason)
    with contextlib.suppress(OSError):
        session.save()
