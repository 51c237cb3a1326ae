"""Frame upscaling: low-res buffers in, high-res buffers or a shaded image out.

    POST /v1/upscale          one low-res frame -> high-res buffers (msgpack) or an image; a
                              ``session`` id keeps the recurrent state between requests
    WS   /v1/upscale/stream   low-res frames in, high-res frames out, in order, one state per connection;
                              a slot taken only once the first request is valid
"""

from __future__ import annotations

import asyncio
import json

import msgspec

from fastapi import APIRouter, Depends, HTTPException, Request, WebSocket
from fastapi.responses import Response

from isosr_net.upscaler import Upscaler
from isosr_server.api.deps import (AuthorizedDep, EngineDep, LimitsDep, MetricsDep, UpscaleSessionsDep,
                                   require_token)
from isosr_server.api.ws import accept, end_ws, rate_limiter, receive
from isosr_server.engine import Engine
from isosr_server.protocol import (MSGPACK_MEDIA_TYPE, HighresBuffers, Limits, ProtocolError, UpscaleRequest,
                                   UpscaleResponse, encode, parse)

BODY_TYPES = (MSGPACK_MEDIA_TYPE, "application/x-msgpack", "application/octet-stream")
IMAGE_TYPES = {"image/png": "png", "image/jpeg": "jpeg", "image/webp": "webp"}

router = APIRouter(prefix="/v1/upscale", tags=["upscale"])


async def parse_upscale(data: bytes, engine: Engine, limits: Limits) -> UpscaleRequest:
    """The request in ``data``, decoded off the event loop (it inflates and checks megabytes of
    arrays), its arrays bounded before they inflate by the limits of a frame that upscales to
    within ``limits`` (`Limits.downscaled`); `ProtocolError` 413 when the upscaled frame would
    exceed the size limits."""
    msg = await asyncio.to_thread(parse, data, limits.downscaled(engine.upscale_factor), (UpscaleRequest,))
    check_upscale(msg, engine, limits)
    return msg


def check_upscale(msg: UpscaleRequest, engine: Engine, limits: Limits) -> None:
    """`ProtocolError` 413 when the upscaled frame would exceed the size limits."""
    h, w = msg.mask.shape
    limits.check_size(w * engine.upscale_factor, h * engine.upscale_factor, "the upscaled frame")


async def run_upscale(engine: Engine, upscaler: Upscaler, msg: UpscaleRequest):
    """``(image or None, buffers or None, times)`` on the device thread; 422 when the network refuses the frame."""
    try:
        return await engine.upscale(upscaler, msg)
    except ValueError as e:  # the network refuses this frame (e.g. fp16 beyond its depth range)
        raise ProtocolError(f"cannot upscale this frame: {e}", http_status=422) from None


async def read_body(request: Request) -> bytes:
    """The msgpack body (415 for another content type); the guard (:mod:`isosr_server.guard`) has
    bounded its size (413) and the time it may take (408) already."""
    kind = request.headers.get("content-type", MSGPACK_MEDIA_TYPE).split(";")[0].strip()
    if kind not in BODY_TYPES:
        raise HTTPException(415, f"send a msgpack body ({MSGPACK_MEDIA_TYPE}), not {kind}")
    return await request.body()


@router.post("", dependencies=[Depends(require_token)])
async def upscale(request: Request, engine: EngineDep, limits: LimitsDep, metrics: MetricsDep,
                  sessions: UpscaleSessionsDep):
    msg = await parse_upscale(await read_body(request), engine, limits)
    accept_type = request.headers.get("accept", "").split(",")[0].split(";")[0].strip()
    if msg.output == "buffers" and accept_type in IMAGE_TYPES:
        msg = msgspec.structs.replace(msg, output=IMAGE_TYPES[accept_type])
    client = request.client.host if request.client else ""
    upscaler = sessions.get(msg.session, client) if msg.session else engine.new_network(Upscaler)
    image, buffers, times = await run_upscale(engine, upscaler, msg)
    sessions.trim(keep=upscaler)
    h, w = msg.mask.shape
    f = engine.upscale_factor
    if image is not None:
        metrics.frame("upscale", msg.output, False, times, len(image))
        return Response(image, media_type=f"image/{msg.output}", headers={"x-isosr-times": json.dumps(times)})
    nbytes = sum(a.nbytes for a in buffers.values())
    metrics.frame("upscale", "buffers", False, times, nbytes)
    reply = UpscaleResponse(seq=0, width=w * f, height=h * f, output="buffers", times=times, nbytes=nbytes,
                            buffers=HighresBuffers(**buffers))
    return Response(encode(reply), media_type=MSGPACK_MEDIA_TYPE)


@router.websocket("/stream")
async def upscale_stream(ws: WebSocket, authorized: AuthorizedDep, engine: EngineDep, limits: LimitsDep,
                         metrics: MetricsDep, sessions: UpscaleSessionsDep):
    if not await accept(ws, authorized, metrics):
        return
    limiter = rate_limiter(ws, limits)
    upscaler = None
    try:
        seq = 0
        while True:
            msg = await parse_upscale(await receive(ws, limiter, limits), engine, limits)
            if msg.session is not None:
                raise ProtocolError("a stream is one session: leave out the session field")
            if upscaler is None:  # a slot is taken only once a valid first request came: a silent stream holds none
                upscaler = sessions.open_stream()
            image, buffers, times = await run_upscale(engine, upscaler, msg)
            sessions.trim()
            h, w = msg.mask.shape
            f = engine.upscale_factor
            nbytes = len(image) if image is not None else sum(a.nbytes for a in buffers.values())
            reply = UpscaleResponse(seq=seq, width=w * f, height=h * f, output=msg.output, times=times,
                                    nbytes=nbytes, buffers=None if buffers is None else HighresBuffers(**buffers),
                                    image=image)
            await ws.send_bytes(encode(reply))
            metrics.frame("upscale", msg.output, False, times, nbytes)
            seq += 1
    except Exception as e:
        await end_ws(ws, "upscale", e, metrics)
    finally:
        if upscaler is not None:
            sessions.close_stream(upscaler)
