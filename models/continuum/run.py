"""Every method on every set: the angle search, one set's evaluation, the joint-prior comparison
and the whole run.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import json
import os
import pathlib
import time
from collections.abc import Sequence

import numpy as np

from polrig.models.continuum.frames import (
    Frames,
    bracket_prior,
    measured_highlights,
    sample_frames,
    set_samples,
)
from polrig.models.continuum.lower_order import models_rows
from polrig.models.continuum.methods import (
    JOINT_PRIORS,
    acquisition_time_s,
    adaptive,
    estimate,
    joint_priors,
    mean_rows,
    score,
)
from polrig.models.continuum.report import (
    joint_markdown,
    markdown,
    min_states_markdown,
    models_markdown,
    plot_trade,
    prior_words,
    search_line,
)
from polrig.models.continuum.sets import (
    ADAPTIVE_MAX_STATES,
    ADAPTIVE_MORE_STATES,
    ADAPTIVE_SHARE,
    ADAPTIVE_TARGETS,
    BRACKET,
    FOUR_STATES,
    OFFSETS_DEG,
    RIG_POSES_DEG,
    RIG_SCENES,
    RIG_THREE,
    RIG_TWO,
    SEARCH_SETS,
    SETS,
    SIZE,
    VARIANTS,
    adaptive_key,
    make_set,
    rig_set,
    rig_size,
)


def fit_highlight_factor(root, net, *, count: int = 128, seed: int = 0, echo=print) -> dict:
    """The sigma factor at the highlights a bracket measured
    (:data:`polrig.models.highlights.SIGMA_FACTOR`), fitted on the uncertainty calibration's
    scenes (:data:`SEARCH_SETS`, ``count`` samples of the all-family set and half as many of the
    held-out families; no reported set): half the 95.45 % quantile of ``|M' - M_true| / sigma``
    over the rescaled pixels' elements, ``sigma`` the calibrated model's on the rescaled
    estimate (factor 1). Returns the factor, the elements it rests on and each set's quantile."""
    ratios, per_set = [], {}
    for tag, (name, kw) in enumerate(SEARCH_SETS.items()):
        d = make_set(pathlib.Path(root), name, kw, count if "all" in name else max(1, count // 2))
        got = []
        for ds, sensor, i, prior in set_samples(d, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, 200 + tag, i]), offsets=(0,),
                               bracket=BRACKET)
            mean, sigma, rescaled = measured_highlights(fr, net.uncertainty)
            if sigma is not None:
                with np.errstate(divide="ignore", invalid="ignore"):
                    e = np.abs(mean - fr.truth) / sigma
                got.append(e.transpose(1, 2, 0, 3, 4)[:, :, rescaled].ravel())
        r = np.concatenate(got) if got else np.zeros(0)
        per_set[name] = {"elements": int(r.size), "factor": float(np.quantile(r, 0.9545) / 2) if r.size else None}
        ratios.append(r)
    r = np.concatenate(ratios)
    out = {"factor": float(np.quantile(r, 0.9545) / 2), "elements": int(r.size), "sets": per_set,
           "bracket": list(BRACKET), "count": count}
    echo(json.dumps(out, indent=1))
    return out


def joint_rows(fr: Frames, offsets: dict[str, tuple[int, ...]], priors: dict[str, np.ndarray | None]
               ) -> dict[str, dict[str, float]]:
    """One sample's rows of the joint-prior comparison (``--joint-compare``): for each of
    ``priors`` (name -> ``prior_correlation``, :func:`joint_priors`), the hybrid at 1, 2, 3 and 4
    states (``offsets``: ``two``, ``three``, ``four``) with :func:`score`, and at two states with
    the lower-order model selection (:func:`models_rows`: its false acceptance and share
    accepted); keys ``<prior>_hybrid<N>`` and ``<prior>_models``. The prior's sigma as calibrated
    (the comparison is of the correlation; ``benchmarks/results/continuum_joint.md`` was measured
    so, before captures scaled it)."""
    rows = {}
    for name, k in priors.items():
        for n, offs in ((1, (0,)), (2, offsets["two"]), (3, offsets["three"]), (4, offsets["four"])):
            rows[f"{name}_hybrid{n}"] = score(fr, *estimate(fr, offs, "hybrid", k, prior_scale=False)) | {
                "states": n, "time_s": 0.0}
        rows[f"{name}_models"] = models_rows(fr, offsets["two"], k, keys=("hybrid2_models",),
                                             prior_scale=False)["hybrid2_models"] \
            | {"states": 2, "time_s": 0.0}
    return rows


def search_states(dirs: Sequence[pathlib.Path], net, seed: int, echo=print,
                  correlation: np.ndarray | None = None) -> dict:
    """Mean hybrid matrix PSNR (over pixels unclipped in every state) of every 2- and 3-state
    set on the search sets; the best of each. ``correlation``: the hybrid's joint prior (None:
    per element)."""
    two = [(0, d) for d in OFFSETS_DEG[1:]]
    three = [(0, a, b) for a in OFFSETS_DEG[1:] for b in OFFSETS_DEG[1:] if a < b]
    acc: dict[tuple, list[float]] = {k: [] for k in two + three}
    n = 0
    for tag, d in enumerate(dirs):
        for ds, sensor, i, prior in set_samples(d, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, 100 + tag, i]))
            n += 1
            for key in acc:
                acc[key].append(score(fr, *estimate(fr, key, "hybrid", correlation))["matrix_psnr_unclipped"])
    mean = {k: float(np.nanmean(v)) for k, v in acc.items()}
    best2 = max(two, key=mean.get)
    best3 = max(three, key=mean.get)
    echo(f"search: {n} samples; best 2 states {best2} {mean[best2]:.2f} dB, best 3 {best3} {mean[best3]:.2f} dB")
    return {"samples": n, "two": {"/".join(map(str, k)): mean[k] for k in two},
            "three": {"/".join(map(str, k)): mean[k] for k in three}, "best_two": list(best2),
            "best_three": list(best3)}


def evaluate_set(data_dir, net, offsets: dict[str, tuple[int, ...]], seed: int, tag: int,
                 targets: Sequence[float] = ADAPTIVE_TARGETS, only_models: bool = False,
                 correlation: np.ndarray | None = None) -> dict:
    """Every method's mean metrics on one set (module docstring), the adaptive capture at each of
    ``targets`` included; with each method's states per pose and acquisition time
    (:func:`acquisition_time_s`; the adaptive's per sample). Also the lower-order model
    comparison at two states (:func:`models_rows`: keys ``holds_single``, ``holds_hybrid2``,
    ``hybrid2_models``); ``only_models``: that alone. ``correlation``: the hybrid's joint prior
    for every hybrid row (the :data:`VARIANTS` rows keep the per-element prior they study); None
    per element."""
    plan = {} if only_models else {"single": ("single", (0,)), "hybrid1": ("hybrid", (0,)), "hybrid2": ("hybrid", offsets["two"]),
            "hybrid3": ("hybrid", offsets["three"]), "hybrid4": ("hybrid", offsets["four"]),
            "reference3": ("reference", offsets["three"]), "reference4": ("reference", offsets["four"])}
    for v in VARIANTS if not only_models else ():
        plan[f"{v}1"] = (v, (0,))
        plan[f"{v}2"] = (v, offsets["two"])
    # the hybrid with the sigma as calibrated (captures scale it: polrig.solve.prior_scale)
    calibrated = {} if only_models else {f"hybrid{n}_calibrated": offsets[k]
                                         for n, k in ((2, "two"), (3, "three"), (4, "four"))}
    # equal capture time: 3 states of 4 frames against 4 states of 3 (12 frames each)
    timed = {} if only_models else {"hybrid3_4frames": (offsets["three"], 4),
                                    "hybrid4_3frames": (offsets["four"], 3)}
    adaptive_keys = {} if only_models else {adaptive_key(t, n): (t, n) for n in (ADAPTIVE_MAX_STATES, ADAPTIVE_MORE_STATES)
                                            for t in targets}
    # an exposure bracket at every state (the "Highlights" rows): the network sees the reference exposure
    bracketed = {} if only_models else {"single_bracket": ("single", (0,)), "hybrid1_bracket": ("hybrid", (0,)),
                                        "hybrid2_bracket": ("hybrid", offsets["two"])}
    model_keys = {"holds_single": "single", "holds_hybrid2": "hybrid2", "hybrid2_models": "hybrid2_models",
                  "hybrid2_geometry": "hybrid2_geometry", "hybrid2_diffuse": "hybrid2_diffuse",
                  "holds_reference4": "reference4",
                  "reference4_models": "reference4_models"}
    rows: dict[str, list] = {k: [] for k in (*plan, *calibrated, *timed, *adaptive_keys, *model_keys, *bracketed)}
    time_s = {key: acquisition_time_s(offs) for key, (_, offs) in plan.items()}
    time_s |= {key: acquisition_time_s(offs) for key, offs in calibrated.items()}
    time_s |= {key: acquisition_time_s(offs, k) for key, (offs, k) in timed.items()}
    time_s |= {key: acquisition_time_s(offs, bracket=BRACKET) for key, (_, offs) in bracketed.items()}
    t0 = time.perf_counter()
    for ds, sensor, i, prior in set_samples(data_dir, net):
        fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i]))
        for key, (method, offs) in plan.items():
            rows[key].append(score(fr, *estimate(fr, offs, method, correlation))
                             | {"states": len(offs), "time_s": time_s[key]})
        for key, offs in calibrated.items():
            rows[key].append(score(fr, *estimate(fr, offs, "hybrid", correlation, prior_scale=False))
                             | {"states": len(offs), "time_s": time_s[key]})
        for key, (offs, k) in timed.items():
            frk = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i, k]), offsets=offs,
                                frames_per_state=k)
            rows[key].append(score(frk, *estimate(frk, offs, "hybrid", correlation), clean=fr.clean)
                             | {"states": len(offs), "time_s": time_s[key]})
        if bracketed:
            frb = bracket_prior(sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i, 99]),
                                              offsets=offsets["two"], bracket=BRACKET), net.uncertainty)
            highlights = frb.mask[None] & ~frb.use & frb.valid[0].all(axis=1)  # clipped, the bracket measured
        for key, (method, offs) in bracketed.items():
            est = estimate(frb, offs, method, correlation)
            hl = score(frb, *est, clean=fr.clean, cover=highlights)
            rows[key].append(score(frb, *est, clean=fr.clean) | {"states": len(offs), "time_s": time_s[key]}
                             | {"hl_inside": hl["inside"], "hl_elements": hl["elements"]})
        for key, (target, most) in adaptive_keys.items():
            *est, taken = adaptive(fr, target, max_states=most, correlation=correlation)
            rows[key].append(score(fr, *est) | {"states": len(taken), "time_s": acquisition_time_s(taken)})
        two_rows = models_rows(fr, offsets["two"], correlation)
        for key, k in model_keys.items():
            if k not in two_rows:
                continue
            n_states = {"single": 1, "reference4": 4, "reference4_models": 4}.get(k, 2)
            rows[key].append(two_rows[k] | {"states": n_states, "time_s": acquisition_time_s(
                {1: (0,), 4: FOUR_STATES}.get(n_states, offsets["two"]))})
    n = len(rows["hybrid2_models"])
    return {"data": str(data_dir) if not hasattr(data_dir, "manifest") else
            f"scene {data_dir.manifest.get('scene')} at poses {data_dir.manifest.get('poses_deg')}", "samples": n, "methods": {k: mean_rows(v) for k, v in rows.items()},
            "seconds": time.perf_counter() - t0}


def joint_compare(root, out_md, *, count: int, sets: Sequence[str], seed: int = 0, weights_dir=None,
                  two=None, three=None, echo=print, rig_scenes: Sequence[str] | None = None,
                  rig_poses: Sequence[float] = RIG_POSES_DEG, size: int | None = None) -> dict:
    """The per-element prior against the joint one (``--joint-compare``, :func:`joint_rows`) on
    ``count`` samples of each of ``sets``, the states ``two``/``three`` (default
    :data:`RIG_TWO`, :data:`RIG_THREE`, as the continuum run found them) and
    :data:`FOUR_STATES`; the frames as :func:`evaluate_set` makes them (same seeds). Writes
    ``out_md`` and its ``.json`` when given. ``rig_scenes``: instead of ``sets``, the default
    rig's named scenes at ``size`` (default :func:`rig_size`), one sample per turntable angle of
    ``rig_poses`` (:func:`rig_set`). :class:`polrig.errors.ConfigError` where the calibration has
    no joint prior (``python -m polrig.models.uncertainty_fit --joint``)."""
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    unknown = [s for s in sets if s not in SETS] if rig_scenes is None else []
    if unknown or count < 1:
        raise ConfigError(f"unknown set(s) {', '.join(unknown)} or --count {count} < 1; sets are {', '.join(SETS)}")
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    k = None if net.uncertainty is None else net.uncertainty.joint_correlation
    if k is None:
        raise ConfigError("the single-shot calibration has no joint prior (python -m polrig.models.uncertainty_fit "
                          "--data DIR [DIR ...] --joint --write)")
    offsets = {"two": tuple(two or RIG_TWO), "three": tuple(three or RIG_THREE), "four": FOUR_STATES}
    size = (rig_size() if size is None else int(size)) if rig_scenes is not None else SIZE
    result: dict = {"count": count if rig_scenes is None else len(rig_poses), "size": size, "seed": seed,
                    "offsets": {a: list(b) for a, b in offsets.items()}, "correlation": k.tolist(), "sets": {}}
    t0 = time.perf_counter()
    names = [n for n in SETS if n in sets] if rig_scenes is None else [f"rig_{n}" for n in rig_scenes]
    for name in names:
        tag = list(SETS).index(name) if rig_scenes is None else names.index(name)
        data = (make_set(pathlib.Path(root), name, SETS[name][1], count) if rig_scenes is None
                else rig_set(name[len("rig_"):], size, rig_poses, seed))
        rows: dict[str, list] = {}
        for ds, sensor, i, prior in set_samples(data, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i]))
            for key, row in joint_rows(fr, offsets, joint_priors(net.uncertainty)).items():
                rows.setdefault(key, []).append(row)
        result["sets"][name] = {"samples": len(rows.get("joint_models", [])),
                                "methods": {key: mean_rows(v) for key, v in rows.items()}}
        m = result["sets"][name]["methods"]
        echo(f"{name}: false acceptance " + " / ".join(f"{100 * m[f'{p}_models']['false_acceptance']:.1f}"
                                                     for p in JOINT_PRIORS) + " %; coverage 1-4 "
             + "; ".join(" / ".join(f"{100 * m[f'{p}_hybrid{n}']['coverage']:.1f}" for p in JOINT_PRIORS)
                         for n in range(1, 5)))
    result["seconds"] = time.perf_counter() - t0
    table = joint_markdown(result)
    echo(table)
    if out_md is not None:
        out_md, out_json = results_paths(out_md)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        what = (f"--count {count} --sets {','.join(sets)}` (models/continuum/run.py `joint_rows`); {count} samples per set"
                if rig_scenes is None else
                f"--rig-scenes {','.join(rig_scenes)} --rig-poses {','.join(f'{p:g}' for p in rig_poses)}` "
                "(models/continuum/run.py `joint_rows`); the default simulated rig's scenes, one sample per turntable "
                "angle")
        atomic_write_text(out_md, "# The network's prior: per element against joint\n\n`python -m polrig.models.continuum "
                          f"--joint-compare {what} at {size}x{size} (those with a lit object pixel scored); "
                          f"{result['seconds']:.0f} s on {os.cpu_count()} CPUs.\n\n" + table + "\n")
    return result


def min_states_compare(out_md, *, scenes: Sequence[str] = RIG_SCENES, poses: Sequence[float] = RIG_POSES_DEG,
                       size: int | None = None, targets: Sequence[float] = ADAPTIVE_TARGETS,
                       min_states: Sequence[int] | None = None, seed: int = 0, weights_dir=None,
                       echo=print) -> dict:
    """The adaptive capture's least number of states before a pose may stop
    (``--min-states-compare``; :func:`adaptive`'s ``min_states``, the capture's ``--min-states``):
    each of ``min_states`` (default: the capture's default, and 3) at each of ``targets`` on the
    default rig's named ``scenes`` at ``size`` (default :func:`rig_size`), one sample per
    turntable angle of ``poses``, the frames as :func:`run` makes them with ``--rig-scenes``
    (same seeds and tags: its adaptive rows at the capture's default are the ``min 2`` column
    here), the joint prior as captures use it. Writes ``out_md`` and its ``.json`` when given."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
    from polrig.sim.scene import SCENES

    if min_states is None:
        min_states = sorted({ADAPTIVE_MIN_STATES, 3})
    bad = [n for n in scenes if n not in SCENES]
    if bad or not scenes:
        raise ConfigError(f"--rig-scenes: unknown scene(s) {', '.join(bad) or '(none given)'}; scenes are "
                          f"{', '.join(SCENES)}")
    if not poses:
        raise ConfigError("--rig-poses: give at least one turntable angle")
    if not min_states or any(m < 1 or m > ADAPTIVE_MAX_STATES for m in min_states):
        raise ConfigError(f"--min-states-compare: give least numbers of states in 1..{ADAPTIVE_MAX_STATES}, "
                          f"got {list(min_states)}")
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    correlation = None if net.uncertainty is None else net.uncertainty.joint_correlation
    size = rig_size() if size is None else int(size)
    result: dict = {"size": size, "seed": seed, "poses_deg": [float(p) for p in poses], "targets": list(targets),
                    "share": ADAPTIVE_SHARE, "max_states": ADAPTIVE_MAX_STATES, "min_states": list(min_states),
                    "prior": "per element" if correlation is None else "joint", "scenes": {}}
    t0 = time.perf_counter()
    for tag, scene in enumerate(scenes):
        rows: dict[str, list] = {}
        for ds, sensor, i, prior in set_samples(rig_set(scene, size, poses, seed), net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i]))
            for t in targets:
                for m in min_states:
                    *est, taken = adaptive(fr, t, min_states=m, correlation=correlation)
                    rows.setdefault(f"{t:g}_min{m}", []).append(
                        score(fr, *est) | {"states": len(taken), "time_s": acquisition_time_s(taken)})
        result["scenes"][scene] = {"samples": len(next(iter(rows.values()), [])),
                                   "methods": {k: mean_rows(v) for k, v in rows.items()}}
        echo(f"{scene}: " + "; ".join(f"{k} {100 * v['coverage']:.1f} % {v['states']:.2f} states {v['time_s']:.2f} s"
                                     for k, v in result["scenes"][scene]["methods"].items()))
    result["seconds"] = time.perf_counter() - t0
    table = min_states_markdown(result)
    echo(table)
    if out_md is not None:
        out_md, out_json = results_paths(out_md)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        atomic_write_text(out_md, "# The adaptive capture's least number of states\n\n`python -m "
                          f"polrig.models.continuum --min-states-compare --rig-scenes {','.join(scenes)} --rig-poses "
                          f"{','.join(f'{p:g}' for p in poses)} --targets {','.join(f'{t:g}' for t in targets)}` "
                          "(models/continuum/run.py `min_states_compare`): the default simulated rig's scenes at "
                          f"{size}x{size}, one sample per turntable angle, the frames of `--rig-scenes`; "
                          f"{result['seconds']:.0f} s on {os.cpu_count()} CPUs. Each cell: "
                          + " / ".join(f"at least {m} states" for m in min_states) + ".\n\n" + table)
    return result


def run(root, out_md, *, count: int, search_count: int, sets: Sequence[str], seed: int = 0,
        weights_dir=None, two=None, three=None, echo=print,
        targets: Sequence[float] = ADAPTIVE_TARGETS, rig_scenes: Sequence[str] | None = None,
        rig_poses: Sequence[float] = RIG_POSES_DEG, size: int | None = None, only_models: bool = False) -> dict:
    """Generate the sets, search the states (unless ``two`` and ``three`` are given), evaluate,
    write ``out_md``, its ``.json`` and the accuracy-against-time plot (:func:`plot_trade`,
    ``.png``) when given.

    ``rig_scenes``: instead of ``sets``, the default rig's named scenes at ``size`` (default
    :func:`rig_size`), one sample per turntable angle of ``rig_poses`` (:func:`rig_set`), with
    the states ``two`` and ``three`` (default :data:`RIG_TWO`, :data:`RIG_THREE`: not searched).
    ``only_models``: only the lower-order model comparison at ``two`` (default :data:`RIG_TWO`,
    not searched; :func:`models_rows`, :func:`models_markdown`), no plot."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    if count < 1 or search_count < 1:
        raise ConfigError(f"--count and --search-count must be >= 1, got {count} and {search_count}")
    unknown = [s for s in sets if s not in SETS]
    if unknown and rig_scenes is None:
        raise ConfigError(f"unknown set(s) {', '.join(unknown)}; sets are {', '.join(SETS)}")
    if rig_scenes is not None:
        from polrig.sim.scene import SCENES

        bad = [n for n in rig_scenes if n not in SCENES]
        if bad or not rig_scenes:
            raise ConfigError(f"--rig-scenes: unknown scene(s) {', '.join(bad) or '(none given)'}; scenes are "
                              f"{', '.join(SCENES)}")
        if not rig_poses:
            raise ConfigError("--rig-poses: give at least one turntable angle")
        size = rig_size() if size is None else int(size)
        if size < 8 or size % 8:
            raise ConfigError(f"--size must be a positive multiple of 8 (the networks' size multiple), got {size}")
        two, three = two or RIG_TWO, three or RIG_THREE
        sets = [f"rig_{n}" for n in rig_scenes]
    elif size is not None:
        raise ConfigError("--size goes with --rig-scenes (the held-out sets are 64x64)")
    if out_md is not None:
        out_md, out_json = results_paths(out_md)
    root = pathlib.Path(root)
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    if net.uncertainty is None:
        raise ConfigError("the single-shot graph has no calibrated uncertainty (models/weights/uncertainty.json)")
    # the prior the captures use: the calibration's joint prior where it holds one
    correlation = net.uncertainty.joint_correlation
    t0 = time.perf_counter()
    result: dict = {"count": count if rig_scenes is None else len(rig_poses), "size": size or SIZE, "seed": seed, "offsets_deg": list(OFFSETS_DEG),
                    "adaptive_targets": list(targets), "adaptive_min_states": ADAPTIVE_MIN_STATES,
                    "prior": "per element" if correlation is None else "joint"}
    if only_models:
        two, three = two or RIG_TWO, three or RIG_THREE
    if two is None or three is None:
        dirs = [make_set(root, name, kw, search_count if "all" in name else max(1, search_count // 2))
                for name, kw in SEARCH_SETS.items()]
        result["search"] = search_states(dirs, net, seed, echo, correlation)
        two = two or tuple(result["search"]["best_two"])
        three = three or tuple(result["search"]["best_three"])
    result["offsets"] = {"two": list(two), "three": list(three), "four": list(FOUR_STATES)}
    if rig_scenes is not None:
        result["rig"] = {"scenes": list(rig_scenes), "poses_deg": [float(p) for p in rig_poses]}
    result["sets"] = {}
    for tag, name in enumerate(sets):
        d = (make_set(root, name, SETS[name][1], count) if rig_scenes is None
             else rig_set(name[len("rig_"):], size, rig_poses, seed))
        r = evaluate_set(d, net, {k: tuple(v) for k, v in result["offsets"].items()}, seed, tag, targets,
                         only_models, correlation)
        result["sets"][name] = r
        m = r["methods"]
        if only_models:
            echo(f"{name}: {r['samples']} scored; PSNR where a model holds: single "
                 f"{m['holds_single']['psnr_holds']:.2f}, hybrid 2 {m['holds_hybrid2']['psnr_holds']:.2f}, "
                 f"+ models {m['hybrid2_models']['psnr_holds']:.2f}, + geometry "
                 f"{m.get('hybrid2_geometry', {}).get('psnr_holds', float('nan')):.2f}")
            continue
        echo(f"{name}: {r['samples']} scored; PSNR single {m['single']['matrix_psnr']:.2f}, hybrid 1-4 "
             + " / ".join(f"{m[f'hybrid{k}']['matrix_psnr']:.2f}" for k in range(1, 5))
             + f", reference 3/4 {m['reference3']['matrix_psnr']:.2f} / {m['reference4']['matrix_psnr']:.2f}; "
             + "coverage " + " / ".join(f"{100 * m[k]['coverage']:.1f}" for k in
                                         ("single", "hybrid1", "hybrid2", "hybrid3", "hybrid4")))
    result["seconds"] = time.perf_counter() - t0
    table = models_markdown(result) if only_models else markdown(result)
    echo(table)
    if out_md is not None and only_models:
        out_md.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        atomic_write_text(out_md, "# Lower-order models at two states\n\n`python -m polrig.models.continuum "
                          f"--models-only --count {count} --sets {','.join(sets)}` (models/continuum/lower_order.py "
                          f"`models_rows`); {count} samples per set at {result['size']}x{result['size']} "
                          f"(those with a lit object pixel scored); {result['seconds']:.0f} s on "
                          f"{os.cpu_count()} CPUs; the hybrid's prior {prior_words(result)}.\n\n" + table + "\n")
    elif out_md is not None:
        out_md.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        plot_trade(result, out_md.with_suffix(".png"))
        n = result["size"]
        command = (f"--count {count} --search-count {search_count}" if rig_scenes is None else
                   f"--rig-scenes {','.join(rig_scenes)} --rig-poses {','.join(f'{p:g}' for p in rig_poses)} "
                   f"--size {n} --two {','.join(map(str, two))} --three {','.join(map(str, three))}")
        what = (f"{count} samples per set at {n}x{n}" if rig_scenes is None else
                f"the default simulated rig's scenes at {n}x{n}"
                + (" (the analyzer grid of its 512x512 colour sensor)" if n == rig_size() else "")
                + f", one sample per turntable angle {', '.join(f'{p:g}' for p in rig_poses)} deg "
                "(models/continuum/sets.py `rig_set`)")
        atomic_write_text(out_md, "# From one state to four: single-shot, hybrid, reference\n\n"
                          f"`python -m polrig.models.continuum {command}"
                          f" --targets {','.join(f'{t:g}' for t in targets)}`"
                          " (models/continuum/__init__.py: sets, frames, metrics and variants in its docstring). "
                          f"{what} (those with a lit object pixel scored); "
                          f"{search_line(result)}{result['seconds']:.0f} s on {os.cpu_count()} CPUs "
                          "(shipped network on onnxruntime, CPU); the hybrid's prior "
                          f"{prior_words(result)}.\n\n" + table + "\n")
    return result
