"""The HTTP bounds below the app (:mod:`isosr_server.transport`) on a real `isosr serve`
subprocess on loopback (CPU), from raw sockets: request heads over the byte and field-count
limits (431 or a close; memory and liveness hold), heads dribbled past the deadline (closed, on a
fresh and on a keep-alive connection), idle sockets over the connection cap (the oldest closed to
make room: liveness answers, the server's descriptors stay near the cap), connections over the
cap while every one is busy (503 and a close), the count released on every path (WebSockets
included), TLS handshakes that stall (counted from the accept, closed by the deadline); and
``/openapi.json`` behind the token.

Every loop is bounded in count and time; no test asserts a duration.
"""

from __future__ import annotations

import os
import select
import socket
import ssl
import time
import urllib.request
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import pytest
from server_fixtures import self_signed_cert
from websockets.sync.client import connect as ws_connect

from isosr_bench.bench_server import ServerProcess, rss_bytes

MiB = 2**20
TOKEN = "transport-test-token"
HEADER_BYTES, HEADER_COUNT, HEADER_TIMEOUT_S = 16384, 20, 0.5
CAP = 16
# Server RSS that four clients each pushing a 16 MiB header may add (the head limit is 16 KiB).
RSS_GOAL = 32 * MiB


def flags(limits: dict) -> tuple[str, ...]:
    return tuple(a for name, value in limits.items() for a in ("--" + name.replace("_", "-"), str(value)))


@contextmanager
def serve(*args: str, tls: ssl.SSLContext | None = None) -> Iterator[ServerProcess]:
    with ServerProcess("cpu", extra_args=("--log-level", "info", *args), tls=tls) as server:
        yield server


@pytest.fixture(scope="module")
def tight():
    """Small heads, a short header deadline, a token."""
    with serve("--token", TOKEN, *flags({"max_header_bytes": HEADER_BYTES, "max_header_count": HEADER_COUNT,
                                          "header_timeout_s": HEADER_TIMEOUT_S})) as server:
        yield server


@pytest.fixture(scope="module")
def capped():
    """A small connection cap and a long header deadline (idle sockets stay until made room for); no token."""
    with serve(*flags({"max_open_connections": CAP, "header_timeout_s": 120, "body_timeout_s": 120})) as server:
        yield server


def dial(server: ServerProcess, timeout: float = 10.0) -> socket.socket:
    return socket.create_connection(("127.0.0.1", server.port), timeout=timeout)


def read_response(sock: socket.socket) -> tuple[int, dict[str, str], bytes]:
    """One HTTP answer off ``sock`` (ConnectionError where the server closed first)."""
    buffer = b""
    while b"\r\n\r\n" not in buffer:
        data = sock.recv(65536)
        if not data:
            raise ConnectionError("closed")
        buffer += data
    head, body = buffer.split(b"\r\n\r\n", 1)
    status, *lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, v in (x.split(":", 1) for x in lines)}
    while len(body) < int(headers.get("content-length", 0)):
        data = sock.recv(65536)
        if not data:
            raise ConnectionError("closed mid-body")
        body += data
    return int(status.split()[1]), headers, body


def get(server: ServerProcess, path: str = "/v2/health/live", headers: dict | None = None,
        ) -> tuple[int, dict[str, str], bytes]:
    lines = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
    with dial(server) as sock:
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n{lines}\r\n".encode())
        return read_response(sock)


def answer_or_close(sock: socket.socket) -> int | str:
    """The status the server answered on ``sock``, or ``closed`` where it closed (or reset) without one."""
    try:
        return read_response(sock)[0]
    except (OSError, ConnectionError):
        return "closed"


def closed_by_server(sock: socket.socket, wait_s: float) -> bool:
    """Whether the server closes ``sock`` (EOF or reset) within ``wait_s`` (answers before it are skipped)."""
    deadline = time.monotonic() + wait_s
    while (left := deadline - time.monotonic()) > 0:
        if select.select([sock], [], [], left)[0]:
            try:
                if not sock.recv(65536):
                    return True
            except OSError:
                return True
    return False


def descriptors(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def test_heads_over_the_byte_limit_get_431_or_a_close_while_memory_and_liveness_hold(tight):
    before = rss_bytes(tight.pid)
    outcomes = []
    for _ in range(4):
        with dial(tight) as sock:
            sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: ")
            chunk = b"a" * 65536
            try:
                for _ in range(16 * MiB // len(chunk)):  # 16 MiB of one header, unless refused first
                    sock.sendall(chunk)
            except OSError:
                pass
            outcomes.append(answer_or_close(sock))
        assert get(tight)[0] == 200
    assert set(outcomes) <= {431, "closed"}, outcomes
    assert rss_bytes(tight.pid) - before < RSS_GOAL
    # A head just within the limit is served.
    assert get(tight, headers={"X-Fill": "a" * (HEADER_BYTES // 2)})[0] == 200


def test_a_head_over_the_limit_sent_whole_gets_431(tight):
    with dial(tight) as sock:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (2 * HEADER_BYTES))
        status, headers, body = read_response(sock)
    assert status == 431 and b"exceeds" in body and headers["connection"] == "close"


def test_more_header_fields_than_the_limit_get_431(tight):
    fields = {f"X-F{i}": "1" for i in range(HEADER_COUNT - 1)}  # and Host: at the limit
    assert get(tight, headers=fields)[0] == 200
    status, headers, body = get(tight, headers={**fields, "X-One-More": "1"})
    assert status == 431 and b"header fields" in body and headers["connection"] == "close"
    assert get(tight)[0] == 200


def dribble_until_closed(sock: socket.socket, data: bytes) -> bool:
    """Send ``data`` a byte every 50 ms (at most 600 bytes: 30 s); whether the server closed first."""
    for byte in data[:600]:
        try:
            sock.sendall(bytes([byte]))
        except OSError:
            return True
        if closed_by_server(sock, 0.05):
            return True
    return False


def test_a_head_dribbled_past_the_deadline_is_closed(tight):
    slow = b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\n" + b"X-Slow: " + b"a" * 1000
    with dial(tight) as sock:
        assert dribble_until_closed(sock, slow)
    # The same on a keep-alive connection: a first request answered, then the next head dribbled.
    with dial(tight) as sock:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert read_response(sock)[0] == 200
        assert dribble_until_closed(sock, slow)
    # A connection that sends nothing is closed too.
    with dial(tight) as sock:
        assert closed_by_server(sock, 30)
    assert get(tight)[0] == 200


def test_the_schema_is_behind_the_token(tight, capped):
    assert get(tight, "/openapi.json")[0] in (401, 403)
    status, _, body = get(tight, "/openapi.json", headers={"Authorization": f"Bearer {TOKEN}"})
    assert status == 200 and b"/v1/upscale" in body
    status, _, body = get(capped, "/openapi.json")  # no token set: open
    assert status == 200 and b"/v1/upscale" in body


def test_idle_sockets_over_the_cap_are_closed_for_room_and_liveness_answers(capped):
    base = descriptors(capped.pid)
    with ExitStack() as stack:
        idle = []
        for i in range(3 * CAP):
            sock = stack.enter_context(dial(capped))
            if i % 2:
                sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 1")  # a head begun, never ended
            idle.append(sock)
            if i % 8 == 7:
                assert get(capped)[0] == 200
        assert get(capped)[0] == 200
        peak = descriptors(capped.pid)
        assert peak <= base + CAP + 4, (base, peak)
        closed = sum(closed_by_server(sock, 0.2) for sock in idle)
        assert closed >= 3 * CAP - CAP, closed  # the newest may still be open, the older were closed
    assert get(capped)[0] == 200


def unasked_answer(sock: socket.socket) -> int:
    """What the server answers on a new connection before it is asked (503 when refused; no
    request is sent then, so the answer is not lost to a reset), else to a GET of liveness."""
    if not select.select([sock], [], [], 1.0)[0]:
        sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    return read_response(sock)[0]


def test_connections_over_the_cap_get_503_while_every_one_is_busy(capped):
    base = descriptors(capped.pid)
    head = (b"POST /v1/upscale HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/msgpack\r\n"
            b"Content-Length: 1000\r\n\r\n")
    with ExitStack() as stack:
        for _ in range(CAP):  # each a request whose body never comes: busy, never closed for room
            stack.enter_context(dial(capped)).sendall(head)
        answers = []
        for _ in range(50):  # until the server has read every head (bounded)
            answers.append(unasked_answer(stack.enter_context(dial(capped))))
            if answers[-1] == 503:
                break
            time.sleep(0.1)
        assert answers[-1] == 503 and set(answers) <= {200, 503}, answers
        assert descriptors(capped.pid) <= base + CAP + 4
    for _ in range(100):  # the busy ones gone (the server sees each close a little later), it answers again
        with dial(capped) as sock:
            sock.sendall(b"GET /v2/health/live HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            if answer_or_close(sock) == 200:
                break
        time.sleep(0.1)
    assert get(capped)[0] == 200


def test_the_count_is_released_on_every_path(capped):
    """Each kind of connection, 3 x CAP times in turn: were any left counted, the cap would refuse."""
    for _ in range(3 * CAP):
        assert get(capped)[0] == 200  # answered, closed by the client
        with dial(capped) as sock:  # 431
            sock.sendall(b"GET / HTTP/1.1\r\nHost: 1\r\n" + b"".join(b"X-%d: 1\r\n" % i for i in range(200)) + b"\r\n")
            assert answer_or_close(sock) in (431, "closed")
        with ws_connect(f"ws://127.0.0.1:{capped.port}/v1/view", proxy=None, open_timeout=30):
            pass  # upgraded, then closed before a message
    assert get(capped)[0] == 200


@pytest.fixture(scope="module")
def tls_capped(tmp_path_factory):
    """HTTPS with a small connection cap and a short header deadline."""
    cert, key = self_signed_cert(tmp_path_factory.mktemp("tls"))
    with serve("--tls-cert", str(cert), "--tls-key", str(key), tls=ssl.create_default_context(cafile=cert),
               *flags({"max_open_connections": CAP, "header_timeout_s": HEADER_TIMEOUT_S})) as server:
        yield server


def https_live(server: ServerProcess) -> int:
    with urllib.request.urlopen(server.url + "/v2/health/live", context=server.tls, timeout=10) as r:
        return r.status


def test_stalled_tls_handshakes_count_and_are_closed_by_the_deadline(tls_capped):
    """Connections that begin a TLS handshake and stall (a record header, no more) count against
    the cap from their accept and are closed within the head's deadline; HTTPS liveness answers
    throughout and the server's descriptors stay near the cap."""
    server = tls_capped
    base = descriptors(server.pid)
    with ExitStack() as stack:
        stalled = []
        for i in range(3 * CAP):
            sock = stack.enter_context(dial(server))
            sock.sendall(b"\x16\x03\x01\x02\x00")  # a ClientHello's record header; its body never comes
            stalled.append(sock)
            if i % 8 == 7:
                assert https_live(server) == 200
        assert descriptors(server.pid) <= base + CAP + 4
        assert all(closed_by_server(sock, 20 * HEADER_TIMEOUT_S) for sock in stalled)
    assert https_live(server) == 200
