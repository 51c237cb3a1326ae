"""WebSocket limits below the application (:mod:`isosr_server.ws_transport`, issue 45), against a
real `isosr serve` subprocess on loopback (CPU, procedural volumes), from raw sockets and clients
on several loopback addresses: the small frame limit before the first message (1009 at the header,
no server memory), the large one after it, pings counted in the message rate, upscale-stream slots
taken only after a valid first request, and the close of a view session that never acknowledges.

Every loop is bounded in count and time; no test asserts a duration.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from contextlib import ExitStack

import msgspec
import pytest
from test_attacks import Reader, assert_no_errors, dial, get, serve
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection
from websockets.sync.client import connect as ws_connect

from isosr_server import protocol as P

MiB = 2**20
VOLUME = "proc:torus@32"
CLIENT_LIMITS = P.Limits(max_message_bytes=2**28)
SERVER_MESSAGES = dict(P.SERVER_VIEW_MESSAGES, upscaled=P.UpscaleResponse)
# Small bounds, so that each limit shows in seconds.
LIMITS = {"max_message_bytes": 32 * MiB, "max_first_message_bytes": 64 * 2**10, "max_messages_per_s": 50,
          "max_sessions": 4, "ack_timeout_s": 3, "open_timeout_s": 30}
# Server RSS that 16 sockets declaring 32 MiB frames before their first message may add.
RSS_GOAL = 8 * MiB


@pytest.fixture(scope="module")
def server():
    with serve(LIMITS) as s:
        yield s


def handshake(server, source: str, path: str, stack: ExitStack) -> socket.socket:
    """A raw WebSocket to ``path`` from ``source`` past its handshake (closed with ``stack``)."""
    sock = stack.enter_context(dial(server, source, timeout=30))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 f"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    return sock


def frame_head(length: int, opcode: int = 0x2) -> bytes:
    """A client frame's header declaring ``length`` payload bytes (masked with a zero key: the payload goes as is)."""
    if length < 126:
        size = bytes([0x80 | length])
    elif length < 2**16:
        size = bytes([0x80 | 126]) + length.to_bytes(2, "big")
    else:
        size = bytes([0x80 | 127]) + length.to_bytes(8, "big")
    return bytes([0x80 | opcode]) + size + bytes(4)


def client(server, source: str, path: str = "/v1/view") -> ClientConnection:
    return ws_connect(f"ws://127.0.0.1:{server.port}{path}", sock=dial(server, source, 30), proxy=None,
                      max_size=CLIENT_LIMITS.max_message_bytes, compression=None, open_timeout=30, close_timeout=2)


def recv(ws: ClientConnection, timeout: float = 60) -> P.Message:
    return P.parse(ws.recv(timeout=timeout), CLIENT_LIMITS, SERVER_MESSAGES)


def open_view(ws: ClientConnection) -> None:
    """``open`` -> ``ready`` and the first frame, acknowledged."""
    ws.send(P.encode(P.OpenMsg(volume=VOLUME, settings=P.SettingsUpdate(mode="full", width=32, height=24,
                                                                          refine=False))))
    assert isinstance(recv(ws), P.ReadyMsg)
    first = recv(ws)
    assert isinstance(first, P.FrameMsg), first
    ws.send(P.encode(P.ReceivedMsg(first.seq)))


def camera(seq: int) -> bytes:
    return P.encode(P.CameraMsg(yaw=float(30 + seq), pitch=20.0, distance=1.8, seq=seq))


def closed_by_server(ws: ClientConnection, messages: int = 50) -> ConnectionClosed:
    """Reads (and acknowledges) what the server still sends until it closes; its close."""
    for _ in range(messages):
        try:
            msg = recv(ws, timeout=30)
        except ConnectionClosed as e:
            assert e.rcvd is not None, e
            return e
        if isinstance(msg, P.FrameMsg):
            try:
                ws.send(P.encode(P.ReceivedMsg(msg.seq)))
            except ConnectionClosed:
                pass
    raise AssertionError("the server did not close")


def upscale_request(h: int, w: int) -> bytes:
    """An upscale request of an ``h`` x ``w`` frame of zeros (float32), output jpeg."""
    arrays = {"mask": (h, w), "normal": (h, w, 3), "depth": (h, w)}
    wire = {n: {"dtype": "float32", "shape": list(shape), "data": bytes(4 * math.prod(shape))}
            for n, shape in arrays.items()}
    return msgspec.msgpack.encode({"type": "upscale", "version": P.PROTOCOL_VERSION, "output": "jpeg", **wire})


# ---- the frame limit before and after the first message -----------------------------------------


def test_a_32_mib_frame_before_open_is_refused_and_holds_no_memory(server):
    """16 sockets (four addresses) declare a 32 MiB frame (within max_message_bytes) before any message
    and send 2 MiB of it: each is closed with 1009 at the header (or dropped), and the server's RSS
    stays put (uvicorn alone would hold the 32 MiB they sent)."""
    assert get(server, "127.0.0.1")[0] == 200
    base = server.rss()
    outcomes = []
    with ExitStack() as stack:
        socks = [handshake(server, f"127.0.4.{1 + k // 4}", "/v1/view", stack) for k in range(16)]
        for sock in socks:
            assert Reader(sock).head()[0] == 101
            try:
                sock.sendall(frame_head(32 * MiB))
                for _ in range(2):
                    sock.sendall(bytes(MiB))
            except OSError:  # refused and closed by the server
                pass
        growth = server.rss() - base
        for sock in socks:
            sock.settimeout(10)
            try:
                outcomes.append(Reader(sock).close_code()[0])
            except (OSError, ConnectionError):
                outcomes.append("dropped")
    print(f"\n16 sockets declaring 32 MiB before open: server RSS growth {growth / MiB:.1f} MiB; {outcomes}")
    assert all(o in (P.CLOSE_TOO_BIG, "dropped") for o in outcomes), outcomes
    assert growth < RSS_GOAL
    assert get(server, "127.0.0.1")[0] == 200
    assert_no_errors(server)


def test_after_a_valid_first_message_messages_up_to_max_message_bytes_are_taken(server):
    big = upscale_request(96, 128)  # ~240 KB: past the first-message limit, within max_message_bytes
    assert LIMITS["max_first_message_bytes"] < len(big) < LIMITS["max_message_bytes"]
    # An upscale stream: a small first request, then the big one right behind it (not waiting for the answer).
    with client(server, "127.0.4.10", "/v1/upscale/stream") as ws:
        ws.send(upscale_request(8, 8))
        ws.send(big)
        answers = [recv(ws), recv(ws)]
        assert [(a.seq, a.width, a.height) for a in answers] == [(0, 32, 32), (1, 512, 384)], answers
    # The same big request as a stream's first message: an upscale stream's first message is a frame.
    with client(server, "127.0.4.10", "/v1/upscale/stream") as ws:
        ws.send(big)
        assert recv(ws).seq == 0
    # A view session's first message over the first-message limit: refused at its header.
    with client(server, "127.0.4.10") as ws:
        try:
            ws.send(big)
        except ConnectionClosed:
            pass
        assert closed_by_server(ws).rcvd.code == P.CLOSE_TOO_BIG
    # A view session: past open, a message over the first limit reaches the app (a bad message: 1007),
    # and one over max_message_bytes is refused at its header (1009).
    with client(server, "127.0.4.10") as ws:
        open_view(ws)
        ws.send(bytes([0xC1]) * (200 * 2**10))
        assert closed_by_server(ws).rcvd.code == P.CLOSE_BAD_MESSAGE
    with client(server, "127.0.4.10") as ws:
        open_view(ws)
        try:
            ws.send(bytes(LIMITS["max_message_bytes"] + 1))
        except ConnectionClosed:
            pass
        assert closed_by_server(ws).rcvd.code == P.CLOSE_TOO_BIG
    assert_no_errors(server)


# ---- pings count as messages --------------------------------------------------------------------


def test_a_ping_flood_closes_its_session_while_another_goes_on(server):
    with client(server, "127.0.4.20") as honest, client(server, "127.0.4.21") as flood:
        open_view(honest)
        open_view(flood)
        closed = None
        for i in range(5000):  # 100 x the rate limit
            try:
                flood.ping(struct.pack("!I", i))
            except ConnectionClosed as e:
                closed = e
                break
        closed = closed_by_server(flood) if closed is None or closed.rcvd is None else closed
        assert closed.rcvd.code == P.CLOSE_POLICY and "pings and pongs" in closed.rcvd.reason, closed
        assert get(server, "127.0.0.1")[0] == 200
        for seq in range(1, 6):  # the honest session still gets a frame for each camera
            honest.send(camera(seq))
            for _ in range(10):
                msg = recv(honest)
                if isinstance(msg, P.FrameMsg):
                    honest.send(P.encode(P.ReceivedMsg(msg.seq)))
                    if msg.ack == seq:
                        break
            else:
                raise AssertionError(f"no frame for camera {seq}")
    assert_no_errors(server)


# ---- upscale-stream slots -----------------------------------------------------------------------


def test_silent_upscale_streams_take_no_slot(server):
    """As many silent upscale streams as there are slots (from two addresses); then a stream that
    sends a valid first request gets an answer, and so does a view session."""
    with ExitStack() as stack:
        silent = [handshake(server, f"127.0.4.{30 + k % 2}", "/v1/upscale/stream", stack)
                  for k in range(LIMITS["max_sessions"])]
        for sock in silent:
            assert Reader(sock).head()[0] == 101
        with client(server, "127.0.4.32", "/v1/upscale/stream") as ws:
            ws.send(upscale_request(8, 8))
            answer = recv(ws)
            assert isinstance(answer, P.UpscaleResponse) and answer.seq == 0, answer
        with client(server, "127.0.4.32") as ws:
            open_view(ws)
        for sock in silent:  # still open: they were not turned away, they just hold nothing
            sock.setblocking(False)
            with pytest.raises(BlockingIOError):
                sock.recv(1)
    assert_no_errors(server)


# ---- sessions that never acknowledge ------------------------------------------------------------


def test_a_session_that_never_acknowledges_is_closed_while_an_acknowledging_one_goes_on(server):
    timeout = LIMITS["ack_timeout_s"]
    with client(server, "127.0.4.40") as honest, client(server, "127.0.4.41") as silent:
        open_view(honest)
        silent.send(P.encode(P.OpenMsg(volume=VOLUME, settings=P.SettingsUpdate(mode="full", width=32, height=24,
                                                                              refine=False))))
        assert isinstance(recv(silent), P.ReadyMsg)
        # The honest session moves its camera and acknowledges every frame, for 3 x the ack timeout.
        frames, seq, start = 0, 0, time.monotonic()
        for _ in range(1000):
            if time.monotonic() - start > 3 * timeout:
                break
            seq += 1
            honest.send(camera(seq))
            for _ in range(10):
                msg = recv(honest)
                if isinstance(msg, P.FrameMsg):
                    honest.send(P.encode(P.ReceivedMsg(msg.seq)))
                    frames += 1
                    if msg.ack == seq:
                        break
            time.sleep(0.1)
        assert frames >= seq
        # The other read its frame but never acknowledged it: closed with the reason.
        msgs = []
        for _ in range(20):
            try:
                msgs.append(recv(silent, timeout=30))
            except ConnectionClosed as e:
                closed = e
                break
        else:
            raise AssertionError("the session that never acknowledges was not closed")
        assert isinstance(msgs[0], P.FrameMsg)
        errors = [m for m in msgs if isinstance(m, P.ErrorMsg)]
        assert errors and errors[0].code == P.CLOSE_IDLE and "was not acknowledged" in errors[0].reason, msgs
        assert closed.rcvd is not None and closed.rcvd.code == P.CLOSE_IDLE and "ack_timeout_s" in closed.rcvd.reason
        # The honest one goes on.
        honest.send(camera(seq + 1))
        for _ in range(10):
            msg = recv(honest)
            if isinstance(msg, P.FrameMsg) and msg.ack == seq + 1:
                break
        else:
            raise AssertionError("the honest session got no frame")
    assert_no_errors(server)
