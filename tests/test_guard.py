"""`isosr_server.guard.Guard` around tiny ASGI apps, driven by a fake server (no sockets): the body
deadline and byte budget, the bytes in flight per client, the connection and session bounds, the
WebSocket first-message deadline, and counters released on every path."""

from __future__ import annotations

import asyncio
import json
import logging

import pytest
from starlette.requests import Request

from isosr_server.guard import RETRY_AFTER_S, Guard
from isosr_server.protocol import CLOSE_IDLE, CLOSE_TOO_MANY, Limits

LIMITS = Limits(max_message_bytes=1000, body_timeout_s=0.3, open_timeout_s=0.3, max_connections=5,
                max_connections_per_client=3, max_sessions_per_client=1)


class Peer:
    """The fake server side of one scope: what the client sends (``inbox``) and what the app answered."""

    def __init__(self, scope: dict, *messages: dict):
        self.scope, self.inbox, self.sent = scope, asyncio.Queue(), []
        for m in messages:
            self.inbox.put_nowait(m)

    async def receive(self) -> dict:
        return await self.inbox.get()

    async def send(self, message: dict) -> None:
        self.sent.append(message)

    def run(self, guard: Guard) -> asyncio.Task:
        return asyncio.create_task(guard(self.scope, self.receive, self.send))

    def status(self) -> int:
        return next(m["status"] for m in self.sent if m["type"] == "http.response.start")

    def headers(self) -> dict[bytes, bytes]:
        return dict(next(m["headers"] for m in self.sent if m["type"] == "http.response.start"))

    def error(self) -> dict:
        return json.loads(b"".join(m.get("body", b"") for m in self.sent if m["type"] == "http.response.body"))

    def close_code(self) -> int | None:
        return next((m["code"] for m in self.sent if m["type"] == "websocket.close"), None)


def post(declared: int | None = None, client: str = "10.0.0.1") -> dict:
    headers = [] if declared is None else [(b"content-length", str(declared).encode())]
    return {"type": "http", "method": "POST", "path": "/up", "headers": headers, "client": (client, 5000)}


def chunk(n: int, more: bool = True) -> dict:
    return {"type": "http.request", "body": b"x" * n, "more_body": more}


def websocket(client: str = "10.0.0.1") -> dict:
    return {"type": "websocket", "path": "/v1/view", "headers": [], "client": (client, 5000)}


async def body_app(scope, receive, send) -> None:
    """Reads the whole body (Starlette: ClientDisconnect on a disconnect), answers its length."""
    body = await Request(scope, receive).body()
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": str(len(body)).encode()})


async def ws_app(scope, receive, send) -> None:
    """Accepts, then echoes until the client leaves."""
    assert (await receive())["type"] == "websocket.connect"
    await send({"type": "websocket.accept"})
    while (message := await receive())["type"] == "websocket.receive":
        await send({"type": "websocket.send", "bytes": message["bytes"]})


def settled(guard: Guard) -> bool:
    return guard.connections == 0 and guard.clients == {}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 10))


@pytest.fixture
def info(caplog):
    caplog.set_level(logging.INFO, "isosr.server.guard")
    yield caplog
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_a_whole_body_passes_and_releases_everything(info):
    async def main():
        guard = Guard(body_app, LIMITS)
        peer = Peer(post(600), chunk(300), chunk(300, more=False))
        await peer.run(guard)
        assert peer.status() == 200 and peer.sent[-1]["body"] == b"600" and settled(guard)
    run(main())


def test_a_late_body_gets_408_and_the_connection_closed(info):
    async def main():
        guard = Guard(body_app, LIMITS)
        peer = Peer(post(600), chunk(300))  # and then nothing
        started = asyncio.get_running_loop().time()
        await peer.run(guard)
        waited = asyncio.get_running_loop().time() - started
        assert peer.status() == 408 and peer.headers()[b"connection"] == b"close"
        assert peer.error() == {"error": "the body did not arrive within 0.3 s", "status": 408}
        assert waited > 0.25 and settled(guard)  # not before its deadline (how late is load's, not the guard's)
    run(main())
    assert "408" in info.text


def test_an_oversized_body_gets_413_by_declared_length_or_by_bytes_read(info):
    called = []

    async def app(scope, receive, send):
        called.append(scope)
        await body_app(scope, receive, send)

    async def main():
        guard = Guard(app, LIMITS)
        # Declared within DRAIN_FACTOR x the limit: read on and dropped, then the 413; the app never runs.
        peer = Peer(post(1500), chunk(1000), chunk(500, more=False))
        await peer.run(guard)
        assert peer.status() == 413 and "1500 bytes exceeds the limit" in peer.error()["error"]
        assert peer.inbox.empty() and not called
        # Declared beyond it, or the client waits for 100 Continue: answered at once, nothing read.
        peer = Peer(post(5000), chunk(1000))
        await peer.run(guard)
        assert peer.status() == 413 and peer.inbox.qsize() == 1
        peer = Peer(post(1500), chunk(1000))
        peer.scope["headers"].append((b"expect", b"100-continue"))
        await peer.run(guard)
        assert peer.status() == 413 and peer.inbox.qsize() == 1
        # No length declared: the app reads a disconnect once the bytes pass the limit.
        peer = Peer(post(), chunk(800), chunk(800), chunk(100, more=False))
        await peer.run(guard)
        assert peer.status() == 413 and len(called) == 1 and peer.inbox.empty() and settled(guard)
    run(main())


def test_bodies_in_flight_per_client_are_bounded(info):
    async def main():
        guard = Guard(body_app, LIMITS)
        a, b = Peer(post(1000)), Peer(post(1000))  # 2 x the limit in flight: the bound
        tasks = [a.run(guard), b.run(guard)]
        await asyncio.sleep(0.01)
        assert guard.clients["10.0.0.1"].body_bytes == 2000
        c = Peer(post(10), chunk(10, more=False))
        other = Peer(post(10, client="10.0.0.2"), chunk(10, more=False))
        await c.run(guard)
        await other.run(guard)
        assert c.status() == 503 and c.headers()[b"retry-after"] == str(RETRY_AFTER_S).encode()
        assert "in flight" in c.error()["error"] and other.status() == 200
        a.inbox.put_nowait(chunk(1000, more=False))
        b.inbox.put_nowait(chunk(1000, more=False))
        await asyncio.gather(*tasks)
        assert a.status() == b.status() == 200 and settled(guard)
        # Undeclared lengths count as read.
        a, b, c = Peer(post(), chunk(900)), Peer(post(), chunk(900)), Peer(post())
        tasks = [a.run(guard), b.run(guard), c.run(guard)]
        await asyncio.sleep(0.01)
        assert guard.clients["10.0.0.1"].body_bytes == 1800
        c.inbox.put_nowait(chunk(300))  # 2100 > 2000
        await tasks[2]
        assert c.status() == 503
        for p in (a, b):
            p.inbox.put_nowait(chunk(0, more=False))
        await asyncio.gather(*tasks)
        assert a.status() == b.status() == 200 and settled(guard)
    run(main())


def test_connections_are_bounded_in_total_and_per_client(info):
    async def main():
        guard = Guard(body_app, LIMITS)
        held = [Peer(post(10, client=c)) for c in ("10.0.0.1",) * 3 + ("10.0.0.2", "10.0.0.3")]
        tasks = [p.run(guard) for p in held]
        await asyncio.sleep(0.01)
        assert guard.connections == 5
        for client, words in (("10.0.0.1", "10.0.0.1 holds 3 connections"), ("10.0.0.4", "server holds 5")):
            peer = Peer(post(10, client=client), chunk(10, more=False))
            await peer.run(guard)
            assert peer.status() == 503 and words in peer.error()["error"]
            assert peer.headers()[b"retry-after"] == b"1" and peer.inbox.qsize() == 1
        for client in ("10.0.0.1", "10.0.0.4"):  # the health probes are answered all the same
            live = Peer(dict(post(client=client), method="GET", path="/v2/health/live"),
                        {"type": "http.request", "body": b"", "more_body": False})
            await live.run(guard)
            assert live.status() == 200 and guard.connections == 5
        ws = Peer(websocket("10.0.0.5"), {"type": "websocket.connect"})
        await ws.run(guard)
        assert [m["type"] for m in ws.sent] == ["websocket.accept", "websocket.close"]
        assert ws.close_code() == CLOSE_TOO_MANY and "try later" in ws.sent[-1]["reason"]
        for p in held:
            p.inbox.put_nowait(chunk(10, more=False))
        await asyncio.gather(*tasks)
        assert settled(guard)
    run(main())


async def failing_ws(scope, receive, send):
    await receive()
    await send({"type": "websocket.accept"})
    await receive()
    raise RuntimeError("a server fault")


def test_a_refusal_that_outlives_the_clients_other_requests_keeps_their_successors_counted(info):
    async def main():
        guard = Guard(body_app, LIMITS)
        b = Peer(post(10))
        others = [Peer(post(10, client=f"10.0.1.{k}")) for k in range(4)]
        tasks = [p.run(guard) for p in [b, *others]]  # the total bound is full
        await asyncio.sleep(0.01)
        refused, release = Peer(post(10)), asyncio.Event()

        async def slow_send(message):  # the refusal's answer waits on a slow client
            await release.wait()
            refused.sent.append(message)
        refused_task = asyncio.create_task(guard(refused.scope, refused.receive, slow_send))
        await asyncio.sleep(0.01)
        b.inbox.put_nowait(chunk(10, more=False))
        await tasks[0]  # the client's last request ends while its refusal is still being answered
        c = Peer(post(10))
        c_task = c.run(guard)
        await asyncio.sleep(0.01)
        release.set()
        await refused_task
        assert refused.status() == 503 and guard.clients["10.0.0.1"].connections == 1
        for p in (c, *others):
            p.inbox.put_nowait(chunk(10, more=False))
        await asyncio.gather(c_task, *tasks[1:])
        assert settled(guard)
    run(main())


def test_counters_are_released_on_every_path(info):
    async def failing(scope, receive, send):
        await receive()
        raise RuntimeError("a server fault")

    async def main():
        guard = Guard(body_app, LIMITS)
        # The client leaves mid-body: Starlette raises ClientDisconnect, the guard logs it at INFO.
        peer = Peer(post(600), chunk(300), {"type": "http.disconnect"})
        await peer.run(guard)
        assert not [m for m in peer.sent if m["type"] == "http.response.start"] and settled(guard)
        # A server fault propagates (the server logs it) and still releases.
        guard = Guard(failing, LIMITS)
        with pytest.raises(RuntimeError):
            await Peer(post(10), chunk(10, more=False)).run(guard)
        assert settled(guard)
        # A WebSocket that fails after its first message.
        guard = Guard(failing_ws, LIMITS)
        with pytest.raises(RuntimeError):
            await Peer(websocket(), {"type": "websocket.connect"},
                       {"type": "websocket.receive", "bytes": b"open"}).run(guard)
        assert settled(guard)
    run(main())
    assert "the client left after 300 body bytes" in info.text


def test_a_websocket_without_a_first_message_is_closed_4408(info):
    async def app(scope, receive, send):
        assert (await receive())["type"] == "websocket.connect"
        await send({"type": "websocket.accept"})
        assert await receive() == {"type": "websocket.disconnect", "code": CLOSE_IDLE}
        with pytest.raises(OSError):
            await send({"type": "websocket.send", "bytes": b"late"})
        seen.append(True)

    seen = []

    async def main():
        guard = Guard(app, LIMITS)
        peer = Peer(websocket(), {"type": "websocket.connect"})
        started = asyncio.get_running_loop().time()
        await peer.run(guard)
        assert 0.25 < asyncio.get_running_loop().time() - started < 2
        assert peer.close_code() == CLOSE_IDLE and "no first message within 0.3 s" in peer.sent[-1]["reason"]
        assert seen and settled(guard)
    run(main())


def test_sessions_per_client_are_bounded(info):
    async def main():
        guard = Guard(ws_app, LIMITS)
        first = Peer(websocket(), {"type": "websocket.connect"}, {"type": "websocket.receive", "bytes": b"open"})
        task = first.run(guard)
        await asyncio.sleep(0.01)
        assert guard.clients["10.0.0.1"].sessions == 1
        second = Peer(websocket(), {"type": "websocket.connect"}, {"type": "websocket.receive", "bytes": b"open"})
        other = Peer(websocket("10.0.0.2"), {"type": "websocket.connect"},
                     {"type": "websocket.receive", "bytes": b"open"}, {"type": "websocket.disconnect", "code": 1000})
        await second.run(guard)
        await other.run(guard)
        assert second.close_code() == CLOSE_TOO_MANY and "holds 1 sessions" in second.sent[-1]["reason"]
        assert other.close_code() is None and other.sent[-1] == {"type": "websocket.send", "bytes": b"open"}
        first.inbox.put_nowait({"type": "websocket.disconnect", "code": 1000})
        await task
        assert settled(guard)
    run(main())


def test_other_scopes_pass_through():
    async def app(scope, receive, send):
        seen.append(scope["type"])

    seen = []
    asyncio.run(Guard(app, LIMITS)({"type": "lifespan"}, None, None))
    assert seen == ["lifespan"]


def test_a_view_whose_client_reads_nothing_ends_idle_with_the_reason():
    """ViewLink.send: a send the client's socket does not take within idle_timeout_s (its buffers full) ends the
    session with CLOSE_IDLE and the reason; one taken in time goes."""
    from isosr_server.api.routes.view import ViewLink
    from isosr_server.protocol import NoticeMsg, ProtocolError

    class Socket:
        def __init__(self, stall_s: float):
            self.stall_s, self.sent = stall_s, []

        async def send_bytes(self, data: bytes) -> None:
            await asyncio.sleep(self.stall_s)
            self.sent.append(data)

    def link(stall_s: float) -> ViewLink:
        view = ViewLink.__new__(ViewLink)  # the send alone: no engine or session behind it
        view.ws, view.limits = Socket(stall_s), Limits(idle_timeout_s=0.05)
        return view

    fast = link(0.0)
    asyncio.run(fast.send(NoticeMsg(text="hello")))
    assert len(fast.ws.sent) == 1
    with pytest.raises(ProtocolError, match="the client read no frame for 0.05 s") as caught:
        asyncio.run(link(5.0).send(NoticeMsg(text="hello")))
    assert caught.value.close_code == CLOSE_IDLE
