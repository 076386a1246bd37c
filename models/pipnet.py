"""PIPNet: polarization initialization parameter network (stage 1 of the ECCV 2026 method).

From one set of analyzer images (``(B, C, 4, H, W)``, normalised, ``docs/conventions.md``),
the mask, the known incident state ``s_in`` (``(B, 3)``, fed as constant planes because it
varies across the dataset) and the viewing directions ``wo`` (``(B, 3, H, W)``, from the
camera model), a shared U-Net backbone feeds three pixel-wise heads: unit normal ``n``
(camera frame), RGB diffuse albedo ``kd`` and unit light direction ``wi``; an image-wide GGX
roughness ``alpha`` comes from masked average pooling of the bottleneck and a small fully
connected branch. Loss: ``cos(n) + 0.5 L1(kd) + 0.5 L1(wi) + 0.3 L1(alpha)`` over the mask.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from models.layers import SIZE_MULTIPLE, UNetBackbone, masked_mean, normalised_stokes, planes, stokes_from_analyzer

#: Roughness range the head can output (GGX alpha).
ALPHA_MIN, ALPHA_MAX = 0.01, 1.0


def pipnet_features(analyzer: torch.Tensor, mask: torch.Tensor, s_in: torch.Tensor,
                    wo: torch.Tensor) -> torch.Tensor:
    """Input planes: analyzer (4C), S1/S0 and S2/S0 (2C), mask, s_in planes (3), wo (3)."""
    stokes = stokes_from_analyzer(analyzer)
    return torch.cat([analyzer.flatten(1, 2), normalised_stokes(stokes), mask,
                      planes(s_in, mask), wo], 1)


class PIPNet(nn.Module):
    def __init__(self, colours: int = 3, width: int = 16):
        super().__init__()
        self.colours = colours
        self.backbone = UNetBackbone(6 * colours + 7, width)
        self.normal_head = nn.Conv2d(width, 3, 1)
        self.kd_head = nn.Conv2d(width, colours, 1)
        self.wi_head = nn.Conv2d(width, 3, 1)
        self.alpha_head = nn.Sequential(nn.Linear(4 * width, 32), nn.ReLU(inplace=True), nn.Linear(32, 1))

    def forward(self, analyzer: torch.Tensor, mask: torch.Tensor, s_in: torch.Tensor,
                wo: torch.Tensor) -> dict[str, torch.Tensor]:
        """-> ``normal`` (B,3,H,W), ``kd`` (B,C,H,W), ``wi`` (B,3,H,W), ``alpha`` (B,)."""
        feat, bottleneck = self.backbone(pipnet_features(analyzer, mask, s_in, wo))
        # Bias the normal towards the viewer and the light towards the upper hemisphere so an
        # untrained head starts from a plausible geometry.
        normal = F.normalize(self.normal_head(feat) + wo, dim=1, eps=1e-6)
        wi = F.normalize(self.wi_head(feat) + wo, dim=1, eps=1e-6)
        kd = F.softplus(self.kd_head(feat))
        small_mask = F.avg_pool2d(mask, SIZE_MULTIPLE, SIZE_MULTIPLE)
        pooled = (bottleneck * small_mask).sum((2, 3)) / small_mask.sum((2, 3)).clamp_min(1e-6)
        alpha = ALPHA_MIN + (ALPHA_MAX - ALPHA_MIN) * torch.sigmoid(self.alpha_head(pooled)[:, 0])
        return {"normal": normal, "kd": kd, "wi": wi, "alpha": alpha}


def pipnet_loss(pred: dict[str, torch.Tensor], normal: torch.Tensor, kd: torch.Tensor,
                wi: torch.Tensor, alpha: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """The paper's loss ``cos(n) + 0.5 L1(kd) + 0.5 L1(wi) + 0.3 L1(alpha)`` over the mask."""
    cos = masked_mean(1.0 - (pred["normal"] * normal).sum(1, keepdim=True), mask)
    l_kd = masked_mean((pred["kd"] - kd).abs(), mask)
    l_wi = masked_mean((pred["wi"] - wi).abs(), mask)
    l_alpha = (pred["alpha"] - alpha).abs().mean()
    total = cos + 0.5 * l_kd + 0.5 * l_wi + 0.3 * l_alpha
    return total, {k: float(v.detach()) for k, v in
                   (("cos_n", cos), ("l1_kd", l_kd), ("l1_wi", l_wi), ("l1_alpha", l_alpha))}
