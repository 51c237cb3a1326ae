"""Images the command line writes: buffer visualizations and atomic PNG files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from isosr_render.atomic import atomic_write
from isosr_render.buffers import FrameBuffers
from isosr_render.images import to_uint8
from isosr_render.surfaces import MAX_SURFACES


def visualize(frame: FrameBuffers, name: str) -> np.ndarray:
    """An 8-bit RGB image of one buffer: color as is, unit vectors and scalars mapped to [0, 1]."""
    a = getattr(frame, name).float().cpu()
    hit = frame.mask.cpu() > 0 if frame.mask is not None else torch.ones(a.shape[:2], dtype=torch.bool)
    if name == "normal":
        rgb = (a + 1.0) * 0.5 * hit[..., None]
    elif name == "position":
        rgb = (a + 0.5).clamp(0, 1) * hit[..., None]
    elif name == "flow":
        mag, ang = cv2.cartToPolar(a[..., 0].numpy(), a[..., 1].numpy(), angleInDegrees=True)
        hsv = np.stack([ang / 2, np.full_like(mag, 255), 255 * mag / max(mag.max(), 1e-6)], -1)
        return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)
    elif name == "depth":
        d = a[hit] if hit.any() else a.flatten()
        lo, hi = float(d.min()), float(d.max())
        gray = torch.where(hit, 1.0 - (a - lo) / max(hi - lo, 1e-12) * 0.8, torch.zeros_like(a))
        rgb = gray[..., None].expand(*gray.shape, 3)
    elif name == "surface":  # several surfaces: brighter by index, black where none
        rgb = ((a + 1.0) / MAX_SURFACES)[..., None].expand(*a.shape, 3)
    elif name == "cap":  # the cut faces' values in grey
        rgb = (a[..., 0] * a[..., 1])[..., None].expand(*a.shape[:2], 3)
    elif a.ndim == 2:
        rgb = a[..., None].expand(*a.shape, 3)
    else:
        rgb = a
    return to_uint8(rgb)


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an RGB image atomically."""
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    atomic_write(path, lambda f: f.write(data.tobytes()))
