"""Single-shot evaluation on sets the analytic model does not describe (issue 23, item 5).

``python -m models.mismatch --data DIR --out benchmarks/results/single_shot_mismatch_NAME.md``
runs the paper's tables of :func:`models.evaluate.evaluate` on a ``polrig sim dataset`` folder
made with another material mix (``--materials``) or with interreflections
(``--indirect-samples``), then the coverage of the calibrated single-shot sigma
(:func:`models.uncertainty_fit.coverage`, plain and mirror-averaged) on the same samples, per
material kind where the set mixes kinds, and where the capture's misfit ``r``
(:func:`models.uncertainty.misfit`) lies against the range the sigma was calibrated on
(``misfit_quantiles`` of ``uncertainty.json``, when recorded). The Markdown is the evaluation's
two tables followed by a coverage table; the JSON holds every number.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

import numpy as np

#: Quantiles of the misfit ``r`` reported per set (and recorded for the calibration sets).
MISFIT_QUANTILES = (0.5, 0.9, 0.99)


def misfit_values(samples) -> np.ndarray:
    """The misfit ``r`` of every unclipped object pixel and colour of
    :class:`models.uncertainty_fit.Sample` s (``(N,)``, finite values only)."""
    from models.uncertainty import features, misfit, observed_frame_rotation, to_observed_frame

    out = []
    for s in samples:
        rot, _ = observed_frame_rotation(s.s_in)
        pred = np.asarray(s.pred, np.float64)
        scale, _ = features(to_observed_frame(pred, rot), s.mask)
        r = misfit(pred, s.s_in, np.asarray(s.stokes, np.float64), scale)
        use = np.asarray(s.mask, bool)[None] & ~np.asarray(s.clipped, bool) & np.isfinite(r)
        out.append(r[use])
    return np.concatenate(out) if out else np.zeros(0)


def _kinds(data_dir) -> tuple[list[str], np.ndarray | None]:
    """``(kind names, kind index per scored sample)`` of a set (None: no ``material_kind``)."""
    from models.data import lit_samples, load_dataset

    ds = load_dataset(data_dir)
    kinds = list((ds.manifest.get("materials") or {}).get("kinds") or [])
    if "material_kind" not in ds.arrays or not kinds:
        return kinds, None
    return kinds, np.asarray(ds["material_kind"])[lit_samples(ds)]


def sigma_checks(data_dir, weights_dir=None) -> dict:
    """Coverage of the shipped sigma on a set: ``{"plain": ..., "mirror_averaged": ...,
    "per_kind": {kind: coverage}, "misfit": {quantile: r}, "misfit_calibration": {...} or None,
    "beyond_calibration_misfit": fraction of pixels whose r exceeds the calibration's 99th
    percentile}``."""
    from models.runtime import WEIGHTS_DIR, SingleShotModel
    from models.uncertainty import calibration_for_graph, how_to_calibrate
    from models.uncertainty_fit import coverage, dataset_samples
    from polrig.errors import ConfigError

    wd = pathlib.Path(weights_dir) if weights_dir is not None else WEIGHTS_DIR
    model, why = calibration_for_graph(wd, "single_shot.onnx")
    if model is None:
        raise ConfigError(f"{why}; {how_to_calibrate(wd)}")
    net = SingleShotModel.load(wd)
    plain = dataset_samples(data_dir, net)
    out = {"plain": coverage(model, plain),
           "mirror_averaged": coverage(model, dataset_samples(data_dir, net, mirror_average=True))}
    kinds, per_sample = _kinds(data_dir)
    if per_sample is not None and len(set(per_sample.tolist())) > 1:
        out["per_kind"] = {kinds[k]: coverage(model, [s for s, j in zip(plain, per_sample) if j == k])
                           for k in sorted(set(per_sample.tolist()))}
    r = misfit_values(plain)
    out["misfit"] = {str(q): float(np.quantile(r, q)) for q in MISFIT_QUANTILES}
    cal = model.calibration.get("misfit_quantiles")
    out["misfit_calibration"] = cal
    if isinstance(cal, dict) and "0.99" in cal:
        out["beyond_calibration_misfit"] = float(np.mean(r > float(cal["0.99"])))
    return out


def truth_realizability(data_dir, *, pixels: int = 400, seed: int = 0) -> dict[str, float]:
    """GK pass rate of the set's own true 3x3 blocks under the evaluation's completion
    (:func:`models.evaluate._realizability`: ``max_min_eigenvalue`` m33, no Cloude filter), over
    the object mask and its lit pixels, averaged over the scored samples. Below 100 % where the
    truth's 4x4 matrix has a circular part (a conductor's or a film's retardance) that a
    completion from the linear block alone cannot restore: the realizability columns of the
    tables are then not a test of physical validity."""
    from models.data import lit_samples, load_dataset
    from models.evaluate import _realizability

    ds = load_dataset(data_dir)
    rng = np.random.default_rng(seed)
    rows = []
    for i in lit_samples(ds):
        mask, lit = ds["mask"][i] > 0, ds["lit"][i] > 0
        rows.append({"gk": _realizability(ds["mueller"][i], mask, rng, pixels, filtered=False)["gk_before"],
                     "gk_lit": _realizability(ds["mueller"][i], mask & lit, rng, pixels,
                                              filtered=False).get("gk_before", float("nan"))})
    return {k: float(np.nanmean([r[k] for r in rows])) for k in ("gk", "gk_lit")}


def coverage_markdown(checks: dict) -> str:
    """The coverage section of the Markdown (:func:`sigma_checks`)."""
    lines = ["Calibrated single-shot sigma (models/uncertainty.py, the shipped uncertainty.json), "
             "fraction of elements within 2 sigma (target 95.45 %):", "",
             "| subset | within 2 sigma | worst element | RMS error / RMS sigma | values |", "|---|---|---|---|---|"]

    def row(name: str, c: dict) -> str:
        per = c["within_2sigma_per_element"]
        flat = [v for r in per for v in r]
        k = int(np.argmin(flat))
        return (f"| {name} | {100 * c['within_2sigma']:.1f} % | m{k // 3}{k % 3} {100 * flat[k]:.1f} % | "
                f"{c['rms_error_over_rms_sigma']:.2f} | {c['pixels']} |")

    lines.append(row("all, one pass", checks["plain"]))
    lines.append(row("all, mirror-averaged", checks["mirror_averaged"]))
    for kind, c in (checks.get("per_kind") or {}).items():
        lines.append(row(f"{kind}, one pass", c))
    m = checks["misfit"]
    lines += ["", "Misfit r of the observation (median / 90th / 99th percentile): "
              + " / ".join(f"{m[str(q)]:.3f}" for q in MISFIT_QUANTILES)]
    cal = checks.get("misfit_calibration")
    if isinstance(cal, dict):
        lines[-1] += (f"; on the calibration sets " + " / ".join(f"{float(cal[str(q)]):.3f}" for q in MISFIT_QUANTILES)
                      + f"; {100 * checks.get('beyond_calibration_misfit', float('nan')):.1f} % of the values "
                        f"beyond the calibration's 99th percentile.")
    return "\n".join(lines)


def run(data_dir, out_md, weights_dir=None, *, limit: int | None = None, seed: int = 0) -> dict:
    """Evaluate ``data_dir`` and write ``out_md`` and its ``.json`` (module docstring)."""
    from models.evaluate import evaluate, markdown_tables, results_paths
    from models.data import read_manifest
    from polrig.rawio import atomic_write_text

    out_md, out_json = results_paths(out_md)
    manifest = read_manifest(data_dir)
    result = evaluate(data_dir, weights_dir, limit=limit, seed=seed)
    result["sigma"] = sigma_checks(data_dir, weights_dir)
    result["truth_realizability"] = tr = truth_realizability(data_dir)
    mats, trans = manifest.get("materials") or {}, manifest.get("transport") or {}
    what = (f"materials `{mats.get('mix', 'baek')}`, indirect samples {trans.get('indirect_samples', 0)}, "
            f"families {', '.join(manifest.get('families_present') or [])}, seed {manifest.get('seed')}")
    out_md.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_json, json.dumps(result, indent=2, default=str))
    atomic_write_text(out_md, "# Single-shot Mueller reconstruction: mismatched held-out set\n\n"
                      f"Produced by `python -m models.mismatch` (models/mismatch.py; the tables are "
                      f"models/evaluate.py's, metric definitions in its docstring). Set: {what}.\n\n"
                      + markdown_tables(result) + "\n\n"
                      + f"The set's own truth passes GK under the same completion in {100 * tr['gk']:.1f} % of "
                        f"the blocks ({100 * tr['gk_lit']:.1f} % lit).\n\n"
                      + coverage_markdown(result["sigma"]) + "\n")
    print(coverage_markdown(result["sigma"]))
    return result


def main(argv: Sequence[str] | None = None) -> int:
    from models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m models.mismatch", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a `polrig sim dataset` folder")
    ap.add_argument("--out", required=True, help="Markdown file (the JSON goes next to it)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--limit", type=int, default=None, help="first N samples only")
    args = ap.parse_args(argv)
    return run_main(ap.prog, lambda: (run(args.data, args.out, args.weights, limit=args.limit), 0)[1])


if __name__ == "__main__":
    sys.exit(main())
