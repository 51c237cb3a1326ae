"""The KServe v2 infer endpoints of both models (``POST /v2/models/isosr[/versions/1]/infer``,
``POST /v2/models/isosr-recon[/versions/1]/infer``) on a real server, called with Triton's own
client (``tritonclient[http]``) in JSON and binary tensors.

The upscaling model's outputs must equal ``POST /v1/upscale``'s for the same frames, the
reconstruction model's those of `Reconstructor.reconstruct` run here in-process on the same
inputs (fp32, the default material for ``color``), recurrent state included. The same library
call computes both sides, so on the CPU they agree to ATOL = 1e-6 (float32 rounding is all a
float16 or JSON transport could add, and it adds none: float16 inputs are compared with the same
float16 values given to the reference); on CUDA to 1e-2 like the upscale tests (the server runs
its networks channels-last with the fast layers, the reference not).
"""

from __future__ import annotations

import json

import msgspec
import numpy as np
import pytest
import torch

from isosr_net.reconstructor import Reconstructor
from isosr_render import FrameBuffers, RenderRequest, ShadingParams, orbit
from isosr_server import protocol as P
from server_fixtures import (DEVICE, FACTOR, H, W, infer_inputs, lib, lib_lowres, running_server,  # noqa: F401
                             server_settings, upscale_body)

httpclient = pytest.importorskip("tritonclient.http", reason="tritonclient[http] is not installed (the test extra)")
from tritonclient.utils import InferenceServerException  # noqa: E402

ATOL = 1e-6 if DEVICE == "cpu" else 1e-2
LIMITS = P.Limits(max_message_bytes=2**20)
INPUTS, OUTPUTS = ("mask", "normal", "depth", "flow"), ("mask", "normal", "depth", "ao")
RECON_INPUTS = ("mask", "normal", "depth", "ao", "position", "flow")
RECON_OUTPUTS = ("mask", "normal", "depth", "ao", "color")
AO_RAYS = 2


@pytest.fixture(scope="module")
def srv():
    with running_server(server_settings(limits=LIMITS)) as s:
        yield s


@pytest.fixture(scope="module")
def client(srv):
    c = httpclient.InferenceServerClient(url=f"127.0.0.1:{srv.port}", network_timeout=120)
    yield c
    c.close()


@pytest.fixture(scope="module")
def frames(lib):
    """Two consecutive low-res frames (the second with flow) as numpy buffers."""
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    return [lib_lowres(lib, c0).to_numpy(), lib_lowres(lib, c1, prev=c0).to_numpy()]


def upscale_post(srv, frame: dict, **fields) -> P.HighresBuffers:
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(frame, **fields))
    assert status == 200, body
    return P.parse(body, P.Limits(), (P.UpscaleResponse,)).buffers


def infer(client, frame: dict, binary: bool = True, datatype: str = "FP32", **kwargs) -> dict[str, np.ndarray]:
    inputs = infer_inputs(frame, INPUTS, datatype, binary)
    outputs = [httpclient.InferRequestedOutput(n, binary_data=binary) for n in OUTPUTS]
    result = client.infer("isosr", inputs, outputs=outputs, **kwargs)
    return {n: result.as_numpy(n) for n in OUTPUTS}


def assert_equal_buffers(got: dict[str, np.ndarray], want: P.HighresBuffers) -> None:
    for name in OUTPUTS:
        assert got[name].dtype == np.float32 and got[name].shape == getattr(want, name).shape
        np.testing.assert_allclose(got[name], getattr(want, name), atol=ATOL, err_msg=name)


def test_metadata_and_readiness_through_tritonclient(client):
    assert client.is_server_ready() and client.is_model_ready("isosr") and client.is_model_ready("isosr", "1")
    assert "binary_tensor_data" in client.get_server_metadata()["extensions"]
    meta = client.get_model_metadata("isosr", "1")
    assert meta["versions"] == ["1"]
    assert [t["name"] for t in meta["inputs"]] == list(INPUTS)
    assert [t["name"] for t in meta["outputs"]] == list(OUTPUTS)


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
def test_infer_equals_upscale_post_with_recurrent_state(srv, client, frames, binary):
    f0, f1 = frames
    want = [upscale_post(srv, f0, session=f"post-{binary}"), upscale_post(srv, f1, session=f"post-{binary}")]
    seq = f"infer-{binary}"
    assert_equal_buffers(infer(client, f0, binary, sequence_id=seq, sequence_start=True), want[0])
    got = infer(client, f1, binary, sequence_id=seq, model_version="1")
    assert_equal_buffers(got, want[1])
    # Without the sequence the second frame starts fresh, and differs.
    fresh = infer(client, f1, binary)
    assert not np.allclose(fresh["normal"], got["normal"], atol=10 * ATOL)
    assert got["mask"].shape == (H, W) and f1["mask"].shape == (H // FACTOR, W // FACTOR)


def test_fp16_inputs_and_default_binary_outputs(srv, client, frames):
    f0 = frames[0]
    half = {n: a.astype(np.float16) for n, a in f0.items()}
    want = upscale_post(srv, half)
    assert_equal_buffers(infer(client, f0, datatype="FP16"), want)
    # No outputs named: all four, binary (tritonclient asks binary_data_output).
    inputs = [httpclient.InferInput(n, list(f0[n].shape), "FP32") for n in ("mask", "normal", "depth")]
    for t in inputs:
        t.set_data_from_numpy(f0[t.name()])
    result = client.infer("isosr", inputs, request_id="r7")
    assert result.get_response()["id"] == "r7"
    assert [o["name"] for o in result.get_response()["outputs"]] == list(OUTPUTS)
    np.testing.assert_allclose(result.as_numpy("ao"), upscale_post(srv, f0).ao, atol=ATOL)


def raw_infer(srv, header: dict, blobs: bytes = b"", headers: dict | None = None,
              path: str = "/v2/models/isosr/infer") -> tuple[int, dict]:
    head = msgspec.json.encode(header)
    extra = {"Inference-Header-Content-Length": str(len(head))} if blobs else {}
    status, _, body = srv.request("POST", path, head + blobs,
                                  {"Content-Type": "application/octet-stream", **extra, **(headers or {})})
    return status, json.loads(body)


def tensor(name: str, a: np.ndarray, datatype: str = "FP32", binary: bool = True, **parameters) -> dict:
    t = {"name": name, "shape": list(a.shape), "datatype": datatype}
    if binary:
        t["parameters"] = {"binary_data_size": a.nbytes, **parameters}
    else:
        t["data"] = a.ravel().tolist()
    return t


def test_bad_tensors_get_4xx_with_reasons(srv, client, frames):
    f = frames[1]
    good = [tensor(n, f[n]) for n in INPUTS]
    blobs = b"".join(f[n].astype("<f4").tobytes() for n in INPUTS)
    h, w = f["mask"].shape
    bad_normal = dict(good[1], shape=[h, w])
    nan_depth = np.full((h, w), np.nan, np.float32)
    cases = [
        ({"inputs": good}, blobs[:-4], 400, "ends 4 bytes before its data"),
        ({"inputs": good}, blobs + b"xx", 400, "2 bytes beyond its binary tensors"),
        ({"inputs": [good[0], bad_normal] + good[2:]}, blobs, 400, "binary_data_size is"),
        ({"inputs": [good[0], dict(good[1], datatype="INT32")] + good[2:]}, blobs, 400,
         "datatype must be FP32 or FP16, got 'INT32'"),
        ({"inputs": good[1:]}, blobs[f["mask"].nbytes:], 400, "missing input 'mask'"),
        ({"inputs": good + [tensor("color", f["mask"])]}, blobs + f["mask"].tobytes(), 400, "unknown input 'color'"),
        ({"inputs": good + [good[0]]}, blobs + f["mask"].tobytes(), 400, "input 'mask' is given twice"),
        ({"inputs": good, "outputs": [{"name": "color"}]}, blobs, 400, "unknown output 'color'"),
        ({"inputs": good, "parameters": {"sequence_id": "../x"}}, blobs, 400, "sequence_id must match"),
        ({"inputs": [tensor(n, f[n], binary=False) for n in INPUTS[:2]] + [tensor("depth", nan_depth, binary=False)]},
         b"", 400, "'depth': NaN or Inf"),  # JSON has no NaN: the encoder writes null
        ({"inputs": [tensor(n, f[n]) for n in INPUTS[:2]] + [tensor("depth", nan_depth)]},
         b"".join(f[n].tobytes() for n in INPUTS[:2]) + nan_depth.tobytes(), 400, "'depth': NaN or Inf"),
        ({"inputs": [tensor("mask", f["mask"], binary=False) | {"data": [[1.0, 2.0], [3.0]]}]}, b"", 400,
         "data must be numbers"),
        ({"inputs": [tensor("mask", f["mask"], binary=False) | {"data": [0.5] * 5}]}, b"", 400, "5 values for shape"),
        ({"inputs": [tensor("mask", f["mask"]) | {"shape": [h, -w]}]}, f["mask"].tobytes(), 400,
         "Expected `int` >= 0"),
        ({"inputs": [tensor(n, 2 * f[n]) for n in INPUTS]}, b"".join((2 * f[n]).tobytes() for n in INPUTS), 400,
         "'mask': values must lie in [0, 1]"),
        ({"inputs": [tensor(n, np.zeros((2, 1100) + f[n].shape[2:], np.float32)) for n in INPUTS]},
         b"".join(np.zeros((2, 1100) + f[n].shape[2:], np.float32).tobytes() for n in INPUTS), 413, "exceeds"),
        ({"inputs": good, "pad": "x" * LIMITS.max_message_bytes}, blobs, 413, "limit"),
    ]
    for header, body, status, words in cases:
        got, reply = raw_infer(srv, header, body)
        assert got == status and words in reply["error"], (words, got, reply)
    assert raw_infer(srv, {"inputs": good}, blobs, {"Inference-Header-Content-Length": "-3"})[1]["error"].startswith(
        "Inference-Header-Content-Length -3 lies outside")
    assert raw_infer(srv, {"inputs": good}, blobs, {"Content-Encoding": "gzip"})[0] == 415
    assert raw_infer(srv, {"inputs": good}, blobs, path="/v2/models/isosr/versions/2/infer")[0] == 404
    assert raw_infer(srv, {"inputs": good}, blobs, path="/v2/models/isosr/versions/1/infer")[0] == 200
    # tritonclient reports the server's reason with the status.
    with pytest.raises(InferenceServerException) as e:
        infer(client, {"mask": f["mask"], "normal": f["normal"]})
    assert e.value.status() == "400" and "missing input 'depth'" in e.value.message()
    assert srv.get_json("/v2/health/ready")[0] == 200
    assert not srv.errors.records, srv.errors.messages()


# ---- the reconstruction model (isosr-recon) ------------------------------------------------------


@pytest.fixture(scope="module")
def full_frames(lib):
    """Two consecutive full-res frames of AO_RAYS AO rays per hit (the second with flow) as numpy buffers."""
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    outputs = ("mask", "normal", "depth", "ao")
    return [lib.renderer.render(cam, RenderRequest(W, H, lib.iso, outputs + (("flow",) if prev else ()),
                                                   ao_samples=AO_RAYS, prev_camera=prev)).to_numpy()
            for cam, prev in ((c0, None), (c1, c0))]


def reconstructed(frames: list[dict], ao_rays: int = AO_RAYS, spp: int = 1) -> list[dict[str, np.ndarray]]:
    """The library's reconstruction of ``frames`` with one recurrent state, in fp32 on DEVICE."""
    reconstructor = Reconstructor(device=DEVICE)
    out = []
    for f in frames:
        frame = FrameBuffers(**{n: torch.from_numpy(a.astype(np.float32)) for n, a in f.items()})
        got = reconstructor.reconstruct(frame, ao_rays, spp, ShadingParams())
        out.append({n: getattr(got, n).cpu().numpy() for n in RECON_OUTPUTS})
    return out


def recon_infer(client, frame: dict, binary: bool = True, datatype: str = "FP32", outputs=RECON_OUTPUTS,
                parameters: dict | None = None, **kwargs) -> dict[str, np.ndarray]:
    inputs = infer_inputs(frame, RECON_INPUTS, datatype, binary)
    wanted = [httpclient.InferRequestedOutput(n, binary_data=binary) for n in outputs]
    result = client.infer("isosr-recon", inputs, outputs=wanted,
                          parameters={"ao_rays": AO_RAYS} if parameters is None else parameters, **kwargs)
    assert [o["name"] for o in result.get_response()["outputs"]] == list(outputs)
    return {n: result.as_numpy(n) for n in outputs}


def assert_equal_recon(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    for name, a in got.items():
        assert a.dtype == np.float32 and a.shape == want[name].shape, name
        np.testing.assert_allclose(a, want[name], atol=ATOL, err_msg=name)


def test_recon_metadata_and_readiness_through_tritonclient(client):
    assert client.is_model_ready("isosr-recon") and client.is_model_ready("isosr-recon", "1")
    meta = client.get_model_metadata("isosr-recon", "1")
    assert meta["name"] == "isosr-recon" and meta["versions"] == ["1"]
    assert [t["name"] for t in meta["inputs"]] == list(RECON_INPUTS)
    assert [t["name"] for t in meta["outputs"]] == list(RECON_OUTPUTS)
    inputs = {t["name"]: t for t in meta["inputs"]}
    assert inputs["normal"]["shape"] == [-1, -1, 3] and inputs["flow"]["shape"] == [-1, -1, 2]
    assert [n for n, t in inputs.items() if t["parameters"]["optional"]] == ["ao", "position", "flow"]
    assert inputs["ao"]["parameters"]["range"] == [0.0, 1.0]
    assert all(t["parameters"]["accepted_datatypes"] == ["FP32", "FP16"] for t in meta["inputs"])
    assert meta["parameters"]["max_ao_rays"] >= AO_RAYS


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "json"])
def test_recon_infer_equals_the_reconstructor_with_recurrent_state(client, frames, full_frames, binary):
    want = reconstructed(full_frames)
    seq = f"recon-{binary}"
    assert_equal_recon(recon_infer(client, full_frames[0], binary, sequence_id=seq, sequence_start=True), want[0])
    # The upscaling model's session of the same id is another state: it leaves this one alone.
    infer(client, frames[0], binary, sequence_id=seq, sequence_start=True)
    got = recon_infer(client, full_frames[1], binary, sequence_id=seq, model_version="1")
    assert_equal_recon(got, want[1])
    # Without the sequence the second frame starts fresh, and differs (in its normal: the rays' interval holds this
    # frame's AO near its input's).
    fresh = recon_infer(client, full_frames[1], binary)
    assert np.abs(fresh["normal"] - got["normal"]).max() > 1e-2
    assert_equal_recon(fresh, reconstructed(full_frames[1:])[0])


def test_recon_infer_with_positions_accumulates_the_rays_as_the_library_does(lib, client):
    """Frames of one view with new rays each (the second with flow) and their hit points: the
    server's second frame is the library's, whose ray history holds both frames' rays."""
    camera, outputs = orbit(30, 20, 1.8), ("mask", "normal", "depth", "ao", "position")
    # AO rays long enough to reach across the torus: at the default radius all see the sky, and the history
    # would have nothing to change.
    frames = [lib.renderer.render(camera, RenderRequest(W, H, lib.iso, outputs + (("flow",) if i else ()), seed=5 + i,
                                                        ao_samples=AO_RAYS, ao_radius=0.5,
                                                        prev_camera=camera if i else None)).to_numpy()
              for i in range(2)]
    want = reconstructed(frames)
    seq = "recon-True"  # a session of an earlier test, started anew: one address holds at most 8
    recon_infer(client, frames[0], sequence_id=seq, sequence_start=True)
    assert_equal_recon(recon_infer(client, frames[1], sequence_id=seq), want[1])
    alone = reconstructed([frames[0], {n: a for n, a in frames[1].items() if n != "position"}])[1]
    assert np.abs(alone["ao"] - want[1]["ao"]).max() > 0.05  # the history changed the frame


def test_recon_fp16_inputs_no_ao_rays_spp_and_chosen_outputs(client, full_frames):
    f0 = full_frames[0]
    half = {n: a.astype(np.float16) for n, a in f0.items()}
    assert_equal_recon(recon_infer(client, f0, datatype="FP16"), reconstructed([half])[0])
    # No AO input (ao_rays 0: AO inferred from the geometry), 2 rays per pixel, two outputs only.
    no_ao = {n: a for n, a in f0.items() if n != "ao"}
    got = recon_infer(client, no_ao, outputs=("color", "ao"), parameters={"spp": 2})
    assert_equal_recon(got, reconstructed([no_ao], ao_rays=0, spp=2)[0])
    assert got["color"].shape == (H, W, 3)


def test_recon_bad_tensors_get_4xx_with_reasons(srv, client, full_frames):
    f = full_frames[1]
    h, w = f["mask"].shape
    names = [n for n in RECON_INPUTS if n in f]  # all but the optional position
    good = [tensor(n, f[n]) for n in names]
    blobs = b"".join(f[n].astype("<f4").tobytes() for n in names)
    rays = {"ao_rays": AO_RAYS}

    def replaced(name: str, a: np.ndarray, datatype: str = "FP32") -> tuple[list, bytes]:
        """The good request with input ``name`` replaced by ``a``."""
        arrays = {n: a if n == name else f[n] for n in names}
        return ([tensor(n, arrays[n], datatype if n == name else "FP32") for n in names],
                b"".join(arrays[n].tobytes() for n in names))

    nan_ao = f["ao"].copy()
    nan_ao[3, 5] = np.nan
    big = {n: np.zeros((2, 4100) + f[n].shape[2:], np.float32) for n in names}
    cases = [
        (*replaced("normal", f["normal"][..., :2].copy()), rays, 400,
         f"'normal': shape [{h}, {w}, 2] does not fit [H, W, 3]"),
        (*replaced("depth", f["depth"][:, :-1].copy()), rays, 400,
         f"'depth': shape [{h}, {w - 1}] does not fit [H, W] with H={h}, W={w}"),
        (*replaced("ao", nan_ao), rays, 400, "'ao': NaN or Inf"),
        (*replaced("ao", 1.5 * f["ao"] + 0.1), rays, 400, "'ao': values must lie in [0, 1]"),
        (*replaced("mask", f["mask"].astype(np.int32), "INT32"), rays, 400,
         "datatype must be FP32 or FP16, got 'INT32'"),
        (good + [tensor("color", f["mask"])], blobs + f["mask"].tobytes(), rays, 400, "unknown input 'color'"),
        (good[1:], blobs[f["mask"].nbytes:], rays, 400, "missing input 'mask'"),
        (good, blobs, {}, 400, "input 'ao' needs the parameter ao_rays"),
        ([t for t in good if t["name"] != "ao"], b"".join(f[n].tobytes() for n in names if n != "ao"), rays,
         400, "parameter ao_rays 2 needs the input 'ao'"),
        (good, blobs, {"ao_rays": 17}, 400, "parameter 'ao_rays' must be an integer in [0, 16], got 17"),
        (good, blobs, rays | {"spp": 0}, 400, "parameter 'spp' must be an integer in [1, 4], got 0"),
        (good, blobs, rays | {"sequence_id": "../x"}, 400, "sequence_id must match"),
        ([tensor(n, big[n]) for n in names], b"".join(big[n].tobytes() for n in names), rays, 413,
         "exceeds"),
    ]
    position = np.zeros((h, w, 3), np.float32)
    for bad, words in [(position[..., :2].copy(), f"'position': shape [{h}, {w}, 2] does not fit [H, W, 3]"),
                       (np.full_like(position, np.nan), "'position': NaN or Inf"),
                       (np.full_like(position, 1e30), "'position': values must lie in [-1e+06, 1e+06]")]:
        cases.append((good + [tensor("position", bad)], blobs + bad.tobytes(), rays, 400, words))
    for inputs, body, parameters, status, words in cases:
        got, reply = raw_infer(srv, {"inputs": inputs, "parameters": parameters}, body,
                               path="/v2/models/isosr-recon/infer")
        assert got == status and words in reply["error"], (words, got, reply)
    got, reply = raw_infer(srv, {"inputs": good, "parameters": rays, "outputs": [{"name": "flow"}]}, blobs,
                           path="/v2/models/isosr-recon/infer")
    assert got == 400 and "unknown output 'flow'; isosr-recon gives mask, normal, depth, ao, color" in reply["error"]
    assert raw_infer(srv, {"inputs": good, "parameters": rays}, blobs,
                     path="/v2/models/isosr-recon/versions/2/infer")[0] == 404
    assert raw_infer(srv, {"inputs": good, "parameters": rays}, blobs,
                     path="/v2/models/isosr-recon/versions/1/infer")[0] == 200
    with pytest.raises(InferenceServerException) as e:
        recon_infer(client, {n: f[n] for n in ("mask", "normal")}, parameters={})
    assert e.value.status() == "400" and "missing input 'depth'" in e.value.message()
    assert srv.get_json("/v2/health/ready")[0] == 200
    assert not srv.errors.records, srv.errors.messages()
