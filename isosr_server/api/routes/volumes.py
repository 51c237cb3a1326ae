"""The volumes a server offers, by name (never by path).

    GET /v1/volumes          names, shapes, value ranges, suggested iso-values; ``error`` where a
                             volume cannot be opened or viewed, why
    GET /v1/volumes/{name}   one volume's info with its histogram (loads it) and, once a session
                             rendered it, where its voxels are (``device``: `MemoryStats`); 422
                             with the reason for one that cannot be opened
    GET /v1/volumes/{name}/mesh?iso=V&format=ply|obj|stl|vtu[&clip=JSON]
                             the isosurface of iso V (data units; default the suggested one) as a
                             triangle mesh file in physical units (:mod:`isosr_render.mesh`), made
                             on the server's device, cut by ``clip`` (a view's ``settings.clip`` as
                             JSON), a device-thread job per slab (:func:`isosr_render.mesh.mesh_steps`:
                             the view sessions' frames interleave); 413 naming the limit for one too
                             large, 422 for no surface, 429 while ``limits.max_mesh_jobs`` others are
                             under way
    GET /v1/volumes/{name}/slices/{x|y|z}?index=K[&iso=V]
                             the orthogonal slice across that axis at voxel K as a PNG, the iso
                             contour (data units) drawn on it (:func:`isosr_render.slices.slice_image`)
"""

from __future__ import annotations

import asyncio
import re
from typing import Annotated, Literal

import torch
from fastapi import APIRouter, Depends, Query, Response

from isosr_render import Volume
from isosr_render.clip import Clip
from isosr_render.mesh import MESH_FORMATS, MeshTooLarge, mesh_bytes, mesh_steps
from isosr_render.slices import AXES, slice_image
from isosr_server.api.deps import CatalogDep, EngineDep, MeshJobsDep, require_token
from isosr_server.encoding import encode_image
from isosr_server.engine import Engine
from isosr_server.protocol import ProtocolError, clip_query
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


@router.get("/{name}/mesh", response_class=Response, responses={200: {"content": {"application/octet-stream": {}}}})
async def get_mesh(name: str, catalog: CatalogDep, engine: EngineDep, jobs: MeshJobsDep, iso: float | None = None,
                   format: Literal[tuple(m[1:] for m in MESH_FORMATS)] = "ply",
                   clip: Annotated[str | None, Query(max_length=4000)] = None):
    volume, info = await load_volume(catalog, name)
    iso = info.iso if iso is None else iso
    normalized = session_iso(volume, name, iso, False, "iso")
    cut = Clip() if clip is None else clip_query(clip).clip()
    jobs.acquire("mesh extractions")  # 429 at the bound, before any work
    try:
        data = await mesh_file(engine, volume, name, iso, normalized, cut, format)
    finally:
        jobs.release()
    return Response(data, media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{re.sub(r"[^A-Za-z0-9_.-]", "_", name)}.{format}"'})


async def mesh_file(engine: Engine, volume: Volume, name: str, iso: float, normalized: float, cut: Clip, format: str) -> bytes:
    """The ``format`` file of the isosurface of ``iso`` (``normalized``) of volume ``name``, cut by ``cut``:
    made a slab at a time on the device thread, written on another."""
    try:
        mesh = await engine.run_steps(mesh_steps(volume, normalized, str(engine.device), clip=cut))
    except ValueError as e:  # a limit (413) or a crop box of zero volume
        raise ProtocolError(str(e), http_status=413 if isinstance(e, MeshTooLarge) else 422) from None
    if len(mesh.faces) == 0:
        kept = " in the clip's kept region" if cut.active else ""
        raise ProtocolError(f"iso {iso:g}: no surface{kept} in {name}", http_status=422)
    return await asyncio.to_thread(mesh_bytes, mesh, f".{format}")
