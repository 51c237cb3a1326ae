"""Request bodies that are client mistakes (issue 45): refused with a 4xx naming the problem (a 1007
close for a view session), never an HTTP 500 or an ERROR line, and within bounded server memory.

On a real server (uvicorn on loopback, in this process: its RSS is the server's, measured as the
peak RSS while a request runs): KServe v2 tensors with a zero dimension, JSON nested 1000 deep in
a KServe body, msgpack nested 1000 deep in a view session's message (and in ``POST /v1/upscale``),
a ~30 MiB KServe body whose declared shape is far over the limits (refused before its ``data`` is
decoded), and valid requests in JSON (flat and nested) and binary tensors, whose outputs equal
``POST /v1/upscale``'s as before. Every loop is bounded; no test asserts a duration.
"""

from __future__ import annotations

import gc
import json
import threading
from contextlib import contextmanager

import msgspec
import numpy as np
import pytest

from isosr_bench.load import proc_status
from isosr_render import orbit
from isosr_server import protocol as P
from server_fixtures import (DEVICE, expect_close, frame, lib, lib_lowres, running_server, send,  # noqa: F401
                             server_settings, session, upscale_body)

MiB = 2**20
ATOL = 1e-6 if DEVICE == "cpu" else 1e-2
# The default limits: a 32 MiB body is within max_message_bytes, so the big bodies reach the decoder.
LIMITS = P.Limits()
INPUTS, OUTPUTS = ("mask", "normal", "depth", "flow"), ("mask", "normal", "depth", "ao")
UPSCALE_PATH, RECON_PATH = "/v2/models/isosr/infer", "/v2/models/isosr-recon/infer"
# Server memory a ~30 MiB refused body may add at its peak (the decoded body took ~900 MiB).
RSS_BOUND = 50 * MiB
DEEP = 1000


@pytest.fixture(scope="module")
def srv():
    with running_server(server_settings(limits=LIMITS)) as s:
        yield s


@pytest.fixture(scope="module")
def frames(lib):  # noqa: F811
    """Two consecutive low-res frames (the second with flow) as numpy buffers."""
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    return [lib_lowres(lib, c0).to_numpy(), lib_lowres(lib, c1, prev=c0).to_numpy()]


def post(srv, body: bytes, header_length: int | None = None, path: str = UPSCALE_PATH) -> tuple[int, dict, bytes]:
    headers = {"Content-Type": "application/octet-stream" if header_length is not None else "application/json"}
    if header_length is not None:
        headers["Inference-Header-Content-Length"] = str(header_length)
    return srv.request("POST", path, body, headers)


def infer_json(srv, header: dict, blobs: bytes = b"", path: str = UPSCALE_PATH) -> tuple[int, dict]:
    head = msgspec.json.encode(header)
    status, _, body = post(srv, head + blobs, len(head) if blobs else None, path)
    return status, json.loads(body)


def tensor(name: str, a: np.ndarray, binary: bool = True, nested: bool = False) -> dict:
    t = {"name": name, "shape": list(a.shape), "datatype": "FP32"}
    if binary:
        t["parameters"] = {"binary_data_size": a.nbytes}
    else:
        t["data"] = a.tolist() if nested else a.ravel().tolist()
    return t


def assert_refused(srv, status: int, reply: dict, want: int, words: str) -> None:
    assert status == want and reply["status"] == want and words in reply["error"], (want, words, status, reply)


def assert_serving(srv) -> None:
    assert srv.get_json("/v2/health/live")[0] == 200
    assert srv.get_json("/v2/health/ready")[0] == 200
    assert not srv.errors.records, srv.errors.messages()


def test_zero_sized_tensors_get_400_naming_the_zero_dimension(srv):
    for path in (UPSCALE_PATH, RECON_PATH):
        for shape in ((0, 4), (4, 0)):
            arrays = {"mask": np.zeros(shape, np.float32), "normal": np.zeros(shape + (3,), np.float32),
                      "depth": np.zeros(shape, np.float32)}
            dim = shape.index(0)
            # JSON tensors (empty data) and binary ones (binary_data_size 0).
            got = infer_json(srv, {"inputs": [tensor(n, a, binary=False) for n, a in arrays.items()]}, path=path)
            assert_refused(srv, *got, 400, f"input 'mask': shape {list(shape)} has a zero dimension (dimension {dim})")
            got = infer_json(srv, {"inputs": [tensor(n, a) for n, a in arrays.items()]}, b"\0", path=path)
            assert_refused(srv, *got, 400, f"input 'mask': shape {list(shape)} has a zero dimension")
    assert_serving(srv)


def test_binary_data_size_must_be_an_integer(srv, frames):
    f = frames[0]
    blobs = b"".join(f[n].astype("<f4").tobytes() for n in INPUTS if n in f)
    inputs = [tensor(n, f[n]) for n in INPUTS if n in f]
    for size in (float(f["mask"].nbytes), True, str(f["mask"].nbytes)):
        inputs[0]["parameters"] = {"binary_data_size": size}
        got = infer_json(srv, {"inputs": inputs}, blobs)
        assert_refused(srv, *got, 400, f"input 'mask': binary_data_size must be an integer, got {size!r}")
    assert_serving(srv)


def nested(depth: int, inner: bytes = b"") -> bytes:
    return b"[" * depth + inner + b"]" * depth


def test_deeply_nested_kserve_bodies_get_400(srv, frames):
    mask = tensor("mask", frames[0]["mask"], binary=False)
    head = b'{"name":"mask","shape":[12,16],"datatype":"FP32","data":'
    bodies = {
        # 1000 levels (about 2 KB) where a tensor's data goes, in an unknown field, in parameters.
        "data": b'{"inputs":[' + head + nested(DEEP, b"0.5") + b"}]}",
        "unknown field": b'{"pad":' + nested(DEEP) + b',"inputs":[' + msgspec.json.encode(mask) + b"]}",
        "parameters": b'{"parameters":{"x":' + nested(DEEP) + b'},"inputs":[' + msgspec.json.encode(mask) + b"]}",
        "outputs": b'{"inputs":[' + msgspec.json.encode(mask) + b'],"outputs":' + nested(DEEP) + b"}",
    }
    for path in (UPSCALE_PATH, RECON_PATH):
        for where, body in bodies.items():
            status, _, reply = post(srv, body, path=path)
            reply = json.loads(reply)
            assert status == 400 and reply["status"] == 400, (where, status, reply)
            assert "nested too deeply" in reply["error"] or "Expected" in reply["error"], (where, reply)
        status, _, reply = post(srv, bodies["data"], path=path)
        assert "JSON nested too deeply" in json.loads(reply)["error"]
        # Nesting within the decoder's depth but beyond the tensor's rank: refused as such, before decoding.
        status, _, reply = post(srv, b'{"inputs":[' + head + nested(100, b"0.5") + b"}]}", path=path)
        assert_refused(srv, status, json.loads(reply), 400, "input 'mask': data nested 100 deep; shape [12, 16]")
    assert_serving(srv)


def deep_msgpack(depth: int = DEEP) -> bytes:
    """A msgpack array nested ``depth`` deep (one byte a level)."""
    return b"\x91" * depth + b"\x90"


def test_deeply_nested_view_messages_close_1007_and_the_server_serves_on(srv, frames):
    deep = deep_msgpack()
    # A camera message whose first field (before its type, so that the decoder skips it) nests 1000 deep;
    # an open message likewise.
    camera = b"\x82\xa3yaw" + deep + b"\xa4type\xa6camera"
    opening = b"\x82\xa6volume" + deep + b"\xa4type\xa4open"
    with session(srv) as (ws, _):
        frame(ws)
        ws.send(camera)
        expect_close(ws, P.CLOSE_BAD_MESSAGE, "malformed msgpack: nested too deeply")
    with srv.view() as ws:  # the open message's own type: refused at the first level that is no string
        ws.send(opening)
        expect_close(ws, P.CLOSE_BAD_MESSAGE, "Expected `str`, got `array` - at `$.volume`")
    # POST /v1/upscale's msgpack body: 400 with the reason.
    status, _, body = srv.request("POST", "/v1/upscale", b"\x82\xa4mask" + deep + b"\xa4type\xa7upscale")
    assert status == 400 and "nested too deeply" in json.loads(body)["error"], (status, body)
    # The server keeps serving: another session gets frames.
    with session(srv) as (ws, _):
        assert isinstance(frame(ws), P.FrameMsg)
        send(ws, P.CameraMsg(yaw=40.0, pitch=20.0, distance=1.8))
        assert isinstance(frame(ws), P.FrameMsg)
    assert_serving(srv)


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


@contextmanager
def peak_rss():
    """Yields a list that holds, after the block, the process's peak RSS during it: the kernel's
    high-water mark reset first where /proc/self/clear_refs allows, else sampled every millisecond."""
    gc.collect()
    out: list[int] = []
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        stop, samples = threading.Event(), [rss()]

        def sample():
            while not stop.wait(0.001):
                samples.append(rss())

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        try:
            yield out
        finally:
            stop.set()
            sampler.join(10)
            out.append(max(samples + [rss()]))
        return
    yield out
    out.append(int(proc_status("self")["VmHWM"].split()[0]) * 1024)


def big_json_body(shape: list[int], mib: int = 30) -> bytes:
    """A JSON infer body of about ``mib`` MiB: a ``mask`` of ``shape`` whose data is that many
    bytes of zeros (two bytes a value), then the other inputs."""
    values = mib * MiB // 2
    data = b"[" + b"0," * (values - 1) + b"0]"
    small = [{"name": n, "shape": [1, 1] + ([3] if n == "normal" else []), "datatype": "FP32",
              "data": [0.0] * (3 if n == "normal" else 1)} for n in ("normal", "depth")]
    return (b'{"inputs":[{"name":"mask","shape":' + json.dumps(shape).encode() + b',"datatype":"FP32","data":'
            + data + b"}," + b",".join(msgspec.json.encode(t) for t in small) + b"]}")


def test_a_body_over_the_limits_is_refused_before_its_data_is_decoded(srv):
    cases = [
        # A shape far over the limits with ~15M values of data: 413 on the declared shape.
        (big_json_body([100_000, 100_000]), None, 413, "input 'mask': declared shape [100000, 100000]"),
        # A shape within the limits with far more values than it holds: counted on the raw bytes.
        (big_json_body([12, 16]), None, 400, "input 'mask': 15728640 values for shape [12, 16] (192 values)"),
    ]
    # Binary tensors: a declared shape over the limits, its 30 MiB of bytes after the header.
    head = msgspec.json.encode({"inputs": [{"name": "mask", "shape": [4096, 2048], "datatype": "FP32",
                                            "parameters": {"binary_data_size": 30 * MiB}}]})
    cases.append((head + bytes(30 * MiB), len(head), 413, "input 'mask': declared shape [4096, 2048]"))
    for body, header_length, want, words in cases:
        assert len(body) >= 30 * MiB
        post(srv, body[:64])  # a warm-up (400: cut short)
        for _ in range(2):
            before = rss()
            with peak_rss() as peak:
                status, _, reply = post(srv, body, header_length)
            assert_refused(srv, status, json.loads(reply), want, words)
            assert peak[0] - before < RSS_BOUND, f"the server's RSS grew {(peak[0] - before) / MiB:.0f} MiB: {words}"
            assert srv.get_json("/v2/health/live")[0] == 200
    assert_serving(srv)


def upscale_post(srv, frame_np: dict, **fields) -> P.HighresBuffers:
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(frame_np, **fields))
    assert status == 200, body
    return P.parse(body, P.Limits(), (P.UpscaleResponse,)).buffers


def outputs_of(reply: bytes, header_length: str | None) -> dict[str, np.ndarray]:
    n = len(reply) if header_length is None else int(header_length)
    head, offset, out = json.loads(reply[:n]), n, {}
    for t in head["outputs"]:
        if "data" in t:
            out[t["name"]] = np.asarray(t["data"], np.float32).reshape(t["shape"])
        else:
            size = t["parameters"]["binary_data_size"]
            out[t["name"]] = np.frombuffer(reply, "<f4", size // 4, offset).reshape(t["shape"])
            offset += size
    return out


def test_valid_requests_still_work_and_give_the_same_output(srv, frames):
    for i, f in enumerate(frames):
        want = upscale_post(srv, f)
        names = [n for n in INPUTS if n in f]
        blobs = b"".join(f[n].astype("<f4").tobytes() for n in names)
        requests = {
            "binary": ({"inputs": [tensor(n, f[n]) for n in names], "parameters": {"binary_data_output": True}}, blobs),
            "flat json": ({"inputs": [tensor(n, f[n], binary=False) for n in names]}, b""),
            "nested json": ({"inputs": [tensor(n, f[n], binary=False, nested=True) for n in names]}, b""),
            "mixed": ({"inputs": [tensor(n, f[n], binary=n != "normal", nested=True) for n in names],
                       "outputs": [{"name": n, "parameters": {"binary_data": n == "ao"}} for n in OUTPUTS]},
                      b"".join(f[n].astype("<f4").tobytes() for n in names if n != "normal")),
        }
        for kind, (header, blob) in requests.items():
            head = msgspec.json.encode(header)
            status, headers, reply = post(srv, head + blob, len(head) if blob else None)
            assert status == 200, (kind, reply[:300])
            got = outputs_of(reply, {k.lower(): v for k, v in headers.items()}.get("inference-header-content-length"))
            for name in OUTPUTS:
                np.testing.assert_allclose(got[name], getattr(want, name), atol=ATOL, err_msg=f"{kind} {i} {name}")
    assert_serving(srv)
