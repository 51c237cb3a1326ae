"""`Guard`: the ASGI middleware that bounds what clients hold on the server before the app sees
them. Pure ASGI: it never buffers a body. Every bound is a `Limits` field.

Connections
    HTTP requests and WebSockets in progress, in total (``max_connections``) and per client
    address (``max_connections_per_client``); the health probes (`HEALTH_PATHS`) are not
    counted and always answered. Over either bound an HTTP request gets 503 with
    ``{"error": reason, "status": 503}``, ``Retry-After`` and ``Connection: close``; a WebSocket
    is accepted and closed at once with CLOSE_TOO_MANY and the reason. (A ``websocket.close``
    before the accept becomes an HTTP 403 handshake denial in uvicorn, which a browser reports as
    1006 without code or reason; the app's token check accepts first for the same reason.)

Request bodies
    A body must arrive within ``body_timeout_s`` of its request (408, and the connection is
    closed) and stay within ``max_message_bytes`` (413: by Content-Length before a byte is read,
    or once the bytes read pass it). A body over the limit by at most DRAIN_FACTOR times is read
    to its end and dropped, within the same deadline, before the 413, so that a client that
    sends its whole body before reading (most do) gets the answer rather than a reset; a bigger
    one, or one whose client waits for ``100 Continue``, is answered at once. The bodies one
    client address has in flight (each counted from its request to its end: the declared
    length, or the bytes read so far where none is declared) stay within CLIENT_BODY_FACTOR
    times ``max_message_bytes``; a body past that gets 503 and Retry-After. Whichever bound a
    body breaks, the app reads ``http.disconnect`` and the guard answers in its place (unless
    the app's answer has begun).

WebSockets
    The first message (a view session's ``open``) must arrive within ``open_timeout_s`` of the
    connection; else the guard closes it with CLOSE_IDLE and the app reads
    ``websocket.disconnect``. A WebSocket past its first message is a session: one client
    address holds at most ``max_sessions_per_client`` (view sessions and upscale streams alike);
    more are closed with CLOSE_TOO_MANY. The app closes a connection whose first message is not
    valid at once (so it counts no longer than that takes) and takes its own slots (the server's
    ``max_sessions``) only after a valid one; until then the WebSocket protocol
    (:mod:`isosr_server.ws_transport`) bounds its frames by ``max_first_message_bytes``. After the
    guard closed a WebSocket the app's sends raise OSError, as for a client gone.

Logging: client mistakes (a late or oversized body, a client gone mid-body, a busy server) are
INFO lines, never ERROR. The client address is the connection's peer (``scope["client"]``):
behind a proxy, the proxy's.
"""

from __future__ import annotations

import asyncio
import json
import logging
from contextlib import suppress
from dataclasses import dataclass

from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from isosr_server.protocol import CLOSE_IDLE, CLOSE_TOO_MANY, SUBPROTOCOL, Limits

log = logging.getLogger("isosr.server.guard")

RETRY_AFTER_S = 1
# An oversized body up to this many times max_message_bytes is read and dropped before the 413.
DRAIN_FACTOR = 2
# The bodies one client address has in flight stay within this many times max_message_bytes.
CLIENT_BODY_FACTOR = 2
HTTP_DISCONNECT: Message = {"type": "http.disconnect"}
# Bodiless GETs that answer from memory: never turned away by the connection bounds, so that an
# orchestrator sees the process alive and ready while clients fill the server (the transport's
# open-connection cap and head limits still bound them).
HEALTH_PATHS = frozenset({"/v2/health/live", "/v2/health/ready"})


@dataclass
class ClientLoad:
    """What one client address holds now."""

    connections: int = 0
    sessions: int = 0
    body_bytes: int = 0

    def empty(self) -> bool:
        return not (self.connections or self.sessions or self.body_bytes)


class Guard:
    """The middleware: ``app.add_middleware(Guard, limits=limits)``.

    Attributes:
        connections: HTTP requests and WebSockets in progress.
        clients: the load of every client address that holds something (none left when idle).
    """

    def __init__(self, app: ASGIApp, limits: Limits) -> None:
        self.app, self.limits = app, limits
        self.connections = 0
        self.clients: dict[str, ClientLoad] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket") or (scope["type"] == "http" and scope["path"] in HEALTH_PATHS
                                                          and scope["method"] == "GET"):
            await self.app(scope, receive, send)
            return
        client = client_address(scope)
        load = self.clients.setdefault(client, ClientLoad())
        try:
            if load.connections >= self.limits.max_connections_per_client:
                await turn_away(scope, receive, send, f"{client} holds {load.connections} connections; try later")
                return
            if self.connections >= self.limits.max_connections:
                await turn_away(scope, receive, send, f"the server holds {self.connections} connections; try later")
                return
            self.connections += 1
            load.connections += 1
            try:
                exchange = HttpExchange if scope["type"] == "http" else WebSocketExchange
                await exchange(self, client, load, scope, receive, send).run()
            finally:
                self.connections -= 1
                load.connections -= 1
        finally:
            if load.empty() and self.clients.get(client) is load:
                del self.clients[client]


class HttpExchange:
    """One HTTP request under the body bounds (module docstring)."""

    def __init__(self, guard: Guard, client: str, load: ClientLoad, scope: Scope, receive: Receive, send: Send):
        self.app, self.limits, self.client, self.load = guard.app, guard.limits, client, load
        self.scope, self._receive, self._send = scope, receive, send
        self.deadline = asyncio.get_running_loop().time() + self.limits.body_timeout_s
        self.declared = content_length(scope)
        self.received = 0  # body bytes read
        self.held = 0  # bytes counted in load.body_bytes
        self.body_done = False
        self.refusal: tuple[int, str] | None = None  # the guard's answer in place of the app's
        self.answered = False  # the app's answer has begun

    async def run(self) -> None:
        try:
            limit = self.limits.max_message_bytes
            if self.declared is not None and self.declared > limit:
                self.refuse(413, f"body of {self.declared} bytes exceeds the limit of {limit} bytes")
            elif self.declared is not None:
                self.hold(self.declared)
            if self.refusal is None:
                try:
                    await self.app(self.scope, self.receive, self.send)
                except ClientDisconnect:  # the app read http.disconnect mid-body
                    if self.refusal is None:
                        log.info("%s %s from %s: the client left after %d body bytes", self.scope["method"],
                                 self.scope["path"], self.client, self.received)
            if self.refusal is not None and not self.answered:
                if self.refusal[0] == 413:
                    await self.drain()
                await respond(self._send, *self.refusal)
        finally:
            self.load.body_bytes -= self.held

    def refuse(self, status: int, reason: str) -> Message:
        """Answer ``status`` in place of the app; what the app reads from now on."""
        if self.refusal is None:
            self.refusal = (status, reason)
            log.info("%s %s from %s: %d %s", self.scope["method"], self.scope["path"], self.client, status, reason)
        return HTTP_DISCONNECT

    def hold(self, size: int) -> None:
        """Count ``size`` more bytes against the client's bodies in flight (a 503 past the bound)."""
        bound = CLIENT_BODY_FACTOR * self.limits.max_message_bytes
        if self.load.body_bytes + size > bound:
            self.refuse(503, f"bodies from {self.client} in flight exceed {bound} bytes; try later")
        else:
            self.load.body_bytes += size
            self.held += size

    async def receive(self) -> Message:
        if self.refusal is not None:
            return HTTP_DISCONNECT
        if self.body_done:
            return await self._receive()
        try:
            async with asyncio.timeout_at(self.deadline):
                message = await self._receive()
        except TimeoutError:
            return self.refuse(408, f"the body did not arrive within {self.limits.body_timeout_s:g} s")
        if message["type"] != "http.request":
            return message
        self.received += len(message.get("body", b""))
        self.body_done = not message.get("more_body", False)
        if self.received > self.limits.max_message_bytes:
            return self.refuse(413, f"body exceeds the limit of {self.limits.max_message_bytes} bytes")
        if self.received > self.held:
            self.hold(self.received - self.held)
        return message if self.refusal is None else HTTP_DISCONNECT

    async def send(self, message: Message) -> None:
        if self.refusal is not None and not self.answered:
            return  # the guard answers; the app's answer (if any) goes nowhere, as to a client gone
        self.answered = True
        await self._send(message)

    async def drain(self) -> None:
        """Read an oversized body on and drop it, as far as DRAIN_FACTOR x the limit and the deadline allow."""
        bound = DRAIN_FACTOR * self.limits.max_message_bytes
        waits = self.received == 0 and any(name == b"expect" and value.lower() == b"100-continue"
                                           for name, value in self.scope["headers"])
        if waits or (self.declared is not None and self.declared > bound):
            return
        with suppress(TimeoutError):
            async with asyncio.timeout_at(self.deadline):
                while not self.body_done and self.received <= bound:
                    message = await self._receive()
                    if message["type"] != "http.request":
                        return
                    self.received += len(message.get("body", b""))
                    self.body_done = not message.get("more_body", False)


class WebSocketExchange:
    """One WebSocket under the first-message deadline and the sessions bound (module docstring)."""

    def __init__(self, guard: Guard, client: str, load: ClientLoad, scope: Scope, receive: Receive, send: Send):
        self.app, self.limits, self.client, self.load = guard.app, guard.limits, client, load
        self.scope, self._receive, self._send = scope, receive, send
        self.deadline = asyncio.get_running_loop().time() + self.limits.open_timeout_s
        self.opened = False  # the first message came
        self.session = False  # counted in load.sessions
        self.closed: int | None = None  # the close code the guard sent

    async def run(self) -> None:
        try:
            await self.app(self.scope, self.receive, self.send)
        finally:
            if self.session:
                self.load.sessions -= 1

    async def receive(self) -> Message:
        if self.closed is not None:
            return {"type": "websocket.disconnect", "code": self.closed}
        if self.opened:
            return await self._receive()
        try:
            async with asyncio.timeout_at(self.deadline):
                message = await self._receive()
        except TimeoutError:
            return await self.close(CLOSE_IDLE, f"no first message within {self.limits.open_timeout_s:g} s")
        if message["type"] == "websocket.receive":
            self.opened = True
            if self.load.sessions >= self.limits.max_sessions_per_client:
                return await self.close(CLOSE_TOO_MANY, f"{self.client} holds {self.load.sessions} sessions; "
                                                        f"try later")
            self.load.sessions += 1
            self.session = True
        return message

    async def send(self, message: Message) -> None:
        if self.closed is not None:
            raise OSError(f"the guard closed this WebSocket ({self.closed})")
        await self._send(message)

    async def close(self, code: int, reason: str) -> Message:
        """Close the WebSocket with ``code``; what the app reads from now on."""
        log.info("WebSocket %s from %s closed: %d %s", self.scope["path"], self.client, code, reason)
        self.closed = code
        with suppress(OSError):  # the client went away meanwhile
            await self._send({"type": "websocket.close", "code": code, "reason": reason})
        return {"type": "websocket.disconnect", "code": code}


def client_address(scope: Scope) -> str:
    """The peer's address (``-`` where the server knows none, e.g. a Unix socket)."""
    client = scope.get("client")
    return client[0] if client else "-"


def content_length(scope: Scope) -> int | None:
    """The declared body length (None: none, or not a number; h11 refuses such requests before us)."""
    for name, value in scope["headers"]:
        if name == b"content-length":
            return int(value) if value.isdigit() else None
    return None


async def turn_away(scope: Scope, receive: Receive, send: Send, reason: str) -> None:
    """Turn a connection away before the app sees it: HTTP 503, or a WebSocket closed with CLOSE_TOO_MANY."""
    log.info("%s %s from %s refused: %s", scope.get("method", "WebSocket"), scope["path"], client_address(scope),
             reason)
    if scope["type"] == "http":
        await respond(send, 503, reason)
        return
    offered = [p.strip() for name, value in scope["headers"] if name == b"sec-websocket-protocol"
               for p in value.decode("latin-1").split(",")]
    with suppress(OSError):  # the client went away meanwhile
        await receive()  # websocket.connect
        await send({"type": "websocket.accept", "subprotocol": SUBPROTOCOL if SUBPROTOCOL in offered else None})
        await send({"type": "websocket.close", "code": CLOSE_TOO_MANY, "reason": reason})


async def respond(send: Send, status: int, reason: str) -> None:
    """A JSON error answer (``{"error": reason, "status": status}``) that closes the connection."""
    body = json.dumps({"error": reason, "status": status}).encode()
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
               (b"connection", b"close")]
    if status == 503:
        headers.append((b"retry-after", str(RETRY_AFTER_S).encode()))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})
