"""ReconNet as fused Triton kernels: the same function, fewer passes, no PyTorch layer.

    fused = fused_reconnet(net)                     # a FusedReconNet; net is untouched
    output, read = fused.step(inputs, flow, previous)
    stack, color, flags = fused.frame(mask, normal, depth, ao, sampling, flow, previous, shading)

Eager ReconNet writes and reads back the concatenated and padded inputs, every layer's features, the
upsampled coarse features, their sum with the skip and its ReLU, the raw output and the output's
pieces, and cuDNN runs 16- to 64-channel 3x3 convolutions poorly. Here every layer is one kernel
(:mod:`isosr_net.fused_kernels`; NHWC fp16, fp32 accumulation): pack (with the previous output's
warp), head, the three stride-2 convolutions, the residual blocks' convolutions (the sum in the
second's epilogue), per decoder level the coarse features upsampled, reduced by its 1x1 convolution
and summed with the skip in one pass and its 3x3 convolution in another, and the tail (with a
``pixel_tail`` model's MLP and the output stack). :meth:`FusedReconNet.frame` is a `Reconstructor`'s
whole frame after the render in these passes alone: the pack reads the render's buffers in place and
checks them, the tail writes the output buffers and the shaded color. A model that upscales x2 runs
in the same passes: the pack reads the previous output's 2 x 2 pixels per input pixel (warped by the
flow upsampled), the tail writes its 24 channels depth-to-space over the inputs upsampled. A model
with a stem of stride 2 too: its head strides over the packed inputs, its tail writes 2 x 2 input
pixels per feature pixel.

The fused path runs on CUDA tensors where Triton imports (and on CPU tensors under Triton's
interpreter, ``TRITON_INTERPRET=1``, for tests); elsewhere :class:`FusedReconNet` runs the
ReconNet it was made from. :func:`fused_traffic` gives each pass's memory-traffic floor.
"""

from __future__ import annotations

import copy
import functools
import os
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.conventions import AO, MASK, SAMPLED_AO, SAMPLING
from isosr_render.shading import ShadingParams
from isosr_render.shapes import check_int, check_shape
from isosr_net.reconnet import INPUTS, LEVELS, OUTPUTS, RECURRENT, UPSCALES, ReconNet, ReconNetConfig, blend_rays_at

PACKED = 16  # channels of the packed input: 10 used (x2: 16), padded to tl.dot's smallest K
MAX_KERNEL_WIDTH = 64  # the widest tile the kernels are checked at (ReconNet's shipped widths)
# The upscales whose packed input (the inputs, and the previous mask and AO at each input pixel's output pixels)
# fits PACKED: x4's 40 channels do not, so an x4 model runs unfused.
FUSED_UPSCALES = tuple(s for s in UPSCALES if INPUTS + RECURRENT * s * s <= PACKED)


def kernel_width(channels: int) -> int:
    """The channels of a kernel's tile for ``channels`` stored: a power of 2, at least 16 (``tl.dot``'s smallest)."""
    return max(16, 1 << (channels - 1).bit_length())


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


def fusable(config: ReconNetConfig) -> bool:
    """Whether the kernels take a ReconNet of ``config``: its widths (and a ``pixel_tail``'s) at most the kernels'
    widest tile (a width under 16 or not a power of 2 is padded in the tiles), an upscale of
    :data:`FUSED_UPSCALES` (any blocks, AO prior, geometry gate and stem stride), and a pixel tail only at an
    upscale of 1 (the tail reads its inputs from the pack, one input pixel an output pixel)."""
    widths = (*config.widths, config.pixel_tail or 1)
    return (config.upscale in FUSED_UPSCALES and all(kernel_width(w) <= MAX_KERNEL_WIDTH for w in widths)
            and not (config.pixel_tail and config.upscale != 1))


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


def _padded_bias(bias: torch.Tensor, co: int) -> torch.Tensor:
    padded = bias.detach().float().new_zeros(co)
    padded[:len(bias)] = bias.detach()
    return padded


def tail_convolution(net: ReconNet) -> tuple[torch.Tensor, torch.Tensor]:
    """The tail's weights and bias as the fused tail reads them: ``net.tail``'s rows, then a ``blend_map`` model's
    map's (one per output pixel of a feature pixel; both 3x3 convolutions of the same features).

    Shape:
        Returns weight (Co, Ci, 3, 3), bias (Co,): Co = ``net.tail``'s outputs plus ``config.cell_side`` squared
        for a blend map.
    """
    weight, bias = net.tail.weight.detach(), net.tail.bias.detach()
    if net.config.blend_map:
        weight = torch.cat([weight, net.ao_blend_map.weight.detach()])
        bias = torch.cat([bias, net.ao_blend_map.bias.detach()])
    return weight, bias


def pixel_tail_weights(mlp: nn.Sequential) -> dict[str, torch.Tensor]:
    """A ``pixel_tail`` model's MLP (``ReconNet.pixel_tail``: 1x1 convolutions of the raw outputs, the inputs and
    the previous mask and AO, ReLU, then to the outputs) as the fields of
    :class:`~isosr_net.fused_kernels.PixelTail`, the hidden units zero-padded to a tile."""
    first, last = mlp[0].weight.detach()[:, :, 0, 0], mlp[2].weight.detach()[:, :, 0, 0]  # (H, 16), (6, H)
    hid = kernel_width(first.shape[0])
    raw, packed = first.new_zeros(OUTPUTS, hid), first.new_zeros(PACKED, hid)
    raw[:, :first.shape[0]] = first[:, :OUTPUTS].t()
    packed[:INPUTS + RECURRENT, :first.shape[0]] = first[:, OUTPUTS:].t()
    out = first.new_zeros(hid, PACKED)
    out[:first.shape[0], :OUTPUTS] = last.t()
    return {"raw": raw.float().contiguous(), "packed": packed.half().contiguous(),
            "bias": _padded_bias(mlp[0].bias, hid), "out": out.half().contiguous(),
            "out_bias": _padded_bias(mlp[2].bias, PACKED)}


class FusedConv(nn.Module):
    """One 3x3 convolution of ReconNet as :func:`~isosr_net.fused_kernels.conv3x3` runs it, with
    the ReLU where the network applies one.

    Shape:
        x: (B, H, W, ci) fp16 NHWC. Returns (B, H/stride, W/stride, co).
    """

    def __init__(self, conv: nn.Conv2d, ci: int, co: int, relu: bool = True):
        super().__init__()
        self.stride, self.relu, self.channels = conv.stride[0], relu, co
        self.register_buffer("weight", tap_weights(conv.weight, kernel_width(ci), kernel_width(co)))
        self.register_buffer("bias", _padded_bias(conv.bias, kernel_width(co)))

    def forward(self, x: torch.Tensor, residual: torch.Tensor | None = None) -> torch.Tensor:
        return _kernels().conv3x3(x, self.weight, self.bias, stride=self.stride, relu=self.relu, residual=residual,
                                  out_channels=self.channels)


class FusedUpsample(nn.Module):
    """A decoder level's input as :func:`~isosr_net.fused_kernels.upsample_add` makes it: the skip
    plus the coarse features upsampled and reduced by the level's 1x1 convolution, ReLU.

    Shape:
        skip: (B, H, W, C) fp16 NHWC. coarse: (B, H/2, W/2, CC) fp16 NHWC. Returns (B, H, W, C).
    """

    def __init__(self, reduce: nn.Conv2d):
        super().__init__()
        c, cc = reduce.out_channels, reduce.in_channels
        weight = reduce.weight.detach().new_zeros(kernel_width(cc), kernel_width(c))
        weight[:cc, :c] = reduce.weight.detach()[:, :, 0, 0].t()
        self.register_buffer("weight", weight.half().contiguous())
        self.register_buffer("bias", _padded_bias(reduce.bias, kernel_width(c)))

    def forward(self, skip: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
        return _kernels().upsample_add(skip, coarse.permute(0, 3, 1, 2), self.weight, self.bias)


class FusedReconNet(nn.Module):
    """A ReconNet as fused kernels (see the module docstring).

    Same interface as :class:`~isosr_net.reconnet.ReconNet`; outputs equal up to fp16 rounding.
    Inference only (no gradients through the kernels).

    Args:
        net: the ReconNet (:func:`fusable`: widths at most :data:`MAX_KERNEL_WIDTH`, an upscale of
            :data:`FUSED_UPSCALES`).

    Shape:
        inputs: (B, 8, H, W). prev_warped: (B, 6, sH, sW). Returns (B, 6, sH, sW), float32 on the
        fused path; s the model's upscale.
    """

    def __init__(self, net: ReconNet):
        super().__init__()
        widths = net.config.widths
        if not fusable(net.config):
            raise ValueError(f"fused_reconnet: the widths and pixel_tail must be at most {MAX_KERNEL_WIDTH}, the "
                             f"upscale one of {FUSED_UPSCALES} (1 with a pixel tail), got {widths}, "
                             f"{net.config.pixel_tail} and {net.config.upscale}")
        self.config = net.config
        self.reference = net
        self.head = FusedConv(net.head, PACKED, widths[0])
        self.down = nn.ModuleList(FusedConv(conv, widths[i], widths[i + 1]) for i, conv in enumerate(net.down))
        self.body = nn.ModuleList(nn.ModuleList([FusedConv(block.conv1, widths[LEVELS], widths[LEVELS]),
                                                 FusedConv(block.conv2, widths[LEVELS], widths[LEVELS], relu=False)])
                                  for block in net.body)
        self.up = nn.ModuleList(FusedUpsample(reduce) for reduce in net.reduce)
        self.fuse = nn.ModuleList(FusedConv(conv, widths[i], widths[i]) for i, conv in enumerate(net.fuse))
        weight, bias = tail_convolution(net)
        tail = kernel_width(weight.shape[0])  # 16, or 32 for x2 and a stem of stride 2
        self.register_buffer("tail_w", tap_weights(weight, kernel_width(widths[0]), tail))
        self.register_buffer("tail_b", _padded_bias(bias, tail))
        # a blend model's weight as a host number: the tail reads it with no sync (inference: it is fixed)
        self.blend_rays = None if net.blend_rays is None else net.blend_rays.item()
        logits = net.gate_logits  # the geometry corrections' factors, read by the tail on the device
        self.register_buffer("gates", None if logits is None else torch.sigmoid(logits.detach().float()))
        mlp = pixel_tail_weights(net.pixel_tail) if net.config.pixel_tail else {}
        for name, tensor in mlp.items():  # buffers, to move with the module
            self.register_buffer(f"pixel_tail_{name}", tensor)
        self.pixel_tail_fields = tuple(mlp)

    def pixel_tail_mlp(self):
        """A ``pixel_tail`` model's MLP as the tail reads it (:class:`~isosr_net.fused_kernels.PixelTail`), or None."""
        fields = {f: getattr(self, f"pixel_tail_{f}") for f in self.pixel_tail_fields}
        return _kernels().PixelTail(**fields) if fields else None

    def forward(self, inputs: torch.Tensor, prev_warped: torch.Tensor, ray_factor: float = 1.0) -> torch.Tensor:
        if not fused_runs_on(inputs.device):
            return self.reference(inputs, prev_warped, ray_factor)
        return self._run(_kernels().ReconSources.of_inputs(inputs), prev_warped, None, ray_factor=ray_factor)["output"]

    def first_previous(self, inputs: torch.Tensor) -> torch.Tensor:
        """The stand-in for the previous output on a sequence's first frame (as ReconNet's)."""
        return self.reference.first_previous(inputs)

    def step(self, inputs: torch.Tensor, flow: torch.Tensor | None, previous: torch.Tensor | None,
             ray_factor: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrent step as :meth:`ReconNet.step`, the warp (or the first frame's stand-in)
        made in the input packing.

        Returns:
            ``(output, read)``: the output (B, 6, sH, sW), and what the network read of the warped
            previous output (or of the first frame's stand-in): its mask and AO, (B, 2, sH, sW).
            Unlike ReconNet's step, the other four channels are neither warped nor returned.

        Shape:
            inputs: (B, 8, H, W). flow: (B, 2, H, W), input pixels. previous: (B, 6, sH, sW); s the
            model's upscale.
        """
        if previous is not None and flow is None:
            raise ValueError("a step with a previous output needs the flow to warp it")
        if not fused_runs_on(inputs.device):
            output, warped = self.reference.step(inputs, flow, previous, ray_factor)
            return output, recurrent_channels(warped)
        results = self._run(_kernels().ReconSources.of_inputs(inputs), previous, flow if previous is not None else None,
                            ray_factor=ray_factor)
        h, w, s = *inputs.shape[-2:], self.config.upscale
        read = results["packed"][:, :h, :w, INPUTS:INPUTS + RECURRENT * s * s].permute(0, 3, 1, 2)
        return results["output"], F.pixel_shuffle(read, s) if s > 1 else read

    def frame(self, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
              sampling: torch.Tensor, flow: torch.Tensor | None, previous: torch.Tensor | None,
              shading: ShadingParams | None, ray_factor: float = 1.0, out: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """:func:`isosr_net.reconstructor.recon_frame` (its arguments, results and shapes; without
        ``precision``: fp16) in the network's passes alone: the pack reads the buffers in place and
        checks them, the tail writes the output buffers (into ``out`` where given, which may be
        ``previous``) and shades them. No host sync."""
        one = (None if t is None else t[None] for t in (mask, normal, depth, ao, flow))
        stack, color, flags = self.frames(*one, sampling=sampling, previous=previous, shading=shading,
                                          ray_factor=ray_factor, out=out)
        return stack, None if color is None else color[0], flags[0]

    def frames(self, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
               flow: torch.Tensor | None, *, sampling: torch.Tensor, previous: torch.Tensor | None,
               shading: ShadingParams | None, ray_factor: float = 1.0, out: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """:meth:`frame` of a batch of frames of several streams in one call: each pass one launch
        for all (:func:`isosr_net.reconstructor.recon_frames`' arguments, results and shapes)."""
        sources = _kernels().ReconSources.of_buffers(mask, normal, depth, ao, sampling)
        results = self._run(sources, previous, None if flow is None else flow.permute(0, 3, 1, 2),
                            as_buffers=True, shading=shading, ray_factor=ray_factor, out=out)
        return results["output"], results["color"], results["flags"]

    def _run(self, sources, prev: torch.Tensor | None, flow: torch.Tensor | None, **tail) -> dict[str, torch.Tensor]:
        results, passes = self.passes(sources, prev, flow, **tail)
        for _, run in passes:
            run()
        return results

    def passes(self, sources, prev: torch.Tensor | None, flow: torch.Tensor | None = None, as_buffers: bool = False,
               shading: ShadingParams | None = None, ray_factor: float = 1.0, out: torch.Tensor | None = None
               ) -> tuple[dict[str, torch.Tensor], list[tuple[str, Callable[[], None]]]]:
        """The fused forward as its passes, to run (or time) one by one: ``(results, [(name, run)])``.

        In order, each pass computes the entry of ``results`` named as it from those before
        (running one again recomputes it): ``pack`` (``packed`` and the input checks' ``flags``),
        ``head``, ``down1``..``down3`` (the encoder levels), ``body1.1``, ``body1.2``, ... (the
        residual blocks' convolutions), per decoder level from the coarsest ``up2`` (the
        upsampled, reduced sum) and ``fuse2``, ..., ``fuse0``, and ``tail`` (``output`` and
        ``color``). Arguments as for :func:`isosr_net.fused_kernels.pack_inputs` (``sources`` a
        :class:`~isosr_net.fused_kernels.ReconSources`) and :func:`~isosr_net.fused_kernels.recon_tail`
        (``out``; a blend model's weight at ``ray_factor``, as :meth:`ReconNet.forward`'s).
        """
        k = _kernels()
        blend_rays = blend_rays_at(self.blend_rays, ray_factor, self.config.blend_beyond)
        results: dict[str, torch.Tensor] = {}
        passes: list[tuple[str, Callable[[], None]]] = []

        def add(name: str, compute: Callable[[], torch.Tensor | tuple], *keys: str) -> None:
            passes.append((name, lambda: results.update(zip(keys or (name,), _as_tuple(compute())))))

        def layer(conv: FusedConv, src: str, residual: str | None = None):
            return lambda: conv(results[src], residual=results[residual] if residual else None)

        add("pack", lambda: k.pack_inputs(sources, prev, flow, multiple=self.config.multiple,
                                          first_frame=self.config.first_frame, upscale=self.config.upscale),
            "packed", "flags")
        add("head", layer(self.head, "packed"))
        skips = ["head"]
        for i, conv in enumerate(self.down):
            add(f"down{i + 1}", layer(conv, skips[-1]))
            skips.append(f"down{i + 1}")
        coarse = skips[-1]
        for j, (conv1, conv2) in enumerate(self.body):
            add(f"body{j + 1}.1", layer(conv1, coarse))
            add(f"body{j + 1}.2", layer(conv2, f"body{j + 1}.1", residual=coarse))
            coarse = f"body{j + 1}.2"
        for i in reversed(range(LEVELS)):
            skip, c = skips[i], coarse
            add(f"up{i}", lambda i=i, skip=skip, c=c: self.up[i](results[skip], results[c]))
            add(f"fuse{i}", layer(self.fuse[i], f"up{i}"))
            coarse = f"fuse{i}"
        mlp = self.pixel_tail_mlp()
        add("tail", lambda: k.recon_tail(results["fuse0"], self.tail_w, self.tail_b, sources, self.config,
                                         as_buffers, shading, out, blend_rays, self.gates, ray_factor,
                                         results["packed"] if mlp else None, mlp),
            "output", "color")
        return results, passes


def _as_tuple(x) -> tuple:
    return x if isinstance(x, tuple) else (x,)


def fused_reconnet(net: ReconNet) -> FusedReconNet:
    """A :class:`FusedReconNet` of ``net`` (eval mode, same device); ``net`` is untouched."""
    if not isinstance(net, ReconNet):
        raise TypeError(f"fused_reconnet needs a ReconNet, got {type(net).__name__}")
    return FusedReconNet(copy.deepcopy(net).eval()).to(next(net.parameters()).device).eval()


def fused_traffic(h: int, w: int, config: ReconNetConfig = ReconNetConfig(), warp: bool = True,
                  frame: bool = False) -> dict[str, int]:
    """Bytes each pass of :meth:`FusedReconNet.passes` must read and write per frame (each tensor
    once; weights ignored): its floor at a memory bandwidth of ``B`` bytes/s is ``bytes / B``.

    Args:
        h, w: the frame's size as rendered (the network's input; the output has ``config.upscale``
            times its sides).
        config: the network's (its widths, blocks, AO prior and upscale).
        warp: the pack warps the previous output (reads the flow) rather than reading it warped.
        frame: as :meth:`FusedReconNet.frame` runs it: the sampling two values rather than two
            planes of an input stack, and the tail writing the shaded color too.

    Returns:
        pass name -> bytes; the inputs and the output are fp32, features fp16.
    """
    check_int(h, "h", 1, where="fused_traffic")
    check_int(w, "w", 1, where="fused_traffic")
    step, widths = config.multiple, config.widths
    padded = (h + -h % step) * (w + -w % step)
    pixels, f32, f16 = h * w, 4, 2
    sampling = 0 if frame else len(range(INPUTS)[SAMPLING])  # per-pixel planes read
    stem = config.stem_stride.bit_length() - 1  # the first level's halvings of the input

    def features(level: int, channels: int) -> int:  # level: of the network (0 at the first level)
        return channels * f16 * padded // 4 ** (level + stem)

    cells = config.upscale ** 2  # output pixels per input pixel
    # The previous output: its mask and AO once (warped: plus the flow's two channels).
    prev = (RECURRENT * cells + (2 if warp else 0)) * f32 * pixels
    packed = PACKED * f16 * padded
    out = {"pack": (AO.start + 1 + sampling) * f32 * pixels + prev + packed,
           "head": packed + features(0, widths[0])}
    for i in range(LEVELS):
        out[f"down{i + 1}"] = features(i, widths[i]) + features(i + 1, widths[i + 1])
    for j in range(config.blocks):
        out[f"body{j + 1}.1"] = features(LEVELS, 2 * widths[LEVELS])
        out[f"body{j + 1}.2"] = features(LEVELS, 3 * widths[LEVELS])
    for i in reversed(range(LEVELS)):
        # skip, the coarser level's output (a quarter of the pixels), the sum; the sum, the output
        out[f"up{i}"] = features(i, 2 * widths[i]) + features(i + 1, widths[i + 1])
        out[f"fuse{i}"] = features(i, 2 * widths[i])
    # the features, the inputs' mask, normal and depth (and the rays' AO and sampling for their
    # prior), the output (and the color)
    given = AO.start + (len(range(INPUTS)[SAMPLED_AO]) + sampling if config.ao_prior != "none" else 0)
    out["tail"] = features(0, widths[0]) + (given + (OUTPUTS + (3 if frame else 0)) * cells) * f32 * pixels
    if config.pixel_tail:  # its MLP reads the packed inputs at each pixel
        out["tail"] += PACKED * f16 * pixels
    return out
