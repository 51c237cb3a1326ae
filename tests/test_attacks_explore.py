"""Attacks on the newest inputs of a real `isosr serve` subprocess on loopback (CPU, procedural
volumes), in the style of tests/test_attacks.py: hostile ``GET /v1/volumes/{name}/mesh`` queries
(clip JSON, isos), many clients meshing the largest procedural volume at once while an honest view
session runs (its frames, liveness, server memory), and hostile ``surfaces``, ``coloring`` and
``clip`` view settings, also toggled fast by several sessions. Every loop is bounded in count and time.
"""

from __future__ import annotations

import json
import math
import threading
import time
import urllib.parse

import msgspec
import pytest

from isosr_server import protocol as P
from test_attacks import CLIENT_LIMITS, MiB, assert_no_errors, get, open_view, serve, view

# The largest volume the server builds (MAX_PROCEDURAL_SIZE), with many triangles: about 1 s a mesh on CPUs.
LARGEST = "proc:cloud:0@128"
# Server RSS that clients meshing LARGEST for a few seconds may add (the bound holds max_mesh_jobs meshes).
MESH_RSS_GOAL = 128 * MiB
BUSY = f"the server already serves mesh extractions (at most {P.Limits().max_mesh_jobs}); try later"


@pytest.fixture(scope="module")
def server():
    with serve({}) as s:
        yield s


def mesh_path(name: str, **query) -> str:
    return f"/v1/volumes/{urllib.parse.quote(name, safe='')}/mesh?{urllib.parse.urlencode(query)}"


def plane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0)) -> dict:
    return {"point": list(point), "normal": list(normal)}


# ---- hostile mesh queries -----------------------------------------------------------------------


HOSTILE_MESHES = [  # (query, status, words of the answer)
    ({"iso": "nan"}, 422, "iso: iso nan is outside"),
    ({"iso": "inf"}, 422, "iso: iso inf is outside"),
    ({"iso": "-1e308"}, 422, "iso: iso -1e+308 is outside"),
    ({"iso": "1"}, 422, "iso: iso 1 is outside"),
    ({"iso": "x"}, 422, "float"),
    ({"format": "exe"}, 422, "format"),
    ({"clip": json.dumps({"planes": [plane(normal=(0, 0, 0))]})}, 400, "clip.planes[0].normal must be a nonzero"),
    ({"clip": json.dumps({"planes": [plane(normal=(1e-200, 0, 0))]})}, 400, "clip.planes[0].normal must be a nonzero"),
    ({"clip": '{"planes": [{"point": [NaN, 0, 0], "normal": [1, 0, 0]}]}'}, 400, "clip: not JSON"),
    ({"clip": json.dumps({"planes": [plane(point=(1e308, 0, 0))]})}, 400, "in `planes[0].point[0]`"),
    ({"clip": json.dumps({"planes": [{"point": [0] * 3, "normal": [1] * 3}] * 100}, separators=(",", ":"))}, 400,
     "length <= 6 in `planes`"),
    ({"clip": json.dumps({"planes": [plane()] * 1000})}, 431, "the request head exceeds"),  # 1000 planes
    ({"clip": "[" * 1990 + "]" * 1990}, 400, "clip: Expected `object`, got `array`"),
    ({"clip": '{"planes": ' + "[" * 1900 + "]" * 1900 + "}"}, 400, "in `planes[0]`"),
    ({"clip": '{"planes": "x"}'}, 400, "in `planes`"),
    ({"clip": '{"cap": 5}'}, 400, "in `cap`"),
    ({"clip": '{"cap": "sideways"}'}, 400, "in `cap`"),
    ({"clip": json.dumps({"cap": "x" * 3900})}, 400, "... in `cap`"),  # the echoed value cut, not the field
    ({"clip": '{"tilt": 1}'}, 400, "unknown field `tilt`"),
    ({"clip": "x" * 4001}, 422, "at most 4000 characters"),
    ({"clip": json.dumps({"box": [[0, 0, 0], [0, 0, 0]]})}, 422, "clip.box ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) has zero"),
    ({"clip": json.dumps({"box": [[1, 1, 1], [0, 0, 0]]})}, 400, "clip.box: lo must not exceed hi"),
    ({"clip": json.dumps({"box": [[0, 0, 0], [1e308] * 3]})}, 400, "in `box[1][0]`"),
    ({"clip": json.dumps({"box": [[1e-300, 0, 0], [2e-300, 1, 1]], "cap": "above"})}, 422, "no surface in the clip"),
    ({"clip": json.dumps({"planes": [plane(point=(9e8, 0, 0), normal=(1, 0, 0))], "cap": "below"})}, 422,
     "no surface in the clip"),
]


@pytest.mark.parametrize("query, status, words", HOSTILE_MESHES)
def test_hostile_mesh_queries_get_4xx_naming_the_field(server, query, status, words):
    got, _, body = get(server, "127.0.0.1", mesh_path("proc:torus@32", **query))
    assert (got, words in json.loads(body)["error"]) == (status, True), body[:300]
    assert_no_errors(server)


def test_extreme_but_valid_clips_give_meshes(server):
    """Six equal planes, all caps, a box far larger than the volume: meshes of the largest volume."""
    for clip in ({"planes": [plane()] * 6, "cap": "below"}, {"box": [[-9e8] * 3, [9e8] * 3], "cap": "above"},
                 {"planes": [plane(normal=(1e-6, 0, 1e9))], "cap": "above"}):
        status, _, body = get(server, "127.0.0.1", mesh_path(LARGEST, format="stl", clip=json.dumps(clip)))
        assert status == 200 and len(body) > 84, body[:300]
    assert_no_errors(server)


# ---- concurrent meshes beside a view session ----------------------------------------------------


def next_frame(ws, timeout: float = 60.0) -> P.FrameMsg:
    """The next frame (notices before it skipped), acknowledged."""
    for _ in range(100):
        msg = P.parse(ws.recv(timeout=timeout), CLIENT_LIMITS, P.SERVER_VIEW_MESSAGES)
        if isinstance(msg, P.FrameMsg):
            ws.send(P.encode(P.ReceivedMsg(msg.seq)))
            return msg
        assert isinstance(msg, P.NoticeMsg), msg
    raise AssertionError("no frame")


def test_many_mesh_clients_leave_the_view_its_frames(server):
    """16 clients from two addresses loop meshes of LARGEST for 4 s (each client's connection
    bound allows them all): past max_mesh_jobs under way they get 429 at once, so the device thread
    never queues more and an honest session, turning its camera meanwhile, keeps its frames;
    liveness (probed between its frames) and memory hold."""
    assert get(server, "127.0.0.1")[0] == 200
    base, peak, live, answers, gaps = server.rss(), 0, [], [], []

    def attack(source: str) -> None:
        for _ in range(1000):  # bounded in count and time
            if time.monotonic() - start > 4.0:
                return
            try:
                status, _, body = get(server, source, mesh_path(LARGEST, format="obj"))
                answers.append((status, json.loads(body)["error"] if status != 200 else ""))
            except OSError as e:  # a client timeout: the mesh waited behind too many others
                answers.append((type(e).__name__, ""))

    with view(server, "127.0.0.2") as ws:
        assert isinstance(open_view(ws), P.ReadyMsg)
        next_frame(ws)
        start = time.monotonic()
        clients = [threading.Thread(target=attack, args=(f"127.0.5.{1 + k % 2}",)) for k in range(16)]
        for c in clients:
            c.start()
        for i in range(1000):
            if time.monotonic() - start > 4.0:
                break
            t = time.monotonic()
            ws.send(P.encode(P.CameraMsg(yaw=float(i), pitch=20.0, distance=1.8)))
            next_frame(ws)
            gaps.append(time.monotonic() - t)
            peak = max(peak, server.rss() - base)
            t = time.monotonic()
            assert get(server, "127.0.0.1")[0] == 200
            live.append(time.monotonic() - t)
        for c in clients:
            c.join(30)
    print(f"\n{len(answers)} mesh answers in 4 s ({sum(s == 200 for s, _ in answers)} meshes); honest session "
          f"{len(gaps)} frames, longest {max(gaps):.2f} s; liveness at most {max(live) * 1000:.0f} ms; "
          f"RSS growth peak {peak / MiB:.0f} MiB")
    assert {s for s, _ in answers} == {200, 429} and all(r == BUSY for s, r in answers if s == 429)
    assert len(gaps) >= 3 and max(gaps) < 10.0
    assert max(live) < 2.0 and peak < MESH_RSS_GOAL
    assert_no_errors(server)


# ---- hostile view settings ----------------------------------------------------------------------


SURFACE = {"iso": 0.0, "color": [1.0, 0.5, 0.0], "opacity": 0.5}
HOSTILE_SETTINGS = [  # (settings update, words of the notice)
    ({"surfaces": [SURFACE | {"opacity": math.nan}]}, "$.settings.surfaces[0].opacity"),
    ({"surfaces": [SURFACE | {"opacity": -1.0}]}, "$.settings.surfaces[0].opacity"),
    ({"surfaces": [SURFACE | {"iso": math.inf}]}, "$.settings.surfaces[0].iso"),
    ({"surfaces": [SURFACE | {"iso": 0.01 * k} for k in range(5)]}, "$.settings.surfaces"),
    ({"surfaces": [SURFACE, SURFACE]}, "settings.surfaces"),
    ({"surfaces": [SURFACE | {"color": [0.5] * 100_000}]}, "$.settings.surfaces[0].color"),
    ({"surfaces": [SURFACE | {"color": [math.nan] * 3}]}, "$.settings.surfaces[0].color[0]"),
    ({"surfaces": "all"}, "$.settings.surfaces"),
    ({"surfaces": [SURFACE | {"glow": 1}]}, "$.settings.surfaces[0]"),
    ({"surfaces": [SURFACE], "coloring": {"by": "gradient"}}, "settings.surfaces"),
    ({"coloring": {"by": "gradient", "colormap": "x" * 10_000}}, "$.settings.coloring.colormap"),
    ({"coloring": {"by": "gradient", "range": [math.nan, 1.0]}}, "$.settings.coloring.range[0]"),
    ({"coloring": {"by": "../../etc/passwd"}}, "$.settings.coloring.by"),
    ({"coloring": {"by": "proc:sphere@128"}}, "settings.coloring.by"),
    ({"clip": {"planes": [plane(point=(math.nan, 0, 0))]}}, "$.settings.clip.planes[0].point[0]"),
    ({"clip": {"planes": [plane()] * 1000}}, "$.settings.clip.planes"),
    ({"clip": {"box": [[1, 1, 1], [0, 0, 0]]}}, "clip.box: lo must not exceed hi"),
]


def send_settings(ws, update: dict, seq: int) -> None:
    ws.send(msgspec.msgpack.encode({"type": "settings", "settings": update, "seq": seq}))


def test_hostile_view_settings_get_a_notice_naming_the_field(server):
    """Each bad setting is refused with a notice naming the field, then a frame acknowledging it."""
    with view(server, "127.0.0.3") as ws:
        assert isinstance(open_view(ws), P.ReadyMsg)
        next_frame(ws)
        for seq, (update, words) in enumerate(HOSTILE_SETTINGS, 1):
            send_settings(ws, update, seq)
            notice = P.parse(ws.recv(timeout=60), CLIENT_LIMITS, P.SERVER_VIEW_MESSAGES)
            assert isinstance(notice, P.NoticeMsg) and words in notice.text, (update, notice)
            assert next_frame(ws).ack == seq
    assert_no_errors(server)


TOGGLES = [{"surfaces": [SURFACE | {"iso": 0.0}, SURFACE | {"iso": 0.05, "opacity": 1.0}]},
           {"surfaces": []}, {"surfaces": [SURFACE | {"iso": 0.02 * k} for k in range(4)]},
           {"surfaces": [], "coloring": {"by": "gradient", "colormap": "magma"}},
           {"coloring": None, "clip": {"planes": [plane()], "cap": "above"}},
           {"clip": {}, "surfaces": [SURFACE]}]


def test_sessions_toggling_surfaces_fast_leave_others_their_frames(server):
    """Four sessions send 40 settings each as fast as they can (several translucent surfaces, none,
    a coloring, a capped clip, in turn; no waiting for frames); each gets a frame acknowledging its
    last, and an honest session's frames keep coming meanwhile."""
    def toggle(source: str, out: list) -> None:
        with view(server, source) as ws:
            assert isinstance(open_view(ws), P.ReadyMsg)
            for seq in range(1, 41):
                send_settings(ws, TOGGLES[seq % len(TOGGLES)], seq)
            for _ in range(200):  # frames of earlier settings may come first
                if next_frame(ws).ack == 40:
                    out.append(source)
                    return

    done: list[str] = []
    sessions = [threading.Thread(target=toggle, args=(f"127.0.6.{k + 1}", done)) for k in range(4)]
    for s in sessions:
        s.start()
    with view(server, "127.0.0.4") as ws:
        assert isinstance(open_view(ws), P.ReadyMsg)
        next_frame(ws)
        for i in range(1000):
            if not any(s.is_alive() for s in sessions):
                break
            ws.send(P.encode(P.CameraMsg(yaw=float(i), pitch=20.0, distance=1.8)))
            next_frame(ws, timeout=10)
            assert get(server, "127.0.0.1")[0] == 200
    for s in sessions:
        s.join(60)
    assert sorted(done) == [f"127.0.6.{k + 1}" for k in range(4)]
    assert_no_errors(server)
