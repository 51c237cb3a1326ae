"""Triton kernels of ReconNet's layers: NHWC fp16 tensors, fp32 accumulation.

Four kinds of pass do all of ReconNet's work (:mod:`isosr_net.fused_recon` runs them in order):

- :func:`pack_inputs`: the network's input channels (the 8 inputs, read in place where they
  lie, :class:`ReconSources`, and the warped previous output's mask and AO; for a model that
  upscales x2, those two of the previous output's 2x2 pixels per input pixel, space-to-depth) as
  one (B, H', W', 16) fp16 tensor, the frame replicate-padded to H' x W' as
  :class:`~isosr_net.reconnet.ReconNet` pads it, unused channels zero; the previous output warped
  by the flow (upsampled for x2) in the same pass where it is given unwarped (or a first frame's
  stand-in made there); and, on the way, the input checks (:data:`~isosr_net.inference.FRAME_FLAGS`):
  one value per program, reduced by one small kernel, read by the host once per frame.
- :func:`conv3x3`: a 3x3 convolution (stride 1 or 2, zero padding) + bias as an implicit GEMM:
  per tile of ``BLOCK_M`` output pixels, one ``tl.dot`` per tap (K = input channels, N = output
  channels); in its epilogue a residual sum and the ReLU.
- :func:`upsample_add`: a decoder level's input ``relu(skip + reduce(bilinear_2x(coarse)))``,
  once per pixel, ``reduce`` the level's 1x1 convolution (ReconNet applies it before upsampling;
  the two commute). Computed in the convolution's loads instead, per tap, the last level took 1.7
  times as long on an H100 at 4K (1.40 ms against 0.30 + 0.50 with this pass); the reduction as a second
  ``tl.dot`` in the coarser convolution's epilogue came out wrong from Triton 3.6 on an H100
  with 4 warps (64 channels), so it is here.
- :func:`recon_tail`: the 3x3 output convolution (6 channels, computed as 16; x2 and a stem of stride 2:
  24 as 32, written depth-to-space) + bias and ReconNet's output over its inputs (x2: upsampled,
  :func:`~isosr_net.reconnet.upsampled_inputs`): mask ``clamp(in + raw, 0, 1)``, normal ``in + raw``,
  depth passed through, AO ``sigmoid(raw)`` or, for a model over the input rays, ``sigmoid(logit(p) +
  raw)`` (:func:`isosr_net.reconnet.ao_output`), ``raw`` first corrected by a ``pixel_tail`` model's
  per-pixel MLP (:class:`PixelTail`, reading the pack's channels of the pixel), written as the (B, 6,
  sH, sW) fp32 stack, cropped to the frame; or as the output buffers' stack
  (:func:`isosr_net.inference.buffer_stack`) and shaded (:func:`isosr_render.shading.shade`), the
  frame's last work, in the same pass.

Tensors store their own channels; a tile holds :func:`kernel_width` of them (a power of 2, at least
16: ``tl.dot``'s smallest K and N), the loads and stores masked past the stored ones and the weights
zero-padded, so a network of 8 full-resolution channels moves 8 a pixel through memory.

Importing this module compiles nothing; set ``TRITON_INTERPRET=1`` before importing it to run
the kernels on CPU tensors (Triton's interpreter, for tests). No kernel syncs with the host or
allocates beyond its output, so a CUDA graph can capture them (after autotuning, which the first
call per shape does).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import torch
import triton
import triton.language as tl
import triton.testing

from isosr_render.conventions import AO, DEPTH, MASK, NORMAL, SAMPLED_AO, SAMPLING
from isosr_render.shading import ShadingParams, light_and_half
from isosr_render.shapes import check_shape
from isosr_net.fused_recon import FUSED_UPSCALES, MAX_KERNEL_WIDTH, PACKED, kernel_width
from isosr_net.inference import FRAME_FLAGS
from isosr_net.reconnet import FIRST_FRAME_MODES, INPUTS, OUTPUTS, ReconNetConfig

INTERPRET = os.environ.get("TRITON_INTERPRET") == "1"
# Pixels per program and warps, autotuned per layer and size class (a frame's pixels' bit length: a
# new window size of a class tunes nothing, so a viewer resizing cannot stall the GPU with tuning;
# a batch of frames takes one frame's config, its grid a row of programs per frame, so a new batch
# size tunes nothing either: keyed on the batch's pixels, each new size tuned every layer while its
# sessions waited, 13% of the device thread at 16 sessions on an H200,
# benchmarks/results/profile_server_reconstruct_16_cuda.json); the interpreter takes the first (FIXED).
CONFIGS = [triton.Config({"BLOCK_M": m}, num_warps=w) for m, w in ((64, 4), (32, 2), (128, 4), (128, 8), (256, 8))]
FIXED = dict(CONFIGS[0].kwargs) if INTERPRET else {}
PACK_BLOCK = 128
# How the pack gets the previous output's mask and AO: as given (warped already), warped by the
# flow, or a first frame's stand-in (ReconNet.first_previous: from the inputs, or zeros).
PREV_GIVEN, PREV_WARP, PREV_INPUTS, PREV_ZEROS = (tl.constexpr(i) for i in range(4))


def _tuned(kernel, key: list[str]):
    """``kernel`` autotuned over CONFIGS per ``key``: each config timed for 20 ms (Triton's default
    125 ms a config stalled a new size class for seconds), the choice kept in Triton's disk cache
    (a later process on the machine tunes nothing)."""
    return kernel if INTERPRET else triton.autotune(CONFIGS, key=key, do_bench=_bench_briefly, cache_results=True)(kernel)


def _bench_briefly(kernel_call, quantiles):
    return triton.testing.do_bench(kernel_call, warmup=5, rep=20, quantiles=quantiles)


@triton.jit
def _rows_and_channels(rows, c, C: tl.constexpr, CP: tl.constexpr):
    """The mask of a (rows, CP) tile of C stored channels: the rows alone where C fills the tile."""
    keep = rows[:, None]
    if C != CP:
        keep = keep & (c < C)[None, :]
    return keep


@triton.jit
def _load_channels(ptrs, c, C: tl.constexpr, CP: tl.constexpr):
    """A (pixels, CP) tile of C stored channels at ``ptrs``, zero past them (every pixel's address valid)."""
    if C == CP:
        v = tl.load(ptrs)
    else:
        v = tl.load(ptrs, mask=(c < C)[None, :], other=0.0)
    return v


@triton.jit
def _plane(ptr, sb, sh, sw, b, y, x, valid):
    """One source plane at pixels (y, x), fp32 (BLOCK,); 0 past ``valid``."""
    return tl.load(ptr + b * sb + y * sh + x * sw, mask=valid, other=0.0).to(tl.float32)


@triton.jit
def _taps_2x(yy, n):
    """Bilinear 2x along one axis (``F.interpolate``, align_corners=False): upsampled index ``yy``
    reads source indices lo = (yy + 1) // 2 - 1 and lo + 1, both clamped to [0, n), the second
    weighted 3/4 for even ``yy`` and 1/4 for odd (so index 0 reads index 0 alone). Returns
    ``(i0, i1, weight of i1)``."""
    lo = (yy + 1) // 2 - 1
    i0 = tl.minimum(tl.maximum(lo, 0), n - 1)
    i1 = tl.minimum(tl.maximum(lo + 1, 0), n - 1)
    return i0, i1, 0.75 - 0.5 * (yy % 2).to(tl.float32)


@triton.jit
def _plane_2x(ptr, sb, sh, sw, b, yy, xx, h, w, valid):
    """``bilinear_2x`` of one (h, w) source plane at pixels (yy, xx) of the upsampled image, fp32 (BLOCK,)."""
    y0, y1, wy = _taps_2x(yy, h)
    x0, x1, wx = _taps_2x(xx, w)
    top = (1.0 - wx) * _plane(ptr, sb, sh, sw, b, y0, x0, valid) + wx * _plane(ptr, sb, sh, sw, b, y0, x1, valid)
    bottom = (1.0 - wx) * _plane(ptr, sb, sh, sw, b, y1, x0, valid) + wx * _plane(ptr, sb, sh, sw, b, y1, x1, valid)
    return (1.0 - wy) * top + wy * bottom


@triton.jit
def _base_plane(ptr, sb, sh, sw, b, yy, xx, h, w, valid, S: tl.constexpr):
    """One input plane as an upscaling ReconNet's base holds it at output pixels (yy, xx): the plane
    itself (S 1), or bilinear 2x (:func:`isosr_net.reconnet.upsampled_inputs`), fp32 (BLOCK,)."""
    if S == 1:
        out = _plane(ptr, sb, sh, sw, b, yy, xx, valid)
    else:
        out = _plane_2x(ptr, sb, sh, sw, b, yy, xx, h, w, valid)
    return out


@triton.jit
def _column(tile, c, K: tl.constexpr):
    """Column K of a (BLOCK, C) tile, (BLOCK,)."""
    return tl.sum(tl.where(c == K, tile, 0.0), axis=1)


@triton.jit
def _not_finite(x):
    """1.0 where ``x`` is NaN or infinite (NaN fails every comparison)."""
    return tl.where(tl.abs(x) <= 3.4028234663852886e38, 0.0, 1.0)


@triton.jit
def _warped(prev_ptr, sp_b, sp_h, sp_w, b, x, y, fx, fy, h, w, valid):
    """One plane of the previous output backward-warped as isosr_net.flow_warp.warp_by_flow:
    previous(p + flow[p]), bilinear, zeros outside. Positions far outside are clamped (all four
    taps stay outside) before the cast."""
    px = tl.minimum(tl.maximum(x.to(tl.float32) + fx, -2.0), w + 1.0)
    py = tl.minimum(tl.maximum(y.to(tl.float32) + fy, -2.0), h + 1.0)
    x0f, y0f = tl.floor(px), tl.floor(py)
    ax, ay = px - x0f, py - y0f
    x0, y0 = x0f.to(tl.int32), y0f.to(tl.int32)
    out = tl.zeros_like(px)
    for corner in tl.static_range(4):
        xx = x0 + corner % 2
        yy = y0 + corner // 2
        weight = (ax if corner % 2 else 1.0 - ax) * (ay if corner // 2 else 1.0 - ay)
        inside = valid & (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
        out += weight * tl.load(prev_ptr + b * sp_b + yy * sp_h + xx * sp_w, mask=inside, other=0.0).to(tl.float32)
    return out


@triton.jit
def _pack_kernel(m_ptr, sm_b, sm_c, sm_h, sm_w, n_ptr, sn_b, sn_c, sn_h, sn_w, d_ptr, sd_b, sd_c, sd_h, sd_w,
                 a_ptr, sa_b, sa_c, sa_h, sa_w, s_ptr, ss_b, ss_c, ss_h, ss_w,
                 prev_ptr, sp_b, sp_c, sp_h, sp_w, flow_ptr, sf_b, sf_c, sf_h, sf_w, out_ptr, flags_ptr,
                 h, w, hp, wp, PREV: tl.constexpr, HAS_AO: tl.constexpr, HAS_FLOW: tl.constexpr,
                 MASK_C: tl.constexpr, NORMAL_C: tl.constexpr, DEPTH_C: tl.constexpr, AO_C: tl.constexpr,
                 SAMPLING_C: tl.constexpr, PREV_MASK: tl.constexpr, PREV_AO: tl.constexpr, N_IN: tl.constexpr,
                 S: tl.constexpr, C: tl.constexpr, BLOCK: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = offs < hp * wp
    y = tl.minimum(offs // wp, h - 1)  # replicate padding: bottom rows and right columns repeat
    x = tl.minimum(offs % wp, w - 1)
    mask = _plane(m_ptr, sm_b, sm_h, sm_w, b, y, x, valid)
    nx = _plane(n_ptr, sn_b, sn_h, sn_w, b, y, x, valid)
    ny = _plane(n_ptr + sn_c, sn_b, sn_h, sn_w, b, y, x, valid)
    nz = _plane(n_ptr + 2 * sn_c, sn_b, sn_h, sn_w, b, y, x, valid)
    depth = _plane(d_ptr, sd_b, sd_h, sd_w, b, y, x, valid)
    rays = tl.zeros((BLOCK,), dtype=tl.float32)
    if HAS_AO:
        rays = _plane(a_ptr, sa_b, sa_h, sa_w, b, y, x, valid)
    s0 = _plane(s_ptr, ss_b, ss_h, ss_w, b, y, x, valid)
    s1 = _plane(s_ptr + ss_c, ss_b, ss_h, ss_w, b, y, x, valid)
    # The input checks (FRAME_FLAGS), over this program's pixels: a flag per buffer that holds
    # NaN or Inf, one for AO outside [0, 1], and the largest finite |depth|.
    # Slot-major (a flag's values of all programs contiguous: their reduction reads rows).
    programs = tl.num_programs(0) * tl.num_programs(1)
    flags = flags_ptr + b * tl.num_programs(0) + tl.program_id(0)
    tl.store(flags + 0 * programs, tl.max(_not_finite(mask)))
    tl.store(flags + 1 * programs, tl.max(tl.maximum(tl.maximum(_not_finite(nx), _not_finite(ny)), _not_finite(nz))))
    tl.store(flags + 2 * programs, tl.max(_not_finite(depth)))
    tl.store(flags + 4 * programs, tl.max(tl.where((rays >= 0.0) & (rays <= 1.0), 0.0, 1.0)))
    tl.store(flags + 5 * programs, tl.max(tl.where(_not_finite(depth) == 0, tl.abs(depth), 0.0)))
    if HAS_FLOW:
        fx = _plane(flow_ptr, sf_b, sf_h, sf_w, b, y, x, valid)
        fy = _plane(flow_ptr + sf_c, sf_b, sf_h, sf_w, b, y, x, valid)
        tl.store(flags + 3 * programs, tl.max(tl.maximum(_not_finite(fx), _not_finite(fy))))
    else:
        tl.store(flags + 3 * programs, 0.0)
    c = tl.arange(0, C)[None, :]
    tile = tl.where(c == MASK_C, mask[:, None], tl.where(c == NORMAL_C, nx[:, None],
           tl.where(c == NORMAL_C + 1, ny[:, None], tl.where(c == NORMAL_C + 2, nz[:, None],
           tl.where(c == DEPTH_C, depth[:, None], tl.where(c == AO_C, rays[:, None],
           tl.where(c == SAMPLING_C, s0[:, None], tl.where(c == SAMPLING_C + 1, s1[:, None], 0.0))))))))
    # The previous output's mask and AO at the S x S output pixels of each input pixel, ordered as
    # F.pixel_unshuffle orders them: channel N_IN + S * S * k + cell, k 0 for the mask, 1 for AO.
    for cell in tl.static_range(S * S):
        yy = y * S + cell // S
        xx = x * S + cell % S
        prev_mask = tl.zeros((BLOCK,), dtype=tl.float32)
        prev_ao = tl.zeros((BLOCK,), dtype=tl.float32)
        if PREV == PREV_WARP:
            fxs = fx
            fys = fy
            if S == 2:  # isosr_net.flow_warp.upscale_flow: bilinear, the lengths doubled
                fxs = 2.0 * _plane_2x(flow_ptr, sf_b, sf_h, sf_w, b, yy, xx, h, w, valid)
                fys = 2.0 * _plane_2x(flow_ptr + sf_c, sf_b, sf_h, sf_w, b, yy, xx, h, w, valid)
            prev_mask = _warped(prev_ptr + PREV_MASK * sp_c, sp_b, sp_h, sp_w, b, xx, yy, fxs, fys, S * h, S * w,
                                valid)
            prev_ao = _warped(prev_ptr + PREV_AO * sp_c, sp_b, sp_h, sp_w, b, xx, yy, fxs, fys, S * h, S * w, valid)
        elif PREV == PREV_GIVEN:
            prev_mask = _plane(prev_ptr + PREV_MASK * sp_c, sp_b, sp_h, sp_w, b, yy, xx, valid)
            prev_ao = _plane(prev_ptr + PREV_AO * sp_c, sp_b, sp_h, sp_w, b, yy, xx, valid)
        elif PREV == PREV_INPUTS:  # ReconNet.first_previous: the (upsampled) mask, and the rays' AO where cast
            prev_mask = _base_plane(m_ptr, sm_b, sm_h, sm_w, b, yy, xx, h, w, valid, S)
            cast = _base_plane(s_ptr, ss_b, ss_h, ss_w, b, yy, xx, h, w, valid, S) > 0
            rays_here = tl.zeros((BLOCK,), dtype=tl.float32)
            if HAS_AO:
                rays_here = _base_plane(a_ptr, sa_b, sa_h, sa_w, b, yy, xx, h, w, valid, S)
            prev_ao = tl.where(cast, rays_here, prev_mask)
        tile = tl.where(c == N_IN + cell, prev_mask[:, None],
                        tl.where(c == N_IN + S * S + cell, prev_ao[:, None], tile))
    tl.store(out_ptr + b * hp * wp * C + offs[:, None] * C + c, tile.to(tl.float16), mask=valid[:, None])


@triton.jit
def _upsampled(c_ptr, b, yy, xx, hc, wc, sc_b, sc_c, sc_h, sc_w, ci, CC: tl.constexpr, CCP: tl.constexpr):
    """``bilinear_2x(coarse)`` at pixels (yy, xx) of the upsampled image, channels ``ci`` (CCP, CC stored), fp32
    (:func:`_taps_2x` along each axis). A tile's pixels past the end read clamped rows too."""
    y0, y1, wy = _taps_2x(yy, hc)
    x0, x1, wx = _taps_2x(xx, wc)
    wy, wx = wy[:, None], wx[:, None]
    base = c_ptr + b * sc_b + ci[None, :] * sc_c
    # Every index is clamped inside the coarse image, so the loads mask no pixel.
    v00 = _load_channels(base + (y0 * sc_h + x0 * sc_w)[:, None], ci, CC, CCP).to(tl.float32)
    v01 = _load_channels(base + (y0 * sc_h + x1 * sc_w)[:, None], ci, CC, CCP).to(tl.float32)
    v10 = _load_channels(base + (y1 * sc_h + x0 * sc_w)[:, None], ci, CC, CCP).to(tl.float32)
    v11 = _load_channels(base + (y1 * sc_h + x1 * sc_w)[:, None], ci, CC, CCP).to(tl.float32)
    return (1.0 - wy) * ((1.0 - wx) * v00 + wx * v01) + wy * ((1.0 - wx) * v10 + wx * v11)


@triton.jit
def _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hi, wi, STRIDE: tl.constexpr, CI: tl.constexpr,
              CIP: tl.constexpr, COP: tl.constexpr, BLOCK_M: tl.constexpr):
    """The 3x3 convolution plus bias at output pixels (y, x) of the NHWC (B, hi, wi, CI) input, fp32 (BLOCK_M, COP);
    the weights (9, CIP, COP) and bias (COP,) zero-padded."""
    ci = tl.arange(0, CIP)
    co = tl.arange(0, COP)
    acc = tl.zeros((BLOCK_M, COP), dtype=tl.float32)
    for tap in tl.static_range(9):
        yy = y * STRIDE + (tap // 3 - 1)
        xx = x * STRIDE + (tap % 3 - 1)
        inside = valid & (yy >= 0) & (yy < hi) & (xx >= 0) & (xx < wi)
        a = tl.load(x_ptr + b * hi * wi * CI + ((yy * wi + xx) * CI)[:, None] + ci[None, :],
                    mask=_rows_and_channels(inside, ci, CI, CIP), other=0.0)
        weights = tl.load(w_ptr + tap * CIP * COP + ci[:, None] * COP + co[None, :])
        acc = tl.dot(a, weights, acc)
    return acc + tl.load(bias_ptr + co)[None, :]


@triton.jit
def _conv_kernel(x_ptr, w_ptr, bias_ptr, out_ptr, res_ptr, hi, wi, ho, wo, size_class, STRIDE: tl.constexpr,
                 RESIDUAL: tl.constexpr, RELU: tl.constexpr, CI: tl.constexpr, CO: tl.constexpr,
                 CIP: tl.constexpr, COP: tl.constexpr, BLOCK_M: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < ho * wo
    y = offs // wo
    x = offs % wo
    acc = _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hi, wi, STRIDE, CI, CIP, COP, BLOCK_M)
    co = tl.arange(0, COP)
    stored = _rows_and_channels(valid, co, CO, COP)
    if RESIDUAL:
        acc += tl.load(res_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], mask=stored,
                       other=0.0).to(tl.float32)
    if RELU:
        acc = tl.maximum(acc, 0.0)
    tl.store(out_ptr + b * ho * wo * CO + offs[:, None] * CO + co[None, :], acc.to(tl.float16), mask=stored)


@triton.jit
def _upsample_add_kernel(x_ptr, c_ptr, rw_ptr, rb_ptr, out_ptr, hp, wp, hc, wc, sc_b, sc_c, sc_h, sc_w,
                         C: tl.constexpr, CC: tl.constexpr, CP: tl.constexpr, CCP: tl.constexpr,
                         BLOCK: tl.constexpr):
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    valid = offs < hp * wp
    ci, cc = tl.arange(0, CP), tl.arange(0, CCP)
    up = _upsampled(c_ptr, b, offs // wp, offs % wp, hc, wc, sc_b, sc_c, sc_h, sc_w, cc, CC, CCP)
    reduced = tl.dot(up.to(tl.float16), tl.load(rw_ptr + cc[:, None] * CP + ci[None, :]))
    pixel = b * hp * wp * C + offs[:, None] * C + ci[None, :]
    stored = _rows_and_channels(valid, ci, C, CP)
    skip = tl.load(x_ptr + pixel, mask=stored, other=0.0).to(tl.float32)
    out = tl.maximum(skip + reduced + tl.load(rb_ptr + ci)[None, :], 0.0)
    tl.store(out_ptr + pixel, out.to(tl.float16), mask=stored)


@triton.jit
def _pixel_mlp(row_ptrs, here, raw_mask, raw_nx, raw_ny, raw_nz, raw_depth, raw_ao, t1r_ptr, t1p_ptr, t1b_ptr, t2_ptr,
               t2b_ptr, MASK_C: tl.constexpr, NORMAL_C: tl.constexpr, DEPTH_C: tl.constexpr, AO_C: tl.constexpr,
               HID: tl.constexpr, PC: tl.constexpr):
    """A pixel tail's correction (:class:`PixelTail`), (BLOCK, PC), its first 6 columns used: the second layer of
    the ReLU of the first's of the pixel's PC packed channels (at ``row_ptrs``) and its 6 raw outputs."""
    j = tl.arange(0, PC)
    hid = tl.arange(0, HID)
    row = tl.load(row_ptrs + j[None, :], mask=here[:, None], other=0.0)
    hidden = tl.dot(row, tl.load(t1p_ptr + j[:, None] * HID + hid[None, :])) + tl.load(t1b_ptr + hid)[None, :]
    hidden += raw_mask[:, None] * tl.load(t1r_ptr + MASK_C * HID + hid)[None, :]
    hidden += raw_nx[:, None] * tl.load(t1r_ptr + NORMAL_C * HID + hid)[None, :]
    hidden += raw_ny[:, None] * tl.load(t1r_ptr + (NORMAL_C + 1) * HID + hid)[None, :]
    hidden += raw_nz[:, None] * tl.load(t1r_ptr + (NORMAL_C + 2) * HID + hid)[None, :]
    hidden += raw_depth[:, None] * tl.load(t1r_ptr + DEPTH_C * HID + hid)[None, :]
    hidden += raw_ao[:, None] * tl.load(t1r_ptr + AO_C * HID + hid)[None, :]
    hidden = tl.maximum(hidden, 0.0).to(tl.float16)
    return tl.dot(hidden, tl.load(t2_ptr + hid[:, None] * PC + j[None, :])) + tl.load(t2b_ptr + j)[None, :]


@triton.jit
def _tail_kernel(x_ptr, w_ptr, bias_ptr, m_ptr, sm_b, sm_c, sm_h, sm_w, n_ptr, sn_b, sn_c, sn_h, sn_w,
                 d_ptr, sd_b, sd_c, sd_h, sd_w, a_ptr, sa_b, sa_c, sa_h, sa_w, s_ptr, ss_b, ss_c, ss_h, ss_w,
                 out_ptr, color_ptr, g_ptr, p_ptr, t1r_ptr, t1p_ptr, t1b_ptr, t2_ptr, t2b_ptr,
                 h, w, gh, gw, hp, wp, size_class, ray_scale, blend_rays, ray_factor, z, z_past,
                 albedo_r, albedo_g, albedo_b, ambient,
                 diffuse, specular, shininess, light_x, light_y, light_z, half_x, half_y, half_z, back_r, back_g, back_b,
                 MASK_C: tl.constexpr, NORMAL_C: tl.constexpr, DEPTH_C: tl.constexpr, AO_C: tl.constexpr,
                 AO_PRIOR: tl.constexpr, BLEND: tl.constexpr, BLEND_MAP: tl.constexpr, BLEND_VARIANCE: tl.constexpr,
                 INTERVAL: tl.constexpr, GATED: tl.constexpr, PIXEL_TAIL: tl.constexpr, HID: tl.constexpr,
                 PC: tl.constexpr, MAX_SPP: tl.constexpr,
                 HAS_AO: tl.constexpr, BUFFERS: tl.constexpr,
                 SHADE: tl.constexpr, OUT: tl.constexpr, S: tl.constexpr, UP: tl.constexpr, CI: tl.constexpr,
                 CIP: tl.constexpr, CO: tl.constexpr, BLOCK_M: tl.constexpr):
    # A program's pixels are the first level's (gh x gw of the hp x wp features), each S x S output pixels; the
    # output UP times the input's sides (S = UP, or S = 2 and UP = 1: a stem of stride 2).
    b = tl.program_id(1).to(tl.int64)
    offs = tl.program_id(0) * BLOCK_M + tl.arange(0, BLOCK_M)
    valid = offs < gh * gw
    y = offs // gw
    x = offs % gw
    raw = _conv_acc(x_ptr, w_ptr, bias_ptr, b, y, x, valid, hp, wp, 1, CI, CIP, CO, BLOCK_M)
    c = tl.arange(0, CO)[None, :]
    if S == UP:  # depth passes through, one read a program's pixel (x2: nearest)
        depth_in = _plane(d_ptr, sd_b, sd_h, sd_w, b, y, x, valid)
    plane = UP * UP * h * w  # an output plane's pixels
    # Per output pixel (S x S per feature pixel: raw channel k * S * S + cell is channel k there, as
    # F.pixel_shuffle orders them), one plane at a time: the (upsampled) inputs plus the raw output.
    gate = tl.full((BLOCK_M,), 1.0, dtype=tl.float32)
    if GATED:  # the geometry corrections' factor at the frame's rays per pixel (reconnet.geometry_gate)
        share = _plane(s_ptr + ss_c, ss_b, ss_h, ss_w, b, y * 0, x * 0, valid)
        spp = tl.where(share == share, tl.minimum(tl.maximum(share * MAX_SPP, 1.0), MAX_SPP * 1.0), MAX_SPP * 1.0)
        index = tl.minimum(tl.maximum(tl.floor(spp + 0.5).to(tl.int32) - 1, 0), MAX_SPP - 1)  # NaN: the last
        gate = tl.load(g_ptr + index, mask=valid, other=1.0)
    for cell in tl.static_range(S * S):
        yy = y * S + cell // S
        xx = x * S + cell % S
        at = yy * (UP * w) + xx
        here = valid & (yy < UP * h) & (xx < UP * w)  # a stem's cells past an odd side: none
        raw_mask = _column(raw, c, MASK_C * S * S + cell)
        raw_nx = _column(raw, c, NORMAL_C * S * S + cell)
        raw_ny = _column(raw, c, (NORMAL_C + 1) * S * S + cell)
        raw_nz = _column(raw, c, (NORMAL_C + 2) * S * S + cell)
        raw_ao = _column(raw, c, AO_C * S * S + cell)
        if PIXEL_TAIL:  # ReconNet.correction: the MLP of the raw outputs and the pixel's packed channels (UP 1)
            at_packed = (b * hp * S + yy) * wp * S + xx  # the pack's pixels: S x S a feature pixel's
            corr = _pixel_mlp(p_ptr + at_packed[:, None] * PC, here, raw_mask, raw_nx, raw_ny, raw_nz,
                              _column(raw, c, DEPTH_C * S * S + cell), raw_ao, t1r_ptr, t1p_ptr, t1b_ptr, t2_ptr,
                              t2b_ptr, MASK_C, NORMAL_C, DEPTH_C, AO_C, HID, PC)
            j = tl.arange(0, PC)[None, :]
            raw_mask += _column(corr, j, MASK_C)
            raw_nx += _column(corr, j, NORMAL_C)
            raw_ny += _column(corr, j, NORMAL_C + 1)
            raw_nz += _column(corr, j, NORMAL_C + 2)
            raw_ao += _column(corr, j, AO_C)
        mask = _base_plane(m_ptr, sm_b, sm_h, sm_w, b, yy, xx, h, w, here, UP) + gate * raw_mask
        mask = tl.minimum(tl.maximum(mask, 0.0), 1.0)
        nx = _base_plane(n_ptr, sn_b, sn_h, sn_w, b, yy, xx, h, w, here, UP) + gate * raw_nx
        ny = _base_plane(n_ptr + sn_c, sn_b, sn_h, sn_w, b, yy, xx, h, w, here, UP) + gate * raw_ny
        nz = _base_plane(n_ptr + 2 * sn_c, sn_b, sn_h, sn_w, b, yy, xx, h, w, here, UP) + gate * raw_nz
        if S == UP:
            depth = depth_in
        else:  # a stem's cells are input pixels
            depth = _plane(d_ptr, sd_b, sd_h, sd_w, b, yy, xx, here)
        ao = tl.sigmoid(raw_ao)
        if AO_PRIOR:  # sigmoid(logit(p) + raw) = p / (p + (1 - p) exp(-raw)), p in (0, 1)
            rays = tl.zeros((BLOCK_M,), dtype=tl.float32)
            if HAS_AO:
                rays = _base_plane(a_ptr, sa_b, sa_h, sa_w, b, yy, xx, h, w, here, UP)
            n = (_base_plane(s_ptr, ss_b, ss_h, ss_w, b, yy, xx, h, w, here, UP)
                 * _base_plane(s_ptr + ss_c, ss_b, ss_h, ss_w, b, yy, xx, h, w, here, UP) * ray_scale)
            p = (n * rays + 0.5) / (n + 1.0)
            ao = tl.minimum(p / (p + (1.0 - p) * tl.exp(-raw_ao)), 1.0)  # fast division: p / p can pass 1
            if BLEND:  # the rays' mean and the network's AO by the rays each stands for (ao_output)
                k = blend_rays
                if BLEND_MAP:  # its per-pixel log-offset, in the rows past the outputs (fused_recon.tail_convolution)
                    k = blend_rays * tl.exp(_column(raw, c, OUT * S * S + cell))
                if BLEND_VARIANCE:  # the mean's variance per ray over its largest: rays that agree outweigh the net
                    k = k * 4.0 * p * (1.0 - p)
                weight = n / tl.maximum(n + k, 1e-12)  # an infinite k: the network's AO alone
                ao = tl.minimum(weight * rays + (1.0 - weight) * ao, 1.0)
            if INTERVAL:  # within the rays' Wilson interval (reconnet.rays_interval at reconnet.interval_z)
                cast = n * ray_factor
                zn = tl.where(z_past > 0, z * tl.sqrt(z_past / tl.maximum(tl.maximum(cast, z_past), 1e-12)), z)
                m = tl.maximum(cast, 1e-12)
                q = tl.minimum(tl.maximum(rays, 0.0), 1.0)
                spread = zn * zn / m
                center = (q + spread / 2.0) / (1.0 + spread)
                half = zn / (1.0 + spread) * tl.sqrt(q * (1.0 - q) / m + spread / (4.0 * m))
                ao = tl.where(cast > 0, tl.minimum(tl.maximum(ao, center - half), center + half), ao)
        if BUFFERS:  # isosr_net.inference.buffer_stack: unit normals and depth where covered, else 0
            covered = mask > 0
            length = tl.maximum(tl.sqrt(nx * nx + ny * ny + nz * nz), 1e-6)
            nx = tl.where(covered, nx / length, 0.0)
            ny = tl.where(covered, ny / length, 0.0)
            nz = tl.where(covered, nz / length, 0.0)
            depth = tl.where(covered, depth, 0.0)
            ao = tl.minimum(tl.maximum(ao, 0.0), 1.0)
            if SHADE:  # isosr_render.shading.shade of these buffers, stored (S H, S W, 3)
                n_dot_l = tl.maximum(nx * light_x + ny * light_y + nz * light_z, 0.0)
                n_dot_h = tl.maximum(nx * half_x + ny * half_y + nz * half_z, 0.0)
                # n_dot_h ** shininess, 0 ** 0 = 1 as torch.pow
                spec = specular * tl.where(n_dot_h > 0, tl.exp2(shininess * tl.log2(tl.maximum(n_dot_h, 1e-30))),
                                           tl.where(shininess == 0, 1.0, 0.0))
                lit = ambient + diffuse * n_dot_l
                color = color_ptr + (b * plane + at) * 3
                tl.store(color, _composite(mask, albedo_r * lit + spec, ao, back_r), mask=here)
                tl.store(color + 1, _composite(mask, albedo_g * lit + spec, ao, back_g), mask=here)
                tl.store(color + 2, _composite(mask, albedo_b * lit + spec, ao, back_b), mask=here)
        out = out_ptr + b * OUT * plane + at
        tl.store(out + MASK_C * plane, mask, mask=here)
        tl.store(out + NORMAL_C * plane, nx, mask=here)
        tl.store(out + (NORMAL_C + 1) * plane, ny, mask=here)
        tl.store(out + (NORMAL_C + 2) * plane, nz, mask=here)
        tl.store(out + DEPTH_C * plane, depth, mask=here)
        tl.store(out + AO_C * plane, ao, mask=here)


@triton.jit
def _composite(mask, lit, ao, back):
    """One color channel: the lit surface times AO over the background by the mask, in [0, 1]."""
    alpha = tl.minimum(tl.maximum(mask, 0.0), 1.0)
    return tl.minimum(tl.maximum(alpha * (lit * ao) + (1.0 - alpha) * back, 0.0), 1.0)


_conv_tuned = _tuned(_conv_kernel, ["size_class", "STRIDE", "CI", "CO"])
_tail_tuned = _tuned(_tail_kernel, ["size_class", "S", "UP", "PIXEL_TAIL"])  # each variant its own tiles


def _size_class(pixels: int) -> int:
    """The autotuning key of a pass over ``pixels`` output pixels a frame (each frame of a batch)."""
    return pixels.bit_length()


def _grid(pixels: int, batch: int):
    return lambda meta: (triton.cdiv(pixels, meta["BLOCK_M"]), batch)


def _tile_width(channels: int, name: str, where: str) -> int:
    """The kernel width of a tensor of ``channels`` (:func:`kernel_width`), refused past :data:`MAX_KERNEL_WIDTH`."""
    width = kernel_width(channels)
    if width > MAX_KERNEL_WIDTH:
        raise ValueError(f"{where}: {name} may have at most {MAX_KERNEL_WIDTH} channels, got {channels}")
    return width


def _check_taps(weight: torch.Tensor, bias: torch.Tensor, ci: int, where: str) -> int:
    """Check tap-major weights (9, kernel_width(ci), CO) fp16 and a (CO,) fp32 bias, CO a kernel width; returns CO."""
    dims = check_shape(weight, f"(9, {_tile_width(ci, 'the input', where)}, CO)", "weight", where)
    check_shape(bias, "(CO)", "bias", where, dims)
    _check_dtypes(weight, bias, where)
    if kernel_width(dims["CO"]) != dims["CO"] or dims["CO"] > MAX_KERNEL_WIDTH:
        raise ValueError(f"{where}: the weights' outputs must be a power of 2 in [16, {MAX_KERNEL_WIDTH}] "
                         f"(zero-padded), got {dims['CO']}")
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


def _check_stored(t: torch.Tensor, name: str, shape: tuple, dtype: torch.dtype, device: torch.device,
                  where: str) -> None:
    """``t`` a contiguous ``dtype`` tensor of ``shape`` on ``device`` (a kernel writes or reads it as laid out)."""
    if (tuple(t.shape), t.dtype, t.device) != (shape, dtype, device) or not t.is_contiguous():
        raise ValueError(f"{where}: {name} must be a contiguous {str(dtype).removeprefix('torch.')} {shape} tensor "
                         f"on {device}, got {t.dtype} {tuple(t.shape)} on {t.device}")

@dataclass(frozen=True)
class ReconSources:
    """Where ReconNet's 8 input channels (:data:`~isosr_render.conventions.RECON_CHANNELS`) lie:
    :func:`pack_inputs` and :func:`recon_tail` read them in place, each a (B, C, H, W) view of any
    strides and float dtype, so that a render's buffers need no stacking.

    Shape:
        mask, depth, ao: (B, 1, H, W). normal: (B, 3, H, W). sampling: (B, 2, H, W), constant
        planes may be expanded (stride 0). ``ao`` None: no AO rays were cast (read as 0).
    """

    mask: torch.Tensor
    normal: torch.Tensor
    depth: torch.Tensor
    ao: torch.Tensor | None
    sampling: torch.Tensor

    @classmethod
    def of_inputs(cls, inputs: torch.Tensor) -> "ReconSources":
        """Views of an input stack (B, 8, H, W)."""
        check_shape(inputs, f"(B, {INPUTS}, H, W)", "inputs", "ReconSources")
        return cls(inputs[:, MASK], inputs[:, NORMAL], inputs[:, DEPTH], inputs[:, SAMPLED_AO], inputs[:, SAMPLING])

    @classmethod
    def of_buffers(cls, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor, ao: torch.Tensor | None,
                   sampling: torch.Tensor) -> "ReconSources":
        """Views of frames' buffers: mask, depth, ao (B, H, W), normal (B, H, W, 3), and the sampling's
        two values (1, 2, 1, 1), or its planes (1 or B, 2, H, W)."""
        b, h, w = mask.shape
        return cls(mask[:, None], normal.permute(0, 3, 1, 2), depth[:, None], None if ao is None else ao[:, None],
                   sampling.expand(b, 2, h, w))

    def check(self, where: str) -> dict[str, int]:
        """Check the shapes and dtypes; returns B, H, W."""
        dims = check_shape(self.mask, "(B, 1, H, W)", "mask", where)
        for name, channels in (("normal", 3), ("depth", 1), ("ao", 1), ("sampling", 2)):
            t = getattr(self, name)
            if t is not None:
                check_shape(t, f"(B, {channels}, H, W)", name, where, dims)
        if not all(t.is_floating_point() for t in self._planes()):
            raise ValueError(f"{where}: the inputs must be floating point")
        return dims

    def args(self) -> list:
        """Each source's tensor and four strides, as the kernels take them (for no AO, the mask's)."""
        return [a for t in self._planes() for a in (t, *t.stride())]

    def _planes(self) -> tuple[torch.Tensor, ...]:
        return self.mask, self.normal, self.depth, self.mask if self.ao is None else self.ao, self.sampling


@dataclass(frozen=True)
class PixelTail:
    """A ``pixel_tail`` model's per-pixel MLP (:meth:`~isosr_net.reconnet.ReconNet.correction`) as
    :func:`recon_tail` reads it: its first layer's columns of the raw outputs (``raw``) and of the packed
    channels (``packed``: the inputs and the previous mask and AO, as :func:`pack_inputs` orders them), its
    hidden units padded to a tile with zeros.

    Shape:
        raw: (6, HID) fp32. packed: (16, HID) fp16, 10 rows used. bias: (HID,) fp32. out: (HID, 16) fp16,
        6 columns used. out_bias: (16,) fp32. HID: :func:`kernel_width` of the hidden units.
    """

    raw: torch.Tensor
    packed: torch.Tensor
    bias: torch.Tensor
    out: torch.Tensor
    out_bias: torch.Tensor

    def check(self, device: torch.device, where: str) -> int:
        """Check the shapes, dtypes and device; returns HID."""
        hid = self.bias.shape[0] if self.bias.dim() == 1 else -1
        expected = {"raw": ((OUTPUTS, hid), torch.float32), "packed": ((PACKED, hid), torch.float16),
                    "bias": ((hid,), torch.float32), "out": ((hid, PACKED), torch.float16),
                    "out_bias": ((PACKED,), torch.float32)}
        for name, (shape, dtype) in expected.items():
            _check_stored(getattr(self, name), f"the pixel tail's {name}", shape, dtype, device, where)
        if hid != kernel_width(hid) or hid > MAX_KERNEL_WIDTH:
            raise ValueError(f"{where}: the pixel tail's hidden units must be padded to a tile of at most "
                             f"{MAX_KERNEL_WIDTH}, got {hid}")
        return hid

    def args(self) -> list[torch.Tensor]:
        return [self.raw, self.packed, self.bias, self.out, self.out_bias]


_CHANNELS = dict(MASK_C=MASK.start, NORMAL_C=NORMAL.start, DEPTH_C=DEPTH.start, AO_C=SAMPLED_AO.start,
                 SAMPLING_C=SAMPLING.start)


def pack_inputs(sources: ReconSources, prev: torch.Tensor | None, flow: torch.Tensor | None = None,
                multiple: int = 8, first_frame: str = "inputs", upscale: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """ReconNet's input channels packed, replicate-padded to multiples of ``multiple``, fp16
    NHWC; and the input checks' flags, computed on the way.

    Args:
        sources: the 8 input channels.
        prev: the previous output (at ``upscale`` times the sides); warped already if ``flow`` is
            None, else warped here by ``flow`` (upsampled: :func:`isosr_net.flow_warp.upscale_flow`).
            None on a sequence's first frame: its stand-in is made here
            (:meth:`~isosr_net.reconnet.ReconNet.first_previous` under ``first_frame``).
        flow: backward flow in input pixels (:func:`isosr_net.flow_warp.warp_by_flow`), or None;
            checked even where nothing is warped.
        first_frame: "inputs" or "zeros" (:class:`~isosr_net.reconnet.ReconNetConfig`).
        upscale: the model's (:attr:`~isosr_net.reconnet.ReconNetConfig.upscale`), 1 or 2.

    Returns:
        ``(packed, flags)``: flags (B, 6) fp32, each frame's in the order of
        :data:`isosr_net.inference.FRAME_FLAGS` (1 where a buffer holds NaN or Inf or AO leaves
        [0, 1], and the largest finite |depth|).

    Shape:
        prev: (B, 6, sH, sW), s the upscale. flow: (B, 2, H, W). Returns packed (B, H', W', 16):
        channels 0-7 the inputs, 8 and 9 the previous mask and AO, 10-15 zero; for x2, 8-11 the
        previous mask and 12-15 its AO at the input pixel's 2 x 2 output pixels (F.pixel_unshuffle).
    """
    dims = sources.check("pack_inputs")
    if upscale not in FUSED_UPSCALES:
        raise ValueError(f"pack_inputs: upscale must be one of {FUSED_UPSCALES}, got {upscale!r}")
    if prev is not None:
        check_shape(prev, f"({dims['B']}, 6, {upscale * dims['H']}, {upscale * dims['W']})", "prev", "pack_inputs")
    if flow is not None:
        check_shape(flow, "(B, 2, H, W)", "flow", "pack_inputs", dims)
        if not flow.is_floating_point():
            raise ValueError(f"pack_inputs: flow must be floating point, got {flow.dtype}")
    if first_frame not in FIRST_FRAME_MODES:
        raise ValueError(f"pack_inputs: first_frame must be one of {FIRST_FRAME_MODES}, got {first_frame!r}")
    mode = (PREV_INPUTS if first_frame == "inputs" else PREV_ZEROS) if prev is None else \
        PREV_GIVEN if flow is None else PREV_WARP
    b, h, w = dims["B"], dims["H"], dims["W"]
    hp, wp = h + -h % multiple, w + -w % multiple
    out = sources.mask.new_empty((b, hp, wp, PACKED), dtype=torch.float16)
    programs = triton.cdiv(hp * wp, PACK_BLOCK)
    flags = sources.mask.new_empty((len(FRAME_FLAGS), b * programs), dtype=torch.float32)
    prev_args = (sources.mask, 0, 0, 0, 0) if prev is None else (prev, *prev.stride())
    flow_args = (sources.mask, 0, 0, 0, 0) if flow is None else (flow, *flow.stride())
    _pack_kernel[(programs, b)](*sources.args(), *prev_args, *flow_args, out, flags, h, w, hp, wp, PREV=mode.value,
                                HAS_AO=sources.ao is not None, HAS_FLOW=flow is not None, **_CHANNELS,
                                PREV_MASK=MASK.start, PREV_AO=AO.start, N_IN=INPUTS, S=upscale, C=PACKED,
                                BLOCK=PACK_BLOCK)
    return out, flags.view(len(FRAME_FLAGS), b, programs).amax(dim=2).T


def conv3x3(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, *, stride: int = 1, relu: bool = True,
            residual: torch.Tensor | None = None, out_channels: int | None = None) -> torch.Tensor:
    """``relu(conv3x3(x) + bias + residual)``: zero padding; the ReLU and residual where asked.

    Args:
        x: NHWC fp16 (contiguous).
        weight: tap-major weights, ``weight[3 * ky + kx, ci, co]``, fp16, zero-padded to kernel widths
            (:func:`isosr_net.fused_recon.tap_weights`).
        bias: fp32, zero-padded as the weights' outputs.
        stride: 1, or 2 (the output has half the sides, even sides asked).
        relu: the ReLU, after the residual sum.
        residual: NHWC fp16 (contiguous), added before the ReLU.
        out_channels: the output's channels (of the weights' ``COP``, the first; default all).

    Shape:
        x: (B, H, W, CI). weight: (9, kernel_width(CI), COP). bias: (COP,). residual: (B, H/s, W/s, CO).
        Returns (B, H/s, W/s, CO), fp16, CO ``out_channels`` (kernel_width(CO) = COP). CI, CO at most
        :data:`MAX_KERNEL_WIDTH`.
    """
    dims = _check_nhwc(x, "x", "conv3x3")
    b, hi, wi, ci = dims["B"], dims["H"], dims["W"], dims["C"]
    cop = _check_taps(weight, bias, ci, "conv3x3")
    co = cop if out_channels is None else out_channels
    if co < 1 or kernel_width(co) != cop:
        raise ValueError(f"conv3x3: {co} output channels take weights of {kernel_width(co)} outputs, got {cop}")
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
                                   _size_class(ho * wo),
                                   STRIDE=stride, RESIDUAL=residual is not None, RELU=relu, CI=ci, CO=co,
                                   CIP=kernel_width(ci), COP=cop, **FIXED)
    return out


def upsample_add(x: torch.Tensor, coarse: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``relu(x + conv1x1(bilinear_2x(coarse)))`` (``F.interpolate``, align_corners=False), fp16 NHWC.

    Args:
        x: NHWC fp16 (contiguous), even sides.
        coarse: half-resolution features, any layout (NHWC reads fastest), any float dtype.
        weight, bias: the 1x1 convolution, ``weight[cc, c]`` fp16 (contiguous), bias fp32, zero-padded to
            kernel widths.

    Shape:
        x: (B, H, W, C). coarse: (B, CC, H/2, W/2). weight: (kernel_width(CC), kernel_width(C)). bias:
        (kernel_width(C),). Returns (B, H, W, C). C and CC at most :data:`MAX_KERNEL_WIDTH`.
    """
    dims = _check_nhwc(x, "x", "upsample_add")
    b, hp, wp, c = dims["B"], dims["H"], dims["W"], dims["C"]
    if hp % 2 or wp % 2:
        raise ValueError(f"upsample_add: x must have even sides, got {hp}x{wp}")
    cc = check_shape(coarse, f"({b}, CC, {hp // 2}, {wp // 2})", "coarse", "upsample_add")["CC"]
    cp, ccp = _tile_width(c, "x", "upsample_add"), _tile_width(cc, "coarse", "upsample_add")
    check_shape(weight, f"({ccp}, {cp})", "weight", "upsample_add")
    check_shape(bias, f"({cp})", "bias", "upsample_add")
    _check_dtypes(weight, bias, "upsample_add")
    out = torch.empty_like(x)
    _upsample_add_kernel[(triton.cdiv(hp * wp, PACK_BLOCK), b)](x, coarse, weight, bias, out, hp, wp, hp // 2, wp // 2,
                                                               *coarse.stride(), C=c, CC=cc, CP=cp, CCP=ccp,
                                                               BLOCK=PACK_BLOCK)
    return out


def recon_tail(y: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, sources: ReconSources,
               config: ReconNetConfig, as_buffers: bool = False, shading: ShadingParams | None = None,
               out: torch.Tensor | None = None, blend_rays: float | None = None,
               gates: torch.Tensor | None = None, ray_factor: float = 1.0, packed: torch.Tensor | None = None,
               pixel_tail: PixelTail | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """ReconNet's output convolution and output stack, cropped to the frame (and written
    depth-to-space at twice its sides for a model that upscales x2); as buffers and shaded where
    asked.

    Args:
        y: the last decoder level's features, NHWC fp16, padded past the frame.
        weight, bias: the output convolution as for :func:`conv3x3`, CO padded to 16 (6 used; x2:
            32, 24 used); a ``blend_map`` model's map in the rows past them (``fused_recon.tail_convolution``).
        sources: the network's inputs (mask, normal and depth read; with ``config.ao_prior``
            "rays" or "blend" the sampled AO and the sampling too).
        config: the network's config (its upscale, AO prior and ray limits, as
            :func:`~isosr_net.reconnet.ao_output`).
        as_buffers: the stack as :func:`isosr_net.inference.buffer_stack` makes it of the output
            (unit normals, depth where covered), not the network's raw output.
        shading: with ``as_buffers``, also shade it (:func:`isosr_render.shading.shade`).
        out: the stack's tensor to write (contiguous, fp32, on ``y``'s device); None: a new one.
            It may be the previous output that the pack read: the tail runs after it.
        blend_rays: with ``config.ao_prior`` "blend", the rays the network's AO stands for (a host number:
            no sync).
        gates: with ``config.geometry_gate``, the geometry corrections' factor per rays per pixel, fp32 on
            ``y``'s device (:func:`~isosr_net.reconnet.geometry_gate`: the sigmoid of its logits).
        ray_factor: the rays behind the sampled AO's mean per ray the sampling channels count (with
            ``config.ao_interval``: :func:`~isosr_net.reconnet.rays_interval` of them all).
        packed, pixel_tail: with ``config.pixel_tail`` (an upscale of 1), the pack's output these features came
            from (:func:`pack_inputs`) and the MLP that reads it per pixel; others neither.

    Returns:
        ``(stack, color or None)``.

    Shape:
        y: (B, H', W', CI). weight: (9, kernel_width(CI), CO). bias: (CO,). sources: H <= H', W <= W'.
        Returns stack (B, 6, sH, sW) fp32 (mask, normal, depth, AO) and color (B, sH, sW, 3)
        fp32, s the upscale.
    """
    launch = tail_launch(y, weight, bias, sources, config, as_buffers, shading, out, blend_rays, gates, ray_factor,
                         packed, pixel_tail)
    _tail_tuned[launch.grid](*launch.args, **launch.constexprs, **FIXED)
    return launch.out, launch.color


@dataclass(frozen=True)
class TailLaunch:
    """:func:`recon_tail`'s launch of its kernel: the grid (of the autotuned ``BLOCK_M``), the arguments and
    compile-time constants, and the outputs it writes."""

    grid: Callable[[dict], tuple[int, int]]
    args: list
    constexprs: dict
    out: torch.Tensor
    color: torch.Tensor | None


def tail_launch(y: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, sources: ReconSources,
                config: ReconNetConfig, as_buffers: bool = False, shading: ShadingParams | None = None,
                out: torch.Tensor | None = None, blend_rays: float | None = None,
                gates: torch.Tensor | None = None, ray_factor: float = 1.0, packed: torch.Tensor | None = None,
                pixel_tail: PixelTail | None = None) -> TailLaunch:
    """:func:`recon_tail`'s checks, outputs and kernel arguments (its arguments), not launched: what
    :func:`isosr_bench.kernel_resources.fused_tail_resources` compiles ahead of time."""
    dims = _check_nhwc(y, "y", "recon_tail")
    b, hp, wp, ci = dims["B"], dims["H"], dims["W"], dims["C"]
    co = _check_taps(weight, bias, ci, "recon_tail")
    frame = sources.check("recon_tail")
    h, w = frame["H"], frame["W"]
    if frame["B"] != b:
        raise ValueError(f"recon_tail: {frame['B']} frames of inputs for {b} of features")
    stem = config.stem_stride
    gh, gw = -(-h // stem), -(-w // stem)  # the first level's pixels that hold the frame's
    if gh > hp or gw > wp:
        raise ValueError(f"recon_tail: inputs of {h}x{w} need {gh}x{gw} features, got {hp}x{wp}")
    if shading is not None and not as_buffers:
        raise ValueError("recon_tail: shading shades the output buffers: pass as_buffers=True")
    if (config.ao_prior == "blend") != (blend_rays is not None):
        raise ValueError(f"recon_tail: blend_rays goes with a blend model's tail, got {blend_rays} for AO prior "
                         f"{config.ao_prior!r}")
    if config.geometry_gate != (gates is not None) or (
            gates is not None and (gates.shape != (config.max_spp,) or gates.dtype != torch.float32
                                   or gates.device != y.device)):
        raise ValueError(f"recon_tail: a gated model's tail takes its {config.max_spp} gates (float32 on {y.device}), "
                         f"others none; got {None if gates is None else (gates.dtype, tuple(gates.shape))} for "
                         f"geometry_gate={config.geometry_gate}")
    s, side = config.upscale, config.cell_side
    if co < (OUTPUTS + config.blend_map) * side * side:
        raise ValueError(f"recon_tail: the model's tail has {(OUTPUTS + config.blend_map) * side * side} outputs, "
                         f"the weights {co}")
    hid = _check_pixel_tail(packed, pixel_tail, config, (b, hp, wp), y.device)
    shape = (b, OUTPUTS, s * h, s * w)
    if out is None:
        out = torch.empty(shape, device=y.device, dtype=torch.float32)
    else:
        _check_stored(out, "out", shape, torch.float32, y.device, "recon_tail")
    color = None if shading is None else torch.empty((b, s * h, s * w, 3), device=y.device, dtype=torch.float32)
    params = shading or ShadingParams()
    light, half = light_and_half(params)
    args = [y, weight, bias, *sources.args(), out, out if color is None else color, bias if gates is None else gates,
            *([y, bias, y, bias, y, bias] if pixel_tail is None else [packed, *pixel_tail.args()]),
            h, w, gh, gw, hp, wp, _size_class(gh * gw), float(config.max_ao_rays * config.max_spp),
            float(blend_rays or 0.0), float(ray_factor), float(config.ao_interval),
            float(config.ao_interval_narrows_past), *params.albedo, params.ambient, params.diffuse, params.specular,
            params.shininess, *light, *half, *params.background]
    constexprs = dict(MASK_C=MASK.start, NORMAL_C=NORMAL.start, DEPTH_C=DEPTH.start, AO_C=AO.start,
                      AO_PRIOR=config.ao_prior != "none", BLEND=config.ao_prior == "blend",
                      BLEND_MAP=config.blend_map, BLEND_VARIANCE=config.blend_variance,
                      INTERVAL=config.ao_interval > 0, GATED=gates is not None, PIXEL_TAIL=pixel_tail is not None,
                      HID=hid, PC=PACKED, MAX_SPP=config.max_spp, HAS_AO=sources.ao is not None,
                      BUFFERS=as_buffers, SHADE=shading is not None, OUT=OUTPUTS, S=side, UP=s, CI=ci,
                      CIP=kernel_width(ci), CO=co)
    return TailLaunch(_grid(gh * gw, b), args, constexprs, out, color)


def _check_pixel_tail(packed: torch.Tensor | None, pixel_tail: PixelTail | None, config: ReconNetConfig,
                      features: tuple[int, int, int], device: torch.device) -> int:
    """recon_tail's check of a pixel tail and the packed inputs it reads; returns its HID (16 for none)."""
    if bool(config.pixel_tail) != (pixel_tail is not None) or (pixel_tail is None) != (packed is None):
        raise ValueError(f"recon_tail: a pixel_tail model's tail takes its MLP and the packed inputs, others neither; "
                         f"got {'an' if pixel_tail else 'no'} MLP and {'the' if packed is not None else 'no'} packed "
                         f"inputs for pixel_tail={config.pixel_tail}")
    if pixel_tail is None:
        return 16
    if config.upscale != 1:
        raise ValueError(f"recon_tail: a pixel tail runs at an upscale of 1, got {config.upscale}")
    b, hp, wp = features
    shape = (b, hp * config.stem_stride, wp * config.stem_stride, PACKED)
    _check_stored(packed, "packed (pack_inputs' output)", shape, torch.float16, device, "recon_tail")
    return pixel_tail.check(device, "recon_tail")
