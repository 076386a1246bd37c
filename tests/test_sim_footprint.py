"""A pixel's footprint on a textured surface (:mod:`polrig.sim.footprint`) against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.sim import footprint
from polrig.sim.footprint import footprint_albedo, stratified_offsets
from polrig.sim.geometry import PinholeCamera, PointLight, TurntableGeometry
from polrig.sim.materials import Material, get_material
from polrig.sim.raycast import surface_hits
from polrig.sim.render import render
from polrig.sim.scene import Scene, SceneObject
from polrig.sim.shapes import Rectangle

DARK = Material("dark", (0.05, 0.1, 0.2), 0.4, 1.5, ks=0.0)
LIGHT = Material("light", (0.85, 0.8, 0.9), 0.4, 1.5, ks=0.0)
FX, CX, W, H, DEPTH_M = 100.0, 15.5, 32, 8, 1.0


def _edge_scene(edge_x_m: float, samples: int) -> Scene:
    """A plate at 1 m square to the camera's axis (camera frame = world frame), ``LIGHT`` where
    local ``x > edge_x_m``, ``DARK`` elsewhere; the light behind the camera."""
    cam = PinholeCamera(FX, FX, CX, 3.5, W, H, np.eye(3), np.zeros(3))
    plate = SceneObject("plate", Rectangle(1.0, 1.0), (DARK, LIGHT), [0.0, 0.0, DEPTH_M],
                        region=lambda p: (p[:, 0] > edge_x_m).astype(int), on_turntable=False,
                        footprint_samples=samples)
    light = PointLight([0.0, 0.0, -0.5])
    return Scene("edge", (plate,), cam, light, TurntableGeometry(), np.array([1.0, 0.0, 0.0]),
                 np.array([0.0, 0.0, DEPTH_M]))


def _expected_fraction(edge_u: float, n: int) -> np.ndarray:
    """Share ``(W,)`` of each column's ``n`` strata (per axis) right of the edge at ``edge_u``
    (pixels): the footprint's light share, a closed form for a plate square to the axis."""
    u = np.arange(W)[:, None] + stratified_offsets(n)[None, :]
    return (u > edge_u).mean(axis=1)


@pytest.mark.parametrize("n", [1, 2, 4, 7])
@pytest.mark.parametrize("edge_u", [12.0, 12.3, 12.61, 13.95])
def test_the_rendered_albedo_is_the_footprints_share_of_each_material(n, edge_u):
    scene = _edge_scene((edge_u - CX) / FX * DEPTH_M, n)
    kd = render(scene).kd  # (3, H, W)
    share = _expected_fraction(edge_u, n)
    want = np.array(DARK.kd)[:, None] + np.subtract(LIGHT.kd, DARK.kd)[:, None] * share[None, :]
    np.testing.assert_allclose(kd, np.broadcast_to(want[:, None, :], kd.shape), atol=1e-12)


def test_an_edge_read_from_the_albedo_moves_with_it_to_within_one_stratum():
    """The edge position recovered from a row's albedo (its light share summed) follows a
    sub-pixel shift to within half a stratum, ``1 / (2 n)`` pixels; the pixel centre alone
    (``n = 1``) snaps it to the grid, up to half a pixel off."""
    worst = {}
    for n in (1, 4, 8):
        err = []
        for edge_u in np.linspace(12.0, 13.0, 21):
            kd = render(_edge_scene((edge_u - CX) / FX * DEPTH_M, n)).kd[0, 0]
            share = (kd - DARK.kd[0]) / (LIGHT.kd[0] - DARK.kd[0])
            err.append(abs((W - 0.5 - share.sum()) - edge_u))
        worst[n] = max(err)
        assert worst[n] <= 0.5 / n + 1e-9
    assert worst[1] > 0.4  # the point sample's error is real, and the footprint's removes it


def test_centre_sample_is_unchanged_where_no_object_asks():
    scene = _edge_scene(0.0023, 1)
    hits = surface_hits(scene, 0.0, np.zeros((W * H, 3)), scene.camera.ray_directions().reshape(-1, 3))
    kd = np.array([m.kd for m in scene.materials])[hits.mat_index]
    assert footprint_albedo(scene, 0.0, hits, kd) is kd


def test_grazing_pixels_keep_their_centre_sample():
    """A sub-pixel ray parallel to the hit's tangent plane cannot meet it: that pixel keeps
    its centre's albedo instead of a division by zero."""
    scene = _edge_scene((12.2 - CX) / FX * DEPTH_M, 4)  # a quarter of column 12 is light
    hits = surface_hits(scene, 0.0, np.zeros((W * H, 3)), scene.camera.ray_directions().reshape(-1, 3))
    k, k3 = (int(np.nonzero(hits.index == r * W + 12)[0][0]) for r in (2, 3))  # column 12
    off = stratified_offsets(4)[0]
    ray = np.array([(12 + off - CX) / FX, (2 + off - 3.5) / FX, 1.0])
    ng = hits.ng.copy()
    ng[k] = np.cross(ray, [0.0, 1.0, 0.0])
    ng[k] /= np.linalg.norm(ng[k])
    kd = np.array([m.kd for m in scene.materials])[hits.mat_index]
    with np.errstate(all="raise"):
        out = footprint_albedo(scene, 0.0, hits._replace(ng=ng), kd)
    np.testing.assert_array_equal(out[k], kd[k])
    np.testing.assert_allclose(out[k3], 0.75 * np.array(DARK.kd) + 0.25 * np.array(LIGHT.kd))


def test_footprint_averaging_needs_materials_that_differ_in_albedo_alone():
    for other in (Material("shiny", LIGHT.kd, 0.4, 1.5, ks=0.5), Material("rough", LIGHT.kd, 0.9, 1.5, ks=0.0),
                  get_material("mirror")):
        with pytest.raises(ValueError, match="same alpha, eta and ks"):
            SceneObject("plate", Rectangle(1.0, 1.0), (DARK, other), region=lambda p: p[:, 0] > 0,
                        footprint_samples=4)
    for bad in (0, 2.5, -1):
        with pytest.raises(ValueError, match="footprint_samples must be an integer"):
            SceneObject("plate", Rectangle(1.0, 1.0), (DARK, LIGHT), footprint_samples=bad)


@pytest.mark.parametrize("angle_deg", [0.0, 9.0, 33.0])
def test_sampling_only_the_edges_gives_the_whole_boards_footprint_means(monkeypatch, angle_deg):
    """The ChArUco target at 320x240: sampling the footprints of the pixels at an edge alone
    (:func:`edge_pixels`) gives the same albedo as sampling every pixel's, and more than a
    handful of pixels do change."""
    from polrig.sim.scene import make_scene
    from polrig.sim.targets import target_scene

    scene = target_scene(make_scene("sphere", 320, 240), "charuco", tilt_deg=35.0, roll_deg=20.0)
    edges = render(scene, angle_deg).kd
    monkeypatch.setattr(footprint, "edge_pixels", lambda m: np.ones(np.shape(m), bool))
    every = render(scene, angle_deg).kd
    np.testing.assert_array_equal(edges, every)
    from polrig.sim import render as render_module
    monkeypatch.setattr(render_module, "footprint_albedo", lambda scene, a, hits, kd: kd)
    centre = render(scene, angle_deg).kd
    changed = np.any(centre != every, axis=0)
    assert changed.sum() > 1000


def test_edge_pixels_finds_every_pixel_a_straight_boundary_crosses():
    """Half-planes at many angles and offsets: every pixel whose footprint the boundary
    crosses (some of its 16 x 16 strata on either side) is flagged."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:40, 0:40].astype(float)
    off = stratified_offsets(16)
    for _ in range(60):
        a = rng.uniform(0, np.pi)
        n = np.array([np.cos(a), np.sin(a)])
        c = rng.uniform(15, 25) * (n[0] + n[1])
        side = lambda uu, vv: (n[0] * uu + n[1] * vv > c)  # noqa: E731
        share = np.mean([side(u + du, v + dv) for du in off for dv in off], axis=0)
        crossed = (share > 0) & (share < 1)
        flagged = footprint.edge_pixels(side(u, v).astype(int))
        assert np.all(flagged[crossed]), (a, c)


def test_the_scene_record_names_footprint_sampling_only_where_an_object_asks():
    """A scene recorded before footprints existed (a session's rig record) reads the same."""
    assert "footprint_samples" not in _edge_scene(0.0, 1).objects[0].to_json()
    assert _edge_scene(0.0, 4).objects[0].to_json()["footprint_samples"] == 4
