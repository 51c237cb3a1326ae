"""SRNet (isosr_net.model): shapes, output ranges, residual structure, recurrence, checkpoints."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from isosr_net.flow_warp import upscale_flow, warp_by_flow
from isosr_net.model import (FORMAT_VERSION, TRAINING_STATE, SRNet, SRNetConfig, build_model, load_checkpoint,
                             load_pretrained, read_config, save_checkpoint, save_pretrained)
from isosr_net.upscaler import DEFAULT_MODEL
from isosr_render.conventions import AO, DEPTH, HIGHRES_CHANNELS, LOWRES_CHANNELS, MASK, NORMAL

TINY = {"channels": 8, "residual_blocks": 1}


def lowres_batch(b: int = 2, h: int = 6, w: int = 5, seed: int = 0) -> torch.Tensor:
    """A plausible (B, 5, h, w) input: binary mask, unit normals and depth on the surface, 0 off it."""
    g = torch.Generator().manual_seed(seed)
    mask = (torch.rand(b, 1, h, w, generator=g) > 0.4).float()
    normal = F.normalize(torch.randn(b, 3, h, w, generator=g), dim=1)
    depth = 1.0 + torch.rand(b, 1, h, w, generator=g)
    return torch.cat([mask, normal * mask, depth * mask], dim=1)


def tiny_net(seed: int = 0, **config) -> SRNet:
    torch.manual_seed(seed)
    return SRNet(SRNetConfig(**{**TINY, **config})).eval()


def test_channel_orders_are_the_documented_ones():
    assert LOWRES_CHANNELS == ("mask", "normal_x", "normal_y", "normal_z", "depth")
    assert HIGHRES_CHANNELS == LOWRES_CHANNELS + ("ao",)


@pytest.mark.parametrize("tail", ["full", "subpixel"])
@pytest.mark.parametrize("upscale", [2, 4, 8])
def test_output_shapes(upscale, tail):
    net = tiny_net(upscale=upscale, tail=tail)
    lowres = lowres_batch(2, 5, 3)
    prev = torch.rand(2, 6, 5 * upscale, 3 * upscale)
    with torch.no_grad():
        out = net(lowres, prev)
        out_step, warped = net.step(lowres, None, None)
    assert out.shape == (2, 6, 5 * upscale, 3 * upscale)
    assert out_step.shape == warped.shape == out.shape


def test_mask_and_ao_lie_in_unit_interval():
    net = tiny_net(seed=1)
    with torch.no_grad():
        for m in net.modules():  # large weights push the raw outputs far outside [0, 1]
            if isinstance(m, torch.nn.Conv2d):
                m.weight.mul_(5.0)
        out = net(lowres_batch(seed=2), 3 * torch.randn(2, 6, 24, 20))
    assert out[:, MASK].min() >= 0 and out[:, MASK].max() <= 1
    assert out[:, AO].min() >= 0 and out[:, AO].max() <= 1
    assert (out[:, MASK] == 0).any() or (out[:, MASK] == 1).any()  # the clamp was needed
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("tail", ["full", "subpixel"])
@pytest.mark.parametrize("upscale", [2, 4])
def test_with_a_zero_tail_the_output_is_the_bilinear_upsampling(upscale, tail):
    net = tiny_net(seed=3, upscale=upscale, tail=tail)
    with torch.no_grad():
        net.tail[-1].weight.zero_()
        net.tail[-1].bias.zero_()
        lowres = lowres_batch(seed=4)
        lowres[:, MASK] = lowres[:, MASK] * 1.4 - 0.2  # outside [0, 1]: the mask gets clamped
        out = net(lowres, torch.rand(2, 6, 6 * upscale, 5 * upscale))
    base = F.interpolate(lowres, scale_factor=upscale, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out[:, MASK], base[:, 0:1].clamp(0, 1))
    torch.testing.assert_close(out[:, NORMAL], base[:, 1:4])
    torch.testing.assert_close(out[:, DEPTH], base[:, 4:5])
    torch.testing.assert_close(out[:, AO], torch.full_like(out[:, AO], 0.5))


def test_the_subpixel_tail_works_at_low_resolution_only():
    full, subpixel = tiny_net(upscale=4), tiny_net(upscale=4, tail="subpixel")
    assert len(full.upsample) == 2 and len(subpixel.upsample) == 0
    assert full.tail[-1].out_channels == 6 and subpixel.tail[-1].out_channels == 6 * 4 * 4
    # Its last conv's channel c s^2 + a s + b is output channel c at row phase a, column phase b
    # (F.pixel_shuffle's layout): a bias there moves that phase of that channel alone.
    with torch.no_grad():
        subpixel.tail[-1].weight.zero_()
        subpixel.tail[-1].bias.zero_()
        subpixel.tail[-1].bias[DEPTH.start * 16 + 1 * 4 + 2] = 1.0
        lowres = lowres_batch(seed=6)
        out = subpixel(lowres, torch.rand(2, 6, 24, 20))
    base = F.interpolate(lowres, scale_factor=4, mode="bilinear", align_corners=False)
    expected = torch.zeros_like(base[:, DEPTH])
    expected[..., 1::4, 2::4] = 1.0
    torch.testing.assert_close(out[:, DEPTH] - base[:, DEPTH], expected)


def test_the_previous_frame_changes_the_output():
    net = tiny_net(seed=5)
    lowres = lowres_batch(seed=6)
    with torch.no_grad():
        a = net(lowres, torch.zeros(2, 6, 24, 20))
        b = net(lowres, torch.rand(2, 6, 24, 20))
    assert not torch.allclose(a, b)


def test_first_frame_zeros_and_upsampled():
    lowres = lowres_batch(seed=7)
    zeros = tiny_net(first_frame="zeros")
    upsampled = tiny_net(first_frame="upsampled")
    torch.testing.assert_close(zeros.first_previous(lowres), torch.zeros(2, 6, 24, 20))
    expected = torch.cat([F.interpolate(lowres, scale_factor=4, mode="bilinear", align_corners=False),
                          torch.ones(2, 1, 24, 20)], dim=1)
    torch.testing.assert_close(upsampled.first_previous(lowres), expected)
    # step() on a first frame feeds exactly that stand-in to the network.
    with torch.no_grad():
        for net in (zeros, upsampled):
            out, warped = net.step(lowres, None, None)
            torch.testing.assert_close(warped, net.first_previous(lowres))
            torch.testing.assert_close(out, net(lowres, net.first_previous(lowres)))
        assert not torch.allclose(zeros.step(lowres, None, None)[0], upsampled.step(lowres, None, None)[0])


def test_step_warps_the_previous_output_by_the_upscaled_flow():
    net = tiny_net(seed=8)
    lowres = lowres_batch(seed=9)
    g = torch.Generator().manual_seed(10)
    previous = torch.rand(2, 6, 24, 20, generator=g)
    flow = torch.randn(2, 2, 6, 5, generator=g)
    with torch.no_grad():
        out, warped = net.step(lowres, flow, previous)
    expected_warped = warp_by_flow(previous, upscale_flow(flow, 4))
    torch.testing.assert_close(warped, expected_warped)
    torch.testing.assert_close(out, net(lowres, expected_warped))


def test_step_with_a_previous_output_needs_the_flow():
    net = tiny_net()
    with pytest.raises(ValueError, match="needs the flow"):
        net.step(lowres_batch(), None, torch.zeros(2, 6, 24, 20))


def test_forward_checks_shapes():
    net = tiny_net()
    with pytest.raises(ValueError, match=r"lowres must be \(B, 5, h, w\), got \(2, 4, 6, 5\)"):
        net(torch.zeros(2, 4, 6, 5), torch.zeros(2, 6, 24, 20))
    with pytest.raises(ValueError, match=r"prev_warped must be \(B, 6, 24, 20\) with B=2, got \(2, 6, 12, 10\)"):
        net(torch.zeros(2, 5, 6, 5), torch.zeros(2, 6, 12, 10))


def test_gradients_reach_every_parameter_and_the_inputs():
    net = tiny_net(seed=11).train()
    lowres = lowres_batch(seed=12).requires_grad_(True)
    prev = torch.rand(2, 6, 24, 20, requires_grad=True)
    net(lowres, prev).square().sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert lowres.grad.abs().sum() > 0 and prev.grad.abs().sum() > 0


@pytest.mark.parametrize("upscale", [0, 1, 3, 6, -4])
def test_config_rejects_upscale_that_is_not_a_power_of_two(upscale):
    with pytest.raises(ValueError, match="power of two"):
        SRNetConfig(upscale=upscale)


@pytest.mark.parametrize("kwargs, match", [
    ({"first_frame": "noise"}, "first_frame must be one of"),
    ({"tail": "bilinear"}, "tail must be one of"),
    ({"channels": 0}, "channels must be >= 1"),
    ({"residual_blocks": -1}, "residual_blocks >= 0"),
])
def test_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SRNetConfig(**kwargs)


def test_build_model():
    net = build_model({"type": "SRNet", "upscale": 2, **TINY})
    assert isinstance(net, SRNet) and net.config == SRNetConfig(upscale=2, **TINY)
    assert isinstance(build_model({"upscale": 8, **TINY}), SRNet)  # "type" defaults to SRNet


@pytest.mark.parametrize("config, match", [
    ({"type": "UNet"}, r"unknown model type 'UNet'; known: \['ReconNet', 'SRNet'\]"),
    ({"type": "SRNet", "width": 8}, "bad model config .*width"),
    ({"type": "SRNet", "upscale": 3}, "power of two"),
])
def test_build_model_errors(config, match):
    with pytest.raises(ValueError, match=match):
        build_model(config)


def test_save_and_load_round_trip(tmp_path):
    net = tiny_net(seed=13, upscale=2, first_frame="upsampled")
    save_pretrained(net, tmp_path / "ckpt", {"step": 7, "validation": {"color_psnr": 30.0}})
    assert sorted(p.name for p in (tmp_path / "ckpt").iterdir()) == ["config.json", "model.safetensors"]
    loaded, config = load_pretrained(tmp_path / "ckpt")
    assert config["model"] == {"type": "SRNet", "upscale": 2, "channels": 8, "residual_blocks": 1,
                               "first_frame": "upsampled", "tail": "full"}
    assert config["step"] == 7 and config["validation"] == {"color_psnr": 30.0}
    assert json.loads((tmp_path / "ckpt" / "config.json").read_text()) == config
    assert not loaded.training and loaded.config == net.config
    lowres = lowres_batch(seed=14)
    with torch.no_grad():
        a, _ = net.step(lowres, None, None)
        b, _ = loaded.step(lowres, None, None)
        flow = torch.randn(2, 2, 6, 5)
        a2, _ = net.step(lowres, flow, a)
        b2, _ = loaded.step(lowres, flow, b)
    assert torch.equal(a, b) and torch.equal(a2, b2)


def test_save_overwrites_an_existing_checkpoint(tmp_path):
    save_pretrained(tiny_net(seed=1), tmp_path)
    second = tiny_net(seed=2)
    save_pretrained(second, tmp_path)
    loaded, _ = load_pretrained(tmp_path)
    for (k, v), (k2, v2) in zip(second.state_dict().items(), loaded.state_dict().items()):
        assert k == k2 and torch.equal(v, v2)


@pytest.mark.parametrize("missing", ["config.json", "model.safetensors"])
def test_load_pretrained_missing_file(tmp_path, missing):
    save_pretrained(tiny_net(), tmp_path)
    (tmp_path / missing).unlink()
    with pytest.raises(FileNotFoundError, match=f"not a model folder, {missing} is missing"):
        load_pretrained(tmp_path)
    with pytest.raises(FileNotFoundError, match="config.json is missing"):
        load_pretrained(tmp_path / "nowhere")


@pytest.mark.parametrize("change", [{"channels": 16}, {"residual_blocks": 2}, {"upscale": 2}])
def test_load_pretrained_weights_that_do_not_fit_the_config(tmp_path, change):
    save_pretrained(tiny_net(), tmp_path)
    path = tmp_path / "config.json"
    config = json.loads(path.read_text())
    config["model"].update(change)
    path.write_text(json.dumps(config))
    with pytest.raises(ValueError, match="weights do not fit the config"):
        load_pretrained(tmp_path)


def test_config_format_version_old_files_read_as_1_future_ones_refused(tmp_path):
    save_pretrained(tiny_net(), tmp_path, {"note": "x"})
    path = tmp_path / "config.json"
    config = json.loads(path.read_text())
    assert config["format_version"] == FORMAT_VERSION == 1 and config["note"] == "x"
    del config["format_version"]
    path.write_text(json.dumps(config))
    assert read_config(tmp_path)["model"] == config["model"]
    load_pretrained(tmp_path)
    for version in (2, "1"):
        path.write_text(json.dumps({**config, "format_version": version}))
        with pytest.raises(ValueError, match=f"unknown format version {version!r}; this isosr reads version 1"):
            load_pretrained(tmp_path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_config(tmp_path)
    with pytest.raises(ValueError, match=r"may not set \['model'\]"):
        save_pretrained(tiny_net(), tmp_path, {"model": {}})


def test_the_shipped_config_holds_no_machine_paths():
    config = read_config(DEFAULT_MODEL)
    assert config["format_version"] == FORMAT_VERSION

    def strings(x):
        if isinstance(x, dict):
            return [s for v in x.values() for s in strings(v)]
        if isinstance(x, list):
            return [s for v in x for s in strings(v)]
        return [x] if isinstance(x, str) else []
    assert not [s for s in strings(config) if s.startswith(("/", "~")) or ":\\" in s]


def test_checkpoints_swap_in_whole_and_resume_from_old_after_a_cut_swap(tmp_path):
    folder = tmp_path / "last"
    assert load_checkpoint(folder) is None
    save_checkpoint(tiny_net(seed=1), folder, {"step": 1})  # a model folder without training state
    assert load_checkpoint(folder) is None
    save_checkpoint(tiny_net(seed=2), folder, {"step": 2}, {"step": 2, "best": 0.5})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last"]  # no .tmp or .old left behind
    found = load_checkpoint(folder)
    assert found.folder == folder and found.config["step"] == 2 and found.state == {"step": 2, "best": 0.5}
    for (k, v), (k2, v2) in zip(tiny_net(seed=2).state_dict().items(), found.model.state_dict().items()):
        assert k == k2 and torch.equal(v, v2)
    folder.rename(tmp_path / "last.old")  # cut between moving the old folder away and the new one in
    assert load_checkpoint(folder).folder == tmp_path / "last.old"
    assert (tmp_path / "last.old" / TRAINING_STATE).is_file()
