"""Accuracy of full-resolution single-shot against superpixel on held-out sets (issue 22, item 1).

``python -m polrig.models.evaluate_full_resolution --data DIR [DIR ...] [--out FILE.md]``

Each sample of a ``polrig sim dataset`` folder (analyzer images and truth at the set's size,
e.g. 256x256) is sampled into the raw mosaic a colour DoFP sensor (IMX250MYR layout, 4x4 cells)
would record: raw pixel ``(y, x)`` keeps the analyzer image of its own colour and angle there.
From that raw frame, three answers are scored against the truth with the matrix PSNR of
:mod:`polrig.models.evaluate` (peak = the largest true ``|m|`` on the object, object pixels only):

* **superpixel**: the networks on the superpixel grid (a quarter of the raw size per axis),
  scored against the truth averaged over each 4x4 cell (the sensor's native resolution);
* **superpixel, upsampled**: that answer bilinearly upsampled to the raw size (no detail),
  scored against the full-resolution truth;
* **full resolution**: :func:`polrig.models.full_resolution.lift` with the bilinear demosaic's detail,
  scored against the full-resolution truth;
* **networks on bilinear**: the networks on the full-resolution bilinear demosaic (the older
  route, ``polrig infer --demosaic bilinear``), scored against the full-resolution truth.

All on object pixels of the truth mask at the scored resolution whose 4x4 cell lies wholly on
the object (edge cells mix object and background in every method). Networks get the set's
incident state, stage zero axis and the cell-averaged mask (as the runtime would).
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import numpy as np

from polrig.models.data import check_network_size, lit_samples, load_dataset
from polrig.models.evaluate import psnr
from polrig.models.full_resolution import lift, upsample
from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
from polrig.sensor.stokes import stokes_from_analyzers

LAYOUT = "imx250myr"
METHODS = ("superpixel", "superpixel_upsampled", "full_resolution", "networks_on_bilinear")


def mosaic(analyzer: np.ndarray, layout) -> np.ndarray:
    """Raw mosaic ``(H, W)`` that a DoFP sensor of ``layout`` records of analyzer images
    ``(C, 4, H, W)``: each pixel keeps its own (colour, angle) image's value there."""
    from polrig.sensor.layouts import ANALYZER_ANGLES_DEG

    h, w = analyzer.shape[-2:]
    ph, pw = layout.period
    raw = np.empty((h, w), np.float32)
    for r in range(ph):
        for q in range(pw):
            k = list(ANALYZER_ANGLES_DEG).index(float(layout.angle_deg[r, q]))
            raw[r::ph, q::pw] = analyzer[int(layout.colour[r, q]), k, r::ph, q::pw]
    return raw


def cell_mean(img: np.ndarray, period: tuple[int, int]) -> np.ndarray:
    """Mean over each ``period`` cell of planes ``(..., H, W)`` -> ``(..., H // ph, W // pw)``."""
    ph, pw = period
    h, w = img.shape[-2] // ph, img.shape[-1] // pw
    x = img[..., : h * ph, : w * pw].reshape(img.shape[:-2] + (h, ph, w, pw))
    return x.mean(axis=(-3, -1))


def score_sample(model: SingleShotModel, ds, i: int, layout) -> dict[str, float]:
    """Matrix PSNR (dB) of the four answers (module docstring) for sample ``i``."""
    from polrig.sensor.demosaic import demosaic_float

    truth, s_in = ds["mueller"][i], ds["s_in"][i]
    period = layout.period
    raw = mosaic(ds["analyzer"][i], layout)
    axis = ds["stage_zero_axis"][i]
    mask_full = ds["mask"][i] > 0
    mask_sp = cell_mean(mask_full.astype(np.float32), period) > 0.5
    whole = cell_mean(mask_full.astype(np.float32), period) == 1.0  # cells wholly on the object
    whole_full = upsample(whole.astype(np.float32), period, mask_full.shape) == 1.0
    sp = demosaic_float(raw, layout, "superpixel")
    m_sp, aux = model.reconstruct(sp, s_in, mask=mask_sp, scale=1.0, stage_zero_axis=axis)
    peak = float(np.abs(truth[..., mask_full]).max())
    truth_sp = cell_mean(truth, period)
    out = {"superpixel": psnr(m_sp, truth_sp, whole, peak)}
    up = upsample(m_sp, period, mask_full.shape) / np.maximum(upsample(mask_sp.astype(np.float32), period,
                                                                       mask_full.shape), 1e-6)
    out["superpixel_upsampled"] = psnr(up, truth, whole_full, peak)
    bil = demosaic_float(raw, layout, "bilinear")
    m_full, _ = lift(m_sp, aux["mask"], stokes_from_analyzers(sp), stokes_from_analyzers(bil), s_in, period)
    out["full_resolution"] = psnr(m_full, truth, whole_full, peak)
    m_bil, _ = model.reconstruct(bil, s_in, mask=mask_full, scale=1.0, stage_zero_axis=axis)
    out["networks_on_bilinear"] = psnr(m_bil, truth, whole_full, peak)
    return out


def evaluate_set(data_dir, weights_dir=None, limit: int | None = None) -> dict:
    """Mean matrix PSNR per method over the lit samples of ``data_dir``."""
    from polrig.sensor.analyzer import resolve_layout

    ds = load_dataset(data_dir, limit)
    check_network_size(ds, data_dir)
    layout = resolve_layout(LAYOUT)
    ph, pw = layout.period
    if ds.shape[0] % (ph * 8) or ds.shape[1] % (pw * 8):
        raise ValueError(f"{data_dir}: sides must be multiples of {ph * 8} (the superpixel grid is a multiple of 8)")
    model = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    rows = [score_sample(model, ds, i, layout) for i in lit_samples(ds)]
    return {"data": str(data_dir), "samples": len(rows), "resolution": list(ds.shape),
            "matrix_psnr_db": {m: float(np.mean([r[m] for r in rows])) for m in METHODS}}


def markdown(results: Sequence[dict]) -> str:
    lines = ["| set | samples | raw size | superpixel (vs cell-mean truth) | superpixel upsampled | "
             "**full resolution** | networks on bilinear |", "|---|---|---|---|---|---|---|"]
    for r in results:
        p = r["matrix_psnr_db"]
        lines.append(f"| {pathlib.Path(r['data']).name} | {r['samples']} | {r['resolution'][1]}x{r['resolution'][0]} | "
                     f"{p['superpixel']:.2f} | {p['superpixel_upsampled']:.2f} | **{p['full_resolution']:.2f}** | "
                     f"{p['networks_on_bilinear']:.2f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import held_out_main

    return held_out_main(argv, "python -m polrig.models.evaluate_full_resolution", __doc__.split("\n\n")[0],
                         evaluate_set, markdown,
                         "# Full-resolution single-shot against superpixel (matrix PSNR, dB)\n\n"
                         "`python -m polrig.models.evaluate_full_resolution` (models/evaluate_full_resolution.py: "
                         "method and scoring in its docstring).")


if __name__ == "__main__":
    raise SystemExit(main())
