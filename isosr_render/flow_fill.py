"""Dense flow: fill the flow of pixels without a hit from their neighbours.

Two methods: OpenCV's Navier-Stokes inpainting as in the paper (CPU, numpy round trip) and
a push-pull pyramid in torch that runs where the tensors are (the GPU alternative; see the
README for the measured times).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

FILL_METHODS = ("none", "ns", "pushpull")


def inpaint_ns(flow: torch.Tensor, mask: torch.Tensor, radius: float = 3.0) -> torch.Tensor:
    """Navier-Stokes inpainting (``cv2.INPAINT_NS``) of the pixels where ``mask < 0.5``.

    Shape:
        flow: (H, W, 2). mask: (H, W). Returns (H, W, 2) on ``flow``'s device.
    """
    holes = (mask < 0.5).to(torch.uint8).cpu().numpy()
    if not holes.any() or holes.all():
        return flow.clone()
    src = flow.detach().cpu().numpy().astype(np.float32)
    filled = np.stack([cv2.inpaint(np.ascontiguousarray(src[..., c]), holes, radius, cv2.INPAINT_NS)
                       for c in range(2)], axis=-1)
    return torch.from_numpy(filled).to(flow.device)


def push_pull(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Fill holes (``mask < 0.5``) by averaging down a pyramid and interpolating back up.

    Covered pixels keep their values exactly.

    Shape:
        flow: (H, W, 2). mask: (H, W). Returns (H, W, 2).
    """
    valid = (mask >= 0.5).to(flow.dtype)[None, None]
    if not valid.any():
        return torch.zeros_like(flow)
    level_v = [flow.permute(2, 0, 1)[None] * valid]
    level_w = [valid]
    while min(level_w[-1].shape[-2:]) > 1:  # push: premultiplied averages
        level_v.append(F.avg_pool2d(level_v[-1], 2, ceil_mode=True))
        level_w.append(F.avg_pool2d(level_w[-1], 2, ceil_mode=True))
    filled = level_v[-1] / level_w[-1].clamp(min=1e-12)
    for v, w in zip(reversed(level_v[:-1]), reversed(level_w[:-1])):  # pull
        up = F.interpolate(filled, size=v.shape[-2:], mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, v / w.clamp(min=1e-12), up)
    return filled[0].permute(1, 2, 0).contiguous()


def fill_flow(flow: torch.Tensor, mask: torch.Tensor, method: str) -> torch.Tensor:
    """Dense flow by ``method``, one of :data:`FILL_METHODS`."""
    if method == "none":
        return flow
    if method == "ns":
        return inpaint_ns(flow, mask)
    if method == "pushpull":
        return push_pull(flow, mask)
    raise ValueError(f"unknown flow fill {method!r}; expected one of {FILL_METHODS}")
