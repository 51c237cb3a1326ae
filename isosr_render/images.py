"""8-bit pixels: the one float -> uint8 rule (decoding encoded images: :mod:`isosr_render.image_codec`)."""

from __future__ import annotations

import numpy as np
import torch


def quantize(image: torch.Tensor) -> torch.Tensor:
    """An image in [0, 1] as uint8 on its own device (clamped, rounded to nearest), e.g. for a
    GPU encoder.

    Shape:
        Any; returned unchanged.
    """
    return (image.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8)


def to_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """An image in [0, 1] as uint8 numpy on the CPU, by :func:`quantize`.

    Raises:
        ValueError: the image holds NaN or Inf.

    Shape:
        Any; returned unchanged.
    """
    t = image.detach().float() if isinstance(image, torch.Tensor) else torch.from_numpy(np.asarray(image, np.float32))
    if not torch.isfinite(t).all():
        raise ValueError("to_uint8: the image holds NaN or Inf values")
    return quantize(t).cpu().numpy()

