"""The volumes a server offers, by name (never by path).

    GET /v1/volumes          names, shapes, value ranges, suggested iso-values
    GET /v1/volumes/{name}   one volume's info with its histogram (loads it)
"""

from __future__ import annotations

from fastapi import APIRouter, Depends

from isosr_server.api.deps import CatalogDep, require_token
from isosr_server.volumes import load_volume

router = APIRouter(prefix="/v1/volumes", tags=["volumes"], dependencies=[Depends(require_token)])


@router.get("")
async def list_volumes(catalog: CatalogDep):
    return {"volumes": [catalog.info(n).to_json() for n in catalog.names()]}


@router.get("/{name}")
async def get_volume(name: str, catalog: CatalogDep):
    return (await load_volume(catalog, name))[1].to_json()
