"""PIPNet's shape-from-polarization prior (polrig.models.pipnet) against the core pBRDF's physics."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from polrig.models.pipnet import PIPNet, diffuse_dolp, diffuse_zenith, sfp_candidates  # noqa: E402
from polrig.optics import pbrdf  # noqa: E402


@pytest.mark.parametrize("eta", [1.3, 1.5, 1.8])
def test_diffuse_zenith_inverts_the_diffuse_dolp(eta):
    zen = torch.linspace(0.0, 0.5 * np.pi - 1e-3, 500, dtype=torch.float64)
    assert torch.allclose(diffuse_zenith(diffuse_dolp(zen, eta), eta), zen, atol=1e-9)
    # values the model cannot produce (noise, specular) clamp to grazing instead of NaN
    over = diffuse_zenith(torch.tensor([0.99, 1.5, -0.1], dtype=torch.float64), eta)
    assert torch.isfinite(over).all() and over[0] > 1.5 and over[2] == 0.0


def test_diffuse_dolp_matches_the_core_pbrdf_transmission():
    """DoLP of the core pBRDF's diffuse block (unpolarized light in) at emission zenith theta."""
    rng = np.random.default_rng(1)
    zen = rng.uniform(0.0, np.deg2rad(85.0), 64)
    wo = np.stack([np.sin(zen), np.zeros_like(zen), np.cos(zen)], -1)
    n = np.broadcast_to([0.0, 0.0, 1.0], wo.shape)
    wi = np.broadcast_to(np.array([0.2, 0.3, 1.0]) / np.linalg.norm([0.2, 0.3, 1.0]), wo.shape)
    _, md = pbrdf.specular_diffuse_blocks(n, wi, wo, alpha=0.3, eta=1.5, stage_zero_axis=[1.0, 0, 0],
                                          camera_x_axis=[0, 1.0, 0])
    s = md[..., 0]  # unpolarized light in
    expect = np.hypot(s[:, 1], s[:, 2]) / s[:, 0]
    got = diffuse_dolp(torch.from_numpy(zen), 1.5).numpy()
    assert np.allclose(got, expect, rtol=1e-9, atol=1e-12)


def _random_geometry(rng, count, max_zenith_deg):
    """Camera-frame unit ``wo`` around -Z (towards the camera), normals at emission zenith up to
    ``max_zenith_deg`` from ``wo`` and lights in front of them."""
    wo = np.stack([rng.normal(0, 0.2, count), rng.normal(0, 0.2, count), -np.ones(count)], -1)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    t = rng.normal(size=(count, 3))
    t -= np.sum(t * wo, -1, keepdims=True) * wo
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    zen = np.deg2rad(rng.uniform(0.0, max_zenith_deg, count))[:, None]
    n = np.cos(zen) * wo + np.sin(zen) * t
    wi = n + rng.normal(0, 0.4, (count, 3))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    keep = (np.sum(wi * n, -1) > 0.05)
    return n[keep], wi[keep], wo[keep]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_true_normal_is_one_of_the_candidates_for_diffuse_light(seed):
    """Pure diffuse reflection of any incident state (the core pBRDF in the rig frames): one of
    the two candidates is the true normal, the other its mirror about the view direction."""
    rng = np.random.default_rng(seed)
    n, wi, wo = _random_geometry(rng, 400, 85.0)
    _, md = pbrdf.specular_diffuse_blocks(n, wi, wo, alpha=0.2, eta=1.5, stage_zero_axis=[0, -1.0, 0],
                                          camera_x_axis=[1.0, 0, 0])
    s_in = np.array([1.0, *(0.98 * np.array([np.cos(0.7 * seed), np.sin(0.7 * seed)]))])
    stokes = np.einsum("pij,j->pi", md, s_in)  # (P, 3)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a.T[None, :, None, :]))  # noqa: E731 (1,3,1,P)
    plus, minus = sfp_candidates(t(stokes)[:, None].repeat(1, 3, 1, 1, 1), t(wo))
    plus, minus = plus[0, :, 0].numpy().T, minus[0, :, 0].numpy().T
    err = np.minimum(np.linalg.norm(plus - n, axis=-1), np.linalg.norm(minus - n, axis=-1))
    # below ~1 deg of emission zenith the polarization direction drowns in the epsilon that
    # guards it (and sin(zenith) makes the normal insensitive to it)
    steep = np.sum(n * wo, -1) < np.cos(np.deg2rad(2.0))
    assert err[steep].max() < 1e-4 and err.max() < 2e-3
    mirror = 2.0 * np.sum(n * wo, -1, keepdims=True) * wo - n
    other = np.where((np.linalg.norm(plus - n, axis=-1) < np.linalg.norm(minus - n, axis=-1))[:, None], minus, plus)
    assert np.allclose(other[steep], mirror[steep], atol=1e-4)


def test_candidates_of_unpolarized_light_face_the_camera():
    wo = torch.nn.functional.normalize(torch.tensor([0.1, -0.2, -1.0], dtype=torch.float64), dim=0)
    stokes = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)[None, None, :, None, None]
    plus, minus = sfp_candidates(stokes, wo[None, :, None, None])
    assert torch.allclose(plus[0, :, 0, 0], wo, atol=1e-9) and torch.allclose(minus[0, :, 0, 0], wo, atol=1e-9)


def test_pipnet_prior_takes_the_candidate_nearer_its_free_normal_as_trusted():
    torch.manual_seed(0)
    net = PIPNet(3, 8, sfp_prior=True).eval()
    wo = torch.nn.functional.normalize(torch.randn(2, 3, 16, 16) * 0.2 + torch.tensor([0, 0, -1.0])[None, :, None, None], dim=1)
    with torch.no_grad():
        # a head that fully trusts the prior returns the candidate nearer to its free normal
        # (a constant head: the free normal is the view direction tilted towards +X)
        net.normal_head.weight.zero_()
        net.normal_head.bias.copy_(torch.tensor([0.5, 0, 0, 30.0]))
        analyzer = torch.rand(2, 3, 4, 16, 16)
        out = net(analyzer, torch.ones(2, 1, 16, 16), torch.tensor([[1.0, 0.9, 0.1]] * 2), wo)
        from polrig.models.layers import stokes_from_analyzer
        plus, minus = sfp_candidates(stokes_from_analyzer(analyzer), wo)
    free = torch.nn.functional.normalize(wo + torch.tensor([0.5, 0, 0])[None, :, None, None], dim=1)
    margin = ((plus - minus) * free).sum(1, keepdim=True)
    nearer = torch.where(margin >= 0, plus, minus)
    clear = (margin.abs() > 0.5)[:, 0]  # away from ties the soft choice is the nearer candidate
    assert torch.allclose(out["normal"].norm(dim=1), torch.ones(2, 16, 16), atol=1e-5)
    assert clear.float().mean() > 0.3
    assert torch.allclose(out["normal"].permute(0, 2, 3, 1)[clear],
                          torch.nn.functional.normalize(nearer, dim=1).permute(0, 2, 3, 1)[clear], atol=1e-5)
    with torch.no_grad():  # no trust: the free normal
        net.normal_head.bias.copy_(torch.tensor([0.5, 0, 0, -30.0]))
        out = net(analyzer, torch.ones(2, 1, 16, 16), torch.tensor([[1.0, 0.9, 0.1]] * 2), wo)
    assert torch.allclose(out["normal"], free, atol=1e-5)


def test_candidate_choice_is_continuous_at_ties():
    """Equidistant candidates blend smoothly: tiny changes of the inputs move the normal a
    little (a hard switch would jump between the two candidates)."""
    torch.manual_seed(1)
    net = PIPNet(3, 8, sfp_prior=True).eval()
    with torch.no_grad():
        net.normal_head.weight.zero_()
        net.normal_head.bias.copy_(torch.tensor([0.0, 0, 0, 30.0]))  # free normal = wo: a tie
        wo = torch.nn.functional.normalize(torch.tensor([0.05, -0.1, -1.0]), dim=0)[None, :, None, None].expand(1, 3, 8, 8)
        analyzer = torch.rand(1, 3, 4, 8, 8)
        a = net(analyzer, torch.ones(1, 1, 8, 8), torch.tensor([[1.0, 0.5, 0.2]]), wo.contiguous())["normal"]
        b = net(analyzer * (1 + 1e-4 * torch.rand_like(analyzer)), torch.ones(1, 1, 8, 8),
                torch.tensor([[1.0, 0.5, 0.2]]), wo.contiguous())["normal"]
    assert float((a - b).abs().max()) < 1e-2


def test_sfp_supervision_targets_the_nearer_candidate_and_its_reliability():
    """The pick is pushed towards the candidate nearer the true normal and the trust towards
    'the nearer candidate is within TRUST_TARGET_DEG': confident right decisions cost almost
    nothing, confident wrong ones a lot; ties (equal dot products) are not supervised."""
    from polrig.models.pipnet import TRUST_TARGET_DEG, sfp_supervision_loss

    n = torch.nn.functional.normalize(torch.tensor([0.3, 0.0, -1.0]), dim=0)[None, :, None, None].expand(1, 3, 4, 4)
    near = n.clone()  # candidate equal to the truth
    far = torch.nn.functional.normalize(torch.tensor([-0.3, 0.0, -1.0]), dim=0)[None, :, None, None].expand(1, 3, 4, 4)
    mask = torch.ones(1, 1, 4, 4)

    def loss(pick, trust, plus=near, minus=far):
        pred = {"sfp_plus": plus, "sfp_minus": minus, "pick_logit": torch.full((1, 1, 4, 4), pick),
                "trust_logit": torch.full((1, 1, 4, 4), trust)}
        return [float(x) for x in sfp_supervision_loss(pred, n, mask)]

    assert loss(20.0, 20.0) == pytest.approx([0.0, 0.0], abs=1e-6)  # picks plus, trusts it
    assert min(loss(-20.0, -20.0)) > 19.0  # picks the far one and distrusts a reliable candidate
    assert loss(-20.0, 20.0, plus=far, minus=near)[0] == pytest.approx(0.0, abs=1e-6)
    # the nearer candidate 2x the trust angle away: not reliable, so distrust is right
    tilt = torch.deg2rad(torch.tensor(2 * TRUST_TARGET_DEG))
    off = torch.nn.functional.normalize(n + torch.tan(tilt) * torch.tensor([0.0, 1.0, 0.0])[None, :, None, None], dim=1)
    assert loss(20.0, -20.0, plus=off)[1] == pytest.approx(0.0, abs=1e-6)
    assert loss(20.0, 20.0, plus=off)[1] > 19.0
    # equal candidates: nothing to pick, the pick is not supervised
    assert loss(-20.0, 20.0, plus=near, minus=near)[0] == 0.0


def test_pipnet_loss_adds_the_sfp_terms_only_when_asked():
    from polrig.models.pipnet import pipnet_loss

    torch.manual_seed(2)
    net = PIPNet(3, 8, sfp_prior=True)
    wo = torch.nn.functional.normalize(torch.randn(2, 3, 16, 16) * 0.2 + torch.tensor([0, 0, -1.0])[None, :, None, None], dim=1)
    pred = net(torch.rand(2, 3, 4, 16, 16), torch.ones(2, 1, 16, 16), torch.tensor([[1.0, 0.9, 0.1]] * 2), wo)
    args = (torch.nn.functional.normalize(torch.randn(2, 3, 16, 16), dim=1), torch.rand(2, 3, 16, 16), wo,
            torch.rand(2), torch.ones(2, 1, 16, 16))
    base, d0 = pipnet_loss(pred, *args)
    total, d1 = pipnet_loss(pred, *args, sfp_weight=0.5)
    assert "bce_pick" not in d0 and {"bce_pick", "bce_trust"} <= set(d1)
    assert float((total - base).detach()) == pytest.approx(0.5 * (d1["bce_pick"] + d1["bce_trust"]), rel=1e-5)
