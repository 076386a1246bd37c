"""PMMNet (stage 2), the single-shot composite graph and the direct Stokes->MM baseline.

PMMNet refines the analytic initialization ``M = ks Ms + kd_c Md`` (``polrig.models.pbrdf_torch``
evaluated on PIPNet's outputs, eta = 1.5, ks = 1) by residual learning under

* polarization-colour decoupling: one wavelength-independent 3x3 block per component
  (specular ``Ms``, diffuse ``Md`` with unit albedo); colour enters only through ``kd``;
* redundant-channel separation: the specular branch (high-frequency attention) predicts
  residuals of ``{m00, m11, m12, m21, m22}``, the diffuse branch (multi-head channel
  attention) residuals of ``{m00, m01, m02, m10, m20}``; each 5-vector is expanded back to
  3x3 (other elements keep the initialization), weighted by ``ks`` and ``kd`` per colour and
  summed into the ``(B, C, 3, 3, H, W)`` Mueller image.

Additions to the paper, needed on the simulator's data and stated in ``models/MODEL_CARD.md``:
the unknown radiometric scales (light fall-off and colour, exposure, the true ``ks``) are
first fitted per pixel to the measured state in closed form (:func:`fit_gains`: one specular
gain, one diffuse gain per colour); the specular branch then also predicts a per-pixel log
gain on ``ks`` and the diffuse branch a per-colour log gain on ``kd``. Final layers start at
zero, so an untrained PMMNet returns exactly the gain-fitted PIPNet-pBRDF initialization.

Loss: ``L1(M) + L_Stokes`` with ``L_Stokes`` the L1 error of ``M S`` over the probe states
``[1,0,0], [1,1,0], [1,0,1]`` for every colour, averaged over the mask.
"""

from __future__ import annotations

import torch
from torch import nn

from polrig.models.layers import (
    HighFrequencyAttention,
    MultiHeadChannelAttention,
    UNetBackbone,
    apply_mueller,
    masked_mean,
    planes,
    signed_log,
    stokes_from_analyzer,
    sum_over,
)
from polrig.models.pbrdf_torch import image_blocks
from polrig.models.pipnet import PIPNet, pipnet_features

#: Element positions (row, col) refined by each branch.
SPECULAR_ELEMENTS = ((0, 0), (1, 1), (1, 2), (2, 1), (2, 2))
DIFFUSE_ELEMENTS = ((0, 0), (0, 1), (0, 2), (1, 0), (2, 0))
#: Probe incident states of the Stokes consistency loss.
PROBE_STATES = ((1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (1.0, 0.0, 1.0))


def _sum2(x: torch.Tensor) -> torch.Tensor:
    """Sum of ``(B, C, 3, H, W)`` over colours and Stokes components -> ``(B, 1, H, W)``."""
    return sum_over(sum_over(x, 2)[:, :, 0], 1)


def renderings(ms: torch.Tensor, md: torch.Tensor, kd: torch.Tensor,
               s_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The two parts of the initialization's rendering of ``s_in``: ``a = Ms s_in`` (B,3,H,W)
    and ``b_c = kd_c Md s_in`` (B,C,3,H,W), for blocks ``(B, 3, 3, H, W)``, ``kd`` (B,C,H,W)
    and states ``(B, 3)``."""
    s = s_in[:, None, :, None, None]
    a = sum_over(ms * s, 2)[:, :, 0]
    b = kd[:, :, None] * sum_over(md * s, 2)[:, None, :, 0]
    return a, b


def fit_gains_to(stokes: torch.Tensor, a: torch.Tensor, b: torch.Tensor, ridge: float = 0.05,
                 eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`fit_gains` from the rendering parts ``a`` (B,3,H,W) and ``b`` (B,C,3,H,W) of
    :func:`renderings` -> ``g_s`` (B,1,H,W), ``g_c`` (B,C,H,W)."""
    r = a[:, None] + b  # rendering of the initialization
    g0 = (_sum2(stokes * r) / (_sum2(r * r) + eps)).clamp_min(0.0)  # (B,1,H,W)
    nb = sum_over(b * b, 2)[:, :, 0]  # (B,C,H,W)
    lam = ridge * (sum_over(a * a, 1) + sum_over(nb, 1)) / 4.0 + eps
    den_c = nb + lam
    bs = sum_over(b * stokes, 2)[:, :, 0]
    ba = sum_over(b * a[:, None], 2)[:, :, 0]
    big_r = stokes - b * ((bs + lam * g0) / den_c)[:, :, None]
    big_q = a[:, None] - b * (ba / den_c)[:, :, None]
    p = (bs - g0 * nb) / den_c
    q = ba / den_c
    num = _sum2(big_r * big_q) + sum_over(lam * p * q, 1) + lam * g0
    den = _sum2(big_q * big_q) + sum_over(lam * q * q, 1) + lam
    g_s = (num / den).clamp_min(0.0)
    g_c = ((bs - g_s * ba + lam * g0) / den_c).clamp_min(0.0)
    return g_s, g_c


def fit_gains(stokes: torch.Tensor, ms: torch.Tensor, md: torch.Tensor, kd: torch.Tensor,
              s_in: torch.Tensor, ridge: float = 0.05, eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel radiometric gains of the pBRDF fitted to the one measured state.

    The measured emergent Stokes ``S_c`` (``(B, C, 3, H, W)``) under ``s_in`` should be
    ``g_s a + g_c b_c`` with ``a = Ms s_in`` (specular, colour independent) and
    ``b_c = kd_c Md s_in`` (:func:`renderings`): the light's fall-off and colour, the exposure
    and the true ``ks`` are unknown scale factors that PIPNet cannot see. Solved per pixel in
    closed form (variable projection of the 4-unknown linear least squares over the ``3 C``
    Stokes values) with a ridge ``ridge * (|a|^2 + sum |b_c|^2) / 4`` towards the common gain
    ``g0`` (the least-squares scale of the whole initialization), which keeps ill-separated
    pixels (specular and diffuse light polarized alike, or no specular at all) at ``g0``.
    Returns ``g_s`` (B,1,H,W) and ``g_c`` (B,C,H,W), both >= 0.
    """
    return fit_gains_to(stokes, *renderings(ms, md, kd, s_in), ridge, eps)


def gain_fitted_rendering(stokes: torch.Tensor, ms: torch.Tensor, md: torch.Tensor, kd: torch.Tensor,
                          s_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The :func:`fit_gains` gains applied: the scaled specular block ``g_s Ms`` (B,3,3,H,W), the
    scaled albedo ``g_c kd`` (B,C,H,W) and the gain-fitted initialization's rendering of
    ``s_in``, ``g_s a + g_c b_c`` (B,C,3,H,W) (:func:`renderings`; the Mueller image of
    :func:`gain_fitted_initialization` times ``s_in``, without forming its 9 C planes)."""
    a, b = renderings(ms, md, kd, s_in)
    g_s, g_c = fit_gains_to(stokes, a, b)
    return ms * g_s[:, :, None], kd * g_c, g_s[:, None] * a[:, None] + g_c[:, :, None] * b


def gain_fitted_initialization(stokes: torch.Tensor, ms: torch.Tensor, md: torch.Tensor, kd: torch.Tensor,
                               s_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The analytic initialization with the :func:`fit_gains` gains applied: the scaled specular
    block ``g_s Ms`` (B,3,3,H,W), the scaled albedo ``g_c kd`` (B,C,H,W) and the Mueller image
    ``g_s Ms + g_c kd Md`` (B,C,3,3,H,W) (unmasked)."""
    ms, kd, _ = gain_fitted_rendering(stokes, ms, md, kd, s_in)
    return ms, kd, ms[:, None] + kd[:, :, None, None] * md[:, None]


def expand5(values: torch.Tensor, elements: tuple[tuple[int, int], ...]) -> torch.Tensor:
    """Place 5 channels ``(B, 5, H, W)`` at ``elements`` of a zero 3x3 -> ``(B, 3, 3, H, W)``."""
    zero = torch.zeros_like(values[:, :1])
    channels = torch.split(values, 1, 1)
    index = {e: i for i, e in enumerate(elements)}
    planes9 = [channels[index[(r, c)]] if (r, c) in index else zero for r in range(3) for c in range(3)]
    return torch.cat(planes9, 1).unflatten(1, (3, 3))


def compose(ms: torch.Tensor, md: torch.Tensor, kd: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """The masked Mueller image ``(Ms + kd_c Md) mask`` (B,C,3,3,H,W) of blocks (B,3,3,H,W),
    albedos ``kd`` (B,C,H,W) and the mask (B,1,H,W), computed as ``Ms mask + (kd_c mask) Md``
    (the mask applied to the 9-plane block and the C albedo planes, not to the 9 C result)."""
    return (ms * mask[:, :, None])[:, None] + (kd * mask)[:, :, None, None] * md[:, None]


def _zero_conv(cin: int, cout: int) -> nn.Conv2d:
    conv = nn.Conv2d(cin, cout, 1)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)
    return conv


class PMMNet(nn.Module):
    """Residual refinement. ``forward(analyzer, mask, s_in, ms_init, md_init, kd_init)``
    -> dict with ``mueller`` (B,C,3,3,H,W), ``ms``, ``md`` (B,3,3,H,W), ``kd`` (B,C,H,W)."""

    def __init__(self, colours: int = 3, width: int = 16, heads: int = 4):
        super().__init__()
        self.colours = colours
        # measured Stokes (3C), measured minus rendered-by-the-init Stokes (3C),
        # Ms (9), Md (9), kd (C), mask (1), s_in planes (3)
        self.backbone = UNetBackbone(7 * colours + 22, width)
        self.spec_att = HighFrequencyAttention(width)
        self.spec_head = nn.Sequential(nn.Conv2d(width, width, 1), nn.ReLU(inplace=True),
                                       _zero_conv(width, 6))
        self.diff_att = MultiHeadChannelAttention(width, heads)
        self.diff_head = nn.Sequential(nn.Conv2d(width, width, 1), nn.ReLU(inplace=True),
                                       _zero_conv(width, 5 + colours))

    def forward(self, analyzer: torch.Tensor, mask: torch.Tensor, s_in: torch.Tensor,
                ms_init: torch.Tensor, md_init: torch.Tensor, kd_init: torch.Tensor) -> dict[str, torch.Tensor]:
        stokes = stokes_from_analyzer(analyzer)
        # Radiometric fit of the analytic initialization to the measured state (fit_gains)
        ms_init, kd_init, rendered = gain_fitted_rendering(stokes, ms_init, md_init, kd_init, s_in)
        x = torch.cat([stokes.flatten(1, 2), (stokes - rendered).flatten(1, 2),
                       signed_log(ms_init.flatten(1, 2)), signed_log(md_init.flatten(1, 2)),
                       kd_init, mask, planes(s_in, mask)], 1)
        feat, _ = self.backbone(x)
        spec = self.spec_head(self.spec_att(feat))
        diff = self.diff_head(self.diff_att(feat))
        ks = torch.exp(spec[:, 5:6].clamp(-6.0, 6.0))[:, :, None]  # (B,1,1,H,W)
        ms = ks * ms_init + expand5(spec[:, :5], SPECULAR_ELEMENTS)
        md = md_init + expand5(diff[:, :5], DIFFUSE_ELEMENTS)
        kd = kd_init * torch.exp(diff[:, 5:].clamp(-6.0, 6.0))
        return {"mueller": compose(ms, md, kd, mask), "ms": ms, "md": md, "kd": kd}


class SingleShotNet(nn.Module):
    """PIPNet -> differentiable pBRDF -> PMMNet as one graph (what ships as ONNX).

    Inputs: ``analyzer`` (B,C,4,H,W) normalised, ``mask`` (B,1,H,W) float {0,1}, ``s_in``
    (B,3) normalised incident Stokes, ``wo`` (B,3,H,W) unit view directions, ``stage_zero_axis``
    (B,3) in the camera frame. Outputs: ``mueller`` (B,C,3,3,H,W), ``mueller_init`` (the
    PIPNet-pBRDF matrix), ``normal``, ``kd``, ``wi``, ``alpha``.
    """

    def __init__(self, pipnet: PIPNet, pmmnet: PMMNet):
        super().__init__()
        self.pipnet, self.pmmnet = pipnet, pmmnet

    def initialization(self, analyzer, mask, s_in, wo, stage_zero_axis):
        p = self.pipnet(analyzer, mask, s_in, wo)
        ms, md = image_blocks(p["normal"], p["wi"], wo, p["alpha"], stage_zero_axis, mask=mask)
        return p, ms, md

    def forward(self, analyzer, mask, s_in, wo, stage_zero_axis):
        p, ms, md = self.initialization(analyzer, mask, s_in, wo, stage_zero_axis)
        m_init = compose(ms, md, p["kd"], mask)
        r = self.pmmnet(analyzer, mask, s_in, ms, md, p["kd"])
        return r["mueller"], m_init, p["normal"], p["kd"], p["wi"], p["alpha"]


SINGLE_SHOT_OUTPUTS = ("mueller", "mueller_init", "normal", "kd", "wi", "alpha")
#: Outputs the frame path reads (:mod:`polrig.models.runtime`: the Mueller image, the light
#: directions that rotate it into the rig's frame, the roughness the result records).
FRAME_OUTPUTS = ("mueller", "wi", "alpha")
#: Outputs the light-direction probe reads (its mean ``wi``): PIPNet alone.
PROBE_OUTPUTS = ("wi",)


class SelectedOutputs(nn.Module):
    """``net``'s outputs named ``outputs`` (of :data:`SINGLE_SHOT_OUTPUTS`), in that order: the
    same function with fewer outputs, so an exported graph holds only the nodes they need."""

    def __init__(self, net: nn.Module, outputs: tuple[str, ...]):
        super().__init__()
        self.net = net
        self.index = [SINGLE_SHOT_OUTPUTS.index(k) for k in outputs]

    def forward(self, analyzer, mask, s_in, wo, stage_zero_axis):
        return self.select(self.net(analyzer, mask, s_in, wo, stage_zero_axis))

    def select(self, out: tuple[torch.Tensor, ...]) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """What :meth:`forward` returns, from ``out``: the wrapped network's outputs on the same
        inputs (so one run of it serves every selection)."""
        picked = tuple(out[i] for i in self.index)
        return picked if len(picked) > 1 else picked[0]


class DirectStokesToMM(nn.Module):
    """Ablation baseline: the same U-Net backbone regresses the 27 Mueller elements directly
    from the analyzer images, their Stokes, the mask, ``s_in`` planes and ``wo`` (no physics)."""

    def __init__(self, colours: int = 3, width: int = 16):
        super().__init__()
        self.colours = colours
        self.backbone = UNetBackbone(9 * colours + 7, width)
        self.head = nn.Sequential(nn.Conv2d(width, width, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(width, 9 * colours, 1))

    def forward(self, analyzer, mask, s_in, wo, stage_zero_axis=None):
        stokes = stokes_from_analyzer(analyzer)
        x = torch.cat([pipnet_features(analyzer, mask, s_in, wo, stokes), stokes.flatten(1, 2)], 1)
        feat, _ = self.backbone(x)
        b, _, h, w = feat.shape
        return self.head(feat).reshape(b, self.colours, 3, 3, h, w) * mask[:, :, None, None]


def mueller_loss(pred: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """``L1(M) + L_Stokes`` over the mask for Mueller images ``(B, C, 3, 3, H, W)``."""
    b, c, _, _, h, w = pred.shape
    l1 = masked_mean((pred - truth).abs().reshape(b, -1, h, w), mask)
    probes = torch.tensor(PROBE_STATES, dtype=pred.dtype, device=pred.device)
    diff = pred - truth
    ls = pred.new_zeros(())
    for s in probes:
        ls = ls + masked_mean(apply_mueller(diff, s.expand(b, 3)).abs().reshape(b, -1, h, w), mask)
    ls = ls * (3.0 / len(probes))  # sum over the 3 Stokes components, mean over probes
    return l1 + ls, {"l1_m": float(l1.detach()), "l_stokes": float(ls.detach())}
