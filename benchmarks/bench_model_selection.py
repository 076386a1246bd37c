"""Lower-order models per pixel (``polrig.solve.model_selection``): false acceptance, RMSE with
and without selection, and the time it adds to the plain reference solve.

``python -m benchmarks model_selection`` (or ``python benchmarks/bench_model_selection.py
[--count N] [--sets ...] [--data DIR] [--out FILE.md]``).

* **Synthetic** (exact forms, one colour, 64x64 pixels per row, 4 states 0/45/90/135, shot and
  read noise): truths of each reduced model (where it holds: the rejection rate is the test's
  level, the RMSE falls), and "full": a reduced block plus a random full-rank perturbation of
  0 to 800 DN (full solve sigma 20-40 DN), the false-acceptance measurement.
* **Simulated sets** (``models/continuum/``'s held-out sets at 64x64, the first ``--count``
  lit samples; frames of 4 states rendered from the truth and sampled with the dataset's
  sensor model, as ``python -m polrig.models.continuum`` makes them): Baek-material scenes
  (``seen_families``), films and depolarizing layers, conductors, dispersive dielectrics,
  interreflections. Object pixels with no clipped sample.

* **Throughput** (``--sizes``, default 64 and 256): a mixed scene, three colours, every pixel
  a random block of one of the six models or an off-model one (as "full" above), 4 states;
  the plain reference solve (compiled), the selection (compiled fits,
  ``polrig/solve/_reduced_kernel.py``) and, at the sizes up to ``--oracle-max`` (default 64),
  the selection with the previous numpy fits (``polrig/solve/_reduced_numpy.py``, the tests'
  oracle), interleaved rounds, medians; pixels/s count pixel-colours; the full-sensor estimate
  is 1224 x 1024 superpixels x 3 colours at the largest size's rate.

Definitions (``polrig/solve/model_selection.py``): a pixel's truth is *detectably off* a model
when its noncentrality ``lambda`` (the truth's distance from the model in the noise metric of
its samples) reaches :func:`~polrig.solve.model_selection.detectable_noncentrality` (the test
rejects with probability 0.95 there); **false acceptance** = the share of the pixels
detectably off every candidate where a reduced model was chosen; **chosen model detectably
wrong** = the share of the pixels given a reduced model whose truth is detectably off that
model. "holds" = the truth within
``lambda < 1`` of some candidate (closer than one noise standard deviation). RMSE in the
sets' normalised units (``x 1000``), over all object pixels and over those subsets. Timing:
the reference solve (compiled kernel) and the selection (compiled fits) of the same samples,
median of ``--rounds`` interleaved rounds, warm, in process.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from polrig.optics.mueller import polarizer_stokes  # noqa: E402
from polrig.solve import chunks  # noqa: E402
from polrig.solve import model_selection as ms  # noqa: E402
from polrig.solve import reduced_models as rm  # noqa: E402
from polrig.solve import reference as ref  # noqa: E402

SIM_SETS = ("seen_families", "film_depolarizing", "conductors", "dispersive", "interreflection_compact")
FOUR = (0, 45, 90, 135)


def noncentrality(truth_blocks: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``(P, n_models)`` distance of each truth from each candidate in the noise metric."""
    return np.stack([rm.fit_model(m, truth_blocks, normal)[1] for m in rm.MODELS], -1)


def thresholds() -> np.ndarray:
    return np.array([ms.detectable_noncentrality(9 - m.n_params) for m in rm.MODELS])


def evaluate(s, meas, var, valid, truth, use, rounds: int, unit: float = 1000.0) -> dict:
    """Solve, select, score the pixels ``use`` ``(C, H, W)`` against ``truth``; time both."""
    t_ref, t_sel = [], []
    ms.select_models(s, meas, var, valid, None,  # warm-up: numba's compiled kernels loaded
                     ref.solve_reference(s, meas, var, valid, dtype=np.float64))
    for _ in range(rounds):  # interleaved
        t0 = time.perf_counter()
        full = ref.solve_reference(s, meas, var, valid, dtype=np.float64)
        t1 = time.perf_counter()
        sel, maps = ms.select_models(s, meas, var, valid, None, full)
        t2 = time.perf_counter()
        t_ref.append(t1 - t0)
        t_sel.append(t2 - t1)
    c, _, _, h, w = truth.shape
    lam_rows, code_rows, err_full, err_sel, cov_full, cov_sel = [], [], [], [], [], []
    for ci in range(c):
        pix = np.flatnonzero((use[ci] & (maps.code[ci] != ms.UNTESTED)).ravel())
        if not pix.size:
            continue
        normal, _, _, _ = ms.normal_equations(s, meas, var, valid, None, ci, pix)
        tb = truth[ci].reshape(9, -1)[:, pix].T
        lam_rows.append(noncentrality(tb, normal))
        code_rows.append(maps.code[ci].ravel()[pix])
        for est, errs, covs in ((full, err_full, cov_full), (sel, err_sel, cov_sel)):
            e = est.mueller[ci].reshape(9, -1)[:, pix].T - tb
            sg = est.sigma[ci].reshape(9, -1)[:, pix].T
            errs.append(e)
            covs.append(np.abs(e) <= 2 * sg + 1e-12)
    lam, code = np.concatenate(lam_rows), np.concatenate(code_rows)
    e_full, e_sel = np.concatenate(err_full), np.concatenate(err_sel)
    thr = thresholds()
    detect = (lam >= thr).all(axis=1)
    chosen = code != 0
    col = {m.code: j for j, m in enumerate(rm.MODELS)}
    lam_chosen = np.array([lam[i, col[c]] if c else 0.0 for i, c in enumerate(code)])
    thr_chosen = np.array([thr[col[c]] if c else np.inf for c in code])
    wrong = chosen & (lam_chosen >= thr_chosen)
    holds = lam.min(axis=1) < 1.0
    rmse = lambda e, m: float(np.sqrt(np.mean(e[m] ** 2)) * unit) if m.any() else float("nan")  # noqa: E731
    every = np.ones(len(code), bool)
    return {
        "pixels": len(code), "accepted": float(np.mean(code != 0)),
        "counts": {name: int(np.sum(code == k)) for k, name in rm.MODEL_CODES.items()},
        "detectable": int(detect.sum()), "holds": int(holds.sum()), "chosen": int(chosen.sum()),
        "chosen_wrong": float(np.mean(wrong[chosen])) if chosen.any() else float("nan"),
        "false_acceptance": float(np.mean(code[detect] != 0)) if detect.any() else float("nan"),
        "rejected_where_holds": float(np.mean(code[holds] == 0)) if holds.any() else float("nan"),
        "rmse_full": rmse(e_full, every), "rmse_sel": rmse(e_sel, every),
        "rmse_full_holds": rmse(e_full, holds), "rmse_sel_holds": rmse(e_sel, holds),
        "rmse_full_detect": rmse(e_full, detect), "rmse_sel_detect": rmse(e_sel, detect),
        "coverage_full": float(np.mean(np.concatenate(cov_full))),
        "coverage_sel": float(np.mean(np.concatenate(cov_sel))),
        "t_ref": float(np.median(t_ref)), "t_sel": float(np.median(t_sel)),
        "solved_pixels": int(c * h * w),
    }


def merge(rows: list[dict]) -> dict:
    """Pool per-sample rows (pixel-weighted means; times summed)."""
    out = {"pixels": sum(r["pixels"] for r in rows), "samples": len(rows)}
    wsum = lambda key, wkey: (sum(r[key] * r[wkey] for r in rows if np.isfinite(r[key]))  # noqa: E731
                              / max(1, sum(r[wkey] for r in rows if np.isfinite(r[key]))))
    out["accepted"] = wsum("accepted", "pixels")
    out["detectable"] = sum(r["detectable"] for r in rows)
    out["chosen"] = sum(r["chosen"] for r in rows)
    out["chosen_wrong"] = wsum("chosen_wrong", "chosen") if out["chosen"] else float("nan")
    out["holds"] = sum(r["holds"] for r in rows)
    out["false_acceptance"] = wsum("false_acceptance", "detectable") if out["detectable"] else float("nan")
    out["rejected_where_holds"] = wsum("rejected_where_holds", "holds") if out["holds"] else float("nan")
    for k in ("full", "sel"):
        out[f"rmse_{k}"] = float(np.sqrt(wsum_sq(rows, f"rmse_{k}", "pixels")))
        out[f"rmse_{k}_holds"] = float(np.sqrt(wsum_sq(rows, f"rmse_{k}_holds", "holds")))
        out[f"rmse_{k}_detect"] = float(np.sqrt(wsum_sq(rows, f"rmse_{k}_detect", "detectable")))
        out[f"coverage_{k}"] = wsum(f"coverage_{k}", "pixels")
    out["counts"] = {n: sum(r["counts"][n] for r in rows) for n in rows[0]["counts"]}
    out["t_ref"] = sum(r["t_ref"] for r in rows)
    out["t_sel"] = sum(r["t_sel"] for r in rows)
    out["solved_pixels"] = sum(r["solved_pixels"] for r in rows)
    return out


def wsum_sq(rows, key, wkey) -> float:
    num = sum(r[key] ** 2 * r[wkey] for r in rows if np.isfinite(r[key]) and r[wkey])
    den = sum(r[wkey] for r in rows if np.isfinite(r[key]) and r[wkey])
    return num / den if den else float("nan")


def synthetic(rounds: int) -> dict[str, dict]:
    rng = np.random.default_rng(2026)
    s = polarizer_stokes(np.radians(FOUR), np.inf)
    out = {}
    h, w = 64, 64
    for name in [m.name for m in rm.MODELS] + ["full"]:
        p = h * w
        if name == "full":
            names = [m.name for m in rm.MODELS]
            base = np.concatenate([rm.random_blocks(rng, names[i % 6], p // 6 + 1, 3000.0)
                                   for i in range(6)])[:p]
            pert = rm.random_blocks(rng, "full", p)
            blocks = base + rng.uniform(0, 800, (p, 1)) * pert / np.linalg.norm(pert, axis=1, keepdims=True)
        else:
            blocks = rm.random_blocks(rng, name, p, 3000.0)
        truth = blocks.reshape(h, w, 3, 3).transpose(2, 3, 0, 1)[None]
        mean = ref.forward_measurements(truth, s)
        var = 4.0 + np.clip(mean, 0, None) / 0.5
        meas = mean + rng.normal(size=mean.shape) * np.sqrt(var)
        out[name] = evaluate(s, meas, var, None, truth, np.ones((1, h, w), bool), rounds, unit=1.0)
        print(f"synthetic {name}: {fmt(out[name])}", flush=True)
    return out


def sim_sets(names, count: int, data: pathlib.Path, rounds: int) -> dict[str, dict]:
    sys.path.insert(0, str(REPO))
    from polrig.models import continuum as cont
    from polrig.models.data import lit_samples, load_dataset
    from polrig.sensor.noise import SensorModel

    out = {}
    for tag, name in enumerate(names):
        d = cont.make_set(data, name, cont.SETS[name][1], count)
        ds = load_dataset(d)
        sensor = SensorModel(**ds.manifest["noise"]["sensor_model"])
        rows = []
        for i in lit_samples(ds):
            zero = np.zeros_like(ds["mueller"][i], dtype=np.float64)
            fr = cont.sample_frames(ds, i, (zero, zero), sensor, np.random.default_rng([7, tag, i]),
                                    offsets=FOUR)
            s, meas, var, valid = cont.stack_states(fr, FOUR)
            use = np.broadcast_to(fr.clean, fr.use.shape) & fr.use
            rows.append(evaluate(s, meas, var, valid, fr.truth, use, rounds))
        out[name] = merge(rows)
        print(f"{name} ({len(rows)} samples): {fmt(out[name])}", flush=True)
    return out


#: superpixels x colours of the rig's sensor (2448 x 2048 DoFP, 2x2 superpixels, RGB)
FULL_SENSOR = 1224 * 1024 * 3


def throughput(sizes, rounds: int, oracle_max: int) -> list[dict]:
    """Pixels/s of the reference solve, the selection and (up to ``oracle_max``) the
    selection with the numpy oracle's fits, on a mixed three-colour scene per size."""
    from polrig.solve._reduced_numpy import fit_model_numpy

    rng = np.random.default_rng(99)
    s = polarizer_stokes(np.radians(FOUR), np.inf)
    names = [m.name for m in rm.MODELS]
    rows = []
    for size in sizes:
        p = 3 * size * size
        base = np.concatenate([rm.random_blocks(rng, names[i % 6], p // 6 + 1, 3000.0)
                               for i in range(6)])[rng.permutation(p)]
        pert = rm.random_blocks(rng, "full", p)
        off = rng.random((p, 1)) < 1 / 7  # about one pixel in seven off every model
        blocks = base + off * rng.uniform(0, 800, (p, 1)) * pert / np.linalg.norm(pert, axis=1, keepdims=True)
        truth = blocks.reshape(3, size, size, 3, 3).transpose(0, 3, 4, 1, 2)
        mean = ref.forward_measurements(truth, s)
        var = 4.0 + np.clip(mean, 0, None) / 0.5
        meas = mean + rng.normal(size=mean.shape) * np.sqrt(var)
        full = ref.solve_reference(s, meas, var, dtype=np.float64)
        ms.select_models(s, meas, var, None, None, full)  # warm-up: compiled kernels loaded
        with_oracle = size <= oracle_max
        times = {"reference": [], "selection": [], "selection (numpy fits)": []}
        for _ in range(rounds):  # interleaved
            t0 = time.perf_counter()
            full = ref.solve_reference(s, meas, var, dtype=np.float64)
            t1 = time.perf_counter()
            _, maps = ms.select_models(s, meas, var, None, None, full)
            t2 = time.perf_counter()
            times["reference"].append(t1 - t0)
            times["selection"].append(t2 - t1)
            if with_oracle:
                compiled = ms.fit_model
                ms.fit_model = fit_model_numpy
                try:
                    t3 = time.perf_counter()
                    _, maps_o = ms.select_models(s, meas, var, None, None, full)
                    times["selection (numpy fits)"].append(time.perf_counter() - t3)
                finally:
                    ms.fit_model = compiled
                same = float(np.mean(maps_o.code == maps.code))
        row = {"size": size, "pixels": p, "accepted": float(np.mean((maps.code != 0) & (maps.code != ms.UNTESTED))),
               "same_codes": same if with_oracle else float("nan")}
        for k, v in times.items():
            if v:
                row[k] = float(np.median(v))
        rows.append(row)
        print(f"throughput {size}x{size}x3: " + ", ".join(
            f"{k} {p / row[k]:.0f} px/s" for k in times if k in row), flush=True)
    return rows


def throughput_markdown(rows: list[dict], rounds: int) -> str:
    text = (f"### Throughput (mixed scene, 3 colours, 4 states; median of {rounds} interleaved rounds, "
            f"warm, in process; {chunks.THREADS} fit threads, {os.cpu_count()} CPUs shared "
            "with other work)\n\n"
            "| size | pixel-colours | accepted | reference solve | selection | selection, numpy fits "
            "(previous) | speed-up | same codes | full sensor (1224x1024x3): reference + selection |\n"
            "|---|---|---|---|---|---|---|---|---|\n")
    def rate(r: dict, k: str) -> str:
        return f"{r['pixels'] / r[k]:,.0f} px/s ({1e3 * r[k]:.0f} ms)" if k in r else "-"

    for r in rows:
        p = r["pixels"]
        old = "selection (numpy fits)"
        speed = f"{r[old] / r['selection']:.1f}x" if old in r else "-"
        same = f"{100 * r['same_codes']:.2f} %" if np.isfinite(r["same_codes"]) else "-"
        sensor = (f"{FULL_SENSOR * r['reference'] / p:.0f} s + "
                  f"{FULL_SENSOR * r['selection'] / p:.0f} s")
        text += (f"| {r['size']}x{r['size']} | {p} | {100 * r['accepted']:.1f} % | {rate(r, 'reference')} | "
                 f"{rate(r, 'selection')} | {rate(r, old)} | {speed} | {same} | {sensor} |\n")
    return text


def fmt(r: dict) -> str:
    return (f"{r['pixels']} px, accepted {100 * r['accepted']:.1f}%, false acceptance "
            f"{100 * r['false_acceptance']:.2f}% of {r['detectable']}, chosen detectably wrong "
            f"{100 * r['chosen_wrong']:.2f}% of {r['chosen']}, RMSE {r['rmse_full']:.3f} -> "
            f"{r['rmse_sel']:.3f} (holds {r['rmse_full_holds']:.3f} -> {r['rmse_sel_holds']:.3f}), "
            f"coverage {100 * r['coverage_full']:.1f} -> {100 * r['coverage_sel']:.1f}%, "
            f"time {1e3 * r['t_ref']:.0f} + {1e3 * r['t_sel']:.0f} ms")


def markdown(syn: dict, sim: dict, args) -> str:
    head = ("| set | pixels | accepted | detectably full | false acceptance | model holds | "
            "rejected where it holds | chosen model detectably wrong | RMSE full -> selected | where a model holds | "
            "where detectably full | within 2 sigma full -> selected | reference solve | selection |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")

    def row(name, r):
        pct = lambda v: "n/a" if not np.isfinite(v) else f"{100 * v:.1f} %"  # noqa: E731
        pair = lambda a, b: "n/a" if not np.isfinite(a) else f"{a:.3f} -> {b:.3f}"  # noqa: E731
        return (f"| {name} | {r['pixels']} | {pct(r['accepted'])} | {r['detectable']} | "
                f"{pct(r['false_acceptance'])} | {r['holds']} | {pct(r['rejected_where_holds'])} | "
                f"{pct(r['chosen_wrong'])} | "
                f"{pair(r['rmse_full'], r['rmse_sel'])} | {pair(r['rmse_full_holds'], r['rmse_sel_holds'])} | "
                f"{pair(r['rmse_full_detect'], r['rmse_sel_detect'])} | "
                f"{100 * r['coverage_full']:.1f} -> {100 * r['coverage_sel']:.1f} % | "
                f"{1e3 * r['t_ref']:.0f} ms | {1e3 * r['t_sel']:.0f} ms |\n")

    text = ("### Synthetic truths (64x64, one colour, m00 1500-3000 DN; RMSE in DN)\n\n"
            + head)
    text += "".join(row(k, v) for k, v in syn.items())
    if sim:
        text += (f"\n### Simulated held-out sets (64x64, {args.count} samples each, object pixels "
                 "unclipped in every state; RMSE x 1000 in normalised units)\n\n" + head)
        text += "".join(row(k, v) for k, v in sim.items())
        counts = "\n".join(f"- {k}: " + ", ".join(f"{n} {c}" for n, c in v["counts"].items() if c)
                           for k, v in sim.items())
        text += "\nChosen models (pixels over colours):\n\n" + counts + "\n"
    return text


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=4, help="samples per simulated set (default 4)")
    ap.add_argument("--sets", nargs="*", default=list(SIM_SETS), help="simulated sets (none: synthetic only)")
    ap.add_argument("--rounds", type=int, default=3, help="timing rounds (default 3)")
    ap.add_argument("--sizes", nargs="*", type=int, default=[64, 256],
                    help="throughput scene sizes (default 64 256; none: skip)")
    ap.add_argument("--oracle-max", type=int, default=64,
                    help="time the numpy fits (the oracle) up to this size (default 64)")
    ap.add_argument("--data", type=pathlib.Path, default=None,
                    help="folder of the generated sets (default: a temporary folder)")
    ap.add_argument("--out", type=pathlib.Path, default=None,
                    help="write the tables to this markdown file (e.g. benchmarks/results/model_selection.md)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    thr = throughput(args.sizes, args.rounds, args.oracle_max) if args.sizes else []
    syn = synthetic(args.rounds)
    with tempfile.TemporaryDirectory() as tmp:
        sim = sim_sets(args.sets, args.count, args.data or pathlib.Path(tmp), args.rounds) if args.sets else {}
    table = (throughput_markdown(thr, args.rounds) + "\n" if thr else "") + markdown(syn, sim, args)
    print("\n" + table)
    print(f"{time.perf_counter() - t0:.0f} s on {os.cpu_count()} CPUs")
    if args.out:
        from polrig.atomic import atomic_write_text

        atomic_write_text(args.out, "# Lower-order models per pixel: false acceptance, RMSE, time\n\n"
                          f"`python benchmarks/bench_model_selection.py --count {args.count} --rounds "
                          f"{args.rounds} --sizes {' '.join(map(str, args.sizes))} --oracle-max "
                          f"{args.oracle_max} --out {args.out}` ({os.cpu_count()} CPUs shared with other "
                          "work; definitions in the benchmark's docstring; warm, in process).\n\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
