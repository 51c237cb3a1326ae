"""Image encoding of shaded frames: PNG, JPEG, WebP; and `CodedImage`, a coded frame of any
encoding (video: :mod:`isosr_server.video`).

JPEG runs on the GPU where the frame is (nvJPEG through ``torchvision.io.encode_jpeg`` on a
CUDA tensor) when torchvision imports, several frames in one call (:func:`encode_jpegs`);
everything else goes through OpenCV's ``cv2.imencode`` on the CPU (libjpeg-turbo, libpng, libwebp;
OpenCV is already a dependency of the renderer).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from isosr_server.codecs import video

try:
    from torchvision.io import encode_jpeg as _gpu_encode_jpeg
except ImportError:  # the CPU install has no torchvision: OpenCV encodes
    _gpu_encode_jpeg = None

# PNG: zlib level 1, the fastest; a shaded frame compresses only a few % more at 9, at several times the cost.
PNG_LEVEL = 1


@dataclass(frozen=True)
class CodedImage:
    """A shaded frame's bytes in ``encoding``: an image, or one video access unit (``keyframe``,
    the stream's WebCodecs ``codec`` string, the encoder's target ``bitrate_kbps``); ``notice``:
    why it is not in the encoding the session asked for."""

    data: bytes
    encoding: str
    keyframe: bool = True
    codec: str | None = None
    bitrate_kbps: int = 0
    notice: str | None = None


def encoder_name(device: str, encoding: str) -> str:
    """Which encoder :func:`encode_image` (or a video encoder) uses for ``encoding`` on ``device`` (for reports)."""
    if encoding in video.CODECS:
        return video.describe(encoding)
    if encoding == "jpeg" and device_jpeg(device):
        return "nvjpeg (torchvision)"
    return f"opencv {cv2.__version__} (cpu)"


def device_jpeg(device: torch.device | str) -> bool:
    """Whether JPEGs of frames on ``device`` are encoded there (nvJPEG on CUDA where torchvision imports)."""
    return _gpu_encode_jpeg is not None and torch.device(device).type == "cuda"


def encode_jpegs(rgbs: Sequence[torch.Tensor], quality: int) -> list[bytes]:
    """JPEGs of frames on a CUDA device (:func:`device_jpeg`), in one nvJPEG call and one copy of
    their bytes to the host.

    Shape:
        rgbs: each (H, W, 3) uint8, on one CUDA device; sizes may differ.
    """
    coded = _gpu_encode_jpeg([rgb.permute(2, 0, 1).contiguous() for rgb in rgbs], quality=quality)
    data = torch.cat(coded).cpu().numpy().tobytes()
    ends = np.cumsum([c.numel() for c in coded]).tolist()
    return [data[a:b] for a, b in zip([0] + ends[:-1], ends)]


def encode_image(rgb: torch.Tensor, encoding: str, quality: int) -> bytes:
    """Encode an image as ``png``, ``jpeg`` or ``webp`` (quality 1-100; PNG is lossless).

    Shape:
        rgb: (H, W, 3) uint8, on any device.
    """
    if rgb.dtype != torch.uint8 or rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"encode_image takes (H, W, 3) uint8, got {tuple(rgb.shape)} {rgb.dtype}")
    if not 1 <= quality <= 100:
        raise ValueError(f"quality must lie in [1, 100], got {quality}")
    if encoding == "jpeg" and device_jpeg(rgb.device):
        return encode_jpegs([rgb], quality)[0]
    params = {"png": (".png", [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL]),
              "jpeg": (".jpg", [cv2.IMWRITE_JPEG_QUALITY, quality]),
              "webp": (".webp", [cv2.IMWRITE_WEBP_QUALITY, quality])}
    if encoding not in params:
        raise ValueError(f"encoding must be one of {', '.join(params)}, got {encoding!r}")
    ext, flags = params[encoding]
    bgr = np.ascontiguousarray(rgb.cpu().numpy()[..., ::-1])
    ok, data = cv2.imencode(ext, bgr, flags)
    if not ok:
        raise RuntimeError(f"OpenCV failed to encode a {tuple(rgb.shape)} image as {encoding}")
    return data.tobytes()
