"""The diffuse completion at two states (polrig.solve.diffuse_geometry): the unobserved
direction in closed form, the diffuse block's rank-one form, and a round trip against hidden
truth (diffuse blocks rendered by the pBRDF, the direction two states leave open corrupted as a
prior would, then predicted back from the geometry)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics.pbrdf import linear_rig_mueller
from polrig.solve import diffuse_geometry as dg
from polrig.solve.model_selection import ModelMaps
from polrig.solve.reference import ReferenceResult

STAGE = np.array([0.0, -1.0, 0.0])
CAM = np.array([1.0, 0.0, 0.0])


def _state(deg: float) -> np.ndarray:
    t = np.deg2rad(2 * deg)
    return np.array([1.0, np.cos(t), np.sin(t)])


@settings(max_examples=60, deadline=None)
@given(st.floats(0, 180), st.floats(1, 179), st.floats(0.5, 1.0), st.floats(0.5, 1.0))
def test_unobserved_direction_is_orthogonal_to_both_states(a, d, pa, pb):
    """Two distinct polarizer states (degree of polarization 0.5 to 1, 1 to 179 deg apart)
    leave one unit direction open, orthogonal to both."""
    s = np.stack([_state(a) * [1, pa, pa], _state(a + d) * [1, pb, pb]])
    u = dg.unobserved_direction(s)
    assert u is not None
    assert abs(np.linalg.norm(u) - 1) < 1e-12
    assert np.abs(s @ u).max() < 1e-9 * np.abs(s).max()


def test_unobserved_direction_none_when_nothing_is_open_or_too_little_is_seen():
    assert dg.unobserved_direction(np.stack([_state(0), _state(60), _state(120)])) is None
    assert dg.unobserved_direction(_state(30)[None]) is None
    assert dg.unobserved_direction(np.stack([_state(30), 2 * _state(30)])) is None
    # 0/90: the plane holds (1, 0, 0) and the seen state's axis; open is the 45 deg axis
    u = dg.unobserved_direction(np.stack([_state(0), _state(90)]))
    assert np.allclose(np.abs(u), [0, 0, 1])


def _geometry(p: int, rng: np.random.Generator):
    """Random views about the optical axis, one light 50 deg off it, normals facing both that
    turn smoothly from one pixel to the next (a surface strip one pixel high: zenith 10-60 deg,
    the azimuth twice round; about 2 deg from a pixel to the next at ``p = 400``)."""
    view = rng.normal([0, 0, 1], 0.05, (p, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    light = np.array([np.sin(np.deg2rad(50)), 0.2, np.cos(np.deg2rad(50))])
    light /= np.linalg.norm(light)
    zen = np.deg2rad(35 + 25 * np.sin(np.linspace(0, 6 * np.pi, p) + rng.uniform(0, 2 * np.pi)))
    azi = np.linspace(0, 4 * np.pi, p) + rng.uniform(0, 2 * np.pi)
    normal = np.stack([np.sin(zen) * np.cos(azi), np.sin(zen) * np.sin(azi), np.cos(zen)], axis=1)
    keep = (normal @ light > 0.2)
    return view[keep], light, normal[keep]


def test_diffuse_block_is_rank_one_in_its_ratios():
    """The unit diffuse block is ``m00 x y^T`` with ``x``, ``y`` from :func:`diffuse_ratios`."""
    rng = np.random.default_rng(1)
    view, light, normal = _geometry(200, rng)
    lights = np.broadcast_to(light, view.shape)
    md = linear_rig_mueller(normal, lights, view, kd=1.0, ks=0.0, alpha=0.1, eta=1.6, components=("diffuse",),
                            stage_zero_axis=STAGE, camera_x_axis=CAM)
    x, y = dg.diffuse_ratios(normal, lights, view, 1.6, STAGE, CAM)
    assert np.allclose(md, md[:, :1, :1] * x[:, :, None] * y[:, None, :], rtol=0, atol=1e-12 * md.max())
    assert np.allclose(x[:, 0], 1) and np.allclose(y[:, 0], 1)
    # polarized transmission: degree of polarization below 1, both ways
    assert (np.hypot(x[:, 1], x[:, 2]) < 1).all() and (np.hypot(y[:, 1], y[:, 2]) < 1).all()


def _result(truth: np.ndarray, code: np.ndarray, sigma: float = 0.01) -> ReferenceResult:
    n_col, _, _, h, w = truth.shape
    zeros = np.zeros((n_col, h, w), np.float32)
    maps = ModelMaps(code.astype(np.uint8), zeros.copy(), zeros.copy())
    return ReferenceResult(truth.astype(np.float32), np.full(truth.shape, sigma, np.float32), zeros,
                           np.zeros((n_col, h, w), np.uint8), 1.0, zeros + 1, np.zeros((n_col, h, w), np.uint16),
                           models=maps)


def _scene(eta: float, seed: int = 0):
    """Diffuse truth ``(3, 3, 3, 1, P)``, its geometry and the 0/30-deg-rotated 0/90 states."""
    rng = np.random.default_rng(seed)
    view, light, normal = _geometry(400, rng)
    p = len(view)
    lights = np.broadcast_to(light, view.shape)
    md = linear_rig_mueller(normal, lights, view, kd=1.0, ks=0.0, alpha=0.1, eta=eta, components=("diffuse",),
                            stage_zero_axis=STAGE, camera_x_axis=CAM)  # (P, 3, 3)
    albedo = rng.uniform(0.3, 1.0, (3, p))
    truth = np.moveaxis(albedo[:, None, None, :] * np.moveaxis(md, 0, -1)[None], -1, -1)[..., None, :]
    guess = normal + rng.normal(0, 0.08, normal.shape)  # the network's normals, ~5 deg off
    guess /= np.linalg.norm(guess, axis=1, keepdims=True)
    geo = dg.DiffuseGeometry(view=view[None], light=light, stage_zero_axis=STAGE, camera_x_axis=CAM,
                             normal_guess=guess[None])
    return truth, geo, np.stack([_state(30), _state(120)])


def _corrupt(truth: np.ndarray, u: np.ndarray, rng: np.random.Generator, size: float = 0.05) -> np.ndarray:
    """The truth with each row's component along ``u`` off by a random amount (a prior's error
    where two states do not look)."""
    err = rng.normal(0, size, truth.shape[:2] + truth.shape[3:]) * truth[:, :, :1, ...].max()
    return truth + err[:, :, None] * u[None, None, :, None, None]


def test_completion_recovers_the_hidden_direction():
    """Diffuse truth, its open direction corrupted: the completion fits the index on the grid
    and brings the open direction's error down tenfold, leaving the observed plane as it was."""
    truth, geo, s = _scene(eta=1.6)
    u = dg.unobserved_direction(s)
    rng = np.random.default_rng(3)
    start = _corrupt(truth, u, rng)
    code = np.full((3, 1, truth.shape[-1]), dg.RANK_ONE)
    out, completed, eta = dg.complete_diffuse(_result(start, code), s, geo)
    assert abs(eta - 1.6) <= 0.05 + 1e-9  # the nearest index on the grid, or its neighbour
    assert completed.all()
    got = out.mueller.astype(np.float64)
    along = lambda m: np.einsum("crk...,k->cr...", m, u)  # noqa: E731
    before = np.sqrt(np.mean((along(start) - along(truth)) ** 2))
    after = np.sqrt(np.mean((along(got) - along(truth)) ** 2))
    assert after < before / 10
    # the observed plane is untouched (to float32)
    for v in s:
        assert np.allclose(np.einsum("crk...,k->cr...", got, v), np.einsum("crk...,k->cr...", start, v),
                           atol=1e-6 * np.abs(start).max())
    # sigma: the model-selection term, the change added in quadrature
    change = got - start
    assert np.allclose(out.sigma.astype(np.float64) ** 2, 0.01**2 + change**2, rtol=1e-5, atol=1e-10)


def test_completion_leaves_other_models_colours_and_three_states_alone():
    truth, geo, s = _scene(eta=1.5, seed=4)
    u = dg.unobserved_direction(s)
    start = _corrupt(truth, u, np.random.default_rng(5))
    p = truth.shape[-1]
    code = np.zeros((3, 1, p), np.uint8)
    code[0, 0, : p // 2] = dg.RANK_ONE  # red only, half the pixels
    out, completed, _ = dg.complete_diffuse(_result(start, code), s, geo)
    changed = (out.mueller != start.astype(np.float32)).any(axis=(1, 2))
    assert not changed[1:].any() and not changed[0, 0, p // 2:].any()
    assert changed[0, 0, : p // 2].mean() > 0.9
    assert (completed == changed).all()
    r = _result(start, np.full((3, 1, p), dg.RANK_ONE))
    three = np.stack([_state(0), _state(60), _state(120)])
    same, none, eta = dg.complete_diffuse(r, three, geo)
    assert same is r and not none.any() and eta is None
    # nothing given the rank-one block: nothing fitted
    same, none, eta = dg.complete_diffuse(_result(start, np.zeros((3, 1, p))), s, geo)
    assert not none.any() and eta is None and np.array_equal(same.mueller, start.astype(np.float32))


def test_light_directions_round_trip_through_the_light_position():
    """A point light over a surface at one depth: the directions of
    :func:`light_directions` give the light's position back (``continuum.light_over_depth``,
    the stand-in for the rig's calibrated light position), and they point from the surface
    point ``-depth * view`` to it."""
    from polrig.models.continuum import light_over_depth

    rng = np.random.default_rng(7)
    view = rng.normal([0, 0, 1], 0.1, (500, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    light = np.array([0.4, -0.7, 0.3])
    wi = dg.light_directions(light, view)
    assert np.allclose(np.linalg.norm(wi, axis=1), 1)
    assert np.allclose(np.cross(wi, light + view), 0, atol=1e-12)
    assert np.allclose(light_over_depth(wi, view), light, atol=1e-10)
    # the same light 2x further, the surface 2x further: the same directions
    assert np.allclose(dg.light_directions(2 * light, view, depth=2.0), wi)


def test_the_fit_takes_the_light_that_explains_the_states():
    """Of two candidate lights, the true one and one 20 deg off, the fit takes the true one in
    either order (its cost is lower: the incident ratio the two states see depends on it)."""
    truth, geo, s = _scene(eta=1.5, seed=8)
    block = truth[0, :, :, 0, :]  # (3, 3, P), red
    x_hat, rho_hat, weights = dg.ratio_weights(block, np.full(block.shape, 0.01**2), s[0], s[1])
    t = np.deg2rad(20)
    wrong = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]]) @ geo.light
    for lights, right in (((geo.light, wrong), 0), ((wrong, geo.light), 1)):
        fit = dg.fit_diffuse_geometry(x_hat, rho_hat, weights, s[0], s[1], geo.view[0], lights, STAGE, CAM,
                                      geo.normal_guess[0])
        assert fit.light == right
        assert abs(fit.eta - 1.5) <= 0.05 + 1e-9


def test_ratio_weights_are_the_inverse_variances_of_the_ratios():
    """The delta method's variances of the measured ratios agree with their spread over noisy
    draws of a block (independent Gaussian errors per element, 1 % of ``m00``), to 10 %."""
    truth, _, s = _scene(eta=1.5, seed=11)
    block = truth[0, :, :, 0, :8]  # (3, 3, P): 8 pixels
    sd = 0.01 * block[0, 0]  # (P,)
    variance = np.broadcast_to(sd**2, block.shape)
    x_hat, rho_hat, weights = dg.ratio_weights(block, variance, s[0], s[1])
    v = s[0] + s[1]
    mv = np.einsum("rkp,k->rp", block, v)
    assert np.allclose(x_hat, (mv / mv[0]).T) and np.allclose(rho_hat, (block[0].T @ s[1]) / (block[0].T @ s[0]))
    rng = np.random.default_rng(12)
    draws = block[None] + rng.normal(size=(20000,) + block.shape) * sd
    mv_d = np.einsum("nrkp,k->nrp", draws, v)
    spread = np.stack([(mv_d[:, 1] / mv_d[:, 0]).var(0), (mv_d[:, 2] / mv_d[:, 0]).var(0),
                       ((draws[:, 0].transpose(0, 2, 1) @ s[1]) / (draws[:, 0].transpose(0, 2, 1) @ s[0])).var(0)],
                      axis=1)
    assert np.allclose(1 / weights, spread, rtol=0.1)


def test_neighbour_mean_averages_valid_neighbours_only():
    """The 3x3 mean of the valid normals: a constant field is kept, an invalid pixel's normal
    does not count, and a pixel with no valid neighbour keeps its own."""
    ys, xs = np.nonzero(np.ones((4, 5), bool))
    n = np.tile([0.0, 0.0, 1.0], (len(ys), 1))
    valid = np.ones(len(ys), bool)
    assert np.allclose(dg.neighbour_mean(n, valid, ys, xs), n)
    tilted = n.copy()
    tilted[7] = [1.0, 0.0, 0.0]  # row 1, column 2
    valid[7] = False
    got = dg.neighbour_mean(tilted, valid, ys, xs)
    assert np.allclose(np.delete(got, 7, axis=0), np.delete(n, 7, axis=0))  # the invalid one does not count
    assert np.allclose(got[7], [0.0, 0.0, 1.0])  # nor for itself: its valid neighbours' mean
    lone = dg.neighbour_mean(tilted[7:8], np.ones(1, bool), ys[7:8], xs[7:8])
    assert np.allclose(lone, [[1.0, 0.0, 0.0]])
    alone = dg.neighbour_mean(tilted[7:8], np.zeros(1, bool), ys[7:8], xs[7:8])
    assert np.allclose(alone, tilted[7:8])  # no valid neighbour: its own
    # the same pixels anywhere in a larger image: the same means, bit for bit (only the pixels' box is summed)
    np.testing.assert_array_equal(dg.neighbour_mean(tilted, valid, ys + 10, xs + 20), got)
    empty = np.zeros(0, int)
    assert dg.neighbour_mean(np.zeros((0, 3)), np.zeros(0, bool), empty, empty).shape == (0, 3)


def test_a_given_index_and_light_are_used_as_given():
    """``complete_diffuse(eta=, light=)``: the index and light chosen elsewhere (the diffuse
    test's) are used, not fitted; one without the other is an error."""
    import pytest

    truth, geo, s = _scene(eta=1.5, seed=13)
    u = dg.unobserved_direction(s)
    start = _corrupt(truth, u, np.random.default_rng(14))
    r = _result(start, np.full((3, 1, truth.shape[-1]), dg.RANK_ONE))
    _, completed, eta = dg.complete_diffuse(r, s, geo, eta=1.8, light=0)
    assert eta == 1.8 and completed.any()
    with pytest.raises(ValueError, match="together"):
        dg.complete_diffuse(r, s, geo, eta=1.5)
