"""polrig.models.layers: the U-Net's full-resolution 1x1 layer, computed without the full-resolution
concatenation (decoder part at half resolution, then upsampled), equals the concatenating
formulation ``conv1x1(cat(up(d), x))`` to float rounding, keeps the plain convolution's
parameters, and exported graphs of either form recover to the same parameters."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402
from torch.nn import functional as F  # noqa: E402

from polrig.models.layers import UNetBackbone, UpsampledConcatConv1x1  # noqa: E402


def _concatenating(conv: nn.Conv2d, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """The formulation the layer replaces: bilinear upsampling of ``low`` to ``high``'s size,
    concatenation, one 1x1 convolution with the layer's own weight and bias (float64)."""
    up = F.interpolate(low.double(), size=high.shape[-2:], mode="bilinear", align_corners=False)
    return F.conv2d(torch.cat([up, high.double()], 1), conv.weight.double(), conv.bias.double())


def _scale(t: torch.Tensor) -> float:
    return max(1.0, float(t.detach().abs().max()))


@settings(max_examples=40)
@given(low_c=st.integers(1, 9), high_c=st.integers(1, 9), out_c=st.integers(1, 6),
       h=st.integers(1, 9), w=st.integers(1, 9), up_h=st.integers(1, 19), up_w=st.integers(1, 19),
       batch=st.integers(1, 2), magnitude=st.sampled_from([1e-3, 1.0, 1e3]), seed=st.integers(0, 2**16))
def test_split_layer_equals_upsample_concat_conv(low_c, high_c, out_c, h, w, up_h, up_w, batch, magnitude, seed):
    # any sizes (odd, even, not a multiple of the low grid, even shrinking): bilinear weights sum to 1
    gen = torch.Generator().manual_seed(seed)
    conv = UpsampledConcatConv1x1(low_c, high_c, out_c)
    with torch.no_grad():
        conv.bias.copy_(torch.randn(out_c, generator=gen))
    low = magnitude * torch.randn(batch, low_c, h, w, generator=gen)
    high = magnitude * torch.randn(batch, high_c, up_h, up_w, generator=gen)
    with torch.no_grad():
        got = conv(low, high)
        ref = _concatenating(conv, low, high)
    assert got.shape == (batch, out_c, up_h, up_w)
    # float32 rounding relative to the magnitude of the summed terms (|W| |inputs| + |b|)
    with torch.no_grad():
        up = F.interpolate(low.double().abs(), size=high.shape[-2:], mode="bilinear", align_corners=False)
        scale = float(F.conv2d(torch.cat([up, high.double().abs()], 1), conv.weight.double().abs(),
                               conv.bias.double().abs()).max())
    assert float((got.double() - ref).abs().max()) <= 1e-5 * scale


def test_split_layer_has_the_plain_convolutions_parameters():
    layer, plain = UpsampledConcatConv1x1(16, 31, 16), nn.Conv2d(47, 16, 1)
    assert isinstance(layer, nn.Conv2d)  # polrig.models.recover finds it with the other convolutions
    assert {k: tuple(v.shape) for k, v in layer.state_dict().items()} == \
        {k: tuple(v.shape) for k, v in plain.state_dict().items()}
    layer.load_state_dict(plain.state_dict())  # a checkpoint of the concatenating form loads as is
    low, high = torch.randn(2, 16, 5, 6), torch.randn(2, 31, 10, 12)
    with torch.no_grad():
        assert torch.allclose(layer(low, high).double(), _concatenating(plain, low, high), atol=1e-5)


def _backbone_concatenating(net: UNetBackbone, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``UNetBackbone.forward`` as it was written before the split (explicitly, float32)."""
    def up(a, like):
        return F.interpolate(a, size=like.shape[-2:], mode="bilinear", align_corners=False)
    e1 = net.enc1(x)
    e2 = net.enc2(e1)
    e3 = net.enc3(e2)
    d2 = net.dec2(up(net.lat3(e3), e2) + e2)
    d1 = net.dec1(up(net.lat2(d2), e1) + e1)
    first = net.full[0]
    full = F.conv2d(torch.cat([up(d1, x), x], 1), first.weight, first.bias)
    return net.full[1:](full), e3


@pytest.mark.parametrize("size", [(8, 8), (16, 24), (17, 23), (33, 9), (40, 64)])
@pytest.mark.parametrize("training", [False, True])
def test_backbone_equals_the_concatenating_formulation(size, training):
    torch.manual_seed(sum(size) + training)
    net = UNetBackbone(7, 8)
    for m in net.modules():  # non-trivial batch norms
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.3, 0.3)
    net.train(training)
    x = torch.randn(2, 7, *size, requires_grad=True)
    full, e3 = net(x)
    ref_full, ref_e3 = _backbone_concatenating(net, x)
    assert full.shape == (2, 8, *size)
    assert float((full - ref_full).detach().abs().max()) <= 1e-5 * _scale(ref_full)
    assert torch.equal(e3, ref_e3)
    # training computes the same gradients (float rounding)
    g = torch.randn_like(full)
    grads = torch.autograd.grad((full * g).sum(), [x, net.full[0].weight])
    ref_grads = torch.autograd.grad((ref_full * g).sum(), [x, net.full[0].weight])
    for a, b in zip(grads, ref_grads):
        assert float((a - b).abs().max()) <= 1e-4 * _scale(b)


def test_exported_graphs_of_both_forms_recover_to_the_same_parameters(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    import shutil

    import onnx

    from polrig.models.export import _export, export_all
    from polrig.models.recover import networks_from_weights
    from polrig.models.runtime import WEIGHTS_DIR

    nets, meta = networks_from_weights(WEIGHTS_DIR)
    gen = torch.Generator().manual_seed(3)
    sample = {"analyzer": 0.2 + 0.6 * torch.rand(1, 3, 4, 16, 24, generator=gen), "mask": torch.ones(1, 1, 16, 24),
              "s_in": torch.tensor([[1.0, 0.9, 0.1]]), "wo": torch.zeros(1, 3, 16, 24),
              "stage_zero_axis": torch.tensor([[0.0, -1.0, 0.0]])}
    sample["wo"][:, 2] = -1.0
    export_all(nets["pipnet"], nets["pmmnet"], nets["direct"], tmp_path, sample,
               {"training": meta["training"]})
    assert not any(m.concatenate for net in nets.values() for m in net.modules()
                   if isinstance(m, UpsampledConcatConv1x1))  # the training form is restored
    convs = lambda path: sum(n.op_type == "Conv" for n in onnx.load(str(path)).graph.node)  # noqa: E731
    # export_all writes the concatenating form, one Conv per layer as in the shipped graphs; the
    # split form has one more Conv per backbone
    split = tmp_path / "split"
    split.mkdir()
    for name in ("single_shot.onnx", "model.json"):
        shutil.copy(tmp_path / name, split / name)
    _export(nets["direct"], sample, ("mueller",), split / "direct.onnx", concatenate=False)
    assert convs(tmp_path / "direct.onnx") == convs(WEIGHTS_DIR / "direct.onnx")
    assert convs(split / "direct.onnx") == convs(WEIGHTS_DIR / "direct.onnx") + 1
    for folder in (tmp_path, split):
        again, _ = networks_from_weights(folder)
        for name, net in nets.items():
            before, after = net.state_dict(), again[name].state_dict()
            assert list(before) == list(after)
            for k in before:
                assert torch.equal(before[k], after[k]), (folder.name, name, k)


# ----------------------------------------------------------------------------- element-wise rewrites
# Each helper is an exact rewrite of a torch formulation that onnxruntime runs slowly: checked
# against that formulation (float64, extremes included), values and gradients.

_EXTREMES = [0.0, -0.0, 1e-30, -1e-30, 1e-7, -3.0, 19.9, 20.0, 20.1, 50.0, -50.0, 1e4, -1e4, 88.0, 100.0]


@settings(max_examples=30)
@given(shape=st.lists(st.integers(1, 4), min_size=2, max_size=5), seed=st.integers(0, 2**16),
       magnitude=st.sampled_from([1e-6, 1.0, 1e6]))
def test_sum_over_is_the_sum_over_the_axis(shape, seed, magnitude):
    from polrig.models.layers import sum_over

    x = torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * magnitude
    for dim in range(-len(shape), len(shape)):
        got = sum_over(x, dim)
        ref = x.sum(dim, keepdim=True)
        assert got.shape == ref.shape
        assert float((got - ref).abs().max()) <= 1e-12 * max(1.0, float(x.abs().max())) * shape[dim]


def test_normalize_channels_is_f_normalize_including_zero_vectors():
    from polrig.models.layers import normalize_channels

    x = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    x[0, :, 0, 0] = 0.0  # below eps: both divide by eps
    x[1, :, 1, 1] = torch.tensor([1e-9, -1e-9, 0.0], dtype=torch.float64)
    x[1, :, 2, 2] = torch.tensor([1e200, 0.0, -1e200], dtype=torch.float64)
    for eps in (1e-12, 1e-6):
        torch.testing.assert_close(normalize_channels(x, eps), F.normalize(x, dim=1, eps=eps), rtol=1e-14, atol=0)


def test_softplus_is_f_softplus_with_its_gradient():
    from polrig.models.layers import softplus

    x = torch.cat([torch.tensor(_EXTREMES, dtype=torch.float64), torch.linspace(-30, 30, 601, dtype=torch.float64)])
    x.requires_grad_(True)
    got, ref = softplus(x), F.softplus(x)
    assert bool(torch.isfinite(got).all())
    # F.softplus returns x itself above its threshold 20, where log1p(exp(-x)) < 2.1e-9
    torch.testing.assert_close(got, ref, rtol=1e-15, atol=2.1e-9)
    (g,) = torch.autograd.grad(got.sum(), x)
    (g_ref,) = torch.autograd.grad(ref.sum(), x)
    away = x.detach() != 0  # at exactly 0 the piecewise form's subgradient differs (measure zero)
    torch.testing.assert_close(g[away], g_ref[away], rtol=1e-12, atol=2.1e-9)
    # float32, as the graph runs it: equal to F.softplus to rounding, x itself above 20
    x32 = x.detach().float()
    torch.testing.assert_close(softplus(x32), F.softplus(x32), rtol=2e-7, atol=1e-7)
    big = x32 > 20
    assert torch.equal(softplus(x32)[big], x32[big])


def test_signed_log_is_sign_times_log1p_including_zero_and_infinities():
    from polrig.models.layers import signed_log

    x = torch.tensor(_EXTREMES + [-1e-38, float("inf"), -float("inf"), 3.5, -3.5], dtype=torch.float32)
    ref = torch.sign(x) * torch.log1p(torch.abs(x))
    assert torch.equal(signed_log(x), ref)
    assert torch.isnan(signed_log(torch.tensor([float("nan")]))).all()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), heads=st.sampled_from([1, 2, 4]), size=st.integers(1, 6),
       magnitude=st.sampled_from([1e-3, 1.0, 30.0]))
def test_channel_attention_equals_the_normalize_then_multiply_form(seed, heads, size, magnitude):
    from polrig.models.layers import MultiHeadChannelAttention

    gen = torch.Generator().manual_seed(seed)
    att = MultiHeadChannelAttention(8, heads).double()
    with torch.no_grad():
        for p in att.parameters():
            p.copy_(torch.randn(p.shape, generator=gen, dtype=torch.float64))
    x = (torch.randn(2, 8, size, size + 1, generator=gen, dtype=torch.float64) * magnitude).requires_grad_(True)

    def reference(x):  # the Restormer formulation: normalised q and k, then their product
        b, c, h, w = x.shape
        q, k, v = att.qkv(x).reshape(b, 3, heads, c // heads, h * w).unbind(1)
        q, k = F.normalize(q, dim=-1), F.normalize(k, dim=-1)
        attn = torch.softmax((q @ k.transpose(-2, -1)) * att.temperature, dim=-1)
        return x + att.proj((attn @ v).reshape(b, c, h, w))

    got, ref = att(x), reference(x)
    torch.testing.assert_close(got, ref, rtol=1e-10, atol=1e-10 * _scale(ref))
    g = torch.randn(got.shape, generator=gen, dtype=torch.float64)
    grads = torch.autograd.grad((got * g).sum(), [x, att.temperature, att.qkv.weight])
    ref_grads = torch.autograd.grad((ref * g).sum(), [x, att.temperature, att.qkv.weight])
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-8 * _scale(b))
