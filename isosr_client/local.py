"""The client's optional part: ``buffers`` frames upscaled by the network and shaded here (torch,
:mod:`isosr_net`). :mod:`isosr_client.view` imports it only when a session upscales its first
buffers frame, so that viewing encoded frames never loads torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render.buffers import FrameBuffers
from isosr_render.images import to_uint8
from isosr_render.shading import shade


class LocalUpscaler:
    """One view session's network and its recurrent state.

    Args:
        model: the model folder (None: the shipped one); it must upscale by the server's ``factor``.
        device: where it runs (``cpu``, ``cuda``, ``cuda:N``).
        factor: the server's upscale factor (``ready.upscale_factor``).

    Raises:
        RuntimeError: ``device`` names a CUDA device this machine lacks (`check_device`).
        ValueError: the model upscales by another factor than the server's.
    """

    def __init__(self, model: str | Path | None, device: str, factor: int):
        check_device(device)
        self.device = device
        self.upscaler = Upscaler(DEFAULT_MODEL if model is None else model, device)
        if self.upscaler.upscale_factor != factor:
            raise ValueError(f"the local model upscales {self.upscaler.upscale_factor}x, the server's {factor}x: "
                             f"give the server's model (model=...)")

    def upscale(self, arrays: dict[str, np.ndarray]) -> FrameBuffers:
        """The network's high-res buffers of one decoded low-res frame (without ``flow`` the
        recurrent state starts afresh); returns once the device is done (for timing).

        Shape:
            arrays: mask, depth (h, w), normal (h, w, 3)[, flow (h, w, 2)] float32. Returns
            mask, depth, ao (H, W), normal (H, W, 3) on ``device``.
        """
        low = FrameBuffers(**{n: torch.from_numpy(a).to(self.device) for n, a in arrays.items()})
        high = self.upscaler.upscale(low)
        if high.mask.is_cuda:
            torch.cuda.synchronize(high.mask.device)
        return high


def check_device(device: str) -> None:
    """Raise RuntimeError ``no CUDA device: ...`` (one line, for the command line) where ``device``
    names a CUDA device that torch does not find here, rather than torch's error at first use."""
    kind = torch.device(device)
    if kind.type != "cuda":
        return
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if (kind.index or 0) >= count:
        found = "none" if count == 0 else f"only {count}"
        raise RuntimeError(f"no CUDA device: {device!r} asked for, but torch finds {found} on this machine; "
                           f"upscale on 'cpu'")


def shade_rgb(high: FrameBuffers) -> np.ndarray:
    """High-res buffers shaded as the server shades them.

    Shape:
        Returns (H, W, 3) uint8 RGB.
    """
    return to_uint8(shade(high.mask, high.normal, high.ao))
