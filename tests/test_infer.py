"""The KServe v2 infer endpoint (``POST /v2/models/isosr[/versions/1]/infer``) on a real server,
called with Triton's own client (``tritonclient[http]``) in JSON and binary tensors.

The outputs must equal ``POST /v1/upscale``'s for the same frames, recurrent state included: the
same engine call computes both, so on the CPU they agree to ATOL = 1e-6 (float32 rounding is all
a float16 or JSON transport could add, and it adds none); on CUDA to 1e-2 like the upscale tests.
"""

from __future__ import annotations

import json

import msgspec
import numpy as np
import pytest

from isosr_render import orbit
from isosr_server import protocol as P
from server_fixtures import (DEVICE, FACTOR, H, W, lib, lib_lowres, running_server, server_settings,  # noqa: F401
                             upscale_body)

httpclient = pytest.importorskip("tritonclient.http", reason="tritonclient[http] is not installed (the test extra)")
from tritonclient.utils import InferenceServerException  # noqa: E402

ATOL = 1e-6 if DEVICE == "cpu" else 1e-2
LIMITS = P.Limits(max_message_bytes=2**20)
INPUTS, OUTPUTS = ("mask", "normal", "depth", "flow"), ("mask", "normal", "depth", "ao")


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
    inputs = []
    for name in INPUTS:
        if name in frame:
            t = httpclient.InferInput(name, list(frame[name].shape), datatype)
            t.set_data_from_numpy(frame[name].astype(np.float16 if datatype == "FP16" else np.float32),
                                  binary_data=binary)
            inputs.append(t)
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
         "mask: values must lie in [0, 1]"),
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
