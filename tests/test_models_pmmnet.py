"""PMMNet's physics pieces: the closed-form gain fit, the 5 -> 3x3 expansion, and the
zero-initialised residuals (an untrained PMMNet returns the gain-fitted initialization); the
rewritten gain fit, rendering and composition against their plain formulations."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from polrig.models.layers import apply_mueller  # noqa: E402
from polrig.models.pmmnet import (  # noqa: E402
    DIFFUSE_ELEMENTS,
    SPECULAR_ELEMENTS,
    PMMNet,
    compose,
    expand5,
    fit_gains,
    fit_gains_to,
    gain_fitted_initialization,
    renderings,
)


def _random_blocks(b=2, h=5, w=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    ms = torch.randn(b, 3, 3, h, w, generator=g, dtype=torch.float64)
    md = torch.randn(b, 3, 3, h, w, generator=g, dtype=torch.float64)
    kd = torch.rand(b, 3, h, w, generator=g, dtype=torch.float64) + 0.1
    s_in = torch.tensor([[0.5, 0.3, -0.2], [0.5, -0.1, 0.45]], dtype=torch.float64)
    return ms, md, kd, s_in


def test_fit_gains_recovers_the_gains_of_an_exact_measurement():
    ms, md, kd, s_in = _random_blocks()
    gs_true = torch.rand(2, 1, 5, 6, dtype=torch.float64) * 3 + 0.2
    gc_true = torch.rand(2, 3, 5, 6, dtype=torch.float64) * 2 + 0.1
    m = (gs_true[:, :, None] * ms)[:, None] + (gc_true * kd)[:, :, None, None] * md[:, None]
    stokes = apply_mueller(m, s_in)
    gs, gc = fit_gains(stokes, ms, md, kd, s_in, ridge=0.0, eps=1e-15)
    np.testing.assert_allclose(gs.numpy(), gs_true.numpy(), rtol=1e-6)
    np.testing.assert_allclose(gc.numpy(), gc_true.numpy(), rtol=1e-6)


def test_fit_gains_without_specular_falls_back_to_the_common_gain():
    ms, md, kd, s_in = _random_blocks(seed=1)
    ms = torch.zeros_like(ms)
    m = 2.5 * kd[:, :, None, None] * md[:, None]
    stokes = apply_mueller(m, s_in)
    gs, gc = fit_gains(stokes, ms, md, kd, s_in)
    np.testing.assert_allclose(gs.numpy(), 2.5, rtol=1e-4)  # = g0, nothing to fit
    np.testing.assert_allclose(gc.numpy(), 2.5, rtol=1e-4)
    # Dark pixels: zero gains, no NaN.
    gs0, gc0 = fit_gains(torch.zeros_like(stokes), ms, md, kd, s_in)
    assert torch.all(gs0 == 0) and torch.all(gc0 == 0)


def test_expand5_places_the_branch_elements():
    v = torch.arange(5, dtype=torch.float32).reshape(1, 5, 1, 1) + 1
    for elements in (SPECULAR_ELEMENTS, DIFFUSE_ELEMENTS):
        m = expand5(v, elements)[0, :, :, 0, 0]
        for i, (r, c) in enumerate(elements):
            assert m[r, c] == i + 1
        assert int((m != 0).sum()) == 5


def test_untrained_pmmnet_is_the_gain_fitted_initialization():
    torch.manual_seed(0)
    b, h, w = 1, 16, 16
    ms, md, kd, _ = _random_blocks(b, h, w, seed=2)
    ms, md, kd = ms.float().abs(), md.float().abs(), kd.float()
    s_in = torch.tensor([[0.5, 0.2, 0.3]])
    m_true = (1.7 * ms)[:, None] + (0.6 * kd)[:, :, None, None] * md[:, None]
    stokes = apply_mueller(m_true, s_in)
    # Analyzer images whose ideal Stokes are `stokes` (I_t = (S0 + S1 cos 2t + S2 sin 2t) / 2).
    t = torch.deg2rad(torch.tensor([0.0, 45.0, 90.0, 135.0]))
    rows = 0.5 * torch.stack([torch.ones(4), torch.cos(2 * t), torch.sin(2 * t)], 1)
    analyzer = torch.einsum("ja,bcahw->bcjhw", rows, stokes)
    mask = torch.ones(b, 1, h, w)
    out = PMMNet(3, 8).eval()(analyzer, mask, s_in, ms, md, kd)
    gs, gc = fit_gains(stokes, ms, md, kd, s_in)
    expected = (gs[:, :, None] * ms)[:, None] + (gc * kd)[:, :, None, None] * md[:, None]
    np.testing.assert_allclose(out["mueller"].detach().numpy(), expected.numpy(), rtol=1e-5, atol=1e-6)
    # The ridge keeps the fit close to, not exactly at, the measurement (true gains 1.7, 0.6).
    rendered = apply_mueller(out["mueller"], s_in).detach()
    assert torch.linalg.norm(rendered - stokes) < 0.05 * torch.linalg.norm(stokes)


def _fit_gains_reference(stokes, ms, md, kd, s_in, ridge=0.05, eps=1e-6):
    """The closed form of :func:`polrig.models.pmmnet.fit_gains` written with plain reductions over
    whole 3 C-plane images (the formulation the split-sum code replaces)."""
    a = (ms * s_in[:, None, :, None, None]).sum(2)
    b = kd[:, :, None] * (md * s_in[:, None, :, None, None]).sum(2)[:, None]
    r = a[:, None] + b
    g0 = ((stokes * r).sum((1, 2)) / ((r * r).sum((1, 2)) + eps)).clamp_min(0.0)[:, None]
    lam = ridge * ((a * a).sum(1, keepdim=True) + (b * b).sum((1, 2))[:, None]) / 4.0 + eps
    nb = (b * b).sum(2)
    den_c = nb + lam
    bs, ba = (b * stokes).sum(2), (b * a[:, None]).sum(2)
    big_r = stokes - b * ((bs + lam * g0) / den_c)[:, :, None]
    big_q = a[:, None] - b * (ba / den_c)[:, :, None]
    p, q = (bs - g0 * nb) / den_c, ba / den_c
    num = (big_r * big_q).sum((1, 2))[:, None] + (lam * p * q).sum(1, keepdim=True) + lam * g0
    den = (big_q * big_q).sum((1, 2))[:, None] + (lam * q * q).sum(1, keepdim=True) + lam
    g_s = (num / den).clamp_min(0.0)
    return g_s, ((bs - g_s * ba + lam * g0) / den_c).clamp_min(0.0)


@pytest.mark.parametrize("case", ["random", "no_specular", "dark", "huge"])
def test_fit_gains_equals_the_reduction_formulation(case):
    ms, md, kd, s_in = _random_blocks(seed=3)
    stokes = torch.randn(2, 3, 3, 5, 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    if case == "no_specular":
        ms = torch.zeros_like(ms)
    elif case == "dark":
        stokes = torch.zeros_like(stokes)
    elif case == "huge":
        ms, stokes = ms * 1e6, stokes * 1e6
    for got, ref in zip(fit_gains(stokes, ms, md, kd, s_in), _fit_gains_reference(stokes, ms, md, kd, s_in)):
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-12)


def test_the_rendering_parts_give_the_gain_fitted_images_rendering():
    """PMMNet renders the gain-fitted initialization as g_s a + g_c b (its fit's own parts)
    instead of applying the 9 C-plane Mueller image to s_in: the same numbers."""
    ms, md, kd, s_in = _random_blocks(seed=5)
    stokes = torch.randn(2, 3, 3, 5, 6, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    _, _, m_init = gain_fitted_initialization(stokes, ms, md, kd, s_in)
    a, b = renderings(ms, md, kd, s_in)
    g_s, g_c = fit_gains_to(stokes, a, b)
    torch.testing.assert_close(g_s[:, None] * a[:, None] + g_c[:, :, None] * b, apply_mueller(m_init, s_in),
                               rtol=1e-12, atol=1e-12)


def test_compose_is_the_masked_mueller_image_for_any_mask():
    ms, md, kd, _ = _random_blocks(seed=7)
    mask = torch.rand(2, 1, 5, 6, generator=torch.Generator().manual_seed(8), dtype=torch.float64)
    mask[:, :, 0] = 0.0
    mask[:, :, 1] = 1.0
    expected = (ms[:, None] + kd[:, :, None, None] * md[:, None]) * mask[:, :, None, None]
    torch.testing.assert_close(compose(ms, md, kd, mask), expected, rtol=1e-14, atol=1e-15)


def test_a_selection_of_the_single_shot_outputs_is_its_forward_on_the_full_outputs():
    """``SelectedOutputs.select`` of the full single-shot function's outputs is what the
    selection's own forward returns, output for output and bit for bit: the export check
    (:func:`polrig.models.export.export_all`) runs the full function once and compares each
    smaller graph with its selection."""
    from polrig.models.pipnet import PIPNet
    from polrig.models.pmmnet import FRAME_OUTPUTS, PROBE_OUTPUTS, SelectedOutputs, SingleShotNet

    torch.manual_seed(0)
    single = SingleShotNet(PIPNet(3, 4, True), PMMNet(3, 4, 2)).eval()
    b, h, w = 2, 16, 16
    wo = torch.nn.functional.normalize(torch.randn(b, 3, h, w) + torch.tensor([0.0, 0.0, 3.0])[:, None, None], dim=1)
    args = (torch.rand(b, 3, 4, h, w), (torch.rand(b, 1, h, w) > 0.2).float(),
            torch.tensor([[1.0, 0.3, -0.2], [1.0, -0.5, 0.1]]), wo, torch.tensor([[0.0, -1.0, 0.0]] * 2))
    with torch.no_grad():
        full = single(*args)
        for outputs in (FRAME_OUTPUTS, PROBE_OUTPUTS):
            sel = SelectedOutputs(single, outputs).eval()
            own, picked = sel(*args), sel.select(full)
            own, picked = (own, picked) if len(outputs) > 1 else ((own,), (picked,))
            assert len(own) == len(picked) == len(outputs)
            for a, p in zip(own, picked):
                assert torch.equal(a, p)
