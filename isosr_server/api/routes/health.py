"""The server's health and metadata, KServe v2 (Open Inference Protocol) style.

    GET /v2/health/live    200 while the process serves requests          (no token)
    GET /v2/health/ready   200 once the models are loaded, 503 before     (no token)
    GET /v2                server metadata: name, version, extensions      (token)

The probes need no token: orchestrators' probes carry none, and they reveal nothing but the
status. Server metadata lists as ``extensions`` the isosr APIs beyond the protocol's own.

Server metadata stays behind the token, as every route but the probes and the viewer page does:
it holds no secret, but its exact version and extensions tell a stranger which release and APIs
to aim at, and nothing that calls without the token (probes, load balancers) needs it. KServe
clients send the token as a header (tritonclient: ``get_server_metadata(headers={"Authorization":
"Bearer TOKEN"})``).
"""

from __future__ import annotations

from importlib.metadata import version

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from isosr_server.api.deps import ReadyDep, require_token

EXTENSIONS = ("isosr-view", "isosr-upscale", "isosr-volumes", "prometheus-metrics", "binary_tensor_data")

router = APIRouter(tags=["health"])


@router.get("/v2/health/live")
async def live():
    return {"live": True}


@router.get("/v2/health/ready")
async def ready(is_ready: ReadyDep):
    return JSONResponse({"ready": is_ready}, 200 if is_ready else 503)


@router.get("/v2", dependencies=[Depends(require_token)])
async def server_metadata():
    """Name, version and extensions; behind the token (the module docstring says why)."""
    return {"name": "isosr", "version": version("isosr"), "extensions": list(EXTENSIONS)}
