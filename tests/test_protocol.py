"""The wire protocol: round trips of every message, validation with reasons that name the field,
limits, versions, fuzzing. (The array and buffers codecs: test_codecs.py.)"""

from __future__ import annotations

import warnings
import zlib

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from isosr_render.conventions import MATERIAL_RGB
from isosr_server import protocol as P
from isosr_server.codecs.arrays import encode_array

LIMITS = P.Limits()
MODES = [P.ModeInfo("auto", "auto (the server chooses)", []),
         P.ModeInfo("full", "full resolution", [P.OptionInfo("ao_rays", 0, 256, default=0)]),
         P.ModeInfo("upscale", "classic upscaling", [P.OptionInfo("interpolation", default="bilinear",
                                                                  choices=["nearest", "bilinear"])], low_res=True)]
raw = msgspec.msgpack.encode  # hostile or outdated wire maps, written as they are


def roundtrip(msg: P.Message, limits: P.Limits = LIMITS) -> P.Message:
    return P.parse(P.encode(msg), limits, (type(msg),))


def wire(msg: P.Message) -> dict:
    """A message as the plain map that travels."""
    return msgspec.msgpack.decode(P.encode(msg))


CAM = P.CameraMsg(yaw=30.0, pitch=20.0, distance=1.8, seq=3)
VOLUME = P.VolumeSummary("proc:sphere", (64, 64, 64), (-1.0, 1.0), 0.0, [1, 2, 3], 3, 0.5)
FLAT = np.ones((6, 8), np.float32)


def buffers_frame() -> P.FrameMsg:
    buffers = P.ViewBuffers(encode_array(FLAT.astype(np.uint8), True), depth=encode_array(FLAT.astype(np.uint16)),
                            depth_range=(1.0, 2.0))
    return P.FrameMsg(seq=4, ack=3, mode="buffers", method="buffers", width=32, height=24, encoding="buffers",
                      times={"render": 1.0, "encode": 0.5, "total": 2.0}, nbytes=buffers.nbytes, buffers=buffers,
                      prev_seq=3)


def test_messages_round_trip():
    legend = P.Legend("depth", 1.0, 2.0, "world units", "stops", [(0.0, 0.5, 1.0), (1.0, 1.0, 0.0)])
    for msg in (CAM, P.CameraMsg(eye=(0.0, 0.5, 2.0), fov_y=30.0), P.CameraMsg(eye=(1.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)),
                P.OpenMsg("proc:sphere", P.SettingsUpdate(mode="full", width=64, height=48), CAM, 0.2, True),
                P.OpenMsg("bonsai"), P.IsoMsg(77.0, seq=9),
                P.SettingsMsg(P.SettingsUpdate(ao_rays=8, encoding="png", interpolation="bicubic", spp=4), seq=1),
                P.FocusMsg("circle", center=(32.0, 24.0), radius=10.0), P.FocusMsg("box", box=(1.0, 2.0, 30.0, 40.0)),
                P.FocusMsg("none"), P.ErrorMsg(1007, "bad"), P.ReceivedMsg(0), P.ReceivedMsg(P.MAX_SEQ),
                P.PickMsg(3.5, 4.5, id=2), P.PickedMsg(3.5, 4.5, 2, False),
                P.PickedMsg(3.5, 4.5, 2, True, (0.1, -0.2, 0.3), (4, 5, 6), (2.0, 5.0, 9.0), 300.0, 1.6),
                P.PickedMsg(3.5, 4.5, 3, True, (0.1, -0.2, 0.3), (4, 5, 6), (2.0, 5.0, 9.0), 0.4, 1.6, surface=3),
                P.ReadyMsg("abc", VOLUME, P.ViewSettings(mode="network"), 4, 8, LIMITS, MODES),
                P.FrameMsg(seq=0, ack=-1, mode="full", method="full, AO 2, spp 1", width=64, height=48,
                           encoding="png", times={"render": 1.0, "total": 2.0}, nbytes=4, image=b"\x89PNG"),
                P.FrameMsg(seq=1, ack=0, mode="auto", method="network x4", width=64, height=48, encoding="jpeg",
                           times={"filter": 0.1}, nbytes=2, image=b"\xff\xd8", refined=True, legend=legend),
                buffers_frame()):
        assert roundtrip(msg) == msg


def test_wire_names_are_the_v3_vocabulary():
    ready = wire(P.ReadyMsg("abc", VOLUME, P.ViewSettings(), 4, 8, LIMITS, MODES))
    assert ready["type"] == "ready" and ready["version"] == 12 and ready["max_recon_ao_rays"] == 8
    assert ready["settings"]["mode"] == "auto" and ready["settings"]["interpolation"] == "bilinear"
    assert {"ao_rays", "refine_ao_rays", "spp", "ao_radius"} <= set(ready["settings"])
    assert ready["settings"]["ao_radius"] == P.AO_RADIUS == 0.05
    assert {"max_ao_rays", "open_timeout_s", "max_sessions_per_client", "body_timeout_s", "max_connections",
            "max_connections_per_client", "max_upscale_bytes"} <= set(ready["limits"])
    frame = wire(buffers_frame())
    assert frame["bytes"] == len(frame["buffers"]["depth"]["data"]) + len(frame["buffers"]["mask"]["data"])
    assert wire(P.SettingsMsg(P.SettingsUpdate(ao_rays=2)))["settings"] == {"ao_rays": 2}  # only what changes
    assert ready["modes"][1] == {"name": "full", "label": "full resolution", "shaded": True, "low_res": False,
                                 "focus": False, "options": [{"name": "ao_rays", "low": 0, "high": 256, "default": 0,
                                                              "choices": None}]}


@pytest.mark.parametrize("clip, match", [
    ({"planes": [{"point": [0, 0, 0], "normal": [0, 0, 1]}] * 7}, r"length <= 6 - at `\$.clip.planes`"),
    ({"planes": [{"point": [0, 0, 0], "normal": [0, 0, 0]}]}, r"clip.planes\[0\].normal must be a nonzero vector"),
    ({"planes": [{"point": [0, float("nan"), 0], "normal": [0, 0, 1]}]}, r"at `\$.clip.planes\[0\].point\[1\]`"),
    ({"box": [[0, 0, 0], [1, -1, 1]]}, r"clip.box: lo must not exceed hi"),
    ({"cap": "inside"}, r"at `\$.clip.cap`"),
])
def test_bad_clip_settings_are_refused_naming_the_field(clip, match):
    with pytest.raises(P.ProtocolError, match=match):
        P.ViewSettings().updated({"clip": clip}, LIMITS)


def test_a_settings_message_refused_for_its_clip_or_coloring_is_a_setting_refused_with_its_seq():
    """Clip and coloring are `NOTICED_SETTINGS` (a live view answers with a notice, not an end); other
    bad settings, and a bad clip in another message, stay plain protocol errors."""
    def parsed(message: dict, expected=P.CLIENT_VIEW_MESSAGES):
        with pytest.raises(P.ProtocolError) as e:
            P.parse(msgspec.msgpack.encode(message), LIMITS, expected)
        return e.value

    zero = {"planes": [{"point": [0, 0, 0], "normal": [0, 0, 0]}]}
    refused = parsed({"type": "settings", "settings": {"clip": zero}, "seq": 7})
    assert isinstance(refused, P.SettingRefused) and refused.seq == 7 and "nonzero vector" in refused.reason
    colormap = parsed({"type": "settings", "settings": {"coloring": {"by": "x", "colormap": "jet"}}, "seq": -1})
    assert isinstance(colormap, P.SettingRefused) and colormap.seq is None  # no valid seq to acknowledge
    assert type(parsed({"type": "settings", "settings": {"width": 0}, "seq": 1})) is P.ProtocolError
    assert type(parsed({"type": "camera", "yaw": "x", "seq": 1})) is P.ProtocolError
    assert isinstance(parsed({"type": "open", "volume": "v", "settings": {"clip": zero}}, (P.OpenMsg,)),
                      P.SettingRefused)  # a ProtocolError still: a bad open ends the session
    with pytest.raises(P.ProtocolError, match=r"clip: Expected `array` of length <= 6 in `planes`"):
        P.clip_query('{"planes": [' + ",".join(['{"point": [0, 0, 0], "normal": [0, 0, 1]}'] * 7) + "]}")
    with pytest.raises(P.ProtocolError, match="clip: not JSON"):
        P.clip_query("{planes")


def test_clip_settings_are_the_renderers_clip():
    st = P.ViewSettings().updated({"clip": {"planes": [{"point": [0, 0, 0.1], "normal": [0, 0, -2]}],
                                            "box": [[-1, -1, -1], [1, 1, 1]], "cap": "above"}}, LIMITS)
    clip = st.clip.clip()
    assert clip.planes == (((0.0, 0.0, 0.1), (0.0, 0.0, -1.0)),) and clip.box[1] == (1.0, 1.0, 1.0) and clip.capped
    msg = P.SettingsMsg(P.SettingsUpdate(clip=st.clip))
    assert roundtrip(msg) == msg and not P.ViewSettings().clip.clip().active


@pytest.mark.parametrize("surfaces, match", [
    ([{"iso": 0.1 * i, "color": [1, 0, 0]} for i in range(5)], r"length <= 4 - at `\$.surfaces`"),
    ([{"iso": 0.1, "color": [1, float("nan"), 0]}], r"at `\$.surfaces\[0\].color\[1\]`"),
    ([{"iso": 0.1, "color": [1, 2, 0]}], r"<= 1.0 - at `\$.surfaces\[0\].color\[1\]`"),
    ([{"iso": float("inf"), "color": [1, 0, 0]}], r"at `\$.surfaces\[0\].iso`"),
    ([{"iso": 0.1, "color": [1, 0]}], r"length 3, got 2 - at `\$.surfaces\[0\].color`"),
    ([{"iso": 0.1, "opacity": -0.1}], r">= 0.0 - at `\$.surfaces\[0\].opacity`"),
    ([{"iso": 0.1, "opacity": float("nan")}], r"at `\$.surfaces\[0\].opacity`"),
])
def test_bad_surfaces_are_refused_naming_the_field(surfaces, match):
    with pytest.raises(P.ProtocolError, match=match):
        P.ViewSettings().updated({"surfaces": surfaces}, LIMITS)


def test_surfaces_round_trip_and_are_the_renderers():
    st = P.ViewSettings().updated({"surfaces": [{"iso": 300.0, "color": [0.9, 0.8, 0.7]},
                                                {"iso": 100.0, "color": [1, 1, 1], "opacity": 0.3}]}, LIMITS)
    msg = P.SettingsMsg(P.SettingsUpdate(surfaces=st.surfaces))
    assert roundtrip(msg) == msg and wire(msg)["settings"]["surfaces"][1] == {"iso": 100.0, "color": [1.0, 1.0, 1.0],
                                                                              "opacity": 0.3}
    surfaces = P.surfaces_of(st.surfaces, lambda v: v / 1000.0)
    assert [(s.iso, s.color, s.opacity) for s in surfaces.items] == [(0.3, (0.9, 0.8, 0.7), 1.0),
                                                                      (0.1, (1.0, 1.0, 1.0), 0.3)]
    assert surfaces.layers == 2
    assert P.surfaces_of((), float) is None and P.ViewSettings().surfaces == ()
    assert P.SurfaceSettings(0.5).color == MATERIAL_RGB
    with pytest.raises(P.ProtocolError, match=r"settings.surfaces: the iso-values must differ"):
        P.surfaces_of(st.surfaces, lambda v: 0.5)
    with pytest.raises(P.ProtocolError, match=r"settings.surfaces: .* not with settings.coloring"):
        st.updated({"coloring": {"by": "gradient"}}, LIMITS)


def test_volume_levels_and_device_memory_round_trip():
    """Issue 22's wire: a multiscale volume's levels in ``ready``, and frames carrying the volume's
    device memory and paging (sent when it changed)."""
    levels = [P.LevelSummary("s0", (64, 64, 64), 524288), P.LevelSummary("s1", (32, 32, 32), 65536)]
    ready = P.ReadyMsg("abc", msgspec.structs.replace(VOLUME, level="s1", levels=levels), P.ViewSettings(), 4, 8, LIMITS, MODES)
    assert roundtrip(ready) == ready and wire(ready)["volume"]["levels"][1] == {"level": "s1", "shape": [32, 32, 32],
                                                                               "bytes": 65536}
    memory = P.VolumeMemory("sparse", "uint16", 2**33, 2**30, 2**31, 2**31, 4096, 300, 280, 2, 320, 2**28, 4.25)
    frame = msgspec.structs.replace(buffers_frame(), device=memory)
    assert roundtrip(frame) == frame and wire(frame)["device"]["last_page_in_s"] == 4.25
    assert "device" in wire(frame) and wire(buffers_frame())["device"] is None
    with pytest.raises(P.ProtocolError, match=r"Invalid enum value 'paged' - at `\$.device.mode`"):
        P.parse(raw(wire(frame) | {"device": wire(frame)["device"] | {"mode": "paged"}}), LIMITS, P.SERVER_VIEW_MESSAGES)


def test_upscale_messages_round_trip_arrays_exactly():
    rng = np.random.default_rng(0)
    mask = (rng.random((6, 8)) > 0.5).astype(np.float32)
    normal = rng.standard_normal((6, 8, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    req = P.UpscaleRequest(mask, normal.astype(np.float16), rng.random((6, 8)).astype(np.float32),
                           rng.standard_normal((6, 8, 2)).astype(np.float32), output="png", session="s-1")
    back = roundtrip(req)
    for name in P.LOWRES_INPUTS:
        np.testing.assert_array_equal(getattr(back, name), getattr(req, name))
        assert getattr(back, name).dtype == getattr(req, name).dtype
    assert (back.output, back.session, back.flow.shape) == ("png", "s-1", (6, 8, 2))
    out = P.HighresBuffers(mask, np.zeros((6, 8, 3), np.float32), mask * 2, mask)
    resp = roundtrip(P.UpscaleResponse(seq=0, width=8, height=6, output="buffers", times={"total": 1.0}, nbytes=123,
                                       buffers=out))
    for name in P.HIGHRES_OUTPUTS:
        np.testing.assert_array_equal(getattr(resp.buffers, name), getattr(out, name))
    image = roundtrip(P.UpscaleResponse(seq=1, width=8, height=6, output="png", times={}, nbytes=3, image=b"PNG"))
    assert image.image == b"PNG" and image.buffers is None


V = P.PROTOCOL_VERSION


@pytest.mark.parametrize("message, words", [
    ({"type": "camera"}, "give eye"),
    ({"type": "camera", "eye": [0, 0, 1], "yaw": 3}, "not both"),
    ({"type": "camera", "eye": [0, 0, 0]}, "coincide"),
    ({"type": "camera", "eye": [0, 1, 0], "up": [0, 2, 0]}, "parallel"),
    ({"type": "camera", "eye": [0, 1, 0]}, "parallel"),
    ({"type": "camera", "eye": [0, 0, 1], "up": [0, 0, 0]}, "zero"),
    ({"type": "camera", "yaw": 0, "pitch": 0, "distance": 1, "up": [1, 0, 0]}, "orbit"),
    ({"type": "camera", "eye": [0, 0, float("nan")]}, r"Expected `float` >= -1000000000.0 - at `\$.eye\[2\]`"),
    ({"type": "camera", "eye": [0, 0]}, r"length 3, got 2 - at `\$.eye`"),
    ({"type": "camera", "yaw": 0, "pitch": 90, "distance": 1}, r"<= 89.9 - at `\$.pitch`"),
    ({"type": "camera", "yaw": 0, "pitch": 0, "distance": 1, "zoom": 2}, "unknown field `zoom`"),
    ({"type": "camera", "yaw": True, "pitch": 0, "distance": 1}, r"got `bool` - at `\$.yaw`"),
    ({"type": "iso", "value": float("inf")}, r"<= 1000000000.0 - at `\$.value`"),
    ({"type": "iso", "value": float("-inf")}, r"at `\$.value`"),
    ({"type": "iso", "value": "7"}, r"Expected `float`, got `str` - at `\$.value`"),
    ({"type": "iso", "value": 1e300}, r"at `\$.value`"),
    ({"type": "iso", "value": 1.0, "seq": 2**64 - 1}, r"at `\$.seq`"),
    ({"type": "settings", "settings": {"mode": "SR!"}}, r"Expected `str` matching regex .* - at `\$.settings.mode`"),
    ({"type": "settings", "settings": {"mode": "bi linear"}}, r"at `\$.settings.mode`"),
    ({"type": "settings", "settings": {"width": 0}}, r"Expected `int` >= 1 - at `\$.settings.width`"),
    ({"type": "settings", "settings": {"width": None}}, r"got `None` - at `\$.settings.width`"),
    ({"type": "settings", "settings": {"ao_rays": -1}}, r">= 0 - at `\$.settings.ao_rays`"),
    ({"type": "settings", "settings": {"ao_rays": 10**6}}, r"<= 256 \(max_ao_rays\) - at `\$.settings.ao_rays`"),
    ({"type": "settings", "settings": {"refine_ao_rays": 257}}, r"max_ao_rays\) - at `\$.settings.refine_ao_rays`"),
    ({"type": "settings", "settings": {"ao_samples": 4}}, r"unknown field `ao_samples` - at `\$.settings`"),
    ({"type": "settings", "settings": {"spp": 5}}, r"<= 4 - at `\$.settings.spp`"),
    ({"type": "settings", "settings": {"interpolation": "lanczos"}}, r"at `\$.settings.interpolation`"),
    ({"type": "settings", "settings": {"ao_radius": 0}}, r"> 0.0 - at `\$.settings.ao_radius`"),
    ({"type": "settings", "settings": {"ao_radius": float("nan")}}, r"at `\$.settings.ao_radius`"),
    ({"type": "settings", "settings": {"quality": 101}}, r"at `\$.settings.quality`"),
    ({"type": "settings", "settings": {"channel": "color"}}, r"at `\$.settings.channel`"),
    ({"type": "settings"}, "missing required field `settings`"),
    ({"type": "settings", "settings": [1]}, r"Expected `object`, got `array` - at `\$.settings`"),
    ({"type": "focus", "shape": "circle", "center": [1, 2]}, "radius"),
    ({"type": "focus", "shape": "box", "box": [5, 5, 1, 9]}, "x0 < x1"),
    ({"type": "focus", "shape": "star"}, r"at `\$.shape`"),
    ({"type": "open", "version": 99, "volume": "proc:sphere"}, "protocol version 99 is not supported"),
    ({"type": "open", "version": V, "volume": "../../etc/passwd"}, r"at `\$.volume`"),
    ({"type": "open", "version": V, "volume": "/abs/path.nii"}, r"at `\$.volume`"),
    ({"type": "open", "version": V}, "missing required field `volume`"),
    ({"type": "open", "version": V, "volume": "x", "camera": {"type": "camera"}}, r"give eye.* - at `\$.camera`"),
    ({"type": "open", "version": V, "volume": "x", "camera": {"type": "iso", "yaw": 1}}, r"at `\$.camera.type`"),
    ({"type": "open", "version": V, "volume": "x", "settings": {"mode": "SR"}}, r"at `\$.settings.mode`"),
    ({"type": "open", "version": V, "volume": "x", "settings": {"ao_rays": 300}}, r"max_ao_rays\) - at `\$.settings"),
    ({"type": "received"}, "missing required field `frame`"),
    ({"type": "received", "frame": -1}, r">= 0 - at `\$.frame`"),
    ({"type": "received", "frame": 2**64 - 1}, r"at `\$.frame`"),
    ({"type": "received", "frame": "3"}, r"at `\$.frame`"),
    ({"type": "received", "frame": 1.0}, r"got `float` - at `\$.frame`"),
    ({"type": "received", "frame": 1, "seq": 4}, "unknown field `seq`"),
    ({"type": "hello"},
     "message type must be one of camera, iso, settings, focus, pick, received, keyframe, open: .*'hello'"),
    ({"no": "type"}, "message type must be one of .*missing required field `type`"),
])
def test_invalid_messages_name_the_problem(message, words):
    with pytest.raises(P.ProtocolError, match=words) as e:
        P.parse(raw(message), LIMITS, dict(P.CLIENT_VIEW_MESSAGES, open=P.OpenMsg))
    assert e.value.close_code == P.CLOSE_BAD_MESSAGE and e.value.http_status == 400
    assert len(e.value.reason) <= 200


@pytest.mark.parametrize("message", [
    {"type": "open", "version": 3, "volume": "proc:sphere"},
    {"type": "upscale", "version": 3, "mask": {"dtype": "float32", "shape": [2, 2], "data": bytes(16)},
     "normal": {"dtype": "float32", "shape": [2, 2, 3], "data": bytes(48)},
     "depth": {"dtype": "float32", "shape": [2, 2], "data": bytes(16)}},
])
def test_version_3_is_refused_with_the_reason(message):
    with pytest.raises(P.ProtocolError) as e:
        P.parse(raw(message), LIMITS, (P.OpenMsg, P.UpscaleRequest))
    assert e.value.reason == "protocol version 3 is not supported; this server speaks 12: update the client"
    assert (e.value.close_code, e.value.http_status) == (P.CLOSE_BAD_MESSAGE, 400)


def test_malformed_truncated_trailing_and_oversize_bytes():
    good = P.encode(P.IsoMsg(1.0))
    for data, words in ((good[:-2], "truncated"), (good + b"\x00", "trailing"), (b"\xc1", "malformed"),
                        (raw([1, 2]), "Expected `object`, got `array`"), (raw({1: 2}), "Expected `str`"),
                        (raw({"type": "iso", "value": msgspec.msgpack.Ext(5, b"x")}), r"got `ext` - at `\$.value`"),
                        (raw({"type": "open", "version": V, "volume": "x", "settings": msgspec.msgpack.Ext(1, b"")}),
                         "ext"),
                        ("text", "binary msgpack")):
        with pytest.raises(P.ProtocolError, match=words) as e:
            P.parse(data, LIMITS, (P.IsoMsg, P.OpenMsg))
        assert e.value.close_code == P.CLOSE_BAD_MESSAGE
    small = P.Limits(max_message_bytes=100)
    with pytest.raises(P.ProtocolError, match="message of 2.. bytes exceeds the limit of 100") as e:
        P.parse(raw({"type": "iso", "value": 1.0, "pad": b"x" * 200}), small, (P.IsoMsg,))
    assert (e.value.close_code, e.value.http_status) == (P.CLOSE_TOO_BIG, 413)


def _upscale_wire(**arrays) -> dict:
    base = wire(P.UpscaleRequest(np.ones((4, 5), np.float32), np.zeros((4, 5, 3), np.float32),
                                 np.ones((4, 5), np.float32)))
    return base | arrays


def _array(dtype="float32", shape=(4, 5), data=None, **extra) -> dict:
    itemsize = np.dtype(dtype).itemsize if dtype in ("float16", "float32", "uint8", "uint16") else 4
    return {"dtype": dtype, "shape": list(shape), "data": bytes(itemsize * int(np.prod(shape))) if data is None
            else data, **extra}


@pytest.mark.parametrize("message, words", [
    (_upscale_wire(depth=_array("float64", data=bytes(160))),
     r"Invalid enum value 'float64' in `dtype` - at `\$.depth`"),
    (_upscale_wire(depth=_array("uint8")), "depth: must be a numpy array of float16 or float32, got uint8"),
    (_upscale_wire(depth=_array(data=bytes(79))), r"79 data bytes, but float32 \(4, 5\) needs 80 - at `\$.depth`"),
    (_upscale_wire(depth=_array(shape=(4, 0))), r"Expected `int` >= 1 in `shape\[1\]` - at `\$.depth`"),
    (_upscale_wire(depth=_array(shape=(1, 1, 1, 1))), r"length <= 3 in `shape` - at `\$.depth`"),
    (_upscale_wire(depth=_array(shape=(5, 4))), r"depth: shape must be \(4, 5\), got \(5, 4\)"),
    (_upscale_wire(normal=_array()), r"normal: shape must be \(4, 5, 3\)"),
    (_upscale_wire(mask=_array(shape=(20,))), "mask: must be a 2-D numpy array"),
    (_upscale_wire(depth=_array(data=np.full(20, np.nan, np.float32).tobytes())),
     r"holds NaN or Inf values - at `\$.depth`"),
    (_upscale_wire(depth=_array(data=b"garbage", zlib=True)), r"corrupt zlib data .* - at `\$.depth`"),
    (_upscale_wire(depth=_array(data=zlib.compress(bytes(81)), zlib=True)), r"inflates past the 80 bytes"),
    (_upscale_wire(depth=_array(data=zlib.compress(bytes(80)) + b"x", zlib=True)), r"after the zlib stream"),
    (_upscale_wire(depth=_array(data="QUJD" * 20)), r"Expected `bytes`, got `str` in `data` - at `\$.depth`"),
    (_upscale_wire(depth=_array(order="F")), r"unknown field `order` - at `\$.depth`"),
    (_upscale_wire(depth=[1, 2]), r"Expected `object`, got `array` - at `\$.depth`"),
    (_upscale_wire(depth=_array(data=msgspec.msgpack.Ext(3, b"x"))), "extension type 3 is not part of the protocol"),
    (_upscale_wire(output="gif"), r"at `\$.output`"),
    (_upscale_wire(session="../x"), r"at `\$.session`"),
    (_upscale_wire(quality=0), r"at `\$.quality`"),
    (_upscale_wire(flow=None, extra=1), "unknown field `extra`"),
])
def test_invalid_upscale_requests_name_the_array(message, words):
    with pytest.raises(P.ProtocolError, match=words) as e:
        P.parse(raw(message), LIMITS, (P.UpscaleRequest,))
    assert e.value.close_code == P.CLOSE_BAD_MESSAGE


@pytest.mark.parametrize("name, value", [("mask", 1.5), ("mask", -0.1), ("normal", 2.0), ("depth", -1.0),
                                         ("depth", 3e38), ("flow", 1e5)])
def test_upscale_inputs_out_of_range_are_refused(name, value):
    arrays = {"mask": np.ones((4, 5), np.float32), "normal": np.zeros((4, 5, 3), np.float32),
              "depth": np.ones((4, 5), np.float32), "flow": np.zeros((4, 5, 2), np.float32)}
    arrays[name].flat[3] = value
    with pytest.raises(P.ProtocolError, match=f"{name}: values must lie in"):
        P.UpscaleRequest(**arrays)  # where it is made
    message = _upscale_wire(**{name: msgspec.to_builtins(encode_array(arrays[name]), builtin_types=(bytes,))})
    with pytest.raises(P.ProtocolError, match=f"{name}: values must lie in"):
        P.parse(raw(message), LIMITS, (P.UpscaleRequest,))  # and where it arrives


def test_array_size_limit_refuses_before_inflating():
    small = P.Limits(max_pixels=100, max_side=1000)
    message = _upscale_wire(depth=_array(shape=(1000, 1000), data=b"garbage", zlib=True))
    with pytest.raises(P.ProtocolError, match=r"array declared shape \(1000, 1000\) of 1000000 elements exceeds") as e:
        P.parse(raw(message), small, (P.UpscaleRequest,))
    assert (e.value.close_code, e.value.http_status) == (P.CLOSE_TOO_BIG, 413)


def test_downscaled_limits_bound_an_upscale_requests_arrays():
    low = LIMITS.downscaled(4)
    assert (low.max_side, low.max_pixels, low.max_message_bytes) == (1024, 518400, LIMITS.max_message_bytes)
    assert low.array_bounds() == (4 * 518400, 1024)
    message = _upscale_wire(depth=_array(shape=(2048, 2048), data=b"garbage", zlib=True))  # within LIMITS' bounds
    with pytest.raises(P.ProtocolError, match=r"declared shape \(2048, 2048\) .* sides <= 1024") as e:
        P.parse(raw(message), low, (P.UpscaleRequest,))
    assert e.value.http_status == 413


def test_float16_inputs_raise_no_overflow_warning():
    """Bounds beyond float16's range (MAX_DEPTH) are compared as Python floats, not cast to float16."""
    arrays = {"mask": np.ones((4, 5)), "normal": np.full((4, 5, 3), 0.5), "depth": np.full((4, 5), 60000.0),
              "flow": np.full((4, 5, 2), -P.FLOW_CLIP)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = roundtrip(P.UpscaleRequest(**{n: a.astype(np.float16) for n, a in arrays.items()}))
    assert back.depth.dtype == np.float16 and back.depth.max() == 60000.0


def test_client_side_limits_bound_frames():
    small = P.Limits(max_side=32)
    with pytest.raises(P.ProtocolError, match="frame 64x48 exceeds the limits") as e:
        roundtrip(P.FrameMsg(seq=0, ack=-1, mode="full", method="full", width=64, height=48, encoding="png",
                             times={}, nbytes=1, image=b"x"), small)
    assert e.value.close_code == P.CLOSE_TOO_BIG


@pytest.mark.parametrize("make, words", [
    (lambda: P.FrameMsg(seq=0, ack=-1, mode="full", method="", width=1, height=1, encoding="png", times={},
                        nbytes=0), "an encoded frame carries image bytes"),
    (lambda: P.FrameMsg(seq=0, ack=-1, mode="buffers", method="", width=1, height=1, encoding="buffers", times={},
                        nbytes=0, image=b"x"), "a buffers frame carries buffers"),
    (lambda: P.UpscaleResponse(seq=0, width=8, height=6, output="png", times={}, nbytes=0), "image output"),
    (lambda: P.UpscaleResponse(seq=0, width=8, height=6, output="buffers", times={}, nbytes=0,
                               buffers=P.HighresBuffers(*[np.zeros((6, 8), np.float32)] * 4)), r"normal: shape"),
    (lambda: P.CameraMsg(yaw=1.0), "give eye"),
    (lambda: P.FocusMsg("box"), "box"),
])
def test_semantic_checks_run_where_messages_are_made(make, words):
    with pytest.raises(P.ProtocolError, match=words):
        make()


def video_frame(**fields) -> P.FrameMsg:
    return P.FrameMsg(**{"seq": 2, "ack": 1, "mode": "full", "method": "full", "width": 63, "height": 48,
                         "encoding": "h264", "times": {"encode": 1.0}, "nbytes": 3, "image": b"\0\0\1",
                         "keyframe": False, "timestamp_us": 40000, "codec": "avc1.64001f", "bitrate_kbps": 2500}
                      | fields)


def test_video_messages_round_trip_and_their_rules():
    """Issue 21's wire: video frames (codec string, keyframe flag, timestamp, bitrate), notices,
    keyframe requests, the encoders ``ready`` names and the bitrate cap's bound."""
    for msg in (video_frame(), video_frame(encoding="av1", codec="av01.0.08M.08", keyframe=True),
                P.NoticeMsg("h264 is not available on this server; sending jpeg"), P.KeyframeMsg(),
                P.ReadyMsg("abc", VOLUME, P.ViewSettings(encoding="vp9", bitrate_kbps=8000), 4, 8, LIMITS, MODES,
                           ["jpeg", "png", "webp", "vp9"])):
        assert roundtrip(msg) == msg
    assert P.ReadyMsg("abc", VOLUME, P.ViewSettings(), 4, 8, LIMITS, MODES).encoders == list(P.IMAGE_ENCODINGS)
    assert P.ENCODINGS == P.IMAGE_ENCODINGS + P.VIDEO_ENCODINGS and "h264" not in P.UPSCALE_OUTPUTS
    assert wire(P.KeyframeMsg()) == {"type": "keyframe"}
    assert P.parse(raw({"type": "keyframe"}), LIMITS, P.CLIENT_VIEW_MESSAGES) == P.KeyframeMsg()
    for make, words in ((lambda: video_frame(codec=None), "a video frame carries its codec string"),
                        (lambda: video_frame(encoding="jpeg"), "a video frame carries its codec string"),
                        (lambda: video_frame(encoding="png", codec=None), "only a video frame can be a delta")):
        with pytest.raises(P.ProtocolError, match=words):
            make()
    with pytest.raises(P.ProtocolError, match="Invalid enum value 'h265'"):
        P.parse(raw(wire(video_frame()) | {"encoding": "h265"}), LIMITS, P.SERVER_VIEW_MESSAGES)
    with pytest.raises(P.ProtocolError, match=r"<= 100000 \(max_bitrate_kbps\) - at `\$.settings.bitrate_kbps`"):
        P.ViewSettings().updated({"bitrate_kbps": 100_001}, LIMITS)
    with pytest.raises(P.ProtocolError, match=r"max_bitrate_kbps"):
        P.parse(raw({"type": "open", "volume": "bonsai", "settings": {"bitrate_kbps": 10**6}}), LIMITS, (P.OpenMsg,))
    assert P.ViewSettings().updated({"bitrate_kbps": 10**6}, P.Limits(max_bitrate_kbps=10**6)).bitrate_kbps == 10**6


def test_frame_times_name_known_stages_only():
    frame = wire(P.FrameMsg(seq=0, ack=-1, mode="full", method="full", width=4, height=4, encoding="png",
                            times={"total": 1.0}, nbytes=1, image=b"x"))
    for times, words in (({"gpu": 1.0}, r"Invalid enum value 'gpu' - at `key` in `\$.times`"),
                         ({"total": -1.0}, r">= 0.0 - at `\$.times\[...\]`")):
        with pytest.raises(P.ProtocolError, match=words):
            P.parse(raw(frame | {"times": times}), LIMITS, P.SERVER_VIEW_MESSAGES)
    assert P.STAGES == ("render", "filter", "network", "shading", "encode", "total")


def test_a_mode_is_a_short_lowercase_name():
    for bad in ("", "Full", "full mode", "x" * 40, "9lives"):
        with pytest.raises(P.ProtocolError, match="mode"):
            P.parse(raw({"type": "settings", "settings": {"mode": bad}}), LIMITS, P.CLIENT_VIEW_MESSAGES)


def test_settings_update_and_size_limit():
    s = P.ViewSettings()
    assert (s.mode, s.ao_rays, s.spp, s.interpolation, s.refine_ao_rays) == ("auto", 0, 1, "bilinear", 64)
    s2 = s.updated({"width": 128, "mode": "full", "ao_rays": 4}, LIMITS)
    assert (s2.width, s2.height, s2.mode, s2.ao_rays) == (128, s.height, "full", 4)
    assert s.updated(P.SettingsUpdate(interpolation="nearest"), LIMITS).interpolation == "nearest"
    with pytest.raises(P.ProtocolError, match="exceeds") as e:
        s.updated({"width": 4096, "height": 4096}, LIMITS)
    assert e.value.close_code == P.CLOSE_TOO_BIG
    with pytest.raises(P.ProtocolError, match="image 5000x480 exceeds") as e:
        s.updated(P.SettingsUpdate(width=5000), LIMITS)
    assert e.value.close_code == P.CLOSE_TOO_BIG
    for update, words in (({"widht": 4}, "unknown field `widht`"), ({"ao_rays": 300}, "max_ao_rays"),
                          ({"mode": "SR!"}, r"Expected `str` matching regex .* - at `\$.mode`")):
        with pytest.raises(P.ProtocolError, match=words) as e:
            s.updated(update, LIMITS)
        assert e.value.close_code == P.CLOSE_BAD_MESSAGE
    assert s.updated({"ao_rays": 300}, P.Limits(max_ao_rays=512)).ao_rays == 300
    with pytest.raises(P.ProtocolError) as e:  # a long bad value is cut, the field's path kept
        s.updated({"coloring": {"by": "gradient", "colormap": "x" * 10_000}}, LIMITS)
    assert len(e.value.reason) <= 200 and e.value.reason.endswith("- at `$.coloring.colormap`")


def test_limits_validate():
    assert P.Limits().open_timeout_s == 10 and P.Limits().max_upscale_bytes == 2 * 2**30
    assert (P.Limits().max_sessions_per_client, P.Limits().max_connections, P.Limits().max_connections_per_client,
            P.Limits().body_timeout_s, P.Limits().max_ao_rays) == (8, 256, 32, 30, 256)
    with pytest.raises(ValueError, match="max_fps"):
        P.Limits(max_fps=0)
    with pytest.raises(ValueError, match="max_sessions"):
        P.Limits(max_sessions=float("nan"))
    with pytest.raises(ValueError, match="max_unacked_frames must be an integer"):
        P.Limits(max_unacked_frames=1.5)
    with pytest.raises(ValueError, match="open_timeout_s"):
        P.Limits(open_timeout_s=-1.0)
    with pytest.raises(ValueError, match="max_upscale_bytes"):
        P.Limits(max_upscale_bytes=float("inf"))
    with pytest.raises(P.ProtocolError, match="limit max_side must be a positive number"):  # arriving in ready
        P.parse(raw(wire(P.ReadyMsg("s", VOLUME, P.ViewSettings(), 4, 8, LIMITS, MODES)) | {"limits": {"max_side": 0}}),
                LIMITS, P.SERVER_VIEW_MESSAGES)


# Values of every wire kind, nested a little: what a hostile client can put in a msgpack map.
_leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(allow_nan=True),
                  st.text(max_size=20), st.binary(max_size=64))
_value = st.recursive(_leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                     st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                      max_leaves=12)
_ALL = dict(P.CLIENT_VIEW_MESSAGES, **P.SERVER_VIEW_MESSAGES, open=P.OpenMsg, upscale=P.UpscaleRequest,
            upscaled=P.UpscaleResponse)
_KEYS = ["type", "eye", "target", "up", "yaw", "pitch", "distance", "fov_y", "seq", "value", "normalized", "settings",
         "shape", "center", "radius", "box", "version", "volume", "camera", "iso", "mask", "normal", "depth",
         "flow", "output", "session", "dtype", "data", "width", "height", "times", "buffers", "image", "code", "frame",
         "method", "limits", "legend", "clip", "coloring", "by", "colormap", "range"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(sorted(_ALL)),
       fields=st.dictionaries(st.sampled_from(_KEYS), _value, max_size=6))
def test_fuzz_every_message_type_gives_protocol_errors_only(kind, fields):
    data = raw({"type": kind, **fields})
    try:
        msg = P.parse(data, LIMITS, _ALL)
    except P.ProtocolError as e:
        assert e.close_code in (P.CLOSE_BAD_MESSAGE, P.CLOSE_TOO_BIG) and e.reason
    else:
        assert isinstance(msg, _ALL[kind])
        assert P.parse(P.encode(msg), LIMITS, _ALL) == msg  # whatever validates can be sent back


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data):
    try:
        msg = P.parse(data, LIMITS, _ALL)
    except P.ProtocolError as e:
        assert e.reason
    else:  # random bytes that happen to form a valid message must give a message
        assert isinstance(msg, P.Message)
