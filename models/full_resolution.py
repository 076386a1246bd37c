"""Single-shot Mueller images at the sensor's own resolution (issue 22, item 1).

Route: the networks run on the **superpixel** analyzer images (the sensor's native sampling,
the sampling they were trained on) and their Mueller image is lifted to the raw resolution
with the **measured detail** of a full-resolution demosaic (bilinear or Newton):

``M_full = up(M) + (S_full - up(S)) s_in^T / |s_in|^2``

``up`` is mask-normalised bilinear upsampling from the superpixel grid (cell centres at raw
``p i + (p - 1) / 2`` for period ``p``, :func:`upsample`), ``S`` the superpixel Stokes image the
networks saw and ``S_full`` the full-resolution one (DN). Only the column the capture measures
takes the detail: ``M_full s_in = up(M s_in) + S_full - up(S)``, i.e. the full-resolution
measurement plus the network's own (upsampled) misfit, while the unobserved part of the matrix
(light polarized at 45 deg to the incident state, the network's prior) stays as smooth as the
grid it was inferred on. No learned parameter: the physics path (PIPNet -> pBRDF -> PMMNet) is
unchanged. These are the building blocks; the single-shot route that uses them for ``polrig
infer``, sessions and the GUI is :class:`polrig.app.single_shot.SingleShot` (its options:
:class:`polrig.acquisition.plan.SingleShotOptions`).

Why not the networks on the full-resolution demosaic: the full colour sensor is 5 Mpx x 3
colours, 16 times the superpixel grid's work and four times the mono full sensor's grid, one
pass of which already holds 1.5 GB of activations; at 512x512 the networks on the bilinear
demosaic took 0.5-0.7 s of CPU per frame against 0.07-0.12 s for this route, at the same
accuracy (``benchmarks/results/single_shot_speed.md``, ``single_shot_full_resolution.md``, busy
2-core machine); and the networks never saw an object at four times its superpixel size in
pixels (the U-Net's receptive field covers a quarter as much of it). That route stays
available as ``polrig infer --demosaic bilinear`` (networks on the full demosaic, resized
to ``max_pixels``).

The same lift, with period 2, is the faster **network binning** mode (:func:`reconstruct_binned`,
``polrig infer --network-binning 2``): the networks on the analyzer grid binned 2x2 and their
answer lifted back to that grid with its own measured detail (accuracy and speed:
``models/MODEL_CARD.md``, "Speed, warm and cold").
"""

from __future__ import annotations

import numpy as np

from polrig.sensor.stokes import stokes_from_analyzers

def bin_cells(img: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor x factor`` cells of planes ``(..., h, w)`` -> ``(..., h // factor,
    w // factor)`` float32 (a partial last row or column of cells is dropped; :func:`lift`
    repeats the edge there). Cell ``i`` covers ``[factor i, factor i + factor)``, its centre at
    ``factor i + (factor - 1) / 2``, where :func:`upsample` puts it back."""
    f = int(factor)
    x = np.asarray(img, np.float32)
    h, w = x.shape[-2] // f, x.shape[-1] // f
    out = np.zeros(x.shape[:-2] + (h, w), np.float32)
    for i in range(f):  # f^2 strided adds: a tenth of np.mean over reshaped cell axes here
        for j in range(f):
            out += x[..., i: h * f: f, j: w * f: f]
    out *= np.float32(1.0 / (f * f))
    return out


def binned_intrinsics(intrinsics, factor: int):
    """Pinhole ``(fx, fy, cx, cy)`` of a grid binned by ``factor`` (:func:`bin_cells`), or None
    for None (the runtime's default camera, which scales with the grid)."""
    if intrinsics is None:
        return None
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    half = 0.5 * (factor - 1)
    return fx / factor, fy / factor, (cx - half) / factor, (cy - half) / factor


def upsample(img: np.ndarray, period: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of superpixel planes ``(..., h, w)`` to the raw grid ``shape``
    ``(H, W)`` (``h = H // ph``): cell ``i`` covers raw ``[ph i, ph i + ph)`` and its value sits
    at the cell centre (OpenCV's half-pixel mapping at an integer factor puts it there); a
    partial last cell of the raw frame repeats the edge. float32 out."""
    h, w = img.shape[-2:]
    flat = np.asarray(img, np.float32).reshape((-1, h, w))
    out = np.empty((flat.shape[0],) + tuple(shape), np.float32)
    for i, plane in enumerate(flat):
        _upsample_into(plane, period, out[i])
    return out.reshape(img.shape[:-2] + tuple(shape))


def _upsample_into(plane: np.ndarray, period: tuple[int, int], dst: np.ndarray) -> None:
    import cv2

    (ph, pw), (h, w), (hh, ww) = period, plane.shape, dst.shape
    src = np.ascontiguousarray(plane, np.float32)
    if (hh, ww) == (h * ph, w * pw) and dst.flags.c_contiguous:  # written in place (no copy)
        cv2.resize(src, (ww, hh), dst=dst, interpolation=cv2.INTER_LINEAR)
        return
    dst[: h * ph, : w * pw] = cv2.resize(src, (w * pw, h * ph), interpolation=cv2.INTER_LINEAR)
    if ww > w * pw:  # a partial last cell: the edge repeats
        dst[: h * ph, w * pw:] = dst[: h * ph, w * pw - 1: w * pw]
    if hh > h * ph:
        dst[h * ph:] = dst[h * ph - 1: h * ph]


def reconstruct_binned(model, analyzer: np.ndarray, s_in, binning: int, *, mask: np.ndarray | None = None,
                       intrinsics=None, stokes: np.ndarray | None = None, **kwargs) -> tuple[np.ndarray, dict]:
    """The faster mode (network binning, :data:`polrig.acquisition.plan.NETWORK_BINNINGS`; its
    accuracy is in ``models/MODEL_CARD.md``, "Speed, warm and cold"): ``model.reconstruct`` (a
    :class:`polrig.models.runtime.SingleShotModel`) on analyzer images ``(C, 4, h, w)`` (DN) binned
    ``binning x binning`` (:func:`bin_cells`), lifted back to ``(h, w)`` with the grid's own
    measured detail (:func:`lift`, period ``binning``). ``mask`` ``(h, w)`` is binned (object
    where more than half the cell is), ``intrinsics`` (of the ``(h, w)`` grid) rescaled;
    ``stokes`` ``(C, 3, h, w)``: the analyzers' Stokes if the caller has them; the other keyword
    arguments go to ``reconstruct`` unchanged. ``aux["mask"]`` is the lifted mask ``(h, w)``;
    ``normal``, ``kd``, ``wi`` and ``mueller_init`` stay on the binned grid under
    ``aux["network_grid"]``; ``timings_s`` gains ``binning_lift``."""
    import time

    if isinstance(binning, bool) or not isinstance(binning, (int, np.integer)) or int(binning) < 2:
        raise ValueError(f"binning must be an integer factor >= 2, got {binning!r}")
    binning = int(binning)
    a = bin_cells(analyzer, binning)
    m = None if mask is None else bin_cells(np.asarray(mask, np.float32), binning) > 0.5
    mueller, aux = model.reconstruct(a, s_in, mask=m, intrinsics=binned_intrinsics(intrinsics, binning), **kwargs)
    t0 = time.perf_counter()
    aux["network_grid"] = {k: aux.pop(k) for k in ("normal", "kd", "wi", "mueller_init") if k in aux}
    fine = stokes_from_analyzers(analyzer) if stokes is None else stokes
    mueller, aux["mask"] = lift(mueller, aux["mask"], stokes_from_analyzers(a), fine, s_in, (binning, binning))
    aux["timings_s"]["binning_lift"] = time.perf_counter() - t0
    return mueller, aux


def lift(mueller: np.ndarray, mask: np.ndarray, stokes: np.ndarray, stokes_full: np.ndarray, s_in,
         period: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(M_full (C, 3, 3, H, W), mask_full (H, W))`` from the networks' Mueller image
    ``mueller`` ``(C, 3, 3, h, w)`` (DN per unit incident S0, 0 outside ``mask`` ``(h, w)``), the
    superpixel Stokes ``stokes`` ``(C, 3, h, w)`` and the full-resolution Stokes
    ``stokes_full`` ``(C, 3, H, W)`` (DN) of the same capture under ``s_in`` ``(3,)`` (module
    docstring). Background (the upsampled mask below one half) is 0, as in the networks'
    image; where ``stokes_full`` is not finite (a clipped sample in the demosaic support) no
    detail is added. Planes are lifted one at a time: the peak is the output plus a few planes."""
    import cv2

    s = np.asarray(s_in, np.float64).reshape(3)
    shape = tuple(stokes_full.shape[-2:])
    c = mueller.shape[0]
    m = np.asarray(mask, bool)
    weight = upsample(m.astype(np.float32), period, shape)
    inside = weight > 0.5
    inside_f = inside.astype(np.float32)
    # The mask normalisation 1 / up(mask) (0 outside) changes only the band along the object's
    # edge: inside, up(mask) is exactly 1 (the bilinear weights at an integer factor are exact
    # binary fractions that sum to 1), and far outside up(M) is already 0. So it is applied to
    # the band's pixels alone, not to every plane's 5 Mpx (the same numbers).
    band = np.flatnonzero((weight > 0.0) & (weight < 1.0))
    band_norm = np.where(inside.reshape(-1)[band], 1.0 / np.maximum(weight.reshape(-1)[band], 1e-6),
                         0.0).astype(np.float32)

    def normalise(plane: np.ndarray) -> None:
        flat = plane.reshape(-1)
        flat[band] *= band_norm
    out = np.empty((c, 3, 3) + shape, np.float32)
    seen = np.empty(shape, np.float32)
    detail = np.empty(shape, np.float32)
    for ci in range(c):
        for r in range(3):
            # the measured detail of row r: full-resolution Stokes minus what the grid saw
            _upsample_into(np.where(m, stokes[ci, r], 0.0), period, seen)
            normalise(seen)
            cv2.subtract(np.asarray(stokes_full[ci, r], np.float32), seen, dst=detail)
            cv2.patchNaNs(detail, 0.0)  # a clipped sample's support: no detail (NaN, never inf, from the demosaic)
            cv2.multiply(detail, inside_f, dst=detail)  # background stays 0
            for k in range(3):
                plane = out[ci, r, k]
                _upsample_into(mueller[ci, r, k], period, plane)
                normalise(plane)
                cv2.scaleAdd(detail, float(s[k] / (s @ s)), plane, dst=plane)
    return out, inside
