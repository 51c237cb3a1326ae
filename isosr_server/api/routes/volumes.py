"""The volumes a server offers, by name (never by path).

    GET /v1/volumes          names, shapes, value ranges, suggested iso-values; ``error`` where a
                             volume cannot be opened or viewed, why
    GET /v1/volumes/{name}   one volume's info with its histogram (loads it) and, once a session
                             rendered it, where its voxels are (``device``: `MemoryStats`); 422
                             with the reason for one that cannot be opened
"""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, Depends

from isosr_server.api.deps import CatalogDep, EngineDep, require_token
from isosr_server.volumes import load_volume

router = APIRouter(prefix="/v1/volumes", tags=["volumes"], dependencies=[Depends(require_token)])


@router.get("")
async def list_volumes(catalog: CatalogDep):
    listing = await asyncio.to_thread(lambda: [catalog.info(n).to_json() for n in catalog.names()])  # reads headers
    return {"volumes": listing}


@router.get("/{name}")
async def get_volume(name: str, catalog: CatalogDep, engine: EngineDep):
    info = (await load_volume(catalog, name))[1].to_json()
    memory = engine.volume_memory().get(name)
    return info | {"device": None if memory is None else memory.to_json()}
