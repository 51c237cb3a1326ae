"""The two models' KServe v2 (Open Inference Protocol) metadata and readiness, and the upscaling
model's inference.

    GET  /v2/models/isosr[/versions/1][/ready]                  the upscaling network (POST /v1/upscale,
                                                                the view modes that upscale)
    POST /v2/models/isosr[/versions/1]/infer                    low-res buffers in, high-res buffers out
    GET  /v2/models/isosr-recon[/versions/1][/ready]            the reconstruction network (reconstruct mode)

Each tensor has one ``datatype``, as the protocol asks: FP32, what the networks compute on and
return. The upscaling inputs are also taken in float16; each says so in its ``parameters``
(``accepted_datatypes: ["FP32", "FP16"]``) rather than as a second model: the same weights serve
both, and ``parameters`` is where the protocol puts a tensor's further properties, so generic
clients still read one datatype. Model facts (upscale factor, precision, device, the model
folder's name: never a machine path) are in the model's ``parameters``. A model's version is
its own (``MODEL_VERSION``), not the wire protocol's.

Inference (:mod:`isosr_server.codecs.kserve`: JSON and binary tensors) computes what
``POST /v1/upscale`` computes. Triton's sequence parameters carry the recurrent state:
``sequence_id`` is the upscale session's id (the same ids as ``/v1/upscale``'s ``session``),
``sequence_start`` resets its state; ``sequence_end`` is accepted, and the state expires after
``idle_timeout_s`` as every upscale session's does. The stage times come in ``x-isosr-times``.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import JSONResponse, Response

from isosr_server.api.deps import (EngineDep, LimitsDep, MetricsDep, ReadyDep, UpscaleSessionsDep, require_ready,
                                   require_token)
from isosr_server.api.routes.upscale import check_upscale, run_upscale
from isosr_server.codecs.kserve import (BINARY_MEDIA_TYPE, HEADER_LENGTH, JSON_MEDIA_TYPE, InferRequest,
                                        decode_request, encode_response)
from isosr_server.protocol import IMAGE_ENCODINGS, SESSION_ID, ProtocolError, UpscaleRequest

UPSCALE_MODEL, RECON_MODEL = "isosr", "isosr-recon"
MODEL_VERSION = "1"
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
    return {"name": name, "versions": [MODEL_VERSION], "platform": PLATFORM, "inputs": inputs,
            "outputs": OUTPUTS, "parameters": parameters}


def readiness(name: str, ready: bool) -> JSONResponse:
    return JSONResponse({"name": name, "ready": ready}, 200 if ready else 503)


router = APIRouter(prefix="/v2/models", tags=["models"], dependencies=[Depends(require_token)])


def route(model: str, tail: str, endpoint, method: str = "GET", ready: bool = False) -> None:
    """``endpoint`` at ``/{model}{tail}`` and at ``/{model}/versions/{MODEL_VERSION}{tail}`` (the
    protocol's two spellings; another version is 404), behind `require_ready` if ``ready``."""
    for path in (f"/{model}{tail}", f"/{model}/versions/{MODEL_VERSION}{tail}"):
        router.add_api_route(path, endpoint, methods=[method], dependencies=[Depends(require_ready)] if ready else [])


async def upscale_model(engine: EngineDep):
    return metadata(UPSCALE_MODEL, UPSCALE_INPUTS, engine.model_info() | {"image_outputs": list(IMAGE_ENCODINGS)})


async def upscale_model_ready(ready: ReadyDep):
    return readiness(UPSCALE_MODEL, ready)


def upscale_request(req: InferRequest) -> UpscaleRequest:
    """The `UpscaleRequest` an infer request asks for; `ProtocolError` (400) for unknown or missing
    inputs, a bad sequence id, or buffers that `UpscaleRequest` refuses."""
    names = [t["name"] for t in UPSCALE_INPUTS]
    unknown = [n for n in req.inputs if n not in names]
    if unknown:
        raise ProtocolError(f"unknown input {unknown[0]!r}; {UPSCALE_MODEL} takes {', '.join(names)}"[:200])
    missing = [t["name"] for t in UPSCALE_INPUTS if not t["parameters"]["optional"] and t["name"] not in req.inputs]
    if missing:
        raise ProtocolError(f"missing input {missing[0]!r}")
    sequence = req.parameters.get("sequence_id", 0)
    if isinstance(sequence, bool) or not isinstance(sequence, int | str):
        raise ProtocolError("sequence_id must be an integer or a string")
    session = str(sequence) if sequence not in (0, "") else None
    if session is not None and not SESSION_ID.fullmatch(session):
        raise ProtocolError(f"sequence_id must match {SESSION_ID.pattern}")
    return UpscaleRequest(req.inputs["mask"], req.inputs["normal"], req.inputs["depth"], req.inputs.get("flow"),
                          session=session, reset=bool(req.parameters.get("sequence_start", False)))


async def upscale_infer(request: Request, engine: EngineDep, limits: LimitsDep, metrics: MetricsDep,
                        sessions: UpscaleSessionsDep):
    if request.headers.get("content-encoding", "identity") != "identity":
        raise HTTPException(415, "send the inference request uncompressed")
    req = await asyncio.to_thread(decode_request, await request.body(), request.headers.get(HEADER_LENGTH))
    msg = upscale_request(req)
    check_upscale(msg, engine, limits)
    client = request.client.host if request.client else ""
    upscaler = sessions.get(msg.session, client) if msg.session else engine.new_upscaler()
    _, buffers, times = await run_upscale(engine, upscaler, msg)
    sessions.trim(keep=msg.session)
    body, header_length = await asyncio.to_thread(encode_response, UPSCALE_MODEL, MODEL_VERSION, req, buffers)
    metrics.frame("upscale", "buffers", False, times, len(body))
    headers = {"x-isosr-times": json.dumps(times)}
    if header_length is not None:
        headers["Inference-Header-Content-Length"] = str(header_length)
    return Response(body, media_type=JSON_MEDIA_TYPE if header_length is None else BINARY_MEDIA_TYPE,
                    headers=headers)


async def recon_model(engine: EngineDep):
    return metadata(RECON_MODEL, RECON_INPUTS, engine.recon_info())


async def recon_model_ready(ready: ReadyDep):
    return readiness(RECON_MODEL, ready)


route(UPSCALE_MODEL, "", upscale_model, ready=True)
route(UPSCALE_MODEL, "/ready", upscale_model_ready)
route(UPSCALE_MODEL, "/infer", upscale_infer, "POST", ready=True)
route(RECON_MODEL, "", recon_model, ready=True)
route(RECON_MODEL, "/ready", recon_model_ready)
