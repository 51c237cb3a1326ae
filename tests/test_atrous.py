"""The a-trous AO filter: against a naive float64 loop, and on the hard cases."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import DEVICE
from isosr_net.atrous import B3, ATrousConfig, ATrousFilter, atrous_filter


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
def test_matches_the_naive_float64_loop(config):
    ao, mask, normal, depth = scene()
    got = atrous_filter(ao, mask, normal, depth, config)[0, 0]
    want = torch.tensor(naive_filter(ao[0, 0].tolist(), mask[0, 0].tolist(), normal[0].permute(1, 2, 0).tolist(),
                                     depth[0, 0].tolist(), config), dtype=torch.float64)
    assert torch.allclose(got, want, atol=1e-12, rtol=0)
    assert (got[mask[0, 0] > 0.5] != ao[0, 0][mask[0, 0] > 0.5]).any()  # it did filter


def test_smooths_noise_on_a_plane_and_keeps_an_edge():
    h, w = 32, 32
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    left = xs < w // 2
    normal = torch.stack([torch.where(left, 0.0, 1.0), torch.zeros(h, w), torch.where(left, 1.0, 0.0)])[None]
    depth = torch.full((1, 1, h, w), 2.0)
    truth = torch.where(left, 0.2, 0.9)[None, None].float()
    g = torch.Generator().manual_seed(1)
    noisy = (truth + 0.2 * torch.randn(1, 1, h, w, generator=g)).clamp(0, 1)
    out = atrous_filter(noisy, torch.ones(1, 1, h, w), normal, depth)
    assert (out - truth).abs().mean() < 0.4 * (noisy - truth).abs().mean()
    # No leaking across the normal edge: each side keeps its own mean.
    assert abs(out[0, 0][left].mean() - 0.2) < 0.03 and abs(out[0, 0][~left].mean() - 0.9) < 0.03


def test_empty_mask_gives_zeros_and_uncovered_pixels_stay_zero():
    ao, mask, normal, depth = scene(dtype=torch.float32)
    out = atrous_filter(ao, torch.zeros_like(mask), normal, depth)
    assert out.abs().max() == 0
    out = atrous_filter(ao, mask, normal, depth)
    assert out[mask < 0.5].abs().max() == 0


def test_full_mask_constant_ao_is_unchanged():
    ao, mask, normal, depth = scene(dtype=torch.float32)
    out = atrous_filter(torch.full_like(ao, 0.37), torch.ones_like(mask), normal, depth)
    assert torch.allclose(out, torch.full_like(out, 0.37), atol=1e-6)


@pytest.mark.parametrize("depth_value", [0.0, 1e-30, 1e30, 3e38])
def test_depth_zero_and_extreme_depths_stay_finite_and_bounded(depth_value):
    ao, mask, normal, depth = scene(dtype=torch.float32)
    depth = torch.full_like(depth, depth_value)
    depth[..., 0, 0] = depth_value * 0.5
    out = atrous_filter(ao, mask, normal, depth)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1


def test_one_pixel_images_and_the_module():
    one = torch.ones(1, 1, 1, 1)
    out = ATrousFilter()(one * 0.4, one, torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1), one)
    assert out.shape == (1, 1, 1, 1) and float(out) == pytest.approx(0.4)


def test_bad_inputs_are_refused_with_the_buffer_named():
    ao, mask, normal, depth = scene(dtype=torch.float32)
    with pytest.raises(ValueError, match="normal must be"):
        atrous_filter(ao, mask, normal[:, :2], depth)
    with pytest.raises(ValueError, match="depth holds NaN"):
        atrous_filter(ao, mask, normal, depth * float("nan"))
    with pytest.raises(ValueError, match="ao must be"):
        atrous_filter(ao[0], mask, normal, depth)
    with pytest.raises(ValueError, match="iterations"):
        ATrousConfig(iterations=6)


@pytest.mark.skipif(DEVICE == "cpu", reason="compiling takes minutes on a CPU; run with ISOSR_TEST_DEVICE=cuda")
def test_the_compiled_filter_matches_the_eager_one_at_two_sizes():
    for h, w in ((7, 9), (64, 96)):
        ao, mask, normal, depth = (t.float().to(DEVICE) for t in scene(h, w))
        eager = atrous_filter(ao, mask, normal, depth)
        assert torch.allclose(atrous_filter(ao, mask, normal, depth, compiled=True), eager, atol=1e-5)
