"""One-bounce indirect light (polrig.sim.interreflection) against a deterministic quadrature of the
same integral over the reflecting surface, and the rendered truth with interreflections:
realizable, unchanged by default, and consistent between the Mueller image and the Stokes
images the simulated camera sees."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.optics import pbrdf
from polrig.optics import realizability as rz
from polrig.sim import surface_bsdf
from polrig.sim.geometry import (
    PinholeCamera,
    PointLight,
    TurntableGeometry,
    look_at,
    rotation_about_axis,
)
from polrig.sim.interreflection import (
    BEAM_REFERENCE,
    as_surface,
    evaluate_materials,
    one_bounce,
)
from polrig.sim.materials import Material, SurfaceMaterial
from polrig.sim.optical_data import CONDUCTORS
from polrig.sim.render import render
from polrig.sim.scene import Scene, SceneObject, make_scene
from polrig.sim.shapes import Rectangle

WALL_HALF = 0.03
WALL_Y = 0.04


def _two_planes(wall_material) -> Scene:
    """A glossy plastic floor (z = 0) and a vertical wall at y = WALL_Y facing -y, lit from
    the front-left; nothing else, so every point of the wall sees the light and the floor."""
    floor = SceneObject("floor", Rectangle(0.08, 0.08), (Material("floor", (0.5, 0.4, 0.3), 0.3, 1.5),),
                        np.zeros(3), on_turntable=False)
    wall = SceneObject("wall", Rectangle(WALL_HALF, WALL_HALF), (wall_material,),
                       [0.0, WALL_Y, WALL_HALF], rotation=rotation_about_axis([1, 0, 0], 90.0),
                       on_turntable=False)
    rc, tc = look_at([0.0, -0.3, 0.2], [0.0, 0.0, 0.01])
    cam = PinholeCamera(60.0, 60.0, 23.5, 23.5, 48, 48, rc, tc)
    light = PointLight([-0.05, -0.1, 0.12])
    return Scene("planes", (floor, wall), cam, light, TurntableGeometry(), [1.0, 0.0, 0.0], [0.0, 0.0, 0.02])


def _quadrature(scene: Scene, p: np.ndarray, wo: np.ndarray, n_grid: int = 200) -> np.ndarray:
    """Indirect radiance Mueller ``(3, 4, 4)`` at floor point ``p`` by the midpoint rule over
    the wall's area: ``sum M_p M_q I / |l - q|^2 cos_q / d^2 dA``."""
    u = (np.arange(n_grid) + 0.5) / n_grid * 2 * WALL_HALF - WALL_HALF
    xx, zz = np.meshgrid(u, u + WALL_HALF)
    q = np.stack([xx.ravel(), np.full(xx.size, WALL_Y), zz.ravel()], -1)
    nq = np.tile([0.0, -1.0, 0.0], (len(q), 1))
    d = np.linalg.norm(p - q, axis=1)
    omega = (q - p) / d[:, None]
    to_l = scene.light.position_m - q
    lq = np.linalg.norm(to_l, axis=1)
    m_q = evaluate_materials(scene, 0.0, np.ones(len(q), int), q, nq, to_l / lq[:, None], -omega,
                             (scene.stage_zero_axis, BEAM_REFERENCE))
    n_p = np.tile([0.0, 0.0, 1.0], (len(q), 1))
    m_p = evaluate_materials(scene, 0.0, np.zeros(len(q), int), np.tile(p, (len(q), 1)), n_p, omega,
                             np.tile(wo, (len(q), 1)), (BEAM_REFERENCE, scene.camera.R[0]))
    cos_q = omega[:, 1]  # the wall normal facing p is -y
    w = cos_q / d ** 2 / lq ** 2 * (2 * WALL_HALF / n_grid) ** 2
    return np.einsum("n,ncij->cij", w, m_p @ m_q)


@pytest.mark.parametrize("wall", [
    Material("wall_plastic", (0.2, 0.6, 0.3), 0.4, 1.6),
    SurfaceMaterial("wall_gold", CONDUCTORS["gold"], 0.35),
], ids=["plastic", "gold"])
def test_one_bounce_agrees_with_quadrature_over_the_reflector(wall):
    """Monte Carlo (12 independent estimates of 400 samples each, mean and standard error) against
    the midpoint rule on a 200 x 200 grid: every Mueller element within 4.5 standard errors plus
    0.5 % of m00 (measured: within 2.0), for a dielectric wall and a rough gold wall (whose
    retardance puts S3 into the beam). The 12 estimates are 12 copies of each point in one call:
    every pixel draws its own directions, so the copies are independent, and the sample loop runs
    once instead of 12 times."""
    scene = _two_planes(wall)
    pts = np.array([[0.0, 0.0, 0.0], [0.015, 0.02, 0.0], [-0.02, 0.01, 0.0]])
    wo = scene.camera.centre_m - pts
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    n = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    copies = 12
    tile = lambda a: np.tile(a, (copies,) + (1,) * (a.ndim - 1))  # noqa: E731  copy-major
    runs = one_bounce(scene, 0.0, tile(pts), tile(n), tile(n), tile(wo), np.zeros(copies * len(pts), int),
                      tile(pts), samples=400, seed=0).reshape((copies, len(pts), 3, 3, 3))
    mean, se = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(len(runs))
    for i, p in enumerate(pts):
        ref = _quadrature(scene, p, wo[i])[..., :3, :3]
        tol = 4.5 * se[i] + 0.005 * ref[:, :1, :1]
        assert ref[:, 0, 0].min() > 0
        assert np.all(np.abs(mean[i] - ref) <= tol), (i, mean[i] - ref, tol)


def test_baek_materials_evaluate_identically_as_surface_materials():
    rng = np.random.default_rng(4)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    wi = n + 0.8 * rng.normal(size=(50, 3))
    wo = n + 0.8 * rng.normal(size=(50, 3))
    mat = Material("m", (0.3, 0.5, 0.7), 0.25, 1.45, ks=0.8)
    for dist in ("ggx", "beckmann"):
        sm = as_surface(mat, dist)
        mine = surface_bsdf.evaluate(n, [0, 0, 1], wi, wo, sm.parameters(np.zeros((50, 3))), distribution=dist)
        ref = pbrdf.mueller(n, wi, wo, kd=np.tile(mat.kd, (50, 1)), alpha=0.25, eta=1.45, ks=0.8, distribution=dist)
        np.testing.assert_allclose(mine, ref, atol=1e-13)


def test_rendered_interreflections_are_realizable_and_consistent():
    scene = make_scene("corner", 48, 48)
    direct = render(scene, 0.0)
    full = render(scene, 0.0, indirect_samples=8)
    assert direct.indirect is None and full.counts["indirect_pixels"] > 200
    # direct part unchanged; indirect light reaches pixels in shadow of the point light
    np.testing.assert_array_equal(full.brdf_lit, direct.brdf_lit)
    rad = full.radiance_mueller()
    assert np.any(rad[..., full.shadow] != 0) and not np.any(direct.radiance_mueller()[..., direct.shadow])
    # the Stokes images are the Mueller image times the incident state
    s_in = np.array([1.0, 0.6, -0.3])
    np.testing.assert_allclose(full.radiance_state(s_in), np.einsum("cijhw,j->cihw", rad, s_in),
                               rtol=1e-5, atol=1e-6 * np.abs(rad).max())
    m = np.moveaxis(rad[..., full.mask], -1, 0).reshape(-1, 3, 3).astype(np.float64)
    m = m[np.abs(m).max(axis=(1, 2)) > 0]
    assert rz.pass_rate(rz.is_physical_linear(m, test="gk")) == 1.0
    assert rz.pass_rate(rz.is_physical_linear(m, rtol=1e-6)) == 1.0
    # deterministic for a seed
    again = render(scene, 0.0, indirect_samples=8)
    np.testing.assert_array_equal(again.indirect, full.indirect)
