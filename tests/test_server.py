"""`isosr serve` end to end: a real uvicorn server on loopback, real WebSocket and HTTP clients.

Frames are compared with what the library gives for the same camera: PNG is lossless and the
CPU renderer and network are deterministic, so `full`, `sr`, `bilinear` and `focus` frames must
match the library's shaded uint8 image to within 1 level; `buffers` frames within the
protocol's coding tolerances; upscale responses to 1e-5.
"""

from __future__ import annotations

import json
import math
import time
from contextlib import ExitStack, contextmanager
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed

from isosr_net.metrics import upscale_baseline
from isosr_net.upscaler import Upscaler
from isosr_render import Camera, FrameBuffers, Renderer, RenderRequest, open_volume, orbit, shade
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_render.procedural import default_iso
from isosr_render.shading import shade_channels_first
from isosr_server import protocol as P
from isosr_server.app import ServerConfig
from isosr_server.encoding import decode_image, to_uint8
from server_fixtures import recv, running_server

VOLUME = "proc:torus@32"
W, H, FACTOR = 64, 48, 4
CAM0 = P.CameraMsg(yaw=30.0, pitch=20.0, distance=1.8)
LIMITS = P.Limits(max_message_bytes=2**20, max_sessions=6, idle_timeout_s=30.0, max_fps=1000.0,
                  max_messages_per_s=5000.0)
TOKEN = "correct-horse-battery"


@pytest.fixture(scope="module")
def volumes_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("volumes")
    x, y, z = np.meshgrid(np.linspace(-1, 1, 20), np.linspace(-1, 1, 16), np.linspace(-1, 1, 12), indexing="ij")
    np.save(root / "blob.npy", (x**2 + y**2 + z**2).astype(np.float32))
    (root / "notes.txt").write_text("not a volume")
    return root


@pytest.fixture(scope="module")
def srv(volumes_dir):
    with running_server(ServerConfig(volumes=volumes_dir, limits=LIMITS)) as s:
        yield s


@pytest.fixture(scope="module")
def lib():
    volume = open_volume(VOLUME)
    return SimpleNamespace(renderer=Renderer(volume, "cpu"), iso=volume.normalized_iso(default_iso(VOLUME)))


def lib_full(lib, camera, ao_samples=0) -> np.ndarray:
    outputs = ("mask", "normal") + (("ao",) if ao_samples else ())
    f = lib.renderer.render(camera, RenderRequest(W, H, lib.iso, outputs, ao_samples=max(ao_samples, 1)))
    return to_uint8(shade(f.mask, f.normal, f.ao)).numpy()


def lib_lowres(lib, camera, prev=None) -> FrameBuffers:
    outputs = LOWRES_BUFFERS + (("flow",) if prev is not None else ())
    return lib.renderer.render(camera, RenderRequest(W // FACTOR, H // FACTOR, lib.iso, outputs, prev_camera=prev))


def lib_sr(lib, cameras) -> list[np.ndarray]:
    """The shaded network frames of a camera path, with one recurrent state."""
    upscaler, out, prev = Upscaler(), [], None
    for cam in cameras:
        high = upscaler.upscale(lib_lowres(lib, cam, prev))
        out.append(to_uint8(shade(high.mask, high.normal, high.ao)).numpy())
        prev = cam
    return out


def assert_image(data: bytes, expected: np.ndarray, levels: int = 1):
    got = decode_image(data)
    assert got.shape == expected.shape
    diff = np.abs(got.astype(int) - expected.astype(int))
    assert diff.max() <= levels, f"max diff {diff.max()} levels"


@contextmanager
def session(srv, volume=VOLUME, camera=CAM0, **settings):
    """An opened view session: ``(ws, ready)``; the first frame is not read yet."""
    with srv.view() as ws:
        ws.send(P.pack(P.OpenMsg(volume, {"width": W, "height": H, "encoding": "png", "refine": False, **settings},
                                 camera).to_wire()))
        ready = recv(ws)
        assert isinstance(ready, P.ReadyMsg), ready
        yield ws, ready


def frame(ws) -> P.FrameMsg:
    msg = recv(ws)
    assert isinstance(msg, P.FrameMsg), msg
    return msg


def send(ws, msg: P.Message):
    ws.send(P.pack(msg.to_wire()))


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
            assert e.value.rcvd.code == code and words[:40] in e.value.rcvd.reason
            return
    raise AssertionError("no close")


def live_view_sessions(srv) -> int:
    text = srv.request("GET", "/metrics")[2].decode()
    return int(float(next(line.split()[-1] for line in text.splitlines() if line.startswith('isosr_sessions{kind="view"}'))))


def cam(yaw, seq=None):
    return P.CameraMsg(yaw=float(yaw), pitch=20.0, distance=1.8, seq=seq)


# ---- HTTP endpoints -------------------------------------------------------------------------


def test_health_model_and_volumes(srv, volumes_dir):
    assert srv.get_json("/v2/health/live") == (200, {"live": True})
    assert srv.get_json("/v2/health/ready") == (200, {"ready": True})
    status, model = srv.get_json("/v2/models/isosr")
    assert status == 200 and model["upscale_factor"] == FACTOR
    assert [i["name"] for i in model["inputs"]] == ["mask", "normal", "depth", "flow"]
    assert [o["name"] for o in model["outputs"]] == ["mask", "normal", "depth", "ao"]
    status, listing = srv.get_json("/v1/volumes")
    names = [v["name"] for v in listing["volumes"]]
    assert status == 200 and "blob" in names and "proc:sphere" in names and "notes" not in names
    status, blob = srv.get_json("/v1/volumes/blob")
    assert status == 200 and blob["shape"] == [20, 16, 12] and sum(blob["histogram"]) == 20 * 16 * 12
    assert blob["value_range"][0] == pytest.approx(np.load(volumes_dir / "blob.npy").min())
    status, torus = srv.get_json("/v1/volumes/proc:torus@32")
    assert status == 200 and torus["iso"] == 0.0 and len(torus["histogram"]) == torus["histogram_bins"]


@pytest.mark.parametrize("path, status", [
    ("/v1/volumes/..%2F..%2Fetc%2Fpasswd", 404), ("/v1/volumes/..secret", 400), ("/v1/volumes/notes", 404),
    ("/v1/volumes/%2Fetc%2Fpasswd", 404), ("/v1/volumes/proc:cloud:1@500", 404), ("/v1/volumes/a..b", 404),
    ("/v1/nothing", 404),
])
def test_volume_names_never_reach_paths(srv, path, status):
    got, body = srv.get_json(path)
    assert got == status and body["status"] == status and body["error"]


# ---- view modes -----------------------------------------------------------------------------


def test_full_mode_matches_the_library(srv, lib):
    with session(srv, mode="full", ao_samples=4) as (ws, ready):
        assert ready.settings["mode"] == "full" and ready.volume["iso"] == 0.0
        f = frame(ws)
        assert (f.seq, f.ack, f.mode, f.encoding, f.refined) == (0, -1, "full", "png", False)
        assert f.nbytes == len(f.image) and f.times["total"] >= f.times["render"] > 0
        assert_image(f.image, lib_full(lib, orbit(30, 20, 1.8), ao_samples=4))
        send(ws, P.SettingsMsg({"ao_samples": 0}, seq=1))
        send(ws, P.CameraMsg(eye=(0.3, 0.9, 1.5), seq=2))
        f = frame(ws)
        while f.ack < 2:
            f = frame(ws)
        eye_cam = P.CameraMsg(eye=(0.3, 0.9, 1.5))
        assert_image(f.image, lib_full(lib, Camera(eye_cam.eye)))


def test_sr_mode_matches_the_library_with_recurrent_state(srv, lib):
    expected = lib_sr(lib, [orbit(30, 20, 1.8), orbit(33, 20, 1.8), orbit(36, 20, 1.8)])
    with session(srv, mode="sr") as (ws, _):
        assert_image(frame(ws).image, expected[0])
        for i, yaw in enumerate((33, 36), start=1):
            send(ws, cam(yaw, seq=i))
            f = frame(ws)
            assert f.ack == i and f.times["network"] > 0
            assert_image(f.image, expected[i])


def test_bilinear_mode_matches_the_library(srv, lib):
    low = lib_lowres(lib, orbit(30, 20, 1.8))
    stack = upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], FACTOR, "bilinear")
    expected = to_uint8(shade_channels_first(stack)[0].permute(1, 2, 0)).numpy()
    with session(srv, mode="bilinear") as (ws, _):
        assert_image(frame(ws).image, expected)


def test_buffers_mode_decodes_to_the_library_buffers(srv, lib):
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    with session(srv, mode="buffers") as (ws, _):
        f0 = frame(ws)
        assert (f0.encoding, f0.prev_seq, f0.width, f0.height) == ("buffers", -1, W, H)
        got = P.decode_view_buffers(f0.buffers, P.Limits())
        want = lib_lowres(lib, c0).to_numpy()
        assert "flow" not in got and got["mask"].shape == (H // FACTOR, W // FACTOR)
        np.testing.assert_array_equal(got["mask"], want["mask"])
        np.testing.assert_allclose(got["normal"], want["normal"], atol=1e-3)
        np.testing.assert_allclose(got["depth"], want["depth"], atol=np.ptp(want["depth"]) / 131070 + 1e-6)
        send(ws, cam(34, seq=1))
        f1 = frame(ws)
        assert f1.prev_seq == f0.seq
        got = P.decode_view_buffers(f1.buffers, P.Limits())
        want = lib_lowres(lib, c1, prev=c0).to_numpy()
        np.testing.assert_allclose(got["flow"], want["flow"], atol=1e-3, rtol=2.0**-11)
        assert f1.nbytes < sum(a.nbytes for a in want.values())
        send(ws, P.IsoMsg(0.01, seq=2))  # a new iso is a cut: no flow, prev_seq -1
        f2 = frame(ws)
        assert f2.prev_seq == -1 and "flow" not in f2.buffers


def test_focus_mode_full_inside_network_outside(srv, lib):
    camera = orbit(30, 20, 1.8)
    # The focus frame is the session's second: the network's recurrent state holds the first.
    full, sr = lib_full(lib, camera, ao_samples=2), lib_sr(lib, [camera, camera])[1]
    box = (8.0, 12.0, 40.0, 36.0)
    with session(srv, mode="focus", ao_samples=2, focus_blend_px=3) as (ws, _):
        frame(ws)
        send(ws, P.FocusMsg("box", box=box, seq=1))
        got = decode_image(frame(ws).image).astype(int)
    inner = (slice(15, 33), slice(11, 37))  # at least 3 px inside the box
    assert np.abs(got[inner] - full[inner]).max() <= 1
    outside = np.ones((H, W), bool)
    outside[12:36, 8:40] = False
    assert np.abs(got[outside] - sr[outside]).max() <= 1
    assert np.abs(full[inner].astype(int) - sr[inner]).max() > 1  # the two differ where it is tested


def test_still_camera_gets_one_refined_frame(srv, lib):
    with session(srv, mode="sr", refine=True, refine_after_s=0.2, refine_ao_samples=8) as (ws, _):
        first = frame(ws)
        refined = frame(ws)
        assert not first.refined and refined.refined and refined.mode == "full" and refined.seq == 1
        assert_image(refined.image, lib_full(lib, orbit(30, 20, 1.8), ao_samples=8))
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.6)  # one refined frame per still period


def test_latest_camera_wins(srv, lib):
    with session(srv, mode="full") as (ws, _):
        frame(ws)
        for i in range(1, 41):
            send(ws, cam(30 + i, seq=i))
        frames = [frame(ws)]
        while frames[-1].ack < 40:
            frames.append(frame(ws))
        assert len(frames) < 20, "stale camera updates must coalesce, not queue"
        assert [f.seq for f in frames] == list(range(1, len(frames) + 1))
        assert_image(frames[-1].image, lib_full(lib, orbit(70, 20, 1.8)))
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.4)  # nothing left queued


@pytest.mark.parametrize("encoding", ["jpeg", "webp"])
def test_lossy_encodings(srv, lib, encoding):
    with session(srv, mode="full", encoding=encoding, quality=90) as (ws, _):
        f = frame(ws)
    assert f.encoding == encoding
    diff = np.abs(decode_image(f.image).astype(int) - lib_full(lib, orbit(30, 20, 1.8)))
    assert diff.mean() < 3


def test_metrics_count_frames_stages_and_errors(srv):
    with session(srv, mode="full") as (ws, _):
        frame(ws)
    with srv.view() as ws:
        ws.send(b"\xc1")
        expect_close(ws, P.CLOSE_BAD_MESSAGE)
    status, _, body = srv.request("GET", "/metrics")
    text = body.decode()
    assert status == 200
    assert 'isosr_frames_total{kind="view",mode="full",refined="false"}' in text
    assert 'isosr_stage_seconds_bucket{le="0.5",mode="full",stage="render"}' in text
    assert 'isosr_errors_total{code="1007",kind="view"}' in text
    assert "isosr_sessions{kind=\"view\"}" in text and "isosr_gpu_memory_bytes 0.0" in text


# ---- upscaling ------------------------------------------------------------------------------


def upscale_body(frame_np: dict, **fields) -> bytes:
    req = P.UpscaleRequest(frame_np["mask"], frame_np["normal"], frame_np["depth"], frame_np.get("flow"), **fields)
    return P.pack(req.to_wire())


def test_upscale_post_buffers_images_and_sessions(srv, lib):
    c0, c1 = orbit(30, 20, 1.8), orbit(33, 20, 1.8)
    f0, f1 = lib_lowres(lib, c0).to_numpy(), lib_lowres(lib, c1, prev=c0).to_numpy()
    upscaler = Upscaler()
    want0 = upscaler.upscale(FrameBuffers(**{k: torch.from_numpy(v) for k, v in f0.items()}))
    want1 = upscaler.upscale(FrameBuffers(**{k: torch.from_numpy(v) for k, v in f1.items()}))

    status, headers, body = srv.request("POST", "/v1/upscale", upscale_body(f0, session="s1"))
    assert status == 200 and headers["content-type"] == P.MSGPACK_MEDIA_TYPE
    resp = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    assert (resp.width, resp.height) == (W, H)
    for name in P.HIGHRES_OUTPUTS:
        np.testing.assert_allclose(resp.buffers[name], getattr(want0, name).numpy(), atol=1e-5)
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(f1, session="s1"))
    resp = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    np.testing.assert_allclose(resp.buffers["normal"], want1.normal.numpy(), atol=1e-5)
    # Without a session the state is fresh, and the result differs.
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(f1))
    fresh = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    assert not np.allclose(fresh.buffers["normal"], want1.normal.numpy(), atol=1e-3)
    # The shaded image: by the accept header, or by the field.
    status, headers, png = srv.request("POST", "/v1/upscale", upscale_body(f0), {"Accept": "image/png"})
    assert status == 200 and headers["content-type"] == "image/png" and "total" in json.loads(headers["x-isosr-times"])
    assert_image(png, to_uint8(shade(want0.mask, want0.normal, want0.ao)).numpy())
    status, headers, jpg = srv.request("POST", "/v1/upscale", upscale_body(f0, output="jpeg", quality=50))
    assert status == 200 and headers["content-type"] == "image/jpeg" and jpg[:2] == b"\xff\xd8"


def test_upscale_stream_in_order_with_state(srv, lib):
    cams = [orbit(30 + 3 * i, 20, 1.8) for i in range(3)]
    lows = [lib_lowres(lib, c, prev) for c, prev in zip(cams, [None] + cams[:-1])]
    expected = lib_sr(lib, cams)
    with srv.ws("/v1/upscale/stream") as ws:
        for low in lows:
            ws.send(upscale_body(low.to_numpy(), output="png"))
        for i in range(3):
            resp = recv(ws)
            assert isinstance(resp, P.UpscaleResponse) and resp.seq == i and resp.output == "png"
            assert_image(resp.image, expected[i])
        ws.send(upscale_body(lows[0].to_numpy(), session="x"))
        expect_close(ws, P.CLOSE_BAD_MESSAGE, "session")


def _wire_frame(lib, **overrides) -> dict:
    f = lib_lowres(lib, orbit(30, 20, 1.8)).to_numpy()
    wire = P.UpscaleRequest(f["mask"], f["normal"], f["depth"]).to_wire()
    wire.update(overrides)
    return wire


def test_upscale_bad_input_gets_4xx_with_reasons(srv, lib):
    good = _wire_frame(lib)
    h, w = good["mask"]["shape"]
    nan_depth = P.encode_array(np.full((h, w), np.nan, np.float32))
    f64 = {"dtype": "float64", "shape": [h, w], "data": bytes(8 * h * w)}
    wide = np.zeros((2, 1100), np.float32)
    cases = [
        (b"\xc1\x00", 400, "malformed"),
        (P.pack(good)[:-7], 400, "malformed"),
        (P.pack(_wire_frame(lib, depth=nan_depth)), 400, "NaN"),
        (P.pack(_wire_frame(lib, depth=f64)), 400, "dtype"),
        (P.pack(_wire_frame(lib, normal=good["depth"])), 400, "shape"),
        (P.pack(_wire_frame(lib, version=7)), 400, "version"),
        (P.pack(_wire_frame(lib, output="gif")), 400, "output"),
        (P.pack(_wire_frame(lib, session="../x")), 400, "session"),
        (P.pack({**good, "pad": b"x" * (LIMITS.max_message_bytes + 1)}), 413, "limit"),
        (P.pack(P.UpscaleRequest(wide, np.zeros((2, 1100, 3), np.float32), wide).to_wire()), 413, "exceeds"),
    ]
    for body, status, words in cases:
        got, headers, reply = srv.request("POST", "/v1/upscale", body)
        reason = json.loads(reply)
        assert (got, reason["status"]) == (status, status) and words in reason["error"], (words, reason)
    got, _, reply = srv.request("POST", "/v1/upscale", P.pack(good), {"Content-Type": "text/plain"})
    assert got == 415 and "msgpack" in json.loads(reply)["error"]
    assert srv.get_json("/v2/health/ready")[0] == 200
    assert not srv.errors.records, srv.errors.messages()


# ---- bad view input -------------------------------------------------------------------------


def test_bad_view_input_closes_that_session_only(srv, lib):
    with session(srv, mode="full") as (honest, _):
        frame(honest)
        seq = 0

        def honest_still_served():
            nonlocal seq
            seq += 1
            send(honest, cam(30 + seq, seq=seq))
            f = frame(honest)
            while f.ack < seq:
                f = frame(honest)
            assert_image(f.image, lib_full(lib, orbit(30 + seq, 20, 1.8)))

        opens = [
            (b"\x92\x01\x02", P.CLOSE_BAD_MESSAGE, "map"),
            (P.pack({"type": "open", "version": 1, "volume": "nope"}), P.CLOSE_NOT_FOUND, "no volume named"),
            (P.pack({"type": "open", "version": 1, "volume": "../blob"}), P.CLOSE_BAD_MESSAGE, "volume"),
            (P.pack({"type": "open", "version": 1, "volume": "proc:cloud:1@400"}), P.CLOSE_NOT_FOUND, "size"),
            (P.pack({"type": "open", "version": 1, "volume": VOLUME, "settings": {"mode": "sr", "width": 66}}),
             P.CLOSE_BAD_MESSAGE, "multiple of the upscale factor"),
            (P.pack({"type": "open", "version": 1, "volume": VOLUME, "settings": {"width": 4096, "height": 4096}}),
             P.CLOSE_TOO_BIG, "exceeds"),
            (P.pack(cam(3).to_wire()), P.CLOSE_BAD_MESSAGE, "message type must be one of open"),
            (b"\x00" * (LIMITS.max_message_bytes + 10), P.CLOSE_TOO_BIG, ""),
        ]
        for data, code, words in opens:
            with srv.view() as ws:
                ws.send(data)
                expect_close(ws, code, words)
            honest_still_served()
        updates = [
            (P.pack({"type": "camera", "eye": [0.0, 0.0, math.nan]}), P.CLOSE_BAD_MESSAGE, "finite"),
            (P.pack({"type": "camera", "eye": [0, 0, 1], "up": [0, 0, 0]}), P.CLOSE_BAD_MESSAGE, "up is zero"),
            (P.pack({"type": "settings", "settings": {"mode": "sr", "width": 63}}), P.CLOSE_BAD_MESSAGE, "multiple"),
            (P.pack({"type": "iso", "value": 1e300}), P.CLOSE_BAD_MESSAGE, "value"),
            (P.pack({"type": "open", "version": 1, "volume": VOLUME}), P.CLOSE_BAD_MESSAGE, "message type"),
            (msgpack.packb({"type": "iso", "value": 0.2})[:-3], P.CLOSE_BAD_MESSAGE, "malformed"),
        ]
        for data, code, words in updates:
            with session(srv, mode="full") as (ws, _):
                frame(ws)
                ws.send(data)
                expect_close(ws, code, words)
            honest_still_served()
        with session(srv, mode="full") as (ws, _):
            frame(ws)
            ws.send("text is not msgpack")
            expect_close(ws, P.CLOSE_BAD_MESSAGE, "text")
        # The session limit: the honest one plus LIMITS.max_sessions - 1 more, then a refusal.
        deadline = time.monotonic() + 10
        while live_view_sessions(srv) > 1:  # sessions of the clients above end as the server sees their close
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with ExitStack() as stack:
            for _ in range(LIMITS.max_sessions - 1):
                ws = stack.enter_context(srv.view())
                send(ws, P.OpenMsg(VOLUME, {"mode": "full", "width": 16, "height": 12, "refine": False}))
                assert isinstance(recv(ws), P.ReadyMsg)
            with srv.view() as ws:  # refused on connecting, before its open message
                expect_close(ws, P.CLOSE_TOO_MANY, "try later")
        honest_still_served()
    assert srv.get_json("/v2/health/live")[0] == 200
    assert not srv.errors.records, srv.errors.messages()


# ---- fuzzing against the live server ---------------------------------------------------------

_leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(allow_nan=True),
                  st.text(max_size=12), st.binary(max_size=32))
_value = st.recursive(_leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                     st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                      max_leaves=8)
VALID_UPDATES = {
    "camera": cam(40, seq=1).to_wire(),
    "look-at": P.CameraMsg(eye=(0.5, 0.5, 1.5), seq=1).to_wire(),
    "iso": P.IsoMsg(0.01, seq=1).to_wire(),
    "settings": P.SettingsMsg({"mode": "bilinear", "width": 16, "height": 12, "quality": 50}, seq=1).to_wire(),
    "focus": P.FocusMsg("circle", center=(8.0, 6.0), radius=4.0, seq=1).to_wire(),
}
VALID_OPEN = P.OpenMsg(VOLUME, {"mode": "full", "width": 16, "height": 12, "refine": False}, CAM0).to_wire()


@st.composite
def mutated(draw, valid: dict) -> dict:
    """A valid message with a few fields deleted, replaced by arbitrary values, or added."""
    d = dict(valid)
    for key in draw(st.lists(st.sampled_from(sorted(valid) + ["extra"]), min_size=1, max_size=3)):
        if draw(st.booleans()):
            d.pop(key, None)
        else:
            d[key] = draw(_value)
    if "settings" in d and isinstance(d["settings"], dict) and draw(st.booleans()):
        d["settings"] = {**d["settings"], draw(st.sampled_from(list(P.ViewSettings.__dataclass_fields__))): draw(_value)}
    return d


def _answer_is_frame_or_close(ws):
    msg = recv(ws)
    if isinstance(msg, P.ErrorMsg):
        assert msg.code in (P.CLOSE_BAD_MESSAGE, P.CLOSE_TOO_BIG, P.CLOSE_NOT_FOUND), msg
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=30)
    else:
        assert isinstance(msg, (P.FrameMsg, P.ReadyMsg)), msg


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_view_messages(srv, data):
    kind = data.draw(st.sampled_from(sorted(VALID_UPDATES)))
    wire = data.draw(mutated(VALID_UPDATES[kind]))
    with srv.view() as ws:
        send(ws, P.OpenMsg(VOLUME, {"mode": "full", "width": 16, "height": 12, "refine": False}))
        recv(ws), recv(ws)
        ws.send(P.pack(wire))
        _answer_is_frame_or_close(ws)


@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(wire=mutated(VALID_OPEN))
def test_fuzz_open(srv, wire):
    with srv.view() as ws:
        ws.send(P.pack(wire))
        _answer_is_frame_or_close(ws)


@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_upscale(srv, lib, data):
    good = _wire_frame(lib)
    wire = data.draw(mutated({**good, "mask": dict(good["mask"]) if data.draw(st.booleans()) else good["mask"]}))
    if isinstance(wire.get("mask"), dict) and data.draw(st.booleans()):
        wire["mask"] = data.draw(mutated(good["mask"]))  # inside an array
    status, _, body = srv.request("POST", "/v1/upscale", P.pack(wire))
    assert status == 200 or (status in (400, 413, 422) and json.loads(body)["error"])


def test_after_fuzzing_the_server_is_healthy_and_correct(srv, lib):
    assert srv.get_json("/v2/health/ready") == (200, {"ready": True})
    with session(srv, mode="full") as (ws, _):
        assert_image(frame(ws).image, lib_full(lib, orbit(30, 20, 1.8)))
    assert not srv.errors.records, srv.errors.messages()


# ---- the token ------------------------------------------------------------------------------


def test_token_required_beyond_loopback():
    with pytest.raises(ValueError, match="--token"):
        ServerConfig(host="0.0.0.0")
    assert ServerConfig(host="0.0.0.0", token=TOKEN).token == TOKEN


def test_token_checked_on_every_request_and_handshake(lib):
    with running_server(ServerConfig(token=TOKEN)) as s:
        for path in ("/v2/health/live", "/v2/health/ready", "/v2/models/isosr", "/v1/volumes", "/metrics"):
            for headers in ({}, {"Authorization": "Bearer wrong-token"}, {P.TOKEN_HEADER: TOKEN[:-1]}):
                status, body = s.get_json(path, headers)
                assert status == 401 and "token" in body["error"], (path, headers)
            assert s.request("GET", path, headers={"Authorization": f"Bearer {TOKEN}"})[0] == 200
        status, _, _ = s.request("POST", "/v1/upscale", P.pack(_wire_frame(lib)))
        assert status == 401
        for kwargs in ({}, {"additional_headers": {"Authorization": "Bearer nope"}},
                       {"subprotocols": [P.SUBPROTOCOL, P.TOKEN_SUBPROTOCOL_PREFIX + "nope"]}):
            for path in ("/v1/view", "/v1/upscale/stream"):
                with s.ws(path, **kwargs) as ws:
                    expect_close(ws, P.CLOSE_UNAUTHORIZED, "token")
        for kwargs in ({"additional_headers": {P.TOKEN_HEADER: TOKEN}},
                       {"subprotocols": [P.SUBPROTOCOL, P.TOKEN_SUBPROTOCOL_PREFIX + TOKEN]}):
            with s.view(**kwargs) as ws:
                send(ws, P.OpenMsg(VOLUME, {"mode": "full", "width": 16, "height": 12}))
                assert isinstance(recv(ws), P.ReadyMsg) and isinstance(recv(ws), P.FrameMsg)
        assert not s.errors.records, s.errors.messages()
