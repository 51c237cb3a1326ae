"""The fast-path rewrites of SRNet's layers equal the originals (float64 references)."""

import pytest
import torch
from torch import nn

from isosr_net.fastpath import (ChannelPaddedConv, SubpixelUpsampleConv, fast_network, fast_reconnet, fast_srnet,
                                phase_weights, upsample_conv)
from isosr_net.model import SRNet, SRNetConfig
from isosr_net.reconnet import ReconNet, ReconNetConfig


@pytest.mark.parametrize("size", [(1, 1), (1, 5), (2, 2), (2, 7), (5, 3), (9, 16)])
def test_subpixel_upsample_conv_equals_upsample_then_conv(size):
    torch.manual_seed(0)
    conv = nn.Conv2d(5, 4, 3, padding=1).double()
    x = torch.randn(2, 5, *size, dtype=torch.float64)
    expected = upsample_conv(x, conv.weight, conv.bias)
    got = SubpixelUpsampleConv(conv)(x)
    assert got.shape == expected.shape == (2, 4, 2 * size[0], 2 * size[1])
    assert torch.allclose(got, expected, rtol=0, atol=1e-12)


def test_the_border_lines_need_their_fix():
    # Without the recomputed borders the pixel-shuffled low-res convolution differs exactly there.
    torch.manual_seed(1)
    conv = nn.Conv2d(3, 2, 3, padding=1).double()
    x = torch.randn(1, 3, 6, 8, dtype=torch.float64)
    padded = nn.functional.pad(x, (1, 1, 1, 1), mode="replicate")
    raw = nn.functional.pixel_shuffle(nn.functional.conv2d(padded, phase_weights(conv.weight),
                                                           conv.bias.repeat_interleave(4)), 2)
    diff = (raw - upsample_conv(x, conv.weight, conv.bias)).abs()
    assert diff[..., 1:-1, 1:-1].max() < 1e-12
    assert diff[..., 0, :].max() > 1e-3 and diff[..., -1, :].max() > 1e-3
    assert diff[..., :, 0].max() > 1e-3 and diff[..., :, -1].max() > 1e-3


def test_phase_weights_sum_like_the_original_kernel():
    # A constant input stays constant under bilinear upsampling, so every phase kernel sums to the original.
    w = torch.randn(3, 2, 3, 3, dtype=torch.float64)
    phases = phase_weights(w).reshape(3, 4, 2, 3, 3)
    assert torch.allclose(phases.sum(dim=(-1, -2)), w.sum(dim=(-1, -2))[:, None].expand(3, 4, 2))


@pytest.mark.parametrize("c_in, c_out, multiple", [(101, 6, 8), (5, 3, 4), (8, 16, 8)])
def test_channel_padded_conv_equals_the_conv(c_in, c_out, multiple):
    torch.manual_seed(3)
    conv = nn.Conv2d(c_in, c_out, 3, padding=1).double()
    padded = ChannelPaddedConv(conv, multiple)
    assert padded.conv.in_channels % multiple == 0 and padded.conv.out_channels % multiple == 0
    assert padded.conv.in_channels - c_in < multiple and padded.conv.out_channels - c_out < multiple
    x = torch.randn(2, c_in, 6, 5, dtype=torch.float64)
    assert torch.allclose(padded(x), conv(x), rtol=0, atol=1e-12)


@pytest.mark.parametrize("upscale", [2, 4, 8])
def test_fast_srnet_equals_srnet(upscale):
    torch.manual_seed(2)
    net = SRNet(SRNetConfig(upscale=upscale, channels=8, residual_blocks=2)).double().eval()
    fast = fast_srnet(net)
    lowres = torch.randn(2, 5, 5, 7, dtype=torch.float64)
    prev = torch.randn(2, 6, 5 * upscale, 7 * upscale, dtype=torch.float64)
    with torch.no_grad():
        assert torch.allclose(fast(lowres, prev), net(lowres, prev), rtol=0, atol=1e-10)
    assert fast.upsample[0].weight.data_ptr() != net.upsample[0].weight.data_ptr()  # a copy


@pytest.mark.parametrize("upscale", [2, 4])
def test_fast_srnet_equals_srnet_with_the_subpixel_tail(upscale):
    torch.manual_seed(3)
    net = SRNet(SRNetConfig(upscale=upscale, channels=8, residual_blocks=1, tail="subpixel")).eval()
    fast = fast_srnet(net)
    lowres = torch.randn(2, 5, 6, 5)
    prev = torch.randn(2, 6, 6 * upscale, 5 * upscale)
    with torch.no_grad():
        torch.testing.assert_close(fast(lowres, prev), net(lowres, prev), rtol=0, atol=1e-5)
    assert isinstance(fast.tail[-1], ChannelPaddedConv) and len(fast.upsample) == 0


def test_bad_inputs_are_clear_errors():
    with pytest.raises(ValueError, match=r"\(Co, Ci, 3, 3\)"):
        phase_weights(torch.zeros(2, 2, 5, 5))
    with pytest.raises(ValueError, match="3x3, stride 1, padding 1"):
        SubpixelUpsampleConv(nn.Conv2d(2, 2, 3, padding=0))
    with pytest.raises(TypeError, match="needs an SRNet"):
        fast_srnet(nn.Conv2d(2, 2, 3))
    with pytest.raises(ValueError, match="ungrouped"):
        ChannelPaddedConv(nn.Conv2d(4, 4, 3, groups=2), 8)


def test_the_channel_padded_reconnet_computes_the_same_frames():
    torch.manual_seed(0)
    net = ReconNet(ReconNetConfig()).eval().double()
    fast = fast_network(net)
    assert fast.head.conv.in_channels == 16 and fast.tail.conv.out_channels == 8
    assert net.head.in_channels == 10 and net.tail.out_channels == 6  # the original is untouched
    inputs, previous = torch.rand(2, 8, 21, 30, dtype=torch.float64), torch.rand(2, 6, 21, 30, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(fast(inputs, previous), net(inputs, previous), rtol=0, atol=1e-12)
    with pytest.raises(TypeError, match="needs a ReconNet"):
        fast_reconnet(torch.nn.Conv2d(1, 1, 1))
