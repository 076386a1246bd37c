"""PIPNet: polarization initialization parameter network (stage 1 of the ECCV 2026 method).

From one set of analyzer images (``(B, C, 4, H, W)``, normalised, ``docs/conventions.md``),
the mask, the known incident state ``s_in`` (``(B, 3)``, fed as constant planes because it
varies across the dataset) and the viewing directions ``wo`` (``(B, 3, H, W)``, from the
camera model), a shared U-Net backbone feeds three pixel-wise heads: unit normal ``n``
(camera frame), RGB diffuse albedo ``kd`` and unit light direction ``wi``; an image-wide GGX
roughness ``alpha`` comes from masked average pooling of the bottleneck and a small fully
connected branch. Loss: ``cos(n) + 0.5 L1(kd) + 0.5 L1(wi) + 0.3 L1(alpha)`` over the mask.

Shape-from-polarization prior (an addition to the paper, ``sfp_prior=True``; ``models/MODEL_CARD.md``):
diffuse reflection leaves the surface polarized in the plane of emission (the plane of ``n``
and ``wo``) with a degree of polarization that depends only on the zenith angle between them
and the index of refraction (Atkinson & Hancock, IEEE TIP 15(6) 2006, eq. 13 and Fig. 3). So
every pixel's measured AoLP and DoLP give, in closed form, two candidate normals
``n+-  = cos(theta) wo +- sin(theta) e`` (``e`` the unit polarization direction in the emergent
frame, ``theta`` the zenith from the inverted diffuse DoLP at eta = 1.5): :func:`sfp_candidates`.
They are local (no shape prior), so they hold on shapes never seen in training; what they miss
is which of the two is right and where specular reflection or noise dominates the
polarization. PIPNet receives both as input planes; its normal head predicts a free normal
``n_f`` and a per-pixel trust ``c`` in (0, 1), the candidate nearer to ``n_f`` is taken
(``n_f`` only has to get the side right, which a shape prior does even where its own normal is
poor) and ``n = normalize(c n_sfp + (1 - c) n_f)``. "Nearer" is a steep sigmoid of the
difference of the two dot products (:data:`SELECT_SHARPNESS`) rather than a hard switch, so the
output is continuous where ``n_f`` is equidistant from both (a hard switch there flips with
rounding: PyTorch and onnxruntime disagreed by 0.3 on such pixels).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from polrig.models.layers import (
    SIZE_MULTIPLE,
    UNetBackbone,
    masked_mean,
    normalised_stokes,
    normalize_channels,
    planes,
    softplus,
    stokes_from_analyzer,
    sum_over,
)
from polrig.models.pbrdf_torch import cross

#: Roughness range the head can output (GGX alpha).
ALPHA_MIN, ALPHA_MAX = 0.01, 1.0
#: Index of refraction of the shape-from-polarization prior (the pBRDF initialization's eta).
SFP_ETA = 1.5
#: Slope of the soft choice between the two candidates in their dot-product difference with
#: the free normal (differences range over [-2, 2]; at 0.1 the nearer one weighs 0.95).
SELECT_SHARPNESS = 30.0


def diffuse_dolp(zenith: torch.Tensor, eta: float = SFP_ETA) -> torch.Tensor:
    """Degree of linear polarization of diffuse reflection at emission zenith ``zenith``
    (rad) for index ``eta`` (Atkinson & Hancock 2006, eq. 13)."""
    s2 = torch.sin(zenith) ** 2
    c = torch.cos(zenith)
    return ((eta - 1.0 / eta) ** 2 * s2
            / (2.0 + 2.0 * eta * eta - (eta + 1.0 / eta) ** 2 * s2 + 4.0 * c * torch.sqrt(eta * eta - s2)))


def diffuse_zenith(dolp: torch.Tensor, eta: float = SFP_ETA) -> torch.Tensor:
    """Inverse of :func:`diffuse_dolp` in closed form: zenith (rad) in [0, pi/2). The
    expression is the one W. Smith's code for Smith, Ramamoorthi & Tozza, "Linear depth
    estimation from an uncalibrated, monocular polarisation image", ECCV 2016 uses
    (``utils/rho_diffuse.m`` of github.com/waps101/depth-from-polarisation), rearranged;
    ``tests/test_models_pipnet.py`` checks it inverts :func:`diffuse_dolp`. DoLP values above
    the model's maximum (grazing emission) are clamped to it. The networks use
    :func:`diffuse_zenith_cos_sin` (no ``acos``)."""
    return torch.acos(torch.sqrt(diffuse_zenith_cos2(dolp, eta)))


def diffuse_zenith_cos2(dolp: torch.Tensor, eta: float = SFP_ETA) -> torch.Tensor:
    """``q = cos^2`` of :func:`diffuse_zenith` in [0, 1], the closed form before its ``acos``."""
    r_max = float(diffuse_dolp(torch.tensor(0.5 * torch.pi - 1e-4, dtype=torch.float64), eta))
    r = dolp.clamp(0.0, r_max)
    e2, e3, e4 = eta * eta, eta ** 3, eta ** 4
    num = (e4 * (1.0 - r * r) + 2.0 * e2 * (2.0 * r * r + r - 1.0) + r * r + 2.0 * r
           - 4.0 * e3 * r * torch.sqrt((1.0 - r * r).clamp_min(0.0)) + 1.0)
    den = (r + 1.0) ** 2 * (e4 + 1.0) + 2.0 * e2 * (3.0 * r * r + 2.0 * r - 1.0)
    return (num / den).clamp(0.0, 1.0)


def diffuse_zenith_cos_sin(dolp: torch.Tensor, eta: float = SFP_ETA) -> tuple[torch.Tensor, torch.Tensor]:
    """``(cos, sin)`` of :func:`diffuse_zenith` without the angle: with ``q`` from
    :func:`diffuse_zenith_cos2`, ``cos(acos sqrt q) = sqrt q`` and ``sin(acos sqrt q) = sqrt(1 - q)``
    exactly on [0, 1] (the zenith lies in [0, pi/2], where the sine is not negative). The
    exported graph then has no ``Acos`` (onnxruntime's CUDA provider has no kernel for it: it
    ran on the host between two copies and kept the graph out of CUDA graphs, issue 31).

    Gradient: ``q`` is computed from the measured Stokes images only (no parameter is upstream
    of it), so training never differentiates through these square roots; where an input does
    require a gradient, the clamps keep the argument in [0, 1] and ``sqrt``'s infinite slope at
    0 (``q = 0`` or ``q = 1``, an unpolarized pixel) is where ``acos``'s was too."""
    q = diffuse_zenith_cos2(dolp, eta)
    return torch.sqrt(q), torch.sqrt((1.0 - q).clamp_min(0.0))


def sfp_candidates(stokes: torch.Tensor, wo: torch.Tensor, eta: float = SFP_ETA,
                   eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """The two diffuse shape-from-polarization normals ``(B, 3, H, W)`` (camera frame) of
    measured Stokes images ``(B, C, 3, H, W)`` (averaged over colours) seen along ``wo``.

    Emergent frame (``docs/conventions.md``): ``k = wo``, ``x`` = camera ``X`` made
    perpendicular to ``k``, ``y = k x x``; the AoLP ``phi`` runs from ``x`` towards ``y``, so the
    polarization direction is ``e = cos(phi) x + sin(phi) y``, computed without angles from
    ``(cos 2phi, sin 2phi) = (S1, S2) / |S1, S2|`` as ``(1 + cos 2phi, sin 2phi)`` or
    ``(sin 2phi, 1 - cos 2phi)`` (both parallel to ``e``, the better conditioned one is used;
    the sign does not matter since both candidates are returned)."""
    s = sum_over(stokes, 1)[:, 0] / stokes.shape[1]  # the mean over colours (B, 3, H, W)
    s0, s1, s2 = s[:, 0:1], s[:, 1:2], s[:, 2:3]
    cos_zen, sin_zen = diffuse_zenith_cos_sin(torch.sqrt(s1 * s1 + s2 * s2) / s0.clamp_min(eps), eta)
    lin = torch.sqrt(s1 * s1 + s2 * s2 + eps * eps)
    c2, sn2 = s1 / lin, s2 / lin
    # the choice as a blend with a {0, 1} weight: picks the finite value exactly, and runs
    # faster in onnxruntime than Where on images
    first = (c2 >= 0).to(c2.dtype)
    ex = first * (1.0 + c2) + (1.0 - first) * sn2
    ey = first * sn2 + (1.0 - first) * (1.0 - c2)
    k = normalize_channels(wo, eps)
    cam_x = torch.cat([torch.ones_like(k[:, :1]), torch.zeros_like(k[:, 1:])], 1)
    x = normalize_channels(cam_x - k[:, :1] * k, eps)
    y = cross(k, x)
    e = normalize_channels(ex * x + ey * y, eps)
    along, across = cos_zen * k, sin_zen * e
    return along + across, along - across


def pipnet_features(analyzer: torch.Tensor, mask: torch.Tensor, s_in: torch.Tensor,
                    wo: torch.Tensor, stokes: torch.Tensor | None = None) -> torch.Tensor:
    """Input planes: analyzer (4C), S1/S0 and S2/S0 (2C), mask, s_in planes (3), wo (3).
    ``stokes``: the analyzer images' Stokes (:func:`stokes_from_analyzer`) if the caller has them."""
    if stokes is None:
        stokes = stokes_from_analyzer(analyzer)
    return torch.cat([analyzer.flatten(1, 2), normalised_stokes(stokes), mask,
                      planes(s_in, mask), wo], 1)


class PIPNet(nn.Module):
    def __init__(self, colours: int = 3, width: int = 16, sfp_prior: bool = False):
        super().__init__()
        self.colours = colours
        self.sfp_prior = sfp_prior
        self.backbone = UNetBackbone(6 * colours + 7 + (6 if sfp_prior else 0), width)
        self.normal_head = nn.Conv2d(width, 4 if sfp_prior else 3, 1)
        self.kd_head = nn.Conv2d(width, colours, 1)
        self.wi_head = nn.Conv2d(width, 3, 1)
        self.alpha_head = nn.Sequential(nn.Linear(4 * width, 32), nn.ReLU(inplace=True), nn.Linear(32, 1))

    def forward(self, analyzer: torch.Tensor, mask: torch.Tensor, s_in: torch.Tensor,
                wo: torch.Tensor) -> dict[str, torch.Tensor]:
        """-> ``normal`` (B,3,H,W), ``kd`` (B,C,H,W), ``wi`` (B,3,H,W), ``alpha`` (B,)."""
        stokes = stokes_from_analyzer(analyzer)
        x = pipnet_features(analyzer, mask, s_in, wo, stokes)
        if self.sfp_prior:
            n_plus, n_minus = sfp_candidates(stokes, wo)
            x = torch.cat([x, n_plus, n_minus], 1)
        feat, bottleneck = self.backbone(x)
        # Bias the normal towards the viewer and the light towards the upper hemisphere so an
        # untrained head starts from a plausible geometry.
        head = self.normal_head(feat)
        normal = normalize_channels(head[:, :3] + wo, 1e-6)
        sfp = {}
        if self.sfp_prior:
            pick_logit = SELECT_SHARPNESS * ((n_plus - n_minus) * normal).sum(1, keepdim=True)
            pick = torch.sigmoid(pick_logit)
            n_sfp = pick * n_plus + (1.0 - pick) * n_minus
            trust = torch.sigmoid(head[:, 3:4])
            normal = normalize_channels(trust * n_sfp + (1.0 - trust) * normal, 1e-6)
            sfp = {"sfp_plus": n_plus, "sfp_minus": n_minus, "pick_logit": pick_logit,
                   "trust_logit": head[:, 3:4]}
        wi = normalize_channels(self.wi_head(feat) + wo, 1e-6)
        kd = softplus(self.kd_head(feat))
        small_mask = F.avg_pool2d(mask, SIZE_MULTIPLE, SIZE_MULTIPLE)
        pooled = (bottleneck * small_mask).sum((2, 3)) / small_mask.sum((2, 3)).clamp_min(1e-6)
        alpha = ALPHA_MIN + (ALPHA_MAX - ALPHA_MIN) * torch.sigmoid(self.alpha_head(pooled)[:, 0])
        return {"normal": normal, "kd": kd, "wi": wi, "alpha": alpha, **sfp}


#: A pixel's nearer SfP candidate counts as reliable (trust target 1) within this angle of the
#: true normal (deg), and the pick is supervised where the candidates' dot products with the
#: true normal differ by more than PICK_MARGIN.
TRUST_TARGET_DEG = 10.0
PICK_MARGIN = 0.05


def sfp_supervision_loss(pred: dict[str, torch.Tensor], normal: torch.Tensor,
                         mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Direct supervision of the SfP prior's two decisions (an addition to the paper's loss):
    binary cross-entropies of the pick (target: the candidate nearer the true normal, where
    the two differ by more than :data:`PICK_MARGIN` in dot product) and of the trust (target:
    the nearer candidate is within :data:`TRUST_TARGET_DEG` of the true normal, i.e. the
    pixel's polarization is diffuse-like and well measured). The cosine loss alone only
    teaches the trust where the candidate beats the free normal, which on the training shapes
    it rarely does; this teaches it where the local physics holds, in the hope that such local
    decisions transfer to shapes never seen. Measured (``models/MODEL_CARD.md``, "How good must
    the geometry be"): they did not; the pick learned on convex objects got worse on terrain.
    Returns ``(pick loss, trust loss)`` averaged over their pixels."""
    da = (pred["sfp_plus"] * normal).sum(1, keepdim=True)
    db = (pred["sfp_minus"] * normal).sum(1, keepdim=True)
    pick_w = mask * ((da - db).abs() > PICK_MARGIN)
    l_pick = (F.binary_cross_entropy_with_logits(pred["pick_logit"], (da > db).to(da.dtype), reduction="none")
              * pick_w).sum() / pick_w.sum().clamp_min(1.0)
    reliable = (torch.maximum(da, db) > torch.cos(torch.deg2rad(torch.tensor(TRUST_TARGET_DEG)))).to(da.dtype)
    l_trust = masked_mean(F.binary_cross_entropy_with_logits(pred["trust_logit"], reliable, reduction="none"), mask)
    return l_pick, l_trust


def pipnet_loss(pred: dict[str, torch.Tensor], normal: torch.Tensor, kd: torch.Tensor,
                wi: torch.Tensor, alpha: torch.Tensor, mask: torch.Tensor,
                sfp_weight: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """The paper's loss ``cos(n) + 0.5 L1(kd) + 0.5 L1(wi) + 0.3 L1(alpha)`` over the mask,
    plus ``sfp_weight`` times the two :func:`sfp_supervision_loss` terms (with the prior)."""
    cos = masked_mean(1.0 - (pred["normal"] * normal).sum(1, keepdim=True), mask)
    l_kd = masked_mean((pred["kd"] - kd).abs(), mask)
    l_wi = masked_mean((pred["wi"] - wi).abs(), mask)
    l_alpha = (pred["alpha"] - alpha).abs().mean()
    total = cos + 0.5 * l_kd + 0.5 * l_wi + 0.3 * l_alpha
    terms = [("cos_n", cos), ("l1_kd", l_kd), ("l1_wi", l_wi), ("l1_alpha", l_alpha)]
    if sfp_weight > 0 and "pick_logit" in pred:
        l_pick, l_trust = sfp_supervision_loss(pred, normal, mask)
        total = total + sfp_weight * (l_pick + l_trust)
        terms += [("bce_pick", l_pick), ("bce_trust", l_trust)]
    return total, {k: float(v.detach()) for k, v in terms}
