"""Where does the single-shot error come from? A geometry ladder on a held-out set.

``python -m polrig.models.diagnose --data DIR [--weights DIR]`` (needs the ``train`` extra: the
analytic pBRDF and the gain fit are the training graph's own torch functions) runs the shipped
graph on every sample and prints, per shape family:

* PIPNet's geometry error: median angle (deg) between predicted and true unit normals over the
  object mask, and between the mean predicted and mean true light direction ``wi``;
* the forward Stokes relative L2 (:mod:`polrig.models.evaluate`, 11 held-out incident states) of the
  pBRDF initialization with the radiometric gains fitted to the one observed state
  (:func:`polrig.models.pmmnet.fit_gains`, i.e. what an untrained PMMNet returns) on a ladder of
  geometries: PIPNet's normal and light; the true normal with PIPNet's light; PIPNet's normal
  with the true light; the true normal and light (eta = 1.5, as the network assumes); and the
  true normal, light and index of refraction; and the light direction fitted by
  :func:`polrig.models.light_fit.fit_light_direction` on PIPNet's and on the true normals (with its
  angular error), which shows whether physics can recover the light once the normals are right;
* the two diffuse shape-from-polarization candidates of every pixel
  (:func:`polrig.models.pipnet.sfp_candidates`) with the true light, the candidate chosen by an
  oracle (the one nearer the true normal) and by Lambertian shading
  (:func:`polrig.models.light_fit.shading_pick`: the one whose ``max(n.wi, 0)`` times one global
  albedo explains the intensity better), each with its median normal error: how good the
  polarization's own normals are, and what choosing between them costs;
* the full model's and the direct baseline's forward L2 for comparison.

The rungs separate what the analytic model could do with perfect geometry from what the
geometry network delivers: the gap between the last rungs and the full model is the error that
better normals and light directions would remove.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from polrig.errors import ConfigError
from polrig.models.data import check_network_size, lit_samples, load_dataset
from polrig.models.evaluate import forward_l2, network_inputs
from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
from polrig.sim.scene import FAMILIES

RUNGS = ("pip_n+pip_wi", "true_n+pip_wi", "pip_n+true_wi", "pip_n+fit_wi", "true_n+fit_wi", "true_n+true_wi",
         "true_n+true_wi+true_eta", "sfp_oracle_n+true_wi", "sfp_shading_n+true_wi")


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = a / np.maximum(np.linalg.norm(a, axis=0, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=0, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, 0), -1.0, 1.0)))


def gain_fitted_pbrdf(normal, wi, sample: dict, eta: float = 1.5) -> np.ndarray:
    """The pBRDF on the given geometry (``(3, H, W)`` camera-frame arrays) with the gains fitted
    to the sample's observed Stokes -> Mueller image ``(C, 3, 3, H, W)``."""
    import torch

    from polrig.models.layers import stokes_from_analyzer
    from polrig.models.pbrdf_torch import image_blocks
    from polrig.models.pmmnet import gain_fitted_initialization

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]  # noqa: E731
    mask = t(sample["mask"])[:, None]
    with torch.no_grad():
        ms, md = image_blocks(t(normal), t(wi), t(sample["wo"]), t(np.asarray([sample["alpha"]]))[0],
                              t(sample["stage_zero_axis"]), eta=eta)
        stokes = stokes_from_analyzer(t(sample["analyzer"]))
        _, _, m = gain_fitted_initialization(stokes, ms, md, torch.ones_like(stokes[:, :, 0]), t(sample["s_in"]))
    return (m * mask[:, :, None, None])[0].numpy()


def fitted_light(normal, sample: dict, pool: int = 2) -> np.ndarray:
    """:func:`polrig.models.light_fit.fit_light_direction` on the given normals -> unit ``(3,)``."""
    import torch

    from polrig.models.layers import stokes_from_analyzer
    from polrig.models.light_fit import (
        fibonacci_directions,
        fit_light_direction,
        local_offsets,
    )

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]  # noqa: E731
    with torch.no_grad():
        w = fit_light_direction(stokes_from_analyzer(t(sample["analyzer"])), t(normal), t(sample["wo"]),
                                torch.tensor([float(sample["alpha"])]), t(sample["s_in"]), t(sample["stage_zero_axis"]),
                                t(sample["mask"])[:, None], candidates=fibonacci_directions(400, 0.3),
                                offsets=local_offsets(8.0), pool=pool)
    return w[0].numpy()


def sfp_geometries(sample: dict, normal: np.ndarray, wi: np.ndarray,
                   mask: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Geometries ``{rung: (normal (3, H, W), wi (3, H, W))}`` from the sample's own
    polarization under the true light ``wi``: its shape-from-polarization candidates chosen per
    pixel by an oracle (the one nearer the true ``normal``) and by Lambertian shading
    (:func:`polrig.models.light_fit.shading_pick`)."""
    import torch

    from polrig.models.layers import stokes_from_analyzer
    from polrig.models.light_fit import shading_pick
    from polrig.models.pipnet import sfp_candidates

    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))[None]  # noqa: E731
    with torch.no_grad():
        stokes = stokes_from_analyzer(t(sample["analyzer"]))
        plus, minus = sfp_candidates(stokes, t(sample["wo"]))
        oracle = torch.where(((plus - minus) * t(normal)).sum(1, keepdim=True) >= 0, plus, minus)
        shading = shading_pick(plus, minus, t(wi), stokes[:, :, 0].mean(1), torch.from_numpy(mask)[None])
    return {"sfp_oracle_n+true_wi": (oracle[0].numpy(), wi), "sfp_shading_n+true_wi": (shading[0].numpy(), wi)}


def diagnose(data_dir, weights_dir=None, limit: int | None = None, echo=print) -> dict:
    """Run the ladder (module docstring); returns ``{family: {metric: mean}}`` and prints a table."""
    ds = load_dataset(data_dir, limit)
    check_network_size(ds, data_dir)
    lit = lit_samples(ds)  # as polrig.models.evaluate: a sample without a lit object pixel has no signal
    if not lit:
        raise ConfigError(f"{data_dir}: no sample with a lit object pixel ({len(ds)} sample(s), nothing to diagnose)")
    wd = pathlib.Path(weights_dir) if weights_dir is not None else WEIGHTS_DIR
    full = SingleShotModel.load(wd)
    direct = SingleShotModel.load(wd, graph="direct.onnx") if (wd / "direct.onnx").is_file() else None
    eta = ds.arrays.get("eta")  # the true index of refraction, where the set records it
    rows: dict[str, list[dict[str, float]]] = {}
    for i in lit:
        mask = ds["mask"][i] > 0
        truth = ds["mueller"][i]
        out = full.run_rig_frame(*network_inputs(ds, i))
        sample = {k: ds[k][i] for k in ("analyzer", "mask", "wo", "alpha", "stage_zero_axis", "s_in")}
        n_pip, w_pip = out["normal"][0], out["wi"][0]
        n_true, w_true = ds["normal"][i], ds["wi"][i]
        r = {"normal_err_deg": float(np.median(_angle_deg(n_pip, n_true)[mask])),
             "light_err_deg": float(_angle_deg(w_pip[:, mask].mean(1)[:, None], w_true[:, mask].mean(1)[:, None])[0]),
             "full": forward_l2(out["mueller"][0], truth, mask)}
        if direct is not None:
            r["direct"] = forward_l2(direct.run_rig_frame(*network_inputs(ds, i), rotate_with=out["wi"])["mueller"][0],
                                     truth, mask)
        mean_true = w_true[:, mask].mean(1)[:, None]
        fits = {}
        for name, n in (("pip_n", n_pip), ("true_n", n_true)):
            w = fitted_light(n, sample)
            r[f"fit_light_{name}_err_deg"] = float(_angle_deg(w[:, None], mean_true)[0])
            fits[name] = np.broadcast_to(w[:, None, None], n_true.shape)
        geometry = {"pip_n+pip_wi": (n_pip, w_pip, 1.5), "true_n+pip_wi": (n_true, w_pip, 1.5),
                    "pip_n+true_wi": (n_pip, w_true, 1.5), "pip_n+fit_wi": (n_pip, fits["pip_n"], 1.5),
                    "true_n+fit_wi": (n_true, fits["true_n"], 1.5), "true_n+true_wi": (n_true, w_true, 1.5)}
        if eta is not None:
            geometry["true_n+true_wi+true_eta"] = (n_true, w_true, float(eta[i]))
        for rung, (n, w) in sfp_geometries(sample, n_true, w_true, mask).items():
            geometry[rung] = (n, w, 1.5)
            r[f"{rung.split('_n+')[0]}_err_deg"] = float(np.median(_angle_deg(n, n_true)[mask]))
        for rung, (n, w, e) in geometry.items():
            r[rung] = forward_l2(gain_fitted_pbrdf(n, w, sample, e), truth, mask)
        family = FAMILIES[int(ds["family"][i])] if "family" in ds.arrays else "all"
        if family != "all":
            rows.setdefault(family, []).append(r)
        rows.setdefault("all", []).append(r)
    result = {f: dict({k: float(np.mean([r[k] for r in rs])) for k in rs[0]}, samples=len(rs)) for f, rs in rows.items()}
    echo(markdown(result))
    return result


def markdown(result: dict) -> str:
    keys = ["normal_err_deg", "light_err_deg", "fit_light_pip_n_err_deg", "fit_light_true_n_err_deg",
            "sfp_oracle_err_deg", "sfp_shading_err_deg", *RUNGS, "full", "direct"]
    keys = [k for k in keys if k in result["all"]]
    lines = ["| family | samples | " + " | ".join(keys) + " |", "|" + "---|" * (len(keys) + 2)]
    for f, r in sorted(result.items(), key=lambda kv: kv[0] == "all"):
        lines.append(f"| {f} | {r['samples']} | " + " | ".join(
            f"{r[k]:.1f}" if k.endswith("_deg") else f"{r[k]:.4f}" for k in keys) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from polrig.formats.argcheck import int_range
    from polrig.models._cli import run_main

    p = argparse.ArgumentParser(prog="python -m polrig.models.diagnose", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="dataset folder (`polrig sim dataset` output)")
    p.add_argument("--weights", default=None, help="folder with single_shot.onnx (default: shipped)")
    p.add_argument("--limit", type=int_range(1, 10**9), default=None, help="use at most the first this many samples")
    p.add_argument("--json", default=None, help="also write the numbers here (a file in an existing folder)")
    args = p.parse_args(argv)
    return run_main(p.prog, lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    from polrig.atomic import atomic_write_text
    from polrig.formats.argcheck import check_output_file

    if args.json:
        check_output_file(pathlib.Path(args.json), "--json")  # before the work
    result = diagnose(args.data, args.weights, args.limit)
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
