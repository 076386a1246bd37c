"""Turn a capture's raw frames into Mueller images (with uncertainty and mask), and score them.

Array level: :mod:`polrig.solve.radiometry` (state radiance, demosaic, solve) and
:mod:`polrig.solve.scoring` (truth on the output grid, score); their names are re-exported here.

The array-level functions live in :mod:`polrig.solve.radiometry` and :mod:`polrig.solve.scoring`, the
calibration and its geometry in :mod:`polrig.app.calibrations`, a session's frame files in
:mod:`polrig.app.sessionio`; this module composes them.

Session level: :class:`Processor` (used by :func:`polrig.app.capture.run_session`) reads a
capture's raw frames back from the session (checksums verified), solves, writes
``mueller.exr`` (Mueller channels plus ``sigma``, ``residual`` and ``mask`` planes), and on the
simulated rig ``truth_mueller.exr`` and a score (the files written and recorded by
:mod:`polrig.app.result_files`); :func:`polrig.app.reconstruct.reprocess_session` does the same
into a new revision for ``polrig reconstruct``.

Uncertainty propagation from the raw samples to the result: :mod:`polrig.solve.radiometry`.
"""

from __future__ import annotations

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
    diffuse_header,
    diffuse_planes,
    missing_geometry,
    solve_diffuse,
)
from polrig.app.records import (  # noqa: F401 (re-exported)
    sensor_model_of,
    session_frame_geometry,
    session_sensor_model,
)
from polrig.app.result_files import (
    CaptureResult,
    TruthScore,
    file_record,
    new_result_path,
    record_result,
    remove_files,
    write_and_score,
)
from polrig.app.session import Session, sha256_file
from polrig.app.sessionio import CaptureFrames, load_capture_frames, read_verified_frame  # noqa: F401 (re-exported)
from polrig.app.single_shot import SingleShot, SingleShotResult
from polrig.choices import DEFAULT_PRIOR_SCALE
from polrig.errors import FormatError
from polrig.formats.exr import channel_suffixes, write_mueller_exr
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
from polrig.solve.reference import ReferenceResult, reason_names
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
        path = new_result_path(session.root, relpath)
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
        :meth:`solve` and :func:`polrig.app.result_files.record_result`, with the file written
        and scored in between (:func:`polrig.app.result_files.write_and_score`)."""
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


