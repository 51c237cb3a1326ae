"""`protocol_class`: uvicorn's h11 HTTP protocol with the bounds uvicorn lacks below the app.

The `Guard` sees only whole requests; what happens before a request's head is complete is
uvicorn's, and uvicorn (0.54) leaves it open: its default parser (httptools) takes a head of any
size (a 128 MiB header cost 21 s of CPU and stalled every request); nothing bounds the number of
header fields or the time a head may take (``timeout_keep_alive`` stops counting at the first
byte of a request, and there is none for a connection's first request); nothing bounds the open
connections, so idle sockets exhaust the file descriptors and the server stops accepting. This
module's protocol, a small subclass of uvicorn's ``H11Protocol`` passed as ``http=``, adds:

- a head (request line and headers) of at most ``max_header_bytes`` (h11's
  ``max_incomplete_event_size`` while it comes, checked again once whole: a head that arrives in
  one read escapes h11's bound) and ``max_header_count`` fields: else 431 and a close;
- a deadline: a request's head must be complete within ``header_timeout_s`` of the connection,
  or of the previous response's end (keep-alive): else the connection is closed;
- at most ``max_open_connections`` open connections (WebSockets upgraded from them included),
  and fewer where the soft descriptor limit leaves less room (FD_RESERVE kept free). At the cap a
  new connection makes room by closing the oldest connection that is waiting for a request's head
  (an idle socket, or a slow one), so that idle sockets cannot lock out an honest client or the
  liveness probe; where every connection is busy with a request, the new one gets 503 and is closed.

With TLS the protocol makes the handshake itself (``loop.start_tls``) rather than leaving it to
the listening socket, so that a connection counts from its accept and its handshake runs within
the head's deadline: connections that never finish a handshake are bounded like idle sockets
(asyncio's own handshake bound, 60 s, left them uncounted that long).

Closed and refused connections are INFO lines, at most one a second per server.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import ssl
import time
from collections import OrderedDict
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import STATUS_PHRASES, H11Protocol

from isosr_server.protocol import Limits

log = logging.getLogger("isosr.server.transport")

# Seconds an idle keep-alive connection stays open (uvicorn's ``timeout_keep_alive``).
KEEP_ALIVE_S = 5
# Descriptors kept free below the soft RLIMIT_NOFILE (beyond those open at the first connection).
FD_RESERVE = 64
# At most one INFO line per this many seconds about closed or refused connections.
LOG_EVERY_S = 1.0
_REFUSAL_BODY = b'{"error": "the server holds too many connections; try later", "status": 503}'
# The answer to a connection over the cap, before it is closed.
REFUSAL = (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\ncontent-length: %d\r\n"
           b"connection: close\r\nretry-after: 1\r\n\r\n%s" % (len(_REFUSAL_BODY), _REFUSAL_BODY))


def protocol_class(limits: Limits, tls: ssl.SSLContext | None = None) -> type[BoundedH11Protocol]:
    """A `BoundedH11Protocol` class for one server (``uvicorn.Config(http=...)``): its ``limits``,
    its TLS context (None: plain HTTP; the listening socket then has none) and its own
    `Connections` (so servers in one process count apart)."""
    return type("BoundedH11Protocol", (BoundedH11Protocol,), {"limits": limits, "tls": tls,
                                                             "registry": Connections(limits)})


def open_descriptors() -> int:
    """The process's open file descriptors (0 where /proc is missing)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 0


class Connections:
    """One server's open connections: their count, those waiting for a request's head (oldest
    first), and the throttled log of what was closed or refused."""

    def __init__(self, limits: Limits) -> None:
        self.limit = limits.max_open_connections
        self._cap: int | None = None
        self.open = 0
        self.waiting: OrderedDict[BoundedH11Protocol, None] = OrderedDict()
        self.events: dict[str, int] = {}
        self.last_log = float("-inf")
        self.flush_pending = False

    @property
    def cap(self) -> int:
        """``limit``, or less where the soft descriptor limit leaves less room (fixed at the first connection)."""
        if self._cap is None:
            soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
            room = self.limit if soft == resource.RLIM_INFINITY else soft - open_descriptors() - FD_RESERVE
            self._cap = max(1, min(self.limit, room))
            if self._cap < self.limit:
                log.info("at most %d open connections (max_open_connections %d): the descriptor limit is %d",
                         self._cap, self.limit, soft)
        return self._cap

    def make_room(self) -> bool:
        """Below the cap, or a waiting connection (the oldest) closed to get there: whether one more may open."""
        if self.open < self.cap:
            return True
        if not self.waiting:
            return False
        oldest = next(iter(self.waiting))
        oldest.drop("closed_for_room")
        return True

    def note(self, event: str, loop) -> None:
        """Count ``event`` for the next INFO line (at most one per LOG_EVERY_S)."""
        self.events[event] = self.events.get(event, 0) + 1
        wait = self.last_log + LOG_EVERY_S - time.monotonic()
        if wait <= 0:
            self.flush()
        elif not self.flush_pending:
            self.flush_pending = True
            loop.call_later(wait, self.flush)

    def flush(self) -> None:
        self.flush_pending = False
        if not self.events:
            return
        self.last_log = time.monotonic()
        words = {"refused": "refused with 503 (every one busy)",
                 "closed_for_room": "closed to make room (waiting for a request head)",
                 "header_timeout": "closed (no complete request head within header_timeout_s)",
                 "too_big": "answered 431 (request head over max_header_bytes or max_header_count)"}
        log.info("HTTP connections: %s; %d open, cap %d", "; ".join(f"{n} {words[e]}" for e, n in self.events.items()),
                 self.open, self.cap)
        self.events.clear()


class HeadBoundedConnection(h11.Connection):
    """h11's server side that also bounds the header count, and hands a head over either bound
    to ``on_refusal(reason)`` (which answers 431 and closes) rather than raising: uvicorn would
    log a WARNING for each."""

    def __init__(self, max_bytes: int, max_count: int, on_request, on_refusal) -> None:
        super().__init__(h11.SERVER, max_incomplete_event_size=max_bytes)
        self.max_bytes, self.max_count, self.on_request, self.on_refusal = max_bytes, max_count, on_request, on_refusal

    def next_event(self) -> Any:
        try:
            event = super().next_event()
        except h11.RemoteProtocolError as e:
            if e.error_status_hint != 431:
                raise
            self.on_refusal(f"the request head exceeds {self.max_bytes} bytes")
            return h11.NEED_DATA  # uvicorn reads no further; the connection is closing
        if isinstance(event, h11.Request):
            self.on_request()
            if len(event.headers) > self.max_count:
                self.on_refusal(f"the request has {len(event.headers)} header fields, more than {self.max_count}")
                return h11.NEED_DATA
            # h11 bounds only a head still incomplete: one that came whole in a read (or pipelined) may be larger.
            size = len(event.method) + len(event.target) + 12 + sum(len(n) + len(v) + 4 for n, v in event.headers)
            if size > self.max_bytes:
                self.on_refusal(f"the request head exceeds {self.max_bytes} bytes")
                return h11.NEED_DATA
        return event


class BoundedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol under the head, deadline and connection bounds (module docstring);
    made per server by `protocol_class`."""

    limits: Limits
    tls: ssl.SSLContext | None
    registry: Connections

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.conn = HeadBoundedConnection(self.limits.max_header_bytes, self.limits.max_header_count,
                                          self.on_request, self.refuse_head)
        self.counted = False  # in registry.open
        self.made = False  # uvicorn's connection_made done (with TLS: after the handshake)
        self.early: list[bytes] = []  # TLS: what the client sent before that
        self.deadline: Any = None  # the header deadline's timer while waiting for a head

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport  # until the handshake ends, the TCP connection (closed by the deadline)
        if not self.registry.make_room():
            self.registry.note("refused", self.loop)
            transport.write(REFUSAL)  # plain HTTP even to a TLS client: it reads a failed handshake
            transport.close()
            return
        self.registry.open += 1
        self.counted = True
        self.await_head()  # with TLS, the handshake counts toward the head's deadline
        if self.tls is None:
            self.made_on(transport)
        else:
            transport.pause_reading()  # the handshake's bytes are the TLS layer's, not h11's
            self.loop.create_task(self.handshake(transport))

    async def handshake(self, transport) -> None:
        """The TLS handshake, bounded by the head's deadline (and its closing to make room)."""
        try:
            secure = await self.loop.start_tls(transport, self, self.tls, server_side=True,
                                               ssl_handshake_timeout=self.limits.header_timeout_s)
        except Exception:  # noqa: BLE001 - failed, stalled or closed by a bound: the client's, never an error here
            secure = None
        if secure is None:  # (None: the connection was lost between the handshake's end and this task going on)
            self.release()  # no connection_lost comes for a connection whose handshake failed
            transport.abort()
            return
        self.made_on(secure)

    def made_on(self, transport) -> None:
        super().connection_made(transport)
        self.made = True
        for data in self.early:
            super().data_received(data)
        self.early.clear()

    def data_received(self, data: bytes) -> None:
        if self.made:
            super().data_received(data)
        else:  # a request that came with the handshake's end, before the handshake's task went on
            self.early.append(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.release()
        if self.made:
            super().connection_lost(exc)

    def release(self) -> None:
        """This connection no longer counts against the cap."""
        self.stop_waiting()
        if self.counted:
            self.counted = False
            self.registry.open -= 1

    def await_head(self) -> None:
        """Start the header deadline; the connection may be closed to make room until its head is complete."""
        self.stop_waiting()
        self.deadline = self.loop.call_later(self.limits.header_timeout_s, self.header_timeout)
        self.registry.waiting[self] = None

    def stop_waiting(self) -> None:
        if self.deadline is not None:
            self.deadline.cancel()
            self.deadline = None
        self.registry.waiting.pop(self, None)

    def on_request(self) -> None:
        """A request's head is complete."""
        self.stop_waiting()

    def header_timeout(self) -> None:
        """Close the connection; it counts (and may be closed at once to make room) until its
        previous response is flushed to a slow reader and the socket is gone."""
        self.deadline = None
        self.registry.note("header_timeout", self.loop)
        self.transport.close()

    def drop(self, event: str) -> None:
        """Close this connection at once (it waits for a head) to make room."""
        self.registry.note(event, self.loop)
        self.release()
        self.transport.abort()

    def on_response_complete(self) -> None:
        if not self.transport.is_closing():
            self.await_head()  # the next head (and the rest of this request's body) within the deadline
        super().on_response_complete()

    def handle_websocket_upgrade(self, event: h11.Request) -> None:
        super().handle_websocket_upgrade(event)
        websocket = self.transport.get_protocol()
        if websocket is self or not self.counted:
            return
        lost = websocket.connection_lost

        def connection_lost(exc: Exception | None) -> None:
            self.release()
            lost(exc)

        websocket.connection_lost = connection_lost  # the WebSocket keeps this connection's place in the count

    def refuse_head(self, reason: str) -> None:
        """Answer 431 with ``{"error": reason, "status": 431}`` and close; only close where a
        response is under way (a chunk's size line over the limit mid-body): the app then reads
        ``http.disconnect``."""
        self.registry.note("too_big", self.loop)
        in_request = self.cycle is not None and not self.cycle.response_complete
        if not in_request and self.conn.our_state in (h11.IDLE, h11.SEND_RESPONSE):
            body = json.dumps({"error": reason, "status": 431}).encode()
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                       (b"connection", b"close")]
            for event in (h11.Response(status_code=431, headers=headers, reason=STATUS_PHRASES[431]),
                          h11.Data(data=body), h11.EndOfMessage()):
                self.transport.write(self.conn.send(event))
        self.transport.close()
