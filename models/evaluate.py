"""Evaluate single-shot reconstruction on a held-out simulated set: the paper's two tables.

``polrig evaluate --data DIR`` (or ``python -m polrig.models.evaluate``) runs seven methods on every
sample of a dataset folder (``polrig sim dataset --holdout`` output: seeds and shape/material
families never seen in training) with a lit object pixel (:func:`polrig.models.data.has_lit_object`;
a set with none is refused) and writes a Markdown table (``--out``, default
``runs/evaluate/single_shot.md``; the published tables live in ``benchmarks/results/``) plus
the numbers as JSON next to it (same name, ``.json``).

Methods (rows), all producing normalised Mueller images ``(C, 3, 3, H, W)``:

* **Full model**: ``single_shot.onnx`` (PIPNet -> pBRDF -> PMMNet) through onnxruntime.
* **PIPNet-pBRDF**: the same graph's ``mueller_init`` (analytic pBRDF on PIPNet's outputs,
  eta = 1.5, ks = 1, kd from PIPNet).
* **Best-fit pBRDF (GT parameters)**: :func:`polrig.optics.pbrdf.specular_diffuse_blocks` on the
  true normal, light and view directions and roughness (eta = 1.5), with one specular gain and
  one diffuse gain per colour (times the true kd) fitted per image to the true Mueller image by
  least squares: an upper bound of what the analytic model can do.
* **Direct Stokes->MM**: ``direct.onnx``, the same backbone regressing 27 elements.
* **Four-state reference (same noise)**: captures under polarizer states 0/45/90/135 deg
  rendered from the true Mueller image with the ideal analyzers
  (:func:`polrig.solve.reference.forward_measurements`), Gaussian noise of the variance the dataset's
  own single-shot images show (``var = a + b I``, fitted on the residuals of its samples with a
  lit object pixel against the noise-free rendering, :func:`fit_noise_model`), solved by :func:`polrig.solve.reference.solve_reference`.
* **Full model, mirror-averaged** and **Direct Stokes->MM, mirror-averaged**: each graph run
  on the sample and on its left-right mirror image, the two answers averaged
  (:mod:`polrig.models.mirror`); both networks get it, so the two rows compare like with like.

Incident frame: each sample's stage zero axis (``stage_zero_axis`` of the shards, which may
differ from the training one) is handled by
:meth:`polrig.models.runtime.SingleShotModel.run_rig_frame`: the graphs run in their training frame
and the results are turned into the sample's frame (the direct baseline, which predicts no
light direction, is turned with the full model's ``wi``); for a sample in the training frame
this is exactly one plain graph call.

Metrics (all over the object mask, averaged over images):

Table 1 (observed state ``s_in``): matrix PSNR (dB, peak = max |m| of the true image, MSE over
the 27 elements), rendering PSNR and SSIM of the four analyzer images per colour rendered under
``s_in`` (peak = max of the true rendering; SSIM of Wang et al. 2004, Gaussian window sigma 1.5,
averaged over mask pixels), DoLP MAE and AoLP wrapped error (deg, ``min(|d|, 180 - |d|)``, over
pixels with true DoLP >= 0.02) of the emergent Stokes under ``s_in``.

Table 2 (11 held-out incident states: linear polarizer at 8 + 16.36 k deg, k = 0..10, on unit
unpolarized light, ``S = 0.5 [1, cos 2t, sin 2t]``): forward Stokes relative L2
``sqrt(sum |S_pred - S_true|^2 / sum |S_true|^2)`` over mask pixels, colours and states, DoLP
MAE, AoLP error; GK and coherency (PSD) pass rates of the 3x3 blocks
completed to 4x4 by :func:`polrig.optics.realizability.complete_linear` (``max_min_eigenvalue``),
tested with :func:`polrig.optics.realizability.is_physical_gk` and
:func:`polrig.optics.realizability.is_physical_coherency`, before and after Cloude filtering of the
completed matrix (:func:`polrig.optics.realizability.cloude_filter`), on up to
``realizability_pixels`` random (pixel, colour) blocks per image of the whole object mask, and
again (``gk_lit``, ``psd_lit``, before filtering) on blocks of its lit pixels only (``lit`` of the
dataset: facing the light, not shadowed). In shadow the true matrix is zero and every method,
the four-state reference included, returns noise, so the lit rates say how physical the
estimates are where there is a signal.
"""

from __future__ import annotations

import json
import pathlib
import time

import cv2
import numpy as np

from polrig.atomic import atomic_write_text, temporary_sibling
from polrig.errors import ConfigError
from polrig.models.data import (
    Dataset,
    check_network_size,
    has_lit_object,
    lit_samples,
    load_dataset,
)
from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
from polrig.optics import pbrdf, realizability
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.stokes import aolp_deg, dolp, ideal_analyzer_matrix
from polrig.solve import reference

METHODS = ("full", "pipnet_pbrdf", "bestfit_pbrdf", "direct", "reference4", "full_mirror", "direct_mirror")
METHOD_NAMES = {"full": "Full model (PIPNet + pBRDF + PMMNet)", "pipnet_pbrdf": "PIPNet-pBRDF alone",
                "bestfit_pbrdf": "Best-fit pBRDF (GT parameters)", "direct": "Direct Stokes->MM (same backbone)",
                "reference4": "Four-state reference (same noise)",
                "full_mirror": "Full model, mirror-averaged (2 passes)",
                "direct_mirror": "Direct Stokes->MM, mirror-averaged (2 passes)"}
HELD_OUT_STATES_DEG = tuple(8.0 + k * 180.0 / 11.0 for k in range(11))
REFERENCE_STATES_DEG = (0.0, 45.0, 90.0, 135.0)
AOLP_MIN_DOLP = 0.02


# ----------------------------------------------------------------------------- helpers

def emergent_stokes(m: np.ndarray, s_in: np.ndarray) -> np.ndarray:
    """``M S`` for a Mueller image ``(C, 3, 3, H, W)`` and one state ``(3,)`` -> ``(C, 3, H, W)``."""
    return np.einsum("cabhw,b->cahw", m, np.asarray(s_in, m.dtype))


def render_analyzer(m: np.ndarray, s_in: np.ndarray) -> np.ndarray:
    """Ideal analyzer images ``(C, 4, H, W)`` of ``M`` under ``s_in``."""
    return np.einsum("jb,cbhw->cjhw", ideal_analyzer_matrix().astype(m.dtype), emergent_stokes(m, s_in))


def forward_l2(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """Relative L2 ``sqrt(sum |S_pred - S_true|^2 / sum |S_true|^2)`` of the emergent Stokes of
    Mueller images ``(C, 3, 3, H, W)`` over the masked pixels, colours and the
    :data:`HELD_OUT_STATES_DEG` polarizer states."""
    num = den = 0.0
    for theta in HELD_OUT_STATES_DEG:
        s = polarizer_stokes(np.deg2rad(theta))
        sp, st = emergent_stokes(pred, s), emergent_stokes(truth, s)
        num += float(np.sum((sp - st)[..., mask].astype(np.float64) ** 2))
        den += float(np.sum(st[..., mask].astype(np.float64) ** 2))
    return float(np.sqrt(num / den)) if den > 0 else float("nan")


def psnr(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, peak: float) -> float:
    """PSNR in dB over the masked pixels of planes ``(..., H, W)``."""
    err = (pred - truth)[..., mask]
    mse = float(np.mean(err.astype(np.float64) ** 2)) if err.size else float("nan")
    if not mse > 0:
        return float("inf") if mse == 0 else float("nan")
    return 10.0 * np.log10(peak * peak / mse)


def ssim_masked(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, peak: float) -> float:
    """Mean SSIM (Wang et al., IEEE TIP 13(4) 2004; Gaussian window sigma 1.5) of planes
    ``(..., H, W)`` over the masked pixels."""
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    vals = []
    for p, t in zip(pred.reshape(-1, *pred.shape[-2:]), truth.reshape(-1, *truth.shape[-2:])):
        p, t = p.astype(np.float64), t.astype(np.float64)
        mp, mt = blur(p), blur(t)
        vp, vt, cov = blur(p * p) - mp * mp, blur(t * t) - mt * mt, blur(p * t) - mp * mt
        s = ((2 * mp * mt + c1) * (2 * cov + c2)) / ((mp * mp + mt * mt + c1) * (vp + vt + c2))
        vals.append(s[mask])
    return float(np.mean(np.concatenate(vals))) if vals else float("nan")


def _dolp_aolp_errors(sp: np.ndarray, st: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    valid_t = np.broadcast_to(mask, st.shape[:1] + mask.shape) & (st[:, 0] > 0)
    valid_p = valid_t & (sp[:, 0] > 0)
    dt, dp = dolp(st, valid_t), dolp(sp, valid_p)
    at, ap = aolp_deg(st, valid_t), aolp_deg(sp, valid_p)
    d = np.abs(ap - at)
    d = np.minimum(d, 180.0 - d)
    return np.abs(dp - dt)[valid_t], d[valid_t & (dt >= AOLP_MIN_DOLP)]


def fit_noise_model(ds: Dataset, limit: int = 64) -> tuple[float, float]:
    """``(a, b)`` of ``var = a + b I`` (normalised units) from the residual between the
    dataset's analyzer images and the noise-free rendering of its true Mueller images, over
    the first ``limit`` samples with a lit object pixel (:func:`polrig.models.data.has_lit_object`,
    the samples :func:`evaluate` scores: an unlit sample is pure noise divided by the 1 DN
    floor of its ``scale``, hundreds of times the noise of a lit one in normalised units).

    Robust to saturated highlights (clipped analyzer values, huge residuals): the variance of
    each of 20 signal bins is ``(1.4826 MAD)^2`` and the line is fitted to the bins by least
    squares weighted by their counts."""
    xs, rs = [], []
    for i in lit_samples(ds)[:limit]:
        mask = ds["mask"][i] > 0
        clean = render_analyzer(ds["mueller"][i], ds["s_in"][i])
        xs.append(clean[:, :, mask].ravel())
        rs.append((ds["analyzer"][i] - clean)[:, :, mask].ravel())
    x, r = np.concatenate(xs), np.concatenate(rs)
    keep = (x >= 0) & (x <= 1.0)
    x, r = x[keep], r[keep]
    if x.size < 100:
        return 1e-8, 0.0
    edges = np.quantile(x, np.linspace(0, 1, 21))
    cx, cv, cw = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (x >= lo) & (x <= hi)
        if sel.sum() < 20:
            continue
        rr = r[sel]
        cx.append(float(np.median(x[sel])))
        cv.append(float((1.4826 * np.median(np.abs(rr - np.median(rr)))) ** 2))
        cw.append(float(sel.sum()))
    cx, cv, cw = (np.asarray(v) for v in (cx, cv, cw))
    a_mat = np.stack([np.ones_like(cx), cx], 1) * np.sqrt(cw)[:, None]
    coef, *_ = np.linalg.lstsq(a_mat, cv * np.sqrt(cw), rcond=None)
    return float(max(coef[0], 1e-12)), float(max(coef[1], 0.0))


def bestfit_pbrdf(ds: Dataset, i: int) -> np.ndarray:
    """pBRDF with the true geometry and roughness, gains fitted by least squares (see module)."""
    mask = ds["mask"][i] > 0
    hw = lambda a: np.moveaxis(a, 0, -1)[mask]  # noqa: E731  (3, H, W) -> (P, 3)
    ms, md = pbrdf.specular_diffuse_blocks(hw(ds["normal"][i]), hw(ds["wi"][i]), hw(ds["wo"][i]),
                                           alpha=float(ds["alpha"][i]), eta=1.5,
                                           stage_zero_axis=ds["stage_zero_axis"][i], camera_x_axis=[1.0, 0, 0])
    kd = hw(ds["kd"][i])  # (P, C)
    truth = np.moveaxis(ds["mueller"][i], (-2, -1), (0, 1))[mask]  # (P, C, 3, 3)
    n_c = truth.shape[1]
    # Unknowns: g_s, g_1..g_C; rows: every (pixel, colour, element).
    cols = [np.broadcast_to(ms[:, None], truth.shape).ravel()]
    for c in range(n_c):
        d = np.zeros(truth.shape)
        d[:, c] = kd[:, c, None, None] * md
        cols.append(d.ravel())
    g, *_ = np.linalg.lstsq(np.stack(cols, 1), truth.ravel(), rcond=None)
    fit = g[0] * ms[:, None] + (g[1:][None, :, None, None] * kd[:, :, None, None]) * md[:, None]
    out = np.zeros(ds["mueller"][i].shape, np.float32)
    out[..., mask] = np.moveaxis(fit, (0,), (-1,)).astype(np.float32)
    return out


def reference_four_state(ds: Dataset, i: int, noise: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Four-state reference solve at the dataset's single-shot noise (see module)."""
    truth = ds["mueller"][i]
    states = polarizer_stokes(np.deg2rad(REFERENCE_STATES_DEG))
    clean = reference.forward_measurements(truth, states)
    var = noise[0] + noise[1] * np.clip(clean, 0, None)
    measured = clean + rng.normal(size=clean.shape) * np.sqrt(var)
    res = reference.solve_reference(states, measured, var)
    return (res.mueller * (ds["mask"][i] > 0)).astype(np.float32)


def network_inputs(ds: Dataset, i: int) -> tuple:
    return (ds["analyzer"][i][None], ds["mask"][i][None, None], ds["s_in"][i][None], ds["wo"][i][None],
            ds["stage_zero_axis"][i][None])


# ----------------------------------------------------------------------------- metrics

def _realizability(pred: np.ndarray, mask: np.ndarray, rng: np.random.Generator, pixels: int,
                   filtered: bool = True) -> dict[str, float]:
    """GK and coherency pass rates of up to ``pixels`` random (pixel, colour) 3x3 blocks of
    ``pred`` (C,3,3,H,W) in ``mask``, completed to 4x4 (``max_min_eigenvalue``), before and
    (``filtered``) after Cloude filtering."""
    blocks = np.moveaxis(pred, (-2, -1), (0, 1))[mask].reshape(-1, 3, 3)
    if not len(blocks):
        return {}
    if len(blocks) > pixels:
        blocks = blocks[rng.choice(len(blocks), pixels, replace=False)]
    completed = realizability.complete_linear(blocks.astype(np.float64))
    out = {"gk_before": float(np.mean(realizability.is_physical_gk(completed))),
           "psd_before": float(np.mean(realizability.is_physical_coherency(completed)))}
    if filtered:
        cf = realizability.cloude_filter(completed)
        out.update(gk_after=float(np.mean(realizability.is_physical_gk(cf))),
                   psd_after=float(np.mean(realizability.is_physical_coherency(cf))))
    return out


def _sample_metrics(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, s_in: np.ndarray,
                    rng: np.random.Generator, realizability_pixels: int,
                    lit: np.ndarray | None = None, lit_rng: np.random.Generator | None = None) -> dict[str, float]:
    out: dict[str, float] = {}
    peak_m = float(np.abs(truth[..., mask]).max()) if mask.any() else 1.0
    out["matrix_psnr"] = psnr(pred, truth, mask, peak_m)
    rp, rt = render_analyzer(pred, s_in), render_analyzer(truth, s_in)
    peak_r = float(rt[..., mask].max()) if mask.any() else 1.0
    out["render_psnr"] = psnr(rp, rt, mask, peak_r)
    out["render_ssim"] = ssim_masked(rp, rt, mask, peak_r)
    dd, da = _dolp_aolp_errors(emergent_stokes(pred, s_in), emergent_stokes(truth, s_in), mask)
    out["dolp_mae"], out["aolp_err"] = float(np.mean(dd)), float(np.mean(da)) if da.size else float("nan")
    # Held-out states.
    out["fwd_l2"] = forward_l2(pred, truth, mask)
    d_all, a_all = [], []
    for theta in HELD_OUT_STATES_DEG:
        s = polarizer_stokes(np.deg2rad(theta))
        dd, da = _dolp_aolp_errors(emergent_stokes(pred, s), emergent_stokes(truth, s), mask)
        d_all.append(dd)
        a_all.append(da)
    out["fwd_dolp_mae"] = float(np.mean(np.concatenate(d_all)))
    a_cat = np.concatenate(a_all)
    out["fwd_aolp_err"] = float(np.mean(a_cat)) if a_cat.size else float("nan")
    # Realizability on a pixel sample: the whole object, then its lit part.
    out.update(_realizability(pred, mask, rng, realizability_pixels))
    if lit is not None:
        r = _realizability(pred, mask & lit, lit_rng or rng, realizability_pixels, filtered=False)
        out["gk_lit"], out["psd_lit"] = r.get("gk_before", float("nan")), r.get("psd_before", float("nan"))
    return out


def evaluate(data_dir: str | pathlib.Path, weights_dir: str | pathlib.Path | None = None, *,
             limit: int | None = None, seed: int = 0, realizability_pixels: int = 400,
             methods: tuple[str, ...] = METHODS, deadline: float | None = None, min_samples: int = 1,
             echo=print) -> dict:
    """Run every method on every sample; returns ``{"methods": {name: {metric: mean}}, ...}``.

    ``methods``: a subset of :data:`METHODS` to score (default all; the full model's graph runs
    whatever the subset, the direct baseline's rotation needs its light). A subset draws fewer
    numbers from the shared random stream, so the realizability rates (random pixel samples)
    and the reference's noise are not the same draws as in a full evaluation; every other
    metric is. ``deadline`` (a :func:`time.perf_counter` value): no new sample is started once
    it has passed and ``min_samples`` samples are scored; the samples are taken in order, so
    ``limit = result["samples_visited"]`` scores exactly the same ones again (e.g. with other
    weights)."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ConfigError(f"unknown method(s) {unknown or 'none given'}; methods are {', '.join(METHODS)}")
    wanted = set(methods)
    ds = load_dataset(data_dir, limit)
    check_network_size(ds, data_dir)
    if not lit_samples(ds):
        raise ConfigError(f"{data_dir}: no sample with a lit object pixel ({len(ds)} sample(s), none scorable)")
    wd = pathlib.Path(weights_dir) if weights_dir is not None else WEIGHTS_DIR
    full = SingleShotModel.load(wd)
    direct = SingleShotModel.load(wd, graph="direct.onnx")
    noise = fit_noise_model(ds) if "reference4" in wanted else None  # only the reference uses it
    rng = np.random.default_rng(seed)
    lit_rng = np.random.default_rng([seed, 1])  # its own stream: the other numbers do not depend on it
    # the mirror-averaged rows sample with streams of their own, so they leave the others' numbers as they were
    streams = {m: (rng, lit_rng) for m in METHODS}
    streams.update({m: (np.random.default_rng([seed, 2, j]), np.random.default_rng([seed, 3, j]))
                    for j, m in enumerate(("full_mirror", "direct_mirror"))})
    per: dict[str, list[dict[str, float]]] = {m: [] for m in METHODS if m in wanted}
    run_graphs = {"full"} | ({"full_mirror"} if wanted & {"full_mirror", "direct_mirror"} else set())
    times: dict[str, float] = {m: 0.0 for m in METHODS if m in wanted | run_graphs}
    t_start = time.time()
    skipped = visited = 0
    for i in range(len(ds)):
        if deadline is not None and visited - skipped >= min_samples and time.perf_counter() > deadline:
            break
        visited += 1
        mask = ds["mask"][i] > 0
        truth, s_in = ds["mueller"][i], ds["s_in"][i]
        if not has_lit_object(ds, i):
            skipped += 1  # nothing lit on the object: no signal to score
            continue
        preds = {}
        t = time.perf_counter()
        out = full.run_rig_frame(*network_inputs(ds, i))
        times["full"] += time.perf_counter() - t
        preds["full"], preds["pipnet_pbrdf"] = out["mueller"][0], out["mueller_init"][0]
        if "bestfit_pbrdf" in wanted:
            t = time.perf_counter()
            preds["bestfit_pbrdf"] = bestfit_pbrdf(ds, i)
            times["bestfit_pbrdf"] += time.perf_counter() - t
        if "direct" in wanted:
            t = time.perf_counter()
            preds["direct"] = direct.run_rig_frame(*network_inputs(ds, i), rotate_with=out["wi"])["mueller"][0]
            times["direct"] += time.perf_counter() - t
        if "reference4" in wanted:
            t = time.perf_counter()
            preds["reference4"] = reference_four_state(ds, i, noise, rng)
            times["reference4"] += time.perf_counter() - t
        if "full_mirror" in run_graphs:
            t = time.perf_counter()  # polrig.models.mirror: the capture and its mirror image, averaged
            out_m = full.run_rig_frame(*network_inputs(ds, i), mirror_average=True)
            preds["full_mirror"] = out_m["mueller"][0]
            times["full_mirror"] += time.perf_counter() - t
        if "direct_mirror" in wanted:
            t = time.perf_counter()
            preds["direct_mirror"] = direct.run_rig_frame(*network_inputs(ds, i), rotate_with=out_m["wi"],
                                                          mirror_average=True)["mueller"][0]
            times["direct_mirror"] += time.perf_counter() - t
        lit = (ds["lit"][i] > 0) if "lit" in ds.arrays else None
        preds = {name: pred for name, pred in preds.items() if name in wanted}
        for name, pred in preds.items():
            per[name].append(_sample_metrics(pred.astype(np.float32), truth, mask, s_in, streams[name][0],
                                             realizability_pixels, lit, streams[name][1]))
    n = len(next(iter(per.values())))
    scores = {m: {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]} for m, rows in per.items() if rows}
    families = sorted({int(f) for f in ds["family"]}) if "family" in ds.arrays else []
    result = {"data": str(data_dir), "holdout": bool(ds.manifest.get("holdout", False)), "samples": n,
              "skipped_unlit": skipped, "resolution": list(ds.shape), "families": families,
              "noise_model": None if noise is None else {"a": noise[0], "b": noise[1]}, "methods": scores,
              "samples_visited": visited,
              "seconds_per_sample": {m: times[m] / max(n, 1) for m in METHODS if m in times},
              "held_out_states_deg": list(HELD_OUT_STATES_DEG), "manifest": ds.manifest,
              "eval_seconds": time.time() - t_start}
    echo(markdown_tables(result))
    return result


def set_words(result: dict) -> str:
    """What the evaluated set is, from its dataset manifest's ``holdout``: ``Held-out set``
    (shape families never trained on, ``polrig sim dataset --holdout``) or ``Set of the training
    families`` (new scenes of them unless it is the training data itself; a result from before
    the key: held out, as ``polrig evaluate`` then assumed)."""
    return "Held-out set" if result.get("holdout", True) else "Set of the training families"


def markdown_tables(result: dict) -> str:
    """The paper's two tables as Markdown."""
    m = result["methods"]
    lines = [f"{set_words(result)}: {result['samples']} samples at {result['resolution'][0]}x{result['resolution'][1]}"
             f" ({result.get('skipped_unlit', 0)} with no lit object pixel skipped).", "",
             "| Method | Matrix PSNR (dB) ↑ | Rendering PSNR (dB) ↑ | Rendering SSIM ↑ | DoLP MAE ↓ | AoLP err. (deg) ↓ |",
             "|---|---|---|---|---|---|"]
    for k in METHODS:
        if k in m:
            r = m[k]
            lines.append(f"| {METHOD_NAMES[k]} | {r['matrix_psnr']:.2f} | {r['render_psnr']:.2f} | "
                         f"{r['render_ssim']:.4f} | {r['dolp_mae']:.4f} | {r['aolp_err']:.2f} |")
    lit = any("gk_lit" in m[k] for k in m)
    lines += ["", "| Method | Forward Stokes L2 (rel.) ↓ | DoLP MAE ↓ | AoLP err. (deg) ↓ | GK pass | PSD pass | GK pass (Cloude) | PSD pass (Cloude) |"
              + (" GK pass (lit) | PSD pass (lit) |" if lit else ""),
              "|---|---|---|---|---|---|---|---|" + ("---|---|" if lit else "")]
    for k in METHODS:
        if k in m:
            r = m[k]
            lines.append(f"| {METHOD_NAMES[k]} | {r['fwd_l2']:.4f} | {r['fwd_dolp_mae']:.4f} | {r['fwd_aolp_err']:.2f} | "
                         f"{100 * r['gk_before']:.1f}% | {100 * r['psd_before']:.1f}% | "
                         f"{100 * r['gk_after']:.1f}% | {100 * r['psd_after']:.1f}% |"
                         + (f" {100 * r.get('gk_lit', float('nan')):.1f}% | {100 * r.get('psd_lit', float('nan')):.1f}% |"
                            if lit else ""))
    return "\n".join(lines)


def results_paths(out_md: str | pathlib.Path) -> tuple[pathlib.Path, pathlib.Path]:
    """``(Markdown, JSON)`` paths of :func:`write_results` for ``out_md`` (a ``.md`` file; the
    JSON is the same name with ``.json``). :class:`ConfigError` (one line naming the path)
    unless both can be written: ``out_md`` ends in ``.md``, neither is a folder, and the folder
    exists (or can be made) and takes a new file. Call before the evaluation."""

    out_md = pathlib.Path(out_md)
    if out_md.suffix.lower() != ".md":
        raise ConfigError(f"--out {out_md}: give a Markdown file name ending in .md (the numbers go next to it "
                          f"as .json)")
    out_json = out_md.with_suffix(".json")
    for path in (out_md, out_json):
        if path.is_dir():
            raise ConfigError(f"--out {out_md}: {path} is a folder")
    folder = out_md.parent
    existing = next(p for p in (folder, *folder.parents, pathlib.Path(".")) if p.exists())
    if not existing.is_dir():
        raise ConfigError(f"--out {out_md}: {existing} is not a folder")
    try:  # the folder (or the one it will be made in) takes a new file: read-only folders, /proc, ... fail here
        probe = temporary_sibling(existing / out_md.name)
        probe.open("x").close()
        probe.unlink()
    except OSError as exc:
        raise ConfigError(f"--out {out_md}: cannot write in {existing} ({exc.strerror or exc})") from None
    return out_md, out_json


def write_results(result: dict, out_md: str | pathlib.Path) -> None:
    """The tables as Markdown at ``out_md`` and the numbers as JSON next to it (same name,
    ``.json``; :func:`results_paths`), each written atomically."""

    out_md, out_json = results_paths(out_md)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_json, json.dumps(result, indent=2, default=str))
    atomic_write_text(out_md, f"# Single-shot Mueller reconstruction: evaluation on a {set_words(result).lower()}\n\n"
                      "Produced by `polrig evaluate` (models/evaluate.py; metric definitions in its docstring).\n\n"
                      + markdown_tables(result) + "\n")
