"""The single-shot route's steps around the networks as ONNX graphs (issue 31, item 3).

So that a frame stays on the execution provider's device from the raw mosaic to the Mueller
image, every step :class:`polrig.app.single_shot.SingleShot` takes around the networks on the
host (numpy, OpenCV) has a graph here that computes the same numbers from the same inputs.
:class:`polrig.models.device_path.DevicePath` chains them with the networks by I/O binding.
They run unchanged on the CPU provider, which is how ``tests/test_device_path.py`` checks each
against its numpy step.

The graphs are built with the ``onnx`` helper API (no torch) by :func:`build_all` and shipped in
``models/weights/device/`` with ``graphs.json`` (how they were made: this module, the ``onnx``
version, the opset, each file's SHA-256). Re-make them with::

    python -m polrig.models.device_graphs

Every graph is independent of the sensor's size and mosaic layout: sizes are dynamic, and what
a layout decides (its class cells, its tent taps) comes in as small inputs. Names, shapes
(``C`` colours, ``K = 4 C`` classes, ``(H, W)`` the raw mosaic, ``(h, w)`` a grid):

``to_device``
    ``raw_host`` ``(H, W)`` uint16 -> ``raw``: the upload from pinned host memory on CUDA.
``superpixel``
    ``raw`` ``(H, W)`` uint16, ``to_adc``, ``black``, ``saturation`` ``(1,)`` float32, ``cells``
    ``(K, ph, pw)`` (1 / the class's count at its cell positions) -> ``analyzer``
    ``(C, 4, H // ph, W // pw)`` float32 ADC DN (:func:`polrig.sensor.demosaic.demosaic`),
    ``clipped`` ``(h, w)`` bool (:func:`polrig.sensor.stokes.saturation_mask`'s superpixel rule).
``bilinear``
    ``raw``, ``to_adc``, ``black``, ``saturation``, ``cells`` (1 at the class's positions),
    ``tent_y`` ``(1, 1, ky, 1)``, ``tent_x`` ``(1, 1, 1, kx)`` -> ``analyzer`` ``(C, 4, H, W)``:
    the normalised convolution of ``polrig.sensor.demosaic``'s ``bilinear`` with reflect-101
    borders, clipped samples (``raw * to_adc >= saturation``) NaN as the route sets them.
``stokes``
    ``analyzer`` ``(C, 4, h, w)`` -> ``stokes`` ``(C, 3, h, w)``, the ideal inverse
    (:func:`polrig.sensor.stokes.ideal_inverse`) in :meth:`~polrig.sensor.stokes.StokesSolver.solve`'s
    order of operations (zero weights after the first skipped: bitwise the same, NaN included).
``s0_snr``
    ``stokes``, ``per_dn``, ``offset`` ``(1,)`` -> ``snr`` ``(C, h, w)`` (:func:`polrig.app.preview.s0_snr`),
    ``clipped`` ``(C, h, w)`` bool (a non-finite Stokes value).
``s0_mean``
    ``analyzer`` -> ``s0`` ``(h, w)``: the colours' mean ``S0``, what :func:`polrig.models.runtime.default_mask` reads.
``mask_stats``
    ``s0`` ``(h, w)``, ``k_low``, ``k_high``, ``k_mid`` ``(1,)`` int64 -> ``low``, ``high``,
    ``mid`` ``(2,)``: the last two of the ``k_low`` smallest and ``k_high`` largest ``S0``
    values and of the ``k_mid`` smallest ``|S0[:, j + 1] - S0[:, j]|`` (``TopK``), ``finite``
    ``(2,)`` int64: how many values and differences are finite: the order statistics of the
    object mask's rule (:func:`polrig.models.runtime.mask_from_s0`: its 1st and 99th percentile
    and the differences' median).
``mask_threshold``
    ``s0``, ``threshold`` ``(1,)`` -> ``mask`` ``(h, w)`` float32 (``S0 > threshold``),
    ``count`` ``(1,)`` int64.
``scale_tail``
    ``analyzer`` ``(C, 4, h, w)``, ``mask`` ``(h, w)`` float32, ``k`` ``(1,)`` int64 -> ``tail``
    ``(k,)``: the ``k`` largest analyzer values inside the mask, descending: the order
    statistics :func:`polrig.models.runtime.default_scale`'s percentile interpolates.
``network_input``
    ``analyzer`` ``(C, 4, h, w)``, ``colours`` ``(4,)`` int64 (the networks' input shape
    ``(Cn, 4, h, w)``: a mono frame is repeated), ``scale`` ``(1,)``, ``mask`` ``(h, w)``,
    ``pads`` ``(2,)`` int64 (bottom, right) -> ``net_analyzer`` ``(1, Cn, 4, h + pb, w + pr)``
    (edge padded), ``net_mask`` ``(1, 1, ...)`` (zero padded): :meth:`~polrig.models.runtime.SingleShotModel.reconstruct`'s.
``reduce``
    ``net_analyzer``, ``net_mask``, ``wo`` ``(1, 3, Hp, Wp)``, ``area_y`` ``(hs, Hp)``,
    ``area_x`` ``(Wp, ws)`` -> ``probe_analyzer``, ``probe_mask``, ``probe_wo``: the probe's
    area-reduced inputs (:func:`polrig.models.runtime.reduce_inputs`; ``area_*`` from
    :func:`area_matrix`).
``masked_mean``
    ``wi`` ``(1, 3, h, w)``, ``mask`` ``(1, 1, h, w)`` -> ``mean`` ``(1, 3)``: the unnormalised
    mean of :func:`polrig.models.runtime.mean_direction`.
``post``
    ``mueller`` ``(1, Cn, 3, 3, Hp, Wp)``, ``wi`` ``(1, 3, Hp, Wp)``, ``size`` ``(2,)`` int64
    ``(h, w)``, ``axes`` ``(4, 3)`` float32 (the rig's and the model's unit stage zero axes,
    their cross product, and ``(a.b, 0, 0)``), ``colour_mix`` ``(Co, Cn)``, ``mask`` ``(h, w)``, ``scale`` ``(1,)``
    -> ``mueller_dn`` ``(Co, 3, 3, h, w)``: crop, ``M R(theta)`` per pixel
    (:func:`polrig.models.runtime.incident_rotation`, :func:`~polrig.models.runtime.rotate_incident_columns`),
    the mono sensor's colour mean, DN.
``lift``
    ``mueller`` ``(C, 3, 3, h, w)``, ``mask`` ``(h, w)`` float32, ``stokes`` ``(C, 3, h, w)``,
    ``stokes_full`` ``(C, 3, H, W)``, ``coef`` ``(3,)`` (``s_k / |s|^2``), ``grid`` ``(2,)``
    int64 ``(h ph, w pw)``, ``pads`` ``(2,)`` int64 -> ``mueller_full`` ``(C, 3, 3, H, W)``,
    ``inside`` ``(H, W)`` bool: :func:`polrig.models.full_resolution.lift`.
``grid_preview``
    ``mueller`` ``(C, 3, 3, h, w)``, ``area_y`` ``(dh, h)``, ``area_x`` ``(w, dw)`` -> ``grid``
    ``(C, 3 dh, 3 dw)``: the live view's 3x3 mosaic of the elements at display size (area
    averaged; :mod:`polrig.app.single_shot`, the live route).
"""

from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np

#: Where the graphs are shipped.
GRAPH_DIR = pathlib.Path(__file__).resolve().parent / "weights" / "device"
#: The opset of every graph (onnxruntime 1.17 and later run it on the CPU and CUDA providers).
OPSET = 17
#: The description file beside the graphs.
MANIFEST = "graphs.json"


class _Graph:
    """A small builder over ``onnx.helper``: named values, one node per call."""

    def __init__(self, name: str):
        self.name = name
        self.nodes: list = []
        self.inputs: list = []
        self.outputs: list = []
        self.inits: list = []
        self._n = 0

    def input(self, name: str, dtype, shape) -> str:
        from onnx import helper

        self.inputs.append(helper.make_tensor_value_info(name, dtype, shape))
        return name

    def output(self, value: str, name: str, dtype, shape) -> None:
        from onnx import helper

        self.op("Identity", [value], name=name)
        self.outputs.append(helper.make_tensor_value_info(name, dtype, shape))

    def const(self, array, dtype=None) -> str:
        from onnx import numpy_helper

        self._n += 1
        name = f"c{self._n}"
        self.inits.append(numpy_helper.from_array(np.asarray(array, dtype), name))
        return name

    def op(self, kind: str, inputs: list[str], name: str | None = None, n_out: int = 1, **attrs):
        from onnx import helper

        outs = [name] if name else []
        while len(outs) < n_out:
            self._n += 1
            outs.append(f"v{self._n}")
        self.nodes.append(helper.make_node(kind, inputs, outs, **attrs))
        return outs[0] if n_out == 1 else outs

    def model(self):
        from onnx import checker, helper

        g = helper.make_graph(self.nodes, self.name, self.inputs, self.outputs, self.inits)
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="polrig.models.device_graphs")
        m.ir_version = 8
        checker.check_model(m)
        return m

    # -- shape helpers -------------------------------------------------------------------------
    def dim(self, value: str, axis: int) -> str:
        """The size of ``value``'s ``axis`` as an int64 ``(1,)``."""
        return self.op("Shape", [value], start=axis, end=axis + 1)

    def cat(self, *parts: str) -> str:
        return self.op("Concat", list(parts), axis=0)

    def i64(self, *v: int) -> str:
        return self.const(np.array(v, np.int64))


FLOAT, UINT16, INT64, BOOL = 1, 4, 7, 9  # onnx.TensorProto codes


def _scaled_raw(g: _Graph) -> tuple[str, str, str]:
    """``raw`` as float32 ADC DN (exact: integers times a power of two), the clipped samples
    (``>= saturation``), and ``cells``."""
    raw = g.input("raw", UINT16, ["H", "W"])
    to_adc = g.input("to_adc", FLOAT, [1])
    sat = g.input("saturation", FLOAT, [1])
    x = g.op("Mul", [g.op("Cast", [raw], to=FLOAT), to_adc])
    return x, g.op("GreaterOrEqual", [x, sat]), g.input("cells", FLOAT, ["K", "ph", "pw"])


def _classes_to_analyzer(g: _Graph, planes: str, rows: str, cols: str) -> str:
    """``(K, rows, cols)`` class planes as ``(K / 4, 4, rows, cols)``."""
    return g.op("Reshape", [planes, g.cat(g.i64(-1, 4), rows, cols)])


def superpixel_graph():
    """:data:`superpixel`: a cell's mean per class as one matrix product with the class weights
    (each weight 1 or 1/2, each output a sum of at most two non-zero terms: the numpy step's
    numbers exactly, for finite raw values)."""
    g = _Graph("superpixel")
    x, clip, cells = _scaled_raw(g)
    black = g.input("black", FLOAT, [1])
    ph, pw = g.dim(cells, 1), g.dim(cells, 2)
    rows = g.op("Div", [g.dim(x, 0), ph])
    cols = g.op("Div", [g.dim(x, 1), pw])
    zero2 = g.i64(0, 0)
    crop = g.cat(g.op("Mul", [rows, ph]), g.op("Mul", [cols, pw]))

    def cells_of(v: str) -> str:  # (H, W) -> (ph * pw, h * w)
        v = g.op("Slice", [v, zero2, crop])
        v = g.op("Reshape", [v, g.cat(rows, ph, cols, pw)])
        v = g.op("Transpose", [v], perm=[1, 3, 0, 2])
        return g.op("Reshape", [v, g.cat(g.op("Mul", [ph, pw]), g.op("Mul", [rows, cols]))])

    weights = g.op("Reshape", [cells, g.cat(g.dim(cells, 0), g.op("Mul", [ph, pw]))])
    a = g.op("Sub", [g.op("MatMul", [weights, cells_of(x)]), black])
    g.output(_classes_to_analyzer(g, a, rows, cols), "analyzer", FLOAT, ["C", 4, "h", "w"])
    clipped = g.op("ReduceMax", [cells_of(g.op("Cast", [clip], to=FLOAT))], axes=[0], keepdims=0)
    clipped = g.op("Cast", [g.op("Reshape", [clipped, g.cat(rows, cols)])], to=BOOL)
    g.output(clipped, "clipped", BOOL, ["h", "w"])
    return g.model()


def bilinear_graph():
    """:data:`bilinear`: ``conv(sparse) / conv(class mask)`` with the separable tent, the
    x pass first as ``cv2.sepFilter2D`` does."""
    g = _Graph("bilinear")
    x, clip, cells = _scaled_raw(g)
    black = g.input("black", FLOAT, [1])
    ty = g.input("tent_y", FLOAT, [1, 1, "ky", 1])
    tx = g.input("tent_x", FLOAT, [1, 1, 1, "kx"])
    x = g.op("Sub", [x, black])
    x = g.op("Where", [clip, g.const(np.float32(np.nan)), x])
    hh, ww = g.dim(x, 0), g.dim(x, 1)
    ph, pw = g.dim(cells, 1), g.dim(cells, 2)
    reps = g.cat(g.i64(1), g.op("Div", [g.op("Add", [hh, g.op("Sub", [ph, g.i64(1)])]), ph]),
                 g.op("Div", [g.op("Add", [ww, g.op("Sub", [pw, g.i64(1)])]), pw]))
    mask = g.op("Slice", [g.op("Tile", [cells, reps]), g.i64(0, 0), g.cat(hh, ww), g.i64(1, 2)])
    mask = g.op("Unsqueeze", [mask, g.i64(1)])  # (K, 1, H, W)
    sparse = g.op("Where", [g.op("Greater", [mask, g.const(np.float32(0))]), x, g.const(np.float32(0))])
    ry = g.op("Div", [g.op("Sub", [g.dim(ty, 2), g.i64(1)]), g.i64(2)])
    rx = g.op("Div", [g.op("Sub", [g.dim(tx, 3), g.i64(1)]), g.i64(2)])
    z = g.i64(0)
    pads = g.cat(z, z, ry, rx, z, z, ry, rx)

    def tent(v: str) -> str:
        v = g.op("Pad", [v, pads], mode="reflect")
        return g.op("Conv", [g.op("Conv", [v, tx]), ty])

    out = g.op("Div", [tent(sparse), tent(mask)])
    out = g.op("Squeeze", [out, g.i64(1)])
    g.output(_classes_to_analyzer(g, out, hh, ww), "analyzer", FLOAT, ["C", 4, "H", "W"])
    return g.model()


def stokes_graph():
    """:data:`stokes`: the ideal inverse unrolled in the numpy solver's order."""
    from polrig.sensor.stokes import ideal_inverse

    g = _Graph("stokes")
    a = g.input("analyzer", FLOAT, ["C", 4, "h", "w"])
    parts = g.op("Split", [a], axis=1, n_out=4)
    p = ideal_inverse().astype(np.float32)
    rows = []
    for j in range(3):
        acc = g.op("Mul", [parts[0], g.const(p[j, 0])])
        for k in range(1, 4):
            if p[j, k]:
                acc = g.op("Add", [acc, g.op("Mul", [parts[k], g.const(p[j, k])])])
        rows.append(acc)
    g.output(g.op("Concat", rows, axis=1), "stokes", FLOAT, ["C", 3, "h", "w"])
    return g.model()


def s0_snr_graph():
    """:data:`s0_snr`: ``S0 / sqrt(max(S0, 0) per_dn / 2 + offset)`` in float32 as
    :func:`polrig.app.preview.s0_snr` (``per_dn`` comes in already halved), NaN where ``S0`` is
    not finite; and the pixels with a non-finite Stokes value."""
    g = _Graph("s0_snr")
    s = g.input("stokes", FLOAT, ["C", 3, "h", "w"])
    half_per_dn = g.input("half_per_dn", FLOAT, [1])
    offset = g.input("offset", FLOAT, [1])
    s0 = g.op("Squeeze", [g.op("Slice", [s, g.i64(0), g.i64(1), g.i64(1)]), g.i64(1)])
    nan = g.const(np.float32(np.nan))
    finite = g.op("Not", [g.op("Or", [g.op("IsNaN", [s0]), g.op("IsInf", [s0])])])
    var = g.op("Max", [g.op("Where", [finite, s0, g.const(np.float32(0))]), g.const(np.float32(0))])
    var = g.op("Add", [g.op("Mul", [var, half_per_dn]), offset])
    snr = g.op("Div", [s0, g.op("Sqrt", [var])])
    g.output(g.op("Where", [finite, snr, nan]), "snr", FLOAT, ["C", "h", "w"])
    bad = g.op("Or", [g.op("IsNaN", [s]), g.op("IsInf", [s])])
    bad = g.op("Cast", [g.op("ReduceMax", [g.op("Cast", [bad], to=FLOAT)], axes=[1], keepdims=0)], to=BOOL)
    g.output(bad, "clipped", BOOL, ["C", "h", "w"])
    return g.model()


def s0_mean_graph():
    """:data:`s0_mean`: ``0.5 (((A0 + A1) + A2) + A3)`` per colour, then the colours' sum over
    their count, in :func:`polrig.models.runtime.stokes_s0`'s and ``np.mean``'s order."""
    g = _Graph("s0_mean")
    a = g.input("analyzer", FLOAT, ["C", 4, "h", "w"])
    p = g.op("Split", [a], axis=1, n_out=4)
    s0 = g.op("Add", [g.op("Add", [g.op("Add", [p[0], p[1]]), p[2]]), p[3]])
    s0 = g.op("Mul", [s0, g.const(np.float32(0.5))])
    total = g.op("ReduceSum", [s0, g.i64(0, 1)], keepdims=0)
    count = g.op("Cast", [g.dim(a, 0)], to=FLOAT)
    g.output(g.op("Div", [total, count]), "s0", FLOAT, ["h", "w"])
    return g.model()


def mask_stats_graph():
    """:data:`mask_stats`: the order statistics :func:`polrig.models.runtime.mask_from_s0`
    interpolates, by ``TopK``: the last two of the ``k_low`` smallest and of the ``k_high``
    largest ``S0`` values, of the ``k_mid`` smallest absolute horizontal neighbour differences,
    and how many values and differences are finite (the host checks they are all)."""
    g = _Graph("mask_stats")
    s0 = g.input("s0", FLOAT, ["h", "w"])
    k_low = g.input("k_low", INT64, [1])
    k_high = g.input("k_high", INT64, [1])
    k_mid = g.input("k_mid", INT64, [1])
    flat = g.op("Reshape", [s0, g.i64(-1)])
    w = g.dim(s0, 1)
    diff = g.op("Abs", [g.op("Sub", [g.op("Slice", [s0, g.i64(1), w, g.i64(1)]),
                                     g.op("Slice", [s0, g.i64(0), g.op("Sub", [w, g.i64(1)]), g.i64(1)])])])
    diff = g.op("Reshape", [diff, g.i64(-1)])

    def last_two(values: str, k: str, largest: int) -> str:
        top = g.op("TopK", [values, k], n_out=2, largest=largest, sorted=1)[0]
        return g.op("Slice", [top, g.i64(-2), g.i64(2 ** 62)])

    g.output(last_two(flat, k_low, 0), "low", FLOAT, [2])
    g.output(last_two(flat, k_high, 1), "high", FLOAT, [2])
    g.output(last_two(diff, k_mid, 0), "mid", FLOAT, [2])

    def finite_count(v: str) -> str:
        bad = g.op("Or", [g.op("IsNaN", [v]), g.op("IsInf", [v])])
        return g.op("ReduceSum", [g.op("Cast", [g.op("Not", [bad])], to=INT64)], keepdims=1)

    g.output(g.op("Concat", [finite_count(flat), finite_count(diff)], axis=0), "finite", INT64, [2])
    return g.model()


def mask_threshold_graph():
    """:data:`mask_threshold`: ``S0 > threshold`` (NaN is not) as float32, and its count."""
    g = _Graph("mask_threshold")
    s0 = g.input("s0", FLOAT, ["h", "w"])
    thr = g.input("threshold", FLOAT, [1])
    m = g.op("Cast", [g.op("Greater", [s0, thr])], to=FLOAT)
    g.output(m, "mask", FLOAT, ["h", "w"])
    count = g.op("ReduceSum", [g.op("Reshape", [g.op("Cast", [m], to=INT64), g.i64(-1)])], keepdims=1)
    g.output(count, "count", INT64, [1])
    return g.model()


def scale_tail_graph():
    """:data:`scale_tail`: ``TopK`` over the analyzer values, those outside the mask at -inf."""
    g = _Graph("scale_tail")
    a = g.input("analyzer", FLOAT, ["C", 4, "h", "w"])
    m = g.input("mask", FLOAT, ["h", "w"])
    k = g.input("k", INT64, [1])
    v = g.op("Where", [g.op("Greater", [m, g.const(np.float32(0.5))]), a, g.const(np.float32(-np.inf))])
    top = g.op("TopK", [g.op("Reshape", [v, g.i64(-1)]), k], n_out=2, largest=1, sorted=1)[0]
    g.output(top, "tail", FLOAT, ["k"])
    return g.model()


def network_input_graph():
    """:data:`network_input`: the analyzer over the scale, repeated to the networks' colours,
    padded at the edge; the mask zero-padded."""
    g = _Graph("network_input")
    a = g.input("analyzer", FLOAT, ["C", 4, "h", "w"])
    colours = g.input("colours", INT64, [4])
    scale = g.input("scale", FLOAT, [1])
    m = g.input("mask", FLOAT, ["h", "w"])
    pads = g.input("pads", INT64, [2])
    z = g.i64(0, 0, 0, 0)
    an = g.op("Div", [g.op("Expand", [a, colours]), scale])
    an = g.op("Pad", [an, g.cat(z, g.i64(0, 0), pads)], mode="edge")
    g.output(g.op("Unsqueeze", [an, g.i64(0)]), "net_analyzer", FLOAT, [1, "Cn", 4, "Hp", "Wp"])
    mk = g.op("Pad", [m, g.cat(g.i64(0, 0), pads)])
    g.output(g.op("Reshape", [mk, g.cat(g.i64(1, 1), g.op("Shape", [mk]))]), "net_mask", FLOAT,
             [1, 1, "Hp", "Wp"])
    return g.model()


def area_matrix(src: int, dst: int) -> np.ndarray:
    """``(dst, src)`` float32 weights of area averaging from ``src`` to ``dst <= src`` samples
    (OpenCV's ``INTER_AREA`` downscale: output ``i`` is the mean over ``[i s, (i + 1) s)``,
    ``s = src / dst``, partial pixels weighted by their overlap)."""
    s = src / float(dst)
    out = np.zeros((dst, src), np.float64)
    for i in range(dst):
        a, b = i * s, (i + 1) * s
        for j in range(int(np.floor(a)), min(src, int(np.ceil(b)))):
            out[i, j] = (min(b, j + 1) - max(a, j)) / s
    return out.astype(np.float32)


def reduce_graph():
    """:data:`reduce`: ``A_y X A_x`` per plane, the mask over one half, ``wo`` renormalised."""
    g = _Graph("reduce")
    an = g.input("net_analyzer", FLOAT, [1, "Cn", 4, "Hp", "Wp"])
    mk = g.input("net_mask", FLOAT, [1, 1, "Hp", "Wp"])
    wo = g.input("wo", FLOAT, [1, 3, "Hp", "Wp"])
    ay = g.input("area_y", FLOAT, ["hs", "Hp"])
    ax = g.input("area_x", FLOAT, ["Wp", "ws"])

    def area(v: str) -> str:
        return g.op("MatMul", [ay, g.op("MatMul", [v, ax])])

    g.output(area(an), "probe_analyzer", FLOAT, [1, "Cn", 4, "hs", "ws"])
    m = g.op("Cast", [g.op("Greater", [area(mk), g.const(np.float32(0.5))])], to=FLOAT)
    g.output(m, "probe_mask", FLOAT, [1, 1, "hs", "ws"])
    v = area(wo)
    norm = g.op("Sqrt", [g.op("ReduceSum", [g.op("Mul", [v, v]), g.i64(1)], keepdims=1)])
    g.output(g.op("Div", [v, g.op("Max", [norm, g.const(np.float32(1e-12))])]), "probe_wo", FLOAT,
             [1, 3, "hs", "ws"])
    return g.model()


def masked_mean_graph():
    """:data:`masked_mean`: ``sum(wi m) / max(sum m, 1)`` per component."""
    g = _Graph("masked_mean")
    wi = g.input("wi", FLOAT, [1, 3, "h", "w"])
    m = g.input("mask", FLOAT, [1, 1, "h", "w"])
    axes = g.i64(2, 3)
    s = g.op("ReduceSum", [g.op("Mul", [wi, m]), axes], keepdims=0)
    n = g.op("Max", [g.op("ReduceSum", [m, axes], keepdims=0), g.const(np.float32(1))])
    g.output(g.op("Div", [s, n]), "mean", FLOAT, [1, 3])
    return g.model()


def post_graph():
    """:data:`post`: the numpy steps' operations in their order (float32 throughout)."""
    g = _Graph("post")
    mu = g.input("mueller", FLOAT, [1, "Cn", 3, 3, "Hp", "Wp"])
    wi = g.input("wi", FLOAT, [1, 3, "Hp", "Wp"])
    size = g.input("size", INT64, [2])
    axes = g.input("axes", FLOAT, [4, 3])
    mix = g.input("colour_mix", FLOAT, ["Co", "Cn"])
    mask = g.input("mask", FLOAT, ["h", "w"])
    scale = g.input("scale", FLOAT, [1])
    to_dn = g.op("Mul", [mask, scale])
    f = lambda v: g.const(np.float32(v))  # noqa: E731
    mu = g.op("Squeeze", [g.op("Slice", [mu, g.i64(0, 0), size, g.i64(4, 5)]), g.i64(0)])  # (Cn, 3, 3, h, w)
    k = g.op("Neg", [g.op("Squeeze", [g.op("Slice", [wi, g.i64(0, 0), size, g.i64(2, 3)]), g.i64(0)])])
    kx, ky, kz = g.op("Split", [k], axis=0, n_out=3)  # (1, h, w) each
    a_rows = g.op("Split", [axes], axis=0, n_out=4)

    def dot(row: str) -> str:  # sum_i k_i v_i in numpy's order (v a (1, 3) row)
        v = g.op("Split", [row], axis=1, n_out=3)
        acc = g.op("Add", [g.const(np.float32(0)), g.op("Mul", [kx, g.op("Squeeze", [v[0]])])])
        acc = g.op("Add", [acc, g.op("Mul", [ky, g.op("Squeeze", [v[1]])])])
        return g.op("Add", [acc, g.op("Mul", [kz, g.op("Squeeze", [v[2]])])])

    ka, kb, kn = dot(a_rows[0]), dot(a_rows[1]), dot(a_rows[2])
    ab = g.op("Squeeze", [g.op("Slice", [a_rows[3], g.i64(0), g.i64(1), g.i64(1)])])
    kk = g.op("Add", [g.op("Add", [g.op("Mul", [kx, kx]), g.op("Mul", [ky, ky])]), g.op("Mul", [kz, kz])])
    c = g.op("Sub", [ab, g.op("Div", [g.op("Mul", [ka, kb]), kk])])
    s = g.op("Div", [kn, g.op("Sqrt", [kk])])
    cc, ss = g.op("Mul", [c, c]), g.op("Mul", [s, s])
    r2 = g.op("Add", [cc, ss])
    ok = g.op("And", [g.op("Not", [g.op("Or", [g.op("IsNaN", [r2]), g.op("IsInf", [r2])])]),
                      g.op("Greater", [r2, f(1e-14)])])
    r2 = g.op("Where", [ok, r2, f(1.0)])
    cos2 = g.op("Where", [ok, g.op("Div", [g.op("Sub", [cc, ss]), r2]), f(1.0)])
    sin2 = g.op("Where", [ok, g.op("Div", [g.op("Mul", [g.op("Mul", [f(2.0), c]), s]), r2]), f(0.0)])
    c0, c1, c2 = g.op("Split", [mu], axis=2, n_out=3)  # columns (Cn, 3, 1, h, w)
    n1 = g.op("Sub", [g.op("Mul", [c1, cos2]), g.op("Mul", [sin2, c2])])
    n2 = g.op("Add", [g.op("Mul", [c2, cos2]), g.op("Mul", [sin2, c1])])
    mu = g.op("Concat", [c0, n1, n2], axis=2)
    mu = g.op("Einsum", [mix, mu], equation="oc,cijhw->oijhw")
    g.output(g.op("Mul", [mu, to_dn]), "mueller_dn", FLOAT, ["Co", 3, 3, "h", "w"])
    return g.model()


def lift_graph():
    """:data:`lift`: ``up(M) g + detail s_k / |s|^2`` with ``g = 1 / up(mask)`` inside (``up``
    half-pixel bilinear at the integer factor, edge-repeated to the raw size), 0 outside, and
    ``detail = (S_full - up(S mask) g)`` with non-finite values 0, 0 outside."""
    g = _Graph("lift")
    mu = g.input("mueller", FLOAT, ["C", 3, 3, "h", "w"])
    m = g.input("mask", FLOAT, ["h", "w"])
    s = g.input("stokes", FLOAT, ["C", 3, "h", "w"])
    sf = g.input("stokes_full", FLOAT, ["C", 3, "H", "W"])
    coef = g.input("coef", FLOAT, [3])
    grid = g.input("grid", INT64, [2])
    pads = g.input("pads", INT64, [2])
    zero = g.const(np.float32(0))

    def up(v: str, lead: int) -> str:
        # as (1, N, h, w): the 4-D case with the outer scales 1, which every provider's linear
        # Resize takes; then back to the lead axes
        shape = g.op("Shape", [v])
        flat = g.op("Reshape", [v, g.cat(g.i64(1, -1), g.op("Slice", [shape, g.i64(lead), g.i64(lead + 2)]))])
        r = g.op("Resize", [flat, "", "", g.cat(g.i64(1), g.dim(flat, 1), grid)], mode="linear",
                 coordinate_transformation_mode="half_pixel")
        r = g.op("Pad", [r, g.cat(g.i64(0, 0, 0, 0, 0, 0), pads)], mode="edge")
        return g.op("Reshape", [r, g.cat(g.op("Slice", [shape, g.i64(0), g.i64(lead)]), g.op("Shape", [r], start=2))])

    w = up(m, 0)
    inside = g.op("Greater", [w, g.const(np.float32(0.5))])
    norm = g.op("Where", [inside, g.op("Reciprocal", [w]), zero])
    obj = g.op("Greater", [m, g.const(np.float32(0.5))])
    seen = g.op("Mul", [up(g.op("Where", [obj, s, zero]), 2), norm])
    detail = g.op("Sub", [sf, seen])
    detail = g.op("Where", [g.op("IsNaN", [detail]), zero, detail])
    detail = g.op("Mul", [detail, g.op("Cast", [inside], to=FLOAT)])  # (C, 3, H, W): row r
    plane = g.op("Mul", [up(mu, 3), norm])
    detail = g.op("Unsqueeze", [detail, g.i64(2)])  # (C, 3, 1, H, W)
    coef = g.op("Reshape", [coef, g.i64(1, 1, 3, 1, 1)])
    g.output(g.op("Add", [g.op("Mul", [detail, coef]), plane]), "mueller_full", FLOAT, ["C", 3, 3, "H", "W"])
    g.output(inside, "inside", BOOL, ["H", "W"])
    return g.model()


def grid_preview_graph():
    """:data:`grid_preview`: each element area-reduced to ``(dh, dw)``, laid out as the matrix."""
    g = _Graph("grid_preview")
    mu = g.input("mueller", FLOAT, ["C", 3, 3, "h", "w"])
    ay = g.input("area_y", FLOAT, ["dh", "h"])
    ax = g.input("area_x", FLOAT, ["w", "dw"])
    small = g.op("MatMul", [ay, g.op("MatMul", [mu, ax])])  # (C, 3, 3, dh, dw)
    grid = g.op("Transpose", [small], perm=[0, 1, 3, 2, 4])  # (C, 3, dh, 3, dw)
    shape = g.cat(g.dim(small, 0), g.op("Mul", [g.dim(small, 3), g.i64(3)]),
                  g.op("Mul", [g.dim(small, 4), g.i64(3)]))
    g.output(g.op("Reshape", [grid, shape]), "grid", FLOAT, ["C", "gh", "gw"])
    return g.model()


def to_device_graph():
    """:data:`to_device`: the raw mosaic as it is (on CUDA the input bound in pinned host memory,
    the output in device memory: onnxruntime's copy between them is the upload)."""
    g = _Graph("to_device")
    g.output(g.input("raw_host", UINT16, ["H", "W"]), "raw", UINT16, ["H", "W"])
    return g.model()


#: Every graph by the file stem it ships as.
BUILDERS = {"superpixel": superpixel_graph, "bilinear": bilinear_graph, "stokes": stokes_graph,
            "s0_snr": s0_snr_graph, "s0_mean": s0_mean_graph, "mask_stats": mask_stats_graph,
            "mask_threshold": mask_threshold_graph, "scale_tail": scale_tail_graph,
            "network_input": network_input_graph, "reduce": reduce_graph,
            "masked_mean": masked_mean_graph, "post": post_graph, "lift": lift_graph,
            "grid_preview": grid_preview_graph, "to_device": to_device_graph}


def build_all(folder: pathlib.Path = GRAPH_DIR) -> dict:
    """Write every graph to ``folder`` with :data:`MANIFEST`; returns the manifest."""
    import onnx

    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for stem, build in BUILDERS.items():
        data = build().SerializeToString(deterministic=True)
        (folder / f"{stem}.onnx").write_bytes(data)
        files[f"{stem}.onnx"] = hashlib.sha256(data).hexdigest()
    manifest = {"made_by": "python -m polrig.models.device_graphs (models/device_graphs.py)",
                "onnx": onnx.__version__, "opset": OPSET, "sha256": files}
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return manifest


if __name__ == "__main__":
    print(json.dumps(build_all(), indent=1))
