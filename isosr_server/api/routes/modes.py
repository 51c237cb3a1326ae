"""The view modes a server offers.

    GET /v1/modes   each mode's name, label and the settings it reads with their bounds
                    (:class:`isosr_server.protocol.ModeInfo`; a view session's ``ready`` lists the same)
"""

from __future__ import annotations

import msgspec
from fastapi import APIRouter, Depends

from isosr_server.api.deps import EngineDep, require_token

router = APIRouter(prefix="/v1/modes", tags=["modes"], dependencies=[Depends(require_token)])


@router.get("")
async def list_modes(engine: EngineDep):
    return {"modes": msgspec.to_builtins(engine.modes)}
