"""Export the trained networks to ONNX and check the graphs against PyTorch.

Shipped graphs (``models/weights/``):

* ``single_shot.onnx``: PIPNet -> differentiable pBRDF (:mod:`polrig.models.pbrdf_torch`, eta = 1.5,
  ks = 1) -> PMMNet as **one graph**. Chosen over "ONNX PIPNet -> numpy :mod:`polrig.optics.pbrdf`
  -> ONNX PMMNet" for speed: one onnxruntime call, no float64 numpy pass over every pixel and
  no copies between sessions (the numpy pBRDF alone costs more than both networks at 512x512
  on this CPU); the torch pBRDF is tested against :mod:`polrig.optics.pbrdf` to 1e-5, so the physics is
  the same. Outputs ``mueller``, ``mueller_init`` (PIPNet-pBRDF alone), ``normal``, ``kd``,
  ``wi``, ``alpha``. No ``Acos`` (:func:`polrig.models.pipnet.diffuse_zenith_cos_sin`).
* ``single_shot_frame.onnx`` (``mueller``, ``wi``, ``alpha``: what the frame path reads) and
  ``single_shot_probe.onnx`` (``wi``: the light-direction probe's, PIPNet alone): the same
  function with fewer outputs, so onnxruntime runs only the nodes those need.
* ``direct.onnx``: the direct Stokes->MM ablation baseline (same backbone, no physics).

Inputs of both: ``analyzer`` (B,C,4,H,W) normalised, ``mask`` (B,1,H,W), ``s_in`` (B,3),
``wo`` (B,3,H,W), ``stage_zero_axis`` (B,3); batch, height and width are dynamic (H and W
multiples of :data:`polrig.models.layers.SIZE_MULTIPLE`). Opset 17, legacy TorchScript exporter. The U-Nets'
full-resolution 1x1 layers are written in their concatenating form, one Conv node each
(:class:`polrig.models.layers.UpsampledConcatConv1x1`: training evaluates the split form).

The check: each graph is run with onnxruntime on the export sample and compared with PyTorch;
the export fails (:class:`ExportError`, nothing replaced in ``weights_dir``) when a network has
a non-finite weight, when either output is non-finite, or when the largest difference exceeds
:data:`EXPORT_TOLERANCE` times ``max(1, max |output|)`` (float32 rounding gives about 1e-6 of
the output; the shipped graphs 6e-5 on outputs up to 11). The graphs and ``model.json`` are
written under temporary names and renamed into place only when every check passed.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import pathlib
import warnings

import numpy as np
import torch

from polrig.atomic import atomic_write_text, temporary_sibling
from polrig.errors import PolrigError
from polrig.models.layers import SIZE_MULTIPLE, UpsampledConcatConv1x1
from polrig.models.pipnet import PIPNet
from polrig.models.pmmnet import (
    FRAME_OUTPUTS,
    PROBE_OUTPUTS,
    SINGLE_SHOT_OUTPUTS,
    DirectStokesToMM,
    PMMNet,
    SelectedOutputs,
    SingleShotNet,
)

OPSET = 17
#: Largest accepted ``max |onnx - torch|`` relative to ``max(1, max |output|)`` (module docstring).
EXPORT_TOLERANCE = 1e-3


class ExportError(PolrigError):
    """An exported graph does not compute what the network does (a failure while running)."""
INPUTS = ("analyzer", "mask", "s_in", "wo", "stage_zero_axis")
_DYNAMIC = {"analyzer": {0: "batch", 3: "height", 4: "width"}, "mask": {0: "batch", 2: "height", 3: "width"},
            "s_in": {0: "batch"}, "wo": {0: "batch", 2: "height", 3: "width"},
            "stage_zero_axis": {0: "batch"}}


@contextlib.contextmanager
def _upsampled_convs_concatenating(model: torch.nn.Module, concatenate: bool):
    """Every :class:`polrig.models.layers.UpsampledConcatConv1x1` of ``model`` in the given form for
    the duration (the previous forms restored after)."""
    layers = [m for m in model.modules() if isinstance(m, UpsampledConcatConv1x1)]
    before = [m.concatenate for m in layers]
    for m in layers:
        m.concatenate = concatenate
    try:
        yield
    finally:
        for m, b in zip(layers, before):
            m.concatenate = b


def _export(model: torch.nn.Module, sample: dict[str, torch.Tensor], outputs: tuple[str, ...],
            path: pathlib.Path, concatenate: bool = True) -> None:
    """Export ``model`` to ``path``. ``concatenate``: the U-Net's full-resolution 1x1 layers in
    their concatenating form (one Conv node each; :class:`polrig.models.layers.UpsampledConcatConv1x1`),
    else in the split form (two)."""
    dyn = dict(_DYNAMIC)
    for name in outputs:
        dyn[name] = {0: "batch"}
    args = tuple(sample[k] for k in INPUTS)
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings(), \
            _upsampled_convs_concatenating(model, concatenate):
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and tracer notes
        torch.onnx.export(model, args, str(path), input_names=list(INPUTS), output_names=list(outputs),
                          opset_version=OPSET, dynamic_axes=dyn, dynamo=False, do_constant_folding=True)


def compare_with_onnxruntime(model: torch.nn.Module, path: pathlib.Path,
                             sample: dict[str, torch.Tensor],
                             reference: torch.Tensor | tuple[torch.Tensor, ...] | None = None) -> float:
    """Max abs difference between the torch model and the ONNX graph on ``sample``;
    ``reference``: what ``model`` returns on ``sample`` where the caller already ran it (else it
    is run here)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = {i.name for i in sess.get_inputs()}
    ort_out = sess.run(None, {k: sample[k].numpy() for k in INPUTS if k in names})
    if reference is None:
        with torch.no_grad():
            reference = model(*(sample[k] for k in INPUTS))
    ref = reference if isinstance(reference, tuple) else (reference,)
    return float(max(np.max(np.abs(o - r.numpy())) for o, r in zip(ort_out, ref)))


#: The single-shot function's graphs with fewer outputs (:data:`SINGLE_SHOT_OUTPUTS`' subsets): the
#: frame path's and the light-direction probe's (:mod:`polrig.models.runtime`).
FRAME_GRAPH = "single_shot_frame.onnx"
PROBE_GRAPH = "single_shot_probe.onnx"


def graphs(single: torch.nn.Module, direct: torch.nn.Module) -> list[tuple[str, torch.nn.Module, tuple[str, ...]]]:
    """``(file, module, output names)`` of every shipped graph (module docstring)."""
    return [("single_shot.onnx", single, SINGLE_SHOT_OUTPUTS),
            (FRAME_GRAPH, SelectedOutputs(single, FRAME_OUTPUTS).eval(), FRAME_OUTPUTS),
            (PROBE_GRAPH, SelectedOutputs(single, PROBE_OUTPUTS).eval(), PROBE_OUTPUTS),
            ("direct.onnx", direct, ("mueller",))]


def export_all(pipnet: PIPNet, pmmnet: PMMNet, direct: DirectStokesToMM, weights_dir: str | pathlib.Path,
               sample: dict[str, torch.Tensor], extra_meta: dict | None = None) -> dict[str, dict]:
    """Export ``single_shot.onnx`` and ``direct.onnx`` plus ``model.json`` into ``weights_dir``;
    returns ``{file: {bytes, max_abs_diff, max_abs_output}}``. Raises :class:`ExportError`
    (and leaves ``weights_dir`` as it was) when a check fails (module docstring)."""
    wd = pathlib.Path(weights_dir)
    single = SingleShotNet(pipnet, pmmnet).eval()
    direct = direct.eval()
    h, w = sample["analyzer"].shape[-2:]
    if h % SIZE_MULTIPLE or w % SIZE_MULTIPLE:
        raise ValueError(f"export sample must be a multiple of {SIZE_MULTIPLE} pixels, got {h}x{w}")
    for name, net in (("pipnet", pipnet), ("pmmnet", pmmnet), ("direct", direct)):
        bad = [k for k, v in net.state_dict().items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
        if bad:
            raise ExportError(f"the {name} network has non-finite weights ({bad[0]}); nothing exported "
                              f"(the training diverged: lower --lr)")
    wd.mkdir(parents=True, exist_ok=True)
    # PyTorch's outputs, each network run once: the smaller single-shot graphs' are a selection
    # of the full graph's (SelectedOutputs.select)
    with torch.no_grad():
        full, baseline = single(*(sample[k] for k in INPUTS)), direct(*(sample[k] for k in INPUTS))
    report, written = {}, []
    try:
        for name, model, outputs in graphs(single, direct):
            tmp = temporary_sibling(wd / name)
            written.append((tmp, wd / name))
            _export(model, sample, outputs, tmp)
            expected = full if model is single else baseline if model is direct else model.select(full)
            first = expected[0] if isinstance(expected, tuple) else expected
            rec = {"bytes": tmp.stat().st_size,
                   "max_abs_diff": compare_with_onnxruntime(model, tmp, sample, reference=expected),
                   "max_abs_output": float(first.abs().max())}
            limit = EXPORT_TOLERANCE * max(1.0, rec["max_abs_output"])
            if not (math.isfinite(rec["max_abs_diff"]) and math.isfinite(rec["max_abs_output"])):
                raise ExportError(f"export check of {name}: max |onnx - torch| = {rec['max_abs_diff']:.3g}, max "
                                  f"|output| = {rec['max_abs_output']:.3g} (non-finite); nothing exported")
            if rec["max_abs_diff"] > limit:
                raise ExportError(f"export check of {name}: max |onnx - torch| = {rec['max_abs_diff']:.3g} exceeds "
                                  f"{limit:.3g} ({EXPORT_TOLERANCE:g} x max(1, max |output| "
                                  f"{rec['max_abs_output']:.3g})); nothing exported")
            report[name] = rec
        meta = {"colours": int(pipnet.colours), "width": int(pipnet.backbone.width), "opset": OPSET,
                "inputs": list(INPUTS), "single_shot_outputs": list(SINGLE_SHOT_OUTPUTS),
                "graph_outputs": {name: list(outputs) for name, _, outputs in graphs(single, direct)},
                # which files belong together: the runtime takes the smaller graphs only beside
                # the full graph they were exported with
                "graph_sha256": {final.name: _sha256(tmp) for tmp, final in written},
                "size_multiple": SIZE_MULTIPLE, "eta": 1.5, "ks": 1.0, "camera_x_axis": [1.0, 0.0, 0.0],
                "conventions_version": _conventions_version(), "export_check": report,
                "export_tolerance": EXPORT_TOLERANCE}
        meta.update(extra_meta or {})
        for tmp, final in written:
            os.replace(tmp, final)
        written = []
    finally:
        for tmp, _ in written:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
    # a calibration of earlier graphs in this folder belongs to them (polrig.models.uncertainty checks the hash)
    atomic_write_text(wd / "model.json", json.dumps(meta, indent=2))
    return report


def _sha256(path: pathlib.Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def _conventions_version() -> str:
    from polrig.optics.conventions import CONVENTIONS_VERSION

    return CONVENTIONS_VERSION
