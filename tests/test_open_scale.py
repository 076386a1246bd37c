"""The prior's scale along the direction two states leave open (polrig.solve.open_scale): the
posterior variance along it is the prior's conditional variance where the samples observe none of
it (closed form) and less with a third state that observes it; on a scene that is Baek's diffuse
term at a known geometry, with a prior whose error along the open direction is ``k`` times its
sigma, the estimated raw scale comes out near ``k`` and the solve with that factor covers the
truth as a right Gaussian's does; too few values give factor 1."""

from __future__ import annotations

import numpy as np

from polrig.optics import mueller as mu
from polrig.solve.hybrid import open_direction, unobserved_precision
from polrig.solve.open_scale import OpenScale, open_scale_of, open_variance
from polrig.solve.prior_scale import MIN_INNOVATIONS
from polrig.solve.reference import forward_measurements


def test_the_open_variance_is_the_posterior_variance_along_the_direction():
    """Two states and the per-element prior: ``1 / (w^T P_r w)`` per row, the samples observe none
    of ``w``; with a third state that observes it, less than half of that."""
    rng = np.random.default_rng(3)
    n, h, w = 1, 3, 4
    truth = np.zeros((n, 3, 3, h, w))
    truth[:, 0, 0] = truth[:, 1, 1] = truth[:, 2, 2] = 1.0
    s3 = mu.polarizer_stokes(np.radians([0.0, 90.0, 45.0]), np.inf)
    meas = forward_measurements(truth, s3)
    var = np.full(meas.shape, 1e-4)
    sigma = 0.05 * (1 + rng.random(truth.shape))
    where = np.ones((n, h, w), bool)
    d = open_direction(s3[:2])
    got = open_variance(s3[:2], meas[:2], var[:2], None, None, sigma, 0, None, where, d)
    p = unobserved_precision(np.moveaxis(sigma, 2, -1), s3[0])
    assert np.allclose(got, 1.0 / np.einsum("i,...ij,j->...", d, p, d), rtol=1e-8)
    assert (open_variance(s3, meas, var, None, None, sigma, 0, None, where, d) < 0.5 * got).all()
    assert not open_variance(s3[:2], meas[:2], var[:2], None, None, sigma, 0, None, ~where, d).any()


def test_the_scale_of_values_drawn_at_a_known_scale_finds_it():
    rng = np.random.default_rng(0)
    v = rng.uniform(0.5, 2.0, 4000)
    for k in (0.5, 1.0, 2.0):
        got = open_scale_of(k * np.sqrt(v) * rng.normal(size=v.size), v, exponent=1.0)
        assert abs(got.raw / k - 1) < 0.06 and got.factor == max(got.raw, 1.0) and got.values == v.size
    half = open_scale_of(2.0 * np.sqrt(v) * rng.normal(size=v.size), v, exponent=0.5)
    assert np.isclose(half.factor, half.raw ** 0.5)
    assert open_scale_of(0.3 * np.sqrt(v) * rng.normal(size=v.size), v).factor == 1.0  # never narrows


def test_too_few_values_give_factor_one():
    got = open_scale_of(np.ones(MIN_INNOVATIONS - 1), np.ones(MIN_INNOVATIONS - 1))
    assert got.factor == 1.0 and got.values == MIN_INNOVATIONS - 1
    assert OpenScale.none().record() == {"factor": 1.0, "raw": 1.0, "exponent": 0.0, "values": 0}


def _diffuse_scene(seed: int, k: float, n: int = 24):
    """Baek's diffuse term at a known geometry (``tests/test_diffuse_test.py``'s surface), its two
    states' noisy samples and a prior whose error along the open direction is ``k`` times its
    sigma (5 % of the brightest ``m00``), with the geometry's normals withheld."""
    from test_diffuse_test import STATES, _blocks, _frames, _geometry, _surface

    view, light, normal = _surface(n, n, seed)
    truth = _blocks(view, light, normal, 1.5, "diffuse", [0.9, 0.7, 0.5])
    rng = np.random.default_rng(seed + 100)
    meas, var, _ = _frames(truth, rng)
    sd = 0.05 * truth[:, 0, 0].max()
    err = rng.normal(0, k * sd, truth.shape[:2] + truth.shape[3:])
    prior = truth + err[:, :, None] * open_direction(STATES)[None, None, :, None, None]
    return STATES, truth, meas, var, prior, np.full(truth.shape, sd), _geometry(view, light, None)


def test_on_a_diffuse_scene_the_scale_finds_the_priors_error_along_the_open_direction():
    """The prior errs along the open direction by ``k`` times its sigma: the raw scale is near ``k``
    (the completion's own error adds a little); at k = 3, solved with that factor (exponent 1)
    the hybrid covers the truth along the open direction as a right Gaussian does (93-98 % within
    2 sigma), where the unscaled solve covers it far less; at k = 0.3 the factor stays 1 (it
    never narrows) and the solve covers it far more."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.open_scale import open_values

    for k, seed in ((3.0, 1), (0.3, 2)):
        s, truth, meas, var, prior, sigma, geo = _diffuse_scene(seed, k)
        kw = dict(prior_mean=prior, prior_sigma=sigma, seen_state=0)
        r = solve_hybrid(s, meas, var, None, dtype=np.float64, **kw)
        got = open_scale_of(*open_values(r, s, meas, var, None, geo, **kw), exponent=1.0)
        assert got.values > 0.8 * truth.shape[0] * 3 * 24 * 24
        assert 0.8 * k < got.raw < 1.35 * k + 0.1
        w = open_direction(s)

        def cover(res):
            err = np.einsum("crkhw,k->crhw", res.mueller - truth, w)
            sd = np.sqrt(np.einsum("crkhw,k->crhw", res.sigma ** 2, w * w))
            return np.mean(np.abs(err) <= 2 * sd)

        scaled = solve_hybrid(s, meas, var, None, dtype=np.float64, open_factor=got.factor, **kw)
        if k > 1:
            assert 0.93 <= cover(scaled) <= 0.985 and cover(r) < 0.6
        else:
            assert got.factor == 1.0 and cover(scaled) == cover(r) > 0.995


def test_the_factor_from_frames_samples_the_objects_bands():
    """:func:`polrig.solve.radiometry.open_scale_from_frames` on the mosaics of a diffuse scene
    whose prior errs along the open direction by 2.5 times its sigma: the factor is the raw
    scale (near 2.5) to :data:`EXPONENT`, a small ``sample_pixels`` takes every k-th of the
    object's bands (fewer values, a factor near the whole's), and one state or no object give
    factor 1 with no values."""
    from test_diffuse_test import STATES, _blocks, _geometry, _surface

    from _state_radiance import noisy_states
    from polrig.sensor.layouts import IMX250MZR
    from polrig.solve.open_scale import EXPONENT
    from polrig.solve.radiometry import open_scale_from_frames

    n = 32  # the superpixel grid; the mosaic is twice that
    view, light, normal = _surface(n, n, 5)
    truth = 2000.0 * _blocks(view, light, normal, 1.5, "diffuse", [0.9])
    rng = np.random.default_rng(6)
    states = noisy_states(rng, np.repeat(np.repeat(truth, 2, axis=-2), 2, axis=-1), STATES, IMX250MZR, 0.0)
    sd = 0.05 * truth[:, 0, 0].max()
    err = rng.normal(0, 2.5 * sd, truth.shape[:2] + truth.shape[3:])
    prior = truth + err[:, :, None] * open_direction(STATES)[None, None, :, None, None]
    sigma = np.full(truth.shape, sd)
    mask = np.ones((n, n), bool)
    args = (states, STATES, IMX250MZR, "superpixel", None, prior, sigma, 0, None, _geometry(view, light, None))
    whole = open_scale_from_frames(*args, mask)
    assert whole.values > 0.8 * 3 * n * n and 2.0 < whole.raw < 3.2
    assert whole.exponent == EXPONENT and np.isclose(whole.factor, whole.raw ** EXPONENT)
    part = open_scale_from_frames(*args, mask, band_rows=4, sample_pixels=n * n // 4)
    assert part.values < 0.35 * whole.values and abs(np.log(part.raw / whole.raw)) < 0.25
    assert open_scale_from_frames(states[:1], STATES[:1], *args[2:], mask) == OpenScale.none()
    assert open_scale_from_frames(*args, np.zeros_like(mask)).values == 0
