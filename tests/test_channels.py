"""The channel view (isosr_server.channels): false colors and legends, hard inputs, that each
mode computes only the buffers the asked channel needs, and the view sessions that ask for it.
``ISOSR_TEST_DEVICE=cuda`` runs the renderer, network and server parts on the GPU."""

from __future__ import annotations

import math

import pytest
import torch

from isosr_net.methods import FrameMethod, Networks, make_runner
from isosr_render import FrameBuffers, Renderer, orbit, parse_procedural
from isosr_server import channels
from isosr_server import views
from isosr_server.protocol import CHANNELS, ProtocolError, ViewSettings
from isosr_server.views import ViewContext

from conftest import DEVICE
from net_fixtures import tiny_model_dir

H, W = 6, 8


def frame(mask=1.0, depth=1.0, flow=(0.0, 0.0), ao=0.5) -> FrameBuffers:
    """A flat frame: every pixel the same values."""
    normal = torch.zeros(H, W, 3)
    normal[..., 2] = 1.0
    return FrameBuffers(mask=torch.full((H, W), float(mask)), normal=normal, depth=torch.full((H, W), float(depth)),
                        ao=torch.full((H, W), float(ao)), flow=torch.tensor(flow).expand(H, W, 2).clone())


@pytest.mark.parametrize("channel", CHANNELS[1:])
def test_false_colors_are_bounded_with_a_legend(channel):
    rgb, legend = channels.false_color(frame(), channel)
    assert rgb.shape == (H, W, 3) and torch.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1
    assert legend["channel"] == channel and math.isfinite(legend["lo"]) and legend["lo"] <= legend["hi"]


def test_false_colors_follow_the_colormaps():
    f = frame(depth=2.0, ao=0.25)
    f.mask[0, 0] = 0.0
    f.depth[1, 1] = 3.0
    f.flow[2, 2] = torch.tensor([3.0, 0.0])  # right: hue 0, red
    f.flow[3, 3] = torch.tensor([0.0, 1.5])  # down, half length: hue 1/4, value 1/2
    normal, _ = channels.false_color(f, "normal")
    assert torch.allclose(normal[1, 1], torch.tensor([0.5, 0.5, 1.0]))
    assert torch.allclose(normal[0, 0], torch.full((3,), channels.NO_SURFACE)), "uncovered pixels are gray"
    depth, legend = channels.false_color(f, "depth")
    assert (legend["lo"], legend["hi"]) == (2.0, 3.0) and legend["stops"][0] == list(channels.DEPTH_STOPS[0])
    assert torch.allclose(depth[1, 1], torch.tensor(channels.DEPTH_STOPS[-1]))
    assert torch.allclose(depth[2, 2], torch.tensor(channels.DEPTH_STOPS[0]))
    ao, _ = channels.false_color(f, "ao")
    assert torch.allclose(ao[1, 1], torch.full((3,), 0.25))
    flow, legend = channels.false_color(f, "flow")
    assert legend["hi"] == 3.0
    assert torch.allclose(flow[2, 2], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(flow[3, 3], torch.tensor([0.25, 0.5, 0.0]))
    assert torch.equal(flow[4, 4], torch.zeros(3)), "still pixels are black"


@pytest.mark.parametrize("case", ["flat", "empty", "huge", "nonfinite", "no_flow"])
def test_hard_buffers_stay_finite(case):
    f = {"flat": frame(depth=0.7), "empty": frame(mask=0.0, depth=0.0), "huge": frame(depth=1e30, flow=(1e30, -1e30)),
         "nonfinite": frame(depth=math.inf, flow=(math.nan, math.inf)), "no_flow": frame()}[case]
    if case == "no_flow":
        f.flow = None
    for channel in CHANNELS[1:]:
        rgb, legend = channels.false_color(f, channel)
        assert torch.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1, (case, channel)
        assert math.isfinite(legend["lo"]) and math.isfinite(legend["hi"]), (case, channel, legend)


CTX = ViewContext(factor=4, precision="fp32")


def test_settings_a_channel_cannot_show_are_refused():
    with pytest.raises(ProtocolError, match=r"full mode makes no AO to show \(give ao_rays > 0\)"):
        views.check(ViewSettings(mode="full", ao_rays=0, channel="ao"), CTX)
    with pytest.raises(ProtocolError, match="upscale mode makes no AO"):
        views.check(ViewSettings(mode="upscale", channel="ao"), CTX)
    with pytest.raises(ProtocolError, match="no channel view"):
        views.check(ViewSettings(mode="buffers", channel="depth"), CTX)
    views.check(ViewSettings(mode="network", ao_rays=0, channel="ao"), CTX)  # the network's AO
    views.check(ViewSettings(mode="auto", channel="ao"), CTX)  # chosen per frame


def test_a_mode_the_server_does_not_offer_is_refused_naming_those_it_does():
    with pytest.raises(ProtocolError, match=r"unknown mode 'sr'; this server offers auto, full, atrous, .*focus"):
        views.check(ViewSettings(mode="sr"), CTX)


def test_every_mode_describes_itself_from_the_registry():
    """Each mode's label and the settings it reads with bounds a method accepts at both ends."""
    infos = {m.name: m for m in views.mode_infos(CTX)}
    assert list(infos) == list(views.VIEWS) and all(m.label for m in infos.values())
    assert infos["upscale"].options[0].choices and infos["focus"].focus and not infos["buffers"].shaded
    for name, info in infos.items():
        defaults = {o.name: o.default for o in info.options}
        for option in (o for o in info.options if o.low is not None):
            for value in (option.low, option.high, option.default):
                views.check(ViewSettings(mode=name, **(defaults | {option.name: value})), CTX)


@pytest.fixture(scope="module")
def renderer():
    return Renderer(parse_procedural("proc:torus@24"), DEVICE)


CAM, PREV = orbit(30, 20, 1.6), orbit(28, 20, 1.6)


@pytest.mark.parametrize("channel, ao_rays, present", [
    ("mask", 0, ["mask"]), ("normal", 0, ["mask", "normal"]), ("depth", 64, ["mask", "depth"]),
    ("ao", 2, ["mask", "ao"]), ("flow", 0, ["mask", "flow"])])
def test_full_mode_renders_only_the_channel(renderer, channel, ao_rays, present):
    runner = make_runner(FrameMethod.of("full", ao_rays=ao_rays), renderer, 0.5, 32, 24, keep=(channel,), shade=False)
    buffers = runner.frame(CAM, PREV).buffers
    assert buffers.present() == present, "no color, no AO rays for a depth view"
    assert buffers.mask.shape == (24, 32) and buffers.mask.max() == 1.0


def test_lowres_modes_show_output_resolution_buffers(renderer, tmp_path_factory):
    tiny = str(tiny_model_dir(tmp_path_factory))  # an x2 model
    network = make_runner(FrameMethod.of("network", factor=2, model=tiny), renderer, 0.5, 32, 24, keep=("flow",),
                          shade=False)
    network.frame(PREV)
    high = network.frame(CAM, PREV)
    assert high.buffers.flow.shape == (24, 32, 2) and high.buffers.ao.shape == (24, 32)
    assert high.buffers.flow.abs().max() > 0, "a moved camera gives flow"
    assert high.buffers.color is None and set(high.times) == {"render", "network"}
    classic = make_runner(FrameMethod.of("upscale", factor=4), renderer, 0.5, 32, 24, keep=("depth",), shade=False)
    low = classic.frame(CAM).buffers
    assert low.depth.shape == (24, 32) and low.ao is None and low.flow is None, "the baseline has no AO"


def test_reconstruct_mode_shows_the_reconstruction(renderer):
    """AO is the network's output, flow its full-res input flow; a channel view advances the
    recurrent state as shaded frames do."""
    method = FrameMethod.of("reconstruct", ao_rays=1)
    shaded = make_runner(method, renderer, 0.5, 32, 24, networks=Networks.eager())
    expected = [shaded.frame(PREV), shaded.frame(CAM, PREV)]
    viewed = make_runner(method, renderer, 0.5, 32, 24, networks=Networks.eager(), keep=("flow",), shade=False)
    got = [viewed.frame(PREV), viewed.frame(CAM, PREV)]
    for g, want in zip(got, expected):
        assert torch.equal(g.buffers.ao, want.buffers.ao) and g.buffers.color is None
    full = make_runner(FrameMethod.of("full"), renderer, 0.5, 32, 24, keep=("flow",), shade=False).frame(CAM, PREV)
    assert torch.equal(got[1].buffers.flow, full.buffers.flow) and got[1].buffers.flow.abs().max() > 0
    assert got[0].buffers.flow is None


# ---- through the server ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    from server_fixtures import running_server, server_settings

    with running_server(server_settings(volumes=tmp_path_factory.mktemp("no_volumes"))) as s:
        yield s


def test_server_serves_the_page_offline(srv):
    status, headers, body = srv.request("GET", "/")
    assert status == 200 and b'<script type="module" src="static/viewer.js">' in body
    assert "default-src 'self'" in headers["content-security-policy"]
    for name in ("viewer.js", "session.js", "msgpack.js", "legend.js"):
        status, headers, body = srv.request("GET", f"/static/{name}")
        assert status == 200 and "javascript" in headers["content-type"]
        assert b"http://" not in body and b"https://" not in body, f"{name} fetches from elsewhere"
    assert srv.request("GET", "/static/../app.py")[0] == 404


def test_view_session_channels_match_the_library(srv):
    from server_fixtures import frame, recv

    from isosr_render.image_codec import decode_image
    from isosr_render.images import to_uint8
    from isosr_server import protocol as P
    from isosr_server.sessions import to_camera

    volume, w, h = "proc:torus@24", 64, 48
    cam0 = P.CameraMsg(yaw=30.0, pitch=20.0, distance=1.6)
    with srv.view() as ws:
        ws.send(P.encode(P.OpenMsg(volume, P.SettingsUpdate(width=w, height=h, mode="network", channel="depth",
                                                            encoding="png", refine=False), cam0)))
        ready = recv(ws)
        assert isinstance(ready, P.ReadyMsg) and ready.settings.channel == "depth"
        first = frame(ws)
        assert first.legend.channel == "depth" and 0 < first.legend.lo < first.legend.hi
        renderer = Renderer(parse_procedural(volume), DEVICE)
        local = make_runner(FrameMethod.of("network", factor=4), renderer, ready.volume.iso_normalized, w, h,
                            networks=Networks.eager(), keep=("depth",), shade=False)
        expected, legend = channels.false_color(local.frame(to_camera(cam0)).buffers, "depth")
        got = decode_image(first.image).astype(int)
        # On a GPU the server's network runs channels-last: other kernels, other rounding.
        tolerance, levels = (1e-6, 1) if DEVICE == "cpu" else (1e-3, 3)
        assert abs(legend["lo"] - first.legend.lo) < tolerance
        assert abs(got - to_uint8(expected).astype(int)).max() <= levels

        ws.send(P.encode(P.SettingsMsg(P.SettingsUpdate(channel="flow", mode="full"), seq=1)))
        still = frame(ws)
        assert (still.ack, still.mode, still.legend.channel, still.legend.hi) == (1, "full", "flow", 0.0)
        ws.send(P.encode(P.CameraMsg(yaw=34.0, pitch=20.0, distance=1.6, seq=2)))
        moved = frame(ws)
        assert moved.ack == 2 and moved.legend.hi > 0, "a moved camera has flow"

        ws.send(P.encode(P.SettingsMsg(P.SettingsUpdate(channel="ao", ao_rays=0))))
        while True:
            msg = recv(ws)
            if isinstance(msg, P.ErrorMsg):
                break
        assert msg.code == P.CLOSE_BAD_MESSAGE and "ao_rays > 0" in msg.reason
