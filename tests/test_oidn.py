"""Intel Open Image Denoise through pyoidn (optional): skipped with the reason where it is not installed."""

from __future__ import annotations

import pytest
import torch

from conftest import DEVICE
from isosr_net.filters import oidn

pytestmark = pytest.mark.skipif(oidn.unavailable() is not None, reason=str(oidn.unavailable()))


def noisy_sphere(h=48, w=64, seed=0):
    """A shaded disc: its clean color, a 1-ray-like noisy version (AO 0 or 1), the albedo and normals."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    inside = (xs ** 2 + ys ** 2 < 0.8).float()
    normal = torch.stack([xs, -ys, (1 - xs ** 2 - ys ** 2).clamp_min(0).sqrt()], -1) * inside[..., None]
    albedo = (0.3 + 0.6 * normal[..., 2:].clamp_min(0)).expand(h, w, 3) * inside[..., None] + (1 - inside[..., None])
    ao = 0.5 + 0.4 * xs
    clean = albedo * (inside * ao + 1 - inside)[..., None]
    hits = (torch.rand(h, w, generator=g) < ao).float()
    noisy = albedo * (inside * hits + 1 - inside)[..., None]
    return clean, noisy, albedo.contiguous(), normal


@pytest.mark.parametrize("quality", oidn.QUALITIES)
def test_denoising_brings_a_noisy_image_closer_to_the_clean_one(quality):
    clean, noisy, albedo, normal = (t.to(DEVICE) for t in noisy_sphere())
    out = oidn.denoise(noisy, albedo, normal, quality)
    assert out.shape == clean.shape and out.dtype == torch.float32 and out.device == clean.device
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    assert (out - clean).square().mean() < 0.5 * (noisy - clean).square().mean()


def test_bad_quality_and_shapes_are_refused():
    clean, noisy, albedo, normal = noisy_sphere(16, 16)
    with pytest.raises(ValueError, match="quality must be one of"):
        oidn.denoise(noisy, albedo, normal, "best")
    with pytest.raises(ValueError, match="normal its shape"):
        oidn.denoise(noisy, albedo, normal[:8])
