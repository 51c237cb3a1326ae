"""`isosr_client.connect(..., reconnect=True)` on a single server: a session whose connection is
lost opens itself again with its camera, iso and settings, and its next frame equals a new
session's in that state; a close for the client's own mistake is not retried. (``full`` frames:
the modes with a recurrent network state start that state afresh in a reopened session.)"""

from __future__ import annotations

import socket

import numpy as np
import pytest

from isosr_client import connect
from isosr_client.view import ServerError
from isosr_server import protocol as P
from server_fixtures import VOLUME, H, W, running_server, server_settings

SETTINGS = {"encoding": "png", "refine": False}


@pytest.fixture(scope="module")
def srv():
    with running_server(server_settings()) as s:
        yield s


def drop(view) -> None:
    """Cut the session's TCP connection under it, as a dying server process does (no close frame),
    and wait until the client's reader has seen it end."""
    view._ws.socket.shutdown(socket.SHUT_RDWR)
    view._ws.recv_events_thread.join(10)


def test_a_lost_session_reopens_in_its_state(srv):
    with connect(srv.http_url, VOLUME, "full", (W, H), settings=SETTINGS, reconnect=True,
                 camera={"yaw": 30, "pitch": 20, "distance": 1.8}) as view:
        view.frame()
        view.set_camera(yaw=50, pitch=10, distance=1.6)
        view.set_iso(0.3, normalized=True)
        view.set_settings(ao_rays=2)
        before = view.frame()
        drop(view)
        after = view.frame()  # the receive finds the connection gone and reopens
        assert view.reconnects == 1 and view.ready.settings == view.settings and view.settings.ao_rays == 2
        np.testing.assert_array_equal(after, before)
        drop(view)
        view.set_camera(yaw=60, pitch=10, distance=1.6)  # the send finds it gone; the open carries the camera
        moved = view.frame()
        assert view.reconnects == 2
    with connect(srv.http_url, VOLUME, "full", (W, H), settings=dict(SETTINGS, ao_rays=2),
                 camera={"yaw": 60, "pitch": 10, "distance": 1.6}, iso=0.3, iso_normalized=True) as fresh:
        np.testing.assert_array_equal(moved, fresh.frame())


def test_without_reconnect_or_for_a_client_mistake_the_session_ends(srv):
    with connect(srv.http_url, VOLUME, "full", (W, H), settings=SETTINGS) as view:
        view.frame()
        drop(view)
        with pytest.raises(ServerError) as e:
            view.frame()
        assert e.value.code == 1006 and view.reconnects == 0
    with connect(srv.http_url, VOLUME, "full", (W, H), settings=SETTINGS, reconnect=True) as view:
        view.frame()
        view._ws.send(b"\xc1")  # malformed msgpack: the server closes with 1007
        view._ws.recv_events_thread.join(10)
        with pytest.raises(ServerError) as e:
            view.frame()
        assert e.value.code == P.CLOSE_BAD_MESSAGE and view.reconnects == 0
