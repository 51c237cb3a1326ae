"""The channel view: one buffer of a view mode as a false-color image, with its legend.

A frame whose settings name a ``channel`` other than ``shaded`` computes the mode's buffers at
output resolution and colors the named one on the device, instead of shading; only the buffers
that channel needs are rendered (standing order 3):

    full      a full-res render of mask + the channel (AO with ``ao_rays`` rays; flow
              relative to the previous frame's camera, zero on a first or refined frame)
    network   the network's output (mask, normal, depth, AO); flow is the network's low-res
              input flow, nearest-upsampled and scaled to output pixels
    upscale   the classic baseline (its AO is 1 everywhere: the baseline knows no occlusion)
    focus     as ``network`` (the lens applies to shaded frames only)
    reconstruct  the network's output (mask, normal, depth, AO); flow is its full-res input
              flow, rendered once more for this view
    buffers   no channel view: the client gets the buffers themselves

Colormaps (the page's legend.js draws the same ones from the frame's ``legend``):
    mask    gray, 0 black to 1 white
    normal  view-space normal xyz in [-1, 1] -> rgb ``n / 2 + 1/2``
    depth   `DEPTH_STOPS` (viridis at 9 stops) from the nearest to the farthest covered pixel
    ao      gray, 0 (occluded) black to 1 white
    flow    hue = direction of the backward flow (x right, y down), value = length / the
            frame's longest flow; black = still; components clipped to +-FLOW_CLIP pixels
Uncovered pixels (mask 0) are `NO_SURFACE` gray, covered ones blend by the mask.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from isosr_net.frame_methods import upscale_classic
from isosr_net.upscaler import Upscaler
from isosr_render import FrameBuffers, Renderer, RenderRequest
from isosr_server.pipeline import FrameSpec, ReconStream, StageTimer, render_lowres
from isosr_server.protocol import CHANNELS, FLOW_CLIP, ProtocolError, ViewSettings

NO_SURFACE = 0.12
# viridis at t = 0, 1/8, ..., 1
DEPTH_STOPS = ((0.267, 0.005, 0.329), (0.279, 0.175, 0.483), (0.230, 0.322, 0.546), (0.173, 0.449, 0.558),
               (0.128, 0.567, 0.551), (0.153, 0.680, 0.510), (0.365, 0.785, 0.387), (0.666, 0.862, 0.196),
               (0.993, 0.906, 0.144))
# Coverage above which a pixel's depth and flow count for the legend's range.
COVERED = 0.5


def check(settings: ViewSettings) -> None:
    """`ProtocolError` for a channel the settings cannot produce."""
    if settings.channel not in CHANNELS:
        raise ProtocolError(f"channel must be one of {', '.join(CHANNELS)}, got {settings.channel!r}")
    if settings.channel == "ao" and settings.mode == "full" and settings.ao_rays == 0:
        raise ProtocolError("the ao channel of full-resolution frames needs ao_rays > 0")


def channel_buffers(renderer: Renderer, upscaler: Upscaler, factor: int, spec: FrameSpec, timer: StageTimer,
                    recon: ReconStream | None = None) -> FrameBuffers:
    """The mode's output-resolution buffers that ``spec.channel`` shows (plus the mask);
    ``recon``: the session's reconstruction (``reconstruct`` mode only)."""
    channel = spec.channel
    if spec.mode == "reconstruct":
        if recon is None:
            raise ValueError("the reconstruct mode's channel view needs the session's ReconStream")
        high = recon.frame(renderer, spec)  # always: keeps the recurrent state in step with the stream
        if channel == "flow":
            high.flow = channel_buffers(renderer, upscaler, factor, replace(spec, mode="full"), timer).flow
        return high
    if spec.mode == "full":
        flow = channel == "flow" and spec.prev_camera is not None
        outputs = ("mask",) + ((channel,) if channel not in ("mask", "flow") or flow else ())
        request = RenderRequest(spec.width, spec.height, spec.iso, outputs, ao_samples=max(spec.ao_samples, 1),
                                ao_radius=spec.ao_radius, prev_camera=spec.prev_camera if flow else None)
        with timer("render"):
            return renderer.render(spec.camera, request)
    if spec.mode in ("network", "focus"):
        low = render_lowres(renderer, spec, factor, timer)
        with timer("network"):
            high = upscaler.upscale(low)  # always: keeps the recurrent state in step with the stream
    elif spec.mode == "upscale":
        low = render_lowres(renderer, spec, factor, timer, flow=channel == "flow")
        with timer("network"):
            high = upscale_classic(low, factor, spec.interpolation)
    else:
        raise ProtocolError(f"mode {spec.mode} has no channel view")
    if channel == "flow" and low.flow is not None:
        high.flow = torch.repeat_interleave(torch.repeat_interleave(low.flow, factor, 0), factor, 1) * factor
    return high


def false_color(buffers: FrameBuffers, channel: str) -> tuple[torch.Tensor, dict]:
    """The channel as RGB in [0, 1] and its legend (``channel, lo, hi, unit, colormap[, stops]``).

    Shape:
        buffers: output-resolution (H, W[, C]) tensors. Returns (H, W, 3).
    """
    mask = buffers.mask.float().clamp(0.0, 1.0)
    covered = mask > COVERED
    if channel == "mask":
        return mask[..., None].expand(*mask.shape, 3).clone(), _legend(channel, 0.0, 1.0, "coverage", "gray")
    if channel == "normal":
        rgb = buffers.normal.float() * 0.5 + 0.5
        legend = _legend(channel, -1.0, 1.0, "view-space xyz", "normal")
    elif channel == "depth":
        depth = torch.nan_to_num(buffers.depth.float(), 0.0, 0.0, 0.0)
        hits = depth[covered]
        lo, hi = (hits.min().item(), hits.max().item()) if hits.numel() else (0.0, 0.0)
        t = ((depth - lo) / max(hi - lo, 1e-12)).clamp(0.0, 1.0)
        rgb = _colormap(t, DEPTH_STOPS)
        legend = _legend(channel, lo, hi, "world units", "stops") | {"stops": [list(s) for s in DEPTH_STOPS]}
    elif channel == "ao":
        ao = buffers.ao.float().clamp(0.0, 1.0)
        rgb = ao[..., None].expand(*ao.shape, 3)
        legend = _legend(channel, 0.0, 1.0, "1 = unoccluded", "gray")
    elif channel == "flow":
        flow = buffers.flow
        if flow is None:  # the first frame after a cut: nothing moved yet
            flow = torch.zeros(*mask.shape, 2, device=mask.device)
        flow = torch.nan_to_num(flow.float(), 0.0, 0.0, 0.0).clamp(-FLOW_CLIP, FLOW_CLIP)
        length = torch.linalg.vector_norm(flow, dim=-1)
        hi = length[covered].max().item() if covered.any() else 0.0
        rgb = _flow_color(flow, length, hi)
        legend = _legend(channel, 0.0, hi, "px to the previous frame", "flow")
    else:
        raise ProtocolError(f"channel must be one of {', '.join(CHANNELS[1:])} here, got {channel!r}")
    alpha = mask[..., None]
    return (alpha * rgb + (1.0 - alpha) * NO_SURFACE).clamp(0.0, 1.0), legend


def _legend(channel: str, lo: float, hi: float, unit: str, colormap: str) -> dict:
    return {"channel": channel, "lo": float(lo), "hi": float(hi), "unit": unit, "colormap": colormap}


def _colormap(t: torch.Tensor, stops: tuple[tuple[float, float, float], ...]) -> torch.Tensor:
    """Piecewise-linear colormap of ``t`` in [0, 1]. Shape: t (H, W) -> (H, W, 3)."""
    table = torch.tensor(stops, dtype=torch.float32, device=t.device)
    x = t * (len(stops) - 1)
    i = x.floor().long().clamp(max=len(stops) - 2)
    f = (x - i)[..., None]
    return table[i] * (1.0 - f) + table[i + 1] * f


def _flow_color(flow: torch.Tensor, length: torch.Tensor, hi: float) -> torch.Tensor:
    """HSV with hue = direction, saturation 1, value = length / hi. Shape: (H, W, 2) -> (H, W, 3)."""
    hue = torch.remainder(torch.atan2(flow[..., 1], flow[..., 0]) / (2 * math.pi), 1.0)
    value = (length / hi).clamp(max=1.0) if hi > 0 else torch.zeros_like(length)
    k = torch.stack([torch.remainder(n + hue * 6, 6) for n in (5.0, 3.0, 1.0)], dim=-1)
    return value[..., None] * (1.0 - torch.minimum(k, 4.0 - k).clamp(0.0, 1.0))


def render_channel(renderer: Renderer, upscaler: Upscaler, factor: int, spec: FrameSpec, timer: StageTimer,
                   recon: ReconStream | None = None) -> tuple[torch.Tensor, dict]:
    """A channel-view frame: ``(rgb (H, W, 3) in [0, 1], legend)`` (arguments: :func:`channel_buffers`)."""
    buffers = channel_buffers(renderer, upscaler, factor, spec, timer, recon)
    with timer("shading"):
        return false_color(buffers, spec.channel)
