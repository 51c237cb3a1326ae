"""A time series served: its steps listed, ``settings.t`` bounded and shown, a step change a cut for every
recurrent mode (nothing ghosts), a step file gone mid-playback a notice while the session goes on;
and the Python client's steps."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed

from isosr_net.methods import RUNNERS, unavailable_kinds
from isosr_render.image_codec import decode_image
from isosr_server import protocol as P
from server_fixtures import frame, recv, running_server, send, server_settings, session

pytest.importorskip("uvicorn", reason="serving needs the server extra")

N = 24
CENTERS = (7.0, 16.0, 11.0)  # the ball's x per step: it jumps


def ball(cx: float) -> np.ndarray:
    """A smooth uint8 ball of radius 6 voxels about (cx, 12, 12), indexed [x, y, z]."""
    x, y, z = np.meshgrid(*(np.arange(N, dtype=np.float64),) * 3, indexing="ij")
    d = np.sqrt((x - cx) ** 2 + (y - 12.0) ** 2 + (z - 12.0) ** 2)
    return np.clip(128 + 40 * (6.0 - d), 0, 255).astype(np.uint8)


def write_series(folder: Path) -> None:
    folder.mkdir()
    for i, c in enumerate(CENTERS):
        np.save(folder / f"run_{i}.npy", ball(c))


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    root = tmp_path_factory.mktemp("volumes")
    write_series(root / "runs")
    write_series(root / "gone")
    with running_server(server_settings(volumes=root)) as s:
        s.root = root
        yield s


# reconstruct at 1 AO ray: the sessions of the tests that need one recurrent mode
RECON = {"mode": "reconstruct", "ao_rays": 1}
# Every recurrent view mode (without the cut, reconstruct's and network's history shows the step before and
# buffers send a flow into it; svgf's depth and normal tests reject its history themselves).
RECURRENT_MODES = [kind for kind, runner in RUNNERS.items()
                   if runner.recurrent and runner.view_mode and kind not in unavailable_kinds()]
CAM = P.CameraMsg(yaw=34.0, pitch=20.0, distance=1.8)


def test_the_listing_and_ready_say_the_steps(srv):
    status, listing = srv.get_json("/v1/volumes")
    assert status == 200
    steps = {v["name"]: v["steps"] for v in listing["volumes"]}
    assert steps["runs"] == 3 and steps["proc:sphere"] == 1
    with session(srv, "runs", **RECON) as (ws, ready):
        assert ready.volume.steps == 3 and ready.settings.t == 0
        assert frame(ws).t == 0


@pytest.mark.parametrize("mode", RECURRENT_MODES)
def test_a_step_change_shows_the_step_and_nothing_of_the_one_before(srv, mode):
    """Step 0 played from a still camera (where history lines up best), then step 1: its first frame
    is a fresh session's first frame of step 1."""
    with session(srv, "runs", camera=CAM, mode=mode, ao_rays=1) as (ws, _):
        frame(ws)
        for seq in (1, 2):  # history builds up on step 0
            send(ws, msgspec.structs.replace(CAM, seq=seq))
            assert frame(ws).t == 0
        send(ws, P.SettingsMsg(P.SettingsUpdate(t=1), seq=100))
        jumped = frame(ws)
        assert jumped.t == 1 and jumped.ack == 100
    before, fresh = frame_at(srv, mode, 0), frame_at(srv, mode, 1)
    assert fresh.t == 1
    if mode == "buffers":  # for the client's network: a cut (no flow), the fresh frame's buffers
        assert jumped.prev_seq == -1 and jumped.buffers.flow is None
        assert jumped.buffers == fresh.buffers and before.buffers != fresh.buffers
    else:
        np.testing.assert_array_equal(decode_image(jumped.image), decode_image(fresh.image))
        moved = decode_image(before.image).astype(int) - decode_image(fresh.image).astype(int)
        assert np.abs(moved).max() > 100  # the ball moved


def frame_at(srv, mode: str, t: int) -> P.FrameMsg:
    """A new session's first frame of step ``t`` from ``CAM``."""
    with session(srv, "runs", camera=CAM, t=t, mode=mode, ao_rays=1) as (ws, _):
        return frame(ws)


def test_a_step_past_the_series_is_refused(srv):
    with session(srv, "runs", **RECON) as (ws, _):
        frame(ws)
        send(ws, P.SettingsMsg(P.SettingsUpdate(t=3)))
        error = recv(ws)
        assert isinstance(error, P.ErrorMsg) and error.code == P.CLOSE_POLICY
        assert "no time step 3 in 'runs', which has 3 (0 to 2)" in error.reason
        with pytest.raises(ConnectionClosed):
            recv(ws)


def test_a_step_file_gone_mid_playback_is_a_notice_and_the_session_goes_on(srv):
    assert srv.get_json("/v1/volumes/gone")[0] == 200  # opened: every file was there
    (srv.root / "gone" / "run_2.npy").unlink()
    with session(srv, "gone", **RECON) as (ws, _):
        assert frame(ws).t == 0
        send(ws, P.SettingsMsg(P.SettingsUpdate(t=1), seq=1))
        assert frame(ws).t == 1
        send(ws, P.SettingsMsg(P.SettingsUpdate(t=2), seq=2))
        notice = recv(ws)
        assert isinstance(notice, P.NoticeMsg)
        assert notice.text.startswith("time step 2 (run_2.npy) cannot be read:") and "showing step 1" in notice.text
        kept = frame(ws)
        assert kept.t == 1 and kept.ack == 2
        send(ws, P.SettingsMsg(P.SettingsUpdate(t=0), seq=3))
        assert frame(ws).t == 0


def test_the_python_client_reads_the_count_and_sets_the_step(srv):
    from isosr_client import connect

    with connect(srv.http_url, volume="runs", mode="reconstruct", size=(64, 48), settings={"ao_rays": 1, "refine": False},
                 camera={"yaw": 30.0, "pitch": 20.0, "distance": 1.8}) as view:
        assert view.steps == 3 and view.step == 0
        view.frame()
        view.set_step(2)
        view.frame()
        assert view.stats is not None and view.step == 2 and view.latest().message.t == 2
        with pytest.raises(P.ProtocolError, match="no time step 3"):
            view.set_step(3)
