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
center tap weighs ``(3/8)^2`` on a covered pixel (0 only where its normal is zero, or its
rounded self-dot below 1 raised to a huge ``sigma_normal`` underflows: then the pixel gets 0),
and the result is a convex combination of AO values: it stays in [0, 1] and finite.

As real-time ray tracers run it: Warp kernels, one thread per pixel, in float32 on every
device; one launch prepares the guides (normalized normal, relative depth, depth gradient),
then one launch per pass ping-pongs two AO buffers.
"""

from __future__ import annotations

import functools
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import torch
import warp as wp
from torch import nn

wp.set_module_options({"enable_backward": False})  # no gradients through the filter

# The B3-spline's taps.
B3 = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)
# Floor of the depth tolerance, so equal depths weigh 1 and nothing divides by zero.
TINY = 1e-12
MAX_ITERATIONS = 5
CPU_THREADS = os.cpu_count() or 1
# The float32 range the kernels compute in: knobs are clamped into it.
FLOAT32_MAX = 3.4028234663852886e38
# Smallest normal length that normalizing divides by (as ``F.normalize``'s eps).
NORMAL_EPS = wp.constant(1e-6)
TINY_WP = wp.constant(TINY)


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


@wp.func
def b3_tap(i: int) -> float:
    """The B3-spline's tap ``i`` in 0..4."""
    if i == 2:
        return 0.375
    if i == 1 or i == 3:
        return 0.25
    return 0.0625


@wp.func
def depth_step(mask: wp.array4d(dtype=float), z: wp.array4d(dtype=float), b: int, y: int, x: int, dy: int,
               dx: int) -> float:
    """Depth change per pixel step along (dy, dx) at a covered pixel: of the forward and backward
    differences to covered neighbors the smaller in magnitude (the forward one on a tie), so
    silhouettes do not count; 0 where neither neighbor is covered."""
    h = z.shape[2]
    w = z.shape[3]
    zp = z[b, 0, y, x]
    fy = y + dy
    fx = x + dx
    by = y - dy
    bx = x - dx
    # Nested ifs: Warp evaluates every operand of ``and``, so bounds come before reads.
    has_fwd = False
    has_bwd = False
    fwd = float(0.0)
    bwd = float(0.0)
    if fy < h and fx < w:
        if mask[b, 0, fy, fx] > 0.5:
            has_fwd = True
            fwd = z[b, 0, fy, fx] - zp
    if by >= 0 and bx >= 0:
        if mask[b, 0, by, bx] > 0.5:
            has_bwd = True
            bwd = zp - z[b, 0, by, bx]
    if has_fwd and (not has_bwd or wp.abs(fwd) <= wp.abs(bwd)):
        return fwd
    return bwd


@wp.kernel
def atrous_prepare_kernel(ao: wp.array4d(dtype=float), mask: wp.array4d(dtype=float),
                          normal: wp.array4d(dtype=float), z: wp.array4d(dtype=float),
                          value: wp.array3d(dtype=float), surface: wp.array3d(dtype=wp.vec4),
                          slope: wp.array3d(dtype=wp.vec2), covered: wp.array3d(dtype=float), row0: int):
    """Per pixel of rows ``row0`` on: clamped AO, unit normal and relative depth (``surface``),
    depth gradient (``slope``, x right and y down) and coverage; all 0 where not covered."""
    b, row, x = wp.tid()
    y = row0 + row
    if mask[b, 0, y, x] <= 0.5:
        value[b, y, x] = 0.0
        surface[b, y, x] = wp.vec4(0.0)
        slope[b, y, x] = wp.vec2(0.0)
        covered[b, y, x] = 0.0
        return
    n = wp.vec3(normal[b, 0, y, x], normal[b, 1, y, x], normal[b, 2, y, x])
    n = n / wp.max(wp.length(n), NORMAL_EPS)
    value[b, y, x] = wp.clamp(ao[b, 0, y, x], 0.0, 1.0)
    surface[b, y, x] = wp.vec4(n[0], n[1], n[2], z[b, 0, y, x])
    slope[b, y, x] = wp.vec2(depth_step(mask, z, b, y, x, 0, 1), depth_step(mask, z, b, y, x, 1, 0))
    covered[b, y, x] = 1.0


@wp.func
def normal_log_weight(cosine: float, sigma_normal: float) -> float:
    """``log(max(0, cosine) ** sigma_normal)`` with ``0 ** 0 = 1``; the cosine clamped to 1 too (a unit
    normal's rounded self-dot may exceed 1)."""
    if sigma_normal == 0.0:
        return 0.0
    if cosine <= 0.0:
        return -wp.inf
    return sigma_normal * wp.log(wp.min(cosine, 1.0))


@wp.kernel
def atrous_pass_kernel(value: wp.array3d(dtype=float), surface: wp.array3d(dtype=wp.vec4),
                       slope: wp.array3d(dtype=wp.vec2), covered: wp.array3d(dtype=float), hole: int,
                       sigma_normal: float, sigma_depth: float, depth_tolerance: float,
                       inverse_sigma_value: float, out: wp.array3d(dtype=float), row0: int):
    """One a-trous pass over rows ``row0`` on, ``hole`` pixels between taps; out-of-image taps count
    as uncovered."""
    b, row, x = wp.tid()
    y = row0 + row
    if covered[b, y, x] == 0.0:
        out[b, y, x] = 0.0
        return
    h = value.shape[1]
    w = value.shape[2]
    sp = surface[b, y, x]
    g = slope[b, y, x]
    vp = value[b, y, x]
    # The tolerance per tap depends only on the offset's projection onto the gradient.
    base_tolerance = depth_tolerance * wp.abs(sp[3]) + TINY_WP
    total = float(0.0)
    weight = float(0.0)
    for a in range(5):
        dy = (a - 2) * hole
        qy = y + dy
        for c in range(5):
            dx = (c - 2) * hole
            qx = x + dx
            if qy >= 0 and qy < h and qx >= 0 and qx < w:
                if covered[b, qy, qx] != 0.0:
                    sq = surface[b, qy, qx]
                    vq = value[b, qy, qx]
                    # The three weights as one exponential (one exp and one log per tap, not four).
                    cosine = sp[0] * sq[0] + sp[1] * sq[1] + sp[2] * sq[2]
                    tolerance = sigma_depth * wp.abs(g[0] * float(dx) + g[1] * float(dy)) + base_tolerance
                    exponent = normal_log_weight(cosine, sigma_normal) - wp.abs(sp[3] - sq[3]) / tolerance \
                        - wp.abs(vp - vq) * inverse_sigma_value
                    wq = b3_tap(a) * b3_tap(c) * wp.exp(exponent)
                    total = total + wq * vq
                    weight = weight + wq
    result = float(0.0)
    if weight > 0.0:
        result = total / wp.max(weight, TINY_WP)
    out[b, y, x] = result


def _check(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor) -> None:
    if ao.ndim != 4 or ao.shape[1] != 1:
        raise ValueError(f"atrous_filter: ao must be (B, 1, H, W), got {tuple(ao.shape)}")
    b, _, h, w = ao.shape
    if not b * h * w:
        raise ValueError(f"atrous_filter: the images are empty, ao is {tuple(ao.shape)}")
    for name, t, c in (("mask", mask, 1), ("normal", normal, 3), ("depth", depth, 1)):
        if tuple(t.shape) != (b, c, h, w):
            raise ValueError(f"atrous_filter: {name} must be {(b, c, h, w)}, got {tuple(t.shape)}")
    for name, t in (("ao", ao), ("mask", mask), ("normal", normal), ("depth", depth)):
        if not t.is_floating_point():
            raise ValueError(f"atrous_filter: {name} must be floating point, got {t.dtype}")
        if t.device != ao.device:
            raise ValueError(f"atrous_filter: {name} is on {t.device}, ao on {ao.device}")
    # One host sync for all four buffers.
    finite = torch.stack([torch.isfinite(t).all() for t in (ao, mask, normal, depth)]).tolist()
    for name, ok in zip(("ao", "mask", "normal", "depth"), finite):
        if not ok:
            raise ValueError(f"atrous_filter: {name} holds NaN or Inf values")


def _float32(value: float) -> float:
    """A knob clamped into float32's range (so the kernels never see inf)."""
    return min(float(value), FLOAT32_MAX)


def atrous_filter(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                  config: ATrousConfig = ATrousConfig()) -> torch.Tensor:
    """Filter noisy AO guided by normals and depth (see the module docstring).

    Runs on the inputs' device (CPU or CUDA, on torch's current stream), in float32.

    Args:
        ao: AO in [0, 1] (few rays, noisy).
        mask: coverage; pixels > 0.5 count as covered.
        normal: view-space normals (normalized here).
        depth: view-space depth, any positive scale (only ratios matter).
        config: the filter's knobs (clamped into float32's range).

    Returns:
        Filtered AO in [0, 1] in ``ao``'s dtype, 0 where not covered.

    Raises:
        ValueError: wrong shapes, dtypes or devices, NaN or Inf in an input.

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W). Returns (B, 1, H, W).
    """
    _check(ao, mask, normal, depth)
    b, _, h, w = ao.shape
    # Relative depth in the inputs' dtype first, so float64 depths beyond float32's range stay finite.
    deepest = torch.where(mask > 0.5, depth.abs(), 0).amax(dim=(1, 2, 3), keepdim=True)
    z = (depth / torch.where(deepest > 0, deepest, 1)).float()
    wp.init()  # a no-op after the first call
    device = wp.device_from_torch(ao.device)
    sources = [wp.from_torch(t.float()) for t in (ao, mask, normal, z)]  # no copies where float32 already
    # The AO ping-pong pair stays in torch, so the result needs no conversion back.
    values = [torch.empty((b, h, w), dtype=torch.float32, device=ao.device) for _ in range(2)]
    value, spare = (wp.from_torch(t) for t in values)
    covered = wp.from_torch(torch.empty((b, h, w), dtype=torch.float32, device=ao.device))
    surface = wp.from_torch(torch.empty((b, h, w, 4), dtype=torch.float32, device=ao.device), dtype=wp.vec4)
    slope = wp.from_torch(torch.empty((b, h, w, 2), dtype=torch.float32, device=ao.device), dtype=wp.vec2)
    # No value weight: its exponent is 0.
    inverse_sigma_value = 0.0 if config.sigma_value is None else _float32(1 / config.sigma_value)
    knobs = [_float32(config.sigma_normal), _float32(config.sigma_depth), _float32(config.depth_tolerance),
             inverse_sigma_value]
    if device.is_cuda:
        launch, stream = _launch_whole, wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(ao.device)))
    else:
        launch, stream = _launch_in_row_bands, nullcontext()
    with stream:
        launch(atrous_prepare_kernel, (b, h, w), [*sources, value, surface, slope, covered], device)
        for i in range(config.iterations):
            launch(atrous_pass_kernel, (b, h, w), [value, surface, slope, covered, 2 ** i, *knobs, spare], device)
            value, spare = spare, value
    return values[config.iterations % 2][:, None].to(ao.dtype)


def _launch_whole(kernel, shape: tuple[int, int, int], inputs: list, device) -> None:
    """One launch over every pixel (GPUs)."""
    wp.launch(kernel, dim=shape, inputs=[*inputs, 0], device=device)


def _launch_in_row_bands(kernel, shape: tuple[int, int, int], inputs: list, device) -> None:
    """Launches over row bands on a thread pool, returning when all are done (Warp's CPU kernels run
    on one thread each; ctypes releases the GIL)."""
    b, h, w = shape
    bands = min(h, 2 * CPU_THREADS)
    starts = [h * i // bands for i in range(bands + 1)]
    jobs = [(starts[i], starts[i + 1] - starts[i]) for i in range(bands)]
    def launch(job: tuple[int, int]) -> None:
        row0, rows = job
        wp.launch(kernel, dim=(b, rows, w), inputs=[*inputs, row0], device=device)

    list(_cpu_pool().map(launch, jobs))


@functools.cache
def _cpu_pool() -> ThreadPoolExecutor:
    """The CPU launches' threads, one per core; the module is loaded first (Warp's module load is
    not for concurrent first calls)."""
    wp.load_module(sys.modules[__name__], device="cpu")
    return ThreadPoolExecutor(CPU_THREADS)


class ATrousFilter(nn.Module):
    """:func:`atrous_filter` as a module (no parameters).

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W). Returns (B, 1, H, W).
    """

    def __init__(self, config: ATrousConfig = ATrousConfig()):
        super().__init__()
        self.config = config

    def forward(self, ao, mask, normal, depth):
        return atrous_filter(ao, mask, normal, depth, self.config)
