"""Re-export the shipped single-shot graphs from their own networks (same parameters) and check
the new graphs against the shipped one (issue 31: the graph without ``Acos``, the frame path's
and the probe's graphs with fewer outputs).

    python -m polrig.models.reship [--weights models/weights] [--reference tests/data/single_shot_reference.npz]

Steps: the networks are recovered from the shipped graphs (:func:`polrig.models.recover.networks_from_weights`),
exported by :func:`polrig.models.export.export_all` into a temporary folder (its own ONNX-vs-torch
check), and every new single-shot graph is compared with the shipped ``single_shot.onnx`` on
held-out simulated samples (:func:`polrig.sim.dataset.make_sample`, ``holdout=True``): each shared
output's largest difference relative to that output's largest magnitude must stay within
its :data:`TOLERANCE`. Only then are the single-shot graphs copied into the weights folder (``direct.onnx``
is left as it is), ``model.json``'s export records updated and ``uncertainty.json``'s
``graph_sha256`` moved to the new file (the calibration is of the function, which is unchanged).
``--reference`` also writes the shipped graph's outputs on two small held-out samples (the test's
reference, ``tests/test_models_graph.py``) before anything is replaced.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import tempfile

import numpy as np

from polrig.atomic import atomic_write_text

#: Largest accepted ``max |new - shipped| / max |shipped|`` per output: issue 31's 1e-5 for the
#: Mueller image, ``kd`` and ``alpha``. ``mueller_init``, ``normal`` and ``wi`` get 5e-5: the
#: shipped graph itself differs from the PyTorch networks it was exported from by up to 2.5e-5 of
#: their maximum on held-out samples (float32 rounding, amplified by the U-Nets; the PyTorch
#: networks with the ``acos`` form and with this one differ by as much, and by up to 3e-4 when
#: the prior's input alone is rounded from float64), so 1e-5 is below the graph's own float32
#: floor there. Their largest differences sit at single pixels (``wi``, ``normal``: outside the
#: object, where nothing reads them; within it <= 7e-6).
TOLERANCE = {"mueller": 1e-5, "kd": 1e-5, "alpha": 1e-5, "mueller_init": 5e-5, "normal": 5e-5, "wi": 5e-5}
SINGLE_SHOT_GRAPHS = ("single_shot.onnx", "single_shot_frame.onnx", "single_shot_probe.onnx")


def heldout_feeds(n: int, size: int, seed: int = 31) -> list[dict[str, np.ndarray]]:
    """``n`` held-out simulated samples as graph inputs (batch 1, ``size`` x ``size``)."""
    from polrig.sim.dataset import make_sample

    out = []
    for i in range(n):
        s = make_sample(i, seed=seed, width=size, height=size, holdout=True)
        out.append({"analyzer": s["analyzer"][None], "mask": s["mask"].astype(np.float32)[None, None],
                    "s_in": s["s_in"][None], "wo": s["wo"].astype(np.float32)[None],
                    "stage_zero_axis": s["stage_zero_axis"][None]})
    return out


def run_graph(path: pathlib.Path, feed: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    return dict(zip(names, sess.run(None, {i.name: feed[i.name] for i in sess.get_inputs()})))


def relative_deviation(new: dict[str, np.ndarray], ref: dict[str, np.ndarray]) -> dict[str, float]:
    """``max |new - ref| / max |ref|`` per output both hold."""
    return {k: float(np.max(np.abs(new[k] - ref[k])) / max(float(np.max(np.abs(ref[k]))), 1e-30))
            for k in new if k in ref}


def node_counts(path: pathlib.Path) -> dict[str, int]:
    import collections

    import onnx

    ops = collections.Counter(n.op_type for n in onnx.load(str(path)).graph.node)
    return {"nodes": sum(ops.values()), "compute": sum(v for k, v in ops.items() if k != "Constant"),
            "Acos": ops.get("Acos", 0)}


def main(argv: list[str] | None = None) -> int:
    import torch

    from polrig.models.export import export_all
    from polrig.models.recover import networks_from_weights
    from polrig.models.uncertainty import graph_sha256

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--weights", default=str(pathlib.Path(__file__).resolve().parent / "weights"))
    ap.add_argument("--reference", default=None)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--size", type=int, default=128)
    args = ap.parse_args(argv)
    wd = pathlib.Path(args.weights)
    shipped = wd / "single_shot.onnx"
    feeds = heldout_feeds(args.samples, args.size)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        old = tmp / "shipped.onnx"
        shutil.copy2(shipped, old)
        if args.reference:
            small = heldout_feeds(2, 48, seed=32)
            arrays = {}
            for i, f in enumerate(small):
                arrays.update({f"{i}/in/{k}": v for k, v in f.items()})
                arrays.update({f"{i}/out/{k}": v for k, v in run_graph(old, f).items()})
            np.savez_compressed(args.reference, **arrays)
            print(f"reference: {args.reference} ({pathlib.Path(args.reference).stat().st_size} bytes)")
        nets, meta = networks_from_weights(wd)
        sample = {k: torch.from_numpy(v) for k, v in feeds[0].items()}
        keep = {k: v for k, v in meta.items() if k not in ("export_check", "graph_outputs", "graph_sha256")}
        report = export_all(nets["pipnet"], nets["pmmnet"], nets["direct"], tmp / "new", sample, extra_meta=keep)
        worst: dict[str, dict[str, float]] = {}
        inside: dict[str, float] = {}  # the full graph's, over the object mask
        for name in SINGLE_SHOT_GRAPHS:
            for f in feeds:
                new, ref = run_graph(tmp / "new" / name, f), run_graph(old, f)
                for k, v in relative_deviation(new, ref).items():
                    worst.setdefault(name, {})[k] = max(worst.get(name, {}).get(k, 0.0), v)
                m = f["mask"][0, 0] > 0
                for k in new:
                    if name == SINGLE_SHOT_GRAPHS[0] and new[k].ndim >= 3 and m.any():
                        d = float(np.abs(new[k] - ref[k])[..., m].max() / np.abs(ref[k]).max())
                        inside[k] = max(inside.get(k, 0.0), d)
        print(json.dumps({"shipped": node_counts(old),
                          **{n: node_counts(tmp / "new" / n) for n in SINGLE_SHOT_GRAPHS}}, indent=1))
        print(json.dumps(worst, indent=1))
        print("within the object mask:", json.dumps(inside))
        bad = {n: {k: v for k, v in d.items() if not v <= TOLERANCE[k]} for n, d in worst.items()}
        if any(bad.values()):
            print(f"NOT re-shipped: outputs beyond their tolerance ({TOLERANCE}): {bad}")
            return 1
        for name in SINGLE_SHOT_GRAPHS:
            shutil.copy2(tmp / "new" / name, wd / name)
        new_meta = json.loads((tmp / "new" / "model.json").read_text())
        new_meta["export_check"]["direct.onnx"] = meta.get("export_check", {}).get("direct.onnx")
        new_meta["graph_sha256"]["direct.onnx"] = graph_sha256(wd / "direct.onnx")  # kept as shipped
        atomic_write_text(wd / "model.json", json.dumps(new_meta, indent=2) + "\n")
        unc_path = wd / "uncertainty.json"
        if unc_path.is_file():
            unc = json.loads(unc_path.read_text())
            unc["graph_sha256"] = graph_sha256(wd / "single_shot.onnx")
            atomic_write_text(unc_path, json.dumps(unc, indent=1) + "\n")
        print("re-shipped:", {n: report[n]["bytes"] for n in SINGLE_SHOT_GRAPHS})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
