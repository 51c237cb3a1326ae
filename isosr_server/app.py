"""The FastAPI app of `isosr serve`: ``create_app(settings)``.

Endpoints (one router per resource in ``api/routes/``; each behind the token when the server has
one, except the health probes and the viewer page):
    WS   /v1/view                        a view session (protocol module docstring)
    POST /v1/upscale                     one low-res frame -> high-res buffers (msgpack) or an image
    WS   /v1/upscale/stream              low-res frames in, high-res frames out, in order
    GET  /v1/volumes, /v1/volumes/{name} the volumes offered; one with its histogram
    GET  /v1/modes                       the view modes offered, with the settings they read
    GET  /v2/health/live, /v2/health/ready (no token), /v2, /v2/models/isosr[-recon][/ready]  KServe v2
    GET  /metrics                        Prometheus
    GET  /, /static/...                  the browser viewer (no token)
    GET  /openapi.json                   the API's schema (behind the token); no docs pages (they would load
                                         scripts from a CDN)

Client mistakes get a 4xx with ``{"error": reason, "status": code}`` or an ``error`` message and a
WebSocket close with a code and reason, and are logged at INFO; only server faults log at ERROR.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.datastructures import State

from isosr_server import transport, ws_transport
from isosr_server.api.deps import require_token
from isosr_server.api.errors import add_exception_handlers
from isosr_server.api.main import api_router
from isosr_server.core.config import Settings
from isosr_server.engine import Engine
from isosr_server.guard import Guard
from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import PROTOCOL_VERSION, Limits
from isosr_server.sessions import SessionCounter, UpscaleSessions
from isosr_server.volumes import VolumeCatalog

log = logging.getLogger("isosr.server")


def uvicorn_options(limits: Limits, tls: ssl.SSLContext | None = None) -> dict:
    """uvicorn settings the protocol needs: WebSocket messages bounded by the limit (uvicorn closes
    bigger ones with 1009), no per-message deflate (frames are compressed already); the WebSocket
    protocol of :mod:`isosr_server.ws_transport` (a small limit before the first message, pings
    counted); the HTTP protocol of :mod:`isosr_server.transport`, which makes the TLS handshakes
    with ``tls`` (uvicorn is then given no certificate)."""
    return {"ws_max_size": limits.max_message_bytes, "ws_per_message_deflate": False,
            "ws": ws_transport.protocol_class(limits),
            # HTTP heads, their deadline and the open connections bounded (isosr_server.transport).
            "http": transport.protocol_class(limits, tls), "h11_max_incomplete_event_size": limits.max_header_bytes,
            "timeout_keep_alive": transport.KEEP_ALIVE_S,
            # With TLS, asyncio's loop: uvloop hands a new connection's first bytes to the protocol even when
            # it pauses reading in connection_made, so a ClientHello reached h11 before the handshake began.
            **({} if tls is None else {"loop": "asyncio"})}


def create_app(settings: Settings) -> FastAPI:
    """The app, its state on ``app.state`` (settings, engine, catalog, metrics, session registries,
    mesh extractions under way, ready); the lifespan loads the models and warms the device, then reports ready."""
    app = FastAPI(title="isosr", version=str(PROTOCOL_VERSION), lifespan=lifespan, docs_url=None, redoc_url=None,
                  openapi_url=None)  # served below, behind the token
    s = app.state
    s.settings = settings
    s.engine = Engine(settings)
    s.catalog = VolumeCatalog(settings.volumes, settings.max_volume_bytes)
    s.metrics = ServerMetrics(s.engine.gpu_memory, s.engine.volume_memory, s.engine.busy_seconds)
    s.view_sessions = SessionCounter(settings.limits.max_sessions)
    s.upscale_sessions = UpscaleSessions(settings.limits, s.engine.new_network)
    s.mesh_jobs = SessionCounter(settings.limits.max_mesh_jobs)
    s.ready = False
    app.add_middleware(Guard, limits=settings.limits)
    add_exception_handlers(app)
    app.include_router(api_router)
    app.add_api_route("/openapi.json", openapi_schema, include_in_schema=False, dependencies=[Depends(require_token)])
    return app


async def openapi_schema(request: Request) -> JSONResponse:
    """``GET /openapi.json``: the API's schema (behind the token when the server has one)."""
    return JSONResponse(request.app.openapi())


@asynccontextmanager
async def lifespan(app: FastAPI):
    s = app.state
    await s.engine.call(s.engine.start_sync)
    s.ready = True
    log.info("isosr server ready: device %s, upscale factor %d, volumes %s", s.engine.device,
             s.engine.upscale_factor, s.catalog.root or "procedural only")
    expiry = asyncio.create_task(expire_upscale_sessions(s))
    try:
        yield
    finally:
        s.ready = False
        expiry.cancel()
        s.engine.shutdown()


async def expire_upscale_sessions(s: State) -> None:
    """Drop idle upscale sessions every few seconds (a quarter of the idle timeout, at most 5 s)."""
    while True:
        await asyncio.sleep(min(5.0, s.settings.limits.idle_timeout_s / 4))
        s.upscale_sessions.expire(time.monotonic())
        s.metrics.sessions.labels("upscale").set(len(s.upscale_sessions))
