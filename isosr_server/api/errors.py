"""Error answers of HTTP routes: ``{"error": reason, "status": code}`` with the status, counted in
the metrics; client mistakes log at INFO (only server faults log at ERROR)."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from isosr_server.api.deps import get_metrics
from isosr_server.protocol import ProtocolError

log = logging.getLogger("isosr.server")


def error_response(request: Request, status: int, reason: str, headers: dict | None = None) -> JSONResponse:
    get_metrics(request).error("http", status)
    return JSONResponse({"error": reason, "status": status}, status, headers=headers)


async def http_error(request: Request, e: StarletteHTTPException) -> JSONResponse:
    """FastAPI's HTTPException and the router's 404 / 405."""
    if e.status_code < 500:
        log.info("%s %s: %d %s", request.method, request.url.path, e.status_code, e.detail)
    return error_response(request, e.status_code, str(e.detail), e.headers)


async def validation_error(request: Request, e: RequestValidationError) -> JSONResponse:
    return error_response(request, 422, str(e.errors())[:500])


async def protocol_error(request: Request, e: ProtocolError) -> JSONResponse:
    log.info("%s %s: %d %s", request.method, request.url.path, e.http_status, e.reason)
    return error_response(request, e.http_status, e.reason)


def add_exception_handlers(app: FastAPI) -> None:
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(ProtocolError, protocol_error)
