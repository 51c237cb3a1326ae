"""The browser viewer: the page at ``GET /`` and its files under ``/static``.

Plain ES modules shipped in ``isosr_server/static`` (package data): no build step, nothing
fetched from elsewhere at run time (the Content-Security-Policy allows this origin only).
The page itself needs no token; every request it makes carries the one the user enters.
The files under ``/static`` are public code that any origin may load (CORS ``*``): the notebook
widget (:mod:`isosr_client.notebook`) imports ``session.js`` and ``video.js`` from its page's origin.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
CSP = ("default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; style-src 'self'; "
       "script-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'")



class PublicStaticFiles(StaticFiles):
    """Static files with ``Access-Control-Allow-Origin: *`` (no credentials travel with them)."""

    def file_response(self, *args, **kwargs):
        response = super().file_response(*args, **kwargs)
        response.headers["Access-Control-Allow-Origin"] = "*"
        return response


router = APIRouter(tags=["viewer"])
router.mount("/static", PublicStaticFiles(directory=STATIC_DIR), name="viewer-static")


@router.get("/", include_in_schema=False)
async def viewer_page():
    return FileResponse(STATIC_DIR / "index.html", headers={"Content-Security-Policy": CSP,
                                                            "Cache-Control": "no-cache"})
