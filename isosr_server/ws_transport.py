"""`LimitedWebSocket`: uvicorn's WebSocket protocol (``websockets-sansio``, the one ``ws="auto"``
picks) with the limits uvicorn lacks, passed as ``ws=`` (:func:`isosr_server.app.uvicorn_options`).

uvicorn has one ``ws_max_size`` per server and counts no control frames. So before its first
message any client could declare a frame of ``max_message_bytes`` and stall, and the server held
what had come of it (megabytes a socket); and pings (each answered with a pong) cost nothing
against the message rate. Here:

* Until its first complete message a view session (``/v1/view``, whose first message is a
  small ``open``) may send frames and messages of at most ``Limits.max_first_message_bytes`` (a
  frame declaring more is refused at its header with close 1009); from the first complete
  message on, ``max_message_bytes``. The limit rises inside the frame parser as that message
  ends, so a message sent right behind it already has the large one. An upscale stream's first
  message is a frame, so its limit is ``max_message_bytes`` from the start (its sockets stay
  bounded by the connections per client). The app validates the first message (``open``, an
  upscale stream's first request) and closes a bad one; session slots are taken only after that.
* Pings and pongs draw on the connection's message budget (``max_messages_per_s``), the same token
  bucket the app draws on for every message (ASGI scope extension `LIMITER`); past it the
  connection is closed with 1008 and the reason.
"""

from __future__ import annotations

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.frames import Frame, Opcode

from isosr_server.protocol import CLOSE_POLICY, Limits
from isosr_server.sessions import RateLimiter

# The route whose first message is small (``open``): the only one with the first-message limit.
SMALL_FIRST_PATH = "/v1/view"
# The scope extension that carries the connection's `RateLimiter` (ASGI ``scope["extensions"]``).
LIMITER = "isosr.rate_limiter"
DATA_OPCODES = (Opcode.TEXT, Opcode.BINARY, Opcode.CONT)
CONTROL_OPCODES = (Opcode.PING, Opcode.PONG)
# After the server failed a connection, how long it waits for the client to end its side.
CLOSE_LINGER_S = 2.0


class LimitedWebSocket(WebSocketsSansIOProtocol):
    """The protocol class; `protocol_class` makes one with the server's limits."""

    limits: Limits = Limits()

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.limiter = RateLimiter(self.limits.max_messages_per_s)
        self.opened = False  # the first complete message came
        self.violation: str | None = None  # why the connection is to be closed with CLOSE_POLICY
        self.failed = False  # closed by close_after
        self.conn.max_message_size = min(self.limits.max_first_message_bytes, self.limits.max_message_bytes)
        parse_frame = self.conn.recv_frame

        def recv_frame(frame: Frame) -> None:  # called by the parser for each frame, before the next is read
            if frame.opcode in CONTROL_OPCODES:
                if self.violation is not None:
                    return  # no more pongs; closed once this data is parsed
                if not self.limiter.allow():
                    self.violation = (f"more than {self.limits.max_messages_per_s:g} messages (pings and pongs "
                                      f"included) a second")
                    return
            parse_frame(frame)
            if not self.opened and frame.opcode in DATA_OPCODES and frame.fin:
                self.opened = True
                self.conn.max_message_size = self.limits.max_message_bytes

        self.conn.recv_frame = recv_frame

    def handle_connect(self, event) -> None:
        super().handle_connect(event)
        if self.response.status_code == 101:
            self.scope["extensions"][LIMITER] = self.limiter  # the app's task has not run yet
            if self.scope["path"] != SMALL_FIRST_PATH:
                self.conn.max_message_size = self.limits.max_message_bytes

    def data_received(self, data: bytes) -> None:
        self.conn.receive_data(data)  # after close_after: discarded until the client's end
        if self.failed:
            return
        if self.conn.parser_exc is not None:  # e.g. a frame over the limit: 1009, queued by the parser
            close = self.conn.close_sent
            self.close_after(close.code if close else 1006, close.reason if close else "")
        elif self.violation is not None and not self.close_sent:
            peer = f"{self.client[0]}:{self.client[1]}" if self.client else "-"
            self.logger.info('%s - "WebSocket %s" closed: %d %s', peer, self.scope["path"], CLOSE_POLICY,
                             self.violation)
            self.conn.fail(CLOSE_POLICY, self.violation)
            self.close_after(CLOSE_POLICY, self.violation)
        else:
            self.handle_events()

    def close_after(self, code: int, reason: str) -> None:
        """The connection failed with ``code`` (its close frame queued): the app reads a disconnect
        (its sends fail as to a client gone), the close frame goes out with the end of our stream,
        and the transport closes when the client ends its own, or CLOSE_LINGER_S later. (uvicorn
        closes at once, and the client, still sending, gets a reset that may drop the close frame.)"""
        self.failed = True
        self.stop_keepalive()
        if self.close_timer is not None:  # the app had begun a close
            self.close_timer.cancel()
        self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = self.disconnected = True
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.close_timer = self.loop.call_later(CLOSE_LINGER_S, self.transport.close)


def protocol_class(limits: Limits) -> type[LimitedWebSocket]:
    """A `LimitedWebSocket` class bound to ``limits`` (uvicorn makes one instance per connection)."""
    return type("IsosrWebSocket", (LimitedWebSocket,), {"limits": limits})
