"""The fused ReconNet kernels against float64 PyTorch references, on the device the kernels run on.

Not collected by itself (the name): ``tests/test_fused_recon.py`` runs it in a subprocess, on the
CPU under Triton's interpreter (``TRITON_INTERPRET=1``, which must be set before the kernels are
imported) and on CUDA where there is a GPU. Directly, on a GPU machine:

    python -m pytest -q tests/fused_checks.py                      # the CUDA kernels
    TRITON_INTERPRET=1 python -m pytest -q tests/fused_checks.py   # the interpreter

Tolerances: the kernels take fp16 operands, accumulate in fp32 and store fp16 features, so a
convolution's output is off by at most about 2^-11 (fp16's half ulp) of its magnitude plus its
operands' rounding, 2^-11 of ``conv(|x|, |w|)``: asserted as 1e-3 of ``|ref| + conv(|x|, |w|)``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from isosr_render.buffers import FrameBuffers
from isosr_render.conventions import AO, DEPTH, MASK, NORMAL, SAMPLED_AO, SAMPLING
from isosr_render.shading import ShadingParams, shade
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net import fused_kernels
from isosr_net.fused_kernels import ReconSources, conv3x3, pack_inputs, recon_tail, upsample_add
from isosr_net.fused_recon import (FusedReconNet, fused_reconnet, fused_runs_on, fused_traffic, kernel_width,
                                   tap_weights)
from isosr_net.inference import FP16_MAX_DEPTH, FRAME_FLAGS, buffer_stack, frame_flags, stack_buffers
from isosr_net.model import load_pretrained, save_pretrained
from isosr_net.reconnet import (AO_PRIORS, BLEND_PARAMETER, GATE_PARAMETER, GATE_RATE, ReconNet, ReconNetConfig,
                                ao_output, geometry_gate, upsampled_inputs)
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL, Reconstructor

from test_reconnet import recon_batch, same_weights

DEVICE = "cpu" if os.environ.get("TRITON_INTERPRET") == "1" else "cuda"
if not fused_runs_on(DEVICE):
    pytest.skip(f"the fused kernels do not run on {DEVICE} here", allow_module_level=True)
SIZES = [(13, 21), (24, 40), (3, 5)]  # sides not multiples of any tile; one frame smaller than a tile


def rand(*shape, scale=1.0, seed=0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(*shape, generator=gen) * scale).to(DEVICE, dtype)


def assert_conv_close(got: torch.Tensor, ref: torch.Tensor, magnitude: torch.Tensor) -> None:
    """``got`` within 1e-3 of ``|ref| + magnitude`` (see the module docstring), elementwise."""
    assert got.shape == ref.shape
    err = (got.double() - ref).abs()
    bound = 1e-3 * (ref.abs() + magnitude) + 1e-6
    assert (err <= bound).all(), f"worst excess {(err - bound).max().item():.3g}, max error {err.max().item():.3g}"


def conv_ref(x: torch.Tensor, taps: torch.Tensor, bias: torch.Tensor, stride: int = 1
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """fp64 ``conv3x3(x) + bias`` of NCHW ``x`` with tap-major weights, and ``conv(|x|, |w|)``."""
    weight = taps.double().reshape(3, 3, *taps.shape[1:]).permute(3, 2, 0, 1)
    return (F.conv2d(x.double(), weight, bias.double(), stride=stride, padding=1),
            F.conv2d(x.double().abs(), weight.abs(), stride=stride, padding=1))


def nchw(x: torch.Tensor) -> torch.Tensor:
    return x.permute(0, 3, 1, 2)


# ---------------------------------------------------------------- pack


def pack(inputs, prev, flow=None, **kw):
    return pack_inputs(ReconSources.of_inputs(inputs), prev, flow, **kw)


@pytest.mark.parametrize("h, w", SIZES)
@pytest.mark.parametrize("layout", ["contiguous", "channels_last"])
def test_pack_lays_out_the_inputs_and_the_warped_previous_replicate_padded(h, w, layout):
    memory = torch.channels_last if layout == "channels_last" else torch.contiguous_format
    inputs = rand(2, 8, h, w, seed=1).contiguous(memory_format=memory)
    warped = rand(2, 6, h, w, seed=2).contiguous(memory_format=memory)
    packed, _ = pack(inputs, warped)
    expected = F.pad(torch.cat([inputs, warped[:, MASK], warped[:, AO]], dim=1), (0, -w % 8, 0, -h % 8),
                     mode="replicate")
    assert packed.shape == (2, h + -h % 8, w + -w % 8, 16) and packed.dtype == torch.float16
    torch.testing.assert_close(nchw(packed)[:, :10], expected.half(), rtol=0, atol=0)
    assert (packed[..., 10:] == 0).all()


@pytest.mark.parametrize("h, w", SIZES)
def test_pack_warps_the_previous_mask_and_ao_like_warp_by_flow(h, w):
    inputs, previous = rand(2, 8, h, w, seed=3), rand(2, 6, h, w, seed=4).abs()
    flow = rand(2, 2, h, w, scale=3.0, seed=5)
    flow[0, :, 0, 0] = torch.tensor([1e6, -1e6])  # far outside: reads zeros
    flow[1, :, -1, -1] = torch.tensor([0.5, -0.25])  # between pixels at the border
    packed, _ = pack(inputs, previous, flow)
    expected = warp_by_flow(previous.double(), flow.double())[:, [MASK.start, AO.start]]
    got = nchw(packed)[:, 8:10, :h, :w].double()
    # fp16 storage, and the reference's normalized grid coordinates rounded in fp32
    assert ((got - expected).abs() <= 1e-3 * expected.abs() + 1e-4).all()
    assert (got[0, :, 0, 0] == 0).all()
    torch.testing.assert_close(nchw(packed)[:, :8, :h, :w], inputs.half(), rtol=0, atol=0)


@pytest.mark.parametrize("first_frame", ["inputs", "zeros"])
def test_pack_makes_the_first_frames_stand_in_and_reads_a_frames_buffers_in_place(first_frame):
    """A frame's buffers (HWC normals, the sampling as two values) pack as their input stack
    does; without a previous output the stand-in is ReconNet.first_previous's."""
    h, w = 13, 21
    x = recon_batch(1, h, w, seed=6).to(DEVICE)
    x[:, 6:8] = torch.tensor([0.25, 0.5], device=DEVICE)[None, :, None, None]  # constant sampling planes
    x[0, 5, :4] = 0  # no ray hit there: the stand-in's AO is the rays'
    net = ReconNet(ReconNetConfig(first_frame=first_frame)).to(DEVICE)
    sources = ReconSources.of_buffers(x[:, 0], x[:, 1:4].permute(0, 2, 3, 1).contiguous(), x[:, 4], x[:, 5],
                                      x[:, 6:8, :1, :1])
    for packed, flags in (pack(x, None, first_frame=first_frame), pack_inputs(sources, None, first_frame=first_frame)):
        stand_in = net.first_previous(x)
        torch.testing.assert_close(nchw(packed)[:, :8, :h, :w], x.half(), rtol=0, atol=0)
        torch.testing.assert_close(nchw(packed)[:, 8:10, :h, :w], stand_in[:, [MASK.start, AO.start]].half(),
                                   rtol=0, atol=0)
        torch.testing.assert_close(flags[0], frame_flags(x[0, 0], x[0, 1:4], x[0, 4], x[0, 5], None), rtol=0, atol=0)


@pytest.mark.parametrize("broken, value", [("mask", float("nan")), ("normal", float("inf")), ("depth", float("-inf")),
                                           ("flow", float("nan")), ("ao", 1.5), ("ao", float("nan")),
                                           ("deepest", -3e4)])
def test_packs_flags_are_the_frames_checks(broken, value):
    """Each of FRAME_FLAGS set by the one bad value it names, as frame_flags computes them, in the
    frame that holds it only (the bad pixel in the first frame's last program's tile; a second
    frame in the batch clean)."""
    h, w = 13, 21
    x = recon_batch(2, h, w, seed=7).to(DEVICE)
    flow = rand(2, h, w, 2, seed=8)
    buffers = {"mask": x[:, 0], "normal": x[:, 1:4].permute(0, 2, 3, 1).contiguous(), "depth": x[:, 4].clone(),
               "ao": x[:, 5].clone(), "flow": flow}
    buffers["mask"] = buffers["mask"].clone()
    target = buffers["depth" if broken == "deepest" else broken]
    target[0].view(-1)[-1] = value
    sources = ReconSources.of_buffers(buffers["mask"], buffers["normal"], buffers["depth"], buffers["ao"],
                                      x[:1, 6:8, :1, :1])
    _, flags = pack_inputs(sources, rand(2, 6, h, w, seed=9), flow.permute(0, 3, 1, 2))
    assert flags.shape == (2, len(FRAME_FLAGS))
    for k in range(2):
        expected = frame_flags(*(buffers[n][k] for n in ("mask", "normal", "depth", "ao", "flow")))
        torch.testing.assert_close(flags[k], expected, rtol=0, atol=0)
    index = FRAME_FLAGS.index(broken)
    assert flags[0, index] == (3e4 if broken == "deepest" else 1)
    assert (flags[0, :5].count_nonzero() == (0 if broken == "deepest" else 1))
    assert flags[1, :5].count_nonzero() == 0


def test_pack_checks_its_inputs():
    inputs, prev = rand(1, 8, 4, 6), rand(1, 6, 4, 6)
    with pytest.raises(ValueError, match=r"pack_inputs: prev must be \(1, 6, 4, 6\), got \(1, 6, 4, 5\)"):
        pack(inputs, prev[..., :5])
    with pytest.raises(ValueError, match=r"ReconSources: inputs must be \(B, 8, H, W\)"):
        pack(inputs[:, :7], prev)
    with pytest.raises(ValueError, match="pack_inputs: flow must be floating point"):
        pack(inputs, prev, rand(1, 2, 4, 6).int())
    with pytest.raises(ValueError, match="pack_inputs: first_frame must be one of"):
        pack(inputs, None, first_frame="noise")
    with pytest.raises(ValueError, match=r"pack_inputs: prev must be \(1, 6, 8, 12\), got \(1, 6, 4, 6\)"):
        pack(inputs, prev, upscale=2)
    with pytest.raises(ValueError, match=r"pack_inputs: upscale must be one of \(1, 2\), got 4"):
        pack(inputs, None, upscale=4)


@pytest.mark.parametrize("previous", ["given", "warped", "inputs", "zeros"])
def test_pack_of_an_x2_model_reads_the_previous_output_space_to_depth(previous):
    """An x2 model's packed input: the inputs, and the previous output (at twice the sides; warped
    by the flow upsampled, or the first frame's stand-in of the upsampled inputs) pixel-unshuffled."""
    h, w = 13, 21
    inputs = recon_batch(2, h, w, seed=42).to(DEVICE)
    inputs[1, 5, :4] = 0  # no ray hit there: the stand-in's AO is the rays'
    prev, flow = rand(2, 6, 2 * h, 2 * w, seed=43).abs(), rand(2, 2, h, w, scale=3.0, seed=44)
    flow[0, :, 0, 0] = torch.tensor([1e6, -1e6])  # far outside: reads zeros
    if previous in ("given", "warped"):
        packed, _ = pack(inputs, prev, flow if previous == "warped" else None, upscale=2)
        read = warp_by_flow(prev.double(), upscale_flow(flow.double(), 2)) if previous == "warped" else prev.double()
    else:
        packed, _ = pack(inputs, None, first_frame=previous, upscale=2)
        read = ReconNet(ReconNetConfig(upscale=2, first_frame=previous)).to(DEVICE).first_previous(inputs.double())
    expected = F.pad(F.pixel_unshuffle(torch.cat([read[:, MASK], read[:, AO]], dim=1), 2), (0, -w % 8, 0, -h % 8),
                     mode="replicate")
    got = nchw(packed)[:, 8:].double()
    assert packed.shape == (2, 16, 24, 16)
    assert ((got - expected).abs() <= 1e-3 * expected.abs() + 1e-4).all(), (got - expected).abs().max()
    torch.testing.assert_close(nchw(packed)[:, :8, :h, :w], inputs.half(), rtol=0, atol=0)


# ---------------------------------------------------------------- convolutions


@pytest.mark.parametrize("h, w", SIZES)
@pytest.mark.parametrize("ci, co", [(16, 16), (32, 16), (16, 32)])
def test_conv3x3_is_conv2d_bias_relu(h, w, ci, co):
    x = rand(2, h, w, ci, seed=6, dtype=torch.float16)
    taps, bias = rand(9, ci, co, scale=0.3, seed=7, dtype=torch.float16), rand(co, seed=8)
    ref, magnitude = conv_ref(nchw(x), taps, bias)
    assert (ref < 0).any() and (ref > 0).any()  # the ReLU has work
    assert_conv_close(nchw(conv3x3(x, taps, bias)), F.relu(ref), magnitude)


@pytest.mark.parametrize("h, w", [(14, 22), (2, 4)])
@pytest.mark.parametrize("ci, co", [(16, 32), (64, 64)])
def test_conv3x3_of_stride_2_is_conv2d_of_stride_2(h, w, ci, co):
    x = rand(2, h, w, ci, seed=6, dtype=torch.float16)
    taps, bias = rand(9, ci, co, scale=0.3, seed=7, dtype=torch.float16), rand(co, seed=8)
    ref, magnitude = conv_ref(nchw(x), taps, bias, stride=2)
    assert_conv_close(nchw(conv3x3(x, taps, bias, stride=2)), F.relu(ref), magnitude)


def padded_bias(bias: torch.Tensor) -> torch.Tensor:
    """A bias zero-padded to its kernel width, as the kernels take it."""
    return F.pad(bias, (0, kernel_width(len(bias)) - len(bias)))


@pytest.mark.parametrize("ci, co, stride", [(8, 16, 1), (16, 8, 1), (3, 24, 1), (8, 8, 2)])
def test_conv3x3_of_fewer_channels_than_a_tile_stores_only_its_own(ci, co, stride):
    """Channels under 16 or not a power of 2: the tensors hold their own, the tile pads them (the weights
    zero-padded by tap_weights); the residual is read and the output written at their own channels."""
    x = rand(2, 6, 10, ci, seed=6, dtype=torch.float16)
    weight, bias = rand(co, ci, 3, 3, scale=0.3, seed=7), rand(co, seed=8)
    residual = rand(2, 6 // stride, 10 // stride, co, seed=9, dtype=torch.float16)
    got = conv3x3(x, tap_weights(weight, kernel_width(ci), kernel_width(co)), padded_bias(bias), stride=stride,
                  relu=False, residual=residual, out_channels=co)
    assert got.shape == (2, 6 // stride, 10 // stride, co)
    ref = (F.conv2d(nchw(x).double(), weight.double(), bias.double(), stride=stride, padding=1)
           + nchw(residual).double())
    magnitude = F.conv2d(nchw(x).double().abs(), weight.double().abs(), stride=stride, padding=1)
    assert_conv_close(nchw(got), ref, magnitude + nchw(residual).double().abs())
    with pytest.raises(ValueError, match=rf"conv3x3: {co} output channels take weights of {kernel_width(co)} outputs, "
                                         r"got 64"):
        conv3x3(x, tap_weights(weight, kernel_width(ci), 64), torch.zeros(64, device=DEVICE), out_channels=co)


def test_a_batch_is_tuned_as_one_of_its_frames(monkeypatch):
    """The autotuning key (size class) of a pass over B frames is one frame's: a new batch size
    tunes nothing while its sessions wait."""
    keyed = []
    monkeypatch.setattr(fused_kernels, "_size_class", lambda pixels: keyed.append(pixels) or pixels.bit_length())
    taps, bias = rand(9, 16, 16, seed=7, dtype=torch.float16), rand(16, seed=8)
    for b in (1, 4):
        conv3x3(rand(b, 14, 22, 16, seed=6, dtype=torch.float16), taps, bias, stride=2)
    assert keyed == [7 * 11, 7 * 11]


@pytest.mark.parametrize("relu", [False, True])
def test_conv3x3_adds_the_residual_then_relu_in_its_epilogue(relu):
    """ReconNet's residual block's second convolution (no ReLU there)."""
    x, residual = rand(2, 5, 9, 64, seed=21, dtype=torch.float16), rand(2, 5, 9, 64, seed=22, dtype=torch.float16)
    taps, bias = rand(9, 64, 64, scale=0.1, seed=23, dtype=torch.float16), rand(64, seed=24)
    conv, magnitude = conv_ref(nchw(x), taps, bias)
    summed = conv + nchw(residual).double()
    assert (summed < 0).any()
    assert_conv_close(nchw(conv3x3(x, taps, bias, relu=relu, residual=residual)),
                      F.relu(summed) if relu else summed, magnitude + nchw(residual).double().abs())


@pytest.mark.parametrize("h, w", [(7, 11), (1, 1)])
@pytest.mark.parametrize("layout", ["contiguous", "channels_last"])
def test_upsample_add_is_the_relu_of_the_skip_plus_the_upsampled_reduced_coarse(h, w, layout):
    """ReconNet's decoder input: the 1x1 reduction of the coarse features (64 -> 32 channels), upsampled, plus the skip."""
    memory = torch.channels_last if layout == "channels_last" else torch.contiguous_format
    coarse = rand(2, 64, h, w, seed=27, dtype=torch.float16).contiguous(memory_format=memory)
    skip = rand(2, 2 * h, 2 * w, 32, seed=28, dtype=torch.float16)
    weight, bias = rand(64, 32, scale=0.2, seed=29, dtype=torch.float16), rand(32, seed=30)
    reduced = torch.einsum("bkhw,kc->bchw", coarse.double(), weight.double()) + bias.double()[:, None, None]
    up = F.interpolate(reduced, scale_factor=2, mode="bilinear", align_corners=False)
    expected = F.relu(nchw(skip).double() + up)
    magnitude = F.interpolate(torch.einsum("bkhw,kc->bchw", coarse.double().abs(), weight.double().abs()),
                              scale_factor=2, mode="bilinear", align_corners=False)
    got = upsample_add(skip, coarse, weight, bias)
    assert got.shape == skip.shape
    # the upsampled coarse rounded to fp16 for the reduction, the sum stored in fp16
    assert_conv_close(nchw(got), expected, magnitude + nchw(skip).double().abs())
    with pytest.raises(ValueError, match="upsample_add: x must have even sides, got 3x4"):
        upsample_add(rand(2, 3, 4, 32, dtype=torch.float16), coarse, weight, bias)
    with pytest.raises(ValueError, match=r"upsample_add: weight must be \(64, 32\), got \(32, 32\)"):
        upsample_add(skip, coarse, weight[:32].contiguous(), bias)


@pytest.mark.parametrize("c, cc", [(8, 16), (16, 8), (12, 40)])
def test_upsample_add_of_fewer_channels_than_a_tile_stores_only_its_own(c, cc):
    """The skip and the output hold their C channels, the coarse its CC; the 1x1 weights zero-padded."""
    coarse = rand(2, cc, 3, 5, seed=27, dtype=torch.float16)
    skip = rand(2, 6, 10, c, seed=28, dtype=torch.float16)
    weight, bias = rand(cc, c, scale=0.2, seed=29), rand(c, seed=30)
    padded = F.pad(weight, (0, kernel_width(c) - c, 0, kernel_width(cc) - cc)).half().contiguous()
    got = upsample_add(skip, coarse, padded, padded_bias(bias))
    assert got.shape == skip.shape
    reduced = torch.einsum("bkhw,kc->bchw", coarse.double(), weight.double()) + bias.double()[:, None, None]
    expected = F.relu(nchw(skip).double() + F.interpolate(reduced, scale_factor=2, mode="bilinear",
                                                          align_corners=False))
    magnitude = F.interpolate(torch.einsum("bkhw,kc->bchw", coarse.double().abs(), weight.double().abs()),
                              scale_factor=2, mode="bilinear", align_corners=False)
    assert_conv_close(nchw(got), expected, magnitude + nchw(skip).double().abs())


def test_conv3x3_checks_its_inputs():
    x, taps, bias = rand(1, 6, 8, 16, dtype=torch.float16), rand(9, 16, 16, dtype=torch.float16), rand(16)
    with pytest.raises(ValueError, match="conv3x3: x must be a contiguous fp16 NHWC tensor, got torch.float32"):
        conv3x3(x.float(), taps, bias)
    with pytest.raises(ValueError, match=r"conv3x3: weight must be \(9, 16, CO\), got \(9, 8, 16\)"):
        conv3x3(x, taps[:, :8], bias)
    with pytest.raises(ValueError, match="conv3x3: weight must be contiguous fp16 and bias fp32"):
        conv3x3(x, taps, bias.half())
    with pytest.raises(ValueError, match="conv3x3: x must have even sides for stride 2"):
        conv3x3(x[:, :5].contiguous(), taps, bias, stride=2)
    with pytest.raises(ValueError, match="conv3x3: stride must be 1 or 2, got 3"):
        conv3x3(x, taps, bias, stride=3)
    with pytest.raises(ValueError, match=r"conv3x3: residual must be \(1, 3, 4, 16\), got \(1, 6, 8, 16\)"):
        conv3x3(x, taps, bias, stride=2, residual=x)
    with pytest.raises(ValueError, match="conv3x3: the input may have at most 64 channels, got 65"):
        conv3x3(rand(1, 6, 8, 65, dtype=torch.float16), taps, bias)
    with pytest.raises(ValueError, match="upsample_add: coarse may have at most 64 channels, got 128"):
        upsample_add(x, rand(1, 128, 3, 4, dtype=torch.float16), taps[0], bias)


def tail_case(h, w, hp, wp):
    features = rand(2, hp, wp, 16, seed=13, dtype=torch.float16)
    taps, bias = tap_weights(rand(6, 16, 3, 3, scale=0.3, seed=14), 16, 16), torch.zeros(16, device=DEVICE)
    bias[:6] = rand(6, seed=15)
    return features, taps, bias, recon_batch(2, h, w, seed=16).to(DEVICE)


# A blend model's weight in the tail's tests: the rays its AO stands for.
BLEND_RAYS = {"blend": 3.0}


def blend_tensor(ao_prior: str) -> torch.Tensor | None:
    """:data:`BLEND_RAYS`'s weight as ao_output takes it (float64), None for the other priors."""
    return None if ao_prior not in BLEND_RAYS else torch.tensor(BLEND_RAYS[ao_prior], dtype=torch.float64)


@pytest.mark.parametrize("ao_prior", AO_PRIORS)
@pytest.mark.parametrize("h, w, hp, wp", [(13, 21, 16, 24), (24, 40, 24, 40), (3, 5, 8, 8)])
def test_tail_is_the_output_convolution_and_reconnets_output_stack(h, w, hp, wp, ao_prior):
    features, taps, bias, inputs = tail_case(h, w, hp, wp)
    raw, magnitude = (t[:, :6, :h, :w] for t in conv_ref(nchw(features), taps, bias))
    given = inputs.double()
    config, blend = ReconNetConfig(ao_prior=ao_prior, max_ao_rays=16), BLEND_RAYS.get(ao_prior)
    out, color = recon_tail(features, taps, bias, ReconSources.of_inputs(inputs), config, blend_rays=blend)
    assert out.shape == (2, 6, h, w) and out.dtype == torch.float32 and color is None
    torch.testing.assert_close(out[:, DEPTH], inputs[:, DEPTH], rtol=0, atol=0)
    # fp32 outputs: only the accumulation's rounding
    tail = torch.cat([(given[:, MASK] + raw[:, MASK]).clamp(0, 1), given[:, NORMAL] + raw[:, NORMAL],
                      given[:, DEPTH], ao_output(raw[:, AO], given, config, blend_tensor(ao_prior))], dim=1)
    err = (out.double() - tail).abs()
    assert (err <= 1e-5 * (magnitude + 1)).all(), err.max()
    assert (out[:, MASK] >= 0).all() and (out[:, MASK] <= 1).all()


@pytest.mark.parametrize("ao_prior", ["rays", "blend"])
@pytest.mark.parametrize("ray_factor", [1.0, 16.0])
@pytest.mark.parametrize("narrows_past", [0.0, 16.0])
def test_an_interval_tail_keeps_its_ao_within_the_rays_interval_as_ao_output(ao_prior, ray_factor, narrows_past):
    """ao_interval: the tail's AO as ao_output's in float64 (the rays' Wilson interval of the rays behind the mean,
    ``ray_factor`` counted, its z falling past ``narrows_past`` rays per pixel), and the interval changes it (a tail
    of AO far off, a blend that trusts it), as the falling z does where a pixel has more rays."""
    h, w = 13, 21
    features, taps, bias, inputs = tail_case(h, w, 16, 24)
    bias[5] = 4.0  # the AO channel's raw output far off
    inputs[1, SAMPLING] = 1.0  # frame 0 at 4 rays per pixel, frame 1 at 64
    raw, magnitude = (t[:, :6, :h, :w] for t in conv_ref(nchw(features), taps, bias))
    config = ReconNetConfig(ao_prior=ao_prior, max_ao_rays=16, ao_interval=2.0, ao_interval_narrows_past=narrows_past)
    blend = 1e3 if ao_prior == "blend" else None
    k = None if blend is None else torch.tensor(blend, dtype=torch.float64)
    out, _ = recon_tail(features, taps, bias, ReconSources.of_inputs(inputs), config, blend_rays=blend,
                        ray_factor=ray_factor)
    expected = ao_output(raw[:, AO], inputs.double(), config, k, ray_factor)
    free = ao_output(raw[:, AO], inputs.double(), dataclasses.replace(config, ao_interval=0.0,
                                                                     ao_interval_narrows_past=0.0), k, ray_factor)
    assert ((out[:, AO].double() - expected).abs() <= 1e-5 * (magnitude[:, AO] + 1)).all()
    assert (expected - free).abs().max() > 0.05
    if narrows_past:
        wide = ao_output(raw[:, AO], inputs.double(), dataclasses.replace(config, ao_interval_narrows_past=0.0), k,
                         ray_factor)
        assert (expected - wide).abs().max() > 1e-3


def test_a_gated_tail_scales_each_frame_s_geometry_corrections_by_its_rays_per_pixel():
    """geometry_gate: frame 0 at 4 rays per pixel takes the 4th gate, frame 1 at 2 the 2nd (float64 reference);
    depth and AO as ungated; the gates must come with a gated config and only with it."""
    h, w = 13, 21
    features, taps, bias, inputs = tail_case(h, w, 16, 24)
    inputs[0, SAMPLING.start + 1], inputs[1, SAMPLING.start + 1] = 1.0, 0.5
    config, gates = ReconNetConfig(ao_prior="rays", max_ao_rays=16, geometry_gate=True), torch.tensor(
        [0.9, 0.3, 0.6, 0.1], device=DEVICE)
    out, _ = recon_tail(features, taps, bias, ReconSources.of_inputs(inputs), config, gates=gates)
    raw, magnitude = (t[:, :6, :h, :w] for t in conv_ref(nchw(features), taps, bias))
    given, gate = inputs.double(), geometry_gate(torch.logit(gates.double()), inputs, config).double()
    assert gate.flatten().tolist() == pytest.approx([0.1, 0.3])
    tail = torch.cat([(given[:, MASK] + gate * raw[:, MASK]).clamp(0, 1), given[:, NORMAL] + gate * raw[:, NORMAL],
                      given[:, DEPTH], ao_output(raw[:, AO], given, config)], dim=1)
    err = (out.double() - tail).abs()
    assert (err <= 1e-5 * (magnitude + 1)).all(), err.max()
    inputs[1, SAMPLING.start + 1] = float("nan")  # a non-finite sampling reads as the most rays per pixel
    out, _ = recon_tail(features, taps, bias, ReconSources.of_inputs(inputs), config, gates=gates)
    assert geometry_gate(torch.logit(gates), inputs, config).flatten().tolist() == pytest.approx([0.1, 0.1])
    torch.testing.assert_close(out[1, NORMAL].double(), given[1, NORMAL] + 0.1 * raw[1, NORMAL], rtol=0, atol=1e-4)
    sources = ReconSources.of_inputs(inputs)
    for wrong_config, wrong_gates in ((config, None), (ReconNetConfig(ao_prior="rays", max_ao_rays=16), gates),
                                      (config, gates[:3]), (config, gates.double())):
        with pytest.raises(ValueError, match="a gated model's tail takes its"):
            recon_tail(features, taps, bias, sources, wrong_config, gates=wrong_gates)


@pytest.mark.parametrize("shading", [ShadingParams(), ShadingParams(shininess=0.0, light_dir=(0.0, 0.0, -1.0),
                                                                    albedo=(1.0, 0.0, 0.5), background=(0.0, 0.2, 1.0))])
def test_tail_writes_the_output_buffers_and_shades_them(shading):
    """as_buffers: the raw tail through buffer_stack (unit normals, depth where covered); the color
    as shade() of those buffers, per frame; a light from behind and shininess 0 (0 ** 0 = 1)."""
    h, w = 13, 21
    features, taps, bias, inputs = tail_case(h, w, 16, 24)
    inputs[:, MASK.start, :3] = 0  # uncovered rows: normals and depth 0 there
    config = ReconNetConfig(ao_prior="rays", max_ao_rays=16)
    sources = ReconSources.of_inputs(inputs)
    raw, _ = recon_tail(features, taps, bias, sources, config)
    stack, color = recon_tail(features, taps, bias, sources, config, as_buffers=True, shading=shading)
    torch.testing.assert_close(stack, buffer_stack(raw), rtol=0, atol=1e-6)
    assert color.shape == (2, h, w, 3)
    for i in range(2):
        frame = stack_buffers(stack[i:i + 1])
        torch.testing.assert_close(color[i], shade(frame.mask, frame.normal, frame.ao, shading), rtol=0, atol=1e-5)
    assert (stack[:, NORMAL][stack[:, MASK].expand(-1, 3, -1, -1) == 0] == 0).all()


def test_tail_checks_its_inputs():
    features, taps, bias = rand(1, 8, 8, 16, dtype=torch.float16), rand(9, 16, 16, dtype=torch.float16), rand(16)
    with pytest.raises(ValueError, match=r"recon_tail: inputs of 9x8 need 9x8 features, got 8x8"):
        recon_tail(features, taps, bias, ReconSources.of_inputs(rand(1, 8, 9, 8)), ReconNetConfig())
    with pytest.raises(ValueError, match=r"recon_tail: 2 frames of inputs for 1 of features"):
        recon_tail(features, taps, bias, ReconSources.of_inputs(rand(2, 8, 8, 8)), ReconNetConfig())
    with pytest.raises(ValueError, match=r"recon_tail: shading shades the output buffers"):
        recon_tail(features, taps, bias, ReconSources.of_inputs(rand(1, 8, 8, 8)), ReconNetConfig(),
                   shading=ShadingParams())
    sources = ReconSources.of_inputs(rand(1, 8, 8, 8))
    for out in (rand(1, 6, 8, 7), rand(1, 6, 8, 8, dtype=torch.float16), rand(1, 8, 8, 6).permute(0, 3, 1, 2)):
        with pytest.raises(ValueError, match=r"recon_tail: out must be a contiguous float32 \(1, 6, 8, 8\) tensor"):
            recon_tail(features, taps, bias, sources, ReconNetConfig(), out=out)


@pytest.mark.parametrize("model", ["x1", "x2"])
def test_a_frame_writes_its_stack_into_the_previous_output_it_read(model):
    """``out`` the previous output itself (a CUDA graph's state): the pack reads it before the
    tail overwrites it, so the frame equals one written to a new tensor, bit for bit."""
    _, fused = shipped(RECON_X2_MODEL if model == "x2" else DEFAULT_RECON_MODEL)
    s = fused.config.upscale
    state, previous = torch.empty(1, 6, 6 * s, 9 * s, device=DEVICE), None
    sampling = torch.full((1, 2, 1, 1), 0.125, device=DEVICE)
    with torch.no_grad():
        for frame in synthetic_frames(2, 6, 9):  # a first frame, then one that reads the state
            args = (frame.mask, frame.normal, frame.depth, frame.ao, sampling, frame.flow)
            stack, color, flags = fused.frame(*args, previous, ShadingParams())
            into, color_into, flags_into = fused.frame(*args, None if previous is None else state, ShadingParams(),
                                                       out=state)
            assert into is state
            previous = stack
            for got, expected in ((into, stack), (color_into, color), (flags_into, flags)):
                torch.testing.assert_close(got, expected, rtol=0, atol=0)


def test_frames_of_several_streams_in_one_call_equal_each_frame_alone():
    """The service's batch (FusedReconNet.frames): two streams' frames, each with its own previous
    output and flow, in one call equal each stream's frame alone, flags per frame."""
    _, fused = shipped(DEFAULT_RECON_MODEL)
    sampling = torch.full((1, 2, 1, 1), 0.125, device=DEVICE)
    streams = [synthetic_frames(2, 6, 9), synthetic_frames(3, 6, 9)[1:]]  # other buffers, flows and states
    with torch.no_grad():
        firsts = [fused.frame(f[0].mask, f[0].normal, f[0].depth, f[0].ao, sampling, None, None, ShadingParams())
                  for f in streams]
        alone = [fused.frame(f[1].mask, f[1].normal, f[1].depth, f[1].ao, sampling, f[1].flow, first[0],
                             ShadingParams()) for f, first in zip(streams, firsts)]
        second = [f[1] for f in streams]
        stack, color, flags = fused.frames(*(torch.stack([getattr(f, n) for f in second])
                                             for n in ("mask", "normal", "depth", "ao", "flow")),
                                           sampling=sampling, previous=torch.cat([first[0] for first in firsts]),
                                           shading=ShadingParams())
    for k, (s, c, fl) in enumerate(alone):
        torch.testing.assert_close(stack[k:k + 1], s, rtol=1e-3, atol=1e-3)
        torch.testing.assert_close(color[k], c, rtol=1e-3, atol=1e-3)
        torch.testing.assert_close(flags[k], fl, rtol=0, atol=0)


@pytest.mark.parametrize("ao_prior", AO_PRIORS)
def test_tail_of_an_x2_model_writes_depth_to_space_over_the_upsampled_inputs(ao_prior):
    """24 output channels computed as 32, pixel-shuffled to twice the sides, over
    upsampled_inputs (bilinear, depth nearest); as buffers and shaded at that size too."""
    h, w, hp, wp = 7, 11, 8, 16
    features = rand(2, hp, wp, 16, seed=45, dtype=torch.float16)
    taps, bias = tap_weights(rand(24, 16, 3, 3, scale=0.3, seed=46), 16, 32), torch.zeros(32, device=DEVICE)
    bias[:24] = rand(24, seed=47)
    inputs = recon_batch(2, h, w, seed=48).to(DEVICE)
    raw, magnitude = (F.pixel_shuffle(t[:, :24, :h, :w], 2) for t in conv_ref(nchw(features), taps, bias))
    given = upsampled_inputs(inputs.double(), 2)
    config, blend = ReconNetConfig(ao_prior=ao_prior, max_ao_rays=16, upscale=2), BLEND_RAYS.get(ao_prior)
    sources = ReconSources.of_inputs(inputs)
    out, _ = recon_tail(features, taps, bias, sources, config, blend_rays=blend)
    assert out.shape == (2, 6, 2 * h, 2 * w)
    expected = torch.cat([(given[:, MASK] + raw[:, MASK]).clamp(0, 1), given[:, NORMAL] + raw[:, NORMAL],
                          given[:, DEPTH], ao_output(raw[:, AO], given, config, blend_tensor(ao_prior))], dim=1)
    err = (out.double() - expected).abs()
    assert (err <= 1e-5 * (magnitude + 1)).all(), err.max()
    shading = ShadingParams()
    stack, color = recon_tail(features, taps, bias, sources, config, as_buffers=True, shading=shading,
                              blend_rays=blend)
    torch.testing.assert_close(stack, buffer_stack(out), rtol=0, atol=1e-6)
    for i in range(2):
        frame = stack_buffers(stack[i:i + 1])
        torch.testing.assert_close(color[i], shade(frame.mask, frame.normal, frame.ao, shading), rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match=r"recon_tail: the model's tail has 24 outputs, the weights 16"):
        recon_tail(features, taps[..., :16].contiguous(), bias[:16], sources, config, blend_rays=blend)
    with pytest.raises(ValueError, match="blend_rays goes with a blend model's tail"):
        recon_tail(features, taps, bias, sources, config, blend_rays=None if blend else 2.0)


# ---------------------------------------------------------------- the whole network


# The shipped model's body without its blend, map and gates: the model before it, over the input rays.
SHIPPED_BODY = DEFAULT_RECON_MODEL.parent / "recon_model_v4"


@functools.cache
def shipped_under(ao_prior: str) -> tuple[ReconNet, FusedReconNet]:
    """The shipped model's body (:data:`SHIPPED_BODY`) under an AO prior (the output's AO differs, the rest
    not; "blend" at :data:`BLEND_RAYS`'s weight), and it fused."""
    net, _ = load_pretrained(SHIPPED_BODY, torch.device(DEVICE))
    net.config = dataclasses.replace(net.config, ao_prior=ao_prior)
    if ao_prior == "blend":
        net.register_parameter(BLEND_PARAMETER, nn.Parameter(torch.tensor(math.log(BLEND_RAYS["blend"]), device=DEVICE)))
    return net.eval(), fused_reconnet(net)


def reference(net, inputs, warped):
    with torch.no_grad():
        return net.double()(inputs.double(), warped.double()).float(), net.float()


# The AO prior changes the tail alone (tested under both above); the interpreter is slow. 16 x 24
# needs no padding and still spans several programs down to half size; a one-pixel frame and a
# one-row one are padded to 8 x 8 and 8 x 40 and cropped back.
@pytest.mark.parametrize("ao_prior, b, h, w", [("none", 1, 13, 21), ("rays", 1, 16, 24), ("rays", 1, 1, 1),
                                                ("none", 1, 1, 37), ("blend", 1, 16, 24)])
def test_the_fused_shipped_model_equals_reconnet(ao_prior, b, h, w):
    net, fused = shipped_under(ao_prior)
    assert isinstance(fused, FusedReconNet)
    inputs = recon_batch(b, h, w, seed=17).to(DEVICE)
    previous, flow = rand(b, 6, h, w, seed=18).sigmoid(), rand(b, 2, h, w, scale=2.0, seed=19)
    with torch.no_grad():
        stepped, read = fused.step(inputs, flow, previous)
        first, first_read = fused.step(inputs, None, None)
        given = fused(inputs, warp_by_flow(previous, flow))
    warped = warp_by_flow(previous.double(), flow.double()).float()
    expected, _ = reference(net, inputs, warped)
    for out in (stepped, given):
        assert out.shape == (b, 6, h, w) and out.dtype == torch.float32 and torch.isfinite(out).all()
        # fp16 features through 9 convolutions: errors of a few 1e-4 on the shipped model
        torch.testing.assert_close(out, expected, rtol=0, atol=2e-3)
        torch.testing.assert_close(out[:, DEPTH], inputs[:, DEPTH], rtol=0, atol=0)
    assert (stepped - given).abs().max() < 2e-3
    torch.testing.assert_close(read.double(), warped[:, [MASK.start, AO.start]].double(), rtol=1e-3, atol=1e-4)
    stand_in = net.first_previous(inputs)
    torch.testing.assert_close(first, reference(net, inputs, stand_in)[0], rtol=0, atol=2e-3)
    torch.testing.assert_close(first_read, stand_in[:, [MASK.start, AO.start]].half(), rtol=0, atol=0)  # as packed


def test_a_fused_blend_model_counts_the_rays_fed_past_what_it_reads_as_reconnet():
    """``ray_factor`` (a frame of 4 times the rays the model reads): the fused blend model's output equals
    ReconNet's at that factor (padded from one pixel to 8 x 8), and differs from its output at factor 1."""
    net, fused = shipped_under("blend")
    inputs, warped = recon_batch(1, 1, 1, seed=23).to(DEVICE), rand(1, 6, 1, 1, seed=24).sigmoid()
    inputs[:, SAMPLED_AO] = 0.9 * inputs[:, MASK]  # a bright mean, so that its weight shows
    with torch.no_grad():
        got, once = fused(inputs, warped, 4.0), fused(inputs, warped)
        expected = net.double()(inputs.double(), warped.double(), 4.0).float()
        net.float()
    torch.testing.assert_close(got, expected, rtol=0, atol=2e-3)
    assert not torch.equal(got[:, AO], once[:, AO])


@pytest.mark.parametrize("spp", [1, 4])
def test_a_fused_gated_model_equals_reconnet(spp):
    """A blend model with gated geometry (gates 0.88, 0.27, 0.62, 0.05 by rays per pixel): fused equals ReconNet
    at 1 and 4 rays per pixel (padded from one pixel to 8 x 8)."""
    base, _ = shipped_under("blend")
    net = same_weights(base, geometry_gate=True)
    with torch.no_grad():
        getattr(net, GATE_PARAMETER).copy_(torch.tensor([2.0, -1.0, 0.5, -3.0]) / GATE_RATE)
    fused = fused_reconnet(net)
    inputs = recon_batch(1, 1, 1, ao_rays=4, spp=spp, seed=25, limits=net.config.limits).to(DEVICE)
    warped = rand(1, 6, 1, 1, seed=26).sigmoid()
    with torch.no_grad():
        got = fused(inputs, warped)
    torch.testing.assert_close(got, reference(net, inputs, warped)[0], rtol=0, atol=2e-3)


@pytest.mark.parametrize("spp, variance", [(1, False), (4, False), (1, True), (4, True)])
def test_a_fused_blend_map_model_equals_reconnet(spp, variance):
    """A blend model with a per-pixel weight (``blend_map``: its conv in the tail's depth rows) and gates, its
    weight by the rays' variance or not (``blend_variance``): fused equals ReconNet (16 x 24, a map varying over
    it), its depth still the input's."""
    base, _ = shipped_under("blend")
    net = same_weights(base, geometry_gate=True, blend_map=True, blend_variance=variance)
    with torch.no_grad():
        weight = net.ao_blend_map.weight
        weight.copy_(0.3 * torch.randn(weight.shape, generator=torch.Generator().manual_seed(27)))
        net.ao_blend_map.bias.fill_(1.0)
    fused = fused_reconnet(net)
    inputs = recon_batch(1, 16, 24, ao_rays=4, spp=spp, seed=28, limits=net.config.limits).to(DEVICE)
    warped = rand(1, 6, 16, 24, seed=29).sigmoid()
    with torch.no_grad():
        got = fused(inputs, warped)
        unmapped = fused_reconnet(same_weights(net, blend_map=False))(inputs, warped)
    torch.testing.assert_close(got, reference(net, inputs, warped)[0], rtol=0, atol=2e-3)
    torch.testing.assert_close(got[:, DEPTH], inputs[:, DEPTH], rtol=0, atol=0)
    assert (got[:, AO] - unmapped[:, AO]).abs().max() > 1e-2  # the map changed the AO


@pytest.mark.parametrize("blocks, widths, stem", [(0, (16, 16, 32, 64), 1), (1, (16, 16, 32, 64), 1),
                                                  (2, (8, 16, 32, 32), 1), (1, (4, 12, 24, 40), 1),
                                                  (2, (32, 32, 64, 64), 2), (2, (32, 64, 64, 64), 2),
                                                  (0, (12, 32, 64, 64), 2)])
def test_other_architectures_fuse_too(blocks, widths, stem):
    """Without residual blocks, or with one; widths other than the shipped: narrower at full resolution (8 or 4
    channels, stored as they are), or not powers of 2; a stem of stride 2 (no layer at the input's resolution,
    the tail's cells over an odd side dropped)."""
    torch.manual_seed(3)
    net = ReconNet(ReconNetConfig(widths=widths, blocks=blocks, stem_stride=stem)).to(DEVICE).eval()
    fused = fused_reconnet(net)
    inputs, warped = recon_batch(1, 6, 9, seed=31).to(DEVICE), rand(1, 6, 6, 9, seed=32).sigmoid()
    with torch.no_grad():
        got = fused(inputs, warped)
    torch.testing.assert_close(got, reference(net, inputs, warped)[0], rtol=0, atol=2e-3)
    # the passes, run one by one, are the ones whose traffic fused_traffic counts
    results, passes = fused.passes(ReconSources.of_inputs(inputs), warped)
    with torch.no_grad():
        for _, run in passes:
            run()
    assert [name for name, _ in passes] == list(fused_traffic(6, 9, net.config, warp=False))
    torch.testing.assert_close(results["output"], got, rtol=0, atol=0)


def pixel_tail_net(stem: int, width: int) -> ReconNet:
    """A blend model with map and gates (the stem's recipe, ``configs/train_recon_stem_pixel.json``) and a pixel tail
    of ``width`` whose last layer is not zero (as trained, unlike at its start): random, seeded."""
    torch.manual_seed(4)
    net = ReconNet(ReconNetConfig(widths=(32, 32, 64, 64), stem_stride=stem, ao_prior="blend", max_ao_rays=16,
                                  geometry_gate=True, blend_map=True, pixel_tail=width)).to(DEVICE).eval()
    with torch.no_grad():
        for layer in (net.pixel_tail[2], net.ao_blend_map):
            layer.weight.normal_(0.0, 0.3)
            layer.bias.normal_(0.0, 0.3)
    return net


@pytest.mark.parametrize("stem, width, h, w", [(2, 16, 6, 9), (1, 16, 5, 7), (2, 24, 1, 3)])
def test_a_pixel_tail_model_fused_equals_reconnet(stem, width, h, w):
    """A pixel tail (an MLP per output pixel of the tail's raw outputs, the inputs and the previous mask and AO,
    read from the pack) on a stem of stride 2 and at full resolution, 16 hidden units or 24 (padded to 32), over
    odd sides: its step, its first frame and its forward of a warped previous output equal ReconNet's; without
    the MLP the output differs (the test sees it)."""
    net = pixel_tail_net(stem, width)
    fused = fused_reconnet(net)
    inputs = recon_batch(1, h, w, ao_rays=4, spp=2, seed=61, limits=net.config.limits).to(DEVICE)
    previous, flow = rand(1, 6, h, w, seed=62).sigmoid(), rand(1, 2, h, w, scale=2.0, seed=63)
    with torch.no_grad():
        stepped, read = fused.step(inputs, flow, previous)
        first, _ = fused.step(inputs, None, None)
        expected, warped = net.double().step(inputs.double(), flow.double(), previous.double())
        expected_first = net(inputs.double(), net.first_previous(inputs.double()))
        given = fused(inputs, warped.float())
        without = fused_reconnet(same_weights(net.float(), pixel_tail=0))(inputs, warped.float())
    for got, ref in ((stepped, expected), (given, expected), (first, expected_first)):
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got.double(), ref, rtol=0, atol=2e-3)
    torch.testing.assert_close(read.double(), warped[:, [MASK.start, AO.start]], rtol=1e-3, atol=1e-4)
    assert (without - given).abs().max() > 1e-2
    _, passes = fused.passes(ReconSources.of_inputs(inputs), warped.float())
    assert [name for name, _ in passes] == list(fused_traffic(h, w, net.config, warp=False))


def test_a_pixel_tail_models_frame_equals_its_step_as_buffers():
    """The frame path (the render's buffers read in place, the sampling as two values, written as buffers and
    shaded) of a pixel tail model: its stack is the step's output as buffer_stack makes it, and finite."""
    net = pixel_tail_net(2, 16)
    fused = fused_reconnet(net)
    sampling = torch.full((1, 2, 1, 1), 0.125, device=DEVICE)
    frame = synthetic_frames(1, 6, 9)[0]
    with torch.no_grad():
        stack, color, _ = fused.frame(frame.mask, frame.normal, frame.depth, frame.ao, sampling, None, None,
                                      ShadingParams())
        inputs = torch.cat([frame.mask[None], frame.normal.permute(2, 0, 1), frame.depth[None], frame.ao[None],
                            sampling[0].expand(2, 6, 9)])[None]
        output, _ = fused.step(inputs, None, None)
    assert torch.isfinite(stack).all() and torch.isfinite(color).all()
    torch.testing.assert_close(stack, buffer_stack(output), rtol=0, atol=1e-5)


def test_recon_tail_checks_a_pixel_tail():
    net = pixel_tail_net(1, 16)
    fused = fused_reconnet(net)
    features = rand(1, 8, 8, 32, seed=64, dtype=torch.float16)
    sources = ReconSources.of_inputs(recon_batch(1, 8, 8, seed=65).to(DEVICE))
    mlp = fused.pixel_tail_mlp()
    packed = torch.zeros(1, 8, 8, 16, device=DEVICE, dtype=torch.float16)
    blend = dict(blend_rays=4.0, gates=fused.gates)
    with pytest.raises(ValueError, match=r"recon_tail: a pixel_tail model's tail takes its MLP and the packed inputs"):
        recon_tail(features, fused.tail_w, fused.tail_b, sources, net.config, **blend)
    with pytest.raises(ValueError, match=r"recon_tail: packed \(pack_inputs' output\) must be a contiguous float16"):
        recon_tail(features, fused.tail_w, fused.tail_b, sources, net.config, **blend, packed=packed.float(),
                   pixel_tail=mlp)
    with pytest.raises(ValueError, match=r"recon_tail: the pixel tail's out must be a contiguous"):
        recon_tail(features, fused.tail_w, fused.tail_b, sources, net.config, **blend, packed=packed,
                   pixel_tail=dataclasses.replace(mlp, out=mlp.out.float()))


@pytest.mark.parametrize("b, h, w", [(1, 11, 13), (1, 1, 1)])
def test_the_shipped_x2_model_fused_equals_reconnet(b, h, w):
    """The shipped x2 model: its step (the previous output at twice the sides, warped by the flow
    upsampled), its first frame and its forward of a warped previous output."""
    net, _ = load_pretrained(RECON_X2_MODEL, torch.device(DEVICE))
    net = net.eval()
    fused = fused_reconnet(net)
    inputs = recon_batch(b, h, w, seed=49).to(DEVICE)
    previous, flow = rand(b, 6, 2 * h, 2 * w, seed=50).sigmoid(), rand(b, 2, h, w, scale=2.0, seed=51)
    with torch.no_grad():
        stepped, read = fused.step(inputs, flow, previous)
        first, first_read = fused.step(inputs, None, None)
        expected, warped = net.double().step(inputs.double(), flow.double(), previous.double())
        stand_in = net.first_previous(inputs.double())
        expected_first = net(inputs.double(), stand_in)
        given = fused(inputs, warped.float())
    assert stepped.shape == (b, 6, 2 * h, 2 * w) and torch.isfinite(stepped).all()
    for got, ref in ((stepped, expected), (given, expected), (first, expected_first)):
        torch.testing.assert_close(got.double(), ref, rtol=0, atol=2e-3)
    torch.testing.assert_close(read.double(), warped[:, [MASK.start, AO.start]], rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(first_read.double(), stand_in[:, [MASK.start, AO.start]], rtol=1e-3, atol=1e-4)
    assert [name for name, _ in fused.passes(ReconSources.of_inputs(inputs), None)[1]] == list(
        fused_traffic(h, w, net.config))


@functools.cache
def shipped(folder: Path) -> tuple[ReconNet, FusedReconNet]:
    net, _ = load_pretrained(folder, torch.device(DEVICE))
    return net.eval(), fused_reconnet(net)


@pytest.mark.parametrize("model", [*(f"x1, AO prior {prior}" for prior in AO_PRIORS), "x1", "x2", "pixel tail"])
def test_hard_frames_stay_finite_and_within_fp16s_own_error(model):
    """An all-empty frame, and depths at fp16's limit for the networks under a previous output all
    ones: finite, in range, and per channel at most 1.5 times as far from the float64 reference as
    ReconNet under fp16 autocast (at depth 1e4 both are off by tenths on the normals, whose raw
    values reach hundreds). The shipped models, x1 (its map and gates) and x2, x1's body under each AO prior, and a
    stem with a pixel tail (random weights: its MLP reads the depth of 1e4 too)."""
    folders = {"x1": DEFAULT_RECON_MODEL, "x2": RECON_X2_MODEL}
    if model == "pixel tail":
        net = pixel_tail_net(2, 16)
        fused = fused_reconnet(net)
    else:
        net, fused = shipped(folders[model]) if model in folders else shipped_under(model.rsplit(" ", 1)[1])
    h, w, s = 6, 9, net.config.upscale
    empty = recon_batch(1, h, w, seed=20).to(DEVICE)
    empty[:, :6] = 0
    deep = recon_batch(1, h, w, seed=21).to(DEVICE)
    deep[:, DEPTH] = torch.where(deep[:, MASK] > 0, FP16_MAX_DEPTH, 0.0)
    cases = ((empty, torch.zeros(1, 6, s * h, s * w, device=DEVICE)),
             (deep, torch.ones(1, 6, s * h, s * w, device=DEVICE)))
    for inputs, warped in cases:
        with torch.no_grad(), torch.autocast(DEVICE, dtype=torch.float16):
            half = net(inputs, warped).float()
        with torch.no_grad():
            out = fused(inputs, warped)
        expected, _ = reference(net, inputs, warped)
        assert torch.isfinite(out).all()
        assert (out[:, MASK] >= 0).all() and (out[:, MASK] <= 1).all()
        assert (out[:, AO] >= 0).all() and (out[:, AO] <= 1).all()
        error = (out - expected).abs().amax(dim=(0, 2, 3))
        assert (error <= 1.5 * (half - expected).abs().amax(dim=(0, 2, 3)) + 2e-3).all(), error


def assert_buffers_close(got: FrameBuffers, expected: FrameBuffers) -> None:
    """An fp16 frame's buffers within fp16's reach of the fp32 reference's: mask, AO and color
    within 2e-3; depth and unit normals where both cover a pixel (mask > 0, the buffers' rule), and
    where only one does, its mask within that tolerance of 0 (seen on an H100: 5e-5 against 0, the
    eager fp16 path too, so a unit normal against none)."""
    for name in ("mask", "ao", "color"):
        torch.testing.assert_close(getattr(got, name), getattr(expected, name), rtol=0, atol=2e-3)
    both = (got.mask > 0) & (expected.mask > 0)
    either = (got.mask > 0) | (expected.mask > 0)
    assert (torch.maximum(got.mask, expected.mask)[either & ~both] <= 2e-3).all()
    torch.testing.assert_close(got.depth[both], expected.depth[both], rtol=0, atol=2e-3)
    # Unit normals of short output normals (where the input had none) turn fp16's rounding
    # into 1e-2 (eager fp16 too).
    torch.testing.assert_close(got.normal[both], expected.normal[both], rtol=0, atol=3e-2)


def synthetic_frames(count: int, h: int, w: int, positions: bool = False) -> list[FrameBuffers]:
    """Random frames as a render gives them (mask, unit normals, depth, AO of 2 rays) and flows;
    with ``positions``, points on a plane (the ray history takes the texels near the flow's)."""
    frames = []
    ys, xs = torch.meshgrid(torch.arange(h, device=DEVICE), torch.arange(w, device=DEVICE), indexing="ij")
    for i in range(count):
        x = recon_batch(1, h, w, seed=30 + i)[0].to(DEVICE)
        flow = None if i == 0 else rand(h, w, 2, scale=1.5, seed=40 + i)
        position = torch.stack([xs * 0.01, ys * 0.01, torch.zeros_like(xs)], dim=-1).float() if positions else None
        frames.append(FrameBuffers(mask=x[MASK.start], normal=x[NORMAL].permute(1, 2, 0), depth=x[DEPTH.start],
                                   ao=x[AO.start], flow=flow, position=position))
    return frames


def test_the_fastest_reconstructor_fuses_on_cuda_in_fp16_only():
    assert isinstance(Reconstructor.fastest(device=DEVICE).net, FusedReconNet) == (DEVICE == "cuda")
    assert not isinstance(Reconstructor.fastest(device=DEVICE, precision="bf16").net, FusedReconNet)


def test_the_service_reconstructs_by_the_fused_kernels_on_cuda_in_fp16():
    pytest.importorskip("msgspec", reason="the service's wire stack is not installed here (the GPU kit lacks it)")
    from isosr_server.engine import serving_network

    served = serving_network(Reconstructor, DEFAULT_RECON_MODEL, DEVICE, "fp16")
    assert isinstance(served.net, FusedReconNet) == (DEVICE == "cuda") and not served.graphs
    assert not isinstance(serving_network(Reconstructor, DEFAULT_RECON_MODEL, DEVICE, "fp32").net, FusedReconNet)


@pytest.fixture(scope="module")
def stem_model(tmp_path_factory) -> Path:
    """A model folder of the shipped x1 model's config with a stem of stride 2, its weights drawn."""
    config = dataclasses.replace(shipped(DEFAULT_RECON_MODEL)[0].config, widths=(32, 32, 64, 64), stem_stride=2)
    torch.manual_seed(5)
    folder = tmp_path_factory.mktemp("stem")
    save_pretrained(ReconNet(config), folder)
    return folder


@pytest.mark.parametrize("positions", [False, True], ids=["rays alone", "ray history"])
@pytest.mark.parametrize("model", [DEFAULT_RECON_MODEL, RECON_X2_MODEL, "stem"])
def test_a_fused_reconstructor_follows_the_reference_frame_by_frame(model, positions, request):
    """The Reconstructor's fused path (its recurrence, warp and shading) against the fp32 eager
    one over a short sequence, the shipped x1 and x2 models and a stem of stride 2 (odd sides), with and
    without the ray history (per-pixel sampling planes); on CUDA also replayed from CUDA graphs."""
    model = request.getfixturevalue("stem_model") if model == "stem" else model
    variants = [Reconstructor(model, device=DEVICE, precision="fp16", fused=True)]
    if DEVICE == "cuda":
        variants.append(Reconstructor(model, device=DEVICE, precision="fp16", fused=True, graphs=True))
    assert all(isinstance(v.net, FusedReconNet) for v in variants)
    reference = Reconstructor(model, device=DEVICE)
    shading = ShadingParams()
    for frame in synthetic_frames(2, 6, 9, positions):  # the second reads the first's output
        expected = reference.reconstruct(frame, 2, 1, shading)
        for variant in variants:
            got = variant.reconstruct(frame, 2, 1, shading)
            read = [MASK.start, AO.start]  # of the previous output, what the next frame reads
            torch.testing.assert_close(variant.previous[:, read], reference.previous[:, read], rtol=0, atol=2e-3)
            assert_buffers_close(got, expected)



def test_a_fused_reconstructor_refuses_a_bad_frame_and_keeps_its_state():
    """The pack's flags raise what the reference's checks raise; the previous output stays."""
    first, second = synthetic_frames(2, 6, 9)
    variants = [Reconstructor(device=DEVICE, precision="fp16", fused=True)]
    if DEVICE == "cuda":
        variants.append(Reconstructor(device=DEVICE, precision="fp16", fused=True, graphs=True))
    for recon in variants:
        recon.reconstruct(first, 2, 1)
        kept = recon.previous.clone()
        for broken, value, message in [("normal", float("nan"), "normal holds NaN or Inf"),
                                       ("flow", float("inf"), "flow holds NaN or Inf"),
                                       ("ao", 2.0, r"ao holds values outside \[0, 1\]"),
                                       ("depth", 2e4, "fp16 takes depths up to 10000, this frame reaches 2e")]:
            bad = dataclasses.replace(second, **{broken: getattr(second, broken).clone()})
            getattr(bad, broken)[3, 4] = value
            with pytest.raises(ValueError, match=message):
                recon.reconstruct(bad, 2, 1, ShadingParams())
            assert torch.equal(recon.previous, kept)
        assert torch.isfinite(recon.reconstruct(second, 2, 1).ao).all()
