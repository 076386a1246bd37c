"""Single-shot Mueller reconstruction with onnxruntime (never imports torch).

:meth:`SingleShotModel.load` opens the shipped graph ``models/weights/single_shot.onnx``
(PIPNet -> pBRDF -> PMMNet in one graph, see :mod:`polrig.models.export` for why one graph) and
:meth:`SingleShotModel.reconstruct` turns one capture's analyzer images ``(C, 4, H, W)`` in DN
under a known incident state ``s_in`` into a Mueller image ``(C, 3, 3, H, W)`` in DN per unit
incident S0 (``docs/conventions.md``, "Radiometric units"). From a raw frame (demosaic, the
full-resolution lift, the result's planes) the one route is :class:`polrig.app.single_shot.SingleShot`.

Steps: mask (given, or ``S0 > mask_fraction * percentile99(S0)``), normalisation by ``scale``
(DN per normalised unit: given, or :func:`default_scale`, the same rule the simulator's
dataset writer uses), view directions ``wo`` from the pinhole intrinsics (default: the
simulated rig's camera, ``fx = fy = 2.5 min(H, W)``, principal point at the image centre),
padding to a multiple of 8 pixels (edge padding, masked out), the network in its training
frame (below), crop, back to DN.

Incident frame: the networks were trained with one stage zero axis (``model.json``
``stage_zero_axis_camera``, the camera's up direction), and PIPNet reads the incident state
``s_in`` without the axis, so an ``s_in`` expressed about another axis means another physical
polarizer direction to it (on the default simulated rig, whose axis is ~85 deg away, its light
direction came out rotated by about that much). :meth:`SingleShotModel.run_rig_frame` therefore
re-expresses ``s_in`` in the training frame (``S_model = R(theta) S_rig``, ``theta`` the angle
between the two incident ``x`` axes about the illumination direction, ``docs/conventions.md``),
runs the graph there, and turns the result back per pixel (``M_rig = M_model R(theta_p)``, with
the network's own light direction ``wi`` for ``theta_p``). This is exact by the definition of
the incident frame wherever ``wi`` is right; the illumination direction for the input rotation
starts at the optical axis and is refined once from the network's mean ``wi``. On inputs whose
short side is 256 pixels or more that mean comes from one pass on the inputs area-reduced to a
short side of about 128 (:func:`probe_shape`), and the full-size graph runs once, at the refined
angle (1.06 passes instead of 2 at the full colour sensor's grid).

Arbitrary sizes: the networks are fully convolutional, so any size runs in one pass (padded
to a multiple of 8). Images with more than ``max_pixels`` pixels (default 1.5 Mpx, about
2 GB of activations) are resized down with area averaging to fit, reconstructed, and the
Mueller image is resized back bilinearly (the output then has the detail of the reduced
size; pass a larger ``max_pixels`` to avoid it). Tiling is not used because the roughness is
image-wide (pooled over the whole mask).

Threading: ``intra_op_num_threads`` = the number of physical cores, one inter-op thread,
sequential execution, all graph optimisations, no spinning by default (onnxruntime
performance tuning guide, "Thread management").
"""

from __future__ import annotations

import json
import os
import pathlib
import time

import numpy as np

from polrig.errors import FormatError
from polrig.models import devices, mirror
from polrig.models.size import SIZE_MULTIPLE
from polrig.models.uncertainty import UncertaintyModel, calibration_for_graph, light_spread
from polrig.sensor.stokes import stokes_from_analyzers
from polrig.solve.quantiles import tail_percentile

WEIGHTS_DIR = pathlib.Path(__file__).resolve().parent / "weights"
#: Percentile of the analyzer values in the mask that the normalisation maps to 1 (polrig.sim.dataset).
SCALE_PERCENTILE = 99.5
#: Stage zero axis of the simulated rig in the camera frame (polrig.sim.dataset manifest), used when
#: neither the caller nor the model's ``model.json`` gives one.
DEFAULT_STAGE_ZERO_AXIS = (0.0, -1.0, 0.0)
#: Incident frames whose ``(cos theta, sin theta)`` before normalisation have a squared length
#: below this (an axis within about 1e-7 rad of the illumination) are degenerate: ``theta = 0``.
DEGENERATE_FRAME_SQ = 1e-14
#: Fraction of the 99th percentile of S0 below which a pixel is background when no mask is given.
MASK_FRACTION = 0.02
#: Largest normalised level (the in-mask 99.5th percentile divided by a caller's ``scale``)
#: that :meth:`SingleShotModel.reconstruct` accepts; the training data sit at 1.
MAX_INPUT_LEVEL = 100.0
#: Noise standard deviations above the darkest percentile of S0 that a small object's pixels
#: must reach (:func:`default_mask`).
MASK_NOISE_SIGMAS = 6.0
#: Focal length of the simulated rig's camera in units of min(H, W) (polrig.sim.scene.default_camera).
DEFAULT_FOCAL_PER_PX = 2.5
#: Colours x pixels of one network pass above which a run gives its memory arena back
#: (:class:`SingleShotModel`): the mono full sensor (3 x 1224 x 1024) does, the colour sensor's
#: superpixel grid (3 x 612 x 512) does not.
SHRINK_ARENA_ABOVE = 2_000_000
#: Short side (pixels) of the reduced pass that estimates the light direction for the
#: incident-frame refinement (:func:`probe_shape`).
PROBE_SIDE = 128
#: Sessions with fixed input sizes a model keeps (:meth:`SingleShotModel.run_normalised`): the
#: probe's and the frame's per sensor size and route (host, device) and a few more; the least
#: recently used goes beyond.
MAX_SESSIONS = 8
#: The graphs with fewer outputs (:mod:`polrig.models.export`) a run asking only for these uses.
OUTPUT_GRAPHS = {"frame": "single_shot_frame.onnx", "probe": "single_shot_probe.onnx"}
#: Graph outputs with a colour axis first (after the batch axis): averaged to one colour for a mono sensor.
COLOUR_OUTPUTS = ("mueller", "mueller_init", "kd", "mueller_disagreement")


def physical_cores() -> int:
    """Physical CPU cores available to this process (``/proc/cpuinfo`` core ids, else the
    affinity mask)."""
    try:
        avail = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - non-Linux
        avail = os.cpu_count() or 1
    try:
        cores, phys = set(), None
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("physical id"):
                phys = line.split(":")[1].strip()
            elif line.startswith("core id"):
                cores.add((phys, line.split(":")[1].strip()))
        if cores:
            return max(1, min(len(cores), avail))
    except OSError:  # pragma: no cover
        pass
    return max(1, avail)


def view_directions(shape: tuple[int, int], intrinsics: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """Unit directions surface -> camera ``wo`` ``(3, H, W)`` (camera frame, OpenCV axes) of a
    pinhole camera with ``intrinsics = (fx, fy, cx, cy)`` in pixels of the analyzer image
    (default: the simulated rig's camera). Pixel centres are at integer coordinates."""
    h, w = shape
    if intrinsics is None:
        f = DEFAULT_FOCAL_PER_PX * min(h, w)
        intrinsics = (f, f, (w - 1) / 2.0, (h - 1) / 2.0)
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    x = (np.arange(w, dtype=np.float64) - cx) / fx
    y = (np.arange(h, dtype=np.float64) - cy) / fy
    ray = np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((1, 1))), 0)
    return (-ray / np.linalg.norm(ray, axis=0, keepdims=True)).astype(np.float32)


def incident_rotation(wi: np.ndarray, stage_zero_axis, model_axis, *,
                      vector_axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """``(cos 2theta, sin 2theta)`` of the basis change from the rig's incident frame (``x`` from
    ``stage_zero_axis``) to the model's (``x`` from ``model_axis``) for light arriving along
    ``-wi`` (surface -> light, camera frame, vector components along ``vector_axis``: ``(..., 3)``
    by default, ``vector_axis=1`` for plane-first images ``(B, 3, H, W)``): ``S_model = R(theta)
    S_rig`` and ``M_rig = M_model R(theta)`` (``docs/conventions.md``, "Stokes reference
    frames"; :func:`polrig.optics.bases.rotation_cos_sin_2theta`). The axes are ``(3,)`` or
    ``(B, 3)``, camera frame, any non-zero length. Computed in ``wi``'s floating dtype (float32
    images stay float32). A degenerate frame (an axis along the illumination) gives
    ``theta = 0``.

    Closed form: with ``k = -wi`` and ``a``, ``b`` the two axes, the frames' ``x`` are ``a`` and
    ``b`` made perpendicular to ``k`` (``u = a - (a.k) k / |k|^2``, likewise ``v``), and
    ``theta`` turns ``u`` into ``v`` about ``k``: ``cos theta ~ u.v = a.b - (a.k)(b.k) / |k|^2``
    and ``sin theta ~ k.(u x v) / |k| = k.(a x b) / |k|``, with the same positive factor
    ``1 / (|u| |v|)``, which cancels in ``cos 2theta = (c^2 - s^2) / (c^2 + s^2)`` and
    ``sin 2theta = 2 c s / (c^2 + s^2)``: three dot products per pixel, no normalisation
    (``tests/test_single_shot_rig.py`` checks it against :mod:`polrig.optics.bases`' Gram-Schmidt
    frames and the pBRDF evaluated in both frames)."""
    w = np.asarray(wi)
    dtype = w.dtype if np.issubdtype(w.dtype, np.floating) else np.float64
    k = [-np.take(w, i, axis=vector_axis).astype(dtype, copy=False) for i in range(3)]

    def unit_axes(v) -> np.ndarray:
        v = np.asarray(v, np.float64).reshape(-1, 3)
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def per_batch(x: np.ndarray) -> np.ndarray:  # (B,) -> broadcastable against a component of k
        return x.astype(dtype).reshape(x.shape[:1] + (1,) * (k[0].ndim - 1) if k[0].ndim else ())

    a, b = unit_axes(stage_zero_axis), unit_axes(model_axis)
    n = np.cross(a, b)
    ka, kb, kn = (sum(k[i] * per_batch(v[:, i]) for i in range(3)) for v in (a, b, n))
    kk = k[0] * k[0] + k[1] * k[1] + k[2] * k[2]
    with np.errstate(invalid="ignore", divide="ignore"):
        c = per_batch(np.sum(a * b, axis=-1)) - ka * kb / kk
        s = kn / np.sqrt(kk)
        r2 = c * c + s * s
        ok = np.isfinite(r2) & (r2 > DEGENERATE_FRAME_SQ)
        r2 = np.where(ok, r2, 1.0)
        cos2 = np.where(ok, (c * c - s * s) / r2, 1.0).astype(dtype, copy=False)
        sin2 = np.where(ok, 2.0 * c * s / r2, 0.0).astype(dtype, copy=False)
    return cos2, sin2


def rotate_stokes(s: np.ndarray, cos2, sin2) -> np.ndarray:
    """``R(theta) S`` for Stokes vectors ``(..., 3)`` (S0 unchanged)."""
    s = np.asarray(s, np.float64)
    c, n = np.asarray(cos2), np.asarray(sin2)
    parts = np.broadcast_arrays(s[..., 0], c * s[..., 1] + n * s[..., 2], c * s[..., 2] - n * s[..., 1])
    return np.stack(parts, -1)


def rotate_incident_columns(m: np.ndarray, cos2: np.ndarray, sin2: np.ndarray, *,
                            overwrite: bool = False) -> np.ndarray:
    """``M R(theta)`` per pixel for a plane-first Mueller image ``(..., 3, 3, H, W)`` and
    ``cos2``/``sin2`` broadcastable to ``(..., H, W)``: the model-frame matrix re-expressed in
    the rig's incident frame (columns 1 and 2 mix as in :func:`polrig.optics.bases.rotate_cols` with
    ``-theta``: ``c1' = c c1 - s c2``, ``c2' = c c2 + s c1``). Computed in ``m``'s own dtype on
    the plane-first layout (no float64 copy, no transposes: a full-sensor image is 4-20 x 10^7
    values). ``overwrite``: write the result into ``m`` (a writable array; the same numbers,
    without copying the unchanged column)."""
    m = np.asarray(m)
    c = np.expand_dims(np.asarray(cos2, m.dtype), -3)  # (..., 1, H, W): same for every row
    s = np.expand_dims(np.asarray(sin2, m.dtype), -3)
    out = m if overwrite else m.copy()
    c1, c2 = out[..., :, 1, :, :], out[..., :, 2, :, :]  # views: updated in place
    old1 = c1.copy()
    np.multiply(c1, c, out=c1)
    c1 -= s * c2
    np.multiply(c2, c, out=c2)
    c2 += s * old1
    return out


def probe_shape(shape: tuple[int, int]) -> tuple[int, int] | None:
    """Size ``(h, w)`` (multiples of :data:`SIZE_MULTIPLE`) of the reduced pass that estimates
    the illumination direction for the incident-frame refinement of a network input of
    ``shape`` (:meth:`SingleShotModel.run_rig_frame`), or None where the input is small enough
    to run twice (its short side below ``2 PROBE_SIDE``). The short side becomes about
    :data:`PROBE_SIDE` pixels, the scale the networks were trained at (64-128), so the probe
    costs a sixteenth of a pass at the full colour sensor's 612x512 grid."""
    h, w = (int(x) for x in shape)
    factor = min(h, w) // PROBE_SIDE
    if factor < 2:
        return None
    side = lambda n: max(SIZE_MULTIPLE, int(round(n / factor / SIZE_MULTIPLE)) * SIZE_MULTIPLE)  # noqa: E731
    return side(h), side(w)


def reduce_inputs(analyzer: np.ndarray, mask: np.ndarray, wo: np.ndarray,
                  shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched network inputs (``(B, C, 4, H, W)``, ``(B, 1, H, W)``, ``(B, 3, H, W)``) area-averaged
    to ``shape``: the mask kept where more than half a reduced pixel is object, the view
    directions renormalised. float32."""
    import cv2

    a = _resize(np.asarray(analyzer, np.float32), shape, cv2.INTER_AREA)
    m = (_resize(np.asarray(mask, np.float32), shape, cv2.INTER_AREA) > 0.5).astype(np.float32)
    v = _resize(np.asarray(wo, np.float32), shape, cv2.INTER_AREA)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    return a, m, v


def mean_direction(wi: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """Unit mean ``(B, 3)`` of direction images ``wi`` ``(B, 3, H, W)`` over ``mask``
    ``(B, 1, H, W)``, or None where a mean vanishes (no object, or directions cancelling)."""
    b = wi.shape[0]
    m = mask.reshape(b, 1, -1)
    w_mean = (wi.reshape(b, 3, -1) * m).sum(-1) / np.maximum(m.sum(-1), 1.0)
    norm = np.linalg.norm(w_mean, axis=-1, keepdims=True)
    return w_mean / norm if np.all(norm > 1e-6) else None


def _within(theta: np.ndarray, prev: np.ndarray, tolerance_deg: float) -> bool:
    """Whether every angle of ``theta`` (rad) is within ``tolerance_deg`` of ``prev`` (mod pi)."""
    return bool(np.all(np.abs(np.rad2deg(np.angle(np.exp(2j * (theta - prev))))) / 2 < tolerance_deg))


def stokes_s0(analyzer: np.ndarray) -> np.ndarray:
    """``S0 = (I0 + I45 + I90 + I135) / 2`` per colour, ``(C, H, W)``."""
    return 0.5 * np.sum(analyzer, axis=1)


def default_mask(analyzer: np.ndarray, fraction: float = MASK_FRACTION) -> np.ndarray:
    """Object mask ``(H, W)`` bool for a lit object on a dark background: finite pixels whose
    mean S0 exceeds ``fraction`` of a reference level, the 99th percentile of S0.

    Where fewer than 1 % of the pixels are lit (a small object), that percentile is background:
    the reference is then the 99th percentile of the pixels above the noise floor, and the mask
    keeps only pixels above the floor too. The floor is the 1st percentile of S0 plus
    :data:`MASK_NOISE_SIGMAS` noise sigmas, the noise estimated from horizontal neighbour
    differences (``1.4826 MAD / sqrt 2``; a dark background is flat, so its differences are
    noise). Where nothing is above the floor (a black frame, or a texture as rough as noise
    filling the frame), the 99th-percentile rule stands."""
    return mask_from_s0(np.mean(stokes_s0(analyzer), axis=0), fraction)


def mask_from_s0(s0: np.ndarray, fraction: float = MASK_FRACTION) -> np.ndarray:
    """:func:`default_mask`'s rule on the colours' mean ``S0`` image ``(H, W)`` (what
    :class:`polrig.models.device_path.DevicePath` copies back from the device for it)."""
    finite = np.isfinite(s0)
    if not finite.any():
        return np.zeros(s0.shape, bool)
    vals = s0[finite]
    diff = np.diff(s0, axis=-1)
    diff = np.abs(diff[np.isfinite(diff)])
    noise = 1.4826 * float(np.median(diff)) / np.sqrt(2.0) if diff.size else 0.0
    floor = tail_percentile(vals, 1.0) + MASK_NOISE_SIGMAS * noise
    ref = tail_percentile(vals, 99.0)
    if not ref > floor:  # fewer than 1 % of the pixels lit: the percentile is background
        lit = vals[vals > floor]
        if lit.size:
            return finite & (s0 > max(fraction * float(np.percentile(lit, 99.0)), floor))
    return finite & (s0 > fraction * ref) if ref > 0 else np.zeros(s0.shape, bool)


def default_scale(analyzer: np.ndarray, mask: np.ndarray) -> float:
    """Normalisation scale (DN per normalised unit) of a capture: the 99.5th percentile of the
    analyzer values (all colours and angles) inside the mask, at least 1 DN. This is the rule
    of the simulator's dataset writer (:data:`polrig.sim.dataset.SCALE_PERCENTILE`), so the networks
    see their training distribution."""
    vals = np.asarray(analyzer)[:, :, mask]
    if not np.isfinite(vals).all():
        vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return 1.0
    return max(tail_percentile(vals, SCALE_PERCENTILE), 1.0)


def _resize(img: np.ndarray, shape: tuple[int, int], interpolation: int) -> np.ndarray:
    import cv2

    flat = img.reshape((-1,) + img.shape[-2:])
    out = np.stack([cv2.resize(p, (shape[1], shape[0]), interpolation=interpolation) for p in flat])
    return out.reshape(img.shape[:-2] + shape)


class _Runner:
    """One session with fixed input sizes. With ``cuda_graph`` (a CUDA session created with
    ``enable_cuda_graph``) it runs through I/O binding at fixed device addresses, as onnxruntime's
    CUDA graphs need: the inputs are copied into device buffers bound once (``update_inplace``),
    the outputs come back from device buffers of the session's fixed output sizes. Where that
    run fails (onnxruntime refuses the capture), ``fallback(error)`` gives a plain session that
    runs from then on.

    A session captures one CUDA graph, at the addresses of the run that captured it, and replays
    it at those addresses whatever is bound later (the inputs and outputs must keep the capturing
    run's addresses: onnxruntime's CUDA execution provider documentation, "Using CUDA Graphs").
    So the runner remembers whose buffers the graph holds (:attr:`_owner`: ``"host"`` for
    :meth:`run`'s own buffers, the inputs' identity for :meth:`run_device`); a run with other
    buffers first takes a fresh session from ``reopen()`` (a new capture). On an H200
    (2026-11-28) a device-route frame after a host-route frame on the same model came back as
    zeros: the replay wrote into the host route's buffers."""

    def __init__(self, session, cuda_graph: bool = False, fallback=None, reopen=None, device: str = "cuda"):
        self.session = session
        self.cuda_graph = cuda_graph
        self._fallback = fallback
        self._reopen = reopen
        #: Where :meth:`run` keeps its bound buffers (``cuda``; ``cpu`` only in tests).
        self.device = device
        self._binding = None
        self._device_binding = None
        self._owner: object = None
        self.inputs = [i.name for i in session.get_inputs()]
        self.outputs = [o.name for o in session.get_outputs()]

    def _claim(self, owner: object) -> None:
        """Make the captured graph (if any) ``owner``'s: with another owner's graph captured,
        a fresh session, and neither owner's bindings kept."""
        if not self.cuda_graph or self._owner is None or self._owner == owner:
            self._owner = owner
            return
        self.session = self._reopen()
        self._binding, self._device_binding, self._owner = None, None, owner

    def run(self, feed: dict[str, np.ndarray], run_options=None) -> dict[str, np.ndarray]:
        if self.cuda_graph:
            try:
                self._claim("host")
                return self._run_bound(feed)
            except Exception as exc:  # onnxruntime's own types: the capture refused
                self.cuda_graph, self._binding = False, None
                self.session = self._fallback(exc)
        outs = self.session.run(None, {k: feed[k] for k in self.inputs}, run_options)
        return dict(zip(self.outputs, outs))

    def run_device(self, inputs: dict, device: str) -> dict:
        """One run on inputs already on the session's device (``OrtValue`` s by input name, as
        :class:`polrig.models.device_path.DevicePath` keeps them), the outputs left there in
        buffers kept per input shapes: the same addresses every frame of a size, as CUDA graphs
        replay them (allocated from the session's fixed output sizes there; by onnxruntime at a
        size's first run otherwise). A refused capture falls back as :meth:`run` does."""
        import onnxruntime as ort

        ident = tuple((k, id(v), tuple(v.shape())) for k, v in sorted(inputs.items()))
        self._claim(ident)
        held = self._device_binding
        if held is not None and held[0] == ident and held[3] is self.session:  # the same buffers
            self.session.run_with_iobinding(held[1])
            return held[2]
        shapes = tuple((k, s) for k, _, s in ident)
        outs = held[2] if held is not None and held[4] == shapes and held[3] is self.session else None
        for attempt in (0, 1):
            binding = self.session.io_binding()
            for name in self.inputs:
                binding.bind_ortvalue_input(name, inputs[name])
            if outs is None and self.cuda_graph:
                outs = {o.name: ort.OrtValue.ortvalue_from_shape_and_type(o.shape, np.float32, device, 0)
                        for o in self.session.get_outputs()}
            for name in self.outputs:
                if outs is None:
                    binding.bind_output(name, device, 0)
                else:
                    binding.bind_ortvalue_output(name, outs[name])
            try:
                self.session.run_with_iobinding(binding)
                break
            except Exception as exc:  # onnxruntime's own types: the capture refused
                if not self.cuda_graph or attempt:
                    raise
                self.cuda_graph, self._binding, outs = False, None, None
                self.session = self._fallback(exc)
        if outs is None:
            outs = dict(zip(self.outputs, binding.get_outputs()))
        # one binding kept (its inputs held alive with it): a size change frees the last one's
        self._device_binding = (ident, binding, outs, self.session, shapes, dict(inputs))
        return outs

    def _run_bound(self, feed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        import onnxruntime as ort

        if self._binding is None:
            binding = self.session.io_binding()
            self._in, self._out = {}, {}
            for name in self.inputs:
                self._in[name] = ort.OrtValue.ortvalue_from_numpy(feed[name], self.device, 0)
                binding.bind_ortvalue_input(name, self._in[name])
            for o in self.session.get_outputs():
                if not all(isinstance(n, int) for n in o.shape):
                    raise ValueError(f"output {o.name} has no fixed size {o.shape}")
                self._out[o.name] = ort.OrtValue.ortvalue_from_shape_and_type(o.shape, np.float32, self.device, 0)
                binding.bind_ortvalue_output(o.name, self._out[o.name])
            self._binding = binding
        else:
            for name, value in self._in.items():
                value.update_inplace(feed[name])
        self.session.run_with_iobinding(self._binding)
        return {k: v.numpy() for k, v in self._out.items()}


class SingleShotModel:
    """onnxruntime session of the shipped single-shot graph (and optionally the baseline).

    Sessions: :attr:`session` holds the graph with dynamic sizes (its outputs' names, the
    provider); made by :meth:`load` it is not optimised and never runs: runs take sessions
    from the ``opener``, created at a graph's first run. With :attr:`fixed_sizes` (the default on CUDA) runs go to sessions with the input
    sizes fixed (``SessionOptions.add_free_dimension_override_by_name``: every shape computation
    folded away), one per graph and input size, created at a size's first run and kept
    (:data:`MAX_SESSIONS`): on CUDA a session that alternates sizes rebuilds every convolution's
    cuDNN plan at each change (onnxruntime issue #23006), and only a fixed-size session can be
    captured as a CUDA graph. Without (the CPU's default, :meth:`load`) each graph has one
    dynamic-size session. A run that needs fewer outputs takes the graph holding only those
    (:data:`OUTPUT_GRAPHS`: the frame path's ``mueller``, ``wi``, ``alpha``; the light-direction
    probe's ``wi``, PIPNet alone), so in the route the probe's and the frame's sizes never share a
    session."""

    def __init__(self, session, meta: dict, weights_dir: pathlib.Path, uncertainty: UncertaintyModel | None = None,
                 uncertainty_problem: str = "", *, opener=None, graph: str = "single_shot.onnx",
                 session_options: dict[str, str] | None = None, fixed_sizes: bool = True):
        self.session = session
        #: ``opener(path, sizes, cuda_graph)`` -> a session of the graph at ``path`` with the input
        #: sizes ``(batch, height, width)`` fixed (``sizes`` None: dynamic sizes); None: every run
        #: on :attr:`session`.
        self._opener = opener
        #: Whether runs take sessions with their sizes fixed (else one dynamic session per graph).
        self.fixed_sizes = bool(fixed_sizes)
        self.graph = graph
        self._runners: dict[tuple, _Runner] = {}
        #: One line per option onnxruntime refused (printed to stderr once each as it happens).
        self.device_notes: list[str] = []
        self._session_options = dict(session_options or {})
        self._cuda_graph: bool | None = None  # whether the fixed-size CUDA sessions replay CUDA graphs
        self.meta = meta
        self.weights_dir = weights_dir
        #: :class:`polrig.models.uncertainty.UncertaintyModel` calibrated for this graph, or None.
        self.uncertainty = uncertainty
        #: Why :attr:`uncertainty` is None (no file, another graph's, unreadable); "" when it is set.
        self.uncertainty_problem = uncertainty_problem
        #: The execution provider that runs the graph (``CPUExecutionProvider``, ``CUDAExecutionProvider``).
        self.provider = devices.used_device(session.get_providers())
        self.input_names = [i.name for i in session.get_inputs()]
        self.output_names = [o.name for o in session.get_outputs()]
        self.colours = int(meta.get("colours", 3))
        import onnxruntime as ort

        #: Runs on more than :data:`SHRINK_ARENA_ABOVE` values per image hand the CPU arena's
        #: memory back when they end (onnxruntime's ``memory.enable_memory_arena_shrinkage``):
        #: the arena otherwise keeps its largest size (1.5 GB at the mono full sensor's
        #: 1224x1024x3) while the Mueller image is post-processed beside it. Measured at that
        #: size (busy machine): peak 2224 -> 1702 MB, about 0.3 s more system time per frame
        #: (the next pass faults its pages in again), so smaller images keep their arena.
        self._shrink = ort.RunOptions()
        self._shrink.add_run_config_entry("memory.enable_memory_arena_shrinkage", "cpu:0")

    @classmethod
    def load(cls, weights_dir: str | os.PathLike | None = None, *, graph: str = "single_shot.onnx",
             threads: int | None = None, spinning: bool = False, device: str = "auto",
             fixed_sizes: bool | None = None) -> "SingleShotModel":
        """Open ``graph`` in ``weights_dir`` (default: the shipped ``models/weights``).

        ``threads``: intra-op threads (default :func:`physical_cores`). ``spinning``: let idle
        worker threads busy-wait between operators (onnxruntime's default); off by default
        because on a shared or oversubscribed CPU spinning threads steal the cores the other
        threads need (see ``benchmarks/bench_single_shot.py`` for both settings). ``device``:
        ``auto`` (CUDA where this onnxruntime offers it, else the CPU), ``cpu`` or ``cuda``
        (:mod:`polrig.models.devices`; a forced ``cuda`` that cannot run raises
        :class:`polrig.models.devices.DeviceUnavailable`); :attr:`provider` is the one really used.
        ``fixed_sizes``: runs on sessions with their input sizes fixed (class docstring); off,
        one dynamic-size session per graph (full, frame, probe: in the route each sees one size).
        Default: on for CUDA, off for the CPU, where fixing the sizes brought no measurable speed
        but more memory (the mono full sensor's 1224x1024 frame: peak 1648 -> 1955 MB: onnxruntime
        folds the shape-dependent constants into image-sized tensors, 25 MB of them in the frame
        graph at that size, and plans the activations otherwise).

        Memory: onnxruntime's memory-pattern planning is off. With dynamic image sizes it plans
        one block for the whole graph at the first run of each new shape; without it the
        activations are allocated and freed as the graph runs (measured at 1224x1024x3, the mono
        full sensor: peak 1.5 GB instead of 2.2 GB, first run no slower;
        ``benchmarks/results/single_shot_speed.md``). The CPU arena stays on (off, runs were
        slower and the peak higher)."""
        import onnxruntime as ort

        providers = devices.choose_providers(device, ort.get_available_providers())
        if devices.CUDA in providers:
            devices.load_cuda_libraries(ort)
        wd = pathlib.Path(weights_dir) if weights_dir is not None else WEIGHTS_DIR
        path = wd / graph
        if not path.is_file():
            raise FileNotFoundError(f"model graph {path} not found")
        meta_path = wd / "model.json"
        try:
            meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise FormatError(f"{meta_path}: not a readable model description ({exc})") from None
        if not isinstance(meta, dict):
            raise FormatError(f"{meta_path}: not a model description (a JSON object expected)")
        n_threads = threads or physical_cores()
        if fixed_sizes is None:
            fixed_sizes = devices.CUDA in providers

        def options(sizes: tuple[int, int, int] | None = None, optimise: bool = True):
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = n_threads
            opts.inter_op_num_threads = 1
            opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            opts.graph_optimization_level = (ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise
                                             else ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
            opts.enable_mem_pattern = False
            opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
            for name, n in zip(("batch", "height", "width"), sizes or ()):
                opts.add_free_dimension_override_by_name(name, int(n))
            return opts

        def opener(p: pathlib.Path, sizes: tuple[int, int, int] | None, cuda_graph: bool = False):
            return ort.InferenceSession(str(p), options(sizes),
                                        providers=devices.session_providers(providers, cuda_graph))

        try:
            # this session only names the graph's inputs, outputs and provider (it never runs:
            # runs take the opener's optimised sessions, made at the first run of each graph):
            # not optimised, so a one-shot run optimises only the graphs it runs (the route's
            # frame and probe graphs, not the full one: 0.3-0.5 s of a cold `polrig infer`)
            sess = ort.InferenceSession(str(path), options(optimise=False),
                                        providers=devices.session_providers(providers))
        except Exception as exc:  # onnxruntime's own exception types: a damaged or foreign file
            reason = (str(exc) or type(exc).__name__).strip().splitlines()[0][:200]
            raise FormatError(f"{path}: not a loadable ONNX graph ({reason})") from exc
        devices.check_session(device, providers, sess.get_providers())
        return cls(sess, meta, wd, *calibration_for_graph(wd, graph), opener=opener, fixed_sizes=fixed_sizes,
                   graph=graph, session_options={"intra_op_num_threads": str(n_threads),
                                                 "fixed_sizes": "1" if fixed_sizes else "0"})

    def run_normalised(self, analyzer: np.ndarray, mask: np.ndarray, s_in: np.ndarray, wo: np.ndarray,
                       stage_zero_axis: np.ndarray, *, release_arena: bool | None = None,
                       outputs: str = "all") -> dict[str, np.ndarray]:
        """One graph call on batched, normalised, padded inputs (names as :mod:`polrig.models.export`).
        ``release_arena``: hand the CPU arena's memory back when the run ends (None: for runs on
        more than :data:`SHRINK_ARENA_ABOVE` colour-pixels). ``outputs``: ``all`` (the graph's),
        ``frame`` or ``probe`` (at least the outputs of :data:`OUTPUT_GRAPHS`' graph; where the
        weights folder has no such graph, the full one's)."""
        feed = {"analyzer": analyzer, "mask": mask, "s_in": s_in, "wo": wo, "stage_zero_axis": stage_zero_axis}
        feed = {k: np.ascontiguousarray(feed[k], dtype=np.float32) for k in self.input_names}
        if release_arena is None:
            release_arena = int(np.prod(np.shape(analyzer)[1:])) // 4 > SHRINK_ARENA_ABOVE  # colours x H x W
        run_options = self._shrink if release_arena else None
        if self._opener is None:
            return dict(zip(self.output_names, self.session.run(None, feed, run_options)))
        b, _, _, h, w = feed["analyzer"].shape
        return self._runner(outputs, (int(b), int(h), int(w)) if self.fixed_sizes else None).run(feed, run_options)

    def _graph_path(self, outputs: str) -> pathlib.Path:
        """The graph a run of ``outputs`` takes: the smaller one where it was exported with this
        graph (``model.json``'s ``graph_sha256`` names both files as they are), else this one."""
        if outputs not in ("all", *OUTPUT_GRAPHS):
            raise ValueError(f"outputs must be all, {', '.join(OUTPUT_GRAPHS)}, got {outputs!r}")
        name = OUTPUT_GRAPHS.get(outputs) if self.graph == "single_shot.onnx" else None
        if name is not None and name in self._companions():
            return self.weights_dir / name
        return self.weights_dir / self.graph

    def _companions(self) -> set[str]:
        """The smaller graphs in :attr:`weights_dir` exported together with :attr:`graph` (checked
        once, by their SHA-256 against ``model.json``; a graph replaced alone has none)."""
        if getattr(self, "_companion_names", None) is None:
            from polrig.models.uncertainty import graph_sha256

            want = self.meta.get("graph_sha256") or {}
            names = set()
            try:
                if want.get(self.graph) == graph_sha256(self.weights_dir / self.graph):
                    names = {n for n in OUTPUT_GRAPHS.values()
                             if (self.weights_dir / n).is_file() and want.get(n) == graph_sha256(self.weights_dir / n)}
            except OSError:
                names = set()
            self._companion_names = names
        return self._companion_names

    def _note(self, line: str) -> None:
        import sys

        if line not in self.device_notes:
            self.device_notes.append(line)
            print(f"polrig: {devices.short_name(self.provider)}: {line}", file=sys.stderr)

    def _runner(self, outputs: str, sizes: tuple[int, int, int] | None, route: str = "host") -> _Runner:
        """The session of ``outputs``' graph at input ``sizes`` (None: its dynamic-size one) for
        ``route`` (``host``: numpy in and out; ``device``: :class:`polrig.models.device_path.DevicePath`'s
        buffers; each route its own session, so that each keeps its own CUDA graph), created
        at the first run of that size, then kept: the least recently used beyond
        :data:`MAX_SESSIONS` goes."""
        path = self._graph_path(outputs)
        key = (path.name, sizes, route)
        runner = self._runners.pop(key, None)
        if runner is None:
            runner = self._new_runner(path, sizes)
        self._runners[key] = runner
        while len(self._runners) > MAX_SESSIONS:
            self._runners.pop(next(iter(self._runners)))
        return runner

    def _new_runner(self, path: pathlib.Path, sizes: tuple[int, int, int] | None) -> _Runner:
        if self.provider != devices.CUDA or self._cuda_graph is False or sizes is None:
            return _Runner(self._opener(path, sizes))
        requested = dict(devices.CUDA_GRAPH_OPTION)
        try:
            sess = self._opener(path, sizes, cuda_graph=True)
        except Exception as exc:  # onnxruntime refused the capture option for this graph
            self._refuse_cuda_graph(requested, exc)
            return _Runner(self._opener(path, sizes))
        reported = sess.get_provider_options().get(devices.CUDA) if devices.CUDA in sess.get_providers() else None
        options, notes = devices.accepted_options(requested, reported)
        if notes or options.get("enable_cuda_graph") != "1":
            for line in notes:
                self._note(line)
            self._cuda_graph = False
            return _Runner(self._opener(path, sizes))

        def fallback(exc: Exception):
            self._refuse_cuda_graph(requested, exc)
            return self._opener(path, sizes)

        self._cuda_graph = True
        return _Runner(sess, cuda_graph=True, fallback=fallback,
                       reopen=lambda: self._opener(path, sizes, cuda_graph=True))

    def _refuse_cuda_graph(self, requested: dict[str, str], exc: Exception) -> None:
        """CUDA graphs refused (session creation or the first run): noted, and not asked again."""
        self._cuda_graph = False
        for line in devices.accepted_options(requested, None, error=str(exc) or type(exc).__name__)[1]:
            self._note(line)

    @property
    def provider_options(self) -> dict[str, str]:
        """The options the provider runs with, as recorded in a result's header: on CUDA those of
        :data:`polrig.models.devices.CUDA_OPTIONS` as the session reports them and
        ``enable_cuda_graph`` (``1`` where the fixed-size sessions replay CUDA graphs, ``0`` where
        onnxruntime refused them or they were not asked for; absent before a fixed-size run); the
        session settings that decide the speed (threads, fixed sizes)."""
        out = dict(self._session_options)
        if self.provider == devices.CUDA:
            reported = self.session.get_provider_options().get(devices.CUDA, {})
            out.update(devices.accepted_options(devices.CUDA_OPTIONS, reported)[0])
            if self._cuda_graph is not None:
                out["enable_cuda_graph"] = "1" if self._cuda_graph else "0"
        return out

    @property
    def model_axis(self) -> np.ndarray:
        """The stage zero axis (camera frame) the networks were trained with (``model.json``)."""
        return np.asarray(self.meta.get("stage_zero_axis_camera", DEFAULT_STAGE_ZERO_AXIS), np.float64)

    def run_rig_frame(self, analyzer: np.ndarray, mask: np.ndarray, s_in: np.ndarray, wo: np.ndarray,
                      stage_zero_axis: np.ndarray, *, wi_guess: np.ndarray | None = None,
                      tolerance_deg: float = 3.0, rotate_with: np.ndarray | None = None,
                      mirror_average: bool = False, probe: bool = True,
                      release_arena: bool | None = None, outputs: str = "all") -> dict[str, np.ndarray]:
        """:meth:`run_normalised` for a rig whose stage zero axis ``(B, 3)`` (camera frame) may
        differ from the training one: the graph runs in the training frame and ``mueller``
        and ``mueller_init`` come back in the rig's frame (module docstring).

        ``wi_guess`` ``(B, 3)``: illumination direction (surface -> light) for the input
        rotation (default: the optical axis, ``(0, 0, -1)``); it is refined from the network's
        mean ``wi`` over the mask until the input angle moves by less than ``tolerance_deg``
        (at most one more pass). ``rotate_with`` ``(B, 3, H, W)``: per-pixel light directions
        for the output rotation instead of the network's ``wi`` (used to run the direct
        baseline, which predicts none). The result also holds ``incident_rotation_deg`` (B,),
        the input rotation used.

        ``mirror_average``: run the capture and its left-right mirror image and average the two
        answers mapped back (:mod:`polrig.models.mirror`; twice the network time); the result then
        also holds ``mueller_disagreement``, half the two answers' absolute difference.

        ``probe`` (inputs whose short side is at least ``2 PROBE_SIDE``, :func:`probe_shape`):
        the light direction for the refinement comes from one pass on the inputs area-reduced to
        a short side of about :data:`PROBE_SIDE`, then the full-size graph runs once at the
        refined angle: at the full colour sensor's 612x512 grid 1.06 passes instead of 2 (a rig on
        the training axis needs no refinement: one full-size pass). ``probe=False``: the full-size
        graph runs for the refinement too (the route before; ``polrig.models.evaluate_speed_modes``
        compares the two). ``release_arena``, ``outputs``: as :meth:`run_normalised`, for the
        full-size passes (the probe's needs ``wi`` alone)."""
        if mirror_average:
            plain = self.run_rig_frame(analyzer, mask, s_in, wo, stage_zero_axis, wi_guess=wi_guess,
                                       tolerance_deg=tolerance_deg, rotate_with=rotate_with, probe=probe,
                                       release_arena=release_arena, outputs=outputs)
            seen = self.run_rig_frame(mirror.analyzer(analyzer), mirror.image(mask), mirror.stokes(s_in),
                                      mirror.vector_image(wo), mirror.vectors(stage_zero_axis),
                                      wi_guess=None if wi_guess is None else mirror.vectors(wi_guess),
                                      tolerance_deg=tolerance_deg, probe=probe, release_arena=release_arena,
                                      outputs=outputs,
                                      rotate_with=None if rotate_with is None else mirror.vector_image(rotate_with))
            back = mirror.outputs(seen)
            out = mirror.average(plain, back)
            out["mueller_disagreement"] = (0.5 * np.abs(plain["mueller"] - back["mueller"])).astype(np.float32)
            return out
        b = analyzer.shape[0]
        axis = np.broadcast_to(np.asarray(stage_zero_axis, np.float64).reshape(-1, 3), (b, 3))
        model_axis = np.broadcast_to(self.model_axis, (b, 3)).astype(np.float32)
        wi = (np.broadcast_to(np.asarray(wi_guess, np.float64).reshape(-1, 3), (b, 3)) if wi_guess is not None
              else np.broadcast_to([0.0, 0.0, -1.0], (b, 3)))
        prev = None
        # (a rig on the training axis needs no refinement: its angle is 0 whatever the light)
        with np.errstate(invalid="ignore", divide="ignore"):
            same_axis = np.allclose(axis / np.linalg.norm(axis, axis=-1, keepdims=True),
                                    self.model_axis / np.linalg.norm(self.model_axis), atol=1e-9)
        small = (probe_shape(analyzer.shape[-2:]) if probe and not same_axis and rotate_with is None
                 and "wi" in self.output_names else None)
        if small is not None:
            # The refinement needs only the image-wide mean ``wi``: it comes from a pass on the
            # area-reduced inputs (probe_shape), and the full-size graph runs once, at the
            # refined angle, instead of twice (module docstring, "Incident frame").
            # One reduced pass: a second moved the 512x512 unseen set's matrix PSNR by 0.006 dB.
            a_s, m_s, wo_s = reduce_inputs(analyzer, mask, wo, small)
            c2, s2 = incident_rotation(wi, axis, self.model_axis)
            reduced = self.run_normalised(a_s, m_s, rotate_stokes(s_in, c2, s2).astype(np.float32), wo_s, model_axis,
                                          outputs="probe")
            w_mean = mean_direction(reduced["wi"], m_s)
            del reduced, a_s, m_s, wo_s
            if w_mean is not None:
                wi = w_mean
        for _ in range(1 if small is not None else 2):
            c2, s2 = incident_rotation(wi, axis, self.model_axis)
            theta = 0.5 * np.arctan2(s2, c2)
            if prev is not None and _within(theta, prev, tolerance_deg):
                break
            out = None  # the previous pass's outputs go before the next pass allocates (peak memory)
            out = self.run_normalised(analyzer, mask, rotate_stokes(s_in, c2, s2).astype(np.float32), wo, model_axis,
                                      release_arena=release_arena, outputs=outputs)
            prev = theta
            if rotate_with is not None or "wi" not in out:
                break
            w_mean = mean_direction(out["wi"], mask)
            if w_mean is None:
                break
            wi = w_mean
        w_pix = rotate_with if rotate_with is not None else out["wi"]  # (B, 3, H, W)
        cp, sp = incident_rotation(w_pix, axis, self.model_axis, vector_axis=1)
        for key in ("mueller", "mueller_init"):
            if key in out:
                ndim = out[key].ndim  # (B, C, 3, 3, H, W)
                shape = (b,) + (1,) * (ndim - 5) + cp.shape[1:]
                out[key] = rotate_incident_columns(out[key], cp.reshape(shape), sp.reshape(shape), overwrite=True)
        out["incident_rotation_deg"] = np.rad2deg(prev).astype(np.float32)
        return out

    def reconstruct(self, analyzer: np.ndarray, s_in, mask: np.ndarray | None = None, scale: float | None = None,
                    *, stage_zero_axis=None, intrinsics=None,
                    max_pixels: int = 1_500_000, with_sigma: bool = False,
                    mirror_average: bool = False, probe: bool = True,
                    release_arena: bool | None = None, outputs: str = "all") -> tuple[np.ndarray, dict]:
        """Mueller image ``(C, 3, 3, H, W)`` float32 in DN per unit incident S0 from analyzer
        images ``(C, 4, H, W)`` in DN (black level removed) under the normalised incident
        state ``s_in`` ``(3,)`` (incident frame, ``docs/conventions.md``).

        Non-finite analyzer values (saturated or bad samples) are replaced by the largest
        finite value of their colour; pixels with no finite value are background.
        ``mask`` ``(H, W)``: object pixels (default :func:`default_mask`); ``scale``: DN per
        normalised unit (default :func:`default_scale`); ``stage_zero_axis``: the polarizer
        stage zero axis in the camera frame (default: the training rig's, from ``model.json``);
        ``intrinsics``: ``(fx, fy, cx, cy)`` of the
        analyzer image (default: the simulated rig's camera). Background pixels are 0.
        ``aux`` holds ``mueller_init`` (PIPNet-pBRDF, DN), ``normal``, ``kd``, ``wi``,
        ``alpha``, ``mask``, ``scale``, ``light_spread`` (the network's light spread over the object,
        rad, :func:`polrig.models.uncertainty.light_spread`; None without ``wi``), ``timings_s`` and, with ``with_sigma`` where the graph has
        a calibrated uncertainty (:mod:`polrig.models.uncertainty`; about 11 ms at 128x128, a third of
        the reconstruction, so off by default), ``sigma`` ``(C, 3, 3, H, W)`` DN: the standard
        deviation of each element (calibrated on simulated held-out sets: about 95 % of the
        errors within 2 sigma, ``models/MODEL_CARD.md``; with ``mirror_average`` it grows with
        the two passes' disagreement) and, where the calibration records its misfit range,
        ``beyond_calibration`` ``(C, H, W)`` bool: object pixels outside it, whose sigma may be
        too small (:meth:`polrig.models.uncertainty.UncertaintyModel.beyond_calibration`).
        ``mirror_average``: average the answers for the capture and its mirror image
        (:mod:`polrig.models.mirror`): a few per cent lower error for twice the network time.
        ``probe``, ``release_arena``, ``outputs``: as :meth:`run_rig_frame` (``frame``: ``aux``
        without ``mueller_init``, ``normal`` and ``kd``, from the graph without them).
        ``aux["provider_options"]``: :attr:`provider_options` after the run.
        """
        t0 = time.perf_counter()
        a = np.asarray(analyzer, dtype=np.float32)
        if a.ndim != 4 or a.shape[1] != 4:
            raise FormatError(f"analyzer images must be (C, 4, H, W), got shape {a.shape}")
        mono = a.shape[0] == 1 and self.colours > 1
        if mono:
            # A mono sensor (e.g. IMX250MZR) integrates one broad band: to the colour network its
            # frame is a grey scene under white light (every colour channel the same). The pBRDF
            # is colour-decoupled (colour only through kd), so the geometry and polarization the
            # network infers do not depend on this; its colour outputs are averaged back to one.
            a = np.repeat(a, self.colours, axis=0)
        elif a.shape[0] != self.colours:
            raise FormatError(f"model expects {self.colours} colour channel(s) (or 1, a mono sensor), "
                              f"analyzer has {a.shape[0]}")
        s = np.asarray(s_in, dtype=np.float32).reshape(-1)
        if s.shape != (3,) or not np.all(np.isfinite(s)):
            raise ValueError(f"s_in must be 3 finite numbers (S0, S1, S2), got {s_in!r}")
        h, w = a.shape[-2:]
        bad = ~np.isfinite(a)
        some_finite = ~np.all(bad, axis=(0, 1))
        if bad.any():
            # Non-finite samples (saturated or defective: polrig.app.processing passes NaN for them)
            # take the largest finite value of their colour: a saturated sample is at least that
            # bright, and the training data hold clipped highlights. Pixels with no finite
            # sample at all leave the mask.
            with np.errstate(invalid="ignore"):
                top = np.max(np.where(bad, -np.inf, a), axis=(1, 2, 3), keepdims=True)
            a = np.where(bad, np.where(np.isfinite(top), top, 0.0), a).astype(np.float32)
        m = default_mask(a) if mask is None else np.asarray(mask).astype(bool)
        if m.shape != (h, w):
            raise FormatError(f"mask must be ({h}, {w}), got {m.shape}")
        m = m & some_finite
        sc = default_scale(a, m) if scale is None else float(scale)
        if not (np.isfinite(sc) and sc > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        if scale is not None and not default_scale(a, m) / sc <= MAX_INPUT_LEVEL:
            raise ValueError(f"scale {sc:g} DN per unit puts the capture's bright pixels at "
                             f"{default_scale(a, m) / sc:.3g} normalised units, the networks were trained at 1; "
                             f"leave the scale unset to take it from the image")
        if stage_zero_axis is None:
            stage_zero_axis = self.meta.get("stage_zero_axis_camera", DEFAULT_STAGE_ZERO_AXIS)
        wo = view_directions((h, w), intrinsics)
        # Size: resize down if needed, then pad to the network's size multiple.
        factor = min(1.0, float(np.sqrt(max_pixels / float(h * w))))
        hr, wr = (max(SIZE_MULTIPLE, int(h * factor)), max(SIZE_MULTIPLE, int(w * factor))) if factor < 1 else (h, w)
        an, mk, won = a / sc, m.astype(np.float32), wo
        if (hr, wr) != (h, w):
            import cv2

            an = _resize(an, (hr, wr), cv2.INTER_AREA)
            mk = (_resize(mk, (hr, wr), cv2.INTER_AREA) > 0.5).astype(np.float32)
            won = view_directions((hr, wr), None if intrinsics is None else
                                  tuple(np.asarray(intrinsics, float) * [wr / w, hr / h, wr / w, hr / h]))
        ph, pw = (-hr) % SIZE_MULTIPLE, (-wr) % SIZE_MULTIPLE
        pad = lambda x: np.pad(x, [(0, 0)] * (x.ndim - 2) + [(0, ph), (0, pw)], mode="edge")  # noqa: E731
        an_p = pad(an)
        mk_p = np.pad(mk, [(0, ph), (0, pw)])
        wo_p = pad(won)
        t1 = time.perf_counter()
        out = self.run_rig_frame(an_p[None], mk_p[None, None], s[None], wo_p[None],
                                 np.asarray(stage_zero_axis, np.float64).reshape(1, 3),
                                 mirror_average=mirror_average, probe=probe, release_arena=release_arena,
                                 outputs=outputs)
        rotation_deg = float(out.pop("incident_rotation_deg")[0])
        # the network's light spread over the object, on its own grid (the sigma's light factor)
        spread = light_spread(out["wi"][0], mk_p > 0) if "wi" in out else None
        t2 = time.perf_counter()
        crop = lambda x: x[0, ..., :hr, :wr]  # noqa: E731
        res = {k: crop(v) for k, v in out.items() if k != "alpha"}
        if (hr, wr) != (h, w):
            import cv2

            res = {k: _resize(v, (h, w), cv2.INTER_LINEAR) for k, v in res.items()}
        if mono:
            res = {k: v.mean(axis=0, keepdims=True) if k in COLOUR_OUTPUTS else v for k, v in res.items()}
        to_dn = (sc * m).astype(np.float32)  # (H, W): normalised units -> DN, background 0
        in_dn = lambda x: np.multiply(x, to_dn, dtype=np.float32)  # noqa: E731  (one pass, a new array)
        mueller = in_dn(res.pop("mueller"))
        disagreement = res.pop("mueller_disagreement", None)
        if disagreement is not None:
            disagreement = in_dn(disagreement)
        aux = {k: in_dn(v) if k == "mueller_init" else v.astype(np.float32) for k, v in res.items()}
        if with_sigma and self.uncertainty is not None:
            # the capture's own Stokes images, in DN like ``mueller`` (a mono frame is repeated: one copy)
            stokes = stokes_from_analyzers(a[:mueller.shape[0]])
            aux["sigma"] = self.uncertainty.sigma(mueller, s, m, stokes, disagreement, spread)
            beyond = self.uncertainty.beyond_calibration(mueller, s, m, stokes)
            if beyond is not None:
                aux["beyond_calibration"] = beyond
        aux.update({"alpha": float(out["alpha"][0]) if "alpha" in out else None, "mask": m, "scale": sc,
                    "light_spread": spread, "incident_rotation_deg": rotation_deg, "provider": self.provider,
                    "provider_options": self.provider_options,
                    "timings_s": {"prepare": t1 - t0, "network": t2 - t1, "finish": time.perf_counter() - t2}})
        return mueller, aux
