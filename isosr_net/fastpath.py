"""Inference-only rewrites of the networks' layers: the same function, cheaper on GPUs.

Two rewrites, each exact up to rounding:

- Channel counts padded to multiples of 8: tensor cores take channels in multiples of 8, and
  cuDNN pads other counts on every call. SRNet's first convolution reads 5 + 6 s^2 channels (101
  at s = 4) and its last writes 6; ReconNet's full-resolution head reads 10 and its tail writes 6
  (on an H100 at 1080p the head ran in cuDNN's "indexed" kernel, 276 us, plus 90 us of padding,
  of about 1.6 ms). Zero input channels with zero weights, and extra output channels that are
  sliced off, change nothing.
- Subpixel upsampling. SRNet upsamples by ``conv3x3(bilinear_2x(x))``. Bilinear 2x
  upsampling is linear, so each of the four output phases (even/odd row, even/odd column) of
  that composite is a 3x3 convolution of the low-res input. One convolution with four times
  the output channels, followed by ``F.pixel_shuffle``, computes all four without
  materializing the upsampled tensor, and with four times the output channels per matrix
  multiply, which tensor cores run faster. Bilinear upsampling clamps at the border
  (replicate padding of the input reproduces that exactly), but the convolution zero-pads the
  *upsampled* image, so the outermost high-res row and column on each side differ; those four
  lines are recomputed exactly from two-pixel strips of the input.
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from isosr_net.model import SRNet
from isosr_net.reconnet import ReconNet

# Low-res taps (rows) of output phase a as weights of the high-res 3x3 taps (columns), for
# bilinear 2x upsampling with align_corners=False: phase 0 reads high-res pixels 2i-1..2i+1,
# phase 1 reads 2i..2i+2, and high-res pixel 2j (2j+1) is 0.75 x[j] + 0.25 x[j-1] (x[j+1]).
PHASE_TAPS = torch.tensor([[[0.75, 0.25, 0.00], [0.25, 0.75, 0.75], [0.00, 0.00, 0.25]],
                           [[0.25, 0.00, 0.00], [0.75, 0.75, 0.25], [0.00, 0.25, 0.75]]], dtype=torch.float64)


def upsample_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``conv3x3(bilinear_2x(x))`` with zero padding, the reference the rewrite must equal.

    Shape:
        x: (B, Ci, h, w). weight: (Co, Ci, 3, 3). Returns (B, Co, 2h, 2w).
    """
    up = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    return F.conv2d(up, weight, bias, padding=1)


def phase_weights(weight: torch.Tensor) -> torch.Tensor:
    """The four low-res 3x3 kernels of ``conv3x3(bilinear_2x(.))``, in ``F.pixel_shuffle`` order.

    Shape:
        weight: (Co, Ci, 3, 3). Returns (4 Co, Ci, 3, 3); output channel ``4 c + 2 a + b`` is
        output channel ``c`` at row phase ``a`` and column phase ``b``.
    """
    if weight.ndim != 4 or weight.shape[-2:] != (3, 3):
        raise ValueError(f"phase_weights: weight must be (Co, Ci, 3, 3), got {tuple(weight.shape)}")
    taps = PHASE_TAPS.to(weight.device)
    kernels = torch.einsum("ajk,oikl,bml->oabijm", taps, weight.double(), taps)
    return kernels.reshape(-1, weight.shape[1], 3, 3).to(weight.dtype)


class SubpixelUpsampleConv(nn.Module):
    """``conv3x3(bilinear_2x(x))`` of a given convolution, computed as one low-res convolution
    plus ``F.pixel_shuffle``, border lines recomputed exactly.

    Shape:
        x: (B, Ci, h, w). Returns (B, Co, 2h, 2w); an input under 2x2 (no inner lines) takes the
        reference composite.
    """

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        if conv.kernel_size != (3, 3) or conv.padding != (1, 1) or conv.stride != (1, 1) or conv.groups != 1:
            raise ValueError(f"SubpixelUpsampleConv needs a 3x3, stride 1, padding 1 convolution, got {conv}")
        bias = conv.bias.detach() if conv.bias is not None else torch.zeros(conv.out_channels)
        self.register_buffer("weight", conv.weight.detach().clone())
        self.register_buffer("bias", bias.clone())
        self.register_buffer("phase_weight", phase_weights(conv.weight.detach()))
        self.register_buffer("phase_bias", bias.repeat_interleave(4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w, b = self.weight.to(x.dtype), self.bias.to(x.dtype)
        if x.shape[-2] < 2 or x.shape[-1] < 2:
            return upsample_conv(x, w, b)
        padded = F.pad(x, (1, 1, 1, 1), mode="replicate")
        y = F.pixel_shuffle(F.conv2d(padded, self.phase_weight.to(x.dtype), self.phase_bias.to(x.dtype)), 2)
        left = upsample_conv(x[..., :, :2], w, b)[..., :, :1]
        right = upsample_conv(x[..., :, -2:], w, b)[..., :, -1:]
        y = torch.cat([left, y[..., :, 1:-1], right], dim=3)
        top = upsample_conv(x[..., :2, :], w, b)[..., :1, :]
        bottom = upsample_conv(x[..., -2:, :], w, b)[..., -1:, :]
        return torch.cat([top, y[..., 1:-1, :], bottom], dim=2)


class ChannelPaddedConv(nn.Module):
    """A convolution whose input and output channel counts are padded up to ``multiple``: zero
    channels appended to the input, extra outputs computed by zero weights and sliced off.

    Shape:
        x: (B, Ci, H, W). Returns what ``conv`` returns, (B, Co, H', W').
    """

    def __init__(self, conv: nn.Conv2d, multiple: int):
        super().__init__()
        if conv.groups != 1:
            raise ValueError(f"ChannelPaddedConv needs an ungrouped convolution, got {conv}")
        self.in_channels, self.out_channels = conv.in_channels, conv.out_channels
        pad_in, pad_out = -conv.in_channels % multiple, -conv.out_channels % multiple
        self.conv = nn.Conv2d(conv.in_channels + pad_in, conv.out_channels + pad_out, conv.kernel_size,
                              conv.stride, conv.padding, bias=conv.bias is not None)
        self.conv.to(conv.weight.device, conv.weight.dtype)
        with torch.no_grad():
            self.conv.weight.zero_()
            self.conv.weight[:conv.out_channels, :conv.in_channels] = conv.weight
            if conv.bias is not None:
                self.conv.bias.zero_()
                self.conv.bias[:conv.out_channels] = conv.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pad_in = self.conv.in_channels - self.in_channels
        if pad_in:
            x = torch.cat([x, x.new_zeros(x.shape[0], pad_in, *x.shape[2:])], dim=1)
        return self.conv(x)[:, :self.out_channels]


class FastSRNet(SRNet):
    """An SRNet with its layers rewritten for speed (see the module docstring); same output."""

    def __init__(self, net: SRNet, channel_multiple: int = 8):
        nn.Module.__init__(self)
        self.config = net.config
        self.body = net.body
        self.head = ChannelPaddedConv(net.head, channel_multiple)
        self.tail = nn.Sequential(net.tail[0], net.tail[1], ChannelPaddedConv(net.tail[2], channel_multiple))
        self.upsample = nn.ModuleList(SubpixelUpsampleConv(conv) for conv in net.upsample)

    def upsample_features(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.upsample:
            x = F.relu(layer(x))
        return x


def fast_srnet(net: SRNet, channel_multiple: int = 8) -> FastSRNet:
    """A rewritten copy of ``net`` (eval mode, same device); ``net`` is untouched."""
    if not isinstance(net, SRNet):
        raise TypeError(f"fast_srnet needs an SRNet, got {type(net).__name__}")
    return FastSRNet(copy.deepcopy(net), channel_multiple).to(next(net.parameters()).device).eval()


def fast_reconnet(net: ReconNet, channel_multiple: int = 8) -> ReconNet:
    """A copy of ``net`` (eval mode, same device) with its full-resolution head and tail
    convolutions channel-padded; ``net`` is untouched."""
    if not isinstance(net, ReconNet):
        raise TypeError(f"fast_reconnet needs a ReconNet, got {type(net).__name__}")
    fast = copy.deepcopy(net)
    fast.head = ChannelPaddedConv(fast.head, channel_multiple)
    fast.tail = ChannelPaddedConv(fast.tail, channel_multiple)
    return fast.eval()


def fast_network(net: nn.Module) -> nn.Module:
    """The rewritten copy of an SRNet (:func:`fast_srnet`) or a ReconNet (:func:`fast_reconnet`)."""
    if isinstance(net, ReconNet):
        return fast_reconnet(net)
    return fast_srnet(net)
