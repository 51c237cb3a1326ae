"""The two models' KServe v2 (Open Inference Protocol) metadata, readiness and inference.

    GET  /v2/models/isosr[/versions/1][/ready]          the upscaling network (POST /v1/upscale, the
                                                        view modes that upscale)
    POST /v2/models/isosr[/versions/1]/infer            low-res buffers in, high-res buffers out
    GET  /v2/models/isosr-recon[/versions/1][/ready]    the reconstruction network (reconstruct mode)
    POST /v2/models/isosr-recon[/versions/1]/infer      full-res buffers (few-ray AO) in, the
                                                        reconstructed buffers and shaded color out

Each model's tensors are declared once (`UPSCALE`, `RECON`: :class:`~isosr_server.codecs.kserve.ModelSpec`);
its metadata and the checks of its requests (names, shapes, value ranges) come from that. Each
tensor has one ``datatype``, as the protocol asks: FP32, what the networks compute on and return.
Inputs are also taken in float16; each says so in its ``parameters`` (``accepted_datatypes:
["FP32", "FP16"]``, with its value ``range``) rather than as a second model: the same weights
serve both, and ``parameters`` is where the protocol puts a tensor's further properties, so
generic clients still read one datatype. Model facts (upscale factor, precision, device, the
model folder's name: never a machine path; the reconstruction's AO ray and spp bounds) are in the
model's ``parameters``. A model's version is its own (``MODEL_VERSION``), not the wire protocol's.

Inference (:mod:`isosr_server.codecs.kserve`: JSON and binary tensors): ``isosr`` computes what
``POST /v1/upscale`` computes; ``isosr-recon`` what `isosr_net.reconstructor.Reconstructor`
computes of a frame rendered with the request's parameters ``ao_rays`` (AO rays per hit, 0 to
its bound: 0 without an ``ao`` input, at least 1 with one) and ``spp`` (rays per pixel, default
1); its ``color`` output (shaded with the default material) is computed only when asked for, or
when the request names no outputs. Triton's sequence parameters carry the recurrent state:
``sequence_id`` is the session's id (the same ids as ``/v1/upscale``'s ``session``: a state per
model and id), ``sequence_start`` resets its state; ``sequence_end`` is accepted, and the state
expires after ``idle_timeout_s`` as every upscale session's does. The stage times come in
``x-isosr-times``.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.responses import JSONResponse, Response

from isosr_net.inference import RecurrentNetwork
from isosr_net.reconnet import RayLimits
from isosr_net.reconstructor import Reconstructor
from isosr_net.upscaler import Upscaler
from isosr_server.api.deps import (EngineDep, LimitsDep, MetricsDep, ReadyDep, UpscaleSessionsDep, require_ready,
                                   require_token)
from isosr_server.api.routes.upscale import check_upscale, run_upscale
from isosr_server.codecs.kserve import (BINARY_MEDIA_TYPE, HEADER_LENGTH, JSON_MEDIA_TYPE, InferRequest, ModelSpec,
                                        TensorSpec, decode_request, encode_response, int_parameter, sequence)
from isosr_server.metrics import ServerMetrics
from isosr_server.protocol import IMAGE_ENCODINGS, LOWRES_BOUNDS, MAX_DEPTH, Limits, ProtocolError, UpscaleRequest
from isosr_server.sessions import UpscaleSessions

MODEL_VERSION = "1"
PLATFORM = "pytorch"
SHAPES = {"mask": ("H", "W"), "normal": ("H", "W", 3), "depth": ("H", "W"), "ao": ("H", "W"), "flow": ("H", "W", 2),
          "position": ("H", "W", 3), "color": ("H", "W", 3)}
UNIT = (0.0, 1.0)


def tensor(name: str, bounds: tuple[float, float] | None = None, optional: bool = False) -> TensorSpec:
    return TensorSpec(name, SHAPES[name], bounds, optional)


SURFACE = tuple(tensor(n, LOWRES_BOUNDS[n]) for n in ("mask", "normal", "depth"))
FLOW = tensor("flow", LOWRES_BOUNDS["flow"], optional=True)
BUFFERS = tuple(tensor(n) for n in ("mask", "normal", "depth", "ao"))
UPSCALE = ModelSpec("isosr", SURFACE + (FLOW,), BUFFERS)
# With positions (world-space hit points) and a sequence, the AO rays accumulate along the flow (isosr_net.ray_history).
POSITION = tensor("position", (-MAX_DEPTH, MAX_DEPTH), optional=True)
RECON = ModelSpec("isosr-recon", SURFACE + (tensor("ao", UNIT, optional=True), POSITION, FLOW),
                  BUFFERS + (tensor("color"),))


def metadata(model: ModelSpec, parameters: dict) -> dict:
    return {"name": model.name, "versions": [MODEL_VERSION], "platform": PLATFORM, **model.metadata(),
            "parameters": parameters}


def readiness(name: str, ready: bool) -> JSONResponse:
    return JSONResponse({"name": name, "ready": ready}, 200 if ready else 503)


router = APIRouter(prefix="/v2/models", tags=["models"], dependencies=[Depends(require_token)])


def route(model: str, tail: str, endpoint, method: str = "GET", ready: bool = False) -> None:
    """``endpoint`` at ``/{model}{tail}`` and at ``/{model}/versions/{MODEL_VERSION}{tail}`` (the
    protocol's two spellings; another version is 404), behind `require_ready` if ``ready``."""
    for path in (f"/{model}{tail}", f"/{model}/versions/{MODEL_VERSION}{tail}"):
        router.add_api_route(path, endpoint, methods=[method], dependencies=[Depends(require_ready)] if ready else [])


async def upscale_model(engine: EngineDep):
    return metadata(UPSCALE, engine.model_info() | {"image_outputs": list(IMAGE_ENCODINGS)})


async def upscale_model_ready(ready: ReadyDep):
    return readiness(UPSCALE.name, ready)


async def read_body(request: Request) -> bytes | bytearray:
    """The request's body; with a Content-Length (which the guard has bounded by ``max_message_bytes``)
    read into one buffer of that size, not gathered in chunks and joined (twice its size at the end)."""
    declared = request.headers.get("content-length", "")
    if not declared.isdigit():
        return await request.body()
    body, n = bytearray(int(declared)), 0
    async for chunk in request.stream():
        if n + len(chunk) > len(body):  # the server refuses this before; kept as a bound of the buffer
            raise ProtocolError(f"the body is longer than its Content-Length {len(body)}")
        body[n:n + len(chunk)] = chunk
        n += len(chunk)
    if n != len(body):
        raise ProtocolError(f"the body has {n} bytes; its Content-Length says {len(body)}")
    return body


async def read_infer(request: Request, model: ModelSpec, limits: Limits) -> tuple[InferRequest, dict[str, int]]:
    """The request's body decoded off the event loop and checked against ``model``'s tensors; the
    sizes of its shape letters. 415 for a compressed body, `ProtocolError` 400 for one that does not
    fit, 413 for a declared tensor over ``limits`` (`Limits.array_bounds`: refused before any
    tensor's values are decoded)."""
    if request.headers.get("content-encoding", "identity") != "identity":
        raise HTTPException(415, "send the inference request uncompressed")
    req = await asyncio.to_thread(decode_request, await read_body(request), request.headers.get(HEADER_LENGTH),
                                  *limits.array_bounds())
    return req, model.check(req)


def stream_network(request: Request, sessions: UpscaleSessions, session: str | None,
                   cls: type[RecurrentNetwork]) -> RecurrentNetwork:
    """The session's network of ``cls`` (its recurrent state), or a fresh one for a request without a session."""
    client = request.client.host if request.client else ""
    return sessions.get(session, client, cls) if session else sessions.make(cls)


async def reply(model: ModelSpec, req: InferRequest, buffers: dict, times: dict, metrics: ServerMetrics,
                kind: str) -> Response:
    """The infer response of ``buffers``, with the stage times in ``x-isosr-times``; counted as a ``kind`` frame."""
    body, header_length = await asyncio.to_thread(encode_response, model.name, MODEL_VERSION, req, buffers)
    metrics.frame(kind, "buffers", False, times, len(body))
    headers = {"x-isosr-times": json.dumps(times)}
    if header_length is not None:
        headers["Inference-Header-Content-Length"] = str(header_length)
    return Response(body, media_type=JSON_MEDIA_TYPE if header_length is None else BINARY_MEDIA_TYPE,
                    headers=headers)


async def upscale_infer(request: Request, engine: EngineDep, limits: LimitsDep, metrics: MetricsDep,
                        sessions: UpscaleSessionsDep):
    # Low-res inputs: the bounds of the frame they upscale to.
    req, _ = await read_infer(request, UPSCALE, limits.downscaled(engine.upscale_factor))
    session, reset = sequence(req)
    msg = UpscaleRequest(req.inputs["mask"], req.inputs["normal"], req.inputs["depth"], req.inputs.get("flow"),
                         session=session, reset=reset)
    check_upscale(msg, engine, limits)
    upscaler = stream_network(request, sessions, session, Upscaler)
    _, buffers, times = await run_upscale(engine, upscaler, msg)
    sessions.trim(keep=upscaler)
    return await reply(UPSCALE, req, buffers, times, metrics, "upscale")


async def recon_model(engine: EngineDep):
    return metadata(RECON, engine.recon_info())


async def recon_model_ready(ready: ReadyDep):
    return readiness(RECON.name, ready)


def recon_sampling(req: InferRequest, limits: RayLimits) -> tuple[int, int]:
    """``(ao_rays, spp)`` of a reconstruction request; `ProtocolError` 400 out of the model's
    ``limits``, or when the ``ao`` input and ``ao_rays`` do not come together."""
    ao_rays = int_parameter(req, "ao_rays", 0, 0, limits.max_ao_rays)
    if "ao" in req.inputs and not ao_rays:
        raise ProtocolError(f"input 'ao' needs the parameter ao_rays (1 to {limits.max_ao_rays}: its AO rays per hit)")
    if ao_rays and "ao" not in req.inputs:
        raise ProtocolError(f"parameter ao_rays {ao_rays} needs the input 'ao'")
    return ao_rays, int_parameter(req, "spp", 1, 1, limits.max_spp)


async def recon_infer(request: Request, engine: EngineDep, limits: LimitsDep, metrics: MetricsDep,
                      sessions: UpscaleSessionsDep):
    req, sizes = await read_infer(request, RECON, limits)
    ao_rays, spp = recon_sampling(req, engine.recon_limits)
    session, reset = sequence(req)
    limits.check_size(sizes["W"], sizes["H"], "the frame")
    reconstructor = stream_network(request, sessions, session, Reconstructor)
    try:
        buffers, times = await engine.reconstruct(reconstructor, req.inputs, ao_rays, spp, RECON.wanted(req), reset)
    except ValueError as e:  # the network refuses this frame (e.g. fp16 beyond its depth range)
        raise ProtocolError(f"cannot reconstruct this frame: {e}", http_status=422) from None
    sessions.trim(keep=reconstructor)
    return await reply(RECON, req, buffers, times, metrics, "reconstruct")


route(UPSCALE.name, "", upscale_model, ready=True)
route(UPSCALE.name, "/ready", upscale_model_ready)
route(UPSCALE.name, "/infer", upscale_infer, "POST", ready=True)
route(RECON.name, "", recon_model, ready=True)
route(RECON.name, "/ready", recon_model_ready)
route(RECON.name, "/infer", recon_infer, "POST", ready=True)
