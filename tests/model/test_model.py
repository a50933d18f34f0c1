"""Tests for s3k.model: U-Net shapes, memory formats, shared weights, BatchNorm folding, detect, FLOPs."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from s3k.model import HeatmapHead, UNet, UNetConfig, conv_layers, count_conv_flops, detect
from s3k.readout.heatmaps import heatmap_moments, peak_window_mean, spatial_softmax


def _randomize_norm_stats(net: nn.Module, seed: int = 0) -> None:
    """Give every BatchNorm non-trivial statistics and affine parameters, as after training."""
    gen = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            n = m.num_features
            m.running_mean.copy_(torch.randn(n, generator=gen) * 0.3)
            m.running_var.copy_(torch.rand(n, generator=gen) + 0.5)
            m.weight.data.copy_(torch.rand(n, generator=gen) + 0.5)
            m.bias.data.copy_(torch.randn(n, generator=gen) * 0.1)


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("size", [(32, 32), (48, 40), (36, 100)])
def test_unet_output_shape(stride, size):
    H, W = size
    net = UNet(3, UNetConfig(channels=(8, 16, 16), res_blocks=1, stride=stride, norm="none")).eval()
    out = net(torch.rand(2, 3, H, W))
    assert out.shape == (2, 3, H // stride, W // stride)
    assert torch.isfinite(out).all()


def test_unet_default_sizes_not_multiple_of_depth():
    net = UNet(5).eval()  # depth 3: heatmap grids of 8-multiples are not required
    for H, W in [(128, 128), (96, 128), (100, 60), (2, 2)]:
        assert net(torch.rand(1, 3, H, W)).shape == (1, 5, H // 2, W // 2)


def test_unet_rejects_bad_inputs():
    net = UNet(2, UNetConfig(stride=4))
    with pytest.raises(ValueError, match="multiples of the heatmap stride 4"):
        net(torch.rand(1, 3, 30, 32))
    with pytest.raises(ValueError, match=r"\(N, 3, H, W\)"):
        net(torch.rand(3, 32, 32))
    with pytest.raises(ValueError, match=r"\(N, 3, H, W\)"):
        net(torch.rand(1, 1, 32, 32))
    with pytest.raises(ValueError, match="num_keypoints"):
        UNet(0)


def test_config_validation_and_round_trip():
    for bad in [dict(stride=3), dict(norm="layer"), dict(channels=()), dict(res_blocks=-1)]:
        with pytest.raises(ValueError, match="UNetConfig"):
            UNetConfig(**bad)
    with pytest.raises(ValueError, match="divisible by 8"):
        UNetConfig(channels=(12, 16), norm="group")
    cfg = UNetConfig(channels=[8, 16], res_blocks=3, stride=4, norm="group")
    assert cfg.channels == (8, 16) and cfg.depth == 1
    assert UNetConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown fields"):
        UNetConfig.from_dict({"widht": 3})


def test_default_model_is_small():
    # The paper found 16-32 channels enough; the default stays in the 50-150k parameter range for CPU speed.
    net = UNet(3)
    n = sum(p.numel() for p in net.parameters())
    assert 50_000 <= n <= 150_000
    assert all(c in (16, 32) for c in net.config.channels)


@pytest.mark.parametrize("norm", ["batch", "group", "none"])
def test_channels_last_output_equals_contiguous(norm):
    torch.manual_seed(0)
    net = UNet(3, UNetConfig(norm=norm)).eval()
    _randomize_norm_stats(net)
    x = torch.rand(2, 3, 64, 48)
    with torch.no_grad():
        ref = net(x)
        net_cl = net.to(memory_format=torch.channels_last)
        out = net_cl(x.contiguous(memory_format=torch.channels_last))
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-4)


def test_same_weights_serve_every_camera():
    torch.manual_seed(1)
    net = UNet(4).eval()
    _randomize_norm_stats(net)
    images = torch.rand(2, 3, 3, 32, 48)  # (B, C, 3, H, W)
    with torch.no_grad():
        logits, mean_uv, var = detect(net, images)
        for b in range(2):
            for c in range(3):
                single = net(images[b, c][None])[0]
                torch.testing.assert_close(logits[b, c], single, atol=1e-5, rtol=1e-4)
        # Swapping two cameras swaps their outputs and nothing else.
        swapped, _, _ = detect(net, images[:, [2, 1, 0]])
    torch.testing.assert_close(swapped, logits[:, [2, 1, 0]], atol=1e-5, rtol=1e-4)
    assert logits.shape == (2, 3, 4, 16, 24)
    # The read-out's precision: float64 from the softmax on.
    probs = spatial_softmax(logits.double())
    ref_mean, ref_var = heatmap_moments(probs, 2)
    torch.testing.assert_close(mean_uv, ref_mean)
    # With a window: the mean within it of the peak, the variance still the whole heatmap's.
    with torch.no_grad():
        _, windowed, windowed_var = detect(net, images, window=3)
    torch.testing.assert_close(windowed, peak_window_mean(probs, 2, 3))
    torch.testing.assert_close(windowed_var, ref_var)
    torch.testing.assert_close(var, ref_var)
    with pytest.raises(ValueError, match=r"\(B, C, 3, H, W\)"):
        detect(net, images[0])


def test_heatmap_head_matches_conv_in_both_layouts():
    head = HeatmapHead(16, 3)
    nn.init.normal_(head.bias)
    x = torch.randn(2, 16, 6, 5)
    ref = nn.functional.conv2d(x, head.weight, head.bias)
    torch.testing.assert_close(head(x), ref)
    torch.testing.assert_close(head(x.contiguous(memory_format=torch.channels_last)), ref)
    x.requires_grad_()
    head(x.contiguous(memory_format=torch.channels_last)).pow(2).sum().backward()
    assert head.weight.grad is not None and head.bias.grad is not None and x.grad is not None


def test_fused_model_matches_eval_model():
    torch.manual_seed(2)
    net = UNet(3)
    _randomize_norm_stats(net, seed=3)
    net.eval()
    fused = net.fused()
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fused.modules())
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.modules())  # original untouched
    x = torch.rand(3, 3, 40, 56)
    with torch.no_grad():
        torch.testing.assert_close(fused(x), net(x), atol=1e-5, rtol=1e-4)


def test_every_parameter_gets_a_gradient():
    net = UNet(3, UNetConfig(encoder_convs=1))
    out = net(torch.rand(4, 3, 32, 32))
    (out * torch.randn_like(out)).sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


def test_count_conv_flops_closed_form():
    conv = nn.Conv2d(4, 6, 3, stride=2, padding=1, bias=True)
    x = torch.rand(2, 4, 10, 12)
    out_numel = 2 * 6 * 5 * 6
    assert count_conv_flops(conv, x) == out_numel * (2 * 4 * 9 + 1)
    # For the U-Net, the count scales with the number of images and with the image area.
    net = UNet(3).eval()
    one = count_conv_flops(net, torch.rand(1, 3, 64, 64))
    assert count_conv_flops(net, torch.rand(4, 3, 64, 64)) == 4 * one
    assert count_conv_flops(net, torch.rand(1, 3, 128, 128)) == 4 * one


def test_conv_layers_lists_every_convolution_with_its_shapes():
    net = UNet(3, UNetConfig(channels=(8, 16), res_blocks=1, stride=2)).eval()
    layers = conv_layers(net, torch.rand(2, 3, 32, 32))
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [m for m, _, _ in layers] == convs  # each once, in call order (here module order)
    assert tuple(layers[0][1]) == (2, 3, 32, 32) and tuple(layers[0][2]) == (2, 8, 16, 16)  # stem
    assert tuple(layers[-1][2]) == (2, 3, 16, 16)  # head: K heatmaps at stride 2
    assert all(not p.requires_grad or p.grad is None for p in net.parameters())
