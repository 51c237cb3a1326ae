"""`isosr serve --replicas`: a real local Ray cluster (2 CPUs, its own temp dir; its dashboard on a
free loopback port, since Ray's state API is served there) with
2 CPU replicas of the app behind Serve's proxy, started and stopped by this module.

- New view sessions go to the replica with the fewest open ones (`isosr_server.placement`).
- An upscale session (``x-session-id``) stays on one replica, and its frames equal the single-process
  server's; so do both models' infer endpoints' through tritonclient.
- Killing one replica's process (its PID from Ray's state API) leaves the sessions on the other
  without an error; a client session on the dead one (``isosr_client.connect(reconnect=True)``)
  reopens on the survivor within two seconds in the same state; new view sessions open on the
  survivor; the upscale session moves, says it restarted, and its frame equals a fresh state's;
  ``/v2/health/ready`` stays 200.
- Deploying one replica instead of two drains the one removed: its session goes on until it
  closes, while new sessions open on the other.
- A browser's permessage-deflate offer: the plain server declines it, Serve's proxy takes it.
- ``/metrics`` names the replica on every isosr_* series (none on the plain server); Ray's
  metrics export carries each replica's.
- Autoscaling between 1 and 2 replicas on sessions per replica adds a replica under sessions and
  drains the one it removes.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import tempfile
import threading
import time
import urllib.request
from collections import Counter
from contextlib import ExitStack, suppress
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from isosr_client import connect, upscale_remote
from isosr_render import RenderRequest, orbit
from isosr_server import protocol as P
from server_fixtures import (VOLUME, H, RunningServer, W, cam, frame, infer_inputs, lib, lib_lowres,  # noqa: F401
                             running_server, self_signed_cert, send, server_settings, session, upscale_body)

ray = pytest.importorskip("ray", reason="ray[serve] is not installed (the cluster extra)")
serve = pytest.importorskip("ray.serve", reason="ray[serve] is not installed (the cluster extra)")
from ray.util.state import list_actors  # noqa: E402

from isosr_server import cluster as cluster_module  # noqa: E402
from isosr_server.cluster import APP_NAME, application  # noqa: E402
from isosr_server.replica import REPLICA_HEADER, RESTARTED_HEADER, SESSION_HEADER  # noqa: E402

pytestmark = pytest.mark.slow
LIMITS = P.Limits(max_sessions_per_client=32, max_message_bytes=2**22)
ATOL = 1e-6
# The reconstruction on a replica against the plain server's: float32 rounding of another summation
# order (a replica's torch runs on other threads; up to 5e-6 measured), far below what a lost
# recurrent state changes (0.03 in AO, 0.9 in normals on this path's second frame).
RECON_ATOL = 1e-4
REPO = Path(__file__).resolve().parents[1]


def quiet_port() -> int:
    """A free loopback port between Ray's worker ports (10002-19999) and the ephemeral ones (32768-)
    that Ray's own servers take while Serve starts."""
    for port in random.sample(range(20000, 32000), 200):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free port in 20000-32000")


# Serve's routers and replicas report ongoing requests to the autoscaler every 10 s by default. The
# variables that Serve's docs name to set that interval take effect only after 2.60: there it is still
# autoscaling_config.metrics_interval_s (router.py), a deprecated field, so a scale-up waits ~10 s here.
AUTOSCALING_PUSH_S = {"RAY_SERVE_HANDLE_AUTOSCALING_METRIC_PUSH_INTERVAL_S": "0.5",
                      "RAY_SERVE_REPLICA_AUTOSCALING_METRIC_PUSH_INTERVAL_S": "0.5"}


@pytest.fixture(scope="module")
def cluster():
    """Ray with 2 CPUs and Serve with 2 replicas on a free port: a `RunningServer` for the proxy."""
    temp = tempfile.mkdtemp(prefix="isosr-ray-")
    started = time.monotonic()
    env = pytest.MonkeyPatch()
    for name, value in AUTOSCALING_PUSH_S.items():  # Ray's processes inherit this process's environment
        env.setenv(name, value)
    # The replicas import this checkout's packages, as this process does. Through the environment, not
    # a job runtime_env: that one puts Serve's controller, proxy and replicas in workers of their own
    # (serve.start 15 s instead of 2 s on the 2-CPU machine, each replica start 3-5 s more).
    env.setenv("PYTHONPATH", str(REPO), prepend=os.pathsep)
    context = ray.init(num_cpus=2, include_dashboard=True, dashboard_host="127.0.0.1",
                       dashboard_port=quiet_port(), _temp_dir=temp, log_to_driver=False,
                       _system_config={"metrics_report_interval_ms": 1000})
    STATE_API.append(f"http://{context.dashboard_url}")  # this cluster's, though others may run here
    RAY_TEMP.append(temp)
    try:
        settings = server_settings(limits=LIMITS)
        port = quiet_port()
        serve.start(http_options={"host": "127.0.0.1", "port": port})
        serve.run(application(settings, replicas=2), name=APP_NAME, route_prefix="/")
        print(f"Ray and 2 replicas ready in {time.monotonic() - started:.1f} s")
        yield RunningServer(port, settings, SimpleNamespace(records=[]), None, started)
    finally:
        ray.shutdown()  # Serve, its proxy and the replicas with it
        env.undo()
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture(scope="module")
def plain():
    with running_server(server_settings(limits=LIMITS)) as s:
        yield s


# The state API's address of the module's cluster and its Ray folder, logs included (set by the fixture).
STATE_API: list[str] = []
RAY_TEMP: list[str] = []


def replica_pids() -> dict[str, int]:
    """The live replicas' ids and process ids, from this cluster's Ray state API."""
    actors = list_actors(address=STATE_API[-1], filters=[("state", "=", "ALIVE")], detail=True)
    return {a.name.rsplit("#", 1)[-1]: a.pid for a in actors if a.class_name.endswith(":IsosrReplica")}


def upscale(srv, frame_np: dict, sid: str | None, header: bool = True) -> tuple[dict, P.HighresBuffers | None, int]:
    headers = {SESSION_HEADER: sid} if header and sid else {}
    status, h, body = srv.request("POST", "/v1/upscale", upscale_body(frame_np, session=sid), headers)
    h = {k.lower(): v for k, v in h.items()}
    return h, P.parse(body, P.Limits(), (P.UpscaleResponse,)).buffers if status == 200 else None, status


def assert_same(got: P.HighresBuffers, want: P.HighresBuffers) -> None:
    for name in P.HIGHRES_OUTPUTS:
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), atol=ATOL, err_msg=name)


@pytest.fixture(scope="module")
def path(lib):
    cams = [orbit(30 + 3 * i, 20, 1.8) for i in range(6)]
    return [lib_lowres(lib, c, prev).to_numpy() for c, prev in zip(cams, [None] + cams[:-1])]


def one_view_each(srv, stack: ExitStack, replicas: int, tries: int = 40, views: dict | None = None) -> dict:
    """One open view session (its first frame read) on each of ``replicas`` replicas, by replica,
    besides the open ``views`` given; sessions that land on a replica that has one already are
    closed at once."""
    views = dict(views or {})
    for _ in range(tries):
        with ExitStack() as attempt:
            ws, _ = attempt.enter_context(session(srv, mode="full"))
            frame(ws)
            replica = ws.response.headers[REPLICA_HEADER]
            if replica not in views:
                views[replica] = ws
                stack.push(attempt.pop_all())
        if len(views) == replicas:
            return views
        time.sleep(0.1)
    raise AssertionError(f"{tries} sessions reached {len(views)} of {replicas} replicas")


def test_new_views_go_to_the_replica_with_the_fewest_sessions(cluster):
    """12 view sessions held open split 6/6 (Serve's consistent hash on each request's id: 23 % of
    runs); once 4 on one replica close, the next 4 all open there (1 run in 16 by chance)."""
    replicas = replica_pids()
    assert len(replicas) == 2
    with ExitStack() as stack:
        opened = []
        for _ in range(12):
            ws, _ = stack.enter_context(session(cluster, mode="full"))
            assert frame(ws).width == W
            opened.append((ws.response.headers[REPLICA_HEADER], ws))
        assert Counter(r for r, _ in opened) == {r: 6 for r in replicas}, opened
        emptied = opened[0][0]
        for ws in [ws for r, ws in opened if r == emptied][:4]:
            ws.close()
        time.sleep(1.0)  # the proxy counts a session out when its request ends, after the close handshake
        placed = []
        for _ in range(4):
            ws, _ = stack.enter_context(session(cluster, mode="full"))
            frame(ws)
            placed.append(ws.response.headers[REPLICA_HEADER])
        assert placed == [emptied] * 4, placed


def test_upscale_session_stays_on_one_replica_and_equals_the_plain_server(cluster, plain, path):
    on = set()
    for f in path[:3]:
        h, got, status = upscale(cluster, f, "cam-a")
        assert status == 200 and RESTARTED_HEADER not in h
        on.add(h[REPLICA_HEADER])
        assert_same(got, upscale(plain, f, "cam-a")[1])
    assert len(on) == 1
    # The session in the body only: refused (it would land on any replica).
    h, _, status = upscale(cluster, path[0], "cam-b", header=False)
    assert status == 400


def test_upscale_remote_keeps_its_session_on_one_replica(cluster, plain, path):
    """`isosr_client.upscale_remote` sends its session id in the routing header: its frames reach
    one replica, which continues the recurrence, and equal the plain server's."""
    got = [upscale_remote(cluster.http_url, f, session="remote-a") for f in path[:3]]
    want = [upscale_remote(plain.http_url, f, session="remote-a") for f in path[:3]]
    assert len({r.replica for r in got}) == 1 and None not in {r.replica for r in got}
    assert not any(r.restarted for r in got) and want[0].replica is None
    for g, w in zip(got, want):
        assert_same(g.buffers, w.buffers)


def triton_infer(srv, model: str, f: dict, seq: str, start: bool, parameters: dict | None = None) -> dict:
    """One tritonclient infer of ``model`` with every input ``f`` has, in session ``seq`` (routed by its header)."""
    httpclient = pytest.importorskip("tritonclient.http", reason="tritonclient[http] is not installed")
    c = httpclient.InferenceServerClient(url=f"127.0.0.1:{srv.port}", network_timeout=120)
    r = c.infer(model, infer_inputs(f, f, "FP32", binary=True), sequence_id=seq, sequence_start=start, headers={SESSION_HEADER: seq},
                parameters=parameters)
    c.close()
    return {o["name"]: r.as_numpy(o["name"]) for o in r.get_response()["outputs"]}


def test_infer_through_the_proxy_with_tritonclient(cluster, plain, path):
    for i, f in enumerate(path[:2]):
        got, want = triton_infer(cluster, "isosr", f, "seq-1", i == 0), triton_infer(plain, "isosr", f, "seq-1", i == 0)
        for n in P.HIGHRES_OUTPUTS:
            np.testing.assert_allclose(got[n], want[n], atol=ATOL, err_msg=n)


def test_recon_infer_through_the_proxy_with_tritonclient(cluster, plain, lib):
    """The reconstruction model's sequence stays on one replica: its continued frame equals the
    plain server's (a fresh state's would not)."""
    cams = [orbit(30, 20, 1.8), orbit(34, 20, 1.8)]
    frames = [lib.renderer.render(c, RenderRequest(W, H, lib.iso, ("mask", "normal", "depth", "ao") + (
        ("flow",) if prev else ()), ao_samples=2, prev_camera=prev)).to_numpy()
        for c, prev in zip(cams, [None, cams[0]])]
    for i, f in enumerate(frames):
        got, want = (triton_infer(srv, "isosr-recon", f, "recon-1", i == 0, {"ao_rays": 2}) for srv in (cluster, plain))
        assert list(got) == ["mask", "normal", "depth", "ao", "color"]
        for n in got:
            np.testing.assert_allclose(got[n], want[n], atol=RECON_ATOL, err_msg=n)


def isosr_samples(text: str, prefix: str = "isosr_") -> list:
    return [s for f in text_string_to_metric_families(text) if f.name.startswith(prefix) for s in f.samples]


def test_a_browsers_deflate_offer_is_declined_by_the_plain_server_and_taken_by_serves_proxy(cluster, plain):
    """Browsers offer permessage-deflate on every WebSocket. The plain server declines it (frames are
    coded images); Serve's proxy, whose uvicorn cannot be configured, accepts it and so deflates every
    frame (docs/serving.md: the reverse proxy in front drops the offer). Frames come either way."""
    for server, deflated in ((plain, False), (cluster, True)):
        with connect(server.http_url, VOLUME, "full", (W, H), settings={"refine": False}, local_upscale=False,
                     timeout=60, compression="deflate") as view:
            view.set_camera(yaw=40.0, pitch=20.0, distance=1.8)
            assert view.frame().shape == (H, W, 3)
            names = [e.name for e in view._ws.protocol.extensions]
            assert names == (["permessage-deflate"] if deflated else []), (server.http_url, names)


def test_metrics_name_their_replica(cluster, plain):
    """``/metrics`` through the proxy: every isosr_* sample names the replica that answered; the
    plain server's name none. Ray's metrics export (the node's ``MetricsExportPort``) carries each
    replica's series (``ray_isosr_*``, Serve's ``replica`` tag) beside Serve's own, and their sum
    is the total."""
    with ExitStack() as stack:
        one_view_each(cluster, stack, 2)
        status, h, body = cluster.request("GET", "/metrics")
        replica = {k.lower(): v for k, v in h.items()}[REPLICA_HEADER]
        samples = isosr_samples(body.decode())
        assert status == 200 and samples and {s.labels.get("replica") for s in samples} == {replica}
        assert {s.labels["kind"]: s.value for s in samples if s.name == "isosr_sessions"}["view"] == 1
        status, _, body = plain.request("GET", "/metrics")
        assert status == 200 and not [s for s in isosr_samples(body.decode()) if "replica" in s.labels]
        export = f"http://127.0.0.1:{ray.nodes()[0]['MetricsExportPort']}/metrics"
        live = set(replica_pids())
        views: dict[str, float] = {}

        def exported() -> bool:
            text = urllib.request.urlopen(export, timeout=10).read().decode()
            views.clear()
            views.update({s.labels["replica"]: s.value for s in isosr_samples(text, "ray_isosr_sessions")
                          if s.labels["kind"] == "view" and s.labels["replica"] in live})
            ongoing = {s.labels["replica"] for s in isosr_samples(text, "ray_serve_replica_processing_queries")}
            return views == {r: 1.0 for r in live} and ongoing >= live

        wait_for(exported, f"Ray's export does not show one view session on each of {live}: {views}", 20)
        assert sum(views.values()) == 2


def test_each_replica_logs_at_the_servers_level(cluster):
    """A replica runs in a Ray worker, not in the process that set up logging: its isosr INFO lines (its start,
    auto's choices) are in the worker's log all the same."""
    logs, pids = Path(RAY_TEMP[-1]) / "session_latest" / "logs", replica_pids()

    def logged() -> set[str]:
        text = "\n".join(f.read_text(errors="replace") for f in logs.rglob("*") if f.suffix in (".err", ".out", ".log"))
        return {r for r, pid in pids.items() if f"INFO isosr.cluster: isosr replica {r} in process {pid}" in text}

    wait_for(lambda: logged() == set(pids), f"not every replica's start is in {logs}: {logged()} of {set(pids)}", 10)


def test_killing_a_replica_moves_only_its_sessions(cluster, plain, path):
    pids = replica_pids()
    h, _, _ = upscale(cluster, path[3], "cam-a")
    doomed = h[REPLICA_HEADER]
    survivor = next(r for r in pids if r != doomed)
    # One open view session on each replica.
    stack = ExitStack()
    views = one_view_each(cluster, stack, 2)
    # A client session on the replica that will die.
    client = None
    for _ in range(24):
        view = stack.enter_context(connect(cluster.http_url, VOLUME, "full", (W, H), reconnect=True,
                                           settings={"encoding": "png", "refine": False}))
        if view.replica == doomed:
            client = view
            break
    assert client is not None and client.frame().shape == (H, W, 3)
    os.kill(pids[doomed], signal.SIGKILL)
    killed = time.monotonic()
    client.set_camera(yaw=45, pitch=20, distance=1.8)
    moved = client.frame()
    print(f"the client's session reopened and framed in {time.monotonic() - killed:.2f} s")
    assert client.reconnects == 1 and client.stats.replica == survivor
    with connect(cluster.http_url, VOLUME, "full", (W, H), settings={"encoding": "png", "refine": False},
                 camera={"yaw": 45, "pitch": 20, "distance": 1.8}) as fresh:
        np.testing.assert_array_equal(moved, fresh.frame())
    # The survivor's session goes on without an error while the other replica is gone.
    ws = views[survivor]
    for i in range(5):
        send(ws, cam(40 + i))
        assert frame(ws).mode == "full"
    # New view sessions open, none on the dead replica; health stays ready.
    health, placed = [], []
    deadline = killed + 30
    while len(placed) < 4 and time.monotonic() < deadline:
        health.append(cluster.request("GET", "/v2/health/ready")[0])
        try:
            with session(cluster, mode="full") as (new, _):
                placed.append(new.response.headers[REPLICA_HEADER])
                frame(new)
        except Exception as e:  # noqa: BLE001 (the window before Serve notices the death is what is measured)
            print(f"{time.monotonic() - killed:.2f} s after the kill: {e!r}")
    assert len(placed) == 4 and doomed not in placed, placed
    assert set(health) == {200}, health
    # The upscale session continues elsewhere and says it restarted; its frame is a fresh state's.
    moved = upscale_remote(cluster.http_url, path[4], session="cam-a")
    assert moved.replica == survivor and moved.restarted
    assert_same(moved.buffers, upscale(plain, path[4], "fresh")[1])
    h, _, _ = upscale(cluster, path[5], "cam-a")
    assert RESTARTED_HEADER not in h
    with suppress(Exception):  # the dead replica's sockets are gone
        stack.close()


def wait_for(predicate, what: str, seconds: float = 30.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)


def test_a_removed_replica_drains_its_sessions(cluster):
    """Deploying again (as a code or settings change does) replaces the replicas one by one; each
    one removed takes no new sessions, serves its open ones until they close, then ends. (With 2
    CPUs and a CPU per replica the new replica starts only once an old one has ended.)"""
    wait_for(lambda: len(replica_pids()) == 2 and serve.status().applications[APP_NAME].status == "RUNNING",
             "Serve did not replace the killed replica")
    stack = ExitStack()
    views = one_view_each(cluster, stack, 2)
    # serve.run returns once the new version runs, which waits for the old replicas' sessions.
    redeploy = threading.Thread(target=serve.run, args=(application(cluster.settings, replicas=1),),
                                kwargs={"name": APP_NAME, "route_prefix": "/"}, daemon=True)
    redeploy.start()
    try:
        wait_for(lambda: replica_states().get("STOPPING") == 1, "no replica is draining")
        kept = settled_replica(cluster)
        drained = next(r for r in views if r != kept)
        for i in range(4):  # the draining replica's session goes on, and so does the other's
            for ws in views.values():
                send(ws, cam(60 + i))
                assert frame(ws).mode == "full"
        assert drained in replica_pids()
        views[drained].close()
        wait_for(lambda: drained not in replica_pids(), "the drained replica did not end after its session closed")
        send(views[kept], cam(70))
        assert frame(views[kept]).mode == "full"
    finally:  # the redeploy ends once the sessions close (else it would outlive this Ray and start another)
        stack.close()
        redeploy.join(60)
    assert not redeploy.is_alive() and replica_states() == {"RUNNING": 1} and not set(replica_pids()) & set(views)


# Serve 2.60 checks the look-back against the deprecated metrics_interval_s (10 s by default), which
# the push intervals above (AUTOSCALING_PUSH_S) are to replace in a later release.
@pytest.mark.filterwarnings("ignore:`look_back_period_s`.*metrics_interval_s:FutureWarning")
def test_autoscaling_adds_a_replica_under_sessions_and_drains_the_one_it_removes(cluster, monkeypatch):
    """``--replicas 1 --max-replicas 2 --sessions-per-replica 2`` (the autoscaler's delays and
    look-back cut to seconds): four sessions on the one replica start a second, where the next
    session opens; with one session left on each, the autoscaler removes a replica, which serves
    its session until that closes, and then ends."""
    for name, value in (("UPSCALE_DELAY_S", 0.0), ("DOWNSCALE_DELAY_S", 1.0), ("LOOK_BACK_PERIOD_S", 1.0)):
        monkeypatch.setattr(cluster_module, name, value)
    started = time.monotonic()
    serve.run(application(cluster.settings, replicas=1, max_replicas=2, sessions_per_replica=2),
              name=APP_NAME, route_prefix="/")
    wait_for(lambda: replica_states() == {"RUNNING": 1}, "the autoscaled deployment did not start")
    with ExitStack() as stack:
        first = []
        for _ in range(4):
            ws, _ = stack.enter_context(session(cluster, mode="full"))
            frame(ws)
            first.append(ws)
        (old,) = {ws.response.headers[REPLICA_HEADER] for ws in first}
        wait_for(lambda: replica_states() == {"RUNNING": 2}, "4 sessions over a target of 2 added no replica", 60)
        scaled = time.monotonic()
        # New sessions open on the new replica once the proxy has heard of it (the first may not).
        views = one_view_each(cluster, stack, 2, tries=30, views={old: first[0]})
        new = next(r for r in views if r != old)
        assert {old, new} <= set(replica_pids())
        for ws in first[1:]:
            ws.close()
        wait_for(lambda: replica_states().get("STOPPING") == 1, "2 sessions on 2 replicas removed none", 60)
        kept = settled_replica(cluster)
        drained = next(r for r in views if r != kept)
        for i in range(4):  # the replica being removed serves its session on, the other too
            for ws in views.values():
                send(ws, cam(80 + i))
                assert frame(ws).mode == "full"
        assert drained in replica_pids() and replica_states().get("STOPPING") == 1
        views[drained].close()
        wait_for(lambda: drained not in replica_pids(), "the removed replica did not end after its session closed")
        send(views[kept], cam(90))
        assert frame(views[kept]).mode == "full"
    wait_for(lambda: replica_states() == {"RUNNING": 1}, "not one replica left")
    drained_s = time.monotonic() - scaled
    print(f"scaled up {scaled - started:.1f} s after deploying; down and drained {drained_s:.1f} s later")


def replica_states() -> dict[str, int]:
    return serve.status().applications[APP_NAME].deployments["IsosrReplica"].replica_states


def settled_replica(srv, runs: int = 5, seconds: float = 10.0) -> str:
    """The replica new view sessions land on once ``runs`` in a row land on the same one."""
    deadline, last, streak = time.monotonic() + seconds, None, 0
    while streak < runs:
        assert time.monotonic() < deadline, "new sessions do not settle on one replica"
        with session(srv, mode="full") as (ws, _):
            replica = ws.response.headers[REPLICA_HEADER]
        streak, last = (streak + 1 if replica == last else 1), replica
    return last


def test_serve_config_and_replica_options(monkeypatch, tmp_path):
    """deploy/serve.yaml is a valid Serve config whose builder makes the app (its proxies' TLS files
    are the app's); bad replica options say why."""
    import yaml
    from ray.serve.schema import ServeDeploySchema

    from isosr_server.cluster import build
    from isosr_server.core.config import Settings

    config = ServeDeploySchema.model_validate(yaml.safe_load((REPO / "deploy" / "serve.yaml").read_text()))
    app = config.applications[0]
    assert app.import_path == "isosr_server.cluster:build" and app.deployments[0].name == "IsosrReplica"
    http = config.http_options
    assert (http.ssl_certfile, http.ssl_keyfile) == (app.args["tls_cert"], app.args["tls_key"])
    with pytest.raises(ValueError, match="--tls-cert /etc/isosr/tls/cert.pem: No such file"):
        build(app.args)  # the cluster's files, absent here
    cert, key = self_signed_cert(tmp_path)
    args = dict(app.args, tls_cert=str(cert), tls_key=str(key))
    with pytest.raises(ValueError, match="requires a token|give --token"):
        build(args)  # host 0.0.0.0 without ISOSR_TOKEN
    monkeypatch.setenv("ISOSR_TOKEN", "correct-horse-battery")
    assert build(args) is not None
    unfronted = {k: v for k, v in args.items() if k != "behind_proxy"}
    with pytest.raises(ValueError, match="Ray Serve's proxy, which bounds neither header size"):
        build(unfronted)  # 0.0.0.0 without saying a reverse proxy fronts Serve's proxies
    assert build(dict(unfronted, host="127.0.0.1")) is not None
    with pytest.raises(ValueError, match="unknown settings: colour"):
        build({"colour": "red"})
    with pytest.raises(ValueError, match="at least 1"):
        application(Settings(), replicas=0)
    with pytest.raises(ValueError, match="needs --device cuda"):
        application(Settings(), replicas=2, gpus_per_replica=0.5)
    with pytest.raises(ValueError, match="must be at least replicas"):
        application(Settings(), replicas=2, max_replicas=1)
    assert application(Settings(), replicas=1, max_replicas=3) is not None


def test_a_replica_with_part_of_a_gpu_budgets_its_part(tmp_path):
    """A replica Ray gave a quarter of a GPU serves with gpu_share 0.25, one with a whole GPU or
    none as before; MPS is seen by its control socket."""
    from isosr_server.cluster import replica_settings
    from isosr_server.core.config import Settings
    from isosr_server.replica import mps_running

    settings = Settings()
    assert replica_settings(settings, {"CPU": 1.0, "GPU": 0.25}).gpu_share == 0.25
    assert replica_settings(settings, {"CPU": 1.0, "GPU": 1.0}) is settings
    assert replica_settings(settings, {"CPU": 1.0}) is settings
    environ = {"CUDA_MPS_PIPE_DIRECTORY": str(tmp_path)}
    assert not mps_running(environ)
    (tmp_path / "control").touch()
    assert mps_running(environ)


@pytest.mark.parametrize("mps", [False, True])
def test_replicas_sharing_a_gpu_without_mps_are_warned_of(tmp_path, monkeypatch, caplog, mps):
    """`serve_replicas` with half a GPU each on a local Ray says MPS is missing before it starts Ray (stopped
    here at ray.init), and says nothing once its control socket is there."""
    from isosr_server.core.config import Settings

    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(tmp_path))
    if mps:
        (tmp_path / "control").touch()

    def stop(**_):
        raise RuntimeError("no Ray in this test")

    monkeypatch.setattr(cluster_module.ray, "init", stop)
    with pytest.raises(RuntimeError, match="no Ray in this test"):
        cluster_module.serve_replicas(Settings(device="cuda"), replicas=2, gpus_per_replica=0.5)
    assert ("without MPS" in caplog.text) is not mps
