"""The FastAPI app of `isosr serve`: ``create_app(config)``.

Endpoints (every one behind the token when the server has one):
    POST /v1/upscale           one low-res frame -> high-res buffers (msgpack) or an image
    WS   /v1/upscale/stream    low-res frames in, high-res frames out, in order, one state per connection
    WS   /v1/view              a view session (protocol module docstring)
    GET  /v1/volumes           the volumes offered (name, shape, value range, suggested iso)
    GET  /v1/volumes/{name}    one volume's info with its histogram (loads it)
    GET  /v2/health/live, /v2/health/ready, /v2/models/isosr, /metrics

Client mistakes get a 4xx with ``{"error": reason, "status": code}`` or an ``error`` message and a
WebSocket close with a code and reason, and are logged at INFO; only server faults log at ERROR.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.websockets import WebSocketDisconnect, WebSocketState

from isosr_render.catalog import shared_volumes_dir
from isosr_server.engine import Engine, EngineConfig
from isosr_server.guard import Guard
from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import (CLOSE_IDLE, CLOSE_INTERNAL, CLOSE_NOT_FOUND, CLOSE_POLICY, CLOSE_UNAUTHORIZED,
                                   MSGPACK_MEDIA_TYPE, PROTOCOL_VERSION, SUBPROTOCOL, TOKEN_HEADER,
                                   TOKEN_SUBPROTOCOL_PREFIX, VOLUME_NAME, ErrorMsg, FocusMsg, Limits, OpenMsg,
                                   ProtocolError, ReadyMsg, UpscaleRequest, UpscaleResponse, ViewSettings,
                                   CLIENT_VIEW_MESSAGES, limits_to_wire, pack, parse)
from isosr_server.sessions import (DEFAULT_CAMERA, RateLimiter, SessionCounter, UpscaleSessions, ViewSession,
                                   ViewState, run_frames, to_camera)
from isosr_server.viewer import add_viewer
from isosr_server.volumes import UnknownVolume, VolumeCatalog

log = logging.getLogger("isosr.server")

LOOPBACK_HOSTS = ("127.0.0.1", "::1", "localhost")
BODY_TYPES = (MSGPACK_MEDIA_TYPE, "application/x-msgpack", "application/octet-stream")
IMAGE_TYPES = {"image/png": "png", "image/jpeg": "jpeg", "image/webp": "webp"}


def default_volumes_dir() -> Path | None:
    """The shared volumes folder (``../shared/volumes`` or ``$ISOSR_SHARED_VOLUMES``) if it exists."""
    root = shared_volumes_dir()
    return root if root.is_dir() else None


@dataclass(frozen=True)
class ServerConfig:
    """Everything `isosr serve` configures.

    Attributes:
        host: the address to bind; any but loopback requires a token.
        volumes: the volumes folder (None: procedural volumes only).
        engine: model, device, precision.
        token: the shared secret clients must send (None: no check, loopback only).
        limits: the protocol limits.
    """

    host: str = "127.0.0.1"
    volumes: Path | None = None
    engine: EngineConfig = field(default_factory=EngineConfig)
    token: str | None = None
    limits: Limits = field(default_factory=Limits)

    def __post_init__(self):
        if self.host not in LOOPBACK_HOSTS and not self.token:
            raise ValueError(f"binding {self.host} exposes the server beyond this machine: give --token "
                             f"(or set ISOSR_TOKEN)")
        if self.token is not None and len(self.token) < 8:
            raise ValueError("the token must have at least 8 characters")


def uvicorn_options(limits: Limits) -> dict:
    """uvicorn settings the protocol needs: WebSocket messages bounded by the limit (uvicorn closes
    bigger ones with 1009), no per-message deflate (frames are compressed already)."""
    return {"ws_max_size": limits.max_message_bytes, "ws_per_message_deflate": False}


def _close_reason(reason: str) -> str:
    """A close reason within the 123 bytes a close frame allows."""
    return reason.encode()[:120].decode(errors="ignore")


def create_app(config: ServerConfig) -> FastAPI:
    """The app: loads the model and warms the device in its lifespan, then reports ready."""
    limits = config.limits
    catalog = VolumeCatalog(config.volumes)
    engine = Engine(config.engine)
    metrics = ServerMetrics(engine.gpu_memory)
    view_sessions = SessionCounter(limits.max_sessions)
    upscale_sessions = UpscaleSessions(limits, engine.new_upscaler)
    status = {"ready": False}

    async def expire_loop():
        while True:
            await asyncio.sleep(min(5.0, limits.idle_timeout_s / 4))
            upscale_sessions.expire(time.monotonic())
            metrics.sessions.labels("upscale").set(len(upscale_sessions))

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        await engine.call(engine.start_sync)
        status["ready"] = True
        log.info("isosr server ready: device %s, upscale factor %d, volumes %s", engine.device,
                 engine.upscale_factor, catalog.root or "procedural only")
        expiry = asyncio.create_task(expire_loop())
        try:
            yield
        finally:
            status["ready"] = False
            expiry.cancel()
            engine.shutdown()

    # ---- auth -------------------------------------------------------------------------------

    def token_ok(given: str | None) -> bool:
        return config.token is None or (given is not None
                                        and secrets.compare_digest(given.encode(), config.token.encode()))

    def header_token(headers) -> str | None:
        auth = headers.get("authorization", "")
        return auth[7:] if auth.lower().startswith("bearer ") else headers.get(TOKEN_HEADER)

    def require_token(request: Request) -> None:
        if not token_ok(header_token(request.headers)):
            raise HTTPException(401, "missing or wrong token (Authorization: Bearer TOKEN)")

    async def accept_ws(ws: WebSocket) -> bool:
        """Accept the handshake; with a missing or wrong token (header or subprotocol) close it at once
        with CLOSE_UNAUTHORIZED and the reason (a browser sees a close code, never a denied handshake's status)."""
        offered = [p.strip() for p in ws.headers.get("sec-websocket-protocol", "").split(",") if p.strip()]
        token = header_token(ws.headers) or next((p[len(TOKEN_SUBPROTOCOL_PREFIX):] for p in offered
                                                  if p.startswith(TOKEN_SUBPROTOCOL_PREFIX)), None)
        await ws.accept(subprotocol=SUBPROTOCOL if SUBPROTOCOL in offered else None)
        if token_ok(token):
            return True
        await end_ws(ws, "auth", ProtocolError("missing or wrong token", CLOSE_UNAUTHORIZED, 401))
        return False

    app = FastAPI(title="isosr", version=str(PROTOCOL_VERSION), lifespan=lifespan)
    app.add_middleware(Guard, limits=limits)
    http = APIRouter(dependencies=[Depends(require_token)])

    @app.exception_handler(StarletteHTTPException)  # FastAPI's HTTPException and the router's 404 / 405
    async def http_error(request: Request, e: StarletteHTTPException):
        if e.status_code < 500:
            log.info("%s %s: %d %s", request.method, request.url.path, e.status_code, e.detail)
        metrics.error("http", e.status_code)
        return JSONResponse({"error": str(e.detail), "status": e.status_code}, e.status_code, headers=e.headers)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, e: RequestValidationError):
        metrics.error("http", 422)
        return JSONResponse({"error": str(e.errors())[:500], "status": 422}, 422)

    @app.exception_handler(ProtocolError)
    async def protocol_error(request: Request, e: ProtocolError):
        log.info("%s %s: %d %s", request.method, request.url.path, e.http_status, e.reason)
        metrics.error("http", e.http_status)
        return JSONResponse({"error": e.reason, "status": e.http_status}, e.http_status)

    # ---- HTTP -------------------------------------------------------------------------------

    @http.get("/v2/health/live")
    async def live():
        return {"live": True}

    @http.get("/v2/health/ready")
    async def ready():
        return JSONResponse({"ready": status["ready"]}, 200 if status["ready"] else 503)

    @http.get("/v2/models/isosr")
    async def model():
        if not status["ready"]:
            raise HTTPException(503, "the model is loading")
        floats = ["FP32", "FP16"]
        return {"name": "isosr", "versions": [str(PROTOCOL_VERSION)], "platform": "pytorch", **engine.model_info(),
                "inputs": [{"name": "mask", "datatype": floats, "shape": [-1, -1]},
                           {"name": "normal", "datatype": floats, "shape": [-1, -1, 3]},
                           {"name": "depth", "datatype": floats, "shape": [-1, -1]},
                           {"name": "flow", "datatype": floats, "shape": [-1, -1, 2], "optional": True}],
                "outputs": [{"name": "mask", "datatype": "FP32", "shape": [-1, -1]},
                            {"name": "normal", "datatype": "FP32", "shape": [-1, -1, 3]},
                            {"name": "depth", "datatype": "FP32", "shape": [-1, -1]},
                            {"name": "ao", "datatype": "FP32", "shape": [-1, -1]}],
                "image_outputs": list(IMAGE_TYPES.values())}

    @http.get("/metrics")
    async def prometheus():
        metrics.sessions.labels("view").set(view_sessions.count)
        metrics.sessions.labels("upscale").set(len(upscale_sessions))
        return Response(metrics.text(), media_type=CONTENT_TYPE_LATEST)

    @http.get("/v1/volumes")
    async def volumes():
        return {"volumes": [catalog.info(n).to_json() for n in catalog.names()]}

    @http.get("/v1/volumes/{name}")
    async def volume(name: str):
        return (await load_volume(name))[1].to_json()

    async def load_volume(name: str):
        """The named volume and its info (loaded off the event loop); 400 / 404 for bad names."""
        if not VOLUME_NAME.match(name):
            raise ProtocolError(f"bad volume name {name!r}: a name from GET /v1/volumes, never a path"[:200])
        try:
            return await asyncio.to_thread(catalog.load, name)
        except UnknownVolume as e:
            raise ProtocolError(str(e), CLOSE_NOT_FOUND, 404) from None

    def check_upscale(msg: UpscaleRequest) -> None:
        h, w = msg.mask.shape
        limits.check_size(w * engine.upscale_factor, h * engine.upscale_factor, "the upscaled frame")

    async def run_upscale(upscaler, msg: UpscaleRequest):
        try:
            return await engine.call(engine.upscale_sync, upscaler, msg)
        except ValueError as e:  # the network refuses this frame (e.g. fp16 beyond its depth range)
            raise ProtocolError(f"cannot upscale this frame: {e}", http_status=422) from None

    @http.post("/v1/upscale")
    async def upscale(request: Request):
        kind = request.headers.get("content-type", MSGPACK_MEDIA_TYPE).split(";")[0].strip()
        if kind not in BODY_TYPES:
            raise HTTPException(415, f"send a msgpack body ({MSGPACK_MEDIA_TYPE}), not {kind}")
        # A body up to twice the limit is read to its end (kept only up to the limit), so that the
        # client, still sending, gets the 413 and its reason rather than a reset connection.
        drain = 2 * limits.max_message_bytes
        declared = request.headers.get("content-length", "")
        too_big = ProtocolError(f"body exceeds the limit of {limits.max_message_bytes} bytes", http_status=413)
        if declared.isdigit() and int(declared) > drain:
            raise too_big
        body, total = bytearray(), 0
        async for chunk in request.stream():
            total += len(chunk)
            if total > drain:
                raise too_big
            if total <= limits.max_message_bytes:
                body += chunk
        if total > limits.max_message_bytes:
            raise too_big
        msg = parse(bytes(body), limits, (UpscaleRequest,))
        accept = request.headers.get("accept", "").split(",")[0].split(";")[0].strip()
        if msg.output == "buffers" and accept in IMAGE_TYPES:
            msg = replace(msg, output=IMAGE_TYPES[accept])
        check_upscale(msg)
        upscaler = upscale_sessions.get(msg.session) if msg.session else engine.new_upscaler()
        image, buffers, times = await run_upscale(upscaler, msg)
        h, w = msg.mask.shape
        f = engine.upscale_factor
        if image is not None:
            metrics.frame("upscale", msg.output, False, times, len(image))
            return Response(image, media_type=f"image/{msg.output}", headers={"x-isosr-times": json.dumps(times)})
        nbytes = sum(a.nbytes for a in buffers.values())
        metrics.frame("upscale", "buffers", False, times, nbytes)
        reply = UpscaleResponse(0, w * f, h * f, "buffers", times, nbytes, buffers=buffers)
        return Response(pack(reply.to_wire()), media_type=MSGPACK_MEDIA_TYPE)

    app.include_router(http)
    add_viewer(app)

    # ---- WebSockets -------------------------------------------------------------------------

    async def receive(ws: WebSocket, limiter: RateLimiter) -> bytes:
        """The next binary message within the idle timeout and the rate limit."""
        try:
            message = await asyncio.wait_for(ws.receive(), limits.idle_timeout_s)
        except TimeoutError:
            raise ProtocolError(f"no message for {limits.idle_timeout_s:g} s", CLOSE_IDLE, 408) from None
        if message["type"] == "websocket.disconnect":
            raise WebSocketDisconnect(message.get("code", 1000))
        if not limiter.allow():
            raise ProtocolError(f"more than {limits.max_messages_per_s:g} messages a second", CLOSE_POLICY, 429)
        if message.get("bytes") is None:
            raise ProtocolError("text messages are not part of the protocol: send binary msgpack")
        return message["bytes"]

    async def end_ws(ws: WebSocket, kind: str, e: BaseException) -> None:
        """Close a WebSocket after an error: an error message and a close code with the reason."""
        if isinstance(e, WebSocketDisconnect):
            return
        if isinstance(e, ProtocolError):
            code, reason = e.close_code, e.reason
            log.info("%s session closed: %d %s", kind, code, reason)
        else:
            code, reason = CLOSE_INTERNAL, "internal server error"
            log.error("%s session failed", kind, exc_info=e)
        metrics.error(kind, code)
        if ws.application_state == WebSocketState.CONNECTED and ws.client_state == WebSocketState.CONNECTED:
            try:
                await ws.send_bytes(pack(ErrorMsg(code, reason).to_wire()))
                await ws.close(code, _close_reason(reason))
            except Exception:  # the client went away meanwhile
                pass

    @app.websocket("/v1/view")
    async def view(ws: WebSocket):
        if not await accept_ws(ws):
            return
        limiter = RateLimiter(limits.max_messages_per_s)
        counted, tasks = False, []
        try:
            session = await open_view(ws, limiter)
            view_sessions.acquire("view sessions")
            counted = True
            metrics.sessions.labels("view").set(view_sessions.count)
            renderer = await engine.call(engine.renderer_sync, session.volume_name, session.volume)
            upscaler, recon = engine.new_upscaler(), engine.new_recon_stream()

            async def make(job):
                return await engine.call(engine.view_frame_sync, renderer, upscaler, recon, job.spec, job.encoding,
                                         job.quality)

            async def send(data: bytes, msg) -> None:
                try:
                    await asyncio.wait_for(ws.send_bytes(data), limits.idle_timeout_s)
                except TimeoutError:
                    raise ProtocolError(f"the client read no frame for {limits.idle_timeout_s:g} s", CLOSE_IDLE,
                                        408) from None
                metrics.frame("view", msg.mode, msg.refined, msg.times, msg.nbytes)

            async def updates():
                while True:
                    session.apply(parse(await receive(ws, limiter), limits, CLIENT_VIEW_MESSAGES))

            tasks = [asyncio.create_task(run_frames(session, make, send, limits.max_fps)),
                     asyncio.create_task(updates())]
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                task.result()  # raises what ended the session
        except Exception as e:
            await end_ws(ws, "view", e)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if counted:
                view_sessions.release()
                metrics.sessions.labels("view").set(view_sessions.count)

    async def open_view(ws: WebSocket, limiter: RateLimiter) -> ViewSession:
        """Read ``open``, load the volume, answer ``ready``: the new session."""
        msg = parse(await receive(ws, limiter), limits, (OpenMsg,))
        volume, info = await load_volume(msg.volume)
        settings = ViewSettings().updated(msg.settings, limits)
        iso = info.iso if msg.iso is None else msg.iso
        normalized = msg.iso if msg.iso is not None and msg.iso_normalized else volume.normalized_iso(iso)
        try:
            camera = to_camera(msg.camera or DEFAULT_CAMERA)
        except ValueError as e:
            raise ProtocolError(f"open.camera: {e}") from None
        state = ViewState(settings, camera, normalized, FocusMsg("none"),
                          msg.camera.seq if msg.camera and msg.camera.seq is not None else -1)
        session = ViewSession(secrets.token_hex(8), msg.volume, volume, state, engine.upscale_factor, limits)
        ready = ReadyMsg(session.id, info.to_json() | {"iso_normalized": normalized}, vars(settings),
                         engine.upscale_factor, limits_to_wire(limits))
        await ws.send_bytes(pack(ready.to_wire()))
        log.info("view session %s opened on %s (%s %dx%d)", session.id, msg.volume, settings.mode, settings.width,
                 settings.height)
        return session

    @app.websocket("/v1/upscale/stream")
    async def upscale_stream(ws: WebSocket):
        if not await accept_ws(ws):
            return
        limiter = RateLimiter(limits.max_messages_per_s)
        opened = False
        try:
            upscaler = upscale_sessions.open_stream()
            opened = True
            seq = 0
            while True:
                msg = parse(await receive(ws, limiter), limits, (UpscaleRequest,))
                if msg.session is not None:
                    raise ProtocolError("a stream is one session: leave out the session field")
                check_upscale(msg)
                image, buffers, times = await run_upscale(upscaler, msg)
                h, w = msg.mask.shape
                f = engine.upscale_factor
                nbytes = len(image) if image is not None else sum(a.nbytes for a in buffers.values())
                reply = UpscaleResponse(seq, w * f, h * f, msg.output, times, nbytes, buffers=buffers, image=image)
                await ws.send_bytes(pack(reply.to_wire()))
                metrics.frame("upscale", msg.output, False, times, nbytes)
                seq += 1
        except Exception as e:
            await end_ws(ws, "upscale", e)
        finally:
            if opened:
                upscale_sessions.close_stream()

    return app
