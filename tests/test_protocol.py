"""The wire protocol: round trips, validation of every message, the buffers coding's tolerances, fuzzing."""

from __future__ import annotations

import math
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from isosr_server import protocol as P

LIMITS = P.Limits()


def roundtrip(msg: P.Message) -> P.Message:
    return P.parse(P.pack(msg.to_wire()), LIMITS, (type(msg),))


def test_messages_round_trip():
    cam = P.CameraMsg(yaw=30.0, pitch=20.0, distance=1.8, seq=3)
    for msg in (cam, P.CameraMsg(eye=(0.0, 0.5, 2.0), fov_y=30.0),
                P.OpenMsg("proc:sphere", {"mode": "full", "width": 64, "height": 48}, cam, 0.2, True),
                P.IsoMsg(77.0, seq=9), P.SettingsMsg({"ao_samples": 8, "encoding": "png"}, seq=1),
                P.FocusMsg("circle", center=(32.0, 24.0), radius=10.0), P.FocusMsg("box", box=(1.0, 2.0, 30.0, 40.0)),
                P.FocusMsg("none"), P.ErrorMsg(1007, "bad"), P.ReceivedMsg(0), P.ReceivedMsg(P.MAX_SEQ),
                P.ReadyMsg("abc", {"name": "x"}, {"mode": "sr"}, 4, P.limits_to_wire(LIMITS)),
                P.FrameMsg(0, -1, "full", 64, 48, "png", {"render": 1.0, "total": 2.0}, 10, image=b"\x89PNG")):
        assert roundtrip(msg) == msg


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
    assert (back.output, back.session) == ("png", "s-1")
    out = {"mask": mask, "normal": np.zeros((6, 8, 3), np.float32), "depth": mask * 2, "ao": mask}
    resp = roundtrip(P.UpscaleResponse(0, 8, 6, "buffers", {"total": 1.0}, 123, buffers=out))
    for name in P.HIGHRES_OUTPUTS:
        np.testing.assert_array_equal(resp.buffers[name], out[name])


@pytest.mark.parametrize("wire, words", [
    ({"type": "camera"}, "eye"),
    ({"type": "camera", "eye": [0, 0, 1], "yaw": 3}, "not both"),
    ({"type": "camera", "eye": [0, 0, 0]}, "coincide"),
    ({"type": "camera", "eye": [0, 1, 0], "up": [0, 2, 0]}, "parallel"),
    ({"type": "camera", "eye": [0, 1, 0]}, "parallel"),
    ({"type": "camera", "eye": [0, 0, 1], "up": [0, 0, 0]}, "zero"),
    ({"type": "camera", "yaw": 0, "pitch": 0, "distance": 1, "up": [1, 0, 0]}, "orbit"),
    ({"type": "camera", "eye": [0, 0, float("nan")]}, "finite"),
    ({"type": "camera", "yaw": 0, "pitch": 90, "distance": 1}, "pitch"),
    ({"type": "camera", "yaw": 0, "pitch": 0, "distance": 1, "zoom": 2}, "unknown fields"),
    ({"type": "camera", "yaw": True, "pitch": 0, "distance": 1}, "yaw"),
    ({"type": "iso", "value": float("inf")}, "finite"),
    ({"type": "iso", "value": "7"}, "value"),
    ({"type": "settings", "settings": {"mode": "fast"}}, "mode"),
    ({"type": "settings", "settings": {"width": 0}}, "width"),
    ({"type": "settings", "settings": {"ao_samples": 10**6}}, "ao_samples"),
    ({"type": "settings", "settings": {"quality": 101}}, "quality"),
    ({"type": "settings"}, "settings"),
    ({"type": "focus", "shape": "circle", "center": [1, 2]}, "radius"),
    ({"type": "focus", "shape": "box", "box": [5, 5, 1, 9]}, "x0 < x1"),
    ({"type": "focus", "shape": "star"}, "shape"),
    ({"type": "open", "version": 99, "volume": "proc:sphere"}, "version"),
    ({"type": "open", "version": P.PROTOCOL_VERSION, "volume": "../../etc/passwd"}, "volume"),
    ({"type": "open", "version": P.PROTOCOL_VERSION, "volume": "/abs/path.nii"}, "volume"),
    ({"type": "open", "version": P.PROTOCOL_VERSION}, "volume"),
    ({"type": "open", "version": 1, "volume": "proc:sphere"}, "version 1 is not supported.*update the client"),
    ({"type": "received"}, "frame"),
    ({"type": "received", "frame": -1}, "frame"),
    ({"type": "received", "frame": 2**64 - 1}, "frame"),
    ({"type": "received", "frame": "3"}, "frame"),
    ({"type": "received", "frame": 1.0}, "frame"),
    ({"type": "received", "frame": 1, "seq": 4}, "unknown fields"),
    ({"type": "hello"}, "type"),
    ({"no": "type"}, "type"),
])
def test_invalid_messages_name_the_problem(wire, words):
    with pytest.raises(P.ProtocolError, match=words) as e:
        P.parse(P.pack(wire), LIMITS, dict(P.CLIENT_VIEW_MESSAGES, open=P.OpenMsg))
    assert e.value.close_code == P.CLOSE_BAD_MESSAGE and e.value.http_status == 400


def test_malformed_truncated_and_oversize_bytes():
    good = P.pack(P.IsoMsg(1.0).to_wire())
    for data, code in ((good[:-2], P.CLOSE_BAD_MESSAGE), (good + b"\x00", P.CLOSE_BAD_MESSAGE),
                       (b"\xc1", P.CLOSE_BAD_MESSAGE), (msgpack.packb([1, 2]), P.CLOSE_BAD_MESSAGE),
                       (msgpack.packb({1: 2}), P.CLOSE_BAD_MESSAGE),
                       (msgpack.packb({"type": "iso", "value": msgpack.ExtType(5, b"x")}), P.CLOSE_BAD_MESSAGE),
                       (b"\x00" * (LIMITS.max_message_bytes + 1), P.CLOSE_TOO_BIG)):
        with pytest.raises(P.ProtocolError) as e:
            P.parse(data, LIMITS, (P.IsoMsg,))
        assert e.value.close_code == code
    small = P.Limits(max_message_bytes=100)
    with pytest.raises(P.ProtocolError, match="exceeds") as e:
        P.parse(P.pack({"type": "iso", "value": 1.0, "pad": b"x" * 200}), small, (P.IsoMsg,))
    assert e.value.http_status == 413


def _array(dtype="float32", shape=(4, 5), data=None, **extra):
    data = bytes(4 * math.prod(shape)) if data is None else data
    return {"dtype": dtype, "shape": list(shape), "data": data, **extra}


@pytest.mark.parametrize("wire, words", [
    (_array("float64", data=bytes(160)), "dtype"),
    (_array("int32"), "dtype"),
    (_array(data=bytes(79)), "needs 80"),
    (_array(shape=(4, 0)), "shape"),
    (_array(shape=(1, 1, 1, 1)), "shape"),
    (_array(shape=(5, 4)), r"shape must be \(4, 5\)"),
    (_array(data=np.full(20, np.nan, np.float32).tobytes()), "NaN or Inf"),
    (_array(data=np.full(20, np.inf, np.float32).tobytes()), "NaN or Inf"),
    (_array(data=b"garbage", zlib=True), "zlib"),
    (_array(data=zlib.compress(bytes(81)), zlib=True), "inflate"),
    (_array(data="text"), "bin"),
    (_array(order="F"), "unknown fields"),
])
def test_invalid_arrays(wire, words):
    with pytest.raises(P.ProtocolError, match=words):
        P.decode_array(wire, "depth", LIMITS, ("float16", "float32"), (4, 5))


@pytest.mark.parametrize("name, value", [("mask", 1.5), ("mask", -0.1), ("normal", 2.0), ("depth", -1.0),
                                         ("depth", 3e38), ("flow", 1e5)])
def test_upscale_inputs_out_of_range_are_refused(name, value):
    arrays = {"mask": np.ones((4, 5), np.float32), "normal": np.zeros((4, 5, 3), np.float32),
              "depth": np.ones((4, 5), np.float32), "flow": np.zeros((4, 5, 2), np.float32)}
    arrays[name].flat[3] = value
    wire = P.UpscaleRequest(**arrays).to_wire()
    with pytest.raises(P.ProtocolError, match=f"{name}: values must lie in"):
        P.parse(P.pack(wire), LIMITS, (P.UpscaleRequest,))


def test_array_element_limit_refuses_before_allocating():
    small = P.Limits(max_pixels=100, max_side=1000)
    with pytest.raises(P.ProtocolError, match="exceed") as e:
        P.decode_array(_array(shape=(1000, 1000), data=b""), "mask", small)
    assert e.value.close_code == P.CLOSE_TOO_BIG


def test_zlib_bomb_is_bounded():
    bomb = zlib.compress(bytes(10**7))  # inflates far beyond the 80 bytes the shape allows
    with pytest.raises(P.ProtocolError, match="inflate"):
        P.decode_array(_array(data=bomb, zlib=True), "depth", LIMITS, shape=(4, 5))


def _random_frame(h=37, w=53, seed=0):
    rng = np.random.default_rng(seed)
    mask = (rng.random((h, w)) > 0.3).astype(np.float32)
    mask[0, :5] = [0.001, 0.3, 0.5, 0.999, 1.0]  # coverage values, one tiny
    n = rng.standard_normal((h, w, 3))
    n[..., 2] = np.where(rng.random((h, w)) > 0.2, np.abs(n[..., 2]), -np.abs(n[..., 2]))  # some z < 0
    n[1, 1] = (0, 0, -1)
    n[1, 2] = (1, 0, 0)
    normal = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32) * (mask > 0)[..., None]
    depth = (rng.uniform(1.2, 2.4, (h, w)) * (mask > 0)).astype(np.float32)
    flow = rng.uniform(-40, 40, (h, w, 2)).astype(np.float32)
    flow[2, 2] = (1e6, -1e6)  # clipped to FLOW_CLIP
    return mask, normal, depth, flow


def test_buffers_coding_within_stated_tolerances():
    mask, normal, depth, flow = _random_frame()
    wire = msgpack.unpackb(P.pack(P.encode_view_buffers(mask, normal, depth, flow)), raw=False)
    out = P.decode_view_buffers(wire, LIMITS)
    covered = mask > 0
    assert np.array_equal(out["mask"] > 0, covered)  # "no hit" survives exactly, even at coverage 0.001
    assert np.abs(out["mask"] - mask)[mask >= 1 / 255].max() <= 0.5 / 255 + 1e-7
    cos = (out["normal"][covered] * normal[covered]).sum(-1)
    assert np.arccos(np.clip(cos, -1, 1)).max() < 1e-3
    assert not out["normal"][~covered].any() and not out["depth"][~covered].any()
    near, far = depth[covered].min(), depth[covered].max()
    assert np.abs(out["depth"] - depth).max() <= (far - near) / 131070 + 1e-6
    clipped = np.clip(flow, -P.FLOW_CLIP, P.FLOW_CLIP)
    assert np.all(np.abs(out["flow"] - clipped) <= np.abs(clipped) * 2.0**-11 + 1e-7)
    assert all(out[k].dtype == np.float32 for k in out)


def test_buffers_coding_edge_cases():
    empty = np.zeros((4, 6), np.float32)
    out = P.decode_view_buffers(P.encode_view_buffers(empty, np.zeros((4, 6, 3), np.float32), empty, None), LIMITS)
    assert not out["mask"].any() and not out["depth"].any() and "flow" not in out
    flat = np.ones((4, 6), np.float32)  # every hit at one depth: near == far
    n = np.tile(np.float32([0, 0, 1]), (4, 6, 1))
    out = P.decode_view_buffers(P.encode_view_buffers(flat, n, flat * 1.5, None), LIMITS)
    np.testing.assert_allclose(out["depth"], 1.5)
    np.testing.assert_allclose(out["normal"], n, atol=1e-4)
    wire = P.encode_view_buffers(flat, n, flat, None)
    wire["depth_range"] = [2.0, 1.0]
    with pytest.raises(P.ProtocolError, match="near <= far"):
        P.decode_view_buffers(wire, LIMITS)
    del wire["depth_range"]
    with pytest.raises(P.ProtocolError, match="depth_range"):
        P.decode_view_buffers(wire, LIMITS)


def test_buffers_coding_is_smaller_than_float32():
    mask, normal, depth, flow = _random_frame(96, 128, seed=1)
    mask[:, :64] = 0  # half the frame empty, as around an object
    normal *= (mask > 0)[..., None]
    coded = len(P.pack(P.encode_view_buffers(mask, normal, depth, flow)))
    assert coded < 0.5 * sum(a.nbytes for a in (mask, normal, depth, flow))


def test_reconstruct_mode_travels_and_every_mode_is_documented():
    assert "reconstruct" in P.MODES
    for mode in P.MODES:
        assert f"\n    {mode} " in P.__doc__, f"the module docstring does not describe mode {mode}"
    settings = {"mode": "reconstruct", "ao_samples": 2, "width": 50, "height": 30}  # full res: any size
    assert roundtrip(P.OpenMsg("proc:sphere", settings)).settings == settings
    assert roundtrip(P.SettingsMsg({"mode": "reconstruct", "ao_samples": 0}, seq=4)).settings["mode"] == "reconstruct"
    # Its frames time the whole reconstruction as one step: total and encode only.
    frame = P.FrameMsg(3, 2, "reconstruct", 50, 30, "webp", {"encode": 1.0, "total": 5.0}, 4, image=b"RIFF")
    assert roundtrip(frame) == frame


def test_settings_update_and_size_limit():
    s = P.ViewSettings()
    s2 = s.updated(P.ViewSettings.read_update({"width": 128, "mode": "full"}, LIMITS), LIMITS)
    assert (s2.width, s2.height, s2.mode) == (128, s.height, "full")
    with pytest.raises(P.ProtocolError, match="exceeds") as e:
        s.updated({"width": 4096, "height": 4096}, LIMITS)
    assert e.value.close_code == P.CLOSE_TOO_BIG


def test_limits_validate():
    with pytest.raises(ValueError, match="max_fps"):
        P.Limits(max_fps=0)
    with pytest.raises(ValueError, match="max_sessions"):
        P.Limits(max_sessions=float("nan"))
    with pytest.raises(ValueError, match="max_unacked_frames must be an integer"):
        P.Limits(max_unacked_frames=1.5)
    with pytest.raises(ValueError, match="max_unacked_frames"):
        P.Limits(max_unacked_frames=0)


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
         "flow", "output", "session", "dtype", "data", "width", "height", "times", "buffers", "image", "code", "frame"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(sorted(_ALL)),
       fields=st.dictionaries(st.sampled_from(_KEYS), _value, max_size=6))
def test_fuzz_every_message_type_gives_protocol_errors_only(kind, fields):
    data = P.pack({"type": kind, **fields})
    try:
        msg = P.parse(data, LIMITS, _ALL)
    except P.ProtocolError as e:
        assert e.close_code in (P.CLOSE_BAD_MESSAGE, P.CLOSE_TOO_BIG) and e.reason
    else:
        assert isinstance(msg, _ALL[kind])
        P.pack(msg.to_wire())  # whatever validates can be sent back


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data):
    try:
        msg = P.parse(data, LIMITS, _ALL)
    except P.ProtocolError as e:
        assert e.reason
    else:  # random bytes that happen to form a valid message must give a message
        assert isinstance(msg, P.Message)
