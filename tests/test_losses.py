"""Tests of isosr_net.losses: float64 references, gradient checks, VGG loading, GAN plumbing."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from isosr_net.architectures import VGG19_LAYERS, SpatioTemporalDiscriminator
from isosr_net.losses import (
    PAPER_LOSSES,
    AdversarialLoss,
    AONoWorseLoss,
    AOPSNRNoWorseLoss,
    ChannelLoss,
    LossContext,
    PerceptualLoss,
    TeacherPSNRNoWorseLoss,
    TemporalLoss,
    ao_excess_error,
    build_losses,
    masked_l1,
    masked_l2,
    psnr_shortfall,
    total_loss,
)
from isosr_render.conventions import AO, DEPTH, MASK, NORMAL

# torchvision's vgg19().features: (index, out channels, in channels) of its 16 convolutions.
_CONVS = [(0, 64, 3), (2, 64, 64), (5, 128, 64), (7, 128, 128), (10, 256, 128), (12, 256, 256),
          (14, 256, 256), (16, 256, 256), (19, 512, 256), (21, 512, 512), (23, 512, 512),
          (25, 512, 512), (28, 512, 512), (30, 512, 512), (32, 512, 512), (34, 512, 512)]


def save_random_vgg19(path: Path, seed: int, prefix: str = "features.") -> dict[str, torch.Tensor]:
    """Write a VGG-19 state dict with He-initialized random weights, keyed like torchvision's."""
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for index, c_out, c_in in _CONVS:
        std = (2.0 / (9 * c_in)) ** 0.5
        state[f"{prefix}{index}.weight"] = torch.randn(c_out, c_in, 3, 3, generator=gen) * std
        state[f"{prefix}{index}.bias"] = torch.randn(c_out, generator=gen) * 0.01
    if prefix:  # a whole torchvision model also carries its classifier
        state["classifier.6.bias"] = torch.zeros(1000)
    if path.suffix == ".safetensors":
        save_file(state, str(path))
    else:
        torch.save(state, path)
    return state


def frame(b: int = 2, h: int = 8, w: int = 8, seed: int = 0, dtype=torch.float64,
          empty_border: bool = True) -> torch.Tensor:
    """A plausible (B, 6, H, W) buffer stack: binary mask, facing normals, depth and AO inside."""
    gen = torch.Generator().manual_seed(seed)
    mask = (torch.rand(b, 1, h, w, generator=gen) > 0.3).to(dtype)
    if empty_border:
        mask[..., 0, :] = 0
    normal = torch.randn(b, 3, h, w, generator=gen, dtype=dtype)
    normal[:, 2] = normal[:, 2].abs() + 0.2
    normal = normal / normal.norm(dim=1, keepdim=True)
    depth = 1.0 + torch.rand(b, 1, h, w, generator=gen, dtype=dtype)
    ao = 0.2 + 0.7 * torch.rand(b, 1, h, w, generator=gen, dtype=dtype)
    return torch.cat([mask, normal * mask, depth * mask, ao * mask], dim=1)


def soft_pred(target: torch.Tensor, seed: int = 1) -> torch.Tensor:
    """A network-like output near ``target``: soft mask in (0, 1), non-unit normals."""
    gen = torch.Generator().manual_seed(seed)
    noise = 0.1 * torch.randn(target.shape, generator=gen, dtype=target.dtype)
    pred = target + noise
    pred[:, MASK] = (0.1 + 0.8 * target[:, MASK] + noise[:, MASK]).clamp(0.05, 0.95)
    pred[:, NORMAL] = pred[:, NORMAL] * 1.3 + torch.tensor([0.0, 0.0, 0.3], dtype=target.dtype).view(1, 3, 1, 1)
    return pred


def numpy_masked(pred, target, mask, channels, power):
    """float64 reference: per-pixel channel mean of |d|^power, averaged over mask > 0."""
    d = np.abs(pred[:, channels] - target[:, channels]) ** power
    per_pixel = d.mean(axis=1)
    inside = mask[:, 0] > 0
    return per_pixel[inside].mean() if inside.any() else 0.0


# ----------------------------------------------------------------------------- masked losses


@pytest.mark.parametrize("fn, power", [(masked_l1, 1), (masked_l2, 2)])
@pytest.mark.parametrize("channels", [NORMAL, DEPTH, AO, slice(None)])
def test_masked_losses_match_numpy(fn, power, channels):
    target = frame(b=3, h=5, w=7)
    pred = soft_pred(target)
    got = fn(pred, target, target[:, MASK], channels)
    want = numpy_masked(pred.numpy(), target.numpy(), target[:, MASK].numpy(), channels, power)
    assert got.shape == ()
    np.testing.assert_allclose(got.item(), want, rtol=1e-7)


@pytest.mark.parametrize("fn", [masked_l1, masked_l2])
def test_masked_losses_empty_mask_is_zero_with_finite_grad(fn):
    pred = torch.rand(2, 6, 4, 4, dtype=torch.float64, requires_grad=True)
    loss = fn(pred, torch.rand(2, 6, 4, 4, dtype=torch.float64), torch.zeros(2, 1, 4, 4), NORMAL)
    loss.backward()
    assert loss.item() == 0.0
    assert torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("fn", [masked_l1, masked_l2])
def test_masked_losses_gradcheck(fn):
    target = frame(b=1, h=3, w=4)
    pred = soft_pred(target).requires_grad_(True)
    target.requires_grad_(True)
    mask = target[:, MASK].detach().clone()  # gradcheck perturbs target in place
    assert torch.autograd.gradcheck(lambda p, t: fn(p, t, mask, NORMAL), (pred, target))


def test_masked_losses_check_shapes():
    x = torch.zeros(2, 6, 4, 4)
    with pytest.raises(ValueError, match="mask must be"):
        masked_l1(x, x, torch.zeros(2, 4, 4), NORMAL)
    with pytest.raises(ValueError, match="target must be"):
        masked_l2(x, x[:1], torch.zeros(2, 1, 4, 4), NORMAL)
    with pytest.raises(ValueError, match="select nothing"):
        masked_l1(x, x, torch.zeros(2, 1, 4, 4), slice(6, 8))


# ----------------------------------------------------------------------------- channel losses


def test_channel_losses_mask_vs_masked_channels():
    target = frame()
    outside = (target[:, MASK] == 0).expand(-1, 6, -1, -1)
    pred = target.clone()
    pred[outside] = 0.5  # wrong only where the ground truth has no surface
    ctx = LossContext(pred, target)
    assert ChannelLoss("normal", "l1")(ctx).item() == 0.0
    assert ChannelLoss("depth", "l2")(ctx).item() == 0.0
    mask_fraction = outside[:, 0].double().mean().item()
    np.testing.assert_allclose(ChannelLoss("mask", "l1", weight=2.0)(ctx).item(), 2.0 * 0.5 * mask_fraction)


def test_channel_loss_weight_and_value():
    target = frame()
    pred = soft_pred(target)
    ctx = LossContext(pred, target)
    want = 3.0 * numpy_masked(pred.numpy(), target.numpy(), target[:, MASK].numpy(), AO, 2)
    np.testing.assert_allclose(ChannelLoss("ao", "l2", weight=3.0)(ctx).item(), want, rtol=1e-7)


@pytest.mark.parametrize("kind", ["l1", "l2"])
def test_color_loss_zero_for_identical_and_positive_otherwise(kind):
    target = frame()
    loss = ChannelLoss("color", kind)
    assert loss(LossContext(target.clone(), target)).item() == 0.0
    assert loss(LossContext(soft_pred(target), target)).item() > 0.0


@pytest.mark.parametrize("kind", ["l1", "l2"])
def test_color_loss_gradcheck(kind):
    target = frame(b=1, h=3, w=3)
    pred = soft_pred(target).requires_grad_(True)
    loss = ChannelLoss("color", kind)
    assert torch.autograd.gradcheck(lambda p: loss(LossContext(p, target)), (pred,))


def test_loss_context_checks_shapes():
    x = torch.zeros(1, 6, 4, 4)
    with pytest.raises(ValueError, match="pred must be"):
        LossContext(torch.zeros(1, 5, 4, 4), x)
    with pytest.raises(ValueError, match="prev_warped"):
        LossContext(x, x, prev_warped=torch.zeros(1, 6, 4, 5))
    with pytest.raises(ValueError, match="lowres_up"):
        LossContext(x, x, lowres_up=torch.zeros(1, 6, 4, 4))


def recon_inputs_for(target: torch.Tensor, rays_ao: torch.Tensor, ao_rays: float = 0.5) -> torch.Tensor:
    """A reconstruction's (B, 8, H, W) inputs: the target's surface, ``rays_ao`` and the sampling channels."""
    sampling = torch.full_like(target[:, :2], ao_rays)
    sampling[:, 1] = 1.0
    return torch.cat([target[:, :5], rays_ao, sampling], dim=1)


def test_ao_excess_error_counts_only_where_the_output_is_further_from_the_truth_than_the_rays():
    t = torch.tensor([[[[0.5, 0.5, 0.5, 0.5]]]], dtype=torch.float64)
    rays = torch.tensor([[[[0.6, 0.4, 0.5, 0.9]]]], dtype=torch.float64)
    pred = torch.tensor([[[[0.55, 0.2, 0.5, 0.0]]]], dtype=torch.float64)
    mask = torch.tensor([[[[1.0, 1.0, 1.0, 0.0]]]], dtype=torch.float64)
    # closer (0.05 < 0.1): 0; further (0.3 > 0.1): 0.2; equal: 0; outside the mask: not counted
    assert ao_excess_error(pred, rays, t, mask).item() == pytest.approx(0.2 / 3)
    assert ao_excess_error(rays, rays, t, mask).item() == 0.0, "the rays' own mean: never worse than itself"
    assert ao_excess_error(pred, rays, t, torch.zeros_like(mask)).item() == 0.0, "nothing covered: 0, finite"
    with pytest.raises(ValueError, match="rays_ao must be"):
        ao_excess_error(pred, rays[..., :3], t, mask)


def test_the_ao_no_worse_loss_reads_the_inputs_rays_and_skips_pixels_without_any():
    target = frame()
    rays_ao = (target[:, AO] + 0.05).clamp(0, 1)
    pred = soft_pred(target)
    loss = AONoWorseLoss(weight=2.0)
    with_rays = LossContext(pred, target, recon_inputs=recon_inputs_for(target, rays_ao))
    surface = target[:, MASK] > 0.5
    expected = ao_excess_error(pred[:, AO], rays_ao, target[:, AO], surface)
    assert loss(with_rays).item() == pytest.approx(2.0 * expected.item()) and expected > 0
    assert loss(LossContext(pred, target, recon_inputs=recon_inputs_for(target, rays_ao, ao_rays=0.0))).item() == 0.0
    exact = pred.clone()
    exact[:, AO] = rays_ao
    assert loss(LossContext(exact, target, recon_inputs=recon_inputs_for(target, rays_ao))).item() == 0.0
    with pytest.raises(ValueError, match="has none at its output's resolution"):
        loss(LossContext(pred, target))
    with pytest.raises(ValueError, match="recon_inputs"):
        LossContext(pred, target, recon_inputs=torch.zeros(2, 7, 8, 8, dtype=pred.dtype))
    grad_pred = pred.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: loss(LossContext(p, target, recon_inputs=recon_inputs_for(target, rays_ao))), (grad_pred,))


def test_psnr_shortfall_counts_each_frame_s_db_below_what_it_was_given_in_float64():
    """Frame 0's output twice as far off as its rays everywhere (6.02 dB short), frame 1's closer (0), frame 2
    covers nothing (0, finite): the mean over the three; equal outputs and rays give 0; errors far under the
    floor count as equal; the gradient is finite and checked in float64."""
    t = torch.full((3, 1, 4, 4), 0.5, dtype=torch.float64)
    rays = t + 0.01
    pred = t.clone()
    pred[0] += 0.02
    pred[1] += 0.005
    mask = torch.ones_like(t)
    mask[2] = 0
    assert psnr_shortfall(pred, rays, t, mask).item() == pytest.approx(10 * math.log10(4) / 3, rel=1e-6)
    assert psnr_shortfall(rays, rays, t, mask).item() == 0.0
    assert psnr_shortfall(t + 1e-7, t + 1e-8, t, mask).item() < 0.01, "both under the floor: no shortfall"
    assert psnr_shortfall(pred, rays, t, torch.zeros_like(mask)).item() == 0.0
    with pytest.raises(ValueError, match="given must be"):
        psnr_shortfall(pred, rays[..., :3], t, mask)
    assert torch.autograd.gradcheck(lambda p: psnr_shortfall(p, rays, t, mask), (pred.clone().requires_grad_(),))


def test_the_ao_psnr_no_worse_loss_lets_a_pixel_s_gain_pay_for_another_s_loss():
    """Unlike ao_no_worse (per pixel), a frame whose output is closer to the truth overall costs nothing even where
    some of its pixels are further; without AO rays nothing counts; an upscaler's context is refused."""
    target = frame()
    rays_ao = (target[:, AO] + 0.05).clamp(0, 1)
    pred = target.clone()
    pred[:, AO] = target[:, AO]
    pred[:, AO, :, :1] = (rays_ao[..., :1] + 0.05).clamp(0, 1)  # one column further than the rays
    context = LossContext(pred, target, recon_inputs=recon_inputs_for(target, rays_ao))
    assert AOPSNRNoWorseLoss(weight=2.0)(context).item() == 0.0
    assert AONoWorseLoss()(context).item() > 0
    worse = pred.clone()
    worse[:, AO] = (rays_ao + 0.05).clamp(0, 1)
    worse_context = LossContext(worse, target, recon_inputs=recon_inputs_for(target, rays_ao))
    surface = target[:, MASK] > 0.5
    expected = psnr_shortfall(worse[:, AO], rays_ao, target[:, AO], surface)
    assert AOPSNRNoWorseLoss(weight=2.0)(worse_context).item() == pytest.approx(2.0 * expected.item()) and expected > 1
    assert AOPSNRNoWorseLoss()(LossContext(worse, target, recon_inputs=recon_inputs_for(
        target, rays_ao, ao_rays=0.0))).item() == 0.0
    with pytest.raises(ValueError, match="ao_psnr_no_worse loss compares"):
        AOPSNRNoWorseLoss()(LossContext(pred, target))


def test_the_teacher_loss_holds_the_shaded_output_to_the_teacher_s_per_frame():
    """A frame shaded closer to the truth than the teacher's costs nothing, one further costs its dB short (the mean
    over frames, weighted); a context without the teacher's output is refused and names the config to give."""
    from isosr_render.shading import shade_channels_first

    target = frame()
    teacher = target.clone()
    teacher[:, AO] = (target[:, AO] - 0.05).clamp(0, 1)
    assert TeacherPSNRNoWorseLoss()(LossContext(target, target, teacher=teacher)).item() == 0.0
    worse = target.clone()
    worse[:, AO] = (target[:, AO] - 0.1).clamp(0, 1)
    color = [shade_channels_first(x) for x in (worse, teacher, target)]
    expected = psnr_shortfall(*color, torch.ones_like(color[0][:, :1]))
    loss = TeacherPSNRNoWorseLoss(weight=0.5)(LossContext(worse, target, teacher=teacher))
    assert expected > 1 and loss.item() == pytest.approx(0.5 * expected.item())
    with pytest.raises(ValueError, match="TrainConfig.teacher"):
        TeacherPSNRNoWorseLoss()(LossContext(worse, target))
    with pytest.raises(ValueError, match="teacher must be"):
        LossContext(worse, target, teacher=teacher[..., :3])


def test_a_channel_loss_against_the_teacher_measures_the_output_against_the_teacher_s():
    """Distillation: the same error as against the truth, with the teacher's output in its place (over the truth's
    surface pixels); without the teacher's output it is refused, and an unknown reference too."""
    target = frame()
    teacher, pred = target.clone(), target.clone()
    teacher[:, NORMAL] = target[:, NORMAL] * 0.9
    pred[:, NORMAL] = target[:, NORMAL] * 0.8
    distill = ChannelLoss("normal", "l1", weight=2.0, against="teacher")
    assert distill.reads_teacher and distill.name == "normal_l1_teacher" and not ChannelLoss("normal").reads_teacher
    expected = masked_l1(pred, teacher, target[:, MASK], NORMAL)
    assert distill(LossContext(pred, target, teacher=teacher)).item() == pytest.approx(2 * expected.item())
    assert expected > 0 and distill(LossContext(teacher, target, teacher=teacher)).item() == 0.0
    with pytest.raises(ValueError, match="TrainConfig.teacher"):
        distill(LossContext(pred, target))
    with pytest.raises(ValueError, match="against must be"):
        ChannelLoss("normal", against="reference")


# ----------------------------------------------------------------------------- perceptual


@pytest.fixture(scope="module")
def vgg_files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("vgg")
    files = {"safetensors": root / "vgg19.safetensors", "pt": root / "vgg19_features.pt"}
    save_random_vgg19(files["safetensors"], seed=0)  # torchvision-style "features." keys
    save_random_vgg19(files["pt"], seed=1, prefix="")  # features-only state dict
    return files


def test_vgg_layer_names_follow_torchvision_indexing():
    assert VGG19_LAYERS["relu1_2"] == 3 and VGG19_LAYERS["relu2_2"] == 8
    assert VGG19_LAYERS["relu3_4"] == 17 and VGG19_LAYERS["relu4_4"] == 26 and VGG19_LAYERS["relu5_4"] == 35
    assert all(VGG19_LAYERS[name] - 1 in {i for i, _, _ in _CONVS} for name in VGG19_LAYERS)


@pytest.mark.parametrize("fmt", ["safetensors", "pt"])
def test_perceptual_loss_loads_and_compares(vgg_files, fmt):
    loss = PerceptualLoss(vgg_files[fmt], weight=2.0)
    loss.train()
    assert not loss.vgg.training
    assert not any(p.requires_grad for p in loss.parameters())
    target = frame(h=32, w=32, dtype=torch.float32)
    assert loss(LossContext(target.clone(), target)).item() == 0.0
    pred = soft_pred(target).requires_grad_(True)
    value = loss(LossContext(pred, target))
    value.backward()
    assert value.item() > 0.0
    assert pred.grad.abs().sum() > 0


def test_perceptual_loss_uses_the_file_weights(vgg_files):
    state = load_file(str(vgg_files["safetensors"]))
    loss = PerceptualLoss(vgg_files["safetensors"], layers=("relu1_1",))
    torch.testing.assert_close(loss.vgg[0].weight, state["features.0.weight"])
    assert len(loss.vgg) == VGG19_LAYERS["relu1_1"] + 1


def test_perceptual_loss_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="VGG-19 weights not found at .*nowhere.safetensors"):
        PerceptualLoss(tmp_path / "nowhere.safetensors")


def test_perceptual_loss_bad_keys(tmp_path):
    path = tmp_path / "bad.pt"
    state = save_random_vgg19(path, seed=2)
    del state["features.34.weight"]
    state["features.0.bias"] = torch.zeros(3)
    state["features.99.weight"] = torch.zeros(1)
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"missing keys \['34.weight'\].*99.weight.*0.bias"):
        PerceptualLoss(path)


def test_perceptual_loss_bad_layer(vgg_files):
    with pytest.raises(ValueError, match="relu9_9"):
        PerceptualLoss(vgg_files["pt"], layers=("relu9_9",))


# ----------------------------------------------------------------------------- temporal


def test_temporal_loss():
    target = frame()
    pred = soft_pred(target)
    loss = TemporalLoss(weight=0.5)
    zero = loss(LossContext(pred, target))
    assert zero.item() == 0.0 and zero.dtype == pred.dtype
    prev = soft_pred(target, seed=5)
    want = 0.5 * numpy_masked(pred.numpy(), prev.numpy(), target[:, MASK].numpy(), slice(None), 2)
    np.testing.assert_allclose(loss(LossContext(pred, target, prev_warped=prev)).item(), want, rtol=1e-7)


# ----------------------------------------------------------------------------- adversarial


def gan_context(requires_grad: bool = True, with_prev: bool = True) -> LossContext:
    target = frame(h=16, w=24, dtype=torch.float32)
    pred = soft_pred(target).requires_grad_(requires_grad)
    prev = soft_pred(target, seed=3) if with_prev else None
    prev_target = frame(h=16, w=24, seed=4, dtype=torch.float32) if with_prev else None
    return LossContext(pred, target, prev_warped=prev, lowres_up=target[:, :5].clone(),
                       prev_target_warped=prev_target)


def test_discriminator_output_shape():
    d = SpatioTemporalDiscriminator()
    assert d(torch.zeros(2, 17, 32, 48)).shape == (2, 1, 4, 6)
    with pytest.raises(ValueError, match=r"\(B, 17, H, W\)"):
        d(torch.zeros(2, 12, 32, 48))


@pytest.mark.parametrize("with_prev", [True, False])
def test_adversarial_generator_loss_reaches_pred_only(with_prev):
    loss = AdversarialLoss(weight=0.1, discriminator_config={"base": 8})
    ctx = gan_context(with_prev=with_prev)
    value = loss(ctx)
    value.backward()
    assert value.ndim == 0 and torch.isfinite(value)
    assert ctx.pred.grad.abs().sum() > 0
    assert all(p.grad is None for p in loss.discriminator.parameters())
    assert all(p.requires_grad for p in loss.discriminator.parameters())


def test_adversarial_discriminator_loss_reaches_discriminator_only():
    loss = AdversarialLoss(weight=0.1, discriminator_config={"base": 8})
    ctx = gan_context()
    d_loss = loss.discriminator_loss(ctx)
    d_loss.backward()
    assert torch.isfinite(d_loss)
    assert ctx.pred.grad is None
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in loss.discriminator.parameters())


def test_adversarial_needs_condition():
    ctx = gan_context()
    ctx.lowres_up = None
    with pytest.raises(ValueError, match="lowres_up"):
        AdversarialLoss()(ctx)


# ----------------------------------------------------------------------------- builder


@pytest.mark.parametrize("name", sorted(PAPER_LOSSES))
def test_build_paper_losses(name, vgg_files):
    configs = copy.deepcopy(PAPER_LOSSES[name])
    for config in configs:
        if config["type"] == "perceptual":
            config["weights_path"] = vgg_files["pt"]
    losses = build_losses(configs)
    assert len(losses) == len(configs)
    ctx = gan_context()
    total, logs = total_loss(losses, ctx)
    total.backward()
    assert set(logs) == {loss.name for loss in losses}
    assert {"mask_l2", "normal_l1", "ao_l1"} <= set(logs)
    if name != "l1-normal":
        assert {"perceptual", "temporal", "adversarial"} <= set(logs)
    np.testing.assert_allclose(total.item(), float(sum(logs.values())), rtol=1e-5)
    assert ctx.pred.grad.abs().sum() > 0
    assert all(c["weights_path"] == "weights/vgg19_features.safetensors"
               for c in PAPER_LOSSES[name] if c["type"] == "perceptual")


@pytest.mark.parametrize("config, match", [
    ({"type": "nope"}, "needs a 'type'"),
    ({"channel": "normal"}, "needs a 'type'"),
    ({"type": "channel", "channel": "color", "kind": "l3"}, "kind must be"),
    ({"type": "channel", "channel": "albedo"}, "channel must be"),
    ({"type": "channel", "channel": "normal", "colour": 1}, "colour"),
    ({"type": "temporal", "weight": -1.0}, "weight must be"),
    ({"type": "adversarial", "discriminator_config": {"width": 3}}, "width"),
])
def test_build_losses_rejects_bad_configs(config, match):
    good = {"type": "channel", "channel": "normal"}
    with pytest.raises(ValueError, match=rf"loss config #1 .*{match}"):
        build_losses([good, config])


def test_build_losses_rejects_duplicates():
    config = {"type": "channel", "channel": "normal", "kind": "l1"}
    with pytest.raises(ValueError, match="#1 .*already configured"):
        build_losses([config, dict(config, weight=2.0)])
