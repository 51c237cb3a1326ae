"""The two models' KServe v2 (Open Inference Protocol) metadata and readiness.

    GET /v2/models/isosr, /v2/models/isosr/ready               the upscaling network (POST /v1/upscale,
                                                               the view modes that upscale)
    GET /v2/models/isosr-recon, /v2/models/isosr-recon/ready   the reconstruction network (reconstruct mode)

Each tensor has one ``datatype``, as the protocol asks: FP32, what the networks compute on and
return. The upscaling inputs are also taken in float16; each says so in its ``parameters``
(``accepted_datatypes: ["FP32", "FP16"]``) rather than as a second model: the same weights serve
both, and ``parameters`` is where the protocol puts a tensor's further properties, so generic
clients still read one datatype. Model facts (upscale factor, precision, device, the model
folder's name: never a machine path) are in the model's ``parameters``.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from isosr_server.api.deps import EngineDep, ReadyDep, require_ready, require_token
from isosr_server.protocol import ENCODINGS, PROTOCOL_VERSION

UPSCALE_MODEL, RECON_MODEL = "isosr", "isosr-recon"
PLATFORM = "pytorch"
SHAPES = {"mask": [-1, -1], "normal": [-1, -1, 3], "depth": [-1, -1], "ao": [-1, -1], "flow": [-1, -1, 2]}


def tensor(name: str, optional: bool = False, fp16: bool = False) -> dict:
    """One tensor's metadata: name, datatype FP32, shape (-1: any size), and in ``parameters``
    whether it may be left out and the datatypes the server takes."""
    return {"name": name, "datatype": "FP32", "shape": SHAPES[name],
            "parameters": {"optional": optional, "accepted_datatypes": ["FP32", "FP16"] if fp16 else ["FP32"]}}


OUTPUTS = [tensor(n) for n in ("mask", "normal", "depth", "ao")]
UPSCALE_INPUTS = [tensor("mask", fp16=True), tensor("normal", fp16=True), tensor("depth", fp16=True),
                  tensor("flow", optional=True, fp16=True)]
RECON_INPUTS = [tensor("mask"), tensor("normal"), tensor("depth"), tensor("ao", optional=True),
                tensor("flow", optional=True)]


def metadata(name: str, inputs: list[dict], parameters: dict) -> dict:
    return {"name": name, "versions": [str(PROTOCOL_VERSION)], "platform": PLATFORM, "inputs": inputs,
            "outputs": OUTPUTS, "parameters": parameters}


def readiness(name: str, ready: bool) -> JSONResponse:
    return JSONResponse({"name": name, "ready": ready}, 200 if ready else 503)


router = APIRouter(prefix="/v2/models", tags=["models"], dependencies=[Depends(require_token)])


@router.get(f"/{UPSCALE_MODEL}", dependencies=[Depends(require_ready)])
async def upscale_model(engine: EngineDep):
    return metadata(UPSCALE_MODEL, UPSCALE_INPUTS, engine.model_info() | {"image_outputs": list(ENCODINGS)})


@router.get(f"/{UPSCALE_MODEL}/ready")
async def upscale_model_ready(ready: ReadyDep):
    return readiness(UPSCALE_MODEL, ready)


@router.get(f"/{RECON_MODEL}", dependencies=[Depends(require_ready)])
async def recon_model(engine: EngineDep):
    return metadata(RECON_MODEL, RECON_INPUTS, engine.recon_info())


@router.get(f"/{RECON_MODEL}/ready")
async def recon_model_ready(ready: ReadyDep):
    return readiness(RECON_MODEL, ready)
