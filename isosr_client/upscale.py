"""``POST /v1/upscale`` from Python: send one low-res frame, get the high-res buffers or an image.

    from isosr_client import upscale_remote
    result = upscale_remote("http://127.0.0.1:8000", low)            # low: FrameBuffers, or a map of arrays
    result.buffers.normal                                            # (H, W, 3) float32 numpy
    png = upscale_remote(url, low, output="png").image               # encoded shaded image bytes

Consecutive frames with the same ``session`` id keep the network's recurrent state on the server;
the id also travels in the ``x-session-id`` header, on which a server of replicas
(``isosr serve --replicas N``) routes them to the replica that holds that state.
The frame's buffers may be numpy arrays or torch tensors (read through ``.detach().cpu().numpy()``;
torch itself is never imported here).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from isosr_client.view import CLIENT_LIMITS, http_call
from isosr_server.protocol import (HIGHRES_OUTPUTS, LOWRES_INPUTS, MSGPACK_MEDIA_TYPE, REPLICA_HEADER, RESTARTED_HEADER,
                                   SESSION_HEADER, HighresBuffers, UpscaleRequest, UpscaleResponse, encode, parse)


@dataclass(frozen=True)
class UpscaleResult:
    """The server's answer: high-res buffers (mask, normal, depth, ao as float32 numpy arrays) or
    the encoded image; ``times`` the server's milliseconds per stage (when it sent them); behind
    replicas, the ``replica`` that answered and whether the session's recurrent state was
    ``restarted`` there (its replica was gone), else None and False."""

    buffers: HighresBuffers | None
    image: bytes | None
    times: dict[str, float]
    replica: str | None = None
    restarted: bool = False


def _numpy(a: Any) -> np.ndarray:
    """A buffer as float16 or float32 numpy (a torch tensor on any device, or array-like)."""
    a = a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)
    return a if a.dtype in (np.float16, np.float32) else a.astype(np.float32)


def upscale_remote(url: str, frame: Any, output: str = "buffers", quality: int = 85, session: str | None = None,
                   reset: bool = False, token: str | None = None, timeout: float = 60.0,
                   cafile: str | Path | None = None) -> UpscaleResult:
    """Upscale one low-res frame on the server.

    Args:
        url: the server, ``http(s)://HOST:PORT``.
        frame: mask, normal, depth and optionally flow, as attributes (a `FrameBuffers`) or a map;
            numpy arrays or torch tensors (any device, any float dtype).
        output: ``buffers``, ``png``, ``jpeg`` or ``webp``.
        quality: jpeg/webp quality 1-100.
        session: an id whose consecutive frames keep the recurrent state (None: a fresh state).
        reset: forget the session's state before this frame.
        token: the server's token, if it has one.
        timeout: seconds.
        cafile: PEM certificates to trust for an https server instead of the system's.

    Raises:
        ValueError: the frame lacks mask, normal or depth; a bad ``cafile`` (`tls_context`).
        ProtocolError: the frame cannot travel (wrong shape, values out of range, NaN/Inf); found
            here, before sending.
        ServerError: the server's 4xx/5xx status and reason.

    Shape:
        frame: mask, depth (h, w), normal (h, w, 3), flow (h, w, 2). Returns buffers of
        (h * factor, w * factor[, 3]).
    """
    get = frame.get if isinstance(frame, Mapping) else lambda name: getattr(frame, name, None)
    arrays = {name: _numpy(a) for name in LOWRES_INPUTS if (a := get(name)) is not None}
    for name in ("mask", "normal", "depth"):
        if name not in arrays:
            raise ValueError(f"the low-res frame lacks its {name} buffer")
    body = encode(UpscaleRequest(**arrays, output=output, quality=quality, session=session, reset=reset))
    parse(body, CLIENT_LIMITS, (UpscaleRequest,))  # bad input fails here, with the server's reason
    headers = {"Content-Type": MSGPACK_MEDIA_TYPE}
    if session is not None:
        headers[SESSION_HEADER] = session  # the replicas' routing key
    reply, data = http_call(url, "/v1/upscale", token, cafile, timeout, body, headers)
    kind, times_header = reply.get("content-type", ""), reply.get("x-isosr-times")
    replica, restarted = reply.get(REPLICA_HEADER), reply.get(RESTARTED_HEADER) == "1"
    if kind.startswith("image/"):
        return UpscaleResult(None, data, json.loads(times_header) if times_header else {}, replica, restarted)
    msg = parse(data, CLIENT_LIMITS, (UpscaleResponse,))
    # Writable copies: the decoded arrays are read-only views of the reply's bytes.
    buffers = HighresBuffers(**{n: np.array(getattr(msg.buffers, n)) for n in HIGHRES_OUTPUTS})
    return UpscaleResult(buffers, None, dict(msg.times), replica, restarted)
