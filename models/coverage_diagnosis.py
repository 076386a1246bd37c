"""Where the one-state sigma misses, element by element: ``python -m polrig.models.coverage_diagnosis``.

Issue 33 asks for 93-97 % of the elements within 2 sigma on every set at every number of states.
At one state the sets spread wider than that band (``benchmarks/results/continuum.md``): the
terrains below, the compact and seen sets above. This tool shows where, on the first ``--count``
lit samples of each set (the held-out sets and the uncertainty calibration's scenes of
:mod:`polrig.models.continuum`, ``SETS`` and ``SEARCH_SETS``, 64x64, the same frames as there):

* **Per element** (the rig's frame), the share of errors within 2 sigma of the single-shot
  estimate, of the hybrid at the seen state alone and of the hybrid at two states 0/90 deg
  (:func:`polrig.solve.hybrid.solve_hybrid`, the calibration's joint prior).
* **Per row of M**, the network's error energy along the seen state's direction ``u``
  (``u = s_0 / |s_0|``: the one direction of each row the frame measures), as a share of the
  row's, against the share the diagonal calibrated sigma gives it. The hybrid keeps the row's
  whole calibrated variance in the plane ``u`` leaves open, which holds where the network's
  error along ``u`` is small (:mod:`polrig.solve.hybrid`, "An observation must never count
  twice"); where it is not, the hybrid's estimate loses that part of the error and its sigma
  does not.
* **A what-if of the light factor** (:mod:`polrig.models.uncertainty`, "The network's certainty
  of the light"): the whole image's sigma is multiplied by ``clip(omega, low, high) /
  reference``, which stops growing at ``high``. Here the first row's factor alone grows on to
  each of ``--knees`` (deg), the other rows' as shipped, and the coverage of both estimates is
  scored again. The first row is the one the light sets: in Baek's diffuse term the block is
  ``x y^T`` with ``y`` the transmission into the surface, set by the light's direction, and
  ``x`` the transmission out, set by the view (:mod:`polrig.solve.diffuse_geometry`).

* **A what-if of the seen direction's share** (:mod:`polrig.solve.hybrid`, "The seen
  direction's share"): the one-state hybrid with the share ``kappa`` of each row's variance along
  ``u`` kept in its unobserved plane, on a grid from 1 (as shipped) to 0 (the plain marginal),
  and with the share per row *fitted on the calibration scenes* (:data:`polrig.models.continuum.SEARCH_SETS`,
  when the run holds them): where the one-state posterior's coverage of the row equals the
  single-shot sigma's on the same pixels (:func:`fit_seen_share`: linear between the grid's
  points; at one state each row's posterior depends on its own share alone), so that the seen
  frame narrows the sigma by what it takes off the error and no more. Every set is then scored
  again at that share.

* **A what-if of the prior's scale from the innovations** (:mod:`polrig.solve.prior_scale`):
  at two, three and four states the prior's sigma times ``c ** gamma``, ``c`` the image's own
  scale from the states after the seen one, on a grid of ``gamma`` at two states (0: the sigma as
  calibrated) and at 0 and :data:`polrig.solve.prior_scale.SHRINK` at three and four; ``gamma`` is
  fitted on the calibration scenes (when the run holds them) where two states cover 95.45 % there.

* **A what-if of the open direction's scale from the diffuse completion** (2026-11-30): at two
  states the hybrid's posterior along the direction ``u`` they leave open is the prior's, and
  nothing the states measure checks it (the innovations above see only the observed
  directions). Where the diffuse test accepts, the completion (fitted without the network's
  normals as its guess, so that it does not lean on the prior) predicts ``m_r . u`` from the
  geometry; ``f_u`` is the quantile scale of the completion less the hybrid along ``u`` against
  the hybrid's own posterior variance there (:mod:`polrig.solve.open_scale`). The hybrid is then
  solved again with the prior's standard deviation along ``u`` times ``max(f_u, 1) ** g`` (it
  widens, never narrows: :mod:`polrig.solve.open_scale`)
  (``solve_hybrid(open_factor=...)``, as captures do with ``--prior-scale geometry``), for each
  exponent ``g`` of :data:`OPEN_EXPONENTS` (0: the innovations' scale alone); scored over all
  elements, with the spread of the samples' own coverage (the 10th-90th percentile). The
  exponent is chosen on the calibration scenes (when the run holds them) by the samples' own
  coverage, not the pooled one (that is 95.45 % at ``g = 0`` by the innovations' own fit): the
  grid's ``g`` of least mean squared distance of each sample's coverage from 95.45 %
  (:func:`fit_open_exponent`), each sample a scene; captures take it as
  :data:`polrig.solve.open_scale.EXPONENT`.

Every table here but the open direction's solves with the sigma as calibrated
(``continuum.estimate``'s ``prior_scale`` False): it is the diagnosis that led to the scale
captures now take by default, and its what-if applies the scale itself; the open direction's
starts from the sigma as captures scale it.

``--rig-scenes``: the default rig's named scenes at its analyzer grid instead, one sample per
turntable angle (:func:`polrig.models.continuum.rig_set`, the frames of ``--rig``).

Prints the tables and writes ``--out`` (Markdown, the numbers next to it as ``.json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time
from collections.abc import Sequence

import numpy as np

from polrig.models import continuum as cn
from polrig.models.scene_bootstrap import coverage_interval, scene_spread
from polrig.solve.prior_scale import SHRINK, innovation_scale, innovations

#: The what-if's knees of the first row's light factor (deg); the shipped knee first.
KNEES_DEG = (None, 11.5, 17.2)
METHODS = {"single": ("single", (0,)), "hybrid1": ("hybrid", (0,)), "hybrid2": ("hybrid", cn.RIG_TWO)}
#: The what-if's shares of the seen direction's variance kept (the shipped 1 first).
SEEN_SHARES = (1.0, 0.8, 0.6, 0.4, 0.2, 0.0)
LABELS = {"single": "single-shot", "hybrid1": "hybrid 1", "hybrid2": "hybrid 2"}
#: The what-if's exponents of the prior's scale from the innovations at two states (0: the sigma as calibrated).
SCALE_SHRINKS = tuple(sorted({0.0, 0.25, 0.5, 0.75, 1.0, SHRINK}))
#: The states of that what-if by their number (the seen state first).
SCALED_STATES = {"2": cn.RIG_TWO, "3": cn.RIG_THREE, "4": cn.FOUR_STATES}
#: The open direction's what-if: exponents of its scale from the diffuse completion (0: as shipped).
OPEN_EXPONENTS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25)


def _knee_key(knee_deg: float | None) -> str:
    return "shipped" if knee_deg is None else f"{knee_deg:g}"


def _frames(data_dir, net, count: int, tag: int, seed: int):
    """The frames (:func:`polrig.models.continuum.sample_frames`) and light spread (rad) of the
    first ``count`` lit samples of the set in ``data_dir``; ``tag`` and ``seed`` draw the frames'
    noise as :func:`polrig.models.continuum.evaluate_set` does."""
    for n, (ds, sensor, i, prior) in enumerate(cn.set_samples(data_dir, net)):
        if n >= count:
            break
        yield cn.sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i])), prior[2]


def _row_counts(fr, mueller, sigma, solved) -> np.ndarray:
    """Per row of ``M``, ``[elements within 2 sigma, elements]`` ``(3, 2)`` over the scored pixels."""
    inside = (np.abs(mueller - fr.truth) <= 2.0 * sigma).transpose(1, 2, 0, 3, 4)[:, :, fr.use & solved]
    return np.stack([inside.reshape(3, -1).sum(axis=1), np.full(3, inside[0].size)], axis=1).astype(float)


def share_coverage(data_dir, net, count: int, tag: int, shares: Sequence[Sequence[float]], seed: int = 0
                   ) -> list[list[list[float]]]:
    """Per share vector of ``shares`` (``(3,)`` each, per row), the one-state hybrid's
    ``[within 2 sigma, elements]`` per row ``(3, 2)`` on the first ``count`` lit samples of the
    set in ``data_dir`` (the calibration's joint prior, the shipped sigma)."""
    counts = np.zeros((len(shares), 3, 2))
    correlation = net.uncertainty.joint_correlation
    for fr, _ in _frames(data_dir, net, count, tag, seed):
        for j, share in enumerate(shares):
            counts[j] += _row_counts(fr, *cn.estimate(fr, (0,), "hybrid", correlation, seen_share=share))
    return counts.tolist()


def fit_seen_share(grid_counts: dict[str, list], single_counts: np.ndarray,
                   shares: Sequence[float] = SEEN_SHARES) -> list[float]:
    """Per row of ``M``, the share ``kappa_r`` at which the one-state hybrid's coverage of the row
    equals the single-shot sigma's on the same pixels (``single_counts`` ``(3, 2)``), from its
    coverage at each of ``shares`` (``grid_counts[str(share)]`` ``(3, 2)``, the counts pooled over
    the calibration scenes; the coverage falls with the share): linear between the grid's points,
    clipped to ``[0, 1]``."""
    order = np.argsort(shares)
    x = np.asarray(shares, float)[order]
    out = []
    for row in range(3):
        cov = np.array([grid_counts[str(float(k))][row][0] / grid_counts[str(float(k))][row][1] for k in x])
        target = single_counts[row][0] / single_counts[row][1]
        out.append(float(np.clip(np.interp(target, cov, x), 0.0, 1.0)) if np.all(np.diff(cov) >= 0)
                   else float(x[np.argmin(np.abs(cov - target))]))
    return out


def diagnose_set(data_dir, net, count: int, tag: int, knees_deg: Sequence[float | None] = KNEES_DEG,
                 seed: int = 0, shares: Sequence[float] = SEEN_SHARES) -> dict:
    """The diagnoses (module docstring) on the first ``count`` lit samples of the set in
    ``data_dir``: ``inside`` and ``elements`` ``(3, 3)`` per method (the shipped sigma), per row
    the error energy along ``u`` and in all (``u_error``, ``error``) and the diagonal sigma's
    (``u_sigma``, ``sigma``), per knee and method the first row's and all elements' counts, and
    the light spreads (deg), and per share of ``shares`` (all rows alike) the one-state hybrid's
    per row (``seen_share``) and the single-shot's per row (``single_rows``) ``[within 2 sigma,
    elements]``, and per number of states of :data:`SCALED_STATES` the hybrid's ``[within 2 sigma,
    elements]`` at each exponent of the prior's scale from the innovations (``prior_scale``,
    :func:`scaled_counts`) and each sample's raw scale (``raw_scales``). ``tag`` and ``seed``
    draw the frames' noise as :func:`polrig.models.continuum.evaluate_set` does."""
    model = net.uncertainty
    if model.spread is None:
        from polrig.errors import ConfigError

        raise ConfigError("the calibrated sigma has no light-spread factor (an older calibration)")
    per = {m: {"inside": np.zeros((3, 3)), "elements": np.zeros((3, 3))} for m in METHODS}
    rows = {k: np.zeros(3) for k in ("u_error", "error", "u_sigma", "sigma")}
    what_if = {_knee_key(k): {m: np.zeros(4) for m in METHODS} for k in knees_deg}
    spreads: list[float] = []
    correlation = model.joint_correlation
    seen_share = np.zeros((len(shares), 3, 2))
    single_rows = np.zeros((3, 2))
    scaled = {n: {str(g): np.zeros(2) for g in (SCALE_SHRINKS if n == "2" else (0.0, SHRINK))} for n in SCALED_STATES}
    raw_scales: dict[str, list[float]] = {n: [] for n in SCALED_STATES}
    opened: dict[str, list] = {str(g): [] for g in OPEN_EXPONENTS}
    open_psnr: dict[str, list] = {str(g): [] for g in OPEN_EXPONENTS}
    open_scales: list[float] = []
    for fr, omega in _frames(data_dir, net, count, tag, seed):
        open_scales.append(open_scale_counts(fr, correlation, OPEN_EXPONENTS, opened, open_psnr))
        for n, offsets in SCALED_STATES.items():
            c = scaled_counts(fr, offsets, correlation, [float(g) for g in scaled[n]], scaled[n])
            raw_scales[n].append(c)
        single_rows += _row_counts(fr, fr.prior, fr.sigma, np.ones(fr.use.shape, bool))
        for j, share in enumerate(shares):
            seen_share[j] += _row_counts(fr, *cn.estimate(fr, (0,), "hybrid", correlation, seen_share=[share] * 3))
        spreads.append(float(np.degrees(omega)))
        u = fr.states[0] / np.linalg.norm(fr.states[0])
        err = (fr.prior - fr.truth).transpose(1, 2, 0, 3, 4)[:, :, fr.use]  # (3, 3, n)
        var = (fr.sigma ** 2).transpose(1, 2, 0, 3, 4)[:, :, fr.use]
        rows["u_error"] += (np.einsum("rkn,k->rn", err, u) ** 2).sum(axis=1)
        rows["error"] += (err ** 2).sum(axis=(1, 2))
        rows["u_sigma"] += np.einsum("rkn,k->rn", var, u ** 2).sum(axis=1)
        rows["sigma"] += var.sum(axis=(1, 2))
        for knee in knees_deg:
            sigma = fr.sigma
            if knee is not None:
                sigma = sigma.copy()
                grown = np.clip(omega, model.spread["low"], np.radians(knee)) / model.spread["reference"]
                sigma[:, 0] *= grown / model.spread_factor(omega)
            frk = dataclasses.replace(fr, sigma=sigma)
            for m, (method, offsets) in METHODS.items():
                mueller, sg, solved = cn.estimate(frk, offsets, method, correlation, prior_scale=False)
                inside = (np.abs(mueller - fr.truth) <= 2.0 * sg).transpose(1, 2, 0, 3, 4)[:, :, fr.use & solved]
                what_if[_knee_key(knee)][m] += (inside[0].sum(), inside[0].size, inside.sum(), inside.size)
                if knee is None:
                    per[m]["inside"] += inside.sum(axis=-1)
                    per[m]["elements"] += inside.shape[-1]
    return {"samples": len(spreads), "light_spread_deg": spreads,
            "per_element": {m: {k: v.tolist() for k, v in d.items()} for m, d in per.items()},
            "rows": {k: v.tolist() for k, v in rows.items()},
            "what_if": {k: {m: v.tolist() for m, v in d.items()} for k, d in what_if.items()},
            "seen_share": {str(float(k)): v.tolist() for k, v in zip(shares, seen_share)},
            "single_rows": single_rows.tolist(),
            "prior_scale": {n: {g: v.tolist() for g, v in d.items()} for n, d in scaled.items()},
            "raw_scales": raw_scales, "open_scale": opened, "open_scales": open_scales,
            "open_psnr": open_psnr}


def scaled_counts(fr, offsets, correlation, shrinks: Sequence[float], counts: dict) -> float:
    """The hybrid of the states ``offsets`` with the prior's sigma times ``c ** gamma`` for each
    ``gamma`` of ``shrinks``, ``c`` the frames' raw scale from the innovations
    (:func:`polrig.solve.prior_scale.innovation_scale`): adds ``[within 2 sigma, elements]`` to
    ``counts[str(gamma)]``; returns ``c``."""
    s, meas, var, valid = cn.stack_states(fr, offsets)
    c = innovation_scale(*innovations(s, meas, var, valid, fr.prior, fr.sigma, 0))
    for g in shrinks:
        frg = dataclasses.replace(fr, sigma=fr.sigma * c ** g)
        sc = cn.score(fr, *cn.estimate(frg, offsets, "hybrid", correlation, prior_scale=False))
        counts[str(g)] += (sc["inside"], sc["elements"])
    return c


def open_scale_counts(fr, correlation, exponents: Sequence[float], counts: dict, psnr: dict | None = None) -> float:
    """The open direction's what-if (module docstring) on one sample: the two-state hybrid of
    :data:`polrig.models.continuum.RIG_TWO`, the prior scaled as captures scale it, solved again
    with the prior's standard deviation along the open direction times ``f_u ** g``
    (:func:`polrig.solve.open_scale.open_values`, ``solve_hybrid(open_factor=...)``; ``max(f_u, 1) ** g``,
    :func:`polrig.solve.open_scale.open_scale_of`) for each ``g`` of ``exponents``: appends ``[within 2 sigma, elements]`` to ``counts[str(g)]`` (and the matrix
    PSNR over the object, dB, to ``psnr[str(g)]`` if given); returns ``f_u`` (1 where fewer than 30
    accepted values)."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.open_scale import open_scale_of, open_values
    from polrig.solve.reference import ILL_CONDITIONED

    two = cn.RIG_TWO
    s, meas, var, valid = cn.stack_states(fr, two)
    sigma = cn.scaled_sigma(fr, two)
    prior = dict(prior_mean=fr.prior, prior_sigma=sigma, seen_state=0, prior_correlation=correlation)
    r = solve_hybrid(s, meas, var, valid, dtype=np.float64, **prior)
    values = open_values(r, s, meas, var, valid, fr.geometry, mask=fr.mask, **prior)
    for g in exponents:
        factor = open_scale_of(*values, exponent=g).factor
        rg = r if factor == 1.0 else solve_hybrid(s, meas, var, valid, dtype=np.float64, open_factor=factor, **prior)
        sc = cn.score(fr, rg.mueller, rg.sigma, (rg.mask & ILL_CONDITIONED) == 0)
        counts[str(g)].append([sc["inside"], sc["elements"]])
        if psnr is not None:
            psnr[str(g)].append(sc["matrix_psnr"])
    return open_scale_of(*values).raw


def fit_open_exponent(per_sample: dict[str, list], target: float = 0.9545) -> float:
    """The exponent of the open direction's what-if whose samples' coverage lies nearest
    ``target`` in the mean square, from each exponent's per-sample ``[within 2 sigma, elements]``
    (``per_sample[str(g)]``, pooled over the calibration scenes' samples); the grid's value."""
    def cost(g: str) -> float:
        a = np.asarray(per_sample[g], float).reshape(-1, 2)
        a = a[a[:, 1] > 0]
        return float(np.mean((a[:, 0] / a[:, 1] - target) ** 2)) if len(a) else float("inf")

    return float(min(per_sample, key=lambda g: (cost(g), float(g))))


def fit_shrink(counts: dict[str, list], target: float = 0.9545) -> float:
    """The exponent ``gamma`` at which two states cover ``target`` of the elements, from the
    counts ``[within 2 sigma, elements]`` pooled over the calibration scenes at each grid
    exponent (``counts[str(gamma)]``): linear between the grid's points where the coverage falls
    with ``gamma``, else the grid's nearest."""
    g = np.array(sorted(float(k) for k in counts))
    cov = np.array([counts[str(k)][0] / counts[str(k)][1] for k in g])
    if np.all(np.diff(cov) <= 0):
        return float(np.clip(np.interp(-target, -cov, g), g[0], g[-1]))
    return float(g[np.argmin(np.abs(cov - target))])


def _pct(a, b) -> str:
    return f"{100.0 * a / b:.1f}" if b else "-"


def markdown(result: dict) -> str:
    """The three tables of :func:`run`'s result."""
    names = {**{k: v[0] for k, v in cn.SETS.items()}, **{k: f"{k} (calibration scenes)" for k in cn.SEARCH_SETS}}
    where = ("the default rig's scenes at its analyzer grid, one sample per turntable angle "
             f"{', '.join(f'{p:g}' for p in cn.RIG_POSES_DEG)} deg" if result.get("rig") else
             "the first lit samples of each set, 64x64")
    lines = ["# Where the sigma misses", "",
             f"`{result['command']}` ({result['seconds']:.0f} s on 2 shared CPUs, one-shot): {where}, the frames "
             "of `models/continuum/`; the calibration's joint prior.", "",
             "**Within 2 sigma per element** (the rig's frame; m00 m01 m02 / m10 m11 m12 / m20 m21 m22; "
             f"hybrid 2 at {'/'.join(map(str, cn.RIG_TWO))} deg):", "",
             "| set | samples | " + " | ".join(LABELS[m] for m in METHODS) + " |",
             "|---|---:|" + "---|" * len(METHODS)]
    for name, r in result["sets"].items():
        cells = []
        for m in METHODS:
            d = r["per_element"][m]
            cells.append(" / ".join(" ".join(_pct(d["inside"][a][b], d["elements"][a][b]) for b in range(3))
                                    for a in range(3)))
        lines.append(f"| {names.get(name, name)} | {r['samples']} | " + " | ".join(cells) + " |")
    if result.get("rig"):
        lines += ["", pooled_line(result)]
    lines += ["", "**The network's error along the seen state's direction u**, per row (share of the row's "
              "error energy; the diagonal calibrated sigma's share of the row's variance after the slash):", "",
              "| set | row 0 | row 1 | row 2 |", "|---|---:|---:|---:|"]
    for name, r in result["sets"].items():
        w = r["rows"]
        lines.append(f"| {names.get(name, name)} | " + " | ".join(
            f"{_pct(w['u_error'][k], w['error'][k])} / {_pct(w['u_sigma'][k], w['sigma'][k])} %" for k in range(3))
            + " |")
    knees = list(next(iter(result["sets"].values()))["what_if"])
    lines += ["", "**What-if: the first row's light factor grown on to a knee** (deg; the other rows as "
              "shipped): within 2 sigma, first row / all elements, %; the sets' light spread (median, "
              "range):", "",
              "| set | light spread (deg) | " + " | ".join(f"{LABELS[m]}, knee {k}" for m in METHODS for k in knees)
              + " |", "|---|---|" + "---:|" * (len(METHODS) * len(knees))]
    for name, r in result["sets"].items():
        s = r["light_spread_deg"]
        spread = f"{np.median(s):.1f} ({min(s):.1f}-{max(s):.1f})" if s else "-"
        cells = [f"{_pct(v[0], v[1])} / {_pct(v[2], v[3])}" for m in METHODS for v in
                 (r["what_if"][k][m] for k in knees)]
        lines.append(f"| {names.get(name, name)} | {spread} | " + " | ".join(cells) + " |")
    lines += _share_table(result, names)
    lines += _scale_table(result, names)
    lines += _open_table(result, names)
    return "\n".join(lines) + "\n"


def pooled_line(result: dict) -> str:
    """All elements pooled over the result's sets (the rig's scenes), per method, with the 90 % bootstrap
    interval over the scenes and the 10th-90th percentile of the scenes' own coverage
    (:mod:`polrig.models.scene_bootstrap`): how well so many scenes pin the aggregate, and how far one
    scene strays from it."""
    cells = []
    for m in METHODS:
        inside = [float(np.sum(r["per_element"][m]["inside"])) for r in result["sets"].values()]
        elements = [float(np.sum(r["per_element"][m]["elements"])) for r in result["sets"].values()]
        low, high = coverage_interval(inside, elements)
        first, last = scene_spread(inside, elements)
        cells.append(f"{LABELS[m]} {_pct(sum(inside), sum(elements))} [{100 * low:.1f}, {100 * high:.1f}] % "
                     f"(scenes {100 * first:.1f}-{100 * last:.1f})")
    return (f"**Pooled over the {len(result['sets'])} scenes**, all elements within 2 sigma [90 % bootstrap interval "
            "over the scenes] (10th-90th percentile of the scenes' own): " + "; ".join(cells) + ".")


def _share_table(result: dict, names: dict) -> list[str]:
    """The seen direction's share what-if (module docstring) as Markdown lines."""
    first = next(iter(result["sets"].values()))
    if "seen_share" not in first:
        return []
    shares = list(first["seen_share"])
    fitted = result.get("fitted_share")
    head = ["single-shot", *(f"kappa {float(k):g}" for k in shares)]
    if fitted is not None:
        head.append("kappa fitted (" + ", ".join(f"{k:.2f}" for k in fitted) + ")")
    total = lambda rows: _pct(sum(r[0] for r in rows), sum(r[1] for r in rows))  # noqa: E731
    lines = ["", "**What-if: the share of the seen direction's variance kept at one state** (within 2 sigma, "
             "all elements, %; the single-shot sigma, then the one-state hybrid at each share, every row alike, "
             "and at the share per row fitted on the calibration scenes, where the hybrid's coverage of the row "
             "equals the single-shot's; shipped: 1):", "",
             "| set | " + " | ".join(head) + " |", "|---|" + "---:|" * len(head)]
    for name, r in result["sets"].items():
        cells = [total(r["single_rows"]), *(total(r["seen_share"][k]) for k in shares)]
        if fitted is not None:
            cells.append(total(r["fitted_share"]))
        lines.append(f"| {names.get(name, name)} | " + " | ".join(cells) + " |")
    return lines


def _open_table(result: dict, names: dict) -> list[str]:
    """The open direction's what-if (module docstring) as Markdown lines."""
    first = next(iter(result["sets"].values()))
    if "open_scale" not in first:
        return []
    gs = list(first["open_scale"])
    fitted = result.get("fitted_open_exponent")
    lines = ["", "**What-if: the open direction's scale from the diffuse completion** (two states "
             f"{'/'.join(map(str, cn.RIG_TWO))}, the prior scaled as captures scale it, then the prior's "
             "standard deviation along the open direction times `max(f_u, 1) ** g` and solved again; g 0: the "
             "innovations' scale alone"
             + ("" if fitted is None else f"; g chosen on the calibration scenes, each sample's coverage nearest "
                                          f"95.45 % in the mean square: {fitted:g}")
             + "): `f_u` median (10-90 %) over the samples; within "
             "2 sigma, all elements, % (the 10th-90th percentile of the samples' own coverage)", "",
             "| set | f_u | " + " | ".join(f"g {float(g):g}" for g in gs) + " |", "|---|---:|" + "---:|" * len(gs)]
    for name, r in result["sets"].items():
        f = np.asarray(r["open_scales"], float)
        cells = [f"{np.median(f):.2f} ({np.quantile(f, 0.1):.2f}-{np.quantile(f, 0.9):.2f})" if f.size else "-"]
        for g in gs:
            inside, elements = zip(*r["open_scale"][g]) if r["open_scale"][g] else ((), ())
            lo, hi = scene_spread(inside, elements)
            cells.append(f"{_pct(sum(inside), sum(elements))} ({100 * lo:.0f}-{100 * hi:.0f})")
        lines.append(f"| {names.get(name, name)} | " + " | ".join(cells) + " |")
    if "open_psnr" not in first:
        return lines
    lines += ["", "Matrix PSNR over the object at each `g` less that at g 0 (dB; the solve with the stretched prior moves "
              "the estimate along the open direction too): median (min..max) over the samples", "",
              "| set | " + " | ".join(f"g {float(g):g}" for g in gs[1:]) + " |", "|---|" + "---:|" * len(gs[1:])]
    for name, r in result["sets"].items():
        base = np.asarray(r["open_psnr"][gs[0]], float)
        cells = []
        for g in gs[1:]:
            dv = np.asarray(r["open_psnr"][g], float) - base
            dv = dv[np.isfinite(dv)]
            cells.append(f"{np.median(dv):+.2f} ({dv.min():+.2f}..{dv.max():+.2f})" if dv.size else "-")
        lines.append(f"| {names.get(name, name)} | " + " | ".join(cells) + " |")
    return lines


def _scale_table(result: dict, names: dict) -> list[str]:
    """The prior's scale what-if (module docstring) as Markdown lines."""
    first = next(iter(result["sets"].values()))
    if "prior_scale" not in first:
        return []
    two = list(first["prior_scale"]["2"])
    more = list(first["prior_scale"]["3"])
    head = ["raw scale c, median (10-90 %)", *(f"2 states, gamma {float(g):g}" for g in two),
            *(f"{n} states, gamma {float(g):g}" for n in ("3", "4") for g in more)]
    fitted = result.get("fitted_shrink")
    lines = ["", "**What-if: the prior's scale from the innovations** (`polrig.solve.prior_scale`: the prior's "
             "sigma times `c ** gamma`, `c` each image's own scale from the states after the seen one; gamma 0: "
             "the sigma as calibrated" + ("" if fitted is None else f"; gamma fitted on the calibration scenes: {fitted:.2f}")
             + "): within 2 sigma, all elements, %", "",
             "| set | " + " | ".join(head) + " |", "|---|" + "---:|" * len(head)]
    for name, r in result["sets"].items():
        c = np.asarray(r["raw_scales"]["2"], float)
        cells = [f"{np.median(c):.2f} ({np.quantile(c, 0.1):.2f}-{np.quantile(c, 0.9):.2f})" if c.size else "-"]
        cells += [_pct(*r["prior_scale"]["2"][g]) for g in two]
        cells += [_pct(*r["prior_scale"][n][g]) for n in ("3", "4") for g in more]
        lines.append(f"| {names.get(name, name)} | " + " | ".join(cells) + " |")
    return lines


def folder_count(name: str, set_count: int) -> int:
    """The samples of set ``name``'s folder as ``python -m benchmarks continuum`` makes them with
    ``set_count`` per held-out set: the calibration scenes' all-family set half as many, their
    held-out families a quarter (:func:`polrig.models.continuum.run`)."""
    if name in cn.SEARCH_SETS:
        return max(1, set_count // 2) if "all" in name else max(1, set_count // 4)
    return set_count


def run(root, out_md, *, count: int, sets: Sequence[str], set_count: int = 64,
        knees_deg: Sequence[float | None] = KNEES_DEG, weights_dir=None, seed: int = 0,
        rig_scenes: Sequence[str] | None = None, echo=print) -> dict:
    """Generate the sets (as :func:`polrig.models.continuum.run` does, :func:`folder_count`
    samples each, reusing a folder already there), diagnose the first ``count`` lit samples of
    each, write ``out_md`` and its ``.json``. ``rig_scenes``: instead of ``sets``, the default
    rig's named scenes at its analyzer grid, one sample per angle of
    :data:`polrig.models.continuum.RIG_POSES_DEG`."""
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    known = {**{k: v[1] for k, v in cn.SETS.items()}, **cn.SEARCH_SETS}
    if rig_scenes is not None:
        from polrig.sim.scene import SCENES

        known, sets = {f"rig_{n}": n for n in SCENES}, [f"rig_{n}" for n in rig_scenes]
    unknown = [s for s in sets if s not in known]
    if unknown or not sets:
        option = "--sets" if rig_scenes is None else "--rig-scenes"
        raise ConfigError(f"{option}: unknown set(s) {', '.join(unknown) or '(none given)'}; sets are {', '.join(known)}")
    if count < 1 or set_count < 1:
        raise ConfigError(f"--count and --set-count must be >= 1, got {count} and {set_count}")
    paths = None if out_md is None else results_paths(out_md)
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    if net.uncertainty is None:
        raise ConfigError("the single-shot graph has no calibrated uncertainty (models/weights/uncertainty.json)")
    t0 = time.perf_counter()
    command = "python -m polrig.models.coverage_diagnosis " + (
        "--rig-scenes " + ",".join(rig_scenes) if rig_scenes is not None else f"--count {count}")
    result: dict = {"command": command, "count": count, "rig": rig_scenes is not None,
                    "knees_deg": [_knee_key(k) for k in knees_deg], "sets": {}}
    data = {}
    for tag, name in enumerate(sets):
        data[name] = d = (cn.rig_set(known[name], cn.rig_size(), cn.RIG_POSES_DEG, seed) if rig_scenes is not None
                          else cn.make_set(pathlib.Path(root), name, known[name], folder_count(name, set_count)))
        result["sets"][name] = diagnose_set(d, net, count, tag, knees_deg, seed)
        echo(f"{name}: {result['sets'][name]['samples']} samples")
    calibration = [n for n in sets if n in cn.SEARCH_SETS]
    if calibration:  # the share per row fitted on the calibration scenes, then every set at it
        grid = {k: np.sum([result["sets"][n]["seen_share"][k] for n in calibration], axis=0).tolist()
                for k in result["sets"][calibration[0]]["seen_share"]}
        single = np.sum([result["sets"][n]["single_rows"] for n in calibration], axis=0)
        result["fitted_share"] = share = fit_seen_share(grid, single)
        echo(f"the seen direction's share fitted on {', '.join(calibration)}: {share}")
        for tag, name in enumerate(sets):
            result["sets"][name]["fitted_share"] = share_coverage(data[name], net, count, tag, [share], seed)[0]
        pooled = {g: np.sum([result["sets"][n]["prior_scale"]["2"][g] for n in calibration], axis=0).tolist()
                  for g in result["sets"][calibration[0]]["prior_scale"]["2"]}
        result["fitted_shrink"] = fit_shrink(pooled)
        echo(f"the innovations' scale exponent fitted on {', '.join(calibration)}: {result['fitted_shrink']:.2f} "
             f"(shipped {SHRINK:g})")
        per_sample = {g: sum((result["sets"][n]["open_scale"][g] for n in calibration), [])
                      for g in result["sets"][calibration[0]]["open_scale"]}
        result["fitted_open_exponent"] = fit_open_exponent(per_sample)
        echo(f"the open direction's exponent chosen on {', '.join(calibration)}: {result['fitted_open_exponent']:g}")
    result["seconds"] = time.perf_counter() - t0
    text = markdown(result)
    echo(text)
    if paths is not None:
        md, js = paths
        md.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(md, text)
        atomic_write_text(js, json.dumps(result, indent=1) + "\n")
    return result


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    every = (*cn.SETS, *cn.SEARCH_SETS)
    ap = argparse.ArgumentParser(prog="python -m polrig.models.coverage_diagnosis",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=16, help="lit samples per set (default 16)")
    ap.add_argument("--sets", default=",".join(every), help=f"comma-separated, of: {', '.join(every)}")
    ap.add_argument("--set-count", type=int, default=64,
                    help="samples of each generated held-out set, as the continuum benchmark makes them (default 64)")
    ap.add_argument("--root", default="runs/continuum", help="where the sets are generated (default runs/continuum)")
    ap.add_argument("--out", default=None, help="Markdown file for the tables (the numbers go next to it as .json)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--rig-scenes", default=None, nargs="?", const=",".join(cn.RIG_SCENES),
                    help="the default rig's named scenes at its analyzer grid instead of --sets (default "
                         f"{','.join(cn.RIG_SCENES)})")
    args = ap.parse_args(argv)
    return run_main(ap.prog, lambda: run(args.root, args.out, count=args.count,
                                         sets=[s for s in args.sets.split(",") if s], set_count=args.set_count,
                                         weights_dir=args.weights,
                                         rig_scenes=None if args.rig_scenes is None else
                                         [n for n in args.rig_scenes.split(",") if n]) and 0)


if __name__ == "__main__":
    raise SystemExit(main())
