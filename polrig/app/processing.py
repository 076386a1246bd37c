"""Turn a capture's raw frames into Mueller images (with uncertainty and mask), and score them.

Array level: :mod:`polrig.solve.radiometry` (state radiance, demosaic, solve) and
:mod:`polrig.solve.scoring` (truth on the output grid, score); their names are re-exported here.

The array-level functions live in :mod:`polrig.solve.radiometry` and :mod:`polrig.solve.scoring`, the
calibration and its geometry in :mod:`polrig.app.calibrations`, a session's frame files in
:mod:`polrig.app.sessionio`; this module composes them.

Session level: :class:`Processor` (used by :func:`polrig.app.capture.run_session`) reads a
capture's raw frames back from the session (checksums verified), solves, writes
``mueller.exr`` (Mueller channels plus ``sigma``, ``residual`` and ``mask`` planes), and on the
simulated rig ``truth_mueller.exr`` and a score; :func:`reprocess_session` does the same into
a new revision for ``polrig reconstruct``.

Uncertainty propagation from the raw samples to the result: :mod:`polrig.solve.radiometry`.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import pathlib
from collections.abc import Hashable, MutableMapping
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from polrig import __version__
from polrig.acquisition.plan import (
    MODES,
    NETWORK_MODES,
    PRIOR_MODES,
    CapturePlan,
    ExrChoice,
    PlanError,
    check_seen_state,
    single_shot_options,
)
from polrig.app.calibrations import (  # noqa: F401 (re-exported)
    NOMINAL_ANALYZER_TOLERANCE,
    NOMINAL_CALIBRATION_ID,
    NOMINAL_GENERATOR_TOLERANCE,
    Calibration,
    calibration_geometry,
    check_calibration_fits,
    check_calibration_fits_rig,
    check_plan,
    frame_layout,
    load_calibration,
    nominal_calibration,
    single_shot_geometry,
    state_set_condition,
)
from polrig.app.diffuse_route import (
    DIFFUSE_PLANES,
    capture_geometry,
    check_diffuse_states,
    check_geometry,
    diffuse_header,
    diffuse_planes,
    missing_geometry,
    solve_diffuse,
)
from polrig.app.preview import write_result_previews
from polrig.app.records import (  # noqa: F401 (re-exported)
    sensor_model_of,
    session_frame_geometry,
    session_sensor_model,
)
from polrig.app.session import (
    COMPLETE,
    FAILED,
    PENDING,
    Session,
    SignalGuard,
    interruption_reason,
    is_disk_full,
    sha256_file,
)
from polrig.app.sessionio import CaptureFrames, load_capture_frames, read_verified_frame  # noqa: F401 (re-exported)
from polrig.app.single_shot import SingleShot, SingleShotResult
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.formats.exr import (
    MuellerRows,
    channel_suffixes,
    write_mueller_exr,
    write_result_exr,
)
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.layouts import MosaicLayout
from polrig.sensor.noise import SensorModel
from polrig.solve.model_selection import (
    MODEL_CHOICES,
    MODEL_PLANES,
    SelectionOptions,
    model_planes,
    selection_header,
)
from polrig.solve.open_scale import OpenScale
from polrig.solve.prior_scale import METHODS as PRIOR_SCALES
from polrig.solve.prior_scale import PriorScale
from polrig.solve.radiometry import (  # noqa: F401 (re-exported)
    StateRadiance,
    adc_scale,
    analyzer_stack,
    open_scale_from_frames,
    prior_scale_from_frames,
    reference_from_frames,
    state_radiance,
)
from polrig.solve.reference import (
    MuellerEstimate,
    ReferenceResult,
    reason_names,
    validate_states,
)
from polrig.solve.scoring import (  # noqa: F401 (re-exported)
    _psnr_db,
    format_score,
    score_against_truth,
    score_on_output_grid,
    truth_on_output_grid,
)


def noise_exposures_us(cf: CaptureFrames) -> list[float]:
    """The capture's exposures as the noise model takes them: a camera without exposure
    control reports none (recorded as unknown, NaN here); its dark current cannot be modelled
    then and counts as 0 us of it (dark frames, when taken, still subtract what there is; a
    bracket needs exposure control anyway)."""
    return [e if math.isfinite(e) else 0.0 for e in cf.exposures_us]


def capture_state_radiance(cf: CaptureFrames, k: int, model: SensorModel) -> StateRadiance:
    """State ``k``'s radiance of capture ``cf`` (:func:`polrig.solve.radiometry.state_radiance`):
    its frames (every exposure) and the capture's darks in ADC DN, under the noise ``model``.
    A function of those frames, their exposures and ``model`` alone."""
    first = cf.first
    scale = adc_scale(model, first.meta.bit_depth)
    adc = lambda f: f.raw.astype(np.float64) * scale if scale != 1 else f.raw  # noqa: E731
    have_darks = any(len(d) for d in cf.darks)
    return state_radiance(
        [[adc(f) for f in lst] for lst in cf.frames[k]], noise_exposures_us(cf), model,
        black_level_dn=float(first.meta.black_level_dn) * scale, code_step_dn=scale,
        darks=[[adc(f) for f in d] for d in cf.darks] if have_darks else None)


def state_key(cf: CaptureFrames, k: int) -> tuple[Hashable, ...] | None:
    """What state ``k``'s radiance (:func:`capture_state_radiance`) is a function of, besides
    the noise model: the checksums of its frame files, of the darks and of the capture's first
    frame (its bit depth and black level), and the exposures; ``None`` for frames that did not
    come from files (no checksums)."""
    if len(cf.checksums) != len(cf.frames) or not cf.checksums[0]:
        return None
    return (cf.checksums[0][0], cf.checksums[k], cf.dark_checksums,
            tuple(repr(float(e)) for e in cf.exposures_us))


def capture_analyzer(cf: CaptureFrames, calibration: Calibration):
    """The calibration's analyzer model of the capture's readout (cropped to it within the
    calibrated area), or None (the ideal analyzer)."""
    analyzer = calibration.analyzer
    if analyzer is not None:  # the frame's readout within the calibrated area
        h, w = cf.first.raw.shape
        ax, ay = calibration.area_offset
        ox, oy = cf.first.meta.offset_xy
        if analyzer.shape != (h, w) or (calibration.sensor is not None and (ox, oy) != (ax, ay)):
            analyzer = analyzer.crop(ox - ax, oy - ay, w, h)
    return analyzer


def process_reference(cf: CaptureFrames, calibration: Calibration, model: SensorModel,
                      method: str, uncertainty_dtype: type = np.float32,
                      prior: Callable[[list[StateRadiance], np.ndarray], Mapping[str, Any]] | None = None,
                      model_selection: SelectionOptions | None = None,
                      states: Sequence[StateRadiance] | None = None
                      ) -> tuple[ReferenceResult, np.ndarray, MosaicLayout, list[StateRadiance]]:
    """Reference solve of one capture's frames: ``(result, s_in, layout, states)``;
    ``uncertainty_dtype`` of its ``sigma``, ``sigma_noise`` and ``residual`` (float16 halves
    their memory: :func:`polrig.solve.radiometry.reference_from_frames`).

    ``prior(states, s_in)``: the hybrid solve instead, with the keywords it returns
    (``prior_mean``, ``prior_sigma``, ``seen_state``, ``prior_correlation``:
    :func:`polrig.solve.radiometry.reference_from_frames`),
    computed from the capture's state radiances (:meth:`Processor.solve`).
    ``model_selection``: lower-order models per pixel (:mod:`polrig.solve.model_selection`;
    the result's ``models`` holds the maps). ``states``: the capture's state radiances
    (:func:`capture_state_radiance` of each state) when already computed."""
    first = cf.first
    lay = frame_layout(first)
    if states is None:
        states = [capture_state_radiance(cf, k, model) for k in range(len(cf.frames))]
    elif len(states) != len(cf.frames):
        raise ValueError(f"{len(states)} state radiances for {len(cf.frames)} states")
    s_in = calibration.incident_stokes(cf.states_deg)
    extra = {} if prior is None else dict(prior(states, s_in))
    result = reference_from_frames(states, s_in, lay, method, capture_analyzer(cf, calibration),
                                   analyzer_tolerance=calibration.analyzer_tolerance,
                                   generator_tolerance=calibration.generator_tolerance,
                                   uncertainty_dtype=uncertainty_dtype,
                                   model_selection=model_selection, **extra)
    return result, s_in, lay, list(states)


#: Roles of a result's PNG previews (:func:`polrig.app.preview.write_result_previews`), by the
#: suffix of their file name (``mueller_grid.png``...).
PREVIEW_ROLES = {"preview_grid": "grid", "preview_dolp": "dolp", "preview_aolp": "aolp"}
#: The channels of the manifest's ``uncertainty`` view, per plane group.
_UNCERTAINTY_CHANNELS = {"sigma": "sigma.M{row}{col}.{colour}",
                         "sigma_noise": "sigma_noise.M{row}{col}.{colour}",
                         "residual": "residual.{colour}"}


@dataclasses.dataclass(frozen=True)
class TruthScore:
    """How to score a capture's result against the simulator's truth file ``truth_path``
    (already verified): the truth as a perfect rig at the output resolution measures it
    (:func:`polrig.solve.scoring.score_on_output_grid`: ``layout``, demosaic ``method``, incident
    states ``s_in`` ``(N, 3)``, the capture's own ``states`` as weights, or for the
    single-shot method ``None`` with the noise ``model`` at ``exposure_us``)."""

    truth_path: pathlib.Path
    layout: MosaicLayout
    method: str
    s_in: np.ndarray
    states: Sequence[StateRadiance] | None = None
    model: SensorModel | None = None
    exposure_us: float | None = None

    def run(self, estimate: MuellerEstimate | ReferenceResult) -> dict[str, Any]:
        """The score (:func:`polrig.solve.scoring.score_against_truth`'s keys) of ``estimate``;
        the truth file is read a band of rows at a time (:class:`polrig.formats.exr.MuellerRows`),
        its ``object_mask`` plane whole."""

        with MuellerRows(self.truth_path) as truth:
            obj = truth.plane("object_mask")  # output pixels whose whole support lies on it
            return score_on_output_grid(estimate, truth, self.layout, self.method, self.s_in,
                                        self.states, model=self.model,
                                        exposure_us=self.exposure_us, object_mask=obj)


@dataclasses.dataclass
class CaptureResult:
    """One capture solved by :meth:`Processor.solve`: ``relpath`` (inside the session,
    ``<capture>/mueller.exr`` or ``<capture>/<revision>/mueller.exr``), ``result`` the solve's
    arrays (the reference solve's or the single-shot route's), ``metadata`` the EXR header's
    polrig entries, ``truth`` how to score it against the simulator's truth (``None`` without a
    truth file), ``extra_planes`` further planes of its EXR. :func:`write_and_score` writes and
    scores it."""

    relpath: str
    result: ReferenceResult | SingleShotResult | MuellerEstimate
    metadata: dict[str, Any]
    truth: TruthScore | None
    #: planes written beside :func:`polrig.formats.exr.result_planes`' (name -> ``(H, W)`` array): the
    #: single-shot ``beyond_calibration.{colour}`` flags, with the ``sigma`` group
    #: (:meth:`polrig.app.single_shot.SingleShotResult.extra_planes`)
    extra_planes: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    #: hybrid: the prior's record for the manifest (:class:`polrig.app.manifest.PriorRecord`)
    prior: dict[str, Any] | None = None
    #: single-shot and hybrid: the network's model for the manifest (:class:`polrig.app.manifest.ModelRecord`)
    model: dict[str, Any] | None = None


def write_result_files(root: pathlib.Path, out: CaptureResult, exr: ExrChoice, *,
                       replace: bool = False) -> dict[str, dict[str, Any]]:
    """Write ``out``'s ``mueller.exr`` (the planes and compression of ``exr``) and its PNG
    previews next to it (``mueller_grid.png``, ``mueller_dolp.png``, ``mueller_aolp.png``:
    :func:`polrig.app.preview.write_result_previews`, from the arrays in memory, every
    :func:`polrig.app.preview.preview_stride`-th pixel of a large result) under ``root``,
    each atomically (temporary name in its folder, then renamed); return their records by
    role (``mueller`` and :data:`PREVIEW_ROLES`: ``path``, ``sha256`` hashed from the file
    as it lies on disk, streamed, ``bytes``). The file's bytes are never held in memory.

    ``replace=False`` refuses (``FileExistsError``) a result file already there (session data
    is never overwritten); a worker of :mod:`polrig.app.cluster` passes ``True``: a file there is
    the unrecorded output of an attempt that died, replaced by identical bytes. The one
    writer of result files, serial (:meth:`Processor.process`) and distributed alike."""

    path = _new_result_path(root, out.relpath, replace)
    res = out.result
    rel = pathlib.PurePosixPath(out.relpath).parent
    previews = {role: path.with_name(f"{path.stem}_{suffix}.png")
                for role, suffix in PREVIEW_ROLES.items()}
    written = {"mueller": path, **previews}
    try:
        write_result_exr(path, res, planes=exr.planes, uncertainty=exr.uncertainty,
                         compression=exr.compression, extra=out.extra_planes, metadata=out.metadata)
        made = write_result_previews(res.mueller, path.parent, stem=path.stem, flags=res.mask)
        if sorted(made) != sorted(previews.values()):  # pragma: no cover - preview's contract
            raise RuntimeError(f"previews {made} are not the expected {previews}")
        return {role: file_record(root, (rel / p.name).as_posix())
                for role, p in written.items()}
    except BaseException:  # no partial result left behind (each file is whole or absent)
        remove_files(written.values())
        raise


def write_and_score(root: pathlib.Path, out: CaptureResult, exr: ExrChoice, *,
                    replace: bool = False
                    ) -> tuple[dict[str, dict[str, Any]], dict[str, Any] | None]:
    """Write ``out``'s result files (:func:`write_result_files`), then score it against the
    truth (``out.truth``; ``None`` without one); return the files' records and the score.

    Consumes ``out``: once the files are written, ``out.result`` is replaced by its
    :class:`polrig.solve.reference.MuellerEstimate`, so that the diagnostic planes are released
    before the truth is read (the peak memory of a scored full-sensor pose is the solve's,
    not the solve's plus the truth's). A score that fails removes the files just written.
    The serial :meth:`Processor.process` and the workers of :mod:`polrig.app.cluster` both call
    it."""
    records = write_result_files(root, out, exr, replace=replace)
    if out.truth is None:
        return records, None
    if not isinstance(out.result, MuellerEstimate):
        out.result = out.result.estimate()
    try:
        return records, out.truth.run(out.result)
    except BaseException:
        remove_files(pathlib.Path(root) / r["path"] for r in records.values())
        raise


def remove_files(paths) -> None:
    """Delete ``paths`` where they exist (best effort: a failure to delete is ignored)."""
    for p in paths:
        with contextlib.suppress(OSError):
            pathlib.Path(p).unlink(missing_ok=True)


def _new_result_path(root: pathlib.Path, relpath: str, replace: bool = False) -> pathlib.Path:
    """``root/relpath`` with its folder made; ``FileExistsError`` if a file is there (unless
    ``replace``): session data is never overwritten."""
    path = pathlib.Path(root) / relpath
    if path.exists() and not replace:
        raise FileExistsError(f"{path}: refusing to overwrite session data")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def file_record(root: pathlib.Path, relpath: str) -> dict[str, Any]:
    """The manifest record (``path``, ``sha256``, ``bytes``) of a file written under ``root``,
    hashed by streaming it from disk (:func:`polrig.app.session.sha256_file`)."""
    path = pathlib.Path(root) / relpath
    return {"path": pathlib.PurePosixPath(relpath).as_posix(), "sha256": sha256_file(path),
            "bytes": path.stat().st_size}


def record_result(session: Session, index: int, revision: str | None,
                  records: dict[str, dict[str, Any]], score: dict[str, Any] | None,
                  exr: ExrChoice = ExrChoice(), prior: Mapping[str, Any] | None = None,
                  model: Mapping[str, Any] | None = None,
                  model_map: bool = False) -> None:
    """Record capture ``index``'s written result files (``records`` by role, as
    :func:`write_result_files` returns: ``mueller`` and its previews) with the ``mueller``
    file's ``uncertainty`` and ``mask`` views (of the planes ``exr`` wrote; no view of planes
    not written), and in ``revision`` (if given) its score and status ``complete``; save the
    manifest (under ``session.mutex``: the next capture's acquisition writes the manifest
    meanwhile). ``prior``: a hybrid result's prior model (:class:`polrig.app.manifest.PriorRecord`),
    recorded beside its files, as is ``model``, the network's model of a single-shot or hybrid
    result (:class:`polrig.app.manifest.ModelRecord`). ``model_map``: the file holds the model selection's
    planes (``models`` view). The one place a result enters a manifest: the serial
    :meth:`Processor.process` and the client of :mod:`polrig.app.cluster` (whose workers write
    the files) both call it."""
    with session.mutex:
        cap = session.capture(index)
        entry = cap if revision is None else cap["revisions"][revision]
        files = entry["files"]
        clash = [role for role in records if role in files]
        if clash:
            raise FileExistsError(f"capture {index} already has a {clash[0]!r} file")
        before = copy.deepcopy(entry)
        path = records["mueller"]["path"]
        files.update({role: dict(rec) for role, rec in records.items()})
        sigma = [c for p, c in _UNCERTAINTY_CHANNELS.items() if p in exr.planes]
        if sigma:
            files["uncertainty"] = {"part_of": "mueller", "path": path,
                                    "channels": ", ".join(sigma)}
        if "mask" in exr.planes:
            files["mask"] = {"part_of": "mueller", "path": path,
                             "channels": "mask.{colour} (reason bits, 0 = valid)"}
        if model_map:
            files["models"] = {"part_of": "mueller", "path": path,
                               "channels": "model.{colour} (codes in the header's "
                                           "model_selection), model_chi2.{colour}, model_p.{colour}; "
                                           "with --models diffuse also specular.{colour}"}
        if prior is not None:
            entry["prior"] = dict(prior)
        if model is not None:
            entry["model"] = dict(model)
        if revision is not None:
            entry.update(status=COMPLETE, score=score)
        try:
            session.save()
        except BaseException:  # not recorded after all: the manifest in memory says so too
            entry.clear()
            entry.update(before)
            raise


def check_prior_scale(choice: str) -> str:
    """``choice`` if it is one of :data:`polrig.solve.prior_scale.METHODS`, else a one-line
    :class:`PlanError` of ``prior_scale``."""
    if choice not in PRIOR_SCALES:
        raise PlanError("prior_scale", f"unknown choice {choice!r}; use {', '.join(PRIOR_SCALES)}")
    return choice


class Processor:
    """Processing of captures inside a session (see :func:`polrig.app.capture.run_session`).

    ``mode``/``demosaic`` as in the plan; ``sensor_model`` the camera's noise model;
    ``mirror_average``: single-shot runs the network on the capture and on its mirror image and
    averages (:mod:`polrig.models.mirror`; twice the network time, a few per cent lower error).
    ``resolution``: single-shot output at the networks' ``superpixel`` grid or the raw frame's
    (``full``; a :class:`PlanError` of ``resolution`` with the reference mode).
    ``network_binning``: 1, or 2 for the single-shot networks on the analyzer grid binned 2x2
    (about half the frame time at full sensor size, no calibrated sigma; a :class:`PlanError` of
    ``network_binning`` with the reference mode). The single-shot settings are checked and
    become :attr:`single_shot_options` (:func:`polrig.acquisition.plan.single_shot_options`), run
    by the one route, :attr:`single_shot` (:class:`polrig.app.single_shot.SingleShot`).
    ``device``: where the network runs (``auto``, ``cpu``, ``cuda``; :mod:`polrig.models.devices`), a
    run option, not part of the plan; the provider used is recorded; the model is the one the
    plan check opened (:meth:`polrig.app.single_shot.SingleShot.open`), not a second load.
    ``model_size``: which shipped model (``auto``, ``small``, ``large``: :mod:`polrig.models.sizes`),
    a run option too; the size, training hardware and minutes are recorded with each result
    (header ``model_size``, ``model_training``; manifest ``model``).
    ``exr``: the result file's planes, precision and compression (the plan's
    :class:`ExrChoice`; half-precision uncertainty is solved in half precision too).
    ``seen_state``: hybrid, the index into the capture's states of the frame the network sees
    (its estimate and calibrated sigma are the prior of the solve of all states,
    :mod:`polrig.solve.hybrid`).
    ``prior_scale``: hybrid and adaptive, ``innovations`` (the calibrated sigma scaled per
    capture by what the states after the seen one show of the network's errors,
    :mod:`polrig.solve.prior_scale`; factor 1 at one state), ``geometry`` (that, and at two
    states the prior along the direction they leave open scaled by what the diffuse term's
    geometry shows of it, :meth:`open_scale`) or ``calibrated`` (as calibrated); default
    :data:`polrig.choices.DEFAULT_PRIOR_SCALE`; a processing option like ``models``, each
    result records its factors (the prior record's ``sigma_scale``).
    ``models``: ``full`` (the default: the 3x3 block everywhere), ``auto`` (reference and
    hybrid: per pixel the lower-order model a likelihood-ratio test accepts,
    :mod:`polrig.solve.model_selection`) or ``diffuse`` (hybrid at two states, ``n_states``: the
    diffuse term tested on their samples alone and the open direction predicted from the rig's
    geometry, :mod:`polrig.app.diffuse_route`; the network then also gives its normals); the
    result then always carries the model map ``model.{colour}`` with ``model_chi2``/``model_p``
    and the header its ``model_selection``.
    """

    def __init__(self, mode: str, demosaic: str, calibration: Calibration,
                 sensor_model: SensorModel, mirror_average: bool = False,
                 resolution: str = "superpixel", device: str = "auto",
                 exr: ExrChoice = ExrChoice(), network_binning: int = 1, seen_state: int = 0,
                 model_size: str = "auto", models: str = "full", n_states: int | None = None,
                 prior_scale: str = DEFAULT_PRIOR_SCALE):
        if mode not in MODES:
            raise PlanError("mode", f"unknown mode {mode!r}; use {', '.join(MODES)}")
        if models not in MODEL_CHOICES:
            raise PlanError("models", f"unknown choice {models!r}; use {', '.join(MODEL_CHOICES)}")
        if models == "auto" and mode == "single-shot":
            raise PlanError("models", "model selection tests the samples of the polarizer states: "
                                      "use the reference or hybrid mode")
        if models == "auto" and mode == "hybrid" and n_states is not None and n_states < 3:
            # with fewer, every pixel would stay untested (polrig.solve.model_selection, "At any
            # rank": captures do not pass the prior to the test)
            raise PlanError("models", f"model selection tests the block on the samples alone, which "
                                      f"takes three polarizer states or more; the plan has {n_states}"
                                      + (" (at two, --models diffuse tests the diffuse term on them)"
                                         if n_states == 2 else ""),
                            subject="auto", what="models")
        if models == "diffuse":
            check_diffuse_states(mode, n_states)
        #: the hybrid prior's scale (:data:`polrig.solve.prior_scale.METHODS`)
        self.prior_scale = check_prior_scale(prior_scale)
        #: ``full``, ``auto`` (model selection, :mod:`polrig.solve.model_selection`) or
        #: ``diffuse`` (:mod:`polrig.app.diffuse_route`)
        self.models = models
        #: the single-shot route's options (``None`` for the reference method); the diffuse
        #: route's first guess of the normals is the network's (the full graph)
        self.single_shot_options = single_shot_options(mode, demosaic, resolution, network_binning,
                                                       mirror_average, exr.planes)
        if models == "diffuse":
            self.single_shot_options = dataclasses.replace(self.single_shot_options, geometry=True)
        self.network_binning = int(network_binning)
        # single-shot: the installed network (loaded once per process and device), or the
        # one-line "no model installed" error
        self.single_shot = SingleShot.open(device, size=model_size) if mode in NETWORK_MODES else None
        #: what the results record of the network's model (size, training hardware and minutes;
        #: :meth:`polrig.app.single_shot.SingleShot.model_header`), None for the reference method
        self.model_header = None if self.single_shot is None else self.single_shot.model_header()
        #: hybrid: the prior's model (manifest ``prior`` record less the seen state); needs the
        #: graph's calibrated sigma (a one-line PlanError of ``mode`` otherwise)
        self.prior_model = (self.single_shot.prior_model(bool(mirror_average)) if mode in PRIOR_MODES
                            else None)
        self.seen_state = int(seen_state)
        self.resolution = resolution
        self.mode = mode
        self.demosaic = demosaic
        self.mirror_average = bool(mirror_average)
        self.calibration = calibration
        self.sensor_model = sensor_model
        self.exr = exr

    # called by run_session while the rig is still at the pose
    def after_acquire(self, session: Session, index: int, rig) -> None:
        """The simulated rig's ground truth of capture ``index`` (``truth_mueller.exr``),
        taken while the rig is still at its pose, compressed as the plan's result files
        (``exr_compression``: ``none`` writes and reads it fastest); nothing on real
        hardware."""
        if rig.truth is None:
            return
        gt = rig.truth.ground_truth()
        cap = session.capture(index)
        planes = {"object_mask": np.asarray(gt["mask"], np.float32)}
        meta = {"source": "polrig simulated rig ground truth", "pose_deg": cap["pose_deg"],
                "units": "DN per unit incident S0 (docs/conventions.md)",
                "exposure_us": gt.get("exposure_us"), "gain_db": gt.get("gain_db")}

        relpath = f"{cap['name']}/truth_mueller.exr"
        path = _new_result_path(session.root, relpath)
        write_mueller_exr(path, gt["mueller"], extra=planes, metadata=meta,  # atomic
                          compression=self.exr.compression)
        with session.mutex:
            files = session.capture(index)["files"]
            files["truth_mueller"] = file_record(session.root, relpath)
            try:
                session.save()
            except BaseException:  # not recorded: neither in memory nor on disk
                del files["truth_mueller"]
                remove_files([path])
                raise

    def process(self, session: Session, index: int, revision: str | None = None
                ) -> dict[str, Any] | None:
        """Solve capture ``index`` from its raw files; write the result files (into
        ``revision`` if given); return the score against the truth (simulated rig) or None.
        :meth:`solve` and :func:`record_result`, with the file written and scored in between
        (:func:`write_and_score`)."""
        out = self.solve(session, index, revision)
        prior = out.prior
        records, score = write_and_score(session.root, out, self.exr)
        try:
            record_result(session, index, revision, records, score, self.exr, prior, out.model,
                          self.models != "full")
        except BaseException:  # not recorded (a full disk...): no unrecorded file left
            remove_files(session.root / r["path"] for r in records.values())
            raise
        return score

    def solve(self, session: Session, index: int, revision: str | None = None
              ) -> "CaptureResult":
        """Capture ``index`` solved from its raw files (checksums verified): the arrays and
        header of its ``mueller.exr`` (for ``revision`` if given) and how to score it; writes
        nothing (:func:`write_result_files` does), so a worker of :mod:`polrig.app.cluster` can
        run it on a session another process writes."""

        cap = session.capture(index)
        cf = load_capture_frames(session, index)
        truth_path = self._verified_truth(session, index)  # damaged truth: refused up front
        geometry = prior_record = prior_header = None
        if self.mode in NETWORK_MODES:
            geometry = self.network_geometry(session, cf)
        if self.mode == "single-shot":
            result, s_in, lay = self.single_shot_result(cf, geometry)
            states = None
            extra_planes = result.extra_planes(self.exr.planes, self.exr.uncertainty)
        else:
            unc = np.float16 if self.exr.uncertainty == "half" else np.float32
            prior = None
            keep: dict[str, Any] = {}
            if self.mode in PRIOR_MODES:
                prior_header = {}
                prior = self.prior_function(cf, geometry, prior_header, keep)
            selection = SelectionOptions() if self.models == "auto" else None
            result, s_in, lay, states = process_reference(cf, self.calibration, self.sensor_model,
                                                          self.demosaic, unc, prior, selection)
            diffuse_extra = {}
            if self.models == "diffuse":
                result, diffuse_meta, diffuse_extra = self.diffuse(result, s_in, lay, states, cf, geometry, keep)
            extra_planes = {}
            if result.models is not None:  # never silent: the map is always written
                extra_planes = model_planes(result.models, channel_suffixes(lay.n_colours)) | diffuse_extra
            if self.mode in PRIOR_MODES:
                prior_record = {**self.prior_model, **prior_header, "seen_state": self.seen_state,
                                "seen_state_deg": float(cf.states_deg[self.seen_state])}
        meta = {
            "calibration_id": self.calibration.id, "mode": self.mode, "demosaic": self.demosaic,
            "pose_deg": cap["pose_deg"], "states_deg": cf.states_deg,
            "incident_state": np.asarray(s_in).tolist(),
            "exposure_us": cf.exposures_us[0], "exposures_us": cf.exposures_us,
            "frames_per_state": len(cf.frames[0][0]), "dark_frames": len(cf.darks[0]),
            "layout": lay.name, "condition_number": result.condition_number,
            "units": "DN per unit incident S0 at exposure_us (docs/conventions.md)",
            "mask_bits": {str(b): n for b, n in reason_names().items()},
            "analyzer_tolerance": list(self.calibration.analyzer_tolerance),
            "generator_tolerance": list(self.calibration.generator_tolerance),
            "planes": {"sigma.M{rc}": "standard deviation of M{rc}: sensor noise and "
                                      "calibration uncertainty",
                       "sigma_noise.M{rc}": "standard deviation of M{rc} from the sensor "
                                            "noise model alone",
                       "mask": "reason bits, 0 = valid", "residual": "chi^2 per dof"},
            "uncertainty_precision": self.exr.uncertainty,
            "software": f"polrig {__version__}", "capture": cap["name"],
            "revision": revision or "capture",
            # who, why, what (manifest.SampleMetadata): flat, its user keys never polrig's own
            **session.manifest["metadata"].header(),
        }
        meta["planes"] = {k: v for k, v in meta["planes"].items()
                          if k.split(".", 1)[0] in self.exr.planes}
        if geometry is not None:
            meta["single_shot_geometry"] = {
                "intrinsics_full_sensor": geometry["intrinsics"],
                "stage_zero_axis_camera": geometry["stage_zero_axis_camera"],
                "sources": geometry["sources"]}
            if self.mode == "single-shot":
                meta.update(result.header(self.exr.planes))  # settings, provider, its planes' meaning
        if self.model_header is not None:
            meta.update(self.model_header)
        if prior_record is not None:
            meta.update(self.hybrid_header(prior_record, s_in))
            meta["planes"] = {k: v for k, v in meta["planes"].items()
                              if k.split(".", 1)[0] in self.exr.planes}
        if self.models == "diffuse":
            meta.update(diffuse_meta)
            meta["planes"] = {**meta["planes"], **DIFFUSE_PLANES}
        elif self.mode != "single-shot" and result.models is not None:
            meta.update(selection_header(result.models))
            meta["planes"] = {**meta["planes"], **MODEL_PLANES}
        folder = cap["name"] if revision is None else f"{cap['name']}/{revision}"
        truth = None if truth_path is None else self.truth_score(
            truth_path, lay, s_in, states if self.mode == "reference" else None,
            noise_exposures_us(cf)[0])
        return CaptureResult(f"{folder}/mueller.exr", result, meta, truth, extra_planes, prior_record,
                             self.manifest_model())

    def diffuse(self, result: ReferenceResult, s_in: np.ndarray, lay: MosaicLayout,
                states: list[StateRadiance], cf: CaptureFrames, geometry: dict[str, Any],
                keep: Mapping[str, Any]) -> tuple[ReferenceResult, dict[str, Any], dict[str, np.ndarray]]:
        """The diffuse route on a two-state hybrid ``result`` (:mod:`polrig.app.diffuse_route`):
        the geometry (``geometry``: :meth:`network_geometry`'s; the network's normals from
        ``keep["net"]``, the prior from ``keep["prior"]``, :meth:`prior_function`), tested on
        the network's object pixels. Returns the result, its header entries and its planes
        besides the model map."""
        net: SingleShotResult = keep["net"]
        grid = result.mueller.shape[-2:]
        where = capture_geometry(geometry, cf.first, grid, net.network_grid.get("normal"))
        out, test, completed = solve_diffuse(result, s_in, states, lay, self.demosaic,
                                             capture_analyzer(cf, self.calibration), where,
                                             prior=keep["prior"], mask=net.object)
        return (out, diffuse_header(test, completed, out.models, geometry["sources"]),
                diffuse_planes(test, channel_suffixes(lay.n_colours)))

    def manifest_model(self) -> dict[str, Any] | None:
        """The manifest's ``model`` record of this processor's results
        (:class:`polrig.app.manifest.ModelRecord`), None for the reference method."""
        if self.model_header is None:
            return None
        return {"size": self.model_header["model_size"], **self.model_header["model_training"]}

    def network_geometry(self, session: Session, cf: CaptureFrames) -> dict[str, Any]:
        """The single-shot geometry of ``session``'s captures (:func:`single_shot_geometry`: the
        calibration's, the simulated rig's configured size, else the frame's)."""
        rig_info = session.manifest.get("rig", {}) or {}
        config = rig_info.get("config")
        size = ((config or {}).get("sim") or {}).get("size")
        return single_shot_geometry(
            self.calibration, config,
            None if size is not None else (cf.first.raw.shape[1], cf.first.raw.shape[0]))

    def prior_function(self, cf: CaptureFrames, geometry: dict[str, Any] | None,
                       header: dict[str, Any], keep: dict[str, Any] | None = None,
                       known: MutableMapping[Hashable, SingleShotResult] | None = None
                       ) -> Callable[[list[StateRadiance], np.ndarray], dict[str, Any]]:
        """The hybrid solve's prior (``process_reference``'s ``prior``) for ``cf``: the single-shot
        route on the seen state's radiance (:attr:`seen_state`; 0 in the adaptive mode), its
        estimate and calibrated sigma (inf on clipped colours, 0 outside its object: no prior)
        times the capture's scale (:attr:`prior_scale`:
        :func:`polrig.solve.radiometry.prior_scale_from_frames`), and the errors' joint correlation
        where the calibration holds one (the prior record's ``joint_prior_version``).
        ``header`` gets the execution provider and the scale's record (``sigma_scale``); ``keep``
        (if given) the route's result as ``"net"`` (the adaptive mode's decisions use its object
        mask) and the keywords returned as ``"prior"`` (the adaptive mode's design and the
        diffuse route use its scaled sigma).

        ``known``: the route's results already computed, by the seen state's
        :func:`state_key` and incident state: one there is taken rather than run again (the
        adaptive mode's later decisions of a pose; the network is deterministic, so the result
        is identical), one computed is added. Valid for this processor and one session's
        geometry only; a capture without frame checksums is always run."""
        k = self.seen_state
        if not 0 <= k < len(cf.states_deg):
            raise PlanError("seen_state", f"the capture has {len(cf.states_deg)} polarizer "
                                          f"state(s): 0..{len(cf.states_deg) - 1}",
                            subject=str(k), what="seen state")

        def prior(states_: list[StateRadiance], s_in_: np.ndarray) -> dict[str, Any]:
            seen = state_key(cf, k)
            key = None if known is None or seen is None else (seen, np.asarray(s_in_[k], np.float64).tobytes())
            net = None if key is None else known.get(key)
            if net is None:
                net = self.single_shot.state(states_[k], cf.first, s_in_[k],
                                             self.single_shot_options, geometry=geometry)
                if key is not None:
                    known[key] = net
            header["execution_provider"] = net.provider
            scale = PriorScale.calibrated()
            if self.prior_scale != "calibrated":
                scale = prior_scale_from_frames(states_, s_in_, frame_layout(cf.first), self.demosaic,
                                                capture_analyzer(cf, self.calibration), net.mueller, net.sigma, k)
            record = scale.record()
            sigma = net.sigma if scale.factor == 1.0 else np.asarray(net.sigma) * np.float32(scale.factor)
            out = {"prior_mean": net.mueller, "prior_sigma": sigma, "seen_state": k,
                   "prior_correlation": self.single_shot.model.uncertainty.joint_correlation}
            if self.prior_scale == "geometry":
                opened = self.open_scale(states_, s_in_, cf, geometry, net, out)
                record = record | {"method": "geometry", "open_direction": opened.record()}
                if opened.factor != 1.0:
                    out["open_factor"] = opened.factor
            header["sigma_scale"] = record
            if keep is not None:
                keep["net"], keep["prior"] = net, out
            return out

        return prior

    def open_scale(self, states: list[StateRadiance], s_in: np.ndarray, cf: CaptureFrames,
                   geometry: Mapping[str, Any] | None, net: SingleShotResult, prior: Mapping[str, Any]) -> OpenScale:
        """The factor along the direction two states leave open (``--prior-scale geometry``:
        :func:`polrig.solve.radiometry.open_scale_from_frames` on the hybrid's ``prior``, tested
        on the network's object); factor 1 (no values) at another number of states or where the
        rig's geometry is not known (:data:`polrig.app.diffuse_route.GEOMETRY_NEEDED`)."""
        if len(states) != 2 or geometry is None or missing_geometry(geometry):
            return OpenScale.none()
        grid = np.shape(net.mueller)[-2:]
        return open_scale_from_frames(states, s_in, frame_layout(cf.first), self.demosaic,
                                      capture_analyzer(cf, self.calibration), prior["prior_mean"],
                                      prior["prior_sigma"], prior["seen_state"], prior["prior_correlation"],
                                      capture_geometry(geometry, cf.first, grid), net.object)

    @staticmethod
    def hybrid_header(prior_record: Mapping[str, Any], s_in: np.ndarray) -> dict[str, Any]:
        """A hybrid result's header entries: the seen state, the prior's model (the manifest's
        ``prior`` record), the state set's own condition number (``inf`` where it does not
        determine the block) and what the planes mean for the posterior."""
        return {
            "seen_state": prior_record["seen_state"], "seen_state_deg": prior_record["seen_state_deg"],
            "mirror_average": prior_record["mirror_average"],
            "execution_provider": prior_record["execution_provider"],
            "prior_model": {k: v for k, v in prior_record.items()
                            if k not in ("seen_state", "seen_state_deg")},
            "condition_number": state_set_condition(s_in),
            "planes": {
                "sigma.M{rc}": "posterior standard deviation of M{rc}: sensor noise, calibration "
                               "uncertainty and the single-shot prior (polrig.solve.hybrid)",
                "sigma_noise.M{rc}": "posterior standard deviation of M{rc} from the sensor noise "
                                     "model and the prior, without the calibration part",
                "mask": "reason bits, 0 = valid",
                "residual": "chi^2 of the samples per effective degree of freedom (n - tr H)"}}

    def single_shot_result(self, cf: CaptureFrames, geometry: dict[str, Any] | None = None
                           ) -> tuple[SingleShotResult, np.ndarray, MosaicLayout]:
        """The capture's one state through the single-shot route
        (:meth:`polrig.app.single_shot.SingleShot.state`): its frames averaged and HDR-merged
        like the reference states (:func:`polrig.solve.radiometry.state_radiance`, in ADC DN with
        the noise model's variance), under the calibration's incident state. Returns the result
        (its planes: :mod:`polrig.app.single_shot`), the incident state ``(1, 3)`` and the layout.

        ``geometry`` (:func:`single_shot_geometry`; default: from the calibration alone): the
        intrinsics and the stage zero axis the incident state is expressed about; without them
        the model assumes its training rig's, which on another rig puts the result in the wrong
        incident frame."""

        first = cf.first
        scale = adc_scale(self.sensor_model, first.meta.bit_depth)
        adc = lambda f: f.raw.astype(np.float64) * scale  # noqa: E731
        state = state_radiance([[adc(f) for f in lst] for lst in cf.frames[0]],
                               noise_exposures_us(cf), self.sensor_model,
                               black_level_dn=float(first.meta.black_level_dn) * scale,
                               darks=[[adc(f) for f in d] for d in cf.darks]
                               if any(len(d) for d in cf.darks) else None,
                               code_step_dn=scale)
        s_in = self.calibration.incident_stokes(cf.states_deg[:1])
        if geometry is None:  # the calibration's geometry only
            geometry = {"intrinsics": self.calibration.intrinsics,
                        "stage_zero_axis_camera": self.calibration.stage_zero_axis_camera}
        result = self.single_shot.state(state, first, s_in[0], self.single_shot_options, geometry=geometry)
        return result, s_in, frame_layout(first)

    @property
    def output_demosaic(self) -> str:
        """The demosaic of the result's grid: the plan's, except at single-shot full resolution,
        where it is the demosaic whose detail lifts the networks' answer
        (:attr:`polrig.acquisition.plan.SingleShotOptions.demosaic`)."""
        return self.demosaic if self.single_shot_options is None else self.single_shot_options.demosaic

    @staticmethod
    def _verified_truth(session: Session, index: int) -> pathlib.Path | None:
        """The capture's truth EXR (simulated rig) after checking its SHA-256, or None
        without one; a missing or changed file is a one-line error naming it."""
        rec = session.capture(index)["files"].get("truth_mueller")
        if rec is None:
            return None
        path = session.root / rec["path"]
        if not path.is_file():
            raise FileNotFoundError(f"{path}: truth file of the session is missing")
        if sha256_file(path) != rec["sha256"]:
            raise FormatError(f"{path}: SHA-256 does not match the session manifest (changed "
                              f"or corrupt truth file)")
        return path

    def truth_score(self, truth_path: pathlib.Path, layout: MosaicLayout, s_in: np.ndarray,
                    states: Sequence[StateRadiance] | None, exposure_us: float) -> TruthScore:
        """How to score a capture of this processor against its (verified) truth file: with
        the capture's own ``states`` as weights (reference), or for the single-shot method
        (``states=None``) at its output resolution with nominal four-state weights and the
        noise model at ``exposure_us``. The hybrid method is scored as the single-shot one (its
        states may not determine the block; the truth is that of a perfect four-state rig at its
        output resolution), so the two compare on the same truth."""
        if states is None or self.mode in PRIOR_MODES:
            return TruthScore(truth_path, layout, self.output_demosaic,
                              polarizer_stokes(np.deg2rad([0, 45, 90, 135]), intensity=1),
                              None, self.sensor_model, exposure_us)
        return TruthScore(truth_path, layout, self.demosaic, s_in, states)


def make_processor(plan: CapturePlan, calibration: Calibration, sensor_model: SensorModel,
                   device: str = "auto", model_size: str = "auto",
                   models: str = "full", prior_scale: str = DEFAULT_PRIOR_SCALE) -> Processor:
    """The :class:`Processor` of ``plan`` (its network on ``device``, of ``model_size``: run options;
    ``models``, ``prior_scale``: :class:`Processor`)."""
    return Processor(plan.mode, plan.demosaic, calibration, sensor_model, plan.mirror_average,
                     plan.resolution, device, plan.exr, plan.network_binning, plan.seen_state,
                     model_size, models, len(plan.states_deg), prior_scale)


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

    ``resolution`` (single-shot output grid, :class:`Processor`; default: the session's where it
    stays single-shot, else ``superpixel``) and ``network_binning`` (single-shot, 1 or 2; default:
    the session's where it stays single-shot, else 1) are recorded with the revision; ``device``
    (where the network runs) is not a setting of the result: the provider used is in its header;
    nor is ``model_size`` (which shipped model, :mod:`polrig.models.sizes`): its results record it.
    ``exr``: the result files' format, fields of :class:`ExrChoice` (``planes``,
    ``uncertainty``, ``compression``) overriding the session plan's; recorded with the
    revision. ``models``: ``full`` (default: never applied silently) or ``auto``
    (:class:`Processor`), recorded with the revision; so is ``prior_scale`` (hybrid:
    ``innovations`` or ``calibrated``, :class:`Processor`).

    A capture that cannot be processed (a raw frame missing or changed, a damaged truth file)
    is marked ``failed`` in the revision with its reason (``on_failed(index, reason)`` is
    called) and the others are processed; at the end :class:`ReconstructIncomplete` names
    the failed captures. A full disk stops the revision (the capture is marked failed, the
    error raised). The session's lock is held while it runs (:class:`SessionBusy` if another
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
    ``exr_compression``, ``models``, ``prior_scale``; ``None`` arguments, and the :class:`ExrChoice` fields ``exr`` does not name or gives as ``None``,
    take the session's), its :class:`Processor` (on
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
                    _mark_revision(session, index, name, FAILED, reason)
                if is_disk_full(exc):
                    raise
                failed.append((index, reason))
                if on_failed:
                    on_failed(index, reason)
                continue
            except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM
                with guard.deferred():
                    _mark_revision(session, index, name, PENDING, interruption_reason(exc))
                raise
            if progress:
                progress(index, score)
    if failed:
        raise ReconstructIncomplete(session, name, failed, len(done))
    return name


def _mark_revision(session: Session, index: int, revision: str, status: str,
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
