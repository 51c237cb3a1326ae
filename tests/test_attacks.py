"""Attacks on a real `isosr serve` subprocess on loopback (CPU, procedural volumes), from raw
sockets: stalled uploads (server memory), clients leaving mid-body (no ERROR lines), silent
WebSockets (view slots), connections over the per-address and total bounds, zlib bombs (server
memory, liveness) and upscale session ids (upscale slots).

Every client binds its own loopback address (127.0.0.0/8 all reaches the server on Linux), so
per-address bounds are tested with several addresses. Every wait is bounded.
"""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
import zlib
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import msgspec
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect as ws_connect

from isosr_bench.bench_server import ServerProcess
from isosr_server import protocol as P

MiB = 2**20
# Server RSS that four clients looping zlib bombs for a few seconds may add.
BOMB_RSS_GOAL = 160 * MiB
# Server RSS that eight stalled 32 MiB uploads may add, 15 s after they stall (the goal; the tests
# stall eight more within the limit alongside).
RSS_GOAL = 96 * MiB
VOLUME = "proc:torus@32"
CLIENT_LIMITS = P.Limits(max_message_bytes=2**28)
# The tight server: short deadlines and small bounds, so that each attack's effect shows in seconds.
TIGHT = {"body_timeout_s": 5, "open_timeout_s": 2, "max_connections": 48, "max_connections_per_client": 8,
         "max_sessions_per_client": 2}


def flags(limits: dict) -> tuple[str, ...]:
    """`isosr serve` options for Limits fields (one ``--name`` flag per field)."""
    return tuple(a for name, value in limits.items() for a in ("--" + name.replace("_", "-"), str(value)))


@contextmanager
def serve(limits: dict) -> Iterator[ServerProcess]:
    """A server logging at INFO (its stderr is kept: see `server_log`)."""
    with ServerProcess("cpu", extra_args=("--log-level", "info", *flags(limits))) as server:
        yield server


@pytest.fixture(scope="module")
def tight():
    with serve(TIGHT) as server:
        yield server


@pytest.fixture(scope="module")
def default():
    with serve({}) as server:
        yield server


def server_log(server: ServerProcess) -> str:
    """The server's stderr so far (read without moving the file offset the server writes at)."""
    fd = server.log.fileno()
    return os.pread(fd, os.fstat(fd).st_size, 0).decode(errors="replace")


def assert_no_errors(server: ServerProcess) -> None:
    text = server_log(server)
    bad = [line for line in text.splitlines() if " ERROR " in line or line.startswith("ERROR") or "Traceback" in line]
    assert not bad, text[-3000:]


def dial(server: ServerProcess, source: str, timeout: float = 10.0) -> socket.socket:
    """A TCP connection to the server from loopback address ``source``."""
    return socket.create_connection(("127.0.0.1", server.port), timeout=timeout, source_address=(source, 0))


def post_head(declared: int, path: str = "/v1/upscale") -> bytes:
    return (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {P.MSGPACK_MEDIA_TYPE}\r\n"
            f"Content-Length: {declared}\r\n\r\n").encode()


def stalled_upload(server: ServerProcess, source: str, declared: int, sent: int) -> socket.socket:
    """A POST /v1/upscale declaring ``declared`` body bytes that sends ``sent`` of them and stalls
    (or less where the server closes first)."""
    sock = dial(server, source)
    sock.sendall(post_head(declared))
    block = bytes(MiB)
    try:
        for start in range(0, sent, MiB):
            sock.sendall(block[:min(MiB, sent - start)])
    except OSError:  # refused and closed by the server
        pass
    return sock


class Reader:
    """Reads HTTP answers and WebSocket frames off a raw socket (bounded by its timeout)."""

    def __init__(self, sock: socket.socket):
        self.sock, self.buffer = sock, b""

    def read(self, n: int) -> bytes:
        while len(self.buffer) < n:
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.buffer += data
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def head(self) -> tuple[int, dict[str, str]]:
        while b"\r\n\r\n" not in self.buffer:
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.buffer += data
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        status, *lines = head.decode("latin-1").split("\r\n")
        return int(status.split()[1]), {k.lower(): v.strip() for k, v in (x.split(":", 1) for x in lines)}

    def response(self) -> tuple[int, dict[str, str], bytes]:
        status, headers = self.head()
        return status, headers, self.read(int(headers.get("content-length", 0)))

    def close_code(self) -> tuple[int, str]:
        """Server frames up to its close frame: the close code and reason."""
        for _ in range(100):
            b0, b1 = self.read(2)
            n = b1 & 0x7F
            if n >= 126:
                n = int.from_bytes(self.read(2 if n == 126 else 8), "big")
            payload = self.read(n)
            if b0 & 0x0F == 0x8:
                return int.from_bytes(payload[:2], "big"), payload[2:].decode()
        raise AssertionError("no close frame")


def status_of(sock: socket.socket) -> int | str:
    """The status of the server's answer on ``sock``, or what went wrong reading it."""
    try:
        return Reader(sock).response()[0]
    except (OSError, ConnectionError) as e:
        return type(e).__name__


def get(server: ServerProcess, source: str, path: str = "/v2/health/live") -> tuple[int, dict[str, str], bytes]:
    with dial(server, source) as sock:
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        return Reader(sock).response()


def silent_websocket(server: ServerProcess, source: str, stack: ExitStack) -> Reader:
    """A WebSocket to /v1/view that completes its handshake and never sends a message (closed with ``stack``)."""
    sock = stack.enter_context(dial(server, source, timeout=30))
    sock.sendall(b"GET /v1/view HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n")
    reader = Reader(sock)
    assert reader.head()[0] == 101
    return reader


def view(server: ServerProcess, source: str, timeout: float = 20.0) -> ClientConnection:
    """A WebSocket to /v1/view from ``source`` (not opened yet)."""
    return ws_connect(f"ws://127.0.0.1:{server.port}/v1/view", sock=dial(server, source, timeout), proxy=None,
                      max_size=CLIENT_LIMITS.max_message_bytes, compression=None, open_timeout=timeout)


def open_view(ws: ClientConnection, timeout: float = 20.0) -> P.Message:
    """Send ``open``; the server's answer (``ready``, or ``error`` before a close)."""
    ws.send(P.encode(P.OpenMsg(volume=VOLUME, settings=P.SettingsUpdate(mode="full", width=64, height=48,
                                                                          refine=False))))
    return P.parse(ws.recv(timeout=timeout), CLIENT_LIMITS, P.SERVER_VIEW_MESSAGES)


def first_frame(server: ServerProcess, source: str, within: float) -> float:
    """Seconds until an honest view session from ``source`` gets its first frame; a session turned
    away (CLOSE_TOO_MANY) is tried again every 0.5 s while time is left."""
    start = time.monotonic()
    for _ in range(int(2 * within) + 1):
        left = max(within - (time.monotonic() - start), 0.1)
        try:
            with view(server, source, timeout=left) as ws:
                ready = open_view(ws, timeout=left)
                if isinstance(ready, P.ReadyMsg):
                    msg = P.parse(ws.recv(timeout=left), CLIENT_LIMITS, P.SERVER_VIEW_MESSAGES)
                    assert isinstance(msg, P.FrameMsg), msg
                    return time.monotonic() - start
                assert isinstance(ready, P.ErrorMsg) and ready.code == P.CLOSE_TOO_MANY, ready
        except ConnectionClosed as e:
            assert e.rcvd is not None and e.rcvd.code == P.CLOSE_TOO_MANY, e
        assert time.monotonic() - start < within - 0.5, f"turned away for {within:g} s"
        time.sleep(0.5)
    raise AssertionError("unreachable: the loop ends by time")


def rss_after_stalled_uploads(server: ServerProcess, seconds: float, answers: bool) -> dict:
    """Eight uploads that send 32 MiB of a declared 64 MiB and stall (from 127.0.0.2), and eight
    within the limit that send 24 MiB of a declared 32 MiB and stall (from 127.0.0.3): the server's
    RSS growth (peak and at the end) over ``seconds`` after the last stalls, the liveness
    probe's latency from 127.0.0.1 meanwhile, and (``answers``) the answer each upload got by then."""
    assert get(server, "127.0.0.1")[0] == 200
    base = server.rss()
    with ExitStack() as stack:
        over = [stack.enter_context(stalled_upload(server, "127.0.0.2", 64 * MiB, 32 * MiB)) for _ in range(8)]
        within = [stack.enter_context(stalled_upload(server, "127.0.0.3", 32 * MiB, 24 * MiB)) for _ in range(8)]
        stalled, peak, live = time.monotonic(), 0, []
        while time.monotonic() - stalled < seconds:
            peak = max(peak, server.rss() - base)
            t = time.monotonic()
            assert get(server, "127.0.0.1")[0] == 200
            live.append(time.monotonic() - t)
            time.sleep(0.5)
        got = {"peak": peak, "end": server.rss() - base, "live_max_s": max(live)}
        if answers:
            for sock in over + within:
                sock.settimeout(0.5)
            got |= {"over": [status_of(s) for s in over], "within": [status_of(s) for s in within]}
        return got


# ---- stalled uploads ----------------------------------------------------------------------------


@pytest.mark.slow
def test_stalled_uploads_hold_no_memory_after_the_body_deadline(tight):
    got = rss_after_stalled_uploads(tight, 15.0, answers=True)
    print(f"\ntight limits: RSS growth peak {got['peak'] / MiB:.0f} MiB, after 15 s {got['end'] / MiB:.0f} MiB; "
          f"liveness at most {got['live_max_s'] * 1000:.0f} ms; answers {got['over']} {got['within']}")
    assert got["end"] < RSS_GOAL and got["peak"] < RSS_GOAL
    assert got["over"] == [413] * 8  # read and dropped, answered at the deadline
    # Two fit the address's bytes in flight (2 x 32 MiB) and time out; the others are refused at once
    # (503, closed while the client still sends: its answer may be lost to the reset).
    assert got["within"][:2] == [408, 408] and all(s in (503, "ConnectionResetError") for s in got["within"][2:])
    assert got["live_max_s"] < 2.0
    assert_no_errors(tight)


@pytest.mark.slow
def test_stalled_uploads_at_the_default_limits(default):
    got = rss_after_stalled_uploads(default, 15.0, answers=False)
    print(f"\ndefault limits: RSS growth peak {got['peak'] / MiB:.0f} MiB, after 15 s {got['end'] / MiB:.0f} MiB; "
          f"liveness at most {got['live_max_s'] * 1000:.0f} ms")
    assert got["end"] < RSS_GOAL and got["peak"] < RSS_GOAL
    assert got["live_max_s"] < 2.0
    assert_no_errors(default)


# ---- clients leaving mid-body -------------------------------------------------------------------


def test_a_client_leaving_mid_body_is_an_info_line(tight):
    info = "from 127.0.0.4: the client left after"

    def lines() -> int:  # the guard's INFO line, or (before it) uvicorn's ERROR with a traceback
        text = server_log(tight)
        return text.count(info) + text.count("Exception in ASGI application")

    for _ in range(3):
        seen = lines()
        with dial(tight, "127.0.0.4") as sock:
            sock.sendall(post_head(MiB) + bytes(MiB // 2))
        deadline = time.monotonic() + 10
        while lines() == seen:
            assert time.monotonic() < deadline, "the server logged nothing about the client leaving"
            time.sleep(0.05)
        assert_no_errors(tight)
    assert server_log(tight).count(info) == 3


# ---- connection bounds --------------------------------------------------------------------------


def test_connections_over_the_bounds_get_503_while_other_addresses_are_served(tight):
    per_client, total = TIGHT["max_connections_per_client"], TIGHT["max_connections"]
    with ExitStack() as stack:
        for _ in range(per_client):  # held by bodies that do not come (within body_timeout_s)
            stack.enter_context(dial(tight, "127.0.0.5")).sendall(post_head(1000))
        time.sleep(0.3)
        with dial(tight, "127.0.0.5") as sock:
            sock.sendall(post_head(10) + bytes(10))
            status, headers, body = Reader(sock).response()
        assert (status, headers["retry-after"], headers["connection"]) == (503, "1", "close")
        assert json.loads(body) == {"error": f"127.0.0.5 holds {per_client} connections; try later", "status": 503}
        assert get(tight, "127.0.0.6")[0] == 200
        ws = silent_websocket(tight, "127.0.0.5", stack)
        assert ws.close_code() == (P.CLOSE_TOO_MANY, f"127.0.0.5 holds {per_client} connections; try later")
        for k in range(total // per_client - 1):  # the rest of the total, from other addresses
            for _ in range(per_client):
                stack.enter_context(dial(tight, f"127.0.1.{k + 1}")).sendall(post_head(1000))
        time.sleep(0.3)
        status, _, body = get(tight, "127.0.0.6", "/v2")
        assert status == 503 and json.loads(body)["error"] == f"the server holds {total} connections; try later"
        assert get(tight, "127.0.0.6")[0] == 200, "liveness is answered at the cap"
    deadline = time.monotonic() + 5
    while get(tight, "127.0.0.5", "/v2")[0] != 200:  # the server sees the closes a little later
        assert time.monotonic() < deadline
        time.sleep(0.1)
    assert_no_errors(tight)


# ---- silent WebSockets --------------------------------------------------------------------------


def test_silent_websockets_do_not_lock_out_an_honest_session(tight):
    with ExitStack() as stack:
        silent = [silent_websocket(tight, f"127.0.2.{1 + k // 8}", stack) for k in range(40)]
        took = first_frame(tight, "127.0.0.7", within=20.0)
        print(f"\ntight limits: first frame {took:.2f} s after 40 silent WebSockets")
        started = time.monotonic()
        assert [ws.close_code()[0] for ws in silent] == [P.CLOSE_IDLE] * 40
        assert time.monotonic() - started < TIGHT["open_timeout_s"] + 2
    assert_no_errors(tight)


def test_view_sessions_per_address_are_bounded(tight):
    with ExitStack() as stack:
        for _ in range(TIGHT["max_sessions_per_client"]):
            assert isinstance(open_view(stack.enter_context(view(tight, "127.0.0.8"))), P.ReadyMsg)
        with view(tight, "127.0.0.8") as ws, pytest.raises(ConnectionClosed) as closed:
            open_view(ws)
        reason = f"127.0.0.8 holds {TIGHT['max_sessions_per_client']} sessions; try later"
        assert (closed.value.rcvd.code, closed.value.rcvd.reason) == (P.CLOSE_TOO_MANY, reason)
        with view(tight, "127.0.0.9") as ws:
            assert isinstance(open_view(ws), P.ReadyMsg)
    assert_no_errors(tight)


@pytest.mark.slow
def test_silent_websockets_at_the_default_limits(default):
    with ExitStack() as stack:
        silent = [silent_websocket(default, "127.0.0.1", stack) for _ in range(40)]
        elsewhere = first_frame(default, "127.0.0.2", within=20.0)
        # The same address holds max_connections_per_client (32) silent ones until open_timeout_s (10 s).
        same = first_frame(default, "127.0.0.1", within=20.0)
        print(f"\ndefault limits: first frame {elsewhere:.2f} s from another address, {same:.2f} s from the "
              f"silent ones' address")
        codes = [ws.close_code()[0] for ws in silent]
        assert sorted(set(codes)) == [P.CLOSE_IDLE, P.CLOSE_TOO_MANY] and codes.count(P.CLOSE_IDLE) == 32
    assert_no_errors(default)


# ---- zlib bombs ---------------------------------------------------------------------------------


def zlib_array(shape: tuple[int, ...], data: bytes) -> dict:
    """A float32 wire array declaring ``shape`` whose data is ``data``, marked as zlib."""
    return {"dtype": "float32", "shape": list(shape), "data": data, "zlib": True}


def zeros_z(n: int) -> bytes:
    """One zlib stream of ``n`` zero bytes (level 9: about 1000 to 1)."""
    return zlib.compress(bytes(n), 9)


def upscale_wire(mask: dict, normal: dict, depth: dict, **fields) -> bytes:
    """A hand-made ``upscale`` body (protocol version 3)."""
    return msgspec.msgpack.encode({"type": "upscale", "version": P.PROTOCOL_VERSION, "mask": mask, "normal": normal,
                                   "depth": depth, **fields})


def bombs() -> dict[str, tuple[bytes, int, str]]:
    """Bodies by name: the body, and the status and words of the answer it must get."""
    n = 256  # a frame well within the limits: 1024x1024 upscaled
    past = zeros_z(100 * MiB)  # ~100 KB: the body ~0.3 MB
    big = 2048  # 8192^2 upscaled: too big, though each array is within the bounds of a 4096^2 frame's
    return {
        "inflates past its shape": (upscale_wire(zlib_array((n, n), past), zlib_array((n, n, 3), past),
                                                 zlib_array((n, n), past)),
                                    400, f"zlib data inflates past the {4 * n * n} bytes its shape declares"),
        "a huge shape": (upscale_wire(zlib_array((big, big), zeros_z(4 * big * big)),
                                      zlib_array((big, big, 3), zeros_z(12 * big * big)),
                                      zlib_array((big, big), zeros_z(4 * big * big))), 413, "exceeds the limits"),
        "trailing garbage": (upscale_wire(zlib_array((n, n), zeros_z(4 * n * n) + b"garbage"),
                                          zlib_array((n, n, 3), zeros_z(12 * n * n)),
                                          zlib_array((n, n), zeros_z(4 * n * n))), 400, "7 bytes after the zlib stream"),
    }


def post(server: ServerProcess, source: str, body: bytes, timeout: float = 30.0) -> tuple[int | str, dict]:
    """POST /v1/upscale from ``source``: the status and the JSON answer (``{}`` where it is none), or
    what went wrong reading it."""
    try:
        with dial(server, source, timeout) as sock:
            sock.sendall(post_head(len(body)) + body)
            status, headers, reply = Reader(sock).response()
    except (OSError, ConnectionError) as e:
        return type(e).__name__, {}
    return status, json.loads(reply) if headers.get("content-type") == "application/json" else {}


@pytest.mark.slow
def test_zlib_bombs_get_4xx_while_liveness_and_memory_hold(default):
    """Four clients loop the bombs for 4 s; meanwhile liveness is probed and the RSS sampled."""
    cases = bombs()
    assert all(len(body) < 400_000 for body, _, _ in cases.values())
    assert get(default, "127.0.0.1")[0] == 200
    base = default.rss()
    answers: list[tuple[str, int | str, str]] = []
    live: list[float] = []
    peak = 0
    start = time.monotonic()

    def attack(source: str) -> None:
        for i in range(10_000):  # bounded in count and time
            if time.monotonic() - start > 4.0:
                return
            name = list(cases)[i % len(cases)]
            status, reply = post(default, source, cases[name][0])
            answers.append((name, status, reply.get("error", "")))

    clients = [threading.Thread(target=attack, args=(f"127.0.3.{k + 1}",)) for k in range(4)]
    for c in clients:
        c.start()
    while any(c.is_alive() for c in clients) and time.monotonic() - start < 30:
        peak = max(peak, default.rss() - base)
        t = time.monotonic()
        assert get(default, "127.0.0.1")[0] == 200
        live.append(time.monotonic() - t)
        time.sleep(0.1)
    for c in clients:
        c.join(10)
    peak = max(peak, default.rss() - base)
    print(f"\nzlib bombs: {len(answers)} answered in 4 s; liveness at most {max(live) * 1000:.0f} ms over "
          f"{len(live)} probes; RSS growth peak {peak / MiB:.0f} MiB")
    assert len(answers) >= 3 * len(cases)
    for name, status, reason in answers:
        assert (status, cases[name][2] in reason) == (cases[name][1], True), (name, status, reason)
    assert max(live) < 1.0
    assert peak < BOMB_RSS_GOAL
    assert_no_errors(default)


# ---- upscale sessions ---------------------------------------------------------------------------


def test_session_ids_from_one_address_leave_another_an_upscale_session(default):
    """40 tiny requests with distinct ``session`` ids from one address (today each holds one of the
    max_sessions upscale slots for idle_timeout_s); then a new id from another address is served."""
    shapes = {"mask": (4, 4), "normal": (4, 4, 3), "depth": (4, 4)}
    tiny = {n: {"dtype": "float32", "shape": list(shape), "data": bytes(4 * math.prod(shape))}
            for n, shape in shapes.items()}
    for k in range(40):
        status, reply = post(default, "127.0.0.11", upscale_wire(**tiny, session=f"attacker-{k}"))
        assert status in (200, 429), reply
    status, reply = post(default, "127.0.0.2", upscale_wire(**tiny, session="honest-1"))
    assert status == 200, reply
    assert_no_errors(default)
