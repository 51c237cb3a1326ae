"""``GET /metrics``: the server's Prometheus metrics (text format)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST

from isosr_server.api.deps import MetricsDep, UpscaleSessionsDep, ViewSessionsDep, require_token

router = APIRouter(tags=["metrics"], dependencies=[Depends(require_token)])


@router.get("/metrics")
async def prometheus(metrics: MetricsDep, view_sessions: ViewSessionsDep, upscale_sessions: UpscaleSessionsDep):
    metrics.sessions.labels("view").set(view_sessions.count)
    metrics.sessions.labels("upscale").set(len(upscale_sessions))
    return Response(metrics.text(), media_type=CONTENT_TYPE_LATEST)
