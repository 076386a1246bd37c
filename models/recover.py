"""PyTorch networks from exported ONNX graphs, so the shipped weights can be fine-tuned.

The repository ships the trained networks as ONNX (``models/weights``), not as PyTorch
checkpoints: that is what runs, and what a training run's checkpoints would otherwise have
to stay next to. :func:`networks_from_weights` turns the graphs back into the three
:mod:`models` networks, and ``polrig train --init-from models/weights`` starts from them.

What the exporter changed and how it is undone:

* Parameters keep their module names (``pipnet.kd_head.weight``) except where the legacy
  TorchScript exporter folded a ``Conv2d(bias=False) -> BatchNorm2d`` pair (eval mode) into
  one convolution ``W' = W g / sqrt(v + e)``, ``b' = beta - g m / sqrt(v + e)``. Those are
  matched by position: the graph's ``Conv`` nodes are in the order the network runs its
  ``Conv2d`` modules (recorded with forward hooks on one small input), and every shape is
  checked. The recovered batch norm is the identity plus ``b'`` (weight 1, mean 0, variance
  ``1 - e``), so the recovered network computes the graph's function exactly in eval mode.
* The split between ``W`` and ``g / sqrt(v + e)`` is lost. Training uses batch statistics, so
  before a recovered network is trained :func:`recalibrate_batchnorm` moves each batch norm's
  statistics to those of its input on the training data (mean ``mu``, variance ``s^2``) and
  sets ``g = sqrt(s^2 + e)``, ``beta = b' + mu`` (in general: keeps the eval-mode function
  ``a x + c`` of each batch norm), so a batch whose statistics are the data's gives the same
  output in training mode.
"""

from __future__ import annotations

import json
import pathlib
from typing import Callable, Iterable

import numpy as np
import torch
from torch import nn

from polrig.errors import FormatError
from polrig.models.layers import UpsampledConcatConv1x1

_TRACE_SIZE = 16


def _trace_inputs(colours: int) -> tuple[torch.Tensor, ...]:
    """One small, plausible input of the exported graphs (only the order of the convolutions
    is recorded from it)."""
    ramp = torch.linspace(0.2, 0.8, _TRACE_SIZE * _TRACE_SIZE).reshape(_TRACE_SIZE, _TRACE_SIZE)
    analyzer = ramp.expand(1, colours, 4, _TRACE_SIZE, _TRACE_SIZE).clone()
    analyzer[:, :, 0] *= 1.2  # some polarization
    mask = torch.ones(1, 1, _TRACE_SIZE, _TRACE_SIZE)
    s_in = torch.tensor([[1.0, 0.9, 0.1]])
    wo = torch.zeros(1, 3, _TRACE_SIZE, _TRACE_SIZE)
    wo[:, 2] = -1.0
    axis = torch.tensor([[0.0, -1.0, 0.0]])
    return analyzer, mask, s_in, wo, axis


def _conv_order(model: nn.Module, inputs: tuple[torch.Tensor, ...]) -> list[str]:
    order: list[str] = []
    hooks = [m.register_forward_hook(lambda mod, i, o, name=name: order.append(name))
             for name, m in model.named_modules() if isinstance(m, nn.Conv2d)]
    try:
        with torch.no_grad():
            model.eval()(*inputs)
    finally:
        for h in hooks:
            h.remove()
    return order


def _split_convs(modules: dict[str, nn.Module], order: list[str], convs: list, init: dict) -> set[str]:
    """Names of the :class:`polrig.models.layers.UpsampledConcatConv1x1` modules that the graph holds as
    two Conv nodes (the split form): their graph weight has fewer input channels than the
    module's. Graphs exported before the split have one Conv of the whole weight."""
    splits, k = set(), 0
    for name in order:
        if k >= len(convs):
            break
        conv = modules[name]
        if isinstance(conv, UpsampledConcatConv1x1) and init[convs[k].input[1]].shape[1] < conv.weight.shape[1]:
            splits.add(name)
            k += 1
        k += 1
    return splits


def load_onnx_into(model: nn.Module, path: str | pathlib.Path, colours: int) -> None:
    """Set ``model``'s parameters and buffers from the ONNX graph at ``path`` that was exported
    from a network of the same architecture (module docstring). Raises :class:`FormatError`
    naming the first mismatch."""
    import onnx
    from onnx import numpy_helper

    path = pathlib.Path(path)
    graph = onnx.load(str(path)).graph
    init = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    own = model.state_dict()
    new: dict[str, torch.Tensor] = {k: torch.from_numpy(np.array(v)) for k, v in init.items() if k in own}
    modules = dict(model.named_modules())
    order = _conv_order(model, _trace_inputs(colours))
    convs = [n for n in graph.node if n.op_type == "Conv"]
    unstored = [n for n in convs if n.input[1] not in init]
    if unstored:
        raise FormatError(f"{path.name}: convolution {unstored[0].name} has no stored weight")
    # an UpsampledConcatConv1x1 is one Conv node (of the concatenation) or two (split form)
    splits = _split_convs(modules, order, convs, init)
    if len(order) + len(splits) != len(convs):
        raise FormatError(f"{path.name}: {len(convs)} convolutions in the graph, {len(order)} in the network "
                          "(another architecture or width?)")
    nodes = iter(convs)
    for name in order:
        conv = modules[name]
        node = next(nodes)
        w = init[node.input[1]]
        if name in splits:
            # the decoder part (no bias, low_channels inputs) and the input part (bias), in graph order
            pair = (node, next(nodes))
            low = [n for n in pair if len(n.input) < 3]
            high = [n for n in pair if len(n.input) > 2]
            if len(low) != 1 or len(high) != 1:
                raise FormatError(f"{path.name}: {name} is split in two convolutions, not one with and one "
                                  "without a bias")
            node, w = high[0], np.concatenate([init[low[0].input[1]], init[high[0].input[1]]], 1)
        if tuple(conv.weight.shape) != w.shape:
            raise FormatError(f"{path.name}: {name}.weight is {tuple(conv.weight.shape)} in the network, "
                              f"{w.shape} in the graph")
        bias = init[node.input[2]] if len(node.input) > 2 else np.zeros(w.shape[0], np.float32)
        new[f"{name}.weight"] = torch.from_numpy(np.array(w))
        if conv.bias is not None:
            new[f"{name}.bias"] = torch.from_numpy(np.array(bias))
            continue
        parent, index = name.rsplit(".", 1)
        bn_name = f"{parent}.{int(index) + 1}"  # the module after the convolution in its Sequential
        bn = modules.get(bn_name)
        if not isinstance(bn, nn.BatchNorm2d):
            raise FormatError(f"{path.name}: {name} has no bias and no batch norm after it")
        new[f"{bn_name}.weight"] = torch.ones(w.shape[0])
        new[f"{bn_name}.bias"] = torch.from_numpy(np.array(bias))
        new[f"{bn_name}.running_mean"] = torch.zeros(w.shape[0])
        new[f"{bn_name}.running_var"] = torch.full((w.shape[0],), 1.0 - bn.eps)
    for key, value in own.items():
        if key.endswith("num_batches_tracked"):
            new[key] = value
    missing = [k for k in own if k not in new]
    if missing:
        raise FormatError(f"{path.name}: no value for {missing[:3]} (another architecture?)")
    wrong = [k for k in own if tuple(new[k].shape) != tuple(own[k].shape)]
    if wrong:
        raise FormatError(f"{path.name}: {wrong[0]} is {tuple(own[wrong[0]].shape)} in the network, "
                          f"{tuple(new[wrong[0]].shape)} in the graph")
    model.load_state_dict(new)


def networks_from_weights(weights_dir: str | pathlib.Path) -> tuple[dict[str, nn.Module], dict]:
    """``({"pipnet", "pmmnet", "direct"}: networks, model.json)`` of a weights folder
    (:func:`polrig.models.export.export_all` output), in eval mode, computing what the graphs compute."""
    from polrig.models.pipnet import PIPNet
    from polrig.models.pmmnet import DirectStokesToMM, PMMNet, SingleShotNet

    wd = pathlib.Path(weights_dir)
    meta_path = wd / "model.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path} not found (a weights folder holds model.json and the ONNX graphs)")
    meta = json.loads(meta_path.read_text())
    colours, width = int(meta["colours"]), int(meta["width"])
    config = (meta.get("training") or {}).get("config", {})
    pipnet = PIPNet(colours, width, bool(config.get("sfp_prior", False)))
    pmmnet, direct = PMMNet(colours, width), DirectStokesToMM(colours, width)
    load_onnx_into(SingleShotNet(pipnet, pmmnet), wd / "single_shot.onnx", colours)
    load_onnx_into(direct, wd / "direct.onnx", colours)
    return {"pipnet": pipnet.eval(), "pmmnet": pmmnet.eval(), "direct": direct.eval()}, meta


def checkpoint_from_weights(weights_dir: str | pathlib.Path) -> dict:
    """A donor in the layout of a ``polrig train`` checkpoint (``config``, ``models``,
    ``times``) for :func:`polrig.models.train.train`'s ``init_from``: the recovered networks, the
    training configuration and per-network epochs and CPU seconds that ``model.json`` records,
    its ``lineage`` and ``size``.
    ``recovered_from_onnx`` tells the trainer to :func:`recalibrate_batchnorm` before training
    a network."""
    nets, meta = networks_from_weights(weights_dir)
    training = meta.get("training") or {}
    # the recipe, not the machine or the subset the last run happened to use
    config = {k: v for k, v in training.get("config", {}).items() if k not in ("threads", "limit")}
    totals = training.get("totals", {})
    times = {}
    for k in nets:
        config.setdefault(f"{k}_epochs", int(totals.get(k, {}).get("epochs", 0)))
        times[k] = float(totals.get(k, {}).get("seconds", 0.0))
    config.setdefault("width", int(meta["width"]))
    return {"config": config, "models": {k: m.state_dict() for k, m in nets.items()}, "times": times,
            "recovered_from_onnx": str(weights_dir), "lineage": list(training.get("lineage") or []),
            "size": meta.get("size"),
            "optimizer_note": "networks recovered from the ONNX graphs, which keep no optimizer state"}


@torch.no_grad()
def recalibrate_batchnorm(model: nn.Module, forward_passes: Iterable[Callable[[], object]]) -> None:
    """Move every batch norm of ``model`` to the statistics of its input over
    ``forward_passes`` (each runs ``model`` on one batch) while keeping its eval-mode function
    ``y = a x + c`` (module docstring): mean ``mu``, variance ``s^2``, weight
    ``a sqrt(s^2 + e)``, bias ``c + a mu``. ``model`` is left in eval mode."""
    bns = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
    sums: dict[nn.Module, list] = {m: [0.0, 0.0, 0] for m in bns}

    def collect(mod, inputs):
        x = inputs[0].double()
        s = sums[mod]
        s[0] = s[0] + x.sum((0, 2, 3))
        s[1] = s[1] + (x * x).sum((0, 2, 3))
        s[2] += x.numel() // x.shape[1]

    hooks = [m.register_forward_pre_hook(collect) for m in bns]
    model.eval()
    try:
        for run in forward_passes:
            run()
    finally:
        for h in hooks:
            h.remove()
    for m in bns:
        total, squares, n = sums[m]
        if n == 0:
            continue
        mean = total / n
        var = (squares / n - mean * mean).clamp_min(0.0)
        gain = m.weight.double() / torch.sqrt(m.running_var.double() + m.eps)  # a
        offset = m.bias.double() - gain * m.running_mean.double()  # c
        m.running_mean.copy_(mean.float())
        m.running_var.copy_(var.float())
        m.weight.copy_((gain * torch.sqrt(var + m.eps)).float())
        m.bias.copy_((offset + gain * mean).float())
