"""Building blocks shared by PIPNet, PMMNet and the direct baseline (PyTorch, ``train`` extra).

All tensors are NCHW. The backbone is a small U-Net (Ronneberger et al., MICCAI 2015) sized
for a CPU: its convolutions run at 1/2, 1/4 and 1/8 of the input resolution and the
full-resolution features come from a pixel-wise (1x1) layer over the upsampled decoder
features concatenated with the input, so heads stay pixel-wise as in the paper while the
cost per full-resolution pixel stays small. Input height and width must be multiples of
:data:`SIZE_MULTIPLE` (the runtime pads).

That pixel-wise layer (:class:`UpsampledConcatConv1x1`) is computed without building the
full-resolution concatenation: a 1x1 convolution is a linear map across channels at each
pixel and bilinear upsampling a linear map across pixels per channel with weights summing to
1, so ``conv1x1(cat(up(d), x); W, b) = up(conv1x1(d; W[:, :k])) + conv1x1(x; W[:, k:], b)``
(``k`` decoder channels). The decoder part runs at half resolution; the parameters are those
of the one ``Conv2d`` (same state dict), and the result differs by float rounding only.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from polrig.models.size import SIZE_MULTIPLE  # noqa: F401  (re-exported: the training modules read it here)


def conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


def _up(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)


class UpsampledConcatConv1x1(nn.Conv2d):
    """``Conv2d(low_channels + high_channels, out_channels, 1)`` applied to
    ``cat([up(low, high), high], 1)`` without forming the concatenation (module docstring):
    ``forward(low (B, low_channels, h, w), high (B, high_channels, H, W)) -> (B, out_channels,
    H, W)``, ``up`` bilinear with ``align_corners=False``. Its weight and bias are the plain
    convolution's, so checkpoints and graphs of the concatenating form load unchanged.

    ``concatenate = True`` evaluates the concatenating form instead (the same function);
    :func:`polrig.models.export.export_all` sets it while exporting: onnxruntime runs the two forms
    at the same speed within the noise of this machine, and the concatenating form rounds as
    the graphs shipped so far do (the split form moves PIPNet's normal by about 1e-5, which
    the pBRDF's narrow specular lobes amplify to 1e-4 of the initialization's maximum)."""

    def __init__(self, low_channels: int, high_channels: int, out_channels: int):
        super().__init__(low_channels + high_channels, out_channels, 1)
        self.low_channels = low_channels
        self.concatenate = False

    def forward(self, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        if self.concatenate:
            return F.conv2d(torch.cat([_up(low, high), high], 1), self.weight, self.bias)
        k = self.low_channels
        return F.conv2d(high, self.weight[:, k:], self.bias) + _up(F.conv2d(low, self.weight[:, :k]), high)


class UNetBackbone(nn.Module):
    """U-Net encoder-decoder with additive skips. ``forward(x) -> (full-resolution features
    (B, width, H, W), bottleneck features (B, 4 width, H/8, W/8))``."""

    def __init__(self, in_channels: int, width: int = 16):
        super().__init__()
        w = width
        self.width = w
        self.enc1 = nn.Sequential(conv_bn_relu(in_channels, w, 2), conv_bn_relu(w, w))
        self.enc2 = nn.Sequential(conv_bn_relu(w, 2 * w, 2), conv_bn_relu(2 * w, 2 * w))
        self.enc3 = nn.Sequential(conv_bn_relu(2 * w, 4 * w, 2), conv_bn_relu(4 * w, 4 * w))
        self.lat3 = nn.Conv2d(4 * w, 2 * w, 1)
        self.dec2 = conv_bn_relu(2 * w, 2 * w)
        self.lat2 = nn.Conv2d(2 * w, w, 1)
        self.dec1 = conv_bn_relu(w, w)
        self.full = nn.Sequential(UpsampledConcatConv1x1(w, in_channels, w), nn.ReLU(inplace=True),
                                  nn.Conv2d(w, w, 1), nn.ReLU(inplace=True))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        e1 = self.enc1(x)
        e2 = self.enc2(e1)
        e3 = self.enc3(e2)
        d2 = self.dec2(_up(self.lat3(e3), e2) + e2)
        d1 = self.dec1(_up(self.lat2(d2), e1) + e1)
        full = self.full[1:](self.full[0](d1, x))  # = self.full(torch.cat([_up(d1, x), x], 1))
        return full, e3


def stokes_from_analyzer(analyzer: torch.Tensor) -> torch.Tensor:
    """Ideal-analyzer Stokes ``(B, C, 3, H, W)`` from analyzer images ``(B, C, 4, H, W)``
    in the order 0, 45, 90, 135 deg (``docs/conventions.md``: ``S0 = (I0+I45+I90+I135)/2``
    (the mean of the two estimates ``I0+I90`` and ``I45+I135``), ``S1 = I0 - I90``,
    ``S2 = I45 - I135``)."""
    i0, i45, i90, i135 = analyzer.unbind(2)
    return torch.stack([0.5 * (i0 + i45 + i90 + i135), i0 - i90, i45 - i135], 2)


def normalised_stokes(stokes: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """``(S1/S0, S2/S0)`` per colour ``(B, 2C, H, W)``: scale-free polarization features."""
    s0 = stokes[:, :, 0:1].clamp_min(eps)
    return (stokes[:, :, 1:] / s0).clamp(-2.0, 2.0).flatten(1, 2)


def planes(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """A per-image vector ``(B, K)`` as ``K`` constant planes shaped like ``like``'s H, W."""
    return v[:, :, None, None].expand(-1, -1, like.shape[-2], like.shape[-1])


def signed_log(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) log(1 + |x|)``: compresses specular peaks of Mueller inputs. The sign is
    ``1 - 2 [x < 0]`` (the same value; ``log(1 + |x|)`` is 0 where ``sign(x)`` is), which
    onnxruntime computes faster than its Sign kernel."""
    return torch.log1p(torch.abs(x)) * (1.0 - 2.0 * (x < 0).to(x.dtype))


def sum_over(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Sum over the short axis ``dim`` (kept with length 1) as a split and additions: the
    same sum as ``x.sum(dim, keepdim=True)``, which onnxruntime runs several times slower
    over a short axis of images (a strided reduction: 0.38 ms against 0.07 ms for 3 planes of
    616x512 on 2 cores)."""
    parts = torch.split(x, 1, dim)
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    return total


def normalize_channels(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``F.normalize(x, dim=1, eps=eps)`` (``x / max(|x|, eps)`` over the channels of a
    ``(B, K, H, W)`` image, K small) with the norm's sum written out (:func:`sum_over`)."""
    return x / torch.sqrt(sum_over(x * x, 1)).clamp_min(eps)


def softplus(x: torch.Tensor) -> torch.Tensor:
    """``log(1 + exp(x))`` written as ``max(x, 0) + log(1 + exp(-|x|))`` (the same function,
    without overflow). onnxruntime's Softplus kernel is about 4 times as slow as these
    element-wise ops on images; above ``x = 20`` the two terms round to ``x`` in float32
    exactly as ``F.softplus``'s threshold does."""
    return x.clamp_min(0.0) + torch.log1p(torch.exp(-x.abs()))


def apply_mueller(m: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """``S_out = M S_in`` for Mueller images ``(B, C, 3, 3, H, W)`` and states ``(B, 3)``
    -> ``(B, C, 3, H, W)``."""
    return sum_over(m * s[:, None, None, :, None, None], 3).squeeze(3)


class HighFrequencyAttention(nn.Module):
    """Spatial attention driven by the high-pass part of the features (features minus their
    3x3 local mean), so the specular branch concentrates on highlights and edges."""

    def __init__(self, channels: int):
        super().__init__()
        self.gate = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        hf = x - F.avg_pool2d(x, 3, 1, 1, count_include_pad=False)
        return x * (1.0 + torch.sigmoid(self.gate(hf)))


class MultiHeadChannelAttention(nn.Module):
    """Multi-head attention across channels (transposed attention: a ``c x c`` map per head,
    linear in the number of pixels; Zamir et al., Restormer, CVPR 2022)."""

    def __init__(self, channels: int, heads: int = 4):
        super().__init__()
        if channels % heads:
            raise ValueError("channels must be a multiple of heads")
        self.heads = heads
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.temperature = nn.Parameter(torch.ones(heads, 1, 1))
        self.proj = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(x).reshape(b, 3, self.heads, c // self.heads, h * w).unbind(1)
        # F.normalize(q) @ F.normalize(k)^T with the norms divided out of the small c x c map
        # (one division of (c/heads)^2 values per head rather than of every pixel's features)
        norms_q = q.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # (B, heads, c/heads, 1)
        norms_k = k.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cosines = (q @ k.transpose(-2, -1)) / (norms_q * norms_k.transpose(-2, -1))
        attn = torch.softmax(cosines * self.temperature, dim=-1)
        out = (attn @ v).reshape(b, c, h, w)
        return x + self.proj(out)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` (B, K, H, W) over masked pixels (mask (B, 1, H, W) in {0, 1}) and K."""
    m = mask.expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)
