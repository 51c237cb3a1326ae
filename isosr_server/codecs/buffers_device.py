"""The ``buffers`` coding's encoder (format: :mod:`isosr_server.codecs.buffers`): quantization in
float32 torch on the frame's own device, so that only the uint8 / uint16 / float16 codes (and two
depth bounds) cross to the host, where zlib packs them. The server's alone: clients never import it.

Its codes equal those of the float64 definition within one code unit (float32 rounding moves a
value across a rounding boundary at most; ``tests/test_codecs.py`` holds that definition).
"""

from __future__ import annotations

import torch

from isosr_render.buffers import FrameBuffers
from isosr_server.codecs.buffers import CODE_MAX, MASK_MAX, pack_view_buffers
from isosr_server.protocol import FLOW_CLIP, ViewBuffers


def mask_codes(mask: torch.Tensor) -> torch.Tensor:
    """Coverage as uint8 ``round(255 m)``, at least 1 where ``m > 0``, 0 elsewhere.

    Shape:
        mask: (h, w) float. Returns (h, w) uint8 on mask's device.
    """
    m = mask.float()
    code = torch.round(m.clamp(0.0, 1.0) * MASK_MAX).clamp_min(1.0)
    return torch.where(m > 0, code, 0.0).to(torch.uint8)


def octahedral_codes(normal: torch.Tensor, covered: torch.Tensor) -> torch.Tensor:
    """Octahedral codes of (not necessarily unit) vectors, 0 where not ``covered``.

    Shape:
        normal: (h, w, 3) float. covered: (h, w) bool. Returns (h, w, 2) uint16 on normal's device.
    """
    n = normal.float()
    n = n / n.abs().sum(-1, keepdim=True).clamp_min(1e-30)
    xy = n[..., :2]
    folded = (1.0 - xy.flip(-1).abs()) * torch.where(xy >= 0, 1.0, -1.0)
    xy = torch.where(n[..., 2:3] < 0, folded, xy)
    code = torch.round((xy.clamp(-1.0, 1.0) * 0.5 + 0.5) * CODE_MAX)
    return torch.where(covered[..., None], code, 0.0).to(torch.uint16)


def depth_codes(depth: torch.Tensor, covered: torch.Tensor) -> tuple[torch.Tensor, tuple[float, float]]:
    """Depth as uint16, linear from the nearest to the farthest covered pixel, 0 where not
    ``covered``; and that (near, far) (0, 0 without a covered pixel; the one host sync).

    Shape:
        depth: (h, w) float. covered: (h, w) bool. Returns (h, w) uint16 on depth's device.
    """
    d = depth.float()
    near, far = torch.stack([torch.where(covered, d, torch.inf).amin(), torch.where(covered, d, -torch.inf).amax()]
                            ).tolist()
    if near > far:  # no covered pixel
        near = far = 0.0
    scale = CODE_MAX / (far - near) if far > near else 0.0
    code = torch.round((d - near) * scale).clamp(0.0, CODE_MAX)
    return torch.where(covered, code, 0.0).to(torch.uint16), (near, far)


def view_buffer_codes(frame: FrameBuffers) -> tuple:
    """A low-res frame's codes on the host, for :func:`~isosr_server.codecs.buffers.pack_view_buffers`:
    ``(mask, normal or None, depth or None, depth_range or None, flow or None)``.

    Shape:
        frame.mask, frame.depth: (h, w). frame.normal: (h, w, 3). frame.flow: (h, w, 2). Any device.
    """
    covered = frame.mask > 0
    normal = None if frame.normal is None else octahedral_codes(frame.normal, covered).cpu().numpy()
    depth, depth_range = None, None
    if frame.depth is not None:
        codes, depth_range = depth_codes(frame.depth, covered)
        depth = codes.cpu().numpy()
    flow = None
    if frame.flow is not None:
        flow = frame.flow.float().clamp(-FLOW_CLIP, FLOW_CLIP).to(torch.float16).cpu().numpy()
    return mask_codes(frame.mask).cpu().numpy(), normal, depth, depth_range, flow


def encode_view_buffers(frame: FrameBuffers) -> ViewBuffers:
    """A low-res frame's mask and what it holds of normal, depth and flow in the buffers coding
    (:func:`view_buffer_codes`, then packed)."""
    return pack_view_buffers(*view_buffer_codes(frame))
