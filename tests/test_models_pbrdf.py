"""The differentiable torch pBRDF (polrig.models.pbrdf_torch) reproduces polrig.optics.pbrdf."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from polrig.models.pbrdf_torch import image_blocks, specular_diffuse_blocks  # noqa: E402
from polrig.optics import pbrdf  # noqa: E402


def _random_geometry(rng: np.random.Generator, n: int):
    normal = rng.normal(size=(n, 3))
    normal[:, 2] = -np.abs(normal[:, 2]) - 0.2  # facing the camera (camera looks along +Z)
    wo = rng.normal(size=(n, 3)) * 0.3 + np.array([0.0, 0.0, -1.0])
    wi = rng.normal(size=(n, 3))
    alpha = rng.uniform(0.02, 0.9, size=n)
    stage = rng.normal(size=(n, 3))
    return normal, wi, wo, alpha, stage


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_torch_pbrdf_matches_core(seed):
    rng = np.random.default_rng(seed)
    normal, wi, wo, alpha, stage = _random_geometry(rng, 4000)
    cam = np.array([1.0, 0.0, 0.0])
    ms_ref, md_ref = pbrdf.specular_diffuse_blocks(normal, wi, wo, alpha=alpha, eta=1.5,
                                                   stage_zero_axis=stage, camera_x_axis=cam)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    ms, md = specular_diffuse_blocks(t(normal), t(wi), t(wo), alpha=t(alpha), stage_zero_axis=t(stage),
                                     camera_x_axis=t(cam), eta=1.5)
    visible = pbrdf.visible(normal, wi, wo)
    assert visible.sum() > 1000 and (~visible).sum() > 100  # both cases exercised
    scale = np.maximum(1.0, np.abs(ms_ref).max(axis=(-1, -2), keepdims=True))
    np.testing.assert_allclose(ms.numpy() / scale, ms_ref / scale, atol=1e-5, rtol=0)
    np.testing.assert_allclose(md.numpy(), md_ref, atol=1e-5, rtol=0)
    # The combination ks Ms + kd Md is the core's linear_rig_mueller.
    kd = rng.uniform(0, 1, size=(4000, 3))
    full = pbrdf.linear_rig_mueller(normal, wi, wo, kd=kd, alpha=alpha, stage_zero_axis=stage,
                                    camera_x_axis=cam)
    mine = ms.numpy()[:, None] + kd[..., None, None] * md.numpy()[:, None]
    np.testing.assert_allclose(mine / scale[:, None], full / scale[:, None], atol=1e-5, rtol=0)


def test_image_wrapper_is_plane_first_and_float32_close():
    rng = np.random.default_rng(5)
    b, h, w = 2, 5, 7
    normal, wi, wo, _, _ = _random_geometry(rng, b * h * w)
    alpha = rng.uniform(0.05, 0.5, size=b)
    stage = rng.normal(size=(b, 3))
    img = lambda v: torch.as_tensor(v.reshape(b, h, w, 3).transpose(0, 3, 1, 2).copy(), dtype=torch.float32)  # noqa: E731
    ms, md = image_blocks(img(normal), img(wi), img(wo), torch.as_tensor(alpha, dtype=torch.float32),
                          torch.as_tensor(stage, dtype=torch.float32))
    assert ms.shape == (b, 3, 3, h, w) and md.shape == (b, 3, 3, h, w)
    ms_ref, md_ref = pbrdf.specular_diffuse_blocks(
        normal.reshape(b, h, w, 3), wi.reshape(b, h, w, 3), wo.reshape(b, h, w, 3),
        alpha=alpha[:, None, None], stage_zero_axis=stage[:, None, None, :], camera_x_axis=[1.0, 0, 0])
    ms_ref = np.moveaxis(ms_ref, (-2, -1), (1, 2))
    md_ref = np.moveaxis(md_ref, (-2, -1), (1, 2))
    scale = np.maximum(1.0, np.abs(ms_ref).max())
    np.testing.assert_allclose(ms.numpy() / scale, ms_ref / scale, atol=2e-4)
    np.testing.assert_allclose(md.numpy(), md_ref, atol=1e-5)


def test_gradients_are_finite_at_degenerate_geometry():
    # Normal incidence and retro-reflection (wi = wo = n) hit every fallback branch.
    n = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64, requires_grad=True)
    wi = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64, requires_grad=True)
    wo = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    ms, md = specular_diffuse_blocks(n, wi, wo, alpha=torch.tensor(0.3, dtype=torch.float64),
                                     stage_zero_axis=torch.tensor([1.0, 0, 0], dtype=torch.float64),
                                     camera_x_axis=torch.tensor([1.0, 0, 0], dtype=torch.float64))
    (ms.sum() + md.sum()).backward()
    assert torch.isfinite(n.grad).all() and torch.isfinite(wi.grad).all()
    ref_s, ref_d = pbrdf.specular_diffuse_blocks(n.detach().numpy(), wi.detach().numpy(), wo.numpy(),
                                                 alpha=0.3, stage_zero_axis=[1.0, 0, 0], camera_x_axis=[1.0, 0, 0])
    np.testing.assert_allclose(ms.detach().numpy(), ref_s, atol=1e-6)
    np.testing.assert_allclose(md.detach().numpy(), ref_d, atol=1e-6)


def test_image_blocks_mask_scales_every_element_for_any_mask():
    # image_blocks(mask=m) applies the mask to the per-pixel scale factors; the blocks are the
    # unmasked ones times m (also for non-binary m), as the single-shot graph composed them before
    rng = np.random.default_rng(6)
    b, h, w = 2, 4, 5
    normal, wi, wo, _, _ = _random_geometry(rng, b * h * w)
    img = lambda v: torch.as_tensor(v.reshape(b, h, w, 3).transpose(0, 3, 1, 2).copy())  # noqa: E731
    alpha = torch.tensor([0.1, 0.6], dtype=torch.float64)
    stage = torch.as_tensor(rng.normal(size=(b, 3)))
    mask = torch.as_tensor(rng.uniform(size=(b, 1, h, w)))
    mask[:, :, 0] = 0.0
    ms, md = image_blocks(img(normal), img(wi), img(wo), alpha, stage)
    ms_m, md_m = image_blocks(img(normal), img(wi), img(wo), alpha, stage, mask=mask)
    torch.testing.assert_close(ms_m, ms * mask[:, None], rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(md_m, md * mask[:, None], rtol=1e-12, atol=1e-15)
