"""Float images to 8-bit: the one conversion every image writer uses."""

from __future__ import annotations

import numpy as np
import torch


def to_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """An image in [0, 1] as uint8 (values clamped, rounded to nearest), on the CPU.

    Raises:
        ValueError: the image holds NaN or Inf.

    Shape:
        Any; returned unchanged.
    """
    a = image.detach().float().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, np.float32)
    if not np.isfinite(a).all():
        raise ValueError("to_uint8: the image holds NaN or Inf values")
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
