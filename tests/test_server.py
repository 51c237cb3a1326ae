"""`isosr serve` end to end: a real uvicorn server on loopback, real WebSocket and HTTP clients.

Frames are compared with what the library gives for the same camera: PNG is lossless and the
CPU renderer and network are deterministic, so `full`, `network`, `upscale` and `focus` frames must
match the library's shaded uint8 image to within 1 level; `buffers` frames within the
protocol's coding tolerances; upscale responses to 1e-5.
"""

from __future__ import annotations

import json
import math
import time
import urllib.parse
from contextlib import ExitStack

import msgspec
import numpy as np
import pytest
import torch
from websockets.exceptions import ConnectionClosed

from isosr_net.methods import FrameMethod, Networks, make_runner, run_sequence
from isosr_bench.load import metric_total
from isosr_net.metrics import upscale_baseline
from isosr_net.reconstructor import DEFAULT_RECON_MODEL, recon_limits
from isosr_net.upscaler import DEFAULT_MODEL, Upscaler
from isosr_render import Camera, FrameBuffers, open_volume, orbit, shade
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_render.shading import shade_channels_first
from isosr_render.picking import pick
from isosr_server import protocol as P
from isosr_server import views
from isosr_server.sessions import to_camera
from isosr_render.image_codec import decode_image
from isosr_render.images import to_uint8
from isosr_server.codecs.arrays import encode_array
from isosr_server.codecs.buffers import decode_view_buffers
from isosr_server.sessions import ViewSession, ViewState
from server_fixtures import (CAM0, CORNER_BYTES, DEVICE, FACTOR, H, LEVELS, VOLUME, W, assert_image,  # noqa: F401
                             cam, expect_close, frame, lib, lib_full, lib_lowres, lib_sr, raw, recv, running_server,
                             send, send_expecting_close, server_settings, session, settle, upscale_body, wire,
                             wire_frame, write_corner_volume)

LIMITS = P.Limits(max_message_bytes=2**20, max_sessions=6, idle_timeout_s=30.0, max_fps=1000.0,
                  max_messages_per_s=5000.0)
TOKEN = "correct-horse-battery"
RECON_LIMITS = recon_limits(DEFAULT_RECON_MODEL)  # the served reconstruction model's


@pytest.fixture(scope="module")
def volumes_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("volumes")
    x, y, z = np.meshgrid(np.linspace(-1, 1, 20), np.linspace(-1, 1, 16), np.linspace(-1, 1, 12), indexing="ij")
    np.save(root / "blob.npy", (x**2 + y**2 + z**2).astype(np.float32))
    (root / "notes.txt").write_text("not a volume")
    return root


@pytest.fixture(scope="module")
def srv(volumes_dir):
    with running_server(server_settings(volumes=volumes_dir, limits=LIMITS)) as s:
        yield s


# ---- HTTP endpoints -------------------------------------------------------------------------


def test_health_model_and_volumes(srv, volumes_dir):
    assert srv.get_json("/v2/health/live") == (200, {"live": True})
    assert srv.get_json("/v2/health/ready") == (200, {"ready": True})
    status, model = srv.get_json("/v2/models/isosr")
    params = model["parameters"]
    assert status == 200 and params["upscale_factor"] == FACTOR and params["precision"] == "fp32"
    assert params["encoders"]["png"].startswith("opencv") and params["model"] == DEFAULT_MODEL.name
    assert [i["name"] for i in model["inputs"]] == ["mask", "normal", "depth", "flow"]
    assert [o["name"] for o in model["outputs"]] == ["mask", "normal", "depth", "ao"]
    status, recon = srv.get_json("/v2/models/isosr-recon")
    assert status == 200 and recon["parameters"] == {"model": DEFAULT_RECON_MODEL.name, "precision": "fp32",
                                                     "device": DEVICE, "max_ao_rays": RECON_LIMITS.max_ao_rays,
                                                     "max_spp": RECON_LIMITS.max_spp}
    for name in ("isosr", "isosr-recon"):
        assert srv.get_json(f"/v2/models/{name}/ready") == (200, {"name": name, "ready": True})
    status, listing = srv.get_json("/v1/volumes")
    names = [v["name"] for v in listing["volumes"]]
    assert status == 200 and "blob" in names and "proc:sphere" in names and "notes" not in names
    status, blob = srv.get_json("/v1/volumes/blob")
    assert status == 200 and blob["shape"] == [20, 16, 12] and sum(blob["histogram"]) == 20 * 16 * 12
    assert blob["value_range"][0] == pytest.approx(np.load(volumes_dir / "blob.npy").min())
    status, torus = srv.get_json("/v1/volumes/proc:torus@32")
    assert status == 200 and torus["iso"] == 0.0 and len(torus["histogram"]) == torus["histogram_bins"]
    listed = {v["name"]: v for v in srv.get_json("/v1/volumes")[1]["volumes"]}
    assert listed["blob"]["iso"] == blob["iso"]  # one suggested iso, listed or loaded


@pytest.mark.parametrize("path, status", [
    ("/v1/volumes/..%2F..%2Fetc%2Fpasswd", 404), ("/v1/volumes/..secret", 400), ("/v1/volumes/notes", 404),
    ("/v1/volumes/%2Fetc%2Fpasswd", 404), ("/v1/volumes/proc:cloud:1@500", 400), ("/v1/volumes/a..b", 404),
    ("/v1/nothing", 404),
])
def test_volume_names_never_reach_paths(srv, path, status):
    got, body = srv.get_json(path)
    assert got == status and body["status"] == status and body["error"]


# ---- view modes -----------------------------------------------------------------------------


def test_a_pick_answers_with_the_librarys_point_between_frames(srv, lib):
    """``pick`` on the session's current view: the library's pick of that camera, iso and size;
    a second pick after a camera change follows it; a point outside the view ends the session."""
    with session(srv, mode="full") as (ws, _):
        frame(ws)
        picks = []
        ring = (24.5, 24.5)  # a pixel on the torus from both cameras
        for k, (x, y, camera) in enumerate([(*ring, CAM0), (*ring, P.CameraMsg(yaw=60.0, pitch=20.0, distance=1.8,
                                                                                seq=1))]):
            if camera is not CAM0:
                send(ws, camera)
            send(ws, P.PickMsg(x, y, id=k + 1))
            while not isinstance(msg := recv(ws), P.PickedMsg):
                send(ws, P.ReceivedMsg(msg.seq))  # frames keep coming meanwhile
            expected = pick(lib.renderer, to_camera(camera), lib.iso, W, H, x, y)
            assert (msg.id, msg.hit, msg.voxel) == (k + 1, expected.hit, expected.voxel)
            assert msg.value == pytest.approx(expected.value) and msg.position == pytest.approx(expected.position)
            picks.append(msg)
        assert all(p.hit for p in picks) and picks[0].position != picks[1].position
        send(ws, P.PickMsg(W + 1.0, 0.0))
        expect_close(ws, P.CLOSE_BAD_MESSAGE, "lies outside the")


def test_a_pick_honours_the_sessions_clip(srv, lib):
    """With a clip in the settings, a pick answers as the library's pick with that clip: here a plane
    square to the view just behind the surface point the pixel shows, capped: the cut face."""
    camera, (x, y) = to_camera(CAM0), (24.5, 24.5)
    plain = pick(lib.renderer, camera, lib.iso, W, H, x, y)
    toward = -np.asarray(camera.eye) / np.linalg.norm(camera.eye)
    point = tuple(float(v) for v in np.asarray(plain.world) + 0.01 * toward)
    cut = P.ClipSettings(planes=(P.ClipPlane(point, tuple(float(v) for v in toward)),), cap="below")
    with session(srv, mode="full", clip=cut) as (ws, _):
        frame(ws)
        send(ws, P.PickMsg(x, y, id=1))
        while not isinstance(msg := recv(ws), P.PickedMsg):
            send(ws, P.ReceivedMsg(msg.seq))
    expected = pick(lib.renderer, camera, lib.iso, W, H, x, y, cut.clip())
    assert expected.cap and not plain.cap and expected.depth > plain.depth
    assert (msg.hit, msg.cap, msg.voxel) == (expected.hit, expected.cap, expected.voxel)
    assert msg.depth == pytest.approx(expected.depth) and msg.position == pytest.approx(expected.position)


def test_a_pick_names_the_surface_it_lands_on(srv, lib):
    """With two surfaces set (the torus's distance field: 0 the torus, 0.05 a fatter one around it), a pick lands
    on the outer one, the second in the list: the library's pick with those surfaces, ``surface`` 1, nearer than
    the session's own iso's."""
    camera, (x, y) = to_camera(CAM0), (24.5, 24.5)
    surfaces = (P.SurfaceSettings(0.0), P.SurfaceSettings(0.05))
    with session(srv, mode="full", surfaces=surfaces) as (ws, _):
        frame(ws)
        send(ws, P.PickMsg(x, y, id=1))
        while not isinstance(msg := recv(ws), P.PickedMsg):
            send(ws, P.ReceivedMsg(msg.seq))
    shown = P.surfaces_of(surfaces, lib.renderer.volume.normalized_iso)
    expected = pick(lib.renderer, camera, shown.iso, W, H, x, y, surfaces=shown)
    plain = pick(lib.renderer, camera, lib.iso, W, H, x, y)
    assert (msg.hit, msg.surface, msg.voxel) == (True, 1, expected.voxel) and expected.surface == 1
    assert msg.depth == pytest.approx(expected.depth) and msg.depth < plain.depth - 0.02


def test_bad_clip_or_coloring_settings_get_a_notice_and_the_session_goes_on(srv):
    """Bad clip or coloring settings (7 planes, a zero normal, NaN, an unknown colour map, a field of
    another grid) are refused whole with a notice naming the field, then a frame that acknowledges
    the message and shows the settings as they were (here a clip and no AO, though each message asks
    for AO rays too); the session goes on."""
    plane = {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}
    bad = [({"clip": {"planes": [plane] * 7}}, "$.settings.clip.planes"),
           ({"clip": {"planes": [plane | {"normal": [0.0, 0.0, 0.0]}]}}, "clip.planes[0].normal must be a nonzero"),
           ({"clip": {"planes": [plane | {"point": [math.nan, 0.0, 0.0]}]}}, "$.settings.clip.planes[0].point[0]"),
           ({"coloring": {"by": "gradient", "colormap": "jet"}}, "$.settings.coloring.colormap"),
           ({"coloring": {"by": "blob"}}, "settings.coloring.by: 'blob' has the grid (20, 16, 12)")]
    cut = P.ClipSettings(planes=(P.ClipPlane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),))
    with session(srv, mode="full", clip=cut) as (ws, _):
        first = frame(ws)
        for seq, (update, words) in enumerate(bad, 1):
            ws.send(raw({"type": "settings", "settings": {"ao_rays": 4} | update, "seq": seq}))
            notice = recv(ws)
            assert isinstance(notice, P.NoticeMsg) and words in notice.text, notice
            assert "kept as they were" in notice.text
            again = frame(ws)
            assert again.ack == seq and again.method == first.method
            np.testing.assert_array_equal(decode_image(again.image), decode_image(first.image))
        send(ws, cam(70.0, seq=10))
        assert frame(ws).ack == 10
    with session(srv, mode="full") as (ws, _):  # the clip is visible: without it the frame differs
        assert not np.array_equal(decode_image(frame(ws).image), decode_image(first.image))


def test_the_mesh_download_takes_a_views_clip(srv):
    """``clip`` (a view's settings.clip as JSON) cuts the mesh; a bad one is a 400 naming the field, a
    crop box of zero volume a 422 naming it."""
    path = "/v1/volumes/proc:torus@32/mesh?format=obj"
    status, _, whole = srv.request("GET", path)
    half = json.dumps({"planes": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0]}]})
    status_half, _, cut = srv.request("GET", f"{path}&clip={urllib.parse.quote(half)}")
    assert status == status_half == 200
    vertices = [[float(v) for v in line.split()[1:]] for line in cut.decode().splitlines() if line.startswith("v ")]
    assert 0 < len(vertices) < whole.decode().count("\nv ")
    zs = np.asarray(vertices)[:, 2]  # physical units: the plane z = 0 in the world is the grid's middle
    assert zs.min() >= 15.5 - 1e-3, zs.min()
    no_point = urllib.parse.quote(json.dumps({"planes": [{}]}))
    status, _, body = srv.request("GET", f"{path}&clip={no_point}")
    assert status == 400 and b"clip: Object missing required field `point`" in body
    flat = json.dumps({"box": [[-0.2, 0.0, -0.2], [0.2, 0.0, 0.2]]})
    status, _, body = srv.request("GET", f"{path}&clip={urllib.parse.quote(flat)}")
    assert status == 422 and b"zero volume" in body


def test_a_mesh_download_is_a_device_thread_job_per_slab():
    """The mesh route runs :func:`mesh_steps` through the engine, each step its own device-thread job
    (other sessions' jobs queue between them): a 64^3 volume in 2^17-voxel slabs of 32 planes, 3
    slabs, so 3 jobs counting crossed cells, 2 meshing (the last slab, planes 62-63, has no surface),
    1 ending; the file equals the library's."""
    import asyncio

    from isosr_render import parse_procedural
    from isosr_render.clip import Clip
    from isosr_render.mesh import extract_mesh, mesh_bytes
    from isosr_server.api.routes.volumes import mesh_file
    from isosr_server.engine import Engine

    engine, jobs = Engine(server_settings()), []
    call = engine.call

    async def counted(fn, *args):
        jobs.append(fn.__name__)
        return await call(fn, *args)
    engine.call = counted
    volume = parse_procedural("proc:torus@64")
    try:
        data = asyncio.run(mesh_file(engine, volume, "proc:torus@64", 0.5, 0.5, Clip(), "obj"))
    finally:
        engine.shutdown()
    assert jobs == ["_advance"] * 6
    library = mesh_bytes(extract_mesh(volume, 0.5, DEVICE), ".obj")
    assert data.split(b"\n", 1)[1] == library.split(b"\n", 1)[1]  # past the header line ("Created by meshio ..., <time>")


def test_full_mode_matches_the_library(srv, lib):
    with session(srv, mode="full", ao_rays=4) as (ws, ready):
        assert ready.settings.mode == "full" and ready.volume.iso == 0.0
        assert ready.max_recon_ao_rays == RECON_LIMITS.max_ao_rays
        assert ready.limits == LIMITS and ready.version == P.PROTOCOL_VERSION == 12
        assert [m.name for m in ready.modes] == list(views.VIEWS)  # auto, the registry's view modes, focus
        f = frame(ws)
        assert (f.seq, f.ack, f.mode, f.encoding, f.refined) == (0, -1, "full", "png", False) and f.method
        assert f.nbytes == len(f.image) and f.times["total"] >= f.times["render"] > 0
        assert_image(f.image, lib_full(lib, orbit(30, 20, 1.8), ao_samples=4))
        send(ws, P.SettingsMsg(P.SettingsUpdate(ao_rays=0), seq=1))
        send(ws, P.CameraMsg(eye=(0.3, 0.9, 1.5), seq=2))
        f = frame(ws)
        while f.ack < 2:
            f = frame(ws)
        eye_cam = P.CameraMsg(eye=(0.3, 0.9, 1.5))
        assert_image(f.image, lib_full(lib, Camera(eye_cam.eye)))


def test_network_mode_matches_the_library_with_recurrent_state(srv, lib):
    expected = lib_sr(lib, [orbit(30, 20, 1.8), orbit(33, 20, 1.8), orbit(36, 20, 1.8)])
    with session(srv, mode="network") as (ws, _):
        assert_image(frame(ws).image, expected[0])
        for i, yaw in enumerate((33, 36), start=1):
            send(ws, cam(yaw, seq=i))
            f = frame(ws)
            assert f.ack == i and f.times["network"] > 0
            assert_image(f.image, expected[i])


@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
def test_upscale_mode_matches_the_library(srv, lib, interpolation):
    low = lib_lowres(lib, orbit(30, 20, 1.8))
    stack = upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], FACTOR, interpolation)
    expected = to_uint8(shade_channels_first(stack)[0].permute(1, 2, 0))
    with session(srv, mode="upscale", interpolation=interpolation) as (ws, _):
        f = frame(ws)
        assert f.mode == "upscale"
        assert_image(f.image, expected)


def test_buffers_mode_decodes_to_the_library_buffers(srv, lib):
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    with session(srv, mode="buffers") as (ws, _):
        f0 = frame(ws)
        assert (f0.encoding, f0.prev_seq, f0.width, f0.height) == ("buffers", -1, W, H)
        got = decode_view_buffers(f0.buffers, P.Limits())
        want = lib_lowres(lib, c0).to_numpy()
        assert "flow" not in got and got["mask"].shape == (H // FACTOR, W // FACTOR)
        np.testing.assert_array_equal(got["mask"], want["mask"])
        np.testing.assert_allclose(got["normal"], want["normal"], atol=1e-3)
        np.testing.assert_allclose(got["depth"], want["depth"], atol=np.ptp(want["depth"]) / 131070 + 1e-6)
        send(ws, cam(34, seq=1))
        f1 = frame(ws)
        assert f1.prev_seq == f0.seq
        got = decode_view_buffers(f1.buffers, P.Limits())
        want = lib_lowres(lib, c1, prev=c0).to_numpy()
        np.testing.assert_allclose(got["flow"], want["flow"], atol=1e-3, rtol=2.0**-11)
        assert f1.nbytes < sum(a.nbytes for a in want.values())
        send(ws, P.IsoMsg(0.01, seq=2))  # a new iso is a cut: no flow, prev_seq -1
        f2 = frame(ws)
        assert f2.prev_seq == -1 and f2.buffers.flow is None


def test_focus_mode_full_inside_network_outside(srv, lib):
    camera = orbit(30, 20, 1.8)
    # The focus frame is the session's second: the network's recurrent state holds the first.
    full, sr = lib_full(lib, camera, ao_samples=2), lib_sr(lib, [camera, camera])[1]
    box = (8.0, 12.0, 40.0, 36.0)
    with session(srv, mode="focus", ao_rays=2, focus_blend_px=3) as (ws, _):
        frame(ws)
        send(ws, P.FocusMsg("box", box=box, seq=1))
        got = decode_image(frame(ws).image).astype(int)
    inner = (slice(15, 33), slice(11, 37))  # at least 3 px inside the box
    assert np.abs(got[inner] - full[inner]).max() <= LEVELS
    outside = np.ones((H, W), bool)
    outside[12:36, 8:40] = False
    assert np.abs(got[outside] - sr[outside]).max() <= LEVELS
    assert np.abs(full[inner].astype(int) - sr[inner]).max() > 10 * LEVELS  # the two differ where it is tested


def lib_recon(lib, cameras, ao_rays=2) -> list[FrameBuffers]:
    """The reconstruct frames of a camera path, with one recurrent state (the server's model and precision)."""
    method = FrameMethod.of("reconstruct", ao_rays=ao_rays)
    runner = make_runner(method, lib.renderer, lib.iso, W, H,
                         networks=Networks.eager())
    return run_sequence(runner, cameras)


def test_reconstruct_mode_matches_the_library_with_recurrent_state(srv, lib):
    cameras = [orbit(30, 20, 1.8), orbit(33, 20, 1.8), orbit(36, 20, 1.8)]
    expected = lib_recon(lib, cameras)
    for f in expected:
        assert bool(torch.isfinite(f.color).all()) and 0.0 <= float(f.color.min()) <= float(f.color.max()) <= 1.0
    with session(srv, mode="reconstruct", ao_rays=2) as (ws, ready):
        assert ready.settings.mode == "reconstruct" and ready.settings.ao_rays == 2
        for i, yaw in enumerate((30, 33, 36)):
            if i:
                send(ws, cam(yaw, seq=i))
            f = frame(ws)
            assert (f.mode, f.width, f.height, f.ack) == ("reconstruct", W, H, i if i else -1)
            assert decode_image(f.image).shape == (H, W, 3)
            assert_image(f.image, to_uint8(expected[i].color))
        send(ws, P.SettingsMsg(P.SettingsUpdate(width=50, height=30), seq=3))  # full resolution: any size
        f = frame(ws)
        assert (f.mode, f.width, f.height, f.ack) == ("reconstruct", 50, 30, 3)
        image = decode_image(f.image)
        assert image.shape == (30, 50, 3) and (image < 200).any() and (image == 255).any()
    # Not a plain render: the network's AO and edges differ from 2 rays' (and from the state-less frame).
    assert np.abs(to_uint8(expected[0].color).astype(int) - lib_full(lib, cameras[0], ao_samples=2)).max() > 10
    stateless = lib_recon(lib, cameras[2:])[0]
    assert not torch.equal(stateless.color, expected[2].color)


def test_mode_switches_network_reconstruct_full_mid_session(srv, lib):
    c0, c1 = orbit(30, 20, 1.8), orbit(34, 20, 1.8)
    recon = lib_recon(lib, [c0, c1], ao_rays=1)  # a new mode is a cut: the first frame has no state
    with session(srv, mode="network") as (ws, _):
        assert_image(frame(ws).image, lib_sr(lib, [c0])[0])
        steps = [(P.SettingsMsg(P.SettingsUpdate(mode="reconstruct", ao_rays=1), seq=1), "reconstruct", recon[0]),
                 (cam(34, seq=2), "reconstruct", recon[1]),
                 (P.SettingsMsg(P.SettingsUpdate(mode="full"), seq=3), "full", lib_full(lib, c1, ao_samples=1))]
        for msg, mode, expected in steps:
            send(ws, msg)
            f = frame(ws)
            while f.ack < msg.seq:
                f = frame(ws)
            assert (f.mode, f.width, f.height) == (mode, W, H)
            assert_image(f.image, expected if isinstance(expected, np.ndarray) else to_uint8(expected.color))
    assert not srv.errors.records, srv.errors.messages()


def test_still_camera_gets_one_refined_frame(srv, lib):
    with session(srv, mode="network", refine=True, refine_after_s=0.2, refine_ao_rays=8) as (ws, _):
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


# ---- flow control ---------------------------------------------------------------------------


def test_frames_wait_for_credit_and_the_next_shows_the_newest_state(srv, lib):
    """Without acknowledgments the server sends max_unacked_frames frames (0 and 1) and then
    nothing, however many cameras arrive; one acknowledgment brings the newest camera's frame."""
    credit = LIMITS.max_unacked_frames
    with session(srv, mode="full") as (ws, _):
        for i in range(1, 21):
            send(ws, cam(30 + i, seq=i))
            time.sleep(0.01)
        frames = [recv(ws) for _ in range(credit)]
        assert [f.seq for f in frames] == list(range(credit))
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.5)  # no credit: nothing rendered
        send(ws, P.ReceivedMsg(0))
        newest = recv(ws)
        assert (newest.seq, newest.ack) == (credit, 20)
        assert_image(newest.image, lib_full(lib, orbit(50, 20, 1.8)))
        send(ws, P.ReceivedMsg(0))  # older than the newest acknowledged: changes nothing
        with pytest.raises(TimeoutError):
            ws.recv(timeout=0.3)
        send(ws, P.ReceivedMsg(newest.seq))
        send(ws, cam(10, seq=21))
        assert frame(ws).ack == 21
    assert not srv.errors.records, srv.errors.messages()


def test_bad_acknowledgments_close_that_session_only(srv, lib):
    """An acknowledgment of a frame never sent (before any frame, ahead of the last, huge, not an
    integer) ends the session with 1007 and the reason; another session is served meanwhile."""
    with session(srv, mode="full") as (honest, _):
        frame(honest)
        bad = [(wire(P.ReceivedMsg(5)), "frame 5 was never sent"),
               ({"type": "received", "frame": 2**60}, "Expected `int` <= 9007199254740992 - at `$.frame`"),
               ({"type": "received", "frame": -1}, "Expected `int` >= 0 - at `$.frame`"),
               ({"type": "received", "frame": 0.5}, "Expected `int`, got `float` - at `$.frame`"),
               ({"type": "received"}, "Object missing required field `frame`")]
        for message, words in bad:  # sent at once after open: before the client read any frame
            with session(srv, mode="full") as (ws, _):
                ws.send(raw(message))
                expect_close(ws, P.CLOSE_BAD_MESSAGE, words)
        with session(srv, mode="full") as (ws, _):
            assert frame(ws).seq == 0  # acknowledged: fine
            send(ws, P.ReceivedMsg(1))  # no update since: frame 1 was never made
            expect_close(ws, P.CLOSE_BAD_MESSAGE, "frame 1 was never sent (the newest sent is 0)")
        send(honest, cam(77, seq=1))
        assert_image(frame(honest).image, lib_full(lib, orbit(77, 20, 1.8)))
    assert not srv.errors.records, srv.errors.messages()


def test_acknowledgment_before_any_frame_names_it(lib):
    """The session's own check, before its frame loop sent anything."""
    state = ViewState(P.ViewSettings(), orbit(30, 20, 1.8), lib.iso, P.FocusMsg("none"))
    view = ViewSession("s", VOLUME, open_volume(VOLUME), state, FACTOR, LIMITS)
    with pytest.raises(P.ProtocolError, match="frame 0 was never sent \\(no frame was sent yet\\)") as e:
        view.apply(P.ReceivedMsg(0))
    assert e.value.close_code == P.CLOSE_BAD_MESSAGE
    assert view.has_credit() and view.unacknowledged() == 0


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
    gpu_bytes = float(next(line.split()[-1] for line in text.splitlines() if line.startswith("isosr_gpu_memory_bytes ")))
    assert 'isosr_sessions{kind="view"}' in text and (gpu_bytes > 0) == (DEVICE != "cpu")
    resident = [line for line in text.splitlines() if line.startswith("isosr_volume_resident_bytes{")]
    assert resident and all('mode="dense"' in line and float(line.split()[-1]) > 0 for line in resident)
    # The device thread's seconds in jobs: some (it made the start-up's and this frame), fewer than the server has run.
    busy = metric_total(srv.http_url, "isosr_device_busy_seconds_total")()
    assert busy is not None and 0 < busy < time.monotonic() - srv.began
    assert metric_total(srv.http_url, "isosr_no_such_seconds_total")() is None
    status, info = srv.get_json(f"/v1/volumes/{VOLUME}")
    assert status == 200 and info["device"]["mode"] == "dense" and info["device"]["resident_bytes"] > 0


def test_an_iso_change_on_a_sparse_volume_reports_the_new_resident_set(tmp_path):
    """Below the volume's dense size (``max_volume_bytes``) the server renders it sparse; frames
    carry the device memory when it changed: after the first frame, after an iso change that
    pages bricks in, and not after a camera move."""
    write_corner_volume(tmp_path)
    settings = server_settings(volumes=tmp_path, limits=LIMITS, max_volume_bytes=CORNER_BYTES - 1)
    with running_server(settings) as s, s.view() as ws:
        ws.send(P.encode(P.OpenMsg("corner", P.SettingsUpdate(mode="full", width=W, height=H, encoding="png",
                                                                refine=False), CAM0, iso=235.0)))  # radius 5
        assert isinstance(recv(ws), P.ReadyMsg)
        small = frame(ws).device
        assert small.mode == "sparse" and small.storage == "uint8" and small.limit_bytes == CORNER_BYTES - 1
        assert small.page_ins == 1 and 0 < small.bricks_resident < small.bricks_total == 512
        send(ws, P.IsoMsg(155.0, seq=1))  # radius 25: more bricks
        big = frame(ws)
        assert big.ack == 1 and big.device.page_ins == 2 and big.device.bricks_needed > small.bricks_needed
        assert small.resident_bytes < big.device.resident_bytes < CORNER_BYTES == big.device.dense_bytes
        send(ws, cam(40, seq=2))
        moved = frame(ws)
        assert moved.ack == 2 and moved.device is None  # unchanged
        status, info = s.get_json("/v1/volumes/corner")
        assert status == 200 and info["device"] == msgspec.to_builtins(big.device)


# ---- upscaling ------------------------------------------------------------------------------


def assert_same_buffers(got: P.HighresBuffers, want: dict, atol: float) -> None:
    """High-res buffers equal within ``atol`` where both masks agree on coverage. Normals and
    depth are zeroed where the mask is 0, so on GPUs a mask within rounding of 0 may flip a
    silhouette pixel (seen once on an H100): at most 0.5% of pixels may disagree there."""
    np.testing.assert_allclose(got.mask, want["mask"], atol=atol)
    agree = (got.mask > 0) == (want["mask"] > 0)
    assert agree.mean() >= (1.0 if DEVICE == "cpu" else 0.995)
    for name in P.HIGHRES_OUTPUTS:
        np.testing.assert_allclose(getattr(got, name)[agree], want[name][agree], atol=atol)


def test_upscale_post_buffers_images_and_sessions(srv, lib):
    c0, c1 = orbit(30, 20, 1.8), orbit(33, 20, 1.8)
    f0, f1 = lib_lowres(lib, c0).to_numpy(), lib_lowres(lib, c1, prev=c0).to_numpy()
    upscaler = Upscaler(device=DEVICE)
    want0 = upscaler.upscale(FrameBuffers(**{k: torch.from_numpy(v) for k, v in f0.items()})).to_numpy()
    want1 = upscaler.upscale(FrameBuffers(**{k: torch.from_numpy(v) for k, v in f1.items()})).to_numpy()
    atol = 1e-5 if DEVICE == "cpu" else 1e-2

    status, headers, body = srv.request("POST", "/v1/upscale", upscale_body(f0, session="s1"))
    assert status == 200 and headers["content-type"] == P.MSGPACK_MEDIA_TYPE
    resp = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    assert (resp.width, resp.height) == (W, H)
    assert_same_buffers(resp.buffers, want0, atol)
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(f1, session="s1"))
    resp = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    assert_same_buffers(resp.buffers, want1, atol)
    # Without a session the state is fresh, and the result differs.
    status, _, body = srv.request("POST", "/v1/upscale", upscale_body(f1))
    fresh = P.parse(body, P.Limits(), (P.UpscaleResponse,))
    assert not np.allclose(fresh.buffers.normal, want1["normal"], atol=10 * atol)
    # The shaded image: by the accept header, or by the field.
    status, headers, png = srv.request("POST", "/v1/upscale", upscale_body(f0), {"Accept": "image/png"})
    assert status == 200 and headers["content-type"] == "image/png" and "total" in json.loads(headers["x-isosr-times"])
    want0 = {k: torch.from_numpy(v) for k, v in want0.items()}
    assert_image(png, to_uint8(shade(want0["mask"], want0["normal"], want0["ao"])))
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


def wire_array(a: np.ndarray) -> dict:
    return msgspec.to_builtins(encode_array(a), builtin_types=(bytes,))


def test_upscale_bad_input_gets_4xx_with_reasons(srv, lib):
    good = wire_frame(lib)
    h, w = good["mask"]["shape"]
    f64 = {"dtype": "float64", "shape": [h, w], "data": bytes(8 * h * w)}
    wide = np.zeros((2, 1100), np.float32)
    cases = [
        (b"\xc1\x00", 400, "malformed"),
        (raw(good)[:-7], 400, "malformed"),
        (raw(wire_frame(lib, depth=wire_array(np.full((h, w), np.nan, np.float32)))), 400,
         "NaN or Inf values - at `$.depth`"),
        (raw(wire_frame(lib, depth=wire_array(np.full((h, w), 3e38, np.float32)))), 400, "depth: values must lie in"),
        (raw(wire_frame(lib, depth=f64)), 400, "Invalid enum value 'float64' in `dtype` - at `$.depth`"),
        (raw(wire_frame(lib, normal=good["depth"])), 400, "normal: shape must be"),
        (raw(wire_frame(lib, version=3)), 400, "protocol version 3 is not supported; this server speaks 12"),
        (raw(wire_frame(lib, output="gif")), 400, "at `$.output`"),
        (raw(wire_frame(lib, session="../x")), 400, "at `$.session`"),
        (raw({**good, "pad": b"x" * LIMITS.max_message_bytes}), 413, "limit"),
        (P.encode(P.UpscaleRequest(wide, np.zeros((2, 1100, 3), np.float32), wide)), 413, "exceeds"),
    ]
    for body, status, words in cases:
        got, headers, reply = srv.request("POST", "/v1/upscale", body)
        reason = json.loads(reply)
        assert (got, reason["status"]) == (status, status) and words in reason["error"], (words, reason)
    got, _, reply = srv.request("POST", "/v1/upscale", raw(good), {"Content-Type": "text/plain"})
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

        v = P.PROTOCOL_VERSION
        opens = [
            (b"\x92\x01\x02", P.CLOSE_BAD_MESSAGE, "Expected `object`, got `array`"),
            (raw({"type": "open", "version": 3, "volume": VOLUME}), P.CLOSE_BAD_MESSAGE,
             "protocol version 3 is not supported; this server speaks 12: update the client"),
            (raw({"type": "open", "version": v, "volume": "nope"}), P.CLOSE_NOT_FOUND, "no volume named"),
            (raw({"type": "open", "version": v, "volume": "../blob"}), P.CLOSE_BAD_MESSAGE,
             "Expected `str` matching regex"),
            (raw({"type": "open", "version": v, "volume": "proc:cloud:1@400"}), P.CLOSE_BAD_MESSAGE, "size"),
            (raw({"type": "open", "version": v, "volume": VOLUME, "settings": {"mode": "network", "width": 66}}),
             P.CLOSE_BAD_MESSAGE, "multiple of the upscale factor"),
            (raw({"type": "open", "version": v, "volume": VOLUME, "settings": {"mode": "sr"}}),
             P.CLOSE_BAD_MESSAGE, "unknown mode 'sr'; this server offers auto, full"),
            (raw({"type": "open", "version": v, "volume": VOLUME, "settings": {"width": 4096, "height": 4096}}),
             P.CLOSE_TOO_BIG, "exceeds"),
            (raw({"type": "open", "version": v, "volume": VOLUME, "settings": {"mode": "reconstruct", "ao_rays": -1}}),
             P.CLOSE_BAD_MESSAGE, "Expected `int` >= 0 - at `$.settings.ao_rays`"),
            (raw({"type": "open", "version": v, "volume": VOLUME, "settings": {"ao_rays": 257}}),
             P.CLOSE_BAD_MESSAGE, "Expected `int` <= 256 (max_ao_rays) - at `$.settings.ao_rays`"),
            (P.encode(cam(3)), P.CLOSE_BAD_MESSAGE, "message type must be one of open"),
            (b"\x00" * (LIMITS.max_message_bytes + 10), P.CLOSE_TOO_BIG, ""),
        ]
        for data, code, words in opens:
            with srv.view() as ws:
                send_expecting_close(ws, data, code, words)
            honest_still_served()
        updates = [
            (raw({"type": "camera", "eye": [0.0, 0.0, math.nan]}), P.CLOSE_BAD_MESSAGE, "at `$.eye[2]`"),
            (raw({"type": "camera", "eye": [0, 0, 1], "up": [0, 0, 0]}), P.CLOSE_BAD_MESSAGE, "up is zero"),
            (raw({"type": "settings", "settings": {"mode": "network", "width": 63}}), P.CLOSE_BAD_MESSAGE, "multiple"),
            (raw({"type": "settings", "settings": {"mode": "reconstruct", "ao_rays": -1}}), P.CLOSE_BAD_MESSAGE,
             "Expected `int` >= 0 - at `$.settings.ao_rays`"),
            (raw({"type": "settings", "settings": {"ao_samples": 1}}), P.CLOSE_BAD_MESSAGE,
             "Object contains unknown field `ao_samples` - at `$.settings`"),
            (raw({"type": "iso", "value": 1e300}), P.CLOSE_BAD_MESSAGE, "at `$.value`"),
            (raw({"type": "open", "version": P.PROTOCOL_VERSION, "volume": VOLUME}), P.CLOSE_BAD_MESSAGE, "message type"),
            (raw({"type": "iso", "value": 0.2})[:-3], P.CLOSE_BAD_MESSAGE, "malformed"),
        ]
        for data, code, words in updates:
            with session(srv, mode="full") as (ws, _):
                frame(ws)
                send_expecting_close(ws, data, code, words)
            honest_still_served()
        with session(srv, mode="full") as (ws, _):
            frame(ws)
            ws.send("text is not msgpack")
            expect_close(ws, P.CLOSE_BAD_MESSAGE, "text")
        # The session limit: the honest one plus LIMITS.max_sessions - 1 more, then a refusal.
        settle(srv, live=1)
        with ExitStack() as stack:
            for _ in range(LIMITS.max_sessions - 1):
                ws = stack.enter_context(srv.view())
                send(ws, P.OpenMsg(VOLUME, P.SettingsUpdate(mode="full", width=16, height=12, refine=False)))
                assert isinstance(recv(ws), P.ReadyMsg)
            with srv.view() as ws:  # refused after its open message: a silent WebSocket holds no slot
                send(ws, P.OpenMsg(VOLUME, {"mode": "full", "width": 16, "height": 12, "refine": False}))
                expect_close(ws, P.CLOSE_TOO_MANY, "try later")
        honest_still_served()
    assert srv.get_json("/v2/health/live")[0] == 200
    assert not srv.errors.records, srv.errors.messages()


# ---- the token ------------------------------------------------------------------------------


def test_token_checked_on_every_request_and_handshake(lib):
    with running_server(server_settings(token=TOKEN)) as s:
        for path in ("/v2/health/live", "/v2/health/ready"):  # probes carry no token
            assert s.request("GET", path)[0] == 200
        for path in ("/v2", "/v2/models/isosr", "/v2/models/isosr-recon/ready", "/v1/volumes", "/metrics"):
            for headers in ({}, {"Authorization": "Bearer wrong-token"}, {P.TOKEN_HEADER: TOKEN[:-1]}):
                status, body = s.get_json(path, headers)
                assert status == 401 and "token" in body["error"], (path, headers)
            assert s.request("GET", path, headers={"Authorization": f"Bearer {TOKEN}"})[0] == 200
        status, _, _ = s.request("POST", "/v1/upscale", raw(wire_frame(lib)))
        assert status == 401
        for kwargs in ({}, {"additional_headers": {"Authorization": "Bearer nope"}},
                       {"subprotocols": [P.SUBPROTOCOL, P.TOKEN_SUBPROTOCOL_PREFIX + "nope"]}):
            for path in ("/v1/view", "/v1/upscale/stream"):
                with s.ws(path, **kwargs) as ws:
                    expect_close(ws, P.CLOSE_UNAUTHORIZED, "token")
        for kwargs in ({"additional_headers": {P.TOKEN_HEADER: TOKEN}},
                       {"subprotocols": [P.SUBPROTOCOL, P.TOKEN_SUBPROTOCOL_PREFIX + TOKEN]}):
            with s.view(**kwargs) as ws:
                send(ws, P.OpenMsg(VOLUME, P.SettingsUpdate(mode="full", width=16, height=12)))
                assert isinstance(recv(ws), P.ReadyMsg) and isinstance(recv(ws), P.FrameMsg)
        assert not s.errors.records, s.errors.messages()


# ---- limits: idle time, message rate, frame rate, session expiry -------------------------------

STRICT = P.Limits(max_message_bytes=2**20, max_sessions=2, idle_timeout_s=0.8, max_fps=10.0, max_messages_per_s=30.0)


@pytest.fixture(scope="module")
def strict_srv():
    with running_server(server_settings(limits=STRICT)) as s:
        yield s


def test_idle_view_session_is_closed(strict_srv):
    with session(strict_srv, mode="full") as (ws, _):
        frame(ws)
        expect_close(ws, P.CLOSE_IDLE, "no message")


def test_session_that_never_acknowledges_is_closed(strict_srv):
    """Cameras keep coming (so the session is not idle) but no frame is acknowledged: after
    idle_timeout_s waiting on credit the server closes it with CLOSE_IDLE and the reason."""
    with session(strict_srv, mode="full") as (ws, _):
        with pytest.raises(ConnectionClosed):  # within 4 s, 5 x the timeout
            for i in range(1, 40):
                send(ws, cam(30 + i, seq=i))
                time.sleep(0.1)  # 10 messages a second: within the rate limit
        expect_close(ws, P.CLOSE_IDLE, "acknowledged no frame")


def test_frame_rate_and_message_rate_limits(strict_srv):
    with session(strict_srv, mode="full") as (ws, _):
        frame(ws)
        for i in range(1, 13):  # 20 messages a second: within the rate, above the frame rate
            send(ws, cam(30 + i, seq=i))
            time.sleep(0.05)
        frames = [frame(ws)]
        while frames[-1].ack < 12:
            frames.append(frame(ws))
        # 12 updates over 0.6 s at 10 frames a second: about 7 frames (12 without the limit).
        assert len(frames) <= 9
        for i in range(13, 60):  # a burst above 30 messages a second
            send(ws, cam(30 + i, seq=i))
        expect_close(ws, P.CLOSE_POLICY, "messages a second")
    assert not strict_srv.errors.records, strict_srv.errors.messages()


def test_upscale_sessions_are_bounded_and_expire(strict_srv, lib):
    """A full server drops its least recently used id (which restarts its recurrence) rather than
    refuse a new one; ids expire after the idle timeout."""
    f = lib_lowres(lib, orbit(30, 20, 1.8)).to_numpy()
    for name in ("a", "b", "c"):  # two slots: "c" takes the place of "a", used least recently
        assert strict_srv.request("POST", "/v1/upscale", upscale_body(f, session=name))[0] == 200
    sessions = strict_srv.app.state.upscale_sessions
    assert [k for _, k in sessions._by_id] == ["b", "c"]
    time.sleep(STRICT.idle_timeout_s + 0.2)
    assert strict_srv.request("POST", "/v1/upscale", upscale_body(f, session="d"))[0] == 200
    assert [k for _, k in sessions._by_id] == ["d"]


def test_a_non_finite_network_output_is_refused_and_resets_the_state():
    """The engine's last guard (one host read for all the buffers): NaN in any output buffer raises
    and forgets the previous output, so that it cannot feed the next frame."""
    from isosr_server.engine import _check_finite

    class Network:
        def reset(self):
            self.was_reset = True

    fine = FrameBuffers(mask=torch.ones(2, 3), normal=torch.zeros(2, 3, 3), ao=torch.ones(2, 3))
    network = Network()
    _check_finite(network, fine)
    assert not hasattr(network, "was_reset")
    fine.normal[1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite values"):
        _check_finite(network, fine)
    assert network.was_reset


@pytest.mark.parametrize("setting, upscale, words", [
    ("recon_model", 2, "renders at full resolution; this model also upscales x2"),
    ("recon_x2_model", 1, "x2 reconstruction must upscale x2, this model upscales x1")])
def test_the_service_refuses_a_reconstruction_model_of_the_wrong_scale(tmp_path, setting, upscale, words):
    import asyncio

    from isosr_net.model import save_pretrained
    from isosr_net.reconnet import ReconNet, ReconNetConfig
    from isosr_server.core.config import Settings
    from isosr_server.engine import Engine

    save_pretrained(ReconNet(ReconNetConfig(widths=(4, 4, 8, 8), blocks=1, upscale=upscale)), tmp_path)
    engine = Engine(Settings(**{setting: tmp_path}))
    try:
        with pytest.raises(ValueError, match=words):
            asyncio.run(engine.call(engine.start_sync))
    finally:
        engine.shutdown()
