"""Accuracy of the runtime's speed-ups against the default route on held-out sets (issue 22, item 2).

``python -m polrig.models.evaluate_speed_modes --data DIR [DIR ...] [--out FILE.md]``

Two comparisons, each scored with the matrix PSNR of :mod:`polrig.models.evaluate` (peak = the largest
true ``|m|`` on the object):

* **network binning** (:func:`polrig.models.full_resolution.reconstruct_binned`, ``polrig infer
  --network-binning 2``): each sample is sampled into the IMX250MYR colour mosaic
  (:func:`polrig.models.evaluate_full_resolution.mosaic`), demosaicked to the superpixel grid (a
  quarter of the set's size per axis), and reconstructed there by the networks (binning 1, the
  default) and by the networks on that grid binned 2x2 then lifted back (binning 2); both are
  scored against the truth averaged over each 4x4 cell, on pixels whose 8x8 raw block lies
  wholly on the object (edge blocks mix object and background in both). Both are also lifted
  to the raw grid with the bilinear demosaic's detail (:func:`polrig.models.full_resolution.lift`, the
  full-resolution route) and scored against the full-resolution truth on the same blocks.
* **light-direction probe** (:func:`polrig.models.runtime.probe_shape`): the networks on the set's own
  analyzer images (so sets of 256x256 or more take the probe), once with the probe (the
  runtime's route: reduced passes for the incident-frame angle, then one full-size pass) and
  once with two full-size passes (the route before), scored against the truth on the object.

Networks get the set's incident state, stage zero axis and mask (cell-averaged on the grids).
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence

import numpy as np

from polrig.models import runtime
from polrig.models.data import check_network_size, lit_samples, load_dataset
from polrig.models.evaluate import psnr
from polrig.models.evaluate_full_resolution import LAYOUT, cell_mean, mosaic
from polrig.models.full_resolution import lift, reconstruct_binned
from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel
from polrig.sensor.stokes import stokes_from_analyzers

METHODS = ("superpixel", "superpixel_binning_2", "full_resolution", "full_resolution_binning_2",
           "two_full_passes", "probe")


def score_sample(model: SingleShotModel, ds, i: int, layout) -> dict[str, float]:
    """Matrix PSNR (dB) of the four answers (module docstring) of sample ``i``."""
    from polrig.sensor.demosaic import demosaic_float

    truth, s_in, axis = ds["mueller"][i], ds["s_in"][i], ds["stage_zero_axis"][i]
    mask_full = ds["mask"][i] > 0
    peak = float(np.abs(truth[..., mask_full]).max())
    period = layout.period
    sp = demosaic_float(mosaic(ds["analyzer"][i], layout), layout, "superpixel")
    mask_sp = cell_mean(mask_full.astype(np.float32), period) > 0.5
    truth_sp = cell_mean(truth, period)
    block = (2 * period[0], 2 * period[1])
    whole = cell_mean(mask_full.astype(np.float32), block) == 1.0  # 8x8 raw blocks wholly on the object
    whole_sp = np.zeros(mask_sp.shape, bool)
    whole_sp[: 2 * whole.shape[0], : 2 * whole.shape[1]] = np.repeat(np.repeat(whole, 2, 0), 2, 1)
    m1, aux1 = model.reconstruct(sp, s_in, mask=mask_sp, scale=1.0, stage_zero_axis=axis)
    m2, aux2 = reconstruct_binned(model, sp, s_in, 2, mask=mask_sp, scale=1.0, stage_zero_axis=axis)
    out = {"superpixel": psnr(m1, truth_sp, whole_sp, peak), "superpixel_binning_2": psnr(m2, truth_sp, whole_sp, peak)}
    s_sp, s_full = stokes_from_analyzers(sp), stokes_from_analyzers(demosaic_float(mosaic(ds["analyzer"][i], layout),
                                                                                   layout, "bilinear"))
    whole_full = np.zeros(mask_full.shape, bool)
    whole_full[: block[0] * whole.shape[0], : block[1] * whole.shape[1]] = np.repeat(np.repeat(whole, block[0], 0),
                                                                                       block[1], 1)
    for name, m, aux in (("full_resolution", m1, aux1), ("full_resolution_binning_2", m2, aux2)):
        lifted, _ = lift(m, aux["mask"], s_sp, s_full, s_in, period)
        out[name] = psnr(lifted, truth, whole_full, peak)
    probe, _ = model.reconstruct(ds["analyzer"][i], s_in, mask=mask_full, scale=1.0, stage_zero_axis=axis)
    two, _ = model.reconstruct(ds["analyzer"][i], s_in, mask=mask_full, scale=1.0, stage_zero_axis=axis, probe=False)
    out["probe"] = psnr(probe, truth, mask_full, peak)
    out["two_full_passes"] = psnr(two, truth, mask_full, peak)
    return out


def evaluate_set(data_dir, weights_dir=None, limit: int | None = None) -> dict:
    """Mean matrix PSNR per method over the lit samples of ``data_dir``."""
    from polrig.sensor.analyzer import resolve_layout

    ds = load_dataset(data_dir, limit)
    check_network_size(ds, data_dir)
    layout = resolve_layout(LAYOUT)
    ph, pw = layout.period
    if ds.shape[0] % (ph * 16) or ds.shape[1] % (pw * 16):
        raise ValueError(f"{data_dir}: sides must be multiples of {ph * 16} (the binned superpixel grid is a "
                         "multiple of 8)")
    model = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    rows = [score_sample(model, ds, i, layout) for i in lit_samples(ds)]
    return {"data": str(data_dir), "samples": len(rows), "resolution": list(ds.shape),
            "probe_shape": runtime.probe_shape(ds.shape),
            "matrix_psnr_db": {m: float(np.mean([r[m] for r in rows])) for m in METHODS},
            "per_sample": rows}


def markdown(results: Sequence[dict]) -> str:
    pairs = (("superpixel", "superpixel_binning_2"), ("full_resolution", "full_resolution_binning_2"),
             ("two_full_passes", "probe"))
    lines = ["| set | samples | size | superpixel (default) | **binning 2** | difference | full resolution (default) | "
             "**binning 2** | difference | two full passes | **probe** | difference |", "|---" * 12 + "|"]
    for r in results:
        p, (h, w) = r["matrix_psnr_db"], r["resolution"]
        cells = [f"{p[a]:.2f} | **{p[b]:.2f}** | {p[b] - p[a]:+.2f}" for a, b in pairs]
        lines.append(f"| {pathlib.Path(r['data']).name} | {r['samples']} | {w}x{h} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import held_out_main

    return held_out_main(argv, "python -m polrig.models.evaluate_speed_modes", __doc__.split("\n\n")[0],
                         evaluate_set, markdown,
                         "# Speed modes against the default route (matrix PSNR, dB)\n\n"
                         "`python -m polrig.models.evaluate_speed_modes` (models/evaluate_speed_modes.py: what is "
                         "compared and on which pixels)")


if __name__ == "__main__":
    raise SystemExit(main())
