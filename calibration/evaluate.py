"""What a calibration buys: reference Mueller acquisition with the calibrated analyzer rows and
incident states versus the nominal (ideal) ones.

:func:`acquire_reference` drives a rig (HAL devices) through ``N`` stage angles, averages
frames, demosaics them (superpixel) and solves the per-pixel 3x3 Mueller block with
:func:`polrig.solve.reference.solve_reference`, either with the ideal analyzer and the nominal
generator (offset 0, ideal polarizer) or with a calibration set's per-pixel analyzer rows
(carried to the superpixel grid by the same demosaic) and fitted generator. Units: DN per
unit incident S0 (``docs/conventions.md``).
"""

from __future__ import annotations

import numpy as np

from polrig.calibration.calset import CalibrationSet
from polrig.calibration.generator import GeneratorModel
from polrig.sensor.analyzer import AnalyzerModel, layout_name_at, resolve_layout
from polrig.sensor.demosaic import demosaic_float
from polrig.solve.reference import solve_reference

DEFAULT_STATES_DEG = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0)


def superpixel_rows(model: AnalyzerModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-output-pixel analyzer rows ``(C, 4, 3, H', W')`` and offsets ``(C, 4, H', W')`` of
    a per-sensor-pixel model on the superpixel grid."""
    lay = model.mosaic_layout
    rows = model.rows()
    a = np.stack([demosaic_float(np.ascontiguousarray(rows[..., j], np.float32), lay,
                                 "superpixel") for j in range(3)], axis=2)
    off = demosaic_float(model.offset_dn.astype(np.float32), lay, "superpixel")
    return a.astype(np.float64), off.astype(np.float64)


def capture_states(rig, states_deg=DEFAULT_STATES_DEG, frames: int = 8) -> tuple[np.ndarray, list]:
    """Mean raw frames ``(N, H, W)`` (black level removed) at each stage angle, with the
    frame metadata."""
    out, metas = [], []
    for a in states_deg:
        rig.stage.move_to(float(a), wait=True, timeout_s=120.0)
        acc = None
        for _ in range(frames):
            f = rig.camera.grab()
            acc = f.raw.astype(np.float64) if acc is None else acc + f.raw
        out.append(acc / frames - f.meta.black_level_dn)
        metas.append(f.meta)
    return np.array(out), metas


def solve_mueller(raw_means: np.ndarray, layout: str, states_deg, *,
                  generator: GeneratorModel, analyzer: AnalyzerModel | None,
                  read_noise_dn: float = 1.0, gain_e_per_dn: float = 2.5, frames: int = 8):
    """Mueller images ``(C, 3, 3, H', W')`` from mean raw frames ``(N, H, W)``: ideal analyzer
    when ``analyzer`` is None, else its per-pixel rows (offsets removed). The weights use a
    shot + read noise variance of the mean of ``frames`` frames."""
    lay = resolve_layout(layout)
    meas = []
    for r in raw_means:
        meas.append(demosaic_float(np.ascontiguousarray(r, np.float32), lay, "superpixel"))
    meas = np.array(meas, dtype=np.float64)  # (N, C, 4, H', W')
    rows = None
    if analyzer is not None:
        rows, off = superpixel_rows(analyzer)
        meas = meas - off[None]
    var = (np.clip(meas, 0, None) / gain_e_per_dn + read_noise_dn ** 2) / frames
    s_in = generator.incident_stokes(np.asarray(states_deg, float))
    return solve_reference(s_in, meas, var, analyzer_rows=rows, dtype=np.float64)


def superpixel_mean(img: np.ndarray, layout: str) -> np.ndarray:
    """Average ``(..., H, W)`` over the layout's cells -> ``(..., H/ph, W/pw)``."""
    ph, pw = resolve_layout(layout).period
    h, w = img.shape[-2:]
    x = img[..., : h // ph * ph, : w // pw * pw]
    x = x.reshape(x.shape[:-2] + (h // ph, ph, w // pw, pw))
    return x.mean(axis=(-3, -1))


def truth_on_superpixel_grid(mueller: np.ndarray, layout: str) -> np.ndarray:
    """Per-colour truth Mueller images ``(C, 3, 3, H, W)`` on the superpixel grid: colour
    ``c`` averaged over the sensor pixels of colour ``c`` in each cell (where the superpixel
    demosaic takes its samples)."""
    lay = resolve_layout(layout)
    cmap = lay.colour_map(mueller.shape[-2:]).astype(float)
    out = []
    for c in range(lay.n_colours):
        w = (cmap == c).astype(float)
        num = superpixel_mean(mueller[c] * w, layout)
        out.append(num / superpixel_mean(w, layout))
    return np.array(out)


def uniform_cells(mueller: np.ndarray, lit: np.ndarray, layout: str,
                  tolerance: float = 0.02) -> np.ndarray:
    """Superpixel-grid mask ``(H', W')`` of cells that are lit everywhere and whose truth
    varies by less than ``tolerance`` (relative to the cell's mean ``m00``) in every element:
    there the superpixel demosaic's spatial offsets between analyzer samples do not matter
    and an error is the calibration's."""
    ph, pw = resolve_layout(layout).period
    h, w = mueller.shape[-2:]
    x = mueller[..., : h // ph * ph, : w // pw * pw]
    x = x.reshape(x.shape[:-2] + (h // ph, ph, w // pw, pw))
    spread = (x.max(axis=(-3, -1)) - x.min(axis=(-3, -1)))  # (C, 3, 3, H', W')
    m00 = np.abs(x[:, 0, 0].mean(axis=(-3, -1)))  # (C, H', W')
    ok = np.all(spread <= tolerance * m00[:, None, None], axis=(0, 1, 2)) & np.all(m00 > 0, axis=0)
    return ok & (superpixel_mean(lit.astype(float), layout) == 1.0)


def mueller_rmse(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """RMS over the masked pixels and the 9 elements, relative to the mean true ``m00``."""
    e = (estimate - truth)[:, :, :, mask]
    return float(np.sqrt(np.mean(e ** 2)) / np.mean(truth[:, 0, 0][:, mask]))


def compare_models(rig, cs: CalibrationSet, truth_mueller: np.ndarray, truth_mask: np.ndarray,
                   states_deg=DEFAULT_STATES_DEG, frames: int = 8,
                   others: dict[str, CalibrationSet] | None = None) -> dict[str, float]:
    """Relative Mueller RMSE of reference acquisition with (a) the ideal analyzer and the
    nominal generator, (b) the ideal analyzer and the calibrated generator, (c) the full
    calibration, and (d) each of ``others`` (named calibration sets, e.g. one calibrated with
    another model; key ``"calibrated:NAME"``), all from the same frames. ``truth_mueller``
    ``(C, 3, 3, h, w)`` on the superpixel grid and ``truth_mask`` ``(h, w)``."""
    raw, metas = capture_states(rig, states_deg, frames)
    w, h, ox, oy = rig.camera.roi
    layout = layout_name_at(rig.camera.layout, ox, oy)
    res = {}
    runs = [("ideal", GeneratorModel(0.0, np.inf), None),
            ("ideal_analyzer_calibrated_generator", cs.generator, None),
            ("calibrated", cs.generator, cs.analyzer_model)]
    runs += [(f"calibrated:{k}", o.generator, o.analyzer_model) for k, o in (others or {}).items()]
    for name, gen, an in runs:
        r = solve_mueller(raw, layout, states_deg, generator=gen, analyzer=an, frames=frames)
        m = truth_mask & np.all(r.mask == 0, axis=0)
        res[name] = mueller_rmse(r.mueller, truth_mueller, m)
    res["improvement"] = res["ideal"] / res["calibrated"]
    return res
