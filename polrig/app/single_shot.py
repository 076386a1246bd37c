"""The one single-shot route (issue 30): a raw frame -> a Mueller result with its planes.

Every single-shot result goes through :class:`SingleShot`: a session's captures (capture and
``polrig reconstruct`` processing, :class:`polrig.app.processing.Processor`), ``polrig infer``
and the GUI's live Mueller view. The option rules live in
:class:`polrig.acquisition.plan.SingleShotOptions`; the result, :class:`SingleShotResult`, is
written by the one result writer, :func:`polrig.formats.exr.write_result_exr`, with one meaning
of its ``mask``: the reference solve's reason bits. ``tests/test_architecture.py`` fails if a
shell or processing builds a route of its own (imports the runtime or its lift, loads a model).

**The model loads once.** :meth:`SingleShot.open` keeps the loaded graph per weights folder and
device for the process: the capture's plan check
(:func:`polrig.app.calibrations.check_plan`), the capture's processing and the GUI's live view
get the same object, so a capture or a window loads the model once.

**Two front ends, one route.** The networks' input is one polarizer state's analyzer images:

* :meth:`SingleShot.frame`: one raw :class:`polrig.sensor.frame.Frame` (``polrig infer``, the
  live view): its values in ADC DN (:func:`polrig.solve.radiometry.adc_scale` of the noise
  model), black level removed, demosaicked; clipped samples (at the saturation level) mark
  their output pixels; ``dark`` from the measured ``S0`` against the noise model's sigma
  (:func:`polrig.app.preview.s0_snr`).
* :meth:`SingleShot.state`: one state's radiance of a capture
  (:func:`polrig.solve.radiometry.state_radiance`: frames averaged, HDR-merged, darks
  subtracted, with the noise model's variance carried through the demosaic); excluded samples
  go to the networks as NaN (:meth:`polrig.models.runtime.SingleShotModel.reconstruct`).

Then the same steps: the networks (:meth:`~polrig.models.runtime.SingleShotModel.reconstruct`,
or :func:`polrig.models.full_resolution.reconstruct_binned` with network binning), at full
resolution the lift with the measured detail of the full-resolution demosaic
(:func:`polrig.models.full_resolution.lift`), and the planes.

**The planes** (:class:`SingleShotResult`): ``mask`` ``(C, H, W)`` reason bits of the reference
solve (:data:`polrig.solve.reference.DARK`: outside the networks' object mask or ``S0`` below
:data:`polrig.solve.reference.MIN_SNR` noise sigmas, per colour: an object turned away from the
light is all noise, which the networks' relative object mask cannot tell;
:data:`~polrig.solve.reference.SATURATED`:
an object pixel of a colour with a clipped or excluded sample in its demosaic support; the
networks' estimate is kept in both; 0 = valid); ``sigma`` the model's calibrated standard
deviation (:mod:`polrig.models.uncertainty`; infinite where ``SATURATED``, NaN where the route is
not calibrated: at full resolution or with network binning); ``sigma_noise`` and ``residual`` 0
(not modelled); the object mask itself as :attr:`SingleShotResult.object` (the Mueller image is
0 outside it).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import threading
import time
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from polrig.acquisition.plan import PlanError, SingleShotOptions
from polrig.app.preview import BACKGROUND, s0_snr
from polrig.errors import FormatError
from polrig.formats.exr import UNCERTAINTY_PRECISIONS, colour_planes
from polrig.models.full_resolution import lift, reconstruct_binned
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import frame_layout
from polrig.sensor.demosaic import demosaic, demosaic_combined, output_shape, preprocess
from polrig.sensor.frame import Frame
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import ideal_inverse, saturation_mask, stokes_from_analyzers
from polrig.solve.radiometry import StateRadiance, adc_scale, analyzer_stack
from polrig.solve.reference import DARK, MIN_SNR, SATURATED, MuellerEstimate

if TYPE_CHECKING:
    from polrig.models.runtime import SingleShotModel

#: The header's description of a single-shot result's ``beyond_calibration.{colour}`` planes.
BEYOND_CALIBRATION_PLANE = ("1 = the pixel's misfit lies beyond the range the single-shot sigma was "
                            "calibrated on (models/uncertainty.py): its sigma may be too small")
#: The header's description of the single-shot ``sigma`` planes where the route is calibrated.
SIGMA_PLANE = ("standard deviation of M{rc}: the single-shot model's calibrated error "
               "(models/uncertainty.py); inf where clipped")
#: The header's descriptions of the other result planes (as a reference solve's file).
OTHER_PLANES = {"sigma_noise.M{rc}": "standard deviation of M{rc} from the sensor noise model alone",
                "mask": "reason bits, 0 = valid", "residual": "chi^2 per dof"}
#: The frame route per execution provider (issue 31): ``device``, the steps around the networks
#: as ONNX graphs on the provider's device with the frame kept there
#: (:class:`polrig.models.device_path.DevicePath`); ``host``, the numpy and OpenCV steps. CUDA
#: takes the device route; the CPU keeps the host route, measured faster there
#: (``benchmarks/results/single_shot_device_route.md``: the same numbers through onnxruntime's
#: CPU kernels instead of OpenCV's). Options the device route does not cover take the host
#: steps (:meth:`polrig.models.device_path.DevicePath.supports`).
FRAME_ROUTES = {"CUDAExecutionProvider": "device", "CPUExecutionProvider": "host"}
#: The header's descriptions of the ``geometry`` planes (:func:`geometry_planes`).
GEOMETRY_PLANES = {
    "geometry.normal.{X,Y,Z}": "the networks' unit surface normal, camera frame (X right, Y down, "
                               "Z forward), towards the camera; NaN outside the object",
    "geometry.albedo.{ch}": "the networks' diffuse albedo kd (pBRDF, Baek et al. 2018)",
    "geometry.light.{X,Y,Z}": "the networks' unit direction towards the light, camera frame",
    "geometry.roughness": "the networks' GGX roughness alpha: one value per image (header "
                          "roughness_alpha), repeated over the object",
}
#: Loaded routes kept per process (weights folder, device, graph files): the oldest beyond this
#: many goes (whoever holds it keeps it).
MAX_OPEN = 4


# -- geometry on the networks' grid ----------------------------------------------------------
def analyzer_grid_intrinsics(intrinsics: Sequence[float], offset_xy: Sequence[int],
                             raw_shape: tuple[int, int], grid_shape: tuple[int, int]
                             ) -> tuple[float, float, float, float]:
    """Full-sensor pinhole intrinsics ``(fx, fy, cx, cy)`` carried to the demosaiced analyzer
    grid of a readout with ROI offset ``offset_xy`` (pixels) and raw size ``raw_shape``
    ``(H, W)``: the principal point moves by the offset, and a grid ``p`` times coarser (the
    ``superpixel`` demosaic of a ``p x p`` mosaic period) has its pixel ``j`` centred on raw
    ``p j + (p - 1) / 2``, so ``f' = f / p`` and ``c' = (c - offset - (p - 1) / 2) / p``.
    A full-resolution grid (``bilinear``, ``newton``) keeps ``f`` and ``c - offset``."""
    if min(grid_shape[:2]) < 1 or min(raw_shape[:2]) < 1:
        raise ValueError(f"raw mosaic {tuple(raw_shape)} gives an empty analyzer grid "
                         f"{tuple(grid_shape)}: it is smaller than one layout cell")
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    ox, oy = (float(v) for v in offset_xy)
    py = raw_shape[0] / float(grid_shape[0])
    px = raw_shape[1] / float(grid_shape[1])
    return (fx / px, fy / py, (cx - ox - (px - 1) / 2) / px, (cy - oy - (py - 1) / 2) / py)


def network_kwargs(geometry: Mapping[str, Any] | None, frame: Frame, method: str = "superpixel"
                   ) -> dict[str, Any]:
    """``stage_zero_axis`` and ``intrinsics`` keyword arguments of
    :meth:`polrig.models.runtime.SingleShotModel.reconstruct` for one raw ``frame`` demosaiced
    with ``method``, from a single-shot geometry (:func:`polrig.app.calibrations.single_shot_geometry`;
    ``None``: the model's training geometry): the intrinsics carried to the analyzer grid by
    :func:`analyzer_grid_intrinsics`."""
    geometry = geometry or {}
    lay = frame_layout(frame)
    raw_shape = tuple(frame.raw.shape[-2:])
    ph, pw = lay.period
    if raw_shape[0] < ph or raw_shape[1] < pw:  # the demosaic's own one-line refusal
        raise ValueError(f"raw mosaic {raw_shape} is smaller than one {ph}x{pw} layout cell")
    intrinsics = geometry.get("intrinsics")
    if intrinsics is not None:
        intrinsics = analyzer_grid_intrinsics(intrinsics, frame.meta.offset_xy, raw_shape,
                                              output_shape(lay, raw_shape, method))
    return {"stage_zero_axis": geometry.get("stage_zero_axis_camera"), "intrinsics": intrinsics}


# -- the result --------------------------------------------------------------------------------
@dataclasses.dataclass(eq=False)
class SingleShotResult:
    """One single-shot reconstruction (module docstring, "The planes"): what
    :func:`polrig.formats.exr.write_result_exr` writes (:class:`polrig.formats.exr.ResultArrays`)
    and what a score or a display reads.

    ``mueller`` ``(C, 3, 3, H, W)`` float32 in ADC DN per unit incident S0 (0 outside
    :attr:`object`); ``sigma``, ``sigma_noise`` the same shape; ``mask`` ``(C, H, W)`` uint8
    reason bits, ``residual`` ``(C, H, W)`` (0); ``object`` ``(H, W)`` bool, the networks'
    object mask on the output grid; ``options`` the route's settings. From the networks:
    ``beyond_calibration`` ``(C, H, W)`` bool (object pixels whose misfit lies beyond the
    sigma's calibration range; only with the sigma) and ``beyond_fraction`` (the object's
    fraction so flagged), ``network_grid`` (``wi`` on the networks' own grid: the route runs the
    frame graph, without ``normal``, ``kd`` and ``mueller_init``; empty on the device route, which
    copies back only what the result's planes use), ``scale`` (ADC DN per
    normalised unit), ``alpha``, ``provider`` (the onnxruntime execution provider that ran them)
    with ``provider_options`` and ``provider_notes``, ``incident_rotation_deg``. From
    :meth:`SingleShot.frame` also ``stokes`` ``(C, 3, H, W)`` (the measured Stokes images on
    the output grid, ADC DN) and ``snr`` ``(C, H, W)`` (their ``S0`` over its noise sigma).
    ``timings_s``: seconds per step."""

    mueller: np.ndarray
    sigma: np.ndarray
    sigma_noise: np.ndarray
    mask: np.ndarray
    residual: np.ndarray
    object: np.ndarray
    options: SingleShotOptions
    stokes: np.ndarray | None = None
    snr: np.ndarray | None = None
    beyond_calibration: np.ndarray | None = None
    beyond_fraction: float | None = None
    network_grid: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    scale: float | None = None
    alpha: float | None = None
    provider: str = ""
    #: The provider's options as it ran them (:attr:`polrig.models.runtime.SingleShotModel.provider_options`)
    provider_options: dict[str, str] = dataclasses.field(default_factory=dict)
    #: One line per option onnxruntime refused (CUDA graphs, ...): the path ran without it.
    provider_notes: list[str] = dataclasses.field(default_factory=list)
    incident_rotation_deg: float | None = None
    timings_s: dict[str, float] = dataclasses.field(default_factory=dict)
    #: The live view's display-size grid of the nine elements ``(C, 3 dh, 3 dw)`` (the device
    #: route's :meth:`SingleShot.live`; then :attr:`mueller` is zeros and no pixel is flagged), else None.
    preview_grid: np.ndarray | None = None
    #: no state set: NaN (the reference solve's condition number, in a score's output)
    condition_number: float = float("nan")

    def estimate(self) -> MuellerEstimate:
        """What a score against a truth reads (the same arrays, not copies)."""
        return MuellerEstimate(self.mueller, self.sigma, self.mask, self.condition_number)

    @property
    def saturated(self) -> np.ndarray:
        """``(H, W)`` bool: object pixels with the ``SATURATED`` bit in some colour."""
        return np.any((self.mask & SATURATED) > 0, axis=0)

    def preview_flags(self) -> np.ndarray:
        """``(C, H, W)`` uint8 display reasons (:data:`polrig.app.preview.MASK_REASONS`):
        ``BACKGROUND`` outside the object, the mask's ``SATURATED`` bits; darkness is left to
        the displays' own signal-to-noise threshold (:func:`polrig.app.preview.display_valid`)."""
        return (np.where(self.object, 0, BACKGROUND).astype(np.uint8)[None]
                | (self.mask & np.uint8(SATURATED)).astype(np.uint8))

    def extra_planes(self, planes: Sequence[str], uncertainty: str = "float") -> dict[str, np.ndarray]:
        """The single-shot planes beside :func:`polrig.formats.exr.result_planes`' of the plane
        groups ``planes``: ``beyond_calibration.{colour}`` (0/1 in the uncertainty planes'
        precision) with the ``sigma`` group where the networks flagged them (they qualify the
        sigma); with the ``geometry`` group (:attr:`SingleShotOptions.geometry` runs the
        networks for it) :func:`geometry_planes`."""
        out: dict[str, np.ndarray] = {}
        if self.beyond_calibration is not None and "sigma" in planes:
            out.update(colour_planes("beyond_calibration", np.asarray(self.beyond_calibration)
                                     .astype(UNCERTAINTY_PRECISIONS[uncertainty])))
        if "geometry" in planes:
            out.update(geometry_planes(self))
        return out

    def header(self, planes: Sequence[str]) -> dict[str, Any]:
        """A result EXR's single-shot header entries for the plane groups ``planes``: the
        settings (``resolution``, ``network_binning`` where it is not 1: a binning-1 result is
        byte-identical to one from before the option, ``mirror_average``; at full resolution the
        grids, the networks' ``network_demosaic`` and the detail's ``output_demosaic``), the
        ``execution_provider`` with its ``execution_provider_options`` (and
        ``execution_provider_notes``, the options onnxruntime refused, where any), the object's
        ``beyond_calibration_fraction`` (``None`` where not known) and ``planes``, what each
        written plane group holds (the ``sigma`` planes' NaN
        where the route is not calibrated)."""
        o = self.options
        out: dict[str, Any] = {"mirror_average": o.mirror_average,
                               "beyond_calibration_fraction": self.beyond_fraction,
                               "resolution": o.resolution}
        if o.network_binning > 1:
            out["network_binning"] = o.network_binning
        out["execution_provider"] = self.provider
        if self.provider_options:
            out["execution_provider_options"] = dict(self.provider_options)
        if self.provider_notes:
            out["execution_provider_notes"] = list(self.provider_notes)
        if o.resolution == "full":
            out["network_demosaic"] = o.network_demosaic
            out["output_demosaic"] = o.demosaic
        notes = {"sigma.M{rc}": SIGMA_PLANE, **OTHER_PLANES}
        why = o.uncalibrated_because()
        if why:
            notes.update({"sigma.M{rc}": "NaN: the single-shot model's uncertainty is calibrated on the "
                                         "networks' unbinned (superpixel) grid only, not " + " or ".join(why),
                          "sigma_noise.M{rc}": "0 (not modelled for the single-shot method)"})
        out["planes"] = {k: v for k, v in notes.items() if k.split(".", 1)[0] in planes}
        if self.beyond_calibration is not None and "sigma" in planes:
            out["planes"]["beyond_calibration"] = BEYOND_CALIBRATION_PLANE
        if "geometry" in planes:
            out["planes"].update(GEOMETRY_PLANES)
            out["roughness_alpha"] = self.alpha
        return out


def _levels(frame: Frame, sensor: SensorModel, black_level_dn: float | None = None,
            saturation_dn: float | None = None) -> tuple[float, float, float]:
    """``(to_adc, black, saturation)``: the factor from the frame's DN to the ADC's and the
    black and saturation levels in ADC DN (defaults: the frame's black level, its bit depth's
    full scale)."""
    to_adc = adc_scale(sensor, frame.meta.bit_depth)
    black = float(frame.meta.black_level_dn if black_level_dn is None else black_level_dn) * to_adc
    saturation = float((2.0 ** frame.meta.bit_depth - 1) if saturation_dn is None else saturation_dn) * to_adc
    return to_adc, black, saturation
def geometry_planes(result: SingleShotResult) -> dict[str, np.ndarray]:
    """The ``geometry`` plane group (:data:`GEOMETRY_PLANES`) of a result whose route ran with
    :attr:`SingleShotOptions.geometry`: the networks' normal and light direction
    (``geometry.normal.{X,Y,Z}``, ``geometry.light.{X,Y,Z}``, camera frame), diffuse albedo
    (``geometry.albedo.{colour}``) and the image's one roughness (``geometry.roughness``), float32,
    NaN outside the object. :class:`ValueError` where the route did not keep them."""
    grid = result.network_grid
    if not all(k in grid for k in ("normal", "kd", "wi")):
        raise ValueError("the geometry planes need the route run with SingleShotOptions(geometry=True)")
    obj = np.asarray(result.object, bool)
    if grid["normal"].shape[-2:] != obj.shape:
        raise ValueError(f"geometry on the networks' grid {grid['normal'].shape[-2:]} is not the "
                         f"output grid {obj.shape}")
    keep = lambda a: np.where(obj, np.asarray(a, np.float32), np.float32(np.nan))  # noqa: E731
    out = {f"geometry.normal.{a}": keep(p) for a, p in zip("XYZ", grid["normal"])}
    out.update(colour_planes("geometry.albedo", keep(grid["kd"])))
    out.update({f"geometry.light.{a}": keep(p) for a, p in zip("XYZ", grid["wi"])})
    alpha = np.nan if result.alpha is None else result.alpha
    out["geometry.roughness"] = keep(np.full(obj.shape, alpha, np.float32))
    return out


@dataclasses.dataclass
class _Network:
    """The networks' answer on the analyzer grid (before a full-resolution lift)."""

    mueller: np.ndarray
    object: np.ndarray
    aux: dict[str, Any]


# -- the route --------------------------------------------------------------------------------
_OPEN: dict[tuple, "SingleShot"] = {}
_OPEN_LOCK = threading.Lock()


def _files_stamp(folder: pathlib.Path) -> tuple:
    """What identifies a weights folder's contents: its graph, description and uncertainty
    calibration files' sizes and modification times."""
    out = []
    for name in ("single_shot.onnx", "model.json", "uncertainty.json"):
        try:
            st = os.stat(folder / name)
        except OSError:
            out.append((name, None))
        else:
            out.append((name, st.st_size, st.st_mtime_ns))
    return tuple(out)


def _runs_on_cuda(device: str) -> bool:
    """Whether a model opened on ``device`` would run on CUDA, for ``--model-size auto``
    (:func:`polrig.models.sizes.choose_size`); asked only where a large model is shipped (else
    ``auto`` takes the small one anyway, and onnxruntime's providers are not looked at)."""
    from polrig.models import sizes

    if device == "cpu" or not sizes.is_shipped("large"):
        return False
    import onnxruntime as ort

    from polrig.models import devices

    return devices.CUDA in devices.choose_providers(device, ort.get_available_providers())


class SingleShot:
    """The single-shot route through one loaded model (:class:`polrig.models.runtime.SingleShotModel`).

    :meth:`open` loads (once per process, weights folder and device) the installed or a given
    model; ``SingleShot(model)`` wraps one already loaded (a test's, a benchmark's). Per frame
    :meth:`frame` or :meth:`state` with the :class:`polrig.acquisition.plan.SingleShotOptions`
    (a live view changes them between frames; the model stays)."""

    def __init__(self, model: "SingleShotModel", frame_route: str | None = None):
        self.model = model
        if frame_route is None:
            frame_route = FRAME_ROUTES.get(model.provider, "host")
        if frame_route not in ("host", "device"):
            raise ValueError(f"frame_route must be host or device, got {frame_route!r}")
        #: How :meth:`frame` runs its steps around the networks (:data:`FRAME_ROUTES`).
        self.frame_route = frame_route
        self._device = None

    @classmethod
    def open(cls, device: str = "auto", weights: str | os.PathLike | None = None,
             size: str = "auto") -> "SingleShot":
        """The route on ``device`` (``auto``, ``cpu``, ``cuda``: :mod:`polrig.models.devices`)
        with the graph in ``weights`` (default: the installed model of ``size``, ``auto``,
        ``small`` or ``large``: :func:`polrig.models.sizes.choose_size`, the small one on a CPU),
        the same object for every caller of this process while the folder's files are unchanged:
        the plan check, the capture's processing and the GUI's live view share one loaded model.

        The installed model missing or unloadable: :class:`polrig.acquisition.plan.PlanError`
        of ``mode`` (one line: use the reference method); a size asked for by name that is not
        shipped: :class:`polrig.models.sizes.ModelSizeUnavailable` (one line: how to get it); a
        given ``weights`` folder's problem is raised as it is (``FileNotFoundError``,
        :class:`polrig.errors.FormatError`); a forced ``cuda`` that cannot run:
        :class:`polrig.models.devices.DeviceUnavailable`."""
        try:
            from polrig.models import runtime, sizes
        except ImportError:
            raise PlanError("mode", "no single-shot model is installed (polrig.models.runtime is "
                                    "missing); use the reference method",
                            subject="single-shot", what="mode") from None
        if weights is not None:
            folder = pathlib.Path(weights)
        else:
            folder = sizes.size_folder(sizes.choose_size(size, size == "auto" and _runs_on_cuda(device)))
        key = (str(folder.resolve()), str(device), _files_stamp(folder))
        with _OPEN_LOCK:
            route = _OPEN.get(key)
            if route is None:
                try:
                    route = cls(runtime.SingleShotModel.load(folder, device=device))
                except (FileNotFoundError, OSError, FormatError) as exc:
                    if weights is not None:
                        raise
                    raise PlanError("mode", f"no single-shot model is installed ({exc}); use the "
                                            f"reference method", subject="single-shot", what="mode") from None
                _OPEN[key] = route
                while len(_OPEN) > MAX_OPEN:
                    _OPEN.pop(next(iter(_OPEN)))
        return route

    def model_header(self) -> dict[str, Any]:
        """What a result records of the model that made it (:func:`polrig.models.sizes.model_record`,
        read from its ``model.json``): the header's ``model_size`` (``small``, ``large``, or None
        for a folder of the user's) and ``model_training`` (width, hardware, minutes)."""
        from polrig.models.sizes import model_record

        record = model_record(self.model.weights_dir, getattr(self.model, "meta", None))
        return {"model_size": record.pop("size"), "model_training": record}

    @property
    def provider(self) -> str:
        """The onnxruntime execution provider that runs the networks."""
        return self.model.provider

    def check_sigma(self) -> None:
        """A one-line :class:`PlanError` of ``mode`` unless the loaded graph has a calibrated
        uncertainty (the hybrid method's prior is its estimate with that sigma)."""
        if self.model.uncertainty is None:
            from polrig.models.uncertainty import how_to_calibrate

            raise PlanError("mode", f"the hybrid method needs the single-shot model's calibrated sigma: "
                                    f"{self.model.uncertainty_problem}; {how_to_calibrate(self.model.weights_dir)}",
                            subject="hybrid", what="mode")

    def prior_model(self, mirror_average: bool) -> dict[str, Any]:
        """What identifies this route as a hybrid result's prior (the manifest's ``prior`` record,
        :class:`polrig.app.manifest.PriorRecord`, less the seen state; the result header's
        ``prior_model``): the graph's file name and SHA-256 (the one its uncertainty calibration
        was verified against at load), the ``uncertainty.json`` SHA-256 and format version, the
        execution provider and ``mirror_average``; ``joint_prior_version`` where the calibration
        holds the joint prior (the hybrid solve then uses it). Needs a calibrated sigma
        (:meth:`check_sigma`)."""
        import hashlib

        from polrig.models.uncertainty import FILE_NAME, VERSION

        self.check_sigma()
        unc = pathlib.Path(self.model.weights_dir) / FILE_NAME
        return {"graph": "single_shot.onnx", "graph_sha256": self.model.uncertainty.graph_sha256,
                "uncertainty_sha256": hashlib.sha256(unc.read_bytes()).hexdigest(),
                "uncertainty_version": int(VERSION), "execution_provider": self.provider,
                "mirror_average": bool(mirror_average),
                **({} if self.model.uncertainty.joint is None
                   else {"joint_prior_version": int(self.model.uncertainty.joint["version"])})}

    # -- front ends ---------------------------------------------------------------------------
    def frame(self, frame: Frame, state_deg: float, options: SingleShotOptions, *,
              geometry: Mapping[str, Any] | None = None, sensor: SensorModel | None = None,
              black_level_dn: float | None = None, saturation_dn: float | None = None,
              scale: float | None = None, stage_zero_axis=None) -> SingleShotResult:
        """One raw frame taken with the ideal polarizer at stage angle ``state_deg``.

        ``sensor``: the camera's noise model (default the IMX250 one): its ADC's DN are the
        result's unit (the frame's values times :func:`polrig.solve.radiometry.adc_scale`) and its
        noise decides ``dark``. ``black_level_dn`` (default the frame's) and ``saturation_dn``
        (the raw value at which the sensor clips, black level included; default the full scale of
        the frame's bit depth) are in the frame's DN. ``geometry``: the rig's single-shot
        geometry (:func:`polrig.app.calibrations.single_shot_geometry`; ``None``: the model's
        training geometry); ``stage_zero_axis`` overrides its axis. ``scale``: ADC DN per
        normalised unit (default: from the image)."""
        self._check(options)
        sensor = sensor or SensorModel()
        to_adc, black, saturation = _levels(frame, sensor, black_level_dn, saturation_dn)
        if self.frame_route == "device" and not self.device_refuses(frame, options):
            return self._frame_on_device(frame, state_deg, options, geometry=geometry, sensor=sensor,
                                         to_adc=to_adc, black=black, saturation=saturation, scale=scale,
                                         stage_zero_axis=stage_zero_axis)
        raw = frame.raw.astype(np.float64) * to_adc if to_adc != 1 else frame.raw
        lay = frame_layout(frame)
        kwargs = network_kwargs(geometry, frame, options.network_demosaic)
        if stage_zero_axis is not None:
            kwargs["stage_zero_axis"] = stage_zero_axis
        full = options.resolution == "full"
        t0 = time.perf_counter()
        analyzer = demosaic(raw, lay, options.network_demosaic, black_level_dn=black)
        clipped = None if full else saturation_mask(raw, lay, options.demosaic, saturation)
        t1 = time.perf_counter()
        stokes = stokes_from_analyzers(analyzer)
        t2 = time.perf_counter()
        s_in = polarizer_stokes(np.deg2rad(float(state_deg))).astype(np.float32)
        net = self._network(analyzer, s_in, options, kwargs, scale=scale, stokes=stokes)
        del analyzer
        timings = dict(net.aux["timings_s"], demosaic=t1 - t0, stokes=t2 - t1)
        mueller, obj = net.mueller, net.object
        if full:  # the measured detail of the full-resolution demosaic (models/full_resolution.py)
            t3 = time.perf_counter()
            x = preprocess(raw, black_level_dn=black)
            x[np.asarray(raw) >= saturation] = np.nan  # clipped samples: the demosaic marks their support
            stokes_full = demosaic_combined(x, lay, options.demosaic, ideal_inverse())  # one colour at a time
            del x
            clipped = ~np.all(np.isfinite(stokes_full), axis=1)
            mueller, obj = lift(mueller, obj, stokes, stokes_full, s_in, lay.period)
            stokes = stokes_full
            timings["full_resolution"] = time.perf_counter() - t3
        snr = s0_snr(stokes[:, 0], sensor, frame.meta.exposure_us)
        with np.errstate(invalid="ignore"):
            low = snr < MIN_SNR  # unknown (a clipped sample's NaN): not dark, SATURATED says why
        result = self._result(mueller, obj, low, clipped, net, options)
        result.stokes, result.snr, result.timings_s = stokes, snr, timings
        return result

    def live(self, frame: Frame, state_deg: float, options: SingleShotOptions, *, max_display_px: int | None,
             geometry: Mapping[str, Any] | None = None, sensor: SensorModel | None = None) -> SingleShotResult:
        """One live-view frame (issue 31, item 4). On the device route the 3x3 grid of the
        elements is rendered on the device at display size (each element area-averaged to a
        long side of ``max_display_px / 3``: :attr:`SingleShotResult.preview_grid`, the only
        image copied back; :attr:`~SingleShotResult.mueller` is zeros; ``None``: the whole
        Mueller image instead) and the light-direction probe runs on every
        :attr:`polrig.models.device_path.DevicePath.probe_every` th frame
        (:data:`~polrig.models.device_path.LIVE_PROBE_EVERY`), its direction reused in between.
        The host route is :meth:`frame` unchanged."""
        if self.frame_route != "device" or self.device_refuses(frame, options):
            return self.frame(frame, state_deg, options, geometry=geometry, sensor=sensor)
        self._check(options)
        sensor = sensor or SensorModel()
        lay = frame_layout(frame)
        raw_shape = tuple(frame.raw.shape[-2:])
        h, w = raw_shape if options.resolution == "full" else output_shape(lay, raw_shape, "superpixel")
        step = max(1, -(-3 * max(h, w) // max(1, int(max_display_px or 1))))
        to_adc, black, saturation = _levels(frame, sensor)
        return self._frame_on_device(
            frame, state_deg, options, geometry=geometry, sensor=sensor, to_adc=to_adc,
            black=black, saturation=saturation, scale=None, stage_zero_axis=None,
            preview_size=None if max_display_px is None else (max(1, h // step), max(1, w // step)),
            probe_every=self.device_path().probe_every)

    def device_path(self):
        """The :class:`polrig.models.device_path.DevicePath` of this route's model (made once)."""
        if self._device is None:
            from polrig.models.device_path import DevicePath

            self._device = DevicePath(self.model)
        return self._device

    def device_refuses(self, frame: Frame, options: SingleShotOptions) -> str:
        """Why the device route cannot take ``frame`` with ``options`` (one line; ``""``: it can)."""
        lay = frame_layout(frame)
        return self.device_path().supports(options, output_shape(lay, tuple(frame.raw.shape[-2:]), "superpixel"))

    def _frame_on_device(self, frame: Frame, state_deg: float, options: SingleShotOptions, *, geometry,
                         sensor: SensorModel, to_adc: float, black: float, saturation: float,
                         scale: float | None, stage_zero_axis, preview_size=None,
                         probe_every: int = 1) -> SingleShotResult:
        """:meth:`frame` with its steps on the provider's device (:data:`FRAME_ROUTES`)."""
        lay = frame_layout(frame)
        kwargs = network_kwargs(geometry, frame, options.network_demosaic)
        if stage_zero_axis is not None:
            kwargs["stage_zero_axis"] = stage_zero_axis
        per_dn, offset = sensor.variance_terms(frame.meta.exposure_us)
        s_in = polarizer_stokes(np.deg2rad(float(state_deg))).astype(np.float32)
        with_sigma = options.with_sigma and self.model.uncertainty is not None
        out = self.device_path().frame(
            frame.raw, lay, to_adc=to_adc, black=black, saturation=saturation, s_in=s_in,
            resolution=options.resolution, stage_zero_axis=kwargs["stage_zero_axis"],
            intrinsics=kwargs["intrinsics"], scale=scale, half_per_dn=float(np.float32(0.5 * per_dn)),
            noise_offset=float(offset), with_stokes=True, preview_size=preview_size,
            probe_every=probe_every)
        m_net = out["object"] if options.resolution != "full" else None
        aux: dict[str, Any] = {"scale": out["scale"], "alpha": out["alpha"], "provider": self.provider,
                               "provider_options": self.model.provider_options,
                               "incident_rotation_deg": out["incident_rotation_deg"], "network_grid": {}}
        mueller = out.get("mueller")
        if with_sigma and mueller is not None:
            unc = self.model.uncertainty
            aux["sigma"] = unc.sigma(mueller, s_in, m_net, out["stokes"], None, out["light_spread"])
            beyond = unc.beyond_calibration(mueller, s_in, m_net, out["stokes"])
            if beyond is not None:
                aux["beyond_calibration"], aux["mask"] = beyond, m_net
        net = _Network(mueller, out["object"], aux)
        if mueller is None:  # the live view's grid: no planes came back (nothing flagged, zeros)
            shape = (lay.n_colours,) + out["object"].shape
            mueller = np.broadcast_to(np.float32(0), shape[:1] + (3, 3) + shape[1:])
            low = clipped = np.broadcast_to(False, shape)
        else:
            with np.errstate(invalid="ignore"):
                low = out["snr"] < MIN_SNR
            clipped = out["clipped"]
        result = self._result(mueller, out["object"], low, clipped, net, options)
        result.stokes, result.snr, result.timings_s = out.get("stokes"), out.get("snr"), out["timings_s"]
        result.preview_grid = out.get("grid")
        return result

    def state(self, state: StateRadiance, frame: Frame, s_in, options: SingleShotOptions, *,
              geometry: Mapping[str, Any] | None = None) -> SingleShotResult:
        """One polarizer state's radiance ``state`` of a capture (ADC DN with its variance,
        :func:`polrig.solve.radiometry.state_radiance`) under the incident state ``s_in``
        ``(3,)``; ``frame``: one of its raw frames (layout, ROI offset, size). ``dark`` compares
        ``S0`` with the sigma the noise model's variance gives it through the demosaic;
        ``SATURATED`` marks the analyzer samples the radiance excluded. ``geometry`` as
        :meth:`frame`."""
        self._check(options)
        lay = frame_layout(frame)
        full = options.resolution == "full"
        measured, variance, valid, _ = analyzer_stack(state, lay, options.network_demosaic)
        bracketed = state.clipped_reference is not None
        if bracketed:  # the networks see what the reference exposure's frame shows, as trained
            seen = analyzer_stack(dataclasses.replace(state, excluded=state.reference_exclusions()), lay,
                                  options.network_demosaic)[2]
        else:
            seen = valid
        network_input = np.where(seen, measured, np.nan)
        net = self._network(network_input, s_in, options,
                            network_kwargs(geometry, frame, options.network_demosaic))
        if bracketed:
            self._measured_highlights(net, s_in, np.where(valid, measured, np.nan), ~np.all(seen, axis=1), options)
        mueller, obj = net.mueller, net.object
        if full:  # the detail from the full-resolution demosaic of the same radiance
            stokes_sp = stokes_from_analyzers(network_input)  # NaN where excluded: no detail there
            measured, variance, valid, _ = analyzer_stack(state, lay, options.demosaic)
            stokes_full = stokes_from_analyzers(np.where(valid, measured, np.nan))
            mueller, obj = lift(mueller, obj, stokes_sp, stokes_full, s_in, lay.period)
            del stokes_sp, stokes_full
        del network_input
        s0, s0_sigma = 0.5 * measured.sum(axis=1), 0.5 * np.sqrt(variance.sum(axis=1))  # (C, H, W)
        with np.errstate(invalid="ignore"):
            low = ~(s0 >= MIN_SNR * s0_sigma)
        result = self._result(mueller, obj, low, ~np.all(valid, axis=1), net, options)
        result.timings_s = dict(net.aux["timings_s"])
        return result

    def _measured_highlights(self, net: _Network, s_in, analyzer: np.ndarray, clipped: np.ndarray,
                             options: SingleShotOptions) -> None:
        """Where the reference exposure clipped (``clipped`` ``(C, h, w)``) but the state's
        bracket measured ``analyzer`` ``(C, 4, h, w)`` (NaN where no exposure did), the
        network's estimate rescaled to the measured intensity and its sigma the calibrated
        model's there (:mod:`polrig.models.highlights`); ``net`` is updated in place."""
        from polrig.models.highlights import highlight_sigma, measured_highlights

        if net.mueller.shape[-2:] != analyzer.shape[-2:]:  # network binning: its grid is not the input's
            return
        stokes = stokes_from_analyzers(analyzer)
        mueller, rescaled = measured_highlights(net.mueller, s_in, stokes, clipped & net.object[None])
        if not rescaled.any():
            return
        net.mueller = mueller
        unc = self.model.uncertainty
        if options.with_sigma and unc is not None and "sigma" in net.aux:
            net.aux["sigma"] = highlight_sigma(
                net.aux["sigma"], unc.sigma(mueller, s_in, net.object, stokes,
                                            light_spread=net.aux.get("light_spread")), rescaled)

    # -- the shared steps ---------------------------------------------------------------------
    def _check(self, options: SingleShotOptions) -> None:
        """Before the work: a sigma asked for needs a calibration of this graph."""
        if options.sigma and self.model.uncertainty is None:
            from polrig.models.uncertainty import how_to_calibrate

            raise PlanError("sigma", f"{self.model.uncertainty_problem}; "
                                     f"{how_to_calibrate(self.model.weights_dir)}")

    def _network(self, analyzer: np.ndarray, s_in, options: SingleShotOptions, kwargs: dict, *,
                 scale: float | None = None, stokes: np.ndarray | None = None) -> _Network:
        """The networks on analyzer images ``(C, 4, h, w)`` (DN): their answer on that grid
        (binned and lifted back with network binning), in the rig's incident frame."""
        # At full resolution the networks' arena goes back before the lift's 0.5-1 GB of planes
        # (the full colour sensor's one-shot peak 1959 -> 1852 MB, no measurable time); the
        # superpixel route keeps it: the next frame's pass would fault it in again (+90 ms CPU).
        release = True if options.resolution == "full" else None
        # the route reads mueller, wi and alpha: the graph without the other outputs (issue 31),
        # unless the geometry planes (normal, kd) are asked for
        kwargs = dict(kwargs, outputs="all" if options.geometry else "frame")
        if options.network_binning > 1:
            mueller, aux = reconstruct_binned(self.model, analyzer, s_in, options.network_binning,
                                              stokes=stokes, scale=scale,
                                              mirror_average=options.mirror_average,
                                              release_arena=release, **kwargs)
            grid = aux.pop("network_grid")
        else:
            mueller, aux = self.model.reconstruct(analyzer, s_in, scale=scale, with_sigma=options.with_sigma,
                                                  mirror_average=options.mirror_average,
                                                  release_arena=release, **kwargs)
            grid = {k: aux.pop(k) for k in ("normal", "kd", "wi", "mueller_init") if k in aux}
        aux["network_grid"] = grid
        return _Network(mueller, np.asarray(aux["mask"], bool), aux)

    def _result(self, mueller: np.ndarray, obj: np.ndarray, low: np.ndarray, clipped: np.ndarray,
                net: _Network, options: SingleShotOptions) -> SingleShotResult:
        """The result's planes from the Mueller image on the output grid, its object mask
        ``obj`` ``(H, W)``, the pixels whose ``S0`` is below the noise threshold ``low`` and
        those with a clipped or excluded sample ``clipped`` (``(C, H, W)``)."""
        aux = net.aux
        c, h, w = mueller.shape[0], mueller.shape[-2], mueller.shape[-1]
        dark = ~obj[None] | low
        clipped = np.asarray(clipped, bool) & obj[None]  # (C, H, W)
        mask = (np.where(dark, DARK, 0) | np.where(clipped, SATURATED, 0)).astype(np.uint8)
        zeros = np.zeros((c, h, w), np.float32)
        if not options.sigma_calibrated:  # not calibrated at this resolution or binning: NaN
            sigma = np.broadcast_to(np.float32(np.nan), mueller.shape)
            sigma_noise = np.broadcast_to(np.float32(0), mueller.shape)
        else:  # the estimate comes from clipped data where SATURATED: no error bound there
            sigma = np.asarray(aux.get("sigma", np.zeros_like(mueller)), np.float32)
            sigma = np.where(clipped[:, None, None], np.float32(np.inf), sigma)
            sigma_noise = np.zeros_like(sigma)
        beyond = aux.get("beyond_calibration")
        fraction = None
        if beyond is not None:
            fraction = self.model.uncertainty.beyond_fraction(beyond, aux["mask"])
        return SingleShotResult(
            mueller.astype(np.float32, copy=False), sigma, sigma_noise, mask, zeros, obj, options,
            beyond_calibration=beyond, beyond_fraction=fraction, network_grid=aux["network_grid"],
            scale=aux.get("scale"), alpha=aux.get("alpha"), provider=aux.get("provider", self.provider),
            provider_options=dict(aux.get("provider_options") or {}),
            provider_notes=list(getattr(self.model, "device_notes", [])),
            incident_rotation_deg=aux.get("incident_rotation_deg"))
