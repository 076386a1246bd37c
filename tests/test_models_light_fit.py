"""Global light-direction fit (polrig.models.light_fit): closed-form gains against least squares, and a
round trip through the core pBRDF (polrig.optics.pbrdf renders, the torch fit recovers the light)."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from polrig.models.light_fit import (  # noqa: E402
    _residuals,
    fibonacci_directions,
    fit_light_direction,
    local_offsets,
    shading_pick,
)
from polrig.models.pbrdf_torch import image_blocks  # noqa: E402
from polrig.optics import pbrdf  # noqa: E402

AXIS = np.array([0.0, -1.0, 0.0])


def _sphere(size: int = 32):
    """Unit normals of a sphere filling a ``size`` x ``size`` image, view directions of a
    pinhole camera (f = 2.5 size) at the origin looking along +Z; ``(3, H, W)`` and mask."""
    v, u = np.mgrid[0:size, 0:size] + 0.5
    x, y = (u - size / 2) / (size / 2 - 1), (v - size / 2) / (size / 2 - 1)
    r2 = x * x + y * y
    mask = r2 < 0.95
    n = np.stack([x, y, -np.sqrt(np.clip(1 - r2, 0, None))])
    ray = np.stack([(u - size / 2) / (2.5 * size), (v - size / 2) / (2.5 * size), np.ones_like(u)])
    wo = -ray / np.linalg.norm(ray, axis=0)
    return n * mask, wo, mask


def _render(n, wo, mask, light, s_in, g_s, g_c, alpha=0.3):
    """Measured Stokes ``(C, 3, H, W)`` of ``g_s Ms + g_c Md`` from the core numpy pBRDF."""
    hw = lambda a: np.moveaxis(a, 0, -1)[mask]  # noqa: E731
    wi = np.broadcast_to(light, hw(n).shape)
    ms, md = pbrdf.specular_diffuse_blocks(hw(n), wi, hw(wo), alpha=alpha, eta=1.5, stage_zero_axis=AXIS,
                                           camera_x_axis=[1.0, 0, 0])
    out = np.zeros((len(g_c), 3) + mask.shape)
    for c, g in enumerate(g_c):
        out[c][:, mask] = ((g_s * ms + g * md) @ s_in).T
    return out


def _t(a):
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None]


def test_closed_form_gains_equal_least_squares():
    n, wo, mask = _sphere(16)
    light = np.array([0.3, -0.4, -0.85]) / np.linalg.norm([0.3, -0.4, -0.85])
    s_in = np.array([1.0, 0.6, -0.7])
    rng = np.random.default_rng(0)
    stokes = _render(n, wo, mask, light, s_in, 0.8, (0.3, 0.5, 0.7)) + rng.normal(0, 0.01, (3, 3, 16, 16)) * mask
    cand = torch.tensor([[[0.1, -0.5, -0.86]]])
    args = (_t(n), _t(wo), torch.tensor([0.3]), _t(s_in), _t(AXIS), _t(mask[None]))
    res = _residuals(cand, _t(stokes), *args)
    ms, md = image_blocks(_t(n), cand.reshape(1, 3, 1, 1).expand(1, 3, 16, 16), _t(wo), torch.tensor([0.3]), _t(AXIS))
    a = (ms * _t(s_in)[:, None, :, None, None]).sum(2)[0].double() * torch.from_numpy(mask)
    b = (md * _t(s_in)[:, None, :, None, None]).sum(2)[0].double() * torch.from_numpy(mask)
    cols = [a.expand(3, 3, 16, 16).reshape(-1)]
    for c in range(3):
        z = torch.zeros(3, 3, 16, 16, dtype=torch.float64)
        z[c] = b
        cols.append(z.reshape(-1))
    amat, y = torch.stack(cols, 1), torch.from_numpy(stokes * mask).reshape(-1)
    sol = torch.linalg.lstsq(amat, y[:, None]).solution
    assert (sol >= 0).all()  # the clamps are inactive here
    assert float(res) == pytest.approx(float(((amat @ sol)[:, 0] - y).pow(2).sum()), rel=1e-4)


@pytest.mark.parametrize("light, s_deg", [((0.3, -0.4, -0.85), 0.0), ((-0.6, -0.2, -0.75), 60.0),
                                          ((0.05, -0.8, -0.6), 135.0)])
def test_recovers_the_light_of_a_core_pbrdf_rendering(light, s_deg):
    n, wo, mask = _sphere(32)
    light = np.asarray(light) / np.linalg.norm(light)
    t = np.deg2rad(2 * s_deg)
    s_in = np.array([1.0, 0.99 * np.cos(t), 0.99 * np.sin(t)])
    stokes = _render(n, wo, mask, light, s_in, 0.6, (0.2, 0.45, 0.8))
    got = fit_light_direction(_t(stokes), _t(n), _t(wo), torch.tensor([0.3]), _t(s_in), _t(AXIS), _t(mask[None]),
                              candidates=fibonacci_directions(400, 0.3), offsets=local_offsets(8.0), pool=2)
    err = np.degrees(np.arccos(np.clip(float((got[0].double() * torch.from_numpy(light)).sum()), -1, 1)))
    assert err < 4.0
    assert torch.allclose(got.norm(dim=1), torch.ones(1), atol=1e-5)


def test_shading_pick_takes_the_candidate_whose_lambertian_shading_explains_the_image():
    """Intensity rendered as 0.7 max(n.wi, 0) from a random choice between two candidates:
    the pick recovers that choice wherever the two shadings differ."""
    rng = np.random.default_rng(4)
    plus = rng.normal(size=(3, 12, 12)) + np.array([0, 0, -2.0])[:, None, None]
    plus /= np.linalg.norm(plus, axis=0)
    minus = plus * np.array([-1, -1, 1.0])[:, None, None]  # azimuth turned by 180 deg about the view axis
    wi = np.array([0.5, 0.2, -0.8]) / np.linalg.norm([0.5, 0.2, -0.8])
    truth = rng.random((12, 12)) < 0.5
    n = np.where(truth[None], plus, minus)
    intensity = 0.7 * np.clip(np.einsum("chw,c->hw", n, wi), 0, None)
    picked = shading_pick(_t(plus), _t(minus), _t(wi)[..., None, None], _t(intensity), torch.ones(1, 12, 12, dtype=bool))
    sp, sm = (np.clip(np.einsum("chw,c->hw", c, wi), 0, None) for c in (plus, minus))
    differ = np.abs(sp - sm) > 1e-3
    assert differ.mean() > 0.5
    np.testing.assert_allclose(picked[0].numpy()[:, differ], n[:, differ], atol=1e-6)

