"""Single-shot evaluation on sets the analytic model does not describe (issue 23, item 5).

``python -m polrig.models.mismatch --data DIR --out benchmarks/results/single_shot_mismatch_NAME.md``
runs the paper's tables of :func:`polrig.models.evaluate.evaluate` on a ``polrig sim dataset`` folder
made with another material mix (``--materials``) or with interreflections
(``--indirect-samples``), then the coverage of the calibrated single-shot sigma
(:func:`polrig.models.uncertainty_fit.coverage`, plain and mirror-averaged) on the same samples, per
material kind where the set mixes kinds (with the full model's forward L2), and where the
capture's misfit ``r`` (:func:`polrig.models.uncertainty.misfit`) lies against the range the sigma was
calibrated on (``misfit_quantiles`` of ``uncertainty.json``; the fraction of pixels that
:meth:`polrig.models.uncertainty.UncertaintyModel.beyond_calibration` flags). The Markdown is the evaluation's
two tables followed by a coverage table; the JSON holds every number.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
from collections.abc import Sequence

import numpy as np


def _kinds(data_dir) -> tuple[list[str], np.ndarray | None]:
    """``(kind names, kind index per scored sample)`` of a set (None: no ``material_kind``)."""
    from polrig.models.data import lit_samples, load_dataset

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
    from polrig.errors import ConfigError
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
    from polrig.models.uncertainty import calibration_for_graph, how_to_calibrate
    from polrig.models.uncertainty_fit import (
        coverage,
        dataset_samples,
        misfit_quantiles,
    )

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
        from polrig.models.evaluate import forward_l2

        out["per_kind"] = {}
        for k in sorted(set(per_sample.tolist())):
            mine = [s for s, j in zip(plain, per_sample) if j == k]
            out["per_kind"][kinds[k]] = dict(coverage(model, mine), samples=len(mine), full_fwd_l2=float(
                np.mean([forward_l2(s.pred, s.truth, np.asarray(s.mask, bool)) for s in mine])))
    out["misfit"] = misfit_quantiles(plain)
    out["misfit_calibration"] = model.calibration.get("misfit_quantiles")
    if model.misfit_limit is not None:  # the runtime's flag (UncertaintyModel.beyond_calibration)
        out.update(_coverage_by_flag(model, plain))
    return out


def _coverage_by_flag(model, samples) -> dict:
    """Fraction of the unclipped object pixels (per colour) that
    :meth:`~polrig.models.uncertainty.UncertaintyModel.beyond_calibration` flags, and the fraction of
    elements within 2 sigma among the flagged and the other pixels."""
    counts = np.zeros((2, 2))  # [flagged?][inside?] elements
    beyond = n = 0
    for smp in samples:
        sig = model.sigma(smp.pred, smp.s_in, smp.mask, smp.stokes, light_spread=smp.light_spread)
        flag = model.beyond_calibration(smp.pred, smp.s_in, smp.mask, smp.stokes)
        use = np.asarray(smp.mask, bool)[None] & ~np.asarray(smp.clipped, bool)
        beyond += int(np.sum(flag & use))
        n += int(use.sum())
        use = use & np.all(np.isfinite(sig), axis=(1, 2))
        inside = np.abs(np.asarray(smp.pred, np.float64) - smp.truth) <= 2.0 * sig  # (C, 3, 3, H, W)
        for f in (0, 1):
            sel = use & (flag == bool(f))
            k = int(np.sum(inside.transpose(1, 2, 0, 3, 4)[:, :, sel]))
            counts[f] += (k, 9 * int(sel.sum()) - k)
    cov = counts[:, 0] / np.maximum(counts.sum(1), 1)
    return {"beyond_calibration_misfit": beyond / max(n, 1),
            "within_2sigma_flagged": float(cov[1]) if counts[1].sum() else None,
            "within_2sigma_not_flagged": float(cov[0]) if counts[0].sum() else None}


def truth_realizability(data_dir, *, pixels: int = 400, seed: int = 0) -> dict[str, float]:
    """GK pass rate of the set's own true 3x3 blocks under the evaluation's completion
    (:func:`polrig.models.evaluate._realizability`: ``max_min_eigenvalue`` m33, no Cloude filter), over
    the object mask and its lit pixels, averaged over the scored samples. Below 100 % where the
    truth's 4x4 matrix has a circular part (a conductor's or a film's retardance) that a
    completion from the linear block alone cannot restore: the realizability columns of the
    tables are then not a test of physical validity."""
    from polrig.models.data import lit_samples, load_dataset
    from polrig.models.evaluate import _realizability

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
             "| subset | within 2 sigma | worst element | RMS error / RMS sigma | blocks (pixel, colour) |", "|---|---|---|---|---|"]

    def row(name: str, c: dict) -> str:
        per = c["within_2sigma_per_element"]
        flat = [v for r in per for v in r]
        k = int(np.argmin(flat))
        return (f"| {name} | {100 * c['within_2sigma']:.1f} % | m{k // 3}{k % 3} {100 * flat[k]:.1f} % | "
                f"{c['rms_error_over_rms_sigma']:.2f} | {c['pixels']} |")

    lines.append(row("all, one pass", checks["plain"]))
    lines.append(row("all, mirror-averaged", checks["mirror_averaged"]))
    for kind, c in (checks.get("per_kind") or {}).items():
        lines.append(row(f"{kind} ({c['samples']} samples; full model forward L2 {c['full_fwd_l2']:.3f}), one pass", c))
    m = checks["misfit"]
    keys = sorted(m, key=float)
    lines += ["", "Misfit r of the observation (median / 90th / 99th percentile): "
              + " / ".join(f"{m[q]:.3f}" for q in keys)]
    cal = checks.get("misfit_calibration")
    if isinstance(cal, dict):
        lines[-1] += ("; on the calibration sets " + " / ".join(f"{float(cal[q]):.3f}" for q in keys)
                      + f"; {100 * checks.get('beyond_calibration_misfit', float('nan')):.1f} % of the object "
                        f"pixels (per colour) beyond the calibration's 99th percentile "
                        f"(`UncertaintyModel.beyond_calibration`)")
        if checks.get("within_2sigma_flagged") is not None:
            lines[-1] += (f"; within 2 sigma {100 * checks['within_2sigma_flagged']:.1f} % of the flagged pixels' "
                          f"elements, {100 * checks['within_2sigma_not_flagged']:.1f} % of the others")
        lines[-1] += "."
    return "\n".join(lines)


def run(data_dir, out_md, weights_dir=None, *, limit: int | None = None, seed: int = 0,
        sigma_only: bool = False) -> dict:
    """Evaluate ``data_dir`` and write ``out_md`` and its ``.json`` (module docstring).
    ``sigma_only``: keep the tables of the JSON already at ``out_md`` (same set) and redo only
    the sigma checks."""
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.data import read_manifest
    from polrig.models.evaluate import evaluate, markdown_tables, results_paths

    out_md, out_json = results_paths(out_md)
    manifest = read_manifest(data_dir)
    if sigma_only:
        try:
            result = json.loads(out_json.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--sigma-only: no readable earlier result {out_json} ({exc})") from None
        if result.get("manifest") != manifest:
            raise ConfigError(f"--sigma-only: {out_json} is the result of another set than {data_dir}")
    else:
        result = evaluate(data_dir, weights_dir, limit=limit, seed=seed)
    result["sigma"] = sigma_checks(data_dir, weights_dir)
    result["truth_realizability"] = tr = truth_realizability(data_dir)
    mats, trans = manifest.get("materials") or {}, manifest.get("transport") or {}
    what = (f"materials `{mats.get('mix', 'baek')}`, indirect samples {trans.get('indirect_samples', 0)}, "
            f"families {', '.join(manifest.get('families_present') or [])}, seed {manifest.get('seed')}")
    out_md.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_json, json.dumps(result, indent=2, default=str))
    atomic_write_text(out_md, "# Single-shot Mueller reconstruction: mismatched held-out set\n\n"
                      f"Produced by `python -m polrig.models.mismatch` (models/mismatch.py; the tables are "
                      f"models/evaluate.py's, metric definitions in its docstring). Set: {what}.\n\n"
                      + markdown_tables(result) + "\n\n"
                      + f"The set's own truth passes GK under the same completion in {100 * tr['gk']:.1f} % of "
                        f"the blocks ({100 * tr['gk_lit']:.1f} % lit).\n\n"
                      + coverage_markdown(result["sigma"]) + "\n")
    print(coverage_markdown(result["sigma"]))
    return result


def summary_table(results: dict[str, dict]) -> str:
    """One Markdown row per result of :func:`run` (``{set label: result}``): forward Stokes L2
    of the five methods, matrix PSNR of the full model and direct regression, and the sigma's
    coverage (one pass / mirror-averaged)."""
    lines = ["| set | scored | Full model | PIPNet-pBRDF alone | Best-fit pBRDF (GT parameters) | Direct Stokes->MM "
             "| Four-state reference | Matrix PSNR full / direct (dB) | within 2 sigma (one pass / mirror-avg.) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for label, r in results.items():
        m = r["methods"]
        fwd = " | ".join(f"{m[k]['fwd_l2']:.3f}" for k in ("full", "pipnet_pbrdf", "bestfit_pbrdf", "direct", "reference4"))
        sig = r.get("sigma")
        cov = (f"{100 * sig['plain']['within_2sigma']:.1f} % / {100 * sig['mirror_averaged']['within_2sigma']:.1f} %"
               if sig else "")
        lines.append(f"| {label} | {r['samples']} | {fwd} | {m['full']['matrix_psnr']:.2f} / "
                     f"{m['direct']['matrix_psnr']:.2f} | {cov} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.mismatch", description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="a `polrig sim dataset` folder")
    ap.add_argument("--out", help="Markdown file (the JSON goes next to it)")
    ap.add_argument("--summary", nargs="+", metavar="LABEL=JSON",
                    help="instead: print one table row per result JSON of earlier runs")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--limit", type=int, default=None, help="first N samples only")
    ap.add_argument("--sigma-only", action="store_true",
                    help="keep the tables of the earlier result at --out, redo the sigma checks")
    args = ap.parse_args(argv)
    if args.summary:
        return run_main(ap.prog, lambda: print(summary_table(_read_results(args.summary))))
    if not (args.data and args.out):
        ap.error("give --data and --out (or --summary)")
    return run_main(ap.prog, lambda: (run(args.data, args.out, args.weights, limit=args.limit,
                                                   sigma_only=args.sigma_only), 0)[1])


def _read_results(items: Sequence[str]) -> dict[str, dict]:
    from polrig.errors import ConfigError, FormatError

    out = {}
    for item in items:
        label, sep, path = item.partition("=")
        if not sep:
            raise ConfigError(f"--summary {item!r}: give LABEL=PATH.json")
        try:
            out[label] = json.loads(pathlib.Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise FormatError(f"{path}: not a readable result JSON ({exc})") from None
    return out


if __name__ == "__main__":
    sys.exit(main())
