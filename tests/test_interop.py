"""A real `isosr serve` subprocess as outside code calls it: tritonclient's KServe v2 HTTP client,
and float16 inputs to ``POST /v1/upscale``. The server has a token, is given its model folders as
absolute paths (which its metadata must not reveal) and runs with RuntimeWarnings as errors."""

from __future__ import annotations

import os
import urllib.request

import numpy as np
import pytest

from isosr_bench.bench_server import ServerProcess
from isosr_net.reconstructor import DEFAULT_RECON_MODEL
from isosr_net.upscaler import DEFAULT_MODEL
from isosr_render import Renderer, RenderRequest, open_volume, orbit, resolve_iso
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_server import protocol as P

http = pytest.importorskip("tritonclient.http", reason="tritonclient[http] is not installed (the test extra)")

TOKEN = "interop-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MODELS = ("isosr", "isosr-recon")
# The Open Inference Protocol's tensor datatypes.
KSERVE_DATATYPES = {"BOOL", "UINT8", "UINT16", "UINT32", "UINT64", "INT8", "INT16", "INT32", "INT64", "FP16", "FP32",
                    "FP64", "BYTES"}
VOLUME = "proc:torus@32"


@pytest.fixture(scope="module")
def server():
    with pytest.MonkeyPatch.context() as env:
        env.setenv("PYTHONWARNINGS", "error::RuntimeWarning")  # the server's interpreter only reads it at start
        args = ("--token", TOKEN, "--model", str(DEFAULT_MODEL.resolve()), "--recon-model",
                str(DEFAULT_RECON_MODEL.resolve()), "--log-level", "info")
        with ServerProcess("cpu", extra_args=args) as s:
            yield s


def server_log(server: ServerProcess) -> str:
    fd = server.log.fileno()
    return os.pread(fd, os.fstat(fd).st_size, 0).decode(errors="replace")


def strings(value) -> list[str]:
    """Every string in a JSON value, keys included."""
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in [k, *strings(v)]]
    if isinstance(value, list):
        return [s for v in value for s in strings(v)]
    return []


def test_tritonclient_reads_health_and_metadata(server):
    client = http.InferenceServerClient(f"127.0.0.1:{server.port}")
    try:
        assert client.is_server_live() and client.is_server_ready()  # probes: no token
        with pytest.raises(http.InferenceServerException, match="token"):
            client.get_server_metadata()  # metadata stays behind the token (routes/health.py says why)
        meta = client.get_server_metadata(headers=AUTH)
        assert meta["name"] == "isosr" and meta["version"] and "isosr-upscale" in meta["extensions"]
        for name in MODELS:
            assert client.is_model_ready(name, headers=AUTH)
            model = client.get_model_metadata(name, headers=AUTH)
            assert model["name"] == name and model["platform"] == "pytorch"
            tensors = model["inputs"] + model["outputs"]
            assert {"mask", "normal", "depth"} <= {t["name"] for t in model["inputs"]}
            for t in tensors:
                assert isinstance(t["datatype"], str) and t["datatype"] in KSERVE_DATATYPES, t
                assert all(isinstance(n, int) for n in t["shape"]), t
            paths = [s for s in strings(model) if os.path.isabs(s) or (os.sep in s and os.path.exists(s))]
            assert not paths, paths
            assert model["parameters"]["model"] == (DEFAULT_MODEL if name == "isosr" else DEFAULT_RECON_MODEL).name
        assert not client.is_model_ready("no-such-model", headers=AUTH)
    finally:
        client.close()


def test_float16_upscale_raises_no_runtime_warning(server):
    """A valid frame in float16 (depth included: MAX_DEPTH lies beyond float16's range) is upscaled;
    a RuntimeWarning anywhere on its path would be a 500 in this server."""
    volume = open_volume(VOLUME)
    renderer = Renderer(volume, "cpu")
    request = RenderRequest(16, 12, resolve_iso(VOLUME, volume), LOWRES_BUFFERS + ("flow",),
                            prev_camera=orbit(28, 20, 1.8))
    low = renderer.render(orbit(30, 20, 1.8), request).to_numpy()
    arrays = {n: low[n].astype(np.float16) for n in P.LOWRES_INPUTS}
    body = P.encode(P.UpscaleRequest(**arrays))
    post = urllib.request.Request(server.url + "/v1/upscale", data=body, method="POST",
                                  headers={"Content-Type": P.MSGPACK_MEDIA_TYPE, **AUTH})
    with urllib.request.urlopen(post, timeout=60) as reply:
        assert reply.status == 200
        msg = P.parse(reply.read(), P.Limits(max_message_bytes=2**28), (P.UpscaleResponse,))
    assert msg.buffers.depth.shape == (48, 64) and np.isfinite(msg.buffers.depth).all()
    assert msg.buffers.mask.max() > 0  # the torus is in view: a real frame, not an empty one
    log = server_log(server)
    assert "RuntimeWarning" not in log and "Traceback" not in log, log[-3000:]
