"""`ReplicaMiddleware` on a stand-in ASGI app (no Ray, no engine): the replica header on every
answer and handshake, the session header check, and when a session is reported restarted."""

from __future__ import annotations

import asyncio

import msgspec
import numpy as np
import pytest

from isosr_server import protocol as P
from isosr_server.replica import REPLICA_HEADER, RESTARTED_HEADER, SESSION_HEADER, ReplicaMiddleware

LOW = np.zeros((2, 2), np.float32)


async def echo_app(scope, receive, send):
    """Reads the whole body (as the routes do), then answers 200, or 422 for a body ``b"bad"``."""
    if scope["type"] == "websocket":
        await receive()
        await send({"type": "websocket.accept"})
        return
    body = b""
    while True:
        message = await receive()
        body += message.get("body", b"")
        if not message.get("more_body"):
            break
    status = 422 if body == b"bad" else 200
    await send({"type": "http.response.start", "status": status, "headers": [(b"content-type", b"text/plain")]})
    await send({"type": "http.response.body", "body": b"ok"})


def call(mw: ReplicaMiddleware, path: str, body: bytes, headers: dict[str, str] | None = None,
         method: str = "POST") -> tuple[int, dict[str, str], bytes]:
    """One HTTP request through the middleware, the body in two chunks: ``(status, headers, body)``."""
    sent: list[dict] = []
    chunks = [{"type": "http.request", "body": body[:5], "more_body": True},
              {"type": "http.request", "body": body[5:], "more_body": False}]

    async def receive():
        return chunks.pop(0)

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "method": method, "path": path,
             "headers": [(k.encode(), v.encode()) for k, v in (headers or {}).items()]}
    asyncio.run(mw(scope, receive, send))
    start = sent[0]
    return start["status"], {k.decode(): v.decode() for k, v in start["headers"]}, b"".join(
        m.get("body", b"") for m in sent[1:])


def handshake(mw: ReplicaMiddleware, headers: list[tuple[bytes, bytes]] = ()) -> list[dict]:
    """A WebSocket handshake to ``/v1/view`` through the middleware: the messages the app sent."""
    sent: list[dict] = []

    async def receive():
        return {"type": "websocket.connect"}

    async def send(message):
        sent.append(message)

    asyncio.run(mw({"type": "websocket", "path": "/v1/view", "headers": list(headers)}, receive, send))
    return sent


def upscale(session: str | None, flow: bool, reset: bool = False) -> bytes:
    return P.encode(P.UpscaleRequest(LOW, np.zeros((2, 2, 3), np.float32), LOW,
                                     np.zeros((2, 2, 2), np.float32) if flow else None, session=session, reset=reset))


def infer(sequence: str | int | None, flow: bool, start: bool = False) -> bytes:
    inputs = [{"name": n, "shape": [2, 2], "datatype": "FP32", "data": [0, 0, 0, 0]}
              for n in ("mask", "normal", "depth") + (("flow",) if flow else ())]
    params = {} if sequence is None else {"sequence_id": sequence, "sequence_start": start}
    return msgspec.json.encode({"inputs": inputs, "parameters": params})


@pytest.fixture
def mw():
    return ReplicaMiddleware(echo_app, replica="r1", idle_timeout_s=60.0, max_sessions=2)


def test_every_answer_and_handshake_names_the_replica(mw):
    status, headers, _ = call(mw, "/v2/health/ready", b"", method="GET")
    assert status == 200 and headers[REPLICA_HEADER] == "r1"
    assert call(mw, "/v1/upscale", b"bad")[1][REPLICA_HEADER] == "r1"
    assert (REPLICA_HEADER.encode(), b"r1") in handshake(mw)[0]["headers"]


def test_a_websockets_deflate_offer_is_warned_of_once(mw, caplog):
    """Serve's proxy takes a browser's permessage-deflate offer and deflates every frame: the replica warns,
    once, naming the fix; a WebSocket without the offer is not warned of."""
    with caplog.at_level("WARNING", logger="isosr.server"):
        handshake(mw)
        handshake(mw, [(b"sec-websocket-extensions", b"x-webkit-deflate-frame")])
        assert not caplog.records
        for _ in range(3):
            handshake(mw, [(b"sec-websocket-extensions", b"permessage-deflate; client_max_window_bits")])
    (record,) = caplog.records
    assert "permessage-deflate" in record.getMessage() and "Sec-WebSocket-Extensions" in record.getMessage()


@pytest.mark.parametrize("path,body", [("/v1/upscale", upscale), ("/v2/models/isosr/infer", infer),
                                       ("/v2/models/isosr-recon/infer", infer)])
def test_sessions_restart_only_when_a_continued_state_is_missing(mw, path, body):
    # A session named in the body but not in the routing header: refused.
    status, headers, reply = call(mw, path, body("a", flow=False))
    assert status == 400 and SESSION_HEADER in msgspec.json.decode(reply)["error"]
    assert call(mw, path, body("a", flow=False), {SESSION_HEADER: "b"})[0] == 400
    # A new session's first frame (no flow) is no restart; nor are its continued frames.
    for flow in (False, True, True):
        status, headers, _ = call(mw, path, body("a", flow=flow), {SESSION_HEADER: "a"})
        assert status == 200 and RESTARTED_HEADER not in headers
    # A continued frame of a session this replica never served: restarted, once.
    assert call(mw, path, body("m", flow=True), {SESSION_HEADER: "m"})[1][RESTARTED_HEADER] == "1"
    assert RESTARTED_HEADER not in call(mw, path, body("m", flow=True), {SESSION_HEADER: "m"})[1]
    # ... unless it resets its state itself.
    resetting = upscale("n", True, reset=True) if path == "/v1/upscale" else infer("n", True, start=True)
    assert RESTARTED_HEADER not in call(mw, path, resetting, {SESSION_HEADER: "n"})[1]
    # The replica remembers at most max_sessions (2): "a" was forgotten first.
    assert call(mw, path, body("a", flow=True), {SESSION_HEADER: "a"})[1][RESTARTED_HEADER] == "1"
    # Session-less requests and failed ones pass untouched.
    assert call(mw, path, body(None, flow=True))[0] == 200
    assert call(mw, path, b"bad", {SESSION_HEADER: "z"})[0] == 422


def test_integer_sequence_ids_match_their_header(mw):
    assert call(mw, "/v2/models/isosr/infer", infer(7, flow=True), {SESSION_HEADER: "7"})[1][RESTARTED_HEADER] == "1"


def test_as_replica_labels_every_metric_series_with_the_replica():
    """`as_replica` on the real app (not started: no model): ``/metrics`` names the replica on every
    isosr_* sample and in the header; the same app without it names none."""
    from fastapi.testclient import TestClient
    from prometheus_client.parser import text_string_to_metric_families

    from isosr_server.app import create_app
    from isosr_server.core.config import Settings
    from isosr_server.replica import as_replica

    def samples(app) -> tuple[dict, list]:
        reply = TestClient(app).get("/metrics")
        assert reply.status_code == 200
        families = text_string_to_metric_families(reply.text)
        return reply.headers, [s for f in families if f.name.startswith("isosr_") for s in f.samples]

    apps = [create_app(Settings()) for _ in range(2)]
    for app in apps:
        app.state.metrics.frame("view", "full", False, {"render": 2.0, "total": 3.0}, 100)
    as_replica(apps[1], "r7")
    headers, plain = samples(apps[0])
    assert plain and REPLICA_HEADER not in headers and not [s for s in plain if "replica" in s.labels]
    headers, labelled = samples(apps[1])
    assert headers[REPLICA_HEADER] == "r7" and len(labelled) == len(plain)
    assert {s.labels.get("replica") for s in labelled} == {"r7"}
