"""Every router of the API, in one ``api_router`` that `create_app` includes."""

from __future__ import annotations

from fastapi import APIRouter

from isosr_server.api.routes import health, metrics, models, modes, upscale, view, viewer, volumes

api_router = APIRouter()
for module in (health, models, modes, volumes, upscale, view, metrics, viewer):
    api_router.include_router(module.router)
