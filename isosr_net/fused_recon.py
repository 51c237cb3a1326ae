"""ReconNet with its full-resolution layers as fused Triton kernels: the same function, fewer passes.

    fused = fused_reconnet(net)                     # a FusedReconNet; net is untouched
    output, read = fused.step(inputs, flow, previous)

At full resolution eager ReconNet writes and reads back the concatenated and padded inputs, the
head's features, the upsampled coarse features, their sum with the skip and its ReLU, the last
decoder level's features, the raw output and the output's pieces, and cuDNN runs 16-channel
3x3 convolutions poorly. Here that work is four kernels (:mod:`isosr_net.fused_kernels`; NHWC
fp16, fp32 accumulation): pack (with the previous output's warp), head, last decoder level
(upsample, skip sum and ReLUs in its loads), tail (with the output stack). The coarse levels
(the stride-2 convolutions, the 1/8 body, the upper decoder levels and the last level's 1x1
reduction, under a tenth of the pixels) stay in PyTorch, fp16 NHWC through cuDNN.

The fused path runs on CUDA tensors where Triton imports (and on CPU tensors under Triton's
interpreter, ``TRITON_INTERPRET=1``, for tests); elsewhere :class:`FusedReconNet` runs the
ReconNet it was made from. :func:`fused_traffic` gives each kernel's memory-traffic floor.
"""

from __future__ import annotations

import copy
import functools
import os
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.conventions import AO, MASK
from isosr_render.shapes import check_int, check_shape
from isosr_net.reconnet import INPUTS, LEVELS, OUTPUTS, RECURRENT, ReconNet

PACKED = 16  # the packed input's channels (isosr_net.fused_kernels.PACKED): 10 used


def recurrent_channels(previous: torch.Tensor) -> torch.Tensor:
    """The previous output's channels the network reads (ReconNet.forward): mask and AO, (B, 2, H, W).
    Slices, not an index list, so that a CUDA graph can capture it (no host-to-device copy)."""
    return torch.cat([previous[:, MASK], previous[:, AO]], dim=1)


@functools.cache
def triton_imports() -> bool:
    """Whether Triton imports here (it ships with PyTorch's CUDA builds)."""
    try:
        import triton  # noqa: F401
    except ImportError:
        return False
    return True


def fused_runs_on(device: torch.device | str) -> bool:
    """Whether the fused kernels run on ``device``: CUDA with Triton, or CPU under Triton's interpreter."""
    kind = torch.device(device).type
    return triton_imports() and (kind == "cuda" or (kind == "cpu" and os.environ.get("TRITON_INTERPRET") == "1"))


def _kernels():
    from isosr_net import fused_kernels  # compiles nothing on import; imports triton

    return fused_kernels


def tap_weights(weight: torch.Tensor, ci: int, co: int) -> torch.Tensor:
    """A 3x3 convolution's weights tap-major for the kernels, zero-padded to ``ci`` in and ``co`` out.

    Shape:
        weight: (Co, Ci, 3, 3), Co <= co, Ci <= ci. Returns (9, ci, co), fp16, ``[3 * ky + kx, i, o]``.
    """
    dims = check_shape(weight, "(Co, Ci, 3, 3)", "weight", "tap_weights")
    if dims["Co"] > co or dims["Ci"] > ci:
        raise ValueError(f"tap_weights: weight {tuple(weight.shape)} does not fit {ci} in, {co} out")
    taps = weight.detach().new_zeros(9, ci, co)
    taps[:, :dims["Ci"], :dims["Co"]] = weight.detach().permute(2, 3, 1, 0).reshape(9, dims["Ci"], dims["Co"])
    return taps.half().contiguous()


def _padded_bias(conv: nn.Conv2d, co: int) -> torch.Tensor:
    bias = conv.bias.detach().float().new_zeros(co)
    bias[:conv.out_channels] = conv.bias.detach()
    return bias


class FusedReconNet(nn.Module):
    """A ReconNet whose full-resolution layers run as fused kernels (see the module docstring).

    Same interface as :class:`~isosr_net.reconnet.ReconNet`; outputs equal up to fp16 rounding.
    Inference only (no gradients through the kernels).

    Shape:
        inputs: (B, 8, H, W). prev_warped: (B, 6, H, W). Returns (B, 6, H, W), float32 on the
        fused path.
    """

    def __init__(self, net: ReconNet):
        super().__init__()
        w0 = net.config.widths[0]
        if w0 < 16 or w0 & (w0 - 1):
            raise ValueError(f"fused_reconnet: the full-resolution width must be a power of 2 >= 16, got {w0}")
        self.config = net.config
        self.reference = net
        self.register_buffer("head_w", tap_weights(net.head.weight, PACKED, w0))
        self.register_buffer("head_b", _padded_bias(net.head, w0))
        self.register_buffer("fuse_w", tap_weights(net.fuse[0].weight, w0, w0))
        self.register_buffer("fuse_b", _padded_bias(net.fuse[0], w0))
        self.register_buffer("tail_w", tap_weights(net.tail.weight, w0, PACKED))
        self.register_buffer("tail_b", _padded_bias(net.tail, PACKED))
        # The coarse levels, fp16 NHWC; fuse[0] and the head and tail are the kernels'.
        coarse = copy.deepcopy(nn.ModuleDict({"down": net.down, "body": net.body, "reduce": net.reduce,
                                              "fuse": net.fuse}))
        self.coarse = coarse.half().to(memory_format=torch.channels_last)

    def forward(self, inputs: torch.Tensor, prev_warped: torch.Tensor) -> torch.Tensor:
        if not fused_runs_on(inputs.device):
            return self.reference(inputs, prev_warped)
        return self._fused(inputs, prev_warped, None)

    def first_previous(self, inputs: torch.Tensor) -> torch.Tensor:
        """The stand-in for the previous output on a sequence's first frame (as ReconNet's)."""
        return self.reference.first_previous(inputs)

    def step(self, inputs: torch.Tensor, flow: torch.Tensor | None,
             previous: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrent step as :meth:`ReconNet.step`, the warp fused into the input packing.

        Returns:
            ``(output, read)``: the output (B, 6, H, W), and what the network read of the warped
            previous output (or of the first frame's stand-in): its mask and AO, (B, 2, H, W).
            Unlike ReconNet's step, the other four channels are neither warped nor returned.

        Shape:
            inputs: (B, 8, H, W). flow: (B, 2, H, W), pixels. previous: (B, 6, H, W).
        """
        if previous is not None and flow is None:
            raise ValueError("a step with a previous output needs the flow to warp it")
        if not fused_runs_on(inputs.device):
            output, warped = self.reference.step(inputs, flow, previous)
            return output, recurrent_channels(warped)
        if previous is None:
            warped = self.first_previous(inputs)
            return self._fused(inputs, warped, None), recurrent_channels(warped)
        output, packed = self._fused(inputs, previous, flow, keep_packed=True)
        h, w = inputs.shape[-2:]
        return output, packed[:, :h, :w, INPUTS:INPUTS + RECURRENT].permute(0, 3, 1, 2)

    def _fused(self, inputs: torch.Tensor, prev: torch.Tensor, flow: torch.Tensor | None,
               keep_packed: bool = False):
        """The fused forward: ``prev`` warped already (``flow`` None) or warped here by ``flow``."""
        dims = check_shape(inputs, f"(B, {INPUTS}, H, W)", "inputs", "FusedReconNet")
        check_shape(prev, f"(B, {OUTPUTS}, H, W)", "prev_warped" if flow is None else "previous", "FusedReconNet",
                    dims)
        results, passes = self.passes(inputs, prev, flow)
        for _, run in passes:
            run()
        return (results["output"], results["packed"]) if keep_packed else results["output"]

    def passes(self, inputs: torch.Tensor, prev: torch.Tensor, flow: torch.Tensor | None = None
               ) -> tuple[dict[str, torch.Tensor], list[tuple[str, Callable[[], None]]]]:
        """The fused forward as its passes, to run (or time) one by one: ``(results, [(name, run)])``.

        In order, ``pack``, ``head``, ``coarse`` (PyTorch), ``fuse`` and ``tail`` each compute one
        entry of ``results`` (``packed``, ``skip``, ``coarse``, ``features``, ``output``) from those
        before; running one again recomputes its entry. Arguments as for :func:`isosr_net.fused_kernels.pack_inputs`.
        """
        k = _kernels()
        results: dict[str, torch.Tensor] = {}

        def pack():
            results["packed"] = k.pack_inputs(inputs, prev, flow, multiple=2 ** LEVELS)

        def head():
            results["skip"] = k.conv3x3(results["packed"], self.head_w, self.head_b)

        def coarse():
            with torch.autocast(inputs.device.type, enabled=False):  # fp16 throughout, as the kernels
                results["coarse"] = self._coarse(results["skip"].permute(0, 3, 1, 2))

        def fuse():
            results["features"] = k.conv3x3(results["skip"], self.fuse_w, self.fuse_b, coarse=results["coarse"])

        def tail():
            results["output"] = k.recon_tail(results["features"], self.tail_w, self.tail_b, inputs, self.config)

        return results, [("pack", pack), ("head", head), ("coarse", coarse), ("fuse", fuse), ("tail", tail)]

    def _coarse(self, skip: torch.Tensor) -> torch.Tensor:
        """ReconNet's levels below full resolution, from the head's features to the last decoder
        level's reduced coarse features, as :meth:`ReconNet.forward` computes them.

        Shape:
            skip: (B, w0, H', W'), NHWC strides. Returns (B, w0, H'/2, W'/2), NHWC strides.
        """
        down, reduce, fuse = self.coarse["down"], self.coarse["reduce"], self.coarse["fuse"]
        skips = [skip]
        for conv in down:
            skips.append(F.relu(conv(skips[-1])))
        y = self.coarse["body"](skips[-1])
        for i in reversed(range(1, LEVELS)):
            y = F.interpolate(reduce[i](y), scale_factor=2, mode="bilinear", align_corners=False)
            y = F.relu(fuse[i](F.relu(y + skips[i])))
        return reduce[0](y)


def fused_reconnet(net: ReconNet) -> FusedReconNet:
    """A :class:`FusedReconNet` of ``net`` (eval mode, same device); ``net`` is untouched."""
    if not isinstance(net, ReconNet):
        raise TypeError(f"fused_reconnet needs a ReconNet, got {type(net).__name__}")
    return FusedReconNet(copy.deepcopy(net).eval()).to(next(net.parameters()).device).eval()


def fused_traffic(h: int, w: int, width: int = 16, warp: bool = True) -> dict[str, int]:
    """Bytes each fused kernel must read and write per frame (each tensor once; weights ignored):
    its floor at a memory bandwidth of ``B`` bytes/s is ``bytes / B``.

    Args:
        h, w: the frame's size.
        width: the full-resolution features' channels (ReconNet's ``widths[0]``).
        warp: the pack warps the previous output (reads the flow) rather than reading it warped.

    Returns:
        ``{"pack", "head", "fuse", "tail"}`` -> bytes; the inputs are fp32, features fp16.
    """
    check_int(h, "h", 1, where="fused_traffic")
    check_int(w, "w", 1, where="fused_traffic")
    step = 2 ** LEVELS
    padded = (h + -h % step) * (w + -w % step)
    pixels, f32, f16 = h * w, 4, 2
    # The previous output: its mask and AO once (warped: plus the flow's two channels).
    prev = (RECURRENT + (2 if warp else 0)) * f32 * pixels
    features = width * f16 * padded
    return {"pack": INPUTS * f32 * pixels + prev + PACKED * f16 * padded,
            "head": PACKED * f16 * padded + features,
            "fuse": features + features // 4 + features,  # skip, coarse (a quarter of the pixels), out
            # features, the inputs' mask, normal and depth, the output stack
            "tail": features + AO.start * f32 * pixels + OUTPUTS * f32 * pixels}
