"""isosr_client: thin clients of `isosr serve` (floor 3): view sessions that upscale and shade
low-res buffers locally (:mod:`isosr_client.view`) and the frame upscaling API (:mod:`isosr_client.upscale`)."""

from isosr_client.upscale import UpscaleResult, upscale_remote
from isosr_client.view import FrameStats, ServerError, ViewFrame, ViewSession, connect
from isosr_render.images import decode_image

__all__ = ["connect", "ViewSession", "ViewFrame", "FrameStats", "ServerError", "decode_image", "upscale_remote",
           "UpscaleResult"]
