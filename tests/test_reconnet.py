"""ReconNet (full-resolution reconstruction), its inputs, the `Reconstructor`, and the shipped model."""

from __future__ import annotations

import math
import os
from dataclasses import replace

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest, open_volume, orbit, orbit_path, resolve_iso
from isosr_render.conventions import AO, DEPTH, MASK, NORMAL, RECON_CHANNELS, SAMPLED_AO, SAMPLING
from isosr_render.sequence import sequence_requests
from isosr_render.shading import ShadingParams, shade
from isosr_net.budget import color_psnr, reference_frames
from isosr_net.methods import FrameMethod, make_runner, run_sequence
from isosr_net.model import save_pretrained
from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.fused_recon import FusedReconNet, fusable
from isosr_net.inference import buffer_stack
from isosr_net.reconnet import (GATE_PARAMETER, GATE_RATE, RayLimits, ReconNet, ReconNetConfig, ao_output,
                                blend_rays_at, interval_z, macs_per_pixel, rays_interval, upsampled_inputs)
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, RECON_X2_MODEL, Reconstructor, recon_inputs, recon_limits
from isosr_net.upscaler import DEFAULT_MODEL

SIZE = (96, 64)  # width, height


def recon_batch(b: int = 2, h: int = 16, w: int = 24, ao_rays: int = 2, spp: int = 1,
                dtype: torch.dtype = torch.float32, seed: int = 0, limits: RayLimits = RayLimits()) -> torch.Tensor:
    """Random ReconNet inputs laid out as RECON_CHANNELS: a binary mask, unit normals, depth, AO, sampling."""
    gen = torch.Generator().manual_seed(seed)
    mask = (torch.rand(b, 1, h, w, generator=gen) > 0.4).to(dtype)
    normal = torch.nn.functional.normalize(torch.randn(b, 3, h, w, generator=gen), dim=1).to(dtype) * mask
    depth = (1.0 + torch.rand(b, 1, h, w, generator=gen)).to(dtype) * mask
    ao = torch.rand(b, 1, h, w, generator=gen).to(dtype) * mask
    base = torch.cat([mask, normal, depth, ao], dim=1)
    return torch.cat([base, limits.channels(ao_rays, spp, base)], dim=1)


def net(seed: int = 0, **config) -> ReconNet:
    torch.manual_seed(seed)
    return ReconNet(ReconNetConfig(**config)).eval()


def same_weights(model: ReconNet, **changes) -> ReconNet:
    """A ReconNet of ``model``'s config with ``changes``, holding ``model``'s weights (those both have; its own
    extra parameters at their start), on its device."""
    twin = ReconNet(replace(model.config, **changes)).to(next(model.parameters()).device).eval()
    twin.load_state_dict(model.state_dict(), strict=False)
    return twin


# ---------------------------------------------------------------- the network


@pytest.mark.parametrize("stem", [1, 2])
@pytest.mark.parametrize("h, w", [(16, 24), (13, 21), (5, 7), (1, 9)])
def test_any_frame_size_comes_back_at_its_size(h, w, stem):
    inputs = recon_batch(h=h, w=w)
    with torch.no_grad():
        out = net(stem_stride=stem)(inputs, torch.rand(2, 6, h, w))
    assert out.shape == (2, 6, h, w) and torch.isfinite(out).all()


@pytest.mark.parametrize("h, w", [(16, 24), (13, 21), (1, 1)])
def test_a_stem_model_writes_each_of_its_features_cells_to_its_own_input_pixel(h, w):
    """With the stem of stride 2, the tail's 4 outputs per channel and feature pixel land on the 2 x 2 input
    pixels under it (depth-to-space, then cropped to the frame): a bias on one cell moves those pixels alone."""
    model = net(stem_stride=2)
    inputs = recon_batch(b=1, h=h, w=w, seed=4)
    with torch.no_grad():
        model.tail.weight.zero_()
        model.tail.bias.zero_()
        model.tail.bias[MASK.start * 4 + 3] = -2.0  # the mask's cell (1, 1): odd rows and columns
        out = model(inputs, torch.rand(1, 6, h, w))
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    moved = (rows % 2 == 1) & (cols % 2 == 1)
    torch.testing.assert_close(out[0, 0][~moved], inputs[0, 0][~moved], rtol=0, atol=0)
    assert (out[0, 0][moved] == 0).all()  # clamped at 0
    torch.testing.assert_close(out[:, NORMAL], inputs[:, NORMAL], rtol=0, atol=0)


def test_mask_lies_in_the_unit_interval_and_ao_strictly_inside_it():
    inputs = recon_batch(h=19, w=11)
    with torch.no_grad():
        out = net(seed=3)(inputs * 5.0, torch.randn(2, 6, 19, 11) * 5.0)  # far outside the trained range
    assert out[:, MASK].min() >= 0 and out[:, MASK].max() <= 1
    assert out[:, AO].min() > 0 and out[:, AO].max() < 1


@pytest.mark.parametrize("config", [{}, {"widths": (8, 12, 20, 24), "blocks": 3},
                                    {"widths": (32, 32, 64, 64), "stem_stride": 2},
                                    {"widths": (32, 32, 64, 64), "stem_stride": 2, "pixel_tail": 16},
                                    {"upscale": 2, "pixel_tail": 8}])
def test_macs_per_pixel_counts_every_convolution(config):
    model = net(**config)
    h, w, s = 32, 48, model.config.upscale  # multiples of 16: no padding
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        model(recon_batch(b=1, h=h, w=w), torch.zeros(1, 6, h * s, w * s))
    assert counter.get_total_flops() / 2 / (h * w * s * s) == pytest.approx(macs_per_pixel(model.config), rel=1e-12)


def test_first_previous_from_the_inputs_takes_sampled_ao_where_rays_were_cast_else_the_mask():
    inputs = torch.cat([recon_batch(b=1, ao_rays=0, seed=1), recon_batch(b=1, ao_rays=2, seed=2)])
    inputs[0, SAMPLED_AO] = 0.0  # what recon_inputs stores without AO rays
    first = net(first_frame="inputs").first_previous(inputs)
    assert first.shape == (2, 6, 16, 24)
    torch.testing.assert_close(first[:, :AO.start], inputs[:, :AO.start], rtol=0, atol=0)
    torch.testing.assert_close(first[0, AO], inputs[0, MASK], rtol=0, atol=0)
    torch.testing.assert_close(first[1, AO], inputs[1, SAMPLED_AO], rtol=0, atol=0)
    assert not torch.equal(inputs[1, SAMPLED_AO], inputs[1, MASK])  # the two cases differ here
    zeros = net(first_frame="zeros").first_previous(inputs)
    assert zeros.shape == (2, 6, 16, 24) and (zeros == 0).all()


def test_step_warps_the_previous_output_and_needs_a_flow_for_it():
    model = net()
    inputs, previous = recon_batch(), torch.rand(2, 6, 16, 24)
    with torch.no_grad():
        out, warped = model.step(inputs, None, None)
        torch.testing.assert_close(warped, model.first_previous(inputs))
        torch.testing.assert_close(out, model(inputs, warped))
        _, warped = model.step(inputs, torch.zeros(2, 2, 16, 24), previous)
        torch.testing.assert_close(warped, previous, rtol=0, atol=1e-6)  # zero flow: nothing moves
    with pytest.raises(ValueError, match="needs the flow"):
        model.step(inputs, None, previous)


def test_forward_checks_shapes():
    with pytest.raises(ValueError, match="inputs"):
        net()(torch.zeros(1, 5, 8, 8), torch.zeros(1, 6, 8, 8))
    with pytest.raises(ValueError, match="prev_warped"):
        net()(torch.zeros(1, 8, 8, 8), torch.zeros(1, 6, 8, 16))


@pytest.mark.parametrize("kwargs, match", [
    ({"widths": (16, 32, 64)}, "widths must be 4 positive integers"),
    ({"widths": (16, 32, 64, 64, 64)}, "widths must be 4 positive integers"),
    ({"widths": (16, 0, 64, 64)}, "widths must be 4 positive integers"),
    ({"widths": (16, 32.0, 64, 64)}, "widths must be 4 positive integers"),
    ({"widths": (True, 32, 64, 64)}, "widths must be 4 positive integers"),
    ({"blocks": -1}, "blocks must be >= 0"),
    ({"first_frame": "upsampled"}, "first_frame must be one of"),
    ({"ao_prior": "mean"}, "ao_prior must be one of"),
    ({"max_ao_rays": 0}, "max_ao_rays must be an integer >= 1, got 0"),
    ({"max_spp": True}, "max_spp must be an integer >= 1, got True"),
    ({"stem_stride": 4}, r"stem_stride must be one of \(1, 2\), got 4"),
    ({"stem_stride": True}, r"stem_stride must be one of \(1, 2\), got True"),
    ({"stem_stride": 2.0}, r"stem_stride must be one of \(1, 2\), got 2.0"),
    ({"stem_stride": 2, "upscale": 2}, "stem_stride 2 goes with upscale 1, got upscale 2"),
    ({"pixel_tail": -1}, "pixel_tail must be an integer >= 0, got -1"),
    ({"pixel_tail": True}, "pixel_tail must be an integer >= 0, got True"),
    ({"pixel_tail": 8.0}, "pixel_tail must be an integer >= 0, got 8.0"),
])
def test_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ReconNetConfig(**kwargs)


def test_config_widths_from_json_become_a_tuple():
    assert ReconNetConfig(widths=[8, 8, 16, 16]).widths == (8, 8, 16, 16)


def test_float32_matches_float64():
    model = net(seed=5)
    inputs, prev = recon_batch(h=13, w=21, seed=5), torch.rand(2, 6, 13, 21, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        single = model(inputs, prev)
        double = model.double()(inputs.double(), prev.double())
    torch.testing.assert_close(single.double(), double, rtol=0, atol=1e-5)


def test_a_pixel_tail_starts_as_the_model_without_it_and_corrects_each_pixel_from_its_own_inputs():
    """pixel_tail: zero at the start (the same output as the model it starts from); trained, a pixel's correction
    moves with that pixel's inputs alone, and equals its MLP in float64."""
    stem = net(seed=2, widths=(8, 8, 16, 16), stem_stride=2, ao_prior="blend", geometry_gate=True)
    tailed = same_weights(stem, pixel_tail=8)
    inputs, prev = recon_batch(h=13, w=21, seed=2), torch.rand(2, 6, 13, 21, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        torch.testing.assert_close(tailed(inputs, prev), stem(inputs, prev), rtol=0, atol=0)
        for p in tailed.pixel_tail.parameters():
            p.copy_(torch.randn_like(p))
    raw, rec = torch.randn(1, 6, 5, 7, dtype=torch.float64), torch.rand(1, 2, 5, 7, dtype=torch.float64)
    base = recon_batch(b=1, h=5, w=7, seed=3).double()
    tailed.double()
    with torch.no_grad():
        out = tailed.correction(raw, base, rec)
        moved = base.clone()
        moved[..., 2, 3] += 0.5
        changed = (tailed.correction(raw, moved, rec) - out).abs().amax(dim=1)[0]
    assert changed[2, 3] > 0 and changed.count_nonzero() == 1
    w1, b1 = tailed.pixel_tail[0].weight[..., 0, 0], tailed.pixel_tail[0].bias
    w2, b2 = tailed.pixel_tail[2].weight[..., 0, 0], tailed.pixel_tail[2].bias
    x = torch.cat([raw, base, rec], dim=1)
    hidden = torch.relu(torch.einsum("oc,bchw->bohw", w1, x) + b1.view(1, -1, 1, 1))
    torch.testing.assert_close(out, raw + torch.einsum("oc,bchw->bohw", w2, hidden) + b2.view(1, -1, 1, 1))


@pytest.mark.parametrize("ao_rays, spp", [(0, 1), (1, 1), (16, 4)])
def test_a_pixel_tail_of_huge_weights_keeps_the_outputs_finite_and_in_range(ao_rays, spp):
    model = net(seed=4, widths=(8, 8, 16, 16), stem_stride=2, ao_prior="blend", geometry_gate=True, pixel_tail=8,
                max_ao_rays=16)
    with torch.no_grad():
        for p in model.pixel_tail.parameters():
            p.copy_(torch.randn_like(p) * 1e3)
        out = model(recon_batch(h=9, w=11, ao_rays=ao_rays, spp=spp, limits=RayLimits(16, 4)),
                    torch.randn(2, 6, 9, 11) * 5.0)
    assert torch.isfinite(out).all()
    assert out[:, MASK].min() >= 0 and out[:, MASK].max() <= 1 and out[:, AO].min() >= 0 and out[:, AO].max() <= 1


# ---------------------------------------------------------------- AO over the input rays


def prior_reference(ao: float, rays: int, spp: int, raw: float) -> float:
    """sigmoid(logit((n a + 1/2) / (n + 1)) + raw) in float64, n = rays * spp."""
    n = rays * spp
    p = (n * ao + 0.5) / (n + 1)
    z = math.log(p / (1 - p)) + raw
    return 1 / (1 + math.exp(-z))


@pytest.mark.parametrize("rays, spp", [(0, 1), (0, 4), (1, 1), (2, 2), (8, 1), (16, 4)])
def test_ao_over_the_rays_matches_float64_and_stays_finite_in_the_unit_interval(rays, spp):
    config = ReconNetConfig(ao_prior="rays", max_ao_rays=16)
    gen = torch.Generator().manual_seed(rays * 10 + spp)
    ao = torch.cat([torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 4), torch.rand(1, 1, 4, 4, generator=gen)])
    inputs = recon_batch(b=3, h=4, w=4, ao_rays=rays, spp=spp, limits=config.limits)
    inputs[:, SAMPLED_AO] = ao
    raw = torch.randn(3, 1, 4, 4, generator=gen) * 3
    out = ao_output(raw, inputs, config)
    expected = torch.tensor([prior_reference(a, rays, spp, r) for a, r in zip(ao.flatten().tolist(),
                                                                                raw.flatten().tolist())],
                            dtype=torch.float64).view_as(out)
    torch.testing.assert_close(out.double(), expected, rtol=0, atol=1e-6)
    for extreme in (-1e4, 1e4):  # a saturated correction: 0 or 1, never NaN
        pinned = ao_output(torch.full_like(raw, extreme), inputs, config)
        assert torch.isfinite(pinned).all() and pinned.min() >= 0 and pinned.max() <= 1
    if rays == 0:  # no rays: prior 1/2, today's sigmoid exactly
        assert torch.equal(out, torch.sigmoid(raw))


@pytest.mark.parametrize("rays, spp", [(0, 1), (1, 1), (4, 2), (16, 4)])
@pytest.mark.parametrize("variance", [False, True])
def test_a_blended_ao_weighs_the_rays_mean_by_their_count_in_float64(rays, spp, variance):
    """ao_prior "blend": w a + (1 - w) o, w = n / (n + k), with ``blend_variance`` k times 4 p (1 - p) of the
    smoothed mean p = (n a + 1/2) / (n + 1), against float64; finite and in [0, 1] for a saturated correction
    and an extreme k; the rays' output exactly where no rays were cast."""
    config = ReconNetConfig(ao_prior="blend", max_ao_rays=16, blend_variance=variance)
    gen = torch.Generator().manual_seed(rays * 10 + spp)
    inputs = recon_batch(b=2, h=4, w=4, ao_rays=rays, spp=spp, limits=config.limits)
    inputs[0, SAMPLED_AO, 0] = 1.0  # a row of rays that all agree (lit)
    raw = torch.randn(2, 1, 4, 4, generator=gen) * 3
    k = torch.tensor(6.0)
    out = ao_output(raw, inputs, config, k)
    n = rays * spp

    def blended(a: float, r: float) -> float:
        p = (n * a + 0.5) / (n + 1)
        k_a = k.item() * (4 * p * (1 - p) if variance else 1.0)
        return (n * a + k_a * prior_reference(a, rays, spp, r)) / (n + k_a)

    expected = torch.tensor([blended(a, r) for a, r in zip(inputs[:, SAMPLED_AO].flatten().tolist(),
                                                           raw.flatten().tolist())], dtype=torch.float64).view_as(out)
    torch.testing.assert_close(out.double(), expected, rtol=0, atol=1e-6)
    for extreme, blend in ((-1e4, torch.tensor(1e-30)), (1e4, torch.tensor(1e30))):
        pinned = ao_output(torch.full_like(raw, extreme), inputs, config, blend)
        assert torch.isfinite(pinned).all() and pinned.min() >= 0 and pinned.max() <= 1
    if rays == 0:
        assert torch.equal(out, ao_output(raw, inputs, ReconNetConfig(ao_prior="rays", max_ao_rays=16)))
    with pytest.raises(ValueError, match="needs its blend_rays"):
        ao_output(raw, inputs, config)


def test_with_many_rays_a_blend_model_converges_to_the_rays_mean_whatever_its_tail():
    """Never worse than its input (issue 49): however wrong the tail, the AO of a "blend" model tends to the
    rays' mean as their count grows (here k = 16 rays against 64 and, pushed, 6400), while a "rays" model's
    correction stays as large."""
    model = net(ao_prior="blend", max_ao_rays=16)
    torch.nn.init.constant_(model.tail.bias, 4.0)  # a tail far off: +4 in logit space
    inputs = recon_batch(b=1, ao_rays=16, spp=4, limits=model.config.limits)
    mean = inputs[:, SAMPLED_AO]
    with torch.no_grad():
        off = (model(inputs, model.first_previous(inputs))[:, AO] - mean).abs().max().item()
        model.ao_blend_log.fill_(math.log(16.0 / 100))  # 100 times the rays against it
        closer = (model(inputs, model.first_previous(inputs))[:, AO] - mean).abs().max().item()
    assert off <= 16 / (64 + 16) + 1e-6 and closer <= 0.16 / 64.16 + 1e-6 and closer < off / 50
    rays = same_weights(model, ao_prior="rays")
    with torch.no_grad():
        assert (rays(inputs, rays.first_previous(inputs))[:, AO] - mean).abs().max().item() > 0.3


def test_the_rays_interval_holds_the_truth_as_often_as_its_z_says_and_narrows_with_the_rays():
    """rays_interval (Wilson, z = 2): over binomial draws of n rays the true AO lies within it in >= 93% of them on
    average over p at every n (nominally 95%) and >= 85% at every p (Wilson's dips next to 0 and 1), it holds the
    rays' own mean, its width shrinks about as 1 / sqrt(n), it is [0, 1] without rays, and it stays within [0, 1]
    for means of rays that all agree."""
    gen = torch.Generator().manual_seed(0)
    truth = torch.tensor([0.0, 0.02, 0.3, 0.5, 0.9, 0.99, 1.0], dtype=torch.float64).view(1, 1, 1, -1)
    for n in (1, 4, 16, 64, 256, 4096):
        draws = torch.binomial(torch.full((4000, 1, 1, 7), float(n), dtype=torch.float64), truth.expand(4000, 1, 1, 7),
                               generator=gen) / n
        low, high = rays_interval(draws, torch.full_like(draws, n), 2.0)
        covered = ((low <= truth) & (truth <= high)).double().mean(0)
        assert covered.mean() >= 0.93 and covered.min() >= 0.85, (n, covered)
        assert (low <= draws).all() and (draws <= high).all() and low.min() >= 0 and high.max() <= 1
    widths = [float(torch.sub(*reversed(rays_interval(torch.tensor([0.5]), torch.tensor([n]), 2.0)))) for n in
              (16.0, 1600.0)]
    assert widths[0] / 10 < widths[1] < widths[0] / 8  # 1 / sqrt(n) but for the z^2 / n terms
    low, high = rays_interval(torch.tensor([0.3, 1.0]), torch.tensor([0.0, 1e12]), 3.0)
    assert low.tolist()[0] == 0 and high.tolist()[0] == 1 and 1 - 1e-6 < low[1] <= high[1] <= 1


def test_an_interval_model_corrects_a_mean_only_as_far_as_its_rays_allow():
    """ao_interval: a "blend" or "rays" model's AO lies within the rays' interval of all the rays behind the mean
    (``ray_factor`` counted), so a tail far off moves a mean of 256 rays by at most ~0.1 and one of a million by
    ~0.002, where without it the blend alone moves it by 16 / (256 + 16); no rays: the network's AO as without it."""
    for prior in ("blend", "rays"):
        config = ReconNetConfig(ao_prior=prior, max_ao_rays=16, ao_interval=2.0)
        inputs = recon_batch(b=1, ao_rays=16, spp=4, limits=config.limits)
        raw, mean = torch.full_like(inputs[:, :1], 4.0), inputs[:, SAMPLED_AO]
        blend = torch.tensor(16.0) if prior == "blend" else None
        for factor, bound in ((4.0, 0.13), (1.6e4, 2.6e-3)):
            out = ao_output(raw, inputs, config, blend, ray_factor=factor)
            low, high = rays_interval(mean, torch.full_like(mean, 64 * factor), 2.0)
            assert (out >= low - 1e-6).all() and (out <= high + 1e-6).all()
            assert (out - mean).abs().max() <= bound
        free = replace(config, ao_interval=0.0)
        assert (ao_output(raw, inputs, free, blend, 4.0) - mean).abs().max() > 0.13
        none = recon_batch(b=1, ao_rays=0, spp=1, limits=config.limits)
        assert torch.equal(ao_output(raw, none, config, blend), ao_output(raw, none, free, blend))
    for bad, match in (({"ao_prior": "none"}, "needs ao_prior"), ({"ao_prior": "rays", "ao_interval": -1.0}, ">= 0")):
        with pytest.raises(ValueError, match=match):
            ReconNetConfig(**{"ao_interval": 2.0, **bad})


def test_the_interval_narrows_as_one_over_the_rays_behind_the_mean_past_its_point():
    """ao_interval_narrows_past 16: z 2 up to 16 rays per pixel (and without rays), 1 at 64, 0.5 at 256, so the
    interval's width falls about as 1 / n there (1 / sqrt(n) below); a frame of 64 rays per pixel gets the AO of
    a constant z = 1, one of 256 (64 the model reads, ``ray_factor`` 4) that of z = 0.5, one of 4 that of z = 2;
    it needs an interval and a count >= 0 that float32 holds (1e300 overflowed it at the first frame)."""
    rays = torch.tensor([0.0, 4.0, 16.0, 64.0, 256.0]).view(1, 1, 1, -1)
    assert interval_z(2.0, rays, 16.0).flatten().tolist() == [2.0, 2.0, 2.0, 1.0, 0.5]
    assert interval_z(2.0, rays, 0.0).flatten().tolist() == [2.0] * 5
    half = torch.tensor([0.5] * 3).view(1, 1, 1, -1)
    count = torch.tensor([16.0, 64.0, 256.0]).view(1, 1, 1, -1)
    low, high = rays_interval(half, count, interval_z(2.0, count, 16.0))
    width = (high - low).flatten()
    assert 3.6 < width[0] / width[1] < 4.4 and 3.6 < width[1] / width[2] < 4.4
    narrowing = ReconNetConfig(ao_prior="blend", max_ao_rays=16, ao_interval=2.0, ao_interval_narrows_past=16.0)
    blend = torch.tensor(16.0)
    for ao_rays, spp, factor, z in ((16, 4, 1.0, 1.0), (16, 4, 4.0, 0.5), (4, 1, 1.0, 2.0)):
        inputs = recon_batch(b=1, ao_rays=ao_rays, spp=spp, limits=narrowing.limits)
        raw = torch.full_like(inputs[:, :1], 4.0)
        constant = replace(narrowing, ao_interval=z, ao_interval_narrows_past=0.0)
        torch.testing.assert_close(ao_output(raw, inputs, narrowing, blend, factor),
                                   ao_output(raw, inputs, constant, blend, factor))
    for bad, match in (({"ao_interval": 0.0}, "needs ao_interval"), ({"ao_interval_narrows_past": -1.0}, ">= 0"),
                       ({"ao_interval_narrows_past": math.inf}, "finite"),
                       ({"ao_interval_narrows_past": 1e300}, "in float32"), ({"ao_interval": 1e300}, "in float32")):
        with pytest.raises(ValueError, match=match):
            ReconNetConfig(**{"ao_prior": "rays", "ao_interval": 2.0, "ao_interval_narrows_past": 16.0, **bad})


def test_a_blend_model_counts_the_rays_fed_past_what_it_reads_in_float64():
    """64 AO rays at spp 4 read as the model's 16 (``ray_factor`` 4): the blend weighs the mean by the 256 rays
    behind it, ``w = 256 / (256 + k)``, against float64 from the "rays" model of the same weights (its AO the
    network's own); a "rays" model's output does not depend on the factor."""
    model = net(ao_prior="blend", max_ao_rays=16)
    torch.nn.init.constant_(model.tail.bias, 4.0)  # a tail far off, so that the weight shows
    rays = same_weights(model, ao_prior="rays")
    inputs = recon_batch(b=1, ao_rays=16, spp=4, limits=model.config.limits)
    warped, mean, k = model.first_previous(inputs), inputs[:, SAMPLED_AO].double(), model.blend_rays.item()
    with torch.no_grad():
        own = rays(inputs, warped)[:, AO].double()
        for factor in (1.0, 4.0, 1e6):
            n = 64 * factor
            torch.testing.assert_close(model(inputs, warped, factor)[:, AO].double(), (n * mean + k * own) / (n + k),
                                       rtol=0, atol=1e-6)
        assert torch.equal(rays(inputs, warped, 4.0), rays(inputs, warped))


def test_a_gated_model_scales_each_frame_s_geometry_corrections_by_its_rays_per_pixel():
    """geometry_gate: in one batch, a frame at 1 ray per pixel and one at 4 take their own gates (sigmoid of
    the logits), on the mask and normal corrections alone (float64 from the ungated twin's tail); at the
    gates' start (logit 6) the output is the ungated one within 0.3% of each correction."""
    gated = net(ao_prior="rays", max_ao_rays=16, geometry_gate=True)
    plain = same_weights(gated, geometry_gate=False)
    inputs = torch.cat([recon_batch(b=1, ao_rays=4, spp=s, seed=s, limits=gated.config.limits) for s in (1, 4)])
    warped, raws = plain.first_previous(inputs), []
    plain.tail.register_forward_hook(lambda module, args, out: raws.append(out.double()))
    with torch.no_grad():
        at_start, ungated = gated(inputs, warped).double(), plain(inputs, warped).double()
        getattr(gated, GATE_PARAMETER).copy_(torch.tensor([1.5, -2.0, 0.0, -4.0]) / GATE_RATE)
        out = gated(inputs, warped).double()
    raw, base = raws[0], inputs.double()
    gate = torch.sigmoid(torch.tensor([1.5, -4.0], dtype=torch.float64)).view(2, 1, 1, 1)
    torch.testing.assert_close(out[:, MASK], (base[:, MASK] + gate * raw[:, MASK]).clamp(0, 1), rtol=0, atol=1e-5)
    torch.testing.assert_close(out[:, NORMAL], base[:, NORMAL] + gate * raw[:, NORMAL], rtol=0, atol=1e-5)
    torch.testing.assert_close(out[:, AO], ungated[:, AO], rtol=0, atol=0)
    assert ((at_start - ungated).abs() <= 0.003 * raw[:, :6].abs() + 1e-6).all()
    with pytest.raises(ValueError, match="geometry_gate must be true or false"):
        ReconNetConfig(geometry_gate="yes")


def test_a_blend_map_weighs_each_pixel_by_its_own_rays_in_float64():
    """blend_map: ``k exp(m)`` per pixel, ``m`` the map's 3x3 conv of the tail's features: at its start (zero)
    the output is the scalar blend's exactly; with a map set, ``w = n / (n + k exp(m))`` against float64 from
    the "rays" twin's AO (the network's own) and the map's output; a saturated map gives the mean or the
    network's AO, finite; a map needs a blend model."""
    model = net(ao_prior="blend", max_ao_rays=16, blend_map=True)
    torch.nn.init.constant_(model.tail.bias, 2.0)  # the network's AO off the mean, so that the weight shows
    scalar, rays = same_weights(model, blend_map=False), same_weights(model, ao_prior="rays", blend_map=False)
    inputs = recon_batch(b=2, ao_rays=4, spp=2, limits=model.config.limits)
    warped, mean, maps = model.first_previous(inputs), inputs[:, SAMPLED_AO].double(), []
    model.ao_blend_map.register_forward_hook(lambda module, args, out: maps.append(out.double()))
    with torch.no_grad():
        assert torch.equal(model(inputs, warped), scalar(inputs, warped))
        torch.nn.init.normal_(model.ao_blend_map.weight, std=0.5, generator=torch.Generator().manual_seed(5))
        out, own = model(inputs, warped)[:, AO].double(), rays(inputs, warped)[:, AO].double()
        n, k = 8.0, model.blend_rays.item()
        weight = n / (n + k * maps[-1].exp())
        assert maps[-1].std() > 0.1  # the weight varies over the frame
        torch.testing.assert_close(out, weight * mean + (1 - weight) * own, rtol=0, atol=1e-6)
        for bias, expected in ((-1e4, mean), (1e4, own)):
            torch.nn.init.zeros_(model.ao_blend_map.weight)
            torch.nn.init.constant_(model.ao_blend_map.bias, bias)
            pinned = model(inputs, warped)[:, AO].double()
            assert torch.isfinite(pinned).all()
            torch.testing.assert_close(pinned, expected, rtol=0, atol=1e-6)
    with pytest.raises(ValueError, match="blend_map weighs a blend model's AO"):
        ReconNetConfig(ao_prior="rays", blend_map=True)
    with pytest.raises(ValueError, match="blend_map must be true or false"):
        ReconNetConfig(ao_prior="blend", blend_map=1)
    with pytest.raises(ValueError, match="blend_variance weighs a blend model's AO"):
        ReconNetConfig(ao_prior="rays", blend_variance=True)


def test_a_blend_model_learns_its_weight_and_fine_tunes_from_a_rays_model(tmp_path):
    model = net(ao_prior="blend", max_ao_rays=16).train()
    inputs = recon_batch(b=1, ao_rays=4, spp=1, limits=model.config.limits)
    model(inputs, model.first_previous(inputs))[:, AO].mean().backward()
    assert model.ao_blend_log.grad is not None and model.ao_blend_log.grad.abs() > 0
    assert model.blend_rays.item() == pytest.approx(16.0) and net(ao_prior="rays").blend_rays is None


def test_ao_from_scratch_is_the_plain_sigmoid_whatever_the_rays():
    inputs, raw = recon_batch(ao_rays=8, spp=4), torch.randn(2, 1, 16, 24)
    assert torch.equal(ao_output(raw, inputs, ReconNetConfig()), torch.sigmoid(raw))


def test_a_silent_tail_returns_the_smoothed_mean_of_the_rays():
    """With the tail's output zero the network adds nothing: AO is the prior, close to the rays'
    mean with many rays, 1/2 with none."""
    model = net(ao_prior="rays", max_ao_rays=16)
    torch.nn.init.zeros_(model.tail.weight)
    torch.nn.init.zeros_(model.tail.bias)
    for rays, spp in ((16, 4), (1, 1), (0, 1)):
        inputs = recon_batch(b=1, ao_rays=rays, spp=spp, limits=model.config.limits)
        with torch.no_grad():
            out = model(inputs, model.first_previous(inputs))
        n = rays * spp
        torch.testing.assert_close(out[:, AO], (n * inputs[:, SAMPLED_AO] + 0.5) / (n + 1))
        torch.testing.assert_close(out[:, MASK], inputs[:, MASK].clamp(0, 1))


def test_ao_over_the_rays_in_bfloat16_autocast_stays_finite_and_close_to_float32():
    model = net(ao_prior="rays", max_ao_rays=16)
    inputs = recon_batch(ao_rays=16, spp=4, limits=model.config.limits)
    inputs[0, SAMPLED_AO] = 1.0
    inputs[1, SAMPLED_AO] = 0.0
    prev = model.first_previous(inputs)
    with torch.no_grad():
        full = model(inputs, prev)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            half = model(inputs, prev).float()
    assert torch.isfinite(half).all() and half[:, AO].min() >= 0 and half[:, AO].max() <= 1
    torch.testing.assert_close(half[:, AO], full[:, AO], rtol=0, atol=2e-2)


# ---------------------------------------------------------------- inputs


@pytest.fixture(scope="module")
def sphere():
    volume = open_volume("proc:sphere@32")
    return Renderer(volume, "cpu"), resolve_iso("proc:sphere@32", volume)


@pytest.fixture(scope="module")
def sphere_frames(sphere) -> list[FrameBuffers]:
    """Two frames of the sphere at 96x64 along an orbit: mask, normal, depth, AO of 2 rays, and the
    second's flow from the first."""
    renderer, iso = sphere
    cameras = [orbit(30.0, 20.0, 1.6), orbit(34.0, 20.0, 1.6)]
    requests = sequence_requests(cameras, *SIZE, iso, ("mask", "normal", "depth", "ao", "flow"), ao_samples=2)
    return [renderer.render(camera, request) for camera, request in requests]


def fresh(frame: FrameBuffers, **changes) -> FrameBuffers:
    """A copy of ``frame`` with ``changes`` (None drops a buffer)."""
    buffers = {name: getattr(frame, name).clone() for name in frame.present()}
    buffers.update(changes)
    return FrameBuffers(**buffers)


def test_recon_inputs_lay_out_the_channels(sphere_frames):
    frame = sphere_frames[1]
    inputs, flow, history = recon_inputs(frame, 2, 3, RayLimits())
    assert inputs.shape == (1, len(RECON_CHANNELS), SIZE[1], SIZE[0]) and inputs.dtype == torch.float32
    torch.testing.assert_close(inputs[0, MASK][0], frame.mask, rtol=0, atol=0)
    torch.testing.assert_close(inputs[0, NORMAL], frame.normal.permute(2, 0, 1), rtol=0, atol=0)
    torch.testing.assert_close(inputs[0, DEPTH][0], frame.depth, rtol=0, atol=0)
    torch.testing.assert_close(inputs[0, SAMPLED_AO][0], frame.ao, rtol=0, atol=0)
    assert (inputs[0, SAMPLING][0] == 2 / 8).all() and (inputs[0, SAMPLING][1] == 3 / 4).all()
    assert flow.shape == (1, 2, SIZE[1], SIZE[0]) and history is None  # no position: no history
    wide, *_ = recon_inputs(frame, 12, 2, RayLimits(16, 2))  # each model's own scale
    assert (wide[0, SAMPLING][0] == 12 / 16).all() and (wide[0, SAMPLING][1] == 1).all()
    no_ao, *_ = recon_inputs(fresh(frame, ao=None), 0, 1, RayLimits())
    assert (no_ao[0, SAMPLED_AO] == 0).all() and (no_ao[0, SAMPLING][0] == 0).all()


@pytest.mark.parametrize("change, ao_rays, spp, match", [
    ({"normal": "nan"}, 2, 1, "normal holds NaN or Inf"),
    ({"depth": "inf"}, 2, 1, "depth holds NaN or Inf"),
    ({"ao": 1.5}, 2, 1, r"outside \[0, 1\]"),
    ({"ao": -0.25}, 2, 1, r"outside \[0, 1\]"),
    ({"ao": "nan"}, 2, 1, r"outside \[0, 1\]"),
    ({"ao": None}, 2, 1, "needs the frame's ao buffer"),
    ({}, 9, 1, r"ao_rays must be an integer in \[0, 8\], got 9"),
    ({}, -1, 1, "ao_rays must be"),
    ({}, True, 1, "ao_rays must be .*got True"),
    ({}, 2, 0, "spp must be"),
    ({}, 2, 1.0, "spp must be"),
    ({}, 2, 8, r"spp must be an integer in \[1, 4\], got 8"),
])
def test_recon_inputs_refuse_hostile_frames(sphere_frames, change, ao_rays, spp, match):
    frame = fresh(sphere_frames[0])
    for name, value in change.items():
        if value is None:
            setattr(frame, name, None)
        else:
            getattr(frame, name)[3, 5:9] = float(value)
    with pytest.raises(ValueError, match=match):
        recon_inputs(frame, ao_rays, spp, RayLimits())


def test_recon_inputs_refuse_a_misshapen_ao(sphere_frames):
    with pytest.raises(ValueError, match="ao"):
        recon_inputs(fresh(sphere_frames[0], ao=torch.zeros(SIZE[1], SIZE[0] - 1)), 2, 1, RayLimits())


# ---------------------------------------------------------------- the Reconstructor


def assert_sane(out: FrameBuffers, height: int, width: int) -> None:
    """Reconstructed buffers: finite, at the frame size, mask and AO in [0, 1], unit normals where covered."""
    assert out.present() == ["mask", "normal", "depth", "ao"]
    for name in out.present():
        assert torch.isfinite(getattr(out, name)).all(), name
    assert out.mask.shape == (height, width) and out.normal.shape == (height, width, 3)
    assert out.mask.min() >= 0 and out.mask.max() <= 1 and out.ao.min() >= 0 and out.ao.max() <= 1
    covered = out.mask > 0
    torch.testing.assert_close(out.normal[covered].norm(dim=-1), torch.ones(int(covered.sum())), rtol=0, atol=1e-4)


def test_the_shipped_model_loads_without_arguments():
    reconstructor = Reconstructor()
    assert isinstance(reconstructor.net, ReconNet) and reconstructor.upscale_factor == 1
    assert reconstructor.precision == "fp32" and reconstructor.device == torch.device("cpu")


@pytest.mark.parametrize("model, prior, limits, narrows_past", [
    (DEFAULT_RECON_MODEL, "blend", RayLimits(16, 4), 16.0),
    (DEFAULT_RECON_MODEL.parent / "recon_model_v7", "blend", RayLimits(16, 4), 64.0),
    (DEFAULT_RECON_MODEL.parent / "recon_model_v6", "blend", RayLimits(16, 4), 64.0),
    (DEFAULT_RECON_MODEL.parent / "recon_model_v5", "blend", RayLimits(16, 4), 64.0),
    (DEFAULT_RECON_MODEL.parent / "recon_model_v4", "rays", RayLimits(16, 4), None),
    (DEFAULT_RECON_MODEL.parent / "recon_model_v1", "none", RayLimits(8, 4), None)])
def test_the_shipped_models_keep_their_configs_and_their_ao_is_that_of_their_tail(sphere_frames, model, prior, limits,
                                                                                  narrows_past):
    """The default and the ones before it (their AO blended with the input rays' mean per pixel, within the rays'
    interval, which narrows past ``narrows_past`` rays), one before those (a correction of that mean) and the
    first model (AO from scratch, a plain sigmoid)."""
    reconstructor = Reconstructor(model)
    config = reconstructor.net.config
    assert (config.ao_prior, config.limits, recon_limits(model)) == (prior, limits, limits)
    assert config.blend_map == config.geometry_gate == (prior == "blend")
    assert (config.blend_beyond, config.ao_interval, config.ao_interval_narrows_past) == (
        (2.0, 2.0, narrows_past) if narrows_past else (0.0, 0.0, 0.0))
    raws, inputs, maps = [], [], []
    reconstructor.net.tail.register_forward_hook(lambda module, args, out: raws.append(out))
    reconstructor.net.register_forward_pre_hook(lambda module, args: inputs.append(args[0]))
    if config.blend_map:
        reconstructor.net.ao_blend_map.register_forward_hook(lambda module, args, out: maps.append(out.float()))
    out = reconstructor.reconstruct(sphere_frames[0], 2, 1)
    blend_rays = reconstructor.net.blend_rays * torch.exp(maps[0]) if maps else None
    expected = ao_output(raws[0][:, AO], inputs[0], config, blend_rays)[0, 0]
    torch.testing.assert_close(out.ao, expected, rtol=0, atol=0)
    if prior == "none":
        torch.testing.assert_close(out.ao, torch.sigmoid(raws[0][0, AO][0]), rtol=0, atol=0)


def test_a_pixel_tail_model_folder_reconstructs(sphere_frames, tmp_path):
    """A saved stem with a (trained-looking) pixel tail loads and reconstructs rendered frames sanely, recurrent;
    the fused kernels take it (their tail runs the MLP: tests/fused_checks.py)."""
    model = net(seed=6, widths=(8, 8, 16, 16), stem_stride=2, ao_prior="blend", geometry_gate=True, pixel_tail=8)
    with torch.no_grad():
        for p in model.pixel_tail.parameters():
            p.copy_(torch.randn_like(p) * 0.3)
    save_pretrained(model, tmp_path / "tailed")
    assert fusable(model.config)
    reconstructor = Reconstructor(tmp_path / "tailed")
    assert reconstructor.net.config.pixel_tail == 8
    for frame in sphere_frames[:2]:
        assert_sane(reconstructor.reconstruct(frame, 2, 1), SIZE[1], SIZE[0])


def test_a_blend_model_reconstructs_through_the_reconstructor_as_its_ao_output_says(sphere_frames, tmp_path):
    """A saved "blend" model loads with its weight and the Reconstructor's AO is :func:`ao_output` of its tail
    with that weight."""
    model = net(seed=3, widths=(4, 4, 8, 8), blocks=1, ao_prior="blend", max_ao_rays=16)
    with torch.no_grad():
        model.ao_blend_log.fill_(math.log(3.0))
    save_pretrained(model, tmp_path / "blend")
    reconstructor = Reconstructor(tmp_path / "blend")
    assert reconstructor.net.blend_rays.item() == pytest.approx(3.0)
    assert fusable(replace(reconstructor.net.config, widths=(16, 16, 32, 32)))  # the tail kernel blends too
    raws, inputs = [], []
    reconstructor.net.tail.register_forward_hook(lambda module, args, out: raws.append(out))
    reconstructor.net.register_forward_pre_hook(lambda module, args: inputs.append(args[0]))
    out = reconstructor.reconstruct(sphere_frames[0], 4, 1)
    expected = ao_output(raws[0][:, AO], inputs[0], reconstructor.net.config, torch.tensor(3.0))[0, 0]
    torch.testing.assert_close(out.ao, expected, rtol=0, atol=1e-6)
    assert torch.isfinite(out.ao).all() and 0 <= out.ao.min() and out.ao.max() <= 1
    # fed 4 times the rays it reads: the mean weighs as 16 rays, the network's AO as its 3 over 4
    reconstructor.reset()
    fed = reconstructor.reconstruct(sphere_frames[0], 4, 1, ray_factor=4.0)
    expected = ao_output(raws[1][:, AO], inputs[1], reconstructor.net.config, torch.tensor(3.0 / 4))[0, 0]
    torch.testing.assert_close(fed.ao, expected, rtol=0, atol=1e-6)
    kept = reconstructor.previous.clone()
    for bad in (0.5, 0, float("nan"), float("inf"), True, "4"):
        with pytest.raises(ValueError, match="ray_factor must be a finite number >= 1"):
            reconstructor.reconstruct(sphere_frames[1], 4, 1, ray_factor=bad)
    assert torch.equal(reconstructor.previous, kept), "a refused factor leaves the stream's state"


def test_past_its_ray_limits_a_blend_beyond_model_trusts_the_rays_mean_more(sphere_frames, tmp_path):
    """``blend_beyond`` g: in a frame of r times the rays the model reads its AO stands for k / r ** g rays (the mean's
    weight n r / (n r + k / r ** g)), so its output lies nearer the mean; within its limits (r = 1), and in a
    model without it, nothing changes. Its weights are a plain blend model's (saved, loaded, fine-tuned alike)."""
    model = net(seed=3, widths=(4, 4, 8, 8), blocks=1, ao_prior="blend", max_ao_rays=16, blend_beyond=1.0)
    with torch.no_grad():
        model.ao_blend_log.fill_(math.log(3.0))
    save_pretrained(model, tmp_path / "beyond")
    reconstructor = Reconstructor(tmp_path / "beyond")
    assert reconstructor.net.config.blend_beyond == 1.0
    raws, inputs = [], []
    reconstructor.net.tail.register_forward_hook(lambda module, args, out: raws.append(out))
    reconstructor.net.register_forward_pre_hook(lambda module, args: inputs.append(args[0]))
    outs = []
    for factor, k in ((1.0, 3.0), (4.0, 3.0 / 4 ** 2)):
        reconstructor.reset()
        outs.append(reconstructor.reconstruct(sphere_frames[0], 4, 1, ray_factor=factor).ao)
        expected = ao_output(raws[-1][:, AO], inputs[-1], reconstructor.net.config, torch.tensor(k))[0, 0]
        torch.testing.assert_close(outs[-1], expected, rtol=0, atol=1e-6)
    plain = same_weights(model, blend_beyond=0.0)
    with torch.no_grad():
        torch.testing.assert_close(model(inputs[0], model.first_previous(inputs[0])),
                                   plain(inputs[0], plain.first_previous(inputs[0])), rtol=0, atol=0)
        discounted = model(inputs[0], model.first_previous(inputs[0]), ray_factor=4.0)[:, AO]
        kept = plain(inputs[0], plain.first_previous(inputs[0]), ray_factor=4.0)[:, AO]
    mean = inputs[0][:, SAMPLED_AO]
    assert torch.isfinite(discounted).all() and ((discounted - mean).abs() <= (kept - mean).abs() + 1e-6).all()
    assert ((discounted - mean).abs() < (kept - mean).abs() - 1e-4).any()
    assert blend_rays_at(None, 4.0, 1.0) is None and blend_rays_at(8.0, 2.0, 2.0) == 1.0
    for bad in (-0.5, math.nan, math.inf, True, "1"):
        with pytest.raises(ValueError, match="blend_beyond must be a finite number >= 0"):
            ReconNetConfig(ao_prior="blend", blend_beyond=bad)
    with pytest.raises(ValueError, match="blend_beyond weighs a blend model's AO"):
        ReconNetConfig(ao_prior="rays", blend_beyond=1.0)


def test_the_reconstruct_method_tells_its_network_the_rays_it_casts_past_the_model_s(sphere):
    renderer, iso = sphere
    factors = [make_runner(FrameMethod.of("reconstruct", ao_rays=a, spp=4), renderer, iso, *SIZE).ray_factor
               for a in (0, 8, 16, 64)]
    assert factors == [1.0, 1.0, 1.0, 4.0]


@pytest.fixture(scope="module")
def wide_model(tmp_path_factory):
    """A random ReconNet over the input rays taking 0-16 AO rays and 1-2 rays per pixel, saved."""
    folder = tmp_path_factory.mktemp("wide_model")
    save_pretrained(net(seed=2, widths=(4, 4, 8, 8), blocks=1, ao_prior="rays", max_ao_rays=16, max_spp=2), folder)
    return folder


def test_a_model_takes_the_rays_of_its_own_limits(wide_model, sphere, sphere_frames):
    assert recon_limits(wide_model) == RayLimits(16, 2)
    renderer, iso = sphere
    frame = renderer.render(orbit(30.0, 20.0, 1.6), RenderRequest(*SIZE, iso, ("mask", "normal", "depth", "ao"),
                                                                   ao_samples=12, spp=2))
    reconstructor = Reconstructor(wide_model)
    out = reconstructor.reconstruct(frame, 12, 2)
    assert_sane(out, SIZE[1], SIZE[0])
    inputs, *_ = recon_inputs(frame, 12, 2, RayLimits(16, 2))
    with torch.no_grad():
        expected = reconstructor.net(inputs, reconstructor.net.first_previous(inputs))
    torch.testing.assert_close(out.ao, expected[0, AO][0], rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"ao_rays must be an integer in \[0, 16\], got 17"):
        reconstructor.reconstruct(sphere_frames[0], 17, 1)
    with pytest.raises(ValueError, match=r"spp must be an integer in \[1, 2\], got 3"):
        reconstructor.reconstruct(sphere_frames[0], 2, 3)


def test_ray_limits_follow_a_rewritten_model_folder(tmp_path):
    """Read once per version of config.json (the views ask per frame), never stale."""
    save_pretrained(net(seed=3, widths=(4, 4, 8, 8), blocks=1, max_ao_rays=16, max_spp=2), tmp_path)
    assert recon_limits(tmp_path) == RayLimits(16, 2)
    save_pretrained(net(seed=3, widths=(4, 4, 8, 8), blocks=1, max_ao_rays=4, max_spp=1), tmp_path)
    config = tmp_path / "config.json"
    stamp = config.stat().st_mtime_ns + 10**9  # a second later, whatever the clock's resolution
    os.utime(config, ns=(stamp, stamp))
    assert recon_limits(tmp_path) == RayLimits(4, 1)


def test_the_frame_method_bounds_are_its_models(wide_model):
    assert FrameMethod.of("reconstruct", ao_rays=16, spp=2, model=str(wide_model)).ao_rays == 16
    with pytest.raises(ValueError, match=r"reconstruct frame method: spp must be an integer in \[1, 2\], got 4"):
        FrameMethod.of("reconstruct", spp=4, model=str(wide_model))
    assert FrameMethod.of("reconstruct", ao_rays=64, spp=4).ao_rays == 64  # read as 16 (RayLimits.read)
    with pytest.raises(ValueError, match=r"reconstruction: ao_rays must be an integer in \[0, 16\], got 17"):
        Reconstructor().reconstruct(FrameBuffers(mask=torch.zeros(2, 2), normal=torch.zeros(2, 2, 3),
                                                 depth=torch.zeros(2, 2), ao=torch.zeros(2, 2)), 17)
    with pytest.raises(ValueError, match="SRNet model, not a reconstruction network"):
        FrameMethod.of("reconstruct", model=str(DEFAULT_MODEL))
    with pytest.raises(FileNotFoundError, match="config.json is missing"):
        FrameMethod.of("reconstruct", model=str(wide_model / "nothing"))


def test_reconstruct_a_rendered_frame(sphere_frames):
    frame = sphere_frames[0]
    out = Reconstructor().reconstruct(frame, 2, 1)
    assert_sane(out, SIZE[1], SIZE[0])
    assert ((out.mask > 0.5) == (frame.mask > 0.5)).float().mean() > 0.98  # the silhouette stays put
    hit = (out.mask > 0.5) & (frame.mask > 0.5)
    # Depth passes through from the render where both cover (the network does not touch it).
    torch.testing.assert_close(out.depth[hit], frame.depth[hit], rtol=0, atol=0)
    assert (out.depth[out.mask == 0] == 0).all()
    assert out.ao[hit].mean() > 0.8  # a sphere occludes little of itself


def test_the_second_frame_carries_the_first_and_a_reset_forgets_it(sphere_frames):
    reconstructor = Reconstructor()
    reconstructor.reconstruct(sphere_frames[0], 2, 1)
    carried = reconstructor.reconstruct(sphere_frames[1], 2, 1)
    reconstructor.reset()
    alone = reconstructor.reconstruct(sphere_frames[1], 2, 1)
    assert_sane(carried, SIZE[1], SIZE[0])
    # The normal: the sphere's AO is near 1, where the rays' interval (ao_interval) leaves the network little room.
    assert (carried.normal - alone.normal).abs().max() > 1e-2
    again = Reconstructor().reconstruct(sphere_frames[1], 2, 1)
    torch.testing.assert_close(alone.normal, again.normal)
    torch.testing.assert_close(alone.ao, again.ao)


def still_frames(renderer: Renderer, iso: float, frames: int, **request) -> list[FrameBuffers]:
    """One view, its rays cast anew each frame (another seed), with positions; flow (zero) after the first."""
    camera, outputs = orbit(30.0, 20.0, 1.6), ("mask", "normal", "depth", "position", "ao")
    return [renderer.render(camera, RenderRequest(*SIZE, iso, outputs + (("flow",) if i else ()), seed=10 + i,
                                                  prev_camera=camera if i else None, **request))
            for i in range(frames)]


def test_the_network_reads_the_accumulated_rays_and_their_count_per_pixel(sphere):
    frames = still_frames(*sphere, 3, ao_samples=2, spp=2)
    reconstructor, net = Reconstructor(), Reconstructor().net
    previous = None
    for frame in frames:
        out = reconstructor.reconstruct(frame, 2, 2)
        history = reconstructor.history
        inputs = torch.cat([frame.mask[None], frame.normal.permute(2, 0, 1), frame.depth[None], history.ao,
                            history.count.clamp(min=4) / net.config.limits.rays(2),
                            torch.full_like(history.ao, 2 / net.config.limits.max_spp)])[None]
        flow = None if frame.flow is None else frame.flow.permute(2, 0, 1)[None]
        with torch.no_grad():
            previous = buffer_stack(net.step(inputs, flow, previous)[0])  # the state a Reconstructor keeps
        torch.testing.assert_close(out.ao, previous[0, AO][0], rtol=0, atol=1e-6)
    covered = frames[0].mask > 0  # any ray per pixel hit
    assert (history.count[0][covered] == 12).all() and (history.count[0][~covered] == 0).all()
    carried = None  # the training data's inputs (isosr_net.datagen) are these
    for frame in frames:
        laid_out, _, carried = recon_inputs(frame, 2, 2, net.config.limits, history=carried)
    torch.testing.assert_close(laid_out, inputs, rtol=0, atol=0)


def test_accumulated_rays_lift_the_reconstruction_of_a_smooth_surface_on_an_orbit():
    """The MRI at 240x136 along the Pareto orbit, 1 AO ray: the same renders reconstructed with their
    positions (accumulated) and without (each frame's rays alone), scored against 64 AO rays at 4
    rays per pixel after a warm-up, as the Pareto study does (there, at 960x540 on a CPU: 33.6 -> 34.8 dB)."""
    from isosr_bench.bench_pareto import bench_cameras
    from isosr_render.catalog import shared_volumes_dir
    if not (shared_volumes_dir() / "volumes.json").is_file():
        pytest.skip(f"shared volumes not found at {shared_volumes_dir()} (set ISOSR_SHARED_VOLUMES)")
    volume = open_volume("shared:avg152t1")
    renderer, iso, size = Renderer(volume, "cpu"), resolve_iso("shared:avg152t1", volume), (240, 136)
    cameras = bench_cameras(8)
    outputs = ("mask", "normal", "depth", "position", "ao", "flow")
    frames = [renderer.render(camera, request)
              for camera, request in sequence_requests(cameras, *size, iso, outputs, ao_samples=1)]
    for i, frame in enumerate(frames):  # new rays each frame
        frame.ao = renderer.render(cameras[i], RenderRequest(*size, iso, ("ao",), seed=100 + i)).ao
    references = [renderer.render(camera, RenderRequest(*size, iso, ("mask", "normal", "ao"), spp=4, ao_samples=64,
                                                        seed=1)) for camera in cameras]
    for reference in references:
        reference.color = shade(reference.mask, reference.normal, reference.ao, ShadingParams())
    psnr = {}
    for name, keep in (("accumulated", {}), ("alone", {"position": None})):
        reconstructor, shading = Reconstructor(), ShadingParams()
        outs = [reconstructor.reconstruct(fresh(frame, **keep), 1, 1, shading) for frame in frames]
        psnr[name] = sum(color_psnr(o, r) for o, r in zip(outs[3:], references[3:])) / 5
    assert psnr["accumulated"] > psnr["alone"] + 0.5, psnr


def test_a_refused_frame_leaves_the_ray_history_alone_and_a_reset_or_a_twin_has_none(sphere):
    frames = still_frames(*sphere, 2, ao_samples=2)
    reconstructor = Reconstructor()
    reconstructor.reconstruct(frames[0], 2, 1)
    kept = reconstructor.history
    hostile = fresh(frames[1])
    hostile.ao[SIZE[1] // 2, SIZE[0] // 2] = float("nan")  # on the sphere: uncovered pixels' AO is not read
    with pytest.raises(ValueError, match="ao"):
        reconstructor.reconstruct(hostile, 2, 1)
    assert reconstructor.history is kept and (kept.count <= 2).all()
    # What a service counts against its bound on held state: the previous output and the history (32 B a pixel).
    assert reconstructor.state_bytes() == reconstructor.previous.nbytes + 32 * SIZE[0] * SIZE[1]
    assert reconstructor.own().history is None
    reconstructor.reset()
    assert reconstructor.history is None and reconstructor.previous is None


def test_a_new_frame_size_starts_over(sphere, sphere_frames):
    renderer, iso = sphere
    request = RenderRequest(48, 32, iso, ("mask", "normal", "depth", "ao", "flow"), ao_samples=2,
                            prev_camera=orbit(30.0, 20.0, 1.6))
    small = renderer.render(orbit(34.0, 20.0, 1.6), request)
    reconstructor = Reconstructor()
    reconstructor.reconstruct(sphere_frames[0], 2, 1)
    out = reconstructor.reconstruct(small, 2, 1)  # a flow, but nothing of this size to warp
    assert_sane(out, 32, 48)
    torch.testing.assert_close(out.ao, Reconstructor().reconstruct(small, 2, 1).ao)


def test_a_reconstructor_has_no_upscaling_api_and_an_upscaler_folder_is_not_a_reconstructor(sphere_frames):
    assert not hasattr(Reconstructor(), "upscale") and not hasattr(Reconstructor(), "step")
    with pytest.raises(ValueError, match="SRNet, not a reconstruction network"):
        Reconstructor(DEFAULT_MODEL)


SHIPPED = pytest.mark.parametrize("model, s", [(DEFAULT_RECON_MODEL, 1), (RECON_X2_MODEL, 2)], ids=["x1", "x2"])


@SHIPPED
def test_extreme_depth_stays_finite(sphere_frames, model, s):
    frame = fresh(sphere_frames[0])
    frame.depth = torch.where(frame.mask > 0, torch.full_like(frame.depth, 1e6), frame.depth)
    out = Reconstructor(model).reconstruct(frame, 2, 1)
    assert_sane(out, s * SIZE[1], s * SIZE[0])


@SHIPPED
def test_an_empty_frame_stays_empty_and_a_camera_inside_the_volume_gives_finite_output(sphere, model, s):
    """The shipped models, x1 and x2 (which renders these frames and makes them twice the sides)."""
    renderer, iso = sphere
    outputs = ("mask", "normal", "depth", "ao")
    empty = renderer.render(orbit(30.0, 20.0, 1.6), RenderRequest(*SIZE, 2.0, outputs, ao_samples=2))
    assert empty.mask.max() == 0
    out = Reconstructor(model).reconstruct(empty, 2, 1)
    assert_sane(out, s * SIZE[1], s * SIZE[0])
    assert out.mask.max() < 0.05
    inside = Camera((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0), 40.0)
    frame = renderer.render(inside, RenderRequest(*SIZE, iso, outputs, ao_samples=2))
    assert_sane(Reconstructor(model).reconstruct(frame, 2, 1), s * SIZE[1], s * SIZE[0])


def test_reconstruct_shades_when_asked_and_a_refused_frame_leaves_the_state_alone(sphere_frames):
    shading = ShadingParams()
    reconstructor = Reconstructor()
    first = reconstructor.reconstruct(sphere_frames[0], 2, 1, shading)
    torch.testing.assert_close(first.color, shade(first.mask, first.normal, first.ao, shading))
    hostile = fresh(sphere_frames[1])
    hostile.normal[3, 5] = float("nan")
    with pytest.raises(ValueError, match="normal holds NaN"):
        reconstructor.reconstruct(hostile, 2, 1)
    after = reconstructor.reconstruct(sphere_frames[1], 2, 1)
    reference = Reconstructor()
    reference.reconstruct(sphere_frames[0], 2, 1)
    torch.testing.assert_close(after.ao, reference.reconstruct(sphere_frames[1], 2, 1).ao, rtol=0, atol=0)


def test_cuda_graphs_are_refused_without_cuda():
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device"):
        Reconstructor(graphs=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA GPU (run on the GPU machine)")
def test_the_captured_path_matches_the_eager_one_frame_by_frame():
    """Compiled and replayed from CUDA graphs against eager fp16 over an orbit, through a size
    change and a refused frame."""
    volume = open_volume("proc:cloud:3@48")
    renderer, iso = Renderer(volume, "cuda"), resolve_iso("proc:cloud:3@48", volume)
    outputs = ("mask", "normal", "depth", "ao", "flow")
    fast = Reconstructor(device="cuda", precision="fp16", channels_last=True, compile="default", graphs=True)
    eager = Reconstructor(device="cuda", precision="fp16")
    shading = ShadingParams()
    for size in (SIZE, (64, 48), SIZE):
        for camera, request in sequence_requests(orbit_path(4, yaw_step=3.0), *size, iso, outputs, ao_samples=2):
            frame = renderer.render(camera, request)
            a, b = fast.reconstruct(frame, 2, 1, shading), eager.reconstruct(frame, 2, 1, shading)
            for name in ("mask", "normal", "ao", "color"):
                torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=2e-2)
    hostile = fresh(frame)
    hostile.ao[0, 0] = 2.0
    kept = fast.previous.clone()
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        fast.reconstruct(hostile, 2, 1, shading)
    torch.testing.assert_close(fast.previous, kept, rtol=0, atol=0)


# ---------------------------------------------------------------- the shipped model's quality


@pytest.mark.parametrize("method, plain, margin", [
    (FrameMethod.of("reconstruct", ao_rays=2), FrameMethod.of("full", ao_rays=2), 0.5),
    (FrameMethod.of("reconstruct", ao_rays=2, factor=2, model=str(RECON_X2_MODEL), model_name="recon_x2"),
     FrameMethod.of("upscale", factor=2), 1.0)])
def test_the_shipped_models_beat_the_frames_they_reconstruct(method, plain, margin):
    """Color PSNR against the many-ray reference: the reconstruction of 2 AO rays and 1 ray per
    pixel against the same render shaded as it is (x1), or the half-size render upsampled (x2: at
    this size it stays below a full-size render with 2 AO rays, as at 4K)."""
    volume = open_volume("proc:cloud:3@48")
    renderer, iso = Renderer(volume, "cpu"), resolve_iso("proc:cloud:3@48", volume)
    cameras = orbit_path(2, yaw0=20.0, yaw_step=3.0)
    references = reference_frames(renderer, iso, SIZE, cameras)
    psnr = {}
    for m in (method, plain):
        frames = run_sequence(make_runner(m, renderer, iso, *SIZE), cameras)
        psnr[m.kind] = [color_psnr(f, r) for f, r in zip(frames, references)]
    for reconstructed, baseline in zip(psnr["reconstruct"], psnr[plain.kind]):
        assert reconstructed > baseline + margin, psnr


def test_the_shipped_x2_model_upscales_and_takes_the_rays_of_the_x1_model():
    config = Reconstructor(RECON_X2_MODEL).net.config
    assert (config.upscale, config.ao_prior, recon_limits(RECON_X2_MODEL)) == (2, "rays", RayLimits(16, 4))


def test_warm_runs_a_first_and_a_carried_frame_per_size_and_forgets_them():
    reconstructor = Reconstructor()
    seen = []
    reconstruct = reconstructor.reconstruct
    reconstructor.reconstruct = lambda frame, *a: seen.append(
        (tuple(frame.mask.shape), reconstructor.carries(*frame.mask.shape, True))) or reconstruct(frame, *a)
    reconstructor.warm([(8, 12), (5, 7)])
    assert seen == [((8, 12), False), ((8, 12), True), ((5, 7), False), ((5, 7), True)]
    assert reconstructor.previous is None


# ---------------------------------------------------------------- reconstructing and upscaling x2 and x4


@pytest.mark.parametrize("s", [2, 4])
def test_an_upscaling_model_corrects_its_inputs_upsampled_at_s_times_the_sides(s):
    """With a silent tail the output is the base: mask and normal bilinear, depth nearest, AO the
    rays' smoothed mean upsampled; the previous output is read at the output's size."""
    model = net(seed=4, upscale=s, ao_prior="rays")
    inputs = recon_batch(h=7, w=10)
    torch.nn.init.zeros_(model.tail.weight)
    torch.nn.init.zeros_(model.tail.bias)
    with torch.no_grad():
        out = model(inputs, torch.rand(2, 6, 7 * s, 10 * s))
    base = upsampled_inputs(inputs, s)
    assert out.shape == (2, 6, 7 * s, 10 * s)
    up = torch.nn.functional.interpolate(inputs, scale_factor=s, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out[:, MASK], up[:, MASK].clamp(0, 1))
    torch.testing.assert_close(out[:, NORMAL], up[:, NORMAL])
    torch.testing.assert_close(out[:, DEPTH], inputs[:, DEPTH].repeat_interleave(s, 2).repeat_interleave(s, 3))
    torch.testing.assert_close(out[:, AO], ao_output(torch.zeros_like(out[:, AO]), base, model.config))
    with pytest.raises(ValueError, match=rf"prev_warped must be \(2, 6, {7 * s}, {10 * s}\)"):
        model(inputs, torch.rand(2, 6, 7, 10))


@pytest.mark.parametrize("s", [2, 4])
def test_an_upscaling_step_warps_the_previous_output_by_the_flow_at_its_size(s):
    model = net(seed=5, upscale=s)
    inputs, flow = recon_batch(h=6, w=9), torch.randn(2, 2, 6, 9)
    with torch.no_grad():
        first, stand_in = model.step(inputs, None, None)
        second, warped = model.step(inputs, flow, first)
    assert first.shape == second.shape == stand_in.shape == (2, 6, 6 * s, 9 * s)
    torch.testing.assert_close(stand_in, model.__class__(ReconNetConfig()).first_previous(upsampled_inputs(inputs, s)))
    torch.testing.assert_close(warped, warp_by_flow(first, upscale_flow(flow, s)))


def test_an_upscaling_model_costs_a_third_of_the_multiply_adds_per_output_pixel():
    model = net(upscale=2)
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        model(recon_batch(b=1, h=16, w=24), torch.zeros(1, 6, 32, 48))
    assert counter.get_total_flops() / 2 / (32 * 48) == pytest.approx(macs_per_pixel(model.config), rel=1e-12)
    assert macs_per_pixel(model.config) < macs_per_pixel(ReconNetConfig()) / 3
    with pytest.raises(ValueError, match=r"upscale must be one of \(1, 2, 4\), got 3"):
        ReconNetConfig(upscale=3)


def saved_upscaler(tmp_path_factory, s: int):
    """A random ReconNet that reconstructs and upscales ``s`` times, saved."""
    folder = tmp_path_factory.mktemp(f"x{s}_model")
    save_pretrained(net(seed=6, widths=(4, 4, 8, 8), blocks=1, ao_prior="rays", upscale=s), folder)
    return folder


@pytest.fixture(scope="module")
def x2_model(tmp_path_factory):
    return saved_upscaler(tmp_path_factory, 2)


@pytest.fixture(scope="module", params=[2, 4], ids=["x2", "x4"])
def upscaling_model(request, tmp_path_factory):
    """``(folder, s)``: a saved random ReconNet that upscales ``s`` times."""
    return saved_upscaler(tmp_path_factory, request.param), request.param


def test_a_reconstructor_of_an_upscaling_model_makes_frames_at_s_times_the_sides(upscaling_model, sphere):
    (folder, s), (renderer, iso) = upscaling_model, sphere
    outputs = ("mask", "normal", "depth", "ao", "flow")
    reconstructor = Reconstructor(folder)
    assert reconstructor.upscale_factor == s
    frames = [renderer.render(camera, request) for camera, request in
              sequence_requests(orbit_path(2, yaw_step=3.0), SIZE[0] // s, SIZE[1] // s, iso, outputs, ao_samples=2)]
    first = reconstructor.reconstruct(frames[0], 2, 1, ShadingParams())
    assert_sane(FrameBuffers(mask=first.mask, normal=first.normal, depth=first.depth, ao=first.ao), SIZE[1], SIZE[0])
    assert first.color.shape == (SIZE[1], SIZE[0], 3)
    assert reconstructor.carries(SIZE[1] // s, SIZE[0] // s, True) and not reconstructor.carries(*SIZE[::-1], True)
    second = reconstructor.reconstruct(frames[1], 2, 1)
    assert_sane(second, SIZE[1], SIZE[0])
    alone = Reconstructor(folder).reconstruct(frames[1], 2, 1)
    assert not torch.equal(second.ao, alone.ao)  # the first frame carried over


def test_the_frame_method_of_an_upscaling_model_renders_at_1_over_s_of_the_sides(upscaling_model, sphere):
    (folder, s), (renderer, iso) = upscaling_model, sphere
    method = FrameMethod.of("reconstruct", ao_rays=2, factor=s, model=str(folder), model_name="recon-up")
    assert method.name == f"x{s}, AO 2, spp 1, recon-up fp32"
    assert FrameMethod.of("reconstruct", model=str(folder)).factor == s  # the model's own by default
    runner = make_runner(method, renderer, iso, *SIZE, keep=("depth",))
    assert (runner.render_request().width, runner.render_request().height) == (SIZE[0] // s, SIZE[1] // s)
    frame = runner.frame(orbit(30.0, 20.0, 1.6))
    assert frame.buffers.color.shape == (SIZE[1], SIZE[0], 3) and torch.isfinite(frame.buffers.color).all()
    with pytest.raises(ValueError, match=f"the model upscales x1, not x{s}"):
        make_runner(FrameMethod.of("reconstruct", factor=s), renderer, iso, *SIZE)
    with pytest.raises(ValueError, match=r"factor must be an integer in \[1, 4\]"):
        FrameMethod.of("reconstruct", factor=8)


def test_the_fused_kernels_run_fp16_on_cuda_and_models_of_their_widths(x2_model, tmp_path):
    """The one rule `fastest` and the service's `served` follow (decided from the model's config,
    without a GPU): the shipped models, x1 and x2, fuse, and so does the 4-channel test model (its
    channels padded in the kernels' tiles); one wider than the kernels' widest tile, or upscaling x4, does not."""
    from isosr_net.fused_recon import triton_imports

    assert Reconstructor.fuses(DEFAULT_RECON_MODEL, "cuda", "fp16") == triton_imports()
    assert Reconstructor.fuses(RECON_X2_MODEL, "cuda", "fp16") == triton_imports()
    assert Reconstructor.fuses(x2_model, "cuda", "fp16") == triton_imports()
    save_pretrained(net(seed=6, widths=(16, 32, 64, 128), blocks=0), tmp_path)
    assert not Reconstructor.fuses(tmp_path, "cuda", "fp16")
    save_pretrained(net(seed=6, upscale=4), tmp_path)  # its packed input, 40 channels, is wider than the kernels'
    assert not Reconstructor.fuses(tmp_path, "cuda", "fp16")
    assert not Reconstructor.fuses(DEFAULT_RECON_MODEL, "cuda", "bf16")
    assert not Reconstructor.fuses(DEFAULT_RECON_MODEL, "cpu", "fp16")
    served = Reconstructor.served(DEFAULT_RECON_MODEL, "cpu", "fp32")
    assert not served.graphs and not isinstance(served.net, FusedReconNet)
