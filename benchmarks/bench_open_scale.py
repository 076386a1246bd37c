"""What the open direction's scale costs a two-state capture at the full sensor, sampled against
every band of the object.

:func:`polrig.solve.radiometry.open_scale_from_frames` (what ``polrig capture --mode hybrid
--states 0,90`` runs before its banded solve with ``--prior-scale geometry``, the default: the
two-state hybrid, the diffuse test and the completion on a sample of the object's row bands,
:mod:`polrig.solve.open_scale`) on the full sensor's mosaics (2448x2048, IMX250MZR mono and
IMX250MYR colour; superpixel demosaic, ideal analyzer), states 0/90, the seen state 0: its sample
(:data:`polrig.solve.radiometry.OPEN_SAMPLE_PIXELS` of the object's pixels times colours) against
every band that holds the object (the alternative: the factor of the whole object), and, for
scale, the banded hybrid solve it precedes (:func:`polrig.solve.radiometry.reference_from_frames`
with the prior). The scene: a diffuse sphere (Baek's diffuse term, refractive index 1.5) filling
a centred disk of :data:`OBJECT_SHARE` of the frame, the simulated sphere's share, seen through a
pinhole under one light 40 deg off the axis, with the sensor model's noise; the prior is the
truth plus an error along the open direction of :data:`PRIOR_ERROR` times its sigma (5 % of the
brightest m00), so the raw factor is about that and the test and completion run where captures
run them. Warm, in process, after one untimed call each; medians of interleaved rounds; the
factor and the values it rests on; the peak of numpy's and Python's allocations
(``tracemalloc``) during one more call of the sampled factor and of the solve.

    python benchmarks/bench_open_scale.py [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
SIZE = (2048, 2448)
#: Share of the frame the sphere covers (the simulated sphere's at the full sensor,
#: ``benchmarks/bench_prior_scale.py``).
OBJECT_SHARE = 0.15
#: The prior's error along the open direction, in units of its sigma.
PRIOR_ERROR = 1.5
#: Pinhole focal length in output pixels per unit of the sensor's width.
FOCAL = 2.0
STAGE_ZERO_AXIS, CAMERA_X_AXIS = np.array([1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])


def scene(layout_name: str, seed: int = 0):
    """The two states' radiances on the full sensor, their incident Stokes, the layout, a prior
    ``(mean, sigma)`` ``(C, 3, 3, H', W')`` on the superpixel grid, its geometry and the sphere's
    mask ``(H', W')``."""
    from polrig.optics.mueller import polarizer_stokes
    from polrig.optics.pbrdf import linear_rig_mueller
    from polrig.sensor.analyzer import AnalyzerModel
    from polrig.sensor.demosaic import output_shape
    from polrig.sensor.layouts import LAYOUTS
    from polrig.sensor.noise import SensorModel
    from polrig.solve.diffuse_geometry import DiffuseGeometry
    from polrig.solve.hybrid import open_direction
    from polrig.solve.radiometry import StateRadiance

    layout = LAYOUTS[layout_name]
    rng = np.random.default_rng(seed)
    c = layout.n_colours
    ho, wo = output_shape(layout, SIZE, "superpixel")
    v, u = np.mgrid[0:ho, 0:wo].astype(np.float64)
    f = FOCAL * wo
    ray = np.stack([(u - wo / 2) / f, (v - ho / 2) / f, np.ones_like(u)], axis=-1)
    view = -ray / np.linalg.norm(ray, axis=-1, keepdims=True)
    radius = np.sqrt(OBJECT_SHARE * ho * wo / np.pi)
    x, y = (u - wo / 2) / radius, (v - ho / 2) / radius
    mask = x * x + y * y < 0.98
    normal = np.stack([x, y, -np.sqrt(np.clip(1 - x * x - y * y, 0, 1))], axis=-1)
    light = np.array([np.sin(np.deg2rad(40)), 0.1, -np.cos(np.deg2rad(40))])
    light /= np.linalg.norm(light)
    truth = np.zeros((c, 3, 3, ho, wo))
    flat = lambda a: np.broadcast_to(a, (ho, wo, 3))[mask]  # noqa: E731
    block = linear_rig_mueller(flat(normal), flat(light), flat(view), kd=1.0, ks=0.0, alpha=0.3, eta=1.5,
                               components=("diffuse",), stage_zero_axis=STAGE_ZERO_AXIS, camera_x_axis=CAMERA_X_AXIS)
    albedo = np.linspace(0.9, 0.5, c)
    for ci in range(c):
        truth[ci][:, :, mask] = 2500.0 * albedo[ci] * np.moveaxis(block, 0, -1)
    s_in = polarizer_stokes(np.deg2rad([0.0, 90.0]), intensity=1.0)
    cell_h, cell_w = SIZE[0] // ho, SIZE[1] // wo
    ideal, model = AnalyzerModel.ideal(layout, SIZE), SensorModel()
    states = []
    for s in s_in:
        stokes = np.einsum("cijhw,j->cihw", truth, s)
        stokes = np.repeat(np.repeat(stokes, cell_h, axis=-2), cell_w, axis=-1)
        mosaic = ideal.mosaic(stokes.astype(np.float32))
        var = model.variance_dn2(mosaic, 1000.0)
        states.append(StateRadiance((mosaic + rng.standard_normal(SIZE).astype(np.float32) * np.sqrt(var)).astype(np.float32),
                                    var.astype(np.float32), np.zeros(SIZE, bool)))
    sd = 0.05 * truth[:, 0, 0].max()
    err = rng.normal(0, PRIOR_ERROR * sd, (c, 3, ho, wo))
    mean = (truth + err[:, :, None] * open_direction(s_in)[None, None, :, None, None]).astype(np.float32)
    sigma = np.where(mask, np.float32(sd), np.float32(0)) * np.ones((c, 3, 3, 1, 1), np.float32)
    geometry = DiffuseGeometry(view=view, light=light, stage_zero_axis=STAGE_ZERO_AXIS, camera_x_axis=CAMERA_X_AXIS)
    return states, s_in, layout, mean, sigma, geometry, mask


def measure(states, s_in, layout, mean, sigma, geometry, mask, rounds: int):
    """The sampled factor, the factor over every object band and the banded hybrid solve: medians
    of ``rounds`` interleaved rounds (s), each factor's answer and the peak MiB of the sampled
    factor and of the solve."""
    from benchmarks.timing import sampled_against_every_band
    from polrig.solve.radiometry import open_scale_from_frames, reference_from_frames

    args = (states, s_in, layout, "superpixel", None, mean, sigma, 0, None, geometry, mask)
    return sampled_against_every_band(
        lambda: open_scale_from_frames(*args),
        lambda: open_scale_from_frames(*args, sample_pixels=10**12),
        lambda: reference_from_frames(states, s_in, layout, "superpixel", prior_mean=mean, prior_sigma=sigma,
                                      seen_state=0),
        rounds)


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(REPO))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "open_scale.md"))
    args = ap.parse_args(argv)
    from polrig.solve.radiometry import OPEN_SAMPLE_PIXELS

    rows = []
    for layout_name in ("imx250mzr", "imx250myr"):
        case = scene(layout_name)
        med, answers, peak = measure(*case, args.rounds)
        rows.append((layout_name, int(case[-1].sum()), med, answers["sampled"], answers["every band"], peak))
        print(f"{layout_name}: sampled {med['sampled']:.3f} s (factor {answers['sampled'].factor:.4f}), every band "
              f"{med['every band']:.3f} s (factor {answers['every band'].factor:.4f}), hybrid solve "
              f"{med['hybrid solve']:.2f} s", flush=True)
    lines = ["# The open direction's scale at the full sensor", "",
             f"`python -m benchmarks open_scale` (`benchmarks/bench_open_scale.py --rounds {args.rounds}`): 2448x2048 "
             f"mosaics, superpixel, ideal analyzer, states 0/90, a diffuse sphere over {100 * OBJECT_SHARE:.0f} % of the "
             f"frame whose prior errs along the open direction by {PRIOR_ERROR:g} times its sigma (module docstring); "
             f"warm, in process, medians of {args.rounds} interleaved rounds on 2 shared CPUs. Sampled: every k-th row "
             f"band holding the object, at most {OPEN_SAMPLE_PIXELS} of its pixels times colours, as captures take it; "
             "every band: the factor of the whole object.", "",
             "| sensor | object pixels | sampled s | factor (raw) | values | every band s | factor (raw) | values | "
             "hybrid solve s | sampled / solve | peak MiB, sampled / solve |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for layout_name, n_obj, med, a, b, peak in rows:
        lines.append(f"| {layout_name} | {n_obj} | {med['sampled']:.3f} | {a.factor:.4f} ({a.raw:.4f}) | {a.values} | "
                     f"{med['every band']:.3f} | {b.factor:.4f} ({b.raw:.4f}) | {b.values} | "
                     f"{med['hybrid solve']:.2f} | {100 * med['sampled'] / med['hybrid solve']:.0f} % | "
                     f"{peak['sampled']:.0f} / {peak['hybrid solve']:.0f} |")
    text = "\n".join(lines) + "\n"
    pathlib.Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
