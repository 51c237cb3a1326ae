"""The volumes a server offers, by name (never by path).

    GET /v1/volumes          names, shapes, value ranges, suggested iso-values; ``error`` where a
                             volume cannot be opened or viewed, why
    GET /v1/volumes/{name}   one volume's info with its histogram (loads it) and, once a session
                             rendered it, where its voxels are (``device``: `MemoryStats`); 422
                             with the reason for one that cannot be opened
    GET /v1/volumes/{name}/slices/{x|y|z}?index=K[&iso=V]
                             the orthogonal slice across that axis at voxel K as a PNG, the iso
                             contour (data units) drawn on it (:func:`isosr_render.slices.slice_image`)
"""

from __future__ import annotations

import asyncio
from typing import Literal

import torch
from fastapi import APIRouter, Depends, Response

from isosr_render.slices import AXES, slice_image
from isosr_server.api.deps import CatalogDep, EngineDep, require_token
from isosr_server.encoding import encode_image
from isosr_server.protocol import ProtocolError
from isosr_server.volumes import load_volume, session_iso

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


@router.get("/{name}/slices/{axis}", response_class=Response, responses={200: {"content": {"image/png": {}}}})
async def get_slice(name: str, axis: Literal[AXES], index: int, catalog: CatalogDep, iso: float | None = None):
    volume = (await load_volume(catalog, name))[0]
    normalized = None if iso is None else session_iso(volume, name, iso, False, "iso")
    try:
        rgb = await asyncio.to_thread(slice_image, volume, AXES.index(axis), index, normalized)
    except ValueError as e:
        raise ProtocolError(str(e)) from None
    return Response(encode_image(torch.from_numpy(rgb), "png", 100), media_type="image/png")
