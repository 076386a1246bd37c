"""The single-shot frame kept on the execution provider's device (issue 31, items 3 and 4).

:class:`DevicePath` runs :meth:`polrig.app.single_shot.SingleShot.frame`'s steps as the ONNX
graphs of :mod:`polrig.models.device_graphs` and the networks' sessions
(:class:`polrig.models.runtime.SingleShotModel`), chained by I/O binding: every intermediate is
an ``OrtValue`` on the session's device, kept per sensor size and reused frame after frame
(persistent buffers at fixed addresses, as the networks' CUDA graphs need). On the CPU provider
the same code runs with the buffers in host memory; that is how the tests check it against the
numpy route.

Per frame, what crosses between host and device:

* up: the raw mosaic (``uint16``, once; on CUDA from a pinned host buffer), a few scalars (black level, saturation, the incident
  state, the scale, the mask's threshold);
* down for the normalisation statistics: order statistics found on the device by ``TopK``,
  from which the host interpolates the percentiles exactly as
  :func:`polrig.solve.quantiles.tail_percentile` does: for the object mask
  (:func:`polrig.models.runtime.mask_from_s0`: the 1st and 99th percentile of ``S0`` and the
  median of its neighbour differences) six numbers and the mask's pixel count, then the mask's
  threshold goes up and is applied there; for the scale the ``k`` largest analyzer values in
  the mask (``k`` about 0.5 % of them, 76 kB at the full colour sensor). Where the mask rule
  needs the whole image (fewer than 65536 pixels, a non-finite ``S0``, fewer than 1 % of the
  pixels lit) the ``S0`` plane ``(h, w)`` comes down and the rule runs on the host (26 ms at
  612x512 on this 2-core machine, busy);
* down for the light-direction probe and the refinement: three numbers each (the masked mean
  ``wi``);
* down at the end, only what is used: for a result (``polrig infer``, the GUI's displays) the
  Mueller image, the object mask, the reason planes (``clipped``), the ``S0`` signal-to-noise
  ``(C, h, w)`` for the ``dark`` bits and the measured Stokes images (the result's, which the
  displays and the calibrated sigma read; :meth:`frame` ``with_stokes``), or for the live view
  only a display-size grid of the nine elements (``preview_size``).

What it does not cover (:meth:`supports` says why, in one line; the route then takes the
numpy steps): network binning, the mirror average, a ``bilinear`` or ``newton`` demosaic as the
networks' input, the ``newton`` detail at full resolution, a network grid above
``max_pixels``.
"""

from __future__ import annotations

import math
import pathlib
import threading
import time

import numpy as np

from polrig.models import devices
from polrig.models.device_graphs import GRAPH_DIR, area_matrix
from polrig.models.runtime import (
    DEFAULT_STAGE_ZERO_AXIS,
    MASK_FRACTION,
    MASK_NOISE_SIGMAS,
    MAX_INPUT_LEVEL,
    SCALE_PERCENTILE,
    incident_rotation,
    mask_from_s0,
    probe_shape,
    rotate_stokes,
    view_directions,
)
from polrig.models.size import SIZE_MULTIPLE
from polrig.models.uncertainty import spread_of_mean
from polrig.solve.quantiles import MIN_SIZE, tail_percentile

#: Network grids above this many pixels take the numpy route (its resize to ``max_pixels``).
MAX_PIXELS = 1_500_000
#: The live view runs the light-direction probe every this many frames and reuses its answer in
#: between (:meth:`DevicePath.frame` ``probe_every``): the light moves slowly against 20 fps.
LIVE_PROBE_EVERY = 8


def superpixel_cells(layout) -> np.ndarray:
    """``(K, ph, pw)`` float32 class weights of a mosaic layout: ``1 / n`` at the ``n`` cell
    positions of class ``(colour, angle)`` (``K = 4 C``, colour-major), the superpixel mean."""
    from polrig.sensor.demosaic import class_positions

    ph, pw = layout.period
    out = np.zeros((layout.n_colours * 4, ph, pw), np.float32)
    for (c, k), pos in class_positions(layout).items():
        for r, q in pos:
            out[4 * c + k, r, q] = np.float32(1.0 / len(pos)) if len(pos) > 1 else 1.0
    return out


def bilinear_inputs(layout) -> dict[str, np.ndarray]:
    """The ``bilinear`` graph's layout inputs: the class cells (1 at a class's positions) and
    the separable tent of half-width the period (:mod:`polrig.sensor.demosaic`)."""
    from polrig.sensor.demosaic import _tent

    ph, pw = layout.period
    return {"cells": (superpixel_cells(layout) > 0).astype(np.float32),
            "tent_y": _tent(ph).reshape(1, 1, -1, 1), "tent_x": _tent(pw).reshape(1, 1, 1, -1)}


def _positions(n: int, q: float) -> tuple[int, int, float]:
    """The two order statistics (0-based ranks) and the fraction that the ``q`` th percentile of
    ``n`` values interpolates (numpy's ``linear`` method, as :func:`polrig.solve.quantiles.tail_percentile`)."""
    pos = q / 100.0 * (n - 1)
    lo = int(math.floor(pos))
    return lo, min(lo + 1, n - 1), pos - lo


def _lerp(a: float, b: float, frac: float) -> float:
    """:func:`polrig.solve.quantiles.tail_percentile`'s interpolation (numpy's, in float64)."""
    a, b = float(a), float(b)
    return b - (b - a) * (1.0 - frac) if frac >= 0.5 else a + (b - a) * frac


def scale_from_tail(tail: np.ndarray, n: int, q: float = SCALE_PERCENTILE) -> float:
    """:func:`polrig.models.runtime.default_scale` from the ``k`` largest of ``n`` values in
    descending order (``k >= n - floor(q (n - 1) / 100)``; all ``n`` where ``n`` is below
    :data:`polrig.solve.quantiles.MIN_SIZE`, whose percentile numpy interpolates in float32):
    the same two order statistics and the same interpolation."""
    if n == 0:
        return 1.0
    if n < MIN_SIZE:
        return max(tail_percentile(np.asarray(tail[:n]), q), 1.0)
    lo, hi, frac = _positions(n, q)
    return max(_lerp(tail[n - 1 - lo], tail[n - 1 - hi], frac), 1.0)


def tail_count(n: int, q: float = SCALE_PERCENTILE) -> int:
    """How many of the largest values :func:`scale_from_tail` needs of ``n``."""
    return n if n < MIN_SIZE else n - int(math.floor(q / 100.0 * (n - 1)))


#: Graphs whose output size depends on an input's value (``k``): their outputs are never kept.
DATA_SHAPED = frozenset({"scale_tail"})


def _host(value) -> np.ndarray:
    """A host input as a graph takes it: floats as float32 (the graphs' one float type)."""
    a = np.asarray(value)
    return a.astype(np.float32) if a.dtype == np.float64 else a


class DevicePath:
    """The frame route on ``model``'s provider (module docstring). ``graphs``: the folder of
    :mod:`polrig.models.device_graphs`' files."""

    def __init__(self, model, graphs: pathlib.Path = GRAPH_DIR):
        import onnxruntime as ort

        self.model = model
        self.device = "cuda" if model.provider == devices.CUDA else "cpu"
        self._ort = ort
        self._graphs = pathlib.Path(graphs)
        self._sessions: dict[str, object] = {}
        self._buffers: dict[tuple, object] = {}
        self._bindings: dict[str, tuple] = {}
        self._lock = threading.Lock()
        #: Whether the raw mosaic goes up from pinned memory (CUDA; None: not tried yet). A refusal
        #: is one of the model's ``device_notes`` (printed once, recorded in the result's header).
        self._pinned: bool | None = None
        self._frames = 0
        self._probe_wi: np.ndarray | None = None
        #: The live view's probe schedule (:meth:`polrig.app.single_shot.SingleShot.live`).
        self.probe_every = LIVE_PROBE_EVERY

    def restart_live(self) -> None:
        """Forget the probe's last direction: the next frame probes (a new live stream)."""
        self._frames, self._probe_wi = 0, None

    # -- capability ---------------------------------------------------------------------------
    def supports(self, options, network_shape: tuple[int, int]) -> str:
        """Why this path cannot take a frame with ``options`` on a network grid of
        ``network_shape`` (one line), or ``""`` where it can."""
        if options.network_binning > 1:
            return "network binning runs on the host"
        if options.mirror_average:
            return "the mirror average runs on the host"
        if options.geometry:
            return "the geometry planes (the full graph's outputs) run on the host"
        if options.network_demosaic != "superpixel":
            return f"a {options.network_demosaic} network input runs on the host"
        if options.resolution == "full" and options.demosaic != "bilinear":
            return f"the {options.demosaic} detail runs on the host"
        if network_shape[0] * network_shape[1] > MAX_PIXELS:
            return "a network grid above 1.5 Mpx is resized on the host"
        if self.model._opener is None:
            return "the model has no per-graph sessions"
        return ""

    # -- plumbing -----------------------------------------------------------------------------
    def session(self, stem: str):
        """The session of graph ``stem`` on the networks' provider (created once)."""
        sess = self._sessions.get(stem)
        if sess is None:
            ort = self._ort
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = int(self.model._session_options.get("intra_op_num_threads", 0) or 0)
            opts.inter_op_num_threads = 1
            opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
            providers = [devices.CUDA, "CPUExecutionProvider"] if self.device == "cuda" else ["CPUExecutionProvider"]
            if self.device == "cuda":
                providers = devices.session_providers(providers)
            sess = ort.InferenceSession(str(self._graphs / f"{stem}.onnx"), opts, providers=providers)
            self._sessions[stem] = sess
        return sess

    def upload(self, name: str, array: np.ndarray):
        """``array`` in the persistent device buffer ``name`` (made at its first shape and dtype,
        refilled in place after; int64 arrays in host memory)."""
        a = np.ascontiguousarray(array)
        key = (name, a.shape, a.dtype.str)
        buf = self._buffers.get(key)
        if buf is None:
            for old in [k for k in self._buffers if k[0] == name]:
                del self._buffers[old]
            # int64 inputs are sizes, pads and counts, which the CUDA kernels read on the host
            # (onnxruntime would otherwise copy them back before each use)
            where = "cpu" if a.dtype == np.int64 else self.device
            buf = self._ort.OrtValue.ortvalue_from_numpy(a.copy(), where, 0)
            self._buffers[key] = buf
        else:
            buf.update_inplace(a)
        return buf

    def _upload_raw(self, raw: np.ndarray):
        """The raw mosaic on the device. On CUDA it goes through a buffer in pinned (page-locked)
        host memory, from which the copy to the device is one DMA transfer (``to_device``);
        where onnxruntime offers no pinned memory the mosaic is copied from pageable memory, and
        a note says so. On the CPU it is the host buffer."""
        if self.device != "cuda" or self._pinned is False:
            return self.upload("raw", raw)
        key = ("raw_pinned", raw.shape, raw.dtype.str)
        buf = self._buffers.get(key)
        try:
            if buf is None:
                for old in [k for k in self._buffers if k[0] == "raw_pinned"]:
                    del self._buffers[old]
                buf = self._ort.OrtValue.ortvalue_from_shape_and_type(raw.shape, raw.dtype, "cuda_pinned", 0)
                self._buffers[key] = buf
            buf.update_inplace(raw)
            out = self.run("to_device", {"raw_host": buf})["raw"]
            self._pinned = True
            return out
        except Exception as exc:  # onnxruntime's own types: no pinned allocator here
            self._pinned = False
            why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:120]
            self.model._note(f"pinned host memory refused ({why}); the raw mosaic goes up from pageable memory")
            return self.upload("raw", raw)

    def run(self, stem: str, inputs: dict) -> dict:
        """Graph ``stem`` on ``inputs`` (``OrtValue`` s on the device, or numpy arrays, uploaded
        into persistent buffers); its outputs stay on the device, in buffers kept per input
        shapes."""
        vals = {k: (v if isinstance(v, self._ort.OrtValue) else self.upload(f"{stem}.{k}", _host(v)))
                for k, v in inputs.items()}
        sess = self.session(stem)
        ident = tuple((k, id(v), tuple(v.shape())) for k, v in sorted(vals.items()))
        held = self._bindings.get(stem)
        if stem in DATA_SHAPED:
            held = None
        if held is not None and held[0] == ident:  # the same buffers: the binding stands
            sess.run_with_iobinding(held[1])
            return held[2]
        binding = sess.io_binding()
        for k, v in vals.items():
            binding.bind_ortvalue_input(k, v)
        shapes = tuple((k, s) for k, _, s in ident)
        outs = held[2] if held is not None and held[3] == shapes else None
        names = [o.name for o in sess.get_outputs()]
        for n in names:
            if outs is None:
                binding.bind_output(n, self.device, 0)
            else:
                binding.bind_ortvalue_output(n, outs[n])
        sess.run_with_iobinding(binding)
        if outs is None:
            outs = dict(zip(names, binding.get_outputs()))
        # one binding per graph, its outputs kept while the input sizes stay (a new size frees them)
        self._bindings[stem] = (ident, binding, outs, shapes, vals)
        return outs

    def numpy(self, stem: str, inputs: dict) -> dict[str, np.ndarray]:
        """:meth:`run` with every output copied to the host (the tests' view of one step)."""
        return {k: v.numpy() for k, v in self.run(stem, inputs).items()}

    def _network(self, outputs: str, feed: dict) -> dict:
        m = self.model
        b, _, _, h, w = feed["analyzer"].shape()
        runner = m._runner(outputs, (int(b), int(h), int(w)) if m.fixed_sizes else None, route="device")
        return runner.run_device({k: feed[k] for k in runner.inputs}, self.device)

    def _object_mask(self, s0, shape: tuple[int, int]) -> tuple[object, int]:
        """The object mask ``(h, w)`` float32 (on the device, or a host array) and its pixel count
        by :func:`polrig.models.runtime.mask_from_s0`'s rule from the colours' mean ``S0`` on the
        device: its 1st and 99th percentiles and the neighbour differences' median come from the
        order statistics ``TopK`` finds there (``mask_stats``), interpolated here as the host rule
        does, and the threshold is applied there (``mask_threshold``). Where the rule needs the
        whole image (fewer than :data:`polrig.solve.quantiles.MIN_SIZE` pixels, a non-finite
        value, fewer than 1 % of the pixels lit) ``S0`` comes to the host and the rule runs there."""
        h, w = shape
        n, m = h * w, h * (w - 1)
        if n >= MIN_SIZE and m >= 2:
            _, hi1, f1 = _positions(n, 1.0)
            lo99, _, f99 = _positions(n, 99.0)
            mid = m // 2 if m % 2 == 0 else (m - 1) // 2  # the (upper) middle rank
            st = self.run("mask_stats", {"s0": s0, "k_low": np.array([hi1 + 1], np.int64),
                                         "k_high": np.array([n - lo99], np.int64),
                                         "k_mid": np.array([mid + 1], np.int64)})
            if st["finite"].numpy().tolist() == [n, m]:
                low, high, mids = (st[k].numpy() for k in ("low", "high", "mid"))
                # np.median: the middle value, or the float32 mean of the two middle ones
                median = float(np.median(mids if m % 2 == 0 else mids[-1:]))
                floor = _lerp(low[0], low[1], f1) + MASK_NOISE_SIGMAS * (1.4826 * median / np.sqrt(2.0))
                ref = _lerp(high[1], high[0], f99)
                if ref > floor:
                    thr = np.float32(MASK_FRACTION * ref) if ref > 0 else np.float32(np.inf)
                    out = self.run("mask_threshold", {"s0": s0, "threshold": np.array([thr], np.float32)})
                    return out["mask"], int(out["count"].numpy()[0])
        obj = mask_from_s0(s0.numpy())
        return obj.astype(np.float32), int(obj.sum())

    def _mean_direction(self, wi, mask) -> np.ndarray | None:
        """:func:`polrig.models.runtime.mean_direction` from the device's masked mean (3 numbers)."""
        mean = self.run("masked_mean", {"wi": wi, "mask": mask})["mean"].numpy().astype(np.float32)
        norm = np.linalg.norm(mean, axis=-1, keepdims=True)
        return mean / norm if np.all(norm > 1e-6) else None

    # -- the frame ------------------------------------------------------------------------------
    def frame(self, *args, **kwargs) -> dict:
        """:meth:`_frame`, one frame at a time (the buffers are this path's: a capture's
        processing and a live view sharing the route take turns)."""
        with self._lock:
            return self._frame(*args, **kwargs)

    def _frame(self, raw: np.ndarray, layout, *, to_adc: float, black: float, saturation: float,
              s_in, resolution: str = "superpixel", stage_zero_axis=None, intrinsics=None,
              scale: float | None = None, half_per_dn: float = 0.0, noise_offset: float = 0.0,
              with_stokes: bool = False, probe_every: int = 1, tolerance_deg: float = 3.0,
              preview_size: tuple[int, int] | None = None) -> dict:
        """One raw mosaic ``(H, W)`` (uint8 or uint16; ADC DN are ``raw to_adc``, ``black``
        and ``saturation`` in ADC DN) under the incident state ``s_in`` ``(3,)`` -> a dict of
        host arrays: ``mueller`` ``(C, 3, 3, h, w)`` DN per unit incident S0 (at
        ``resolution`` ``full`` the lifted ``(C, 3, 3, H, W)``), ``object`` ``(h, w)`` bool,
        ``clipped`` ``(C, h, w)`` bool, ``snr`` ``(C, h, w)`` (``half_per_dn``, ``noise_offset``:
        :meth:`polrig.sensor.noise.SensorModel.variance_terms`, the first halved), ``stokes``
        ``(C, 3, h, w)`` with ``with_stokes`` (on the output grid: ``(C, 3, H, W)`` at full
        resolution), ``scale``, ``alpha``,
        ``incident_rotation_deg`` (``wi`` is not copied); ``timings_s`` per step
        (``upload``, ``pre``, ``statistics``, ``network``, ``post``, ``copy_back``). With
        ``preview_size`` ``(dh, dw)``: ``grid`` ``(C, 3 dh, 3 dw)``, the live view's matrix
        grid, instead of ``mueller``, ``snr`` and ``clipped``. ``probe_every``: run the light-direction probe on every
        this many frames and reuse the last one's direction in between (the live view)."""
        m = self.model
        t = {"upload": 0.0, "pre": 0.0, "statistics": 0.0, "network": 0.0, "post": 0.0, "copy_back": 0.0}
        clock = [time.perf_counter()]

        def lap(step: str) -> None:
            now = time.perf_counter()
            t[step] += now - clock[0]
            clock[0] = now

        raw = np.asarray(raw)
        if raw.dtype != np.uint16:
            raw = raw.astype(np.uint16)
        f32 = lambda v: np.asarray([v], np.float32)  # noqa: E731
        raw_d = self._upload_raw(raw)
        lap("upload")
        common = {"raw": raw_d, "to_adc": f32(to_adc), "saturation": f32(saturation), "black": f32(black)}
        sp = self.run("superpixel", {**common, "cells": superpixel_cells(layout)})
        analyzer = sp["analyzer"]
        c, _, h, w = analyzer.shape()
        cn = m.colours if c == 1 else c
        colours = np.array([cn, 4, h, w], np.int64)
        lap("pre")
        # the normalisation statistics: the object mask and the scale from order statistics on the device
        mask_f, count = self._object_mask(self.run("s0_mean", {"analyzer": analyzer})["s0"], (h, w))
        n = count * cn * 4
        default = 1.0
        if n:
            # a mono frame goes to the networks repeated to their colours: its statistics are
            # those of every value ``reps`` times, whose largest are the original's repeated
            reps = cn // c
            need = tail_count(n)
            tail = self.run("scale_tail", {"analyzer": analyzer, "mask": mask_f,
                                           "k": np.array([-(-need // reps)], np.int64)})["tail"].numpy()
            default = scale_from_tail(np.repeat(tail, reps)[:need], n)
        sc = default if scale is None else float(scale)
        if not (np.isfinite(sc) and sc > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        if scale is not None and not default / sc <= MAX_INPUT_LEVEL:
            raise ValueError(f"scale {sc:g} DN per unit puts the capture's bright pixels at "
                             f"{default / sc:.3g} normalised units, the networks were trained at 1; "
                             f"leave the scale unset to take it from the image")
        lap("statistics")
        pads = np.array([(-h) % SIZE_MULTIPLE, (-w) % SIZE_MULTIPLE], np.int64)
        net = self.run("network_input", {"analyzer": analyzer, "colours": colours, "scale": f32(sc),
                                         "mask": mask_f, "pads": pads})
        hp, wp = h + int(pads[0]), w + int(pads[1])
        wo = self.upload("wo", np.pad(view_directions((h, w), intrinsics),
                                      [(0, 0), (0, int(pads[0])), (0, int(pads[1]))], mode="edge")[None])
        lap("pre")
        axis = np.asarray(m.meta.get("stage_zero_axis_camera", DEFAULT_STAGE_ZERO_AXIS) if stage_zero_axis is None
                          else stage_zero_axis, np.float64).reshape(1, 3)
        model_axis = m.model_axis
        s = np.asarray(s_in, np.float32).reshape(1, 3)
        feed = {"analyzer": net["net_analyzer"], "mask": net["net_mask"], "wo": wo,
                "stage_zero_axis": self.upload("model_axis", model_axis.astype(np.float32).reshape(1, 3))}
        wi = np.array([[0.0, 0.0, -1.0]])
        with np.errstate(invalid="ignore", divide="ignore"):
            same_axis = np.allclose(axis / np.linalg.norm(axis, axis=-1, keepdims=True),
                                    model_axis / np.linalg.norm(model_axis), atol=1e-9)
        small = probe_shape((hp, wp)) if not same_axis and "wi" in m.output_names else None
        self._frames += 1
        if small is not None:
            if self._probe_wi is not None and (self._frames - 1) % max(1, int(probe_every)):
                wi = self._probe_wi
            else:
                red = self.run("reduce", {"net_analyzer": net["net_analyzer"], "net_mask": net["net_mask"],
                                          "wo": wo, "area_y": area_matrix(hp, small[0]),
                                          "area_x": area_matrix(wp, small[1]).T.copy()})
                c2, s2 = incident_rotation(wi, axis, model_axis)
                probe = self._network("probe", {
                    "analyzer": red["probe_analyzer"], "mask": red["probe_mask"], "wo": red["probe_wo"],
                    "stage_zero_axis": feed["stage_zero_axis"],
                    "s_in": self.upload("probe_s_in", rotate_stokes(s, c2, s2).astype(np.float32))})
                w_mean = self._mean_direction(probe["wi"], red["probe_mask"])
                if w_mean is not None:
                    wi = w_mean
                self._probe_wi = wi
        prev = out = None
        for last in ([True] if small is not None else [False, True]):
            c2, s2 = incident_rotation(wi, axis, model_axis)
            theta = 0.5 * np.arctan2(s2, c2)
            if prev is not None and bool(np.all(np.abs(np.rad2deg(np.angle(np.exp(2j * (theta - prev))))) / 2
                                                < tolerance_deg)):
                break
            feed["s_in"] = self.upload("s_in", rotate_stokes(s, c2, s2).astype(np.float32))
            out = self._network("frame", feed)
            prev = theta
            if last or "wi" not in out:
                break
            w_mean = self._mean_direction(out["wi"], net["net_mask"])
            if w_mean is None:
                break
            wi = w_mean
        light = None  # the network's light spread over the object (the sigma's light factor)
        if with_stokes and preview_size is None and "wi" in out:
            light = spread_of_mean(self.run("masked_mean", {"wi": out["wi"], "mask": net["net_mask"]})["mean"]
                                   .numpy().reshape(3))
        lap("network")
        a, b = (v / np.linalg.norm(v) for v in (axis.reshape(3), model_axis.reshape(3)))
        axes = np.stack([a, b, np.cross(a, b), [float(np.sum(a * b)), 0.0, 0.0]]).astype(np.float32)
        mix = np.eye(cn, dtype=np.float32) if c == cn else np.full((1, cn), 1.0 / cn, np.float32)
        post = self.run("post", {"mueller": out["mueller"], "wi": out["wi"], "size": np.array([h, w], np.int64),
                                 "axes": axes, "colour_mix": mix, "mask": mask_f, "scale": f32(sc)})
        mueller = post["mueller_dn"]
        stokes = None  # the network grid's Stokes: for the lift, the SNR, the sigma
        if resolution == "full" or preview_size is None or with_stokes:
            stokes = self.run("stokes", {"analyzer": analyzer})["stokes"]
        result = {"scale": sc, "default_scale": default,
                  "alpha": None, "incident_rotation_deg": float(np.rad2deg(prev).reshape(-1)[0])}
        if resolution == "full":
            bil = self.run("bilinear", {**common, **bilinear_inputs(layout)})
            full = self.run("stokes", {"analyzer": bil["analyzer"]})["stokes"]
            ph, pw = layout.period
            hh, ww = raw.shape
            coef = np.asarray(s_in, np.float64).reshape(3)
            lifted = self.run("lift", {"mueller": mueller, "mask": mask_f, "stokes": stokes, "stokes_full": full,
                                       "coef": (coef / (coef @ coef)).astype(np.float32),
                                       "grid": np.array([h * ph, w * pw], np.int64),
                                       "pads": np.array([hh - h * ph, ww - w * pw], np.int64)})
            mueller = lifted["mueller_full"]
            if preview_size is None:
                snr = self.run("s0_snr", {"stokes": full, "half_per_dn": f32(half_per_dn),
                                          "offset": f32(noise_offset)})
                clipped = snr["clipped"]
        elif preview_size is None:
            snr = self.run("s0_snr", {"stokes": stokes, "half_per_dn": f32(half_per_dn), "offset": f32(noise_offset)})
            clipped = sp["clipped"]
        if preview_size is not None:
            shape = mueller.shape()
            dh, dw = preview_size
            grid = self.run("grid_preview", {"mueller": mueller, "area_y": area_matrix(shape[-2], dh),
                                             "area_x": area_matrix(shape[-1], dw).T.copy()})["grid"]
        lap("post")
        # on the CPU provider ``numpy()`` is a view of the persistent buffer, which the next frame
        # overwrites: a result keeps its own copy (from a device, ``numpy()`` is the copy back)
        back = (lambda v: v.numpy()) if self.device == "cuda" else (lambda v: v.numpy().copy())  # noqa: E731
        if "alpha" in out:
            result["alpha"] = float(out["alpha"].numpy().reshape(-1)[0])
        if preview_size is not None:
            result["grid"] = back(grid)
        else:
            result["mueller"] = back(mueller)
        if resolution == "full":
            result["object"] = back(lifted["inside"])
        else:
            result["object"] = (mask_f if isinstance(mask_f, np.ndarray) else mask_f.numpy()) > 0.5
        if preview_size is None:  # the planes of a file (the live grid shows none)
            result["snr"] = back(snr["snr"])
            cl = back(clipped)
            result["clipped"] = np.broadcast_to(cl, (c,) + cl.shape[-2:]) if cl.ndim == 2 else cl
        if with_stokes and preview_size is None:  # on the output grid (the raw one at full resolution)
            result["stokes"] = back(full if resolution == "full" else stokes)
        lap("copy_back")
        result["timings_s"] = t
        result["light_spread"] = light
        return result
