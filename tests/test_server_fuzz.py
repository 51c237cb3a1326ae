"""Fuzzing `isosr serve` over the wire (hypothesis, bounded examples): every view message type,
``open``, and the upscale request, each a valid message with fields deleted, replaced or added.
Every answer must be a frame or a clean error close (or a 4xx with a reason); afterwards the
server still answers health and an honest session still gets correct frames."""

from __future__ import annotations

import json

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed

from isosr_render import orbit
from isosr_server import protocol as P
from server_fixtures import (CAM0, DEVICE, VOLUME, assert_image, cam, frame, lib, lib_full, raw, recv,  # noqa: F401
                             running_server, send, server_settings, session, settle, wire, wire_frame)

LIMITS = P.Limits(max_message_bytes=2**20, max_sessions=6, max_fps=1000.0, max_messages_per_s=5000.0)


@pytest.fixture(scope="module")
def srv():
    with running_server(server_settings(limits=LIMITS)) as s:
        yield s


_leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(allow_nan=True),
                  st.text(max_size=12), st.binary(max_size=32))
_value = st.recursive(_leaf, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                     st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                      max_leaves=8)
SMALL_FULL = P.SettingsUpdate(mode="full", width=16, height=12, refine=False)
VALID_UPDATES = {
    "camera": wire(cam(40, seq=1)),
    "look-at": wire(P.CameraMsg(eye=(0.5, 0.5, 1.5), seq=1)),
    "iso": wire(P.IsoMsg(0.01, seq=1)),
    "settings": wire(P.SettingsMsg(P.SettingsUpdate(mode="upscale", width=16, height=12, quality=50,
                                                    interpolation="nearest"), seq=1)),
    "focus": wire(P.FocusMsg("circle", center=(8.0, 6.0), radius=4.0, seq=1)),
}
VALID_OPEN = wire(P.OpenMsg(VOLUME, SMALL_FULL, CAM0))


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
        d["settings"] = {**d["settings"], draw(st.sampled_from(P.ViewSettings.__struct_fields__)): draw(_value)}
    return d


def _answer_is_frame_or_close(ws):
    msg = recv(ws)
    while isinstance(msg, P.NoticeMsg):  # a refused settings update: its reason, then a frame of the settings kept
        assert msg.text.startswith("settings refused, kept as they were: "), msg
        msg = recv(ws)
    if isinstance(msg, P.ErrorMsg):
        refused_iso = msg.code == P.CLOSE_POLICY and "value range" in msg.reason  # an iso outside the volume's
        assert msg.code in (P.CLOSE_BAD_MESSAGE, P.CLOSE_TOO_BIG, P.CLOSE_NOT_FOUND) or refused_iso, msg
        with pytest.raises(ConnectionClosed):
            ws.recv(timeout=30)
    else:
        assert isinstance(msg, (P.FrameMsg, P.ReadyMsg)), msg


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_view_messages(srv, data):
    kind = data.draw(st.sampled_from(sorted(VALID_UPDATES)))
    message = data.draw(mutated(VALID_UPDATES[kind]))
    settle(srv)
    with srv.view() as ws:
        send(ws, P.OpenMsg(VOLUME, SMALL_FULL))
        recv(ws), recv(ws)
        ws.send(raw(message))
        _answer_is_frame_or_close(ws)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_acknowledgments(srv, data):
    """``received`` with any frame value (wrong, huge, negative, not an integer) or fields, after
    frame 0: a clean 1007 close, or (frame 0) accepted; then a camera still gets its frame."""
    message = data.draw(st.one_of(mutated(wire(P.ReceivedMsg(0))),
                                  st.builds(lambda n: wire(P.ReceivedMsg(n)), st.integers(0, P.MAX_SEQ))))
    settle(srv)
    with srv.view() as ws:
        send(ws, P.OpenMsg(VOLUME, SMALL_FULL))
        recv(ws), recv(ws)
        ws.send(raw(message))
        try:
            send(ws, cam(50, seq=1))  # frame 1 needs no acknowledgment: max_unacked_frames is 2
        except ConnectionClosed as closed:  # the server refused the acknowledgment first
            assert closed.rcvd is not None and closed.rcvd.code == P.CLOSE_BAD_MESSAGE, closed
            return
        _answer_is_frame_or_close(ws)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(message=mutated(VALID_OPEN))
@example(message={**VALID_OPEN, "iso": 1, "iso_normalized": False})  # outside the volume's range: 1008 naming it
def test_fuzz_open(srv, message):
    settle(srv)
    with srv.view() as ws:
        ws.send(raw(message))
        _answer_is_frame_or_close(ws)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_fuzz_upscale(srv, lib, data):
    good = wire_frame(lib)
    message = data.draw(mutated({**good, "mask": dict(good["mask"]) if data.draw(st.booleans()) else good["mask"]}))
    if isinstance(message.get("mask"), dict) and data.draw(st.booleans()):
        message["mask"] = data.draw(mutated(good["mask"]))  # inside an array
    status, _, body = srv.request("POST", "/v1/upscale", raw(message))
    assert status == 200 or (status in (400, 413, 422) and json.loads(body)["error"])


def test_after_fuzzing_the_server_is_healthy_and_correct(srv, lib):
    assert srv.get_json("/v2/health/ready") == (200, {"ready": True})
    with session(srv, mode="full") as (ws, _):
        assert_image(frame(ws).image, lib_full(lib, orbit(30, 20, 1.8)))
    assert not srv.errors.records, srv.errors.messages()
