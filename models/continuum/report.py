"""The results' markdown tables and the plot of accuracy against acquisition time.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import json
import pathlib
from collections.abc import Sequence

import numpy as np

from polrig.models.continuum.lower_order import HOLDS_REL, two_state_bound_db
from polrig.models.continuum.methods import JOINT_PRIORS
from polrig.models.continuum.sets import (
    ADAPTIVE_MAX_STATES,
    ADAPTIVE_SHARE,
    BRACKET,
    SIZE,
    adaptive_budget,
    adaptive_label,
    set_label,
)


def markdown(result: dict) -> str:
    off = result["offsets"]
    name = lambda k: "/".join(map(str, off[k]))  # noqa: E731
    cols = [("single", "single-shot"), ("hybrid1", "hybrid 1 (0)"), ("hybrid2", f"hybrid 2 ({name('two')})"),
            ("hybrid3", f"hybrid 3 ({name('three')})"), ("hybrid4", f"hybrid 4 ({name('four')})"),
            ("reference3", "reference 3"), ("reference4", "reference 4")]
    first = next(iter(result["sets"].values()))["methods"]
    adaptive_cols = [(k, adaptive_label(k)) for k in first if k.startswith("adaptive_")]
    cols += adaptive_cols
    lines = []
    for metric, title, fmt in (("matrix_psnr", "Matrix PSNR (dB), object pixels", "{:.2f}"),
                               ("matrix_psnr_unclipped", "Matrix PSNR (dB), object pixels with no clipped sample in "
                                                         "any state", "{:.2f}"),
                               ("fwd_l2", "Forward Stokes L2 (rel.)", "{:.4f}"),
                               ("coverage", "Within 2 sigma", "{:.1%}")):
        psnr_table = metric.startswith("matrix_psnr")
        extra = (" | hybrid 2 - single | hybrid 4 - hybrid 3 | same, equal time (4 vs 3 frames per state) |"
                 if psnr_table else " |")
        lines += [f"**{title}**", "", "| set | scored | " + " | ".join(c[1] for c in cols) + extra,
                  "|---|---:|" + "---:|" * len(cols) + ("---:|---:|---:|" if psnr_table else "")]
        for key, r in result["sets"].items():
            m = r["methods"]
            cells = [fmt.format(m[c][metric]).replace("%", " %") for c, _ in cols]
            row = f"| {set_label(key)} | {r['samples']} | " + " | ".join(cells) + " |"
            if psnr_table:
                row += (f" {m['hybrid2'][metric] - m['single'][metric]:+.2f} |"
                        f" {m['hybrid4'][metric] - m['hybrid3'][metric]:+.2f} |"
                        f" {m['hybrid4_3frames'][metric] - m['hybrid3_4frames'][metric]:+.2f} |")
            lines.append(row)
        lines.append("")
    if "coverage_interval" in first["single"]:
        lines += coverage_interval_table(result, [c for c in cols if not c[0].startswith("reference")])
    if "time_s" in first["single"]:
        timed = [("single", "single-shot"), ("hybrid2", "hybrid 2"), ("hybrid3", "hybrid 3"),
                 ("hybrid4", "hybrid 4"), ("hybrid3_4frames", "hybrid 3, 4 frames each"),
                 ("hybrid4_3frames", "hybrid 4, 3 frames each"), *adaptive_cols]
        lines += ["**States per pose and acquisition time** (mean states / seconds per pose on the simulated rig: "
                  "stage motion, exposure and readout, `acquisition_time_s`; the adaptive capture stops when "
                  f"{100 * ADAPTIVE_SHARE:.0f} % of the object pixels have a relative posterior sigma at most its target "
                  f"with at least {result.get('adaptive_min_states', 1)} states taken, at most {ADAPTIVE_MAX_STATES} "
                  f"states)", "",
                  "| set | " + " | ".join(c[1] for c in timed) + " |", "|---|" + "---:|" * len(timed)]
        for key, r in result["sets"].items():
            m = r["methods"]
            lines.append(f"| {set_label(key)} | " + " | ".join(f"{m[c]['states']:.2f} / {m[c]['time_s']:.2f} s"
                                                           for c, _ in timed) + " |")
        lines.append("")
    if "hybrid2_bracket" in first:
        br = " / ".join(["1"] + [f"1/{1 / f:g}" for f in BRACKET])
        lines += [f"**Highlights: an exposure bracket at every state** ({br} of the exposure, merged; the network "
                  "sees the reference exposure, and where it clipped but a shorter exposure measured the pixel its "
                  "estimate takes the measured intensity with a calibrated sigma: `polrig.models.highlights`). "
                  "Matrix PSNR (dB) over the object / within 2 sigma (pixels whose seen frame did not clip) / within "
                  "2 sigma at the highlights the bracket measured / seconds per pose", "",
                  "| set | single-shot | single-shot, bracket | hybrid 1, bracket | hybrid 2 | hybrid 2, bracket | "
                  "hybrid 2 bracket - single-shot | hybrid 2 bracket - single-shot bracket |", "|---|" + "---:|" * 7]
        for key, r in result["sets"].items():
            m = r["methods"]
            cell = lambda k: (f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} % / "  # noqa: E731
                              + (f"{100 * m[k]['coverage_highlights']:.1f} %" if m[k].get("highlight_elements") else "-")
                              + f" / {m[k]['time_s']:.2f} s")
            plain = lambda k: f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} % / - / {m[k]['time_s']:.2f} s"  # noqa: E731
            lines.append(f"| {set_label(key)} | {plain('single')} | {cell('single_bracket')} | {cell('hybrid1_bracket')} | "
                         f"{plain('hybrid2')} | {cell('hybrid2_bracket')} | "
                         f"{m['hybrid2_bracket']['matrix_psnr'] - m['single']['matrix_psnr']:+.2f} | "
                         f"{m['hybrid2_bracket']['matrix_psnr'] - m['single_bracket']['matrix_psnr']:+.2f} |")
        lines.append("")
    if "hybrid2_calibrated" in first:
        lines += prior_scale_table(result)
    two_shipped = "hybrid2_calibrated" if "hybrid2_calibrated" in first else "hybrid2"
    lines += ["**The seen state's treatment** (matrix PSNR dB / within 2 sigma; 1 state, and 2 states "
              f"{name('two')}; every column with the sigma as calibrated)", "",
              "| set | hybrid (shipped) 1 | marginal 1 | naive 1 | exclude 1 (= single-shot) | hybrid (shipped) 2 | "
              "marginal 2 | naive 2 | exclude 2 |", "|---|" + "---:|" * 8]
    for key, r in result["sets"].items():
        m = r["methods"]
        cell = lambda k: f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} %"  # noqa: E731
        keys = ("hybrid1", "marginal1", "naive1", "exclude1", two_shipped, "marginal2", "naive2", "exclude2")
        lines.append(f"| {set_label(key)} | " + " | ".join(cell(k) for k in keys) + " |")
    if "hybrid2_models" in first:
        lines += ["", models_markdown(result)]
    return "\n".join(lines)


def prior_scale_table(result: dict) -> list[str]:
    """The hybrid at 2, 3 and 4 states with the prior's sigma as calibrated against scaled as
    captures scale it (:func:`scaled_sigma`, and at two states :func:`open_factor`): matrix PSNR
    and within 2 sigma, per set."""
    head = [f"{n} states: {what}" for n in (2, 3, 4) for what in ("PSNR dB", "within 2 sigma")]
    lines = ["**The prior's scale** (`polrig.solve.prior_scale`, `polrig.solve.open_scale`; the captures' default): "
             "the hybrid with the network's sigma as calibrated -> scaled per sample by the states after the seen one "
             "and, at two states, along the direction they leave open by the diffuse term's geometry", "",
             "| set | " + " | ".join(head) + " |", "|---|" + "---:|" * len(head)]
    for key, r in result["sets"].items():
        m = r["methods"]
        cells = []
        for n in (2, 3, 4):
            a, b = m[f"hybrid{n}_calibrated"], m[f"hybrid{n}"]
            cells += [f"{a['matrix_psnr']:.2f} -> {b['matrix_psnr']:.2f}",
                      f"{100 * a['coverage']:.1f} -> {100 * b['coverage']:.1f} %"]
        lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return lines + [""]


def coverage_interval_table(result: dict, cols: Sequence[tuple[str, str]]) -> list[str]:
    """The coverage table's figures with their 90 % scene-bootstrap intervals and the middle 80 % of
    the samples' own coverage (:mod:`polrig.models.scene_bootstrap`), as Markdown lines."""
    unit = ("the scene's poses: with a handful of them a rough guide, and silent on other scenes" if result.get("rig")
            else "the set's scenes")
    lines = [f"**Within 2 sigma, how sure each figure is**: the set's coverage [its 90 % bootstrap interval, "
             f"resampling {unit}] (the 10th-90th percentile of the samples' own coverage). Issue 33 asks for "
             "93-97 %.", "",
             "| set | " + " | ".join(c[1] for c in cols) + " |", "|---|" + "---:|" * len(cols)]
    for key, r in result["sets"].items():
        m = r["methods"]
        cells = [f"{100 * m[c]['coverage']:.1f} [{100 * m[c]['coverage_interval'][0]:.1f}, "
                 f"{100 * m[c]['coverage_interval'][1]:.1f}] ({100 * m[c]['coverage_scenes'][0]:.0f}-"
                 f"{100 * m[c]['coverage_scenes'][1]:.0f})" for c, _ in cols]
        lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return lines + [""]


def models_markdown(result: dict) -> str:
    """The lower-order model comparison at two states (:func:`models_rows`) as a Markdown table."""
    two = "/".join(map(str, result["offsets"]["two"]))
    lines = [f"**Lower-order models at two states ({two})**: single-shot, hybrid 2 and hybrid 2 with the model "
             "selection (`select_models` with the network's prior: at two states the test runs on the hybrid's "
             "posterior system). \"holds\": object pixels with no clipped sample, lit in every colour (`lit_pixels`), "
             f"where in every colour the truth is within {100 * HOLDS_REL:g} % (relative Frobenius) of its nearest "
             "candidate model (`model_holds`); \"all\": every object pixel. Matrix PSNR in dB; \"reduced\": share of the "
             "scored colour-pixels given a reduced model. False acceptance: a reduced model chosen where the "
             "truth is detectably off every candidate (`detectably_off_every_model`: noncentrality on the hybrid's "
             "posterior system with the network's sigma at least the test's 95 % power point), of that share of the "
             "scored colour-pixels. The bound: the four-state reference solve (0/45/90/135, no prior) and the same "
             "with the selection, scored alike; \"single + 6\" is the PSNR the issue's +6 dB asks for; \"two-state "
             "bound\": the most two states could give where a model holds (`two_state_bound_db`: the four-state "
             "selection with half its samples, combined with the single-shot estimate as independent). \"+ geometry\": "
             "hybrid 2 + models with the direction the two states leave open predicted from the diffuse term's "
             "geometry where the selection chose `rank_one` (`complete_diffuse`: of two light fields per image the one of least cost, "
             "normals and one refractive index fitted to the measured ratios in their noise, pulled first towards the network's "
             "normals, then towards the 3x3 neighbours' mean), \"completed\" the share of "
             "the scored colour-pixels it changed.", "",
             "| set | scored | holds (share of pixels) | single-shot, holds | hybrid 2, holds | hybrid 2 + models, holds "
             "| + models - single, holds | + geometry, holds | + geometry - single, holds | single + 6, holds "
             "| reference 4 / + models, holds | two-state bound, holds "
             "| hybrid 2, all | "
             "hybrid 2 + models / + geometry, all | + models / + geometry - single, all | "
             "reduced, all / holds; completed, all | within 2 sigma, hybrid 2 / + models / + geometry / reference 4 + models | "
             "false acceptance (detectably off every model) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    nan = {"psnr_holds": float("nan"), "coverage": float("nan"), "matrix_psnr": float("nan"), "accepted": float("nan")}
    for key, r in result["sets"].items():
        m = r["methods"]
        sgl, hyb, sel = m["holds_single"], m["holds_hybrid2"], m["hybrid2_models"]
        ref4, ref4m = m.get("holds_reference4", nan), m.get("reference4_models", nan)
        geo = nan | m.get("hybrid2_geometry", {})
        lines.append(
            f"| {set_label(key)} | {r['samples']} | {100 * sel.get('holds_share', float('nan')):.1f} % | "
            f"{sgl['psnr_holds']:.2f} | {hyb['psnr_holds']:.2f} | {sel['psnr_holds']:.2f} | "
            f"{sel['psnr_holds'] - sgl['psnr_holds']:+.2f} | {geo['psnr_holds']:.2f} | "
            f"{geo['psnr_holds'] - sgl['psnr_holds']:+.2f} | {sgl['psnr_holds'] + 6:.2f} | "
            f"{ref4['psnr_holds']:.2f} / {ref4m['psnr_holds']:.2f} | "
            f"{two_state_bound_db(sgl['psnr_holds'], ref4m['psnr_holds']):.2f} | {hyb['matrix_psnr']:.2f} | "
            f"{sel['matrix_psnr']:.2f} / {geo['matrix_psnr']:.2f} | {sel['matrix_psnr'] - sgl['matrix_psnr']:+.2f} / "
            f"{geo['matrix_psnr'] - sgl['matrix_psnr']:+.2f} | "
            f"{100 * sel['accepted']:.0f} / {100 * sel['accepted_holds']:.0f} / {100 * geo['accepted']:.0f} % | "
            f"{100 * hyb['coverage']:.1f} / {100 * sel['coverage']:.1f} / {100 * geo['coverage']:.1f} / "
            f"{100 * ref4m['coverage']:.1f} % | "
            f"{100 * sel.get('false_acceptance', float('nan')):.1f} % of "
            f"{100 * sel.get('detectable_share', float('nan')):.0f} % |")
    return "\n".join(lines + diffuse_markdown(result))


def diffuse_markdown(result: dict) -> list[str]:
    """The lines of the diffuse route's table (:func:`diffuse_row`), none where no set has it."""
    if not any("hybrid2_diffuse" in r["methods"] for r in result["sets"].values()):
        return []
    lines = ["", "**The diffuse term, with the specular term where significant, tested on the two states' samples "
             "alone** (`polrig.solve.diffuse_test`: no model selection, no prior in the test; hybrid 2 with the "
             "specular term the test fitted taken off, the rank-one estimate and the diffuse completion of the rest, "
             "and the specular term put back, where the test accepts: `complete_tested_diffuse(specular=True)`). "
             "Columns as above; \"accepted\": share of the scored colour-pixels; \"with the specular term\": of "
             "them, those where it was significant; false acceptance where the samples can tell: accepted, of the "
             "colour-pixels where the test rejects at least 95 % of 200 noise draws about the truth "
             "(`diffuse_test_power`: its Monte Carlo power), and of those where the truth's own statistic is at "
             "least the noncentral chi-square's 95 % power point under both models (`detectably_off_diffuse`: "
             "it overstates the power where the misfit is flat in the normal, which the choice of normal "
             "absorbs), each with its share of the scored colour-pixels; the selection's false acceptance "
             "(above, noncentral) alongside. (The prior's metric of the selection, off every one of its "
             "candidates, does not apply: the diffuse + specular block is none of them.)", "",
             "| set | accepted, all / holds | with the specular term | PSNR, holds | - single, holds | single + 6, holds "
             "| PSNR, all | - single, all | - hybrid 2 + models / + geometry, all | within 2 sigma "
             "| false acceptance where the samples can tell: Monte Carlo / noncentral / the selection's |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for key, r in result["sets"].items():
        m = r["methods"]
        if "hybrid2_diffuse" not in m:
            continue
        d, sgl, sel = m["hybrid2_diffuse"], m["holds_single"], m["hybrid2_models"]
        geo = m.get("hybrid2_geometry", {"matrix_psnr": float("nan")})
        lines.append(
            f"| {set_label(key)} | {100 * d['accepted']:.0f} / {100 * d['accepted_holds']:.0f} % | "
            f"{100 * d.get('specular', float('nan')):.0f} % | {d['psnr_holds']:.2f} | {d['psnr_holds'] - sgl['psnr_holds']:+.2f} | {sgl['psnr_holds'] + 6:.2f} | "
            f"{d['matrix_psnr']:.2f} | {d['matrix_psnr'] - sgl['matrix_psnr']:+.2f} | "
            f"{d['matrix_psnr'] - sel['matrix_psnr']:+.2f} / {d['matrix_psnr'] - geo['matrix_psnr']:+.2f} | "
            f"{100 * d['coverage']:.1f} % | "
            f"{100 * d.get('false_acceptance_mc', float('nan')):.1f} % of {100 * d.get('detectable_mc_share', float('nan')):.1f} % / "
            f"{100 * d.get('false_acceptance', float('nan')):.1f} % of {100 * d.get('detectable_share', float('nan')):.1f} % / "
            f"{100 * sel.get('false_acceptance', float('nan')):.1f} % |")
    return lines


def min_states_markdown(result: dict) -> str:
    """:func:`polrig.models.continuum.run.min_states_compare`'s result as Markdown: per target, each
    rig scene's coverage within 2 sigma, matrix PSNR over the object, and states and hardware
    seconds per pose, for each least number of states before a pose may stop."""
    mins = result["min_states"]
    lines = []
    for t in result["targets"]:
        cols = [f"min {m}" for m in mins]
        lines += [f"**Target {t:g}** (relative posterior sigma, {100 * result['share']:.0f} % of the object pixels): "
                  + " / ".join(cols) + " states before a pose may stop", "",
                  "| scene | poses | within 2 sigma | matrix PSNR (dB) | states per pose | seconds per pose |",
                  "|---|---:|---:|---:|---:|---:|"]
        rows = []
        for scene, r in result["scenes"].items():
            m = [r["methods"][f"{t:g}_min{k}"] for k in mins]
            rows.append(m)
            lines.append(f"| {scene} | {r['samples']} | " + " / ".join(f"{100 * x['coverage']:.1f}" for x in m)
                         + " % | " + " / ".join(f"{x['matrix_psnr']:.2f}" for x in m) + " | "
                         + " / ".join(f"{x['states']:.2f}" for x in m) + " | "
                         + " / ".join(f"{x['time_s']:.2f}" for x in m) + " |")
        cov = [[x[k]["coverage"] for x in rows] for k in range(len(mins))]
        lines.append("| **all scenes** (coverage range; mean PSNR, states and seconds) | | "
                     + " / ".join(f"{100 * min(c):.1f}-{100 * max(c):.1f}" for c in cov) + " % | "
                     + " / ".join(f"{np.mean([x[k]['matrix_psnr'] for x in rows]):.2f}" for k in range(len(mins)))
                     + " | " + " / ".join(f"{np.mean([x[k]['states'] for x in rows]):.2f}" for k in range(len(mins)))
                     + " | " + " / ".join(f"{np.mean([x[k]['time_s'] for x in rows]):.2f}" for k in range(len(mins)))
                     + " |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def joint_markdown(result: dict) -> str:
    """:func:`joint_compare`'s result as Markdown tables: per set, each prior's
    (:data:`JOINT_PRIORS`) false acceptance at two states, coverage within 2 sigma and matrix
    PSNR at 1 to 4 states."""
    off = result["offsets"]
    first = next(iter(result["sets"].values()))["methods"]
    priors = [p for p in JOINT_PRIORS if f"{p}_models" in first]
    head = " / ".join(priors)
    lines = ["**False acceptance of the two-state model test** "
             f"({'/'.join(map(str, off['two']))}; a reduced model chosen where the truth is detectably off every "
             "candidate in the test's own metric, of that share of the scored colour-pixels), the share given a "
             "reduced model where one holds, and the matrix PSNR there (hybrid 2 + models)", "",
             "| set | scored | " + " | ".join(f"false acceptance, {p}" for p in priors)
             + f" | reduced where one holds, {head} | PSNR where one holds, {head} (dB) |",
             "|---|---:|" + "---:|" * (len(priors) + 2)]
    for key, r in result["sets"].items():
        m = [r["methods"][f"{p}_models"] for p in priors]
        lines.append(f"| {set_label(key)} | {r['samples']} | "
                     + " | ".join(f"{100 * x['false_acceptance']:.1f} % of {100 * x['detectable_share']:.0f} %"
                                  for x in m)
                     + " | " + " / ".join(f"{100 * x['accepted_holds']:.0f}" for x in m) + " % | "
                     + " / ".join(f"{x['psnr_holds']:.2f}" for x in m) + " |")
    states = [(1, "0"), (2, "/".join(map(str, off["two"]))), (3, "/".join(map(str, off["three"]))),
              (4, "/".join(map(str, off["four"])))]
    for metric, title, fmt in (("coverage", "Within 2 sigma, hybrid", "{:.1%}"),
                               ("matrix_psnr", "Matrix PSNR (dB), hybrid, object pixels", "{:.2f}")):
        lines += ["", f"**{title}**: {head}" + (" (each joint prior - diagonal)" if metric == "matrix_psnr" else ""),
                  "", "| set | " + " | ".join(f"{n} ({o})" for n, o in states) + " |",
                  "|---|" + "---:|" * len(states)]
        for key, r in result["sets"].items():
            m = r["methods"]
            cells = []
            for n, _ in states:
                vals = [m[f"{p}_hybrid{n}"][metric] for p in priors]
                cell = " / ".join(fmt.format(v) for v in vals).replace("%", " %")
                if metric == "matrix_psnr":
                    cell += " (" + ", ".join(f"{v - vals[0]:+.2f}" for v in vals[1:]) + ")"
                cells.append(cell)
            lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def prior_words(result: dict) -> str:
    """How a run's hybrid rows used the network's prior (the captures' choice)."""
    if result.get("prior") == "joint":
        return ("jointly calibrated (the calibration's `joint_prior`, as captures use it; "
                "`--joint-compare` sets it against the per-element one)")
    return "per element (the calibration holds no joint prior)"


def search_line(result: dict) -> str:
    s = result.get("search")
    if not s:
        return "states given, not searched; "
    best = lambda part: sorted(s[part].items(), key=lambda kv: -kv[1])[:3]  # noqa: E731
    return ("states searched on " + f"{s['samples']} samples (PSNR over unclipped pixels; best 2-state sets "
            + ", ".join(f"{k} {v:.2f}" for k, v in best("two")) + " dB; best 3-state sets "
            + ", ".join(f"{k} {v:.2f}" for k, v in best("three")) + " dB); ")


#: The methods of the trade plot (:func:`trade_points`): result key, label, marker; then one
#: row per adaptive target (``adaptive_<t>``) in the result.
TRADE_METHODS = (("single", "single-shot", "o"), ("hybrid1", "hybrid 1", "v"), ("hybrid2", "hybrid 2", "s"),
                 ("hybrid3", "hybrid 3", "^"), ("hybrid4", "hybrid 4", "D"), ("reference3", "reference 3", "<"),
                 ("reference4", "reference 4", ">"), ("hybrid3_4frames", "hybrid 3 x 4 frames", "P"),
                 ("hybrid4_3frames", "hybrid 4 x 3 frames", "X"))
#: The trade plot's panels: result metric, axis label.
TRADE_METRICS = (("matrix_psnr", "matrix PSNR (dB), object pixels"), ("fwd_l2", "forward Stokes L2 (rel.)"))


def trade_methods(result: dict) -> list[tuple[str, str, str]]:
    """``(key, label, marker)`` of the methods :func:`trade_points` plots: those of
    :data:`TRADE_METHODS` every set of ``result`` holds, then its adaptive targets."""
    sets = list(result["sets"].values())
    have = lambda k: all(k in s["methods"] for s in sets)  # noqa: E731
    rows = [m for m in TRADE_METHODS if have(m[0])]
    adaptive_keys = sorted((k for k in (sets[0]["methods"] if sets else {}) if k.startswith("adaptive_") and have(k)),
                           key=lambda k: (adaptive_budget(k), -float(k.split("_")[1])))
    return rows + [(k, adaptive_label(k), m) for k, m in zip(adaptive_keys, "*hpd")]


def trade_points(result: dict) -> list[dict]:
    """The trade's points: one per set and method (:func:`trade_methods`) of a :func:`run`
    result (or its JSON), each ``{"set", "method", "label", "time_s", "states"}`` and the
    :data:`TRADE_METRICS` (time in seconds per pose, :func:`acquisition_time_s`).
    :class:`ValueError` when there is none (no set, or no trade method every set holds)."""
    if not trade_methods(result) or not result["sets"]:
        raise ValueError("no set holds the trade's methods (" + ", ".join(k for k, _, _ in TRADE_METHODS) + ")")
    out = []
    for name, r in result["sets"].items():
        for key, label, _ in trade_methods(result):
            m = r["methods"][key]
            out.append({"set": name, "method": key, "label": label, "time_s": float(m["time_s"]),
                        "states": float(m["states"])} | {k: float(m[k]) for k, _ in TRADE_METRICS})
    return out


def trade_figure(result: dict):
    """The accuracy-against-time figure of a :func:`run` result: one panel per
    :data:`TRADE_METRICS` against the acquisition time per pose (the L2 on a log axis); a small point per set
    (one colour per set) and method (one marker per method), and per method the median over the
    sets with its range (min..max, both axes). Returns ``(figure, points)`` (:func:`trade_points`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    points = trade_points(result)
    methods = trade_methods(result)
    sets = list(result["sets"])
    colours = {s: plt.get_cmap("tab10")(i % 10) for i, s in enumerate(sets)}
    fig, axes = plt.subplots(1, len(TRADE_METRICS), figsize=(12, 5.2), constrained_layout=True)
    for ax, (metric, title) in zip(np.atleast_1d(axes), TRADE_METRICS):
        for key, label, marker in methods:
            rows = [p for p in points if p["method"] == key]
            t = np.array([p["time_s"] for p in rows])
            y = np.array([p[metric] for p in rows])
            ax.scatter(t, y, s=14, marker=marker, c=[colours[p["set"]] for p in rows], alpha=0.8, linewidths=0)
            tm, ym = float(np.median(t)), float(np.median(y))
            ax.errorbar([tm], [ym], xerr=[[tm - t.min()], [t.max() - tm]], yerr=[[ym - y.min()], [y.max() - ym]],
                        fmt=marker, ms=8, mfc="none", mec="black", ecolor="0.35", elinewidth=0.8, capsize=2)
        ax.set_xlim(left=-0.3)
        ax.set_xlabel("acquisition time per pose (s, simulated rig)")
        ax.set_ylabel(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.axvline(0.0, color="0.6", lw=0.5)
        if metric == "fwd_l2":
            ax.set_yscale("log")
    handles = [Line2D([], [], ls="none", marker=m, mfc="none", mec="black", ms=7, label=lab) for _, lab, m in methods]
    handles += [Line2D([], [], ls="none", marker="o", color=colours[s], ms=6, label=set_label(s)) for s in sets]
    fig.legend(handles=handles, loc="outside right center", fontsize=7, frameon=False)
    fig.suptitle(f"Speed against accuracy: {len(sets)} sets at {result.get('size', SIZE)}x{result.get('size', SIZE)}"
                 " (open black: median over the sets, bars: min..max)", fontsize=10)
    return fig, points


def plot_trade(result: dict, path) -> list[dict]:
    """Write :func:`trade_figure` of ``result`` to ``path`` (PNG); returns its points."""
    import io

    import matplotlib.pyplot as plt

    from polrig.atomic import atomic_write_bytes

    fig, points = trade_figure(result)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(pathlib.Path(path), buf.getvalue())
    return points


def plot_from_json(path) -> pathlib.Path:
    """Draw :func:`plot_trade` of a results JSON (:func:`run`'s) next to it as ``.png``; returns
    the PNG's path. :class:`polrig.errors.ConfigError` (one line naming the file) unless it is a
    readable results JSON."""
    from polrig.errors import ConfigError

    path = pathlib.Path(path)
    try:
        result = json.loads(path.read_text())
        trade_points(result)
    except FileNotFoundError:
        raise ConfigError(f"--plot-only {path}: no such file") from None
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"--plot-only {path}: not a continuum results JSON ({type(exc).__name__}: {exc})") from None
    png = path.with_suffix(".png")
    plot_trade(result, png)
    return png
