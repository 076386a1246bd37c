"""What the hybrid prior's scale costs a capture at the full sensor, sampled against every band.

:func:`polrig.solve.radiometry.prior_scale_from_frames` (what ``polrig capture --mode hybrid``
runs before its banded solve, ``--prior-scale innovations``, the default) on the full sensor's
mosaics (2448x2048, IMX250MZR mono and IMX250MYR colour; superpixel demosaic, ideal analyzer),
two states 0/90 and four 0/45/90/135, the seen state 0: its sample of the row bands
(:data:`polrig.solve.radiometry.SCALE_SAMPLE_PIXELS`) against every band (the alternative: the
exact scale of the whole image), and, for scale, the banded hybrid solve it precedes
(:func:`polrig.solve.radiometry.reference_from_frames` with the prior). Synthetic smooth Mueller
images with the sensor model's noise; the prior is the truth on the output grid plus Gaussian
errors of 1.5 times a per-element sigma of 5 % of m00 (independent per element: the hybrid's
plane covariance, which the innovations are measured against, keeps the row's variance along
the seen direction, so the raw scale is not 1.5 here; its recovery of a known scale is tested in
``tests/test_prior_scale.py``). Each case twice: the prior over the whole frame, and over a
centred disk of :data:`OBJECT_SHARE` of it, about the share of the simulated sphere at the full
sensor (its 192842 tested pixels of the mono's 1224x1024 superpixel grid,
``benchmarks/results/diffuse_route.md``), the network's object; off it the prior has no sigma,
as the network gives none there, and the scale computes only the object's pixels. Warm, in
process, after one untimed call each; medians of interleaved rounds; the factor of each and the
number of innovations; the peak of numpy's and Python's allocations (``tracemalloc``) during one
more call of the sampled scale and of the solve.

    python benchmarks/bench_prior_scale.py [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
SIZE = (2048, 2448)
STATE_SETS = {"2 states (0/90)": (0.0, 90.0), "4 states (0/45/90/135)": (0.0, 45.0, 90.0, 135.0)}
#: Share of the frame the second case's object covers (module docstring).
OBJECT_SHARE = 0.15


def on_object(sigma: np.ndarray, share: float) -> np.ndarray:
    """``sigma`` ``(C, 3, 3, H, W)`` with no prior (0) outside a centred disk of ``share`` of the frame."""
    h, w = sigma.shape[-2:]
    v, u = np.mgrid[0:h, 0:w]
    disk = (v - h / 2) ** 2 + (u - w / 2) ** 2 <= share * h * w / np.pi
    return np.where(disk, sigma, 0).astype(sigma.dtype)


def frames(layout_name: str, states_deg, seed: int = 0):
    """The states' radiances on the full sensor, their incident Stokes and a prior on the
    superpixel grid (``(mean, sigma)``, ``(C, 3, 3, H', W')``)."""
    from polrig.optics.mueller import polarizer_stokes
    from polrig.sensor.analyzer import AnalyzerModel
    from polrig.sensor.demosaic import output_shape
    from polrig.sensor.layouts import LAYOUTS
    from polrig.sensor.noise import SensorModel
    from polrig.solve.radiometry import StateRadiance

    layout = LAYOUTS[layout_name]
    rng = np.random.default_rng(seed)
    h, w = SIZE
    c = layout.n_colours
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    base = rng.uniform(-0.25, 0.25, (c, 3, 3)).astype(np.float32) + np.diag([1.0, 0.6, 0.5]).astype(np.float32)
    shade = (1.0 + 0.3 * np.sin(u / 97.0 + v / 131.0)).astype(np.float32)
    s_in = polarizer_stokes(np.deg2rad(states_deg), intensity=1.0)
    ideal, model = AnalyzerModel.ideal(layout, SIZE), SensorModel()
    out = []
    for s in s_in:
        stokes = 900.0 * np.einsum("cij,j->ci", base, s.astype(np.float32))[:, :, None, None] * shade
        mosaic = ideal.mosaic(stokes)
        var = model.variance_dn2(mosaic, 1000.0)
        out.append(StateRadiance((mosaic + rng.standard_normal(SIZE).astype(np.float32) * np.sqrt(var)).astype(np.float32),
                                 var.astype(np.float32), np.zeros(SIZE, bool)))
    ho, wo = output_shape(layout, SIZE, "superpixel")
    cell_h, cell_w = h // ho, w // wo
    truth = 900.0 * base[:, :, :, None, None] * shade[::cell_h, ::cell_w][None, None, None]
    sigma = np.broadcast_to(0.05 * truth[:, :1, :1], truth.shape).astype(np.float32)
    mean = (truth + 1.5 * sigma * rng.standard_normal(truth.shape).astype(np.float32)).astype(np.float32)
    return out, s_in, layout, mean, sigma


def measure(states, s_in, layout, mean, sigma, rounds: int):
    """The sampled scale, the scale over every band and the banded hybrid solve of one case:
    medians of ``rounds`` interleaved rounds (s), each one's answer (the solve's not kept) and
    the peak MiB of the sampled scale and of the solve."""
    from benchmarks.timing import sampled_against_every_band
    from polrig.solve.radiometry import prior_scale_from_frames, reference_from_frames

    return sampled_against_every_band(
        lambda: prior_scale_from_frames(states, s_in, layout, "superpixel", None, mean, sigma, 0),
        lambda: prior_scale_from_frames(states, s_in, layout, "superpixel", None, mean, sigma, 0, sample_pixels=10**12),
        lambda: reference_from_frames(states, s_in, layout, "superpixel", prior_mean=mean, prior_sigma=sigma,
                                      seen_state=0),
        rounds)


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(REPO))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "prior_scale.md"))
    args = ap.parse_args(argv)
    from polrig.solve.radiometry import SCALE_SAMPLE_PIXELS

    rows = []
    for layout_name in ("imx250mzr", "imx250myr"):
        for label, states_deg in STATE_SETS.items():
            states, s_in, layout, mean, whole = frames(layout_name, states_deg)
            cases = (("whole frame", whole), (f"{100 * OBJECT_SHARE:.0f} % of it", on_object(whole, OBJECT_SHARE)))
            for where, sigma in cases:
                med, answers, peak = measure(states, s_in, layout, mean, sigma, args.rounds)
                rows.append((layout_name, label, where, med, answers["sampled"], answers["every band"], peak))
                print(f"{layout_name} {label}, prior over {where}: sampled {med['sampled']:.3f} s (factor "
                      f"{answers['sampled'].factor:.4f}), every band {med['every band']:.3f} s (factor "
                      f"{answers['every band'].factor:.4f}), hybrid solve {med['hybrid solve']:.2f} s", flush=True)
    lines = ["# The hybrid prior's scale at the full sensor", "",
             f"`python -m benchmarks prior_scale` (`benchmarks/bench_prior_scale.py --rounds {args.rounds}`): "
             f"2448x2048 mosaics, superpixel, ideal analyzer, synthetic scene, the prior over the whole frame or "
             f"over a centred disk of {100 * OBJECT_SHARE:.0f} % of it, the simulated sphere's share (module "
             f"docstring); warm, in process, medians of {args.rounds} interleaved rounds on 2 shared CPUs. Sampled: "
             f"every k-th row band, at most {SCALE_SAMPLE_PIXELS} output pixels times colours, as captures take it; "
             "every band: the exact scale of the whole image. Only the object's pixels are computed.", "",
             "| sensor | states | prior over | sampled s | factor (raw) | innovations | every band s | factor (raw) | "
             "innovations | hybrid solve s | sampled / solve | peak MiB, sampled / solve |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for layout_name, label, where, med, a, b, peak in rows:
        lines.append(f"| {layout_name} | {label} | {where} | {med['sampled']:.3f} | {a.factor:.4f} ({a.raw:.4f}) | "
                     f"{a.innovations} | {med['every band']:.3f} | {b.factor:.4f} ({b.raw:.4f}) | {b.innovations} | "
                     f"{med['hybrid solve']:.2f} | {100 * med['sampled'] / med['hybrid solve']:.0f} % | "
                     f"{peak['sampled']:.0f} / {peak['hybrid solve']:.0f} |")
    text = "\n".join(lines) + "\n"
    pathlib.Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
