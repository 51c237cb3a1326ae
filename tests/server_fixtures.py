"""A real `isosr serve` app on uvicorn on a free loopback port, in a background thread, for tests;
HTTP and WebSocket helpers; a root-logger handler that collects ERROR records; and the library's
own frames (references) for the test volume and size."""

from __future__ import annotations

import datetime
import ipaddress
import json
import logging
import os
import threading
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import msgspec
import numpy as np
import pytest
import uvicorn
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from isosr_net.upscaler import Upscaler
from isosr_render import FrameBuffers, Renderer, RenderRequest, open_volume, orbit, resolve_iso, shade
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_server import protocol as P
from isosr_server.app import create_app, uvicorn_options
from isosr_server.core.config import Settings
from isosr_render.image_codec import decode_image
from isosr_render.images import to_uint8
from isosr_client.serve_process import free_port

if TYPE_CHECKING:  # the TLS helpers import cryptography when called: the GPU machine's kit has none
    from cryptography.hazmat.primitives.asymmetric import ec

# Clients accept big frames (the server's limit bounds what clients send).
CLIENT_LIMITS = P.Limits(max_message_bytes=2**28)
# Wire maps written as they are (hostile, outdated or hand-made messages).
raw = msgspec.msgpack.encode


class ErrorRecords(logging.Handler):
    """Collects every record at ERROR or above that reaches the root logger."""

    def __init__(self):
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def messages(self) -> list[str]:
        return [f"{r.name}: {r.getMessage()}" for r in self.records]


class RunningServer:
    """Where a test server listens, with helpers to call it."""

    def __init__(self, port: int, settings: Settings, errors: ErrorRecords, app, began: float):
        self.port, self.settings, self.errors, self.app = port, settings, errors, app
        self.began = began  # time.monotonic() before the app was made
        ws = "wss" if settings.scheme == "https" else "ws"
        self.http_url, self.ws_url = f"{settings.scheme}://127.0.0.1:{port}", f"{ws}://127.0.0.1:{port}"

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: dict | None = None) -> tuple[int, dict, bytes]:
        """``(status, headers, body)``; 4xx and 5xx are answers, not exceptions."""
        req = urllib.request.Request(self.http_url + path, data=body, method=method, headers=headers or {})
        if body is not None and "Content-Type" not in (headers or {}):
            req.add_header("Content-Type", P.MSGPACK_MEDIA_TYPE)
        try:
            with urllib.request.urlopen(req, timeout=60) as r:
                return r.status, dict(r.headers), r.read()
        except urllib.error.HTTPError as e:
            return e.code, dict(e.headers), e.read()

    def get_json(self, path: str, headers: dict | None = None) -> tuple[int, dict]:
        status, _, body = self.request("GET", path, headers=headers)
        return status, json.loads(body)

    def view(self, **kwargs):
        """A WebSocket connection to ``/v1/view`` (not yet opened)."""
        return self.ws("/v1/view", **kwargs)

    def ws(self, path: str, **kwargs):
        return connect(self.ws_url + path, max_size=2**28, proxy=None, compression=None, open_timeout=30, **kwargs)


def recv(ws, timeout: float = 60) -> P.Message:
    """The next server message of a view or upscale connection, validated."""
    return P.parse(ws.recv(timeout=timeout), CLIENT_LIMITS,
                   dict(P.SERVER_VIEW_MESSAGES, upscaled=P.UpscaleResponse))


@contextmanager
def running_server(settings: Settings):
    """Start the app on uvicorn in a thread (HTTPS with the settings' certificate); yields a
    `RunningServer`; stops it after."""
    errors = ErrorRecords()
    logging.getLogger().addHandler(errors)
    logging.getLogger("isosr").setLevel(logging.INFO)
    port, began = free_port(), time.monotonic()
    # log_config=None: uvicorn leaves logging alone, so its records reach the root logger too.
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None,
                                           **uvicorn_options(settings.limits, settings.tls_context())))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 120
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the test server did not start")
        time.sleep(0.02)
    try:
        yield RunningServer(port, settings, errors, app, began)
    finally:
        server.should_exit = True
        thread.join(30)
        logging.getLogger().removeHandler(errors)


# ISOSR_TEST_DEVICE=cuda runs server and references on the GPU (nvJPEG included where torchvision is).
DEVICE = os.environ.get("ISOSR_TEST_DEVICE", "cpu")
# Shaded uint8 levels a frame may differ from the library's: CPU runs are deterministic; on CUDA the
# server's network runs channels-last, the reference's not, which moves a few pixels by a level or two.
LEVELS = 1 if DEVICE == "cpu" else 3
VOLUME = "proc:torus@32"
W, H, FACTOR = 64, 48, 4
CAM0 = P.CameraMsg(yaw=30.0, pitch=20.0, distance=1.8)


# A 64^3 uint8 volume (bytes on the device) whose iso-surfaces are spheres about a corner voxel: a small
# iso-value (large radius) needs more bricks than a large one.
CORNER_BYTES = 64**3


def write_corner_volume(folder: Path) -> None:
    """``corner.npy`` in ``folder``: uint8 255 - 4 r, r the distance to voxel (8, 8, 8), clipped at 0."""
    x, y, z = np.meshgrid(*(np.arange(64),) * 3, indexing="ij")
    r = np.sqrt((x - 8.0) ** 2 + (y - 8.0) ** 2 + (z - 8.0) ** 2)
    np.save(folder / "corner.npy", np.clip(255 - 4 * r, 0, 255).astype(np.uint8))


def server_settings(**fields) -> Settings:
    """A test server's settings: on DEVICE, in fp32 (the library references' precision)."""
    return Settings(device=DEVICE, precision="fp32", **fields)


@pytest.fixture(scope="module")
def lib():
    volume = open_volume(VOLUME)
    return SimpleNamespace(renderer=Renderer(volume, DEVICE), iso=resolve_iso(VOLUME, volume))


def lib_full(lib, camera, ao_samples=0) -> np.ndarray:
    outputs = ("mask", "normal") + (("ao",) if ao_samples else ())
    f = lib.renderer.render(camera, RenderRequest(W, H, lib.iso, outputs, ao_samples=max(ao_samples, 1)))
    return to_uint8(shade(f.mask, f.normal, f.ao))


def lib_lowres(lib, camera, prev=None) -> FrameBuffers:
    outputs = LOWRES_BUFFERS + (("flow",) if prev is not None else ())
    return lib.renderer.render(camera, RenderRequest(W // FACTOR, H // FACTOR, lib.iso, outputs, prev_camera=prev))


def lib_sr(lib, cameras) -> list[np.ndarray]:
    """The shaded network frames of a camera path, with one recurrent state."""
    upscaler, out, prev = Upscaler(device=DEVICE), [], None
    for cam in cameras:
        high = upscaler.upscale(lib_lowres(lib, cam, prev))
        out.append(to_uint8(shade(high.mask, high.normal, high.ao)))
        prev = cam
    return out


def assert_image(data: bytes, expected: np.ndarray, levels: int = LEVELS):
    got = decode_image(data)
    assert got.shape == expected.shape
    diff = np.abs(got.astype(int) - expected.astype(int))
    assert diff.max() <= levels, f"max diff {diff.max()} levels"


@contextmanager
def session(srv, volume=VOLUME, camera=CAM0, **settings):
    """An opened view session: ``(ws, ready)``; the first frame is not read yet."""
    with srv.view() as ws:
        ws.send(P.encode(P.OpenMsg(volume, P.SettingsUpdate(**{"width": W, "height": H, "encoding": "png",
                                                                 "refine": False, **settings}), camera)))
        ready = recv(ws)
        assert isinstance(ready, P.ReadyMsg), ready
        yield ws, ready


def frame(ws) -> P.FrameMsg:
    """The next message, a frame; acknowledged (``received``) as a client does."""
    msg = recv(ws)
    assert isinstance(msg, P.FrameMsg), msg
    send(ws, P.ReceivedMsg(msg.seq))
    return msg


def send(ws, msg: P.Message):
    ws.send(P.encode(msg))


def send_expecting_close(ws, data: bytes | str, code: int, words: str = ""):
    """Sends ``data`` that the server must refuse; its close may arrive while a large send is still
    in flight (then the send itself raises), else ``expect_close`` reads it."""
    try:
        ws.send(data)
    except ConnectionClosed as e:
        assert_close_frame(e, code, words)
        return
    expect_close(ws, code, words)


def assert_close_frame(closed: ConnectionClosed, code: int, words: str) -> None:
    """The server's close frame has ``code`` and the start of ``words`` (a close's reason is cut short)."""
    assert closed.rcvd is not None and closed.rcvd.code == code and words[:40] in closed.rcvd.reason, closed


def expect_close(ws, code: int, words: str = ""):
    """Frames may precede it; then an error message (unless uvicorn closed first) and the close."""
    for _ in range(20):
        try:
            msg = recv(ws, timeout=30)
        except ConnectionClosed as e:
            assert e.rcvd is not None and e.rcvd.code == code, e
            return
        if isinstance(msg, P.ErrorMsg):
            assert msg.code == code and words in msg.reason, msg
            with pytest.raises(ConnectionClosed) as e:
                ws.recv(timeout=30)
            assert_close_frame(e.value, code, words)
            return
    raise AssertionError("no close")


def live_view_sessions(srv) -> int:
    text = srv.request("GET", "/metrics")[2].decode()
    return int(float(next(line.split()[-1] for line in text.splitlines() if line.startswith('isosr_sessions{kind="view"}'))))


def settle(srv, live: int = 0):
    """Wait until the server has ended the sessions whose clients closed (it sees each close a little later)."""
    deadline = time.monotonic() + 10
    while live_view_sessions(srv) > live:
        assert time.monotonic() < deadline, "view sessions did not end"
        time.sleep(0.01)


def cam(yaw, seq=None):
    return P.CameraMsg(yaw=float(yaw), pitch=20.0, distance=1.8, seq=seq)


def wire(msg: P.Message) -> dict:
    """A message as the plain map that travels."""
    return msgspec.msgpack.decode(P.encode(msg))


def upscale_body(frame_np: dict, **fields) -> bytes:
    req = P.UpscaleRequest(frame_np["mask"], frame_np["normal"], frame_np["depth"], frame_np.get("flow"), **fields)
    return P.encode(req)


def wire_frame(lib, **overrides) -> dict:
    f = lib_lowres(lib, orbit(30, 20, 1.8)).to_numpy()
    return wire(P.UpscaleRequest(f["mask"], f["normal"], f["depth"])) | overrides


def write_key(path: Path) -> ec.EllipticCurvePrivateKey:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    return key


def self_signed_cert(folder: Path) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and localhost, and its key, written into ``folder``:
    ``(cert.pem, key.pem)``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.x509.oid import NameOID

    key = write_key(folder / "key.pem")
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "isosr test")])
    now = datetime.datetime.now(datetime.UTC)
    certificate = (
        x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost"),
                                                    x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256()))
    (folder / "cert.pem").write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    return folder / "cert.pem", folder / "key.pem"


def infer_inputs(frame: dict, names, datatype: str, binary: bool) -> list:
    """tritonclient inputs of the arrays of ``frame`` named in ``names``, as ``datatype``."""
    from tritonclient import http as httpclient  # the test extra; its tests skip without it
    inputs = []
    for name in names:
        if name in frame:
            t = httpclient.InferInput(name, list(frame[name].shape), datatype)
            t.set_data_from_numpy(frame[name].astype(np.float16 if datatype == "FP16" else np.float32),
                                  binary_data=binary)
            inputs.append(t)
    return inputs
