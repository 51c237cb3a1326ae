"""Flow warping: the one function that aligns a previous frame with the current one.

Flow follows :mod:`isosr_render.conventions`: backward, in pixels of the image it belongs to,
x right and y down; ``flow[p]`` points from pixel ``p`` of the current frame to where the
same surface point lay in the previous frame. So the warped previous frame is
``previous(p + flow[p])``, sampled bilinearly; points that come from outside the previous
frame read zeros.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from isosr_render.shapes import check_shape


def warp_by_flow(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward-warp ``image`` by ``flow``: ``out[p] = image[p + flow[p]]`` (bilinear, zeros outside).

    Shape:
        image: (B, C, H, W). flow: (B, 2, H, W), pixels. Returns (B, C, H, W).
    """
    dims = check_shape(image, "(B, C, H, W)", "image", "warp_by_flow")
    check_shape(flow, "(B, 2, H, W)", "flow", "warp_by_flow", dims)
    _, _, h, w = image.shape
    ys = torch.arange(h, device=flow.device, dtype=flow.dtype) + 0.5
    xs = torch.arange(w, device=flow.device, dtype=flow.dtype) + 0.5
    # Sample positions in grid_sample's normalized coordinates (align_corners=False: -1 and 1
    # are the outer edges of the border pixels).
    gx = (xs[None, None, :] + flow[:, 0]) * (2.0 / w) - 1.0
    gy = (ys[None, :, None] + flow[:, 1]) * (2.0 / h) - 1.0
    grid = torch.stack([gx, gy], dim=-1).to(image.dtype)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def upscale_flow(flow: torch.Tensor, factor: int) -> torch.Tensor:
    """Low-res flow to ``factor`` times the resolution: bilinear, and lengths scaled by ``factor``.

    Shape:
        flow: (B, 2, H, W). Returns (B, 2, H * factor, W * factor).
    """
    check_shape(flow, "(B, 2, H, W)", "flow", "upscale_flow")
    return F.interpolate(flow, scale_factor=factor, mode="bilinear", align_corners=False) * factor

