"""The SVGF-style temporal AO filter: the few rays of many frames, reprojected along the flow.

Schied et al. (2017), "Spatiotemporal Variance-Guided Filtering", on this project's AO (the
demodulated signal: color is AO times the AO-free shading). Per frame:

1. Guides as the a-trous filter's (:func:`isosr_net.filters.atrous.prepare_guides`).
2. Reprojection and blend (one kernel): a covered pixel ``p`` looks up the previous frame's
   history at ``p + flow[p]`` (bilinear: the 4 texels around it). A texel counts only if it
   lies in the image and was covered, its depth matches the depth the pixel's world point
   ``P`` has in the previous view, ``-dot(P - eye_prev, back_prev)``, within
   ``depth_tolerance`` of it plus the depth change the pixel's gradient predicts over the
   texel's offset, and its normal is within ``normal_cosine`` of the pixel's (view-space
   normals: the threshold must allow one frame's camera turn). The counted texels' bilinear
   weights, renormalized, average the history's AO, moments (AO, AO^2) and length; where they
   sum to less than ``MIN_HISTORY_WEIGHT`` the pixel is disoccluded and its history restarts.
   History length ``n`` = previous length + 1 (1 on a restart), capped at ``MAX_HISTORY``; AO
   and moments blend in the new sample by ``max(alpha, 1/n)`` (a plain mean while the history
   is short). The AO's variance is ``max(0, m2 - m1^2)`` of the moments once ``n`` reaches
   ``min_history`` (SVGF: 4); before, the spatial estimate: the moments of this frame's samples
   over a (2 radius + 1)^2 window weighted by the a-trous normal and depth weights
   (:func:`isosr_net.filters.atrous.edge_exponent`), times ``min_history / n``.
3. The variance-guided a-trous filter (:func:`isosr_net.filters.atrous.atrous_passes`, luminance weight
   ``sigma_variance``); its first pass's output is the next frame's history AO (as SVGF).

A frame without a previous camera, or a history of another size, starts every pixel anew.
Uncovered pixels get AO 0 and no history. Warp kernels in float32 on every device.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import warp as wp

from isosr_render import Camera
from isosr_net.filters.atrous import (TINY_WP, ATrousConfig, Guides, atrous_passes, check_buffers, depth_step, edge_exponent,
                              float32_knob, on_device, prepare_guides, reprojected_texel)

wp.set_module_options({"enable_backward": False})  # no gradients through the filter

# A history length cap (its blend weight is alpha long before), so that lengths stay small numbers.
MAX_HISTORY = 1024
# Reprojected texels whose bilinear weights sum to less than this are a disocclusion (SVGF: 0.01).
MIN_HISTORY_WEIGHT = 0.01
MAX_RADIUS = 5
MAX_HISTORY_WP = wp.constant(float(MAX_HISTORY))
MIN_HISTORY_WEIGHT_WP = wp.constant(MIN_HISTORY_WEIGHT)


@dataclass(frozen=True)
class SVGFConfig:
    """The temporal part's knobs (SVGF's defaults); the a-trous part takes an `ATrousConfig`.

    Attributes:
        alpha: the new frame's weight in the AO blend once the history is long (1/alpha frames).
        moments_alpha: the same for the moments.
        depth_tolerance: reprojected depths may differ by this fraction of the expected depth.
        normal_cosine: reprojected normals must have at least this cosine with the pixel's.
        min_history: frames of history from which the temporal variance is used.
        radius: the spatial variance's window radius (pixels).
        sigma_variance: the a-trous value weight's tolerance in standard deviations.
    """

    alpha: float = 0.2
    moments_alpha: float = 0.2
    depth_tolerance: float = 0.01
    normal_cosine: float = 0.9
    min_history: int = 4
    radius: int = 3
    sigma_variance: float = 4.0

    def __post_init__(self):
        for name in ("alpha", "moments_alpha"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value <= 1):
                raise ValueError(f"SVGFConfig.{name} must be in (0, 1], got {value!r}")
        if not (isinstance(self.depth_tolerance, (int, float)) and 0 <= self.depth_tolerance < float("inf")):
            raise ValueError(f"SVGFConfig.depth_tolerance must be a finite number >= 0, got {self.depth_tolerance!r}")
        if not (isinstance(self.normal_cosine, (int, float)) and -1 <= self.normal_cosine <= 1):
            raise ValueError(f"SVGFConfig.normal_cosine must be in [-1, 1], got {self.normal_cosine!r}")
        if not (isinstance(self.min_history, int) and 1 <= self.min_history <= MAX_HISTORY):
            raise ValueError(f"SVGFConfig.min_history must be an integer in [1, {MAX_HISTORY}], "
                             f"got {self.min_history!r}")
        if not (isinstance(self.radius, int) and 0 <= self.radius <= MAX_RADIUS):
            raise ValueError(f"SVGFConfig.radius must be an integer in [0, {MAX_RADIUS}], got {self.radius!r}")
        if not (isinstance(self.sigma_variance, (int, float)) and 0 < self.sigma_variance < float("inf")):
            raise ValueError(f"SVGFConfig.sigma_variance must be positive and finite, got {self.sigma_variance!r}")


@dataclass
class SVGFHistory:
    """One stream's history after a frame (float32, on the frame's device; 0 where not covered).

    Shape:
        ao, length: (B, H, W). moments: (B, H, W, 2), AO and AO^2. surface: (B, H, W, 4), unit
        view-space normal and depth (world units).
    """

    ao: torch.Tensor
    moments: torch.Tensor
    length: torch.Tensor
    surface: torch.Tensor


@wp.struct
class Previous:
    """The previous frame's history as the kernel reads it, and its camera."""

    ao: wp.array3d(dtype=float)
    moments: wp.array3d(dtype=wp.vec2)
    length: wp.array3d(dtype=float)
    surface: wp.array3d(dtype=wp.vec4)
    present: int  # 0: no history (every pixel starts anew); the arrays are 1-element stand-ins
    eye: wp.vec3
    back: wp.vec3


@wp.struct
class Knobs:
    """:class:`SVGFConfig` and the a-trous weights the spatial variance uses, as the kernel reads them."""

    alpha: float
    moments_alpha: float
    depth_tolerance: float
    normal_cosine: float
    min_history: float
    radius: int
    sigma_normal: float
    sigma_depth: float
    edge_depth_tolerance: float


@wp.func
def reprojection_weight(prev: Previous, b: int, qy: int, qx: int, w: float, n: wp.vec3, expected: float,
                        allowance: float, knobs: Knobs) -> float:
    """The bilinear weight ``w`` of history texel (qy, qx), or 0 where it does not count (module docstring)."""
    if w <= 0.0 or qy < 0 or qy >= prev.length.shape[1] or qx < 0 or qx >= prev.length.shape[2]:
        return 0.0
    if prev.length[b, qy, qx] <= 0.0:
        return 0.0
    s = prev.surface[b, qy, qx]
    if wp.abs(s[3] - expected) > knobs.depth_tolerance * expected + allowance:
        return 0.0
    if n[0] * s[0] + n[1] * s[1] + n[2] * s[2] < knobs.normal_cosine:
        return 0.0
    return w


@wp.func
def spatial_variance(value: wp.array3d(dtype=float), surface: wp.array3d(dtype=wp.vec4),
                     slope: wp.array3d(dtype=wp.vec2), covered: wp.array3d(dtype=float), b: int, y: int, x: int,
                     knobs: Knobs) -> float:
    """The variance of this frame's samples around a covered pixel, weighted by the a-trous weights."""
    h = value.shape[1]
    w = value.shape[2]
    sp = surface[b, y, x]
    g = slope[b, y, x]
    base_tolerance = knobs.edge_depth_tolerance * wp.abs(sp[3]) + TINY_WP
    weight = float(0.0)
    m1 = float(0.0)
    m2 = float(0.0)
    for dy in range(-knobs.radius, knobs.radius + 1):
        for dx in range(-knobs.radius, knobs.radius + 1):
            qy = y + dy
            qx = x + dx
            if qy >= 0 and qy < h and qx >= 0 and qx < w:
                if covered[b, qy, qx] != 0.0:
                    wq = wp.exp(edge_exponent(sp, surface[b, qy, qx], g, dx, dy, base_tolerance, knobs.sigma_normal,
                                              knobs.sigma_depth))
                    v = value[b, qy, qx]
                    weight = weight + wq
                    m1 = m1 + wq * v
                    m2 = m2 + wq * v * v
    if weight <= 0.0:
        return 0.0
    m1 = m1 / weight
    return wp.max(m2 / weight - m1 * m1, 0.0)


@wp.kernel
def svgf_temporal_kernel(value: wp.array3d(dtype=float), surface: wp.array3d(dtype=wp.vec4),
                         slope: wp.array3d(dtype=wp.vec2), covered: wp.array3d(dtype=float),
                         mask: wp.array4d(dtype=float), depth: wp.array4d(dtype=float),
                         position: wp.array4d(dtype=float), flow: wp.array4d(dtype=float), prev: Previous,
                         knobs: Knobs, ao_out: wp.array3d(dtype=float), moments_out: wp.array3d(dtype=wp.vec2),
                         length_out: wp.array3d(dtype=float), surface_out: wp.array3d(dtype=wp.vec4),
                         variance_out: wp.array3d(dtype=float), row0: int):
    """Step 2 of the module docstring for the pixels of rows ``row0`` on."""
    b, row, x = wp.tid()
    y = row0 + row
    if covered[b, y, x] == 0.0:
        ao_out[b, y, x] = 0.0
        moments_out[b, y, x] = wp.vec2(0.0)
        length_out[b, y, x] = 0.0
        surface_out[b, y, x] = wp.vec4(0.0)
        variance_out[b, y, x] = 0.0
        return
    sp = surface[b, y, x]
    n = wp.vec3(sp[0], sp[1], sp[2])
    z = depth[b, 0, y, x]
    sample = value[b, y, x]
    total = float(0.0)
    ao = float(0.0)
    moments = wp.vec2(0.0)
    length = float(0.0)
    if prev.present != 0:
        p = wp.vec3(position[b, 0, y, x], position[b, 1, y, x], position[b, 2, y, x])
        expected = -wp.dot(p - prev.eye, prev.back)
        if expected > 0.0:
            x0, y0, fx, fy = reprojected_texel(x, y, flow[b, 0, y, x], flow[b, 1, y, x], prev.length.shape[1],
                                               prev.length.shape[2])
            gx = depth_step(mask, depth, b, y, x, 0, 1)
            gy = depth_step(mask, depth, b, y, x, 1, 0)
            for j in range(2):
                for i in range(2):
                    qx = x0 + i
                    qy = y0 + j
                    w = wp.where(i == 1, fx, 1.0 - fx) * wp.where(j == 1, fy, 1.0 - fy)
                    allowance = wp.abs(gx * (float(i) - fx)) + wp.abs(gy * (float(j) - fy))  # |q - (p + flow)|
                    w = reprojection_weight(prev, b, qy, qx, w, n, expected, allowance, knobs)
                    if w > 0.0:
                        total = total + w
                        ao = ao + w * prev.ao[b, qy, qx]
                        moments = moments + w * prev.moments[b, qy, qx]
                        length = length + w * prev.length[b, qy, qx]
    if total >= MIN_HISTORY_WEIGHT_WP:
        ao = ao / total
        moments = moments / total
        length = wp.min(length / total + 1.0, MAX_HISTORY_WP)
    else:
        ao = 0.0
        moments = wp.vec2(0.0)
        length = 1.0
    alpha = wp.max(knobs.alpha, 1.0 / length)
    moments_alpha = wp.max(knobs.moments_alpha, 1.0 / length)
    ao = ao + alpha * (sample - ao)
    moments = moments + moments_alpha * (wp.vec2(sample, sample * sample) - moments)
    variance = wp.max(moments[1] - moments[0] * moments[0], 0.0)
    if length < knobs.min_history:
        variance = spatial_variance(value, surface, slope, covered, b, y, x, knobs) * knobs.min_history / length
    ao_out[b, y, x] = ao
    moments_out[b, y, x] = moments
    length_out[b, y, x] = length
    surface_out[b, y, x] = wp.vec4(n[0], n[1], n[2], z)
    variance_out[b, y, x] = variance


def svgf_filter(ao: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor,
                position: torch.Tensor, flow: torch.Tensor | None, prev_camera: Camera | None,
                history: SVGFHistory | None, config: SVGFConfig = SVGFConfig(),
                atrous: ATrousConfig = ATrousConfig()) -> tuple[torch.Tensor, SVGFHistory]:
    """One frame of the temporal filter (module docstring).

    Runs on the inputs' device (CPU or CUDA, on torch's current stream), in float32.

    Args:
        ao: this frame's AO in [0, 1] (few rays, noisy).
        mask: coverage; pixels > 0.5 count as covered.
        normal: view-space normals (normalized here).
        depth: view-space depth, world units.
        position: world-space hit points.
        flow: backward flow to the previous frame, pixels (conventions); None: no previous frame.
        prev_camera: the previous frame's camera; None: no previous frame.
        history: the previous frame's history (None: none).
        config: the temporal knobs.
        atrous: the a-trous filter's knobs.

    Returns:
        Filtered AO in [0, 1] in ``ao``'s dtype (0 where not covered), and the history for the next frame.

    Raises:
        ValueError: wrong shapes, dtypes or devices, NaN or Inf in an input.

    Shape:
        ao, mask, depth: (B, 1, H, W). normal, position: (B, 3, H, W). flow: (B, 2, H, W). Returns (B, 1, H, W).
    """
    guides = {"mask": (mask, 1), "normal": (normal, 3), "depth": (depth, 1), "position": (position, 3)}
    check_buffers("svgf_filter", ao, guides | ({} if flow is None else {"flow": (flow, 2)}))
    b, _, h, w = ao.shape
    prepared = prepare_guides(ao, mask, normal, depth)
    new = functools.partial(torch.empty, dtype=torch.float32, device=ao.device)
    out = SVGFHistory(new((b, h, w)), new((b, h, w, 2)), new((b, h, w)), new((b, h, w, 4)))
    variance = new((b, h, w))
    continued = (flow is not None and prev_camera is not None and history is not None
                 and tuple(history.length.shape) == (b, h, w) and history.length.device == ao.device)
    sources = [wp.from_torch(t.float()) for t in (mask, depth, position, flow if continued else depth)]
    with on_device(ao.device) as launch:
        launch(svgf_temporal_kernel, (b, h, w),
               [*prepared.arrays(), *sources, _previous(history if continued else None, prev_camera, ao.device),
                _knobs(config, atrous), wp.from_torch(out.ao), wp.from_torch(out.moments, dtype=wp.vec2),
                wp.from_torch(out.length), wp.from_torch(out.surface, dtype=wp.vec4), wp.from_torch(variance)])
    filtered, first = atrous_passes(out.ao, Guides(out.ao, prepared.surface, prepared.slope, prepared.covered),
                                    atrous, variance, config.sigma_variance)
    out.ao = first
    return filtered[:, None].to(ao.dtype), out


def _previous(history: SVGFHistory | None, camera: Camera | None, device: torch.device) -> Previous:
    """The kernel's view of the history (1-element stand-ins and ``present`` 0 without one)."""
    prev = Previous()
    if history is None:
        one = functools.partial(torch.zeros, dtype=torch.float32, device=device)
        history = SVGFHistory(one((1, 1, 1)), one((1, 1, 1, 2)), one((1, 1, 1)), one((1, 1, 1, 4)))
        prev.present = 0
        prev.eye = prev.back = wp.vec3(0.0)
    else:
        _, _, back = camera.basis()
        prev.present = 1
        prev.eye = wp.vec3(*camera.eye)
        prev.back = wp.vec3(*back)
    prev.ao = wp.from_torch(history.ao)
    prev.moments = wp.from_torch(history.moments, dtype=wp.vec2)
    prev.length = wp.from_torch(history.length)
    prev.surface = wp.from_torch(history.surface, dtype=wp.vec4)
    return prev


def _knobs(config: SVGFConfig, atrous: ATrousConfig) -> Knobs:
    knobs = Knobs()
    knobs.alpha = float(config.alpha)
    knobs.moments_alpha = float(config.moments_alpha)
    knobs.depth_tolerance = float32_knob(config.depth_tolerance)
    knobs.normal_cosine = float(config.normal_cosine)
    knobs.min_history = float(config.min_history)
    knobs.radius = config.radius
    knobs.sigma_normal = float32_knob(atrous.sigma_normal)
    knobs.sigma_depth = float32_knob(atrous.sigma_depth)
    knobs.edge_depth_tolerance = float32_knob(atrous.depth_tolerance)
    return knobs
