"""The channel view: one buffer of a view mode's frame as a false-color image, with its legend.

A frame whose settings name a ``channel`` other than ``shaded`` is made by the mode's method with
that buffer kept (:mod:`isosr_server.views`): a buffer the method makes is its own (a network's
AO, depth and mask are its outputs), any other is ray cast besides and nothing more (flow against
the previous frame's camera, zero on a first or refined frame; a low-res method's flow
nearest-upsampled and scaled to output pixels). The buffer is colored on the device instead of
shading. ``buffers`` frames have no channel view: the client gets the buffers themselves.

Colormaps (the page's legend.js draws the same ones from the frame's ``legend``):
    mask    gray, 0 black to 1 white
    normal  view-space normal xyz in [-1, 1] -> rgb ``n / 2 + 1/2``
    depth   `DEPTH_STOPS` (viridis) from the nearest to the farthest covered pixel
    ao      gray, 0 (occluded) black to 1 white
    flow    hue = direction of the backward flow (x right, y down), value = length / the
            frame's longest flow; black = still; components clipped to +-FLOW_CLIP pixels
Uncovered pixels (mask 0) are `NO_SURFACE` gray, covered ones blend by the mask.
"""

from __future__ import annotations

import math

import torch

from isosr_render import FrameBuffers
from isosr_render.color_field import ramp
from isosr_render.coloring import COLORMAPS
from isosr_server.protocol import CHANNELS, FLOW_CLIP, ProtocolError

NO_SURFACE = 0.12
DEPTH_STOPS = COLORMAPS["viridis"]
# Coverage above which a pixel's depth and flow count for the legend's range.
COVERED = 0.5


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
        rgb = ramp(t, DEPTH_STOPS)
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


def _flow_color(flow: torch.Tensor, length: torch.Tensor, hi: float) -> torch.Tensor:
    """HSV with hue = direction, saturation 1, value = length / hi. Shape: (H, W, 2) -> (H, W, 3)."""
    hue = torch.remainder(torch.atan2(flow[..., 1], flow[..., 0]) / (2 * math.pi), 1.0)
    value = (length / hi).clamp(max=1.0) if hi > 0 else torch.zeros_like(length)
    k = torch.stack([torch.remainder(n + hue * 6, 6) for n in (5.0, 3.0, 1.0)], dim=-1)
    return value[..., None] * (1.0 - torch.minimum(k, 4.0 - k).clamp(0.0, 1.0))
