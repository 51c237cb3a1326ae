"""The edge-avoiding a-trous AO filter: the non-learned reconstruction a network must beat.

Dammertz, Sewtz, Hanika and Lensch (2010), "Edge-Avoiding A-Trous Wavelet Transform for
fast Global Illumination Filtering", as SVGF (Schied et al. 2017) uses it: a 5x5 B3-spline
kernel applied ``iterations`` times with holes 1, 2, 4, 8, 16 between its taps, each tap
weighted by how alike the two pixels' surfaces are:

- normal: ``max(0, dot(n_p, n_q)) ** sigma_normal``;
- depth: ``exp(-|z_p - z_q| / (sigma_depth * |grad z_p . (q - p)| + depth_tolerance * z_p))``,
  the difference measured against the change the depth gradient predicts (so slanted planes
  blur along themselves), depth taken relative to the image's deepest covered pixel;
- optionally AO value: ``exp(-|ao_p - ao_q| / sigma_value)``; or, variance-guided as SVGF
  (:mod:`isosr_net.filters.svgf`), ``exp(-|ao_p - ao_q| / (sigma_variance * sqrt(g(var_p)) + VARIANCE_EPS))``
  with ``g`` a 3x3 Gaussian (1/4, 1/8, 1/16 taps) over the covered pixels, and each pass
  filtering the variance too, ``sum(w_q^2 var_q) / sum(w_q)^2``.

Only covered pixels (mask > 0.5) contribute and receive values; uncovered ones stay 0. The
center tap weighs ``(3/8)^2`` on a covered pixel (0 only where its normal is zero, or its
rounded self-dot below 1 raised to a huge ``sigma_normal`` underflows: then the pixel gets 0),
and the result is a convex combination of AO values: it stays in [0, 1] and finite.

As real-time ray tracers run it: Warp kernels, one thread per pixel, in float32 on every
device; one launch prepares the guides (normalized normal, relative depth, depth gradient,
:func:`prepare_guides`), then one launch per pass (:func:`atrous_passes`). The SVGF filter
reuses both and the tap weight (:func:`edge_exponent`).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Generator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
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
# Added to the variance-guided value tolerance (as SVGF's 1e-10), so that zero variance divides nothing by zero.
VARIANCE_EPS = 1e-10
VARIANCE_EPS_WP = wp.constant(VARIANCE_EPS)


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


@wp.func
def reprojected_texel(x: int, y: int, u: float, v: float, h: int, w: int):
    """Where pixel (x, y) moved by the flow (u, v) lands among an h x w image's texels: the top-left
    texel (x0, y0) of the 2x2 around it and the bilinear fractions (fx, fy); kept within a texel of
    the image (beyond, no tap is inside) so that the indices fit an int."""
    sx = wp.clamp(float(x) + u, -2.0, float(w) + 1.0)
    sy = wp.clamp(float(y) + v, -2.0, float(h) + 1.0)
    x0 = int(wp.floor(sx))
    y0 = int(wp.floor(sy))
    return x0, y0, sx - float(x0), sy - float(y0)


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


@wp.func
def edge_exponent(sp: wp.vec4, sq: wp.vec4, g: wp.vec2, dx: int, dy: int, base_tolerance: float,
                  sigma_normal: float, sigma_depth: float) -> float:
    """The log of the normal and depth weights of the tap ``q`` at offset (dx, dy) from ``p`` (module
    docstring), from their ``surface`` guides and ``p``'s depth gradient ``g``."""
    cosine = sp[0] * sq[0] + sp[1] * sq[1] + sp[2] * sq[2]
    tolerance = sigma_depth * wp.abs(g[0] * float(dx) + g[1] * float(dy)) + base_tolerance
    return normal_log_weight(cosine, sigma_normal) - wp.abs(sp[3] - sq[3]) / tolerance


@wp.func
def blurred_variance(variance: wp.array3d(dtype=float), covered: wp.array3d(dtype=float), b: int, y: int,
                     x: int) -> float:
    """The 3x3 Gaussian of ``variance`` over the covered pixels around a covered one."""
    h = variance.shape[1]
    w = variance.shape[2]
    total = float(0.0)
    weight = float(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            qy = y + dy
            qx = x + dx
            if qy >= 0 and qy < h and qx >= 0 and qx < w:
                if covered[b, qy, qx] != 0.0:
                    k = b3_tap(dy + 2) * b3_tap(dx + 2)  # 3/8, 1/4 taps: the same shape as 1/4, 1/8
                    total = total + k * variance[b, qy, qx]
                    weight = weight + k
    return total / wp.max(weight, TINY_WP)


@wp.kernel
def atrous_pass_kernel(value: wp.array3d(dtype=float), surface: wp.array3d(dtype=wp.vec4),
                       slope: wp.array3d(dtype=wp.vec2), covered: wp.array3d(dtype=float), hole: int,
                       sigma_normal: float, sigma_depth: float, depth_tolerance: float,
                       inverse_sigma_value: float, variance: wp.array3d(dtype=float), sigma_variance: float,
                       out: wp.array3d(dtype=float), variance_out: wp.array3d(dtype=float), row0: int):
    """One a-trous pass over rows ``row0`` on, ``hole`` pixels between taps; out-of-image taps count
    as uncovered. With ``sigma_variance`` > 0 the value weight follows ``variance`` (SVGF) and the
    pass writes the filtered variance to ``variance_out``; else both arrays are not read."""
    b, row, x = wp.tid()
    y = row0 + row
    guided = sigma_variance > 0.0
    if covered[b, y, x] == 0.0:
        out[b, y, x] = 0.0
        if guided:
            variance_out[b, y, x] = 0.0
        return
    h = value.shape[1]
    w = value.shape[2]
    sp = surface[b, y, x]
    g = slope[b, y, x]
    vp = value[b, y, x]
    inverse_value = inverse_sigma_value
    if guided:
        inverse_value = 1.0 / (sigma_variance * wp.sqrt(blurred_variance(variance, covered, b, y, x))
                               + VARIANCE_EPS_WP)
    # The tolerance per tap depends only on the offset's projection onto the gradient.
    base_tolerance = depth_tolerance * wp.abs(sp[3]) + TINY_WP
    total = float(0.0)
    weight = float(0.0)
    total_variance = float(0.0)
    for a in range(5):
        dy = (a - 2) * hole
        qy = y + dy
        for c in range(5):
            dx = (c - 2) * hole
            qx = x + dx
            if qy >= 0 and qy < h and qx >= 0 and qx < w:
                if covered[b, qy, qx] != 0.0:
                    vq = value[b, qy, qx]
                    # The weights as one exponential (one exp and one log per tap, not four).
                    exponent = edge_exponent(sp, surface[b, qy, qx], g, dx, dy, base_tolerance, sigma_normal,
                                             sigma_depth) - wp.abs(vp - vq) * inverse_value
                    wq = b3_tap(a) * b3_tap(c) * wp.exp(exponent)
                    total = total + wq * vq
                    weight = weight + wq
                    if guided:
                        total_variance = total_variance + wq * wq * variance[b, qy, qx]
    result = float(0.0)
    filtered_variance = float(0.0)
    if weight > 0.0:
        result = total / wp.max(weight, TINY_WP)
        filtered_variance = total_variance / wp.max(weight * weight, TINY_WP)
    out[b, y, x] = result
    if guided:
        variance_out[b, y, x] = filtered_variance


def check_buffers(where: str, ao: torch.Tensor, guides: dict[str, tuple[torch.Tensor, int]],
                  finite: bool = True) -> None:
    """ValueError unless ``ao`` is (B, 1, H, W) and each guide ``name: (tensor, channels)`` is
    (B, channels, H, W), all floating point, on ``ao``'s device, and (``finite``, one host sync)
    finite (``where`` names the caller)."""
    if ao.ndim != 4 or ao.shape[1] != 1:
        raise ValueError(f"{where}: ao must be (B, 1, H, W), got {tuple(ao.shape)}")
    b, _, h, w = ao.shape
    if not b * h * w:
        raise ValueError(f"{where}: the images are empty, ao is {tuple(ao.shape)}")
    for name, (t, c) in guides.items():
        if tuple(t.shape) != (b, c, h, w):
            raise ValueError(f"{where}: {name} must be {(b, c, h, w)}, got {tuple(t.shape)}")
    named = {"ao": ao, **{name: t for name, (t, _) in guides.items()}}
    for name, t in named.items():
        if not t.is_floating_point():
            raise ValueError(f"{where}: {name} must be floating point, got {t.dtype}")
        if t.device != ao.device:
            raise ValueError(f"{where}: {name} is on {t.device}, ao on {ao.device}")
    if not finite:
        return
    # One host sync for all the buffers.
    ok_values = torch.stack([torch.isfinite(t).all() for t in named.values()]).tolist()
    for name, ok in zip(named, ok_values):
        if not ok:
            raise ValueError(f"{where}: {name} holds NaN or Inf values")


def float32_knob(value: float) -> float:
    """A knob clamped into float32's range (so the kernels never see inf)."""
    return min(float(value), FLOAT32_MAX)


@dataclass
class Guides:
    """What :func:`prepare_guides` makes, on the inputs' device (float32; 0 where not covered).

    Shape:
        value, covered: (B, H, W). surface: (B, H, W, 4), unit normal and relative depth. slope: (B, H, W, 2).
    """

    value: torch.Tensor
    surface: torch.Tensor
    slope: torch.Tensor
    covered: torch.Tensor

    def arrays(self) -> list[wp.array]:
        """value, surface, slope, covered as the kernels take them (no copies)."""
        return [wp.from_torch(self.value), wp.from_torch(self.surface, dtype=wp.vec4),
                wp.from_torch(self.slope, dtype=wp.vec2), wp.from_torch(self.covered)]


def prepare_guides(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor) -> Guides:
    """The clamped AO and the filter's guides (module docstring), after no checks (callers check).

    Shape:
        ao, mask, depth: (B, 1, H, W). normal: (B, 3, H, W).
    """
    b, _, h, w = ao.shape
    # Relative depth in the inputs' dtype first, so float64 depths beyond float32's range stay finite.
    deepest = torch.where(mask > 0.5, depth.abs(), 0).amax(dim=(1, 2, 3), keepdim=True)
    z = (depth / torch.where(deepest > 0, deepest, 1)).float()
    wp.init()  # a no-op after the first call
    sources = [wp.from_torch(t.float()) for t in (ao, mask, normal, z)]  # no copies where float32 already
    new = functools.partial(torch.empty, dtype=torch.float32, device=ao.device)
    guides = Guides(new((b, h, w)), new((b, h, w, 4)), new((b, h, w, 2)), new((b, h, w)))
    with on_device(ao.device) as launch:
        launch(atrous_prepare_kernel, (b, h, w), [*sources, *guides.arrays()])
    return guides


def atrous_passes(value: torch.Tensor, guides: Guides, config: ATrousConfig, variance: torch.Tensor | None = None,
                  sigma_variance: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The filter's passes over ``value`` (module docstring), variance-guided where ``variance`` is given.

    Returns:
        The last pass's output and the first's (SVGF keeps that one as its history).

    Shape:
        value, variance: (B, H, W), float32 on the guides' device. Returns two (B, H, W).
    """
    b, h, w = value.shape
    new = functools.partial(torch.empty, dtype=torch.float32, device=value.device)
    first, spare = new((b, h, w)), (new((b, h, w)), new((b, h, w)))
    guided = variance is not None
    if guided:  # the input variance, then each pass's output, ping-ponged
        variance_in, variance_outs = wp.from_torch(variance), [wp.from_torch(new((b, h, w))) for _ in range(2)]
    else:  # unguided passes read and write no variance: a 1-element stand-in
        variance_in = wp.from_torch(new((1, 1, 1)))
        variance_outs = [variance_in] * 2
    _, surface, slope, covered = guides.arrays()
    # No value weight: its exponent is 0.
    inverse_sigma_value = 0.0 if config.sigma_value is None else float32_knob(1 / config.sigma_value)
    knobs = [float32_knob(config.sigma_normal), float32_knob(config.sigma_depth),
             float32_knob(config.depth_tolerance), inverse_sigma_value]
    sigma = float32_knob(sigma_variance) if guided else 0.0
    source, out = value, value
    with on_device(value.device) as launch:
        for i in range(config.iterations):
            out = first if i == 0 else spare[i % 2]
            launch(atrous_pass_kernel, (b, h, w), [wp.from_torch(source), surface, slope, covered, 2 ** i, *knobs,
                                                   variance_in, sigma, wp.from_torch(out), variance_outs[i % 2]])
            source, variance_in = out, variance_outs[i % 2]
    return out, first


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
    check_buffers("atrous_filter", ao, {"mask": (mask, 1), "normal": (normal, 3), "depth": (depth, 1)})
    guides = prepare_guides(ao, mask, normal, depth)
    return atrous_passes(guides.value, guides, config)[0][:, None].to(ao.dtype)


@contextmanager
def on_device(device: torch.device) -> Generator[Callable[[wp.Kernel, tuple[int, int, int], list], None]]:
    """``launch(kernel, (B, H, W), inputs)`` for the kernels of this filter, SVGF's and the ray
    history's, which take the first row ``row0`` last: on GPUs one launch on torch's current stream
    (no event between streams: a CUDA graph may capture it), on CPUs row bands on a thread pool
    (Warp's CPU kernels run on one thread each; ctypes releases the GIL)."""
    wp_device = wp.device_from_torch(device)
    if wp_device.is_cuda:
        stream = wp.stream_from_torch(torch.cuda.current_stream(device))
        yield lambda kernel, shape, inputs: _launch_whole(kernel, shape, inputs, wp_device, stream)
    else:
        yield lambda kernel, shape, inputs: _launch_in_row_bands(kernel, shape, inputs, wp_device)


def _launch_whole(kernel, shape: tuple[int, int, int], inputs: list, device, stream: wp.Stream | None = None) -> None:
    """One launch over every pixel (GPUs: on ``stream``)."""
    wp.launch(kernel, dim=shape, inputs=[*inputs, 0], device=device, stream=stream)


def _launch_in_row_bands(kernel, shape: tuple[int, int, int], inputs: list, device) -> None:
    """Launches over row bands on a thread pool, returning when all are done."""
    b, h, w = shape
    bands = min(h, 2 * CPU_THREADS)
    starts = [h * i // bands for i in range(bands + 1)]
    jobs = [(starts[i], starts[i + 1] - starts[i]) for i in range(bands)]
    def launch(job: tuple[int, int]) -> None:
        row0, rows = job
        wp.launch(kernel, dim=(b, rows, w), inputs=[*inputs, row0], device=device)

    list(_cpu_pool(kernel.module).map(launch, jobs))


_LOADED: set[str] = set()


def _cpu_pool(module: wp.context.Module) -> ThreadPoolExecutor:
    """The CPU launches' threads, one per core, once ``module`` is loaded (Warp's module load is not
    for concurrent first calls)."""
    if module.name not in _LOADED:
        wp.load_module(module, device="cpu")
        _LOADED.add(module.name)
    return _pool()


@functools.cache
def _pool() -> ThreadPoolExecutor:
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
