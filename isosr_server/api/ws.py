"""WebSocket plumbing of the streaming routes: the handshake with the token check, a bounded
receive, and the close after an error (an ``error`` message, then the close code and reason)."""

from __future__ import annotations

import asyncio
import logging

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import (CLOSE_IDLE, CLOSE_INTERNAL, CLOSE_POLICY, CLOSE_UNAUTHORIZED, SUBPROTOCOL,
                                   ErrorMsg, Limits, ProtocolError, encode)
from isosr_server.sessions import RateLimiter
from isosr_server.ws_transport import LIMITER

log = logging.getLogger("isosr.server")


async def accept(ws: WebSocket, authorized: bool, metrics: ServerMetrics) -> bool:
    """Accept the handshake; unless ``authorized`` close it at once with CLOSE_UNAUTHORIZED and the reason."""
    await ws.accept(subprotocol=SUBPROTOCOL if SUBPROTOCOL in ws.scope.get("subprotocols", ()) else None)
    if authorized:
        return True
    await end_ws(ws, "auth", ProtocolError("missing or wrong token", CLOSE_UNAUTHORIZED, 401), metrics)
    return False


def rate_limiter(ws: WebSocket, limits: Limits) -> RateLimiter:
    """The connection's message budget: the one its pings and pongs draw on too (the scope extension
    of :mod:`isosr_server.ws_transport`), or a new one where the server has none (another ASGI server)."""
    limiter = ws.scope.get("extensions", {}).get(LIMITER)
    return limiter if isinstance(limiter, RateLimiter) else RateLimiter(limits.max_messages_per_s)


async def receive(ws: WebSocket, limiter: RateLimiter, limits: Limits) -> bytes:
    """The next binary message within the idle timeout and the rate limit."""
    try:
        message = await asyncio.wait_for(ws.receive(), limits.idle_timeout_s)
    except TimeoutError:
        raise ProtocolError(f"no message for {limits.idle_timeout_s:g} s", CLOSE_IDLE, 408) from None
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000))
    if not limiter.allow():
        raise ProtocolError(f"more than {limits.max_messages_per_s:g} messages a second", CLOSE_POLICY, 429)
    if message.get("bytes") is None:
        raise ProtocolError("text messages are not part of the protocol: send binary msgpack")
    return message["bytes"]


async def end_ws(ws: WebSocket, kind: str, e: BaseException, metrics: ServerMetrics) -> None:
    """Close a WebSocket after an error: an error message and a close code with the reason.
    Client mistakes (`ProtocolError`) log at INFO, anything else at ERROR as a server fault."""
    if isinstance(e, WebSocketDisconnect):
        return
    if isinstance(e, ProtocolError):
        code, reason = e.close_code, e.reason
        log.info("%s session closed: %d %s", kind, code, reason)
    else:
        code, reason = CLOSE_INTERNAL, "internal server error"
        log.error("%s session failed", kind, exc_info=e)
    metrics.error(kind, code)
    if ws.application_state == WebSocketState.CONNECTED and ws.client_state == WebSocketState.CONNECTED:
        try:
            await ws.send_bytes(encode(ErrorMsg(code, reason)))
            await ws.close(code, close_reason(reason))
        except Exception:  # the client went away meanwhile
            pass


def close_reason(reason: str) -> str:
    """A close reason within the 123 bytes a close frame allows."""
    return reason.encode()[:120].decode(errors="ignore")
