"""``POST /v1/upscale`` from Python: send one low-res frame, get the high-res buffers or an image.

    from isosr_client import upscale_remote
    result = upscale_remote("http://127.0.0.1:8000", low)            # low: FrameBuffers (mask, normal, depth[, flow])
    result.buffers.normal                                            # (H, W, 3) float32 tensor
    png = upscale_remote(url, low, output="png").image               # encoded shaded image bytes

Consecutive frames with the same ``session`` id keep the network's recurrent state on the server.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from dataclasses import dataclass

import numpy as np
import torch

from isosr_client.view import CLIENT_LIMITS, ServerError, auth_headers, endpoint
from isosr_render.buffers import FrameBuffers
from isosr_server.protocol import MSGPACK_MEDIA_TYPE, UpscaleRequest, UpscaleResponse, pack, parse


@dataclass(frozen=True)
class UpscaleResult:
    """The server's answer: high-res buffers (mask, normal, depth, ao as float32 CPU tensors) or
    the encoded image; ``times`` the server's milliseconds per stage (when it sent them)."""

    buffers: FrameBuffers | None
    image: bytes | None
    times: dict[str, float]


def upscale_remote(url: str, frame: FrameBuffers, output: str = "buffers", quality: int = 85,
                   session: str | None = None, reset: bool = False, token: str | None = None,
                   timeout: float = 60.0) -> UpscaleResult:
    """Upscale one low-res frame on the server.

    Args:
        url: the server, ``http://HOST:PORT``.
        frame: mask, normal, depth and optionally flow (float16/float32, any device).
        output: ``buffers``, ``png``, ``jpeg`` or ``webp``.
        quality: jpeg/webp quality 1-100.
        session: an id whose consecutive frames keep the recurrent state (None: a fresh state).
        reset: forget the session's state before this frame.
        token: the server's token, if it has one.
        timeout: seconds.

    Raises:
        ProtocolError: the frame cannot travel (missing buffer, wrong shape or dtype, NaN/Inf);
            found here, before sending.
        ServerError: the server's 4xx/5xx status and reason.
    """
    arrays = {}
    for name in ("mask", "normal", "depth", "flow"):
        t = getattr(frame, name)
        if t is not None:
            a = t.detach().cpu().numpy()
            arrays[name] = a if a.dtype in (np.float16, np.float32) else a.astype(np.float32)
    for name in ("mask", "normal", "depth"):
        if name not in arrays:
            raise ValueError(f"the low-res frame lacks its {name} buffer")
    body = pack(UpscaleRequest(**arrays, output=output, quality=quality, session=session, reset=reset).to_wire())
    parse(body, CLIENT_LIMITS, (UpscaleRequest,))  # bad input fails here, with the server's reason
    request = urllib.request.Request(endpoint(url, "/v1/upscale", websocket=False), data=body, method="POST",
                                     headers={"Content-Type": MSGPACK_MEDIA_TYPE, **auth_headers(token)})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as reply:
            kind, data = reply.headers.get("content-type", ""), reply.read()
            times_header = reply.headers.get("x-isosr-times")
    except urllib.error.HTTPError as e:
        detail = e.read()
        try:
            reason = json.loads(detail)["error"]
        except (ValueError, KeyError, TypeError):
            reason = detail.decode(errors="replace")[:200]
        raise ServerError(e.code, reason) from None
    if kind.startswith("image/"):
        return UpscaleResult(None, data, json.loads(times_header) if times_header else {})
    msg = parse(data, CLIENT_LIMITS, (UpscaleResponse,))
    buffers = FrameBuffers(**{n: torch.from_numpy(np.array(a)) for n, a in msg.buffers.items()})
    return UpscaleResult(buffers, None, dict(msg.times))
