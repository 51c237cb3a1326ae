"""Typed dependencies: the app's state (set on ``app.state`` by `create_app`) and the token check.

Routes reach the engine, catalog, settings, metrics and session registries only through these,
so a test can replace any of them: ``app.dependency_overrides[get_engine] = lambda: fake``.
Each takes the `HTTPConnection`, so HTTP and WebSocket routes use the same ones.
"""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, HTTPException
from fastapi.requests import HTTPConnection

from isosr_server.core.config import Settings
from isosr_server.engine import Engine
from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import TOKEN_HEADER, TOKEN_SUBPROTOCOL_PREFIX, Limits
from isosr_server.sessions import SessionCounter, UpscaleSessions
from isosr_server.volumes import VolumeCatalog


def get_settings(conn: HTTPConnection) -> Settings:
    return conn.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_limits(settings: SettingsDep) -> Limits:
    return settings.limits


LimitsDep = Annotated[Limits, Depends(get_limits)]


def get_engine(conn: HTTPConnection) -> Engine:
    return conn.app.state.engine


EngineDep = Annotated[Engine, Depends(get_engine)]


def get_catalog(conn: HTTPConnection) -> VolumeCatalog:
    return conn.app.state.catalog


CatalogDep = Annotated[VolumeCatalog, Depends(get_catalog)]


def get_metrics(conn: HTTPConnection) -> ServerMetrics:
    return conn.app.state.metrics


MetricsDep = Annotated[ServerMetrics, Depends(get_metrics)]


def get_view_sessions(conn: HTTPConnection) -> SessionCounter:
    """The count of live view sessions, bounded by ``max_sessions``."""
    return conn.app.state.view_sessions


ViewSessionsDep = Annotated[SessionCounter, Depends(get_view_sessions)]


def get_upscale_sessions(conn: HTTPConnection) -> UpscaleSessions:
    return conn.app.state.upscale_sessions


UpscaleSessionsDep = Annotated[UpscaleSessions, Depends(get_upscale_sessions)]


def get_mesh_jobs(conn: HTTPConnection) -> SessionCounter:
    """The count of mesh extractions under way, bounded by ``limits.max_mesh_jobs``."""
    return conn.app.state.mesh_jobs


MeshJobsDep = Annotated[SessionCounter, Depends(get_mesh_jobs)]


def is_ready(conn: HTTPConnection) -> bool:
    """Whether the models are loaded and the device warmed (the lifespan's start-up is done)."""
    return conn.app.state.ready


ReadyDep = Annotated[bool, Depends(is_ready)]


def require_ready(ready: ReadyDep) -> None:
    """503 while the models load."""
    if not ready:
        raise HTTPException(503, "the model is loading")


def given_token(conn: HTTPConnection) -> str | None:
    """The token a request carries: ``Authorization: Bearer TOKEN``, else the ``x-isosr-token``
    header, else (WebSockets only: browsers cannot set headers) the ``isosr-token.TOKEN`` subprotocol."""
    auth = conn.headers.get("authorization", "")
    token = auth[7:] if auth.lower().startswith("bearer ") else conn.headers.get(TOKEN_HEADER)
    if token is None and conn.scope["type"] == "websocket":
        token = next((p[len(TOKEN_SUBPROTOCOL_PREFIX):] for p in conn.scope.get("subprotocols", ())
                      if p.startswith(TOKEN_SUBPROTOCOL_PREFIX)), None)
    return token


def is_authorized(conn: HTTPConnection, settings: SettingsDep) -> bool:
    """Whether the request may pass: the server has no token, or the request carries it (constant-time compare)."""
    if settings.token is None:
        return True
    token = given_token(conn)
    return token is not None and secrets.compare_digest(token.encode(), settings.token.encode())


AuthorizedDep = Annotated[bool, Depends(is_authorized)]


def require_token(authorized: AuthorizedDep) -> None:
    """HTTP routes' token check: 401 with the reason. (WebSocket routes accept first and then close
    with CLOSE_UNAUTHORIZED: a browser sees a close code, never a denied handshake's status.)"""
    if not authorized:
        raise HTTPException(401, "missing or wrong token (Authorization: Bearer TOKEN)")
