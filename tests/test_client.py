"""The thin client (`isosr_client`, `isosr client`) against a real `isosr serve` subprocess on
loopback: every mode's frames against the library, the upscaling API, errors, the command
line, load, a slow client beside a fast one, and the server benchmark's smoke run.

Frames are 64x48 (16x12 low-res): the CPU runs the network at about 3 frames/s there."""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from client_fixtures import server  # noqa: F401  (the module's server fixture)
from server_fixtures import running_server
from websockets.sync.client import connect as ws_connect

from isosr_bench import bench_server, sessions
from isosr_bench.common import RESULTS_DIR, write_result
from isosr_cli.main import main
from isosr_client import ServerError, connect, decode_image, upscale_remote
from isosr_client.drive import Orbit, drag, drive
from isosr_client.volumes import slice_remote, volumes_remote
from isosr_client.view import CLIENT_LIMITS, FrameStats
from isosr_render.images import to_uint8
from isosr_net.methods import FrameMethod, Networks, make_runner, run_sequence
from isosr_net.metrics import upscale_baseline
from isosr_net.reconstructor import recon_limits
from isosr_net.upscaler import Upscaler
from isosr_render import FrameBuffers, Renderer, RenderRequest, open_volume, orbit
from isosr_render.clip import Clip
from isosr_render.color_field import ColorField
from isosr_render.coloring import Coloring
from isosr_render.conventions import LOWRES_BUFFERS
from isosr_render.picking import pick
from isosr_render.slices import CONTOUR_RGB, slice_image
from isosr_render.shading import shade, shade_channels_first
from isosr_render.surfaces import Surfaces
from isosr_server.core.config import Settings
from isosr_server.protocol import (CLOSE_BAD_MESSAGE, SERVER_VIEW_MESSAGES, AutoChoice, CameraMsg, FrameMsg, Limits,
                                   OpenMsg, ProtocolError, ReadyMsg, ReceivedMsg, SettingsUpdate, encode, parse)

VOLUME = "proc:cloud:0@32"
SIZE = (64, 48)
PATH = Orbit(30.0, 20.0, 1.8, 3.0)
FRAMES = 3
LOSSLESS = {"encoding": "png", "refine": False}


@pytest.fixture(scope="module")
def library(server):  # noqa: F811
    """The renderer of the volume the server shows, and its normalized iso (as ``ready`` says)."""
    with connect(server.url, VOLUME, "full", SIZE, settings=LOSSLESS) as view:
        iso = view.ready.volume.iso_normalized
    return Renderer(open_volume(VOLUME), "cpu"), iso


def session_frames(url: str, mode: str, settings: dict = LOSSLESS, focus=None, frames: int = FRAMES):
    """RGB frames and stats of PATH's first ``frames`` cameras in one session, closed loop (each
    update waits for its frame), so the server's recurrent chain is always the same: the open
    frame at camera 0, [the focus update's frame at camera 0,] cameras 1, 2, ..."""
    with connect(url, VOLUME, mode, SIZE, settings=settings, camera=PATH.camera(0)) as view:
        first = view.latest()
        if focus is not None:
            view.set_focus(**focus)
            first = view.latest()
        images, stats = [first.rgb()], [first.stats]
        for i in range(1, frames):
            view.set_camera(**PATH.camera(i))
            images.append(view.frame())
            stats.append(view.stats)
    return images, stats


def lowres_frames(renderer, iso, frames: int = FRAMES, factor: int = 4):
    """The network's inputs along PATH, flow from the second frame on, as the server renders them."""
    w, h = SIZE[0] // factor, SIZE[1] // factor
    out = []
    for i in range(frames):
        prev = None if i == 0 else orbit(**PATH.camera(i - 1))
        request = RenderRequest(w, h, iso, LOWRES_BUFFERS + (("flow",) if prev else ()), prev_camera=prev)
        out.append(renderer.render(orbit(**PATH.camera(i)), request))
    return out


def test_client_imports_without_torch():
    """``import isosr_client`` loads neither torch nor Warp (nor the renderer or the network), in a
    fresh interpreter: what a notebook or a browser-side tool pays for the client alone (its time is
    a benchmark's to say, not this test's)."""
    check = ("import sys; import isosr_client; "
             "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'warp') "
             "or m in ('isosr_render.renderer', 'isosr_net.upscaler')))")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, env=env, timeout=60,
                            cwd=root)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "[]", f"import isosr_client loaded {result.stdout.strip()}"


def level_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(np.int16) - b.astype(np.int16))


def test_full_and_network_frames_equal_the_library(server, library):  # noqa: F811
    """full: the renderer + shading; network: + the Upscaler with its recurrent state. PNG is lossless,
    so the frames equal the library's within 1 level (float rounding across processes)."""
    renderer, iso = library
    full, stats = session_frames(server.url, "full")
    for i, image in enumerate(full):
        ref = renderer.render(orbit(**PATH.camera(i)), RenderRequest(*SIZE, iso, ("mask", "normal")))
        assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
        assert level_diff(image, to_uint8(shade(ref.mask, ref.normal))).max() <= 1
        assert (image != 255).any()  # the surface is in view
    assert all(s.nbytes > 0 and s.latency_ms > 0 and "render" in s.server_ms and not s.refined for s in stats)

    sr, _ = session_frames(server.url, "network")
    upscaler = Upscaler()
    for image, low in zip(sr, lowres_frames(renderer, iso)):
        high = upscaler.upscale(low)
        assert level_diff(image, to_uint8(shade(high.mask, high.normal, high.ao))).max() <= 1


def test_clipped_frames_equal_the_library(server, library):  # noqa: F811
    """set_clip: the server's frames are the library's with the same clip, cut faces in grey; a bad
    plane is refused naming it before anything is sent."""
    renderer, iso = library
    planes, box = [((0.0, 0.0, 0.05), (0.0, 0.0, -1.0))], ((-0.4, -0.5, -0.5), (0.5, 0.5, 0.5))
    clip = Clip(tuple(planes), box, "above")
    camera = PATH.camera(0)
    with connect(server.url, VOLUME, "full", SIZE, settings=LOSSLESS, camera=camera) as view:
        plain = view.latest().rgb()
        with pytest.raises(ProtocolError, match=r"clip.planes\[0\].normal must be a nonzero vector"):
            view.set_clip([((0, 0, 0), (0, 0, 0))])
        view.set_clip(planes, box, "above")
        image = view.frame()
        assert view.settings.clip.clip() == clip
    ref = renderer.render(orbit(**camera), RenderRequest(*SIZE, iso, ("mask", "normal", "cap"), clip=clip))
    assert (ref.cap[..., 0] > 0).any() and (level_diff(image, plain) > 8).any()
    assert level_diff(image, to_uint8(shade(ref.mask, ref.normal, cap=ref.cap))).max() <= 1


def test_colored_frames_equal_the_library(server, library):  # noqa: F811
    """set_coloring: the server's frames are the library's with the same coloring (a second volume of the
    grid, by name), with its legend; bad settings are refused naming the field."""
    renderer, iso = library
    field_name, camera = "proc:sphere@32", PATH.camera(0)
    with connect(server.url, VOLUME, "full", SIZE, settings=LOSSLESS, camera=camera) as view:
        plain = view.latest().rgb()
        with pytest.raises(ProtocolError, match=r"coloring.colormap"):
            view.set_coloring(field_name, "jet")
        with pytest.raises(ProtocolError, match=r"coloring.range\[1\]"):
            view.set_coloring(field_name, range=(1.0, float("nan")))
        with pytest.raises(ProtocolError, match=r"coloring.range must be finite with lo <= hi"):
            view.set_coloring(field_name, range=(2.0, 1.0))
        view.set_coloring(field_name, "magma", (0.0, 1.0))
        frame = view.latest()
        image, legend = frame.rgb(), frame.message.legend
        assert (legend.colormap, legend.lo, legend.hi, legend.unit) == \
            ("magma", 0.0, 1.0, field_name)
    field = ColorField.of(Coloring(field_name, "magma", (0.0, 1.0)), renderer.volume, open_volume(field_name))
    ref = renderer.render(orbit(**camera), RenderRequest(*SIZE, iso, ("mask", "normal"), coloring=field))
    assert (level_diff(image, plain) > 8).any()
    assert level_diff(image, to_uint8(shade(ref.mask, ref.normal, albedo=ref.albedo))).max() <= 1
    with connect(server.url, VOLUME, "full", SIZE, settings=LOSSLESS) as view:  # refused, the session goes on
        before = view.frame()
        view.set_coloring("proc:sphere@16")
        with pytest.warns(UserWarning, match=r"\(16, 16, 16\), not the viewed volume's \(32, 32, 32\)"):
            after = view.latest()
        assert view.latest().message.legend is None and np.array_equal(after.rgb(), before)


def test_several_surfaces_equal_the_library(server, library):  # noqa: F811
    """set_surfaces: the server's frames are the library's with the same surfaces (isos in data units, each its
    colour); bad ones are refused naming the field, and no surfaces is the one iso again."""
    renderer, iso = library
    lo, hi = renderer.volume.value_range
    pairs = [(lo + iso * (hi - lo), (0.2, 0.4, 0.9)), (lo + (iso - 0.1) * (hi - lo), (0.9, 0.3, 0.2))]
    camera = PATH.camera(0)
    with connect(server.url, VOLUME, "full", SIZE, settings=LOSSLESS, camera=camera) as view:
        plain = view.latest().rgb()
        with pytest.raises(ProtocolError, match=r"surfaces\[0\].color\[2\]"):
            view.set_surfaces([(0.5, (0.0, 0.0, 1.5))])
        with pytest.raises(ProtocolError, match=r"length <= 4"):
            view.set_surfaces([(0.1 * i, (0.0, 0.0, 0.0)) for i in range(5)])
        with pytest.warns(UserWarning, match="settings refused.*must differ"):  # equal isos: a notice
            view.set_surfaces([(pairs[0][0], (1.0, 0.0, 0.0)), (pairs[0][0], (0.0, 0.0, 1.0))])
            assert level_diff(view.latest().rgb(), plain).max() <= 1
        assert any("settings refused" in n and "must differ" in n for n in view.notices), list(view.notices)
        view.set_surfaces(pairs)
        image = view.frame()
        view.set_surfaces()
        again = view.frame()
    surfaces = Surfaces.of([(renderer.volume.normalized_iso(v), c) for v, c in pairs])
    ref = renderer.render(orbit(**camera), RenderRequest(*SIZE, surfaces.iso, ("mask", "normal", "surface"),
                                                         surfaces=surfaces))
    assert (ref.surface == 1).any() and (level_diff(image, plain) > 8).any()
    assert level_diff(image, to_uint8(shade(ref.mask, ref.normal, albedo=ref.albedo))).max() <= 1
    assert level_diff(again, plain).max() <= 1
    # The outer one translucent: network mode's method runs on each layer and composites them, as the library's.
    translucent = [pairs[0], (*pairs[1], 0.4)]
    with connect(server.url, VOLUME, "network", SIZE, settings=LOSSLESS, camera=camera) as view:
        view.set_surfaces(translucent)
        frame = view.latest()
        image = frame.rgb()
    surfaces = Surfaces.of([(renderer.volume.normalized_iso(v), *rest) for v, *rest in translucent])
    method = FrameMethod.of("network", factor=SIZE[0] // 16)
    runner = make_runner(method, renderer, surfaces.iso, *SIZE, networks=Networks.eager(), surfaces=surfaces)
    want = runner.frame(orbit(**camera))
    assert frame.message.method == method.name and (want.buffers.behind.mask > 0).any()
    assert level_diff(image, to_uint8(want.buffers.color)).max() <= 1


def test_buffers_mode_upscaled_here_equals_network(server):  # noqa: F811
    """buffers + local Upscaler and shading == the server's network frames, up to the buffers coding
    (mask 1/255, normals < 1e-3 rad, depth 16 bit, flow float16): stated bound 40 dB PSNR and a
    mean difference under 0.5 levels; the recurrent state continues (prev_seq) across frames."""
    sr, _ = session_frames(server.url, "network")
    buffers, stats = session_frames(server.url, "buffers", {"refine": False})
    for a, b in zip(buffers, sr):
        assert bench_server.psnr(a, b) > 40.0
        assert level_diff(a, b).mean() < 0.5
    assert all(s.mode == "buffers" and "network" in s.client_ms and "decode" in s.client_ms for s in stats)
    assert all(s.nbytes > 0 for s in stats)


def test_upscale_and_focus_frames(server, library):  # noqa: F811
    """upscale: the library's bilinear baseline, shaded. focus: full resolution deep inside the
    circle, the network frame well outside it."""
    renderer, iso = library
    bilinear, _ = session_frames(server.url, "upscale", frames=1)
    low = lowres_frames(renderer, iso, frames=1)[0]
    stack = upscale_baseline(low.channels_first(LOWRES_BUFFERS)[None], 4, "bilinear")
    assert level_diff(bilinear[0], to_uint8(shade_channels_first(stack)[0].permute(1, 2, 0))).max() <= 1

    center, radius, blend = (32.0, 24.0), 12.0, 4
    focus, _ = session_frames(server.url, "focus", dict(LOSSLESS, focus_blend_px=blend), frames=2,
                              focus={"shape": "circle", "center": center, "radius": radius})
    full, _ = session_frames(server.url, "full", frames=2)
    sr, _ = session_frames(server.url, "network", frames=2, focus={"shape": "none"})  # the same recurrent chain
    y, x = np.mgrid[:SIZE[1], :SIZE[0]] + 0.5
    dist = np.hypot(x - center[0], y - center[1])
    inside, outside = dist < radius - blend - 1, dist > radius + 1
    for f, a, b in zip(focus, full, sr):
        assert level_diff(f[inside], a[inside]).max() <= 1
        assert level_diff(f[outside], b[outside]).max() <= 1
        assert (f[inside] != 255).any()


def test_reconstruct_frames_equal_the_library(server, library):  # noqa: F811
    """reconstruct: a full-res render with 2 AO rays per hit, the Reconstructor with its recurrent
    state, shading (the library's FrameRunner), at a size no upscale factor divides."""
    renderer, iso = library
    size = (50, 30)
    with connect(server.url, VOLUME, "reconstruct", size, settings=dict(LOSSLESS, ao_rays=2),
                 camera=PATH.camera(0)) as view:
        images = [view.latest().rgb()]
        for i in range(1, FRAMES):
            view.set_camera(**PATH.camera(i))
            images.append(view.frame())
        assert view.stats.mode == "reconstruct" and "total" in view.stats.server_ms
    method = FrameMethod.of("reconstruct", ao_rays=2)
    runner = make_runner(method, renderer, iso, *size, networks=Networks.eager())
    expected = run_sequence(runner, [orbit(**PATH.camera(i)) for i in range(FRAMES)])
    for image, want in zip(images, expected):
        assert image.shape == (size[1], size[0], 3) and (image != 255).any()
        assert level_diff(image, to_uint8(want.color)).max() <= 1


def test_refined_frame_for_a_still_camera(server, library):  # noqa: F811
    """A still camera gets one refined frame: full resolution with refine_ao_rays AO rays."""
    renderer, iso = library
    settings = {"encoding": "png", "refine": True, "refine_after_s": 0.2, "refine_ao_rays": 4, "ao_radius": 0.1}
    with connect(server.url, VOLUME, "network", SIZE, settings=settings) as view:
        view.set_camera(**PATH.camera(0))
        first = view.latest()
        assert not first.stats.refined
        image = view.frame(refined=True, timeout=60)
        assert view.stats.refined and view.stats.mode == "full"
    request = RenderRequest(*SIZE, iso, ("mask", "normal", "ao"), ao_samples=4, ao_radius=0.1)
    ref = renderer.render(orbit(**PATH.camera(0)), request)
    assert level_diff(image, to_uint8(shade(ref.mask, ref.normal, ref.ao))).max() <= 1


def test_upscale_api_buffers_image_and_session_state(server, library):  # noqa: F811
    """POST /v1/upscale: buffers (float32 numpy) equal the local Upscaler's (1e-5), the PNG its
    shading; a session id carries the recurrent state to the next frame; torch tensors and numpy
    arrays both travel."""
    renderer, iso = library
    frames = lowres_frames(renderer, iso, frames=2)
    local = Upscaler()
    for i, low in enumerate(frames):
        sent = low if i == 0 else low.to_numpy()  # a FrameBuffers of tensors, then a map of numpy arrays
        result = upscale_remote(server.url, sent, session="client-test")
        ref = local.upscale(low)
        for name in ("mask", "normal", "depth", "ao"):
            got = getattr(result.buffers, name)
            assert isinstance(got, np.ndarray) and got.dtype == np.float32 and got.flags.writeable
            np.testing.assert_allclose(got, getattr(ref, name).numpy(), atol=1e-5, rtol=1e-5)
        assert "network" in result.times and result.replica is None and not result.restarted
    png = upscale_remote(server.url, frames[0], output="png")
    ref = Upscaler().upscale(frames[0])
    assert level_diff(decode_image(png.image), to_uint8(shade(ref.mask, ref.normal, ref.ao))).max() <= 1
    with pytest.raises(ValueError, match="depth"):
        upscale_remote(server.url, FrameBuffers(mask=frames[0].mask, normal=frames[0].normal))
    bad = FrameBuffers(mask=frames[0].mask, normal=frames[0].normal, depth=frames[0].depth * float("nan"))
    with pytest.raises(ProtocolError, match="NaN"):
        upscale_remote(server.url, bad)


def test_pick_two_points_and_their_distance(server, library):  # noqa: F811
    """``View.pick``: the library's pick of the view's camera; two hits give a physical distance;
    frames keep coming around the picks."""
    renderer, iso = library
    with connect(server.url, VOLUME, "full", SIZE, settings={"refine": False}) as view:
        view.set_camera(yaw=30.0, pitch=20.0, distance=1.6)
        view.latest()
        points = [(x + 0.5, SIZE[1] / 2 + 0.5) for x in range(0, SIZE[0], 4)]
        picks = [view.pick(*p) for p in points]
        hits = [p for p in picks if p.hit]
        assert len(hits) >= 2, "the cloud is in view"
        expected = pick(renderer, orbit(30.0, 20.0, 1.6), iso, *SIZE, hits[0].x, hits[0].y)
        assert hits[0].voxel == expected.voxel and hits[0].value == pytest.approx(expected.value)
        assert math.dist(hits[0].position, hits[-1].position) > 0
        view.set_camera(yaw=40.0, pitch=20.0, distance=1.6)
        assert view.latest().stats.ack >= 1


def test_slices_over_http_equal_the_librarys_and_bad_ones_are_refused(server, library):  # noqa: F811
    """``GET /v1/volumes/NAME/slices/AXIS``: the library's slice image, losslessly; an index outside
    the volume is a 400 and an iso outside its range a 422, each naming the problem."""
    renderer, iso = library
    volume = renderer.volume
    lo, hi = volume.value_range
    data_iso = lo + iso * (hi - lo)
    for axis, name in enumerate("xyz"):
        got = slice_remote(server.url, VOLUME, name, 16, iso=data_iso)
        assert np.array_equal(got, slice_image(volume, axis, 16, volume.normalized_iso(data_iso)))
    assert (got == CONTOUR_RGB).all(-1).any(), "the iso contour is drawn"
    assert all("name" in v and ("shape" in v or "error" in v) for v in volumes_remote(server.url))  # the folder's
    with pytest.raises(ServerError, match=r"index must be an integer in \[0, 31\]") as e:
        slice_remote(server.url, VOLUME, "z", 32)
    assert e.value.code == 400
    with pytest.raises(ServerError, match="iso") as e:
        slice_remote(server.url, VOLUME, "z", 3, iso=hi + 10 * (hi - lo))
    assert e.value.code == 422


def test_client_errors_are_clear(server):  # noqa: F811
    """Bad input fails with the reason (before sending where the client can tell), the server's
    refusals come back as ServerError with its code, and the server serves on."""
    with pytest.raises(ServerError) as e:
        connect(server.url, "no_such_volume", "network", SIZE)
    assert e.value.code == 4404
    with pytest.raises(ServerError, match="unknown mode 'sharpest'; this server offers auto, full") as e:
        connect(server.url, VOLUME, "sharpest", SIZE)  # the server's registry decides
    assert e.value.code == CLOSE_BAD_MESSAGE
    with pytest.raises(ValueError, match="URL"):
        connect("ftp://127.0.0.1:1", VOLUME)
    with pytest.raises(ProtocolError, match="unknown field `ao_samples`"):
        connect(server.url, VOLUME, "full", SIZE, settings={"ao_samples": 2})
    with pytest.raises(ServerError, match="multiple of the upscale factor"):
        connect(server.url, VOLUME, "network", (63, 48))
    most = recon_limits().max_ao_rays  # the shipped model's: more rays are cast and read as that many
    with connect(server.url, VOLUME, "reconstruct", SIZE, settings={"ao_rays": most + 1}) as view:
        assert view.frame().shape == (SIZE[1], SIZE[0], 3)
    with connect(server.url, VOLUME, "network", SIZE, settings=LOSSLESS) as view:
        assert view.ready.max_recon_ao_rays == most and view.settings.mode == "network"
        with pytest.raises(ProtocolError, match="eye"):
            view.set_camera(yaw=10.0)
        with pytest.raises(ProtocolError, match=r"quality"):
            view.set_settings(quality=500)
        with pytest.raises(ProtocolError, match="exceeds the limits"):
            view.set_settings(width=4096, height=4096)
        assert view.settings.quality == 85 and view.settings.width == SIZE[0]  # nothing changed
        view.set_camera(**PATH.camera(0))
        assert view.frame().shape == (SIZE[1], SIZE[0], 3)


def test_token_travels_and_its_absence_is_a_clear_refusal(library):
    """Against a server with a token: the client's header gets frames and upscaling; without it,
    or with a wrong one, the session and the POST are refused (401 / 4401) with the server's reason."""
    token = "client-test-token"
    renderer, iso = library
    low = lowres_frames(renderer, iso, frames=1)[0]
    with running_server(Settings(token=token)) as s:
        for wrong in (None, "not-the-token"):
            with pytest.raises(ServerError) as e:
                connect(s.http_url, VOLUME, "network", SIZE, token=wrong)
            assert e.value.code in (401, 4401) and "token" in e.value.reason  # a denied handshake, or a close
            with pytest.raises(ServerError) as e:
                upscale_remote(s.http_url, low, token=wrong)
            assert e.value.code == 401 and "token" in e.value.reason
        with connect(s.http_url, VOLUME, "network", SIZE, token=token, settings=LOSSLESS) as view:
            assert view.frame().shape == (SIZE[1], SIZE[0], 3)
        assert upscale_remote(s.http_url, low, token=token).buffers.ao.shape == (SIZE[1], SIZE[0])


def test_cli_writes_frames_and_prints_costs(server, tmp_path, capsys):  # noqa: F811
    out = tmp_path / "frames"
    code = main(["client", server.url, "--volume", VOLUME, "--mode", "buffers", "--frames", "3", "--size", "64x48",
                 "--orbit", "30,20,1.8,3", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["frame_0000.png", "frame_0001.png", "frame_0002.png",
                                                     "summary.json"]
    assert decode_image((out / "frame_0002.png").read_bytes()).shape == (48, 64, 3)
    summary = json.loads((out / "summary.json").read_text())
    buffers, full = summary["runs"]
    assert buffers["mode"] == "buffers" and full["mode"] == "full" and buffers["frames"] == full["frames"] == 3
    assert buffers["full_bytes_per_frame"] == full["bytes_per_frame"] > 0
    for line in ("buffers", "full", "sends"):
        assert line in printed
    assert f"{buffers['bytes_per_frame']:.0f}" in printed

    focus = tmp_path / "focus"
    assert main(["client", server.url, "--volume", VOLUME, "--mode", "focus", "--frames", "1", "--size", "64x48",
                 "--focus", "32,24,12", "--no-compare", "--out", str(focus)]) == 0
    assert json.loads((focus / "summary.json").read_text())["runs"][0]["mode"] == "focus"
    recon = tmp_path / "reconstruct"
    assert main(["client", server.url, "--volume", VOLUME, "--mode", "reconstruct", "--ao-rays", "1", "--frames",
                 "1", "--size", "50x30", "--no-compare", "--out", str(recon)]) == 0
    assert decode_image((recon / "frame_0000.png").read_bytes()).shape == (30, 50, 3)
    assert json.loads((recon / "summary.json").read_text())["runs"][0]["mode"] == "reconstruct"
    capsys.readouterr()

    bad = tmp_path / "bad"
    assert main(["client", server.url, "--volume", VOLUME, "--orbit", "30,20", "--out", str(bad)]) == 2
    assert "--orbit must be" in capsys.readouterr().err and not bad.exists()
    assert main(["client", server.url, "--volume", "nope", "--out", str(bad)]) == 2
    assert "4404" in capsys.readouterr().err and not bad.exists()


def test_cli_without_the_cuda_device_asked_for_ends_in_one_line(server):  # noqa: F811
    """``--device cuda`` where torch finds no CUDA device (or cuda:N past the last one on a GPU
    machine): exit 2 and one line naming the cause, no traceback."""
    device = f"cuda:{torch.cuda.device_count()}" if torch.cuda.is_available() else "cuda"
    done = subprocess.run([sys.executable, "-m", "isosr_cli.main", "client", server.url, "--volume", VOLUME,
                           "--mode", "buffers", "--frames", "1", "--size", "64x48", "--no-compare", "--device",
                           device], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"isosr client: error: no CUDA device: {device!r}"), done.stderr


def test_sessions_dealt_to_client_processes(server):  # noqa: F811
    """Sessions dealt to two client processes start their timed span together and all frame: the
    result adds every process's frames and sessions as one process's threads would."""
    result = sessions.run_sessions(server.url, VOLUME, 3, 1.0, "full", SIZE, {}, warmup_frames=1, processes=2)
    assert result["errors"] == [] and result["sessions"] == 3
    assert result["frames"] >= 3 and result["fps"] > 0
    assert result["fps"] == pytest.approx(3 * result["fps_per_session"], rel=0.5)
    assert result["methods"] == ["full, AO 0, spp 1"] and result["choices"] == {}


def test_auto_sessions_report_what_auto_expected_of_each_method(server):  # noqa: F811
    """An auto case's result says, per method the frames name, what the policy expected of it."""
    result = sessions.run_sessions(server.url, VOLUME, 2, 1.0, "auto", SIZE, {}, warmup_frames=1)
    assert result["errors"] == [] and set(result["choices"]) == set(result["methods"])
    for method, expected in result["choices"].items():
        assert expected["frames"] >= 1 and expected["budget_ms"] > 0, (method, expected)
        assert set(expected["sources"]) <= {"probe", "table", "prior"}
        assert (expected["psnr_db"] is None) == (expected["sources"] == ["prior"]), (method, expected)
    assert sum(e["frames"] for e in result["choices"].values()) == result["frames"]
    assert sum(e["fps"] for e in result["choices"].values()) == pytest.approx(result["fps"])
    assert sum(e["sessions"] for e in result["choices"].values()) == 2
    line = sessions.choices_line(result["choices"])
    assert all(f"{method}: " in line for method in result["methods"]) and " ms (" in line, line


def test_auto_choices_say_which_sessions_got_each_method_and_at_what_rate():
    """Per method: its frames a second over all sessions, and the sessions that made most of their frames with it
    at their own rates; a session without timed seconds counts toward no rate (no division by zero)."""
    def frames(*methods: str) -> list[FrameStats]:
        choice = AutoChoice(budget_ms=10.0, ms=5.0, psnr_db=30.0, fits=True, source="probe")
        return [FrameStats(i, i, "auto", m, False, 10.0, 100, 120, {}, choice=choice) for i, m in enumerate(methods)]
    learned, plain = "full, AO 1, spp 1, recon fp16", "full, AO 8, spp 1"
    stats = [frames(learned, learned, learned, plain), frames(plain, plain), frames(learned, plain, plain),
             frames(plain)]
    choices = sessions.auto_choices(stats, [2.0, 1.0, 1.0, 0.0])
    assert choices[learned]["frames"] == 4 and choices[plain]["frames"] == 6  # the untimed session too
    assert choices[learned]["fps"] == pytest.approx(3 / 2 + 1) and choices[plain]["fps"] == pytest.approx(1 / 2 + 2 + 2)
    assert choices[learned]["sessions"] == 1 and choices[learned]["session_fps_min"] == pytest.approx(2.0)
    assert choices[plain]["sessions"] == 2 and choices[plain]["session_fps_min"] == pytest.approx(2.0)
    assert choices[plain]["session_fps_mean"] == pytest.approx(2.5)
    assert "mostly in 1 sessions at 2.0-2.0/s" in sessions.choices_line(choices)
    assert sessions.auto_choices([frames(plain)], [0.0])[plain]["session_fps_min"] is None


def test_a_case_settles_untimed_before_its_timed_span(server):  # noqa: F811
    """settle_s: the sessions' frames of their first seconds (auto's probes, its first choices) are not timed: the
    timed frames start later in the session's sequence than without it."""
    first = {}
    for settle in (0.0, 1.0):
        job = (server.url, VOLUME, 1, 0.5, "full", SIZE, {}, None, 1, 100_000, None, settle, 0.0)
        stats, busy, errors = sessions.drive_sessions(job, range(1), threading.Barrier(1))
        assert errors == [] and stats[0] and busy[0] > 0
        first[settle] = stats[0][0].seq
    assert first[1.0] > first[0.0] + 1, first

def test_a_dragging_viewer_takes_frames_as_they_come_and_sees_its_last_camera(server):  # noqa: F811
    """drag: 12 cameras sent at 40 Hz without waiting for frames; the frames come in order, each with a camera
    sent (the server coalesces: no more frames than cameras, and the session's opening one), the last showing the
    last camera. Counts, not rates."""
    with connect(server.url, VOLUME, "full", SIZE, settings={"refine": False}, local_upscale=False) as view:
        view.latest()
        stats, seconds = drag(view, PATH, 12, 40.0)
        assert view.latest(timeout=5.0).stats is stats[-1]  # the newest frame, with every camera sent
    acks = [s.ack for s in stats]
    assert seconds > 0 and 1 <= len(stats) <= 12 + 1
    assert acks == sorted(acks) and [s.seq for s in stats] == sorted({s.seq for s in stats})
    with pytest.raises(ValueError, match="rate_hz must be a positive finite number"):
        drag(view, PATH, 1, 0.0)


def test_sessions_drag_when_asked_and_say_so(server, capsys):  # noqa: F811
    """run_sessions' drag_hz: the sessions drag (their frames timed over the span they sent cameras in); the
    benchmarks' --drag-hz takes a rate of 0 or more and names the client model of each row."""
    result = sessions.run_sessions(server.url, VOLUME, 2, 1.0, "full", SIZE, {}, warmup_frames=1, drag_hz=30.0)
    assert result["errors"] == [] and result["sessions"] == 2 and result["frames"] >= 2
    assert sessions.client_model(30.0) == "drag 30 Hz" and sessions.client_model(0.0) == "closed loop"
    parser = argparse.ArgumentParser()
    sessions.add_drag_argument(parser)
    assert parser.parse_args(["--drag-hz", "60"]).drag_hz == 60.0 and parser.parse_args([]).drag_hz == 0.0
    for bad in ("-1", "nan", "inf"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--drag-hz", bad])
        assert "a rate in Hz, 0 or more" in capsys.readouterr().err


@pytest.mark.slow
def test_load_16_sessions_30s(server):  # noqa: F811
    """16 concurrent view sessions (all modes) for 30 s: no errors, every session served, and the
    server's RSS grows by less than 64 MiB from after a warm-up round to the end (what a leak of
    one 64x48 frame per frame served would exceed several times over)."""
    modes = ("full", "network", "upscale", "buffers", "focus")
    # Warm-up: every mode's first frames (allocations, caches) before the baseline.
    for mode in modes:
        sessions.run_sessions(server.url, VOLUME, 1, 0.0, mode, SIZE, {}, warmup_frames=1)
    rss_before = server.rss()
    results = {}
    threads = []
    for mode in modes:
        n = {"full": 4, "network": 3, "upscale": 3, "buffers": 4, "focus": 2}[mode]  # 16 sessions
        t = threading.Thread(target=lambda m=mode, n=n: results.__setitem__(
            m, sessions.run_sessions(server.url, VOLUME, n, 30.0, m, SIZE, {},
                                         focus=(32.0, 24.0, 12.0) if m == "focus" else None, warmup_frames=1)))
        threads.append(t)
        t.start()
    for t in threads:
        t.join(300)
    rss_after = server.rss()
    frames = sum(r.get("frames", 0) for r in results.values())
    rows = [dict(bench_server.case_row(m, 0, r), rss_growth_mib=(rss_after - rss_before) / 2**20)
            for m, r in results.items()]
    for r in rows:
        print(f"load {r['mode']:<9} x{r['sessions']}: {r.get('frames', 0)} frames, {r.get('fps', 0):.1f} fps, "
              f"p50 {r.get('latency_p50_ms', 0):.0f} ms, p99 {r.get('latency_p99_ms', 0):.0f} ms")
    print(f"load: {frames} frames in 30 s, server RSS {rss_before / 2**20:.0f} -> {rss_after / 2**20:.0f} MiB")
    if os.environ.get("ISOSR_WRITE_LOAD_RESULT"):
        write_result("load_client", "cpu", rows, RESULTS_DIR)
    assert sorted(results) == sorted(modes) and sum(r["sessions"] for r in results.values()) == 16
    assert all(r["errors"] == [] for r in results.values()), {m: r["errors"] for m, r in results.items()}
    assert all(r["frames"] >= r["sessions"] for r in results.values())
    assert rss_after - rss_before < 64 * 2**20


def view_frames_sent(url: str) -> int:
    """The server's count of view frames sent (``GET /metrics``)."""
    with urllib.request.urlopen(url + "/metrics", timeout=30) as r:
        lines = r.read().decode().splitlines()
    return round(sum(float(line.split()[-1]) for line in lines if line.startswith('isosr_frames_total{kind="view"')))


# The slow client's frames: about 8 times the fast client's render and encode time on the CPU.
SLOW_SETTINGS = SettingsUpdate(mode="full", width=512, height=384, ao_rays=4, encoding="png", refine=False)


def stalled_view(port: int, seconds: float, read_every_s: float | None, stop: threading.Event | None = None):
    """A raw view session (`SLOW_SETTINGS` frames) that sends a camera every 50 ms for
    ``seconds`` (or until ``stop``) and reads and acknowledges a frame every ``read_every_s``
    (None: never reads, never acknowledges); loopback socket buffers (megabytes: hundreds of
    frames fit before a send blocks). Returns the frames read, the open connection (for the
    caller to close) and the newest camera's seq."""
    # max_queue=1: the client takes no frame off the socket before it reads one. close_timeout: unread
    # frames may delay the server's close frame, and the test need not wait for it.
    ws = ws_connect(f"ws://127.0.0.1:{port}/v1/view", max_size=2**28, compression=None, max_queue=1,
                    open_timeout=30, close_timeout=1, proxy=None).__enter__()
    ws.send(encode(OpenMsg(VOLUME, SLOW_SETTINGS)))
    seq, last_read, end, frames = 0, time.monotonic(), time.monotonic() + seconds, []
    while time.monotonic() < end and not (stop and stop.is_set()):
        seq += 1
        ws.send(encode(CameraMsg(**PATH.camera(seq), seq=seq)))
        if read_every_s is not None and time.monotonic() - last_read >= read_every_s:
            msg = parse(ws.recv(timeout=30), CLIENT_LIMITS, SERVER_VIEW_MESSAGES)
            if isinstance(msg, FrameMsg):
                ws.send(encode(ReceivedMsg(msg.seq)))
                frames.append(msg)
            last_read = time.monotonic()
        time.sleep(0.05)
    return frames, ws, seq


def test_a_slow_client_costs_one_frame_per_frame_it_reads(server):  # noqa: F811
    """A client that sends cameras at 20/s but reads (and acknowledges) one frame a second, beside
    a fast closed-loop client: the server makes the slow one no more frames than it read plus its
    credit (flow control: without it the server renders for the slow one until megabytes of
    socket buffers fill), the fast one keeps getting frames, and the server's memory stays put.
    Counts, not rates: how fast either goes is the benchmarks' (bench_server)."""
    credit = Limits().max_unacked_frames
    stop = threading.Event()
    slow_frames = []

    def slow() -> None:
        frames, ws, _ = stalled_view(server.port, 60.0, 1.0, stop)
        ws.close()
        slow_frames.extend(frames)

    rss_before, sent_before = server.rss(), view_frames_sent(server.url)
    thread = threading.Thread(target=slow, daemon=True)
    thread.start()
    time.sleep(2.0)  # the slow client's first frames wait unread
    with connect(server.url, VOLUME, "upscale", SIZE, settings={"refine": False}, local_upscale=False) as view:
        fast, _ = drive(view, PATH, 30, rgb=False)
    time.sleep(3.0)  # a few more of the slow one's reads, one a second
    stop.set()
    thread.join(60)
    made = view_frames_sent(server.url) - sent_before
    print(f"{len(fast)} fast frames, {len(slow_frames)} slow frames read, {made} frames sent in all; "
          f"server RSS {rss_before / 2**20:.0f} -> {server.rss() / 2**20:.0f} MiB")
    assert len(fast) == 30 and len(slow_frames) >= 3
    assert slow_frames[-1].ack > slow_frames[0].ack  # it sees the camera move
    assert slow_frames[-1].seq < len(slow_frames) + credit, "the slow client was made frames it did not read"
    assert made <= len(fast) + 2 + len(slow_frames) + credit  # the fast one's warm-up: drive's first frames
    assert server.rss() - rss_before < 64 * 2**20


def test_stalled_client_gets_max_unacked_frames_then_the_newest(server):  # noqa: F811
    """A client that sends cameras for 3 s and never reads or acknowledges: the server makes
    max_unacked_frames (2) frames for it, however many cameras come (frame seqs count every
    frame made: the one after the acknowledgment is number 2), and its memory stays put; once
    the client reads and acknowledges them, the next frame shows its newest camera."""
    credit = Limits().max_unacked_frames
    rss_before, sent_before = server.rss(), view_frames_sent(server.url)
    _, ws, newest = stalled_view(server.port, 3.0, None)
    with ws:
        assert view_frames_sent(server.url) - sent_before == credit  # 60 cameras came
        # The bound of the load test: a 512x384 AO frame's first allocations move RSS by 10-30 MiB.
        assert server.rss() - rss_before < 64 * 2**20
        frames = [parse(ws.recv(timeout=30), CLIENT_LIMITS, SERVER_VIEW_MESSAGES) for _ in range(credit + 1)]
        assert isinstance(frames[0], ReadyMsg) and [f.seq for f in frames[1:]] == list(range(credit))
        ws.send(encode(ReceivedMsg(credit - 1)))
        nxt = parse(ws.recv(timeout=30), CLIENT_LIMITS, SERVER_VIEW_MESSAGES)
        assert (nxt.seq, nxt.ack) == (credit, newest)


def test_bench_server_smoke(server, tmp_path):  # noqa: F811
    bench_server.main(["--smoke", "--url", server.url, "--out", str(tmp_path)])
    record = json.loads((tmp_path / "bench_server_smoke_cpu.json").read_text())
    cases = [r for r in record["rows"] if "mode" in r]
    assert {(r["mode"], r["ao"]) for r in cases} == set(bench_server.CASES)
    assert all(r["methods"] for r in cases)
    assert all(r["errors"] == 0 and r["fps"] > 0 and r["bytes_per_frame"] > 0 for r in cases)
    assert all(r["latency_p99_ms"] >= r["latency_p50_ms"] > 0 for r in cases)
    sr = next(r for r in cases if r["mode"] == "network" and r["sessions"] == 1)
    assert sr["network_ms"] > 0 and sr["render_ms"] > 0
    study, auto = record["rows"][-2:]
    assert auto["study"] == "auto_quality" and 10 < auto["auto_psnr_db"] < 100 and auto["fixed"]
    assert study["study"] == "matched_quality" and 10 < study["buffers_psnr_db"] < 100
    assert [j["quality"] for j in study["jpeg"]] == [10, 50, 90]


def test_the_server_makes_the_volumes_mesh_and_refuses_a_large_one(server, library, tmp_path):  # noqa: F811
    """``GET /v1/volumes/NAME/mesh``: the library's mesh of that iso as a file; an iso outside the
    range is a 422 naming it."""
    meshio = pytest.importorskip("meshio", reason="meshes need meshio (the mesh extra)")
    from isosr_client.view import http_call
    from isosr_render.mesh import extract_mesh

    renderer, iso = library
    volume = renderer.volume
    lo, hi = volume.value_range
    reply, data = http_call(server.url, f"/v1/volumes/{VOLUME}/mesh?iso={lo + iso * (hi - lo)}&format=obj")
    assert "attachment" in reply.get("content-disposition", "")
    (tmp_path / "m.obj").write_bytes(data)
    expected = extract_mesh(volume, volume.normalized_iso(lo + iso * (hi - lo)))
    assert len(meshio.read(tmp_path / "m.obj").cells[0].data) == len(expected.faces) > 0
    with pytest.raises(ServerError, match="iso") as e:
        http_call(server.url, f"/v1/volumes/{VOLUME}/mesh?iso={hi + (hi - lo)}")
    assert e.value.code == 422
