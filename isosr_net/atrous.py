"""The edge-avoiding a-trous AO filter: the non-learned reconstruction a network must beat.

Dammertz, Sewtz, Hanika and Lensch (2010), "Edge-Avoiding A-Trous Wavelet Transform for
fast Global Illumination Filtering", as SVGF (Schied et al. 2017) uses it: a 5x5 B3-spline
kernel applied ``iterations`` times with holes 1, 2, 4, 8, 16 between its taps, each tap
weighted by how alike the two pixels' surfaces are:

- normal: ``max(0, dot(n_p, n_q)) ** sigma_normal``;
- depth: ``exp(-|z_p - z_q| / (sigma_depth * |grad z_p . (q - p)| + depth_tolerance * z_p))``,
  the difference measured against the change the depth gradient predicts (so slanted planes
  blur along themselves), depth taken relative to the image's deepest covered pixel;
- optionally AO value: ``exp(-|ao_p - ao_q| / sigma_value)``.

Only covered pixels (mask > 0.5) contribute and receive values; uncovered ones stay 0. The
center tap always weighs ``(3/8)^2`` on a covered pixel, so the result is a convex combination
of AO values: it stays in [0, 1] and finite.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

# The B3-spline's taps.
B3 = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)
# Floor of the depth tolerance, so equal depths weigh 1 and nothing divides by zero.
TINY = 1e-12
MAX_ITERATIONS = 5


@dataclass(frozen=True)
class ATrousConfig:
    """The filter's knobs (defaults as in SVGF).

    Attributes:
        iterations: passes, holes 1, 2, ..., 2^(iterations - 1); 1 to 5.
        sigma_normal: exponent of the normal weight.
        sigma_depth: depth tolerance in multiples of the change the depth gradient predicts.
        depth_tolerance: plus this fraction of the pixel's (relative) depth.
        sigma_value: AO-value tolerance; None: no value weight.
    """

    iterations: int = 5
    sigma_normal: float = 128.0
    sigma_depth: float = 1.0
    depth_tolerance: float = 1e-3
    sigma_value: float | None = None

    def __post_init__(self):
        if not isinstance(self.iterations, int) or not 1 <= self.iterations <= MAX_ITERATIONS:
            raise ValueError(f"iterations must be an integer in [1, {MAX_ITERATIONS}], got {self.iterations!r}")
        for name in ("sigma_normal", "sigma_depth", "depth_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value < float("inf")):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.sigma_value is not None and not (0 < self.sigma_value < float("inf")):
            raise ValueError(f"sigma_value must be positive and finite or None, got {self.sigma_value!r}")


def _check(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor) -> None:
    if ao.ndim != 4 or ao.shape[1] != 1:
        raise ValueError(f"atrous_filter: ao must be (B, 1, H, W), got {tuple(ao.shape)}")
    b, _, h, w = ao.shape
    for name, t, c in (("mask", mask, 1), ("normal", normal, 3), ("depth", depth, 1)):
        if tuple(t.shape) != (b, c, h, w):
            raise ValueError(f"atrous_filter: {name} must be {(b, c, h, w)}, got {tuple(t.shape)}")
    for name, t in (("ao", ao), ("mask", mask), ("normal", normal), ("depth", depth)):
        if not t.is_floating_point():
            raise ValueError(f"atrous_filter: {name} must be floating point, got {t.dtype}")
        if not torch.isfinite(t).all():
            raise ValueError(f"atrous_filter: {name} holds NaN or Inf values")


def depth_gradient(depth: torch.Tensor, covered: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel depth change per pixel step, x right and y down: of the forward and backward
    differences between covered pixels the smaller in magnitude (so silhouettes do not count),
    0 where neither neighbor is covered.

    Shape:
        depth, covered: (B, 1, H, W). Returns two (B, 1, H, W).
    """
    def along(pad_fwd, pad_bwd, diff, both):
        fwd = torch.where(F.pad(both, pad_fwd) > 0, F.pad(diff, pad_fwd), torch.inf)
        bwd = torch.where(F.pad(both, pad_bwd) > 0, F.pad(diff, pad_bwd), torch.inf)
        g = torch.where(fwd.abs() <= bwd.abs(), fwd, bwd)
        return torch.where(torch.isfinite(g), g, torch.zeros_like(g))

    gx = along((0, 1), (1, 0), depth[..., 1:] - depth[..., :-1], covered[..., 1:] * covered[..., :-1])
    gy = along((0, 0, 0, 1), (0, 0, 1, 0), depth[..., 1:, :] - depth[..., :-1, :],
               covered[..., 1:, :] * covered[..., :-1, :])
    return gx, gy


def atrous_filter(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                  config: ATrousConfig = ATrousConfig(), compiled: bool = False) -> torch.Tensor:
    """Filter noisy AO guided by normals and depth (see the module docstring).

    Args:
        ao: AO in [0, 1] (few rays, noisy).
        mask: coverage; pixels > 0.5 count as covered.
        normal: view-space normals (normalized here).
        depth: view-space depth, any positive scale (only ratios matter).
        config: the filter's knobs.
        compiled: run the filter compiled by ``torch.compile`` (for GPUs; the first call of a
            process compiles).

    Returns:
        Filtered AO in [0, 1], 0 where not covered.

    Raises:
        ValueError: wrong shapes or dtypes, NaN or Inf in an input.

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W). Returns (B, 1, H, W).
    """
    _check(ao, mask, normal, depth)
    core = compiled_core() if compiled else _filter
    return core(ao, mask, normal, depth, config.iterations, config.sigma_normal, config.sigma_depth,
                config.depth_tolerance, config.sigma_value)


@functools.cache
def compiled_core():
    """The filter compiled by ``torch.compile``: eager, it launches some 2700 small kernels per
    frame, which a GPU shader would fuse; compiled, a few fused ones. Shapes are dynamic, so one
    compilation serves every image size (checked on the CPU: equal to eager within 1.2e-7)."""
    return torch.compile(_filter, dynamic=True)


def _filter(ao, mask, normal, depth, iterations: int, sigma_normal: float, sigma_depth: float,
            depth_tolerance: float, sigma_value: float | None) -> torch.Tensor:
    """:func:`atrous_filter` after its checks."""
    covered = (mask > 0.5).to(ao.dtype)
    deepest = (depth.abs() * covered).amax(dim=(1, 2, 3), keepdim=True)
    z = depth / torch.where(deepest > 0, deepest, torch.ones_like(deepest)) * covered
    gx, gy = depth_gradient(z, covered)
    n = F.normalize(normal, dim=1, eps=1e-6) * covered
    value = ao.clamp(0.0, 1.0) * covered
    for i in range(iterations):
        value = _pass(value, covered, n, z, gx, gy, 2 ** i, sigma_normal, sigma_depth, depth_tolerance, sigma_value)
    return value * covered


def _pass(value, covered, n, z, gx, gy, hole: int, sigma_normal: float, sigma_depth: float, depth_tolerance: float,
          sigma_value: float | None) -> torch.Tensor:
    """One a-trous pass with ``hole`` pixels between taps; out-of-image taps count as uncovered."""
    h, w = value.shape[-2:]
    pad = 2 * hole
    padded = [F.pad(t, (pad, pad, pad, pad)) for t in (value, covered, n, z)]
    # The tolerance per tap depends only on the offset's projection onto the gradient.
    base_tolerance = depth_tolerance * z.abs() + TINY
    total = torch.zeros_like(value)
    weight = torch.zeros_like(value)
    for a, ky in enumerate(B3):
        dy = (a - 2) * hole
        for b, kx in enumerate(B3):
            dx = (b - 2) * hole
            vq, cq, nq, zq = (t[..., pad + dy:pad + dy + h, pad + dx:pad + dx + w] for t in padded)
            wq = (ky * kx) * cq * (n * nq).sum(1, keepdim=True).clamp_min(0.0).pow(sigma_normal)
            tolerance = sigma_depth * (gx * dx + gy * dy).abs() + base_tolerance
            wq = wq * torch.exp(-(z - zq).abs() / tolerance)
            if sigma_value is not None:
                wq = wq * torch.exp(-(value - vq).abs() / sigma_value)
            total = total + wq * vq
            weight = weight + wq
    return torch.where(weight > 0, total / weight.clamp_min(TINY), torch.zeros_like(total))


class ATrousFilter(nn.Module):
    """:func:`atrous_filter` as a module (no parameters).

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W). Returns (B, 1, H, W).
    """

    def __init__(self, config: ATrousConfig = ATrousConfig(), compiled: bool = False):
        super().__init__()
        self.config, self.compiled = config, compiled

    def forward(self, ao, mask, normal, depth):
        return atrous_filter(ao, mask, normal, depth, self.config, self.compiled)
