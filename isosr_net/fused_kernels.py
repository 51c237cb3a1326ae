"""Triton kernels of ReconNet's layers: NHWC fp16 tensors, fp32 accumulation.

Four kinds of pass do all of ReconNet's work (:mod:`isosr_net.fused_recon` runs them in order):

- :func:`pack_inputs`: the network's 10 input channels (the 8 inputs and the warped previous
  output's mask and AO) as one (B, H', W', 16) fp16 tensor, the frame replicate-padded to
  H' x W' as :class:`~isosr_net.reconnet.ReconNet` pads it, channels 10-15 zero; the previous
  output warped by the flow in the same pass where it is given unwarped.
- :func:`conv3x3`: a 3x3 convolution (stride 1 or 2, zero padding) + bias as an implicit GEMM:
  per tile of ``BLOCK_M`` output pixels, one ``tl.dot`` per tap (K = input channels, N = output
  channels); in its epilogue a residual sum and the ReLU.
- :func:`upsample_add`: a decoder level's input ``relu(skip + reduce(bilinear_2x(coarse)))``,
  once per pixel, ``reduce`` the level's 1x1 convolution (ReconNet applies it before upsampling;
  the two commute). Computed in the convolution's loads instead, per tap, the last level took 1.7
  times as long on an H100 at 4K (1.40 ms against 0.30 + 0.50 with this pass); the reduction as a second
  ``tl.dot`` in the coarser convolution's epilogue came out wrong from Triton 3.6 on an H100
  with 4 warps (64 channels), so it is here.
- :func:`recon_tail`: the 3x3 output convolution (6 channels, computed as 16) + bias and
  ReconNet's output: mask ``clamp(in + raw, 0, 1)``, normal ``in + raw``, depth passed through,
  AO ``sigmoid(raw)`` or, for a model over the input rays, ``sigmoid(logit(p) + raw)``
  (:func:`isosr_net.reconnet.ao_output`), written as the (B, 6, H, W) fp32 stack, cropped to the frame.

Importing this module compiles nothing; set ``TRITON_INTERPRET=1`` before importing it to run
the kernels on CPU tensors (Triton's interpreter, for tests). No kernel syncs with the host or
allocates beyond its output, so a CUDA graph can capture them (after autotuning, which the first
call per shape does).
"""

from __future__ import annotations

import os

import torch
import triton
import triton.language as tl

from isosr_render.conventions import AO, DEPTH, MASK, SAMPLED_AO, SAMPLING
from isosr_render.shapes import check_shape
from isosr_net.reconnet import INPUTS, OUTPUTS, ReconNetConfig

INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
PACKED = 16  # channels of the packed input: 10 used, padded to tl.dot's smallest K
# Pixels per program and warps, autotuned per shape; the interpreter takes the first (FIXED).
CONFIGS = [triton.Config({"BLOCK_M": m}, num_warps=w) for m, w in ((64, 4), (32, 2), (128, 4), (128, 8), (256, 8))]
FIXED = dict(CONFIGS[0].kwargs) if INTERPRET else {}
PACK_BLOCK = 128


def _tuned(kernel, key: list[str]):
    return kernel if INTERPRET else triton.autotune(CONFIGS, key=key)(kernel)


@triton.jit
def _pack_kernel(inp_ptr, prev_ptr, flow_ptr, out_ptr, h, w, hp, wp,
                 si_b, si_c, si_h, si_w, sp_b, sp_c, sp_h, sp_w, sf_b, sf_c, sf_h, sf_w,
                 WARP: tl.constexpr, N_IN: tl.constexpr, PREV_MASK: tl.constexpr, PREV_AO: tl.constexpr,
                 C: tl.constexpr, BLOCK: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = offs < hp * wp
    y = tl.minimum(offs // wp, h - 1)  # replicate padding: bottom rows and right columns repeat
    x = tl.minimum(offs % wp, w - 1)
    c = tl.arange(0, C)[None, :]
    vals = tl.load(inp_ptr + b * si_b + c * si_c + (y * si_h + x * si_w)[:, None],
                   mask=valid[:, None] & (c < N_IN), other=0.0).to(tl.float32)
    recurrent = (c >= N_IN) & (c < N_IN + 2)
    channel = tl.where(c == N_IN, PREV_MASK, PREV_AO) * sp_c
    if WARP:
        # Backward warp as isosr_net.flow_warp.warp_by_flow: previous(p + flow[p]), bilinear, zeros
        # outside. Positions far outside are clamped (all four taps stay outside) before the cast.
        fx = tl.load(flow_ptr + b * sf_b + y * sf_h + x * sf_w, mask=valid, other=0.0)
        fy = tl.load(flow_ptr + b * sf_b + sf_c + y * sf_h + x * sf_w, mask=valid, other=0.0)
        px = tl.minimum(tl.maximum(x.to(tl.float32) + fx, -2.0), w + 1.0)
        py = tl.minimum(tl.maximum(y.to(tl.float32) + fy, -2.0), h + 1.0)
        x0f, y0f = tl.floor(px), tl.floor(py)
        ax, ay = px - x0f, py - y0f
        x0, y0 = x0f.to(tl.int32), y0f.to(tl.int32)
        for corner in tl.static_range(4):
            xx = x0 + corner % 2
            yy = y0 + corner // 2
            weight = (ax if corner % 2 else 1.0 - ax) * (ay if corner // 2 else 1.0 - ay)
            inside = valid & (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            tap = tl.load(prev_ptr + b * sp_b + channel + (yy * sp_h + xx * sp_w)[:, None],
                          mask=inside[:, None] & recurrent, other=0.0)
            vals += weight[:, None] * tap.to(tl.float32)
    else:
        vals += tl.load(prev_ptr + b * sp_b + channel + (y * sp_h + x * sp_w)[:, None],
                        mask=valid[:, None] & recurrent, other=0.0).to(tl.float32)
    tl.store(out_ptr + b * hp * wp * C + offs[:, None] * C + c, vals.to(tl.float16), mask=valid[:, None])


@triton.jit
def _upsampled(c_ptr, b, yy, xx, hc, wc, sc_b, sc_c, sc_h, sc_w, ci):
    """``bilinear_2x(coarse)`` at pixels (yy, xx) of the upsampled image, channels ``ci``, fp32.

    Bilinear 2x with align_corners=False: full-res row Y reads coarse rows lo = (Y + 1) // 2 - 1
    and lo + 1, the second weighted 3/4 for even Y and 1/4 for odd Y, both clamped to the image
    (so row 0 reads row 0 alone), as F.interpolate does; the same along columns. A tile's pixels
    past the end read clamped rows too.
    """
    ylo = (yy + 1) // 2 - 1
    xlo = (xx + 1) // 2 - 1
    y0 = tl.minimum(tl.maximum(ylo, 0), hc - 1)
    x0 = tl.minimum(tl.maximum(xlo, 0), wc - 1)
    y1 = tl.minimum(tl.maximum(ylo + 1, 0), hc - 1)
    x1 = tl.minimum(tl.maximum(xlo + 1, 0), wc - 1)
    wy = (0.75 - 0.5 * (yy % 2).to(tl.float32))[:, None]
    wx = (0.75 - 0.5 * (xx % 2).to(tl.float32))[:, None]
    base = c_ptr + b * sc_b + ci[None, :] * sc_c
    # Every index is clamped inside the coarse image, so the loads need no mask.
    v00 = tl.load(base + (y0 * sc_h + x0 * sc_w)[:, None]).to(tl.float32)
    v01 = tl.load(base + (y0 * sc_h + x1 * sc_w)[:, None]).to(tl.float32)
    v10 = tl.load(base + (y1 * sc_h + x0 * sc_w)[:, None]).to(tl.float32)
    v11 = tl.load(base + (y1 * sc_h + x1 * sc_w)[:, None]).to(tl.float32)
    return (1.0 - wy) * ((1.0 - wx) * v00 + wx * v01) + wy * ((1.0 - wx) * v10 + wx * v11)


@triton.jit
def _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hi, wi, STRIDE: tl.constexpr, CI: tl.constexpr,
              CO: tl.constexpr, BLOCK_M: tl.constexpr):
    """The 3x3 convolution plus bias at output pixels (y, x) of the NHWC (B, hi, wi, CI) input, fp32 (BLOCK_M, CO)."""
    ci = tl.arange(0, CI)
    co = tl.arange(0, CO)
    acc = tl.zeros((BLOCK_M, CO), dtype=tl.float32)
    for tap in tl.static_range(9):
        yy = y * STRIDE + (tap // 3 - 1)
        xx = x * STRIDE + (tap % 3 - 1)
        inside = valid & (yy >= 0) & (yy < hi) & (xx >= 0) & (xx < wi)
        a = tl.load(x_ptr + b * hi * wi * CI + ((yy * wi + xx) * CI)[:, None] + ci[None, :],
                    mask=inside[:, None], other=0.0)
        weights = tl.load(w_ptr + tap * CI * CO + ci[:, None] * CO + co[None, :])
        acc = tl.dot(a, weights, acc)
    return acc + tl.load(bias_ptr + co)[None, :]


@triton.jit
def _conv_kernel(x_ptr, w_ptr, bias_ptr, out_ptr, res_ptr, hi, wi, ho, wo, STRIDE: tl.constexpr,
                 RESIDUAL: tl.constexpr, RELU: tl.constexpr, CI: tl.constexpr, CO: tl.constexpr,
                 BLOCK_M: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < ho * wo
    y = offs // wo
    x = offs % wo
    acc = _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hi, wi, STRIDE, CI, CO, BLOCK_M)
    co = tl.arange(0, CO)
    if RESIDUAL:
        acc += tl.load(res_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], mask=valid[:, None],
                       other=0.0).to(tl.float32)
    if RELU:
        acc = tl.maximum(acc, 0.0)
    tl.store(out_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], acc.to(tl.float16), mask=valid[:, None])


@triton.jit
def _upsample_add_kernel(x_ptr, c_ptr, rw_ptr, rb_ptr, out_ptr, hp, wp, hc, wc, sc_b, sc_c, sc_h, sc_w,
                         C: tl.constexpr, CC: tl.constexpr, BLOCK: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = offs < hp * wp
    ci = tl.arange(0, C)
    up = _upsampled(c_ptr, b, offs // wp, offs % wp, hc, wc, sc_b, sc_c, sc_h, sc_w, tl.arange(0, CC))
    reduced = tl.dot(up.to(tl.float16), tl.load(rw_ptr + tl.arange(0, CC)[:, None] * C + ci[None, :]))
    pixel = b * hp * wp * C + offs[:, None] * C + ci[None, :]
    skip = tl.load(x_ptr + pixel, mask=valid[:, None], other=0.0).to(tl.float32)
    out = tl.maximum(skip + reduced + tl.load(rb_ptr + ci)[None, :], 0.0)
    tl.store(out_ptr + pixel, out.to(tl.float16), mask=valid[:, None])


@triton.jit
def _tail_kernel(x_ptr, w_ptr, bias_ptr, inp_ptr, out_ptr, h, w, hp, wp, si_b, si_c, si_h, si_w, ray_scale,
                 MASK_C: tl.constexpr, DEPTH_C: tl.constexpr, AO_C: tl.constexpr, RAYS_C: tl.constexpr,
                 SAMPLING_C: tl.constexpr, AO_PRIOR: tl.constexpr, OUT: tl.constexpr,
                 CI: tl.constexpr, CO: tl.constexpr, BLOCK_M: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < h * w
    y = offs // w
    x = offs % w
    raw = _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hp, wp, 1, CI, CO, BLOCK_M)
    c = tl.arange(0, CO)[None, :]
    # The inputs' first channels are the output's (mask, normal, depth), in the same order; the
    # channels other than mask, depth and AO are the normal's.
    given = tl.load(inp_ptr + b * si_b + c * si_c + (y * si_h + x * si_w)[:, None],
                    mask=valid[:, None] & (c < AO_C), other=0.0).to(tl.float32)
    ao = tl.sigmoid(raw)
    if AO_PRIOR:  # sigmoid(logit(p) + raw) = p / (p + (1 - p) exp(-raw)), p in (0, 1)
        pixel = b * si_b + y * si_h + x * si_w
        rays = tl.load(inp_ptr + pixel + RAYS_C * si_c, mask=valid, other=0.0).to(tl.float32)
        n = (tl.load(inp_ptr + pixel + SAMPLING_C * si_c, mask=valid, other=0.0).to(tl.float32)
             * tl.load(inp_ptr + pixel + (SAMPLING_C + 1) * si_c, mask=valid, other=0.0).to(tl.float32) * ray_scale)
        p = ((n * rays + 0.5) / (n + 1.0))[:, None]
        ao = tl.minimum(p / (p + (1.0 - p) * tl.exp(-raw)), 1.0)  # fast division: p / p can pass 1
    out = tl.where(c == MASK_C, tl.minimum(tl.maximum(given + raw, 0.0), 1.0),
                   tl.where(c == DEPTH_C, given, tl.where(c == AO_C, ao, given + raw)))
    tl.store(out_ptr + b * OUT * h * w + c * h * w + offs[:, None], out, mask=valid[:, None] & (c < OUT))


_conv_tuned = _tuned(_conv_kernel, ["ho", "wo", "STRIDE", "CI", "CO"])
_tail_tuned = _tuned(_tail_kernel, ["hp", "wp"])


def _grid(pixels: int, batch: int):
    return lambda meta: (triton.cdiv(pixels, meta["BLOCK_M"]), batch)


def _check_taps(weight: torch.Tensor, bias: torch.Tensor, ci: int, where: str) -> int:
    """Check tap-major weights (9, CI, CO) fp16 and a (CO,) fp32 bias; returns CO."""
    dims = check_shape(weight, f"(9, {ci}, CO)", "weight", where)
    check_shape(bias, "(CO)", "bias", where, dims)
    _check_dtypes(weight, bias, where)
    return dims["CO"]


def _check_dtypes(weight: torch.Tensor, bias: torch.Tensor, where: str) -> None:
    """Weights as the kernels read them: contiguous fp16, the bias fp32."""
    if weight.dtype != torch.float16 or bias.dtype != torch.float32 or not weight.is_contiguous():
        raise ValueError(f"{where}: weight must be contiguous fp16 and bias fp32, got {weight.dtype}, {bias.dtype}")


def _check_nhwc(x: torch.Tensor, name: str, where: str) -> dict[str, int]:
    dims = check_shape(x, "(B, H, W, C)", name, where)
    if x.dtype != torch.float16 or not x.is_contiguous():
        raise ValueError(f"{where}: {name} must be a contiguous fp16 NHWC tensor, got {x.dtype}")
    return dims


def pack_inputs(inputs: torch.Tensor, prev: torch.Tensor, flow: torch.Tensor | None = None,
                multiple: int = 8) -> torch.Tensor:
    """ReconNet's 10 input channels packed, replicate-padded to multiples of ``multiple``, fp16 NHWC.

    Args:
        inputs: the 8 input channels (:data:`isosr_render.conventions.RECON_CHANNELS`), any layout.
        prev: the previous output; warped already if ``flow`` is None, else warped here by ``flow``.
        flow: backward flow in pixels (:func:`isosr_net.flow_warp.warp_by_flow`), or None.

    Shape:
        inputs: (B, 8, H, W). prev: (B, 6, H, W). flow: (B, 2, H, W). Returns (B, H', W', 16):
        channels 0-7 the inputs, 8 and 9 the previous mask and AO, 10-15 zero.
    """
    dims = check_shape(inputs, f"(B, {INPUTS}, H, W)", "inputs", "pack_inputs")
    check_shape(prev, "(B, 6, H, W)", "prev", "pack_inputs", dims)
    if flow is not None:
        check_shape(flow, "(B, 2, H, W)", "flow", "pack_inputs", dims)
        if flow.dtype != torch.float32:
            raise ValueError(f"pack_inputs: flow must be float32, got {flow.dtype}")
    b, h, w = dims["B"], dims["H"], dims["W"]
    hp, wp = h + -h % multiple, w + -w % multiple
    out = inputs.new_empty((b, hp, wp, PACKED), dtype=torch.float16)
    strides_f = flow.stride() if flow is not None else (0, 0, 0, 0)
    _pack_kernel[(triton.cdiv(hp * wp, PACK_BLOCK), b)](
        inputs, prev, inputs if flow is None else flow, out, h, w, hp, wp, *inputs.stride(), *prev.stride(),
        *strides_f, WARP=flow is not None, N_IN=INPUTS, PREV_MASK=MASK.start, PREV_AO=AO.start, C=PACKED,
        BLOCK=PACK_BLOCK)
    return out


def conv3x3(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, *, stride: int = 1, relu: bool = True,
            residual: torch.Tensor | None = None) -> torch.Tensor:
    """``relu(conv3x3(x) + bias + residual)``: zero padding; the ReLU and residual where asked.

    Args:
        x: NHWC fp16 (contiguous).
        weight: tap-major weights, ``weight[3 * ky + kx, ci, co]``, fp16 (:func:`isosr_net.fused_recon.tap_weights`).
        bias: fp32.
        stride: 1, or 2 (the output has half the sides, even sides asked).
        relu: the ReLU, after the residual sum.
        residual: NHWC fp16 (contiguous), added before the ReLU.

    Shape:
        x: (B, H, W, CI). weight: (9, CI, CO). bias: (CO,). residual: (B, H/s, W/s, CO).
        Returns (B, H/s, W/s, CO), fp16. CI and CO powers of 2, at least 16.
    """
    dims = _check_nhwc(x, "x", "conv3x3")
    b, hi, wi, ci = dims["B"], dims["H"], dims["W"], dims["C"]
    co = _check_taps(weight, bias, ci, "conv3x3")
    if stride not in (1, 2):
        raise ValueError(f"conv3x3: stride must be 1 or 2, got {stride}")
    if stride == 2 and (hi % 2 or wi % 2):
        raise ValueError(f"conv3x3: x must have even sides for stride 2, got {hi}x{wi}")
    ho, wo = hi // stride, wi // stride
    if residual is not None:
        _check_nhwc(residual, "residual", "conv3x3")
        check_shape(residual, f"({b}, {ho}, {wo}, {co})", "residual", "conv3x3")
    out = x.new_empty((b, ho, wo, co))
    _conv_tuned[_grid(ho * wo, b)](x, weight, bias, out, x if residual is None else residual, hi, wi, ho, wo,
                                   STRIDE=stride, RESIDUAL=residual is not None, RELU=relu, CI=ci, CO=co, **FIXED)
    return out


def upsample_add(x: torch.Tensor, coarse: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``relu(x + conv1x1(bilinear_2x(coarse)))`` (``F.interpolate``, align_corners=False), fp16 NHWC.

    Args:
        x: NHWC fp16 (contiguous), even sides.
        coarse: half-resolution features, any layout (NHWC reads fastest), any float dtype.
        weight, bias: the 1x1 convolution, ``weight[cc, c]`` fp16 (contiguous), bias fp32.

    Shape:
        x: (B, H, W, C). coarse: (B, CC, H/2, W/2). weight: (CC, C). bias: (C,). Returns
        (B, H, W, C). C and CC powers of 2, at least 16.
    """
    dims = _check_nhwc(x, "x", "upsample_add")
    b, hp, wp, c = dims["B"], dims["H"], dims["W"], dims["C"]
    if hp % 2 or wp % 2:
        raise ValueError(f"upsample_add: x must have even sides, got {hp}x{wp}")
    cc = check_shape(coarse, f"({b}, CC, {hp // 2}, {wp // 2})", "coarse", "upsample_add")["CC"]
    check_shape(weight, f"({cc}, {c})", "weight", "upsample_add")
    check_shape(bias, f"({c})", "bias", "upsample_add")
    _check_dtypes(weight, bias, "upsample_add")
    out = torch.empty_like(x)
    _upsample_add_kernel[(triton.cdiv(hp * wp, PACK_BLOCK), b)](x, coarse, weight, bias, out, hp, wp, hp // 2, wp // 2,
                                                               *coarse.stride(), C=c, CC=cc, BLOCK=PACK_BLOCK)
    return out


def recon_tail(y: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, inputs: torch.Tensor,
               config: ReconNetConfig) -> torch.Tensor:
    """ReconNet's output convolution and output stack, cropped to the frame.

    Args:
        y: the last decoder level's features, NHWC fp16, padded past the frame.
        weight, bias: the output convolution as for :func:`conv3x3`, CO padded to 16 (6 used).
        inputs: the network's inputs (mask, normal and depth read; with ``config.ao_prior``
            "rays" the sampled AO and the sampling channels too), any layout.
        config: the network's config (its AO prior and ray limits, as :func:`~isosr_net.reconnet.ao_output`).

    Shape:
        y: (B, H', W', CI). weight: (9, CI, 16). bias: (16,). inputs: (B, 8, H, W), H <= H', W <= W'.
        Returns (B, 6, H, W), fp32: mask, normal, depth, AO.
    """
    dims = _check_nhwc(y, "y", "recon_tail")
    b, hp, wp, ci = dims["B"], dims["H"], dims["W"], dims["C"]
    co = _check_taps(weight, bias, ci, "recon_tail")
    h, w = (check_shape(inputs, f"({b}, {INPUTS}, H, W)", "inputs", "recon_tail")[k] for k in "HW")
    if h > hp or w > wp:
        raise ValueError(f"recon_tail: inputs are {h}x{w}, larger than the features' {hp}x{wp}")
    out = torch.empty((b, OUTPUTS, h, w), device=y.device, dtype=torch.float32)
    _tail_tuned[_grid(h * w, b)](y, weight, bias, inputs, out, h, w, hp, wp, *inputs.stride(),
                                 float(config.max_ao_rays * config.max_spp), MASK_C=MASK.start, DEPTH_C=DEPTH.start,
                                 AO_C=AO.start, RAYS_C=SAMPLED_AO.start, SAMPLING_C=SAMPLING.start,
                                 AO_PRIOR=config.ao_prior == "rays", OUT=OUTPUTS, CI=ci, CO=co, **FIXED)
    return out
