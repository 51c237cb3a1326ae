"""Inference (isosr_net.upscaler): shapes and conventions of the output, recurrent state, tiling,
precision, and input validation."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from isosr_net.model import load_pretrained
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_net.inference import output_buffers, surface_tensors
from isosr_render.steps import count_steps
from isosr_render.buffers import FrameBuffers
from net_fixtures import render_lowres_frames, tiny_model_dir


@pytest.fixture
def frames24() -> list[FrameBuffers]:
    return render_lowres_frames(24, 24)


@pytest.fixture(scope="module")
def default_upscaler() -> Upscaler:
    if not (DEFAULT_MODEL / "model.safetensors").is_file():
        pytest.skip(f"the shipped model is missing at {DEFAULT_MODEL}")
    return Upscaler()


def check_output(out: FrameBuffers, h: int, w: int) -> None:
    """Output conventions: sizes, mask alpha and AO in [0, 1], unit normals on the surface, 0 off it."""
    assert out.present() == ["mask", "normal", "depth", "ao"]
    assert out.mask.shape == out.depth.shape == out.ao.shape == (h, w) and out.normal.shape == (h, w, 3)
    assert all(t.dtype == torch.float32 for t in (out.mask, out.normal, out.depth, out.ao))
    assert out.mask.min() >= 0 and out.mask.max() <= 1
    assert out.ao.min() >= 0 and out.ao.max() <= 1
    covered = out.mask > 0
    assert covered.any() and (~covered).any()
    torch.testing.assert_close(out.normal[covered].norm(dim=-1), torch.ones(int(covered.sum())), atol=1e-4, rtol=0)
    assert (out.normal[~covered] == 0).all() and (out.depth[~covered] == 0).all()


def test_the_shipped_model_upscales_4x(default_upscaler, frames24):
    default_upscaler.reset()
    assert default_upscaler.upscale_factor == 4 and default_upscaler.net.config.upscale == 4
    for frame in frames24:
        check_output(default_upscaler.upscale(frame), 96, 96)


def pooled_agreement(upscaler: Upscaler, frame: FrameBuffers) -> dict:
    """The output average-pooled to the input size, where both cover fully."""
    out = upscaler.upscale(frame)
    s = upscaler.upscale_factor
    pool = lambda x: F.avg_pool2d(x[None], s)[0]  # noqa: E731
    mask = pool(out.mask[None])[0]
    both = (mask > 0.9) & (frame.mask > 0)
    normal = F.normalize(pool(out.normal.permute(2, 0, 1)), dim=0).permute(1, 2, 0)
    return {"mask_error": float((mask - frame.mask).abs().mean()),
            "normal_cos": (normal[both] * frame.normal[both]).sum(-1),
            "depth_error": (pool(out.depth[None])[0][both] - frame.depth[both]).abs()}


def test_the_shipped_model_follows_the_input_mask_and_normals(default_upscaler, frames24):
    default_upscaler.reset()
    for frame in frames24:
        agreement = pooled_agreement(default_upscaler, frame)
        assert agreement["mask_error"] < 0.05
        assert agreement["normal_cos"].median() > 0.98 and agreement["normal_cos"].min() > 0.5


def test_the_shipped_model_follows_the_input_depth(default_upscaler, frames24):
    default_upscaler.reset()
    for frame in frames24:
        assert pooled_agreement(default_upscaler, frame)["depth_error"].median() < 0.05


@pytest.mark.parametrize("upscale", [2, 4])
def test_a_tiny_checkpoint_upscales_by_its_factor(tmp_path_factory, frames24, upscale):
    up = Upscaler(tiny_model_dir(tmp_path_factory, upscale=upscale))
    assert up.upscale_factor == upscale
    for frame in frames24[:2]:
        out = up.upscale(frame)
        assert out.mask.shape == (24 * upscale, 24 * upscale) and out.normal.shape == (24 * upscale, 24 * upscale, 3)


def test_non_square_frames(tmp_path_factory):
    frames = render_lowres_frames(20, 12, frames=2)
    up = Upscaler(tiny_model_dir(tmp_path_factory))
    for frame in frames:
        out = up.upscale(frame)
        assert out.mask.shape == (24, 40) and out.normal.shape == (24, 40, 3)


def test_the_previous_output_is_used(tmp_path_factory, frames24):
    model = tiny_model_dir(tmp_path_factory)
    up = Upscaler(model)
    up.upscale(frames24[0])
    continued = up.upscale(frames24[1])
    up.reset()
    assert up.previous is None
    after_reset = up.upscale(frames24[1])  # with its flow, but nothing to warp
    assert not torch.allclose(continued.mask, after_reset.mask) or not torch.allclose(continued.ao, after_reset.ao)
    # After reset() the stream starts anew: the same as a fresh upscaler.
    fresh = Upscaler(model).upscale(frames24[1])
    for name in ("mask", "normal", "depth", "ao"):
        torch.testing.assert_close(getattr(after_reset, name), getattr(fresh, name))


def test_the_state_is_the_warped_previous_output(tmp_path_factory, frames24):
    up = Upscaler(tiny_model_dir(tmp_path_factory))
    lowres0, _ = surface_tensors(frames24[0])
    lowres1, flow1 = surface_tensors(frames24[1])
    out0 = up.step(lowres0, None)
    assert torch.equal(up.previous, out0)
    out1 = up.step(lowres1, flow1)
    with torch.no_grad():
        expected, _ = up.net.step(lowres1, flow1, out0)
    torch.testing.assert_close(out1, expected)


def test_a_frame_without_flow_resets(tmp_path_factory, frames24):
    model = tiny_model_dir(tmp_path_factory)
    up = Upscaler(model)
    up.upscale(frames24[0])
    cut = frames24[1]
    cut.flow = None  # a camera cut: no flow to the previous frame
    out = up.upscale(cut)
    fresh = Upscaler(model).upscale(cut)
    for name in ("mask", "normal", "depth", "ao"):
        torch.testing.assert_close(getattr(out, name), getattr(fresh, name))


def test_a_frame_size_change_resets_instead_of_crashing(tmp_path_factory, frames24):
    model = tiny_model_dir(tmp_path_factory)
    up = Upscaler(model)
    up.upscale(frames24[0])
    small = render_lowres_frames(16, 12, frames=2)[1]  # has a flow of its own size
    out = up.upscale(small)
    assert out.mask.shape == (24, 32)
    small.flow = None
    fresh = Upscaler(model).upscale(small)
    torch.testing.assert_close(out.mask, fresh.mask)
    torch.testing.assert_close(out.ao, fresh.ao)
    assert up.previous.shape == (1, 6, 24, 32)


def test_tiled_equals_untiled_on_the_shipped_model(default_upscaler):
    frames = render_lowres_frames(40, 28, frames=2)
    tiled = Upscaler(tile=8)  # default halo
    default_upscaler.reset()
    for frame in frames:
        whole = default_upscaler.step(*surface_tensors(frame))
        parts = tiled.step(*surface_tensors(frame))
        assert parts.shape == whole.shape == (1, 6, 112, 160)
        torch.testing.assert_close(parts, whole, atol=1e-4, rtol=0)


def test_a_tiled_frame_runs_in_slices_one_a_tile(default_upscaler):
    """Tiles of 8 over a 40x28 frame: 5 x 4 tiles, a yield between each two (a scheduler may
    interleave other work there); the same output as run whole."""
    frame = render_lowres_frames(40, 28, frames=1)[0]
    slices, out = count_steps(Upscaler(tile=8).steps(*surface_tensors(frame)))
    assert slices == 5 * 4 - 1
    default_upscaler.reset()
    torch.testing.assert_close(out, default_upscaler.step(*surface_tensors(frame)), atol=1e-4, rtol=0)


def test_a_tile_covering_the_frame_runs_whole(tmp_path_factory, frames24):
    model = tiny_model_dir(tmp_path_factory)
    a = Upscaler(model).step(*surface_tensors(frames24[0]))
    b = Upscaler(model, tile=32).step(*surface_tensors(frames24[0]))
    assert torch.equal(a, b)


@pytest.mark.parametrize("precision, max_mask_diff", [("bf16", 0.25), ("fp16", 0.02)])
def test_reduced_precision_runs_and_stays_close(default_upscaler, frames24, precision, max_mask_diff):
    low = Upscaler(precision=precision)
    default_upscaler.reset()
    for frame in frames24[:2]:
        ref = default_upscaler.step(*surface_tensors(frame))
        out = low.step(*surface_tensors(frame))
        assert out.dtype == torch.float32 and out.shape == ref.shape and torch.isfinite(out).all()
        assert (out - ref).abs().mean() < 0.02
        assert (out[:, 0] - ref[:, 0]).abs().max() < max_mask_diff


def test_fp16_refuses_depths_beyond_its_range_where_bf16_stays_finite(default_upscaler, frames24):
    lowres, _ = surface_tensors(frames24[0])
    lowres[:, 4] = torch.where(lowres[:, 0] > 0, 1e5, 0.0)  # a surface 1e5 world units away
    with pytest.raises(ValueError, match=r"fp16 takes depths up to 10000, this frame reaches 1e\+05"):
        Upscaler(precision="fp16").step(lowres, None)
    assert torch.isfinite(Upscaler(precision="bf16").step(lowres, None)).all()


def test_fast_layers_give_the_same_frames(default_upscaler):
    frames = render_lowres_frames(40, 28, frames=3)
    fast = Upscaler(fast_layers=True, channels_last=True)
    default_upscaler.reset()
    for frame in frames:
        ref = default_upscaler.step(*surface_tensors(frame))
        torch.testing.assert_close(fast.step(*surface_tensors(frame)), ref, atol=1e-4, rtol=0)
    assert type(fast.net).__name__ == "FastSRNet" and type(default_upscaler.net).__name__ == "SRNet"


def test_fastest_on_a_cpu_is_eager_fp32():
    up = Upscaler.fastest(device="cpu")
    assert up.precision == "fp32" and up._network is up.net
    assert type(up.net).__name__ == "SRNet"


# ---------------------------------------------------------------- inputs and errors


def test_surface_tensors_layout(frames24):
    frame = frames24[1]
    lowres, flow = surface_tensors(frame)
    assert lowres.shape == (1, 5, 24, 24) and flow.shape == (1, 2, 24, 24)
    assert torch.equal(lowres[0, 0], frame.mask) and torch.equal(lowres[0, 4], frame.depth)
    assert torch.equal(lowres[0, 1:4], frame.normal.permute(2, 0, 1))
    assert torch.equal(flow[0], frame.flow.permute(2, 0, 1))
    assert surface_tensors(frames24[0])[1] is None
    double = FrameBuffers(mask=frame.mask.double(), normal=frame.normal.double(), depth=frame.depth.double())
    assert surface_tensors(double)[0].dtype == torch.float32


def test_output_buffers_conventions():
    out = torch.zeros(1, 6, 4, 4)
    out[0, 0, :2] = 0.7  # covered top half
    out[0, 1:4] = torch.tensor([0.0, 3.0, 4.0]).view(3, 1, 1)  # not unit length
    out[0, 4] = 2.0
    out[0, 5] = 1.5  # AO past 1
    frame = output_buffers(out)
    torch.testing.assert_close(frame.normal[:2], torch.tensor([0.0, 0.6, 0.8]).expand(2, 4, 3))
    assert (frame.normal[2:] == 0).all() and (frame.depth[2:] == 0).all() and (frame.depth[:2] == 2).all()
    assert (frame.ao == 1).all() and torch.equal(frame.mask, out[0, 0])


def bad_frames(frame: FrameBuffers) -> list[tuple[str, FrameBuffers, str]]:
    m, n, d, f = frame.mask, frame.normal, frame.depth, frame.flow
    nan_normal = n.clone()
    nan_normal[3, 4, 0] = float("nan")
    inf_flow = f.clone()
    inf_flow[0, 0, 1] = float("inf")
    return [
        ("no mask", FrameBuffers(normal=n, depth=d), "lacks its mask buffer"),
        ("no normal", FrameBuffers(mask=m, depth=d), "lacks its normal buffer"),
        ("no depth", FrameBuffers(mask=m, normal=n), "lacks its depth buffer"),
        ("mask 3d", FrameBuffers(mask=m[..., None], normal=n, depth=d),
         r"mask must be \(H, W\), got \(24, 24, 1\)"),
        ("normal 2ch", FrameBuffers(mask=m, normal=n[..., :2], depth=d),
         r"normal must be \(H, W, 3\) with H=24, W=24, got \(24, 24, 2\)"),
        ("depth size", FrameBuffers(mask=m, normal=n, depth=d[:-1]),
         r"depth must be \(H, W\) with H=24, W=24, got \(23, 24\)"),
        ("flow size", FrameBuffers(mask=m, normal=n, depth=d, flow=f[:, :-2]),
         r"flow must be \(H, W, 2\) with H=24, W=24, got \(24, 22, 2\)"),
        ("int mask", FrameBuffers(mask=m.to(torch.int32), normal=n, depth=d),
         "mask must be floating point, got torch.int32"),
        ("bool mask", FrameBuffers(mask=m > 0, normal=n, depth=d), "mask must be floating point"),
        ("int flow", FrameBuffers(mask=m, normal=n, depth=d, flow=f.to(torch.int64)), "flow must be floating point"),
        ("nan normal", FrameBuffers(mask=m, normal=nan_normal, depth=d), "normal holds NaN or Inf"),
        ("inf flow", FrameBuffers(mask=m, normal=n, depth=d, flow=inf_flow), "flow holds NaN or Inf"),
    ]


BAD_CASES = ["no mask", "no normal", "no depth", "mask 3d", "normal 2ch", "depth size", "flow size", "int mask",
             "bool mask", "int flow", "nan normal", "inf flow"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_is_a_clear_value_error(tmp_path_factory, frames24, case):
    up = Upscaler(tiny_model_dir(tmp_path_factory))
    cases = {name: (frame, match) for name, frame, match in bad_frames(frames24[1])}
    assert sorted(cases) == sorted(BAD_CASES)
    frame, match = cases[case]
    with pytest.raises(ValueError, match=match):
        up.upscale(frame)
    assert up.previous is None  # nothing ran


def test_bad_constructor_arguments(tmp_path_factory, tmp_path):
    model = tiny_model_dir(tmp_path_factory)
    with pytest.raises(ValueError, match=r"precision must be one of \['bf16', 'fp16', 'fp32'\], got 'fp64'"):
        Upscaler(model, precision="fp64")
    with pytest.raises(ValueError, match="tile must be positive, got 0"):
        Upscaler(model, tile=0)
    with pytest.raises(FileNotFoundError, match="not a model folder"):
        Upscaler(tmp_path)


def test_the_default_model_is_the_shipped_folder(default_upscaler):
    net, config = load_pretrained(DEFAULT_MODEL)
    assert default_upscaler.config == config
    for k, v in net.state_dict().items():
        assert torch.equal(default_upscaler.net.state_dict()[k], v)
    assert not default_upscaler.net.training


@pytest.mark.parametrize("case", ["empty frame", "full frame", "huge flow", "far depth"])
def test_hard_inputs_give_finite_bounded_outputs(default_upscaler, frames24, case):
    """Frames with nothing or everything covered, flow pointing far outside, a distant surface."""
    frame = frames24[1]
    mask, normal, depth, flow = frame.mask.clone(), frame.normal.clone(), frame.depth.clone(), frame.flow.clone()
    if case == "empty frame":
        mask, normal, depth, flow = (torch.zeros_like(t) for t in (mask, normal, depth, flow))
    elif case == "full frame":
        mask = torch.ones_like(mask)
        normal = torch.zeros_like(normal)
        normal[..., 2] = 1.0
        depth = torch.full_like(depth, 1.5)
    elif case == "huge flow":
        flow = torch.full_like(flow, 1e6)
    else:
        depth = depth * 1e4
    default_upscaler.reset()
    default_upscaler.upscale(frames24[0])
    out = default_upscaler.upscale(FrameBuffers(mask=mask, normal=normal, depth=depth, flow=flow))
    for name in ("mask", "normal", "depth", "ao"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert out.mask.min() >= 0 and out.mask.max() <= 1 and out.ao.min() >= 0 and out.ao.max() <= 1
    if case == "empty frame":
        assert out.mask.max() < 0.5  # no surface appears from nothing
    if case == "full frame":
        assert out.mask.min() > 0.5
