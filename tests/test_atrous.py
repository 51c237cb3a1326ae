"""The a-trous AO filter (Warp kernels): against a float64 torch reference (itself checked against a
naive float64 loop), and on the hard cases, on ``ISOSR_TEST_DEVICE``."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from conftest import DEVICE
import isosr_net.filters.atrous as atrous_module
from isosr_net.filters.atrous import B3, TINY, ATrousConfig, ATrousFilter, atrous_filter

# The kernels compute in float32; the reference in float64.
TOLERANCE = 1e-5


def naive_filter(ao, mask, normal, depth, config: ATrousConfig):
    """The module docstring's definition, pixel by pixel in Python floats (one image)."""
    h, w = len(ao), len(ao[0])
    cov = [[mask[y][x] > 0.5 for x in range(w)] for y in range(h)]
    deepest = max([abs(depth[y][x]) for y in range(h) for x in range(w) if cov[y][x]] or [0.0]) or 1.0
    z = [[depth[y][x] / deepest if cov[y][x] else 0.0 for x in range(w)] for y in range(h)]
    n = []
    for y in range(h):
        row = []
        for x in range(w):
            v = normal[y][x]
            length = max(math.sqrt(sum(c * c for c in v)), 1e-6)
            row.append([c / length if cov[y][x] else 0.0 for c in v])
        n.append(row)

    def grad(y, x, dy, dx):
        options = []
        for s in (1, -1):  # forward, then backward
            qy, qx = y + s * dy, x + s * dx
            if 0 <= qy < h and 0 <= qx < w and cov[y][x] and cov[qy][qx]:
                options.append(s * (z[qy][qx] - z[y][x]))
        return min(options, key=abs) if options else 0.0

    gx = [[grad(y, x, 0, 1) for x in range(w)] for y in range(h)]
    gy = [[grad(y, x, 1, 0) for x in range(w)] for y in range(h)]
    value = [[min(max(ao[y][x], 0.0), 1.0) if cov[y][x] else 0.0 for x in range(w)] for y in range(h)]
    for i in range(config.iterations):
        hole = 2 ** i
        new = [[0.0] * w for _ in range(h)]
        for y in range(h):
            for x in range(w):
                total = weight = 0.0
                for a in range(5):
                    for b in range(5):
                        dy, dx = (a - 2) * hole, (b - 2) * hole
                        qy, qx = y + dy, x + dx
                        if not (0 <= qy < h and 0 <= qx < w and cov[qy][qx]):
                            continue
                        wn = max(0.0, sum(p * q for p, q in zip(n[y][x], n[qy][qx]))) ** config.sigma_normal
                        tol = config.sigma_depth * abs(gx[y][x] * dx + gy[y][x] * dy) \
                            + config.depth_tolerance * abs(z[y][x]) + 1e-12
                        wz = math.exp(-abs(z[y][x] - z[qy][qx]) / tol)
                        wv = 1.0 if config.sigma_value is None else \
                            math.exp(-abs(value[y][x] - value[qy][qx]) / config.sigma_value)
                        wq = B3[a] * B3[b] * wn * wz * wv
                        total += wq * value[qy][qx]
                        weight += wq
                new[y][x] = total / weight if weight > 0 else 0.0
        value = new
    return [[value[y][x] if cov[y][x] else 0.0 for x in range(w)] for y in range(h)]

def reference_filter(ao, mask, normal, depth, config: ATrousConfig) -> torch.Tensor:
    """The module docstring's definition in whole-image torch operations (float64 in these tests).

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W). Returns (B, 1, H, W).
    """
    covered = (mask > 0.5).to(ao.dtype)
    deepest = (depth.abs() * covered).amax(dim=(1, 2, 3), keepdim=True)
    z = depth / torch.where(deepest > 0, deepest, torch.ones_like(deepest)) * covered
    gx, gy = reference_depth_gradient(z, covered)
    n = F.normalize(normal, dim=1, eps=1e-6) * covered
    value = ao.clamp(0.0, 1.0) * covered
    for i in range(config.iterations):
        value = reference_pass(value, covered, n, z, gx, gy, 2 ** i, config)
    return value * covered


def reference_depth_gradient(depth, covered):
    """Per-pixel depth change per pixel step, x right and y down: of the forward and backward
    differences between covered pixels the smaller in magnitude, 0 where neither neighbor is covered."""
    def along(pad_fwd, pad_bwd, diff, both):
        fwd = torch.where(F.pad(both, pad_fwd) > 0, F.pad(diff, pad_fwd), torch.inf)
        bwd = torch.where(F.pad(both, pad_bwd) > 0, F.pad(diff, pad_bwd), torch.inf)
        g = torch.where(fwd.abs() <= bwd.abs(), fwd, bwd)
        return torch.where(torch.isfinite(g), g, torch.zeros_like(g))

    gx = along((0, 1), (1, 0), depth[..., 1:] - depth[..., :-1], covered[..., 1:] * covered[..., :-1])
    gy = along((0, 0, 0, 1), (0, 0, 1, 0), depth[..., 1:, :] - depth[..., :-1, :],
               covered[..., 1:, :] * covered[..., :-1, :])
    return gx, gy


def reference_pass(value, covered, n, z, gx, gy, hole: int, config: ATrousConfig):
    """One a-trous pass with ``hole`` pixels between taps; out-of-image taps count as uncovered."""
    h, w = value.shape[-2:]
    pad = 2 * hole
    padded = [F.pad(t, (pad, pad, pad, pad)) for t in (value, covered, n, z)]
    base_tolerance = config.depth_tolerance * z.abs() + TINY
    total = torch.zeros_like(value)
    weight = torch.zeros_like(value)
    for a, ky in enumerate(B3):
        dy = (a - 2) * hole
        for b, kx in enumerate(B3):
            dx = (b - 2) * hole
            vq, cq, nq, zq = (t[..., pad + dy:pad + dy + h, pad + dx:pad + dx + w] for t in padded)
            wq = (ky * kx) * cq * (n * nq).sum(1, keepdim=True).clamp_min(0.0).pow(config.sigma_normal)
            tolerance = config.sigma_depth * (gx * dx + gy * dy).abs() + base_tolerance
            wq = wq * torch.exp(-(z - zq).abs() / tolerance)
            if config.sigma_value is not None:
                wq = wq * torch.exp(-(value - vq).abs() / config.sigma_value)
            total = total + wq * vq
            weight = weight + wq
    return torch.where(weight > 0, total / weight.clamp_min(TINY), torch.zeros_like(total))


def filtered_and_reference(ao, mask, normal, depth, config: ATrousConfig = ATrousConfig()):
    """The filter on DEVICE from float32 inputs, and the float64 reference from the same values."""
    inputs = [t.float() for t in (ao, mask, normal, depth)]
    got = atrous_filter(*(t.to(DEVICE) for t in inputs), config).cpu()
    assert got.dtype == torch.float32
    return got.double(), reference_filter(*(t.double() for t in inputs), config)


def assert_matches_reference(ao, mask, normal, depth, config: ATrousConfig = ATrousConfig()):
    got, want = filtered_and_reference(ao, mask, normal, depth, config)
    assert torch.isfinite(got).all() and got.min() >= 0 and got.max() <= 1
    assert (got - want).abs().max() <= TOLERANCE, float((got - want).abs().max())
    return got


def scene(h=7, w=9, seed=0, dtype=torch.float64):
    """A slanted plane and a step in depth, two normal directions, noisy AO, a few holes in the mask."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    right = xs >= w // 2
    depth = 2.0 + 0.05 * xs + 0.02 * ys + right * 0.5
    normal = torch.stack([torch.where(right, 0.6, 0.0), torch.zeros_like(xs), torch.where(right, 0.8, 1.0)])
    normal = normal + 0.05 * torch.randn(3, h, w, generator=g, dtype=dtype)
    mask = (torch.rand(h, w, generator=g, dtype=dtype) > 0.15).to(dtype)
    ao = torch.rand(h, w, generator=g, dtype=dtype)
    return ao[None, None], mask[None, None], normal[None], depth[None, None]


@pytest.mark.parametrize("config", [ATrousConfig(iterations=2, sigma_depth=1.0),
                                    ATrousConfig(iterations=3, sigma_normal=16.0, sigma_value=0.3)])
def test_the_reference_matches_the_naive_float64_loop(config):
    ao, mask, normal, depth = scene()
    got = reference_filter(ao, mask, normal, depth, config)[0, 0]
    want = torch.tensor(naive_filter(ao[0, 0].tolist(), mask[0, 0].tolist(), normal[0].permute(1, 2, 0).tolist(),
                                     depth[0, 0].tolist(), config), dtype=torch.float64)
    assert torch.allclose(got, want, atol=1e-12, rtol=0)
    assert (got[mask[0, 0] > 0.5] != ao[0, 0][mask[0, 0] > 0.5]).any()  # it did filter


CONFIGS = [ATrousConfig(), ATrousConfig(iterations=2, sigma_depth=1.0),
           ATrousConfig(iterations=3, sigma_normal=16.0, sigma_value=0.3),
           ATrousConfig(iterations=4, sigma_normal=0.0, sigma_depth=0.0, depth_tolerance=0.0),
           ATrousConfig(sigma_normal=4.0, sigma_depth=4.0, depth_tolerance=0.05, sigma_value=0.05)]


@pytest.mark.parametrize("config", CONFIGS)
def test_matches_the_float64_reference_on_a_structured_scene(config):
    got = assert_matches_reference(*scene(24, 40, seed=3), config)
    ao, mask = scene(24, 40, seed=3)[:2]
    if config.sigma_depth > 0:
        assert (got - ao.double() * (mask > 0.5)).abs().max() > 0.01  # it did filter


@pytest.mark.parametrize("seed", range(3))
def test_matches_the_float64_reference_on_random_inputs(seed):
    """Random normals, depths over three decades with random steps, half the pixels covered, batch of 2."""
    g = torch.Generator().manual_seed(seed)
    b, h, w = 2, 19, 33
    ao = torch.rand(b, 1, h, w, generator=g) * 1.4 - 0.2  # values outside [0, 1] are clamped
    mask = torch.rand(b, 1, h, w, generator=g)
    normal = torch.randn(b, 3, h, w, generator=g)
    depth = 10 ** (3 * torch.rand(b, 1, h, w, generator=g)) * (1 + 0.01 * torch.randn(b, 1, h, w, generator=g))
    smooth = 5 + 0.1 * torch.arange(w) + 0.05 * torch.arange(h)[:, None]  # and one smooth slanted image
    depth[1, 0] = smooth
    for config in (ATrousConfig(), ATrousConfig(sigma_normal=2.0, sigma_value=0.2)):
        assert_matches_reference(ao, mask, normal, depth, config)


@pytest.mark.parametrize("h, w", [(1, 1), (1, 17), (17, 1), (2, 3), (5, 5)])
def test_tiny_images_and_holes_larger_than_the_image(h, w):
    assert_matches_reference(*scene(h, w, seed=h * w), ATrousConfig(iterations=5, sigma_normal=8.0))


def test_the_output_keeps_the_input_dtype_and_a_strided_normal_view_works():
    ao, mask, normal, depth = scene(9, 12, seed=5)
    out64 = atrous_filter(*(t.to(DEVICE) for t in (ao, mask, normal, depth)))
    assert out64.dtype == torch.float64
    channels_last = normal.float().permute(0, 2, 3, 1).contiguous().to(DEVICE)  # (B, H, W, 3) as the renderer's
    out = atrous_filter(*(t.float().to(DEVICE) for t in (ao, mask)), channels_last.permute(0, 3, 1, 2),
                        depth.float().to(DEVICE))
    assert torch.equal(out, atrous_filter(*(t.float().to(DEVICE) for t in (ao, mask, normal, depth))))
    assert (out.double() - out64).abs().max() <= TOLERANCE


def test_smooths_noise_on_a_plane_and_keeps_an_edge():
    h, w = 32, 32
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    left = xs < w // 2
    normal = torch.stack([torch.where(left, 0.0, 1.0), torch.zeros(h, w), torch.where(left, 1.0, 0.0)])[None]
    depth = torch.full((1, 1, h, w), 2.0)
    truth = torch.where(left, 0.2, 0.9)[None, None].float()
    g = torch.Generator().manual_seed(1)
    noisy = (truth + 0.2 * torch.randn(1, 1, h, w, generator=g)).clamp(0, 1)
    out = assert_matches_reference(noisy, torch.ones(1, 1, h, w), normal, depth).float()
    assert (out - truth).abs().mean() < 0.4 * (noisy - truth).abs().mean()
    # No leaking across the normal edge: each side keeps its own mean.
    assert abs(out[0, 0][left].mean() - 0.2) < 0.03 and abs(out[0, 0][~left].mean() - 0.9) < 0.03


def test_empty_mask_gives_zeros_and_uncovered_pixels_stay_zero():
    ao, mask, normal, depth = scene()
    out = assert_matches_reference(ao, torch.zeros_like(mask), normal, depth)
    assert out.abs().max() == 0
    out = assert_matches_reference(ao, mask, normal, depth)
    assert out[mask < 0.5].abs().max() == 0


def test_full_mask_constant_ao_is_unchanged():
    ao, mask, normal, depth = scene()
    out = assert_matches_reference(torch.full_like(ao, 0.37), torch.ones_like(mask), normal, depth)
    assert torch.allclose(out, torch.full_like(out, 0.37), atol=1e-6)


@pytest.mark.parametrize("depth_value", [0.0, 1e-30, 1e30, 3e38])
def test_depth_zero_and_extreme_depths_stay_finite_and_bounded(depth_value):
    ao, mask, normal, depth = scene()
    depth = torch.full_like(depth, depth_value)
    depth[..., 0, 0] = depth_value * 0.5
    assert_matches_reference(ao, mask, normal, depth)  # finite, in [0, 1], as the reference


def test_float64_depths_beyond_float32_and_zero_normals_stay_finite():
    ao, mask, normal, depth = scene()
    normal[..., :3, :] = 0.0  # covered pixels without a normal: no tap weighs anything there
    out = atrous_filter(*(t.to(DEVICE) for t in (ao, mask, normal, depth * 1e300)))
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    assert out[..., :3, :].abs().max() == 0
    assert (out.cpu() - reference_filter(ao, mask, normal, depth, ATrousConfig())).abs().max() <= TOLERANCE


@pytest.mark.parametrize("config", [ATrousConfig(sigma_normal=1e300, sigma_depth=1e300, depth_tolerance=1e300),
                                    ATrousConfig(sigma_normal=1e-300, sigma_depth=1e-300, sigma_value=1e-300),
                                    ATrousConfig(sigma_value=1e300)])
def test_extreme_knobs_stay_finite_and_bounded(config):
    """Knobs beyond float32's range are clamped into it, never inf or a flushed 0 (0 / 0 in the kernel)."""
    ao, mask, normal, depth = scene(dtype=torch.float32)
    out = atrous_filter(*(t.to(DEVICE) for t in (ao, mask, normal, depth)), config)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    if config.sigma_normal < 1e3:  # beyond, a unit normal's rounded self-dot (below 1) may weigh 0
        assert out[mask.to(DEVICE) > 0.5].min() > 0  # every covered pixel kept weight (its own tap at least)


def test_one_pixel_images_and_the_module():
    one = torch.ones(1, 1, 1, 1, device=DEVICE)
    out = ATrousFilter()(one * 0.4, one, torch.tensor([0.0, 0.0, 1.0], device=DEVICE).view(1, 3, 1, 1), one)
    assert out.shape == (1, 1, 1, 1) and float(out) == pytest.approx(0.4)


def test_bad_inputs_are_refused_with_the_buffer_named():
    ao, mask, normal, depth = scene(dtype=torch.float32)
    with pytest.raises(ValueError, match="normal must be"):
        atrous_filter(ao, mask, normal[:, :2], depth)
    with pytest.raises(ValueError, match="depth holds NaN"):
        atrous_filter(ao, mask, normal, depth * float("nan"))
    with pytest.raises(ValueError, match="ao must be"):
        atrous_filter(ao[0], mask, normal, depth)
    with pytest.raises(ValueError, match="mask must be floating point"):
        atrous_filter(ao, mask > 0.5, normal, depth)
    with pytest.raises(ValueError, match="empty"):
        atrous_filter(*(t[..., :0] for t in (ao, mask, normal, depth)))
    with pytest.raises(ValueError, match="iterations"):
        ATrousConfig(iterations=6)
    if DEVICE != "cpu":
        with pytest.raises(ValueError, match="depth is on"):
            atrous_filter(*(t.to(DEVICE) for t in (ao, mask, normal)), depth)


@pytest.mark.skipif(DEVICE != "cpu", reason="CPU row bands; the GPU machine's Warp has no CPU backend")
def test_row_bands_and_one_whole_launch_agree_bit_for_bit(monkeypatch):
    """The CPU's row bands on a thread pool against the GPU's single launch, run on the CPU."""
    inputs = [t.float() for t in scene(37, 23, seed=4)]
    banded = atrous_filter(*inputs, ATrousConfig(sigma_value=0.3))
    monkeypatch.setattr(atrous_module, "_launch_in_row_bands", atrous_module._launch_whole)
    assert torch.equal(banded, atrous_filter(*inputs, ATrousConfig(sigma_value=0.3)))
