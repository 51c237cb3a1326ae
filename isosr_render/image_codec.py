"""Decoding of encoded images (PNG, JPEG, WebP) to 8-bit RGB: numpy only, no torch, so that
thin clients can use it; OpenCV loads on the first decode."""

from __future__ import annotations

import numpy as np


def decode_image(data: bytes) -> np.ndarray:
    """PNG, JPEG or WebP bytes -> (H, W, 3) uint8 RGB (OpenCV).

    Raises:
        ValueError: the bytes are not an image OpenCV reads.
    """
    import cv2  # here, not at import: OpenCV costs a client that never decodes an image a tenth of a second

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("not a PNG, JPEG or WebP image")
    return np.ascontiguousarray(bgr[..., ::-1])
