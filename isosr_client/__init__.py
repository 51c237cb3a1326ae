"""isosr_client: thin clients of `isosr serve` (floor 4): view sessions (:mod:`isosr_client.view`)
the frame upscaling API (:mod:`isosr_client.upscale`) and the volumes' listing and slices
(:mod:`isosr_client.volumes`); in a notebook, the viewer as a widget (`widget`, :mod:`isosr_client.notebook`).

Importing it loads numpy, msgspec, websockets and the protocol only; torch and the network load
only where ``buffers`` frames are upscaled here (:mod:`isosr_client.local`), OpenCV at the first
image decoded; anywidget (the ``notebook`` extra) at the first use of `widget` or `Viewer`.
"""

from isosr_client.upscale import UpscaleResult, upscale_remote
from isosr_client.view import FrameStats, ServerError, ViewFrame, ViewSession, connect
from isosr_client.volumes import slice_remote, volumes_remote
from isosr_render.image_codec import decode_image

__all__ = ["connect", "ViewSession", "ViewFrame", "FrameStats", "ServerError", "decode_image", "upscale_remote",
           "UpscaleResult", "slice_remote", "volumes_remote"]


def __getattr__(name: str):
    """`widget` and `Viewer`, imported at first use (they need the ``notebook`` extra)."""
    if name in ("widget", "Viewer"):
        from isosr_client import notebook
        return getattr(notebook, name)
    raise AttributeError(f"module 'isosr_client' has no attribute {name!r}")
