"""What one replica of a multi-replica service adds to the app (no Ray import; :mod:`isosr_server.cluster`
calls `as_replica`).

- The app's metrics carry ``replica="<name>"`` on every series (`ServerMetrics.const_labels`).
- Every HTTP response and every WebSocket handshake names the replica: ``x-isosr-replica``.
- Upscale sessions (``POST /v1/upscale`` with ``session``, ``POST /v2/models/{isosr,isosr-recon}/infer`` with
  ``sequence_id``) are routed by the request router on the ``x-session-id`` header
  (`SESSION_HEADER`), so their requests must carry the id there too: a successful request whose
  body names a session the header does not gets 400 instead of its answer (else it would land on
  any replica and silently lose its recurrent state).
- A session that continues its recurrence (a frame with flow and no reset) on a replica that
  has not served it before (its replica is gone, or the replicas changed) had its state started
  afresh: the answer says so with ``x-isosr-session-restarted: 1``.

- A view WebSocket that offers permessage-deflate (every browser's does) gets it from Serve's proxy
  (behind ``--ingress haproxy``: from the replica's own server, uvicorn as Serve configures it), which then
  deflates each of its frames on its one event loop: the replica warns once, naming the fix (the reverse
  proxy in front drops the offer, docs/serving.md).

Replicas that share a GPU (``--gpus-per-replica`` under 1) run their kernels together only under
NVIDIA's Multi-Process Service (`mps_running`); without it their contexts take turns on the GPU.

The middleware reads the body the app reads (after the guard has bounded it) and decides when
the app's answer starts; a replica remembers the sessions it served for ``idle_timeout_s``, as
long as the app keeps their state. (The app may also drop a state early to stay within
``max_upscale_bytes``; that restart is not reported, as on a single server.)
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import msgspec
from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from isosr_server.codecs.kserve import HEADER_LENGTH
from isosr_server.protocol import REPLICA_HEADER, RESTARTED_HEADER, SESSION_HEADER

__all__ = ["REPLICA_HEADER", "RESTARTED_HEADER", "SESSION_HEADER", "ReplicaMiddleware", "as_replica", "session_of"]
UPSCALE_PATH = "/v1/upscale"
INFER_SUFFIX = "/infer"
NIL = b"\xc0"  # msgpack nil
MPS_PIPE_DIRECTORY = "/tmp/nvidia-mps"  # CUDA's default, where CUDA_MPS_PIPE_DIRECTORY is unset
DEFLATE_OFFER = b"permessage-deflate"
log = logging.getLogger("isosr.server")


class _UpscalePeek(msgspec.Struct):
    session: str | None = None
    flow: msgspec.Raw = msgspec.Raw(NIL)
    reset: bool = False


class _Named(msgspec.Struct):
    name: str = ""


class _InferPeek(msgspec.Struct):
    inputs: list[_Named] = []
    parameters: dict[str, object] = {}


def session_of(path: str, headers: dict[str, str], body: bytes) -> tuple[str | None, bool]:
    """``(session id or None, whether the frame continues a recurrence)`` of an upscale request's body."""
    try:
        if path == UPSCALE_PATH:
            peek = msgspec.msgpack.decode(body, type=_UpscalePeek)
            return peek.session, bytes(peek.flow) != NIL and not peek.reset
        n = int(headers.get(HEADER_LENGTH, len(body)))
        infer = msgspec.json.decode(body[:n], type=_InferPeek)
    except (msgspec.DecodeError, ValueError):
        return None, False
    sequence = infer.parameters.get("sequence_id", 0)
    session = None if sequence in (0, "") else str(sequence)
    return session, any(t.name == "flow" for t in infer.inputs) and not infer.parameters.get("sequence_start", False)


def mps_running(environ: Mapping[str, str] = os.environ) -> bool:
    """Whether an MPS control daemon (``nvidia-cuda-mps-control -d``) serves this machine's CUDA
    programs started with ``environ``: its control socket in ``CUDA_MPS_PIPE_DIRECTORY``."""
    return (Path(environ.get("CUDA_MPS_PIPE_DIRECTORY") or MPS_PIPE_DIRECTORY) / "control").exists()


def as_replica(app: FastAPI, replica: str) -> None:
    """Make ``app`` (`create_app`'s, not started yet) the replica named ``replica``: label its
    metrics and install `ReplicaMiddleware` with its limits."""
    limits = app.state.settings.limits
    app.state.metrics.const_labels = {"replica": replica}
    app.add_middleware(ReplicaMiddleware, replica=replica, idle_timeout_s=limits.idle_timeout_s,
                       max_sessions=limits.max_sessions)


class ReplicaMiddleware:
    """``app.add_middleware(ReplicaMiddleware, replica=id, idle_timeout_s=...)``.

    Attributes:
        served: the sessions this replica served, with when they were last used (monotonic s).
    """

    def __init__(self, app: ASGIApp, replica: str, idle_timeout_s: float, max_sessions: int) -> None:
        self.app, self.replica = app, replica
        self.idle_timeout_s, self.max_sessions = idle_timeout_s, max_sessions
        self.served: OrderedDict[str, float] = OrderedDict()
        self.deflate_warned = False

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        named = (REPLICA_HEADER.encode(), self.replica.encode())
        if scope["type"] == "websocket":
            self.warn_of_deflate(scope)
            async def send_ws(message: Message) -> None:
                if message["type"] == "websocket.accept":
                    message = {**message, "headers": [*message.get("headers", []), named]}
                await send(message)
            return await self.app(scope, receive, send_ws)
        path = scope.get("path", "")
        if scope["type"] != "http" or scope.get("method") != "POST" or not (
                path == UPSCALE_PATH or path.endswith(INFER_SUFFIX)):
            async def send_http(message: Message) -> None:
                if message["type"] == "http.response.start":
                    message = {**message, "headers": [*message.get("headers", []), named]}
                await send(message)
            return await self.app(scope, receive, send_http)
        await self.upscale(scope, receive, send, named)

    def warn_of_deflate(self, scope: Scope) -> None:
        """Once: a WebSocket offered permessage-deflate, which Serve's proxy or this replica's own server takes
        (module docstring)."""
        if not self.deflate_warned and any(k.lower() == b"sec-websocket-extensions" and DEFLATE_OFFER in v.lower()
                                           for k, v in scope.get("headers", [])):
            self.deflate_warned = True
            log.warning("replica %s: a WebSocket offered permessage-deflate (browsers do), and Serve's proxy (behind "
                        "HAProxy: this replica's own server) deflates each of its frames on its one event loop, "
                        "which then bounds every session's frames there: let "
                        "the reverse proxy in front drop the offer (nginx: proxy_set_header Sec-WebSocket-Extensions "
                        "\"\"; docs/serving.md, 'Replicas beyond this machine')", self.replica)

    async def upscale(self, scope: Scope, receive: Receive, send: Send, named: tuple[bytes, bytes]) -> None:
        """An upscale request: keep the body the app reads; check and mark the answer when it starts."""
        chunks: list[bytes] = []
        replaced = False

        async def keep() -> Message:
            message = await receive()
            if message["type"] == "http.request":
                chunks.append(message.get("body", b""))
            return message

        async def mark(message: Message) -> None:
            nonlocal replaced
            if replaced:
                return
            if message["type"] == "http.response.start":
                extra = [named]
                if message["status"] == 200:
                    headers = {k.decode().lower(): v.decode() for k, v in scope["headers"]}
                    session, continues = session_of(scope["path"], headers, b"".join(chunks))
                    if session is not None and headers.get(SESSION_HEADER) != session:
                        replaced = True
                        return await refuse(send, named, f"behind replicas a session's requests carry its id in "
                                                         f"the {SESSION_HEADER} header too (the routing key)")
                    if session is not None:
                        if continues and not self.knows(session):
                            extra.append((RESTARTED_HEADER.encode(), b"1"))
                        self.remember(session)
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        await self.app(scope, keep, mark)

    def knows(self, session: str) -> bool:
        used = self.served.get(session)
        return used is not None and time.monotonic() - used <= self.idle_timeout_s

    def remember(self, session: str) -> None:
        self.served[session] = time.monotonic()
        self.served.move_to_end(session)
        while len(self.served) > self.max_sessions:
            self.served.popitem(last=False)


async def refuse(send: Send, named: tuple[bytes, bytes], reason: str) -> None:
    body = json.dumps({"error": reason, "status": 400}).encode()
    await send({"type": "http.response.start", "status": 400,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            named]})
    await send({"type": "http.response.body", "body": body})
