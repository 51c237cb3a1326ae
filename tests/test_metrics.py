"""Evaluation metrics: references for PSNR and SSIM, baselines, frame scores and flicker."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torchmetrics.functional.image import structural_similarity_index_measure

from isosr_render.shading import shade_channels_first
from isosr_net.metrics import (eval_region, frame_scores, masked_psnr, masked_ssim, scene_region,
                               temporal_instability, upscale_baseline)
from isosr_render.conventions import AO, DEPTH, MASK, NORMAL
from isosr_render.shading import shade


def highres_stack(batch: int = 2, size: int = 32, seed: int = 0) -> torch.Tensor:
    """(B, 6, H, W) buffers of a disk: unit normals facing the camera, depth and AO, 0 off the disk."""
    g = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    mask = (((x - size / 2) ** 2 + (y - size / 2) ** 2) < (size / 3) ** 2).float().expand(batch, 1, -1, -1)
    normal = torch.rand(batch, 3, size, size, generator=g) * 2 - 1
    normal[:, 2] = normal[:, 2].abs() + 0.2
    normal = F.normalize(normal, dim=1)
    depth = torch.rand(batch, 1, size, size, generator=g) + 1.0
    ao = torch.rand(batch, 1, size, size, generator=g)
    return torch.cat([mask, normal * mask, depth * mask, ao * mask], dim=1)


def identity_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    return image


def roll_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Exact warp for a constant integer flow: samples ``image`` at ``p + flow`` (periodic)."""
    fx, fy = int(flow[0, 0, 0, 0]), int(flow[0, 1, 0, 0])
    return torch.roll(image, shifts=(-fy, -fx), dims=(-2, -1))


@pytest.mark.parametrize("data_range", [1.0, 2.0])
def test_masked_psnr_matches_a_float64_reference(data_range):
    g = torch.Generator().manual_seed(1)
    pred, target = torch.rand(3, 3, 16, 20, generator=g), torch.rand(3, 3, 16, 20, generator=g)
    mask = torch.rand(3, 1, 16, 20, generator=g)
    p, t, m = pred.double().numpy(), target.double().numpy(), mask.numpy()[:, 0] > 0.5
    expected = [10 * np.log10(data_range ** 2 / np.mean((p[b] - t[b])[:, m[b]] ** 2)) for b in range(3)]
    np.testing.assert_allclose(masked_psnr(pred, target, mask, data_range).numpy(), expected, rtol=1e-5)


def test_identical_inputs_score_perfectly():
    image = torch.rand(2, 3, 16, 16, generator=torch.Generator().manual_seed(2))
    mask = torch.ones(2, 1, 16, 16)
    assert (masked_psnr(image, image, mask) >= 90).all()
    torch.testing.assert_close(masked_ssim(image, image, mask), torch.ones(2))


def test_masked_ssim_with_a_full_mask_is_torchmetrics_ssim():
    g = torch.Generator().manual_seed(3)
    pred = torch.rand(2, 3, 24, 20, generator=g)
    target = (pred + 0.2 * torch.rand(2, 3, 24, 20, generator=g)).clamp(0, 1)
    ours = masked_ssim(pred, target, torch.ones(2, 1, 24, 20, dtype=torch.bool))
    torch.testing.assert_close(ours, structural_similarity_index_measure(pred, target, data_range=1.0,
                                                                         reduction="none"))
    torch.testing.assert_close(ours.mean(), structural_similarity_index_measure(pred, target, data_range=1.0))


def test_an_empty_mask_scores_nan_and_nanmean_skips_it():
    g = torch.Generator().manual_seed(4)
    pred, target = torch.rand(2, 3, 16, 16, generator=g), torch.rand(2, 3, 16, 16, generator=g)
    mask = torch.ones(2, 1, 16, 16)
    mask[1] = 0
    for score in (masked_psnr(pred, target, mask), masked_ssim(pred, target, mask)):
        assert torch.isfinite(score[0]) and torch.isnan(score[1])
        assert torch.nanmean(score) == score[0]


def test_eval_region_is_the_union_of_the_masks():
    pred_mask = torch.tensor([[[[0.9, 0.2, 0.6, 0.0]]]])
    target_mask = torch.tensor([[[[0.0, 1.0, 1.0, 0.5]]]])
    assert eval_region(pred_mask, target_mask).tolist() == [[[[True, True, True, False]]]]


def test_the_scene_region_is_the_references_cover_and_its_neighbours_for_every_method():
    """A half-covered pixel whose mask one method puts a hair above 0.5 joins that method's union region, with
    the error of its colour there, and not the other's; the scene's region scores both on the same pixels."""
    target_mask = torch.zeros(1, 1, 1, 6)
    target_mask[..., 1] = 1.0
    assert scene_region(target_mask).tolist() == [[[[True, True, True, False, False, False]]]]
    ref = torch.zeros(1, 3, 1, 6)
    ref[..., 1] = 0.8
    a, b = ref.clone(), ref.clone()
    a[..., 2] = b[..., 2] = 0.5  # both colour the half-covered pixel the same, off the reference's 0
    mask_a, mask_b = target_mask.clone(), target_mask.clone()
    mask_a[..., 2], mask_b[..., 2] = 0.5, 0.5 + 1e-6
    union = [float(masked_psnr(c, ref, eval_region(m, target_mask))) for c, m in ((a, mask_a), (b, mask_b))]
    scene = [float(masked_psnr(c, ref, scene_region(target_mask))) for c in (a, b)]
    assert union[0] > union[1] + 10 and scene[0] == scene[1]


def test_shade_channels_first_is_shade_with_ao_and_without_it_for_five_channels():
    hr = highres_stack()
    last = hr.permute(0, 2, 3, 1)
    with_ao = shade(last[..., 0], last[..., NORMAL], last[..., 5]).permute(0, 3, 1, 2)
    without_ao = shade(last[..., 0], last[..., NORMAL]).permute(0, 3, 1, 2)
    torch.testing.assert_close(shade_channels_first(hr), with_ao)
    torch.testing.assert_close(shade_channels_first(hr[:, :5]), without_ao)


@pytest.mark.parametrize("mode", ["nearest", "bilinear", "bicubic"])
@pytest.mark.parametrize("factor", [2, 4, 8])
def test_upscale_baseline_shapes_mask_normals_and_ao(factor, mode):
    lowres = highres_stack(size=12)[:, :5]
    up = upscale_baseline(lowres, factor, mode)
    assert up.shape == (2, 6, 12 * factor, 12 * factor)
    assert up[:, MASK].min() >= 0 and up[:, MASK].max() <= 1
    covered = (up[:, MASK] > 0).expand(-1, 3, -1, -1)
    lengths = up[:, NORMAL].norm(dim=1, keepdim=True).expand(-1, 3, -1, -1)
    torch.testing.assert_close(lengths[covered], torch.ones_like(lengths[covered]))
    assert (up[:, AO] == 1).all()


def test_nearest_upscaling_reproduces_blocks():
    lowres = highres_stack(size=8)[:, :5]
    up = upscale_baseline(lowres, 4, "nearest")
    blocks = lowres.repeat_interleave(4, dim=-2).repeat_interleave(4, dim=-1)
    assert torch.equal(up[:, MASK], blocks[:, MASK]) and torch.equal(up[:, DEPTH], blocks[:, DEPTH])
    torch.testing.assert_close(up[:, NORMAL], blocks[:, NORMAL])


def test_bilinear_upscaling_of_a_constant_field_is_that_constant():
    constant = torch.tensor([1.0, 0.6, 0.0, 0.8, 0.37])
    up = upscale_baseline(constant.view(1, 5, 1, 1).expand(1, 5, 6, 7), 4, "bilinear")
    torch.testing.assert_close(up, torch.cat([constant, torch.ones(1)]).view(1, 6, 1, 1).expand(1, 6, 24, 28))


def test_frame_scores_a_perfect_prediction_beats_a_noisy_one_on_every_score():
    target = highres_stack()
    g = torch.Generator().manual_seed(5)
    noisy = target + 0.1 * torch.randn(target.shape, generator=g)
    noisy[:, MASK] = target[:, MASK]
    noisy[:, MASK, 8:12] = 1 - target[:, MASK, 8:12]
    perfect, worse = frame_scores(target.clone(), target), frame_scores(noisy, target)
    assert set(perfect) == {"color_psnr", "color_ssim", "normal_psnr", "ao_psnr", "mask_iou"}
    for name in perfect:
        assert perfect[name].shape == (2,) and (perfect[name] > worse[name]).all(), name
    torch.testing.assert_close(perfect["mask_iou"], torch.ones(2))


def test_temporal_instability_is_zero_when_steady_and_positive_under_flicker():
    frames = highres_stack(batch=2).expand(4, -1, -1, -1, -1).clone()
    flows = torch.zeros(4, 2, 2, 32, 32)
    assert (temporal_instability(frames, flows, identity_warp) == 0).all()
    frames[1::2, :, AO] *= 0.5
    assert (temporal_instability(frames, flows, identity_warp) > 0).all()


def test_temporal_instability_follows_the_flow():
    frame = highres_stack(batch=1)
    frames = torch.stack([torch.roll(frame, shifts=(2 * t, 3 * t), dims=(-2, -1)) for t in range(3)])
    flows = torch.tensor([-3.0, -2.0]).view(1, 1, 2, 1, 1).expand(3, 1, 2, 32, 32)
    assert temporal_instability(frames, flows, roll_warp) == 0
    assert temporal_instability(frames, flows, identity_warp) > 0


@pytest.mark.parametrize("call, match", [
    (lambda: shade_channels_first(torch.zeros(1, 4, 8, 8)), r"stack must be .*\(1, 4, 8, 8\)"),
    (lambda: eval_region(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 9)), r"target_mask .*\(1, 1, 8, 9\)"),
    (lambda: scene_region(torch.zeros(1, 8, 8)), r"target_mask .*\(1, 8, 8\)"),
    (lambda: masked_psnr(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8), torch.ones(1, 8, 8)), r"pred .*\(3, 8, 8\)"),
    (lambda: masked_psnr(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), torch.ones(1, 3, 8, 8)),
     r"mask .*\(1, 3, 8, 8\)"),
    (lambda: masked_ssim(torch.zeros(1, 3, 8, 8), torch.zeros(1, 3, 8, 8), torch.ones(1, 1, 8, 8)),
     r"pred .*\(1, 3, 8, 8\)"),
    (lambda: masked_ssim(torch.zeros(1, 3, 16, 16), torch.zeros(1, 1, 16, 16), torch.ones(1, 1, 16, 16)),
     r"target .*\(1, 1, 16, 16\)"),
    (lambda: upscale_baseline(torch.zeros(1, 6, 8, 8), 2), r"lowres .*\(1, 6, 8, 8\)"),
    (lambda: upscale_baseline(torch.zeros(1, 5, 8, 8), 0), "factor"),
    (lambda: upscale_baseline(torch.zeros(1, 5, 8, 8), 2, "area"), "mode"),
    (lambda: frame_scores(torch.zeros(1, 5, 16, 16), torch.zeros(1, 5, 16, 16)), r"pred .*\(1, 5, 16, 16\)"),
    (lambda: frame_scores(torch.zeros(1, 6, 16, 16), torch.zeros(2, 6, 16, 16)), r"target .*\(2, 6, 16, 16\)"),
    (lambda: temporal_instability(torch.zeros(1, 1, 6, 8, 8), torch.zeros(1, 1, 2, 8, 8), identity_warp),
     r"outputs .*\(1, 1, 6, 8, 8\)"),
    (lambda: temporal_instability(torch.zeros(2, 1, 6, 8, 8), torch.zeros(2, 1, 2, 8, 7), identity_warp),
     r"flows_hr .*\(2, 1, 2, 8, 7\)"),
])
def test_bad_inputs_are_refused_with_the_argument_and_its_shape(call, match):
    with pytest.raises(ValueError, match=match):
        call()
